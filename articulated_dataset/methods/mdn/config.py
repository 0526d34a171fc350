"""Training settings of the mixture density network: the presets (``full``, ``small``) and
:class:`TrainConfig`, checked when made."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import TypeGuard

from articulated_dataset.core.errors import UserError, option

#: Fraction of the training split's objects held out for validation.
DEFAULT_VAL_FRACTION = 0.1
DEFAULT_SEED = 0
#: Seeds are below 2**32: the per-epoch generator seed ``seed * EPOCH_SEED_STRIDE + epoch``
#: must stay inside torch's 64-bit seed range.
MAX_SEED = 2**32 - 1
#: Largest peak learning rate: AdamW's step is about lr per weight, so beyond 1 every step
#: moves the weights by more than their own scale and training diverges (NaN losses).
MAX_LR = 1.0
#: --epochs above this is a typo (1e6 epochs of the smallest split already take days).
MAX_EPOCHS = 1_000_000
#: Most torch threads per logical CPU: more only adds context switches (and a huge count would
#: make OpenMP try to start that many threads).
MAX_THREADS_PER_CPU = 4


def check_per_cpu(quantity: str, n: int) -> None:
    """A :class:`~articulated_dataset.core.errors.UserError` where ``n`` (torch threads, worker
    processes; the ``quantity`` named ``"threads"``, ``"workers"``) is more than
    :data:`MAX_THREADS_PER_CPU` per logical CPU of this machine."""
    import os

    most = MAX_THREADS_PER_CPU * (os.cpu_count() or 1)
    if n > most:
        raise UserError(f"{option(quantity)} {n} is more than {MAX_THREADS_PER_CPU} per logical CPU of this machine "
                        f"(at most {most})")


@dataclass(frozen=True)
class Preset:
    """Network size and input resolution; ``full`` is ResNet-18 at the native resolution."""

    height_px: int
    width_px: int
    width: int
    blocks: tuple[int, ...]
    stem: str
    head_hidden: int
    epochs: int
    batch_size: int
    lr: float


PRESETS = {
    # ResNet-18 (64 channels, 2-2-2-2 blocks, ImageNet stem) on the 192x108 images.
    "full": Preset(height_px=108, width_px=192, width=64, blocks=(2, 2, 2, 2), stem="imagenet",
                   head_hidden=256, epochs=30, batch_size=128, lr=1e-3),
    # A narrow one-block-per-stage ResNet on 96x54 images: a few minutes per class on 2 CPU cores
    # for 16,000 images (docs/model.md has the measured time).
    "small": Preset(height_px=54, width_px=96, width=16, blocks=(1, 1, 1, 1), stem="light",
                    head_hidden=128, epochs=8, batch_size=64, lr=2e-3),
}


@dataclass(frozen=True)
class TrainConfig:
    """Everything that determines a training run (stored in the checkpoint)."""

    class_name: str
    preset: str = "full"
    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    val_fraction: float = DEFAULT_VAL_FRACTION
    seed: int = DEFAULT_SEED
    n_components: int | None = None
    # overrides of the preset (None = preset value)
    height_px: int | None = None
    width_px: int | None = None
    width: int | None = None
    blocks: tuple[int, ...] | None = None
    max_objects: int | None = None  # use only the first N objects of the split (None = all)

    def resolved(self) -> "TrainConfig":
        """The config with every None filled from the preset."""
        if self.preset not in PRESETS:
            raise UserError(f"unknown preset {self.preset!r}; expected one of {', '.join(PRESETS)}")
        p = PRESETS[self.preset]
        from articulated_dataset.methods.mdn.model import DEFAULT_COMPONENTS

        def pick(v, default):
            return default if v is None else v

        c = replace(
            self, epochs=pick(self.epochs, p.epochs), batch_size=pick(self.batch_size, p.batch_size), lr=pick(self.lr, p.lr),
            n_components=pick(self.n_components, DEFAULT_COMPONENTS), height_px=pick(self.height_px, p.height_px),
            width_px=pick(self.width_px, p.width_px), width=pick(self.width, p.width),
            blocks=tuple(pick(self.blocks, p.blocks)),
        )
        for name, v in ((option("epochs"), c.epochs), (option("batch_size"), c.batch_size),
                        (option("components"), c.n_components),
                        ("input height", c.height_px), ("input width", c.width_px), ("network width", c.width)):
            if not is_int(v) or v <= 0:
                raise UserError(f"{name} must be a positive whole number, got {v!r}")
        if c.epochs > MAX_EPOCHS:  # type: ignore[operator]  # an int: checked in the loop above
            raise UserError(f"{option('epochs')} must be at most {MAX_EPOCHS:,}, got {c.epochs!r}")
        from articulated_dataset.benchmark.predictions import MAX_MIXTURE_COMPONENTS

        if c.n_components > MAX_MIXTURE_COMPONENTS:  # type: ignore[operator]  # an int: checked in the loop above
            raise UserError(f"{option('components')} must be at most {MAX_MIXTURE_COMPONENTS} (the predictions "
                            f"format's limit), got {c.n_components}")
        if not (isinstance(c.blocks, tuple) and c.blocks and all(is_int(b) and b > 0 for b in c.blocks)):
            raise UserError(f"network blocks must be positive whole numbers, got {c.blocks!r}")
        if not is_real_number(c.lr) or not 0.0 < c.lr <= MAX_LR:
            raise UserError(f"{option('lr')} must be a number in (0, {MAX_LR:g}], got {c.lr!r}")
        if not is_real_number(c.val_fraction) or not 0.0 <= c.val_fraction < 1.0:
            raise UserError(f"{option('val_fraction')} must be in [0, 1), got {c.val_fraction!r}")
        if not is_int(c.seed) or not 0 <= c.seed <= MAX_SEED:
            raise UserError(f"{option('seed')} must be a whole number in [0, {MAX_SEED}], got {c.seed!r}")
        if c.max_objects is not None and (not is_int(c.max_objects) or c.max_objects <= 0):
            raise UserError(f"{option('max_objects')} must be a positive whole number, got {c.max_objects!r}")
        return c

    def to_dict(self) -> dict:
        """The settings as plain JSON types (``blocks`` as a list; stored in checkpoints)."""
        d = asdict(self)
        if d["blocks"] is not None:
            d["blocks"] = list(d["blocks"])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """The settings from their :meth:`to_dict` form."""
        d = dict(d)
        if isinstance(d.get("blocks"), list):
            d["blocks"] = tuple(d["blocks"])
        return cls(**d)

    def input_config(self):
        """The network input's configuration (:class:`~.preprocess.InputConfig`) at these settings' image size."""
        from articulated_dataset.methods.mdn.preprocess import InputConfig

        return InputConfig(height_px=self.height_px, width_px=self.width_px)  # type: ignore[arg-type]  # (resolved)

    def model_config(self, target_dim: int):
        """The network's architecture (:class:`~.model.ModelConfig`) for targets of ``target_dim`` values, from the
        preset and these settings."""
        from articulated_dataset.methods.mdn.model import ModelConfig
        from articulated_dataset.methods.mdn.preprocess import N_SCALARS

        p = PRESETS[self.preset]
        # (called on a resolved config: every setting is set)
        return ModelConfig(in_channels=self.input_config().channels, target_dim=target_dim, n_components=self.n_components,  # type: ignore[arg-type]
                           width=self.width, blocks=tuple(self.blocks), stem=p.stem, head_hidden=p.head_hidden,  # type: ignore[arg-type]
                           n_scalars=N_SCALARS)


def is_int(v) -> TypeGuard[int]:
    """True for an int that is not a bool."""
    return isinstance(v, int) and not isinstance(v, bool)


def is_real_number(v) -> TypeGuard[float]:
    """A finite int or float (not a bool); an int too large for a float (a checkpoint may hold
    any Python int: 10**400) is not one."""
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:
        return False
