"""Freshly generated arrays against committed SHA-256 digests (docs/generation.md, Reproducibility).

A tiny split of every class (2 objects x 2 images, seed 0): its labels must match the digests on
every supported MuJoCo release, its depth and masks on :data:`GOLDEN_MUJOCO_VERSION`, the release
the digests were made with.  Both rest on Mesa's software rasteriser (llvmpipe, through EGL or
OSMesa); another GL driver rasterises silhouette edges its own way, so there the comparison is
skipped.  After a deliberate change of the generated data, print the new digests with
``python tests/project/test_golden_bytes.py`` and commit them with the change.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from articulated_dataset.classes.registry import class_names
from articulated_dataset.core.mujoco_support import installed_mujoco_version
from articulated_dataset.format import LABEL_FIELDS, Split
from articulated_dataset.generation import GenerationConfig, generate_split

#: The MuJoCo release whose depth and masks :data:`GOLDEN` holds.
GOLDEN_MUJOCO_VERSION = "4.0.1"
#: The split each digest is made from: small, so that every class renders in a few seconds.
N_OBJECTS = 2
IMAGES_PER_OBJECT = 2
#: Substring of ``GL_RENDERER`` of the rasteriser the digests were made with.
GOLDEN_RASTERISER = "llvmpipe"

#: {class: {"labels", "depth", "mask": SHA-256 of :func:`digests`' arrays}}.
GOLDEN = {
    "cabinet": {"labels": "a36c28b68913350d6b8d19d9c634fdb1f976479b793611e976d833036d55ba70",
                "depth": "29d691e3c7a79b575f7ee0ccf5cd7e8143da4dc3c67257bf4665daf8d92e222d",
                "mask": "bc1c6474235f7d108f0556666e9486c50276d595368ffde31afe78cc6010104c"},
    "drawer": {"labels": "3d453320d8860fba9c5078c102f0069fdbbf1d52f0279f3076bbda8db3b715d6",
               "depth": "41e191c46f5b4f5bfafae1175722a50f0fc3440684a5d09533057fd53a06ef31",
               "mask": "51eef1dfd884aaf74467e8c09a616f60a1355c947fc10a61b2055b6904e39ef9"},
    "microwave": {"labels": "57492c07d74f690bf8cf90794686a9372f1c38ed31fb223a08e5b188157c8f86",
                  "depth": "287b575256afb763f37d6bbe21a3f17e60823587c7cee1aabc0eac77ae68e91f",
                  "mask": "84ec443155d4712369a89177af2748d8ae4196baeada5637e0feec33dbe2c627"},
    "toaster": {"labels": "a850b19f8f143376517ab3bd4867a0391c2a802e8bf544b2ac58855a35200c07",
                "depth": "68bca59f17397e570fe31ee17068aa83927f938fd97abbb6d1dadc861979b790",
                "mask": "e531b3c9686fed5a214aaa99930f40f2edb827e4ae2565d3bc8e0b7f05d70e91"},
    "cabinet2": {"labels": "f64ba5fb5f595c697eb5a6b9c06ea8bc6e526dd767cf4012f501aed2d2fdf358",
                 "depth": "bc06f1258b8b479125dbb6a5e3a385ea48cddb6ed2e395a8b234d55540460fc9",
                 "mask": "42e5b2a37a572c92f1d2ae20f7c99e367da0dbf8d169403e0d278e8b5bbf037f"},
    "refrigerator": {"labels": "1daa3e961c01e12420f0d061d26f2a90b8d75a78f0c875d02e436c95bbf5a62a",
                     "depth": "8ed49f7451a6f25f68ef595e5d20a38280cf03a5854631a1a70395fb23cecd99",
                     "mask": "a7a79311b800df526cc377e550dd67313c0969d152bd85eaf1dd52b90d24aba9"},
    "oven": {"labels": "ccd7a0257d28066335800f4fe3011b288dc92b1d2f57697ceec5d882b173e470",
             "depth": "28e4334b0cec38a20cd09434fc1055cc246cf7429cc6a20e4707b4e99a6d8d9a",
             "mask": "eb5320872ab70d34fdc16d5c01a44ba9a6614d166544e5470c334fa9c07be2cd"},
    "dishwasher": {"labels": "046f8bacf162b73ae0f091e3902513b630ccd2edf65e9d1684b0049be39ef6e9",
                   "depth": "b714455d959338f8ee34dfa0ed5b89a446ab51c40af3d0b4534d546415949a0e",
                   "mask": "90fc0777962a79ae3fc2aac51167a16d2e5271d9ef42d5ad7f7735ac24c08e0c"},
    "lidded_box": {"labels": "2affc73035a79890626085d9cb145384a6a40af30476885d3fbc1f5ef3d8c732",
                   "depth": "e2c1492fb53a9eb7833e6ad6d386075eaad470923f915d64bfce0aef1877ce56",
                   "mask": "dee1c44bc9009080e1d699e29a74250fb187ff90fe12f4867fa045ab39cc0d2d"},
}


def _digest(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over each array's name, dtype, shape and bytes (little-endian, C order), in name order."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        a = a.astype(a.dtype.newbyteorder("<"), copy=False)
        h.update(f"{name} {a.dtype.str} {a.shape}\n".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def digests(split_dir: Path) -> dict[str, str]:
    """The split's digests: every label field together, the depth, the masks."""
    with Split(split_dir) as split:
        labels = split.labels()
        return {"labels": _digest({name: labels[name] for name in LABEL_FIELDS}),
                "depth": _digest({"depth": split.read("depth")}), "mask": _digest({"mask": split.read("mask")})}


