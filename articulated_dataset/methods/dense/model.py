"""The dense network: a small U-Net from the 9-channel point image to per-pixel outputs.

Encoder: a stride-2 stem at the input resolution (so the handle's few pixels are seen at
full resolution), then four stride-2 stages (widths ``w, 2w, 4w, 6w``) and a global
context vector added back at the bottom; decoder: bilinear upsampling with skip
connections back to the output resolution (input / 4).  Per output pixel it predicts
(:meth:`DenseNet.split`):

* ``seg``: logits over (body, part 0 .. part J-1) (background is given by validity);
* per joint j: ``offset`` (3, m) from the pixel's point to the axis origin, ``rot6`` (6): the
  axis direction and the frame's x axis (Gram-Schmidt at aggregation), ``q`` (1, rad or m),
  ``part_offset`` (3, m, axis frame), ``conf`` (3 logits weighting the pixel's origin,
  rotation and q votes);
* per image, voted by every pixel: ``geometry`` (depth, width, height in m, chirality logit)
  and one confidence logit.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.nn import functional as F

from articulated_dataset.methods.dense.features import N_INPUT_CHANNELS

log = logging.getLogger(__name__)
#: Non-empty once a :class:`PackedConv2d` has warned that oneDNN refused to prepack (one warning per process).
_PACKING_WARNED: list = []

#: Offsets are predicted in units of this (m).
OFFSET_SCALE_M = 0.5
#: Per-joint channels: offset 3, rot6 6, q 1, part offset 3, confidences 3 (in this order: the
#: slices below, within a joint's block).
JOINT_CHANNELS = 16
OFFSET_CHANNELS = slice(0, 3)
ROT6_CHANNELS = slice(3, 9)
Q_CHANNEL = 9
PART_OFFSET_CHANNELS = slice(10, 13)
CONF_CHANNELS = slice(13, 16)
#: Geometry channels: depth, width, height, chirality logit, confidence.
GEOMETRY_CHANNELS = 5
#: The arithmetic an inference copy of the network may run in (:meth:`DenseNet.folded`).
PRECISIONS = ("float32", "bfloat16")


def bfloat16_native() -> bool:
    """Whether this CPU computes bfloat16 convolutions natively (oneDNN's AVX512-BF16 or AMX
    kernels); elsewhere ``precision="bfloat16"`` is emulated, and slower than float32."""
    return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())


@dataclass(frozen=True)
class DenseConfig:
    """Architecture (stored in checkpoints)."""

    n_joints: int
    width: int = 16
    height_px: int = 108
    width_px: int = 192

    def to_dict(self) -> dict:
        """The architecture as a dict (stored in checkpoints)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "DenseConfig":
        """The architecture from a checkpoint's dict (other keys ignored)."""
        return cls(**{k: d[k] for k in ("n_joints", "width", "height_px", "width_px")})


def _mkldnn_packing_available() -> bool:
    """Whether this PyTorch has oneDNN's convolution with prepacked weights (CPU builds with
    MKL-DNN: :class:`PackedConv2d`)."""
    try:
        return bool(torch.backends.mkldnn.is_available()) and hasattr(torch.ops.mkldnn, "_convolution_pointwise") \
            and hasattr(torch.ops.mkldnn, "_reorder_convolution_weight")
    except (AttributeError, RuntimeError):  # pragma: no cover - builds without the ops
        return False


