"""Robot cameras: ``generate --camera head``, ``--intrinsics`` presets, ``--resolution``.

The stored labels of head-camera shards are checked against their own pixels image by
image (every class, two objects each): the camera moves between images, so each image's
labels must explain that image's depth.
"""

import json
import math

import mujoco
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.classes.registry import all_classes, get_class
from articulated_dataset.cli import main
from articulated_dataset.core.camera import INTRINSICS_PRESETS, CameraConfig, backproject, project
from articulated_dataset.format import open_split, read_manifest
from articulated_dataset.generation import GenerationConfig, generate_split
from articulated_dataset.generation.mujoco_scene import _set_intrinsics
from articulated_dataset.generation.render import DepthRenderer
from articulated_dataset.generation.viewpoint import (
    HEAD_AIM_JITTER_DEG,
    HEAD_HEIGHT_M,
    HEAD_PITCH_DEG,
    HEAD_ROLL_DEG,
    aim_pitch_rad,
    head_views,
    level_pose_from_camera,
    object_in_camera,
)
from articulated_dataset.tools.verify import verify_split
from helpers_core import IMAGE_CHECK_FIELDS, assert_one_line_error, check_stored_images

PRESETS = list(INTRINSICS_PRESETS)


# --------------------------------------------------------------------------------------
# Intrinsics presets
# --------------------------------------------------------------------------------------

def test_presets_scale_with_the_image_and_the_default_camera_is_unchanged():
    for name, cal in INTRINSICS_PRESETS.items():
        native = CameraConfig(cal.width_px, cal.height_px, intrinsics=name)
        assert np.allclose(native.K, [[cal.fx_px, 0, cal.cx_px], [0, cal.fy_px, cal.cy_px], [0, 0, 1]])
        half = CameraConfig(cal.width_px // 2, cal.height_px // 2, intrinsics=name)
        # halving the image halves the focal lengths; pixel edges (not centres) scale
        assert np.allclose(half.K[[0, 1], [0, 1]], native.K[[0, 1], [0, 1]] / 2)
        assert half.K[0, 2] == pytest.approx((cal.cx_px + 0.5) / 2 - 0.5)
        assert 30 < native.vfov_deg < 80 and half.vfov_deg == pytest.approx(native.vfov_deg, rel=1e-6)
        assert CameraConfig(**native.to_dict()) == native  # what a manifest stores reads back
    default = CameraConfig()
    assert default.to_dict() == {"width_px": 192, "height_px": 108, "vfov_deg": default.vfov_deg}
    assert np.allclose(default.K, [[default.focal_px, 0, 95.5], [0, default.focal_px, 53.5], [0, 0, 1]])
    stored = GenerationConfig("cabinet").to_dict()["camera"]  # the manifest's camera: no new keys by default
    assert stored == {"width_px": 192, "height_px": 108, "vfov_deg": default.vfov_deg}
    with pytest.raises(ValueError, match="unknown intrinsics"):
        CameraConfig(intrinsics="kinect9")
    with pytest.raises(ValueError, match="unknown camera mount"):
        CameraConfig(mount="shoulder")


@pytest.mark.parametrize("preset", PRESETS)
def test_mujoco_renders_points_where_K_projects_them(preset):
    """Spheres at known camera-frame points render centred on ``project(p, K)`` for a preset
    scaled to a non-native aspect (non-square pixels, off-centre principal point)."""
    camera = CameraConfig(160, 90, intrinsics=preset)
    spec = mujoco.MjSpec()
    spec.stat.extent = 1.0
    spec.visual.map.znear, spec.visual.map.zfar = 0.05, 12.0
    spec.visual.global_.offwidth, spec.visual.global_.offheight = 160, 90
    cam = spec.worldbody.add_camera(name="camera", pos=[0, 0, 0], xyaxes=[0, -1, 0, 0, 0, 1])
    _set_intrinsics(cam, camera)
    points = np.array([[2.0, 0.5, 0.3], [2.0, -0.6, -0.4], [2.5, 0.0, 0.0], [1.5, 0.3, -0.3]])
    body = spec.worldbody.add_body()
    for p in points:
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.06, 0, 0], pos=list(p))
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    mujoco.mj_camlight(model, data)
    r = DepthRenderer(camera)
    try:
        r.bind(model)
        depth, geom = r.render(data)
    finally:
        r.close()
    uv, _ = project(points, camera.K)
    for g in range(len(points)):
        v, u = np.nonzero(geom == g)
        assert len(u) > 10
        assert abs(u.mean() - uv[g, 0]) < 0.35 and abs(v.mean() - uv[g, 1]) < 0.35
        # the nearest pixel back-projects onto the sphere's front surface
        front = backproject(depth, camera.K, geom == g)
        assert np.abs(np.linalg.norm(front - points[g], axis=1) - 0.06).max() < 0.004
    wrong = CameraConfig(160, 90).K  # the paper's K does not explain these pixels
    uv_wrong, _ = project(points, wrong)
    assert max(abs(np.nonzero(geom == g)[1].mean() - uv_wrong[g, 0]) for g in range(len(points))) > 2


