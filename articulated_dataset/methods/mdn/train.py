"""Training loop of the per-class mixture density network (``artdata train``).

* Data: one class's training split is read shard by shard, each depth image reduced to the
  model input (:mod:`articulated_dataset.methods.mdn.preprocess`) and held in memory as float16
  (2 bytes x 2 planes x h x w per image: 13 GB for 160,000 images at 192x108, 0.2 GB for
  16,000 at the small preset's 96x54); targets are encoded by
  :class:`articulated_dataset.training.targets.TargetLayout`, axis origins made relative to the
  image anchor (:func:`.data.anchored_columns`), and normalised with
  :class:`articulated_dataset.training.targets.NormStats` computed from the training images (the
  validation objects excluded).  Columns constant in training are not modelled
  (:func:`.data.active_columns`).
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

Settings are in :mod:`.config`, the data in :mod:`.data`, checkpoints in :mod:`.checkpoint`.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.safeio import check_memory
from articulated_dataset.methods.mdn.checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    atomic_torch_save,
    load_checkpoint,
    prepare_training_output,
    restore_training_state,
    state_problem,
)
from articulated_dataset.methods.mdn.config import TrainConfig, check_per_cpu
from articulated_dataset.methods.mdn.data import (
    active_columns,
    anchored_columns,
    expand_active,
    load_split,
    resolve_split_dir,
    shift_anchored,
    split_by_object,
    split_identity,
)

if TYPE_CHECKING:
    import torch

    from articulated_dataset.methods.mdn.checkpoint import MdnCheckpoint

log = logging.getLogger(__name__)


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
#: Offset mixing the seed and the epoch into the shuffling generator's seed.
EPOCH_SEED_STRIDE = 1_000_003
#: Bytes held per mixture-head parameter while training: float32 weight, gradient and
#: AdamW's two moments.
BYTES_PER_TRAINED_PARAMETER = 4 * 4


def resolve_device(device: str | None) -> torch.device:
    """The torch device for ``--device``: ``auto`` (or None, empty) picks CUDA when available, else the CPU; an
    unknown device, or CUDA without a GPU, is the user's mistake."""
    import torch

    if device in (None, "", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise UserError(f"unknown {option('device')} {device!r} (expected auto, cpu, cuda or cuda:N)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"{option('device')} {device}: no CUDA GPU is available")
    return dev


def configure_threads(n_threads: int | None = None) -> int:
    """Use every core this process may run on for intra-op parallelism (2 here) unless told
    otherwise; returns the number set.  Called once per process by the commands."""
    import torch

    if n_threads is None:
        from articulated_dataset.core.pool import usable_cpus

        n_threads = usable_cpus()
    check_per_cpu("threads", n_threads)
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

    from articulated_dataset.methods.mdn.loss import mean_of_best, mixture_log_prob
    from articulated_dataset.methods.mdn.preprocess import assemble_inputs

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
          progress: bool = True, stop_after_epoch: int | None = None, echo=None) -> MdnCheckpoint:
    """Train (or resume training) the class's MDN on the split at ``data``; checkpoint to ``out``.

    ``stop_after_epoch`` ends the run early after that many epochs in total (the
    checkpoint can be resumed).  ``echo`` (a callable taking one line) reports each epoch.
    Returns the checkpoint dict of the last epoch.
    """
    import contextlib

    import torch
    from tqdm.auto import tqdm

    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.methods.mdn.loss import mixture_nll
    from articulated_dataset.methods.mdn.model import MixtureDensityNetwork, count_parameters
    from articulated_dataset.methods.mdn.preprocess import assemble_inputs
    from articulated_dataset.training.targets import NormStats, TargetLayout

    out = Path(out)
    config = config.resolved()
    obj_class = get_class(config.class_name)
    split_dir = resolve_split_dir(data)
    ckpt = prepare_training_output(split_dir, obj_class.name, out, resume=resume, load=load_checkpoint, config=config,
                                   example_name="model.pt")
    if ckpt is not None and ckpt.get("finished"):
        log.info("%s: training already finished (%d epochs)", out, ckpt["epoch"])
        return ckpt
    from articulated_dataset.core.safeio import check_can_create, ensure_dir

    ensure_dir(out.parent)
    check_can_create(out)

    dev = resolve_device(device)
    layout = TargetLayout.for_class(obj_class.name)
    names = list(layout.names)
    input_config = config.input_config()
    prepared = load_split(split_dir, layout, input_config, max_objects=config.max_objects, progress=progress)
    bad = ~np.isfinite(prepared.targets).all(1)
    if bad.any():  # (else the loss is NaN from the first step, reported as a learning rate too high)
        raise UserError(f"{split_dir}: {int(bad.sum())} image(s) have NaN or infinite labels (a real split without full "
                        f"ground truth, or a damaged one: 'artdata verify'); training needs every label")
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
    prepared.planes = None  # type: ignore[assignment]  # the slices above are copies: free the full array
    if dev.type == "cuda":  # the whole training set fits in GPU memory at these sizes
        planes_tr, scalars_tr, y_tr = planes_tr.to(dev), scalars_tr.to(dev), y_tr.to(dev)
    n_train = len(tr_idx)
    if n_train < 2:
        raise UserError(f"{split_dir}: only {n_train} training image(s) after holding out validation objects")

    model_config = config.model_config(len(active))
    # (config is resolved: every setting below is set)
    check_memory(float(config.n_components) * (model_config.head_hidden + 1) * (2 * len(active) + 1)  # type: ignore[arg-type]
                 * BYTES_PER_TRAINED_PARAMETER, f"a mixture head of {config.n_components} components")
    torch.manual_seed(config.seed)
    # channels-last only on a GPU (tensor-core kernels).  On the CPU, oneDNN's channels-last
    # backward pass of this network corrupts the heap with one thread on AVX2-only machines
    # (glibc aborts: "corrupted size vs. prev_size"; reproduced with ONEDNN_MAX_CPU_ISA=AVX2,
    # tests/methods/mdn/test_mdn.py::test_cpu_training_keeps_the_default_layout), so the CPU keeps the default layout.
    memory_layout = torch.channels_last if dev.type == "cuda" else torch.contiguous_format
    # (Module.to takes memory_format; torch's overloads leave it out)
    model = MixtureDensityNetwork(model_config).to(dev, memory_format=memory_layout)  # type: ignore[call-overload]
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=WEIGHT_DECAY)  # type: ignore[arg-type]
    batch: int = min(config.batch_size, n_train)  # type: ignore[type-var, assignment]
    steps_per_epoch = n_train // batch  # the last incomplete batch is dropped (BatchNorm needs > 1 sample)
    total_steps = steps_per_epoch * config.epochs  # type: ignore[operator]  # (resolved)
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
        try:
            history = restore_training_state(ckpt, model, optimizer, scheduler, scaler)
        except UserError as exc:  # name the file
            raise UserError(f"{out}: {exc.message}") from None
        start_epoch = int(ckpt["epoch"])
        if start_epoch > config.epochs:  # type: ignore[operator]  # (resolved)
            raise UserError(f"{option('resume')}: {out} is at epoch {start_epoch} "
                            f"of a training of {config.epochs}; not resumable")
    log.info("%s: %d train / %d val images, %s parameters, device %s", obj_class.name, n_train, len(va_idx),
             f"{count_parameters(model):,}", dev)
    identity = split_identity(split_dir)  # read once: every checkpoint records it

    def checkpoint(epoch: int, finished: bool) -> MdnCheckpoint:
        return {
            "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "class_name": obj_class.name,
            "layout_names": names, "anchored_columns": [list(c) for c in anchored], "active_columns": [int(i) for i in active], "norm_stats": _plain(stats.to_dict()), "model_config": model_config.to_dict(),
            "input_config": input_config.to_dict(), "train_config": config.to_dict(),
            "data": {"split_dir": str(split_dir), "split": identity, "n_train": int(n_train),
                     "n_val": int(len(va_idx))},
            "epoch": epoch, "finished": finished, "history": history,
            "model_state": model.state_dict(), "optimizer_state": optimizer.state_dict(),
            "scheduler_state": scheduler.state_dict(), "scaler_state": scaler.state_dict(),
            "rng_state": torch.get_rng_state(),
        }

    last: int = stop_after_epoch if stop_after_epoch is not None else config.epochs  # type: ignore[assignment]  # (resolved)
    last = min(last, config.epochs)  # type: ignore[type-var, assignment]  # (resolved)
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
            x = assemble_inputs(planes_tr[idx].to(dev, non_blocking=True), input_config).contiguous(
                memory_format=memory_layout)
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
        # never replace the last checkpoint with diverged weights (no reader loads them, --resume included)
        if state_problem(model.state_dict()) is not None:  # as the dense trainer checks its weights
            raise UserError(f"training diverged in epoch {epoch + 1} (non-finite weights); {out} keeps the last "
                            f"checkpoint; lower {option('lr')}")
        history.append(record)
        result = checkpoint(epoch + 1, finished=(epoch + 1 == config.epochs))
        atomic_torch_save(result, out)
        line = "  ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in record.items())
        log.info("%s", line)
        if echo is not None:
            echo(line)
    return load_checkpoint(out) if start_epoch >= last else result


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
