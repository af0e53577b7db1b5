#!/usr/bin/env python3
"""Converts released PyTorch weights of the frozen reference networks into the
safetensors files the Rust code loads (key names unchanged).

    convert_reference_weights.py lpips --alexnet alexnet-owt-7be5be79.pth \
        [--lin .venv/lib/python3.*/site-packages/lpips/weights/v0.1/alex.pth] --out lpips_alex.safetensors
    convert_reference_weights.py raft --pth raft_large_C_T_SKHT_V2-ff5fadd5.pth --out raft_large.safetensors
    convert_reference_weights.py i3d --pth rgb_imagenet.pt --out i3d.safetensors

lpips: torchvision AlexNet `features.*` (the classifier is dropped) plus the
`lpips` package's v0.1 heads `lin{0..4}.model.1.weight` (default: the copy
shipped inside the installed `lpips` package).
raft: torchvision RAFT state dicts (raft_small / raft_large), keys as-is.
i3d: a Kinetics-400 `InceptionI3d` state dict of the common PyTorch port
(Conv3d_1a_7x7.conv3d.weight ... logits.conv3d.bias); BatchNorm
`num_batches_tracked` counters are dropped.
Run with the project venv: .venv/bin/python (scripts/setup-venv.sh creates it).
"""
import argparse
import os
import sys


def load(path):
    import torch

    sd = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(sd, dict) and "state_dict" in sd:
        sd = sd["state_dict"]
    if not isinstance(sd, dict):
        raise SystemExit(f"{path}: expected a state dict, got {type(sd).__name__}")
    return {k.removeprefix("module."): v for k, v in sd.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="net", required=True)
    lp = sub.add_parser("lpips")
    lp.add_argument("--alexnet", required=True, help="torchvision alexnet-owt-7be5be79.pth")
    lp.add_argument("--lin", help="lpips weights/v0.1/alex.pth (default: the installed package's)")
    lp.add_argument("--out", required=True)
    rf = sub.add_parser("raft")
    rf.add_argument("--pth", required=True, help="torchvision raft_small/raft_large weights")
    rf.add_argument("--out", required=True)
    i3 = sub.add_parser("i3d")
    i3.add_argument("--pth", required=True, help="InceptionI3d Kinetics-400 weights (e.g. rgb_imagenet.pt)")
    i3.add_argument("--out", required=True)
    args = ap.parse_args()
    from safetensors.torch import save_file

    if args.net == "lpips":
        trunk = {k: v for k, v in load(args.alexnet).items() if k.startswith("features.")}
        want = {f"features.{i}.{p}" for i in (0, 3, 6, 8, 10) for p in ("weight", "bias")}
        missing = sorted(want - trunk.keys())
        if missing:
            raise SystemExit(f"{args.alexnet}: not a torchvision AlexNet, missing {missing}")
        lin_path = args.lin
        if lin_path is None:
            import lpips

            lin_path = os.path.join(os.path.dirname(lpips.__file__), "weights", "v0.1", "alex.pth")
        lin = load(lin_path)
        heads = {f"lin{k}.model.1.weight" for k in range(5)}
        if not heads <= lin.keys():
            raise SystemExit(f"{lin_path}: missing LPIPS heads {sorted(heads - lin.keys())}")
        state = {k: trunk[k] for k in sorted(want)} | {k: lin[k] for k in sorted(heads)}
    elif args.net == "i3d":
        state = {k: v for k, v in load(args.pth).items() if not k.endswith("num_batches_tracked")}
        need = {"Conv3d_1a_7x7.conv3d.weight", "Mixed_5c.b3b.bn.running_var", "logits.conv3d.weight"}
        if not need <= state.keys():
            raise SystemExit(f"{args.pth}: not an InceptionI3d state dict, missing {sorted(need - state.keys())}")
        if tuple(state["logits.conv3d.weight"].shape[:2]) != (400, 1024):
            raise SystemExit(
                f"{args.pth}: logits.conv3d.weight has shape {tuple(state['logits.conv3d.weight'].shape)}, "
                "expected [400, 1024, 1, 1, 1] (Kinetics-400)"
            )
    else:
        state = load(args.pth)
    state = {k: v.contiguous() for k, v in state.items()}
    tmp = args.out + ".tmp"
    save_file(state, tmp)
    os.replace(tmp, args.out)
    print(f"wrote {len(state)} tensors to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
