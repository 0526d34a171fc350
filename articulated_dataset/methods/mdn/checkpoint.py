"""Checkpoints of the mixture density network: atomic saving, reading an untrusted file,
the checks a checkpoint must pass before it is used, the training output folder, and the
model rebuilt from a checkpoint."""

from __future__ import annotations

import pickle
import warnings
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Callable, TypedDict, TypeVar, cast

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.format import Split
from articulated_dataset.methods.mdn.config import TrainConfig, is_int, is_real_number

CHECKPOINT_FORMAT = "artdata-mdn"
CHECKPOINT_VERSION = 1


class _MdnCheckpointRequired(TypedDict):
    format: str  # CHECKPOINT_FORMAT
    version: int  # CHECKPOINT_VERSION
    class_name: str
    layout_names: list[str]  # the target vector's column names (TargetLayout.names)
    norm_stats: dict  # NormStats.to_dict()
    model_config: dict  # ModelConfig.to_dict()
    input_config: dict  # InputConfig.to_dict()
    train_config: dict  # TrainConfig.to_dict()
    model_state: dict  # the network's state_dict (name -> tensor)


class MdnCheckpoint(_MdnCheckpointRequired, total=False):
    """An MDN checkpoint as :func:`load_checkpoint` returns it and ``artdata train --model mdn``
    writes it (:mod:`articulated_dataset.methods.mdn.train`): the keys every checkpoint has, then
    the columns trained and anchored (all and none where absent), the training data and run, and
    the optimiser's state to resume from."""

    anchored_columns: list[list[int]]  # column groups shifted by the image's anchor (m)
    active_columns: list[int]  # the target columns trained
    data: dict  # the training split: folder, identity, image counts
    epoch: int  # epochs finished
    finished: bool
    history: list  # one dict of losses and validation errors per epoch
    optimizer_state: dict
    scheduler_state: dict
    scaler_state: dict
    rng_state: Any  # torch.Tensor: the CPU generator's state


#: A checkpoint type of :func:`prepare_training_output` (the one its ``load`` returns).
CheckpointT = TypeVar("CheckpointT", bound=Mapping[str, Any])
#: An unreadable checkpoint's error message quotes at most this many characters of the cause.
UNREADABLE_DETAIL_CHARS = 200


def atomic_torch_save(obj: Mapping[str, Any], path: Path) -> None:
    """Write ``obj`` with ``torch.save`` to ``path`` atomically, through
    :func:`~articulated_dataset.core.safeio.atomic_file` (an unwritable path is one line)."""
    import torch

    from articulated_dataset.core.safeio import atomic_file

    # through safeio: an unwritable place (a folder, /proc, a full disk) is one line and the
    # temporary file is removed; torch.save of a path raises RuntimeError, of a file object OSError
    with atomic_file(path) as f:
        torch.save(obj, f)


def restore_training_state(ckpt: Mapping[str, Any], model, optimizer, scheduler, scaler=None) -> list[dict]:
    """Continue an interrupted training (``--resume``; the MDN's and the dense model's): load the
    checkpoint's model, optimizer, learning-rate schedule and, when given, AMP gradient-scaler
    state and torch's CPU random state; returns a copy of its per-epoch history."""
    import torch

    what = "the training state"
    try:
        what = "'model_state'"
        model.load_state_dict(ckpt["model_state"])
        what = "'optimizer_state'"
        optimizer.load_state_dict(ckpt["optimizer_state"])
        params = {id(p): p for group in optimizer.param_groups for p in group["params"]}
        for group in optimizer.param_groups:  # torch checks only the groups' sizes; a wrong moment fails at step 1
            if not all(isinstance(v, (int, float, bool, tuple, list, str, type(None))) for v in group.values()) or \
                    not all(isinstance(group[k], (int, float)) for k in ("lr", "weight_decay", "eps") if k in group):
                raise ValueError("a parameter group holds values of the wrong type")
            _check_group_numbers(group)
        for p, st in optimizer.state.items():
            for k, v in st.items():
                if torch.is_tensor(v) and v.dim() > 0 and v.shape != params.get(id(p), p).shape:
                    raise ValueError(f"state {k!r} of shape {tuple(v.shape)} for a parameter of shape {tuple(p.shape)}")
                if torch.is_tensor(v) and v.is_floating_point() and not bool(torch.isfinite(v).all()):
                    raise ValueError(f"state {k!r} holds NaN or infinite values")
                if k in NON_NEGATIVE_STATE and (not torch.is_tensor(v) or v.is_complex() or bool((v < 0).any())):
                    raise ValueError(f"state {k!r} holds negative values (a step count or a second moment)")
        what = "'scheduler_state'"
        total = getattr(scheduler, "total_steps", None)
        scheduler.load_state_dict(ckpt["scheduler_state"])
        if getattr(scheduler, "total_steps", None) != total:
            raise ValueError(f"a schedule of {getattr(scheduler, 'total_steps', None)} steps, this training has {total}")
        with warnings.catch_warnings():  # get_lr outside step() warns; it raises for a step past the schedule
            warnings.simplefilter("ignore")
            scheduler.get_lr()
        if scaler is not None:
            what = "'scaler_state'"
            scaler.load_state_dict(ckpt["scaler_state"])
        what = "'rng_state'"
        torch.set_rng_state(ckpt["rng_state"])
        what = "'history'"
        history = ckpt["history"]
        if not isinstance(history, list) or not all(isinstance(r, dict) for r in history):
            raise TypeError("not a list of per-epoch records")
        return list(history)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, RuntimeError) as exc:
        raise UserError(f"checkpoint field {what} cannot be restored ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0][:160] if str(exc) else ''}); it is not resumable") from None


