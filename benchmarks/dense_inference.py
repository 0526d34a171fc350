"""Inference speed of the dense estimator on this machine.

    python benchmarks/dense_inference.py [--model dense|PATH] [--class microwave] [--threads 2] [--batch 128]

Prints images/s of (a) the network alone on ready inputs, (b) the whole batched pipeline
from depth images (input features + network + vote modes + mixture), and (c) the
milliseconds of one ``articulated_dataset.estimate`` call (one image, model loaded).  Uses
the shipped weights (or a checkpoint) and rendered test images (a small split is generated
under ``--root`` if needed).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default="dense")
    p.add_argument("--class", dest="class_name", default="microwave")
    p.add_argument("--root", type=Path, default=Path("data-bench-inference"))
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)

    import numpy as np
    import torch

    import articulated_dataset as ad
    from articulated_dataset.models.dense.features import make_inputs
    from articulated_dataset.models.dense.predict import predict_arrays
    from articulated_dataset.models.dense.checkpoint import build_dense_model, load_dense_checkpoint
    from articulated_dataset.models.dense.data import load_dense_split
    from articulated_dataset.models import resolve_model
    from articulated_dataset.generation import GenerationConfig, generate_split

    torch.set_num_threads(args.threads)
    n_objects = max(1, -(-args.batch // 16))
    split = generate_split(GenerationConfig(args.class_name, split="test", n_objects=n_objects, seed=1), args.root,
                           resume=True, progress=False)
    ref = resolve_model(args.model, args.class_name)
    ckpt = load_dense_checkpoint(ref.path)
    model = build_dense_model(ckpt)
    c = model.config
    data = load_dense_split(split, c.n_joints, (c.height_px, c.width_px), with_labels=False)
    idx = np.arange(min(args.batch, len(data.sample_id)))
    with torch.no_grad():
        x = make_inputs(data.depth(idx), torch.from_numpy(data.K[idx]))["x"]
        model(x)
        t0 = time.perf_counter()
        for _ in range(args.repeats):
            model(x)
        net = args.repeats * len(idx) / (time.perf_counter() - t0)
    predict_arrays(model, data, idx, joint_types=ckpt["joint_types"], calibration=ckpt.get("calibration"),
                                        refinement=ckpt.get("refinement"))
    t0 = time.perf_counter()
    for _ in range(args.repeats):
        predict_arrays(model, data, idx, joint_types=ckpt["joint_types"], calibration=ckpt.get("calibration"),
                       refinement=ckpt.get("refinement"), batch_size=args.batch)
    full = args.repeats * len(idx) / (time.perf_counter() - t0)
    import h5py

    with h5py.File(next(split.glob("shard-*.h5")), "r") as f:
        depths, K = f["depth"][:20], f["K"][()]
    ad.estimate(depths[0], K, args.class_name, model=args.model)
    t0 = time.perf_counter()
    for d in depths:
        ad.estimate(d, K, args.class_name, model=args.model)
    one_ms = 1e3 * (time.perf_counter() - t0) / len(depths)
    print(f"{args.class_name} {ref.name}: {torch.get_num_threads()} threads, batch {len(idx)}; "
          f"network {net:.0f} img/s; batched pipeline {full:.0f} img/s; estimate() {one_ms:.1f} ms/image; "
          f"load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
