"""A model on third-party objects: generate, predict and score each object of a mapping file.

    python benchmarks/third_party.py objects.json --out work-third-party --model dense
    python benchmarks/third_party.py objects.yaml --out work-third-party --images 16 --json third_party.json
    python benchmarks/third_party.py objects.yaml --out work-third-party --resume

The mapping file (``.json``, ``.yaml``/``.yml`` or ``.toml``) holds one table with the list
``objects``; each entry names one third-party object and the built-in class whose model reads it:

* ``urdf`` (required): the URDF, relative to the mapping file's folder (or absolute);
* ``class`` (required): the built-in class (``predict --as-class``); the entry's joints must be
  the class's joint types, in order;
* ``joints``: the joints to articulate, a list of names or one ``"a,b"`` text (``generate
  --joints``; default: the importer's choice);
* ``scale``: a number or ``"auto:CLASS"`` (``generate --scale``; default 1);
* ``mesh_root``: the folder its meshes may be read from, relative to the mapping file's folder
  (``generate --mesh-root``);
* ``name``: the class name of its split (``generate --class-name``; default ``<folder>-<file
  stem>`` of the URDF).  Names must differ between entries.

For each entry, in file order, the script runs (in this process, the ``artdata`` command line)
``artdata generate --urdf URDF --split test --n OBJECTS --images IMAGES --seed SEED --out
ROOT/data`` and ``artdata predict --model MODEL ROOT/data/NAME/test --as-class CLASS --out
ROOT/predictions/NAME.h5``, then scores the predictions with
:func:`articulated_dataset.benchmark.score` (metric version :data:`METRIC_VERSION`) and reads the
split's masks for the cut-off fraction.  ``--objects`` is ``generate --n``: a URDF is one
geometry, so its "objects" are draws of the pose table (camera placement) and its images the
configurations; the issue's figures use one object of 16 images per URDF.  ``--model`` is a
shipped model or a checkpoint; ``{class}`` in it is replaced by the entry's class.

Each entry's figures and the exact commands go to ``ROOT/results/NAME.json``; ``--resume``
skips the entries whose record there was made with the same settings (and reruns the others,
replacing their partial output); ``--overwrite`` reruns everything.  Without either, an entry
whose output exists stops the run.

Two tables are printed: one row per object (mapping entry: mean over its images), one row per
class (mean over the images of the class's objects).  Columns, per image then averaged (joints
of two-door cabinets averaged first), as ``artdata score`` defines them (docs/scoring.md):

* ``pos cm``: axis position error, the paper's first column;
* ``head deg``: frame heading (the paper's axis rotation error);
* ``config``: configuration error, deg (revolute) or cm (prismatic), the paper's third column;
* ``dir deg``: axis direction error, the angle between the axis lines;
* ``line cm``: distance between the axis lines (revolute joints);
* ``side``: fraction of images whose door lies on the true side of the predicted hinge
  (``mechanism_side_accuracy``; revolute joints);
* ``chiral``: fraction of images with the true hinge-side label (``chirality_accuracy``);
* ``cut-off``: fraction of images where the object (body or a moving part) reaches the image's
  border (:func:`articulated_dataset.format.object_on_border`).

``--json FILE`` writes every record (all metrics of ``artdata score --json`` per object, the
commands, the class means).  A bad mapping file or entry (missing URDF, unknown class...) and a
command that fails stop the run with one line ``third_party: error: ...`` and exit code 2.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import os
import shlex
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from articulated_dataset.core.errors import UserError  # noqa: E402  (imports neither MuJoCo nor torch)

#: Metric version of the scores (:data:`articulated_dataset.benchmark.metrics.METRIC_VERSIONS`).
METRIC_VERSION = 3
#: The split every entry is generated as and predicted from.
SPLIT = "test"
#: Keys an entry of the mapping file may have.
ENTRY_KEYS = ("urdf", "class", "joints", "scale", "mesh_root", "name")
#: Largest mapping file read (bytes): a list of objects, never data.
MAX_MAPPING_BYTES = 1 << 20
#: Defaults of the options.
DEFAULT_MODEL = "dense"
DEFAULT_IMAGES = 16
DEFAULT_OBJECTS = 1
#: Metric keys of ``artdata score`` shown in the tables, with their column titles.
COLUMNS = (("axis_position_error_cm", "pos cm"), ("axis_rotation_error_deg", "head deg"),
           ("configuration_error", "config"), ("axis_direction_error_deg", "dir deg"),
           ("axis_line_distance_cm", "line cm"), ("mechanism_side_accuracy", "side"),
           ("chirality_accuracy", "chiral"))
#: Key and title of the cut-off fraction (not a score metric: read from the split's masks).
CUTOFF_KEY, CUTOFF_TITLE = "cutoff_fraction", "cut-off"
#: Version of the per-entry record (``ROOT/results/NAME.json``); a record of another is redone.
RECORD_VERSION = 1
log = logging.getLogger("third_party")


def read_mapping(path: Path) -> list[dict]:
    """The entries of the mapping file ``path``, checked and with paths resolved against its folder:
    ``{"name", "urdf", "class", "joints" (list or None), "scale" (text or None), "mesh_root"}``.
    Any problem is one :class:`~articulated_dataset.core.errors.UserError` naming the file and entry."""
    from articulated_dataset.classes.registry import class_names
    from articulated_dataset.format.shards import is_class_name
    from articulated_dataset.generation.urdf_import.ranges import default_class_name

    if not path.is_file():
        raise UserError(f"mapping file not found: {path}")
    with open(path, "rb") as f:
        raw = f.read(MAX_MAPPING_BYTES + 1)
    if len(raw) > MAX_MAPPING_BYTES:
        raise UserError(f"mapping file {path} is larger than {MAX_MAPPING_BYTES} bytes")
    import tomllib
    import yaml

    suffix = path.suffix.lower()
    try:
        text = raw.decode("utf-8")
        if suffix in (".yaml", ".yml"):
            data = yaml.safe_load(text)
        elif suffix == ".toml":
            data = tomllib.loads(text)
        else:
            data = json.loads(text)
    except (ValueError, RecursionError, yaml.YAMLError) as exc:  # UTF-8, JSON, TOML and YAML errors
        raise UserError(f"cannot parse mapping file {path}: {' '.join(str(exc).split()) or type(exc).__name__}") from None
    if not isinstance(data, dict) or not isinstance(data.get("objects"), list) or not data["objects"]:
        raise UserError(f"mapping file {path} must hold a table with a non-empty list 'objects'")
    builtins = class_names()
    base = path.resolve().parent
    entries, seen = [], {}
    for i, item in enumerate(data["objects"]):
        where = f"{path}: objects[{i}]"
        if not isinstance(item, dict):
            raise UserError(f"{where}: expected a table of {', '.join(ENTRY_KEYS)}, got {type(item).__name__}")
        unknown = sorted(set(map(str, item)) - set(ENTRY_KEYS))
        if unknown:
            raise UserError(f"{where}: unknown key(s) {', '.join(unknown)} (expected {', '.join(ENTRY_KEYS)})")
        for key in ("urdf", "class"):
            if not isinstance(item.get(key), str) or not item[key]:
                raise UserError(f"{where}: '{key}' (text) is required")
        urdf = base / item["urdf"]
        if not urdf.is_file():
            raise UserError(f"{where}: URDF file not found: {urdf}")
        if item["class"] not in builtins:
            raise UserError(f"{where}: unknown class {item['class']!r} (one of {', '.join(builtins)})")
        joints = item.get("joints")
        if isinstance(joints, str):
            joints = [j.strip() for j in joints.split(",")]
        if joints is not None and (not isinstance(joints, list) or not joints
                                   or not all(isinstance(j, str) and j for j in joints)):
            raise UserError(f"{where}: 'joints' must be a list of joint names or one 'a,b' text")
        scale = item.get("scale")
        if isinstance(scale, bool) or not (scale is None or isinstance(scale, (int, float, str))):
            raise UserError(f"{where}: 'scale' must be a number or 'auto:CLASS'")
        mesh_root = item.get("mesh_root")
        if mesh_root is not None and not isinstance(mesh_root, str):
            raise UserError(f"{where}: 'mesh_root' must be a folder (text)")
        name = item.get("name", default_class_name(urdf))
        if not is_class_name(name) or name in builtins:
            raise UserError(f"{where}: name {str(name)[:80]!r} is not a class name of its own (1-32 characters from "
                            "A-Z a-z 0-9 _ . -, not starting with . or -, not a built-in class)")
        if name in seen:
            raise UserError(f"{where}: name {name!r} is also objects[{seen[name]}]'s; give each entry its own 'name'")
        seen[name] = i
        entries.append({"name": name, "urdf": str(urdf), "class": item["class"], "joints": joints,
                        "scale": None if scale is None else str(scale),
                        "mesh_root": None if mesh_root is None else str(base / mesh_root)})
    return entries


def run_artdata(args: list[str], where: str) -> str:
    """Run ``artdata ARGS`` in this process (one torch import for every command); its standard
    output.  A failure is a UserError naming ``where`` (the entry) and holding the command's line."""
    from articulated_dataset.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main.main(args, prog_name="artdata", standalone_mode=False)
    if code != 0:
        lines = err.getvalue().strip().splitlines()
        message = lines[-1].removeprefix("artdata: error: ") if lines else f"exit code {code}"
        raise UserError(f"{where}: artdata {args[0]} failed: {message}")
    return out.getvalue()


