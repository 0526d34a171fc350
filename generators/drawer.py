"""Drawer: one prismatic drawer sliding out of a shell."""

from articulated_dataset.classes import PRISMATIC, JointSpec, ObjectClass
from articulated_dataset.tables import SamplingTable

from .common import YAW_RAD
from .realistic import DRAWER, realistic_table

TABLE = SamplingTable(
    geometry={"depth_m": (0.45, 0.60), "width_m": (0.30, 0.76), "height_m": (0.10, 0.30)},
    pose={"x_m": (1.0, 2.0), "y_m": (-0.5, 0.5), "z_m": (-0.8, 0.0), "yaw_rad": YAW_RAD},
    q=((0.0, 0.40),),  # the paper's 0-40 cm
)

#: ``--table realistic``: sizes from standard dimensions (generators/realistic.py).
REALISTIC_TABLE = realistic_table(TABLE, *DRAWER)

CLASS = ObjectClass(
    name="drawer",
    template="drawer.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("drawer_slide", PRISMATIC, "drawer"),),
    description="1 prismatic drawer sliding out of a hollow shell",
    order=1,
    realistic_table=REALISTIC_TABLE,
    mirror_joints=(0,),
)
