"""``artdata train --resume`` of a checkpoint whose ``data`` record is not a mapping: one line
naming the file, which is kept, for the MDN and the dense model (not an ``AttributeError: 'list'
object has no attribute 'get'`` traceback)."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from click.testing import CliRunner  # noqa: E402

from articulated_dataset.cli import main  # noqa: E402
from articulated_dataset.generation import GenerationConfig, generate_split  # noqa: E402

MODELS = {"mdn": ["--small", "--epochs", "2", "--batch-size", "16", "--components", "3"],
          "dense": ["--model", "dense", "--epochs", "2", "--width", "4", "--batch-size", "16"]}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("ckdata")
    return generate_split(GenerationConfig("cabinet", split="train", n_objects=2, images_per_object=4), root)


def _train(data, out, model, *extra):
    return CliRunner().invoke(main, ["train", "--model", "mdn", "--class", "cabinet", str(data), "--out", str(out),
                                     "--val-fraction", "0", "-q", *MODELS[model], *extra])


@pytest.mark.parametrize("record", [[1, 2], "split", 7])
@pytest.mark.parametrize("model", list(MODELS))
def test_a_data_record_that_is_not_a_mapping_is_one_line(data, tmp_path, model, record):
    out = tmp_path / "m.pt"
    assert _train(data, out, model).exit_code == 0
    ckpt = torch.load(out, weights_only=True)
    ckpt.update(data=record, finished=False)
    ckpt["epoch" if model == "mdn" else "step"] = 1
    torch.save(ckpt, out)
    before = out.read_bytes()
    result = _train(data, out, model, "--resume")
    err = [line for line in result.stderr.strip().splitlines() if "no validation objects" not in line]
    assert result.exit_code == 2 and len(err) == 1 and err[0].startswith("artdata: error:"), (err, result.exception)
    assert "'data'" in err[0] and str(out) in err[0]
    assert out.read_bytes() == before
