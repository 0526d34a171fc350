"""Real-capture ingestion: synthetic captures made from rendered images ingest back to them."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from articulated_dataset.cli import main
from articulated_dataset.core.camera import R_CAMERA_TO_OPTICAL, CameraConfig, backproject
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.images.resample import crop_intrinsics, resample_depth
from articulated_dataset.format import LABEL_FIELDS, open_split
from articulated_dataset.generation.labels import mat_to_quat
from articulated_dataset.ingest.capture import DEPTH_QUANTUM_M
from articulated_dataset.ingest.readers import load_depth
from articulated_dataset.ingest.write import real_sample_id
from helpers_core import assert_one_line_error

#: Upsampling factor and placement of the synthetic 512 x 424 "Kinect v2" frame.
SCALE = 2
KINECT_W, KINECT_H = 512, 424
OFFSET_U, OFFSET_V = 64, 104
GT_KEYS = ("q", "axis_pose", "part_offset", "geometry", "object_pose")


def _sample(tiny_root, class_name: str, index: int):
    _, shards = open_split(tiny_root / class_name / "test")
    sh = shards[0]
    return sh.sample(index), sh.K


def _upsampled_K(K: np.ndarray, scale: int = SCALE, ou: int = OFFSET_U, ov: int = OFFSET_V) -> np.ndarray:
    """Intrinsics of the image made by repeating each pixel scale x scale times at offset (ou, ov):
    pixel u covers [u - 0.5, u + 0.5] -> [s u + ou - 0.5, s u + ou + s - 0.5], centre s u + ou + (s - 1) / 2."""
    return np.array([[scale * K[0, 0], 0, scale * K[0, 2] + ou + 0.5 * (scale - 1)],
                     [0, scale * K[1, 1], scale * K[1, 2] + ov + 0.5 * (scale - 1)], [0, 0, 1]])


def _upsample(img: np.ndarray, scale: int = SCALE, size=(KINECT_W, KINECT_H), ou: int = OFFSET_U, ov: int = OFFSET_V):
    W, H = size
    out = np.zeros((H, W), img.dtype)
    out[ov : ov + img.shape[0] * scale, ou : ou + img.shape[1] * scale] = np.kron(img, np.ones((scale, scale), img.dtype))
    return out


def _write_capture(folder, name: str, s: dict, K: np.ndarray, *, gt: dict | None = None, fmt: str = "png", mask: bool = True):
    folder.mkdir(parents=True, exist_ok=True)
    depth = _upsample(s["depth"].astype(np.float64))
    if fmt == "png":
        Image.fromarray(np.rint(depth * 1000).astype(np.uint16)).save(folder / f"{name}.png")
    elif fmt == "npy":
        np.save(folder / f"{name}.npy", depth.astype(np.float32))
    elif fmt == "exr":
        import OpenEXR

        OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                     {"Z": depth.astype(np.float32)}).write(str(folder / f"{name}.exr"))
    if mask:
        Image.fromarray(_upsample(s["mask"])).save(folder / f"{name}.mask.png")
    Kb = _upsampled_K(K)
    (folder / "camera.json").write_text(json.dumps({"fx": Kb[0, 0], "fy": Kb[1, 1], "cx": Kb[0, 2], "cy": Kb[1, 2],
                                                    "width": KINECT_W, "height": KINECT_H}))
    if gt is None:
        gt = {k: s[k].tolist() for k in GT_KEYS}
    (folder / f"{name}.labels.json").write_text(json.dumps(gt))


def _ingest(args):
    return CliRunner().invoke(main, ["ingest", "-q", *map(str, args)])


@pytest.mark.parametrize("class_name", ["cabinet2", "drawer"])
def test_round_trip_from_upsampled_kinect_frame(tiny_root, tmp_path, class_name):
    samples = [_sample(tiny_root, class_name, i) for i in (0, 5)]
    for i, (s, K) in enumerate(samples):
        _write_capture(tmp_path / "cap", f"frame{i}", s, K)
    res = _ingest(["--class", class_name, "--out", tmp_path / "out", tmp_path / "cap"])
    assert res.exit_code == 0, res.output
    manifest, shards = open_split(tmp_path / "out" / class_name / "real")
    assert manifest["split"] == "real" and manifest["n_images"] == 2 and manifest["complete"]
    assert manifest["config"]["camera"]["width_px"] == 192
    sh = shards[0]
    np.testing.assert_allclose(sh.K, CameraConfig().K)
    assert sh.attrs["split"] == "real"
    for i, (s, _) in enumerate(samples):
        got = sh.sample(i)
        assert np.abs(got["depth"] - s["depth"]).max() <= 0.5e-3 + DEPTH_QUANTUM_M
        np.testing.assert_array_equal(got["mask"], s["mask"])
        np.testing.assert_array_equal(got["visible_pixels"], s["visible_pixels"])
        for k in ("q", "axis_origin", "axis_direction", "part_offset", "geometry", "object_pose", "object_yaw"):
            np.testing.assert_allclose(got[k], s[k], atol=2e-6, err_msg=k)
        # quaternions agree up to sign
        assert np.allclose(got["axis_pose"][:, 3:], s["axis_pose"][:, 3:], atol=2e-6) or \
            np.allclose(got["axis_pose"][:, 3:], -s["axis_pose"][:, 3:], atol=2e-6)
        assert got["sample_id"] == real_sample_id(class_name, "real", f"frame{i}")
        assert got["image_index"] == i and got["object_index"] == 0


def test_optical_frame_ground_truth_and_other_formats(tiny_root, tmp_path):
    s, K = _sample(tiny_root, "microwave", 2)
    R = R_CAMERA_TO_OPTICAL
    rot = [R @ _quat_matrix(q) for q in s["axis_pose"][:, 3:]]
    obj_rot = R @ _quat_matrix(s["object_pose"][3:])
    gt = {"frame": "optical", "q": s["q"].tolist(),
          "axis_pose": [list(R @ p[:3]) + list(mat_to_quat(r)) for p, r in zip(s["axis_pose"], rot)],
          "object_pose": list(R @ s["object_pose"][:3]) + list(mat_to_quat(obj_rot)),
          "geometry": s["geometry"].tolist()}
    gt = json.loads(json.dumps(gt, default=float))
    for fmt in ("exr", "npy"):
        _write_capture(tmp_path / fmt, "cap", s, K, gt=gt, fmt=fmt)
        res = _ingest(["--class", "microwave", "--out", tmp_path / f"out-{fmt}", tmp_path / fmt])
        assert res.exit_code == 0, res.output
        _, [sh] = open_split(tmp_path / f"out-{fmt}" / "microwave" / "real")
        got = sh.sample(0)
        assert np.abs(got["depth"] - s["depth"]).max() <= DEPTH_QUANTUM_M
        for k in ("axis_origin", "axis_direction", "object_pose", "object_yaw", "q"):
            np.testing.assert_allclose(got[k], s[k], atol=2e-6, err_msg=k)
        assert np.isnan(got["part_offset"]).all()  # not given: NaN


def _quat_matrix(q):
    import mujoco

    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.asarray(q, np.float64))
    return m.reshape(3, 3)


def test_no_ground_truth_gives_nan_labels_and_binary_mask(tiny_root, tmp_path):
    s, K = _sample(tiny_root, "toaster", 1)
    _write_capture(tmp_path / "cap", "t", s, K)
    (tmp_path / "cap" / "t.labels.json").unlink()
    binary = (_upsample(s["mask"]) > 0).astype(np.uint8) * 255
    Image.fromarray(binary).save(tmp_path / "cap" / "t.mask.png")
    res = _ingest(["--class", "toaster", "--out", tmp_path / "out", tmp_path / "cap" / "t.png"])
    assert res.exit_code == 0, res.output
    _, [sh] = open_split(tmp_path / "out" / "toaster" / "real")
    got = sh.sample(0)
    for k in LABEL_FIELDS:
        if got[k].dtype.kind == "f":
            assert np.isnan(got[k]).all(), k
    np.testing.assert_array_equal(got["mask"], (s["mask"] > 0).astype(np.uint8))
    assert got["visible_pixels"].tolist() == [int((s["mask"] > 0).sum()), 0]


def test_point_clouds_rasterise_back(tiny_root, tmp_path):
    import trimesh

    s, K = _sample(tiny_root, "cabinet", 4)
    cam_points = backproject(s["depth"], K)
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"K": K.ravel().tolist(), "width": 192, "height": 108}))
    opt = cam_points @ R_CAMERA_TO_OPTICAL.T
    trimesh.PointCloud(opt).export(tmp_path / "c.ply")
    _write_pcd(tmp_path / "c.pcd", opt, binary=False)
    _write_pcd(tmp_path / "b.pcd", cam_points, binary=True)
    for name, frame in (("c.ply", "optical"), ("c.pcd", "optical"), ("b.pcd", "camera")):
        out = tmp_path / f"out-{name}"
        res = _ingest(["--class", "cabinet", "--out", out, "--intrinsics", cam, "--cloud-frame", frame, tmp_path / name])
        assert res.exit_code == 0, res.output
        _, [sh] = open_split(out / "cabinet" / "real")
        got = sh.sample(0)
        assert np.abs(got["depth"] - s["depth"]).max() <= DEPTH_QUANTUM_M, name
        np.testing.assert_array_equal(got["mask"] > 0, s["depth"] > 0)


def _write_pcd(path, points, binary: bool):
    n = len(points)
    header = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
              f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {'binary' if binary else 'ascii'}\n")
    if binary:
        path.write_bytes(header.encode() + points.astype("<f4").tobytes())
    else:
        path.write_text(header + "\n".join(" ".join(f"{v:.9g}" for v in p) for p in points) + "\n")


def test_crop_intrinsics_hand_worked():
    K = np.array([[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]])
    mask = np.zeros((480, 640), bool)
    mask[200:290, 100:200] = True  # 100 x 90 px box
    Kc = crop_intrinsics(K, mask, (192, 108), margin=0.0)
    # window 160 x 90 (aspect 16:9) from (69.5, 199.5); scale 1.2
    np.testing.assert_allclose(Kc, [[480.0, 0, 299.5], [0, 480.0, 47.5], [0, 0, 1]])


def test_crop_fit_of_a_realsense_frame(tiny_root, tmp_path):
    """A 640 x 480 frame (object off-centre, coarser scale) cropped around the mask: the
    ingested cloud coincides with the original object's cloud."""
    s, K = _sample(tiny_root, "microwave", 6)
    folder = tmp_path / "rs"
    folder.mkdir()
    size, ou, ov = (640, 480), 240, 250
    Image.fromarray(np.rint(_upsample(s["depth"].astype(np.float64), 2, size, ou, ov) * 1000).astype(np.uint16)).save(folder / "rs.png")
    Image.fromarray(_upsample(s["mask"], 2, size, ou, ov)).save(folder / "rs.mask.png")
    Kr = _upsampled_K(K, 2, ou, ov)
    res = _ingest(["--class", "microwave", "--out", tmp_path / "out", "--fit", "crop", "--resample", "min",
                   "--fx", Kr[0, 0], "--fy", Kr[1, 1], "--cx", Kr[0, 2], "--cy", Kr[1, 2], folder])
    assert res.exit_code == 0, res.output
    _, [sh] = open_split(tmp_path / "out" / "microwave" / "real")
    got = sh.sample(0)
    Kc = sh.K
    assert Kc[0, 0] == pytest.approx(Kc[1, 1]) and Kc[0, 0] != pytest.approx(K[0, 0])
    ys, xs = np.nonzero(got["mask"])
    # the mask's box is centred in the crop and spans its longer side minus the margins
    assert abs(0.5 * (xs.min() + xs.max()) - 95.5) < 2 and abs(0.5 * (ys.min() + ys.max()) - 53.5) < 2
    new = backproject(got["depth"], Kc, got["mask"] > 0)
    old = backproject(s["depth"], K, s["mask"] > 0)
    np.testing.assert_allclose(new.mean(axis=0), old.mean(axis=0), atol=0.01)
    # every ingested point lies on the original surface: within one original pixel footprint
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(old).query(new)
    assert np.percentile(dist, 95) < 1.5 * s["depth"].max() / K[0, 0]


