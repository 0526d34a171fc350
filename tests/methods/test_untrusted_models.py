"""Checkpoints and model inputs from strangers: a zip checkpoint whose records declare more
than the file can hold is refused before ``torch.load`` allocates it; ``estimate`` takes a
tensor that requires grad; an estimate with a negative size is refused, not printed."""

from __future__ import annotations

import io
import struct
import zipfile

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from click.testing import CliRunner  # noqa: E402

import articulated_dataset  # noqa: E402
from articulated_dataset.cli import main  # noqa: E402
from articulated_dataset.core.errors import UserError  # noqa: E402
from articulated_dataset.format import Shard, open_split  # noqa: E402
from articulated_dataset.methods.mdn import checkpoint
from helpers_core import assert_one_line_error

#: Size of the zeros a crafted record inflates to: 64 MiB from a file of about 64 KB.
BOMB_BYTES = 64 << 20
#: Offset of the uncompressed size in a zip central-directory header (APPNOTE 4.3.12).
CENTRAL_UNCOMPRESSED_SIZE_OFFSET = 24
CENTRAL_HEADER_SIGNATURE = b"PK\x01\x02"


@pytest.fixture(scope="module")
def drawer_image(tiny_root):
    """(depth (H, W) float32 m, K (3, 3), split folder) of the tiny drawer test split's first image."""
    split = tiny_root / "drawer" / "test"
    _, shards = open_split(split)
    sh = Shard(shards[0].path)
    try:
        return sh.read("depth", 0), sh.K, split
    finally:
        sh.close()


def _records(replace: dict) -> bytes:
    """A real checkpoint's zip with some records' contents replaced (``{name suffix: (bytes, method)}``)."""
    buf = io.BytesIO()
    torch.save({"w": torch.zeros(4)}, buf)
    src = zipfile.ZipFile(io.BytesIO(buf.getvalue()))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as z:
        for info in src.infolist():
            hit = next((v for k, v in replace.items() if info.filename.endswith(k)), None)
            if hit is None:
                z.writestr(info.filename, src.read(info))
            else:
                z.writestr(info.filename, hit[0], compress_type=hit[1])
    return out.getvalue()


def _never_loaded(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("torch.load ran on a refused checkpoint")

    monkeypatch.setattr(torch, "load", fail)


def test_a_deflated_record_bomb_is_refused_before_torch_load(tmp_path, drawer_image, monkeypatch):
    path = tmp_path / "bomb.pt"
    path.write_bytes(_records({"data/0": (bytes(BOMB_BYTES), zipfile.ZIP_DEFLATED)}))
    assert path.stat().st_size < BOMB_BYTES / 100
    _never_loaded(monkeypatch)
    with pytest.raises(UserError, match="records declare") as info:
        checkpoint.read_checkpoint_file(path)
    assert str(path) in str(info.value)
    _, _, split = drawer_image
    result = CliRunner().invoke(main, ["predict", "--model", str(path), str(split), "--out",
                                       str(tmp_path / "p.h5"), "-q"])
    assert_one_line_error(result, "records declare")


def test_a_record_whose_sizes_lie_is_refused_before_torch_load(tmp_path, monkeypatch):
    data = bytearray(_records({}))
    at = data.index(CENTRAL_HEADER_SIGNATURE)  # the first record, stored: its sizes must be equal
    struct.pack_into("<I", data, at + CENTRAL_UNCOMPRESSED_SIZE_OFFSET, 1 << 20)
    path = tmp_path / "lie.pt"
    path.write_bytes(bytes(data))
    _never_loaded(monkeypatch)
    with pytest.raises(UserError, match="sizes are false"):
        checkpoint.read_checkpoint_file(path)


def test_a_checkpoint_written_by_torch_save_passes_the_record_check(tmp_path):
    from articulated_dataset.methods.mdn.model import MixtureDensityNetwork, ModelConfig

    state = MixtureDensityNetwork(ModelConfig(in_channels=4, target_dim=8, n_components=3, width=4,
                                              blocks=(1, 1))).state_dict()
    path = tmp_path / "state.pt"
    torch.save({"model_state": state}, path)
    loaded = checkpoint.read_checkpoint_file(path)
    assert all(torch.equal(loaded["model_state"][k], v) for k, v in state.items())


def test_estimate_takes_tensors_that_require_grad(drawer_image):
    depth, K, _ = drawer_image
    d = torch.from_numpy(np.array(depth)).requires_grad_(True)
    k = torch.from_numpy(np.array(K)).requires_grad_(True)
    est = articulated_dataset.estimate(d, k, "drawer")
    reference = articulated_dataset.estimate(depth, K, "drawer")
    np.testing.assert_allclose(est.axis_origin_m, reference.axis_origin_m)


def test_an_estimate_with_a_negative_size_is_refused(drawer_image, monkeypatch):
    from articulated_dataset.methods.dense import predict as dense_predict

    real = dense_predict.modes_to_arrays

    def negative_depth(*args, **kwargs):  # a checkpoint whose weights pass its checks but give nonsense
        arrays = real(*args, **kwargs)
        arrays["geometry"][:, 0] = -0.2
        return arrays

    monkeypatch.setattr(dense_predict, "modes_to_arrays", negative_depth)
    depth, K, _ = drawer_image
    with pytest.raises(UserError, match="depth below 0"):
        articulated_dataset.estimate(depth, K, "drawer")
