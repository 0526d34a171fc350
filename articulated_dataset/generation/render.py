"""Stage 4 of the pipeline: offscreen depth + part-mask rendering with MuJoCo.

One :class:`DepthRenderer` per process owns the GL context and one ``MjrContext``; every
frame is a single render pass whose colour buffer holds segmentation ids and whose depth
buffer holds depth, read back together.  Models made only of primitive geoms (all built-in
classes) share the one ``MjrContext``; a model with meshes, textures or height fields gets
one built for its assets, reused by later models with the same assets.
"""

from __future__ import annotations

import atexit
import hashlib
import logging
import os
from collections import OrderedDict

import mujoco
import numpy as np

from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.core.errors import RenderError

#: MuJoCo geom group of scene and occluder geoms (articulated_dataset.scenes, .occluders).
CONTEXT_GEOM_GROUP = 3

log = logging.getLogger(__name__)

_MISSING_GL_HELP = (
    "cannot create an offscreen OpenGL context with MUJOCO_GL={backend!r}: {exc}. "
    "Rendering needs EGL from Mesa (Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri) "
    "or OSMesa (apt-get install libosmesa6, then MUJOCO_GL=osmesa)."
)


def _make_gl_context(width: int, height: int):
    backend = os.environ.get("MUJOCO_GL", "egl").lower()
    try:
        if backend == "egl":
            from mujoco.egl import GLContext
        elif backend == "osmesa":
            from mujoco.osmesa import GLContext
        elif backend == "glfw":
            from mujoco.glfw import GLContext
        else:
            raise RenderError(f"unsupported MUJOCO_GL={backend!r}; use egl or osmesa")
        ctx = GLContext(width, height)
        ctx.make_current()
        return ctx
    except RenderError:
        raise
    except Exception as exc:
        raise RenderError(_MISSING_GL_HELP.format(backend=backend, exc=exc)) from exc


def _needs_own_context(model: mujoco.MjModel) -> bool:
    return bool(model.nmesh or model.ntex or model.nhfield or model.nskin)


#: Model arrays an ``MjrContext`` uploads (meshes, textures, height fields, skins): two models
#: equal in all of them can share a context (e.g. every object of a third-party URDF class,
#: which differ only in pose).
_CONTEXT_ASSET_FIELDS = (
    "mesh_vertadr", "mesh_vertnum", "mesh_faceadr", "mesh_facenum", "mesh_normaladr", "mesh_texcoordadr",
    "mesh_vert", "mesh_normal", "mesh_face", "mesh_facenormal", "mesh_facetexcoord", "mesh_texcoord",
    "tex_type", "tex_height", "tex_width", "tex_nchannel", "tex_data", "hfield_size", "hfield_nrow",
    "hfield_ncol", "hfield_data", "skin_vertnum", "skin_vert", "skin_face",
)
#: Asset-holding contexts kept per renderer (least recently used dropped first).
_ASSET_CONTEXT_CACHE_SIZE = 4


def _asset_key(model: mujoco.MjModel) -> bytes:
    h = hashlib.blake2b(digest_size=16)
    for name in _CONTEXT_ASSET_FIELDS:
        a = getattr(model, name, None)
        if a is not None:
            h.update(name.encode())
            h.update(np.ascontiguousarray(a).tobytes())
    return h.digest()


