"""Hostile data: nothing read from a data file runs as code or leads outside the named folders.

Every case runs the CLI as a user does on a crafted input and checks that

* the command ends with exactly one line ``artdata: error: ...`` and exit code 2;
* nothing outside the named folders changed: the whole test folder (a ``victim/`` folder with
  canary files, the input copies, the output folder) is compared byte for byte before and
  after (only the processed-URDF cache may change);
* no injected payload ran: each payload would create a file ``PWNED`` if evaluated.

Where a traversal would *succeed* if followed (a valid shard, image or mesh is placed where the
hostile name points), the old behaviour passes silently, so these tests fail on it.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.core.images.exr import INDEX_NAME
from articulated_dataset.format import MANIFEST_NAME, resolve_inside
from articulated_dataset.generation import GenerationConfig, generate_split, urdf_import
from articulated_dataset.generation.templating import render_urdf
from articulated_dataset.tools.exr import export_split

#: What a payload would create if it were ever evaluated.
PWNED = "PWNED"


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------

def run(*args) -> object:
    result = CliRunner().invoke(main, [str(a) for a in args])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result


def message_lines(result) -> list[str]:
    """Output lines other than progress-bar redraws."""
    return [ln for ln in result.output.replace("\r", "\n").splitlines() if ln.strip() and "img/s" not in ln]


def assert_refused(result, needle: str | None = None) -> str:
    lines = message_lines(result)
    assert result.exit_code == 2, result.output
    assert len(lines) == 1 and lines[0].startswith("artdata: error: "), result.output
    assert "Traceback" not in result.output
    if needle is not None:
        assert needle in lines[0], lines[0]
    return lines[0]


def snapshot(root: Path, skip: tuple[str, ...] = ("cache",)) -> dict:
    """Every path under ``root`` (links not followed) with its bytes / link target."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        d = Path(dirpath)
        dirnames[:] = [n for n in dirnames if not (d == root and n in skip)]
        for n in dirnames + filenames:
            p = d / n
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = "link:" + os.readlink(p)
            elif p.is_file():
                out[rel] = p.read_bytes()
            else:
                out[rel] = "dir"
    return out


class World:
    """A test folder: ``victim/`` (must never change) and copies of the inputs."""

    def __init__(self, root: Path):
        self.root = root
        self.victim = root / "victim"
        (self.victim / "x" / "train").mkdir(parents=True)
        (self.victim / "canary.txt").write_text("canary")
        (self.victim / "x" / "train" / "keep.txt").write_text("keep")
        self.before = None

    def freeze(self) -> None:
        self.before = snapshot(self.root)

    def assert_untouched(self) -> None:
        assert not list(self.root.rglob(PWNED)) and not Path(PWNED).exists(), "a payload ran"
        after = snapshot(self.root)
        changed = sorted(set(after) ^ set(self.before)) + sorted(k for k in after if k in self.before
                                                                 and after[k] != self.before[k])
        assert not changed, f"changed by a refused command: {changed[:5]}"


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A tiny drawer split (2 shards, 2 images each) and its EXR export."""
    root = tmp_path_factory.mktemp("hostile-base")
    split = generate_split(GenerationConfig("drawer", n_objects=2, images_per_object=2, objects_per_shard=1), root / "gen")
    export = export_split(split, root / "exp" / "drawer" / "train")
    predictions = root / "mean.h5"
    assert run("baseline", "mean", "--train", split, "--test", split, "--out", predictions, "-q").exit_code == 0
    return {"split": split, "export": export, "predictions": predictions}


@pytest.fixture
def world(tmp_path):
    return World(tmp_path)


def _copy_split(base, world) -> Path:
    split = world.root / "data" / "drawer" / "train"
    shutil.copytree(base["split"], split)
    return split


def _edit_json(path: Path, edit) -> None:
    d = json.loads(path.read_text())
    edit(d)
    path.write_text(json.dumps(d))


def _set_class(value):
    def edit(m):
        if value is _MISSING:
            del m["class_name"]
        else:
            m["class_name"] = value
    return edit


_MISSING = object()

# --------------------------------------------------------------------------------------
# 1. names read from manifests: class names and shard files
# --------------------------------------------------------------------------------------

BAD_CLASS_NAMES = ["../../../victim/x", "../../x", "..", ".", "", "/tmp/abs-class", "a/b", "a\\b", "x" * 40,
                   ".hidden", "-rf", "a\nb", "${1+1}", 5, None, ["drawer"], _MISSING]
CLASS_IDS = ["up3", "up2", "dotdot", "dot", "empty", "absolute", "slash", "backslash", "long", "hidden", "option",
             "newline", "xacro", "int", "null", "list", "missing"]
READERS = ["info", "export", "show"]


def _read_cmd(cmd: str, split: Path, world: World):
    if cmd == "info":
        return run("info", split)
    if cmd == "export":
        return run("export", split, world.root / "out", "--overwrite", "-q")
    return run("show", split, "--out", world.root / "out" / "gallery.png", "-q")


@pytest.mark.parametrize("cmd", READERS)
@pytest.mark.parametrize("value", BAD_CLASS_NAMES, ids=CLASS_IDS)
def test_manifest_class_name_is_a_name(base, world, cmd, value):
    split = _copy_split(base, world)
    _edit_json(split / MANIFEST_NAME, _set_class(value))
    world.freeze()
    assert_refused(_read_cmd(cmd, split, world), "manifest.json")
    world.assert_untouched()


def _outside_shard(base, world) -> Path:
    """A valid shard outside the split: a followed traversal would read it successfully."""
    target = world.victim / "shard-00000.h5"
    shutil.copy(base["split"] / "shard-00000.h5", target)
    return target


SHARD_NAMES = ["../../../victim/shard-00000.h5", "{abs}", "shard-00000.h5/../../../../victim/shard-00000.h5",
               "sub/shard-00000.h5", "shard-0.h5", "x.h5", "", 7, None]
SHARD_IDS = ["up3", "absolute", "embedded-up", "subfolder", "short-number", "other-name", "empty", "int", "null"]


@pytest.mark.parametrize("cmd", READERS)
@pytest.mark.parametrize("value", SHARD_NAMES, ids=SHARD_IDS)
def test_manifest_shard_file_is_a_shard_name(base, world, cmd, value):
    split = _copy_split(base, world)
    outside = _outside_shard(base, world)
    value = str(outside) if value == "{abs}" else value

    def edit(m):
        m["shards"][0]["file"] = value
    _edit_json(split / MANIFEST_NAME, edit)
    world.freeze()
    assert_refused(_read_cmd(cmd, split, world), "shard")
    world.assert_untouched()


@pytest.mark.parametrize("cmd", READERS)
def test_shard_symlink_leading_out_is_refused(base, world, cmd):
    split = _copy_split(base, world)
    outside = _outside_shard(base, world)
    (split / "shard-00000.h5").unlink()
    (split / "shard-00000.h5").symlink_to(outside)
    world.freeze()
    assert_refused(_read_cmd(cmd, split, world), "leads outside")
    world.assert_untouched()


@pytest.mark.parametrize("listed", [True, False], ids=["listed", "no-manifest"])
def test_verify_reports_a_shard_symlink_leading_out_without_reading_it(base, world, listed):
    """verify followed the link: it hashed and read the file outside the split and said "OK"
    (every other reader refuses the split)."""
    split = _copy_split(base, world)
    outside = _outside_shard(base, world)
    (split / "shard-00000.h5").unlink()
    (split / "shard-00000.h5").symlink_to(outside)
    if not listed:
        (split / MANIFEST_NAME).unlink()
    world.freeze()
    result = run("verify", split, "--workers", 1)
    assert result.exit_code == 1, result.output
    assert "leads outside" in result.output and "Traceback" not in result.output
    world.assert_untouched()


@pytest.mark.parametrize("value", BAD_CLASS_NAMES[:8], ids=CLASS_IDS[:8])
def test_loader_refuses_manifest_names(base, world, value):
    from articulated_dataset.training.loaders.reader import ShardReader

    split = _copy_split(base, world)
    _edit_json(split / MANIFEST_NAME, _set_class(value))
    with pytest.raises(DataFormatError, match="invalid class name"):
        ShardReader(split)


def test_export_overwrite_never_deletes_outside(base, world):
    """The issue's case: class_name ../../x with --overwrite deleted and wrote outside the output."""
    split = _copy_split(base, world)
    _edit_json(split / MANIFEST_NAME, _set_class("../victim/x"))
    (world.root / "out").mkdir()
    world.freeze()
    assert_refused(run("export", split, world.root / "out", "--overwrite", "-q"))
    world.assert_untouched()


