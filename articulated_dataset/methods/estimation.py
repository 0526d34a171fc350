"""One depth image in, the object's articulation out: ``articulated_dataset.estimate`` and ``artdata estimate``.

:func:`estimate` runs a dense model (the shipped one for the class, or a checkpoint) on one
depth image with its intrinsics and returns an :class:`Estimate`: for every joint the axis
origin (m) and unit direction in the camera frame (x forward, y left, z up), the
configuration q (rad or m), the part offset, the object geometry, and the uncertainty (the
mixture's per-column standard deviations and its components).  Images of any size and
intrinsics are resampled onto the model's camera as ``artdata ingest`` does
(:func:`articulated_dataset.ingest.capture.ingest_capture`); the estimate is in the original
camera's frame (resampling changes intrinsics only).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.inputs import (  # noqa: F401  (re-exported)
    MAX_UNMASKED_VALID_FRACTION,
    check_split_has_depth,
    valid_depth_images,
)
from articulated_dataset.methods.protocol import get_method

log = logging.getLogger(__name__)

#: Depths (m) the models were trained on lie within this range; valid medians outside it
#: usually mean wrong units (millimetres stored as metres, or the reverse).
PLAUSIBLE_MEDIAN_DEPTH_M = (0.1, 10.0)
#: Fewest object pixels (at the model resolution) an estimate is attempted with.
MIN_OBJECT_PIXELS = 20
#: Fewest pixels on each side of a depth image an estimate is attempted from (the network's input
#: resolution is 4 times its output's, whose smallest useful size is a few pixels).
MIN_IMAGE_SIDE_PX = 8


@dataclass
class Estimate:
    """The estimate of one image (camera frame, metres / radians)."""

    class_name: str
    joint_types: list[str]
    axis_origin_m: np.ndarray  # (J, 3)
    axis_direction: np.ndarray  # (J, 3) unit
    axis_pose: np.ndarray  # (J, 7) origin + quaternion (w, x, y, z) of the axis frame
    q: np.ndarray  # (J,) rad (revolute) or m (prismatic)
    part_offset_m: np.ndarray  # (J, 3) part centre in the axis frame
    geometry: np.ndarray  # (4,) depth, width, height (m), chirality probability
    std: dict = field(default_factory=dict)  # column name -> standard deviation of the heaviest component
    mixture_weights: np.ndarray | None = None  # (M,)
    mixture_means: np.ndarray | None = None  # (M, D)
    mixture_scales: np.ndarray | None = None  # (M, D)
    mixture_layout: list[str] = field(default_factory=list)
    model: str = ""
    #: weight of the mixture's last component, the outlier component (broad, centred on the
    #: estimate: docs/dense.md, "Uncertainty"); 0 where the model has none
    outlier_weight: float = 0.0
    #: the image borders the object's pixels reach (of "top", "bottom", "left", "right"): there the
    #: object continues out of view, and what lies beyond (a door's mid-height, where its hinge's
    #: origin is) is inferred, not measured (docs/dense.md, "Renders that show the whole object")
    cut_off: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-ready: lists of floats, one entry per joint."""
        joints = []
        for j, jt in enumerate(self.joint_types):
            joints.append({
                "type": jt,
                "axis_origin_m": self.axis_origin_m[j].tolist(),
                "axis_direction": self.axis_direction[j].tolist(),
                "axis_quaternion_wxyz": self.axis_pose[j, 3:].tolist(),
                ("q_rad" if jt != "prismatic" else "q_m"): float(self.q[j]),
                "part_offset_m": self.part_offset_m[j].tolist(),
                "std": {k.split(".", 1)[1]: v for k, v in self.std.items() if k.startswith(f"j{j}.")},
            })
        g = self.geometry
        return {
            "class": self.class_name, "model": self.model, "frame": "camera (x forward, y left, z up), metres",
            "joints": joints,
            "geometry": {"depth_m": float(g[0]), "width_m": float(g[1]), "height_m": float(g[2]), "chirality": float(g[3]),
                         "std": {k.split(".", 1)[1]: v for k, v in self.std.items() if k.startswith("geometry.")}},
            "mixture": {"weights": (self.mixture_weights.tolist() if self.mixture_weights is not None else []),
                        "n_components": 0 if self.mixture_weights is None else int(len(self.mixture_weights)),
                        "outlier_weight": float(self.outlier_weight)},
            "cut_off": list(self.cut_off),
        }

    def summary(self) -> str:
        """Human-readable lines."""
        lines = [f"{self.class_name} ({self.model}), camera frame: x forward, y left, z up"]
        for j, jt in enumerate(self.joint_types):
            o, d = self.axis_origin_m[j], self.axis_direction[j]
            so = [self.std.get(f"j{j}.origin.{c}", float("nan")) for c in "xyz"]
            unit = "m" if jt == "prismatic" else "deg"
            qv = self.q[j] if jt == "prismatic" else np.degrees(self.q[j])
            qs = self.std.get(f"j{j}.q", float("nan"))
            qs = qs if jt == "prismatic" else np.degrees(qs)
            lines.append(f"joint {j} ({jt}): axis origin ({o[0]:.3f}, {o[1]:.3f}, {o[2]:.3f}) m "
                         f"+/- ({so[0]:.3f}, {so[1]:.3f}, {so[2]:.3f}), direction ({d[0]:.3f}, {d[1]:.3f}, {d[2]:.3f}), "
                         f"q {qv:.3f} +/- {qs:.3f} {unit}")
        g = self.geometry
        lines.append(f"geometry: depth {g[0]:.3f} m, width {g[1]:.3f} m, height {g[2]:.3f} m, chirality {g[3]:.2f}")
        if self.mixture_weights is not None and len(self.mixture_weights) > 1:
            modes = self.mixture_weights[:-1] if self.outlier_weight > 0 else self.mixture_weights
            line = "mixture weights: " + ", ".join(f"{v:.2f}" for v in np.sort(modes)[::-1] if v > 1e-3)
            if self.outlier_weight > 0:
                line += f" (modes); outlier component {self.outlier_weight:.4f}"
            lines.append(line)
        if self.cut_off:
            lines.append(f"the object reaches the image's {' and '.join(self.cut_off)} border"
                         f"{'s' if len(self.cut_off) > 1 else ''}: what lies beyond is inferred, not measured "
                         f"(a view that shows the whole object gives a more accurate estimate)")
        return "\n".join(lines)


