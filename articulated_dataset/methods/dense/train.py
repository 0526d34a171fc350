"""Training of the dense estimator (``artdata train --model dense``).

* Data: the class's training split, every image held in memory at the model resolution
  (:func:`~articulated_dataset.methods.dense.data.load_dense_split`), per-pixel part labels at
  the output resolution, and the labels (axis origin, axis frame, q, part offset, geometry).
* Validation: a held-out part of the TRAINING split chosen by object (the MDN's
  :func:`~articulated_dataset.methods.mdn.data.split_by_object`); the test split is never read.
  After the last epoch the geometric refinement (:mod:`articulated_dataset.methods.dense.refine`) is
  chosen and the uncertainty calibration (:mod:`articulated_dataset.methods.dense.predict`) fitted on
  the validation objects (:func:`~articulated_dataset.methods.dense.predict.fit_inference`).
  With ``--noise`` every validation image passes through the noise model, the same draw every
  epoch and in a refit (:func:`noisy_validation`): the errors, the refinement choice and the
  calibration are those of the sensor the model is trained for.
* Loss, per valid output pixel ``i`` (weighted by its valid fraction) and image:
  ``CE(seg) + 0.5 huber(|v_i - o| / 5 cm) + |r6_i - r6| / ROT_SCALE + |q_i - q| / s_q
  + |po_i - po| / 10 cm + |g_i - g| / 10 cm + BCE(chirality)``, plus the same terms on the
  image's softmax-weighted estimate (:func:`~articulated_dataset.methods.dense.aggregate.weighted_mean`),
  where ``r6 = (axis, frame x axis)``, ``s_q`` the training std of q per joint.
* Optimisation: AdamW with a one-cycle schedule, gradient clipping.  Checkpoints are written
  atomically every :data:`CHECKPOINT_EVERY_STEPS` steps and after every epoch with the
  optimizer, schedule and history; the batch order of epoch ``e`` depends only on
  ``(seed, e)``, so a resumed run continues exactly where it stopped
  (:mod:`articulated_dataset.methods.dense.checkpoint` reads them back).
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.dense.checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    DenseCheckpoint,
    build_dense_model,
    build_inference_model,
    load_dense_checkpoint,
)
from articulated_dataset.methods.dense.data import (
    DenseData,
    concat_dense_data,
    load_dense_split,
    mixture_order,
    split_object_indices,
)

if TYPE_CHECKING:
    import torch

    from articulated_dataset.methods.dense.predict import CalibrationRecord

log = logging.getLogger(__name__)

#: A calibration-only refit (:func:`refit_inference`) fits the modes' scales as before and compares
#: them with the checkpoint's: the same validation objects give them again to within this median
#: relative difference over the columns' factors and floors (float rounding moves them by
#: 0.1-0.4%, though a floor in a flat stretch of its likelihood may jump by 30%);
#: other objects move most floors by several per cent (each is a fraction of the residuals' median).
SAME_CALIBRATION_TOLERANCE = 0.01

#: Scales of the loss terms (see the module docstring).
ORIGIN_SCALE_M = 0.05
ROT_SCALE = 0.5
OFFSET_SCALE_M = 0.1
GEOMETRY_SCALE_M = 0.1
ORIGIN_WEIGHT = 0.5
#: Floor of the q normalisation (rad or m).
MIN_Q_SCALE = 1e-3
WEIGHT_DECAY = 1e-4
GRAD_CLIP_NORM = 10.0
WARMUP_FRACTION = 0.1
MIN_SCHEDULE_STEPS = 4
CHECKPOINT_EVERY_STEPS = 200
EPOCH_SEED_STRIDE = 1_000_003
#: The epoch key of the validation images' noise (``--noise``): one fixed draw per image, which
#: no training epoch reaches (epochs count from 0).
VALIDATION_NOISE_EPOCH = 2**31 - 1


@dataclass(frozen=True)
class DenseTrainConfig:
    """Training settings of a dense model (``artdata train --model dense``; stored in checkpoints)."""
    class_name: str
    epochs: int = 2
    batch_size: int = 64
    lr: float = 3e-3
    width: int = 16
    val_fraction: float = 0.05
    max_objects: int | None = None
    seed: int = 0
    #: Start from this checkpoint's weights (same class and architecture) with a fresh schedule:
    #: how a finished training is continued for more steps (``--init-from``).
    init_from: str | None = None
    #: Multiplies both axis-origin loss terms (per pixel and per image; ``--origin-weight``): more
    #: than 1 trades the rotation and q votes, which the geometric refinement measures anyway,
    #: for the axis position, which it can only partly measure.
    origin_weight: float = 1.0
    #: A depth-noise model of :mod:`articulated_dataset.core.noise` (``--noise``, e.g. ``kinect2``)
    #: applied to ``noise_fraction`` of the images, drawn afresh every epoch (each image's generator
    #: fixed by the seed, epoch and image, as the loaders' transforms draw: a resumed run draws the
    #: same): the network then sees a sensor's depth as well as renders.  The validation images
    #: all pass through it (:func:`noisy_validation`).  None: renders only.
    noise: str | None = None
    noise_fraction: float = 0.5
    #: Prompt kinds (:data:`~articulated_dataset.methods.prompts.PROMPT_KINDS`, ``--prompts``): in
    #: a split with a scene or occluders each image's object is segmented from a simulated prompt
    #: of these kinds in turn (by sample id), as a robot's images will be at prediction
    #: (``predict --prompt``); an isolated split keeps every pixel.  None: every pixel everywhere.
    prompts: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "width"):
            v = getattr(self, name)
            if not isinstance(v, int) or v <= 0:
                raise UserError(f"--{name.replace('_', '-')} must be a positive integer, got {v!r}")
        from articulated_dataset.methods.mdn.config import MAX_EPOCHS, MAX_LR, MAX_SEED

        if self.epochs > MAX_EPOCHS:
            raise UserError(f"{option('epochs')} must be at most {MAX_EPOCHS:,}, got {self.epochs}")
        from articulated_dataset.methods.dense.checkpoint import MAX_NETWORK_WIDTH

        if self.width > MAX_NETWORK_WIDTH:  # a checkpoint no reader would load (load_dense_checkpoint)
            raise UserError(f"{option('width')} must be at most {MAX_NETWORK_WIDTH}, got {self.width}")
        if not (math.isfinite(self.lr) and 0 < self.lr <= MAX_LR):
            raise UserError(f"{option('lr')} must be a number in (0, {MAX_LR:g}], got {self.lr}")
        if not isinstance(self.seed, int) or not 0 <= self.seed <= MAX_SEED:
            raise UserError(f"{option('seed')} must be a whole number in [0, {MAX_SEED}], got {self.seed!r}")
        if not (math.isfinite(self.origin_weight) and self.origin_weight > 0):
            raise UserError(f"{option('origin_weight')} must be a positive finite number, got {self.origin_weight}")
        if not (0.0 <= self.val_fraction < 1.0):
            raise UserError(f"{option('val_fraction')} must be in [0, 1), got {self.val_fraction}")
        if self.max_objects is not None and self.max_objects <= 0:
            raise UserError(f"{option('max_objects')} must be positive, got {self.max_objects}")
        if self.noise is not None:
            from articulated_dataset.core.noise import get_noise_model

            get_noise_model(self.noise)  # an unknown name: a UserError listing the models
        if not (0.0 < self.noise_fraction <= 1.0):
            raise UserError(f"{option('noise_fraction')} must be in (0, 1], got {self.noise_fraction}")
        if self.prompts is not None:
            from articulated_dataset.methods.prompts import PROMPT_KINDS

            kinds = tuple(self.prompts)
            if not kinds or any(k not in PROMPT_KINDS for k in kinds):
                raise UserError(f"{option('prompts')} must be kinds of {', '.join(PROMPT_KINDS)}, got "
                                f"{','.join(map(str, kinds))!r}")
            object.__setattr__(self, "prompts", kinds)  # a checkpoint's list read back: the same tuple

    def to_dict(self) -> dict:
        """The settings as a dict (stored in checkpoints)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "DenseTrainConfig":
        """The settings from a checkpoint's dict (keys this version does not know are ignored, missing ones take
        their defaults)."""
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})


