"""The dense estimator's fast inference stages against plain references: the network input
(``features.make_inputs``) against the whole-image formulas, the box-frame alignment against its
thresholded ``torch.where`` form, and the refined quantities (``refine.refined_quantities``) against
a loop over images and joints, on random scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from torch.nn import functional as F  # noqa: E402

from articulated_dataset.methods.dense import handle as DH
from articulated_dataset.methods.dense import refine as R
from articulated_dataset.methods.dense.aggregate import image_groups  # noqa: E402
from articulated_dataset.methods.dense.features import (  # noqa: E402
    HOLE_MAX_SPREAD_M,
    N_INPUT_CHANNELS,
    NORMAL_MAX_STEP_M,
    OUTPUT_STRIDE,
    POINT_SCALE_M,
    backproject_torch,
    make_inputs,
)


def _random_depth(rng: np.random.Generator, B: int, H: int, W: int,
                  dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth images of tilted planes with a step (a depth edge) and holes, one image without any
    return; and their intrinsics (``dtype``)."""
    v, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    depth = np.zeros((B, H, W))
    for b in range(B - 1):
        d = 1.0 + rng.uniform(0, 1) + rng.uniform(-0.02, 0.02) * u + rng.uniform(-0.02, 0.02) * v
        d = d + np.where(u > rng.integers(W // 3, W), 0.3, 0.0)  # a step: no normal across it
        keep = rng.uniform(size=(H, W)) > 0.2
        keep &= (np.abs(u - rng.uniform(0, W)) < rng.uniform(W / 4, W)) & (np.abs(v - rng.uniform(0, H)) < rng.uniform(H / 4, H))
        depth[b] = np.where(keep, d, 0.0)
    f = rng.uniform(20, 40, B)
    K = np.zeros((B, 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = f, f * 1.1, (W - 1) / 2, (H - 1) / 2 + 1, 1
    return torch.tensor(depth, dtype=dtype), torch.tensor(K, dtype=dtype)


def _reference_fill(depth: torch.Tensor) -> torch.Tensor:
    """features.fill_holes as a whole-image formula: every pixel without a return whose four
    neighbours have returns within HOLE_MAX_SPREAD_M of each other takes their mean."""
    d = depth.clone()
    around = torch.stack([d[:, :-2, 1:-1], d[:, 2:, 1:-1], d[:, 1:-1, :-2], d[:, 1:-1, 2:]])
    hole = (d[:, 1:-1, 1:-1] <= 0) & (around > 0).all(0) & (around.amax(0) - around.amin(0) < HOLE_MAX_SPREAD_M)
    d[:, 1:-1, 1:-1] = torch.where(hole, around.mean(0), d[:, 1:-1, 1:-1])
    return d


def _reference_inputs(depth: torch.Tensor, K: torch.Tensor) -> dict:
    """The network input written as whole-image formulas (no lists of pixels)."""
    depth = _reference_fill(depth)
    B, H, W = depth.shape
    valid = depth > 0
    w = valid.to(depth.dtype)
    pts = backproject_torch(depth * w, K)
    anchor = pts.sum((2, 3)) / w.sum((1, 2)).clamp_min(1.0)[:, None]
    relative = torch.where(valid[:, None], (pts - anchor[:, :, None, None]) / POINT_SCALE_M, 0.0)
    normals = torch.zeros(B, 3, H, W)
    dx = pts[:, :, 1:-1, 2:] - pts[:, :, 1:-1, :-2]
    dy = pts[:, :, 2:, 1:-1] - pts[:, :, :-2, 1:-1]
    max2 = (2 * NORMAL_MAX_STEP_M) ** 2
    ok = (dx[:, 0] * dx[:, 0] + dx[:, 1] * dx[:, 1] + dx[:, 2] * dx[:, 2] < max2)
    ok &= (dy[:, 0] * dy[:, 0] + dy[:, 1] * dy[:, 1] + dy[:, 2] * dy[:, 2] < max2)
    ok &= valid[:, 1:-1, 2:] & valid[:, 1:-1, :-2] & valid[:, 2:, 1:-1] & valid[:, :-2, 1:-1] & valid[:, 1:-1, 1:-1]
    n = torch.stack([dx[:, 1] * dy[:, 2] - dx[:, 2] * dy[:, 1], dx[:, 2] * dy[:, 0] - dx[:, 0] * dy[:, 2],
                     dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0]], 1)
    scale = torch.rsqrt((n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2]).clamp_min(1e-24))
    scale = torch.where(n[:, 0] * scale > 0, -scale, scale)
    normals[:, :, 1:-1, 1:-1] = torch.where(ok[:, None], n * scale[:, None], 0.0)
    pooled = F.avg_pool2d(torch.cat([pts, w[:, None]], 1), OUTPUT_STRIDE, ceil_mode=True)
    u = torch.linspace(-1, 1, W).view(1, 1, 1, W).expand(B, 1, H, W)
    v = torch.linspace(-1, 1, H).view(1, 1, H, 1).expand(B, 1, H, W)
    x = torch.cat([relative, w[:, None], normals, u, v], 1)
    return {"x": x, "anchor": anchor, "points_out": pooled[:, :3] / pooled[:, 3:4].clamp_min(1e-6),
            "weight_out": pooled[:, 3]}


@pytest.mark.parametrize("hw", [(24, 32), (22, 30)])  # windows that divide the image, and ones that do not
def test_network_input_matches_the_whole_image_formulas(hw):
    depth, K = _random_depth(np.random.default_rng(3), 6, *hw)
    ref = _reference_inputs(depth, K)
    filled = _reference_fill(depth)
    assert ((filled > 0) & (depth <= 0)).sum() > 10  # holes are filled ...
    assert (filled <= 0).sum() > 100  # ... not the other gaps
    assert (ref["x"][:, 4:7].abs().sum(1) > 0.5).sum() > 200  # normals exist
    assert (ref["weight_out"] == 0).any() and ((ref["weight_out"] > 0) & (ref["weight_out"] < 1)).any()
    got = make_inputs(depth, K)
    stale = torch.full((6, N_INPUT_CHANNELS, *hw), 7.0)  # a previous batch's input, written over
    again = make_inputs(depth, K, out=stale)
    assert again["x"].data_ptr() == stale.data_ptr()
    for out in (got, again):
        assert set(out) == set(ref)
        for key in ref:
            assert out[key].shape == ref[key].shape, key
            assert torch.equal(out[key], ref[key]), key  # the same numbers, not merely close


def _reference_alignment(frame: torch.Tensor, normals: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Step 2 with the matched signed axes' weights as ``torch.where`` of the thresholds."""
    B, J = frame.shape[:2]
    for inlier_deg in R.INLIER_ANGLES_DEG:
        cos_in = math.cos(math.radians(inlier_deg))
        c = frame.transpose(-1, -2).reshape(B, J * 3, 3) @ normals.transpose(1, 2).contiguous()
        w = weights[:, None]
        signed_w = torch.where(c > cos_in, w, torch.where(c < -cos_in, -w, 0.0))
        H = (signed_w @ normals).view(B, J, 3, 3) + R.PRIOR_WEIGHT_PX * frame.transpose(-1, -2)
        U, _, Vh = torch.linalg.svd(H)
        d = torch.sign(torch.linalg.det(Vh.transpose(-1, -2) @ U.transpose(-1, -2)))
        D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
        frame = Vh.transpose(-1, -2) @ D @ U.transpose(-1, -2)
    return frame


def _random_frames(gen: torch.Generator, *shape) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(*shape, 3, 3, generator=gen))
    return q * torch.linalg.det(q)[..., None, None].sign()  # rotations (det +1)


def test_frame_alignment_matches_the_thresholded_reference():
    gen = torch.Generator().manual_seed(5)
    B, J, P = 4, 2, 500
    frame = _random_frames(gen, B, J)
    # normals near the first joint's signed axes (inliers at every angle) plus uniform ones, some absent
    axes = frame[:, 0].transpose(1, 2)[:, torch.randint(0, 3, (P,), generator=gen)]  # (B, P, 3)
    signs = torch.randint(0, 2, (B, P, 1), generator=gen) * 2.0 - 1.0
    normals = F.normalize(signs * axes + 0.08 * torch.randn(B, P, 3, generator=gen), dim=-1)
    normals[:, ::3] = F.normalize(torch.randn(B, len(range(0, P, 3)), 3, generator=gen), dim=-1)
    normals[:, ::7] = 0.0
    weights = (torch.rand(B, P, generator=gen) > 0.3).float()
    got = R._align_to_normals(frame, normals, weights)
    ref = _reference_alignment(frame, normals, weights)
    # the same matched axes; the sums' order differs (the products' layouts), so the last bits may
    torch.testing.assert_close(got, ref, atol=1e-6, rtol=0.0)
    assert (got - frame).abs().max() > 1e-3  # the alignment did move the frames


def _reference_one_sided(x: torch.Tensor, allowed: torch.Tensor, v: int, u: int):
    """Pixel (v, u)'s one-sided normal of ``features.one_sided_normals`` from the image's input ``x``
    (C, H, W), written out pixel by pixel: along each axis the shorter difference to a valid,
    allowed neighbour within NORMAL_MAX_STEP_M (the forward one on a tie); None without one."""
    from articulated_dataset.methods.dense.features import NORMAL_MAX_STEP_M

    H, W = x.shape[1:]
    p = x[0:3, v, u]
    tangents = []
    for dv, du in ((0, 1), (1, 0)):
        best = None
        for sign in (1, -1):
            vv, uu = v + sign * dv, u + sign * du
            if not (0 <= vv < H and 0 <= uu < W) or x[3, vv, uu] <= 0 or not allowed[vv, uu]:
                continue
            d = (x[0:3, vv, uu] - p) if sign > 0 else (p - x[0:3, vv, uu])
            length2 = float((d * d).sum())
            if length2 < (NORMAL_MAX_STEP_M / POINT_SCALE_M) ** 2 and (best is None or length2 < best[0]):
                best = (length2, d)
        if best is None:
            return None
        tangents.append(best[1])
    n = torch.linalg.cross(tangents[0], tangents[1])
    if float((n * n).sum()) <= 1e-24:
        return None
    n = n / n.norm()
    return -n if n[0] > 0 else n


def _reference_shell(points, normals, real, xf, yf, zc, front_m) -> float:
    """refine.shell_front for one image's pixels (n, 3), written out face by face."""
    along, best, edge = points @ zc, 0, float("nan")
    behind = along < front_m - R.DRAWER_PANEL_M - R.SHELL_PANEL_MARGIN_M
    for a in (xf, -xf, yf, -yf):
        face = real & (normals @ a > math.cos(math.radians(R.SHELL_FACE_MAX_DEG)))
        if face.any():
            shell = face & ((points @ a - torch.quantile((points @ a)[face], 1 - R.SHELL_PLANE_QUANTILE)).abs() < R.SHELL_FLUSH_M) & behind
            if shell.sum() >= max(R.SHELL_MIN_PX, best + 1):
                best, edge = int(shell.sum()), float(along[shell].max())
    return edge


def test_shell_edge_matches_a_face_by_face_loop():
    """refine.shell_front on rows of pixels with box faces in every direction (noisy normals, faces
    at random offsets, some pixels without a normal, a row without a front) against the loop."""
    gen = torch.Generator().manual_seed(3)
    R_, n = 8, 400
    frames = torch.linalg.qr(torch.randn(R_, 3, 3, generator=gen, dtype=torch.float64))[0]
    frames[:, :, 2] *= torch.det(frames)[:, None]  # right-handed
    axis_of = torch.randint(0, 5, (R_, n), generator=gen)  # 0-3: +-x, +-y faces; 4: the front (z)
    dirs = torch.stack([frames[..., 0], -frames[..., 0], frames[..., 1], -frames[..., 1], -frames[..., 2]], 1)  # (R, 5, 3)
    normals = F.normalize(dirs.gather(1, axis_of[..., None].expand(R_, n, 3)) + 0.15 * torch.randn(R_, n, 3, generator=gen,
                                                                                                    dtype=torch.float64), dim=-1)
    # points: on each face's plane (offset 0.2 m, or 2 cm in for a set-in tray face) at a random depth along z
    along = -1.5 - 0.4 * torch.rand(R_, n, generator=gen, dtype=torch.float64)
    offset = 0.2 - 0.022 * (torch.rand(R_, n, generator=gen) < 0.3)
    lateral = 0.1 * torch.randn(R_, n, 3, generator=gen, dtype=torch.float64)
    normal_dir = dirs.gather(1, axis_of[..., None].expand(R_, n, 3))
    pull = -frames[..., 2]
    points = (lateral - (lateral * normal_dir).sum(-1, keepdim=True) * normal_dir
              - (lateral * pull[:, None]).sum(-1, keepdim=True) * pull[:, None]
              + offset[..., None] * normal_dir + along[..., None] * pull[:, None])
    real = torch.rand(R_, n, generator=gen) > 0.1
    front_m = torch.full((R_,), -1.45, dtype=torch.float64)
    front_m[3] = float("nan")
    got = R.shell_front(list(points.permute(2, 0, 1)), list(normals.permute(2, 0, 1)), real, frames, pull, front_m)
    want = torch.tensor([_reference_shell(points[i], normals[i], real[i], frames[i, :, 0], frames[i, :, 1], pull[i],
                                          front_m[i]) for i in range(R_)], dtype=torch.float64)
    assert torch.isfinite(want).sum() >= R_ - 1 and torch.isnan(want[3])
    assert torch.equal(got.isnan(), want.isnan()) and torch.allclose(got.nan_to_num(), want.nan_to_num(), atol=1e-9)


def _reference_refinement(parts: dict, inputs: dict, modes: dict, joint_types, one_sided: bool = False) -> dict:
    """Steps 1-3, 5, 6, 10 and 11 image by image and joint by joint, from the whole-image input (with
    ``one_sided``, step 2 with the one-sided normals of the pixels without one: _reference_one_sided)."""
    x = inputs["x"]
    B, _, H, W = x.shape
    J = len(joint_types)
    frames = R._sign_free_frame(parts, inputs["weight_out"] > 0)
    label_out = parts["seg"].argmax(1)  # (B, h, w): 0 body, 1 + j part j
    label = label_out.repeat_interleave(OUTPUT_STRIDE, 1).repeat_interleave(OUTPUT_STRIDE, 2)[:, :H, :W]
    nan = float("nan")
    voted_q = (modes["weight"] * modes["q"]).sum(-1)  # (B, J)
    out = {"axis": torch.zeros(B, J, modes["origin"].shape[2], 3), "q": torch.full((B, J), nan), "q_folded": torch.full((B, J), nan),
           "q_signed": torch.full((B, J), nan), "box_x": torch.zeros(B, J, 3),
           "door_px": torch.zeros(B, J), "frame_px": torch.zeros(B), "door_mid": torch.full((B, J), nan),
           "door_cut": torch.zeros(B, J), "door_face_normal": torch.zeros(B, J, 3), "door_face_m": torch.full((B, J), nan)}
    out["xaxis"] = out["axis"].clone()
    prismatic = "prismatic" in joint_types
    if prismatic:
        out.update({"front_axis": torch.zeros(B, J, 3), "front_m": torch.full((B, J), nan),
                    "front_centre": torch.zeros(B, J, 3), "front_cut": torch.zeros(B, J),
                    "shell_front_m": torch.full((B, J), nan)})
    rows = torch.arange(H)[:, None].expand(H, W)
    cols_all = torch.arange(W)[None, :].expand(H, W)
    for b in range(B):
        valid = x[b, 3] > 0
        normals, relative = x[b, 4:7].permute(1, 2, 0)[valid], x[b, 0:3].permute(1, 2, 0)[valid]  # (n, 3)
        lab, row, cols = label[b][valid], rows[valid], cols_all[valid]
        has_normal = (normals * normals).sum(-1) > R.MIN_NORMAL_NORM**2
        frame_px = lab == 0
        for j, t in enumerate(joint_types):
            if t == "prismatic":
                frame_px |= lab == 1 + j
        out["frame_px"][b] = frame_px.sum()
        weights = (frame_px & has_normal).to(normals.dtype)
        fit_normals = normals
        if one_sided:
            allowed = torch.zeros(H, W, dtype=torch.bool)
            allowed[valid] = frame_px
            fit_normals = normals.clone()
            vu = valid.nonzero()
            for k in (frame_px & ~has_normal).nonzero()[:, 0].tolist():
                n = _reference_one_sided(x[b], allowed, int(vu[k, 0]), int(vu[k, 1]))
                if n is not None:
                    fit_normals[k], weights[k] = n, 1.0
        frame = _reference_alignment(frames[b:b + 1], fit_normals[None], weights[None])[0]  # (J, 3, 3)
        points = relative * POINT_SCALE_M + inputs["anchor"][b]
        for j, t in enumerate(joint_types):
            xf, yf, zf = frame[j, :, 0], frame[j, :, 1], frame[j, :, 2]
            if t == "revolute":
                side = torch.sign(((inputs["anchor"][b] - modes["origin"][b, j]) * xf).sum(-1))
            else:
                side = torch.sign((modes["axis"][b, j] * zf).sum(-1))
            side = torch.where(side == 0, 1.0, side)[:, None]  # (M, 1)
            out["axis"][b, j], out["xaxis"][b, j] = side * zf, side * xf
            out["box_x"][b, j] = xf
            door = lab == 1 + j
            with_normal = door & has_normal
            out["door_px"][b, j] = with_normal.sum()
            if t == "revolute" and with_normal.any():
                n = normals[with_normal]
                angles = torch.sort(torch.atan2((n @ xf).abs(), (n @ yf).abs())).values
                out["q"][b, j] = angles[(len(angles) + 1) // 2 - 1]  # the lower median
                near = voted_q[b, j]
                folded = torch.sort(torch.where((math.pi / 2 - angles - near).abs() < (angles - near).abs(),
                                                math.pi / 2 - angles, angles)).values
                out["q_folded"][b, j] = folded[(len(folded) + 1) // 2 - 1]
                # signed: -atan2(n.x, n.y) modulo pi / 2, its lower median about the circular mean
                u = np.remainder(-np.arctan2((n @ xf).double().numpy(), (n @ yf).double().numpy()), math.pi / 2)
                centre = np.angle(np.exp(4j * u).sum()) / 4
                around = np.sort(centre + np.remainder(u - centre + math.pi / 4, math.pi / 2) - math.pi / 4)
                out["q_signed"][b, j] = float(around[(len(around) + 1) // 2 - 1])
            # step 10: the face's normal and offset, from every FACE_STRIDE-th door pixel (image order)
            read = torch.zeros_like(door)
            read[door.nonzero()[:: DH.FACE_STRIDE, 0]] = True
            face_px = read & has_normal
            if face_px.any():
                n = normals[face_px]
                n = torch.where(((n * points[face_px]).sum(-1) > 0)[:, None], -n, n)  # facing the camera along the ray
                perpendicular = lambda v: F.normalize(v - (v @ zf) * zf, dim=0, eps=1e-12)  # noqa: E731
                u = perpendicular(n.sum(0))
                for angle_deg in DH.FACE_INLIER_DEG:
                    inlier = n @ u > math.cos(math.radians(angle_deg))
                    u = perpendicular(n[inlier].sum(0))
                out["door_face_normal"][b, j] = u
                offsets = torch.sort(points[face_px][inlier] @ u).values
                if t == "revolute" and inlier.sum() >= DH.FACE_MIN_PX:
                    out["door_face_m"][b, j] = offsets[(len(offsets) + 1) // 2 - 1]
            if door.any():
                along = points[door] @ (side[0, 0] * zf)
                lo, hi = torch.quantile(along, R.DOOR_EXTENT_QUANTILE), torch.quantile(along, 1 - R.DOOR_EXTENT_QUANTILE)
                if t == "revolute" and door.sum() >= R.DOOR_EXTENT_MIN_PX:
                    out["door_mid"][b, j] = 0.5 * (lo + hi)
                out["door_cut"][b, j] = float(row[door].min() <= OUTPUT_STRIDE or row[door].max() >= H - 1 - OUTPUT_STRIDE)
            if prismatic:  # step 11: the drawer's front, from its pixels facing along the axis
                zc = -zf if float(zf @ inputs["anchor"][b]) > 0 else zf
                out["front_axis"][b, j] = zc
                facing = door & has_normal & ((normals @ zc).abs() > math.cos(math.radians(R.FRONT_MAX_DEG)))
                if t == "prismatic" and facing.any():
                    along = points[facing] @ zc
                    band = along >= torch.quantile(along, 1 - R.FRONT_TOP_QUANTILE) - R.FRONT_BAND_M
                    if band.sum() >= R.FRONT_MIN_PX:
                        front = torch.sort(along[band]).values
                        out["front_m"][b, j] = front[(len(front) + 1) // 2 - 1]
                        for a in (xf, yf):
                            u = points[facing][band] @ a
                            mid = 0.5 * (torch.quantile(u, R.DOOR_EXTENT_QUANTILE) + torch.quantile(u, 1 - R.DOOR_EXTENT_QUANTILE))
                            out["front_centre"][b, j] += mid * a
                    else:
                        out["front_centre"][b, j] = nan
                    r_, c_ = row[facing][band], cols[facing][band]
                    s = OUTPUT_STRIDE
                    out["front_cut"][b, j] = float(bool(((r_ <= s) | (r_ >= H - 1 - s) | (c_ <= s) | (c_ >= W - 1 - s)).any()))
                else:
                    out["front_centre"][b, j] = nan
                if t == "prismatic":  # the shell's edge, from every pixel on a face flush with the front's edges
                    out["shell_front_m"][b, j] = _reference_shell(points, normals, has_normal, xf, yf, zc,
                                                                  out["front_m"][b, j])
    return out


@pytest.fixture
def float64_default():
    """float64 for the tensors the test makes (its reference's too); the default restored after."""
    before = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(before)


@pytest.mark.parametrize("joint_types, one_sided", [(["revolute", "revolute"], False), (["prismatic", "revolute"], False),
                                                     (["revolute", "revolute"], True)])
def test_refined_quantities_match_a_loop_over_images(joint_types, one_sided, monkeypatch, float64_default):
    # in float64: the batch and the loop sum in different orders, which in float32 moves a nearly
    # degenerate frame fit (one-sided normals, an AMD EPYC's kernels) by 4e-4 rad in q
    rng = np.random.default_rng(11)
    gen = torch.Generator().manual_seed(11)
    B, H, W, J, M = 9, 32, 48, len(joint_types), 2
    depth, K = _random_depth(rng, B, H, W, torch.float64)
    depth[2, : H // 2] = 0.0  # an image whose doors may reach no edge
    inputs = make_inputs(depth, K)
    h, w = H // OUTPUT_STRIDE, W // OUTPUT_STRIDE
    seg = torch.randn(B, 1 + J, h, w, generator=gen) * 2
    seg[:, 0, :, : w // 3] += 3.0  # a body on the left
    # the votes' frames: z up (a door's hinge), a drawer's z along the camera's axis (its front, the planes, faces it)
    bias = torch.tensor([[3.0, 0, 0, 0, 3, 0] if t == "prismatic" else [0, 0, 3.0, 3, 0, 0] for t in joint_types])
    parts = {"seg": seg, "rot6": torch.randn(B, J, 6, h, w, generator=gen) + bias.view(1, J, 6, 1, 1),
             "conf": torch.randn(B, J, 3, h, w, generator=gen)}
    modes = {"origin": torch.randn(B, J, M, 3, generator=gen) + torch.tensor([1.5, 0, 0]),
             "axis": F.normalize(torch.randn(B, J, M, 3, generator=gen), dim=-1),
             "weight": torch.softmax(torch.randn(B, J, M, generator=gen), -1),
             "q": torch.rand(B, J, M, generator=gen) * (math.pi / 2)}
    monkeypatch.setattr(R, "image_groups", lambda counts: image_groups(counts, 4))  # several groups of images
    got = R.refined_quantities(parts, inputs, modes, joint_types, frame_one_sided=one_sided)
    ref = _reference_refinement(parts, inputs, modes, joint_types, one_sided)
    if one_sided:  # the one-sided normals turned the frames (else the test could not tell)
        central = R.refined_quantities(parts, inputs, modes, joint_types)
        assert not torch.allclose(central["box_x"], got["box_x"], atol=1e-4)
    assert set(got) == set(ref)
    assert torch.isfinite(ref["q"]).sum() >= 6 and torch.isfinite(ref["door_mid"]).sum() >= 4
    assert torch.isfinite(ref["door_face_m"]).sum() >= 4
    assert ref["door_cut"].sum() >= 1 and (ref["door_cut"] == 0).sum() >= 1
    if "prismatic" in joint_types:  # step 11 measured some fronts (the planes run out of these small images: cut)
        assert torch.isfinite(ref["front_m"]).sum() >= 3  # (no face here is parallel to the axis: see the next test)
    for key in ref:
        assert got[key].shape == ref[key].shape, key
        assert torch.equal(got[key].isnan(), ref[key].isnan()), key
        assert torch.allclose(got[key].nan_to_num(), ref[key].nan_to_num(), atol=2e-5), key

