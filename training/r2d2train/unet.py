"""The R2D2 U-Net (fastMRI style), as the reference implementation builds it.

Per level two blocks of [3x3 conv (no bias), InstanceNorm, LeakyReLU(0.2)]; 2x2 average
pooling down; 2x2 transposed conv (no bias) + InstanceNorm + LeakyReLU up, concatenated
`[up, skip]`; final 1x1 conv with bias to one channel. The reference uses 64 base channels and
4 poolings (31.0 M parameters); the series shipped here is scaled down for CPU training.
"""
import torch
from torch import nn
import torch.nn.functional as F


class ConvBlock(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.layers = nn.Sequential(
            nn.Conv2d(cin, cout, 3, padding=1, bias=False),
            nn.InstanceNorm2d(cout),
            nn.LeakyReLU(0.2),
            nn.Conv2d(cout, cout, 3, padding=1, bias=False),
            nn.InstanceNorm2d(cout),
            nn.LeakyReLU(0.2),
        )

    def forward(self, x):
        return self.layers(x)


class UpBlock(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.layers = nn.Sequential(
            nn.ConvTranspose2d(cin, cout, 2, stride=2, bias=False),
            nn.InstanceNorm2d(cout),
            nn.LeakyReLU(0.2),
        )

    def forward(self, x):
        return self.layers(x)


class UNet(nn.Module):
    """Input [B, 2, H, W] (H, W multiples of 2^poolings), output [B, 1, H, W]."""

    def __init__(self, base_channels=16, poolings=3, in_channels=2, out_channels=1):
        super().__init__()
        self.base_channels, self.poolings = base_channels, poolings
        ch = base_channels
        self.down = nn.ModuleList([ConvBlock(in_channels, ch)])
        for _ in range(poolings - 1):
            self.down.append(ConvBlock(ch, ch * 2))
            ch *= 2
        self.bottom = ConvBlock(ch, ch * 2)
        self.up = nn.ModuleList()
        self.up_conv = nn.ModuleList()
        for level in range(poolings):
            self.up.append(UpBlock(ch * 2, ch))
            if level < poolings - 1:
                self.up_conv.append(ConvBlock(ch * 2, ch))
            else:
                self.up_conv.append(nn.Sequential(ConvBlock(ch * 2, ch), nn.Conv2d(ch, out_channels, 1, bias=True)))
            ch //= 2

    def forward(self, x):
        skips = []
        for block in self.down:
            x = block(x)
            skips.append(x)
            x = F.avg_pool2d(x, 2, stride=2)
        x = self.bottom(x)
        for up, conv in zip(self.up, self.up_conv):
            x = torch.cat([up(x), skips.pop()], dim=1)
            x = conv(x)
        return x


def parameter_count(model):
    return sum(p.numel() for p in model.parameters())
