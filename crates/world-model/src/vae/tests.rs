use super::*;

#[test]
fn frame_batches_match_diffusers() {
    assert_eq!(frame_batches(1, 8), vec![(0, 1)]);
    assert_eq!(frame_batches(5, 8), vec![(0, 5)]);
    assert_eq!(frame_batches(9, 8), vec![(0, 9)]);
    assert_eq!(frame_batches(13, 8), vec![(0, 13)]);
    assert_eq!(frame_batches(16, 8), vec![(0, 8), (8, 16)]);
    assert_eq!(frame_batches(17, 8), vec![(0, 9), (9, 17)]);
    assert_eq!(frame_batches(49, 8).len(), 6);
    assert_eq!(frame_batches(49, 8)[0], (0, 9));
    assert_eq!(
        frame_batches(13, 2),
        vec![(0, 3), (3, 5), (5, 7), (7, 9), (9, 11), (11, 13)]
    );
    assert_eq!(frame_batches(1, 2), vec![(0, 1)]);
}

#[test]
fn presets_validate() {
    for cfg in [
        VaeConfig::cogvideox_5b_i2v(),
        VaeConfig::cogvideox_2b(),
        VaeConfig::tiny(),
    ] {
        cfg.validate(Path::new("preset"))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(cfg.spatial_compression(), 8);
        assert_eq!(cfg.temporal_compress_level(), 2);
    }
    use crate::transformer::TransformerConfig;
    for (small, tf, space, time_levels) in [
        (VaeConfig::small(), TransformerConfig::small(), 4, 2),
        (VaeConfig::small_2x(), TransformerConfig::small_2x(), 2, 0),
        (
            VaeConfig::small_2x(),
            TransformerConfig::small_2x_wide(),
            2,
            0,
        ),
    ] {
        tf.validate(Path::new("transformer preset"))
            .unwrap_or_else(|e| panic!("{e}"));
        small
            .validate(Path::new("small"))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            (small.spatial_compression(), small.temporal_compress_level()),
            (space, time_levels)
        );
        // The small transformer denoises the small VAE's latents (noisy ++ image).
        assert_eq!(
            (tf.in_channels, tf.out_channels()),
            (2 * small.latent_channels, small.latent_channels)
        );
        assert_eq!(
            (tf.sample_height, tf.sample_width),
            (
                small.sample_height / small.spatial_compression(),
                small.sample_width / small.spatial_compression()
            )
        );
        // Every token covers 8x8 pixels in both presets.
        assert_eq!(tf.patch_size * small.spatial_compression(), 8);
        // A token's noise and image values fit its width, so the
        // sampler can see all the noise it has to remove.
        assert!(tf.patch_size.pow(2) * tf.in_channels <= tf.inner_dim());
        // Its learned positions are sized for the VAE's latent frames.
        assert_eq!(
            tf.temporal_compression_ratio,
            small.temporal_compression_ratio as i64
        );
    }
    let t = Tiling::for_config(&VaeConfig::cogvideox_5b_i2v());
    assert_eq!(
        (t.tile_sample_min_height, t.tile_sample_min_width),
        (240, 360)
    );
    assert_eq!(
        (t.tile_latent_min_height, t.tile_latent_min_width),
        (30, 45)
    );
}

#[test]
fn time_compression_beyond_the_resampling_blocks_is_refused() {
    let cfg = VaeConfig {
        temporal_compression_ratio: 4.0,
        ..VaeConfig::small_2x()
    };
    let e = cfg
        .validate(Path::new("vae/config.json"))
        .expect_err("4x time with one resampling block")
        .to_string();
    assert!(
        e.contains("temporal_compression_ratio") && e.contains("only 1 resamplers"),
        "{e}"
    );
}

#[test]
fn config_parses_diffusers_json() {
    let json = r#"{"_class_name": "AutoencoderKLCogVideoX", "_diffusers_version": "0.30.0",
            "scaling_factor": 0.7, "block_out_channels": [128, 256, 256, 512]}"#;
    let cfg: VaeConfig = serde_json::from_str(json).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(cfg, VaeConfig::cogvideox_5b_i2v());
}

