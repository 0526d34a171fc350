"""The ``--small`` MDN against the NN baseline, per class, on a CPU.

For each class: (optionally) generate ``--train-objects`` training and ``--test-objects``
test objects, train the ``small`` preset on the whole training split (``artdata train
--small``), predict the test split (``artdata predict``), run the NN baseline on the same
splits, score both with the benchmark scorer and print one table: the paper's three
errors (mean over test images) for MDN and NN, whether the MDN beats NN on position and on
configuration, and the training time and epochs.

    python benchmarks/train_small.py --root /tmp/artdata_bench --generate            # 1,000 / 200 objects
    python benchmarks/train_small.py --root /tmp/artdata_bench --classes cabinet,drawer --epochs 8

Outputs (checkpoints, predictions, JSON summary) go to ``--out`` (default ROOT/_mdn_small).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

from articulated_dataset.core.pool import configure_allocator, configure_openmp_wait  # noqa: E402

configure_openmp_wait()  # before torch loads its OpenMP runtime: the commands' wait policy
configure_allocator()  # and their allocator settings

PAPER_METRICS = ("axis_position_error_cm", "axis_rotation_error_deg", "configuration_error")


def ensure_split(root: Path, class_name: str, split: str, n_objects: int, workers: int, generate: bool) -> Path:
    from articulated_dataset.format import read_manifest
    from articulated_dataset.generation import GenerationConfig, generate_split, split_dir_for

    config = GenerationConfig(class_name, split=split, n_objects=n_objects)
    split_dir = Path(split_dir_for(root, config))
    if (split_dir / "manifest.json").is_file() and read_manifest(split_dir).get("complete"):
        return split_dir
    if not generate:
        raise SystemExit(f"{split_dir}: missing; pass --generate or run: artdata generate --class {class_name} "
                         f"--split {split} --n {n_objects} --out {root}")
    t0 = time.perf_counter()
    generate_split(config, root, workers=workers, resume=True, progress=True)
    print(f"generated {split_dir} in {time.perf_counter() - t0:.0f} s", flush=True)
    return split_dir


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, required=True, help="data root holding <class>/{train,test}")
    ap.add_argument("--classes", default=None, help="comma-separated (default: every registered class)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--generate", action="store_true", help="generate missing splits")
    ap.add_argument("--train-objects", type=int, default=1000)
    ap.add_argument("--test-objects", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2, help="generation / NN workers")
    ap.add_argument("--epochs", type=int, default=None, help="default: the small preset's")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--estimate", default="mean-of-best", choices=["mean-of-best", "mode"])
    ap.add_argument("--retrain", action="store_true", help="train again even if a finished checkpoint exists")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args()

    import torch

    from articulated_dataset.benchmark.predictions import write_predictions
    from articulated_dataset.benchmark.scoring import score
    from articulated_dataset.classes.registry import class_names
    from articulated_dataset.methods.baselines import run_baseline
    from articulated_dataset.methods.mdn.checkpoint import load_checkpoint
    from articulated_dataset.methods.mdn.config import TrainConfig
    from articulated_dataset.methods.mdn.predict import predict_split
    from articulated_dataset.methods.mdn.train import configure_threads, train

    threads = configure_threads(args.threads)
    classes = args.classes.split(",") if args.classes else list(class_names())
    out = args.out or args.root / "_mdn_small"
    out.mkdir(parents=True, exist_ok=True)
    print(f"torch {torch.__version__}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"{threads} torch threads, load average {os.getloadavg()[0]:.1f}", flush=True)
    results = {}
    for c in classes:
        train_dir = ensure_split(args.root, c, "train", args.train_objects, args.workers, args.generate)
        test_dir = ensure_split(args.root, c, "test", args.test_objects, args.workers, args.generate)
        model = out / f"{c}.pt"
        if args.retrain and model.exists():
            model.unlink()
        cfg = TrainConfig(class_name=c, preset="small", epochs=args.epochs, seed=args.seed)
        t0 = time.perf_counter()
        if model.exists() and load_checkpoint(model).get("finished"):
            ckpt = load_checkpoint(model)
            train_s = sum(h["seconds"] for h in ckpt["history"])
            print(f"{c}: reusing {model}", flush=True)
        else:
            ckpt = train(train_dir, model, cfg, resume=model.exists(), progress=not args.quiet,
                         echo=lambda line, c=c: print(f"{c}: {line}", flush=True))
            train_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        _, arrays = predict_split(model, test_dir, estimate=args.estimate, progress=not args.quiet)
        predict_s = time.perf_counter() - t1
        mdn_h5, nn_h5 = out / f"{c}-mdn.h5", out / f"{c}-nn.h5"
        write_predictions(mdn_h5, "MDN-small", {c: arrays}, attrs={"estimate": args.estimate})
        t2 = time.perf_counter()
        run_baseline("nn", train_dir, test_dir, nn_h5, workers=args.workers, progress=not args.quiet)
        nn_s = time.perf_counter() - t2
        report = score([str(mdn_h5), str(nn_h5)], test_dir)
        print(report.format_table(), flush=True)
        rows = {r.method: r for r in report.rows}
        results[c] = {
            "mdn": {m: rows["MDN-small"].metrics[m] for m in PAPER_METRICS},
            "nn": {m: rows["NN"].metrics[m] for m in PAPER_METRICS},
            "mdn_extra": {m: rows["MDN-small"].metrics[m] for m in ("nll", "coverage_50", "coverage_90", "chirality_accuracy")
                          if m in rows["MDN-small"].metrics},
            "config_units": rows["MDN-small"].configuration_units,
            "epochs": ckpt["epoch"], "n_train_images": ckpt["data"]["n_train"], "n_val_images": ckpt["data"]["n_val"],
            "train_s": train_s, "predict_s": predict_s, "nn_s": nn_s, "n_test_images": rows["MDN-small"].n_scored,
        }
        (out / "summary.json").write_text(json.dumps(results, indent=1))

    print("\nSmall MDN vs NN (mean error over test images; MDN wins where marked *)")
    print(f"{'class':13s} {'MDN pos cm':>10s} {'NN pos cm':>10s} {'MDN rot deg':>11s} {'NN rot deg':>10s} "
          f"{'MDN config':>10s} {'NN config':>10s} {'units':>5s} {'epochs':>6s} {'train s':>7s}")
    for c, r in results.items():
        mp, np_ = r["mdn"]["axis_position_error_cm"][0], r["nn"]["axis_position_error_cm"][0]
        mr, nr = r["mdn"]["axis_rotation_error_deg"][0], r["nn"]["axis_rotation_error_deg"][0]
        mc, nc = r["mdn"]["configuration_error"][0], r["nn"]["configuration_error"][0]
        print(f"{c:13s} {mp:>9.2f}{'*' if mp < np_ else ' '} {np_:>10.2f} {mr:>10.2f}{'*' if mr < nr else ' '} {nr:>10.2f} "
              f"{mc:>9.2f}{'*' if mc < nc else ' '} {nc:>10.2f} {r['config_units']:>5s} {r['epochs']:>6d} {r['train_s']:>7.0f}")
    beats = all(r["mdn"]["axis_position_error_cm"][0] < r["nn"]["axis_position_error_cm"][0]
                and r["mdn"]["configuration_error"][0] < r["nn"]["configuration_error"][0] for r in results.values())
    print(f"\nMDN-small beats NN on position and configuration for every class run: {beats}")
    print(f"summary: {out / 'summary.json'}")


if __name__ == "__main__":
    main()
