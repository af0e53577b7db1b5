//! `bridgev2w eval` (video metrics between predicted and ground-truth videos)
//! and `bridgev2w eval-policy` (MMRV and Pearson r between real and
//! world-model success rates).

use anyhow::{bail, Context, Result};
use bridgev2w_eval::ranking::{mmrv, pearson};
use bridgev2w_eval::video::{mask_iou, psnr, ssim, Frame};
use clap::Args;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The metrics, in the paper's column order.
const METRICS: [&str; 5] = ["psnr", "ssim", "lpips", "fvd", "mask_iou"];

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Predicted videos: one folder of PNG frames (000000.png, ...) or one H.264
    /// `NAME.mp4` per video.
    #[arg(long)]
    pub pred: PathBuf,
    /// Ground-truth videos, matched to --pred by name.
    #[arg(long)]
    pub gt: PathBuf,
    /// Robot masks of the predicted videos (one folder of PNG masks per video, non-zero = robot).
    #[arg(long, requires = "masks_gt")]
    pub masks_pred: Option<PathBuf>,
    /// Robot masks of the ground-truth videos (e.g. from the dataset or `bridgev2w masks`).
    #[arg(long, requires = "masks_pred")]
    pub masks_gt: Option<PathBuf>,
    /// Comma-separated metrics: psnr, ssim, lpips, fvd, mask_iou.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "psnr,ssim,lpips,fvd,mask_iou"
    )]
    pub metrics: Vec<String>,
    /// Also write the results as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// LPIPS weights (AlexNet trunk + v0.1 heads, safetensors; see
    /// scripts/convert_reference_weights.py). Without them LPIPS is reported unavailable.
    #[arg(long)]
    pub lpips_weights: Option<PathBuf>,
    /// I3D (Kinetics-400) weights for FVD (safetensors with the PyTorch
    /// `InceptionI3d` key names; see scripts/convert_reference_weights.py).
    /// Without them FVD is reported unavailable.
    #[arg(long)]
    pub i3d_weights: Option<PathBuf>,
    /// Device for the LPIPS and I3D networks: cpu, cuda, cuda:N or auto.
    #[arg(long, default_value = "auto")]
    pub device: bridgev2w_world_model::ComputeDevice,
}

#[derive(Debug, Args)]
pub struct EvalPolicyArgs {
    /// Real-robot success rates: JSON {"task": {"policy": rate}} or CSV task,policy,success_rate.
    #[arg(long)]
    pub real: PathBuf,
    /// World-model success rates for the same tasks and policies, same formats.
    #[arg(long)]
    pub sim: PathBuf,
    /// Also write the results as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// The video names of a directory, sorted: sub-folders of PNG frames, and
/// `NAME.mp4` files (H.264) named by their stem.
fn video_names(dir: &Path, what: &str) -> Result<Vec<String>> {
    let entries =
        std::fs::read_dir(dir).with_context(|| format!("{what} directory {}", dir.display()))?;
    let mut names = Vec::new();
    for e in entries {
        let e = e.with_context(|| format!("reading {what} directory {}", dir.display()))?;
        let path = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') {
            continue;
        }
        if path.is_dir() {
            names.push(name);
        } else if is_mp4(&path) {
            let stem = path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            if dir.join(&stem).is_dir() {
                bail!(
                    "{what} directory {}: video \"{stem}\" is both a folder and {name}: keep one",
                    dir.display()
                );
            }
            names.push(stem);
        }
    }
    if names.is_empty() {
        bail!(
            "{what} directory {} holds no videos (expected one folder of PNG frames or one .mp4 per video)",
            dir.display()
        );
    }
    names.sort();
    Ok(names)
}

fn is_mp4(path: &Path) -> bool {
    path.is_file()
        && path
            .extension()
            .is_some_and(|x| x.eq_ignore_ascii_case("mp4"))
}

