"""Third-party articulated objects from URDF files (e.g. PartNet-Mobility).

``artdata generate --urdf FILE`` renders a user-supplied URDF with the dataset's camera,
pose and configuration sampling and label definitions.  The URDF is turned into a
*processed* URDF that the pipeline treats like any class template:

* yourdfpy parses and checks the file; mesh paths are resolved relative to the URDF
  (``package://`` prefixes are tried relative to the URDF's folder and its parents);
* each link's geometry is its ``<visual>`` elements (its ``<collision>`` elements if it
  has no visual).  Meshes are loaded with trimesh, scaled, placed by their ``<origin>`` and
  merged into one binary STL per link (MuJoCo reads STL; a flat mesh gets a
  :data:`FLAT_MESH_THICKNESS_M` thickness because MuJoCo needs a 3-D convex hull), with
  every triangle made double-sided (MuJoCo culls back faces; see :func:`double_sided`);
  primitive boxes, cylinders and spheres are kept as they are;
* the joints to articulate (``--joints``, default: every revolute, continuous and
  prismatic joint with a non-empty range, in file order) keep their type; every other
  joint is frozen (``fixed``) at its URDF zero, the pose the meshes are modelled in;
* joint coordinates are re-parametrised so that q = 0 is a joint limit and positive q
  moves towards the other limit (the dataset's "q = 0 is closed, positive q opens"):
  limits ``[lo, hi]`` with ``lo >= 0`` are kept; ``hi <= 0`` flips the axis, giving
  ``[-hi, -lo]``; ``lo < 0 < hi`` moves the zero to ``lo`` (the joint origin is turned /
  shifted by ``lo`` along the axis), giving ``[0, hi - lo]``.  Continuous joints use the
  built-in revolute range [0, pi/2] rad;
* every link gets a fixed unit inertia: only kinematics is ever computed.

The processed files live in a content-addressed cache folder (:func:`cache_root`), rebuilt
on demand by any process (spawned workers, Ray workers on other nodes) from the
*definition*: a small JSON-able dict (source path, joints, options, sha256 of the URDF and
its meshes) that :class:`articulated_dataset.pipeline.GenerationConfig` carries in its
``third_party`` field.  A worker whose files differ from the driver's (changed file,
different copy on another node) stops with an error instead of writing different data.

Object frame and default pose table: the object frame is the URDF root link's frame; the
pose table places that frame (x, y, z, yaw), like the ``base`` link of the built-in
classes.  The default ranges keep the whole object (all links at q = 0) inside the image:
see :func:`view_pose_ranges`.  Third-party objects have no chirality (always 0) and a
fixed geometry (the table's geometry ranges are the body's bounding box, for reference).
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
import os
import re
import shutil
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .camera import CameraConfig
from .errors import UserError
from .registry import PRISMATIC, REVOLUTE, JointSpec, ObjectClass, class_names
from .tables import SamplingTable

log = logging.getLogger(__name__)

#: Version of the processed-model recipe; part of the cache key (bump when it changes).
IMPORT_VERSION = 2
#: Environment variable overriding the cache folder of processed URDF models.
CACHE_ENV = "ARTDATA_CACHE_DIR"
PROCESSED_URDF_NAME = "model.urdf"

#: URDF joint types that can be articulated, and the dataset joint type each becomes.
MOVABLE_TYPES = {"revolute": REVOLUTE, "continuous": REVOLUTE, "prismatic": PRISMATIC}
#: URDF joint types that cannot be articulated (frozen if not selected).
UNSUPPORTED_TYPES = ("floating", "planar")

#: Mass (kg) and principal inertia (kg m^2) given to every link: MuJoCo needs positive
#: values to compile, and the pipeline only ever computes kinematics.
LINK_MASS_KG = 1.0
LINK_INERTIA_KG_M2 = 1e-2
#: Effort (N or N m) and velocity (m/s or rad/s) written into re-parametrised <limit>s
#: (required by URDF, unused by kinematics).
LIMIT_EFFORT = 1.0
LIMIT_VELOCITY = 1.0
#: Thickness (m) given to a link mesh whose vertices are coplanar (0.1 mm: invisible at
#: any depth-sensor resolution; MuJoCo cannot take a flat mesh's convex hull).
FLAT_MESH_THICKNESS_M = 1e-4
#: Smallest size (m) of a geometry-table entry (the table needs positive ranges).
MIN_GEOMETRY_M = 1e-3
#: Nearest-distance margin of the default pose table: at the nearest distance the object's
#: bounding sphere fills 1 / VIEW_MARGIN (80%) of the narrower field of view.
VIEW_MARGIN = 1.25
#: Farthest distance of the default pose table relative to the nearest one.
FAR_DISTANCE_RATIO = 1.5
#: Class names are stored in the shards' ``class`` field (S32: 32 ASCII bytes).
MAX_CLASS_NAME_CHARS = 32
_NAME_OK = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
#: yourdfpy validation messages not treated as errors: a <limit>'s effort and velocity do
#: not matter for kinematics (PartNet-Mobility omits them), and URDF defaults a missing
#: lower / upper to 0.
_LENIENT_VALIDATION = re.compile(r"'(effort|velocity|lower|upper)'")


# --------------------------------------------------------------------------------------
# Pure helpers
# --------------------------------------------------------------------------------------

def view_pose_ranges(box_lo, box_hi, camera: CameraConfig, yaw_rad: tuple[float, float]) -> dict:
    """Default pose ranges that keep an object's bounding box inside the image.

    ``box_lo``, ``box_hi``: corners (m) of the object's axis-aligned bounding box in its
    root-link frame (z up).  The yaw rotates the object about the root frame's z axis, so
    the rule uses the sphere centred on that axis at the box's mid-height ``c_z`` that
    holds the box: radius ``r = max |corner - (0, 0, c_z)|``.  With ``alpha`` the smaller
    half field of view (vertical or horizontal) and ``m`` = :data:`VIEW_MARGIN`:

    * ``x_m`` in ``[d, FAR_DISTANCE_RATIO d]`` with ``d = m r / sin(alpha)``: at distance
      ``d`` the sphere is ``m`` times smaller than the view cone;
    * ``y_m`` in ``[-s, s]`` and ``z_m`` in ``[-s - c_z, s - c_z]`` with
      ``s = d tan(alpha) - r / cos(alpha) = (m - 1) r / cos(alpha)``: the largest offset of
      the sphere's centre that keeps it inside the frustum's side planes at distance ``d``
      (a point at distance x and offset s is ``x sin(alpha) - s cos(alpha)`` from the plane),
      hence at every sampled distance;
    * ``yaw_rad`` as given.

    Returns ``{"x_m": (lo, hi), "y_m": ..., "z_m": ..., "yaw_rad": ...}`` (metres, radians).
    """
    lo, hi = np.asarray(box_lo, float), np.asarray(box_hi, float)
    c_z = 0.5 * (lo[2] + hi[2])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    r = float(np.max(np.linalg.norm(corners - np.array([0.0, 0.0, c_z]), axis=1)))
    half_v = math.radians(camera.vfov_deg) / 2
    half_h = math.atan(math.tan(half_v) * camera.width_px / camera.height_px)
    alpha = min(half_v, half_h)
    d = VIEW_MARGIN * r / math.sin(alpha)
    s = (VIEW_MARGIN - 1.0) * r / math.cos(alpha)
    return {
        "x_m": (d, FAR_DISTANCE_RATIO * d),
        "y_m": (-s, s),
        "z_m": (-s - c_z, s - c_z),
        "yaw_rad": (float(yaw_rad[0]), float(yaw_rad[1])),
    }


def reparametrize_range(lower: float, upper: float) -> tuple[tuple[float, float], bool, float]:
    """New range of a joint with URDF limits ``[lower, upper]`` so that it starts at q >= 0.

    Returns ``((lo', hi'), flip, offset)``; URDF coordinate ``q = offset + s q'`` with
    ``s = -1`` if ``flip`` else ``+1``:

    * ``lower >= 0``: unchanged, ``((lower, upper), False, 0)``;
    * ``upper <= 0``: axis flipped, ``((-upper, -lower), True, 0)``;
    * ``lower < 0 < upper``: zero moved to ``lower``, ``((0, upper - lower), False, lower)``.
    """
    if lower >= 0:
        return (lower, upper), False, 0.0
    if upper <= 0:
        return (0.0 - upper, 0.0 - lower), True, 0.0  # 0.0 - x: no negative zero
    return (0.0, upper - lower), False, lower


def _joint_motion(urdf_type: str, axis: np.ndarray, q: float) -> np.ndarray:
    """4x4 motion of a joint's child frame at coordinate ``q`` (rad or m) along unit ``axis``."""
    import trimesh

    if MOVABLE_TYPES[urdf_type] == PRISMATIC:
        return trimesh.transformations.translation_matrix(q * axis)
    return trimesh.transformations.rotation_matrix(q, axis)


