"""scipy is an optional dependency (the baselines extra): without it, each feature that needs it
fails with one line naming the feature and the install command, not a bare ModuleNotFoundError."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from articulated_dataset.core.errors import UserError, import_optional


@pytest.fixture
def no_scipy(monkeypatch):
    for name in list(sys.modules):
        if name == "scipy" or name.startswith("scipy."):
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "scipy", None)  # "import scipy" raises ImportError


def _one_line_naming(exc_info, what):
    msg = str(exc_info.value)
    assert "\n" not in msg and what in msg and "pip install" in msg


def test_import_optional_names_the_feature_and_the_install_command(no_scipy):
    with pytest.raises(UserError) as e:
        import_optional("scipy.spatial", "the ICP baseline")
    _one_line_naming(e, "the ICP baseline")


def test_an_installed_package_that_fails_to_import_stays_a_real_error(tmp_path, monkeypatch):
    (tmp_path / "fakepkg_xyz").mkdir()
    (tmp_path / "fakepkg_xyz" / "__init__.py").write_text("import no_such_dependency_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ImportError) as e:
        import_optional("fakepkg_xyz", "nothing")
    assert not isinstance(e.value, UserError) and e.value.name == "no_such_dependency_xyz"


def test_mixture_scoring_without_scipy_is_one_line(no_scipy):
    from articulated_dataset.benchmark import metrics

    with pytest.raises(UserError) as e:
        metrics.mixture_marginal_cdf(np.zeros((1, 2)), np.ones((1, 1)), np.zeros((1, 1, 2)), np.ones((1, 1, 2)))
    _one_line_naming(e, "scoring mixture calibration")


def test_handle_close_up_without_scipy_is_one_line(no_scipy):
    from articulated_dataset import manipulation

    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    with pytest.raises(UserError) as e:
        manipulation.find_handle(np.ones((48, 64)), K, np.random.default_rng(0))
    _one_line_naming(e, "handle close-up")
