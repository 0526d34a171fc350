"""``artdata verify``: check generated splits against their manifests and the format."""

from __future__ import annotations

import json
import os

import click

from articulated_dataset.core.errors import UserError

#: Exit status when data problems were found (2 is reserved for usage errors).
EXIT_PROBLEMS = 1


@click.command("verify")
@click.argument("path", type=click.Path())
@click.option("--quick", is_flag=True, help="Manifest, checksums and format only; skip reading the arrays.")
@click.option("--workers", type=int, default=None, help="Processes checking shards in parallel (default: all cores).")
@click.option("--json", "as_json", is_flag=True, help="Print a JSON report instead of text.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar; print only problems and the summary line.")
@click.pass_context
def verify_cmd(ctx, path, quick, workers, as_json, quiet):
    """Verify generated data at PATH (a split folder, a class folder or an output root).

    Checks manifests (shard list, sizes, sha256 checksums, counts), the shard format
    (attributes, datasets, dtypes, shapes) and the label invariants (finite values, unit
    axes, normalised quaternions, q within the table's limits, masks, depth, sample ids).
    Exit status: 0 all good, 1 problems found, 2 usage error.
    """
    from tqdm import tqdm

    from articulated_dataset.format.manifest import printable
    from articulated_dataset.tools.verify import count_shards, find_splits, verify_splits

    if workers is None:
        workers = os.cpu_count() or 1
    if workers <= 0:
        raise UserError(f"--workers must be positive, got {workers}")
    split_dirs = find_splits(path)
    with tqdm(total=count_shards(split_dirs), unit="shard", desc="verify", disable=quiet or as_json,
              leave=False, dynamic_ncols=True) as bar:
        reports = verify_splits(split_dirs, content=not quick, workers=workers, progress=bar.update)
    bad = [r for r in reports if not r.ok]
    if as_json:
        click.echo(json.dumps({"ok": not bad, "splits": [r.to_dict() for r in reports]}, indent=1))
    else:
        for r in reports:
            if r.ok and not quiet:
                extra = "" if r.content_checked else " (quick: arrays not read)"
                click.echo(printable(f"{r.split_dir}: OK, {r.n_shards} shards, {r.n_images} images{extra}"))
            elif not r.ok:
                click.echo(printable(f"{r.split_dir}: {len(r.errors)} problem(s)"))
            for prob in r.problems:
                if not prob.warning or not quiet:
                    click.echo(printable(f"  {prob}"))  # names from the data: control characters escaped
        n_images = sum(r.n_images for r in reports)
        if bad:
            click.echo(f"verify: problems in {len(bad)} of {len(reports)} split(s)")
        else:
            click.echo(f"verify: all {len(reports)} split(s) OK ({n_images} images)")
    if bad:
        ctx.exit(EXIT_PROBLEMS)


COMMANDS = [verify_cmd]
