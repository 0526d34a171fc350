"""ResNet-18 mixture density network on a single depth image (plain PyTorch).

The backbone is ResNet-18 (He et al. 2016: a stem, four stages of two basic residual
blocks, global average pooling) written out here because torchvision is not a
dependency.  Its stem takes the depth channel (plus the optional validity-mask and pixel
coordinate channels of :class:`InputConfig`) instead of RGB.  ``width`` (channels of the
first stage; ResNet-18 uses 64) and ``blocks`` (basic blocks per stage; ResNet-18 uses
``(2, 2, 2, 2)``) shrink it for the CPU ``--small`` preset.

Fully connected heads (Bishop 1994, "Mixture density networks") read the pooled features
concatenated with per-image scalars (the normalised median depth and image anchor, see
:mod:`articulated_dataset.methods.mdn.preprocess`; the backbone only sees depth relative to the
median) and give, for ``M`` components over a ``D``-dimensional normalised target::

    logits (B, M)      mixing weights pi = softmax(logits)
    means  (B, M, D)   mu_k = s(x) + d_k(x): a shared regression plus per-component offsets
    scales (B, M, D)   sigma = softplus(raw) + scale_floor  (> 0, never below the floor)

The shared term ``s`` does not change the family of mixtures; it gives the backbone the
gradient of a plain regression from the first step (docs/model.md has the measurement).

torch is imported at module import time: import this module only where torch is needed.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.nn import functional as F

#: Mixture components; the paper found m = 20 sufficient (Section 3.1).
DEFAULT_COMPONENTS = 20
#: Lower bound of every mixture scale, in normalised target units (label / training std).
#: Columns that take a few discrete values (chirality, the sign of a vertical hinge axis)
#: would otherwise let components shrink towards zero width on them: the likelihood grows
#: without bound there and their gradients, ~ 1 / sigma^2, drown those of the continuous
#: columns (measured: the axis position stopped improving).  At 0.05 std the floor is
#: 1-2 cm for axis positions and ~1.3 deg for configurations, below the errors reached.
DEFAULT_SCALE_FLOOR = 0.05
#: ResNet-18: 64 channels in the first stage, two basic blocks in each of four stages.
RESNET18_WIDTH = 64
RESNET18_BLOCKS = (2, 2, 2, 2)
STEMS = ("imagenet", "light", "light-pool")
#: Hidden units of each fully connected head.
DEFAULT_HEAD_HIDDEN = 256


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of a :class:`MixtureDensityNetwork` (stored in checkpoints).

    ``stem``: ``"imagenet"`` is ResNet's 7x7 stride-2 convolution + 3x3 stride-2 max pool
    (total stride 4); ``"light"`` is a 3x3 stride-2 convolution without pooling (stride 2);
    ``"light-pool"`` adds the 3x3 stride-2 max pool (stride 4) at 1/9 of the 7x7's cost.
    """

    in_channels: int
    target_dim: int
    n_components: int = DEFAULT_COMPONENTS
    width: int = RESNET18_WIDTH
    blocks: tuple[int, ...] = RESNET18_BLOCKS
    stem: str = "imagenet"
    head_hidden: int = DEFAULT_HEAD_HIDDEN
    scale_floor: float = DEFAULT_SCALE_FLOOR
    n_scalars: int = 1  # extra per-image scalars given to the heads (the median depth)
    shared_mean: bool = True  # means = shared regression + per-component offsets

    def to_dict(self) -> dict:
        """The architecture as plain JSON types (``blocks`` as a list; stored in checkpoints)."""
        d = asdict(self)
        d["blocks"] = list(self.blocks)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        """The architecture from its :meth:`to_dict` form."""
        d = dict(d)
        d["blocks"] = tuple(d["blocks"])
        return cls(**d)


