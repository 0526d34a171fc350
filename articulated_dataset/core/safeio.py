"""Safe writes: every file is written to a temporary sibling, fsync'ed and renamed into place.

A reader (or a later run) sees the old file or the new one, never a mix, and a failure
never destroys what was there.  Operating-system refusals that are the user's to fix (disk
full, quota, read-only filesystem, no permission, a missing folder) become one
:class:`WriteError` naming the file and the free space left on its filesystem; the
temporary file is removed.  Any other exception propagates unchanged (after the cleanup).

Use :func:`atomic_write_bytes` / :func:`atomic_write_text` for data in memory,
:func:`atomic_file` for writers that take a file object (torch.save, matplotlib, PIL),
:func:`atomic_path` for writers that need a file name, and :func:`atomic_write_h5` for HDF5
files: the file is built in memory and written with one ordinary write, so a full disk can
never leave the HDF5 library in a broken state.

Temporary files are created exclusively (``O_CREAT | O_EXCL | O_NOFOLLOW``) under a name
nobody can predict, ``.NAME.<random hex>.partial`` beside ``NAME``: a symbolic link planted
in an output folder, at any name, is never followed, truncated or renamed into place (the
final rename replaces ``NAME`` itself, never what a link there points to).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import secrets
import stat
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

from articulated_dataset.core.errors import UserError

log = logging.getLogger(__name__)

#: Suffix of temporary siblings (``.name.<random hex>.partial``); a file with it is never valid data.
TMP_SUFFIX = ".partial"
#: Random bytes in a temporary file's name (written as hex): unguessable, so no link can wait there.
TMP_TOKEN_BYTES = 8
#: A temporary file's name: the final name (its first bytes), a random token, the suffix.
TMP_NAME = re.compile(r"\.(?P<name>.+)\.[0-9a-f]{%d}%s" % (2 * TMP_TOKEN_BYTES, re.escape(TMP_SUFFIX)), re.DOTALL)
#: Bytes of the final name kept in its temporary's name, so that the temporary's name stays
#: within every filesystem's name limit (NAME_MAX: 255 bytes on most, 143 on eCryptfs).
TMP_NAME_KEEP_BYTES = 100
#: Fresh names tried before giving up (one clash in 2**64 names is already unheard of).
TMP_NAME_ATTEMPTS = 16
#: Opening a new temporary file: created here and now, never an existing file or a link
#: (``O_EXCL`` fails on any existing name, a dangling link included; ``O_NOFOLLOW`` too).
_CREATE_FLAGS = (os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
                 | getattr(os, "O_BINARY", 0))
#: Permissions of a new file before the umask, as ``open(path, "w")`` gives (``mkstemp``'s 0600
#: would hide outputs written into a shared folder from the group that reads them).
NEW_FILE_MODE = 0o666
#: Name and path length limits where the filesystem does not say (Linux's NAME_MAX and PATH_MAX).
DEFAULT_NAME_MAX = 255
DEFAULT_PATH_MAX = 4096
#: Characters of an over-long path quoted in its error message.
LONG_PATH_QUOTE_CHARS = 120

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
#: Name of the HDF5 file built in :func:`atomic_write_h5`'s private scratch folder.
H5_SCRATCH_NAME = "file.h5"
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
        return (type(self), (self.message, self.path, self.errno))

    @property
    def disk_full(self) -> bool:
        """True when the error's errno means a full filesystem or an exceeded quota."""
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
    """``path`` or its nearest parent that exists (a name too long to look up counts as missing)."""
    path = Path(os.path.abspath(path))
    while path != path.parent:
        try:
            os.stat(path)
            return path
        except (OSError, ValueError):  # missing, a dangling link, ENAMETOOLONG, a NUL byte
            path = path.parent
    return path


def _pathconf(path: Path, name: str, default: int) -> int:
    try:
        value = os.pathconf(path, name)
    except (OSError, ValueError, AttributeError):
        return default
    return value if value and value > 0 else default


