"""Galleries of labelled depth images (``artdata show``).

Each panel shows one stored image: depth colour-mapped per image (near = bright, far =
dark, :data:`DEPTH_CMAP`, perceptually uniform) with pixels without a return in a neutral
light grey, lightly hill-shaded so surfaces read as 3-D; the labelled joint axes are drawn
on top, projected with the shard's intrinsics ``K`` (:func:`articulated_dataset.camera.project`):

* revolute joint: the hinge line through ``axis_origin`` along ``axis_direction``, over
  the moving part's visible extent along the axis (its mask pixels back-projected), with
  an arrowhead at the ``+axis_direction`` end (positive q opens, right-hand rule);
* prismatic joint: an arrow from ``axis_origin`` (the part's front face at q = 0) to
  ``axis_origin + q_max * axis_direction`` (the table's full travel), with a ring at the
  front face's current position ``axis_origin + q * axis_direction``;
* a filled dot at ``axis_origin``.

One colour per joint (:data:`JOINT_COLOURS`), shared by the axis, the q read-out and the
moving part's outline.  ``rgb=True`` adds a shaded colour preview rendered from the same
scene, rebuilt from the manifest's generation config (body grey, parts tinted in their
joint's colour).

Real (ingested) splits: labels a capture lacks are NaN.  A revolute axis without part pixels
(binary masks) and without body extent (no geometry or object pose) spans the whole object's
visible extent along the axis; q not labelled reads "no label"; an image without axis labels
says so in its panel.

Figures are laid out with fixed sizes (no tight bounding box), so a gallery's pixel size is
:func:`gallery_size_px` and every panel's position is known (:class:`Panel`).  No text is
clipped: a split header or the legend too wide for the figure wraps onto more lines (the
figure grows by :data:`HEADER_LINE_IN` / :data:`LEGEND_LINE_IN` a line), a sample title or
joint name too wide for its panel is drawn smaller (:class:`TextFitter` measures them).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import backproject, project
from .errors import DataFormatError, UserError
from .context_labels import context_details, object_depth, tint_context  # scene/occluder pixels: own colours
from .format import MASK_BACKGROUND, MASK_FIRST_PART, PRISMATIC, Shard, Split
from .units import format_q

log = logging.getLogger(__name__)

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
    return JOINT_COLOURS[j % len(JOINT_COLOURS)]


# --------------------------------------------------------------------------------------
# Pure helpers
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
    w, x, y, z = object_quat_wxyz
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
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


# --------------------------------------------------------------------------------------
# Data access
# --------------------------------------------------------------------------------------

@dataclass
class SplitView:
    """A split folder opened for display (through :class:`articulated_dataset.format.Split`):
    manifest, shards and the class's joint info."""

    split_dir: Path
    manifest: dict
    shards: list[Shard]
    joint_names: list[str]
    joint_types: list[str]
    q_max: list[float]
    images_per_object: int
    #: Real (ingested) splits: images of each object (objects may have different numbers of
    #: captures; ``images_per_object`` is then the largest); None for generated splits.
    object_images: dict[int, int] | None = None

    @classmethod
    def open(cls, split_dir: str | Path) -> "SplitView":
        split_dir = Path(split_dir)
        split = Split(split_dir)  # manifest, names and shard paths checked
        manifest, shards = split.manifest, split.shards
        if not shards:
            raise DataFormatError(f"{split_dir}: the manifest lists no shards (nothing generated yet)")
        attrs = shards[0].attrs
        try:
            table = json.loads(attrs["sampling_table"])
            return cls(split_dir, manifest, shards, json.loads(attrs["joint_names"]), json.loads(attrs["joint_types"]),
                       [float(r[1]) for r in table["q"]], int(attrs["images_per_object"]),
                       _object_images(manifest))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise DataFormatError(f"{shards[0].path}: unreadable joint attributes ({exc})") from None

    @property
    def name(self) -> str:
        return f"{self.manifest['class_name']}/{self.split_dir.name}"

    @property
    def n_objects(self) -> int:
        return int(self.manifest["n_objects"])

    def locate(self, object_index: int) -> tuple[Shard, int]:
        """The shard holding ``object_index`` and the row of its first image."""
        for rec, sh in zip(self.manifest["shards"], self.shards):
            if rec["object_start"] <= object_index < rec["object_stop"]:
                if self.object_images is not None:
                    return sh, sum(self.object_images.get(o, 0) for o in range(rec["object_start"], object_index))
                return sh, (object_index - rec["object_start"]) * self.images_per_object
        raise UserError(f"object {object_index} is not in {self.name} (it holds objects 0..{self.n_objects - 1})")

    def sample(self, object_index: int, image_index: int) -> dict:
        sh, row = self.locate(object_index)
        s = sh.sample(row + image_index)
        if int(s["object_index"]) != object_index or int(s["image_index"]) != image_index:
            raise DataFormatError(f"{sh.path}: row {row + image_index} holds object {int(s['object_index'])} image "
                                  f"{int(s['image_index'])}, expected object {object_index} image {image_index}")
        s["K"] = sh.K
        return s

    def close(self) -> None:
        for sh in self.shards:
            sh.close()


