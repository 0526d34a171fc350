"""Training loop of the per-class mixture density network (``artdata train``).

* Data: one class's training split is read shard by shard, each depth image reduced to the
  model input (:mod:`articulated_dataset.mdn.preprocess`) and held in memory as float16
  (2 bytes x 2 planes x h x w per image: 13 GB for 160,000 images at 192x108, 0.2 GB for
  16,000 at the small preset's 96x54); targets are encoded by
  :class:`articulated_dataset.targets.TargetLayout`, axis origins made relative to the
  image anchor (:func:`anchored_columns`), and normalised with
  :class:`articulated_dataset.targets.NormStats` computed from the training images (the
  validation objects excluded).  Columns constant in training are not modelled
  (:func:`active_columns`).
* Validation: a held-out part of the TRAINING split, chosen by object index (a seeded
  permutation of the split's objects; ``val_fraction`` of them, all their images), so no
  object is both trained on and validated on.  The test split is never read.
* Optimisation: AdamW, cosine learning-rate decay with a linear warm-up, gradient-norm
  clipping; mixed precision (bfloat16 autocast, or float16 with loss scaling) on a GPU,
  float32 on the CPU.
* Checkpoints: written atomically after every epoch (model, optimizer, schedule, loss
  scaler, RNG state, history, configuration, layout, normalisation).  ``resume=True``
  continues from the checkpoint to the identical state: the batch order of epoch ``e``
  depends only on ``(seed, e)``, so an interrupted and resumed run equals an
  uninterrupted one.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import DataFormatError, UserError, check_memory
from ..format import Split, one_split_dir

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "artdata-mdn"
CHECKPOINT_VERSION = 1
#: Fraction of the training split's objects held out for validation.
DEFAULT_VAL_FRACTION = 0.1
DEFAULT_SEED = 0
#: Images preprocessed per chunk while loading (bounds the float32 temporaries).
LOAD_CHUNK = 512
#: Warm-up length: this fraction of all steps, at most WARMUP_MAX_STEPS.
WARMUP_FRACTION = 0.05
WARMUP_MAX_STEPS = 500
#: Gradient norms are clipped to this: a safety net for the rare huge gradients of a label far
#: outside every component; healthy steps of the small preset measured 20-100.
GRAD_CLIP_NORM = 100.0
#: Decoupled weight decay of AdamW.
WEIGHT_DECAY = 1e-4
#: Final learning rate as a fraction of the peak (cosine schedule).
FINAL_LR_FRACTION = 0.01
#: A column is constant when its std is within this factor of the NormStats floor.
CONSTANT_COLUMN_TOLERANCE = 1.0 + 1e-6
#: Offset mixing the seed and the epoch into the shuffling generator's seed.
EPOCH_SEED_STRIDE = 1_000_003
#: Seeds are below 2**32: the per-epoch generator seed ``seed * EPOCH_SEED_STRIDE + epoch``
#: must stay inside torch's 64-bit seed range.
MAX_SEED = 2**32 - 1
#: Most torch threads per logical CPU: more only adds context switches (and a huge count would
#: make OpenMP try to start that many threads).
MAX_THREADS_PER_CPU = 4
#: Largest peak learning rate: AdamW's step is about lr per weight, so beyond 1 every step
#: moves the weights by more than their own scale and training diverges (NaN losses).
MAX_LR = 1.0
#: Bytes held per mixture-head parameter while training: float32 weight, gradient and
#: AdamW's two moments.
BYTES_PER_TRAINED_PARAMETER = 4 * 4


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
        from .model import DEFAULT_COMPONENTS

        def pick(v, default):
            return default if v is None else v

        c = replace(
            self, epochs=pick(self.epochs, p.epochs), batch_size=pick(self.batch_size, p.batch_size), lr=pick(self.lr, p.lr),
            n_components=pick(self.n_components, DEFAULT_COMPONENTS), height_px=pick(self.height_px, p.height_px),
            width_px=pick(self.width_px, p.width_px), width=pick(self.width, p.width),
            blocks=tuple(pick(self.blocks, p.blocks)),
        )
        for name, v in (("--epochs", c.epochs), ("--batch-size", c.batch_size), ("--components", c.n_components),
                        ("input height", c.height_px), ("input width", c.width_px), ("network width", c.width)):
            if not _is_int(v) or v <= 0:
                raise UserError(f"{name} must be a positive whole number, got {v!r}")
        if not (isinstance(c.blocks, tuple) and c.blocks and all(_is_int(b) and b > 0 for b in c.blocks)):
            raise UserError(f"network blocks must be positive whole numbers, got {c.blocks!r}")
        if not _is_real_number(c.lr) or not 0.0 < c.lr <= MAX_LR:
            raise UserError(f"--lr must be a number in (0, {MAX_LR:g}], got {c.lr!r}")
        if not _is_real_number(c.val_fraction) or not 0.0 <= c.val_fraction < 1.0:
            raise UserError(f"--val-fraction must be in [0, 1), got {c.val_fraction!r}")
        if not _is_int(c.seed) or not 0 <= c.seed <= MAX_SEED:
            raise UserError(f"--seed must be a whole number in [0, {MAX_SEED}], got {c.seed!r}")
        if c.max_objects is not None and (not _is_int(c.max_objects) or c.max_objects <= 0):
            raise UserError(f"--max-objects must be a positive whole number, got {c.max_objects!r}")
        return c

    def to_dict(self) -> dict:
        d = asdict(self)
        if d["blocks"] is not None:
            d["blocks"] = list(d["blocks"])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        d = dict(d)
        if isinstance(d.get("blocks"), list):
            d["blocks"] = tuple(d["blocks"])
        return cls(**d)

    def input_config(self):
        from .preprocess import InputConfig

        return InputConfig(height_px=self.height_px, width_px=self.width_px)

    def model_config(self, target_dim: int):
        from .model import ModelConfig
        from .preprocess import N_SCALARS

        p = PRESETS[self.preset]
        return ModelConfig(in_channels=self.input_config().channels, target_dim=target_dim, n_components=self.n_components,
                           width=self.width, blocks=tuple(self.blocks), stem=p.stem, head_hidden=p.head_hidden,
                           n_scalars=N_SCALARS)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_real_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# --------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------

@dataclass
class PreparedSplit:
    """A split reduced to model inputs, in memory (torch tensors, CPU)."""

    planes: "object"  # torch.Tensor (N, 2, h, w) float16
    scalars: "object"  # torch.Tensor (N, 1) float32
    targets: np.ndarray  # (N, D) float32, label units (encoded, not normalised)
    anchor: "object"  # torch.Tensor (N, 3) float32, metres: centroid of the valid pixels (preprocess.image_anchor)
    object_index: np.ndarray  # (N,) int64
    sample_id: np.ndarray  # (N,) int64
    shard_of: np.ndarray = field(default=None)  # (N,) index of the shard each image came from


def resolve_split_dir(data: str | Path) -> Path:
    """The one split folder at ``data`` (a UserError if there is none or several)."""
    return one_split_dir(data)


def split_class(split_dir: Path) -> str:
    return Split(split_dir).class_name


def load_split(split_dir: Path, layout, input_config, *, max_objects: int | None = None, progress: bool = False,
               with_targets: bool = True) -> PreparedSplit:
    """Read every shard of ``split_dir`` and reduce it to model inputs (and encoded targets)."""
    import torch
    from tqdm.auto import tqdm

    from .preprocess import preprocess_depth

    split = Split(split_dir)
    manifest, shards = split.manifest, split.shards
    if not shards:
        raise DataFormatError(f"{split_dir}: the split has no shards")
    planes, scalars, anchors, targets, obj, sid, shard_of = [], [], [], [], [], [], []
    total = int(manifest.get("n_images", 0)) or None
    bar = tqdm(total=total, desc=f"loading {split_dir}", unit="img", disable=not progress, leave=False)
    for s_idx, sh in enumerate(shards):
        oi = sh.read("object_index")
        keep = np.ones(len(oi), bool) if max_objects is None else oi < max_objects
        if not keep.any():
            sh.close()
            continue
        idx = np.nonzero(keep)[0]
        K = sh.K
        for start in range(0, len(idx), LOAD_CHUNK):
            sel = idx[start : start + LOAD_CHUNK]
            depth = sh.read("depth", slice(int(sel[0]), int(sel[-1]) + 1))[sel - sel[0]]
            p, s, a = preprocess_depth(depth, input_config, K)
            planes.append(p)
            scalars.append(s)
            anchors.append(a)
            bar.update(len(sel))
        if with_targets:
            labels = sh.labels()
            labels = {k: v[idx] for k, v in labels.items()}
            targets.append(np.asarray(layout.encode(labels), np.float32))
        obj.append(oi[idx].astype(np.int64))
        sid.append(sh.read("sample_id")[idx].astype(np.int64))
        shard_of.append(np.full(len(idx), s_idx))
        sh.close()
    bar.close()
    if not planes:
        raise UserError(f"{split_dir}: no images selected")
    return PreparedSplit(
        planes=torch.cat(planes), scalars=torch.cat(scalars), anchor=torch.cat(anchors),
        targets=np.concatenate(targets) if with_targets else np.zeros((sum(len(o) for o in obj), 0), np.float32),
        object_index=np.concatenate(obj), sample_id=np.concatenate(sid), shard_of=np.concatenate(shard_of),
    )


def split_by_object(object_index: np.ndarray, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks (train, val) over images: ``round(val_fraction * n_objects)`` objects (at
    least one when val_fraction > 0 and there are two objects or more), chosen by a
    permutation seeded with ``seed``, go to validation with all their images."""
    objects = np.unique(object_index)
    n_val = int(round(val_fraction * len(objects)))
    if val_fraction > 0 and len(objects) >= 2:
        n_val = min(max(n_val, 1), len(objects) - 1)
    else:
        n_val = 0
    perm = np.random.default_rng(seed).permutation(objects)
    val = np.isin(object_index, perm[:n_val])
    return ~val, val


