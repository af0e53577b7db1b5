//! Unit tests of the data-parallel engine.

#![allow(clippy::unwrap_used)]

use super::*;
use std::collections::HashMap;

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
    assert_eq!(
        DistEnv::from_vars(vars(&[("WORLD_SIZE", "1"), ("RANK", "0")])).unwrap(),
        None
    );
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
    }
}

#[test]
fn three_ranks_all_reduce_and_broadcast_over_tcp() {
    let port = free_port();
    let handles: Vec<_> = (0..3)
        .map(|rank| {
            std::thread::spawn(move || {
                let mut c = TcpCollective::connect(&env(rank, 3, port, 20.0), 7).unwrap();
                assert_eq!((c.rank(), c.world()), (rank, 3));
                let t = Tensor::from_slice(&[rank as f32, 1.0, -2.0 * rank as f32]);
                let mut t = t.view([3, 1]);
                c.all_reduce_sum(&mut t).unwrap();
                let got = Vec::<f32>::try_from(&t.reshape(-1)).unwrap();
                let b = c.broadcast_bytes(&[rank as u8; 3]).unwrap();
                (got, b, t.size())
            })
        })
        .collect();
    for h in handles {
        let (got, b, size) = h.join().unwrap();
        assert_eq!(got, vec![3.0, 3.0, -6.0]);
        assert_eq!(b, vec![0u8; 3]);
        assert_eq!(size, vec![3, 1]);
    }
}

#[test]
fn buffer_lengths_are_agreed_on_or_every_rank_stops() {
    let run = |lens: [usize; 3]| {
        let port = free_port();
        let handles: Vec<_> = (0..3)
            .map(|rank| {
                std::thread::spawn(move || {
                    let mut c = TcpCollective::connect(&env(rank, 3, port, 20.0), 5).unwrap();
                    c.agree_on_len(lens[rank], "test all-reduce")
                        .map_err(|e| e.to_string())
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().unwrap())
            .collect::<Vec<_>>()
    };
    assert!(run([10, 10, 10]).iter().all(|r| r.is_ok()));
    // Rank 1 differs: all three stop, each naming the counts.
    for (rank, r) in run([10, 11, 10]).into_iter().enumerate() {
        let e = r.unwrap_err();
        assert!(
            e.contains("test all-reduce")
                && e.contains("1 rank(s)")
                && e.contains("rank 0's 10")
                && e.contains(&format!("rank {rank} holds")),
            "{e}"
        );
    }
}

#[test]
fn nccl_without_a_gpu_fails_clearly_on_every_rank() {
    // No GPU here: NCCL either cannot be loaded or cannot use cuda:0;
    // both ranks must get an error (none may wait for the other forever).
    let port = free_port();
    let handles: Vec<_> = (0..2)
        .map(|rank| {
            std::thread::spawn(move || {
                let tcp = TcpCollective::connect(&env(rank, 2, port, 20.0), 3).unwrap();
                NcclCollective::new(tcp, 0)
                    .map(|_| ())
                    .unwrap_err()
                    .to_string()
            })
        })
        .collect();
    for h in handles {
        let e = h.join().unwrap();
        eprintln!("{e}");
        assert!(
            e.contains("libnccl") || e.contains("NCCL") || e.contains("cuda:0"),
            "{e}"
        );
    }
}

#[test]
fn unreachable_master_and_mismatched_config_are_clear_errors() {
    let port = free_port(); // nobody listens there
    let start = Instant::now();
    let e = TcpCollective::connect(&env(1, 2, port, 0.5), 0)
        .unwrap_err()
        .to_string();
    assert!(start.elapsed() < Duration::from_secs(10), "{e}");
    assert!(
        e.contains("MASTER_ADDR=127.0.0.1") && e.contains(&format!("MASTER_PORT={port}")),
        "{e}"
    );
    // Rank 0 alone times out naming the missing ranks.
    let e = TcpCollective::connect(&env(0, 2, free_port(), 0.3), 0)
        .unwrap_err()
        .to_string();
    assert!(e.contains("only 0 of the 1"), "{e}");
    // Different configurations are refused on both sides.
    let port = free_port();
    let root = std::thread::spawn(move || TcpCollective::connect(&env(0, 2, port, 20.0), 1));
    let e = TcpCollective::connect(&env(1, 2, port, 20.0), 2)
        .unwrap_err()
        .to_string();
    assert!(e.contains("configuration differs"), "{e}");
    let e = root.join().unwrap().unwrap_err().to_string();
    assert!(e.contains("configuration differs"), "{e}");
}
