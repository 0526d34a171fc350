"""The dense estimator's outlier component: its fit, the mixture it joins, and its refit."""

from __future__ import annotations

import numpy as np
import pytest

from articulated_dataset.benchmark import metrics as M
from articulated_dataset.methods.dense.predict import (
    OUTLIER_WEIGHT_BOUNDS,
    fit_outlier_component,
    mixture_from_modes,
    with_outlier_component,
)

D = 5  # columns of the synthetic mixtures


def _gaussian_mixture(rng, n: int, outlier_share: float):
    """n images whose one-component mixture has scale 0.01 about each image's estimate, the truth
    drawn from it, except ``outlier_share`` of the images, whose truth is off by about 1 in every
    column (an estimate that failed outright: 100 scales)."""
    means = rng.normal(size=(n, 1, D))
    scales = np.full((n, 1, D), 0.01)
    y = means[:, 0] + 0.01 * rng.standard_normal((n, D))
    bad = rng.random(n) < outlier_share
    y[bad] += rng.choice([-1.0, 1.0], size=(bad.sum(), D)) * (1 + 0.2 * rng.random((bad.sum(), D)))
    return {"mixture_weights": np.ones((n, 1)), "mixture_means": means, "mixture_scales": scales}, y, bad


@pytest.mark.parametrize("share", [0.005, 0.02])
def test_the_outlier_components_weight_is_the_share_of_gross_failures(share):
    arrays, y, bad = _gaussian_mixture(np.random.default_rng(0), 8000, share)
    fit = fit_outlier_component(arrays, y)
    assert fit["weight"] == pytest.approx(bad.mean(), rel=0.2)
    # the failures belong to the component, the others to the mixture's own
    assert fit["responsibility"][bad].min() > 0.99 and fit["responsibility"][~bad].max() < 0.01
    assert fit["validation_nll"]["without"] > 100 and fit["validation_nll"]["with"] < -15
    # wide enough for a failure: about the failures' distance in every column
    assert all(0.3 < s < 3.0 for s in fit["scale"])


def test_without_failures_the_component_keeps_its_smallest_weight_as_a_safety_net():
    arrays, y, bad = _gaussian_mixture(np.random.default_rng(1), 4000, 0.0)
    assert not bad.any()
    fit = fit_outlier_component(arrays, y)
    assert fit["weight"] == OUTLIER_WEIGHT_BOUNDS[0]
    # it costs the good images about -log(1 - weight) nats, and is still as wide as the class's spread
    assert fit["validation_nll"]["with"] - fit["validation_nll"]["without"] == pytest.approx(
        -np.log1p(-OUTLIER_WEIGHT_BOUNDS[0]), abs=1e-5)
    np.testing.assert_allclose(fit["scale"], y.std(0), rtol=1e-9)


def test_the_fit_is_at_least_as_likely_as_every_weight_and_scale_of_a_grid():
    """Brute-force reference: expectation-maximisation ends no worse than the best of a grid of
    weights and scales (scales at or above the fit's floor, as the fit keeps them)."""
    arrays, y, _ = _gaussian_mixture(np.random.default_rng(2), 3000, 0.03)
    fit = fit_outlier_component(arrays, y)
    point = arrays["mixture_means"][:, 0]
    floor = np.maximum(y.std(0), np.sqrt(((y - point) ** 2).mean(0)))
    best = np.inf
    for eps in np.geomspace(*OUTLIER_WEIGHT_BOUNDS, 15):
        for factor in np.linspace(1.0, 3.0, 9):
            w, mu, s, _ = with_outlier_component(arrays["mixture_weights"], arrays["mixture_means"],
                                                 arrays["mixture_scales"], np.zeros((len(y), 1, D)), point,
                                                 {"weight": eps, "scale": floor * factor})
            best = min(best, float(M.mixture_nll(y, w, mu, s).mean()))
    assert fit["validation_nll"]["with"] <= best + 1e-6