def dense_loss(model, out, inputs: dict, data: DenseData, idx: np.ndarray, q_scale,
               origin_weight: float = 1.0) -> tuple[torch.Tensor, dict]:
    """The training loss of one batch (module docstring; ``origin_weight`` multiplies both origin
    terms) and its parts as floats."""
    import torch
    from torch.nn import functional as F

    from articulated_dataset.methods.dense.aggregate import weighted_mean

    parts = model.split(out)
    J = model.config.n_joints
    w_pix = inputs["weight_out"]
    valid = w_pix > 0
    norm = w_pix.sum().clamp_min(1.0)
    dev = out.device
    lab = torch.from_numpy(data.labels_out[idx]).to(dev).long()  # type: ignore[index]  # training data has labels
    o_t, r_t, q_t, po_t, g_t = (torch.from_numpy(a[idx]).to(dev) for a in  # type: ignore[index]  # (labels: as above)
                                (data.origin, data.rot6, data.q, data.part_offset, data.geometry))

    def pix(x):  # (B, J, H, W) or (B, H, W) per-pixel loss -> weighted mean
        if x.dim() == 4:
            return (x * w_pix[:, None]).sum() / (norm * x.shape[1])
        return (x * w_pix).sum() / norm

    ce = F.cross_entropy(parts["seg"], (lab - 1).clamp_min(0), reduction="none")
    votes = inputs["points_out"][:, None] + parts["offset"]
    dist = (votes - o_t[..., None, None]).norm(dim=2) / ORIGIN_SCALE_M
    l_o = pix(F.smooth_l1_loss(dist, torch.zeros_like(dist), reduction="none"))
    l_r = pix((parts["rot6"] - r_t[..., None, None]).abs().sum(2)) / ROT_SCALE
    qs = q_scale.view(1, J, 1, 1)
    l_q = pix(((parts["q"] - q_t[..., None, None]) / qs).abs())
    l_po = pix((parts["part_offset"] - po_t[..., None, None]).abs().sum(2)) / OFFSET_SCALE_M
    g = parts["geometry"]
    l_g = pix((g[:, :3] - g_t[:, :3, None, None]).abs().sum(1)) / GEOMETRY_SCALE_M
    chir_t = g_t[:, 3:4, None].expand_as(g[:, 3])
    l_c = pix(F.binary_cross_entropy_with_logits(g[:, 3], chir_t.nan_to_num(0.0), reduction="none"))
    img = weighted_mean(parts, inputs["points_out"], valid)
    li_o = ((img["origin"] - o_t).norm(dim=-1) / ORIGIN_SCALE_M).mean()
    li_r = (img["rot6"] - r_t).abs().sum(-1).mean() / ROT_SCALE
    li_q = ((img["q"] - q_t) / q_scale).abs().mean()
    li_po = (img["part_offset"] - po_t).abs().sum(-1).mean() / OFFSET_SCALE_M
    li_g = (img["geometry"][:, :3] - g_t[:, :3]).abs().sum(-1).mean() / GEOMETRY_SCALE_M
    total = (pix(ce) + origin_weight * (ORIGIN_WEIGHT * l_o + li_o) + l_r + l_q + l_po + l_g + l_c
             + li_r + li_q + li_po + li_g)
    stats = {"loss": float(total.detach()), "seg": float(pix(ce).detach()),
             "origin_cm": float((img["origin"] - o_t).norm(dim=-1).mean().detach()) * 100}
    return total, stats


