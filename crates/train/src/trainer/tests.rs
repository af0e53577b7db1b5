use super::setup::random_preset;
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
