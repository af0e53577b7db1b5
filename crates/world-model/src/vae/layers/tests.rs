use super::*;
use tch::{Device, Kind};

/// A 3 -> `out` causal 3x3x3 convolution with N(0, 0.2²) weights and bias.
fn random_conv(seed: i64, out: i64) -> (nn::VarStore, CausalConv3d) {
    tch::manual_seed(seed);
    let vs = nn::VarStore::new(Device::Cpu);
    let conv = CausalConv3d::new(vs.root() / "c", 3, out, 3);
    tch::no_grad(|| {
        for mut v in vs.variables().into_values() {
            let r = Tensor::randn_like(&v) * 0.2;
            v.copy_(&r);
        }
    });
    (vs, conv)
}

#[test]
fn inflated_causal_conv_is_the_frame_by_frame_conv_and_keeps_single_frames() {
    let (vs, conv) = random_conv(1, 4);
    let frame = Tensor::randn([1, 3, 1, 5, 6], (Kind::Float, Device::Cpu));
    let clip = Tensor::randn([1, 3, 4, 5, 6], (Kind::Float, Device::Cpu));
    let (single_before, _) = conv.forward(&frame, None).unwrap();
    let (clip_before, _) = conv.forward(&clip, None).unwrap();
    assert_eq!(crate::vae::inflate_image_weights(&vs), 1);
    let (single_after, _) = conv.forward(&frame, None).unwrap();
    assert!(
        (&single_after - &single_before)
            .abs()
            .max()
            .double_value(&[])
            < 1e-5
    );
    // Every output frame is now the conv of its own frame alone.
    let (clip_after, _) = conv.forward(&clip, None).unwrap();
    for t in 0..4 {
        let (alone, _) = conv.forward(&clip.narrow(2, t, 1), None).unwrap();
        let d = (clip_after.narrow(2, t, 1) - alone)
            .abs()
            .max()
            .double_value(&[]);
        assert!(d < 1e-5, "frame {t}: {d}");
    }
    // Before, later frames mixed in their predecessors.
    let (alone, _) = conv.forward(&clip.narrow(2, 3, 1), None).unwrap();
    assert!(
        (clip_before.narrow(2, 3, 1) - alone)
            .abs()
            .max()
            .double_value(&[])
            > 1e-2
    );
}

#[test]
fn one_frame_causal_conv_matches_the_time_padded_3d_conv() {
    let (_vs, conv) = random_conv(0, 5);
    let x = Tensor::randn([2, 3, 1, 6, 7], (Kind::Float, Device::Cpu));
    let (fast, cache) = conv.forward(&x, None).unwrap();
    // The general path: the frame k = 3 times, one 3-D convolution.
    let slow = conv.conv.forward(&x.repeat([1, 1, 3, 1, 1])).unwrap();
    assert_eq!(fast.size(), vec![2, 5, 1, 6, 7]);
    let diff = (&fast - &slow).abs().max().double_value(&[]);
    assert!(diff < 1e-5, "{diff}");
    // The cache for the next frames is the general path's: the frame, twice.
    assert!(cache.unwrap().equal(&x.repeat([1, 1, 2, 1, 1])));
    // With a cache (a later frame batch) the 3-D path runs as before.
    let (next, _) = conv.forward(&x, Some(&x.repeat([1, 1, 2, 1, 1]))).unwrap();
    assert!((&next - &slow).abs().max().double_value(&[]) < 1e-5);
}

#[test]
fn first_batch_causal_conv_matches_the_time_padded_3d_conv() {
    let (_vs, conv) = random_conv(2, 4);
    for t in [2, 3, 5] {
        let x = Tensor::randn([2, 3, t, 6, 7], (Kind::Float, Device::Cpu));
        let (fast, cache) = conv.forward(&x, None).unwrap();
        // diffusers' way: the first frame twice in front, one 3-D convolution.
        let padded = Tensor::cat(&[x.narrow(2, 0, 1).repeat([1, 1, 2, 1, 1]), x.copy()], 2);
        let slow = conv.conv.forward(&padded).unwrap();
        assert_eq!(fast.size(), slow.size(), "T = {t}");
        let scale = slow.abs().max().double_value(&[]);
        let diff = (&fast - &slow).abs().max().double_value(&[]);
        assert!(diff <= 1e-6 * scale, "T = {t}: {diff} of {scale}");
        assert!(cache.unwrap().equal(&padded.narrow(2, t, 2)), "T = {t}");
    }
}

