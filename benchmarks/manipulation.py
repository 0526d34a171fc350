"""Manipulation success: open test objects in simulation with true or predicted kinematics.

For every class found under ``--data`` (``<root>/<class>/<split>``), the first ``--objects``
objects of the split are opened "from closed": each object's view nearest closed (smallest
sum over joints of q / q_max; with the default 16 views it lies in the first 1/16 of the
range for 1-DoF objects, the first 1/4 per joint for 2-DoF ones) is the observation; the
simulated object starts at that view's true configuration, and the robot opens EACH joint
in turn (2-DoF objects give two trials per object, the other joint left where it is) to
60 deg / 20 cm, clipped to the joint range.  The plan comes from the truth labels of that
view and from every ``--predictions NAME=FILE`` (matched by sample_id).  Success, force
limit and the gripper model are those of :mod:`articulated_dataset.manipulation`
(docs/manipulation.md).

    python benchmarks/manipulation.py --data data --objects 20
    python benchmarks/manipulation.py --data data --predictions mean=preds/mean.h5 \\
        --predictions nn=preds/nn.h5 --scores scores.json --json manipulation.json
    python benchmarks/manipulation.py --data data --figure docs/img/manipulation.png --objects 0
    python benchmarks/manipulation.py --data data --objects 50 --model dense --model mdn-small \
        --closed-loop dense --threads 1 --json manipulation.json

``--model NAME`` (a shipped model) or ``--model NAME=CHECKPOINT`` (``{class}`` in the path is
replaced by each class) estimates from each observed view's stored depth image (1 image);
``--closed-loop [NAME ...]`` also opens with those models in closed loop
(:func:`articulated_dataset.manipulation.closed_loop_trial`: extra views before grasping,
one image after each segment of the motion), reported as ``NAME-closed-loop``.  The
``images`` column is the mean number of depth images a method's controller used (truth: 0;
predictions files, perturbed truth and one-view models: 1).

With ``--scores`` (the JSON of ``artdata score --json``) the Table 1 errors of each
(class, method) are printed beside its success rate.  ``--perturb NAME=POS_CM,ROT_DEG,Q_DEG,Q_CM``
adds the truth with random errors of those mean sizes (a what-if for a model of that accuracy).

A class generated from a third-party URDF (``artdata generate --urdf``) is rebuilt from the
URDF given with ``--urdf CLASS=FILE`` (and ``--mesh-root CLASS=DIR`` where it was generated with
one), used only if its sha256 is the one the split recorded; the path its manifest records is
not opened outside the split folder, so without ``--urdf`` such a class stops the run with one
line.  Classes named with ``--urdf`` are run besides the built-in ones found under ``--data``.

Columns: ``success`` (all three below); ``grasped`` (the planned grasp lands within
GRASP_CAPTURE_M of the true handle bar); ``reached`` (final configuration within 5 deg / 2 cm
of the target); ``<=limits`` (of the grasped trials: peak force <= MAX_FORCE_N and torque <=
MAX_TORQUE_NM); ``median |dq|`` (all trials); median / max peak force and max peak torque
(grasped trials).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from articulated_dataset.classes.registry import REVOLUTE  # noqa: E402
from articulated_dataset.core.rotations import axis_angle_quat, quat_multiply  # noqa: E402

#: Table 1 metrics shown beside the success rate (keys of ``artdata score --json`` rows).
TABLE1_METRICS = (("axis_position_error_cm", "pos cm"), ("axis_rotation_error_deg", "rot deg"),
                  ("configuration_error", "config"))
TRUTH = "truth"


def nearest_closed_rows(labels: dict, q_ranges, n_objects: int | None) -> list[int]:
    """Row of each object's view nearest closed: argmin over its views of sum_j q_j / q_max_j."""
    span = np.array([max(hi - lo, 1e-12) for lo, hi in q_ranges])
    score = (labels["q"].astype(np.float64) / span).sum(axis=1)
    objects = np.unique(labels["object_index"])
    if n_objects is not None:
        objects = objects[:n_objects]
    rows = []
    for k in objects:
        idx = np.nonzero(labels["object_index"] == k)[0]
        rows.append(int(idx[np.argmin(score[idx])]))
    return rows


