"""End-to-end scoring on the shared tiny dataset, the predictions format, and bad input via the CLI."""

from __future__ import annotations

import csv
import io
import json
import logging
import shutil

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.benchmark import metrics as M
from articulated_dataset.benchmark.predictions import PREDICTIONS_FORMAT_VERSION, read_predictions, write_predictions
from articulated_dataset.benchmark.scoring import score, target_matrix
from articulated_dataset.classes.registry import class_names
from articulated_dataset.cli import main
from articulated_dataset.core.errors import UserError
from articulated_dataset.format import open_split
from helpers_core import assert_one_line_error, raw_write

FIELDS = ("sample_id", "axis_pose", "q", "geometry", "part_offset")


def truth_labels(split_dir, fields=FIELDS):
    _, shards = open_split(split_dir)
    return {k: np.concatenate([s.read(k) for s in shards]) for k in fields}


def perfect(root, classes, split="test"):
    return {c: truth_labels(root / c / split) for c in classes}


def run(*args):
    result = CliRunner().invoke(main, [str(a) for a in args])
    return result


# ---------------------------------------------------------------- end to end

def test_perfect_predictions_score_zero(tiny_root, tmp_path):
    classes = ["cabinet", "drawer", "cabinet2"]
    pred = perfect(tiny_root, classes)
    write_predictions(tmp_path / "p.h5", "Oracle", pred)
    report = score(tmp_path / "p.h5", tiny_root)
    assert [r.class_name for r in report.rows] == classes
    for r in report.rows:
        assert r.split == "test" and r.complete and r.n_scored == r.n_truth == len(pred[r.class_name]["sample_id"])
        for name in ("axis_position_error_cm", "axis_rotation_error_deg", "configuration_error",
                     "axis_direction_error_deg", "geometry_width_error_cm"):
            assert r.metrics[name][0] == pytest.approx(0.0, abs=1e-4), name
        assert r.metrics["opd_success"][0] == 1.0 and r.metrics["chirality_accuracy"][0] == 1.0
        assert r.metrics.get("mechanism_side_accuracy", (1.0,))[0] == 1.0
    assert "axis_line_distance_cm" not in report.rows[1].metrics  # drawer: prismatic only
    assert "mechanism_side_accuracy" not in report.rows[1].metrics
    assert set(report.unscored_classes) == set(class_names()) - set(classes)


def test_shift_and_rotation_give_the_known_errors(tiny_root, tmp_path):
    classes = ["microwave", "drawer", "refrigerator"]
    pred = perfect(tiny_root, classes)
    for arrays in pred.values():
        pose = arrays["axis_pose"].astype(np.float64)
        pose[..., 0] += 0.03  # 3 cm along camera x
        rz = np.array([np.cos(np.radians(2.5)), 0.0, 0.0, np.sin(np.radians(2.5))])  # 5 deg about camera z
        pose[..., 3:] = M.quat_multiply(np.broadcast_to(rz, pose[..., 3:].shape), pose[..., 3:])
        arrays["axis_pose"] = pose
        arrays["q"] = arrays["q"] + np.where(np.arange(arrays["q"].shape[1]) == 0, 0.01, 0.03)
    write_predictions(tmp_path / "p.h5", "Shifted", pred, attrs={"note": "3 cm + 5 deg"})
    report = score(tmp_path / "p.h5", tiny_root)
    by_class = {r.class_name: r for r in report.rows}
    for r in report.rows:
        assert r.metrics["axis_position_error_cm"][0] == pytest.approx(3.0, abs=1e-4)
        assert r.metrics["axis_position_error_cm"][1] == pytest.approx(0.0, abs=1e-4)
        assert r.metrics["axis_rotation_error_deg"][0] == pytest.approx(5.0, abs=1e-3)
    assert by_class["drawer"].metrics["configuration_error"][0] == pytest.approx(1.0, abs=1e-4)  # 0.01 m
    assert by_class["microwave"].metrics["configuration_error"][0] == pytest.approx(np.degrees(0.01), abs=1e-4)
    # 2-DoF refrigerator: mean of 0.01 rad and 0.03 rad
    assert by_class["refrigerator"].metrics["configuration_error"][0] == pytest.approx(np.degrees(0.02), abs=1e-4)
    assert by_class["refrigerator"].per_joint["configuration_error"] == pytest.approx([np.degrees(0.01), np.degrees(0.03)], abs=1e-4)
    # doors hinge about vertical axes: rotating them about z leaves the direction; the drawer's turns by 5 deg
    assert by_class["microwave"].metrics["axis_direction_error_deg"][0] == pytest.approx(0.0, abs=1e-3)
    assert by_class["drawer"].metrics["axis_direction_error_deg"][0] == pytest.approx(5.0, abs=1e-3)
    table = report.format_table()
    assert "Microwave - Shifted" in table and "3.00 +/- 0.00" in table and "5.00 +/- 0.00" in table


