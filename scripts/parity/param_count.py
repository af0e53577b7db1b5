#!/usr/bin/env python3
"""Prints the parameter count of a diffusers model built from a config, on the
meta device (no memory, no weights).

    param_count.py --component transformer|vae --config CONFIG.json

Run with the project venv: .venv/bin/python. Prints one JSON line {"parameters": N}.
"""
import argparse
import json


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--component", choices=["transformer", "vae"], required=True)
    ap.add_argument("--config", required=True, help="a diffusers config.json")
    args = ap.parse_args()
    import torch
    from diffusers import AutoencoderKLCogVideoX, CogVideoXTransformer3DModel

    with open(args.config) as f:
        cfg = {k: v for k, v in json.load(f).items() if not k.startswith("_")}
    cls = CogVideoXTransformer3DModel if args.component == "transformer" else AutoencoderKLCogVideoX
    with torch.device("meta"):
        model = cls(**cfg)
    print(json.dumps({"parameters": sum(p.numel() for p in model.parameters())}))


if __name__ == "__main__":
    main()
