"""``artdata export-model``: the dense network as ONNX (onnxruntime's outputs against PyTorch's) and
checkpoints as safetensors pairs (read back without pickle, refused when the pair does not hold)."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("safetensors")

from click.testing import CliRunner  # noqa: E402

from articulated_dataset.cli import main  # noqa: E402
from articulated_dataset.core.errors import UserError  # noqa: E402
from articulated_dataset.methods import shipped_models  # noqa: E402
from articulated_dataset.methods.safetensors_checkpoint import (  # noqa: E402
    checkpoint_difference,
    read_safetensors_checkpoint,
    write_safetensors_checkpoint,
)
from helpers_core import assert_one_line_error, generated_split  # noqa: E402

pytestmark = pytest.mark.skipif(not shipped_models(), reason="this checkout ships no weights")


def _run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_onnx_export_of_the_dense_network_matches_pytorch(tmp_path):
    """onnxruntime runs the exported graph on a random batch (another size than the export's check
    batch: the batch axis is free) within ``ONNX_ATOL + ONNX_RTOL |torch|`` of PyTorch's outputs."""
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.dense.checkpoint import build_dense_model, load_dense_checkpoint
    from articulated_dataset.methods.export import ONNX_ATOL, ONNX_INPUT, ONNX_OUTPUTS, ONNX_RTOL

    out = tmp_path / "dense-drawer.onnx"
    res = _run("export-model", "--model", "dense", "--class", "drawer", "--format", "onnx", "--out", out)
    assert res.exit_code == 0, res.output
    assert "onnxruntime's outputs on a random batch" in res.output
    props = {p.key: p.value for p in onnx.load(out).metadata_props}
    assert props["artdata_class_name"] == "drawer" and json.loads(props["artdata_joint_types"]) == ["prismatic"]

    net = build_dense_model(load_dense_checkpoint(resolve_model("dense", "drawer").path))
    cfg = net.config
    x = np.random.default_rng(5).standard_normal((3, 9, cfg.height_px, cfg.width_px)).astype(np.float32)
    got = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"]).run(list(ONNX_OUTPUTS), {ONNX_INPUT: x})
    with torch.inference_mode():
        want = net.split(net(torch.from_numpy(x)))
    for name, a in zip(ONNX_OUTPUTS, got):
        b = want[name].numpy()
        assert a.shape == b.shape and a.shape[0] == 3, name
        np.testing.assert_allclose(a, b, rtol=ONNX_RTOL, atol=ONNX_ATOL, err_msg=name)

    assert_one_line_error(_run("export-model", "--model", "dense", "--class", "drawer", "--format", "onnx",
                               "--out", out), "exists; pass --overwrite")
    assert_one_line_error(_run("export-model", "--model", "mdn-small", "--class", "drawer", "--format", "onnx",
                               "--out", tmp_path / "m.onnx"), "the ONNX export covers the dense network")


def _training_checkpoint(path):
    """A dense checkpoint as ``artdata train`` writes it (``torch.save``, with optimizer state whose
    keys are whole numbers and RNG state) from the shipped microwave model; the checkpoint."""
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.dense.checkpoint import load_dense_checkpoint

    ckpt = dict(load_dense_checkpoint(resolve_model("dense", "microwave").path))
    ckpt["optimizer_state"] = {"state": {0: {"step": torch.tensor(3.0), "exp_avg": torch.zeros(4)}},
                               "param_groups": [{"lr": 1e-3, "params": [0]}]}
    ckpt["rng_state"] = torch.zeros(8, dtype=torch.uint8)
    torch.save(ckpt, path)
    return ckpt


