"""Helpers for tests that ingest real captures: write one capture folder entry."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image


def write_capture(folder: Path, name: str, s: dict, K: np.ndarray, labels: dict | None) -> None:
    """A real capture of the stored sample ``s`` at the training resolution: 16-bit PNG (mm), BINARY
    mask (no part labels), camera.json and, if given, ``NAME.labels.json``."""
    folder.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.rint(s["depth"].astype(np.float64) * 1000).astype(np.uint16)).save(folder / f"{name}.png")
    Image.fromarray((s["mask"] > 0).astype(np.uint8) * 255).save(folder / f"{name}.mask.png")
    H, W = s["depth"].shape
    (folder / "camera.json").write_text(json.dumps({"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
                                                    "width": W, "height": H}))
    if labels is not None:
        (folder / f"{name}.labels.json").write_text(json.dumps(labels))