def sanitize_class_name(text: str) -> str:
    """Characters outside ``[A-Za-z0-9_.-]`` replaced by ``_``."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text)


def default_class_name(urdf_path: str | Path) -> str:
    """``<folder>-<file stem>`` of the URDF, sanitised (``7128/mobility.urdf`` -> ``7128-mobility``)."""
    p = Path(urdf_path)
    return sanitize_class_name(f"{p.parent.name}-{p.stem}" if p.parent.name else p.stem)


def check_class_name(name: str) -> str:
    """A valid, new class name (ASCII, <= 32 characters, not a built-in class)."""
    if not _NAME_OK.match(name) or len(name) > MAX_CLASS_NAME_CHARS:
        raise UserError(
            f"invalid class name {name!r}: use 1-{MAX_CLASS_NAME_CHARS} characters from A-Z a-z 0-9 _ . - "
            "(pass --class-name)"
        )
    if name in class_names():
        raise UserError(f"class name {name!r} is a built-in class; pass another --class-name")
    return name


def cache_root() -> Path:
    """Folder of processed models: ``$ARTDATA_CACHE_DIR``, else ``$XDG_CACHE_HOME/articulated_dataset``
    (default ``~/.cache/articulated_dataset``)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "articulated_dataset"


# --------------------------------------------------------------------------------------
# Parsing and checking the URDF
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Element:
    """One geometry element of a link: a resolved mesh file or a primitive."""

    origin: np.ndarray  # 4x4 in the link frame
    geometry: object  # yourdfpy Geometry
    mesh_file: str | None  # absolute path of a mesh
    source: str  # "visual" or "collision"


