"""Two-door cabinet: a left and a right revolute door (2 DoF)."""

from articulated_dataset.classes.base import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.classes.common import NEAR_POSE_M, REVOLUTE_Q_RAD, YAW_RAD
from articulated_dataset.classes.realistic import CABINET2, realistic_table
from articulated_dataset.classes.varied import CABINET_DOOR_Q_RAD, CABINET_STRUCTURE, varied_table
from articulated_dataset.core.tables import SamplingTable

TABLE = SamplingTable(
    geometry={"depth_m": (0.56, 0.64), "width_m": (0.60, 1.40), "height_m": (0.60, 1.40)},
    pose={**NEAR_POSE_M, "yaw_rad": YAW_RAD},
    q=(REVOLUTE_Q_RAD, REVOLUTE_Q_RAD),
)

#: ``--table realistic``: sizes from standard dimensions (classes/realistic.py).
REALISTIC_TABLE = realistic_table(TABLE, *CABINET2)

#: ``--table varied``: the realistic sizes, doors opening to 120 degrees and the structure
#: variables of classes/varied.py (classes/cabinet2/cabinet2_varied.urdf.xacro).
VARIED_TABLE = varied_table(REALISTIC_TABLE, (CABINET_DOOR_Q_RAD, CABINET_DOOR_Q_RAD), CABINET_STRUCTURE)

CLASS = ObjectClass(
    name="cabinet2",
    template="cabinet2.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("left_door_hinge", REVOLUTE, "left_door"), JointSpec("right_door_hinge", REVOLUTE, "right_door")),
    description="two-door cabinet: left door (joint 0) and right door (joint 1)",
    order=4,
    realistic_table=REALISTIC_TABLE,
    varied_table=VARIED_TABLE,
    varied_template="cabinet2_varied.urdf.xacro",
    mirror_joints=(1, 0),
    placement="under_counter",
)