def perturb(estimate, joint_types, rng: np.random.Generator, errors: tuple[float, float, float], name: str):
    """The truth with random errors of the given MEAN sizes (axis position m, axis rotation rad,
    configuration rad | m): position offset ~ N(0, s^2 I) with s = e / sqrt(8 / pi) (the mean of
    a 3-D Gaussian's norm is s sqrt(8 / pi)); the axis frame turned by |N(0, s^2)|,
    s = e sqrt(pi / 2), about a random axis perpendicular to the joint axis; q + N(0, s^2)."""
    from articulated_dataset import manipulation as M
    from articulated_dataset.manipulation import ObjectKinematics

    pos_e, rot_e, q_e = errors
    pose = estimate.axis_pose.copy()
    q = estimate.q.copy()
    for j in range(len(q)):
        _, rot = M.axis_frame(pose[j])
        pose[j, :3] += rng.normal(0.0, pos_e / math.sqrt(8 / math.pi), 3)
        phi = rng.uniform(0, 2 * math.pi)
        turn_axis = math.cos(phi) * rot[:, 0] + math.sin(phi) * rot[:, 1]
        angle = abs(rng.normal(0.0, rot_e * math.sqrt(math.pi / 2)))
        pose[j, 3:] = quat_multiply(axis_angle_quat(turn_axis, angle), pose[j, 3:])
        q_scale = q_e[0] if joint_types[j] == REVOLUTE else q_e[1]
        q[j] += rng.normal(0.0, q_scale * math.sqrt(math.pi / 2))
    return ObjectKinematics(pose, q, estimate.part_offset, estimate.geometry, source=name)


def run_class(split_dir: Path, n_objects: int | None, predictions: dict[str, list[Path]], perturbations: dict,
              seed: int, progress: bool, models: dict[str, str] | None = None,
              closed_loop: set[str] | None = None, touch: bool = True, urdf: Path | None = None,
              mesh_root: Path | None = None) -> list[dict]:
    """One record per (object, joint, method) trial of one split.

    ``models``: method name -> ``--model`` spec (a shipped name, or a checkpoint path in which
    ``{class}`` is replaced by the class name); each estimates from the observed view's stored
    depth image (1 image), and those named in ``closed_loop`` also run
    :func:`~articulated_dataset.manipulation.closed_loop_trial` as method ``NAME-closed-loop``
    (``touch``: closing the part by touch first, its ``close_first``).
    A class without a checkpoint (a missing ``{class}`` file, no shipped weights) has no
    trials for that method (reported as missing).  ``urdf`` / ``mesh_root``: the files a
    third-party URDF class is rebuilt from (``--urdf``, ``--mesh-root``)."""
    from tqdm import tqdm

    from articulated_dataset import manipulation as M
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.generation import GenerationConfig
    from articulated_dataset.generation.sampling import stable_key

    path, manifest, labels = M.read_split_labels(split_dir)
    config = GenerationConfig.from_dict(manifest["config"])
    cls = config.class_name
    estimates = {}
    for name, files in predictions.items():
        for p in files:
            if cls in classes_in(p):
                _, estimates[name] = M.load_prediction_estimates(p, cls)
                break
    rng = np.random.default_rng([seed, stable_key(cls)])
    estimators = {}
    for name, spec in (models or {}).items():
        try:
            estimators[name] = M.make_estimator(spec.replace("{class}", cls), cls)
        except UserError as exc:
            print(f"manipulation.py: {cls}: no {name} model ({exc}); its trials are reported missing", file=sys.stderr)
    rows = nearest_closed_rows(labels, config.table.q, n_objects)
    records = []
    for r in tqdm(rows, desc=f"{cls}/{manifest['split']}", disable=not progress, dynamic_ncols=True):
        row = M.label_row(labels, r)
        obj = M.load_true_object(manifest, row, split_dir=split_dir, urdf=urdf, mesh_root=mesh_root,
                                 hint=f"; give its URDF with --urdf {cls}=FILE")
        sid = int(row["sample_id"])
        methods = {TRUTH: obj.truth()}
        for name, errors in perturbations.items():
            methods[name] = perturb(obj.truth(), obj.joint_types, rng, errors, name)
        methods.update({name: est[sid] for name, est in estimates.items() if sid in est})
        images = {name: 1 for name in methods if name != TRUTH}  # one image: the observed view (or its prediction)
        images[TRUTH] = 0
        failed = {}  # method -> why the model gave no estimate of the observed image
        if estimators:
            depth, K, _ = M.stored_image(split_dir, r)
            for name, est in estimators.items():
                images[name] = 1
                try:
                    methods[name] = est(depth, K)
                except UserError as exc:
                    failed[name] = str(exc)
        ident = {"class": cls, "object_index": int(row["object_index"]), "image_index": int(row["image_index"]),
                 "sample_id": sid}
        for j in range(obj.n_joints):
            for name, estimate in methods.items():
                _, res = M.run_trial(obj, estimate, j)
                res.images_used = images[name]
                records.append({"method": name, **ident, **res.to_dict()})
            for name, why in failed.items():
                target = obj.clip_target(j, M.default_target(obj.joint_types[j]))
                records.append({"method": name, **ident, **M.no_plan_result(obj, j, target, why).to_dict()})
            if closed_loop:
                for name, est in ((n, e) for n, e in estimators.items() if n in closed_loop):
                    loop_rng = np.random.default_rng([seed, stable_key(cls), sid, j])
                    try:
                        _, res = M.closed_loop_trial(obj, est, j, depth, K, loop_rng, close_first=touch)
                    except UserError as exc:  # no estimate of the observed image
                        target = obj.clip_target(j, M.default_target(obj.joint_types[j]))
                        res = M.no_plan_result(obj, j, target, str(exc))
                    records.append({"method": f"{name}-closed-loop", **ident, **res.to_dict(),
                                    "views": res.views})
        for name in list(estimates) + [n for n in (models or {}) if n not in estimators]:
            if name not in methods:
                records.append({"class": cls, "method": name, "sample_id": sid, "missing": True})
    return records


