"""Reproduce the paper's Table 1 (simulation results) in one command.

For every class (default: all six), at a chosen scale:

1. generate (or reuse) ``ROOT/<class>/train``, ``ROOT/<class>/test`` and the mean object
   ``ROOT/<class>/mean`` (``generate_split`` with ``resume``: a finished split is reused, an
   interrupted one continued; a split generated with other settings is an error);
2. run the baselines (Mean, NN, ICP: :mod:`articulated_dataset.methods.baselines`) and, if asked,
   the reference MDN (``--mdn-model CLASS=CKPT`` / ``--mdn-dir DIR`` holding ``<class>.pt``,
   or ``--train-mdn`` to train ``artdata train --small`` per class first), each writing
   ``ROOT/table1-predictions/<class>-<method>.h5``;
3. score everything with :func:`articulated_dataset.benchmark.score` against the test splits;
4. print our Table 1 beside the paper's (mean +/- std; ratio = our mean / paper mean per
   cell) and write ``OUT/table1.md`` and ``OUT/table1.json`` (OUT defaults to ROOT).

Scales: ``--small`` = 300 training / 50 test objects per class (minutes on 2 cores);
``--full`` = the paper's 10,000 / 1,000 objects (160,000 / 16,000 images) per class; or
``--train-objects N --test-objects M``.

``--framing table4|whole`` is ``artdata generate --framing`` of the training and test splits
(docs/generation.md, Framing): the default draws poses from Table 4's ranges, ``whole`` only
poses that keep the whole object in view.  The mean object (the centre of the table's ranges)
is the same for both.  Each framing needs its own ``--root`` (default ``data-table1``, and
``data-table1-whole`` for ``whole``): a split of the other framing is refused, not reused.

    python benchmarks/reproduce_table1.py --small --root data-table1
    python benchmarks/reproduce_table1.py --full --root /big/disk/table1 --workers 16
    python benchmarks/reproduce_table1.py --small --root data-table1 --train-mdn
    python benchmarks/reproduce_table1.py --train-objects 1000 --test-objects 1000 --test-seed 2026 \
        --methods mean nn --shipped dense mdn-small --root data-table1k
    python benchmarks/reproduce_table1.py --train-objects 1000 --test-objects 1000 --test-seed 2026 \
        --methods mean nn --shipped dense mdn-small --framing whole --root data-table1k-whole

The paper's microwave NN row repeats its cabinet NN row digit for digit (probably a
typesetting slip); it is shown as printed and flagged.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

#: Paper, Table 1: (class, method) -> ((position cm), (rotation deg), (configuration deg | cm)), each (mean, std).
PAPER_TABLE1 = {
    ("cabinet", "Mean"): ((53.83, 18.36), (10.81, 14.29), (40.62, 26.06)),
    ("cabinet", "NN"): ((18.08, 11.31), (10.39, 12.02), (19.66, 17.30)),
    ("cabinet", "ICP"): ((35.68, 17.36), (34.75, 26.76), (40.58, 26.13)),
    ("cabinet", "MDN"): ((1.84, 4.43), (0.36, 1.03), (1.61, 1.70)),
    ("drawer", "Mean"): ((55.59, 17.98), (11.22, 14.42), (9.75, 5.43)),
    ("drawer", "NN"): ((16.51, 9.99), (8.72, 11.84), (9.89, 8.03)),
    ("drawer", "ICP"): ((22.8, 12.36), (19.33, 25.02), (16.47, 11.16)),
    ("drawer", "MDN"): ((5.23, 3.91), (1.14, 3.38), (4.64, 4.05)),
    ("microwave", "Mean"): ((50.78, 16.73), (11.33, 14.28), (22.74, 12.88)),
    ("microwave", "NN"): ((18.08, 11.31), (10.39, 12.02), (19.66, 17.30)),
    ("microwave", "ICP"): ((21.29, 10.76), (25.3, 20.0), (40.64, 26.14)),
    ("microwave", "MDN"): ((1.28, 1.31), (0.34, 1.58), (1.73, 2.11)),
    ("toaster", "Mean"): ((61.65, 18.58), (11.48, 14.08), (22.75, 12.89)),
    ("toaster", "NN"): ((14.59, 8.37), (10.58, 12.40), (18.79, 20.70)),
    ("toaster", "ICP"): ((16.22, 5.9), (21.26, 20.22), (40.73, 26.15)),
    ("toaster", "MDN"): ((2.33, 1.46), (0.80, 1.60), (3.22, 4.06)),
    ("cabinet2", "Mean"): ((62.43, 20.04), (11.16, 14.41), (42.91, 21.52)),
    ("cabinet2", "NN"): ((17.16, 10.20), (10.81, 11.95), (39.95, 35.99)),
    ("cabinet2", "ICP"): ((19.56, 9.9), (26.22, 22.92), (66.08, 33.77)),
    ("cabinet2", "MDN"): ((3.81, 2.71), (2.14, 4.59), (11.97, 9.56)),
    ("refrigerator", "Mean"): ((108.96, 56.02), (11.17, 14.23), (35.23, 23.09)),
    ("refrigerator", "NN"): ((24.69, 16.00), (8.92, 11.39), (24.07, 32.20)),
    ("refrigerator", "ICP"): ((58.25, 35.16), (27.15, 19.89), (42.3, 29.6)),
    ("refrigerator", "MDN"): ((4.67, 9.17), (0.75, 3.93), (6.59, 11.17)),
}
#: Cells of the paper known to be suspect: (class, method) -> note.
PAPER_NOTES = {
    ("microwave", "NN"): "the paper's microwave NN row repeats its cabinet NN row digit for digit "
                         "(probably a typesetting slip); ratios compare with those numbers as printed",
}
#: Objects per class (train, test) of the named scales.
SCALES = {"small": (300, 50), "full": (10_000, 1_000)}
#: Data root of each framing when --root is not given.
DEFAULT_ROOTS = {"table4": Path("data-table1"), "whole": Path("data-table1-whole")}
BASELINE_METHODS = ("mean", "nn", "icp")
#: Scorer metric keys of the three Table 1 columns, in order.
TABLE1_METRICS = ("axis_position_error_cm", "axis_rotation_error_deg", "configuration_error")
PREDICTIONS_DIR = "table1-predictions"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    scale = p.add_mutually_exclusive_group()
    scale.add_argument("--small", action="store_true", help="300 train / 50 test objects per class (default).")
    scale.add_argument("--full", action="store_true", help="The paper's 10,000 train / 1,000 test objects per class.")
    p.add_argument("--train-objects", type=int, default=None, help="Override the scale's training objects per class.")
    p.add_argument("--test-objects", type=int, default=None, help="Override the scale's test objects per class.")
    p.add_argument("--root", type=Path, default=None,
                   help="Data root (<class>/{train,test,mean}; default: data-table1, data-table1-whole with --framing whole).")
    p.add_argument("--framing", choices=sorted(DEFAULT_ROOTS), default="table4",
                   help="Framing of the train and test splits (artdata generate --framing; default: table4).")
    p.add_argument("--out", type=Path, default=None, help="Folder for table1.md / table1.json (default: ROOT).")
    p.add_argument("--classes", nargs="+", default=None, help="Classes (default: every registered class).")
    p.add_argument("--methods", nargs="+", default=list(BASELINE_METHODS), choices=BASELINE_METHODS,
                   help="Baselines to run (default: all).")
    p.add_argument("--seed", type=int, default=0, help="Dataset seed.")
    p.add_argument("--test-seed", type=int, default=None,
                   help="Seed of the test split (default: --seed); the shipped models were trained on seed 0.")
    p.add_argument("--shipped", nargs="+", default=[], choices=["dense", "mdn-small"],
                   help="Also score these shipped models (artdata models) on the test split.")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="Worker processes (default: all cores).")
    p.add_argument("--mdn-model", action="append", default=[], metavar="CLASS=CKPT",
                   help="Trained MDN checkpoint of a class (repeatable); scored as the reference model.")
    p.add_argument("--mdn-dir", type=Path, default=None, help="Folder holding <class>.pt MDN checkpoints.")
    p.add_argument("--train-mdn", action="store_true",
                   help="Train 'artdata train --small' per class (ROOT/mdn/<class>.pt) when no checkpoint is given.")
    p.add_argument("--quiet", "-q", action="store_true", help="No progress bars.")
    args = p.parse_args(argv)
    n_train, n_test = SCALES["full" if args.full else "small"]
    args.scale = "full" if args.full else "small"
    args.n_train = args.train_objects or n_train
    args.n_test = args.test_objects or n_test
    if args.root is None:
        args.root = DEFAULT_ROOTS[args.framing]
    if args.n_train <= 0 or args.n_test <= 0:
        p.error("object counts must be positive")
    return args


def _mdn_checkpoints(args, classes) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for item in args.mdn_model:
        if "=" not in item:
            sys.exit(f"reproduce_table1: --mdn-model expects CLASS=CKPT, got {item!r}")
        cls, path = item.split("=", 1)
        out[cls] = Path(path)
    if args.mdn_dir is not None:
        for cls in classes:
            cand = args.mdn_dir / f"{cls}.pt"
            if cls not in out and cand.is_file():
                out[cls] = cand
    return out


def generate_class(cls: str, args) -> dict:
    """Generate (or reuse) the train/test splits and the mean object; returns seconds per split."""
    from articulated_dataset.format.manifest import DEFAULT_FRAMING
    from articulated_dataset.generation import GenerationConfig, generate_split

    seconds = {}
    test_seed = args.seed if args.test_seed is None else args.test_seed
    for split, n, mean in (("train", args.n_train, False), ("test", args.n_test, False), ("mean", 1, True)):
        config = GenerationConfig(cls, split="train" if mean else split, n_objects=n,
                                  seed=test_seed if split == "test" else args.seed, mean=mean,
                                  framing=DEFAULT_FRAMING if mean else args.framing)
        t0 = time.perf_counter()
        generate_split(config, args.root, workers=args.workers, resume=True, progress=not args.quiet)
        seconds[split] = time.perf_counter() - t0
    return seconds


def run_mdn(cls: str, ckpt: Path | None, args, pred_dir: Path) -> tuple[Path | None, float]:
    """Predictions of the reference MDN (trained first with --train-mdn); (None, 0) without a model."""
    t0 = time.perf_counter()
    train_dir, test_dir = args.root / cls / "train", args.root / cls / "test"
    if ckpt is None and args.train_mdn:
        ckpt = args.root / "mdn" / f"{cls}.pt"
        if not ckpt.is_file():
            ckpt.parent.mkdir(parents=True, exist_ok=True)
            cmd = ["artdata", "train", "--model", "mdn", "--class", cls, str(train_dir), "--out", str(ckpt), "--small"]
            print("$ " + " ".join(cmd), flush=True)
            subprocess.run(cmd + (["--quiet"] if args.quiet else []), check=True)
    if ckpt is None:
        return None, 0.0
    out = pred_dir / f"{cls}-mdn.h5"
    cmd = ["artdata", "predict", "--model", str(ckpt), str(test_dir), "--out", str(out), "--overwrite"]
    print("$ " + " ".join(cmd), flush=True)
    subprocess.run(cmd + (["--quiet"] if args.quiet else []), check=True)
    return out, time.perf_counter() - t0


def paper_method(method: str) -> str:
    """The paper's row a method compares with (MDN variants and the dense estimator -> the paper's "MDN")."""
    return "MDN" if method.upper().startswith("MDN") or method == "dense" else method


def build_rows(report, timings: dict) -> list[dict]:
    rows = []
    for r in report.rows:
        paper = PAPER_TABLE1.get((r.class_name, paper_method(r.method)))
        cells = []
        for k, name in enumerate(TABLE1_METRICS):
            mean, std = r.metrics[name]
            p = paper[k] if paper else None
            cells.append({"metric": name, "mean": mean, "std": std,
                          "paper_mean": p[0] if p else None, "paper_std": p[1] if p else None,
                          "ratio": (mean / p[0]) if p and p[0] else None})
        rows.append({"class": r.class_name, "method": r.method, "configuration_units": r.configuration_units,
                     "n_scored": r.n_scored, "n_truth": r.n_truth, "cells": cells,
                     "seconds": timings.get((r.class_name, r.method)),
                     "paper_note": PAPER_NOTES.get((r.class_name, paper_method(r.method)))})
    return rows


def _fmt(mean, std) -> str:
    return "-" if mean is None else f"{mean:.2f} +/- {std:.2f}"


def format_markdown(rows: list[dict], header: dict) -> str:
    lines = [
        f"Scale: {header['n_train']} training / {header['n_test']} test objects per class "
        f"(x 16 images), framing {header.get('framing', 'table4')}; seed {header['seed']} "
        f"(test split: seed {header.get('test_seed', header['seed'])}); "
        f"{header['workers']} workers; total {header['total_s']:.0f} s.",
        "",
        "| class | method | position (cm): ours | paper | ratio | rotation (deg): ours | paper | ratio "
        "| configuration: ours | paper | ratio | images | time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    notes = []
    for row in rows:
        cells = []
        for c in row["cells"]:
            ratio = "-" if c["ratio"] is None else f"{c['ratio']:.2f}"
            cells += [_fmt(c["mean"], c["std"]), _fmt(c["paper_mean"], c["paper_std"]), ratio]
        cells[6] += f" {row['configuration_units']}"
        mark = ""
        if row["paper_note"]:
            if row["paper_note"] not in notes:
                notes.append(row["paper_note"])
            mark = f" ({chr(ord('a') + notes.index(row['paper_note']))})"
        secs = "-" if row["seconds"] is None else f"{row['seconds']:.1f}"
        lines.append(f"| {row['class']} | {row['method']}{mark} | " + " | ".join(cells)
                     + f" | {row['n_scored']}/{row['n_truth']} | {secs} |")
    for k, n in enumerate(notes):
        lines.append(f"\n({chr(ord('a') + k)}) {n[0].upper() + n[1:]}.")
    return "\n".join(lines) + "\n"


def format_text(rows: list[dict]) -> str:
    head = f"{'class - method':24s} {'position cm (paper) ratio':>34s} {'rotation deg (paper) ratio':>34s} {'configuration (paper) ratio':>38s}"
    lines = [head]
    for row in rows:
        parts = [f"{row['class']} - {row['method']}".ljust(24)]
        for c in row["cells"]:
            ratio = "  -  " if c["ratio"] is None else f"{c['ratio']:5.2f}"
            paper = "-" if c["paper_mean"] is None else f"{c['paper_mean']:.2f}"
            parts.append(f"{_fmt(c['mean'], c['std']):>17s} ({paper:>6s}) {ratio}".rjust(34))
        lines.append(" ".join(parts) + ("  *" if row["paper_note"] else ""))
    for note in dict.fromkeys(r["paper_note"] for r in rows if r["paper_note"]):
        lines.append(f"* {note}")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    from articulated_dataset.benchmark.scoring import score
    from articulated_dataset.classes.registry import class_names
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.methods.baselines import BASELINES, run_baseline

    classes = args.classes or class_names()
    out_dir = args.out or args.root
    pred_dir = args.root / PREDICTIONS_DIR
    pred_dir.mkdir(parents=True, exist_ok=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    mdn = _mdn_checkpoints(args, classes)
    t_start = time.perf_counter()
    timings: dict = {}
    gen_seconds: dict = {}
    files: list[Path] = []
    try:
        for cls in classes:
            gen_seconds[cls] = generate_class(cls, args)
            print(f"{cls}: data ready ({', '.join(f'{k} {v:.1f} s' for k, v in gen_seconds[cls].items())})", flush=True)
            train_dir, test_dir = args.root / cls / "train", args.root / cls / "test"
            for name in args.methods:
                out = pred_dir / f"{cls}-{name}.h5"
                t0 = time.perf_counter()
                result = run_baseline(name, train_dir, test_dir, out, mean_dir=args.root / cls / "mean",
                                      workers=args.workers, progress=not args.quiet)
                dt = time.perf_counter() - t0
                timings[(cls, BASELINES[name][1])] = dt
                n = len(result.predictions["sample_id"])
                print(f"{cls}: {result.method} on {n} test images in {dt:.1f} s ({1e3 * dt / max(n, 1):.1f} ms/image)",
                      flush=True)
                files.append(out)
            for name in args.shipped:
                out = pred_dir / f"{cls}-shipped-{name}.h5"
                t0 = time.perf_counter()
                cmd = ["artdata", "predict", "--model", name, str(test_dir), "--out", str(out), "--overwrite",
                       "--method", name if name == "dense" else "MDN-small (shipped)"]
                print("$ " + " ".join(cmd), flush=True)
                subprocess.run(cmd + (["--quiet"] if args.quiet else []), check=True)
                timings[(cls, name if name == "dense" else "MDN-small (shipped)")] = time.perf_counter() - t0
                files.append(out)
            mdn_file, dt = run_mdn(cls, mdn.get(cls), args, pred_dir)
            if mdn_file is not None:
                files.append(mdn_file)
                timings[(cls, "MDN")] = dt
        report = score(files, args.root, split="test")
    except UserError as exc:
        print(f"reproduce_table1: error: {exc}", file=sys.stderr)
        return 2
    # MDN rows carry the method name of the checkpoint ("MDN" or "MDN-small"): key timings by class
    for r in report.rows:
        if paper_method(r.method) == "MDN" and (r.class_name, "MDN") in timings:
            timings[(r.class_name, r.method)] = timings[(r.class_name, "MDN")]
    total = time.perf_counter() - t_start
    rows = build_rows(report, timings)
    header = {"scale": args.scale, "n_train": args.n_train, "n_test": args.n_test, "seed": args.seed, "framing": args.framing,
              "test_seed": args.seed if args.test_seed is None else args.test_seed,
              "workers": args.workers, "total_s": total, "root": str(args.root),
              "generation_s": gen_seconds, "cpu_count": os.cpu_count()}
    md = format_markdown(rows, header)
    (out_dir / "table1.md").write_text(md)
    (out_dir / "table1.json").write_text(json.dumps({"header": header, "rows": rows,
                                                     "score_report": report.to_dict()}, indent=1) + "\n")
    print()
    print(format_text(rows))
    print()
    print(f"total {total:.0f} s (generation {sum(sum(v.values()) for v in gen_seconds.values()):.0f} s); "
          f"wrote {out_dir / 'table1.md'} and {out_dir / 'table1.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
