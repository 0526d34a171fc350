"""Writes never follow a link planted in an output folder, and an unwritable output is one line.

Each command writes its output through a temporary sibling created exclusively under an
unpredictable name (``.NAME.<random hex>.partial``).  At a predictable name (``NAME.partial``, a
probe ``.artdata-write-test-<pid>.partial``) a symbolic link planted there would make the command
overwrite the file it points to.  Here links wait at those names (and at the
split's lock and ``OUT/<class>``), pointing at a victim file outside; the victim must stay as
it was and the output must be right.  Also: output names too long for the filesystem, and a
``--resume`` into a split folder that cannot be written, end in one line.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.core import safeio
from articulated_dataset.format import sha256_file
from helpers_core import assert_one_line_error, tree_snapshot
from helpers_real import write_capture

#: A split that renders in a moment: 32x18 px, two images per object, four objects per shard.
TINY = ["--class", "drawer", "--images", "2", "--width", "32", "--height", "18", "--workers", "1", "--quiet"]
#: Objects in the shared split: two shards (4 + 2), enough for the MDN to hold out validation objects.
N_OBJECTS = 6
#: What the planted links point to.
VICTIM_TEXT = b"a file outside every output folder\n"
#: A path component longer than any filesystem's NAME_MAX (255 bytes).
LONG_NAME = "n" * 300
#: A path longer than Linux's PATH_MAX (4096 bytes), of components of allowed length.
LONG_PATH = "/".join(["p" * 200] * 25)


def cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def split(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("data")
    result = cli("generate", *TINY, "--n", N_OBJECTS, "--objects-per-shard", 4, "--out", root)
    assert result.exit_code == 0, result.output
    return root / "drawer" / "train"


@pytest.fixture(scope="module")
def predictions(split, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("predictions") / "mean.h5"
    result = cli("baseline", "mean", "--train", split, "--test", split, "--out", out, "--quiet")
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture
def victim(tmp_path) -> Path:
    path = tmp_path / "victim" / "precious.txt"
    path.parent.mkdir()
    path.write_bytes(VICTIM_TEXT)
    return path


def plant_links(out: Path, victim: Path) -> list[Path]:
    """Links to ``victim`` at the predictable names a write of ``out`` could go through: ``out.partial`` and
    this process's write probe ``.artdata-write-test-<pid>.partial`` (CliRunner runs in-process)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    links = [out.with_name(out.name + safeio.TMP_SUFFIX),
             out.parent / f".artdata-write-test-{os.getpid()}{safeio.TMP_SUFFIX}"]
    for link in links:
        link.symlink_to(victim)
    return links


def assert_untouched(victim: Path, links: list[Path]) -> None:
    assert victim.read_bytes() == VICTIM_TEXT
    for link in links:  # neither followed nor renamed into place
        assert link.is_symlink() and Path(os.readlink(link)) == victim
    assert [p.name for p in victim.parent.iterdir()] == [victim.name]


# --------------------------------------------------------------------------------------
# safeio itself
# --------------------------------------------------------------------------------------

def _write_bytes(path):
    safeio.atomic_write_bytes(path, b"new content")


def _write_h5(path):
    safeio.atomic_write_h5(path, lambda f: f.create_dataset("x", data=np.arange(3)))


def _write_by_name(path):
    with safeio.atomic_path(path) as tmp:
        Path(tmp).write_bytes(b"new content")


def _write_file_object(path):
    with safeio.atomic_file(path) as f:
        f.write(b"new content")


def _read(path):
    if path.suffix == ".h5":
        with h5py.File(path, "r") as f:
            return f["x"][()].tolist()
    return path.read_bytes()


@pytest.mark.parametrize("write", [_write_bytes, _write_h5, _write_by_name, _write_file_object])
@pytest.mark.parametrize("dangling", [False, True])
def test_atomic_writers_never_write_through_a_planted_link(tmp_path, victim, write, dangling):
    out = tmp_path / "out" / ("result.h5" if write is _write_h5 else "result.bin")
    links = plant_links(out, victim)
    if dangling:  # a link to a file not there yet: following it would create the file
        for link in links:
            link.unlink()
            link.symlink_to(victim.parent / "created.txt")
    write(out)
    assert _read(out) == ([0, 1, 2] if write is _write_h5 else b"new content")
    assert out.is_file() and not out.is_symlink()
    assert victim.read_bytes() == VICTIM_TEXT and not (victim.parent / "created.txt").exists()
    assert sorted(p.name for p in out.parent.iterdir()) == sorted([out.name] + [link.name for link in links])