# --------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------

def atomic_torch_save(obj: dict, path: Path) -> None:
    import torch

    tmp = path.with_name(path.name + ".partial")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def read_checkpoint_file(path: str | Path, map_location="cpu"):
    """``torch.load(path, weights_only=True)`` (tensors and plain containers only: nothing in the
    file is executed); a missing or unreadable file is a one-line UserError.  The contents are
    the caller's to check (:func:`load_checkpoint`, the dense model's loader)."""
    import torch

    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint not found: {path}")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch.load raises many types on a corrupt file (even IndexError)
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise UserError(f"{path}: not a readable model checkpoint ({first})") from None


def prepare_training_output(split_dir: Path, class_name: str, out: Path, *, resume: bool, load, config,
                            example_name: str) -> dict | None:
    """Checks shared by every ``artdata train``: the split holds ``class_name`` and is generated
    (not ingested real captures), ``out`` is a file, and ``--resume`` finds a checkpoint trained
    with the same ``config`` (``load(out)`` reads it; its ``train_config`` is compared through
    ``type(config).from_dict``).  Returns that checkpoint, or None for a new run."""
    split = Split(split_dir)
    if split.class_name != class_name:
        raise UserError(f"{split_dir}: holds class {split.class_name!r}, not {class_name!r} (--class)")
    if split.is_real:
        raise UserError(f"{split_dir} holds ingested real captures (labels NaN where not given); train on a generated "
                        f"split and use real splits with 'artdata predict'")
    if out.exists() and out.is_dir():
        raise UserError(f"--out {out} is a directory; give a file name such as {example_name}")
    if not resume:
        if out.exists():
            raise UserError(f"{out} exists; pass --resume to continue its training or choose another --out")
        return None
    if not out.exists():
        raise UserError(f"--resume: no checkpoint at {out} to resume from")
    ckpt = load(out)
    old = type(config).from_dict(ckpt["train_config"])
    if old != config:
        diff = [k for k in config.to_dict() if config.to_dict()[k] != old.to_dict().get(k)]
        raise UserError(f"--resume: {out} was trained with different settings ({', '.join(diff)}); "
                        f"repeat the original options")
    return ckpt