def commands_of(entry: dict, paths: dict, settings: dict, replace: bool) -> list[list[str]]:
    """The ``artdata`` commands (argument lists, without ``artdata``) that make an entry's predictions."""
    generate = ["generate", "--urdf", entry["urdf"], "--class-name", entry["name"], "--split", SPLIT,
                "--n", str(settings["objects"]), "--images", str(settings["images"]), "--seed", str(settings["seed"]),
                "--out", str(paths["data"]), "-q"]
    if entry["joints"]:
        generate += ["--joints", ",".join(entry["joints"])]
    if entry["scale"] is not None:
        generate += ["--scale", entry["scale"]]
    if entry["mesh_root"] is not None:
        generate += ["--mesh-root", entry["mesh_root"]]
    if settings["workers"] is not None:
        generate += ["--workers", str(settings["workers"])]
    model = settings["model"].replace("{class}", entry["class"])
    predict = ["predict", "--model", model, str(paths["split"]), "--as-class", entry["class"],
               "--out", str(paths["predictions"]), "--device", settings["device"], "-q"]
    if replace:
        generate.append("--overwrite")
        predict.append("--overwrite")
    return [generate, predict]


def cutoff_fraction(split_dir: Path) -> tuple[float, int]:
    """Fraction of the split's images where the object reaches the image's border, and the image count."""
    import numpy as np

    from articulated_dataset.format import Split, object_on_border

    flags = []
    with Split(split_dir) as split:
        for shard in split.shards:
            flags.append(object_on_border(shard.read("mask")))
    flags = np.concatenate(flags)
    return float(flags.mean()), int(len(flags))


