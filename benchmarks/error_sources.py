"""Where a model's errors come from: the Table 1 errors of a predictions file split by what each image shows.

    python benchmarks/error_sources.py --predictions data/predictions/cabinet-dense.h5 --truth data/cabinet/test

Per image (mean over the joints): axis position error (cm), axis rotation error (deg) and
configuration error, scored as ``artdata score`` scores them
(:mod:`articulated_dataset.benchmark.metrics`).  Two tables:

* by the body's visible pixels (the shard's ``visible_pixels``: 0, 1-499, 500 or more): each
  group's share of the images, its mean errors and its share of the whole mean (its sum over
  all images' count), so the images that decide the mean stand out;
* per joint, by whether the moving part's pixels (mask code ``2 + j``) touch the image's top
  row, its bottom row, both or neither: the position error split into its component along the
  true joint axis (``|d . z|``) and across it (``|d - (d . z) z|``), over the images whose
  position error is below ``--outlier-cm`` (a wrong hinge side would swamp the means; their
  share is printed).  A door's axis origin is at its mid-height, so a door cut off by the
  image leaves that height to inference.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

#: Body-pixel groups (lower bounds) of the first table.
BODY_PIXEL_GROUPS = (0, 1, 500)
#: Images with a larger position error (cm) are left out of the along / across means.
OUTLIER_CM = 20.0
CM_PER_M = 100.0


def per_image_errors(predictions: Path, truth: Path):
    """(class, per-image errors and image facts) of ``predictions`` against the split ``truth``."""
    import h5py
    import numpy as np

    from articulated_dataset.benchmark import metrics as M
    from articulated_dataset.benchmark.predictions import read_predictions
    from articulated_dataset.format import MASK_FIRST_PART
    from articulated_dataset.registry import get_class
    from articulated_dataset.rotations import quat_to_matrix

    _, by_class = read_predictions(predictions)
    if len(by_class) != 1:
        raise SystemExit(f"{predictions}: expected one class, found {sorted(by_class)}")
    (class_name, pred), = by_class.items()
    row_of = {int(s): i for i, s in enumerate(pred["sample_id"])}
    shards = sorted(Path(truth).glob("shard-*.h5"))
    if not shards:
        raise SystemExit(f"{truth}: no shard-*.h5")
    J = get_class(class_name).n_joints
    cols = {k: [] for k in ("rows", "pose", "q", "body_px", "top", "bottom", "seen")}
    for path in shards:
        with h5py.File(path, "r") as f:
            ids = f["sample_id"][:]
            mask = f["mask"][:]
            cols["rows"].append(np.array([row_of.get(int(s), -1) for s in ids]))
            cols["pose"].append(f["axis_pose"][:])
            cols["q"].append(f["q"][:])
            cols["body_px"].append(f["visible_pixels"][:, 0])
            part = np.stack([mask == MASK_FIRST_PART + j for j in range(J)], 1)  # (N, J, H, W)
            cols["top"].append(part[:, :, 0, :].any(-1))
            cols["bottom"].append(part[:, :, -1, :].any(-1))
            cols["seen"].append(part.any((-1, -2)))
    c = {k: np.concatenate(v) for k, v in cols.items()}
    if (c["rows"] < 0).any():
        raise SystemExit(f"{predictions}: {(c['rows'] < 0).sum()} images of {truth} have no prediction")
    pose, q = pred["axis_pose"][c["rows"]].astype(np.float64), pred["q"][c["rows"]].astype(np.float64)
    true_pose = c["pose"].astype(np.float64)
    prismatic = np.array([t == "prismatic" for t in get_class(class_name).joint_types])
    diff = pose[..., :3] - true_pose[..., :3]
    z = quat_to_matrix(true_pose[..., 3:])[..., :, 2]  # (N, J, 3): the true joint axes
    along = (diff * z).sum(-1)
    out = {
        "pos": M.axis_position_error_cm(pose[..., :3], true_pose[..., :3]),
        "rot": M.axis_rotation_error_deg(pose[..., 3:], true_pose[..., 3:]),
        "config": M.configuration_error(q, c["q"].astype(np.float64), prismatic),
        "along": CM_PER_M * np.abs(along),
        "across": CM_PER_M * np.linalg.norm(diff - along[..., None] * z, axis=-1),
        "body_px": c["body_px"], "top": c["top"], "bottom": c["bottom"], "seen": c["seen"],
    }
    return class_name, prismatic, out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--predictions", type=Path, required=True, help="predictions.h5 of one class")
    p.add_argument("--truth", type=Path, required=True, help="the split it predicts")
    p.add_argument("--outlier-cm", type=float, default=OUTLIER_CM)
    args = p.parse_args(argv)
    import numpy as np

    class_name, prismatic, e = per_image_errors(args.predictions, args.truth)
    pos, rot, cfg = (e[k].mean(1) for k in ("pos", "rot", "config"))
    n = len(pos)
    unit = "cm" if prismatic.all() else "deg" if not prismatic.any() else "deg|cm"
    print(f"{class_name}: {n} images; mean position {pos.mean():.2f} cm, rotation {rot.mean():.2f} deg, "
          f"configuration {cfg.mean():.2f} {unit}; medians {np.median(pos):.2f} / {np.median(rot):.3f} / "
          f"{np.median(cfg):.3f}")
    print("\nby the body's visible pixels: share of images; mean position / rotation / configuration; "
          "their part of the whole mean")
    bounds = list(BODY_PIXEL_GROUPS) + [np.inf]
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        s = (e["body_px"] >= lo) & (e["body_px"] < hi)
        if not s.any():
            continue
        name = f"{lo}" if hi == lo + 1 else f"{lo}+" if hi == np.inf else f"{lo}-{int(hi) - 1}"
        print(f"  {name:>7} px  {s.mean():6.3f}   {pos[s].mean():6.2f} / {rot[s].mean():6.2f} / {cfg[s].mean():6.2f}"
              f"   {pos[s].sum() / n:5.2f} / {rot[s].sum() / n:5.2f} / {cfg[s].sum() / n:5.2f}")
    print(f"\nper joint, by where its part meets the image's edge: share; position along / across the true "
          f"axis (cm, images under {args.outlier_cm:g} cm); mean position (cm, all)")
    for j in range(e["pos"].shape[1]):
        ok = e["pos"][:, j] < args.outlier_cm
        top, bottom, seen = e["top"][:, j], e["bottom"][:, j], e["seen"][:, j]
        print(f"  joint {j}: {100 * (1 - ok.mean()):.1f}% of the images above {args.outlier_cm:g} cm")
        for name, s in (("top cut", top & ~bottom), ("bottom cut", bottom & ~top), ("both cut", top & bottom),
                        ("in view", seen & ~top & ~bottom), ("not seen", ~seen)):
            if not s.any():
                continue
            inl = s & ok
            along = e["along"][inl, j].mean() if inl.any() else float("nan")
            across = e["across"][inl, j].mean() if inl.any() else float("nan")
            print(f"    {name:<10} {s.mean():6.3f}   {along:6.2f} / {across:6.2f}   {e['pos'][s, j].mean():6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
