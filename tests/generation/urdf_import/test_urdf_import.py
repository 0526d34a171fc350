"""Third-party URDF objects: import checks, labels against hand-worked geometry, the CLI.

The test objects are built here: boxes exported with trimesh to OBJ files, joined by
URDF joints.  Expected labels follow from the boxes' dimensions (see each builder).
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.core.camera import CameraConfig, backproject
from articulated_dataset.core.errors import UserError
from articulated_dataset.format import open_split, read_manifest, sha256_file
from articulated_dataset.generation import GenerationConfig, generate_split, urdf_import
from articulated_dataset.generation.urdf_import import import_urdf
from articulated_dataset.generation.urdf_import.build import _class_for_key
from articulated_dataset.generation.urdf_import.process import FLAT_MESH_THICKNESS_M, _thicken_if_flat, double_sided
from articulated_dataset.generation.urdf_import.ranges import VIEW_MARGIN, reparametrize_range, view_pose_ranges

#: Tolerance (m) of label positions: float32 storage of ~2 m coordinates.
POS_TOL_M = 1e-4
#: Tolerance (m) of back-projected depth pixels against the part's box (depth quantum,
#: float32 depth, rasterisation at silhouette edges).
PIXEL_TOL_M = 5e-3

# ---- cabinet: plinth + body (fixed) + door hinged on its left front edge -------------
# URDF axis +z with limits [-1.5, 0]: opening (towards the camera) is negative URDF q, so
# the importer flips the axis: dataset axis -z, q in [0, 1.5].
CAB_D, CAB_W, CAB_H, PLINTH, PANEL = 0.5, 0.6, 0.8, 0.05, 0.02
CAB_HINGE = np.array([-CAB_D / 2, CAB_W / 2, PLINTH])
# ---- chest: body (root link) + drawer (prismatic) + door (revolute) -----------------
# Both joints have limits straddling 0, so their zero is moved to the lower limit.
CH_D, CH_W, CH_H = 0.5, 0.6, 0.9
DRAWER_ORIGIN = np.array([-CH_D / 2, 0.0, 0.75 * CH_H])
DRAWER_EXT, DRAWER_CENTRE = np.array([0.4, 0.5, 0.15]), np.array([0.08, 0.0, 0.0])
DRAWER_LIMITS = (-0.1, 0.2)
DOOR_GAP = 0.04
DOOR_ORIGIN = np.array([-CH_D / 2 - DOOR_GAP, -CH_W / 2, 0.02])
DOOR_EXT, DOOR_CENTRE = np.array([PANEL, CH_W, 0.5]), np.array([-PANEL / 2, CH_W / 2, 0.25])
DOOR_LIMITS = (-0.05, 1.2)


def _box_obj(path, extents, centre):
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(centre)
    m.export(str(path))


def _link(name, mesh=None, box=None):
    geom = ""
    if mesh:
        geom = f'<visual><geometry><mesh filename="{mesh}"/></geometry></visual>'
    if box:
        size, xyz = box
        geom += f'<visual><origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}"/><geometry><box size="{size[0]} {size[1]} {size[2]}"/></geometry></visual>'
    return f'<link name="{name}">{geom}</link>'


def _joint(name, jtype, parent, child, xyz=(0, 0, 0), axis=None, limits=None):
    s = f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/><child link="{child}"/>'
    s += f'<origin xyz="{xyz[0]} {xyz[1]} {xyz[2]}"/>'
    if axis is not None:
        s += f'<axis xyz="{axis[0]} {axis[1]} {axis[2]}"/>'
    if limits is not None:
        s += f'<limit lower="{limits[0]}" upper="{limits[1]}" effort="1" velocity="1"/>'
    return s + "</joint>"


def _write_urdf(path, name, body):
    path.write_text(f'<?xml version="1.0"?>\n<robot name="{name}">{body}</robot>\n')
    return path


@pytest.fixture(scope="module")
def objects(tmp_path_factory):
    """Test URDFs (and a private model cache: spawned workers inherit the variable)."""
    root = tmp_path_factory.mktemp("urdf")
    old = os.environ.get(urdf_import.CACHE_ENV)
    os.environ[urdf_import.CACHE_ENV] = str(root / "cache")
    meshes = root / "cabinet" / "meshes"
    meshes.mkdir(parents=True)
    _box_obj(meshes / "body.obj", [CAB_D, CAB_W, CAB_H], [0, 0, CAB_H / 2])
    _box_obj(meshes / "door.obj", [PANEL, CAB_W, CAB_H], [-PANEL / 2, -CAB_W / 2, CAB_H / 2])
    cab_links = (_link("base", box=((CAB_D, CAB_W, PLINTH), (0, 0, PLINTH / 2)))
                 + _link("body", "meshes/body.obj") + _link("door", "meshes/door.obj")
                 + _joint("mount", "fixed", "base", "body", (0, 0, PLINTH))
                 + _joint("hinge", "revolute", "body", "door", (-CAB_D / 2, CAB_W / 2, 0), (0, 0, 1), (-1.5, 0.0)))
    cabinet = _write_urdf(root / "cabinet" / "cabinet.urdf", "test_cabinet", cab_links)
    knob = _link("knob", "meshes/knob_missing.obj") + _joint("knob_fix", "fixed", "door", "knob")
    broken = _write_urdf(root / "cabinet" / "broken.urdf", "test_cabinet", cab_links + knob)

    cm = root / "chest" / "parts"
    cm.mkdir(parents=True)
    _box_obj(cm / "body.obj", [CH_D, CH_W, CH_H], [0, 0, CH_H / 2])
    _box_obj(cm / "drawer.obj", DRAWER_EXT, DRAWER_CENTRE)
    _box_obj(cm / "door.obj", DOOR_EXT, DOOR_CENTRE)
    chest = _write_urdf(root / "chest" / "chest.urdf", "test_chest", (
        _link("chest", "parts/body.obj") + _link("drawer", "parts/drawer.obj") + _link("door", "parts/door.obj")
        + _joint("slide", "prismatic", "chest", "drawer", DRAWER_ORIGIN, (-1, 0, 0), DRAWER_LIMITS)
        + _joint("flap", "revolute", "chest", "door", DOOR_ORIGIN, (0, 0, 1), DOOR_LIMITS)))
    yield {"root": root, "cabinet": cabinet, "broken": broken, "chest": chest}
    if old is None:
        os.environ.pop(urdf_import.CACHE_ENV, None)
    else:
        os.environ[urdf_import.CACHE_ENV] = old


def _rot(axis, angle):
    return trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]


def _object_frame(labels, i):
    """(t, R): root-link pose in the camera frame of image i."""
    pose = labels["object_pose"][i].astype(float)
    return pose[:3], trimesh.transformations.quaternion_matrix(pose[3:])[:3, :3]


def _in_box(points, centre, extents, tol):
    return np.all(np.abs(points - centre) <= extents / 2 + tol, axis=1)


def _generate(obj, out, n=3, images=4, **kw):
    cfg = GenerationConfig(obj.obj_class.name, n_objects=n, images_per_object=images, objects_per_shard=2,
                           third_party=obj.definition, **kw)
    return cfg, generate_split(cfg, out)


def _check_split_integrity(split_dir, obj):
    manifest, shards = open_split(split_dir)  # validates every shard against the schema
    assert manifest["complete"]
    for rec in read_manifest(split_dir)["shards"]:
        assert sha256_file(split_dir / rec["file"]) == rec["sha256"]
    for sh in shards:
        a = sh.attrs
        assert a["class_name"] == obj.obj_class.name
        assert json.loads(a["joint_names"]) == [j.name for j in obj.obj_class.joints]
        assert json.loads(a["joint_types"]) == list(obj.obj_class.joint_types)
    return shards


def test_cabinet_end_to_end_labels_follow_the_conventions(objects, tmp_path):
    obj = import_urdf(objects["cabinet"])
    assert obj.obj_class.name == "cabinet-cabinet"  # <folder>-<stem>
    assert [j.name for j in obj.obj_class.joints] == ["hinge"] and obj.obj_class.base_link == "base"
    assert obj.obj_class.table.q == ((0.0, 1.5),)
    assert any("flipped" in n for n in obj.notes)
    cfg, split = _generate(obj, tmp_path)
    shards = _check_split_integrity(split, obj)
    K = CameraConfig().K
    axis_root = np.array([0.0, 0.0, -1.0])  # flipped: positive q opens towards the camera
    door_centre_root = CAB_HINGE + np.array([-PANEL / 2, -CAB_W / 2, CAB_H / 2])
    expected_origin_root = np.array([CAB_HINGE[0], CAB_HINGE[1], door_centre_root[2]])
    n_images = 0
    for sh in shards:
        L = sh.labels()
        for i in range(len(sh)):
            n_images += 1
            t, R = _object_frame(L, i)
            q = float(L["q"][i, 0])
            assert 0.0 <= q <= 1.5
            d = L["axis_direction"][i, 0].astype(float)
            assert abs(np.linalg.norm(d) - 1) < 1e-6
            np.testing.assert_allclose(d, R @ axis_root, atol=1e-5)
            # axis origin: on the hinge line, nearest the door's centre
            np.testing.assert_allclose(L["axis_origin"][i, 0], t + R @ expected_origin_root, atol=POS_TOL_M)
            np.testing.assert_allclose(L["geometry"][i], [CAB_D, CAB_W, PLINTH + CAB_H, 0], atol=POS_TOL_M)
            mask, depth = sh.read("mask", i), sh.read("depth", i)
            assert (mask == 2).sum() == L["visible_pixels"][i, 1] >= cfg.min_part_pixels
            # every door pixel, rotated back by q about the hinge, lies on the closed door's box
            pts = (backproject(depth, K, mask == 2) - t) @ R  # root frame
            closed = (pts - CAB_HINGE) @ _rot(axis_root, q) + CAB_HINGE  # inverse rotation: row @ R(q)
            assert _in_box(closed, door_centre_root, np.array([PANEL, CAB_W, CAB_H]), PIXEL_TOL_M).all()
            body = (backproject(depth, K, mask == 1) - t) @ R
            body_box_centre = np.array([0, 0, (PLINTH + CAB_H) / 2])
            assert _in_box(body, body_box_centre, np.array([CAB_D, CAB_W, PLINTH + CAB_H]), PIXEL_TOL_M).all()
    assert n_images == 3 * 4


def test_chest_two_joints_with_moved_zero(objects, tmp_path):
    obj = import_urdf(objects["chest"], joints=["flap", "slide"], class_name="chest")
    assert obj.obj_class.joint_types == ("revolute", "prismatic")
    np.testing.assert_allclose(obj.obj_class.table.q, [(0, 1.25), (0, 0.3)], atol=1e-12)
    cfg, split = _generate(obj, tmp_path, n=2)
    shards = _check_split_integrity(split, obj)
    K = CameraConfig().K
    z = np.array([0.0, 0.0, 1.0])
    for sh in shards:
        L = sh.labels()
        for i in range(len(sh)):
            t, R = _object_frame(L, i)
            q_door, q_drawer = (float(v) for v in L["q"][i])
            assert 0 <= q_door <= 1.25 and 0 <= q_drawer <= 0.3
            # door: URDF coordinate = q + lower limit
            centre0 = DOOR_ORIGIN + _rot(z, DOOR_LIMITS[0]) @ DOOR_CENTRE
            np.testing.assert_allclose(L["axis_direction"][i, 0], R @ z, atol=1e-5)
            origin_root = np.array([DOOR_ORIGIN[0], DOOR_ORIGIN[1], centre0[2]])
            np.testing.assert_allclose(L["axis_origin"][i, 0], t + R @ origin_root, atol=POS_TOL_M)
            depth, mask = sh.read("depth", i), sh.read("mask", i)
            pts = (backproject(depth, K, mask == 2) - t) @ R
            local = (pts - DOOR_ORIGIN) @ _rot(z, q_door + DOOR_LIMITS[0])
            assert len(local) >= cfg.min_part_pixels and _in_box(local, DOOR_CENTRE, DOOR_EXT, PIXEL_TOL_M).all()
            # drawer: leading face centre at q = 0 (URDF q = lower limit), axis -x
            a = np.array([-1.0, 0.0, 0.0])
            frame0 = DRAWER_ORIGIN + DRAWER_LIMITS[0] * a
            face0 = frame0 + DRAWER_CENTRE + a * DRAWER_EXT[0] / 2
            np.testing.assert_allclose(L["axis_direction"][i, 1], R @ a, atol=1e-5)
            np.testing.assert_allclose(L["axis_origin"][i, 1], t + R @ face0, atol=POS_TOL_M)
            pts = (backproject(depth, K, mask == 3) - t) @ R
            local = pts - (frame0 + q_drawer * a)
            assert len(local) >= cfg.min_part_pixels and _in_box(local, DRAWER_CENTRE, DRAWER_EXT, PIXEL_TOL_M).all()
            # chirality 1: joint 0 (the door) hinges on the right (-y) of its panel
            np.testing.assert_allclose(L["geometry"][i], [CH_D, CH_W, CH_H, 1], atol=POS_TOL_M)


#: Factor of the --scale test (a power of two: scaled coordinates are exact in binary).
SCALE = 2.0


def test_scale_scales_the_whole_scene_about_the_camera(objects, tmp_path):
    """--scale s multiplies every length: with the same seed the pose table, the sampled
    positions, prismatic q, every position label and the depth scale by s, while revolute q,
    orientations and the mask (the same projection) stay the same."""
    plain = import_urdf(objects["chest"], class_name="chest-s")  # one name: the same sampled draws
    big = import_urdf(objects["chest"], class_name="chest-s", scale=SCALE)
    assert big.definition["scale"] == SCALE and "scale" not in plain.definition
    t1, t2 = plain.obj_class.table, big.obj_class.table
    assert [j.name for j in big.obj_class.joints] == ["slide", "flap"]
    np.testing.assert_allclose(t2.q, [np.multiply(t1.q[0], SCALE), t1.q[1]], rtol=1e-12)  # slide (m) scales, flap not
    for k in ("x_m", "y_m", "z_m"):
        np.testing.assert_allclose(t2.pose[k], np.multiply(t1.pose[k], SCALE), rtol=1e-9, atol=1e-12)
    assert t2.pose["yaw_rad"] == t1.pose["yaw_rad"]
    _, s1 = _generate(plain, tmp_path / "a", n=1)
    _, s2 = _generate(big, tmp_path / "b", n=1)
    (_, [a]), (_, [b]) = open_split(s1), open_split(s2)
    la, lb = a.labels(), b.labels()
    for k in ("axis_origin", "part_offset", "geometry"):
        cols = slice(0, 3) if k == "geometry" else slice(None)  # geometry's 4th value is chirality
        np.testing.assert_allclose(lb[k][..., cols], SCALE * la[k][..., cols], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(lb["object_pose"][:, :3], SCALE * la["object_pose"][:, :3], rtol=1e-5)
    np.testing.assert_allclose(lb["object_pose"][:, 3:], la["object_pose"][:, 3:], atol=1e-6)
    np.testing.assert_allclose(lb["q"], la["q"] * [SCALE, 1.0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(lb["axis_direction"], la["axis_direction"], atol=1e-6)
    ma, mb = a.read("mask"), b.read("mask")
    assert np.mean(ma == mb) > 0.999  # the same projection (rasterisation may differ on a few edge pixels)
    both = (ma == mb) & (ma > 0)
    np.testing.assert_allclose(b.read("depth")[both], SCALE * a.read("depth")[both], rtol=0.01)


@pytest.mark.slow
def test_cli_with_spawned_workers_matches_serial_and_resumes(objects, tmp_path):
    obj = import_urdf(objects["chest"], class_name="chest-cli")
    cfg = GenerationConfig("chest-cli", n_objects=2, images_per_object=4, objects_per_shard=1, third_party=obj.definition)
    serial = generate_split(cfg, tmp_path / "serial")
    args = ["generate", "--urdf", str(objects["chest"]), "--class-name", "chest-cli", "--n", "2", "--images", "4",
            "--objects-per-shard", "1", "--out", str(tmp_path / "cli")]
    r = CliRunner().invoke(main, args + ["--workers", "2"])
    assert r.exit_code == 0, r.output
    assert "joints inferred: slide, flap" in r.output and "pose x_m in [" in r.output
    cli = tmp_path / "cli" / "chest-cli" / "train"
    for f in ("manifest.json", "shard-00000.h5", "shard-00001.h5"):
        assert (serial / f).read_bytes() == (cli / f).read_bytes(), f
    r = CliRunner().invoke(main, args + ["--workers", "1", "--resume", "--quiet"])
    assert r.exit_code == 0, r.output


def test_missing_mesh_names_the_file_and_can_be_skipped(objects, tmp_path):
    with pytest.raises(UserError, match=r"mesh file not found: .*knob_missing\.obj \(link 'knob'"):
        import_urdf(objects["broken"], class_name="broken")
    r = CliRunner().invoke(main, ["generate", "--urdf", str(objects["broken"]), "--class-name", "broken", "--out", str(tmp_path)])
    assert r.exit_code == 2 and "knob_missing.obj" in r.output and "Traceback" not in r.output
    obj = import_urdf(objects["broken"], class_name="broken", skip_missing_meshes=True)
    assert any("skipped missing mesh" in n and "knob_missing.obj" in n for n in obj.notes)
    _, split = _generate(obj, tmp_path, n=1)
    _check_split_integrity(split, obj)


def test_changed_files_are_refused_by_workers(objects, tmp_path):
    import shutil

    folder = tmp_path / "copy"
    shutil.copytree(objects["cabinet"].parent, folder)
    obj = import_urdf(folder / "cabinet.urdf", class_name="changed")
    _box_obj(folder / "meshes" / "door.obj", [PANEL, CAB_W, CAB_H / 2], [-PANEL / 2, -CAB_W / 2, CAB_H / 4])
    _class_for_key.cache_clear()  # as in a fresh worker process
    with pytest.raises(UserError, match="differ from the files"):
        urdf_import.class_from_definition(obj.definition)


def test_data_is_verified_without_the_urdf_files(objects, tmp_path):
    import shutil

    folder = tmp_path / "copy"
    shutil.copytree(objects["cabinet"].parent, folder)
    obj = import_urdf(folder / "cabinet.urdf", class_name="portable")
    _, split = _generate(obj, tmp_path / "data", n=1)
    shutil.rmtree(folder)  # the data travels without its source files
    r = CliRunner().invoke(main, ["verify", str(split), "--quiet"])
    assert r.exit_code == 0, r.output
    assert GenerationConfig.from_dict(read_manifest(split)["config"]).third_party == obj.definition
    # the loaders read it too (joint count from the manifest, not the registry)
    from articulated_dataset.training.loaders.reader import ShardReader

    reader = ShardReader([split])
    sample = reader[len(reader) - 1]
    assert sample["axis_pose"].shape == (obj.obj_class.n_joints, 7) and sample["depth"].shape == (108, 192)


def _simple(tmp_path, joint_xml, name="simple", child_mesh=True):
    folder = tmp_path / name
    folder.mkdir()
    _box_obj(folder / "a.obj", [0.4, 0.4, 0.4], [0, 0, 0.2])
    _box_obj(folder / "b.obj", [0.02, 0.4, 0.4], [-0.01, 0, 0.2])
    body = _link("root", "a.obj") + _link("part", "b.obj" if child_mesh else None) + joint_xml
    return _write_urdf(folder / f"{name}.urdf", name, body)


@pytest.mark.parametrize("jtype", ["floating", "planar"])
def test_unsupported_joint_types(tmp_path, jtype):
    path = _simple(tmp_path, _joint("j", jtype, "root", "part", (-0.2, 0, 0)))
    with pytest.raises(UserError, match=f"joint 'j' of .*simple.urdf is {jtype}"):
        import_urdf(path, joints=["j"])
    with pytest.raises(UserError, match="no joint to articulate"):
        import_urdf(path)  # frozen when not selected: nothing left to articulate


def test_continuous_joint_uses_the_revolute_default_range(tmp_path):
    path = _simple(tmp_path, _joint("spin", "continuous", "root", "part", (-0.2, 0.2, 0), (0, 0, 1)))
    with pytest.raises(UserError, match=r"continuous joints \(spin\) turn freely: articulate them with joints"):
        import_urdf(path)  # not chosen by default: knobs and turntables do not open
    obj = import_urdf(path, joints=["spin"])
    assert obj.obj_class.joint_types == ("revolute",)
    assert obj.obj_class.table.q == ((0.0, math.pi / 2),)


@pytest.mark.slow
def test_hidden_part_error_names_joints(tmp_path, monkeypatch):
    """A part no pose shows (here: inside the body) cannot be labelled: the error says to
    choose the joints that open."""
    monkeypatch.setenv(urdf_import.CACHE_ENV, str(tmp_path / "cache"))
    _box_obj(tmp_path / "body.obj", [0.4, 0.4, 0.4], [0, 0, 0.2])
    _box_obj(tmp_path / "inner.obj", [0.1, 0.1, 0.1], [0, 0, 0.2])  # well inside the body
    path = _write_urdf(tmp_path / "hidden.urdf", "hidden", _link("root", "body.obj") + _link("part", "inner.obj")
                       + _joint("inner", "prismatic", "root", "part", (0, 0, 0), (-1, 0, 0), (0, 0.05)))
    r = CliRunner().invoke(main, ["generate", "--urdf", str(path), "--class-name", "hidden", "--n", "1", "--images", "1",
                                  "--out", str(tmp_path / "out"), "-q"])
    assert r.exit_code == 2, r.output
    assert "no pose in the table shows every moving part" in r.output and "--joints" in r.output


@pytest.mark.parametrize("case, pattern", [
    ("no_file", r"URDF file not found: .*nothere\.urdf"),
    ("bad_xml", r"cannot parse URDF .*bad\.urdf"),
    ("unknown_joint", r"has no joint 'nope'; its joints: j"),
    ("no_limit", r"prismatic joint 'j' of .*simple.urdf has no <limit>"),
    ("package_path", r"mesh file not found: .*nowhere/x\.obj"),
    ("no_part_geometry", r"joint 'j' of .* moves no geometry"),
    ("bad_name", r"invalid class name"),
    ("duplicate_joint", r"invalid URDF .*: duplicate joint name 'j'"),  # not "listed twice in --joints" (not given)
])
def test_bad_inputs_give_one_line_errors(tmp_path, case, pattern):
    kwargs = {}
    if case == "no_file":
        path = tmp_path / "nothere.urdf"
    elif case == "bad_xml":
        path = tmp_path / "bad.urdf"
        path.write_text("<robot name='x'><link name='a'></robot>")
    elif case == "no_limit":
        path = _simple(tmp_path, '<joint name="j" type="prismatic"><parent link="root"/><child link="part"/>'
                                 '<axis xyz="1 0 0"/></joint>')
        kwargs["joints"] = ["j"]
    elif case == "package_path":
        path = _simple(tmp_path, _joint("j", "prismatic", "root", "part", (-0.2, 0, 0), (-1, 0, 0), (0, 0.2)))
        path.write_text(path.read_text().replace('filename="b.obj"', 'filename="package://nowhere/x.obj"'))
    elif case == "duplicate_joint":
        path = _simple(tmp_path, _link("part2", "b.obj") + _joint("j", "prismatic", "root", "part", (-0.2, 0, 0), (-1, 0, 0),
                                                                  (0, 0.2))
                       + _joint("j", "prismatic", "root", "part2", (0.2, 0, 0), (1, 0, 0), (0, 0.2)))
    elif case == "no_part_geometry":
        path = _simple(tmp_path, _joint("j", "prismatic", "root", "part", (-0.2, 0, 0), (-1, 0, 0), (0, 0.2)),
                       child_mesh=False)
    else:
        path = _simple(tmp_path, _joint("j", "prismatic", "root", "part", (-0.2, 0, 0), (-1, 0, 0), (0, 0.2)))
        kwargs["joints"] = ["nope"] if case == "unknown_joint" else ["j"]
        if case == "bad_name":
            kwargs["class_name"] = "a/b"
    with pytest.raises(UserError, match=pattern) as exc:
        import_urdf(path, **kwargs)
    assert "\n" not in str(exc.value)


def test_reparametrize_range_cases():
    # closed = the limit nearer the URDF zero (ties: the lower one); q = 0 there, opening positive
    assert reparametrize_range(0.0, 1.0) == ((0.0, 1.0), False, 0.0)
    assert reparametrize_range(0.2, 1.0) == ((0.0, 0.8), False, 0.2)
    assert reparametrize_range(-1.5, 0.0) == ((0.0, 1.5), True, 0.0)
    assert reparametrize_range(-2.0, -0.5) == ((0.0, 1.5), True, -0.5)
    assert reparametrize_range(-0.25, 1.0) == ((0.0, 1.25), False, -0.25)
    assert reparametrize_range(-1.0, 0.25) == ((0.0, 1.25), True, 0.25)
    assert reparametrize_range(-0.5, 0.5) == ((0.0, 1.0), False, -0.5)


def test_default_pose_table_keeps_the_box_in_view():
    """Brute force: the box's corners at extreme poses project inside the image."""
    cam = CameraConfig()
    lo, hi = np.array([-0.3, -0.5, 0.0]), np.array([0.4, 0.5, 1.6])
    ranges = view_pose_ranges(lo, hi, cam, (-math.pi / 4, math.pi / 4))
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    K, inside = cam.K, 0
    for x in ranges["x_m"]:
        for y in ranges["y_m"]:
            for zz in ranges["z_m"]:
                for yaw in np.linspace(*ranges["yaw_rad"], 7):
                    p = corners @ _rot([0, 0, 1], yaw).T + [x, y, zz]
                    u = K[0, 2] - K[0, 0] * p[:, 1] / p[:, 0]
                    v = K[1, 2] - K[1, 1] * p[:, 2] / p[:, 0]
                    assert (u >= 0).all() and (u <= cam.width_px - 1).all()
                    assert (v >= 0).all() and (v <= cam.height_px - 1).all()
                    inside += 1
    assert inside == 2 * 2 * 2 * 7
    # nearest distance: the bounding sphere fills 1 / VIEW_MARGIN of the vertical view
    r = np.linalg.norm(corners - [0, 0, 0.8], axis=1).max()
    assert ranges["x_m"][0] == pytest.approx(VIEW_MARGIN * r / math.sin(math.radians(cam.vfov_deg) / 2))


