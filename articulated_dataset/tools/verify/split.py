"""Verifying split folders: find them, check each manifest, run the shard checks (in worker
processes with ``workers > 1``) and collect one :class:`SplitReport` per split."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from articulated_dataset.core.errors import DataFormatError
from articulated_dataset.format import MANIFEST_NAME, TMP_SUFFIX, find_split_dirs, resolve_inside
from articulated_dataset.format.discovery import SHARD_GLOB
from articulated_dataset.tools.verify.manifest import (
    Problem,
    check_manifest_counts,
    check_mujoco_version,
    check_real_manifest,
    load_manifest,
    manifest_config,
)
from articulated_dataset.tools.verify.shard import ShardExpectation, check_shard

#: Largest number of problems listed per shard before the rest are summarised.
MAX_PROBLEMS_PER_FILE = 20


@dataclass
class SplitReport:
    """Result of verifying one split folder."""

    split_dir: Path
    problems: list[Problem] = field(default_factory=list)
    n_shards: int = 0
    n_images: int = 0
    content_checked: bool = True

    @property
    def errors(self) -> list[Problem]:
        """The problems that are not warnings."""
        return [p for p in self.problems if not p.warning]

    @property
    def ok(self) -> bool:
        """True when no problem is an error."""
        return not self.errors

    def to_dict(self) -> dict:
        """The report as plain JSON types (``artdata verify --json``)."""
        return {"split_dir": str(self.split_dir), "ok": self.ok, "shards": self.n_shards, "images": self.n_images,
                "content_checked": self.content_checked,
                "problems": [{"file": p.where, "message": p.message, "warning": p.warning} for p in self.problems]}


def find_splits(path: str | Path) -> list[Path]:
    """Split folders at ``path`` or one/two levels below it (``<class>/<split>``).

    A folder counts if it holds a manifest or shard files, so a split whose manifest was
    lost is still found (and reported).  Nothing found is a :class:`UserError`.
    """
    return find_split_dirs(path, unlisted_shards=True)


def _check_shard_task(args):
    """Executor task (top-level, picklable): ``(path, ShardResult)``."""
    path, expect, content = args
    return path, check_shard(path, expect, content=content)


def _inside(split_dir: Path, name: str, report: SplitReport) -> bool:
    """Whether shard ``name`` stays inside ``split_dir`` (a symbolic link leading out is
    reported as a problem and never read, as every other reader refuses it)."""
    try:
        resolve_inside(split_dir, name)
    except DataFormatError as exc:
        report.problems.append(Problem(name, f"{str(exc).split(': ', 1)[-1]} (not read)"))
        return False
    return True


def _plan_split(split_dir: Path, content: bool) -> tuple[SplitReport, list]:
    """Manifest-level checks of one split and the shard tasks still to run."""
    report = SplitReport(split_dir, content_checked=content)
    manifest, problems = load_manifest(split_dir)
    report.problems += problems
    on_disk = sorted(p.name for p in split_dir.glob(SHARD_GLOB))
    outside = {name for name in on_disk if not _inside(split_dir, name, report)}
    for leftover in sorted(split_dir.glob(f"*{TMP_SUFFIX}")):
        report.problems.append(Problem(leftover.name, "leftover temporary file of an interrupted write "
                                                      "(removed by 'artdata generate ... --resume')", warning=True))
    if manifest is None:
        return report, [(split_dir / name, None, content) for name in on_disk if name not in outside]
    config, msg = manifest_config(manifest)
    if msg:
        report.problems.append(Problem(MANIFEST_NAME, msg))
    real = "real" in manifest
    captures_of: dict = {}
    if real:
        problems, captures_of = check_real_manifest(manifest, config)
        report.problems += problems
    else:
        report.problems += check_manifest_counts(manifest, config)
        report.problems += check_mujoco_version(manifest)
    listed = [r["file"] for r in manifest["shards"]]
    for name in on_disk:
        if name not in listed:
            report.problems.append(Problem(name, "shard file not listed in the manifest (interrupted run? "
                                                 "finish it with 'artdata generate ... --resume')"))
    tasks = []
    for r in manifest["shards"]:
        if r["file"] in outside or (r["file"] not in on_disk and not _inside(split_dir, r["file"], report)):
            continue
        expect = ShardExpectation(
            n_images=r["n_images"], n_bytes=r["bytes"], sha256=r["sha256"], object_start=r["object_start"],
            object_stop=r["object_stop"], class_name=manifest["class_name"], split=manifest["split"],
            seed=manifest["seed"], camera=config.camera if config is not None else None, real=real,
            capture_names=captures_of.get(r["file"]), rgb=config.rgb if config is not None else None,
            framing=config.framing if config is not None else None)
        tasks.append((split_dir / r["file"], expect, content))
    return report, tasks


def _finish_split(report: SplitReport, tasks: list, results: dict) -> SplitReport:
    all_ids = []
    for path, _, _ in tasks:
        res = results[path]
        report.n_shards += 1
        report.n_images += res.n_images
        shown = res.problems[:MAX_PROBLEMS_PER_FILE]
        report.problems += [Problem(path.name, m) for m in shown]
        if len(res.problems) > len(shown):
            report.problems.append(Problem(path.name, f"... and {len(res.problems) - len(shown)} more problems"))
        if res.sample_ids is not None:
            all_ids.append(res.sample_ids)
    if len(all_ids) > 1:
        ids = np.concatenate(all_ids)
        uniq, counts = np.unique(ids, return_counts=True)
        if (counts > 1).any():
            report.problems.append(Problem(report.split_dir.name, f"sample_id: {int((counts > 1).sum())} ids appear in "
                                                                  f"more than one shard of the split "
                                                                  f"(e.g. {int(uniq[counts > 1][0])})"))
    return report


def verify_splits(split_dirs, *, content: bool = True, workers: int = 1, progress=None) -> list[SplitReport]:
    """Verify split folders (manifest, checksums, format and, with ``content``, the label
    invariants), checking shards in ``workers`` processes.  ``progress(n)`` is called after
    each shard.  Never raises for bad data: problems are in the returned reports."""
    plans = [_plan_split(Path(d), content) for d in split_dirs]
    tasks = [t for _, ts in plans for t in ts]
    results = dict(_map(tasks, workers, progress))
    return [_finish_split(report, ts, results) for report, ts in plans]


def verify_split(split_dir: str | Path, *, content: bool = True, workers: int = 1, progress=None) -> SplitReport:
    """:func:`verify_splits` for one split folder."""
    return verify_splits([split_dir], content=content, workers=workers, progress=progress)[0]


def _map(tasks: list, workers: int, progress):
    if workers <= 1 or len(tasks) <= 1:
        for t in tasks:
            out = _check_shard_task(t)
            if progress is not None:
                progress(1)
            yield out
        return
    from articulated_dataset.core.pool import process_map

    for out in process_map(_check_shard_task, tasks, min(workers, len(tasks)), ordered=True):
        if progress is not None:
            progress(1)
        yield out


def count_shards(split_dirs) -> int:
    """Shards that :func:`verify_split` will open (listed in the manifest, else on disk)."""
    total = 0
    for d in split_dirs:
        manifest, _ = load_manifest(Path(d))
        total += len(manifest["shards"]) if manifest is not None else len(list(Path(d).glob(SHARD_GLOB)))
    return total
