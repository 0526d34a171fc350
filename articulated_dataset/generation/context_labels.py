"""Occlusion labels of splits with ``--scene`` or ``--occluders`` (format 1.1): the rule that
bounds them, their invariants (``artdata verify``) and how ``artdata show`` draws the pixels
that are not the object.  Needs neither MuJoCo nor the generator.
"""

from __future__ import annotations

import json

import numpy as np

from articulated_dataset.format.schema import MASK_OCCLUDER, MASK_SCENE, OPTIONAL_FIELDS, resolve_shape

#: Every moving part keeps at least this fraction of its pixels (visible / alone) in every
#: image of a split with a scene or occluders (the visibility rejection's bound; the stored
#: ``visible_fraction`` of the moving parts lies in this range).
VISIBLE_FRACTION_RANGE = (0.3, 1.0)
#: Colours (RGB in [0, 1]) ``artdata show`` paints scene and occluder pixels with, shaded by
#: depth: neither is in the depth colormap, so the object stands out.
SCENE_SHOW_RGB = (0.80, 0.84, 0.90)
OCCLUDER_SHOW_RGB = (0.30, 0.33, 0.36)


def visible_fraction(visible: np.ndarray, unoccluded: np.ndarray) -> np.ndarray:
    """``visible / unoccluded`` as stored (float32; 1 where the part alone covers no pixel)."""
    v, u = np.asarray(visible, np.float64), np.asarray(unoccluded, np.float64)
    return np.where(u > 0, v / np.maximum(u, 1.0), 1.0).astype(np.float32)


def context_mask_codes(attrs: dict) -> tuple[int, ...]:
    """Mask codes a shard may hold besides the object's: 255 with a scene, 254 with occluders."""
    return tuple(code for key, code in (("scene", MASK_SCENE), ("occluders", MASK_OCCLUDER)) if key in attrs)


def visible_fraction_bound(attrs: dict) -> float:
    """The lowest ``visible_fraction`` of a moving part the shard's generator allowed."""
    for key in ("occluders", "scene"):
        try:
            return float(json.loads(attrs[key])["visible_fraction"][0])
        except (KeyError, TypeError, ValueError, IndexError):
            continue
    return VISIBLE_FRACTION_RANGE[0]


def optional_field_problems(f, fields, expected: bool, why_needed: str, where_unexpected: str, *,
                            N: int, J: int, H: int, W: int) -> list[str]:
    """Problems of optional datasets ``fields`` of an open shard ``f``: present exactly when
    ``expected``, each with its declared dtype and shape."""
    p = []
    for fd in fields:
        if fd.name not in f:
            if expected:
                p.append(f"missing dataset {fd.name!r} ({why_needed})")
            continue
        if not expected:
            p.append(f"dataset {fd.name!r} in {where_unexpected}")
        ds, shape = f[fd.name], resolve_shape(fd.shape, N=N, J=J, H=H, W=W)
        if tuple(ds.shape) != shape or np.dtype(ds.dtype) != np.dtype(fd.dtype):
            p.append(f"dataset {fd.name!r} is {ds.dtype} {tuple(ds.shape)}, expected {fd.dtype} {shape}")
    return p


def occlusion_problems(f, attrs: dict, arrays: dict, *, J: int, N: int, H: int, W: int) -> list[str]:
    """Problems of a shard's occlusion fields (``f``: the open HDF5 file): present exactly
    when the shard has a scene or occluders, declared dtype and shape, ``unoccluded_pixels >=
    visible_pixels``, ``visible_fraction`` = their ratio, moving parts within the bound."""
    context = bool(context_mask_codes(attrs))
    p = optional_field_problems(f, OPTIONAL_FIELDS, context, "a split with a scene or occluders stores it",
                                "a shard without scene or occluders", N=N, J=J, H=H, W=W)
    if p or not context or "visible_pixels" not in arrays:
        return p
    try:
        vis, alone, frac = arrays["visible_pixels"], f["unoccluded_pixels"][()], f["visible_fraction"][()]
    except (OSError, RuntimeError, ValueError) as exc:
        return [f"cannot read the occlusion datasets ({str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__})"]
    rows = lambda bad: f"{int(bad.any(axis=-1).sum())} image(s)"  # noqa: E731
    bad = alone < vis
    if bad.any():
        p.append(f"unoccluded_pixels: fewer than visible_pixels in {rows(bad)} (occluders cannot reveal pixels)")
    bad = frac != visible_fraction(vis, alone)
    if bad.any():
        p.append(f"visible_fraction: differs from visible_pixels / unoccluded_pixels in {rows(bad)}")
    lo = visible_fraction_bound(attrs)
    bad = frac[:, 1:] < np.float32(lo)
    if J and bad.any():
        p.append(f"visible_fraction: a moving part keeps less than {lo:g} of its pixels in {rows(bad)}")
    return p


def tint_context(rgb: np.ndarray, mask: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
    """``rgb`` (H, W, 3) floats with scene pixels painted :data:`SCENE_SHOW_RGB` and occluder
    pixels :data:`OCCLUDER_SHOW_RGB`, darker with depth (a relief); other pixels unchanged."""
    out = np.array(rgb, dtype=np.float64, copy=True)
    shade = np.ones(mask.shape)
    if depth is not None and (depth > 0).any():
        d = np.asarray(depth, np.float64)
        lo, hi = d[d > 0].min(), d.max()
        shade = 1.0 - 0.35 * (d - lo) / max(hi - lo, 1e-9)
    for code, colour in ((MASK_SCENE, SCENE_SHOW_RGB), (MASK_OCCLUDER, OCCLUDER_SHOW_RGB)):
        sel = mask == code
        out[sel] = np.asarray(colour)[None] * shade[sel][:, None]
    return out


def object_depth(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``depth`` with scene and occluder pixels set to 0, so that ``artdata show`` spreads its
    depth colours over the object alone (the input itself when there are none)."""
    context = mask >= MASK_OCCLUDER
    return np.where(context, 0.0, depth) if context.any() else depth


def context_details(config: dict) -> list[str]:
    """Words ``artdata show`` adds to a split's header: its scene and occluders, with the
    colours their pixels are drawn in."""
    out = []
    if config.get("scene", "none") != "none":
        out.append(f"{config['scene']} scene (pale blue-grey)")
    if config.get("occluders", 0):
        out.append(f"{config['occluders']} occluder{'s' if config['occluders'] != 1 else ''}/image (slate)")
    return out
