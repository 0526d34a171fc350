"""How a gallery looks: colours, sizes and fonts (module constants), the depth colouring with
hill shading, and the geometry of a drawn joint axis (its extent over the part)."""

from __future__ import annotations

import math

import numpy as np

from articulated_dataset.core.rotations import quat_to_matrix
from articulated_dataset.format import PRISMATIC

#: Perceptually uniform colormap for depth; near pixels get the bright end.
DEPTH_CMAP = "viridis"
#: Colour of pixels without a depth return (neutral light grey, outside the colormap).
BACKGROUND_RGB = (0.88, 0.88, 0.88)
#: One colour per joint (j-th joint uses entry j mod len): red, white-ish magenta, orange,
#: cyan -- all far from viridis's purple-green-yellow and from the grey background.
JOINT_COLOURS = ("#ff1f3d", "#ff5cf4", "#ff8c00", "#00e5ff")
#: Hill-shading strength: fraction of a pixel's colour taken from the light-source shade.
SHADE_FRACTION = 0.35
#: Light direction for the hill shading (degrees): from the upper left, as usual for reliefs.
LIGHT_AZIMUTH_DEG = 315.0
LIGHT_ALTITUDE_DEG = 45.0
#: Revolute axes span the moving part's visible extent along the axis, plus this fraction
#: at each end; without visible part pixels, this fraction of the body's extent.
AXIS_MARGIN_FRACTION = 0.12
AXIS_LENGTH_FRACTION = 0.8
#: Length (m) of a revolute axis drawn without any extent to go by (no part or object
#: pixels, no geometry label).
DEFAULT_AXIS_LENGTH_M = 0.5
#: Layout (inches): panel width, title band above each sample, gap between samples,
#: header band above each split, footer band with the legend.
PANEL_WIDTH_IN = 3.2
TITLE_IN = 0.32
GAP_IN = 0.12
HEADER_IN = 0.42
FOOTER_IN = 0.34
#: Extra band height (inches) per further line of a wrapped split header / legend.
HEADER_LINE_IN = 0.2
LEGEND_LINE_IN = 0.14
#: Font sizes (points): split header (name; its details when wrapped), sample title, joint
#: captions, legend.  Text that would not fit its place is wrapped (header, legend) or
#: drawn smaller (titles, joint names), never clipped.
HEADER_PT = 11.0
HEADER_DETAIL_PT = 9.0
TITLE_PT = 9.5
CAPTION_PT = 8.0
MIN_CAPTION_PT = 5.5
LEGEND_PT = 7.5
#: Text is fitted into this fraction of its width (glyph hinting differs a little with the
#: dpi and the output format).
TEXT_FIT_FRACTION = 0.97
#: Text is measured at most at this dpi (:class:`TextFitter`).
MAX_MEASURE_DPI = 300
#: Indent (inches) of a joint name after its colour bullet, and the least gap before q.
CAPTION_NAME_IN = 0.16
CAPTION_GAP_NAME_Q_IN = 0.1
DEFAULT_DPI = 100
#: Smallest dpi: the captions' smallest font (6.5 pt) is 6.5 dpi / 72 pixels high, and FreeType
#: refuses fonts under one pixel (dpi < 11).
MIN_DPI = 12
DEFAULT_N_SAMPLES = 12
DEFAULT_COLUMNS = 4
#: With --rgb each sample takes two panels (depth | colour).
DEFAULT_COLUMNS_RGB = 2
#: Marker sizes (points) of the axis origin dot and the prismatic position ring.
ORIGIN_MARKER_PT = 7.5
RING_MARKER_PT = 9.0
AXIS_LINE_PT = 2.2
#: Height (inches) of one q read-out line in the caption band below each panel.
CAPTION_LINE_IN = 0.19
#: Space between a panel and its caption (inches).
CAPTION_GAP_IN = 0.03
#: RGB preview: colour of the body (warm light grey) and how much white the parts' joint
#: colours are mixed with.
BODY_RGBA = (0.72, 0.70, 0.66, 1.0)
PART_TINT_WHITE = 0.35


def joint_colour(j: int) -> str:
    """Colour of joint ``j`` (:data:`JOINT_COLOURS`, cycled)."""
    return JOINT_COLOURS[j % len(JOINT_COLOURS)]


# --------------------------------------------------------------------------------------
# Pure functions
# --------------------------------------------------------------------------------------