class PackedConv2d(nn.Module):
    """An inference copy of a (folded) float32 CPU convolution, optionally with the ReLU after it,
    computed by oneDNN with its weights reordered ONCE into oneDNN's blocked layout for the input's
    shape (``torch.ops.mkldnn._reorder_convolution_weight`` and ``_convolution_pointwise``, the
    kernels ``torch.compile`` with freezing emits for a CPU convolution).  ``nn.Conv2d`` reorders
    the weights on every call; prepacked, a cabinet batch of 128 takes 218 instead of 237 ms on one
    idle core (``benchmarks/dense_inference.py --threads 1``), 1.4-1.7x less time where another
    process loads the machine, and whole test splits in two worker processes run 6-11% faster;
    the outputs the same to float rounding (within about
    3e-5).  The packed weights are an opaque tensor: made
    at the first call (again when the input's channels or size change) and left out when the module
    is pickled (a prediction worker packs its own)."""

    def __init__(self, conv: nn.Conv2d, relu: bool):
        super().__init__()
        self.register_buffer("weight", conv.weight.detach().clone())
        self.register_buffer("bias", None if conv.bias is None else conv.bias.detach().clone())
        self.conv_args = (list(conv.padding), list(conv.stride), list(conv.dilation), int(conv.groups))
        self.relu = bool(relu)
        self._packed: tuple | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The convolution (and ReLU) of ``x`` with the prepacked weights, packed at the first call for the input's
        shape; where oneDNN refuses, the plain convolution."""
        key = tuple(x.shape[1:])
        if self._packed is None or self._packed[0] != key:
            try:
                packed = torch.ops.mkldnn._reorder_convolution_weight(self.weight, *self.conv_args, list(x.shape))
            except RuntimeError as exc:  # oneDNN refuses this CPU or shape: the plain convolution, same function
                if not _PACKING_WARNED:
                    log.warning("oneDNN weight prepacking failed (%s); computing the convolutions unpacked", exc)
                    _PACKING_WARNED.append(True)
                packed = None
            self._packed = (key, packed)
        if self._packed[1] is None:
            padding, stride, dilation, groups = self.conv_args
            # (registered buffers, and the convolution's own arguments)
            y = F.conv2d(x, self.weight, self.bias, stride, padding, dilation, groups)  # type: ignore[arg-type]
            return F.relu(y) if self.relu else y
        return torch.ops.mkldnn._convolution_pointwise(x, self._packed[1], self.bias, *self.conv_args,
                                                      "relu" if self.relu else "none", [], "")

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_packed"] = None
        return state


def _cbr(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class DenseNet(nn.Module):
    """The dense U-Net (module docstring): a (B, 9, H, W) point image to (B, n_out, H / 4, W / 4) per-pixel outputs."""
    def __init__(self, config: DenseConfig):
        super().__init__()
        self.config = config
        J, w = config.n_joints, config.width
        c0, c1, c2, c3, c4 = w, w, 2 * w, 4 * w, 6 * w
        self.stem = _cbr(N_INPUT_CHANNELS, c0, 2)                       # 1/2
        self.e1 = nn.Sequential(_cbr(c0, c1, 2), _cbr(c1, c1))          # 1/4 (output resolution)
        self.e2 = nn.Sequential(_cbr(c1, c2, 2), _cbr(c2, c2))          # 1/8
        self.e3 = nn.Sequential(_cbr(c2, c3, 2), _cbr(c3, c3))          # 1/16
        self.e4 = nn.Sequential(_cbr(c3, c4, 2), _cbr(c4, c4))          # 1/32
        self.context = nn.Sequential(nn.Linear(c4, c4), nn.ReLU(inplace=True))
        self.d3 = _cbr(c4 + c3, c3)
        self.d2 = _cbr(c3 + c2, c2)
        self.d1 = nn.Sequential(_cbr(c2 + c1, 2 * w), nn.Conv2d(2 * w, 2 * w, 1, bias=False), nn.BatchNorm2d(2 * w),
                                nn.ReLU(inplace=True))
        self.n_out = (1 + J) + J * JOINT_CHANNELS + GEOMETRY_CHANNELS
        self.head = nn.Conv2d(2 * w, self.n_out, 1)
        # the weights in channels-last layout: the convolutions then run 2-2.5x faster on the CPU
        # (oneDNN's NHWC kernels; measured in benchmarks/dense_inference.py) and a training
        # step about 1.35x (0.75 instead of 1.03 s per batch of 128 on 2 cores); the input may be in either layout, the output is made contiguous
        self.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # (not in torch's overloads)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Raw outputs (B, n_out, H / 4, W / 4), float32, of a batch ``x`` (B, 9, H, W) of point images."""
        dtype = self.head.weight.dtype
        if x.dtype != dtype:  # a bfloat16 copy (folded(precision="bfloat16")) takes float32 inputs
            x = x.to(dtype)
        f1 = self.e1(self.stem(x))
        f2 = self.e2(f1)
        f3 = self.e3(f2)
        f4 = self.e4(f3)
        f4 = f4 + self.context(f4.mean((2, 3)))[:, :, None, None]

        def up(a, ref):
            return F.interpolate(a, size=ref.shape[2:], mode="bilinear", align_corners=False)

        y = self.d3(torch.cat([up(f4, f3), f3], 1))
        y = self.d2(torch.cat([up(y, f2), f2], 1))
        y = self.d1(torch.cat([up(y, f1), f1], 1))
        # float32 in the default layout, in one copy (a bfloat16 network's: 1.8x faster than two)
        return self.head(y).to(torch.float32, memory_format=torch.contiguous_format)

    def folded(self, precision: str = "float32") -> "DenseNet":
        """A copy for inference: eval mode, every batch normalisation folded into the convolution
        before it (:func:`torch.nn.utils.fusion.fuse_conv_bn_eval`: ``w' = w g / s``, ``b' = beta +
        (b - mu) g / s`` with ``s = sqrt(var + eps)``), channels-last.  The same function to float
        rounding (outputs within about 1e-5; predictions within 1e-6 m and rad), one pass over each
        layer's activations fewer: 5-8% of the batched pipeline (``benchmarks/dense_inference.py``).
        The stem's weights stay in the default layout: on the 9-channel input (which
        :func:`~.features.make_inputs` writes channel by channel) the stem runs 1.6x as fast as in
        channels-last with the input converted to it (32 images on one core: 6.6 against 10.7 ms;
        every later layer reads the stem's output in channels-last).  It has no batch
        normalisation to train; its ``state_dict`` is not a checkpoint's.

        ``precision="bfloat16"``: the folded weights rounded to bfloat16 (8 significant bits) and
        every layer computed in it (the stem again in the default layout: 3% faster than
        converting its input to channels-last); inputs and outputs stay float32.  On a CPU with native bfloat16
        arithmetic (AVX512-BF16 or AMX: :func:`bfloat16_native`) the network runs about twice
        as fast; the outputs differ from float32's by the rounding (docs/dense.md "Precision")."""
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        import copy

        from torch.nn.utils.fusion import fuse_conv_bn_eval

        model = copy.deepcopy(self).eval()
        for seq in model.modules():
            if isinstance(seq, nn.Sequential):
                for i in range(len(seq) - 1):
                    if isinstance(seq[i], nn.Conv2d) and isinstance(seq[i + 1], nn.BatchNorm2d):
                        seq[i], seq[i + 1] = fuse_conv_bn_eval(seq[i], seq[i + 1]), nn.Identity()  # type: ignore[type-var, arg-type]  # checked just above
        model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # (not in torch's overloads)
        if precision == "bfloat16":
            model.to(dtype=torch.bfloat16)  # each weight keeps its layout
        model.stem.to(memory_format=torch.contiguous_format)  # type: ignore[call-overload]  # (not in torch's overloads)
        if precision == "float32" and model.head.weight.device.type == "cpu" and _mkldnn_packing_available():
            _pack_convolutions(model)
        return model

    def split(self, out: torch.Tensor) -> dict:
        """Named views of the raw output (B, n_out, h, w)."""
        J = self.config.n_joints
        B, _, H, W = out.shape
        r = out[:, 1 + J : 1 + J + J * JOINT_CHANNELS].reshape(B, J, JOINT_CHANNELS, H, W)
        g = out[:, 1 + J + J * JOINT_CHANNELS :]
        return {
            "seg": out[:, : 1 + J],
            "offset": r[:, :, OFFSET_CHANNELS] * OFFSET_SCALE_M,
            "rot6": r[:, :, ROT6_CHANNELS],
            "q": r[:, :, Q_CHANNEL],
            "part_offset": r[:, :, PART_OFFSET_CHANNELS] * OFFSET_SCALE_M,
            "conf": r[:, :, CONF_CHANNELS],
            "geometry": g[:, 0:4],
            "geometry_conf": g[:, 4],
        }


def _pack_convolutions(model: nn.Module) -> None:
    """Replace every convolution of a folded network by a :class:`PackedConv2d`, with the ReLU that
    follows it (after the folded batch normalisation's :class:`~torch.nn.Identity`) fused in."""
    for seq in [m for m in model.modules() if isinstance(m, nn.Sequential)]:
        layers = list(seq)
        for i, layer in enumerate(layers):
            if isinstance(layer, nn.Conv2d):
                j = i + 1
                while j < len(layers) and isinstance(layers[j], nn.Identity):
                    j += 1
                relu = j < len(layers) and isinstance(layers[j], nn.ReLU)
                seq[i] = PackedConv2d(layer, relu)
                if relu:
                    seq[j] = nn.Identity()
    model.head = PackedConv2d(model.head, False)  # type: ignore[arg-type]  # the head is an nn.Conv2d


def count_parameters(model: nn.Module) -> int:
    """Number of parameters (scalars) of ``model``."""
    return sum(p.numel() for p in model.parameters())
