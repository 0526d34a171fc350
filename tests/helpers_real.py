"""Shared functions of the tests that ingest real captures: write one capture folder entry."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from click.testing import CliRunner
from PIL import Image

from articulated_dataset.cli import main
from articulated_dataset.format import open_split


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


def ingest_uneven_cabinet2(tiny_root: Path, root: Path) -> Path:
    """An ingested cabinet2 real split under ``root``: object 0 ("kitchen") has two views labelled with
    q and axis_pose only (no geometry, no object pose; binary mask: no part pixels), object 1 one
    view without labels.  Returns the split folder."""
    _, shards = open_split(tiny_root / "cabinet2" / "test")
    sh = shards[0]
    for name, row in (("a", 0), ("c", 5)):
        s = sh.sample(row)
        write_capture(root / "caps", name, s, sh.K, {"q": s["q"].tolist(), "axis_pose": s["axis_pose"].tolist(),
                                                     "object": "kitchen"})
    write_capture(root / "nolabels", "b", sh.sample(3), sh.K, None)
    for folder, extra in (("caps", []), ("nolabels", ["--append"])):
        res = CliRunner().invoke(main, ["ingest", str(root / folder), "--class", "cabinet2", "--out", str(root / "out"),
                                        "-q", *extra])
        assert res.exit_code == 0, res.output
    return root / "out" / "cabinet2" / "real"