def rep_titles(tmp_path) -> dict:
    titles = {k: v["title"] for k, v in json.loads((tmp_path / "r.json").read_text())["metrics"].items()}
    return {k: titles[k] for k in ("axis_position_error_cm", "opd_success")}


def test_cli_table_json_csv(tiny_root, tmp_path):
    write_predictions(tmp_path / "p.h5", "Oracle", perfect(tiny_root, ["toaster"]))
    result = run("score", tmp_path / "p.h5", "--truth", tiny_root, "--json", tmp_path / "r.json", "--csv", tmp_path / "r.csv")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert lines[0].startswith("truth toaster: split 'test', 48 images")
    assert "Axis position (cm)" in lines[2] and "Frame heading (deg)" in lines[2]
    assert max(len(line) for line in lines) <= 100 and any("Frame heading: the paper's axis rotation" in x for x in lines)
    wide = run("score", tmp_path / "p.h5", "--truth", tiny_root, "--wide").output.splitlines()
    assert "Axis position (cm)" in wide[2] and "Frame heading (deg)" in wide[2]  # one name per metric
    assert any(line.startswith("Standard metrics") and "OPD succ." in line and "Axis dir. (deg)" in line
               and "Cov. 90%" not in line for line in wide)
    assert rep_titles(tmp_path) == {"axis_position_error_cm": "Axis position (cm)", "opd_success": "OPD succ."}
    assert lines[3].startswith("Toaster - Oracle") and "0.00 +/- 0.00 deg" in lines[3] and "48/48" in lines[3]
    rep = json.loads((tmp_path / "r.json").read_text())
    row = rep["rows"][0]
    assert row["n_scored"] == row["n_truth"] == 48 and row["metrics"]["configuration_error"]["units"] == "deg"
    assert rep["truth_sets"]["toaster"]["split"] == "test"
    assert rep["metric_version"] == M.METRIC_VERSION == 3
    assert f"Metric version {M.METRIC_VERSION}" in lines[-1]
    rows = list(csv.DictReader(io.StringIO((tmp_path / "r.csv").read_text())))
    assert rows[0]["class"] == "toaster" and float(rows[0]["axis_position_error_cm_mean"]) == 0.0
    assert rows[0]["metric_version"] == "3"
    assert row["n_objects"] == int(rows[0]["n_objects"]) == 3 and rows[0]["axis_position_error_cm_sem"] == "0"
    assert row["metrics"]["accuracy_5deg_5cm"]["mean"] == 1.0 and row["metrics"]["opd_success"]["sem"] == 0.0
    assert any(x.startswith("SEM") for x in lines) and any(x.startswith("Fewer than 100 objects") for x in lines)
    assert rows[0]["nll_mean"] == ""  # no mixture given
    out = run("score", tmp_path / "p.h5", "--truth", tiny_root, "--json", "-")
    assert json.loads(out.output)["rows"][0]["method"] == "Oracle"


def test_partial_coverage_is_reported(tiny_root, tmp_path):
    pred = perfect(tiny_root, ["cabinet"])
    keep = np.arange(len(pred["cabinet"]["sample_id"])) % 3 == 0
    pred["cabinet"] = {k: v[keep] for k, v in pred["cabinet"].items()}
    write_predictions(tmp_path / "p.h5", "Some", pred)
    result = run("score", tmp_path / "p.h5", "--truth", tiny_root)
    assert result.exit_code == 0
    assert "16/48*" in result.output and "partial coverage" in result.output
    report = score(tmp_path / "p.h5", tiny_root)
    assert (report.rows[0].n_scored, report.rows[0].n_truth) == (16, 48) and report.notes
    assert_one_line_error(run("score", tmp_path / "p.h5", "--truth", tiny_root, "--require-complete"), "16/48")


