"""From a definition to an :class:`~articulated_dataset.classes.base.ObjectClass`: the class's
joints, geometry and sampling table measured on the processed model, the checks that it fits
the camera, and :func:`import_urdf`, the entry point."""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import re
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from articulated_dataset.classes.base import JointSpec, ObjectClass
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.tables import SamplingTable
from articulated_dataset.format import is_class_name
from articulated_dataset.generation.urdf_import.parse import (
    infer_joints,
    load_structure,
    one_line,
    plan_joint,
    quietly,
    source_digest,
)
from articulated_dataset.generation.urdf_import.process import ensure_processed
from articulated_dataset.generation.urdf_import.ranges import (
    FAR_DISTANCE_RATIO,
    MOVABLE_TYPES,
    VIEW_MARGIN,
    check_class_name,
    default_class_name,
    half_fov,
    view_pose_ranges,
    yaw_sphere,
)

#: Version of the processed-model recipe; part of the cache key (bump when it changes).
IMPORT_VERSION = 3
#: ``--scale auto:CLASS``: the prefix before the built-in class whose standard sizes the object takes.
AUTO_SCALE_PREFIX = "auto:"
#: Aspect-ratio mismatches (log ratio) closer than this are ties in :func:`auto_scale`.
AUTO_SCALE_TIE = 1e-9
#: Smallest size (m) of a geometry-table entry (the table needs positive ranges).
MIN_GEOMETRY_M = 1e-3
#: Keys of a third-party definition (``GenerationConfig.third_party``); ``scale`` and
#: ``mesh_root`` are present only when not the default (so default imports keep their bytes).
_DEFINITION_KEYS = {"urdf", "class_name", "joints", "skip_missing_meshes", "camera", "sha256", "import_version"}
_OPTIONAL_DEFINITION_KEYS = {"scale", "mesh_root"}


class SourceMismatchError(UserError):
    """The URDF or its meshes are not the files a definition records (their sha256 differs)."""


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
        """Lines describing the import: the URDF, root link and joint count, the inference notes, and each pose
        range."""
        c = self.obj_class
        lines = [f"{c.name}: {self.definition['urdf']} (root link {c.base_link!r}, {c.n_joints} joint(s))"]
        lines += [f"  {n}" for n in self.notes]
        for k, (lo, hi) in c.table.pose.items():
            lines.append(f"  pose {k} in [{lo:.3f}, {hi:.3f}]")
        return lines


def _geom_points(model, data, g: int | np.integer) -> np.ndarray:
    """World points bounding geom ``g``: its mesh vertices, or its local bounding-box corners."""
    import mujoco

    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
        m = model.geom_dataid[g]
        local = model.mesh_vert[model.mesh_vertadr[m]: model.mesh_vertadr[m] + model.mesh_vertnum[m]].astype(float)
    else:
        c, h = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        local = c + np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
    return data.geom_xpos[g] + local @ data.geom_xmat[g].reshape(3, 3).T