# --------------------------------------------------------------------------------------
# Head camera views
# --------------------------------------------------------------------------------------

def test_head_views_stay_in_range_aim_at_the_object_and_are_recoverable():
    rng = np.random.default_rng(3)
    geometry = {"depth_m": 0.6, "width_m": 0.8, "height_m": 0.9}
    for pose in ({"x_m": 1.5, "y_m": 0.2, "z_m": -0.6, "yaw_rad": 0.3}, {"x_m": 1.0, "y_m": -0.4, "z_m": 0.3, "yaw_rad": -0.7}):
        views = head_views(rng, pose, geometry, 200)
        h, pitch, roll = views.T
        assert (h >= HEAD_HEIGHT_M[0]).all() and (h <= HEAD_HEIGHT_M[1]).all() and h.std() > 0.1
        assert (np.degrees(pitch) >= HEAD_PITCH_DEG[0] - 1e-9).all() and (np.degrees(pitch) <= HEAD_PITCH_DEG[1] + 1e-9).all()
        assert (np.abs(np.degrees(roll)) <= HEAD_ROLL_DEG[1] + 1e-9).all() and np.abs(roll).max() > 0
        aim = np.array([aim_pitch_rad(pose, geometry, x) for x in h])
        unclipped = (np.degrees(pitch) > HEAD_PITCH_DEG[0] + 1e-9) & (np.degrees(pitch) < HEAD_PITCH_DEG[1] - 1e-9)
        assert np.all(np.abs(np.degrees(pitch - aim))[unclipped] <= HEAD_AIM_JITTER_DEG + 1e-9)
        for view in views[:20]:
            T = object_in_camera(pose, view)
            # the object's box centre lies near the image's vertical centre (aimed pitch)
            centre = T[:3, :3] @ np.array([0, 0, geometry["height_m"] / 2]) + T[:3, 3]
            if unclipped[0]:
                assert abs(math.degrees(math.atan2(centre[2], centre[0]))) <= HEAD_AIM_JITTER_DEG + 1e-6
            quat = np.array(mujoco_quat(T[:3, :3]))
            level = level_pose_from_camera(np.concatenate([T[:3, 3], quat])[None])
            assert level["pitch_rad"][0] == pytest.approx(view[1], abs=1e-9)
            assert level["roll_rad"][0] == pytest.approx(view[2], abs=1e-9)
            for k in ("x_m", "y_m", "yaw_rad"):
                assert level[k][0] == pytest.approx(pose[k], abs=1e-9)
            assert level["z_m"][0] == pytest.approx(pose["z_m"] - (view[0] - np.mean(HEAD_HEIGHT_M)), abs=1e-9)
    centre = head_views(None, pose, geometry, 4)
    assert np.allclose(centre[:, 0], np.mean(HEAD_HEIGHT_M)) and np.allclose(centre[:, 2], 0)
    assert np.allclose(object_in_camera(pose), object_in_camera(pose, None))


def mujoco_quat(R):
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R).ravel())
    return q


# --------------------------------------------------------------------------------------
# Generated head-camera shards: per-image labels against the pixels
# --------------------------------------------------------------------------------------

CLASSES = all_classes()


@pytest.fixture(scope="module")
def head_root(tmp_path_factory):
    """``root/<class>/train``: 2 objects x 16 images of every class with the head camera,
    the presets taken in turn, at 192x108 (non-square pixels for kinect2)."""
    root = tmp_path_factory.mktemp("head")
    for i, c in enumerate(CLASSES):
        camera = CameraConfig(192, 108, intrinsics=PRESETS[i % len(PRESETS)], mount="head")
        generate_split(GenerationConfig(c.name, n_objects=2, objects_per_shard=2, camera=camera), root)
    return root


