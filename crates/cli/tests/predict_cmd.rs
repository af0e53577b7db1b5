//! `bridgev2w predict` end to end on random tiny weights (shapes, files, determinism,
//! and the errors a user meets first).

use bridgev2w_io::npy::{read_npy, write_npy};
use std::path::Path;

use crate::common;

use common::{ok, run, s};

#[test]
fn predict_writes_frames_and_video_deterministically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let img = image::RgbImage::from_fn(96, 64, |x, y| image::Rgb([x as u8, y as u8, 128]));
    img.save(d.join("first.png")).expect("png");
    let mut masks = vec![0u8; 9 * 64 * 96];
    for t in 0..9 {
        for y in 20..40 {
            for x in 10 + 3 * t..30 + 3 * t {
                masks[(t * 64 + y) * 96 + x] = 1;
            }
        }
    }
    write_npy(&d.join("masks.npy"), &[9, 64, 96], &masks).expect("npy");
    let args = |out: &str| {
        vec![
            "predict".to_owned(),
            "--model".into(),
            "random:tiny".into(),
            "--image".into(),
            s(&d.join("first.png")).into(),
            "--masks".into(),
            s(&d.join("masks.npy")).into(),
            "--out".into(),
            s(&d.join(out)).into(),
            "--steps".into(),
            "3".into(),
            "--device".into(),
            "cpu".into(),
        ]
    };
    // "b" with the caching CPU allocator off (BRIDGEV2W_CPU_CACHE_MB=0):
    // the allocator changes no result.
    for (out, cache_mb) in [("a", "2048"), ("b", "0")] {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
            .args(args(out))
            .env("BRIDGEV2W_CPU_CACHE_MB", cache_mb)
            .output()
            .expect("run bridgev2w");
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let va = read_npy(&d.join("a/video.npy")).expect("video a");
    let vb = read_npy(&d.join("b/video.npy")).expect("video b");
    assert_eq!(va.shape, [9, 64, 96, 3]);
    assert_eq!(va.data, vb.data, "same seed, same video (cache on and off)");
    for i in 0..9 {
        assert!(d.join(format!("a/frames/{i:06}.png")).is_file());
    }
    // video.mp4: the same frames as H.264, each decoded frame nearer
    // its own predicted frame than the next one (the codec is lossy, and
    // random weights predict noise).
    let mp4 = bridgev2w_data::video::decode_mp4(&d.join("a/video.mp4")).expect("video.mp4");
    assert_eq!((mp4.frames.len(), mp4.width, mp4.height), (9, 96, 64));
    let px = 96 * 64 * 3;
    let mean_abs = |t: usize, u: usize| {
        let want = &va.data[u * px..(u + 1) * px];
        mp4.frames[t]
            .iter()
            .zip(want)
            .map(|(&a, &b)| (f64::from(a) - b).abs())
            .sum::<f64>()
            / px as f64
    };
    for t in 0..9 {
        let (own, next) = (mean_abs(t, t), mean_abs(t, (t + 1) % 9));
        assert!(own < 20.0 && own < next, "frame {t}: {own} vs {next}");
    }

    // Masks at another resolution: the error says how to render them.
    write_npy(&d.join("small.npy"), &[9, 32, 48], &vec![0u8; 9 * 32 * 48]).expect("npy");
    let mut a = args("c");
    a[6] = s(&d.join("small.npy")).into();
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("[9, 32, 48]") && err.contains("--width 96 --height 64"),
        "{err}"
    );
    // Soft (float) masks are refused, not thresholded; link labels (uint16,
    // labels.npy) are the silhouette for this binary model: the same video.
    let labels: Vec<u16> = masks.iter().map(|&v| u16::from(v) * 7).collect();
    write_npy(&d.join("labels.npy"), &[9, 64, 96], &labels).expect("npy");
    let mut a = args("l");
    a[6] = s(&d.join("labels.npy")).into();
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let vl = read_npy(&d.join("l/video.npy")).expect("labels video");
    assert_eq!(vl.data, va.data, "labels predict what the binary masks do");
    let soft: Vec<f32> = masks.iter().map(|&v| f32::from(v) * 0.5).collect();
    write_npy(&d.join("soft.npy"), &[9, 64, 96], &soft).expect("npy");
    let mut a = args("e");
    a[6] = s(&d.join("soft.npy")).into();
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("dtype <f4") && err.contains("binary"), "{err}");
    // A grey (anti-aliased) mask: 255 inside, 128 on the edge.
    let grey: Vec<u8> = masks
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            if v == 0 {
                0
            } else if i % 2 == 0 {
                128
            } else {
                255
            }
        })
        .collect();
    write_npy(&d.join("grey.npy"), &[9, 64, 96], &grey).expect("npy");
    a[6] = s(&d.join("grey.npy")).into();
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("a value of 128 next to 255"), "{err}");
    assert!(
        !d.join("e").exists()
            && std::fs::read_dir(d).expect("read_dir").all(|e| !e
                .expect("entry")
                .file_name()
                .to_string_lossy()
                .contains("bridgev2w-tmp"))
    );
    // An existing output is refused (nothing of it changes), or replaced
    // whole with --overwrite.
    std::fs::write(d.join("a/notes.txt"), "mine").expect("write");
    let o = run(&args("a").iter().map(String::as_str).collect::<Vec<_>>());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("already exists") && err.contains("--overwrite"),
        "{err}"
    );
    assert!(d.join("a/notes.txt").is_file());
    let mut a = args("a");
    a.push("--overwrite".into());
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!d.join("a/notes.txt").exists() && d.join("a/video.npy").is_file());
    // An unknown random preset lists the presets there are.
    let mut a = args("f");
    a[2] = "random:huge".into();
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("random:huge")
            && err.contains("random:tiny")
            && err.contains("random:small2x-wide"),
        "{err}"
    );
    // A folder that is not a diffusers pipeline.
    let mut a = args("d");
    a[2] = s(d).into();
    let o = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("model_index.json"),
        "{err}"
    );
}