def test_a_training_checkpoint_exports_to_a_pair_that_predicts_the_same(tmp_path):
    """``--format safetensors`` of a ``.pt`` (still read with ``weights_only``) writes the checkpoint
    without its training state; the pair reads back bit for bit and ``--model`` takes it."""
    import articulated_dataset as ad
    from articulated_dataset.methods.shipped import without_training_state

    ckpt = _training_checkpoint(tmp_path / "run.pt")
    res = _run("export-model", "--model", tmp_path / "run.pt", "--format", "safetensors",
               "--out", tmp_path / "run.safetensors")
    assert res.exit_code == 0, res.output
    back = read_safetensors_checkpoint(tmp_path / "run.safetensors")
    assert checkpoint_difference(without_training_state(ckpt), back) is None
    assert "optimizer_state" not in json.loads((tmp_path / "run.json").read_text())
    from safetensors.torch import load_file  # the weights file alone is the network's state_dict

    assert set(load_file(tmp_path / "run.safetensors")) == set(ckpt["model_state"])
    depth = np.zeros((108, 192))
    depth[30:80, 60:140] = 1.5  # a flat box face 1.5 m away
    K = np.array([[150.0, 0, 95.5], [0, 150.0, 53.5], [0, 0, 1]])
    estimates = [ad.estimate(depth, K, "microwave", model=str(tmp_path / name)).to_dict()["joints"]
                 for name in ("run.pt", "run.safetensors")]
    assert estimates[0] == estimates[1]


@pytest.mark.parametrize("damage", ["json-edited", "json-missing", "json-array", "weights-truncated",
                                    "tensor-unnamed"])
def test_a_pair_that_does_not_hold_is_one_line(tmp_path, damage):
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.mdn.checkpoint import read_checkpoint_file

    ckpt = read_checkpoint_file(resolve_model("dense", "toaster").path)
    st, js = write_safetensors_checkpoint(ckpt, tmp_path / "m.safetensors")
    needle = {"json-edited": "not the configuration these weights were written with",
              "json-missing": "m.json is missing", "json-array": "not a JSON object",
              "weights-truncated": "not a readable safetensors file",
              "tensor-unnamed": "holds tensors its configuration does not name"}[damage]
    if damage == "json-edited":
        js.write_text(js.read_text().replace('"class_name": "toaster"', '"class_name": "drawer"'))
    elif damage == "json-missing":
        js.unlink()
    elif damage in ("json-array", "tensor-unnamed"):  # a consistent pair (the weights record this JSON) of bad content
        config = json.loads(js.read_text())
        if damage == "tensor-unnamed":
            config["model_state"].popitem()
        _write_pair_of(st, js, [config] if damage == "json-array" else config, _tensors(st))
    else:
        st.write_bytes(st.read_bytes()[:-100])
    res = _run("export-model", "--model", st, "--format", "safetensors", "--out", tmp_path / "copy.safetensors")
    assert_one_line_error(res, needle)
    assert not (tmp_path / "copy.safetensors").exists()


def _tensors(path) -> dict:
    from safetensors.torch import load_file

    return load_file(path)


def _write_pair_of(st, js, config, tensors) -> None:
    """``st`` and ``js`` rewritten as a pair whose weights record ``config``'s SHA-256."""
    import hashlib

    from safetensors.torch import save_file

    from articulated_dataset.methods.safetensors_checkpoint import CONFIG_SHA256_KEY

    text = json.dumps(config)
    js.write_text(text)
    save_file(tensors, st, metadata={CONFIG_SHA256_KEY: hashlib.sha256(text.encode()).hexdigest()})


@pytest.mark.parametrize("value, needle", [(float("nan"), "JSON holds finite numbers only"),
                                           ({1: 2}, "a key that is not a string"),
                                           ({"__tensor__": "x"}, "stands for a tensor"),
                                           ({1, 2}, "holds a set")])
def test_what_json_cannot_hold_is_refused_before_writing(tmp_path, value, needle):
    with pytest.raises(UserError, match=needle):
        write_safetensors_checkpoint({"format": "artdata-dense", "extra": value, "model_state": {}},
                                     tmp_path / "m.safetensors")
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def microwave_split(tmp_path_factory):
    """A one-object microwave test split, as ``artdata generate`` writes it."""
    return generated_split(tmp_path_factory.mktemp("export-split"), "microwave", 1, seed=3)


@pytest.mark.parametrize("kind", ["dense", "mdn"])
def test_training_refuses_a_safetensors_name(microwave_split, tmp_path, kind):
    """``train`` writes ``torch.save`` files: one named ``.safetensors`` would be read as a pair and load nowhere."""
    split = microwave_split
    res = _run("train", "--model", kind, "--class", "microwave", split, "--out", tmp_path / "m.safetensors")
    assert_one_line_error(res, "training writes a torch checkpoint", "export-model --model m.pt --format safetensors")
    assert not (tmp_path / "m.safetensors").exists()
