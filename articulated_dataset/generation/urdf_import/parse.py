"""Reading a third-party URDF as data: safe XML parsing, name and number checks, mesh paths
resolved inside the mesh root, scaling, the source digest, and the plan of each joint to
articulate (its type, range and re-parametrisation)."""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import re
import struct
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from articulated_dataset.classes.base import PRISMATIC
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.units import normalise
from articulated_dataset.generation.urdf_import.ranges import MOVABLE_TYPES, reparametrize_range

#: URDF joint types that cannot be articulated (frozen if not selected).
UNSUPPORTED_TYPES = ("floating", "planar")
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
#: Mesh formats read, by the file's suffix (trimesh parses a file by its suffix): text or plain
#: binary geometry whose size in memory follows the file's.  trimesh reads more: archives
#: (``.zip``, ``.3mf``, ``.zae``: 1.6 MB inflated to 3.3 GB), COLLADA ``.dae`` (parsed with
#: huge-tree XML, a zip archive whatever the name, textures opened with every PIL decoder),
#: 2-D drawings; convert such a mesh to one of these first.
MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb", ".gltf")
#: Largest mesh file read (bytes), and largest file a glTF mesh names as its buffer: an ASCII
#: STL of MuJoCo's 200,000 triangles per link takes about 50 MB; the geometry of a larger file
#: could not be rendered anyway.
MAX_MESH_FILE_BYTES = 64 << 20
#: yourdfpy validation messages not treated as errors: a <limit>'s effort and velocity do
#: not matter for kinematics (PartNet-Mobility omits them), and URDF defaults a missing
#: lower / upper to 0.
_LENIENT_VALIDATION = re.compile(r"'(effort|velocity|lower|upper)'")


@dataclass(frozen=True)
class _Element:
    """One geometry element of a link: a resolved mesh file or a primitive."""

    origin: np.ndarray  # 4x4 in the link frame
    geometry: object  # yourdfpy Geometry
    mesh_file: str | None  # absolute path of a mesh
    source: str  # "visual" or "collision"
    scale: float = 1.0  # --scale, applied to a mesh's vertices after its own <mesh scale>


@dataclass
class Parsed:
    """A parsed and checked URDF: the yourdfpy robot, its root link, each link's parent joint and geometry elements,
    and the mesh files not found."""
    path: Path
    robot: Any  # yourdfpy Robot
    root: str
    parent_joint: dict  # child link -> joint
    elements: dict  # link name -> [_Element]
    missing: list  # (link, file) of mesh files not found


def one_line(exc: Exception) -> str:
    """The first line of ``exc``'s message, at most 200 characters."""
    return (str(exc).splitlines() or [""])[0][:200]


@contextlib.contextmanager
def quietly():
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
        raise UserError(f"cannot parse URDF {path}: {one_line(exc)}") from None
    if tree.docinfo.doctype or tree.docinfo.internalDTD is not None:
        raise UserError(f"URDF {path} has a DOCTYPE; entity declarations are refused (a URDF needs none)")
    root = tree.getroot()
    if root.tag != "robot":
        raise UserError(f"{path} is not a URDF (root element <{str(root.tag)[:40]}>, expected <robot>)")
    if any(isinstance(e, etree._Entity) for e in root.iter()):
        raise UserError(f"URDF {path} uses entity references; refused")
    etree.cleanup_namespaces(root)
    return root


def _parse(path: Path) -> Any:
    """yourdfpy Robot of ``path`` (parsed by :func:`_safe_xml`), or a one-line UserError naming the file."""
    import yourdfpy

    root = _safe_xml(path)
    try:
        robot = yourdfpy.URDF._parse_robot(xml_element=root)
        urdf = yourdfpy.URDF(robot=robot, build_scene_graph=False, build_collision_scene_graph=False,
                             load_meshes=False, load_collision_meshes=False, mesh_dir=str(path.parent))
    except Exception as exc:  # yourdfpy raises KeyError/AttributeError/ValueError on bad elements
        raise UserError(f"cannot parse URDF {path}: {type(exc).__name__}: {one_line(exc)}") from None
    for j in urdf.robot.joints:
        if j.type in ("revolute", "prismatic") and j.limit is None:
            raise UserError(f"{j.type} joint {j.name!r} of {path} has no <limit> (URDF requires one)")
    urdf.validate()
    errors = [e for e in urdf.errors if not _LENIENT_VALIDATION.search(str(e))]
    if errors:
        raise UserError(f"invalid URDF {path}: {one_line(errors[0])}")
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
                        f"read only from the URDF's folder or the folder given with {option('mesh_root')}")
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