def _build_class(definition: dict, fit_camera: bool = True) -> tuple[ObjectClass, tuple[str, ...]]:
    """The class of a definition and the import's notes; ``fit_camera`` False skips the check that
    the object fits the camera's depth range (to measure an object before ``--scale auto:CLASS``)."""
    import mujoco

    from articulated_dataset.classes.common import YAW_RAD
    from articulated_dataset.format.schema import MASK_BODY, MASK_FIRST_PART
    from articulated_dataset.generation.compiled import compile_object
    from articulated_dataset.generation.labels import read_object_labels

    definition = _check_definition(definition)
    path = Path(definition["urdf"])
    scale = float(definition.get("scale", 1.0))
    mesh_root = Path(definition["mesh_root"]) if definition.get("mesh_root") else None
    parsed = load_structure(path, mesh_root, scale)
    notes = [f"lengths scaled by {scale:g} (--scale)"] if scale != 1.0 else []
    if parsed.missing:
        if not definition["skip_missing_meshes"]:
            link, f = parsed.missing[0]
            raise UserError(f"mesh file not found: {f} (link {link!r} of {path}); fix the path or pass "
                            f"{option('skip_missing_meshes')}")
        for link, f in parsed.missing:
            notes.append(f"skipped missing mesh {f} (link {link!r})")
    digest = source_digest(parsed)
    if definition["sha256"] != digest:
        raise SourceMismatchError(
            f"{path} or its meshes differ from the files the generation was started with "
            "(changed since, or a different copy on this node)"
        )
    plans = [plan_joint(parsed, name) for name in definition["joints"]]
    if not plans:
        raise UserError(f"{path}: no joint to articulate (no revolute, continuous or prismatic joint with a range)")
    if len({p.name for p in plans}) != len(plans):
        raise UserError(f"{path}: a joint is listed twice in {option('joints')}")
    notes += [p.note for p in plans]
    recipe = [IMPORT_VERSION, digest, definition["joints"], definition["skip_missing_meshes"]]
    if scale != 1.0:  # only then: default imports keep their cache key
        recipe.append(scale)
    key = hashlib.sha256(json.dumps(recipe).encode()).hexdigest()[:24]
    template = ensure_processed(parsed, plans, key)

    try:
        camera = CameraConfig(**definition["camera"])
    except (TypeError, ValueError) as exc:
        raise UserError(f"corrupt third-party URDF definition: camera ({one_line(exc)})") from None
    provisional = SamplingTable(
        geometry={k: (1.0, 1.0) for k in ("depth_m", "width_m", "height_m")},
        pose={"x_m": (1, 1), "y_m": (0, 0), "z_m": (0, 0), "yaw_rad": (0, 0)},
        q=tuple(p.q_range for p in plans),
    )
    obj_class = ObjectClass(
        name=definition["class_name"], template=str(template), table=provisional,
        joints=tuple(JointSpec(p.name, MOVABLE_TYPES[p.urdf_type], p.part) for p in plans),
        base_link=parsed.root, sided=True, description=f"third-party URDF {path}",
    )
    # Compile once at the identity pose (object frame = camera frame): checks that MuJoCo
    # reads the processed model and measures the object for the default pose table.
    try:
        with warnings.catch_warnings():  # a model MuJoCo warns about here would warn on every object
            warnings.simplefilter("error")
            obj = compile_object(obj_class, template.read_text(), {"x_m": 0.0, "y_m": 0.0, "z_m": 0.0, "yaw_rad": 0.0},
                                 camera)
    except (ValueError, Warning) as exc:  # MuJoCo's compiler refuses the model (degenerate mesh, ...)
        raise UserError(f"{path}: MuJoCo cannot compile the object ({one_line(exc)})") from None
    model, info = obj.model, obj.info
    data = mujoco.MjData(model)
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
    if fit_camera:
        _check_fits_camera(pts.min(axis=0), pts.max(axis=0), camera, path)
    table = SamplingTable(
        geometry={"depth_m": (size[0], size[0]), "width_m": (size[1], size[1]), "height_m": (size[2], size[2])},
        pose=view_pose_ranges(pts.min(axis=0), pts.max(axis=0), camera, YAW_RAD),
        q=tuple(p.q_range for p in plans),
    )
    return replace(obj_class, table=table), tuple(notes)


def _check_fits_camera(box_lo, box_hi, camera: CameraConfig, path: Path) -> None:
    """The default pose table's nearest and farthest views must lie within the depth range
    (:data:`articulated_dataset.generation.mujoco_scene.NEAR_CLIP_M` .. ``FAR_CLIP_M``); else say --scale."""
    from articulated_dataset.generation.mujoco_scene import FAR_CLIP_M, NEAR_CLIP_M

    _, r = yaw_sphere(box_lo, box_hi)
    d = VIEW_MARGIN * r / math.sin(half_fov(camera))
    if not math.isfinite(r) or FAR_DISTANCE_RATIO * d + r > FAR_CLIP_M:
        raise UserError(f"{path}: the object is {2 * r:.3g} m across, too large to view within the camera's "
                        f"{FAR_CLIP_M:g} m depth range; check its units and pass {option('scale')} "
                        f"(e.g. {option('scale')} 0.001 for mm)")
    if d - r < NEAR_CLIP_M:
        raise UserError(f"{path}: the object is {2 * r:.3g} m across, too small to view beyond the camera's "
                        f"{NEAR_CLIP_M:g} m near plane; check its units and pass {option('scale')}")


def _check_definition(definition) -> dict:
    """A third-party definition (possibly read back from a manifest) with the expected keys
    and types; a bad one is a one-line UserError."""
    ok: object = (isinstance(definition, dict) and _DEFINITION_KEYS <= set(definition)
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
                        f"expected the keys and types that 'artdata generate {option('urdf_path')}' writes")
    return definition


@functools.lru_cache(maxsize=16)
def _class_for_key(key: str) -> tuple[ObjectClass, tuple[str, ...]]:
    return _build_class(json.loads(key))


def class_from_definition(definition: dict) -> ObjectClass:
    """The :class:`ObjectClass` of a third-party definition (built once per process)."""
    with quietly():
        return _class_for_key(json.dumps(definition, sort_keys=True))[0]


def auto_scale_class(scale) -> ObjectClass | None:
    """The built-in class of ``--scale auto:CLASS`` (None for a number); it must have a realistic
    table (its standard sizes)."""
    if not (isinstance(scale, str) and scale.strip().lower().startswith(AUTO_SCALE_PREFIX)):
        return None
    from articulated_dataset.classes.registry import class_names, get_class

    name = scale.strip()[len(AUTO_SCALE_PREFIX):]
    if name not in class_names():
        raise UserError(f"{option('scale')} {AUTO_SCALE_PREFIX}CLASS names a built-in class "
                        f"({', '.join(class_names())}), got {name[:40]!r}")
    obj_class = get_class(name)
    if obj_class.realistic_table is None or obj_class.realistic_table.shape is None:
        raise UserError(f"{option('scale')} {AUTO_SCALE_PREFIX}{name}: class {name!r} has no standard sizes "
                        "(realistic table)")
    return obj_class


