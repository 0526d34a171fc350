"""Safe writes: every file is written to a temporary sibling, fsync'ed and renamed into place.

A reader (or a later run) sees the old file or the new one, never a mix, and a failure
never destroys what was there.  Operating-system refusals that are the user's to fix (disk
full, quota, read-only filesystem, no permission, a missing folder) become one
:class:`WriteError` naming the file and the free space left on its filesystem; the
temporary file is removed.  Any other exception propagates unchanged (after the cleanup).

Use :func:`atomic_write_bytes` / :func:`atomic_write_text` for data in memory,
:func:`atomic_path` for writers that need a file name (matplotlib, PIL), and
:func:`atomic_write_h5` for HDF5 files: the file is built in memory and written with one
ordinary write, so a full disk can never leave the HDF5 library in a broken state.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
from pathlib import Path
from typing import Callable, Iterator

from .errors import UserError

log = logging.getLogger(__name__)

#: Suffix of temporary siblings (``name.partial``); a file with it is never valid data.
TMP_SUFFIX = ".partial"

#: errno values that mean "this output cannot be written here" (the user's to fix).
_REASONS = {
    errno.ENOSPC: "no space left on device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EFBIG: "file too large for this filesystem",
    errno.EROFS: "read-only filesystem",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.ENOENT: "no such file or directory",
    errno.ENOTDIR: "a parent is not a directory",
    errno.EISDIR: "is a directory",
    errno.EEXIST: "exists and is not a directory",
    errno.ENAMETOOLONG: "file name too long",
    errno.EINVAL: "invalid file name for this filesystem",
    errno.ELOOP: "too many levels of symbolic links",
    errno.EIO: "input/output error",
    errno.ENXIO: "no such device",
    errno.ENODEV: "no such device",
}
#: errno values of a full filesystem (the message suggests freeing space).
_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}
#: Appended to the message of a full filesystem.
FULL_HINT = "; free some space and run again"
#: Units of :func:`format_bytes` (powers of 1000).
_UNITS = ("B", "kB", "MB", "GB", "TB", "PB", "EB")
_KILO = 1000.0


class WriteError(UserError):
    """A file could not be written (disk full, read-only, permission...); one line."""

    def __init__(self, message: str, path: str = "", errno_: int | None = None):
        super().__init__(message)
        self.path = path
        self.errno = errno_

    def __reduce__(self):  # picklable across worker processes with its fields
        return (type(self), (str(self), self.path, self.errno))

    @property
    def disk_full(self) -> bool:
        return self.errno in _FULL


def format_bytes(n: float) -> str:
    """``1234567`` -> ``'1.2 MB'`` (decimal units)."""
    n = float(n)
    for unit in _UNITS:
        if abs(n) < _KILO or unit == _UNITS[-1]:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= _KILO
    raise AssertionError("unreachable")


def _existing_ancestor(path: Path) -> Path:
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def free_bytes(path: str | Path) -> int | None:
    """Bytes available to this user on the filesystem of ``path`` (or of its nearest existing
    parent); None if unknown."""
    try:
        st = os.statvfs(_existing_ancestor(Path(path)))
    except OSError:
        return None
    if st.f_blocks == 0:  # a pseudo filesystem (/proc, /sys): no size to speak of
        return None
    return st.f_bavail * st.f_frsize


def free_space_text(path: str | Path) -> str:
    free = free_bytes(path)
    return "free space unknown" if free is None else f"{format_bytes(free)} free"


def write_error(path: str | Path, exc: OSError, action: str = "write") -> WriteError | None:
    """The :class:`WriteError` for ``exc`` raised while writing ``path``; None if ``exc`` is
    not a refusal the user can fix (then it is a bug and should propagate)."""
    code = exc.errno
    if code not in _REASONS:
        return None
    reason = _REASONS[code]
    message = f"cannot {action} {path}: {reason} ({free_space_text(path)} on its filesystem)"
    if code in _FULL:
        message += FULL_HINT
    return WriteError(message, str(path), code)


@contextlib.contextmanager
def translated(path: str | Path, action: str = "write") -> Iterator[None]:
    """Turn a user-fixable :class:`OSError` inside the block into a :class:`WriteError`."""
    try:
        yield
    except OSError as exc:
        err = write_error(path, exc, action)
        if err is None:
            raise
        raise err from None


def temporary_sibling(path: str | Path) -> Path:
    """``dir/name.partial`` for ``dir/name``."""
    path = Path(path)
    return path.with_name(path.name + TMP_SUFFIX)


def fsync_dir(path: str | Path) -> None:
    """Make a rename in ``path`` durable (best effort: some filesystems refuse)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _remove_quietly(path: Path) -> None:
    try:
        path.unlink()
    except FileNotFoundError:
        pass
    except OSError as exc:  # nothing more can be done; say so in the log
        log.warning("could not remove temporary file %s: %s", path, exc)


