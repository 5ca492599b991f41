"""The segmentation network (PyTorch): a small Bayesian SegNet-style encoder-decoder for CPUs.

Only training and ONNX export use this module; inference runs the exported graph through
onnxruntime (:mod:`stablecues.semantics.inference`), so ``torch`` is needed only here.

Architecture ("BayesLiteSeg"): a residual encoder down to 1/16 of the input with dilated blocks
for context, and a mirrored decoder that upsamples bilinearly and adds projected encoder skips
(SegNet passes pooling indices; adding the skip features carries the same boundary detail and
exports cleanly). As in Bayesian SegNet, dropout (p = 0.5) sits at the centre of the network:
on the encoder's output (1/16) and on the first decoder stage (1/8). Every layer after the first
dropout is the *stochastic head*; everything before it is the deterministic *trunk*.

Monte-Carlo dropout is made cheap by giving the forward pass explicit dropout masks with a
leading sample axis T: the trunk runs once on the single image, its output is broadcast against
the T masks, and only the head runs on a batch of T. The output is the softmax of each sample at
1/4 of the input resolution, shape (T, 11, ceil(H/4), ceil(W/4)).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .classes import NUM_CLASSES

#: ImageNet statistics, applied inside the network to RGB input scaled to [0, 1].
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)
DROPOUT_P = 0.5


class ConvBNReLU(nn.Sequential):
    """3x3 (or k x k) convolution, batch norm, ReLU."""

    def __init__(self, cin: int, cout: int, k: int = 3, stride: int = 1, dilation: int = 1) -> None:
        pad = dilation * (k - 1) // 2
        super().__init__(
            nn.Conv2d(cin, cout, k, stride, pad, dilation=dilation, bias=False),
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
        )


class ResBlock(nn.Module):
    """Two 3x3 convolutions with batch norm and an identity shortcut (ResNet basic block)."""

    def __init__(self, channels: int, dilation: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, 1, dilation, dilation=dilation, bias=False)
        self.bn1 = nn.BatchNorm2d(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, 1, dilation, dilation=dilation, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)), inplace=True)
        y = self.bn2(self.conv2(y))
        return F.relu(x + y, inplace=True)


class BayesLiteSeg(nn.Module):
    """Small Bayesian SegNet-style network.

    Args:
        widths: channels at 1/2, 1/4, 1/8 and 1/16 of the input.
        num_classes: output classes (11 for CamVid).
        p: dropout probability at the two central dropout layers.
    """

    def __init__(
        self,
        widths: tuple[int, int, int, int] = (16, 32, 64, 128),
        num_classes: int = NUM_CLASSES,
        p: float = DROPOUT_P,
    ) -> None:
        super().__init__()
        c1, c2, c3, c4 = widths
        self.widths = widths
        self.p = p
        self.mean: torch.Tensor
        self.std: torch.Tensor
        self.register_buffer("mean", torch.tensor(MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(STD).view(1, 3, 1, 1))
        # deterministic trunk (encoder)
        self.stem = ConvBNReLU(3, c1, stride=2)  # 1/2
        self.enc2 = nn.Sequential(ConvBNReLU(c1, c2, stride=2), ResBlock(c2))  # 1/4
        self.enc3 = nn.Sequential(ConvBNReLU(c2, c3, stride=2), ResBlock(c3), ResBlock(c3))  # 1/8
        self.enc4 = nn.Sequential(
            ConvBNReLU(c3, c4, stride=2), ResBlock(c4), ResBlock(c4, dilation=2), ResBlock(c4, dilation=4)
        )  # 1/16
        self.skip8 = nn.Sequential(nn.Conv2d(c3, c3, 1, bias=False), nn.BatchNorm2d(c3))
        self.skip4 = nn.Sequential(nn.Conv2d(c2, c2, 1, bias=False), nn.BatchNorm2d(c2))
        # stochastic head (decoder)
        self.dec8_in = nn.Sequential(nn.Conv2d(c4, c3, 1, bias=False), nn.BatchNorm2d(c3))
        self.dec8 = ConvBNReLU(c3, c3)
        self.dec4_in = nn.Sequential(nn.Conv2d(c3, c2, 1, bias=False), nn.BatchNorm2d(c2))
        self.dec4 = ConvBNReLU(c2, c2)
        self.classifier = nn.Conv2d(c2, num_classes, 1)

    # -- the two halves -------------------------------------------------------------------
    def trunk(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Deterministic encoder.

        Args:
            image: (B, 3, H, W) float32 RGB in [0, 1].

        Returns:
            (x16, s8, s4): encoder output at 1/16 and projected skips at 1/8 and 1/4.
        """
        x = (image - self.mean) / self.std
        f4 = self.enc2(self.stem(x))
        f8 = self.enc3(f4)
        x16 = self.enc4(f8)
        return x16, self.skip8(f8), self.skip4(f4)

    def head(
        self,
        x16: torch.Tensor,
        s8: torch.Tensor,
        s4: torch.Tensor,
        mask16: torch.Tensor | None = None,
        mask8: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Stochastic decoder; returns (T, C, ceil(H/4), ceil(W/4)) logits.

        With masks given, ``x16`` (1 sample) is multiplied by ``mask16`` (T, c4, h16, w16) and the
        1/8 decoder features by ``mask8`` (T, c3, h8, w8): the masks hold 0 or 1/(1-p) (inverted
        dropout) and their first axis is the Monte-Carlo sample. Without masks, dropout follows
        ``self.training`` (random masks in training, identity in evaluation).
        """
        x16 = x16 * mask16 if mask16 is not None else F.dropout(x16, self.p, self.training)
        y = self.dec8_in(x16)
        y = F.interpolate(y, size=s8.shape[-2:], mode="bilinear", align_corners=False)
        y = self.dec8(F.relu(y + s8))
        y = y * mask8 if mask8 is not None else F.dropout(y, self.p, self.training)
        y = self.dec4_in(y)
        y = F.interpolate(y, size=s4.shape[-2:], mode="bilinear", align_corners=False)
        y = self.dec4(F.relu(y + s4))
        return self.classifier(y)

    def forward(
        self,
        image: torch.Tensor,
        mask16: torch.Tensor | None = None,
        mask8: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Logits at 1/4 of the input, (B, C, ceil(H/4), ceil(W/4)) (B = T with masks)."""
        x16, s8, s4 = self.trunk(image)
        return self.head(x16, s8, s4, mask16, mask8)

    def mask_shapes(self, height: int, width: int) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """(channels, h, w) of the two dropout masks for an input of ``height`` x ``width``."""
        h, w = height, width
        for _ in range(3):
            h, w = (h + 1) // 2, (w + 1) // 2
        h8, w8 = h, w
        h16, w16 = (h + 1) // 2, (w + 1) // 2
        return (self.widths[3], h16, w16), (self.widths[2], h8, w8)


class SamplingWrapper(nn.Module):
    """The graph that is exported: image and masks in, per-sample softmax out."""

    def __init__(self, net: BayesLiteSeg) -> None:
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor, mask16: torch.Tensor, mask8: torch.Tensor) -> torch.Tensor:
        """(1, 3, H, W) RGB [0, 1] + masks -> (T, C, H/4, W/4) float32 softmax."""
        return torch.softmax(self.net(image, mask16, mask8), dim=1)


def count_parameters(net: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in net.parameters() if p.requires_grad)