@dataclass
class _Parsed:
    path: Path
    robot: object  # yourdfpy Robot
    root: str
    parent_joint: dict  # child link -> joint
    elements: dict  # link name -> [_Element]
    missing: list  # (link, file) of mesh files not found


def _parse(path: Path) -> object:
    """yourdfpy Robot of ``path``, or a one-line UserError naming the file."""
    import yourdfpy
    from lxml import etree

    if not path.is_file():
        raise UserError(f"URDF file not found: {path}")
    try:
        etree.parse(str(path))  # yourdfpy silently "recovers" malformed XML: check first
    except (etree.XMLSyntaxError, OSError) as exc:
        raise UserError(f"cannot parse URDF {path}: {exc}") from None
    try:
        urdf = yourdfpy.URDF.load(str(path), build_scene_graph=False, build_collision_scene_graph=False,
                                  load_meshes=False, load_collision_meshes=False)
    except Exception as exc:  # yourdfpy raises KeyError/AttributeError/ValueError on bad elements
        raise UserError(f"cannot parse URDF {path}: {type(exc).__name__}: {exc}") from None
    for j in urdf.robot.joints:
        if j.type in ("revolute", "prismatic") and j.limit is None:
            raise UserError(f"{j.type} joint {j.name!r} of {path} has no <limit> (URDF requires one)")
    urdf.validate()
    errors = [e for e in urdf.errors if not _LENIENT_VALIDATION.search(str(e))]
    if errors:
        raise UserError(f"invalid URDF {path}: {errors[0]}")
    return urdf.robot


