"""Refrigerator: two revolute doors stacked vertically, hinged on the same side (2 DoF).

The paper's height range (82-88 cm) describes an under-counter refrigerator, not a
full-size one; it is kept as published so the benchmark reproduces the paper (see
DATASHEET.md), and a table file can override it.

``--table varied`` (:data:`VARIED_TABLE`, classes/refrigerator/refrigerator_varied.urdf.xacro):
the realistic sizes (compact to large full-size, 0.76-1.82 m tall, 0.42-0.88 m wide:
classes/realistic.py), doors hinged on either side and opening to 130 degrees, and :data:`REFRIGERATOR_STRUCTURE`
drawn per object.  Joint 0 stays the lower door and joint 1 the upper one whichever is the
freezer's.  Sources of the ranges (by name; every number is a *typical range* compiled from
these catalogues and guides, not a measurement of our own):

* top freezer (the freezer door above) or bottom freezer (below), the freezer compartment
  25-35% of the height: manufacturers' specification sheets of two-door top- and
  bottom-freezer models (GE, Whirlpool, Frigidaire top-freezers; Bosch, Liebherr, Samsung
  bottom-freezer combis with a hinged freezer door), which rate the freezer at roughly a
  quarter to a third of the total volume (AHAM HRF-1 volumes);
* doors 5-8 cm thick: the specification sheets' "depth with door" and "depth without door"
  (the cabinet), 2-3 in apart with the handle excluded (foamed-in-place insulated doors);
* cabinet walls 35-60 mm and the mullion between the compartments 40-70 mm: polyurethane
  foam insulation of household refrigerators between steel skin and liner (ASHRAE Handbook,
  Refrigeration, "Household Refrigerators and Freezers");
* the hinge pin 0-30 mm in from the body's side, anywhere across the door's thickness: the
  pin of the top and bottom hinge brackets enters the door's ends near its hinge-side edge
  (door-reversal instructions of the same manufacturers); where across the thickness is
  assumed uniform;
* toe grille 5-12 cm high, set back 0-3 cm: base grilles of freestanding refrigerators
  (manufacturers' parts diagrams: the grille covers the machine compartment under the lower
  door); compact models without one stand on feet (share assumed);
* glass shelves 0-3 in the fresh-food compartment, set back 5-10 cm behind the cabinet's
  front (clear of the door bins): specification sheets list 2-4 adjustable shelves;
* vertical bar handles on the free side, 15-75 cm long (at most 0.8 of the door's height),
  15-30 mm thick, standing 30-60 mm off the door, 30-80 mm from the free edge: replacement
  refrigerator handles of the same manufacturers (fresh-food handles about 12-30 in,
  freezer handles about 6-15 in); "none" stands for recessed grips in the door's edge and
  handle-less doors (a groove a box cannot cut); shares assumed; the handle lies anywhere
  from the end next to the other door (where pulls usually are) to the door's middle;
* doors hinged on the left or the right with equal probability (the paper's refrigerators
  all hinge on the left): the doors are reversible (door-reversal instructions), and which
  side a kitchen needs is its own; the even share is assumed;
* openings to 130 degrees: installation guides (doors are usually preset to open to about
  130 degrees; built-in door stops allow about 125 degrees and can be set down to 90).

How often each structure occurs (probabilities and option weights) is this package's
assumption, not a published statistic, and each variable is drawn independently of the
others and of the size class.
"""

import math
from dataclasses import replace

from articulated_dataset.classes.base import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.classes.common import REVOLUTE_Q_RAD, YAW_RAD
from articulated_dataset.classes.realistic import REFRIGERATOR, realistic_table
from articulated_dataset.classes.varied import varied_table
from articulated_dataset.core.tables import SamplingTable

TABLE = SamplingTable(
    geometry={"depth_m": (0.60, 0.80), "width_m": (0.60, 0.90), "height_m": (0.82, 0.88)},
    pose={"x_m": (1.5, 3.5), "y_m": (-1.0, 1.0), "z_m": (-1.5, -0.7), "yaw_rad": YAW_RAD},
    q=(REVOLUTE_Q_RAD, REVOLUTE_Q_RAD),
    chirality_p=0.0,
)

#: ``--table realistic``: sizes from standard dimensions (classes/realistic.py).
REALISTIC_TABLE = realistic_table(TABLE, *REFRIGERATOR)

#: Widest opening of a varied refrigerator door (rad): 130 degrees (the usual door stop).
REFRIGERATOR_DOOR_Q_RAD = (0.0, math.radians(130.0))

#: Structure variables of the varied refrigerator: name -> range, probability or option
#: weights (see the module's sources).  Every argument of refrigerator_varied.urdf.xacro.
REFRIGERATOR_STRUCTURE = {
    "layout_weights": {"top_freezer": 0.6, "bottom_freezer": 0.4},
    "freezer_frac": (0.25, 0.35),
    "wall_thickness_m": (0.035, 0.06),
    "mullion_m": (0.04, 0.07),
    "door_thickness_m": (0.05, 0.08),
    "hinge_inset_m": (0.0, 0.03),
    "hinge_depth_frac": (0.0, 1.0),
    "grille_p": 0.7,
    "grille_height_m": (0.05, 0.12),
    "grille_setback_m": (0.0, 0.03),
    "shelves_weights": {"0": 0.1, "1": 0.2, "2": 0.35, "3": 0.35},
    "shelf_setback_m": (0.05, 0.10),
    "handle_weights": {"bar_vertical": 0.8, "none": 0.2},
    "handle_length_m": (0.15, 0.75),
    "handle_width_m": (0.015, 0.03),
    "handle_standoff_m": (0.03, 0.06),
    "handle_inset_m": (0.03, 0.08),
    "handle_z_frac": (0.0, 0.5),
}

#: Probability of doors hinged on the right in ``--table varied``: either side (reversible doors).
VARIED_CHIRALITY_P = 0.5

#: ``--table varied``: the realistic sizes, doors hinged on either side and opening to 130
#: degrees, and the structure variables above (classes/refrigerator/refrigerator_varied.urdf.xacro).
VARIED_TABLE = replace(varied_table(REALISTIC_TABLE, (REFRIGERATOR_DOOR_Q_RAD,) * 2, REFRIGERATOR_STRUCTURE),
                       chirality_p=VARIED_CHIRALITY_P)

CLASS = ObjectClass(
    name="refrigerator",
    template="refrigerator.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("lower_door_hinge", REVOLUTE, "lower_door"), JointSpec("upper_door_hinge", REVOLUTE, "upper_door")),
    sided=True,
    description="2 revolute doors stacked vertically (joint 0 lower, joint 1 upper), hinged on the same side",
    order=5,
    realistic_table=REALISTIC_TABLE,
    varied_table=VARIED_TABLE,
    varied_template="refrigerator_varied.urdf.xacro",
    placement="floor",
)