_CLASSES_IN: dict[Path, tuple[str, dict]] = {}


def classes_in(path: Path) -> list[str]:
    """Classes of a predictions file (read once)."""
    from articulated_dataset.benchmark.predictions import read_predictions

    if path not in _CLASSES_IN:
        attrs, per_class = read_predictions(path)
        _CLASSES_IN[path] = (str(attrs.get("method", path.stem)), per_class)
    return list(_CLASSES_IN[path][1])


def summarize(records: list[dict]) -> list[dict]:
    """Success rates and medians per (class, method), in first-seen order."""
    from articulated_dataset.core.units import format_q

    keys = list(dict.fromkeys((r["class"], r["method"]) for r in records))
    out = []
    for cls, method in keys:
        rs = [r for r in records if r["class"] == cls and r["method"] == method and not r.get("missing")]
        missing = sum(1 for r in records if r["class"] == cls and r["method"] == method and r.get("missing"))
        if not rs:
            out.append({"class": cls, "method": method, "trials": 0, "missing": missing})
            continue
        frac = lambda k, rr: float(np.mean([bool(r[k]) for r in rr])) if rr else float("nan")  # noqa: E731
        held = [r for r in rs if r["grasped"]]  # forces exist only for trials that held the handle
        types = sorted({r["joint_type"] for r in rs})
        err = float(np.median([r["error"] for r in rs]))
        force = [r["max_force_n"] for r in held]
        out.append({
            "class": cls, "method": method, "trials": len(rs), "missing": missing,
            "success": frac("success", rs), "grasped": frac("grasped", rs), "reached": frac("reached", rs),
            "within_limits_of_grasped": frac("within_limits", held),
            "median_error": err, "median_error_text": format_q(err, types[0]) if len(types) == 1 else f"{err:.3f}",
            "median_max_force_n": float(np.median(force)) if held else float("nan"),
            "max_max_force_n": float(np.max(force)) if held else float("nan"),
            "max_max_torque_nm": float(np.max([r["max_torque_nm"] for r in held])) if held else float("nan"),
            "mean_images_used": float(np.mean([r.get("images_used", 0) for r in rs])),
            "max_images_used": int(np.max([r.get("images_used", 0) for r in rs])),
            "q_reached": [r["q_reached"] for r in rs], "q_target": [r["q_target"] for r in rs],
        })
    return out


def load_scores(path: Path | None) -> list[dict]:
    if path is None:
        return []
    try:
        return json.loads(Path(path).read_text()).get("rows", [])
    except (OSError, json.JSONDecodeError, AttributeError) as exc:
        sys.exit(f"manipulation.py: error: cannot read scores {path}: {exc}")


def find_score(scores: list[dict], cls: str, name: str, paths: list[Path]) -> dict | None:
    """The scores row of (class, method): matched by predictions path, then by name / the files' method attribute."""
    resolved = {Path(p).resolve() for p in paths}
    for row in scores:
        p = row.get("predictions")
        if row.get("class") == cls and p and Path(p).resolve() in resolved:
            return row
    methods = {name} | {_CLASSES_IN[p][0] for p in paths if p in _CLASSES_IN}
    for row in scores:
        if row.get("class") == cls and row.get("method") in methods:
            return row
    return None


