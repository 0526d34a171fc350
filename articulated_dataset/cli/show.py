"""``artdata show``: a gallery of labelled depth images (joint axes drawn, q printed)."""

from __future__ import annotations

from pathlib import Path

import click

from articulated_dataset.cli.plan import URDF_HINT, check_object_file_options, object_file_options
from articulated_dataset.core.errors import UserError

#: What ends the refusal of --rgb to rebuild a third-party URDF object from recorded paths
#: outside its split folder.
RGB_URDF_HINT = f"{URDF_HINT}, or generate the split with --rgb to store its colour images"

#: the most indices one range of --objects/--images may expand to (a typo like 0-99999999999 must
#: not allocate gigabytes before the bounds check).
MAX_RANGE = 1_000_000


def parse_index_list(text: str | None, what: str) -> list[int] | None:
    """``"0,3,5-7"`` -> [0, 3, 5, 6, 7]; None stays None."""
    if text is None:
        return None
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part:
                lo, hi = (int(x) for x in part.split("-", 1))
                if hi < lo:
                    raise ValueError
                if hi - lo >= MAX_RANGE:  # every index past the split's end is refused later anyway
                    raise UserError(f"--{what}: range {part} is longer than {MAX_RANGE:,} indices")
                out.extend(range(lo, hi + 1))
            else:
                if not part.isascii():
                    raise ValueError  # int() would read '١' as 1
                out.append(int(part))
        except ValueError:
            raise UserError(f"--{what}: expected indices like 0,3,5-7, got {text!r}") from None
    if not out:
        raise UserError(f"--{what}: no indices given")
    if min(out) < 0:
        raise UserError(f"--{what}: indices must be >= 0, got {min(out)}")
    return sorted(set(out))


@click.command("show")
@click.argument("path", type=click.Path())
@click.option("--out", "out", type=click.Path(dir_okay=False), default=None,
              help="Gallery image to write (.png; .pdf/.svg/.jpg also work).")
@click.option("--per-sample", "per_sample_dir", type=click.Path(file_okay=False), default=None,
              help="Also (or instead) write one PNG per sample into this folder.")
@click.option("--n", "n_samples", type=int, default=12, show_default=True, help="Samples per split.")
@click.option("--objects", default=None, help="Object indices to draw from, e.g. 0,3,5-7 (default: spread over all).")
@click.option("--images", default=None, help="Image indices to draw from, e.g. 0,15 (default: spread over all).")
@click.option("--cols", type=int, default=None, help="Samples per row (default: 4, or 2 with --rgb).")
@click.option("--rgb", is_flag=True, help="Add a shaded colour preview rendered from the same scene (rebuilt from the manifest).")
@click.option("--no-outline", is_flag=True, help="Do not outline the moving parts.")
@click.option("--predictions", "predictions", type=click.Path(dir_okay=False), default=None,
              help="predictions.h5 (artdata predict / baseline): draw its axes dashed beside the true ones.")
@click.option("--dpi", type=int, default=100, show_default=True)
@object_file_options("--rgb")
@click.option("--quiet", "-q", is_flag=True, help="Print nothing on success.")
def show_cmd(path, out, per_sample_dir, n_samples, objects, images, cols, rgb, no_outline, predictions, dpi, urdf,
             mesh_root, quiet):
    """Draw labelled samples of the data at PATH (split, class folder or output root).

    Depth is colour-mapped per image (near bright, far dark; grey = no return); each joint's
    axis is drawn in its own colour (line with arrow = +q, dot = axis origin; for drawers the
    arrow spans the full travel and a ring marks the front's current position), and q is
    printed in degrees (revolute) or centimetres (prismatic).  --rgb rebuilds a split generated
    with --urdf from the URDF named with --urdf (its recorded path is opened only inside the split
    folder), unless the split stores colour images.
    """
    from articulated_dataset.core.safeio import check_can_create, check_outputs_distinct
    from articulated_dataset.format import find_split_dirs
    from articulated_dataset.tools.viz.gallery import make_gallery
    from articulated_dataset.tools.viz.style import DEFAULT_COLUMNS, DEFAULT_COLUMNS_RGB

    check_object_file_options(urdf, mesh_root)
    if urdf is not None and not rgb:
        raise UserError("--urdf names the URDF --rgb rebuilds a third-party object's scene from: add --rgb")
    split_dirs = find_split_dirs(path)
    # the predictions drawn are never written over (an --out of the same name replaced them with the gallery)
    check_outputs_distinct([predictions], [out])
    if out is not None:
        check_can_create(out)  # before drawing: a read-only or missing target is one line now
    if per_sample_dir is not None:
        check_can_create(Path(per_sample_dir) / "probe.png")
    if cols is None:
        cols = DEFAULT_COLUMNS_RGB if rgb else DEFAULT_COLUMNS
    panels = make_gallery(split_dirs, out=out, per_sample_dir=per_sample_dir, n=n_samples,
                          objects=parse_index_list(objects, "objects"), images=parse_index_list(images, "images"),
                          rgb=rgb, cols=cols, dpi=dpi, outline=not no_outline, predictions=predictions,
                          urdf=urdf, mesh_root=mesh_root, rebuild_hint=RGB_URDF_HINT)
    if not quiet:
        n_drawn = len({(p.split, p.object_index, p.image_index) for p in panels})
        written = [str(out)] if out else []
        if per_sample_dir:
            n_files = len({p.file for p in panels if str(p.file) != str(out)})
            written.append(f"{n_files} PNG files in {per_sample_dir}")
        click.echo(f"wrote {' and '.join(written)} ({n_drawn} samples from {len(split_dirs)} split(s))")


COMMANDS = [show_cmd]
