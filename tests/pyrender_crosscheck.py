"""Render one generated object with pyrender (from yourdfpy's collision scene) and with
MuJoCo, and print JSON statistics of their agreement.  Run as a script by
tests/generation/test_render_crosscheck.py as ``python pyrender_crosscheck.py OBJECT_INDEX CLASS...`` (a subprocess keeps the two renderers' GL contexts apart).

pyrender's IntrinsicsCamera puts pixel centres at half-integer coordinates, ours (OpenCV)
at integers: its principal point is ours + 0.5 px.
"""

import json
import os
import sys
import tempfile

os.environ["PYOPENGL_PLATFORM"] = "egl"

import numpy as np  # noqa: E402
import pyrender  # noqa: E402
import yourdfpy  # noqa: E402

from helpers_core import compile_object, final_object, render_at  # noqa: E402

PYRENDER_PIXEL_CENTRE_OFFSET = 0.5


_RENDERERS = {}


def _renderer(width: int, height: int):
    """One pyrender context per process: re-creating it after MuJoCo's fails on EGL."""
    if (width, height) not in _RENDERERS:
        _RENDERERS[(width, height)] = pyrender.OffscreenRenderer(width, height)
    return _RENDERERS[(width, height)]


def main(class_name: str, index: int) -> None:
    config, sample = final_object(class_name, index=index)
    urdf, model, data, info, labels = compile_object(config, sample)
    obj_class = config.obj_class
    q = np.array([0.4 * (hi - lo) + lo for lo, hi in obj_class.table.q])
    depth_mj, _ = render_at(config, model, data, info, q)
    with tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False) as f:
        f.write(urdf)
    robot = yourdfpy.URDF.load(f.name, build_scene_graph=False, build_collision_scene_graph=True,
                               load_meshes=False, load_collision_meshes=True)
    robot.update_cfg({j.name: float(q[i]) for i, j in enumerate(obj_class.joints)})
    tm = robot.collision_scene
    c, s = np.cos(sample.pose["yaw_rad"]), np.sin(sample.pose["yaw_rad"])
    world_T_base = np.eye(4)
    world_T_base[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    world_T_base[:3, 3] = [sample.pose["x_m"], sample.pose["y_m"], sample.pose["z_m"]]
    scene = pyrender.Scene()
    for name, geom in tm.geometry.items():
        for node in tm.graph.geometry_nodes[name]:
            scene.add(pyrender.Mesh.from_trimesh(geom, smooth=False), pose=world_T_base @ tm.graph[node][0])
    K = config.camera.K
    cam = pyrender.IntrinsicsCamera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2] + PYRENDER_PIXEL_CENTRE_OFFSET,
                                    cy=K[1, 2] + PYRENDER_PIXEL_CENTRE_OFFSET, znear=0.05, zfar=12.0)
    cam_pose = np.eye(4)  # OpenGL camera (looks down -z, y up) in our camera frame (x fwd, y left, z up)
    cam_pose[:3, :3] = [[0, 0, -1], [-1, 0, 0], [0, 1, 0]]
    scene.add(cam, pose=cam_pose)
    depth_pr = _renderer(config.camera.width_px, config.camera.height_px).render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
    both = (depth_pr > 0) & (depth_mj > 0)
    print(json.dumps({
        "class": class_name,
        "pixels": int((depth_mj > 0).sum()),
        "silhouette_disagreement": float(((depth_pr > 0) != (depth_mj > 0)).sum() / max((depth_mj > 0).sum(), 1)),
        "median_abs_depth_diff_m": float(np.median(np.abs(depth_pr - depth_mj)[both])),
    }))


if __name__ == "__main__":
    for name in sys.argv[2:]:
        main(name, int(sys.argv[1]))