def load_structure(path: Path, mesh_root: Path | None = None, scale: float = 1.0) -> Parsed:
    """Parse and check ``path``; ``mesh_root``: the folder meshes must lie in (default the
    URDF's folder); ``scale``: the --scale factor (1: the file as it is)."""
    robot = _parse(path)
    if scale != 1.0:
        robot = _scaled_robot(robot, scale)
    mesh_root = path.parent if mesh_root is None else mesh_root
    links = [link.name for link in robot.links]
    if len(set(links)) != len(links):
        raise UserError(f"invalid URDF {path}: duplicate link names")
    joint_names = [j.name for j in robot.joints]
    repeated = sorted({n for n in joint_names if joint_names.count(n) > 1})
    if repeated:  # (else the default --joints, every movable joint, named one twice)
        raise UserError(f"invalid URDF {path}: duplicate joint name {str(repeated[0])[:80]!r}")
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
                check_mesh_file(mesh_file, f"link {link.name!r} of {path}")
            if scale != 1.0:
                out.append(_Element(_scaled_origin(origin, scale), _scaled_geometry(item.geometry, scale), mesh_file,
                                    source, scale))
            else:
                out.append(_Element(origin, item.geometry, mesh_file, source))
        elements[link.name] = out
    return Parsed(path, robot, roots[0], parent_joint, elements, missing)


def source_digest(parsed: Parsed) -> str:
    """sha256 over the URDF's bytes and every mesh file it uses (path relative to the URDF), and
    the buffer files a glTF mesh refers to (its geometry lives there: a changed ``.bin`` is a
    changed object for the cache key and the workers' check)."""
    h = hashlib.sha256()
    h.update(parsed.path.read_bytes())
    meshes = sorted({e.mesh_file for els in parsed.elements.values() for e in els if e.mesh_file})
    for f in meshes + sorted({buffer for mesh in meshes for buffer in gltf_buffer_files(mesh)} - set(meshes)):
        h.update(os.path.relpath(f, parsed.path.parent).encode("utf-8"))
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def check_mesh_file(mesh_file, where: str | None = None) -> None:
    """A mesh file must have one of the :data:`MESH_SUFFIXES` and at most
    :data:`MAX_MESH_FILE_BYTES`, checked before it is read (``where``: the link that uses it)."""
    path = Path(mesh_file)
    name = f"mesh file {path}" + (f" ({where})" if where else "")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise UserError(f"{name}: {path.suffix or 'no suffix'!r} is not a mesh format read here "
                        f"(use {', '.join(MESH_SUFFIXES)})")
    size = path.stat().st_size
    if size > MAX_MESH_FILE_BYTES:
        raise UserError(f"{name} has {size:,} bytes, over the {MAX_MESH_FILE_BYTES:,} read for a mesh; simplify it")


#: The glTF binary container: its 12-byte header (magic, version, length) and the header of
#: its first chunk (length, type), which holds the JSON document.
GLB_HEADER = struct.Struct("<4sII")
GLB_CHUNK_HEADER = struct.Struct("<I4s")


def gltf_document(mesh_file) -> dict | None:
    """The JSON document of a ``.gltf`` mesh, or of a ``.glb`` mesh's JSON chunk; None for another
    mesh or a document that cannot be read (trimesh then reports the file when it loads it)."""
    import json

    from articulated_dataset.format.shards import JSON_TEXT_ERRORS

    path = Path(mesh_file)
    suffix = path.suffix.lower()
    if suffix not in (".gltf", ".glb") or path.stat().st_size > MAX_MESH_FILE_BYTES:
        return None
    data = path.read_bytes()
    if suffix == ".glb":
        if len(data) < GLB_HEADER.size + GLB_CHUNK_HEADER.size or data[:4] != b"glTF":
            return None
        length, kind = GLB_CHUNK_HEADER.unpack_from(data, GLB_HEADER.size)
        start = GLB_HEADER.size + GLB_CHUNK_HEADER.size
        if kind != b"JSON":
            return None
        data = data[start : start + length]
    try:
        doc = json.loads(data)
    except JSON_TEXT_ERRORS:
        return None
    return doc if isinstance(doc, dict) else None


def check_gltf_accessors(mesh_file) -> None:
    """Every accessor of a glTF mesh must read its data from a buffer: one without a
    ``bufferView`` (compressed data an extension decodes, or zeros of its declared count) makes
    trimesh allocate whatever count the file declares (a few bytes of JSON for gigabytes)."""
    doc = gltf_document(mesh_file)
    accessors = doc.get("accessors") if doc is not None else None
    for i, a in enumerate(accessors if isinstance(accessors, list) else []):
        if not isinstance(a, dict) or not isinstance(a.get("bufferView"), int):
            raise UserError(f"cannot read mesh file {mesh_file}: its accessor {i} has no bufferView (compressed or "
                            f"placeholder data is not read; export the glTF without compression)")


