//! Unit tests of the data-parallel engine.

#![allow(clippy::unwrap_used)]

use super::*;
use std::collections::HashMap;
use std::net::TcpListener;
use std::time::Instant;
use tch::{Device, Kind, Tensor};

fn vars(pairs: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
    let m: HashMap<String, String> = pairs
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    move |k| m.get(k).cloned()
}

#[test]
fn environment_parsing_and_errors() {
    assert_eq!(DistEnv::from_vars(vars(&[])).unwrap(), None);
    // One rank is a group of one (torchrun --nproc-per-node 1).
    let one = DistEnv::from_vars(vars(&[("WORLD_SIZE", "1"), ("RANK", "0")]))
        .unwrap()
        .unwrap();
    assert_eq!((one.rank, one.world, one.use_agent_store), (0, 1, false));
    assert_eq!(one.timeout, DEFAULT_TIMEOUT);
    assert_eq!(one.bucket_bytes, 25 << 20);
    let agent = DistEnv::from_vars(vars(&[
        ("WORLD_SIZE", "2"),
        ("RANK", "1"),
        ("TORCHELASTIC_USE_AGENT_STORE", "True"),
        ("TORCHELASTIC_RESTART_COUNT", "3"),
        ("BRIDGEV2W_BUCKET_MB", "0.5"),
        ("BRIDGEV2W_DIST_TIMEOUT", "12"),
    ]))
    .unwrap()
    .unwrap();
    assert!(agent.use_agent_store);
    assert_eq!(agent.restart_count, 3);
    assert_eq!(agent.bucket_bytes, 1 << 19);
    assert_eq!(agent.timeout, Duration::from_secs(12));
    let e = DistEnv::from_vars(vars(&[
        ("WORLD_SIZE", "4"),
        ("RANK", "2"),
        ("MASTER_ADDR", "node0"),
        ("MASTER_PORT", "1234"),
        ("LOCAL_RANK", "1"),
    ]))
    .unwrap()
    .unwrap();
    assert_eq!((e.rank, e.world, e.local_rank), (2, 4, Some(1)));
    assert_eq!(e.master(), "node0:1234");
    let d = DistEnv::from_vars(vars(&[("WORLD_SIZE", "2"), ("RANK", "1")]))
        .unwrap()
        .unwrap();
    assert_eq!(d.master(), "127.0.0.1:29500");
    for (pairs, needles) in [
        (vec![("WORLD_SIZE", "2")], vec!["RANK", "WORLD_SIZE=2"]),
        (vec![("RANK", "1")], vec!["WORLD_SIZE", "RANK=1"]),
        (
            vec![("WORLD_SIZE", "2"), ("RANK", "2")],
            vec!["RANK=2", "WORLD_SIZE=2"],
        ),
        (
            vec![("WORLD_SIZE", "two"), ("RANK", "0")],
            vec!["WORLD_SIZE", "two"],
        ),
        (
            vec![("WORLD_SIZE", "0"), ("RANK", "0")],
            vec!["WORLD_SIZE=0"],
        ),
        (
            vec![("WORLD_SIZE", "2"), ("RANK", "0"), ("MASTER_PORT", "70000")],
            vec!["MASTER_PORT", "70000"],
        ),
        (
            vec![("WORLD_SIZE", "2"), ("RANK", "0"), ("LOCAL_RANK", "-1")],
            vec!["LOCAL_RANK", "-1"],
        ),
        (
            vec![
                ("WORLD_SIZE", "2"),
                ("RANK", "0"),
                ("TORCHELASTIC_USE_AGENT_STORE", "yes please"),
            ],
            vec!["TORCHELASTIC_USE_AGENT_STORE", "yes please"],
        ),
        (
            vec![
                ("WORLD_SIZE", "2"),
                ("RANK", "0"),
                ("BRIDGEV2W_BUCKET_MB", "0"),
            ],
            vec!["BRIDGEV2W_BUCKET_MB", "\"0\""],
        ),
        (
            vec![
                ("WORLD_SIZE", "2"),
                ("RANK", "0"),
                ("BRIDGEV2W_DIST_TIMEOUT", "-3"),
            ],
            vec!["BRIDGEV2W_DIST_TIMEOUT", "-3"],
        ),
    ] {
        let e = DistEnv::from_vars(vars(&pairs)).unwrap_err().to_string();
        for n in needles {
            assert!(e.contains(n), "{pairs:?}: {e}");
        }
    }
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn env(rank: usize, world: usize, port: u16, timeout_s: f64) -> DistEnv {
    DistEnv {
        rank,
        world,
        master_addr: "127.0.0.1".into(),
        master_port: port,
        local_rank: None,
        timeout: Duration::from_secs_f64(timeout_s),
        use_agent_store: false,
        restart_count: 0,
        bucket_bytes: 25 << 20,
    }
}

/// Runs `f(env of rank r)` on `world` threads; their results in rank order.
fn ranks<T: Send + 'static>(
    world: usize,
    make_env: impl Fn(usize) -> DistEnv,
    f: impl Fn(DistEnv) -> T + Send + Sync + Clone + 'static,
) -> Vec<T> {
    let handles: Vec<_> = (0..world)
        .map(|r| {
            let e = make_env(r);
            let f = f.clone();
            std::thread::spawn(move || f(e))
        })
        .collect();
    handles.into_iter().map(|h| h.join().unwrap()).collect()
}