def format_table(summary: list[dict], scores: list[dict], predictions: dict[str, list[Path]]) -> str:
    head = f"{'class':13s} {'method':22s} {'trials':>6s} {'success':>8s} {'grasped':>8s} {'reached':>8s} {'<=limits':>8s} " \
           f"{'median |dq|':>12s} {'median F':>9s} {'max F':>7s} {'max tau':>8s} {'images':>7s}"
    if scores:
        head += "   Table 1: " + "  ".join(f"{t:>14s}" for _, t in TABLE1_METRICS)
    lines = [head, "-" * len(head)]
    for s in summary:
        if s["trials"] == 0:
            lines.append(f"{s['class']:13s} {s['method']:22s} {0:6d}  (no predictions for the selected views)")
            continue
        pct = lambda k: f"{100 * s[k]:7.1f}%" if s[k] == s[k] else f"{'-':>8s}"  # noqa: E731  (NaN: no grasp)
        num = lambda v, fmt, unit: f"{v:{fmt}}{unit}" if v == v else "-"  # noqa: E731
        line = (f"{s['class']:13s} {s['method']:22s} {s['trials']:6d} {pct('success')} {pct('grasped')} {pct('reached')} "
                f"{pct('within_limits_of_grasped')} {s['median_error_text']:>12s} "
                f"{num(s['median_max_force_n'], '.1f', ' N'):>9s} {num(s['max_max_force_n'], '.0f', ' N'):>7s} "
                f"{num(s['max_max_torque_nm'], '.1f', ' Nm'):>8s} {s['mean_images_used']:7.1f}")
        if scores and s["method"] in predictions:
            row = find_score(scores, s["class"], s["method"], predictions[s["method"]])
            cells = []
            for key, _ in TABLE1_METRICS:
                m = (row or {}).get("metrics", {}).get(key)
                cells.append(f"{m['mean']:6.2f} +/- {m['std']:5.2f}" if m and m.get("mean") is not None else f"{'-':>14s}")
            line += "   " + "  ".join(cells)
        if s["missing"]:
            line += f"   ({s['missing']} views without a prediction)"
        lines.append(line)
    return "\n".join(lines)


# --------------------------------------------------------------------------------------
# Figure: before / after depth renders with the planned path
# --------------------------------------------------------------------------------------

#: Figure renders at twice the dataset's default resolution (same field of view).
FIGURE_SCALE = 2
#: Shift of the axis in the "wrong axis" panel (m), along the axis frame's y (out of the door).
FIGURE_AXIS_OFFSET_M = 0.10


def _figure_case(split_dir: Path, joint: int, offset_m: float, title: str) -> dict:
    """Simulate and render one case of the figure (true grasp; true or shifted axis)."""
    import mujoco

    from articulated_dataset import manipulation as M
    from articulated_dataset.core.camera import CameraConfig, project
    from articulated_dataset.generation import GenerationConfig
    from articulated_dataset.generation.mujoco_scene import set_configuration
    from articulated_dataset.generation.render import process_renderer

    path, manifest, labels = M.read_split_labels(split_dir)
    config = GenerationConfig.from_dict(manifest["config"])
    row = M.label_row(labels, nearest_closed_rows(labels, config.table.q, 1)[0])
    cam0 = config.camera
    camera = CameraConfig(cam0.width_px * FIGURE_SCALE, cam0.height_px * FIGURE_SCALE, cam0.vfov_deg)
    obj = M.load_true_object(manifest, row, camera=camera)
    truth = obj.truth()
    jt = obj.joint_types[joint]
    target = obj.clip_target(joint, M.default_target(jt))
    grasp = M.grasp_pose_from_estimate(truth.axis_pose[joint], truth.part_offset[joint], truth.geometry, jt, truth.q[joint])
    origin, rot = M.axis_frame(truth.axis_pose[joint])
    planned_origin = origin + offset_m * rot[:, 1]
    # the true grasp, planned about the true axis or about one shifted out of the door (y)
    wps = M.plan_waypoints(jt, planned_origin, rot[:, 2], truth.q[joint], target, grasp)
    res = M.execute_plan(obj, wps, joint, target, record=True)
    renderer = process_renderer(camera)
    renderer.bind(obj.model)
    data = mujoco.MjData(obj.model)
    set_configuration(obj.model, data, obj.info.joint_ids, np.asarray(row["q"], np.float64))
    before, _ = renderer.render(data)
    set_configuration(obj.model, data, obj.info.joint_ids, res.trace["q"][-1])
    after, _ = renderer.render(data)
    K = camera.K
    return {
        "title": title, "before": before, "after": after, "result": res, "joint_type": jt,
        "planned_px": project(wps[:, :3], K)[0], "achieved_px": project(res.trace["grasp"], K)[0],
        "planned": wps[:, :3], "achieved": res.trace["grasp"], "origin": origin, "planned_origin": planned_origin,
        "revolute": jt == REVOLUTE,
    }


