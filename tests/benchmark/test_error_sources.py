"""benchmarks/error_sources.py: per-image errors equal the scorer's means, the along / across split
recombines to the position error, and the groups partition the images."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.benchmark import score
from articulated_dataset.cli import main
from helpers_core import ROOT, generated_split, load_script

pytest.importorskip("torch")


@pytest.fixture(scope="module")
def predicted(tmp_path_factory):
    root = tmp_path_factory.mktemp("errsrc")
    split = generated_split(root, "cabinet2", 2, 9)
    out = root / "p.h5"
    r = CliRunner().invoke(main, ["predict", "--model", "dense", str(split), "--out", str(out), "--no-mirror",
                                  "--threads", "1", "-q"])
    assert r.exit_code == 0, r.output
    return out, split


def test_per_image_errors_match_the_scorer(predicted):
    bench = load_script(ROOT / "benchmarks" / "error_sources.py", "error_sources")
    out, split = predicted
    class_name, prismatic, e = bench.per_image_errors(out, split)
    assert class_name == "cabinet2" and not prismatic.any()
    m = score(out, split).rows[0].metrics
    assert e["pos"].mean() == pytest.approx(m["axis_position_error_cm"][0], rel=1e-6)
    assert e["rot"].mean() == pytest.approx(m["axis_rotation_error_deg"][0], rel=1e-6)
    assert e["config"].mean() == pytest.approx(m["configuration_error"][0], rel=1e-6)
    assert np.allclose(e["along"] ** 2 + e["across"] ** 2, e["pos"] ** 2, rtol=1e-6, atol=1e-6)
    groups = [(e["top"] & ~e["bottom"]), (e["bottom"] & ~e["top"]), (e["top"] & e["bottom"]),
              (e["seen"] & ~e["top"] & ~e["bottom"]), ~e["seen"]]
    assert (sum(g.astype(int) for g in groups) == 1).all()
    assert e["body_px"].shape == (32,) and (e["body_px"] >= 0).all()
    # an image showing the whole object has no part on its top or bottom row, and shows every part
    assert e["whole"].shape == (32,) and not (e["whole"][:, None] & (e["top"] | e["bottom"] | ~e["seen"])).any()


def test_prints_both_tables(predicted, capsys):
    bench = load_script(ROOT / "benchmarks" / "error_sources.py", "error_sources")
    out, split = predicted
    assert bench.main(["--predictions", str(out), "--truth", str(split)]) == 0
    text = capsys.readouterr().out
    assert text.startswith("cabinet2: 32 images; mean position")
    assert "by the body's visible pixels" in text and "joint 1:" in text
    assert "shows the whole object" in text and "  cut off " in text


def test_a_missing_truth_folder_is_one_line(predicted, tmp_path, capsys):
    bench = load_script(ROOT / "benchmarks" / "error_sources.py", "error_sources")
    out, _ = predicted
    assert bench.main(["--predictions", str(out), "--truth", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error_sources: error: ") and "manifest.json" in err and "\n" not in err
