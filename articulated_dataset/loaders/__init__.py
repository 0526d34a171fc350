"""Data loaders over the HDF5 shards.

* :mod:`.reader` (numpy only, always importable): :class:`ShardReader` random access across
  splits and classes, :func:`plan_epoch` (shuffling and sharding shared by every loader).
* :mod:`.torch` (``pip install torch==2.13.0``): ``DepthDataset``, ``ShardIterableDataset``,
  ``EpochBatchSampler``, ``make_loader``.
* :mod:`.jax` (``pip install ".[jax]"``): ``ShardDataSource`` (grain data source), ``JaxLoader``.

Importing this package imports neither torch nor jax; import the submodules explicitly.
See docs/loaders.md.
"""

from .reader import (
    DEFAULT_BLOCK_SIZE,
    DEFAULT_FIELDS,
    NUMERIC_FIELDS,
    BatchProcessor,
    ShardReader,
    load_batch,
    plan_epoch,
)

__all__ = ["ShardReader", "plan_epoch", "BatchProcessor", "load_batch", "DEFAULT_FIELDS", "NUMERIC_FIELDS",
           "DEFAULT_BLOCK_SIZE"]
