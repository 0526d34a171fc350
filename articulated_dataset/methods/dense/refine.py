"""Geometric refinement of the voted estimate: the object's box frame and door angles from surface normals.

The network's votes locate the axis well but leave the axis frame a few degrees off (its
rotation votes are regressed pixel by pixel; a door whose hinge side is uncertain even
averages two frames) and regress ``q`` towards the class mean where the door is hard to see.
Every object of the benchmark is a box whose faces are parallel to the axis frame, and the
input already holds each pixel's surface normal, so both can be measured instead of
regressed (:func:`refined_quantities`, per image and joint):

1. **Sign-free votes.**  Every pixel's 6-D rotation vote gives an axis ``z_i`` and ``x_i``;
   the axis *line* is the principal eigenvector of ``sum_i w_i z_i z_i^T`` and
   ``y = normalise(sum_i w_i z_i x x_i)`` (``w_i`` the rotation confidences): both are
   unchanged when a pixel votes for the mirrored frame (``z, x -> -z, -x``), so two hinge sides
   no longer cancel.  ``x = y x z``.
2. **Box frame** (Manhattan alignment).  The normals of the body's pixels and of prismatic parts'
   pixels (a drawer only translates: its front shows the pull axis where the body shows only a
   rim) (network segmentation, upsampled) are matched to the nearest signed frame axis (inliers within
   an angle that shrinks over the rounds, :data:`INLIER_ANGLES_DEG`) and the rotation that best maps the axes onto the normals is found
   by Kabsch's SVD (where the fit chooses ``frame_one_sided``, the pixels the input has no normal for, a
   face seen as a strip one or two pixels wide, get one from one-sided differences along the
   strip and to a neighbour that is itself such a pixel: :func:`~.features.one_sided_normals`);
   :data:`PRIOR_WEIGHT_PX` pseudo-normals on
   the current axes keep a direction no face constrains where it was.  Where the fit chooses
   ``frame_strip_elongation``, an image whose body is seen only as a thin strip (fewer than
   :data:`STRIP_MAX_PX` of those pixels: the side wall beside a door seen edge-on, the top's
   front edge) adds one more: the strip's points, projected on the plane across the axis, lie
   on a line along a face of the box, so its perpendicular there is a face's normal, weighted by
   the strip's pixels (:func:`strip_normals`), where the line's variance exceeds the variance
   across it that many times.  Where the result turns a
   mode's voted frame by more than ``max_turn_deg`` (fitted; :func:`frame_turn_deg`) the voted
   frame is kept.
3. **Axis side.**  Per vote mode, ``x`` points from the mode's axis origin towards the centre
   of the visible object (a door's hinge is on the object's edge), ``z`` follows (``y = z x x``
   is kept); prismatic joints keep the sign of their votes.
4. **Hinge offset.**  The label's ``x`` points at the door's centre, which lies a constant
   ``t`` (m) in front of the box face: ``x`` is turned about ``z`` by ``atan2(t, r)``, with ``r``
   the voted radius (``part_offset`` x) and ``t`` fitted on validation objects
   (:func:`~.fit.fit_refinement`).
5. **Door angle.**  A door turned by ``q`` about ``z`` has its normal at ``q`` from ``y``:
   ``q = median_i atan2(|n_i . x|, |n_i . y|)`` over the door's pixels with a normal
   (weighted median; used when at least ``min_door_px`` such pixels exist).  The door's edge, and
   a door seen almost edge-on (the cabinet's wide-open doors), show faces whose normals are at
   ``pi / 2 - q``: where the fit chooses ``door_angle_folded``, each pixel's angle ``a_i`` is
   replaced by ``pi / 2 - a_i`` where that is nearer the votes' ``q`` (the modes' ``q`` by
   weight), so the votes pick the face and the normals give the angle.  Where it chooses
   ``door_angle_signed``, the angle keeps its signs: ``-atan2(n . x, n . y)`` modulo ``pi / 2`` is ``q`` on the door's faces and edges
   alike (``x`` the mode's, from the hinge towards the door); its median on that circle, and of
   the angles equal modulo ``pi / 2`` the one nearest the mode's vote (:func:`signed_door_angle`).
   ``door_angle_gate_deg`` keeps the votes where the
   measured angle is further from them.
6. **Hinge height.**  A door's axis origin is at the door's mid-height (the templates' convention:
   ``common.xacro``'s ``side_door``), and the door's pixels show its extent along the axis: the
   origin is moved along ``z`` to the middle of the :data:`DOOR_EXTENT_QUANTILE` and
   ``1 - DOOR_EXTENT_QUANTILE`` quantiles of the door pixels' ``p . z``.  Not where the door's
   pixels reach within one output pixel of the image's top or bottom rows (the door is cut off),
   nor where the move would exceed ``door_extent_gate_m``.  It corrects the votes' tails (a
   misjudged door height) and is used only where it lowers the validation position error.
7. **Hinge side from the handle** (:mod:`.handle`).  A closed door whose vote mode puts the hinge
   at the door's handle is mirrored across the door (the cabinet's one-image side errors).
8. **Mirror image** (:mod:`.mirror`).  Where the class's mirror image is again an object of the
   class, the network's part logits, origin offsets, ``q`` and vote confidences are averaged with
   its outputs on the image reflected left-right (reflected back) before the votes are counted:
   every other step runs once, on the averaged outputs.
9. **Hinge height from the handle** (:mod:`.handle`, applied after step 6, before 7).  A door's
   handle is centred at its mid-height: where the handle is seen whole, the origin is moved along
   the axis to the handle's height (behind a fitted gate); where the fit chooses it, also where
   the image's top or bottom border cuts the bar (its centre half a bar's length from its visible
   end).  It is used only where it lowers the
   validation position error by at least :data:`~.fit.HANDLE_HEIGHT_MIN_GAIN` (it measures the
   handle of every door, a cost at inference).
10. **Hinge plane from the door's face** (applied last).  The hinge lies in the plane of the door's
   outer face (``common.xacro``'s ``side_door``: the panel's front face, at its hinge edge), and
   the door's face pixels measure that plane to a millimetre where the votes place the origin
   ~0.5 cm off it.  The door's face (:func:`~.handle.door_face`, which steps 7 and 9 read too):
   its normal ``n`` is the mean of its pixels' normals (each turned to face the camera along its
   pixel's ray, taken perpendicular to the axis) within
   :data:`~.handle.FACE_INLIER_DEG` of the previous mean, and its offset ``f`` the median of
   ``p . n`` over the pixels within the last angle.  Per
   vote mode, the face seen is the outer one where ``n`` is within :data:`DOOR_FACE_MAX_DEG` of
   the door's ``y`` (the frame's ``y`` turned by the mode's ``q`` about its axis), the inner one
   (an open door seen from its inside) where it is within that of ``-y``, neither where the door is seen
   edge-on; the origin is moved along ``n`` onto the plane ``f`` plus the fitted offset of that
   face (``door_face_offsets_m``: the outer face's ~0, the inner face's ~minus the panel's
   thickness) where that moves it by less than ``door_face_gate_m``.  The axis' line moves
   across the hinge only; steps 6 and 9 set its height along it.
11. **A drawer's front** (prismatic joints; :func:`drawer_front`).  The axis origin is the centre of
   the drawer front's outer face when closed (``drawer.urdf.xacro``), so the front's plane is at
   ``o . z + q`` along the pull axis ``z`` and its centre is the origin moved along ``z``.  The
   front's pixels (the part's, with a normal within :data:`FRONT_MAX_DEG` of ``z``, the front-most
   :data:`FRONT_BAND_M` of them: not the tray's back wall seen over the open top) measure both to
   millimetres where the votes place the plane ~2 cm off (the drawer's seed-14 selection objects:
   2.2 cm mean).  Where the front is not cut by the image's border, the origin is moved across
   the axis to the middle of the front's extent along ``x`` and ``y`` (the
   :data:`DOOR_EXTENT_QUANTILE` quantiles) where that moves it by less than
   ``drawer_centre_gate_m``.  Along the axis, the origin is moved to the shell's edge
   (:func:`shell_front`) plus a fitted offset (``drawer_shell_offset_m``: the panel's 2 cm and
   the edge pixels' bias) where that moves it by less than ``drawer_shell_gate_m``: the box's
   faces parallel to the axis (the shell's top, bottom and sides) are flush with the front
   panel's edges, and the tray's are set in by the shell's wall, so on such a face the pixels
   more than a panel behind the front are the shell's, and the front-most of them is its edge,
   where a closed drawer's panel begins.  Last, ``q`` becomes the front plane's distance from the
   mode's origin along its axis, less a fitted offset (``drawer_front_offset_m``, the outer face's
   ~0), where that moves it by less than ``drawer_front_gate_m``.

:func:`~.fit.fit_refinement` chooses, on the training split's validation objects, which steps
are used (each only where it lowers the validation error) and fits ``t``; the choice is stored
in the checkpoint (``"refinement"``) and applied by :func:`apply_refinement` at inference.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TypedDict, cast

import numpy as np
import torch
from torch.nn import functional as F

from articulated_dataset.methods.dense.aggregate import (
    SPLIT_FACTOR,
    argmax_channels,
    compact_mask,
    gram_schmidt6,
    image_groups,
    lower_median,
    rows_dot,
    softmax_weights,
)
from articulated_dataset.methods.dense.features import MIN_NORMAL_NORM, OUTPUT_STRIDE, POINT_SCALE_M, one_sided_normals
from articulated_dataset.methods.dense.handle import (
    EVERY_DOOR_DEG,
    HANDLE_KEYS,
    MIN_RADIUS_M,
    apply_handle_height,
    apply_handle_side,
    door_face,
    door_handles,
    handle_candidates,
)

#: Manhattan alignment rounds: a normal is matched to a frame axis within these angles (deg).  The
#: last two rounds leave out the normals of a face's border pixels, whose central differences mix
#: two faces and sit a few degrees off the face (on a cabinet's side wall: columns at 0, -0.9 and
#: 5.1 deg from it), which a 5-degree round still averages in.  A further 0.5-degree round changes
#: the rotation by 0.01 deg or less.
INLIER_ANGLES_DEG = (25.0, 10.0, 5.0, 2.0, 1.0)
#: Weight (in pixels) of the current frame's own axes in each alignment round.
PRIOR_WEIGHT_PX = 10.0
#: Step 2's strip (:func:`strip_normals`): an image's box-frame pixels are read as a strip only
#: where there are at least :data:`STRIP_MIN_PX` and fewer than :data:`STRIP_MAX_PX` of them (a
#: body seen whole has faces with normals, and a strip read there turns frames without lowering
#: the configuration error).
STRIP_MIN_PX = 10
STRIP_MAX_PX = 500
#: ... and where its points' standard deviation along their line is at least this (m): a strip
#: seen end-on (a column of pixels down one vertical edge) projects to a point across the axis,
#: whose "line" is rounding (0.01 and 0.03 m give the same validation errors).
STRIP_MIN_SPREAD_M = 0.01
#: The frame alignment reads the normals of every this-many-th row and column (2 is ~10% faster
#: and measured ~0.05 deg worse on microwave validation objects).
ALIGN_STRIDE = 1
#: Step 5's door angles (:func:`refined_quantities`' keys): from the normals' unsigned angles, folded
#: towards the votes, and signed.
DOOR_ANGLES = ("q", "q_folded", "q_signed")
#: Step 6: the door's extent along the axis is read between these quantiles of its pixels.
DOOR_EXTENT_QUANTILE = 0.005
#: Step 6 needs at least this many door pixels.
DOOR_EXTENT_MIN_PX = 10
#: Step 10 reads a face as the door's outer or inner face within this angle (deg) of the door's
#: ``y`` or ``-y``; a door seen nearer edge-on keeps its origin.
DOOR_FACE_MAX_DEG = 25.0
#: Step 11 reads a drawer's pixels whose normal is within this angle (deg) of its pull axis as its
#: front's (the front panel and the handle bar's face; a central difference across the panel's
#: edge mixes in a side and is further off).
FRONT_MAX_DEG = 10.0
#: ... the front-most of them within this distance (m) along the axis of the
#: :data:`FRONT_TOP_QUANTILE` quantile: the panel and the bar 3 cm in front of it
#: (``handle_standoff_m``), not the open tray's back wall tens of centimetres behind.
FRONT_BAND_M = 0.05
FRONT_TOP_QUANTILE = 0.02
#: ... and needs at least this many such pixels.
FRONT_MIN_PX = 10
#: Step 11's shell edge: the box faces parallel to the pull axis (the shell's outer faces, with the
#: front panel's edges flush with them; the tray's sides are set in by the shell's wall and
#: clearance) are read from the pixels whose normal is within this angle (deg) of a frame axis
#: across the pull axis ...
SHELL_FACE_MAX_DEG = 20.0
#: ... and which lie within this distance (m) of the face's plane (the ``1 - SHELL_PLANE_QUANTILE``
#: quantile of their coordinates along its normal: the outermost face) ...
SHELL_FLUSH_M = 0.01
SHELL_PLANE_QUANTILE = 0.02
#: ... further behind the front's plane than the front panel's thickness (``drawer.urdf.xacro``'s
#: ``panel_m``) plus :data:`SHELL_PANEL_MARGIN_M`: the shell's pixels, whose front-most one is its
#: edge, where the drawer leaves it; the face with the most such pixels (at least
#: :data:`SHELL_MIN_PX`) is read.
DRAWER_PANEL_M = 0.02
SHELL_PANEL_MARGIN_M = 0.01
SHELL_MIN_PX = 5
#: Refinement format version stored in checkpoints (2: ``max_turn_deg``; 3: ``door_extent``;
#: 4: ``handle_max_q_deg``; 5: ``mirror_joints``; 6: ``frame_min_prob``; 7: ``handle_height_gate_m``;
#: 8: ``handle_cut_bars``; 9: ``door_angle_folded``; 10: ``door_angle_signed``, ``door_angle_gate_deg``;
#: 11: ``door_face_gate_m``, ``door_face_offsets_m``; 12: ``frame_one_sided``; 13: ``drawer_front_gate_m``,
#: ``drawer_front_offset_m``, ``drawer_centre_gate_m``, ``drawer_shell_gate_m``, ``drawer_shell_offset_m``;
#: 14: ``frame_strip_elongation``; older versions read as without them).  The versions name the
#: stored fields, not their implementation: every version's ``mirror_joints`` averages the
#: network's outputs (:mod:`.mirror`).
REFINEMENT_VERSION = 14


class _RefinementRecordRequired(TypedDict):
    frame: bool
    hinge_offset_m: float
    min_door_px: int | None


class RefinementRecord(_RefinementRecordRequired, total=False):
    """A :class:`Refinement` as a checkpoint stores it (``"refinement"``; :meth:`Refinement.to_dict`):
    its fields as plain JSON values (pairs and tuples as lists; lengths m, angles deg).  A key that
    a refinement of a lower :data:`REFINEMENT_VERSION` lacks takes the field's default."""

    door_angle_folded: bool
    door_angle_signed: bool
    door_angle_gate_deg: float | None
    max_turn_deg: float | None
    frame_min_prob: float | None
    frame_one_sided: bool
    frame_strip_elongation: float | None
    door_extent: bool
    door_extent_gate_m: float | None
    split_factor: float | None
    handle_max_q_deg: float | None
    handle_min_px: float
    handle_height_gate_m: float | None
    handle_cut_bars: bool
    mirror_joints: list[int] | None
    door_face_gate_m: float | None
    door_face_offsets_m: list[float | None]
    drawer_front_gate_m: float | None
    drawer_front_offset_m: float
    drawer_centre_gate_m: float | None
    drawer_shell_gate_m: float | None
    drawer_shell_offset_m: float
    version: int


