"""I3D fixtures: an Inception-v1-inflated-3D network written here in plain torch
(layout and key names of the common PyTorch port, `InceptionI3d`), randomly
initialised including BatchNorm statistics, and its logits on a random video.

model/i3d.safetensors: Conv3d_1a_7x7.conv3d.weight, <unit>.bn.{weight,bias,running_mean,running_var},
                       Mixed_3b.b0 ... Mixed_5c.b3b, logits.conv3d.{weight,bias}
io inputs:  video [B,3,T,224,224] in [-1,1]
io outputs: logits [B,400] (the logits averaged over the remaining time steps)
"""
import os


def add_args(parser):
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--batch", type=int, default=1)


def _same(size, k, s):
    total = max(k - s, 0) if size % s == 0 else max(k - size % s, 0)
    return total // 2, total - total // 2


def _pad(x, k, s):
    import torch.nn.functional as F

    t, h, w = x.shape[2:]
    pt, ph, pw = _same(t, k[0], s[0]), _same(h, k[1], s[1]), _same(w, k[2], s[2])
    return F.pad(x, (pw[0], pw[1], ph[0], ph[1], pt[0], pt[1]))


def _network():
    import torch
    from torch import nn
    import torch.nn.functional as F

    class Unit(nn.Module):
        def __init__(self, cin, cout, k=(1, 1, 1), s=(1, 1, 1), bn=True):
            super().__init__()
            self.k, self.s = k, s
            self.conv3d = nn.Conv3d(cin, cout, k, s, padding=0, bias=not bn)
            self.bn = nn.BatchNorm3d(cout, eps=1e-3, momentum=0.01) if bn else None

        def forward(self, x):
            y = self.conv3d(_pad(x, self.k, self.s))
            return F.relu(self.bn(y)) if self.bn is not None else y

    class Mixed(nn.Module):
        def __init__(self, cin, o):
            super().__init__()
            self.b0 = Unit(cin, o[0])
            self.b1a, self.b1b = Unit(cin, o[1]), Unit(o[1], o[2], (3, 3, 3))
            self.b2a, self.b2b = Unit(cin, o[3]), Unit(o[3], o[4], (3, 3, 3))
            self.b3b = Unit(cin, o[5])

        def forward(self, x):
            pooled = F.max_pool3d(_pad(x, (3, 3, 3), (1, 1, 1)), (3, 3, 3), (1, 1, 1))
            return torch.cat(
                [self.b0(x), self.b1b(self.b1a(x)), self.b2b(self.b2a(x)), self.b3b(pooled)], 1
            )

    class I3D(nn.Module):
        def __init__(self):
            super().__init__()
            self.Conv3d_1a_7x7 = Unit(3, 64, (7, 7, 7), (2, 2, 2))
            self.Conv3d_2b_1x1 = Unit(64, 64)
            self.Conv3d_2c_3x3 = Unit(64, 192, (3, 3, 3))
            spec = [
                ("Mixed_3b", 192, [64, 96, 128, 16, 32, 32]),
                ("Mixed_3c", 256, [128, 128, 192, 32, 96, 64]),
                ("Mixed_4b", 480, [192, 96, 208, 16, 48, 64]),
                ("Mixed_4c", 512, [160, 112, 224, 24, 64, 64]),
                ("Mixed_4d", 512, [128, 128, 256, 24, 64, 64]),
                ("Mixed_4e", 512, [112, 144, 288, 32, 64, 64]),
                ("Mixed_4f", 528, [256, 160, 320, 32, 128, 128]),
                ("Mixed_5b", 832, [256, 160, 320, 32, 128, 128]),
                ("Mixed_5c", 832, [384, 192, 384, 48, 128, 128]),
            ]
            self.names = [n for n, _, _ in spec]
            for n, cin, o in spec:
                setattr(self, n, Mixed(cin, o))
            self.logits = Unit(1024, 400, bn=False)

        def forward(self, x):
            def pool(h, k, s):
                return F.max_pool3d(_pad(h, k, s), k, s)

            h = self.Conv3d_1a_7x7(x)
            h = pool(h, (1, 3, 3), (1, 2, 2))
            h = self.Conv3d_2c_3x3(self.Conv3d_2b_1x1(h))
            h = pool(h, (1, 3, 3), (1, 2, 2))
            for n in self.names:
                if n == "Mixed_4b":
                    h = pool(h, (3, 3, 3), (2, 2, 2))
                if n == "Mixed_5b":
                    h = pool(h, (2, 2, 2), (2, 2, 2))
                h = getattr(self, n)(h)
            h = F.avg_pool3d(h, (2, 7, 7), (1, 1, 1))
            return self.logits(h).squeeze(4).squeeze(3).mean(2)

    return I3D()


def build(args, model_dir):
    import torch
    from safetensors.torch import save_file

    model = _network().eval()
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm3d):
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.2, 0.2)
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 1.5)
    state = {k: v.contiguous() for k, v in model.state_dict().items() if not k.endswith("num_batches_tracked")}
    os.makedirs(model_dir, exist_ok=True)
    save_file(state, os.path.join(model_dir, "i3d.safetensors"))
    video = torch.rand(args.batch, 3, args.frames, 224, 224) * 2 - 1
    with torch.no_grad():
        logits = model(video)
    params = sum(v.numel() for k, v in state.items() if "running" not in k)
    meta = {"frames": args.frames, "batch": args.batch, "parameters": params}
    return meta, {"video": video, "logits": logits}
