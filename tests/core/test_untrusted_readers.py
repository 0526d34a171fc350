"""Readers of files that may come from strangers: depth images, masks, point clouds, EXR
exports and URDF meshes.

* images are decoded by PIL's PNG decoder alone, whatever a file's content: an EPS named
  ``*.png`` never reaches PIL's EPS decoder (which runs Ghostscript on it), a TIFF named
  ``*.png`` is refused; an image's size is checked from its header before a pixel is decoded;
* an EXR whose stored pixels (data window) are a part of its image (display window) is read
  with the pixels in their place, not shifted to the corner;
* a PLY capture's texture is never opened, and its header must not declare more rows than
  the file holds (also a PCD's);
* a URDF mesh is read only in a listed format, up to a size, and its placed triangles are
  counted before they are built;
* ``ingest --overwrite`` replaces only a split that ingest wrote.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import threading
import zipfile

import numpy as np
import OpenEXR
import pytest
import trimesh
from click.testing import CliRunner
from PIL import Image

from articulated_dataset.cli import main
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.images.exr import read_depth_exr, read_mask_png
from articulated_dataset.core.images.intrinsics import MAX_SOURCE_PIXELS
from articulated_dataset.format import open_split
from articulated_dataset.generation import urdf_import
from articulated_dataset.generation.urdf_import import import_urdf, parse
from articulated_dataset.ingest.readers import load_cloud, load_depth, load_mask
from articulated_dataset.tools.exr import export_split
from helpers_core import assert_one_line_error, png_header
from helpers_real import write_capture

#: An Encapsulated PostScript file: PIL's EPS decoder hands it to Ghostscript to draw.
EPS = b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 1 1\n0 0 moveto 1 1 lineto stroke\nshowpage\n%%EOF\n"
CAMERA = {"fx": 105.3, "fy": 105.3, "cx": 95.5, "cy": 53.5, "width": 192, "height": 108}


def _depth_mm() -> np.ndarray:
    depth = np.zeros((108, 192), np.uint16)
    depth[30:80, 60:130] = 1500
    return depth


@pytest.fixture
def foreign_decoders(monkeypatch) -> list:
    """Every opening of a file by PIL's EPS decoder and every process started, recorded."""
    from PIL import EpsImagePlugin

    calls = []
    eps_open, popen_init = EpsImagePlugin.EpsImageFile._open, subprocess.Popen.__init__

    def recording_eps_open(self):
        calls.append("PIL's EPS decoder")
        return eps_open(self)

    def recording_popen_init(self, args, *rest, **kwargs):
        calls.append(f"process {args!r}")
        return popen_init(self, args, *rest, **kwargs)

    monkeypatch.setattr(EpsImagePlugin.EpsImageFile, "_open", recording_eps_open)
    monkeypatch.setattr(subprocess.Popen, "__init__", recording_popen_init)
    return calls


def _run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


# --------------------------------------------------------------------------------------
# Images: PNG only, size from the header
# --------------------------------------------------------------------------------------

def _estimate_depth_eps(tmp_path) -> list:
    (tmp_path / "d.png").write_bytes(EPS)
    return ["estimate", tmp_path / "d.png", "--class", "microwave"]


def _estimate_mask_eps(tmp_path) -> list:
    Image.fromarray(_depth_mm()).save(tmp_path / "d.png")
    (tmp_path / "m.png").write_bytes(EPS)
    return ["estimate", tmp_path / "d.png", "--mask", tmp_path / "m.png", "--class", "microwave"]


def _ingest_mask_eps(tmp_path) -> list:
    Image.fromarray(_depth_mm()).save(tmp_path / "c.png")
    (tmp_path / "c.mask.png").write_bytes(EPS)
    return ["ingest", tmp_path / "c.png", "--class", "microwave", "--out", tmp_path / "out", "-q"]


@pytest.mark.parametrize("make", [_estimate_depth_eps, _estimate_mask_eps, _ingest_mask_eps],
                         ids=["estimate depth", "estimate mask", "ingest mask"])
def test_an_eps_file_named_png_never_reaches_the_eps_decoder(tmp_path, foreign_decoders, make):
    (tmp_path / "camera.json").write_text(json.dumps(CAMERA))
    line = assert_one_line_error(_run(*make(tmp_path)), "not PNG data")
    assert foreign_decoders == [], (foreign_decoders, line)


