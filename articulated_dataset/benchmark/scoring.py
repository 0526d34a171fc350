"""The benchmark scorer: predictions.h5 against ground-truth shards.

``score(predictions, truth_path, split=None) -> Report``:

1. read and validate each predictions file (:func:`articulated_dataset.benchmark.predictions.read_predictions`);
2. pick one truth split per predicted class under ``truth_path`` (:func:`select_truth`);
3. align predictions to the truth by ``sample_id`` (unknown ids are an error; missing ids
   give partial coverage, reported as ``n_scored / n_truth``);
4. compute per-image metrics (:func:`image_metrics`, averaged over the joints of 2-DoF
   objects) and aggregate them per (class, method) as mean and standard deviation.

The :class:`Report` prints the paper's Table 1 layout (:meth:`Report.format_table`) and
serialises to JSON and CSV (:mod:`.report`); the truth side is :mod:`.truth`.  All formulas are
in :mod:`articulated_dataset.benchmark.metrics` and docs/scoring.md.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from articulated_dataset.benchmark import metrics as M
from articulated_dataset.benchmark.predictions import MIXTURE_LAYOUT_ATTR, read_predictions
from articulated_dataset.benchmark.report import Report, ScoreRow, aggregate, standard_errors
from articulated_dataset.benchmark.truth import TruthSet, align, available_truth, select_truth
from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.format.schema import PRISMATIC

log = logging.getLogger(__name__)

#: Central interval masses whose coverage is reported for mixtures.
COVERAGE_MASSES = (0.5, 0.9)


# --------------------------------------------------------------------------------------
# Target vectors for mixture likelihoods
# --------------------------------------------------------------------------------------

def target_matrix(layout: list[str], truth: dict, where: str = "", class_name: str = "") -> np.ndarray:
    """True target vectors ``(N, D)`` in label units (float32 precision, returned as float64), column d named ``layout[d]``.

    The columns are taken from :meth:`articulated_dataset.training.targets.TargetLayout.encode` of the
    truth labels (``axis_pose``, ``q``, ``part_offset``, ``geometry``): ``j{j}.origin.{x,y,z}``
    (m), ``j{j}.axis.{x,y,z}`` (axis frame z), ``j{j}.xaxis.{x,y,z}`` (axis frame x),
    ``j{j}.q`` (rad | m), ``j{j}.offset.{x,y,z}`` (m), ``geometry.{depth,width,height,chirality}``.
    ``layout`` may be any subset of these names in any order; a name outside the class's
    layout is a :class:`DataFormatError`.
    """
    from articulated_dataset.training.targets import TargetLayout

    J = truth["axis_pose"].shape[1]
    full = TargetLayout(class_name or "?", J)
    index = {name: i for i, name in enumerate(full.names)}
    unknown = [name for name in layout if name not in index]
    if unknown:
        raise DataFormatError(
            f"{where}: {MIXTURE_LAYOUT_ATTR} column {unknown[0]!r} is not in the target layout of a class with {J} "
            f"joint(s) (j0..j{J - 1}.origin|axis|xaxis|offset.<x|y|z>, j<j>.q, geometry.depth|width|height|chirality)")
    y = full.encode({k: truth[k] for k in full.fields})
    return y[:, [index[name] for name in layout]].astype(np.float64)


# --------------------------------------------------------------------------------------
# Per-image metrics
# --------------------------------------------------------------------------------------

def accuracy_metric_name(max_direction_deg: float, max_distance_cm: float) -> str:
    """``accuracy_5deg_5cm`` for the thresholds (5, 5): the report's key of an accuracy metric."""
    return f"accuracy_{max_direction_deg:g}deg_{max_distance_cm:g}cm"


