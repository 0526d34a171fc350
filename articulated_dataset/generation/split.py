"""Stage 6 of the pipeline at the split level: writing a whole split with its manifest
(:func:`generate_split`), and the split folder's lifecycle around it.

Every shard is a pure function of the :class:`GenerationConfig` and its index
(:func:`~articulated_dataset.generation.pipeline.generate_shard`), so executors (local
processes, or Ray; :mod:`articulated_dataset.core.pool`) only map
:func:`~articulated_dataset.generation.pipeline.run_shard` over shard indices and any
executor gives identical bytes.  Around them: the split's lock, ``--resume`` (the shards a
run of the same settings completed), ``--overwrite`` (a staging sibling swapped in when
complete), the memory and disk checks, and what a failed run keeps.
"""

from __future__ import annotations

import errno
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

from articulated_dataset.core.errors import DataFormatError, UserError, option
from articulated_dataset.core.mujoco_support import different_mujoco, manifest_entry
from articulated_dataset.core.safeio import (
    FULL_HINT,
    WriteError,
    available_memory_bytes,
    check_free_space,
    check_name_length,
    check_writable_dir,
    ensure_dir,
    format_bytes,
    fsync_dir,
    remove_created_dirs,
    temporary_target,
    translated,
)
from articulated_dataset.format.manifest import write_manifest
from articulated_dataset.format.records import split_manifest
from articulated_dataset.generation.config import GenerationConfig, split_dir_for
from articulated_dataset.generation.pipeline import run_shard, shard_attrs

log = logging.getLogger(__name__)


#: Files of a split folder that this package writes (the manifest and shards; their temporary
#: siblings are recognised by :func:`_is_own_temporary`).  Nothing else in a split folder is
#: ever deleted or replaced.
_DATA_FILE = re.compile(r"manifest\.json|shard-[0-9]{5,}\.h5")
_SHARD_FILE = re.compile(r"shard-([0-9]{5,})\.h5")
#: Siblings of ``OUT/<class>/<split>`` (hidden): the lock held while a run writes the split,
#: the new split an ``--overwrite`` builds, and the old one while the two are swapped.
LOCK_SUFFIX = ".lock"
STAGING_SUFFIX = ".new"
RETIRED_SUFFIX = ".old"
#: Opening the lock file: created if missing, never through a symbolic link (a dangling link
#: would otherwise create a file wherever it points).
LOCK_OPEN_FLAGS = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
#: Permissions of a new lock file (before the umask).
LOCK_FILE_MODE = 0o644
#: Memory one image takes in a shard's buffers while it is generated (float32 depth + uint8
#: mask), and the renderer's own buffers (RGB, depth, GL colour/depth/stencil), per pixel.
SHARD_BUFFER_BYTES_PER_PIXEL = 5
RENDERER_BYTES_PER_PIXEL = 24
#: Memory of one worker process before its first shard (Python, NumPy, MuJoCo, the GL
#: driver; ~200-250 MB measured), counted for each worker process a run would start.
WORKER_PROCESS_BYTES = 250e6
#: Fraction of the available memory generation may plan to use (the rest: Python, MuJoCo,
#: the GL driver, other programs).
MEMORY_BUDGET_FRACTION = 0.5
#: A lower bound of a shard's size on disk per pixel: measured 0.08-0.10 byte/pixel (1.6-2.1
#: KB per 192x108 image); a split certainly needs more than this, so a run that would not fit
#: is refused before it starts.
MIN_DISK_BYTES_PER_PIXEL = 0.02


def _sibling(split_dir: Path, suffix: str) -> Path:
    return split_dir.parent / f".{split_dir.name}{suffix}"


def _is_own_temporary(name: str) -> bool:
    """Whether ``name`` is a temporary file's name of a manifest or shard
    (``.shard-00000.h5.<hex>.partial``; ``shard-00000.h5.partial`` from earlier versions)."""
    target = temporary_target(name)
    return target is not None and _DATA_FILE.fullmatch(target) is not None


