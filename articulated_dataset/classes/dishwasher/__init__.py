"""Dishwasher: an under-counter dishwasher, one revolute door hinged at its bottom edge above
a toe-kick, opening downwards, with racks inside.

The paper has no dishwasher.  The default table (``--table paper``, the class's own) draws
the sizes of built-in dishwashers uniformly and builds one structure
(classes/dishwasher/dishwasher.urdf.xacro: a 10 cm toe-kick, a plain door with its controls on
the top edge and a bar handle, two racks); ``--table realistic`` draws the sizes from the
18-in and 24-in size classes; ``--table varied`` draws the structure per object
(:data:`DISHWASHER_STRUCTURE`).  In ``--scene kitchen`` the counter top rests on it.

Sources of the ranges (by name; every number is a *typical range* compiled from these
references, not a measurement of our own):

* sizes: built-in dishwashers 18 in (compact) or 24 in (standard) wide, 33.5-35 in tall to
  fit under a 34.5-36 in counter (adjustable feet), 22.5-24.5 in deep without the door
  (Bosch, Whirlpool, GE, Miele and KitchenAid installation instructions; NKBA Kitchen
  Planning Guidelines for the opening under the counter);
* toe-kick: a kick plate 3.5-5.5 in (0.09-0.14 m) high, set back 1-2.5 in (0.025-0.065 m) in
  line with the cabinets' toe-kicks (the same installation instructions, NKBA);
* doors: 1.5-3 in (0.04-0.07 m) thick with the inner liner; a cabinet-matching panel makes a
  door with no visible handle or controls ("panel-ready" models);
* controls: on the door's top edge (top-control, hidden when closed) or in a 3-5 in
  (0.08-0.12 m) strip across the door's face (front-control);
* handles: a bar across 0.4-0.8 of the door, 1-1.5 in (0.025-0.04 m) off the door, or a
  pocket 1.5-2.5 in (0.035-0.06 m) high under the top edge, cut 2 cm into the door;
* openings: the door opens to horizontal, 90 degrees.

How often each structure occurs is this package's assumption, not a published statistic;
each variable is drawn independently of the others and of the size class.
"""

from articulated_dataset.classes.base import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.classes.common import REVOLUTE_Q_RAD, YAW_RAD
from articulated_dataset.classes.realistic import realistic_table, standard
from articulated_dataset.classes.varied import varied_table
from articulated_dataset.core.tables import SamplingTable

TABLE = SamplingTable(
    geometry={"depth_m": (0.55, 0.63), "width_m": (0.44, 0.61), "height_m": (0.81, 0.89)},
    pose={"x_m": (1.2, 2.2), "y_m": (-0.5, 0.5), "z_m": (-0.8, -0.2), "yaw_rad": YAW_RAD},
    q=(REVOLUTE_Q_RAD,),
)

#: Size bounds (m) of ``--table realistic``: every size class at least 3 sigma inside.
REALISTIC_BOUNDS_M = {"depth_m": (0.53, 0.65), "width_m": (0.43, 0.63), "height_m": (0.80, 0.91)}

#: ``--table realistic``: standard and compact built-in dishwashers (sources above).
REALISTIC_TABLE = realistic_table(TABLE, REALISTIC_BOUNDS_M, (
    standard("24-in standard", 0.85, [22.5, 23.5, 24.5], [23.6], [33.5, 34, 35], std_m=(0.008, 0.002, 0.006)),
    standard("18-in compact", 0.15, [22.5, 23.5], [17.6], [33.5, 34, 35], std_m=(0.008, 0.002, 0.006)),
))

#: Structure variables of the varied dishwasher: name -> range, probability or option weights
#: (sources in the module's docstring).  Every argument of
#: classes/dishwasher/dishwasher_varied.urdf.xacro.
DISHWASHER_STRUCTURE = {
    "kick_height_m": (0.09, 0.14),
    "kick_setback_m": (0.025, 0.065),
    "door_thickness_m": (0.04, 0.07),
    "controls_weights": {"top": 0.6, "front": 0.4},
    "control_height_m": (0.08, 0.12),
    "handle_weights": {"bar": 0.55, "pocket": 0.3, "none": 0.15},
    "handle_length_frac": (0.4, 0.8),
    "handle_width_m": (0.012, 0.025),
    "handle_standoff_m": (0.025, 0.04),
    "handle_inset_m": (0.035, 0.06),
    "racks_p": 0.8,
}

#: ``--table varied``: the realistic sizes, the 90-degree opening and the structure variables
#: above (classes/dishwasher/dishwasher_varied.urdf.xacro).
VARIED_TABLE = varied_table(REALISTIC_TABLE, (REVOLUTE_Q_RAD,), DISHWASHER_STRUCTURE)

CLASS = ObjectClass(
    name="dishwasher",
    template="dishwasher.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("door_hinge", REVOLUTE, "door"),),
    description="dishwasher (under-counter): 1 revolute door hinged at the bottom above a toe-kick",
    order=8,
    realistic_table=REALISTIC_TABLE,
    varied_table=VARIED_TABLE,
    varied_template="dishwasher_varied.urdf.xacro",
    placement="under_counter",
)

__all__ = ["CLASS", "DISHWASHER_STRUCTURE", "REALISTIC_TABLE", "TABLE", "VARIED_TABLE"]
