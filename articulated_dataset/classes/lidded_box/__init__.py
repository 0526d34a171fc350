"""Lidded box: a storage box, chest, pencil case or tool box, one revolute lid hinged along
the body's top back edge, opening up and over to the back (to 200 degrees: a lid that falls
back towards the table behind the box).

The paper has no lidded box; real labelled depth of hinged-lid boxes is the most common
public articulated real data (pencil cases, storage boxes).  The default table
(``--table paper``, the class's own) draws sizes from a pencil case's to a chest's uniformly
and builds one structure (classes/lidded_box/lidded_box.urdf.xacro: a 2 cm lid overlaying
12 mm walls by 1 cm, a latch); ``--table realistic`` draws the sizes from size classes;
``--table varied`` draws the structure per object (:data:`LIDDED_BOX_STRUCTURE`).

Sources of the ranges (by name; every number is a *typical range* compiled from these
references, not a measurement of our own):

* sizes: hinged pencil cases and pencil boxes 18-22 cm x 8-12 cm x 3-6 cm (stationery
  catalogues); shoe and storage boxes with hinged lids 30-40 x 20-30 x 12-20 cm; tool boxes
  14-22 in (0.36-0.56 m) wide, 7-10 in deep and high (Stanley, DeWalt, Craftsman
  catalogues); blanket chests and trunks 30-48 in (0.76-1.2 m) wide, 16-20 in deep, 18-24 in
  high (furniture catalogues); boxes 16-28 cm wide at 0.55-1.2 m from a RealSense in the
  public mixed-reality box captures this class is benchmarked on;
* walls: 3-20 mm (moulded plastic 3-5 mm, plywood and board 9-20 mm); lids 5-30 mm thick,
  overlaying the walls by 0-2 cm or sitting inset;
* latches and handles: 3-10 cm across, standing 1-2 cm off the lid's front edge;
* openings: a lid on a piano or butt hinge swings past vertical until it rests on the table
  or a stay; 200 degrees lets it lie past flat behind the box.

How often each structure occurs is this package's assumption, not a published statistic;
each variable is drawn independently of the others and of the size class.
"""

import math

from articulated_dataset.classes.base import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.classes.common import YAW_RAD
from articulated_dataset.classes.realistic import realistic_table, typical
from articulated_dataset.classes.varied import varied_table
from articulated_dataset.core.tables import SamplingTable

#: A lid's configuration range (rad): closed to 200 degrees, past flat behind the box.
LID_Q_RAD = (0.0, math.radians(200.0))

TABLE = SamplingTable(
    geometry={"depth_m": (0.08, 0.50), "width_m": (0.15, 0.90), "height_m": (0.04, 0.45)},
    pose={"x_m": (0.6, 1.6), "y_m": (-0.4, 0.4), "z_m": (-0.55, -0.25), "yaw_rad": YAW_RAD},
    q=(LID_Q_RAD,),
)

#: Size bounds (m) of ``--table realistic``: every size class at least 3 sigma inside.
REALISTIC_BOUNDS_M = {"depth_m": (0.06, 0.62), "width_m": (0.13, 1.05), "height_m": (0.03, 0.62)}

#: ``--table realistic``: size classes (depth, width, height in m; sources above).
REALISTIC_TABLE = realistic_table(TABLE, REALISTIC_BOUNDS_M, (
    typical("pencil case", 0.25, (0.10, 0.20, 0.045), (0.010, 0.012, 0.006), 0.3, 0.3, 0.3),
    typical("storage box", 0.35, (0.25, 0.35, 0.16), (0.030, 0.040, 0.025), 0.5, 0.4, 0.4),
    typical("tool box", 0.25, (0.22, 0.46, 0.22), (0.020, 0.045, 0.025), 0.5, 0.4, 0.5),
    typical("chest", 0.15, (0.45, 0.90, 0.50), (0.030, 0.060, 0.040), 0.4, 0.3, 0.3),
))

#: Structure variables of the varied lidded box: name -> range, probability or option weights
#: (sources in the module's docstring).  Every argument of
#: classes/lidded_box/lidded_box_varied.urdf.xacro.
LIDDED_BOX_STRUCTURE = {
    "lid_weights": {"overlay": 0.75, "inset": 0.25},
    "lid_thickness_m": (0.005, 0.03),
    "overhang_m": (0.0, 0.02),
    "box_wall_m": (0.003, 0.02),
    "latch_p": 0.6,
    "latch_length_m": (0.03, 0.10),
    "latch_standoff_m": (0.01, 0.02),
}

#: ``--table varied``: the realistic sizes, the 200-degree opening and the structure variables
#: above (classes/lidded_box/lidded_box_varied.urdf.xacro).
VARIED_TABLE = varied_table(REALISTIC_TABLE, (LID_Q_RAD,), LIDDED_BOX_STRUCTURE)

CLASS = ObjectClass(
    name="lidded_box",
    template="lidded_box.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("lid_hinge", REVOLUTE, "lid"),),
    description="lidded box (pencil case to chest): 1 revolute lid hinged at the top back edge, opening to 200 deg",
    order=9,
    realistic_table=REALISTIC_TABLE,
    varied_table=VARIED_TABLE,
    varied_template="lidded_box_varied.urdf.xacro",
    placement="on_counter",
)

__all__ = ["CLASS", "LIDDED_BOX_STRUCTURE", "LID_Q_RAD", "REALISTIC_TABLE", "TABLE", "VARIED_TABLE"]
