"""Per-pixel votes -> image estimates: a differentiable mean for training, modes for inference.

Notation for one image and joint: valid output pixels ``i`` with origin votes
``v_i = p_i + offset_i`` (m), confidence weights ``w_i = softmax_i(c_i)`` over the valid
pixels (one confidence per quantity: origin, rotation, q).

* :func:`weighted_mean` (training and the image-level loss): ``o = sum_i w_i v_i``, the
  rotation ``r6 = sum_i w^r_i r6_i`` and ``q = sum_i w^q_i q_i``.
* :func:`vote_modes` (inference): mean-shift on the origin votes with a Gaussian kernel of
  bandwidth :data:`BANDWIDTH_M`, started from the :data:`N_STARTS` heaviest votes; converged
  point of highest kernel density is the first mode; the votes within :data:`MODE_SEPARATION_M`
  of it are set aside and the search repeats on the rest (while they carry at least
  :data:`MIN_MODE_MASS` of the weight), at most :data:`MAX_MODES` modes per joint; a later mode is
  kept only when it stands ``split_factor`` (default :data:`SPLIT_FACTOR`; chosen per class on
  validation objects, see :func:`~.predict.choose_split_factor`) times the two modes' spreads from
  the first (one wide cloud is one mode; ``None``: one mode, the weighted mean of every vote).  Every vote joins its nearest kept
  mode; a mode's weight is the sum of its votes' ``w_i``, its estimate the weighted mean of
  its own votes (origin, rotation, q, part offset), and its spread their weighted standard
  deviation.  So a two-sided ambiguity (the hinge of a closed door) gives two components
  with their own weights, never their average.
"""

from __future__ import annotations

import torch

#: Mean-shift kernel bandwidth (m).
BANDWIDTH_M = 0.05
#: Mean-shift iterations and starting points.
N_ITERATIONS = 10
N_STARTS = 8
#: Kept modes must be at least this far apart (m).
MODE_SEPARATION_M = 0.15
#: Modes per joint.
MAX_MODES = 2
#: A further mode is kept only when its centre is more than this many times the two modes'
#: summed vote spreads (root of the summed coordinate variances) away from the first's.
SPLIT_FACTOR = 1.5
#: A further mode is sought only while the votes not yet explained carry this much weight.
MIN_MODE_MASS = 0.05
#: :func:`vote_modes` and the refinement take the images in groups of this many with similar
#: numbers of valid pixels, each padded to its group's largest image rather than the batch's
#: (objects' sizes vary ten-fold).
IMAGE_GROUP = 32
#: Logit given to invalid pixels (excluded from every softmax).
_MASKED_LOGIT = -1e9
#: Mean-shift kernel exponents are clipped at this: ``exp(-87)`` = 1.6e-38 is just above float32's
#: smallest normal number (1.2e-38); beyond it exp returns subnormals on a ~30x slower path.  The
#: clipped kernel differs from the exact one by < 2e-38 (the weight of far votes), below float noise.
_MAX_KERNEL_EXPONENT = 87.0


def softmax_weights(logits: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, J, h, w) logits, (B, h, w) validity -> (B, J, N) weights summing to 1 over valid pixels."""
    B, J = logits.shape[:2]
    v = valid[:, None].expand(B, J, *valid.shape[1:]).flatten(2)
    return torch.softmax(logits.flatten(2).masked_fill(~v, _MASKED_LOGIT), -1)


def argmax_channels(x: torch.Tensor) -> torch.Tensor:
    """``x.argmax(1)`` for a few channels (the first on ties), by comparisons: argmax over a
    middle axis is several times slower."""
    best, arg = x[:, 0], torch.zeros_like(x[:, 0], dtype=torch.long)
    for k in range(1, x.shape[1]):
        better = x[:, k] > best
        best, arg = torch.where(better, x[:, k], best), arg.masked_fill(better, k)
    return arg


def compact_mask(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, P) bool -> the column indices (R, n) of each row's True entries, in order and padded
    with 0, and which of them are real (R, n); ``n`` is the largest row count (at least 1).
    A mask more than a quarter True is compacted by a running count and one scatter (the
    pixels of the cabinets' images and doors: twice as fast), a sparser one from its ``nonzero``."""
    R, P = mask.shape
    running = mask.cumsum(1, dtype=torch.int32)  # (int32: the compaction takes half the time in int64's)
    counts = running[:, -1]
    n = max(int(counts.max()), 1) if R else 1
    idx = torch.zeros(R, n + 1, dtype=torch.long)
    if 4 * int(counts.sum()) > mask.numel():
        # each True entry's position among its row's, the others into a spare last column
        target = torch.where(mask, running - 1, n).long()
        idx.scatter_(1, target, torch.arange(P).expand(R, P))
    else:
        rows, cols = mask.nonzero(as_tuple=True)
        idx[rows, torch.arange(len(rows)) - (counts.cumsum(0) - counts)[rows]] = cols
    return idx[:, :n], torch.arange(n) < counts[:, None]