def _resolve_mesh(filename: str, urdf_dir: Path) -> str:
    """Absolute path of a mesh reference (relative, absolute, ``file://`` or ``package://``)."""
    import yourdfpy

    return os.path.abspath(yourdfpy.filename_handler_magic(filename, dir=str(urdf_dir)))


def _load_structure(path: Path) -> _Parsed:
    robot = _parse(path)
    links = [link.name for link in robot.links]
    if len(set(links)) != len(links):
        raise UserError(f"invalid URDF {path}: duplicate link names")
    parent_joint: dict = {}
    for j in robot.joints:
        for end in (j.parent, j.child):
            if end not in links:
                raise UserError(f"invalid URDF {path}: joint {j.name!r} refers to unknown link {end!r}")
        if j.child in parent_joint:
            raise UserError(f"invalid URDF {path}: link {j.child!r} has two parent joints")
        parent_joint[j.child] = j
    roots = [name for name in links if name not in parent_joint]
    if len(roots) != 1:
        raise UserError(f"invalid URDF {path}: expected one root link, found {roots or 'none (a cycle)'}")
    urdf_dir = path.parent
    elements: dict = {}
    missing: list = []
    for link in robot.links:
        source, items = ("visual", link.visuals) if link.visuals else ("collision", link.collisions)
        out = []
        for item in items:
            origin = np.eye(4) if item.origin is None else np.asarray(item.origin, float)
            mesh_file = None
            if item.geometry.mesh is not None:
                mesh_file = _resolve_mesh(item.geometry.mesh.filename, urdf_dir)
                if not os.path.isfile(mesh_file):
                    missing.append((link.name, mesh_file))
                    continue
            out.append(_Element(origin, item.geometry, mesh_file, source))
        elements[link.name] = out
    return _Parsed(path, robot, roots[0], parent_joint, elements, missing)


def _source_digest(parsed: _Parsed) -> str:
    """sha256 over the URDF's bytes and every mesh file it uses (path relative to the URDF)."""
    h = hashlib.sha256()
    h.update(parsed.path.read_bytes())
    files = sorted({e.mesh_file for els in parsed.elements.values() for e in els if e.mesh_file})
    for f in files:
        h.update(os.path.relpath(f, parsed.path.parent).encode("utf-8"))
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def _limits(joint) -> tuple[float, float]:
    """URDF limits (rad or m) of a revolute or prismatic joint; a missing bound is 0 (URDF default)."""
    lo, hi = joint.limit.lower, joint.limit.upper
    return float(lo or 0.0), float(hi or 0.0)


def _infer_joints(parsed: _Parsed) -> list[str]:
    """Every revolute / continuous / prismatic joint without ``<mimic>`` whose range is not empty."""
    names = []
    for j in parsed.robot.joints:
        if j.type not in MOVABLE_TYPES or j.mimic is not None:
            continue
        if j.type != "continuous" and _limits(j)[1] <= _limits(j)[0]:
            continue
        names.append(j.name)
    return names


@dataclass(frozen=True)
class _JointPlan:
    name: str
    urdf_type: str
    part: str
    q_range: tuple[float, float]
    flip: bool
    offset: float
    note: str


