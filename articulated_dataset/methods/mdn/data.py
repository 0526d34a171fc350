"""Training data of the mixture density network: a split read into memory as model inputs
and encoded targets (:func:`load_split`), the validation objects held out of the training
split (:func:`split_by_object`), and the target columns made relative to the image anchor or
left out when constant."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from articulated_dataset.core.errors import DataFormatError, UserError, option
from articulated_dataset.format import Split, one_split_dir

if TYPE_CHECKING:
    import torch


#: Images preprocessed per chunk while loading (bounds the float32 temporaries).
LOAD_CHUNK = 512
#: A column is constant when its std is within this factor of the NormStats floor.
CONSTANT_COLUMN_TOLERANCE = 1.0 + 1e-6


@dataclass
class PreparedSplit:
    """A split reduced to model inputs, in memory (torch tensors, CPU)."""

    planes: torch.Tensor  # (N, 2, h, w) float16
    scalars: torch.Tensor  # (N, 1) float32
    targets: np.ndarray  # (N, D) float32, label units (encoded, not normalised)
    anchor: torch.Tensor  # (N, 3) float32, metres: centroid of the valid pixels (preprocess.image_anchor)
    object_index: np.ndarray  # (N,) int64
    sample_id: np.ndarray  # (N,) int64
    shard_of: np.ndarray | None = field(default=None)  # (N,) index of the shard each image came from


def resolve_split_dir(data: str | Path) -> Path:
    """The one split folder at ``data`` (a UserError if there is none or several)."""
    return one_split_dir(data)


def split_class(split_dir: Path) -> str:
    return Split(split_dir).class_name


def split_identity(split_dir: Path) -> dict | None:
    """What names a generated split, from its manifest: class, split name, seed and objects (None
    for a split without them, e.g. ingested captures); a checkpoint records it so that ``--resume``
    continues on the same split wherever its folder now is."""
    from articulated_dataset.format import read_manifest

    try:
        cfg = read_manifest(split_dir)["config"]
        return {"class_name": str(cfg["class_name"]), "split": str(cfg["split"]), "seed": int(cfg["seed"]),
                "n_objects": int(cfg["n_objects"])}
    except (KeyError, TypeError, ValueError, UserError):
        return None


def checked_split_class(split_dir: Path, model_class: str, as_class: str | None = None, what: str = "the model") -> str:
    """The class of the split at ``split_dir``, which a model trained on ``model_class`` predicts:
    the same class, or, with ``as_class`` (``predict --as-class``; it must be ``model_class``), a
    third-party split (``generate --urdf``) whose joint types are the class's, in order (a
    PartNet-Mobility microwave read as a microwave).  Returns the split's class, the predictions'
    group (``score`` compares them with the split's labels); anything else is a UserError."""
    from articulated_dataset.classes.registry import class_names, get_class

    data_class = split_class(split_dir)
    if as_class is not None and as_class != model_class:
        raise UserError(f"{option('as_class')} {as_class}: {what} was trained on {model_class!r}")
    if data_class == model_class:
        return data_class
    if as_class is None:
        hint = ("" if data_class in class_names()
                else f" (a third-party object of that class: pass {option('as_class')} {model_class})")
        raise UserError(f"{split_dir}: holds class {data_class!r} but {what} was trained on {model_class!r}{hint}")
    if data_class in class_names():
        raise UserError(f"{option('as_class')} {as_class}: {split_dir} holds the built-in class {data_class!r}; "
                        f"{option('as_class')} reads a third-party split (generate {option('urdf_path')}) as a class")
    types, expected = list(Split(split_dir).joint_types()), list(get_class(as_class).joint_types)
    if types != expected:
        raise UserError(f"{option('as_class')} {as_class}: {split_dir} has joints {types}, the {as_class!r} class "
                        f"{expected} (choose and order its joints with "
                        f"generate {option('urdf_path')} {option('joints')})")
    return data_class


def load_split(split_dir: Path, layout, input_config, *, max_objects: int | None = None, progress: bool = False,
               with_targets: bool = True, workers: int | None = 1) -> PreparedSplit:
    """Read every shard of ``split_dir`` and reduce it to model inputs (and encoded targets).
    ``workers``: processes reading the shards (:func:`~articulated_dataset.core.pool.ordered_map`;
    None: one per CPU for large splits); the result is the same.  One by default: the float16
    planes cross the process boundary by pickling, and on 2 cores two processes were no faster
    (16,000 images: 16.9 s against 15.1); many cores (a GPU machine's) gain."""
    import torch
    from tqdm.auto import tqdm

    from articulated_dataset.core.pool import ordered_map

    split = Split(split_dir)
    manifest, shards = split.manifest, split.shards
    if not shards:
        raise DataFormatError(f"{split_dir}: the split has no shards")
    tasks = [(sh.path, s_idx, layout, input_config, max_objects, with_targets) for s_idx, sh in enumerate(shards)]
    total = int(manifest.get("n_images", 0)) or None
    bar = tqdm(total=total, desc=f"loading {split_dir}", unit="img", disable=not progress, leave=False)
    parts = []
    for part in ordered_map(_load_shard, tasks, workers):
        bar.update(int(part["n_read"]))
        if part["n_read"]:
            parts.append(part)
    bar.close()
    if not parts:
        raise UserError(f"{split_dir}: no images selected")
    from articulated_dataset.methods.inputs import check_split_has_depth

    check_split_has_depth(split_dir, sum(p["n_valid"] for p in parts), sum(p["n_read"] for p in parts))

    def cat(key):
        return np.concatenate([p[key] for p in parts])

    return PreparedSplit(
        planes=torch.from_numpy(cat("planes")), scalars=torch.from_numpy(cat("scalars")),
        anchor=torch.from_numpy(cat("anchor")),
        targets=cat("targets") if with_targets else np.zeros((sum(p["n_read"] for p in parts), 0), np.float32),
        object_index=cat("object_index"), sample_id=cat("sample_id"), shard_of=cat("shard_of"),
    )


def _load_shard(task) -> dict:
    """One shard's part of :func:`load_split` as numpy arrays (a top-level function: process
    workers run it): ``task`` = (path, shard index, layout, input config, max_objects, with_targets)."""
    import torch

    from articulated_dataset.format.shards import Shard
    from articulated_dataset.methods.inputs import valid_depth_images
    from articulated_dataset.methods.mdn.preprocess import preprocess_depth

    path, s_idx, layout, input_config, max_objects, with_targets = task
    sh = Shard(path)
    try:
        oi = sh.read("object_index")
        keep = np.ones(len(oi), bool) if max_objects is None else oi < max_objects
        idx = np.nonzero(keep)[0]
        out: dict = {"n_read": len(idx)}
        if not len(idx):
            return out
        K = sh.K
        planes, scalars, anchors = [], [], []
        for start in range(0, len(idx), LOAD_CHUNK):
            sel = idx[start : start + LOAD_CHUNK]
            depth = sh.read("depth", slice(int(sel[0]), int(sel[-1]) + 1))[sel - sel[0]]
            out["n_valid"] = out.get("n_valid", 0) + int(valid_depth_images(depth).sum())
            p, s, a = preprocess_depth(depth, input_config, K)
            planes.append(p)
            scalars.append(s)
            anchors.append(a)
        out.update(planes=torch.cat(planes).numpy(), scalars=torch.cat(scalars).numpy(),
                   anchor=torch.cat(anchors).numpy())
        if with_targets:
            labels = {k: v[idx] for k, v in sh.labels().items()}
            out["targets"] = np.asarray(layout.encode(labels), np.float32)
        out.update(object_index=oi[idx].astype(np.int64), sample_id=sh.read("sample_id")[idx].astype(np.int64),
                   shard_of=np.full(len(idx), s_idx))
        return out
    finally:
        sh.close()


def split_by_object(object_index: np.ndarray, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks (train, val) over images: ``round(val_fraction * n_objects)`` objects (at
    least one when val_fraction > 0 and there are two objects or more), chosen by a
    permutation seeded with ``seed``, go to validation with all their images."""
    objects = np.unique(object_index)
    n_val = int(round(val_fraction * len(objects)))
    if val_fraction > 0 and len(objects) >= 2:
        n_val = min(max(n_val, 1), len(objects) - 1)
    else:
        n_val = 0
    perm = np.random.default_rng(seed).permutation(objects)
    val = np.isin(object_index, perm[:n_val])
    return ~val, val


def anchored_columns(names: list[str]) -> list[tuple[int, int]]:
    """``(column, axis)`` of every axis-origin column (``j{j}.origin.{x,y,z}``): these are
    predicted relative to the image anchor's coordinate ``axis`` (0, 1, 2 = x, y, z)."""
    out = []
    for c, n in enumerate(names):
        head, _, rest = n.partition(".")
        kind, _, comp = rest.partition(".")
        if kind == "origin" and comp in ("x", "y", "z"):
            out.append((c, "xyz".index(comp)))
    return out


def shift_anchored(y: np.ndarray, anchor_m: np.ndarray, anchored, sign: float) -> np.ndarray:
    """``y[..., c] + sign * anchor[:, axis]`` for each anchored ``(c, axis)``; ``y`` (N, ..., D)
    in label units, ``anchor_m`` (N, 3).  ``sign = -1`` makes targets anchor-relative,
    ``+1`` restores camera-frame labels."""
    out = np.array(y, dtype=np.float64, copy=True)
    a = np.asarray(anchor_m, np.float64)
    for c, axis in anchored:
        out[..., c] += sign * a[:, axis].reshape((-1,) + (1,) * (out.ndim - 2))
    return out


def active_columns(stats) -> np.ndarray:
    """Indices of the target columns the mixture models: those that vary in the training
    data.  A column whose standard deviation is at the NormStats floor (constant up to label
    precision, e.g. the x/y components of a vertical hinge axis or the chirality of a
    one-sided class) is not modelled: its normalised estimate is 0 (the training value) and
    its scale 1 (the floor, in label units).  Modelling it would let the likelihood grow
    without bound as its scales shrink, and its huge gradients would swamp the others."""
    std = np.asarray(stats.std, np.float64)
    return np.nonzero(std > stats.std_floor * CONSTANT_COLUMN_TOLERANCE)[0]


def expand_active(x: np.ndarray, active: np.ndarray, dim: int, fill: float) -> np.ndarray:
    """Arrays (..., len(active)) over the modelled columns -> (..., dim), other columns ``fill``."""
    out = np.full(x.shape[:-1] + (dim,), fill, dtype=np.float64)
    out[..., active] = x
    return out
