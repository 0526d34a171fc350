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

``d435`` (:class:`StereoDepthNoise`, Intel RealSense D435 active stereo) runs the same stages
with the stereo sensor's physics: the axial noise is a Gaussian disparity error of
``D435_SUBPIXEL_PX`` native pixels, ``z' = f B / (f B / z + s n)`` (to first order the datasheet's
``RMS = z^2 s / (f B)``: quadratic in distance); pixels next to a discontinuity are dropped
instead of mixed; and the pixels the right imager cannot see (the stereo shadow left of every
foreground edge, ``f B (1/z_near - 1/z_far)`` pixels wide, and the band of width ``f B / z`` at
the left image border) return nothing (:func:`stereo_occlusion_mask`).

``azure-kinect`` (:class:`MultipathTofNoise`, Azure Kinect DK time of flight, NFOV unbinned) has
a random error growing linearly with distance up to the specification's 17 mm at the end of
the operating range (0.5 - 3.86 m), one systematic offset per image within the specification's
``11 mm + 0.1%`` of distance, a multipath bias pushing concave regions away
(:func:`concavity_m`; the strongest are invalidated, as the sensor's depth engine does), and
flying pixels of which a share is invalidated.

Sources of the constants: docs/real_data.md (with a comparison to the structured-light
Kinect v1 models of Nguyen et al. 2012 and Khoshelham & Elberink 2012).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from articulated_dataset.core.camera import INTRINSICS_PRESETS
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
#: Rows and columns of the window :func:`concavity_m` averages over (odd: the centre is one;
#: a numerical choice that keeps the cost independent of the window's size).
CONCAVITY_SAMPLES_PER_SIDE = 9

# --------------------------------------------------------------------------------------
# Intel RealSense D435 constants (active stereo)
# --------------------------------------------------------------------------------------

#: Distance (m) between the D435's left and right imagers: 50 mm (Intel RealSense D400 Series
#: Product Family Datasheet, depth module properties).
D435_BASELINE_M = 0.050
#: RMS disparity ("subpixel") error of the D4 vision processor on a well-textured target (px):
#: about 0.08 in Intel's white paper "Tuning depth cameras for best performance"
#: (Grunnet-Jepsen, Sweetser, Woodfill), the value of its (and the datasheet's) depth RMS error
#: formula ``RMS = z^2 subpixel / (focal_px baseline)``.  The infrared projector supplies the
#: texture on plain surfaces (Intel white paper "Projectors for D400 series depth cameras").
D435_SUBPIXEL_PX = 0.08
#: Width (px) of the D435's recommended depth mode, 848 x 480 (tuning white paper) ...
D435_NATIVE_WIDTH_PX = 848
#: ... and its horizontal depth field of view (deg): 87 +- 3 deg (datasheet).
D435_HFOV_DEG = 87.0
#: Focal length (px) of that mode as the datasheet computes it: ``(W / 2) / tan(HFOV / 2)``
#: (446.8 px; a unit's calibration gives about 425 px: ``core.camera.INTRINSICS_PRESETS["d435"]``).
D435_NATIVE_FOCAL_PX = 0.5 * D435_NATIVE_WIDTH_PX / math.tan(math.radians(0.5 * D435_HFOV_DEG))
#: Disparity search range of the D4 vision processor (px): the nearest depth it measures is
#: ``focal_px baseline / 126`` (tuning white paper, "MinZ"): 0.18 m at 848 x 480.
D435_DISPARITY_RANGE_PX = 126
#: Farthest depth (m) kept: Intel's D435 specification gives a range to about 10 m.
D435_MAX_RANGE_M = 10.0
#: Output step: the D400 series' uint16 depth in its default depth unit, 1 mm.
D435_DEPTH_STEP_M = 0.001
#: Width (native px) of the band of invalid pixels on each side of a depth edge, where the
#: matching window straddles both surfaces and the match is rejected: one pixel (a geometric
#: argument, as for ``KINECT2_FLYING_BAND_NATIVE_PX``; not a fitted value).
D435_EDGE_BAND_NATIVE_PX = 1.0
#: Share of those edge pixels that read a mixed depth instead: none (stereo matching picks one
#: surface or rejects the pixel; it does not average them as a time-of-flight pixel does).
D435_EDGE_MIX_FRACTION = 0.0
#: Oblique surfaces and isolated holes: the Kinect v2's modelling choices (no D435 measurement
#: is used for them).
D435_GRAZING_START_DEG = KINECT2_GRAZING_START_DEG
D435_GRAZING_END_DEG = KINECT2_GRAZING_END_DEG
D435_RANDOM_HOLE_P = KINECT2_RANDOM_HOLE_P

# --------------------------------------------------------------------------------------
# Azure Kinect DK constants (time of flight, NFOV unbinned mode)
# --------------------------------------------------------------------------------------

#: Operating range of the NFOV unbinned mode (m), Azure Kinect DK hardware specification
#: ("Depth camera supported operating modes": 0.5 - 3.86 m).
AZURE_MIN_RANGE_M = 0.5
AZURE_MAX_RANGE_M = 3.86
#: Random error (temporal standard deviation) within the operating range: <= 17 mm for targets
#: of 15 - 95% reflectivity (same specification).  The model reaches it at the end of the range.
AZURE_RANDOM_STD_MAX_M = 0.017
#: Typical systematic error without multipath interference: < 11 mm + 0.1% of the distance
#: (same specification).
AZURE_SYSTEMATIC_CONST_M = 0.011
AZURE_SYSTEMATIC_FRACTION = 0.001
#: Focal length (px) of the NFOV unbinned depth camera (640 x 576): ``sqrt(fx fy)`` of the
#: Azure Kinect Sensor SDK calibration in ``core.camera.INTRINSICS_PRESETS["azure-kinect"]``.
AZURE_NATIVE_FOCAL_PX = math.sqrt(INTRINSICS_PRESETS["azure-kinect"].fx_px * INTRINSICS_PRESETS["azure-kinect"].fy_px)
#: Band of mixed ("flying") pixels at an edge: one native pixel, as for the Kinect v2.
AZURE_FLYING_BAND_NATIVE_PX = KINECT2_FLYING_BAND_NATIVE_PX
#: Share of those edge pixels that keep a mixed depth; the rest are invalidated, as the depth
#: engine invalidates mixed foreground/background signals ("Invalidation" in Microsoft's Azure
#: Kinect DK depth camera documentation) but leaves some flying pixels: a modelling choice.
AZURE_EDGE_MIX_FRACTION = 0.5
#: Multipath model (a modelling choice, order of magnitude only): light reaching a pixel via a
#: second surface within this radius (m) ...
AZURE_MULTIPATH_RADIUS_M = 0.1
#: ... lengthens its path: the depth grows by this fraction of the pixel's concavity
#: (:func:`concavity_m`): 1 cm at the crease of a 90 deg corner seen head-on.
AZURE_MULTIPATH_GAIN = 0.2
#: Oblique surfaces (low IR signal) and isolated holes: the Kinect v2's modelling choices.
AZURE_GRAZING_START_DEG = KINECT2_GRAZING_START_DEG
AZURE_GRAZING_END_DEG = KINECT2_GRAZING_END_DEG
AZURE_RANDOM_HOLE_P = KINECT2_RANDOM_HOLE_P
#: Output step: the sensor's uint16 depth in millimetres.
AZURE_DEPTH_STEP_M = 0.001


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


def stereo_occlusion_mask(depth_m: np.ndarray, K: np.ndarray, baseline_m: float) -> np.ndarray:
    """Pixels of the (left, reference) image that the right imager of a rectified stereo pair
    cannot see, as an (H, W) bool array.

    The right imager sits ``baseline_m`` along the image's +u axis: a point at column ``u`` and
    depth ``z`` appears there at ``u_r = u - fx B / z``.  A pixel is hidden when a pixel to its
    right lands left of it (``min_{u' > u} u_r(u') < u_r(u)``: that nearer surface covers it; a
    band ``fx B (1/z_near - 1/z_far)`` px wide left of every foreground edge) or when it falls left
    of the right image, whose first pixel's left border is at ``u_r = -1/2`` (the band
    ``fx B / z`` px wide at the left border).  Pixels without depth neither hide others nor count
    as hidden.
    """
    z = np.asarray(depth_m, np.float64)
    valid = z > 0
    u = np.arange(z.shape[1], dtype=np.float64)[None, :]
    u_right = u - np.where(valid, K[0, 0] * baseline_m / np.where(valid, z, 1.0), 0.0)
    right_min = np.minimum.accumulate(u_right[:, ::-1], axis=1)[:, ::-1]  # min over u' >= u
    covered = np.concatenate([right_min[:, 1:] < u_right[:, :-1], np.zeros((z.shape[0], 1), bool)], axis=1)
    return valid & (covered | (u_right < -0.5))


def concavity_m(depth_m: np.ndarray, K: np.ndarray, radius_m: float) -> np.ndarray:
    """How far (m, in [0, radius_m]) each pixel lies behind the surfaces around it.

    ``max(0, z - mean(max(z_n, z - radius_m)))`` over the valid pixels ``n`` of a square window of
    half-width ``round(f radius_m / z_med)`` px (at least 1; ``f = sqrt(fx fy)``, ``z_med`` the
    median valid depth: the window spans about ``radius_m`` at the image's typical depth),
    sampled on ``CONCAVITY_SAMPLES_PER_SIDE`` evenly spaced rows and columns.  Neighbours more
    than ``radius_m`` nearer count as ``radius_m`` nearer.  Planes, tilted or not, and convex
    shapes give 0 (the mean of ``1 / (a u + b v + c)`` over a window is at least its centre
    value; clipping only raises it); the crease of a 90 deg corner seen head-on gives about
    ``radius_m / 2``; a surface next to a nearer one a positive value.  0 where there is no depth.
    """
    z = np.asarray(depth_m, np.float64)
    H, W = z.shape
    valid = z > 0
    if not valid.any():
        return np.zeros_like(z)
    f = math.sqrt(K[0, 0] * K[1, 1])
    r = max(1, int(round(f * radius_m / float(np.median(z[valid])))))
    offsets = np.unique(np.rint(np.linspace(-r, r, CONCAVITY_SAMPLES_PER_SIDE)).astype(np.int64))
    padded = np.pad(z, r)  # outside the image: no depth
    floor = z - radius_m
    total = np.zeros_like(z)
    count = np.zeros_like(z)
    for dv in offsets:
        for du in offsets:
            nb = padded[r + dv : r + dv + H, r + du : r + du + W]
            ok = nb > 0
            total += np.where(ok, np.maximum(nb, floor), 0.0)
            count += ok
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / count
    return np.where(valid, np.maximum(z - mean, 0.0), 0.0)


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
    ``axial_scale`` multiplies :func:`kinect2_axial_sigma_m`.  ``edge_mix_fraction`` is the share
    of the pixels at an edge that read a mixed depth; the others are dropped.

    Sensors differ in three methods, which subclasses replace: :meth:`perturbed_depth_m` (the
    axial noise), :meth:`draw_extra` (random numbers beyond the common ones, drawn after them)
    and :meth:`scene_effects` (a depth offset and lost returns computed from the clean image).
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
    edge_mix_fraction: float = 1.0

    def lateral_sigma_px(self, K: np.ndarray) -> float:
        """Lateral standard deviation in pixels of an image with intrinsics ``K``:
        ``sigma_native * f / f_native``, ``f = sqrt(fx fy)``."""
        return self.lateral_sigma_native_px * math.sqrt(K[0, 0] * K[1, 1]) / self.native_focal_px

    def flying_probability(self, K: np.ndarray) -> float:
        """Probability that a pixel next to a discontinuity is an edge artefact (mixed, or dropped:
        ``edge_mix_fraction``): ``min(1, band_native * f / f_native)``."""
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

    def perturbed_depth_m(self, z_m: np.ndarray, theta_rad: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """Depth after the axial noise, given one standard normal draw per pixel (``normal``):
        ``z + sigma_z(z, theta) n``."""
        return z_m + self.axial_sigma_m(z_m, theta_rad) * normal

    def draw_extra(self, rng: np.random.Generator) -> dict:
        """Random numbers of this sensor beyond the common ones (drawn after them); none here."""
        return {}

    def scene_effects(self, clean_m: np.ndarray, K: np.ndarray, extra: dict) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(offset_m, lost)`` from the clean depth: a depth offset (m) added to the valid pixels
        after the axial noise, and the pixels that return nothing; ``None``: no such effect (here)."""
        return None, None

    def __call__(self, depth_m: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A noisy copy of ``depth_m`` (H, W, metres; 0 = no return) rendered with intrinsics ``K``: lateral jitter,
        axial noise, flying pixels, missing returns and quantisation, drawn from ``rng`` in a fixed order."""
        depth_m, K = _check_inputs(depth_m, K)
        clean = depth_m.astype(np.float64)
        H, W = clean.shape
        # Fixed draw order (and sizes) keeps outputs reproducible for a given generator state.
        lateral = rng.standard_normal((2, H, W))
        axial = rng.standard_normal((H, W))
        u_fly = rng.random((H, W))
        a_fly = rng.random((H, W))
        u_graze = rng.random((H, W))
        u_hole = rng.random((H, W))
        extra = self.draw_extra(rng)

        theta = incidence_angle_rad(clean, K)
        partner = discontinuity_partner(clean, K)
        offset, lost = self.scene_effects(clean, K, extra)

        # 1. lateral: nearest-neighbour read at a Gaussian pixel offset
        s = self.lateral_sigma_px(K)
        z = clean
        if s > 0:
            v, u = np.mgrid[0:H, 0:W]
            vs = np.clip(v + np.rint(s * lateral[0]).astype(np.int64), 0, H - 1)
            us = np.clip(u + np.rint(s * lateral[1]).astype(np.int64), 0, W - 1)
            z, theta, partner = z[vs, us], theta[vs, us], partner[vs, us]
            offset = None if offset is None else offset[vs, us]
            lost = None if lost is None else lost[vs, us]
        valid = z > 0
        # 2. axial (and the sensor's offsets)
        out = np.where(valid, self.perturbed_depth_m(z, theta, axial), 0.0)
        if offset is not None:
            out = np.where(valid, out + offset, 0.0)
        # 3. edges: mixed ("flying") or dropped pixels
        p_fly = self.flying_probability(K)
        fly = valid & ~np.isnan(partner) & (u_fly < p_fly)
        mixed = fly & (partner > 0) & (u_fly < p_fly * self.edge_mix_fraction)
        out = np.where(mixed, z + a_fly * (np.nan_to_num(partner) - z), out)
        out[fly & ~mixed] = 0.0
        # 4. missing returns
        drop = (u_graze < self.grazing_drop_probability(theta)) | (u_hole < self.random_hole_p)
        drop |= (z < self.min_range_m) | (z > self.max_range_m)
        if lost is not None:
            drop |= lost
        out[drop | ~valid] = 0.0
        out = np.maximum(out, 0.0)
        # 5. quantisation
        if self.depth_step_m > 0:
            out = np.rint(out / self.depth_step_m) * self.depth_step_m
        return out.astype(np.float32)


@dataclass(frozen=True)
class StereoDepthNoise(DepthSensorNoise):
    """An active-stereo depth-noise model (defaults: the Intel RealSense D435 constants above).

    The stages of :class:`DepthSensorNoise`, with: the axial noise a Gaussian error of
    ``subpixel_px`` (native pixels) on the disparity ``d = f_native B / z``, so that
    ``z' = f_native B / (d + subpixel_px n)`` (no return where ``d' <= 0``), whose standard
    deviation is to first order :meth:`axial_sigma_m` ``= z^2 subpixel / (f_native B)``; edge pixels
    dropped (``edge_mix_fraction`` 0); and the pixels hidden from the right imager lost
    (:func:`stereo_occlusion_mask`, with the image's own ``fx``).  ``axial_scale`` multiplies
    ``subpixel_px``.
    """

    native_focal_px: float = D435_NATIVE_FOCAL_PX
    lateral_sigma_native_px: float = 0.0
    flying_band_native_px: float = D435_EDGE_BAND_NATIVE_PX
    min_range_m: float = D435_NATIVE_FOCAL_PX * D435_BASELINE_M / D435_DISPARITY_RANGE_PX
    max_range_m: float = D435_MAX_RANGE_M
    grazing_start_deg: float = D435_GRAZING_START_DEG
    grazing_end_deg: float = D435_GRAZING_END_DEG
    random_hole_p: float = D435_RANDOM_HOLE_P
    depth_step_m: float = D435_DEPTH_STEP_M
    edge_mix_fraction: float = D435_EDGE_MIX_FRACTION
    baseline_m: float = D435_BASELINE_M
    subpixel_px: float = D435_SUBPIXEL_PX

    def axial_sigma_m(self, z_m: np.ndarray, theta_rad: np.ndarray | float = 0.0) -> np.ndarray:
        """Depth RMS error (m) at ``z_m``: ``z^2 subpixel / (f_native B)`` (Intel's formula; the
        incidence angle does not enter it)."""
        z = np.asarray(z_m, np.float64)
        return self.axial_scale * self.subpixel_px * z * z / (self.native_focal_px * self.baseline_m)

    def perturbed_depth_m(self, z_m: np.ndarray, theta_rad: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """Depth from the disparity ``f B / z`` plus ``axial_scale * subpixel_px * n``; 0 where the
        disparity is not positive."""
        fb = self.native_focal_px * self.baseline_m
        valid = z_m > 0
        disparity_px = np.where(valid, fb / np.where(valid, z_m, 1.0), 0.0) + self.axial_scale * self.subpixel_px * normal
        ok = valid & (disparity_px > 0)
        return np.where(ok, fb / np.where(ok, disparity_px, 1.0), 0.0)

    def scene_effects(self, clean_m: np.ndarray, K: np.ndarray, extra: dict) -> tuple[np.ndarray | None, np.ndarray | None]:
        """No offset; the stereo shadow and left border band are lost."""
        return None, stereo_occlusion_mask(clean_m, K, self.baseline_m)


@dataclass(frozen=True)
class MultipathTofNoise(DepthSensorNoise):
    """A time-of-flight model built from a specification sheet (defaults: the Azure Kinect DK
    NFOV unbinned constants above).

    The stages of :class:`DepthSensorNoise`, with: the axial noise :meth:`axial_sigma_m`
    ``= random_std_max_m (z / max_range_m) / sqrt(cos theta)`` (shot noise of a signal falling
    as ``cos theta / z^2``, scaled so that a head-on target at the end of the operating range
    has the specification's bound); a systematic offset ``s (systematic_const_m +
    systematic_fraction z)``, ``s ~ U(-1, 1)`` drawn once per image; a multipath offset
    ``multipath_gain * concavity_m(depth, K, multipath_radius_m)`` (depth pushed away inside
    corners and next to nearer surfaces), the pixels whose multipath offset exceeds the
    systematic bound ``systematic_const_m + systematic_fraction z`` being lost (the depth engine
    invalidates such ambiguous returns); and a share ``1 - edge_mix_fraction`` of the edge pixels
    dropped instead of mixed.  ``axial_scale`` multiplies the random error (e.g. 0.5 for a target
    4x brighter than the specification's 15% reflectivity).
    """

    native_focal_px: float = AZURE_NATIVE_FOCAL_PX
    lateral_sigma_native_px: float = 0.0
    flying_band_native_px: float = AZURE_FLYING_BAND_NATIVE_PX
    min_range_m: float = AZURE_MIN_RANGE_M
    max_range_m: float = AZURE_MAX_RANGE_M
    grazing_start_deg: float = AZURE_GRAZING_START_DEG
    grazing_end_deg: float = AZURE_GRAZING_END_DEG
    random_hole_p: float = AZURE_RANDOM_HOLE_P
    depth_step_m: float = AZURE_DEPTH_STEP_M
    edge_mix_fraction: float = AZURE_EDGE_MIX_FRACTION
    random_std_max_m: float = AZURE_RANDOM_STD_MAX_M
    systematic_const_m: float = AZURE_SYSTEMATIC_CONST_M
    systematic_fraction: float = AZURE_SYSTEMATIC_FRACTION
    multipath_radius_m: float = AZURE_MULTIPATH_RADIUS_M
    multipath_gain: float = AZURE_MULTIPATH_GAIN

    def axial_sigma_m(self, z_m: np.ndarray, theta_rad: np.ndarray | float = 0.0) -> np.ndarray:
        """Random error (m): ``random_std_max_m (z / max_range_m) / sqrt(cos theta)``, the angle
        capped at ``grazing_end_deg``."""
        theta = np.minimum(np.asarray(theta_rad, np.float64), math.radians(self.grazing_end_deg))
        z = np.asarray(z_m, np.float64)
        return self.axial_scale * self.random_std_max_m * (z / self.max_range_m) / np.sqrt(np.cos(theta))

    def systematic_bound_m(self, z_m: np.ndarray) -> np.ndarray:
        """The specification's systematic error bound (m) at depth ``z_m``."""
        return self.systematic_const_m + self.systematic_fraction * np.asarray(z_m, np.float64)

    def multipath_offset_m(self, depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
        """Depth added by multipath interference (m, >= 0): ``multipath_gain * concavity``."""
        return self.multipath_gain * concavity_m(depth_m, K, self.multipath_radius_m)

    def draw_extra(self, rng: np.random.Generator) -> dict:
        """The image's systematic-error sign and size ``s ~ U(-1, 1)``."""
        return {"systematic": 2.0 * rng.random() - 1.0}

    def scene_effects(self, clean_m: np.ndarray, K: np.ndarray, extra: dict) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Offset: systematic + multipath; lost: multipath beyond the systematic bound."""
        bound = self.systematic_bound_m(clean_m)
        multipath = self.multipath_offset_m(clean_m, K)
        return extra["systematic"] * bound + multipath, multipath > bound


#: Kinect v2 (time of flight), constants above.
KINECT2 = DepthSensorNoise()
#: Intel RealSense D435 (active stereo), 848 x 480 mode, constants above.
D435 = StereoDepthNoise()
#: Azure Kinect DK (time of flight), NFOV unbinned mode, constants above.
AZURE_KINECT = MultipathTofNoise()

#: Registry of noise models by name (``artdata generate --noise NAME``, ``artdata train --noise NAME``).
NOISE_MODELS: dict = {
    "none": no_noise,
    "kinect2": KINECT2,
    "d435": D435,
    "azure-kinect": AZURE_KINECT,
}


def get_noise_model(name: str):
    """The noise model registered as ``name``; unknown names are a :class:`UserError` listing
    the valid ones."""
    try:
        return NOISE_MODELS[name]
    except (KeyError, TypeError):
        raise UserError(f"unknown noise model {name!r}; choose from: {', '.join(NOISE_MODELS)}") from None


__all__ = [
    "NOISE_MODELS", "get_noise_model", "DepthSensorNoise", "StereoDepthNoise", "MultipathTofNoise", "KINECT2", "D435",
    "AZURE_KINECT", "no_noise", "kinect2_axial_sigma_m", "incidence_angle_rad", "discontinuity_partner",
    "edge_thresholds_m", "stereo_occlusion_mask", "concavity_m",
]
