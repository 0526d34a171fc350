"""Time of the dense estimator's inference fit (the end of ``artdata train --model dense``).

    python benchmarks/fit_inference.py [--model dense|PATH] [--class cabinet|all] [--objects 40] [--threads 1]

Runs :func:`articulated_dataset.methods.dense.predict.fit_inference` (the vote modes' split factor,
the refinement's choices among its candidates, the mirror image, the calibration) of the shipped
weights (or a checkpoint) on ``--objects`` labelled objects of a rendered split (generated under
``--root`` with ``--seed`` if needed; a stand-in for a training split's validation objects), and
prints per class the seconds, the images and the refinement chosen.  To compare two versions of
the package, run it with each on the ``PYTHONPATH`` (``PYTHONPATH=old-checkout python
benchmarks/fit_inference.py``), one after the other on the same machine.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default="dense", help="a shipped model's name or a dense checkpoint")
    p.add_argument("--class", dest="class_name", default="cabinet", help="a class, or 'all'")
    p.add_argument("--objects", type=int, default=40, help="labelled objects to fit on (16 images each)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--seed", type=int, default=14, help="the rendered split's seed (not a test seed)")
    p.add_argument("--root", type=Path, default=Path("data-bench-fit"))
    args = p.parse_args(argv)
    import numpy as np
    import torch

    from articulated_dataset.classes.registry import class_names, get_class
    from articulated_dataset.core.pool import configure_allocator
    from articulated_dataset.generation import GenerationConfig, generate_split
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.dense.checkpoint import build_inference_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.predict import fit_inference

    torch.set_num_threads(args.threads)
    configure_allocator()
    print(f"package: {Path(__import__('articulated_dataset').__file__).parent}")
    for name in class_names() if args.class_name == "all" else [args.class_name]:
        split = generate_split(GenerationConfig(name, split="test", n_objects=args.objects, seed=args.seed), args.root,
                               resume=True, progress=False)
        ckpt = load_dense_checkpoint(resolve_model(args.model, name).path)
        model = build_inference_model(ckpt)
        c = model.config
        data = load_dense_split(split, c.n_joints, (c.height_px, c.width_px))
        idx = np.arange(len(data.sample_id))
        t0 = time.perf_counter()
        result = fit_inference(model, data, idx, list(ckpt["joint_types"]), mirror_joints=get_class(name).mirror_joints)
        seconds = time.perf_counter() - t0
        print(f"{name}: {seconds:.1f} s for {len(idx)} images on {args.threads} thread(s); refinement chosen: "
              f"{json.dumps(result['refinement'], sort_keys=True)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
