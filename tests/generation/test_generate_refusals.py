"""``artdata generate`` against input no run can use, and faults, run as a user runs it (the CLI).

Every case must end with one line ``artdata: error: ...`` and exit code 2, and must leave
everything outside the folder it names as it was (canary files next to it); a refused run
changes nothing at all.  Cases: absurd options, bad sampling tables, output folders no run may write into
(files, symbolic links, foreign files, another run's lock, read-only filesystems), resumes
that would adopt other runs' shards, corrupt manifests, failed overwrites, a full disk.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.format import sha256_file
from helpers_core import assert_one_line_error
from helpers_core import tree_snapshot as snapshot

#: A split that renders in a fraction of a second: one 32x18 image per object.
TINY = ["--class", "drawer", "--images", "1", "--width", "32", "--height", "18", "--workers", "1", "--quiet"]
#: A table under which no pose shows the drawer (it sits 900 m to the side): the run fails
#: after its pose attempts, having written nothing.
INVISIBLE_TABLE = {"pose": {"y_m": [900.0, 1000.0]}}


def generate(*args):
    return CliRunner().invoke(main, ["generate", *map(str, args)])


@pytest.fixture
def sandbox(tmp_path):
    """``tmp_path`` with canary files beside the output folder ``tmp_path/out``."""
    (tmp_path / "canary.txt").write_text("do not touch\n")
    (tmp_path / "canaries").mkdir()
    (tmp_path / "canaries" / "keep.h5").write_bytes(b"user data")
    (tmp_path / "canaries" / "shard-00000.h5.partial").write_bytes(b"someone else's")
    return tmp_path


@pytest.fixture(scope="module")
def tiny_split(tmp_path_factory):
    """A complete tiny split (2 objects, one per shard) to copy into cases."""
    root = tmp_path_factory.mktemp("tiny")
    result = generate(*TINY, "--n", 2, "--objects-per-shard", 1, "--out", root)
    assert result.exit_code == 0, result.output
    return root / "drawer" / "train"


def copy_split(tiny_split, out: Path) -> Path:
    split = out / "drawer" / "train"
    split.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(tiny_split, split)
    return split


# --------------------------------------------------------------------------------------
# Absurd options: refused before anything is created
# --------------------------------------------------------------------------------------

ABSURD = {
    "n-zero": (["--n", "0"], "positive"),
    "n-negative": (["--n", "-1"], "positive"),
    "n-trillion": (["--n", "1000000000000"], "needs at least"),
    "n-not-int": (["--n", "abc"], "--n"),
    "images-zero": (["--n", "1", "--images", "0"], "positive"),
    "images-negative": (["--n", "1", "--images", "-4"], "positive"),
    "images-huge": (["--n", "1", "--images", "1000000000000"], "memory"),
    "objects-per-shard-zero": (["--n", "1", "--objects-per-shard", "0"], "positive"),
    "objects-per-shard-negative": (["--n", "1", "--objects-per-shard", "-2"], "positive"),
    "objects-per-shard-huge": (["--n", "100000000", "--objects-per-shard", "100000000"], "memory"),
    "width-zero": (["--n", "1", "--width", "0"], "positive"),
    "width-negative": (["--n", "1", "--width", "-32"], "positive"),
    "width-huge": (["--n", "1", "--width", "100000"], "--width"),
    "height-huge": (["--n", "1", "--height", "1000000000"], "--height"),
    "width-height-memory": (["--n", "64", "--images", "64", "--width", "16384", "--height", "16384"], "memory"),
    "vfov-zero": (["--n", "1", "--vfov", "0"], "field of view"),
    "vfov-180": (["--n", "1", "--vfov", "180"], "field of view"),
    "vfov-negative": (["--n", "1", "--vfov", "-5"], "field of view"),
    "vfov-nan": (["--n", "1", "--vfov", "nan"], "field of view"),
    "vfov-inf": (["--n", "1", "--vfov", "inf"], "field of view"),
    "seed-negative": (["--n", "1", "--seed", "-1"], "seed"),
    "seed-2**63": (["--n", "1", "--seed", str(2**63)], "seed"),
    "seed-2**64": (["--n", "1", "--seed", str(2**64)], "seed"),
    "seed-huge": (["--n", "1", "--seed", "1" + "0" * 40], "seed"),
    "seed-not-int": (["--n", "1", "--seed", "1.5"], "--seed"),
    "workers-zero": (["--n", "1", "--workers", "0"], "--workers"),
    "workers-negative": (["--n", "1", "--workers", "-3"], "--workers"),
    "workers-huge": (["--n", "100000", "--objects-per-shard", "1", "--workers", "100000"], "memory"),
    "mean-with-n": (["--mean", "--n", "2"], "--mean"),
    "mean-with-n-zero": (["--mean", "--n", "0"], "--mean"),
    "split-empty": (["--n", "1", "--split", ""], "split"),
    "split-traversal": (["--n", "1", "--split", "../../escape"], "split"),
    "split-hidden": (["--n", "1", "--split", ".hidden"], "split"),
    "split-nested": (["--n", "1", "--split", "a/b"], "split"),
    "resume-and-overwrite": (["--n", "1", "--resume", "--overwrite"], "mutually exclusive"),
    "noise-unknown": (["--n", "1", "--noise", "bogus"], "noise"),
    "executor-unknown": (["--n", "1", "--executor", "bogus"], "executor"),
    "address-without-ray": (["--n", "1", "--address", "auto"], "--address"),
    "joints-without-urdf": (["--n", "1", "--joints", "a,b"], "--joints"),
    "class-name-without-urdf": (["--n", "1", "--class-name", "x"], "--class-name"),
    "table-missing": (["--n", "1", "--table", "no-such-table.json"], "not found"),
}


@pytest.mark.parametrize("case", sorted(ABSURD))
def test_absurd_options_are_refused_and_create_nothing(sandbox, case):
    args, needle = ABSURD[case]
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, *args, "--out", sandbox / "out"), needle)
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("args, needle", [
    (["--class", "nope", "--n", "1"], "unknown object class"),
    (["--class", "Drawer", "--n", "1"], "did you mean 'drawer'"),
    (["--n", "1"], "--class"),
    (["--class", "drawer", "--urdf", "x.urdf", "--n", "1"], "either --class or --urdf"),
], ids=["class-unknown", "class-wrong-case", "class-missing", "class-and-urdf"])
def test_class_choice_errors(sandbox, args, needle):
    before = snapshot(sandbox)
    assert_one_line_error(generate(*args, "--quiet", "--out", sandbox / "out"), needle)
    assert snapshot(sandbox) == before


# --------------------------------------------------------------------------------------
# Sampling tables
# --------------------------------------------------------------------------------------

BAD_TABLES = {
    "geometry-list": ('{"geometry": [1, 2]}', "geometry"),
    "geometry-string": ('{"geometry": "big"}', "geometry"),
    "geometry-pair-of-strings": ('{"geometry": {"height_m": ["a", "b"]}}', "geometry.height_m"),
    "geometry-triple": ('{"geometry": {"height_m": [0.1, 0.2, 0.3]}}', "geometry.height_m"),
    "geometry-scalar": ('{"geometry": {"height_m": 0.2}}', "geometry.height_m"),
    "geometry-bool": ('{"geometry": {"height_m": [true, true]}}', "geometry.height_m"),
    "geometry-null": ('{"geometry": {"height_m": null}}', "geometry.height_m"),
    "height-1e308": ('{"geometry": {"height_m": [1e308, 1e308]}}', "geometry.height_m"),
    "height-1e-9": ('{"geometry": {"height_m": [1e-9, 1e-9]}}', "geometry.height_m"),
    "height-overflow": ('{"geometry": {"height_m": [1, 1e400]}}', "geometry.height_m"),
    "depth-negative": ('{"geometry": {"depth_m": [-0.5, 0.5]}}', "geometry.depth_m"),
    "width-zero": ('{"geometry": {"width_m": [0, 0.5]}}', "geometry.width_m"),
    "width-reversed": ('{"geometry": {"width_m": [0.9, 0.5]}}', "geometry.width_m"),
    "geometry-unknown-key": ('{"geometry": {"length_m": [1, 2]}}', "length_m"),
    "pose-unknown-key": ('{"pose": {"roll_rad": [0, 1]}}', "roll_rad"),
    "pose-far": ('{"pose": {"x_m": [1e9, 1e9]}}', "pose.x_m"),
    "yaw-huge": ('{"pose": {"yaw_rad": [0, 1e6]}}', "pose.yaw_rad"),
    "q-scalar": ('{"q": 5}', "q"),
    "q-string": ('{"q": "open"}', "q"),
    "q-wrong-count": ('{"q": [[0, 0.1], [0, 0.1]]}', "q needs"),
    "q-negative": ('{"q": [[-0.1, 0.2]]}', "q[0]"),
    "q-huge": ('{"q": [[0, 1e30]]}', "q[0]"),
    "q-pair-of-lists": ('{"q": [[[0], [1]]]}', "q[0]"),
    "chirality-string": ('{"chirality_p": "abc"}', "chirality_p"),
    "chirality-above-one": ('{"chirality_p": 1.5}', "chirality_p"),
    "chirality-list": ('{"chirality_p": [0.5]}', "chirality_p"),
    "extra-unknown-key": ('{"extra": {"handle_m": 0.1}}', "extra.handle_m"),
    "extra-not-a-table": ('{"extra": [1]}', "extra"),
    "top-unknown-key": ('{"colour": "red"}', "colour"),
    "top-list": ("[1, 2]", "one table"),
    "top-number": ("3", "one table"),
    "nan-literal": ('{"chirality_p": NaN}', "NaN"),
    "infinity-literal": ('{"geometry": {"height_m": [0.1, Infinity]}}', "Infinity"),
    "not-json": ("{geometry: ", "cannot parse"),
    "empty-file": ("", "cannot parse"),
    "deeply-nested": ("[" * 100000 + "]" * 100000, "sampling table"),
    # integers beyond a float (JSON and TOML read them exactly): float() overflowed (a traceback)
    "integer-beyond-float": ('{"chirality_p": 1%s}' % ("0" * 400), "chirality_p"),
    "range-integer-beyond-float": ('{"pose": {"x_m": [1, 1%s]}}' % ("0" * 400), "pose.x_m"),
}


@pytest.mark.parametrize("case", sorted(BAD_TABLES))
def test_bad_tables_name_the_key(sandbox, case):
    text, needle = BAD_TABLES[case]
    table = sandbox / "canaries" / "table.json"
    table.write_text(text)
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--table", table, "--out", sandbox / "out"), needle)
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("name, data, needle", [
    ("latin1.json", b'{"geometry": {"height_m": [0.1, 0.2]}, "note": "\xe9"}', "UTF-8"),
    ("utf16.json", '{"chirality_p": 0.5}'.encode("utf-16"), "UTF-8"),
    ("binary.json", bytes(range(256)), "UTF-8"),
    ("bad.toml", b"geometry = [1, 2", "cannot parse"),
    ("types.toml", b'chirality_p = "abc"\n', "chirality_p"),
    ("nan.toml", b"chirality_p = nan\n", "chirality_p"),
    ("huge.json", b" " * (2 << 20) + b"{}", "larger than"),
], ids=lambda v: v if isinstance(v, str) and v.endswith(("json", "toml")) else "")
def test_unreadable_table_files(sandbox, name, data, needle):
    table = sandbox / "canaries" / name
    table.write_bytes(data)
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--table", table, "--out", sandbox / "out"), needle)
    assert snapshot(sandbox) == before


def test_table_given_as_a_folder(sandbox):
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--table", sandbox / "canaries", "--out", sandbox / "out"))
    assert snapshot(sandbox) == before


# --------------------------------------------------------------------------------------
# Output folders
# --------------------------------------------------------------------------------------

def test_out_is_a_file(sandbox):
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--out", sandbox / "canary.txt"))
    assert snapshot(sandbox) == before


def test_out_below_a_file(sandbox):
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--out", sandbox / "canary.txt" / "sub"), "canary.txt")
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("out", ["/proc/artdata-out", "/proc/self/artdata", "/sys/artdata-out"])
def test_out_in_a_pseudo_filesystem(sandbox, out):
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--out", out), "cannot")
    assert snapshot(sandbox) == before
    assert not Path(out).exists()


def test_split_path_is_a_file(sandbox):
    (sandbox / "out" / "drawer").mkdir(parents=True)
    (sandbox / "out" / "drawer" / "train").write_text("not a folder")
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--out", sandbox / "out"), "not a folder")
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("mode", ["", "--resume", "--overwrite"])
def test_symlinked_split_folder_is_refused_and_its_target_untouched(sandbox, tiny_split, mode):
    """The link's target holds a generated split and someone's partial file: nothing there
    may be deleted or replaced, whatever the mode."""
    target = sandbox / "canaries" / "elsewhere"
    shutil.copytree(tiny_split, target)
    (target / "shard-00007.h5.partial").write_bytes(b"a concurrent writer's")
    (sandbox / "out" / "drawer").mkdir(parents=True)
    (sandbox / "out" / "drawer" / "train").symlink_to(target)
    before = snapshot(sandbox)
    args = [mode] if mode else []
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", *args, "--out", sandbox / "out"),
                          "symbolic link")
    assert snapshot(sandbox) == before


def test_refused_run_deletes_no_partial_file(sandbox, tiny_split):
    """"already holds generated data": another run's .partial files in the split survive."""
    split = copy_split(tiny_split, sandbox / "out")
    (split / "shard-00001.h5.partial").write_bytes(b"being written by another run")
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--out", sandbox / "out"),
                          "--resume", "--overwrite")
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("mode", ["", "--resume", "--overwrite"])
def test_a_running_generate_locks_its_split(sandbox, tiny_split, mode):
    split = copy_split(tiny_split, sandbox / "out")
    lock = split.parent / ".train.lock"
    with open(lock, "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        before = snapshot(sandbox)
        args = [mode] if mode else []
        assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", *args, "--out", sandbox / "out"),
                              "another artdata generate")
        assert snapshot(sandbox) == before


