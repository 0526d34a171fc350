"""The command contract: a user's mistake, whatever the command and whatever is wrong with its
input, ends in exactly one stderr line ``artdata: error: ...`` with exit code 2, prints nothing
on stdout, writes nothing (neither the output it names nor anything beside it) and leaves every
input as it was (the case's own folder and the shared input data).

Tables: click usage errors of every command (unknown options, bad values of every typed option,
bad choices, missing arguments); absurd numbers; real (ingested) splits used where they cannot
be; damaged or foreign model checkpoints; malformed real captures; and every command that reads
a file or folder against every kind of damage its input can have (missing, empty, truncated, of
the wrong type, huge, a special file, a link leading out, crafted JSON, YAML, HDF5 or checkpoint
content), each beside a control row in which the undamaged input is accepted.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import click
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from articulated_dataset.classes.registry import REVOLUTE
from articulated_dataset.cli import EXIT_ENVIRONMENT_ERROR, main
from articulated_dataset.format import open_split
from articulated_dataset.generation.urdf_import import CACHE_ENV
from helpers_core import assert_one_line_error, assert_unchanged, run_cli, split_copy_with, tree_snapshot
from helpers_real import write_capture

#: Small checkpoint settings (seconds to train on the tiny split).
TINY_MDN = dict(preset="small", width=4, blocks=(1, 1), height_px=27, width_px=48, n_components=3, batch_size=16)


# --------------------------------------------------------------------------------------
# Shared inputs (built once per module; never modified by a case)
# --------------------------------------------------------------------------------------

@dataclass
class Inputs:
    tiny: Path  # tiny_root: <class>/{train,test}
    captures: Path  # one valid cabinet capture (with labels)
    real: Path  # an ingested cabinet real split: image 0 labelled, image 1 without labels
    model: Path  # a tiny cabinet MDN checkpoint
    label: dict  # the valid capture's labels


@pytest.fixture(scope="module")
def inputs(tiny_root, tmp_path_factory) -> Inputs:
    from articulated_dataset.methods.mdn.config import TrainConfig
    from articulated_dataset.methods.mdn.train import train

    root = tmp_path_factory.mktemp("contract-inputs")
    _, shards = open_split(tiny_root / "cabinet" / "test")
    sh = shards[0]
    s0, s1 = sh.sample(0), sh.sample(3)
    label = {"q": s0["q"].tolist(), "axis_pose": s0["axis_pose"].tolist(), "geometry": s0["geometry"].tolist(),
             "object": "kitchen"}
    write_capture(root / "caps", "a", s0, sh.K, label)
    write_capture(root / "nolabels", "b", s1, sh.K, None)
    for folder, extra in (("caps", []), ("nolabels", ["--append"])):
        res = CliRunner().invoke(main, ["ingest", str(root / folder), "--class", "cabinet", "--out", str(root / "out"),
                                        "-q", *extra])
        assert res.exit_code == 0, res.output
    model = root / "cabinet.pt"
    train(tiny_root / "cabinet" / "train", model, TrainConfig(class_name="cabinet", epochs=1, **TINY_MDN), progress=False)
    return Inputs(tiny_root, root / "caps", root / "out" / "cabinet" / "real", model, label)


@dataclass
class Env:
    """What a case builds its arguments from: the shared inputs and its own empty folder."""

    inputs: Inputs
    tmp: Path

    @property
    def tiny(self) -> Path:
        return self.inputs.tiny

    def split(self, class_name: str = "cabinet", split: str = "test") -> str:
        return str(self.tiny / class_name / split)

    def capture(self, *, labels=None, camera=None, depth=None, mask=None) -> str:
        """A private copy of the valid capture folder with some files replaced."""
        dst = self.tmp / "caps"
        shutil.copytree(self.inputs.captures, dst)
        if labels is not None:
            data = labels if isinstance(labels, (str, bytes)) else json.dumps(labels)
            (dst / "a.labels.json").write_bytes(data if isinstance(data, bytes) else data.encode())
        if camera is not None:
            (dst / "camera.json").write_text(camera if isinstance(camera, str) else json.dumps(camera))
        if depth is not None:
            depth(dst / "a.png")
        if mask is not None:
            mask(dst / "a.mask.png")
        return str(dst)

    def checkpoint(self, change: Callable[[dict], object]) -> str:
        """A private copy of the tiny checkpoint with ``change(ckpt)`` applied (its return value,
        if not None, is saved instead)."""
        import torch

        ckpt = torch.load(self.inputs.model, weights_only=True)
        replaced = change(ckpt)
        path = self.tmp / "bad.pt"
        torch.save(ckpt if replaced is None else replaced, path)
        return str(path)


@pytest.fixture()
def env(inputs, tmp_path, monkeypatch) -> Env:
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)  # default outputs (e.g. --out data) would land here
    return Env(inputs, work)


def run_case(env: Env, args: list, needle: str | None) -> None:
    """``artdata ARGS`` is refused by the contract: one line holding ``needle``, nothing written
    or changed (the case's folder byte for byte, the shared inputs by size and time)."""
    shared = [env.tiny, env.inputs.real.parent.parent.parent]
    before = [tree_snapshot(p, digests=False) for p in shared]
    own = tree_snapshot(env.tmp)
    result = CliRunner().invoke(main, [str(a) for a in args])
    assert_one_line_error(result, *([needle] if needle else []))
    assert_unchanged(env.tmp, own)
    for root, b in zip(shared, before):
        assert_unchanged(root, b, digests=False)


# --------------------------------------------------------------------------------------
# 1. Click usage errors of every command
# --------------------------------------------------------------------------------------

def _commands(group: click.Group = main, path: tuple = ()):
    for name in group.list_commands(None):  # the CLI imports a command's module when asked for it
        cmd = group.get_command(None, name)
        if isinstance(cmd, click.Group):
            yield from _commands(cmd, path + (name,))
        else:
            yield path + (name,), cmd


#: A value click's conversion refuses, per option type.
_BAD_VALUES = {click.INT: "abc", click.FLOAT: "1.5.2"}


def _usage_cases():
    cases = []
    for path, cmd in _commands():
        name = " ".join(path)
        cases.append(pytest.param([*path, "--no-such-option"], "No such option", id=f"{name}:unknown-option"))
        if any(p.required for p in cmd.params):
            cases.append(pytest.param(list(path), "(see artdata " + name + " --help)", id=f"{name}:no-arguments"))
        for p in cmd.params:
            if not isinstance(p, click.Option) or p.is_flag or p.name == "help":
                continue
            opt = p.opts[0]
            if isinstance(p.type, click.Choice):
                cases.append(pytest.param([*path, opt, "not-a-choice"], f"'{opt}'", id=f"{name}:{opt}-choice"))
            elif p.type in _BAD_VALUES:
                cases.append(pytest.param([*path, opt, _BAD_VALUES[p.type]], f"'{opt}'", id=f"{name}:{opt}-type"))
            elif p.type.name == "class":
                cases.append(pytest.param([*path, opt, "sofa"], "sofa", id=f"{name}:{opt}-class"))
            elif isinstance(p.type, click.Path):  # '' named no path: generate --out '' wrote into the working folder
                cases.append(pytest.param([*path, opt, ""], f"'{opt}': an empty path", id=f"{name}:{opt}-empty-path"))
            if opt in ("--out", "--n", "--workers", "--class"):
                # (click gives this error no command: the hint names it from the command line)
                cases.append(pytest.param([*path, opt], f"'{opt}' requires an argument. (see artdata {name} --help)",
                                          id=f"{name}:{opt}-without-value"))
    cases.append(pytest.param(["no-such-command"], "No such command", id="unknown-command"))
    cases.append(pytest.param(["baseline"], "missing command", id="baseline:no-subcommand"))
    return cases


@pytest.mark.parametrize("args, needle", _usage_cases())
def test_usage_errors_are_one_line(env, args, needle):
    run_case(env, args, needle)


# --------------------------------------------------------------------------------------
# 2. Absurd numbers, real splits where they cannot be used, bad checkpoints, bad captures
# --------------------------------------------------------------------------------------

def _set(d: dict, key: str, value):
    d[key] = value


def _nested(key: str, sub: str, value):
    def change(ckpt):
        ckpt[key][sub] = value
    return change


def _save_png(values):
    return lambda path: Image.fromarray(np.asarray(values(np.array(Image.open(path))))).save(path)


CASES: dict[str, tuple[Callable[[Env], list], str]] = {
    # plan
    "plan:step-1e-12": (lambda e: ["plan", e.split(), "--index", 0, "--step", "1e-12deg", "-q"], "waypoints"),
    "plan:step-zero": (lambda e: ["plan", e.split(), "--index", 0, "--step", "0deg", "-q"], "--step"),
    "plan:step-negative": (lambda e: ["plan", e.split(), "--index", 0, "--step", "-1deg", "-q"], "--step must be positive"),
    "plan:step-wrong-unit": (lambda e: ["plan", e.split(), "--index", 0, "--step", "1cm", "-q"], "prismatic"),
    "plan:target-overflow": (lambda e: ["plan", e.split(), "--index", 0, "--target", "1e999deg", "-q"], "too large"),
    "plan:target-text": (lambda e: ["plan", e.split(), "--index", 0, "--target", "wide", "-q"], "cannot parse"),
    "plan:index-negative": (lambda e: ["plan", e.split(), "--index", -1, "-q"], "--index"),
    "plan:index-huge": (lambda e: ["plan", e.split(), "--index", 10**12, "-q"], "out of range"),
    "plan:joint-huge": (lambda e: ["plan", e.split(), "--index", 0, "--joint", 7, "-q"], "--joint 7"),
    "plan:joint-negative": (lambda e: ["plan", e.split(), "--index", 0, "--joint", -1, "-q"], "--joint -1"),
    "plan:class-folder": (lambda e: ["plan", e.tiny / "cabinet", "--index", 0, "-q"], "splits"),
    "plan:out-in-proc": (lambda e: ["plan", e.split(), "--index", 0, "-q", "--out", "/proc/artdata-plan.json"],
                         "cannot write"),
    "plan:out-stdout": (lambda e: ["plan", e.split(), "--index", 0, "-q", "--out", "-"],
                        "give a file name"),  # it wrote a file named '-' where '-' means standard output elsewhere
    "plan:out-dev-null": (lambda e: ["plan", e.split(), "--index", 0, "-q", "--out", "/dev/null"],
                          "not a regular file"),  # refused before the plan is made and printed, not after
    "plan:out-under-a-file": (lambda e: ["plan", e.split(), "--index", 0, "-q", "--out",
                                         _write(e.tmp / "f", b"x") + "/plan.json"], "not a directory"),
    "plan:nan-axis-label": (lambda e: ["plan", _nan_axis_copy(e), "--index", 0, "-q"], "not finite"),
    # damaged object pose labels: a ValueError from the rebuild (a traceback)
    **{f"plan:{name}": (lambda e, field=field, value=value: ["plan", _label_copy(e, field, value), "--index", 0,
                                                              "-q"], "run 'artdata verify'")
       for name, field, value in [("nan-object-pose", "object_pose", np.nan), ("far-object-pose", "object_pose", 1e30),
                                  ("nan-object-yaw", "object_yaw", np.nan), ("negative-object-index", "object_index", -1)]},
    "plan:missing-data": (lambda e: ["plan", e.tmp / "nope", "--index", 0, "-q"], None),
    "plan:seed-negative": (lambda e: ["plan", e.split(), "--index", 0, "--model", "mdn-small", "--simulate",
                                      "--closed-loop", "--seed", -5, "-q"], "--seed must be >= 0"),
    # show
    "show:dpi-100000": (lambda e: ["show", e.split(), "--out", "g.png", "--dpi", 100000, "-q"], "figure"),
    "show:dpi-zero": (lambda e: ["show", e.split(), "--out", "g.png", "--dpi", 0, "-q"], "--dpi"),
    "show:dpi-1": (lambda e: ["show", e.split(), "--out", "g.png", "--dpi", 1, "-q"], "--dpi must be at least"),
    "show:n-zero": (lambda e: ["show", e.split(), "--out", "g.png", "--n", 0, "-q"], "positive"),
    "show:cols-zero": (lambda e: ["show", e.split(), "--out", "g.png", "--cols", 0, "-q"], "positive"),
    "show:objects-reversed": (lambda e: ["show", e.split(), "--out", "g.png", "--objects", "5-3", "-q"], "--objects"),
    "show:images-text": (lambda e: ["show", e.split(), "--out", "g.png", "--images", "a,b", "-q"], "--images"),
    "show:object-missing": (lambda e: ["show", e.split(), "--out", "g.png", "--objects", "99", "-q"], "object 99"),
    "show:unknown-format": (lambda e: ["show", e.split(), "--out", "g.xyz", "-q"], "format"),
    # baselines
    "nn:block-1000": (lambda e: ["baseline", "nn", "--train", e.split(split="train"), "--test", e.split(), "--out", "p.h5",
                                 "--block", 1000, "-q"], "--block 1000"),
    "nn:block-zero": (lambda e: ["baseline", "nn", "--train", e.split(split="train"), "--test", e.split(), "--out", "p.h5",
                                 "--block", 0, "-q"], "--block"),
    "nn:workers-zero": (lambda e: ["baseline", "nn", "--train", e.split(split="train"), "--test", e.split(), "--out", "p.h5",
                                   "--workers", 0, "-q"], "--workers"),
    "nn:class-mismatch": (lambda e: ["baseline", "nn", "--train", e.split(split="train"), "--test", e.split("drawer"),
                                     "--out", "p.h5", "-q"], "class mismatch"),
    "icp:limit-zero": (lambda e: ["baseline", "icp", "--train", e.split(split="train"), "--test", e.split(), "--out", "p.h5",
                                  "--limit", 0, "-q"], "--limit"),
    "icp:mean-object-is-test": (lambda e: ["baseline", "icp", "--train", e.split(split="train"), "--test", e.split(),
                                           "--out", "p.h5", "--mean-object", e.split(), "-q"], "not a mean object"),
    "mean:missing-train": (lambda e: ["baseline", "mean", "--train", e.tmp / "nope", "--test", e.split(), "--out", "p.h5"],
                           "not found"),
    # train
    **{f"train:{name}": (lambda e, extra=extra: ["train", "--model", "mdn", "--class", "cabinet", e.split(split="train"),
                                                 "--out", "m.pt", "-q", *extra], needle)
       for name, extra, needle in [
           ("lr-nan", ["--lr", "nan"], "--lr"), ("lr-inf", ["--lr", "inf"], "--lr"), ("lr-negative", ["--lr", "-1e-3"], "--lr"),
           ("lr-10", ["--lr", "10"], "--lr"), ("epochs-zero", ["--epochs", "0"], "--epochs"),
           ("epochs-negative", ["--epochs", "-3"], "--epochs"), ("batch-zero", ["--batch-size", "0"], "--batch-size"),
           ("components-zero", ["--components", "0"], "--components"),
           ("seed-negative", ["--seed", "-1"], "--seed"), ("seed-huge", ["--seed", str(2**40)], "--seed"),
           ("val-fraction-nan", ["--val-fraction", "nan"], "--val-fraction"),
           ("val-fraction-one", ["--val-fraction", "1"], "--val-fraction"),
           ("max-objects-zero", ["--max-objects", "0"], "--max-objects"), ("threads-zero", ["--threads", "0"], "--threads"),
           ("threads-huge", ["--threads", str(10**9)], "--threads"),
           ("device-tpu", ["--device", "tpu"], "--device"), ("components-huge", ["--components", str(10**12)], "--components must be at most"),
       ]},
    "train:class-mismatch": (lambda e: ["train", "--model", "mdn", "--class", "drawer", e.split(split="train"), "--out", "m.pt", "-q"],
                             "not 'drawer'"),
    "train:resume-nothing": (lambda e: ["train", "--model", "mdn", "--class", "cabinet", e.split(split="train"), "--out", "m.pt",
                                        "--resume", "-q"], "--resume"),
    "train:class-wrong-case": (lambda e: ["train", "--model", "mdn", "--class", "Cabinet", e.split(split="train"), "--out",
                                          "m.pt", "-q"], "did you mean 'cabinet'"),
    # predict: options and checkpoints
    "predict:threads-huge": (lambda e: ["predict", "--model", e.inputs.model, e.split(), "--out", "p.h5",
                                        "--threads", 10**9, "-q"], "--threads"),
    "predict:other-class": (lambda e: ["predict", "--model", e.inputs.model, e.split("drawer"), "--out", "p.h5",
                                       "-q"], "'cabinet'"),
    **{f"checkpoint:{name}": (lambda e, change=change: ["predict", "--model", e.checkpoint(change), e.split(),
                                                        "--out", "p.h5", "-q"], needle)
       for name, change, needle in [
           ("not-a-dict", lambda c: [1, 2, 3], None),
           ("no-format", lambda c: c.pop("format"), None),
           ("version-text", lambda c: _set(c, "version", "abc"), "version"),
           ("version-2", lambda c: _set(c, "version", 2), "version"),
           ("missing-stats", lambda c: c.pop("norm_stats"), None),
           ("class-number", lambda c: _set(c, "class_name", 5), None),
           ("class-unknown", lambda c: _set(c, "class_name", "sofa"), "sofa"),
           ("layout", lambda c: _set(c, "layout_names", ["x"]), "target layout"),
           ("train-config-key", _nested("train_config", "bogus", 1), "train_config"),
           ("train-config-lr", _nested("train_config", "lr", float("nan")), "--lr"),
           ("train-config-epochs-text", _nested("train_config", "epochs", "30"), "--epochs"),
           ("model-width-huge", _nested("model_config", "width", 10**9), "model_config"),
           ("model-config-missing", lambda c: c["model_config"].pop("blocks"), None),
           ("input-config", _nested("input_config", "height_px", 10**6), "input_config"),
           ("stats-std-zero", lambda c: _set(c["norm_stats"], "std", [0.0] * len(c["norm_stats"]["std"])), None),
           ("stats-mean-nan", lambda c: _set(c["norm_stats"], "mean", [float("nan")] * len(c["norm_stats"]["mean"])),
            None),
           ("stats-short", lambda c: _set(c["norm_stats"], "mean", [0.0]), None),
           ("weights-nan", lambda c: next(v for v in c["model_state"].values() if v.is_floating_point()).fill_(float("nan")),
            None),
           ("weights-text", lambda c: _set(c, "model_state", {"w": "abc"}), "model_state"),
           ("active-columns", lambda c: _set(c, "active_columns", [10**6]), "active_columns"),
           ("epoch-negative", lambda c: _set(c, "epoch", -1), "epoch"),
       ]},
    "checkpoint:not-torch": (lambda e: ["predict", "--model", _write(e.tmp / "x.pt", b"not a checkpoint"),
                                        e.split(), "--out", "p.h5", "-q"], "not a readable model checkpoint"),
    "checkpoint:empty": (lambda e: ["predict", "--model", _write(e.tmp / "x.pt", b""), e.split(), "--out", "p.h5",
                                    "-q"], "not a readable model checkpoint"),
    "checkpoint:truncated": (lambda e: ["predict", "--model", _write(e.tmp / "x.pt", e.inputs.model.read_bytes()[:5000]),
                                        e.split(), "--out", "p.h5", "-q"], "not a readable model checkpoint"),
    "checkpoint:pickled-object": (lambda e: ["predict", "--model", _pickled(e.tmp / "x.pt"), e.split(),
                                             "--out", "p.h5", "-q"], "not a readable model checkpoint"),
    "checkpoint:missing": (lambda e: ["predict", "--model", e.tmp / "none.pt", e.split(), "--out", "p.h5", "-q"],
                           "none.pt"),
    # verify
    "verify:workers-zero": (lambda e: ["verify", e.split(), "--workers", 0], "--workers"),
    "verify:workers-negative": (lambda e: ["verify", e.split(), "--workers", -4], "--workers"),
    "verify:missing": (lambda e: ["verify", e.tmp / "nope"], "no such directory"),
    # real splits where they cannot be used
    "real:plan-simulate": (lambda e: ["plan", e.inputs.real, "--index", 0, "--simulate", "-q"], "real capture"),
    "real:plan-no-labels": (lambda e: ["plan", e.inputs.real, "--index", 1, "-q"], "lack axis_pose, q"),
    "real:mean-train": (lambda e: ["baseline", "mean", "--train", e.inputs.real, "--test", e.split(), "--out", "p.h5"],
                        "real captures"),
    "real:nn-train": (lambda e: ["baseline", "nn", "--train", e.inputs.real, "--test", e.split(), "--out", "p.h5", "-q"],
                      "real captures"),
    "real:icp-mean-object": (lambda e: ["baseline", "icp", "--train", e.split(split="train"), "--test", e.split(),
                                        "--out", "p.h5", "--mean-object", e.inputs.real, "-q"], "real captures"),
    "real:train": (lambda e: ["train", "--model", "mdn", "--class", "cabinet", e.inputs.real, "--out", "m.pt", "-q"],
                   "real captures"),
}


def _write(path: Path, data: bytes) -> str:
    path.write_bytes(data)
    return str(path)


class _Payload:
    """An object whose unpickling would run code: weights_only loading must refuse it."""

    def __reduce__(self):
        return (os.system, ("touch pwned",))


def _pickled(path: Path) -> str:
    import torch

    torch.save({"format": "artdata-mdn", "payload": _Payload()}, path)
    return str(path)


def _manifest(folder: Path, manifest: dict) -> str:
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return str(folder)


def _nan_axis_copy(e: Env) -> Path:
    """A copy of the cabinet test split whose first image's axis origin is NaN."""
    import h5py

    dst = e.tmp / "nan" / "cabinet" / "test"
    shutil.copytree(e.tiny / "cabinet" / "test", dst)
    with h5py.File(dst / "shard-00000.h5", "r+") as f:
        pose = f["axis_pose"][()]
        pose[0, 0, 0] = np.nan
        f["axis_pose"][...] = pose
    return dst


def _label_copy(e: Env, field: str, value) -> Path:
    """A copy of the cabinet test split whose label ``field`` is ``value`` in every image."""
    return split_copy_with(e.tiny / "cabinet" / "test", e.tmp / "damaged" / "cabinet" / "test", field, value)


def _cloud(e: Env, body: bytes) -> list:
    """A point-cloud capture ``c.pcd`` (x, y, z fields, then ``body``) with the training camera."""
    folder = e.tmp / "cloud"
    folder.mkdir()
    (folder / "c.pcd").write_bytes(b"FIELDS x y z\n" + body)
    (folder / "camera.json").write_text(json.dumps(_CAMERA))
    return _ingest(e, str(folder / "c.pcd"))


def _corrupt_real(e: Env) -> Path:
    """A copy of the real split whose manifest's real record lists objects as a string."""
    root = e.tmp / "realcopy"
    shutil.copytree(e.inputs.real, root / "cabinet" / "real")
    path = root / "cabinet" / "real" / "manifest.json"
    m = json.loads(path.read_text())
    m["real"]["objects"] = "kitchen"
    path.write_text(json.dumps(m))
    return root


def _ingest(e: Env, folder: str, *extra) -> list:
    return ["ingest", folder, "--class", "cabinet", "--out", e.tmp / "out", "-q", *extra]


def _label(e: Env, **changes) -> dict:
    return {**e.inputs.label, **changes}


_CAMERA = {"fx": 100.0, "fy": 100.0, "cx": 95.5, "cy": 53.5, "width": 192, "height": 108}
INGEST_CASES: dict[str, tuple[Callable[[Env], list], str]] = {
    **{f"ingest:fx-{fx}": (lambda e, fx=fx: _ingest(e, e.capture(), "--fx", fx, "--fy", fx, "--cx", 95.5, "--cy", 53.5),
                           needle)
       for fx, needle in [("1e308", "field of view"), ("1e6", "field of view"), ("0.001", "field of view"),
                          ("0", "positive"), ("-100", "positive"), ("nan", "finite"), ("inf", "finite")]},
    "ingest:cx-outside": (lambda e: _ingest(e, e.capture(), "--fx", 100, "--fy", 100, "--cx", 5000, "--cy", 53.5),
                          "principal point"),
    "ingest:partial-intrinsics": (lambda e: _ingest(e, e.capture(), "--fx", 100), "go together"),
    **{f"ingest:camera-{name}": (lambda e, cam=cam: _ingest(e, e.capture(camera=cam)), needle)
       for name, cam, needle in [
           ("fx-1e308", {**_CAMERA, "fx": 1e308}, "field of view"), ("fx-text", {**_CAMERA, "fx": "100"}, "numbers"),
           ("fx-bool", {**_CAMERA, "fx": True}, "numbers"), ("fx-list", {**_CAMERA, "fx": [100, 1]}, "one number"),
           ("width-text", {**_CAMERA, "width": "192"}, "whole numbers"),
           ("width-float", {**_CAMERA, "width": 192.5}, "whole numbers"),
           ("width-zero", {**_CAMERA, "width": 0}, "frame"), ("size-huge", {**_CAMERA, "width": 10**6, "height": 10**6},
                                                             "frame"),
           ("size-mismatch", {**_CAMERA, "width": 512, "height": 424}, "camera file"),
           ("K-eight", {"K": [1] * 8}, "9 numbers"), ("K-text", {"K": ["a"] * 9}, "numbers"),
           ("K-skew", {"K": [100, 5, 95.5, 0, 100, 53.5, 0, 0, 1]}, "no skew"),
           ("none", {"width": 192}, "no intrinsics"), ("list", "[1, 2]", "mapping"), ("not-json", "{fx: 1", "cannot parse"),
       ]},
    "ingest:png-in-metres": (lambda e: _ingest(e, e.capture(depth=_save_png(
        lambda a: np.rint(a / 1000.0).astype(np.uint16)))), "--depth-units m"),
    "ingest:png-8-bit": (lambda e: _ingest(e, e.capture(depth=_save_png(lambda a: (a > 0).astype(np.uint8)))), "16-bit"),
    "ingest:mask-size": (lambda e: _ingest(e, e.capture(mask=_save_png(lambda a: a[:10, :10]))), "mask is 10x10"),
    "ingest:mask-values": (lambda e: _ingest(e, e.capture(mask=_save_png(lambda a: np.full_like(a, 9)))), "neither binary"),
    "ingest:mask-empty": (lambda e: _ingest(e, e.capture(mask=_save_png(lambda a: np.zeros_like(a)))), "no object pixel"),
    **{f"ingest:labels-{name}": (lambda e, change=change: _ingest(e, e.capture(labels=change(e))), needle)
       for name, change, needle in [
           ("q-minus-5", lambda e: _label(e, q=[-5.0]), "joint range"), ("q-100", lambda e: _label(e, q=[100.0]), "joint range"),
           ("q-nan", lambda e: '{"q": [NaN]}', "NaN"),
           ("q-infinity", lambda e: '{"q": [Infinity]}', "NaN or infinite"),
           ("q-null-element", lambda e: {"q": [None]}, "numbers"), ("q-text", lambda e: {"q": ["0.1"]}, "numbers"),
           ("q-bool", lambda e: {"q": [True]}, "numbers"), ("q-scalar", lambda e: {"q": 0.1}, "shape"),
           ("q-two-joints", lambda e: {"q": [0.1, 0.2]}, "shape"),
           ("geometry-negative", lambda e: {"geometry": [-0.5, 0.6, 0.7, 0]}, "body dimensions"),
           ("geometry-huge", lambda e: {"geometry": [0.5, 60.0, 0.7, 0]}, "body dimensions"),
           ("chirality", lambda e: {"geometry": [0.5, 0.6, 0.7, 0.5]}, "chirality"),
           ("object-far", lambda e: {"object_pose": [500.0, 0, 0, 1, 0, 0, 0]}, "20 m"),
           ("quaternion-norm", lambda e: {"object_pose": [1.5, 0, 0, 5, 0, 0, 0]}, "unit quaternion"),
           ("quaternion-zero", lambda e: {"axis_pose": [[1.5, 0, 0, 0, 0, 0, 0]]}, "zero length"),
           ("yaw-text", lambda e: {"object_yaw": "abc"}, "numbers"),
           ("yaw-disagrees", lambda e: {"object_pose": [1.5, 0, 0, 1, 0, 0, 0], "object_yaw": 1.0}, "disagrees"),
           ("origin-far", lambda e: {"axis_origin": [[0, 0, 1e6]]}, "20 m"),
           ("unknown-key", lambda e: {"q": [0.1], "qq": 1}, "unknown key"),
           ("frame", lambda e: {"frame": "world"}, "unknown frame"), ("frame-list", lambda e: {"frame": ["camera"]}, "frame"),
           ("class", lambda e: {"class": "drawer"}, "not 'cabinet'"),
           ("object-number", lambda e: {"object": 5}, "'object'"),
           ("object-newline", lambda e: {"object": "a\nb"}, "printable name"),  # stored in the manifest, printed
           ("object-escape", lambda e: {"object": "\x1b[2J"}, "printable name"),
           ("object-long", lambda e: {"object": "x" * 10_000}, "at most 256"),
           ("top-level-list", lambda e: "[1, 2]", "mapping"), ("not-json", lambda e: "{q: [0", "cannot parse"),
           ("not-utf8", lambda e: b'{"q": [0.1], "object": "\xff"}', "UTF-8"),
       ]},
    "ingest:source-size-zero": (lambda e: _ingest(e, e.capture(), "--source-size", "0x0"), "--source-size"),
    "ingest:source-size-huge": (lambda e: _ingest(e, e.capture(), "--source-size", "100000x100000"), "--source-size"),
    "ingest:source-size-text": (lambda e: _ingest(e, e.capture(), "--source-size", "wide"), "--source-size"),
    "ingest:training-size-huge": (lambda e: _ingest(e, e.capture(), "--width", 10**6, "--height", 10**6), "memory"),
    "ingest:training-vfov-tiny": (lambda e: _ingest(e, e.capture(), "--vfov", "1e-9"), "field of view"),
    "ingest:training-vfov-180": (lambda e: _ingest(e, e.capture(), "--vfov", "180"), None),
    "ingest:crop-margin-nan": (lambda e: _ingest(e, e.capture(), "--crop-margin", "nan"), "crop margin"),
    "ingest:like-missing": (lambda e: _ingest(e, e.capture(), "--like", e.tmp / "nope"), "no such directory"),
    "ingest:like-no-camera": (lambda e: _ingest(e, e.capture(), "--like", _manifest(e.tmp / "x" / "cabinet" / "test", {
        "format_version": "1.0", "class_name": "cabinet", "split": "test", "shards": [],
        "config": {"camera": {"width_px": "192"}}})), "no readable camera"),
    **{f"ingest:pcd-{name}": (lambda e, body=body: _cloud(e, body), needle)
       for name, body, needle in [
           ("type", b"SIZE 4 4 4\nTYPE X F F\nCOUNT 1 1 1\nPOINTS 1\nDATA binary\n123456789012", "malformed PCD header"),
           ("size", b"SIZE 3 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1\nDATA binary\n123456789012", "malformed PCD header"),
           ("count-zero", b"SIZE 4 4 4\nTYPE F F F\nCOUNT 0 1 1\nPOINTS 1\nDATA binary\n123456789012",
            "malformed PCD header"),
           ("short-size", b"SIZE 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1\nDATA binary\n123456789012", "malformed PCD header"),
           ("points-negative", b"SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS -1\nDATA binary\n1234", "malformed PCD header"),
           ("points-huge", b"SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1000000000000\nDATA binary\n1234", "shorter"),
           ("ascii-columns", b"SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1\nDATA ascii\n1 2\n", "2 values"),
           ("ascii-bytes", b"SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1\nDATA ascii\n\xff\n", "malformed PCD data"),
           ("ascii-empty", b"SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 3\nDATA ascii\n", "no finite points"),
           ("compressed", b"SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 1\nDATA binary_compressed\n1234", "not supported"),
           ("no-header-end", b"SIZE 4 4 4\nTYPE F F F", "truncated"),
       ]},
    "ingest:append-corrupt-record": (lambda e: _ingest(e, e.capture(), "--append", "--out", _corrupt_real(e)),
                                     "corrupt real-split record"),
    "ingest:unknown-class": (lambda e: ["ingest", e.capture(), "--class", "sofa", "--out", e.tmp / "out", "-q"], "sofa"),
    "ingest:class-wrong-case": (lambda e: ["ingest", e.capture(), "--class", "Drawer", "--out", e.tmp / "out", "-q"],
                                "did you mean 'drawer'"),
    "ingest:missing-capture": (lambda e: _ingest(e, str(e.tmp / "nope.png")), "no such file"),
    "ingest:existing-split": (lambda e: ["ingest", e.capture(), "--class", "cabinet", "--out",
                                         e.inputs.real.parent.parent, "-q"], "already holds data"),
}


@pytest.mark.parametrize("name", list(CASES) + list(INGEST_CASES))
def test_refused_input_is_one_line(env, name):
    build, needle = CASES.get(name) or INGEST_CASES[name]
    run_case(env, build(env), needle)
    assert not (env.tmp / "pwned").exists()


# --------------------------------------------------------------------------------------
# 3. A machine without a GL backend: commands that do not render still work
# --------------------------------------------------------------------------------------

def test_without_gl_only_rendering_commands_stop(tmp_path):
    env = {**os.environ, "MUJOCO_GL": "no-such-backend"}
    code = "from articulated_dataset.cli import main; main()"
    ok = subprocess.run([sys.executable, "-c", code, "score", "--help"], env=env, capture_output=True, text=True)
    assert ok.returncode == 0 and "Score PREDICTIONS" in ok.stdout, ok.stderr
    bad = subprocess.run([sys.executable, "-c", code, "generate", "--class", "drawer", "--n", "1", "--out", str(tmp_path)],
                         env=env, capture_output=True, text=True)
    assert_one_line_error(bad, "MUJOCO_GL='no-such-backend'", code=EXIT_ENVIRONMENT_ERROR)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------
# 4. The legitimate uses of a real split next to the refused ones above
# --------------------------------------------------------------------------------------

def test_real_split_plans_from_its_labels(env):
    """Image 0 has q, axis_pose and geometry but no part_offset: the handle is placed from the
    geometry, exactly as manipulation.grasp_pose_from_estimate does with part_offset None."""
    from articulated_dataset import manipulation as M

    res = CliRunner().invoke(main, ["plan", str(env.inputs.real), "--index", "0", "-q", "--out", "plan.json"])
    assert res.exit_code == 0, res.output
    plan = json.loads((env.tmp / "plan.json").read_text())
    label = env.inputs.label
    want = M.grasp_pose_from_estimate(label["axis_pose"][0], None, label["geometry"], REVOLUTE, label["q"][0])
    np.testing.assert_allclose(plan["grasp_pose"], want, atol=1e-5)  # float32 storage of the labels
    assert plan["q_true"] == pytest.approx(label["q"][0], abs=1e-6) and plan["source"] == "truth"


def test_real_split_is_test_data_for_the_baselines(env):
    res = CliRunner().invoke(main, ["baseline", "mean", "--train", env.split(split="train"), "--test", str(env.inputs.real),
                                    "--out", "p.h5", "-q"])
    assert res.exit_code == 0, res.output
    from articulated_dataset.benchmark.predictions import read_predictions
    from articulated_dataset.ingest.write import real_sample_id

    _, per_class = read_predictions(env.tmp / "p.h5")
    ids = per_class["cabinet"]["sample_id"].tolist()
    assert ids == [real_sample_id("cabinet", "real", "a"), real_sample_id("cabinet", "real", "b")]


def test_a_checkpoint_that_would_run_code_is_refused_without_advice_to_run_it(tmp_path, monkeypatch):
    """torch's own message advises loading with weights_only=False; the error names what was
    refused (the global) instead, and nothing runs."""
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.methods.mdn.checkpoint import read_checkpoint_file

    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError) as err:
        read_checkpoint_file(_pickled(tmp_path / "x.pt"))
    message = str(err.value)
    assert "not a readable model checkpoint" in message and "system" in message, message
    assert "weights_only" not in message and "\n" not in message, message
    assert not (tmp_path / "pwned").exists()


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux)")
def test_a_full_output_is_one_line():
    """Standard output on a full device (as a full disk): one line and the environment's exit code,
    not a traceback from inside click's echo."""
    with open("/dev/full", "w") as full:
        r = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", "models"], stdout=full,
                           stderr=subprocess.PIPE, text=True, timeout=120)
    assert_one_line_error(r, "No space left", code=EXIT_ENVIRONMENT_ERROR)


