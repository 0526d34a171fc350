"""The dense estimator's checkpoints: the file's format and version, reading and checking one
(:func:`load_dense_checkpoint`), and the network rebuilt from it (:func:`build_dense_model`; for
inference, its batch normalisations folded: :func:`build_inference_model`).
Writing is training's (:mod:`articulated_dataset.models.dense.train`)."""

from __future__ import annotations

from pathlib import Path

from ...errors import UserError

CHECKPOINT_FORMAT = "artdata-dense"
CHECKPOINT_VERSION = 1


def load_dense_checkpoint(path: str | Path) -> dict:
    """Load and check a dense checkpoint (``weights_only``); any problem is one UserError line."""
    from ..mdn.checkpoint import read_checkpoint_file

    path = Path(path)
    ckpt = read_checkpoint_file(path)
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path}: not an artdata dense-model checkpoint (written by 'artdata train --model dense')")
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise UserError(f"{path}: dense checkpoint version {ckpt.get('version')!r} is not readable "
                        f"(expected {CHECKPOINT_VERSION})")
    need = {"class_name": str, "model_config": dict, "train_config": dict, "model_state": dict, "q_scale": list,
            "joint_types": list}
    for key, typ in need.items():
        if not isinstance(ckpt.get(key), typ):
            raise UserError(f"{path}: checkpoint field {key!r} is missing or not a {typ.__name__}")
    problem = calibration_problem(ckpt.get("calibration"), 13 * len(ckpt["joint_types"]) + 4)
    if problem is not None:
        raise UserError(f"{path}: checkpoint field 'calibration' is malformed: {problem}")
    problem = refinement_problem(ckpt.get("refinement"), len(ckpt["joint_types"]))
    if problem is not None:
        raise UserError(f"{path}: checkpoint field 'refinement' is malformed: {problem}")
    return ckpt


def refinement_problem(refinement, n_joints: int) -> str | None:
    """What is wrong with a checkpoint's ``refinement`` (None: nothing; absent is allowed: the
    votes are used as they are): a dict that :meth:`~.refine.Refinement.from_dict` reads, whose
    numbers are finite (an integer pixel count non-negative) and whose ``mirror_joints`` (where
    given) orders the ``n_joints`` joints."""
    import dataclasses

    from ..mdn.config import is_real_number
    from .refine import Refinement

    if refinement is None:
        return None
    if not isinstance(refinement, dict):
        return "not a dict"
    try:
        r = Refinement.from_dict(refinement)
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        return f"{type(exc).__name__}: {str(exc)[:120]}"
    for field in dataclasses.fields(r):
        value = getattr(r, field.name)
        values = value if isinstance(value, tuple) else (value,)
        for v in values:
            if isinstance(v, float) and not is_real_number(v):
                return f"{field.name!r} is not finite"
            if isinstance(v, int) and not isinstance(v, bool) and v < 0:
                return f"{field.name!r} is negative"
    if r.mirror_joints is not None and sorted(r.mirror_joints) != list(range(n_joints)):
        return f"'mirror_joints' {list(r.mirror_joints)} does not order the {n_joints} joints"
    return None


def _numbers(value, n: int, *, positive: bool) -> bool:
    """Whether ``value`` is a list of ``n`` finite numbers, each >= 0 (> 0 with ``positive``)."""
    from ..mdn.config import is_real_number

    return (isinstance(value, (list, tuple)) and len(value) == n
            and all(is_real_number(v) and (v > 0 if positive else v >= 0) for v in value))


def calibration_problem(calibration, n_columns: int) -> str | None:
    """What is wrong with a checkpoint's ``calibration`` (None: nothing; absent is allowed, the
    modes then keep their raw spreads): per-column ``spread_factor`` and ``floor`` lists of
    ``n_columns`` finite non-negative numbers and, where present, an ``outlier`` component with a
    ``weight`` in [0, 1) and ``n_columns`` positive finite ``scale`` values
    (:func:`~.predict.fit_outlier_component`)."""
    from ..mdn.config import is_real_number

    if calibration is None:
        return None
    if not isinstance(calibration, dict):
        return "not a dict"
    for key in ("spread_factor", "floor"):
        if not _numbers(calibration.get(key), n_columns, positive=False):
            return f"{key!r} is not {n_columns} finite non-negative numbers"
    outlier = calibration.get("outlier")
    if outlier is None:
        return None
    if not isinstance(outlier, dict):
        return "'outlier' is not a dict"
    w = outlier.get("weight")
    if not (is_real_number(w) and 0 <= w < 1):
        return "the outlier component's 'weight' is not a number in [0, 1)"
    if not _numbers(outlier.get("scale"), n_columns, positive=True):
        return f"the outlier component's 'scale' is not {n_columns} finite positive numbers"
    return None


def build_dense_model(ckpt: dict):
    """The network of a checkpoint, weights loaded, eval mode."""
    from .model import DenseConfig, DenseNet

    try:
        model = DenseNet(DenseConfig.from_dict(ckpt["model_config"]))
        model.load_state_dict(ckpt["model_state"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise UserError(f"checkpoint weights do not match its model configuration "
                        f"({str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__})") from None
    if model.config.n_joints != len(ckpt["joint_types"]):
        raise UserError("checkpoint's joint types do not match its model configuration")
    return model.eval()


def build_inference_model(ckpt: dict, precision: str = "float32"):
    """The network of a checkpoint for inference: :func:`build_dense_model` with its batch
    normalisations folded into its convolutions (:meth:`~.model.DenseNet.folded`), computing in
    ``precision`` (``"float32"`` or ``"bfloat16"``)."""
    return build_dense_model(ckpt).folded(precision)
