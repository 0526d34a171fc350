"""Inference speed of the dense estimator on this machine.

    python benchmarks/dense_inference.py [--model dense|PATH] [--class microwave|all] [--threads 2] [--batch 128]
                                         [--batches 3]

Prints, per class, images/s of (a) the network alone on ready inputs, (b) the whole batched
pipeline from depth images (input features + network + vote modes + refinement + mixture) on one
batch and (c) on ``--batches`` batches in a row (the rendered batch repeated: a split's steady
state, where every batch after the first writes its input into the previous one's tensor), and
(d) the milliseconds of one ``articulated_dataset.estimate`` call (one image, model loaded), (e)
images/s of ``--split-batches`` batches predicted as ``artdata predict`` runs a split of that
size (``predict_split``'s worker processes, :func:`~articulated_dataset.methods.dense.predict.default_workers`;
timed once, the workers' start included);
then the batch's milliseconds per stage ("other": the one-batch pipeline's time beyond the
stages: reading the depth, conversions to numpy; where the model uses the mirror image, refinement
step 8, the network's time is also given with its second pass and the outputs' average).  Every figure is the fastest of ``--repeats``
runs after one warm-up run (no one-time cost is timed; on a shared machine the fastest run is the
one least disturbed by other processes).  Uses the shipped weights (or a checkpoint) and
rendered test images (a small split is generated under ``--root`` if needed).
"""

from __future__ import annotations

import argparse
import inspect
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

#: Images of the rendered split per object.
IMAGES_PER_OBJECT = 16
#: estimate() is timed on this many images.
N_SINGLE = 20


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default="dense")
    p.add_argument("--class", dest="class_name", default="microwave", help="a class, or 'all'")
    p.add_argument("--root", type=Path, default=Path("data-bench-inference"))
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--batches", type=int, default=3)
    p.add_argument("--split-batches", type=int, default=32,
                   help="(e): batches predicted as predict_split does, in its worker processes (0: skip)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--no-mirror", action="store_true", help="skip the refinement's mirror image (predict --no-mirror)")
    p.add_argument("--precision", choices=["float32", "bfloat16"], default="float32",
                   help="the network's arithmetic (predict --precision)")
    p.add_argument("--default-allocator", action="store_true",
                   help="leave glibc's malloc as it is (the commands set it to reuse freed memory: "
                        "articulated_dataset.core.pool.configure_allocator)")
    args = p.parse_args(argv)

    from articulated_dataset.core.pool import configure_allocator, configure_openmp_wait

    configure_openmp_wait(args.threads)  # before torch loads its OpenMP runtime: the commands' choice
    if not args.default_allocator:
        configure_allocator()  # and their allocator settings
    import torch

    from articulated_dataset.classes.registry import class_names

    torch.set_num_threads(args.threads)
    for name in class_names() if args.class_name == "all" else [args.class_name]:
        bench_class(args, name)
    return 0