def noisy_depth(depth_m: np.ndarray, K: np.ndarray, images: np.ndarray, noise: str, fraction: float, *, seed: int,
                epoch: int) -> np.ndarray:
    """A batch's depth images (B, H, W) m with intrinsics (B, 3, 3), of the split's images
    ``images`` (B,), each passed with probability ``fraction`` through the noise model ``noise``
    (:class:`~articulated_dataset.training.transforms.SensorNoise`), with the generator the loaders give
    that image in that epoch (:func:`~articulated_dataset.training.transforms.sample_rng`); the others as
    they are.  A new array."""
    from articulated_dataset.training.transforms import SensorNoise, sample_rng

    transform = SensorNoise(noise)
    out = np.array(depth_m, np.float32, copy=True)
    for b, image in enumerate(images):
        rng = sample_rng(seed, epoch, int(image))
        if rng.random() < fraction:
            out[b] = transform({"depth": out[b], "K": K[b]}, rng)["depth"]
    return out


def noisy_validation(data_: DenseData, va_idx: np.ndarray, noise: str, *, seed: int) -> tuple[DenseData, np.ndarray]:
    """The validation images ``va_idx`` of ``data_`` as a :class:`DenseData` of their own (and
    its indices, ``0..n-1``), every image's depth passed through the noise model ``noise``
    with the generator :func:`~articulated_dataset.training.transforms.sample_rng` gives it for
    ``(seed, VALIDATION_NOISE_EPOCH, sample_id)``: the same noise in every epoch's validation,
    in the fit after training and in a refit (which reads only these objects)."""
    from dataclasses import fields, replace

    from articulated_dataset.methods.dense.data import quantise_depth

    va_idx = np.asarray(va_idx, np.int64)
    sub = replace(data_, **{f.name: (None if getattr(data_, f.name) is None else getattr(data_, f.name)[va_idx])  # type: ignore[arg-type]  # field by field
                            for f in fields(data_)})
    depth = noisy_depth(sub.depth(np.arange(len(va_idx))).numpy(), sub.K, sub.sample_id, noise, 1.0, seed=seed,
                        epoch=VALIDATION_NOISE_EPOCH)
    return replace(sub, depth_q=quantise_depth(depth)), np.arange(len(va_idx))


def atomic_save(obj: Mapping[str, Any], path: Path) -> None:
    """Write ``obj`` with ``torch.save`` to ``path`` atomically
    (:func:`~articulated_dataset.methods.mdn.checkpoint.atomic_torch_save`)."""
    from articulated_dataset.methods.mdn.checkpoint import atomic_torch_save

    atomic_torch_save(obj, path)