def test_several_methods_and_files(tiny_root, tmp_path):
    write_predictions(tmp_path / "a.h5", "A", perfect(tiny_root, ["cabinet", "drawer"]))
    write_predictions(tmp_path / "b.h5", "B", perfect(tiny_root, ["drawer"]))
    report = score([tmp_path / "a.h5", tmp_path / "b.h5"], tiny_root)
    assert [(r.class_name, r.method) for r in report.rows] == [("cabinet", "A"), ("drawer", "A"), ("drawer", "B")]
    assert_one_line_error(run("score", tmp_path / "a.h5", tmp_path / "a.h5", "--truth", tiny_root), "also in")


def test_truth_split_selection(tiny_root, tmp_path):
    write_predictions(tmp_path / "train.h5", "T", perfect(tiny_root, ["cabinet"], split="train"))
    report = score(tmp_path / "train.h5", tiny_root, split="train")
    assert report.rows[0].split == "train" and report.rows[0].n_truth == 96
    # the split folder itself
    assert score(tmp_path / "train.h5", tiny_root / "cabinet" / "train").rows[0].complete
    # default is 'test': train ids are unknown there
    assert_one_line_error(run("score", tmp_path / "train.h5", "--truth", tiny_root), "not in the truth set")
    assert_one_line_error(run("score", tmp_path / "train.h5", "--truth", tiny_root, "--split", "nope"), "no split 'nope'")
    # several splits, none called test: --split is required; a 'real' split scores the same way (Table 2)
    root = tmp_path / "root"
    shutil.copytree(tiny_root / "cabinet" / "train", root / "cabinet" / "real")
    shutil.copytree(tiny_root / "cabinet" / "train", root / "cabinet" / "val")
    assert_one_line_error(run("score", tmp_path / "train.h5", "--truth", root), "--split", "real, val")
    result = run("score", tmp_path / "train.h5", "--truth", root, "--split", "real")
    assert result.exit_code == 0 and "truth cabinet: split 'real'" in result.output


def test_mixture_nll_and_calibration_end_to_end(tiny_root, tmp_path):
    stats = pytest.importorskip("scipy.stats")
    truth = truth_labels(tiny_root / "cabinet2" / "test", FIELDS + ("axis_origin", "axis_direction"))
    J = 2
    layout = [f"j{j}.{k}.{c}" for j in range(J) for k in ("origin", "axis", "xaxis") for c in "xyz"]
    layout += [f"j{j}.q" for j in range(J)] + [f"j{j}.offset.{c}" for j in range(J) for c in "xyz"]
    layout += [f"geometry.{k}" for k in ("depth", "width", "height", "chirality")]
    targets = pytest.importorskip("articulated_dataset.training.targets")
    assert sorted(layout) == sorted(targets.TargetLayout.for_class("cabinet2").names)  # the reference MDN's columns
    layout = layout[::-1]  # any order is accepted
    t64 = {k: truth[k].astype(np.float64) for k in FIELDS}
    y = target_matrix(layout, t64)
    # columns against the stored axis_origin / axis_direction datasets (independent of axis_pose)
    np.testing.assert_allclose(y[:, layout.index("j1.origin.z")], truth["axis_origin"][:, 1, 2], atol=1e-6)
    np.testing.assert_allclose(y[:, layout.index("j0.axis.y")], truth["axis_direction"][:, 0, 1], atol=1e-5)
    np.testing.assert_allclose(y[:, layout.index("geometry.width")], truth["geometry"][:, 1], atol=1e-7)
    N, D = y.shape
    rng = np.random.default_rng(0)
    means = np.stack([y + rng.normal(scale=0.05, size=y.shape), y + 1.0], axis=1)
    scales = np.full((N, 2, D), 0.05)
    weights = np.tile([0.8, 0.2], (N, 1))
    pred = dict(truth_labels(tiny_root / "cabinet2" / "test"), mixture_weights=weights, mixture_means=means,
                mixture_scales=scales, mixture_layout=layout)
    write_predictions(tmp_path / "m.h5", "MDN", {"cabinet2": pred})
    row = score(tmp_path / "m.h5", tiny_root).rows[0]
    logp = np.log(weights) + stats.norm.logpdf(y[:, None, :], means, scales).sum(-1)
    expected_nll = -np.log(np.exp(logp - logp.max(1, keepdims=True)).sum(1)) - logp.max(1)
    assert row.metrics["nll"][0] == pytest.approx(expected_nll.mean(), rel=1e-6)
    lo, hi = M.mixture_marginal_interval(weights, means, scales, 0.9)
    assert row.metrics["coverage_90"][0] == pytest.approx(((y >= lo) & (y <= hi)).mean(), abs=1e-9)
    assert 0.0 < row.metrics["coverage_50"][0] < row.metrics["coverage_90"][0] <= 1.0


