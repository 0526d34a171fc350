"""The dense estimator on each generation setting: generate, optionally mask, predict, score.

For every class and setting (the paper's default; ``--scene kitchen|room``; ``--occluders 2``;
both; ``--camera head``; ``--table realistic``; ``--intrinsics d435``) this generates a small test
split with ``artdata generate``, predicts it with ``artdata predict`` (the shipped dense model,
trained on the paper's setting, or any checkpoint given with ``--models``) and scores it with
``artdata score``, then prints one Markdown table per metric: axis position (cm), axis rotation
(deg, the paper's frame heading), configuration (deg; drawer cm) and 90% interval coverage.

For settings with a scene or occluders it also scores the model "with the object's mask": a
robot would segment the object first, so a copy of the split is written with the depth zeroed
wherever the stored mask is not the object's (codes 1 .. 1 + J: body and moving parts; scene
255, occluders 254 and background 0 are dropped) and predicted in the same way, against the same
truth.  ``artdata predict`` itself uses every pixel with a depth return, scene included.

    python benchmarks/settings.py                                   # microwave, 10 objects, every setting
    python benchmarks/settings.py --root /tmp/settings --objects 50 --classes all
    python benchmarks/settings.py --classes microwave --settings default kitchen+occluders2 \\
        --models dense runs/dense-microwave-kitchen.pt              # a checkpoint beside the shipped model

Splits, masked copies and predictions stay under ``--root`` and are reused by a later run with
the same settings (an existing split is kept when complete with the same object count; an
existing predictions file is kept unless ``--overwrite``).  Everything runs one process, one
torch thread (``--threads``) by default: the machines these figures come from are shared.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np

CLASSES = ("cabinet", "drawer", "microwave", "toaster", "cabinet2", "refrigerator")
#: Setting name -> extra ``artdata generate`` options.
SETTINGS: dict[str, list[str]] = {
    "default": [],
    "kitchen": ["--scene", "kitchen"],
    "room": ["--scene", "room"],
    "occluders2": ["--occluders", "2"],
    "kitchen+occluders2": ["--scene", "kitchen", "--occluders", "2"],
    "head": ["--camera", "head"],
    "realistic": ["--table", "realistic"],
    "d435": ["--intrinsics", "d435", "--resolution", "640x360"],
}
#: Settings whose images hold pixels that are not the object's (scored masked too).
MASKABLE = ("kitchen", "room", "occluders2", "kitchen+occluders2")
#: Mask codes of the object: 1 body, 2 + j moving part j (format/schema.py).
MASK_BODY = 1
METRICS = (("axis_position_error_cm", "Axis position (cm)"),
           ("axis_rotation_error_deg", "Axis rotation (deg, frame heading)"),
           ("configuration_error", "Configuration (deg; drawer cm)"),
           ("coverage_90", "90% interval coverage"))
SPLIT = "test"


def artdata(*args: str, quiet: bool = True) -> None:
    """Run one ``artdata`` command of this environment; stop with its output if it fails."""
    cmd = [sys.executable, "-m", "articulated_dataset.cli", *args]
    res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")})
    if res.returncode != 0:
        sys.exit(f"failed ({res.returncode}): artdata {' '.join(args)}\n{res.stdout[-2000:]}{res.stderr[-2000:]}")
    if not quiet and res.stdout.strip():
        print(res.stdout.rstrip())


def split_is_complete(split_dir: Path, objects: int) -> bool:
    try:
        manifest = json.loads((split_dir / "manifest.json").read_text())
    except (OSError, ValueError):
        return False
    return bool(manifest.get("complete")) and int(manifest.get("n_objects", -1)) == objects


def generate(root: Path, setting: str, class_name: str, objects: int, seed: int, workers: int) -> Path:
    """The setting's test split of ``class_name`` (generated unless already there)."""
    out = root / setting
    split_dir = out / class_name / SPLIT
    if not split_is_complete(split_dir, objects):
        artdata("generate", "--class", class_name, "--n", str(objects), "--split", SPLIT, "--seed", str(seed),
                "--out", str(out), "--workers", str(workers), "--overwrite", "-q", *SETTINGS[setting])
    return split_dir


def object_only(depth: np.ndarray, mask: np.ndarray, n_joints: int) -> tuple[np.ndarray, np.ndarray]:
    """``depth`` and ``mask`` with 0 (no return, background) wherever ``mask`` is not the
    object's (body or a moving part): what a robot has after segmenting the object."""
    keep = (mask >= MASK_BODY) & (mask <= MASK_BODY + n_joints)
    return np.where(keep, depth, np.zeros_like(depth)), np.where(keep, mask, np.zeros_like(mask))