def train_dense(data: str | Path | list, out: str | Path, config: DenseTrainConfig, *, resume: bool = False,
                progress: bool = True, echo=None, stop_after_steps: int | None = None, device: str | None = "cpu",
                fit: bool = True, mix_weights: list[float] | None = None) -> DenseCheckpoint:
    """Train (or resume) the dense estimator of ``config.class_name`` on the split at ``data``,
    or on a mixture of the splits of a list ``data`` (:func:`check_mixture`): each split holds
    out its own validation objects, each batch draws its images from the splits in proportion
    to ``mix_weights`` (:func:`~.data.mixture_order`; None: to their sizes, one concatenated
    split), and the checkpoint's ``data["splits"]`` records every split's identity and weight.

    ``stop_after_steps`` stops early (checkpointed, resumable) after that many steps in total.
    ``device``: where the training steps run (``cpu``, ``cuda``, ``cuda:N`` or ``auto``); the
    per-epoch validation and the inference fit always run on the CPU, as inference does, and the
    checkpoint holds CPU tensors.  ``fit=False`` leaves the refinement choice and calibration out
    of the finished checkpoint (:func:`refit_inference` adds them later, on another machine).
    Returns the last checkpoint.
    """
    import torch
    from tqdm.auto import tqdm

    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.methods.dense.features import make_inputs
    from articulated_dataset.methods.dense.model import DenseConfig, DenseNet, count_parameters
    from articulated_dataset.methods.dense.predict import fit_inference, predict_arrays, quick_errors
    from articulated_dataset.methods.mdn.checkpoint import prepare_training_output, state_problem
    from articulated_dataset.methods.mdn.data import resolve_split_dir, split_by_object, split_identity
    from articulated_dataset.methods.mdn.train import resolve_device

    out = Path(out)
    dev = resolve_device(device)
    obj_class = get_class(config.class_name)
    split_dirs = [resolve_split_dir(d) for d in (data if isinstance(data, (list, tuple)) else [data])]
    split_dir = split_dirs[0]
    mixture = len(split_dirs) > 1
    weights = check_mixture(split_dirs, obj_class.name, mix_weights)
    ckpt = prepare_training_output(split_dir, obj_class.name, out, resume=resume, load=load_dense_checkpoint,
                                   config=config, example_name="dense.pt")
    identities = [split_identity(d) for d in split_dirs]  # read once: every checkpoint records them
    mixture_record = [{"split_dir": str(d), "split": ident, "weight": None if weights is None else float(w)}
                      for d, ident, w in zip(split_dirs, identities, weights if weights is not None
                                             else [None] * len(split_dirs))]
    if ckpt is not None:
        check_same_mixture(ckpt, out, mixture_record)
    if ckpt is not None and ckpt.get("finished"):
        log.info("%s: training already finished", out)
        return ckpt
    from articulated_dataset.core.safeio import check_can_create, ensure_dir

    ensure_dir(out.parent)  # a parent that is a file, /proc: one line now, not after the training
    check_can_create(out)

    J = obj_class.n_joints
    model_config = DenseConfig(n_joints=J, width=config.width)
    hw = (model_config.height_px, model_config.width_px)
    t_load = time.perf_counter()
    from articulated_dataset.methods.inputs import split_has_context
    from articulated_dataset.methods.prompts import class_extent_m

    extent_m = class_extent_m(obj_class.name)
    loaded = [load_dense_split(d, J, hw, max_objects=config.max_objects, progress=progress,
                               prompt=config.prompts if config.prompts and split_has_context(d) else None,
                               max_extent_m=extent_m) for d in split_dirs]
    data_ = loaded[0] if not mixture else concat_dense_data(loaded)
    source = np.concatenate([np.full(len(p.sample_id), s) for s, p in enumerate(loaded)])  # each image's split
    t_load = time.perf_counter() - t_load
    for name in ("origin", "rot6", "q", "part_offset", "geometry"):  # every label the losses read
        bad = ~np.isfinite(getattr(data_, name)).reshape(len(data_.sample_id), -1).all(1)
        if bad.any():  # (else the first step's loss is NaN, reported as a learning rate too high)
            where = split_dirs[int(source[np.argmax(bad)])]  # the split of the first such image
            raise UserError(f"{where}: {int(bad.sum())} image(s) have NaN or infinite '{name}' labels (a real split "
                            f"without full ground truth, or a damaged one: 'artdata verify'); training needs every label")
    val_mask = np.zeros(len(source), bool)
    for s in range(len(split_dirs)):  # each split holds out its own validation objects
        at = np.nonzero(source == s)[0]
        val_mask[at] = split_by_object(data_.object_index[at], config.val_fraction, config.seed)[1]
    tr_idx, va_idx = np.nonzero(~val_mask)[0], np.nonzero(val_mask)[0]
    tr_pools = [tr_idx[source[tr_idx] == s] for s in range(len(split_dirs))]
    for d, pool in zip(split_dirs, tr_pools):
        if mixture and len(pool) == 0:
            raise UserError(f"{d}: no training images after holding out validation objects")
    val_data, val_idx = (data_, va_idx) if config.noise is None or not len(va_idx) else \
        noisy_validation(data_, va_idx, config.noise, seed=config.seed)
    n_train = len(tr_idx)
    batch = min(config.batch_size, n_train)
    if n_train < 2:
        raise UserError(f"{split_dir}: only {n_train} training image(s) after holding out validation objects")
    q_scale = np.maximum(data_.q[tr_idx].std(0), MIN_Q_SCALE) if ckpt is None else np.asarray(ckpt["q_scale"], np.float64)  # type: ignore[index]  # training data has labels
    q_scale_t = torch.tensor(q_scale, dtype=torch.float32)

    torch.manual_seed(config.seed)
    model = DenseNet(model_config)
    if config.init_from is not None and ckpt is None:
        init = load_dense_checkpoint(config.init_from)
        if init["class_name"] != obj_class.name:
            raise UserError(f"{option('init_from')} {config.init_from}: a {init['class_name']!r} model; this "
                            f"training is of {obj_class.name!r} (scripts/transplant_dense.py moves weights between "
                            "classes)")
        if DenseConfig.from_dict(init["model_config"]) != model_config:
            raise UserError(f"{option('init_from')} {config.init_from}: a model of another configuration "
                            f"({init['model_config']}); expected {model_config.to_dict()}")
        model.load_state_dict(build_dense_model(init).state_dict())
        if "q_scale" in init:
            q_scale = np.asarray(init["q_scale"], np.float64)
            q_scale_t = torch.tensor(q_scale, dtype=torch.float32)
    model.to(dev)
    q_scale_t = q_scale_t.to(dev)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=WEIGHT_DECAY)
    steps_per_epoch = n_train // batch
    total_steps = steps_per_epoch * config.epochs
    # the warm-up spans at least 2 steps and the schedule at least MIN_SCHEDULE_STEPS (OneCycleLR divides
    # by each phase's length: a run of a few steps would otherwise fail)
    schedule_steps = max(total_steps, MIN_SCHEDULE_STEPS)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=config.lr, total_steps=schedule_steps,
                                                    pct_start=min(0.5, max(WARMUP_FRACTION, 2.0 / schedule_steps)))
    history: list[dict] = []
    step = 0
    cpu_seconds = 0.0
    if ckpt is not None:
        from articulated_dataset.methods.mdn.checkpoint import restore_training_state

        try:
            history = restore_training_state(ckpt, model, optimizer, scheduler)
        except UserError as exc:  # name the file
            raise UserError(f"{out}: {exc.message}") from None
        step = int(ckpt["step"])
        if step > total_steps:
            raise UserError(f"{option('resume')}: {out} is at step {step} of a training of {total_steps} steps; not "
                            "resumable")
        try:
            cpu_seconds = float(ckpt.get("cpu_seconds", 0.0))
        except (TypeError, ValueError):
            raise UserError(f"{out}: checkpoint field 'cpu_seconds' is not a number") from None
    log.info("%s: %d train / %d val images, %s parameters, device %s", obj_class.name, n_train, len(va_idx),
             f"{count_parameters(model):,}", dev)
    identity = identities[0]
    generated = generation_of(identity)
    machine = machine_description(dev)

    def checkpoint(finished: bool, calibration: CalibrationRecord | None = None) -> DenseCheckpoint:
        return {
            "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "class_name": obj_class.name,
            "joint_types": list(obj_class.joint_types), "model_config": model_config.to_dict(),
            "train_config": config.to_dict(), "q_scale": [float(v) for v in q_scale],
            "data": {"split_dir": str(split_dir), "split": identity, "n_train_images": int(n_train),
                     "n_val_images": int(len(va_idx)),
                     "n_objects": int(len(np.unique(data_.object_index))), "generated": generated,
                     **({"splits": [{**m, "n_train_images": int(len(pool)),
                                     "n_val_images": int((source[va_idx] == s).sum())}
                                    for s, (m, pool) in enumerate(zip(mixture_record, tr_pools))]}
                        if mixture else {})},
            "machine": machine, "device": dev.type,
            "step": step, "total_steps": total_steps, "finished": finished, "history": history,
            "cpu_seconds": cpu_seconds, "calibration": calibration,
            "model_state": _on_cpu(model.state_dict()), "optimizer_state": _on_cpu(optimizer.state_dict()),
            "scheduler_state": scheduler.state_dict(), "rng_state": torch.get_rng_state(),
        }

    def validate() -> dict:
        if not len(va_idx):
            return {}
        arrays = predict_arrays(inference_copy(model), val_data, val_idx, joint_types=list(obj_class.joint_types),
                                calibration=None)
        together = quick_errors(arrays, val_data, val_idx, list(obj_class.joint_types))
        if not mixture:
            return together
        per_split = {}  # the same predictions, scored split by split ("s0_...", "s1_...")
        rows = np.arange(len(val_idx))
        for s in range(len(split_dirs)):
            mine = source[va_idx] == s
            if mine.any():
                sub = {k: (v[rows[mine]] if isinstance(v, np.ndarray) and len(v) == len(rows) else v)
                       for k, v in arrays.items()}
                per_split.update({f"s{s}_{k}": v for k, v in
                                  quick_errors(sub, val_data, val_idx[mine], list(obj_class.joint_types)).items()})
        return {**together, **per_split}

    end = total_steps if stop_after_steps is None else min(total_steps, stop_after_steps)
    bar = tqdm(total=total_steps, initial=step, desc=f"training {obj_class.name}", unit="step", disable=not progress)
    running: dict[str, float] = {}
    n_run = 0
    cpu0 = time.process_time()
    while step < end:
        epoch, pos = divmod(step, steps_per_epoch)
        gen = np.random.default_rng(config.seed * EPOCH_SEED_STRIDE + epoch)
        order = gen.permutation(tr_idx) if weights is None else \
            mixture_order(tr_pools, weights, steps_per_epoch * batch, gen)
        model.train()
        while pos < steps_per_epoch and step < end:
            idx = np.sort(order[pos * batch : (pos + 1) * batch])
            depth = data_.depth(idx)
            if config.noise is not None:  # each image's own generator: the same after a resume
                depth = torch.from_numpy(noisy_depth(depth.numpy(), data_.K[idx], idx, config.noise, config.noise_fraction,
                                                     seed=config.seed, epoch=epoch))
            inputs = make_inputs(depth.to(dev), torch.from_numpy(data_.K[idx]).to(dev))
            out_ = model(inputs["x"])
            loss, st = dense_loss(model, out_, inputs, data_, idx, q_scale_t, config.origin_weight)
            if not torch.isfinite(loss):
                raise UserError(f"non-finite training loss at step {step}; {out} keeps the last checkpoint; lower "
                                f"{option('lr')}")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), GRAD_CLIP_NORM)
            optimizer.step()
            scheduler.step()
            step += 1
            pos += 1
            for k, v in st.items():
                running[k] = running.get(k, 0.0) + v
            n_run += 1
            bar.update(1)
            if step % 10 == 0:
                bar.set_postfix({k: f"{v / n_run:.3g}" for k, v in running.items()})
            if step % CHECKPOINT_EVERY_STEPS == 0 or pos == steps_per_epoch or step == end:
                # never replace the last checkpoint with diverged weights (a --resume would refuse them)
                if state_problem(model.state_dict()) is not None:
                    raise UserError(f"training diverged by step {step} (non-finite weights); {out} keeps the last "
                                    f"checkpoint; lower {option('lr')}")
                cpu_seconds += time.process_time() - cpu0
                cpu0 = time.process_time()
                if pos == steps_per_epoch or step == total_steps:
                    record = {"epoch": epoch + 1, "step": step, "cpu_seconds": round(cpu_seconds, 1),
                              **{f"train_{k}": round(v / max(n_run, 1), 4) for k, v in running.items()},
                              **{f"val_{k}": round(v, 4) for k, v in validate().items()}}
                    history.append(record)
                    running, n_run = {}, 0
                    line = "  ".join(f"{k} {v}" for k, v in record.items())
                    log.info("%s", line)
                    if echo is not None:
                        echo(line)
                    model.train()
                atomic_save(checkpoint(finished=False), out)
    bar.close()
    if step < total_steps:
        return checkpoint(finished=False)
    result = checkpoint(finished=True)
    if fit and not len(va_idx):
        log.warning("%s: no validation objects (--val-fraction %g of the split's objects): the checkpoint gets no "
                    "refinement or uncertainty calibration, and its estimates are the plain votes", out,
                    config.val_fraction)
    if fit and len(va_idx):  # refinement choice and uncertainty calibration on the validation objects
        # (the fit's keys and types are the checkpoint's, its calibration and refinement never None)
        result.update(fit_inference(inference_copy(model), val_data, val_idx, list(obj_class.joint_types),  # type: ignore[typeddict-item]
                                    mirror_joints=obj_class.mirror_joints))
    result["load_seconds"] = round(t_load, 1)
    atomic_save(result, out)
    return result