#[test]
fn buckets_pack_gradients_in_reverse_order_up_to_the_cap() {
    // 4-byte values, cap 40 bytes = 10 values.
    assert_eq!(
        bucket_ranges(&[3, 4, 5, 20, 2], 40),
        vec![vec![4], vec![3], vec![2, 1], vec![0]]
    );
    assert_eq!(bucket_ranges(&[1, 1, 1], 1 << 20), vec![vec![2, 1, 0]]);
    assert!(bucket_ranges(&[], 40).is_empty());
}

#[test]
fn three_ranks_average_gradients_in_buckets_over_gloo() {
    let port = free_port();
    let out = ranks(
        3,
        |r| DistEnv {
            // 16-byte buckets: every gradient below is a bucket or two of its own.
            bucket_bytes: 16,
            ..env(r, 3, port, 30.0)
        },
        |e| {
            let rank = e.rank as f64;
            let mut c = C10dCollective::connect(&e, Device::Cpu, 7).unwrap();
            assert_eq!((c.rank(), c.world(), c.name()), (e.rank, 3, "gloo"));
            let grads = [
                Tensor::from_slice(&[1.0f32, 2.0, 3.0, 4.0, 5.0]) * (rank + 1.0),
                Tensor::from_slice(&[rank as f32; 6]).view([2, 3]),
                Tensor::from_slice(&[-rank as f32]),
            ];
            let mut scalars = [rank, 10.0 * rank];
            average_gradients(&mut c, &grads, &mut scalars).unwrap();
            c.barrier().unwrap();
            let g: Vec<Vec<f32>> = grads
                .iter()
                .map(|g| Vec::<f32>::try_from(&g.reshape(-1)).unwrap())
                .collect();
            (g, scalars, grads[1].size())
        },
    );
    for (g, scalars, size) in out {
        // mean of (1, 2, 3) x [1..5]; mean of 0, 1, 2; mean of 0, -1, -2
        assert_eq!(g[0], vec![2.0, 4.0, 6.0, 8.0, 10.0]);
        assert_eq!(g[1], vec![1.0; 6]);
        assert_eq!(g[2], vec![-1.0]);
        assert_eq!(scalars, [1.0, 10.0]);
        assert_eq!(size, vec![2, 3]);
    }
}