@pytest.mark.parametrize("mode", ["", "--overwrite"])
def test_foreign_files_in_the_split_are_never_replaced(sandbox, tiny_split, mode):
    split = copy_split(tiny_split, sandbox / "out")
    (split / "notes.txt").write_text("my notes")
    before = snapshot(sandbox)
    args = [mode] if mode else []
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", *args, "--out", sandbox / "out"))
    assert snapshot(sandbox) == before


def test_a_folder_of_other_files_is_not_a_split(sandbox):
    split = sandbox / "out" / "drawer" / "train"
    split.mkdir(parents=True)
    (split / "photo.png").write_bytes(b"png")
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--out", sandbox / "out"), "not empty")
    assert snapshot(sandbox) == before


# --------------------------------------------------------------------------------------
# Failed runs: nothing left behind, the previous split kept
# --------------------------------------------------------------------------------------

def test_failed_run_leaves_nothing(sandbox):
    table = sandbox / "canaries" / "invisible.json"
    table.write_text(json.dumps(INVISIBLE_TABLE))
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--table", table, "--out", sandbox / "out"), "no pose")
    assert snapshot(sandbox) == before  # no stub manifest, no empty folders
    # ... so the same command without the bad table runs without --resume/--overwrite
    assert generate(*TINY, "--n", "1", "--out", sandbox / "out").exit_code == 0


