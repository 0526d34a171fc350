"""Where a model's errors come from: the Table 1 errors of a predictions file split by what each image shows.

    python benchmarks/error_sources.py --predictions data/predictions/cabinet-dense.h5 --truth data/cabinet/test

Per image (mean over the joints): axis position error (cm), axis rotation error (deg) and
configuration error, scored as ``artdata score`` scores them
(:mod:`articulated_dataset.benchmark.metrics`).  Three tables:

* by the body's visible pixels (the shard's ``visible_pixels``: 0, 1-499, 500 or more): each
  group's share of the images, its mean errors and its share of the whole mean (its sum over
  all images' count), so the images that decide the mean stand out;
* per joint, by whether the moving part's pixels (mask code ``2 + j``) touch the image's top
  row, its bottom row, both or neither: the position error split into its component along the
  true joint axis (``|d . z|``) and across it (``|d - (d . z) z|``), over the images whose
  position error is below ``--outlier-cm`` (a wrong hinge side would swamp the means; their
  share is printed).  A door's axis origin is at its mid-height, so a door cut off by the
  image leaves that height to inference;
* by whether the image shows the whole object (no pixel of the body or of a part on the image's
  border rows and columns: :func:`articulated_dataset.format.object_on_border`, the rule of
  ``artdata generate --framing whole``), and of those, the ones with at least 500 body
  pixels: each group's share and mean errors.  The paper's pose table (Appendix A) puts a
  metre-high cabinet close to a level camera, so most renders cut it off; the paper's text says
  positions were drawn "from the view frustum of the camera".  This table tells how a model does
  on the renders that show everything (docs/dense.md).
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
    """(class, prismatic joints, per-image errors and image facts) of ``predictions`` against the split
    ``truth``, row i the predictions' image i: the scorer's own truth reading, alignment and per-joint
    metrics (:func:`~articulated_dataset.benchmark.scoring.image_metrics`), plus each image's
    body pixels and where its moving parts meet the image's edge (read from the shards' masks)."""
    import numpy as np

    from articulated_dataset.benchmark.predictions import read_predictions
    from articulated_dataset.benchmark.scoring import image_metrics
    from articulated_dataset.benchmark.truth import align, load_truth_set
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.core.rotations import quat_to_matrix
    from articulated_dataset.format import MASK_FIRST_PART, Split, object_on_border

    _, by_class = read_predictions(predictions)
    if len(by_class) != 1:
        raise UserError(f"{predictions}: expected one class, found {sorted(by_class)}")
    (class_name, pred), = by_class.items()
    labels = load_truth_set(truth)
    if labels.class_name != class_name:
        raise UserError(f"{predictions}: class {class_name!r}, but {truth} holds {labels.class_name!r}")
    idx = align(pred["sample_id"], labels.arrays["sample_id"], str(predictions), str(truth))
    if len(np.unique(idx)) != labels.n_images:
        raise UserError(f"{predictions}: {labels.n_images - len(np.unique(idx))} images of {truth} have no prediction")
    t = {k: v[idx] for k, v in labels.arrays.items()}
    with np.errstate(all="ignore"):  # as the scorer: NaN truth stays NaN
        _, per_joint = image_metrics(pred, t, labels.joint_types, str(predictions))
    J = len(labels.joint_types)
    facts = {k: [] for k in ("sample_id", "body_px", "top", "bottom", "seen", "whole")}
    with Split(truth) as split:
        for shard in split.shards:
            mask = shard.read("mask")
            part = np.stack([mask == MASK_FIRST_PART + j for j in range(J)], 1)  # (N, J, H, W)
            facts["sample_id"].append(shard.read("sample_id").astype(np.int64))
            facts["body_px"].append(shard.read("visible_pixels")[:, 0])
            facts["top"].append(part[:, :, 0, :].any(-1))
            facts["bottom"].append(part[:, :, -1, :].any(-1))
            facts["seen"].append(part.any((-1, -2)))
            facts["whole"].append(~object_on_border(mask))
    facts = {k: np.concatenate(v) for k, v in facts.items()}
    order = np.argsort(facts["sample_id"], kind="stable")[idx]  # the truth's order (sorted ids), then idx
    prismatic = np.array([jt == "prismatic" for jt in labels.joint_types])
    diff = pred["axis_pose"][..., :3] - t["axis_pose"][..., :3]
    z = quat_to_matrix(t["axis_pose"][..., 3:])[..., :, 2]  # (N, J, 3): the true joint axes
    along = (diff * z).sum(-1)
    out = {
        "pos": per_joint["axis_position_error_cm"],
        "rot": per_joint["axis_rotation_error_deg"],
        "config": per_joint["configuration_error"],
        "along": CM_PER_M * np.abs(along),
        "across": CM_PER_M * np.linalg.norm(diff - along[..., None] * z, axis=-1),
        **{k: facts[k][order] for k in ("body_px", "top", "bottom", "seen", "whole")},
        "sample_id": np.asarray(pred["sample_id"], dtype=np.int64),
    }
    return class_name, prismatic, out


def per_image_errors_of(predictions: Path, truth: Path, sample_ids) -> dict:
    """:func:`per_image_errors`' per-image arrays with row i the image ``sample_ids[i]`` (the other
    scripts' own image order)."""
    _, _, e = per_image_errors(predictions, truth)  # rows: the predictions' images
    row = {int(sid): r for r, sid in enumerate(e["sample_id"])}
    at = [row[int(sid)] for sid in sample_ids]
    return {k: v[at] for k, v in e.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--predictions", type=Path, required=True, help="predictions.h5 of one class")
    p.add_argument("--truth", type=Path, required=True, help="the split it predicts")
    p.add_argument("--outlier-cm", type=float, default=OUTLIER_CM)
    args = p.parse_args(argv)
    import numpy as np

    from articulated_dataset.core.errors import UserError

    try:
        class_name, prismatic, e = per_image_errors(args.predictions, args.truth)
    except UserError as exc:  # a missing or malformed file: one line, as the commands report it
        print(f"error_sources: error: {exc}", file=sys.stderr)
        return 2
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
    print("\nby whether the image shows the whole object (none of its pixels on the image's border): share of "
          "images; mean position / rotation / configuration")
    whole = e["whole"]
    for name, s in (("cut off", ~whole), ("whole", whole),
                    (f"whole, body {BODY_PIXEL_GROUPS[-1]}+ px", whole & (e["body_px"] >= BODY_PIXEL_GROUPS[-1]))):
        if s.any():
            print(f"  {name:<22} {s.mean():6.3f}   {pos[s].mean():6.2f} / {rot[s].mean():6.2f} / {cfg[s].mean():6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