#[test]
fn different_gradients_stop_every_rank_naming_them() {
    let port = free_port();
    let out = ranks(
        3,
        |r| env(r, 3, port, 30.0),
        |e| {
            let mut c = C10dCollective::connect(&e, Device::Cpu, 5).unwrap();
            let n = if e.rank == 1 { 11 } else { 10 };
            let grads = [Tensor::ones([n], (Kind::Float, Device::Cpu))];
            average_gradients(&mut c, &grads, &mut [0.0])
                .unwrap_err()
                .to_string()
        },
    );
    for (rank, e) in out.into_iter().enumerate() {
        assert!(
            e.contains("rank 0 holds 1 gradients of 10 values")
                && e.contains("rank 1 holds 1 gradients of 11 values")
                && e.contains(&format!("rank {rank} stops")),
            "{e}"
        );
    }
}

#[test]
fn nccl_without_a_gpu_fails_clearly_on_every_rank() {
    // No GPU here: every rank gets an error (none waits for the other forever).
    let port = free_port();
    let out = ranks(
        2,
        |r| env(r, 2, port, 30.0),
        |e| {
            C10dCollective::connect(&e, Device::Cuda(0), 3)
                .map(|_| ())
                .unwrap_err()
                .to_string()
        },
    );
    for e in out {
        eprintln!("{e}");
        assert!(
            e.contains("nccl") || e.contains("NCCL") || e.contains("CUDA"),
            "{e}"
        );
    }
}

#[test]
fn torchrun_agent_store_every_rank_a_client() {
    // torchrun's agent hosts the store on MASTER_PORT; the ranks must not bind it.
    let port = free_port();
    let agent = bridgev2w_torch_ext::c10d::Store::tcp(
        "127.0.0.1",
        port,
        true,
        2,
        Duration::from_secs(30),
        "",
    )
    .unwrap();
    let out = ranks(
        2,
        |r| DistEnv {
            use_agent_store: true,
            restart_count: 1,
            ..env(r, 2, port, 30.0)
        },
        |e| {
            let mut c = C10dCollective::connect(&e, Device::Cpu, 9).unwrap();
            let mut t = Tensor::from_slice(&[e.rank as f32 + 1.0]);
            c.all_reduce_sum(&mut t).unwrap();
            t.double_value(&[0])
        },
    );
    assert_eq!(out, vec![3.0, 3.0]);
    // The ranks' keys sit under the attempt's prefix in the agent's store.
    assert!(agent.check("bridgev2w/attempt_1/joined").unwrap());
}

#[test]
fn unreachable_store_missing_or_doubled_ranks_and_mismatched_config_are_clear_errors() {
    let port = free_port(); // nobody listens there
    let start = Instant::now();
    let e = C10dCollective::connect(&env(1, 2, port, 0.5), Device::Cpu, 0)
        .unwrap_err()
        .to_string();
    assert!(start.elapsed() < Duration::from_secs(15), "{e}");
    assert!(
        e.contains("MASTER_ADDR=127.0.0.1") && e.contains(&format!("MASTER_PORT={port}")),
        "{e}"
    );
    // Rank 0 alone times out naming the missing rank.
    let e = C10dCollective::connect(&env(0, 2, free_port(), 0.5), Device::Cpu, 0)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("only 1 of WORLD_SIZE=2") && e.contains("missing: rank(s) 1"),
        "{e}"
    );
    // RANK=0 twice (and no rank 1): both processes stop, naming it.
    let port = free_port();
    let out = ranks(
        2,
        |_| env(0, 2, port, 5.0),
        |e| {
            C10dCollective::connect(&e, Device::Cpu, 0)
                .unwrap_err()
                .to_string()
        },
    );
    for e in out {
        eprintln!("{e}");
        assert!(
            e.contains("RANK=0 by 2") || e.contains("host the store"),
            "{e}"
        );
    }
    // Different configurations are refused on both sides.
    let port = free_port();
    let out = ranks(
        2,
        |r| env(r, 2, port, 20.0),
        |e| {
            C10dCollective::connect(&e, Device::Cpu, e.rank as u64 + 1)
                .unwrap_err()
                .to_string()
        },
    );
    for e in out {
        assert!(
            e.contains("configuration differs")
                && e.contains("config 0000000000000001")
                && e.contains("rank 1 has WORLD_SIZE=2 config 0000000000000002"),
            "{e}"
        );
    }
}
