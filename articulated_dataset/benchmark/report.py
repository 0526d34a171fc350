"""The score report: the metric table (names, titles, units), one :class:`ScoreRow` per
(class, method) aggregated over images, and the :class:`Report` that prints the paper's
Table 1 layout and serialises to JSON and CSV.  :mod:`articulated_dataset.benchmark.scoring`
fills it; the formulas are in :mod:`articulated_dataset.benchmark.metrics` and docs/scoring.md.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field

import numpy as np

from ..format.schema import PRISMATIC, REVOLUTE
from . import metrics as M


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
