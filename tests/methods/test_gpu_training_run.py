"""scripts/gpu_training_run.py, the script a GPU machine runs, exercised on the CPU."""

import json
import subprocess
import sys

import pytest

torch = pytest.importorskip("torch")

from articulated_dataset.methods import WEIGHTS_DIR  # noqa: E402
from helpers_core import ROOT


@pytest.mark.slow
def test_gpu_training_run_script_on_the_cpu(tmp_path):
    """scripts/gpu_training_run.py (what a GPU machine runs) as a CPU smoke test: it generates the
    split, sizes the dense model's epochs to its deadline, trains from the shipped weights and
    leaves an unfitted finished checkpoint whose record names the split and the machine."""
    repo = ROOT
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, str(repo / "scripts" / "gpu_training_run.py"), "--class", "microwave",
                        "--seed", "5", "--objects", "3", "--init-from", str(WEIGHTS_DIR / "dense-microwave.safetensors"),
                        "--minutes", "0.5", "--batch-size", "16", "--val-fraction", "0.34", "--workers", "1",
                        "--device", "cpu", "--no-mdn", "--out", str(out), "--work", str(tmp_path / "work")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    run = json.loads((out / "run.json").read_text())
    assert run["return_codes"] == {"dense": 0}
    info = json.loads((out / "dense-run.json").read_text())
    assert info["epochs"] >= 1 and info["n_images"] == 48
    ckpt = torch.load(out / "dense-microwave.pt", map_location="cpu", weights_only=True)
    assert ckpt["finished"] and ckpt.get("calibration") is None
    assert ckpt["data"]["generated"] == {"class_name": "microwave", "seed": 5, "n_objects": 3}
    assert ckpt["train_config"]["init_from"] == str(WEIGHTS_DIR / "dense-microwave.safetensors")
