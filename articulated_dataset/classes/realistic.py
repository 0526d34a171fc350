"""Realistic sampling tables (``artdata generate --table realistic``): joint distributions of
an object's depth, width and height built from published standard dimensions.

The paper samples each size independently and uniformly ("the length, width, and height of
objects was sampled independently, which does not accurately reflect the true joint
distribution").  Here each class's sizes come from a small mixture of size classes
(:class:`~articulated_dataset.core.tables.ShapeComponent`): kitchen cabinets and drawers take
standard nominal sizes (e.g. widths in 3-inch steps) with a few millimetres of jitter;
appliances take a correlated normal around each capacity class's typical size (a larger
oven is wider, taller and deeper together).  Samples are truncated to each table's geometry
bounds.  Pose, configuration ranges and chirality stay the paper's (Appendix A).

Sources (by name; this package was written without access to them, so every number is a
*typical range* compiled from these standard references and catalogues, not a measurement):

* Cabinets: NKBA Kitchen Planning Guidelines (National Kitchen & Bath Association): base
  cabinets 34.5 in tall (36 in with the countertop) and 24 in deep; wall cabinets 12 in
  deep and 30, 36 or 42 in tall; over-refrigerator wall cabinets 12-18 in tall; tall (pantry,
  utility) cabinets 84, 90 or 96 in.  ANSI/KCMA A161.1 (Kitchen Cabinet Manufacturers
  Association, performance and construction of kitchen and vanity cabinets) and the
  specification books of KCMA-certified manufacturers (e.g. KraftMaid, American Woodmark) and
  IKEA's SEKTION planning guide: widths of 9-48 in in 3-in steps, one door up to 24 in wide,
  two doors from 24 in.  NKBA Bathroom Planning Guidelines: vanities 21 in deep, 30.5-34.5 in
  tall.
* Drawers: drawer-runner catalogues (Blum TANDEM/MOVENTO, Hettich): 21-22 in runners in a
  24-in base cabinet (drawer shells ~23 in deep); door-and-drawer-front catalogues: top
  drawer fronts 5.5-6.5 in, deep (pot) drawers 9.5-12 in; furniture catalogues (IKEA MALM,
  HEMNES chests): chests 16-20 in deep, 24-36 in wide; office-furniture catalogues (Steelcase,
  HON mobile pedestals): 15-16 in wide, ~22 in deep, 5-in box and 11-in file drawers.
* Microwaves: manufacturers' specification sheets (Panasonic, GE, Whirlpool, Samsung) by
  capacity class: compact 0.5-0.9 cu ft (~0.46 x 0.27 x 0.35 m, W x H x D), mid-size
  1.0-1.4 cu ft (~0.53 x 0.31 x 0.42 m), full-size 1.5-2.2 cu ft (~0.58 x 0.35 x 0.47 m);
  over-the-range models fill a 30-in range opening (0.76 x 0.42 x 0.41 m).
* Toaster ovens: manufacturers' specification sheets (Black+Decker, Hamilton Beach,
  Cuisinart, Breville): 4-slice (~0.39 x 0.21 x 0.28 m), 6-slice / 12-in pizza (~0.45 x 0.26
  x 0.34 m), large and air-fryer ovens (~0.51 x 0.31 x 0.40 m).
* Refrigerators (two stacked doors, top freezer, as the template): manufacturers'
  specification sheets (GE, Whirlpool, Frigidaire; compact two-door models by Danby and
  Frigidaire) by capacity class as AHAM HRF-1 rates it: compact 3-4.5 cu ft (~0.48 x 0.86 x
  0.50 m, W x H x D), apartment 10-12 cu ft (~0.60 x 1.57 x 0.66 m), standard 14-18 cu ft
  (~0.75 x 1.66 x 0.74 m), large 19-21 cu ft (~0.83 x 1.72 x 0.79 m); NKBA refrigerator
  openings of 30, 33 and 36 in.

The weights of the size classes (how common each is) are this package's assumption, not a
published statistic.  ``python -m articulated_dataset.classes.realistic`` prints the
tables as Markdown (docs/generation.md, "Realistic shapes").
"""

from __future__ import annotations

from dataclasses import replace

