"""PyTorch datasets and loaders over the shards (needs torch: ``pip install torch --index-url
https://download.pytorch.org/whl/cpu``, PyTorch's CPU build).

* :class:`DepthDataset`: map-style; ``ds[i]`` one sample, ``ds[[i, j]]`` a batch; works with a
  stock ``DataLoader`` (auto-batching reads each batch at once through ``__getitems__``) and
  ``DistributedSampler``.
* :class:`EpochBatchSampler`: the batches of :func:`~articulated_dataset.training.loaders.epoch.plan_epoch`
  for one rank, for ``DataLoader(ds, sampler=..., batch_size=None)``.
* :class:`ShardIterableDataset`: iterable; the rank's batches of the epoch plan, dealt to the
  DataLoader workers in turn, so batches are the same whatever ``num_workers`` is.
* :func:`make_loader`: a DataLoader with ``set_epoch(epoch)`` over either of them.

Layout: ``depth`` is channels-first, ``(B, 1, H, W)`` float32 m (one sample: ``(1, H, W)``);
``mask`` stays ``(B, H, W)`` uint8 (a class-index map, the layout of segmentation targets);
``K`` is float32.  String fields (``class``) become a ``str`` per sample / a list of ``str`` per
batch.  Every rank gets the same number of batches (``remainder="pad"`` by default, as
``DistributedSampler``).  Call ``set_epoch(epoch)`` before each epoch (``make_loader``'s
loader advances the epoch itself when it is not called); the epoch is kept in a shared-memory
tensor, so it also reaches persistent workers.  A dataset whose epoch is never set (a stock
DataLoader whose sampler alone gets ``set_epoch``) still gives each read of a sample a new
augmentation (see :meth:`_SharedEpoch.transform_epoch`).  In a worker process, batches are
read straight into shared memory, so handing them to the main process copies nothing.

Why one module of ~440 lines: it is everything that imports torch (an optional dependency,
imported once at the top), and its four public classes share the private shared-memory and
epoch functions; the framework-neutral parts are already in :mod:`.reader`, :mod:`.epoch` and
:mod:`.batch`.
"""

from __future__ import annotations

import hashlib
from typing import Any, Sequence

import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.training.loaders.batch import BatchProcessor, load_batch
from articulated_dataset.training.loaders.epoch import (
    DEFAULT_BLOCK_SIZE,
    SAMPLE_ORDER_STREAM,
    check_batch_size,
    n_batches,
    part_bounds,
    plan_epoch,
)
from articulated_dataset.training.loaders.reader import TORCH_INSTALL, ShardReader, index_array, require

torch = require("torch", "articulated_dataset.training.loaders.torch", TORCH_INSTALL)
from torch.utils.data import DataLoader, Dataset, IterableDataset, Sampler, get_worker_info  # noqa: E402

#: Default batch size of :func:`make_loader`.
DEFAULT_BATCH_SIZE = 128
#: Default DataLoader workers of :func:`make_loader` (the benchmark's 2-core configuration).
DEFAULT_NUM_WORKERS = 2
#: Batches each worker prepares ahead in make_loader: 4 (13 MB each at batch 128, 192x108)
#: absorbed scheduling jitter better than torch's default 2 on a busy 2-core machine.
DEFAULT_PREFETCH_FACTOR = 4
#: Images read at once by ShardIterableDataset when it yields single samples.
DEFAULT_READ_SIZE = 128
#: Alignment of each field inside a worker's shared-memory batch block (a cache line).
SHARED_ALIGN_BYTES = 64


def _reader(source, fields) -> ShardReader:
    if isinstance(source, ShardReader):
        if fields is not None and tuple(fields) != source.fields:
            return ShardReader(source.split_dirs, fields=fields)
        return source
    return ShardReader(source, fields=fields)


def _decode_strings(a: np.ndarray):
    if a.ndim == 0:
        return a.item().decode("ascii", "replace").rstrip("\x00")
    return [x.decode("ascii", "replace").rstrip("\x00") for x in a.reshape(-1)]