#: Optimizer state entries that are counts or second moments: never negative (a negative second
#: moment makes AdamW's update NaN, a negative step a complex bias correction).
NON_NEGATIVE_STATE = ("step", "exp_avg_sq", "max_exp_avg_sq")
#: Parameter-group numbers that are rates or decays: never negative.
NON_NEGATIVE_GROUP_NUMBERS = ("lr", "initial_lr", "max_lr", "min_lr", "weight_decay")


def _check_group_numbers(group: dict) -> None:
    """A restored parameter group's numbers must be usable: finite, rates and decays >= 0,
    ``eps`` > 0 and ``betas`` two numbers in [0, 1) (else the first step turns every weight NaN,
    or fails inside the optimizer with a TypeError)."""
    def number(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    for k, v in group.items():
        if k != "params" and number(v) and not is_real_number(v):  # (an int past a float too: 10**400)
            raise ValueError(f"parameter group value {k!r} is {str(v)[:40]}")
    for k in NON_NEGATIVE_GROUP_NUMBERS:
        if number(group.get(k)) and group[k] < 0:
            raise ValueError(f"parameter group value {k!r} is negative ({group[k]})")
    if "eps" in group and not group["eps"] > 0:
        raise ValueError(f"parameter group value 'eps' is {group['eps']}, not > 0")
    if "betas" in group:
        betas = group["betas"]
        if not (isinstance(betas, (tuple, list)) and len(betas) == 2
                and all(number(b) and 0 <= b < 1 for b in betas)):
            raise ValueError(f"parameter group value 'betas' is {str(betas)[:40]}, not two numbers in [0, 1)")


#: Largest total of the uncompressed sizes a checkpoint's zip records may declare (bytes): over ten
#: times a full-preset MDN's training checkpoint (12 M weights and their two AdamW moments, ~150 MB).
MAX_CHECKPOINT_BYTES = 2 << 30
#: Largest ratio of that total to the file's size.  ``torch.save`` stores its records uncompressed
#: (ratio 1); a file re-packed with deflate shrinks float weights a little.  ``torch.load`` allocates
#: each record's declared size before reading it: a 1 MB file of deflated zeros would cost 1 GB.
MAX_CHECKPOINT_EXPANSION = 4.0
#: Deflate's largest possible ratio (RFC 1951: a 258-byte match costs at least 2 bits, ~1032:1);
#: a record declaring more than this times its compressed size lies about its size.
MAX_DEFLATE_RATIO = 1032
#: Compression methods of the zip records torch's reader decodes (stored, deflated).
READABLE_ZIP_METHODS = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED)