@pytest.mark.parametrize("cmd, marker", [("export", INDEX_NAME), ("import-exr", MANIFEST_NAME)])
def test_overwrite_replaces_only_our_own_folders(base, world, cmd, marker):
    source = _copy_split(base, world) if cmd == "export" else _copy_export(base, world)
    target = world.root / "out" / "drawer" / "train"
    target.mkdir(parents=True)
    (target / "thesis.tex").write_text("mine")
    world.freeze()
    args = [source, world.root / "out"] if cmd == "export" else [source, "--out", world.root / "out"]
    assert_refused(run(cmd, *args, "--overwrite", "-q"), f"holds no {marker}")
    world.assert_untouched()


@pytest.mark.parametrize("cmd", ["export", "import-exr"])
@pytest.mark.parametrize("overwrite", [False, True], ids=["plain", "overwrite"])
def test_two_sources_with_one_target_are_refused_before_writing(base, world, cmd, overwrite):
    """A copied class folder (its manifest still names drawer): both splits went to
    out/drawer/train, so the run failed after writing the first (a partial output) or, with
    --overwrite, replaced the first by the second and reported both as exported (exit 0)."""
    if cmd == "export":
        source = _copy_split(base, world)
        shutil.copytree(source, world.root / "data" / "drawer_backup" / "train")
        args = [world.root / "data", world.root / "out"]
    else:
        source = _copy_export(base, world)
        shutil.copytree(source, world.root / "exp" / "drawer_backup" / "train")
        args = [world.root / "exp", "--out", world.root / "out"]
    world.freeze()
    assert_refused(run(cmd, *args, "-q", *(["--overwrite"] if overwrite else [])), "both be written")
    world.assert_untouched()


@pytest.mark.parametrize("case", ["image-twice", "negative-image", "across-shards"])
def test_export_refuses_indices_that_would_overwrite_or_garble_files(base, world, case):
    """Two images with one (object, image) index: the second overwrote the first's files and
    the export ended with exit 0, holding fewer images than split.json lists (import-exr then
    refused it); a negative index gave stems import-exr refuses."""
    import h5py

    split = _copy_split(base, world)
    shard = split / ("shard-00001.h5" if case == "across-shards" else "shard-00000.h5")
    with h5py.File(shard, "r+") as f:
        if case == "across-shards":  # shard 1 claims object 0, as shard 0 does
            values, name = np.zeros_like(f["object_index"][:]), "object_index"
        else:
            values, name = np.array([0, 0] if case == "image-twice" else [-1, 1], f["image_index"].dtype), "image_index"
        del f[name]
        f.create_dataset(name, data=values)
    _edit_json(split / MANIFEST_NAME, lambda m: m["shards"][int(case == "across-shards")].update(
        bytes=shard.stat().st_size, sha256=__import__("hashlib").sha256(shard.read_bytes()).hexdigest()))
    world.freeze()
    assert_refused(run("export", split, world.root / "out", "-q"), "artdata verify")
    world.assert_untouched()


def test_export_overwrite_swaps_in_a_complete_export(base, world):
    split = _copy_split(base, world)
    target = world.root / "out" / "drawer" / "train"
    assert run("export", split, world.root / "out", "-q").exit_code == 0
    assert run("export", split, world.root / "out", "--overwrite", "-q").exit_code == 0
    assert (target / INDEX_NAME).is_file() and not list(target.parent.glob(".*partial*"))


