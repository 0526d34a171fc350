"""articulated_dataset: synthetic articulated-object depth data, benchmark and baselines.

Importing the package selects MuJoCo's EGL offscreen backend unless ``MUJOCO_GL`` is
already set (``MUJOCO_GL=osmesa`` for the software fallback).
"""

import os as _os

_os.environ.setdefault("MUJOCO_GL", "egl")
if _os.environ["MUJOCO_GL"] in ("egl", "osmesa"):
    _os.environ.setdefault("PYOPENGL_PLATFORM", _os.environ["MUJOCO_GL"])

from articulated_dataset.core import compat as _compat

_compat.install()

__version__ = "0.1.0"

#: Version of the on-disk shard format (bump when stored samples change).
FORMAT_VERSION = "1.0"


def estimate(depth_m, K, class_name, mask=None, model="dense", mirror=True, precision="float32", *, point=None,
             box=None):
    """Estimate an object's articulation from one depth image: see
    :func:`articulated_dataset.methods.estimation.estimate` (imports torch on first use)."""
    from articulated_dataset.methods.estimation import estimate as _estimate

    return _estimate(depth_m, K, class_name, mask=mask, model=model, mirror=mirror, precision=precision, point=point,
                     box=box)


def load_model(name, class_name=None):
    """A shipped model (``"dense"``, ``"dense-kinect2"``, ``"mdn-small"``, with the class) or a
    checkpoint file, ready to use: ``.estimate(depth_m, K)`` one depth image, ``.predict(split)``
    a split.  See :func:`articulated_dataset.methods.load.load_model` (imports torch on first use)."""
    from articulated_dataset.methods.load import load_model as _load_model

    return _load_model(name, class_name)


def __getattr__(name):
    """Old top-level module names (``articulated_dataset.registry`` ...), moved in 0.2."""
    return _compat.moved_attribute(name)
