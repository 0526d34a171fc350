"""Shared functions of the tests: render chosen configurations of one object and check its labels,
the one-line error rule (:func:`assert_one_line_error`), snapshots of folders a refused command
must leave as they were, crafted files, and the repository's root (:data:`ROOT`)."""

from __future__ import annotations

import dataclasses
import importlib.util
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np

from articulated_dataset.benchmark.predictions import PREDICTIONS_FORMAT_VERSION
from articulated_dataset.classes.base import PRISMATIC
from articulated_dataset.core.camera import CameraConfig, backproject
from articulated_dataset.core.rotations import quat_to_matrix
from articulated_dataset.generation import GenerationConfig, object_sample, render_object
from articulated_dataset.generation.compiled import compile_object as compile_urdf
from articulated_dataset.generation.labels import MASK_BODY, MASK_FIRST_PART, geom_corners_world, read_object_labels
from articulated_dataset.generation.mujoco_scene import ORIGIN_POSE, ObjectPlacer, set_configuration
from articulated_dataset.generation.render import process_renderer
from articulated_dataset.generation.templating import object_urdf
from articulated_dataset.generation.viewpoint import object_in_camera

#: The repository's root folder (tests/ is one level below it, whatever the test file's depth).
ROOT = Path(__file__).resolve().parent.parent


def final_object(class_name: str, index: int = 0, camera: CameraConfig | None = None, split: str = "train", table=None):
    """(config, sample) of a visible object, its pose as finally used by the pipeline
    (``table``: a sampling table other than the class's default, e.g. its realistic one)."""
    config = GenerationConfig(class_name, split=split, n_objects=index + 1, camera=camera or CameraConfig(), table=table)
    renderer = process_renderer(config.camera)
    _, sample, _ = render_object(object_sample(config, index), config, renderer)
    return config, sample


def object_transform(sample, image: int = 0) -> np.ndarray:
    """4x4 pose of the object's base in the camera frame of image ``image`` (the sampled
    pose; with a head camera, seen from that image's camera)."""
    return object_in_camera(sample.pose, None if sample.views is None else sample.views[image])


def compile_object(config, sample, image: int = 0):
    """Compile the object as the pipeline rendered image ``image`` (a head camera's object is
    built at the origin and placed in that image's camera frame); labels read from the model."""
    obj_class = config.obj_class
    urdf = object_urdf(obj_class, sample, config.table)
    head = sample.views is not None
    obj = compile_urdf(obj_class, urdf, ORIGIN_POSE if head else sample.pose, config.camera)
    model, info = obj.model, obj.info
    data = mujoco.MjData(model)
    if head:
        ObjectPlacer(model, info.base_body).place(object_transform(sample, image))
    labels = read_object_labels(model, data, info, obj_class)
    return urdf, model, data, info, labels


def closed_boxes(model, data, info, sample, n_joints: int) -> tuple[tuple, list[tuple]]:
    """Boxes (lo, hi) in the object frame at q = 0: the whole closed object's (every geom,
    handles included) and each moving part's (its non-handle geoms)."""
    set_configuration(model, data, info.joint_ids, np.zeros(n_joints))
    T = object_transform(sample)

    def box(geoms):
        p = to_object_frame(geom_corners_world(model, data, geoms), T)
        return p.min(0), p.max(0)

    parts = [box(np.nonzero((info.geom_part == MASK_FIRST_PART + j) & ~info.geom_is_handle)[0]) for j in range(n_joints)]
    return box(np.arange(model.ngeom)), parts


def closed_face(part_box, d: float, h: float) -> tuple[int, float]:
    """The closed part's outer face, as (axis, coordinate) in the object frame: of its box's
    front (x = lo) and top (z = hi) faces, the one that stands outside the body's box (in front of
    x = -d/2, above z = h) with the larger area: a door's or drawer's front, a lid's top."""
    (lo, hi) = part_box
    size = hi - lo
    faces = []
    if lo[0] < -d / 2 - OUTSIDE_TOL_M:
        faces.append((size[1] * size[2], 0, lo[0]))
    if hi[2] > h + OUTSIDE_TOL_M:
        faces.append((size[0] * size[1], 2, hi[2]))
    assert faces, part_box
    _, axis, value = max(faces)
    return axis, value


_MARGINS: dict = {}


