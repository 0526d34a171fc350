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
import re
import textwrap
from dataclasses import dataclass, field

import numpy as np

from articulated_dataset.benchmark import metrics as M
from articulated_dataset.format.manifest import printable
from articulated_dataset.format.schema import PRISMATIC, REVOLUTE

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
    #: first metric version that reports it
    since: int = 2


CONFIG_UNITS = {REVOLUTE: "deg", PRISMATIC: "cm"}

METRICS: tuple[MetricSpec, ...] = (
    MetricSpec("axis_position_error_cm", "Axis position (cm)", "cm", paper=True),
    MetricSpec("axis_rotation_error_deg", "Frame heading (deg)", "deg", paper=True),
    MetricSpec("configuration_error", "Configuration", "deg (revolute) | cm (prismatic)", paper=True),
    MetricSpec("axis_direction_error_deg", "Axis dir. (deg)", "deg"),
    MetricSpec("axis_line_distance_cm", "Line dist. (cm)", "cm"),
    MetricSpec("axis_position_along_cm", "Along axis (cm)", "cm", since=3),
    MetricSpec("axis_position_across_cm", "Across axis (cm)", "cm", since=3),
    MetricSpec("accuracy_5deg_5cm", "Acc. 5/5", "fraction", since=3),
    MetricSpec("accuracy_10deg_10cm", "Acc. 10/10", "fraction", since=3),
    MetricSpec("opd_success", "OPD succ.", "fraction"),
    MetricSpec("geometry_depth_error_cm", "Depth (cm)", "cm"),
    MetricSpec("geometry_width_error_cm", "Width (cm)", "cm"),
    MetricSpec("geometry_height_error_cm", "Height (cm)", "cm"),
    MetricSpec("chirality_accuracy", "Chirality", "fraction"),
    MetricSpec("mechanism_side_accuracy", "Side", "fraction"),
    MetricSpec("nll", "NLL (nats)", "nats"),
    MetricSpec("coverage_50", "Cov. 50%", "fraction"),
    MetricSpec("coverage_90", "Cov. 90%", "fraction"),
)
METRICS_BY_NAME = {m.name: m for m in METRICS}


def metrics_of_version(version: int) -> tuple[MetricSpec, ...]:
    """The metrics that metric version ``version`` reports, in report order."""
    return tuple(m for m in METRICS if m.since <= version)


