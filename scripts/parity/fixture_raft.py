"""RAFT fixtures: torchvision's raft_large / raft_small with random weights (and
randomised batch-norm statistics, so evaluation-mode normalisation matters), in
evaluation mode.

model/<variant>.safetensors: the state dict, torchvision key names.
io inputs:  image1, image2 [B,3,H,W] in [-1,1] (image2: image1 shifted by a few
            pixels plus noise, so the flow is non-trivial)
io outputs: flow_first (after the first refinement), flow (after --iterations)
"""
import os


def add_args(parser):
    parser.add_argument("--variant", choices=["raft_large", "raft_small"], default="raft_small")
    parser.add_argument("--shape", default="1,3,128,128", help="B,3,H,W (H, W multiples of 8, >= 128)")
    parser.add_argument("--iterations", type=int, default=3)


def build(args, model_dir):
    import torch
    from safetensors.torch import save_file
    from torchvision.models.optical_flow import raft_large, raft_small

    b, c, h, w = (int(v) for v in args.shape.split(","))
    model = (raft_large if args.variant == "raft_large" else raft_small)(weights=None)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 1.5)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.2, 0.2)
    model.eval()
    os.makedirs(model_dir, exist_ok=True)
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, os.path.join(model_dir, f"{args.variant}.safetensors"))
    # A smooth random image and a shifted copy.
    base = torch.nn.functional.interpolate(torch.rand(b, c, h // 8, w // 8), size=(h, w), mode="bilinear", align_corners=False)
    image1 = base * 2 - 1
    image2 = torch.roll(image1, shifts=(2, 3), dims=(2, 3)) + 0.05 * torch.randn(b, c, h, w)
    with torch.no_grad():
        flows = model(image1, image2, num_flow_updates=args.iterations)
    meta = {"variant": args.variant, "iterations": args.iterations, "shape": [b, c, h, w]}
    return meta, {"image1": image1, "image2": image2, "flow_first": flows[0], "flow": flows[-1]}