def test_resample_min_depth_keeps_nearest_surface():
    depth = np.full((4, 4), 2.0)
    depth[1, 2] = 1.0
    mask = np.ones((4, 4), np.uint8)
    mask[1, 2] = 2
    K_src = np.array([[10.0, 0, 1.5], [0, 10.0, 1.5], [0, 0, 1]])
    K_dst = np.array([[5.0, 0, 0.5], [0, 5.0, 0.5], [0, 0, 1]])  # 2x2 image, each pixel a 2x2 footprint
    d, m = resample_depth(depth, mask, K_src, K_dst, (2, 2), "min")
    np.testing.assert_array_equal(d, [[2.0, 1.0], [2.0, 2.0]])
    np.testing.assert_array_equal(m, [[1, 2], [1, 1]])
    d, _ = resample_depth(depth, mask, K_src, K_dst, (2, 2), "nearest")
    assert set(np.unique(d)) <= {1.0, 2.0}


def test_kinect_intrinsics_plane_keeps_z(tmp_path):
    """A plane at constant z seen by a real Kinect v2 K keeps its z; rays outside its field of
    view get no return."""
    W, H = 512, 424
    Kk = np.array([[365.5, 0, 255.5], [0, 365.5, 211.5], [0, 0, 1]])
    np.save(tmp_path / "plane.npy", np.full((H, W), 1.25, np.float32))
    res = _ingest(["--class", "drawer", "--out", tmp_path / "out", "--fx", 365.5, "--fy", 365.5, "--cx", 255.5,
                   "--cy", 211.5, tmp_path / "plane.npy"])
    assert res.exit_code == 0, res.output
    _, [sh] = open_split(tmp_path / "out" / "drawer" / "real")
    d = sh.read("depth", 0)
    K = CameraConfig().K
    half_fov = math.atan(0.5 * W / Kk[0, 0])
    u = np.arange(192)
    inside = np.abs(np.arctan((u - K[0, 2]) / K[0, 0])) < half_fov - 0.01
    outside = np.abs(np.arctan((u - K[0, 2]) / K[0, 0])) > half_fov + 0.01
    assert np.allclose(d[:, inside], 1.25, atol=DEPTH_QUANTUM_M)
    assert (d[:, outside] == 0).all()


