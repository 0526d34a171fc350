"""Refrigerator: two revolute doors stacked vertically, hinged on the same side (2 DoF).

The paper's height range (82-88 cm) describes an under-counter refrigerator, not a
full-size one; it is kept as published so the benchmark reproduces the paper (see
DATASHEET.md), and a table file can override it.
"""

from articulated_dataset.classes import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.tables import SamplingTable

from .common import REVOLUTE_Q_RAD, YAW_RAD
from .realistic import REFRIGERATOR, realistic_table

TABLE = SamplingTable(
    geometry={"depth_m": (0.60, 0.80), "width_m": (0.60, 0.90), "height_m": (0.82, 0.88)},
    pose={"x_m": (1.5, 3.5), "y_m": (-1.0, 1.0), "z_m": (-1.5, -0.7), "yaw_rad": YAW_RAD},
    q=(REVOLUTE_Q_RAD, REVOLUTE_Q_RAD),
    chirality_p=0.0,
)

#: ``--table realistic``: sizes from standard dimensions (generators/realistic.py).
REALISTIC_TABLE = realistic_table(TABLE, *REFRIGERATOR)

CLASS = ObjectClass(
    name="refrigerator",
    template="refrigerator.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("lower_door_hinge", REVOLUTE, "lower_door"), JointSpec("upper_door_hinge", REVOLUTE, "upper_door")),
    sided=True,
    description="2 revolute doors stacked vertically (joint 0 lower, joint 1 upper), hinged on the same side",
    order=5,
    realistic_table=REALISTIC_TABLE,
)