def check_checkpoint_records(path: Path) -> None:
    """Refuse (one line) a zip checkpoint whose records would make ``torch.load`` allocate more than
    the file can hold: a record's declared sizes that its compression method cannot give (stored
    but larger than its data, deflated past :data:`MAX_DEFLATE_RATIO`, a method torch does not
    read), or a declared total past :data:`MAX_CHECKPOINT_EXPANSION` times the file's size or
    :data:`MAX_CHECKPOINT_BYTES`.  Reads the zip directory only; a file that is not a zip is left to
    ``torch.load`` (the legacy format, or an unreadable file)."""
    from articulated_dataset.core.safeio import format_bytes

    size = path.stat().st_size
    try:
        with zipfile.ZipFile(path) as z:
            records = z.infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError):
        return
    total = 0
    for r in records:
        name = r.filename[:80]
        if r.compress_type not in READABLE_ZIP_METHODS:
            raise UserError(f"{path}: not a readable model checkpoint (record {name!r} uses zip compression method "
                            f"{r.compress_type}; torch writes records stored or deflated)")
        stored = r.compress_type == zipfile.ZIP_STORED
        if (stored and r.file_size != r.compress_size) or \
                (not stored and r.file_size > MAX_DEFLATE_RATIO * max(r.compress_size, 1)):
            raise UserError(f"{path}: not a readable model checkpoint (record {name!r} declares {r.file_size} bytes "
                            f"from {r.compress_size} {'stored' if stored else 'deflated'} bytes; its sizes are false)")
        total += r.file_size
    if total > MAX_CHECKPOINT_EXPANSION * size or total > MAX_CHECKPOINT_BYTES:
        raise UserError(f"{path}: not a readable model checkpoint (its records declare {format_bytes(total)} from a "
                        f"{format_bytes(size)} file; refused: at most {MAX_CHECKPOINT_EXPANSION:g} times the file's "
                        f"size and {format_bytes(MAX_CHECKPOINT_BYTES)})")


def read_checkpoint_file(path: str | Path, map_location="cpu"):
    """``torch.load(path, weights_only=True)`` (tensors and plain containers only: nothing in the
    file is executed) once its zip records' sizes are checked (:func:`check_checkpoint_records`);
    a missing or unreadable file is a one-line UserError.  The contents are the caller's to check
    (:func:`load_checkpoint`, the dense model's loader).  A ``NAME.safetensors`` file is read with
    its ``NAME.json``, without pickle (:mod:`~articulated_dataset.methods.safetensors_checkpoint`)."""
    import torch

    from articulated_dataset.methods.safetensors_checkpoint import is_safetensors_path, read_safetensors_checkpoint

    if is_safetensors_path(path):
        return read_safetensors_checkpoint(path, map_location)
    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint not found: {path}")
    check_checkpoint_records(path)
    try:
        with warnings.catch_warnings():  # torch's warnings on a foreign file (e.g. a bare pickle's protocol):
            warnings.simplefilter("ignore")  # the one error line below says what is wrong
            return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch's message advises weights_only=False (running the file's code): not ours to echo
        raise UserError(f"{path}: not a readable model checkpoint (not tensors and plain containers only: "
                        f"{_refusal(exc)}; checkpoints are read without running anything in them)") from None
    except Exception as exc:  # noqa: BLE001 - torch.load raises many types on a corrupt file (even IndexError)
        first = str(exc).strip().splitlines()[0][:UNREADABLE_DETAIL_CHARS] if str(exc).strip() else type(exc).__name__
        raise UserError(f"{path}: not a readable model checkpoint ({first})") from None


def _refusal(exc: Exception) -> str:
    """What torch's weights-only unpickler refused, from its message: its first line that is not
    advice about ``weights_only`` (to load with ``weights_only=False``, running the file's code)
    or a pointer to the documentation."""
    advice = ("weights_only", "Check the documentation", "file an issue", "two options", "Alternatively")
    for line in str(exc).splitlines():
        line = line.strip().removeprefix("WeightsUnpickler error:").strip()
        if line and not any(a in line for a in advice):
            return line.split(". ")[0][:UNREADABLE_DETAIL_CHARS]
    return type(exc).__name__