class BasicBlock(nn.Module):
    """Two 3x3 conv-BN layers with an identity (or 1x1 conv-BN projection) shortcut."""

    def __init__(self, c_in: int, c_out: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.shortcut = nn.Sequential()
        if stride != 1 or c_in != c_out:
            self.shortcut = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride=stride, bias=False), nn.BatchNorm2d(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``relu(bn(conv(relu(bn(conv(x))))) + shortcut(x))``."""
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return F.relu(y + self.shortcut(x))


class ResNet(nn.Module):
    """ResNet backbone: stem, stages of basic blocks (channels doubling, stride 2 from the
    second stage on), global average pooling.  Output: (B, width * 2**(stages-1))."""

    def __init__(self, in_channels: int, width: int = RESNET18_WIDTH, blocks=RESNET18_BLOCKS, stem: str = "imagenet"):
        super().__init__()
        if stem == "imagenet":
            self.stem = nn.Sequential(
                nn.Conv2d(in_channels, width, 7, stride=2, padding=3, bias=False), nn.BatchNorm2d(width),
                nn.ReLU(inplace=True), nn.MaxPool2d(3, stride=2, padding=1),
            )
        elif stem in ("light", "light-pool"):
            layers = [nn.Conv2d(in_channels, width, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(width), nn.ReLU(inplace=True)]
            if stem == "light-pool":
                layers.append(nn.MaxPool2d(3, stride=2, padding=1))
            self.stem = nn.Sequential(*layers)
        else:
            raise ValueError(f"unknown stem {stem!r} (expected one of {STEMS})")
        layers = []
        c_in = width
        for stage, n_blocks in enumerate(blocks):
            c_out = width * 2**stage
            for b in range(n_blocks):
                layers.append(BasicBlock(c_in, c_out, stride=2 if (stage > 0 and b == 0) else 1))
                c_in = c_out
        self.stages = nn.Sequential(*layers)
        self.out_features = c_in
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        # zero-init the last BN of each residual branch: every block starts as the identity
        for m in self.modules():
            if isinstance(m, BasicBlock):
                nn.init.zeros_(m.bn2.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Pooled features (B, width * 2**(stages-1)) of images ``x`` (B, C, H, W)."""
        x = self.stages(self.stem(x))
        return torch.flatten(F.adaptive_avg_pool2d(x, 1), 1)


def _head(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, n_out))


class MixtureDensityNetwork(nn.Module):
    """Backbone + three heads giving a diagonal Gaussian mixture over the normalised target.

    ``forward(images (B, C, H, W), scalars (B, n_scalars))`` returns ``(logits (B, M),
    means (B, M, D), scales (B, M, D))``, all float32 (the heads run outside autocast so
    the likelihood is computed in full precision).
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        c = config
        self.backbone = ResNet(c.in_channels, c.width, c.blocks, c.stem)
        n_feat = self.backbone.out_features + c.n_scalars
        self.pi_head = _head(n_feat, c.head_hidden, c.n_components)
        self.mu_head = _head(n_feat, c.head_hidden, c.n_components * c.target_dim)
        self.shared_mu_head = _head(n_feat, c.head_hidden, c.target_dim) if c.shared_mean else None
        self.sigma_head = _head(n_feat, c.head_hidden, c.n_components * c.target_dim)
        # Start near the data: scales about one standard deviation, means spread around 0.
        nn.init.zeros_(self.sigma_head[-1].weight)  # type: ignore[arg-type]  # the head's last layer: an nn.Linear
        nn.init.constant_(self.sigma_head[-1].bias, _softplus_inverse(1.0 - c.scale_floor))  # type: ignore[arg-type]

    def forward(self, images: torch.Tensor, scalars: torch.Tensor):
        """``(logits (B, M), means (B, M, D), scales (B, M, D))`` of the mixture for ``images`` (B, C, H, W) and
        ``scalars`` (B, n_scalars); the heads run in float32."""
        feats = self.backbone(images)
        h = torch.cat([feats.float(), scalars.float()], dim=1)
        with torch.autocast(device_type=h.device.type, enabled=False):
            B, M, D = h.shape[0], self.config.n_components, self.config.target_dim
            logits = self.pi_head(h)
            means = self.mu_head(h).view(B, M, D)
            if self.shared_mu_head is not None:
                means = means + self.shared_mu_head(h)[:, None, :]
            scales = F.softplus(self.sigma_head(h)).view(B, M, D) + self.config.scale_floor
        return logits, means, scales


def _softplus_inverse(y: float) -> float:
    """x with softplus(x) = log(1 + e^x) = y (y > 0)."""
    return y + math.log(-math.expm1(-y))


def count_parameters(model: nn.Module) -> int:
    """Number of parameters (scalars) of ``model``."""
    return sum(p.numel() for p in model.parameters())


__all__ = [
    "DEFAULT_COMPONENTS", "DEFAULT_SCALE_FLOOR", "RESNET18_WIDTH", "RESNET18_BLOCKS", "ModelConfig",
    "BasicBlock", "ResNet", "MixtureDensityNetwork", "count_parameters",
]