#[test]
fn a_scaling_factor_that_would_make_the_latents_zero_or_infinite_is_refused() {
    // From a file: the error names the file, the field and the value.
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("config.json");
    for v in ["0", "0.0", "-0.7", "1e30", "1e-30"] {
        let json =
            format!(r#"{{"scaling_factor": {v}, "block_out_channels": [128, 256, 256, 512]}}"#);
        std::fs::write(&path, json).expect("write");
        let e = VaeConfig::from_file(&path)
            .map(|_| ())
            .expect_err("refused")
            .to_string();
        assert!(
            e.contains(&path.display().to_string())
                && e.contains("scaling_factor")
                && e.contains("[1e-6, 1e6]"),
            "{v}: {e}"
        );
    }
    // JSON has no NaN or infinity: a config built in code.
    for v in [f64::NAN, f64::INFINITY, 0.0] {
        let cfg = VaeConfig {
            scaling_factor: v,
            ..VaeConfig::cogvideox_5b_i2v()
        };
        let e = cfg
            .validate(Path::new("vae preset"))
            .expect_err("refused")
            .to_string();
        assert!(
            e.contains("scaling_factor") && e.contains(&format!("{v}:")),
            "{e}"
        );
    }
    for v in [MIN_SCALING_FACTOR, 0.18215, MAX_SCALING_FACTOR] {
        let cfg = VaeConfig {
            scaling_factor: v,
            ..VaeConfig::cogvideox_5b_i2v()
        };
        assert!(cfg.validate(Path::new("vae preset")).is_ok(), "{v}");
    }
}

/// `decode_recorded` + `decode_backward` (both batch replays) against
/// `decode` and autograd through `decode_with_grad` on `z`: the same video,
/// the same gradient of `sum(video * g)` (within 1e-5 of its largest value).
/// Returns `g` and the reference gradient.
fn check_decode_backward(vae: &AutoencoderKLCogVideoX, z: &Tensor) -> (Tensor, Tensor) {
    let max = |t: Tensor| f64::try_from(t.abs().max()).expect("max");
    let plain = vae.decode(z).expect("decode");
    let leaf = z.detach().set_requires_grad(true);
    let out = vae.decode_with_grad(&leaf).expect("with grad");
    let g = Tensor::randn(out.size(), (Kind::Float, tch::Device::Cpu));
    let objective = (&out * &g).sum(Kind::Float);
    let reference = Tensor::run_backward(&[objective], &[&leaf], false, false).remove(0);
    for replay in [BatchReplay::Whole, BatchReplay::Stepwise] {
        let (video, record) = vae.decode_recorded(z, replay).expect("recorded");
        assert_eq!(video.size(), plain.size());
        assert!(max(&video - &plain) < 1e-6);
        let ours = vae.decode_backward(&record, &g).expect("backward");
        assert_eq!(ours.size(), z.size());
        let (err, scale) = (max(&ours - &reference), max(reference.shallow_clone()));
        assert!(
            scale > 0.0 && err <= 1e-5 * scale,
            "{replay:?}: max error {err} of {scale}"
        );
    }
    let (_, record) = vae
        .decode_recorded(z, BatchReplay::Stepwise)
        .expect("recorded");
    let e = vae
        .decode_backward(&record, &g.narrow(2, 0, 2))
        .expect_err("wrong shape")
        .to_string();
    assert!(e.contains("expected the decoded video's"), "{e}");
    (g, reference)
}

/// A `VaeConfig::tiny()` VAE with PyTorch's initialisation from `seed`.
fn tiny_vae(seed: i64) -> (VarStore, AutoencoderKLCogVideoX) {
    tch::manual_seed(seed);
    let vs = VarStore::new(tch::Device::Cpu);
    let vae = AutoencoderKLCogVideoX::new(&VaeConfig::tiny(), vs.root()).expect("vae");
    init_like_pytorch(&vs);
    (vs, vae)
}

#[test]
fn decode_backward_matches_autograd_through_the_whole_decode() {
    let (_vs, vae) = tiny_vae(3);
    let c = VaeConfig::tiny().latent_channels;
    // 5 latent frames: three batches (1, 2, 2) linked by the conv caches.
    let z = Tensor::randn([1, c, 5, 3, 4], (Kind::Float, tch::Device::Cpu));
    let (g, reference) = check_decode_backward(&vae, &z);
    // Without the caches' gradients, the first batch's latents would miss
    // the later frames' share of their gradient.
    let leaf = z.narrow(2, 0, 1).detach().set_requires_grad(true);
    let out = vae.decode_with_grad(&leaf).expect("first batch");
    let objective = (&out * g.narrow(2, 0, out.size()[2])).sum(Kind::Float);
    let own = Tensor::run_backward(&[objective], &[&leaf], false, false).remove(0);
    let diff = f64::try_from((own - reference.narrow(2, 0, 1)).abs().max()).expect("max");
    let scale = f64::try_from(reference.abs().max()).expect("max");
    assert!(
        diff > 1e-4 * scale,
        "the caches carried no gradient ({diff})"
    );
}

#[test]
fn tiled_decode_backward_matches_autograd_through_the_tiled_decode() {
    let (_vs, mut vae) = tiny_vae(4);
    vae.enable_tiling(TilingOptions {
        tile_sample_min_height: Some(24),
        tile_sample_min_width: Some(32),
        ..TilingOptions::default()
    })
    .expect("tiling");
    let c = VaeConfig::tiny().latent_channels;
    // 4x6 latents in 3x4 tiles: overlapping tiles in both directions; 5
    // latent frames: three batches per tile, linked by the conv caches.
    let z = Tensor::randn([1, c, 5, 4, 6], (Kind::Float, tch::Device::Cpu));
    let _ = check_decode_backward(&vae, &z);
    // The stepwise record keeps no tile's caches (each tile's are computed
    // again at its replay); the whole-batch one keeps every tile's, more
    // than the latents and tile outputs both keep.
    let bytes = |replay| vae.decode_recorded(&z, replay).expect("recorded").1.bytes();
    let (whole, stepwise) = (bytes(BatchReplay::Whole), bytes(BatchReplay::Stepwise));
    assert!(
        stepwise > 0 && whole > 2 * stepwise,
        "{whole} vs {stepwise}"
    );
}

#[test]
fn the_last_batch_alone_is_the_decode_of_a_still_clip_and_close_otherwise() {
    let (_vs, vae) = tiny_vae(5);
    let c = VaeConfig::tiny().latent_channels;
    let cpu = (Kind::Float, tch::Device::Cpu);
    let diff = |a: &Tensor, b: &Tensor| f64::try_from((a - b).abs().max()).expect("max");
    // 5 latent frames: batches (0..3), (3..5); the last one alone.
    let moving = Tensor::randn([2, c, 5, 3, 4], cpu);
    let full = vae.decode(&moving).expect("decode");
    let last = vae.decode_last_batch(&moving).expect("last batch");
    let (t_full, t_last) = (full.size()[2], last.size()[2]);
    assert!(t_last < t_full, "{t_last} of {t_full} frames");
    assert_eq!(last.size()[..2], full.size()[..2]);
    assert_eq!(last.size()[3..], full.size()[3..]);
    let tail = |v: &Tensor| v.narrow(2, t_full - t_last, t_last);
    // A still clip: the frames the causal convolutions repeat are the ones
    // the conv cache would have held, so the last frames are the decode's.
    let still = moving.narrow(2, 2, 1).repeat([1, 1, 5, 1, 1]);
    let (full_still, last_still) = (
        vae.decode(&still).expect("decode"),
        vae.decode_last_batch(&still).expect("last batch"),
    );
    let d = diff(&tail(&full_still), &last_still);
    assert!(d < 1e-4, "{d}");
    // A clip in motion: an approximation, not the same frames.
    let d = diff(&tail(&full), &last);
    assert!(d > 1e-3, "{d}");
    // Bad latents: the decoder's own error.
    assert!(vae
        .decode_last_batch(&Tensor::zeros([1, c + 1, 5, 3, 4], cpu))
        .is_err());
}

#[test]
fn tile_sizes_parse_print_and_must_join() {
    let size: TileSize = "144x200".parse().expect("HxW");
    assert_eq!(
        (size.height_px, size.width_px, size.to_string()),
        (144, 200, "144x200".to_owned())
    );
    for bad in ["144", "x200", "144x", "0x200", "144x-8", "144 by 200"] {
        let e = bad.parse::<TileSize>().expect_err(bad).to_string();
        assert!(e.contains(bad) && e.contains("HEIGHTxWIDTH"), "{bad}: {e}");
    }
    let (_vs, mut vae) = tiny_vae(0);
    // The overlaps' whole latent pixels: 1/6 of a multiple of 6, 1/5 of one of 5.
    for (h, w) in [(240, 360), (144, 200), (48, 40)] {
        let size = TileSize {
            height_px: h,
            width_px: w,
        };
        vae.enable_tiles(size, "tile").expect("joining tiles");
        let t = vae.tiling();
        assert_eq!((t.tile_sample_min_height, t.tile_sample_min_width), (h, w));
        assert!(vae.uses_tiling() && vae.tiles_join());
    }
    let before = vae.tiling();
    for (h, w) in [(64, 96), (120, 180), (244, 360)] {
        let size = TileSize {
            height_px: h,
            width_px: w,
        };
        let e = vae
            .enable_tiles(size, "model.vae_tile")
            .expect_err("tiles that do not join")
            .to_string();
        assert!(
            e.contains("model.vae_tile")
                && e.contains(&format!("{h}x{w} px"))
                && e.contains("would not join")
                && e.contains("a multiple of 6 high and 5 wide"),
            "{e}"
        );
        // Refused: the tiling as it was.
        assert_eq!(vae.tiling(), before);
    }
    vae.disable_tiling();
    let e = vae
        .enable_tiles(
            TileSize {
                height_px: 8,
                width_px: 8,
            },
            "tile",
        )
        .expect_err("no stride")
        .to_string();
    assert!(
        e.contains("`tile`: 8x8 px") && e.contains("no stride"),
        "{e}"
    );
    assert!(!vae.uses_tiling());
}

#[test]
fn vae_tiling_modes_parse_and_follow_the_frame_size() {
    for (text, want) in [
        ("auto", VaeTiling::Auto),
        ("off", VaeTiling::Off),
        (
            "144x200",
            VaeTiling::Tiles(TileSize {
                height_px: 144,
                width_px: 200,
            }),
        ),
    ] {
        let got: VaeTiling = text.parse().expect(text);
        assert_eq!((got, got.to_string()), (want, text.to_owned()));
    }
    for bad in ["on", "144", "tiles"] {
        let e = bad.parse::<VaeTiling>().expect_err(bad).to_string();
        assert!(
            e.contains("vae_tile")
                && e.contains(bad)
                && e.contains("\"auto\"")
                && e.contains("HEIGHTxWIDTH"),
            "{bad}: {e}"
        );
    }
    let (_vs, mut vae) = tiny_vae(0);
    let default_tiles = vae.tiling();
    // Auto: whole frames at 256x256 and below, the VAE's own tiles above.
    vae.set_tiling(VaeTiling::Auto, (256, 256), "f")
        .expect("auto");
    assert!(!vae.uses_tiling());
    vae.set_tiling(VaeTiling::Auto, (480, 720), "f")
        .expect("auto");
    assert!(vae.uses_tiling());
    assert_eq!(vae.tiling(), default_tiles);
    vae.set_tiling(VaeTiling::Off, (480, 720), "f")
        .expect("off");
    assert!(!vae.uses_tiling());
    // Tiles at any size, below 256x256 too.
    let size = TileSize {
        height_px: 48,
        width_px: 40,
    };
    vae.set_tiling(VaeTiling::Tiles(size), (64, 96), "f")
        .expect("tiles");
    let t = vae.tiling();
    assert!(vae.uses_tiling());
    assert_eq!(
        (t.tile_sample_min_height, t.tile_sample_min_width),
        (48, 40)
    );
    let bad = TileSize {
        height_px: 64,
        width_px: 96,
    };
    let e = vae
        .set_tiling(VaeTiling::Tiles(bad), (64, 96), "--vae-tile")
        .expect_err("tiles that do not join")
        .to_string();
    assert!(
        e.contains("--vae-tile") && e.contains("would not join"),
        "{e}"
    );
    assert_eq!(vae.tiling(), t, "refused: the tiling as it was");
    // Auto again: the VAE's own tiles, not the last ones set.
    vae.set_tiling(VaeTiling::Auto, (480, 720), "f")
        .expect("auto");
    assert_eq!(vae.tiling(), default_tiles);
}