def image_metrics(pred: dict, truth: dict, joint_types, where: str = "",
                  metric_version: int = M.METRIC_VERSION) -> tuple[dict, dict]:
    """Per-image metrics of aligned predictions and truth (row i = same image in both).

    ``pred``/``truth`` hold ``axis_pose (N, J, 7)`` (unit quaternions), ``q (N, J)`` and
    optionally ``geometry (N, 4)``, ``part_offset (N, J, 3)`` and the mixture datasets
    (``pred``), ``geometry`` and ``part_offset`` (``truth``).  Returns ``(per_image,
    per_joint)``: ``{metric: (N,)}`` with 2-DoF objects averaged over joints, and
    ``{metric: (N, J)}`` for :data:`.report.PER_JOINT_METRICS`.  NaN marks an undefined value (truth
    missing, real captures), infinity a real one (NLL of a zero density).  Metrics that do not
    apply (no geometry or mixture predicted) are absent; the line distance and the mechanism
    side average revolute joints only.

    A predicted joint that is the true joint written with the other axis sign
    (:func:`metrics.canonical_axis_sign`) is re-expressed first; the rotation and
    configuration errors are computed on it.

    ``metric_version`` (:data:`metrics.METRIC_VERSIONS`): 3 adds the position error along and
    across the true axis, the accuracies at :data:`metrics.ACCURACY_THRESHOLDS` (per joint,
    averaged over joints) and scores ``opd_success`` by OPD's criterion
    (:func:`metrics.opd_motion_success`); 2 gives version 2's metrics exactly.
    """
    if metric_version not in M.METRIC_VERSIONS:
        raise UserError(f"metric version {metric_version} is not one of {', '.join(map(str, M.METRIC_VERSIONS))}")
    prismatic = np.array([t == PRISMATIC for t in joint_types], bool)
    revolute = ~prismatic
    pp, tp = pred["axis_pose"], truth["axis_pose"]
    o_p, o_t, r_t = pp[..., :3], tp[..., :3], tp[..., 3:]
    r_p, q_p = M.canonical_axis_sign(pp[..., 3:], pred["q"], r_t)
    d_p, d_t = M.quat_axis_z(r_p), M.quat_axis_z(r_t)
    per_joint = {
        "axis_position_error_cm": M.axis_position_error_cm(o_p, o_t),
        "axis_rotation_error_deg": M.axis_rotation_error_deg(r_p, r_t),
        "configuration_error": M.configuration_error(q_p, truth["q"], prismatic),
        "axis_direction_error_deg": M.axis_direction_error_deg(d_p, d_t),
    }
    out = {k: v.mean(axis=1) for k, v in per_joint.items()}
    side = np.full(o_p.shape[:2], np.nan)  # prismatic joints: no side
    if revolute.any():
        line = M.line_distance_cm(o_p[:, revolute], d_p[:, revolute], o_t[:, revolute], d_t[:, revolute])
        out["axis_line_distance_cm"] = line.mean(axis=1)
        side_p = M.part_side(r_p[:, revolute], pred["part_offset"][:, revolute]) if "part_offset" in pred else None
        side_x = M.part_side(r_p[:, revolute])  # the label convention: x points at the part
        side_p = side_x if side_p is None else np.where(np.isnan(side_p), side_x, side_p)
        side_t = M.part_side(r_t[:, revolute], truth["part_offset"][:, revolute])
        side[:, revolute] = M.mechanism_side_correct(side_p, side_t)
        out["mechanism_side_accuracy"] = side[:, revolute].mean(axis=1)
    origin_to_line = M.point_to_line_distance_cm(o_p, o_t, d_t)
    diag = M.object_diagonal_m(truth["geometry"])[:, None]
    e_dir = per_joint["axis_direction_error_deg"]
    if metric_version == 2:
        out["opd_success"] = M.opd_success(e_dir, origin_to_line, diag, revolute, side).mean(axis=1)
    else:
        out["opd_success"] = M.opd_motion_success(e_dir, origin_to_line, diag, revolute).mean(axis=1)
        along, across = M.position_error_components_cm(o_p, o_t, d_t)
        out["axis_position_along_cm"], out["axis_position_across_cm"] = along.mean(axis=1), across.mean(axis=1)
        line_all = M.line_distance_cm(o_p, d_p, o_t, d_t)
        for max_deg, max_cm in M.ACCURACY_THRESHOLDS:
            out[accuracy_metric_name(max_deg, max_cm)] = M.axis_accuracy(e_dir, line_all, revolute, max_deg,
                                                                         max_cm).mean(axis=1)
    if "geometry" in pred:
        g_err = M.geometry_error_cm(pred["geometry"], truth["geometry"])
        out["geometry_depth_error_cm"], out["geometry_width_error_cm"], out["geometry_height_error_cm"] = g_err.T
        out["chirality_accuracy"] = M.chirality_correct(pred["geometry"], truth["geometry"])
    if "mixture_weights" in pred:
        y = target_matrix(pred[MIXTURE_LAYOUT_ATTR], truth, where)
        w, mu, sigma = pred["mixture_weights"], pred["mixture_means"], pred["mixture_scales"]
        out["nll"] = M.mixture_nll(y, w, mu, sigma)
        u = M.mixture_marginal_cdf(y, w, mu, sigma)  # PIT values; see metrics.interval_coverage
        for mass in COVERAGE_MASSES:
            cover = (np.abs(u - 0.5) <= 0.5 * mass).mean(axis=1)
            out[f"coverage_{round(100 * mass)}"] = np.where(np.isnan(u).any(axis=1), np.nan, cover)
    return out, per_joint


