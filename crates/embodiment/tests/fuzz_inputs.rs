//! Fuzzing the user-file parsers of `bridgev2w masks`: `.npy` arrays, camera
//! JSON and joint/action trajectories as JSON or CSV. Mutations of valid
//! files (numbers swapped for extreme or malformed ones, header fields
//! rewritten, truncations, duplicated or deleted spans, byte flips) must give
//! `Ok` or an error, never a panic; an accepted input must satisfy the type's
//! invariants (finite values, consistent shapes, a valid camera); and no
//! parse may allocate more than `ALLOC_FACTOR` times the input plus
//! `ALLOC_SLACK` on the Rust heap (a header that claims a huge shape must be
//! refused before its buffer is allocated).
//!
//! In the test suite each target runs `FUZZ_CASES` cases (default 1500);
//! `scripts/fuzz.sh npy|camera|trajectory SECONDS` runs one for a wall-clock
//! budget instead (`support/fuzz.rs` has the loop and the contract).

#[path = "support/fuzz.rs"]
mod fuzz;

use bridgev2w_embodiment::actions::{parse_csv_rows, parse_json_rows, ActionError, Trajectory};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_io::npy::{encode_npy, parse_npy};
use fuzz::{mutate_text, run_target};
use peak_alloc::PeakAlloc;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Counts the bytes the Rust heap holds and their peak.
#[global_allocator]
static ALLOCATOR: PeakAlloc = PeakAlloc;

fn guarded<T>(target: &str, case: usize, data: &[u8], parse: impl FnOnce() -> T) -> T {
    fuzz::guarded(&ALLOCATOR, target, case, data, parse)
}

/// Valid `.npy` files: several dtypes, ranks and versions.
fn npy_seeds() -> Vec<Vec<u8>> {
    let mut out = vec![
        encode_npy(
            &[3, 4],
            &(0..12).map(|i| i as f32 * 0.5).collect::<Vec<_>>(),
        ),
        encode_npy(
            &[2, 3, 5],
            &(0..30).map(|i| (i % 2) as u8).collect::<Vec<_>>(),
        ),
        encode_npy(&[7], &(0..7).map(f64::from).collect::<Vec<_>>()),
        encode_npy(&[2, 2], &[1u16, 2, 3, 4]),
    ];
    // Version 2.0 of the first (4-byte header length).
    let v1 = out[0].clone();
    let hlen = u16::from_le_bytes([v1[8], v1[9]]) as usize;
    let mut v2 = b"\x93NUMPY\x02\x00".to_vec();
    v2.extend_from_slice(&(hlen as u32).to_le_bytes());
    v2.extend_from_slice(&v1[10..]);
    out.push(v2);
    out
}

/// Header-aware `.npy` mutation: shape, dtype, order, version and length
/// fields, plus the text mutations on the header and raw flips of the data.
fn mutate_npy(seed: &[u8], rng: &mut ChaCha8Rng) -> Vec<u8> {
    let mut d = seed.to_vec();
    let header_start = if d[6] == 1 { 10 } else { 12 };
    match rng.gen_range(0..6) {
        // The header's text (shape numbers, dtype letters, quotes, brackets).
        0 | 1 => {
            let hlen = if d[6] == 1 {
                u16::from_le_bytes([d[8], d[9]]) as usize
            } else {
                u32::from_le_bytes([d[8], d[9], d[10], d[11]]) as usize
            };
            let end = (header_start + hlen).min(d.len());
            let header = mutate_text(&d[header_start..end], rng);
            d.splice(header_start..end, header);
        }
        // Another dtype.
        2 => {
            const DESCRS: [&str; 10] = [
                "'<f4'", "'>f8'", "'|u1'", "'<i8'", "'|b1'", "'<c16'", "'<U3'", "'|O'", "'<f2'",
                "'<u16'",
            ];
            let text = String::from_utf8_lossy(&d).into_owned();
            if let Some(at) = text.find("'descr': ") {
                let from = at + "'descr': ".len();
                if let Some(len) = text[from..].find(',') {
                    let w = DESCRS[rng.gen_range(0..DESCRS.len())];
                    d.splice(from..from + len, w.bytes());
                }
            }
        }
        // The version byte or the header length.
        3 => {
            if rng.gen_bool(0.5) {
                d[6] = [0u8, 1, 2, 3, 4, 255][rng.gen_range(0..6)];
            } else {
                let v: u32 = [0, 1, 9, 0xFFFF, 0x7FFF_FFFF, u32::MAX][rng.gen_range(0..6)];
                let n = if d[6] == 1 { 2 } else { 4 };
                d[8..8 + n].copy_from_slice(&v.to_le_bytes()[..n]);
            }
        }
        // A shape entry replaced by a huge one.
        4 => {
            let text = String::from_utf8_lossy(&d).into_owned();
            if let Some(at) = text.find("'shape': (") {
                let from = at + "'shape': (".len();
                if let Some(len) = text[from..].find(')') {
                    let huge = [
                        "4294967296, 4294967296",
                        "18446744073709551615,",
                        "0, 100000000000",
                        "3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20",
                        "-1, 4",
                        "",
                    ];
                    d.splice(from..from + len, huge[rng.gen_range(0..huge.len())].bytes());
                }
            }
        }
        // Raw bytes: truncation, flips, appended data.
        _ => d = mutate_text(&d, rng),
    }
    d
}

