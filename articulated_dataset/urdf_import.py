"""Third-party articulated objects from URDF files (e.g. PartNet-Mobility).

``artdata generate --urdf FILE`` renders a user-supplied URDF with the dataset's camera,
pose and configuration sampling and label definitions.  The URDF is turned into a
*processed* URDF that the pipeline treats like any class template:

* the file is data, never code: it is parsed as plain XML (lxml with entity expansion,
  network access and DTDs off, no XInclude; a DOCTYPE is refused) and read into yourdfpy's
  structures; it never goes through xacro (only our own ``*.xacro`` templates do), and link
  and joint names must be plain identifiers (:data:`URDF_NAME_CHARS`);
* mesh paths are resolved with yourdfpy relative to the URDF (``package://`` prefixes are
  tried relative to the URDF's folder and its parents) and must lie inside the *mesh root*:
  the URDF's folder, or the folder the user names (``--mesh-root``);
* each link's geometry is its ``<visual>`` elements (its ``<collision>`` elements if it
  has no visual).  Meshes are loaded with trimesh, scaled, placed by their ``<origin>`` and
  merged into one binary STL per link (MuJoCo reads STL; a flat mesh gets a
  :data:`FLAT_MESH_THICKNESS_M` thickness because MuJoCo needs a 3-D convex hull), with
  every triangle made double-sided (MuJoCo culls back faces; see :func:`double_sided`);
  primitive boxes, cylinders and spheres are kept as they are;
* the joints to articulate (``--joints``, default: every revolute and prismatic joint with
  a finite, non-empty range, in file order: the parts that open; ``continuous`` joints such
  as knobs are articulated only when named) keep their type; every other joint is frozen
  (``fixed``) at its URDF zero, the pose the meshes are modelled in;
* ``--scale s`` multiplies every length (mesh vertices, primitive sizes, joint and element
  origins, prismatic limits) by ``s``, for files in other units (PartNet-Mobility's are
  normalised); labels are read from the scaled model, so they follow;
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

import contextlib
import functools
import hashlib
import json
import logging
import math
import os
import re
import shutil
import tempfile
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .camera import CameraConfig
from .errors import UserError
from .classes import PRISMATIC, REVOLUTE, JointSpec, ObjectClass
from .format import MAX_CLASS_NAME_CHARS, is_class_name
from .tables import SamplingTable
from .units import normalise

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
#: Link and joint names: plain identifiers (ROS-style names also use ``/`` and ``:``).  A
#: name holding ``$``, braces, quotes or control characters is refused (never evaluated).
URDF_NAME_CHARS = "A-Z a-z 0-9 _ . - / : +"
_URDF_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_./:+-]*")
#: Longest link or joint name accepted.
MAX_URDF_NAME_CHARS = 128
#: Largest |limit| of a revolute joint (rad): one full turn, plus the rounding of files that
#: write 2 pi as 6.2832.  Beyond that the value is a placeholder (1e30, "unlimited").
LIMIT_ROUNDING_RAD = 1e-3
MAX_REVOLUTE_LIMIT_RAD = 2 * math.pi + LIMIT_ROUNDING_RAD
#: Largest |limit| of a prismatic joint (m, after --scale): no articulated object opens
#: farther; a larger value is a placeholder or a unit mistake.
MAX_PRISMATIC_LIMIT_M = 10.0
#: Largest magnitude of a length in the file (origins, sizes, mesh scales and vertices, in
#: the file's units): beyond any object in metres or millimetres.  Larger values are
#: placeholders and break the numerics (SVDs that never converge, MuJoCo inertia failures).
MAX_FILE_LENGTH = 1e6
#: Most triangles MuJoCo's STL reader takes in one mesh file (its stl_decoder's limit).
MUJOCO_MAX_STL_FACES = 200_000
#: yourdfpy validation messages not treated as errors: a <limit>'s effort and velocity do
#: not matter for kinematics (PartNet-Mobility omits them), and URDF defaults a missing
#: lower / upper to 0.
_LENIENT_VALIDATION = re.compile(r"'(effort|velocity|lower|upper)'")
#: Keys of a third-party definition (``GenerationConfig.third_party``); ``scale`` and
#: ``mesh_root`` are present only when not the default (so default imports keep their bytes).
_DEFINITION_KEYS = {"urdf", "class_name", "joints", "skip_missing_meshes", "camera", "sha256", "import_version"}
_OPTIONAL_DEFINITION_KEYS = {"scale", "mesh_root"}


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
    c_z, r = _yaw_sphere(box_lo, box_hi)
    alpha = _half_fov(camera)
    d = VIEW_MARGIN * r / math.sin(alpha)
    s = (VIEW_MARGIN - 1.0) * r / math.cos(alpha)
    return {
        "x_m": (d, FAR_DISTANCE_RATIO * d),
        "y_m": (-s, s),
        "z_m": (-s - c_z, s - c_z),
        "yaw_rad": (float(yaw_rad[0]), float(yaw_rad[1])),
    }


def _yaw_sphere(box_lo, box_hi) -> tuple[float, float]:
    """``(c_z, r)``: mid-height (m) and radius (m) of the sphere centred on the root z axis
    at the box's mid-height that holds the box (see :func:`view_pose_ranges`)."""
    lo, hi = np.asarray(box_lo, float), np.asarray(box_hi, float)
    c_z = 0.5 * (lo[2] + hi[2])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return float(c_z), float(np.max(np.linalg.norm(corners - np.array([0.0, 0.0, c_z]), axis=1)))


