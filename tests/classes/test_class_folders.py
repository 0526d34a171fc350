"""Each built-in class is one folder, ``articulated_dataset/classes/<name>/``: its module, its
templates, a README whose tables give every sampled range of the class's tables with its value
and its source, and a CHANGELOG keyed by package version."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from packaging.version import Version

import articulated_dataset
import articulated_dataset.classes
from articulated_dataset.classes.base import ObjectClass
from articulated_dataset.classes.registry import class_names, get_class
from articulated_dataset.core.tables import TABLE_NAMES, SamplingTable

#: The folder holding one folder per built-in class.
CLASSES_DIR = Path(articulated_dataset.classes.__file__).parent
#: A README heading starts the rows of table NAME when it holds "`--table NAME`"; any other
#: heading ends them.
_TABLE_HEADING = re.compile(r"`--table (\w+)")
#: A relative Markdown link's target: ``[text](target)``.
_LINK = re.compile(r"\]\(([^)\s]+)\)")
#: The generation docs (the tables' sampling, "Realistic shapes", "Varied structure"), linked from
#: every class README (relative to the class folder).
GENERATION_DOC = "../../../docs/generation.md"
#: A version heading of a CHANGELOG (Keep a Changelog): ``## [X.Y.Z]``.
_VERSION_HEADING = re.compile(r"^## \[(\d+(?:\.\d+)*)\]", re.MULTILINE)


def _number(v: float) -> str:
    return f"{v:.6g}"


def _range(r) -> str:
    return f"[{_number(r[0])}, {_number(r[1])}]"


def _structure_value(value) -> str:
    if isinstance(value, dict):
        return ", ".join(f"{option}: {_number(w)}" for option, w in value.items())
    if isinstance(value, tuple):
        return _range(value)
    return _number(value)


def table_variables(table: SamplingTable) -> dict[str, str]:
    """Every sampled variable of ``table`` -> the value its README row starts with: geometry,
    pose and configuration ranges, ``chirality_p``, ``extra`` values, structure variables and,
    with a joint size distribution, each size class (by name: its probability)."""
    rows = {k: _range(r) for k, r in {**table.geometry, **table.pose}.items()}
    rows.update({f"q[{j}]": _range(r) for j, r in enumerate(table.q)})
    rows["chirality_p"] = _number(table.chirality_p)
    rows.update({f"extra.{k}": _number(v) for k, v in table.extra.items()})
    rows.update({k: _structure_value(v) for k, v in table.structure.items()})
    if table.shape is not None:
        rows.update({c.name: f"{p:.4g}" for c, p in zip(table.shape.components, table.shape.probabilities)})
    return rows


def readme_rows(text: str) -> dict[str, dict[str, tuple[str, str]]]:
    """{table name: {variable: (value cell, source cell)}} of a README: the rows of the Markdown
    tables under each heading naming ``--table NAME`` (header rows left out), keyed by their
    first cell without backticks."""
    rows: dict[str, dict[str, tuple[str, str]]] = {}
    lines = text.splitlines()
    current = None
    for i, line in enumerate(lines):
        if line.startswith("#"):
            match = _TABLE_HEADING.search(line)
            current = match.group(1) if match else None
            continue
        is_header = i + 1 < len(lines) and lines[i + 1].startswith("|---")
        if current is None or not line.startswith("|") or line.startswith("|---") or is_header:
            continue
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        rows.setdefault(current, {})[cells[0].strip("`")] = (cells[1] if len(cells) > 1 else "", cells[-1])
    return rows


def class_tables(obj_class: ObjectClass) -> dict[str, SamplingTable]:
    """The class's named tables (``--table paper|realistic|varied``) that it has."""
    tables = {"paper": obj_class.table, "realistic": obj_class.realistic_table, "varied": obj_class.varied_table}
    assert set(tables) == set(TABLE_NAMES)
    return {name: table for name, table in tables.items() if table is not None}