#[test]
fn time_pooling_is_avg_pool3d_and_runs_in_bf16_on_the_cpu() {
    tch::manual_seed(3);
    let mut vs = nn::VarStore::new(Device::Cpu);
    let down = Downsample3D::new(vs.root() / "d", 3, true);
    tch::no_grad(|| {
        for mut v in vs.variables().into_values() {
            let r = Tensor::randn_like(&v) * 0.2;
            v.copy_(&r);
        }
    });
    let pooled =
        |x: &Tensor| x.avg_pool3d([2, 1, 1], [2, 1, 1], [0, 0, 0], false, true, None::<i64>);
    let mut f32_outputs = Vec::new();
    for t in [1i64, 4, 5] {
        let x = Tensor::randn([2, 3, t, 6, 8], (Kind::Float, Device::Cpu));
        let got = down.forward(&x).unwrap();
        // The reference: diffusers' avg_pool3d, the first frame kept
        // alone for an odd count.
        let reference = match t {
            1 => x.shallow_clone(),
            _ if t % 2 == 1 => Tensor::cat(&[x.narrow(2, 0, 1), pooled(&x.narrow(2, 1, t - 1))], 2),
            _ => pooled(&x),
        };
        let want = down
            .conv
            .forward(&reference.constant_pad_nd([0, 1, 0, 1]))
            .unwrap();
        let d = (&got - &want).abs().max().double_value(&[]);
        assert!(d < 1e-6, "t = {t}: {d}");
        f32_outputs.push((x, got));
    }
    // The same downsampler in bf16 on the CPU, where avg_pool3d has no
    // bf16 kernel: it runs and stays within bf16 rounding of f32.
    vs.bfloat16();
    for (x, want) in f32_outputs {
        let got = down.forward(&x.to_kind(Kind::BFloat16)).unwrap();
        assert_eq!(got.kind(), Kind::BFloat16);
        let scale = want.abs().max().double_value(&[]);
        let d = (got.to_kind(Kind::Float) - &want)
            .abs()
            .max()
            .double_value(&[]);
        assert!(
            scale > 0.1 && d < 0.05 * scale,
            "bf16 off by {d} (scale {scale})"
        );
    }
}

/// The largest difference between `a` and `b` over the largest value of `b`.
fn relative_difference(a: &Tensor, b: &Tensor) -> f64 {
    let scale = b.abs().max().double_value(&[]);
    (a - b).abs().max().double_value(&[]) / scale
}