def _modes(N: int = 3):
    m = {"weight": np.array([[[0.7, 0.3]]] * N), "q": np.array([[[0.2, 0.4]]] * N),
         "q_std": np.full((N, 1, 2), 0.05)}
    for key in ("origin", "axis", "xaxis", "part_offset", "origin_std", "axis_std", "xaxis_std", "offset_std"):
        m[key] = np.tile(np.array([0.0, 0.0, 1.0]), (N, 1, 2, 1))
    m["origin"][:, 0, 1] = [0.5, 0.0, 1.0]
    m["geometry"], m["geometry_std"] = np.ones((N, 4)), np.full((N, 4), 0.1)
    return m


def test_the_component_follows_the_modes_and_leaves_the_point_estimate():
    D1 = 13 + 4
    calibration = {"spread_factor": [1.0] * D1, "floor": [1e-3] * D1}
    plain = mixture_from_modes(_modes(), np.arange(3), 1, 2, calibration)
    scale = list(np.linspace(0.5, 2.0, D1))
    robust = mixture_from_modes(_modes(), np.arange(3), 1, 2, {**calibration, "outlier": {"weight": 0.02, "scale": scale}})
    for key in ("axis_pose", "q", "geometry", "part_offset"):
        np.testing.assert_array_equal(robust[key], plain[key])
    np.testing.assert_allclose(robust["mixture_weights"][:, :2], 0.98 * plain["mixture_weights"])
    np.testing.assert_allclose(robust["mixture_weights"][:, 2], 0.02)
    np.testing.assert_allclose(robust["mixture_weights"].sum(-1), 1.0)
    heaviest = plain["mixture_weights"].argmax(-1)
    np.testing.assert_array_equal(robust["mixture_means"][:, 2], plain["mixture_means"][np.arange(3), heaviest])
    np.testing.assert_array_equal(robust["mixture_scales"][:, 2], np.tile(scale, (3, 1)))
    assert robust["spread"].shape == robust["mixture_means"].shape
    # a truth 1 m off: the plain mixture gives it a vanishing density, the robust one a finite NLL
    y = robust["mixture_means"][:, 2] + 1.0
    assert M.mixture_nll(y, plain["mixture_weights"], plain["mixture_means"], plain["mixture_scales"]).min() > 1e5
    assert M.mixture_nll(y, robust["mixture_weights"], robust["mixture_means"], robust["mixture_scales"]).max() < 50


def test_an_image_set_without_a_defined_target_is_an_error():
    arrays, y, _ = _gaussian_mixture(np.random.default_rng(3), 10, 0.0)
    with pytest.raises(ValueError, match="no validation image"):
        fit_outlier_component(arrays, np.full_like(y, np.nan))


@pytest.mark.slow
def test_a_calibration_only_refit_keeps_the_estimates_and_adds_the_component(tiny_root, tmp_path):
    """``scripts/fit_dense_inference.py --calibration-only``: the refinement and so every point
    estimate and mode stay; the calibration gains the outlier component; the split the refit
    reads is recorded; a split generated otherwise than the checkpoint's is one line."""
    torch = pytest.importorskip("torch")
    from articulated_dataset.core.errors import UserError
    from articulated_dataset.methods.dense.checkpoint import build_inference_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.predict import predict_arrays
    from articulated_dataset.methods.dense.train import DenseTrainConfig, refit_inference, train_dense

    torch.set_num_threads(1)
    split = tiny_root / "drawer" / "train"
    cfg = DenseTrainConfig("drawer", epochs=1, batch_size=16, width=4, val_fraction=0.2, max_objects=3)
    trained = train_dense(split, tmp_path / "a.pt", cfg, progress=False)
    old = dict(trained, calibration={k: v for k, v in trained["calibration"].items() if k != "outlier"})
    torch.save(old, tmp_path / "old.pt")  # a checkpoint calibrated before the component
    refit = refit_inference(tmp_path / "old.pt", split, tmp_path / "b.pt", progress=False, calibration_only=True)
    assert refit["refinement"] == trained["refinement"] and refit["refit_of"]["calibration_only"] is True
    assert refit["calibration"] == trained["calibration"]  # what training's own fit gives
    assert OUTLIER_WEIGHT_BOUNDS[0] <= refit["calibration"]["outlier"]["weight"] <= OUTLIER_WEIGHT_BOUNDS[1]

    d = load_dense_split(split, 1, (108, 192))
    idx = np.arange(len(d.sample_id))
    before, after = (predict_arrays(build_inference_model(c), d, idx, joint_types=["prismatic"],
                                    calibration=c["calibration"], refinement=c["refinement"])
                     for c in (old, load_dense_checkpoint(tmp_path / "b.pt")))
    for key in ("axis_pose", "q", "geometry", "part_offset"):
        np.testing.assert_array_equal(after[key], before[key])
    assert after["mixture_weights"].shape[1] == before["mixture_weights"].shape[1] + 1

    other = dict(old, data={**old["data"], "generated": {**old["data"]["generated"], "seed": 999}})
    torch.save(other, tmp_path / "other.pt")
    with pytest.raises(UserError, match="validation objects are not there"):
        refit_inference(tmp_path / "other.pt", split, tmp_path / "c.pt", progress=False, calibration_only=True)