def _half_fov(camera: CameraConfig) -> float:
    """The smaller half field of view (rad), vertical or horizontal."""
    half_v = math.radians(camera.vfov_deg) / 2
    return min(half_v, math.atan(math.tan(half_v) * camera.width_px / camera.height_px))


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
    """A valid class name (:func:`articulated_dataset.format.is_class_name`); the registry
    refuses a built-in's name when the class is registered (:func:`articulated_dataset.registry.register`)."""
    if not is_class_name(name):
        raise UserError(
            f"invalid class name {str(name)[:80]!r}: use 1-{MAX_CLASS_NAME_CHARS} characters from A-Z a-z 0-9 _ . -, "
            "not starting with . or - (pass --class-name)"
        )
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
    scale: float = 1.0  # --scale, applied to a mesh's vertices after its own <mesh scale>


@dataclass
class _Parsed:
    path: Path
    robot: object  # yourdfpy Robot
    root: str
    parent_joint: dict  # child link -> joint
    elements: dict  # link name -> [_Element]
    missing: list  # (link, file) of mesh files not found


def _one_line(exc: Exception) -> str:
    return (str(exc).splitlines() or [""])[0][:200]


@contextlib.contextmanager
def _quietly():
    """Hostile numbers (inf, nan) make numpy and trimesh warn, and yourdfpy logs each mesh it
    cannot find: the checks below report such input in one line, so keep the rest quiet."""
    ylog = logging.getLogger("yourdfpy")
    level = ylog.level
    ylog.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            yield
    finally:
        ylog.setLevel(level)


def _safe_xml(path: Path):
    """The root element of ``path`` parsed as plain XML: no entity expansion, no DTD, no
    network, no XInclude (lxml only includes when asked), comments and processing
    instructions dropped.  A DOCTYPE (the only way to declare entities) is refused."""
    from lxml import etree

    if not path.is_file():
        raise UserError(f"URDF file not found: {path}")
    parser = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, dtd_validation=False,
                             huge_tree=False, remove_blank_text=True, remove_comments=True, remove_pis=True)
    try:
        tree = etree.parse(str(path), parser)
    except (etree.XMLSyntaxError, OSError, ValueError) as exc:
        raise UserError(f"cannot parse URDF {path}: {_one_line(exc)}") from None
    if tree.docinfo.doctype or tree.docinfo.internalDTD is not None:
        raise UserError(f"URDF {path} has a DOCTYPE; entity declarations are refused (a URDF needs none)")
    root = tree.getroot()
    if root.tag != "robot":
        raise UserError(f"{path} is not a URDF (root element <{str(root.tag)[:40]}>, expected <robot>)")
    if any(isinstance(e, etree._Entity) for e in root.iter()):
        raise UserError(f"URDF {path} uses entity references; refused")
    etree.cleanup_namespaces(root)
    return root


