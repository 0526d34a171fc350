"""A model in the robot's view: every class in scenes, behind occluders and seen by a head camera,
prompted by a click, a box, the mask or nothing, on noise-free and noisy depth.

    python benchmarks/robot_view.py --root work-robot-view --objects 4 --json robot_view.json
    python benchmarks/robot_view.py --root work-robot-view --classes microwave --settings isolated head-kitchen-occ2 \\
        --prompts point box --noise none d435

For every class, setting and noise model the script generates a test split (``artdata generate
--split test --seed SEED``, :data:`SETTINGS` gives each setting's options), then for every prompt
predicts it (``artdata predict --model MODEL --prompt P``: the prompt simulated from the split's
mask, docs/robot_view.md) and scores it with :func:`articulated_dataset.benchmark.score`.  It
prints one table (the fraction of images answered: ``none`` answers only where it finds an
object; axis position cm, configuration deg | cm, 90% interval coverage over the answered
images, and the ratio
of position and configuration to the same class, prompt and noise in the ``isolated`` setting,
measured in the same run) and writes every figure with ``--json``.

Settings: ``isolated`` (the paper's view), ``kitchen``, ``room``, ``occ1``/``occ2``/``occ3`` (1-3
occluders, no scene) and ``head-kitchen-occ2`` (the head camera in a kitchen with 2 occluders).
Noise: ``none``, ``kinect2``, ``d435`` (``artdata generate --noise``).  A split or a prediction that
exists is reused (``--root`` keeps them); ``--overwrite`` redoes them.  A failing command stops the
run with one line ``robot_view: error: ...`` and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from articulated_dataset.core.errors import UserError  # noqa: E402  (imports neither MuJoCo nor torch)

sys.path.insert(0, str(Path(__file__).parent))  # third_party.py beside this script
from third_party import run_artdata, text_grid  # noqa: E402  (run_artdata: artdata in this process)

log = logging.getLogger("robot_view")

#: Setting -> the ``artdata generate`` options that make it.
SETTINGS = {
    "isolated": [],
    "kitchen": ["--scene", "kitchen"],
    "room": ["--scene", "room"],
    "occ1": ["--occluders", "1"],
    "occ2": ["--occluders", "2"],
    "occ3": ["--occluders", "3"],
    "head-kitchen-occ2": ["--camera", "head", "--scene", "kitchen", "--occluders", "2"],
}
#: The setting the ratios compare with.
REFERENCE_SETTING = "isolated"
PROMPTS = ("point", "box", "mask", "none")
NOISE = ("none", "kinect2", "d435")
#: Test seed: unused by the shipped models' training and selection.
DEFAULT_SEED = 2027
DEFAULT_OBJECTS = 4
DEFAULT_IMAGES = 16
#: The figures kept per row (the scorer's metric names).
FIGURES = ("axis_position_error_cm", "configuration_error", "coverage_90")


def split_dir(root: Path, setting: str, noise: str, class_name: str) -> Path:
    return root / "data" / f"{setting}-{noise}" / class_name / "test"


def measure(root: Path, class_name: str, setting: str, noise: str, prompt: str, args) -> dict:
    """Generate (or reuse) the split, predict it with the prompt, score it: the row's figures."""
    from articulated_dataset.benchmark import score

    split = split_dir(root, setting, noise, class_name)
    where = f"{class_name} {setting} {noise}"
    if args.overwrite or not (split / "manifest.json").is_file():
        run_artdata(["generate", "--class", class_name, "--split", "test", "--n", str(args.objects),
                     "--images", str(args.images), "--seed", str(args.seed), "--noise", noise,
                     "--out", str(split.parent.parent), "-q", *(["--overwrite"] if split.exists() else []),
                     *SETTINGS[setting]], where)
    predictions = root / "predictions" / f"{setting}-{noise}-{prompt}-{class_name}.h5"
    if args.overwrite or not predictions.is_file():
        run_artdata(["predict", "--model", args.model, str(split), "--prompt", prompt, "--out", str(predictions),
                     "-q", *(["--overwrite"] if predictions.exists() else [])], f"{where} {prompt}")
    row = score(predictions, split).rows[0]
    figures = {name: float(row.metrics[name][0]) if name in row.metrics else None for name in FIGURES}
    return {"class": class_name, "setting": setting, "noise": noise, "prompt": prompt, "images": row.n_truth,
            "answered": row.n_scored / row.n_truth, "configuration_units": row.configuration_units, **figures}


