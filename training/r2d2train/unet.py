"""The R2D2 U-Net (fastMRI style), as the reference implementation builds it.

Per level two blocks of [3x3 conv (no bias), InstanceNorm, LeakyReLU(0.2)]; 2x2 average
pooling down; 2x2 transposed conv (no bias) + InstanceNorm + LeakyReLU up, concatenated
`[up, skip]`; final 1x1 conv with bias to one channel. The reference uses 64 base channels and
4 poolings (31.0 M parameters); the series shipped here is scaled down for CPU training.

`norm="none"` drops the instance normalisation and every bias. InstanceNorm takes statistics
over the whole image, so a network with it answers differently on a crop than on the same
pixels inside the full field: crops are then no valid training samples for full-field
inference. Without it the network is local (each output pixel depends only on its receptive
field) and positively homogeneous (N(c u) = c N(u) for c > 0, as LeakyReLU, convolutions
without bias and average pooling are), so bright and faint emission meet the same
operator, as in bias-free denoisers (Mohan et al. 2020) and the reference's U-WDSR, which has
no feature normalisation either.
"""
import torch
from torch import nn
import torch.nn.functional as F


NORMS = ("instance", "none")


def _norm(kind, channels):
    return nn.InstanceNorm2d(channels) if kind == "instance" else nn.Identity()


class ConvBlock(nn.Module):
    def __init__(self, cin, cout, norm="instance"):
        super().__init__()
        self.layers = nn.Sequential(
            nn.Conv2d(cin, cout, 3, padding=1, bias=False),
            _norm(norm, cout),
            nn.LeakyReLU(0.2),
            nn.Conv2d(cout, cout, 3, padding=1, bias=False),
            _norm(norm, cout),
            nn.LeakyReLU(0.2),
        )

    def forward(self, x):
        return self.layers(x)


class UpBlock(nn.Module):
    def __init__(self, cin, cout, norm="instance"):
        super().__init__()
        self.layers = nn.Sequential(
            nn.ConvTranspose2d(cin, cout, 2, stride=2, bias=False),
            _norm(norm, cout),
            nn.LeakyReLU(0.2),
        )

    def forward(self, x):
        return self.layers(x)


class UNet(nn.Module):
    """Input [B, 2, H, W] (H, W multiples of 2^poolings), output [B, 1, H, W]."""

    def __init__(self, base_channels=16, poolings=3, in_channels=2, out_channels=1, norm="instance"):
        super().__init__()
        if norm not in NORMS:
            raise ValueError(f"norm: expected one of {NORMS}, got {norm!r}")
        self.base_channels, self.poolings, self.norm = base_channels, poolings, norm
        ch = base_channels
        self.down = nn.ModuleList([ConvBlock(in_channels, ch, norm)])
        for _ in range(poolings - 1):
            self.down.append(ConvBlock(ch, ch * 2, norm))
            ch *= 2
        self.bottom = ConvBlock(ch, ch * 2, norm)
        self.up = nn.ModuleList()
        self.up_conv = nn.ModuleList()
        for level in range(poolings):
            self.up.append(UpBlock(ch * 2, ch, norm))
            if level < poolings - 1:
                self.up_conv.append(ConvBlock(ch * 2, ch, norm))
            else:
                last = nn.Conv2d(ch, out_channels, 1, bias=(norm == "instance"))
                self.up_conv.append(nn.Sequential(ConvBlock(ch * 2, ch, norm), last))
            ch //= 2
        if norm == "none":
            # He initialisation for LeakyReLU keeps the signal's scale through the depth when
            # no normalisation restores it (PyTorch's default shrinks it at every layer); the
            # output layer starts small, so network 1 starts near the zero increment.
            for m in self.modules():
                if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                    nn.init.kaiming_normal_(m.weight, a=0.2, nonlinearity="leaky_relu")
            with torch.no_grad():
                last.weight.mul_(0.1)

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
