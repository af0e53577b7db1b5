#!/usr/bin/env python3
"""Writes a parity fixture: a randomly initialised diffusers module (or scheduler)
built from a config and a seed, its inputs and its outputs.

    make_parity_fixture.py KIND --out DIR [--seed S] [kind options]

DIR/meta.json        {"kind": KIND, "seed": S, ...kind-specific fields}
DIR/model/           diffusers save_pretrained() output (scheduler_config.json for schedulers)
DIR/io.safetensors   inputs and expected outputs (names per kind, see the fixture_*.py modules)

The Rust side (`bridgev2w parity DIR`, crates/world-model/src/parity.rs) loads model/,
recomputes the outputs from the inputs and reports the errors.
Run with the project venv: .venv/bin/python (scripts/setup-venv.sh creates it).
"""
import argparse
import importlib
import json
import os
import shutil
import sys
import tempfile

KINDS = {
    "transformer": "fixture_transformer",
    "vae": "fixture_vae",
    "scheduler": "fixture_scheduler",
    "lpips": "fixture_lpips",
    "raft": "fixture_raft",
    "i3d": "fixture_i3d",
}


def main() -> int:
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("kind", choices=sorted(KINDS))
    parser.add_argument("--out", required=True, help="fixture directory to write (replaced atomically)")
    parser.add_argument("--seed", type=int, default=0)
    known, _ = parser.parse_known_args()
    module = importlib.import_module(KINDS[known.kind])
    module.add_args(parser)
    args = parser.parse_args()

    import torch
    from safetensors.torch import save_file

    torch.manual_seed(args.seed)
    torch.use_deterministic_algorithms(True)
    torch.set_num_threads(max(1, os.cpu_count() or 1))

    out = os.path.abspath(args.out)
    parent = os.path.dirname(out)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".fixture-", dir=parent)
    try:
        meta, io = module.build(args, os.path.join(tmp, "model"))
        meta = {"kind": args.kind, "seed": args.seed, **meta}
        io = {k: v.detach().contiguous().cpu() for k, v in io.items()}
        save_file(io, os.path.join(tmp, "io.safetensors"))
        with open(os.path.join(tmp, "meta.json"), "w") as f:
            json.dump(meta, f, indent=2, sort_keys=True)
        if os.path.exists(out):
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    print(f"wrote {args.kind} fixture to {out}: " + ", ".join(f"{k}{list(v.shape)}" for k, v in io.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
