"""A model written for use outside this package (``artdata export-model``; docs/dense.md, "Exporting").

* ``safetensors``: a checkpoint (a shipped model or an ``artdata train`` file) as
  ``NAME.safetensors`` + ``NAME.json`` (:mod:`.safetensors_checkpoint`), without the state only
  continuing its training reads (:data:`~.shipped.TRAINING_STATE_KEYS`); ``--model`` accepts it.
* ``onnx``: the dense network, one forward pass, as an ONNX graph: input ``x`` (B, 9, H, W), the
  network input :func:`~.dense.features.make_inputs` builds; outputs the named views of
  :meth:`~.dense.model.DenseNet.split` (:data:`ONNX_OUTPUTS`).  Before it is written, onnxruntime
  runs it on a random batch and its outputs are compared with PyTorch's
  (:data:`ONNX_ATOL`, :data:`ONNX_RTOL`).  What comes after the network (mirror averaging, the
  vote modes, the refinement, the calibrated mixture) stays in Python.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.protocol import get_method

if TYPE_CHECKING:
    from articulated_dataset.methods.dense.checkpoint import DenseCheckpoint

log = logging.getLogger(__name__)

#: ``--format`` values of ``artdata export-model``.
EXPORT_FORMATS = ("onnx", "safetensors")
#: ONNX operator set the graph is written with (onnxruntime 1.14 and later run it).
ONNX_OPSET = 17
#: The graph's input and output names (the outputs: :meth:`~.dense.model.DenseNet.split`'s keys).
ONNX_INPUT = "x"
ONNX_OUTPUTS = ("seg", "offset", "rot6", "q", "part_offset", "conf", "geometry", "geometry_conf")
#: Name of the graph's batch dimension (the only one that varies).
ONNX_BATCH_AXIS = "batch"
#: Images of the random batch (standard normal inputs) an ONNX graph is checked on.
ONNX_CHECK_IMAGES = 2
#: Largest difference allowed between onnxruntime's outputs and PyTorch's on that batch:
#: ``|onnx - torch| <= ONNX_ATOL + ONNX_RTOL * |torch|`` element-wise (float32; the two runtimes
#: order their sums differently: measured differences are about 1e-6 to 1e-5).
ONNX_ATOL = 1e-4
ONNX_RTOL = 1e-4
#: ``onnx.ModelProto.metadata_props`` key prefix of what the graph records about its model.
ONNX_METADATA_PREFIX = "artdata_"
#: How to install the ONNX export's dependencies.
ONNX_INSTALL = 'pip install onnx onnxruntime (or pip install -e ".[onnx]" from the repository checkout)'


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_model` wrote: the files, the model's name and class, and for ONNX the
    largest difference from PyTorch on the check batch (None for safetensors)."""

    files: tuple
    model: str
    class_name: str
    format: str
    max_abs_difference: float | None = None


def export_model(model: str, class_name: str | None, out: str | Path, fmt: str, *,
                 rng: np.random.Generator | None = None) -> ExportResult:
    """Write ``model`` (a shipped model's name with its ``class_name``, or a checkpoint file) to
    ``out`` in ``fmt`` (:data:`EXPORT_FORMATS`).  ``rng``: draws the ONNX check batch (default:
    ``np.random.default_rng(0)``).  A wrong model, class or format is a one-line :class:`UserError`."""
    from articulated_dataset.methods.shipped import resolve_model

    if fmt not in EXPORT_FORMATS:
        raise UserError(f"{option('fmt')} must be one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}")
    out = Path(out)
    ref = resolve_model(model, class_name)
    if fmt == "safetensors":
        return _export_safetensors(ref, out)
    if not get_method(ref.kind).onnx_export:
        raise UserError(f"{option('model')} {model}: the ONNX export covers the dense network (a shipped 'dense' or "
                        f"'dense-kinect2' model, or an 'artdata train {option('model_kind')} dense' checkpoint)")
    return _export_onnx(ref, out, np.random.default_rng(0) if rng is None else rng)


def _export_safetensors(ref, out: Path) -> ExportResult:
    from articulated_dataset.methods.safetensors_checkpoint import (
        SAFETENSORS_SUFFIX,
        checkpoint_difference,
        read_safetensors_checkpoint,
        write_safetensors_checkpoint,
    )
    from articulated_dataset.methods.shipped import load_model_checkpoint, without_training_state

    if out.suffix != SAFETENSORS_SUFFIX:
        raise UserError(f"{option('out')} {out}: a safetensors checkpoint's name ends in {SAFETENSORS_SUFFIX} "
                        f"(its configuration is written beside it as {out.stem}.json)")
    ckpt = without_training_state(load_model_checkpoint(ref))
    files = write_safetensors_checkpoint(ckpt, out)
    difference = checkpoint_difference(ckpt, read_safetensors_checkpoint(out))
    if difference is not None:  # the writer's and the reader's layouts disagree: a bug
        raise RuntimeError(f"{out}: does not read back as the checkpoint written ({difference})")
    log.info("%s: %s (%s) written as safetensors", out, ref.name, ref.class_name)
    return ExportResult(files, ref.name, ref.class_name, "safetensors")