def prepare_training_output(split_dir: Path, class_name: str, out: Path, *, resume: bool,
                            load: Callable[[Path], CheckpointT], config, example_name: str) -> CheckpointT | None:
    """Checks shared by every ``artdata train``: the split holds ``class_name`` and is generated
    (not ingested real captures), ``out`` is a file, and ``--resume`` finds a checkpoint trained
    with the same ``config`` (``load(out)`` reads it; its ``train_config`` is compared through
    ``type(config).from_dict``).  Returns that checkpoint, or None for a new run."""
    from articulated_dataset.core.safeio import check_name_length
    from articulated_dataset.methods.safetensors_checkpoint import is_safetensors_path

    check_name_length(out)
    if is_safetensors_path(out):  # read back as a safetensors pair, a torch.save file under that name loads nowhere
        raise UserError(f"{option('out')} {out}: training writes a torch checkpoint (e.g. {example_name}); convert it "
                        f"when it is done with 'artdata export-model {option('model')} "
                        f"{Path(out).with_suffix('.pt').name} {option('fmt')} "
                        f"safetensors {option('out')} {Path(out).name}'")
    split = Split(split_dir)
    if split.class_name != class_name:
        raise UserError(f"{split_dir}: holds class {split.class_name!r}, not {class_name!r} ({option('class_name')})")
    if split.is_real:
        raise UserError(f"{split_dir} holds ingested real captures (labels NaN where not given); train on a generated "
                        f"split and use real splits with 'artdata predict'")
    if out.exists() and out.is_dir():
        raise UserError(f"{option('out')} {out} is a directory; give a file name such as {example_name}")
    if not resume:
        if out.exists():
            raise UserError(f"{out} exists; pass {option('resume')} to continue "
                            f"its training or choose another {option('out')}")
        return None
    if not out.exists():
        raise UserError(f"{option('resume')}: no checkpoint at {out} to resume from")
    ckpt = load(out)
    old = type(config).from_dict(ckpt["train_config"])
    if old != config:
        diff = [k for k in config.to_dict() if config.to_dict()[k] != old.to_dict().get(k)]
        raise UserError(f"{option('resume')}: {out} was trained with different settings ({', '.join(diff)}); "
                        f"repeat the original options")
    # the split's identity, not its recorded path (a path from a file is never looked up; a split
    # moved since still resumes); checkpoints from before the record are not checked
    from articulated_dataset.methods.mdn.data import split_identity

    recorded, current = data_record(ckpt, out).get("split"), split_identity(split_dir)
    if recorded is not None and current is not None and recorded != current:
        raise UserError(f"{option('resume')}: {out} was trained on another split ({str(recorded)[:160]}), not "
                        f"{split_dir} ({current}); resume on the same split or start a new {option('out')}")
    return ckpt


def data_record(ckpt: Mapping[str, Any], path) -> dict:
    """A checkpoint's record of its training data (``ckpt["data"]``; ``{}`` where absent or null);
    anything but a mapping is a one-line UserError naming ``path``."""
    data = ckpt.get("data")
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise UserError(f"{path}: checkpoint field 'data' is {type(data).__name__}, not a mapping (corrupt checkpoint)")
    return data


def load_checkpoint(path: str | Path, map_location="cpu") -> MdnCheckpoint:
    """Load and check an ``artdata train`` checkpoint; any problem is a one-line UserError.

    The file is read with ``torch.load(weights_only=True)`` (tensors and plain containers
    only: nothing in it is executed) and every field the package reads is checked
    (:func:`check_checkpoint`) before a network is built from it.
    """
    path = Path(path)
    ckpt = read_checkpoint_file(path, map_location)
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path}: not an artdata MDN checkpoint (written by 'artdata train')")
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise UserError(f"{path}: checkpoint version {str(ckpt.get('version'))[:40]} is not readable "
                        f"(expected {CHECKPOINT_VERSION})")
    for key in ("class_name", "layout_names", "norm_stats", "model_config", "input_config", "train_config", "model_state"):
        if key not in ckpt:
            raise UserError(f"{path}: checkpoint is missing {key!r}")
    check_checkpoint(ckpt, path)
    return cast(MdnCheckpoint, ckpt)  # (every field it reads checked above)


