"""``artdata export`` / ``artdata import-exr``: OpenEXR interchange that round-trips exactly."""

from __future__ import annotations

import os

import click

from articulated_dataset.core.errors import UserError

#: Interchange formats ``artdata export`` can write.
EXPORT_FORMATS = ("exr",)


def _distinct_targets(sources, targets) -> None:
    """Refuse, before anything is written, two sources with one output folder (two class
    folders whose manifests name the same class, e.g. a copy ``data/drawer_backup``): the
    second refused after the first was written, or with --overwrite silently replaced it."""
    seen: dict[str, object] = {}
    for source, target in zip(sources, targets):
        key = os.path.normpath(os.path.abspath(target))
        if key in seen:
            raise UserError(f"{seen[key]} and {source} would both be written to {target} (their manifests name the "
                            "same class and split); give them one at a time with different outputs")
        seen[key] = source


@click.command("export")
@click.argument("path", type=click.Path())
@click.argument("out_root", type=click.Path(file_okay=False))
@click.option("--format", "fmt", type=click.Choice(EXPORT_FORMATS), default="exr", show_default=True,
              help="exr: float32 single-channel OpenEXR depth (ZIP), 8-bit PNG mask, JSON labels per image.")
@click.option("--overwrite", is_flag=True, help="Replace existing exported folders.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
def export_cmd(path, out_root, fmt, overwrite, quiet):
    """Export the splits at PATH (split, class folder or output root) to OUT_ROOT/<class>/<split>/.

    Each image becomes <stem>.exr (depth, channel "Z", metres), <stem>.mask.png and
    <stem>.json (labels, K); split.json indexes the folder.  'artdata import-exr' turns such
    a folder back into identical shards.
    """
    from tqdm import tqdm

    from articulated_dataset.format import Split, find_split_dirs
    from articulated_dataset.tools.exr import export_split, target_dir

    split_dirs = find_split_dirs(path)
    opened = [Split(d) for d in split_dirs]  # names and shard paths checked before any output
    targets = [target_dir(out_root, s.manifest, s.name) for s in opened]
    _distinct_targets(split_dirs, targets)
    total = sum(len(sh) for s in opened for sh in s.shards)
    for s in opened:
        s.close()
    with tqdm(total=total, unit="img", desc=f"export {fmt}", disable=quiet, dynamic_ncols=True, leave=False) as bar:
        for d, target in zip(split_dirs, targets):
            export_split(d, target, overwrite=overwrite, progress=bar.update)
    if not quiet:
        click.echo(f"exported {total} images from {len(split_dirs)} split(s) to {out_root}")


@click.command("import-exr")
@click.argument("path", type=click.Path())
@click.option("--out", "out_root", type=click.Path(file_okay=False), required=True,
              help="Output root: shards go to OUT/<class>/<split>/.")
@click.option("--overwrite", is_flag=True, help="Replace existing split folders.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
def import_cmd(path, out_root, overwrite, quiet):
    """Rebuild HDF5 shards from folders written by 'artdata export --format exr' (exact round trip)."""
    from tqdm import tqdm

    from articulated_dataset.tools.exr import find_exports, import_split, load_index, target_dir

    exports = find_exports(path)
    indexes = [load_index(d) for d in exports]  # bad folders fail here, before any output
    targets = [target_dir(out_root, ix, d.name) for d, ix in zip(exports, indexes)]
    _distinct_targets(exports, targets)
    total = sum(len(s["samples"]) for ix in indexes for s in ix["shards"])
    with tqdm(total=total, unit="img", desc="import exr", disable=quiet, dynamic_ncols=True, leave=False) as bar:
        for d, target in zip(exports, targets):
            import_split(d, target, overwrite=overwrite, progress=bar.update)
    if not quiet:
        click.echo(f"imported {total} images into {len(exports)} split(s) under {out_root}")


COMMANDS = [export_cmd, import_cmd]
