"""Generation throughput and size: end to end vs the bare MuJoCo depth render of the same scenes.

Per class (one process): labelled images/s end to end (sampling, xacro, compile, render,
labels, compression, write), images/s of the bare render of the same scenes (compiled
beforehand; per image only mj_kinematics + mj_camlight + mjv_updateScene + mjr_render +
mjr_readPixels of the depth buffer: the floor), their ratio, and bytes per image on disk.
Whole machine (``--workers N``): the same two rates with N processes, measured in the same run.

    python benchmarks/generation.py                      # all classes, 48 objects each, workers 1 and 2
    python benchmarks/generation.py --objects 128 --workers 2
    python benchmarks/generation.py --objects 8 --workers --option-objects 24   # + options only

Generation options beside the default (one process, ``--option-objects`` per class):
end-to-end images/s with ``--camera head``, with ``--intrinsics kinect2`` at the default size,
with ``--table realistic``, with ``--scene kitchen``/``room``, with ``--occluders 2``, with
both, with ``--rgb`` alone and with all three, each next to the paper's setting measured in the same run (a figure, not a target).

Targets: end to end >= 60% of the bare rate; < 4 KB per image; whole machine
>= 1,000 images/s on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")


def _scenes(class_name: str, n_objects: int, seed: int):
    """The final (visible) samples of objects 0..n-1 as the pipeline renders them."""
    from articulated_dataset.generation import GenerationConfig, object_sample, render_object
    from articulated_dataset.generation.render import process_renderer

    config = GenerationConfig(class_name, n_objects=n_objects, seed=seed)
    renderer = process_renderer(config.camera)
    return config, [render_object(object_sample(config, k), config, renderer)[1] for k in range(n_objects)]


def _bare_render(args) -> tuple[int, float]:
    """Render the given scenes with bare MuJoCo calls; returns (images, seconds)."""
    class_name, indices, n_objects, seed = args
    import mujoco
    import numpy as np

    from articulated_dataset.generation.compiled import compile_object
    from articulated_dataset.generation.render import process_renderer
    from articulated_dataset.generation.templating import object_urdf

    config, samples = _scenes(class_name, n_objects, seed)
    obj_class = config.obj_class
    r = process_renderer(config.camera)
    prepared = []
    for k in indices:
        s = samples[k]
        obj = compile_object(obj_class, object_urdf(obj_class, s, config.table), s.pose, config.camera)
        prepared.append((obj.model, mujoco.MjData(obj.model), obj.info.qpos_adr, s.q))
    H, W = config.camera.height_px, config.camera.width_px
    depth = np.zeros((H, W), np.float32)
    n = 0
    seconds = 0.0
    for model, data, adr, qs in prepared:
        r.bind(model)
        t0 = time.perf_counter()
        for q in qs:
            data.qpos[adr] = q
            mujoco.mj_kinematics(model, data)
            mujoco.mj_camlight(model, data)
            mujoco.mjv_updateScene(model, data, r._opt, None, r._cam, mujoco.mjtCatBit.mjCAT_ALL, r._scn)
            mujoco.mjr_render(r._viewport, r._scn, r._con)
            mujoco.mjr_readPixels(None, depth, r._viewport, r._con)
            n += 1
        seconds += time.perf_counter() - t0
    return n, seconds


def _one_raster_thread() -> None:
    os.environ.setdefault("LP_NUM_THREADS", "1")


#: Generation options timed beside the default: name -> keyword arguments of _end_to_end
#: (``camera``: CameraConfig keyword arguments; ``table``: a table name, ``--table NAME``).
OPTIONS = {"default": {}, "--camera head": {"camera": {"mount": "head"}},
           "--intrinsics kinect2": {"camera": {"intrinsics": "kinect2"}}, "--table realistic": {"table": "realistic"},
           "--scene kitchen": {"scene": "kitchen"}, "--scene room": {"scene": "room"}, "--occluders 2": {"occluders": 2},
           "--scene kitchen --occluders 2": {"scene": "kitchen", "occluders": 2}, "--rgb": {"rgb": True},
           "--rgb --scene kitchen --occluders 2": {"rgb": True, "scene": "kitchen", "occluders": 2}}


def _end_to_end(class_name: str, n_objects: int, seed: int, workers: int, out: Path,
                camera: dict | None = None, table: str = "paper", scene: str = "none",
                occluders: int = 0, rgb: bool = False) -> tuple[int, float, int, float]:
    """(images, seconds, bytes, mean pose draws per object) of one generate_split run
    (``camera``: CameraConfig keyword arguments besides the default image size; ``table``:
    the class's table of that name; ``scene``, ``occluders``, ``rgb``: --scene, --occluders, --rgb)."""
    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.core.camera import CameraConfig
    from articulated_dataset.format import read_manifest
    from articulated_dataset.format.manifest import DEFAULT_OBJECTS_PER_SHARD
    from articulated_dataset.generation import GenerationConfig, generate_split

    per_shard = min(DEFAULT_OBJECTS_PER_SHARD, max(1, n_objects // max(workers, 1) // 2))
    config = GenerationConfig(class_name, n_objects=n_objects, seed=seed, objects_per_shard=per_shard,
                              camera=CameraConfig(**(camera or {})), table=get_class(class_name).named_table(table),
                              scene=scene, occluders=occluders, rgb=rgb)
    t0 = time.perf_counter()
    split = generate_split(config, out, workers=workers, overwrite=True)
    seconds = time.perf_counter() - t0
    m = read_manifest(split)
    attempts = sum(s["pose_attempts"] for s in m["shards"]) / m["n_objects"]
    return m["n_images"], seconds, sum(s["bytes"] for s in m["shards"]), attempts


def main() -> None:
    from articulated_dataset.classes.registry import class_names
    from articulated_dataset.core.camera import CameraConfig
    from articulated_dataset.generation.render import process_renderer

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--classes", nargs="*", default=None)
    ap.add_argument("--objects", type=int, default=48, help="objects per class, single-process comparison")
    ap.add_argument("--workers", type=int, nargs="*", default=[2], help="whole-machine runs with these worker counts")
    ap.add_argument("--machine-objects", type=int, default=256,
                    help="objects per class in the whole-machine runs (start-up of the worker processes included)")
    ap.add_argument("--option-objects", type=int, default=24,
                    help="objects per class for the generation options beside the default (0: skip)")
    ap.add_argument("--option-names", nargs="*", default=None, metavar="OPTION",
                    help="time only these options, named without dashes (e.g. default rgb 'scene kitchen occluders 2'); "
                         "default: all")
    ap.add_argument("--seed", type=int, default=1234)
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args()
    classes = args.classes or class_names()
    process_renderer(CameraConfig())  # GL context creation is per process, not per image
    results = {"per_class": {}, "machine": {}, "cpu_count": os.cpu_count()}
    print(f"{'class':14s} {'e2e img/s':>10s} {'bare img/s':>11s} {'ratio':>6s} {'bytes/img':>10s} {'pose draws/obj':>15s}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in classes:
            _end_to_end(name, 2, args.seed + 1, 1, Path(tmp) / "warm")  # warm caches (template parse)
            n, sec, nbytes, attempts = _end_to_end(name, args.objects, args.seed, 1, Path(tmp))
            bn, bsec = _bare_render((name, range(args.objects), args.objects, args.seed))
            e2e, bare = n / sec, bn / bsec
            results["per_class"][name] = {"e2e_img_s": e2e, "bare_img_s": bare, "ratio": e2e / bare,
                                          "bytes_per_img": nbytes / n, "pose_draws_per_object": attempts}
            print(f"{name:14s} {e2e:10.0f} {bare:11.0f} {e2e / bare:6.2f} {nbytes / n:10.0f} {attempts:15.2f}")
        if args.option_objects > 0:
            results["options"] = {}
            print(f"\nend to end, 1 process, {args.option_objects} objects per class (img/s; pose draws/object):")
            chosen = {k: v for k, v in OPTIONS.items() if args.option_names is None or k.replace("--", "") in args.option_names}
            print(f"{'class':14s} " + " ".join(f"{k:>30s}" for k in chosen))
            for name in classes:
                row = {}
                for label, option in chosen.items():
                    n, sec, nbytes, attempts = _end_to_end(name, args.option_objects, args.seed, 1, Path(tmp) / "options",
                                                           **option)
                    row[label] = {"e2e_img_s": n / sec, "bytes_per_img": nbytes / n, "pose_draws_per_object": attempts}
                results["options"][name] = row
                print(f"{name:14s} " + " ".join(f"{v['e2e_img_s']:>13.0f} ({v['pose_draws_per_object']:4.2f}) {v['bytes_per_img']:6.0f} B"
                                                 for v in row.values()))
        for w in args.workers:
            ctx = mp.get_context("spawn")
            tot_n = tot_sec = 0.0
            bare_n = 0
            bare_wall = 0.0
            per_class = {}
            for name in classes:
                n, sec, _, _ = _end_to_end(name, args.machine_objects, args.seed, w, Path(tmp))
                per_class[name] = n / sec
                tot_n += n
                tot_sec += sec
                chunks = [(name, range(i, args.objects, w), args.objects, args.seed) for i in range(w)]
                with ctx.Pool(w, initializer=_one_raster_thread) as pool:
                    parts = pool.map(_bare_render, chunks)
                bare_n += sum(p[0] for p in parts)
                bare_wall += max(p[1] for p in parts)
            e2e, bare = tot_n / tot_sec, bare_n / bare_wall
            results["machine"][w] = {"e2e_img_s": e2e, "bare_img_s": bare, "ratio": e2e / bare, "per_class_e2e_img_s": per_class}
            print("  per class: " + ", ".join(f"{k} {v:.0f}" for k, v in per_class.items()))
            print(f"whole machine, {w} workers: end to end {e2e:.0f} img/s (incl. process start-up), bare render {bare:.0f} img/s, ratio {e2e / bare:.2f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
