"""The project speaks of itself: no development narrative in the package, the tests, the
benchmarks, the scripts or the docs (history lives in CHANGELOG.md, keyed by version, and in
``git log``)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: Where the search runs (CHANGELOG.md is history by design, but speaks by version, not by episode).
SEARCHED = ("articulated_dataset", "tests", "benchmarks", "scripts", "docs", "README.md", "DATASHEET.md",
            "CHANGELOG.md", ".ci")
SUFFIXES = {".py", ".md", ".toml", ".cfg", ".sh", ".yaml", ".yml", ".xacro", ""}
#: Words that narrate how the work was done rather than what the code does.
NARRATIVE = re.compile(
    r"\b(sessions?|sweeps?|helpers?|this time|previously|episodes?|subagents?|"
    r"(fourth|fifth|sixth|seventh|eighth|ninth|tenth|\w+teenth|\w+tieth|\w+ty-(first|second|third|\w+th)) "
    r"(round|attempt|try|refit|run|sweep|session|pass|model|chain|training))\b", re.I)
#: Code words that contain them: third-party API names and pytest's fixture scope.
ALLOWED = re.compile(r'scope="session"|InferenceSession|\bsession(\.run\(| = ort\.)|onnx\.helper|\bhelper = |, helper\)')


def _files():
    for name in SEARCHED:
        path = ROOT / name
        paths = [path] if path.is_file() else (p for p in path.rglob("*") if p.is_file())
        for p in paths:
            if "__pycache__" in p.parts or p.suffix not in SUFFIXES or p.name == Path(__file__).name:
                continue
            yield p


def test_no_development_narrative():
    found = []
    for path in _files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            if NARRATIVE.search(ALLOWED.sub("", line)):
                found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert found == [], "narrative words (say what the code does; history goes to CHANGELOG.md):\n" + "\n".join(found)


#: The longest a model card may be: what the model is, how to use it, how it works, what it scores.
MAX_MODEL_CARD_LINES = 400


def test_the_dense_model_card_is_reference_sized():
    lines = (ROOT / "docs" / "dense.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_MODEL_CARD_LINES, f"docs/dense.md has {len(lines)} lines: history belongs in CHANGELOG.md"
