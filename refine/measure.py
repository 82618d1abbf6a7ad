"""What the refine job measures: per-pixel maps of a flow, computed once per flow, and the metrics
of a prediction and its refinement on the same pixels.

Photometric error of three kinds side by side (DESIGN.md §6): L1 on raw intensities (``photo``,
0..255), structural dissimilarity (``ssim``, (1 − SSIM) / 2) and the census distance (``census``,
Hamming distance of 7×7 census bits / 48). L1 alone misleads on real images: exposure changes
between the frames charge a correct flow, and a flow method that bends its flow to match
brightness is rewarded; census compares only the order of neighbouring grey levels. With ground
truth, also end-point error (``epe``), angular error (``ae``) and the KITTI outlier rate (``fl``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

#: photometric metrics: (record key prefix, ``photometric_error_maps`` kind, what it is)
PHOTO = (("census", "census", "census distance (0-1)"),
         ("ssim", "ssim", "SSIM dissimilarity (0-1)"),
         ("photo", "l1", "L1 photometric error (0-255)"))
#: ground-truth metrics: (record key prefix, ``flow_error_maps`` name)
FLOW_ERRORS = (("epe", "e_E"), ("ae", "e_A"), ("fl", "Fl"))


#: how far the windowed kinds reach: the 7-tap SSIM window and the 7×7 census both see 3 px
_REACH = 3


def flow_maps(pair: dict, flow: Tensor, reference: dict[str, Tensor] | None = None) -> dict[str, Tensor]:
    """The per-pixel maps of one flow (2, H, W), computed once and reduced over any region.

    Returns ``flow`` (NaN and inf replaced by 0) and ``finite`` (1, H, W); per photometric prefix
    of :data:`PHOTO` the error map (``census``, ``ssim``, ``photo``) and where it is defined
    (``census_valid``, ...: the sample point, and for the windowed kinds its window, inside
    image 2); with ground truth ``e_E`` (px), ``e_A`` (rad), ``Fl`` (0/1) and ``gt_valid``.

    ``reference``: the maps of another flow of the same pair (the prediction, for its
    refinement). Only the box within reach of the pixels where the two flows differ is then
    computed, the rest is copied: the refiner changes the road, and census and SSIM over a whole
    KITTI frame cost 0.1 s per flow. The values equal a computation over the whole image (the
    census and L1 bit for bit, SSIM to float rounding of its convolutions).
    """
    finite = torch.isfinite(flow).all(dim=0, keepdim=True)
    # inf as well as NaN to 0 (nan_to_num's default turns inf into the dtype's largest value,
    # whose end-point error overflows); ``finite`` keeps these pixels out of every metric
    f = torch.nan_to_num(flow, nan=0.0, posinf=0.0, neginf=0.0)
    if reference is None:
        return {"flow": f, "finite": finite, **_maps_in_box(pair, f, None)}
    changed = (f != reference["flow"]).any(dim=0, keepdim=True) | (finite != reference["finite"])
    box = _bounding_box(changed[0], _REACH)
    out = {**reference, "flow": f, "finite": finite}
    if box is None:
        return out
    top, bottom, left, right = box
    for key, part in _maps_in_box(pair, f, box).items():
        full = out[key].clone()
        full[:, top:bottom, left:right] = part
        out[key] = full
    return out


def _bounding_box(mask: Tensor, margin: int) -> tuple[int, int, int, int] | None:
    """(top, bottom, left, right), ends exclusive, of the True pixels of an (H, W) mask grown by
    ``margin`` and clipped to the image; None when nothing is True."""
    rows, cols = mask.any(dim=1).nonzero(), mask.any(dim=0).nonzero()
    if rows.numel() == 0:
        return None
    H, W = mask.shape
    return (max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, H),
            max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, W))


def _maps_in_box(pair: dict, f: Tensor, box: tuple[int, int, int, int] | None) -> dict[str, Tensor]:
    """The photometric and ground-truth maps of the finite flow ``f`` (2, H, W) inside ``box``
    (top, bottom, left, right; None: the whole image), each (1, h, w)."""
    from fsof_torch import photometric_error_maps
    from fsof_torch.evaluation.metrics import flow_error_maps

    image1, image2 = pair["image1"], pair["image2"]
    H, W = f.shape[-2:]
    top, bottom, left, right = (0, H, 0, W) if box is None else box
    if box is None:
        window = (0, H, 0, W)
        flow_w = f
    else:
        # The photometric maps of a sub-image: images cut to a window that holds every sample
        # point of the box's pixels and of their census and SSIM windows. The flow is rewritten
        # so that the warp's sample coordinates (pixel + flow, in the warp's dtype) are the whole
        # image's shifted by the window's origin, without a new rounding (for any flow that does
        # not carry a pixel most of the way across the image): the same taps and weights.
        window = _window(f, box)
        wt, wb, wl, wr = window
        dtype = torch.promote_types(torch.promote_types(image1.dtype, image2.dtype), f.dtype)
        dtype = torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype
        v, u = (torch.arange(a, b, dtype=dtype, device=f.device) for a, b in ((wt, wb), (wl, wr)))
        grid = torch.stack(torch.broadcast_tensors(u[None, :], v[:, None]))
        flow_w = (grid + f[:, wt:wb, wl:wr].to(dtype)) - grid
    wt, wb, wl, wr = window
    photo = photometric_error_maps(image1[None, :, wt:wb, wl:wr], image2[None, :, wt:wb, wl:wr], flow_w[None],
                                   kinds=tuple(kind for _, kind, _ in PHOTO))
    inner = (slice(None), slice(top - wt, bottom - wt), slice(left - wl, right - wl))
    maps = {}
    for prefix, kind, _ in PHOTO:
        error, valid = photo[kind]
        maps[prefix], maps[f"{prefix}_valid"] = error[0][inner], valid[0][inner]
    if pair.get("flow") is not None:
        gt, valid = pair["flow"], pair["valid"]
        cut = (slice(None), slice(top, bottom), slice(left, right))
        errors, counted = flow_error_maps(f[cut][None], gt[cut][None].to(f.dtype), None, valid[cut][None])
        maps.update({name: errors[name][0] for _, name in FLOW_ERRORS})
        maps["gt_valid"] = counted[0]
    return maps


def _window(f: Tensor, box: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """The sub-image that computes ``box`` exactly: the box grown by the windows' reach, joined
    with the bilinear taps of every sample point of those pixels that lies inside the image."""
    H, W = f.shape[-2:]
    top, bottom, left, right = (max(box[0] - _REACH, 0), min(box[1] + _REACH, H),
                                max(box[2] - _REACH, 0), min(box[3] + _REACH, W))
    v, u = torch.meshgrid(torch.arange(top, bottom, dtype=f.dtype, device=f.device),
                          torch.arange(left, right, dtype=f.dtype, device=f.device), indexing="ij")
    x, y = u + f[0, top:bottom, left:right], v + f[1, top:bottom, left:right]
    inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    if bool(inside.any()):
        big = torch.full((), float("inf"), dtype=f.dtype, device=f.device)
        small = -big
        x_min, x_max = float(torch.where(inside, x, big).min()), float(torch.where(inside, x, small).max())
        y_min, y_max = float(torch.where(inside, y, big).min()), float(torch.where(inside, y, small).max())
        top, bottom = min(top, math.floor(y_min)), max(bottom, min(math.floor(y_max) + 2, H))
        left, right = min(left, math.floor(x_min)), max(right, min(math.floor(x_max) + 2, W))
    return top, bottom, left, right


def _labels(classes: Tensor, own: Tensor, n_classes: int) -> tuple[Tensor, list[int]]:
    """Each pixel's class where ``own`` holds, else ``n_classes`` (left out), flattened; and the
    number of counted pixels per class. ``classes``: (1, H, W) int64 in [0, n_classes)."""
    labels = torch.where(own, classes, n_classes).reshape(-1)
    return labels, torch.bincount(labels, minlength=n_classes + 1)[:n_classes].tolist()


def _class_sums(labels: Tensor, values: Tensor, n_classes: int) -> list[float]:
    """Float64 sum of ``values`` (1, H, W) per class of :func:`_labels`: one pass per map,
    whatever the number of regions (a masked sum per metric and region, 36 per flow, cost twice as
    much on a KITTI frame). ``scatter_add_`` adds in pixel order, as ``bincount`` with weights
    does (the same sums, bit for bit), in half its time on the CPU."""
    weights = values.reshape(-1).to(torch.float64)
    sums = torch.zeros(n_classes + 1, dtype=torch.float64, device=weights.device)
    return sums.scatter_add_(0, labels, weights)[:n_classes].tolist()


def compare(before: dict[str, Tensor], after: dict[str, Tensor], road: Tensor) -> tuple[dict, dict]:
    """Metrics of the prediction and of the refined flow on the same pixels.

    Each photometric kind (:data:`PHOTO`) is averaged over the pixels where both flows are finite
    and both are defined (sample point, and window, inside image2; so that a flow that pushes
    pixels out of the image is not rewarded for it), inside the road and overall: keys
    ``census_road``, ``ssim_all``, ``photo_road`` (L1), ... each with its pixel count
    (``..._n``; the metric None where that count is 0). With ground truth: e_E / e_A / Fl over the
    valid ground-truth pixels where both flows are finite (KITTI style: ``epe_road``, ``epe_all``,
    ``ae_*``, ``fl_*``), and each
    photometric kind once more over those pixels (``census_road_noc``, ``photo_all_noc``, ...): a
    pixel occluded in image 2 has no true match, so no flow explains its brightness and the error
    there rewards a flow that points at a look-alike instead (on the synthetic scene the exact
    flow scores 24.9 grey levels of L1 on its occluded road pixels, DIS 10.4).
    """
    finite = before["finite"] & after["finite"]
    gt = "gt_valid" in before
    # every pixel in one class: road or not (+1), and with ground truth, valid there or not (+2);
    # a region is a set of classes
    classes = road.to(torch.int64)
    regions = {"road": (1,), "all": (0, 1)}
    if gt:
        classes = classes + 2 * before["gt_valid"].to(torch.int64)
        regions = {"road": (1, 3), "all": (0, 1, 2, 3), "road_noc": (3,), "all_noc": (2, 3)}
    n_classes = 4 if gt else 2
    common = {prefix: finite & before[f"{prefix}_valid"] & after[f"{prefix}_valid"] for prefix, _, _ in PHOTO}
    columns = [(prefix, prefix, common[prefix], regions) for prefix, _, _ in PHOTO]
    if gt:  # flow errors are counted on the ground truth's valid pixels only
        columns += [(prefix, name, finite, {"road": (3,), "all": (2, 3)}) for prefix, name in FLOW_ERRORS]
    out: tuple[dict, dict] = ({}, {})
    for prefix, name, own, column_regions in columns:
        labels, counts = _labels(classes, own, n_classes)  # the same pixels before and after
        for stage, maps in zip(out, (before, after)):
            sums = _class_sums(labels, maps[name], n_classes)
            for region, members in column_regions.items():
                n = sum(counts[c] for c in members)
                # over no pixel (e.g. a flow that is NaN everywhere) a metric has no value, not 0
                stage[f"{prefix}_{region}"] = sum(sums[c] for c in members) / n if n else None
                stage[f"{prefix}_{region}_n"] = n
    return out


def evaluate(pair: dict, pred: Tensor, refined: Tensor, road: Tensor) -> tuple[dict, dict]:
    """:func:`compare` of a prediction and its refinement (both (2, H, W)); ``road`` (1, H, W)."""
    return compare(flow_maps(pair, pred), flow_maps(pair, refined), road)


def error_panel(maps: dict[str, Tensor]) -> tuple[Tensor, Tensor, str]:
    """The map a figure shows for a flow, where it is defined, and its name: end-point error with
    ground truth, else the census distance (the photometric judge that exposure changes do not
    fool)."""
    if "e_E" in maps:
        return maps["e_E"], maps["gt_valid"] & maps["finite"], "end-point error (px)"
    return maps["census"], maps["census_valid"] & maps["finite"], "census distance (0-1)"


def max_flow(pair: dict, pred: Tensor, road: Tensor | None = None) -> float:
    """One colour scale for before and after: the 99th percentile of the ground truth's magnitude
    over its valid pixels, or of the prediction's, inside the road when ``road`` (1, H, W) has
    pixels (the road is what the figures are about; the much larger flow of nearby buildings
    would wash it out), else over the image."""
    if pair.get("flow") is not None:
        flow, valid = pair["flow"], pair["valid"]
    else:
        flow = torch.nan_to_num(pred, nan=0.0, posinf=0.0, neginf=0.0)
        valid = torch.isfinite(pred).all(dim=0, keepdim=True)
    if road is not None and bool((valid & road).any()):
        valid = valid & road
    mag = torch.where(valid[0], torch.hypot(flow[0], flow[1]), torch.full((), -1.0, dtype=flow.dtype)).flatten()
    n_valid = int(valid.sum())
    if n_valid == 0:
        return 1.0
    k = mag.numel() - n_valid + max(1, math.ceil(0.99 * n_valid))  # the invalid -1s sort first
    return max(float(mag.kthvalue(k).values), 1.0)
