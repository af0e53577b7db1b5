//! `ServedPolicy` against a real server of openpi's websocket protocol
//! (`tests/data/openpi_server.py`, written with openpi-client's own
//! msgpack-numpy and `websockets`, in `.venv-policy`: `./run test` makes it
//! with `scripts/setup-policy-venv.sh`): observations arrive as the server
//! checks them, chunks come back as end-effector actions, and a server that
//! answers with the wrong shape, non-finite values, a non-numeric dtype, an
//! error, too slowly, or closes is an error naming the policy, the step and
//! the field.

use crate::policy_server;

use bridgev2w_io::frame::RgbFrame;
use bridgev2w_plan::policy::Policy;
use bridgev2w_plan::served::{ActionLayout, ServedPolicy, ServedPolicyConfig, TcpKinematics};
use bridgev2w_plan::Observation;
use policy_server::{free_port, server};

fn config() -> ServedPolicyConfig {
    let mut c = ServedPolicyConfig::default();
    c.observation.ee_pose = "observation/ee_pose".into();
    c.timeout_s = 20.0;
    c
}

fn observation() -> Observation {
    let (w, h) = (96, 64);
    Observation {
        image: RgbFrame {
            width: w,
            height: h,
            rgb: (0..w * h * 3).map(|i| (i % 251) as f32 / 255.0).collect(),
        },
        joints: vec![0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, 0.04],
        ee: [0.4, 0.0, 0.4, std::f64::consts::PI, 0.0, 0.0, 0.3],
        scene: None,
    }
}

fn error_of(mode: &str, extra: &[&str], c: ServedPolicyConfig) -> String {
    let s = server(mode, extra);
    let mut p = ServedPolicy::connect("srv", &s.url, c).expect("connect");
    p.act(&observation()).expect_err("a failure").to_string()
}

#[test]
fn a_served_policy_answers_with_end_effector_chunks() {
    let s = server("good", &[]);
    let mut p = ServedPolicy::connect("srv", &s.url, config()).expect("connect");
    let meta = p.metadata().to_string();
    assert!(
        meta.contains("\"policy\"") && meta.contains("\"test\""),
        "{meta}"
    );
    p.reset(0);
    for _ in 0..2 {
        let chunk = p.act(&observation()).expect("a chunk");
        assert_eq!(chunk.len(), 4);
        assert!((chunk[0][0] - 0.41).abs() < 1e-6 && (chunk[3][0] - 0.44).abs() < 1e-6);
        assert!((chunk[0][3] - std::f64::consts::PI).abs() < 1e-6);
        assert!((chunk[2][6] - 0.3).abs() < 1e-6, "{chunk:?}");
    }
    // Deltas are added to the observed pose; `execute` keeps the first rows.
    let d = server("delta", &[]);
    let mut c = config();
    c.action.layout = ActionLayout::EeDelta;
    c.action.execute = 2;
    let mut p = ServedPolicy::connect("delta", &d.url, c).expect("connect");
    let chunk = p.act(&observation()).expect("a chunk");
    assert_eq!(chunk.len(), 2);
    assert!((chunk[1][0] - 0.42).abs() < 1e-6, "{chunk:?}");
}