def test_append_and_overwrite(tiny_root, tmp_path):
    s, K = _sample(tiny_root, "drawer", 0)
    _write_capture(tmp_path / "a", "a", s, K)
    _write_capture(tmp_path / "b", "b", s, K)
    out = tmp_path / "out"
    assert _ingest(["--class", "drawer", "--out", out, tmp_path / "a"]).exit_code == 0
    res = _ingest(["--class", "drawer", "--out", out, tmp_path / "b"])
    assert res.exit_code == 2 and "--append" in res.output
    assert _ingest(["--class", "drawer", "--out", out, "--append", tmp_path / "b"]).exit_code == 0
    manifest, shards = open_split(out / "drawer" / "real")
    assert manifest["n_images"] == 2 and len(shards) == 2
    assert [sh.read("image_index", 0) for sh in shards] == [0, 1]
    res = _ingest(["--class", "drawer", "--out", out, "--append", tmp_path / "b"])
    assert res.exit_code == 2 and "already ingested" in res.output
    assert _ingest(["--class", "drawer", "--out", out, "--overwrite", tmp_path / "b"]).exit_code == 0
    assert open_split(out / "drawer" / "real")[0]["n_images"] == 1


def _bad(tmp_path, tiny_root, case: str):
    s, K = _sample(tiny_root, "drawer", 0)
    cap = tmp_path / "cap"
    _write_capture(cap, "x", s, K)
    args = ["--class", "drawer", "--out", tmp_path / "out", cap / "x.png"]
    if case == "mask size":
        Image.fromarray(np.zeros((10, 10), np.uint8)).save(cap / "x.mask.png")
    elif case == "no intrinsics":
        (cap / "camera.json").unlink()
    elif case == "8-bit depth":
        Image.fromarray(np.zeros((KINECT_H, KINECT_W), np.uint8)).save(cap / "x.png")
    elif case == "integer npy":
        np.save(cap / "y.npy", np.zeros((KINECT_H, KINECT_W), np.uint16))
        args[-1] = cap / "y.npy"
    elif case == "mm in metres":
        np.save(cap / "y.npy", np.full((KINECT_H, KINECT_W), 1500.0, np.float32))
        args[-1] = cap / "y.npy"
    elif case == "partial fx":
        args += ["--fx", "300"]
    elif case == "bad gt":
        (cap / "x.labels.json").write_text(json.dumps({"q": [0.1, 0.2]}))
    elif case == "bad mask values":
        Image.fromarray(np.full((KINECT_H, KINECT_W), 7, np.uint8)).save(cap / "x.mask.png")
    elif case == "empty mask":
        Image.fromarray(np.zeros((KINECT_H, KINECT_W), np.uint8)).save(cap / "x.mask.png")
    elif case == "crop without mask":
        (cap / "x.mask.png").unlink()
        args += ["--fit", "crop"]
    elif case == "unknown class":
        args[1] = "sofa"
    elif case == "missing file":
        args[-1] = cap / "nope.png"
    return _ingest(args)