def test_flat_meshes_are_thickened_and_all_faces_doubled():
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 1, 2], [1, 3, 2]], process=False)
    thick = _thicken_if_flat(flat)
    assert np.ptp(thick.vertices[:, 2]) == pytest.approx(FLAT_MESH_THICKNESS_M)
    box = trimesh.creation.box()
    assert _thicken_if_flat(box) is box
    ds = double_sided(box)
    assert len(ds.faces) == 2 * len(box.faces)
    np.testing.assert_array_equal(ds.faces[len(box.faces):], box.faces[:, ::-1])


@pytest.mark.slow
def test_a_third_party_object_predicted_as_a_built_in_class(objects, tmp_path):
    """predict --as-class: the shipped cabinet models (dense and the paper's MDN) predict a
    third-party cabinet (a door on a box, a URDF of its own), written under the split's class so
    score compares them with its labels; without it, or as a class of other joints, or for a
    built-in split of another class, one line naming the problem."""
    from click.testing import CliRunner

    from articulated_dataset.benchmark.predictions import read_predictions
    from articulated_dataset.cli import main

    obj = import_urdf(objects["cabinet"], class_name="door-box")
    _generate(obj, tmp_path / "data", n=4, images=4, split="test")
    split = tmp_path / "data" / "door-box" / "test"

    def run(*args):
        r = CliRunner().invoke(main, list(args))
        return r.exit_code, r.output

    out = tmp_path / "p.h5"
    for extra, needle in [([], "--as-class"), (["--as-class", "drawer"], "joints ['revolute']"),
                          (["--as-class", "nope"], "unknown object class")]:
        code, text = run("predict", "--model", "dense", str(split), "--out", str(out), *extra)
        assert code == 2 and text.count("\n") == 1 and needle in text, text
    code, text = run("predict", "--model", "dense", str(tiny_root_cabinet2(tmp_path)), "--out", str(out),
                     "--as-class", "cabinet")
    assert code == 2 and text.count("\n") == 1 and "built-in class 'cabinet2'" in text, text
    from articulated_dataset.methods import resolve_model

    microwave = str(resolve_model("dense", "microwave").path)  # a checkpoint file of another class
    code, text = run("predict", "--model", microwave, str(split), "--out", str(out), "--as-class", "cabinet")
    assert code == 2 and text.count("\n") == 1 and "is a 'microwave' model" in text, text
    for model in ("dense", "mdn-small"):
        code, text = run("predict", "--model", model, str(split), "--out", str(out), "--as-class", "cabinet",
                         "--overwrite", "-q")
        assert code == 0, text
        attrs, per_class = read_predictions(out)
        assert list(per_class) == ["door-box"] and attrs["as_class"] == "cabinet"
        assert len(per_class["door-box"]["sample_id"]) == 16
        code, text = run("score", str(out), "--truth", str(split), "--json", "-")
        assert code == 0, text
        row = json.loads(text)["rows"][0]
        assert row["class"] == "door-box" and row["n_scored"] == 16 and row["complete"]
        assert np.isfinite(row["metrics"]["axis_position_error_cm"]["mean"])


