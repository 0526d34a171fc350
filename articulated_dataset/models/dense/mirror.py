"""Step 8 of the refinement: the estimate averaged with its mirror image's.

Where a class's mirror image is again an object of the class
(:attr:`~articulated_dataset.classes.ObjectClass.mirror_joints`: the cabinet hinged on either
side, the two-door cabinet, the drawer), the depth image reflected left-right is a second,
equally valid input.  The network is not exactly equivariant to the reflection (its errors on
the two images are partly independent), so averaging the two estimates lowers the error: on
the 64 seed-11 validation objects the two-door cabinet's position went from 3.91 to 3.72 cm
and the cabinet's from 7.69 to 7.22 cm.  It doubles the inference time, so
:func:`~.predict.fit_inference` uses it only where it lowers a model's validation position
error by at least :data:`MIRROR_MIN_GAIN`.

* The mirror image of a depth image ``D`` with intrinsics ``K`` is ``D'[v, u] = D[v, W - 1 - u]``
  with ``c_x' = W - 1 - c_x`` (:func:`mirror_inputs`): every pixel back-projects to the original
  point reflected across the camera's ``x z`` plane (camera ``y`` negated).
* Its estimate (vote modes after steps 1-7) is reflected back: origins with ``y`` negated, and
  joint ``k`` of the mirror image is the original's joint ``mirror_joints[k]``.
* Each mode of the original estimate is paired with the nearest reflected mode of the same
  joint; where the two origins are within :data:`MIRROR_GATE_M` (the same hypothesis, not the
  door's other side) the mode's origin and ``q`` become the means of the two (:func:`merge_mirrored`).
  A revolute joint's ``q`` (the door's opening angle) and a prismatic one's (its travel) are
  the same in the mirror image.  The frame, weights and spreads are the original's.
"""

from __future__ import annotations

import numpy as np

#: A reflected mode further than this (m) from a mode is another hypothesis (the door's other
#: side), not a second measurement of it: the mode is left as it is.
MIRROR_GATE_M = 0.10
#: :func:`~.predict.fit_inference` averages with the mirror image only where that lowers the
#: validation position error by at least this fraction (it doubles the inference time).
MIRROR_MIN_GAIN = 0.03
#: The camera-frame axis a left-right reflection of the image negates (the camera's ``y`` points
#: left: :func:`~.features.backproject_torch`).
MIRROR_AXIS = 1


def with_mirror(refinement, mirror: bool):
    """A checkpoint's refinement (a :class:`~.refine.Refinement`, its dict or None) as a
    :class:`~.refine.Refinement`, without this step unless ``mirror`` (``predict --no-mirror``:
    half the work of the classes that use it, for their 4-7% higher position error)."""
    from dataclasses import replace

    from .refine import as_refinement

    refinement = as_refinement(refinement)
    if mirror or refinement is None or refinement.mirror_joints is None:
        return refinement
    return replace(refinement, mirror_joints=None)


def mirror_intrinsics(K, width_px: int):
    """Intrinsics (B, 3, 3) (torch or numpy; a new array) that back-project the mirror images of
    ``width_px``-wide images to the reflected points: ``c_x' = W - 1 - c_x``."""
    K2 = K.clone() if hasattr(K, "clone") else K.copy()
    K2[:, 0, 2] = (width_px - 1) - K[:, 0, 2]
    return K2


def mirror_inputs(depth_m, K):
    """A batch of depth images (B, H, W) and intrinsics (B, 3, 3) (torch) -> their mirror images
    (reflected left-right) and the intrinsics that back-project them to the reflected points."""
    return depth_m.flip(-1), mirror_intrinsics(K, depth_m.shape[-1])


def merge_mirrored(m: dict, mirrored: dict, mirror_joints) -> dict:
    """Mode arrays ``m`` (numpy, (B, J, M, ...) as after :func:`~.refine.apply_refinement`) averaged
    with ``mirrored``, the same arrays of the mirror images (module docstring)."""
    perm = list(mirror_joints)
    o2 = mirrored["origin"][:, perm].copy()  # (B, J, M, 3): joint k of the original
    o2[..., MIRROR_AXIS] *= -1
    q2 = mirrored["q"][:, perm]
    used2 = mirrored["weight"][:, perm] > 0
    d = np.linalg.norm(m["origin"][:, :, :, None] - o2[:, :, None], axis=-1)  # (B, J, M, M2)
    d = np.where(used2[:, :, None], d, np.inf)
    nearest = d.argmin(-1)  # (B, J, M)
    close = (np.take_along_axis(d, nearest[..., None], -1)[..., 0] < MIRROR_GATE_M) & (m["weight"] > 0)
    o_pair = np.take_along_axis(o2, nearest[..., None], 2)
    q_pair = np.take_along_axis(q2, nearest, 2)
    out = dict(m)
    out["origin"] = np.where(close[..., None], 0.5 * (m["origin"] + o_pair), m["origin"])
    out["q"] = np.where(close, 0.5 * (m["q"] + q_pair), m["q"])
    return out


def mirrored_data(data):
    """A :class:`~.data.DenseData` of the mirror images of ``data``'s (labels dropped: they belong to
    the originals)."""
    from dataclasses import replace

    return replace(data, depth_q=np.ascontiguousarray(data.depth_q[:, :, ::-1]),
                   K=mirror_intrinsics(data.K, data.depth_q.shape[-1]), labels_out=None, origin=None,
                   rot6=None, q=None, part_offset=None, geometry=None)