def closed_margins_m(obj_class) -> tuple[np.ndarray, np.ndarray]:
    """How far a closed object of the class (default table, every geom) reaches beyond its body's
    box [-d/2, d/2] x [-w/2, w/2] x [0, h] (the stored ``geometry`` label): (below lo, above hi),
    in m, at least 0.  The templates
    build doors, lids, handles and overhangs of fixed sizes, so one object tells the class's."""
    if obj_class.name not in _MARGINS:
        config, sample = final_object(obj_class.name, index=1)
        _, model, data, info, labels = compile_object(config, sample)
        (lo, hi), _ = closed_boxes(model, data, info, sample, obj_class.n_joints)
        d, w, h = np.asarray(labels["geometry"], np.float64)[:3]  # the body's box, as stored
        _MARGINS[obj_class.name] = (np.maximum(np.array([-d / 2, -w / 2, 0.0]) - lo, 0.0),
                                    np.maximum(hi - np.array([d / 2, w / 2, h]), 0.0))
    return _MARGINS[obj_class.name]


def render_at(config, model, data, info, q):
    renderer = process_renderer(config.camera)
    renderer.bind(model)
    set_configuration(model, data, info.joint_ids, np.asarray(q, dtype=float))
    depth, geom_id = renderer.render(data)
    return depth, info.mask_from_geoms(geom_id)


def part_points(config, depth, mask, joint):
    return backproject(depth, config.camera.K, mask == MASK_FIRST_PART + joint)


def rotate_about_axis(points, origin, direction, angle_rad):
    """Rodrigues rotation of points about the line (origin, unit direction)."""
    k = direction / np.linalg.norm(direction)
    p = points - origin
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return origin + p * c + np.cross(k, p) * s + np.outer(p @ k, k) * (1 - c)


def to_object_frame(points, pose):
    """Camera-frame points -> object frame given the sampled pose (x_m, y_m, z_m, yaw_rad)
    or a 4x4 pose of the object in the camera frame (:func:`object_transform`)."""
    T = pose if isinstance(pose, np.ndarray) else object_in_camera(pose)
    return (points - T[:3, 3]) @ T[:3, :3]


def nearest_distances(a, b, chunk=2048):
    """For each point of a, the distance to the nearest point of b (brute force)."""
    out = np.empty(len(a))
    for i in range(0, len(a), chunk):
        d2 = ((a[i:i + chunk, None, :] - b[None, :, :]) ** 2).sum(-1)
        out[i:i + chunk] = np.sqrt(d2.min(1))
    return out


def with_q(sample, q):
    return dataclasses.replace(sample, q=np.atleast_2d(q))


def surface_distances(points, depth, mask_sel, K):
    """Depth residual (m) of camera-frame points against a rendered surface.

    Each point is projected into the image; the surface depth there is interpolated
    bilinearly in inverse depth (exact inside a planar face) from the four neighbouring
    pixels, which must all belong to ``mask_sel``.  Returns |z_point - z_surface| for the
    points that project inside such pixel quads.
    """
    from articulated_dataset.core.camera import project

    uv, z = project(points, K)
    H, W = depth.shape
    u0 = np.floor(uv[:, 0]).astype(int)
    v0 = np.floor(uv[:, 1]).astype(int)
    ok = (u0 >= 0) & (v0 >= 0) & (u0 < W - 1) & (v0 < H - 1) & (z > 0)
    u0, v0, uv, z = u0[ok], v0[ok], uv[ok], z[ok]
    quad = [(v0, u0), (v0, u0 + 1), (v0 + 1, u0), (v0 + 1, u0 + 1)]
    inside = np.all([mask_sel[v, u] for v, u in quad], axis=0)
    fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
    inv = [1.0 / np.where(depth[v, u] > 0, depth[v, u], np.inf) for v, u in quad]
    inv_z = inv[0] * (1 - fu) * (1 - fv) + inv[1] * fu * (1 - fv) + inv[2] * (1 - fu) * fv + inv[3] * fu * fv
    return np.abs(z[inside] - 1.0 / inv_z[inside])


#: Template constants (classes/common.xacro): panel thickness and handle standoff (m),
#: and the tolerance of a pixel's point against the object's box.
PANEL_M = 0.02
HANDLE_STANDOFF_M = 0.03
BOX_TOL_M = 0.003
#: How far a closed part's face must stand beyond the body's box to count as outside it (m).
OUTSIDE_TOL_M = 1e-4
#: Stored fields :func:`check_stored_images` reads.
IMAGE_CHECK_FIELDS = ("depth", "mask", "q", "axis_origin", "axis_direction", "object_pose", "geometry")