def _own_entries(folder: Path) -> tuple[list[Path], list[Path]]:
    """``(ours, foreign)`` entries of ``folder``: regular files named as we name them, and
    everything else (other files, folders, symbolic links).  A symbolic link named as one of
    our temporary files (planted there: ours are never links) counts as ours, a leftover to
    remove: removing it deletes the link itself, never what it points to."""
    ours: list[Path] = []
    foreign: list[Path] = []
    for p in sorted(folder.iterdir()):
        if p.is_symlink():
            own = _is_own_temporary(p.name)
        else:
            own = (_DATA_FILE.fullmatch(p.name) is not None or _is_own_temporary(p.name)) and p.is_file()
        (ours if own else foreign).append(p)
    return ours, foreign


def _remove_own_folder(folder: Path) -> None:
    """Delete ``folder`` if it holds only files we write (else leave it and say so)."""
    if not folder.is_dir() or folder.is_symlink():
        return
    ours, foreign = _own_entries(folder)
    if foreign:
        raise UserError(f"{folder} holds files artdata did not write ({', '.join(p.name for p in foreign[:3])}); "
                        "move them away (nothing was deleted)")
    for p in ours:
        p.unlink()
    folder.rmdir()


class SplitLock:
    """Exclusive lock of one split folder while a run writes it: ``OUT/<class>/.<split>.lock``
    (``flock``, released by the kernel when the process dies, whatever kills it).

    The lock file is removed when released; a run that finds the file replaced after locking
    it locks the new one, so two runs never both hold the lock.
    """

    def __init__(self, split_dir: Path):
        self.split_dir = split_dir
        self.path = _sibling(split_dir, LOCK_SUFFIX)
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock (non-blocking): another run holding it, or a symbolic link at the lock path, is the user's
        mistake. Without ``fcntl`` (Windows) it logs a warning and locks nothing."""
        try:
            import fcntl
        except ImportError:  # no flock (Windows): runs are not protected from each other
            log.warning("no file locking on this platform: do not run two generate commands on %s", self.split_dir)
            return
        while True:
            try:
                with translated(self.path, "create lock file"):
                    fd = os.open(self.path, LOCK_OPEN_FLAGS, LOCK_FILE_MODE)
            except WriteError as exc:
                if exc.errno == errno.ELOOP:  # O_NOFOLLOW: a link there, dangling or not
                    raise UserError(f"{self.path} is a symbolic link; the lock file is never opened through a link "
                                    "(remove it)") from None
                raise
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise UserError(f"another artdata generate is writing {self.split_dir} (it holds {self.path}); "
                                "wait for it to finish or stop it") from None
            try:
                st, held = os.lstat(self.path), os.fstat(fd)
                same = (st.st_dev, st.st_ino) == (held.st_dev, held.st_ino)
            except FileNotFoundError:
                same = False
            if same:
                self._fd = fd
                return
            os.close(fd)  # released and removed by the run that held it: lock the new file

    def release(self) -> None:
        """Remove the lock file and release the lock (nothing if not held)."""
        if self._fd is None:
            return
        try:
            os.unlink(self.path)
        except OSError:
            pass
        os.close(self._fd)
        self._fd = None


@dataclass
class _Run:
    """What :func:`_begin` decided: where shards go and what already exists."""

    split_dir: Path
    target: Path  # split_dir, or its staging sibling with --overwrite
    records: dict[int, dict]
    created: list[Path]  # folders this run created (removed again if it writes nothing)
    lock: SplitLock


def _restore_interrupted_swap(split_dir: Path) -> None:
    """An ``--overwrite`` killed between its two renames left the old split as
    ``.<split>.old`` and no split: put the old split back (lock held)."""
    retired = _sibling(split_dir, RETIRED_SUFFIX)
    if retired.is_dir() and not retired.is_symlink() and not split_dir.exists() and not split_dir.is_symlink():
        os.rename(retired, split_dir)


def _remove_interrupted_siblings(split_dir: Path) -> None:
    """Remove the ``.new``/``.old`` siblings a killed ``--overwrite`` left (lock held, and
    only once this run proceeds)."""
    for suffix in (STAGING_SUFFIX, RETIRED_SUFFIX):
        _remove_own_folder(_sibling(split_dir, suffix))


def _refuse_links(split_dir: Path) -> None:
    """Refuse a symbolic link at ``OUT/<class>``, the split folder or its staging and retired
    siblings: the split, its lock and an ``--overwrite``'s removals would land wherever the
    link points, outside what the user named (``OUT``)."""
    for p in (split_dir.parent, split_dir, _sibling(split_dir, STAGING_SUFFIX), _sibling(split_dir, RETIRED_SUFFIX)):
        if p.is_symlink():
            raise UserError(f"{p} is a symbolic link; generate writes only into real folders, never through a link "
                            f"inside {option('out_root')} (remove the link, or give its target as "
                            f"{option('out_root')})")


def _begin(split_dir: Path, config: GenerationConfig, *, resume: bool, overwrite: bool) -> _Run:
    """Lock the split and decide what to do.  A refusal changes nothing on disk (and removes
    the folders and lock it created to find out)."""
    _refuse_links(split_dir)
    if split_dir.exists() and not split_dir.is_dir():
        raise UserError(f"{split_dir} exists and is not a folder")
    created = ensure_dir(split_dir.parent)
    lock = SplitLock(split_dir)
    try:
        lock.acquire()
        _restore_interrupted_swap(split_dir)  # a restore, never a deletion
        ours, foreign = _own_entries(split_dir) if split_dir.is_dir() else ([], [])
        data = [p for p in ours if not _is_own_temporary(p.name)]
        stale = [p for p in ours if _is_own_temporary(p.name)]  # a killed run's (or a planted link); no run holds the lock
        names = ", ".join(p.name for p in foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        records: dict[int, dict] = {}
        target = split_dir
        if not data:
            if foreign:
                raise UserError(f"{split_dir} is not empty and holds no generated split ({names}); "
                                f"choose another {option('out_root')} or {option('split')}")
        elif not (resume or overwrite):
            raise UserError(f"{split_dir} already holds generated data; pass {option('resume')} to continue it or "
                            f"{option('overwrite')} to replace it")
        elif overwrite:
            if foreign:
                raise UserError(f"{split_dir} holds files artdata did not write ({names}); {option('overwrite')} "
                                "replaces only generated splits: move them away first")
            target = _sibling(split_dir, STAGING_SUFFIX)
        else:
            records = _resume_records(split_dir, config)
        if split_dir.is_dir():  # e.g. a --resume into a read-only folder: one line now, before any work
            check_writable_dir(split_dir)
        # Proceeding: now (and only now) remove what killed runs left (a link: the link itself).
        _remove_interrupted_siblings(split_dir)
        for p in stale:
            with translated(p, "remove"):
                p.unlink()
        created += ensure_dir(target)
    except BaseException:
        lock.release()
        remove_created_dirs(created)
        raise
    return _Run(split_dir, target, records, created, lock)


def _resume_records(split_dir: Path, config: GenerationConfig) -> dict[int, dict]:
    """Records of the shards a run of ``config`` already completed in ``split_dir``; a
    manifest or shard of other settings is refused (never adopted)."""
    from articulated_dataset.format import MANIFEST_NAME, Shard, read_manifest, resolve_inside, sha256_file

    records: dict[int, dict] = {}
    manifest_path = split_dir / MANIFEST_NAME
    different = f"{option('resume')} needs the same command (or use {option('overwrite')})"
    if manifest_path.exists():
        old = read_manifest(split_dir)
        try:
            old_config = GenerationConfig.from_dict(old["config"])
            listed = [(_SHARD_FILE.fullmatch(rec["file"]), rec) for rec in old["shards"]]
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise DataFormatError(f"{manifest_path}: corrupt manifest ({type(exc).__name__}: {exc}); "
                                  f"use {option('overwrite')}") from None
        if old_config != config:
            raise UserError(f"{split_dir} was generated with different settings; {different}")
        other_mujoco = different_mujoco(old, str(manifest_path))  # its depth bytes could differ
        if other_mujoco is not None:
            raise UserError(f"{split_dir} was {other_mujoco}; {option('resume')} needs the same MuJoCo "
                            f"(or use {option('overwrite')})")
        for m, rec in listed:
            if m is None or int(m.group(1)) >= config.n_shards:
                raise DataFormatError(f"{manifest_path}: corrupt manifest (shard file {str(rec['file'])[:80]!r}); "
                                      f"use {option('overwrite')}")
            records[int(m.group(1))] = rec
    # Shards listed but missing or of another size are generated again; shards on disk but
    # not in the manifest (killed between rename and manifest update) are complete by
    # construction (atomic rename) if they were written with these settings.
    # A listed record is kept only as this command would have written it; any other (a
    # tampered count, object range or checksum) is dropped, so its file is checked and
    # adopted below like an unlisted one (or generated again).
    for i, rec in list(records.items()):
        path = split_dir / rec["file"]
        if not path.is_file() or path.stat().st_size != rec.get("bytes") or not _record_as_written(rec, config, i):
            del records[i]
    for path in sorted(split_dir.iterdir()):
        m = _SHARD_FILE.fullmatch(path.name)
        if m is None or int(m.group(1)) in records:
            continue
        i = int(m.group(1))
        if i >= config.n_shards:
            raise UserError(f"{path} is not a shard of this command ({config.n_shards} shards); {different}")
        resolve_inside(split_dir, path.name)  # a symbolic link leading out is refused, never read or adopted
        sh = Shard(path)
        try:
            attrs, n = sh.attrs, len(sh)
        finally:
            sh.close()
        objects = config.shard_objects(i)
        for key, want in shard_attrs(config, objects).items():
            have = attrs.get(key)
            if key != "package_version" and have != want:
                raise UserError(f"{path} was generated with different settings ({key} = {str(have)[:60]}, "
                                f"this command: {str(want)[:60]}); {different}")
        records[i] = {"file": path.name, "n_images": n, "bytes": path.stat().st_size, "sha256": sha256_file(path),
                      "object_start": objects.start, "object_stop": objects.stop,
                      "pose_attempts": int(attrs.get("pose_attempts", 0))}
    return records


_SHA256 = re.compile(r"[0-9a-f]{64}")


def _record_as_written(rec: dict, config: GenerationConfig, i: int) -> bool:
    """Whether manifest record ``rec`` of shard ``i`` holds what a run of ``config`` writes."""
    objects = config.shard_objects(i)
    pose_attempts = rec.get("pose_attempts", 0)
    return (rec.get("object_start") == objects.start and rec.get("object_stop") == objects.stop
            and rec.get("n_images") == len(objects) * config.images_per_object
            and isinstance(rec.get("sha256"), str) and _SHA256.fullmatch(rec["sha256"]) is not None
            and isinstance(pose_attempts, int) and not isinstance(pose_attempts, bool) and 0 <= pose_attempts < 2**63)


def _finish_overwrite(run: _Run) -> None:
    """Swap the complete new split (staging sibling) in for the old one."""
    retired = _sibling(run.split_dir, RETIRED_SUFFIX)
    with translated(run.split_dir, "replace"):
        os.rename(run.split_dir, retired)
        os.rename(run.target, run.split_dir)
    fsync_dir(run.split_dir.parent)
    _remove_own_folder(retired)


def _remove_own_temporaries(folder: Path) -> None:
    """Remove the temporary files of manifests and shards in ``folder`` (lock held: no run
    writes them any more; a worker killed and retried by Ray leaves one; a link: the link
    itself)."""
    for p in folder.iterdir():
        if _is_own_temporary(p.name):
            p.unlink(missing_ok=True)


def _abandon(run: _Run) -> None:
    """After a failure: drop what cannot be continued, keep what ``--resume`` can."""
    if run.target != run.split_dir:  # an --overwrite: the old split stays as it was
        _remove_own_folder(run.target)
    elif run.target.is_dir():
        _remove_own_temporaries(run.target)


def check_resources(config: GenerationConfig, split_dir: Path, *, workers: int, remote: bool = False,
                    done_images: int = 0) -> None:
    """Refuse (one line) a run whose shards cannot fit in this machine's memory or whose
    images cannot fit on the output's filesystem, before anything is allocated."""
    pixels = config.camera.width_px * config.camera.height_px
    per_shard = min(config.objects_per_shard, config.n_objects) * config.images_per_object
    if not remote:
        in_flight = max(1, min(workers, config.n_shards))
        process = WORKER_PROCESS_BYTES if in_flight > 1 else 0.0  # one worker runs in this process
        need = in_flight * (per_shard * pixels * SHARD_BUFFER_BYTES_PER_PIXEL + pixels * RENDERER_BYTES_PER_PIXEL + process)
        avail = available_memory_bytes()
        if avail is not None and need > MEMORY_BUDGET_FRACTION * avail:
            raise UserError(
                f"{in_flight} worker(s) with shards of {per_shard} images of {config.camera.width_px}x{config.camera.height_px} px "
                f"need {format_bytes(need)} of memory, more than half of the {format_bytes(avail)} available; "
                f"lower {option('objects_per_shard')}, {option('images_per_object')}, "
                f"{option('width')}/{option('height')} or {option('workers')}")
    remaining = config.n_objects * config.images_per_object - done_images
    check_free_space(split_dir.parent if not split_dir.exists() else split_dir,
                     remaining * pixels * MIN_DISK_BYTES_PER_PIXEL, f"{remaining} images of {pixels} px")