@pytest.mark.parametrize("case, message", [
    ("mask size", "mask is 10x10 px but the depth is 512x424"),
    ("no intrinsics", "intrinsics missing"),
    ("8-bit depth", "16-bit"),
    ("integer npy", "unknown units"),
    ("mm in metres", "millimetres"),
    ("partial fx", "go together"),
    ("bad gt", "'q' has shape (2,), expected (1,)"),
    ("bad mask values", "neither binary"),
    ("empty mask", "marks no object pixel"),
    ("crop without mask", "needs a segmentation mask"),
    ("unknown class", "unknown object class"),
    ("missing file", "no such file"),
])
def test_bad_inputs_exit_2_with_one_line(tmp_path, tiny_root, case, message):
    res = _bad(tmp_path, tiny_root, case)
    assert_one_line_error(res, message)


def test_load_depth_units(tmp_path):
    np.save(tmp_path / "mm.npy", np.full((3, 3), 1500, np.uint16))
    np.testing.assert_allclose(load_depth(tmp_path / "mm.npy", "mm"), 1.5)
    with pytest.raises(UserError, match="unknown units"):
        load_depth(tmp_path / "mm.npy")


def test_intrinsics_plausibility_hand_worked():
    from articulated_dataset.core.images.intrinsics import check_intrinsics, intrinsics_matrix

    # Kinect v2 depth camera: 2 atan(256 / 365.456) = 70.02 deg wide, 2 atan(212 / 365.456) = 60.24 deg high
    kinect = intrinsics_matrix(365.456, 365.456, 254.878, 205.395)
    check_intrinsics(kinect, (512, 424), "kinect")
    # fx = 2 * 256 / tan(0.45 deg) = 0.9 deg wide: below the 1 deg floor; fx = 256 / tan(86 deg) = 172 deg
    for fx in (256 / math.tan(math.radians(0.45)), 256 / math.tan(math.radians(86.0)), 1e308):
        with pytest.raises(UserError, match="field of view"):
            check_intrinsics(intrinsics_matrix(fx, 365.0, 255.5, 211.5), (512, 424), "x")
    with pytest.raises(UserError, match="principal point"):
        check_intrinsics(intrinsics_matrix(365.0, 365.0, 512.0, 211.5), (512, 424), "x")
    check_intrinsics(intrinsics_matrix(365.0, 365.0, 511.5, -0.5), (512, 424), "x")  # the image's outer edges