def _object_images(manifest: dict) -> dict[int, int] | None:
    """{object: number of images} of a real split's manifest (its shards' ``object_images``), else None."""
    if "real" not in manifest:
        return None
    try:
        return {int(o): int(c) for rec in manifest["shards"] for o, c in rec.get("object_images", {}).items()}
    except (AttributeError, TypeError, ValueError) as exc:
        raise DataFormatError(f"manifest: unreadable object_images ({exc})") from None


def select_samples(n_objects: int, images_per_object: int, n: int, objects=None, images=None,
                   object_images: dict[int, int] | None = None) -> list[tuple[int, int]]:
    """``n`` (object, image) pairs spread over the candidates.

    Objects are taken evenly spaced over ``objects`` (default: all) and images evenly
    spaced over ``images`` (default: all), so a gallery sweeps from closed to open.  With
    fewer candidate pairs than ``n``, all of them are returned.  ``object_images`` (real
    splits: images of each object) leaves out the pairs an object does not have.
    """
    objects = list(range(n_objects)) if objects is None else list(objects)
    images = list(range(images_per_object)) if images is None else list(images)
    pairs = [(o, i) for o in objects for i in images if object_images is None or i < object_images.get(o, 0)]
    if len(pairs) <= n:
        return pairs
    if len(objects) >= n:
        objs = [objects[(k * len(objects)) // n] for k in range(n)]
    else:
        objs = [objects[k % len(objects)] for k in range(n)]
    if n == 1:
        return [(objs[0], images[0]) if (objs[0], images[0]) in pairs else pairs[0]]
    imgs = [images[round(k * (len(images) - 1) / (n - 1))] for k in range(n)]
    out, seen, candidates = [], set(), set(pairs)
    for p in zip(objs, imgs):
        if p in candidates and p not in seen:
            seen.add(p)
            out.append(p)
    for p in pairs:  # fill duplicates (few objects, few images) from the remaining pairs
        if len(out) >= n:
            break
        if p not in seen:
            seen.add(p)
            out.append(p)
    return sorted(out)


# --------------------------------------------------------------------------------------
# RGB preview (rebuilds the scene)
# --------------------------------------------------------------------------------------

def preview_rgb(manifest: dict, object_index: int, image_indices, stored_depth: dict | None = None) -> dict[int, np.ndarray]:
    """Shaded colour renders (H, W, 3) uint8 of one object's images, from its rebuilt scene.

    The object is re-sampled from the manifest's config (``object_sample``), rendered with
    :func:`pipeline.render_object` to get the final pose (visibility redraws included),
    then recompiled with geom colours by part and rendered with ``render_rgb``.  If
    ``stored_depth`` ({image_index: depth}) is given, a mismatch with the re-rendered
    depth is logged as a warning (the stored data came from another package version).
    """
    import mujoco

    from .labels import model_info
    from .pipeline import GenerationConfig, object_sample, render_object
    from .render import process_renderer
    from .scene import ORIGIN_POSE, ObjectPlacer, build_model, set_configuration
    from .templating import render_urdf
    from .viewpoint import object_in_camera
    from matplotlib.colors import to_rgba

    try:
        config = GenerationConfig.from_dict(manifest["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataFormatError(f"manifest config cannot be read back ({exc}); --rgb needs it") from None
    renderer = process_renderer(config.camera)
    sample0 = object_sample(config, object_index)
    arrays, sample, _ = render_object(sample0, config, renderer, check_visibility=not config.mean)
    obj_class = config.obj_class
    if stored_depth:
        for i, d in stored_depth.items():
            if not np.array_equal(arrays["depth"][i], d):
                log.warning("%s object %d image %d: re-rendered depth differs from the stored image; the RGB preview "
                            "may not match (data from another package version?)", config.class_name, object_index, i)
                break
    urdf = render_urdf(obj_class.template_path(), sample.template_mappings(config.table))
    head = sample.views is not None  # a head camera: the object is placed in each image's camera frame
    model = build_model(urdf, ORIGIN_POSE if head else sample.pose, config.camera, obj_class.base_link)
    info = model_info(model, obj_class)
    placer = ObjectPlacer(model, info.base_body) if head else None
    for g in range(model.ngeom):
        part = int(info.geom_part[g])
        if part >= MASK_FIRST_PART:
            c = np.array(to_rgba(joint_colour(part - MASK_FIRST_PART)))
            model.geom_rgba[g] = (1 - PART_TINT_WHITE) * c + PART_TINT_WHITE * np.ones(4)
        elif part != MASK_BACKGROUND:
            model.geom_rgba[g] = BODY_RGBA
    data = mujoco.MjData(model)
    renderer.bind(model)
    out = {}
    for i in image_indices:
        if placer is not None:
            placer.place(object_in_camera(sample.pose, sample.views[i]))
        set_configuration(model, data, info.joint_ids, sample.q[i])
        out[i] = renderer.render_rgb(data)
    return out


# --------------------------------------------------------------------------------------
# Drawing
# --------------------------------------------------------------------------------------

@dataclass
class Panel:
    """Where one image landed in a saved figure (for tests and tools).

    ``box_px``: (left, top, width, height) of the image in the PNG's pixel coordinates
    (origin top-left); ``size``: the image's (W, H).
    """

    file: Path
    split: str
    object_index: int
    image_index: int
    kind: str  # "depth" or "rgb"
    box_px: tuple[float, float, float, float]
    size: tuple[int, int]
    axis_origin: np.ndarray = field(repr=False, default=None)
    K: np.ndarray = field(repr=False, default=None)

    def to_png(self, uv: np.ndarray) -> np.ndarray:
        """Image pixel coordinates (integer = pixel centre) -> PNG pixel coordinates (x, y)."""
        left, top, width, height = self.box_px
        W, H = self.size
        uv = np.atleast_2d(uv)
        return np.stack([left + (uv[:, 0] + 0.5) * width / W, top + (uv[:, 1] + 0.5) * height / H], axis=1)


def _draw_axes(ax, s: dict, view: SplitView) -> None:
    """Axis lines, origin dots and prismatic position rings of one sample (image coords)."""
    import matplotlib.patheffects as pe
    from matplotlib.patches import FancyArrowPatch

    K = s["K"]
    halo = [pe.Stroke(linewidth=AXIS_LINE_PT + 1.6, foreground="white", alpha=0.85), pe.Normal()]
    markers = []
    # the whole object's visible points: the span of axes whose body extent is unknown (real captures)
    object_points = backproject(s["depth"], K, s["mask"] != MASK_BACKGROUND)
    for j, jtype in enumerate(view.joint_types):
        colour = joint_colour(j)
        extent = extent_along(s["axis_direction"][j], s["object_pose"][3:], s["geometry"][:3])
        part = backproject(s["depth"], K, s["mask"] == MASK_FIRST_PART + j)
        seg, marks = axis_segment_m(jtype, s["axis_origin"][j], s["axis_direction"][j], q=float(s["q"][j]),
                                    q_max=view.q_max[j], body_extent_m=extent, part_points_m=part,
                                    object_points_m=object_points)
        uv, _ = project(seg, K)
        if np.all(np.isfinite(uv)):
            arrow = FancyArrowPatch(tuple(uv[0]), tuple(uv[1]), arrowstyle="-|>,head_length=5,head_width=2.6",
                                    color=colour, lw=AXIS_LINE_PT, shrinkA=0, shrinkB=0, zorder=4, path_effects=halo)
            ax.add_patch(arrow)  # patches added to axes are clipped to them
        muv, _ = project(marks, K)
        markers.append((j, colour, muv))
    pred = s.get("prediction")
    if pred is not None:  # predicted axes: dashed, hollow square at the predicted origin
        from .rotations import quat_to_matrix

        for j, jtype in enumerate(view.joint_types):
            colour = joint_colour(j)
            direction = quat_to_matrix(pred["axis_pose"][j, 3:])[:, 2]
            extent = extent_along(direction, s["object_pose"][3:], s["geometry"][:3])
            seg, marks = axis_segment_m(jtype, pred["axis_pose"][j, :3], direction, q=float(pred["q"][j]),
                                        q_max=view.q_max[j], body_extent_m=extent, object_points_m=object_points)
            uv, _ = project(seg, K)
            if np.all(np.isfinite(uv)):
                ax.plot(uv[:, 0], uv[:, 1], "--", color=colour, lw=AXIS_LINE_PT * 0.8, zorder=4, path_effects=halo)
            muv, _ = project(marks, K)
            if np.all(np.isfinite(muv[0])):
                ax.plot(*muv[0], "s", ms=ORIGIN_MARKER_PT, mfc="none", mec=colour, mew=1.6, zorder=6)
    for j, colour, muv in markers:  # dots above every line
        if np.all(np.isfinite(muv[0])):
            ax.plot(*muv[0], "o", ms=ORIGIN_MARKER_PT, mfc=colour, mec="white", mew=1.2, zorder=6)
        if len(muv) > 1 and np.all(np.isfinite(muv[1])):
            ax.plot(*muv[1], "o", ms=RING_MARKER_PT, mfc="none", mec=colour, mew=2.0, zorder=5,
                    path_effects=[pe.Stroke(linewidth=3.2, foreground="white", alpha=0.85), pe.Normal()])


def _draw_outlines(ax, mask: np.ndarray, n_joints: int) -> None:
    for j in range(n_joints):
        part = (mask == MASK_FIRST_PART + j).astype(float)
        if part.any() and not part.all():
            ax.contour(part, levels=[0.5], colors=[joint_colour(j)], linewidths=0.8, alpha=0.9, zorder=3)


def _text_colour_on(colour) -> str:
    """Black or white, whichever contrasts more with ``colour`` (relative luminance > 0.5: black)."""
    from matplotlib.colors import to_rgb

    r, g, b = to_rgb(colour)
    return "#111111" if 0.2126 * r + 0.7152 * g + 0.0722 * b > 0.5 else "white"


class TextFitter:
    """Measures text as a figure at ``dpi`` draws it (Agg), to wrap or shrink it into its place
    (above :data:`MAX_MEASURE_DPI`, at that dpi: glyph hinting no longer matters, and fonts at
    absurd resolutions take absurd memory)."""

    def __init__(self, dpi: int):
        from matplotlib.backends.backend_agg import RendererAgg

        dpi = min(dpi, MAX_MEASURE_DPI)
        self.dpi = dpi
        self._renderer = RendererAgg(8, 8, dpi)

    def width_in(self, text: str, size: float, weight: str = "normal") -> float:
        from matplotlib.font_manager import FontProperties

        w, _, _ = self._renderer.get_text_width_height_descent(text, FontProperties(size=size, weight=weight),
                                                                ismath=False)
        return w / self.dpi

    def fit_size(self, text: str, size: float, width_in: float, weight: str = "normal") -> float:
        """``size``, or the smaller size at which ``text`` takes at most ``width_in``."""
        w = self.width_in(text, size, weight)
        room = TEXT_FIT_FRACTION * width_in
        return size if w <= room else size * room / w

    def wrap(self, chunks, sep: str, width_in: float, size: float, weight: str = "normal") -> list[str]:
        """Lines of ``chunks`` joined by ``sep``, each at most ``width_in`` wide: broken between
        chunks, and between words inside a chunk too wide for a line of its own (a single word
        wider than the line stays whole: draw the lines at :meth:`fit_size` of the widest)."""
        room = TEXT_FIT_FRACTION * width_in

        def fits(text):
            return self.width_in(text, size, weight) <= room

        lines, cur = [], ""
        for chunk in chunks:
            if cur and fits(cur + sep + chunk):
                cur += sep + chunk
                continue
            if cur:
                lines.append(cur)
                cur = ""
            if fits(chunk):
                cur = chunk
                continue
            for word in chunk.split(" "):
                if cur and fits(cur + " " + word):
                    cur += " " + word
                else:
                    if cur:
                        lines.append(cur)
                    cur = word
        if cur:
            lines.append(cur)
        return lines

    def fit_lines(self, lines: list[str], size: float, width_in: float, weight: str = "normal") -> float:
        """The size at which the widest of ``lines`` fits ``width_in``."""
        return min(self.fit_size(line, size, width_in, weight) for line in lines)


def _fig_text(fig, x, y, text, **kw):
    """``fig.text`` for text that may come from a data file: never parsed as mathtext."""
    return fig.text(x, y, text, parse_math=False, **kw)


def _draw_caption(fig, s: dict, view: SplitView, fit: TextFitter, *, left_in, top_in, fig_w_in, fig_h_in) -> None:
    """q of each joint, one line per joint below the panel: a bullet in the joint's colour,
    the joint name and q (degrees or centimetres; :data:`~.units.NO_LABEL_TEXT` where not labelled).
    A name too long for the room left of q is drawn smaller (down to :data:`MIN_CAPTION_PT`),
    then shortened with an ellipsis."""
    for j, (name, jtype) in enumerate(zip(view.joint_names, view.joint_types)):
        y = (top_in - (j + 0.5) * CAPTION_LINE_IN) / fig_h_in
        q_text = format_q(float(s["q"][j]), jtype)
        room = PANEL_WIDTH_IN - CAPTION_NAME_IN - CAPTION_GAP_NAME_Q_IN - fit.width_in(q_text, CAPTION_PT, "bold")
        size = max(fit.fit_size(name, CAPTION_PT, room), MIN_CAPTION_PT)
        while len(name) > 1 and fit.width_in(name, size) > TEXT_FIT_FRACTION * room:
            name = name[:-2] + "\u2026"
        _fig_text(fig, left_in / fig_w_in, y, "\u25cf", color=joint_colour(j), fontsize=9, ha="left", va="center")
        _fig_text(fig, (left_in + CAPTION_NAME_IN) / fig_w_in, y, name, color="#333333", fontsize=size, ha="left",
                  va="center")
        _fig_text(fig, (left_in + PANEL_WIDTH_IN) / fig_w_in, y, q_text, color="#111111" if math.isfinite(s["q"][j])
                  else "#777777", fontsize=CAPTION_PT, fontweight="bold", ha="right", va="center")


def _panel_axes(fig, left_in, bottom_in, width_in, height_in, fig_w_in, fig_h_in):
    ax = fig.add_axes((left_in / fig_w_in, bottom_in / fig_h_in, width_in / fig_w_in, height_in / fig_h_in))
    ax.set_axis_off()
    return ax


def _draw_sample(fig, s: dict, view: SplitView, rgb_img, fit: TextFitter, *, left_in, bottom_in, panel_w_in,
                 panel_h_in, fig_w_in, fig_h_in, outline: bool) -> list:
    """Title, depth panel (and RGB panel) of one sample; returns [(kind, axes)]."""
    H, W = s["depth"].shape
    obj, img = int(s["object_index"]), int(s["image_index"])
    n_panels = 2 if rgb_img is not None else 1
    cell_w = n_panels * panel_w_in + (n_panels - 1) * GAP_IN / 2
    title = f"{view.manifest['class_name']}  \u00b7  object {obj}  \u00b7  image {img}"
    _fig_text(fig, (left_in + cell_w / 2) / fig_w_in, (bottom_in + panel_h_in + TITLE_IN * 0.45) / fig_h_in, title,
              ha="center", va="center", fontsize=fit.fit_size(title, TITLE_PT, cell_w), color="#222222")
    out = []
    ax = _panel_axes(fig, left_in, bottom_in, panel_w_in, panel_h_in, fig_w_in, fig_h_in)
    depth_rgb = tint_context(depth_to_rgb(object_depth(s["depth"], s["mask"]), float(s["K"][0, 0])), s["mask"], s["depth"])
    ax.imshow(depth_rgb, interpolation="nearest", extent=(-0.5, W - 0.5, H - 0.5, -0.5), aspect="auto")
    valid = s["depth"][s["depth"] > 0]
    if valid.size:
        ax.text(0.985, 0.975, f"{valid.min():.2f}\u2013{valid.max():.2f} m", transform=ax.transAxes, fontsize=6.5,
                color="#333333", ha="right", va="top", zorder=7,
                bbox=dict(boxstyle="round,pad=0.15", fc=(1, 1, 1, 0.6), ec="none"))
    if outline:
        _draw_outlines(ax, s["mask"], len(view.joint_types))
    _draw_axes(ax, s, view)
    if not np.isfinite(s["axis_origin"]).any():
        ax.text(0.015, 0.025, "no axis labels", transform=ax.transAxes, fontsize=6.5, color="#333333", ha="left",
                va="bottom", zorder=7, bbox=dict(boxstyle="round,pad=0.15", fc=(1, 1, 1, 0.6), ec="none"))
    _draw_caption(fig, s, view, fit, left_in=left_in, top_in=bottom_in - CAPTION_GAP_IN, fig_w_in=fig_w_in, fig_h_in=fig_h_in)
    ax.set_xlim(-0.5, W - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    out.append(("depth", ax))
    if rgb_img is not None:
        rgb = rgb_img.astype(np.float64) / 255.0
        rgb[s["mask"] == MASK_BACKGROUND] = BACKGROUND_RGB
        ax2 = _panel_axes(fig, left_in + panel_w_in + GAP_IN / 2, bottom_in, panel_w_in, panel_h_in, fig_w_in, fig_h_in)
        ax2.imshow(rgb, interpolation="nearest", extent=(-0.5, W - 0.5, H - 0.5, -0.5), aspect="auto")
        _draw_axes(ax2, s, view)
        ax2.set_xlim(-0.5, W - 0.5)
        ax2.set_ylim(H - 0.5, -0.5)
        out.append(("rgb", ax2))
    return out


#: The legend below a gallery: its items (wrapped between items to the figure's width).
LEGEND_ITEMS = ("colour: depth per image, near = bright, far = dark", "grey: no return",
                "line: joint axis, arrow = +q", "dot: axis origin", "ring: drawer front now", "one colour per joint")
LEGEND_PREDICTIONS_ITEM = "dashed line, square: predicted axis and origin"
LEGEND_SEP = "   \u00b7   "


def legend_lines(width_in: float, *, predictions: bool, dpi: int = DEFAULT_DPI) -> list[str]:
    """The legend's lines in a figure ``width_in`` wide (one line where it fits)."""
    items = LEGEND_ITEMS + ((LEGEND_PREDICTIONS_ITEM,) if predictions else ())
    return TextFitter(dpi).wrap(items, LEGEND_SEP, width_in - 2 * GAP_IN, LEGEND_PT)


def split_header(view: SplitView, image_wh: tuple[int, int]) -> tuple[str, list[str]]:
    """A split's header: its name and the details after it (counts, image size, seed; a real
    split says "real captures" instead of its seed)."""
    cam = view.manifest.get("config", {}).get("camera", {})
    W, H = image_wh
    source = "real captures" if "real" in view.manifest else f"seed {view.manifest['seed']}"
    return view.name, [f"{view.manifest['n_objects']} objects", f"{view.manifest['n_images']} images",
                       f"{cam.get('width_px', W)}\u00d7{cam.get('height_px', H)} px", source,
                       *context_details(view.manifest.get("config", {}))]


def header_lines(name: str, details: list[str], width_in: float, fit: TextFitter) -> list[tuple[str, float, str]]:
    """(text, size, weight) of each line of a split header within ``width_in``: one bold line
    ``name  --  details`` where it fits, else the name (bold) over the wrapped details."""
    room = width_in - 2 * GAP_IN
    one = f"{name}   \u2014   {', '.join(details)}"
    if fit.width_in(one, HEADER_PT, "bold") <= TEXT_FIT_FRACTION * room:
        return [(one, HEADER_PT, "bold")]
    lines = fit.wrap(details, ", ", room, HEADER_DETAIL_PT)
    size = fit.fit_lines(lines, HEADER_DETAIL_PT, room)
    return [(name, fit.fit_size(name, HEADER_PT, room, "bold"), "bold")] + [(line, size, "normal") for line in lines]


def gallery_size_px(n_rows_per_split: list[int], cols: int, image_wh: tuple[int, int], *, rgb: bool,
                    n_joints: int, dpi: int = DEFAULT_DPI, predictions: bool = False,
                    views: list[SplitView] | None = None) -> tuple[int, int]:
    """Pixel size (width, height) of a gallery with the given rows per split, whose classes
    have at most ``n_joints`` joints (one caption line each).  ``predictions``: the legend
    explains predicted axes too; ``views``: the splits, whose headers may wrap in a narrow
    gallery (without them each header is taken to fit one line)."""
    fig_w = _layout(n_rows_per_split, cols, image_wh, rgb=rgb, n_joints=n_joints)[0]
    fit = TextFitter(dpi)
    n_header = ([len(header_lines(*split_header(v, image_wh), fig_w, fit)) for v in views] if views is not None
                else None)
    n_legend = len(legend_lines(fig_w, predictions=predictions, dpi=dpi))
    w_in, h_in, _, _, _ = _layout(n_rows_per_split, cols, image_wh, rgb=rgb, n_joints=n_joints,
                                  header_lines=n_header, legend_lines=n_legend)
    return int(round(w_in * dpi)), int(round(h_in * dpi))


def _header_in(n_lines: int) -> float:
    return HEADER_IN + (n_lines - 1) * HEADER_LINE_IN


def _footer_in(n_lines: int) -> float:
    return FOOTER_IN + (n_lines - 1) * LEGEND_LINE_IN


def _layout(n_rows_per_split, cols, image_wh, *, rgb, n_joints, header_lines=None, legend_lines=1):
    """Figure width/height, sample cell width, panel height and row height (inches);
    ``header_lines``: lines of each split's header (default one each), ``legend_lines``: of the legend."""
    W, H = image_wh
    panel_h = PANEL_WIDTH_IN * H / W
    n_panels = 2 if rgb else 1
    cell_w = n_panels * PANEL_WIDTH_IN + (n_panels - 1) * GAP_IN / 2
    row_h = TITLE_IN + panel_h + CAPTION_GAP_IN + n_joints * CAPTION_LINE_IN + GAP_IN
    fig_w = cols * cell_w + (cols + 1) * GAP_IN
    header_lines = header_lines or [1] * len(n_rows_per_split)
    fig_h = sum(_header_in(k) + r * row_h for r, k in zip(n_rows_per_split, header_lines)) + _footer_in(legend_lines)
    return fig_w, fig_h, cell_w, panel_h, row_h


def _new_figure(w_in: float, h_in: float, dpi: int):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w_in, h_in), dpi=dpi, facecolor="white")
    return fig


#: Largest figure side in pixels (matplotlib's Agg renderer refuses 2**16 and more).
MAX_FIGURE_SIDE_PX = 2**16 - 1
#: Bytes per pixel of the RGBA canvas matplotlib draws into.
CANVAS_BYTES_PER_PIXEL = 4
#: Fraction of the available memory one figure's canvas may take.
FIGURE_MEMORY_FRACTION = 0.5


def check_figure_size(w_in: float, h_in: float, dpi: int, path: Path) -> None:
    """Refuse (one line) a figure too large to draw, before matplotlib allocates it."""
    from .safeio import available_memory_bytes, format_bytes

    w_px, h_px = w_in * dpi, h_in * dpi
    if max(w_px, h_px) > MAX_FIGURE_SIDE_PX:
        raise UserError(f"{path}: a {w_px:.0f}x{h_px:.0f} px figure is larger than {MAX_FIGURE_SIDE_PX} px a side; "
                        "lower --dpi, --n or --cols")
    need = w_px * h_px * CANVAS_BYTES_PER_PIXEL
    avail = available_memory_bytes()
    if avail is not None and need > FIGURE_MEMORY_FRACTION * avail:
        raise UserError(f"{path}: a {w_px:.0f}x{h_px:.0f} px figure needs {format_bytes(need)} of memory, more than "
                        f"half of the {format_bytes(avail)} available; lower --dpi, --n or --cols")


def _save(fig, path: Path, dpi: int) -> None:
    """Write the figure atomically (a failure leaves no partial file and ``path`` as it was)."""
    from .safeio import atomic_path, ensure_dir

    ensure_dir(path.parent)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lower().lstrip("."), dpi=dpi, facecolor="white")


def _panel_record(fig, ax, kind, file, view, s, dpi) -> Panel:
    fig_h_px = fig.get_figheight() * dpi
    bb = ax.get_position()  # figure fraction
    fig_w_px = fig.get_figwidth() * dpi
    box = (bb.x0 * fig_w_px, fig_h_px - bb.y1 * fig_h_px, bb.width * fig_w_px, bb.height * fig_h_px)
    H, W = s["depth"].shape
    return Panel(file, view.name, int(s["object_index"]), int(s["image_index"]), kind, box, (W, H),
                 np.asarray(s["axis_origin"]), np.asarray(s["K"]))


def check_output_format(path: str | Path) -> Path:
    """The output path if matplotlib can write its format (by extension), else a UserError."""
    from matplotlib.figure import Figure

    path = Path(path)
    ext = path.suffix.lower().lstrip(".")
    supported = Figure().canvas.get_supported_filetypes()
    if ext not in supported:
        raise UserError(f"cannot write {path}: unknown image format {('.' + ext) if ext else '(no extension)'}; "
                        f"use one of {', '.join('.' + e for e in sorted(supported))}")
    return path


def make_gallery(split_dirs, *, out: str | Path | None = None, per_sample_dir: str | Path | None = None,
                 n: int = DEFAULT_N_SAMPLES, objects=None, images=None, rgb: bool = False, cols: int = DEFAULT_COLUMNS,
                 dpi: int = DEFAULT_DPI, outline: bool = True, progress=None, predictions=None) -> list[Panel]:
    """Draw ``n`` samples of each split into one gallery (``out``) and/or one PNG per sample
    (``per_sample_dir``).  Returns the panels drawn (with their positions in the files).

    ``predictions``: a predictions.h5 path; its axes are drawn dashed beside the true ones
    (images it does not cover are drawn without).

    ``objects`` / ``images``: candidate object and image indices (default: all).
    ``progress(k)`` is called after each sample.
    """
    if out is None and per_sample_dir is None:
        raise UserError("nothing to write: give --out FILE and/or --per-sample DIR")
    if n <= 0:
        raise UserError(f"number of samples must be positive, got {n}")
    if cols <= 0:
        raise UserError(f"number of columns must be positive, got {cols}")
    if dpi < MIN_DPI:
        raise UserError(f"--dpi must be at least {MIN_DPI} (the captions' smallest font needs one pixel), got {dpi}")
    if out is not None:
        out = check_output_format(out)
    pred_by_class = _read_predicted_axes(predictions) if predictions is not None else None
    views = [SplitView.open(d) for d in split_dirs]
    try:
        return _make_gallery(views, out, Path(per_sample_dir) if per_sample_dir else None, n, objects, images, rgb,
                             cols, dpi, outline, progress, pred_by_class)
    finally:
        for v in views:
            v.close()


def _read_predicted_axes(path) -> dict:
    """class -> {sample_id: {"axis_pose": (J, 7), "q": (J,)}} of a predictions file."""
    from .benchmark.predictions import read_predictions

    _, per_class = read_predictions(path)
    return {c: {int(i): {"axis_pose": a["axis_pose"][k], "q": a["q"][k]} for k, i in enumerate(a["sample_id"])}
            for c, a in per_class.items()}


def _make_gallery(views, out, per_sample_dir, n, objects, images, rgb, cols, dpi, outline, progress,
                  pred_by_class=None) -> list[Panel]:
    picks = []
    for v in views:
        for o in objects or []:
            if not 0 <= o < v.n_objects:
                raise UserError(f"object {o} is not in {v.name} (it holds objects 0..{v.n_objects - 1})")
        if rgb and "real" in v.manifest:
            raise UserError(f"--rgb rebuilds a generated object's scene; {v.name} holds real captures (no scene to "
                            "rebuild): leave out --rgb")
        for i in images or []:
            if not 0 <= i < v.images_per_object:
                raise UserError(f"image {i} is not in {v.name} (objects have images 0..{v.images_per_object - 1})")
        picks.append(select_samples(v.n_objects, v.images_per_object, n, objects, images, v.object_images))
        if not picks[-1]:
            raise UserError(f"{v.name} has no image {', '.join(map(str, images or []))} of object(s) "
                            f"{', '.join(map(str, objects or []))}")
    samples, rgbs = [], []
    for v, pairs in zip(views, picks):
        ss = [v.sample(o, i) for o, i in pairs]
        if pred_by_class is not None:
            cls = v.manifest["class_name"]
            if cls not in pred_by_class:
                raise UserError(f"the predictions hold no {cls!r} images (they hold: {', '.join(sorted(pred_by_class))})")
            for smp in ss:
                hit = pred_by_class[cls].get(int(smp["sample_id"]))
                if hit is not None and hit["axis_pose"].shape[0] == len(v.joint_types):
                    smp["prediction"] = hit
        samples.append(ss)
        if rgb:
            by_obj: dict[int, list[int]] = {}
            for o, i in pairs:
                by_obj.setdefault(o, []).append(i)
            stored = {(int(s["object_index"]), int(s["image_index"])): s["depth"] for s in ss}
            rendered = {}
            for o, idx in by_obj.items():
                for i, im in preview_rgb(v.manifest, o, idx, {i: stored[(o, i)] for i in idx}).items():
                    rendered[(o, i)] = im
            rgbs.append([rendered[p] for p in pairs])
        else:
            rgbs.append([None] * len(pairs))
    panels: list[Panel] = []
    if out is not None:
        panels += _gallery_figure(views, samples, rgbs, out, cols, dpi, outline, rgb)
    if per_sample_dir is not None:
        for v, ss, rr in zip(views, samples, rgbs):
            for s, r in zip(ss, rr):
                name = f"{v.manifest['class_name']}_{v.split_dir.name}_o{int(s['object_index']):06d}_i{int(s['image_index']):03d}.png"
                panels += _gallery_figure([v], [[s]], [[r]], per_sample_dir / name, 1, dpi, outline, rgb, header=False)
                if progress is not None:
                    progress(1)
    return panels


def _gallery_figure(views, samples, rgbs, path: Path, cols: int, dpi: int, outline: bool, rgb: bool,
                    header: bool = True) -> list[Panel]:
    H, W = samples[0][0]["depth"].shape
    cols = min(cols, max(len(ss) for ss in samples))
    rows = [-(-len(ss) // cols) for ss in samples]
    max_j = max(len(v.joint_types) for v in views)
    fig_w, fig_h = _layout(rows, cols, (W, H), rgb=rgb, n_joints=max_j)[:2]
    # before measuring text (wrapping only makes a figure taller)
    check_figure_size(fig_w, fig_h if header else fig_h - HEADER_IN * len(views) - FOOTER_IN + GAP_IN, dpi, path)
    fit = TextFitter(dpi)
    headers = [header_lines(*split_header(v, (W, H)), fig_w, fit) for v in views]
    with_pred = any("prediction" in s for ss in samples for s in ss)
    legend = legend_lines(fig_w, predictions=with_pred, dpi=dpi)
    fig_w, fig_h, cell_w, panel_h, row_h = _layout(rows, cols, (W, H), rgb=rgb, n_joints=max_j,
                                                   header_lines=[len(h) for h in headers], legend_lines=len(legend))
    if not header:
        fig_h -= sum(_header_in(len(h)) for h in headers) + _footer_in(len(legend))
        fig_h += GAP_IN
    check_figure_size(fig_w, fig_h, dpi, path)
    fig = _new_figure(fig_w, fig_h, dpi)
    placed = []
    top = fig_h
    for v, ss, rr, n_rows, lines in zip(views, samples, rgbs, rows, headers):
        if header:
            for k, (text, size, weight) in enumerate(lines):
                y = top - HEADER_IN * 0.5 - k * HEADER_LINE_IN
                _fig_text(fig, GAP_IN / fig_w, y / fig_h, text, ha="left", va="center", fontsize=size,
                          fontweight=weight, color="#111111")
            top -= _header_in(len(lines))
        else:
            top -= GAP_IN
        for k, (s, r) in enumerate(zip(ss, rr)):
            row, col = divmod(k, cols)
            left = GAP_IN + col * (cell_w + GAP_IN)
            bottom = top - row * row_h - TITLE_IN - panel_h
            for kind, ax in _draw_sample(fig, s, v, r, fit, left_in=left, bottom_in=bottom, panel_w_in=PANEL_WIDTH_IN,
                                         panel_h_in=panel_h, fig_w_in=fig_w, fig_h_in=fig_h, outline=outline):
                placed.append((ax, kind, v, s))
        top -= n_rows * row_h
    if header:
        size = fit.fit_lines(legend, LEGEND_PT, fig_w - 2 * GAP_IN)
        for k, line in enumerate(legend):
            y = _footer_in(len(legend)) - FOOTER_IN * 0.5 - k * LEGEND_LINE_IN
            _fig_text(fig, GAP_IN / fig_w, y / fig_h, line, ha="left", va="center", fontsize=size, color="#555555")
    _save(fig, path, dpi)
    return [_panel_record(fig, ax, kind, path, v, s, dpi) for ax, kind, v, s in placed]