/// `--model OWNER/NAME` resolves from the Hugging Face cache, offline: a
/// cache tree built around a tiny random model (`refs/main` -> a snapshot);
/// a name the cache lacks is an error listing where it looked.
#[test]
fn predict_finds_a_hub_name_in_the_hugging_face_cache() {
    use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
    use bridgev2w_world_model::scheduler::SchedulerConfig;
    use bridgev2w_world_model::spec::RandomPreset;
    use bridgev2w_world_model::ComputeDevice;
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let cache = d.join("hf/hub");
    let repo = cache.join("models--bridgev2w-test--tiny-i2v");
    let commit = "4f1c2e0b9a8d7c6b5a4f3e2d1c0b9a8f7e6d5c4b";
    let (vae, tf) = RandomPreset::Tiny.configs();
    let model = BridgeV2W::random(
        BridgeV2WConfig::tiny(),
        &vae,
        &tf,
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        0,
    )
    .expect("a tiny model");
    model
        .save_backbone(&repo.join("snapshots").join(commit))
        .expect("a snapshot");
    // The adapters carry the model's settings (64x96, 9 frames).
    model
        .save_weights(&d.join("bridgev2w.safetensors"))
        .expect("weights");
    std::fs::create_dir_all(repo.join("refs")).expect("refs");
    std::fs::write(repo.join("refs/main"), commit).expect("refs/main");
    image::RgbImage::from_pixel(96, 64, image::Rgb([90, 120, 150]))
        .save(d.join("first.png"))
        .expect("png");
    write_npy(&d.join("masks.npy"), &[9, 64, 96], &vec![0u8; 9 * 64 * 96]).expect("npy");
    let predict = |model: &str, out: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
            .env("HF_HOME", d.join("hf"))
            .env_remove("HF_HUB_CACHE")
            .env_remove("HUGGINGFACE_HUB_CACHE")
            .current_dir(d)
            .args([
                "predict",
                "--model",
                model,
                "--weights",
                "bridgev2w.safetensors",
                "--image",
                "first.png",
                "--masks",
                "masks.npy",
                "--out",
                out,
                "--steps",
                "2",
                "--device",
                "cpu",
            ])
            .output()
            .expect("run bridgev2w")
    };
    let o = predict("bridgev2w-test/tiny-i2v", "a");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(
        read_npy(&d.join("a/video.npy")).expect("video").shape,
        [9, 64, 96, 3]
    );
    let o = predict("bridgev2w-test/other", "b");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success()
            && err.contains("bridgev2w-test/other: no such local folder")
            && err.contains("models--bridgev2w-test--other: not in the cache")
            && err.contains("huggingface-cli download"),
        "{err}"
    );
}

