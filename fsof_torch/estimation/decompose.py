"""The ``"plane"`` parameters of a road homography: a closed-form start and a fit on its flow.

Fitting is iterative and data dependent: it is not differentiable; its results are detached.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from .._check import batch_choices, check_float_tensor, check_has_values, check_int, check_shape, result_dtype
from ..geometry.camera import Camera
from ..geometry.road_flow import flow_from_map
from ..geometry.road_models import ROAD_MODELS, plane_from_homography
from .combine import where_motion
from .flow_fit import RoadFit, fit_road

__all__ = ["decompose_homography"]

#: The grid holds the pixels whose rays lie at least this far below the horizon of the attitude it
#: is built for (or half as far as the grid reaches below it, where that is less than twice this):
#: a road normal turned by θ moves a unit ray's height over the road by at most θ, so these pixels
#: are on the road, and their flow is the plane's, for every attitude within the margin. (A pixel
#: above the road's true horizon costs the fit as a far outlier: on the grid below the camera's
#: own horizon a road tilted by 1° from the camera's attitude was not found.)
_MARGIN = math.radians(3.0)
#: Fits on the grid below the previous fit's own horizon, until the grid stops changing: a road
#: attitude beyond the margin is approached by the first fit and found by the next (tested up to 5°
#: of roll and pitch from the camera's, tests/test_estimation_helpers.py).
_MAX_FITS = 3
#: The grid also holds only the pixels whose road point the homography takes to within this many times
#: the grid's own width and height beyond its edges at t+1 (seen in an image three times the grid's
#: size): the road just ahead of the camera at t+1 has an arbitrarily large flow, which dominated the
#: normal equations of a long step (a forward step of 8 m with a KITTI camera at 1.65 m: exact, and
#: reported as failed). Within the grid itself (0) a tilted road's grid lost the pixels that lead the
#: fits to it (tests/test_estimation_helpers.py).
_SEEN = 1.0


def decompose_homography(H: Tensor, camera: Camera, *, size: int = 192) -> RoadFit:
    """The ``"plane"`` parameters of road homographies (B, 3, 3) (pixels of t -> t+1).

    A calibrated homography ``K⁻¹ H K ∝ R + t nᵀ / h`` has two physical decompositions in general;
    the one reached from the camera's own roll and pitch (its calibrated attitude over the road)
    is returned, and with the camera height h the translation is metric. The start decomposes H
    with the road's normal of the camera's attitude
    (:func:`~fsof_torch.geometry.road_models.plane_from_homography`); :func:`fit_road` then frees
    the normal too, on the homography's own flow over the grid pixels whose rays lie a margin
    (3°) below the camera's horizon, then, while that grid changes (at most twice more), below
    the previous fit's own horizon; of those, the pixels that H takes to within the grid's own
    size beyond its edges (the road just ahead of the camera at t+1 has an unbounded flow). It
    is exact (residual about 1e-13 px) for a road homography whose road attitude is within a few
    degrees of the camera's and seen by the grid (tested to 5° of roll and pitch on a KITTI
    camera, and forward steps to 15 m, 9 camera heights, with ``success``). A homography without
    a translation holds no road normal: its roll and pitch are the start's, without ``success``. Every invertible homography is the motion of some
    plane; where that plane lies far from the camera's attitude or out of the grid's view, the fit
    may not reach it, and the residual says so. OpenCV's closed-form
    ``decomposeHomographyMat`` returns NaN for the commonest road motion, a translation without
    rotation.

    Args:
        H: (B, 3, 3) road homographies for the camera's K: finite and invertible, of any scale and
            sign (the sign is read from the determinant, positive at the physical scale).
        camera: K, height, and the roll and pitch to start from (batch 1 or B).
        size: the grid's longer side in pixels (each sample's camera is scaled to it: its grid
            is a virtual image around its own principal point, whatever its batch-mates'; for a
            camera looking up so far that its horizon lies below that image, the image of the
            same size just below the horizon).

    Returns:
        The :class:`RoadFit` of the ``"plane"`` model (``fit.params``; ``fit.residual``: how far
        the plane's flow is from the homography's on the grid, in the sample's grid pixels;
        ``fit.camera`` is the scaled camera; ``fit.iterations`` counts all its fits' iterations).
        ``fit.homography`` is the plane's homography for ``fit.camera``, so in the grid's pixels
        and not H: with ``S = fit.camera.K @ camera.K⁻¹``, ``S⁻¹ @ fit.homography @ S`` is H up
        to scale (to the residual's precision). ``fit.flow`` and ``fit.valid`` lie on a canvas as
        large as the batch's largest grid, each sample's grid at its top left (not valid beyond
        it). Its values are in H's dtype promoted with the camera's (float32 for half precision);
        the fit itself runs in float64.
    """
    check_float_tensor(H, "H")
    check_shape(H, "H", ("B", 3, 3))
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    B = H.shape[0]
    if camera.batch_size not in (1, B):
        raise ValueError(f"camera: expected batch {batch_choices(B)} (H's B), got {camera.batch_size}")
    size = check_int(size, "size", minimum=8)
    check_has_values(H, "H", "to decompose (the decomposition is a fit)")
    check_has_values(camera.K, "camera", "to decompose a homography (the decomposition is a fit)")
    if B == 0:
        raise ValueError("H: expected a non-empty batch, got shape (0, 3, 3)")
    H64 = H.detach().to(torch.float64)
    usable = torch.isfinite(H64).all((1, 2)) & (torch.linalg.det(H64).abs() > 0)
    if not bool(usable.all()):
        bad = (~usable).nonzero().flatten().tolist()
        raise ValueError(f"H: expected finite, invertible homographies, got samples {bad} "
                         f"that are not: {H64[bad[0]].tolist()}")
    cam = camera.to(torch.float64).expand(B).to(device=H.device)
    # each sample's own virtual image around its principal point, scaled so that its longer side
    # is ``size`` (the principal point's distance from the corner, also where a crop put it above
    # or left of the image): a sample's grid, and its residual in that grid's pixels, do not
    # depend on its batch-mates (one host read for the grids' sizes). A camera looking up so far
    # that its horizon lies below that image (no pixel of it sees the road) gets the image of the
    # same size just below the horizon (else its grid would be empty: the closed form came back
    # unrefined, with a residual of 0 over no pixel).
    ends = torch.stack([cam.horizon_row(torch.zeros_like(cam.cx)), cam.horizon_row(2.0 * cam.cx.abs())], dim=-1)
    scales, grids, tops = [], [], []
    for cx, cy, rows in zip(cam.cx.abs().tolist(), cam.cy.abs().tolist(), ends.tolist()):
        w0, h0 = 2.0 * cx + 1.0, 2.0 * cy + 1.0
        below = all(math.isfinite(r) for r in rows) and min(rows) >= h0 - 1.0  # (the horizon is a line)
        tops.append(max(rows) if below else 0.0)
        s = size / max(w0, h0)
        scales.append(s)
        grids.append((max(int(round(h0 * s)), 8), max(int(round(w0 * s)), 8)))
    # (Camera.cropped's shift by ``tops`` rows, then Camera.scaled's resize, one factor per sample)
    K_top = cam.K.clone()
    K_top[:, 1, 2] -= torch.tensor(tops, dtype=torch.float64, device=H.device)
    s = torch.tensor(scales, dtype=torch.float64, device=H.device)
    one, zero = torch.ones_like(s), torch.zeros_like(s)
    resize = torch.stack([s, zero, 0.5 * s - 0.5, zero, s, 0.5 * s - 0.5, zero, zero, one], dim=-1).reshape(B, 3, 3)
    small = cam.replace(K=resize @ K_top)
    S = small.K @ cam.K_inv()
    Hs = S @ H.to(torch.float64) @ torch.linalg.inv(S)
    # H's scale, and its sign from the determinant: at its physical scale K⁻¹ H K = R + t nᵀ / h has
    # det = h' / h > 0 (h' the camera's height over the road at t+1), and the grid's test q_z > 0 (the
    # road point in front of the camera at t+1) holds only at a positive scale. (H[2, 2] is q_z at
    # pixel (0, 0), whose road point can lie behind either camera: dividing by it emptied the grid of
    # such a homography, and it can be 0.)
    scale = torch.sign(torch.linalg.det(Hs)) / Hs.abs().amax(dim=(1, 2))
    Hs = Hs * scale.reshape(B, 1, 1)
    # one canvas for the batch, each sample's points only in its own grid at its top left (the
    # mask's raster order, and so the fit's sample of points, is then the sample's own)
    canvas = (max(g[0] for g in grids), max(g[1] for g in grids))
    rows = torch.tensor([g[0] for g in grids], device=H.device)
    cols = torch.tensor([g[1] for g in grids], device=H.device)
    inside = ((torch.arange(canvas[0], device=H.device) < rows[:, None])[:, None, :, None]
              & (torch.arange(canvas[1], device=H.device) < cols[:, None])[:, None, None, :])
    v, u = torch.meshgrid(torch.arange(canvas[0], dtype=torch.float64, device=H.device),
                          torch.arange(canvas[1], dtype=torch.float64, device=H.device), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)]).reshape(3, -1)
    extent = torch.stack([cols, rows], dim=-1).to(torch.float64).reshape(B, 2, 1, 1)  # (each sample's grid: w, h)
    ray_norm = (small.K_inv() @ pix).norm(dim=1)  # (B, h·w): |K⁻¹ p̃|

    def road_grid(roll: Tensor, pitch: Tensor) -> tuple[Tensor, Tensor]:
        """H's flow below the horizon of the road attitude (roll, pitch), and the grid pixels to
        fit: the rays at least the margin below that horizon (_MARGIN)."""
        horizon = ROAD_MODELS["paper"].horizon_row(small, torch.stack([torch.zeros_like(roll)] * 3 + [roll, pitch], dim=-1))
        flow, valid = flow_from_map(Hs, horizon, canvas)
        sine = ((horizon @ pix)[:, 0] / ray_norm).reshape(B, 1, *canvas)  # a · p̃ = n · K⁻¹ p̃
        deepest = torch.where(inside, sine, -1.0).flatten(1).amax(1)
        margin = torch.clamp(0.5 * deepest, max=math.sin(_MARGIN)).reshape(B, 1, 1, 1)
        # and whose road point H takes to at most the grid's own size beyond its edges (_SEEN): a point just
        # ahead of the camera at t+1 has an unbounded flow, and such pixels left an exact fit of a long step
        # ill-conditioned, reported as failed (from about 4 camera heights forward on a KITTI camera)
        ends = pix[:2].reshape(1, 2, *canvas) + flow
        seen = ((ends >= -_SEEN * extent) & (ends <= (1.0 + _SEEN) * extent)).all(1, keepdim=True)
        return flow, valid & inside & (sine >= margin) & seen

    def fit_grid(flow: Tensor, grid: Tensor, init: object) -> RoadFit:
        return fit_road(flow, grid, small, model="plane", fixed=(), init=init, robust="l2", polish=False, bounds=None,
                        max_points=4096, min_inlier_fraction=0.0, tol=1e-12)

    flow, grid = road_grid(small.roll, small.pitch)
    fit = fit_grid(flow, grid, plane_from_homography(Hs, small))
    for _ in range(_MAX_FITS - 1):
        flow, next_grid = road_grid(fit.params["roll"], fit.params["pitch"])
        # a sample whose grid stays keeps its fit (as it would alone, whatever its batch-mates do)
        moved = (next_grid != grid).flatten(1).any(1)
        if not bool(moved.any()):
            break
        refit = fit_grid(flow, next_grid, fit)
        refit.iterations = refit.iterations + fit.iterations
        fit = where_motion(moved, refit, fit)
        grid = torch.where(moved.reshape(B, 1, 1, 1), next_grid, grid)
    fit.valid = fit.valid & inside
    fit.flow = torch.where(inside, fit.flow, 0.0)
    dtype = result_dtype(H, camera.K)
    if dtype != fit.homography.dtype:
        fit = replace(fit, params={k: v.to(dtype) for k, v in fit.params.items()}, homography=fit.homography.to(dtype),
                      flow=fit.flow.to(dtype), residual=fit.residual.to(dtype), covariance=fit.covariance.to(dtype),
                      cost=fit.cost.to(dtype), camera=fit.camera.to(dtype))
    return fit