#[test]
fn time_pooled_causal_conv_is_the_conv_then_diffusers_pooling() {
    let (_vs, conv) = random_conv(5, 4);
    let opts = (Kind::Float, Device::Cpu);
    // (frames, a cache from an earlier frame batch): odd and even counts,
    // one frame, the first batch and later ones.
    for (t, cached) in [
        (1, false),
        (2, false),
        (3, false),
        (4, false),
        (5, false),
        (9, false),
        (1, true),
        (2, true),
        (3, true),
        (8, true),
    ] {
        let x = Tensor::randn([2, 3, t, 6, 7], opts).set_requires_grad(true);
        let cache = cached.then(|| Tensor::randn([2, 3, 2, 6, 7], opts));
        let (ours, our_cache) = conv.forward_time_pooled(&x, cache.as_ref()).unwrap();
        let (full, their_cache) = conv.forward(&x, cache.as_ref()).unwrap();
        let theirs = pool_frame_pairs(&full).unwrap();
        assert_eq!(ours.size(), theirs.size(), "T = {t}, cached {cached}");
        let d = relative_difference(&ours, &theirs);
        assert!(d < 1e-6, "T = {t}, cached {cached}: {d}");
        assert!(our_cache.unwrap().equal(&their_cache.unwrap()));
        // The gradient too (the in-place correction of the first pair).
        let g = Tensor::randn_like(&ours);
        let grad = |out: &Tensor| {
            Tensor::run_backward(&[(out * &g).sum(Kind::Float)], &[&x], false, false).remove(0)
        };
        let d = relative_difference(&grad(&ours), &grad(&theirs));
        assert!(d < 1e-5, "T = {t}, cached {cached}: gradient {d}");
    }
    // The first batch's own path (no cache, odd T >= 3), not a fallback.
    let x = Tensor::randn([1, 3, 7, 5, 4], opts);
    let (ours, _) = conv.first_batch_time_pooled(&x).unwrap();
    let theirs = pool_frame_pairs(&conv.forward(&x, None).unwrap().0).unwrap();
    assert!(relative_difference(&ours, &theirs) < 1e-6);
    assert_eq!(ours.size(), vec![1, 4, 4, 5, 4]);
}

#[test]
fn down_block_pools_time_inside_its_last_resnet_with_diffusers_values() {
    let opts = (Kind::Float, Device::Cpu);
    // 4 -> 8 channels in two resnets (the pooled last one's shortcut is
    // the identity) and in one (the pooled one has a 1x1x1 shortcut).
    for (cin, layers) in [(4, 2), (4, 1)] {
        tch::manual_seed(6);
        let mut vs = nn::VarStore::new(Device::Cpu);
        let block = DownBlock3D::new(
            vs.root(),
            cin,
            8,
            layers,
            4,
            1e-6,
            Activation::Silu,
            true,
            true,
        );
        tch::no_grad(|| {
            for mut v in vs.variables().into_values() {
                let r = Tensor::randn_like(&v) * 0.3;
                v.copy_(&r);
            }
        });
        // diffusers' order: every resnet in full, then the downsampler
        // (its pooling, padding and strided convolution).
        let mut vs_ref = nn::VarStore::new(Device::Cpu);
        let resnets = ResnetBlock3D::stack(
            &vs_ref.root(),
            cin,
            8,
            layers,
            4,
            1e-6,
            Activation::Silu,
            None,
        );
        let down = Downsample3D::new(vs_ref.root() / "downsamplers" / 0, 8, true);
        vs_ref.copy(&vs).unwrap();
        let reference = |x: &Tensor, cache: &[ResnetCache]| {
            let mut h = x.shallow_clone();
            let mut caches = Vec::new();
            for (i, r) in resnets.iter().enumerate() {
                let (out, c) = r.forward(&h, None, cache.get(i)).unwrap();
                h = out;
                caches.push(c);
            }
            (down.forward(&h).unwrap(), caches)
        };
        // A first batch of 5 frames, then a later one of 4 with its cache.
        let first = Tensor::randn([1, cin, 5, 8, 10], opts);
        let later = Tensor::randn([1, cin, 4, 8, 10], opts);
        let (ours, our_cache) = block.forward(&first, None).unwrap();
        let (theirs, their_cache) = reference(&first, &[]);
        assert_eq!(ours.size(), vec![1, 8, 3, 4, 5]);
        assert!(
            relative_difference(&ours, &theirs) < 1e-5,
            "{cin}, {layers}"
        );
        let their_tensors: Vec<&Tensor> =
            their_cache.iter().flat_map(ResnetCache::tensors).collect();
        assert_eq!(our_cache.tensors().len(), their_tensors.len());
        for (a, b) in our_cache.tensors().iter().zip(their_tensors) {
            assert!(a.equal(b));
        }
        let (ours, _) = block.forward(&later, Some(&our_cache)).unwrap();
        let (theirs, _) = reference(&later, &their_cache);
        assert_eq!(ours.size(), vec![1, 8, 2, 4, 5]);
        assert!(
            relative_difference(&ours, &theirs) < 1e-5,
            "{cin}, {layers}"
        );
        // bf16 on the CPU: within bf16 rounding of f32.
        vs.bfloat16();
        let (ours, _) = block.forward(&first.to_kind(Kind::BFloat16), None).unwrap();
        let (theirs, _) = reference(&first, &[]);
        let d = relative_difference(&ours.to_kind(Kind::Float), &theirs);
        assert!(d < 0.05, "bf16: {d}");
    }
}