def depth_to_rgb(depth_m: np.ndarray, focal_px: float | None = None, *, cmap: str = DEPTH_CMAP,
                 shade: float = SHADE_FRACTION) -> np.ndarray:
    """Colour-map one depth image to (H, W, 3) floats in [0, 1].

    Valid pixels (depth > 0) map ``t = (d_max - d) / (d_max - d_min)`` (near = 1) through
    ``cmap``; pixels with depth 0 get :data:`BACKGROUND_RGB`.  With ``focal_px`` the colour
    is blended (weight ``shade``) with a Lambertian shade of the surface: the depth image
    is treated as a height field in pixel units, ``relief = -depth * f / median(depth)``
    (a pixel spans ``depth / f`` metres), so the shading follows the true surface slopes.
    """
    from matplotlib import colormaps
    from matplotlib.colors import LightSource

    depth_m = np.asarray(depth_m, np.float64)
    valid = depth_m > 0
    out = np.empty(depth_m.shape + (3,))
    out[:] = BACKGROUND_RGB
    if not valid.any():
        return out
    lo, hi = depth_m[valid].min(), depth_m[valid].max()
    t = np.where(valid, (hi - depth_m) / max(hi - lo, 1e-9), 0.0)
    rgb = colormaps[cmap](t)[..., :3]
    if shade > 0 and focal_px:
        scale = focal_px / float(np.median(depth_m[valid]))
        # background at the far plane: silhouettes get a thin shaded rim
        relief = -np.where(valid, depth_m, hi) * scale
        ls = LightSource(azdeg=LIGHT_AZIMUTH_DEG, altdeg=LIGHT_ALTITUDE_DEG)
        intensity = ls.hillshade(relief, vert_exag=1.0, dx=1.0, dy=1.0)
        rgb = np.clip(rgb * ((1 - shade) + shade * 2.0 * intensity[..., None]), 0.0, 1.0)
    out[valid] = rgb[valid]
    return out


def extent_along(direction: np.ndarray, object_quat_wxyz: np.ndarray, dims_m: np.ndarray) -> float:
    """Extent (m) of the object's body box along a unit direction (camera frame).

    ``sum_i |d . e_i| * dims_i`` with ``e_i`` the object's axes (columns of the rotation of
    ``object_quat_wxyz``) and ``dims = (depth, width, height)``.
    """
    R = quat_to_matrix(object_quat_wxyz)
    return float(np.abs(R.T @ np.asarray(direction, np.float64)) @ np.asarray(dims_m, np.float64))


def axis_segment_m(joint_type: str, origin: np.ndarray, direction: np.ndarray, *, q: float, q_max: float,
                   body_extent_m: float, part_points_m: np.ndarray | None = None,
                   object_points_m: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """3-D end points (2, 3) of the drawn axis (camera frame, m) and the marker point(s).

    Revolute, with the moving part's visible points ``P`` (camera frame): the hinge line
    over the part's extent along the axis, ``t = (P - origin) . a``, from
    ``origin + (t_min - m) a`` to ``origin + (t_max + m) a`` with a margin
    ``m = AXIS_MARGIN_FRACTION (t_max - t_min)``; without points, ``origin -/+ (L/2) a``
    with ``L = AXIS_LENGTH_FRACTION * body_extent_m``; where the body's extent is not known
    (real captures without geometry or object pose: NaN), the same span over the whole
    object's visible points ``object_points_m``; without those either, ``L =``
    :data:`DEFAULT_AXIS_LENGTH_M`.  Marker: the origin.
    Prismatic: ``origin`` to ``origin + q_max a``; markers: the origin and the current
    front-face position ``origin + q a`` (NaN where q is not labelled).
    """
    origin, a = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
    if joint_type == PRISMATIC:
        return np.stack([origin, origin + q_max * a]), np.stack([origin, origin + q * a])
    for points in (part_points_m, None if math.isfinite(body_extent_m) else object_points_m):
        if points is not None and len(points):
            t = (np.asarray(points, np.float64) - origin) @ a
            lo, hi = float(t.min()), float(t.max())
            margin = AXIS_MARGIN_FRACTION * (hi - lo)
            return np.stack([origin + (lo - margin) * a, origin + (hi + margin) * a]), origin[None]
    length = AXIS_LENGTH_FRACTION * body_extent_m if math.isfinite(body_extent_m) else DEFAULT_AXIS_LENGTH_M
    return np.stack([origin - 0.5 * length * a, origin + 0.5 * length * a]), origin[None]
