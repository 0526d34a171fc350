"""Executors: how shard tasks are run.  They wrap the pipeline's stages, never the reverse.

:func:`process_map` is the package's one local process pool (generation, verify and the
baselines use it): spawned workers that end with their parent, a bounded queue of lazily
produced tasks, and a one-line error, not a hang, when a worker dies.

An executor has one method, ``map_unordered(fn, tasks, progress=None)``, yielding
``fn(task)`` results in any order.  ``fn`` must be a picklable top-level function of one
argument returning ``(shard_index, record)``; in-process executors may pass a
``progress(n_images)`` callback as a keyword argument.

:class:`RayExecutor` runs one Ray task per shard on a Ray cluster (``pip install ray``);
:func:`get_executor` picks an executor by name (``artdata generate --executor``).
"""

from __future__ import annotations

import itertools
import logging
import multiprocessing as mp
import os
from pathlib import Path
from typing import Callable, Iterable, Iterator

from articulated_dataset.core.errors import UserError, option

log = logging.getLogger(__name__)


class SerialExecutor:
    """Run tasks one after another in this process (reports progress per object)."""

    def map_unordered(self, fn: Callable, tasks: Iterable, progress=None) -> Iterator:
        """``fn(task, progress=progress)`` for each task, one after another in this process."""
        for task in tasks:
            yield fn(task, progress=progress)


#: Linux ``prctl`` option: signal this process when its parent dies.
PR_SET_PDEATHSIG = 1
#: Seconds between a worker's checks that its parent (the generate command) is alive.
PARENT_POLL_S = 0.5
#: Tasks queued per worker beyond the one it runs (tasks are produced lazily: a split of a
#: billion shards never becomes a list).
QUEUED_TASKS_PER_WORKER = 2


def _die_with_parent(parent_pid: int) -> None:
    """Make this worker end when the process that started it ends, however it ends
    (SIGKILL included): the kernel's parent-death signal on Linux, and everywhere a thread
    that exits the worker once its parent has gone (the worker is re-parented)."""
    import signal
    import sys
    import threading
    import time

    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # no prctl: the thread below still ends the worker
            log.debug("prctl(PR_SET_PDEATHSIG) unavailable")
    if os.getppid() != parent_pid:  # the parent died before the signal was armed
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(PARENT_POLL_S)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="artdata-parent-watch", daemon=True).start()


def _worker_init(parent_pid: int, initializer: Callable | None = None, initargs: tuple = ()) -> None:
    # One llvmpipe rasteriser thread per worker: the pool provides the parallelism.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    _die_with_parent(parent_pid)
    if initializer is not None:
        initializer(*initargs)


#: The one-line error when a worker of :func:`process_map` dies.
WORKER_DIED = "a worker process died (killed or out of memory?)"


def process_map(fn: Callable, tasks: Iterable, workers: int, *, ordered: bool = False,
                initializer: Callable | None = None, initargs: tuple = (), died: str = WORKER_DIED) -> Iterator:
    """``fn(task)`` for every task in ``workers`` local processes, yielded as they finish (in
    the tasks' order if ``ordered``).

    Workers are spawned (GL contexts and HDF5 state never cross a fork), run
    ``initializer(*initargs)`` once, and end with the process that started them (killed
    included).  At most ``workers * (1 + QUEUED_TASKS_PER_WORKER)`` tasks are submitted at a
    time, so ``tasks`` may be a lazy iterable of any length.  concurrent.futures rather than
    multiprocessing.Pool: a worker that dies (killed, out of memory, a crash in the GL driver)
    breaks the pool, reported as the one-line :class:`UserError` ``died``, where Pool would
    replace the worker and wait for its lost task forever.
    """
    from collections import deque
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    if workers < 1:
        raise ValueError("workers must be >= 1")
    queue = iter(tasks)
    first = list(itertools.islice(queue, workers))
    if not first:
        return
    pool = ProcessPoolExecutor(max_workers=len(first), mp_context=mp.get_context("spawn"),
                               initializer=_worker_init, initargs=(os.getpid(), initializer, initargs))
    limit = len(first) * (1 + QUEUED_TASKS_PER_WORKER)

    def result(future):
        try:
            return future.result()
        except BrokenProcessPool:  # not the input's fault, but one line is all there is to say
            raise UserError(died) from None

    try:
        submitted = deque(pool.submit(fn, task) for task in first)
        while submitted:
            submitted.extend(pool.submit(fn, task) for task in itertools.islice(queue, limit - len(submitted)))
            if ordered:
                yield result(submitted.popleft())
                continue
            done, _ = wait(submitted, return_when=FIRST_COMPLETED)
            for future in done:
                submitted.remove(future)
                yield result(future)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