def test_missing_ray_leaves_nothing(sandbox, monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "ray", None)  # "import ray" fails as if not installed
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--executor", "ray", "--out", sandbox / "out"), "pip install")
    assert snapshot(sandbox) == before


def test_failed_overwrite_keeps_the_previous_split(sandbox, tiny_split):
    copy_split(tiny_split, sandbox / "out")
    table = sandbox / "canaries" / "invisible.json"
    table.write_text(json.dumps(INVISIBLE_TABLE))
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--table", table, "--overwrite",
                                   "--out", sandbox / "out"), "no pose")
    assert snapshot(sandbox) == before


def test_overwrite_replaces_only_when_complete_and_leaves_no_sibling(sandbox, tiny_split):
    split = copy_split(tiny_split, sandbox / "out")
    old = snapshot(split)
    assert generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--seed", "1", "--overwrite",
                    "--out", sandbox / "out").exit_code == 0
    assert snapshot(split) != old and json.loads((split / "manifest.json").read_text())["seed"] == 1
    assert sorted(p.name for p in split.parent.iterdir()) == ["train"]  # no lock, staging or old folder


# --------------------------------------------------------------------------------------
# Resume: never adopt another run's shards
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("option, value", [("--seed", "1"), ("--images", "2"), ("--width", "48"), ("--noise", "kinect2"),
                                           ("--vfov", "50")])
