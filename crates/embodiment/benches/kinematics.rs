//! Forward kinematics and warm-started IK on the built-in Franka.

use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::{random_q, IkOptions, IkSolver, SplitMix64};
use criterion::{black_box, criterion_group, criterion_main, Criterion};

fn bench(c: &mut Criterion) {
    let Ok(e) = Embodiment::builtin("franka") else {
        return;
    };
    let r = &e.robot;
    let mut rng = SplitMix64::new(1);
    let qs: Vec<Vec<f64>> = (0..256).map(|_| random_q(r, &mut rng)).collect();
    let mut buf = Vec::new();
    let mut i = 0;
    c.bench_function("fk_franka_all_links", |b| {
        b.iter(|| {
            i = (i + 1) % qs.len();
            r.link_poses_into(black_box(&qs[i]), &mut buf);
            black_box(&buf);
        })
    });
    let Some(tcp) = r.link_index("panda_hand_tcp") else {
        return;
    };
    let solver = IkSolver::new(r, tcp, None);
    let opts = IkOptions::default();
    // Consecutive frames 0.02 rad apart per joint: a typical warm start.
    let path: Vec<Vec<f64>> = (0..200)
        .map(|k| {
            let mut q = e.home.clone();
            for (j, v) in q.iter_mut().take(7).enumerate() {
                *v += 0.3 * ((k as f64) * 0.02 + j as f64).sin();
            }
            q
        })
        .collect();
    let targets: Vec<_> = path.iter().map(|q| r.link_pose(tcp, q)).collect();
    let mut k = 0;
    c.bench_function("ik_franka_warm_start", |b| {
        b.iter(|| {
            k = (k + 1) % (targets.len() - 1);
            black_box(solver.solve(&targets[k + 1], &path[k], &opts));
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