from articulated_dataset.core.tables import GEOMETRY_KEYS, SamplingTable, ShapeComponent, ShapeMixture

#: One inch in metres.
INCH_M = 0.0254


def inches(*values: float) -> tuple[float, ...]:
    """Sizes given in inches, in metres (rounded to 0.1 mm)."""
    return tuple(round(v * INCH_M, 4) for v in values)


def standard(name: str, weight: float, depth_in, width_in, height_in, std_m=(0.008, 0.003, 0.006)) -> ShapeComponent:
    """A size class of standard nominal sizes (inches; one list per dimension, each value
    equally likely) with a small independent jitter ``std_m`` (depth, width, height; m)."""
    return ShapeComponent(name, weight, dict(zip(GEOMETRY_KEYS, (inches(*depth_in), inches(*width_in), inches(*height_in)))),
                          dict(zip(GEOMETRY_KEYS, std_m)))


def typical(name: str, weight: float, mean_m, std_m, corr_dw: float, corr_dh: float, corr_wh: float) -> ShapeComponent:
    """A size class around one typical size ``mean_m`` (depth, width, height; m) with a
    correlated normal spread (standard deviations ``std_m``, pairwise correlations)."""
    corr = ((1.0, corr_dw, corr_dh), (corr_dw, 1.0, corr_wh), (corr_dh, corr_wh, 1.0))
    return ShapeComponent(name, weight, {k: (m,) for k, m in zip(GEOMETRY_KEYS, mean_m)}, dict(zip(GEOMETRY_KEYS, std_m)), corr)


def realistic_table(paper: SamplingTable, bounds: dict, components: tuple[ShapeComponent, ...]) -> SamplingTable:
    """The paper's table with its geometry drawn from ``components``, truncated to ``bounds``."""
    return replace(paper, geometry=bounds, shape=ShapeMixture(components))


def _steps(lo: float, hi: float, step: float = 3.0) -> tuple[float, ...]:
    n = int(round((hi - lo) / step))
    return tuple(lo + step * i for i in range(n + 1))


# ---- one (bounds, components) per class; bounds keep every class >= 3 sigma inside ----------

CABINET = (
    {"depth_m": (0.28, 0.66), "width_m": (0.20, 0.66), "height_m": (0.70, 2.50)},
    (
        standard("base, 1 door", 0.50, [24], _steps(9, 24), [34.5]),
        standard("wall, 1 door", 0.35, [12], _steps(9, 24), [30, 36, 42], std_m=(0.008, 0.003, 0.003)),
        standard("tall, 1 door", 0.10, [24], [18, 24], [84, 90, 96], std_m=(0.008, 0.003, 0.005)),
        standard("vanity, 1 door", 0.05, [21], _steps(12, 24), [30.5, 34.5]),
    ),
)

CABINET2 = (
    {"depth_m": (0.28, 0.66), "width_m": (0.58, 1.25), "height_m": (0.28, 2.50)},
    (
        standard("base, 2 doors", 0.45, [24], _steps(24, 48), [34.5]),
        standard("wall, 2 doors", 0.30, [12], _steps(24, 36), [30, 36, 42], std_m=(0.008, 0.003, 0.003)),
        standard("over-refrigerator wall", 0.07, [12, 24], [30, 33, 36], [12, 15, 18], std_m=(0.008, 0.003, 0.003)),
        standard("tall, 2 doors", 0.10, [24], [24, 30, 36], [84, 90, 96], std_m=(0.008, 0.003, 0.005)),
        standard("vanity, 2 doors", 0.08, [21], [30, 36, 42, 48], [30.5, 34.5]),
    ),
)

DRAWER = (
    # shells deeper than the paper's 0.40 m drawer travel: the drawer never leaves its shell
    {"depth_m": (0.44, 0.62), "width_m": (0.28, 0.94), "height_m": (0.09, 0.32)},
    (
        standard("kitchen top drawer", 0.40, [23], _steps(12, 36), [5.5, 6, 6.5], std_m=(0.006, 0.003, 0.004)),
        standard("kitchen deep drawer", 0.30, [23], [15, 18, 21, 24, 30, 36], [9.5, 11, 12], std_m=(0.006, 0.003, 0.004)),
        standard("chest of drawers", 0.20, [18], [24, 30, 33, 36], [6, 8, 10], std_m=(0.008, 0.005, 0.005)),
        standard("office pedestal", 0.10, [22], [15, 16], [5, 11], std_m=(0.006, 0.003, 0.004)),
    ),
)

