"""Toaster oven: one revolute door hinged at its bottom edge, opening downwards.

``--table varied`` (classes/toaster/toaster_varied.urdf.xacro) adds the structures real
toaster ovens (and the ovens a model reads as toaster ovens) have, drawn per object
(:data:`TOASTER_STRUCTURE`): the control panel beside the door, above it, or below it (then
the door's hinge sits on top of the panel, not at the body's bottom), a rail of the body's
front frame under the door, a door of varied thickness with or without a window (a glass
pane set back in the door's frame: in depth, a thin inset region), a handle bar of varied
size, and feet.  Doors open to 90 degrees, as the paper's.

Sources of the ranges (by name; this package was written without access to them, so every
number is a *typical range* compiled from these references, not a measurement of our own):

* control panels: beside the door on most toaster ovens, 9-14 cm of a 39-51 cm front,
  0.2-0.3 (Black+Decker, Hamilton Beach, Cuisinart, Breville specification sheets and product
  photographs); a strip above the door (flip-up and air-fry ovens such as Ninja's; built-in
  wall ovens) or below it (ovens whose door sits above a control strip, vent or drawer:
  freestanding ranges' and some countertop ovens'), 0.12-0.35 of the front's height, which
  puts the hinge where real ovens have it, 12-26 cm up a 0.9 m range (issue notes measured
  on third-party ovens);
* doors: 15-30 mm thick, glass in a 20-50 mm metal frame, the pane 3-8 mm behind the frame's
  face; a 5-30 mm rail of the body's frame under the door (same catalogues; a 1/8 in gap
  around the door, Hamilton Beach support notes, is the template's 2 mm gap);
* handles: a horizontal bar across half to most of the door's width, 12-25 mm thick,
  standing 20-40 mm off the door, its centre line 15-40 mm below the door's top edge;
* feet: 10-30 mm tall, 15-40 mm across, 10-50 mm in from the body's corners;
* openings: bottom-hinged doors stop at about 90 degrees (the paper's range).

How often each structure occurs (the probabilities and option weights) is this package's
assumption, not a published statistic; each variable is drawn independently of the others
and of the size class.
"""

from articulated_dataset.classes.base import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.classes.common import NEAR_POSE_M, REVOLUTE_Q_RAD, YAW_RAD
from articulated_dataset.classes.realistic import TOASTER, realistic_table
from articulated_dataset.classes.varied import varied_table
from articulated_dataset.core.tables import SamplingTable

TABLE = SamplingTable(
    geometry={"depth_m": (0.20, 0.50), "width_m": (0.40, 0.60), "height_m": (0.20, 0.50)},
    pose={**NEAR_POSE_M, "yaw_rad": YAW_RAD},
    q=(REVOLUTE_Q_RAD,),
)

#: ``--table realistic``: sizes from standard dimensions (classes/realistic.py).
REALISTIC_TABLE = realistic_table(TABLE, *TOASTER)

#: Structure variables of the varied toaster oven: name -> range, probability or option
#: weights (sources in the module's docstring).  Every argument of
#: classes/toaster/toaster_varied.urdf.xacro.
TOASTER_STRUCTURE = {
    "panel_weights": {"side": 0.6, "above": 0.15, "below": 0.25},
    "panel_width_frac": (0.2, 0.3),
    "panel_height_frac": (0.12, 0.35),
    "door_rail_m": (0.005, 0.030),
    "door_thickness_m": (0.015, 0.030),
    "window_p": 0.9,
    "window_border_m": (0.02, 0.05),
    "window_recess_m": (0.003, 0.008),
    "handle_length_frac": (0.5, 0.85),
    "handle_width_m": (0.012, 0.025),
    "handle_standoff_m": (0.02, 0.04),
    "handle_inset_m": (0.015, 0.040),
    "feet_p": 0.8,
    "foot_height_m": (0.010, 0.030),
    "foot_size_m": (0.015, 0.040),
    "foot_inset_m": (0.010, 0.050),
}

#: ``--table varied``: the realistic sizes, the paper's 90-degree opening and the structure
#: variables above (classes/toaster/toaster_varied.urdf.xacro).
VARIED_TABLE = varied_table(REALISTIC_TABLE, (REVOLUTE_Q_RAD,), TOASTER_STRUCTURE)

CLASS = ObjectClass(
    name="toaster",
    template="toaster.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("door_hinge", REVOLUTE, "door"),),
    description="toaster oven: 1 revolute door hinged at the bottom, opening downwards",
    order=3,
    realistic_table=REALISTIC_TABLE,
    varied_table=VARIED_TABLE,
    varied_template="toaster_varied.urdf.xacro",
    placement="on_counter",
)
