"""Depth-sensor noise models (sim-to-real): seeded corruptions of rendered z-depth images.

A model is a callable ``model(depth_m, K, rng) -> depth_m``: ``depth_m`` is an (H, W) float32
z-depth image in metres (0 = no return), ``K`` its 3x3 OpenCV intrinsics and ``rng`` a
``numpy.random.Generator`` (all randomness comes from it: same generator state, same output).
:data:`NOISE_MODELS` maps names to models; :func:`get_noise_model` looks one up.  The
generation pipeline applies one per image (``GenerationConfig(noise=...)``, seeded per object
by :func:`articulated_dataset.generation.pipeline.noise_rng`); the loaders wrap them as transforms.

``kinect2`` (:class:`DepthSensorNoise` with the Kinect v2 constants below) applies, in order:

1. **lateral noise**: every pixel reads the depth of the pixel at a Gaussian offset
   ``(du, dv) ~ N(0, s^2)`` (rounded to whole pixels, nearest neighbour), with
   ``s = LATERAL_SIGMA_NATIVE_PX * f_image / f_native`` so the offset has the published size
   in metres whatever the image resolution; it only changes values near depth edges.
2. **axial noise**: ``z += N(0, sigma_z(z, theta)^2)`` with Fankhauser et al. (2015)'s indoor model
   ``sigma_z [mm] = 1.5 - 0.5 z + 0.3 z^2 + 0.1 z^(3/2) theta^2 / (pi/2 - theta)^2``
   (``z`` in m, ``theta`` the incidence angle in rad, estimated from the clean depth image:
   :func:`incidence_angle_rad`).
3. **flying pixels**: a pixel next to a depth discontinuity becomes, with probability
   ``p_edge = min(1, FLYING_BAND_NATIVE_PX * f_image / f_native)``, a mix
   ``z + a (z_far - z)``, ``a ~ U(0, 1)``, of its depth and the far side's (time-of-flight
   pixels straddling an edge integrate both surfaces); next to a no-return pixel it is
   dropped instead (nothing to mix with).
4. **missing returns**: outside the operating range, on grazing surfaces (drop probability
   rising linearly from 0 at ``GRAZING_START_DEG`` to 1 at ``GRAZING_END_DEG``) and at random
   (``RANDOM_HOLE_P``) the depth becomes 0.
5. **quantisation** to the sensor's output step (1 mm: Kinect v2 frames are uint16 mm).

Sources of the constants: docs/real_data.md (with a comparison to the structured-light
Kinect v1 models of Nguyen et al. 2012 and Khoshelham & Elberink 2012).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from articulated_dataset.core.errors import UserError
from articulated_dataset.core.units import MM_PER_M

# --------------------------------------------------------------------------------------
# Kinect v2 constants
# --------------------------------------------------------------------------------------

#: Axial noise polynomial of Fankhauser et al. 2015 (ICAR, "Kinect v2 for mobile robot
#: navigation: evaluation and modeling"), indoor fit: sigma_z = C0 + C1 z + C2 z^2 [mm, z in m] ...
KINECT2_AXIAL_C0_MM = 1.5
KINECT2_AXIAL_C1_MM_PER_M = -0.5
KINECT2_AXIAL_C2_MM_PER_M2 = 0.3
#: ... plus C_theta z^(3/2) theta^2 / (pi/2 - theta)^2 for a surface seen at incidence theta.
KINECT2_AXIAL_THETA_MM = 0.1
#: Lateral noise of the same paper: about 1.6 native pixels, independent of distance.
KINECT2_LATERAL_SIGMA_NATIVE_PX = 1.6
#: Focal length (px) of the Kinect v2 depth camera at its native 512 x 424 resolution
#: (typical factory intrinsics: fx = fy ~ 365.5 px, i.e. a 70.6 deg horizontal field of view).
KINECT2_NATIVE_FOCAL_PX = 365.5
#: Operating range of the Kinect v2 depth camera (Microsoft specification: 0.5 - 4.5 m).
KINECT2_MIN_RANGE_M = 0.5
KINECT2_MAX_RANGE_M = 4.5
#: Output step: the sensor delivers uint16 depth in millimetres.
KINECT2_DEPTH_STEP_M = 0.001
#: Width (native px) of the band of mixed "flying" pixels on each side of a depth edge: one
#: pixel whose footprint straddles the edge (a geometric argument, not a fitted value).
KINECT2_FLYING_BAND_NATIVE_PX = 1.0
#: Incidence angles where returns start to drop out / are all lost (deg).  Nguyen et al. 2012
#: fit their angle-independent axial model only up to 60-70 deg; Fankhauser's angle term grows
#: without bound as theta -> 90 deg.  The ramp between the two values is a modelling choice.
KINECT2_GRAZING_START_DEG = 70.0
KINECT2_GRAZING_END_DEG = 85.0
#: Probability of an isolated missing return on a valid surface (a modelling choice; real
#: frames also lose pixels to low-albedo and specular materials, which are not modelled).
KINECT2_RANDOM_HOLE_P = 0.01
#: A jump between neighbouring pixels counts as a depth discontinuity when it exceeds what a
#: surface seen at this incidence angle would give: |dz| > (z / f) tan(angle) (per pixel).
EDGE_MAX_SURFACE_ANGLE_DEG = 85.0


def kinect2_axial_sigma_m(z_m: np.ndarray, theta_rad: np.ndarray | float = 0.0) -> np.ndarray:
    """Axial standard deviation (m) of the Kinect v2 at depth ``z_m`` and incidence ``theta_rad``.

    ``sigma_z = [1.5 - 0.5 z + 0.3 z^2 + 0.1 z^(3/2) theta^2 / (pi/2 - theta)^2] mm``
    (Fankhauser et al. 2015, indoor), ``z`` in metres, ``theta`` in radians (< pi/2).
    """
    z = np.asarray(z_m, np.float64)
    theta = np.asarray(theta_rad, np.float64)
    angle_term = theta**2 / (0.5 * math.pi - theta) ** 2
    sigma_mm = (KINECT2_AXIAL_C0_MM + KINECT2_AXIAL_C1_MM_PER_M * z + KINECT2_AXIAL_C2_MM_PER_M2 * z**2
                + KINECT2_AXIAL_THETA_MM * np.power(np.maximum(z, 0.0), 1.5) * angle_term)
    return sigma_mm / MM_PER_M


# --------------------------------------------------------------------------------------
# Geometry from a depth image
# --------------------------------------------------------------------------------------

def _points_optical(depth_m: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Optical-frame coordinates ``(X, Y, Z)``, each (H, W), of ``z K^-1 (u, v, 1)`` per pixel."""
    H, W = depth_m.shape
    z = depth_m.astype(np.float64)
    x = ((np.arange(W) - K[0, 2]) / K[0, 0])[None, :] * z
    y = ((np.arange(H) - K[1, 2]) / K[1, 1])[:, None] * z
    return x, y, z