_MODEL_CACHE: dict = {}


def _load(model: str, class_name: str, precision: str = "float32"):
    from articulated_dataset.methods.dense.checkpoint import build_inference_model, load_dense_checkpoint
    from articulated_dataset.methods.shipped import resolve_model

    ref = resolve_model(model, class_name)
    if not get_method(ref.kind).single_image:
        raise UserError(f"{option('model')} {model}: single-image estimates use a dense model (the shipped 'dense' or "
                        f"a 'artdata train {option('model_kind')} dense' "
                        "checkpoint); run MDN models with 'artdata predict'")
    key = (str(ref.path), ref.path.stat().st_mtime_ns, precision)
    if key not in _MODEL_CACHE:
        ckpt = load_dense_checkpoint(ref.path)
        _MODEL_CACHE[key] = (ckpt, build_inference_model(ckpt, precision), ref.name)
    return _MODEL_CACHE[key]


def check_depth(depth_m: np.ndarray, mask: np.ndarray | None, where: str = "depth") -> None:
    """One-line errors for images no model can use (no pixels, wrong units, a scene without a mask)."""
    d = np.asarray(depth_m)
    if d.ndim != 2:
        raise UserError(f"{where}: expected a 2-D depth image, got shape {d.shape}")
    if min(d.shape) < MIN_IMAGE_SIDE_PX:
        raise UserError(f"{where}: a {d.shape[1]}x{d.shape[0]} image is too small to estimate from "
                        f"(at least {MIN_IMAGE_SIDE_PX} pixels on each side)")
    valid = np.isfinite(d) & (d > 0)
    if mask is not None:
        if mask.shape != d.shape:
            raise UserError(f"{where}: mask shape {mask.shape} differs from the depth's {d.shape}")
        if not mask.any():
            raise UserError(f"{where}: the mask marks no object pixel")
        valid &= mask
    if not valid.any():
        raise UserError(f"{where}: no valid depth pixel" + (" inside the mask" if mask is not None else ""))
    med = float(np.median(d[valid]))
    lo, hi = PLAUSIBLE_MEDIAN_DEPTH_M
    if med > hi:
        raise UserError(f"{where}: median depth {med:g} m is implausible; are the values millimetres? (give metres)")
    if med < lo:
        raise UserError(f"{where}: median depth {med:g} m is implausible; are the values in other units? (give metres)")
    from articulated_dataset.ingest.readers import MAX_PLAUSIBLE_DEPTH_M  # the file readers' bound

    top = float(d[valid].max())
    if top > MAX_PLAUSIBLE_DEPTH_M:  # as the file readers refuse it: one far pixel moved the estimate to infinity
        raise UserError(f"{where}: depth up to {top:g} m is not plausible for a depth sensor "
                        f"(at most {MAX_PLAUSIBLE_DEPTH_M:g} m); give metres, and mask out what is not the object")
    if mask is None and valid.mean() > MAX_UNMASKED_VALID_FRACTION:
        raise UserError(f"{where}: {100 * valid.mean():.0f}% of the pixels have depth (a scene, not an isolated object); "
                        f"prompt the object with {option('mask')}, {option('point')} or {option('box')}")


