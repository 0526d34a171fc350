"""Splits from strangers: nothing a manifest or a shard names is followed outside the split folder.

Every reader (``info``, ``export``, ``show``; the loaders; ``verify``) is given a crafted copy of a
small split and must end with exactly one line ``artdata: error: ...`` and exit code 2 (``verify``:
the problem reported, exit 1), leaving the whole test folder as it was: a ``victim/`` folder of
canary files beside the inputs is compared byte for byte before and after.  Where a name or a
link would lead to a valid file if it were followed (a valid shard placed where the name points),
following it would pass silently, so these tables fail on it.  Cases: class and shard names read
from manifests, shard links leading out, HDF5 layouts that read other files (external storage,
virtual datasets, external and soft links), shards declaring images they do not store, corrupt
chunks, and :func:`~articulated_dataset.format.resolve_inside`, the central check.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.format import MANIFEST_NAME, resolve_inside
from helpers_core import GuardedFolder, assert_one_line_error, edit_json, run_cli


def _copy_split(two_shard_split, guarded) -> Path:
    split = guarded.root / "data" / "drawer" / "train"
    shutil.copytree(two_shard_split["split"], split)
    return split


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


def _read_cmd(cmd: str, split: Path, guarded: GuardedFolder):
    if cmd == "info":
        return run_cli("info", split)
    if cmd == "export":
        return run_cli("export", split, guarded.root / "out", "--overwrite", "-q")
    return run_cli("show", split, "--out", guarded.root / "out" / "gallery.png", "-q")


@pytest.mark.parametrize("cmd", READERS)
@pytest.mark.parametrize("value", BAD_CLASS_NAMES, ids=CLASS_IDS)
def test_manifest_class_name_is_a_name(two_shard_split, guarded, cmd, value):
    split = _copy_split(two_shard_split, guarded)
    edit_json(split / MANIFEST_NAME, _set_class(value))
    guarded.freeze()
    assert_one_line_error(_read_cmd(cmd, split, guarded), "manifest.json")
    guarded.assert_untouched()


def _outside_shard(two_shard_split, guarded) -> Path:
    """A valid shard outside the split: a followed traversal would read it successfully."""
    target = guarded.victim / "shard-00000.h5"
    shutil.copy(two_shard_split["split"] / "shard-00000.h5", target)
    return target


SHARD_NAMES = ["../../../victim/shard-00000.h5", "{abs}", "shard-00000.h5/../../../../victim/shard-00000.h5",
               "sub/shard-00000.h5", "shard-0.h5", "x.h5", "", 7, None]
SHARD_IDS = ["up3", "absolute", "embedded-up", "subfolder", "short-number", "other-name", "empty", "int", "null"]


@pytest.mark.parametrize("cmd", READERS)
@pytest.mark.parametrize("value", SHARD_NAMES, ids=SHARD_IDS)
def test_manifest_shard_file_is_a_shard_name(two_shard_split, guarded, cmd, value):
    split = _copy_split(two_shard_split, guarded)
    outside = _outside_shard(two_shard_split, guarded)
    value = str(outside) if value == "{abs}" else value

    def edit(m):
        m["shards"][0]["file"] = value
    edit_json(split / MANIFEST_NAME, edit)
    guarded.freeze()
    assert_one_line_error(_read_cmd(cmd, split, guarded), "shard")
    guarded.assert_untouched()


@pytest.mark.parametrize("cmd", READERS)
def test_shard_symlink_leading_out_is_refused(two_shard_split, guarded, cmd):
    split = _copy_split(two_shard_split, guarded)
    outside = _outside_shard(two_shard_split, guarded)
    (split / "shard-00000.h5").unlink()
    (split / "shard-00000.h5").symlink_to(outside)
    guarded.freeze()
    assert_one_line_error(_read_cmd(cmd, split, guarded), "leads outside")
    guarded.assert_untouched()


@pytest.mark.parametrize("listed", [True, False], ids=["listed", "no-manifest"])
def test_verify_reports_a_shard_symlink_leading_out_without_reading_it(two_shard_split, guarded, listed):
    """verify followed the link: it hashed and read the file outside the split and said "OK"
    (every other reader refuses the split)."""
    split = _copy_split(two_shard_split, guarded)
    outside = _outside_shard(two_shard_split, guarded)
    (split / "shard-00000.h5").unlink()
    (split / "shard-00000.h5").symlink_to(outside)
    if not listed:
        (split / MANIFEST_NAME).unlink()
    guarded.freeze()
    result = run_cli("verify", split, "--workers", 1)
    assert result.exit_code == 1, result.output
    assert "leads outside" in result.output and "Traceback" not in result.output
    guarded.assert_untouched()


@pytest.mark.parametrize("value", BAD_CLASS_NAMES[:8], ids=CLASS_IDS[:8])
def test_loader_refuses_manifest_names(two_shard_split, guarded, value):
    from articulated_dataset.training.loaders.reader import ShardReader

    split = _copy_split(two_shard_split, guarded)
    edit_json(split / MANIFEST_NAME, _set_class(value))
    with pytest.raises(DataFormatError, match="invalid class name"):
        ShardReader(split)



# --------------------------------------------------------------------------------------
# 3. HDF5 layouts that read elsewhere, and damaged shards
# --------------------------------------------------------------------------------------

def _replace_dataset(path: Path, name: str, make) -> None:
    with h5py.File(path, "a") as f:
        data = f[name][()]
        del f[name]
        make(f, name, data)


def _external_storage(guarded):
    def make(f, name, data):
        raw = guarded.victim / "q.bin"
        raw.write_bytes(np.ascontiguousarray(data).tobytes())  # the right bytes: following it would "work"
        f.create_dataset(name, shape=data.shape, dtype=data.dtype, external=[(str(raw), 0, data.nbytes)])
    return make


def _outside_h5(guarded, name, data) -> Path:
    """An HDF5 file outside the split holding the right data: following a reference to it would "work"."""
    src = guarded.victim / "src.h5"
    with h5py.File(src, "w") as g:
        g[name] = data
    return src


def _virtual(guarded):
    def make(f, name, data):
        layout = h5py.VirtualLayout(shape=data.shape, dtype=data.dtype)
        layout[...] = h5py.VirtualSource(str(_outside_h5(guarded, name, data)), name, shape=data.shape)
        f.create_virtual_dataset(name, layout)
    return make


def _external_link(guarded):
    def make(f, name, data):
        f[name] = h5py.ExternalLink(str(_outside_h5(guarded, name, data)), "/" + name)
    return make


def _soft_loop(guarded):
    def make(f, name, data):
        f[name] = h5py.SoftLink("/" + name)
    return make


def _soft_alias(guarded):
    def make(f, name, data):
        f[name + "_real"] = data
        f[name] = h5py.SoftLink("/" + name + "_real")
    return make


def _deep_groups(guarded):
    def make(f, name, data):
        f[name] = data
        f.create_group("a/b/c/d/e/f")
    return make


H5_LAYOUTS = {"external-storage": (_external_storage, "external storage"), "virtual": (_virtual, "virtual dataset"),
              "external-link": (_external_link, "external link"), "soft-loop": (_soft_loop, "soft link"),
              "soft-alias": (_soft_alias, "soft link"), "deep-groups": (_deep_groups, "nested deeper")}


@pytest.mark.parametrize("cmd", READERS)
@pytest.mark.parametrize("layout", list(H5_LAYOUTS))
def test_hdf5_layouts_reading_elsewhere_are_refused(two_shard_split, guarded, cmd, layout):
    split = _copy_split(two_shard_split, guarded)
    maker, needle = H5_LAYOUTS[layout]
    _replace_dataset(split / "shard-00001.h5", "q", maker(guarded))
    guarded.freeze()
    line = assert_one_line_error(_read_cmd(cmd, split, guarded), needle)
    assert "shard-00001.h5" in line
    guarded.assert_untouched()


#: Images a crafted shard declares without storing them (unwritten chunks read as zeros).
DECLARED_IMAGES = 10**8


@pytest.mark.parametrize("cmd", READERS)
def test_declared_but_unstored_images_are_refused(two_shard_split, guarded, cmd):
    """A tiny shard declaring 10^8 images (terabytes of zeros once read): refused before any read."""
    split = _copy_split(two_shard_split, guarded)
    with h5py.File(split / "shard-00001.h5", "a") as f:
        for name in [n for n in f if n not in ("K", "R")]:
            shape, dtype = f[name].shape, f[name].dtype
            del f[name]
            f.create_dataset(name, shape=(DECLARED_IMAGES,) + shape[1:], dtype=dtype, chunks=(1,) + shape[1:],
                             compression="gzip")
    guarded.freeze()
    assert_one_line_error(_read_cmd(cmd, split, guarded), f"declares {DECLARED_IMAGES} images")
    guarded.assert_untouched()


@pytest.mark.parametrize("layout", list(H5_LAYOUTS))
def test_verify_reports_hdf5_layouts(two_shard_split, guarded, layout):
    """verify reports the layout as a problem of the shard (exit 1) and reads nothing elsewhere."""
    split = _copy_split(two_shard_split, guarded)
    maker, needle = H5_LAYOUTS[layout]
    _replace_dataset(split / "shard-00001.h5", "q", maker(guarded))
    guarded.freeze()
    result = run_cli("verify", split, "-q")
    assert result.exit_code == 1 and "Traceback" not in result.output, result.output
    assert any(ln.strip().startswith("shard-00001.h5:") and needle in ln for ln in result.output.splitlines()), result.output
    guarded.assert_untouched()


def _corrupt_chunk(path: Path, name: str) -> None:
    """Overwrite the compressed bytes of the dataset's first chunk (the HDF5 structure stays valid)."""
    with h5py.File(path, "r") as f:
        info = f[name].id.get_chunk_info(0)
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset)
        fh.write(bytes(range(256)) * (info.size // 256) + b"\xff" * (info.size % 256))


@pytest.mark.parametrize("cmd", READERS)
@pytest.mark.parametrize("name", ["q", "depth", "visible_pixels"])
def test_corrupt_chunk_is_one_line_pointing_to_verify(two_shard_split, guarded, cmd, name):
    split = _copy_split(two_shard_split, guarded)
    _corrupt_chunk(split / "shard-00000.h5", name)
    guarded.freeze()
    result = _read_cmd(cmd, split, guarded)
    if cmd == "info" and name == "depth":  # info reads labels only: nothing damaged is read
        assert result.exit_code == 0, result.output
        return
    line = assert_one_line_error(result, "artdata verify")
    assert "shard-00000.h5" in line
    guarded.assert_untouched()


@pytest.mark.parametrize("cmd", ["score", "baseline-mean", "baseline-nn", "verify"])
def test_corrupt_chunk_in_other_readers(two_shard_split, guarded, cmd):
    split = _copy_split(two_shard_split, guarded)
    for name in ("q", "depth"):
        _corrupt_chunk(split / "shard-00001.h5", name)
    guarded.freeze()
    if cmd == "score":
        result = run_cli("score", two_shard_split["predictions"], "--truth", split)
    elif cmd == "verify":  # verify reports the damage as a problem (exit 1), never a traceback
        result = run_cli("verify", split, "-q")
        assert result.exit_code == 1 and "shard-00001.h5" in result.output and "Traceback" not in result.output
        return
    else:
        method = cmd.split("-")[1]
        result = run_cli("baseline", method, "--train", split, "--test", split, "--out", guarded.root / "p.h5", "-q")
    line = assert_one_line_error(result, "artdata verify")
    assert "shard-00001.h5" in line
    guarded.assert_untouched()


@pytest.mark.parametrize("damage", ["corrupt", "external"])
def test_loader_reports_damaged_shards(two_shard_split, guarded, damage):
    from articulated_dataset.training.loaders.reader import ShardReader

    split = _copy_split(two_shard_split, guarded)
    if damage == "corrupt":
        _corrupt_chunk(split / "shard-00000.h5", "depth")
    else:
        _replace_dataset(split / "shard-00000.h5", "q", _external_storage(guarded))
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
# 5. manifests and shard attributes that no reader should trust: nested past the recursion
#    limit, a shard listed twice, counts beyond a float, a completeness flag that is no boolean
# --------------------------------------------------------------------------------------

#: Nesting far past Python's recursion limit (the JSON parser recurses once per level).
DEEP = 100_000


def test_json_nested_past_the_recursion_limit(split_copy):
    split = split_copy()
    manifest = json.loads((split / "manifest.json").read_text())
    text = json.dumps({**manifest, "zz": []})
    (split / "manifest.json").write_text(text.replace('"zz": []', '"zz": ' + "[" * DEEP + "]" * DEEP))
    assert_one_line_error(run_cli("info", split))
    assert_one_line_error(run_cli("show", split, "--out", split.parent / "g.png"))
    result = run_cli("verify", split)
    assert result.exit_code != 0 and "Traceback" not in result.output and "corrupt JSON" in result.output, result.output


def test_a_shard_attribute_nested_past_the_recursion_limit(split_copy):
    split = split_copy()
    shard = next(split.glob("shard-*.h5"))
    with h5py.File(shard, "r+") as f:
        f.attrs["joint_types"] = "[" * DEEP + "]" * DEEP
    result = run_cli("info", split)  # the summary leaves the joints out (not a RecursionError)
    assert result.exit_code in (0, 2) and "Traceback" not in result.output and "RecursionError" not in result.output
    result = run_cli("verify", split)
    assert result.exit_code != 0 and "Traceback" not in result.output and "joint_types" in result.output, result.output


def test_a_manifest_listing_a_shard_twice_is_refused_by_the_readers(split_copy):
    from articulated_dataset.training.loaders.reader import ShardReader

    split = split_copy()
    edit_json(split / "manifest.json", lambda m: m["shards"].append(dict(m["shards"][0])))
    with pytest.raises(UserError, match="listed twice"):
        ShardReader(split)  # serving the shard's images twice
    assert_one_line_error(run_cli("info", split), "listed twice")


@pytest.mark.parametrize("edit", ["bytes", "n_images", "width_px"])
def test_info_on_counts_beyond_a_float_is_one_line(split_copy, edit):
    """info divides a byte count by the image count: 10**400 is refused, not an OverflowError."""
    split = split_copy()
    m = json.loads((split / "manifest.json").read_text())
    target = {"bytes": m["shards"][0], "n_images": m, "width_px": m["config"]["camera"]}[edit]
    target[edit] = 10**400
    (split / "manifest.json").write_text(json.dumps(m))
    assert_one_line_error(run_cli("info", split))


@pytest.mark.parametrize("value", ["no", 0, None, [False]])
def test_a_manifest_complete_flag_that_is_not_a_boolean_is_refused(split_copy, value):
    """'complete': "no" must not read as complete (bool("no") is true) in info and every reader."""
    split = split_copy()
    edit_json(split / "manifest.json", lambda m: m.update(complete=value))
    assert_one_line_error(run_cli("info", split), "field 'complete'")