# --------------------------------------------------------------------------------------
# 2. import-exr: names in split.json and label files
# --------------------------------------------------------------------------------------

def _copy_export(base, world) -> Path:
    exp = world.root / "exp" / "drawer" / "train"
    shutil.copytree(base["export"], exp)
    return exp


def _index_edit(kind: str, value):
    def edit(ix):
        if kind == "class":
            ix["manifest"]["class_name"] = value
        elif kind == "file":
            ix["shards"][0]["file"] = value
            ix["manifest"]["shards"][0]["file"] = value
        elif kind == "stem":
            ix["shards"][0]["samples"][0] = value
        elif kind == "manifest-file":
            ix["manifest"]["shards"][0]["file"] = value
    return edit


INDEX_CASES = [("class", "../../victim/x"), ("class", "../victim/x"), ("class", "/tmp/abs-class"), ("class", ".."),
               ("class", "a/b"), ("class", ""), ("class", 3), ("file", "../../../victim/shard-00000.h5"),
               ("file", "{abs}"), ("file", "shard-00000.h5/../x.h5"), ("file", None),
               ("manifest-file", "../../victim/shard-00000.h5"),
               ("stem", "../../../victim/o000000_i000"), ("stem", "{abs-stem}"), ("stem", "o000000_i000/../../x"),
               ("stem", "nope"), ("stem", 12), ("stem", "")]


@pytest.mark.parametrize("overwrite", [False, True], ids=["plain", "overwrite"])
@pytest.mark.parametrize("kind, value", INDEX_CASES, ids=[f"{k}-{i}" for i, (k, _) in enumerate(INDEX_CASES)])
def test_import_exr_names_stay_inside(base, world, kind, value, overwrite):
    exp = _copy_export(base, world)
    # valid files where a followed traversal would land: an import would then succeed
    for suffix in (".exr", ".mask.png", ".json"):
        shutil.copy(exp / f"o000000_i000{suffix}", world.victim / f"o000000_i000{suffix}")
    value = {"{abs}": str(world.victim / "shard-00000.h5"),
             "{abs-stem}": str(world.victim / "o000000_i000")}.get(value, value) if isinstance(value, str) else value
    _edit_json(exp / INDEX_NAME, _index_edit(kind, value))
    out = world.root / "out"
    if overwrite:  # an earlier import, which --overwrite may replace (and nothing else)
        (out / "drawer" / "train").mkdir(parents=True)
        (out / "drawer" / "train" / MANIFEST_NAME).write_text("{}")
    world.freeze()
    args = ["import-exr", exp, "--out", out, "-q"] + (["--overwrite"] if overwrite else [])
    assert_refused(run(*args), "split.json")
    world.assert_untouched()


def _shard0(ix):
    return ix["shards"][0]


INDEX_CONTENT = {
    "attrs-nested": lambda ix: _shard0(ix)["attrs"].update(x={"a": 1}),
    "attrs-not-object": lambda ix: _shard0(ix).update(attrs=[1]),
    "attrs-null": lambda ix: _shard0(ix)["attrs"].update(x=None),
    "attrs-mixed-list": lambda ix: _shard0(ix)["attrs"].update(x=[1, "a"]),
    "height-text": lambda ix: _shard0(ix)["attrs"].update(image_height="abc"),
    "height-huge": lambda ix: _shard0(ix)["attrs"].update(image_height=10**12),
    "joints-negative": lambda ix: _shard0(ix)["attrs"].update(n_joints=-3),
    "K-text": lambda ix: _shard0(ix).update(K="abc"),
    "K-ragged": lambda ix: _shard0(ix).update(K=[[1, 2], [3]]),
    "K-nan": lambda ix: _shard0(ix).update(K=[["nan"] * 3] * 3),
    "samples-twice": lambda ix: _shard0(ix).update(samples=_shard0(ix)["samples"] * 2),
    "samples-empty": lambda ix: _shard0(ix).update(samples=[]),
    "shard-twice": lambda ix: ix["shards"].append(json.loads(json.dumps(_shard0(ix)))),
    "manifest-config": lambda ix: ix["manifest"].update(config="x"),
    "manifest-count": lambda ix: ix["manifest"]["shards"][0].update(n_images="x"),
}


@pytest.mark.parametrize("case", list(INDEX_CONTENT))
def test_import_exr_index_content_is_checked(base, world, case):
    """Malformed or inconsistent split.json content: one line, nothing written (not a traceback,
    a 10 PiB allocation or a silently wrong split)."""
    exp = _copy_export(base, world)
    _edit_json(exp / INDEX_NAME, INDEX_CONTENT[case])
    world.freeze()
    assert_refused(run("import-exr", exp, "--out", world.root / "out", "-q"))
    world.assert_untouched()


@pytest.mark.parametrize("value", [float("nan"), 100.0, -5.0])
def test_import_exr_label_values_are_verified(base, world, value):
    exp = _copy_export(base, world)
    _edit_json(exp / "o000001_i001.json", lambda lab: lab.update(q=[value]))
    world.freeze()
    assert_refused(run("import-exr", exp, "--out", world.root / "out", "-q"), "fails verification")
    world.assert_untouched()


#: Side (px) a hostile image header claims (kept moderate: a regression must not exhaust memory).
CLAIMED_SIDE_PX = 4000


def _claim_size_exr(path: Path) -> None:
    """Patch the EXR header's dataWindow to CLAIMED_SIDE_PX squared (the pixels stay small)."""
    import struct

    b = bytearray(path.read_bytes())
    key = b"dataWindow\x00box2i\x00"
    off = b.index(key) + len(key) + 4  # after the attribute's size field
    b[off:off + 16] = struct.pack("<4i", 0, 0, CLAIMED_SIDE_PX - 1, CLAIMED_SIDE_PX - 1)
    path.write_bytes(bytes(b))