def generate_digests(root: Path) -> dict[str, dict[str, str]]:
    """:func:`digests` of a freshly generated tiny split of every class, under ``root``."""
    out = {}
    for name in class_names():
        config = GenerationConfig(name, n_objects=N_OBJECTS, images_per_object=IMAGES_PER_OBJECT)
        out[name] = digests(generate_split(config, root))
    return out


def gl_renderer() -> str:
    """``GL_RENDERER`` of the offscreen context current in this process (the renderer's, after
    :func:`generate_digests`)."""
    from OpenGL import GL

    name = GL.glGetString(GL.GL_RENDERER)
    return "an unknown GL driver" if name is None else name.decode(errors="replace")


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    digests_now = generate_digests(tmp_path_factory.mktemp("golden"))
    renderer = gl_renderer()
    if GOLDEN_RASTERISER not in renderer:
        pytest.skip(f"the digests are of Mesa's {GOLDEN_RASTERISER} rasteriser; this machine renders with {renderer}")
    return digests_now


@pytest.mark.parametrize("class_name", class_names())
def test_labels_match_the_committed_digests(fresh, class_name):
    assert fresh[class_name]["labels"] == GOLDEN[class_name]["labels"], class_name


@pytest.mark.parametrize("class_name", class_names())
def test_depth_and_masks_match_the_committed_digests(fresh, class_name):
    found = installed_mujoco_version()
    if found != GOLDEN_MUJOCO_VERSION:
        pytest.skip(f"the depth and mask digests are of MuJoCo {GOLDEN_MUJOCO_VERSION}; installed: MuJoCo {found} "
                    "(labels are still compared)")
    assert fresh[class_name]["depth"] == GOLDEN[class_name]["depth"], class_name
    assert fresh[class_name]["mask"] == GOLDEN[class_name]["mask"], class_name


if __name__ == "__main__":  # print the digests of this machine's MuJoCo, to commit as GOLDEN
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        found = generate_digests(Path(tmp))
    print(f"# MuJoCo {installed_mujoco_version()}, {gl_renderer()}", file=sys.stderr)
    print(json.dumps(found, indent=4))
