"""Microwave: one side-hinged revolute door (hinged on the left, as most microwaves)."""

from articulated_dataset.classes import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.tables import SamplingTable

from .common import NEAR_POSE_M, REVOLUTE_Q_RAD, YAW_RAD
from .realistic import MICROWAVE, realistic_table

TABLE = SamplingTable(
    geometry={"depth_m": (0.25, 0.56), "width_m": (0.40, 0.76), "height_m": (0.22, 0.45)},
    pose={**NEAR_POSE_M, "yaw_rad": YAW_RAD},
    q=(REVOLUTE_Q_RAD,),
    chirality_p=0.0,  # the paper gives no mirrored microwaves; override to mirror some
)

#: ``--table realistic``: sizes from standard dimensions (generators/realistic.py).
REALISTIC_TABLE = realistic_table(TABLE, *MICROWAVE)

CLASS = ObjectClass(
    name="microwave",
    template="microwave.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("door_hinge", REVOLUTE, "door"),),
    sided=True,
    description="1 revolute side-hinged door beside a control panel",
    order=2,
    realistic_table=REALISTIC_TABLE,
)