def test_an_eps_file_in_an_exr_export_never_reaches_the_eps_decoder(tiny_root, tmp_path, foreign_decoders):
    """A mask of an export, through ``import-exr``, and a colour image as ``import-exr`` reads a
    ``--rgb`` export's (which ended in a traceback)."""
    exported = export_split(tiny_root / "drawer" / "test", tmp_path / "exp" / "drawer" / "test")
    next(exported.glob("*.mask.png")).write_bytes(EPS)
    assert_one_line_error(_run("import-exr", tmp_path / "exp", "--out", tmp_path / "back", "-q"), "not PNG data")
    rgb = next(exported.glob("*.mask.png")).with_name("colour.rgb.png")
    rgb.write_bytes(EPS)
    with pytest.raises(UserError, match="not PNG data"):
        read_mask_png(rgb, (108, 192), what="colour", mode="RGB")
    assert foreign_decoders == []


def test_a_tiff_named_png_is_refused(tmp_path):
    Image.fromarray(_depth_mm()).save(tmp_path / "d.png", format="TIFF")
    with pytest.raises(UserError, match="not PNG data"):
        load_depth(tmp_path / "d.png")
    Image.fromarray((_depth_mm() > 0).astype(np.uint8) * 255).save(tmp_path / "m.png", format="TIFF")
    with pytest.raises(UserError, match="not PNG data"):
        load_mask(tmp_path / "m.png", (108, 192), 1)


def test_a_mask_must_be_named_png(tmp_path):
    Image.fromarray((_depth_mm() > 0).astype(np.uint8) * 255).save(tmp_path / "m.tif", format="PNG")
    with pytest.raises(UserError, match=r"must be a PNG file named \*\.png"):
        load_mask(tmp_path / "m.tif", (108, 192), 1)


@pytest.mark.parametrize("side_px", [5000, 10000], ids=["25 Mpx", "100 Mpx"])
@pytest.mark.parametrize("what", ["depth", "mask"])
def test_an_image_over_the_pixel_limit_is_refused_before_decoding(tmp_path, monkeypatch, side_px, what):
    """A few hundred bytes declare the size: no pixel is decoded (a 230 KB PNG of 120 Mpx took
    27 s and 3.4 GB before estimate refused its intrinsics)."""
    from PIL import ImageFile

    assert side_px**2 > MAX_SOURCE_PIXELS
    decoded = []
    load = ImageFile.ImageFile.load
    monkeypatch.setattr(ImageFile.ImageFile, "load", lambda self: decoded.append(self.size) or load(self))
    (tmp_path / "camera.json").write_text(json.dumps({k: CAMERA[k] for k in ("fx", "fy", "cx", "cy")}))
    if what == "depth":
        (tmp_path / "d.png").write_bytes(png_header(side_px, side_px, 16))
        args = [tmp_path / "d.png"]
    else:
        Image.fromarray(_depth_mm()).save(tmp_path / "d.png")
        (tmp_path / "m.png").write_bytes(png_header(side_px, side_px, 8))
        args = [tmp_path / "d.png", "--mask", tmp_path / "m.png"]
    assert_one_line_error(_run("estimate", *args, "--class", "microwave"), f"at most {MAX_SOURCE_PIXELS:,} pixels")
    assert (side_px, side_px) not in decoded


# --------------------------------------------------------------------------------------
# EXR data windows
# --------------------------------------------------------------------------------------

def _write_exr(path, z: np.ndarray, data_window, display_window) -> None:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "dataWindow": data_window, "displayWindow": display_window}
    with OpenEXR.File(header, {"Z": z.astype(np.float32)}) as f:
        f.write(str(path))


def test_an_exr_crop_is_read_in_its_place(tmp_path):
    """Stored pixels x 2..7, y 3..6 of a 10 x 8 image: they stay there, the rest is no return
    (read from the corner, an estimate with the sensor's intrinsics would be 57 cm off)."""
    z = np.arange(1, 25, dtype=np.float32).reshape(4, 6) / 10.0 + 1.0
    _write_exr(tmp_path / "crop.exr", z, ((2, 3), (7, 6)), ((0, 0), (9, 7)))
    depth = load_depth(tmp_path / "crop.exr")
    expected = np.zeros((8, 10))
    expected[3:7, 2:8] = z
    np.testing.assert_array_equal(depth, expected)
    # stored pixels reaching beyond the image (overscan) are cut at its edges
    _write_exr(tmp_path / "over.exr", z, ((-2, -1), (3, 2)), ((0, 0), (9, 7)))
    expected = np.zeros((8, 10))
    expected[0:3, 0:4] = z[1:, 2:]
    np.testing.assert_array_equal(load_depth(tmp_path / "over.exr"), expected)