def _claim_size_png(path: Path) -> None:
    from PIL import Image

    Image.new("L", (CLAIMED_SIDE_PX, CLAIMED_SIDE_PX)).save(path)


@pytest.mark.parametrize("suffix, claim", [(".exr", _claim_size_exr), (".mask.png", _claim_size_png)], ids=["exr", "png"])
def test_import_exr_image_size_checked_before_decoding(base, world, suffix, claim):
    exp = _copy_export(base, world)
    claim(exp / f"o000001_i000{suffix}")
    world.freeze()
    assert_refused(run("import-exr", exp, "--out", world.root / "out", "-q"),
                   f"is {CLAIMED_SIDE_PX}x{CLAIMED_SIDE_PX} px, expected")
    world.assert_untouched()


@pytest.mark.parametrize("suffix", [".exr", ".mask.png", ".json"])
def test_import_exr_file_symlink_leading_out(base, world, suffix):
    exp = _copy_export(base, world)
    shutil.copy(exp / f"o000000_i000{suffix}", world.victim / f"o000000_i000{suffix}")
    (exp / f"o000000_i000{suffix}").unlink()
    (exp / f"o000000_i000{suffix}").symlink_to(world.victim / f"o000000_i000{suffix}")
    world.freeze()
    assert_refused(run("import-exr", exp, "--out", world.root / "out", "-q"), "leads outside")
    world.assert_untouched()


def test_import_exr_failure_keeps_the_previous_split(base, world):
    """A failed --overwrite (damaged image found while reading) leaves the old split as it was."""
    exp = _copy_export(base, world)
    out = world.root / "out"
    assert run("import-exr", exp, "--out", out, "-q").exit_code == 0
    (exp / "o000001_i001.exr").write_bytes(b"garbage")
    world.freeze()
    assert_refused(run("import-exr", exp, "--out", out, "--overwrite", "-q"), "o000001_i001.exr")
    world.assert_untouched()


# --------------------------------------------------------------------------------------
# 3. HDF5 layouts that read elsewhere, and damaged shards
# --------------------------------------------------------------------------------------

def _replace_dataset(path: Path, name: str, make) -> None:
    with h5py.File(path, "a") as f:
        data = f[name][()]
        del f[name]
        make(f, name, data)


def _external_storage(world):
    def make(f, name, data):
        raw = world.victim / "q.bin"
        raw.write_bytes(np.ascontiguousarray(data).tobytes())  # the right bytes: following it would "work"
        f.create_dataset(name, shape=data.shape, dtype=data.dtype, external=[(str(raw), 0, data.nbytes)])
    return make


def _outside_h5(world, name, data) -> Path:
    """An HDF5 file outside the split holding the right data: following a reference to it would "work"."""
    src = world.victim / "src.h5"
    with h5py.File(src, "w") as g:
        g[name] = data
    return src


def _virtual(world):
    def make(f, name, data):
        layout = h5py.VirtualLayout(shape=data.shape, dtype=data.dtype)
        layout[...] = h5py.VirtualSource(str(_outside_h5(world, name, data)), name, shape=data.shape)
        f.create_virtual_dataset(name, layout)
    return make


def _external_link(world):
    def make(f, name, data):
        f[name] = h5py.ExternalLink(str(_outside_h5(world, name, data)), "/" + name)
    return make


def _soft_loop(world):
    def make(f, name, data):
        f[name] = h5py.SoftLink("/" + name)
    return make


def _soft_alias(world):
    def make(f, name, data):
        f[name + "_real"] = data
        f[name] = h5py.SoftLink("/" + name + "_real")
    return make


def _deep_groups(world):
    def make(f, name, data):
        f[name] = data
        f.create_group("a/b/c/d/e/f")
    return make


H5_LAYOUTS = {"external-storage": (_external_storage, "external storage"), "virtual": (_virtual, "virtual dataset"),
              "external-link": (_external_link, "external link"), "soft-loop": (_soft_loop, "soft link"),
              "soft-alias": (_soft_alias, "soft link"), "deep-groups": (_deep_groups, "nested deeper")}


@pytest.mark.parametrize("cmd", READERS)
@pytest.mark.parametrize("layout", list(H5_LAYOUTS))
def test_hdf5_layouts_reading_elsewhere_are_refused(base, world, cmd, layout):
    split = _copy_split(base, world)
    maker, needle = H5_LAYOUTS[layout]
    _replace_dataset(split / "shard-00001.h5", "q", maker(world))
    world.freeze()
    line = assert_refused(_read_cmd(cmd, split, world), needle)
    assert "shard-00001.h5" in line
    world.assert_untouched()


#: Images a hostile shard declares without storing them (unwritten chunks read as zeros).
DECLARED_IMAGES = 10**8


@pytest.mark.parametrize("cmd", READERS)
def test_declared_but_unstored_images_are_refused(base, world, cmd):
    """A tiny shard declaring 10^8 images (terabytes of zeros once read): refused before any read."""
    split = _copy_split(base, world)
    with h5py.File(split / "shard-00001.h5", "a") as f:
        for name in [n for n in f if n not in ("K", "R")]:
            shape, dtype = f[name].shape, f[name].dtype
            del f[name]
            f.create_dataset(name, shape=(DECLARED_IMAGES,) + shape[1:], dtype=dtype, chunks=(1,) + shape[1:],
                             compression="gzip")
    world.freeze()
    assert_refused(_read_cmd(cmd, split, world), f"declares {DECLARED_IMAGES} images")
    world.assert_untouched()


@pytest.mark.parametrize("layout", list(H5_LAYOUTS))
def test_verify_reports_hdf5_layouts(base, world, layout):
    """verify reports the layout as a problem of the shard (exit 1) and reads nothing elsewhere."""
    split = _copy_split(base, world)
    maker, needle = H5_LAYOUTS[layout]
    _replace_dataset(split / "shard-00001.h5", "q", maker(world))
    world.freeze()
    result = run("verify", split, "-q")
    assert result.exit_code == 1 and "Traceback" not in result.output, result.output
    assert any(ln.strip().startswith("shard-00001.h5:") and needle in ln for ln in message_lines(result)), result.output
    world.assert_untouched()


