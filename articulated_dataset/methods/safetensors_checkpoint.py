"""Checkpoints as a pair of files read without pickle: ``NAME.safetensors`` holds every tensor (the
`safetensors <https://huggingface.co/docs/safetensors>`_ format) and ``NAME.json`` beside it
everything else the checkpoint holds (its format and version, model and training configuration,
calibration, refinement, data identity, history).

Reading either file runs nothing: the JSON is parsed as data, and the safetensors header declares
each tensor's dtype, shape and byte range, which the reader checks against the file before
copying the bytes (a file allocates at most its own size).  The shipped models
(``articulated_dataset/methods/weights/``) are stored this way; a checkpoint written by ``artdata train``
(a ``torch.save`` file, read with ``torch.load(weights_only=True)``) converts with ``artdata
export-model --format safetensors``.

Layout.  In the JSON each tensor is replaced by ``{"__tensor__": NAME}``, NAME being its key in
the safetensors file: a weight of ``model_state`` under its parameter name (so
``safetensors.torch.load_file`` gives the network's ``state_dict``), any other tensor under its
path in the checkpoint, its keys and list indices joined by ``/`` (``calibration/scale/0``).  The
safetensors header's metadata records the JSON's SHA-256 (:data:`CONFIG_SHA256_KEY`): a pair
whose halves come from different checkpoints is refused.  The JSON holds objects with string
keys, lists, strings, whole and finite real numbers, booleans and null: a checkpoint holding
anything else is refused when written (a tuple is written as a list).
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

from articulated_dataset.core.errors import UserError

#: Suffix of a checkpoint's tensor file; its configuration is the same name with :data:`CONFIG_SUFFIX`.
SAFETENSORS_SUFFIX = ".safetensors"
CONFIG_SUFFIX = ".json"
#: The JSON object that stands for a tensor: ``{TENSOR_KEY: name in the safetensors file}``.
TENSOR_KEY = "__tensor__"
#: The checkpoint key whose tensors keep their own names (the network's weights).
STATE_KEY = "model_state"
#: Separator of the path of any other tensor in its name.
PATH_SEPARATOR = "/"
#: Metadata of the safetensors header: the SHA-256 (hex) of the JSON written with it, and the
#: framework the tensors are for (the key other safetensors readers look for).
CONFIG_SHA256_KEY = "artdata_config_sha256"
FRAMEWORK_METADATA = {"format": "pt"}
#: Largest configuration file read (bytes): a shipped dense model's is about 40 kB, a training
#: history of thousands of epochs a few MB.
MAX_CONFIG_BYTES = 64 << 20
#: Characters of a path or a message quoted in an error.
QUOTE_CHARS = 80
#: How to install the safetensors reader (also in the ``torch`` extra).
SAFETENSORS_INSTALL = 'pip install safetensors (or pip install -e ".[torch]" from the repository checkout)'


def config_path(path: str | Path) -> Path:
    """The configuration file (``NAME.json``) of the tensor file ``NAME.safetensors``."""
    return Path(path).with_suffix(CONFIG_SUFFIX)


def is_safetensors_path(path: str | Path) -> bool:
    """Whether ``path`` names a checkpoint stored as a safetensors pair (by its suffix)."""
    return Path(path).suffix == SAFETENSORS_SUFFIX


def _where(path: tuple) -> str:
    return PATH_SEPARATOR.join(str(p) for p in path)[:QUOTE_CHARS] or "(the checkpoint)"


def split_tensors(ckpt: dict) -> tuple[dict, dict]:
    """``(config, tensors)``: ``ckpt`` with each tensor replaced by its placeholder, and the tensors
    by name (contiguous CPU copies), as the module docstring lays them out.  Anything JSON cannot
    hold (a key that is not a string, a non-finite number, an object of another type) or a name
    used twice is a one-line :class:`UserError`."""
    import torch

    tensors: dict = {}

    def walk(value, path: tuple):
        if isinstance(value, torch.Tensor):
            if value.layout != torch.strided or value.is_meta:
                raise UserError(f"checkpoint field {_where(path)!r} is not a dense tensor with values")
            name = path[1] if len(path) == 2 and path[0] == STATE_KEY else PATH_SEPARATOR.join(str(p) for p in path)
            if name in tensors:
                raise UserError(f"checkpoint field {_where(path)!r}: tensor name {name[:QUOTE_CHARS]!r} is used twice")
            tensors[name] = value.detach().to("cpu").clone(memory_format=torch.contiguous_format)
            return {TENSOR_KEY: name}
        if isinstance(value, dict):
            bad = next((k for k in value if not isinstance(k, str)), None)
            if bad is not None:
                raise UserError(f"checkpoint field {_where(path)!r} has a key that is not a string ({bad!r:.40}); "
                                f"JSON keys are strings")
            if TENSOR_KEY in value:
                raise UserError(f"checkpoint field {_where(path)!r} has the key {TENSOR_KEY!r}, which stands for "
                                f"a tensor")
            return {k: walk(v, path + (k,)) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [walk(v, path + (i,)) for i, v in enumerate(value)]
        if isinstance(value, float) and not math.isfinite(value):
            raise UserError(f"checkpoint field {_where(path)!r} is {value}; JSON holds finite numbers only")
        if value is None or isinstance(value, (str, bool, int, float)):
            return value
        raise UserError(f"checkpoint field {_where(path)!r} holds a {type(value).__name__}, which JSON cannot hold")

    if not isinstance(ckpt, dict):
        raise UserError(f"a checkpoint is a dict, got {type(ckpt).__name__}")
    return walk(ckpt, ()), tensors


def join_tensors(config: dict, tensors: dict, where: str) -> dict:
    """The checkpoint of :func:`split_tensors`' ``(config, tensors)``: each placeholder replaced by
    its tensor.  A placeholder naming no tensor, or a tensor no placeholder names, is a one-line
    :class:`UserError` naming ``where``."""
    used: set = set()

    def walk(value, path: tuple):
        if isinstance(value, dict):
            if TENSOR_KEY in value:
                name = value[TENSOR_KEY]
                if len(value) != 1 or not isinstance(name, str) or name not in tensors or name in used:
                    raise UserError(f"{where}: field {_where(path)!r} names no tensor of the weights file "
                                    f"({str(name)[:QUOTE_CHARS]!r})")
                used.add(name)
                return tensors[name]
            return {k: walk(v, path + (k,)) for k, v in value.items()}
        if isinstance(value, list):
            return [walk(v, path + (i,)) for i, v in enumerate(value)]
        return value

    ckpt = walk(config, ())
    unused = sorted(set(tensors) - used)
    if unused:
        raise UserError(f"{where}: the weights file holds tensors its configuration does not name "
                        f"({unused[0][:QUOTE_CHARS]!r}{' ...' if len(unused) > 1 else ''})")
    return ckpt


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a JSON number")


def write_safetensors_checkpoint(ckpt: dict, path: str | Path) -> tuple[Path, Path]:
    """Write ``ckpt`` as ``path`` (``NAME.safetensors``) and its configuration ``NAME.json``, each
    atomically (the JSON first); returns both paths.  What JSON cannot hold is a one-line
    :class:`UserError` before anything is written (:func:`split_tensors`)."""
    from articulated_dataset.core.errors import import_optional
    from articulated_dataset.core.safeio import atomic_write_bytes, atomic_write_text

    path = Path(path)
    if not is_safetensors_path(path):
        raise UserError(f"{path}: a safetensors checkpoint's name ends in {SAFETENSORS_SUFFIX}")
    st = import_optional("safetensors.torch", "writing a safetensors checkpoint", SAFETENSORS_INSTALL)
    config, tensors = split_tensors(ckpt)
    text = json.dumps(config, indent=1, allow_nan=False) + "\n"
    digest = hashlib.sha256(text.encode("utf-8")).hexdigest()
    data = st.save(tensors, metadata={**FRAMEWORK_METADATA, CONFIG_SHA256_KEY: digest})
    atomic_write_text(config_path(path), text)
    atomic_write_bytes(path, data)
    return path, config_path(path)


def _read_config_bytes(config: Path, path: Path) -> bytes:
    if not config.is_file():
        raise UserError(f"{path}: its configuration {config.name} is missing (a safetensors checkpoint is a pair: "
                        f"NAME{SAFETENSORS_SUFFIX} and NAME{CONFIG_SUFFIX} beside it)")
    try:
        with open(config, "rb") as fh:
            raw = fh.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise UserError(f"{config}: cannot read ({exc.strerror or exc})") from None
    if len(raw) > MAX_CONFIG_BYTES:
        from articulated_dataset.core.safeio import format_bytes

        raise UserError(f"{config}: larger than {format_bytes(MAX_CONFIG_BYTES)}; not a checkpoint's configuration")
    return raw


def read_safetensors_checkpoint(path: str | Path, map_location="cpu") -> dict:
    """The checkpoint stored as ``path`` (``NAME.safetensors``) and ``NAME.json``: the JSON with
    its tensor placeholders replaced by the tensors (:func:`join_tensors`), on ``map_location``.
    No pickle and no code: a missing or unreadable file, a JSON that is not one object of plain
    data, or a pair whose halves do not belong together is a one-line :class:`UserError`.  The
    contents are the caller's to check (as for a ``torch.save`` checkpoint)."""
    from articulated_dataset.core.errors import import_optional

    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint not found: {path}")
    config = config_path(path)
    raw = _read_config_bytes(config, path)
    import_optional("safetensors.torch", "reading a safetensors checkpoint", SAFETENSORS_INSTALL)
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            metadata = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError, TypeError) as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:QUOTE_CHARS * 2]
        raise UserError(f"{path}: not a readable safetensors file ({first})") from None
    if metadata.get(CONFIG_SHA256_KEY) != hashlib.sha256(raw).hexdigest():
        raise UserError(f"{path}: {config.name} is not the configuration these weights were written with "
                        f"(its SHA-256 differs from the one the weights file records)")
    from articulated_dataset.format.shards import JSON_TEXT_ERRORS

    try:
        data = json.loads(raw.decode("utf-8"), parse_constant=_reject_constant)
    except RecursionError:
        raise UserError(f"{config}: not a checkpoint's configuration (nested too deeply)") from None
    except (*JSON_TEXT_ERRORS, ValueError) as exc:
        raise UserError(f"{config}: not a checkpoint's configuration ({str(exc)[:QUOTE_CHARS * 2]})") from None
    if not isinstance(data, dict):
        raise UserError(f"{config}: not a checkpoint's configuration (not a JSON object)")
    if map_location not in (None, "cpu"):
        tensors = {name: t.to(map_location) for name, t in tensors.items()}
    return join_tensors(data, tensors, str(path))


def checkpoint_difference(a, b, path: tuple = ()) -> str | None:
    """Where two checkpoints differ (None: nowhere): the first field whose tensors differ in dtype,
    shape or any bit, whose other values differ, or whose keys differ in name or order (a tuple
    and a list with the same items are the same: JSON has lists only)."""
    import torch

    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        same = (isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor) and a.dtype == b.dtype
                and a.shape == b.shape and torch.equal(a.cpu(), b.cpu()))
        return None if same else f"{_where(path)}: the tensors differ"
    if isinstance(a, dict) and isinstance(b, dict):
        if list(a) != list(b):
            return f"{_where(path)}: the keys differ"
        return next((d for k in a if (d := checkpoint_difference(a[k], b[k], path + (k,))) is not None), None)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return f"{_where(path)}: the lengths differ"
        return next((d for i, (x, y) in enumerate(zip(a, b))
                     if (d := checkpoint_difference(x, y, path + (i,))) is not None), None)
    if type(a) is not type(b) or a != b:
        return f"{_where(path)}: {str(a)[:40]!r} and {str(b)[:40]!r} differ"
    return None
