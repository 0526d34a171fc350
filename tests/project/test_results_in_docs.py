"""Benchmark results in the docs are rendered from the JSON the benchmarks write
(docs/results/*.json), never retyped: each table in the docs is the benchmark's own rendering."""

from __future__ import annotations

import json

import pytest

from helpers_core import ROOT, load_script

TABLE1_RESULTS = sorted((ROOT / "docs" / "results").glob("table1-*.json"))


@pytest.mark.parametrize("results", TABLE1_RESULTS, ids=lambda p: p.stem)
def test_table1_in_the_baselines_doc_is_the_scripts_rendering(results):
    script = load_script(ROOT / "benchmarks" / "reproduce_table1.py", "reproduce_table1")
    record = json.loads(results.read_text())
    table = script.format_markdown(record["rows"], record["header"])
    doc = (ROOT / "docs" / "baselines.md").read_text()
    assert table in doc, f"docs/baselines.md lacks the table of {results.name}: paste the script's table1.md"
    assert f"docs/results/{results.name}" in doc  # the doc names its source


def test_there_are_table1_results_for_both_framings():
    framings = {json.loads(p.read_text())["header"].get("framing") for p in TABLE1_RESULTS}
    assert {"table4", "whole"} <= framings


def test_third_party_figures_in_the_docs_are_the_scripts_rendering():
    """docs/third_party_urdf.md shows benchmarks/third_party.py's own tables of
    docs/results/third_party_dense.json."""
    script = load_script(ROOT / "benchmarks" / "third_party.py", "third_party")
    record = json.loads((ROOT / "docs" / "results" / "third_party_dense.json").read_text())
    doc = (ROOT / "docs" / "third_party_urdf.md").read_text()
    for part in script.format_report(record).split("\n\n"):
        assert part.strip() in doc, "docs/third_party_urdf.md lacks the script's table: paste its output"
    assert "docs/results/third_party_dense.json" in doc


def test_robot_view_figures_in_the_docs_are_the_scripts_rendering():
    """docs/robot_view.md shows benchmarks/robot_view.py's own table of docs/results/robot_view.json."""
    script = load_script(ROOT / "benchmarks" / "robot_view.py", "robot_view")
    record = json.loads((ROOT / "docs" / "results" / "robot_view.json").read_text())
    doc = (ROOT / "docs" / "robot_view.md").read_text()
    assert script.format_table(record["rows"]) in doc, "docs/robot_view.md lacks the script's table: paste its output"
    assert "docs/results/robot_view.json" in doc


def test_the_shipped_models_table_in_the_model_card_is_rendered_from_their_records():
    """docs/dense.md's table of the shipped models is benchmarks/shipped_models.py's rendering of the
    test figures models.json records and of the Table 1 baselines' JSON."""
    shipped = load_script(ROOT / "benchmarks" / "shipped_models.py", "shipped_models")
    table1 = load_script(ROOT / "benchmarks" / "reproduce_table1.py", "reproduce_table1")
    models = json.loads((ROOT / "articulated_dataset" / "methods" / "weights" / "models.json").read_text())["models"]
    rows = json.loads((ROOT / "docs" / "results" / "table1-table4.json").read_text())["rows"]
    table = shipped.format_markdown(models, rows, table1.PAPER_TABLE1)
    assert table in (ROOT / "docs" / "dense.md").read_text(), "docs/dense.md: paste shipped_models.format_markdown's table"
