"""Values whose arithmetic overflows give the error line alone, without numpy's RuntimeWarning
(two more stderr lines) before it: an axis direction or quaternion of 1e300 components in a
label file, a ``.npy`` header declaring a shape whose size overflows."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from articulated_dataset.cli import main
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.units import normalise

CAMERA = {"fx": 100.0, "fy": 100.0, "cx": 95.5, "cy": 53.5, "width": 192, "height": 108}


def _capture(folder, labels=None, npy_header=None):
    folder.mkdir()
    depth = np.zeros((108, 192), np.uint16)
    depth[40:70, 80:120] = 1500
    if npy_header is None:
        Image.fromarray(depth).save(folder / "frame.png")
    else:
        import numpy.lib.format as F

        with open(folder / "frame.npy", "wb") as fh:
            F.write_array_header_1_0(fh, npy_header)
    (folder / "camera.json").write_text(json.dumps(CAMERA))
    if labels is not None:
        (folder / "frame.labels.json").write_text(json.dumps(labels))
    return folder


def _quiet(call):
    """``call()``; every warning it issues is recorded, as a shell would print it on stderr."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = call()
    printed = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert not printed, printed
    return result


def _one_line(args) -> str:
    result = _quiet(lambda: CliRunner().invoke(main, [str(a) for a in args]))
    err = result.stderr.strip()
    assert result.exit_code == 2 and len(err.splitlines()) == 1 and err.startswith("artdata: error:"), \
        (result.exit_code, err, result.exception)
    return err


@pytest.mark.parametrize("labels", [{"axis_direction": [[1e300, 1e300, 0]]},
                                    {"axis_pose": [[1.5, 0, 0, 1e200, 1e200, 0, 0]]},
                                    {"object_pose": [1.5, 0, 0, 1e300, 1e300, 0, 0]}],
                         ids=["direction", "axis quaternion", "object quaternion"])
def test_a_label_vector_whose_length_overflows_is_one_line(tmp_path, labels):
    folder = _capture(tmp_path / "cap", labels=labels)
    err = _one_line(["ingest", folder, "--class", "cabinet", "--out", tmp_path / "out", "-q"])
    assert "frame.labels.json" in err
    assert not (tmp_path / "out").exists()


def test_an_npy_header_whose_size_overflows_is_one_line(tmp_path):
    folder = _capture(tmp_path / "cap", npy_header={"descr": "<f8", "fortran_order": False, "shape": (2**62, 2**62)})
    err = _one_line(["ingest", folder, "--class", "cabinet", "--out", tmp_path / "out", "-q"])
    assert "frame.npy" in err


def test_normalise_of_an_overflowing_vector_warns_nothing():
    def call():
        with pytest.raises(UserError, match="infinite"):
            normalise([1e300, 1e300, 0.0], what="v")
    _quiet(call)