#: :func:`ordered_map` runs at least this many tasks (a split's shards) in one process per CPU by
#: default: a spawned worker costs about a second to start, so a small split reads faster in one.
PARALLEL_MIN_TASKS = 16


def ordered_map(fn: Callable, tasks: list, workers: int | None = None) -> Iterator:
    """``fn(task)`` for every task, in the tasks' order: in this process (``workers`` <= 1) or in
    ``workers`` spawned processes (:func:`process_map`); None: one per CPU when there are at least
    :data:`PARALLEL_MIN_TASKS` tasks, else this process.  How the model loaders read a split's
    shards (``fn`` a module-level function: workers import it)."""
    if workers is None:
        workers = (os.cpu_count() or 1) if len(tasks) >= PARALLEL_MIN_TASKS else 1
    workers = min(workers, len(tasks))
    if workers <= 1:
        return map(fn, tasks)
    return process_map(fn, tasks, workers, ordered=True)


class ProcessExecutor:
    """Run tasks in ``workers`` local processes (:func:`process_map`).

    Workers end with the process that started them (killed included), so a killed
    ``generate`` leaves no process writing its split.
    """

    def __init__(self, workers: int):
        if workers < 1:
            raise ValueError("workers must be >= 1")
        self.workers = workers

    def map_unordered(self, fn: Callable, tasks: Iterable, progress=None) -> Iterator:
        """``fn(task)`` for each task, yielded as the worker processes finish them; ``progress`` is called with each
        result's image count."""
        died = ("a generation worker process died (killed or out of memory?); completed shards are kept, "
                f"continue with {option('resume')}")
        for result in process_map(fn, tasks, self.workers, died=died):
            if progress is not None:
                progress(result[1]["n_images"])
            yield result


#: libgomp's busy-wait before an idle OpenMP worker thread sleeps (``GOMP_SPINCOUNT``, spins)
#: on a machine with a free CPU for every thread.  Measured on the 2-core machine
#: (``benchmarks/dense_inference.py``, microwave, batch 128): idle, 0 spins (passive) 416, 10,000
#: spins 712 images/s; with one busy process beside it 386 against 208; training steps 218
#: against 285 idle.  Larger counts (libgomp's default 300,000) gain nothing idle and collapse
#: to 9-27 images/s beside two busy processes.
IDLE_MACHINE_SPIN_COUNT = 10_000
#: The machine counts as idle when its other processes leave at least ``threads`` minus this
#: many CPUs free (a shell, an editor or the process's own start-up use a little).
FREE_CPU_TOLERANCE = 0.25
#: Seconds over which ``/proc/stat`` is sampled for the CPUs other processes keep busy.
BUSY_SAMPLE_S = 0.1
#: The OpenMP settings a user may set; where any is set, nothing is chosen for them.
OPENMP_WAIT_VARIABLES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def openmp_wait_settings(threads: int, busy_cpus: float | None, n_cpus: int) -> dict[str, str]:
    """How PyTorch's OpenMP threads should wait between parallel regions, as environment variables.

    Spinning threads answer the next region at once: the dense pipeline's many small operations
    run 1.7x faster on an idle machine.  Spinning threads also take CPU time that other processes
    need, so on a busy machine they wait passively (sleep at once).  The machine is idle when
    ``n_cpus - busy_cpus >= threads - FREE_CPU_TOLERANCE``, ``busy_cpus`` the CPUs' worth of work
    other processes do now (None, unknown: busy): then ``GOMP_SPINCOUNT`` =
    :data:`IDLE_MACHINE_SPIN_COUNT`, else ``OMP_WAIT_POLICY=PASSIVE``.
    """
    if busy_cpus is not None and n_cpus - busy_cpus >= threads - FREE_CPU_TOLERANCE:
        return {"GOMP_SPINCOUNT": str(IDLE_MACHINE_SPIN_COUNT)}
    return {"OMP_WAIT_POLICY": "PASSIVE"}


