"""The paper's pyramid depth network (Greene & Roy, Sec. III-B), in PyTorch.

Input resolution — our decision. The paper says the feature extractors run at levels L3..L6
(16/32/64/128 filters, first conv of each block stride 2), which leaves open what feeds L3: a
coarse L2 image (64x128), or the full 256x512 image through a stem. We take the **full 256x512
gray image through a two-layer stride-2 stem** (L1: 8 filters, L2: 16 filters), because

* the photometric losses at D0..D2 (the paper's fine-to-coarse point) compare full-resolution
  images, so the network must see full-resolution texture to be taught by them;
* a 64x128 input throws away exactly the fine texture the stereo losses supervise through, and
  makes distant (small-disparity) pixels sub-pixel at the input;
* it stays cheap: the stem adds ~1.3 k parameters and ~1 ms per image in onnxruntime.

Levels: ``L_k`` has stride ``2**k``; for a 256x512 input L3 is 32x64 and L6 is 4x8.

Blocks (all 3x3 convs, ReLU):

* feature extractor at L3..L6: ``conv(stride 2) → conv`` + 1x1 projected skip, then ``conv →
  conv`` + identity skip (two residual blocks, four convs);
* disparity estimator at L3..L6: residual 3x3 layers with 96/64/32/8 filters then a 3x3 conv
  to 2 channels and a sigmoid scaled by ``max_d_frac`` (left and right disparity as a fraction
  of image width);
* upsampler: stride-2 transposed conv of the coarser level's fused features and bilinear
  upsampling of its disparity; L5..L3 concatenate their own features with both.

Parameter count: see :func:`count_parameters` (1,597,672 with the defaults, vs the paper's
2.3 M; the text does not specify the difference, DESIGN.md notes the same gap). ``width``
multiplies every channel count (stem, features, estimators; the cost grows about as its square):
an experiment of issue #31's (a wider network as a seed-spread stabilizer), 1.0 in every shipped
model.

Example::

    >>> import torch
    >>> net = PyramidDepthNet()
    >>> outs = net(torch.zeros(1, 1, 256, 512))
    >>> [tuple(o.shape) for o in outs]
    [(1, 2, 32, 64), (1, 2, 16, 32), (1, 2, 8, 16), (1, 2, 4, 8)]
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

FEATURE_CHANNELS = (16, 32, 64, 128)  # L3..L6
ESTIMATOR_CHANNELS = (96, 64, 32, 8)
STEM_CHANNELS = (8, 16)  # L1, L2


def _widened(channels: tuple[int, ...], width: float) -> tuple[int, ...]:
    """``channels`` times ``width``, rounded (at least 1 each)."""
    return tuple(max(1, round(c * width)) for c in channels)


def _conv(c_in: int, c_out: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1)


class FeatureBlock(nn.Module):
    """Two residual blocks (four 3x3 convs), the first conv with stride 2: (B,Ci,H,W) -> (B,Co,H/2,W/2)."""

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.conv1 = _conv(c_in, c_out, stride=2)
        self.conv2 = _conv(c_out, c_out)
        self.skip = nn.Conv2d(c_in, c_out, 1, stride=2)
        self.conv3 = _conv(c_out, c_out)
        self.conv4 = _conv(c_out, c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.conv2(F.relu(self.conv1(x))) + self.skip(x))
        return F.relu(self.conv4(F.relu(self.conv3(y))) + y)


class DisparityEstimator(nn.Module):
    """3x3 residual layers 96/64/32/8 then sigmoid: features -> (B, 2, H, W) d_frac (left, right)."""

    def __init__(self, c_in: int, max_d_frac: float, channels: tuple[int, ...] = ESTIMATOR_CHANNELS) -> None:
        super().__init__()
        chans = (c_in, *channels)
        self.convs = nn.ModuleList(_conv(a, b) for a, b in zip(chans[:-1], chans[1:]))
        self.skips = nn.ModuleList(
            nn.Identity() if a == b else nn.Conv2d(a, b, 1, bias=False) for a, b in zip(chans[:-1], chans[1:])
        )
        self.out = _conv(chans[-1], 2)
        # start near typical street-scene disparities (sigmoid(-2.2)·0.3 ≈ 0.03 of the width), not 0.15
        nn.init.constant_(self.out.bias, -2.2)
        self.max_d_frac = float(max_d_frac)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for conv, skip in zip(self.convs, self.skips):
            x = F.relu(conv(x) + skip(x))
        return self.max_d_frac * torch.sigmoid(self.out(x))


class PyramidDepthNet(nn.Module):
    """Gray image (B, 1, H, W), normalized, H and W multiples of 64 -> disparities L3..L6.

    ``forward`` returns a list ``[D3, D4, D5, D6]``, each (B, 2, H/2**k, W/2**k), channel 0 the
    left and channel 1 the right disparity, as a fraction of image width in (0, max_d_frac).
    """

    def __init__(self, max_d_frac: float = 0.3, width: float = 1.0) -> None:
        super().__init__()
        s1, s2 = _widened(STEM_CHANNELS, width)
        feature_channels = _widened(FEATURE_CHANNELS, width)
        self.stem = nn.Sequential(_conv(1, s1, 2), nn.ReLU(inplace=True), _conv(s1, s2, 2), nn.ReLU(inplace=True))
        chans = (s2, *feature_channels)
        self.features = nn.ModuleList(FeatureBlock(a, b) for a, b in zip(chans[:-1], chans[1:]))
        # fused channels at each level: own features (+ upsampled coarser fused features + 2 disp)
        fused = [feature_channels[-1]]
        for c in reversed(feature_channels[:-1]):
            fused.insert(0, c + c + 2)
        self.fused_channels = tuple(fused)  # L3..L6
        self.upsamplers = nn.ModuleList(
            nn.ConvTranspose2d(fused[k + 1], feature_channels[k], 4, stride=2, padding=1)
            for k in range(len(feature_channels) - 1)
        )
        estimator_channels = _widened(ESTIMATOR_CHANNELS, width)
        self.estimators = nn.ModuleList(DisparityEstimator(c, max_d_frac, estimator_channels) for c in fused)
        self.max_d_frac = float(max_d_frac)

    def forward(self, image: torch.Tensor) -> list[torch.Tensor]:
        x = self.stem(image)
        feats = []
        for block in self.features:
            x = block(x)
            feats.append(x)
        n = len(feats)
        disps: list[torch.Tensor] = [None] * n  # type: ignore[list-item]
        fused = feats[-1]
        disps[-1] = self.estimators[-1](fused)
        for k in range(n - 2, -1, -1):
            up_feat = F.relu(self.upsamplers[k](fused))
            up_disp = F.interpolate(disps[k + 1], scale_factor=2.0, mode="bilinear", align_corners=False)
            fused = torch.cat([feats[k], up_feat, up_disp], dim=1)
            disps[k] = self.estimators[k](fused)
        return disps


class ExportWrapper(nn.Module):
    """What goes into ONNX: normalized image (B, 1, H, W) -> left L3 d_frac (B, H/8, W/8)."""

    def __init__(self, net: PyramidDepthNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.net(image)[0][:, 0]


class EnsembleExportWrapper(nn.Module):
    """Several networks as one ONNX graph: normalized image (B, 1, H, W) -> the arithmetic mean of
    their left L3 d_frac (B, H/8, W/8). One input, one output: the same contract as one network.

    Averaging seeds of one recipe damps the seed-to-seed spread of the metric level (issue #31);
    the cost is one forward pass per member.
    """

    def __init__(self, nets: list[PyramidDepthNet]) -> None:
        super().__init__()
        if not nets:
            raise ValueError("an ensemble needs at least one network")
        self.nets = nn.ModuleList(nets)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return torch.stack([net(image)[0][:, 0] for net in self.nets], dim=0).mean(dim=0)


def count_parameters(net: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in net.parameters() if p.requires_grad)
