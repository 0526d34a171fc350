"""``artdata models``: the pretrained models shipped with the package."""

from __future__ import annotations

import json
import re
import textwrap

import click

#: Test sets of the figures in models.json: (key, what the test data is).
TEST_SETS = (("test", "clean"), ("test_kinect2", "kinect2 noise"))
#: Most characters per line of the table.
TABLE_WIDTH = 100


@click.command("models")
@click.option("--json", "as_json", is_flag=True, help="Print the full descriptions (training data, figures) as JSON.")
def models_cmd(as_json):
    """List the shipped models: one row per model, class and test data, with its training data and
    test figures (docs/dense.md for dense and dense-kinect2, docs/model.md for mdn-small)."""
    from articulated_dataset.methods import shipped_models

    entries = shipped_models()
    if as_json:
        click.echo(json.dumps(entries, indent=2))
        return
    if not entries:
        click.echo("no shipped models in this installation")
        return
    for line in model_table(entries):
        click.echo(line)


def training_data(m: dict) -> str:
    """``"12000 obj"`` or ``"4000 obj, kinect2"``: the objects a model was trained on and the depth
    noise model of its last training (``--noise``)."""
    t = m.get("training", {})
    noise_option = re.search(r"--noise (\S+)", str(t.get("command", "")))
    noise = noise_option.group(1) if noise_option else ""
    objects = f"{t['objects']} obj" if "objects" in t else "-"
    return f"{objects}, {noise}" if noise else objects


def model_table(entries: list[dict]) -> list[str]:
    """One row per (model, class, test set) holding figures; the columns name what each number is."""
    head = (f"{'model':<13} {'class':<13} {'training data':<17} {'test data':<13} {'pos cm':>7} {'rot deg':>7} "
            f"{'config':>9} {'cov90':>6} {'NLL':>7}")
    lines = [head]
    for key, test_data in TEST_SETS:
        for m in entries:
            t = m.get(key)
            if not t and key == TEST_SETS[0][0] and not any(m.get(k) for k, _ in TEST_SETS):
                t, test_data_shown = {}, "not measured"  # listed all the same, its figures "-"
            elif not t:
                continue
            else:
                test_data_shown = test_data
            unit = "cm" if m.get("config_unit") == "cm" else "deg"
            cfg = f"{t['config']:.2f} {unit}" if "config" in t else "-"
            pos = f"{t['pos_cm']:.2f}" if "pos_cm" in t else "-"
            rot = f"{t['rot_deg']:.2f}" if "rot_deg" in t else "-"
            cov = f"{t['coverage_90']:.3f}" if "coverage_90" in t else "-"
            nll = f"{t['nll']:.1f}" if "nll" in t else "-"  # mean nats per image; absent where not measured
            lines.append(f"{m['name']:<13} {m['class_name']:<13} {training_data(m):<17} {test_data_shown:<13} {pos:>7} "
                         f"{rot:>7} {cfg:>9} {cov:>6} {nll:>7}")
    legend = ("test data: 1,000 unseen test objects per class (seed 2026), clean depth or with Kinect v2 depth "
              "noise (artdata generate --noise kinect2); scored with artdata score, metric version 2 or 3 (each model's "
              "is in --json; the paper's three columns are the same numbers in both). pos cm: axis position; rot deg: frame heading; "
              "config: configuration error; cov90: 90% interval coverage; NLL: mean nats per image. Files, "
              "checksums and training commands: artdata models --json; docs/dense.md, docs/model.md.")
    return lines + [""] + textwrap.wrap(legend, TABLE_WIDTH)


COMMANDS = [models_cmd]
