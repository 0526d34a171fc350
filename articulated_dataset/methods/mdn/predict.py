"""Inference of a trained MDN on a split (``artdata predict``).

For every image the network gives a mixture over the normalised target; the point
estimate (``mean-of-best`` or ``mode``, :mod:`articulated_dataset.methods.mdn.loss`) is
denormalised (``y = y_norm * std + mean``) and decoded into the label convention by
:meth:`TargetLayout.decode` (the 6-D rotation becomes a quaternion by Gram-Schmidt).  The
mixture itself is written in label units: means ``mu * std + mean``, scales
``sigma * std``, weights ``softmax(logits)``, so ``artdata score`` can report the
likelihood and calibration metrics.

``snap_to_cloud`` replaces each joint's axis origin by the segmented, back-projected point
that is most likely under the mixture's marginal over that origin (the paper's Table 2
procedure, :mod:`articulated_dataset.benchmark.pointlik`).  Labels of the predicted split are never
read.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.mdn.loss import ESTIMATES

log = logging.getLogger(__name__)

#: Images per forward pass at inference.
DEFAULT_PREDICT_BATCH = 256


def predict_split(model_path: str | Path, data: str | Path, *, estimate: str = "mean-of-best", snap_to_cloud: bool = False,
                  batch_size: int = DEFAULT_PREDICT_BATCH, device: str | None = None, progress: bool = True,
                  as_class: str | None = None) -> tuple[str, dict]:
    """Run the checkpoint at ``model_path`` on the split at ``data`` (of the checkpoint's class, or,
    with ``as_class``, a third-party split read as that class: :func:`~.data.checked_split_class`).

    Returns ``(the split's class, arrays)`` with the datasets of
    :func:`articulated_dataset.benchmark.predictions.write_predictions` (``sample_id``, ``axis_pose``,
    ``q``, ``geometry``, ``part_offset``, ``mixture_weights``, ``mixture_means``,
    ``mixture_scales``, ``mixture_layout``).
    """
    import torch

    from articulated_dataset.benchmark.predictions import bounded_geometry
    from articulated_dataset.methods.mdn.checkpoint import build_model_from_checkpoint, load_checkpoint
    from articulated_dataset.methods.mdn.data import (
        checked_split_class,
        expand_active,
        load_split,
        resolve_split_dir,
        shift_anchored,
    )
    from articulated_dataset.methods.mdn.loss import point_estimate
    from articulated_dataset.methods.mdn.preprocess import InputConfig, assemble_inputs
    from articulated_dataset.methods.mdn.train import resolve_device
    from articulated_dataset.training.targets import NormStats, TargetLayout

    if estimate not in ESTIMATES:
        raise UserError(f"unknown estimate {estimate!r}; expected one of {', '.join(ESTIMATES)}")
    if batch_size <= 0:
        raise UserError(f"{option('batch_size')} must be positive, got {batch_size}")
    ckpt = load_checkpoint(model_path)
    class_name = ckpt["class_name"]
    split_dir = resolve_split_dir(data)
    data_class = checked_split_class(split_dir, class_name, as_class, f"the model {model_path}")
    layout = TargetLayout.for_class(class_name)
    names = list(layout.names)
    if names != list(ckpt["layout_names"]):
        raise UserError(f"{model_path}: the checkpoint's target layout differs from this version's {class_name!r} layout; retrain it")
    stats = NormStats.from_dict(ckpt["norm_stats"])
    dev = resolve_device(device)
    model = build_model_from_checkpoint(ckpt, dev)
    input_config = InputConfig.from_dict(ckpt["input_config"])
    prepared = load_split(split_dir, layout, input_config, progress=progress, with_targets=False)

    from tqdm.auto import tqdm

    weights, means, scales, est = [], [], [], []
    N = prepared.planes.shape[0]
    with torch.no_grad():
        for start in tqdm(range(0, N, batch_size), desc="predicting", unit="batch", disable=not progress, leave=False):
            x = assemble_inputs(prepared.planes[start : start + batch_size].to(dev), input_config)
            s = prepared.scalars[start : start + batch_size].to(dev)
            if dev.type == "cuda":
                with torch.autocast("cuda", dtype=torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16):
                    logits, mu, sigma = model(x, s)
            else:
                logits, mu, sigma = model(x, s)
            est.append(point_estimate(logits, mu, sigma, estimate).cpu().numpy())
            weights.append(torch.softmax(logits.double(), dim=-1).cpu().numpy())
            means.append(mu.cpu().numpy())
            scales.append(sigma.cpu().numpy())
    # columns not modelled (constant in training) get their training value and a unit scale
    active = np.asarray(ckpt.get("active_columns", range(len(names))), np.int64)
    D = len(names)
    est_n, w = expand_active(np.concatenate(est), active, D, 0.0), np.concatenate(weights)
    mu_n = expand_active(np.concatenate(means), active, D, 0.0)
    sigma_n = expand_active(np.concatenate(scales), active, D, 1.0)
    M = mu_n.shape[1]
    stats.check_layout(layout)
    std = np.asarray(stats.std, np.float64)
    # back to camera-frame label units: y = y_n * std + mean, then add the image anchor to the origins
    anchored = [tuple(c) for c in ckpt.get("anchored_columns", [])]
    anchor = prepared.anchor.numpy()
    mu_lab = np.asarray(stats.denormalize(mu_n.reshape(N * M, D)), np.float64).reshape(N, M, D)
    mu_lab = shift_anchored(mu_lab, anchor, anchored, 1.0)
    sigma_lab = sigma_n.astype(np.float64) * std
    est_lab = shift_anchored(stats.denormalize(est_n), anchor, anchored, 1.0)
    decoded = layout.decode(est_lab)
    geometry = bounded_geometry(decoded["geometry"])
    arrays = {
        "sample_id": prepared.sample_id,
        "axis_pose": np.asarray(decoded["axis_pose"], np.float64),
        "q": np.asarray(decoded["q"], np.float64),
        "geometry": geometry,
        "part_offset": np.asarray(decoded["part_offset"], np.float64),
        "mixture_weights": w, "mixture_means": mu_lab, "mixture_scales": sigma_lab, "mixture_layout": names,
    }
    if snap_to_cloud:
        arrays["axis_pose"] = _snap(split_dir, prepared, arrays, names, progress)
    return data_class, arrays


def _snap(split_dir: Path, prepared, arrays: dict, names: list[str], progress: bool) -> np.ndarray:
    """Axis poses with every joint's origin moved to the most likely segmented point."""
    from tqdm.auto import tqdm

    from articulated_dataset.benchmark.pointlik import snap_axis_poses, snap_batch
    from articulated_dataset.format import Split

    shards = Split(split_dir).shards
    pose = arrays["axis_pose"].copy()
    J = pose.shape[1]
    for s_idx, sh in enumerate(tqdm(shards, desc="snapping to the cloud", unit="shard", disable=not progress, leave=False)):
        rows = np.nonzero(prepared.shard_of == s_idx)[0]
        if len(rows) == 0:
            continue
        depth, mask, K = sh.read("depth"), sh.read("mask"), sh.K
        origins, _ = snap_batch(depth, mask, K, arrays["mixture_weights"][rows], arrays["mixture_means"][rows],
                                arrays["mixture_scales"][rows], names, J, fallback=pose[rows, :, :3])
        pose[rows] = snap_axis_poses(pose[rows], origins)
        sh.close()
    return pose
