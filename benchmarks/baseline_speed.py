"""Speed of the Table 1 baselines at the paper's scale (160,000 training / 16,000 test images).

* NN: depth-feature extraction throughput on real shards, then the exact search of 16,000
  queries against 160,000 training features (D = 48 x 27 = 1,296).  The feature matrices are
  real features of a rendered split tiled to full size with 1 cm Gaussian noise (the search
  time depends on the sizes, not on the content; the noise keeps every vector distinct).
* ICP: ms per test image (wall and CPU time of this process), per class, on real test images.

    python benchmarks/baseline_speed.py            # full sizes (~2 GB of RAM for NN)
    python benchmarks/baseline_speed.py --quick    # 1/10 of the NN sizes, 16 ICP images per class

Prints wall-clock and CPU seconds; on a shared machine the CPU time is the steadier figure.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

#: The paper's sizes per class: 10,000 / 1,000 objects x 16 images.
FULL_TRAIN_IMAGES = 160_000
FULL_TEST_IMAGES = 16_000
#: Noise (m) added to tiled real features so that no two vectors are equal.
TILE_NOISE_M = 0.01


class Timer:
    def __enter__(self):
        self.wall0, self.cpu0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.wall0
        self.cpu = time.process_time() - self.cpu0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="1/10 of the NN sizes and 16 ICP images per class.")
    p.add_argument("--objects", type=int, default=40, help="Objects rendered per class for the real inputs.")
    p.add_argument("--icp-images", type=int, default=64, help="ICP test images timed per class.")
    p.add_argument("--classes", nargs="+", default=None)
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = p.parse_args(argv)
    scale = 10 if args.quick else 1
    n_train, n_test = FULL_TRAIN_IMAGES // scale, FULL_TEST_IMAGES // scale
    icp_images = 16 if args.quick else args.icp_images

    from articulated_dataset.classes.registry import class_names
    from articulated_dataset.generation import GenerationConfig, generate_split
    from articulated_dataset.methods.baselines import icp_model, nn
    from articulated_dataset.methods.baselines.common import open_split_checked

    classes = args.classes or class_names()
    print(f"{os.cpu_count()} CPUs; load average {os.getloadavg()[0]:.1f}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for cls in classes:
            generate_split(GenerationConfig(cls, split="test", n_objects=args.objects), root, workers=args.workers)
            generate_split(GenerationConfig(cls, mean=True, n_objects=1), root, workers=1)

        # ---- NN: features
        split = open_split_checked(root / classes[0] / "test", "test")
        with Timer() as t:
            feats = nn.split_features(split, workers=1)
        split.close()
        n_img = len(feats)
        print(f"NN features ({classes[0]}): {n_img} images in {t.wall:.2f} s wall / {t.cpu:.2f} s CPU "
              f"= {n_img / t.wall:.0f} images/s per process; {FULL_TRAIN_IMAGES + FULL_TEST_IMAGES} images "
              f"-> {(FULL_TRAIN_IMAGES + FULL_TEST_IMAGES) / (n_img / t.wall) / args.workers:.0f} s with {args.workers} workers",
              flush=True)

        # ---- NN: search at full size
        rng = np.random.default_rng(0)
        train = feats[rng.integers(0, n_img, n_train)] + rng.normal(0, TILE_NOISE_M, (n_train, feats.shape[1])).astype(np.float32)
        query = feats[rng.integers(0, n_img, n_test)] + rng.normal(0, TILE_NOISE_M, (n_test, feats.shape[1])).astype(np.float32)
        with Timer() as t_build:
            index = nn.ExactNearestNeighbour(train)
        with Timer() as t:
            idx, _ = index.query(query)
        print(f"NN search: {n_test} queries x {n_train} training images (D = {index.dim}): "
              f"{t.wall:.1f} s wall / {t.cpu:.1f} s CPU (index {t_build.wall:.1f} s); "
              f"{index.n_reranked / n_test:.1f} exact re-rankings per query", flush=True)
        # spot-check exactness on a few queries
        check = rng.integers(0, n_test, 5)
        for q in check:
            d = ((train.astype(np.float64) - query[q].astype(np.float64)) ** 2).sum(1)
            assert int(np.argmin(d)) == int(idx[q]), "NN search is not exact"
        del train, query, index

        # ---- ICP
        for cls in classes:
            mean = open_split_checked(root / cls / "mean", "mean")
            test = open_split_checked(root / cls / "test", "test")
            model = icp_model.MeanObjectModel.from_split(mean, test.yaw_range_rad)
            sh = test.shards[0]
            n = min(icp_images, len(sh))
            depth, mask, K = sh.read("depth", slice(0, n)), sh.read("mask", slice(0, n)), sh.K
            with Timer() as t:
                for d, m in zip(depth, mask):
                    model.predict_image(d, m, K)
            mean.close()
            test.close()
            print(f"ICP {cls}: {n} images, {1e3 * t.wall / n:.0f} ms/image wall, {1e3 * t.cpu / n:.0f} ms/image CPU "
                  f"-> {FULL_TEST_IMAGES} images in {FULL_TEST_IMAGES * t.cpu / n / args.workers / 60:.1f} min "
                  f"on {args.workers} workers (CPU time)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