def masked_copy(split_dir: Path, dest: Path) -> Path:
    """A copy of the split whose depth and mask keep the object's pixels only (labels unchanged;
    the manifest's shard checksums are those of the copied files, so ``artdata verify`` reads it).  Written beside ``dest`` and
    renamed into place; an existing copy of the same split is reused."""
    manifest = json.loads((split_dir / "manifest.json").read_text())
    if (dest / "manifest.json").exists():
        old = json.loads((dest / "manifest.json").read_text())
        if old.get("masked_from") == [s["sha256"] for s in manifest["shards"]]:
            return dest
        shutil.rmtree(dest)
    tmp = dest.with_name(dest.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    shards = []
    for entry in manifest["shards"]:
        path = tmp / entry["file"]
        shutil.copyfile(split_dir / entry["file"], path)
        with h5py.File(path, "r+") as f:
            n_joints = int(f.attrs["n_joints"])
            depth, mask = object_only(f["depth"][()], f["mask"][()], n_joints)
            f["depth"][...] = depth
            f["mask"][...] = mask
        data = path.read_bytes()
        shards.append({**entry, "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()})
    copy = {**manifest, "shards": shards, "masked_from": [s["sha256"] for s in manifest["shards"]]}
    (tmp / "manifest.json").write_text(json.dumps(copy, indent=1, sort_keys=True) + "\n")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp.rename(dest)
    return dest


def model_name(model: str) -> str:
    return model if not model.endswith(".pt") else Path(model).stem


def predict_and_score(model: str, data_dir: Path, truth_dir: Path, preds: Path, threads: int, overwrite: bool) -> dict:
    """Predict ``data_dir`` with ``model`` (unless ``preds`` exists) and score it against ``truth_dir``."""
    if overwrite or not preds.exists():
        preds.parent.mkdir(parents=True, exist_ok=True)
        artdata("predict", "--model", model, str(data_dir), "--out", str(preds), "--threads", str(threads),
                "--device", "cpu", "--overwrite", "-q")
    table = preds.with_suffix(".csv")
    artdata("score", str(preds), "--truth", str(truth_dir), "--csv", str(table))
    with open(table, newline="") as f:
        row = next(csv.DictReader(f))
    return {k: float(row[f"{k}_mean"]) for k, _ in METRICS} | {"images": int(row["n_scored"])}


def run(args) -> list[dict]:
    root = Path(args.root)
    rows = []
    for class_name in args.classes:
        for setting in args.settings:
            t0 = time.perf_counter()
            split_dir = generate(root, setting, class_name, args.objects, args.seed, args.workers)
            inputs = [("", split_dir)]
            if setting in MASKABLE and not args.no_mask:
                inputs.append((" (object mask)", masked_copy(split_dir, root / f"{setting}-masked" / class_name / SPLIT)))
            for model in args.models:
                for suffix, data_dir in inputs:
                    tag = "masked" if suffix else "raw"
                    preds = root / "predictions" / model_name(model) / f"{class_name}-{setting}-{tag}.h5"
                    scores = predict_and_score(model, data_dir, split_dir, preds, args.threads, args.overwrite)
                    rows.append({"class": class_name, "setting": setting + suffix, "model": model_name(model), **scores})
            print(f"{class_name} {setting}: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return rows


def markdown(rows: list[dict]) -> str:
    """One Markdown table per metric: a row per (setting, model), a column per class (the model
    column only when there are several models)."""
    classes = list(dict.fromkeys(r["class"] for r in rows))
    several = len({r["model"] for r in rows}) > 1
    lines = []
    for key, title in METRICS:
        lines += [f"**{title}**", "", "| setting | " + ("model | " if several else "") + " | ".join(classes) + " |",
                  "|---|" + ("---|" if several else "") + "---|" * len(classes)]
        for setting, model in dict.fromkeys((r["setting"], r["model"]) for r in rows):
            cells = []
            for c in classes:
                r = next((r for r in rows if (r["class"], r["setting"], r["model"]) == (c, setting, model)), None)
                cells.append("-" if r is None else f"{r[key]:.3f}" if key == "coverage_90" else f"{r[key]:.2f}")
            lines.append(f"| {setting} | " + (f"{model} | " if several else "") + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", default="data-settings", help="Folder for the splits, masked copies and predictions.")
    p.add_argument("--objects", type=int, default=10, help="Test objects per class and setting (16 images each).")
    p.add_argument("--seed", type=int, default=2026, help="Test seed (the shipped models never saw 2026).")
    p.add_argument("--classes", nargs="+", default=["microwave"], help=f"Classes, or 'all' ({', '.join(CLASSES)}).")
    p.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS), metavar="SETTING",
                   help=f"Settings (default: all of {', '.join(SETTINGS)}).")
    p.add_argument("--models", nargs="+", default=["dense"],
                   help="Models for 'artdata predict --model': dense (the shipped one) and/or checkpoint files.")
    p.add_argument("--no-mask", action="store_true", help="Skip the object-mask variants of scene/occluder settings.")
    p.add_argument("--threads", type=int, default=1, help="torch threads of artdata predict.")
    p.add_argument("--workers", type=int, default=1, help="Worker processes of artdata generate.")
    p.add_argument("--overwrite", action="store_true", help="Predict again even where a predictions file exists.")
    p.add_argument("--json", help="Also write the rows as JSON to this file.")
    args = p.parse_args(argv)
    if args.classes == ["all"]:
        args.classes = list(CLASSES)
    unknown = sorted(set(args.classes) - set(CLASSES))
    if unknown or args.objects < 1:
        p.error(f"unknown classes {unknown}" if unknown else "--objects must be >= 1")
    rows = run(args)
    if args.json:
        tmp = Path(args.json + ".partial")
        tmp.write_text(json.dumps(rows, indent=1) + "\n")
        tmp.replace(args.json)
    print(markdown(rows))


if __name__ == "__main__":
    main()
