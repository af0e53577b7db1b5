//! Opening the sources: episodes read into memory with their masks
//! (stored, rendered from the joints, or segmented) and link labels.

use super::*;

impl ClipDataset {
    /// A single source with `calc` masks (stored ones only) and one clip per
    /// video and epoch.
    pub fn open(
        root: &Path,
        split: &str,
        video_key: Option<&str>,
        clip_frames: usize,
        height: usize,
        width: usize,
    ) -> Result<Self> {
        let spec = SourceSpec {
            root: root.to_path_buf(),
            split: split.to_string(),
            video_key: video_key.map(str::to_string),
            masks: MaskKind::Calc {
                robot: None,
                cache: root.join(".bridgev2w-mask-cache"),
            },
            weight: 1.0,
        };
        Self::open_sources(&[spec], clip_frames, height, width, 1)
    }

    /// Reads every source's episodes (see [`SourceSpec`]); all sources must
    /// share one action size.
    pub fn open_sources(
        specs: &[SourceSpec],
        clip_frames: usize,
        height: usize,
        width: usize,
        clips_per_video: usize,
    ) -> Result<Self> {
        if specs.is_empty() {
            return Err(TrainError::input("data", "no dataset given"));
        }
        if clips_per_video == 0 {
            return Err(TrainError::input(
                "data.clips_per_video",
                "0: expected >= 1",
            ));
        }
        let mut episodes = Vec::new();
        let mut sources = Vec::new();
        let mut action_dim: Option<(usize, String)> = None;
        for (s, spec) in specs.iter().enumerate() {
            if !(spec.weight.is_finite() && spec.weight > 0.0) {
                return Err(TrainError::input(
                    format!("dataset {}", spec.root.display()),
                    format!("weight {}: expected a positive number", spec.weight),
                ));
            }
            let (eps, a) = Self::read_source(spec, s, clip_frames)?;
            let name = spec.root.display().to_string();
            match &action_dim {
                Some((d, first)) if *d != a => {
                    return Err(TrainError::input(
                        format!("dataset {name}"),
                        format!("action size {a} differs from {first}'s {d}: mixed sources need one action layout"),
                    ))
                }
                Some(_) => {}
                None => action_dim = Some((a, name.clone())),
            }
            episodes.extend(eps);
            sources.push((name, spec.weight));
        }
        Ok(Self {
            episodes,
            action_dim: action_dim.map_or(0, |(a, _)| a),
            clip_frames,
            height,
            width,
            clips_per_video,
            sources,
            mask_coding: MaskCoding::Binary,
        })
    }

    /// Sets the batches' mask coding; [`MaskCoding::Links`] needs link labels
    /// in every episode (an error names the first dataset without them).
    pub fn set_mask_coding(&mut self, coding: MaskCoding) -> Result<()> {
        if coding == MaskCoding::Links {
            if let Some(e) = self.episodes.iter().find(|e| !e.link_labels) {
                let (name, _) = &self.sources[e.source];
                return Err(TrainError::input(
                    format!("dataset {name} episode {}", e.index),
                    format!("no link labels (labels/episode_{:06}.npy, which `bridgev2w synth` writes): model.mask_coding = \"links\" needs them; use \"binary\"", e.index),
                ));
            }
        }
        self.mask_coding = coding;
        Ok(())
    }