def check_mixture(split_dirs: list[Path], class_name: str, mix_weights: list[float] | None) -> np.ndarray | None:
    """The splits of a mixture checked (each of ``class_name`` and generated, each given once) and
    their sampling weights as an array (None: sample in proportion to the splits' sizes); a
    mismatch is one line naming the split."""
    from articulated_dataset.format import Split

    seen = set()
    for d in split_dirs:
        key = Path(d).resolve()
        if key in seen:
            raise UserError(f"{d}: given twice; give each split once and weight it with {option('mix_weights')}")
        seen.add(key)
        split = Split(d)
        if split.class_name != class_name:
            raise UserError(f"{d}: holds class {split.class_name!r}, not {class_name!r} ({option('class_name')})")
        if split.is_real:
            raise UserError(f"{d} holds ingested real captures (labels NaN where not given); train on generated splits")
    if mix_weights is None:
        return None
    if len(split_dirs) < 2:
        raise UserError(f"{option('mix_weights')} weights several splits; give two split folders or more")
    w = np.asarray([float(v) for v in mix_weights], np.float64)
    if len(w) != len(split_dirs):
        raise UserError(f"{option('mix_weights')} has {len(w)} weight(s) for {len(split_dirs)} split(s); give one per "
                        "split")
    if not (np.isfinite(w).all() and (w > 0).all()):
        raise UserError(f"{option('mix_weights')} must be positive finite numbers, got {','.join(f'{v:g}' for v in w)}")
    return w


