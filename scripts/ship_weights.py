"""Package trained checkpoints as the shipped models (maintainers' tool; see docs/model.md).

    python scripts/ship_weights.py --dense-dir RUNS --mdn-dir RUNS [--results shipped.json]
    python scripts/ship_weights.py --dense-dir RUNS --mdn-dir RUNS --classes cabinet --update [--results shipped.json]
    python scripts/ship_weights.py --dense-dir EMPTY --mdn-dir EMPTY --dense-kinect2-dir RUNS --update \
        --results shipped.json --results shipped-kinect2.json

Reads ``RUNS/dense-<class>.pt`` (``artdata train --model dense``),
``RUNS/mdn-small-<class>.pt`` (``artdata train --small``) and, with ``--dense-kinect2-dir``,
``RUNS/dense-kinect2-<class>.pt`` (``artdata train --model dense --noise kinect2``), keeps what inference needs
(:func:`articulated_dataset.methods.strip_for_shipping`: no optimizer, schedule or RNG
state), writes ``articulated_dataset/methods/weights/<model>-<class>.safetensors`` with its ``.json``
(:mod:`articulated_dataset.methods.safetensors_checkpoint`: read without pickle) and
``articulated_dataset/methods/weights/models.json`` (files, SHA-256s, sizes, training data and
recipe, history, and the test figures of ``benchmarks/shipped_models.py --json`` when
``--results`` is given: ``test`` from the noise-free test split, ``test_kinect2`` from the same
objects through the Kinect v2 noise model, ``--noise kinect2``).  Only finished trainings are shipped.  ``--update`` keeps the manifest's
other entries (the models not shipped now) and updates their test figures from ``--results``
where those were measured on the same file (SHA-256).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from articulated_dataset.classes.registry import class_names, get_class
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.tables import TABLE_NAMES
from articulated_dataset.format import sha256_file
from articulated_dataset.format.manifest import DEFAULT_FRAMING, FRAMINGS, MANIFEST_NAME, read_manifest
from articulated_dataset.methods import MODELS_MANIFEST, SHIPPED, WEIGHTS_DIR, strip_for_shipping
from articulated_dataset.methods.dense.train import split_generation
from articulated_dataset.methods.mdn.checkpoint import read_checkpoint_file
from articulated_dataset.methods.safetensors_checkpoint import SAFETENSORS_SUFFIX, write_safetensors_checkpoint

MACHINE = "2-core x86_64 CPU VM shared with other jobs, no GPU, PyTorch 2.13.0 CPU"
#: Per model kind (``SHIPPED``): the training command, ``{file}`` the shipped model's file.
TRAIN_COMMANDS = {
    "dense": "artdata train --model dense --class {c} --data data/{c}/train --out {file}{opts}",
    "mdn": "artdata train --class {c} --data data/{c}/train --out {file} --small --max-objects 1000 --seed 0",
}
FILES = {"dense": "dense-{c}.pt", "dense-kinect2": "dense-kinect2-{c}.pt", "mdn-small": "mdn-small-{c}.pt"}
#: The test figures kept per model: manifest key -> the noise model of the test split measured.
TEST_KEYS = {"test": "none", "test_kinect2": "kinect2"}


def _data_command(c: str, ckpt: dict) -> tuple[str, int]:
    """The generate command of the checkpoint's training split (the generation settings the
    checkpoint recorded; else from the split's manifest when it is still there; else the shipped
    recipe's seed-0 split) and its seed."""
    data = ckpt.get("data", {})
    generated = data.get("generated") or split_generation(Path(data.get("split_dir", "")))
    # the split is gone and nothing was recorded: the documented default recipe
    n, seed = (int(generated["n_objects"]), int(generated["seed"])) if generated else (4000, 0)
    data = "data" if seed == 0 else f"data-seed{seed}"
    return f"artdata generate --class {c} --n {n} --split train --seed {seed} --out {data}", seed


def _table_name(c: str, split_folder: Path) -> str:
    """The named table (``artdata generate --table``) a split of class ``c`` was generated with,
    read from its manifest (``paper`` when the manifest is gone); another table is an error: the
    recipe could not be repeated."""
    if not (split_folder / MANIFEST_NAME).is_file():
        return "paper"
    stored = read_manifest(split_folder)["config"].get("table")
    obj_class = get_class(c)
    for name in TABLE_NAMES:
        try:
            table = obj_class.named_table(name)
        except UserError:  # the class has no such table
            continue
        if stored is None or json.loads(table.to_json()) == stored:
            return name
    raise ValueError(f"{split_folder}: its sampling table is none of the class's named tables")