def check_checkpoint(ckpt: dict, path) -> None:
    """Every field of a loaded checkpoint that the package reads has the type and value
    ``artdata train`` writes: the class is registered and its target layout matches; the
    training config is valid and implies the stored model and input configs (so no size read
    from the file is allocated unchecked); the normalisation statistics fit the layout and are
    finite; the column lists are in range; the weights are finite tensors; the epoch count is
    a whole number.  Otherwise a one-line :class:`UserError` naming ``path``."""

    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.methods.mdn.model import ModelConfig
    from articulated_dataset.methods.mdn.preprocess import InputConfig
    from articulated_dataset.training.targets import NormStats, TargetLayout

    def bad(what: str) -> UserError:
        return UserError(f"{path}: corrupt checkpoint: {what}")

    name = ckpt["class_name"]
    if not isinstance(name, str):
        raise bad("class_name is not a string")
    try:
        obj_class = get_class(name)
    except UserError as exc:
        raise UserError(f"{path}: {exc}") from None
    layout = TargetLayout.for_class(obj_class.name)
    if not isinstance(ckpt["layout_names"], list) or list(ckpt["layout_names"]) != list(layout.names):
        raise UserError(f"{path}: the checkpoint's target layout differs from this version's {name!r} layout; retrain it")
    for key in ("train_config", "model_config", "input_config", "norm_stats", "model_state"):
        if not isinstance(ckpt[key], dict):
            raise bad(f"{key} is not a mapping")
    try:
        config = TrainConfig.from_dict(ckpt["train_config"])
    except TypeError as exc:
        raise bad(f"train_config ({str(exc).splitlines()[0][:120]})") from None
    try:
        config = config.resolved()
    except UserError as exc:
        raise bad(f"train_config: {exc.message}") from None
    if config.class_name != name:
        raise bad(f"train_config is for class {str(config.class_name)[:40]!r}, the checkpoint for {name!r}")
    D = len(layout.names)
    active = ckpt.get("active_columns", list(range(D)))
    if not (isinstance(active, list) and active and all(is_int(i) and 0 <= i < D for i in active)
            and active == sorted(set(active))):
        raise bad(f"active_columns must be increasing column indices in [0, {D})")
    anchored = ckpt.get("anchored_columns", [])
    if not (isinstance(anchored, list) and all(isinstance(c, list) and len(c) == 2 and all(is_int(i) and 0 <= i < D for i in c)
                                                for c in anchored)):
        raise bad(f"anchored_columns must be pairs of column indices in [0, {D})")
    try:
        model_config = ModelConfig.from_dict(ckpt["model_config"])
        input_config = InputConfig.from_dict(ckpt["input_config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise bad(f"model or input config ({type(exc).__name__}: {str(exc).splitlines()[0][:120] if str(exc) else ''})") from None
    if model_config != config.model_config(len(active)) or input_config != config.input_config():
        raise bad("model_config / input_config do not follow from its train_config")
    try:
        stats = NormStats.from_dict(ckpt["norm_stats"])
        stats.check_layout(layout)
        finite = np.isfinite(np.asarray(stats.mean, np.float64)).all() and np.isfinite(np.asarray(stats.std, np.float64)).all()
    except UserError as exc:
        raise bad(str(exc)) from None
    except (TypeError, ValueError) as exc:
        raise bad(f"norm_stats ({str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__})") from None
    if not finite or not (np.asarray(stats.std, np.float64) > 0).all():
        raise bad("norm_stats must have finite means and positive finite standard deviations")
    problem = state_problem(ckpt["model_state"])
    if problem is not None:
        raise bad(f"model_state {problem}")
    if not is_int(ckpt.get("epoch", 0)) or ckpt.get("epoch", 0) < 0:
        raise bad("epoch must be a whole number >= 0")


#: The one integer buffer of a network's state: a batch normalisation's count of training batches.
BATCH_COUNTER_SUFFIX = "num_batches_tracked"


def state_problem(state: dict) -> str | None:
    """What is wrong with a checkpoint's ``model_state`` (None: nothing): it must map parameter
    names to tensors, floating point (but for :data:`BATCH_COUNTER_SUFFIX`) and finite, every batch normalisation's running
    variance non-negative (a negative one is a NaN after its square root)."""
    import torch

    if not all(isinstance(k, str) and isinstance(v, torch.Tensor) and v.layout == torch.strided for k, v in state.items()):
        return "must map parameter names to (dense) tensors"
    if any(v.is_meta for v in state.values()):  # (map_location="cpu" leaves a meta tensor one; a live GPU network's are fine)
        return "holds tensors without values (meta tensors)"
    whole = [k for k, v in state.items() if not v.is_floating_point() and not k.endswith(BATCH_COUNTER_SUFFIX)]
    if whole:
        return f"holds weights that are not floating point ({whole[0][:60]!r})"
    if not all(bool(torch.isfinite(v).all()) for v in state.values() if v.is_floating_point()):
        return "holds NaN or infinite weights"
    if any(bool((v < 0).any()) for k, v in state.items() if k.endswith("running_var")):
        return "holds a negative batch-normalisation variance"
    return None


def build_model_from_checkpoint(ckpt: MdnCheckpoint, device="cpu"):
    """The network of a checkpoint, weights loaded, in eval mode."""
    from articulated_dataset.methods.mdn.model import MixtureDensityNetwork, ModelConfig

    model = MixtureDensityNetwork(ModelConfig.from_dict(ckpt["model_config"]))
    try:
        model.load_state_dict(ckpt["model_state"])
    except RuntimeError as exc:
        raise UserError(f"checkpoint weights do not match its model configuration ({str(exc).splitlines()[0][:160]})") from None
    return model.to(device).eval()