def check_same_mixture(ckpt: Mapping[str, Any], out: Path, current: list[dict]) -> None:
    """``--resume``: the checkpoint was trained on the same splits (identities, in order) with the
    same weights as ``current``; else one line naming the first difference."""
    from articulated_dataset.methods.mdn.checkpoint import data_record

    data = data_record(ckpt, out)
    recorded = data.get("splits")
    if recorded is None:  # one split: what a single-split checkpoint records
        recorded = [{"split": data.get("split"), "weight": None}]
    if not isinstance(recorded, list) or not all(isinstance(r, dict) for r in recorded):
        raise UserError(f"{out}: checkpoint field 'data.splits' is not a list of mappings (corrupt checkpoint)")
    if len(recorded) != len(current):
        raise UserError(f"{option('resume')}: {out} was trained on {len(recorded)} split(s), not {len(current)}; "
                        f"give the same splits and {option('mix_weights')}")
    for i, (r, c) in enumerate(zip(recorded, current)):
        if r.get("split") is not None and c["split"] is not None and r.get("split") != c["split"]:
            raise UserError(f"{option('resume')}: split {i + 1} of {out} was {str(r.get('split'))[:160]}, not "
                            f"{c['split_dir']} ({c['split']}); give the same splits in the same order")
        if r.get("weight") != c["weight"]:
            raise UserError(f"{option('resume')}: split {i + 1} ({c['split_dir']}) was weighted {r.get('weight')}, "
                            f"not {c['weight']}; repeat the original {option('mix_weights')}")