MICROWAVE = (
    {"depth_m": (0.26, 0.56), "width_m": (0.38, 0.80), "height_m": (0.22, 0.47)},
    (
        typical("compact countertop", 0.30, (0.345, 0.46, 0.27), (0.020, 0.018, 0.012), 0.6, 0.5, 0.6),
        typical("mid-size countertop", 0.35, (0.42, 0.53, 0.31), (0.018, 0.018, 0.012), 0.6, 0.5, 0.6),
        typical("full-size countertop", 0.20, (0.47, 0.58, 0.345), (0.022, 0.020, 0.012), 0.6, 0.5, 0.6),
        typical("over-the-range", 0.15, (0.41, 0.76, 0.42), (0.015, 0.004, 0.012), 0.0, 0.5, 0.0),
    ),
)

TOASTER = (
    {"depth_m": (0.21, 0.50), "width_m": (0.32, 0.60), "height_m": (0.17, 0.40)},
    (
        typical("4-slice", 0.35, (0.28, 0.39, 0.21), (0.020, 0.020, 0.012), 0.5, 0.5, 0.5),
        typical("6-slice / 12-in pizza", 0.40, (0.34, 0.45, 0.26), (0.020, 0.020, 0.015), 0.5, 0.5, 0.5),
        typical("large / air fryer", 0.25, (0.40, 0.51, 0.31), (0.022, 0.022, 0.020), 0.5, 0.5, 0.5),
    ),
)

REFRIGERATOR = (
    {"depth_m": (0.43, 0.86), "width_m": (0.42, 0.88), "height_m": (0.76, 1.82)},
    (
        typical("compact two-door", 0.15, (0.50, 0.48, 0.86), (0.020, 0.015, 0.030), 0.5, 0.4, 0.4),
        typical("apartment top-freezer", 0.20, (0.66, 0.60, 1.57), (0.020, 0.012, 0.030), 0.5, 0.4, 0.4),
        typical("standard top-freezer", 0.45, (0.74, 0.75, 1.66), (0.025, 0.015, 0.025), 0.5, 0.4, 0.5),
        typical("large top-freezer", 0.20, (0.79, 0.83, 1.72), (0.020, 0.015, 0.025), 0.5, 0.4, 0.5),
    ),
)


def markdown_table(table: SamplingTable) -> str:
    """A realistic table's size classes as Markdown rows: weight, sizes (m) and spread."""
    rows = ["| size class | weight | depth (m) | width (m) | height (m) | jitter sd d/w/h (mm) | corr dw/dh/wh |",
            "|---|---|---|---|---|---|---|"]
    for c, p in zip(table.shape.components, table.shape.probabilities):  # type: ignore[union-attr]  # a realistic table has a shape
        sizes = [", ".join(f"{v:.3f}" for v in c.sizes_m[k]) for k in GEOMETRY_KEYS]
        sd = "/".join(f"{1000 * c.std_m[k]:g}" for k in GEOMETRY_KEYS)
        corr = "/".join(f"{v:g}" for v in (c.corr[0][1], c.corr[0][2], c.corr[1][2]))
        rows.append(f"| {c.name} | {p:.2f} | {sizes[0]} | {sizes[1]} | {sizes[2]} | {sd} | {corr} |")
    (dl, dh), (wl, wh), (hl, hh) = (table.geometry[k] for k in GEOMETRY_KEYS)
    rows.append(f"| *bounds* | | {dl:g}-{dh:g} | {wl:g}-{wh:g} | {hl:g}-{hh:g} | | |")
    return "\n".join(rows)


def _main() -> None:  # pragma: no cover - prints the docs tables
    from articulated_dataset.classes.registry import all_classes

    for c in all_classes():
        if c.realistic_table is not None:
            print(f"**{c.name}**\n\n{markdown_table(c.realistic_table)}\n")


if __name__ == "__main__":
    _main()
