"""Varied tables (``artdata generate --table varied``): the realistic sizes
(:mod:`articulated_dataset.classes.realistic`) with the structures real objects of a class
have, drawn per object, and openings as wide as their hinges allow.

The paper's objects are all built one way: every door spans the whole front, hinges on the
body's edge, carries one 12 cm bar at mid-height, and the body stands on the floor.  A model
trained on them reads a real cabinet's hinge where a paper cabinet's would be.  A varied
table holds *structure variables* (:attr:`~articulated_dataset.core.tables.SamplingTable.structure`;
the kind of each is read from its name's suffix: ``_p`` a probability, ``_m`` a range of
lengths, ``_frac`` a range of fractions, ``_weights`` the weights of named options); each
object draws one value of each from its own structure stream
(:data:`~articulated_dataset.generation.sampling.STRUCTURE_STREAM`), and the class's varied
template (``classes/*_varied.urdf.xacro``, macros in ``classes/varied.xacro``)
builds it.  That template's argument defaults build the paper's object (a test compiles both
and compares them), and the paper's and realistic tables hold no structure, so their data is
unchanged.

Sources of the ranges (by name; every number is a *typical range* from these standards and
catalogues, not a measurement of our own):

* carcass boards 5/8-3/4 in (16-19 mm): ANSI/KCMA A161.1 cabinet construction, European 16
  and 18 mm carcass board (IKEA SEKTION 18 mm);
* doors 5/8-7/8 in (16-22 mm), 3/4 in the most common: door manufacturers' catalogues;
* face frames of 3/4 in stock, stiles and rails 1-1/2 to 2 in (38-51 mm): face-frame cabinet
  specifications (KCMA-certified manufacturers);
* overlay: half overlay ~8 mm on a frameless 16-19 mm side, standard overlay 1/2 in and full
  overlay 1-1/4 in on a face frame (8-32 mm): concealed-hinge catalogues (Blum CLIP top,
  Salice, Grass); an overlay beyond the front edge's width is a full overlay (no reveal);
* inset doors with a 1/16-1/8 in (1.5-3 mm) reveal: inset-cabinetry specifications;
* toe-kick 4-6 in high (100-150 mm) and 2-3 in deep (50-75 mm): NKBA Kitchen Planning
  Guidelines; cabinet legs 30-50 mm square, 100-150 mm tall (adjustable cabinet legs,
  furniture legs);
* countertops 2-4 cm thick (stone slabs 2 and 3 cm, 1-1/2 in laminate) overhanging the
  cabinet front 1-1/2 in (20-40 mm): NKBA;
* pulls 96-320 mm between hole centres (the 32-mm system's standard spacings), 10-16 mm bars
  standing 25-38 mm off the door; knobs 1-1-1/2 in (25-38 mm); placed 1-1/4 to 3 in (30-80
  mm) from the free edge: hardware catalogues (Hafele, Richelieu, Amerock);
* openings to 120 degrees: wide-angle concealed hinges (Blum CLIP top 110 and 120 degrees;
  155 and 170 degree models exist).

How often each structure occurs (the probabilities and option weights) is this package's
assumption, not a published statistic, and each variable is drawn independently of the
others and of the size class.  ``python -m articulated_dataset.classes.varied`` prints the
tables as Markdown (docs/generation.md, "Varied structure").
"""

from __future__ import annotations

import math
from dataclasses import replace

from articulated_dataset.core.tables import SamplingTable

#: Widest opening of a varied cabinet door (rad): 120 degrees (wide-angle hinges).
CABINET_DOOR_Q_RAD = (0.0, 2.0 * math.pi / 3.0)

#: Structure variables of the varied cabinets (one and two doors): name -> range, probability
#: or option weights (see the module's sources).  Every argument of classes/varied.xacro.
CABINET_STRUCTURE = {
    "door_inset_p": 0.25,
    "overlay_m": (0.008, 0.032),
    "inset_gap_m": (0.0015, 0.003),
    "carcass_m": (0.016, 0.019),
    "door_thickness_m": (0.016, 0.022),
    "face_frame_p": 0.4,
    "stile_m": (0.038, 0.051),
    "frame_thickness_m": (0.018, 0.020),
    "base_weights": {"none": 0.3, "plinth": 0.5, "legs": 0.2},
    "base_height_m": (0.10, 0.15),
    "plinth_setback_m": (0.05, 0.075),
    "leg_size_m": (0.03, 0.05),
    "leg_inset_m": (0.0, 0.04),
    "countertop_p": 0.3,
    "countertop_thickness_m": (0.02, 0.04),
    "countertop_overhang_m": (0.02, 0.04),
    "shelves_weights": {"0": 0.25, "1": 0.5, "2": 0.25},
    "shelf_setback_m": (0.01, 0.05),
    "handle_weights": {"bar_vertical": 0.4, "bar_horizontal": 0.2, "knob": 0.2, "none": 0.2},
    "handle_length_m": (0.096, 0.320),
    "handle_width_m": (0.010, 0.016),
    "handle_standoff_m": (0.025, 0.038),
    "handle_inset_m": (0.03, 0.08),
    "handle_z_frac": (0.1, 0.9),
    "knob_m": (0.025, 0.038),
}


def varied_table(realistic: SamplingTable, q: tuple, structure: dict) -> SamplingTable:
    """The realistic table with the widest openings ``q`` and the structure variables."""
    return replace(realistic, q=q, structure=structure)


def markdown_table(table: SamplingTable) -> str:
    """A varied table's structure variables as Markdown rows: name, kind and range."""
    rows = ["| variable | kind | range, probability or option weights |", "|---|---|---|"]
    for name, value in table.structure.items():
        if isinstance(value, dict):
            kind, shown = "options", ", ".join(f"{o}: {w:g}" for o, w in value.items())
        elif isinstance(value, tuple):
            kind = "length (m)" if name.endswith("_m") else "fraction"
            shown = f"{value[0]:g}-{value[1]:g}"
        else:
            kind, shown = "probability", f"{value:g}"
        rows.append(f"| `{name}` | {kind} | {shown} |")
    return "\n".join(rows)


def _main() -> None:  # pragma: no cover - prints the docs tables
    from articulated_dataset.classes.base import PRISMATIC
    from articulated_dataset.classes.registry import all_classes

    for c in all_classes():
        if c.varied_table is not None:
            q = ", ".join(f"{hi:.2f} m" if joint_type == PRISMATIC else f"{math.degrees(hi):.0f} deg"
                          for joint_type, (_, hi) in zip(c.joint_types, c.varied_table.q))
            print(f"**{c.name}** (widest opening: {q})\n\n{markdown_table(c.varied_table)}\n")


if __name__ == "__main__":
    _main()