def unmove(points, origin, direction, joint_type, q):
    """Points of a part at configuration ``q`` moved back to the closed configuration."""
    if joint_type == PRISMATIC:
        return points - q * direction
    return rotate_about_axis(points, origin, direction, -q)


def check_stored_images(obj_class, a: dict, K) -> tuple[int, int, int]:
    """The stored labels ``a`` (:data:`IMAGE_CHECK_FIELDS`) against their own pixels, image
    by image: body pixels lie in the object's box (object_pose, geometry); each moving part's
    pixels, moved back by -q about the labelled axis, lie in the closed object's box (+
    handle).  Returns (parts open >= 30% checked, those whose pixels *not* moved back leave
    the box: the negative control, body pixels seen)."""
    detected = checked = n_body = 0
    for i in range(len(a["q"])):
        pose = a["object_pose"][i].astype(np.float64)
        R, t = quat_to_matrix(pose[3:]), pose[:3]
        d, w, h = a["geometry"][i, :3].astype(np.float64)
        below, above = closed_margins_m(obj_class)
        lo = np.array([-d / 2 - max(below[0], PANEL_M + HANDLE_STANDOFF_M), -w / 2 - below[1], -below[2]]) - BOX_TOL_M
        hi = np.array([d / 2, w / 2, h]) + above + BOX_TOL_M
        inside = lambda p: np.all((p >= lo) & (p <= hi), axis=1)  # noqa: E731
        body = (backproject(a["depth"][i], K, a["mask"][i] == MASK_BODY) - t) @ R
        assert len(body) == 0 or inside(body).mean() > 0.995  # doors may hide most of the body
        n_body += len(body)
        for j, spec in enumerate(obj_class.joints):
            pts = backproject(a["depth"][i], K, a["mask"][i] == MASK_FIRST_PART + j)
            o, u, q = (a[k][i, j].astype(np.float64) for k in ("axis_origin", "axis_direction", "q"))
            closed = (unmove(pts, o, u, spec.type, q) - t) @ R
            assert inside(closed).mean() > 0.995, (obj_class.name, i, j)
            lo_q, hi_q = obj_class.table.q[j]
            if q >= lo_q + 0.3 * (hi_q - lo_q):
                checked += 1
                detected += inside((pts - t) @ R).mean() < 0.9
    return checked, detected, n_body


def write_flap_urdf(folder):
    """A third-party URDF for tests: a box with a flap, one revolute joint, primitive geometry
    only.  Returns the file's path (``folder/flap.urdf``)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "flap.urdf"
    box = '<geometry><box size="{}"/></geometry>'
    path.write_text(f"""<robot name="flap">
  <link name="base"><visual><origin xyz="0 0 0.2"/>{box.format("0.4 0.4 0.4")}</visual></link>
  <link name="flap"><visual><origin xyz="0.01 -0.2 0.2"/>{box.format("0.02 0.4 0.4")}</visual></link>
  <joint name="hinge" type="revolute"><parent link="base"/><child link="flap"/><origin xyz="-0.2 0.2 0"/>
    <axis xyz="0 0 1"/><limit lower="0" upper="1.5" effort="1" velocity="1"/></joint>
</robot>""")
    return path


def load_script(path: Path, name: str):
    """A script of the repository (benchmarks/, scripts/: not a package) imported as module ``name``."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # before it runs: its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def generated_split(root: Path, class_name: str, n_objects: int, seed: int) -> Path:
    """``artdata generate`` of ``n_objects`` test objects of ``class_name`` under ``root``, as a user runs it; the split's folder."""
    from click.testing import CliRunner

    from articulated_dataset.cli import main

    r = CliRunner().invoke(main, ["generate", "--class", class_name, "--n", str(n_objects), "--split", "test",
                                  "--seed", str(seed), "--out", str(root), "-q"])
    assert r.exit_code == 0, r.output
    return Path(root) / class_name / "test"


def split_copy_with(src: Path, dst: Path, field: str, value) -> Path:
    """A copy at ``dst`` of the split folder ``src`` whose shard dataset ``field`` holds ``value``
    in every image (a damaged split, as a hand-edited file would be); ``dst``."""
    import shutil

    import h5py

    shutil.copytree(src, dst)
    for shard in Path(dst).glob("shard-*.h5"):
        with h5py.File(shard, "r+") as f:
            a = f[field][()]
            a[...] = value
            f[field][...] = a
    return Path(dst)