# --------------------------------------------------------------------------------------
# 5. Every command that reads a file or folder x every kind of damage its input can have
# --------------------------------------------------------------------------------------
# A slot is one kind of input (a split folder, a predictions file, a checkpoint, ...): how a
# case makes its private valid copy, the commands that read it and the damage it can have.  A
# damage turns the valid copy into what the command is given and names what the error line
# must name (None: the line need only follow the contract).  Each (slot, command) also runs
# once on the undamaged copy, which must be accepted: the refusals are the damage's doing.

#: Seconds a command may take on a damaged input before it counts as hung (a FIFO opened for
#: reading waits for a writer that never comes).
HANG_S = 60
#: Images a crafted shard declares (unwritten chunks: a file of kilobytes).
DECLARED_ROWS = 10**8
#: Rows a crafted predictions file declares: more memory than any machine has.
DECLARED_PREDICTION_ROWS = 10**13
#: Side (px) of the image a crafted PNG header declares (10^10 pixels).
DECLARED_SIDE_PX = 100_000
#: Nesting of crafted JSON, far past Python's recursion limit.
DEEP = 100_000
#: The class of every valid input in this section, and its tiny split.
DAMAGE_CLASS = "microwave"


@dataclass
class Valid:
    """Undamaged inputs of the damage table, built once (never modified by a case)."""

    split: Path  # the tiny microwave test split
    train: Path  # the tiny microwave train split
    predictions: Path  # predictions for ``split`` (its own labels)
    checkpoint: Path  # the shipped dense microwave model as a .pt checkpoint
    capture: Path  # one capture of ``split``'s first image: a.png (mm), a.mask.png, camera.json, a.labels.json
    export: Path  # ``split`` exported to EXR


