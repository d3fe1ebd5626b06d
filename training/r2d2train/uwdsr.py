"""The U-WDSR network of R2D2 v2 (Aghabiglou et al. 2025): the R2D2 U-Net's levels with each
convolution block replaced by a WDSR block stack (weight-normalised convolutions, no feature
normalisation).

Per level (`ConvBlock`): subtract 0.5 from the input; a 3x3 head convolution to 32 residual
units; 16 residual blocks [3x3 conv 32 -> 128, ReLU, 3x3 conv 128 -> 32, added to the block's
input]; a 3x3 tail convolution to the level's channels; plus a 5x5 skip convolution from the
input; then add 0.5 back. Down: 2x2 average pooling; up: a weight-normalised 2x2 transposed
convolution, concatenated `[up, skip]`; the last level ends with a plain 1x1 convolution to
one channel. The reference's published series use 64 base channels and 4 poolings.

Parameter names are the reference's (`down_sample_layers`, `conv`, `up_transpose_conv`,
`up_conv`; `weight_g`, `weight_v`, `bias` on each weight-normalised convolution), so a
reference checkpoint's `state_dict` loads once its Lightning prefix is removed. Weight
normalisation is computed here (weight = g v / |v|, the norm over every dimension but the
first, as `torch.nn.utils.weight_norm` with its default dim 0), so the names do not depend on
the PyTorch version; `fold_weight_norm` freezes it into plain weights for export.
"""
import math

import torch
from torch import nn
import torch.nn.functional as F

RESIDUAL_UNITS = 32
BLOCKS = 16
WIDTH_MULTIPLIER = 4
IMAGE_MEAN = 0.5
SKIP_KERNEL = 5


class _WeightNormConv(nn.Module):
    """A convolution whose weight is g v / |v| (norm over all dimensions but the first)."""

    transposed = False

    def __init__(self, weight_shape, stride=1, padding=0, g_init=1.0):
        super().__init__()
        v = torch.empty(weight_shape)
        nn.init.kaiming_uniform_(v, a=math.sqrt(5))
        self.weight_v = nn.Parameter(v)
        self.weight_g = nn.Parameter(torch.full((weight_shape[0],) + (1,) * (len(weight_shape) - 1), float(g_init)))
        self.bias = nn.Parameter(torch.zeros(weight_shape[1] if self.transposed else weight_shape[0]))
        self.stride, self.padding = stride, padding
        self.folded = None

    def weight(self):
        if self.folded is not None:
            return self.folded
        dims = tuple(range(1, self.weight_v.dim()))
        return self.weight_g * self.weight_v / self.weight_v.pow(2).sum(dim=dims, keepdim=True).sqrt()

    def forward(self, x):
        if self.transposed:
            return F.conv_transpose2d(x, self.weight(), self.bias, stride=self.stride)
        return F.conv2d(x, self.weight(), self.bias, stride=self.stride, padding=self.padding)


class WNConv2d(_WeightNormConv):
    def __init__(self, cin, cout, kernel, g_init=1.0):
        super().__init__((cout, cin, kernel, kernel), padding=kernel // 2, g_init=g_init)


class WNConvTranspose2d(_WeightNormConv):
    transposed = True

    def __init__(self, cin, cout):
        super().__init__((cin, cout, 2, 2), stride=2)


class ResidualBlock(nn.Module):
    def __init__(self, units, res_scale):
        super().__init__()
        wide = units * WIDTH_MULTIPLIER
        self.body = nn.Sequential(WNConv2d(units, wide, 3, g_init=2.0), nn.ReLU(), WNConv2d(wide, units, 3, g_init=res_scale))

    def forward(self, x):
        return self.body(x) + x


class ConvBlock(nn.Module):
    """One level: WDSR body plus a 5x5 skip, around the image mean 0.5."""

    def __init__(self, cin, cout):
        super().__init__()
        body = [WNConv2d(cin, RESIDUAL_UNITS, 3)]
        body += [ResidualBlock(RESIDUAL_UNITS, 1 / math.sqrt(BLOCKS)) for _ in range(BLOCKS)]
        body.append(WNConv2d(RESIDUAL_UNITS, cout, 3))
        self.body = nn.Sequential(*body)
        # The reference builds the skip only when the channel counts differ, which they always
        # do in this U-Net; an empty skip would be the identity.
        self.skip = nn.Sequential(WNConv2d(cin, cout, SKIP_KERNEL)) if cin != cout else nn.Sequential()

    def forward(self, x):
        x = x - IMAGE_MEAN
        return self.body(x) + self.skip(x) + IMAGE_MEAN


class TransposeConvBlock(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.layers = nn.Sequential(WNConvTranspose2d(cin, cout))

    def forward(self, x):
        return self.layers(x)


class UWDSR(nn.Module):
    """Input [B, 2, H, W] (H, W multiples of 2^poolings), output [B, 1, H, W]."""

    def __init__(self, base_channels=64, poolings=4, in_channels=2, out_channels=1):
        super().__init__()
        self.base_channels, self.poolings = base_channels, poolings
        ch = base_channels
        self.down_sample_layers = nn.ModuleList([ConvBlock(in_channels, ch)])
        for _ in range(poolings - 1):
            self.down_sample_layers.append(ConvBlock(ch, ch * 2))
            ch *= 2
        self.conv = ConvBlock(ch, ch * 2)
        self.up_transpose_conv = nn.ModuleList()
        self.up_conv = nn.ModuleList()
        for level in range(poolings):
            self.up_transpose_conv.append(TransposeConvBlock(ch * 2, ch))
            if level < poolings - 1:
                self.up_conv.append(ConvBlock(ch * 2, ch))
            else:
                self.up_conv.append(nn.Sequential(ConvBlock(ch * 2, ch), nn.Conv2d(ch, out_channels, 1)))
            ch //= 2

    def forward(self, x):
        skips = []
        for block in self.down_sample_layers:
            x = block(x)
            skips.append(x)
            x = F.avg_pool2d(x, 2, stride=2)
        x = self.conv(x)
        for up, conv in zip(self.up_transpose_conv, self.up_conv):
            x = conv(torch.cat([up(x), skips.pop()], dim=1))
        return x


def fold_weight_norm(model):
    """Freeze every weight normalisation into a plain weight (for inference and export)."""
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, _WeightNormConv):
                m.folded = None
                m.folded = m.weight().detach().clone()
    return model