def edge_thresholds_m(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Per-pixel jump (m) above which a neighbour is across a discontinuity:
    ``(z / f) tan(EDGE_MAX_SURFACE_ANGLE_DEG)`` with ``f = sqrt(fx fy)``."""
    f = math.sqrt(K[0, 0] * K[1, 1])
    return depth_m.astype(np.float64) / f * math.tan(math.radians(EDGE_MAX_SURFACE_ANGLE_DEG))


def _tangent(c: np.ndarray, ok: np.ndarray, axis: int) -> np.ndarray:
    """Finite-difference derivative of one coordinate image ``c`` along image ``axis``.

    Central difference where both neighbours are continuous with the pixel, else the one-sided
    difference that is; NaN where neither is.  ``ok`` marks, for each pixel pair (i, i+1) along
    ``axis``, that both are valid and continuous.
    """
    d = np.diff(c, axis=axis)  # d[i] = c[i+1] - c[i]
    pad_shape = (c.shape[0], 1) if axis == 1 else (1, c.shape[1])
    nan = np.full(pad_shape, np.nan)
    false = np.zeros(pad_shape, bool)
    fwd = np.concatenate([d, nan], axis=axis)  # c[i+1] - c[i]
    bwd = np.concatenate([nan, d], axis=axis)  # c[i] - c[i-1]
    ok_f = np.concatenate([ok, false], axis=axis)
    ok_b = np.concatenate([false, ok], axis=axis)
    return np.where(ok_f & ok_b, 0.5 * (fwd + bwd), np.where(ok_f, fwd, np.where(ok_b, bwd, np.nan)))


def incidence_angle_rad(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Angle (rad, in [0, pi/2]) between each pixel's viewing ray and its surface normal.

    The surface normal is ``n = t_u x t_v`` from finite differences of the back-projected
    points (central where continuous, one-sided at discontinuities: see
    :func:`edge_thresholds_m`); ``theta = arccos(|n . p| / (|n| |p|))`` with ``p`` the point
    (the ray from the camera centre).  Pixels without depth, or without a continuous neighbour
    along one image axis, get 0 (treated as facing the camera).
    """
    depth_m = np.asarray(depth_m)
    X, Y, Z = _points_optical(depth_m, K)
    valid = depth_m > 0
    thr = edge_thresholds_m(depth_m, K)
    ok_u = valid[:, 1:] & valid[:, :-1] & (np.abs(np.diff(Z, axis=1)) <= np.minimum(thr[:, 1:], thr[:, :-1]))
    ok_v = valid[1:, :] & valid[:-1, :] & (np.abs(np.diff(Z, axis=0)) <= np.minimum(thr[1:, :], thr[:-1, :]))
    ux, uy, uz = (_tangent(c, ok_u, 1) for c in (X, Y, Z))
    vx, vy, vz = (_tangent(c, ok_v, 0) for c in (X, Y, Z))
    nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs(nx * X + ny * Y + nz * Z) / np.sqrt((nx * nx + ny * ny + nz * nz) * (X * X + Y * Y + Z * Z))
    theta = np.arccos(np.clip(cos, 0.0, 1.0))
    return np.where(valid & np.isfinite(theta), theta, 0.0)


def discontinuity_partner(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """For each pixel, the depth (m) of the farthest 4-neighbour across a discontinuity.

    Returns an (H, W) float64 array: ``NaN`` where no neighbour is across a discontinuity,
    ``0`` where the pixel borders a no-return pixel (and no farther surface), else the
    neighbour's depth (larger or smaller than the pixel's own).  Only valid pixels are marked.
    """
    z = np.asarray(depth_m, np.float64)
    H, W = z.shape
    thr = edge_thresholds_m(z, K)
    valid = z > 0
    out = np.full((H, W), np.nan)
    best_jump = np.full((H, W), -1.0)
    padded = np.pad(z, 1, constant_values=np.nan)  # image border is not a discontinuity
    for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        nb = padded[1 + dv : 1 + dv + H, 1 + du : 1 + du + W]
        with np.errstate(invalid="ignore"):
            to_hole = valid & (nb == 0)
            jump = np.abs(nb - z)
            cross = valid & (nb > 0) & (jump > np.maximum(thr, edge_thresholds_m(np.nan_to_num(nb), K)))
        take = cross & (jump > best_jump)
        out[take] = nb[take]
        best_jump[take] = jump[take]
        hole_only = to_hole & np.isnan(out)
        out[hole_only] = 0.0
    return out


# --------------------------------------------------------------------------------------
# Models
# --------------------------------------------------------------------------------------

def _check_inputs(depth_m, K) -> tuple[np.ndarray, np.ndarray]:
    depth_m = np.asarray(depth_m)
    K = np.asarray(K, np.float64)
    if depth_m.ndim != 2:
        raise ValueError(f"depth must be an (H, W) image, got shape {depth_m.shape}")
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got shape {K.shape}")
    return depth_m, K


def no_noise(depth_m: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The identity model: returns the depth unchanged (as float32); draws nothing from ``rng``."""
    depth_m, _ = _check_inputs(depth_m, K)
    return depth_m.astype(np.float32, copy=False)


@dataclass(frozen=True)
class DepthSensorNoise:
    """A time-of-flight depth-noise model (see the module docstring for the stages).

    Set a probability or a sigma scale to 0 (``dataclasses.replace``) to switch one stage off.
    ``axial_scale`` multiplies :func:`kinect2_axial_sigma_m`.
    """

    native_focal_px: float = KINECT2_NATIVE_FOCAL_PX
    lateral_sigma_native_px: float = KINECT2_LATERAL_SIGMA_NATIVE_PX
    axial_scale: float = 1.0
    flying_band_native_px: float = KINECT2_FLYING_BAND_NATIVE_PX
    min_range_m: float = KINECT2_MIN_RANGE_M
    max_range_m: float = KINECT2_MAX_RANGE_M
    grazing_start_deg: float = KINECT2_GRAZING_START_DEG
    grazing_end_deg: float = KINECT2_GRAZING_END_DEG
    random_hole_p: float = KINECT2_RANDOM_HOLE_P
    depth_step_m: float = KINECT2_DEPTH_STEP_M

    def lateral_sigma_px(self, K: np.ndarray) -> float:
        """Lateral standard deviation in pixels of an image with intrinsics ``K``:
        ``sigma_native * f / f_native``, ``f = sqrt(fx fy)``."""
        return self.lateral_sigma_native_px * math.sqrt(K[0, 0] * K[1, 1]) / self.native_focal_px

    def flying_probability(self, K: np.ndarray) -> float:
        """Probability that a pixel next to a discontinuity is a flying pixel:
        ``min(1, band_native * f / f_native)``."""
        return min(1.0, self.flying_band_native_px * math.sqrt(K[0, 0] * K[1, 1]) / self.native_focal_px)

    def grazing_drop_probability(self, theta_rad: np.ndarray) -> np.ndarray:
        """Drop probability of a return at incidence ``theta_rad``: linear from 0 at
        ``grazing_start_deg`` to 1 at ``grazing_end_deg``."""
        lo, hi = math.radians(self.grazing_start_deg), math.radians(self.grazing_end_deg)
        return np.clip((np.asarray(theta_rad) - lo) / max(hi - lo, 1e-12), 0.0, 1.0)

    def axial_sigma_m(self, z_m: np.ndarray, theta_rad: np.ndarray) -> np.ndarray:
        """Axial standard deviation (m); the angle is capped at ``grazing_end_deg``."""
        theta = np.minimum(theta_rad, math.radians(self.grazing_end_deg))
        return self.axial_scale * kinect2_axial_sigma_m(z_m, theta)

    def __call__(self, depth_m: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A noisy copy of ``depth_m`` (H, W, metres; 0 = no return) rendered with intrinsics ``K``: lateral jitter,
        axial noise, flying pixels, missing returns and quantisation, drawn from ``rng`` in a fixed order."""
        depth_m, K = _check_inputs(depth_m, K)
        clean = depth_m.astype(np.float64)
        H, W = clean.shape
        valid = clean > 0
        # Fixed draw order (and sizes) keeps outputs reproducible for a given generator state.
        lateral = rng.standard_normal((2, H, W))
        axial = rng.standard_normal((H, W))
        u_fly = rng.random((H, W))
        a_fly = rng.random((H, W))
        u_graze = rng.random((H, W))
        u_hole = rng.random((H, W))

        theta = incidence_angle_rad(clean, K)
        partner = discontinuity_partner(clean, K)

        # 1. lateral: nearest-neighbour read at a Gaussian pixel offset
        s = self.lateral_sigma_px(K)
        z = clean
        if s > 0:
            v, u = np.mgrid[0:H, 0:W]
            vs = np.clip(v + np.rint(s * lateral[0]).astype(np.int64), 0, H - 1)
            us = np.clip(u + np.rint(s * lateral[1]).astype(np.int64), 0, W - 1)
            z, theta, partner = z[vs, us], theta[vs, us], partner[vs, us]
        valid = z > 0
        # 2. axial
        out = np.where(valid, z + self.axial_sigma_m(z, theta) * axial, 0.0)
        # 3. flying pixels
        p_fly = self.flying_probability(K)
        fly = valid & ~np.isnan(partner) & (u_fly < p_fly)
        mixed = fly & (partner > 0)
        out = np.where(mixed, z + a_fly * (np.nan_to_num(partner) - z), out)
        out[fly & (partner == 0)] = 0.0
        # 4. missing returns
        drop = (u_graze < self.grazing_drop_probability(theta)) | (u_hole < self.random_hole_p)
        drop |= (z < self.min_range_m) | (z > self.max_range_m)
        out[drop | ~valid] = 0.0
        out = np.maximum(out, 0.0)
        # 5. quantisation
        if self.depth_step_m > 0:
            out = np.rint(out / self.depth_step_m) * self.depth_step_m
        return out.astype(np.float32)


#: Kinect v2 (time of flight), constants above.
KINECT2 = DepthSensorNoise()

#: Registry of noise models by name (``artdata generate --noise NAME``).
NOISE_MODELS: dict = {
    "none": no_noise,
    "kinect2": KINECT2,
}


def get_noise_model(name: str):
    """The noise model registered as ``name``; unknown names are a :class:`UserError` listing
    the valid ones."""
    try:
        return NOISE_MODELS[name]
    except (KeyError, TypeError):
        raise UserError(f"unknown noise model {name!r}; choose from: {', '.join(NOISE_MODELS)}") from None


__all__ = [
    "NOISE_MODELS", "get_noise_model", "DepthSensorNoise", "KINECT2", "no_noise", "kinect2_axial_sigma_m",
    "incidence_angle_rad", "discontinuity_partner", "edge_thresholds_m",
]