def _plan_joint(parsed: _Parsed, name: str) -> _JointPlan:
    from .generators._common import REVOLUTE_Q_RAD

    joints = {j.name: j for j in parsed.robot.joints}
    if name not in joints:
        raise UserError(f"URDF {parsed.path} has no joint {name!r}; its joints: {', '.join(joints) or 'none'}")
    j = joints[name]
    if j.type in MOVABLE_TYPES:
        _unit_axis(j, parsed.path)
    if j.type in UNSUPPORTED_TYPES or j.type not in MOVABLE_TYPES:
        raise UserError(
            f"joint {name!r} of {parsed.path} is {j.type}: only revolute, continuous and prismatic joints can be articulated"
        )
    if j.mimic is not None:
        raise UserError(f"joint {name!r} of {parsed.path} mimics joint {j.mimic.joint!r}; articulate that joint instead")
    if j.type == "continuous":
        return _JointPlan(name, j.type, j.child, tuple(REVOLUTE_Q_RAD), False, 0.0,
                          f"{name}: continuous, q in the revolute default [0, pi/2] rad (set it with --table)")
    lower, upper = _limits(j)
    if upper <= lower:
        raise UserError(f"joint {name!r} of {parsed.path} has an empty range [{lower}, {upper}]")
    q_range, flip, offset = reparametrize_range(lower, upper)
    unit = "m" if MOVABLE_TYPES[j.type] == PRISMATIC else "rad"
    how = "axis flipped" if flip else (f"zero moved to the lower limit {lower:g} {unit}" if offset else "as in the URDF")
    note = f"{name}: {j.type}, URDF limits [{lower:g}, {upper:g}] {unit} -> q in [{q_range[0]:g}, {q_range[1]:g}] {unit} ({how})"
    return _JointPlan(name, j.type, j.child, q_range, flip, offset, note)


# --------------------------------------------------------------------------------------
# Processed model (cache)
# --------------------------------------------------------------------------------------

