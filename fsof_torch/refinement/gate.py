"""The never-worse gate: the model flow replaces the prediction only where it explains the images
at least as well.

Once the road model's flow is known, both it and the network's prediction are judged by how well
they explain the two images, per sample and per local region of the mask (a grid of cells). The
judge is a census distance (DESIGN.md §6), indifferent to offsets and brightening between the
frames (not to a darkening: :mod:`~fsof_torch.evaluation.census`):
at an even subsample of the mask's pixels, the order of the pixel against a ring of 16 neighbours
at radius 3 in image 1, against the same order in image 2 at the flow's end point (bilinear). Only
neighbours whose order is clear in image 1 count (a ternary census): weak texture, where a wrong
flow matches as well as a right one by chance, is no evidence. A cell keeps the prediction where
the model's mean distance exceeds the prediction's by more than ``margin`` plus ``z`` standard
errors of the difference (the model is the physically constrained estimate; the prediction has
to be clearly better) and the prediction explains the cell itself (its mean distance at most
``occlusion``, over every point of the cell it can be judged at, also where the model's end point
leaves image 2: where neither flow does, the road is occluded in image 2 or the content is new,
and the model's geometry is the better guess); so does every cell of a sample where that holds
over the whole mask. Cells with too few points follow their sample's decision. A prediction that
is not finite at a point, or whose end point leaves image 2, cannot be judged there: where the
model can be judged the point counts, the prediction's distance taken as ``occlusion`` (a flow
that just explains the point), so the model wins it only where it explains it; a non-finite
prediction's as the model's where that is larger (it explains nothing, so it never wins a point:
on real road even the exact flow's distance can exceed ``occlusion``). Over a sample's
whole mask the standard error is the larger of the points' own and one from the sums of 16 x 16
pixel blocks of points (neighbouring points' rings overlap and image content is correlated: they
are not independent evidence); the cells and object regions take their points' own, which errs
toward keeping the prediction (a region's part inside a cell too: its test can only hand the
part back to the cell's decision).

The object test (``objects``) judges the connected regions of the mask where the two flows
differ by more than ``object_px`` (2 and 4 times that too) on their own: a region where the
prediction explains the images significantly better keeps it, except in its part inside a cell
whose own points significantly favour the model (a region's average does not overrule its parts).

A sample is *confirmed* when at least ``min_points`` of its points count and over its whole
mask the model explains the images better than the prediction by more than ``z`` standard
errors, and *informative* when at least ``min_points`` of its points count and one of the two
flows explains them (its mean distance at most
``occlusion``; where the prediction cannot be judged anywhere, the model alone decides). With
``require_evidence`` (the default) a sample whose images are not informative and do not confirm
the model keeps its prediction everywhere: on dark, noisy or textureless frames the census is
noise for any flow, and replacing the prediction would rest on the model alone.

Images are (B, C, H, W) on 0..255 (grey or RGB); flows (B, 2, H, W) in pixels; masks (B, 1, H, W)
bool. Not differentiable (a decision). Host reads: the mask's pixels (one ``nonzero``), with
``objects`` the object test, whose connected regions OpenCV finds on the CPU (the mask's bounding
box, the flows' difference over it and each region's decision), and on the CPU whether the model
flow is finite everywhere (the pixels where it is not keep the prediction); the values are not checked.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from .._check import (all_finite, check_float_tensor, check_has_values, check_image_pair, check_int, check_mask,
                      check_number, check_shape, inference, summary_repr, tracing)
from ..estimation.sampling import MaskPoints, sample_mask
from ..evaluation.census import CONTRAST, RING, census_ring_distance, census_ring_distances
from ..evaluation.photometric import to_grey

__all__ = ["ImageGate", "GateResult", "census_ring_distance"]

_MAX_OBJECT_PX = 1e6
# the side (pixels) of the square blocks over which a sample's mean difference takes its standard
# error: twice a point's footprint (the ring's diameter, and the pixel that bilinear sampling adds),
# so that points whose census rings overlap mostly share a block
_BLOCK = 2 * (2 * max(max(abs(dx), abs(dy)) for dx, dy in RING) + 2)


class GateResult(NamedTuple):
    """What :class:`ImageGate` decided.

    Attributes:
        use_model: (B, 1, H, W) bool, mask pixels where the model flow is used (never one where
            it is not finite: no flow to use, as :func:`~fsof_torch.refinement.fusion.fuse_flow` requires).
        evidence: (B, 1, H, W) float in [0, 1], the image evidence for the model over the
            prediction per cell (0.5: no preference, also in a cell with too few points), for
            confidence fusion; 0 outside the mask, and in a sample whose model is not used
            (``model_used`` False: also one whose images give no evidence either way).
        cost_model, cost_prediction: (B,) mean census distances over the points that count
            (the prediction's ``occlusion`` where it leaves image 2, and where it is not finite
            the larger of ``occlusion`` and the model's).
        points: (B,) the number of points that count: textured points the model can be judged
            at, where the prediction can be judged too or is lost (not finite, or leaving image 2).
        cells, cells_kept: (B,) cells of the (coarse) grid with enough points, and of those the
            cells where the model is used at none of their pixels (after the object test).
        model_used: (B,) bool, False where the model is worse over the whole mask, where the mask
            is empty, or (with ``require_evidence``) where the images neither inform nor confirm.
        confirmed: (B,) bool, at least ``min_points`` points count and the model explains the
            images significantly better than the prediction over the whole mask.
        informative: (B,) bool, at least ``min_points`` points count and one of the two flows
            explains the images (mean census distance at most ``occlusion``).
        textured: (B,) the share of the judged points with enough clear texture to count.
    """

    use_model: Tensor
    evidence: Tensor
    cost_model: Tensor
    cost_prediction: Tensor
    points: Tensor
    cells: Tensor
    cells_kept: Tensor
    model_used: Tensor
    confirmed: Tensor
    informative: Tensor
    textured: Tensor
    __repr__ = summary_repr  # (one line, tensors as their shapes)


def _sum_by(index: Tensor, v: Tensor, n: int) -> Tensor:
    """(B, n) or (B, K, n): the sums of ``v`` (B, N), or of each of its K rows (B, K, N), over the
    points of each group, ``index`` (B, N) int64 in [0, n)."""
    if v.dim() == 3:
        index = index.unsqueeze(1).expand_as(v)
    return torch.zeros(*v.shape[:-1], n, dtype=v.dtype, device=v.device).scatter_add_(-1, index, v)


def _mean_and_error(v: Tensor, w: Tensor, block: Tensor | None = None, blocks: int = 0) -> tuple[Tensor, Tensor]:
    """The weighted mean of ``v`` (B, N) over points of weight ``w`` (0 or 1) and its standard
    error (B,) each.

    With ``block`` (B, N) int64, each point's block (of ``blocks``), the error is also estimated
    from the blocks' sums (a cluster-robust error: points whose census footprints overlap, or whose
    images are correlated, are not independent evidence), and the larger of the two is returned.
    With G blocks holding points, the blocks' estimate is sum_b (S_b - n_b mean)^2 / n^2 times
    G / (G - 1), S_b and n_b the block's weighted sum and weight; a single block gives 0 (the
    points' estimate then stands)."""
    n = w.sum(1).clamp_min(1)
    mean = (v * w).sum(1) / n
    var = ((v.square() * w).sum(1) / n - mean.square()).clamp_min(0) / n
    if block is not None:
        def per_block(x: Tensor) -> Tensor:
            return _sum_by(block, x, blocks)

        G = (per_block(w) > 0).sum(1)
        clustered = per_block((v - mean.unsqueeze(1)) * w).square().sum(1) / n.square() * G / (G - 1).clamp_min(1)
        var = torch.maximum(var, clustered)
    return mean, var.sqrt()


