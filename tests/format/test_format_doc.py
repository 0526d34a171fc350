"""docs/format.md holds the schema's field table as the schema generates it (optional format 1.1
fields included) and documents the context mask codes, so a reader in another language sees
every field a split can hold."""

from __future__ import annotations

from articulated_dataset.format.schema import (
    FIELDS,
    MASK_OCCLUDER,
    MASK_SCENE,
    OPTIONAL_FIELDS,
    RGB_FIELDS,
    markdown_table,
)
from helpers_core import ROOT

PAGE = ROOT / "docs" / "format.md"


def test_page_holds_the_generated_field_table():
    text = PAGE.read_text()
    table = markdown_table()
    assert f"\n{table}\n\n" in text, "docs/format.md: regenerate the table with python -m articulated_dataset.format.schema"
    rows = [line for line in table.splitlines()[2:]]
    assert len(rows) == len(FIELDS) + len(OPTIONAL_FIELDS) + len(RGB_FIELDS)
    for f in OPTIONAL_FIELDS:
        row = next(r for r in rows if r.startswith(f"| `{f.name}` |"))
        assert "format 1.1" in row
    for f in RGB_FIELDS:
        row = next(r for r in rows if r.startswith(f"| `{f.name}` |"))
        assert "format 1.2" in row


def test_page_documents_the_context_mask_codes():
    text = " ".join(PAGE.read_text().split())  # line breaks as spaces
    assert f"**{MASK_OCCLUDER}**, an occluder" in text and f"**{MASK_SCENE}**, scene geometry" in text
    for name in ("unoccluded_pixels", "visible_fraction"):
        assert f"**{name}**" in text
