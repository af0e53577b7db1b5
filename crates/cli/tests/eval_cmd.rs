//! `bridgev2w eval` and `bridgev2w eval-policy`.

use std::path::Path;
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
        .args(args)
        .output()
        .expect("run bridgev2w")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn write_png(path: &Path, w: u32, h: u32, f: impl Fn(u32, u32, u32) -> u8) {
    std::fs::create_dir_all(path.parent().expect("parent")).expect("mkdir");
    let img = image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([f(x, y, 0), f(x, y, 1), f(x, y, 2)])
    });
    img.save(path).expect("save png");
}

fn pattern(x: u32, y: u32, c: u32, t: u32) -> u8 {
    (20 + (x * 7 + y * 13 + c * 29 + t * 31) % 180) as u8
}

#[test]
fn eval_psnr_ssim_mask_iou_json() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    for t in 0..3u32 {
        let name = format!("{t:06}.png");
        // Video "a": identical; video "b": every value +10.
        write_png(&d.join("gt/a").join(&name), 24, 16, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join("pred/a").join(&name), 24, 16, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join("gt/b").join(&name), 24, 16, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join("pred/b").join(&name), 24, 16, |x, y, c| {
            pattern(x, y, c, t) + 10
        });
        // Masks: "a" agree; "b": left half vs left three quarters (IoU 2/3).
        let mask = |limit: u32| move |x: u32, _y: u32, _c: u32| if x < limit { 255 } else { 0 };
        write_png(&d.join("mgt/a").join(&name), 24, 16, mask(12));
        write_png(&d.join("mpred/a").join(&name), 24, 16, mask(12));
        write_png(&d.join("mgt/b").join(&name), 24, 16, mask(12));
        write_png(&d.join("mpred/b").join(&name), 24, 16, mask(18));
    }
    let p = |s: &str| d.join(s).to_string_lossy().into_owned();
    let json = p("out.json");
    let o = run(&[
        "eval",
        "--pred",
        &p("pred"),
        "--gt",
        &p("gt"),
        "--masks-pred",
        &p("mpred"),
        "--masks-gt",
        &p("mgt"),
        "--json",
        &json,
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(
        table.contains("| videos | PSNR | SSIM | LPIPS | FVD | Mask-IoU |"),
        "{table}"
    );
    assert!(table.contains("lpips: unavailable"), "{table}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("parse");
    assert_eq!(v["num_videos"], 2);
    // PSNR: 100 (identical) and 20 log10(255 / 10), averaged over videos.
    let expected_psnr = (100.0 + 20.0 * (255.0f64 / 10.0).log10()) / 2.0;
    let got = v["psnr"].as_f64().expect("psnr");
    assert!(
        (got - expected_psnr).abs() < 1e-4,
        "{got} vs {expected_psnr}"
    );
    // SSIM: 1 for "a"; for "b" a constant offset keeps the structure term at
    // 1 and lowers only the luminance term, so the mean lies just below 1.
    let ssim = v["ssim"].as_f64().expect("ssim");
    assert!(ssim > 0.99 && ssim < 1.0, "{ssim}");
    let iou = v["mask_iou"].as_f64().expect("iou");
    assert!((iou - (1.0 + 12.0 / 18.0) / 2.0).abs() < 1e-9, "{iou}");
    assert!(
        v["lpips"].is_null() && v["unavailable"]["fvd"].is_string(),
        "{v}"
    );
}

#[test]
fn eval_bad_input_names_video_and_frame() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let p = |s: &str| d.join(s).to_string_lossy().into_owned();
    for t in 0..2u32 {
        let name = format!("{t:06}.png");
        write_png(&d.join("gt/v").join(&name), 16, 16, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join("pred/v").join(&name), 16, 16, |x, y, c| {
            pattern(x, y, c, t)
        });
    }
    // Unmatched names.
    write_png(&d.join("pred/w/000000.png"), 16, 16, |_, _, _| 0);
    let o = run(&["eval", "--pred", &p("pred"), "--gt", &p("gt")]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("missing in --gt: [\"w\"]"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_dir_all(d.join("pred/w")).expect("rm");
    // Frame-count mismatch.
    write_png(&d.join("pred/v/000002.png"), 16, 16, |_, _, _| 0);
    let o = run(&[
        "eval",
        "--pred",
        &p("pred"),
        "--gt",
        &p("gt"),
        "--metrics",
        "psnr",
    ]);
    assert!(
        stderr(&o).contains("video \"v\": 3 predicted frames vs 2"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_file(d.join("pred/v/000002.png")).expect("rm");
    // Resolution mismatch names the frame.
    write_png(&d.join("pred/v/000001.png"), 16, 12, |_, _, _| 0);
    let o = run(&[
        "eval",
        "--pred",
        &p("pred"),
        "--gt",
        &p("gt"),
        "--metrics",
        "psnr",
    ]);
    assert!(
        stderr(&o).contains("video \"v\", frame 1: predicted 16x12"),
        "{}",
        stderr(&o)
    );
    // Corrupt image.
    std::fs::write(d.join("pred/v/000001.png"), b"not a png").expect("write");
    let o = run(&[
        "eval",
        "--pred",
        &p("pred"),
        "--gt",
        &p("gt"),
        "--metrics",
        "ssim",
    ]);
    assert!(
        stderr(&o).contains("000001.png: not a readable image"),
        "{}",
        stderr(&o)
    );
    // Unknown metric, empty folder.
    let o = run(&[
        "eval",
        "--pred",
        &p("pred"),
        "--gt",
        &p("gt"),
        "--metrics",
        "psnr,bleu",
    ]);
    assert!(
        stderr(&o).contains("unknown metric \"bleu\""),
        "{}",
        stderr(&o)
    );
    std::fs::create_dir_all(d.join("empty")).expect("mkdir");
    let o = run(&["eval", "--pred", &p("empty"), "--gt", &p("gt")]);
    assert!(stderr(&o).contains("holds no videos"), "{}", stderr(&o));
}

#[test]
fn eval_pairs_frames_by_number_not_by_sorted_name() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let p = |s: &str| d.join(s).to_string_lossy().into_owned();
    // Identical frames, named 0.png..10.png against 000000.png..000010.png:
    // sorted as strings, "10.png" comes before "2.png".
    for t in 0..11u32 {
        write_png(&d.join(format!("pred/v/{t}.png")), 16, 16, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join(format!("gt/v/{t:06}.png")), 16, 16, |x, y, c| {
            pattern(x, y, c, t)
        });
    }
    let json = p("out.json");
    let args = [
        "eval",
        "--pred",
        &p("pred"),
        "--gt",
        &p("gt"),
        "--metrics",
        "psnr",
        "--json",
        &json,
        "--overwrite",
    ];
    let o = run(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("parse");
    assert_eq!(v["psnr"].as_f64(), Some(100.0), "{v}");
    // A missing frame is named instead of shifting the rest.
    std::fs::remove_file(d.join("pred/v/5.png")).expect("rm");
    let o = run(&args);
    assert!(
        stderr(&o).contains("ground-truth frames 5 has no predicted one"),
        "{}",
        stderr(&o)
    );
    // A frame without a number, and two files of one number.
    write_png(&d.join("pred/v/5.png"), 16, 16, |x, y, c| {
        pattern(x, y, c, 5)
    });
    write_png(&d.join("pred/v/last.png"), 16, 16, |_, _, _| 0);
    let o = run(&args);
    assert!(
        stderr(&o).contains("expected a frame number"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_file(d.join("pred/v/last.png")).expect("rm");
    write_png(&d.join("pred/v/0005.png"), 16, 16, |_, _, _| 0);
    let o = run(&args);
    assert!(stderr(&o).contains("are both frame 5"), "{}", stderr(&o));
}

#[test]
fn eval_policy_table_and_json() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let real = d.join("real.json");
    let sim = d.join("sim.csv");
    std::fs::write(
        &real,
        r#"{"push": {"p1": 0.2, "p2": 0.6, "p3": 0.8}, "pick": {"p1": 0.1, "p2": 0.5, "p3": 0.9}}"#,
    )
    .expect("write");
    // push: p1 and p2 swapped (MMRV 0.8 / 3); pick: same order, linear (r = 1).
    std::fs::write(&sim, "task,policy,success_rate\npush,p1,0.5\npush,p2,0.1\npush,p3,0.9\npick,p1,0.2\npick,p2,0.6\npick,p3,1.0\n")
        .expect("write");
    let json = d.join("out.json");
    let o = run(&[
        "eval-policy",
        "--real",
        &real.to_string_lossy(),
        "--sim",
        &sim.to_string_lossy(),
        "--json",
        &json.to_string_lossy(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(table.contains("| push | 0.267 |"), "{table}");
    assert!(table.contains("| pick | 0.000 | 1.000 |"), "{table}");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("parse");
    let avg = v["average"]["mmrv"].as_f64().expect("avg");
    assert!((avg - 0.8 / 6.0).abs() < 1e-9, "{avg}");
    // Mismatched policies and out-of-range rates are errors naming them.
    std::fs::write(
        &sim,
        "push,p1,0.5\npush,p2,0.1\npick,p1,0.2\npick,p2,0.6\npick,p3,1.0\n",
    )
    .expect("write");
    let o = run(&[
        "eval-policy",
        "--real",
        &real.to_string_lossy(),
        "--sim",
        &sim.to_string_lossy(),
    ]);
    assert!(
        stderr(&o).contains("task \"push\": policies differ"),
        "{}",
        stderr(&o)
    );
    std::fs::write(&sim, "push,p1,1.5\n").expect("write");
    let o = run(&[
        "eval-policy",
        "--real",
        &real.to_string_lossy(),
        "--sim",
        &sim.to_string_lossy(),
    ]);
    assert!(
        stderr(&o).contains("success rate 1.5 is outside [0, 1]"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn eval_lpips_with_weights_file() {
    use bridgev2w_world_model::nets::lpips::Lpips;
    use bridgev2w_world_model::ComputeDevice;
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    // Random trunk, heads of ones: a valid (untrained) LPIPS network.
    tch::manual_seed(3);
    let net = Lpips::new(ComputeDevice::Cpu).expect("lpips");
    let mut named: Vec<(String, tch::Tensor)> = net.var_store().variables().into_iter().collect();
    for (k, t) in &mut named {
        if k.starts_with("lin") {
            *t = t.ones_like();
        }
    }
    let weights = d.join("lpips.safetensors");
    bridgev2w_world_model::weights::save_safetensors(&named, &weights).expect("save");
    for t in 0..2u32 {
        let name = format!("{t:06}.png");
        write_png(&d.join("gt/a").join(&name), 40, 32, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join("pred/a").join(&name), 40, 32, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join("gt/b").join(&name), 40, 32, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join("pred/b").join(&name), 40, 32, |x, y, c| {
            pattern(y, x, c, t + 1)
        });
    }
    let p = |s: &str| d.join(s).to_string_lossy().into_owned();
    let json = p("out.json");
    let o = run(&[
        "eval",
        "--pred",
        &p("pred"),
        "--gt",
        &p("gt"),
        "--metrics",
        "lpips",
        "--lpips-weights",
        &p("lpips.safetensors"),
        "--device",
        "cpu",
        "--json",
        &json,
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("parse");
    let got = v["lpips"].as_f64().expect("lpips");
    // Video "a" is identical (0); "b" differs: the mean is half of b's.
    let net = Lpips::load(&[weights], ComputeDevice::Cpu).expect("load");
    let frame = |f: &dyn Fn(u32, u32, u32) -> u8| bridgev2w_io::frame::RgbFrame {
        height: 32,
        width: 40,
        rgb: (0..32u32)
            .flat_map(|y| (0..40u32).flat_map(move |x| (0..3u32).map(move |c| (x, y, c))))
            .map(|(x, y, c)| f32::from(f(x, y, c)) / 255.0)
            .collect(),
    };
    let b: f64 = (0..2u32)
        .map(|t| {
            net.distance(
                &frame(&|x, y, c| pattern(y, x, c, t + 1)),
                &frame(&|x, y, c| pattern(x, y, c, t)),
            )
            .expect("distance")
        })
        .sum::<f64>()
        / 2.0;
    assert!(b > 0.0);
    assert!((got - b / 2.0).abs() < 1e-5 * b, "{got} vs {}", b / 2.0);
}

#[test]
fn eval_reads_h264_mp4_videos() {
    use bridgev2w_data::video::Mp4VideoWriter;
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let (w, h) = (48u32, 32u32);
    let mp4_path = d.join("pred/clip.mp4");
    std::fs::create_dir_all(d.join("pred")).expect("mkdir");
    let mut writer = Mp4VideoWriter::new(&mp4_path, w as usize, h as usize, 10).expect("writer");
    for t in 0..4u32 {
        let f = |x: u32, y: u32, c: u32| (30 + x + 2 * y + c * 30 + t * 5) as u8;
        write_png(&d.join("gt/clip").join(format!("{t:06}.png")), w, h, f);
        let rgb: Vec<u8> = (0..h)
            .flat_map(|y| (0..w).flat_map(move |x| (0..3).map(move |c| f(x, y, c))))
            .collect();
        writer.push(&rgb, t == 0).expect("encode");
    }
    std::fs::write(&mp4_path, writer.to_bytes().expect("mux")).expect("write mp4");
    let p = |s: &str| d.join(s).to_string_lossy().into_owned();
    let json = p("out.json");
    let o = run(&[
        "eval",
        "--pred",
        &p("pred"),
        "--gt",
        &p("gt"),
        "--metrics",
        "psnr,ssim",
        "--json",
        &json,
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&json).expect("json")).expect("parse");
    assert_eq!(v["num_videos"], 1);
    let psnr = v["psnr"].as_f64().expect("psnr");
    assert!(
        psnr > 30.0 && psnr < 100.0,
        "lossy H.264 round trip: {psnr} dB"
    );
    assert!(v["ssim"].as_f64().expect("ssim") > 0.9);
    // The same name as a folder and an .mp4 is ambiguous.
    write_png(&d.join("pred/clip/000000.png"), w, h, |_, _, _| 0);
    let o = run(&["eval", "--pred", &p("pred"), "--gt", &p("gt")]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("both a folder and clip.mp4"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn eval_fvd_with_i3d_weights() {
    use bridgev2w_world_model::nets::i3d::I3d;
    use bridgev2w_world_model::ComputeDevice;
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    // Random (untrained) I3D: convolutions ~ N(0, 0.05^2), BatchNorm identity-like.
    tch::manual_seed(4);
    let net = I3d::new(ComputeDevice::Cpu).expect("i3d");
    let mut named: Vec<(String, tch::Tensor)> = net.var_store().variables().into_iter().collect();
    for (k, t) in &mut named {
        *t = if k.ends_with("running_var") || k.ends_with("bn.weight") {
            t.ones_like()
        } else if k.ends_with("conv3d.weight") {
            t.randn_like() * 0.05
        } else {
            t.zeros_like()
        };
    }
    let weights = d.join("i3d.safetensors");
    bridgev2w_world_model::weights::save_safetensors(&named, &weights).expect("save");
    for v in 0..3u32 {
        for t in 0..16u32 {
            let name = format!("{t:06}.png");
            let f = move |x: u32, y: u32, c: u32| pattern(x + v * 5, y, c, t);
            write_png(&d.join(format!("gt/v{v}")).join(&name), 32, 24, f);
            write_png(&d.join(format!("same/v{v}")).join(&name), 32, 24, f);
            write_png(
                &d.join(format!("pred/v{v}")).join(&name),
                32,
                24,
                move |x, y, c| pattern(y * 2, x, c, 3 * t + v),
            );
        }
    }
    let p = |s: &str| d.join(s).to_string_lossy().into_owned();
    let fvd = |pred: &str| {
        let json = p(&format!("{pred}.json"));
        let o = run(&[
            "eval",
            "--pred",
            &p(pred),
            "--gt",
            &p("gt"),
            "--metrics",
            "fvd",
            "--i3d-weights",
            &p("i3d.safetensors"),
            "--device",
            "cpu",
            "--json",
            &json,
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("parse");
        assert!(
            v["unavailable"].as_object().is_some_and(|m| m.is_empty()),
            "{v}"
        );
        v["fvd"].as_f64().expect("fvd")
    };
    let same = fvd("same");
    let differ = fvd("pred");
    assert!(
        same.abs() < 1e-6 * differ.max(1e-12),
        "same {same}, different {differ}"
    );
    assert!(differ > 0.0, "{differ}");
    // Too short for the protocol: the error names the video.
    for t in 0..4u32 {
        let name = format!("{t:06}.png");
        write_png(&d.join("sgt/s").join(&name), 32, 24, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join("spred/s").join(&name), 32, 24, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join("sgt/s2").join(&name), 32, 24, |x, y, c| {
            pattern(x, y, c, t)
        });
        write_png(&d.join("spred/s2").join(&name), 32, 24, |x, y, c| {
            pattern(x, y, c, t)
        });
    }
    let o = run(&[
        "eval",
        "--pred",
        &p("spred"),
        "--gt",
        &p("sgt"),
        "--metrics",
        "fvd",
        "--i3d-weights",
        &p("i3d.safetensors"),
        "--device",
        "cpu",
    ]);
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(e.contains("\"s\"") && e.contains("16"), "{e}");
}