def generate_split(
    config: GenerationConfig,
    out_root: str | Path,
    *,
    workers: int = 1,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = False,
    executor=None,
) -> Path:
    """Generate every shard of ``config`` under ``out_root/<class>/<split>`` and its manifest.

    Shards are independent, so the result is byte-identical for any executor, any number of
    ``workers`` and across interruptions with ``resume``.  ``executor`` (see
    :mod:`articulated_dataset.core.pool`) defaults to local processes (``workers``).
    Returns the split folder.

    Lifecycle (docs/security.md): the split is locked while a run writes it; a refused run
    changes nothing; ``overwrite`` builds the new split beside the old one and swaps them
    only when it is complete; a failed run keeps its complete shards for ``resume`` and
    leaves nothing if it completed none.
    """
    from tqdm import tqdm

    from articulated_dataset.core.pool import local_executor

    if resume and overwrite:
        raise UserError(f"{option('resume')} and {option('overwrite')} are mutually exclusive")
    if executor is None:
        executor = local_executor(workers)
    split_dir = split_dir_for(out_root, config)
    check_name_length(_sibling(split_dir, LOCK_SUFFIX))  # the longest name a run writes beside the split
    remote = getattr(executor, "remote", False)  # Ray: shards are built in other machines' memory
    check_resources(config, split_dir, workers=workers, remote=remote)
    run = _begin(split_dir, config, resume=resume, overwrite=overwrite)
    records = run.records
    try:
        done_images = sum(r["n_images"] for r in records.values())
        if done_images:
            check_resources(config, split_dir, workers=workers, remote=remote, done_images=done_images)
        total_images = config.n_objects * config.images_per_object
        bar = tqdm(total=total_images, initial=done_images, unit="img", disable=not progress,
                   desc=f"{config.class_name}/{config.split}", dynamic_ncols=True)
        todo = ((config, i, run.target) for i in range(config.n_shards) if i not in records)
        try:
            for i, rec in executor.map_unordered(run_shard, todo, progress=bar.update):
                records[i] = rec
                write_manifest(run.target, split_manifest(config, [records[i] for i in sorted(records)], **manifest_entry()))
        finally:
            bar.close()
        write_manifest(run.target, split_manifest(config, [records[i] for i in sorted(records)], **manifest_entry()))
        _remove_own_temporaries(run.target)
        if run.target != split_dir:
            _finish_overwrite(run)
    except BaseException as exc:
        _abandon(run)
        run.lock.release()
        remove_created_dirs(run.created)  # only folders still empty: a run that wrote nothing leaves nothing
        if isinstance(exc, WriteError) and run.target == split_dir and records:
            when = "once there is space" if exc.disk_full else "once the folder can be written"
            raise WriteError(f"{exc.message.removesuffix(FULL_HINT)}; the {len(records)} complete shard(s) are kept: "
                             f"run the same command with {option('resume')} {when}", exc.path, exc.errno) from None
        raise
    run.lock.release()
    return split_dir
