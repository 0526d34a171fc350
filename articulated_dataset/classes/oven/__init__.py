"""Oven: a kitchen range or a built-in oven, one revolute door hinged at its bottom edge
above a storage drawer, a plinth or a trim strip, opening downwards, with a control panel
above.

The paper has no oven; a toaster oven's model reads a kitchen oven's hinge at the body's
bottom, where a range has a drawer or a plinth (12-26 cm up a 0.9 m range).  The default
table (``--table paper``, the class's own) draws the sizes of ranges and built-in ovens
uniformly and builds one structure (classes/oven/oven.urdf.xacro: a storage drawer 15 cm
high, a 10 cm control panel, a door with a window, racks inside); ``--table realistic``
draws the sizes from size classes; ``--table varied`` draws the structure per object
(:data:`OVEN_STRUCTURE`).

Sources of the ranges (by name; every number is a *typical range* compiled from these
references, not a measurement of our own):

* sizes: freestanding and slide-in ranges 20, 24, 30 and 36 in wide (30 in the most common),
  36 in to the cooking surface (the counter's height) and 25-28 in deep without the door and
  handle; built-in single wall ovens 24, 27 and 30 in wide, 27-30 in tall, 23-25 in deep
  (GE, Whirlpool, Frigidaire, Bosch and Samsung specification sheets; NKBA Kitchen Planning
  Guidelines for the 36 in counter height);
* the base zone: a storage or warming drawer 5-9 in (0.12-0.23 m) high under the oven door
  of most freestanding ranges; a recessed toe-kick 3-5 in (0.08-0.13 m) on others; a trim
  strip 1-2.5 in (0.03-0.06 m) under a built-in oven's door (the same specification sheets);
* control panels: a front control strip 3-6 in (0.08-0.15 m) above the door (front-control
  ranges and wall ovens); knobs about 1.5 in (the knob template's 4 cm);
* doors: 1.5-2.5 in (0.04-0.06 m) thick with a triple-glazed window set 5-15 mm back in a
  2-4 in (0.05-0.10 m) frame; a handle bar across 0.6-0.9 of the door, 2-3 in (0.05-0.07 m)
  off the door, 1-2 in below its top edge;
* openings: oven doors open to horizontal, 90 degrees (the spring hinges' stop);
* cooktops: a glass-ceramic or steel top 8-20 mm thick on ranges; none on built-in ovens.

How often each structure occurs is this package's assumption, not a published statistic;
each variable is drawn independently of the others and of the size class.
"""

from articulated_dataset.classes.base import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.classes.common import REVOLUTE_Q_RAD, YAW_RAD
from articulated_dataset.classes.realistic import realistic_table, standard
from articulated_dataset.classes.varied import varied_table
from articulated_dataset.core.tables import SamplingTable

TABLE = SamplingTable(
    geometry={"depth_m": (0.55, 0.72), "width_m": (0.50, 0.92), "height_m": (0.68, 0.95)},
    pose={"x_m": (1.2, 2.2), "y_m": (-0.5, 0.5), "z_m": (-0.8, -0.2), "yaw_rad": YAW_RAD},
    q=(REVOLUTE_Q_RAD,),
)

#: Size bounds (m) of ``--table realistic``: every size class at least 3 sigma inside.
REALISTIC_BOUNDS_M = {"depth_m": (0.55, 0.72), "width_m": (0.48, 0.95), "height_m": (0.66, 0.97)}

#: ``--table realistic``: ranges and built-in ovens by nominal width (sources above).
REALISTIC_TABLE = realistic_table(TABLE, REALISTIC_BOUNDS_M, (
    standard("30-in range", 0.45, [26, 27], [30], [36], std_m=(0.008, 0.003, 0.006)),
    standard("24-in or 20-in range", 0.15, [25, 26], [20, 24], [36], std_m=(0.008, 0.003, 0.006)),
    standard("36-in range", 0.10, [27], [36], [36], std_m=(0.008, 0.003, 0.006)),
    standard("built-in wall oven", 0.30, [23, 24, 25], [24, 27, 30], [27, 28.5, 30], std_m=(0.008, 0.003, 0.006)),
))

#: Structure variables of the varied oven: name -> range, probability or option weights
#: (sources in the module's docstring).  Every argument of classes/oven/oven_varied.urdf.xacro.
OVEN_STRUCTURE = {
    "base_weights": {"drawer": 0.55, "plinth": 0.25, "trim": 0.2},
    "drawer_height_m": (0.12, 0.23),
    "plinth_height_m": (0.08, 0.13),
    "trim_height_m": (0.03, 0.06),
    "plinth_setback_m": (0.03, 0.07),
    "panel_height_m": (0.08, 0.15),
    "knobs_p": 0.5,
    "cooktop_p": 0.6,
    "cooktop_thickness_m": (0.008, 0.020),
    "door_margin_m": (0.003, 0.03),
    "door_thickness_m": (0.04, 0.06),
    "window_p": 0.85,
    "window_border_m": (0.05, 0.10),
    "window_recess_m": (0.005, 0.015),
    "racks_p": 0.8,
    "handle_length_frac": (0.6, 0.9),
    "handle_width_m": (0.015, 0.03),
    "handle_standoff_m": (0.05, 0.07),
    "handle_inset_m": (0.025, 0.05),
}

#: ``--table varied``: the realistic sizes, the 90-degree opening and the structure variables
#: above (classes/oven/oven_varied.urdf.xacro).
VARIED_TABLE = varied_table(REALISTIC_TABLE, (REVOLUTE_Q_RAD,), OVEN_STRUCTURE)

CLASS = ObjectClass(
    name="oven",
    template="oven.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("door_hinge", REVOLUTE, "door"),),
    description="oven (range or built-in): 1 revolute door hinged at the bottom above a drawer, plinth or trim",
    order=7,
    realistic_table=REALISTIC_TABLE,
    varied_table=VARIED_TABLE,
    varied_template="oven_varied.urdf.xacro",
    placement="floor",
)

__all__ = ["CLASS", "OVEN_STRUCTURE", "REALISTIC_TABLE", "TABLE", "VARIED_TABLE"]