#: The first words of every line the command line prints for a user's mistake.
ERROR_PREFIX = "artdata: error: "
#: What every frame of a progress bar shows (its rate), as opposed to an error line.
PROGRESS_FRAME = "img/s"


def assert_one_line_error(result, *needles, code: int = 2, prefix: str = ERROR_PREFIX, ignore: tuple[str, ...] = ()) -> str:
    """The house rule for a user's mistake: exit code ``code``, nothing on standard output and
    one line ``artdata: error: ...`` on standard error holding every needle, never a traceback;
    the line.

    ``result``: a ``CliRunner`` result, a ``subprocess.CompletedProcess`` (captured as text) or
    an ``(exit code, stdout, stderr)`` triple (a script's ``main()`` and ``capsys``).  ``prefix``:
    the line's first words (a script's own ``NAME: error: ``).  ``ignore``: substrings of
    standard-error lines left out of the count (a progress bar's frames, a warning a command logs
    before it stops).
    """
    if isinstance(result, tuple):
        (found, out, err), exc = result, None
    elif isinstance(result, subprocess.CompletedProcess):
        found, out, err, exc = result.returncode, result.stdout, result.stderr, None
    else:
        found, out, err, exc = result.exit_code, result.stdout, result.stderr, result.exception
    out, err = out or "", err or ""
    assert found == code, (found, out, err, exc)
    assert out == "", (out, err)
    assert "Traceback" not in err, err
    frames = err.replace("\r", "\n").splitlines()  # a progress bar redraws its line after a carriage return
    lines = [ln for ln in frames if ln.strip() and not any(s in ln for s in ignore)]
    assert len(lines) == 1 and lines[0].startswith(prefix), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def run_cli(*args):
    """``artdata ARGS`` run in this process (arguments converted to text); the ``CliRunner`` result.
    A traceback is never the outcome: an exception other than the exit is a failure here."""
    from click.testing import CliRunner

    from articulated_dataset.cli import main

    result = CliRunner().invoke(main, [str(a) for a in args])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result


def edit_json(path: Path, edit) -> None:
    """The JSON file at ``path`` rewritten with ``edit(its value)`` applied in place."""
    import json

    value = json.loads(path.read_text())
    edit(value)
    path.write_text(json.dumps(value))


def tree_snapshot(root: Path, *, skip: tuple[str, ...] = (), digests: bool = True, times: bool = False) -> dict:
    """Every entry under ``root`` (links not followed, special files not opened): file digests
    (or, with ``digests=False``, sizes and modification times: cheap for large read-only inputs),
    link targets, folders.  ``skip``: names of folders directly under ``root`` left out;
    ``times``: each file's modification time recorded beside its digest (a rewrite of the same
    bytes is a change)."""
    import hashlib
    import os
    import stat

    out = {}
    for folder, dirs, files in os.walk(root):
        if Path(folder) == Path(root):
            dirs[:] = [d for d in dirs if d not in skip]
        for name in dirs + files:
            p = Path(folder) / name
            rel = p.relative_to(root).as_posix()
            st = p.lstat()
            if stat.S_ISLNK(st.st_mode):
                out[rel] = ("link", os.readlink(p))
            elif stat.S_ISDIR(st.st_mode):
                out[rel] = ("dir",)
            elif not stat.S_ISREG(st.st_mode):
                out[rel] = ("special", stat.S_IFMT(st.st_mode))
            elif digests:
                out[rel] = ("file", hashlib.sha256(p.read_bytes()).hexdigest()) + ((st.st_mtime_ns,) if times else ())
            else:
                out[rel] = ("file", st.st_size, st.st_mtime_ns)
    return out


def assert_unchanged(root: Path, before: dict, **snapshot_options) -> None:
    """``root`` as :func:`tree_snapshot` (with the same options) recorded it in ``before``."""
    after = tree_snapshot(root, **snapshot_options)
    changed = sorted(set(after) ^ set(before)) + sorted(k for k in after if k in before and after[k] != before[k])
    assert not changed, f"{root}: changed by a refused command: {changed[:5]}"


#: What an injected payload would create if it were ever evaluated.
PWNED = "PWNED"