def score_class(pred: dict, truth: TruthSet, method: str, predictions_path: str,
                metric_version: int = M.METRIC_VERSION) -> ScoreRow:
    """Score one class of one predictions file against its truth split."""
    where = f"{predictions_path}:/{truth.class_name}"
    idx = align(pred["sample_id"], truth.arrays["sample_id"], where, str(truth.path))
    J_pred, J_true = pred["axis_pose"].shape[1], len(truth.joint_types)
    if J_pred != J_true:
        raise DataFormatError(f"{where}/axis_pose: {J_pred} joints predicted, the truth ({truth.path}) has {J_true}")
    t = {k: v[idx] for k, v in truth.arrays.items()}
    with np.errstate(all="ignore"):  # NaN truth and zero mixture densities are handled as values
        per_image, per_joint = image_metrics(pred, t, truth.joint_types, where, metric_version)
        metrics, joints, defined, infinite = aggregate(per_image, per_joint)
        sem = standard_errors(per_image, t["object_index"]) if metric_version >= 3 else {}
    return ScoreRow(class_name=truth.class_name, method=method, split=truth.split, truth_path=str(truth.path),
                    predictions_path=str(predictions_path), n_scored=len(idx), n_truth=truth.n_images,
                    joint_types=truth.joint_types, metrics=metrics, per_joint=joints, n_defined=defined,
                    n_infinite=infinite, sem=sem, n_objects=len(np.unique(t["object_index"])),
                    metric_version=metric_version)


def _class_order(name: str) -> tuple:
    from articulated_dataset.classes.registry import class_names

    names = class_names()
    return (names.index(name), "") if name in names else (len(names), name)


def score(predictions, truth_path: str | Path, split: str | None = None,
          metric_version: int = M.METRIC_VERSION) -> Report:
    """Score one predictions file (or a list of them) against the truth under ``truth_path``.

    ``truth_path`` is a split folder or a folder with ``<class>/<split>/`` below it; ``split``
    picks the split when a class has several (default :data:`.truth.DEFAULT_SPLIT`);
    ``metric_version`` one of :data:`.metrics.METRIC_VERSIONS`.  Returns a :class:`Report` with
    one row per (class, method).  Bad input raises :class:`UserError`.
    """
    if metric_version not in M.METRIC_VERSIONS:
        raise UserError(f"metric version {metric_version} is not one of {', '.join(map(str, M.METRIC_VERSIONS))}")
    paths = [predictions] if isinstance(predictions, (str, Path)) else list(predictions)
    if not paths:
        raise UserError("no predictions file given")
    loaded = [(str(p), *read_predictions(p)) for p in paths]
    classes = sorted({c for _, _, per_class in loaded for c in per_class}, key=_class_order)
    sources: dict[str, str] = {}
    for path, _, per_class in loaded:
        for c in per_class:
            sources.setdefault(c, path)
    truth = select_truth(truth_path, classes, split, sources)
    rows: list[ScoreRow] = []
    notes: list[str] = []
    seen: dict[tuple[str, str], str] = {}
    for path, attrs, per_class in loaded:
        method = str(attrs["method"])
        for cls, pred in per_class.items():
            key = (cls, method)
            if key in seen:
                raise UserError(f"{path}: class {cls!r} of method {method!r} is also in {seen[key]}")
            seen[key] = path
            row = score_class(pred, truth[cls], method, path, metric_version)
            if not row.complete:
                msg = (f"{cls} - {method}: partial coverage, {row.n_scored} of {row.n_truth} truth images "
                       f"predicted ({100.0 * row.n_scored / row.n_truth:.1f}%)")
                log.warning(msg)
                notes.append(msg)
            for name, k in row.n_defined.items():
                notes.append(f"{cls} - {method}: {name} averaged over the {k} of {row.n_scored} images whose truth defines it")
            for name, k in row.n_infinite.items():
                notes.append(f"{cls} - {method}: {name} is infinite for {k} of {row.n_scored} images "
                             f"(the prediction gives the truth zero density in float64), so its mean is infinite")
            incomplete = f"{cls}: truth split {truth[cls].path} is incomplete (generation was interrupted)"
            if not truth[cls].complete and incomplete not in notes:
                notes.append(incomplete)
            rows.append(row)
    order = {c: i for i, c in enumerate(classes)}
    rows.sort(key=lambda r: order[r.class_name])  # stable: file order within a class
    unscored = sorted(set(available_truth(truth_path)) - set(classes), key=_class_order)
    return Report(truth_root=str(truth_path), split=split, rows=rows, notes=notes, unscored_classes=unscored,
                  metric_version=metric_version)
