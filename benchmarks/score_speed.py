"""Speed of ``artdata score`` on a full six-class test set (6 x 16,000 images).

Builds synthetic truth shards with the real shard writer (labels only, 1x1 depth images) for
every registered class, writes predictions (truth + noise, optionally with 5-component
mixtures over the reference MDN target layout), then times :func:`articulated_dataset.benchmark.score`
end to end (reading and validating both sides, aligning by sample_id, all metrics, the table).

    python benchmarks/score_speed.py                 # 16,000 images per class, in a temp folder
    python benchmarks/score_speed.py --dir /tmp/sb   # keep/reuse the synthetic data
    python benchmarks/score_speed.py --images 1600   # smaller

Target: under 5 s for 96,000 images on a 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from articulated_dataset import FORMAT_VERSION
from articulated_dataset.benchmark.predictions import write_predictions
from articulated_dataset.benchmark.scoring import score, target_matrix
from articulated_dataset.classes.registry import all_classes
from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL, CameraConfig
from articulated_dataset.core.rotations import quat_multiply
from articulated_dataset.format import FIELDS, open_split, write_manifest, write_shard
from articulated_dataset.training.targets import TargetLayout

#: Images of one class in the paper's test split (1,000 objects x 16 images).
PAPER_TEST_IMAGES = 16_000
IMAGES_PER_OBJECT = 16
#: Mixture components of the synthetic MDN predictions.
N_COMPONENTS = 5
#: Prediction noise: position (m), rotation (rad), configuration (rad or m).
NOISE_POS_M, NOISE_ROT_RAD, NOISE_Q = 0.03, 0.02, 0.05


def _unit_quats(rng, shape):
    q = rng.normal(size=shape + (4,))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def synthetic_labels(class_name: str, n_joints: int, n: int, rng: np.random.Generator, id_offset: int) -> dict:
    """Schema-valid arrays for ``n`` images with random labels and 1x1 images."""
    shapes = {"N": n, "J": n_joints, "H": 1, "W": 1, "P": 1 + n_joints}
    arrays = {}
    for f in FIELDS:
        shape = tuple(shapes[s] if isinstance(s, str) else s for s in f.shape)
        if f.dtype.startswith("S"):
            arrays[f.name] = np.full(shape, class_name.encode(), dtype=f.dtype)
        else:
            arrays[f.name] = rng.uniform(0.0, 1.0, size=shape).astype(f.dtype)
    pose = arrays["axis_pose"]
    pose[..., :3] = rng.uniform([1.0, -1.0, -0.5], [3.0, 1.0, 1.0], size=(n, n_joints, 3))
    pose[..., 3:] = _unit_quats(rng, (n, n_joints))
    arrays["geometry"][:, :3] = rng.uniform(0.3, 1.2, size=(n, 3))
    arrays["geometry"][:, 3] = rng.integers(0, 2, size=n)
    arrays["sample_id"] = id_offset + np.arange(n, dtype=np.int64)
    arrays["object_index"] = np.arange(n, dtype=np.int64) // IMAGES_PER_OBJECT
    arrays["image_index"] = (np.arange(n) % IMAGES_PER_OBJECT).astype(np.int32)
    return arrays


def build_truth(root: Path, n_images: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    camera = CameraConfig(1, 1)
    for k, obj_class in enumerate(all_classes()):
        split_dir = root / obj_class.name / "test"
        if (split_dir / "manifest.json").is_file():
            continue
        split_dir.mkdir(parents=True, exist_ok=True)
        arrays = synthetic_labels(obj_class.name, obj_class.n_joints, n_images, rng, id_offset=(k + 1) << 40)
        attrs = {"format_version": FORMAT_VERSION, "class_name": obj_class.name, "split": "test", "seed": seed,
                 "n_joints": obj_class.n_joints, "joint_types": json.dumps(list(obj_class.joint_types))}
        record = write_shard(split_dir / "shard-00000.h5", arrays, attrs, camera.K, R_CAMERA_TO_OPTICAL)
        write_manifest(split_dir, {"format_version": FORMAT_VERSION, "class_name": obj_class.name, "split": "test",
                                   "seed": seed, "complete": True, "n_images": n_images, "shards": [record]})


def build_predictions(root: Path, path: Path, seed: int, mixtures: bool) -> None:
    rng = np.random.default_rng(seed + 1)
    per_class = {}
    for obj_class in all_classes():
        _, shards = open_split(root / obj_class.name / "test")
        t = {k: shards[0].read(k).astype(np.float64) for k in ("axis_pose", "q", "geometry", "part_offset")}
        ids = shards[0].read("sample_id")
        n, J = t["q"].shape
        pose = t["axis_pose"].copy()
        pose[..., :3] += rng.normal(scale=NOISE_POS_M, size=(n, J, 3))
        dq = np.concatenate([np.ones((n, J, 1)), 0.5 * rng.normal(scale=NOISE_ROT_RAD, size=(n, J, 3))], axis=-1)
        pose[..., 3:] = quat_multiply(dq / np.linalg.norm(dq, axis=-1, keepdims=True), pose[..., 3:])
        pred = {"sample_id": ids, "axis_pose": pose.astype(np.float32),
                "q": (t["q"] + rng.normal(scale=NOISE_Q, size=(n, J))).astype(np.float32),
                "geometry": (t["geometry"] + rng.normal(scale=0.02, size=(n, 4))).astype(np.float32)}
        if mixtures:
            layout = TargetLayout.for_class(obj_class.name).names  # the reference MDN's columns
            y = target_matrix(layout, t)
            pred["mixture_weights"] = rng.dirichlet(np.ones(N_COMPONENTS), size=n).astype(np.float32)
            pred["mixture_means"] = (y[:, None, :] + rng.normal(scale=0.05, size=(n, N_COMPONENTS, len(layout)))).astype(np.float32)
            pred["mixture_scales"] = rng.uniform(0.02, 0.1, size=(n, N_COMPONENTS, len(layout))).astype(np.float32)
            pred["mixture_layout"] = layout
        per_class[obj_class.name] = pred
    write_predictions(path, "Synthetic" + ("-MDN" if mixtures else ""), per_class)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=PAPER_TEST_IMAGES, help="images per class")
    parser.add_argument("--dir", type=Path, default=None, help="folder for the synthetic data (default: a temp folder)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=3, help="timed runs (the best is reported)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        base = args.dir or Path(tmp)
        root = base / f"truth-{args.images}"
        t0 = time.perf_counter()
        build_truth(root, args.images, args.seed)
        preds = {}
        for mixtures in (False, True):
            path = base / f"predictions-{args.images}{'-mdn' if mixtures else ''}.h5"
            if not path.is_file():
                build_predictions(root, path, args.seed, mixtures)
            preds[mixtures] = path
        print(f"setup (synthetic truth + predictions): {time.perf_counter() - t0:.1f} s")
        n_classes = len(all_classes())
        for mixtures, path in preds.items():
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                report = score(path, root)
                report.format_table()
                times.append(time.perf_counter() - t0)
            n = sum(r.n_scored for r in report.rows)
            assert n == n_classes * args.images
            label = "with 5-component mixtures (NLL + calibration)" if mixtures else "point predictions + geometry"
            print(f"score {n} images ({n_classes} classes x {args.images}), {label}: "
                  f"best {min(times):.2f} s, median {sorted(times)[len(times) // 2]:.2f} s "
                  f"({n / min(times) / 1e3:.0f} k images/s)")


if __name__ == "__main__":
    main()
