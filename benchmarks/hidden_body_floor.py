"""How well could any estimator tell a door's angle from the object's turn where the door hides the body?  An oracle's floor.

    python benchmarks/hidden_body_floor.py --truth data/cabinet/test [--predictions data/predictions/cabinet-dense.h5]

Where an open door hides the whole body (the cabinet: 15% of the paper's poses), the image shows
only the door: its hinge and its heading, the object's yaw plus ``q`` about the vertical hinge.
Turning the object by ``d`` about its hinge line while opening the door by ``d`` less leaves the
door where it was; while the body stays hidden, the image is the same.  So the image does not say
how the heading splits into the yaw and ``q``, and the frame's rotation and the configuration are
wrong by the same angle.

The oracle here knows everything about the image's object (its sizes, hinge side, base height,
pose and ``q``) except that split.  For every image with at most ``--max-body-px`` body pixels it
renders the object turned about the hinge line by ``d`` in ``--step-deg`` steps, ``q`` by ``d``
less (with the split's own compiled model, placed as the generator places it), and keeps each
turn whose render has the same mask, pixel for pixel, and the same depth (within
:data:`DEPTH_TOL_M`), and whose yaw, base position and ``q`` lie in the sampling table's ranges.
The table draws them uniformly and independently, so the posterior of ``q`` is uniform over the
kept turns.  Its median is the oracle's estimate, and the posterior's mean absolute deviation from
it is the oracle's expected error.  That error is in ``q`` and, equally, in the frame's rotation
about the hinge (deg).  The mean over all images (0 for the images not searched) is a floor for
the mean configuration error and the mean axis rotation error of any estimator that sees only the
image, since it knows less than the oracle.

The floor is approximate in three ways, each making it lower than the truth's:

* the oracle knows the object's sizes, its base height and the hinge side;
* the generator's rejection of poses that hide a moving part in another of the object's images
  is not applied to the turned poses;
* the images with more than ``--max-body-px`` body pixels are counted as known exactly.

With ``--predictions``, the model's configuration and rotation errors are printed beside the
floor, per group of images.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

#: Candidate renders count as the same image where no depth differs by more than this (m).
DEPTH_TOL_M = 1e-4
#: The unturned render may differ from the stored mask in this many pixels: the rebuilt object is
#: moved by its root body instead of compiled at its pose, and the rounding moves a silhouette
#: pixel now and then (one pixel in 1 of the 1,746 searched images of a 1,000-object cabinet split).
STORED_MASK_TOL_PX = 8
#: A class qualifies where its only joint is revolute about the object's vertical (|z . up| above this).
VERTICAL_COS = 0.999
#: Groups of the printed table, by the body's visible pixels (lower bounds).
BODY_PIXEL_GROUPS = (0, 1, 101, 500)
DEFAULT_STEP_DEG = 0.5
DEFAULT_MAX_BODY_PX = 499


def posterior_error(feasible_q, true_q: float) -> tuple[float, float]:
    """(expected, realised) absolute error of the oracle's estimate, the median of the uniform
    posterior on ``feasible_q`` (1-D, rad): ``mean_k |q_k - median|`` and ``|median - true_q|``."""
    import numpy as np

    feasible_q = np.asarray(feasible_q, dtype=np.float64)
    median = float(np.median(feasible_q))
    return float(np.abs(feasible_q - median).mean()), abs(median - float(true_q))


class TurnedObject:
    """One stored object compiled once and rendered turned about its hinge line.

    ``render(d, q)`` places the object yawed by ``d`` (rad) more than stored, its base moved so that
    the hinge line stays where it was, the door at ``q``, and returns ``(depth_m, mask, pose)`` of
    the render (``pose``: the base's ``x_m``, ``y_m``, ``z_m``, ``yaw_rad``).  Building one binds
    ``renderer`` to it: render the last one built."""

    def __init__(self, config, object_index: int, object_pose, object_yaw: float, axis_origin, renderer):
        import mujoco
        import numpy as np

        from articulated_dataset.generation import compile_object, stored_sample
        from articulated_dataset.generation.mujoco_scene import ORIGIN_POSE, ObjectPlacer
        from articulated_dataset.generation.templating import object_urdf

        self.object_index = object_index
        sample = stored_sample(config, object_index, object_pose, object_yaw)
        obj = compile_object(config.obj_class, object_urdf(config.obj_class, sample, config.table), ORIGIN_POSE,
                             config.camera)
        self.model, self.info, self.renderer = obj.model, obj.info, renderer
        self.data = mujoco.MjData(self.model)
        self.placer = ObjectPlacer(self.model, self.info.base_body)
        renderer.bind(self.model)  # the renderer renders this object until another is built
        self.pose = dict(sample.pose)
        self.base_m = np.array([self.pose["x_m"], self.pose["y_m"], self.pose["z_m"]])
        self.hinge_m = np.asarray(axis_origin, dtype=np.float64)
        # the hinge in the object's yawed frame, which turns with the object
        self.hinge_in_object_m = _rot_z(self.pose["yaw_rad"]).T @ (self.hinge_m - self.base_m)

    def turned_pose(self, d_rad: float) -> dict:
        yaw = self.pose["yaw_rad"] + d_rad
        base = self.hinge_m - _rot_z(yaw) @ self.hinge_in_object_m
        return {"x_m": float(base[0]), "y_m": float(base[1]), "z_m": self.pose["z_m"], "yaw_rad": float(yaw)}

    def render(self, d_rad: float, q_rad: float):
        import numpy as np

        from articulated_dataset.generation.mujoco_scene import set_configuration
        from articulated_dataset.generation.viewpoint import object_in_camera

        pose = self.turned_pose(d_rad)
        self.placer.place(object_in_camera(pose))
        set_configuration(self.model, self.data, self.info.joint_ids, np.array([q_rad]))
        depth, geom = self.renderer.render(self.data)
        return depth.copy(), self.info.mask_from_geoms(geom), pose


def _rot_z(yaw_rad: float):
    """3x3 rotation by ``yaw_rad`` about the camera frame's z (up)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("z", yaw_rad).as_matrix()


def _in(v: float, bounds) -> bool:
    return bounds[0] <= v <= bounds[1]


def image_floor(obj: TurnedObject, q_rad: float, opens_with_yaw: float, table, step_rad: float, stored_mask=None):
    """The q (rad) of every kept turn of one image (the stored pose's included), in turn order.

    ``opens_with_yaw`` is +1 where the door's axis points up (a turn ``d`` of the object is undone by
    ``q - d``), -1 where it points down."""
    import numpy as np

    from articulated_dataset.core.errors import UserError

    depth0, mask0, _ = obj.render(0.0, q_rad)
    if stored_mask is not None and int((mask0 != stored_mask).sum()) > STORED_MASK_TOL_PX:
        raise UserError("the rebuilt object does not render the stored mask (data from another version?)")
    (q_lo, q_hi), = table.q
    kept = []
    reach = int(math.ceil((q_hi - q_lo) / step_rad))
    for k in range(-reach, reach + 1):
        d = k * step_rad
        q = q_rad - opens_with_yaw * d
        if not _in(q, (q_lo, q_hi)):
            continue
        pose = obj.turned_pose(d)
        if not all(_in(pose[key], table.pose[key]) for key in ("x_m", "y_m", "yaw_rad")):
            continue
        depth, mask, _ = obj.render(d, q)
        if np.array_equal(mask, mask0) and float(np.abs(depth - depth0).max()) <= DEPTH_TOL_M:
            kept.append(q)
    return np.array(kept)


def split_floors(truth: Path, step_deg: float = DEFAULT_STEP_DEG, max_body_px: int = DEFAULT_MAX_BODY_PX,
                 progress: bool = True) -> dict:
    """Per image of the split ``truth`` (in sample_id order): ``sample_id``, ``body_px``, ``searched``
    and the oracle's ``expected_deg`` / ``realised_deg`` errors (0 where not searched) and the
    number of kept turns ``kept``."""
    import numpy as np
    from tqdm import tqdm

    from articulated_dataset.core.errors import UserError
    from articulated_dataset.core.rotations import quat_to_matrix
    from articulated_dataset.format import Split
    from articulated_dataset.generation import GenerationConfig
    from articulated_dataset.generation.render import process_renderer

    if not step_deg > 0 or not math.isfinite(step_deg):
        raise UserError(f"--step-deg must be a positive number of degrees, got {step_deg}")
    from articulated_dataset.methods.mdn.data import resolve_split_dir

    split_dir = resolve_split_dir(truth)
    rows = {k: [] for k in ("sample_id", "body_px", "searched", "expected_deg", "realised_deg", "kept")}
    with Split(split_dir) as split:
        config = GenerationConfig.from_dict(split.manifest["config"])
        name = config.class_name
        if config.obj_class.n_joints != 1 or config.obj_class.joint_types[0] != "revolute":
            raise UserError(f"{truth}: holds {name!r}; the floor needs one revolute joint")
        if config.camera.mount != "fixed" or config.has_context:
            raise UserError(f"{truth}: generated with a head camera, a scene or occluders; the oracle rebuilds "
                            "the object alone in the fixed camera")
        renderer = process_renderer(config.camera)
        step = math.radians(step_deg)
        todo = sum(int((sh.read("visible_pixels")[:, 0] <= max_body_px).sum()) for sh in split.shards)
        bar = tqdm(total=todo, desc="hidden-body floor", unit="img", disable=not progress)
        for shard in split.shards:
            oi, sid = shard.read("object_index"), shard.read("sample_id").astype(np.int64)
            vp, q, ap = shard.read("visible_pixels"), shard.read("q"), shard.read("axis_pose").astype(np.float64)
            pose, yaw = shard.read("object_pose"), shard.read("object_yaw").reshape(len(sid), -1)[:, 0]
            mask = shard.read("mask")
            z = quat_to_matrix(ap[:, 0, 3:])[:, :, 2]
            if (np.abs(z[:, 2]) < VERTICAL_COS).any():
                raise UserError(f"{truth}: holds {name!r}, whose door does not turn about the vertical")
            searched = vp[:, 0] <= max_body_px
            obj = None  # the object of the images being searched, built once (a shard holds each object's images together)
            for i in range(len(sid)):
                rows["sample_id"].append(sid[i]), rows["body_px"].append(int(vp[i, 0]))
                rows["searched"].append(bool(searched[i]))
                if not searched[i]:
                    rows["expected_deg"].append(0.0), rows["realised_deg"].append(0.0), rows["kept"].append(1)
                    continue
                if obj is None or obj.object_index != int(oi[i]):
                    obj = TurnedObject(config, int(oi[i]), pose[i], float(yaw[i]), ap[i, 0, :3], renderer)
                kept = image_floor(obj, float(q[i, 0]), float(np.sign(z[i, 2])), config.table, step, mask[i])
                expected, realised = posterior_error(kept, float(q[i, 0]))
                rows["expected_deg"].append(math.degrees(expected)), rows["realised_deg"].append(math.degrees(realised))
                rows["kept"].append(len(kept))
                bar.update(1)
        bar.close()
    out = {k: np.asarray(v) for k, v in rows.items()}
    order = np.argsort(out["sample_id"], kind="stable")
    out = {k: v[order] for k, v in out.items()}
    out["class_name"] = name
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--truth", type=Path, required=True, help="a split of a class with one door hinged about the vertical")
    p.add_argument("--predictions", type=Path, default=None, help="predictions.h5 of that split (optional)")
    p.add_argument("--step-deg", type=float, default=DEFAULT_STEP_DEG, help="the turns' step (deg)")
    p.add_argument("--max-body-px", type=int, default=DEFAULT_MAX_BODY_PX,
                   help="search the images with at most this many body pixels (the others count as known)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    import numpy as np

    from articulated_dataset.core.errors import UserError

    try:
        f = split_floors(args.truth, args.step_deg, args.max_body_px, progress=not args.quiet)
        model = None
        if args.predictions is not None:
            sys.path.insert(0, str(Path(__file__).parent))
            from error_sources import per_image_errors_of

            e = per_image_errors_of(args.predictions, args.truth, f["sample_id"])
            model = e["config"][:, 0], e["rot"][:, 0]
    except UserError as exc:  # a missing or malformed folder, another class, a bad option: one line
        print(f"hidden_body_floor: error: {exc}", file=sys.stderr)
        return 2
    n = len(f["sample_id"])
    print(f"{f['class_name']}: {n} images, {int(f['searched'].sum())} searched (at most {args.max_body_px} body pixels), "
          f"turns of {args.step_deg:g} deg")
    print("body pixels: share of the images; the oracle's mean error (deg): expected, on the truth; part of the mean"
          + ("; the model's configuration, rotation error" if model is not None else ""))
    bounds = BODY_PIXEL_GROUPS + (np.inf,)
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        s = (f["body_px"] >= lo) & (f["body_px"] < hi)
        if not s.any():
            continue
        label = f"{lo}" if hi == lo + 1 else (f"{lo}+" if hi == np.inf else f"{lo}-{int(hi) - 1}")
        known = " (not searched: 0)" if not f["searched"][s].any() else ""
        line = (f"  {label:<8} {s.mean():6.3f}   {f['expected_deg'][s].mean():6.2f} {f['realised_deg'][s].mean():6.2f}"
                f"   {f['expected_deg'][s].sum() / n:6.3f}")
        if model is not None:
            line += f"   {model[0][s].mean():6.2f} {model[1][s].mean():6.2f}"
        print(line + known)
    print(f"floor of the mean configuration error and of the mean axis rotation error (deg): {f['expected_deg'].mean():.2f}")
    if model is not None:
        print(f"the model's: configuration {model[0].mean():.2f}, rotation {model[1].mean():.2f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
