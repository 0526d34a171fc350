"""The dense estimator's data: a split held in memory at the model resolution
(:class:`DenseData`, read by :func:`load_dense_split`), for training and for prediction.

Depth is held as uint16 in units of :data:`DEPTH_STORE_QUANTUM_M` (41 KB per 192x108 image,
2.7 GB for 4,000 objects x 16 images); part labels at the network's output resolution; the
labels as the loss reads them (axis origin, axis frame as 6-D, q, part offset, geometry).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from articulated_dataset.core.errors import DataFormatError, UserError, option

if TYPE_CHECKING:
    import torch

#: Depth held in memory as uint16 multiples of this (m): 8 m range, 0.12 mm steps (the shards' quantum).
DEPTH_STORE_QUANTUM_M = 1.0 / 8192
#: Images read from a shard at a time.
LOAD_CHUNK = 256
#: The arrays each shard contributes to a :class:`DenseData` (before the labels' conversion).
_COLUMNS = ("depth_q", "K", "labels_out", "axis_pose", "q", "part_offset", "geometry", "object_index", "sample_id",
            "shard_of")


@dataclass
class DenseData:
    """A split in memory, at the model resolution."""

    depth_q: np.ndarray  # (N, H, W) uint16, DEPTH_STORE_QUANTUM_M units, 0 = no return
    K: np.ndarray  # (N, 3, 3) float32, scaled to the model resolution
    labels_out: np.ndarray | None  # (N, h, w) uint8 part labels at the output resolution
    origin: np.ndarray | None  # (N, J, 3) m
    rot6: np.ndarray | None  # (N, J, 6): axis (frame z) and frame x
    q: np.ndarray | None  # (N, J)
    part_offset: np.ndarray | None  # (N, J, 3) m
    geometry: np.ndarray | None  # (N, 4)
    object_index: np.ndarray
    sample_id: np.ndarray
    shard_of: np.ndarray

    def depth(self, idx) -> torch.Tensor:
        import torch

        return torch.from_numpy(self.depth_q[idx].astype(np.float32) * DEPTH_STORE_QUANTUM_M)


def quantise_depth(depth_m: np.ndarray) -> np.ndarray:
    """Metres -> uint16 store units (``rint(d / DEPTH_STORE_QUANTUM_M)``); returns too far (> 8 m),
    negative or non-finite depths as 0 (no return).  The quantum is a power of two, so ``d /
    quantum`` is exact in float32 and float32 depths are scaled in float32 (7x faster than in
    float64: a whole split is quantised as it is read; the same numbers)."""
    d = np.asarray(depth_m)
    q = np.multiply(d, 1.0 / DEPTH_STORE_QUANTUM_M, dtype=np.float32 if d.dtype == np.float32 else np.float64)
    np.rint(q, out=q)
    q[~((q >= 0) & (q <= np.iinfo(np.uint16).max))] = 0  # NaN compares false: 0 too
    return q.astype(np.uint16)


def split_object_indices(split_dir: Path, max_objects: int | None = None) -> np.ndarray:
    """The object index of every image of a split, in :func:`load_dense_split`'s order (read from
    the shards' ``object_index`` column only), those of the first ``max_objects`` objects."""
    from articulated_dataset.format import open_split
    from articulated_dataset.format.shards import Shard

    _, shards = open_split(split_dir)
    out = []
    for info in shards:
        sh = Shard(info.path)
        try:
            oi = np.asarray(sh.read("object_index"), np.int64)
        finally:
            sh.close()
        out.append(oi if max_objects is None else oi[oi < max_objects])
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def load_dense_split(split_dir: Path, n_joints: int, hw: tuple[int, int], *, max_objects: int | None = None,
                     objects: np.ndarray | None = None, with_labels: bool = True, object_mask: bool = False,
                     progress: bool = False, workers: int | None = None, prompt: str | tuple[str, ...] | None = None,
                     max_extent_m: float | None = None) -> DenseData:
    """Read a split into a :class:`DenseData` (labels only if ``with_labels``); ``objects``: only
    the images of these object indices (a refit reads its validation objects, not the split: a
    10,000-object split would take 13 GB on the way).  ``object_mask``:
    the depth outside the object's mask codes (body and parts) is set to no return, as a
    robot's object segmentation would leave it (scenes and occluders removed).  ``prompt`` (of
    :data:`~articulated_dataset.methods.prompts.PROMPT_KINDS`): each image's object segmented from
    the prompt a click or a detector would give (:func:`~articulated_dataset.methods.prompts.simulated_prompt`
    of its label mask, :func:`~articulated_dataset.methods.prompts.segment_from_prompt` with
    ``max_extent_m``) and the depth outside it set to no return; ``"mask"`` is ``object_mask``;
    a tuple of kinds: image with sample id ``i`` takes kind ``i % len(prompt)``.  ``workers`` > 1
    reads the shards in that many processes (the same arrays, in the same order); None: one per
    CPU for splits of at least :data:`~articulated_dataset.core.pool.PARALLEL_MIN_TASKS` shards."""
    from tqdm.auto import tqdm

    from articulated_dataset.core.pool import ordered_map
    from articulated_dataset.format import open_split
    from articulated_dataset.core.rotations import quat_to_matrix

    manifest, shards = open_split(split_dir)
    if not shards:
        raise DataFormatError(f"{split_dir}: the split has no shards")
    wanted = None if objects is None else np.unique(np.asarray(objects, np.int64))
    kinds = (prompt,) if isinstance(prompt, str) else tuple(prompt or ())
    if kinds == ("mask",):
        object_mask = True
    # per image: the label mask's object codes (object_mask), a segmentation from a simulated prompt, or all pixels
    keep_pixels = "mask" if object_mask else None if not kinds or (kinds == ("none",) and max_extent_m is None) \
        else (kinds, float(max_extent_m or 0.0))
    tasks = [(sh.path, s_idx, n_joints, tuple(hw), max_objects, with_labels, keep_pixels, wanted)
             for s_idx, sh in enumerate(shards)]
    bar = tqdm(total=int(manifest.get("n_images", 0)) or None, desc=f"loading {split_dir}", unit="img",
               disable=not progress, leave=False)
    parts = []
    for part in ordered_map(_load_shard, tasks, workers):
        bar.update(int(part["n_read"]))
        if part["object_index"] is not None:
            parts.append(part)
    bar.close()
    if not parts:
        raise UserError(f"{split_dir}: no images selected")
    from articulated_dataset.methods.inputs import check_split_has_depth

    n_valid = sum(p.get("n_valid", 0) for p in parts)
    if kinds == ("none",) and keep_pixels is not None and not n_valid and sum(p.get("n_raw_valid", 0) for p in parts):
        raise UserError(f"{split_dir}: no object was found in any image without a prompt; "
                        f"use {option('prompt')} point, box or mask")
    check_split_has_depth(split_dir, n_valid, sum(p["n_read"] for p in parts))
    cat: dict[str, Any] = {k: None if parts[0][k] is None else np.concatenate([p[k] for p in parts]) for k in _COLUMNS}
    origin = rot6 = None
    if with_labels:
        pose = cat["axis_pose"]
        R = quat_to_matrix(pose[..., 3:])
        origin = pose[..., :3].astype(np.float32)
        rot6 = np.concatenate([R[..., :, 2], R[..., :, 0]], -1).astype(np.float32)
    f32 = (lambda a: None if a is None else a.astype(np.float32))
    return DenseData(depth_q=cat["depth_q"], K=cat["K"], labels_out=cat["labels_out"], origin=origin, rot6=rot6,
                     q=f32(cat["q"]), part_offset=f32(cat["part_offset"]), geometry=f32(cat["geometry"]),
                     object_index=cat["object_index"], sample_id=cat["sample_id"], shard_of=cat["shard_of"])


