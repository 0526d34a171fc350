"""Latency of one estimate in the robot's view: ``articulated_dataset.estimate`` on one image with a
click, a box or no prompt, on one core.

    python benchmarks/prompt_latency.py --root work-latency
    python benchmarks/prompt_latency.py --root work-latency --classes microwave --resolution 640x480

For every class the script renders (or reuses, under ``--root``) a test split as a robot sees it
(``artdata generate --camera head --scene kitchen --occluders 2``, ``--resolution``), makes each
image's simulated prompt from its label mask (docs/robot_view.md) and times, per prompt, the
segmentation from the prompt alone (``segment_from_prompt``) and the whole ``ad.estimate`` call
(segmentation, model and refinement; the model loaded once before).  It prints the median and
the 90th percentile over the images, in milliseconds, with torch held to ``--threads`` (default
1: one core).  The target of docs/robot_view.md is a point-prompted estimate under 50 ms.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

sys.path.insert(0, str(Path(__file__).parent))  # third_party.py beside this script
from third_party import run_artdata, text_grid  # noqa: E402  (run_artdata: artdata in this process)

#: The robot's view the images are rendered in (``artdata generate`` options).
VIEW = ["--camera", "head", "--scene", "kitchen", "--occluders", "2"]
PROMPTS = ("point", "box", "none")
DEFAULT_OBJECTS = 2
DEFAULT_SEED = 2027
#: Percentile reported beside the median.
HIGH_PERCENTILE = 90


def split_dir(root: Path, resolution: str, class_name: str) -> Path:
    return root / resolution / class_name / "test"


def measure(class_name: str, split: Path, model: str) -> list[dict]:
    """Per prompt: the milliseconds of each image's segmentation and estimate."""
    import numpy as np

    import articulated_dataset as ad
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.format import open_split
    from articulated_dataset.format.shards import Shard
    from articulated_dataset.methods.prompts import class_extent_m, segment_from_prompt, simulated_prompt

    _, shards = open_split(split)
    sh = Shard(shards[0].path)
    try:
        depth, mask, K = sh.read("depth"), sh.read("mask"), np.asarray(sh.K, np.float64)
    finally:
        sh.close()
    extent = class_extent_m(class_name)
    ad.estimate(depth[0], K, class_name, model=model, mask=mask[0] > 0)  # loads the model once
    rows = []
    for kind in PROMPTS:
        seg_ms, est_ms, refused = [], [], 0
        for d, m in zip(depth, mask):
            prompt = simulated_prompt(kind, m)
            kwargs = {} if kind == "none" else {kind: prompt.point_px if kind == "point" else prompt.box_px}
            t0 = time.perf_counter()
            try:
                segment_from_prompt(d, K, prompt, max_extent_m=extent)
            except UserError:
                refused += 1
                continue
            t1 = time.perf_counter()
            ad.estimate(d, K, class_name, model=model, **kwargs)
            t2 = time.perf_counter()
            seg_ms.append(1e3 * (t1 - t0))
            est_ms.append(1e3 * (t2 - t1))
        pct = (lambda v, q: float(np.percentile(v, q)) if v else float("nan"))
        rows.append({"class": class_name, "prompt": kind, "images": len(depth), "refused": refused,
                     "segment_ms": pct(seg_ms, 50), "segment_ms_high": pct(seg_ms, HIGH_PERCENTILE),
                     "estimate_ms": pct(est_ms, 50), "estimate_ms_high": pct(est_ms, HIGH_PERCENTILE)})
    return rows


def format_table(rows: list[dict]) -> str:
    """The fixed-width table the script prints."""
    titles = ["class", "prompt", "images", "refused", "segment ms", f"p{HIGH_PERCENTILE}", "estimate ms",
              f"p{HIGH_PERCENTILE}"]
    body = [[r["class"], r["prompt"], str(r["images"]), str(r["refused"]), f"{r['segment_ms']:.1f}",
             f"{r['segment_ms_high']:.1f}", f"{r['estimate_ms']:.1f}", f"{r['estimate_ms_high']:.1f}"] for r in rows]
    return text_grid(titles, body, 2)


def main(argv=None) -> int:
    from articulated_dataset.classes.registry import PAPER_CLASSES, class_names
    from articulated_dataset.core.errors import UserError

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--root", type=Path, required=True, help="work folder for the rendered splits")
    p.add_argument("--classes", nargs="+", default=list(PAPER_CLASSES), choices=class_names())
    p.add_argument("--resolution", default="192x108", help="image size WxH (artdata generate --resolution)")
    p.add_argument("--objects", type=int, default=DEFAULT_OBJECTS, help="test objects per class (16 images each)")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED)
    p.add_argument("--model", default="dense")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1: one core)")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    rows = []
    try:
        for c in args.classes:
            split = split_dir(args.root, args.resolution, c)
            if not (split / "manifest.json").is_file():
                run_artdata(["generate", "--class", c, "--split", "test", "--n", str(args.objects), "--seed",
                             str(args.seed), "--resolution", args.resolution, "--out", str(split.parent.parent),
                             "-q", *VIEW], c)
            rows += measure(c, split, args.model)
    except UserError as exc:
        print(f"prompt_latency: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    print(f"model {args.model}, {args.threads} thread(s), {args.resolution}, head camera in a kitchen with 2 "
          f"occluders, {args.objects} object(s) x 16 images per class; milliseconds per image\n")
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