class ImageGate:
    """Keeps the prediction wherever the model explains the images worse (see the module).

    Args (keyword-only):
        grid: (rows, columns) of cells over the image (their evidence drives confidence fusion).
        objects: also test the connected regions where the flows differ by more than
            ``object_px`` (pixels, > 0 and at most 1e6), 2 or 4 times that (objects smaller than a
            cell, such as a car inside the mask); a region keeps the prediction on
            ``min_points_fine`` points or more, except in its part inside a cell whose own points
            there (``min_points`` or more) favour the model by ``z`` standard errors.
        points: mask pixels per sample that are judged (an even subsample).
        min_points: a cell with fewer points follows its sample's decision; a sample with fewer is
            neither informative nor confirmed (``require_evidence``).
        margin, z: the model may be worse than the prediction by ``margin`` census distance plus
            ``z`` standard errors of the difference and still be used (over a sample's mask, the
            errors from blocks of points where larger: see the module).
        occlusion: the prediction's mean distance above which it does not explain a cell either.
        temperature: the census difference (prediction − model) at which the confidence evidence
            is 0.73, and 0.27 at minus that (a logistic of (prediction − model) / temperature).
        contrast: grey levels above which a neighbour's order in image 1 is clear.
        min_neighbours: points with fewer clear neighbours (weak texture) do not count.
        require_evidence: a sample whose images are not informative keeps its prediction unless
            they confirm the model.
    """

    def __init__(self, *, grid: tuple[int, int] = (8, 16), objects: bool = True, object_px: float = 1.0,
                 min_points_fine: int = 4, points: int = 6000, min_points: int = 12,
                 margin: float = 0.0, z: float = 2.0, occlusion: float = 0.35, temperature: float = 0.02,
                 contrast: float = CONTRAST, min_neighbours: int = 4, require_evidence: bool = True) -> None:
        if not isinstance(grid, (tuple, list)) or len(grid) != 2:
            raise TypeError(f"grid: expected (rows, columns) of positive integers, got {grid!r}")
        grid = tuple(check_int(v, "grid", minimum=1) for v in grid)
        if not isinstance(objects, bool):
            raise TypeError(f"objects: expected a bool, got {objects!r}")
        points, min_points, min_points_fine = (check_int(v, name, minimum=1) for name, v in (
            ("points", points), ("min_points", min_points), ("min_points_fine", min_points_fine)))
        # (every neighbour of the ring, or fewer: more could never be met, and refining would stop)
        min_neighbours = check_int(min_neighbours, "min_neighbours", minimum=0)
        if min_neighbours > len(RING):
            raise ValueError(f"min_neighbours: expected at most {len(RING)} (the ring's neighbours), "
                             f"got {min_neighbours}")
        self.grid, self.points, self.min_points, self.min_points_fine = grid, points, min_points, min_points_fine
        # (no flow differs by more than an image's size; the test squares 4 times the threshold)
        object_px = check_number(object_px, "object_px", positive=True)
        if object_px > _MAX_OBJECT_PX:
            raise ValueError(f"object_px: expected at most {_MAX_OBJECT_PX:g} pixels, got {object_px!r}")
        self.objects, self.object_px = objects, object_px
        self.margin, self.occlusion = (check_number(v, n, nonnegative=True) for n, v in (("margin", margin),
                                                                                         ("occlusion", occlusion)))
        self.temperature = check_number(temperature, "temperature", positive=True)
        self.z = check_number(z, "z", nonnegative=True)
        self.contrast = check_number(contrast, "contrast", nonnegative=True)
        self.min_neighbours = min_neighbours
        if not isinstance(require_evidence, bool):
            raise TypeError(f"require_evidence: expected a bool, got {require_evidence!r}")
        self.require_evidence = require_evidence

    @inference
    def __call__(self, image1: Tensor, image2: Tensor, prediction: Tensor, model: Tensor,
                 mask: Tensor) -> GateResult:
        """Judge ``prediction`` against ``model`` (each (B, 2, H, W) px) by ``image1`` and ``image2``
        (B, 1 or 3, H, W) on 0..255 inside ``mask`` (B, 1, H, W) bool. Values are not checked (no
        error for them): a point where an image or the model is not finite gives no evidence
        either way, and a pixel where the model is not finite keeps the prediction (``use_model``
        False there); one where the prediction is not finite counts for the model (a prediction that
        cannot be judged never wins a point: see the module). All five on one device (else a ValueError naming the argument). The gate
        samples the mask's pixels (data dependent): on the meta device it raises a ValueError."""
        # (the images first: a flow or mask of another size is named, not the frames)
        dims = check_image_pair(image1, image2)
        check_shape(check_float_tensor(prediction, "prediction"), "prediction", ("B", 2, "H", "W"), dims)
        check_shape(check_float_tensor(model, "model"), "model", ("B", 2, "H", "W"), dims)
        check_shape(check_mask(mask, "mask"), "mask", ("B", 1, "H", "W"), dims)
        named = {"prediction": prediction, "image1": image1, "image2": image2, "model": model, "mask": mask}
        for name, t in named.items():
            check_has_values(t, name, "to judge by the images (the gate samples the mask's pixels; "
                             "a refiner with gate=None infers shapes on the meta device)")
            if t.device != prediction.device:
                raise ValueError(f"{name}: expected the device of prediction ({prediction.device}), got {t.device}")
        B, _, H, W = prediction.shape
        work = torch.promote_types(prediction.dtype, torch.float32)
        g1, g2 = to_grey(image1.detach().to(work)), to_grey(image2.detach().to(work))
        pts = sample_mask(mask, self.points)
        x = (pts.pix % W).to(work)
        y = torch.div(pts.pix, W, rounding_mode="floor").to(work)

        def at(f: Tensor) -> Tensor:
            return f.detach().to(work).reshape(B, 2, -1).gather(2, pts.pix.unsqueeze(1).expand(B, 2, -1))

        fp, fm = at(prediction), at(model)
        finite = torch.isfinite(fp).all(1)
        # a prediction that is not finite, or whose end point leaves image 2, cannot be judged
        # there: where the model can be judged, the prediction's distance is taken as the
        # occlusion threshold (a flow that just explains the point): the model wins the point
        # where it explains it (a wrong prediction far off the image, or NaN), not where a right
        # prediction leaves the frame near its border and a wrong model stays inside
        def leaves(f: Tensor) -> Tensor:
            """(B, N) bool: the flow's end point leaves image 2 (also where it is not finite)."""
            x2, y2 = x + f[:, 0], y + f[:, 1]
            return ~((x2 >= 0) & (x2 <= W - 1) & (y2 >= 0) & (y2 <= H - 1))

        lost = leaves(fp)
        fp = torch.where(finite.unsqueeze(1), fp, fm)
        (d_pred, n_clear, ok_pred), (d_model, _, ok_model) = census_ring_distances(g1, g2, x, y, (fp, fm), self.contrast)
        # (a non-finite prediction was judged with the model's flow: its distance there is the
        # model's, at least ``occlusion``: it never wins a point, also where real images leave
        # even the exact flow above ``occlusion``)
        d_pred = torch.where(lost, torch.where(finite, self.occlusion, d_pred.clamp_min(self.occlusion)), d_pred)
        # points that count: real, textured, judged by the model and judged by the prediction or
        # lost by it
        judged = pts.sel & ok_model & ((ok_pred & finite) | lost)
        count = judged & (n_clear >= self.min_neighbours)
        w = count.to(work)
        delta = d_model - d_pred  # > 0: the prediction explains the point better
        n_all = w.sum(1)
        cost_pred = (d_pred * w).sum(1) / n_all.clamp_min(1)
        # whether the prediction explains points (mean distance at most ``occlusion``) is judged
        # by the sum of its excess over ``occlusion``: 0 exactly where it is lost, where the mean
        # of n equal distances ``occlusion`` can round above it (n = 44 in float32)
        excess = d_pred - self.occlusion
        cost_model = (d_model * w).sum(1) / n_all.clamp_min(1)
        # the mean difference's standard error also from blocks of points (neighbouring points
        # are not independent evidence)
        rows, cols = math.ceil(H / _BLOCK), math.ceil(W / _BLOCK)
        block = torch.div(pts.pix, W * _BLOCK, rounding_mode="floor") * cols \
            + torch.div(pts.pix % W, _BLOCK, rounding_mode="floor")
        mean_all, se_all = _mean_and_error(delta, w, block, rows * cols)
        # the prediction is kept only where it explains the images itself: where neither flow
        # does (occluded in image 2, new content), the model's geometry is the better guess
        # (no textured point at all is no evidence against the model either)
        explains = (excess * w).sum(1) <= 0
        model_used = ~((mean_all > self.margin + self.z * se_all) & explains)
        # (fewer points than a cell needs are too few to judge a sample by: a handful of census
        # distances can favour either flow by chance, and no standard error would show it; they
        # neither confirm the model nor inform)
        enough_points = n_all >= self.min_points
        # confirmed: the model better by z standard errors (no margin: the images decide)
        confirmed = enough_points & (-mean_all > self.z * se_all)
        # (a prediction lost at every point that counts "explains" them by construction, each at
        # ``occlusion`` exactly: whether such images inform is the model's alone to say)
        informative = enough_points & ((cost_model <= self.occlusion) | (explains & (count & ~lost).any(1)))
        if self.require_evidence:
            model_used = model_used & (confirmed | informative)
        model_used = model_used & (pts.count > 0)  # (no mask pixel: the model is used nowhere)
        (rows, cols), ch, cw = self.grid, math.ceil(H / self.grid[0]), math.ceil(W / self.grid[1])
        cell = (torch.div(y, ch, rounding_mode="floor") * cols + torch.div(x, cw, rounding_mode="floor")).long()
        # whether the prediction explains a cell (or an object region) itself: its mean distance
        # also over the points whose model end point leaves image 2 (the prediction judged there):
        # a cell's few points that the model can be judged at, near an edge the road leaves
        # through, do not speak for the prediction over the rest of the cell
        model_lost = leaves(fm) & torch.isfinite(fm).all(1)
        w_pred = (count | (pts.sel & model_lost & ok_pred & finite & (n_clear >= self.min_neighbours))).to(work)
        # what the cells and the object regions sum over their points: the weights, the weighted
        # differences and their squares, and the prediction's excess over ``occlusion`` weighted
        terms = torch.stack([w, delta * w, delta.square() * w, excess * w_pred], dim=1)  # (B, 4, N)
        cell_model, evidence, enough, kept = self._cells(cell, terms, model_used, (H, W))
        # (a sample whose model is not used has no cell that uses it; a pixel whose model flow is
        # not finite cannot be judged and is no flow to use: it keeps the prediction, as
        # fuse_flow, which takes use_model as its mask, requires the model finite there)
        use_model = mask & cell_model
        # (on the CPU, where a read costs no wait, one min/max pass settles the common case: a bool
        # per value costs about 2 ms on a KITTI frame, one thread, 0.2 ms the pass (all_finite),
        # beside the gate's 5 ms in python benchmarks/bench_image_fit.py --kitti15)
        if model.device.type != "cpu" or tracing() or not all_finite(model):
            use_model = use_model & torch.isfinite(model).all(1, keepdim=True)
        kept = (enough & kept).sum(1)
        objects = self._objects(prediction, model, mask, pts, cell, terms) if self.objects else None
        if objects is not None:
            use_model = use_model & ~objects
            # the cells that keep the prediction, counted again: an object region may keep it in
            # the whole of a cell that uses the model by its own test (a cell with enough points
            # holds mask pixels)
            pad = (0, cols * cw - W, 0, rows * ch - H)
            used = F.pad(use_model.view(torch.uint8), pad).reshape(B, rows, ch, cols, cw).amax(dim=(2, 4))
            kept = (enough & (used.reshape(B, -1) == 0)).sum(1)
        # (a full-size result, made outside inference mode without autograd: returned as made, not
        # copied out of inference mode at the end; the same values)
        with torch.inference_mode(False), torch.no_grad():
            evidence_map = torch.where(mask, evidence, 0.0)
        textured = n_all / judged.sum(1).clamp_min(1)
        return GateResult(use_model, evidence_map, cost_model, cost_pred, n_all.long(), enough.sum(1), kept, model_used,
                          confirmed, informative, textured)

    def _objects(self, prediction: Tensor, model: Tensor, mask: Tensor, pts: MaskPoints, cell: Tensor,
                 terms: Tensor) -> Tensor | None:
        """(B, 1, H, W) bool: the connected regions of the mask where the two flows differ by more
        than ``object_px`` (or 2 or 4 times that) and the prediction explains the images
        significantly better (a car inside the mask, whatever its shape and however it meets the
        cells), less each region's part in a cell (``cell`` (B, N), each point's) whose own points,
        ``min_points`` or more, significantly favour the model: a region's average does not
        overrule its parts' evidence. None where no region keeps the prediction. Whether the
        prediction explains a region: its excess over ``occlusion`` summed over the points of weight
        w_pred (as the cells'); ``terms``: the sums' terms at the points (see :meth:`_cells`)."""
        import cv2
        import numpy as np

        B, _, H, W = prediction.shape
        (grid_rows, grid_cols), C = self.grid, self.grid[0] * self.grid[1]
        ch, cw = math.ceil(H / grid_rows), math.ceil(W / grid_cols)
        if pts.every.numel() == 0:
            return None
        kept, box_cell = None, None

        # the flows' squared difference at the mask's pixels, 0 elsewhere, over the mask's bounding
        # box (the batch's: its first and last rows and columns, one host read): the regions lie
        # inside it
        # (as bytes: torch's reductions of bool tensors are several times slower)
        m8 = mask.view(torch.uint8)
        rows, cols = m8.amax(dim=(0, 1, 3)), m8.amax(dim=(0, 1, 2))  # (H,), (W,): 1 where the mask is
        top, bottom, left, right = torch.stack([rows.argmax(), H - 1 - rows.flip(0).argmax(), cols.argmax(),
                                                W - 1 - cols.flip(0).argmax()]).tolist()
        h, w_box = bottom - top + 1, right - left + 1
        box = (..., slice(top, bottom + 1), slice(left, right + 1))
        # (the two channels added as planes: a sum over the channel dimension of the box's strided
        # view is several times slower, python benchmarks/bench_image_fit.py --baseline)
        gap = (prediction[box].detach() - model[box].detach()).square_()
        gap = gap[:, 0] + gap[:, 1]
        gap = torch.where(mask[box][:, 0], gap, 0.0)
        # connected regions on the CPU (OpenCV): one transfer per call
        gap = gap.to("cpu", torch.float32).numpy()  # (NumPy has no bfloat16)
        # the judged points in the box (padding points, which carry no weight, clamped into it)
        px, py = pts.pix % W - left, torch.div(pts.pix, W, rounding_mode="floor") - top
        pix_np = (py.clamp(0, h - 1) * w_box + px.clamp(0, w_box - 1)).to("cpu").numpy()
        # a region of large differences inside one of small ones (a car beside a patch of road
        # the prediction got slightly wrong) stands apart at a higher threshold
        for threshold in (self.object_px, 2 * self.object_px, 4 * self.object_px):
            found = [cv2.connectedComponents((g > threshold ** 2).view(np.uint8), connectivity=8) for g in gap]
            L = max(n for n, _ in found)
            if L == 1:
                break  # no region apart at this threshold, nor at higher ones
            # each point's region (0: the flows agree), read frame by frame (no stacked copy of the labels)
            at = np.stack([labels.reshape(-1)[p] for (_, labels), p in zip(found, pix_np)]).astype(np.int64)
            at = torch.from_numpy(at).to(pts.pix.device)
            n, s, s2, s_pred = _sum_by(at, terms, L).unbind(1)
            diff = s / n.clamp_min(1)
            var = (s2 / n.clamp_min(1) - diff.square()).clamp_min(0)
            keep = ((n >= self.min_points_fine) & (diff > self.margin + self.z * (var / n.clamp_min(1)).sqrt())
                    & (s_pred <= 0))
            keep[:, 0] = False
            if not bool(keep.any()):
                continue
            # each region's part in each cell: where its own points favour the model by z
            # standard errors (no margin: the images decide, as for confirmed), the cell's
            # decision stands there
            n_p, s_p, s2_p = _sum_by(at * C + cell, terms[:, :3], L * C).unbind(1)
            diff_p = s_p / n_p.clamp_min(1)
            var_p = (s2_p / n_p.clamp_min(1) - diff_p.square()).clamp_min(0)
            favours = (n_p >= self.min_points) & (-diff_p > self.z * (var_p / n_p.clamp_min(1)).sqrt())
            keep_p = (keep.unsqueeze(2) & ~favours.reshape(B, L, C)).to("cpu").numpy()
            if kept is None:
                kept = np.zeros((B, H, W), dtype=bool)
                # each box pixel's cell
                box_cell = (np.arange(top, bottom + 1)[:, None] // ch) * grid_cols \
                    + np.arange(left, right + 1)[None, :] // cw
            kept[:, top:bottom + 1, left:right + 1] |= np.stack([keep_p[b][labels, box_cell]
                                                                  for b, (_, labels) in enumerate(found)])
        return None if kept is None else torch.from_numpy(kept).to(prediction.device).unsqueeze(1)

    def _cells(self, cell: Tensor, terms: Tensor, model_used: Tensor,
               size: tuple[int, int]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The decision on one grid of cells (``cell`` (B, N), each point's): where the model is
        used (B, 1, H, W) bool, the evidence for it (B, 1, H, W; 0 in a sample whose model is not
        used), and per cell (B, rows * columns) bool whether it has enough points and whether it
        keeps the prediction. ``terms`` (B, 4, N): at each point its weight w, w times the
        difference ``delta`` of the distances, w times its square, and the prediction's distance
        less ``occlusion`` times its weight ``w_pred``: the difference is judged over the points of
        weight w; the prediction explains a cell where its mean distance over those of w_pred (also
        where only the prediction can be judged) is at most ``occlusion``: its summed excess at
        most 0."""
        (H, W), (rows, cols), B, min_points = size, self.grid, terms.shape[0], self.min_points
        ch, cw = math.ceil(H / rows), math.ceil(W / cols)
        n, s, s2, s_pred = _sum_by(cell, terms, rows * cols).unbind(1)
        diff = s / n.clamp_min(1)  # > 0: the prediction explains the cell better
        var = (s2 / n.clamp_min(1) - diff.square()).clamp_min(0)
        worse = (diff > self.margin + self.z * (var / n.clamp_min(1)).sqrt()) \
            & (s_pred <= 0)
        enough = n >= min_points
        cell_model = torch.where(enough, ~worse, model_used.unsqueeze(1)) & model_used.unsqueeze(1)
        evidence = torch.where(enough, torch.sigmoid(-diff / self.temperature),
                               (0.5 * model_used.to(diff.dtype)).unsqueeze(1)) * model_used.unsqueeze(1)

        def to_pixels(c: Tensor) -> Tensor:
            # each cell's value over its ch x cw pixels (one copy: a broadcast view, reshaped)
            m = c.reshape(B, 1, rows, 1, cols, 1).expand(B, 1, rows, ch, cols, cw).reshape(B, 1, rows * ch, cols * cw)
            return m[..., :H, :W]

        return to_pixels(cell_model), to_pixels(evidence), enough, ~cell_model.reshape(B, -1)

    def __repr__(self) -> str:  # (these options, then the others where they are not the defaults)
        shown = ("grid", "objects", "points", "margin", "occlusion", "require_evidence")
        default = ImageGate.__init__.__kwdefaults__
        rest = [f"{k}={getattr(self, k)!r}" for k in default if k not in shown and getattr(self, k) != default[k]]
        return f"ImageGate({', '.join([f'{k}={getattr(self, k)}' for k in shown] + rest)})"
