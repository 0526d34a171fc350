"""The processed model: each link's meshes merged into one double-sided STL, the joints
re-parametrised or frozen, unit inertias, written once into a content-addressed cache folder
that any process can rebuild."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from articulated_dataset.classes.base import REVOLUTE
from articulated_dataset.core.errors import UserError
from articulated_dataset.generation.urdf_import.panel import primitive_protrudes, protruding
from articulated_dataset.generation.urdf_import.parse import (
    MAX_FILE_LENGTH,
    MAX_MESH_FILE_BYTES,
    JointPlan,
    Parsed,
    check_gltf_accessors,
    check_mesh_file,
    one_line,
    unit_axis,
)
from articulated_dataset.generation.urdf_import.ranges import (
    CACHE_ENV,
    MOVABLE_TYPES,
    cache_root,
    joint_motion,
    sanitize_class_name,
)

PROCESSED_URDF_NAME = "model.urdf"
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
#: Most triangles MuJoCo's STL reader takes in one mesh file (its stl_decoder's limit).
MUJOCO_MAX_STL_FACES = 200_000


#: Most placed copies of geometry one mesh file may hold (nodes of a glTF scene that place a
#: mesh): each becomes a mesh object when the scene is flattened, so a file of tiny nodes
#: would be millions of them.  A link is one rigid part; a few hundred pieces is a lot.
MAX_MESH_INSTANCES = 10_000


def _regular_file_resolver(path: str):
    """trimesh's resolver for the files a mesh refers to (a glTF's buffers), reading only
    regular files of at most :data:`~.parse.MAX_MESH_FILE_BYTES`: its own reads any path inside
    the mesh's folder, so a FIFO named as a buffer blocked the import forever (and /dev-like
    files are no mesh data either)."""
    import stat

    from trimesh.resolvers import FilePathResolver

    class RegularFiles(FilePathResolver):
        def get(self, name: str):
            for candidate in (name.strip(), name.strip().lstrip("/"), os.path.split(name)[-1]):
                try:
                    target = self.absolute(candidate)
                    st = os.stat(target)
                except (ValueError, OSError):
                    continue
                if not stat.S_ISREG(st.st_mode):
                    raise ValueError(f"{name[:80]!r} referred to by the mesh is not a regular file")
                if st.st_size > MAX_MESH_FILE_BYTES:
                    raise ValueError(f"{name[:80]!r} referred to by the mesh has {st.st_size:,} bytes, over "
                                     f"{MAX_MESH_FILE_BYTES:,}")
                break
            return super().get(name)

    return RegularFiles(path)


def _load_mesh(path: str):
    """The mesh file ``path`` (a suffix of :data:`~.parse.MESH_SUFFIXES`, at most
    :data:`~.parse.MAX_MESH_FILE_BYTES`) as one trimesh, its scene's placed copies merged; the
    count of placed triangles is checked before they are built."""
    import trimesh

    check_mesh_file(path)
    check_gltf_accessors(path)
    try:
        # trimesh reads the files a mesh refers to (materials, buffers) only inside the
        # mesh's folder, and only regular files; materials are skipped anyway.
        scene = trimesh.load_scene(path, file_type=Path(path).suffix.lower().lstrip("."), process=False,
                                   skip_materials=True, resolver=_regular_file_resolver(path))
    except Exception as exc:  # unreadable or unsupported file: the user's
        raise UserError(f"cannot read mesh file {path}: {one_line(exc)}") from None
    placed = {name: len(nodes) for name, nodes in scene.graph.geometry_nodes.items()}  # copies of each geometry
    if sum(placed.values()) > MAX_MESH_INSTANCES:
        raise UserError(f"mesh file {path} places {sum(placed.values()):,} pieces of geometry, over "
                        f"{MAX_MESH_INSTANCES:,}; merge them")
    n_faces = sum(len(getattr(scene.geometry.get(name), "faces", ())) * n for name, n in placed.items())
    if 2 * n_faces > MUJOCO_MAX_STL_FACES:  # double-sided: the link's mesh would be refused below
        raise UserError(f"mesh file {path} has {n_faces:,} triangles, {2 * n_faces:,} once double-sided, over "
                        f"MuJoCo's {MUJOCO_MAX_STL_FACES:,} per mesh; simplify it to under "
                        f"{MUJOCO_MAX_STL_FACES // 2:,} triangles (e.g. trimesh's simplify_quadric_decimation)")
    try:
        mesh = scene.to_mesh()
    except Exception as exc:
        raise UserError(f"cannot read mesh file {path}: {one_line(exc)}") from None
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


def _processed_robot(parsed: Parsed, plans: list[JointPlan], mesh_files: dict, handle_primitives: dict):
    """yourdfpy Robot of the processed model (meshes replaced by the per-link STL files:
    ``mesh_files[link, ""]`` the link's panel, ``mesh_files[link, HANDLE_SUFFIX]`` its protrusions;
    ``handle_primitives[link]``: indices of the link's primitive elements that protrude)."""
    import yourdfpy

    from articulated_dataset.generation.labels import HANDLE_SUFFIX

    by_name = {p.name: p for p in plans}
    links = []
    for i, link in enumerate(parsed.robot.links):
        collisions = []
        for suffix in ("", HANDLE_SUFFIX):
            key = (link.name, suffix)
            if key in mesh_files:
                collisions.append(yourdfpy.Collision(
                    name=f"g{i}_mesh{suffix}", origin=None,
                    geometry=yourdfpy.Geometry(mesh=yourdfpy.Mesh(filename=mesh_files[key]))))
        for k, e in enumerate(parsed.elements[link.name]):
            if e.mesh_file is None:
                suffix = HANDLE_SUFFIX if k in handle_primitives.get(link.name, ()) else ""
                collisions.append(yourdfpy.Collision(name=f"g{i}_{k}{suffix}", origin=e.origin, geometry=e.geometry))
        inertial = yourdfpy.Inertial(origin=np.eye(4), mass=LINK_MASS_KG, inertia=np.eye(3) * LINK_INERTIA_KG_M2)
        links.append(yourdfpy.Link(name=link.name, inertial=inertial, visuals=[], collisions=collisions))
    joints = []
    for j in parsed.robot.joints:
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, float)
        plan = by_name.get(j.name)
        if plan is None:
            joints.append(yourdfpy.Joint(name=j.name, type="fixed", parent=j.parent, child=j.child, origin=origin))
            continue
        axis = unit_axis(j, parsed.path)
        if plan.offset:
            origin = origin @ joint_motion(j.type, axis, plan.offset)
        if plan.flip:
            axis = -axis
        limit = yourdfpy.Limit(effort=LIMIT_EFFORT, velocity=LIMIT_VELOCITY, lower=plan.q_range[0], upper=plan.q_range[1])
        jtype = "revolute" if MOVABLE_TYPES[j.type] == REVOLUTE else "prismatic"
        joints.append(yourdfpy.Joint(name=j.name, type=jtype, parent=j.parent, child=j.child, origin=origin,
                                     axis=axis, limit=limit))
    return yourdfpy.Robot(name=sanitize_class_name(parsed.robot.name or "object"), links=links, joints=joints)