def gram_schmidt6(r6: torch.Tensor, dim: int = -1) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 6) -> unit axis z = a/|a| and x = normalised (b - (b.z) z) (components along ``dim``)."""
    a, b = r6.narrow(dim, 0, 3), r6.narrow(dim, 3, 3)
    z = _normalize(a, dim)
    x = _normalize(b - (b * z).sum(dim, keepdim=True) * z, dim)
    return z, x


def _normalize(v: torch.Tensor, dim: int, eps: float = 1e-12) -> torch.Tensor:
    """``torch.nn.functional.normalize`` (``v / max(|v|, eps)``) for 3-vectors along ``dim``, with the norm written
    out: ``torch.linalg.vector_norm`` over a short strided axis is several times slower."""
    sq = v * v
    return v / torch.sqrt(sq.select(dim, 0) + sq.select(dim, 1) + sq.select(dim, 2)).clamp_min(eps).unsqueeze(dim)


def weighted_mean(parts: dict, points: torch.Tensor, valid: torch.Tensor) -> dict:
    """Softmax-weighted image estimates (differentiable).

    ``parts``: :meth:`DenseNet.split` output; ``points`` (B, 3, h, w); ``valid`` (B, h, w) bool.
    Returns ``origin`` (B, J, 3), ``rot6`` (B, J, 6), ``q`` (B, J), ``part_offset`` (B, J, 3),
    ``geometry`` (B, 4) (chirality as a logit).
    """
    conf = parts["conf"]
    wo, wr, wq = (softmax_weights(conf[:, :, k], valid) for k in range(3))
    votes = (points[:, None] + parts["offset"]).flatten(3)  # (B, J, 3, N)
    wg = softmax_weights(parts["geometry_conf"][:, None], valid)[:, 0]  # (B, N)
    return {
        "origin": (votes * wo[:, :, None]).sum(-1),
        "rot6": (parts["rot6"].flatten(3) * wr[:, :, None]).sum(-1),
        "q": (parts["q"].flatten(2) * wq).sum(-1),
        "part_offset": (parts["part_offset"].flatten(3) * wo[:, :, None]).sum(-1),
        "geometry": (parts["geometry"].flatten(2) * wg[:, None]).sum(-1),
    }


def _wmean_std(x: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """x (..., C, N), w (..., N) summing to 1 -> weighted mean and std (..., C)."""
    m = (x * w[..., None, :]).sum(-1)
    var = (((x - m[..., None]) ** 2) * w[..., None, :]).sum(-1)
    return m, var.clamp_min(0).sqrt()


def image_groups(counts: torch.Tensor, size: int = IMAGE_GROUP) -> tuple[list, torch.Tensor]:
    """Groups of at most ``size`` images by increasing ``counts`` (B,): their row indices, and the
    permutation that puts the groups' concatenated results back in batch order."""
    order = torch.argsort(counts, stable=True)
    return list(order.split(size)), torch.argsort(order)


@torch.no_grad()
def vote_modes(parts: dict, points: torch.Tensor, valid: torch.Tensor, split_factor: float | None = SPLIT_FACTOR) -> dict:
    """Mode-seeking aggregation per joint (see the module docstring), in :func:`image_groups`.

    Returns, with ``M = MAX_MODES``: ``weight`` (B, J, M) (0 for an unused mode; sums to 1),
    ``origin`` (B, J, M, 3), ``axis`` and ``xaxis`` (B, J, M, 3) unit, ``q`` (B, J, M),
    ``part_offset`` (B, J, M, 3), and spreads ``origin_std``, ``axis_std``, ``xaxis_std``,
    ``offset_std`` (B, J, M, 3), ``q_std`` (B, J, M); ``geometry`` (B, 4) with chirality in
    [0, 1] and ``geometry_std`` (B, 4).
    """
    groups, back = image_groups(valid.flatten(1).sum(1))
    if len(groups) == 1:
        return _vote_modes(parts, points, valid, split_factor)
    used = ("conf", "offset", "rot6", "q", "part_offset", "geometry", "geometry_conf")  # not the segmentation
    out = [_vote_modes({k: parts[k][rows] for k in used}, points[rows], valid[rows], split_factor) for rows in groups]
    return {k: torch.cat([o[k] for o in out])[back] for k in out[0]}


