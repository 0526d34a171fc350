"""How well could any estimator place a cut-off door's hinge height?  An oracle's error floor.

    python benchmarks/height_floor.py --truth data/cabinet/test [--predictions data/predictions/cabinet-dense.h5]

A door's axis origin is labelled at the door's mid-height.  In the cabinet and the two-door
cabinet every door is the object's full height, ``height_m``, drawn uniformly from the sampling
table's range and independently of everything else (the paper's Appendix A), and the paper's poses
put these objects close to the camera, so most images cut the door's top off.  There the image
bounds the height but does not give it.

The oracle here knows everything about the image except the object's height.  That includes the
pose, and so the door's bottom, the hinge line and the door's angle.  From the image it also
knows:

* **the object's top.**  Where a pixel of the object (body or door) lies within
  :data:`TOP_SEEN_TOL_M` of its top (the top wall's underside, seen through an open door,
  included), the height is known exactly (the bottom is known).  Otherwise
  the height is at least that of the object's highest visible point.  An open door shows the
  body's inside, whose back edge, further from the camera, the image may show below a door whose
  top it cuts off.
* **the handle.**  ``side_door`` centres the handle bar, 12 cm long, at the door's mid-height.
  Where the handle is found in the door's true pixels (:func:`~articulated_dataset.methods.dense.handle.handle_evidence`),
  the height is known exactly.  Where it is not found and the strip of the door where it would
  be is seen, the bar lies outside the strip's visible extent.

The posterior of the door's half height ``D`` is the prior (uniform) restricted to what those
facts allow, evaluated on a grid of :data:`GRID_POINTS` values.  Its median is the oracle's
estimate, and the posterior's mean absolute deviation from it is the oracle's expected error
along the hinge (m).  The origin moves with ``D``, since the bottom is known.  The mean over the
images is a floor for the position error of any estimator that sees only the image: its position
error is at least its error along the hinge, and it knows less than the oracle.

The floor is approximate in two ways:

* the handle's strip is assumed to face the camera wherever it is seen, which gives the oracle
  more than the image does (its floor is then lower);
* the pixels near the image's border are read at the image's resolution.

With ``--predictions``, the model's error along the true hinge is printed beside the floor, per
group of images.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

#: Classes whose every door is the object's full height (their templates: ``door_h="${h}"``).
FULL_HEIGHT_DOOR_CLASSES = ("cabinet", "cabinet2")
#: The body's walls are this thick (m; common.xacro's wall_m): the underside of its top wall, seen
#: through an open door, lies this far below the top.
WALL_M = 0.018
#: The object's top counts as seen where a pixel of the object is within this distance (m) of it
#: (the top wall's underside included).
TOP_SEEN_TOL_M = WALL_M + 0.007
#: The handle's centre is this far (m) from the door's free edge (common.xacro's handle_inset_m).
HANDLE_INSET_M = 0.05
#: The strip where the handle would be: door pixels this far (m) either side of its line.
HANDLE_STRIP_HALF_WIDTH_M = 0.03
#: ... needs at least this many pixels to say where the handle is not.
HANDLE_STRIP_MIN_PX = 5
#: Values of the half height on the posterior's grid.
GRID_POINTS = 2001
CM_PER_M = 100.0


def door_facts(truth: Path):
    """Per image and door: the class, sample ids (N,), and arrays (N, J) of the object's highest
    visible point above the door's bottom (m), whether the object's top is out of view, whether its
    handle is found (in the split's masks at the network's output resolution, as training labels them), the visible extent (lowest, highest, m above the bottom) of the strip where the
    handle would be (NaN without enough pixels), and the true half height (m)."""
    import numpy as np
    import torch

    from articulated_dataset.core.rotations import quat_to_matrix
    from articulated_dataset.format import MASK_FIRST_PART, Split
    from articulated_dataset.methods.dense.features import backproject_torch, make_inputs, output_labels
    from articulated_dataset.methods.dense.handle import handle_evidence

    out = {k: [] for k in ("sample_id", "top_m", "cut", "handle", "strip_lo_m", "strip_hi_m", "half_m")}
    with Split(truth) as split:
        class_name = split.class_name
        for shard in split.shards:
            depth = shard.read("depth").astype(np.float32)
            mask = shard.read("mask")
            pose = shard.read("axis_pose").astype(np.float64)
            q = shard.read("q").astype(np.float64)
            radius = shard.read("part_offset")[..., 0].astype(np.float64)
            height_m = shard.read("geometry")[:, 2].astype(np.float64)
            K = np.broadcast_to(shard.K, (len(depth), 3, 3)).astype(np.float32)
            N, H, W = depth.shape
            J = q.shape[1]
            pts = backproject_torch(torch.from_numpy(depth), torch.from_numpy(K)).numpy().astype(np.float64)
            R = quat_to_matrix(pose[..., 3:])
            z, x = R[..., :, 2], R[..., :, 0]
            # the door's direction now: the closed door's x turned by q about the hinge
            xq = np.cos(q)[..., None] * x + np.sin(q)[..., None] * np.cross(z, x)
            # handles in the doors' true pixels, as refinement step 9 finds them
            inputs = make_inputs(torch.from_numpy(depth), torch.from_numpy(K))
            labels = torch.from_numpy(output_labels(mask, J).astype(np.int64))  # 0 background, 1 body, 2 + j door j
            seg = torch.nn.functional.one_hot((labels - 1).clamp_min(0), 1 + J).permute(0, 3, 1, 2).float()
            ev = handle_evidence({"seg": seg}, inputs, torch.from_numpy(z.astype(np.float32)),
                                 ["revolute"] * J, torch.ones(N, J, dtype=torch.bool))
            found = ev["handle_px"].numpy() > 0
            facts = {k: np.full((N, J), np.nan) for k in ("top_m", "strip_lo_m", "strip_hi_m", "half_m")}
            cut = np.zeros((N, J), bool)
            for i in range(N):
                true_half_m = 0.5 * float(height_m[i])  # full-height doors
                # every pixel of the object (body and doors) lies at or below its top: an open
                # door shows the body's inside, whose back edge the image may show below a cut door
                obj = (mask[i] >= 1) & (mask[i] < MASK_FIRST_PART + J) & (depth[i] > 0)
                p_obj = pts[i][:, obj].T
                for j in range(J):
                    door = (mask[i] == MASK_FIRST_PART + j) & (depth[i] > 0)
                    if not door.any():
                        continue
                    p = pts[i][:, door].T  # (n, 3)
                    up = z[i, j] * np.sign(z[i, j, 2])  # the hinge line, pointing up (camera z is up)
                    s = (p - pose[i, j, :3]) @ up  # height above the origin (the mid-height)
                    u_obj = (p_obj - pose[i, j, :3]) @ up + true_half_m
                    facts["top_m"][i, j] = u_obj.max()
                    cut[i, j] = bool(u_obj.max() < 2.0 * true_half_m - TOP_SEEN_TOL_M)  # the top out of view
                    u = s + true_half_m  # heights above the door's bottom, which the oracle knows
                    facts["half_m"][i, j] = true_half_m
                    a = (p - pose[i, j, :3]) @ xq[i, j]  # across the door from the hinge
                    strip = np.abs(a - (2.0 * radius[i, j] - HANDLE_INSET_M)) < HANDLE_STRIP_HALF_WIDTH_M
                    if strip.sum() >= HANDLE_STRIP_MIN_PX:
                        facts["strip_lo_m"][i, j], facts["strip_hi_m"][i, j] = u[strip].min(), u[strip].max()
            out["sample_id"].append(shard.read("sample_id").astype(np.int64))
            out["cut"].append(cut)
            out["handle"].append(found)
            for k, v in facts.items():
                out[k].append(v)
    return class_name, {k: np.concatenate(v) for k, v in out.items()}


def oracle_along_error_m(f: dict, half_range_m: tuple[float, float]):
    """The oracle's expected error (m) along the hinge per image and door (module docstring), and its
    error on the image's true height (m): over many images the two agree where the posterior is right."""
    import numpy as np

    from articulated_dataset.methods.dense.handle import HANDLE_LEN_M

    grid = np.linspace(half_range_m[0], half_range_m[1], GRID_POINTS)
    err = np.zeros(f["cut"].shape)
    realised = np.zeros(f["cut"].shape)
    for i, j in zip(*np.nonzero(f["cut"] & ~f["handle"] & np.isfinite(f["half_m"]))):
        allowed = 2.0 * grid >= f["top_m"][i, j] - 1e-9
        lo, hi = f["strip_lo_m"][i, j], f["strip_hi_m"][i, j]
        if np.isfinite(lo):
            allowed &= (grid + 0.5 * HANDLE_LEN_M < lo) | (grid - 0.5 * HANDLE_LEN_M > hi)
        if not allowed.any():  # the facts exclude every height: the handle missed; the door's top alone
            allowed = 2.0 * grid >= f["top_m"][i, j] - 1e-9
        post = grid[allowed]
        err[i, j] = np.abs(post - np.median(post)).mean()
        realised[i, j] = abs(np.median(post) - f["half_m"][i, j])
    return err, realised


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--truth", type=Path, required=True, help="a split of the cabinet or the two-door cabinet")
    p.add_argument("--predictions", type=Path, default=None, help="predictions.h5 of that split (optional)")
    args = p.parse_args(argv)
    import numpy as np

    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.methods.mdn.data import resolve_split_dir, split_class

    try:
        class_name = split_class(resolve_split_dir(args.truth))
        if class_name not in FULL_HEIGHT_DOOR_CLASSES:
            raise UserError(f"{args.truth}: holds {class_name!r}; only {', '.join(FULL_HEIGHT_DOOR_CLASSES)} "
                            "have doors of the object's full height")
        _, f = door_facts(args.truth)
    except UserError as exc:  # a missing or malformed folder, or another class: one line
        print(f"height_floor: error: {exc}", file=sys.stderr)
        return 2
    lo, hi = get_class(class_name).table.geometry["height_m"]
    err, realised = oracle_along_error_m(f, (0.5 * lo, 0.5 * hi))
    n, J = err.shape
    print(f"{class_name}: {n} images, {J} door(s); height_m uniform on [{lo:g}, {hi:g}] m")
    model = None
    if args.predictions is not None:
        sys.path.insert(0, str(Path(__file__).parent))
        from error_sources import per_image_errors_of

        model = per_image_errors_of(args.predictions, args.truth, f["sample_id"])["along"]  # cm, in the truth's order
    print("per door: share of the images; the oracle's mean error along the hinge (cm): expected, on the truth"
          + ("; the model's" if model is not None else ""))
    for j in range(J):
        groups = (("top seen", ~f["cut"][:, j]), ("cut, handle found", f["cut"][:, j] & f["handle"][:, j]),
                  ("cut, no handle", f["cut"][:, j] & ~f["handle"][:, j]), ("all", np.ones(n, bool)))
        print(f"  door {j}")
        for name, s in groups:
            if not s.any():
                continue
            line = f"    {name:<18} {s.mean():6.3f}   {CM_PER_M * err[s, j].mean():6.2f} {CM_PER_M * realised[s, j].mean():6.2f}"
            if model is not None:
                line += f"   {model[s, j].mean():6.2f}"
            print(line)
    print(f"floor of the mean axis position error (cm, mean over the doors): {CM_PER_M * err.mean():.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