def load_checkpoint(path: str | Path, map_location="cpu") -> dict:
    """Load and check an ``artdata train`` checkpoint; any problem is a one-line UserError.

    The file is read with ``torch.load(weights_only=True)`` (tensors and plain containers
    only: nothing in it is executed) and every field the package reads is checked
    (:func:`check_checkpoint`) before a network is built from it.
    """
    path = Path(path)
    ckpt = read_checkpoint_file(path, map_location)
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path}: not an artdata MDN checkpoint (written by 'artdata train')")
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise UserError(f"{path}: checkpoint version {str(ckpt.get('version'))[:40]} is not readable "
                        f"(expected {CHECKPOINT_VERSION})")
    for key in ("class_name", "layout_names", "norm_stats", "model_config", "input_config", "train_config", "model_state"):
        if key not in ckpt:
            raise UserError(f"{path}: checkpoint is missing {key!r}")
    check_checkpoint(ckpt, path)
    return ckpt


def check_checkpoint(ckpt: dict, path) -> None:
    """Every field of a loaded checkpoint that the package reads has the type and value
    ``artdata train`` writes: the class is registered and its target layout matches; the
    training config is valid and implies the stored model and input configs (so no size read
    from the file is allocated unchecked); the normalisation statistics fit the layout and are
    finite; the column lists are in range; the weights are finite tensors; the epoch count is
    a whole number.  Otherwise a one-line :class:`UserError` naming ``path``."""
    import torch

    from ..registry import get_class
    from ..targets import NormStats, TargetLayout
    from .model import ModelConfig
    from .preprocess import InputConfig

    def bad(what: str) -> UserError:
        return UserError(f"{path}: corrupt checkpoint: {what}")

    name = ckpt["class_name"]
    if not isinstance(name, str):
        raise bad("class_name is not a string")
    try:
        obj_class = get_class(name)
    except UserError as exc:
        raise UserError(f"{path}: {exc}") from None
    layout = TargetLayout.for_class(obj_class.name)
    if not isinstance(ckpt["layout_names"], list) or list(ckpt["layout_names"]) != list(layout.names):
        raise UserError(f"{path}: the checkpoint's target layout differs from this version's {name!r} layout; retrain it")
    for key in ("train_config", "model_config", "input_config", "norm_stats", "model_state"):
        if not isinstance(ckpt[key], dict):
            raise bad(f"{key} is not a mapping")
    try:
        config = TrainConfig.from_dict(ckpt["train_config"])
    except TypeError as exc:
        raise bad(f"train_config ({str(exc).splitlines()[0][:120]})") from None
    try:
        config = config.resolved()
    except UserError as exc:
        raise bad(f"train_config: {exc}") from None
    if config.class_name != name:
        raise bad(f"train_config is for class {str(config.class_name)[:40]!r}, the checkpoint for {name!r}")
    D = len(layout.names)
    active = ckpt.get("active_columns", list(range(D)))
    if not (isinstance(active, list) and active and all(_is_int(i) and 0 <= i < D for i in active)
            and active == sorted(set(active))):
        raise bad(f"active_columns must be increasing column indices in [0, {D})")
    anchored = ckpt.get("anchored_columns", [])
    if not (isinstance(anchored, list) and all(isinstance(c, list) and len(c) == 2 and all(_is_int(i) and 0 <= i < D for i in c)
                                                for c in anchored)):
        raise bad(f"anchored_columns must be pairs of column indices in [0, {D})")
    try:
        model_config = ModelConfig.from_dict(ckpt["model_config"])
        input_config = InputConfig.from_dict(ckpt["input_config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise bad(f"model or input config ({type(exc).__name__}: {str(exc).splitlines()[0][:120] if str(exc) else ''})") from None
    if model_config != config.model_config(len(active)) or input_config != config.input_config():
        raise bad("model_config / input_config do not follow from its train_config")
    try:
        stats = NormStats.from_dict(ckpt["norm_stats"])
        stats.check_layout(layout)
        finite = np.isfinite(np.asarray(stats.mean, np.float64)).all() and np.isfinite(np.asarray(stats.std, np.float64)).all()
    except UserError as exc:
        raise bad(str(exc)) from None
    except (TypeError, ValueError) as exc:
        raise bad(f"norm_stats ({str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__})") from None
    if not finite or not (np.asarray(stats.std, np.float64) > 0).all():
        raise bad("norm_stats must have finite means and positive finite standard deviations")
    state = ckpt["model_state"]
    if not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()):
        raise bad("model_state must map parameter names to tensors")
    if not all(bool(torch.isfinite(v).all()) for v in state.values() if v.is_floating_point()):
        raise bad("model_state holds NaN or infinite weights")
    if not _is_int(ckpt.get("epoch", 0)) or ckpt.get("epoch", 0) < 0:
        raise bad("epoch must be a whole number >= 0")


def build_model_from_checkpoint(ckpt: dict, device="cpu"):
    """The network of a checkpoint, weights loaded, in eval mode."""
    from .model import MixtureDensityNetwork, ModelConfig

    model = MixtureDensityNetwork(ModelConfig.from_dict(ckpt["model_config"]))
    try:
        model.load_state_dict(ckpt["model_state"])
    except RuntimeError as exc:
        raise UserError(f"checkpoint weights do not match its model configuration ({str(exc).splitlines()[0][:160]})") from None
    return model.to(device).eval()


# --------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------

def resolve_device(device: str | None) -> "object":
    import torch

    if device in (None, "", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise UserError(f"unknown --device {device!r} (expected auto, cpu, cuda or cuda:N)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"--device {device}: no CUDA GPU is available")
    return dev


def configure_threads(n_threads: int | None = None) -> int:
    """Use every core this process may run on for intra-op parallelism (2 here) unless told
    otherwise; returns the number set.  Called once per process by the commands."""
    import torch

    if n_threads is None:
        try:
            n_threads = len(os.sched_getaffinity(0))
        except AttributeError:  # pragma: no cover - non-Linux
            n_threads = os.cpu_count() or 1
    most = MAX_THREADS_PER_CPU * (os.cpu_count() or 1)
    if n_threads > most:
        raise UserError(f"--threads {n_threads} is more than {MAX_THREADS_PER_CPU} per logical CPU of this machine "
                        f"(at most {most})")
    torch.set_num_threads(max(1, int(n_threads)))
    return torch.get_num_threads()


def lr_factor(step: int, total_steps: int) -> float:
    """Learning-rate multiplier: linear warm-up over ``w = min(WARMUP_MAX_STEPS,
    WARMUP_FRACTION * total)`` steps, then cosine decay from 1 to FINAL_LR_FRACTION."""
    warm = max(1, min(WARMUP_MAX_STEPS, int(WARMUP_FRACTION * total_steps)))
    if step < warm:
        return (step + 1) / warm
    t = min(1.0, (step - warm) / max(1, total_steps - warm))
    return FINAL_LR_FRACTION + (1.0 - FINAL_LR_FRACTION) * 0.5 * (1.0 + math.cos(math.pi * t))


def _column_groups(names: list[str]) -> dict[str, list[int]]:
    """Indices of each joint's origin columns and of the q columns (for validation metrics)."""
    groups: dict[str, list[int]] = {}
    for i, n in enumerate(names):
        head, _, rest = n.partition(".")
        if rest.startswith("origin."):
            groups.setdefault(f"{head}.origin", []).append(i)
        elif rest == "q":
            groups.setdefault("q", []).append(i)
    return groups


def evaluate(model, planes, scalars, targets_norm, active, stats, names, input_config, device, batch_size: int, amp) -> dict:
    """Validation NLL (nats/image, normalised units, modelled columns) and the mean-of-best
    estimate's mean axis-origin error (cm) and mean |q error| (label units, rad or m) over the
    given images; ``targets_norm`` (N, D) normalised, ``active`` the modelled column indices."""
    import torch

    from .loss import mean_of_best, mixture_log_prob
    from .preprocess import assemble_inputs

    model.eval()
    nll, est = [], []
    with torch.no_grad():
        for start in range(0, planes.shape[0], batch_size):
            x = assemble_inputs(planes[start : start + batch_size].to(device), input_config)
            s = scalars[start : start + batch_size].to(device)
            y = torch.as_tensor(targets_norm[start : start + batch_size][:, active], device=device)
            with amp():
                logits, means, scales = model(x, s)
            nll.append(-mixture_log_prob(logits, means, scales, y).cpu())
            est.append(mean_of_best(logits, means).cpu())
    est_lab = np.asarray(stats.denormalize(expand_active(torch.cat(est).numpy(), active, len(names), 0.0)))
    truth = np.asarray(stats.denormalize(targets_norm))
    groups = _column_groups(names)
    origin_cm = [100.0 * np.linalg.norm(est_lab[:, g] - truth[:, g], axis=1) for k, g in groups.items() if k != "q"]
    out = {"val_nll": float(torch.cat(nll).mean())}
    if origin_cm:
        out["val_origin_error_cm"] = float(np.mean(origin_cm))
    if "q" in groups:
        out["val_q_error"] = float(np.mean(np.abs(est_lab[:, groups["q"]] - truth[:, groups["q"]])))
    return out


def train(data: str | Path, out: str | Path, config: TrainConfig, *, device: str | None = None, resume: bool = False,
          progress: bool = True, stop_after_epoch: int | None = None, echo=None) -> dict:
    """Train (or resume training) the class's MDN on the split at ``data``; checkpoint to ``out``.

    ``stop_after_epoch`` ends the run early after that many epochs in total (the
    checkpoint can be resumed).  ``echo`` (a callable taking one line) reports each epoch.
    Returns the checkpoint dict of the last epoch.
    """
    import contextlib

    import torch
    from tqdm.auto import tqdm

    from ..registry import get_class
    from ..targets import NormStats, TargetLayout
    from .loss import mixture_nll
    from .model import MixtureDensityNetwork, count_parameters
    from .preprocess import assemble_inputs

    out = Path(out)
    config = config.resolved()
    obj_class = get_class(config.class_name)
    split_dir = resolve_split_dir(data)
    ckpt = prepare_training_output(split_dir, obj_class.name, out, resume=resume, load=load_checkpoint, config=config,
                                   example_name="model.pt")
    if ckpt is not None and ckpt.get("finished"):
        log.info("%s: training already finished (%d epochs)", out, ckpt["epoch"])
        return ckpt
    out.parent.mkdir(parents=True, exist_ok=True)

    dev = resolve_device(device)
    layout = TargetLayout.for_class(obj_class.name)
    names = list(layout.names)
    input_config = config.input_config()
    prepared = load_split(split_dir, layout, input_config, max_objects=config.max_objects, progress=progress)
    train_mask, val_mask = split_by_object(prepared.object_index, config.val_fraction, config.seed)
    anchored = anchored_columns(names)
    prepared.targets = shift_anchored(prepared.targets, prepared.anchor.numpy(), anchored, -1.0).astype(np.float32)
    if ckpt is not None:
        stats = NormStats.from_dict(ckpt["norm_stats"])
    else:
        # statistics of the images trained on (validation objects excluded)
        stats = NormStats.from_targets(prepared.targets[train_mask], layout)
        stats.sources = [str(split_dir)]
    targets_norm = np.asarray(stats.normalize(prepared.targets), np.float32)
    tr_idx, va_idx = np.nonzero(train_mask)[0], np.nonzero(val_mask)[0]
    planes_tr, scalars_tr = prepared.planes[tr_idx], prepared.scalars[tr_idx]
    active = active_columns(stats)
    y_tr = torch.as_tensor(targets_norm[tr_idx][:, active])
    planes_va, scalars_va, y_va = prepared.planes[va_idx], prepared.scalars[va_idx], targets_norm[va_idx]
    prepared.planes = None  # the slices above are copies: free the full array
    if dev.type == "cuda":  # the whole training set fits in GPU memory at these sizes
        planes_tr, scalars_tr, y_tr = planes_tr.to(dev), scalars_tr.to(dev), y_tr.to(dev)
    n_train = len(tr_idx)
    if n_train < 2:
        raise UserError(f"{split_dir}: only {n_train} training image(s) after holding out validation objects")

    model_config = config.model_config(len(active))
    check_memory(float(config.n_components) * (model_config.head_hidden + 1) * (2 * len(active) + 1)
                 * BYTES_PER_TRAINED_PARAMETER, f"a mixture head of {config.n_components} components")
    torch.manual_seed(config.seed)
    model = MixtureDensityNetwork(model_config).to(dev, memory_format=torch.channels_last)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=WEIGHT_DECAY)
    batch = min(config.batch_size, n_train)
    steps_per_epoch = n_train // batch  # the last incomplete batch is dropped (BatchNorm needs > 1 sample)
    total_steps = steps_per_epoch * config.epochs
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: lr_factor(step, total_steps))
    use_bf16 = dev.type == "cuda" and torch.cuda.is_bf16_supported()
    use_fp16 = dev.type == "cuda" and not use_bf16
    scaler = torch.amp.GradScaler("cuda", enabled=use_fp16)

    def amp():
        if dev.type != "cuda":
            return contextlib.nullcontext()
        return torch.autocast("cuda", dtype=torch.bfloat16 if use_bf16 else torch.float16)

    history: list[dict] = []
    start_epoch = 0
    if ckpt is not None:
        model.load_state_dict(ckpt["model_state"])
        optimizer.load_state_dict(ckpt["optimizer_state"])
        scheduler.load_state_dict(ckpt["scheduler_state"])
        scaler.load_state_dict(ckpt["scaler_state"])
        torch.set_rng_state(ckpt["rng_state"])
        history = list(ckpt["history"])
        start_epoch = int(ckpt["epoch"])
    log.info("%s: %d train / %d val images, %s parameters, device %s", obj_class.name, n_train, len(va_idx),
             f"{count_parameters(model):,}", dev)

    def checkpoint(epoch: int, finished: bool) -> dict:
        return {
            "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "class_name": obj_class.name,
            "layout_names": names, "anchored_columns": [list(c) for c in anchored], "active_columns": [int(i) for i in active], "norm_stats": _plain(stats.to_dict()), "model_config": model_config.to_dict(),
            "input_config": input_config.to_dict(), "train_config": config.to_dict(),
            "data": {"split_dir": str(split_dir), "n_train": int(n_train), "n_val": int(len(va_idx))},
            "epoch": epoch, "finished": finished, "history": history,
            "model_state": model.state_dict(), "optimizer_state": optimizer.state_dict(),
            "scheduler_state": scheduler.state_dict(), "scaler_state": scaler.state_dict(),
            "rng_state": torch.get_rng_state(),
        }

    last = stop_after_epoch if stop_after_epoch is not None else config.epochs
    last = min(last, config.epochs)
    for epoch in range(start_epoch, last):
        t0 = time.perf_counter()
        model.train()
        gen = torch.Generator().manual_seed(config.seed * EPOCH_SEED_STRIDE + epoch)
        order = torch.randperm(n_train, generator=gen)
        bar = tqdm(range(steps_per_epoch), desc=f"epoch {epoch + 1}/{config.epochs}", unit="batch",
                   disable=not progress, leave=False)
        running, n_seen = 0.0, 0
        for step in bar:
            idx = order[step * batch : (step + 1) * batch].to(planes_tr.device)
            x = assemble_inputs(planes_tr[idx].to(dev, non_blocking=True), input_config).contiguous(memory_format=torch.channels_last)
            s = scalars_tr[idx].to(dev, non_blocking=True)
            y = y_tr[idx].to(dev, non_blocking=True)
            with amp():
                logits, means, scales = model(x, s)
            loss = mixture_nll(logits, means, scales, y)
            optimizer.zero_grad(set_to_none=True)
            scaler.scale(loss).backward()
            scaler.unscale_(optimizer)
            torch.nn.utils.clip_grad_norm_(model.parameters(), GRAD_CLIP_NORM)
            scaler.step(optimizer)
            scaler.update()
            scheduler.step()
            running += float(loss.detach()) * len(idx)
            n_seen += len(idx)
            if step % 10 == 0:
                bar.set_postfix(nll=f"{running / n_seen:.3f}")
        bar.close()
        record = {"epoch": epoch + 1, "train_nll": running / max(n_seen, 1), "lr": optimizer.param_groups[0]["lr"]}
        if len(va_idx):
            record.update(evaluate(model, planes_va, scalars_va, y_va, active, stats, names, input_config, dev, 2 * batch, amp))
        record["seconds"] = time.perf_counter() - t0
        history.append(record)
        result = checkpoint(epoch + 1, finished=(epoch + 1 == config.epochs))
        atomic_torch_save(result, out)
        line = "  ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in record.items())
        log.info("%s", line)
        if echo is not None:
            echo(line)
    return load_checkpoint(out) if start_epoch >= last else result


def anchored_columns(names: list[str]) -> list[tuple[int, int]]:
    """``(column, axis)`` of every axis-origin column (``j{j}.origin.{x,y,z}``): these are
    predicted relative to the image anchor's coordinate ``axis`` (0, 1, 2 = x, y, z)."""
    out = []
    for c, n in enumerate(names):
        head, _, rest = n.partition(".")
        kind, _, comp = rest.partition(".")
        if kind == "origin" and comp in ("x", "y", "z"):
            out.append((c, "xyz".index(comp)))
    return out


def shift_anchored(y: np.ndarray, anchor_m: np.ndarray, anchored, sign: float) -> np.ndarray:
    """``y[..., c] + sign * anchor[:, axis]`` for each anchored ``(c, axis)``; ``y`` (N, ..., D)
    in label units, ``anchor_m`` (N, 3).  ``sign = -1`` makes targets anchor-relative,
    ``+1`` restores camera-frame labels."""
    out = np.array(y, dtype=np.float64, copy=True)
    a = np.asarray(anchor_m, np.float64)
    for c, axis in anchored:
        out[..., c] += sign * a[:, axis].reshape((-1,) + (1,) * (out.ndim - 2))
    return out


def active_columns(stats) -> np.ndarray:
    """Indices of the target columns the mixture models: those that vary in the training
    data.  A column whose standard deviation is at the NormStats floor (constant up to label
    precision, e.g. the x/y components of a vertical hinge axis or the chirality of a
    one-sided class) is not modelled: its normalised estimate is 0 (the training value) and
    its scale 1 (the floor, in label units).  Modelling it would let the likelihood grow
    without bound as its scales shrink, and its huge gradients would swamp the others."""
    std = np.asarray(stats.std, np.float64)
    return np.nonzero(std > stats.std_floor * CONSTANT_COLUMN_TOLERANCE)[0]


def expand_active(x: np.ndarray, active: np.ndarray, dim: int, fill: float) -> np.ndarray:
    """Arrays (..., len(active)) over the modelled columns -> (..., dim), other columns ``fill``."""
    out = np.full(x.shape[:-1] + (dim,), fill, dtype=np.float64)
    out[..., active] = x
    return out


def _plain(obj):
    """Convert numpy values in nested dicts/lists to plain Python (checkpoints load with weights_only)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
