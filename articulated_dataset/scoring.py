"""The benchmark scorer: predictions.h5 against ground-truth shards.

``score(predictions, truth_path, split=None) -> Report``:

1. read and validate each predictions file (:func:`articulated_dataset.predictions.read_predictions`);
2. pick one truth split per predicted class under ``truth_path`` (:func:`select_truth`);
3. align predictions to the truth by ``sample_id`` (unknown ids are an error; missing ids
   give partial coverage, reported as ``n_scored / n_truth``);
4. compute per-image metrics (:func:`image_metrics`, averaged over the joints of 2-DoF
   objects) and aggregate them per (class, method) as mean and standard deviation.

The :class:`Report` prints the paper's Table 1 layout (:meth:`Report.format_table`) and
serialises to JSON and CSV.  All formulas are in :mod:`articulated_dataset.metrics` and
docs/scoring.md.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import metrics as M
from .errors import DataFormatError, UserError
from .predictions import MIXTURE_LAYOUT_ATTR, read_predictions
from .registry import PRISMATIC, REVOLUTE
from .format import Split, splits_by_class

log = logging.getLogger(__name__)

#: Truth split chosen when a class has several and no ``split`` is given.
DEFAULT_SPLIT = "test"
#: Label fields the scorer reads from the truth shards.
TRUTH_FIELDS = ("sample_id", "axis_pose", "q", "geometry", "part_offset")
#: Central interval masses whose coverage is reported for mixtures.
COVERAGE_MASSES = (0.5, 0.9)


# --------------------------------------------------------------------------------------
# Metric table
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class MetricSpec:
    """One reported metric: key (JSON/CSV), column title, units and whether it is a paper metric."""

    name: str
    title: str
    units: str
    paper: bool = False


CONFIG_UNITS = {REVOLUTE: "deg", PRISMATIC: "cm"}

METRICS: tuple[MetricSpec, ...] = (
    MetricSpec("axis_position_error_cm", "Axis Position Error (cm)", "cm", paper=True),
    MetricSpec("axis_rotation_error_deg", "Axis Rotation Error (degrees)", "deg", paper=True),
    MetricSpec("configuration_error", "Configuration Error", "deg (revolute) | cm (prismatic)", paper=True),
    MetricSpec("axis_direction_error_deg", "Direction (deg)", "deg"),
    MetricSpec("axis_line_distance_cm", "Line dist. (cm)", "cm"),
    MetricSpec("opd_success", "OPD success", "fraction"),
    MetricSpec("geometry_depth_error_cm", "Depth (cm)", "cm"),
    MetricSpec("geometry_width_error_cm", "Width (cm)", "cm"),
    MetricSpec("geometry_height_error_cm", "Height (cm)", "cm"),
    MetricSpec("chirality_accuracy", "Chirality acc.", "fraction"),
    MetricSpec("mechanism_side_accuracy", "Side acc.", "fraction"),
    MetricSpec("nll", "NLL (nats)", "nats"),
    MetricSpec("coverage_50", "Cov. 50%", "fraction"),
    MetricSpec("coverage_90", "Cov. 90%", "fraction"),
)
METRICS_BY_NAME = {m.name: m for m in METRICS}
#: Most characters per line of the default table (``artdata score``; ``--wide`` has no limit).
TABLE_WIDTH = 100
#: Column names of the default table: short, and saying which rotation is meant.
SHORT_TITLES = {
    "axis_position_error_cm": "Axis position (cm)",
    "axis_rotation_error_deg": "Frame heading (deg)",
    "configuration_error": "Configuration",
    "axis_direction_error_deg": "Axis dir. (deg)",
    "axis_line_distance_cm": "Line dist. (cm)",
    "opd_success": "OPD succ.",
    "geometry_depth_error_cm": "Depth (cm)",
    "geometry_width_error_cm": "Width (cm)",
    "geometry_height_error_cm": "Height (cm)",
    "chirality_accuracy": "Chirality",
    "mechanism_side_accuracy": "Side",
    "nll": "NLL (nats)",
    "coverage_50": "Cov. 50%",
    "coverage_90": "Cov. 90%",
}
#: What the default table's short names mean (docs/scoring.md has the formulas).
TABLE_LEGEND = [
    "Axis position: distance between axis origins. Frame heading: the paper's axis rotation error, the",
    "heading of the axis frame about the camera's vertical (a mirrored door scores 180). Axis dir.: angle",
    "between the axis lines, sign folded. Chirality, Side, OPD succ., Cov.: fractions of images.",
]
#: Per-joint means are kept for these (JSON ``per_joint``).
PER_JOINT_METRICS = ("axis_position_error_cm", "axis_rotation_error_deg", "configuration_error",
                     "axis_direction_error_deg")


# --------------------------------------------------------------------------------------
# Truth
# --------------------------------------------------------------------------------------

@dataclass
class TruthSet:
    """The labels of one split of one class, sorted by ``sample_id``."""

    class_name: str
    split: str
    path: Path
    joint_types: tuple[str, ...]
    complete: bool
    arrays: dict[str, np.ndarray]

    @property
    def n_images(self) -> int:
        return int(self.arrays["sample_id"].shape[0])


def load_truth_set(split_dir: str | Path) -> TruthSet:
    """Read the label fields the scorer needs from every shard of a split folder."""
    split_dir = Path(split_dir)
    split = Split(split_dir)  # checks the manifest and that every shard path stays inside the folder
    if not split.shards:
        raise DataFormatError(f"{split_dir}: the split has no shards")
    joint_types = split.joint_types()  # every shard's, known and equal
    arrays = split.read_fields(TRUTH_FIELDS)
    ids = arrays["sample_id"].astype(np.int64)
    order = np.argsort(ids, kind="stable")
    arrays = {k: np.asarray(v[order], np.float64) if k != "sample_id" else ids[order] for k, v in arrays.items()}
    if arrays["axis_pose"].shape[1] != len(joint_types):
        raise DataFormatError(f"{split_dir}: {arrays['axis_pose'].shape[1]} joints in axis_pose but {len(joint_types)} joint types")
    dup = arrays["sample_id"][1:] == arrays["sample_id"][:-1]
    if dup.any():
        raise DataFormatError(f"{split_dir}: {int(dup.sum())} duplicated sample ids in the truth")
    quat = arrays["axis_pose"][..., 3:]
    with np.errstate(all="ignore"):  # a NaN or zero quaternion (undefined truth) stays NaN
        arrays["axis_pose"][..., 3:] = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    return TruthSet(class_name=split.class_name, split=split_dir.name, path=split_dir,
                    joint_types=joint_types, complete=split.complete, arrays=arrays)


def available_truth(truth_path: str | Path) -> dict[str, dict[str, Path]]:
    """``{class: {split name: split folder}}`` of the splits under ``truth_path``
    (:func:`articulated_dataset.format.splits_by_class`)."""
    return splits_by_class(truth_path)


def select_truth(truth_path: str | Path, classes, split: str | None = None,
                 sources: dict[str, str] | None = None) -> dict[str, TruthSet]:
    """Load one truth split for each class in ``classes``.

    With ``split`` given, the split folder of that name; otherwise the only split of the class
    or, among several, :data:`DEFAULT_SPLIT`.  A class without truth, an ambiguous choice or
    a missing split is a :class:`UserError`.  ``sources[class]`` names the predictions file of a
    class in messages.
    """
    found = available_truth(truth_path)
    out = {}
    for cls in classes:
        splits = found.get(cls)
        if not splits:
            have = ", ".join(sorted(found)) or "none"
            where = f"{sources[cls]}:/{cls}" if sources and cls in sources else f"class {cls!r}"
            raise UserError(f"{where}: predictions for a class with no truth under {truth_path} (classes there: {have})")
        if split is not None:
            if split not in splits:
                raise UserError(f"class {cls!r} has no split {split!r} under {truth_path} (splits: {', '.join(sorted(splits))})")
            chosen = split
        elif len(splits) == 1:
            chosen = next(iter(splits))
        elif DEFAULT_SPLIT in splits:
            chosen = DEFAULT_SPLIT
        else:
            raise UserError(f"class {cls!r} has several splits under {truth_path} ({', '.join(sorted(splits))}); "
                            f"choose one with --split")
        out[cls] = load_truth_set(splits[chosen])
    return out


# --------------------------------------------------------------------------------------
# Target vectors for mixture likelihoods
# --------------------------------------------------------------------------------------

def target_matrix(layout: list[str], truth: dict, where: str = "", class_name: str = "") -> np.ndarray:
    """True target vectors ``(N, D)`` in label units (float32 precision, returned as float64), column d named ``layout[d]``.

    The columns are taken from :meth:`articulated_dataset.targets.TargetLayout.encode` of the
    truth labels (``axis_pose``, ``q``, ``part_offset``, ``geometry``): ``j{j}.origin.{x,y,z}``
    (m), ``j{j}.axis.{x,y,z}`` (axis frame z), ``j{j}.xaxis.{x,y,z}`` (axis frame x),
    ``j{j}.q`` (rad | m), ``j{j}.offset.{x,y,z}`` (m), ``geometry.{depth,width,height,chirality}``.
    ``layout`` may be any subset of these names in any order; a name outside the class's
    layout is a :class:`DataFormatError`.
    """
    from .targets import TargetLayout

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

def image_metrics(pred: dict, truth: dict, joint_types, where: str = "") -> tuple[dict, dict]:
    """Per-image metrics of aligned predictions and truth (row i = same image in both).

    ``pred``/``truth`` hold ``axis_pose (N, J, 7)`` (unit quaternions), ``q (N, J)`` and
    optionally ``geometry (N, 4)``, ``part_offset (N, J, 3)`` and the mixture datasets
    (``pred``), ``geometry`` and ``part_offset`` (``truth``).  Returns ``(per_image,
    per_joint)``: ``{metric: (N,)}`` with 2-DoF objects averaged over joints, and
    ``{metric: (N, J)}`` for :data:`PER_JOINT_METRICS`.  NaN marks an undefined value (truth
    missing, real captures), infinity a real one (NLL of a zero density).  Metrics that do not
    apply (no geometry or mixture predicted) are absent; the line distance and the mechanism
    side average revolute joints only.

    A predicted joint that is the true joint written with the other axis sign
    (:func:`metrics.canonical_axis_sign`) is re-expressed first; the rotation and
    configuration errors are computed on it.
    """
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
    out["opd_success"] = M.opd_success(per_joint["axis_direction_error_deg"], origin_to_line, diag, revolute,
                                       side).mean(axis=1)
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


# --------------------------------------------------------------------------------------
# Rows and report
# --------------------------------------------------------------------------------------

def _clean(x: float) -> float | str | None:
    """A metric value for JSON: a float, ``"inf"``/``"-inf"`` for an infinite one (strict JSON has no
    infinity; e.g. the NLL of a truth the mixture gives zero density), None where undefined (NaN)."""
    if x is None or math.isnan(x):
        return None
    return float(x) if math.isfinite(x) else ("inf" if x > 0 else "-inf")


def _cell(x: float | None) -> str:
    """A metric value for CSV: ``%.6g`` (``inf`` included), empty where undefined."""
    return "" if x is None or math.isnan(x) else f"{x:.6g}"


@dataclass
class ScoreRow:
    """Aggregated metrics of one (class, method): ``metrics[name] = (mean, std)`` over images.

    ``std`` is the population standard deviation (ddof = 0).  ``n_scored`` images of the
    ``n_truth`` in the truth split were predicted and scored.
    """

    class_name: str
    method: str
    split: str
    truth_path: str
    predictions_path: str
    n_scored: int
    n_truth: int
    joint_types: tuple[str, ...]
    metrics: dict[str, tuple[float, float]]
    per_joint: dict[str, list[float]] = field(default_factory=dict)
    #: images whose truth defines the metric, where fewer than n_scored (real captures may
    #: lack some ground truth, stored as NaN): metric name -> count.
    n_defined: dict[str, int] = field(default_factory=dict)
    #: images whose value is infinite (counted in the mean, which is then infinite): name -> count.
    n_infinite: dict[str, int] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        return self.n_scored == self.n_truth

    @property
    def configuration_units(self) -> str:
        units = sorted({CONFIG_UNITS[t] for t in self.joint_types})
        return units[0] if len(units) == 1 else "mixed (deg | cm)"

    @property
    def label(self) -> str:
        return f"{self.class_name.capitalize()} - {self.method}"

    def to_dict(self) -> dict:
        return {
            "class": self.class_name,
            "method": self.method,
            "split": self.split,
            "truth": self.truth_path,
            "predictions": self.predictions_path,
            "n_scored": self.n_scored,
            "n_truth": self.n_truth,
            "complete": self.complete,
            "joint_types": list(self.joint_types),
            "configuration_units": self.configuration_units,
            "metrics": {
                name: {"mean": _clean(mean), "std": _clean(std),
                       "units": self.configuration_units if name == "configuration_error" else METRICS_BY_NAME[name].units}
                for name, (mean, std) in self.metrics.items()
            },
            "per_joint": {k: [_clean(v) for v in vals] for k, vals in self.per_joint.items()},
            "n_defined": dict(self.n_defined),
            "n_infinite": dict(self.n_infinite),
        }


def _defined_mean_std(v: np.ndarray) -> tuple[float, float]:
    """Mean and population std over the defined (non-NaN) values; an infinite value is a value:
    it makes the mean infinite (and the std infinite), it is never dropped."""
    v = v[~np.isnan(v)]
    if not len(v):
        return float("nan"), float("nan")
    if not np.isfinite(v).all():
        return float(v.mean()), float("inf")
    return float(v.mean()), float(v.std())


def aggregate(per_image: dict, per_joint: dict) -> tuple[dict, dict, dict, dict]:
    """Mean and population std of each per-image metric over the images where it is defined
    (not NaN: real truth may lack labels); per-joint means; counts of defined images for the
    metrics undefined somewhere; counts of infinite values."""
    metrics = {name: _defined_mean_std(np.asarray(v, dtype=np.float64)) for name, v in per_image.items()}
    joints = {}
    for name in PER_JOINT_METRICS:
        if name in per_joint:
            pj = np.asarray(per_joint[name], dtype=np.float64)
            joints[name] = [_defined_mean_std(pj[:, j])[0] for j in range(pj.shape[1])]
    defined = {name: int((~np.isnan(v)).sum()) for name, v in per_image.items() if np.isnan(v).any()}
    infinite = {name: int(np.isinf(v).sum()) for name, v in per_image.items() if np.isinf(v).any()}
    return metrics, joints, defined, infinite


def _pm(mean: float, std: float, digits: int = 2) -> str:
    return f"{mean:.{digits}f} +/- {std:.{digits}f}"


@dataclass
class Report:
    """Scores of one or more methods against one truth root.

    ``rows`` are ordered by class (registry order, then by name) and by the order of the
    prediction files; ``notes`` holds partial-coverage and other warnings.
    """

    truth_root: str
    split: str | None
    rows: list[ScoreRow]
    notes: list[str] = field(default_factory=list)
    unscored_classes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "metric_version": M.METRIC_VERSION,
            "truth_root": self.truth_root,
            "split": self.split,
            "truth_sets": self.truth_sets(),
            "metrics": {m.name: {"title": m.title, "units": m.units, "paper": m.paper} for m in METRICS},
            "rows": [r.to_dict() for r in self.rows],
            "unscored_truth_classes": self.unscored_classes,
            "notes": self.notes,
        }

    def to_json(self, indent: int = 1) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    def truth_sets(self) -> dict[str, dict]:
        """``{class: {split, path, n_images}}`` of the truth used for each scored class."""
        out = {}
        for r in self.rows:
            out.setdefault(r.class_name, {"split": r.split, "path": r.truth_path, "n_images": r.n_truth})
        return out

    def to_csv(self) -> str:
        """One line per row: identification, counts, then ``<metric>_mean`` / ``<metric>_std``."""
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        head = ["class", "method", "split", "truth", "n_scored", "n_truth", "configuration_units", "metric_version"]
        writer.writerow(head + [f"{m.name}_{s}" for m in METRICS for s in ("mean", "std")])
        for r in self.rows:
            vals = []
            for m in METRICS:
                mean, std = r.metrics.get(m.name, (None, None))
                vals += [_cell(mean), _cell(std)]
            writer.writerow([r.class_name, r.method, r.split, r.truth_path, r.n_scored, r.n_truth, r.configuration_units,
                             M.METRIC_VERSION] + vals)
        return buf.getvalue()

    def format_table(self, standard: bool = True, wide: bool = False) -> str:
        """The paper's Table 1 layout (mean +/- std, n scored / n truth); then the standard metrics.

        Default: lines of at most :data:`TABLE_WIDTH` characters (the standard metrics wrap into
        blocks) with short, unambiguous column names and a legend; ``wide``: one line per row
        with the metric titles of :data:`METRICS`.
        """
        lines = []
        sets = self.truth_sets()
        for c, s in sets.items():
            lines.append(f"truth {c}: split {s['split']!r}, {s['n_images']} images, {s['path']}")
        lines.append("")
        width = max([len(r.label) for r in self.rows] + [len("Standard metrics")])
        paper = [m for m in METRICS if m.paper]

        def title(m):
            return m.title if wide else SHORT_TITLES.get(m.name, m.title)

        def block(head: str, metrics, cells_of, min_w: int) -> list[str]:
            cols = [title(m) for m in metrics]
            rows = [cells_of(r) for r in self.rows]
            colw = [max([len(c), min_w] + [len(row[k]) for row in rows]) for k, c in enumerate(cols)]
            out = [head.ljust(width) + "  " + "  ".join(c.rjust(w) for c, w in zip(cols, colw))]
            out += [r.label.ljust(width) + "  " + "  ".join(c.rjust(w) for c, w in zip(row, colw))
                    for r, row in zip(self.rows, rows)]
            return out

        class _Images:  # the Images column of the paper block
            name, title, units = "images", "Images", ""

        partial = False

        def paper_cells(r):
            nonlocal partial
            cells = []
            for m in paper:
                mean, std = r.metrics[m.name]
                unit = {"deg": " deg", "cm": " cm"}.get(r.configuration_units, "") if m.name == "configuration_error" else ""
                cells.append("-" if math.isnan(mean) else _pm(mean, std) + unit)  # "-": no image defines it
            partial |= not r.complete
            cells.append(f"{r.n_scored}/{r.n_truth}{'' if r.complete else '*'}")
            return cells

        lines += block("", paper + [_Images], paper_cells, 11 if not wide else 20)
        if partial:
            lines.append("* partial coverage: only the predicted images are averaged (n scored / n in the truth split)")
        if standard:
            std_metrics = [m for m in METRICS if not m.paper and any(m.name in r.metrics for r in self.rows)]

            def std_cell(r, m):
                mean, std = r.metrics.get(m.name, (None, None))
                if mean is None or math.isnan(mean):
                    return "-"
                return f"{mean:.3f}" if m.units == "fraction" else _pm(mean, std)

            groups, current = [], []
            for m in std_metrics:  # wrap into blocks that fit the width (all in one block when wide)
                trial = current + [m]
                need = width + sum(2 + max(len(title(x)), 8, *(len(std_cell(r, x)) for r in self.rows)) for x in trial)
                if current and not wide and need > TABLE_WIDTH:
                    groups.append(current)
                    trial = [m]
                current = trial
            if current:
                groups.append(current)
            for g in groups:
                lines.append("")
                lines += block("Standard metrics", g, lambda r, g=g: [std_cell(r, m) for m in g], 8 if not wide else 15)
        if not wide:
            lines.append("")
            lines += TABLE_LEGEND
        if self.unscored_classes:
            lines.append(f"Truth classes without predictions (not scored): {', '.join(self.unscored_classes)}")
        lines += [f"Note: {n}" for n in self.notes]
        lines.append(f"Metric version {M.METRIC_VERSION} (docs/scoring.md); numbers of other versions are not comparable.")
        return "\n".join(lines)


def align(pred_ids: np.ndarray, truth_ids: np.ndarray, where: str, truth_where: str = "") -> np.ndarray:
    """Index into the sorted ``truth_ids`` of each prediction id; unknown ids are a DataFormatError."""
    idx = np.searchsorted(truth_ids, pred_ids)
    idx_c = np.minimum(idx, len(truth_ids) - 1)
    unknown = truth_ids[idx_c] != pred_ids
    if unknown.any():
        raise DataFormatError(f"{where}/sample_id: {int(unknown.sum())} of {len(pred_ids)} ids are not in the truth set "
                              f"{truth_where} (e.g. {int(pred_ids[unknown][0])})")
    return idx_c


def score_class(pred: dict, truth: TruthSet, method: str, predictions_path: str) -> ScoreRow:
    """Score one class of one predictions file against its truth split."""
    where = f"{predictions_path}:/{truth.class_name}"
    idx = align(pred["sample_id"], truth.arrays["sample_id"], where, str(truth.path))
    J_pred, J_true = pred["axis_pose"].shape[1], len(truth.joint_types)
    if J_pred != J_true:
        raise DataFormatError(f"{where}/axis_pose: {J_pred} joints predicted, the truth ({truth.path}) has {J_true}")
    t = {k: v[idx] for k, v in truth.arrays.items()}
    with np.errstate(all="ignore"):  # NaN truth and zero mixture densities are handled as values
        per_image, per_joint = image_metrics(pred, t, truth.joint_types, where)
        metrics, joints, defined, infinite = aggregate(per_image, per_joint)
    return ScoreRow(class_name=truth.class_name, method=method, split=truth.split, truth_path=str(truth.path),
                    predictions_path=str(predictions_path), n_scored=len(idx), n_truth=truth.n_images,
                    joint_types=truth.joint_types, metrics=metrics, per_joint=joints, n_defined=defined,
                    n_infinite=infinite)


def _class_order(name: str) -> tuple:
    from .registry import class_names

    names = class_names()
    return (names.index(name), "") if name in names else (len(names), name)


def score(predictions, truth_path: str | Path, split: str | None = None) -> Report:
    """Score one predictions file (or a list of them) against the truth under ``truth_path``.

    ``truth_path`` is a split folder or a folder with ``<class>/<split>/`` below it; ``split``
    picks the split when a class has several (default :data:`DEFAULT_SPLIT`).  Returns a
    :class:`Report` with one row per (class, method).  Bad input raises :class:`UserError`.
    """
    paths = [predictions] if isinstance(predictions, (str, Path)) else list(predictions)
    if not paths:
        raise UserError("no predictions file given")
    loaded = [(str(p), *read_predictions(p)) for p in paths]
    classes = sorted({c for _, _, per_class in loaded for c in per_class}, key=_class_order)
    sources = {}
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
            row = score_class(pred, truth[cls], method, path)
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
    return Report(truth_root=str(truth_path), split=split, rows=rows, notes=notes, unscored_classes=unscored)