def test_an_exr_image_declared_over_the_pixel_limit_is_refused(tmp_path):
    """The image (display window) is allocated whole: its size is checked like the stored part's."""
    _write_exr(tmp_path / "d.exr", np.ones((4, 6)), ((0, 0), (5, 3)), ((0, 0), (99_999, 99_999)))
    with pytest.raises(UserError, match=f"at most {MAX_SOURCE_PIXELS:,} pixels"):
        load_depth(tmp_path / "d.exr")


def test_an_exported_exr_must_store_its_whole_image(tmp_path):
    """An export's depth images are whole: stored pixels placed elsewhere are refused, not shifted."""
    _write_exr(tmp_path / "d.exr", np.ones((108, 192)), ((1, 1), (192, 108)), ((0, 0), (193, 109)))
    with pytest.raises(UserError, match="data window"):
        read_depth_exr(tmp_path / "d.exr", (108, 192))


def test_an_exr_of_many_channels_or_parts_is_refused_from_its_header(tmp_path):
    """OpenEXR decodes every channel: 40 compressed channels of 2000 x 2000 px are a 650 KB file
    and 640 MB decoded.  The channel count and the parts are read from the header first."""
    from articulated_dataset.core.images.exr import MAX_EXR_CHANNELS

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    channels = {f"C{i}": np.zeros((8, 10), np.float32) for i in range(MAX_EXR_CHANNELS)}
    channels["Z"] = np.ones((8, 10), np.float32)
    with OpenEXR.File(header, channels) as f:
        f.write(str(tmp_path / "many.exr"))
    for read in (load_depth, lambda path: read_depth_exr(path, (8, 10))):
        with pytest.raises(UserError, match=f"at most {MAX_EXR_CHANNELS} channels"):
            read(tmp_path / "many.exr")
    parts = [OpenEXR.Part(dict(header), {"Z": np.ones((8, 10), np.float32)}, f"p{i}") for i in range(2)]
    with OpenEXR.File(parts) as f:
        f.write(str(tmp_path / "parts.exr"))
    with pytest.raises(UserError, match="one part"):
        load_depth(tmp_path / "parts.exr")


def test_import_exr_refuses_an_index_declaring_huge_images(tiny_root, tmp_path):
    """An export index declares its images' size, and each depth image is decoded at that size:
    a size past import-exr's limit is one line before any image is read."""
    from articulated_dataset.tools.exr.restore import MAX_IMPORT_PIXELS

    exported = export_split(tiny_root / "drawer" / "test", tmp_path / "exp" / "drawer" / "test")
    index = json.loads((exported / "split.json").read_text())
    for shard in index["shards"]:
        shard["attrs"]["image_height"] = shard["attrs"]["image_width"] = 16384
    (exported / "split.json").write_text(json.dumps(index))
    line = assert_one_line_error(_run("import-exr", tmp_path / "exp", "--out", tmp_path / "back", "-q"),
                                 f"at most {MAX_IMPORT_PIXELS:,} pixels")
    assert "16384x16384" in line and not (tmp_path / "back").exists()


# --------------------------------------------------------------------------------------
# Point clouds
# --------------------------------------------------------------------------------------

def _ascii_ply(path, n_declared: int, rows: list[str], comment: str = "") -> None:
    path.write_text(f"ply\nformat ascii 1.0\n{comment}element vertex {n_declared}\nproperty float x\n"
                    f"property float y\nproperty float z\nend_header\n" + "".join(r + "\n" for r in rows))


def test_a_ply_declaring_more_points_than_it_holds_is_refused(tmp_path):
    _ascii_ply(tmp_path / "c.ply", 2_000_000_000, ["0 0 1.5"])
    with pytest.raises(UserError, match="declares 2,000,000,000 rows"):
        load_cloud(tmp_path / "c.ply")
    _ascii_ply(tmp_path / "ok.ply", 2, ["0 0 1.5", "0.1 0 1.5"])
    assert load_cloud(tmp_path / "ok.ply").shape == (2, 3)
    (tmp_path / "last.ply").write_bytes((tmp_path / "ok.ply").read_bytes().rstrip(b"\n"))  # no final newline
    assert load_cloud(tmp_path / "last.ply").shape == (2, 3)


