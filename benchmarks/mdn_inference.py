"""Inference speed of the reference MDN: images per second, full and small networks.

For each preset (``full``: ResNet-18 at 192x108; ``small``: the ``--small`` network at
96x54) and each available device (CPU always; CUDA when present), the script times

* ``network``: forward passes of the network on batches already in the input format, and
* ``+ preprocess``: depth images (192x108, metres) -> input planes -> forward -> point
  estimate (mean of the best component), i.e. what ``artdata predict`` does per batch
  besides reading the file.

The figure is images per second over ``--iters`` timed batches after ``--warmup`` batches
(median batch time).  Uses random weights (speed does not depend on them) and, for the
preprocessing path, synthetic depth images with a box-shaped object.

    python benchmarks/mdn_inference.py [--batch 64] [--iters 10] [--threads N] [--devices cpu,cuda]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

from articulated_dataset.core.pool import configure_allocator, configure_openmp_wait  # noqa: E402

configure_openmp_wait()  # before torch loads its OpenMP runtime: the commands' wait policy
configure_allocator()  # and their allocator settings

import numpy as np  # noqa: E402
import torch  # noqa: E402

from articulated_dataset.core.camera import CameraConfig  # noqa: E402
from articulated_dataset.methods.mdn.config import PRESETS, TrainConfig  # noqa: E402
from articulated_dataset.methods.mdn.loss import mean_of_best  # noqa: E402
from articulated_dataset.methods.mdn.model import MixtureDensityNetwork, count_parameters  # noqa: E402
from articulated_dataset.methods.mdn.preprocess import assemble_inputs, preprocess_depth  # noqa: E402
from articulated_dataset.methods.mdn.train import configure_threads  # noqa: E402

#: Target columns of a 2-joint class (13 per joint + 4 geometry), the larger case.
TARGET_DIM = 30


def synthetic_depth(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 108, 192) depth images: a box-shaped object 1-3 m away on an empty background."""
    cam = CameraConfig()
    d = np.zeros((n, cam.height_px, cam.width_px), np.float32)
    for i in range(n):
        top, left = rng.integers(10, 40), rng.integers(20, 90)
        d[i, top : top + 50, left : left + 80] = rng.uniform(1.0, 3.0) + rng.uniform(0, 0.3, (50, 80))
    return d


def time_batches(fn, warmup: int, iters: int, sync) -> float:
    for _ in range(warmup):
        fn()
    sync()
    times = []
    for _ in range(iters):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--iters", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--threads", type=int, default=None, help="CPU threads (default: all cores of this process)")
    ap.add_argument("--devices", default=None, help="comma-separated, default: cpu plus cuda if available")
    args = ap.parse_args()

    threads = configure_threads(args.threads)
    devices = args.devices.split(",") if args.devices else ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    rng = np.random.default_rng(0)
    depth = synthetic_depth(args.batch, rng)
    K = CameraConfig().K
    print(f"torch {torch.__version__}, {platform.processor() or platform.machine()}, {threads} CPU threads, "
          f"load average {os.getloadavg()[0]:.1f}; batch {args.batch}, median of {args.iters} batches")
    if "cuda" in devices:
        print(f"GPU: {torch.cuda.get_device_name(0)}")
    print(f"{'network':8s} {'input':>8s} {'params':>11s} {'device':>6s} {'network img/s':>14s} {'+ preprocess img/s':>19s}")
    for preset in PRESETS:
        cfg = TrainConfig(class_name="cabinet2", preset=preset).resolved()
        ic = cfg.input_config()
        torch.manual_seed(0)
        for dev_name in devices:
            dev = torch.device(dev_name)
            model = MixtureDensityNetwork(cfg.model_config(TARGET_DIM)).to(dev, memory_format=torch.channels_last).eval()
            planes, scalars, _ = preprocess_depth(depth, ic, K)
            x = assemble_inputs(planes, ic).to(dev).contiguous(memory_format=torch.channels_last)
            s = scalars.to(dev)
            use_amp = dev.type == "cuda"
            sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)

            def forward(x=x, s=s, model=model, use_amp=use_amp):
                with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16, enabled=use_amp):
                    return model(x, s)

            def end_to_end(model=model, ic=ic, dev=dev, use_amp=use_amp):
                p, sc, _ = preprocess_depth(depth, ic, K)
                xi = assemble_inputs(p.to(dev), ic).contiguous(memory_format=torch.channels_last)
                with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16, enabled=use_amp):
                    logits, means, _ = model(xi, sc.to(dev))
                return mean_of_best(logits, means).cpu()

            t_net = time_batches(forward, args.warmup, args.iters, sync)
            t_all = time_batches(end_to_end, args.warmup, args.iters, sync)
            print(f"{preset:8s} {ic.width_px:>4d}x{ic.height_px:<3d} {count_parameters(model):>11,d} {dev_name:>6s} "
                  f"{args.batch / t_net:>14.0f} {args.batch / t_all:>19.0f}")


if __name__ == "__main__":
    main()
