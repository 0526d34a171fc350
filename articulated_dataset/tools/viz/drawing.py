"""Drawing one panel: the depth image, the labelled (and predicted) axes, part outlines,
captions fitted to the panel (:class:`TextFitter`), the split header and the legend."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from articulated_dataset.core.camera import backproject, project
from articulated_dataset.core.units import format_q
from articulated_dataset.format import MASK_BACKGROUND, MASK_FIRST_PART
from articulated_dataset.generation.context_labels import (  # scene/occluder pixels: own colours
    context_details,
    object_depth,
    tint_context,
)
from articulated_dataset.tools.viz.data import SplitView
from articulated_dataset.tools.viz.style import (
    AXIS_LINE_PT,
    BACKGROUND_RGB,
    CAPTION_GAP_IN,
    CAPTION_GAP_NAME_Q_IN,
    CAPTION_LINE_IN,
    CAPTION_NAME_IN,
    CAPTION_PT,
    DEFAULT_DPI,
    GAP_IN,
    HEADER_DETAIL_PT,
    HEADER_PT,
    LEGEND_PT,
    MAX_MEASURE_DPI,
    MIN_CAPTION_PT,
    ORIGIN_MARKER_PT,
    PANEL_WIDTH_IN,
    RING_MARKER_PT,
    TEXT_FIT_FRACTION,
    TITLE_IN,
    TITLE_PT,
    axis_segment_m,
    depth_to_rgb,
    extent_along,
    joint_colour,
)


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
    axis_origin: np.ndarray | None = field(repr=False, default=None)
    K: np.ndarray | None = field(repr=False, default=None)

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
        from articulated_dataset.core.rotations import quat_to_matrix

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
    for _, colour, muv in markers:  # dots above every line
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
        """Width (inches) of ``text`` drawn at font ``size`` (points) and ``weight``."""
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


def fig_text(fig, x, y, text, **kw):
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
        fig_text(fig, left_in / fig_w_in, y, "\u25cf", color=joint_colour(j), fontsize=9, ha="left", va="center")
        fig_text(fig, (left_in + CAPTION_NAME_IN) / fig_w_in, y, name, color="#333333", fontsize=size, ha="left",
                  va="center")
        fig_text(fig, (left_in + PANEL_WIDTH_IN) / fig_w_in, y, q_text, color="#111111" if math.isfinite(s["q"][j])
                  else "#777777", fontsize=CAPTION_PT, fontweight="bold", ha="right", va="center")


def _panel_axes(fig, left_in, bottom_in, width_in, height_in, fig_w_in, fig_h_in):
    ax = fig.add_axes((left_in / fig_w_in, bottom_in / fig_h_in, width_in / fig_w_in, height_in / fig_h_in))
    ax.set_axis_off()
    return ax


def draw_sample(fig, s: dict, view: SplitView, rgb_img, fit: TextFitter, *, left_in, bottom_in, panel_w_in,
                 panel_h_in, fig_w_in, fig_h_in, outline: bool) -> list:
    """Title, depth panel (and RGB panel) of one sample; returns [(kind, axes)]."""
    H, W = s["depth"].shape
    obj, img = int(s["object_index"]), int(s["image_index"])
    n_panels = 2 if rgb_img is not None else 1
    cell_w = n_panels * panel_w_in + (n_panels - 1) * GAP_IN / 2
    title = f"{view.manifest['class_name']}  \u00b7  object {obj}  \u00b7  image {img}"
    fig_text(fig, (left_in + cell_w / 2) / fig_w_in, (bottom_in + panel_h_in + TITLE_IN * 0.45) / fig_h_in, title,
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