def _parse(path: Path) -> object:
    """yourdfpy Robot of ``path`` (parsed by :func:`_safe_xml`), or a one-line UserError naming the file."""
    import yourdfpy

    root = _safe_xml(path)
    try:
        robot = yourdfpy.URDF._parse_robot(xml_element=root)
        urdf = yourdfpy.URDF(robot=robot, build_scene_graph=False, build_collision_scene_graph=False,
                             load_meshes=False, load_collision_meshes=False, mesh_dir=str(path.parent))
    except Exception as exc:  # yourdfpy raises KeyError/AttributeError/ValueError on bad elements
        raise UserError(f"cannot parse URDF {path}: {type(exc).__name__}: {_one_line(exc)}") from None
    for j in urdf.robot.joints:
        if j.type in ("revolute", "prismatic") and j.limit is None:
            raise UserError(f"{j.type} joint {j.name!r} of {path} has no <limit> (URDF requires one)")
    urdf.validate()
    errors = [e for e in urdf.errors if not _LENIENT_VALIDATION.search(str(e))]
    if errors:
        raise UserError(f"invalid URDF {path}: {_one_line(errors[0])}")
    _check_names(urdf.robot, path)
    _check_numbers(urdf.robot, path)
    return urdf.robot


def _check_names(robot, path: Path) -> None:
    """Every link and joint name is a plain identifier (see :data:`URDF_NAME_CHARS`)."""
    for kind, items in (("link", robot.links), ("joint", robot.joints)):
        for item in items:
            name = item.name
            if not isinstance(name, str) or len(name) > MAX_URDF_NAME_CHARS or not _URDF_NAME_RE.fullmatch(name):
                raise UserError(f"URDF {path}: invalid {kind} name {str(name)[:60]!r} (use 1-{MAX_URDF_NAME_CHARS} "
                                f"characters from {URDF_NAME_CHARS}; names are identifiers, never evaluated)")


def _finite(values, what: str, path: Path) -> np.ndarray:
    """``values`` as floats, each finite and at most :data:`MAX_FILE_LENGTH` in magnitude."""
    a = np.asarray(values, float)
    bad = ~np.isfinite(a) | (np.abs(a) > MAX_FILE_LENGTH)
    if np.any(bad):
        raise UserError(f"URDF {path}: {what} holds {a[bad].ravel()[0]:g}: lengths must be finite and within "
                        f"+-{MAX_FILE_LENGTH:g}")
    return a


def _check_numbers(robot, path: Path) -> None:
    """Origins finite; mesh scales finite and non-zero; primitive sizes finite and positive."""
    for j in robot.joints:
        if j.origin is not None:
            _finite(j.origin, f"origin of joint {j.name!r}", path)
        if j.axis is not None and (np.size(j.axis) != 3 or not np.all(np.isfinite(np.asarray(j.axis, float)))):
            raise UserError(f"URDF {path}: <axis xyz> of joint {j.name!r} must be 3 finite numbers")
    for link in robot.links:
        for kind, items in (("visual", link.visuals), ("collision", link.collisions)):
            for item in items:
                where = f"a {kind} of link {link.name!r}"
                if item.origin is not None:
                    _finite(item.origin, f"origin of {where}", path)
                g = item.geometry
                if g is None:
                    continue
                if g.mesh is not None and g.mesh.scale is not None:
                    sc = _finite(g.mesh.scale, f"mesh scale of {where}", path)
                    if sc.size not in (1, 3):
                        raise UserError(f"URDF {path}: mesh scale of {where} must be 3 numbers")
                    if np.any(sc == 0):
                        raise UserError(f"URDF {path}: mesh scale of {where} has a zero factor")
                sizes = []
                if g.box is not None:
                    sizes.append(("box size", g.box.size))
                if g.cylinder is not None:
                    sizes += [("cylinder radius", g.cylinder.radius), ("cylinder length", g.cylinder.length)]
                if g.sphere is not None:
                    sizes.append(("sphere radius", g.sphere.radius))
                for what, v in sizes:
                    a = _finite(0.0 if v is None else v, f"{what} of {where}", path)
                    if np.any(a <= 0):
                        raise UserError(f"URDF {path}: {what} of {where} must be positive, "
                                        f"got {np.array2string(a.ravel(), separator=' ')}")


