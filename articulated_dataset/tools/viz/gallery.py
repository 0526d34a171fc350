"""Galleries (``artdata show``): the figure layout and its size in pixels, the checks on the
output and figure size, and :func:`make_gallery`, which draws the panels of one or more splits."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.format.manifest import check_stored_object_files, third_party_definition
from articulated_dataset.tools.viz.data import RGB_REBUILD_HINT, SplitView, preview_rgb, select_samples
from articulated_dataset.tools.viz.drawing import (
    Panel,
    TextFitter,
    draw_sample,
    fig_text,
    header_lines,
    legend_lines,
    split_header,
)
from articulated_dataset.tools.viz.style import (
    CAPTION_GAP_IN,
    CAPTION_LINE_IN,
    DEFAULT_COLUMNS,
    DEFAULT_DPI,
    DEFAULT_N_SAMPLES,
    FOOTER_IN,
    GAP_IN,
    HEADER_IN,
    HEADER_LINE_IN,
    LEGEND_LINE_IN,
    LEGEND_PT,
    MIN_DPI,
    PANEL_WIDTH_IN,
    TITLE_IN,
)


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
    from articulated_dataset.core.safeio import available_memory_bytes, format_bytes

    w_px, h_px = w_in * dpi, h_in * dpi
    if max(w_px, h_px) > MAX_FIGURE_SIDE_PX:
        raise UserError(f"{path}: a {w_px:.0f}x{h_px:.0f} px figure is larger than {MAX_FIGURE_SIDE_PX} px a side; "
                        f"lower {option('dpi')}, {option('n_samples')} or {option('cols')}")
    need = w_px * h_px * CANVAS_BYTES_PER_PIXEL
    avail = available_memory_bytes()
    if avail is not None and need > FIGURE_MEMORY_FRACTION * avail:
        raise UserError(f"{path}: a {w_px:.0f}x{h_px:.0f} px figure needs {format_bytes(need)} of memory, more than "
                        f"half of the {format_bytes(avail)} available; lower "
                        f"{option('dpi')}, {option('n_samples')} or {option('cols')}")


def _save(fig, path: Path, dpi: int) -> None:
    """Write the figure atomically (a failure leaves no partial file and ``path`` as it was)."""
    from articulated_dataset.core.safeio import atomic_file, ensure_dir

    ensure_dir(path.parent)
    with atomic_file(path) as f:
        fig.savefig(f, format=path.suffix.lower().lstrip("."), dpi=dpi, facecolor="white")


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
                 dpi: int = DEFAULT_DPI, outline: bool = True, progress=None, predictions=None, urdf=None,
                 mesh_root=None, rebuild_hint: str = RGB_REBUILD_HINT) -> list[Panel]:
    """Draw ``n`` samples of each split into one gallery (``out``) and/or one PNG per sample
    (``per_sample_dir``).  Returns the panels drawn (with their positions in the files).

    ``predictions``: a predictions.h5 path; its axes are drawn dashed beside the true ones
    (images it does not cover are drawn without).

    ``objects`` / ``images``: candidate object and image indices (default: all).
    ``progress(k)`` is called after each sample.

    ``rgb`` rebuilds the scene of a split that stores no colour images.  A third-party URDF
    object is rebuilt only from files inside its split folder (else one line ending with
    ``rebuild_hint``), or from ``urdf`` (and ``mesh_root``), the files of the object the caller
    names, used for every third-party split drawn when their sha256 is the one it recorded
    (:func:`~articulated_dataset.generation.objects.stored_object_config`).
    """
    if out is None and per_sample_dir is None:
        raise UserError(f"nothing to write: give {option('out')} FILE and/or {option('per_sample_dir')} DIR")
    if n <= 0:
        raise UserError(f"number of samples must be positive, got {n}")
    if cols <= 0:
        raise UserError(f"number of columns must be positive, got {cols}")
    if dpi < MIN_DPI:
        raise UserError(f"{option('dpi')} must be at least {MIN_DPI} (the "
                        f"captions' smallest font needs one pixel), got {dpi}")
    if out is not None:
        out = check_output_format(out)
    pred_by_class = _read_predicted_axes(predictions) if predictions is not None else None
    views = [SplitView.open(d) for d in split_dirs]
    try:
        return _make_gallery(views, out, Path(per_sample_dir) if per_sample_dir else None, n, objects, images, rgb,
                             cols, dpi, outline, progress, pred_by_class,
                             ObjectFiles(urdf, mesh_root, rebuild_hint))
    finally:
        for v in views:
            v.close()


def stored_colour(view: SplitView) -> bool:
    """Whether the split stores colour images (``generate --rgb``): shown as the colour panel."""
    config = view.manifest.get("config")
    return isinstance(config, dict) and config.get("rgb") is True


def _read_predicted_axes(path) -> dict:
    """class -> {sample_id: {"axis_pose": (J, 7), "q": (J,)}} of a predictions file."""
    from articulated_dataset.benchmark.predictions import read_predictions

    _, per_class = read_predictions(path)
    return {c: {int(i): {"axis_pose": a["axis_pose"][k], "q": a["q"][k]} for k, i in enumerate(a["sample_id"])}
            for c, a in per_class.items()}


@dataclass(frozen=True)
class ObjectFiles:
    """What rebuilds a third-party object's scene for ``--rgb``: the URDF and mesh folder the
    caller named (None: the recorded paths, inside the split folder only) and the refusal's hint."""

    urdf: object = None
    mesh_root: object = None
    hint: str = RGB_REBUILD_HINT

    def of(self, view: SplitView) -> dict:
        """``preview_rgb``'s keyword arguments for ``view`` (the named files for a third-party split)."""
        third_party = third_party_definition(view.manifest.get("config"), view.split_dir) is not None
        return {"hint": self.hint, **({"urdf": self.urdf, "mesh_root": self.mesh_root} if third_party else {})}


