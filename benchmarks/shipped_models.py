"""Score the shipped models (``artdata models``) on unseen test objects, beside the paper's MDN row.

For every class (default: all six): generate (or reuse) ``ROOT/<class>/test`` with
``--test-objects`` objects from ``--seed`` (default 2026: not the training seed 0 of the
shipped weights), predict it with each shipped model (``--models``, default ``dense
mdn-small``), score with :func:`articulated_dataset.benchmark.score`, and print one table:
axis position (cm), axis rotation (deg), configuration (deg | cm), 90% interval coverage, mean
NLL (nats per image: the scorer's, over the mixture's columns) and inference speed (images/s,
network + aggregation, the split already in memory for dense; in ``predict_split``'s worker
processes where it uses them, their start included).
``--precision bfloat16``: the dense network in bfloat16 (``artdata predict --precision``).
``--noise kinect2``: the same objects rendered through that depth-noise model (``artdata generate
--noise``), under ``ROOT/noise-kinect2/``, for the models meant for real sensors
(``dense-kinect2``) and beside them.  ``--json`` writes every figure.

    python benchmarks/shipped_models.py --root data-shipped --test-objects 1000
    python benchmarks/shipped_models.py --root data-shipped --test-objects 1000 --noise kinect2 --models dense dense-kinect2
    python benchmarks/shipped_models.py --root data-shipped --test-objects 50 --classes microwave
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
from articulated_dataset.core.pool import configure_allocator, configure_openmp_wait  # noqa: E402

configure_openmp_wait()  # before torch loads its OpenMP runtime: the commands' wait policy
configure_allocator()  # and their allocator settings
sys.path.insert(0, str(Path(__file__).resolve().parent))

from reproduce_table1 import PAPER_TABLE1  # noqa: E402

TABLE_METRICS = ("axis_position_error_cm", "axis_rotation_error_deg", "configuration_error")


def format_markdown(models: list[dict], table1_rows: list[dict], paper: dict) -> str:
    """The shipped models' test figures as docs/dense.md shows them: per class, Mean and NN (rows of
    ``benchmarks/reproduce_table1.py``'s JSON), MDN-small and dense (the ``test`` figures that
    ``scripts/ship_weights.py --results`` records in ``models.json`` from this script's ``--json``),
    the paper's MDN (``paper``: reproduce_table1's ``PAPER_TABLE1``), and coverage / NLL.  Position
    cm / rotation deg / configuration; the dense cell is bold where it is at or below the paper's in
    all three."""
    def cell(values):
        return " / ".join(f"{v:.2f}" for v in values)

    shipped = {(m["name"], m["class_name"]): m["test"] for m in models if m.get("test")}
    baseline = {(r["class"], r["method"]): [c["mean"] for c in r["cells"]] for r in table1_rows}
    lines = ["| class | Mean | NN | MDN-small (shipped) | dense (shipped) | paper's MDN | coverage / NLL: dense; MDN-small |",
             "|---|---|---|---|---|---|---|"]
    for c in dict.fromkeys(r["class"] for r in table1_rows):
        dense, small = shipped[("dense", c)], shipped[("mdn-small", c)]
        mdn = [m for m, _ in paper[(c, "MDN")]]
        d = [dense["pos_cm"], dense["rot_deg"], dense["config"]]
        dense_cell = cell(d) if any(a > b for a, b in zip(d, mdn)) else f"**{cell(d)}**"
        lines.append(f"| {c} | {cell(baseline[(c, 'Mean')])} | {cell(baseline[(c, 'NN')])} | "
                     f"{cell([small['pos_cm'], small['rot_deg'], small['config']])} | {dense_cell} | {cell(mdn)} | "
                     f"{dense['coverage_90']:.3f} / {dense['nll']:.1f}; {small['coverage_90']:.3f} / {small['nll']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--root", type=Path, default=Path("data-shipped"))
    p.add_argument("--test-objects", type=int, default=1000)
    p.add_argument("--seed", type=int, default=2026, help="Test split seed (the shipped weights were trained on seed 0).")
    p.add_argument("--classes", nargs="+", default=None)
    p.add_argument("--models", nargs="+", default=["dense", "mdn-small"])
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    p.add_argument("--no-mirror", action="store_true",
                   help="Dense: skip the refinement's mirror image (predict --no-mirror); predictions go to <class>-<model>-no-mirror.h5")
    p.add_argument("--precision", choices=["float32", "bfloat16"], default="float32",
                   help="the dense network's arithmetic (predict --precision)")
    p.add_argument("--noise", default="none", help="render the test objects through this depth-noise model (generate --noise)")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--quiet", "-q", action="store_true")
    args = p.parse_args(argv)

    import torch

    from articulated_dataset.benchmark.predictions import write_predictions
    from articulated_dataset.benchmark.scoring import score
    from articulated_dataset.classes.registry import class_names
    from articulated_dataset.generation import GenerationConfig, generate_split
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.mdn.train import configure_threads

    configure_threads(None)
    classes = args.classes or class_names()
    results = []
    for cls in classes:
        cfg = GenerationConfig(cls, split="test", n_objects=args.test_objects, seed=args.seed, noise=args.noise)
        root = args.root if args.noise == "none" else args.root / f"noise-{args.noise}"
        split_dir = generate_split(cfg, root, workers=args.workers, resume=True, progress=not args.quiet)
        for name in args.models:
            ref = resolve_model(name, cls)
            tag = ("-no-mirror" if args.no_mirror else "") + ("" if args.precision == "float32" else f"-{args.precision}")
            out = root / "predictions" / f"{cls}-{name}{tag}.h5"
            out.parent.mkdir(parents=True, exist_ok=True)
            t0 = time.perf_counter()
            if ref.kind == "dense":
                import numpy as np

                from articulated_dataset.methods.dense.checkpoint import build_inference_model, load_dense_checkpoint
                from articulated_dataset.methods.dense.data import load_dense_split
                from articulated_dataset.methods.dense.mirror import with_mirror
                from articulated_dataset.methods.dense.predict import default_workers, predict_arrays

                ckpt = load_dense_checkpoint(ref.path)
                model = build_inference_model(ckpt, args.precision)
                c = model.config
                data = load_dense_split(split_dir, c.n_joints, (c.height_px, c.width_px), with_labels=False)
                t1 = time.perf_counter()
                arrays = predict_arrays(model, data, np.arange(len(data.sample_id)), joint_types=ckpt["joint_types"],
                                        calibration=ckpt.get("calibration"),
                                        refinement=with_mirror(ckpt.get("refinement"), not args.no_mirror),
                                        workers=default_workers(len(data.sample_id)))
                arrays.pop("spread")
                speed = len(data.sample_id) / (time.perf_counter() - t1)
                method = "dense"
            else:
                from articulated_dataset.methods.mdn.predict import predict_split

                _, arrays = predict_split(ref.path, split_dir, progress=False)
                speed = len(arrays["sample_id"]) / (time.perf_counter() - t0)
                method = "MDN-small"
            write_predictions(out, method, {cls: arrays})
            row = score(out, split_dir).rows[0]
            m = row.metrics
            from articulated_dataset.format import sha256_file

            rec = {"class": cls, "model": name, "method": method, "sha256": sha256_file(ref.path), "n_images": row.n_scored,
                   "mirror": not (args.no_mirror and ref.kind == "dense"),
                   "precision": args.precision if ref.kind == "dense" else "float32",
                   **{k: m[k][0] for k in TABLE_METRICS}, "coverage_90": m.get("coverage_90", (float("nan"),))[0],
                   "nll": m.get("nll", (float("nan"),))[0],
                   "images_per_s": speed, "test_seed": args.seed, "test_objects": args.test_objects, "noise": args.noise,
                   "all_metrics": {k: v[0] for k, v in m.items()}}
            results.append(rec)
            if not args.quiet:
                print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in rec.items() if k != "all_metrics"}),
                      flush=True)
    from articulated_dataset.benchmark.metrics import METRIC_VERSION

    noise = "" if args.noise == "none" else f", depth through the {args.noise} noise model"
    print(f"\nTest: {args.test_objects} objects per class, seed {args.seed}{noise}; scorer metric version {METRIC_VERSION}")
    print(f"{'class':<13} {'model':<13} {'pos cm':>14} {'rot deg':>14} {'config':>14} {'cov90':>6} {'NLL':>10} {'img/s':>7}")
    for r in results:
        paper = PAPER_TABLE1.get((r["class"], "MDN"))
        cells = [f"{r[k]:.2f} ({paper[i][0]:.2f})" if paper else f"{r[k]:.2f}" for i, k in enumerate(TABLE_METRICS)]
        print(f"{r['class']:<13} {r['model']:<13} {cells[0]:>14} {cells[1]:>14} {cells[2]:>14} {r['coverage_90']:>6.3f} "
              f"{r['nll']:>10.4g} {r['images_per_s']:>7.0f}")
    print("(paper's MDN in parentheses; configuration in deg, cm for the drawer)")
    if args.json:
        args.json.write_text(json.dumps({"metric_version": METRIC_VERSION, "results": results}, indent=1))
    torch.set_num_threads(torch.get_num_threads())
    return 0


if __name__ == "__main__":
    sys.exit(main())
