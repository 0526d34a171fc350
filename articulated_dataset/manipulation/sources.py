"""Where estimates come from: a predictions file, or a model run on one depth image.

:func:`load_prediction_estimates` reads a predictions file's estimates of one class;
:func:`make_estimator` wraps a shipped model or a checkpoint (dense or MDN) as a
:class:`DepthEstimator`, ``estimator(depth_m, K) -> ObjectKinematics``, the dense model's other
mixture components kept as alternatives (:func:`estimate_with_alternatives`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.manipulation.hypotheses import ObjectKinematics


def load_prediction_estimates(path: str | Path, class_name: str) -> tuple[str, dict[int, ObjectKinematics]]:
    """``(method, {sample_id: ObjectKinematics})`` for one class of a predictions file
    (:func:`articulated_dataset.benchmark.predictions.read_predictions`)."""
    from articulated_dataset.benchmark.predictions import read_predictions

    attrs, per_class = read_predictions(path)
    if class_name not in per_class:
        raise UserError(f"{path}: no predictions for class {class_name!r} (has {', '.join(per_class)})")
    p = per_class[class_name]
    method = str(attrs.get("method", Path(path).stem))
    out = {}
    for i, sid in enumerate(p["sample_id"]):
        out[int(sid)] = ObjectKinematics(
            axis_pose=p["axis_pose"][i], q=p["q"][i],
            part_offset=p["part_offset"][i] if "part_offset" in p else None,
            geometry=p["geometry"][i] if "geometry" in p else None, source=method,
        )
    return method, out


@dataclass
class DepthEstimator:
    """A model that turns one depth image of a ``class_name`` object into an :class:`ObjectKinematics`
    in that image's camera frame: ``estimator(depth_m, K)``.  Built by :func:`make_estimator`."""

    name: str  # display / method name (dense, MDN-small, ...)
    kind: str  # dense | mdn
    class_name: str
    _fn: Callable[[np.ndarray, np.ndarray], ObjectKinematics] | None = field(repr=False, default=None)

    def __call__(self, depth_m: np.ndarray, K: np.ndarray) -> ObjectKinematics:
        """The model's estimate for one depth image ``depth_m`` (H, W, metres) with intrinsics ``K`` (3, 3), in its
        camera frame."""
        return self._fn(np.asarray(depth_m, np.float32), np.asarray(K, np.float64))  # type: ignore[misc]  # set by make_estimator


def make_estimator(model: str, class_name: str) -> DepthEstimator:
    """The estimator of ``--model`` (a shipped name, ``dense``, ``dense-kinect2`` or ``mdn-small``, or a checkpoint
    path of either kind) for ``class_name``.  Unknown names, a wrong class or an unreadable
    file are a :class:`UserError` (:func:`articulated_dataset.methods.shipped.resolve_model`)."""
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.protocol import get_method

    ref = resolve_model(model, class_name)
    name = ref.name  # a shipped model's name, or the kind of a checkpoint file's model
    if get_method(ref.kind).single_image:
        from articulated_dataset.methods.estimation import estimate

        path = str(ref.path)  # resolved (and checksummed) once

        def fn(depth, K):
            return estimate_with_alternatives(estimate(depth, K, class_name, model=path), name)

        return DepthEstimator(name, "dense", class_name, fn)
    return DepthEstimator(name, "mdn", class_name, _mdn_single_image(ref.path, class_name, name))


#: Mixture components lighter than this (of the image's total weight) are not planning hypotheses.
HYPOTHESIS_MIN_WEIGHT = 0.05


def estimate_with_alternatives(e, source: str) -> ObjectKinematics:
    """A planner's :class:`ObjectKinematics` from an :class:`articulated_dataset.methods.estimation.Estimate` (the model's output): the
    heaviest mixture component, with every other component of at least
    :data:`HYPOTHESIS_MIN_WEIGHT` as an alternative (decoded like the point estimate)."""
    from articulated_dataset.training.targets import TargetLayout

    main = ObjectKinematics(e.axis_pose.astype(np.float64), e.q.astype(np.float64), e.part_offset_m.astype(np.float64),
                    e.geometry.astype(np.float64), source=source)
    w = e.mixture_weights
    if w is None or len(w) < 2:
        return main
    best = int(np.argmax(w))
    main.weight = float(w[best] / w.sum())
    others = [k for k in np.argsort(-w) if k != best and w[k] / w.sum() >= HYPOTHESIS_MIN_WEIGHT]
    if others:
        d = TargetLayout.for_class(e.class_name).decode(e.mixture_means[others])
        for i, k in enumerate(others):
            main.alternatives.append(ObjectKinematics(d["axis_pose"][i].astype(np.float64), d["q"][i].astype(np.float64),
                                              d["part_offset"][i].astype(np.float64), d["geometry"][i].astype(np.float64),
                                              source=source, weight=float(w[k] / w.sum())))
    return main


def _mdn_single_image(path: Path, class_name: str, name: str):
    """One-image inference of an MDN checkpoint (the ``mean-of-best`` point estimate, decoded
    as :func:`articulated_dataset.methods.mdn.predict.predict_split` does for a split)."""
    import torch

    from articulated_dataset.methods.mdn.checkpoint import build_model_from_checkpoint, load_checkpoint
    from articulated_dataset.methods.mdn.data import expand_active, shift_anchored
    from articulated_dataset.methods.mdn.loss import point_estimate
    from articulated_dataset.methods.mdn.preprocess import InputConfig, assemble_inputs, preprocess_depth
    from articulated_dataset.training.targets import NormStats, TargetLayout

    ckpt = load_checkpoint(path)
    layout = TargetLayout.for_class(class_name)
    names = list(layout.names)
    if names != list(ckpt["layout_names"]):
        raise UserError(f"{path}: the checkpoint's target layout differs from this version's {class_name!r} layout; retrain it")
    stats = NormStats.from_dict(ckpt["norm_stats"])
    net = build_model_from_checkpoint(ckpt, "cpu")
    input_config = InputConfig.from_dict(ckpt["input_config"])
    active = np.asarray(ckpt.get("active_columns", range(len(names))), np.int64)
    anchored = [tuple(c) for c in ckpt.get("anchored_columns", [])]

    def fn(depth, K):
        planes, scalars, anchor = preprocess_depth(depth[None], input_config, K)
        with torch.no_grad():
            logits, mu, sigma = net(assemble_inputs(planes, input_config), scalars)
            est = point_estimate(logits, mu, sigma, "mean-of-best").numpy()
        est = shift_anchored(stats.denormalize(expand_active(est, active, len(names), 0.0)), anchor.numpy(), anchored, 1.0)
        d = layout.decode(est)
        return ObjectKinematics(np.asarray(d["axis_pose"][0], np.float64), np.asarray(d["q"][0], np.float64),
                        np.asarray(d["part_offset"][0], np.float64), np.asarray(d["geometry"][0], np.float64), source=name)

    return fn
