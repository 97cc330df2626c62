"""The MFuseNet reference network in PyTorch, shared by `bench-pytorch.py` and `train-torch.py`.

Written from the paper and the layer list of the authors' `FuseNetwork` (`weihaosky/MFuseNet`,
`network.py`): the same layers, shapes and `state_dict` names as `fuse::mfusenet::network`, so
that our safetensors weights and checkpoints load into it with `load_state_dict`.
"""

import torch
from torch import nn
import torch.nn.functional as F


def conv_bn(cin, cout, k, stride=1):
    # Conv3d without bias, then BatchNorm3d: `<name>.0.weight`, `<name>.1.{weight,bias,running_*}`.
    return nn.Sequential(nn.Conv3d(cin, cout, k, stride=stride, padding=k // 2, bias=False), nn.BatchNorm3d(cout))


def up_bn(cin, cout):
    # ConvTranspose3d k3 s2 p1 op1 (doubles D, H, W), no bias, then BatchNorm3d.
    return nn.Sequential(
        nn.ConvTranspose3d(cin, cout, 3, stride=2, padding=1, output_padding=1, bias=False), nn.BatchNorm3d(cout)
    )


class Reference(nn.Module):
    """MFuseNet for `views` cost volumes of shape [B, D, H, W] (D, H, W multiples of 4).

    `views = 0` is the view-count-agnostic variant (`fuse::nn::pool`, weights files marked
    `view_fusion = mean-max`): any number of volumes, their features' mean and maximum (8 channels,
    the mean's first) instead of the features side by side.

    `sharp = True` (`fuse::mfusenet::Network::sharp`, read from `concat.0.weight`'s 5·N input
    channels): each view also brings a sharp volume (per-pixel costs) straight into `concat`,
    after its four feature channels; `logits` then takes the N views' volumes and after them
    their N sharp volumes."""

    # Kernel sizes: feature.0, .2, .4, .6; concat, dconv21, uconv2, distill1 (the rest are 3).
    # `lite` (`fuse::mfusenet::Architecture::Lite`, metadata `architecture = lite`): about a
    # fifth of the paper's work per voxel, the same channels and `state_dict` names.
    KERNELS = {"paper": ((7, 5, 5, 3), (7, 7, 7, 5)), "lite": ((5, 3, 3, 3), (3, 7, 3, 3))}

    def __init__(self, views, architecture="paper", sharp=False):
        super().__init__()
        self.views = views
        self.sharp = sharp and views > 0
        self.architecture = architecture
        (f0, f2, f4, f6), (kc, k21, ku2, kd1) = self.KERNELS[architecture]
        relu = lambda: nn.ReLU(True)  # noqa: E731
        self.feature = nn.Sequential(
            conv_bn(1, 4, f0), relu(), conv_bn(4, 4, f2), relu(), conv_bn(4, 4, f4), relu(), conv_bn(4, 4, f6), relu()
        )
        self.concat = conv_bn(8 if views == 0 else (5 if self.sharp else 4) * views, 4, kc)
        self.down1 = conv_bn(4, 4, 3, stride=2)
        self.dconv1 = conv_bn(4, 4, 3)
        self.down2 = conv_bn(4, 4, 3, stride=2)
        self.dconv21 = conv_bn(4, 4, k21)
        self.dconv22 = conv_bn(4, 4, 3)
        self.up1 = up_bn(4, 4)
        self.uconv1 = conv_bn(8, 4, 3)
        self.up2 = up_bn(4, 4)
        self.uconv2 = conv_bn(8, 4, ku2)
        self.distill1 = conv_bn(4, 4, kd1)
        self.classify = nn.Conv3d(4, 1, 3, padding=1)

    def logits(self, volumes):
        # volumes: `views` tensors [B, D, H, W] (and as many sharp ones) -> logits [B, D, H, W]
        sharp = volumes[self.views:] if self.sharp else []
        volumes = volumes[: self.views] if self.sharp else volumes
        features = [self.feature(v.unsqueeze(1)) for v in volumes]  # N x [B, 4, D, H, W]
        if self.sharp:
            # Each view's features, then its sharp volume: [B, 5N, D, H, W].
            c = torch.cat([t for f, s in zip(features, sharp) for t in (f, s.unsqueeze(1))], 1)
        elif self.views == 0:
            stacked = torch.stack(features)  # [N, B, 4, D, H, W]
            c = torch.cat((stacked.mean(0), stacked.amax(0)), 1)  # [B, 8, D, H, W]
        else:
            c = torch.cat(features, 1)  # [B, 4N, D, H, W]
        c = F.relu(self.concat(c))  # [B, 4, D, H, W]
        d1 = F.relu(self.down1(c))  # [B, 4, D/2, H/2, W/2]
        d1 = F.relu(self.dconv1(d1)) + d1
        d2 = F.relu(self.down2(d1))  # [B, 4, D/4, H/4, W/4]
        d2 = F.relu(self.dconv21(d2)) + d2
        d2 = F.relu(self.dconv22(d2)) + d2
        u1 = F.relu(self.uconv1(torch.cat((F.relu(self.up1(d2)), d1), 1)))  # [B, 4, D/2, H/2, W/2]
        u2 = F.relu(self.uconv2(torch.cat((F.relu(self.up2(u1)), c), 1)))  # [B, 4, D, H, W]
        c = F.relu(self.distill1(u2)) + u2
        return self.classify(c).squeeze(1)  # [B, D, H, W]

    def forward(self, volumes):
        p = F.softmax(self.logits(volumes), dim=1)
        d = torch.arange(p.shape[1], dtype=p.dtype, device=p.device).view(1, -1, 1, 1)
        return (p * d).sum(1)  # [B, H, W]