def _moving_axes(parsed: Parsed, plans: list[JointPlan]) -> dict:
    """``{link: (axis, prismatic)}`` of each articulated link: its joint's axis in the link's
    frame (a prismatic joint's: its opening direction, after the re-parametrisation)."""
    joints = {j.name: j for j in parsed.robot.joints}
    out = {}
    for p in plans:
        axis = unit_axis(joints[p.name], parsed.path)
        out[p.part] = (-axis if p.flip else axis, MOVABLE_TYPES[p.urdf_type] != REVOLUTE)
    return out


def _primitive_mesh(element):
    """A primitive element (box, cylinder, sphere) as a trimesh in the link frame, or None."""
    import trimesh

    g = element.geometry
    if g.box is not None:
        return trimesh.creation.box(extents=np.asarray(g.box.size, float), transform=element.origin)
    if g.cylinder is not None:
        return trimesh.creation.cylinder(radius=float(g.cylinder.radius), height=float(g.cylinder.length),
                                         transform=element.origin)
    if g.sphere is not None:
        m = trimesh.creation.icosphere(radius=float(g.sphere.radius))
        m.apply_transform(element.origin)
        return m
    return None


def _split_protrusions(mesh, elements: list, axis: np.ndarray, prismatic: bool) -> tuple[dict, set]:
    """An articulated link's geometry split into its panel and its protrusions
    (:mod:`.panel`): ``({"": panel mesh or None, HANDLE_SUFFIX: protrusion mesh or None},
    indices of the primitive elements that protrude)``."""
    import trimesh

    from articulated_dataset.generation.labels import HANDLE_SUFFIX

    primitives = {k: _primitive_mesh(e) for k, e in enumerate(elements) if e.mesh_file is None}
    primitives = {k: m for k, m in primitives.items() if m is not None}
    pieces = ([mesh] if mesh is not None else []) + list(primitives.values())
    if not pieces:
        return {"": mesh}, set()
    masks = protruding(pieces, axis, prismatic)
    handles = {k for k, m in zip(primitives, masks[len(masks) - len(primitives):]) if primitive_protrudes(m, primitives[k])}
    if mesh is None or not masks[0].any() or masks[0].all():
        return {"": mesh}, handles
    faces = np.asarray(mesh.faces)

    def part(keep):
        piece = trimesh.Trimesh(np.asarray(mesh.vertices), faces[keep], process=False)
        piece.remove_unreferenced_vertices()
        return _thicken_if_flat(piece)

    return {"": part(~masks[0]), HANDLE_SUFFIX: part(masks[0])}, handles


def _write_processed(parsed: Parsed, plans: list[JointPlan], folder: Path, final: Path) -> None:
    """Write the per-link STL files and the processed URDF into ``folder`` (paths point to ``final``)."""
    import yourdfpy
    from lxml import etree

    moving = _moving_axes(parsed, plans)
    mesh_files, handle_primitives = {}, {}
    for i, link in enumerate(parsed.robot.links):
        mesh = _link_mesh(parsed.elements[link.name], link.name, parsed.path)
        pieces = {"": mesh}
        if link.name in moving:
            pieces, handle_primitives[link.name] = _split_protrusions(mesh, parsed.elements[link.name], *moving[link.name])
        for suffix, piece in pieces.items():
            if piece is not None:
                name = f"link_{i:04d}{suffix}.stl"
                piece.export(str(folder / name), file_type="stl")
                mesh_files[link.name, suffix] = str(final / name)
    robot = _processed_robot(parsed, plans, mesh_files, handle_primitives)
    urdf = yourdfpy.URDF(robot=robot, build_scene_graph=False, load_meshes=False,
                         filename_handler=yourdfpy.filename_handler_null)
    tree = urdf.write_xml()
    mj = etree.SubElement(tree.getroot(), "mujoco")
    # Absolute mesh paths as written (MuJoCo strips folders from URDF mesh paths by default).
    etree.SubElement(mj, "compiler", attrib={"strippath": "false", "fusestatic": "false"})
    (folder / PROCESSED_URDF_NAME).write_bytes(etree.tostring(tree, xml_declaration=True, encoding="utf-8", pretty_print=True))


def ensure_processed(parsed: Parsed, plans: list[JointPlan], key: str) -> Path:
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