class DepthRenderer:
    """Renders z-depth (m) and per-geom segmentation of a model's camera.

    Create once per process; :meth:`bind` a model (cheap), then :meth:`render` frames.
    """

    def __init__(self, camera: CameraConfig):
        self.camera = camera
        self._gl = _make_gl_context(camera.width_px, camera.height_px)
        self._shared_con: mujoco.MjrContext | None = None
        self._asset_cons: OrderedDict[bytes, mujoco.MjrContext] = OrderedDict()
        self._con = None
        self._model = None
        self._rgb = np.zeros((camera.height_px, camera.width_px, 3), np.uint8)
        self._depth = np.zeros((camera.height_px, camera.width_px), np.float32)
        self._viewport = mujoco.MjrRect(0, 0, camera.width_px, camera.height_px)
        self._opt = mujoco.MjvOption()
        # The context render (``--scene``/``--occluders``) also draws their geom group; the
        # default render draws MuJoCo's default groups 0-2 only, as it always has.
        self._context_opt = mujoco.MjvOption()
        self._context_opt.geomgroup[CONTEXT_GEOM_GROUP] = 1
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FIXED

    def _context_for(self, model: mujoco.MjModel) -> mujoco.MjrContext:
        self._gl.make_current()
        if _needs_own_context(model):
            key = _asset_key(model)
            con = self._asset_cons.pop(key, None)
            if con is None:
                con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_50)
            self._asset_cons[key] = con
            while len(self._asset_cons) > _ASSET_CONTEXT_CACHE_SIZE:
                self._asset_cons.popitem(last=False)
        else:
            if self._shared_con is None:
                self._shared_con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_50)
            con = self._shared_con
        if con.offWidth < self.camera.width_px or con.offHeight < self.camera.height_px:
            raise RenderError(
                f"offscreen buffer {con.offWidth}x{con.offHeight} smaller than the image "
                f"{self.camera.width_px}x{self.camera.height_px}"
            )
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, con)
        return con

    def bind(self, model: mujoco.MjModel, camera_name: str = "camera") -> None:
        """Prepare rendering of ``model`` from its camera ``camera_name``."""
        self._model = model
        self._con = self._context_for(model)
        self._scn = mujoco.MjvScene(model, maxgeom=max(64, 2 * model.ngeom))
        self._scn.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 1
        self._scn.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 1
        cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera_name)
        if cam_id < 0:
            raise ValueError(f"model has no camera named {camera_name!r}")
        self._cam.fixedcamid = cam_id
        extent = model.stat.extent
        self._near = model.vis.map.znear * extent
        self._far = model.vis.map.zfar * extent

    def render(self, data: mujoco.MjData, depth_out: np.ndarray | None = None, *,
               context: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Render the bound model in state ``data`` (kinematics must be up to date).

        Returns ``(depth_m, geom_id)``: float32 z-depth along the optical axis in metres
        (0 where nothing was hit) and int32 MuJoCo geom ids (-1 for background), both
        (H, W) with row 0 at the top of the image.  ``depth_out`` (H, W) float32, if given,
        receives the depth (and is returned).  ``context``: also draw the scene and occluder
        geoms (group :data:`CONTEXT_GEOM_GROUP`); without it the object is rendered alone.
        """
        model = self._model
        opt = self._context_opt if context else self._opt
        mujoco.mjv_updateScene(model, data, opt, None, self._cam, mujoco.mjtCatBit.mjCAT_ALL, self._scn)
        mujoco.mjr_render(self._viewport, self._scn, self._con)
        mujoco.mjr_readPixels(self._rgb, self._depth, self._viewport, self._con)
        # Segmentation colour encodes (index in scene geoms + 1) in R, G, B (low byte first);
        # 0 = background.  Scenes of fewer than 255 geoms need only the red channel.
        ngeom = self._scn.ngeom
        rgb = self._rgb[::-1]
        if ngeom < 255:
            seg: np.ndarray = rgb[..., 0]
        else:
            seg = rgb[..., 0].astype(np.int32) | (rgb[..., 1].astype(np.int32) << 8) | (rgb[..., 2].astype(np.int32) << 16)
        lookup = np.full(ngeom + 1, -1, np.int32)
        for i in range(ngeom):
            g = self._scn.geoms[i]
            if g.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                lookup[i + 1] = g.objid
        geom_id = lookup[seg]
        buf = self._depth[::-1]
        near, far = self._near, self._far
        depth = np.empty(buf.shape, np.float32) if depth_out is None else depth_out
        # OpenGL depth buffer value d in [0, 1] -> linear z: z = n / (1 - d (1 - n / f)).
        np.multiply(buf, -(1.0 - near / far), out=depth)
        depth += 1.0
        np.divide(near, depth, out=depth)
        depth[buf >= 1.0] = 0.0
        return depth, geom_id

    def render_rgb(self, data: mujoco.MjData, out: np.ndarray | None = None, *, context: bool = False) -> np.ndarray:
        """A shaded colour image of the bound model (H, W, 3) uint8, row 0 at the top: the
        ``--rgb`` images (:mod:`articulated_dataset.generation.appearance`) and gallery
        previews.  ``out`` (H, W, 3) uint8, if given, receives it (and is returned);
        ``context`` as in :meth:`render`."""
        self._scn.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 0
        self._scn.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 0
        try:
            opt = self._context_opt if context else self._opt
            mujoco.mjv_updateScene(self._model, data, opt, None, self._cam, mujoco.mjtCatBit.mjCAT_ALL, self._scn)
            mujoco.mjr_render(self._viewport, self._scn, self._con)
            mujoco.mjr_readPixels(self._rgb, self._depth, self._viewport, self._con)
            if out is None:
                return self._rgb[::-1].copy()
            out[...] = self._rgb[::-1]
            return out
        finally:
            self._scn.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 1
            self._scn.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 1

    def close(self) -> None:
        """Release the rendering contexts and the GL context (a failure to free it is ignored)."""
        self._shared_con = self._con = None
        self._asset_cons.clear()
        if self._gl is not None:
            try:
                self._gl.free()
            except Exception:  # freeing at interpreter exit can fail harmlessly
                pass
            self._gl = None


_PROCESS_RENDERERS: dict[tuple[int, CameraConfig], DepthRenderer] = {}


def _close_process_renderers() -> None:
    """Free GL contexts before interpreter shutdown (OSMesa's destructor fails once modules
    are torn down, printing an ignored exception).  :func:`process_renderer` registers it to run
    at exit after each context is created, so it runs before the exit hooks the GL library
    registered meanwhile (MuJoCo 3.x's EGL module terminates its display in one, after which
    destroying a context fails with an EGLError that Python prints as ignored)."""
    for key in [k for k in _PROCESS_RENDERERS if k[0] == os.getpid()]:
        _PROCESS_RENDERERS.pop(key).close()


def process_renderer(camera: CameraConfig) -> DepthRenderer:
    """The renderer of this process for ``camera`` (created on first use, then reused).

    Keyed by process id too: a GL context never crosses a ``fork``.
    """
    key = (os.getpid(), camera)
    r = _PROCESS_RENDERERS.get(key)
    if r is None:
        r = _PROCESS_RENDERERS[key] = DepthRenderer(camera)
        atexit.unregister(_close_process_renderers)  # exit hooks run last registered first
        atexit.register(_close_process_renderers)
    return r