def check_name_length(path: str | Path) -> None:
    """A :class:`WriteError` if ``path`` can be no file's name: one of its components is longer
    than its filesystem allows (NAME_MAX, 255 bytes on most), or the whole path (made absolute)
    is longer than PATH_MAX.  Checked before anything is looked up, created or computed, since
    every later step would fail with ``File name too long``."""
    text = os.fsencode(os.path.abspath(path))
    base = _existing_ancestor(Path(os.fsdecode(text)))
    name_max = _pathconf(base, "PC_NAME_MAX", DEFAULT_NAME_MAX)
    path_max = _pathconf(base, "PC_PATH_MAX", DEFAULT_PATH_MAX)
    shown = str(path)
    if len(shown) > LONG_PATH_QUOTE_CHARS:
        shown = shown[:LONG_PATH_QUOTE_CHARS] + "..."
    longest = max((len(part) for part in text.split(b"/")), default=0)
    if longest > name_max:
        raise WriteError(f"cannot write {shown}: file name too long (a name of {longest} bytes; this filesystem "
                         f"allows {name_max})", str(path), errno.ENAMETOOLONG)
    if len(text) >= path_max:
        raise WriteError(f"cannot write {shown}: path too long ({len(text)} bytes; at most {path_max - 1})",
                         str(path), errno.ENAMETOOLONG)


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
    """``'1.2 GB free'`` for the filesystem of ``path``, or ``'free space unknown'``."""
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


def temporary_name(name: str) -> str:
    """A fresh temporary file name for final name ``name``: ``.name.<random hex>.partial``
    (``name`` cut to :data:`TMP_NAME_KEEP_BYTES`)."""
    kept = os.fsdecode(os.fsencode(name)[:TMP_NAME_KEEP_BYTES])
    return f".{kept}.{secrets.token_hex(TMP_TOKEN_BYTES)}{TMP_SUFFIX}"


def temporary_target(name: str) -> str | None:
    """The final name a temporary file named ``name`` was written for (``.NAME.<hex>.partial``,
    or ``NAME.partial`` as earlier versions named them); None if ``name`` is no temporary's."""
    m = TMP_NAME.fullmatch(name)
    if m is not None:
        return m.group("name")
    if name.endswith(TMP_SUFFIX) and len(name) > len(TMP_SUFFIX):
        return name[: -len(TMP_SUFFIX)]
    return None


def create_temporary(path: str | Path) -> tuple[int, Path]:
    """Create an empty temporary file beside ``path`` (``.NAME.<random hex>.partial``) and
    return ``(fd, its path)``, ``fd`` open for writing.  The name is new and created
    exclusively, so the file is this process's own: never an existing file, never a link.
    Raises :class:`OSError` (translate it with :func:`write_error`)."""
    path = Path(path)
    for _ in range(TMP_NAME_ATTEMPTS):
        tmp = path.with_name(temporary_name(path.name))
        try:
            return os.open(tmp, _CREATE_FLAGS, NEW_FILE_MODE), tmp
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no unused temporary file name", str(path))


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
    check_name_length(path)
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
    try:
        mode = os.stat(path).st_mode  # follows a link: /dev/stdout -> /proc/self/fd/1 -> a pipe
    except (OSError, ValueError):
        return
    if not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):
        raise WriteError(f"cannot write {path}: not a regular file (a device, FIFO or socket would be replaced); "
                         "use '-' for standard output where offered", str(path), errno.EINVAL)