def entry_paths(root: Path, name: str) -> dict:
    return {"data": root / "data", "split": root / "data" / name / SPLIT,
            "predictions": root / "predictions" / f"{name}.h5", "record": root / "results" / f"{name}.json"}


def run_entry(entry: dict, root: Path, settings: dict, *, resume: bool, overwrite: bool) -> dict:
    """Generate, predict and score one entry (or read its record, with ``resume``); its record."""
    from articulated_dataset.benchmark import score
    from articulated_dataset.core.safeio import atomic_write_text

    paths = entry_paths(root, entry["name"])
    # what the figures depend on (workers and device change the speed only)
    key = {"record_version": RECORD_VERSION, "entry": entry,
           "settings": {k: settings[k] for k in ("model", "images", "objects", "seed")}}
    if paths["record"].is_file():
        try:
            old = json.loads(paths["record"].read_text())
        except ValueError:
            old = None
        if resume and isinstance(old, dict) and old.get("key") == key:
            log.info("%s: done before, skipped (%s)", entry["name"], paths["record"])
            return old
    exists = paths["record"].exists() or paths["split"].exists() or paths["predictions"].exists()
    if exists and not (resume or overwrite):
        raise UserError(f"{entry['name']}: output exists under {root}; pass --resume to keep finished objects "
                        "or --overwrite to redo them")
    commands = commands_of(entry, paths, settings, replace=exists)
    outputs = []
    for args in commands:
        log.info("$ %s", shlex.join(["artdata", *args]))
        outputs.append(run_artdata(args, entry["name"]))
    row = score(paths["predictions"], paths["split"], metric_version=METRIC_VERSION).rows[0]
    cutoff, n_images = cutoff_fraction(paths["split"])
    figures = {name: _finite(row.metrics[name][0]) if name in row.metrics else None for name, _ in COLUMNS}
    figures[CUTOFF_KEY] = cutoff
    counts = {name: row.n_defined.get(name, row.n_scored) for name in figures if figures[name] is not None}
    counts[CUTOFF_KEY] = n_images
    record = {"key": key, "name": entry["name"], "class": entry["class"], "urdf": entry["urdf"],
              "commands": [shlex.join(["artdata", *args]) for args in commands],
              "command_output": outputs,
              "n_images": row.n_scored, "n_objects": row.n_objects, "configuration_units": row.configuration_units,
              "figures": figures, "image_counts": counts, "score": row.to_dict()}
    paths["record"].parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(paths["record"], json.dumps(record, indent=1, allow_nan=False) + "\n")
    return record