@dataclass(frozen=True)
class Refinement:
    """What :func:`apply_refinement` changes (fitted per class by :func:`~.fit.fit_refinement`)."""

    #: replace the voted axis frame by the box frame (steps 1-4)
    frame: bool = False
    #: the door centre's offset in front of the box face (m), step 4
    hinge_offset_m: float = 0.0
    #: use the normal-based door angle where at least this many door pixels have a normal (None: never)
    min_door_px: int | None = None
    #: step 5 reads each door pixel's angle or its complement, whichever is nearer the voted ``q``
    door_angle_folded: bool = False
    #: step 5 reads each door pixel's angle with its signs, on the circle of period 90 degrees
    #: (:func:`signed_door_angle`; overrides ``door_angle_folded``)
    door_angle_signed: bool = False
    #: ... only where it lies within this many degrees of the mode's voted angle (None: anywhere)
    door_angle_gate_deg: float | None = None
    #: keep a mode's voted frame where the box frame turns it by more than this (deg; None: never)
    max_turn_deg: float | None = None
    #: step 2 fits the box frame to the pixels whose segmentation probability of their label
    #: exceeds this (None: every pixel of the body and of prismatic parts)
    frame_min_prob: float | None = None
    #: ... and gives those of them whose normal the input lacks (a face seen as a strip one or two
    #: pixels wide) a normal from one-sided differences (:func:`~.features.one_sided_normals`)
    frame_one_sided: bool = False
    #: ... and, in an image whose body is a thin strip, reads the strip's direction across the axis
    #: where its points' variance along it is at least this many times that across it
    #: (:func:`strip_normals`; None: never)
    frame_strip_elongation: float | None = None
    #: move a door's axis origin to the door's mid-height (step 6)
    door_extent: bool = False
    #: ... only where that moves it by less than this (m; None: any distance)
    door_extent_gate_m: float | None = None
    #: the vote modes' split factor (:func:`~.aggregate.vote_modes`; None: one mode per joint), chosen
    #: on validation objects before the steps above (:func:`~.predict.choose_split_factor`)
    split_factor: float | None = SPLIT_FACTOR
    #: step 7: mirror a door whose vote mode puts its hinge at its handle, for doors whose angle is
    #: below this (deg; None: never), with at least ``handle_min_px`` handle pixels
    handle_max_q_deg: float | None = None
    handle_min_px: float = 1.0
    #: step 9: move a door's axis origin to its handle's height where that moves it by less than
    #: this (m; None: never)
    handle_height_gate_m: float | None = None
    #: ... also from a bar the image's top or bottom border cuts: its centre half a bar's length
    #: from its visible end (:func:`~.handle.handle_cut_usable`)
    handle_cut_bars: bool = False
    #: step 8 (:mod:`.mirror`): average with the mirror image's estimate, whose joint ``k`` is joint
    #: ``mirror_joints[k]`` (None: never)
    mirror_joints: tuple[int, ...] | None = None
    #: step 10: move a door's axis origin onto its face's plane where that moves it by less than
    #: this (m; None: never) ...
    door_face_gate_m: float | None = None
    #: ... the hinge plane's offset (m) along the face's normal from the outer face and from the
    #: inner face (fitted: :func:`~.fit.fit_door_face_offsets`; None: that face was never seen on
    #: the validation objects, and a mode that sees it keeps its origin)
    door_face_offsets_m: tuple[float | None, float | None] = (0.0, 0.0)
    #: step 11: a drawer's ``q`` from its front's plane where that moves it by less than this (m;
    #: None: never) ...
    drawer_front_gate_m: float | None = None
    #: ... the plane's offset (m) along the pull axis from the front's outer face at ``q`` (fitted)
    drawer_front_offset_m: float = 0.0
    #: step 11: a drawer's origin moved across its axis to its front's centre where the front is seen
    #: whole and that moves it by less than this (m; None: never)
    drawer_centre_gate_m: float | None = None
    #: step 11: a drawer's origin moved along its axis to its shell's edge plus
    #: ``drawer_shell_offset_m`` where that moves it by less than this (m; None: never)
    drawer_shell_gate_m: float | None = None
    drawer_shell_offset_m: float = 0.0
    version: int = REFINEMENT_VERSION

    @property
    def needed(self) -> bool:
        """Whether it changes anything (else the refined quantities need not be computed)."""
        return (self.frame or self.min_door_px is not None or self.door_extent or self.handle_max_q_deg is not None
                or self.handle_height_gate_m is not None or self.door_face_gate_m is not None
                or self.drawer_front_gate_m is not None or self.drawer_centre_gate_m is not None
                or self.drawer_shell_gate_m is not None)

    @property
    def door_angles(self) -> tuple[str, ...]:
        """The step-5 door angles inference reads (of :data:`DOOR_ANGLES`): :func:`apply_refinement`'s
        and the handles' choice of doors; :func:`refined_quantities` computes only these."""
        used = set()
        if self.min_door_px is not None:
            used.add("q_signed" if self.door_angle_signed else "q_folded" if self.door_angle_folded else "q")
        handle_deg = self.handle_evidence_max_q_deg
        if handle_deg is not None and handle_deg < EVERY_DOOR_DEG:  # which doors' handles are measured
            used.add("q")  # (:func:`~.handle.handle_candidates_evidence`)
        return tuple(k for k in DOOR_ANGLES if k in used)

    @property
    def handle_evidence_max_q_deg(self) -> float | None:
        """The door angle (deg) below which inference measures the doors' handles
        (:func:`~.handle.handle_candidates_evidence`): every door's for step 9, step 7's limit
        otherwise (None: no handle is measured)."""
        return EVERY_DOOR_DEG if self.handle_height_gate_m is not None else self.handle_max_q_deg

    def to_dict(self) -> RefinementRecord:
        """The refinement as plain JSON types (stored in checkpoints)."""
        d = asdict(self)
        d["mirror_joints"] = None if self.mirror_joints is None else [int(k) for k in self.mirror_joints]
        d["door_face_offsets_m"] = [_optional_float(v) for v in self.door_face_offsets_m]
        return cast(RefinementRecord, d)  # (asdict: every field, by name)

    @classmethod
    def from_dict(cls, d: RefinementRecord | None) -> "Refinement | None":
        """The refinement stored by :meth:`to_dict` (None for None); an absent optional key takes its default."""
        if d is None:
            return None
        turn, gate = d.get("max_turn_deg"), d.get("door_extent_gate_m")
        return cls(frame=bool(d["frame"]), hinge_offset_m=float(d["hinge_offset_m"]),
                   min_door_px=None if d["min_door_px"] is None else int(d["min_door_px"]),
                   door_angle_folded=bool(d.get("door_angle_folded", False)),
                   door_angle_signed=bool(d.get("door_angle_signed", False)),
                   door_angle_gate_deg=_optional_float(d.get("door_angle_gate_deg")),
                   max_turn_deg=None if turn is None else float(turn), door_extent=bool(d.get("door_extent", False)),
                   frame_min_prob=_optional_float(d.get("frame_min_prob")),
                   frame_one_sided=bool(d.get("frame_one_sided", False)),
                   frame_strip_elongation=_optional_float(d.get("frame_strip_elongation")),
                   door_extent_gate_m=None if gate is None else float(gate),
                   split_factor=_optional_float(d["split_factor"]) if "split_factor" in d else SPLIT_FACTOR,
                   handle_max_q_deg=_optional_float(d.get("handle_max_q_deg")),
                   handle_min_px=float(d.get("handle_min_px", 1.0)),
                   handle_height_gate_m=_optional_float(d.get("handle_height_gate_m")),
                   handle_cut_bars=bool(d.get("handle_cut_bars", False)),
                   mirror_joints=None if d.get("mirror_joints") is None else tuple(int(k) for k in d["mirror_joints"]),  # type: ignore[union-attr]  # not None: checked first
                   door_face_gate_m=_optional_float(d.get("door_face_gate_m")),
                   door_face_offsets_m=_float_pair(d.get("door_face_offsets_m", (0.0, 0.0))),
                   drawer_front_gate_m=_optional_float(d.get("drawer_front_gate_m")),
                   drawer_front_offset_m=float(d.get("drawer_front_offset_m", 0.0)),
                   drawer_centre_gate_m=_optional_float(d.get("drawer_centre_gate_m")),
                   drawer_shell_gate_m=_optional_float(d.get("drawer_shell_gate_m")),
                   drawer_shell_offset_m=float(d.get("drawer_shell_offset_m", 0.0)),
                   version=int(d.get("version", REFINEMENT_VERSION)))


