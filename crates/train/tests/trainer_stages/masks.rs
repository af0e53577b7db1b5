//! The clip pipeline's mask sources: `calc`, `seg`, their mixing, and
//! link-coded masks.

use crate::common::{config, dataset, lock};
use bridgev2w_train::trainer::Trainer;
use std::path::Path;

/// The clip pipeline's mask sources agree with the masks the synthetic world
/// wrote: `calc` rendered from the joint states and calibration (and cached),
/// and `seg` read back from PNG folders; mixing draws from both.
#[test]
fn calc_and_seg_mask_sources_and_mixing() {
    use bridgev2w_train::data::{ClipDataset, MaskKind, SourceSpec};
    let src = dataset();
    let reference = ClipDataset::open(src, "train", None, 9, 64, 96).unwrap();
    assert!(reference.has_masks());
    // A copy without masks/: calc masks are rendered for the robot and cached.
    let tmp = tempfile::tempdir().unwrap();
    let copy = tmp.path().join("nomasks");
    copy_dir(src, &copy);
    std::fs::remove_dir_all(copy.join("masks")).unwrap();
    let cache = tmp.path().join("cache");
    let spec = |masks: MaskKind, weight: f64| SourceSpec {
        root: copy.clone(),
        split: "train".into(),
        video_key: None,
        masks,
        weight,
    };
    let calc = MaskKind::Calc {
        robot: Some("franka".into()),
        cache: cache.clone(),
    };
    let rendered = ClipDataset::open_sources(&[spec(calc.clone(), 1.0)], 9, 64, 96, 3).unwrap();
    for (a, b) in rendered.episodes.iter().zip(&reference.episodes) {
        let (ma, mb) = (a.masks.as_ref().unwrap(), b.masks.as_ref().unwrap());
        let differ = ma.iter().zip(mb).filter(|(x, y)| x != y).count();
        assert_eq!(
            differ, 0,
            "episode {}: rendered calc masks differ from the synthetic ground truth",
            a.index
        );
    }
    let cached: Vec<_> = std::fs::read_dir(cache.join("observation.images.main"))
        .unwrap()
        .flatten()
        .collect();
    assert_eq!(cached.len(), 2, "one cache file per episode");
    assert!(cached[0]
        .file_name()
        .to_string_lossy()
        .ends_with("_96x64.npy"));
    // Rendering needs the calibration: its absence is an error naming the file and episode.
    let nocal = tmp.path().join("nocal");
    copy_dir(&copy, &nocal);
    std::fs::remove_dir_all(nocal.join("meta/calibration")).unwrap();
    let err = ClipDataset::open_sources(
        &[SourceSpec {
            root: nocal.clone(),
            ..spec(
                MaskKind::Calc {
                    robot: Some("franka".into()),
                    cache: tmp.path().join("c3"),
                },
                1.0,
            )
        }],
        9,
        64,
        96,
        1,
    )
    .unwrap_err();
    assert!(
        err.to_string()
            .contains("missing camera calibration of episode"),
        "{err}"
    );
    // Without a robot and without masks/, calc gives no masks (the ablation's case).
    let none = ClipDataset::open_sources(
        &[spec(
            MaskKind::Calc {
                robot: None,
                cache: tmp.path().join("c2"),
            },
            1.0,
        )],
        9,
        64,
        96,
        1,
    )
    .unwrap();
    assert!(!none.has_masks());

    // seg: PNG folders (here: the ground truth at half resolution, upsampled nearest).
    let seg = tmp.path().join("seg");
    for e in &reference.episodes {
        let dir = seg.join(format!("episode_{:06}", e.index));
        std::fs::create_dir_all(&dir).unwrap();
        let m = e.masks.as_ref().unwrap();
        for f in 0..e.frames {
            let half: Vec<u8> = (0..32 * 48)
                .map(|k| 255 * u8::from(m[f * 64 * 96 + (k / 48) * 2 * 96 + (k % 48) * 2] != 0))
                .collect();
            std::fs::write(
                dir.join(format!("{f:06}.png")),
                bridgev2w_io::png::encode_gray8(48, 32, &half),
            )
            .unwrap();
        }
    }
    let open_seg = || {
        ClipDataset::open_sources(
            &[spec(MaskKind::Seg { dir: seg.clone() }, 1.0)],
            9,
            64,
            96,
            1,
        )
    };
    let segd = open_seg().unwrap();
    for (a, b) in segd.episodes.iter().zip(&reference.episodes) {
        let (ma, mb) = (a.masks.as_ref().unwrap(), b.masks.as_ref().unwrap());
        // seg masks are 0/1; the reference holds the synthetic link labels.
        let agree = ma
            .iter()
            .zip(mb)
            .filter(|(x, y)| (**x != 0) == (**y != 0))
            .count() as f64
            / ma.len() as f64;
        assert!(
            agree > 0.97,
            "seg masks agree with the ground truth on {agree}"
        );
    }
    // A missing frame is an error naming the folder.
    std::fs::remove_file(seg.join(format!(
        "episode_{:06}/000003.png",
        reference.episodes[0].index
    )))
    .unwrap();
    let err = open_seg().unwrap_err();
    assert!(
        err.to_string().contains("11 PNG masks for 12 video frames"),
        "{err}"
    );

    // Mixing: weights 3:1 between two sources; every epoch covers each video clips_per_video times
    // within its share.
    let mixed =
        ClipDataset::open_sources(&[spec(calc.clone(), 3.0), spec(calc, 1.0)], 9, 64, 96, 20)
            .unwrap();
    assert_eq!(mixed.episodes.len(), 4);
    assert_eq!(mixed.steps_per_epoch(4), 20);
    let slots = mixed.epoch_slots(5, 0, 4000);
    let first = slots
        .iter()
        .filter(|&&i| mixed.episodes[i].source == 0)
        .count() as f64
        / 4000.0;
    assert!((first - 0.75).abs() < 0.03, "share of source 0: {first}");
    assert_eq!(slots, mixed.epoch_slots(5, 0, 4000), "deterministic");
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            copy_dir(&p, &to.join(e.file_name()));
        } else {
            std::fs::copy(&p, to.join(e.file_name())).unwrap();
        }
    }
}

#[test]
fn link_coded_masks_train_from_the_datasets_labels_and_need_them() {
    use bridgev2w_world_model::bridge::MaskCoding;
    let _g = lock();
    let tmp = tempfile::tempdir().unwrap();
    let mut c = config(&tmp.path().join("run"));
    c.model.mask_coding = MaskCoding::Links;
    let t = Trainer::new(c.clone()).unwrap();
    assert_eq!(t.model.config().mask_coding, MaskCoding::Links);
    let batch = t.batch(0).unwrap();
    // Channel 0 is the silhouette (+-1); channel 1 codes the link, so robot
    // pixels take values strictly between -1 and 1 as well.
    let silhouette = batch.masks.select(1, 0);
    assert_eq!(silhouette.abs().min().double_value(&[]), 1.0);
    let ramp = batch.masks.select(1, 1);
    let inside = ramp.gt(-0.99).logical_and(&ramp.lt(0.99));
    assert!(inside.any().int64_value(&[]) == 1, "no link-coded pixel");
    // A dataset without labels/ is refused by name.
    let copy = tmp.path().join("nolabels");
    copy_dir(dataset(), &copy);
    std::fs::remove_dir_all(copy.join("labels")).unwrap();
    c.data.dataset = copy;
    c.train.out = tmp.path().join("run2");
    let e = Trainer::new(c)
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(
        e.contains("labels/episode_") && e.contains("mask_coding"),
        "{e}"
    );
}