@pytest.fixture(scope="module")
def valid(tiny_root, tmp_path_factory) -> Valid:
    import torch

    from articulated_dataset.benchmark import write_predictions
    from articulated_dataset.methods.mdn.checkpoint import read_checkpoint_file
    from articulated_dataset.methods.shipped import WEIGHTS_DIR
    from articulated_dataset.tools.exr import export_split

    root = tmp_path_factory.mktemp("contract-valid")
    split = tiny_root / DAMAGE_CLASS / "test"
    _, shards = open_split(split)
    fields = ("sample_id", "axis_pose", "q", "geometry", "part_offset")
    write_predictions(root / "p.h5", "truth", {DAMAGE_CLASS: {k: np.concatenate([s.read(k) for s in shards])
                                                              for k in fields}})
    torch.save(dict(read_checkpoint_file(WEIGHTS_DIR / f"dense-{DAMAGE_CLASS}.safetensors")), root / "m.pt")
    sh = shards[0]
    s0 = sh.sample(0)
    write_capture(root / "caps", "a", s0, sh.K, {"q": s0["q"].tolist(), "axis_pose": s0["axis_pose"].tolist()})
    for s in shards:
        s.close()
    export = export_split(split, root / "exp" / DAMAGE_CLASS / "test")
    return Valid(split, tiny_root / DAMAGE_CLASS / "train", root / "p.h5", root / "m.pt", root / "caps", export)