def _make_gallery(views, out, per_sample_dir, n, objects, images, rgb, cols, dpi, outline, progress,
                  pred_by_class=None, files: ObjectFiles = ObjectFiles()) -> list[Panel]:
    picks = []
    named_used = False
    for v in views:
        for o in objects or []:
            if not 0 <= o < v.n_objects:
                raise UserError(f"object {o} is not in {v.name} (it holds objects 0..{v.n_objects - 1})")
        if rgb and "real" in v.manifest:
            raise UserError(f"{option('rgb')} rebuilds a generated object's scene; {v.name} holds real captures (no "
                            f"scene to rebuild): leave out {option('rgb')}")
        if rgb and not stored_colour(v):  # before any image is drawn: the files the object is rebuilt from
            named = files.of(v)
            if named.get("urdf") is None:
                check_stored_object_files(v.manifest.get("config"), v.split_dir, option("rgb"), files.hint)
            else:  # the named files' sha256 against the recorded one
                from articulated_dataset.generation.objects import stored_object_config

                stored_object_config(v.manifest.get("config"), v.split_dir, option("rgb"), **named)
                named_used = True
        for i in images or []:
            if not 0 <= i < v.images_per_object:
                raise UserError(f"image {i} is not in {v.name} (objects have images 0..{v.images_per_object - 1})")
        picks.append(select_samples(v.n_objects, v.images_per_object, n, objects, images, v.object_images))
        if not picks[-1]:
            raise UserError(f"{v.name} has no image {', '.join(map(str, images or []))} of object(s) "
                            f"{', '.join(map(str, objects or []))}")
    if files.urdf is not None and not named_used:
        raise UserError(f"the URDF {files.urdf} is not used: no split drawn rebuilds a third-party URDF object's "
                        "scene (only a colour preview of a split generated from a URDF, without stored colour "
                        "images, does)")
    samples, rgbs = [], []
    for v, pairs in zip(views, picks):
        ss = [v.sample(o, i) for o, i in pairs]
        if pred_by_class is not None:
            cls = v.manifest["class_name"]
            if cls not in pred_by_class:
                raise UserError(f"the predictions hold no {cls!r} images (they hold: {', '.join(sorted(pred_by_class))})")
            for smp in ss:
                hit = pred_by_class[cls].get(int(smp["sample_id"]))
                if hit is not None and hit["axis_pose"].shape[0] != len(v.joint_types):
                    raise UserError(f"the predictions give {hit['axis_pose'].shape[0]} joint(s) per {cls!r} image, "
                                    f"{v.name} has {len(v.joint_types)}")
                if hit is not None:
                    smp["prediction"] = hit
            if not any("prediction" in smp for smp in ss):
                raise UserError(f"the predictions hold none of the drawn {v.name} images (sample ids of another "
                                "split?); predict this split or choose "
                                f"{option('objects')}/{option('images')} that were predicted")
        samples.append(ss)
        if stored_colour(v):  # a --rgb split: its own colour images, nothing rebuilt
            sh_rows = [v.locate(o) for o, _ in pairs]
            rgbs.append([sh.read("rgb", row + i) for (sh, row), (_, i) in zip(sh_rows, pairs)])
        elif rgb:
            by_obj: dict[int, list[int]] = {}
            for o, i in pairs:
                by_obj.setdefault(o, []).append(i)
            stored = {(int(s["object_index"]), int(s["image_index"])): s["depth"] for s in ss}
            rendered = {}
            for o, idx in by_obj.items():
                for i, im in preview_rgb(v.manifest, o, idx, {i: stored[(o, i)] for i in idx}, v.split_dir,
                                         **files.of(v)).items():
                    rendered[(o, i)] = im
            rgbs.append([rendered[p] for p in pairs])
        else:
            rgbs.append([None] * len(pairs))
    rgb = rgb or any(stored_colour(v) for v in views)  # a colour panel beside every depth panel
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
                fig_text(fig, GAP_IN / fig_w, y / fig_h, text, ha="left", va="center", fontsize=size,
                          fontweight=weight, color="#111111")
            top -= _header_in(len(lines))
        else:
            top -= GAP_IN
        for k, (s, r) in enumerate(zip(ss, rr)):
            row, col = divmod(k, cols)
            left = GAP_IN + col * (cell_w + GAP_IN)
            bottom = top - row * row_h - TITLE_IN - panel_h
            for kind, ax in draw_sample(fig, s, v, r, fit, left_in=left, bottom_in=bottom, panel_w_in=PANEL_WIDTH_IN,
                                         panel_h_in=panel_h, fig_w_in=fig_w, fig_h_in=fig_h, outline=outline):
                placed.append((ax, kind, v, s))
        top -= n_rows * row_h
    if header:
        size = fit.fit_lines(legend, LEGEND_PT, fig_w - 2 * GAP_IN)
        for k, line in enumerate(legend):
            y = _footer_in(len(legend)) - FOOTER_IN * 0.5 - k * LEGEND_LINE_IN
            fig_text(fig, GAP_IN / fig_w, y / fig_h, line, ha="left", va="center", fontsize=size, color="#555555")
    _save(fig, path, dpi)
    return [_panel_record(fig, ax, kind, path, v, s, dpi) for ax, kind, v, s in placed]