def test_a_column_the_class_holds_constant_keeps_its_kinds_floor():
    """A vertical hinge's axis is (0, 0, -1) in every image, so the validation images show no
    spread in ``j0.axis.z``; a failure that flips the frame reads +1 there.  The component's
    scale in that column is its kind's floor (half a unit), so the flip costs a few scales, not
    thousands (the seed-2026 test microwaves: 10^6 nats before the floor)."""
    from articulated_dataset.methods.dense.predict import OUTLIER_MIN_SCALES, _layout_names

    rng = np.random.default_rng(4)
    names = _layout_names(1)
    n, d = 2000, len(names)
    means = rng.normal(size=(n, 1, d))
    axis_z = names.index("j0.axis.z")
    means[:, 0, axis_z] = -1.0
    y = means[:, 0] + 0.001 * rng.standard_normal((n, d))
    y[:, axis_z] = -1.0
    flipped = np.arange(n) < 10
    means[flipped, 0, axis_z] = 1.0  # the estimate's frame flipped
    arrays = {"mixture_weights": np.ones((n, 1)), "mixture_means": means,
              "mixture_scales": np.full((n, 1, d), 0.001), "mixture_layout": names}
    fit = fit_outlier_component(arrays, y)
    assert fit["scale"][axis_z] >= OUTLIER_MIN_SCALES["axis"]
    w, mu, s, _ = with_outlier_component(arrays["mixture_weights"], means, arrays["mixture_scales"],
                                         np.zeros_like(means), means[:, 0], fit)
    nll = M.mixture_nll(y, w, mu, s)
    assert nll[flipped].max() < 100 and np.median(nll[~flipped]) < -50


def test_validation_labels_without_a_complete_image_leave_the_component_out(caplog):
    """Labels with an undefined column in every image (real captures' truth) still calibrate the
    modes, column by column; the component, which needs whole target vectors, is left out with a
    warning instead of failing the end of a training run."""
    from types import SimpleNamespace

    from articulated_dataset.methods.dense.predict import fitted_calibration

    rng = np.random.default_rng(5)
    N, J, M_ = 32, 1, 2
    m = {"weight": np.tile([[[0.8, 0.2]]], (N, 1, 1)), "q": rng.random((N, J, M_)),
         "q_std": np.full((N, J, M_), 0.05)}
    for key in ("origin", "axis", "xaxis", "part_offset"):
        m[key] = rng.normal(size=(N, J, M_, 3))
    for key in ("origin_std", "axis_std", "xaxis_std", "offset_std"):
        m[key] = np.full((N, J, M_, 3), 0.01)
    m["geometry"], m["geometry_std"] = rng.random((N, 4)), np.full((N, 4), 0.01)
    q = m["q"][:, :, 0].astype(np.float32)
    data = SimpleNamespace(sample_id=np.arange(N), origin=m["origin"][:, :, 0].astype(np.float32),
                           rot6=np.concatenate([m["axis"][:, :, 0], m["xaxis"][:, :, 0]], -1).astype(np.float32),
                           q=q, part_offset=m["part_offset"][:, :, 0].astype(np.float32),
                           geometry=np.full((N, 4), np.nan, np.float32))
    model = SimpleNamespace(config=SimpleNamespace(n_joints=J))
    with caplog.at_level("WARNING"):
        calibration = fitted_calibration(m, model, data, np.arange(N))
    assert "outlier" not in calibration and len(calibration["floor"]) == 17
    assert "no outlier component" in caplog.text
