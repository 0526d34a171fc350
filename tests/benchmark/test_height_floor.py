"""benchmarks/height_floor.py: the oracle's posterior on hand-worked cases, its facts against rendered
pixels, and the script as a user runs it."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from helpers_core import ROOT, generated_split, load_script

pytest.importorskip("torch")
HALF_RANGE_M = (0.3, 0.7)  # the cabinet's height_m 0.6-1.4 m, halved
#: The grid's step is 0.4 m / 2000: posterior means are exact to about that.
GRID_TOL_M = 5e-4


@pytest.fixture(scope="module")
def bench():
    return load_script(ROOT / "benchmarks" / "height_floor.py", "height_floor")


def _facts(**kw):
    f = {"cut": np.array([[True]]), "handle": np.array([[False]]), "top_m": np.array([[0.2]]),
         "strip_lo_m": np.array([[np.nan]]), "strip_hi_m": np.array([[np.nan]]), "half_m": np.array([[0.6]])}
    f.update({k: np.array([[v]]) for k, v in kw.items()})
    return f


def test_the_posterior_on_hand_worked_cases(bench):
    # the top cut off below every height the prior allows: D uniform on [0.3, 0.7], MAD 0.4 / 4
    err, realised = bench.oracle_along_error_m(_facts(), HALF_RANGE_M)
    assert err[0, 0] == pytest.approx(0.1, abs=GRID_TOL_M)
    assert realised[0, 0] == pytest.approx(abs(0.5 - 0.6), abs=GRID_TOL_M)  # the median 0.5 against 0.6
    # the object's highest visible point 1.0 m above the bottom: D >= 0.5, uniform on [0.5, 0.7]
    err, _ = bench.oracle_along_error_m(_facts(top_m=1.0), HALF_RANGE_M)
    assert err[0, 0] == pytest.approx(0.05, abs=GRID_TOL_M)
    # no handle on a strip seen from 0 to 0.6 m: the bar (6 cm either side of D) is above it, D > 0.66
    err, _ = bench.oracle_along_error_m(_facts(strip_lo_m=0.0, strip_hi_m=0.6), HALF_RANGE_M)
    assert err[0, 0] == pytest.approx(0.01, abs=GRID_TOL_M)
    # ... and seen from 0.5 to 0.6 m: the bar below (D < 0.44) or above (D > 0.66) it
    err, _ = bench.oracle_along_error_m(_facts(strip_lo_m=0.5, strip_hi_m=0.6), HALF_RANGE_M)
    fine = np.linspace(0.3, 0.7, 400_001)  # the same uniform posterior, 200 times finer
    post = fine[(fine < 0.44) | (fine > 0.66)]
    assert err[0, 0] == pytest.approx(np.abs(post - np.median(post)).mean(), abs=GRID_TOL_M)
    # the top seen, or the handle found: the height is known
    for kw in ({"cut": False}, {"handle": True}):
        err, realised = bench.oracle_along_error_m(_facts(**kw), HALF_RANGE_M)
        assert err[0, 0] == 0 and realised[0, 0] == 0


def test_the_facts_against_rendered_pixels(bench, tmp_path):
    """Every pixel of a rendered cabinet lies at or below its top; where the top counts as seen a
    pixel is within the tolerance of it; the handle's strip lies on the door."""
    split = generated_split(tmp_path, "cabinet", 3, seed=4)
    class_name, f = bench.door_facts(split)
    assert class_name == "cabinet" and f["top_m"].shape == (48, 1)
    ok = np.isfinite(f["top_m"])
    assert ok.all()
    assert (f["top_m"] <= 2 * f["half_m"] + 0.005).all()  # depth quantisation: well under 5 mm
    seen = ~f["cut"]
    assert seen.any() and (f["top_m"][seen] >= 2 * f["half_m"][seen] - bench.TOP_SEEN_TOL_M).all()
    strip = np.isfinite(f["strip_lo_m"])
    assert strip.any()
    assert (f["strip_lo_m"][strip] >= -0.005).all() and (f["strip_hi_m"][strip] <= 2 * f["half_m"][strip] + 0.005).all()


@pytest.mark.slow
def test_the_script_as_a_user_runs_it(bench, tmp_path, capsys):
    split = generated_split(tmp_path, "cabinet", 2, seed=6)
    out = tmp_path / "p.h5"
    r = CliRunner().invoke(main, ["predict", "--model", "dense", str(split), "--out", str(out), "--no-mirror",
                                  "--threads", "1", "-q"])
    assert r.exit_code == 0, r.output
    assert bench.main(["--truth", str(split), "--predictions", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.startswith("cabinet: 32 images, 1 door(s)") and "floor of the mean axis position error" in text
    assert "top seen" in text
    # a class whose doors are not its full height: one line, exit 2
    other = generated_split(tmp_path / "m", "microwave", 1, seed=6)
    assert bench.main(["--truth", str(other)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("height_floor: error: ") and "\n" not in err