def _detached(value):
    """A torch tensor as a numpy array: detached from autograd (a tensor that requires grad refuses
    ``numpy()``) and copied off its device; anything else unchanged.  torch is not imported for it."""
    if type(value).__module__.split(".")[0] == "torch" and callable(getattr(value, "detach", None)):
        return value.detach().cpu().numpy()
    return value


def _real_array(value, what: str, kinds: str = "fiu") -> np.ndarray:
    """``value`` as a numpy array of real numbers (floating point or integer); booleans, complex
    numbers, strings, objects and ragged lists are a :class:`UserError` (never converted: a
    boolean image read as 1 m, a complex one without its imaginary part, would be a wrong answer).
    ``kinds``: the numpy dtype kinds accepted (``"bfiu"`` for a mask, which may be boolean)."""
    try:
        a = np.asarray(_detached(value))
    except (TypeError, ValueError, RuntimeError) as exc:
        raise UserError(f"{what} must be an array of numbers ({str(exc).splitlines()[0][:80]})") from None
    if a.dtype.kind not in kinds:
        raise UserError(f"{what} must be an array of {'booleans or ' if 'b' in kinds else ''}real numbers, "
                        f"got dtype {a.dtype}")
    return a


def estimate(depth_m: np.ndarray, K: np.ndarray, class_name: str, mask: np.ndarray | None = None,
             model: str = "dense", mirror: bool = True, precision: str = "float32", *,
             point: tuple[int, int] | None = None, box: tuple[int, int, int, int] | None = None) -> Estimate:
    """Estimate the articulation of a ``class_name`` object in one depth image.

    ``depth_m``: (H, W) z-depth in metres (0 or NaN = no return); ``K``: 3x3 intrinsics of that
    image (OpenCV convention, pixel centres at integers); ``mask``: optional (H, W) boolean object
    mask (pixels outside it are ignored).  Instead of a mask, ``point`` (u, v: a pixel on the
    object, column and row) or ``box`` (x0, y0, x1, y1: the pixels around it, inclusive) prompts
    the object: its pixels are segmented from the depth (:mod:`~articulated_dataset.methods.prompts`,
    docs/robot_view.md) and used as a mask is; at most one of the three.  Without any, an image
    with returns on at most :data:`~articulated_dataset.methods.inputs.MAX_UNMASKED_VALID_FRACTION`
    of its pixels shows an isolated object, read from every pixel with depth; in one with more (a
    scene) the object is found apart from the scene's large planes, or refused in one line
    (:func:`~articulated_dataset.methods.prompts.find_object`).  ``model``: ``"dense"`` (shipped weights),
    ``"dense-kinect2"`` (shipped weights trained for a real sensor's noisy depth) or a dense
    checkpoint path.  ``mirror=False`` skips the refinement's mirror image where the model uses
    it (cabinet, two-door cabinet, drawer: faster, a 4-6% higher position error).
    ``precision``: the network's arithmetic, ``"float32"`` or ``"bfloat16"`` (docs/dense.md,
    "Precision").  Bad input
    raises :class:`~articulated_dataset.core.errors.UserError`.
    """
    return _estimate(depth_m, K, class_name, mask, model, mirror, precision, point=point, box=box)


def one_prompt(*, mask=None, point=None, box=None):
    """The :class:`~articulated_dataset.methods.prompts.Prompt` of ``point`` or ``box`` (None for a
    mask or nothing); two of the three at once, or a malformed one, is a one-line :class:`UserError`."""
    from articulated_dataset.methods.prompts import Prompt

    given = [name for name, value in (("mask", mask), ("point", point), ("box", box)) if value is not None]
    if len(given) > 1:
        raise UserError(f"give one prompt of the object: {' or '.join(option(n) for n in given)}, not both")
    if point is not None:
        return Prompt("point", point_px=_detached(point))
    if box is not None:
        return Prompt("box", box_px=_detached(box))
    return None


