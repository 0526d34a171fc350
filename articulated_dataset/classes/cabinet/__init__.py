"""Cabinet: one revolute door, hinged left or right with equal probability."""

from articulated_dataset.classes.base import REVOLUTE, JointSpec, ObjectClass
from articulated_dataset.classes.common import NEAR_POSE_M, REVOLUTE_Q_RAD, YAW_RAD
from articulated_dataset.classes.realistic import CABINET, realistic_table
from articulated_dataset.classes.varied import CABINET_DOOR_Q_RAD, CABINET_STRUCTURE, varied_table
from articulated_dataset.core.tables import SamplingTable

TABLE = SamplingTable(
    geometry={"depth_m": (0.56, 0.64), "width_m": (0.60, 1.40), "height_m": (0.60, 1.40)},
    pose={**NEAR_POSE_M, "yaw_rad": YAW_RAD},
    q=(REVOLUTE_Q_RAD,),
    chirality_p=0.5,  # "Cabinets that open clockwise/counterclockwise ... with equal probability"
)

#: ``--table realistic``: sizes from standard dimensions (classes/realistic.py).
REALISTIC_TABLE = realistic_table(TABLE, *CABINET)

#: ``--table varied``: the realistic sizes, doors opening to 120 degrees and the structure
#: variables of classes/varied.py (classes/cabinet/cabinet_varied.urdf.xacro).
VARIED_TABLE = varied_table(REALISTIC_TABLE, (CABINET_DOOR_Q_RAD,), CABINET_STRUCTURE)

CLASS = ObjectClass(
    name="cabinet",
    template="cabinet.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("door_hinge", REVOLUTE, "door"),),
    sided=True,
    description="1 revolute door, hinged on the left or right front edge",
    order=0,
    realistic_table=REALISTIC_TABLE,
    varied_table=VARIED_TABLE,
    varied_template="cabinet_varied.urdf.xacro",
    mirror_joints=(0,),
    placement="under_counter",
)