def _mixture_commands(c: str, ckpt: dict, name: str) -> tuple[str, str] | None:
    """For a checkpoint trained on a mixture of splits (``data.splits``): the generate command of
    every split (its seed, size and framing, read from the split's manifest where it is still
    there) joined by ``&&``, and the positional-DIR training command with ``--mix-weights``."""
    splits = (ckpt.get("data") or {}).get("splits")
    if not splits:
        return None
    generates, dirs = [], []
    for rec in splits:
        ident = rec["split"]
        framing = DEFAULT_FRAMING
        split_folder = Path(rec.get("split_dir", ""))
        if (split_folder / MANIFEST_NAME).is_file():
            framing = read_manifest(split_folder)["config"].get("framing", DEFAULT_FRAMING)
            if framing not in FRAMINGS:
                raise ValueError(f"{split_folder}: unknown framing {str(framing)[:40]!r} in its manifest")
        default = framing == DEFAULT_FRAMING
        table = _table_name(c, split_folder)
        out = f"data-seed{ident['seed']}" + ("" if default else f"-{framing}") + ("" if table == "paper" else f"-{table}")
        generates.append(f"artdata generate --class {c} --n {ident['n_objects']} --split train --seed {ident['seed']}"
                         + ("" if default else f" --framing {framing}") + ("" if table == "paper" else f" --table {table}")
                         + f" --out {out}")
        dirs.append(f"{out}/{c}/train")
    weights = ",".join(f"{rec['weight']:g}" for rec in splits)
    train = TRAIN_COMMANDS["dense"].format(c=c, file=FILES[name].format(c=c), opts="").replace(
        f"--data data/{c}/train", " ".join(dirs) + f" --mix-weights {weights}")
    return " && ".join(generates), train


def _previous_record(init_from: str, shipped: list[dict]) -> dict | None:
    """The models.json record (before this run) of the weights a training was continued from, when
    those were shipped weights (found by SHA-256), so the lineage of a continuation is kept."""
    path = Path(init_from)
    if not path.is_file():
        return None
    digest = sha256_file(path)
    for e in shipped:
        if digest in _digests(e):
            return {"file": e["file"], "sha256": e["sha256"], "training": e["training"]}
    return None


def _digests(entry: dict) -> set:
    """The SHA-256s a shipped model's weights had: its file's and, for a pair converted from a
    ``.pt`` (scripts/convert_weights_safetensors.py), that file's (the same checkpoint)."""
    return {entry["sha256"], (entry.get("converted_from") or {}).get("sha256")} - {None}


def _unshipped_record(c: str, init_from: str, shipped) -> dict:
    """The lineage of a continuation whose starting weights were never shipped: that checkpoint's
    own training record (itself continued from shipped weights, or trained from scratch), when the
    file is still there; its name otherwise."""
    path = Path(init_from)
    if not path.is_file():
        return {"checkpoint": path.name}
    init = read_checkpoint_file(path)  # a .pt (weights_only: no code runs) or a safetensors pair
    if init.get("transplant") is not None:  # another class's weights (scripts/transplant_dense.py)
        t = init["transplant"]
        return {"checkpoint": path.name, "transplant": t,
                "command": f"python scripts/transplant_dense.py --from {t['from']['file']} --like {t['like']['file']} "
                           f"--out {path.name}"}
    parent = init.get("train_config", {}).get("init_from")
    previous = _previous_record(parent, shipped) if parent else None
    return {"checkpoint": path.name, "training": _training_record("dense", c, init, previous, shipped)}


def _refit_note(ckpt: dict) -> str:
    """How a refitted checkpoint's inference was fitted: ``--clean`` where training used a noise
    model and the refit did not (its ``refit_of`` records the validation images' noise)."""
    # (a refit from before --clean recorded no validation_noise: it fitted as training did)
    refit = ckpt["refit_of"]
    clean = ckpt.get("train_config", {}).get("noise") is not None and refit.get("validation_noise", "as trained") is None
    if refit.get("calibration_only"):
        return (f"scripts/fit_dense_inference.py --checkpoint {refit['file']}{' --clean' if clean else ''} "
                "--calibration-only: the calibration (the modes' scales and the outlier component) on the same "
                f"validation objects{', noise-free' if clean else ''}, the refinement kept")
    if clean:
        return (f"scripts/fit_dense_inference.py --checkpoint {refit['file']} --clean: on the same "
                "validation objects, noise-free")
    return "scripts/fit_dense_inference.py on the same validation objects"