@contextlib.contextmanager
def _replacing(path: Path) -> Iterator[tuple[BinaryIO, Path]]:
    """Create a temporary file beside ``path`` and yield ``(file object on it, its path)``; on
    success the file is fsync'ed and renamed to ``path``, on any failure removed (``path``
    untouched) and an :class:`OSError` the user can fix raised as a :class:`WriteError`."""
    check_name_length(path)
    _refuse_special_file(path)
    tmp = None
    try:
        fd, tmp = create_temporary(path)
        with os.fdopen(fd, "wb") as f:
            yield f, tmp
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)  # replaces the entry ``path`` (a link there included), never a link's target
    except BaseException as exc:
        if tmp is not None:
            _remove_quietly(tmp)  # first, so that the message gives the free space without it
        err = write_error(path, exc) if isinstance(exc, OSError) else None
        if err is None:
            raise
        raise err from None
    fsync_dir(path.parent)


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[BinaryIO]:
    """Yield a binary file object to write ``path``'s new content to (a new temporary file
    beside it); on success it is fsync'ed and renamed to ``path``.  On any failure the
    temporary file is removed and ``path`` is untouched."""
    with _replacing(Path(path)) as (f, _tmp):
        yield f


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield the path of a new, empty temporary file beside ``path`` (created exclusively under
    an unpredictable name) for writers that need a name; on success it is fsync'ed and renamed
    to ``path``.  On any failure the temporary file is removed and ``path`` is untouched.
    Prefer :func:`atomic_file` where the writer takes a file object."""
    path = Path(path)
    with _replacing(path) as (_f, tmp):
        yield tmp
        # The writer wrote by name: make sure the name still is this file, not a link put there
        # meanwhile (O_NOFOLLOW: ELOOP, a WriteError), and sync what it wrote.
        fd = os.open(tmp, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (new temporary sibling + fsync + rename)."""
    with atomic_file(path) as f:
        f.write(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_h5(path: str | Path, build: Callable, **file_kwargs) -> None:
    """Build an HDF5 file with ``build(h5py.File)`` and write it atomically to ``path``.

    HDF5's core driver builds the file in memory and, when it is closed, writes it in one piece
    to a scratch file in a private folder of the system's temporary directory (made by
    ``tempfile.mkdtemp``, mode 0700: nobody else can plant a link there); those bytes, the same
    as a file written directly with the same ``file_kwargs`` (shards stay byte-identical), are
    then written to ``path`` with :func:`atomic_write_bytes`.  A full disk or an unwritable
    folder at ``path`` therefore fails one ordinary write, a :class:`WriteError` with the
    operating system's reason, instead of failing inside HDF5 (whose errors carry no errno, and
    whose metadata cache a full disk left in a broken state that crashed the process).
    """
    import shutil
    import tempfile

    import h5py

    path = Path(path)
    check_name_length(path)
    scratch = tempfile.mkdtemp(prefix="artdata-h5-")
    try:
        built = os.path.join(scratch, H5_SCRATCH_NAME)
        f = h5py.File(built, "w", driver="core", backing_store=True, **file_kwargs)
        try:
            build(f)
        finally:
            try:
                f.close()
            except OSError as exc:  # the scratch write failed: HDF5 says why, without an errno
                raise WriteError(f"cannot write {path}: building it in the temporary folder {scratch} failed "
                                 f"({free_space_text(scratch)} there; set TMPDIR to a folder with space): {exc}",
                                 str(path)) from None
        with open(built, "rb") as fh:
            image = fh.read()
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    atomic_write_bytes(path, image)


def _probe_create(folder: Path, path: Path | None = None) -> None:
    """Create and remove a new temporary file in existing ``folder``; a :class:`WriteError`
    naming ``path`` (default: ``folder``) if it cannot be created."""
    target = folder if path is None else path
    try:
        fd, probe = create_temporary(folder / ".artdata-write-test")
    except OSError as exc:
        err = write_error(target, exc)
        if err is None:
            raise
        raise err from None
    os.close(fd)
    _remove_quietly(probe)


def check_writable_dir(path: str | Path) -> None:
    """Raise a :class:`WriteError` unless a file can be created in existing folder ``path``."""
    check_name_length(path)
    _probe_create(Path(path))


def check_outputs_distinct(inputs: list, outputs: list, names: str = "the outputs",
                           input_folders: list | tuple = ()) -> None:
    """Refuse an output path that is one of the input files ``inputs`` (writing it would replace
    an input: a checkpoint, a predictions file), lies inside one of ``input_folders`` (a split
    whose manifest or shard it would replace), or is named twice (the second write would replace
    the first); ``None``, ``""`` and ``-`` (stdout) outputs and inputs, and inputs that are no file,
    are skipped.  ``names``
    names the outputs in the message.  An output too long to be a file name is refused first
    (:func:`check_name_length`)."""
    for out in outputs:
        if out and out != "-":
            check_name_length(out)

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
    check_name_length(path)
    if path.is_dir():
        raise WriteError(f"cannot write {path}: is a directory", str(path), errno.EISDIR)
    _refuse_special_file(path)  # as atomic_path refuses it, but before the work
    parent = _existing_ancestor(path.parent)
    if not parent.is_dir():
        raise WriteError(f"cannot write {path}: {parent} is not a directory", str(path), errno.ENOTDIR)
    _probe_create(parent, path)


def check_free_space(path: str | Path, need_bytes: float, what: str) -> None:
    """A :class:`WriteError` if ``path`` is too long to be a name (:func:`check_name_length`) or
    its filesystem has less than ``need_bytes`` free."""
    check_name_length(path)
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


def check_memory(need_bytes: float, what: str) -> None:
    """Raise a :class:`UserError` naming ``what`` if ``need_bytes`` exceeds the memory this
    process can still allocate (unknown availability: no check).  Call it before allocating
    anything whose size comes from the user (image sizes, block sizes, counts)."""
    available = available_memory_bytes()
    if available is not None and need_bytes > available:
        raise UserError(f"{what} needs about {format_bytes(need_bytes)} of memory; this machine has "
                        f"{format_bytes(available)} available")
