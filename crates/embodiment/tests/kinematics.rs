//! Kinematics of the built-in robots against independent references.

use bridgev2w_embodiment::actions::{actions_to_joints, Trajectory};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::{
    pose_error, pose_from_xyz_rpy, random_q, xyz_rpy_from_pose, IkOptions, IkSolver, SplitMix64,
};
use nalgebra::{Isometry3, Matrix4};
use std::f64::consts::FRAC_PI_2;

/// Modified (Craig) DH: RotX(alpha) TransX(a) RotZ(theta) TransZ(d), as a
/// plain 4x4 matrix product, independent of the URDF code path.
fn mdh(a: f64, d: f64, alpha: f64, theta: f64) -> Matrix4<f64> {
    let (sa, ca) = alpha.sin_cos();
    let (st, ct) = theta.sin_cos();
    Matrix4::new(
        ct,
        -st,
        0.0,
        a, //
        st * ca,
        ct * ca,
        -sa,
        -d * sa, //
        st * sa,
        ct * sa,
        ca,
        d * ca, //
        0.0,
        0.0,
        0.0,
        1.0,
    )
}

fn rot_z(t: f64) -> Matrix4<f64> {
    mdh(0.0, 0.0, 0.0, t)
}

fn trans_z(d: f64) -> Matrix4<f64> {
    mdh(0.0, d, 0.0, 0.0)
}

/// Panda DH chain: poses of link1..7, link8 (flange), hand, hand_tcp.
fn panda_dh(q: &[f64]) -> Vec<Matrix4<f64>> {
    let table = [
        (0.0, 0.333, 0.0),
        (0.0, 0.0, -FRAC_PI_2),
        (0.0, 0.316, FRAC_PI_2),
        (0.0825, 0.0, FRAC_PI_2),
        (-0.0825, 0.384, -FRAC_PI_2),
        (0.0, 0.0, FRAC_PI_2),
        (0.088, 0.0, FRAC_PI_2),
    ];
    let mut t = Matrix4::identity();
    let mut out = Vec::new();
    for (i, (a, d, alpha)) in table.iter().enumerate() {
        t *= mdh(*a, *d, *alpha, q[i]);
        out.push(t);
    }
    t *= mdh(0.0, 0.107, 0.0, 0.0);
    out.push(t);
    t *= rot_z(-std::f64::consts::FRAC_PI_4);
    out.push(t);
    t *= trans_z(0.1034);
    out.push(t);
    out
}

fn max_abs_diff(a: &Isometry3<f64>, b: &Matrix4<f64>) -> f64 {
    (a.to_homogeneous() - b).abs().max()
}

#[test]
fn franka_fk_matches_the_dh_table() {
    let e = Embodiment::builtin("franka").expect("franka");
    let robot = &e.robot;
    assert_eq!(robot.dof(), 8, "7 arm joints + 1 finger joint");
    let names = [
        "panda_link1",
        "panda_link2",
        "panda_link3",
        "panda_link4",
        "panda_link5",
        "panda_link6",
        "panda_link7",
        "panda_link8",
        "panda_hand",
        "panda_hand_tcp",
    ];
    let idx: Vec<usize> = names
        .iter()
        .map(|n| robot.link_index(n).expect(n))
        .collect();
    let mut rng = SplitMix64::new(1);
    for _ in 0..500 {
        let q = random_q(robot, &mut rng);
        let poses = robot.link_poses(&q);
        let reference = panda_dh(&q);
        for (k, &l) in idx.iter().enumerate() {
            let err = max_abs_diff(&poses[l], &reference[k]);
            assert!(
                err < 1e-9,
                "{} differs from DH by {err} at q={q:?}",
                names[k]
            );
            // link_pose walks only the chain; same answer.
            assert!(max_abs_diff(&robot.link_pose(l, &q), &reference[k]) < 1e-9);
        }
    }
}