def test_write_read_roundtrip_and_writer_rejects(tmp_path):
    n = 4
    ids = np.arange(10, 10 + n, dtype=np.int64)
    pose = np.zeros((n, 1, 7), np.float32)
    pose[..., 3] = 1.0
    arrays = {"sample_id": ids, "axis_pose": pose, "q": np.zeros((n, 1), np.float32), "geometry": np.ones((n, 4))}
    write_predictions(tmp_path / "p.h5", "M", {"drawer": arrays}, attrs={"epochs": 3, "config": {"lr": 0.1}})
    attrs, per_class = read_predictions(tmp_path / "p.h5")
    assert attrs["method"] == "M" and attrs["format_version"] == PREDICTIONS_FORMAT_VERSION and attrs["epochs"] == 3
    assert json.loads(attrs["config"]) == {"lr": 0.1}
    np.testing.assert_array_equal(per_class["drawer"]["sample_id"], ids)
    assert per_class["drawer"]["axis_pose"].shape == (n, 1, 7)
    with pytest.raises(UserError, match="q"):
        write_predictions(tmp_path / "x.h5", "M", {"drawer": {**arrays, "q": np.zeros((n, 2))}})
    with pytest.raises(UserError, match="NaN"):
        write_predictions(tmp_path / "x.h5", "M", {"drawer": {**arrays, "geometry": np.full((n, 4), np.nan)}})
    with pytest.raises(UserError):
        write_predictions(tmp_path / "x.h5", "", {"drawer": arrays})
    assert not (tmp_path / "x.h5").exists()


# ---------------------------------------------------------------- bad input through the CLI

@pytest.fixture(scope="module")
def good(tiny_root):
    """Valid arrays for the cabinet test split (float64 copies)."""
    return {k: np.array(v) for k, v in truth_labels(tiny_root / "cabinet" / "test").items()}


def _with(good, **changes):
    arrays = dict(good)
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    return {"cabinet": arrays}


def _bad_pose(good, fn):
    pose = good["axis_pose"].copy()
    fn(pose)
    return pose


