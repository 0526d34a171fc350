"""benchmarks/third_party.py: a mapping file's objects generated, predicted and scored, with one
table per object and per class; a bad entry or a failing command stops with one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from articulated_dataset.benchmark import score
from helpers_core import ROOT, assert_one_line_error, load_script, write_flap_urdf

pytest.importorskip("torch")

#: The flap URDF's door is hinged on a vertical side edge, as a microwave's.
FLAP_CLASS = "microwave"
#: The first words of the script's error line.
SCRIPT_ERROR_PREFIX = "third_party: error: "
FIGURES = ("axis_position_error_cm", "axis_rotation_error_deg", "configuration_error", "axis_direction_error_deg",
           "axis_line_distance_cm", "mechanism_side_accuracy", "chirality_accuracy", "cutoff_fraction")


def bench():
    return load_script(ROOT / "benchmarks" / "third_party.py", "third_party_bench")


def write_mapping(folder: Path, **entry) -> Path:
    """``folder/objects.json`` naming the flap URDF (``folder/urdf/flap.urdf``) with ``entry``'s keys."""
    write_flap_urdf(folder / "urdf")
    path = folder / "objects.json"
    path.write_text(json.dumps({"objects": [{"urdf": "urdf/flap.urdf", "joints": ["hinge"], "class": FLAP_CLASS,
                                             "name": "flap", **entry}]}))
    return path


@pytest.mark.slow
def test_each_object_is_generated_predicted_and_scored(tmp_path, capsys):
    b = bench()
    mapping = write_mapping(tmp_path)
    work, out = tmp_path / "work", tmp_path / "result.json"
    args = [str(mapping), "--out", str(work), "--images", "2", "--workers", "1", "--json", str(out)]
    assert b.main(args) == 0
    text = capsys.readouterr().out
    assert "per object" in text and "per class" in text and "cut-off" in text and "dir deg" in text
    result = json.loads(out.read_text())
    assert result["metric_version"] == 3
    (obj,) = result["objects"]
    assert obj["name"] == "flap" and obj["class"] == FLAP_CLASS and obj["n_images"] == 2
    assert set(obj["figures"]) == set(FIGURES) and all(obj["figures"][k] is not None for k in FIGURES)
    assert 0 <= obj["figures"]["cutoff_fraction"] <= 1 and 0 <= obj["figures"]["mechanism_side_accuracy"] <= 1
    generate, predict = obj["commands"]
    assert generate.startswith("artdata generate --urdf ") and "--images 2" in generate and "--split test" in generate
    assert predict.startswith("artdata predict --model dense ") and f"--as-class {FLAP_CLASS}" in predict
    # the figures are the scorer's, on the files the commands wrote
    row = score(work / "predictions" / "flap.h5", work / "data" / "flap" / "test", metric_version=3).rows[0]
    assert obj["figures"]["axis_position_error_cm"] == pytest.approx(row.metrics["axis_position_error_cm"][0])
    (cls,) = result["classes"]
    assert cls["class"] == FLAP_CLASS and cls["objects"] == ["flap"] and cls["n_images"] == 2
    assert cls["figures"] == pytest.approx(obj["figures"])
    # a finished entry is kept with --resume, and its output stops a run without it
    record = work / "results" / "flap.json"
    before = record.stat().st_mtime_ns
    assert b.main([*args, "--resume"]) == 0 and record.stat().st_mtime_ns == before
    capsys.readouterr()
    assert_one_line_error((b.main(args), *capsys.readouterr()), "flap", "--resume", prefix=SCRIPT_ERROR_PREFIX)


def test_class_means_are_over_the_images_of_the_class():
    b = bench()

    def record(name, cls, n, pos, side):
        figures = {k: None for k in FIGURES} | {"axis_position_error_cm": pos, "mechanism_side_accuracy": side}
        counts = {k: n for k, v in figures.items() if v is not None}
        return {"name": name, "class": cls, "n_images": n, "configuration_units": "deg", "figures": figures,
                "image_counts": counts}

    rows = b.class_means([record("a", "cabinet", 2, 10.0, 0.5), record("b", "drawer", 4, 3.0, None),
                          record("c", "cabinet", 6, 2.0, 1.0)])
    assert [r["class"] for r in rows] == ["cabinet", "drawer"]
    cab, drawer = rows
    assert cab["objects"] == ["a", "c"] and cab["n_images"] == 8
    assert cab["figures"]["axis_position_error_cm"] == pytest.approx((2 * 10.0 + 6 * 2.0) / 8)
    assert cab["figures"]["mechanism_side_accuracy"] == pytest.approx((2 * 0.5 + 6 * 1.0) / 8)
    assert drawer["figures"]["mechanism_side_accuracy"] is None and drawer["figures"]["cutoff_fraction"] is None


@pytest.mark.parametrize("entry, needle", [({"urdf": "urdf/missing.urdf"}, "URDF file not found"),
                                           ({"class": "washing_machine"}, "unknown class 'washing_machine'"),
                                           ({"colour": "red"}, "unknown key(s) colour")])
def test_a_bad_mapping_entry_is_one_line(tmp_path, capsys, entry, needle):
    mapping = write_mapping(tmp_path, **entry)
    code = bench().main([str(mapping), "--out", str(tmp_path / "work")])
    assert_one_line_error((code, *capsys.readouterr()), "objects[0]", needle, prefix=SCRIPT_ERROR_PREFIX)
    assert not (tmp_path / "work").exists()


def test_a_failing_command_is_one_line_naming_the_object(tmp_path, capsys):
    """The flap's one revolute joint is not a drawer's: predict --as-class drawer refuses it."""
    mapping = write_mapping(tmp_path, **{"class": "drawer"})
    code = bench().main([str(mapping), "--out", str(tmp_path / "work"), "--images", "1", "--workers", "1"])
    assert_one_line_error((code, *capsys.readouterr()), "flap: artdata predict failed", "joints",
                          prefix=SCRIPT_ERROR_PREFIX)


def test_json_yaml_and_toml_mappings_read_alike(tmp_path):
    b = bench()
    write_mapping(tmp_path, scale="auto:microwave")
    (tmp_path / "objects.yaml").write_text("objects:\n  - urdf: urdf/flap.urdf\n    joints: hinge\n"
                                           "    class: microwave\n    name: flap\n    scale: auto:microwave\n")
    (tmp_path / "objects.toml").write_text('[[objects]]\nurdf = "urdf/flap.urdf"\njoints = ["hinge"]\n'
                                           'class = "microwave"\nname = "flap"\nscale = "auto:microwave"\n')
    entries = [b.read_mapping(tmp_path / f"objects.{ext}") for ext in ("json", "yaml", "toml")]
    assert entries[0] == entries[1] == entries[2]
    (entry,) = entries[0]
    assert entry["urdf"] == str(tmp_path.resolve() / "urdf" / "flap.urdf") and entry["joints"] == ["hinge"]