def auto_scale(width_m: float, height_m: float, like: ObjectClass) -> tuple[float, tuple[str, ...]]:
    """The scale of ``--scale auto:CLASS`` for a body ``width_m`` x ``height_m`` (m, at scale 1),
    and one note saying what it chose.

    Among the standard (width, height) pairs of the class's realistic table (each component's
    ``sizes_m``), the pair whose aspect ratio ``H / W`` is nearest the body's (in log ratio;
    ties: the component listed first, then the smaller size); the scale makes the body's front
    area ``w h`` that pair's, ``s = sqrt(W H / (w h))``, keeping the object's proportions.
    Deterministic: the same file and class give the same scale.
    """
    aspect = math.log(height_m / width_m)
    best = None
    for c in like.realistic_table.shape.components:  # type: ignore[union-attr]  # auto_scale_class checked both
        for W in sorted(c.sizes_m["width_m"]):
            for H in sorted(c.sizes_m["height_m"]):
                miss = abs(math.log(H / W) - aspect)
                if best is None or miss < best[0] - AUTO_SCALE_TIE:
                    best = (miss, c.name, W, H)
    _, component, W, H = best  # type: ignore[misc]  # a realistic table has a size class
    s = float(f"{math.sqrt(W * H / (width_m * height_m)):.6g}")
    note = (f"--scale auto:{like.name}: body {width_m:.3g} x {height_m:.3g} (width x height) scaled by {s:g} to "
            f"{width_m * s:.3f} x {height_m * s:.3f} m, the {like.name} size class {component!r} "
            f"({W:.3f} x {H:.3f} m has the nearest proportions)")
    return s, (note,)


def import_urdf(
    urdf_path: str | Path,
    *,
    joints: list[str] | None = None,
    class_name: str | None = None,
    skip_missing_meshes: bool = False,
    camera: CameraConfig | None = None,
    scale: float | str = 1.0,
    mesh_root: str | Path | None = None,
) -> UrdfObject:
    """Check a URDF and prepare it for generation.

    ``joints``: names of the joints to articulate, in label order (default: inferred, see
    :func:`infer_joints`).  ``class_name``: the dataset class name (default
    :func:`default_class_name`).  ``skip_missing_meshes``: drop mesh references whose file
    does not exist instead of stopping.  ``camera``: the camera the default pose table is
    computed for.  ``scale``: multiplies every length of the file (mesh vertices, primitive
    sizes, origins, prismatic limits; e.g. 0.001 for a file in millimetres), or
    ``"auto:CLASS"``: the scale that gives the body a standard size of the built-in class
    ``CLASS`` (:func:`auto_scale`; recorded in the definition as the number).  ``mesh_root``:
    the folder meshes may be read from (default: the URDF's folder).  Raises
    :class:`UserError` with one line naming the file on any problem.
    """
    with quietly():
        return _import_urdf(urdf_path, joints, class_name, skip_missing_meshes, camera, scale, mesh_root)


def _import_urdf(urdf_path, joints, class_name, skip_missing_meshes, camera, scale, mesh_root) -> UrdfObject:
    path = Path(urdf_path).expanduser().resolve()
    like = auto_scale_class(scale)
    if like is None:
        try:
            scale = float(scale)
        except (TypeError, ValueError):
            raise UserError(f"{option('scale')} must be a number or {AUTO_SCALE_PREFIX}CLASS, "
                            f"got {str(scale)[:80]!r}") from None
        if not (math.isfinite(scale) and scale > 0):
            raise UserError(f"{option('scale')} must be a positive finite number, got {scale:g}")
    else:
        scale = 1.0
    if mesh_root is not None:
        mesh_root = Path(mesh_root).expanduser().resolve()
        if not mesh_root.is_dir():
            raise UserError(f"{option('mesh_root')} {mesh_root} is not a folder")
    parsed = load_structure(path, mesh_root, scale)
    camera = camera or CameraConfig()
    inferred = joints is None
    if inferred:
        joints = infer_joints(parsed)
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
        definition["sha256"] = source_digest(parsed)
    auto_note: tuple[str, ...] = ()
    if like is not None:
        size = _build_class(definition, fit_camera=False)[0].table.geometry
        scale, auto_note = auto_scale(size["width_m"][0], size["height_m"][0], like)
        if scale != 1.0:  # the digest is of the files, whatever the scale
            definition["scale"] = scale
    obj_class, notes = _class_for_key(json.dumps(definition, sort_keys=True))
    notes = auto_note + notes
    if inferred:
        notes = (f"joints inferred: {', '.join(joints)} (choose with --joints)",) + notes
    return UrdfObject(definition, obj_class, notes)
