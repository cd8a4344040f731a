"""BEV encoder and the two element detector heads (paper Sec. III-B and Implementation).

Shapes: B batch, C_in view-transform channels, H x W the output BEV grid, S the cell size,
Hc x Wc = H/S x W/S, K classes. The view transform's grid is H/2 x W/2 (or H x W with
``stem_stride = 2``, the official layout).

Architecture (the official InstaGraM ``BevEncode``, with the heads reordered so that only the
distance transform is ever computed at full resolution; parameter count unchanged):

* encoder: stem conv7x7 (C_in -> 64) - BN - ReLU, then ResNet-18 stages ``layer1..layer3``
  ("3 residual blocks": two BasicBlocks each, strides 1, 2, 2) and an up-block that upsamples the
  last stage to the first and fuses them -> F_bev [B, 256, H/2, W/2].
* vertex head (SuperPoint interest-point decoder): conv3x3 256->256 - BN - ReLU - conv3x3 256->128 -
  BN - ReLU - conv1x1 128->S*S+1, where the two 3x3 convolutions *stride* from H/2 down to the cell
  grid H/S (the official code convolves at H/2 and max-pools twice: 4x the work for the same
  parameters) -> logits [B, S*S+1, Hc, Wc].
* distance-transform head: conv3x3 256->128 - BN - ReLU - conv1x1 128->K at H/2, bilinear x2 upsampling
  to H x W, ReLU, clamp to [0, dt_clip]. The official code upsamples F_bev first and convolves at
  full resolution (4x the work); here only K channels ever exist at full resolution.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from .backbone import Up, conv_bn_relu


class BasicBlock(nn.Module):
    """ResNet BasicBlock: conv3x3-BN-ReLU-conv3x3-BN + (projected) identity, ReLU."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        nn.init.zeros_(self.bn2.weight)  # zero-init residual, as the official encoder
        self.shortcut = nn.Identity()
        if stride != 1 or cin != cout:  # projected identity
            self.shortcut = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)), inplace=True)
        return F.relu(self.bn2(self.conv2(y)) + self.shortcut(x), inplace=True)


def strided_conv_bn_relu(cin: int, cout: int, stride: int) -> nn.Sequential:
    """conv - BN - ReLU mapping size n to n / stride: kernel 3 up to stride 3, kernel = stride beyond."""
    kernel = max(3, stride)
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride=stride, padding=(kernel - stride + 1) // 2, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


def cell_strides(cell_size: int) -> tuple[int, int]:
    """Strides of the vertex head's two convolutions from F_bev (H/2) to the cell grid (H/S)."""
    factor = cell_size // 2
    first = 2 if factor % 2 == 0 else factor
    return first, factor // first


class BEVHeads(nn.Module):
    """BEV features -> {F_bev, vertex logits, distance transform}."""

    def __init__(self, *, in_channels: int, num_classes: int, cell_size: int, dt_clip: float, channels: int = 256,
                 stage_channels: tuple[int, ...] = (64, 128, 256), head_channels: int = 128, stem_stride: int = 1,
                 distance_head: bool = True):
        super().__init__()
        self.cell_size, self.dt_clip = cell_size, dt_clip
        c0 = stage_channels[0]
        self.stem = conv_bn_relu(in_channels, c0, kernel=7, stride=stem_stride)
        widths = (c0, *stage_channels)  # strides 1, 2, 2, ...
        self.stages = nn.ModuleList(nn.Sequential(BasicBlock(cin, c, 2 if i else 1), BasicBlock(c, c))
                                    for i, (cin, c) in enumerate(zip(widths[:-1], widths[1:])))
        self.up = Up(stage_channels[0], stage_channels[-1], channels)
        s1, s2 = cell_strides(cell_size)
        self.vertex_head = nn.Sequential(strided_conv_bn_relu(channels, channels, s1),
                                         strided_conv_bn_relu(channels, head_channels, s2),
                                         nn.Conv2d(head_channels, cell_size * cell_size + 1, kernel_size=1))
        # without it (model.bev_heads.distance_head=false): no pred_distance, as the official
        # visual-descriptor variant (its BevEncode built without distance_reg)
        self.distance_head = nn.Sequential(
            conv_bn_relu(channels, head_channels), nn.Conv2d(head_channels, num_classes, kernel_size=1)
        ) if distance_head else None

    def forward(self, bev: torch.Tensor, fuse: Callable[[torch.Tensor], torch.Tensor] | None = None
                ) -> dict[str, torch.Tensor]:
        """bev [B, C_in, H/2, W/2] (or [B, C_in, H, W] with stem_stride 2) ->
        ``bev_features`` [B, 256, H/2, W/2], ``pred_vertex_logits`` [B, S*S+1, Hc, Wc],
        ``pred_distance`` [B, K, H, W] in [0, dt_clip] (only with the distance head).

        ``fuse``: applied to the first stage's output [B, stage_channels[0], H/2, W/2] (the temporal
        memory's fusion, models/temporal.py); the rest of the encoder sees its result. The two halves are
        methods of their own so that int8 (precision.py) quantizes each as one graph."""
        first = self.first_stage(bev)
        return self.rest(first if fuse is None else fuse(first))

    def first_stage(self, bev: torch.Tensor) -> torch.Tensor:
        """The stem and the first stage: bev -> [B, stage_channels[0], H/2, W/2]."""
        return self.stages[0](self.stem(bev))

    def rest(self, first: torch.Tensor) -> dict[str, torch.Tensor]:
        """The first stage's (fused) output -> the later stages, the up-block and the heads (``forward``)."""
        x = first
        for stage in self.stages[1:]:
            x = stage(x)
        features = self.up(first, x)  # F_bev
        out = {"bev_features": features, "pred_vertex_logits": self.vertex_head(features)}
        if self.distance_head is not None:
            distance = self.distance_head(features)
            distance = F.interpolate(distance, scale_factor=2.0, mode="bilinear", align_corners=False)
            out["pred_distance"] = distance.relu().clamp(max=self.dt_clip)
        return out
