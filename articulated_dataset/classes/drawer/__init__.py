"""Drawer: one prismatic drawer sliding out of a shell.

``--table varied`` (:data:`VARIED_TABLE`, classes/drawer/drawer_varied.urdf.xacro) builds the
labelled drawer into a carcass the way real drawers are built: fronts overlaid on the carcass
edges or inset in their openings, a column of drawer fronts (only the labelled one moves; the
others are closed parts of the body), a drawer over a door (the common base cabinet) or a
drawer column beside a door, a tray drawer (a low front in an open compartment), bar, knob,
recessed or no handles, a countertop and a plinth or legs.  The sizes are those of the whole
carcass (:data:`VARIED_SHAPE`): a single drawer unit, a kitchen drawer base, a chest of
drawers or an office pedestal.

Sources of the varied ranges (by name; every number is a *typical range* from these
standards and catalogues, not a measurement of our own; the ranges shared with the cabinets
are cited in :mod:`articulated_dataset.classes.varied`):

* carcass sizes: NKBA Kitchen Planning Guidelines (base cabinets 24 in deep, 34.5 in tall
  without the countertop; drawer bases 12-36 in wide); furniture catalogues (IKEA MALM chests
  48 cm deep, 78, 100 and 123 cm tall, 40 and 80 cm wide; HEMNES 50 cm deep; 24-36 in
  chests); office-furniture catalogues (Steelcase, HON pedestals ~22 in deep, 15-16 in wide,
  27-28 in tall);
* drawer fronts 4-12 in (10-30 cm) high: door-and-drawer-front catalogues (top drawer fronts
  5.5-6.5 in, deep pot drawers 9.5-12 in; chest drawers 6-10 in);
* 1/16-1/8 in (2-4 mm) between full-overlay fronts: concealed-hinge and drawer-runner
  planning guides (Blum, Hettich: 2-3 mm front gaps);
* drawer-front thickness 5/8-7/8 in (16-22 mm): the door range of door catalogues;
* full-extension runners (Blum TANDEM/MOVENTO, Hettich Quadro, Accuride 3832) travel the
  runner's nominal length, which is the drawer box's length: the carcass depth less its back
  and a few millimetres.  The labelled drawer opens from 0 (closed) to :data:`DRAWER_Q_M`, the
  extension of the shortest box the table can build (:func:`shortest_box_m`), so no drawer
  leaves its carcass;
* roll-out trays with 2-1/2 to 4 in (60-100 mm) fronts: pull-out shelf catalogues (Rev-A-Shelf,
  Knape & Vogt);
* a door beside a drawer bank taking 40-60% of a combination base (18 in drawers beside a
  15-24 in door in 33-42 in units): kitchen cabinet specification books (KraftMaid, IKEA
  SEKTION planning guide);
* pulls centred across the front (offset pulls on wide fronts), at mid-height or in the upper
  part of deep fronts; J-pull and finger-pull channels 20-35 mm high: hardware installation
  guides (Amerock, Richelieu) and handle-less front profiles (Blum, Hafele).

How often each structure occurs (probabilities and option weights) is this package's
assumption, not a published statistic.
"""

from dataclasses import replace

from articulated_dataset.classes.base import PRISMATIC, JointSpec, ObjectClass
from articulated_dataset.classes.common import YAW_RAD
from articulated_dataset.classes.realistic import DRAWER, _steps, realistic_table, standard
from articulated_dataset.classes.varied import CABINET_STRUCTURE, varied_table
from articulated_dataset.core.tables import SamplingTable, ShapeMixture

TABLE = SamplingTable(
    geometry={"depth_m": (0.45, 0.60), "width_m": (0.30, 0.76), "height_m": (0.10, 0.30)},
    pose={"x_m": (1.0, 2.0), "y_m": (-0.5, 0.5), "z_m": (-0.8, 0.0), "yaw_rad": YAW_RAD},
    q=((0.0, 0.40),),  # the paper's 0-40 cm
)

#: ``--table realistic``: sizes from standard dimensions (classes/realistic.py).
REALISTIC_TABLE = realistic_table(TABLE, *DRAWER)

