"""The dense estimator's checkpoints: the file's format and version, reading and checking one
(:func:`load_dense_checkpoint`), and the network rebuilt from it (:func:`build_dense_model`; for
inference, its batch normalisations folded: :func:`build_inference_model`).
Writing is training's (:mod:`articulated_dataset.methods.dense.train`)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, TypedDict, cast

from articulated_dataset.core.errors import UserError, option

if TYPE_CHECKING:
    import torch

    from articulated_dataset.methods.dense.predict import CalibrationRecord
    from articulated_dataset.methods.dense.refine import RefinementRecord

CHECKPOINT_FORMAT = "artdata-dense"
CHECKPOINT_VERSION = 1
#: Bounds of a checkpoint's ``model_config``, checked before anything is allocated from it: the
#: network's base width (the shipped models': 16) and the sides of its input image (192 x 108; the
#: network downsamples by 32).
MAX_NETWORK_WIDTH = 256
MIN_INPUT_SIDE_PX = 32
MAX_INPUT_SIDE_PX = 4096
#: Largest whole number a checkpoint's counts (its step, a refinement's pixel counts) may hold: they
#: are compared with numpy integers and stored as HDF5 attributes (64-bit), and 10**400 is a Python int.
MAX_CHECKPOINT_COUNT = 2**31 - 1


class _DenseCheckpointRequired(TypedDict):
    format: str  # CHECKPOINT_FORMAT
    version: int  # CHECKPOINT_VERSION
    class_name: str
    joint_types: list[str]
    model_config: dict  # DenseConfig.to_dict()
    train_config: dict  # DenseTrainConfig.to_dict()
    model_state: dict  # the network's state_dict (name -> tensor)
    q_scale: list[float]  # per joint, rad or m: the q loss's scale
    step: int  # training steps taken


class DenseCheckpoint(_DenseCheckpointRequired, total=False):
    """A dense checkpoint as :func:`load_dense_checkpoint` returns it and training writes it
    (:mod:`articulated_dataset.methods.dense.train`): the keys every checkpoint has, then those of
    a training run (its data, machine, history, optimiser state), of the inference fit
    (``calibration``, ``refinement``) and of a refit.  An exported checkpoint
    (:mod:`articulated_dataset.methods.safetensors_checkpoint`) holds the same keys."""

    finished: bool
    total_steps: int
    data: dict  # the training split(s): folder, identity, image and object counts
    machine: str  # where training ran (CPU cores, GPU, PyTorch)
    device: str  # torch device type: "cpu" or "cuda"
    history: list  # one dict of losses and validation errors per evaluation
    cpu_seconds: float
    load_seconds: float  # reading the training split(s)
    calibration: CalibrationRecord | None
    refinement: RefinementRecord | None
    refinement_report: dict  # the fit's validation errors of each choice (cm, deg)
    refit_of: dict  # the checkpoint refitted: file name, sha256, validation noise
    optimizer_state: dict
    scheduler_state: dict
    rng_state: torch.Tensor


def load_dense_checkpoint(path: str | Path) -> DenseCheckpoint:
    """Load and check a dense checkpoint: a ``.pt`` file (``torch.load(weights_only=True)``) or a
    ``NAME.safetensors`` file with its ``NAME.json`` (no pickle); any problem is one UserError line
    (:func:`~..mdn.checkpoint.read_checkpoint_file`)."""
    from articulated_dataset.methods.mdn.checkpoint import read_checkpoint_file

    path = Path(path)
    ckpt = read_checkpoint_file(path)
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path}: not an artdata dense-model checkpoint (written by "
                        f"'artdata train {option('model_kind')} dense')")
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise UserError(f"{path}: dense checkpoint version {ckpt.get('version')!r} is not readable "
                        f"(expected {CHECKPOINT_VERSION})")
    need = {"class_name": str, "model_config": dict, "train_config": dict, "model_state": dict, "q_scale": list,
            "joint_types": list}
    for key, typ in need.items():
        if not isinstance(ckpt.get(key), typ):
            raise UserError(f"{path}: checkpoint field {key!r} is missing or not a {typ.__name__}")
    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.methods.mdn.checkpoint import state_problem
    from articulated_dataset.methods.mdn.config import is_int

    try:
        obj_class = get_class(ckpt["class_name"])
    except UserError as exc:
        raise UserError(f"{path}: {exc}") from None
    if list(ckpt["joint_types"]) != list(obj_class.joint_types):
        raise UserError(f"{path}: checkpoint joint types {str(ckpt['joint_types'])[:80]} are not the "
                        f"{obj_class.name!r} class's {list(obj_class.joint_types)}")
    limits = {"n_joints": (obj_class.n_joints, obj_class.n_joints), "width": (1, MAX_NETWORK_WIDTH),
              "height_px": (MIN_INPUT_SIDE_PX, MAX_INPUT_SIDE_PX), "width_px": (MIN_INPUT_SIDE_PX, MAX_INPUT_SIDE_PX)}
    for key, (lo, hi) in limits.items():
        value = ckpt["model_config"].get(key)
        if not (is_int(value) and lo <= value <= hi):
            raise UserError(f"{path}: checkpoint field 'model_config' {key!r} must be a whole number in "
                            f"[{lo}, {hi}], got {str(value)[:40]}")
    problem = state_problem(ckpt["model_state"])
    if problem is not None:
        raise UserError(f"{path}: checkpoint field 'model_state' {problem}")
    if not _numbers(ckpt["q_scale"], obj_class.n_joints, positive=True):
        raise UserError(f"{path}: checkpoint field 'q_scale' must hold {obj_class.n_joints} positive finite numbers")
    if not isinstance(ckpt.get("finished", False), bool):
        raise UserError(f"{path}: checkpoint field 'finished' must be true or false")
    if not (is_int(ckpt.get("step")) and 0 <= ckpt["step"] <= MAX_CHECKPOINT_COUNT):
        raise UserError(f"{path}: checkpoint field 'step' is missing or not a whole number in [0, {MAX_CHECKPOINT_COUNT}]")
    problem = calibration_problem(ckpt.get("calibration"), 13 * len(ckpt["joint_types"]) + 4)
    if problem is not None:
        raise UserError(f"{path}: checkpoint field 'calibration' is malformed: {problem}")
    problem = refinement_problem(ckpt.get("refinement"), len(ckpt["joint_types"]))
    if problem is not None:
        raise UserError(f"{path}: checkpoint field 'refinement' is malformed: {problem}")
    return cast(DenseCheckpoint, ckpt)  # (every field it reads checked above)


#: A refinement's probability fields lie in [0, 1); its gates (deg, m) and ratios are positive;
#: its angle gates (deg) at most a half turn.
_REFINEMENT_PROBABILITIES = ("frame_min_prob",)
_REFINEMENT_POSITIVE = ("door_angle_gate_deg", "max_turn_deg", "door_extent_gate_m", "split_factor",
                        "handle_height_gate_m", "door_face_gate_m", "drawer_front_gate_m", "drawer_centre_gate_m",
                        "drawer_shell_gate_m", "frame_strip_elongation")
_REFINEMENT_ANGLES_DEG = ("door_angle_gate_deg", "max_turn_deg", "handle_max_q_deg")
HALF_TURN_DEG = 180.0
#: ... and its lengths (offsets and gates, m) are within this of zero.
MAX_REFINEMENT_LENGTH_M = 10.0


def refinement_problem(refinement, n_joints: int) -> str | None:
    """What is wrong with a checkpoint's ``refinement`` (None: nothing; absent is allowed: the
    votes are used as they are): a dict whose fields have their declared types (a switch true or
    false, never a string; a number finite; a count a non-negative whole number; null only where a
    field may be), which :meth:`~.refine.Refinement.from_dict` reads, whose probabilities lie in
    [0, 1), gates and ratios are positive, angle gates at most :data:`HALF_TURN_DEG`, version is
    one this package reads, and whose ``mirror_joints`` (where given) orders the ``n_joints``
    joints."""
    import dataclasses

    from articulated_dataset.methods.dense.refine import REFINEMENT_VERSION, Refinement
    from articulated_dataset.methods.mdn.config import is_int, is_real_number

    if refinement is None:
        return None
    if not isinstance(refinement, dict):
        return "not a dict"
    known = {field.name for field in dataclasses.fields(Refinement)}
    unknown = [k for k in refinement if k not in known]
    if unknown:
        return f"unknown field {str(unknown[0])[:40]!r}"
    for field in dataclasses.fields(Refinement):
        if field.name not in refinement:
            continue
        v, kind = refinement[field.name], str(field.type)
        if v is None:
            if not kind.endswith("| None"):  # an optional field's type ends so (a pair's items may be None)
                return f"{field.name!r} may not be null"
        elif kind.startswith("bool"):
            if not isinstance(v, bool):
                return f"{field.name!r} must be true or false, got {str(v)[:40]!r}"
        elif kind.startswith("int"):
            if not is_int(v) or not 0 <= v <= MAX_CHECKPOINT_COUNT:
                return f"{field.name!r} must be a whole number in [0, {MAX_CHECKPOINT_COUNT}], got {str(v)[:40]!r}"
        elif kind.startswith("float"):
            if not is_real_number(v):
                return f"{field.name!r} must be a finite number, got {str(v)[:40]!r}"
        elif kind.startswith("tuple"):
            item_ok = is_int if "int" in kind else (lambda x: x is None or is_real_number(x))
            if not (isinstance(v, (list, tuple)) and all(item_ok(x) for x in v)):
                return f"{field.name!r} must be a list of {'joint indices' if 'int' in kind else 'finite numbers'}"
    try:
        r: Refinement = Refinement.from_dict(refinement)  # type: ignore[assignment, arg-type]  # a checked dict: never None
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        return f"{type(exc).__name__}: {str(exc)[:120]}"
    for name in _REFINEMENT_PROBABILITIES:
        if getattr(r, name) is not None and not 0.0 <= getattr(r, name) < 1.0:
            return f"{name!r} must be a probability in [0, 1), got {getattr(r, name)}"
    for name in _REFINEMENT_POSITIVE:
        if getattr(r, name) is not None and not getattr(r, name) > 0:
            return f"{name!r} must be positive, got {getattr(r, name)}"
    for field in dataclasses.fields(r):  # lengths (m): within a room's size
        values = getattr(r, field.name) if field.name.endswith("_m") else None
        for v in values if isinstance(values, tuple) else (values,):
            if v is not None and abs(v) > MAX_REFINEMENT_LENGTH_M:
                return f"{field.name!r} must be within +-{MAX_REFINEMENT_LENGTH_M:g} m, got {v:.4g}"
    for name in _REFINEMENT_ANGLES_DEG:
        if getattr(r, name) is not None and not 0 <= getattr(r, name) <= HALF_TURN_DEG:
            return f"{name!r} must be an angle in [0, {HALF_TURN_DEG:g}] deg, got {getattr(r, name)}"
    if r.handle_min_px < 0:
        return "'handle_min_px' is negative"
    if not 1 <= r.version <= REFINEMENT_VERSION:
        return f"version {r.version} is not one this package reads (1-{REFINEMENT_VERSION})"
    if len(r.door_face_offsets_m) != 2:
        return "'door_face_offsets_m' must hold two offsets"
    if r.mirror_joints is not None and sorted(r.mirror_joints) != list(range(n_joints)):
        return f"'mirror_joints' {list(r.mirror_joints)} does not order the {n_joints} joints"
    return None


def _numbers(value, n: int, *, positive: bool, at_most: float = float("inf")) -> bool:
    """Whether ``value`` is a list of ``n`` finite numbers, each >= 0 (> 0 with ``positive``) and
    at most ``at_most``."""
    from articulated_dataset.methods.mdn.config import is_real_number

    return (isinstance(value, (list, tuple)) and len(value) == n
            and all(is_real_number(v) and (v > 0 if positive else v >= 0) and v <= at_most for v in value))


#: Bounds of a calibration's numbers: the fit chooses spread factors in [0.05, 50]
#: (``predict.CAL_SPREAD_FACTORS``) and floors and outlier scales of centimetres and degrees; a
#: factor or floor of 1e300 overflowed the scales to infinity (a RuntimeWarning, then "Infinity"
#: in ``estimate --json`` and a refused predictions file after the whole split was predicted).
MAX_CALIBRATION_FACTOR = 1000.0
MAX_CALIBRATION_SCALE = 100.0


def calibration_problem(calibration, n_columns: int) -> str | None:
    """What is wrong with a checkpoint's ``calibration`` (None: nothing; absent is allowed, the
    modes then keep their raw spreads): per-column ``spread_factor`` and ``floor`` lists of
    ``n_columns`` finite non-negative numbers and, where present, an ``outlier`` component with a
    ``weight`` in [0, 1) and ``n_columns`` positive finite ``scale`` values
    (:func:`~.predict.fit_outlier_component`)."""
    from articulated_dataset.methods.mdn.config import is_real_number

    if calibration is None:
        return None
    if not isinstance(calibration, dict):
        return "not a dict"
    for key in ("spread_factor", "floor"):
        bound = MAX_CALIBRATION_FACTOR if key == "spread_factor" else MAX_CALIBRATION_SCALE
        if not _numbers(calibration.get(key), n_columns, positive=False, at_most=bound):
            return f"{key!r} is not {n_columns} finite non-negative numbers of at most {bound:g}"
    outlier = calibration.get("outlier")
    if outlier is None:
        return None
    if not isinstance(outlier, dict):
        return "'outlier' is not a dict"
    w = outlier.get("weight")
    if not (is_real_number(w) and 0 <= w < 1):
        return "the outlier component's 'weight' is not a number in [0, 1)"
    if not _numbers(outlier.get("scale"), n_columns, positive=True, at_most=MAX_CALIBRATION_SCALE):
        return f"the outlier component's 'scale' is not {n_columns} finite positive numbers of at most {MAX_CALIBRATION_SCALE:g}"
    return None


def build_dense_model(ckpt: DenseCheckpoint):
    """The network of a checkpoint, weights loaded, eval mode."""
    from articulated_dataset.methods.dense.model import DenseConfig, DenseNet

    try:
        model = DenseNet(DenseConfig.from_dict(ckpt["model_config"]))
        model.load_state_dict(ckpt["model_state"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise UserError(f"checkpoint weights do not match its model configuration "
                        f"({str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__})") from None
    if model.config.n_joints != len(ckpt["joint_types"]):
        raise UserError("checkpoint's joint types do not match its model configuration")
    return model.eval()


def build_inference_model(ckpt: DenseCheckpoint, precision: str = "float32"):
    """The network of a checkpoint for inference: :func:`build_dense_model` with its batch
    normalisations folded into its convolutions (:meth:`~.model.DenseNet.folded`), computing in
    ``precision`` (``"float32"`` or ``"bfloat16"``)."""
    return build_dense_model(ckpt).folded(precision)