class SharedAllocator:
    """``alloc(specs)`` for :meth:`ShardReader.get_batch` in DataLoader workers: the batch's arrays
    as numpy views of ONE tensor storage in shared memory (like ``default_collate`` in workers,
    but one block per batch rather than one per field: each shared block costs a file descriptor,
    a mapping and fresh page faults on both sides).  The batch is then not copied again when the
    worker hands it to the main process; :func:`to_torch` gives back the tensors themselves."""

    def __init__(self) -> None:
        self.tensors: dict[int, tuple[np.ndarray, torch.Tensor]] = {}  # type: ignore[name-defined]  # torch: require()

    def __call__(self, specs: dict) -> dict:
        layout, total = {}, 0
        for name, (shape, dtype) in specs.items():
            dtype = np.dtype(dtype)
            if dtype.kind in "SU":
                continue
            total = -(-total // SHARED_ALIGN_BYTES) * SHARED_ALIGN_BYTES
            layout[name] = total
            total += int(np.prod(shape)) * dtype.itemsize
        storage = torch.UntypedStorage._new_shared(max(total, 1))
        out = {}
        for name, (shape, dtype) in specs.items():
            dtype = np.dtype(dtype)
            if name not in layout:
                out[name] = np.empty(shape, dtype)
                continue
            tdtype = torch.from_numpy(np.empty(0, dtype)).dtype
            t = torch.empty(0, dtype=tdtype).set_(storage, layout[name] // dtype.itemsize, tuple(shape))
            a = t.numpy()
            self.tensors[id(a)] = (a, t)
            out[name] = a
        return out

    def tensor(self, a) -> torch.Tensor | None:  # type: ignore[name-defined]  # torch comes from require()
        hit = self.tensors.get(id(a))
        return hit[1] if hit is not None and hit[0] is a else None


def _worker_alloc() -> SharedAllocator | None:
    """A shared-memory allocator inside DataLoader workers; None in the main process."""
    return SharedAllocator() if get_worker_info() is not None and hasattr(torch.UntypedStorage, "_new_shared") else None


def to_torch(batch: dict, alloc: SharedAllocator | None = None) -> dict:
    """numpy arrays -> tensors (sharing memory where possible); byte strings -> ``str``."""
    out = {}
    for k, v in batch.items():
        t = alloc.tensor(v) if alloc is not None else None
        if t is not None:
            out[k] = t
            continue
        v = np.asarray(v)
        if v.dtype.kind in "SU":
            out[k] = _decode_strings(v.astype("S") if v.dtype.kind == "U" else v)
        else:
            if not v.flags.c_contiguous:
                v = np.ascontiguousarray(v)
            if not v.flags.writeable:
                v = v.copy()
            out[k] = torch.from_numpy(v)
    return out


def _split_batch(batch: dict, n: int) -> list[dict]:
    return [{k: v[i] for k, v in batch.items()} for i in range(n)]


#: Axis of the channel that the torch loaders add to ``depth`` (channels-first: (B, 1, H, W)).
DEPTH_CHANNEL_AXIS = -3


def _channels_first(batch: dict) -> dict:
    """``depth`` (B, H, W) -> (B, 1, H, W): a view, so a shared-memory batch stays shared."""
    if "depth" in batch:
        batch["depth"] = batch["depth"].unsqueeze(DEPTH_CHANNEL_AXIS)
    return batch


#: First word of the transform keys of a dataset whose epoch was never set (a stock DataLoader):
#: keeps them apart from the keys ``(epoch,)`` of set epochs.
UNSET_EPOCH_TAG = 0xA070
_U32 = 0xFFFFFFFF


def _pass_entropy() -> int:
    """A 64-bit value that changes at every pass of a stock DataLoader.

    In a worker: the DataLoader's base seed of the pass (``worker_info.seed - worker_info.id``,
    drawn from torch's RNG when the pass starts; the same in every worker of the pass).  In the
    main process (``num_workers=0``): a digest of torch's global RNG state, which the DataLoader
    advances when each pass starts (it draws that base seed).  Both follow ``torch.manual_seed``."""
    info = get_worker_info()
    if info is not None:
        return (int(info.seed) - int(info.id)) & 0xFFFFFFFFFFFFFFFF
    digest = hashlib.blake2b(torch.get_rng_state().numpy().tobytes(), digest_size=8).digest()
    return int.from_bytes(digest, "little")


class _SharedEpoch:
    """An epoch counter in shared memory: ``set_epoch`` in the main process reaches workers that
    were started earlier (persistent workers; fork or spawn).  Also counts, in shared memory,
    how often each sample was read (for :meth:`transform_epoch` when no epoch is set)."""

    def _init_epoch(self, n_samples: int) -> None:
        self._epoch = torch.full((), -1, dtype=torch.int64).share_memory_()  # -1: never set
        self._visits = torch.zeros(int(n_samples), dtype=torch.int32).share_memory_()

    @property
    def epoch(self) -> int:
        """The epoch set by ``set_epoch`` (0 if it never was)."""
        return max(int(self._epoch), 0)

    @property
    def epoch_is_set(self) -> bool:
        return int(self._epoch) >= 0

    def set_epoch(self, epoch: int) -> None:
        if int(epoch) < 0:
            raise UserError(f"epoch must be >= 0, got {epoch}")
        self._epoch.fill_(int(epoch))

    def transform_epoch(self, indices: np.ndarray, rank: int):
        """What seeds the transforms of a batch (see :func:`articulated_dataset.training.transforms.sample_rng`).

        With an epoch set: the epoch (an int): the augmentation of a sample depends only on
        ``(seed, epoch, index)``: the same in both frameworks, with any number of workers.
        Never set (a stock DataLoader whose ``DistributedSampler`` alone gets ``set_epoch``):
        one key per sample, ``(tag, pass entropy, rank, visits)``: the pass entropy (see
        :func:`_pass_entropy`) changes every pass, and ``visits`` (how often this dataset, in any
        of its workers, read the sample before) every time the sample is read again, so the
        augmentation changes every epoch either way (also with persistent workers)."""
        epoch = int(self._epoch)
        if epoch >= 0:
            return epoch
        idx = np.asarray(indices, dtype=np.int64)
        visits = self._visits.numpy()
        seen = visits[idx].astype(np.int64)
        np.add.at(visits, idx, 1)
        entropy = _pass_entropy()
        keys = np.empty((len(idx), 5), dtype=np.int64)
        keys[:, 0], keys[:, 1], keys[:, 2], keys[:, 3], keys[:, 4] = (UNSET_EPOCH_TAG, entropy >> 32, entropy & _U32,
                                                                      rank, seen)
        return keys


def distributed_rank_world(rank: int | None, world_size: int | None) -> tuple[int, int]:
    """``(rank, world_size)``: given values, else torch.distributed's when initialised, else (0, 1)."""
    if rank is None or world_size is None:
        dist = torch.distributed
        if dist.is_available() and dist.is_initialized():
            rank = dist.get_rank() if rank is None else rank
            world_size = dist.get_world_size() if world_size is None else world_size
        else:
            rank = 0 if rank is None else rank
            world_size = 1 if world_size is None else world_size
    if world_size <= 0 or not 0 <= rank < world_size:
        raise UserError(f"rank {rank} is not in [0, world_size = {world_size})")
    return int(rank), int(world_size)


class DepthDataset(_SharedEpoch, Dataset):
    """Map-style dataset: item ``i`` is a dict of tensors (``depth`` (1, H, W); ``index`` added;
    ``target`` if a :class:`~articulated_dataset.training.targets.TargetLayout` is given, normalised by
    ``norm``).

    ``transform(sample, rng)`` (see :mod:`articulated_dataset.training.transforms`) is seeded by
    ``(seed, epoch, i)`` once ``set_epoch`` was called; without it (a stock DataLoader with
    ``DistributedSampler``) each read of a sample gets a new augmentation
    (:meth:`~_SharedEpoch.transform_epoch`).
    """

    def __init__(self, source, fields: Sequence[str] | None = None, *, target=None, norm=None, transform=None,
                 seed: int = 0):
        self.reader = _reader(source, fields)
        self.processor = BatchProcessor(self.reader.fields, transform=transform, target=target, norm=norm, seed=seed)
        self._init_epoch(len(self.reader))

    def __len__(self) -> int:
        return len(self.reader)

    def _load(self, indices) -> dict:
        alloc = _worker_alloc()
        epoch = self.epoch
        if self.processor.transform is not None:
            epoch = self.transform_epoch(indices, distributed_rank_world(None, None)[0])
        return _channels_first(to_torch(load_batch(self.reader, self.processor, indices, epoch, alloc=alloc), alloc))

    def __getitem__(self, i):
        """One sample (int) or a stacked batch (sequence / array of ints)."""
        if isinstance(i, (int, np.integer)):
            n = len(self)
            j = int(i) + n if int(i) < 0 else int(i)
            if not 0 <= j < n:
                raise IndexError(f"sample index {i} out of range for a dataset of {n} images")
            return {k: v[0] for k, v in self._load(np.asarray([j], dtype=np.int64)).items()}
        if isinstance(i, torch.Tensor):
            i = i.numpy()
        idx = index_array(i)
        n = len(self)
        inside = (idx >= -n) & (idx < 0)  # negative indices count from the end, as for one sample
        return self._load(np.where(inside, idx + n, idx))

    def __getitems__(self, indices) -> list[dict]:
        """DataLoader auto-batching hook: one batched read, returned as per-sample dicts."""
        return _split_batch(self._load(index_array(indices)), len(indices))


class EpochBatchSampler(Sampler):
    """Batches of :func:`plan_epoch` for ``rank`` of ``world_size`` (``set_epoch`` per epoch).

    ``remainder`` (``"pad"``, ``"drop"`` or ``"uneven"``): what happens to the samples that do
    not divide equally among the ranks (:data:`~articulated_dataset.training.loaders.epoch.REMAINDER_MODES`);
    with ``"pad"`` or ``"drop"`` every rank gets the same number of batches."""

    def __init__(self, shard_sizes, batch_size: int, *, shuffle: bool = True, seed: int = 0, rank: int | None = None,
                 world_size: int | None = None, block_size: int = DEFAULT_BLOCK_SIZE, drop_last: bool = False,
                 remainder: str = "pad"):
        self.shard_sizes = np.asarray(shard_sizes, dtype=np.int64)
        self.rank, self.world_size = distributed_rank_world(rank, world_size)
        self.kw: dict[str, Any] = dict(batch_size=batch_size, seed=seed, shuffle=shuffle, block_size=block_size,
                                       drop_last=drop_last, remainder=remainder)
        self.epoch = 0
        plan_epoch(self.shard_sizes, epoch=0, part_index=self.rank, part_count=self.world_size, **self.kw)  # validate

    def set_epoch(self, epoch: int) -> None:
        """Use epoch ``epoch``'s shuffle on the next pass."""
        self.epoch = int(epoch)

    def batches(self) -> list[np.ndarray]:
        """The batches (arrays of global sample indices) of this rank in the current epoch."""
        return plan_epoch(self.shard_sizes, epoch=self.epoch, part_index=self.rank, part_count=self.world_size, **self.kw)

    def __iter__(self):
        for b in self.batches():
            yield b.tolist()

    def __len__(self) -> int:
        a, b = part_bounds(int(self.shard_sizes.sum()), self.world_size, self.rank, self.kw["remainder"])
        return n_batches(b - a, int(self.kw["batch_size"]), self.kw["drop_last"])


class ShardIterableDataset(_SharedEpoch, IterableDataset):
    """Iterable dataset over shard blocks for one rank of ``world_size``.

    The rank's batches of :func:`plan_epoch` (``seed``, current epoch, ``remainder``) are dealt
    to the DataLoader workers in turn (batch ``b`` to worker ``b mod num_workers``), and the
    DataLoader hands them on in that order: the batches are the same whatever ``num_workers``
    is.  With ``batch_size`` it yields whole batches (use ``DataLoader(ds, batch_size=None)``;
    ``len(ds)`` is the number of batches); without, single samples (``len(ds)`` of them), read
    ``read_size`` at a time and (with ``shuffle``) yielded in a random order within each read;
    the DataLoader's ``batch_size`` then groups them inside each worker (PyTorch's rule for
    iterable datasets), so give ``batch_size`` here for batches independent of the workers.
    """

    def __init__(self, source, fields: Sequence[str] | None = None, *, batch_size: int | None = None,
                 shuffle: bool = True, seed: int = 0, rank: int | None = None, world_size: int | None = None,
                 block_size: int = DEFAULT_BLOCK_SIZE, drop_last: bool = False, remainder: str = "pad",
                 target=None, norm=None, transform=None, read_size: int = DEFAULT_READ_SIZE):
        super().__init__()
        self.reader = _reader(source, fields)
        self.processor = BatchProcessor(self.reader.fields, transform=transform, target=target, norm=norm, seed=seed)
        self.rank, self.world_size = distributed_rank_world(rank, world_size)
        check_batch_size(batch_size, allow_none=True)  # 0 would silently read batches of read_size
        self.batch_size = batch_size
        self.read_size = int(batch_size or read_size)
        self.shuffle, self.seed, self.block_size = bool(shuffle), seed, block_size
        self.drop_last = bool(drop_last and batch_size is not None)
        self.remainder = remainder
        self._init_epoch(len(self.reader))
        self.plan()  # validate the options now, not in a worker

    def plan(self, epoch: int | None = None) -> list[np.ndarray]:
        """This rank's batches (index arrays) in ``epoch`` (default: the current epoch)."""
        epoch = self.epoch if epoch is None else epoch
        return plan_epoch(self.reader.shard_sizes, batch_size=self.read_size, seed=self.seed, epoch=epoch,
                          shuffle=self.shuffle, part_index=self.rank, part_count=self.world_size,
                          block_size=self.block_size, drop_last=self.drop_last, remainder=self.remainder)

    def __len__(self) -> int:
        a, b = part_bounds(len(self.reader), self.world_size, self.rank, self.remainder)
        return n_batches(b - a, self.read_size, self.drop_last) if self.batch_size is not None else b - a

    def __iter__(self):
        info = get_worker_info()
        worker, n_workers = (info.id, info.num_workers) if info is not None else (0, 1)
        epoch = self.epoch
        plan = self.plan(epoch)
        for c in range(worker, len(plan), n_workers):
            indices = plan[c]
            alloc = _worker_alloc() if self.batch_size is not None else None
            key = self.transform_epoch(indices, self.rank) if self.processor.transform is not None else epoch
            batch = _channels_first(to_torch(load_batch(self.reader, self.processor, indices, key, alloc=alloc), alloc))
            if self.batch_size is not None:
                yield batch
                continue
            samples = _split_batch(batch, len(indices))
            order: np.ndarray | range
            if self.shuffle:
                rng = np.random.default_rng([self.seed, epoch, SAMPLE_ORDER_STREAM, self.rank, self.world_size, c])
                order = rng.permutation(len(samples))
            else:
                order = range(len(samples))
            for k in order:
                yield samples[k]


class EpochDataLoader(DataLoader):
    """A DataLoader whose ``set_epoch(epoch)`` reaches its dataset and batch sampler.

    A pass that starts without ``set_epoch`` having been called since the previous pass runs
    the next epoch (the first pass runs epoch 0), so a loop that forgets ``set_epoch`` still
    reshuffles and re-augments every epoch."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._epoch, self._epoch_given, self._passes = 0, False, 0
        self._propagate(0)

    def _propagate(self, epoch: int) -> None:
        for obj in (self.dataset, self.batch_sampler, self.sampler):
            if hasattr(obj, "set_epoch"):
                obj.set_epoch(epoch)  # type: ignore[union-attr]  # hasattr checked
        self._epoch = int(epoch)

    @property
    def epoch(self) -> int:
        """The epoch the dataset and batch sampler were last set to."""
        return self._epoch

    def set_epoch(self, epoch: int) -> None:
        """Set epoch ``epoch`` (>= 0) on the dataset and batch sampler for the next pass; a negative epoch is the
        user's mistake."""
        if int(epoch) < 0:
            raise UserError(f"epoch must be >= 0, got {epoch}")
        self._propagate(epoch)
        self._epoch_given = True

    def __iter__(self):
        if self._passes and not self._epoch_given:
            self._propagate(self._epoch + 1)
        self._epoch_given = False
        self._passes += 1
        return super().__iter__()


def make_loader(source, *, batch_size: int = DEFAULT_BATCH_SIZE, fields: Sequence[str] | None = None,
                shuffle: bool = True, seed: int = 0, num_workers: int = DEFAULT_NUM_WORKERS,
                rank: int | None = None, world_size: int | None = None, drop_last: bool = False,
                remainder: str = "pad", block_size: int = DEFAULT_BLOCK_SIZE, target=None, norm=None,
                transform=None, iterable: bool = True, **dataloader_kwargs) -> EpochDataLoader:
    """A DataLoader of dict batches over ``source`` (split folders or a ShardReader).

    ``iterable=True``: :class:`ShardIterableDataset` (batches read in the workers);
    ``iterable=False``: :class:`DepthDataset` with :class:`EpochBatchSampler` (batches planned in
    the main process, read by any worker).  Both give the batches of :func:`plan_epoch` for the
    rank, whatever ``num_workers`` is; every rank gets the same number of batches
    (``remainder="pad"``: samples that do not divide equally among the ranks are repeated from
    the start of the epoch, as ``DistributedSampler`` does; ``"drop"`` leaves them out;
    ``"uneven"`` keeps every sample exactly once, for evaluation).  ``len(loader)`` is the
    number of batches per epoch of this rank.  Call ``loader.set_epoch(epoch)`` before each
    epoch (without it, each pass runs the next epoch).  Extra keyword arguments go to
    ``torch.utils.data.DataLoader`` (e.g. ``pin_memory``).
    """
    if num_workers < 0:
        raise UserError(f"num_workers must be >= 0, got {num_workers}")
    if num_workers > 0:
        dataloader_kwargs.setdefault("prefetch_factor", DEFAULT_PREFETCH_FACTOR)
        dataloader_kwargs.setdefault("persistent_workers", True)
    if iterable:
        ds: ShardIterableDataset | DepthDataset = ShardIterableDataset(
            source, fields, batch_size=batch_size, shuffle=shuffle, seed=seed, rank=rank, world_size=world_size,
            block_size=block_size, drop_last=drop_last, remainder=remainder, target=target, norm=norm,
            transform=transform)
        return EpochDataLoader(ds, batch_size=None, num_workers=num_workers, **dataloader_kwargs)
    ds = DepthDataset(source, fields, target=target, norm=norm, transform=transform, seed=seed)
    sampler = EpochBatchSampler(ds.reader.shard_sizes, batch_size, shuffle=shuffle, seed=seed, rank=rank,
                                world_size=world_size, block_size=block_size, drop_last=drop_last,
                                remainder=remainder)
    return EpochDataLoader(ds, sampler=sampler, batch_size=None, num_workers=num_workers, **dataloader_kwargs)


__all__ = ["DepthDataset", "ShardIterableDataset", "EpochBatchSampler", "EpochDataLoader", "make_loader", "to_torch",
           "distributed_rank_world", "DEPTH_CHANNEL_AXIS"]