#: Margin (px) around the object and the path when cropping the renders.
FIGURE_CROP_MARGIN_PX = 20


def _crop_box(case: dict) -> tuple[int, int, int, int]:
    H, W = case["before"].shape
    v, u = np.nonzero((case["before"] > 0) | (case["after"] > 0))
    pts = np.concatenate([case["planned_px"], case["achieved_px"]])
    pts = pts[np.isfinite(pts).all(axis=1)]
    u0, u1 = min(u.min(), pts[:, 0].min()), max(u.max(), pts[:, 0].max())
    v0, v1 = min(v.min(), pts[:, 1].min()), max(v.max(), pts[:, 1].max())
    m = FIGURE_CROP_MARGIN_PX
    return (int(max(u0 - m, 0)), int(min(u1 + m, W - 1)), int(max(v0 - m, 0)), int(min(v1 + m, H - 1)))


def _save_figure(fig, out: Path) -> None:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    print(f"wrote {out}")


def make_figure(root: Path, split: str, out: Path) -> None:
    """Rows: cabinet (true axis), cabinet (axis shifted 10 cm), drawer (true axis).
    Columns: depth before, depth after (with planned and simulated handle paths), top view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from articulated_dataset.core.units import format_q
    from articulated_dataset.manipulation import MAX_FORCE_N

    cases = []
    for cls, joint, offset, title in (("cabinet", 0, 0.0, "cabinet, true axis"),
                                      ("cabinet", 0, FIGURE_AXIS_OFFSET_M,
                                       f"cabinet, axis shifted {100 * FIGURE_AXIS_OFFSET_M:.0f} cm"),
                                      ("drawer", 0, 0.0, "drawer, true axis")):
        d = root / cls / split
        if (d / "manifest.json").is_file():
            cases.append(_figure_case(d, joint, offset, title))
    if not cases:
        sys.exit(f"manipulation.py: error: no cabinet/drawer {split} split under {root} for the figure")
    fig, axes = plt.subplots(len(cases), 3, figsize=(13, 3.4 * len(cases)), squeeze=False,
                             gridspec_kw={"width_ratios": [1, 1, 0.75]})
    for case, row in zip(cases, axes):
        res, jt = case["result"], case["joint_type"]
        u0, u1, v0, v1 = _crop_box(case)
        valid = np.concatenate([case["before"][case["before"] > 0], case["after"][case["after"] > 0]])
        vmin, vmax = float(valid.min()), float(valid.max())
        for ax, key in ((row[0], "before"), (row[1], "after")):
            ax.imshow(np.ma.masked_equal(case[key], 0.0), cmap="viridis_r", vmin=vmin, vmax=vmax, interpolation="nearest")
            p, a = case["planned_px"], case["achieved_px"]
            ax.plot(p[:, 0], p[:, 1], "-", color="white", lw=4)
            ax.plot(p[:, 0], p[:, 1], "-", color="tab:red", lw=2, label="planned grasp path")
            ax.plot(p[0, 0], p[0, 1], "o", color="tab:red", ms=6, mec="white")
            ax.plot(p[-1, 0], p[-1, 1], "*", color="tab:red", ms=13, mec="white")
            if key == "after":
                ax.plot(a[:, 0], a[:, 1], "--", color="black", lw=1.5, label="handle (simulated)")
            ax.set_xlim(u0, u1)
            ax.set_ylim(v1, v0)
            ax.set_xticks([])
            ax.set_yticks([])
        row[0].set_title(f"{case['title']}: before, q = {format_q(res.q_start, jt)}", fontsize=9)
        verdict = "success" if res.success else "FAILURE"
        row[1].set_title(f"after: q = {format_q(res.q_reached, jt)} (target {format_q(res.q_target, jt)}),\n"
                         f"peak force {res.max_force_n:.0f} N (limit {MAX_FORCE_N:.0f} N): {verdict}", fontsize=9)
        row[1].legend(loc="lower right", fontsize=7, framealpha=0.85)
        # top view: camera frame seen from above, x (forward) up, y (left) to the left
        ax = row[2]
        P, A = case["planned"], case["achieved"]
        ax.plot(-P[:, 1], P[:, 0], "-", color="tab:red", lw=2, label="planned")
        ax.plot(-A[:, 1], A[:, 0], "--", color="black", lw=1.5, label="simulated")
        if case["revolute"]:
            o, po = case["origin"], case["planned_origin"]
            ax.plot(-o[1], o[0], "kx", ms=9, mew=2, label="true axis")
            if np.linalg.norm(po - o) > 0:
                ax.plot(-po[1], po[0], "+", color="tab:red", ms=11, mew=2, label="planned axis")
            for pt, style in ((P[0], ":"), (A[-1], ":")):
                ax.plot([-o[1], -pt[1]], [o[0], pt[0]], style, color="gray", lw=1)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("-y (m, right)", fontsize=8)
        ax.set_ylabel("x (m, forward)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title("top view (camera frame)", fontsize=9)
        ax.legend(fontsize=7, loc="best", framealpha=0.85)
    _save_figure(fig, out)


# --------------------------------------------------------------------------------------
# Figure: estimated versus true handle trajectory (open and closed loop)
# --------------------------------------------------------------------------------------

#: Door classes tried (first with data and a model) and the drawer, for the trajectory figure.
TRAJECTORY_DOORS = ("cabinet", "microwave", "refrigerator", "cabinet2", "toaster")
TRAJECTORY_DRAWER = "drawer"


def _trajectory_case(split_dir: Path, spec: str, name: str, seed: int) -> dict | None:
    """Open and closed loop on the view nearest closed of the split's first object, recorded."""
    from articulated_dataset import manipulation as M
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.generation import GenerationConfig
    from articulated_dataset.generation.sampling import stable_key

    path, manifest, labels = M.read_split_labels(split_dir)
    config = GenerationConfig.from_dict(manifest["config"])
    try:
        est = M.make_estimator(spec.replace("{class}", config.class_name), config.class_name)
    except UserError:
        return None
    r = nearest_closed_rows(labels, config.table.q, 1)[0]
    row = M.label_row(labels, r)
    obj = M.load_true_object(manifest, row)
    depth, K, _ = M.stored_image(split_dir, r)
    estimate = est(depth, K)
    plan, open_res = M.run_trial(obj, estimate, 0, record=True)
    open_res.images_used = 1
    loop_plan, loop_res = M.closed_loop_trial(obj, est, 0, depth, K, np.random.default_rng([seed, stable_key(config.class_name)]),
                                              record=True)
    truth = obj.truth()
    true_plan, true_res = M.run_trial(obj, truth, 0, record=True)
    return {"class": config.class_name, "name": name, "obj": obj, "plan": plan, "open": open_res, "loop_plan": loop_plan,
            "loop": loop_res, "true_plan": true_plan, "true": true_res, "estimate": estimate}


