"""What every loader adds to a batch (:class:`BatchProcessor`): the seeded per-sample transform,
the (normalised) target vector and the sample indices; :func:`load_batch` reads and processes one."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.training.loaders.epoch import check_seed
from articulated_dataset.training.loaders.reader import ShardReader, index_array

#: Key of the global sample index that the loaders add to every batch.
INDEX_KEY = "index"
#: Key of the (normalised) target vector added when a TargetLayout is given.
TARGET_KEY = "target"


#: dtype of the intrinsics ``K`` in loader batches (the reader keeps the stored float64):
#: training code multiplies them with float32 tensors.
LOADER_K_DTYPE = np.float32


class BatchProcessor:
    """Applies the optional transform (per sample, seeded by ``(seed, epoch, index)``), adds the
    target vector (``target``, float32 (B, D), normalised if ``norm`` is given) and the global
    sample indices (``index``, int64), and gives ``K`` as :data:`LOADER_K_DTYPE`.

    ``epoch`` of :meth:`__call__` is an int, or, for a dataset whose epoch was never set, one key
    (a sequence of non-negative ints) per sample: see
    :func:`articulated_dataset.training.transforms.sample_rng`."""

    def __init__(self, fields: Sequence[str], *, transform=None, target=None, norm=None, seed: int = 0):
        self.transform = transform
        self.target = target
        self.norm = norm
        self.seed = check_seed("seed", seed)
        #: dtypes the reader allocates for fields whose loader dtype differs from the stored one
        self.dtypes = {"K": np.dtype(LOADER_K_DTYPE)} if "K" in fields else {}
        if norm is not None and target is None:
            raise UserError("normalisation statistics need a target layout (target=TargetLayout.for_class(...))")
        if target is not None:
            missing = [f for f in target.fields if f not in fields]
            if missing:
                raise UserError(f"the target vector needs the field(s) {', '.join(missing)}; add them to fields")
            if norm is not None:
                norm.check_layout(target)

    def __call__(self, batch: dict, indices: np.ndarray, epoch) -> dict:
        """``batch`` (field -> array) of the samples ``indices`` transformed, with ``target`` and ``index`` added and
        the configured dtypes restored."""
        indices = index_array(indices)
        if self.transform is not None:
            from articulated_dataset.training.transforms import apply_to_batch

            batch = apply_to_batch(self.transform, batch, indices, seed=self.seed, epoch=epoch)
        if self.target is not None:
            vec = self.target.encode(batch)
            batch[TARGET_KEY] = self.norm.normalize(vec) if self.norm is not None else vec
        for name, dtype in self.dtypes.items():
            if name in batch and batch[name].dtype != dtype:  # a transform made it float64 again
                batch[name] = batch[name].astype(dtype)
        batch[INDEX_KEY] = indices.copy()
        return batch


def load_batch(reader: ShardReader, processor: BatchProcessor, indices, epoch, alloc=None) -> dict:
    """Read and process one batch: the single code path of every loader."""
    indices = index_array(indices)
    return processor(reader.get_batch(indices, alloc=alloc, dtypes=processor.dtypes), indices, epoch)