def _vote_modes(parts: dict, points: torch.Tensor, valid: torch.Tensor, split_factor: float | None) -> dict:
    """:func:`vote_modes` of one group of images."""
    conf = parts["conf"]
    B, J = conf.shape[:2]
    # compact every image's valid pixels to the front (padding masked): objects cover a third
    # of the image, so every operation below runs on ~3x fewer pixels
    flat_valid = valid.flatten(1)
    n_max = max(int(flat_valid.sum(1).max()), 1)
    order = torch.sort((~flat_valid).to(torch.uint8), dim=1, stable=True).indices[:, :n_max]  # (B, n)
    valid_c = torch.gather(flat_valid, 1, order)

    def compact(x):  # (B, J, C, H, W) or (B, J, H, W) -> (B, J, C, n) / (B, J, n)
        x = x.flatten(-2)
        idx = order[:, None, None] if x.dim() == 4 else order[:, None]
        return torch.gather(x, -1, idx.expand(*x.shape[:-1], n_max))

    def weights(logits):  # softmax over the valid pixels
        return torch.softmax(compact(logits).masked_fill(~valid_c[:, None], _MASKED_LOGIT), -1)

    wo, wr, wq = (weights(conf[:, :, k]) for k in range(3))
    votes = compact(points[:, None].expand(B, J, 3, *points.shape[2:]) + parts["offset"])  # (B, J, 3, n)
    vt = votes.transpose(-1, -2)  # (B, J, n, 3)
    v2 = (vt * vt).sum(-1)[:, :, None]  # (B, J, 1, n)
    N = n_max
    S = min(N_STARTS, N)
    inv2bw2 = 1.0 / (2 * BANDWIDTH_M**2)
    remaining = valid_c[:, None].expand(B, J, N).clone()  # (B, J, n)
    centres: list | torch.Tensor  # the modes found (a list), then stacked (a tensor)
    used: list | torch.Tensor
    centres, used = [], []
    max_d2 = _MAX_KERNEL_EXPONENT / inv2bw2
    for r in range(MAX_MODES):
        w_rem = wo * remaining
        top = w_rem.topk(S, -1).indices
        modes = torch.gather(vt, 2, top[..., None].expand(B, J, S, 3))  # (B, J, S, 3)
        for _ in range(N_ITERATIONS):
            # |v - m|^2 = |v|^2 + |m|^2 - 2 m.v, as matrix products (no (S, N, 3) temporaries);
            # the kernel is computed in place in that one (B, J, S, n) tensor
            # (the product is added into the |v|^2 + |m|^2 tensor in place: baddbmm would copy it first)
            k = (v2 + (modes * modes).sum(-1, keepdim=True)).flatten(0, 1).baddbmm_(
                modes.flatten(0, 1), votes.flatten(0, 1), alpha=-2).view(B, J, S, N)
            k.clamp_(0, max_d2).mul_(-inv2bw2).exp_().mul_(w_rem[:, :, None])
            density = k.sum(-1)
            modes = (k @ vt) / density[..., None].clamp_min(1e-30)
        best = density.argmax(-1)
        centre = torch.gather(modes, 2, best[:, :, None, None].expand(B, J, 1, 3))[:, :, 0]  # (B, J, 3)
        mass = w_rem.sum(-1)
        used.append(mass > (0.0 if r == 0 else MIN_MODE_MASS))
        centres.append(centre)
        remaining &= ((votes - centre[..., None]) ** 2).sum(2) > MODE_SEPARATION_M**2
    centres = torch.stack(centres, -1)  # (B, J, 3, M)
    used = torch.stack(used, -1)  # (B, J, M)
    diff = votes[:, :, :, None, :] - centres[..., None]  # (B, J, 3, M, N)
    d2_all = diff[:, :, 0] ** 2 + diff[:, :, 1] ** 2 + diff[:, :, 2] ** 2  # (B, J, M, N)

    def assign(used):  # one-hot (B, J, M, N) of each vote's nearest used mode (the first on ties)
        d = d2_all.masked_fill(~used[..., None], float("inf"))
        best_d2, best = d[:, :, 0], torch.zeros_like(d[:, :, 0], dtype=torch.long)
        for k in range(1, MAX_MODES):  # a loop over the few modes: faster than argmin over a middle axis
            closer = d[:, :, k] < best_d2
            best_d2, best = torch.where(closer, d[:, :, k], best_d2), torch.where(closer, k, best)
        return torch.stack([best == k for k in range(MAX_MODES)], 2).float()

    def within(w, member):  # weights restricted to each mode, renormalised
        wm = w[:, :, None] * member
        return wm / wm.sum(-1, keepdim=True).clamp_min(1e-30), wm.sum(-1)

    # a later mode stays only if it is separated from the first by more than split_factor times
    # their spreads (a wide single cloud cut in two halves is not two modes; None: never)
    member = assign(used)
    w_o, _ = within(wo, member)
    c, c_std = _wmean_std(votes[:, :, None], w_o)  # (B, J, M, 3)
    spread = c_std.norm(dim=-1)
    gap = (c - c[:, :, :1]).norm(dim=-1)
    first = torch.arange(MAX_MODES) == 0
    used = used & (first if split_factor is None else (gap > split_factor * (spread + spread[:, :, :1])) | first)
    member = assign(used)
    w_o, mass = within(wo, member)
    w_r, _ = within(wr, member)
    w_q, _ = within(wq, member)
    origin, origin_std = _wmean_std(votes[:, :, None], w_o)
    r6 = compact(parts["rot6"])[:, :, None]  # (B, J, 1, 6, n)
    r6_mean = (r6 * w_r[..., None, :]).sum(-1)
    axis, xaxis = gram_schmidt6(r6_mean)
    z_pix, x_pix = gram_schmidt6(r6, dim=-2)  # (B, J, 1, 3, N)
    _, axis_std = _wmean_std(z_pix, w_r)
    _, xaxis_std = _wmean_std(x_pix, w_r)
    q, q_std = _wmean_std(compact(parts["q"])[:, :, None, None], w_q)
    offset, offset_std = _wmean_std(compact(parts["part_offset"])[:, :, None], w_o)
    weight = torch.where(used, mass, torch.zeros_like(mass))
    weight = weight / weight.sum(-1, keepdim=True).clamp_min(1e-30)
    wg = softmax_weights(parts["geometry_conf"][:, None], valid)[:, 0]
    geometry, geometry_std = _wmean_std(parts["geometry"].flatten(2), wg)
    chirality = torch.sigmoid(parts["geometry"][:, 3].flatten(1))
    geometry = geometry.clone()
    geometry[:, 3] = (chirality * wg).sum(-1)
    geometry_std = geometry_std.clone()
    geometry_std[:, 3] = (((chirality - geometry[:, 3:4]) ** 2) * wg).sum(-1).sqrt()
    per_mode = {
        "weight": weight, "origin": origin, "axis": axis, "xaxis": xaxis, "q": q[..., 0], "part_offset": offset,
        "origin_std": origin_std, "axis_std": axis_std, "xaxis_std": xaxis_std, "q_std": q_std[..., 0],
        "offset_std": offset_std,
    }
    order = torch.sort(weight, dim=-1, descending=True, stable=True).indices  # heaviest mode first
    out = {}
    for key, v in per_mode.items():
        idx = order if v.dim() == 3 else order[..., None].expand(*order.shape, v.shape[-1])
        out[key] = torch.gather(v, 2, idx)
    out["geometry"], out["geometry_std"] = geometry, geometry_std
    return out