def _load_shard(task) -> dict:
    """One shard's arrays for :func:`load_dense_split` (a top-level function: process workers run
    it): ``task`` = (path, shard index, n_joints, hw, max_objects, with_labels, object pixels kept (None, "mask" or
    (prompt kinds, max extent in m)), objects or None).
    ``object_index`` is None when no image of the shard is selected; ``n_read`` counts its images read."""
    import torch

    from articulated_dataset.format.shards import Shard
    from articulated_dataset.methods.inputs import valid_depth_images
    from articulated_dataset.methods.dense.features import output_labels, resize_depth, scale_intrinsics

    path, s_idx, n_joints, hw, max_objects, with_labels, object_mask, objects = task
    out: dict = dict.fromkeys(_COLUMNS)
    sh = Shard(path)
    try:
        J = sh.file["q"].shape[1]  # the shard's own shapes are consistent (Shard checks them): its J against the class's
        if J != n_joints:
            raise DataFormatError(f"{path}: labels of {J} joint(s) but the class has {n_joints}; "
                                  f"the shard does not belong to this split")
        oi = sh.read("object_index")
        keep = np.ones(len(oi), bool) if max_objects is None else oi < max_objects
        if objects is not None:
            keep &= np.isin(oi, objects)
        idx = np.nonzero(keep)[0]
        out["n_read"] = len(idx)
        if len(idx) == 0:
            return out
        K = np.asarray(sh.K, np.float64)
        sample_id = np.asarray(sh.read("sample_id")).astype(np.int64)
        cols: dict[str, list] = {"depth_q": [], "K": [], "labels_out": []}
        for start in range(0, len(idx), LOAD_CHUNK):
            sel = idx[start : start + LOAD_CHUNK]
            rows = slice(int(sel[0]), int(sel[-1]) + 1)
            depth = sh.read("depth", rows)[sel - sel[0]]
            if object_mask == "mask":
                from articulated_dataset.format import MASK_BODY

                m = sh.read("mask", rows)[sel - sel[0]]
                depth = np.where((m >= MASK_BODY) & (m <= MASK_BODY + n_joints), depth, 0)
            elif object_mask is not None:
                from articulated_dataset.methods.prompts import prompted_depth

                out["n_raw_valid"] = out.get("n_raw_valid", 0) + int(valid_depth_images(depth).sum())
                kinds, extent_m = object_mask
                m = sh.read("mask", rows)[sel - sel[0]]
                depth = np.stack([prompted_depth(d_i, K, kinds[int(s_i) % len(kinds)], m_i, max_extent_m=extent_m)
                                  for d_i, m_i, s_i in zip(depth, m, sample_id[sel])])
            out["n_valid"] = out.get("n_valid", 0) + int(valid_depth_images(depth).sum())
            src_hw = depth.shape[1:]
            if tuple(src_hw) != tuple(hw):
                depth = resize_depth(torch.from_numpy(np.asarray(depth, np.float32)), hw).numpy()
            cols["depth_q"].append(quantise_depth(depth))
            cols["K"].append(np.repeat(scale_intrinsics(K, src_hw, hw)[None].astype(np.float32), len(sel), 0))
            if with_labels:
                mask = sh.read("mask", rows)[sel - sel[0]]
                if tuple(src_hw) != tuple(hw):
                    mask = torch.nn.functional.interpolate(torch.from_numpy(mask[:, None]).float(), size=hw,
                                                           mode="nearest")[:, 0].numpy().astype(np.uint8)
                cols["labels_out"].append(output_labels(mask, n_joints))
        for k, v in cols.items():
            out[k] = np.concatenate(v) if v else None
        if with_labels:
            for k in ("axis_pose", "q", "part_offset", "geometry"):
                out[k] = np.asarray(sh.read(k), np.float64)[idx]
        out["object_index"] = oi[idx].astype(np.int64)
        out["sample_id"] = sample_id[idx]
        out["shard_of"] = np.full(len(idx), s_idx)
        return out
    finally:
        sh.close()