#: Below this many objects scored, the table says that its means are uncertain (see the SEM).
FEW_OBJECTS = 100
#: Most characters per line of the default table (``artdata score``; ``--wide`` has no limit).
TABLE_WIDTH = 100
#: What the default table's short names mean (docs/scoring.md has the formulas), per metric version.
TABLE_LEGEND = [
    "Axis position: distance between axis origins. Frame heading: the paper's axis rotation error, the",
    "heading of the axis frame about the camera's vertical (a mirrored door scores 180). Axis dir.: angle",
    "between the axis lines, sign folded. Chirality, Side, OPD succ., Cov.: fractions of images.",
]
TABLE_LEGEND_V3 = [
    "+/-: standard deviation over images. SEM: standard error of the mean over objects (the mean's",
    "uncertainty). Axis position: distance between axis origins; Along/Across axis: its parts along and",
    "across the true axis. Frame heading: the paper's axis rotation error, the heading of the axis frame",
    "about the camera's vertical (a mirrored door scores 180). Axis dir.: angle between the axis lines,",
    "sign folded. Line dist.: distance between the axis lines (hinges). Acc. 5/5, 10/10: fraction of",
    "joints with Axis dir. <= 5 deg and Line dist. <= 5 cm (10/10 cm; drawers: direction only).",
    "OPD succ.: OPD's motion criterion (Axis dir. <= 10 deg, origin within 0.25 box diagonals of the true",
    "hinge line). Chirality: hinge side label; Side: the part on the true side of the axis. NLL (nats):",
    "mixture negative log-likelihood. Cov. 50%/90%: truth inside the central 50%/90% interval.",
    "Chirality, Side, OPD succ., Acc., Cov.: fractions of images.",
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


#: First characters that make a spreadsheet read a CSV cell as a formula (OWASP, CSV injection):
#: ``=HYPERLINK(...)``, ``+``/``-``/``@`` expressions, and a tab or carriage return before them.
FORMULA_START_CHARS = ("=", "+", "-", "@", "\t", "\r")
#: A plain decimal number (``-1.5``, ``+2e-3``): a spreadsheet reads it as a number, not a formula.
_DECIMAL_RE = re.compile(r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")


def _text_cell(text) -> str:
    """A text cell of the CSV report (class, method, split, truth path), which may come from a
    stranger's file: non-printable characters escaped (:func:`~articulated_dataset.format.manifest.printable`),
    and a cell a spreadsheet would evaluate (starting with :data:`FORMULA_START_CHARS`) prefixed
    with ``'`` so that it stays text; a plain number (``-3``) is left as it is."""
    text = str(text)
    if text.startswith(FORMULA_START_CHARS) and not _DECIMAL_RE.fullmatch(text):
        text = "'" + text
    return printable(text)


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
    #: standard error of each mean over objects (:func:`metrics.standard_error_of_mean`): name -> SEM.
    sem: dict[str, float] = field(default_factory=dict)
    #: objects among the scored images
    n_objects: int = 0
    metric_version: int = M.METRIC_VERSION

    @property
    def complete(self) -> bool:
        """True when every image of the truth split was scored (``n_scored == n_truth``)."""
        return self.n_scored == self.n_truth

    @property
    def configuration_units(self) -> str:
        """Units of the configuration error: ``deg`` (revolute joints), ``cm`` (prismatic), or ``mixed (deg | cm)``."""
        units = sorted({CONFIG_UNITS[t] for t in self.joint_types})
        return units[0] if len(units) == 1 else "mixed (deg | cm)"

    @property
    def label(self) -> str:
        """Row label of the printed table: ``Class - method``."""
        return f"{self.class_name.capitalize()} - {self.method}"

    def to_dict(self) -> dict:
        """The row as JSON-ready plain types: identification, counts, each metric's mean, std (and, from metric
        version 3, SEM) with its units, per-joint means and the defined / infinite counts; non-finite values
        cleaned for JSON."""
        v3 = self.metric_version >= 3

        def entry(name: str, mean: float, std: float) -> dict:
            out = {"mean": _clean(mean), "std": _clean(std)}
            if v3:
                out["sem"] = _clean(self.sem.get(name, float("nan")))
            out["units"] = self.configuration_units if name == "configuration_error" else METRICS_BY_NAME[name].units
            return out

        extra = {"n_objects": self.n_objects} if v3 else {}
        return {
            "class": self.class_name,
            "method": self.method,
            "split": self.split,
            "truth": self.truth_path,
            "predictions": self.predictions_path,
            "n_scored": self.n_scored,
            "n_truth": self.n_truth,
            **extra,
            "complete": self.complete,
            "joint_types": list(self.joint_types),
            "configuration_units": self.configuration_units,
            "metrics": {name: entry(name, mean, std) for name, (mean, std) in self.metrics.items()},
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


def standard_errors(per_image: dict, object_index: np.ndarray) -> dict[str, float]:
    """Standard error of each per-image metric's mean over the objects of ``object_index``
    (:func:`metrics.standard_error_of_mean`)."""
    return {name: M.standard_error_of_mean(np.asarray(v, np.float64), object_index) for name, v in per_image.items()}


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
    metric_version: int = M.METRIC_VERSION

    @property
    def metrics(self) -> tuple[MetricSpec, ...]:
        """The metric specifications of this report's metric version."""
        return metrics_of_version(self.metric_version)

    def to_dict(self) -> dict:
        """The report as JSON-ready plain types: metric version, truth root and sets, metric titles and units, rows,
        unscored classes and notes."""
        return {
            "metric_version": self.metric_version,
            "truth_root": self.truth_root,
            "split": self.split,
            "truth_sets": self.truth_sets(),
            "metrics": {m.name: {"title": m.title, "units": m.units, "paper": m.paper} for m in self.metrics},
            "rows": [r.to_dict() for r in self.rows],
            "unscored_truth_classes": self.unscored_classes,
            "notes": self.notes,
        }

    def to_json(self, indent: int = 1) -> str:
        """:meth:`to_dict` as JSON text, indented by ``indent`` spaces."""
        return json.dumps(self.to_dict(), indent=indent)

    def truth_sets(self) -> dict[str, dict]:
        """``{class: {split, path, n_images}}`` of the truth used for each scored class."""
        out: dict[str, dict] = {}
        for r in self.rows:
            out.setdefault(r.class_name, {"split": r.split, "path": r.truth_path, "n_images": r.n_truth})
        return out

    def to_csv(self) -> str:
        """One line per row: identification, counts, then ``<metric>_mean`` / ``<metric>_std`` (and, from
        metric version 3, ``<metric>_sem`` and the ``n_objects`` column)."""
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        v3 = self.metric_version >= 3
        stats = ("mean", "std", "sem") if v3 else ("mean", "std")
        head = ["class", "method", "split", "truth", "n_scored", "n_truth"] + (["n_objects"] if v3 else [])
        head += ["configuration_units", "metric_version"]
        writer.writerow(head + [f"{m.name}_{s}" for m in self.metrics for s in stats])
        for r in self.rows:
            vals = []
            for m in self.metrics:
                mean, std = r.metrics.get(m.name, (None, None))
                vals += [_cell(mean), _cell(std)] + ([_cell(r.sem.get(m.name))] if v3 else [])
            ident: list = [_text_cell(t) for t in (r.class_name, r.method, r.split, r.truth_path)]
            ident += [r.n_scored, r.n_truth] + ([r.n_objects] if v3 else [])
            writer.writerow(ident + [r.configuration_units, self.metric_version] + vals)
        return buf.getvalue()

    def format_table(self, standard: bool = True, wide: bool = False) -> str:
        """The paper's Table 1 layout (mean +/- std, n scored / n truth); then the standard metrics.

        Default: lines of at most :data:`TABLE_WIDTH` characters (the standard metrics wrap into
        blocks); ``wide``: the standard metrics of a row on one line.  Both name each metric by
        its title in :data:`METRICS` (the names of every output) and end with the legend.
        """
        lines = []
        sets = self.truth_sets()
        for c, s in sets.items():
            lines.append(f"truth {c}: split {s['split']!r}, {s['n_images']} images, {s['path']}")
        lines.append("")
        width = max([len(r.label) for r in self.rows] + [len("Standard metrics")])
        paper = [m for m in METRICS if m.paper]

        def title(m):
            return m.title

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
        if self.metric_version >= 3:
            class _Objects:  # the Objects column of the SEM block
                name, title, units = "objects", "Objects", ""

            def sem_cells(r):
                cells = []
                for m in paper:
                    sem = r.sem.get(m.name, float("nan"))
                    cells.append("-" if math.isnan(sem) else f"{sem:.2f}")
                return cells + [str(r.n_objects)]

            lines.append("")
            lines += block("SEM", paper + [_Objects], sem_cells, 11 if not wide else 20)
            few = [r.label for r in self.rows if r.n_objects < FEW_OBJECTS]
            if few:
                lines += textwrap.wrap(f"Fewer than {FEW_OBJECTS} objects scored ({', '.join(few)}): each mean is "
                                       f"uncertain by about its SEM; compare methods on the same objects.",
                                       TABLE_WIDTH)
        if standard:
            std_metrics = [m for m in self.metrics if not m.paper and any(m.name in r.metrics for r in self.rows)]

            def std_cell(r, m):
                mean, std = r.metrics.get(m.name, (None, None))
                if mean is None or math.isnan(mean):
                    return "-"
                return f"{mean:.3f}" if m.units == "fraction" else _pm(mean, std)

            groups: list[list[MetricSpec]] = []
            current: list[MetricSpec] = []
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
        lines.append("")
        lines += TABLE_LEGEND_V3 if self.metric_version >= 3 else TABLE_LEGEND
        if self.unscored_classes:
            lines += textwrap.wrap(f"Truth classes without predictions (not scored): {', '.join(self.unscored_classes)}",
                                   width=TABLE_WIDTH, subsequent_indent="  ")
        lines += [f"Note: {n}" for n in self.notes]
        lines.append(f"Metric version {self.metric_version} (docs/scoring.md); numbers of other versions are not comparable.")
        return "\n".join(printable(line) for line in lines)  # folder and split names from the data: escaped
