"""Benchmark results in the docs are rendered from the JSON the benchmarks write
(docs/results/*.json), never retyped: each table in the docs is the benchmark's own rendering."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from helpers_core import load_script

ROOT = Path(__file__).resolve().parents[1]
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