fn check_npy(case: usize, data: &[u8]) {
    if let Ok(a) = guarded("npy", case, data, || parse_npy(data)) {
        let n: Option<usize> = a.shape.iter().try_fold(1usize, |p, &s| p.checked_mul(s));
        assert_eq!(
            n,
            Some(a.data.len()),
            "npy case {case}: shape {:?} but {} values",
            a.shape,
            a.data.len()
        );
    }
}

#[test]
fn mutated_npy_files_never_panic_nor_over_allocate() {
    run_target("npy", &npy_seeds(), mutate_npy, check_npy);
}

fn camera_seeds() -> Vec<Vec<u8>> {
    vec![
        br#"{"fx": 600, "fy": 600, "cx": 359.5, "cy": 239.5, "width": 720, "height": 480,
 "distortion": [0.1, -0.05, 0.001, 0.002, 0.0],
 "world_from_camera": [[1, 0, 0, 0.5], [0, -1, 0, 0.1], [0, 0, -1, 1.2], [0, 0, 0, 1]]}"#
            .to_vec(),
        br#"{"fx": 300.5, "fy": 301, "cx": 160, "cy": 120, "width": 320, "height": 240,
 "distortion": {"k1": 0.01, "k2": 0, "p1": 0, "p2": 0, "k3": 0},
 "extrinsics_xyz_rpy": [0.8, -0.2, 0.5, -2.1, 0.0, 1.57]}"#
            .to_vec(),
    ]
}

fn check_camera(case: usize, data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    match guarded("camera", case, data, || {
        Camera::from_json_str(&text, "fuzz.json")
    }) {
        Ok(cam) => {
            let k = &cam.intrinsics;
            assert!(
                k.validate().is_ok(),
                "camera case {case}: accepted invalid intrinsics {k:?}"
            );
            let m = cam.world_from_camera.to_homogeneous();
            assert!(
                m.iter().all(|v| v.is_finite()),
                "camera case {case}: non-finite extrinsics"
            );
        }
        Err(e) => assert!(
            e.to_string().contains("fuzz.json"),
            "camera case {case}: the error does not name the file: {e}"
        ),
    }
}

#[test]
fn mutated_camera_json_never_panics_nor_accepts_garbage() {
    run_target("camera", &camera_seeds(), mutate_text, check_camera);
}

fn trajectory_seeds() -> Vec<Vec<u8>> {
    vec![
        b"[[0.4, 0.0, 0.5, 3.14, 0.0, 0.0, 0.0],\n [0.41, 0.01, 0.49, 3.14, 0.0, 0.1, 1.0]]"
            .to_vec(),
        b"x,y,z,roll,pitch,yaw,gripper\n0.4,0.0,0.5,3.14,0,0,0\n0.41,0.01,0.49,3.14,0,0.1,1\n"
            .to_vec(),
        b"0,0.1,-0.2,0.3,0,0,0,0.02\n0,0.1,-0.2,0.3,0,0.5,0,0.04\n".to_vec(),
    ]
}

fn check_trajectory(case: usize, data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    type Parse = fn(&str, &str) -> Result<Vec<Vec<f64>>, ActionError>;
    for (kind, parse) in [
        ("json", parse_json_rows as Parse),
        ("csv", parse_csv_rows as Parse),
    ] {
        let result = guarded("trajectory", case, data, || {
            parse(&text, "fuzz").and_then(|rows| Trajectory::new("fuzz", rows))
        });
        match result {
            Ok(t) => {
                assert!(!t.is_empty(), "{kind} case {case}: an empty trajectory");
                assert!(
                    t.rows
                        .iter()
                        .all(|r| r.len() == t.dim() && r.iter().all(|v| v.is_finite())),
                    "{kind} case {case}: ragged or non-finite rows accepted"
                );
            }
            Err(e) => assert!(
                e.to_string().contains("fuzz"),
                "{kind} case {case}: the error does not name the source: {e}"
            ),
        }
    }
}

#[test]
fn mutated_trajectories_never_panic_nor_accept_garbage() {
    run_target(
        "trajectory",
        &trajectory_seeds(),
        mutate_text,
        check_trajectory,
    );
}