def readme_problems(obj_class: ObjectClass, text: str) -> list[str]:
    """What the README ``text`` of ``obj_class`` gets wrong, one line each: a variable of one of
    its tables without a row, a row whose value is not the code's or whose source is empty, and
    a row for a variable the table does not have."""
    documented = readme_rows(text)
    problems = []
    for table_name, table in class_tables(obj_class).items():
        rows = documented.get(table_name, {})
        expected = table_variables(table)
        for variable, value in expected.items():
            if variable not in rows:
                problems.append(f"--table {table_name}: {variable} has no row (add its value and source)")
                continue
            cell, source = rows[variable]
            if not (cell == value or cell.startswith(value + " ")):
                problems.append(f"--table {table_name}: {variable} reads {cell!r}, the code's value is {value}")
            if not source or source == cell:
                problems.append(f"--table {table_name}: {variable} has no source")
        problems += [f"--table {table_name}: row {variable} names no variable of the table"
                     for variable in rows if variable not in expected]
    return problems


def _readme(name: str) -> str:
    return (CLASSES_DIR / name / "README.md").read_text(encoding="utf-8")


@pytest.mark.parametrize("name", class_names())
def test_class_folder_holds_its_files(name):
    obj_class = get_class(name)
    folder = CLASSES_DIR / name
    files = ["__init__.py", f"{name}.urdf.xacro", "README.md", "CHANGELOG.md"]
    files += [obj_class.varied_template] if obj_class.varied_template else []
    missing = [f for f in files if not (folder / f).is_file()]
    assert not missing, f"classes/{name}/ lacks {', '.join(missing)}"
    assert obj_class.template == f"{name}.urdf.xacro"
    assert obj_class.template_path().parent == folder
    if obj_class.varied_template:
        assert obj_class.template_path(varied=True).parent == folder


@pytest.mark.parametrize("name", class_names())
def test_readme_gives_every_sampled_range_with_its_source(name):
    problems = readme_problems(get_class(name), _readme(name))
    assert not problems, (f"classes/{name}/README.md, 'Sampled ranges', against the class's tables:\n  "
                          + "\n  ".join(problems))


@pytest.mark.parametrize("name", class_names())
def test_readme_links_resolve(name):
    folder = CLASSES_DIR / name
    targets = [t.split("#", 1)[0] for t in _LINK.findall(_readme(name)) if "://" not in t]
    assert GENERATION_DOC in targets, f"classes/{name}/README.md does not link {GENERATION_DOC}"
    broken = [t for t in targets if t and not (folder / t).exists()]
    assert not broken, f"classes/{name}/README.md links to missing files: {broken}"


def test_readme_check_names_what_is_wrong():
    """The README check fails, naming the variable, for a range without a row, a value other
    than the code's, a row without a source and a row the tables do not have."""
    obj_class = get_class("cabinet")
    text = _readme("cabinet")
    assert readme_problems(obj_class, text) == []
    overlay = next(line for line in text.splitlines() if line.startswith("| `overlay_m` |"))
    assert readme_problems(obj_class, text.replace(overlay + "\n", "")) == [
        "--table varied: overlay_m has no row (add its value and source)"]
    assert readme_problems(obj_class, text.replace("| `overlay_m` | [0.008, 0.032] m", "| `overlay_m` | [0.008, 0.03] m")) == [
        "--table varied: overlay_m reads '[0.008, 0.03] m', the code's value is [0.008, 0.032]"]
    unsourced = overlay.rsplit("|", 2)[0] + "| |"
    assert readme_problems(obj_class, text.replace(overlay, unsourced)) == ["--table varied: overlay_m has no source"]
    assert readme_problems(obj_class, text.replace(overlay, overlay + "\n" + overlay.replace("overlay_m", "veneer_m"))) == [
        "--table varied: row veneer_m names no variable of the table"]


@pytest.mark.parametrize("name", class_names())
def test_changelog_is_keyed_by_released_versions(name):
    """Headings ``## [X.Y.Z]`` of released versions (none after the package's), or ``## [Unreleased]``
    alone for a class added since the last release."""
    text = (CLASSES_DIR / name / "CHANGELOG.md").read_text(encoding="utf-8")
    versions = [Version(v) for v in _VERSION_HEADING.findall(text)]
    current = Version(articulated_dataset.__version__)
    unreleased = "\n## [Unreleased]\n" in text
    assert versions or unreleased, f"classes/{name}/CHANGELOG.md has no '## [X.Y.Z]' or '## [Unreleased]' heading"
    assert not versions or min(versions) <= current
    newer = [str(v) for v in versions if v > current]
    assert not newer, f"classes/{name}/CHANGELOG.md names versions after the package's {current}: {newer}"
