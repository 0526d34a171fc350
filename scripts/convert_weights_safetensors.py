"""Convert the shipped checkpoints from ``torch.save`` files to safetensors pairs (maintainers' tool).

    python scripts/convert_weights_safetensors.py [--weights-dir articulated_dataset/methods/weights] [--keep-pt]

For every ``models.json`` entry whose ``file`` is a ``.pt``: reads it with
``torch.load(weights_only=True)``, writes ``NAME.safetensors`` (the tensors) and ``NAME.json``
(everything else) with :func:`articulated_dataset.methods.safetensors_checkpoint.write_safetensors_checkpoint`,
reads the pair back and stops unless it is the same checkpoint (every tensor's dtype, shape and bits,
every other value; :func:`~articulated_dataset.methods.safetensors_checkpoint.checkpoint_difference`),
so the models predict exactly as before.  The entry then names the pair (``file``, ``sha256``,
``bytes``, ``config``, ``config_sha256``, ``config_bytes``) and keeps the ``.pt`` it came from
(``converted_from``: file, SHA-256, size; the figures measured on it hold for the pair).  The
``.pt`` is removed unless ``--keep-pt``.  Entries already converted are left as they are.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from articulated_dataset.core.safeio import atomic_write_text
from articulated_dataset.format import sha256_file
from articulated_dataset.methods import WEIGHTS_DIR
from articulated_dataset.methods.safetensors_checkpoint import (
    SAFETENSORS_SUFFIX,
    checkpoint_difference,
    read_safetensors_checkpoint,
    write_safetensors_checkpoint,
)

#: Suffix of the ``torch.save`` checkpoints converted.
PT_SUFFIX = ".pt"


def convert_entry(entry: dict, weights_dir: Path) -> dict:
    """The ``models.json`` entry of the safetensors pair written from the entry's ``.pt`` (checked
    to read back as the same checkpoint)."""
    src = weights_dir / entry["file"]
    ckpt = torch.load(src, map_location="cpu", weights_only=True)
    dst, config = write_safetensors_checkpoint(ckpt, src.with_suffix(SAFETENSORS_SUFFIX))
    difference = checkpoint_difference(ckpt, read_safetensors_checkpoint(dst))
    if difference is not None:
        raise SystemExit(f"{dst}: does not read back as {src.name} ({difference})")
    out = {}
    for key, value in entry.items():
        if key == "file":
            value = dst.name
        elif key == "sha256":
            value = sha256_file(dst)
        out[key] = value
        if key == "bytes":
            out["bytes"] = dst.stat().st_size
            out.update(config=config.name, config_sha256=sha256_file(config), config_bytes=config.stat().st_size)
    out["converted_from"] = {"file": src.name, "sha256": entry["sha256"], "bytes": entry["bytes"]}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--weights-dir", type=Path, default=WEIGHTS_DIR, help="folder of models.json and the checkpoints")
    p.add_argument("--keep-pt", action="store_true", help="leave the converted .pt files in place")
    args = p.parse_args(argv)
    manifest = args.weights_dir / "models.json"
    models = json.loads(manifest.read_text())["models"]
    before = after = 0
    converted = []
    for i, entry in enumerate(models):
        if not entry["file"].endswith(PT_SUFFIX):
            continue
        models[i] = convert_entry(entry, args.weights_dir)
        converted.append(args.weights_dir / entry["file"])
        before += entry["bytes"]
        after += models[i]["bytes"] + models[i]["config_bytes"]
        print(f"{entry['file']} ({entry['bytes']:,} B) -> {models[i]['file']} ({models[i]['bytes']:,} B) + "
              f"{models[i]['config']} ({models[i]['config_bytes']:,} B): the same checkpoint")
    atomic_write_text(manifest, json.dumps({"models": models}, indent=1) + "\n")
    if not args.keep_pt:
        for path in converted:
            path.unlink()
    print(f"{manifest}: {len(converted)} of {len(models)} models converted, {before:,} -> {after:,} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