def ensure_dir(path: str | Path) -> list[Path]:
    """Create folder ``path`` and its missing parents; return the folders created (outermost
    first), so that a failed run can remove exactly those.  Errors are :class:`WriteError`."""
    path = Path(path)
    missing = []
    p = path
    while not p.exists() and not p.is_symlink() and p != p.parent:
        missing.append(p)
        p = p.parent
    if p.exists() and not p.is_dir():
        raise WriteError(f"cannot create {path}: {p} exists and is not a directory", str(path), errno.ENOTDIR)
    created = []
    for d in reversed(missing):
        with translated(d, "create folder"):
            try:
                d.mkdir()
            except FileExistsError:  # made meanwhile by someone else: not ours to remove
                if not d.is_dir():
                    raise
                continue
        created.append(d)
    return created


def remove_created_dirs(created: list[Path]) -> None:
    """Remove the folders :func:`ensure_dir` created, innermost first, where still empty."""
    for d in reversed(created):
        try:
            d.rmdir()
        except OSError:  # not empty (someone else's files) or gone: leave it
            return


def _refuse_special_file(path: Path) -> None:
    """A :class:`WriteError` where ``path`` exists and is neither a regular file nor a folder (a
    device, FIFO or socket: writing would replace it)."""
    import stat

    try:
        mode = os.stat(path).st_mode  # follows a link: /dev/stdout -> /proc/self/fd/1 -> a pipe
    except OSError:
        return
    if not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):
        raise WriteError(f"cannot write {path}: not a regular file (a device, FIFO or socket would be replaced); "
                         "use '-' for standard output where offered", str(path), errno.EINVAL)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling path to write; on success it is fsync'ed and renamed to
    ``path``.  On any failure the temporary file is removed and ``path`` is untouched."""
    path = Path(path)
    _refuse_special_file(path)
    tmp = temporary_sibling(path)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        _remove_quietly(tmp)  # first, so that the message gives the free space without it
        err = write_error(path, exc) if isinstance(exc, OSError) else None
        if err is None:
            raise
        raise err from None
    fsync_dir(path.parent)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary sibling + fsync + rename)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


#: HDF5 reports the operating system's error inside its message ("errno = 28, ...").
_H5_ERRNO = re.compile(r"errno = (\d+)")


def _h5_errno(exc: BaseException) -> int | None:
    code = getattr(exc, "errno", None)
    if code is None:
        m = _H5_ERRNO.search(str(exc))
        code = int(m.group(1)) if m else None
    return code


def atomic_write_h5(path: str | Path, build: Callable, **file_kwargs) -> None:
    """Build an HDF5 file with ``build(h5py.File)`` and write it atomically to ``path``.

    HDF5's core driver keeps the file in memory and writes it in one piece when it is
    closed, with the same bytes as a file written directly (same ``file_kwargs``); a full
    disk then fails that one write, which becomes a :class:`WriteError`, instead of failing
    inside HDF5's metadata cache (which left it in a broken state that crashed the process).
    """
    import h5py

    with atomic_path(path) as tmp:
        try:
            f = h5py.File(tmp, "w", driver="core", backing_store=True, **file_kwargs)
            try:
                build(f)
            finally:
                f.close()
        except (OSError, RuntimeError) as exc:
            code = _h5_errno(exc)
            if code is None or code not in _REASONS:
                raise
            raise OSError(code, os.strerror(code)) from None


def check_writable_dir(path: str | Path) -> None:
    """Raise a :class:`WriteError` unless a file can be created in existing folder ``path``."""
    probe = Path(path) / f".artdata-write-test-{os.getpid()}{TMP_SUFFIX}"
    with translated(path):
        probe.write_bytes(b"")
    _remove_quietly(probe)


def check_outputs_distinct(inputs: list, outputs: list, names: str = "the outputs", input_folders: list = ()) -> None:
    """Refuse an output path that is one of the input files ``inputs`` (writing it would replace
    an input: a checkpoint, a predictions file), lies inside one of ``input_folders`` (a split
    whose manifest or shard it would replace), or is named twice (the second write would replace
    the first); ``None``, ``""`` and ``-`` (stdout) outputs and inputs, and inputs that are no file,
    are skipped.  ``names``
    names the outputs in the message."""
    def resolved(p) -> Path | None:
        try:
            return Path(p).resolve()
        except (OSError, RuntimeError):
            return None

    def same(a, b) -> bool:
        return resolved(a) is not None and resolved(a) == resolved(b)

    files = [o for o in outputs if o and o != "-"]
    for i, out in enumerate(files):
        for inp in inputs:
            if inp and inp != "-" and Path(inp).is_file() and same(out, inp):  # (not a shipped model's name)
                raise UserError(f"output {out} is also an input ({inp}); choose another name")
        target = resolved(out)
        for folder in input_folders:
            root = resolved(folder) if folder else None
            if target is not None and root is not None and root in target.parents:
                raise UserError(f"output {out} lies inside the input folder {folder}; write it elsewhere")
        if any(same(out, other) for other in files[:i]):
            raise UserError(f"{names} name the same file {out}; choose two names")


def check_can_create(path: str | Path) -> None:
    """Before long work whose result goes to file ``path``: a :class:`WriteError` now if it
    could not be written (read-only filesystem, no permission, a parent that is a file, a
    folder at ``path``).  Creates nothing that stays (a probe file in the nearest existing
    parent, removed at once)."""
    path = Path(path)
    if path.is_dir():
        raise WriteError(f"cannot write {path}: is a directory", str(path), errno.EISDIR)
    _refuse_special_file(path)  # as atomic_path refuses it, but before the work
    parent = _existing_ancestor(path.parent)
    if not parent.is_dir():
        raise WriteError(f"cannot write {path}: {parent} is not a directory", str(path), errno.ENOTDIR)
    probe = parent / f".artdata-write-test-{os.getpid()}{TMP_SUFFIX}"
    try:
        probe.write_bytes(b"")
    except OSError as exc:
        err = write_error(path, exc)
        if err is None:
            raise
        raise err from None
    _remove_quietly(probe)


def check_free_space(path: str | Path, need_bytes: float, what: str) -> None:
    """A :class:`WriteError` if the filesystem of ``path`` has less than ``need_bytes`` free."""
    free = free_bytes(path)
    if free is not None and need_bytes > free:
        raise WriteError(f"{what} needs at least {format_bytes(need_bytes)} in {path}, which has "
                         f"{format_bytes(free)} free", str(path), errno.ENOSPC)


#: Linux cgroup v2 / v1 memory limit and usage of this process's container, if any.
_CGROUP_LIMITS = (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                  ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"))


def available_memory_bytes() -> int | None:
    """Memory this process can still allocate without swapping (MemAvailable, capped by a
    cgroup limit); None if unknown."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024  # kB
                    break
    except (OSError, ValueError):
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            avail = None
    for limit_file, usage_file in _CGROUP_LIMITS:
        try:
            text = Path(limit_file).read_text().strip()
        except OSError:
            continue
        if text.isdigit():  # "max": no limit
            try:
                used = int(Path(usage_file).read_text().strip())
            except (OSError, ValueError):
                used = 0
            left = max(int(text) - used, 0)
            avail = left if avail is None else min(avail, left)
        break
    return avail