def inference_copy(model):
    """The CPU inference copy (:meth:`~.model.DenseNet.folded`) of a network in training, wherever it
    trains: moved to the CPU before folding, so a GPU-trained network's copy gets the CPU's
    prepacked convolutions too (the validation and the inference fit run on the CPU).  A CPU network
    is copied once (by ``folded``); a GPU network is first copied to the CPU (``deepcopy`` then
    ``cpu()``, which moves the copy in place)."""
    import copy

    on_cpu = all(t.device.type == "cpu" for t in itertools.chain(model.parameters(), model.buffers()))
    return (model if on_cpu else copy.deepcopy(model).cpu()).folded()


def split_generation(split_dir: Path) -> dict | None:
    """The generation settings of a split (class, seed, objects): its identity
    (:func:`~articulated_dataset.methods.mdn.data.split_identity`, read from its manifest) without
    the split's name; how the training data of a checkpoint is made again once the folder is gone.
    None for a split without them (an ingested one, an unreadable manifest)."""
    from articulated_dataset.methods.mdn.data import split_identity

    return generation_of(split_identity(split_dir))


def generation_of(identity: dict | None) -> dict | None:
    """A split's generation settings (:func:`split_generation`) from its identity (None: none)."""
    return None if identity is None else {k: identity[k] for k in ("class_name", "seed", "n_objects")}


def machine_description(dev) -> str:
    """One line naming where training ran: the CPU's cores, the GPU if used, PyTorch's version."""
    import os
    import platform

    import torch

    text = f"{platform.machine()} CPU, {os.cpu_count()} cores"
    if dev.type == "cuda":
        text += f", {torch.cuda.get_device_name(dev)}"
    return f"{text}, PyTorch {torch.__version__}"


def _on_cpu(state):
    """A state dict (nested dicts and lists of tensors) with every tensor on the CPU."""
    import torch

    if isinstance(state, torch.Tensor):
        return state.detach().cpu()
    if isinstance(state, dict):
        return {k: _on_cpu(v) for k, v in state.items()}
    if isinstance(state, (list, tuple)):
        return type(state)(_on_cpu(v) for v in state)
    return state