def test_a_pcd_declaring_more_points_than_it_holds_is_refused(tmp_path):
    (tmp_path / "c.pcd").write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1000\nDATA ascii\n0 0 1.5\n")
    with pytest.raises(UserError, match="holds 1 points, its header declares 1,000"):
        load_cloud(tmp_path / "c.pcd")


def test_a_ply_texture_that_is_a_fifo_is_never_opened(tmp_path):
    """trimesh's resolver opened ``comment TextureFile`` whatever it was: a FIFO blocked forever."""
    os.mkfifo(tmp_path / "tex.png")
    _ascii_ply(tmp_path / "c.ply", 1, ["0 0 1.5"], comment="comment TextureFile tex.png\n")
    result = []
    reader = threading.Thread(target=lambda: result.append(load_cloud(tmp_path / "c.ply")), daemon=True)
    reader.start()
    reader.join(60)
    if reader.is_alive():  # unblock the reader so the test process can end
        with open(tmp_path / "tex.png", "wb"):
            pass
        reader.join(10)
        pytest.fail("reading the point cloud opened its texture")
    assert result[0].shape == (1, 3)


@pytest.mark.parametrize("texture", ["outside", "eps"])
def test_a_ply_texture_is_ignored(tmp_path, caplog, foreign_decoders, texture):
    """A texture outside the capture's folder or in EPS is not opened (no logged traceback, no
    PIL EPS decoder).  Ingest needs no colour: the capture is read without it, quietly."""
    folder = tmp_path / "caps"
    folder.mkdir()
    (tmp_path / "secret.png").write_bytes(EPS)
    if texture == "eps":
        (folder / "tex.png").write_bytes(EPS)
    name = "../secret.png" if texture == "outside" else "tex.png"
    grid = [f"{x:.3f} {y:.3f} 1.5" for x in np.linspace(-0.1, 0.1, 20) for y in np.linspace(-0.1, 0.1, 20)]
    _ascii_ply(folder / "c.ply", len(grid), grid, comment=f"comment TextureFile {name}\n")
    (folder / "camera.json").write_text(json.dumps(CAMERA))
    with caplog.at_level(logging.DEBUG):
        result = _run("ingest", folder / "c.ply", "--class", "microwave", "--out", tmp_path / "out", "-q")
    assert result.exit_code == 0, result.output
    assert result.output == ""
    assert not [r for r in caplog.records if r.exc_info or "image" in r.getMessage()], caplog.text
    assert foreign_decoders == []


# --------------------------------------------------------------------------------------
# URDF meshes
# --------------------------------------------------------------------------------------

def _object(folder, door_mesh: str) -> os.PathLike:
    """A box body with a door whose geometry is ``door_mesh`` (a file name in ``folder``)."""
    body = trimesh.creation.box(extents=[0.4, 0.4, 0.4])
    body.apply_translation([0, 0, 0.2])
    body.export(str(folder / "body.obj"))
    path = folder / "obj.urdf"
    path.write_text(
        '<?xml version="1.0"?>\n<robot name="obj">'
        '<link name="base"><visual><geometry><mesh filename="body.obj"/></geometry></visual></link>'
        f'<link name="door"><visual><geometry><mesh filename="{door_mesh}"/></geometry></visual></link>'
        '<joint name="hinge" type="revolute"><parent link="base"/><child link="door"/>'
        '<origin xyz="-0.2 0.2 0"/><axis xyz="0 0 -1"/><limit lower="0" upper="1.5" effort="1" velocity="1"/>'
        '</joint></robot>\n')
    return path


def _door() -> trimesh.Trimesh:
    door = trimesh.creation.box(extents=[0.02, 0.4, 0.4])
    door.apply_translation([-0.01, -0.2, 0.2])
    return door


@pytest.fixture
def obj(tmp_path, monkeypatch):
    """The object's folder (its name is the class name's first part); the model cache beside it."""
    monkeypatch.setenv(urdf_import.CACHE_ENV, str(tmp_path / "cache"))
    (tmp_path / "obj").mkdir()
    return tmp_path / "obj"