#[test]
fn mimic_finger_moves_opposite() {
    let e = Embodiment::builtin("franka").expect("franka");
    let r = &e.robot;
    let (lf, rf, hand) = (
        r.link_index("panda_leftfinger").expect("lf"),
        r.link_index("panda_rightfinger").expect("rf"),
        r.link_index("panda_hand").expect("hand"),
    );
    let mut q = e.home.clone();
    let g = r.dof_index("panda_finger_joint1").expect("finger dof");
    q[g] = 0.03;
    let p = r.link_poses(&q);
    let l_in_hand = p[hand].inverse() * p[lf];
    let r_in_hand = p[hand].inverse() * p[rf];
    assert!(
        (l_in_hand.translation.y - 0.03).abs() < 1e-12,
        "{l_in_hand}"
    );
    assert!(
        (r_in_hand.translation.y + 0.03).abs() < 1e-12,
        "{r_in_hand}"
    );
}

#[test]
fn trajectory_fk_is_parallel_and_deterministic() {
    let e = Embodiment::builtin("franka").expect("franka");
    let mut rng = SplitMix64::new(7);
    let qs: Vec<Vec<f64>> = (0..300).map(|_| random_q(&e.robot, &mut rng)).collect();
    let batched = e.robot.trajectory_link_poses(&qs);
    for (q, poses) in qs.iter().zip(&batched) {
        assert_eq!(&e.robot.link_poses(q), poses);
    }
}

#[test]
fn euler_convention_is_extrinsic_xyz() {
    // R = Rz(yaw) Ry(pitch) Rx(roll): rotating x by roll=90deg maps y to z.
    let p = pose_from_xyz_rpy([0.0, 0.0, 0.0, FRAC_PI_2, 0.0, 0.0]);
    let y = p.rotation * nalgebra::Vector3::y();
    assert!((y - nalgebra::Vector3::z()).norm() < 1e-12);
    // Extrinsic: roll then yaw about fixed axes: x-axis after roll stays x, after yaw 90 -> y.
    let p = pose_from_xyz_rpy([0.0, 0.0, 0.0, 0.3, 0.0, FRAC_PI_2]);
    let x = p.rotation * nalgebra::Vector3::x();
    assert!((x - nalgebra::Vector3::y()).norm() < 1e-12, "{x}");
    let v = [0.1, -0.2, 0.3, 0.4, -0.5, 0.6];
    let back = xyz_rpy_from_pose(&pose_from_xyz_rpy(v));
    for k in 0..6 {
        assert!((back[k] - v[k]).abs() < 1e-12);
    }
}

/// FK -> IK -> FK over random reachable poses, warm-started from a nearby
/// configuration (as consecutive frames of a trajectory are).
#[test]
fn ik_round_trip_warm_start() {
    let e = Embodiment::builtin("franka").expect("franka");
    let r = &e.robot;
    let tcp = r.link_index("panda_hand_tcp").expect("tcp");
    let solver = IkSolver::new(r, tcp, None);
    assert_eq!(
        solver.free_dofs(),
        &[0, 1, 2, 3, 4, 5, 6],
        "finger joint is not on the tcp chain"
    );
    let opts = IkOptions::default();
    let limits = r.dof_limits();
    let mut rng = SplitMix64::new(42);
    let n = 1000;
    let mut ok = 0;
    for _ in 0..n {
        let q_true = random_q(r, &mut rng);
        let target = r.link_pose(tcp, &q_true);
        // Previous frame: within ~0.1 rad per joint.
        let q_prev: Vec<f64> = q_true
            .iter()
            .zip(&limits)
            .map(|(v, (lo, hi))| (v + rng.uniform(-0.1, 0.1)).clamp(*lo, *hi))
            .collect();
        let sol = solver.solve(&target, &q_prev, &opts);
        let (dp, dr) = pose_error(&r.link_pose(tcp, &sol.q), &target);
        // The reported residual is the true residual.
        assert!((dp - sol.position_error_m).abs() < 1e-9);
        assert!(r.check_q(&sol.q, 1e-12).is_ok(), "solution within limits");
        if dp <= 1e-3 && dr <= 0.5f64.to_radians() {
            ok += 1;
        }
    }
    eprintln!("warm-start IK: {ok}/{n} within 1 mm / 0.5 deg");
    assert!(ok * 100 >= 99 * n, "{ok}/{n} poses reached with warm start");
}