def test_resume_without_manifest_refuses_other_settings_shards(sandbox, tiny_split, option, value):
    split = copy_split(tiny_split, sandbox / "out")
    (split / "manifest.json").unlink()
    args = [a for a in TINY]
    if option in args:
        args[args.index(option) + 1] = value
    else:
        args += [option, value]
    before = snapshot(sandbox)
    assert_one_line_error(generate(*args, "--n", "2", "--objects-per-shard", "1", "--resume", "--out", sandbox / "out"),
                          "different settings")
    assert snapshot(sandbox) == before


def test_resume_without_manifest_adopts_its_own_shards(sandbox, tiny_split):
    split = copy_split(tiny_split, sandbox / "out")
    (split / "manifest.json").unlink()
    assert generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--resume", "--out", sandbox / "out").exit_code == 0
    assert (split / "manifest.json").read_bytes() == (tiny_split / "manifest.json").read_bytes()


CORRUPT_MANIFESTS = {
    "not-json": "{",
    "list": "[]",
    "no-config": '{"format_version": "%(v)s", "shards": []}',
    "config-wrong-type": '{"format_version": "%(v)s", "config": 5, "shards": []}',
    "traversal-shard": None,  # filled in from the real manifest below
    "absolute-shard": None,
}


def test_integer_beyond_a_float_in_a_manifest_table(sandbox, tiny_split):
    """A manifest's table holding 10**400 (an exact JSON integer): verify reports it and
    --resume refuses it in one line (both raised OverflowError)."""
    split = copy_split(tiny_split, sandbox / "out")
    manifest = json.loads((split / "manifest.json").read_text())
    manifest["config"]["table"]["chirality_p"] = 10**400
    (split / "manifest.json").write_text(json.dumps(manifest))
    before = snapshot(sandbox)
    result = CliRunner().invoke(main, ["verify", "-q", str(split)])
    assert result.exit_code == 1 and "chirality_p" in result.output, (result.output, result.exception)
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--resume", "--out", sandbox / "out"),
                          "chirality_p")
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("case", sorted(CORRUPT_MANIFESTS))
def test_resume_with_a_corrupt_manifest(sandbox, tiny_split, case):
    split = copy_split(tiny_split, sandbox / "out")
    manifest = json.loads((split / "manifest.json").read_text())
    if case in ("traversal-shard", "absolute-shard"):
        manifest["shards"][0]["file"] = "../../canary.txt" if case == "traversal-shard" else str(sandbox / "canary.txt")
        text = json.dumps(manifest)
    else:
        text = CORRUPT_MANIFESTS[case] % {"v": manifest["format_version"]}
    (split / "manifest.json").write_text(text)
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--resume", "--out", sandbox / "out"))
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("content", [b"", b"not hdf5 at all", b"\x89HDF\r\n\x1a\n" + b"\0" * 100])
def test_resume_with_a_foreign_shard_file(sandbox, tiny_split, content):
    split = copy_split(tiny_split, sandbox / "out")
    (split / "manifest.json").unlink()
    (split / "shard-00001.h5").write_bytes(content)
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--resume", "--out", sandbox / "out"))
    assert snapshot(sandbox) == before


