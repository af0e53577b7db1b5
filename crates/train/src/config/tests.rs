use super::*;

#[test]
fn sizes_beyond_the_limits_name_the_field() {
    let base = "[model]\nbackbone = \"random:tiny\"\n[data]\ndataset = \"d\"\n";
    for (extra, field) in [
        ("width = 100000\n", "data.width"),
        ("frames = 4000000000\n", "data.frames"),
    ] {
        let text = format!("{base}{extra}");
        let e = TrainConfig::from_toml(&text).unwrap_err().to_string();
        assert!(e.contains(field) && e.contains("at most"), "{e}");
    }
    let e = TrainConfig::from_toml(&format!("{base}[train]\nbatch_size = 100000000\n"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("train.batch_size"), "{e}");
    // A learning rate of 0 would train nothing (found by fuzz_config); one
    // beyond MAX_LR, or infinite, diverges to NaN at the first steps.
    for lr in ["0.0", "-1e-4", "nan", "inf", "-inf", "1e300", "1.5"] {
        let e = TrainConfig::from_toml(&format!("{base}[train]\nlr = {lr}\n"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("train.lr") && e.contains("> 0") && e.contains("at most 1"),
            "{lr}: {e}"
        );
    }
    assert!(TrainConfig::from_toml(&format!("{base}[train]\nlr = {MAX_LR}\n")).is_ok());
    // AdamW's eps = 0 divides 0 by 0 for a parameter whose gradient is 0.
    for eps in ["0.0", "-1e-8", "nan", "inf"] {
        let e = TrainConfig::from_toml(&format!("{base}[train]\neps = {eps}\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("train.eps") && e.contains("> 0"), "{eps}: {e}");
    }
    // The other float fields: NaN, infinite and negative values are named.
    for (field, v) in [
        ("weight_decay", "-1.0"),
        ("grad_clip", "nan"),
        ("lambda_dyn", "inf"),
        ("lambda_flow", "-0.5"),
        ("kl_weight", "nan"),
        ("beta1", "nan"),
        ("beta2", "-0.1"),
        ("condition_dropout", "nan"),
        ("image_noise_log_mean", "inf"),
    ] {
        let e = TrainConfig::from_toml(&format!("{base}[train]\n{field} = {v}\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains(&format!("train.{field}")), "{field} = {v}: {e}");
    }
    // Found by `scripts/fuzz.sh train-config 60`: lora_alpha = nan passed.
    for (table, line, field) in [
        ("[model]\n", "lora_alpha = nan\n", "model.lora_alpha"),
        ("[data]\n", "weight = -1.0\n", "data.weight"),
        ("[data]\n", "weight = inf\n", "data.weight"),
        ("[data]\n", "weight = nan\n", "data.weight"),
    ] {
        let text = base.replace(table, &format!("{table}{line}"));
        let e = TrainConfig::from_toml(&text)
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(e.contains(field), "{line}: {e}");
    }
    // model.transformer: a known preset, over a backbone folder only.
    let folder = base.replace("random:tiny", "some/folder");
    let c = TrainConfig::from_toml(
        &folder.replace("[model]\n", "[model]\ntransformer = \"small2x-wide\"\n"),
    )
    .unwrap();
    assert_eq!(c.model.transformer.as_deref(), Some("small2x-wide"));
    let e =
        TrainConfig::from_toml(&folder.replace("[model]\n", "[model]\ntransformer = \"huge\"\n"))
            .map(|_| ())
            .unwrap_err()
            .to_string();
    assert!(
        e.contains("model.transformer") && e.contains("small2x-wide"),
        "{e}"
    );
    let e =
        TrainConfig::from_toml(&base.replace("[model]\n", "[model]\ntransformer = \"small\"\n"))
            .map(|_| ())
            .unwrap_err()
            .to_string();
    assert!(
        e.contains("model.transformer") && e.contains("random:small"),
        "{e}"
    );
    let e = TrainConfig::from_toml(&format!("{base}[train]\nimage_noise_log_std = nan\n"))
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(e.contains("train.image_noise_log"), "{e}");
    // A typed stage: an unknown one lists the stages.
    let e = TrainConfig::from_toml(&format!("{base}[train]\nstage = \"fine\"\n"))
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("fine") && e.contains("prior") && e.contains("vae"),
        "{e}"
    );
    assert_eq!("prior".parse::<Stage>().unwrap(), Stage::Prior);
    // A typed device: written back as named (`auto` and `cuda` stay), an
    // unknown one names the value and the choices.
    for name in ["cpu", "auto", "cuda", "cuda:1"] {
        let text = base.replace("[data]", &format!("device = \"{name}\"\n[data]"));
        let cfg = TrainConfig::from_toml(&text).unwrap();
        assert_eq!(cfg.model.device.to_string(), name);
        let again = TrainConfig::from_toml(&cfg.to_toml().unwrap()).unwrap();
        assert_eq!(again.model.device, cfg.model.device);
    }
    let e = TrainConfig::from_toml(&base.replace("[data]", "device = \"gpu\"\n[data]"))
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(e.contains("gpu") && e.contains("cuda:N"), "{e}");
    // A typed RAFT variant: an unknown one names both.
    let e = TrainConfig::from_toml(&format!("{base}[train]\nraft_model = \"raft_huge\"\n"))
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("raft_huge") && e.contains("raft_large") && e.contains("raft_small"),
        "{e}"
    );
    assert_eq!(Stage::Vae.to_string(), "vae");
    // vae_parts: only a vae stage, and never with the inflation that
    // rewrites the encoder it keeps.
    let c = TrainConfig::from_toml(&format!(
        "{base}[train]\nstage = \"vae\"\nvae_parts = \"decoder\"\n"
    ))
    .unwrap();
    assert_eq!(c.train.vae_parts, VaeParts::Decoder);
    assert!(VaeParts::Decoder.trains("decoder.conv_in.conv.weight"));
    assert!(!VaeParts::Decoder.trains("encoder.conv_in.conv.weight"));
    for (extra, want) in [
        ("vae_parts = \"decoder\"\n", "with stage \"bridgev2w\""),
        (
            "stage = \"vae\"\nvae_parts = \"decoder\"\ninflate_image_vae = true\n",
            "inflate_image_vae = true",
        ),
        ("stage = \"vae\"\nvae_parts = \"encoder\"\n", "encoder"),
    ] {
        let e = TrainConfig::from_toml(&format!("{base}[train]\n{extra}"))
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(e.contains("vae_parts") && e.contains(want), "{extra}: {e}");
    }
    for d in ["1.0", "-0.1", "nan"] {
        let e = TrainConfig::from_toml(&format!("{base}[train]\nema_decay = {d}\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("train.ema_decay") && e.contains("[0, 1)"), "{e}");
    }
    for w in ["-1.0", "nan", "inf"] {
        let e = TrainConfig::from_toml(&format!("{base}[train]\nmotion_loss_weight = {w}\n"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("train.motion_loss_weight") && e.contains(">= 0"),
            "{e}"
        );
    }
    let c = TrainConfig::from_toml(&format!("{base}[train]\nmotion_loss_weight = 4.0\n")).unwrap();
    assert_eq!(c.train.motion_loss_weight, 4.0);
}

#[test]
fn paper_defaults_and_parsing() {
    let c = TrainConfig::from_toml("[data]\ndataset = \"d\"\n").unwrap();
    assert_eq!(c.train.lr, 2e-5);
    assert_eq!((c.train.beta1, c.train.beta2), (0.9, 0.95));
    assert_eq!(c.train.eps, 1e-8);
    assert_eq!(c.train.weight_decay, 1e-4);
    assert_eq!(c.train.grad_clip, 1.0);
    assert_eq!(c.train.warmup_steps, 100);
    assert_eq!((c.model.lora_rank, c.model.lora_alpha), (64, 64.0));
    assert_eq!((c.train.lambda_dyn, c.train.dyn_k), (0.1, 4));
    assert_eq!((c.train.lambda_flow, c.train.e_switch), (0.05, 5));
    assert!(c.ablation.mask_action && c.ablation.controlnet);
    // Round trip.
    let back = TrainConfig::from_toml(&c.to_toml().unwrap()).unwrap();
    assert_eq!(back, c);
    // Unknown keys and bad values are errors naming the field.
    let e = TrainConfig::from_toml("[train]\nlearning_rate = 1\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("learning_rate"), "{e}");
    let e = TrainConfig::from_toml("[train]\nbeta2 = 1.5\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("beta2"), "{e}");
    assert_eq!(c.train.autocast, Autocast::Auto);
    let e = TrainConfig::from_toml("[train]\nautocast = \"fp16\"\n")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("autocast") && e.contains("fp16") && e.contains("bf16"),
        "{e}"
    );
}

#[test]
fn warmup_then_constant() {
    let mut c = TrainConfig::default();
    c.train.warmup_steps = 4;
    c.train.lr = 1.0;
    let lrs: Vec<f64> = (0..6).map(|s| c.lr_at(s)).collect();
    assert_eq!(lrs, vec![0.25, 0.5, 0.75, 1.0, 1.0, 1.0]);
}