#[test]
fn ik_cold_start_uses_restarts() {
    let e = Embodiment::builtin("franka").expect("franka");
    let r = &e.robot;
    let tcp = r.link_index("panda_hand_tcp").expect("tcp");
    let solver = IkSolver::new(r, tcp, None);
    let opts = IkOptions::default();
    let mut rng = SplitMix64::new(3);
    let n = 200;
    let mut ok = 0;
    for _ in 0..n {
        let target = r.link_pose(tcp, &random_q(r, &mut rng));
        let sol = solver.solve(&target, &e.home, &opts);
        ok += usize::from(sol.reached);
        // Deterministic: the same solve gives the same answer.
        assert_eq!(solver.solve(&target, &e.home, &opts), sol);
    }
    eprintln!("cold-start IK: {ok}/{n} reached");
    assert!(
        ok * 100 >= 97 * n,
        "{ok}/{n} reached from home with restarts"
    );
}

#[test]
fn ik_unreachable_target_is_reported_not_silently_wrong() {
    let e = Embodiment::builtin("franka").expect("franka");
    let tcp = e.robot.link_index("panda_hand_tcp").expect("tcp");
    let solver = IkSolver::new(&e.robot, tcp, None);
    let opts = IkOptions {
        restarts: 4,
        ..IkOptions::default()
    };
    let sol = solver.solve(
        &pose_from_xyz_rpy([2.0, 0.0, 0.5, 3.1, 0.0, 0.0]),
        &e.home,
        &opts,
    );
    assert!(!sol.reached);
    assert!(sol.position_error_m > 0.5, "{}", sol.position_error_m);
}

fn franka_actions_from_joints(e: &Embodiment, qs: &[Vec<f64>], gripper: f64) -> Trajectory {
    let tcp = e.robot.link_index("panda_hand_tcp").expect("tcp");
    let rows = qs
        .iter()
        .map(|q| {
            let mut a = xyz_rpy_from_pose(&e.robot.link_pose(tcp, q)).to_vec();
            a.push(gripper);
            a
        })
        .collect();
    Trajectory::new("test-actions", rows).expect("valid")
}

#[test]
fn actions_to_joints_follow_a_trajectory() {
    let e = Embodiment::builtin("franka").expect("franka");
    let tcp = e.robot.link_index("panda_hand_tcp").expect("tcp");
    // A smooth joint-space sweep from home.
    let qs: Vec<Vec<f64>> = (0..40)
        .map(|t| {
            let s = t as f64 / 39.0;
            let mut q = e.home.clone();
            q[0] += 0.8 * s;
            q[1] += 0.3 * (s * 3.0).sin();
            q[3] += 0.4 * s;
            q[5] -= 0.3 * s;
            q
        })
        .collect();
    let actions = franka_actions_from_joints(&e, &qs, 1.0);
    let (joints, residuals) = actions_to_joints(
        &e.robot,
        &e.end_effectors,
        &actions,
        &e.home,
        &IkOptions::default(),
        false,
    )
    .expect("reachable");
    assert_eq!(joints.len(), 40);
    assert_eq!(residuals.len(), 40);
    let g = e.robot.dof_index("panda_finger_joint1").expect("finger");
    for (f, q) in joints.iter().enumerate() {
        let (dp, dr) = pose_error(&e.robot.link_pose(tcp, q), &e.robot.link_pose(tcp, &qs[f]));
        assert!(
            dp < 1e-3 && dr < 0.5f64.to_radians(),
            "frame {f}: {dp} m {dr} rad"
        );
        assert!(q[g].abs() < 1e-12, "gripper 1 = closed = lower limit");
    }
    // Warm start: after the first frame, no restarts were needed.
    assert!(residuals.iter().skip(1).all(|r| r.restarts == 0));
}