def bench_class(args, class_name: str) -> None:
    import h5py
    import numpy as np
    import torch

    import articulated_dataset as ad
    from articulated_dataset.generation import GenerationConfig, generate_split
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.dense.aggregate import vote_modes
    from articulated_dataset.methods.dense.checkpoint import build_inference_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.features import make_inputs
    from articulated_dataset.methods.dense.predict import default_workers, modes_to_arrays, predict_arrays
    try:  # the pipeline's network call (32 images at a time); a checkout without it calls the model
        from articulated_dataset.methods.dense.predict import network_outputs
    except ImportError:  # pragma: no cover - comparing with older code
        def network_outputs(model, x):
            return model(x)
    from articulated_dataset.methods.dense.refine import apply_refinement, refined_quantities, split_factor_of

    n_objects = max(1, -(-args.batch // IMAGES_PER_OBJECT))
    split = generate_split(GenerationConfig(class_name, split="test", n_objects=n_objects, seed=1), args.root,
                           resume=True, progress=False)
    ref = resolve_model(args.model, class_name)
    ckpt = load_dense_checkpoint(ref.path)
    model = build_inference_model(ckpt, args.precision) if args.precision != "float32" else build_inference_model(ckpt)
    c = model.config
    data = load_dense_split(split, c.n_joints, (c.height_px, c.width_px), with_labels=False)
    idx = np.arange(min(args.batch, len(data.sample_id)))
    try:
        from articulated_dataset.methods.dense.mirror import with_mirror
    except ImportError:  # pragma: no cover - comparing with older code
        def with_mirror(refinement, mirror):
            return refinement
    refinement = with_mirror(ckpt.get("refinement"), not args.no_mirror)
    joint_types = list(ckpt["joint_types"])

    def timed(fn):  # the fastest of the repeats' seconds, after one warm-up call; and its result
        out = fn()
        best = float("inf")
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            out = fn()
            best = min(best, time.perf_counter() - t0)
        return best, out

    with torch.inference_mode():
        t_inputs, inputs = timed(lambda: make_inputs(data.depth(idx), torch.from_numpy(data.K[idx])))
        t_net, out = timed(lambda: network_outputs(model, inputs["x"]))  # as the pipeline runs it
        mirror_joints = getattr(refinement, "mirror_joints", None)
        t_net_pipeline = t_net
        if mirror_joints is not None:  # step 8: the network on the mirror images too, outputs averaged
            t_net_pipeline, out = timed(lambda: network_outputs(model, inputs["x"], mirror_joints))
        parts = model.split(out)
        t_modes, modes = timed(lambda: vote_modes(parts, inputs["points_out"], inputs["weight_out"] > 0,
                                                  split_factor=split_factor_of(refinement)))
        # as the pipeline runs it: the refinement's pixel threshold, only the door angles it reads and,
        # for steps 7 and 9, the doors' handles (measured on the door pixels the refinement gathers)
        refine_options = {} if refinement is None else {"frame_min_prob": getattr(refinement, "frame_min_prob", None)}
        if getattr(refinement, "frame_one_sided", False):  # older code has no one-sided normals
            refine_options["frame_one_sided"] = True
        if getattr(refinement, "frame_strip_elongation", None) is not None:  # older code reads no strip
            refine_options["frame_strip_elongation"] = refinement.frame_strip_elongation
        if hasattr(refinement, "door_angles"):  # pragma: no branch - older code computes every angle
            refine_options["door_angles"] = refinement.door_angles
        handle_deg = None if refinement is None else getattr(refinement, "handle_evidence_max_q_deg",
                                                              getattr(refinement, "handle_max_q_deg", None))
        in_refinement = "handle_max_q_deg" in inspect.signature(refined_quantities).parameters
        if handle_deg is not None and in_refinement:
            refine_options["handle_max_q_deg"] = handle_deg
        t_refine, r = timed(lambda: refined_quantities(parts, inputs, modes, joint_types, **refine_options))
        if handle_deg is not None and not in_refinement:  # pragma: no cover - older code measures them apart
            from articulated_dataset.methods.dense.handle import handle_candidates_evidence

            t_handle, h = timed(lambda: handle_candidates_evidence(parts, inputs, modes, r, joint_types, handle_deg))
            t_refine += t_handle
            r.update(h)
    as_np = lambda d: {k: v.numpy().astype(np.float64) for k, v in d.items()}  # noqa: E731
    t_mixture, _ = timed(lambda: modes_to_arrays(apply_refinement(as_np(modes), as_np(r), refinement, joint_types),
                                                 data.sample_id[idx], model, ckpt.get("calibration")))
    def pipeline(images):
        return predict_arrays(model, data, images, joint_types=joint_types, calibration=ckpt.get("calibration"),
                              refinement=refinement, batch_size=args.batch)

    t_full, _ = timed(lambda: pipeline(idx))
    t_split, _ = timed(lambda: pipeline(np.tile(idx, args.batches)))
    many = np.tile(idx, args.split_batches)
    workers = default_workers(len(many))
    t0 = time.perf_counter()
    if len(many):  # timed once, the workers' start included: what a user's predict of that many images sees
        predict_arrays(model, data, many, joint_types=joint_types, calibration=ckpt.get("calibration"),
                       refinement=refinement, batch_size=args.batch, workers=workers)
    t_many = time.perf_counter() - t0
    with h5py.File(next(split.glob("shard-*.h5")), "r") as f:
        depths, K = f["depth"][:N_SINGLE], f["K"][()]
    options = {"mirror": False} if args.no_mirror else {}
    if args.precision != "float32":
        options["precision"] = args.precision
    ad.estimate(depths[0], K, class_name, model=args.model, **options)
    t0 = time.perf_counter()
    for d in depths:
        ad.estimate(d, K, class_name, model=args.model, **options)
    one_ms = 1e3 * (time.perf_counter() - t0) / len(depths)  # the mean over the images
    n = len(idx)
    print(f"{class_name} {ref.name}: {torch.get_num_threads()} threads, batch {n}, {args.precision}; "
          f"network {n / t_net:.0f} img/s; batched pipeline {n / t_full:.0f} img/s (one batch), "
          f"{args.batches * n / t_split:.0f} img/s ({args.batches} batches); "
          + (f"{len(many)} images as predict_split runs them ({workers} process{'es' if workers > 1 else ''}, "
             f"{max(1, torch.get_num_threads() // workers)} thread(s) each, their start included): "
             f"{len(many) / t_many:.0f} img/s; " if len(many) else "")
          + f"estimate() {one_ms:.1f} ms/image; "
          f"load average {os.getloadavg()[0]:.1f}; OpenMP wait: {wait_policy()}")
    other = t_full - (t_inputs + t_net_pipeline + t_modes + t_refine + t_mixture)
    network = f"network {1e3 * t_net:.0f}" + ("" if mirror_joints is None else
                                              f" (with the mirror images and their average: {1e3 * t_net_pipeline:.0f})")
    print(f"  ms per batch: inputs {1e3 * t_inputs:.0f}, {network}, vote modes {1e3 * t_modes:.0f}, "
          f"refinement {1e3 * t_refine:.0f}, mixture {1e3 * t_mixture:.0f}, other {1e3 * other:.0f}", flush=True)


def wait_policy() -> str:
    """The OpenMP wait settings in effect (:func:`articulated_dataset.core.pool.configure_openmp_wait`)."""
    from articulated_dataset.core.pool import OPENMP_WAIT_VARIABLES

    return ", ".join(f"{v}={os.environ[v]}" for v in OPENMP_WAIT_VARIABLES if v in os.environ) or "libgomp's default"


if __name__ == "__main__":
    sys.exit(main())