def _estimate(depth_m, K, class_name: str, mask, model: str, mirror: bool, precision: str, *, where: str = "depth",
              before_model: Callable[[], object] | None = None, point=None, box=None) -> Estimate:
    """:func:`estimate`, its depth named ``where`` in error messages (a file's path), with
    ``before_model`` run once the inputs are checked and before the model is loaded."""
    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.core.camera import CameraConfig
    from articulated_dataset.core.errors import TORCH_INSTALL, import_optional
    from articulated_dataset.core.images.intrinsics import check_intrinsics, pinhole_matrix
    from articulated_dataset.core.images.resample import crop_intrinsics, mask_fraction_inside, resample_depth

    obj_class = get_class(class_name)
    depth = np.nan_to_num(_real_array(depth_m, "depth").astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    m = None if mask is None else _real_array(mask, "mask", "bfiu")
    if m is not None and m.dtype.kind == "f" and not np.isfinite(m).all():
        raise UserError("mask holds NaN or infinite values")
    m = None if m is None else m.astype(bool)
    prompt = one_prompt(mask=m, point=point, box=box)
    scene_in_view = bool((depth > 0).mean() > MAX_UNMASKED_VALID_FRACTION)
    if prompt is None and m is None and scene_in_view:  # no prompt in a scene: the object is found in the depth
        from articulated_dataset.methods.prompts import Prompt

        prompt = Prompt("none")
    if prompt is not None:  # the image's own checks first; the scene rule applies to the segmented pixels
        check_depth(depth, np.ones(depth.shape, bool), where)
        prompt.check_image(depth.shape)
    else:
        check_depth(depth, m, where)
    K = pinhole_matrix(_real_array(K, "intrinsics"), "intrinsics")
    check_intrinsics(K, (depth.shape[1], depth.shape[0]), "intrinsics")
    if prompt is not None:
        from articulated_dataset.methods.prompts import class_extent_m, segment_from_prompt

        m = segment_from_prompt(depth, K, prompt, max_extent_m=class_extent_m(obj_class.name))
        check_depth(depth, m, where)
    if before_model is not None:
        before_model()
    # once the inputs are checked: a wrong file fails before torch's import; no torch is one line
    torch = import_optional("torch", "the dense model (estimate)", TORCH_INSTALL)
    from articulated_dataset.methods.dense.mirror import with_mirror
    from articulated_dataset.methods.dense.predict import check_precision, modes_to_arrays, refined_batch

    check_precision(precision)

    ckpt, net, name = _load(model, obj_class.name, precision)
    cfg = net.config
    if m is not None:
        depth = np.where(m, depth, 0.0)
    obj_mask = (depth > 0).astype(np.uint8)
    cut_off = image_borders_reached(obj_mask > 0)
    size = (cfg.width_px, cfg.height_px)
    K_dst = CameraConfig(cfg.width_px, cfg.height_px).K
    if mask_fraction_inside(obj_mask > 0, K, K_dst, size) < 1.0:
        # the object does not fit the training camera: zoom onto it as 'ingest --fit crop' does
        K_dst = crop_intrinsics(K, obj_mask > 0, size)
    depth_r, _ = resample_depth(depth, obj_mask, K, K_dst, size, "nearest")
    if int((depth_r > 0).sum()) < MIN_OBJECT_PIXELS:
        raise UserError(f"only {int((depth_r > 0).sum())} object pixels remain on the model's {cfg.width_px}x{cfg.height_px} "
                        f"camera (need {MIN_OBJECT_PIXELS}); is the object in view and are the intrinsics right?")
    joint_types = list(obj_class.joint_types)
    modes = refined_batch(net, torch.from_numpy(depth_r.astype(np.float32))[None],
                          torch.from_numpy(K_dst.astype(np.float32))[None], joint_types=joint_types,
                          refinement=with_mirror(ckpt.get("refinement"), mirror))
    arrays = modes_to_arrays(modes, np.zeros(1, np.int64), net, ckpt.get("calibration"))
    from articulated_dataset.benchmark.predictions import ALL_DATASETS, MIXTURE_LAYOUT_ATTR, validate_class
    from articulated_dataset.core.errors import DataFormatError
    from articulated_dataset.core.rotations import quat_to_matrix

    try:  # as a predictions file is checked before it is written: finite, within bounds, unit quaternions,
        # sizes >= 0, a chirality in [0, 1]
        validate_class(name, {k: v for k, v in arrays.items() if k in ALL_DATASETS or k == MIXTURE_LAYOUT_ATTR})
    except DataFormatError as exc:  # weights that pass the checkpoint's checks but compute nonsense
        raise UserError(f"the model's estimate is not usable ({exc}); is its checkpoint damaged, or trained "
                        f"too briefly?") from None

    pose = arrays["axis_pose"][0]
    best = int(arrays["mixture_weights"][0].argmax())
    std = {n: float(s) for n, s in zip(arrays["mixture_layout"], arrays["mixture_scales"][0, best])}
    return Estimate(
        class_name=obj_class.name, joint_types=list(obj_class.joint_types), axis_origin_m=pose[:, :3],
        axis_direction=quat_to_matrix(pose[:, 3:])[:, :, 2], axis_pose=pose, q=arrays["q"][0],
        part_offset_m=arrays["part_offset"][0], geometry=arrays["geometry"][0], std=std,
        mixture_weights=arrays["mixture_weights"][0], mixture_means=arrays["mixture_means"][0],
        mixture_scales=arrays["mixture_scales"][0], mixture_layout=list(arrays["mixture_layout"]), model=name,
        outlier_weight=float(((ckpt.get("calibration") or {}).get("outlier") or {}).get("weight", 0.0)),
        cut_off=cut_off,
    )


def image_borders_reached(mask: np.ndarray) -> list[str]:
    """The borders of the image (of ``"top"``, ``"bottom"``, ``"left"``, ``"right"``) that the
    (H, W) boolean ``mask`` has a pixel on."""
    edges = {"top": mask[0], "bottom": mask[-1], "left": mask[:, 0], "right": mask[:, -1]}
    return [name for name, edge in edges.items() if edge.any()]


#: Suffixes of a split's shards (HDF5): a file that is one is not a depth image.
SHARD_SUFFIXES = (".h5", ".hdf5")


def estimate_file(depth_path: str | Path, class_name: str, *, camera_path: str | Path | None = None,
                  mask_path: str | Path | None = None, depth_units: str = "auto", model: str = "dense",
                  mirror: bool = True, precision: str = "float32",
                  before_model: Callable[[], object] | None = None, point: tuple[int, int] | None = None,
                  box: tuple[int, int, int, int] | None = None) -> Estimate:
    """:func:`estimate` of a depth file (16-bit PNG in mm, EXR or .npy in m; ``depth_units``
    overrides) with its camera file (default: ``NAME.camera.json`` or ``camera.json`` beside
    it, as ``artdata ingest`` finds them) and an optional object mask PNG (non-zero = object), or
    a ``point`` or ``box`` prompt instead of the mask (:func:`estimate`).
    ``before_model`` runs once the files are read and before the model is (``artdata
    estimate`` imports torch and sets its threads there, so a wrong file fails fast)."""
    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.core.images.exr import DEPTH_SUFFIX, LABEL_SUFFIX
    from articulated_dataset.core.images.intrinsics import load_intrinsics
    from articulated_dataset.ingest.captures import capture_files
    from articulated_dataset.ingest.readers import load_depth, load_mask

    depth_path = Path(depth_path)
    if not depth_path.is_file():
        raise UserError(f"depth file not found: {depth_path}")
    if depth_path.suffix.lower() in SHARD_SUFFIXES:
        raise UserError(f"{depth_path} is a shard of a split, not one depth image: predict a whole split with 'artdata "
                        f"predict {option('model')} {model} DIR', or export its "
                        f"images with 'artdata export DIR {option('fmt')} exr OUT'")
    if camera_path is None:
        camera = capture_files(depth_path).camera
        exported = depth_path.with_name(depth_path.name[: -len(DEPTH_SUFFIX)] + LABEL_SUFFIX)
        if camera is None and depth_path.name.endswith(DEPTH_SUFFIX) and exported.is_file():
            camera = exported  # an 'artdata export' image: its label file holds the intrinsics K
        if camera is None:
            raise UserError(f"{depth_path}: intrinsics missing; pass {option('camera_path')} "
                            "FILE (fx, fy, cx, cy) or put camera.json next to it")
    else:
        camera = Path(camera_path)
    K, size = load_intrinsics(camera)
    d = load_depth(depth_path, depth_units)
    if size is not None and (d.shape[1], d.shape[0]) != tuple(size):
        raise UserError(f"{depth_path}: depth is {d.shape[1]}x{d.shape[0]} px but {camera} says {size[0]}x{size[1]}")
    one_prompt(mask=mask_path, point=point, box=box)  # two prompts: one line before the mask is read
    mask = None
    if mask_path is not None:
        mask = load_mask(mask_path, d.shape, get_class(class_name).n_joints) > 0
    return _estimate(d, K, class_name, mask, model, mirror, precision, where=str(depth_path), before_model=before_model,
                     point=point, box=box)