TAMPERED_RECORDS = {
    "n-images-beyond-float": ("n_images", 10**400),  # not an OverflowError in the free-space check
    "object-range": ("object_stop", 10**6),
    "negative-start": ("object_start", -5),
    "checksum-not-hex": ("sha256", "../../x"),
    "checksum-other": ("sha256", "0" * 64),  # a wrong (but well-formed) checksum is verify's to find
    "pose-attempts": ("pose_attempts", 10**400),
}


@pytest.mark.parametrize("case", sorted(TAMPERED_RECORDS))
def test_resume_never_carries_a_tampered_record_into_a_complete_manifest(sandbox, tiny_split, case):
    """--resume kept a listed record as it was (only its size was compared): the run ended
    "complete" with exit 0 and a manifest that verify rejects, or in a traceback."""
    split = copy_split(tiny_split, sandbox / "out")
    original = json.loads((split / "manifest.json").read_text())
    manifest = json.loads(json.dumps(original))
    (split / "shard-00001.h5").unlink()
    manifest["shards"], manifest["complete"] = manifest["shards"][:1], False
    key, value = TAMPERED_RECORDS[case]
    manifest["shards"][0][key] = value
    (split / "manifest.json").write_text(json.dumps(manifest))
    result = generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--resume", "--out", sandbox / "out")
    if case == "checksum-other":  # kept, as any listed shard of the right size; verify reports it
        assert result.exit_code == 0, result.output
        return
    assert result.exit_code == 0, (result.output, result.exception)
    resumed = json.loads((split / "manifest.json").read_text())
    assert resumed["shards"] == original["shards"] and resumed["complete"] is True
    assert CliRunner().invoke(main, ["verify", "-q", str(split)]).exit_code == 0


