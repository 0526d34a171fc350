"""Input from strangers for ``artdata score`` and the predictions reader.

Every case runs the CLI as a user does and must end with exactly one stderr line
``artdata: error: ...``, exit code 2, nothing on stdout, and no file created, changed or
removed anywhere in the case's folders (predictions, truth, outputs) -- a refused
``--json``/``--csv`` leaves no partial file.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.benchmark import write_predictions
from articulated_dataset.benchmark.predictions import PREDICTIONS_FORMAT_VERSION, read_predictions, validate_class
from articulated_dataset.cli import main
from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.format import open_split
from helpers_core import assert_one_line_error, assert_unchanged, raw_write, tree_snapshot

FIELDS = ("sample_id", "axis_pose", "q", "geometry", "part_offset")
CLASS = "cabinet"


# ---------------------------------------------------------------- fixtures and shared functions

@pytest.fixture(scope="module")
def good(tiny_root):
    """Valid prediction arrays (the truth itself) for the tiny cabinet test split."""
    _, shards = open_split(tiny_root / CLASS / "test")
    arrays = {k: np.concatenate([s.read(k) for s in shards]) for k in FIELDS}
    for s in shards:
        s.close()
    return arrays


def changed(good, **changes) -> dict:
    """``{CLASS: arrays}`` with some datasets replaced (``None`` removes one)."""
    arrays = {k: np.array(v) for k, v in good.items()}
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    return {CLASS: arrays}


def with_value(good, name, index, value) -> dict:
    a = np.array(good[name], np.float64)
    a[index] = value
    return changed(good, **{name: a})


def mixture(good, layout=("j0.q", "j0.origin.x"), **over) -> tuple[dict, dict]:
    n, D = len(good["q"]), len(layout)
    arrays = {k: np.array(v) for k, v in good.items()}
    arrays.update(mixture_weights=np.full((n, 2), 0.5), mixture_means=np.zeros((n, 2, D)),
                  mixture_scales=np.ones((n, 2, D)))
    arrays.update(over)
    return {CLASS: arrays}, {CLASS: {"mixture_layout": json.dumps(list(layout)) if isinstance(layout, tuple) else layout}}


class Case:
    """The folders of one case: ``work`` (predictions, outputs) and ``truth`` (a private copy of
    the tiny cabinet test split, ``truth/cabinet/test``)."""

    def __init__(self, tmp_path: Path, tiny_root: Path, good: dict):
        self.work = tmp_path / "work"
        self.work.mkdir()
        self.truth = tmp_path / "truth"
        shutil.copytree(tiny_root / CLASS / "test", self.truth / CLASS / "test")
        self.split = self.truth / CLASS / "test"
        self.good = good

    def preds(self, groups=None, attrs=None, group_attrs=None) -> Path:
        """Write ``work/p.h5``; ``attrs`` may replace the root ``method``/``format_version`` (None: absent)."""
        attrs = attrs or {}
        return raw_write(self.work / "p.h5", changed(self.good) if groups is None else groups,
                         method=attrs.get("method", "crafted"), version=attrs.get("format_version", PREDICTIONS_FORMAT_VERSION),
                         group_attrs=group_attrs)

    def manifest(self) -> dict:
        return json.loads((self.split / "manifest.json").read_text())

    def set_manifest(self, m) -> None:
        (self.split / "manifest.json").write_text(json.dumps(m))

    def shard(self) -> Path:
        return self.split / self.manifest()["shards"][0]["file"]


def score_args(c: Case, preds: Path | None = None, *extra) -> list:
    return ["score", preds or c.preds(), "--truth", c.truth, *extra]


# ---------------------------------------------------------------- the cases
# Each builder takes a Case and returns (CLI arguments, needles the error line must contain).

def _corrupt_chunk(c: Case):
    p = c.work / "p.h5"
    groups = changed(c.good)
    with h5py.File(p, "w") as f:
        f.attrs.update(format_version=PREDICTIONS_FORMAT_VERSION, method="crafted")
        g = f.create_group(CLASS)
        for k, v in groups[CLASS].items():
            if k == "q":
                g.create_dataset(k, data=np.asarray(v, np.float64), chunks=(len(v), 1), compression="gzip")
            else:
                g.create_dataset(k, data=v)
        info = g["q"].id.get_chunk_info(0)
    data = bytearray(p.read_bytes())
    for i in range(info.byte_offset, info.byte_offset + info.size):
        data[i] ^= 0x5A
    p.write_bytes(bytes(data))
    return score_args(c, p), ["/cabinet/q", "cannot read"]


def _huge_declared(c: Case):
    p = c.work / "p.h5"
    with h5py.File(p, "w") as f:
        f.attrs.update(format_version=PREDICTIONS_FORMAT_VERSION, method="crafted")
        g = f.create_group(CLASS)
        g.create_dataset("sample_id", shape=(10**13,), dtype=np.int64, chunks=(1024,))  # unallocated: tiny file
        for k in ("axis_pose", "q"):
            g.create_dataset(k, data=c.good[k])
    return score_args(c, p), ["of memory", "available"]


def _huge_mixture(c: Case):
    """A mixture of 2 million components per image in a few kilobytes (unallocated chunks): refused
    from its shape, before it is read (it took 3.6 GB of memory to refuse)."""
    p = c.work / "p.h5"
    n = len(c.good["q"])
    with h5py.File(p, "w") as f:
        f.attrs.update(format_version=PREDICTIONS_FORMAT_VERSION, method="crafted")
        g = f.create_group(CLASS)
        for k in ("sample_id", "axis_pose", "q"):
            g.create_dataset(k, data=c.good[k])
        g.attrs["mixture_layout"] = json.dumps(["j0.q"])
        g.create_dataset("mixture_weights", shape=(n, 2_000_000), dtype=np.float64, chunks=(1, 4096))
        for k in ("mixture_means", "mixture_scales"):
            g.create_dataset(k, shape=(n, 2_000_000, 1), dtype=np.float64, chunks=(1, 4096, 1))
    return score_args(c, p), ["2000000 components", "at most"]


def _soft_link(c: Case):
    p = c.preds()
    with h5py.File(p, "a") as f:
        f[CLASS]["geometry_link"] = h5py.SoftLink(f"/{CLASS}/q")
    return score_args(c, p), ["soft link", "refused"]


def _external_link(c: Case):
    other = raw_write(c.work / "other.h5", changed(c.good))
    p = c.preds(groups={})
    with h5py.File(p, "a") as f:
        f[CLASS] = h5py.ExternalLink(str(other), f"/{CLASS}")
    return score_args(c, p), ["external link", "refused"]


def _external_storage(c: Case):
    raw = c.work / "raw.bin"
    raw.write_bytes(np.asarray(c.good["q"], np.float64).tobytes())
    p = c.preds(groups=changed(c.good, q=None))
    with h5py.File(p, "a") as f:
        f[CLASS].create_dataset("q", shape=c.good["q"].shape, dtype=np.float64, external=[(str(raw), 0, raw.stat().st_size)])
    return score_args(c, p), ["external storage", "refused"]


def _truncated(c: Case):
    p = c.preds()
    p.write_bytes(p.read_bytes()[:1000])
    return score_args(c, p), ["not a readable HDF5 file"]


def _fifo(c: Case):
    p = c.work / "fifo.h5"
    os.mkfifo(p)
    return score_args(c, p), ["not a regular file"]


def _dangling(c: Case):
    p = c.work / "p.h5"
    p.symlink_to(c.work / "nowhere.h5")
    return score_args(c, p), ["file not found"]


def _nested_group(c: Case):
    p = c.preds()
    with h5py.File(p, "a") as f:
        f[CLASS].create_group("inner")
    return score_args(c, p), ["'inner' is a group"]


def _class_group_name(name):
    def build(c: Case):
        return score_args(c, c.preds(groups={name: changed(c.good)[CLASS]})), ["invalid class group name"]
    return build


def _attr_case(attrs, needles):
    return lambda c: (score_args(c, c.preds(attrs=attrs)), needles)


def _groups_case(fn, needles):
    return lambda c: (score_args(c, c.preds(groups=fn(c.good))), needles)


def _mixture_case(needles, layout=("j0.q", "j0.origin.x"), **over):
    """``over``: dataset name -> function of the number of images giving the array."""
    def build(c: Case):
        n = len(c.good["q"])
        groups, gattrs = mixture(c.good, layout, **{k: fn(n) for k, fn in over.items()})
        return score_args(c, c.preds(groups=groups, group_attrs=gattrs)), needles
    return build


def _manifest_shard_file(name):
    def build(c: Case):
        m = c.manifest()
        m["shards"][0]["file"] = name
        c.set_manifest(m)
        return score_args(c), ["manifest.json", "shard"]
    return build


def _shard_symlink_outside(c: Case):
    outside = c.work / "elsewhere.h5"
    shutil.copy(c.shard(), outside)
    c.shard().unlink()
    c.shard().symlink_to(outside)
    return score_args(c), ["outside", "refused"]


def _manifest_edit(fn, needles):
    def build(c: Case):
        c.set_manifest(fn(c.manifest()))
        return score_args(c), needles
    return build


def _manifest_text(text, needles):
    def build(c: Case):
        (c.split / "manifest.json").write_bytes(text)
        return score_args(c), needles
    return build


def _damaged_shard(c: Case):
    shard = c.shard()
    shard.write_bytes(shard.read_bytes()[:2048])
    return score_args(c), [shard.name]


def _joint_types_attr(c: Case):
    with h5py.File(c.shard(), "a") as f:
        f.attrs["joint_types"] = "not json ["
    return score_args(c), ["joint_types"]


def _output_is_input(c: Case):
    p = c.preds()
    return score_args(c, p, "--json", p), ["also an input"]


def _outputs_same(c: Case):
    out = c.work / "r.out"
    return score_args(c, None, "--json", out, "--csv", out), ["same file"]


def _json_missing_dir(c: Case):
    return score_args(c, None, "--json", c.work / "no" / "such" / "r.json"), ["cannot write", "no such file"]


def _json_under_file(c: Case):
    (c.work / "plain").write_text("x")
    return score_args(c, None, "--csv", c.work / "plain" / "r.csv"), ["cannot write", "not a directory"]


def _json_proc(c: Case):
    return score_args(c, None, "--json", "/proc/artdata-score.json"), ["cannot write"]


def _json_dir(c: Case):
    return score_args(c, None, "--json", c.work), ["is a directory"]


def _partial_required(c: Case):
    keep = np.arange(len(c.good["q"])) % 2 == 0
    groups = {CLASS: {k: np.asarray(v)[keep] for k, v in c.good.items()}}
    return score_args(c, c.preds(groups=groups), "--require-complete"), ["partial coverage", f"{keep.sum()}/{len(keep)}"]


def _truth_missing(c: Case):
    return ["score", c.preds(), "--truth", c.work / "nowhere"], ["no such directory"]


def _truth_is_file(c: Case):
    return ["score", c.preds(), "--truth", c.preds()], ["expected a directory", "got a file"]


def _truth_empty(c: Case):
    (c.work / "empty").mkdir()
    return ["score", c.preds(), "--truth", c.work / "empty"], ["no generated split"]


def _bad_split(c: Case):
    return score_args(c, None, "--split", "../../etc"), ["no split '../../etc'"]


def _missing_preds(c: Case):
    return score_args(c, c.work / "missing.h5"), ["file not found"]


def _text_preds(c: Case):
    (c.work / "t.h5").write_text("not hdf5\n")
    return score_args(c, c.work / "t.h5"), ["not a readable HDF5 file"]


def _empty_preds(c: Case):
    (c.work / "e.h5").write_bytes(b"")
    return score_args(c, c.work / "e.h5"), ["not a readable HDF5 file"]


def _dir_preds(c: Case):
    return score_args(c, c.work), ["directory"]


def _usage(args_fn, needles):
    return lambda c: (args_fn(c), needles)


CASES = {
    # absurd values
    "q 1e300": (lambda c: (score_args(c, c.preds(groups=with_value(c.good, "q", (0, 0), 1e300))), ["/cabinet/q", "beyond"])),
    "q -1e7": (lambda c: (score_args(c, c.preds(groups=with_value(c.good, "q", (5, 0), -1e7))), ["/cabinet/q", "beyond"])),
    "position 1e9 m": (lambda c: (score_args(c, c.preds(groups=with_value(c.good, "axis_pose", (3, 0, 1), 1e9))), ["axis_pose", "beyond"])),
    "geometry -1e300": (lambda c: (score_args(c, c.preds(groups=with_value(c.good, "geometry", (0, 2), -1e300))), ["geometry", "beyond"])),
    "part offset inf": (lambda c: (score_args(c, c.preds(groups=with_value(c.good, "part_offset", (1, 0, 0), np.inf))), ["part_offset", "NaN/inf"])),
    "q nan": (lambda c: (score_args(c, c.preds(groups=with_value(c.good, "q", (2, 0), np.nan))), ["/cabinet/q", "NaN/inf"])),
    "quaternion 1e300": (lambda c: (score_args(c, c.preds(groups=with_value(c.good, "axis_pose", (0, 0, 3), 1e300))), ["axis_pose", "beyond"])),
    "zero quaternion": (lambda c: (score_args(c, c.preds(groups=with_value(c.good, "axis_pose", (0, 0, slice(3, 7)), 0.0))), ["zero-length quaternion"])),
    "mixture scale 1e300": (_mixture_case(["mixture_scales", "beyond"], mixture_scales=lambda n: np.full((n, 2, 2), 1e300))),
    "mixture mean 1e12": (_mixture_case(["mixture_means", "beyond"], mixture_means=lambda n: np.full((n, 2, 2), 1e12))),
    "mixture weight 1e308": (_mixture_case(["mixture_weights", "beyond"], mixture_weights=lambda n: np.full((n, 2), 1e308))),
    "mixture scale 0": (_mixture_case(["mixture_scales", "<= 0"], mixture_scales=lambda n: np.zeros((n, 2, 2)))),
    "mixture scale nan": (_mixture_case(["mixture_scales", "NaN/inf"], mixture_scales=lambda n: np.full((n, 2, 2), np.nan))),
    "mixture weights all zero": (_mixture_case(["all weights zero"], mixture_weights=lambda n: np.zeros((n, 2)))),
    "mixture weight negative": (_mixture_case(["negative weights"], mixture_weights=lambda n: np.tile([1.5, -0.5], (n, 1)))),
    # ids and shapes
    "ids uint64 max": (_groups_case(lambda g: changed(g, sample_id=np.full(len(g["q"]), np.iinfo(np.uint64).max, np.uint64)), ["sample_id", "63-bit"])),
    "ids float": (_groups_case(lambda g: changed(g, sample_id=g["sample_id"].astype(np.float64)), ["sample_id", "dtype"])),
    "ids 2-D": (_groups_case(lambda g: changed(g, sample_id=g["sample_id"][:, None]), ["sample_id", "shape"])),
    "ids scalar": (_groups_case(lambda g: changed(g, sample_id=np.int64(5)), ["sample_id", "shape"])),
    "ids duplicated": (_groups_case(lambda g: changed(g, sample_id=np.concatenate([g["sample_id"][:1], g["sample_id"][:-1]])), ["duplicated"])),
    "ids unknown": (_groups_case(lambda g: changed(g, sample_id=g["sample_id"] ^ 1), ["not in the truth set"])),
    "two joints for a cabinet": (_groups_case(lambda g: changed(g, axis_pose=np.repeat(g["axis_pose"], 2, axis=1), q=np.repeat(g["q"], 2, axis=1),
                                                                 part_offset=np.repeat(g["part_offset"], 2, axis=1)), ["2 joints predicted"])),
    "zero joints": (_groups_case(lambda g: changed(g, axis_pose=g["axis_pose"][:, :0], q=g["q"][:, :0], part_offset=None), ["zero joints"])),
    "pose width 6": (_groups_case(lambda g: changed(g, axis_pose=g["axis_pose"][..., :6]), ["axis_pose", "shape"])),
    "q bool": (_groups_case(lambda g: changed(g, q=g["q"] > 0.5), ["/cabinet/q", "dtype"])),
    "geometry complex": (_groups_case(lambda g: changed(g, geometry=g["geometry"].astype(np.complex128)), ["geometry", "not numeric"])),
    "q strings": (_groups_case(lambda g: changed(g, q=np.array([b"x"] * len(g["q"]))), ["/cabinet/q", "not numeric"])),
    "unknown dataset": (_groups_case(lambda g: {CLASS: dict(g, extra=np.zeros(len(g["q"])))}, ["unknown dataset 'extra'"])),
    "missing q": (_groups_case(lambda g: changed(g, q=None), ["missing dataset 'q'"])),
    "empty group": (_groups_case(lambda g: {CLASS: {}}, ["missing dataset"])),
    "no rows": (_groups_case(lambda g: {CLASS: {k: np.asarray(v)[:0] for k, v in g.items()}}, ["no predictions"])),
    "no groups": (_groups_case(lambda g: {}, ["no class groups"])),
    "class without truth": (_groups_case(lambda g: {"toaster": changed(g)[CLASS]}, ["no truth"])),
    # names and attributes
    "class name with newline": _class_group_name("cab\ninet"),
    "class name with spaces": _class_group_name("rm -rf x"),
    "class name starting with dash": _class_group_name("-cabinet"),
    "class name 40 chars": _class_group_name("c" * 40),
    "class name dot-dot": _class_group_name(".."),
    "method with newline": _attr_case({"method": "a\nartdata: error: fake"}, ["method name", "printable"]),
    "method 10k chars": _attr_case({"method": "m" * 10000}, ["method name", "at most 100"]),
    "method not utf-8": _attr_case({"method": np.bytes_(b"\xff\xfe")}, ["'method'", "cannot be read"]),
    "method missing": _attr_case({"method": None}, ["'method'"]),
    "method empty": _attr_case({"method": "  "}, ["'method'"]),
    "method array": _attr_case({"method": np.arange(3)}, ["'method'"]),
    "version missing": _attr_case({"format_version": None}, ["no format_version"]),
    "version 2.0": _attr_case({"format_version": "2.0"}, ["version '2.0'"]),
    "version not utf-8": _attr_case({"format_version": np.bytes_(b"\xc3\x28")}, ["'format_version'", "cannot be read"]),
    "layout not json": _mixture_case(["mixture_layout", "JSON list"], layout="[j0.q"),
    "layout object": _mixture_case(["mixture_layout", "list of column names"], layout='{"a": 1}'),
    "layout repeated": _mixture_case(["repeats column names"], layout=("j0.q", "j0.q")),
    "layout unknown column": _mixture_case(["not in the target layout"], layout=("j0.q", "j7.origin.x")),
    "dataset instead of group": (lambda c: (score_args(c, _dataset_root(c)), ["expected a class group"])),
    "nested group": _nested_group,
    # files
    "corrupt chunk": _corrupt_chunk,
    "huge declared dataset": _huge_declared,
    "huge declared mixture": _huge_mixture,
    "soft link": _soft_link,
    "external link": _external_link,
    "external storage": _external_storage,
    "truncated file": _truncated,
    "fifo": _fifo,
    "dangling symlink": _dangling,
    "missing file": _missing_preds,
    "text file": _text_preds,
    "empty file": _empty_preds,
    "directory": _dir_preds,
    # truth
    "manifest shard ../": _manifest_shard_file("../../../etc/passwd"),
    "manifest shard absolute": _manifest_shard_file("/etc/passwd"),
    "manifest shard in a subfolder": _manifest_shard_file("sub/shard-00000.h5"),
    "shard symlink outside": _shard_symlink_outside,
    "manifest class ../": _manifest_edit(lambda m: dict(m, class_name="../../x"), ["invalid class name"]),
    "manifest without class": _manifest_edit(lambda m: {k: v for k, v in m.items() if k != "class_name"}, ["no class_name"]),
    "manifest shards not a list": _manifest_edit(lambda m: dict(m, shards="shard-00000.h5"), ["corrupt manifest"]),
    "manifest list": _manifest_text(b"[1, 2]", ["not a JSON object"]),
    "manifest not json": _manifest_text(b"{oops", ["corrupt manifest"]),
    "manifest not utf-8": _manifest_text(b"\xff\xfe{}", ["corrupt manifest"]),
    "damaged shard": _damaged_shard,
    "shard joint_types garbage": _joint_types_attr,
    "truth missing": _truth_missing,
    "truth is a file": _truth_is_file,
    "truth empty folder": _truth_empty,
    "split traversal": _bad_split,
    # outputs
    "output is the predictions file": _output_is_input,
    "json and csv the same file": _outputs_same,
    "json in a missing folder": _json_missing_dir,
    "csv under a file": _json_under_file,
    "json in /proc": _json_proc,
    "json a directory": _json_dir,
    # '' was taken as no report (exit 0, nothing written); two '-' printed both reports on one stream
    "json empty name": lambda c: (score_args(c, None, "--json", ""), ["'--json'", "empty path"]),
    "csv blank name": lambda c: (score_args(c, None, "--csv", " "), ["'--csv'", "empty path"]),
    "json and csv both stdout": lambda c: (score_args(c, None, "--json", "-", "--csv", "-"), ["standard output"]),
    "require complete": _partial_required,
    # usage
    "no predictions": _usage(lambda c: ["score", "--truth", c.truth], ["PREDICTIONS"]),
    "no truth option": _usage(lambda c: ["score", c.preds()], ["--truth"]),
    "unknown option": _usage(lambda c: ["score", c.preds(), "--truth", c.truth, "--bogus"], ["--bogus"]),
}


def _dataset_root(c: Case) -> Path:
    p = c.work / "p.h5"
    with h5py.File(p, "w") as f:
        f.attrs.update(format_version=PREDICTIONS_FORMAT_VERSION, method="crafted")
        f.create_dataset(CLASS, data=np.zeros(3))
    return p


@pytest.mark.parametrize("case", list(CASES))
def test_refused_score_input(case, tiny_root, good, tmp_path):
    c = Case(tmp_path, tiny_root, good)
    args, needles = CASES[case](c)
    before = tree_snapshot(tmp_path, times=True)
    result = CliRunner().invoke(main, [str(a) for a in args])
    assert_one_line_error(result, *needles)
    assert_unchanged(tmp_path, before, times=True)  # nothing written, changed or removed (no partial outputs)


def test_a_failed_write_keeps_the_previous_report(tiny_root, good, tmp_path):
    """An existing --json is replaced only by a complete report: refused runs leave it as it was."""
    c = Case(tmp_path, tiny_root, good)
    out = c.work / "report.json"
    ok = CliRunner().invoke(main, [str(a) for a in score_args(c, None, "--json", out)])
    assert ok.exit_code == 0, ok.output
    first = out.read_bytes()
    assert json.loads(first)["metric_version"] == 3  # the current metric version
    bad = raw_write(c.work / "bad.h5", with_value(good, "q", (0, 0), 1e300))
    result = CliRunner().invoke(main, [str(a) for a in score_args(c, bad, "--json", out)])
    assert result.exit_code == 2 and out.read_bytes() == first
    assert not list(c.work.glob("*.partial"))


# ---------------------------------------------------------------- truth labels no prediction may hold
# The truth is held, as the predictions file is, to finite values within +-1e6 and non-zero
# quaternions, so ``artdata score`` never prints ``inf +/- inf deg`` or an axis position error of
# 5e40 cm with exit code 0.  NaN (a label not given, as in real captures) is scored as undefined.

def _truth_copy(tiny_root, tmp_path, change):
    """A copy of the tiny cabinet test split whose first shard has ``change(its labels)`` applied;
    (the copy, the labels as they were)."""
    copy = tmp_path / "truth" / CLASS / "test"
    shutil.copytree(tiny_root / CLASS / "test", copy)
    shard = copy / json.loads((copy / "manifest.json").read_text())["shards"][0]["file"]
    with h5py.File(shard, "r+") as f:
        arrays = {k: f[k][()] for k in FIELDS}
        name, a = change({k: v.copy() for k, v in arrays.items()})
        f[name][...] = a
    return copy, arrays


def _score_truth(tmp_path, truth, arrays):
    preds = tmp_path / "p.h5"
    write_predictions(preds, "M", {CLASS: {k: arrays[k] for k in FIELDS}})
    return CliRunner().invoke(main, ["score", str(preds), "--truth", str(truth)])


def _set(name, value, sl=(0,)):
    def change(a):
        a[name][sl] = value
        return name, a[name]
    return change


@pytest.mark.parametrize("change,needle", [
    (_set("q", np.inf), "'q'"),
    (_set("axis_pose", 3e38), "'axis_pose'"),
    (_set("geometry", -np.inf), "'geometry'"),
    (_set("axis_pose", 0.0, (0, 0, slice(3, 7))), "zero-length"),
], ids=["q inf", "pose 3e38", "geometry -inf", "zero quaternion"])
def test_a_truth_label_no_prediction_may_hold_is_one_line(tiny_root, tmp_path, change, needle):
    truth, arrays = _truth_copy(tiny_root, tmp_path, change)
    assert_one_line_error(_score_truth(tmp_path, truth, arrays), needle, "verify")


def test_a_nan_truth_label_is_still_undefined(tiny_root, tmp_path):
    truth, arrays = _truth_copy(tiny_root, tmp_path, _set("q", np.nan))
    result = _score_truth(tmp_path, truth, arrays)
    assert result.exit_code == 0, result.output


# ---------------------------------------------------------------- mixture layouts and columns

def _write_layout(path, layout) -> None:
    """A one-joint cabinet predictions file whose ``mixture_layout`` attribute is ``layout``."""
    with h5py.File(path, "w") as f:
        f.attrs.update(format_version="1.0", method="crafted")
        g = f.create_group(CLASS)
        g["sample_id"] = np.arange(2, dtype=np.int64)
        g["axis_pose"] = np.tile([1.0, 0, 0, 1, 0, 0, 0], (2, 1, 1))
        g["q"] = np.zeros((2, 1))
        g["mixture_weights"] = np.ones((2, 1))
        g["mixture_means"] = np.zeros((2, 1, 1))
        g["mixture_scales"] = np.ones((2, 1, 1))
        g.attrs["mixture_layout"] = layout


@pytest.mark.parametrize("layout", [np.array([b"\xff"], dtype="S1"), np.array([b"j0.q", b"\xc3("], dtype="S4")],
                         ids=["one", "second"])
def test_a_layout_array_that_is_not_utf8_is_one_line(tmp_path, layout):
    """Byte strings that are not UTF-8: one line naming the attribute, not a UnicodeDecodeError."""
    path = tmp_path / "p.h5"
    _write_layout(path, layout)
    with pytest.raises(DataFormatError, match="mixture_layout"):
        read_predictions(path)
    assert_one_line_error(CliRunner().invoke(main, ["score", str(path), "--truth", str(tmp_path)]), "mixture_layout")


def test_layout_bytes_given_to_validate_class(tmp_path):
    """The Python API takes the layout as bytes too (a JSON text of it)."""
    arrays = {"sample_id": np.arange(1), "axis_pose": np.array([[[0, 0, 0, 1.0, 0, 0, 0]]]), "q": np.zeros((1, 1)),
              "mixture_weights": np.ones((1, 1)), "mixture_means": np.zeros((1, 1, 1)),
              "mixture_scales": np.ones((1, 1, 1)), "mixture_layout": b'["\xff"]'}
    with pytest.raises(DataFormatError, match="UTF-8"):
        validate_class("x", arrays)


def test_a_mixture_of_no_column_is_refused(tiny_root, tmp_path):
    """A mixture naming no column: refused when written (it would score NLL 0.00 +/- 0.00)."""
    _, shards = open_split(tiny_root / "microwave" / "test")
    ids = shards[0].read("sample_id").astype(np.int64)
    n = len(ids)
    arrays = {"sample_id": ids, "axis_pose": shards[0].read("axis_pose"),
              "q": shards[0].read("q"), "mixture_weights": np.ones((n, 1)), "mixture_means": np.zeros((n, 1, 0)),
              "mixture_scales": np.ones((n, 1, 0)), "mixture_layout": []}
    with pytest.raises(UserError, match="names no column"):
        write_predictions(tmp_path / "p.h5", "crafted", {"microwave": arrays})

