"""``artdata models``: the pretrained models shipped with the package."""

from __future__ import annotations

import json

import click


@click.command("models")
@click.option("--json", "as_json", is_flag=True, help="Print the full descriptions (training data, figures) as JSON.")
def models_cmd(as_json):
    """List the shipped models: name, class, training data and test figures (docs/model.md)."""
    from ..models import shipped_models

    entries = shipped_models()
    if as_json:
        click.echo(json.dumps(entries, indent=2))
        return
    if not entries:
        click.echo("no shipped models in this installation")
        return
    _table(entries, "test")
    click.echo("test figures: 1,000 unseen test objects per class (seed 2026), artdata score metric version 2 "
               "(cov90: 90% interval coverage; NLL: mean nats per image); details: artdata models --json, docs/dense.md")
    noisy = [m for m in entries if "test_kinect2" in m]
    if noisy:
        click.echo("")
        _table(noisy, "test_kinect2")
        click.echo("the same test objects with Kinect v2 depth noise (artdata generate --noise kinect2): what a real "
                   "sensor's depth costs; dense-kinect2 is trained for it (docs/real_data.md)")


def _table(entries: list[dict], key: str) -> None:
    """One row per model: its name, class, training objects and the test figures under ``key``."""
    click.echo(f"{'model':<13} {'class':<13} {'train objects':>13} {'pos cm':>7} {'rot deg':>8} {'config':>12} "
               f"{'cov90':>6} {'NLL':>9}  file")
    for m in entries:
        t = m.get(key, {})
        unit = "cm" if m.get("config_unit") == "cm" else "deg"
        cfg = f"{t['config']:.2f} {unit}" if "config" in t else "-"
        pos = f"{t['pos_cm']:.2f}" if "pos_cm" in t else "-"
        rot = f"{t['rot_deg']:.2f}" if "rot_deg" in t else "-"
        cov = f"{t['coverage_90']:.3f}" if "coverage_90" in t else "-"
        nll = f"{t['nll']:.1f}" if "nll" in t else "-"  # mean nats per image; absent where not measured
        click.echo(f"{m['name']:<13} {m['class_name']:<13} {m.get('training', {}).get('objects', '-'):>13} {pos:>7} "
                   f"{rot:>8} {cfg:>12} {cov:>6} {nll:>9}  {m['file']}")


COMMANDS = [models_cmd]
