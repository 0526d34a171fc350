"""``artdata export-model``: a shipped model or a checkpoint as ONNX (the dense network) or as a
safetensors pair (docs/dense.md, "Exporting")."""

from __future__ import annotations

from pathlib import Path

import click

from articulated_dataset.cli.options import ClassChoice, prepare_torch
from articulated_dataset.core.errors import UserError
from articulated_dataset.methods.export import EXPORT_FORMATS


@click.command("export-model")
@click.option("--model", default="dense", show_default=True,
              help="A shipped model (dense, dense-kinect2, mdn-small; see 'artdata models') or a checkpoint file "
                   "(.pt from 'artdata train', or .safetensors with its .json).")
@click.option("--class", "class_name", type=ClassChoice(), default=None,
              help="The class of a shipped model (a checkpoint file carries its own).")
@click.option("--format", "fmt", type=click.Choice(EXPORT_FORMATS), required=True,
              help="onnx: the dense network's forward pass as an ONNX graph, checked against PyTorch with "
                   "onnxruntime (needs the onnx extra); safetensors: the checkpoint as NAME.safetensors + "
                   "NAME.json, without training state, loadable with --model.")
@click.option("--out", type=click.Path(dir_okay=False), required=True,
              help="File to write: FILE.onnx, or NAME.safetensors (NAME.json is written beside it).")
@click.option("--overwrite", is_flag=True, help="Replace existing output files.")
@click.option("--quiet", "-q", is_flag=True, help="No summary.")
def export_model_cmd(model, class_name, fmt, out, overwrite, quiet):
    """Export a model for use outside this package: the dense network as ONNX (the voting, refinement and
    calibration after it stay in Python), or any checkpoint as safetensors + JSON (read without pickle)."""
    from articulated_dataset.core.safeio import check_can_create, check_outputs_distinct
    from articulated_dataset.methods.safetensors_checkpoint import config_path, is_safetensors_path

    out = Path(out)
    outputs = [out, config_path(out)] if fmt == "safetensors" else [out]
    check_outputs_distinct([model, *([config_path(model)] if is_safetensors_path(model) else [])], outputs)
    for path in outputs:
        if path.is_dir():
            raise UserError(f"--out {path} is a directory; give a file name")
        if path.exists() and not overwrite:
            raise UserError(f"{path} exists; pass --overwrite to replace it")
        check_can_create(path)
    prepare_torch(None)
    from articulated_dataset.methods.export import ONNX_ATOL, ONNX_CHECK_IMAGES, ONNX_RTOL, export_model

    result = export_model(model, class_name, out, fmt)
    if quiet:
        return
    names = " and ".join(str(p) for p in result.files)
    if fmt == "onnx":
        click.echo(f"{names}: the {result.model} network for {result.class_name}; onnxruntime's outputs on a random "
                   f"batch of {ONNX_CHECK_IMAGES} are within {result.max_abs_difference:.1g} of PyTorch's "
                   f"(allowed: {ONNX_ATOL:g} + {ONNX_RTOL:g} x |value|)")
    else:
        click.echo(f"{names}: the {result.model} model for {result.class_name} (weights and configuration, read "
                   f"without pickle: --model {out})")


COMMANDS = [export_model_cmd]