def test_a_link_at_the_output_itself_is_replaced_not_followed(tmp_path, victim):
    out = tmp_path / "result.json"
    out.symlink_to(victim)
    safeio.atomic_write_text(out, "{}\n")
    assert out.read_text() == "{}\n" and not out.is_symlink()
    assert victim.read_bytes() == VICTIM_TEXT


def test_temporary_names_are_unpredictable_and_recognised(tmp_path):
    names = {safeio.temporary_name("shard-00001.h5") for _ in range(50)}
    assert len(names) == 50
    for name in names:
        assert name.startswith(".shard-00001.h5.") and name.endswith(safeio.TMP_SUFFIX)
        assert safeio.temporary_target(name) == "shard-00001.h5"
    assert safeio.temporary_target("shard-00001.h5.partial") == "shard-00001.h5"  # the predictable form is still recognised
    assert safeio.temporary_target("shard-00001.h5") is None
    # a final name at the filesystem's limit still has a temporary that can be created
    long_out = tmp_path / ("x" * 250 + ".h5")
    safeio.atomic_write_bytes(long_out, b"ok")
    assert long_out.read_bytes() == b"ok" and [p.name for p in tmp_path.iterdir()] == [long_out.name]


def test_new_files_get_the_usual_permissions(tmp_path):
    """Not mkstemp's 0600: outputs in a shared folder stay readable by those the umask allows."""
    umask = os.umask(0o022)
    try:
        safeio.atomic_write_bytes(tmp_path / "out.bin", b"x")
    finally:
        os.umask(umask)
    assert (tmp_path / "out.bin").stat().st_mode & 0o777 == 0o644


@pytest.mark.parametrize("check", ["check_can_create", "check_writable_dir"])
def test_write_probes_never_write_through_a_planted_link(tmp_path, victim, check):
    out = tmp_path / "out" / "result.json"
    links = plant_links(out, victim)
    if check == "check_can_create":
        safeio.check_can_create(out)
    else:
        safeio.check_writable_dir(out.parent)
    assert_untouched(victim, links)
    assert sorted(p.name for p in out.parent.iterdir()) == sorted(link.name for link in links)


# --------------------------------------------------------------------------------------
# Commands writing a file (--out, --json, --csv)
# --------------------------------------------------------------------------------------

def _score_json(split, predictions, out):
    return ["score", predictions, "--truth", split, "--json", out]


def _score_csv(split, predictions, out):
    return ["score", predictions, "--truth", split, "--csv", out]


def _baseline(split, predictions, out):
    return ["baseline", "mean", "--train", split, "--test", split, "--out", out, "--quiet"]


def _plan(split, predictions, out):
    return ["plan", split, "--index", 0, "--out", out]


def _show(split, predictions, out):
    return ["show", split, "--out", out, "--quiet"]


def _train(split, predictions, out):
    return ["train", "--model", "mdn", "--small", "--class", "drawer", split, "--out", out,
            "--epochs", 1, "--batch-size", 4]


def _check_json(out):
    assert isinstance(json.loads(out.read_text()), dict)


def _check_csv(out):
    lines = out.read_text().splitlines()
    assert len(lines) >= 2 and "drawer" in lines[1]


def _check_predictions(out):
    from articulated_dataset.benchmark.predictions import read_predictions

    _, per_class = read_predictions(out)
    assert len(per_class["drawer"]["sample_id"]) == N_OBJECTS * 2


def _check_png(out):
    from PIL import Image

    with Image.open(out) as im:
        assert im.format == "PNG" and im.width > 0


def _check_checkpoint(out):
    from articulated_dataset.methods.mdn.checkpoint import load_checkpoint

    assert load_checkpoint(out)["class_name"] == "drawer"