def _training_record(name: str, c: str, ckpt: dict, previous: dict | None = None, shipped=()) -> dict:
    refit = ckpt.get("refit_of")
    if refit is not None:  # shipped weights whose inference was refitted (scripts/fit_dense_inference.py)
        for e in shipped:
            if refit["sha256"] in _digests(e):
                note = _refit_note(ckpt)
                if refit.get("calibration_only") and e["training"].get("refit"):  # a refit of a refit: both, in order
                    note = f"{e['training']['refit']}; then {note}"
                rec = {**e["training"], "refinement": ckpt["refinement"],
                       "refinement_validation": ckpt.get("refinement_report"), "refit": note}
                if (ckpt.get("data") or {}).get("generated"):  # the split it was fitted on, named by the refit
                    before = rec["data_command"].split("--out ")[-1]
                    rec["data_command"] = _data_command(c, ckpt)[0]
                    rec["command"] = rec["command"].replace(f"--data {before}/", f"--data {rec['data_command'].split('--out ')[-1]}/")
                if ckpt.get("selection") is not None:
                    rec["selection"] = ckpt["selection"]
                return rec
    tc = ckpt.get("train_config", {})
    data_command, seed = _data_command(c, ckpt)
    data = data_command.split("--out ")[-1]
    dense = SHIPPED[name] == "dense"
    if dense:
        opts = f" --epochs {tc.get('epochs')}" + (f" --lr {tc.get('lr')}" if tc.get("lr") != 3e-3 else "")
        if tc.get("init_from"):
            opts += f" --init-from {Path(tc['init_from']).name}"
        if tc.get("origin_weight", 1.0) != 1.0:
            opts += f" --origin-weight {tc['origin_weight']:g}"
        if tc.get("batch_size", 64) != 64:
            opts += f" --batch-size {tc['batch_size']}"
        if tc.get("val_fraction", 0.05) != 0.05:
            opts += f" --val-fraction {tc['val_fraction']:g}"
        if tc.get("max_objects") is not None:
            opts += f" --max-objects {tc['max_objects']}"
        if tc.get("noise") is not None:
            opts += f" --noise {tc['noise']}" + (f" --noise-fraction {tc['noise_fraction']:g}"
                                                 if tc.get("noise_fraction", 0.5) != 0.5 else "")
        if ckpt.get("device") == "cuda":
            opts += " --device cuda"
        command = TRAIN_COMMANDS["dense"].format(c=c, file=FILES[name].format(c=c), opts=opts).replace("data/", f"{data}/")
        mixture = _mixture_commands(c, ckpt, name)
        if mixture is not None:
            data_command, command = mixture[0], mixture[1] + opts
    else:
        command = TRAIN_COMMANDS["mdn"].format(c=c, file=FILES[name].format(c=c))
    rec = {"data_command": data_command, "command": command, "seed": int(tc.get("seed", 0)),
           "machine": ckpt.get("machine") or MACHINE}
    if ckpt.get("refinement") is not None:
        rec["refinement"] = ckpt["refinement"]
        rec["refinement_validation"] = ckpt.get("refinement_report")
    if ckpt.get("selection") is not None:  # which candidate was shipped, chosen on validation objects
        rec["selection"] = ckpt["selection"]
    if refit is not None:  # a refit of a full checkpoint (not of a shipped file): its own record, marked
        rec["refit"] = _refit_note(ckpt)
    if dense and tc.get("init_from"):
        rec["continued_from"] = previous if previous is not None else _unshipped_record(c, tc["init_from"], shipped)
    hist = ckpt.get("history", [])
    if dense:
        rec.update(objects=ckpt["data"]["n_objects"], train_images=ckpt["data"]["n_train_images"],
                   val_images=ckpt["data"]["n_val_images"], steps=ckpt["step"], cpu_seconds=round(ckpt.get("cpu_seconds", 0.0)),
                   validation=hist[-1] if hist else None)
    else:
        rec.update(objects=int(ckpt["train_config"].get("max_objects") or 0), train_images=ckpt["data"]["n_train"],
                   val_images=ckpt["data"]["n_val"], epochs=ckpt["epoch"],
                   seconds=round(sum(h.get("seconds", 0.0) for h in hist)), validation=hist[-1] if hist else None)
    return rec


def _test_record(r: dict, metric_version: int) -> dict:
    """A model's ``test`` entry from its ``benchmarks/shipped_models.py --json`` record (with the
    noise model where the test split had one; the speed only from the noise-free split, where the
    figures are measured alone on the machine)."""
    rec = {"pos_cm": r["axis_position_error_cm"], "rot_deg": r["axis_rotation_error_deg"],
           "config": r["configuration_error"], "coverage_90": r["coverage_90"],
           **({"nll": r["nll"]} if r.get("nll") is not None else {}),
           "images": r["n_images"], "objects": r["test_objects"], "seed": r["test_seed"],
           "images_per_s": r["images_per_s"], "metric_version": metric_version}
    if r.get("noise", "none") != "none":
        rec["noise"] = r["noise"]
        del rec["images_per_s"]
    return rec


