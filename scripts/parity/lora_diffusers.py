#!/usr/bin/env python3
"""Runs a diffusers CogVideoX transformer before and after loading a LoRA file with
diffusers' own loader: the reference of `bridgev2w export-lora`'s test
(crates/world-model/tests/lora_export.rs).

    lora_diffusers.py --backbone DIR --lora DIR --inputs IN.safetensors --out OUT.safetensors

--backbone  a CogVideoXImageToVideoPipeline folder (model_index.json, transformer/, ...)
--lora      a folder with pytorch_lora_weights.safetensors, loaded by the pipeline's
            load_lora_weights (CogVideoXLoraLoaderMixin, through PEFT)
IN          hidden_states [B,F,C,H,W], encoder_hidden_states [B,L,D], timestep [B] int64,
            rope_cos / rope_sin [N, head_dim] (RoPE models), ofs [1] (models with ofs)
OUT         sample_base (before the LoRA), sample_lora (after)
stdout      JSON: lora_layers (modules PEFT adapted), r, lora_alpha
Run with the project venv: .venv/bin/python (scripts/setup-venv.sh creates it).
"""
import argparse
import json
import sys


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--backbone", required=True)
    parser.add_argument("--lora", required=True)
    parser.add_argument("--inputs", required=True)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()

    import torch
    from diffusers import CogVideoXImageToVideoPipeline
    from safetensors.torch import load_file, save_file

    torch.use_deterministic_algorithms(True)
    io = load_file(args.inputs)
    # The backbone folder has no text encoder (the prompt comes as embeddings).
    pipe = CogVideoXImageToVideoPipeline.from_pretrained(
        args.backbone, text_encoder=None, tokenizer=None, dtype=torch.float32
    )
    pipe.set_progress_bar_config(disable=True)
    transformer = pipe.transformer.eval()
    rope = (io["rope_cos"], io["rope_sin"]) if "rope_cos" in io else None

    def forward():
        with torch.no_grad():
            return transformer(
                hidden_states=io["hidden_states"],
                encoder_hidden_states=io["encoder_hidden_states"],
                timestep=io["timestep"],
                ofs=io.get("ofs"),
                image_rotary_emb=rope,
                return_dict=False,
            )[0]

    base = forward()
    pipe.load_lora_weights(args.lora, adapter_name="bridgev2w")
    lora = forward()

    from peft.tuners.lora import LoraLayer

    layers = [m for m in transformer.modules() if isinstance(m, LoraLayer)]
    cfg = transformer.peft_config["bridgev2w"]
    save_file({"sample_base": base.contiguous(), "sample_lora": lora.contiguous()}, args.out)
    print(json.dumps({"lora_layers": len(layers), "r": cfg.r, "lora_alpha": cfg.lora_alpha}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