def test_resume_never_adopts_a_shard_symlink_leading_out(sandbox, tiny_split):
    """An unlisted shard-00001.h5 linking to a valid shard elsewhere is refused, not opened, hashed
    and adopted (after which every reader would refuse the split)."""
    split = copy_split(tiny_split, sandbox / "out")
    manifest = json.loads((split / "manifest.json").read_text())
    manifest["shards"], manifest["complete"] = manifest["shards"][:1], False
    (split / "manifest.json").write_text(json.dumps(manifest))
    outside = sandbox / "canaries" / "shard-00001.h5"
    shutil.move(split / "shard-00001.h5", outside)
    (split / "shard-00001.h5").symlink_to(outside)
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--resume", "--out", sandbox / "out"),
                          "leads outside")
    assert snapshot(sandbox) == before


def test_resume_with_a_shard_beyond_the_run(sandbox, tiny_split):
    split = copy_split(tiny_split, sandbox / "out")
    (split / "manifest.json").unlink()
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "1", "--objects-per-shard", "1", "--resume", "--out", sandbox / "out"),
                          "shard-00001.h5")
    assert snapshot(sandbox) == before


# --------------------------------------------------------------------------------------
# Read-only and full filesystems (root: a small tmpfs mounted for the test)
# --------------------------------------------------------------------------------------