def _finite(value: float) -> float | None:
    """``value``, or None where it is NaN or infinite (no image defines it; JSON has no NaN)."""
    import math

    return float(value) if math.isfinite(value) else None


def class_means(records: list[dict]) -> list[dict]:
    """One row per class (first appearance order): each figure's mean over the images of the
    class's objects (each object's mean weighted by its images that define the figure)."""
    out = {}
    for rec in records:
        row = out.setdefault(rec["class"], {"class": rec["class"], "objects": [], "n_images": 0,
                                            "configuration_units": rec["configuration_units"], "_sums": {}})
        row["objects"].append(rec["name"])
        row["n_images"] += rec["n_images"]
        for name, value in rec["figures"].items():
            if value is not None:
                total, n = row["_sums"].get(name, (0.0, 0))
                k = rec["image_counts"][name]
                row["_sums"][name] = (total + value * k, n + k)
    rows = []
    for row in out.values():
        sums = row.pop("_sums")
        row["figures"] = {name: (sums[name][0] / sums[name][1] if sums.get(name, (0, 0))[1] else None)
                          for name in [n for n, _ in COLUMNS] + [CUTOFF_KEY]}
        rows.append(row)
    return rows


def _cell(value, fraction: bool = False) -> str:
    if value is None:
        return "-"
    return f"{value:.3f}" if fraction else f"{value:.2f}"


def format_table(rows: list[dict], leading: list[tuple[str, object]]) -> str:
    """A fixed-width table of ``rows`` (records or class rows): the ``leading`` columns
    ``(title, row -> text)``, the image count, then :data:`COLUMNS` and the cut-off fraction."""
    titles = [t for t, _ in leading] + ["images"] + [t for _, t in COLUMNS] + [CUTOFF_TITLE]
    fractions = {"mechanism_side_accuracy", "chirality_accuracy", CUTOFF_KEY}
    body = []
    for r in rows:
        cells = [str(f(r)) for _, f in leading] + [str(r["n_images"])]
        for name in [n for n, _ in COLUMNS] + [CUTOFF_KEY]:
            cell = _cell(r["figures"].get(name), name in fractions)
            if name == "configuration_error" and cell != "-":
                cell += " " + r["configuration_units"]
            cells.append(cell)
        body.append(cells)
    return text_grid(titles, body, len(leading))


