"""Toaster oven: one revolute door hinged at its bottom edge, opening downwards."""

from articulated_dataset.classes import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.tables import SamplingTable

from .common import NEAR_POSE_M, REVOLUTE_Q_RAD, YAW_RAD
from .realistic import TOASTER, realistic_table

TABLE = SamplingTable(
    geometry={"depth_m": (0.20, 0.50), "width_m": (0.40, 0.60), "height_m": (0.20, 0.50)},
    pose={**NEAR_POSE_M, "yaw_rad": YAW_RAD},
    q=(REVOLUTE_Q_RAD,),
)

#: ``--table realistic``: sizes from standard dimensions (generators/realistic.py).
REALISTIC_TABLE = realistic_table(TABLE, *TOASTER)

CLASS = ObjectClass(
    name="toaster",
    template="toaster.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("door_hinge", REVOLUTE, "door"),),
    description="toaster oven: 1 revolute door hinged at the bottom, opening downwards",
    order=3,
    realistic_table=REALISTIC_TABLE,
)