# ---- damage: each takes the valid private copy and returns (what the command gets, needle)

def _missing(p: Path):
    shutil.rmtree(p) if p.is_dir() else p.unlink()
    return p, p.name


def _empty(p: Path):
    if p.is_dir():
        shutil.rmtree(p)
        p.mkdir()
        return p, None
    p.write_bytes(b"")
    return p, p.name


def _truncated(p: Path):
    data = p.read_bytes()
    p.write_bytes(data[:len(data) // 3])
    return p, p.name


def _folder_for_file(p: Path):
    p.unlink()
    p.mkdir()
    (p / "x").write_text("x")
    return p, p.name


def _file_for_folder(p: Path):
    shutil.rmtree(p)
    p.write_text("a file, not a folder")
    return p, p.name


def _fifo(p: Path):
    shutil.rmtree(p) if p.is_dir() else p.unlink()
    os.mkfifo(p)
    return p, p.name


def _text(p: Path):
    p.write_text("plain text, not this file's format\n")
    return p, p.name


def _binary(p: Path):
    p.write_bytes(bytes(range(256)) * 16)
    return p, p.name


def _in(name: str, damage: Callable):
    """``damage`` of the file ``name`` inside the folder input; the command is given the folder."""
    def apply(p: Path):
        _, needle = damage(p / name)
        return p, needle
    return apply


def _link_out(name: str):
    """The folder's file ``name`` replaced by a link to a valid copy of it outside the folder."""
    def apply(p: Path):
        outside = p.parent / f"outside-{Path(name).name}"
        shutil.move(p / name, outside)
        (p / name).symlink_to(outside)
        return p, "outside"
    return apply


def _json(name: str | None, text: str):
    """The JSON file ``name`` of the folder input (None: the file input itself) holding ``text``."""
    def apply(p: Path):
        f = p if name is None else p / name
        f.write_text(text)
        return p, f.name
    return apply


def _manifest_edit(edit: Callable[[dict], None]):
    def apply(p: Path):
        m = json.loads((p / "manifest.json").read_text())
        edit(m)
        (p / "manifest.json").write_text(json.dumps(m))
        return p, "manifest.json"
    return apply


def _shard_edit(edit: Callable):
    """``edit(h5py.File)`` of the split's first shard (manifest left as it was)."""
    def apply(p: Path):
        import h5py

        shard = sorted(p.glob("shard-*.h5"))[0]
        with h5py.File(shard, "a") as f:
            edit(f, p)
        return p, shard.name
    return apply


def _external_link(f, folder: Path) -> None:
    """The shard's ``q`` read from an HDF5 file outside the split that holds the right values."""
    import h5py

    outside = folder.parent / "outside.h5"
    with h5py.File(outside, "w") as g:
        g["q"] = f["q"][()]
    del f["q"]
    f["q"] = h5py.ExternalLink(str(outside), "/q")


def _declares_rows(f, folder: Path) -> None:
    """Every per-image dataset declares DECLARED_ROWS images (unwritten chunks: kilobytes)."""
    for name in [n for n in f if n not in ("K", "R_camera_to_optical")]:
        shape, dtype = f[name].shape, f[name].dtype
        del f[name]
        f.create_dataset(name, shape=(DECLARED_ROWS,) + shape[1:], dtype=dtype, chunks=(1,) + shape[1:],
                         compression="gzip")


SHARD = "shard-00000.h5"
SPLIT_DAMAGE = {
    "missing": _missing,
    "file-for-folder": _file_for_folder,
    "empty-folder": _empty,
    "manifest-missing": _in("manifest.json", _missing),
    "manifest-empty": _in("manifest.json", _empty),
    "manifest-truncated": _in("manifest.json", _truncated),
    "manifest-folder": _in("manifest.json", _folder_for_file),
    "manifest-fifo": _in("manifest.json", _fifo),
    "manifest-binary": _in("manifest.json", _binary),
    "manifest-list": _json("manifest.json", "[1, 2]"),
    "manifest-nested": _json("manifest.json", "[" * DEEP + "]" * DEEP),
    "manifest-class-traversal": _manifest_edit(lambda m: m.update(class_name="../../victim")),
    "manifest-shard-traversal": _manifest_edit(lambda m: m["shards"][0].update(file="../../outside.h5")),
    "shard-missing": _in(SHARD, _missing),
    "shard-empty": _in(SHARD, _empty),
    "shard-truncated": _in(SHARD, _truncated),
    "shard-folder": _in(SHARD, _folder_for_file),
    "shard-fifo": _in(SHARD, _fifo),
    "shard-text": _in(SHARD, _text),
    "shard-link-out": _link_out(SHARD),
    "shard-external-link": _shard_edit(_external_link),
    "shard-declares-1e8-images": _shard_edit(_declares_rows),
}


def _predictions_external_link(p: Path):
    import h5py

    outside = p.parent / "outside.h5"
    shutil.copy(p, outside)
    with h5py.File(p, "a") as f:
        del f[DAMAGE_CLASS]
        f[DAMAGE_CLASS] = h5py.ExternalLink(str(outside), "/" + DAMAGE_CLASS)
    return p, "external link"


def _predictions_declares_rows(p: Path):
    import h5py

    with h5py.File(p, "a") as f:
        g = f[DAMAGE_CLASS]
        del g["sample_id"]
        g.create_dataset("sample_id", shape=(DECLARED_PREDICTION_ROWS,), dtype=np.int64, chunks=(1024,))
    return p, "of memory"


def _predictions_not_utf8_method(p: Path):
    import h5py

    with h5py.File(p, "a") as f:
        f.attrs["method"] = np.bytes_(b"\xff\xfe")
    return p, "'method'"


PREDICTIONS_DAMAGE = {
    "missing": _missing, "empty": _empty, "truncated": _truncated, "folder": _folder_for_file, "fifo": _fifo,
    "text": _text, "external-link": _predictions_external_link, "declares-1e13-rows": _predictions_declares_rows,
    "method-not-utf8": _predictions_not_utf8_method,
}


def _checkpoint(change: Callable[[dict], object]):
    """The checkpoint replaced by ``change(its dict)`` saved with torch."""
    def apply(p: Path):
        import torch

        torch.save(change(torch.load(p, weights_only=True)), p)
        return p, p.name
    return apply


CHECKPOINT_DAMAGE = {
    "missing": _missing, "empty": _empty, "truncated": _truncated, "folder": _folder_for_file, "fifo": _fifo,
    "text": _text,
    "pickled-code": _checkpoint(lambda c: {**c, "payload": _Payload()}),
    "a-list": _checkpoint(lambda c: [1, 2, 3]),
    "weights-text": _checkpoint(lambda c: {**c, "model_state": {"w": "abc"}}),
    "class-traversal": _checkpoint(lambda c: {**c, "class_name": "../../x"}),
}


def _png_declaring(side_px: int, bit_depth: int):
    def apply(p: Path):
        from helpers_core import png_header

        p.write_bytes(png_header(side_px, side_px, bit_depth))
        return p, p.name
    return apply


def _png_of(make: Callable[[np.ndarray], np.ndarray]):
    """The PNG rewritten with ``make(its pixels)``."""
    def apply(p: Path):
        Image.fromarray(make(np.array(Image.open(p)))).save(p)
        return p, None
    return apply


DEPTH_DAMAGE = {
    "missing": _missing, "empty": _empty, "truncated": _truncated, "folder": _folder_for_file, "fifo": _fifo,
    "text": _text, "declares-1e10-pixels": _png_declaring(DECLARED_SIDE_PX, 16),
    "8-bit": _png_of(lambda a: (a > 0).astype(np.uint8)),
    "no-object": _png_of(lambda a: np.zeros_like(a)),
}
CAMERA_DAMAGE = {
    "empty": _empty, "truncated": _truncated, "folder": _folder_for_file, "fifo": _fifo, "binary": _binary,
    "list": _json(None, "[100, 100, 95.5, 53.5]"), "nested": _json(None, '{"fx": ' + "[" * DEEP + "]" * DEEP + "}"),
    "text-values": _json(None, '{"fx": "a", "fy": "b", "cx": "c", "cy": "d"}'),
    "zero-focal": _json(None, '{"fx": 0, "fy": 0, "cx": 95.5, "cy": 53.5}'),
}
LABELS_DAMAGE = {
    "empty": _empty, "truncated": _truncated, "folder": _folder_for_file, "fifo": _fifo, "binary": _binary,
    "list": _json(None, "[1, 2]"), "nested": _json(None, '{"q": ' + "[" * DEEP + "]" * DEEP + "}"),
    "q-text": _json(None, '{"q": ["open"]}'), "q-nan": _json(None, '{"q": [NaN]}'),
    "yaml-keys-not-text": None,  # filled in below: a YAML label file given with --labels
}

INDEX = "split.json"
FIRST_EXR = "o000000_i000.exr"
EXPORT_DAMAGE = {
    "missing": _missing, "file-for-folder": _file_for_folder, "empty-folder": _empty,
    "index-missing": _in(INDEX, _missing), "index-empty": _in(INDEX, _empty), "index-truncated": _in(INDEX, _truncated),
    "index-folder": _in(INDEX, _folder_for_file), "index-fifo": _in(INDEX, _fifo), "index-list": _json(INDEX, "[1]"),
    "index-nested": _json(INDEX, "[" * DEEP + "]" * DEEP),
    "exr-missing": _in(FIRST_EXR, _missing), "exr-empty": _in(FIRST_EXR, _empty),
    "exr-truncated": _in(FIRST_EXR, _truncated), "exr-folder": _in(FIRST_EXR, _folder_for_file),
    "exr-fifo": _in(FIRST_EXR, _fifo), "exr-text": _in(FIRST_EXR, _text), "exr-link-out": _link_out(FIRST_EXR),
    "label-truncated": _in("o000000_i000.json", _truncated), "label-link-out": _link_out("o000000_i000.json"),
    "mask-declares-1e10-pixels": _in("o000000_i000.mask.png", _png_declaring(DECLARED_SIDE_PX, 8)),
}
TABLE_DAMAGE = {
    "missing": _missing, "empty": _empty, "truncated": _truncated, "folder": _folder_for_file, "fifo": _fifo,
    "binary": _binary, "huge": _json(None, " " * (4 << 20) + "{}"), "list": _json(None, "[1, 2]"),
    "nested": _json(None, "[" * DEEP + "]" * DEEP), "unknown-key": _json(None, '{"colour": "red"}'),
}
URDF_DAMAGE = {
    "missing": _missing, "empty": _empty, "truncated": _truncated, "folder": _folder_for_file, "fifo": _fifo,
    "binary": _binary, "not-a-robot": _json(None, '<?xml version="1.0"?>\n<mujoco/>\n'),
    "entity": None,  # filled in below: an XML entity reading a file outside
}


def _urdf_entity(p: Path):
    """The URDF's robot name an external entity: the file it names must never be read."""
    head = f'<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY x SYSTEM "file://{p.parent.parent}/canary.txt">]>\n'
    p.write_text(head + p.read_text().replace('<robot name="flap">', '<robot name="&x;">'))
    return p, None


URDF_DAMAGE["entity"] = _urdf_entity


def _yaml_labels(p: Path):
    """A YAML label file (given with --labels) whose keys are not all text."""
    yaml_file = p.with_name("a.labels.yaml")
    yaml_file.write_text("q: [0.1]\n1: 2\n")
    p.unlink()
    return yaml_file, "keys must be names"


LABELS_DAMAGE["yaml-keys-not-text"] = _yaml_labels


# ---- slots: the valid private copy and the commands that read it

def _copy_split(e: Env, v: Valid) -> Path:
    dst = e.tmp / "data" / DAMAGE_CLASS / "test"
    shutil.copytree(v.split, dst)
    return dst


def _copy_file(name: str, src: Callable[[Valid], Path]):
    def make(e: Env, v: Valid) -> Path:
        dst = e.tmp / "in" / name
        dst.parent.mkdir(parents=True)
        shutil.copy(src(v), dst)
        return dst
    return make


def _copy_capture_file(name: str):
    """A private copy of the capture folder; the slot's input is its file ``name``."""
    def make(e: Env, v: Valid) -> Path:
        shutil.copytree(v.capture, e.tmp / "caps")
        return e.tmp / "caps" / name
    return make


def _copy_export(e: Env, v: Valid) -> Path:
    dst = e.tmp / "exp" / DAMAGE_CLASS / "test"
    shutil.copytree(v.export, dst)
    return dst


def _write_table(e: Env, v: Valid) -> Path:
    (e.tmp / "in").mkdir()
    path = e.tmp / "in" / "table.json"
    path.write_text('{"chirality_p": 0.5}')
    return path


def _write_urdf(e: Env, v: Valid) -> Path:
    from helpers_core import write_flap_urdf

    (e.tmp / "canary.txt").write_text("canary")
    return write_flap_urdf(e.tmp / "urdf")


def _estimate(e: Env, depth: Path, *extra) -> list:
    return ["estimate", depth, "--class", DAMAGE_CLASS, *extra]


def _ingest_capture(e: Env, captures: Path, *extra) -> list:
    return ["ingest", captures, "--class", DAMAGE_CLASS, "--out", e.tmp / "out", "-q", *extra]


@dataclass(frozen=True)
class Slot:
    make: Callable[[Env, Valid], Path]  # the valid private copy
    commands: dict[str, Callable[[Env, Valid, Path], list]]  # name -> arguments given the input
    damage: dict[str, Callable[[Path], tuple]]


SLOTS = {
    "split": Slot(_copy_split, {
        "info": lambda e, v, p: ["info", p],
        "show": lambda e, v, p: ["show", p, "--out", e.tmp / "g.png", "-q"],
        "export": lambda e, v, p: ["export", p, e.tmp / "out", "-q"],
        "plan": lambda e, v, p: ["plan", p, "--index", 0, "-q", "--out", e.tmp / "plan.json"],
        "baseline-mean": lambda e, v, p: ["baseline", "mean", "--train", p, "--test", v.split, "--out", e.tmp / "p.h5",
                                          "-q"],
        "predict": lambda e, v, p: ["predict", "--model", "dense", p, "--out", e.tmp / "p.h5", "-q"],
        "train": lambda e, v, p: ["train", "--model", "mdn", "--class", DAMAGE_CLASS, p, "--out", e.tmp / "m.pt",
                                  "--small", "--epochs", 1, "--max-objects", 1, "-q"],
        "score-truth": lambda e, v, p: ["score", v.predictions, "--truth", p],
    }, SPLIT_DAMAGE),
    "predictions": Slot(_copy_file("p.h5", lambda v: v.predictions), {
        "score": lambda e, v, p: ["score", p, "--truth", v.split],
        "show": lambda e, v, p: ["show", v.split, "--predictions", p, "--out", e.tmp / "g.png", "--n", 2, "-q"],
        "plan": lambda e, v, p: ["plan", v.split, "--index", 0, "--predictions", p, "-q"],
    }, PREDICTIONS_DAMAGE),
    "checkpoint": Slot(_copy_file("m.pt", lambda v: v.checkpoint), {
        "predict": lambda e, v, p: ["predict", "--model", p, v.split, "--out", e.tmp / "p.h5", "-q"],
        "estimate": lambda e, v, p: _estimate(e, v.capture / "a.png", "--model", p),
        "export-model": lambda e, v, p: ["export-model", "--model", p, "--format", "safetensors", "--out",
                                         e.tmp / "m.safetensors", "-q"],
    }, CHECKPOINT_DAMAGE),
    "depth-image": Slot(_copy_capture_file("a.png"), {
        "estimate": lambda e, v, p: _estimate(e, p),
        "ingest": lambda e, v, p: _ingest_capture(e, p),
    }, DEPTH_DAMAGE),
    "camera-file": Slot(_copy_capture_file("camera.json"), {
        "estimate": lambda e, v, p: _estimate(e, p.parent / "a.png"),
        "ingest": lambda e, v, p: _ingest_capture(e, p.parent),
    }, CAMERA_DAMAGE),
    "label-file": Slot(_copy_capture_file("a.labels.json"), {
        "ingest": lambda e, v, p: _ingest_capture(e, p.parent / "a.png", *(["--labels", p] if p.suffix == ".yaml" else [])),
    }, LABELS_DAMAGE),
    "export": Slot(_copy_export, {
        "import-exr": lambda e, v, p: ["import-exr", p, "--out", e.tmp / "out", "-q"],
    }, EXPORT_DAMAGE),
    "sampling-table": Slot(_write_table, {
        "generate": lambda e, v, p: ["generate", "--class", "drawer", "--n", 1, "--images", 1, "--table", p, "--out",
                                     e.tmp / "out", "-q", "--workers", 1],
    }, TABLE_DAMAGE),
    "urdf": Slot(_write_urdf, {
        "generate": lambda e, v, p: ["generate", "--urdf", p, "--n", 1, "--images", 1, "--out", e.tmp / "out", "-q",
                                     "--workers", 1],
    }, URDF_DAMAGE),
}


def _invoke_guarded(args: list, fifos: list[Path]):
    """``CliRunner().invoke(main, args)``, failing (not hanging) if it waits on a FIFO for HANG_S."""
    import threading

    box = []
    worker = threading.Thread(target=lambda: box.append(CliRunner().invoke(main, [str(a) for a in args])), daemon=True)
    worker.start()
    worker.join(HANG_S)
    if worker.is_alive():  # open each FIFO for writing so that the blocked reader sees its end
        for fifo in fifos:
            with contextlib.suppress(OSError):
                os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        worker.join(10)
        pytest.fail(f"artdata {' '.join(map(str, args[:2]))} waited on a FIFO for {HANG_S} s")
    return box[0]


#: (slot, command, damage) rows a command accepts by design, with the reason: not in the table.
ACCEPTED = {
    ("depth-image", "ingest", "no-object"): "a capture without a depth return is stored, with a warning (estimate "
                                            "refuses it: nothing can be estimated from it)",
}
#: Rows that break the contract today, with what happens: strict, so that the fix makes them fail
#: until they are moved back into the table.
KNOWN_BREACHES: dict = {}
#: Rows run as a real process: CliRunner's stand-in stdout receives a warning the OpenEXR binding
#: writes for a truncated file, which a real process's standard output never shows.
REAL_PROCESS = {("export", "import-exr", "exr-truncated")}


def _damage_rows():
    for slot_name, slot in SLOTS.items():
        for command in slot.commands:
            for damage in slot.damage:
                row = (slot_name, command, damage)
                if row in ACCEPTED:
                    continue
                marks = [pytest.mark.xfail(strict=True, reason=KNOWN_BREACHES[row])] if row in KNOWN_BREACHES else []
                yield pytest.param(*row, id=":".join(row), marks=marks)


def _control_rows():
    for slot_name, slot in SLOTS.items():
        for command in slot.commands:
            slow = command in ("predict", "train", "generate", "estimate", "plan", "show", "export-model")
            yield pytest.param(slot_name, command, id=f"{slot_name}:{command}",
                               marks=[pytest.mark.slow] if slow else [])


@pytest.mark.parametrize("slot_name, command, damage", list(_damage_rows()))
def test_damaged_input_is_one_line(env, valid, monkeypatch, slot_name, command, damage):
    slot = SLOTS[slot_name]
    monkeypatch.setenv(CACHE_ENV, str(env.tmp.parent / "cache"))
    given, needle = slot.damage[damage](slot.make(env, valid))
    args = slot.commands[command](env, valid, given)
    shared = [env.tiny, valid.predictions.parent]  # the tiny dataset, the valid inputs
    before = [tree_snapshot(p, digests=False) for p in shared]
    own = tree_snapshot(env.tmp)
    if (slot_name, command, damage) in REAL_PROCESS:
        result = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", *map(str, args)], capture_output=True,
                                text=True, timeout=HANG_S, stdin=subprocess.DEVNULL)
    else:
        result = _invoke_guarded(args, [p for p in env.tmp.rglob("*") if p.is_fifo()])
    assert_one_line_error(result, *([needle] if needle else []))
    assert_unchanged(env.tmp, own)
    for root, b in zip(shared, before):
        assert_unchanged(root, b, digests=False)
    assert not (env.tmp / "pwned").exists()


@pytest.mark.parametrize("slot_name, command", list(_control_rows()))
def test_undamaged_input_is_accepted(env, valid, monkeypatch, slot_name, command):
    """The control of each row above: the same command on the valid copy succeeds."""
    slot = SLOTS[slot_name]
    monkeypatch.setenv(CACHE_ENV, str(env.tmp.parent / "cache"))
    args = slot.commands[command](env, valid, slot.make(env, valid))
    result = CliRunner().invoke(main, [str(a) for a in args])
    assert result.exit_code == 0, (result.output, result.exception)


# --------------------------------------------------------------------------------------
# 6. An output named where an input lies: refused, the input kept
# --------------------------------------------------------------------------------------

def test_a_baseline_or_a_report_never_replaces_a_shard_of_its_inputs(split_copy, tmp_path):
    split = split_copy()
    train = split_copy("microwave", "train")
    shard = next(split.glob("shard-*.h5"))
    before = shard.read_bytes()
    assert_one_line_error(run_cli("baseline", "mean", "--train", train, "--test", split, "--out", shard, "--overwrite"),
                          "inside the input folder")
    preds = tmp_path / "mean.h5"
    assert run_cli("baseline", "mean", "--train", train, "--test", split, "--out", preds).exit_code == 0
    assert_one_line_error(run_cli("score", preds, "--truth", split, "--csv", shard), "inside the input folder")
    assert shard.read_bytes() == before  # neither replaced the truth's shard
    if Path("/proc/version").exists():  # a report that cannot be written: neither is, not one of two
        assert_one_line_error(run_cli("score", preds, "--truth", split, "--json", tmp_path / "r.json",
                                      "--csv", "/proc/version"))
        assert not (tmp_path / "r.json").exists()
    if hasattr(os, "mkfifo"):  # a FIFO (or a device, or a link to standard output) is not replaced by a file
        fifo = tmp_path / "fifo"
        os.mkfifo(fifo)
        assert_one_line_error(run_cli("score", preds, "--truth", split, "--json", fifo), "not a regular file")
        assert fifo.is_fifo()