def _optional_float(v) -> float | None:
    return None if v is None else float(v)


def _float_pair(v) -> tuple[float | None, float | None]:
    a, b = v  # a stored pair: a list or tuple of two numbers (or None)
    return _optional_float(a), _optional_float(b)


def split_factor_of(refinement) -> float | None:
    """The vote modes' split factor a checkpoint's refinement (a :class:`Refinement`, its dict or
    None) asks for (:data:`~.aggregate.SPLIT_FACTOR` when it does not say)."""
    refinement = as_refinement(refinement)
    return SPLIT_FACTOR if refinement is None else refinement.split_factor


def as_refinement(refinement) -> "Refinement | None":
    """A :class:`Refinement` from one, its dict (a checkpoint's ``"refinement"``), or None."""
    return Refinement.from_dict(refinement) if isinstance(refinement, dict) else refinement  # type: ignore[arg-type]  # a stored record


def rotate_about(v: torch.Tensor, axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotate ``v`` (..., 3) about the unit ``axis`` (..., 3) by ``angle`` (...) rad (Rodrigues)."""
    c, s = torch.cos(angle)[..., None], torch.sin(angle)[..., None]
    return v * c + torch.cross(axis, v, dim=-1) * s + axis * (axis * v).sum(-1, keepdim=True) * (1 - c)


def weighted_median(values: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Weighted median over the last dimension (the smallest value whose cumulative weight reaches
    half the total); NaN where the weights sum to 0."""
    v, order = torch.sort(values, -1)
    cw = torch.gather(weights, -1, order).cumsum(-1)
    total = cw[..., -1:]
    k = torch.searchsorted(cw.contiguous(), (0.5 * total).contiguous()).clamp_max(values.shape[-1] - 1)
    med = torch.gather(v, -1, k)[..., 0]
    return torch.where(total[..., 0] > 0, med, torch.full_like(med, float("nan")))


def _quantile_pair(values: torch.Tensor, real: torch.Tensor, q: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``torch.nanquantile`` (linear interpolation) of each row's ``real`` entries at ``q`` and
    ``1 - q`` (``q`` small), reading only the few smallest and largest entries (:func:`torch.topk`)
    instead of sorting the rows; NaN for a row without real entries."""
    count = real.sum(-1, keepdim=True)  # (R, 1)
    quant = torch.tensor([q, 1 - q], dtype=values.dtype)[:, None, None]
    ranks = (quant * (count - 1)).clamp_min(0)  # (2, R, 1), as torch.quantile computes them
    below, above, weight = ranks.long(), ranks.ceil().long(), ranks - ranks.long()
    k = min(int(math.ceil(q * max(int(count.max()) - 1, 0))) + 2, values.shape[-1])
    inf = torch.tensor(float("inf"), dtype=values.dtype)
    smallest = torch.topk(torch.where(real, values, inf), k, -1, largest=False).values  # ascending
    largest = torch.topk(torch.where(real, values, -inf), k, -1, largest=True).values  # descending
    # the ascending rank r among the largest entries is position count - 1 - r
    at = lambda v, r: v.gather(-1, r.clamp(0, k - 1))  # noqa: E731
    lo = torch.lerp(at(smallest, below[0]), at(smallest, above[0]), weight[0])[..., 0]
    hi = torch.lerp(at(largest, count - 1 - below[1]), at(largest, count - 1 - above[1]), weight[1])[..., 0]
    none = count[..., 0] == 0
    return lo.masked_fill(none, float("nan")), hi.masked_fill(none, float("nan"))


def _sign_free_frame(parts: dict, valid: torch.Tensor) -> torch.Tensor:
    """Step 1: (B, J, 3, 3) frames with columns x, y, z from the rotation votes."""
    wr = softmax_weights(parts["conf"][:, :, 1], valid)  # (B, J, N)
    z_pix, x_pix = gram_schmidt6(parts["rot6"].flatten(3), dim=2)  # (B, J, 3, N)
    scatter = (wr[:, :, None] * z_pix) @ z_pix.transpose(-1, -2)  # sum_i w_i z_i z_i^T
    z = torch.linalg.eigh(scatter)[1][..., -1]  # principal direction, sign arbitrary
    y = (wr[:, :, None] * _cross(z_pix, x_pix, dim=2)).sum(-1)
    y = F.normalize(y - (y * z).sum(-1, keepdim=True) * z, dim=-1, eps=1e-12)
    return torch.stack([torch.cross(y, z, dim=-1), y, z], -1)


def _cross(a: torch.Tensor, b: torch.Tensor, dim: int) -> torch.Tensor:
    """``torch.cross(a, b, dim)`` written out: several times faster along a short strided axis."""
    a0, a1, a2 = a.unbind(dim)
    b0, b1, b2 = b.unbind(dim)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim)


def _align_to_normals(frame: torch.Tensor, normals: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Step 2: Manhattan alignment of (B, J, 3, 3) frames to (B, P, 3) unit normals weighted (B, P).

    A unit normal within an inlier angle (< 45 deg) of a signed frame axis is nearest to that
    axis, so matching "nearest axis, if within the angle" is the threshold ``|n . a_k| > cos``.
    The weights multiply the normals before the matched axes' signs (+-1) do: the same numbers as
    weighting the signs for the 0 / 1 weights of :func:`refined_quantities`.
    """
    B, J = frame.shape[:2]
    normals_t = normals.transpose(1, 2).contiguous()  # (B, 3, P)
    # w_p n_p as (B, P, 3) rows of a (B, 3, P) tensor: the product below then reduces along
    # contiguous rows (2.3x faster than over a (B, P, 3) tensor's columns)
    weighted = (normals_t * weights[:, None]).transpose(1, 2)
    for inlier_deg in INLIER_ANGLES_DEG:
        cos_in = math.cos(math.radians(inlier_deg))
        # every normal in every frame's coordinates at once: (B, J * 3, P), row 3 j + k for axis k of joint j
        c = frame.transpose(-1, -2).reshape(B, J * 3, 3) @ normals_t
        # +-1 on the matched signed axis, 0 elsewhere: hardshrink keeps c exactly where |c| > cos, and
        # its sign is the axis' (one fused kernel: 2.7x faster than sign(|c| - cos) clamped at 0 times
        # sign(c); comparisons, bool -> float conversions and a broadcast torch.where are slower still)
        signed = F.hardshrink(c, cos_in).sign_()
        # H = sum_p w_p a_p n_p^T with a_p the matched signed axis (row k: the normals matched to
        # +-axis k), plus the prior (the current axes onto themselves); R = V diag(1, 1, d) U^T
        rows = signed @ weighted  # (B, J * 3, 3)
        H = rows.view(B, J, 3, 3) + PRIOR_WEIGHT_PX * frame.transpose(-1, -2)
        U, _, Vh = torch.linalg.svd(H)
        d = torch.sign(torch.linalg.det(Vh.transpose(-1, -2) @ U.transpose(-1, -2)))
        D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
        frame = Vh.transpose(-1, -2) @ D @ U.transpose(-1, -2)
    return frame


def strip_sized(count: torch.Tensor) -> torch.Tensor:
    """Whether images with ``count`` (R,) box-frame pixels may be read as a strip: at least
    :data:`STRIP_MIN_PX` and fewer than :data:`STRIP_MAX_PX`."""
    return (count >= STRIP_MIN_PX) & (count < STRIP_MAX_PX)


def strip_normals(points: torch.Tensor, strip: torch.Tensor, axis: torch.Tensor,
                  min_elongation: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 2's strip: per image, the unit normal (R, 3) across ``axis`` (R, 3) of the line its
    ``strip`` pixels' points lie on, and its weight (R,): their count where :func:`strip_sized` and
    the points' variance along the line is at least ``min_elongation`` times the variance across it
    and its standard deviation at least :data:`STRIP_MIN_SPREAD_M`, 0 elsewhere.  ``points`` (R, 3, n) m (any origin), ``strip`` (R, n)
    bool.

    The points are projected on the plane across the axis (``S_h = P S P``, ``S`` their covariance,
    ``P = I - a a^T``); the line is ``S_h``'s principal eigenvector ``d`` (variance ``l_2``, across
    it ``l_1``, along the axis 0) and the normal ``a x d``.  A face of the box seen as a strip one or
    two pixels wide (a side wall beside a door seen edge-on, the top's front edge) has too few
    pixels with a normal, but its points still lie on the face: on the seed-14 selection cabinets,
    the true body pixels' line turned by a median of 0.0 deg from the box's axes (modulo 90) where
    the voted frame's configuration error was 4-6 deg."""
    w = strip.to(points.dtype)
    count = w.sum(-1)
    mean = (points * w[:, None]).sum(-1) / count.clamp_min(1.0)[:, None]
    d = (points - mean[..., None]) * w[:, None]  # (R, 3, n), 0 off the strip
    cov = d @ d.transpose(1, 2) / count.clamp_min(1.0)[:, None, None]
    P = torch.eye(3, dtype=points.dtype) - axis[:, :, None] * axis[:, None, :]
    variance, direction = torch.linalg.eigh(P @ cov @ P)  # ascending: ~0 (along the axis), across, along
    normal = F.normalize(_cross(axis, direction[..., 2], dim=-1), dim=-1, eps=1e-12)
    line = variance[:, 2] >= min_elongation * variance[:, 1].clamp_min(torch.finfo(points.dtype).tiny)
    used = strip_sized(count) & line & (variance[:, 2] >= STRIP_MIN_SPREAD_M**2)
    return normal, torch.where(used, count, 0.0)


@torch.no_grad()
def refined_quantities(parts: dict, inputs: dict, modes: dict, joint_types, frame_min_prob: float | None = None,
                       door_angles: tuple[str, ...] = DOOR_ANGLES, handle_max_q_deg: float | None = None,
                       frame_one_sided: bool = False, frame_strip_elongation: float | None = None) -> dict:
    """Steps 1-3, 5 and 6 for a batch (see the module docstring); step 2 on the pixels whose
    label's segmentation probability exceeds ``frame_min_prob`` (None: all of them), with
    ``frame_one_sided`` also on those without a central-difference normal, from one-sided
    differences (:attr:`Refinement.frame_one_sided`), with ``frame_strip_elongation`` also on the
    direction of a body seen as a strip (:func:`strip_normals`); of step 5's
    angles only ``door_angles`` (a subset of :data:`DOOR_ANGLES`: a refinement's
    :attr:`Refinement.door_angles`; the choice among them on validation objects needs all); with
    ``handle_max_q_deg`` (:attr:`Refinement.handle_evidence_max_q_deg`), also the handles of the
    doors steps 7 and 9 read (:func:`~.handle.handle_candidates`; 0 for the others): the keys of
    :func:`~.handle.handle_candidates_evidence`, from :func:`~.handle.door_handles` on the door
    pixels gathered here.

    ``parts``: :meth:`DenseNet.split` output; ``inputs``: :func:`~.features.make_inputs` output;
    ``modes``: :func:`~.aggregate.vote_modes` output.  Returns ``axis``, ``xaxis`` (B, J, M, 3)
    of the box frame with each mode's side, ``q`` (B, J) normal-based door angle (rad, NaN when
    no door pixel has a normal; NaN for prismatic joints), ``q_folded`` and ``q_signed`` (B, J: the
    folded angle; the signed one modulo ``pi / 2`` for the frame whose x is ``box_x`` (B, J, 3), the
    box frame's x before step 3's sides), ``door_px`` (B, J), ``frame_px`` (B,: step 2's candidate
    pixels, with a normal or without, whose number :func:`strip_sized` reads), and for step 6
    ``door_mid`` (B, J: the door's mid-height as a coordinate along ``axis[:, :, 0]``, m; NaN
    with fewer than :data:`DOOR_EXTENT_MIN_PX` door pixels or for prismatic joints) and
    ``door_cut`` (B, J: 1 where the door's pixels reach the image's top or bottom output row).

    Only the valid pixels (a third of the image or fewer) are read: the images are taken in
    groups with similar numbers of valid pixels (:func:`~.aggregate.image_groups`), each image's
    gathered to the front of a row padded to the group's largest (:func:`~.aggregate.compact_mask`), each door's
    again for the medians and quantiles.
    """
    x = inputs["x"]
    valid_px = x[:, 3].flatten(1) > 0  # (B, H * W)
    frame = _sign_free_frame(parts, inputs["weight_out"] > 0)
    voted_q = (modes["weight"] * modes["q"]).sum(-1)  # (B, J): the modes' q, by weight (step 5's folding)
    rows_of, back = image_groups(x[:, 3].sum((1, 2)))  # the validity channel's sum: no bool -> int conversion
    groups = []
    for rows in rows_of:
        groups.append(_refine_images(x, rows, valid_px[rows], parts["seg"][rows], frame[rows], inputs["anchor"][rows],
                                     modes["origin"][rows], modes["axis"][rows], voted_q[rows], joint_types,
                                     frame_min_prob, door_angles, handle_max_q_deg is not None, frame_one_sided,
                                     frame_strip_elongation))
    out = {k: torch.cat([g[k] for g in groups])[back] for k in groups[0]}
    if handle_max_q_deg is not None and handle_max_q_deg < EVERY_DOOR_DEG:
        # measured for every revolute door; only the candidates keep theirs
        keep = handle_candidates(modes, out, handle_max_q_deg)  # (B, J)
        for k in HANDLE_KEYS:
            out[k] = torch.where(keep.view(keep.shape + (1,) * (out[k].dim() - 2)), out[k], 0.0)
    return out


def _refine_images(x: torch.Tensor, rows: torch.Tensor, valid_px: torch.Tensor, seg: torch.Tensor, frame: torch.Tensor,
                   anchor: torch.Tensor, origin: torch.Tensor, voted_axis: torch.Tensor, voted_q: torch.Tensor,
                   joint_types, frame_min_prob: float | None = None, door_angles: tuple[str, ...] = (),
                   handles: bool = False, frame_one_sided: bool = False,
                   frame_strip_elongation: float | None = None) -> dict:
    """:func:`refined_quantities` of the images ``rows`` of the input ``x``: their valid pixels
    (R, H * W), segmentation logits, sign-free frames (step 1), anchors, voted origins and axes and
    the voted door angles (R, J) rad."""
    R, J = frame.shape[:2]
    H, W = x.shape[2:]
    idx, ok = compact_mask(valid_px)  # (R, n): the valid pixels
    n = idx.shape[1]
    # channels 4-6 (normals) of the valid pixels, channels first (R, 3, n) (index_select: faster than
    # indexing with a tensor; every later product is then written component by component, several
    # times faster than a batched product with an inner size of 3); channels 0-2 (relative points) and
    # the doors' normals are read at the doors' pixels only (steps 5 and 6)
    at = (rows[:, None] * x[0].numel() + idx).view(-1)
    x_flat = x.contiguous().view(-1)
    P = H * W
    normals = torch.stack([x_flat[c * P:].index_select(0, at).view(R, n) for c in (4, 5, 6)], 1)
    n0, n1, n2 = normals.unbind(1)
    has_normal = ok & ((n0 * n0 + n1 * n1 + n2 * n2) > MIN_NORMAL_NORM**2)
    # each pixel's label is its output pixel's (nearest upsampling): 0 body, 1 + j part j
    h_out, w_out = seg.shape[2:]
    out_pixel = (torch.arange(H) // OUTPUT_STRIDE * w_out)[:, None] + torch.arange(W) // OUTPUT_STRIDE
    at_out = out_pixel.flatten()[idx]  # (R, n): each valid pixel's output pixel
    label = torch.gather(argmax_channels(seg).flatten(1), 1, at_out)  # (R, n)
    row = idx // W
    # the body's faces, and a drawer's: a prismatic part only translates, so its faces stay parallel
    # to the frame's (the front of a drawer shows the pull axis where the body shows only a rim)
    frame_px = label == 0
    for j, t in enumerate(joint_types):
        if t == "prismatic":
            frame_px = frame_px | (label == 1 + j)
    frame_px &= ok
    if frame_min_prob is not None:  # only the pixels the segmentation is sure of (an open door's pixels
        # taken for the body's would pull the frame towards the door's face)
        confidence = torch.softmax(seg, 1).amax(1).flatten(1)  # (R, h * w): the label's probability
        frame_px &= torch.gather(confidence, 1, at_out) > frame_min_prob
    count = frame_px.sum(-1)  # the fit's candidates, with a normal or without (whether a strip may be read)
    if frame_strip_elongation is not None:  # every candidate of the images whose count may make a strip
        # (most images show more of the body: their weight is 0 unread)
        strip_normal, strip_weight = frame[:, 0, :, 0].clone(), x.new_zeros(R)
        some = strip_sized(count).nonzero()[:, 0]
        if len(some):
            at_some = at.view(R, n).index_select(0, some).view(-1)
            points: torch.Tensor | list  # a (S, 3, n) tensor here, three (R, n) components at step 11
            points = torch.stack([x_flat[c * P:].index_select(0, at_some).view(len(some), n) for c in range(3)], 1)
            strip_normal[some], strip_weight[some] = strip_normals(points * POINT_SCALE_M, frame_px.index_select(0, some),
                                                                   frame[some, 0, :, 2], frame_strip_elongation)
    if frame_one_sided:  # the candidates without a central-difference normal get a one-sided one
        # whose neighbours are candidates too (a strip's neighbour across its edge is another face)
        P = H * W
        allowed = torch.zeros(R * P, dtype=torch.bool)
        allowed[(torch.arange(R)[:, None] * P + idx)[frame_px]] = True
        missing = (frame_px & ~has_normal).view(-1).nonzero()[:, 0]  # into the (R * n) valid pixels
        one_sided, defined = one_sided_normals(x.contiguous(), at.index_select(0, missing), allowed,
                                               (missing // n) * P + idx.reshape(-1).index_select(0, missing))
        missing, one_sided = missing[defined], one_sided[:, defined]
        frame_px = (frame_px & has_normal).view(-1).index_fill(0, missing, True).view(R, n)
    else:
        frame_px &= has_normal
    if ALIGN_STRIDE > 1:  # the frame fit uses every ALIGN_STRIDE-th row and column (neighbouring normals share pixels)
        frame_px &= (row % ALIGN_STRIDE == 0) & (idx % W % ALIGN_STRIDE == 0)
    # the fit reads only its own pixels, gathered to the front of each row (the others have weight 0)
    fidx, fok = compact_mask(frame_px)
    f = fidx.shape[1]
    frame_normals = torch.gather(normals, 2, fidx[:, None].expand(R, 3, f))  # (R, 3, f)
    if frame_one_sided:  # the one-sided normals into their places there (a pixel's place in its row:
        # the number of fit pixels before it)
        kept = frame_px.view(-1).index_select(0, missing)  # (ALIGN_STRIDE may have left some out)
        missing, one_sided = missing[kept], one_sided[:, kept]
        place = (frame_px.cumsum(1) - 1).view(-1).index_select(0, missing)
        at_fit = (missing // n) * (3 * f) + place
        flat = frame_normals.view(-1)
        for c in range(3):
            flat.index_copy_(0, at_fit + c * f, one_sided[c])
    frame_normals, frame_weights = frame_normals.transpose(1, 2), fok.to(x.dtype)  # (R, f, 3), (R, f)
    if frame_strip_elongation is not None:  # one more normal per image, weighted by the strip's pixels
        frame_normals = torch.cat([frame_normals, strip_normal[:, None]], 1)
        frame_weights = torch.cat([frame_weights, strip_weight[:, None]], 1)
    frame = _align_to_normals(frame, frame_normals, frame_weights)
    xf, yf, zf = frame[..., 0], frame[..., 1], frame[..., 2]  # (R, J, 3)
    # step 3: each mode's side
    revolute = torch.tensor([t == "revolute" for t in joint_types])
    to_centre = anchor[:, None, None] - origin  # (R, J, M, 3)
    side_rev = torch.sign((to_centre * xf[:, :, None]).sum(-1))
    side_pri = torch.sign((voted_axis * zf[:, :, None]).sum(-1))
    side = torch.where(revolute[None, :, None], side_rev, side_pri)
    side = torch.where(side == 0, torch.ones_like(side), side)[..., None]
    # each door's pixels, gathered once for steps 5 and 6: (R * J, m) rows of the (R * n) valid pixels
    door = torch.stack([label == 1 + j for j in range(J)], 1) & ok[:, None]  # (R, J, n)
    didx, dok = compact_mask(door.flatten(0, 1))  # (R * J, m)
    m = didx.shape[1]
    door_at = (torch.arange(R).repeat_interleave(J)[:, None] * n + didx).view(-1)
    # step 5: door angles, over each door's pixels with a normal (the median by value: the other
    # pixels, which the selection leaves out, may sit anywhere in the row)
    with_normal = dok & has_normal.view(-1).index_select(0, door_at).view(R * J, m)
    door_px_at = at.index_select(0, door_at)  # the doors' pixels in the input
    door_normal = [x_flat[c * P:].index_select(0, door_px_at).view(R * J, m) for c in (4, 5, 6)]
    n_x, n_y = rows_dot(door_normal, xf.reshape(R * J, 3)), rows_dot(door_normal, yf.reshape(R * J, 3))
    angles = {}  # equal weights; NaN for prismatic joints
    per_door = lambda values: torch.where(revolute[None], lower_median(values, with_normal).view(R, J),  # noqa: E731
                                          torch.tensor(float("nan"), dtype=x.dtype))
    if "q" in door_angles or "q_folded" in door_angles:
        angle = torch.atan2(n_x.abs(), n_y.abs())  # (R * J, m) in [0, pi / 2]
    if "q" in door_angles:
        angles["q"] = per_door(angle)
    if "q_folded" in door_angles:
        # step 5, folded: each pixel's angle or its complement, whichever is nearer the voted angle (a
        # door's edge, or a door seen almost edge-on, shows normals at pi / 2 - q)
        complement = (math.pi / 2) - angle
        near = voted_q.reshape(R * J, 1)
        angles["q_folded"] = per_door(torch.where((complement - near).abs() < (angle - near).abs(), complement, angle))
    if "q_signed" in door_angles:
        # step 5, signed: the angle of each normal from y towards x, signs kept; the door's four faces
        # (outer and inner face, free and hinge edge) put it at -q, pi - q, pi / 2 - q and -pi / 2 - q,
        # so -angle mod pi / 2 is q on every face (for x = +xf; -q for x = -xf); its median on the
        # circle of period pi / 2 (about the pixels' circular mean, so a closed door's 0 and 89.9 degrees
        # are neighbours)
        # (u = -theta mod pi / 2 with theta = atan2(n . x, n . y): sin 4u = -sin 4 theta, cos 4u = cos 4 theta,
        # and u's remainder need not be taken before the one about the centre)
        theta = torch.atan2(n_x, n_y)  # (R * J, m)
        weight = with_normal.to(theta.dtype)
        four = 4.0 * theta
        centre = torch.atan2(-(weight * torch.sin(four)).sum(-1), (weight * torch.cos(four)).sum(-1))[:, None] / 4.0
        angles["q_signed"] = per_door(torch.remainder(math.pi / 4 - centre - theta, math.pi / 2) + centre - math.pi / 4)
    # step 6: the doors' points in the camera frame (m; component by component, (R * J, m) each: a
    # (R * J, m, 3) stack and product cost twice as much), their coordinates along the axis and their
    # image rows
    door_axis = (side[:, :, 0, 0, None] * zf).reshape(R * J, 3)
    door_anchor = anchor.repeat_interleave(J, 0)
    door_points = [x_flat[c * P:].index_select(0, door_px_at).view(R * J, m) * POINT_SCALE_M + door_anchor[:, c:c + 1]
                   for c in range(3)]
    along = rows_dot(door_points, door_axis)
    door_row = row.view(-1).index_select(0, door_at).view(R * J, m)
    door_mid, door_cut = _door_extent(along, door_row, dok, revolute, (R, J), H)
    if revolute.any():  # step 10's face (and steps 7 and 9's): doors that turn only
        face_normal, face_offset = door_face(door_normal, door_points, with_normal, zf.reshape(R * J, 3))
    else:
        face_normal, face_offset = x.new_zeros(R * J, 3), x.new_full((R * J,), float("nan"))
    nan = torch.tensor(float("nan"), dtype=x.dtype)
    face_m = torch.where(revolute[None], face_offset.view(R, J), nan)
    out = {"axis": side * zf[:, :, None], "xaxis": side * xf[:, :, None], **angles, "box_x": xf,
           "door_px": with_normal.sum(-1).view(R, J).to(x.dtype), "frame_px": count.to(x.dtype),
           "door_mid": door_mid, "door_cut": door_cut,
           "door_face_normal": face_normal.view(R, J, 3), "door_face_m": face_m}
    if not revolute.all():  # step 11: the drawers' fronts, from the same pixels
        door_col = (idx % W).view(-1).index_select(0, door_at).view(R * J, m)
        front = drawer_front(door_points, door_normal, with_normal & ~revolute.repeat(R)[:, None], door_row, door_col,
                             frame.reshape(R * J, 3, 3), door_anchor, (H, W))
        out.update({k: v.view(R, J, *v.shape[1:]) for k, v in front.items()})
        # the shell's edge, from every valid pixel (the segmentation's labels are a quarter of the
        # resolution, too coarse for an edge)
        points = [x_flat[c * P:].index_select(0, at).view(R, n) * POINT_SCALE_M + anchor[:, c:c + 1] for c in range(3)]
        out["shell_front_m"] = torch.stack([
            shell_front(points, normals.unbind(1), has_normal, frame[:, j], out["front_axis"][:, j], out["front_m"][:, j])
            if joint_types[j] == "prismatic" else torch.full((R,), float("nan"), dtype=x.dtype) for j in range(J)], 1)
    if handles:  # steps 7 and 9: the revolute doors' handles, from the same pixels
        measured = dok & revolute.repeat(R)[:, None]
        found = door_handles(door_points, door_normal, measured, door_row, door_axis, H, face=(face_normal, face_offset))
        out.update({k: v.view(R, J, *v.shape[1:]) for k, v in found.items()})
    return out


def drawer_front(points: list, normals: list, real: torch.Tensor, row: torch.Tensor, col: torch.Tensor,
                 frame: torch.Tensor, anchor: torch.Tensor, image_hw: tuple[int, int]) -> dict:
    """Step 11's measurements of each part (rows R of the gathered part pixels): ``points`` and
    ``normals`` (three (R, m) components each, camera frame, m), which of them are ``real`` with a
    normal (R, m), their image rows and columns (R, m), the parts' box frames (R, 3, 3: columns x,
    y, z) and the objects' anchors (R, 3).  The front's pixels: a normal within
    :data:`FRONT_MAX_DEG` of ``z`` and a coordinate along ``zc`` (``z`` turned to face the camera,
    from the anchor) within :data:`FRONT_BAND_M` of the :data:`FRONT_TOP_QUANTILE` quantile from the
    front.  Returns ``front_axis`` (R, 3) ``zc``, ``front_m`` (R) their median coordinate along it
    (NaN with fewer than :data:`FRONT_MIN_PX`), ``front_centre`` (R, 3) the point whose coordinates
    along ``x`` and ``y`` are the middles of their :data:`DOOR_EXTENT_QUANTILE` quantiles (and 0
    along ``z``), and ``front_cut`` (R) 1.0 where one of them lies within an output pixel of the
    image's border (the extent is then the image's, not the front's)."""
    H, W = image_hw
    x, y, z = frame.unbind(-1)  # (R, 3) each
    toward = torch.where((z * anchor).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(z.dtype)  # (R, 1)
    zc = toward * z
    facing = real & (rows_dot(normals, zc).abs() > math.cos(math.radians(FRONT_MAX_DEG)))
    along = rows_dot(points, zc)
    top = _quantile_pair(along, facing, FRONT_TOP_QUANTILE)[1][:, None]
    band = facing & (along >= top - FRONT_BAND_M)
    enough = band.sum(-1) >= FRONT_MIN_PX
    nan = torch.tensor(float("nan"), dtype=along.dtype)
    front = torch.where(enough, lower_median(along, band), nan)
    mids = []
    for a in (x, y):
        lo, hi = _quantile_pair(rows_dot(points, a), band, DOOR_EXTENT_QUANTILE)
        mids.append(torch.where(enough, 0.5 * (lo + hi), nan))
    centre = mids[0][:, None] * x + mids[1][:, None] * y
    s = OUTPUT_STRIDE
    near_border = (row <= s) | (row >= H - 1 - s) | (col <= s) | (col >= W - 1 - s)
    cut = (band & near_border).any(-1)
    return {"front_axis": zc, "front_m": front, "front_centre": centre, "front_cut": cut.to(along.dtype)}


def shell_front(points: list, normals: Sequence, real: torch.Tensor, frame: torch.Tensor, front_axis: torch.Tensor,
                front_m: torch.Tensor) -> torch.Tensor:
    """Step 11's shell edge (R,) m along ``front_axis`` (R, 3): of the image's pixels (``points`` and
    ``normals``: three (R, n) components each, camera frame, m; ``real`` those with a normal (R, n)),
    on each box face parallel to the axis (a normal within :data:`SHELL_FACE_MAX_DEG` of ``x``,
    ``-x``, ``y`` or ``-y`` of ``frame`` (R, 3, 3), within :data:`SHELL_FLUSH_M` of its outermost
    plane) and further behind the front's plane ``front_m`` (R) than :data:`DRAWER_PANEL_M` plus
    :data:`SHELL_PANEL_MARGIN_M`, the largest coordinate along the axis, read on the face with the
    most such pixels; NaN where no face has :data:`SHELL_MIN_PX`."""
    along = rows_dot(points, front_axis)
    behind_front = along < (front_m - DRAWER_PANEL_M - SHELL_PANEL_MARGIN_M)[:, None]  # False where front_m is NaN
    cos = math.cos(math.radians(SHELL_FACE_MAX_DEG))
    best_count = torch.zeros(len(along), dtype=torch.long)
    best = torch.full((len(along),), float("nan"), dtype=along.dtype)
    for axis in (frame[..., 0], -frame[..., 0], frame[..., 1], -frame[..., 1]):
        face = real & (rows_dot(normals, axis) > cos)
        out_m = rows_dot(points, axis)
        plane = _quantile_pair(out_m, face, SHELL_PLANE_QUANTILE)[1][:, None]  # NaN without face pixels: none is flush
        shell = face & ((out_m - plane).abs() < SHELL_FLUSH_M) & behind_front
        count = shell.sum(-1)
        edge = torch.where(shell, along, -float("inf")).amax(-1)
        take = (count >= SHELL_MIN_PX) & (count > best_count)
        best = torch.where(take, edge, best)
        best_count = torch.where(take, count, best_count)
    return best


def _door_extent(along: torch.Tensor, row: torch.Tensor, real: torch.Tensor, revolute: torch.Tensor,
                 shape: tuple[int, int], H: int) -> tuple:
    """Step 6: each door's mid-height along its axis (``shape`` (B, J), m) and whether it is cut off
    (B, J), from its pixels' coordinates along the axis (B * J, m) m, image rows (B * J, m) and
    which of them are real (B * J, m)."""
    B, J = shape
    lo, hi = (v.view(B, J) for v in _quantile_pair(along, real, DOOR_EXTENT_QUANTILE))
    enough = revolute[None] & (real.sum(-1).view(B, J) >= DOOR_EXTENT_MIN_PX)
    mid = torch.where(enough, 0.5 * (lo + hi), torch.full_like(lo, float("nan")))
    top = torch.where(real, row, H).amin(-1).view(B, J)
    bottom = torch.where(real, row, -1).amax(-1).view(B, J)
    cut = (top <= OUTPUT_STRIDE) | (bottom >= H - 1 - OUTPUT_STRIDE)
    return mid, cut.to(along.dtype)


def hinge_offset_angle(radius_m: np.ndarray, hinge_offset_m: float) -> np.ndarray:
    """Step 4: the turn (rad) about ``z`` from the box face's direction to the door centre's."""
    return np.arctan2(hinge_offset_m, np.maximum(radius_m, MIN_RADIUS_M))


def frame_turn_deg(axis_a: np.ndarray, xaxis_a: np.ndarray, axis_b: np.ndarray, xaxis_b: np.ndarray) -> np.ndarray:
    """How far apart two frames' lines are (deg): the larger of the angles between their axis
    lines and between their x lines, signs ignored (a frame and its mirrored side are 0 apart)."""
    def line_angle(a, b):
        cos = np.abs((a * b).sum(-1)) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-12)
        return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))

    return np.maximum(line_angle(axis_a, axis_b), line_angle(xaxis_a, xaxis_b))


def apply_refinement(m: dict, r: dict, refinement: "Refinement | None", joint_types) -> dict:
    """Mode arrays ``m`` (numpy, :func:`vote_modes` keys) with the refinement ``r`` (numpy,
    :func:`refined_quantities`; None when ``refinement`` is None or not :attr:`Refinement.needed`)
    applied as ``refinement`` says; ``m`` itself when nothing changes."""
    if refinement is None or not refinement.needed:
        return m
    out = dict(m)
    revolute = np.array([t == "revolute" for t in joint_types])
    if refinement.frame:
        axis, xaxis = r["axis"].copy(), r["xaxis"].copy()
        angle = hinge_offset_angle(m["part_offset"][..., 0], refinement.hinge_offset_m)
        angle = np.where(revolute[None, :, None], angle, 0.0)
        xaxis = rotate_about(torch.from_numpy(xaxis), torch.from_numpy(axis), torch.from_numpy(angle)).numpy()
        if refinement.max_turn_deg is not None:
            keep = frame_turn_deg(m["axis"], m["xaxis"], r["axis"], r["xaxis"]) > refinement.max_turn_deg
            axis = np.where(keep[..., None], m["axis"], axis)
            xaxis = np.where(keep[..., None], m["xaxis"], xaxis)
        out["axis"], out["xaxis"] = axis, xaxis
    if refinement.min_door_px is not None:
        out["q"] = door_angle(m["q"], r, refinement, out.get("xaxis"), revolute)
    if refinement.door_extent and "door_mid" in r:
        z = r["axis"][:, :, :1]  # (B, J, 1, 3): one line per joint
        shift = r["door_mid"][..., None] - (m["origin"] * z).sum(-1)  # (B, J, M)
        use = revolute[None, :, None] & (r["door_cut"][..., None] == 0) & np.isfinite(shift)
        if refinement.door_extent_gate_m is not None:
            use &= np.abs(shift) < refinement.door_extent_gate_m
        out["origin"] = m["origin"] + np.where(use, shift, 0.0)[..., None] * z
    out = apply_handle_height(out, r, refinement.handle_height_gate_m, joint_types, refinement.handle_cut_bars)
    sided = apply_handle_side(out, r, refinement.handle_max_q_deg, refinement.handle_min_px, joint_types)
    if sided is not out and refinement.min_door_px is not None and refinement.door_angle_signed:
        sided = dict(sided)  # a mirrored mode's x is turned round: its door angle is read again
        sided["q"] = door_angle(m["q"], r, refinement, sided["xaxis"], revolute)
    if refinement.door_face_gate_m is not None and "door_face_m" in r:
        sided = dict(sided)
        sided["origin"] = door_face_origin(sided, r, refinement.door_face_gate_m, refinement.door_face_offsets_m,
                                           revolute)
    if refinement.drawer_centre_gate_m is not None and "front_centre" in r:
        sided = dict(sided)
        sided["origin"] = drawer_centre_origin(sided, r, refinement.drawer_centre_gate_m, ~revolute)
    if refinement.drawer_shell_gate_m is not None and "shell_front_m" in r:
        sided = dict(sided)
        sided["origin"] = drawer_shell_origin(sided, r, refinement.drawer_shell_gate_m, refinement.drawer_shell_offset_m,
                                              ~revolute)
    if refinement.drawer_front_gate_m is not None and "front_m" in r:
        sided = dict(sided)
        sided["q"] = drawer_front_q(sided, r, refinement.drawer_front_gate_m, refinement.drawer_front_offset_m,
                                    ~revolute)
    return sided


#: Step 11 reads a mode's ``q`` from the front's plane only where the mode's axis is within this
#: angle (deg) of the front's (a mode whose axis points into the body reads nothing).
FRONT_AXIS_MAX_DEG = 25.0


def drawer_front_travel(mm: dict, r: dict, offset_m: float) -> np.ndarray:
    """Step 11: each vote mode's travel (B, J, M) m from its origin along its axis to the drawer
    front's plane (``r["front_m"]`` along ``r["front_axis"]``) less ``offset_m``: the ``q`` that puts
    the front's outer face there.  NaN where the plane was not measured or the mode's axis is not
    within :data:`FRONT_AXIS_MAX_DEG` of the front's."""
    a = mm["axis"] / np.maximum(np.linalg.norm(mm["axis"], axis=-1, keepdims=True), 1e-12)
    zc = r["front_axis"][:, :, None]  # (B, J, 1, 3)
    cos = (a * zc).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        travel = (r["front_m"][..., None] - offset_m - (mm["origin"] * zc).sum(-1)) / cos
    return np.where(cos > math.cos(math.radians(FRONT_AXIS_MAX_DEG)), travel, np.nan)


def drawer_front_q(mm: dict, r: dict, gate_m: float, offset_m: float, prismatic: np.ndarray) -> np.ndarray:
    """Step 11: the vote modes' ``q`` (B, J, M) m, :func:`drawer_front_travel` where it is finite and
    within ``gate_m`` of the mode's ``q`` (prismatic joints only)."""
    q = drawer_front_travel(mm, r, offset_m)
    with np.errstate(invalid="ignore"):
        use = prismatic[None, :, None] & np.isfinite(q) & (np.abs(q - mm["q"]) < gate_m)
    return np.where(use, q, mm["q"])


def drawer_shell_origin(mm: dict, r: dict, gate_m: float, offset_m: float, prismatic: np.ndarray) -> np.ndarray:
    """Step 11: the vote modes' origins (B, J, M, 3) moved along the front's axis to the shell's edge
    (``r["shell_front_m"]``) plus ``offset_m`` where the move is shorter than ``gate_m`` (prismatic
    joints only).  The closed drawer's outer face is there (the template's panel, 2 cm in front of
    the shell; the fitted offset also holds the edge pixels' bias)."""
    zc = r["front_axis"][:, :, None]  # (B, J, 1, 3)
    with np.errstate(invalid="ignore"):
        shift = (r["shell_front_m"] + offset_m)[..., None] - (mm["origin"] * zc).sum(-1)  # (B, J, M)
        use = prismatic[None, :, None] & np.isfinite(shift) & (np.abs(shift) < gate_m)
    return mm["origin"] + np.where(use, shift, 0.0)[..., None] * zc


def drawer_centre_origin(mm: dict, r: dict, gate_m: float, prismatic: np.ndarray) -> np.ndarray:
    """Step 11: the vote modes' origins (B, J, M, 3) moved across the front's axis onto its centre
    (``r["front_centre"]``) where the front is not cut by the image's border and the move is
    shorter than ``gate_m`` (prismatic joints only)."""
    zc = r["front_axis"][:, :, None]  # (B, J, 1, 3)
    centre = r["front_centre"][:, :, None]
    d = centre - mm["origin"]
    shift = d - (d * zc).sum(-1, keepdims=True) * zc  # across the axis only
    with np.errstate(invalid="ignore"):
        use = (prismatic[None, :, None] & (r["front_cut"][..., None] == 0) & np.isfinite(shift).all(-1)
               & (np.linalg.norm(shift, axis=-1) < gate_m))
    return mm["origin"] + np.where(use[..., None], shift, 0.0)


def door_face_side(mm: dict, r: dict) -> np.ndarray:
    """Step 10: the cosine (B, J, M) between each door's face normal (``r["door_face_normal"]``)
    and each vote mode's door ``y``: the frame's ``y = z x x`` turned by the mode's ``q`` about its
    axis ``z`` (mode arrays ``mm``: ``axis``, ``xaxis``, ``q``).  Near 1 the face seen is the door's
    outer face, near -1 its inner face."""
    z = mm["axis"] / np.maximum(np.linalg.norm(mm["axis"], axis=-1, keepdims=True), 1e-12)
    y = np.cross(z, mm["xaxis"])
    y = y / np.maximum(np.linalg.norm(y, axis=-1, keepdims=True), 1e-12)
    y_door = rotate_about(torch.from_numpy(y), torch.from_numpy(z), torch.from_numpy(np.asarray(mm["q"], float))).numpy()
    return (r["door_face_normal"][:, :, None] * y_door).sum(-1)


def door_face_origin(mm: dict, r: dict, gate_m: float, offsets_m: tuple, revolute: np.ndarray) -> np.ndarray:
    """Step 10: the vote modes' origins (B, J, M, 3) moved along their door's face normal onto the
    face's plane plus ``offsets_m`` (outer face, inner face; m) where the face seen is one of them
    (:func:`door_face_side`, within :data:`DOOR_FACE_MAX_DEG`), its offset is known (not None) and
    the move is shorter than ``gate_m``."""
    side = door_face_side(mm, r)
    n = r["door_face_normal"][:, :, None]  # (B, J, 1, 3)
    known = [np.nan if v is None else v for v in offsets_m]  # a face never seen: no move
    plane = r["door_face_m"][..., None] + np.where(side > 0, known[0], known[1])
    with np.errstate(invalid="ignore"):
        shift = plane - (mm["origin"] * n).sum(-1)
        use = (revolute[None, :, None] & (np.abs(side) > math.cos(math.radians(DOOR_FACE_MAX_DEG)))
               & np.isfinite(shift) & (np.abs(shift) < gate_m))
    return mm["origin"] + np.where(use, shift, 0.0)[..., None] * n


def door_angle(voted_q: np.ndarray, r: dict, refinement: "Refinement", xaxis: np.ndarray | None, revolute: np.ndarray) -> np.ndarray:
    """Step 5 as ``refinement`` says: each vote mode's door angle (B, J, M) rad, the normal-based one
    (plain, folded or :func:`signed_door_angle` for the modes' x axes ``xaxis`` (B, J, M, 3), which only
    the signed one reads) where at least ``min_door_px`` door pixels have a normal and it lies within
    ``door_angle_gate_deg`` of the mode's voted angle ``voted_q`` (B, J, M); the voted angle elsewhere."""
    if refinement.door_angle_signed:
        q = signed_door_angle(r["q_signed"], r["box_x"], xaxis, voted_q)  # type: ignore[arg-type]  # given when signed
    else:
        q = np.broadcast_to((r["q_folded"] if refinement.door_angle_folded else r["q"])[..., None], voted_q.shape)
    with np.errstate(invalid="ignore"):
        use = revolute[None, :, None] & (r["door_px"] >= refinement.min_door_px)[..., None] & np.isfinite(q)
        if refinement.door_angle_gate_deg is not None:
            use &= np.abs(q - voted_q) < math.radians(refinement.door_angle_gate_deg)
    return np.where(use, q, voted_q)


def signed_door_angle(q_signed: np.ndarray, box_x: np.ndarray, xaxis: np.ndarray, near_q: np.ndarray) -> np.ndarray:
    """Step 5, signed: each vote mode's door angle (B, J, M) rad from :func:`refined_quantities`'
    ``q_signed`` (B, J; the angle modulo ``pi / 2`` for the frame whose x is the box frame's ``box_x``
    (B, J, 3)), the modes' x axes ``xaxis`` (B, J, M, 3: where a mode's x points the other way, its
    angle is ``-q_signed``) and their voted angles ``near_q`` (B, J, M): of the angles equal modulo
    ``pi / 2``, the one nearest the mode's vote.  The normals fix the angle up to quarter turns,
    which only a door near 0 or 90 degrees leaves to the votes."""
    side = np.where((xaxis * box_x[:, :, None]).sum(-1) < 0, -1.0, 1.0)
    base = side * q_signed[..., None]
    return base + np.round((near_q - base) / (math.pi / 2)) * (math.pi / 2)