def _load_mesh(path: str):
    import trimesh

    try:
        mesh = trimesh.load_mesh(path, process=False, skip_materials=True)
    except Exception as exc:  # unreadable or unsupported file: the user's
        raise UserError(f"cannot read mesh file {path}: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise UserError(f"mesh file {path} holds no triangles")
    return mesh


def _link_mesh(elements: list):
    """The link's meshes (scaled, placed) merged into one trimesh in the link frame, or None."""
    import trimesh

    parts = []
    for e in elements:
        if e.mesh_file is None:
            continue
        m = _load_mesh(e.mesh_file).copy()
        scale = e.geometry.mesh.scale
        if scale is not None:
            s = np.broadcast_to(np.asarray(scale, float), (3,))
            m.apply_transform(np.diag([s[0], s[1], s[2], 1.0]))
        m.apply_transform(e.origin)
        parts.append(m)
    if not parts:
        return None
    mesh = _thicken_if_flat(trimesh.util.concatenate(parts) if len(parts) > 1 else parts[0])
    return double_sided(mesh)


def double_sided(mesh):
    """The mesh with every triangle also present with reversed winding.

    MuJoCo's renderer culls back faces, and third-party meshes are often not consistently
    wound (or not closed): a depth sensor sees a surface from either side, so both are kept.
    """
    import trimesh

    faces = np.asarray(mesh.faces)
    return trimesh.Trimesh(np.asarray(mesh.vertices), np.concatenate([faces, faces[:, ::-1]]), process=False)


def _thicken_if_flat(mesh):
    """Give a mesh whose vertices are (nearly) coplanar a :data:`FLAT_MESH_THICKNESS_M` thickness.

    A second copy of the sheet, shifted along the plane's normal (the direction of least
    spread of the vertices), with reversed faces, so both sides are surfaces.
    """
    import trimesh

    v = np.asarray(mesh.vertices, float)
    centred = v - v.mean(axis=0)
    _, sv, vt = np.linalg.svd(centred, full_matrices=False)
    if len(v) >= 4 and sv[-1] > FLAT_MESH_THICKNESS_M * max(sv[0], 1e-12):
        return mesh
    normal = vt[-1]
    back = trimesh.Trimesh(v + FLAT_MESH_THICKNESS_M * normal, np.asarray(mesh.faces)[:, ::-1], process=False)
    return trimesh.util.concatenate([mesh, back])


#: Shortest joint axis (URDF units) accepted before normalising it.
MIN_AXIS_NORM = 1e-9


def _unit_axis(joint, path: Path) -> np.ndarray:
    """The joint's unit axis (URDF default ``1 0 0``)."""
    axis = np.array([1.0, 0.0, 0.0]) if joint.axis is None else np.asarray(joint.axis, float)
    norm = float(np.linalg.norm(axis))
    if not np.isfinite(norm) or norm < MIN_AXIS_NORM:
        raise UserError(f"joint {joint.name!r} of {path} has a zero or invalid <axis xyz>")
    return axis / norm


def _processed_robot(parsed: _Parsed, plans: list[_JointPlan], mesh_files: dict):
    """yourdfpy Robot of the processed model (meshes replaced by the per-link STL files)."""
    import yourdfpy

    by_name = {p.name: p for p in plans}
    links = []
    for i, link in enumerate(parsed.robot.links):
        collisions = []
        if link.name in mesh_files:
            collisions.append(yourdfpy.Collision(
                name=f"g{i}_mesh", origin=None, geometry=yourdfpy.Geometry(mesh=yourdfpy.Mesh(filename=mesh_files[link.name]))))
        for k, e in enumerate(parsed.elements[link.name]):
            if e.mesh_file is None:
                collisions.append(yourdfpy.Collision(name=f"g{i}_{k}", origin=e.origin, geometry=e.geometry))
        inertial = yourdfpy.Inertial(origin=np.eye(4), mass=LINK_MASS_KG, inertia=np.eye(3) * LINK_INERTIA_KG_M2)
        links.append(yourdfpy.Link(name=link.name, inertial=inertial, visuals=[], collisions=collisions))
    joints = []
    for j in parsed.robot.joints:
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, float)
        plan = by_name.get(j.name)
        if plan is None:
            joints.append(yourdfpy.Joint(name=j.name, type="fixed", parent=j.parent, child=j.child, origin=origin))
            continue
        axis = _unit_axis(j, parsed.path)
        if plan.offset:
            origin = origin @ _joint_motion(j.type, axis, plan.offset)
        if plan.flip:
            axis = -axis
        limit = yourdfpy.Limit(effort=LIMIT_EFFORT, velocity=LIMIT_VELOCITY, lower=plan.q_range[0], upper=plan.q_range[1])
        jtype = "revolute" if MOVABLE_TYPES[j.type] == REVOLUTE else "prismatic"
        joints.append(yourdfpy.Joint(name=j.name, type=jtype, parent=j.parent, child=j.child, origin=origin,
                                     axis=axis, limit=limit))
    return yourdfpy.Robot(name=sanitize_class_name(parsed.robot.name or "object"), links=links, joints=joints)


def _write_processed(parsed: _Parsed, plans: list[_JointPlan], folder: Path, final: Path) -> None:
    """Write the per-link STL files and the processed URDF into ``folder`` (paths point to ``final``)."""
    import yourdfpy
    from lxml import etree

    mesh_files = {}
    for i, link in enumerate(parsed.robot.links):
        mesh = _link_mesh(parsed.elements[link.name])
        if mesh is not None:
            name = f"link_{i:04d}.stl"
            mesh.export(str(folder / name), file_type="stl")
            mesh_files[link.name] = str(final / name)
    robot = _processed_robot(parsed, plans, mesh_files)
    urdf = yourdfpy.URDF(robot=robot, build_scene_graph=False, load_meshes=False,
                         filename_handler=yourdfpy.filename_handler_null)
    tree = urdf.write_xml()
    mj = etree.SubElement(tree.getroot(), "mujoco")
    # Absolute mesh paths as written (MuJoCo strips folders from URDF mesh paths by default).
    etree.SubElement(mj, "compiler", attrib={"strippath": "false", "fusestatic": "false"})
    (folder / PROCESSED_URDF_NAME).write_bytes(etree.tostring(tree, xml_declaration=True, encoding="utf-8", pretty_print=True))


