"""The one units module: vector normalisation, configurations in words and parsed back."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from articulated_dataset.core.errors import UserError
from articulated_dataset.core.units import NO_LABEL_TEXT, format_q, normalise, parse_quantity
from articulated_dataset.format import PRISMATIC, REVOLUTE


def test_normalise_stacks_and_keeps_zero_vectors():
    v = np.array([[3.0, 0.0, 4.0], [0.0, 0.0, 0.0], [0.0, -2.0, 0.0]])
    np.testing.assert_array_equal(normalise(v), [[0.6, 0.0, 0.8], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    deep = np.arange(24, dtype=float).reshape(2, 4, 3) + 1
    np.testing.assert_allclose(np.linalg.norm(normalise(deep), axis=-1), 1.0, rtol=1e-15)
    tiny = np.array([[1e-12, 0.0, 0.0], [2.0, 0.0, 0.0]])
    np.testing.assert_array_equal(normalise(tiny, min_norm=1e-9), [[1e-12, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert normalise([1, 1]).dtype == np.float64


def test_normalise_arithmetic_is_the_labels_and_readers():
    """A single vector is divided by numpy's norm(v) (the generator's labels: their bytes),
    a stack by norm(v, axis=-1) (the readers'); the two differ in the last bit for some vectors."""
    rng = np.random.default_rng(1)
    v = rng.normal(size=(2000, 3)) * 7.3
    singles = np.stack([normalise(x) for x in v])
    np.testing.assert_array_equal(singles, np.stack([x / np.linalg.norm(x) for x in v]))
    np.testing.assert_array_equal(normalise(v), v / np.linalg.norm(v, axis=-1, keepdims=True))
    if not (singles != normalise(v)).any():  # so the first check can fail (on most machines)
        pytest.skip("this machine's numpy gives norm(v) and norm(v, axis=-1) the same bits for all "
                    "2,000 vectors: the two arithmetics cannot be told apart here")


def test_normalise_checked():
    with pytest.raises(UserError, match="^axis_direction has zero length$"):
        normalise([0.0, 0.0, 0.0], what="axis_direction")
    with pytest.raises(ValueError, match="has zero length"):
        normalise([[1.0, 0, 0], [1e-13, 0, 0]], min_norm=1e-12, what="frame", error=ValueError)
    with pytest.raises(UserError, match="NaN or infinite"):
        normalise([np.nan, 1.0, 0.0], what="normal")
    np.testing.assert_array_equal(normalise([0.0, 2.0, 0.0], min_norm=1e-9, what="a"), [0.0, 1.0, 0.0])


@pytest.mark.parametrize("q,joint_type,decimals,text", [
    (math.pi / 3, REVOLUTE, 1, "60.0 deg"), (math.pi / 3, REVOLUTE, 2, "60.00 deg"),
    (0.2345, PRISMATIC, 1, "23.4 cm"), (0.2, PRISMATIC, 2, "20.00 cm"), (-0.5, PRISMATIC, 0, "-50 cm"),
    (float("nan"), REVOLUTE, 1, NO_LABEL_TEXT), (float("nan"), PRISMATIC, 2, NO_LABEL_TEXT),
])
def test_format_q(q, joint_type, decimals, text):
    assert format_q(q, joint_type, decimals) == text


@pytest.mark.parametrize("q,joint_type", [(1.0, REVOLUTE), (-0.25, REVOLUTE), (0.123, PRISMATIC), (0.0, PRISMATIC)])
def test_format_q_reads_back(q, joint_type):
    """What format_q writes, parse_quantity reads: the same joint type and q to the shown digits."""
    value, kind = parse_quantity(format_q(q, joint_type, 6).replace(" ", ""))
    assert kind == joint_type and value == pytest.approx(q, abs=1e-6)


def test_normalise_of_an_overflowing_vector_warns_nothing():
    """1e300 components: the error alone, without numpy's RuntimeWarning (two stderr lines in a shell)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(UserError, match="infinite"):
            normalise([1e300, 1e300, 0.0], what="v")
    printed = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert not printed, printed


def test_point_line_distance_by_hand():
    """(3, 4, 9) from the z axis is 5 m, whatever the direction's length; a point on the line is 0;
    stacks broadcast."""
    import numpy as np

    from articulated_dataset.core.units import point_line_distance_m

    assert point_line_distance_m([3.0, 4.0, 9.0], [0, 0, 0], [0, 0, 2.0]) == pytest.approx(5.0)
    assert point_line_distance_m([1.0, 1.0, 5.0], [1.0, 1.0, 0.0], [0, 0, -1.0]) == pytest.approx(0.0)
    np.testing.assert_allclose(point_line_distance_m([[0, 2.0, 0], [0, 0, 7.0]], [0, 0, 0], [1.0, 0, 0]), [2.0, 7.0])