#[test]
fn action_errors_name_frame_and_value() {
    let e = Embodiment::builtin("franka").expect("franka");
    let opts = IkOptions::default();
    let wrong = Trajectory::new("a.json", vec![vec![0.0; 6]]).expect("valid table");
    let err = actions_to_joints(&e.robot, &e.end_effectors, &wrong, &e.home, &opts, false)
        .expect_err("wrong dim")
        .to_string();
    assert!(
        err.contains("6 values per frame") && err.contains("expects 7"),
        "{err}"
    );

    let far = Trajectory::new(
        "far.json",
        vec![
            vec![0.4, 0.0, 0.5, 3.1, 0.0, 0.0, 0.0],
            vec![3.0, 0.0, 0.5, 3.1, 0.0, 0.0, 0.0],
        ],
    )
    .expect("valid table");
    let err = actions_to_joints(&e.robot, &e.end_effectors, &far, &e.home, &opts, false)
        .expect_err("unreachable")
        .to_string();
    assert!(
        err.contains("far.json") && err.contains("frame 1") && err.contains("--allow-ik-residual"),
        "{err}"
    );
    let (joints, res) =
        actions_to_joints(&e.robot, &e.end_effectors, &far, &e.home, &opts, true).expect("allowed");
    assert_eq!(joints.len(), 2);
    assert!(res[0].reached && !res[1].reached);

    let bad_grip =
        Trajectory::new("g.json", vec![vec![0.4, 0.0, 0.5, 3.1, 0.0, 0.0, 1.5]]).expect("valid");
    let err = actions_to_joints(&e.robot, &e.end_effectors, &bad_grip, &e.home, &opts, false)
        .expect_err("gripper")
        .to_string();
    assert!(err.contains("1.5") && err.contains("gripper"), "{err}");

    let err = Trajectory::new("n.json", vec![vec![0.0, f64::NAN]])
        .expect_err("nan")
        .to_string();
    assert!(
        err.contains("frame 0, column 1") && err.contains("NaN"),
        "{err}"
    );
    let err = Trajectory::new("r.json", vec![vec![0.0, 1.0], vec![1.0]])
        .expect_err("ragged")
        .to_string();
    assert!(err.contains("frame 1 has 1 values"), "{err}");
}

/// Dual-arm 14-D actions (left then right) on the AgiBot G1: each arm's IK
/// moves only its own joints; grippers map onto their finger joints.
#[test]
fn dual_arm_actions_round_trip() {
    let e = Embodiment::builtin("dual-arm").expect("g1");
    let r = &e.robot;
    assert_eq!(e.action_dim(), 14);
    let (lt, rt) = (e.end_effectors[0].link, e.end_effectors[1].link);
    // A joint-space motion of both arms from a bent-elbow pose.
    let qs: Vec<Vec<f64>> = (0..20)
        .map(|t| {
            let s = t as f64 / 19.0;
            let mut q = e.home.clone();
            for (arm, sign) in [("left", 1.0), ("right", -1.0)] {
                let d = |j: usize| r.dof_index(&format!("{arm}_arm_joint{j}")).expect("joint");
                q[d(1)] = -0.6 - 0.3 * s;
                q[d(2)] = sign * (0.2 + 0.2 * s);
                q[d(4)] = -1.2 + 0.4 * s;
                q[d(6)] = 0.3 * s;
            }
            q
        })
        .collect();
    let rows: Vec<Vec<f64>> = qs
        .iter()
        .enumerate()
        .map(|(t, q)| {
            let mut a = xyz_rpy_from_pose(&r.link_pose(lt, q)).to_vec();
            a.push(if t < 10 { 0.0 } else { 1.0 });
            a.extend(xyz_rpy_from_pose(&r.link_pose(rt, q)));
            a.push(0.5);
            a
        })
        .collect();
    let actions = Trajectory::new("dual.json", rows).expect("valid");
    let (joints, residuals) = actions_to_joints(
        r,
        &e.end_effectors,
        &actions,
        &e.home,
        &IkOptions::default(),
        false,
    )
    .expect("reachable");
    assert_eq!(residuals.len(), 40, "one residual per arm per frame");
    let lg = e.end_effectors[0].gripper_dof.expect("left gripper");
    let rg = e.end_effectors[1].gripper_dof.expect("right gripper");
    let (lo, hi) = r.dof_limits()[lg];
    for (t, q) in joints.iter().enumerate() {
        for link in [lt, rt] {
            let (dp, dr) = pose_error(&r.link_pose(link, q), &r.link_pose(link, &qs[t]));
            assert!(
                dp < 1e-3 && dr < 0.5f64.to_radians(),
                "frame {t}: {dp} m {dr} rad"
            );
        }
        let expected_left = if t < 10 { hi } else { lo };
        assert!((q[lg] - expected_left).abs() < 1e-12);
        assert!((q[rg] - 0.5 * (lo + hi)).abs() < 1e-12);
    }
}
