"""Values shared by several tables of the paper's Appendix A (Table 4)."""

import math

#: Rotation about z: [-pi/4, pi/4] rad for every class.
YAW_RAD = (-math.pi / 4, math.pi / 4)
#: Revolute configuration range: [0, pi/2] rad.
REVOLUTE_Q_RAD = (0.0, math.pi / 2)
#: Position ranges (m) of the base centre shared by cabinet, microwave, toaster, cabinet2.
NEAR_POSE_M = {"x_m": (1.0, 2.0), "y_m": (-0.5, 0.5), "z_m": (-0.7, 0.3)}