#: Carcass sizes of the varied drawers (the whole body: carcass, countertop, base and the
#: closed fronts; inches): the realistic single-drawer units and the carcasses that hold
#: several drawers.  Bounds keep every size class >= 3 sigma inside.
VARIED_SHAPE = (
    {"depth_m": (0.44, 0.64), "width_m": (0.28, 0.94), "height_m": (0.09, 1.25)},
    (
        *(replace(c, weight=0.4 * c.weight) for c in DRAWER[1]),
        standard("kitchen drawer base carcass", 0.30, [24], _steps(12, 36), [34.5], std_m=(0.006, 0.003, 0.004)),
        standard("chest carcass", 0.20, [19, 20], [16, 24, 30, 33, 36], [30, 39, 48], std_m=(0.008, 0.005, 0.006)),
        standard("office pedestal carcass", 0.10, [22], [15, 16], [27, 28], std_m=(0.006, 0.003, 0.004)),
    ),
)

#: Height (m) from which a varied carcass stands on the floor and takes its countertop and
#: plinth or legs (kitchen drawer bases, chests, pedestals: 0.69 m and taller); a single
#: drawer's shell (at most 0.32 m) is built without them.  The template's "standing".
FLOOR_STANDING_M = 0.5
#: Drawer runner clearance behind the box (m): the template's clear_m.
BOX_CLEARANCE_M = 0.004
#: Drawer structure variables shared with the cabinets (same meaning, ranges and sources).
_SHARED = ("overlay_m", "inset_gap_m", "carcass_m", "base_weights", "base_height_m", "plinth_setback_m",
           "leg_size_m", "leg_inset_m", "countertop_p", "countertop_thickness_m", "countertop_overhang_m",
           "handle_length_m", "handle_width_m", "handle_standoff_m", "knob_m")

#: Structure variables of the varied drawers: name -> range, probability or option weights
#: (the module's sources); every argument of classes/drawer/drawer_varied.urdf.xacro.
DRAWER_STRUCTURE = {
    **{name: CABINET_STRUCTURE[name] for name in _SHARED},
    "front_inset_p": 0.2,
    "front_thickness_m": CABINET_STRUCTURE["door_thickness_m"],
    "front_gap_m": (0.002, 0.004),
    "front_height_m": (0.10, 0.30),
    "layout_weights": {"stack": 0.5, "over_door": 0.3, "beside_door": 0.2},
    "slot_frac": (0.0, 1.0),
    "column_frac": (0.4, 0.6),
    "door_left_p": 0.5,
    "tray_p": 0.15,
    "tray_front_m": (0.06, 0.10),
    "handle_weights": {"bar": 0.5, "knob": 0.2, "recessed": 0.15, "none": 0.15},
    "handle_y_frac": (0.3, 0.7),
    "handle_z_frac": (0.3, 0.85),
    "grip_height_m": (0.02, 0.035),
}


def shortest_box_m(depth_m: float, structure: dict) -> float:
    """Length (m) of the shortest drawer box the template builds in a carcass ``depth_m``
    deep with ``structure``'s ranges: less the thickest back board and the runner clearance,
    and the most the front takes: an inset front's thickness and, in front of the carcass,
    the lead of a countertop's overhang or of a closed front's bar or knob (an overlay front
    takes its thickness from the lead instead, no more)."""
    taken = structure["front_thickness_m"][1] + max(structure["countertop_overhang_m"][1], structure["handle_standoff_m"][1])
    return depth_m - structure["carcass_m"][1] - BOX_CLEARANCE_M - taken


#: Widest opening of a varied drawer (m): full extension of the shortest box (0.355 m),
#: rounded down to the centimetre.
DRAWER_Q_M = (0.0, 0.35)

#: Height of a varied carcass's base below the camera (m): 20 cm lower than the paper's
#: drawer (-0.8 to 0 m), so that a labelled drawer low in a carcass up to 1.25 m tall is
#: seen as often as a top one.
VARIED_Z_M = (-1.0, 0.0)

#: ``--table varied``: carcass sizes (:data:`VARIED_SHAPE`), the labelled drawer opening to
#: :data:`DRAWER_Q_M` and the structure variables :data:`DRAWER_STRUCTURE`.
VARIED_TABLE = varied_table(
    replace(REALISTIC_TABLE, geometry=VARIED_SHAPE[0], shape=ShapeMixture(VARIED_SHAPE[1]),
            pose={**TABLE.pose, "z_m": VARIED_Z_M}),
    (DRAWER_Q_M,), DRAWER_STRUCTURE)

CLASS = ObjectClass(
    name="drawer",
    template="drawer.urdf.xacro",
    table=TABLE,
    joints=(JointSpec("drawer_slide", PRISMATIC, "drawer"),),
    description="1 prismatic drawer sliding out of a hollow shell",
    order=1,
    realistic_table=REALISTIC_TABLE,
    varied_table=VARIED_TABLE,
    varied_template="drawer_varied.urdf.xacro",
    mirror_joints=(0,),
    placement="under_counter_drawer",
)