#[test]
fn joint_chunks_go_through_forward_kinematics() {
    let e = bridgev2w_embodiment::embodiment::Embodiment::builtin("franka").expect("franka");
    let k = TcpKinematics {
        robot: std::sync::Arc::new(e.robot.clone()),
        link: e.end_effectors[0].link,
    };
    let mut obs = observation();
    obs.joints = e.home.clone();
    let home = k.pose(&obs.joints);
    obs.ee[..6].copy_from_slice(&home);
    // Joint positions: the observed joints give the observed pose back.
    let s = server("joints", &[]);
    let mut c = config();
    c.action.layout = ActionLayout::JointPosition;
    let mut p = ServedPolicy::connect("joints", &s.url, c.clone()).expect("connect");
    let e1 = p.act(&obs).expect_err("no kinematics").to_string();
    assert!(e1.contains("forward kinematics"), "{e1}");
    p.set_kinematics(Some(k.clone()));
    let chunk = p.act(&obs).expect("a chunk");
    assert_eq!(chunk.len(), 4);
    for a in &chunk {
        for (x, y) in a.iter().zip(&obs.ee) {
            assert!((x - y).abs() < 1e-9, "{a:?} vs {:?}", obs.ee);
        }
    }
    // Joint velocities: 0.1 rad/s on joint 1 at 10 rows per second, chained.
    let v = server("joint_velocity", &[]);
    c.action.layout = ActionLayout::JointVelocity;
    c.action.control_hz = 10.0;
    let mut p = ServedPolicy::connect("vel", &v.url, c.clone()).expect("connect");
    p.set_kinematics(Some(k.clone()));
    let chunk = p.act(&obs).expect("a chunk");
    for (i, a) in chunk.iter().enumerate() {
        let mut q = obs.joints.clone();
        q[0] += 0.01 * (i + 1) as f64;
        let want = k.pose(&q);
        for (x, y) in a.iter().zip(&want) {
            assert!((x - y).abs() < 1e-9, "row {i}: {a:?} vs {want:?}");
        }
    }
    // A 7-wide chunk is not [steps, 8] for 7 arm joints and the gripper.
    let g = server("good", &[]);
    let mut p = ServedPolicy::connect("wide", &g.url, c).expect("connect");
    p.set_kinematics(Some(k));
    let e2 = p.act(&obs).expect_err("wrong width").to_string();
    assert!(
        e2.contains("expected [steps, 8] (7 arm joints and the gripper per step)"),
        "{e2}"
    );
}

#[test]
fn bad_answers_are_named_by_policy_step_and_field() {
    let cases: [(&str, &[&str], &[&str]); 5] = [
        ("wrong_shape", &[], &["shape [4, 6]", "expected [steps, 7]"]),
        ("non_finite", &[], &["row 1, column 2 is NaN"]),
        ("strings", &[], &["dtype <U1", "numeric"]),
        (
            "error",
            &[],
            &[
                "the server reported an error",
                "inference failed on purpose",
            ],
        ),
        ("close", &[], &["closed the connection"]),
    ];
    for (mode, extra, wants) in cases {
        let e = error_of(mode, extra, config());
        assert!(e.starts_with("policy srv, step 0: "), "{mode}: {e}");
        for w in wants {
            assert!(e.contains(w), "{mode}: {w:?} not in {e}");
        }
    }
    // A server that takes longer than the timeout.
    let mut quick = config();
    quick.timeout_s = 0.5;
    let e = error_of("slow", &["--delay", "3"], quick);
    assert!(e.contains("no answer within 0.5 s"), "{e}");
    // An observation the server does not expect: its check names the key.
    let mut small = config();
    small.observation.image_size = [100, 120];
    let e = error_of("good", &[], small);
    assert!(e.contains("image uint8 (100, 120, 3)"), "{e}");
}

#[test]
fn unreachable_servers_and_other_schemes_are_refused() {
    let port = free_port();
    let e = ServedPolicy::connect("gone", &format!("ws://127.0.0.1:{port}"), config())
        .expect_err("nothing listens")
        .to_string();
    assert!(
        e.contains("policy gone: ") && e.contains("cannot connect"),
        "{e}"
    );
    let e = ServedPolicy::connect("tls", "wss://example.org:443", config())
        .expect_err("no TLS")
        .to_string();
    assert!(e.contains("wss:// (TLS) is not built in"), "{e}");
    let e = ServedPolicy::connect("http", "http://127.0.0.1:1", config())
        .expect_err("not a websocket URL")
        .to_string();
    assert!(e.contains("expected a ws://HOST:PORT URL"), "{e}");
}
