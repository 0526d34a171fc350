"""Independent renderer: pyrender on yourdfpy's parse of the same URDF agrees with MuJoCo."""

import json
import subprocess
import sys

import pytest

from articulated_dataset.classes.registry import class_names
from helpers_core import ROOT

#: Where the cross-check script lies (beside the shared test modules).
HERE = ROOT / "tests"
#: A gross-error check (a wrong camera orientation, a misplaced part, a wrong joint sign
#: disagree on most pixels).  pyrender's projection differs from MuJoCo's by a fraction of a
#: pixel, which moves silhouette edges of small objects (up to ~10% of their pixels) and,
#: on surfaces seen at grazing angles, depth by up to ~1 cm.  K itself is checked exactly
#: against MuJoCo's rasterisation in test_camera_intrinsics_match_mujoco_rasterisation.
MAX_SILHOUETTE_DISAGREEMENT = 0.15
MAX_MEDIAN_DEPTH_DIFF_M = 0.012


@pytest.fixture(scope="module")
def pyrender_stats():
    out = subprocess.run([sys.executable, str(HERE / "pyrender_crosscheck.py"), "3", *class_names()], cwd=HERE,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    return {r["class"]: r for r in rows}


@pytest.mark.parametrize("name", class_names())
def test_pyrender_and_mujoco_render_the_same_depth(pyrender_stats, name):
    stats = pyrender_stats[name]
    assert stats["pixels"] > 100
    assert stats["silhouette_disagreement"] < MAX_SILHOUETTE_DISAGREEMENT
    assert stats["median_abs_depth_diff_m"] < MAX_MEDIAN_DEPTH_DIFF_M


def test_camera_intrinsics_match_mujoco_rasterisation():
    """Boxes of many sizes cover exactly the pixel centres that K predicts."""
    import mujoco
    import numpy as np

    from articulated_dataset.core.camera import CameraConfig, project
    from articulated_dataset.generation.mujoco_scene import build_model, set_configuration
    from articulated_dataset.generation.render import process_renderer

    cam = CameraConfig()
    renderer = process_renderer(cam)
    distance_m = 2.0
    for half_width_m in np.linspace(0.05, 0.6, 12):
        for centre_z_m in (0.0, 0.13):
            urdf = ('<robot name="r"><link name="base"><collision name="a"><geometry>'
                    f'<box size="0.01 {2 * half_width_m} {half_width_m}"/></geometry></collision></link></robot>')
            model = build_model(urdf, dict(x_m=distance_m, y_m=0.0, z_m=centre_z_m, yaw_rad=0.0), cam)
            data = mujoco.MjData(model)
            set_configuration(model, data, np.zeros(0, dtype=int), [])
            renderer.bind(model)
            depth, _ = renderer.render(data)
            front = distance_m - 0.005
            corners = np.array([[front, half_width_m, centre_z_m + half_width_m / 2],
                                [front, -half_width_m, centre_z_m - half_width_m / 2]])
            (u0, v0), (u1, v1) = project(corners, cam.K)[0]
            assert np.array_equal(np.nonzero((depth > 0).any(0))[0], np.arange(np.ceil(u0), np.floor(u1) + 1))
            assert np.array_equal(np.nonzero((depth > 0).any(1))[0], np.arange(np.ceil(v0), np.floor(v1) + 1))