    /// The episodes of one source and their action size.
    fn read_source(
        spec: &SourceSpec,
        source: usize,
        clip_frames: usize,
    ) -> Result<(Vec<Episode>, usize)> {
        let (root, split, video_key) = (
            spec.root.as_path(),
            spec.split.as_str(),
            spec.video_key.as_deref(),
        );
        let embodiment = match &spec.masks {
            MaskKind::Calc { robot: Some(r), .. } => Some(
                Embodiment::load(r, &Default::default(), &[], &[])
                    .map_err(|e| TrainError::input("data.robot", e.to_string()))?,
            ),
            _ => None,
        };
        let ds = LeRobotDataset::open(root)
            .map_err(|e| TrainError::input(format!("dataset {}", root.display()), e.to_string()))?;
        let key = match video_key {
            Some(k) => k.to_owned(),
            None => ds.video_keys.first().cloned().ok_or_else(|| {
                TrainError::input(format!("dataset {}", root.display()), "no video keys")
            })?,
        };
        let has_splits = ds.episodes.iter().any(|e| e.split.is_some());
        let chosen: Vec<i64> = ds
            .episodes
            .iter()
            .filter(|e| !has_splits || e.split.as_deref() == Some(split))
            .map(|e| e.episode_index)
            .collect();
        if chosen.is_empty() {
            return Err(TrainError::input(
                format!("dataset {}", root.display()),
                format!("no episodes in split {split:?}"),
            ));
        }
        let derr = |e: bridgev2w_data::lerobot::DatasetError| {
            TrainError::input(format!("dataset {}", root.display()), e.to_string())
        };
        let mut episodes = Vec::with_capacity(chosen.len());
        let mut action_dim = None;
        for idx in chosen {
            let rows = ds.read_episode(idx).map_err(derr)?.frames;
            let frames = ds.read_video(idx, &key).map_err(derr)?;
            let t = frames.len();
            if t < clip_frames {
                return Err(TrainError::input(
                    format!("dataset {} episode {idx}", root.display()),
                    format!("{t} frames, shorter than a clip of {clip_frames}"),
                ));
            }
            let (h, w) = match video_shape(&ds, &key) {
                Some(hw) => hw,
                None => {
                    return Err(TrainError::input(
                        format!("dataset {}", root.display()),
                        format!("no shape for video {key:?} in meta/info.json"),
                    ))
                }
            };
            let masks: Option<EpisodeMasks> = match &spec.masks {
                MaskKind::Calc { robot, cache } => {
                    let stored = root.join(format!("masks/episode_{idx:06}.npy")).is_file();
                    if stored || robot.is_some() {
                        Some(
                            calc_masks(&ds, idx, &key, (t, w, h), embodiment.as_ref(), cache)
                                .map_err(derr)?,
                        )
                    } else {
                        None
                    }
                }
                MaskKind::Seg { dir } => Some(seg_masks(dir, idx, t).map_err(derr)?),
            };
            let mut rgb = Vec::with_capacity(t * h * w * 3);
            for (i, f) in frames.iter().enumerate() {
                if f.len() != h * w * 3 {
                    return Err(TrainError::input(
                        format!("dataset {} episode {idx} frame {i}", root.display()),
                        format!("{} bytes, expected {h}x{w}x3", f.len()),
                    ));
                }
                rgb.extend_from_slice(f);
            }
            // The dataset's link labels, where it has them, in place of 0/1.
            let (masks, link_labels) = match (masks, &spec.masks) {
                (Some(m), MaskKind::Calc { .. }) => {
                    match read_link_labels(&ds, idx, &m).map_err(derr)? {
                        Some(data) => (Some(EpisodeMasks { data, ..m }), true),
                        None => (Some(m), false),
                    }
                }
                (m, _) => (m, false),
            };
            let masks = match masks {
                Some(m) => {
                    if m.frames != t {
                        return Err(TrainError::input(
                            format!("dataset {} episode {idx} masks", root.display()),
                            format!("{} mask frames for {t} video frames", m.frames),
                        ));
                    }
                    check_mask_aspect(&m, (h, w)).map_err(|message| {
                        TrainError::input(
                            format!("dataset {} episode {idx} masks", root.display()),
                            message,
                        )
                    })?;
                    Some(resize_masks_nearest(&m, (h, w)))
                }
                None => None,
            };
            let a = rows.first().map(|r| r.action.len()).unwrap_or(0);
            if a == 0 || rows.len() != t || rows.iter().any(|r| r.action.len() != a) {
                return Err(TrainError::input(
                    format!("dataset {} episode {idx}", root.display()),
                    format!(
                        "{} action rows for {t} frames (expected one non-empty action per frame, one size)",
                        rows.len()
                    ),
                ));
            }
            if *action_dim.get_or_insert(a) != a {
                return Err(TrainError::input(
                    format!("dataset {} episode {idx}", root.display()),
                    format!("action size {a} differs from other episodes'"),
                ));
            }
            episodes.push(Episode {
                index: idx,
                frames: t,
                height: h,
                width: w,
                rgb,
                masks,
                link_labels,
                actions: rows.iter().flat_map(|r| r.action.iter().copied()).collect(),
                source,
            });
        }
        Ok((episodes, action_dim.unwrap_or(0)))
    }
}

/// Masks of another size than the video's `(h, w)` are resized, but only
/// when they have its aspect ratio (within 2 %): anything else (e.g. masks
/// stored `[T, W, H]`) would be stretched into garbage.
pub(super) fn check_mask_aspect(
    m: &EpisodeMasks,
    (h, w): (usize, usize),
) -> std::result::Result<(), String> {
    if (m.height, m.width) == (h, w) {
        return Ok(());
    }
    let mask = m.width as f64 / m.height as f64;
    let video = w as f64 / h as f64;
    if (mask / video - 1.0).abs() <= 0.02 {
        return Ok(());
    }
    // Transposed: the mask's H/W is the video's W/H.
    let hint = if m.height * h == m.width * w {
        " (stored [T, W, H]? expected [T, H, W])"
    } else {
        ""
    };
    Err(format!(
        "{}x{} (HxW) for {h}x{w} video frames{hint}: masks of another aspect ratio cannot be resized to the video",
        m.height, m.width
    ))
}

/// Nearest-neighbour resize of every mask frame to `(h, w)` (masks from a
/// segmentation tool may come at another resolution than the video).
fn resize_masks_nearest(m: &EpisodeMasks, (h, w): (usize, usize)) -> Vec<u8> {
    if (m.height, m.width) == (h, w) {
        return m.data.clone();
    }
    let mut out = Vec::with_capacity(m.frames * h * w);
    for f in 0..m.frames {
        let frame = &m.data[f * m.height * m.width..(f + 1) * m.height * m.width];
        for y in 0..h {
            let sy = ((y as f64 + 0.5) * m.height as f64 / h as f64) as usize;
            for x in 0..w {
                let sx = ((x as f64 + 0.5) * m.width as f64 / w as f64) as usize;
                out.push(frame[sy.min(m.height - 1) * m.width + sx.min(m.width - 1)]);
            }
        }
    }
    out
}

fn video_shape(ds: &LeRobotDataset, key: &str) -> Option<(usize, usize)> {
    let shape = ds
        .info
        .get("features")?
        .get(key)?
        .get("shape")?
        .as_array()?;
    let dims: Vec<usize> = shape
        .iter()
        .filter_map(|v| v.as_u64().map(|x| x as usize))
        .collect();
    let names = ds.info["features"][key]
        .get("names")
        .and_then(|n| n.as_array())
        .map(|n| n.iter().filter_map(|x| x.as_str()).collect::<Vec<_>>());
    match (dims.as_slice(), names.as_deref()) {
        ([c, h, w], Some(["channels", ..])) if *c == 3 => Some((*h, *w)),
        ([h, w, 3], _) => Some((*h, *w)),
        _ => None,
    }
}