def rows_dot(v, a: torch.Tensor) -> torch.Tensor:
    """``v . a`` per entry: ``v`` three components (x, y, z) of (R, m) each, ``a`` (R, 3) one vector
    per row -> (R, m), written component by component (a (R, m, 3) stack and a reduction over its
    last axis cost about twice as much)."""
    return v[0] * a[:, 0:1] + v[1] * a[:, 1:2] + v[2] * a[:, 2:3]


def lower_median(values: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
    """:func:`weighted_median` with weight 1 on the ``real`` entries (last dimension) and 0 elsewhere:
    the ``ceil(c / 2)``-th smallest of a row's ``c`` real entries (NaN without any), found by
    selection (:func:`torch.kthvalue`) instead of a sort.  The other entries become -inf or +inf,
    so many of each that every row's median lands at the same rank."""
    count = real.sum(-1, keepdim=True)  # (R, 1)
    rank = torch.div(count - 1, 2, rounding_mode="floor")  # 0-based rank of the median among the real entries
    target = int(rank.max()) if rank.numel() else 0
    # the first (target - rank) entries that are not real go below every real one, the rest above
    below = (~real).cumsum(-1, dtype=torch.int32) <= target - rank
    filler = torch.where(below, float("-inf"), float("inf")).to(values.dtype)
    med = torch.kthvalue(torch.where(real, values, filler), max(target, 0) + 1, -1).values
    return torch.where(count[..., 0] > 0, med, torch.full_like(med, float("nan")))
