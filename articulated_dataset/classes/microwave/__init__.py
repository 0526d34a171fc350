"""Microwave: one side-hinged revolute door (hinged on the left, as most microwaves).

``--table varied`` (classes/microwave/microwave_varied.urdf.xacro) adds the structures real
microwaves have, drawn per object (:data:`MICROWAVE_STRUCTURE`): a keypad of varied width
beside the door's free edge (left or right with the hinge side), a door of varied thickness
with or without a window (a glass pane set back in the door's frame: in depth, a thin inset
region), a vertical bar handle, a recessed grip or a push button, and a countertop body on
feet or a built-in one in a trim frame; doors open to 105 degrees.

Sources of the ranges (by name; this package was written without access to them, so every
number is a *typical range* compiled from these references, not a measurement of our own):

* keypads: countertop microwaves 45-60 cm wide carry a 10-13 cm keypad, over-the-range models
  (76 cm) about 15-18 cm: 0.18-0.27 of the front (manufacturers' specification sheets and
  product photographs: Panasonic, GE, Whirlpool, Samsung, Sharp); the paper's 0.25;
* doors: 25-45 mm thick with their choke frame (replacement door assemblies of the same
  makers); the window's frame 25-50 mm on the hinge side, top and bottom and 50-90 mm on the
  latch side, where the handle or the latch sits; the pane set 3-10 mm behind the frame's
  face (same photographs and parts listings);
* handles: vertical bars over half to most of the door's height, 15-30 mm thick, standing
  25-45 mm off the door, 15-40 mm from its free edge; a recessed grip 15-30 mm wide and deep
  between the door and the keypad; a push-button door release 20-40 mm tall at the keypad's
  bottom (GE, Panasonic, Sharp, Whirlpool models);
* trim frames: built-in trim kits are 27 or 30 in wide outside (GE Appliances, "Built-In
  Countertop Microwave"), around a microwave of 22-24 in: 1-1/2 to 4 in (38-100 mm) a side;
  25-50 mm above, 40-90 mm below (the lower vent grille); a 10-20 mm plate.  A trim frame
  takes the object's box, so the microwave inside it is smaller;
* feet: countertop microwaves stand on 8-20 mm rubber feet, 15-40 mm across, 20-60 mm in from
  the body's corners (product photographs; woodworking forum notes that the feet keep the
  bottom high enough to draw in air);
* openings: side-hinged microwave doors stop at 100-110 degrees (product specifications and
  photographs); 105 degrees here.

How often each structure occurs (the probabilities and option weights) and the share of
right-hinged microwaves (:data:`MICROWAVE_VARIED_CHIRALITY_P`; most are hinged on the left,
so the side is learnt from the keypad and door, not from a prior) are this package's
assumption, not a published statistic; each variable is drawn independently of the others
and of the size class.
"""

import math
from dataclasses import replace

from articulated_dataset.classes.base import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.classes.common import NEAR_POSE_M, REVOLUTE_Q_RAD, YAW_RAD
from articulated_dataset.classes.realistic import MICROWAVE, realistic_table
from articulated_dataset.classes.varied import varied_table
from articulated_dataset.core.tables import SamplingTable

TABLE = SamplingTable(
    geometry={"depth_m": (0.25, 0.56), "width_m": (0.40, 0.76), "height_m": (0.22, 0.45)},
    pose={**NEAR_POSE_M, "yaw_rad": YAW_RAD},
    q=(REVOLUTE_Q_RAD,),
    chirality_p=0.0,  # the paper gives no mirrored microwaves; override to mirror some
)

#: ``--table realistic``: sizes from standard dimensions (classes/realistic.py).
REALISTIC_TABLE = realistic_table(TABLE, *MICROWAVE)

#: Widest opening of a varied microwave door (rad): 105 degrees (side-hinged doors stop at 100-110).
MICROWAVE_DOOR_Q_RAD = (0.0, math.radians(105.0))
#: Share of varied microwaves hinged on the right (keypad on the left); an assumption.
MICROWAVE_VARIED_CHIRALITY_P = 0.2

#: Structure variables of the varied microwave: name -> range, probability or option weights
#: (sources in the module's docstring).  Every argument of classes/microwave/microwave_varied.urdf.xacro.
MICROWAVE_STRUCTURE = {
    "keypad_width_frac": (0.18, 0.27),
    "door_thickness_m": (0.025, 0.045),
    "window_p": 0.85,
    "window_border_m": (0.025, 0.05),
    "window_free_border_m": (0.05, 0.09),
    "window_recess_m": (0.003, 0.010),
    "handle_weights": {"bar": 0.45, "recess": 0.25, "button": 0.3},
    "handle_length_frac": (0.5, 0.85),
    "handle_width_m": (0.015, 0.030),
    "handle_standoff_m": (0.025, 0.045),
    "handle_inset_m": (0.015, 0.040),
    "grip_width_m": (0.015, 0.030),
    "grip_depth_m": (0.015, 0.030),
    "button_height_m": (0.02, 0.04),
    "trim_p": 0.2,
    "trim_side_m": (0.038, 0.100),
    "trim_top_m": (0.025, 0.050),
    "trim_bottom_m": (0.040, 0.090),
    "trim_thickness_m": (0.010, 0.020),
    "feet_p": 0.8,
    "foot_height_m": (0.008, 0.020),
    "foot_size_m": (0.015, 0.040),
    "foot_inset_m": (0.020, 0.060),
}

#: ``--table varied``: the realistic sizes, doors opening to 105 degrees, some hinged on the
#: right, and the structure variables above (classes/microwave/microwave_varied.urdf.xacro).
VARIED_TABLE = replace(varied_table(REALISTIC_TABLE, (MICROWAVE_DOOR_Q_RAD,), MICROWAVE_STRUCTURE),
                       chirality_p=MICROWAVE_VARIED_CHIRALITY_P)

CLASS = ObjectClass(
    name="microwave",
    template="microwave.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("door_hinge", REVOLUTE, "door"),),
    sided=True,
    description="1 revolute side-hinged door beside a control panel",
    order=2,
    realistic_table=REALISTIC_TABLE,
    varied_table=VARIED_TABLE,
    varied_template="microwave_varied.urdf.xacro",
    placement="on_counter",
)
