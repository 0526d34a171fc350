"""JAX input pipeline over the shards (``pip install ".[jax]"``: jax, jaxlib, grain).

* :class:`ShardDataSource`: a ShardReader that satisfies grain's ``RandomAccessDataSource``
  protocol (``__len__``, ``__getitem__``, a checkpoint-stable ``__repr__``, and the batched
  ``_getitems`` that grain's batch push-down calls), for users who build their own grain
  pipeline: ``grain.MapDataset.source(ShardDataSource(path)).shuffle(seed=0).batch(128)``.
* :class:`JaxLoader`: the recommended loader.  It yields dicts of numpy arrays (ready for
  :func:`device_put`) following :func:`~articulated_dataset.training.loaders.epoch.plan_epoch`, the same
  shuffling, sharding and batches as the PyTorch loaders (a process is one part:
  ``process_index`` of ``process_count``, defaults from ``jax.process_index()`` /
  ``jax.process_count()``; every process gets the same number of batches).  With
  ``num_workers > 0`` batches are read in grain worker processes
  (``MapDataset.to_iter_dataset().mp_prefetch``), arrive through shared memory and the workers
  stay alive from one epoch to the next (``close()`` stops them); each worker prepares at most
  ``prefetch_batches`` batches ahead.

Layout: ``depth`` is channels-last, ``(B, H, W, 1)`` float32 m (the NHWC layout of
``flax.linen.Conv``); ``mask`` ``(B, H, W)`` uint8; ``K`` float32.  By default the string field
``class`` is left out (``jax.device_put`` takes numbers only); ``class_index`` gives the class
as an integer.  :func:`device_put` keeps 64-bit integer fields (``sample_id``, ``index``, ...) on
the host unless JAX runs with 64-bit types (``jax_enable_x64``): JAX would otherwise truncate
them to 32 bits, and predictions are matched by ``sample_id``.  Neither jax nor grain is
imported until needed.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.training.loaders.batch import BatchProcessor, load_batch
from articulated_dataset.training.loaders.epoch import DEFAULT_BLOCK_SIZE, n_batches, part_bounds, plan_epoch
from articulated_dataset.training.loaders.reader import (
    JAX_INSTALL,
    NUMERIC_FIELDS,
    OPTIONAL_IMAGE_FIELDS,
    ShardReader,
    require,
)

#: Batches each grain worker prepares ahead.
DEFAULT_PREFETCH_BATCHES = 2
#: Reader threads in each grain worker (0: the worker reads its batches itself).
WORKER_READ_THREADS = 0
#: Alignment of each field inside a worker's shared-memory batch block (a cache line).
SHARED_ALIGN_BYTES = 64
#: Key of the shared block in the elements grain workers send.
PACKED_KEY = "__packed_block__"
#: Length of the endless batch sequence handed to grain (never reached: 2**62 batches).
ENDLESS_LENGTH = 2**62
#: Epoch plans a worker keeps (it only moves forward).
PLAN_CACHE_EPOCHS = 4
#: Consecutive epochs without a batch for this process before the stream gives up.
MAX_EMPTY_EPOCHS = 64
#: Axis of the channel that the JAX loader adds to ``depth`` (channels-last: (B, H, W, 1)).
DEPTH_CHANNEL_AXIS = -1


class ShardDataSource(ShardReader):
    """grain ``RandomAccessDataSource`` over split folders: record ``i`` is sample ``i`` of
    :class:`ShardReader` (a dict of numpy arrays)."""

    def _getitems(self, indices: Sequence[int]) -> list[dict]:
        batch = self.get_batch(indices)  # get_batch refuses non-integer indices
        return [{k: v[i] for k, v in batch.items()} for i in range(len(indices))]

    def __repr__(self) -> str:  # stable across processes: grain checkpoints compare it
        return f"ShardDataSource(split_dirs={[str(d) for d in self.split_dirs]!r}, fields={list(self.fields)!r})"


class _EpochStream:
    """The batches of consecutive epochs from ``start_epoch`` on, as one endless sequence.

    grain's worker processes are spawned (seconds each); building the pipeline once over this
    sequence keeps them alive from one epoch to the next.  Element ``k`` is found by walking the
    epochs' plan lengths (each plan is recomputed deterministically where it is needed).
    """

    def __init__(self, reader: ShardReader, processor: BatchProcessor, plan_kw: dict, start_epoch: int,
                 packed: bool = False):
        self.reader, self.processor, self.plan_kw, self.start_epoch = reader, processor, plan_kw, start_epoch
        self.packed = packed  # in grain workers: batches in one shared-memory block (see _PackedAlloc)
        self._cache: dict[int, list] = {}
        self._cursor = (start_epoch, 0)  # (epoch, number of the epoch's first element)

    def __len__(self) -> int:
        return ENDLESS_LENGTH

    def plan(self, epoch: int) -> list[np.ndarray]:
        plan = self._cache.get(epoch)
        if plan is None:
            plan = plan_epoch(self.reader.shard_sizes, epoch=epoch, **self.plan_kw)
            if len(self._cache) >= PLAN_CACHE_EPOCHS:
                self._cache.pop(min(self._cache))
            self._cache[epoch] = plan
        return plan

    def locate(self, k: int) -> tuple[int, int]:
        """(epoch, batch number) of element ``k``."""
        epoch, first = self._cursor if k >= self._cursor[1] else (self.start_epoch, 0)
        empty = 0
        while True:
            n = len(self.plan(epoch))
            if k < first + n:
                self._cursor = (epoch, first)
                return epoch, k - first
            empty = empty + 1 if n == 0 else 0
            if empty > MAX_EMPTY_EPOCHS:
                raise IndexError(f"no batches for this process in {MAX_EMPTY_EPOCHS} consecutive epochs")
            epoch, first = epoch + 1, first + n

    def __getitem__(self, k: int) -> dict:
        epoch, b = self.locate(int(k))
        if not self.packed:
            return load_batch(self.reader, self.processor, self.plan(epoch)[b], epoch)
        alloc = _PackedAlloc()
        return alloc.pack(load_batch(self.reader, self.processor, self.plan(epoch)[b], epoch, alloc=alloc))


class _PackedAlloc:
    """Allocator for :meth:`ShardReader.get_batch` in grain workers: every field of a batch in ONE
    grain ``SharedMemoryArray``.  grain hands a SharedMemoryArray to the main process by name
    without copying (other arrays are copied into one shared segment each), so the decoded batch
    crosses the process boundary with one segment instead of a copy per field."""

    def __init__(self) -> None:
        self.block: Any = None  # the batch's grain SharedMemoryArray
        self.views: dict[int, tuple[np.ndarray, str, int]] = {}

    def __call__(self, specs: dict) -> dict:
        from grain.multiprocessing import SharedMemoryArray

        offsets, total = {}, 0
        for name, (shape, dtype) in specs.items():
            total = -(-total // SHARED_ALIGN_BYTES) * SHARED_ALIGN_BYTES
            offsets[name] = total
            total += int(np.prod(shape)) * np.dtype(dtype).itemsize
        self.block = SharedMemoryArray((max(total, 1),), np.uint8)
        out = {}
        for name, (shape, dtype) in specs.items():
            dtype = np.dtype(dtype)
            nbytes = int(np.prod(shape)) * dtype.itemsize
            view = np.asarray(self.block[offsets[name] : offsets[name] + nbytes]).view(dtype).reshape(shape)
            self.views[id(view)] = (view, name, offsets[name])
            out[name] = view
        return out

    def pack(self, batch: dict) -> dict:
        """The element grain transports: the block, where each field lies in it, other arrays."""
        layout, extra = [], {}
        for k, v in batch.items():
            hit = self.views.get(id(v))
            if hit is not None and hit[0] is v:
                layout.append((k, hit[2], tuple(v.shape), v.dtype.str))
            else:
                extra[k] = v
        return {PACKED_KEY: self.block, "layout": tuple(layout), "extra": extra, "keys": tuple(batch)}


def unpack(element: dict) -> dict:
    """Inverse of :meth:`_PackedAlloc.pack` in the main process (views of the shared block,
    which is unlinked when the last view is dropped)."""
    if PACKED_KEY not in element:
        return {k: np.asarray(v) for k, v in element.items()}
    block = element[PACKED_KEY]
    out = {k: np.asarray(v) for k, v in element["extra"].items()}
    for name, offset, shape, dtype in element["layout"]:
        dtype = np.dtype(dtype)
        nbytes = int(np.prod(shape)) * dtype.itemsize
        out[name] = np.asarray(block[offset : offset + nbytes]).view(dtype).reshape(shape)
    return {k: out[k] for k in element["keys"]}


def _absl_flags_ready() -> None:
    """grain's worker processes read absl flags; a program that never parsed them (anything but an
    ``absl.app`` main) would fail with UnparsedFlagAccessError, so mark them parsed (defaults kept)."""
    flags = require("absl.flags", "JaxLoader(num_workers > 0)", JAX_INSTALL)

    if not flags.FLAGS.is_parsed():
        flags.FLAGS.mark_as_parsed()


def _process_defaults(process_index: int | None, process_count: int | None) -> tuple[int, int]:
    if process_index is None or process_count is None:
        try:
            import jax
        except ModuleNotFoundError:  # jax missing: numpy batches still work on one process
            jax = None  # type: ignore[assignment]  # the module, or None where it is missing
        process_index = (jax.process_index() if jax else 0) if process_index is None else process_index
        process_count = (jax.process_count() if jax else 1) if process_count is None else process_count
    if process_count <= 0 or not 0 <= process_index < process_count:
        raise UserError(f"process index {process_index} is not in [0, process_count = {process_count})")
    return int(process_index), int(process_count)


class JaxLoader:
    """Batches of numpy arrays for one JAX process; ``set_epoch(epoch)`` before each epoch
    (without it, each pass runs the next epoch; the first pass runs epoch 0).

    ``fields`` default: every numeric field (:data:`~articulated_dataset.training.loaders.reader.NUMERIC_FIELDS`),
    and ``rgb`` when every split stores colour images.
    Every batch holds ``index`` (global sample indices) and, with ``target``, ``target``.
    ``remainder`` as in :func:`~articulated_dataset.training.loaders.epoch.plan_epoch` (default ``"pad"``:
    every process gets the same number of batches).  ``len(loader)``: batches per epoch.
    """

    def __init__(self, source, batch_size: int, *, fields: Sequence[str] | None = None, shuffle: bool = True,
                 seed: int = 0, process_index: int | None = None, process_count: int | None = None,
                 block_size: int = DEFAULT_BLOCK_SIZE, drop_last: bool = False, remainder: str = "pad",
                 target=None, norm=None, transform=None, num_workers: int = 0,
                 prefetch_batches: int = DEFAULT_PREFETCH_BATCHES):
        if fields is None:  # every numeric field, rgb where every split has it
            fields = NUMERIC_FIELDS + tuple(f for f in ShardReader(source.split_dirs if isinstance(source, ShardReader) else source).fields
                                            if f in OPTIONAL_IMAGE_FIELDS)
        if isinstance(source, ShardReader) and tuple(fields) == source.fields:
            self.reader = source
        else:
            self.reader = ShardReader(source.split_dirs if isinstance(source, ShardReader) else source, fields=fields)
        self.processor = BatchProcessor(self.reader.fields, transform=transform, target=target, norm=norm, seed=seed)
        self.process_index, self.process_count = _process_defaults(process_index, process_count)
        if num_workers < 0:
            raise UserError(f"num_workers must be >= 0, got {num_workers}")
        self.num_workers, self.prefetch_batches = int(num_workers), max(1, int(prefetch_batches))
        if self.num_workers > 0:  # one clear line now, not a ModuleNotFoundError in the first epoch
            require("grain", f"JaxLoader(num_workers={self.num_workers})", JAX_INSTALL + "; or num_workers=0")
        self.kw: dict[str, Any] = dict(batch_size=batch_size, seed=seed, shuffle=shuffle, block_size=block_size,
                                       drop_last=drop_last, remainder=remainder)
        self.epoch = 0
        self._epoch_given, self._passes = False, 0
        self._it: Any = None  # grain iterator of the worker processes, kept across epochs
        self._next_epoch: int | None = None
        self.batches()  # validate the options now

    def set_epoch(self, epoch: int) -> None:
        """Run epoch ``epoch`` (>= 0) on the next pass; a negative epoch is the user's mistake."""
        if int(epoch) < 0:
            raise UserError(f"epoch must be >= 0, got {epoch}")
        self.epoch = int(epoch)
        self._epoch_given = True

    def batches(self) -> list[np.ndarray]:
        """This process's batches (index arrays) in the current epoch."""
        return plan_epoch(self.reader.shard_sizes, epoch=self.epoch, part_index=self.process_index,
                          part_count=self.process_count, **self.kw)

    def __len__(self) -> int:
        a, b = part_bounds(len(self.reader), self.process_count, self.process_index, self.kw["remainder"])
        return n_batches(b - a, int(self.kw["batch_size"]), self.kw["drop_last"])

    def _plan_kw(self) -> dict:
        return dict(part_index=self.process_index, part_count=self.process_count, **self.kw)

    def __iter__(self):
        if self._passes and not self._epoch_given:
            self.epoch += 1
        self._epoch_given = False
        self._passes += 1
        return self._iter_epoch()

    def _iter_epoch(self):
        n = len(self.batches())
        if self.num_workers == 0:
            stream = _EpochStream(self.reader, self.processor, self._plan_kw(), self.epoch)
            for b in range(n):
                yield _channels_last(stream[b])
            return
        if n == 0:
            return
        if self._it is None or self._next_epoch != self.epoch:
            self.close()
            self._it = self._start_workers()
        finished = False
        try:
            for _ in range(n):
                yield _channels_last(unpack(next(self._it)))
            finished = True
        finally:
            if finished:
                self._next_epoch = self.epoch + 1
            else:  # abandoned mid-epoch: the workers are ahead of the next epoch's start
                self.close()

    def _start_workers(self):
        import grain

        _absl_flags_ready()
        stream = _EpochStream(self.reader, self.processor, self._plan_kw(), self.epoch, packed=True)
        # each worker reads its batches in turn (no reader threads: h5py and the GIL serialise them anyway), and
        # prepares at most prefetch_batches ahead: grain's default read-ahead (500 elements, 16 threads) filled
        # /dev/shm with hundreds of batch blocks per worker, left behind at close
        read = grain.ReadOptions(num_threads=WORKER_READ_THREADS, prefetch_buffer_size=self.prefetch_batches)
        ds = grain.MapDataset.source(stream).to_iter_dataset(read)
        ds = ds.mp_prefetch(grain.MultiprocessingOptions(num_workers=self.num_workers,
                                                         per_worker_buffer_size=self.prefetch_batches))
        return iter(ds)

    def close(self) -> None:
        """Stop the worker processes (they restart on the next iteration)."""
        it, self._it, self._next_epoch = self._it, None, None
        if it is not None and hasattr(it, "close"):
            it.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass


def _channels_last(batch: dict) -> dict:
    """``depth`` (B, H, W) -> (B, H, W, 1) (a view)."""
    if "depth" in batch:
        batch["depth"] = np.expand_dims(batch["depth"], DEPTH_CHANNEL_AXIS)
    return batch


def device_put(batch: dict, device=None) -> dict:
    """``jax.device_put`` of every array of a batch, except 64-bit integer arrays when JAX runs
    without 64-bit types (the default): those (``sample_id``, ``index``, ``class_index``, ...)
    stay numpy arrays on the host, exact, because JAX would silently truncate them to 32 bits
    (``sample_id`` 3971172795307752716 would become -33325812).  With
    ``jax.config.update("jax_enable_x64", True)`` everything goes to the device."""
    jax = require("jax", "articulated_dataset.training.loaders.jax.device_put", JAX_INSTALL)
    x64 = bool(jax.config.read("jax_enable_x64"))
    out = {}
    for k, v in batch.items():
        a = np.asarray(v)
        out[k] = a if (a.dtype.kind in "iu" and a.dtype.itemsize == 8 and not x64) else jax.device_put(v, device)
    return out


__all__ = ["ShardDataSource", "JaxLoader", "device_put"]
