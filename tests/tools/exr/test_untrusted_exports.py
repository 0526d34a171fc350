"""EXR exports from strangers, and what ``export`` and ``import-exr`` may replace.

``import-exr`` reads names (class, shard files, image stems) from ``split.json`` and label files:
none may lead outside the export or the output folder, the index's content is checked before
anything is decoded, and an image's size is checked from its header.  ``export`` and
``import-exr --overwrite`` replace only folders they wrote themselves, never write two sources
into one target, and refuse image indices that would overwrite each other's files.  Every refusal
is one line ``artdata: error: ...`` with exit code 2 and leaves the whole test folder (a
``victim/`` folder of canary files beside the inputs) as it was.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from articulated_dataset.core.images.exr import INDEX_NAME
from articulated_dataset.format import MANIFEST_NAME
from helpers_core import assert_one_line_error, edit_json, run_cli


def _copy_split(two_shard_split, guarded) -> Path:
    split = guarded.root / "data" / "drawer" / "train"
    shutil.copytree(two_shard_split["split"], split)
    return split


def test_export_overwrite_never_deletes_outside(two_shard_split, guarded):
    """A class_name leading out of the output (../victim/x) with --overwrite neither deletes nor writes there."""
    split = _copy_split(two_shard_split, guarded)
    edit_json(split / MANIFEST_NAME, lambda m: m.update(class_name="../victim/x"))
    (guarded.root / "out").mkdir()
    guarded.freeze()
    assert_one_line_error(run_cli("export", split, guarded.root / "out", "--overwrite", "-q"))
    guarded.assert_untouched()


@pytest.mark.parametrize("cmd, marker", [("export", INDEX_NAME), ("import-exr", MANIFEST_NAME)])
def test_overwrite_replaces_only_our_own_folders(two_shard_split, guarded, cmd, marker):
    source = _copy_split(two_shard_split, guarded) if cmd == "export" else _copy_export(two_shard_split, guarded)
    target = guarded.root / "out" / "drawer" / "train"
    target.mkdir(parents=True)
    (target / "thesis.tex").write_text("mine")
    guarded.freeze()
    args = [source, guarded.root / "out"] if cmd == "export" else [source, "--out", guarded.root / "out"]
    assert_one_line_error(run_cli(cmd, *args, "--overwrite", "-q"), f"holds no {marker}")
    guarded.assert_untouched()


@pytest.mark.parametrize("cmd", ["export", "import-exr"])
@pytest.mark.parametrize("overwrite", [False, True], ids=["plain", "overwrite"])
def test_two_sources_with_one_target_are_refused_before_writing(two_shard_split, guarded, cmd, overwrite):
    """A copied class folder (its manifest still names drawer): both splits went to
    out/drawer/train, so the run failed after writing the first (a partial output) or, with
    --overwrite, replaced the first by the second and reported both as exported (exit 0)."""
    if cmd == "export":
        source = _copy_split(two_shard_split, guarded)
        shutil.copytree(source, guarded.root / "data" / "drawer_backup" / "train")
        args = [guarded.root / "data", guarded.root / "out"]
    else:
        source = _copy_export(two_shard_split, guarded)
        shutil.copytree(source, guarded.root / "exp" / "drawer_backup" / "train")
        args = [guarded.root / "exp", "--out", guarded.root / "out"]
    guarded.freeze()
    assert_one_line_error(run_cli(cmd, *args, "-q", *(["--overwrite"] if overwrite else [])), "both be written")
    guarded.assert_untouched()


@pytest.mark.parametrize("case", ["image-twice", "negative-image", "across-shards"])
def test_export_refuses_indices_that_would_overwrite_or_garble_files(two_shard_split, guarded, case):
    """Two images with one (object, image) index: the second overwrote the first's files and
    the export ended with exit 0, holding fewer images than split.json lists (import-exr then
    refused it); a negative index gave stems import-exr refuses."""
    import h5py

    split = _copy_split(two_shard_split, guarded)
    shard = split / ("shard-00001.h5" if case == "across-shards" else "shard-00000.h5")
    with h5py.File(shard, "r+") as f:
        if case == "across-shards":  # shard 1 claims object 0, as shard 0 does
            values, name = np.zeros_like(f["object_index"][:]), "object_index"
        else:
            values, name = np.array([0, 0] if case == "image-twice" else [-1, 1], f["image_index"].dtype), "image_index"
        del f[name]
        f.create_dataset(name, data=values)
    edit_json(split / MANIFEST_NAME, lambda m: m["shards"][int(case == "across-shards")].update(
        bytes=shard.stat().st_size, sha256=hashlib.sha256(shard.read_bytes()).hexdigest()))
    guarded.freeze()
    assert_one_line_error(run_cli("export", split, guarded.root / "out", "-q"), "artdata verify")
    guarded.assert_untouched()


def test_export_overwrite_swaps_in_a_complete_export(two_shard_split, guarded):
    split = _copy_split(two_shard_split, guarded)
    target = guarded.root / "out" / "drawer" / "train"
    assert run_cli("export", split, guarded.root / "out", "-q").exit_code == 0
    assert run_cli("export", split, guarded.root / "out", "--overwrite", "-q").exit_code == 0
    assert (target / INDEX_NAME).is_file() and not list(target.parent.glob(".*partial*"))



# --------------------------------------------------------------------------------------
# 2. import-exr: names in split.json and label files
# --------------------------------------------------------------------------------------

def _copy_export(two_shard_split, guarded) -> Path:
    exp = guarded.root / "exp" / "drawer" / "train"
    shutil.copytree(two_shard_split["export"], exp)
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
def test_import_exr_names_stay_inside(two_shard_split, guarded, kind, value, overwrite):
    exp = _copy_export(two_shard_split, guarded)
    # valid files where a followed traversal would land: an import would then succeed
    for suffix in (".exr", ".mask.png", ".json"):
        shutil.copy(exp / f"o000000_i000{suffix}", guarded.victim / f"o000000_i000{suffix}")
    value = {"{abs}": str(guarded.victim / "shard-00000.h5"),
             "{abs-stem}": str(guarded.victim / "o000000_i000")}.get(value, value) if isinstance(value, str) else value
    edit_json(exp / INDEX_NAME, _index_edit(kind, value))
    out = guarded.root / "out"
    if overwrite:  # an earlier import, which --overwrite may replace (and nothing else)
        (out / "drawer" / "train").mkdir(parents=True)
        (out / "drawer" / "train" / MANIFEST_NAME).write_text("{}")
    guarded.freeze()
    args = ["import-exr", exp, "--out", out, "-q"] + (["--overwrite"] if overwrite else [])
    assert_one_line_error(run_cli(*args), "split.json")
    guarded.assert_untouched()


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
def test_import_exr_index_content_is_checked(two_shard_split, guarded, case):
    """Malformed or inconsistent split.json content: one line, nothing written (not a traceback,
    a 10 PiB allocation or a silently wrong split)."""
    exp = _copy_export(two_shard_split, guarded)
    edit_json(exp / INDEX_NAME, INDEX_CONTENT[case])
    guarded.freeze()
    assert_one_line_error(run_cli("import-exr", exp, "--out", guarded.root / "out", "-q"))
    guarded.assert_untouched()


@pytest.mark.parametrize("value", [float("nan"), 100.0, -5.0])
def test_import_exr_label_values_are_verified(two_shard_split, guarded, value):
    exp = _copy_export(two_shard_split, guarded)
    edit_json(exp / "o000001_i001.json", lambda lab: lab.update(q=[value]))
    guarded.freeze()
    assert_one_line_error(run_cli("import-exr", exp, "--out", guarded.root / "out", "-q"), "fails verification")
    guarded.assert_untouched()


#: Side (px) a crafted image header claims (kept moderate: a reader that decodes it must not exhaust memory).
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
def test_import_exr_image_size_checked_before_decoding(two_shard_split, guarded, suffix, claim):
    exp = _copy_export(two_shard_split, guarded)
    claim(exp / f"o000001_i000{suffix}")
    guarded.freeze()
    assert_one_line_error(run_cli("import-exr", exp, "--out", guarded.root / "out", "-q"),
                   f"is {CLAIMED_SIDE_PX}x{CLAIMED_SIDE_PX} px, expected")
    guarded.assert_untouched()


@pytest.mark.parametrize("suffix", [".exr", ".mask.png", ".json"])
def test_import_exr_file_symlink_leading_out(two_shard_split, guarded, suffix):
    exp = _copy_export(two_shard_split, guarded)
    shutil.copy(exp / f"o000000_i000{suffix}", guarded.victim / f"o000000_i000{suffix}")
    (exp / f"o000000_i000{suffix}").unlink()
    (exp / f"o000000_i000{suffix}").symlink_to(guarded.victim / f"o000000_i000{suffix}")
    guarded.freeze()
    assert_one_line_error(run_cli("import-exr", exp, "--out", guarded.root / "out", "-q"), "leads outside")
    guarded.assert_untouched()


def test_import_exr_failure_keeps_the_previous_split(two_shard_split, guarded):
    """A failed --overwrite (damaged image found while reading) leaves the old split as it was."""
    exp = _copy_export(two_shard_split, guarded)
    out = guarded.root / "out"
    assert run_cli("import-exr", exp, "--out", out, "-q").exit_code == 0
    (exp / "o000001_i001.exr").write_bytes(b"garbage")
    guarded.freeze()
    assert_one_line_error(run_cli("import-exr", exp, "--out", out, "--overwrite", "-q"), "o000001_i001.exr")
    guarded.assert_untouched()


def test_import_exr_of_a_label_beyond_float32_is_one_line(split_copy, tmp_path):
    """A label of 1e300 is refused in one line, without numpy's overflow warning before it (a real
    process: CliRunner does not see warnings written to the real stderr)."""
    import subprocess
    import sys

    assert run_cli("export", split_copy(), tmp_path / "exp", "-q").exit_code == 0
    label = next((tmp_path / "exp").rglob("o000000_i000.json"))
    edit_json(label, lambda data: data.update(q=[1e300] * len(data["q"])))
    r = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", "import-exr", str(label.parent), "--out",
                        str(tmp_path / "back"), "-q"], capture_output=True, text=True, timeout=300)
    assert_one_line_error(r)