def refit_inference(checkpoint: str | Path, data: str | Path, out: str | Path, *, progress: bool = True,
                    clean: bool = False, calibration_only: bool = False) -> dict:
    """Refit what inference needs beyond the weights (refinement choice, calibration) of a finished
    dense checkpoint on the validation objects of its training split ``data`` (the same objects
    training held out: its ``val_fraction``, ``seed`` and ``max_objects``), and write the result
    to ``out`` atomically (through the noise model when it was trained with ``--noise``, as
    training fits, unless ``clean``: a model trained with noise fitted for noise-free depth).
    For checkpoints trained before a refinement existed, or a refinement version.
    ``calibration_only``: keep the checkpoint's refinement (and so its point estimates and
    modes) and refit only the calibration (:func:`~.predict.fitted_calibration`: for
    checkpoints fitted before the outlier component)."""
    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.core.safeio import check_can_create
    from articulated_dataset.methods.dense.predict import (
        PREDICT_BATCH,
        _refined_images,
        fit_calibration,
        fit_inference,
        fitted_calibration,
        modes_to_arrays,
    )
    from articulated_dataset.methods.dense.refine import as_refinement
    from articulated_dataset.methods.mdn.checkpoint import data_record
    from articulated_dataset.methods.mdn.data import resolve_split_dir, split_by_object, split_class

    ckpt = load_dense_checkpoint(checkpoint)
    if not ckpt.get("finished"):
        raise UserError(f"{checkpoint}: training is not finished (resume it first)")
    check_can_create(out)  # a folder, /proc, a parent that is a file: one line before the fit, not after it
    split_dir = resolve_split_dir(data)
    if split_class(split_dir) != ckpt["class_name"]:
        raise UserError(f"{split_dir}: holds class {split_class(split_dir)!r}, the checkpoint {ckpt['class_name']!r}")
    if data_record(ckpt, checkpoint).get("splits") is not None:
        raise UserError(f"{checkpoint}: trained on a mixture of splits; a refit reads one split's validation objects")
    config = DenseTrainConfig.from_dict(ckpt["train_config"])
    recorded, generated = data_record(ckpt, checkpoint).get("generated"), split_generation(split_dir)
    if recorded is not None and generated is not None and recorded != generated:
        raise UserError(f"{split_dir}: generated as {generated}, but the checkpoint was trained on a split generated as "
                        f"{recorded}: its validation objects are not there")
    model = build_inference_model(ckpt)
    c = model.config
    # the objects training held out (split_by_object depends on the set of objects only), then only their images
    objects = np.unique(split_object_indices(split_dir, config.max_objects))
    _, val_mask = split_by_object(objects, config.val_fraction, config.seed)
    if not val_mask.any():
        raise UserError(f"{checkpoint}: trained without validation objects ({option('val_fraction')} 0): nothing to "
                        "fit on")
    data_ = load_dense_split(split_dir, c.n_joints, (c.height_px, c.width_px), max_objects=config.max_objects,
                             objects=objects[val_mask], progress=progress)
    va_idx = np.arange(len(data_.sample_id))
    noise = None if clean else config.noise
    if noise is not None:  # the validation images as training saw them (noisy_validation)
        data_, va_idx = noisy_validation(data_, va_idx, noise, seed=config.seed)
    from articulated_dataset.format import sha256_file

    result = dict(ckpt)
    if calibration_only:
        if ckpt.get("refinement") is None:
            raise UserError(f"{checkpoint}: has no refinement to keep; refit it whole (without "
                            f"{option('calibration_only')})")
        modes = _refined_images(model, data_, va_idx, list(ckpt["joint_types"]), as_refinement(ckpt["refinement"]),
                                PREDICT_BATCH, progress)
        plain = fit_calibration(modes_to_arrays(modes, data_.sample_id[va_idx], model, None), data_, va_idx)
        if ckpt.get("calibration") is not None:  # the same objects give the same scales as before, the outlier aside
            change = np.median([abs(a / b - 1.0) for key in ("spread_factor", "floor")
                                for a, b in zip(plain[key], ckpt["calibration"][key])])  # type: ignore[index]  # checked just above
            log.info("%s: the modes' scales fitted as before differ from the checkpoint's by %.2g (median relative "
                     "difference of the columns' factors and floors): %s", checkpoint, change,
                     "the same validation objects" if change < SAME_CALIBRATION_TOLERANCE else
                     "not the images the checkpoint was calibrated on (another split, or another refinement version)")
        result["calibration"] = fitted_calibration(modes, model, data_, va_idx, plain)
    else:
        result.update(fit_inference(model, data_, va_idx, list(ckpt["joint_types"]),
                                    mirror_joints=get_class(ckpt["class_name"]).mirror_joints, progress=progress))
    if recorded is None and generated is not None:  # checkpoints from before the record: the split named now
        result["data"] = {**data_record(ckpt, checkpoint), "generated": generated}
    result["refit_of"] = {"file": Path(checkpoint).name, "sha256": sha256_file(Path(checkpoint)),
                          "validation_noise": noise, **({"calibration_only": True} if calibration_only else {})}
    out = Path(out)
    from articulated_dataset.core.safeio import ensure_dir

    ensure_dir(out.parent)
    atomic_save(result, out)
    return result
