"""Data loaders over the HDF5 shards.

* :mod:`.reader` (numpy only, always importable): :class:`ShardReader` random access across
  splits and classes, :func:`plan_epoch` (shuffling and sharding shared by every loader).
* :mod:`.torch` (PyTorch: ``pip install torch --index-url https://download.pytorch.org/whl/cpu``):
  ``DepthDataset``, ``ShardIterableDataset``, ``EpochBatchSampler``, ``make_loader``; ``depth``
  channels-first ``(B, 1, H, W)``.
* :mod:`.jax` (``pip install -e ".[jax]"`` from the checkout): ``ShardDataSource`` (grain data
  source), ``JaxLoader``, ``device_put``; ``depth`` channels-last ``(B, H, W, 1)``.

Both loaders give every rank (process) the same number of batches (``remainder="pad"``, as
``DistributedSampler``), batches that do not depend on the number of workers, and ``K`` as float32.

Importing this package imports neither torch nor jax; import the submodules explicitly.
See docs/loaders.md.
"""

from articulated_dataset.training.loaders.batch import BatchProcessor, load_batch
from articulated_dataset.training.loaders.epoch import DEFAULT_BLOCK_SIZE, REMAINDER_MODES, plan_epoch
from articulated_dataset.training.loaders.reader import DEFAULT_FIELDS, NUMERIC_FIELDS, ShardReader

__all__ = ["ShardReader", "plan_epoch", "BatchProcessor", "load_batch", "DEFAULT_FIELDS", "NUMERIC_FIELDS",
           "DEFAULT_BLOCK_SIZE", "REMAINDER_MODES"]
