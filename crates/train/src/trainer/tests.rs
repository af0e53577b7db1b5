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