class GuardedFolder:
    """A test's folder holding ``victim/`` (canary files that must never change) beside its inputs
    and outputs: :meth:`freeze` records every file, :meth:`assert_untouched` checks that nothing
    changed and that no payload ran (the processed-URDF cache, ``cache/``, may change)."""

    def __init__(self, root: Path):
        self.root = root
        self.victim = root / "victim"
        (self.victim / "x" / "train").mkdir(parents=True)
        (self.victim / "canary.txt").write_text("canary")
        (self.victim / "x" / "train" / "keep.txt").write_text("keep")
        self.before = None

    def freeze(self) -> None:
        self.before = tree_snapshot(self.root, skip=("cache",))

    def assert_untouched(self) -> None:
        assert not list(self.root.rglob(PWNED)) and not Path(PWNED).exists(), "a payload ran"
        assert_unchanged(self.root, self.before, skip=("cache",))


def raw_write(path, groups, method="raw", version=PREDICTIONS_FORMAT_VERSION, group_attrs=None):
    """Write a predictions file with h5py directly (no validation), to build broken files
    (``method`` or ``version`` None: the attribute left out)."""
    import h5py

    with h5py.File(path, "w") as f:
        if version is not None:
            f.attrs["format_version"] = version
        if method is not None:
            f.attrs["method"] = method
        for cls, arrays in groups.items():
            g = f.create_group(cls)
            for k, v in arrays.items():
                g.create_dataset(k, data=v)
            for k, v in (group_attrs or {}).get(cls, {}).items():
                g.attrs[k] = v
    return path


def png_header(width: int, height: int, bit_depth: int) -> bytes:
    """A greyscale PNG declaring width x height pixels, with (almost) no pixel data."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")


def flap_split_outside(root: Path, split: str = "train") -> tuple[Path, Path]:
    """A one-object, one-image split generated from the flap URDF (:func:`write_flap_urdf`) kept
    outside the split folder, as a user's third-party URDF is: ``(urdf, split folder)``."""
    from click.testing import CliRunner

    from articulated_dataset.cli import main

    urdf = write_flap_urdf(root / "urdf")
    result = CliRunner().invoke(main, ["generate", "--urdf", str(urdf), "--n", "1", "--images", "1", "--split", split,
                                       "--out", str(root / "out"), "-q", "--workers", "1"])
    assert result.exit_code == 0, result.output
    (split_dir,) = [p.parent for p in (root / "out").glob(f"*/{split}/manifest.json")]
    return urdf, split_dir


def check_forced_split(split: Path, obj_class, table, *, front_m: float | None = None,
                       standoff_m: float | None = None, min_body_px: int = 1000):
    """The checks every forced varied structure passes: ``split`` verifies, its manifest records
    ``table``, its labels explain its pixels (:func:`check_stored_images`, the body's box reaching
    ``front_m`` of door or front and ``standoff_m`` of handle in front of it, where given), and each
    object's ``geometry`` is its sampled size.  Yields ``(config, arrays, sample, rows)`` per object
    for a test's own checks (``rows``: the object's images in ``arrays``)."""
    from articulated_dataset.format import open_split
    from articulated_dataset.tools.verify import verify_split

    global PANEL_M, HANDLE_STANDOFF_M
    report = verify_split(split)
    assert report.ok, report.problems
    manifest, shards = open_split(split)
    config = GenerationConfig.from_dict(manifest["config"])
    assert config.table == table
    K = np.asarray(shards[0].K)
    counts = np.zeros(3, int)
    saved = PANEL_M, HANDLE_STANDOFF_M
    PANEL_M = saved[0] if front_m is None else front_m
    HANDLE_STANDOFF_M = saved[1] if standoff_m is None else standoff_m
    try:
        for sh in shards:
            a = {k: sh.read(k) for k in (*IMAGE_CHECK_FIELDS, "object_index")}
            sh.close()
            counts += check_stored_images(obj_class, a, K)
            for k in np.unique(a["object_index"]):
                sample = object_sample(config, int(k))
                rows = a["object_index"] == k
                sizes = a["geometry"][rows, :3].astype(np.float64)  # every fixed part's box: the sampled size
                assert np.allclose(sizes, [sample.geometry[key] for key in ("depth_m", "width_m", "height_m")], atol=1e-6)
                yield config, a, sample, rows
    finally:
        PANEL_M, HANDLE_STANDOFF_M = saved
    checked, detected, n_body = counts
    assert checked > 0 and detected >= 0.9 * checked and n_body > min_body_px