def make_trajectory_figure(root: Path, split: str, models: dict[str, str], out: Path, seed: int,
                           classes: list[str] | None = None) -> None:
    """Top views (camera frame seen from above) of a door and a drawer: the true handle path,
    the one-image plan and the closed loop's commanded path, with the true and estimated axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from articulated_dataset.core.units import format_q

    name, spec = next(iter(models.items()))
    cases = []
    for group in (TRAJECTORY_DOORS, (TRAJECTORY_DRAWER,)):
        for cls in (c for c in group if classes is None or c in classes):
            d = root / cls / split
            case = _trajectory_case(d, spec, name, seed) if (d / "manifest.json").is_file() else None
            if case is not None:
                cases.append(case)
                break
    if not cases:
        sys.exit(f"manipulation.py: error: no door or drawer {split} split under {root} with a {name} model")
    fig, axes = plt.subplots(1, len(cases), figsize=(6.2 * len(cases), 5.2), squeeze=False)
    for case, ax in zip(cases, axes[0]):
        jt = case["obj"].joint_types[0]
        tp = case["true"].trace["grasp"]
        ax.plot(-tp[:, 1], tp[:, 0], "-", color="black", lw=3, alpha=0.35, label="true handle path (truth plan)")
        for key, colour, label in (("open", "tab:red", f"{name}, 1 image"), ("loop", "tab:blue", f"{name}, closed loop")):
            res = case[key]
            verdict = "success" if res.success else "failure"
            what = (f"{label}: reached {format_q(res.q_reached, jt)}, {res.images_used} image(s), "
                    f"peak {res.max_force_n:.0f} N: {verdict}")
            if res.grasped:
                cmd = res.trace["command"]
                ax.plot(-cmd[:, 1], cmd[:, 0], "--", color=colour, lw=1.6, label=f"{what} (commanded)")
                g = res.trace["grasp"]
                ax.plot(-g[:, 1], g[:, 0], ":", color=colour, lw=1.2)
            else:
                wp = (case["plan"] if key == "open" else case["loop_plan"]).waypoints
                ax.plot(-wp[:, 1], wp[:, 0], "--", color=colour, lw=1.6, label=f"{what} (planned; {res.failure_reason()})")
        ax.plot(-case["true_plan"].axis_origin[1], case["true_plan"].axis_origin[0], "kx", ms=10, mew=2, label="true axis")
        eo = case["plan"].axis_origin
        ax.plot(-eo[1], eo[0], "+", color="tab:red", ms=12, mew=2, label="estimated axis (1 image)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("-y (m, right)")
        ax.set_ylabel("x (m, forward)")
        ax.set_title(f"{case['class']} (joint 0, {jt}): open from {format_q(case['true'].q_start, jt)} "
                     f"to {format_q(case['true'].q_target, jt)}", fontsize=9)
        ax.legend(fontsize=6.5, loc="upper center", bbox_to_anchor=(0.5, -0.12), framealpha=0.85)
    _save_figure(fig, out)


def _parse_predictions(items: list[str]) -> dict[str, list[Path]]:
    """``NAME=FILE`` items; a NAME may repeat (e.g. one file per class)."""
    out: dict[str, list[Path]] = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            sys.exit(f"manipulation.py: error: --predictions takes NAME=FILE, got {item!r}")
        if name == TRUTH:
            sys.exit(f"manipulation.py: error: the predictions name {TRUTH!r} is reserved")
        if not Path(path).is_file():
            sys.exit(f"manipulation.py: error: predictions file not found: {path}")
        out.setdefault(name, []).append(Path(path))
    return out


def _parse_class_paths(items: list[str], option: str) -> dict[str, Path]:
    """``CLASS=PATH`` items (``--urdf``, ``--mesh-root``) -> {class: path}, one per class."""
    out = {}
    for item in items:
        cls, sep, path = item.partition("=")
        if not sep or not cls or not path or cls in out:
            sys.exit(f"manipulation.py: error: {option} takes CLASS=PATH once per class, got {item!r}")
        out[cls] = Path(path)
    return out


def _parse_models(items: list[str], taken) -> dict[str, str]:
    """``NAME`` (a shipped model, its own name) or ``NAME=SPEC`` items -> {name: spec}."""
    out = {}
    for item in items:
        name, sep, spec = item.partition("=")
        spec = spec if sep else name
        if not name or not spec or name == TRUTH or name in taken or name in out:
            sys.exit(f"manipulation.py: error: bad or duplicate --model name in {item!r}")
        out[name] = spec
    return out


def _parse_perturb(items: list[str], taken) -> dict[str, tuple[float, float, float]]:
    """``NAME=POS_CM,ROT_DEG,Q_DEG,Q_CM`` -> (m, rad, (rad, m))."""
    out = {}
    for item in items:
        name, sep, values = item.partition("=")
        try:
            pos_cm, rot_deg, q_deg, q_cm = (float(v) for v in values.split(","))
        except ValueError:
            sys.exit(f"manipulation.py: error: --perturb takes NAME=POS_CM,ROT_DEG,Q_DEG,Q_CM, got {item!r}")
        if not sep or not name or name == TRUTH or name in taken or name in out:
            sys.exit(f"manipulation.py: error: bad or duplicate --perturb name in {item!r}")
        out[name] = (pos_cm / 100.0, math.radians(rot_deg), (math.radians(q_deg), q_cm / 100.0))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="root holding <class>/<split>/ folders")
    ap.add_argument("--split", default="test")
    ap.add_argument("--classes", nargs="*", default=None, help="default: every class of the paper (the grasp rule's) and URDF object with the "
                    "split under --data")
    ap.add_argument("--objects", type=int, default=20, help="objects per class (first N of the split); 0 = none")
    ap.add_argument("--predictions", action="append", default=[], metavar="NAME=FILE",
                    help="predictions.h5 of a method (repeat; a NAME may repeat, e.g. one file per class)")
    ap.add_argument("--model", action="append", default=[], metavar="NAME[=SPEC]",
                    help="estimate from each observed view's depth image with a model: a shipped one (dense, "
                         "dense-kinect2, mdn-small) or NAME=CHECKPOINT, where {class} in the path is replaced by each "
                         "class (repeat)")
    ap.add_argument("--closed-loop", nargs="*", default=None, metavar="NAME",
                    help="also open in closed loop (extra views, re-estimation while opening) with these --model "
                         "names (none given: every --model); reported as NAME-closed-loop")
    ap.add_argument("--no-touch", action="store_true",
                    help="closed loop without first closing the part by touch (configuration from the images only)")
    ap.add_argument("--threads", type=int, default=1, help="CPU threads for the models (torch)")
    ap.add_argument("--perturb", action="append", default=[], metavar="NAME=POS_CM,ROT_DEG,Q_DEG,Q_CM",
                    help="also plan from the truth with random errors of these MEAN sizes (e.g. Table 1's 'Ours')")
    ap.add_argument("--seed", type=int, default=0, help="seed of --perturb's errors")
    ap.add_argument("--scores", type=Path, default=None, help="JSON of `artdata score --json` for the Table 1 columns")
    ap.add_argument("--json", type=Path, default=None, help="write summary + per-trial records here")
    ap.add_argument("--figure", type=Path, default=None, help="also draw the before/after figure (PNG)")
    ap.add_argument("--trajectory-figure", type=Path, default=None,
                    help="also draw estimated (first --model) versus true handle paths of a door and a drawer (PNG; "
                         "the first door class and the drawer, among --classes, with data and a model)")
    ap.add_argument("--urdf", action="append", default=[], metavar="CLASS=FILE",
                    help="the URDF a third-party class (artdata generate --urdf) was generated from, to rebuild its "
                         "objects (repeat; the class is run besides the built-in ones)")
    ap.add_argument("--mesh-root", action="append", default=[], metavar="CLASS=DIR",
                    help="with --urdf: the folder its meshes are read from, as given to generate --mesh-root")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args(argv)

    from articulated_dataset.core.errors import UserError
    from articulated_dataset.manipulation import GRASP_RULE_CLASSES

    predictions = _parse_predictions(args.predictions)
    models = _parse_models(args.model, predictions)
    loop_names = None if args.closed_loop is None else set(args.closed_loop or models)
    if loop_names is not None and (not models or not loop_names <= set(models)):
        sys.exit("manipulation.py: error: --closed-loop takes names given with --model (none: all of them)")
    if models:
        import torch

        torch.set_num_threads(max(1, args.threads))
    perturbations = _parse_perturb(args.perturb, {**predictions, **models})
    urdfs = _parse_class_paths(args.urdf, "--urdf")
    mesh_roots = _parse_class_paths(args.mesh_root, "--mesh-root")
    if not set(mesh_roots) <= set(urdfs):
        sys.exit("manipulation.py: error: --mesh-root CLASS=DIR needs --urdf CLASS=FILE for the same class")
    try:
        for files in predictions.values():
            for p in files:
                classes_in(p)
    except UserError as exc:
        sys.exit(f"manipulation.py: error: {exc}")
    scores = load_scores(args.scores)
    classes = args.classes or [c for c in [*GRASP_RULE_CLASSES, *urdfs]
                               if (args.data / c / args.split / "manifest.json").is_file()]
    records: list[dict] = []
    t0 = time.perf_counter()
    if args.objects > 0:
        if not classes:
            sys.exit(f"manipulation.py: error: no <class>/{args.split}/manifest.json under {args.data}")
        for cls in classes:
            try:
                records += run_class(args.data / cls / args.split, args.objects, predictions, perturbations,
                                     args.seed, not args.quiet, models, loop_names, not args.no_touch,
                                     urdfs.get(cls), mesh_roots.get(cls))
            except UserError as exc:
                sys.exit(f"manipulation.py: error: {exc}")
        seconds = time.perf_counter() - t0
        summary = summarize(records)
        n_trials = sum(1 for r in records if not r.get("missing"))
        print(f"\nopening from the view nearest closed to 60 deg / 20 cm (clipped), {args.objects} objects per class, "
              f"split {args.split!r}; {n_trials} trials in {seconds:.1f} s ({seconds / max(n_trials, 1):.2f} s/trial)")
        print(format_table(summary, scores, predictions))
        if args.json:
            clean = [{k: (None if isinstance(v, float) and v != v else v) for k, v in s.items()} for s in summary]
            args.json.write_text(json.dumps({"summary": clean, "trials": records}, indent=1) + "\n")
            print(f"wrote {args.json}")
    if args.figure:
        make_figure(args.data, args.split, args.figure)
    if args.trajectory_figure:
        if not models:
            sys.exit("manipulation.py: error: --trajectory-figure needs a --model")
        make_trajectory_figure(args.data, args.split, models, args.trajectory_figure, args.seed, args.classes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