/// The frames of video `name` under `dir`, by frame number:
/// `dir/name/*.png` (numbered by the digits at the end of their names) or
/// `dir/name.mp4` (numbered from 0).
fn load_frames(dir: &Path, name: &str) -> Result<Vec<(u64, Frame)>> {
    let mp4 = dir.join(format!("{name}.mp4"));
    if is_mp4(&mp4) {
        let video = bridgev2w_data::video::decode_mp4(&mp4)?;
        return video
            .frames
            .iter()
            .enumerate()
            .map(|(i, f)| {
                Frame::from_rgb8(video.width, video.height, f)
                    .map(|f| (i as u64, f))
                    .with_context(|| format!("{}: frame {i}", mp4.display()))
            })
            .collect();
    }
    frame_files(&dir.join(name))?
        .into_iter()
        .map(|(i, f)| Ok((i, read_frame(&f)?)))
        .collect()
}

/// The PNG files of one video folder with their frame numbers (the digits
/// at the end of the file's stem: `000007.png`, `7.png` and `frame_7.png`
/// are frame 7), in frame order. A file without a number, or two files of
/// one number, is an error.
fn frame_files(dir: &Path) -> Result<Vec<(u64, PathBuf)>> {
    let mut files: Vec<(u64, PathBuf)> = std::fs::read_dir(dir)
        .with_context(|| format!("video folder {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x.eq_ignore_ascii_case("png")))
        .map(|p| Ok((frame_number(&p)?, p)))
        .collect::<Result<_>>()?;
    if files.is_empty() {
        bail!("video folder {} has no PNG frames", dir.display());
    }
    files.sort();
    if let Some(w) = files.windows(2).find(|w| w[0].0 == w[1].0) {
        bail!(
            "{} and {} are both frame {}: one file per frame number",
            w[0].1.display(),
            w[1].1.display(),
            w[0].0
        );
    }
    Ok(files)
}

/// The number at the end of a frame file's stem.
fn frame_number(path: &Path) -> Result<u64> {
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    let digits = stem.len() - stem.trim_end_matches(|c: char| c.is_ascii_digit()).len();
    stem[stem.len() - digits..].parse().map_err(|_| {
        anyhow::anyhow!(
            "frame {}: expected a frame number at the end of its name (e.g. 000007.png)",
            path.display()
        )
    })
}

/// Checks that predicted and ground-truth frames have the same numbers
/// (pairs are made by number, not by position).
fn check_numbers(name: &str, what: &str, pred: &[u64], gt: &[u64]) -> Result<()> {
    if pred == gt {
        return Ok(());
    }
    let missing = |from: &[u64], to: &[u64]| from.iter().find(|i| !to.contains(i)).copied();
    let detail = match (missing(gt, pred), missing(pred, gt)) {
        (Some(i), _) => format!("ground-truth {what} {i} has no predicted one"),
        (None, Some(i)) => format!("predicted {what} {i} has no ground-truth one"),
        (None, None) => String::new(),
    };
    bail!(
        "video \"{name}\": {} predicted {what} vs {} ground-truth {what}; {detail}: {what} are paired by frame number",
        pred.len(),
        gt.len()
    )
}

fn read_frame(path: &Path) -> Result<Frame> {
    let img = image::open(path)
        .with_context(|| format!("frame {}: not a readable image", path.display()))?
        .to_rgb8();
    let (w, h) = img.dimensions();
    Ok(Frame::from_rgb8(w as usize, h as usize, img.as_raw())?)
}

fn read_mask(path: &Path) -> Result<(u32, u32, Vec<u8>)> {
    let img = image::open(path)
        .with_context(|| format!("mask {}: not a readable image", path.display()))?
        .to_luma8();
    let (w, h) = img.dimensions();
    Ok((w, h, img.into_raw()))
}

/// Per-video values of the frame metrics.
#[derive(Debug, Default, Clone)]
struct VideoScores {
    psnr: Option<f64>,
    ssim: Option<f64>,
    mask_iou: Option<f64>,
}

fn score_video(a: &EvalArgs, name: &str, want: &BTreeMap<&str, bool>) -> Result<VideoScores> {
    let mut s = VideoScores::default();
    if want["psnr"] || want["ssim"] {
        let pred = load_frames(&a.pred, name)?;
        let gt = load_frames(&a.gt, name)?;
        let numbers = |v: &[(u64, Frame)]| v.iter().map(|f| f.0).collect::<Vec<_>>();
        check_numbers(name, "frames", &numbers(&pred), &numbers(&gt))?;
        let (mut sum_psnr, mut sum_ssim) = (0.0, 0.0);
        for ((i, fp), (_, fg)) in pred.iter().zip(&gt) {
            if (fp.width, fp.height) != (fg.width, fg.height) {
                bail!(
                    "video \"{name}\", frame {i}: predicted {}x{} vs ground truth {}x{}: resolutions must match",
                    fp.width, fp.height, fg.width, fg.height
                );
            }
            if want["psnr"] {
                sum_psnr += psnr(fp, fg)?;
            }
            if want["ssim"] {
                sum_ssim += ssim(fp, fg).with_context(|| format!("video \"{name}\", frame {i}"))?;
            }
        }
        let n = pred.len() as f64;
        s.psnr = want["psnr"].then_some(sum_psnr / n);
        s.ssim = want["ssim"].then_some(sum_ssim / n);
    }
    if want["mask_iou"] {
        if let (Some(mp), Some(mg)) = (&a.masks_pred, &a.masks_gt) {
            let pred = frame_files(&mp.join(name))?;
            let gt = frame_files(&mg.join(name))?;
            let numbers = |v: &[(u64, PathBuf)]| v.iter().map(|f| f.0).collect::<Vec<_>>();
            check_numbers(name, "masks", &numbers(&pred), &numbers(&gt))?;
            let mut sum = 0.0;
            for ((i, p), (_, g)) in pred.iter().zip(&gt) {
                let ((wp, hp, vp), (wg, hg, vg)) = (read_mask(p)?, read_mask(g)?);
                if (wp, hp) != (wg, hg) {
                    bail!("video \"{name}\", mask {i}: predicted {wp}x{hp} vs ground truth {wg}x{hg}: resolutions must match");
                }
                sum += mask_iou(&vp, &vg)?;
            }
            s.mask_iou = Some(sum / pred.len() as f64);
        }
    }
    Ok(s)
}

pub fn run_eval(a: &EvalArgs) -> Result<()> {
    let mut want: BTreeMap<&str, bool> = METRICS.iter().map(|&m| (m, false)).collect();
    for m in &a.metrics {
        let m = m.trim().to_ascii_lowercase();
        match want.get_mut(m.as_str()) {
            Some(w) => *w = true,
            None => bail!(
                "--metrics: unknown metric \"{m}\" (expected some of {})",
                METRICS.join(", ")
            ),
        }
    }
    let names = video_names(&a.pred, "--pred")?;
    let gt_names = video_names(&a.gt, "--gt")?;
    let missing: Vec<&String> = names.iter().filter(|n| !gt_names.contains(n)).collect();
    let extra: Vec<&String> = gt_names.iter().filter(|n| !names.contains(n)).collect();
    if !missing.is_empty() || !extra.is_empty() {
        bail!(
            "--pred and --gt videos must match by name: missing in --gt: {missing:?}; missing in --pred: {extra:?}"
        );
    }
    let mut unavailable: BTreeMap<&str, String> = BTreeMap::new();
    if want["mask_iou"] && a.masks_pred.is_none() {
        unavailable.insert(
            "mask_iou",
            "needs robot masks of both videos: --masks-pred DIR --masks-gt DIR".into(),
        );
    }
    if want["lpips"] && a.lpips_weights.is_none() {
        unavailable.insert(
            "lpips",
            "needs AlexNet + LPIPS v0.1 weights: --lpips-weights FILE".into(),
        );
    }
    if want["fvd"] && a.i3d_weights.is_none() {
        unavailable.insert("fvd", "needs I3D weights: --i3d-weights FILE".into());
    } else if want["fvd"] && names.len() < 2 {
        unavailable.insert(
            "fvd",
            format!(
                "needs at least 2 videos per side to fit the feature Gaussians, got {}",
                names.len()
            ),
        );
    }
    let pb = indicatif::ProgressBar::new(names.len() as u64).with_style(
        indicatif::ProgressStyle::with_template(
            "{msg} {bar:40} {pos}/{len} videos [{elapsed}<{eta}]",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    pb.set_message("evaluating");
    let scores = names
        .par_iter()
        .map(|n| {
            let r = score_video(a, n, &want);
            pb.inc(1);
            r
        })
        .collect::<Result<Vec<_>>>()?;
    pb.finish_and_clear();
    let lpips = match (&a.lpips_weights, want["lpips"]) {
        (Some(weights), true) => Some(lpips_scores(a, weights, &names)?),
        _ => None,
    };
    // FVD is computed exactly when it was asked for and not ruled unavailable.
    let fvd = match &a.i3d_weights {
        Some(weights) if want["fvd"] && !unavailable.contains_key("fvd") => {
            Some(fvd_score(a, weights, &names)?)
        }
        _ => None,
    };
    let mean = |f: fn(&VideoScores) -> Option<f64>| -> Option<f64> {
        let v: Vec<f64> = scores.iter().filter_map(f).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let values: BTreeMap<&str, Option<f64>> = [
        ("psnr", mean(|s| s.psnr)),
        ("ssim", mean(|s| s.ssim)),
        (
            "lpips",
            lpips.map(|v| v.iter().sum::<f64>() / v.len() as f64),
        ),
        ("fvd", fvd),
        ("mask_iou", mean(|s| s.mask_iou)),
    ]
    .into_iter()
    .collect();
    let shown: Vec<&str> = METRICS.iter().copied().filter(|m| want[m]).collect();
    let header = ["PSNR", "SSIM", "LPIPS", "FVD", "Mask-IoU"];
    let mut text = String::new();
    let cols: Vec<&str> = shown
        .iter()
        .map(|m| header[METRICS.iter().position(|x| x == m).unwrap_or(0)])
        .collect();
    text.push_str(&format!("| videos | {} |\n", cols.join(" | ")));
    text.push_str(&format!("|---|{}\n", "---|".repeat(cols.len())));
    let cells: Vec<String> = shown
        .iter()
        .map(|m| match values[m] {
            Some(v) if *m == "psnr" => format!("{v:.2}"),
            Some(v) => format!("{v:.4}"),
            None => "n/a".into(),
        })
        .collect();
    text.push_str(&format!("| {} | {} |\n", names.len(), cells.join(" | ")));
    for (m, why) in &unavailable {
        text.push_str(&format!("\n{m}: unavailable: {why}"));
    }
    if !unavailable.is_empty() {
        text.push('\n');
    }
    crate::print_stdout(&text)?;
    if let Some(path) = &a.json {
        let mut obj = serde_json::Map::new();
        for m in &shown {
            obj.insert((*m).into(), serde_json::json!(values[m]));
        }
        obj.insert("num_videos".into(), serde_json::json!(names.len()));
        obj.insert("unavailable".into(), serde_json::json!(unavailable));
        write_json_atomic(path, &serde_json::Value::Object(obj))?;
    }
    Ok(())
}

/// Video `name` under `dir` and its frame numbers.
fn read_video(dir: &Path, name: &str) -> Result<(Vec<u64>, bridgev2w_world_model::video::Video)> {
    let frames = load_frames(dir, name)?;
    let mut data = Vec::new();
    let mut size = None;
    for (i, frame) in &frames {
        let s = (frame.width, frame.height);
        if *size.get_or_insert(s) != s {
            bail!(
                "video \"{name}\" in {}: frame {i} is {}x{}, earlier frames {}x{}",
                dir.display(),
                s.0,
                s.1,
                size.map_or(0, |x| x.0),
                size.map_or(0, |x| x.1)
            );
        }
        data.extend_from_slice(&frame.rgb);
    }
    let (width, height) = size.unwrap_or((0, 0));
    let numbers = frames.iter().map(|f| f.0).collect();
    Ok((
        numbers,
        bridgev2w_world_model::video::Video {
            frames: frames.len(),
            height,
            width,
            data,
        },
    ))
}

/// Mean LPIPS over the frames of every video (one network, videos in turn).
fn lpips_scores(a: &EvalArgs, weights: &Path, names: &[String]) -> Result<Vec<f64>> {
    use bridgev2w_world_model::nets::lpips::Lpips;
    let device = a.device;
    let net = Lpips::load(&[weights.to_path_buf()], device)
        .with_context(|| format!("loading LPIPS weights {}", weights.display()))?;
    let pb = indicatif::ProgressBar::new(names.len() as u64);
    pb.set_message("LPIPS");
    let mut out = Vec::with_capacity(names.len());
    for name in names {
        let ((np, p), (ng, g)) = (read_video(&a.pred, name)?, read_video(&a.gt, name)?);
        check_numbers(name, "frames", &np, &ng)?;
        if (p.frames, p.height, p.width) != (g.frames, g.height, g.width) {
            bail!(
                "video \"{name}\": predicted {} frames of {}x{} vs ground truth {} frames of {}x{}",
                p.frames,
                p.width,
                p.height,
                g.frames,
                g.width,
                g.height
            );
        }
        out.push(
            net.video_distance(&p, &g, 8)
                .with_context(|| format!("LPIPS of video \"{name}\""))?,
        );
        pb.inc(1);
    }
    pb.finish_and_clear();
    Ok(out)
}

/// FVD between the predicted and ground-truth videos: I3D logits of each
/// video's first 16 frames at 224x224, Gaussians fitted per side, Frechet
/// distance. FVD depends on the number of videos and on the implementation;
/// compare numbers computed the same way only.
fn fvd_score(a: &EvalArgs, weights: &Path, names: &[String]) -> Result<f64> {
    use bridgev2w_eval::frechet::{frechet_distance, Gaussian};
    use bridgev2w_world_model::nets::i3d::I3d;
    let device = a.device;
    let net = I3d::load(&[weights.to_path_buf()], device)
        .with_context(|| format!("loading I3D weights {}", weights.display()))?;
    let pb = indicatif::ProgressBar::new(2 * names.len() as u64);
    pb.set_message("FVD");
    let (mut pred, mut gt) = (Vec::new(), Vec::new());
    for name in names {
        for (dir, out) in [(&a.pred, &mut pred), (&a.gt, &mut gt)] {
            let (_, v) = read_video(dir, name)?;
            out.push(net.fvd_features(&v).with_context(|| {
                format!("FVD features of video \"{name}\" in {}", dir.display())
            })?);
            pb.inc(1);
        }
    }
    pb.finish_and_clear();
    Ok(frechet_distance(
        &Gaussian::fit(&pred)?,
        &Gaussian::fit(&gt)?,
    )?)
}

/// Success rates per task and policy.
type Rates = BTreeMap<String, BTreeMap<String, f64>>;

fn read_rates(path: &Path) -> Result<Rates> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let rates: Rates = if path
        .extension()
        .is_some_and(|x| x.eq_ignore_ascii_case("csv"))
    {
        let mut rates = Rates::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || (i == 0 && line.to_ascii_lowercase().starts_with("task")) {
                continue;
            }
            let f: Vec<&str> = line.split(',').map(str::trim).collect();
            let [task, policy, rate] = f[..] else {
                bail!(
                    "{}, line {}: expected task,policy,success_rate, got \"{line}\"",
                    path.display(),
                    i + 1
                );
            };
            let rate: f64 = rate.parse().map_err(|_| {
                anyhow::anyhow!(
                    "{}, line {}: success rate \"{rate}\" is not a number",
                    path.display(),
                    i + 1
                )
            })?;
            rates
                .entry(task.into())
                .or_default()
                .insert(policy.into(), rate);
        }
        rates
    } else {
        serde_json::from_str(&text).with_context(|| {
            format!(
                "{}: expected JSON {{\"task\": {{\"policy\": success_rate}}}}",
                path.display()
            )
        })?
    };
    for (task, policies) in &rates {
        for (policy, r) in policies {
            if !(r.is_finite() && (0.0..=1.0).contains(r)) {
                bail!(
                    "{}: task \"{task}\", policy \"{policy}\": success rate {r} is outside [0, 1]",
                    path.display()
                );
            }
        }
    }
    if rates.is_empty() {
        bail!("{}: no success rates", path.display());
    }
    Ok(rates)
}

pub fn run_eval_policy(a: &EvalPolicyArgs) -> Result<()> {
    let real = read_rates(&a.real)?;
    let sim = read_rates(&a.sim)?;
    let mut rows = Vec::new();
    for (task, real_p) in &real {
        let Some(sim_p) = sim.get(task) else {
            bail!(
                "task \"{task}\" is in {} but not in {}",
                a.real.display(),
                a.sim.display()
            );
        };
        let policies: Vec<&String> = real_p.keys().collect();
        if sim_p.keys().collect::<Vec<_>>() != policies {
            bail!(
                "task \"{task}\": policies differ between {} ({:?}) and {} ({:?})",
                a.real.display(),
                policies,
                a.sim.display(),
                sim_p.keys().collect::<Vec<_>>()
            );
        }
        let r: Vec<f64> = real_p.values().copied().collect();
        let s: Vec<f64> = sim_p.values().copied().collect();
        rows.push((task.clone(), mmrv(&s, &r)?, pearson(&s, &r)?));
    }
    if let Some(task) = sim.keys().find(|t| !real.contains_key(*t)) {
        bail!(
            "task \"{task}\" is in {} but not in {}",
            a.sim.display(),
            a.real.display()
        );
    }
    let n = rows.len() as f64;
    let avg = (
        rows.iter().map(|r| r.1).sum::<f64>() / n,
        rows.iter().map(|r| r.2).sum::<f64>() / n,
    );
    let mut text = String::from("| Tasks | MMRV | Pearson r |\n|---|---|---|\n");
    for (t, m, p) in &rows {
        text.push_str(&format!("| {t} | {m:.3} | {p:.3} |\n"));
    }
    text.push_str(&format!("| Avg. | {:.3} | {:.3} |\n", avg.0, avg.1));
    crate::print_stdout(&text)?;
    if let Some(path) = &a.json {
        let tasks: serde_json::Map<String, serde_json::Value> = rows
            .iter()
            .map(|(t, m, p)| (t.clone(), serde_json::json!({"mmrv": m, "pearson": p})))
            .collect();
        let v = serde_json::json!({"tasks": tasks, "average": {"mmrv": avg.0, "pearson": avg.1}});
        write_json_atomic(path, &v)?;
    }
    Ok(())
}

/// Writes JSON through a temporary file in the same directory, renamed into place.
fn write_json_atomic(path: &Path, v: &serde_json::Value) -> Result<()> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let mut tmp = tempfile::NamedTempFile::new_in(dir)
        .with_context(|| format!("creating a temporary file in {}", dir.display()))?;
    serde_json::to_writer_pretty(&mut tmp, v)?;
    tmp.persist(path)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
