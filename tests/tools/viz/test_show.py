"""``artdata show``: gallery files, axis placement (pixel check against ``project``), bad inputs."""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest
from click.testing import CliRunner
from matplotlib.colors import to_rgb
from matplotlib.image import imread

from articulated_dataset.classes.registry import PRISMATIC, REVOLUTE
from articulated_dataset.cli import main
from articulated_dataset.core.camera import project
from articulated_dataset.core.units import format_q
from articulated_dataset.tools.viz.data import SplitView, preview_rgb, select_samples
from articulated_dataset.tools.viz.drawing import legend_lines
from articulated_dataset.tools.viz.gallery import gallery_size_px, make_gallery
from articulated_dataset.tools.viz.style import (
    BACKGROUND_RGB,
    DEFAULT_DPI,
    axis_segment_m,
    depth_to_rgb,
    extent_along,
    joint_colour,
)
from helpers_core import assert_one_line_error, run_cli
from helpers_real import ingest_uneven_cabinet2

#: Max per-channel difference between a drawn colour and the PNG's pixel (8-bit rounding
#: and antialiasing at the centre of a 10 px marker stay far below this).
COLOUR_TOL = 0.06
#: Only check origins this many image pixels inside the image (markers near the edge are clipped).
EDGE_PX = 3


def run_show(*args):
    result = CliRunner().invoke(main, ["show", *map(str, args)])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    assert "Traceback" not in result.output
    return result


def _png_rgb(path):
    img = imread(str(path))
    return img[..., :3]


def _check_origins(panels, png):
    """Every depth panel's in-image axis origins are drawn in their joint's colour."""
    checked = 0
    for p in panels:
        if p.kind != "depth":
            continue
        uv, z = project(p.axis_origin, p.K)
        W, H = p.size
        for j, (u, v) in enumerate(uv):
            if not (np.isfinite(u) and EDGE_PX <= u <= W - 1 - EDGE_PX and EDGE_PX <= v <= H - 1 - EDGE_PX):
                continue
            x, y = p.to_png(np.array([u, v]))[0]
            pixel = png[int(round(y)), int(round(x))]
            np.testing.assert_allclose(pixel, to_rgb(joint_colour(j)), atol=COLOUR_TOL,
                                       err_msg=f"{p.split} object {p.object_index} image {p.image_index} joint {j}")
            checked += 1
    return checked