def add_ratios(rows: list[dict]) -> None:
    """Each row's position and configuration over the same class, noise and prompt in the
    reference setting (None where that row is missing)."""
    ref = {(r["class"], r["noise"], r["prompt"]): r for r in rows if r["setting"] == REFERENCE_SETTING}
    for r in rows:
        base = ref.get((r["class"], r["noise"], r["prompt"]))
        for key, name in (("position_ratio", "axis_position_error_cm"), ("configuration_ratio", "configuration_error")):
            ok = base is not None and base[name] and r[name] is not None
            r[key] = r[name] / base[name] if ok else None


def format_table(rows: list[dict]) -> str:
    """The fixed-width table the script prints."""
    titles = ["class", "setting", "noise", "prompt", "images", "answered", "pos cm", "config", "cov90", "pos x", "config x"]

    def num(v, fmt="{:.2f}"):
        return "-" if v is None else fmt.format(v)

    body = [[r["class"], r["setting"], r["noise"], r["prompt"], str(r["images"]),
             num(r.get("answered", 1.0), "{:.3f}"), num(r["axis_position_error_cm"]),
             num(r["configuration_error"]) + " " + r["configuration_units"], num(r["coverage_90"], "{:.3f}"),
             num(r["position_ratio"]), num(r["configuration_ratio"])] for r in rows]
    return text_grid(titles, body, 4)


def parse_args(argv=None) -> argparse.Namespace:
    from articulated_dataset.classes.registry import class_names

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--root", type=Path, required=True, help="work folder: ROOT/data, ROOT/predictions")
    p.add_argument("--classes", nargs="+", default=None, choices=class_names(), help="default: every class")
    p.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    p.add_argument("--prompts", nargs="+", default=list(PROMPTS), choices=PROMPTS)
    p.add_argument("--noise", nargs="+", default=list(NOISE), choices=NOISE)
    p.add_argument("--model", default="dense", help="a shipped dense model or a dense checkpoint")
    p.add_argument("--objects", type=int, default=DEFAULT_OBJECTS, help="test objects per class and setting")
    p.add_argument("--images", type=int, default=DEFAULT_IMAGES, help="images per object")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED, help="test split seed")
    p.add_argument("--json", type=Path, default=None, help="write every row here")
    p.add_argument("--overwrite", action="store_true", help="regenerate splits and predictions that exist")
    args = p.parse_args(argv)
    args.classes = args.classes or class_names()
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    from articulated_dataset.core.safeio import atomic_write_text

    settings = list(dict.fromkeys([REFERENCE_SETTING, *args.settings]))  # the ratios need the reference
    try:
        for name in ("objects", "images"):
            if getattr(args, name) < 1:
                raise UserError(f"--{name} must be at least 1, got {getattr(args, name)}")
        rows = [measure(args.root, c, s, n, p, args)
                for c in args.classes for s in settings for n in args.noise for p in args.prompts]
        add_ratios(rows)
        if args.json is not None:
            doc = {"settings": {s: SETTINGS[s] for s in settings}, "seed": args.seed, "objects": args.objects,
                   "images": args.images, "model": args.model, "rows": rows}
            atomic_write_text(args.json, json.dumps(doc, indent=1, allow_nan=False) + "\n")
    except UserError as exc:
        print(f"robot_view: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    print(f"model {args.model}, {args.objects} object(s) x {args.images} images per class and setting, "
          f"seed {args.seed}; ratios against the {REFERENCE_SETTING} setting\n")
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