def concat_dense_data(parts: list[DenseData]) -> DenseData:
    """Several splits' :class:`DenseData` as one, in order; each split's object indices shifted
    past the previous splits' (its objects stay distinct from theirs), ``shard_of`` likewise."""
    from dataclasses import fields, replace

    obj_offset = shard_offset = 0
    shifted = []
    for part in parts:
        shifted.append(replace(part, object_index=part.object_index + obj_offset,
                               shard_of=part.shard_of + shard_offset))
        obj_offset += int(part.object_index.max()) + 1 if len(part.object_index) else 0
        shard_offset += int(part.shard_of.max()) + 1 if len(part.shard_of) else 0
    return DenseData(**{f.name: None if getattr(shifted[0], f.name) is None else  # type: ignore[arg-type]  # field by field
                        np.concatenate([getattr(p, f.name) for p in shifted]) for f in fields(DenseData)})


def mixture_order(pools: list[np.ndarray], weights: np.ndarray, n: int, gen: np.random.Generator) -> np.ndarray:
    """``n`` image indices drawn from the ``pools`` (one array of image indices per split) in
    proportion to ``weights``: each position picks its split with probability ``weights /
    weights.sum()``, and each split hands out its images in a fresh permutation, another
    permutation after it runs out (a small split weighted high repeats its images within an epoch)."""
    w = np.asarray(weights, np.float64)
    choice = gen.choice(len(pools), size=n, p=w / w.sum())
    order = np.empty(n, np.int64)
    for s, pool in enumerate(pools):
        at = np.nonzero(choice == s)[0]
        if not len(at):
            continue
        rounds = -(-len(at) // len(pool))
        order[at] = np.concatenate([gen.permutation(pool) for _ in range(rounds)])[: len(at)]
    return order