def _resolve_mesh(filename: str, urdf_dir: Path, mesh_root: Path, link: str, path: Path) -> str:
    """Absolute path of a mesh reference (relative, absolute, ``file://`` or ``package://``),
    which must lie inside ``mesh_root`` (symbolic links resolved)."""
    import yourdfpy

    if not isinstance(filename, str) or not filename or "\0" in filename:
        raise UserError(f"URDF {path}: invalid mesh file name {str(filename)[:80]!r} (link {link!r})")
    resolved = yourdfpy.filename_handler_magic(filename, dir=str(urdf_dir))
    if not os.path.isfile(resolved):  # not found: report (and check) it relative to the URDF
        resolved = os.path.join(urdf_dir, yourdfpy.filename_handler_ignore_directive(filename))
    resolved = os.path.abspath(resolved)
    try:
        inside = Path(resolved).resolve().is_relative_to(mesh_root.resolve())
    except (OSError, RuntimeError):  # a symbolic-link loop
        inside = False
    if not inside:
        raise UserError(f"mesh file {filename[:120]!r} (link {link!r} of {path}) lies outside {mesh_root}: meshes are "
                        "read only from the URDF's folder or the folder given with --mesh-root")
    return resolved


def _scaled_robot(robot, scale: float):
    """``robot`` with joint origins and prismatic limits multiplied by ``scale`` (lengths)."""
    joints = []
    for j in robot.joints:
        origin = None if j.origin is None else _scaled_origin(j.origin, scale)
        limit = j.limit
        if limit is not None and j.type == "prismatic":
            limit = replace(limit, lower=None if limit.lower is None else limit.lower * scale,
                            upper=None if limit.upper is None else limit.upper * scale)
        joints.append(replace(j, origin=origin, limit=limit))
    return replace(robot, joints=joints)


def _scaled_origin(origin, scale: float) -> np.ndarray:
    out = np.array(origin, float)
    out[:3, 3] *= scale
    return out


def _scaled_geometry(geometry, scale: float):
    """A primitive's sizes multiplied by ``scale`` (meshes are scaled when loaded)."""
    import yourdfpy

    if geometry.box is not None:
        return replace(geometry, box=yourdfpy.Box(size=np.asarray(geometry.box.size, float) * scale))
    if geometry.cylinder is not None:
        return replace(geometry, cylinder=yourdfpy.Cylinder(radius=geometry.cylinder.radius * scale,
                                                            length=geometry.cylinder.length * scale))
    if geometry.sphere is not None:
        return replace(geometry, sphere=yourdfpy.Sphere(radius=geometry.sphere.radius * scale))
    return geometry