def _ensure_processed(parsed: _Parsed, plans: list[_JointPlan], key: str) -> Path:
    """The processed URDF in the cache (built atomically: a temporary folder renamed)."""
    root = cache_root() / "urdf"
    final = root / key
    target = final / PROCESSED_URDF_NAME
    if target.is_file():
        return target
    try:
        root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key}-", dir=root))
    except OSError as exc:
        raise UserError(f"cannot write the model cache {root}: {exc.strerror or exc} (set {CACHE_ENV})") from None
    try:
        _write_processed(parsed, plans, tmp, final)
        try:
            os.rename(tmp, final)
        except OSError:
            if not target.is_file():  # not a concurrent build of the same key: a real failure
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return target


# --------------------------------------------------------------------------------------
# Definition -> ObjectClass
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class UrdfObject:
    """A third-party object ready for generation.

    ``definition`` goes into ``GenerationConfig(third_party=...)``; ``obj_class`` is its
    (unregistered) :class:`ObjectClass`; ``notes`` say what was inferred, one line each.
    """

    definition: dict
    obj_class: ObjectClass
    notes: tuple[str, ...]

    def summary(self) -> list[str]:
        c = self.obj_class
        lines = [f"{c.name}: {self.definition['urdf']} (root link {c.base_link!r}, {c.n_joints} joint(s))"]
        lines += [f"  {n}" for n in self.notes]
        for k, (lo, hi) in c.table.pose.items():
            lines.append(f"  pose {k} in [{lo:.3f}, {hi:.3f}]")
        return lines


def _geom_points(model, data, g: int) -> np.ndarray:
    """World points bounding geom ``g``: its mesh vertices, or its local bounding-box corners."""
    import mujoco

    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
        m = model.geom_dataid[g]
        local = model.mesh_vert[model.mesh_vertadr[m]: model.mesh_vertadr[m] + model.mesh_vertnum[m]].astype(float)
    else:
        c, h = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        local = c + np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
    return data.geom_xpos[g] + local @ data.geom_xmat[g].reshape(3, 3).T


def _build_class(definition: dict) -> tuple[ObjectClass, tuple[str, ...]]:
    import mujoco

    from .generators._common import YAW_RAD
    from .labels import MASK_BODY, MASK_FIRST_PART, model_info, read_object_labels
    from .scene import build_model

    path = Path(definition["urdf"])
    parsed = _load_structure(path)
    notes = []
    if parsed.missing:
        if not definition["skip_missing_meshes"]:
            link, f = parsed.missing[0]
            raise UserError(f"mesh file not found: {f} (link {link!r} of {path}); fix the path or pass --skip-missing-meshes")
        for link, f in parsed.missing:
            notes.append(f"skipped missing mesh {f} (link {link!r})")
    digest = _source_digest(parsed)
    if definition.get("sha256") and definition["sha256"] != digest:
        raise UserError(
            f"{path} or its meshes differ from the files the generation was started with "
            "(changed since, or a different copy on this node)"
        )
    plans = [_plan_joint(parsed, name) for name in definition["joints"]]
    if not plans:
        raise UserError(f"{path}: no joint to articulate (no revolute, continuous or prismatic joint with a range)")
    if len({p.name for p in plans}) != len(plans):
        raise UserError(f"{path}: a joint is listed twice in --joints")
    notes += [p.note for p in plans]
    key = hashlib.sha256(json.dumps([IMPORT_VERSION, digest, definition["joints"], definition["skip_missing_meshes"]])
                         .encode()).hexdigest()[:24]
    template = _ensure_processed(parsed, plans, key)

    camera = CameraConfig(**definition["camera"])
    provisional = SamplingTable(
        geometry={k: (1.0, 1.0) for k in ("depth_m", "width_m", "height_m")},
        pose={"x_m": (1, 1), "y_m": (0, 0), "z_m": (0, 0), "yaw_rad": (0, 0)},
        q=tuple(p.q_range for p in plans),
    )
    obj_class = ObjectClass(
        name=definition["class_name"], template=str(template), table=provisional,
        joints=tuple(JointSpec(p.name, MOVABLE_TYPES[p.urdf_type], p.part) for p in plans),
        base_link=parsed.root, sided=False, description=f"third-party URDF {path}",
    )
    # Compile once at the identity pose (object frame = camera frame): checks that MuJoCo
    # reads the processed model and measures the object for the default pose table.
    model = build_model(template.read_text(), {"x_m": 0.0, "y_m": 0.0, "z_m": 0.0, "yaw_rad": 0.0}, camera, parsed.root)
    data = mujoco.MjData(model)
    info = model_info(model, obj_class)
    for j, p in enumerate(plans):
        if not np.any(info.geom_part == MASK_FIRST_PART + j):
            raise UserError(f"joint {p.name!r} of {path} moves no geometry (link {p.part!r} and its children have none)")
    if not np.any(info.geom_part == MASK_BODY):
        raise UserError(f"{path}: the links that do not move (root {parsed.root!r} and its fixed children) have no geometry")
    try:
        read_object_labels(model, data, info, obj_class)  # leaves data at q = 0
    except ValueError as exc:
        raise UserError(f"{path}: labels undefined at q = 0 ({exc}); a revolute part's centre lies on its axis?") from None
    obj_geoms = np.nonzero(info.geom_part >= MASK_BODY)[0]
    pts = np.concatenate([_geom_points(model, data, g) for g in obj_geoms])
    body = np.concatenate([_geom_points(model, data, g) for g in np.nonzero(info.geom_part == MASK_BODY)[0]])
    size = np.maximum(body.max(axis=0) - body.min(axis=0), MIN_GEOMETRY_M)
    table = SamplingTable(
        geometry={"depth_m": (size[0], size[0]), "width_m": (size[1], size[1]), "height_m": (size[2], size[2])},
        pose=view_pose_ranges(pts.min(axis=0), pts.max(axis=0), camera, YAW_RAD),
        q=tuple(p.q_range for p in plans),
    )
    return replace(obj_class, table=table), tuple(notes)


