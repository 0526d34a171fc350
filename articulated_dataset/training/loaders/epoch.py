"""The epoch plan shared by every loader (:func:`plan_epoch`): shuffled blocks of consecutive
images grouped into batches, split among ranks, with the remainder padded, dropped or left uneven;
the one definition of shuffling and sharding for the PyTorch and the JAX loaders."""

from __future__ import annotations

import numpy as np

from articulated_dataset.core.errors import UserError

#: Images per contiguous block in :func:`plan_epoch`.  Batches are unions of shuffled blocks, so
#: a block is the unit of contiguous reading.  Measured CPU per 192x108 image (depth + mask +
#: labels): 126 us read one by one, 113 us in runs of 4, 103 us in slabs of 128 (decompression
#: dominates); a batch of 128 still mixes 32 blocks, i.e. up to 32 objects (16 images each).
DEFAULT_BLOCK_SIZE = 4
#: Stream tags keep the shuffling and the transform random streams independent for one seed.
PLAN_STREAM = 0x5EED0001
SAMPLE_ORDER_STREAM = 0x5EED0002


def check_batch_size(value, *, allow_none: bool = False) -> int | None:
    """A batch size: a positive whole number (a bool, 1.5 or 0 is a UserError), or with
    ``allow_none`` None (single samples)."""
    if value is None and allow_none:
        return None
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
        raise UserError(f"batch size must be a positive integer{' or None (single samples)' if allow_none else ''}, "
                        f"got {value!r}")
    return int(value)


def check_seed(name: str, value) -> int:
    """``value`` as an int; anything but a non-negative integer is the user's mistake."""
    if not isinstance(value, (int, np.integer)) or value < 0:
        raise UserError(f"{name} must be a non-negative integer, got {value!r}")
    return int(value)


#: How :func:`plan_epoch` deals with the ``N mod P`` samples that do not divide equally among
#: ``P`` parts (ranks): ``"pad"`` repeats samples from the start of the epoch's order until every
#: part has ``ceil(N / P)`` (``DistributedSampler(drop_last=False)``), ``"drop"`` leaves them out
#: of the epoch, every part has ``floor(N / P)`` (``DistributedSampler(drop_last=True)``);
#: ``"uneven"`` keeps every sample exactly once and parts differ by up to one sample.
REMAINDER_MODES = ("pad", "drop", "uneven")


def check_remainder(remainder: str) -> str:
    """``remainder`` if it is one of :data:`REMAINDER_MODES`; anything else is the user's mistake."""
    if remainder not in REMAINDER_MODES:
        raise UserError(f"remainder must be one of {', '.join(map(repr, REMAINDER_MODES))}, got {remainder!r}")
    return remainder


def part_bounds(n_samples: int, part_count: int, part_index: int, remainder: str = "pad") -> tuple[int, int]:
    """``[start, stop)`` of part ``part_index`` in the epoch's (padded or cut) sample sequence."""
    n, P = int(n_samples), int(part_count)
    total = {"pad": -(-n // P) * P, "drop": n // P * P, "uneven": n}[check_remainder(remainder)] if n else 0
    return part_index * total // P, (part_index + 1) * total // P


def n_batches(n_samples: int, batch_size: int, drop_last: bool) -> int:
    """Batches of ``batch_size`` cut from ``n_samples`` (a short last one kept unless ``drop_last``)."""
    return n_samples // batch_size if drop_last else -(-n_samples // batch_size)


def plan_epoch(shard_sizes, *, batch_size: int, seed: int = 0, epoch: int = 0, shuffle: bool = True,
               part_index: int = 0, part_count: int = 1, block_size: int = DEFAULT_BLOCK_SIZE,
               drop_last: bool = False, remainder: str = "pad") -> list[np.ndarray]:
    """The batches (arrays of global sample indices) of one part of one epoch.

    1. Every shard is cut into blocks of ``block_size`` consecutive images (a block never
       crosses a shard boundary).
    2. With ``shuffle``, the blocks are permuted by a generator seeded with ``(seed, epoch)``:
       the same for every part, different for every epoch.  Their images, in that block
       order, are the epoch's sample sequence (``N`` samples).
    3. The sequence is made divisible by ``P = part_count`` as :data:`REMAINDER_MODES` says
       (default ``"pad"``: repeated from its start to ``ceil(N / P) P``, as
       ``DistributedSampler`` does), and part ``p`` takes the contiguous range
       ``[p T / P, (p + 1) T / P)`` of it (``T`` its length): every part gets the same number of
       samples, hence of batches (ranks of a collective training step must), and together the
       parts hold every sample once (plus the padding).  Parts are distributed ranks or JAX
       processes.
    4. The part's samples are cut into consecutive batches of ``batch_size`` (the last one
       shorter unless ``drop_last``).  Each batch is sorted: the order inside a batch does not
       matter to a training step, and sorted indices are read without reordering copies.
    """
    sizes = np.asarray(shard_sizes, dtype=np.int64).reshape(-1)
    check_batch_size(batch_size)
    if block_size is None or int(block_size) <= 0:
        raise UserError(f"block size must be positive, got {block_size}")
    if part_count <= 0 or not 0 <= part_index < part_count:
        raise UserError(f"part index {part_index} is not in [0, {part_count})")
    check_remainder(remainder)
    batch_size, block_size = int(batch_size), int(block_size)
    seed, epoch = check_seed("seed", seed), check_seed("epoch", epoch)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    starts = np.concatenate([np.arange(o, o + n, block_size) for o, n in zip(offsets[:-1], sizes)] or [np.zeros(0, np.int64)])
    shard_end = np.repeat(offsets[1:], -(-sizes // block_size))
    stops = np.minimum(starts + block_size, shard_end)
    nb = len(starts)
    order = np.random.default_rng([seed, epoch, PLAN_STREAM]).permutation(nb) if shuffle else np.arange(nb)
    lengths = (stops - starts)[order]
    n = int(lengths.sum())
    a, b = part_bounds(n, part_count, part_index, remainder)
    pos = np.arange(a, b, dtype=np.int64) % max(n, 1)  # positions in the sequence ("pad" wraps around)
    first = np.concatenate([[0], np.cumsum(lengths)])  # sequence position of each (ordered) block's first image
    k = np.searchsorted(first, pos, side="right") - 1
    idx = (starts[order][k] + pos - first[k]).astype(np.int64) if len(pos) else np.zeros(0, np.int64)
    batches = [idx[i : i + batch_size] for i in range(0, len(idx), batch_size)]
    if drop_last and batches and len(batches[-1]) < batch_size:
        batches.pop()
    return [np.sort(b) for b in batches]