@pytest.mark.parametrize("args, name, check", [
    (_score_json, "report.json", _check_json),
    (_score_csv, "report.csv", _check_csv),
    (_baseline, "mean.h5", _check_predictions),
    (_plan, "plan.json", _check_json),
    (_show, "gallery.png", _check_png),
    (_train, "mdn.pt", _check_checkpoint),
], ids=["score-json", "score-csv", "baseline", "plan", "show", "train"])
def test_commands_never_write_through_a_link_at_a_temporary_name(tmp_path, split, predictions, victim, args, name, check):
    out = tmp_path / "out" / name
    links = plant_links(out, victim)
    result = cli(*args(split, predictions, out))
    assert result.exit_code == 0, result.output
    check(out)
    assert out.is_file() and not out.is_symlink()
    assert_untouched(victim, links)
    assert sorted(p.name for p in out.parent.iterdir()) == sorted([out.name] + [link.name for link in links])


# --------------------------------------------------------------------------------------
# generate: --resume through a planted shard link, linked class folders, the lock
# --------------------------------------------------------------------------------------

def test_resume_never_writes_through_a_planted_partial_shard_link(tmp_path, split, victim):
    """A split shipped with its second shard missing and ``shard-00001.h5.partial`` linking
    outside: the resumed split is the complete one, the victim as it was, the link (not its
    target) removed as a leftover temporary."""
    out = tmp_path / "out"
    copy = out / "drawer" / "train"
    shutil.copytree(split, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["shards"], manifest["complete"] = manifest["shards"][:1], False
    (copy / "manifest.json").write_text(json.dumps(manifest))
    (copy / "shard-00001.h5").unlink()
    (copy / "shard-00001.h5.partial").symlink_to(victim)
    result = cli("generate", *TINY, "--n", N_OBJECTS, "--objects-per-shard", 4, "--resume", "--out", out)
    assert result.exit_code == 0, result.output
    assert victim.read_bytes() == VICTIM_TEXT
    assert {p.name: sha256_file(p) for p in copy.iterdir()} == {p.name: sha256_file(p) for p in split.iterdir()}


@pytest.mark.parametrize("link, mode", [("drawer", "--split=val"), ("drawer", "--overwrite"), ("drawer", "--resume"),
                                        ("drawer/.train.new", "--overwrite"), ("drawer/.train.old", "--overwrite")])
def test_generate_refuses_a_linked_class_folder_or_sibling(tmp_path, split, link, mode):
    """``OUT/<class>`` (or the split's staging or retired sibling) linking elsewhere: the split,
    its lock and an --overwrite's removals would land there.  One line, nothing changed."""
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(split, elsewhere / "train")
    out = tmp_path / "out"
    if link != "drawer":
        shutil.copytree(split, out / "drawer" / "train")
    (out / link).parent.mkdir(parents=True, exist_ok=True)
    (out / link).symlink_to(elsewhere if link == "drawer" else elsewhere / "train")
    before = tree_snapshot(tmp_path)
    assert_one_line_error(cli("generate", *TINY, "--n", N_OBJECTS, "--objects-per-shard", 4, mode, "--out", out),
                          "symbolic link")
    assert tree_snapshot(tmp_path) == before


@pytest.mark.parametrize("dangling", [True, False])
def test_generate_never_opens_its_lock_through_a_link(tmp_path, victim, dangling):
    out = tmp_path / "out"
    (out / "drawer").mkdir(parents=True)
    target = victim.parent / "lock-target" if dangling else victim
    (out / "drawer" / ".train.lock").symlink_to(target)
    before = tree_snapshot(tmp_path)
    assert_one_line_error(cli("generate", *TINY, "--n", 1, "--out", out), ".train.lock", "symbolic link")
    assert tree_snapshot(tmp_path) == before


# --------------------------------------------------------------------------------------
# ingest: its staging folder
# --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def captures(split, tmp_path_factory) -> Path:
    from articulated_dataset.format import open_split

    folder = tmp_path_factory.mktemp("captures")
    _, shards = open_split(split)
    write_capture(folder, "a", shards[0].sample(0), shards[0].K, None)
    return folder


def test_ingest_never_stages_into_a_planted_folder_link(tmp_path, captures):
    """Ingest built the split in ``.<split>.ingest-<pid>``: a link planted there for this pid
    received the manifest and shards, and was then renamed into place as the split."""
    out = tmp_path / "out"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "manifest.json").write_text("someone's manifest\n")
    (out / "drawer").mkdir(parents=True)
    (out / "drawer" / f".real.ingest-{os.getpid()}").symlink_to(elsewhere)
    before = tree_snapshot(elsewhere)
    result = cli("ingest", captures, "--class", "drawer", "--out", out, "--quiet")
    assert result.exit_code == 0, result.output
    assert tree_snapshot(elsewhere) == before
    split = out / "drawer" / "real"
    assert split.is_dir() and not split.is_symlink() and (split / "manifest.json").is_file()