@functools.lru_cache(maxsize=16)
def _class_for_key(key: str) -> tuple[ObjectClass, tuple[str, ...]]:
    return _build_class(json.loads(key))


def class_from_definition(definition: dict) -> ObjectClass:
    """The :class:`ObjectClass` of a third-party definition (built once per process)."""
    return _class_for_key(json.dumps(definition, sort_keys=True))[0]


def import_urdf(
    urdf_path: str | Path,
    *,
    joints: list[str] | None = None,
    class_name: str | None = None,
    skip_missing_meshes: bool = False,
    camera: CameraConfig | None = None,
) -> UrdfObject:
    """Check a URDF and prepare it for generation.

    ``joints``: names of the joints to articulate, in label order (default: inferred, see
    :func:`_infer_joints`).  ``class_name``: the dataset class name (default
    :func:`default_class_name`).  ``skip_missing_meshes``: drop mesh references whose file
    does not exist instead of stopping.  ``camera``: the camera the default pose table is
    computed for.  Raises :class:`UserError` with one line naming the file on any problem.
    """
    path = Path(urdf_path).expanduser().resolve()
    parsed = _load_structure(path)
    camera = camera or CameraConfig()
    inferred = joints is None
    if inferred:
        joints = _infer_joints(parsed)
    name = check_class_name(class_name if class_name is not None else default_class_name(path))
    definition = json.loads(json.dumps({
        "urdf": str(path),
        "class_name": name,
        "joints": list(joints),
        "skip_missing_meshes": bool(skip_missing_meshes),
        "camera": camera.to_dict(),
        "sha256": None,
        "import_version": IMPORT_VERSION,
    }))
    if not parsed.missing or skip_missing_meshes:
        definition["sha256"] = _source_digest(parsed)
    obj_class, notes = _class_for_key(json.dumps(definition, sort_keys=True))
    if inferred:
        notes = (f"joints inferred: {', '.join(joints)} (choose with --joints)",) + notes
    return UrdfObject(definition, obj_class, notes)