def _load_structure(path: Path, mesh_root: Path | None = None, scale: float = 1.0) -> _Parsed:
    """Parse and check ``path``; ``mesh_root``: the folder meshes must lie in (default the
    URDF's folder); ``scale``: the --scale factor (1: the file as it is)."""
    robot = _parse(path)
    if scale != 1.0:
        robot = _scaled_robot(robot, scale)
    mesh_root = path.parent if mesh_root is None else mesh_root
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
            if item.geometry is None:
                raise UserError(f"invalid URDF {path}: a {source} of link {link.name!r} has no <geometry>")
            origin = np.eye(4) if item.origin is None else np.asarray(item.origin, float)
            mesh_file = None
            if item.geometry.mesh is not None:
                mesh_file = _resolve_mesh(item.geometry.mesh.filename, urdf_dir, mesh_root, link.name, path)
                if not os.path.isfile(mesh_file):
                    missing.append((link.name, mesh_file))
                    continue
            if scale != 1.0:
                out.append(_Element(_scaled_origin(origin, scale), _scaled_geometry(item.geometry, scale), mesh_file,
                                    source, scale))
            else:
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
    """The parts that open: every revolute / prismatic joint without ``<mimic>`` whose range
    is not empty.  ``continuous`` joints (knobs, turntables) are used only when named."""
    names = []
    for j in parsed.robot.joints:
        if j.type not in ("revolute", "prismatic") or j.mimic is not None:
            continue
        if _limits(j)[1] <= _limits(j)[0]:
            continue
        names.append(j.name)
    if not names:
        free = [j.name for j in parsed.robot.joints if j.type == "continuous" and j.mimic is None]
        hint = (f"; its continuous joints ({', '.join(free[:5])}) turn freely: articulate them with --joints"
                if free else "")
        raise UserError(f"{parsed.path}: no joint to articulate by default (no revolute or prismatic joint with a "
                        f"range){hint}")
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
    from .generators.common import REVOLUTE_Q_RAD

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
    unit = "m" if MOVABLE_TYPES[j.type] == PRISMATIC else "rad"
    bound = MAX_PRISMATIC_LIMIT_M if unit == "m" else MAX_REVOLUTE_LIMIT_RAD
    if not (math.isfinite(lower) and math.isfinite(upper)) or max(abs(lower), abs(upper)) > bound:
        raise UserError(f"joint {name!r} of {parsed.path} has limits [{lower:g}, {upper:g}] {unit}, beyond "
                        f"+-{bound:g} {unit} (a placeholder, not a range); fix the <limit> or choose other --joints")
    if upper <= lower:
        raise UserError(f"joint {name!r} of {parsed.path} has an empty range [{lower}, {upper}]")
    q_range, flip, offset = reparametrize_range(lower, upper)
    how = "axis flipped" if flip else (f"zero moved to the lower limit {lower:g} {unit}" if offset else "as in the URDF")
    note = f"{name}: {j.type}, URDF limits [{lower:g}, {upper:g}] {unit} -> q in [{q_range[0]:g}, {q_range[1]:g}] {unit} ({how})"
    return _JointPlan(name, j.type, j.child, q_range, flip, offset, note)


# --------------------------------------------------------------------------------------
# Processed model (cache)
# --------------------------------------------------------------------------------------