def _named_outputs(net):
    """A module whose outputs are ``net``'s named views (:data:`ONNX_OUTPUTS`), as a tuple."""
    import torch

    class NamedOutputs(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.net = net

        def forward(self, x):
            parts = self.net.split(self.net(x))
            return tuple(parts[name] for name in ONNX_OUTPUTS)

    return NamedOutputs().eval()


def onnx_metadata(ckpt: DenseCheckpoint, ref) -> dict:
    """What an exported graph records about its model (``metadata_props``, strings): the model,
    class, joint types, network configuration, the input's channels and scales, and the SHA-256
    of the checkpoint it was exported from."""
    from articulated_dataset.format import sha256_file
    from articulated_dataset.methods.dense.features import (
        N_INPUT_CHANNELS,
        NORMAL_CHANNELS,
        OUTPUT_STRIDE,
        PIXEL_CHANNELS,
        POINT_CHANNELS,
        POINT_SCALE_M,
        VALIDITY_CHANNEL,
    )
    from articulated_dataset.methods.dense.model import OFFSET_SCALE_M

    def span(s: slice) -> list:
        return [s.start, s.stop]

    fields = {
        "model": ref.name, "class_name": ckpt["class_name"], "joint_types": ckpt["joint_types"],
        "model_config": ckpt["model_config"], "source_sha256": sha256_file(ref.path),
        "input": {"channels": N_INPUT_CHANNELS, "points": span(POINT_CHANNELS), "validity": VALIDITY_CHANNEL,
                  "normals": span(NORMAL_CHANNELS), "pixel_uv": span(PIXEL_CHANNELS), "point_scale_m": POINT_SCALE_M},
        "outputs": list(ONNX_OUTPUTS), "output_stride": OUTPUT_STRIDE, "offset_scale_m": OFFSET_SCALE_M,
    }
    return {ONNX_METADATA_PREFIX + k: v if isinstance(v, str) else json.dumps(v) for k, v in fields.items()}


def onnx_difference(graph: bytes, module, x: np.ndarray) -> float:
    """The largest ``|onnx - torch|`` over the outputs of ``graph`` (run by onnxruntime on one
    thread) and of ``module`` on the batch ``x``; a difference beyond :data:`ONNX_ATOL` +
    :data:`ONNX_RTOL` ``|torch|`` raises (the exporter's or a runtime's bug, not the user's)."""
    import torch

    from articulated_dataset.core.errors import import_optional

    ort = import_optional("onnxruntime", "checking an ONNX export", ONNX_INSTALL)
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(graph, options, providers=["CPUExecutionProvider"])
    got = session.run(list(ONNX_OUTPUTS), {ONNX_INPUT: x})
    with torch.inference_mode():
        want = [t.numpy() for t in module(torch.from_numpy(x))]
    worst = 0.0
    for name, a, b in zip(ONNX_OUTPUTS, got, want):
        if a.shape != b.shape or not np.allclose(a, b, rtol=ONNX_RTOL, atol=ONNX_ATOL):
            raise RuntimeError(f"ONNX output {name!r} differs from PyTorch's beyond atol {ONNX_ATOL:g} + "
                               f"rtol {ONNX_RTOL:g} (shapes {a.shape} and {b.shape})")
        worst = max(worst, float(np.abs(a - b).max(initial=0.0)))
    return worst


def _export_onnx(ref, out: Path, rng: np.random.Generator) -> ExportResult:
    import io
    import warnings

    import torch

    from articulated_dataset.core.errors import import_optional
    from articulated_dataset.core.safeio import atomic_write_bytes
    from articulated_dataset.methods.dense.checkpoint import build_dense_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.features import N_INPUT_CHANNELS

    onnx = import_optional("onnx", f"artdata export-model {option('fmt')} onnx", ONNX_INSTALL)
    import_optional("onnxruntime", f"artdata export-model {option('fmt')} onnx", ONNX_INSTALL)
    ckpt = load_dense_checkpoint(ref.path)
    module = _named_outputs(build_dense_model(ckpt))
    cfg = module.net.config
    x = rng.standard_normal((ONNX_CHECK_IMAGES, N_INPUT_CHANNELS, cfg.height_px, cfg.width_px)).astype(np.float32)
    buffer = io.BytesIO()
    with warnings.catch_warnings():  # the TorchScript-based exporter (dynamo=False) warns that it is not the
        warnings.simplefilter("ignore")  # default; it needs no onnxscript and exports this network exactly
        # (torch.onnx.export writes to a file object too; its annotation names paths only)
        torch.onnx.export(module, (torch.from_numpy(x),), buffer, dynamo=False, input_names=[ONNX_INPUT],  # type: ignore[arg-type]
                          output_names=list(ONNX_OUTPUTS), opset_version=ONNX_OPSET,
                          dynamic_axes={name: {0: ONNX_BATCH_AXIS} for name in (ONNX_INPUT, *ONNX_OUTPUTS)})
    graph = onnx.load_from_string(buffer.getvalue())
    onnx.helper.set_model_props(graph, onnx_metadata(ckpt, ref))
    onnx.checker.check_model(graph)
    data = graph.SerializeToString()
    worst = onnx_difference(data, module, x)
    atomic_write_bytes(out, data)
    log.info("%s: %s (%s) as ONNX, largest difference from PyTorch %.2g", out, ref.name, ref.class_name, worst)
    return ExportResult((out,), ref.name, ref.class_name, "onnx", worst)
