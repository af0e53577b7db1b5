#!/usr/bin/env python3
"""Writes the T5 embedding of BridgeV2W's fixed prompt for `bridgev2w predict --prompt-embeds`.

The prompt ("Follow this action sequence represented in mask") never changes, so the
Rust pipeline does not run T5: it reads `prompt_embeds` ([1, L, D]) from the file this
script writes. The encoding follows diffusers' CogVideoX pipelines: the tokenizer pads
and truncates to `--max-length` tokens (226) with special tokens, and the embedding is
the text encoder's last hidden state.

    .venv/bin/python scripts/encode_prompt.py --model CogVideoX-5b-I2V --out prompt.safetensors
"""

import argparse
import sys
from pathlib import Path

PROMPT = "Follow this action sequence represented in mask"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True, type=Path,
                    help="a CogVideoX diffusers folder with tokenizer/ and text_encoder/")
    ap.add_argument("--out", required=True, type=Path, help="output .safetensors")
    ap.add_argument("--prompt", default=PROMPT)
    ap.add_argument("--max-length", type=int, default=226)
    ap.add_argument("--dtype", choices=["float32", "bfloat16"], default="float32")
    args = ap.parse_args()

    for sub in ("tokenizer", "text_encoder"):
        if not (args.model / sub).is_dir():
            print(f"error: {args.model / sub} not found: --model must be a CogVideoX folder "
                  f"with tokenizer/ and text_encoder/", file=sys.stderr)
            return 2

    import torch
    from safetensors.torch import save_file
    from transformers import AutoTokenizer, T5EncoderModel

    tokenizer = AutoTokenizer.from_pretrained(args.model / "tokenizer")
    encoder = T5EncoderModel.from_pretrained(args.model / "text_encoder",
                                             torch_dtype=getattr(torch, args.dtype))
    encoder.eval()
    ids = tokenizer(args.prompt, padding="max_length", max_length=args.max_length,
                    truncation=True, add_special_tokens=True, return_tensors="pt").input_ids
    with torch.no_grad():
        embeds = encoder(ids)[0]  # [1, L, D]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(f".{args.out.name}.tmp")
    save_file({"prompt_embeds": embeds.contiguous()}, str(tmp),
              metadata={"prompt": args.prompt, "max_length": str(args.max_length)})
    tmp.replace(args.out)
    print(f"wrote {args.out}: prompt_embeds {list(embeds.shape)} {embeds.dtype}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