# --------------------------------------------------------------------------------------
# Output names too long for the filesystem
# --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def export(split, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export")
    result = cli("export", split, out, "--quiet")
    assert result.exit_code == 0, result.output
    return out / "drawer" / "train"


LONG_OUTPUTS = {
    "generate": lambda s, p, c, e, out: ["generate", *TINY, "--n", 1, "--out", out],
    "export": lambda s, p, c, e, out: ["export", s, out, "--quiet"],
    "import-exr": lambda s, p, c, e, out: ["import-exr", e, "--out", out, "--quiet"],
    "ingest": lambda s, p, c, e, out: ["ingest", c, "--class", "drawer", "--out", out, "--quiet"],
    "baseline": lambda s, p, c, e, out: _baseline(s, p, out),
    "predict": lambda s, p, c, e, out: ["predict", "--model", "mdn-small", s, "--out", out, "--quiet"],
    "train": lambda s, p, c, e, out: _train(s, p, out),
    "plan": lambda s, p, c, e, out: _plan(s, p, out),
    "show": lambda s, p, c, e, out: _show(s, p, f"{out}.png"),
    "show-per-sample": lambda s, p, c, e, out: ["show", s, "--per-sample", out, "--quiet"],
    "score-json": lambda s, p, c, e, out: _score_json(s, p, out),
    "score-csv": lambda s, p, c, e, out: _score_csv(s, p, out),
    "card": lambda s, p, c, e, out: ["card", s, "--out", out],
}


@pytest.mark.parametrize("command", list(LONG_OUTPUTS))
@pytest.mark.parametrize("long", [LONG_NAME, f"{LONG_NAME}/inside", LONG_PATH], ids=["name", "parent", "path"])
def test_output_names_too_long_are_one_line(tmp_path, split, predictions, captures, export, command, long):
    before = tree_snapshot(tmp_path)
    result = cli(*LONG_OUTPUTS[command](split, predictions, captures, export, tmp_path / long))
    assert_one_line_error(result, "too long")
    assert tree_snapshot(tmp_path) == before


# --------------------------------------------------------------------------------------
# --resume into a split folder that cannot be written
# --------------------------------------------------------------------------------------

@pytest.fixture
def read_only_split(tmp_path, split):
    """An incomplete copy of ``split`` whose folder is a read-only bind mount (its class folder
    stays writable: the lock can be taken, the shards cannot be written)."""
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("a read-only bind mount needs root")
    copy = tmp_path / "out" / "drawer" / "train"
    shutil.copytree(split, copy)
    (copy / "shard-00001.h5").unlink()
    if subprocess.run(["mount", "--bind", str(copy), str(copy)], capture_output=True).returncode != 0:
        pytest.skip("cannot bind-mount here")
    try:
        if subprocess.run(["mount", "-o", "remount,bind,ro", str(copy)], capture_output=True).returncode != 0:
            pytest.skip("cannot remount read-only here")
        yield copy
    finally:
        subprocess.run(["umount", "-l", str(copy)], check=False)


def test_resume_into_an_unwritable_split_folder_is_one_line(tmp_path, read_only_split):
    before = tree_snapshot(tmp_path)
    result = cli("generate", *TINY, "--n", N_OBJECTS, "--objects-per-shard", 4, "--resume", "--out", tmp_path / "out")
    assert_one_line_error(result, "read-only", str(read_only_split))
    assert tree_snapshot(tmp_path) == before


def test_an_hdf5_file_into_an_unwritable_folder_is_a_write_error(read_only_split):
    """HDF5's own error carries no errno; the file is built in memory and written by Python."""
    with pytest.raises(safeio.WriteError, match="read-only"):
        _write_h5(read_only_split / "new.h5")
