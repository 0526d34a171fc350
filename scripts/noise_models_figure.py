"""The figure of docs/real_data.md, "Sensor noise models": one rendered depth image without
noise and through every sensor-noise model of ``articulated_dataset.core.noise.NOISE_MODELS``.

    python scripts/noise_models_figure.py --out docs/img/noise-models.png

Renders one microwave (``artdata generate --class microwave --n 1 --images 1``, at
``--resolution``, in a temporary folder), applies each model with the generator
``numpy.random.default_rng(--seed)`` and draws, per model, the depth (top row; no return in
black) and the difference to the render in millimetres (bottom row).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from articulated_dataset.core.camera import CameraConfig, parse_resolution  # noqa: E402
from articulated_dataset.core.noise import NOISE_MODELS  # noqa: E402
from articulated_dataset.core.units import MM_PER_M  # noqa: E402
from articulated_dataset.format import open_split  # noqa: E402
from articulated_dataset.generation import GenerationConfig, generate_split  # noqa: E402

#: Image size of the render: the D435's 848 x 480 mode halved, so edge effects are a few pixels wide.
DEFAULT_RESOLUTION = "424x240"
#: Seed of the object and the noise: a microwave with its door open 53 deg, 1.5 m away.
DEFAULT_SEED = 4
#: Colour range of the difference row (mm): the axial noise of all three sensors at 1 - 2 m fits in it.
DIFF_RANGE_MM = 20.0
#: Margin (px) around the object's bounding box in the crop drawn.
CROP_MARGIN_PX = 12
#: Width (in) of one panel.
PANEL_WIDTH_IN = 3.2


def render(resolution: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Depth (m) and K of one rendered microwave, noise-free."""
    width, height = parse_resolution(resolution)
    config = GenerationConfig("microwave", split="test", n_objects=1, images_per_object=1, seed=seed,
                              camera=CameraConfig(width, height))
    with tempfile.TemporaryDirectory() as tmp:
        _, [shard] = open_split(generate_split(config, Path(tmp)))
        return np.asarray(shard.sample(0)["depth"], np.float32), np.asarray(shard.K, np.float64)


def crop_box(depth_m: np.ndarray) -> tuple[slice, slice]:
    """Rows and columns around the pixels with depth, grown by ``CROP_MARGIN_PX``."""
    rows, cols = np.nonzero(depth_m > 0)
    H, W = depth_m.shape
    return (slice(max(rows.min() - CROP_MARGIN_PX, 0), min(rows.max() + CROP_MARGIN_PX + 1, H)),
            slice(max(cols.min() - CROP_MARGIN_PX, 0), min(cols.max() + CROP_MARGIN_PX + 1, W)))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="PNG file to write.")
    parser.add_argument("--resolution", default=DEFAULT_RESOLUTION, help="WxH of the render.")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help="Seed of the object and of the noise.")
    parser.add_argument("--dpi", type=int, default=80)
    args = parser.parse_args(argv)

    clean, K = render(args.resolution, args.seed)
    images = {"no noise": clean}
    for name, model in NOISE_MODELS.items():
        if name != "none":
            images[name] = model(clean, K, np.random.default_rng(args.seed))
    rows, cols = crop_box(clean)
    valid = clean > 0
    lo, hi = float(clean[valid].min()), float(clean[valid].max())

    aspect = (rows.stop - rows.start) / (cols.stop - cols.start)
    fig, axes = plt.subplots(2, len(images), figsize=(PANEL_WIDTH_IN * len(images), 2 * PANEL_WIDTH_IN * aspect),
                             squeeze=False, layout="constrained")
    depth_cmap = plt.get_cmap("viridis").with_extremes(bad="black")
    diff_cmap = plt.get_cmap("coolwarm").with_extremes(bad="black")
    for k, (title, depth) in enumerate(images.items()):
        d = depth[rows, cols]
        im = axes[0, k].imshow(np.ma.masked_equal(d, 0.0), cmap=depth_cmap, vmin=lo, vmax=hi)
        axes[0, k].set_title(title)
        diff_mm = np.where((d > 0) & (clean[rows, cols] > 0), (d - clean[rows, cols]) * MM_PER_M, np.nan)
        dim = axes[1, k].imshow(np.ma.masked_invalid(diff_mm), cmap=diff_cmap, vmin=-DIFF_RANGE_MM, vmax=DIFF_RANGE_MM)
        for ax in axes[:, k]:
            ax.set_xticks([])
            ax.set_yticks([])
    axes[0, 0].set_ylabel("depth")
    axes[1, 0].set_ylabel("noisy - render")
    axes[1, 0].set_frame_on(False)
    axes[1, 0].images[0].remove()  # the render against itself: nothing to show
    fig.colorbar(im, ax=axes[0, :].tolist(), shrink=0.8, label="depth (m)")
    fig.colorbar(dim, ax=axes[1, :].tolist(), shrink=0.8, label="difference (mm)")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=args.dpi, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    main()