@contextlib.contextmanager
def _tmpfs(path: Path, options: str):
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    path.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.decode().strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MB tmpfs."""
    with _tmpfs(tmp_path / "small", "size=2m") as path:
        yield path


@pytest.fixture
def readonly_disk(tmp_path):
    """A read-only tmpfs holding a canary file and a complete split."""
    path = tmp_path / "ro"
    with _tmpfs(path, "size=1m") as mounted:
        (mounted / "canary.txt").write_text("read-only canary")
        assert generate(*TINY, "--n", "1", "--out", mounted / "data").exit_code == 0
        subprocess.run(["mount", "-o", "remount,ro", str(mounted)], check=True)
        yield mounted


@pytest.mark.parametrize("mode", ["", "--resume", "--overwrite", "--split=test"])
def test_read_only_output(readonly_disk, mode):
    before = snapshot(readonly_disk)
    args = [mode] if mode else []
    assert_one_line_error(generate(*TINY, "--n", "1", *args, "--out", readonly_disk / "data"), "read-only")
    assert snapshot(readonly_disk) == before


def _fill(disk: Path, leave_bytes: int) -> Path:
    free = shutil.disk_usage(disk).free
    filler = disk / "filler.bin"
    filler.write_bytes(b"\0" * max(free - leave_bytes, 0))
    return filler


def test_disk_full_is_one_line_keeps_complete_shards_and_resumes_identically(tmp_path, small_disk):
    args = [*TINY, "--n", "6", "--objects-per-shard", "1", "--width", "96", "--height", "54", "--images", "2"]
    reference = tmp_path / "reference"
    assert generate(*args, "--out", reference).exit_code == 0
    ref_split = reference / "drawer" / "train"
    shard_bytes = max(p.stat().st_size for p in ref_split.glob("shard-*.h5"))
    filler = _fill(small_disk, 2 * shard_bytes + 16 * 4096)  # a few shards fit, not six
    line = assert_one_line_error(generate(*args, "--out", small_disk / "data"), "no space left", "free")
    split = small_disk / "data" / "drawer" / "train"
    kept = sorted(p.name for p in split.glob("shard-*.h5")) if split.exists() else []
    assert not list(small_disk.rglob("*.partial"))
    assert 0 < len(kept) < 6 and "--resume" in line
    filler.unlink()  # space freed: the same command with --resume completes the split
    result = generate(*args, "--resume", "--out", small_disk / "data")
    assert result.exit_code == 0, result.output
    assert {p.name: sha256_file(p) for p in split.iterdir()} == {p.name: sha256_file(p) for p in ref_split.iterdir()}


def test_disk_full_with_nothing_written_leaves_nothing(small_disk):
    _fill(small_disk, 0)
    before = snapshot(small_disk)
    assert_one_line_error(generate(*TINY, "--n", "1", "--out", small_disk / "data"))
    assert snapshot(small_disk) == before


def test_disk_full_show_leaves_no_partial_file(small_disk, tiny_split):
    _fill(small_disk, 0)
    before = snapshot(small_disk)
    result = CliRunner().invoke(main, ["show", str(tiny_split), "--out", str(small_disk / "gallery.png"), "--quiet"])
    assert_one_line_error(result, "gallery.png")
    assert snapshot(small_disk) == before


# --------------------------------------------------------------------------------------
# Outputs of show and baseline: refused before any work, nothing left behind
# --------------------------------------------------------------------------------------

def _show(split, *args):
    return CliRunner().invoke(main, ["show", str(split), "--quiet", *map(str, args)])


def _baseline(split, out):
    return CliRunner().invoke(main, ["baseline", "mean", "--train", str(split), "--test", str(split), "--out", str(out),
                                     "--quiet"])


@pytest.mark.parametrize("out, needle", [
    ("/proc/artdata-gallery.png", "cannot write"),
    ("/proc/self/status", "cannot write"),
    ("canary.txt/sub.png", "not a directory"),
    ("canaries", "directory"),
])
def test_show_output_refused(sandbox, tiny_split, out, needle):
    before = snapshot(sandbox)
    target = out if out.startswith("/") else sandbox / out
    assert_one_line_error(_show(tiny_split, "--out", target), needle)
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("dpi", ["100000", "0", "-1"])
def test_show_absurd_dpi(sandbox, tiny_split, dpi):
    before = snapshot(sandbox)
    assert_one_line_error(_show(tiny_split, "--out", sandbox / "g.png", "--dpi", dpi), "dpi" if dpi != "100000" else "px")
    assert snapshot(sandbox) == before


@pytest.mark.parametrize("out, needle", [
    ("/proc/artdata-predictions.h5", "cannot write"),
    ("canary.txt/predictions.h5", "not a directory"),
    ("canaries", "directory"),
])
def test_baseline_output_refused(sandbox, tiny_split, out, needle):
    before = snapshot(sandbox)
    target = out if out.startswith("/") else sandbox / out
    assert_one_line_error(_baseline(tiny_split, target), needle)
    assert snapshot(sandbox) == before


def test_show_and_baseline_on_a_read_only_filesystem(readonly_disk, tiny_split):
    before = snapshot(readonly_disk)
    assert_one_line_error(_show(tiny_split, "--out", readonly_disk / "g.png"), "read-only")
    assert_one_line_error(_baseline(tiny_split, readonly_disk / "p.h5"), "read-only")
    assert snapshot(readonly_disk) == before


# --------------------------------------------------------------------------------------
# What a killed --overwrite leaves behind
# --------------------------------------------------------------------------------------

def test_killed_between_the_swap_renames_the_old_split_comes_back(sandbox, tiny_split):
    split = copy_split(tiny_split, sandbox / "out")
    split.rename(split.parent / ".train.old")
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--out", sandbox / "out"),
                          "already holds generated data")
    assert snapshot(split) == snapshot(tiny_split)
    assert sorted(p.name for p in split.parent.iterdir()) == ["train"]


def test_a_killed_overwrites_staging_folder_is_kept_by_refused_runs_and_removed_by_the_next(sandbox, tiny_split):
    split = copy_split(tiny_split, sandbox / "out")
    staging = split.parent / ".train.new"
    shutil.copytree(tiny_split, staging)
    (staging / "shard-00001.h5.partial").write_bytes(b"killed mid-write")
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--out", sandbox / "out"))
    assert snapshot(sandbox) == before
    assert generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--overwrite", "--out", sandbox / "out").exit_code == 0
    assert sorted(p.name for p in split.parent.iterdir()) == ["train"]
    assert snapshot(split) == snapshot(tiny_split)


def test_a_staging_folder_with_foreign_files_is_never_deleted(sandbox, tiny_split):
    split = copy_split(tiny_split, sandbox / "out")
    staging = split.parent / ".train.new"
    staging.mkdir()
    (staging / "mine.txt").write_text("not artdata's")
    before = snapshot(sandbox)
    assert_one_line_error(generate(*TINY, "--n", "2", "--objects-per-shard", "1", "--overwrite", "--out", sandbox / "out"),
                          "mine.txt")
    assert snapshot(sandbox) == before


def test_generate_refuses_a_split_name_that_is_not_utf8(tmp_path):
    assert_one_line_error(generate("--class", "microwave", "--n", "1", "--images", "4", "--split", "t\udcff",
                                   "--out", tmp_path), "invalid split name")
