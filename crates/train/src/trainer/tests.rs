use super::setup::random_preset;
use crate::guarded;
use crate::TrainError;
use bridgev2w_world_model::transformer::TransformerConfig;
use bridgev2w_world_model::vae::VaeConfig;

#[test]
fn random_presets_by_name_and_an_unknown_one_lists_them() {
    let (vae, tf) = random_preset("random:small2x-wide").unwrap().unwrap();
    assert_eq!(vae, VaeConfig::small_2x());
    assert_eq!(
        tf.inner_dim(),
        2 * TransformerConfig::small_2x().inner_dim()
    );
    assert!(random_preset("some/folder").unwrap().is_none());
    let e = random_preset("random:huge").unwrap_err().to_string();
    assert!(
        e.contains("random:small2x-wide") && e.contains("random:huge"),
        "{e}"
    );
}

#[test]
fn a_panic_in_a_step_is_an_error_and_an_out_of_memory_one_names_the_step() {
    assert_eq!(guarded(|| Ok(3)).unwrap(), 3);
    // libtorch's message as an op's panic carries it.
    let oom = "Internal torch error: CUDA out of memory. Tried to allocate 10.55 GiB. GPU 0 has a total capacity of 79.19 GiB of which 1.40 GiB is free.\nException raised from malloc at CUDACachingAllocator.cpp:1574 (most recent call first):\nframe #0: ...";
    let e = guarded(|| -> crate::Result<()> { panic!("{oom}") })
        .unwrap_err()
        .on_out_of_memory(
            || "training step 7 (1 clip(s) of 25 frames at 480x720)".to_owned(),
            crate::TRAIN_MEMORY_ADVICE,
        );
    let text = e.to_string();
    assert!(matches!(e, TrainError::OutOfMemory { .. }), "{text}");
    assert!(
        text.contains("training step 7 (1 clip(s) of 25 frames at 480x720)")
            && text.contains("Tried to allocate 10.55 GiB")
            && text.contains("expandable_segments")
            && !text.contains("frame #0"),
        "{text}"
    );
    // Another panic stays libtorch's error; `during` is not evaluated for it.
    let e = guarded(|| -> crate::Result<()> { panic!("shape mismatch") })
        .unwrap_err()
        .on_out_of_memory(|| unreachable!("only for out-of-memory"), "");
    assert!(
        matches!(&e, TrainError::Torch(t) if t.to_string().contains("shape mismatch")),
        "{e}"
    );
}

/// A batch within the config's bounds but beyond the machine (65536 clips
/// of 1024 frames at 8192x8192) is refused before the data is read (the
/// dataset named here does not exist), with the estimate.
#[test]
fn a_training_batch_beyond_the_machine_is_refused_before_the_data_is_read() {
    let text = "[model]\nbackbone = \"random:tiny\"\ndevice = \"cpu\"\n[data]\ndataset = \"/nonexistent/dataset\"\nframes = 1021\nwidth = 8192\nheight = 8192\n[train]\nbatch_size = 65536\n";
    let cfg = crate::config::TrainConfig::from_toml(text).unwrap();
    let e = super::Trainer::new(cfg).map(|_| ()).unwrap_err();
    let text = e.to_string();
    if bridgev2w_io::memory::available_bytes().is_some() {
        assert!(matches!(e, TrainError::Memory(_)), "{text}");
        assert!(
            text.starts_with("a training batch of 65536 clip(s) of 1021 frames at 8192x8192"),
            "{text}"
        );
        assert!(
            text.contains("is available") && text.contains("train.batch_size"),
            "{text}"
        );
    }
}

/// A backbone folder whose transformer or VAE config is there but not its
/// weights is named before the data is read (the dataset named here does
/// not exist) and before a model of the config's clip size is built.
#[test]
fn a_backbone_folder_without_its_weights_is_named_before_the_data_is_read() {
    use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
    use bridgev2w_world_model::scheduler::SchedulerConfig;
    use bridgev2w_world_model::ComputeDevice;
    let m = BridgeV2W::random(
        BridgeV2WConfig::tiny(),
        &VaeConfig::tiny(),
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        0,
    )
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("backbone");
    m.save_backbone(&root).unwrap();
    let config = |pretrained: bool| {
        let text = format!(
            "[model]\nbackbone = {:?}\ndevice = \"cpu\"\n[data]\ndataset = \"/nonexistent/dataset\"\n[ablation]\npretrained = {pretrained}\n",
            root.display().to_string()
        );
        crate::config::TrainConfig::from_toml(&text).unwrap()
    };
    let error = |pretrained| {
        super::Trainer::new(config(pretrained))
            .map(|_| ())
            .unwrap_err()
            .to_string()
    };
    let weights = |c: &str| root.join(c).join("diffusion_pytorch_model.safetensors");
    std::fs::remove_file(weights("transformer")).unwrap();
    let e = error(true);
    assert!(
        e.contains("model.backbone")
            && e.contains(&weights("transformer").display().to_string())
            && e.contains("not its weights"),
        "{e}"
    );
    // A transformer trained from scratch needs the VAE's weights only.
    let e = error(false);
    assert!(e.contains("/nonexistent/dataset"), "{e}");
    std::fs::remove_file(weights("vae")).unwrap();
    let e = error(false);
    assert!(
        e.contains(&weights("vae").display().to_string()) && e.contains("not its weights"),
        "{e}"
    );
}
