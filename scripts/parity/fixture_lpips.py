"""LPIPS fixtures: the `lpips` package's LPIPS(net='alex', version='0.1') with its
shipped v0.1 linear heads and a randomly initialised AlexNet trunk (the ImageNet
trunk cannot be downloaded here; the computation is the same).

model/lpips_alex.safetensors: features.{0,3,6,8,10}.{weight,bias} (torchvision
AlexNet names) and lin{0..4}.model.1.weight (the package's names).
io inputs:  in0, in1 [B,3,H,W] in [-1,1] (in1 a perturbed copy of in0)
io outputs: distance [B]
"""
import os


def add_args(parser):
    parser.add_argument("--shape", default="2,3,64,96", help="input shape B,3,H,W")


def build(args, model_dir):
    import torch
    import lpips
    from safetensors.torch import save_file

    b, c, h, w = (int(v) for v in args.shape.split(","))
    model = lpips.LPIPS(net="alex", version="0.1", pretrained=True, pnet_rand=True, verbose=False).eval()
    # The trunk's slices hold torchvision's features.N modules under their indices.
    state = {}
    for name, t in model.net.state_dict().items():
        _slice, index, param = name.split(".")
        state[f"features.{index}.{param}"] = t.contiguous()
    for k in range(5):
        state[f"lin{k}.model.1.weight"] = getattr(model, f"lin{k}").model[1].weight.detach().contiguous()
    os.makedirs(model_dir, exist_ok=True)
    save_file(state, os.path.join(model_dir, "lpips_alex.safetensors"))
    in0 = torch.rand(b, c, h, w) * 2 - 1
    in1 = (in0 + 0.3 * torch.randn(b, c, h, w)).clamp(-1, 1)
    with torch.no_grad():
        distance = model(in0, in1).reshape(b)
    meta = {"net": "alex", "version": "0.1", "shape": [b, c, h, w]}
    return meta, {"in0": in0, "in1": in1, "distance": distance}
