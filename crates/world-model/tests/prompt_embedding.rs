//! `scripts/encode_prompt.py` against diffusers' own T5 prompt encoding, read back by
//! `PromptEmbedding`, on a tiny T5 (random weights, a sentencepiece vocabulary
//! trained on the spot: no download).

#![allow(clippy::unwrap_used)]

use crate::common;

use bridgev2w_world_model::checkpoint::PromptEmbedding;
use std::process::Command;

const MAKE_TINY_T5: &str = r#"
import sys, types, torch, sentencepiece as spm
from pathlib import Path
from safetensors.torch import save_file
from transformers import AutoTokenizer, T5Config, T5EncoderModel
from diffusers import CogVideoXImageToVideoPipeline
root = Path(sys.argv[1]); (root / "tokenizer").mkdir(parents=True, exist_ok=True)
corpus = root / "corpus.txt"
corpus.write_text("\n".join(["Follow this action sequence represented in mask",
                             "a robot arm pushes the red block to the left"] * 40))
spm.SentencePieceTrainer.train(input=str(corpus), model_prefix=str(root / "tokenizer" / "spiece"),
    vocab_size=32, model_type="unigram", pad_id=0, eos_id=1, unk_id=2, bos_id=-1, minloglevel=2)
(root / "tokenizer" / "tokenizer_config.json").write_text(
    '{"tokenizer_class": "T5Tokenizer", "model_max_length": 226, "extra_ids": 0}')
torch.manual_seed(0)
cfg = T5Config(vocab_size=32, d_model=16, d_kv=4, d_ff=32, num_layers=2, num_heads=4)
T5EncoderModel(cfg).save_pretrained(root / "text_encoder")
# The reference: diffusers' pipeline method on the same tokenizer and encoder.
tok = AutoTokenizer.from_pretrained(root / "tokenizer")
enc = T5EncoderModel.from_pretrained(root / "text_encoder")
me = types.SimpleNamespace(tokenizer=tok, text_encoder=enc, _execution_device=torch.device("cpu"))
ref = CogVideoXImageToVideoPipeline._get_t5_prompt_embeds(
    me, prompt="Follow this action sequence represented in mask", num_videos_per_prompt=1,
    max_sequence_length=226, device=torch.device("cpu"), dtype=torch.float32)
save_file({"prompt_embeds": ref.contiguous()}, str(root / "reference.safetensors"))
"#;

#[test]
fn encode_prompt_matches_diffusers_and_loads() {
    let dir = tempfile::tempdir().unwrap();
    let python = common::venv_python();
    let run = |cmd: &mut Command| {
        let out = cmd.output().unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    };
    run(Command::new(&python)
        .arg("-c")
        .arg(MAKE_TINY_T5)
        .arg(dir.path()));
    let out = dir.path().join("prompt.safetensors");
    run(Command::new(&python)
        .arg(common::repo_root().join("scripts/encode_prompt.py"))
        .arg("--model")
        .arg(dir.path())
        .arg("--out")
        .arg(&out));
    let ours = PromptEmbedding::load(&out, 16).unwrap();
    let reference = PromptEmbedding::load(&dir.path().join("reference.safetensors"), 16).unwrap();
    assert_eq!(ours.embeds.size(), [226, 16]);
    let diff = (&ours.embeds - &reference.embeds)
        .abs()
        .max()
        .double_value(&[]);
    // Same tokens and weights; float reductions may differ in the last bits.
    assert!(diff < 1e-4, "max abs diff {diff}");
    let spread = ours.embeds.std(false).double_value(&[]);
    assert!(spread > 1e-3, "a real (non-constant) embedding");
    // A missing folder is a clear error.
    let bad = Command::new(&python)
        .arg(common::repo_root().join("scripts/encode_prompt.py"))
        .arg("--model")
        .arg(dir.path().join("nope"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("tokenizer"));
}