def _tests(results: dict, name: str, c: str, sha256: str, *, require_sha256: bool = False) -> dict:
    """The manifest's test entries (:data:`TEST_KEYS`) of a model file from the measured results
    measured on this very file (by SHA-256; a result without one counts as this file's unless
    ``require_sha256``)."""
    out = {}
    for key, noise in TEST_KEYS.items():
        r = results.get((name, c, noise))
        if r is not None and r.get("sha256", None if require_sha256 else sha256) == sha256:
            out[key] = _test_record(r, r["metric_version"])
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dense-dir", type=Path, required=True)
    p.add_argument("--mdn-dir", type=Path, required=True)
    p.add_argument("--dense-kinect2-dir", type=Path, default=None, help="folder of the dense-kinect2-<class>.pt to ship")
    p.add_argument("--results", type=Path, action="append", default=[],
                   help="benchmarks/shipped_models.py --json output (repeatable: with and without --noise)")
    p.add_argument("--classes", nargs="+", default=None)
    p.add_argument("--previous", type=Path, action="append", default=None,
                   help="models.json of weights shipped before (repeatable; default: the current one); "
                        "continuations and refits of those weights keep their training record from it")
    p.add_argument("--update", action="store_true",
                   help="keep the current manifest's entries of the models not shipped now (their test figures "
                        "updated from --results where measured on the same file)")
    args = p.parse_args(argv)
    results = {}
    for path in args.results:
        doc = json.loads(path.read_text())
        for r in doc["results"]:
            results[(r["model"], r["class"], r.get("noise") or "none")] = {**r, "metric_version": doc["metric_version"]}
    WEIGHTS_DIR.mkdir(exist_ok=True)
    entries = []
    shipped = [e for path in (args.previous or [MODELS_MANIFEST]) if path.is_file()
               for e in json.loads(path.read_text())["models"]]
    for c in args.classes or class_names():
        for name, folder in (("dense", args.dense_dir), ("dense-kinect2", args.dense_kinect2_dir), ("mdn-small", args.mdn_dir)):
            if folder is None:
                continue
            src = folder / FILES[name].format(c=c)
            if not src.is_file():
                print(f"skip {name} {c}: no {src}", file=sys.stderr)
                continue
            ckpt = torch.load(src, map_location="cpu", weights_only=True)
            if not ckpt.get("finished"):
                print(f"skip {name} {c}: training not finished", file=sys.stderr)
                continue
            init_from = ckpt.get("train_config", {}).get("init_from")
            previous = _previous_record(init_from, shipped) if SHIPPED[name] == "dense" and init_from else None
            dst, config = write_safetensors_checkpoint(strip_for_shipping(ckpt),
                                                       (WEIGHTS_DIR / FILES[name].format(c=c)).with_suffix(SAFETENSORS_SUFFIX))
            entry = {"name": name, "class_name": c, "kind": SHIPPED[name], "file": dst.name,
                     "sha256": sha256_file(dst), "bytes": dst.stat().st_size, "config": config.name,
                     "config_sha256": sha256_file(config), "config_bytes": config.stat().st_size,
                     "config_unit": "cm" if "prismatic" in str(ckpt.get("joint_types", "")) or c == "drawer" else "deg",
                     "training": _training_record(name, c, ckpt, previous, shipped)}
            entry.update(_tests(results, name, c, entry["sha256"]))
            entries.append(entry)
            print(f"{dst}: {entry['bytes'] / 1e6:.2f} MB")
    if args.update and MODELS_MANIFEST.is_file():
        shipped_now = {(e["name"], e["class_name"]) for e in entries}
        kept = [e for e in json.loads(MODELS_MANIFEST.read_text())["models"] if (e["name"], e["class_name"]) not in shipped_now]
        for e in kept:
            for digest in _digests(e):  # figures measured on the .pt a pair was converted from hold for the pair
                e.update(_tests(results, e["name"], e["class_name"], digest, require_sha256=True))
        order = {(n, c): i for i, (c, n) in enumerate((c, n) for c in class_names() for n in FILES)}
        entries = sorted(entries + kept, key=lambda e: order.get((e["name"], e["class_name"]), len(order)))
    MODELS_MANIFEST.write_text(json.dumps({"models": entries}, indent=1) + "\n")
    total = sum(e["bytes"] + e.get("config_bytes", 0) for e in entries)
    print(f"{MODELS_MANIFEST}: {len(entries)} models, {total / 1e6:.1f} MB of weights")
    return 0


if __name__ == "__main__":
    sys.exit(main())
