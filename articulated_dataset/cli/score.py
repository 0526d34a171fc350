"""``artdata score``: score predictions.h5 files against ground-truth shards (Table 1/2 metrics)."""

from __future__ import annotations

from pathlib import Path

import click

from articulated_dataset.benchmark.metrics import METRIC_VERSION, METRIC_VERSIONS
from articulated_dataset.core.errors import UserError


def _write(path: str, text: str) -> None:
    """Print ``text`` (``-``) or write it atomically: a failure leaves no partial file and
    whatever was at ``path`` intact (one line naming the file and the free space)."""
    if path == "-":
        click.echo(text, nl=not text.endswith("\n"))
        return
    from articulated_dataset.core.safeio import atomic_write_text

    if Path(path).is_dir():
        raise UserError(f"cannot write {path}: is a directory")
    atomic_write_text(path, text)


@click.command("score")
@click.argument("predictions", nargs=-1, required=True, type=click.Path())
@click.option("--truth", "truth_path", required=True, type=click.Path(),
              help="Ground truth: a split folder, or a folder with <class>/<split>/ below it.")
@click.option("--split", default=None,
              help="Truth split to use when a class has several (default: test). E.g. 'real' for Table 2.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), default=None,
              help="Write the full report as JSON to this file ('-' prints it instead of the table).")
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False), default=None,
              help="Write one CSV line per (class, method) to this file ('-' prints it instead of the table).")
@click.option("--require-complete", is_flag=True,
              help="Exit with code 2 if some truth images of a predicted class have no prediction.")
@click.option("--wide", is_flag=True, help="One line per row with every metric (default: at most 100 columns, "
                                           "the standard metrics in blocks).")
@click.option("--metric-version", type=click.Choice([str(v) for v in METRIC_VERSIONS]), default=str(METRIC_VERSION),
              show_default=True, help="Metric definitions to compute (docs/scoring.md, Versions); 2 reproduces "
                                      "version-2 numbers.")
def score_cmd(predictions, truth_path, split, json_path, csv_path, require_complete, wide, metric_version):
    """Score PREDICTIONS (one or more predictions.h5 files) against the truth.

    Prints the paper's Table 1 layout (axis position error in cm, axis rotation error in
    degrees, configuration error in degrees or cm, as mean +/- standard deviation over images,
    and the number of images scored), the standard error of each mean over objects, then the
    standard metrics.  See docs/scoring.md.
    """
    from articulated_dataset.benchmark.scoring import score
    from articulated_dataset.core.safeio import check_can_create, check_outputs_distinct
    from articulated_dataset.format import find_split_dirs

    try:  # the truth's split folders: a report must not replace one of their shards or manifests
        truth_splits = find_split_dirs(truth_path)
    except UserError:
        truth_splits = []  # score() reports the bad --truth itself
    if json_path == "-" and csv_path == "-":  # two reports on one stream cannot be told apart
        raise UserError("--json - and --csv - would both print to standard output; write one of them to a file")
    check_outputs_distinct(list(predictions), [json_path, csv_path], "--json and --csv", input_folders=truth_splits)
    for target in (json_path, csv_path):  # both writable before either is written: no half-written report
        if target and target != "-":
            check_can_create(target)
    report = score(list(predictions), truth_path, split=split, metric_version=int(metric_version))
    if require_complete:
        partial = [f"{r.class_name} - {r.method} ({r.n_scored}/{r.n_truth})" for r in report.rows if not r.complete]
        if partial:
            raise UserError(f"partial coverage with --require-complete: {', '.join(partial)}")
    if json_path:
        _write(json_path, report.to_json() + "\n")
    if csv_path:
        _write(csv_path, report.to_csv())
    if "-" not in (json_path, csv_path):
        click.echo(report.format_table(wide=wide))


COMMANDS = [score_cmd]