@pytest.mark.parametrize("cls", ["cabinet2", "drawer"])
def test_gallery_size_and_axis_position(tiny_root, tmp_path, cls):
    split = tiny_root / cls / "train"
    out = tmp_path / "gallery.png"
    panels = make_gallery([split], out=out, n=8, cols=4)
    png = _png_rgb(out)
    J = 2 if cls == "cabinet2" else 1
    assert png.shape[1::-1] == gallery_size_px([2], 4, (192, 108), rgb=False, n_joints=J, dpi=DEFAULT_DPI)
    assert len(panels) == 8 and {p.file for p in panels} == {out}
    assert _check_origins(panels, png) >= 4
    # the panel box maps image pixels onto the PNG: a background pixel shows the background grey
    p = panels[0]
    view = SplitView.open(split)
    s = view.sample(p.object_index, p.image_index)
    view.close()
    background = np.argwhere(s["depth"] == 0)
    v, u = background[len(background) // 2]
    x, y = p.to_png(np.array([u, v], float))[0]
    np.testing.assert_allclose(png[int(round(y)), int(round(x))], BACKGROUND_RGB, atol=COLOUR_TOL)


def test_cli_gallery_and_per_sample_pngs(tiny_root, tmp_path):
    out = tmp_path / "g.png"
    per = tmp_path / "per"
    result = run_show(tiny_root / "cabinet" / "test", "--out", out, "--per-sample", per, "--n", "3", "--objects", "1")
    assert result.exit_code == 0, result.output
    assert out.is_file()
    names = sorted(p.name for p in per.iterdir())
    assert names == [f"cabinet_test_o000001_i{i:03d}.png" for i in (0, 8, 15)]
    assert _png_rgb(out).shape[1::-1] == gallery_size_px([1], 3, (192, 108), rgb=False, n_joints=1)


def test_rgb_preview_matches_the_stored_scene(tiny_root, tmp_path, caplog):
    split = tiny_root / "microwave" / "test"
    view = SplitView.open(split)
    s = view.sample(2, 9)
    with caplog.at_level(logging.WARNING):
        rgb = preview_rgb(view.manifest, 2, [9], {9: s["depth"]})[9]
    view.close()
    assert "differs" not in caplog.text  # the rebuilt scene re-renders the stored depth exactly
    assert rgb.shape == (108, 192, 3) and rgb.dtype == np.uint8
    lit = rgb.reshape(-1, 3).sum(1) > 0
    fg = (s["mask"] > 0).ravel()
    assert lit[fg].mean() > 0.95 and lit[~fg].mean() < 0.05  # the object is where the mask says

    out = tmp_path / "rgb.png"
    panels = make_gallery([split], out=out, n=2, rgb=True, cols=2)
    assert sorted(p.kind for p in panels) == ["depth", "depth", "rgb", "rgb"]
    png = _png_rgb(out)
    assert png.shape[1::-1] == gallery_size_px([1], 2, (192, 108), rgb=True, n_joints=1)
    _check_origins(panels, png)


def test_select_samples_hand_worked():
    # 6 objects x 16 images, 4 samples: objects 0, 1, 3, 4 and images 0, 5, 10, 15
    assert select_samples(6, 16, 4) == [(0, 0), (1, 5), (3, 10), (4, 15)]
    assert select_samples(2, 3, 10) == [(o, i) for o in range(2) for i in range(3)]
    assert select_samples(6, 16, 3, objects=[2]) == [(2, 0), (2, 8), (2, 15)]  # 7.5 rounds half to even
    assert select_samples(6, 16, 2, images=[4]) == [(0, 4), (3, 4)]


def test_axis_geometry_hand_worked():
    origin, a = np.array([2.0, 0.1, 0.2]), np.array([0.0, 0.0, 1.0])
    seg, marks = axis_segment_m(PRISMATIC, origin, -np.array([1.0, 0, 0]), q=0.1, q_max=0.4, body_extent_m=1.0)
    np.testing.assert_allclose(seg, [[2.0, 0.1, 0.2], [1.6, 0.1, 0.2]])
    np.testing.assert_allclose(marks, [[2.0, 0.1, 0.2], [1.9, 0.1, 0.2]])
    pts = np.array([[2.0, 0.0, -0.3], [2.1, 0.3, 0.7]])  # t = -0.5 and 0.5, margin 0.12
    seg, marks = axis_segment_m(REVOLUTE, origin, a, q=0.3, q_max=1.5, body_extent_m=9.0, part_points_m=pts)
    np.testing.assert_allclose(seg[:, 2], [0.2 - 0.62, 0.2 + 0.62])
    seg, _ = axis_segment_m(REVOLUTE, origin, a, q=0.3, q_max=1.5, body_extent_m=1.0)
    np.testing.assert_allclose(seg[:, 2], [0.2 - 0.4, 0.2 + 0.4])
    # body box 0.5 x 1.0 x 2.0 (depth, width, height) yawed by 90 deg: its width lies along camera x
    yaw90 = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    assert extent_along(np.array([1.0, 0, 0]), yaw90, np.array([0.5, 1.0, 2.0])) == pytest.approx(1.0)
    assert extent_along(np.array([0, 0, 1.0]), yaw90, np.array([0.5, 1.0, 2.0])) == pytest.approx(2.0)
    assert format_q(np.pi / 4, REVOLUTE) == "45.0 deg" and format_q(0.234, PRISMATIC) == "23.4 cm"


def test_depth_colours():
    d = np.zeros((4, 5), np.float32)
    d[1:3, 1:4] = [[1.0, 1.5, 2.0], [1.0, 1.5, 2.0]]
    rgb = depth_to_rgb(d, focal_px=100.0)
    np.testing.assert_allclose(rgb[0, 0], BACKGROUND_RGB)
    assert rgb[1, 1].sum() > rgb[1, 3].sum()  # near is brighter than far
    flat = depth_to_rgb(d, None)
    from matplotlib import colormaps

    np.testing.assert_allclose(flat[1, 1], colormaps["viridis"](1.0)[:3])
    np.testing.assert_allclose(flat[1, 3], colormaps["viridis"](0.0)[:3])


@pytest.mark.parametrize("args, needle", [
    (["--n", "0", "--out", "g.png"], "number of samples must be positive"),
    (["--objects", "99", "--out", "g.png"], "object 99 is not in cabinet/train"),
    (["--objects", "a,b", "--out", "g.png"], "--objects: expected indices"),
    (["--images", "16", "--out", "g.png"], "image 16 is not in cabinet/train"),
    (["--out", "g.xyz"], "unknown image format .xyz"),
    ([], "nothing to write"),
])
def test_bad_options_are_one_line_errors(tiny_root, tmp_path, monkeypatch, args, needle):
    monkeypatch.chdir(tmp_path)
    result = run_show(tiny_root / "cabinet" / "train", *args)
    assert result.exit_code == 2, result.output
    assert needle in result.output and len(result.output.strip().splitlines()) == 1, result.output


def test_bad_data_is_a_one_line_error(tiny_root, tmp_path):
    assert run_show(tmp_path / "missing", "--out", tmp_path / "g.png").exit_code == 2
    split = tmp_path / "cabinet" / "train"
    shutil.copytree(tiny_root / "cabinet" / "train", split)
    (split / "shard-00000.h5").write_bytes(b"not hdf5")
    result = run_show(split, "--out", tmp_path / "g.png")
    assert result.exit_code == 2
    assert "shard-00000.h5" in result.output and len(result.output.strip().splitlines()) == 1
    (split / "manifest.json").write_text("{")
    result = run_show(split, "--out", tmp_path / "g.png")
    assert result.exit_code == 2 and "corrupt manifest" in result.output


# --------------------------------------------------------------------------------------
# Nothing clipped; real (ingested) splits draw their axes
# --------------------------------------------------------------------------------------

#: Slack (figure pixels) for a text's extent at the figure's edge (antialiasing rounding).
EDGE_SLACK_PX = 0.5


@pytest.fixture(scope="module")
def real_split(tiny_root, tmp_path_factory):
    return ingest_uneven_cabinet2(tiny_root, tmp_path_factory.mktemp("real_show"))


def _write_predictions(split, path, object_image_pairs):
    """Predictions for the given images: the true axes moved 5 cm along camera y."""
    from articulated_dataset.benchmark.predictions import write_predictions

    view = SplitView.open(split)
    ss = [view.sample(o, i) for o, i in object_image_pairs]
    view.close()
    pose = np.stack([s["axis_pose"] for s in ss]).astype(np.float64)
    pose[..., 1] += 0.05
    write_predictions(path, "test", {view.manifest["class_name"]: {
        "sample_id": np.array([int(s["sample_id"]) for s in ss]), "axis_pose": pose,
        "q": np.stack([s["q"] for s in ss]).astype(np.float64)}})
    return path


@pytest.fixture
def saved_figures(monkeypatch):
    """Every figure make_gallery saves, drawn with Agg (for text extents)."""
    from articulated_dataset.tools.viz import gallery

    figs = []
    real_save = gallery._save

    def save(fig, path, dpi):
        real_save(fig, path, dpi)
        figs.append(fig)

    monkeypatch.setattr(gallery, "_save", save)
    return figs


def _check_texts_inside(fig):
    """Every text lies inside the figure (axes texts inside their axes), and no two figure texts overlap."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    W, H = fig.bbox.width, fig.bbox.height
    boxes = []
    for t in fig.texts:
        if not t.get_text():
            continue
        bb = t.get_window_extent(renderer)
        assert (bb.x0 >= -EDGE_SLACK_PX and bb.y0 >= -EDGE_SLACK_PX and bb.x1 <= W + EDGE_SLACK_PX
                and bb.y1 <= H + EDGE_SLACK_PX), f"{t.get_text()!r} at {bb.bounds} leaves the {W}x{H} figure"
        boxes.append((t.get_text(), bb))
    for ax in fig.axes:
        for t in ax.texts:
            bb, abb = t.get_window_extent(renderer), ax.get_window_extent(renderer)
            assert abb.x0 - EDGE_SLACK_PX <= bb.x0 and bb.x1 <= abb.x1 + EDGE_SLACK_PX, t.get_text()
            assert abb.y0 - EDGE_SLACK_PX <= bb.y0 and bb.y1 <= abb.y1 + EDGE_SLACK_PX, t.get_text()
    for k, (ta, a) in enumerate(boxes):
        for tb, b in boxes[k + 1:]:
            assert not a.overlaps(b), f"{ta!r} {a.bounds} overlaps {tb!r} {b.bounds}"
    return [text for text, _ in boxes]


@pytest.mark.parametrize("cls, n, cols, rgb", [
    ("cabinet2", 1, 4, False), ("drawer", 1, 4, False), ("cabinet2", 2, 4, False), ("refrigerator", 5, 3, False),
    ("microwave", 1, 2, True)])
@pytest.mark.parametrize("with_predictions", [False, True], ids=["truth", "predictions"])
def test_no_text_is_clipped_simulated(tiny_root, tmp_path, saved_figures, cls, n, cols, rgb, with_predictions):
    split = tiny_root / cls / "test"
    preds = _write_predictions(split, tmp_path / "p.h5", select_samples(3, 16, n)) if with_predictions else None
    out = tmp_path / "g.png"
    panels = make_gallery([split], out=out, n=n, cols=cols, rgb=rgb, predictions=preds,
                          per_sample_dir=tmp_path / "per" if n == 1 else None)
    texts = _check_texts_inside(saved_figures[0])
    for fig in saved_figures[1:]:
        _check_texts_inside(fig)
    assert any(t.startswith(f"{cls}/test") for t in texts)  # the header is drawn
    legend = legend_lines(saved_figures[0].get_figwidth(), predictions=with_predictions)
    assert all(line in texts for line in legend), (legend, texts)
    assert any("predicted axis" in t for t in texts) == with_predictions
    view = SplitView.open(split)
    J = len(view.joint_types)
    rows = -(-len(panels) // (2 if rgb else 1) // cols) if n > cols else 1
    expected = gallery_size_px([rows], min(cols, n), (192, 108), rgb=rgb, n_joints=J, predictions=with_predictions,
                               views=[view])
    view.close()
    assert _png_rgb(out).shape[1::-1] == expected


def test_one_sample_gallery_wraps_header_and_legend(tiny_root, tmp_path, saved_figures):
    """In a one-column gallery the header and legend are too wide for one line: they wrap (the
    figure grows), each line fits."""
    out = tmp_path / "g.png"
    make_gallery([tiny_root / "cabinet2" / "test"], out=out, n=1)
    texts = _check_texts_inside(saved_figures[0])
    assert "cabinet2/test" in texts and any(t.startswith("3 objects, 48 images") for t in texts)
    legend = legend_lines(saved_figures[0].get_figwidth(), predictions=False)
    assert len(legend) >= 2 and all(line in texts for line in legend)
    one_line = gallery_size_px([1], 1, (192, 108), rgb=False, n_joints=2)
    assert _png_rgb(out).shape[0] > one_line[1]


def _axis_arrows(ax):
    from matplotlib.patches import FancyArrowPatch

    return [p for p in ax.patches if isinstance(p, FancyArrowPatch)]


@pytest.mark.parametrize("n", [1, 3])
@pytest.mark.parametrize("with_predictions", [False, True], ids=["truth", "predictions"])
def test_real_split_draws_full_axes_and_nothing_clipped(real_split, tmp_path, saved_figures, n, with_predictions):
    preds = _write_predictions(real_split, tmp_path / "p.h5", [(0, 0), (0, 1)]) if with_predictions else None
    out = tmp_path / "g.png"
    panels = make_gallery([real_split], out=out, n=n, predictions=preds)
    assert len(panels) == n
    fig = saved_figures[0]
    texts = _check_texts_inside(fig)
    assert any(t.startswith("cabinet2/real") for t in texts) and any("real captures" in t for t in texts)
    png = _png_rgb(out)
    view = SplitView.open(real_split)
    checked = 0
    for p, ax in zip(panels, fig.axes):
        s = view.sample(p.object_index, p.image_index)
        if not np.isfinite(s["axis_origin"]).any():  # the unlabelled capture: a note, no axis
            assert not _axis_arrows(ax) and any(t.get_text() == "no axis labels" for t in ax.texts)
            continue
        assert np.isnan(s["geometry"]).all() and not (s["mask"] >= 2).any()  # the case that drew only a dot
        arrows = _axis_arrows(ax)
        assert len(arrows) == len(view.joint_types), "every labelled joint gets an axis line with an arrowhead"
        for j, arrow in enumerate(arrows):
            (u0, v0), (u1, v1) = arrow._posA_posB
            assert np.hypot(u1 - u0, v1 - v0) > 20, "a full-length hinge line, not a dot"
            # the line's middle (inside the image) is drawn in the joint's colour in the PNG
            mid = np.array([(u0 + u1) / 2, (v0 + v1) / 2])
            if 2 <= mid[0] <= 189 and 2 <= mid[1] <= 105:
                x, y = p.to_png(mid)[0]
                np.testing.assert_allclose(png[int(round(y)), int(round(x))], to_rgb(joint_colour(j)), atol=COLOUR_TOL)
                checked += 1
        n_dashed = sum(line.get_linestyle() == "--" for line in ax.lines)
        assert n_dashed == (len(view.joint_types) if with_predictions else 0)
    view.close()
    assert checked >= 1


def test_unlabelled_q_reads_no_label(real_split, tmp_path, saved_figures):
    make_gallery([real_split], out=tmp_path / "g.png", n=3)
    texts = _check_texts_inside(saved_figures[0])
    assert texts.count("no label") == 2  # the unlabelled capture's two joints; never "nan"
    assert not any("nan" in t for t in texts)


def test_text_wrapping_fits_and_keeps_words():
    from articulated_dataset.tools.viz.drawing import LEGEND_ITEMS, LEGEND_SEP, TextFitter
    from articulated_dataset.tools.viz.style import TEXT_FIT_FRACTION

    fit = TextFitter(DEFAULT_DPI)
    for width_in in (1.5, 3.2, 6.0, 40.0):
        lines = fit.wrap(LEGEND_ITEMS, LEGEND_SEP, width_in, 7.5)
        assert all(fit.width_in(line, 7.5) <= TEXT_FIT_FRACTION * width_in for line in lines), width_in
        sep = LEGEND_SEP.strip()
        assert [w for w in " ".join(lines).split() if w != sep] == " ".join(LEGEND_ITEMS).split()  # breaks drop only separators
    assert len(fit.wrap(LEGEND_ITEMS, LEGEND_SEP, 40.0, 7.5)) == 1
    assert fit.fit_size("a" * 200, 10.0, 1.0) < 10.0 and fit.fit_size("a", 10.0, 1.0) == 10.0


def test_cli_show_real_split(real_split, tmp_path):
    result = run_show(real_split, "--out", tmp_path / "g.png", "--n", "1")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "g.png").stat().st_size > 1000


def test_real_split_with_uneven_images_per_object(real_split, tmp_path):
    """Object 0 has two captures, object 1 one: the default gallery (12 asked) draws all three, and a
    pair that does not exist is never asked for."""
    view = SplitView.open(real_split)
    assert view.object_images == {0: 2, 1: 1} and view.images_per_object == 2
    view.close()
    panels = make_gallery([real_split], out=tmp_path / "g.png")
    assert sorted((p.object_index, p.image_index) for p in panels) == [(0, 0), (0, 1), (1, 0)]
    assert select_samples(2, 2, 12, object_images={0: 2, 1: 1}) == [(0, 0), (0, 1), (1, 0)]
    assert select_samples(3, 4, 2, object_images={0: 1, 1: 4, 2: 1}) == [(0, 0), (1, 3)]
    assert select_samples(2, 2, 1, images=[1], object_images={0: 1, 1: 2}) == [(1, 1)]
    result = run_show(real_split, "--out", tmp_path / "h.png", "--objects", "1", "--images", "1")
    assert result.exit_code == 2 and "no image 1 of object(s) 1" in result.output
    # --rgb re-renders a generated object: a real split has none (it drew an unrelated random object)
    result = run_show(real_split, "--out", tmp_path / "r.png", "--rgb")
    assert result.exit_code == 2 and "real captures" in result.output and len(result.output.strip().splitlines()) == 1
    assert not (tmp_path / "r.png").exists()


def test_predictions_that_match_no_drawn_image_are_refused(tiny_root, tmp_path):
    """--predictions of another split (no drawn image's sample id) or with another class's number
    of joints is one line, exit 2 (not a figure without a predicted axis and no word)."""
    from articulated_dataset.benchmark.predictions import write_predictions

    split = tiny_root / "microwave" / "test"
    good = _write_predictions(split, tmp_path / "good.h5", [(0, 0), (0, 1)])
    out = tmp_path / "g.png"
    r = CliRunner().invoke(main, ["show", str(split), "--predictions", str(good), "--objects", "0", "--images", "0,1",
                                  "--out", str(out)])
    assert r.exit_code == 0 and out.is_file(), r.output
    view = SplitView.open(split)
    s = view.sample(0, 0)
    view.close()
    other = tmp_path / "other.h5"  # another split's sample ids
    write_predictions(other, "test", {"microwave": {"sample_id": np.array([int(s["sample_id"]) + 1]),
                                                    "axis_pose": s["axis_pose"][None].astype(np.float64),
                                                    "q": s["q"][None].astype(np.float64)}})
    two = tmp_path / "two.h5"  # two joints per microwave image
    write_predictions(two, "test", {"microwave": {"sample_id": np.array([int(s["sample_id"])]),
                                                  "axis_pose": np.repeat(s["axis_pose"][None], 2, 1).astype(np.float64),
                                                  "q": np.repeat(s["q"][None], 2, 1).astype(np.float64)}})
    for preds, needle in [(other, "hold none of the drawn"), (two, "2 joint(s)")]:
        r = CliRunner().invoke(main, ["show", str(split), "--predictions", str(preds), "--objects", "0", "--images", "0",
                                      "--out", str(tmp_path / "x.png")])
        assert r.exit_code == 2 and r.output.count("\n") == 1 and needle in r.output, r.output


def test_show_refuses_huge_ranges_and_non_ascii_digits(split_copy, tmp_path):
    split = split_copy()
    for option, value in (("--objects", "0-99999999999999999"), ("--images", "0-99999999"), ("--objects", "\u0661")):
        assert_one_line_error(run_cli("show", split, option, value, "--out", tmp_path / "g.png"), option)