def text_grid(titles: list[str], body: list[list[str]], left: int) -> str:
    """A fixed-width table: the ``titles``, a rule of dashes, then the ``body`` rows; each column as
    wide as its widest cell, two spaces apart, the first ``left`` columns aligned left, the others
    right."""
    widths = [max(len(t), *(len(c[i]) for c in body)) for i, t in enumerate(titles)]

    def line(cells):
        return "  ".join(c.ljust(w) if i < left else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))

    return "\n".join([line(titles), line(["-" * w for w in widths])] + [line(c) for c in body])


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("mapping", type=Path, help="mapping file (.json, .yaml/.yml or .toml) with a list 'objects'")
    p.add_argument("--out", type=Path, required=True, help="work folder: ROOT/data, ROOT/predictions, ROOT/results")
    p.add_argument("--model", default=DEFAULT_MODEL,
                   help="a shipped model or a checkpoint file; {class} is replaced by each entry's class")
    p.add_argument("--images", type=int, default=DEFAULT_IMAGES, help="images (configurations) per object")
    p.add_argument("--objects", type=int, default=DEFAULT_OBJECTS,
                   help="objects per entry (generate --n: draws of the pose table of the same URDF)")
    p.add_argument("--seed", type=int, default=0, help="generate --seed")
    p.add_argument("--workers", type=int, default=None, help="generate --workers (default: generate's)")
    p.add_argument("--device", default="auto", help="predict --device")
    p.add_argument("--json", type=Path, default=None, help="write every figure and command here")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true", help="skip entries already done with the same settings")
    mode.add_argument("--overwrite", action="store_true", help="redo every entry, replacing its output")
    p.add_argument("-v", "--verbose", action="store_true", help="print each command before it runs")
    return p.parse_args(argv)


def run(args: argparse.Namespace) -> dict:
    """Every entry's record and the class means (the ``--json`` document)."""
    for option in ("images", "objects"):
        if getattr(args, option) < 1:
            raise UserError(f"--{option} must be at least 1, got {getattr(args, option)}")
    entries = read_mapping(args.mapping)
    settings = {"model": args.model, "images": args.images, "objects": args.objects, "seed": args.seed,
                "workers": args.workers, "device": args.device}
    records = [run_entry(e, args.out, settings, resume=args.resume, overwrite=args.overwrite) for e in entries]
    return {"mapping": str(args.mapping), "root": str(args.out), "metric_version": METRIC_VERSION,
            "settings": settings, "objects": records, "classes": class_means(records)}


def main(argv=None) -> int:
    args = parse_args(argv)
    # before the commands run: their own logging set-up is then a no-op, so their warnings reach stderr
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    log.setLevel(logging.INFO if args.verbose else logging.WARNING)
    from articulated_dataset.core.safeio import atomic_write_text

    try:
        result = run(args)
        if args.json is not None:
            atomic_write_text(args.json, json.dumps(result, indent=1, allow_nan=False) + "\n")
    except UserError as exc:
        print(f"third_party: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    print(f"model {args.model}, {args.objects} object(s) x {args.images} images per entry, "
          f"metric version {METRIC_VERSION}\n")
    print(format_report(result))
    return 0


def format_report(result: dict) -> str:
    """The two tables the script prints for a ``--json`` document: per object, then per class."""
    return "\n".join([
        "per object (mean over its images)",
        format_table(result["objects"], [("object", lambda r: r["name"]), ("class", lambda r: r["class"])]),
        "\nper class (mean over the images of its objects)",
        format_table(result["classes"], [("class", lambda r: r["class"]), ("objects", lambda r: len(r["objects"]))]),
    ])


if __name__ == "__main__":
    sys.exit(main())
