"""``articulated_dataset.load_model``: a shipped model or a checkpoint file as a ready object whose
``estimate`` is ``articulated_dataset.estimate`` and whose ``predict`` is ``artdata predict``."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("safetensors")

import articulated_dataset as ad  # noqa: E402
from articulated_dataset.core.errors import UserError  # noqa: E402
from articulated_dataset.methods import shipped_models  # noqa: E402
from helpers_core import generated_split  # noqa: E402

pytestmark = pytest.mark.skipif(not shipped_models(), reason="this checkout ships no weights")


@pytest.fixture(scope="module")
def microwave_split(tmp_path_factory):
    """One test object of the microwave class (its 16 images), as ``artdata generate`` writes it."""
    return generated_split(tmp_path_factory.mktemp("load-model"), "microwave", 1, seed=31)


def _image(split, index: int = 3):
    import h5py

    with h5py.File(next(split.glob("shard-*.h5")), "r") as f:
        depth, K = f["depth"][index], f["K"][()]
    return depth, (K[0] if K.ndim == 3 else K)


def test_a_shipped_model_estimates_as_estimate_does(microwave_split):
    model = ad.load_model("dense-kinect2", "microwave")
    assert (model.name, model.kind, model.class_name, model.joint_types) == ("dense-kinect2", "dense", "microwave",
                                                                            ("revolute",))
    assert model.path.suffix == ".safetensors" and model.checkpoint["class_name"] == "microwave"
    depth, K = _image(microwave_split)
    est = model.estimate(depth, K)
    assert est.to_dict() == ad.estimate(depth, K, "microwave", model="dense-kinect2").to_dict()
    assert est.model == "dense-kinect2"
    net = model.network()
    assert isinstance(net, torch.nn.Module) and not net.training


def test_predict_returns_the_predictions_files_arrays(microwave_split, tmp_path):
    from articulated_dataset.benchmark.predictions import read_predictions

    model = ad.load_model("dense", "microwave")
    arrays = model.predict(microwave_split, tmp_path / "p.h5", mirror=False)
    attrs, per_class = read_predictions(tmp_path / "p.h5")
    assert attrs["method"] == "dense" and set(per_class) == {"microwave"}
    assert arrays.keys() == per_class["microwave"].keys() and len(arrays["sample_id"]) == 16
    for name, a in arrays.items():
        assert np.array_equal(a, per_class["microwave"][name]), name
    # another class's split is refused, not predicted by that class's model
    with pytest.raises(UserError, match="a 'cabinet' model, but the data is 'microwave'"):
        ad.load_model("dense", "cabinet").predict(microwave_split)


def test_a_checkpoint_file_loads_with_its_own_class(microwave_split, tmp_path):
    """A ``.pt`` as ``artdata train`` writes it (read with ``weights_only``) and the same
    checkpoint as a safetensors pair give the shipped model's estimate."""
    from articulated_dataset.methods.safetensors_checkpoint import write_safetensors_checkpoint

    shipped = ad.load_model("dense", "microwave")
    torch.save(shipped.checkpoint, tmp_path / "mine.pt")
    write_safetensors_checkpoint(shipped.checkpoint, tmp_path / "mine.safetensors")
    depth, K = _image(microwave_split, 7)
    want = shipped.estimate(depth, K).to_dict()
    for path in (tmp_path / "mine.pt", tmp_path / "mine.safetensors"):
        model = ad.load_model(path)
        assert (model.kind, model.class_name, model.path) == ("dense", "microwave", path)
        got = model.estimate(depth, K).to_dict()
        assert {k: v for k, v in got.items() if k != "model"} == {k: v for k, v in want.items() if k != "model"}
    with pytest.raises(UserError, match="a 'microwave' model, but the data is 'drawer'"):
        ad.load_model(tmp_path / "mine.pt", "drawer")


def test_wrong_names_and_an_mdn_estimate_are_one_line_errors():
    with pytest.raises(UserError, match="needs the object class"):
        ad.load_model("dense")
    with pytest.raises(UserError, match="no shipped 'dense' model for class 'bogus'"):
        ad.load_model("dense", "bogus")
    with pytest.raises(UserError, match="neither a shipped model"):
        ad.load_model("no-such-model.pt")
    if not any(m["name"] == "mdn-small" and m["class_name"] == "drawer" for m in shipped_models()):
        pytest.skip("no shipped mdn-small model")
    mdn = ad.load_model("mdn-small", "drawer")
    assert mdn.kind == "mdn" and mdn.name == "mdn-small" and mdn.joint_types == ("prismatic",)
    with pytest.raises(UserError, match="single-image estimates use a dense model"):
        mdn.estimate(np.ones((108, 192)), np.eye(3))


def test_load_model_is_exported_without_importing_torch():
    code = "import sys, articulated_dataset as ad; assert callable(ad.load_model); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