def tiny_root_cabinet2(tmp_path):
    """A built-in split (two-door cabinet, one object), as a user's."""
    from articulated_dataset.generation import GenerationConfig, generate_split

    generate_split(GenerationConfig("cabinet2", split="test", n_objects=1, images_per_object=2), tmp_path / "builtin")
    return tmp_path / "builtin" / "cabinet2" / "test"


def test_the_source_digest_covers_a_gltf_meshs_buffer(tmp_path):
    """A glTF mesh keeps its geometry in the buffer files it names: changing the .bin changes the
    object, so it must change the digest (the cache key, and the workers' check that every node
    builds the same object); a mesh of another format keeps the digest it had."""
    from articulated_dataset.generation.urdf_import.parse import load_structure, source_digest

    _box_obj(tmp_path / "a.obj", [0.4, 0.4, 0.4], [0, 0, 0.2])
    door = trimesh.creation.box(extents=[0.02, 0.4, 0.4])
    exported = trimesh.exchange.gltf.export_gltf(trimesh.Scene(door))
    gltf = json.loads(exported["model.gltf"])
    (tmp_path / "door.bin").write_bytes(exported[gltf["buffers"][0]["uri"]])
    gltf["buffers"][0]["uri"] = "door.bin"
    (tmp_path / "door.gltf").write_text(json.dumps(gltf))
    path = _write_urdf(tmp_path / "g.urdf", "g", _link("root", "a.obj") + _link("part", "door.gltf")
                       + _joint("j", "prismatic", "root", "part", (-0.2, 0, 0), (-1, 0, 0), (0, 0.2)))
    before = source_digest(load_structure(path))
    data = bytearray((tmp_path / "door.bin").read_bytes())
    data[0] ^= 1
    (tmp_path / "door.bin").write_bytes(bytes(data))
    assert source_digest(load_structure(path)) != before