def gltf_buffer_files(mesh_file) -> list:
    """The regular files that the ``buffers`` of a ``.gltf`` or ``.glb`` mesh name (relative URIs
    inside the mesh's folder; ``data:`` URIs are inside the JSON, a ``.glb``'s own buffer inside
    the file), or [] for another mesh or a JSON that cannot be read (trimesh then reports the
    file when it loads it)."""
    import stat
    from urllib.parse import unquote

    path = Path(mesh_file)
    doc = gltf_document(path)
    buffers = doc.get("buffers") if doc is not None else None
    out = []
    folder = path.parent.resolve()
    for b in buffers if isinstance(buffers, list) else []:
        uri = b.get("uri") if isinstance(b, dict) else None
        if not isinstance(uri, str) or uri.startswith("data:"):
            continue
        try:
            target = (folder / unquote(uri)).resolve()
            inside = folder in target.parents and stat.S_ISREG(os.stat(target).st_mode)
        except (OSError, ValueError, RuntimeError):
            continue
        if inside:
            out.append(str(target))
    return out


def _limits(joint) -> tuple[float, float]:
    """URDF limits (rad or m) of a revolute or prismatic joint; a missing bound is 0 (URDF default)."""
    lo, hi = joint.limit.lower, joint.limit.upper
    return float(lo or 0.0), float(hi or 0.0)


def infer_joints(parsed: Parsed) -> list[str]:
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
        hint = (f"; its continuous joints ({', '.join(free[:5])}) turn freely: articulate them with {option('joints')}"
                if free else "")
        raise UserError(f"{parsed.path}: no joint to articulate by default (no revolute or prismatic joint with a "
                        f"range){hint}")
    return names


@dataclass(frozen=True)
class JointPlan:
    """How one URDF joint becomes a dataset joint: its URDF type, moving link, range of q (rad or m, 0 = closed),
    whether the axis is flipped, the URDF coordinate of q = 0, and a note for the summary."""
    name: str
    urdf_type: str
    part: str
    q_range: tuple[float, float]
    flip: bool
    offset: float
    note: str


def plan_joint(parsed: Parsed, name: str) -> JointPlan:
    """The :class:`JointPlan` of joint ``name``: q reparametrised so that 0 is closed (:func:`reparametrize_range`);
    a continuous joint gets the revolute default range. An unknown, fixed, mimic or unsupported joint, or limits
    that are empty, infinite or implausibly large, are the user's mistake."""
    from articulated_dataset.classes.common import REVOLUTE_Q_RAD

    joints = {j.name: j for j in parsed.robot.joints}
    if name not in joints:
        raise UserError(f"URDF {parsed.path} has no joint {name!r}; its joints: {', '.join(joints) or 'none'}")
    j = joints[name]
    if j.type in MOVABLE_TYPES:
        unit_axis(j, parsed.path)
    if j.type in UNSUPPORTED_TYPES or j.type not in MOVABLE_TYPES:
        raise UserError(
            f"joint {name!r} of {parsed.path} is {j.type}: only revolute, continuous and prismatic joints can be articulated"
        )
    if j.mimic is not None:
        raise UserError(f"joint {name!r} of {parsed.path} mimics joint {j.mimic.joint!r}; articulate that joint instead")
    if j.type == "continuous":
        return JointPlan(name, j.type, j.child, tuple(REVOLUTE_Q_RAD), False, 0.0,  # type: ignore[arg-type]  # a (low, high) pair
                          f"{name}: continuous, q in the revolute default [0, pi/2] rad (set it with --table)")
    lower, upper = _limits(j)
    unit = "m" if MOVABLE_TYPES[j.type] == PRISMATIC else "rad"
    bound = MAX_PRISMATIC_LIMIT_M if unit == "m" else MAX_REVOLUTE_LIMIT_RAD
    if not (math.isfinite(lower) and math.isfinite(upper)) or max(abs(lower), abs(upper)) > bound:
        raise UserError(f"joint {name!r} of {parsed.path} has limits [{lower:g}, {upper:g}] {unit}, beyond "
                        f"+-{bound:g} {unit} (a placeholder, not a range); fix the <limit> or choose "
                        f"other {option('joints')}")
    if upper <= lower:
        raise UserError(f"joint {name!r} of {parsed.path} has an empty range [{lower}, {upper}]")
    q_range, flip, offset = reparametrize_range(lower, upper)
    if flip:
        how = f"closed at the upper limit {upper:g} {unit}: axis flipped" + (", zero moved there" if offset else "")
    else:
        how = f"closed at the lower limit: zero moved to {lower:g} {unit}" if offset else "as in the URDF"
    note = f"{name}: {j.type}, URDF limits [{lower:g}, {upper:g}] {unit} -> q in [{q_range[0]:g}, {q_range[1]:g}] {unit} ({how})"
    return JointPlan(name, j.type, j.child, q_range, flip, offset, note)


#: Shortest joint axis (URDF units) accepted before normalising it.
MIN_AXIS_NORM = 1e-9


def unit_axis(joint, path: Path) -> np.ndarray:
    """The joint's unit axis (URDF default ``1 0 0``)."""
    axis = np.array([1.0, 0.0, 0.0]) if joint.axis is None else np.asarray(joint.axis, float)
    return normalise(axis, min_norm=MIN_AXIS_NORM, what=f"{path}: <axis xyz> of joint {joint.name!r}")
