"""Hostile input across the commands: every case ends in exactly one stderr line
``artdata: error: ...`` with exit code 2, prints nothing on stdout, and changes nothing on
disk (neither the test's working folder, where every output is named, nor the shared input
data).

Case groups: click usage errors of every command (unknown options, bad values of every
typed option, bad choices, missing arguments); absurd numbers; real (ingested) splits used
where they cannot be; damaged or foreign model checkpoints; malformed real captures.
"""

from __future__ import annotations

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
from articulated_dataset.cli import EXIT_ENVIRONMENT_ERROR, EXIT_USER_ERROR, main
from articulated_dataset.format import open_split
from helpers_core import split_copy_with
from helpers_real import write_capture

ERROR_PREFIX = "artdata: error: "
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

    root = tmp_path_factory.mktemp("hostile")
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


def _tree(root: Path) -> dict:
    """``{relative path: (size, mtime_ns)}`` of every file and folder under ``root``."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = p.lstat()
            out[str(p.relative_to(root))] = (st.st_size if p.is_file() else 0, st.st_mtime_ns)
    return out


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


def assert_one_line_error(result, needle: str | None = None, code: int = EXIT_USER_ERROR) -> str:
    assert result.exit_code == code, (result.exit_code, result.output, result.exception)
    assert result.stdout == "", result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(ERROR_PREFIX), result.stderr
    if needle is not None:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def run_case(env: Env, args: list, needle: str | None) -> None:
    watched = [env.tmp, env.tiny, env.inputs.real.parent.parent.parent]
    before = [_tree(p) for p in watched]
    result = CliRunner().invoke(main, [str(a) for a in args])
    assert_one_line_error(result, needle)
    after = [_tree(p) for p in watched]
    for root, b, a in zip(watched, before, after):
        assert a == b, f"{root}: changed by a refused command: {sorted(set(a) ^ set(b)) or 'modified files'}"


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
def test_hostile_case_is_one_line(env, name):
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
    assert bad.returncode == EXIT_ENVIRONMENT_ERROR, bad.stderr
    lines = bad.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(ERROR_PREFIX) and "MUJOCO_GL='no-such-backend'" in lines[0]
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
    assert r.returncode == 3 and r.stderr.count("\n") == 1 and "No space left" in r.stderr, r.stderr