def test_the_mesh_object_imports(obj):
    """Control: the object with an OBJ door imports, so each refusal below is caused by its mesh."""
    _door().export(str(obj / "door.obj"))
    assert import_urdf(_object(obj, "door.obj")).obj_class.n_joints == 1


@pytest.mark.parametrize("suffix", [".zip", ".3mf", ".dae", ".svg"])
def test_a_mesh_in_an_unlisted_format_is_refused(obj, suffix):
    """An archive inflates in trimesh (1.6 MB to 3.3 GB); it is refused by its name, unread."""
    with zipfile.ZipFile(obj / f"door{suffix}", "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("door.obj", trimesh.exchange.obj.export_obj(_door()))
    with pytest.raises(UserError, match=f"'{suffix}' is not a mesh format read here"):
        import_urdf(_object(obj, f"door{suffix}"))


def test_a_mesh_over_the_size_limit_is_refused(obj, monkeypatch):
    trimesh.creation.icosphere(radius=0.1).export(str(obj / "door.obj"))  # larger than the body's file
    path = _object(obj, "door.obj")
    monkeypatch.setattr(parse, "MAX_MESH_FILE_BYTES", (obj / "door.obj").stat().st_size - 1)
    with pytest.raises(UserError, match="door.obj .* bytes, over the"):
        import_urdf(path)


def _gltf(door: trimesh.Trimesh) -> dict:
    return json.loads(trimesh.exchange.gltf.export_gltf(trimesh.Scene(door), embed_buffers=True)["model.gltf"])


def test_a_gltf_accessor_without_data_is_refused(obj):
    """An accessor without a bufferView is zeros of its declared count (or compressed data):
    a few bytes of JSON declare gigabytes."""
    gltf = _gltf(_door())
    position = gltf["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    del gltf["accessors"][position]["bufferView"]
    (obj / "door.gltf").write_text(json.dumps(gltf))
    with pytest.raises(UserError, match="accessor .* has no bufferView"):
        import_urdf(_object(obj, "door.gltf"))


def test_placed_copies_are_counted_before_they_are_built(obj, monkeypatch):
    """A glTF's nodes may place one mesh many times: 2,000 copies of 80 triangles are refused
    from the count (the link's limit) before the copies exist."""
    flattened, to_mesh = [], trimesh.Scene.to_mesh
    monkeypatch.setattr(trimesh.Scene, "to_mesh", lambda self: flattened.append(len(self.graph.nodes_geometry))
                        or to_mesh(self))
    gltf = _gltf(trimesh.creation.icosphere(subdivisions=1, radius=0.1))  # 80 triangles
    gltf["nodes"] = [{"mesh": 0, "translation": [0.0, 0.0, 0.001 * i]} for i in range(2_000)]
    gltf["scenes"] = [{"nodes": list(range(2_000))}]
    (obj / "door.gltf").write_text(json.dumps(gltf))
    with pytest.raises(UserError, match="160,000 triangles.*MuJoCo"):
        import_urdf(_object(obj, "door.gltf"))
    assert 2_000 not in flattened


# --------------------------------------------------------------------------------------
# ingest --overwrite
# --------------------------------------------------------------------------------------

def test_ingest_overwrite_replaces_only_a_real_split(tiny_root, tmp_path):
    """``--overwrite --split train`` replaced a generated training split with one capture."""
    generated = tmp_path / "out" / "cabinet" / "train"
    shutil.copytree(tiny_root / "cabinet" / "train", generated)
    before = {p.name: p.read_bytes() for p in generated.iterdir()}
    _, shards = open_split(tiny_root / "cabinet" / "test")
    write_capture(tmp_path / "caps", "c", shards[0].sample(0), shards[0].K, None)
    ingest = ["ingest", tmp_path / "caps", "--class", "cabinet", "--out", tmp_path / "out", "-q"]
    assert_one_line_error(_run(*ingest, "--split", "train", "--overwrite"), "--overwrite replaces only a real split")
    assert {p.name: p.read_bytes() for p in generated.iterdir()} == before
    assert _run(*ingest, "--split", "real").exit_code == 0  # a real split is still replaced
    assert _run(*ingest, "--split", "real", "--overwrite").exit_code == 0