BAD_CASES = {
    "missing dataset": (lambda g: _with(g, q=None), ["missing dataset 'q'", "/cabinet"]),
    "wrong shape": (lambda g: _with(g, axis_pose=g["axis_pose"][..., :6]), ["axis_pose", "shape"]),
    "wrong joint count": (lambda g: _with(g, q=np.zeros((len(g["q"]), 2), np.float32)), ["q", "shape"]),
    "float ids": (lambda g: _with(g, sample_id=g["sample_id"].astype(np.float64)), ["sample_id", "dtype"]),
    "int pose": (lambda g: _with(g, axis_pose=g["axis_pose"].astype(np.int32)), ["axis_pose", "dtype"]),
    "string q": (lambda g: _with(g, q=np.array([b"a"] * len(g["q"]))), ["/q", "dtype"]),
    "nan": (lambda g: _with(g, q=np.where(np.arange(len(g["q"]))[:, None] == 3, np.nan, g["q"])), ["/q", "NaN/inf"]),
    "inf": (lambda g: _with(g, axis_pose=_bad_pose(g, lambda p: p.__setitem__((5, 0, 1), np.inf))), ["axis_pose", "NaN/inf"]),
    "zero quaternion": (lambda g: _with(g, axis_pose=_bad_pose(g, lambda p: p.__setitem__((2, 0, slice(3, 7)), 0))),
                        ["axis_pose", "zero-length quaternion"]),
    "duplicated ids": (lambda g: _with(g, sample_id=np.concatenate([g["sample_id"][:1], g["sample_id"][:-1]])),
                       ["sample_id", "duplicated"]),
    "unknown ids": (lambda g: _with(g, sample_id=g["sample_id"] + 1), ["sample_id", "not in the truth set"]),
    "empty": (lambda g: {"cabinet": {k: v[:0] for k, v in g.items()}}, ["no predictions"]),
    "no truth for class": (lambda g: {"nonexistent_class": dict(g)}, ["/nonexistent_class", "no truth"]),
    "no groups": (lambda g: {}, ["no class groups"]),
    "partial mixture": (lambda g: _with(g, mixture_weights=np.ones((len(g["q"]), 1))), ["mixture", "missing"]),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_predictions_exit_2(case, good, tiny_root, tmp_path):
    build, needles = BAD_CASES[case]
    path = raw_write(tmp_path / "bad.h5", build(good))
    assert_one_line_error(run("score", path, "--truth", tiny_root), str(path), *needles)


def _mixture(good, D=3, layout=("j0.q", "j0.origin.x", "geometry.height"), **over):
    n = len(good["q"])
    arrays = dict(good, mixture_weights=np.full((n, 2), 0.5), mixture_means=np.zeros((n, 2, D)),
                  mixture_scales=np.ones((n, 2, D)))
    arrays.update(over)
    attrs = {"cabinet": {"mixture_layout": json.dumps(list(layout))}} if layout is not None else None
    return {"cabinet": arrays}, attrs


@pytest.mark.parametrize("case, over, needles", [
    ("no layout", {"layout": None}, ["mixture_layout"]),
    ("unknown column", {"layout": ("j0.q", "j0.origin.w", "geometry.height")}, ["'j0.origin.w'", "not in the target layout"]),
    ("joint out of range", {"layout": ("j0.q", "j3.q", "geometry.height")}, ["'j3.q'", "1 joint(s)"]),
    ("layout length", {"layout": ("j0.q", "j0.origin.x")}, ["mixture_means", "shape"]),
    ("negative scale", {"mixture_scales": -np.ones((48, 2, 3))}, ["mixture_scales", "<= 0"]),
    ("negative weight", {"mixture_weights": np.tile([1.5, -0.5], (48, 1))}, ["mixture_weights", "negative"]),
])
def test_bad_mixtures_exit_2(case, over, needles, good, tiny_root, tmp_path):
    layout = over.pop("layout", ("j0.q", "j0.origin.x", "geometry.height"))
    groups, attrs = _mixture(good, layout=layout, **over)
    path = raw_write(tmp_path / "bad.h5", groups, group_attrs=attrs)
    assert_one_line_error(run("score", path, "--truth", tiny_root), *needles)


def test_bad_files_and_options_exit_2(good, tiny_root, tmp_path):
    assert_one_line_error(run("score", tmp_path / "missing.h5", "--truth", tiny_root), "file not found", "missing.h5")
    (tmp_path / "text.h5").write_text("not hdf5\n")
    assert_one_line_error(run("score", tmp_path / "text.h5", "--truth", tiny_root), "not a readable HDF5 file")
    assert_one_line_error(run("score", tmp_path, "--truth", tiny_root), "directory")
    p = raw_write(tmp_path / "nov.h5", _with(good), version=None)
    assert_one_line_error(run("score", p, "--truth", tiny_root), "no format_version")
    p = raw_write(tmp_path / "v9.h5", _with(good), version="9.0")
    assert_one_line_error(run("score", p, "--truth", tiny_root), "version '9.0'")
    p = raw_write(tmp_path / "nom.h5", _with(good), method=None)
    assert_one_line_error(run("score", p, "--truth", tiny_root), "'method'")
    p = raw_write(tmp_path / "ok.h5", _with(good))
    assert_one_line_error(run("score", p, "--truth", tmp_path / "nowhere"), "no such directory")
    assert_one_line_error(run("score", p, "--truth", tmp_path), "no generated split")
    with h5py.File(tmp_path / "ds.h5", "w") as f:
        f.attrs.update(format_version=PREDICTIONS_FORMAT_VERSION, method="x")
        f.create_dataset("cabinet", data=np.zeros(3))
    assert_one_line_error(run("score", tmp_path / "ds.h5", "--truth", tiny_root), "expected a class group")


def test_non_unit_quaternions_are_normalised_with_a_warning(good, tiny_root, tmp_path, caplog):
    pose = good["axis_pose"].astype(np.float64)
    pose[:, :, 3:] *= 2.0  # same rotation, norm 2
    p = raw_write(tmp_path / "q.h5", _with(good, axis_pose=pose))
    with caplog.at_level(logging.WARNING, logger="articulated_dataset.benchmark.predictions"):
        report = score(p, tiny_root)
    assert any("non-unit quaternions" in r.getMessage() and "normalised" in r.getMessage() for r in caplog.records)
    assert report.rows[0].metrics["axis_rotation_error_deg"][0] == pytest.approx(0.0, abs=1e-4)
    assert run("score", p, "--truth", tiny_root).exit_code == 0


def test_truth_without_some_labels_is_averaged_where_defined(tiny_root, tmp_path):
    """Real captures may lack ground truth (NaN): metrics use the images that define them."""
    import shutil

    import h5py
    import numpy as np

    from articulated_dataset.benchmark.predictions import write_predictions
    from articulated_dataset.benchmark.scoring import score
    from articulated_dataset.format import open_split

    split = tmp_path / "drawer" / "test"
    shutil.copytree(tiny_root / "drawer" / "test", split)
    _, shards = open_split(split)
    pred = {k: np.concatenate([s.read(k) for s in shards]) for k in ("sample_id", "axis_pose", "q", "geometry")}
    for s in shards:
        s.close()
    n = len(pred["sample_id"])
    missing = 10
    with h5py.File(shards[0].path, "r+") as f:
        pose = f["axis_pose"][()]
        pose[:missing] = np.nan
        f["axis_pose"][...] = pose
    pred["axis_pose"][:, :, 0] += 0.02  # 2 cm shift everywhere
    write_predictions(tmp_path / "p.h5", "shifted", {"drawer": pred})
    report = score(tmp_path / "p.h5", split)
    row = report.rows[0]
    assert row.metrics["axis_position_error_cm"][0] == pytest.approx(2.0, abs=1e-3)
    assert row.metrics["configuration_error"][0] == pytest.approx(0.0, abs=1e-6)
    assert row.n_defined["axis_position_error_cm"] == n - missing
    assert "configuration_error" not in row.n_defined
    assert any(f"{n - missing} of {n}" in note for note in report.notes)


# ---------------------------------------------------------------- mirrored frames, chirality, scales, metric versions

def test_mirrored_cabinet_is_not_perfect(tiny_root, tmp_path):
    """The issue's reproduction: true origin and q, axis_pose quaternion times (0, 0, 1, 0) on the right."""
    pred = perfect(tiny_root, ["cabinet"])
    pose = pred["cabinet"]["axis_pose"].astype(np.float64)
    pose[..., 3:] = M.quat_multiply(pose[..., 3:], np.array([0.0, 0.0, 1.0, 0.0]))
    pred["cabinet"]["axis_pose"] = pose
    write_predictions(tmp_path / "m.h5", "Mirror", pred)
    r = score(tmp_path / "m.h5", tiny_root, metric_version=2).rows[0]
    assert r.metrics["axis_rotation_error_deg"][0] == pytest.approx(180.0, abs=1e-3)
    assert r.metrics["axis_direction_error_deg"][0] == pytest.approx(0.0, abs=1e-3)  # folded: the same line
    assert r.metrics["opd_success"][0] == 0.0 and r.metrics["mechanism_side_accuracy"][0] == 0.0
    v3 = score(tmp_path / "m.h5", tiny_root).rows[0]  # OPD's criterion sees the hinge line only
    assert v3.metrics["opd_success"][0] == 1.0 and v3.metrics["mechanism_side_accuracy"][0] == 0.0
    assert r.metrics["chirality_accuracy"][0] == 1.0  # the geometry prediction was left true
    # the same joint written with the other axis sign (axis reversed, x kept, q negated): perfect
    pred = perfect(tiny_root, ["cabinet"])
    pose = pred["cabinet"]["axis_pose"].astype(np.float64)
    pose[..., 3:] = M.quat_multiply(pose[..., 3:], np.array([0.0, 1.0, 0.0, 0.0]))
    pred["cabinet"].update(axis_pose=pose, q=-pred["cabinet"]["q"],
                           part_offset=pred["cabinet"]["part_offset"] * np.array([1.0, 1.0, -1.0], np.float32))
    write_predictions(tmp_path / "r.h5", "Reversed", pred)
    r = score(tmp_path / "r.h5", tiny_root).rows[0]
    for name in ("axis_position_error_cm", "axis_rotation_error_deg", "configuration_error", "axis_direction_error_deg"):
        assert r.metrics[name][0] == pytest.approx(0.0, abs=1e-3), name
    assert r.metrics["opd_success"][0] == 1.0 and r.metrics["mechanism_side_accuracy"][0] == 1.0


def test_undefined_true_chirality_is_excluded(tiny_root, tmp_path):
    split = tmp_path / "cabinet" / "test"
    shutil.copytree(tiny_root / "cabinet" / "test", split)
    pred = truth_labels(split)
    _, shards = open_split(split)
    paths = [s.path for s in shards]
    for s in shards:
        s.close()
    n_nan = 16
    with h5py.File(paths[0], "r+") as f:  # the first object's truth has no chirality (like a real capture)
        g = f["geometry"][()]
        g[:n_nan, 3] = np.nan
        f["geometry"][...] = g
    pred["geometry"][:, 3] = 1.0 - pred["geometry"][:, 3]  # every predicted chirality wrong
    write_predictions(tmp_path / "p.h5", "Wrong side", {"cabinet": pred})
    report = score(tmp_path / "p.h5", split)
    row = report.rows[0]
    assert row.metrics["chirality_accuracy"][0] == 0.0  # v1 counted NaN truth as correct for c_pred < 0.5
    assert row.n_defined["chirality_accuracy"] == row.n_scored - n_nan
    assert any("chirality_accuracy averaged over" in n for n in report.notes)


def test_tiny_mixture_scales_give_infinite_nll_never_dropped(good, tiny_root, tmp_path):
    n = len(good["q"])
    groups, attrs = _mixture(good, D=1, layout=("j0.q",), mixture_means=np.full((n, 2, 1), 0.123),
                             mixture_scales=np.full((n, 2, 1), 1e-200))
    path = raw_write(tmp_path / "tiny.h5", groups, group_attrs=attrs)
    result = run("score", path, "--truth", tiny_root, "--json", tmp_path / "r.json", "--csv", tmp_path / "r.csv")
    assert result.exit_code == 0, result.output
    assert "Traceback" not in result.output and "Warning" not in result.output
    assert "inf +/- inf" in result.output and "nll is infinite for 48 of 48 images" in result.output
    rep = json.loads((tmp_path / "r.json").read_text())  # strict JSON: infinity as the string "inf"
    assert rep["rows"][0]["metrics"]["nll"]["mean"] == "inf" and rep["rows"][0]["n_infinite"] == {"nll": 48}
    rows = list(csv.DictReader(io.StringIO((tmp_path / "r.csv").read_text())))
    assert rows[0]["nll_mean"] == "inf"
    # one image with a finite density and the rest infinite: still infinite, and all 48 counted
    row = score(path, tiny_root).rows[0]
    assert row.metrics["nll"][0] == float("inf") and "nll" not in row.n_defined


def test_truth_reader_refuses_shards_outside_the_split(tiny_root, tmp_path, monkeypatch):
    """The split reader's own check on resolved shard paths (format.Split), independent of the manifest-name checks."""
    from articulated_dataset.benchmark import truth
    from articulated_dataset.core.errors import DataFormatError
    from articulated_dataset.format import split as split_module

    split = tmp_path / "cabinet" / "test"
    shutil.copytree(tiny_root / "cabinet" / "test", split)
    outside = shutil.copy(next(split.glob("shard-*.h5")), tmp_path / "elsewhere.h5")
    for path in (outside, split / ".." / "test" / ".." / ".." / "elsewhere.h5", split):
        monkeypatch.setattr(split_module, "shard_paths", lambda d, m, p=path: [p])
        with pytest.raises(DataFormatError, match="outside the split folder"):
            truth.load_truth_set(split)


def test_metric_version_2_reproduces_version_2_reports(tiny_root, tmp_path):
    """--metric-version 2 gives version 2's columns and numbers; version 3 adds its metrics and SEMs."""
    write_predictions(tmp_path / "p.h5", "Oracle", perfect(tiny_root, ["toaster"]))
    v2 = run("score", tmp_path / "p.h5", "--truth", tiny_root, "--metric-version", "2", "--csv", "-")
    assert v2.exit_code == 0, v2.output
    head = v2.output.splitlines()[0].split(",")
    assert "n_objects" not in head and not any(c.endswith("_sem") or c.startswith("accuracy_") for c in head)
    assert v2.output.splitlines()[1].split(",")[head.index("metric_version")] == "2"
    v3 = run("score", tmp_path / "p.h5", "--truth", tiny_root, "--csv", "-").output.splitlines()[0].split(",")
    assert {"accuracy_5deg_5cm_mean", "axis_position_along_cm_sem", "n_objects"} <= set(v3)
    bad = run("score", tmp_path / "p.h5", "--truth", tiny_root, "--metric-version", "1")
    assert bad.exit_code == 2 and "--metric-version" in bad.output
