"""Counts of the scene and occluder options per class, for DATASHEET.md.

Generates ``--objects`` objects per class (seed 0, 16 images each) with each setting and
prints, per class: pose draws per object, the moving parts' ``visible_fraction`` (mean,
minimum, share of part-images below 0.9), and the shares of the image covered by the object,
the scene and the occluders.

    python benchmarks/context_counts.py --objects 20
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

SETTINGS = {"--scene kitchen": ("kitchen", 0), "--scene room": ("room", 0), "--occluders 2": ("none", 2),
            "--scene kitchen --occluders 2": ("kitchen", 2)}


def counts(class_name: str, scene: str, occluders: int, n_objects: int, root: Path, seed: int = 0) -> dict:
    import numpy as np

    from articulated_dataset.format import open_split
    from articulated_dataset.format.schema import MASK_OCCLUDER, MASK_SCENE
    from articulated_dataset.generation import GenerationConfig, generate_split

    config = GenerationConfig(class_name, n_objects=n_objects, seed=seed, objects_per_shard=n_objects, scene=scene,
                              occluders=occluders)
    manifest, shards = open_split(generate_split(config, root, overwrite=True))
    mask = np.concatenate([s.read("mask") for s in shards])
    frac = np.concatenate([s.read("visible_fraction") for s in shards])[:, 1:]
    for s in shards:
        s.close()
    px = mask.size
    return {"pose_draws_per_object": sum(r["pose_attempts"] for r in manifest["shards"]) / n_objects,
            "visible_fraction_mean": float(frac.mean()), "visible_fraction_min": float(frac.min()),
            "share_below_0.9": float((frac < 0.9).mean()),
            "object_px_share": float(((mask >= 1) & (mask < MASK_OCCLUDER)).sum() / px),
            "scene_px_share": float((mask == MASK_SCENE).sum() / px),
            "occluder_px_share": float((mask == MASK_OCCLUDER).sum() / px)}


def main() -> None:
    from articulated_dataset.classes.registry import class_names

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", type=int, default=20)
    ap.add_argument("--classes", nargs="*", default=None)
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, (scene, occluders) in SETTINGS.items():
            print(f"\n{label}: {args.objects} objects x 16 images per class, seed 0")
            print("| class | pose draws/object | visible fraction mean (min) | part-images < 0.9 visible "
                  "| image share object / scene / occluders |")
            print("|---|---|---|---|---|")
            for name in args.classes or class_names():
                c = counts(name, scene, occluders, args.objects, Path(tmp) / label.replace(" ", ""))
                results.setdefault(label, {})[name] = c
                print(f"| {name} | {c['pose_draws_per_object']:.2f} | {c['visible_fraction_mean']:.2f} "
                      f"({c['visible_fraction_min']:.2f}) | {100 * c['share_below_0.9']:.0f}% | "
                      f"{100 * c['object_px_share']:.0f}% / {100 * c['scene_px_share']:.0f}% / "
                      f"{100 * c['occluder_px_share']:.0f}% |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
