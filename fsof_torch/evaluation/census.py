"""The ternary census on a ring: how well a flow explains two images at sample points, indifferent
to exposure changes between the frames (DESIGN.md §6).

At a point of image 1, the order of the pixel against 16 neighbours on a ring of radius 3 is
compared with the same order in image 2 at the flow's end point (bilinear). Only neighbours whose
order is clear in image 1 count (a ternary census): weak texture, where a wrong flow matches as
well as a right one by chance, is no evidence. A change of exposure that keeps the order of the
grey levels and does not shrink their differences (an offset, a gain of at least 1, a clipped
brightening elsewhere) leaves the distance alone. A darkening does not: the threshold applies in
image 2 as well, so a gain g < 1 turns the neighbours whose difference in image 1 lies in
(threshold, threshold / g] into changed ones (on the road of the KITTI frame 000000_10, grey from
RGB, the exact flow's distance is about 0.12 at g = 0.8 and 0.37 at g = 0.5;
tests/test_gate.py). The
never-worse gate (:class:`~fsof_torch.refinement.gate.ImageGate`) judges flows by it, and the
image fit's screens rank their turns and steps backwards by it.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from .._check import check_float_tensor, check_number, check_shape

__all__ = ["RING", "CONTRAST", "census_ring_distance", "census_ring_distances"]

#: the 16 neighbours (dx, dy) on a ring of radius 3 (a Bresenham circle, as the FAST corner
#: detector's)
RING = ((0, -3), (1, -3), (2, -2), (3, -1), (3, 0), (3, 1), (2, 2), (1, 3),
        (0, 3), (-1, 3), (-2, 2), (-3, 1), (-3, 0), (-3, -1), (-2, -2), (-1, -3))
#: the default grey levels above which a neighbour's order is clear (the gate's and the image
#: fit's screens of turns and of steps backwards)
CONTRAST = 2.0


def census_ring_distance(grey1: Tensor, grey2: Tensor, x: Tensor, y: Tensor, flow: Tensor,
                         threshold: float = CONTRAST) -> tuple[Tensor, Tensor, Tensor]:
    """Ternary census distance of the points (x, y) (B, N) of image 1 (whole pixels: image 1 is
    read there, not interpolated; a fraction is dropped) against image 2 at x + flow (flow
    (B, 2, N), bilinear; the fraction kept), over the 16 ring neighbours.

    ``grey1``, ``grey2``: (B, 1, H, W) float grey images
    (:func:`~fsof_torch.evaluation.photometric.to_grey` converts RGB); ``x``, ``y``: (B, N) float or
    integer pixel coordinates; ``flow``: (B, 2, N) float pixels; all on one device.

    A neighbour counts where its order relative to the centre is clear in image 1 (a difference
    above ``threshold`` grey levels, a number >= 0); the distance is the fraction of those whose
    order differs in image 2 (there: sign of the difference, 0 within the threshold). Weak texture
    carries no evidence either way, so it does not count. Returns the distance (B, N), the number
    of neighbours that count (B, N) and flags of points whose samples lie in both images and are
    finite there, at a finite flow (B, N): a point flagged False is no evidence either way.
    Image 2 is interpolated at float32 positions at least (in half precision a position across a
    wide image would be off by up to half a pixel), its values rounded to its dtype.
    """
    dims = check_shape(check_float_tensor(grey1, "grey1"), "grey1", ("B", 1, "H", "W"))
    check_shape(check_float_tensor(grey2, "grey2"), "grey2", ("B", 1, "H", "W"), dims)
    for name, t in (("x", x), ("y", y)):
        if not isinstance(t, Tensor):
            raise TypeError(f"{name}: expected a tensor (B, N) of pixel coordinates, got {type(t).__name__}")
        if t.dtype == torch.bool or t.is_complex():
            raise TypeError(f"{name}: expected float or integer pixel coordinates, got dtype {t.dtype}")
        check_shape(t, name, ("B", "N"), dims)
    check_shape(check_float_tensor(flow, "flow"), "flow", ("B", 2, "N"), dims)
    for name, t in (("grey2", grey2), ("x", x), ("y", y), ("flow", flow)):
        if t.device != grey1.device:
            raise ValueError(f"{name}: expected the device of grey1 ({grey1.device}), got {t.device}")
    threshold = check_number(threshold, "threshold", nonnegative=True)
    return census_ring_distances(grey1, grey2, x, y, (flow,), threshold)[0]


def census_ring_distances(grey1: Tensor, grey2: Tensor, x: Tensor, y: Tensor, flows: Sequence[Tensor],
                          threshold: float) -> list[tuple[Tensor, Tensor, Tensor]]:
    """:func:`census_ring_distance` for several flows at the same points (image 1 read once), without
    checking its arguments (for loops that have checked them).

    All 17 samples of a point lie inside an image where its centre lies ``r`` = 3 pixels (the
    ring's radius) inside it: the tests, the indices and the sampling grid are formed per point
    and the ring's offsets added to them. A point with a non-finite sample in either image is
    flagged as outside: a NaN or inf pixel orders against nothing."""
    B, _, H, W = grey1.shape
    N, r = x.shape[-1], 3
    dx, dy = (torch.tensor([0] + [d[k] for d in RING], device=x.device) for k in (0, 1))  # (17,)
    R = dx.numel() - 1

    def inside(u: Tensor, v: Tensor) -> Tensor:
        return (u >= r) & (u <= W - 1 - r) & (v >= r) & (v <= H - 1 - r)

    # image 1 at whole pixels: its values themselves (the indices clamped where the point does
    # not count)
    x1, y1 = x.trunc(), y.trunc()
    centre = y1.clamp(r, H - 1 - r).long() * W + x1.clamp(r, W - 1 - r).long()
    flat = (centre.unsqueeze(1) + (dy * W + dx).unsqueeze(-1)).clamp_(0, H * W - 1)
    # (sizes spelled out, not -1: an empty batch has no size to infer)
    v1 = grey1.reshape(B, H * W).gather(1, flat.reshape(B, (R + 1) * N))
    d1 = v1.reshape(B, R + 1, N)[:, 1:] - v1.reshape(B, R + 1, N)[:, :1]
    clear = d1.abs() > threshold
    # each clear neighbour's order (±1), 0 where not clear: a neighbour keeps its order in image 2
    # where order1 · d2 > threshold (never where it is 0, nor at a NaN), which counts the
    # ternary matches in one product and one comparison (a NaN difference, never clear, leaves a
    # NaN order, whose product compares False as 0's does). The counts (at most 16) are summed as
    # bytes: a bool tensor's sum converts it to int64 first, several times slower.
    order1 = torch.sign(d1).mul_(clear)
    n = clear.view(torch.uint8).sum(1, dtype=torch.uint8).long()
    in1 = inside(x1, y1) & _finite_along(v1.reshape(B, R + 1, N), 1)
    # image 2, bilinear at the end points: corner-aligned normalised coordinates (grid_sample's)
    # (the positions and the interpolation in float32 at least: in half precision a normalised
    # coordinate is off by up to half a pixel across a KITTI-wide image; the values are then
    # rounded to image 2's dtype)
    sample = torch.promote_types(grey2.dtype, torch.float32)
    g2 = grey2.to(sample)
    sx, sy = 2.0 / max(W - 1, 1), 2.0 / max(H - 1, 1)
    ring = torch.stack([dx * sx, dy * sy], dim=-1).to(sample).unsqueeze(1)  # (17, 1, 2)
    out = []
    for flow in flows:
        # the end points in float32 at least (integer coordinates plus a half-precision flow
        # would round them to half precision)
        at_least = torch.promote_types(x.dtype if x.is_floating_point() else torch.float32, flow.dtype)
        at_least = torch.promote_types(at_least, torch.float32)
        x2, y2 = x.to(at_least) + flow[:, 0].to(at_least), y.to(at_least) + flow[:, 1].to(at_least)
        # (B, 17, N, 2): each coordinate written into the grid (a broadcast sum over a last
        # dimension of 2 is several times slower)
        at = x2.new_empty((B, R + 1, N, 2), dtype=sample)
        for k, (c, s) in enumerate(((x2, sx), (y2, sy))):
            torch.add((c.to(sample) * s - 1.0).unsqueeze(1), ring[..., k], out=at[..., k])
        v2 = F.grid_sample(g2, at.reshape(B, 1, (R + 1) * N, 2), mode="bilinear", padding_mode="border",
                           align_corners=True).reshape(B, R + 1, N).to(grey2.dtype)
        # (in image 2's dtype, as its own differences are compared with the threshold: ±1 and 0
        # are exact in any dtype, and so is the product)
        d2 = v2[:, 1:] - v2[:, :1]
        kept = (order1.to(d2.dtype) * d2 > threshold).view(torch.uint8).sum(1, dtype=torch.uint8)
        dist = (n - kept).to(grey1.dtype) / n.clamp_min(1)
        # (a non-finite flow lies inside no image: its comparisons are False)
        out.append((dist, n, in1 & inside(x2, y2) & _finite_along(v2, 1)))
    return out


def _finite_along(x: Tensor, dim: int) -> Tensor:
    """Whether every value of float ``x`` along ``dim`` is finite, by the largest magnitude there
    (NaN propagates through ``amax``, an inf is its own maximum): one float reduction, where
    ``torch.isfinite(x).all(dim)`` writes a bool per value and reduces those (slow on the CPU)."""
    return x.abs().amax(dim) < math.inf