def _corrupt_chunk(path: Path, name: str) -> None:
    """Overwrite the compressed bytes of the dataset's first chunk (the HDF5 structure stays valid)."""
    with h5py.File(path, "r") as f:
        info = f[name].id.get_chunk_info(0)
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset)
        fh.write(bytes(range(256)) * (info.size // 256) + b"\xff" * (info.size % 256))


@pytest.mark.parametrize("cmd", READERS)
@pytest.mark.parametrize("name", ["q", "depth", "visible_pixels"])
def test_corrupt_chunk_is_one_line_pointing_to_verify(base, world, cmd, name):
    split = _copy_split(base, world)
    _corrupt_chunk(split / "shard-00000.h5", name)
    world.freeze()
    result = _read_cmd(cmd, split, world)
    if cmd == "info" and name == "depth":  # info reads labels only: nothing damaged is read
        assert result.exit_code == 0, result.output
        return
    line = assert_refused(result, "artdata verify")
    assert "shard-00000.h5" in line
    world.assert_untouched()


@pytest.mark.parametrize("cmd", ["score", "baseline-mean", "baseline-nn", "verify"])
def test_corrupt_chunk_in_other_readers(base, world, cmd):
    split = _copy_split(base, world)
    for name in ("q", "depth"):
        _corrupt_chunk(split / "shard-00001.h5", name)
    world.freeze()
    if cmd == "score":
        result = run("score", base["predictions"], "--truth", split)
    elif cmd == "verify":  # verify reports the damage as a problem (exit 1), never a traceback
        result = run("verify", split, "-q")
        assert result.exit_code == 1 and "shard-00001.h5" in result.output and "Traceback" not in result.output
        return
    else:
        method = cmd.split("-")[1]
        result = run("baseline", method, "--train", split, "--test", split, "--out", world.root / "p.h5", "-q")
    line = assert_refused(result, "artdata verify")
    assert "shard-00001.h5" in line
    world.assert_untouched()


@pytest.mark.parametrize("damage", ["corrupt", "external"])
def test_loader_reports_damaged_shards(base, world, damage):
    from articulated_dataset.training.loaders.reader import ShardReader

    split = _copy_split(base, world)
    if damage == "corrupt":
        _corrupt_chunk(split / "shard-00000.h5", "depth")
    else:
        _replace_dataset(split / "shard-00000.h5", "q", _external_storage(world))
    with pytest.raises(DataFormatError, match="shard-00000.h5") as exc:
        ShardReader(split).get_batch([0, 1])
    assert "\n" not in str(exc.value)


# --------------------------------------------------------------------------------------
# 4. resolve_inside, the central check
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["../x", "a/../../x", "/etc/passwd", "", ".", "..", "a/./b", "a//b", "a\0b", None, 3])
def test_resolve_inside_refuses_non_names(tmp_path, name):
    with pytest.raises(DataFormatError):
        resolve_inside(tmp_path, name)


def test_resolve_inside_follows_links(tmp_path):
    (tmp_path / "root").mkdir()
    (tmp_path / "root" / "out").symlink_to(tmp_path)
    (tmp_path / "root" / "loop").symlink_to(tmp_path / "root" / "loop")
    for name in ("out", "out/x", "loop/x"):
        with pytest.raises(DataFormatError):
            resolve_inside(tmp_path / "root", name)
    assert resolve_inside(tmp_path / "root", "a/shard-00000.h5") == tmp_path / "root" / "a" / "shard-00000.h5"


# --------------------------------------------------------------------------------------
# 5. third-party URDFs: never evaluated, meshes only from the URDF's folder, sane numbers
# --------------------------------------------------------------------------------------

def _payloads(pwned: Path) -> dict[str, str]:
    """Strings that create ``pwned`` if xacro (or Python) ever evaluates them."""
    return {
        # the issue's payload: xacro's dunder check does not look inside comprehensions
        "comprehension": ("${[c.__init__.__globals__['system']('touch " + str(pwned) + "') for x in [1] "
                          "for c in x.__class__.__base__.__subclasses__() if c.__name__ == '_wrap_close']}"),
        "eval": "$(eval __import__('os').system('touch " + str(pwned) + "'))",
        "import": "${__import__('os').system('touch " + str(pwned) + "')}",
    }


OBJ_D = 0.4  # m: body cube side of the test object


def _urdf_folder(world) -> Path:
    folder = world.root / "obj"
    folder.mkdir()
    body = trimesh.creation.box(extents=[OBJ_D] * 3)
    body.apply_translation([0, 0, OBJ_D / 2])
    body.export(str(folder / "body.obj"))
    door = trimesh.creation.box(extents=[0.02, OBJ_D, OBJ_D])
    door.apply_translation([-0.01, -OBJ_D / 2, OBJ_D / 2])
    door.export(str(folder / "door.obj"))
    return folder


def _urdf(robot="obj", base="base", door="door", joint="hinge", parent=None, child=None, body_mesh="body.obj",
          door_geom='<mesh filename="door.obj"/>', joint_type="revolute", limit='lower="0" upper="1.5"',
          origin='xyz="-0.2 0.2 0"', axis="0 0 -1", extra_link="", visual_name="", material="", mimic="",
          door_origin="") -> str:
    parent = base if parent is None else parent
    child = door if child is None else child
    limit_xml = f"<limit {limit} effort=\"1\" velocity=\"1\"/>" if limit is not None else ""
    return (f'<?xml version="1.0"?>\n<robot name="{robot}">'
            f'<link name="{base}"><visual{visual_name}><geometry><mesh filename="{body_mesh}"/></geometry>{material}'
            f'</visual></link>'
            f'<link name="{door}"><visual>{door_origin}<geometry>{door_geom}</geometry></visual></link>{extra_link}'
            f'<joint name="{joint}" type="{joint_type}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin {origin}/><axis xyz="{axis}"/>{limit_xml}{mimic}</joint></robot>\n')


def _generate_urdf(world, text: str, *extra, name="obj.urdf"):
    folder = world.root / "obj" if (world.root / "obj").is_dir() else _urdf_folder(world)
    path = folder / name
    path.write_text(text, encoding="utf-8")
    world.freeze()
    return run("generate", "--urdf", path, "--n", 1, "--images", 1, "--out", world.root / "out", "-q", *extra)


@pytest.fixture
def urdf_world(world, monkeypatch):
    monkeypatch.setenv(urdf_import.CACHE_ENV, str(world.root / "cache"))
    return world


@pytest.mark.slow
def test_the_test_object_generates(urdf_world):
    """Control: the unmodified object generates, so each refusal below is caused by its change."""
    result = _generate_urdf(urdf_world, _urdf())
    assert result.exit_code == 0, result.output
    assert (urdf_world.root / "out" / "obj-obj" / "train" / MANIFEST_NAME).is_file()


NAME_FIELDS = ["joint", "base", "door", "parent", "child"]


@pytest.mark.parametrize("field", NAME_FIELDS)
@pytest.mark.parametrize("payload", ["comprehension", "eval", "import"])
def test_injection_in_names_is_refused_never_run(urdf_world, field, payload):
    text = _payloads(urdf_world.root / PWNED)[payload].replace('"', "&quot;")
    assert_refused(_generate_urdf(urdf_world, _urdf(**{field: text})))
    urdf_world.assert_untouched()


@pytest.mark.parametrize("field, extra", [("body_mesh", ["--skip-missing-meshes"]), ("robot", []), ("material", []),
                                          ("visual_name", [])])
def test_injection_where_names_are_not_used_stays_inert(urdf_world, field, extra):
    """Text that never becomes a name is carried as data: the object generates, nothing runs."""
    text = _payloads(urdf_world.root / PWNED)["comprehension"].replace('"', "&quot;")
    value = {"material": f'<material name="{text}"/>', "visual_name": f' name="{text}"'}.get(field, text)
    result = _generate_urdf(urdf_world, _urdf(**{field: value}), *extra)
    if field == "body_mesh":  # the body has no geometry left: refused, nothing ran
        assert_refused(result, "no geometry")
    else:
        assert result.exit_code == 0, result.output
    assert not list(urdf_world.root.rglob(PWNED))


BAD_NAMES = {"space": "a b", "quote": "a&quot;b", "newline": "a&#10;b", "brace": "a{b}", "dollar": "a$b",
             "unicode": "门", "long": "j" * 200, "dot-start": ".j", "dash-start": "-j", "backtick": "a`b`"}


@pytest.mark.parametrize("field", ["joint", "door"])
@pytest.mark.parametrize("bad", list(BAD_NAMES))
def test_names_must_be_identifiers(urdf_world, field, bad):
    assert_refused(_generate_urdf(urdf_world, _urdf(**{field: BAD_NAMES[bad]})), "name")
    urdf_world.assert_untouched()


def test_plain_urdf_is_never_expanded(tmp_path):
    """The templating stage returns a plain URDF as it is: nothing in it is evaluated."""
    text = _urdf(joint=_payloads(tmp_path / PWNED)["comprehension"].replace('"', "&quot;"))
    (tmp_path / "model.urdf").write_text(text)
    assert render_urdf(tmp_path / "model.urdf", {"x": "1"}) == text
    assert not (tmp_path / PWNED).exists()


XML_ATTACKS = {
    "xxe-file": ('<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY x SYSTEM "file://{victim}/canary.txt">]>\n', "&x;"),
    "entity-bomb": ('<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;">]>\n',
                    "&b;"),
    "xxe-param": ('<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY % p SYSTEM "file://{victim}/canary.txt"> %p;]>\n',
                  "hinge"),
}


@pytest.mark.parametrize("attack", list(XML_ATTACKS))
def test_xml_entities_are_refused(urdf_world, attack):
    head, name = XML_ATTACKS[attack]
    body = _urdf(joint=name).split("\n", 1)[1]
    result = _generate_urdf(urdf_world, head.format(victim=urdf_world.victim) + body)
    assert_refused(result)
    urdf_world.assert_untouched()


def test_xinclude_is_not_processed(urdf_world):
    """An XInclude element is an unknown element, never followed: the joint it would bring is missing."""
    text = _urdf().replace("<joint ", '<xi:include xmlns:xi="http://www.w3.org/2001/XInclude" href="joint.xml"/><j ')
    text = text.replace("</joint>", "</j>")
    assert_refused(_generate_urdf(urdf_world, text))
    urdf_world.assert_untouched()


def _mesh_outside(world) -> Path:
    world.victim.mkdir(exist_ok=True)
    m = trimesh.creation.box(extents=[0.02, OBJ_D, OBJ_D])
    m.apply_translation([-0.01, -OBJ_D / 2, OBJ_D / 2])
    m.export(str(world.victim / "door.obj"))
    return world.victim / "door.obj"


MESH_REFS = ["../victim/door.obj", "{abs}", "file://{abs}", "package://../victim/door.obj", "link.obj",
             "sub/../../victim/door.obj"]


@pytest.mark.parametrize("ref", MESH_REFS)
def test_meshes_only_from_the_urdf_folder(urdf_world, ref):
    outside = _mesh_outside(urdf_world)
    folder = _urdf_folder(urdf_world)
    (folder / "link.obj").symlink_to(outside)
    (folder / "sub").mkdir()
    ref = ref.replace("{abs}", str(outside))
    assert_refused(_generate_urdf(urdf_world, _urdf(door_geom=f'<mesh filename="{ref}"/>')), "lies outside")
    urdf_world.assert_untouched()


def test_mesh_root_allows_a_named_folder(urdf_world):
    _mesh_outside(urdf_world)
    result = _generate_urdf(urdf_world, _urdf(door_geom='<mesh filename="../victim/door.obj"/>'),
                            "--mesh-root", urdf_world.root)
    assert result.exit_code == 0, result.output


ABSURD = {
    "mesh-scale-zero": dict(door_geom='<mesh filename="door.obj" scale="0 0 0"/>'),
    "mesh-scale-one-zero": dict(door_geom='<mesh filename="door.obj" scale="1 0 1"/>'),
    "mesh-scale-nan": dict(door_geom='<mesh filename="door.obj" scale="nan nan nan"/>'),
    "mesh-scale-inf": dict(door_geom='<mesh filename="door.obj" scale="1 inf 1"/>'),
    "box-negative": dict(door_geom='<box size="-0.02 0.4 0.4"/>'),
    "box-zero": dict(door_geom='<box size="0 0.4 0.4"/>'),
    "box-nan": dict(door_geom='<box size="nan 0.4 0.4"/>'),
    "box-overflow": dict(door_geom='<box size="1e400 0.4 0.4"/>'),
    "cylinder-negative": dict(door_geom='<cylinder radius="-0.1" length="0.4"/>'),
    "cylinder-zero-length": dict(door_geom='<cylinder radius="0.1" length="0"/>'),
    "sphere-negative": dict(door_geom='<sphere radius="-0.1"/>'),
    "joint-origin-nan": dict(origin='xyz="nan 0.2 0"'),
    "joint-origin-overflow": dict(origin='xyz="1e400 0.2 0"'),
    "joint-rpy-nan": dict(origin='xyz="-0.2 0.2 0" rpy="nan 0 0"'),
    "visual-origin-nan": dict(door_origin='<origin xyz="0 nan 0"/>'),
    "limit-1e30": dict(limit='lower="0" upper="1e30"'),
    "limit-minus-1e30": dict(limit='lower="-1e30" upper="0"'),
    "limit-nan": dict(limit='lower="0" upper="nan"'),
    "limit-inf": dict(limit='lower="0" upper="inf"'),
    "prismatic-1e30": dict(joint_type="prismatic", axis="-1 0 0", limit='lower="0" upper="1e30"'),
    "prismatic-100m": dict(joint_type="prismatic", axis="-1 0 0", limit='lower="0" upper="100"'),
    "axis-zero": dict(axis="0 0 0"),
    "axis-nan": dict(axis="nan 0 1"),
    "object-too-big": dict(door_geom='<box size="0.02 400 400"/>'),
    "empty-range": dict(limit='lower="1" upper="1"'),
    "no-limit": dict(limit=None),
}


@pytest.mark.parametrize("case", list(ABSURD))
def test_absurd_numbers_are_one_line(urdf_world, case):
    extra = ["--joints", "hinge"] if case in ("empty-range",) else []
    assert_refused(_generate_urdf(urdf_world, _urdf(**ABSURD[case]), *extra))
    urdf_world.assert_untouched()


@pytest.mark.parametrize("scale", ["0", "-1", "nan", "inf", "1e6", "1e-6", "abc"])
def test_bad_scale(urdf_world, scale):
    assert_refused(_generate_urdf(urdf_world, _urdf(), "--scale", scale))
    urdf_world.assert_untouched()


def _mesh_file(world, name: str, content: bytes | None = None, mesh=None) -> str:
    folder = world.root / "obj" if (world.root / "obj").is_dir() else _urdf_folder(world)
    if mesh is not None:
        mesh.export(str(folder / name))
    else:
        (folder / name).write_bytes(content)
    return name


def _many_faces() -> trimesh.Trimesh:
    """A mesh of 110,000 triangles (220,000 once double-sided): over MuJoCo's STL limit."""
    n = 110_000
    rng = np.random.default_rng(0)
    v = rng.uniform(-0.2, 0.2, (3 * n, 3)) + [0, 0, 0.2]
    return trimesh.Trimesh(v, np.arange(3 * n).reshape(n, 3), process=False)


MESH_FILES = {
    "nan-vertex": (b"v nan 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n", None, "not finite"),
    "no-triangles": (b"v 0 0 0\nv 1 0 0\n", None, "no triangles"),
    "garbage": (bytes(range(256)) * 4, None, "mesh file"),
    "too-many-faces": (None, _many_faces, "MuJoCo"),
}


@pytest.mark.parametrize("case", list(MESH_FILES))
def test_bad_meshes(urdf_world, case):
    content, make, needle = MESH_FILES[case]
    suffix = ".stl" if make else ".obj"
    name = _mesh_file(urdf_world, "bad" + suffix, content, make() if make else None)
    assert_refused(_generate_urdf(urdf_world, _urdf(door_geom=f'<mesh filename="{name}"/>')), needle)
    urdf_world.assert_untouched()


@pytest.mark.parametrize("buffer", ["fifo", "directory"])
def test_a_mesh_buffer_that_is_not_a_regular_file(urdf_world, buffer):
    """A glTF inside the URDF's folder naming a FIFO as its buffer is refused, not read forever
    (the mesh file itself and the files it names must be regular files)."""
    import threading

    folder = _urdf_folder(urdf_world)
    door = trimesh.creation.box(extents=[0.02, OBJ_D, OBJ_D])
    door.apply_translation([-0.01, -OBJ_D / 2, OBJ_D / 2])
    gltf = json.loads(trimesh.exchange.gltf.export_gltf(trimesh.Scene(door))["model.gltf"])
    gltf["buffers"][0]["uri"] = "door.bin"
    (folder / "door.gltf").write_text(json.dumps(gltf))
    if buffer == "fifo":
        os.mkfifo(folder / "door.bin")
    else:
        (folder / "door.bin").mkdir()
    result = []
    worker = threading.Thread(target=lambda: result.append(
        _generate_urdf(urdf_world, _urdf(door_geom='<mesh filename="door.gltf"/>'))), daemon=True)
    worker.start()
    worker.join(60)
    if worker.is_alive():  # unblock the reader so the test process can end
        with open(folder / "door.bin", "wb"):
            pass
        worker.join(10)
        pytest.fail("reading the mesh's buffer blocked")
    assert_refused(result[0], "door.gltf")
    urdf_world.assert_untouched()


@pytest.mark.parametrize("class_name", ["../x", "/tmp/x", "..", ".x", "-x", "a/b", "x" * 40, "${1}"])
def test_class_name_option_is_a_name(urdf_world, class_name):
    assert_refused(_generate_urdf(urdf_world, _urdf(), "--class-name", class_name), "class name")
    urdf_world.assert_untouched()


def test_continuous_joints_are_not_chosen_by_default(urdf_world):
    line = assert_refused(_generate_urdf(urdf_world, _urdf(joint_type="continuous", limit=None)))
    assert "--joints" in line
    urdf_world.assert_untouched()


def test_not_a_robot(urdf_world):
    assert_refused(_generate_urdf(urdf_world, '<?xml version="1.0"?>\n<mujoco><include file="/etc/passwd"/></mujoco>\n'),
                   "not a URDF")


# --------------------------------------------------------------------------------------
# 6. rebuilding a stored third-party object reads the definition back safely
# --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def urdf_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile-urdf")
    old = os.environ.get(urdf_import.CACHE_ENV)
    os.environ[urdf_import.CACHE_ENV] = str(root / "cache")
    world = World(root / "w")
    folder = _urdf_folder(world)
    (folder / "obj.urdf").write_text(_urdf())
    obj = urdf_import.import_urdf(folder / "obj.urdf", class_name="hostile")
    split = generate_split(GenerationConfig("hostile", n_objects=1, images_per_object=1, third_party=obj.definition),
                           root / "data")
    yield {"split": split, "folder": folder}
    if old is None:
        os.environ.pop(urdf_import.CACHE_ENV, None)
    else:
        os.environ[urdf_import.CACHE_ENV] = old


def _source_sha256(urdf: Path, meshes=("body.obj", "door.obj")) -> str:
    """The sha256 a definition records (urdf_import.parse.source_digest), computed independently."""
    import hashlib

    h = hashlib.sha256(urdf.read_bytes())
    for name in sorted(meshes):
        h.update(name.encode())
        h.update((urdf.parent / name).read_bytes())
    return h.hexdigest()


def _definition_edit(key, value, folder: Path, pwned: Path):
    def edit(m):
        d = m["config"]["third_party"]
        if key == "urdf-payload":  # an injected joint name in the URDF the definition names, with its true sha256
            payload = _payloads(pwned)["comprehension"]
            (folder / "evil.urdf").write_text(_urdf(joint=payload.replace('"', "&quot;")))
            d["urdf"], d["joints"], d["sha256"] = str(folder / "evil.urdf"), [payload], _source_sha256(folder / "evil.urdf")
        else:
            d[key] = value
    return edit


DEFINITION_CASES = [("urdf-payload", None), ("class_name", "../../x"), ("urdf", "relative.urdf"),
                    ("sha256", "0" * 64), ("sha256", "x"), ("scale", -1), ("mesh_root", "rel"), ("camera", "wide"),
                    ("joints", "hinge"), ("unknown_key", 1)]


@pytest.mark.parametrize("how", ["show-rgb", "plan-simulate"])
@pytest.mark.parametrize("key, value", DEFINITION_CASES, ids=[f"{k}-{i}" for i, (k, _) in enumerate(DEFINITION_CASES)])
def test_rebuild_reads_the_definition_safely(urdf_split, tmp_path, how, key, value):
    world = World(tmp_path)
    split = world.root / "data" / "hostile" / "train"
    shutil.copytree(urdf_split["split"], split)
    _edit_json(split / MANIFEST_NAME, _definition_edit(key, value, urdf_split["folder"], world.root / PWNED))
    world.freeze()
    if how == "show-rgb":
        result = run("show", split, "--rgb", "--n", 1, "--out", world.root / "out.png", "-q")
    else:
        result = run("plan", split, "--index", 0, "--simulate", "-q")
    assert_refused(result)
    world.assert_untouched()
    assert not (urdf_split["folder"] / PWNED).exists()


def test_rebuilt_definition_checked_by_the_library(urdf_split):
    from articulated_dataset.format import read_manifest

    cfg = read_manifest(urdf_split["split"])["config"]
    cfg["third_party"]["class_name"] = "../x"
    with pytest.raises(UserError, match="corrupt third-party URDF definition"):
        GenerationConfig.from_dict(cfg).obj_class  # noqa: B018 - the property reads and checks


# --------------------------------------------------------------------------------------
# 7. as a real process: nothing else reaches stderr (library logs, numpy warnings)
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("case", ["missing-mesh", "inf-origin"])  # a yourdfpy log line, numpy/trimesh warnings
def test_stderr_is_one_line_in_a_real_process(world, case):
    """CliRunner does not see what logging handlers and Python warnings write to the real
    stderr; a subprocess does."""
    import subprocess
    import sys

    _urdf_folder(world)
    text = {"missing-mesh": _urdf(door_geom='<mesh filename="nothere.obj"/>'),
            "inf-origin": _urdf(origin='xyz="1e400 0 0" rpy="1e400 0 0"')}[case]
    (world.root / "obj" / "obj.urdf").write_text(text)
    args = ["generate", "--urdf", str(world.root / "obj" / "obj.urdf"), "--n", "1", "--out", str(world.root / "out"), "-q"]
    env = {**os.environ, urdf_import.CACHE_ENV: str(world.root / "cache"), "PYTHONWARNINGS": "default"}
    world.freeze()
    proc = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", *args], capture_output=True, text=True,
                          env=env, timeout=120)
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2 and proc.stdout == "", proc.stderr
    assert len(lines) == 1 and lines[0].startswith("artdata: error: "), proc.stderr
    world.assert_untouched()