def test_depth_units_are_checked_both_ways(tmp_path):
    png = tmp_path / "d.png"
    Image.fromarray(np.full((4, 4), 2, np.uint16)).save(png)  # 2 "mm": a frame in metres
    with pytest.raises(UserError, match="depth_units m"):
        load_depth(png)
    np.testing.assert_allclose(load_depth(png, "m"), 2.0)
    Image.fromarray(np.full((4, 4), 150, np.uint16)).save(png)  # 15 cm: a close but real return
    np.testing.assert_allclose(load_depth(png), 0.15)
    np.save(tmp_path / "d.npy", np.full((4, 4), 1500.0, np.float32))
    with pytest.raises(UserError, match="depth_units mm"):
        load_depth(tmp_path / "d.npy")


def test_label_rules_accept_real_labels_and_wrap_yaw(tmp_path):
    from articulated_dataset.ingest.ground_truth import load_ground_truth, real_label_problems

    path = tmp_path / "x.labels.json"
    # a cabinet opened 2 deg past its 90 deg range (labelling error), yaw given as 7 rad
    path.write_text(json.dumps({"q": [math.radians(92.0)], "object_yaw": 7.0, "geometry": [0.6, 0.8, 0.9, 1]}))
    labels = load_ground_truth(path, 1, "cabinet")
    assert math.isclose(float(labels["object_yaw"]), 7.0 - 2 * math.pi)
    assert np.isnan(labels["part_offset"]).all() and np.isnan(labels["axis_pose"]).all()
    fields = {k: np.asarray(v)[None] for k, v in labels.items() if k != "object"}
    assert real_label_problems(fields, ("revolute",), ((0.0, math.pi / 2),)) == []
    fields["q"] = np.array([[math.radians(96.0)]])  # 6 deg past: beyond the 5 deg tolerance
    [(message, bad)] = real_label_problems(fields, ("revolute",), ((0.0, math.pi / 2),))
    assert message.startswith("q[0]: outside the class's joint range") and bad.tolist() == [True]


