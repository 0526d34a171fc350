"""The paper's Table 1 baselines: Mean, nearest neighbour (NN) and ICP to the mean object.

Each baseline predicts, for every image of a class's test split, the axis pose, the
configuration, the geometry and the part offset, and is written as a ``predictions.h5``
(:mod:`articulated_dataset.benchmark.predictions`) so that ``artdata score`` scores it like any other
method.  See docs/baselines.md.

``run_baseline(name, train_dir, test_dir, out, ...)`` runs one of :data:`BASELINES` and
writes its predictions; the modules (:mod:`.mean`, :mod:`.nn`, :mod:`.icp` with :mod:`.icp_model`
and :mod:`.clouds`) hold the algorithms.  scipy (ICP) is imported only when ICP runs.
"""

from __future__ import annotations

from pathlib import Path

from articulated_dataset.core.errors import UserError, option

#: CLI name -> (module, method name written in predictions files).
BASELINES = {"mean": ("mean", "Mean"), "nn": ("nn", "NN"), "icp": ("icp", "ICP")}


def baseline_module(name: str):
    """The module implementing baseline ``name`` (one of :data:`BASELINES`)."""
    import importlib

    if name not in BASELINES:
        raise UserError(f"unknown baseline {name!r}; choose from: {', '.join(BASELINES)}")
    return importlib.import_module(f"{__name__}.{BASELINES[name][0]}")


def run_baseline(name: str, train_dir, test_dir, out, *, mean_dir=None, workers: int | None = 1,
                 progress: bool = False, overwrite: bool = True, **options):
    """Run baseline ``name`` on one class and write ``out`` (predictions.h5); returns the
    :class:`~.common.BaselineResult`.  Every baseline's ``predict`` takes the same arguments
    (``mean_dir``: the mean-object split, used by ICP only; ``options``: baseline specific).
    ``workers`` None: all cores.  An existing ``out`` without ``overwrite``, a target that cannot be
    created and a non-positive ``workers`` are :class:`~articulated_dataset.core.errors.UserError`,
    raised before the baseline runs."""
    import os

    from articulated_dataset.core.errors import UserError
    from articulated_dataset.core.safeio import check_can_create, check_outputs_distinct
    from articulated_dataset.methods.baselines.common import write_result

    out = Path(out)
    # a shard or manifest of an input split must never be replaced by the predictions
    folders = [d for d in (train_dir, test_dir, mean_dir) if d]
    if name == "icp" and not mean_dir:  # ICP reads the mean object next to the training split (or its cache)
        from articulated_dataset.methods.baselines.icp import MEAN_CACHE_DIR, default_mean_dir

        folders += [default_mean_dir(train_dir), Path(train_dir).parent / MEAN_CACHE_DIR]
    check_outputs_distinct([], [out], input_folders=folders)
    if out.exists() and not overwrite:
        raise UserError(f"{out} exists; pass {option('overwrite')} to replace it")
    check_can_create(out)  # a read-only or full target is one line now, not after the run
    if workers is None:
        workers = os.cpu_count() or 1
    if workers <= 0:
        raise UserError(f"{option('workers')} must be positive, got {workers}")

    result = baseline_module(name).predict(train_dir, test_dir, mean_dir=mean_dir, workers=workers,
                                           progress=progress, **options)
    write_result(result, Path(out))
    return result