def _load_mesh(path: str):
    import trimesh

    try:
        # trimesh reads the files a mesh refers to (materials, buffers) only inside the
        # mesh's folder; materials are skipped anyway.
        mesh = trimesh.load_mesh(path, process=False, skip_materials=True)
    except Exception as exc:  # unreadable or unsupported file: the user's
        raise UserError(f"cannot read mesh file {path}: {_one_line(exc)}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise UserError(f"mesh file {path} holds no triangles")
    if not np.all(np.isfinite(mesh.vertices)) or np.any(np.abs(mesh.vertices) > MAX_FILE_LENGTH):
        raise UserError(f"mesh file {path} has vertices that are not finite numbers or beyond +-{MAX_FILE_LENGTH:g}")
    return mesh


def _link_mesh(elements: list, link: str = "", path: Path | None = None):
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
        if e.scale != 1.0:
            m.apply_scale(e.scale)
        m.apply_transform(e.origin)
        parts.append(m)
    if not parts:
        return None
    n_faces = sum(len(m.faces) for m in parts)
    mesh = double_sided(_thicken_if_flat(trimesh.util.concatenate(parts) if len(parts) > 1 else parts[0]))
    if len(mesh.faces) > MUJOCO_MAX_STL_FACES:
        raise UserError(f"link {link!r} of {path}: its meshes have {n_faces} triangles, {len(mesh.faces)} once "
                        f"double-sided, over MuJoCo's {MUJOCO_MAX_STL_FACES} per mesh; simplify them to under "
                        f"{MUJOCO_MAX_STL_FACES // 2} triangles (e.g. trimesh's simplify_quadric_decimation)")
    return mesh


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
    return normalise(axis, min_norm=MIN_AXIS_NORM, what=f"{path}: <axis xyz> of joint {joint.name!r}")


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
        mesh = _link_mesh(parsed.elements[link.name], link.name, parsed.path)
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

    from .generators.common import YAW_RAD
    from .labels import MASK_BODY, MASK_FIRST_PART, model_info, read_object_labels
    from .scene import build_model

    definition = _check_definition(definition)
    path = Path(definition["urdf"])
    scale = float(definition.get("scale", 1.0))
    mesh_root = Path(definition["mesh_root"]) if definition.get("mesh_root") else None
    parsed = _load_structure(path, mesh_root, scale)
    notes = [f"lengths scaled by {scale:g} (--scale)"] if scale != 1.0 else []
    if parsed.missing:
        if not definition["skip_missing_meshes"]:
            link, f = parsed.missing[0]
            raise UserError(f"mesh file not found: {f} (link {link!r} of {path}); fix the path or pass --skip-missing-meshes")
        for link, f in parsed.missing:
            notes.append(f"skipped missing mesh {f} (link {link!r})")
    digest = _source_digest(parsed)
    if definition["sha256"] != digest:
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
    recipe = [IMPORT_VERSION, digest, definition["joints"], definition["skip_missing_meshes"]]
    if scale != 1.0:  # only then: default imports keep their cache key
        recipe.append(scale)
    key = hashlib.sha256(json.dumps(recipe).encode()).hexdigest()[:24]
    template = _ensure_processed(parsed, plans, key)

    try:
        camera = CameraConfig(**definition["camera"])
    except (TypeError, ValueError) as exc:
        raise UserError(f"corrupt third-party URDF definition: camera ({_one_line(exc)})") from None
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
    try:
        with warnings.catch_warnings():  # a model MuJoCo warns about here would warn on every object
            warnings.simplefilter("error")
            model = build_model(template.read_text(), {"x_m": 0.0, "y_m": 0.0, "z_m": 0.0, "yaw_rad": 0.0}, camera,
                                parsed.root)
    except (ValueError, Warning) as exc:  # MuJoCo's compiler refuses the model (degenerate mesh, ...)
        raise UserError(f"{path}: MuJoCo cannot compile the object ({_one_line(exc)})") from None
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
    _check_fits_camera(pts.min(axis=0), pts.max(axis=0), camera, path)
    table = SamplingTable(
        geometry={"depth_m": (size[0], size[0]), "width_m": (size[1], size[1]), "height_m": (size[2], size[2])},
        pose=view_pose_ranges(pts.min(axis=0), pts.max(axis=0), camera, YAW_RAD),
        q=tuple(p.q_range for p in plans),
    )
    return replace(obj_class, table=table), tuple(notes)


def _check_fits_camera(box_lo, box_hi, camera: CameraConfig, path: Path) -> None:
    """The default pose table's nearest and farthest views must lie within the depth range
    (:data:`articulated_dataset.scene.NEAR_CLIP_M` .. ``FAR_CLIP_M``); else say --scale."""
    from .scene import FAR_CLIP_M, NEAR_CLIP_M

    _, r = _yaw_sphere(box_lo, box_hi)
    d = VIEW_MARGIN * r / math.sin(_half_fov(camera))
    if not math.isfinite(r) or FAR_DISTANCE_RATIO * d + r > FAR_CLIP_M:
        raise UserError(f"{path}: the object is {2 * r:.3g} m across, too large to view within the camera's "
                        f"{FAR_CLIP_M:g} m depth range; check its units and pass --scale (e.g. --scale 0.001 for mm)")
    if d - r < NEAR_CLIP_M:
        raise UserError(f"{path}: the object is {2 * r:.3g} m across, too small to view beyond the camera's "
                        f"{NEAR_CLIP_M:g} m near plane; check its units and pass --scale")


def _check_definition(definition) -> dict:
    """A third-party definition (possibly read back from a manifest) with the expected keys
    and types; a bad one is a one-line UserError."""
    ok = (isinstance(definition, dict) and _DEFINITION_KEYS <= set(definition)
          and set(definition) <= _DEFINITION_KEYS | _OPTIONAL_DEFINITION_KEYS)
    if ok:
        d = definition
        scale = d.get("scale", 1.0)
        ok = (isinstance(d["urdf"], str) and os.path.isabs(d["urdf"]) and "\0" not in d["urdf"]
              and is_class_name(d["class_name"])
              and isinstance(d["joints"], list) and all(isinstance(j, str) for j in d["joints"])
              and isinstance(d["skip_missing_meshes"], bool) and isinstance(d["camera"], dict)
              and (d["sha256"] is None or (isinstance(d["sha256"], str) and re.fullmatch(r"[0-9a-f]{64}", d["sha256"])))
              and isinstance(scale, (int, float)) and not isinstance(scale, bool) and math.isfinite(scale) and scale > 0
              and (d.get("mesh_root") is None or (isinstance(d["mesh_root"], str) and os.path.isabs(d["mesh_root"])
                                                  and "\0" not in d["mesh_root"])))
    if not ok:
        raise UserError("corrupt third-party URDF definition (the 'third_party' entry of the generation config): "
                        "expected the keys and types that 'artdata generate --urdf' writes")
    return definition


@functools.lru_cache(maxsize=16)
def _class_for_key(key: str) -> tuple[ObjectClass, tuple[str, ...]]:
    return _build_class(json.loads(key))


def class_from_definition(definition: dict) -> ObjectClass:
    """The :class:`ObjectClass` of a third-party definition (built once per process)."""
    with _quietly():
        return _class_for_key(json.dumps(definition, sort_keys=True))[0]


def import_urdf(
    urdf_path: str | Path,
    *,
    joints: list[str] | None = None,
    class_name: str | None = None,
    skip_missing_meshes: bool = False,
    camera: CameraConfig | None = None,
    scale: float = 1.0,
    mesh_root: str | Path | None = None,
) -> UrdfObject:
    """Check a URDF and prepare it for generation.

    ``joints``: names of the joints to articulate, in label order (default: inferred, see
    :func:`_infer_joints`).  ``class_name``: the dataset class name (default
    :func:`default_class_name`).  ``skip_missing_meshes``: drop mesh references whose file
    does not exist instead of stopping.  ``camera``: the camera the default pose table is
    computed for.  ``scale``: multiplies every length of the file (mesh vertices, primitive
    sizes, origins, prismatic limits; e.g. 0.001 for a file in millimetres).  ``mesh_root``:
    the folder meshes may be read from (default: the URDF's folder).  Raises
    :class:`UserError` with one line naming the file on any problem.
    """
    with _quietly():
        return _import_urdf(urdf_path, joints, class_name, skip_missing_meshes, camera, scale, mesh_root)


def _import_urdf(urdf_path, joints, class_name, skip_missing_meshes, camera, scale, mesh_root) -> UrdfObject:
    path = Path(urdf_path).expanduser().resolve()
    try:
        scale = float(scale)
    except (TypeError, ValueError):
        raise UserError(f"--scale must be a number, got {scale!r}") from None
    if not (math.isfinite(scale) and scale > 0):
        raise UserError(f"--scale must be a positive finite number, got {scale:g}")
    if mesh_root is not None:
        mesh_root = Path(mesh_root).expanduser().resolve()
        if not mesh_root.is_dir():
            raise UserError(f"--mesh-root {mesh_root} is not a folder")
    parsed = _load_structure(path, mesh_root, scale)
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
    if scale != 1.0:  # only when given: a default import's definition (and bytes) stay as they were
        definition["scale"] = scale
    if mesh_root is not None:
        definition["mesh_root"] = str(mesh_root)
    if not parsed.missing or skip_missing_meshes:
        definition["sha256"] = _source_digest(parsed)
    obj_class, notes = _class_for_key(json.dumps(definition, sort_keys=True))
    if inferred:
        notes = (f"joints inferred: {', '.join(joints)} (choose with --joints)",) + notes
    return UrdfObject(definition, obj_class, notes)