@pytest.mark.parametrize("obj_class", CLASSES, ids=lambda c: c.name)
def test_head_camera_labels_explain_every_image(head_root, obj_class):
    """In every image: body pixels lie in the object's box (object_pose, geometry); each
    moving part's pixels, moved back by -q about the labelled axis, lie in the closed
    object's box (+ handle); not moving them back fails for parts open >= 30%."""
    manifest, shards = open_split(head_root / obj_class.name / "train")
    K = np.asarray(shards[0].K)
    assert manifest["config"]["camera"]["mount"] == "head" and json.loads(shards[0].attrs["camera_mount"])["mount"] == "head"
    assert np.allclose(K, CameraConfig(**manifest["config"]["camera"]).K)
    detected = checked = n_body = 0
    pitches = []
    for sh in shards:
        a = {k: sh.read(k) for k in IMAGE_CHECK_FIELDS}
        sh.close()
        pitches += list(level_pose_from_camera(a["object_pose"].astype(np.float64))["pitch_rad"])
        counts = check_stored_images(obj_class, a, K)
        checked, detected, n_body = checked + counts[0], detected + counts[1], n_body + counts[2]
    assert checked > 0 and detected >= 0.9 * checked and n_body > 1000
    assert np.degrees(np.ptp(pitches)) > 5  # the camera really moves between images


def test_head_camera_split_verifies_and_is_seeded(head_root, tmp_path):
    for c in CLASSES:
        report = verify_split(head_root / c.name / "train")
        assert report.ok, report.problems
    # the same objects (camera stream apart from the sampling stream), bytes independent of shards
    camera = CameraConfig(192, 108, intrinsics="kinect2", mount="head")
    a = generate_split(GenerationConfig("cabinet", n_objects=2, objects_per_shard=2, camera=camera), tmp_path / "a")
    b = generate_split(GenerationConfig("cabinet", n_objects=2, objects_per_shard=1, camera=camera), tmp_path / "b")
    c = generate_split(GenerationConfig("cabinet", n_objects=2, objects_per_shard=2, camera=camera, seed=1), tmp_path / "c")
    _, sa = open_split(a)
    _, sb = open_split(b)
    _, sc = open_split(c)
    for key in ("depth", "q", "object_pose", "geometry"):
        joined = np.concatenate([s.read(key) for s in sb])
        assert np.array_equal(sa[0].read(key), joined)
    assert not np.array_equal(sa[0].read("object_pose"), sc[0].read("object_pose"))
    again = generate_split(GenerationConfig("cabinet", n_objects=2, objects_per_shard=2, camera=camera), tmp_path / "again")
    assert read_manifest(a)["shards"][0]["sha256"] == read_manifest(again)["shards"][0]["sha256"]  # same seed, same bytes
    fixed = generate_split(GenerationConfig("cabinet", n_objects=2, objects_per_shard=2), tmp_path / "f")
    _, sf = open_split(fixed)
    assert np.array_equal(sf[0].read("geometry"), sa[0].read("geometry"))  # the same objects
    for s in sa + sb + sc + sf:
        s.close()


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("args", [
    ["--resolution", "0x5"],
    ["--resolution", "192"],
    ["--resolution", "192x108", "--width", "64"],
    ["--intrinsics", "kinect9"],
    ["--intrinsics", "d435", "--vfov", "40"],
    ["--camera", "shoulder"],
])
def test_cli_refuses_bad_camera_options_in_one_line(tmp_path, args):
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--n", "1", "--out", str(tmp_path), "-q", *args])
    assert_one_line_error(r)
    assert not any(tmp_path.iterdir())


def test_cli_records_the_camera_in_manifest_and_shards(tmp_path):
    r = CliRunner().invoke(main, ["generate", "--class", "toaster", "--n", "1", "--images", "2", "--out", str(tmp_path), "-q",
                                  "--workers", "1", "--camera", "head", "--intrinsics", "azure-kinect", "--resolution", "80x72"])
    assert r.exit_code == 0, r.output
    split = tmp_path / "toaster" / "train"
    cam = read_manifest(split)["config"]["camera"]
    assert (cam["width_px"], cam["height_px"], cam["intrinsics"], cam["mount"]) == (80, 72, "azure-kinect", "head")
    _, shards = open_split(split)
    attrs, K = shards[0].attrs, shards[0].K
    shards[0].close()
    assert attrs["intrinsics"] == "azure-kinect" and (attrs["image_width"], attrs["image_height"]) == (80, 72)
    assert json.loads(attrs["camera_mount"])["height_m"] == list(HEAD_HEIGHT_M)
    assert np.allclose(K, CameraConfig(80, 72, intrinsics="azure-kinect").K)
    assert get_class("toaster").name == read_manifest(split)["class_name"]