/// diffusers' spatial norm as written there: the latent resized to the
/// features, both 1x1x1 convolutions at full size, then `norm * y + b`.
fn spatial_norm_as_diffusers(norm: &SpatialNorm3D, f: &Tensor, zq: &Tensor) -> Tensor {
    let s = f.size();
    let (t, h, w) = (s[2], s[3], s[4]);
    let zq = if t > 1 && t % 2 == 1 {
        let zt = zq.size()[2];
        let first = zq
            .narrow(2, 0, 1)
            .upsample_nearest3d([1, h, w], None, None, None);
        let rest = zq
            .narrow(2, 1, zt - 1)
            .upsample_nearest3d([t - 1, h, w], None, None, None);
        Tensor::cat(&[first, rest], 2)
    } else {
        zq.upsample_nearest3d([t, h, w], None, None, None)
    };
    let (y, _) = norm.conv_y.forward(&zq, None).unwrap();
    let (b, _) = norm.conv_b.forward(&zq, None).unwrap();
    norm.norm_layer.forward(f).unwrap() * y + b
}

#[test]
fn spatial_norm_runs_its_convolutions_at_the_latents_size_with_diffusers_values() {
    tch::manual_seed(4);
    let vs = nn::VarStore::new(Device::Cpu);
    let norm = SpatialNorm3D::new(vs.root() / "n", 8, 3, 4);
    tch::no_grad(|| {
        for mut v in vs.variables().into_values() {
            let r = Tensor::randn_like(&v) * 0.5;
            v.copy_(&r);
        }
    });
    // (feature frames, height, width) for a latent of 3 frames at 2x3:
    // odd and even frame counts, one frame, integer factors (broadcast) and
    // factors libtorch does not map in blocks (5 of 2, 7 of 3: resized).
    for (t, h, w) in [
        (9, 8, 12),
        (5, 2, 3),
        (4, 4, 6),
        (1, 4, 6),
        (9, 5, 7),
        (3, 16, 3),
    ] {
        let f = Tensor::randn([2, 8, t, h, w], (Kind::Float, Device::Cpu)).set_requires_grad(true);
        let zq = Tensor::randn([2, 3, 3, 2, 3], (Kind::Float, Device::Cpu)).set_requires_grad(true);
        let ours = norm.forward(&f, &zq).unwrap();
        let theirs = spatial_norm_as_diffusers(&norm, &f, &zq);
        assert_eq!(ours.size(), vec![2, 8, t, h, w]);
        let diff = (&ours - &theirs).abs().max().double_value(&[]);
        assert!(diff < 1e-5, "{t}x{h}x{w}: {diff}");
        // The gradients too (decode_backward replays these layers).
        let g = Tensor::randn_like(&ours);
        let grads = |out: &Tensor| {
            Tensor::run_backward(&[(out * &g).sum(Kind::Float)], &[&f, &zq], false, false)
        };
        for (a, b) in grads(&ours).iter().zip(grads(&theirs).iter()) {
            let d = (a - b).abs().max().double_value(&[]);
            assert!(d < 1e-4, "{t}x{h}x{w}: gradient {d}");
        }
    }
    assert_eq!(nearest_block(60, 480).unwrap(), Some(8));
    assert_eq!(nearest_block(3, 7).unwrap(), None);
    assert_eq!(nearest_block(4, 4).unwrap(), Some(1));
}