def _files(folder):
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_failed_overwrite_or_append_leaves_the_split_as_it_was(tiny_root, tmp_path, monkeypatch):
    import articulated_dataset.format.shards as shards_module
    from articulated_dataset.core.errors import UserError as _UserError

    s, K = _sample(tiny_root, "drawer", 0)
    for name in ("a", "b"):
        _write_capture(tmp_path / name, name, s, K)
    out = tmp_path / "out"
    assert _ingest(["--class", "drawer", "--out", out, tmp_path / "a"]).exit_code == 0
    before = _files(out)
    real_write = shards_module.write_shard

    def failing(path, *args, **kwargs):  # the shard is written, then the disk "fills up"
        real_write(path, *args, **kwargs)
        raise _UserError(f"cannot write {path}: no space left on device")

    monkeypatch.setattr(shards_module, "write_shard", failing)
    for extra in (["--overwrite"], ["--append"]):
        res = _ingest(["--class", "drawer", "--out", out, *extra, tmp_path / "b"])
        assert res.exit_code == 2 and "no space left" in res.output, res.output
        assert _files(out) == before  # old shards and manifest byte-identical, nothing left behind
        assert sorted(p.name for p in (out / "drawer").iterdir()) == ["real"]
    monkeypatch.setattr(shards_module, "write_shard", real_write)
    assert _ingest(["--class", "drawer", "--out", out, "--overwrite", tmp_path / "b"]).exit_code == 0
    manifest, _ = open_split(out / "drawer" / "real")
    assert manifest["real"]["captures"] == ["b"]
    assert sorted(p.name for p in (out / "drawer").iterdir()) == ["real"]  # no .old / .ingest folders


def test_split_folder_with_foreign_files_is_refused(tiny_root, tmp_path):
    s, K = _sample(tiny_root, "drawer", 0)
    _write_capture(tmp_path / "a", "a", s, K)
    split = tmp_path / "out" / "drawer" / "real"
    split.mkdir(parents=True)
    (split / "notes.txt").write_text("mine")
    res = _ingest(["--class", "drawer", "--out", tmp_path / "out", "--overwrite", tmp_path / "a"])
    assert res.exit_code == 2 and "did not write" in res.output and "notes.txt" in res.output
    assert [p.name for p in split.iterdir()] == ["notes.txt"]
