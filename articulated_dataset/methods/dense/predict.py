"""Inference of the dense estimator: splits (``artdata predict --model dense``) and single images.

For each image the vote modes of every joint (:func:`~articulated_dataset.methods.dense.aggregate.vote_modes`)
become mixture components over the class's target columns (:class:`~articulated_dataset.training.targets.TargetLayout`):
with ``J`` joints and ``M`` modes per joint the mixture has ``M**J`` components, one per
combination, weighted by the product of the modes' weights.  A component's standard
deviation in column ``d`` is ``sigma_d = sqrt((k_d s_d)^2 + f_d^2)`` where ``s_d`` is the
spread of its votes in that column and ``(k_d, f_d)`` the calibration fitted on the
training split's validation objects by maximum likelihood (:func:`fit_calibration`).  The
point estimate is the heaviest component's mean (never an average of modes).

Where the calibration holds an outlier component (:func:`fit_outlier_component`), one more
component follows the modes': centred on the point estimate, at least as wide as the class's spread
of every column (and a floor per kind of column), with a small weight fitted on the same
validation objects.  It stands for the
estimate's gross failures (a door's hinge put on the wrong side, a frame turned 180 deg), which
the modes' Gaussians, fitted to the far more numerous good estimates, would give a density of
zero: without the component one such image decides a class's mean NLL (the cabinet's: 1.4e6
nats on 3,200 selection images, its median -60).  The point estimate and the modes are unchanged.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict, cast

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.dense.data import DenseData

if TYPE_CHECKING:
    from articulated_dataset.methods.dense.checkpoint import DenseCheckpoint
    from articulated_dataset.methods.dense.refine import RefinementRecord

log = logging.getLogger(__name__)

#: Images per batch of inference (input features, vote modes, refinement).
PREDICT_BATCH = 128
#: ... of which the network takes this many at a time: the same numbers (each image's output is its
#: own), and a third faster on two CPU threads, whose caches and allocator hold the smaller activations.
NETWORK_CHUNK = 32
#: :func:`predict_split` shares a split among worker processes (:func:`default_workers`) where it
#: has at least this many images: a spawned worker costs about 2 s to start (importing torch), which
#: 4,096 drawer images (the fastest class with the mirror image) about repay on the 2-core machine.
PARALLEL_MIN_IMAGES = 4096
#: Images a worker process is sent at a time (uint16 depth: 21 MB at 192 x 108).
WORKER_TASK_IMAGES = 512
#: Weight given to a mode that does not exist (keeps log-weights finite), before renormalising.
MIN_COMPONENT_WEIGHT = 1e-9
#: Every class's joints are closed at q = 0 and open to positive q (the templates' URDF limits,
#: ``lower="0"``; the tests check every registered class's table): a vote mode's q below it, rad or
#: m, is read as closed (0.16% of the cabinet's seed-14 selection images had one, down to -19 deg).
Q_CLOSED = 0.0
#: Calibration grids: spread factors and floors (as fractions of the residuals' median).
CAL_SPREAD_FACTORS = np.geomspace(0.05, 50.0, 41)
CAL_FLOOR_FRACTIONS = np.concatenate([[0.0], np.geomspace(0.02, 5.0, 33)])
#: Scale floor of any column (label units) so densities stay finite.
MIN_SCALE = 1e-6
#: Split factors of the vote modes tried by :func:`choose_split_factor` (None: one mode per joint).
SPLIT_FACTOR_CANDIDATES = (1.5, 2.0, 3.0, 5.0, None)
#: ... which keeps the default unless another lowers the validation position error by this fraction.
SPLIT_MIN_GAIN = 0.01
#: The outlier component's weight (:func:`fit_outlier_component`) is fitted within these bounds:
#: at least a safety net for failures the validation images did not show, at most far below a
#: planning hypothesis's weight (``manipulation.estimators.HYPOTHESIS_MIN_WEIGHT``, 0.05) and below
#: the heaviest mode's (at least ``(1 - weight) / 4`` with two joints of two modes).
OUTLIER_WEIGHT_BOUNDS = (1e-4, 0.03)
#: ... starting from this weight, for at most this many rounds of expectation-maximisation, until
#: the validation NLL (nats per image) changes by less than the tolerance.
OUTLIER_INITIAL_WEIGHT = 0.01
OUTLIER_MAX_ROUNDS = 100
OUTLIER_TOLERANCE_NATS = 1e-6
#: :func:`fitted_calibration` alternates the modes' scales and the outlier component this many times.
OUTLIER_CALIBRATION_ROUNDS = 2
#: The outlier component's smallest scale per kind of target column (label units: m, unit-vector
#: components, rad or m for q, the chirality probability), where the class holds a column constant
#: and the validation images show no spread in it: a vertical hinge's axis is (0, 0, -1) in every
#: image, a door's part offset across the door about 0, a one-sided class's chirality 0 or 1.  An
#: estimate that failed outright may still move them (a microwave's frame flipped about its door:
#: the axis read as (0, 0, +1), off by 2; without this floor the test microwaves' and
#: refrigerators' NLL reaches ~10^6 nats).  Half the range of a unit vector's component and of the
#: chirality (a flipped axis is then 4 scales off: 8 nats), 5 cm, 0.1 rad (or 10 cm) of q.
OUTLIER_MIN_SCALES = {"origin": 0.05, "axis": 0.5, "xaxis": 0.5, "q": 0.1, "offset": 0.05,
                      "depth": 0.05, "width": 0.05, "height": 0.05, "chirality": 0.5}


class _OutlierRecordRequired(TypedDict):
    weight: float
    scale: list[float]
    n_images: int
    validation_nll: dict[str, float]


class OutlierRecord(_OutlierRecordRequired, total=False):
    """The outlier component of a calibration (:func:`fit_outlier_component`): its weight, its
    scale per target column (label units), the validation images it was fitted on and their mean
    NLL (nats per image) ``{"without", "with"}`` it; while fitting, each image's responsibility
    (N,), which the stored record leaves out."""

    responsibility: np.ndarray


class _CalibrationRecordRequired(TypedDict):
    spread_factor: list[float]
    floor: list[float]
    n_images: int


class CalibrationRecord(_CalibrationRecordRequired, total=False):
    """A dense checkpoint's ``"calibration"`` (:func:`fit_calibration`, :func:`fitted_calibration`):
    per target column the vote spread's factor ``k`` and the floor ``f`` (label units) of the
    modes' scales ``sqrt((k spread)^2 + f^2)``, the validation images fitted on, and the outlier
    component where one was fitted."""

    outlier: OutlierRecord


class InferenceFit(TypedDict):
    """What :func:`fit_inference` fits for a dense checkpoint beyond its weights: the refinement,
    the calibration, and the validation errors (cm, deg) of each choice made."""

    refinement: RefinementRecord
    calibration: CalibrationRecord
    refinement_report: dict


def _layout_names(J: int) -> list[str]:
    from articulated_dataset.training.targets import TargetLayout

    return TargetLayout("-", J).names


def predict_arrays(model, data, idx: np.ndarray, *, joint_types: list[str], calibration: CalibrationRecord | None,
                   refinement=None, batch_size: int = PREDICT_BATCH, progress: bool = False,
                   workers: int = 1) -> dict:
    """Predictions of ``model`` for the images ``idx`` of a :class:`~articulated_dataset.methods.dense.data.DenseData`.

    ``refinement``: the checkpoint's :class:`~articulated_dataset.methods.dense.refine.Refinement` (or
    its dict) applied to the vote modes, or None.  ``workers`` > 1: the images are shared among
    that many spawned processes (:func:`_predict_in_workers`), each running this process's torch
    threads divided among them; the same predictions to float rounding.  Returns the datasets of
    :func:`articulated_dataset.benchmark.predictions.write_predictions` (``sample_id``, ``axis_pose``,
    ``q``, ``geometry``, ``part_offset``, ``mixture_*``, ``mixture_layout``) plus ``spread``
    (N, M, D), the raw vote spreads.
    """
    from articulated_dataset.methods.dense.refine import as_refinement

    refinement = as_refinement(refinement)
    if workers > 1 and len(idx) > batch_size:
        modes = _predict_in_workers(model, data, idx, joint_types, refinement, batch_size, workers, progress)
    else:
        modes = _refined_images(model, data, idx, joint_types, refinement, batch_size, progress)
    return modes_to_arrays(modes, data.sample_id[idx], model, calibration)


def _refined_images(model, data, idx: np.ndarray, joint_types: list[str], refinement, batch_size: int,
                    progress: bool) -> dict:
    """:func:`refined_batch` over the images ``idx`` of ``data``, batch by batch, concatenated."""
    return _concatenated(_over_batches(data, idx, batch_size, progress, lambda depth, K, workspace: refined_batch(
        model, depth, K, joint_types=joint_types, refinement=refinement, workspace=workspace)))


def default_workers(n_images: int) -> int:
    """Worker processes :func:`predict_split` shares ``n_images`` among: one per torch thread of
    this process (up to the usable CPUs) where there are at least :data:`PARALLEL_MIN_IMAGES`, else
    1 (this process).  Processes rather than threads: much of the pipeline (the vote modes, the
    refinement) is small tensor operations that one thread runs as fast as two: on the 2-core
    machine two 1-thread processes predicted 16,000 test images 1.7-1.9x as fast as one 2-thread
    process (microwave 790 against 412 images/s, drawer 543 against 314; docs/dense.md, "Speed")."""
    import torch

    from articulated_dataset.core.pool import usable_cpus

    if n_images < PARALLEL_MIN_IMAGES:
        return 1
    return max(1, min(torch.get_num_threads(), usable_cpus()))


@dataclass
class _Images:
    """The depth (store units) and intrinsics of some images: what inference reads of a
    :class:`~.data.DenseData` (a worker's task)."""

    depth_q: np.ndarray
    K: np.ndarray
    depth = DenseData.depth


#: A worker process's model, joint types and refinement (:func:`_init_worker`).
_WORKER: dict = {}


def _init_worker(model, joint_types: list[str], refinement, threads: int) -> None:
    import torch

    from articulated_dataset.core.pool import configure_allocator

    configure_allocator()
    torch.set_num_threads(threads)
    _WORKER.update(model=model, joint_types=joint_types, refinement=refinement)


def _predict_task(task: tuple) -> dict:
    """A worker's images (depth in store units, K, batch size) -> their refined vote modes."""
    depth_q, K, batch_size = task
    w = _WORKER
    return _refined_images(w["model"], _Images(depth_q, K), np.arange(len(depth_q)), w["joint_types"],
                           w["refinement"], batch_size, False)


def _predict_in_workers(model, data, idx: np.ndarray, joint_types: list[str], refinement, batch_size: int,
                        workers: int, progress: bool) -> dict:
    """:func:`_refined_images` of the images ``idx``, :data:`WORKER_TASK_IMAGES` at a time in
    ``workers`` spawned processes (:func:`~articulated_dataset.core.pool.process_map`, in order),
    each with this process's torch threads divided among them (at least one)."""
    import torch
    from tqdm.auto import tqdm

    from articulated_dataset.core.pool import process_map

    task_images = max(batch_size, WORKER_TASK_IMAGES // batch_size * batch_size)  # whole batches
    starts = range(0, len(idx), task_images)
    tasks = ((data.depth_q[idx[s : s + task_images]], data.K[idx[s : s + task_images]], batch_size) for s in starts)
    threads = max(1, torch.get_num_threads() // workers)
    chunks = []
    with tqdm(total=len(idx), desc="predicting", unit="image", disable=not progress, leave=False) as bar:
        for modes in process_map(_predict_task, tasks, min(workers, len(starts)), ordered=True,
                                 initializer=_init_worker, initargs=(model, joint_types, refinement, threads),
                                 died="a prediction worker process died (killed or out of memory?)"):
            chunks.append(modes)
            bar.update(len(next(iter(modes.values()))))
    return _concatenated(chunks)


def _over_batches(data, idx: np.ndarray, batch_size: int, progress: bool, fn) -> list:
    """``fn(depth_m, K, workspace)`` of every batch of the images ``idx`` of a split in memory, in
    order (``workspace``: one dict for the whole loop, see :func:`batch_modes`)."""
    import torch
    from tqdm.auto import tqdm

    out: list = []
    workspace: dict = {}
    for s in tqdm(range(0, len(idx), batch_size), desc="predicting", unit="batch", disable=not progress, leave=False):
        b = idx[s : s + batch_size]
        out.append(fn(data.depth(b), torch.from_numpy(data.K[b]), workspace))
    return out


def _concatenated(chunks: list) -> dict:
    """Per-batch dicts of arrays -> one dict, concatenated along the images."""
    return {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}


def refined_batch(model, depth_m, K, *, joint_types: list[str], refinement, workspace: dict | None = None) -> dict:
    """One batch of depth images (B, H, W) m and intrinsics (B, 3, 3) at the model's resolution ->
    the refined vote modes (numpy) the checkpoint's ``refinement`` (a
    :class:`~.refine.Refinement`, its dict or None) asks for: :func:`batch_modes` (where it names
    ``mirror_joints``, on the network's outputs averaged with its outputs on the mirror images:
    step 8, :mod:`.mirror`), then :func:`~.refine.apply_refinement` (steps 1-7)."""
    from articulated_dataset.methods.dense.refine import apply_refinement, as_refinement, split_factor_of

    refinement = as_refinement(refinement)
    m, r = batch_modes(model, depth_m, K, joint_types=joint_types,
                       refine=refinement is not None and refinement.needed, split_factor=split_factor_of(refinement),
                       mirror_joints=None if refinement is None else refinement.mirror_joints, workspace=workspace,
                       **refinement_keywords_of(refinement))
    return apply_refinement(m, r, refinement, joint_types)  # type: ignore[arg-type]  # r is None only when unread


def modes_to_arrays(m: dict, sample_id: np.ndarray, model, calibration: CalibrationRecord | None) -> dict:
    """Mode arrays of ``model`` (numpy) -> prediction arrays (:func:`mixture_from_modes`)."""
    from articulated_dataset.methods.dense.aggregate import MAX_MODES

    return mixture_from_modes(m, sample_id, model.config.n_joints, MAX_MODES, calibration)


def refinement_keywords(*, handle_max_q_deg: float | None = None, frame_min_prob: float | None = None,
                        door_angles: tuple[str, ...] | None = None, frame_one_sided: bool = False,
                        frame_strip_elongation: float | None = None) -> dict:
    """The keywords of :func:`~.refine.refined_quantities` for one candidate refinement: with
    ``handle_max_q_deg``, also the handles of the doors whose angle may be below it
    (:func:`~.handle.handle_evidence`); ``frame_min_prob``: the box frame's pixel threshold,
    :attr:`~.refine.Refinement.frame_min_prob`; ``frame_one_sided``:
    :attr:`~.refine.Refinement.frame_one_sided`; ``frame_strip_elongation``:
    :attr:`~.refine.Refinement.frame_strip_elongation`; ``door_angles``: step 5's angles to
    compute, None: all."""
    from articulated_dataset.methods.dense.refine import DOOR_ANGLES

    return dict(frame_min_prob=frame_min_prob, door_angles=DOOR_ANGLES if door_angles is None else door_angles,
                handle_max_q_deg=handle_max_q_deg, frame_one_sided=frame_one_sided,
                frame_strip_elongation=frame_strip_elongation)


def refinement_keywords_of(refinement) -> dict:
    """The arguments of :func:`refinement_keywords` that a checkpoint's
    :class:`~.refine.Refinement` (None: none) asks for: the handles, box-frame pixels, normals,
    strip and door angles its steps read."""
    if refinement is None:
        return {}
    return dict(handle_max_q_deg=refinement.handle_evidence_max_q_deg, frame_min_prob=refinement.frame_min_prob,
                door_angles=refinement.door_angles, frame_one_sided=refinement.frame_one_sided,
                frame_strip_elongation=refinement.frame_strip_elongation)


def batch_modes(model, depth_m, K, *, joint_types: list[str], refine: bool, split_factor: float | None,
                mirror_joints=None, workspace: dict | None = None, **refinement) -> tuple[dict, dict | None]:
    """One batch of depth images (B, H, W) m and intrinsics (B, 3, 3) at the model's resolution ->
    vote modes (:func:`~.aggregate.vote_modes` with ``split_factor``, a checkpoint's
    :func:`~.refine.split_factor_of`) and, with ``refine``, the refined quantities
    (:func:`~.refine.refined_quantities` with ``refinement``, the keywords of
    :func:`refinement_keywords`), as float64 numpy arrays: :func:`batch_candidates` of one candidate.
    ``workspace``: see :func:`batch_candidates`."""
    m, rs = batch_candidates(model, depth_m, K, joint_types=joint_types, split_factor=split_factor,
                             mirror_joints=mirror_joints, workspace=workspace,
                             candidates={0: refinement_keywords(**refinement)} if refine else {})
    return m, rs.get(0)


def batch_candidates(model, depth_m, K, *, joint_types: list[str], split_factor: float | None, candidates: dict,
                     mirror_joints=None, workspace: dict | None = None) -> tuple[dict, dict]:
    """One batch of depth images (B, H, W) m and intrinsics (B, 3, 3) at the model's resolution ->
    the vote modes (:func:`~.aggregate.vote_modes` with ``split_factor``; the network's outputs
    averaged with its outputs on the mirror images where ``mirror_joints`` is given) and, for each of
    ``candidates`` ({name: :func:`refinement_keywords`}), the refined quantities
    (:func:`~.refine.refined_quantities`), as float64 numpy arrays ``(modes, {name: quantities})``:
    the network and the vote modes run once, the refinement once per candidate (how
    :func:`fit_inference` compares refinements).  ``workspace``: a dict a loop over batches passes
    to every call, which keeps the network input's tensor for the next batch to write into (a fresh
    one costs more in page faults than filling it)."""
    import torch

    from articulated_dataset.methods.dense.aggregate import vote_modes
    from articulated_dataset.methods.dense.features import make_inputs
    from articulated_dataset.methods.dense.refine import refined_quantities

    if model.training:
        model.eval()
    with torch.inference_mode():
        inputs = make_inputs(depth_m, K, out=None if workspace is None else workspace.pop("x", None))
        out = network_outputs(model, inputs["x"], mirror_joints)
        if not bool(torch.isfinite(out).all()):  # finite weights can still overflow float32 (e.g. 1e38)
            raise UserError("the model's network gives NaN or infinite outputs: its checkpoint's weights overflow "
                            "float32 arithmetic (a damaged or foreign checkpoint)")
        parts = model.split(out)
        modes = vote_modes(parts, inputs["points_out"], inputs["weight_out"] > 0, split_factor=split_factor)
        rs = {name: refined_quantities(parts, inputs, modes, joint_types, **kw) for name, kw in candidates.items()}
    if workspace is not None:
        workspace["x"] = inputs["x"]
    as_np = lambda d: {k: v.numpy().astype(np.float64) for k, v in d.items()}  # noqa: E731
    return as_np(modes), {name: as_np(r) for name, r in rs.items()}


def network_outputs(model, x, mirror_joints=None):
    """``model(x)`` for a batch of inputs, :data:`NETWORK_CHUNK` images at a time; with
    ``mirror_joints``, averaged with its outputs on the mirror images
    (:func:`~.mirror.merge_mirrored_outputs`)."""
    import torch

    from articulated_dataset.methods.dense.mirror import merge_mirrored_outputs, mirror_network_input

    def run(inputs, prepare=lambda chunk: chunk):  # prepare: what each chunk's input is made into
        if len(inputs) <= NETWORK_CHUNK:
            return model(prepare(inputs))
        return torch.cat([model(prepare(chunk)) for chunk in inputs.split(NETWORK_CHUNK)])

    if mirror_joints is None:
        return run(x)
    if 2 * len(x) <= NETWORK_CHUNK:  # a few images (estimate()): one call for both, its fixed costs paid once
        both = run(torch.cat([x, mirror_network_input(x)]))
        out, out_mirror = both[: len(x)], both[len(x) :]
    else:  # the mirror input made a chunk at a time, while the chunk is in the caches (and without
        # executors.configure_allocator a batch's, 95 MB, would be fresh pages every time)
        out, out_mirror = run(x), run(x, mirror_network_input)
    return merge_mirrored_outputs(out, out_mirror, model.config.n_joints, mirror_joints)


def predict_modes(model, data, idx: np.ndarray, *, joint_types: list[str], refine: bool = True,
                  batch_size: int = PREDICT_BATCH, progress: bool = False, split_factor: float | None,
                  mirror_joints=None, **refinement) -> tuple[dict, dict | None]:
    """:func:`batch_modes` over the images ``idx`` of a split in memory, batch by batch, concatenated
    (the refined quantities are None without ``refine``; ``refinement``: the keywords of
    :func:`refinement_keywords`)."""
    m, rs = predict_candidates(model, data, idx, joint_types=joint_types, split_factor=split_factor,
                               candidates={0: refinement_keywords(**refinement)} if refine else {},
                               mirror_joints=mirror_joints, batch_size=batch_size, progress=progress)
    return m, rs.get(0)


def predict_candidates(model, data, idx: np.ndarray, *, joint_types: list[str], split_factor: float | None,
                       candidates: dict, mirror_joints=None, batch_size: int = PREDICT_BATCH,
                       progress: bool = False) -> tuple[dict, dict]:
    """:func:`batch_candidates` over the images ``idx`` of a split in memory, batch by batch,
    concatenated: ``(modes, {name: refined quantities})``."""
    chunks = _over_batches(data, idx, batch_size, progress, lambda depth, K, workspace: batch_candidates(
        model, depth, K, joint_types=joint_types, split_factor=split_factor, candidates=candidates,
        mirror_joints=mirror_joints, workspace=workspace))
    return (_concatenated([m for m, _ in chunks]),
            {name: _concatenated([rs[name] for _, rs in chunks]) for name in candidates})


def mixture_from_modes(m: dict, sample_id: np.ndarray, J: int, n_modes: int,
                       calibration: CalibrationRecord | None) -> dict:
    """Mode arrays of :func:`vote_modes` (numpy) -> prediction arrays with a mixture (``m`` is not changed)."""
    m = dict(m)
    N = len(sample_id)
    w = m["weight"].copy()  # (N, J, M)
    unused = w <= 0
    for key in ("origin", "axis", "xaxis", "part_offset", "origin_std", "axis_std", "xaxis_std", "offset_std"):
        m[key] = np.where(unused[..., None], m[key][:, :, :1], m[key])
    for key in ("q", "q_std"):
        m[key] = np.where(unused, m[key][:, :, :1], m[key])
    m["q"] = np.maximum(m["q"], Q_CLOSED)  # a joint is never closed past its closed state
    w = np.maximum(w, MIN_COMPONENT_WEIGHT)
    w /= w.sum(-1, keepdims=True)
    combos = list(itertools.product(range(n_modes), repeat=J))
    C = len(combos)
    D = 13 * J + 4
    means = np.zeros((N, C, D))
    spread = np.zeros((N, C, D))
    weights = np.ones((N, C))
    for c, combo in enumerate(combos):
        for j, k in enumerate(combo):
            o = 13 * j
            means[:, c, o : o + 3] = m["origin"][:, j, k]
            means[:, c, o + 3 : o + 6] = m["axis"][:, j, k]
            means[:, c, o + 6 : o + 9] = m["xaxis"][:, j, k]
            means[:, c, o + 9] = m["q"][:, j, k]
            means[:, c, o + 10 : o + 13] = m["part_offset"][:, j, k]
            spread[:, c, o : o + 3] = m["origin_std"][:, j, k]
            spread[:, c, o + 3 : o + 6] = m["axis_std"][:, j, k]
            spread[:, c, o + 6 : o + 9] = m["xaxis_std"][:, j, k]
            spread[:, c, o + 9] = m["q_std"][:, j, k]
            spread[:, c, o + 10 : o + 13] = m["offset_std"][:, j, k]
            weights[:, c] *= w[:, j, k]
        means[:, c, 13 * J :] = m["geometry"]
        spread[:, c, 13 * J :] = m["geometry_std"]
    weights /= weights.sum(-1, keepdims=True)
    scales = apply_calibration(spread, calibration)
    best = weights.argmax(-1)
    point = means[np.arange(N), best]  # (N, D)
    outlier = None if calibration is None else calibration.get("outlier")
    if outlier is not None:  # the last component (module docstring): after the point estimate is chosen
        weights, means, scales, spread = with_outlier_component(weights, means, scales, spread, point, outlier)
    from articulated_dataset.training.targets import TargetLayout

    decoded = TargetLayout("-", J).decode(point)
    from articulated_dataset.benchmark.predictions import bounded_geometry

    geometry = bounded_geometry(decoded["geometry"])
    return {
        "sample_id": np.asarray(sample_id, np.int64),
        "axis_pose": np.asarray(decoded["axis_pose"], np.float64),
        "q": np.asarray(decoded["q"], np.float64),
        "geometry": geometry,
        "part_offset": np.asarray(decoded["part_offset"], np.float64),
        "mixture_weights": weights, "mixture_means": means, "mixture_scales": scales,
        "mixture_layout": _layout_names(J), "spread": spread,
    }


def apply_calibration(spread: np.ndarray, calibration: CalibrationRecord | None) -> np.ndarray:
    """``sigma = sqrt((k spread)^2 + f^2)`` per column (k = 1, f = 0 without calibration)."""
    D = spread.shape[-1]
    k = np.ones(D) if calibration is None else np.asarray(calibration["spread_factor"], np.float64)
    f = np.zeros(D) if calibration is None else np.asarray(calibration["floor"], np.float64)
    return np.maximum(np.sqrt((k * spread) ** 2 + f**2), MIN_SCALE)


def truth_columns(data, idx: np.ndarray) -> np.ndarray:
    """Target vectors (N, D) of the images ``idx`` (layout order)."""
    J = data.origin.shape[1]
    cols = [np.concatenate([data.origin[idx, j], data.rot6[idx, j, :3], data.rot6[idx, j, 3:], data.q[idx, j, None],
                            data.part_offset[idx, j]], -1) for j in range(J)]
    return np.concatenate(cols + [data.geometry[idx]], -1).astype(np.float64)


def fit_calibration(arrays: dict, data, idx: np.ndarray, image_weights: np.ndarray | None = None) -> CalibrationRecord:
    """Per column ``(k, f)`` maximising the Gaussian likelihood of the heaviest component's
    residuals on the validation images (grids :data:`CAL_SPREAD_FACTORS`, :data:`CAL_FLOOR_FRACTIONS`),
    each image's log-likelihood weighted by ``image_weights`` (N,) where given (the share of the
    image the modes explain rather than the outlier component: :func:`fitted_calibration`)."""
    y = truth_columns(data, idx)
    N = len(idx)
    image_w = np.ones(N) if image_weights is None else np.asarray(image_weights, np.float64)
    best = arrays["mixture_weights"].argmax(-1)
    mu = arrays["mixture_means"][np.arange(N), best]
    s = arrays["spread"][np.arange(N), best]
    res = y - mu
    ok = np.isfinite(res)
    D = y.shape[1]
    k_out, f_out = np.ones(D), np.full(D, MIN_SCALE)
    for d in range(D):
        r, sd, iw = res[ok[:, d], d], s[ok[:, d], d], image_w[ok[:, d]]
        if len(r) == 0 or not iw.sum() > 0:
            continue
        iw = iw / iw.sum()
        med = max(float(np.median(np.abs(r))), MIN_SCALE)
        best_nll = np.inf
        for k in CAL_SPREAD_FACTORS:
            for ff in CAL_FLOOR_FRACTIONS:
                sig = np.maximum(np.sqrt((k * sd) ** 2 + (ff * med) ** 2), MIN_SCALE)
                nll = float(np.dot(iw, np.log(sig) + 0.5 * (r / sig) ** 2))
                if nll < best_nll:
                    best_nll, k_out[d], f_out[d] = nll, k, max(ff * med, MIN_SCALE)
    return {"spread_factor": [float(v) for v in k_out], "floor": [float(v) for v in f_out], "n_images": int(N)}


def with_outlier_component(weights: np.ndarray, means: np.ndarray, scales: np.ndarray, spread: np.ndarray,
                           point: np.ndarray, outlier: OutlierRecord) -> tuple[np.ndarray, ...]:
    """A mixture (weights (N, C), means and scales (N, C, D)) and its vote spreads with the outlier
    component of :func:`fit_outlier_component` appended: weight ``eps`` (the others scaled by
    ``1 - eps``), mean ``point`` (N, D), scales ``outlier["scale"]`` (D,), spread 0."""
    eps = float(outlier["weight"])
    N, _, D = means.shape
    scale = np.broadcast_to(np.asarray(outlier["scale"], np.float64), (N, 1, D))
    return (np.concatenate([weights * (1.0 - eps), np.full((N, 1), eps)], 1),
            np.concatenate([means, point[:, None]], 1), np.concatenate([scales, scale], 1),
            np.concatenate([spread, np.zeros((N, 1, D))], 1))


def outlier_scale_floors(layout: list[str]) -> np.ndarray:
    """:data:`OUTLIER_MIN_SCALES` of each column of a mixture layout (names such as ``j0.axis.z``,
    ``j1.q``, ``geometry.chirality``: the kind is the second part)."""
    return np.array([OUTLIER_MIN_SCALES[name.split(".")[1]] for name in layout], np.float64)


def fit_outlier_component(arrays: dict, y: np.ndarray) -> OutlierRecord:
    """The outlier component of a calibrated mixture (module docstring), fitted on validation
    images: ``arrays`` their predictions (:func:`mixture_from_modes` with the calibration,
    without an outlier component), ``y`` (N, D) their target vectors (:func:`truth_columns`;
    images with an undefined column are left out).

    With the mixture's density ``p(y)`` and the point estimate ``m``, the model is
    ``(1 - eps) p(y) + eps N(y; m, diag(s^2))``.  Expectation-maximisation: each image's
    responsibility ``g = eps N / ((1 - eps) p + eps N)``; then ``eps = mean(g)`` (within
    :data:`OUTLIER_WEIGHT_BOUNDS`) and ``s_d^2 = sum g r_d^2 / sum g`` with ``r = y - m``, but
    never below the floor ``s0_d = max(std of y_d, rms of r_d, c_d)`` over the images: the class's
    own spread of the column (what an estimate that failed outright is off by), the estimates'
    error, or the column kind's :data:`OUTLIER_MIN_SCALES` (``c_d``, where ``arrays`` names its
    ``mixture_layout``; for the columns the class holds constant), whichever is largest, so the
    component stays a broad one even where the validation images show no failure.  Starts from
    ``eps`` = :data:`OUTLIER_INITIAL_WEIGHT` and ``s = s0``.

    Returns ``{"weight", "scale" (D,), "n_images", "validation_nll": {"without", "with"},
    "responsibility"}``: the mean NLL (nats per image) of the mixture without and with the
    component, and each image's responsibility ``g`` (N,; 0 for the images left out)."""
    from articulated_dataset.benchmark.metrics import mixture_nll

    ok = np.isfinite(y).all(-1)
    if not ok.any():
        raise ValueError("no validation image with every target column defined")
    w, mu, sigma, y = (arrays["mixture_weights"][ok], arrays["mixture_means"][ok], arrays["mixture_scales"][ok],
                       np.asarray(y, np.float64)[ok])
    n = len(y)
    point = mu[np.arange(n), w.argmax(-1)]
    r2 = (y - point) ** 2
    kind_floor = outlier_scale_floors(list(arrays["mixture_layout"])) if "mixture_layout" in arrays else MIN_SCALE
    floor = np.maximum(np.maximum(y.std(0), np.sqrt(r2.mean(0))), kind_floor)
    with np.errstate(over="ignore"):  # a gross failure's mixture density underflows to 0: NLL inf
        log_core = -mixture_nll(y, w, mu, sigma)
    lo, hi = OUTLIER_WEIGHT_BOUNDS

    one = np.ones((n, 1))

    def log_terms(eps: float, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # per image: log(eps N(y; m, s)) and log of the whole density
        a = np.log(eps) - mixture_nll(y, one, point[:, None], np.broadcast_to(scale, (n, 1, len(scale))))
        return a, np.logaddexp(a, np.log1p(-eps) + log_core)

    eps, scale = OUTLIER_INITIAL_WEIGHT, floor.copy()
    a, total = log_terms(eps, scale)
    nll = float(-total.mean())
    for _ in range(OUTLIER_MAX_ROUNDS):
        g = np.exp(a - total)  # responsibilities
        eps_next = float(np.clip(g.mean(), lo, hi))
        scale_next = np.maximum(np.sqrt((g[:, None] * r2).sum(0) / max(g.sum(), np.finfo(float).tiny)), floor)
        a_next, total_next = log_terms(eps_next, scale_next)
        nll_next = float(-total_next.mean())
        if not nll - nll_next >= OUTLIER_TOLERANCE_NATS:  # converged (the bounds and floor may stop the ascent)
            break
        eps, scale, a, total, nll = eps_next, scale_next, a_next, total_next, nll_next
    responsibility = np.zeros(len(ok))
    responsibility[ok] = np.exp(a - total)
    return {"weight": eps, "scale": [float(v) for v in scale], "n_images": int(n),
            "validation_nll": {"without": float(-log_core.mean()), "with": nll}, "responsibility": responsibility}


def choose_split_factor(model, data, idx: np.ndarray, *, batch_size: int = PREDICT_BATCH) -> tuple[float | None, dict]:
    """The vote modes' split factor for a model: of :data:`SPLIT_FACTOR_CANDIDATES`, the one whose
    heaviest modes have the lowest mean axis position error on the validation images ``idx``
    (votes alone, before the refinement); the default :data:`~.aggregate.SPLIT_FACTOR` unless
    another lowers it by :data:`SPLIT_MIN_GAIN`.  A second mode keeps a two-sided ambiguity apart,
    but where there is none it only halves the votes an estimate averages.  Returns the factor and
    the mean error (cm) of every candidate."""
    import torch

    from articulated_dataset.benchmark import metrics as M
    from articulated_dataset.methods.dense.aggregate import SPLIT_FACTOR, vote_modes
    from articulated_dataset.methods.dense.features import make_inputs

    true_origin = _true_pose(data, idx)[..., :3]
    errors: dict[float | None, list] = {c: [] for c in SPLIT_FACTOR_CANDIDATES}
    model.eval()
    for s in range(0, len(idx), batch_size):
        b = idx[s : s + batch_size]
        with torch.no_grad():
            inputs = make_inputs(data.depth(b), torch.from_numpy(data.K[b]))
            parts = model.split(network_outputs(model, inputs["x"]))
            valid = inputs["weight_out"] > 0
            for c in SPLIT_FACTOR_CANDIDATES:
                modes = vote_modes(parts, inputs["points_out"], valid, split_factor=c)
                heaviest = modes["weight"].argmax(-1)[..., None, None]
                origin = torch.take_along_dim(modes["origin"], heaviest, dim=2)[:, :, 0].numpy()
                errors[c].append(M.axis_position_error_cm(origin, true_origin[s : s + len(b)]))
    mean = {c: float(np.mean(np.concatenate(e))) for c, e in errors.items()}
    best: float | None = SPLIT_FACTOR
    for c in SPLIT_FACTOR_CANDIDATES:
        if mean[c] < min(mean[best], mean[SPLIT_FACTOR] * (1 - SPLIT_MIN_GAIN)):
            best = c
    return best, {("never" if c is None else f"{c:g}"): e for c, e in mean.items()}


def fit_inference(model, data, idx: np.ndarray, joint_types: list[str], *, mirror_joints=None,
                  progress: bool = False) -> InferenceFit:
    """Fit what inference needs beyond the weights on validation images ``idx`` (with labels):
    the vote modes' split factor (:func:`choose_split_factor`), the refinement
    (:func:`~.fit.fit_refinement`, once for each box-frame pixel threshold of
    :data:`~.fit.FRAME_PROB_CANDIDATES` with and without one-sided normals, then the best of these
    with each strip elongation of :data:`~.fit.FRAME_STRIP_CANDIDATES` (the best kept where it lowers
    the rotation error by :data:`~.fit.FRAME_STRIP_MIN_GAIN`); then, where the class's ``mirror_joints`` is given, whether
    averaging the network's outputs with its outputs on the mirror images (:mod:`.mirror`) lowers
    the position error by at least
    :data:`~.mirror.MIRROR_MIN_GAIN`), then the uncertainty calibration of the refined predictions
    (:func:`fitted_calibration`: the modes' scales and the outlier component).  Returns ``{"refinement": dict, "calibration": dict,
    "refinement_report": dict}`` for the checkpoint."""
    from dataclasses import replace

    from articulated_dataset.methods.dense.fit import (
        FRAME_ONE_SIDED_CANDIDATES,
        FRAME_PROB_CANDIDATES,
        FRAME_STRIP_CANDIDATES,
        FRAME_STRIP_MIN_GAIN,
        configuration_error,
        fit_refinement,
        rotation_error_deg,
    )
    from articulated_dataset.methods.dense.handle import EVERY_DOOR_DEG
    from articulated_dataset.methods.dense.mirror import MIRROR_MIN_GAIN
    from articulated_dataset.methods.dense.refine import apply_refinement, strip_sized

    split_factor, split_report = choose_split_factor(model, data, idx)
    truth = {"axis_pose": _true_pose(data, idx), "q": data.q[idx].astype(np.float64),
             "part_offset": data.part_offset[idx].astype(np.float64)}
    # the refinement fitted once per box-frame pixel threshold and normal reading (central differences
    # only, or one-sided ones too); the one with the lowest rotation error kept (the configuration
    # decides between equal rotations: the box frame unused; the first candidate between equal pairs)
    # then, with the chosen pair, the body's strip (each elongation of FRAME_STRIP_CANDIDATES; the
    # best kept only where it lowers the rotation error by FRAME_STRIP_MIN_GAIN: it costs inference time)
    # the network and vote modes run once for the six pairs, the refinement once per pair; the strip only
    # changes the images whose box-frame pixels may make one (refine.strip_sized), which alone are
    # refined again with each elongation (the others' quantities are the chosen pair's)
    frame_report = {}

    def frame_fit(p, one_sided, strip, m_p, r_p):
        refinement_p, report_p = fit_refinement(m_p, r_p, truth, joint_types)
        refined_p = apply_refinement(m_p, r_p, refinement_p, joint_types)
        errors = (round(rotation_error_deg(refined_p, truth), 9), configuration_error(refined_p, truth, joint_types))
        name = (("all pixels" if p is None else f"probability>{p:g}") + (", one-sided normals" if one_sided else "")
                + ("" if strip is None else f", strip elongation {strip:g}"))
        frame_report[name] = {"rotation_deg": errors[0], "configuration": errors[1]}
        return errors, (p, one_sided, strip, m_p, r_p, refinement_p, report_p)

    def keywords(p, one_sided, strip=None):
        return refinement_keywords(handle_max_q_deg=EVERY_DOOR_DEG, frame_min_prob=p, frame_one_sided=one_sided,
                                   frame_strip_elongation=strip)

    pairs = list(itertools.product(FRAME_PROB_CANDIDATES, FRAME_ONE_SIDED_CANDIDATES))
    m, rs = predict_candidates(model, data, idx, joint_types=joint_types, split_factor=split_factor,
                               candidates={pair: keywords(*pair) for pair in pairs}, progress=progress)
    best = min((frame_fit(*pair, None, m, rs[pair]) for pair in pairs), key=lambda f: f[0])
    p, one_sided, r_pair = best[1][0], best[1][1], best[1][4]
    rows = np.flatnonzero(strip_sized(r_pair["frame_px"]))
    r_rows = dict.fromkeys(FRAME_STRIP_CANDIDATES)
    if len(rows):
        _, r_rows = predict_candidates(model, data, idx[rows], joint_types=joint_types, split_factor=split_factor,
                                       candidates={strip: keywords(p, one_sided, strip) for strip in FRAME_STRIP_CANDIDATES},
                                       progress=progress)
    strips = [frame_fit(p, one_sided, strip, m, _with_rows(r_pair, rows, r_rows[strip])) for strip in FRAME_STRIP_CANDIDATES]
    best_strip = min(strips, key=lambda f: f[0])
    if best_strip[0][0] < best[0][0] * (1 - FRAME_STRIP_MIN_GAIN):
        best = best_strip
    p, one_sided, strip, m, r, refinement, report = best[1]
    refinement = replace(refinement, split_factor=split_factor, frame_min_prob=p, frame_one_sided=one_sided,
                         frame_strip_elongation=strip)
    report["frame_min_prob"] = frame_report
    report["split_factor_position_cm"] = split_report
    refined = apply_refinement(m, r, refinement, joint_types)
    if mirror_joints is not None:
        mm, mr = predict_modes(model, data, idx, joint_types=joint_types, progress=progress,
                               refine=refinement.needed, split_factor=split_factor, mirror_joints=mirror_joints,
                               **refinement_keywords_of(refinement))
        merged = apply_refinement(mm, mr, refinement, joint_types)  # type: ignore[arg-type]  # (as refined_batch)
        pos = {name: quick_errors(modes_to_arrays(x, data.sample_id[idx], model, None), data, idx, joint_types)["pos_cm"]
               for name, x in (("without", refined), ("with", merged))}
        report["mirror_position_cm"] = pos
        if pos["with"] < pos["without"] * (1 - MIRROR_MIN_GAIN):
            refinement, refined = replace(refinement, mirror_joints=tuple(mirror_joints)), merged
    return {"refinement": refinement.to_dict(), "calibration": fitted_calibration(refined, model, data, idx),
            "refinement_report": report}


def _with_rows(r: dict, rows: np.ndarray, r_rows: dict | None) -> dict:
    """Refined quantities ``r`` of some images with the images ``rows`` replaced by ``r_rows``'s
    (None: none replaced)."""
    if r_rows is None:
        return r
    out = {k: v.copy() for k, v in r.items()}
    for k, v in out.items():
        v[rows] = r_rows[k]
    return out


def fitted_calibration(modes: dict, model, data, idx: np.ndarray,
                       plain: CalibrationRecord | None = None) -> CalibrationRecord:
    """The calibration of a model's refined vote modes (numpy) of the validation images ``idx``,
    the modes' scales and the outlier component fitted together: :func:`fit_calibration`, then
    :data:`OUTLIER_CALIBRATION_ROUNDS` times the outlier component of the calibrated mixture
    (:func:`fit_outlier_component`) and the modes' scales refitted with each image weighted by
    ``1 - g``, its share the modes explain (so the few gross failures no longer widen every
    image's scales), then the outlier component of the final scales (under ``"outlier"``; none,
    with a warning, where no image has every target column defined).  ``plain``: the first
    :func:`fit_calibration` of these modes where the caller has it already."""
    uncalibrated = modes_to_arrays(modes, data.sample_id[idx], model, None)
    y = truth_columns(data, idx)
    calibration = fit_calibration(uncalibrated, data, idx) if plain is None else cast(CalibrationRecord, dict(plain))
    if not np.isfinite(y).all(-1).any():  # labels with undefined columns in every image (real captures)
        log.warning("no validation image has every target column defined: the mixtures get no outlier component")
        return calibration
    for _ in range(OUTLIER_CALIBRATION_ROUNDS):
        outlier = fit_outlier_component(modes_to_arrays(modes, data.sample_id[idx], model, calibration), y)
        calibration = fit_calibration(uncalibrated, data, idx, 1.0 - outlier["responsibility"])
    outlier = fit_outlier_component(modes_to_arrays(modes, data.sample_id[idx], model, calibration), y)
    outlier.pop("responsibility")
    calibration["outlier"] = outlier
    return calibration


def quick_errors(arrays: dict, data, idx: np.ndarray, joint_types: list[str]) -> dict:
    """Mean axis position (cm), axis rotation (deg) and configuration errors of point estimates."""
    from articulated_dataset.benchmark import metrics as M

    pose = arrays["axis_pose"]
    true_pose = _true_pose(data, idx)
    pos = M.axis_position_error_cm(pose[..., :3], true_pose[..., :3])
    rot = M.axis_rotation_error_deg(pose[..., 3:], true_pose[..., 3:])
    prismatic = np.array([t == "prismatic" for t in joint_types])
    cfg = M.configuration_error(arrays["q"], data.q[idx], prismatic)
    return {"pos_cm": float(np.mean(pos)), "rot_deg": float(np.mean(rot)), "config": float(np.mean(cfg))}


def _true_pose(data, idx: np.ndarray) -> np.ndarray:
    """The labelled axis poses (N, J, 7) of the images ``idx``: origin (m) + quaternion (w, x, y, z)."""
    return np.concatenate([data.origin[idx], _quat_from_rot6(data.rot6[idx])], -1).astype(np.float64)


def _quat_from_rot6(r6: np.ndarray) -> np.ndarray:
    from articulated_dataset.core.rotations import matrix_to_quat
    from articulated_dataset.training.targets import gram_schmidt

    return matrix_to_quat(gram_schmidt(r6[..., :3], r6[..., 3:]))


def check_precision(precision: str) -> None:
    """``--precision`` of ``predict`` and ``estimate``: one of :data:`~.model.PRECISIONS`
    (else a UserError); ``bfloat16`` on a CPU without native bfloat16 arithmetic logs a warning
    (oneDNN emulates it, slower than float32)."""
    from articulated_dataset.methods.dense.model import PRECISIONS, bfloat16_native

    if precision not in PRECISIONS:
        raise UserError(f"{option('precision')} must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    if precision == "bfloat16" and not bfloat16_native():
        log.warning("this CPU has no native bfloat16 arithmetic (AVX512-BF16 or AMX): --precision bfloat16 is "
                    "emulated and slower than float32")


def _class_extent(class_name: str, prompt: str | None) -> float | None:
    """The largest size of ``class_name``'s objects where a point, box or no prompt's segmentation
    needs it, else None."""
    if prompt not in ("point", "box", "none"):
        return None
    from articulated_dataset.methods.prompts import class_extent_m

    return class_extent_m(class_name)


def predict_split(ckpt: DenseCheckpoint, data: str | Path, *, batch_size: int = PREDICT_BATCH, object_mask: bool = False,
                  mirror: bool = True, workers: int | None = None, precision: str = "float32",
                  progress: bool = True, as_class: str | None = None, prompt: str | None = None) -> tuple[str, dict]:
    """Run a loaded dense checkpoint on the split at ``data``; ``(class_name, arrays)`` as
    :func:`articulated_dataset.benchmark.predictions.write_predictions` takes them.  Labels are not
    read; with ``object_mask`` the split's mask keeps only the object's pixels
    (:func:`~.data.load_dense_split`); with ``prompt`` (``point``, ``box``, ``mask``, ``none``) each
    image's object is segmented from the prompt a click or a detector would give
    (:mod:`articulated_dataset.methods.prompts`; ``mask`` is ``object_mask``).  A split with a scene or occluders
    predicted without either
    logs a warning: the model was trained on isolated objects and reads every pixel with depth.
    ``mirror=False`` skips the refinement's mirror image (:func:`~.mirror.with_mirror`).
    ``workers``: processes that share the images (:func:`predict_arrays`); None:
    :func:`default_workers`.  ``precision``: the network's arithmetic (:func:`check_precision`).
    ``as_class``: read a third-party split (``generate --urdf``) as the checkpoint's class
    (:func:`~articulated_dataset.methods.mdn.data.checked_split_class`); the returned class is the split's."""
    from articulated_dataset.methods.dense.checkpoint import build_inference_model
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.mirror import with_mirror
    from articulated_dataset.methods.mdn.data import checked_split_class, resolve_split_dir

    if batch_size <= 0:
        raise UserError(f"{option('batch_size')} must be positive, got {batch_size}")
    if workers is not None:
        from articulated_dataset.methods.mdn.config import check_per_cpu

        if workers <= 0:
            raise UserError(f"{option('workers')} must be positive, got {workers}")
        check_per_cpu("workers", workers)
    check_precision(precision)
    class_name = ckpt["class_name"]
    split_dir = resolve_split_dir(data)
    data_class = checked_split_class(split_dir, class_name, as_class, "the dense model")
    if prompt is not None:
        from articulated_dataset.methods.prompts import PROMPT_KINDS

        if prompt not in PROMPT_KINDS:
            raise UserError(f"{option('prompt')} must be one of {', '.join(PROMPT_KINDS)}, got {prompt!r}")
    if not object_mask and prompt is None:
        from articulated_dataset.methods.inputs import split_context, split_has_context

        if split_has_context(split_dir):
            log.warning("%s: the split has a scene or occluders (scene %s, %s occluders per image); the model reads "
                        "every pixel with depth: pass --object-mask or --prompt to give it only the object's pixels, "
                        "as a robot's segmentation would", split_dir, *split_context(split_dir))
    model = build_inference_model(ckpt, precision)
    cfg = model.config
    d = load_dense_split(split_dir, cfg.n_joints, (cfg.height_px, cfg.width_px), with_labels=False,
                         object_mask=object_mask, progress=progress, prompt=prompt,
                         max_extent_m=_class_extent(class_name, prompt))
    idx = np.arange(len(d.sample_id))
    if prompt == "none":  # an image where no object was found gets no answer (the scorer reports the coverage)
        idx = idx[d.depth_q.reshape(len(idx), -1).any(axis=1)]
        log.info("dense: an object was found in %d of %d images", len(idx), len(d.sample_id))
    n = len(idx)
    workers = default_workers(n) if workers is None else workers
    t0 = time.perf_counter()
    arrays = predict_arrays(model, d, idx, joint_types=list(ckpt["joint_types"]),
                            calibration=ckpt.get("calibration"), refinement=with_mirror(ckpt.get("refinement"), mirror),
                            batch_size=batch_size, progress=progress, workers=workers)
    log.info("dense: %d images in %.1f s (%d process%s)", n, time.perf_counter() - t0, workers,
             "" if workers == 1 else "es")
    arrays.pop("spread")
    return data_class, arrays