def _cpu_times() -> tuple[int, int] | None:
    """(idle, total) jiffies of all CPUs from ``/proc/stat``; None where it cannot be read."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu":
        return None
    ticks = [int(v) for v in fields[1:9]]  # user nice system idle iowait irq softirq steal
    return ticks[3] + ticks[4], sum(ticks)


def busy_cpus_now(sample_s: float = BUSY_SAMPLE_S) -> float | None:
    """The CPUs' worth of work the machine's processes do over the next ``sample_s`` seconds
    (``/proc/stat``; this process sleeps meanwhile), else the 1-minute load average; None where
    neither can be read."""
    import time

    first = _cpu_times()
    if first is not None:
        time.sleep(sample_s)
        second = _cpu_times()
        if second is not None and second[1] > first[1]:
            idle_share = (second[0] - first[0]) / (second[1] - first[1])
            return (os.cpu_count() or 1) * (1.0 - idle_share)
    try:
        return os.getloadavg()[0]
    except OSError:  # pragma: no cover - no load average on this platform
        return None


def configure_openmp_wait(threads: int | None = None) -> dict[str, str]:
    """Choose the OpenMP wait policy (:func:`openmp_wait_settings`) for ``threads`` (default: every
    CPU this process may use) and set it in the environment, before PyTorch starts its OpenMP
    runtime (which reads it once).  A user's own ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` is
    kept (returns {}); so is everything once torch is imported (logged)."""
    import sys

    if any(v in os.environ for v in OPENMP_WAIT_VARIABLES):
        return {}
    if "torch" in sys.modules:
        log.debug("torch is already imported: its OpenMP wait policy is left as it is")
        return {}
    if threads is None:
        threads = usable_cpus()
    chosen = openmp_wait_settings(threads, busy_cpus_now(), os.cpu_count() or 1)
    os.environ.update(chosen)
    log.debug("OpenMP wait for %d threads: %s", threads, chosen)
    return chosen


def usable_cpus() -> int:
    """Number of CPUs this process may run on (its affinity mask where the platform has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        return os.cpu_count() or 1


def local_executor(workers: int):
    """Serial for one worker, a process pool otherwise."""
    return SerialExecutor() if workers <= 1 else ProcessExecutor(workers)


# --------------------------------------------------------------------------------------
# Ray
# --------------------------------------------------------------------------------------

#: Times Ray re-runs a task whose worker process or node died (a shard is a pure function
#: of its config and index, so a re-run writes the same bytes).
DEFAULT_MAX_RETRIES = 3
#: CPUs reserved per task: one renderer (one llvmpipe thread) per task.
CPUS_PER_TASK = 1
#: Tasks in flight without --workers (Ray queues them until CPUs are free; a bound keeps a
#: split of millions of shards from being submitted at once).
DEFAULT_TASKS_IN_FLIGHT = 1024
#: How to install Ray, which ``--executor ray`` needs.
RAY_INSTALL_HELP = (f"{option('executor')} ray needs Ray: pip install 'articulated_dataset[ray]' "
                    "(or pip install 'ray>=2.9')")
#: Ray's command that starts a cluster's head node and prints its address.
RAY_HEAD_COMMAND = "ray start --head"
#: Seconds to wait for a TCP connection to a Ray cluster's address before ``ray.init`` (which
#: retries an address where nothing listens without end).
RAY_CONNECT_TIMEOUT_S = 10.0
#: HTTP/2's client connection preface and an empty SETTINGS frame (RFC 9113, 3.4 and 6.5): a
#: gRPC server (Ray's GCS, the Ray Client server) answers with a SETTINGS frame of its own.
HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"
HTTP2_EMPTY_SETTINGS = b"\x00\x00\x00\x04\x00\x00\x00\x00\x00"
#: An HTTP/2 frame header's length, the index of its type byte, and the SETTINGS type.
HTTP2_FRAME_HEADER_BYTES = 9
HTTP2_FRAME_TYPE_BYTE = 3
HTTP2_SETTINGS_FRAME = 0x04
#: Prefix of a Ray Client address (``ray://HOST:PORT``).
RAY_CLIENT_SCHEME = "ray://"


def _host_port(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of a Ray address ``[ray://]HOST:PORT`` (IPv6 hosts in brackets); None for
    ``auto``/``local`` or anything else Ray resolves itself."""
    rest = address[len(RAY_CLIENT_SCHEME):] if address.startswith(RAY_CLIENT_SCHEME) else address
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def check_reachable(address: str | None, timeout_s: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """Refuse (one line) a Ray address ``[ray://]HOST:PORT`` where no TCP connection opens within
    ``timeout_s``, or where what answers is not a gRPC server (a Ray head node's GCS and a Ray
    Client server both are): ``ray.init`` would retry the first forever and wait on the second
    without end.  The check sends HTTP/2's client preface with an empty SETTINGS frame and
    expects a frame of type SETTINGS back, as every HTTP/2 server sends first."""
    import socket

    target = _host_port(address) if address else None
    if target is None:
        return
    try:
        conn = socket.create_connection(target, timeout=timeout_s)
    except (OSError, ValueError) as exc:  # refused, unreachable, timed out, unknown host, port out of range
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc) or type(exc).__name__
        raise UserError(f"cannot connect to the Ray cluster at {address} (waited up to {timeout_s:g} s): {reason}") from None
    head = b""
    with conn:
        try:
            conn.sendall(HTTP2_PREFACE + HTTP2_EMPTY_SETTINGS)
            while len(head) < HTTP2_FRAME_HEADER_BYTES:
                chunk = conn.recv(HTTP2_FRAME_HEADER_BYTES - len(head))
                if not chunk:
                    break
                head += chunk
        except OSError:  # reset, or no answer within timeout_s: not a gRPC server
            pass
    if len(head) < HTTP2_FRAME_HEADER_BYTES or head[HTTP2_FRAME_TYPE_BYTE] != HTTP2_SETTINGS_FRAME:
        raise UserError(f"{address} answers, but not as a Ray cluster (no gRPC server there); is it the head node's "
                        f"address and port ({RAY_HEAD_COMMAND} prints it)?")


def _import_ray():
    try:
        import ray
    except ImportError:
        raise UserError(RAY_INSTALL_HELP) from None
    return ray


#: Driver environment variables passed on to Ray workers when set (GL backend, the
#: processed-URDF cache folder of articulated_dataset.generation.urdf_import).
FORWARDED_ENV = ("PYOPENGL_PLATFORM", "ARTDATA_CACHE_DIR")


def _worker_env() -> dict[str, str]:
    """Environment of Ray workers: one llvmpipe thread, the driver's GL backend."""
    env = {"LP_NUM_THREADS": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    env.update({k: os.environ[k] for k in FORWARDED_ENV if os.environ.get(k)})
    return env


def _ray_task(fn: Callable, task, driver_version: str, driver_mujoco: str | None = None):
    """Body of every Ray task: refuse a node whose package or MuJoCo release differs from the
    driver's (the manifest records the driver's MuJoCo as the one that rendered the split), then run."""
    from articulated_dataset import __version__
    from articulated_dataset.core.mujoco_support import installed_mujoco_version

    node_mujoco = installed_mujoco_version()
    if __version__ != driver_version or (driver_mujoco is not None and node_mujoco != driver_mujoco):
        import socket

        raise UserError(
            f"Ray node {socket.gethostname()} has articulated_dataset {__version__} and MuJoCo {node_mujoco}, "
            f"the driver {driver_version} and MuJoCo {driver_mujoco}; install the same versions on every node"
        )
    return fn(task)


def _is_shard_task(task) -> bool:
    """Pipeline shard tasks are ``(config, shard_index, split_dir)``."""
    return isinstance(task, tuple) and len(task) == 3 and isinstance(task[2], (str, Path))


def _absolute_task(task):
    """A shard task with an absolute output folder (Ray workers do not run in the driver's
    working directory)."""
    if _is_shard_task(task):
        return (task[0], task[1], Path(task[2]).absolute())
    return task


def _check_visible(task, result) -> None:
    """For pipeline shard tasks: the driver must see the shard a worker wrote, i.e. the
    output folder is on a filesystem shared by every node."""
    if not _is_shard_task(task):
        return
    record = result[1] if isinstance(result, tuple) and len(result) == 2 else None
    if not isinstance(record, dict) or "file" not in record:
        return
    path = Path(task[2]) / record["file"]
    if not path.is_file() or path.stat().st_size != record.get("bytes"):
        raise UserError(
            f"shard {path} written by a Ray worker is not visible to the driver: {option('out_root')} must be a shared "
            "filesystem mounted at the same path on every node"
        )


class RayExecutor:
    """One Ray task per shard on a Ray cluster; results are yielded as tasks finish.

    ``address``: ``None`` (``RAY_ADDRESS`` if set, else start a local Ray instance),
    ``"auto"`` (the cluster this machine belongs to) or ``"HOST:PORT"`` /
    ``"ray://HOST:PORT"``.  If Ray is already initialised in this process that instance is
    used.  ``workers``: at most this many tasks in flight (None:
    :data:`DEFAULT_TASKS_IN_FLIGHT`; Ray schedules them on free CPUs); for a local instance also its CPU count.
    ``max_retries``: re-runs of a task whose worker died (an exception raised by the task
    itself is not retried: generation is deterministic, it would fail again).
    """

    #: Shards are built in the memory of the cluster's nodes, not this machine's.
    remote = True

    def __init__(self, address: str | None = None, workers: int | None = None, max_retries: int = DEFAULT_MAX_RETRIES):
        if workers is not None and workers < 1:
            raise UserError(f"{option('workers')} must be positive, got {workers}")
        if max_retries < 0:
            raise ValueError("max_retries must be >= 0")
        self.address = address
        self.workers = workers
        self.max_retries = max_retries

    def _connect(self, ray) -> bool:
        """Initialise Ray unless it already is; True if this call started it."""
        if ray.is_initialized():
            return False
        kwargs = {"include_dashboard": False, "log_to_driver": False, "runtime_env": {"env_vars": _worker_env()}}
        if self.address is None and self.workers is not None and not os.environ.get("RAY_ADDRESS"):
            kwargs["num_cpus"] = self.workers
        check_reachable(self.address or os.environ.get("RAY_ADDRESS"))
        try:
            ray.init(address=self.address, **kwargs)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise UserError(f"cannot connect to the Ray cluster at {self.address or 'RAY_ADDRESS/local'}: {first}") from None
        return True

    def map_unordered(self, fn: Callable, tasks: Iterable, progress=None) -> Iterator:
        """``fn(task)`` for each task as one Ray task, yielded as they finish, with at most ``workers`` (or
        :data:`DEFAULT_TASKS_IN_FLIGHT`) in flight; ``progress`` is called with each result's image count. Pending
        tasks are cancelled on an error or interruption, and a Ray instance started here is shut down."""
        from articulated_dataset import __version__
        from articulated_dataset.core.mujoco_support import installed_mujoco_version

        queue: Iterator = (_absolute_task(t) for t in tasks)
        first = next(queue, None)
        if first is None:
            return
        queue = itertools.chain([first], queue)
        ray = _import_ray()
        started = self._connect(ray)
        remote = ray.remote(_ray_task).options(
            num_cpus=CPUS_PER_TASK, max_retries=self.max_retries, retry_exceptions=False,
            runtime_env={"env_vars": _worker_env()},
        )
        limit = self.workers or DEFAULT_TASKS_IN_FLIGHT
        pending: dict = {}

        def submit() -> None:
            for task in queue:
                pending[remote.remote(fn, task, __version__, installed_mujoco_version())] = task
                if len(pending) >= limit:
                    return

        try:
            submit()
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                ref = done[0]
                task = pending.pop(ref)
                result = self._get(ray, ref)
                _check_visible(task, result)
                submit()
                if progress is not None:
                    progress(result[1]["n_images"])
                yield result
        finally:
            for ref in pending:  # interrupted or failed: do not leave tasks writing shards
                ray.cancel(ref, force=True)
            if started:
                ray.shutdown()

    @staticmethod
    def _get(ray, ref):
        """``ray.get``, re-raising a task's UserError as itself (one line, no Ray traceback)."""
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            cause = getattr(exc, "cause", None)
            if isinstance(cause, UserError):
                raise UserError(str(cause)) from None
            if isinstance(cause, ModuleNotFoundError):
                raise UserError(f"a Ray node cannot import {cause.name!r}: install articulated_dataset on every node") from None
            raise


#: Executors by ``--executor`` name: factory(workers, address).
EXECUTORS: dict[str, Callable] = {
    "local": lambda workers, address: local_executor(workers or os.cpu_count() or 1),
    "ray": lambda workers, address: RayExecutor(address=address, workers=workers),
}


def get_executor(name: str = "local", workers: int | None = None, address: str | None = None):
    """The executor called ``name`` (see :data:`EXECUTORS`).

    ``workers``: local processes (default: all cores) or, for Ray, the most tasks in
    flight.  ``address`` (Ray only): ``auto`` or ``HOST:PORT``.
    """
    if name not in EXECUTORS:
        raise UserError(f"unknown executor {name!r}; choose from: {', '.join(EXECUTORS)}")
    if workers is not None and workers < 1:
        raise UserError(f"{option('workers')} must be positive, got {workers}")
    if address is not None and name != "ray":
        raise UserError(f"{option('address')} is for {option('executor')} ray")
    return EXECUTORS[name](workers, address)


# --------------------------------------------------------------------------------------
# The C allocator
# --------------------------------------------------------------------------------------

#: glibc ``mallopt`` parameters (``malloc.h``).
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
#: Free memory at the top of the heap that glibc keeps instead of returning it to the system
#: (bytes; an ``int`` for ``mallopt``).
KEEP_FREE_HEAP_BYTES = 1 << 30
#: Settings of the C allocator a user may make; where any is set, :func:`configure_allocator`
#: changes nothing (``LD_PRELOAD``: another allocator such as jemalloc or tcmalloc).
ALLOCATOR_VARIABLES = ("MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_",
                       "GLIBC_TUNABLES", "LD_PRELOAD")


def configure_allocator() -> bool:
    """Make glibc's ``malloc`` keep freed memory for the next allocation in this process:
    ``mallopt(M_MMAP_MAX, 0)`` (large blocks from the heap, not from fresh ``mmap`` pages) and
    ``mallopt(M_TRIM_THRESHOLD, KEEP_FREE_HEAP_BYTES)``.

    By default every block above 32 MB is mapped fresh and unmapped when freed, so each of the
    dense pipeline's batch-sized tensors (the network input of 128 images is 95 MB) costs its
    pages' faults and zeroing every time: 40-45 ms per such tensor on one core of the 2-core
    machine, 20% of the batched pipeline's time (``benchmarks/dense_inference.py``: cabinet
    305-327 against 399-411 images/s).  The cost: the process keeps its peak heap until it ends.
    For commands and worker processes, never called by library functions.  Returns whether it
    was set: not where a user set any of :data:`ALLOCATOR_VARIABLES`, nor without glibc."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux") or any(v in os.environ for v in ALLOCATOR_VARIABLES):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # pragma: no cover - no mallopt (not glibc)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(M_MMAP_MAX, 0) == 1 and mallopt(M_TRIM_THRESHOLD, KEEP_FREE_HEAP_BYTES) == 1
    log.debug("malloc keeps freed memory: %s", ok)
    return ok
