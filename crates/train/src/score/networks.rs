//! The network metrics of [`crate::score`]: LPIPS (AlexNet trunk + v0.1
//! heads) per video, and FVD (I3D features, Frechet distance between the
//! predicted and the ground-truth sets).

use super::error::{invalid, Result, ScoreError};
use super::files::{check_numbers, read_video};
use bridgev2w_eval::frechet::{frechet_distance, Gaussian};
use bridgev2w_io::progress::Progress;
use bridgev2w_world_model::nets::i3d::I3d;
use bridgev2w_world_model::nets::lpips::Lpips;
use bridgev2w_world_model::ComputeDevice;
use std::path::Path;

/// Frames per LPIPS batch.
const LPIPS_BATCH: usize = 8;

/// Mean LPIPS over the frames of every video `names` (one network, videos
/// in turn), predicted (`pred`) against ground truth (`gt`).
pub fn lpips_scores(
    pred: &Path,
    gt: &Path,
    weights: &Path,
    device: ComputeDevice,
    names: &[String],
    progress: &dyn Progress,
) -> Result<Vec<f64>> {
    let net =
        Lpips::load(&[weights.to_path_buf()], device).map_err(|source| ScoreError::Network {
            context: format!("loading LPIPS weights {}", weights.display()),
            source,
        })?;
    progress.start(names.len(), "LPIPS");
    let mut out = Vec::with_capacity(names.len());
    for name in names {
        let ((np, p), (ng, g)) = (read_video(pred, name)?, read_video(gt, name)?);
        check_numbers(name, "frames", &np, &ng)?;
        if (p.frames, p.height, p.width) != (g.frames, g.height, g.width) {
            return invalid!(
                "video \"{name}\": predicted {} frames of {}x{} vs ground truth {} frames of {}x{}",
                p.frames,
                p.width,
                p.height,
                g.frames,
                g.width,
                g.height
            );
        }
        out.push(net.video_distance(&p, &g, LPIPS_BATCH).map_err(|source| {
            ScoreError::Network {
                context: format!("LPIPS of video \"{name}\""),
                source,
            }
        })?);
        progress.tick();
    }
    progress.finish();
    Ok(out)
}

/// FVD between the predicted and ground-truth videos: I3D logits of each
/// video's first 16 frames at 224x224, Gaussians fitted per side, Frechet
/// distance. FVD depends on the number of videos and on the implementation;
/// compare numbers computed the same way only.
pub fn fvd_score(
    pred: &Path,
    gt: &Path,
    weights: &Path,
    device: ComputeDevice,
    names: &[String],
    progress: &dyn Progress,
) -> Result<f64> {
    let net =
        I3d::load(&[weights.to_path_buf()], device).map_err(|source| ScoreError::Network {
            context: format!("loading I3D weights {}", weights.display()),
            source,
        })?;
    progress.start(2 * names.len(), "FVD");
    let (mut pred_features, mut gt_features) = (Vec::new(), Vec::new());
    for name in names {
        for (dir, out) in [(pred, &mut pred_features), (gt, &mut gt_features)] {
            let (_, v) = read_video(dir, name)?;
            out.push(net.fvd_features(&v).map_err(|source| ScoreError::Network {
                context: format!("FVD features of video \"{name}\" in {}", dir.display()),
                source,
            })?);
            progress.tick();
        }
    }
    progress.finish();
    Ok(frechet_distance(
        &Gaussian::fit(&pred_features)?,
        &Gaussian::fit(&gt_features)?,
    )?)
}
