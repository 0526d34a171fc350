"""PyTorch datasets over the shards (``pip install torch==2.13.0`` first: the CPU build).

* :class:`DepthDataset`: map-style; ``ds[i]`` is a dict of tensors, ``ds[[i, j, ...]]`` a batch
  (one contiguous read per run of images), ``__getitems__`` serves DataLoader auto-batching.
* :class:`EpochBatchSampler`: the batches of :func:`~articulated_dataset.loaders.reader.plan_epoch`
  for one distributed rank; with ``DataLoader(ds, sampler=..., batch_size=None)``.
* :class:`ShardIterableDataset`: iterable; splits the blocks of the shards across distributed
  ranks *and* DataLoader workers (part ``rank * num_workers + worker``), so every sample is seen
  exactly once per epoch; deterministic per-epoch shuffling from ``(seed, epoch)``.
* :func:`make_loader`: a DataLoader with ``set_epoch(epoch)`` over either of them.

String fields (``class``) become a ``str`` per sample / a list of ``str`` per batch.  Call
``set_epoch(epoch)`` before iterating each epoch (as with ``DistributedSampler``).  The epoch is
kept in a shared-memory tensor, so it also reaches persistent workers (``make_loader`` keeps its
workers alive across epochs).  In a worker process, batches are read straight into shared
memory, so handing them to the main process copies nothing.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, IterableDataset, Sampler, get_worker_info

from ..errors import UserError
from .reader import DEFAULT_BLOCK_SIZE, SAMPLE_ORDER_STREAM, BatchProcessor, ShardReader, load_batch, plan_epoch

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

    def __init__(self):
        self.tensors: dict[int, tuple[np.ndarray, torch.Tensor]] = {}

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

    def tensor(self, a) -> torch.Tensor | None:
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


class _SharedEpoch:
    """An epoch counter in shared memory: ``set_epoch`` in the main process reaches workers that
    were started earlier (persistent workers; fork or spawn)."""

    def _init_epoch(self) -> None:
        self._epoch = torch.zeros((), dtype=torch.int64).share_memory_()

    @property
    def epoch(self) -> int:
        return int(self._epoch)

    def set_epoch(self, epoch: int) -> None:
        if int(epoch) < 0:
            raise UserError(f"epoch must be >= 0, got {epoch}")
        self._epoch.fill_(int(epoch))


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
    """Map-style dataset: item ``i`` is a dict of tensors (``index`` added; ``target`` if a
    :class:`~articulated_dataset.targets.TargetLayout` is given, normalised by ``norm``).

    ``transform(sample, rng)`` (see :mod:`articulated_dataset.transforms`) is seeded by
    ``(seed, epoch, i)``; ``set_epoch`` changes the epoch.
    """

    def __init__(self, source, fields: Sequence[str] | None = None, *, target=None, norm=None, transform=None,
                 seed: int = 0):
        self.reader = _reader(source, fields)
        self.processor = BatchProcessor(self.reader.fields, transform=transform, target=target, norm=norm, seed=seed)
        self._init_epoch()

    def __len__(self) -> int:
        return len(self.reader)

    def _load(self, indices) -> dict:
        alloc = _worker_alloc()
        return to_torch(load_batch(self.reader, self.processor, indices, self.epoch, alloc=alloc), alloc)

    def __getitem__(self, i):
        """One sample (int) or a stacked batch (sequence / array of ints)."""
        if isinstance(i, (int, np.integer)):
            n = len(self)
            j = int(i) + n if int(i) < 0 else int(i)
            if not 0 <= j < n:
                raise IndexError(f"sample index {i} out of range for a dataset of {n} images")
            return {k: v[0] for k, v in self._load([j]).items()}
        if isinstance(i, torch.Tensor):
            i = i.numpy()
        return self._load(np.asarray(i, dtype=np.int64))

    def __getitems__(self, indices) -> list[dict]:
        """DataLoader auto-batching hook: one batched read, returned as per-sample dicts."""
        return _split_batch(self._load(np.asarray(indices, dtype=np.int64)), len(indices))


class EpochBatchSampler(Sampler):
    """Batches of :func:`plan_epoch` for ``rank`` of ``world_size`` (``set_epoch`` per epoch)."""

    def __init__(self, shard_sizes, batch_size: int, *, shuffle: bool = True, seed: int = 0, rank: int | None = None,
                 world_size: int | None = None, block_size: int = DEFAULT_BLOCK_SIZE, drop_last: bool = False,
                 equal_parts: bool = False):
        self.shard_sizes = np.asarray(shard_sizes, dtype=np.int64)
        self.rank, self.world_size = distributed_rank_world(rank, world_size)
        self.kw = dict(batch_size=batch_size, seed=seed, shuffle=shuffle, block_size=block_size, drop_last=drop_last,
                       equal_parts=equal_parts)
        self.epoch = 0
        plan_epoch(self.shard_sizes, epoch=0, part_index=self.rank, part_count=self.world_size, **self.kw)  # validate

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def batches(self) -> list[np.ndarray]:
        return plan_epoch(self.shard_sizes, epoch=self.epoch, part_index=self.rank, part_count=self.world_size, **self.kw)

    def __iter__(self):
        for b in self.batches():
            yield b.tolist()

    def __len__(self) -> int:
        return len(self.batches())


class ShardIterableDataset(_SharedEpoch, IterableDataset):
    """Iterable dataset over shard blocks, split across ranks and DataLoader workers.

    Part ``p = rank * num_workers + worker_id`` of ``P = world_size * num_workers`` iterates its
    batches of :func:`plan_epoch` (``seed``, current epoch).  With ``batch_size`` it yields whole
    batches (use ``DataLoader(ds, batch_size=None)``); without, single samples, read
    ``read_size`` at a time and (with ``shuffle``) yielded in a random order within them.
    """

    def __init__(self, source, fields: Sequence[str] | None = None, *, batch_size: int | None = None,
                 shuffle: bool = True, seed: int = 0, rank: int | None = None, world_size: int | None = None,
                 block_size: int = DEFAULT_BLOCK_SIZE, drop_last: bool = False, equal_parts: bool = False,
                 target=None, norm=None, transform=None, read_size: int = DEFAULT_READ_SIZE):
        super().__init__()
        self.reader = _reader(source, fields)
        self.processor = BatchProcessor(self.reader.fields, transform=transform, target=target, norm=norm, seed=seed)
        self.rank, self.world_size = distributed_rank_world(rank, world_size)
        self.batch_size = batch_size
        self.read_size = int(batch_size or read_size)
        self.shuffle, self.seed, self.block_size = bool(shuffle), seed, block_size
        self.drop_last = bool(drop_last and batch_size is not None)
        self.equal_parts = bool(equal_parts)
        self._init_epoch()
        self.plan(part_index=0, part_count=1)  # validate the options now, not in a worker

    def plan(self, part_index: int, part_count: int, epoch: int | None = None) -> list[np.ndarray]:
        """The batches (index arrays) of one part in ``epoch`` (default: the current epoch)."""
        epoch = self.epoch if epoch is None else epoch
        return plan_epoch(self.reader.shard_sizes, batch_size=self.read_size, seed=self.seed, epoch=epoch,
                          shuffle=self.shuffle, part_index=part_index, part_count=part_count,
                          block_size=self.block_size, drop_last=self.drop_last, equal_parts=self.equal_parts)

    def part(self) -> tuple[int, int]:
        """``(part_index, part_count)`` of the calling process (worker and rank)."""
        info = get_worker_info()
        worker, n_workers = (info.id, info.num_workers) if info is not None else (0, 1)
        return self.rank * n_workers + worker, self.world_size * n_workers

    def __iter__(self):
        part_index, part_count = self.part()
        epoch = self.epoch
        rng = np.random.default_rng([self.seed, epoch, SAMPLE_ORDER_STREAM, part_index, part_count])
        for indices in self.plan(part_index, part_count, epoch):
            alloc = _worker_alloc() if self.batch_size is not None else None
            batch = to_torch(load_batch(self.reader, self.processor, indices, epoch, alloc=alloc), alloc)
            if self.batch_size is not None:
                yield batch
                continue
            samples = _split_batch(batch, len(indices))
            order = rng.permutation(len(samples)) if self.shuffle else range(len(samples))
            for k in order:
                yield samples[k]


class EpochDataLoader(DataLoader):
    """A DataLoader whose ``set_epoch(epoch)`` reaches its dataset and batch sampler."""

    def set_epoch(self, epoch: int) -> None:
        for obj in (self.dataset, self.batch_sampler, self.sampler):
            if hasattr(obj, "set_epoch"):
                obj.set_epoch(epoch)


def make_loader(source, *, batch_size: int = DEFAULT_BATCH_SIZE, fields: Sequence[str] | None = None,
                shuffle: bool = True, seed: int = 0, num_workers: int = DEFAULT_NUM_WORKERS,
                rank: int | None = None, world_size: int | None = None, drop_last: bool = False,
                equal_parts: bool = False, block_size: int = DEFAULT_BLOCK_SIZE, target=None, norm=None,
                transform=None, iterable: bool = True, **dataloader_kwargs) -> EpochDataLoader:
    """A DataLoader of dict batches over ``source`` (split folders or a ShardReader).

    ``iterable=True``: :class:`ShardIterableDataset` (batches formed in the workers);
    ``iterable=False``: :class:`DepthDataset` with :class:`EpochBatchSampler` (batches formed in
    the main process, handed to any worker).  Both follow :func:`plan_epoch` and cover each
    sample once per epoch across ranks.  Call ``loader.set_epoch(epoch)`` before each epoch.
    Extra keyword arguments go to ``torch.utils.data.DataLoader`` (e.g. ``pin_memory``).
    """
    if num_workers < 0:
        raise UserError(f"num_workers must be >= 0, got {num_workers}")
    if num_workers > 0:
        dataloader_kwargs.setdefault("prefetch_factor", DEFAULT_PREFETCH_FACTOR)
        dataloader_kwargs.setdefault("persistent_workers", True)
    if iterable:
        ds = ShardIterableDataset(source, fields, batch_size=batch_size, shuffle=shuffle, seed=seed, rank=rank,
                                  world_size=world_size, block_size=block_size, drop_last=drop_last,
                                  equal_parts=equal_parts, target=target, norm=norm, transform=transform)
        return EpochDataLoader(ds, batch_size=None, num_workers=num_workers, **dataloader_kwargs)
    ds = DepthDataset(source, fields, target=target, norm=norm, transform=transform, seed=seed)
    sampler = EpochBatchSampler(ds.reader.shard_sizes, batch_size, shuffle=shuffle, seed=seed, rank=rank,
                                world_size=world_size, block_size=block_size, drop_last=drop_last,
                                equal_parts=equal_parts)
    return EpochDataLoader(ds, sampler=sampler, batch_size=None, num_workers=num_workers, **dataloader_kwargs)


__all__ = ["DepthDataset", "ShardIterableDataset", "EpochBatchSampler", "EpochDataLoader", "make_loader", "to_torch",
           "distributed_rank_world"]