/// A moving box of robot pixels (`speed` pixels a frame), 9 frames of 64x96.
fn box_masks(speed: usize) -> Vec<u8> {
    let mut masks = vec![0u8; 9 * 64 * 96];
    for t in 0..9 {
        for y in 20..40 {
            for x in 10 + speed * t..30 + speed * t {
                masks[(t * 64 + y) * 96 + x] = 1;
            }
        }
    }
    masks
}

/// The largest difference between two uint8 videos (read as f64 values).
fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// Several clips in one call (`--masks` repeated or a folder): each clip in
/// its own folder, equal to the single-clip prediction of the same masks
/// and seed (shared batch noise) to one uint8 level (float rounding of a
/// batch of 2 vs 1 may move a value across a rounding boundary), whatever
/// the batch size; bad clips are refused before anything is predicted,
/// naming the file.
#[test]
fn predict_batches_clips_as_their_single_predictions() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let img = image::RgbImage::from_fn(96, 64, |x, y| image::Rgb([x as u8, y as u8, 128]));
    img.save(d.join("first.png")).expect("png");
    std::fs::create_dir_all(d.join("clips")).expect("clips");
    std::fs::create_dir_all(d.join("x")).expect("x");
    write_npy(&d.join("clips/a.npy"), &[9, 64, 96], &box_masks(3)).expect("npy");
    write_npy(&d.join("clips/b.npy"), &[9, 64, 96], &box_masks(6)).expect("npy");
    std::fs::write(d.join("clips/notes.txt"), "not masks").expect("notes");
    std::fs::copy(d.join("clips/a.npy"), d.join("x/a.npy")).expect("copy");
    // random:tiny's ControlNet starts with zero output projections, so its
    // masks change nothing: these weights are random:tiny's with them
    // perturbed, so each clip's masks show in its video.
    let model = bridgev2w_world_model::bridge::BridgeV2W::random(
        bridgev2w_world_model::bridge::BridgeV2WConfig::tiny(),
        &bridgev2w_world_model::spec::RandomPreset::Tiny.configs().0,
        &bridgev2w_world_model::spec::RandomPreset::Tiny.configs().1,
        bridgev2w_world_model::scheduler::SchedulerConfig::cogvideox_5b_i2v(),
        bridgev2w_world_model::ComputeDevice::Cpu,
        0,
    )
    .expect("a tiny model");
    tch::manual_seed(1);
    tch::no_grad(|| {
        for (name, mut v) in model.adapters.variables() {
            if name.contains("out_projectors") {
                v.copy_(&(tch::Tensor::randn_like(&v) * 0.05));
            }
        }
    });
    model.save_backbone(&d.join("backbone")).expect("backbone");
    model
        .save_weights(&d.join("bridgev2w.safetensors"))
        .expect("weights");
    let (backbone, weights) = (d.join("backbone"), d.join("bridgev2w.safetensors"));
    let (first, outs) = (d.join("first.png"), d.to_path_buf());
    let predict = |masks: &[&Path], out: &str, extra: &[&str]| {
        let out = outs.join(out);
        let mut a = vec![
            "predict",
            "--model",
            s(&backbone),
            "--weights",
            s(&weights),
            "--image",
            s(&first),
            "--out",
            s(&out),
            "--steps",
            "3",
            "--seed",
            "5",
            "--device",
            "cpu",
        ];
        for m in masks {
            a.extend(["--masks", s(m)]);
        }
        a.extend(extra);
        run(&a)
    };
    let video = |path: &str| read_npy(&d.join(path)).expect(path).data;
    let (a, b) = (d.join("clips/a.npy"), d.join("clips/b.npy"));
    for (m, out) in [(&a, "single-a"), (&b, "single-b")] {
        let o = predict(&[m], out, &[]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    // Two clips in one batch.
    let o = predict(&[&a, &b], "batch", &["--batch-size", "2"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("wrote 2 clips of 9 frames"));
    for clip in ["a", "b"] {
        let single = video(&format!("single-{clip}/video.npy"));
        let batched = video(&format!("batch/{clip}/video.npy"));
        let diff = max_diff(&single, &batched);
        eprintln!("batch clip {clip}: {diff} uint8 levels from its single prediction");
        assert!(
            diff <= 1.0,
            "clip {clip}: {diff} uint8 levels from its single prediction"
        );
        assert!(d.join(format!("batch/{clip}/video.mp4")).is_file());
        for i in 0..9 {
            assert!(d.join(format!("batch/{clip}/frames/{i:06}.png")).is_file());
        }
    }
    assert!(
        max_diff(&video("batch/a/video.npy"), &video("batch/b/video.npy")) > 1.0,
        "other masks, other video"
    );
    let index: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(d.join("batch/clips.json")).expect("clips.json"),
    )
    .expect("json");
    assert_eq!(index["clips"][1]["name"], "b");
    assert_eq!(index["clips"][1]["masks"], s(&b));
    // A folder (its .npy files by name) and a file, in batches of 2 (the
    // second batch a single clip): a repeated stem numbers every clip.
    let o = predict(
        &[&d.join("clips"), &d.join("x/a.npy")],
        "mixed",
        &["--batch-size", "2"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let names: Vec<String> = std::fs::read_dir(d.join("mixed"))
        .expect("mixed")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    assert_eq!(names, ["000-a", "001-b", "002-a", "clips.json"]);
    for (clip, single) in [("000-a", "a"), ("001-b", "b"), ("002-a", "a")] {
        let diff = max_diff(
            &video(&format!("single-{single}/video.npy")),
            &video(&format!("mixed/{clip}/video.npy")),
        );
        eprintln!("clip {clip}: {diff} uint8 levels from its single prediction");
        assert!(diff <= 1.0, "clip {clip}: {diff}");
    }
    // An existing output is refused, whole.
    let o = predict(&[&a, &b], "batch", &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--overwrite"), "{err}");
    assert!(d.join("batch/clips.json").is_file());

    // Bad input: nothing is written.
    // A clip at another shape: the error names its file.
    write_npy(
        &d.join("clips/c.npy"),
        &[9, 32, 48],
        &vec![0u8; 9 * 32 * 48],
    )
    .expect("npy");
    let o = predict(&[&d.join("clips")], "bad", &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("c.npy") && err.contains("[9, 32, 48]"),
        "{err}"
    );
    // A folder without masks.
    std::fs::create_dir_all(d.join("empty")).expect("empty");
    std::fs::write(d.join("empty/readme.txt"), "nothing").expect("readme");
    let o = predict(&[&a, &d.join("empty")], "bad", &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains(s(&d.join("empty"))) && err.contains("no .npy"),
        "{err}"
    );
    // A missing file, named.
    let o = predict(&[&a, &d.join("missing.npy")], "bad", &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("missing.npy"), "{err}");
    let o = predict(&[&a, &b], "bad", &["--batch-size", "0"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--batch-size"), "{err}");
    assert!(
        !d.join("bad").exists()
            && std::fs::read_dir(d).expect("read_dir").all(|e| !e
                .expect("entry")
                .file_name()
                .to_string_lossy()
                .contains("bridgev2w-tmp"))
    );
}

/// `--keep-static MARGIN_PX`: outside the region the masks have swept in
/// frames 0..=t (dilated by the margin) frame t is the first frame, byte for
/// byte; inside it, the prediction without the option (same seed).
#[test]
fn predict_keeps_the_static_scene_outside_the_swept_region() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let img = image::RgbImage::from_fn(96, 64, |x, y| image::Rgb([x as u8, y as u8, 128]));
    img.save(d.join("first.png")).expect("png");
    let masks = box_masks(3);
    write_npy(&d.join("masks.npy"), &[9, 64, 96], &masks).expect("npy");
    let run_predict = |out: &str, extra: &[&str]| {
        let (o, out) = predict_tiny(d, out, extra);
        ok(&o);
        read_npy(&out.join("video.npy")).expect("video").data
    };
    let kept = run_predict("kept", &["--keep-static", "1"]);
    let free = run_predict("free", &[]);
    let (mut outside, mut inside) = (0, 0);
    for t in 0..9usize {
        for y in 0..64usize {
            for x in 0..96usize {
                // Swept: a robot pixel of frames 0..=t within 1 pixel (square).
                let swept = (0..=t).any(|u| {
                    (y.saturating_sub(1)..=(y + 1).min(63)).any(|yy| {
                        (x.saturating_sub(1)..=(x + 1).min(95))
                            .any(|xx| masks[(u * 64 + yy) * 96 + xx] != 0)
                    })
                });
                for c in 0..3 {
                    let i = ((t * 64 + y) * 96 + x) * 3 + c;
                    if swept {
                        assert_eq!(kept[i], free[i], "frame {t} ({y}, {x}) inside");
                        inside += 1;
                    } else {
                        let want = f64::from(img.get_pixel(x as u32, y as u32)[c]);
                        assert_eq!(kept[i], want, "frame {t} ({y}, {x}) outside");
                        outside += 1;
                    }
                }
            }
        }
    }
    assert!(
        inside > 0 && outside > inside,
        "{inside} inside, {outside} outside"
    );
    assert!(
        kept.iter().zip(&free).any(|(a, b)| a != b),
        "random weights predict noise: the static scene must differ"
    );
}

/// `--vae-tile HxW`: the VAE decodes in those tiles at any resolution (here
/// below 256x256, where the default is whole frames), so the video differs
/// from the whole-frame one where the tiles blend; tiles that would not
/// join, a size that is not HxW, and tiles with `--no-vae-tiling` are
/// refused, and a refused call leaves no output.
#[test]
fn predict_decodes_in_the_vae_tiles_asked_for() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let img = image::RgbImage::from_fn(96, 64, |x, y| image::Rgb([x as u8, y as u8, 128]));
    img.save(d.join("first.png")).expect("png");
    write_npy(&d.join("masks.npy"), &[9, 64, 96], &box_masks(3)).expect("npy");
    let predict = |out: &str, extra: &[&str]| predict_tiny(d, out, extra);
    let (o, whole) = predict("whole", &[]);
    ok(&o);
    let (o, tiled) = predict("tiled", &["--vae-tile", "48x40"]);
    ok(&o);
    let whole = read_npy(&whole.join("video.npy")).expect("whole video");
    let tiled = read_npy(&tiled.join("video.npy")).expect("tiled video");
    assert_eq!(tiled.shape, [9, 64, 96, 3]);
    assert_eq!(tiled.shape, whole.shape);
    assert!(
        whole.data.iter().zip(&tiled.data).any(|(a, b)| a != b),
        "the tiles must be used: the tiled decode blends where they overlap"
    );
    // Tiles whose latent strides would not join: refused by name.
    let (o, out) = predict("bad", &["--vae-tile", "64x96"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("--vae-tile") && err.contains("64x96 px") && err.contains("would not join"),
        "{err}"
    );
    assert!(!out.exists(), "a refused call leaves no output");
    // Not HxW, or with --no-vae-tiling: usage errors.
    for extra in [
        &["--vae-tile", "144"][..],
        &["--vae-tile", "48x40", "--no-vae-tiling"],
    ] {
        let (o, out) = predict("usage", extra);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{extra:?}: {err}");
        assert!(err.contains("--vae-tile"), "{err}");
        assert!(!out.exists());
    }
}

/// `bridgev2w predict` of `random:tiny` with 2 steps on the CPU, from
/// `d/first.png` and `d/masks.npy` into `d/OUT`, with `extra` flags: the
/// run's output and the output folder.
fn predict_tiny(d: &Path, out: &str, extra: &[&str]) -> (std::process::Output, std::path::PathBuf) {
    let (first, masks, out) = (d.join("first.png"), d.join("masks.npy"), d.join(out));
    let mut args = vec![
        "predict",
        "--model",
        "random:tiny",
        "--image",
        s(&first),
        "--masks",
        s(&masks),
        "--steps",
        "2",
        "--device",
        "cpu",
        "--out",
        s(&out),
    ];
    args.extend_from_slice(extra);
    (run(&args), out)
}

/// An output that is, or contains, an input is refused before anything is
/// written, and the input survives; a mask file whose stem is not a plain
/// name (`...npy`: `..`) cannot become a clip folder outside `--out`.
#[test]
fn predict_refuses_an_output_over_its_inputs_and_clip_names_that_are_paths() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    image::RgbImage::from_fn(96, 64, |x, y| image::Rgb([x as u8, y as u8, 128]))
        .save(d.join("first.png"))
        .expect("png");
    let masks_dir = d.join("clips");
    std::fs::create_dir(&masks_dir).expect("mkdir");
    write_npy(
        &masks_dir.join("a.npy"),
        &[9, 64, 96],
        &vec![0u8; 9 * 64 * 96],
    )
    .expect("npy");
    for out in [&masks_dir, d] {
        let o = run(&[
            "predict",
            "--model",
            "random:tiny",
            "--image",
            s(&d.join("first.png")),
            "--masks",
            s(&masks_dir),
            "--steps",
            "2",
            "--device",
            "cpu",
            "--out",
            s(out),
            "--overwrite",
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success(),
            "--out {} over its input passed",
            out.display()
        );
        assert!(
            err.contains(s(&masks_dir))
                && (err.contains("is the input") || err.contains("contains the input")),
            "{err}"
        );
        assert!(masks_dir.join("a.npy").is_file(), "the input survives");
    }
    std::fs::rename(masks_dir.join("a.npy"), masks_dir.join("...npy")).expect("rename");
    let o = run(&[
        "predict",
        "--model",
        "random:tiny",
        "--image",
        s(&d.join("first.png")),
        "--masks",
        s(&masks_dir),
        "--steps",
        "2",
        "--device",
        "cpu",
        "--out",
        s(&d.join("o")),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("...npy") && err.contains("plain name"),
        "{err}"
    );
    assert!(!d.join("o").exists());
}

/// A synthetic dataset's own files feed `predict` as they are (issue 73):
/// its `labels/` (uint8 link labels) for the shipped link-coded model, and
/// for a binary model both its `labels/` and its `masks/` (the same
/// silhouette, the same video); the link-coded model refuses the binary
/// masks, naming its coding.
#[test]
fn predict_takes_a_datasets_own_labels_and_masks_for_both_codings() {
    let tmp = tempfile::tempdir().expect("tmp");
    let d = tmp.path();
    let ds = d.join("ds");
    let o = run(&[
        "synth",
        "--out",
        s(&ds),
        "--episodes-per-split",
        "1,0,0,0",
        "--frames",
        "9",
        "--tasks",
        "push",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mp4 = ds.join("videos/observation.images.main/chunk-000/file-000.mp4");
    let v = bridgev2w_data::video::decode_mp4(&mp4).expect("decode");
    let first = d.join("first.png");
    image::RgbImage::from_raw(v.width as u32, v.height as u32, v.frames[0].clone())
        .expect("frame")
        .save(&first)
        .expect("png");
    let (labels, masks) = (
        ds.join("labels/episode_000000.npy"),
        ds.join("masks/episode_000000.npy"),
    );
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo-model");
    let predict = |model: &[&str], m: &Path, out: &str| {
        let mut a = vec!["predict"];
        a.extend_from_slice(model);
        let out = d.join(out);
        a.extend(["--image", s(&first), "--masks", s(m), "--steps", "2"]);
        a.extend(["--out", s(&out)]);
        run(&a)
    };
    let (backbone, weights) = (
        shipped.join("backbone"),
        shipped.join("bridgev2w.safetensors"),
    );
    let links = ["--model", s(&backbone), "--weights", s(&weights)];
    let o = predict(&links, &labels, "links-labels");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(d.join("links-labels/video.npy").is_file());
    let o = predict(&links, &masks, "links-masks");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success()
            && err.contains("episode_000000.npy")
            && err.contains("binary masks")
            && err.contains("mask_coding = \"links\""),
        "{err}"
    );
    assert!(!d.join("links-masks").exists());
    let binary = ["--model", "random:tiny"];
    for (m, out) in [(&labels, "bin-labels"), (&masks, "bin-masks")] {
        let o = predict(&binary, m, out);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let a = read_npy(&d.join("bin-labels/video.npy")).expect("video");
    let b = read_npy(&d.join("bin-masks/video.npy")).expect("video");
    assert_eq!(a.data, b.data, "a binary model sees the labels' silhouette");
}
