//! Property-based fuzzing of the URDF path: mutated documents must give a
//! robot or an error, never a panic, and any robot accepted must be usable
//! (finite forward kinematics at a valid configuration). Inputs that once
//! broke it live in `tests/data/urdf/regressions/` and are replayed here.

use bridgev2w_embodiment::robot::{LoadOptions, Robot};
use proptest::prelude::*;

const SEED_URDFS: [&str; 2] = [
    include_str!("../robots/franka/franka.urdf"),
    include_str!("../robots/dual_arm/dual_arm.urdf"),
];

/// Odd attribute values that parsers and builders trip over.
const WEIRD: [&str; 13] = [
    "1e39",
    "nan",
    "inf",
    "-inf",
    "1e309",
    "",
    "0 0",
    "1 2 3 4",
    "-0",
    "0",
    "abc",
    "1e-320",
    "999999999999",
];

fn check(text: &str) -> Result<(), TestCaseError> {
    let result = std::panic::catch_unwind(|| {
        Robot::from_urdf_str(text, "fuzz.urdf", None, &LoadOptions::default())
    });
    let Ok(result) = result else {
        return Err(TestCaseError::fail("Robot::from_urdf_str panicked"));
    };
    if let Ok(robot) = result {
        let q: Vec<f64> = robot
            .dof_limits()
            .iter()
            .map(|(lo, hi)| 0.0f64.clamp(*lo, *hi))
            .collect();
        let poses = robot.link_poses(&q);
        prop_assert_eq!(poses.len(), robot.links.len());
        for p in &poses {
            prop_assert!(
                p.translation.vector.iter().all(|v| v.is_finite()),
                "non-finite FK"
            );
        }
        for l in &robot.links {
            if let Some(m) = &l.mesh {
                let n = m.vertices.len() as u32;
                prop_assert!(m.triangles.iter().all(|t| t.iter().all(|&i| i < n)));
                prop_assert!(m.vertices.iter().all(|v| v.iter().all(|c| c.is_finite())));
            }
        }
    }
    Ok(())
}

/// Replace the value of the `k`-th attribute (any `="..."`) with `value`.
fn replace_attribute(text: &str, k: usize, value: &str) -> String {
    let starts: Vec<usize> = text.match_indices("=\"").map(|(i, _)| i + 2).collect();
    if starts.is_empty() {
        return text.to_string();
    }
    let s = starts[k % starts.len()];
    let e = text[s..].find('"').map_or(text.len(), |i| s + i);
    format!("{}{}{}", &text[..s], value, &text[e..])
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn attribute_values_never_panic(doc in 0usize..2, k in 0usize..10_000, w in 0usize..WEIRD.len()) {
        check(&replace_attribute(SEED_URDFS[doc], k, WEIRD[w]))?;
    }

    #[test]
    fn truncation_and_splices_never_panic(doc in 0usize..2, cut in 0usize..100_000, at in 0usize..100_000, ins in "[<>/=\" a-z0-9.]{0,12}") {
        let t = SEED_URDFS[doc];
        let mut cut = cut % (t.len() + 1);
        while !t.is_char_boundary(cut) { cut -= 1; }
        check(&t[..cut])?;
        let mut at = at % (t.len() + 1);
        while !t.is_char_boundary(at) { at -= 1; }
        check(&format!("{}{}{}", &t[..at], ins, &t[at..]))?;
    }

    #[test]
    fn deleted_elements_never_panic(doc in 0usize..2, k in 0usize..10_000) {
        // Remove the k-th line: drops joints, links, limits, parents...
        let t = SEED_URDFS[doc];
        let lines: Vec<&str> = t.lines().collect();
        let k = k % lines.len();
        let s: String = lines.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, l)| *l).collect::<Vec<_>>().join("\n");
        check(&s)?;
    }
}

#[test]
fn regressions_never_panic() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/urdf/regressions");
    let mut n = 0;
    for entry in std::fs::read_dir(dir).expect("regressions dir") {
        let path = entry.expect("entry").path();
        if path.extension().is_some_and(|e| e == "urdf") {
            match std::fs::read_to_string(&path) {
                Ok(text) => check(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display())),
                Err(_) => {
                    // Not UTF-8: the file loader must report it, not panic.
                    let err = Robot::from_urdf_file(&path, &LoadOptions::default())
                        .expect_err("invalid UTF-8");
                    assert!(err.to_string().contains(&*path.to_string_lossy()), "{err}");
                }
            }
            n += 1;
        }
    }
    assert!(n > 0, "the regression corpus is not empty");
}
