"""Road motion from the two images themselves: a direct, coarse-to-fine, robust photometric fit.

Flow methods fail on the road exactly where its motion is large and its texture weak (the bottom
of the image), and a fit to such a flow inherits the failure. The road's motion is nevertheless
fixed by a handful of parameters, and the images determine them. For any road model
(:mod:`fsof_torch.geometry.road_models`) this module minimises, with the library's one solver,

    E(p, a, b) = Σ_points ρ( a · I_2(x + f(x; p)) + b − I_1(x) ) + priors(p)

over the road pixels x of frame t, where a gain a and an offset b absorb an exposure change
between the frames, ρ is a robust kernel (moving cars and mask errors are outliers), and the
priors are Gaussian (a MAP estimate; DESIGN.md §10: the camera's attitude over the road stays
within about a degree of its calibration, the body's pitch and roll change by tenths of a degree
per frame, its vertical motion is centimetres).

- **Coarse to fine** over an image pyramid (kornia), each level starting where the coarser one
  ended.
- **Pixel selection weighted by gradient**: at each level, of road pixels evenly spread over
  the mask, those with the strongest gradient (they carry the information; ``max_points`` and
  ``gradient_fraction`` in :func:`fit_image`).
- **Cheap iterations**: the sample points are fixed per level; an iteration evaluates the model's
  3×3 map, samples the second image and its gradients at the points (one ``grid_sample``) and
  uses the average of both images' gradients (efficient second-order minimisation).
- **Several starts**, each solved at the coarsest level and chosen by the robust image cost both
  ways (:mod:`~fsof_torch.estimation.starts`): zero motion, straight ahead at a few speeds, and
  whatever the caller gives (a fit to a network's flow, the previous frame's motion, a
  constant-velocity prediction).
- **Bounds** that make absurd answers impossible, and the fit's own confidence: its robust
  cost, its inlier share and its parameters' covariance.

Images are (B, 1 or 3, H, W) on 0..``data_range`` (converted to grey and to the 0..255 scale);
the mask marks road pixels of image 1. Not differentiable: it runs in ``torch.inference_mode`` and its
results are ordinary, detached tensors.
"""

from __future__ import annotations

import inspect
import math
from typing import Any, Mapping, Sequence

import torch
from torch import Tensor

from .._check import (autocast_off, batch_choices, check_data_range, check_fit_flags, check_has_values,
                      check_image_pair, check_image_range, check_keywords, check_same_device, check_shape, inference,
                      result_dtype, scalar)
from ..evaluation.photometric import to_grey
from ..geometry.camera import Camera
from ..geometry.road_flow import flow_from_map
from ..geometry.road_models import RoadModel, pack_params
from .flow_fit import RoadFit
from .sampling import sample_mask
from .confidence import backward_correlation, detail_correlation, photometric_inliers, spread_out, warped_samples
from .priors import DEG, calibration_prior, clear_of_bounds, physical_bounds, prior_arrays
from .pyramid import band, gaussian_blur, image_pyramid, level_camera, mask_pyramid, pyramid_levels
from .image_options import check_bounds, check_prior_values, checked_options, held_parameters
from .image_problem import level_problem, level_scale
from .starts import (REVERSE_STARTS, TURN_STARTS, better_fit, reverse_moves, screened_start, start_list, starts_ahead,
                     turn_moves, two_way_cost)
from .solver import Solution, positive_definite, solve

__all__ = ["fit_image", "fit_photometric", "check_image_fit_options", "calibration_prior", "physical_bounds",
           "image_pyramid", "gaussian_blur", "DEG"]

# a coarser level ends when a step moves (or the next step is predicted to move) the residuals by
# less than this fraction of their RMS
_COARSE_RESOLUTION = 0.1
# the steps backwards solved in turn, best screened first: a receding road leaves much of image 1's
# near road out of image 2's view, and at the coarsest level the census tells the steps apart less
# surely than it does the turns (python benchmarks/turn_screen.py; tests/test_fit_starts.py, fast
# backward frames whose best-ranked step descends to a wrong motion)
_REVERSE_TRIES = 2


def _grey_pair(image1: Tensor, image2: Tensor, dtype: torch.dtype) -> Tensor | None:
    """The (B, 2, H, W) tensor of ``dtype`` (contiguous) whose two channels are grey frames
    ``image1`` and ``image2`` (B, 1, H, W), where they are that (read as it is: not written), else
    None."""
    B, C, H, W = image1.shape
    if not (C == 1 and image2.shape == image1.shape and image1.dtype == image2.dtype == dtype
            and image1.device == image2.device and image1.stride() == image2.stride() == (2 * H * W, H * W, W, 1)):
        return None
    if image1.untyped_storage().data_ptr() != image2.untyped_storage().data_ptr() or \
            image2.storage_offset() != image1.storage_offset() + H * W:
        return None
    return image1.detach().as_strided((B, 2, H, W), (2 * H * W, H * W, W, 1))


def _check_images(image1: Tensor, image2: Tensor, mask: Tensor, camera: Camera,
                  data_range: float) -> tuple[dict, Tensor]:
    dims = check_image_pair(image1, image2)
    if dims["H"] < 2 or dims["W"] < 2:
        raise ValueError(f"image1: expected images of at least 2x2 pixels, got {tuple(image1.shape)}")
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise TypeError(f"mask: expected a bool tensor of shape (B, 1, H, W), got "
                        f"{mask.dtype if isinstance(mask, Tensor) else type(mask).__name__}")
    if mask.dim() == 4 and mask.shape[0] == 1 and dims["B"] != 1:
        mask = mask.expand(dims["B"], -1, -1, -1)
    check_shape(mask, "mask", ("B", 1, "H", "W"), dims)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    if camera.batch_size not in (1, dims["B"]):
        raise ValueError(f"camera: expected batch {batch_choices(dims['B'])} (the images' B), got {camera.batch_size}")
    data_range = check_data_range(data_range)
    check_image_range(image1, "image1", data_range)
    check_image_range(image2, "image2", data_range)
    return dims, mask


@inference
def fit_image(image1: Tensor, image2: Tensor, mask: Tensor, camera: Camera, *,
              model: str | RoadModel = "plane", fixed: object = None, init: Any = None,
              starts: Sequence[Any] = (), prior: Mapping[str, tuple[Any, Any]] | str | None = "calibration",
              bounds: str | tuple[Tensor, Tensor] | None = "physical", levels: int | None = None,
              min_size: int = 16, max_iter: int = 12, tol: float = 1e-6, resolution: float = 0.02,
              smooth_sigma: float = 0.0, highpass: float | None = 4.0, band_levels: int = 2, masked_band: bool = False,
              robust: str = "cauchy", scale: float | None = None, max_points: int | None = 3000,
              gradient_fraction: float = 0.5, fine_points: int | None = None, affine: bool = True,
              inlier_threshold: float = 10.0,
              min_points: int = 100, min_inlier_fraction: float = 0.25, min_correlation: float = 0.5,
              data_range: float = 255.0, check_every: int | None = 2,
              forward_starts: Sequence[float] = (2.0, 4.0), turn_starts: Sequence[float] = TURN_STARTS,
              reverse_starts: Sequence[float] = REVERSE_STARTS,
              retry_starts: int = 2, retry_without_prior: bool = True) -> RoadFit:
    """Fit a road model's motion by minimising the road's robust photometric error.

    Args:
        image1, image2: the frames at t and t+1, (B, 3, H, W) RGB or (B, 1, H, W) grey, on
            0..``data_range``.
        mask: road pixels of image1 (B, 1, H, W) bool (batch 1 broadcasts).
        camera: intrinsics at the images' resolution, known height, and the calibrated roll and
            pitch (start, and centre of the prior and the bounds).
        model: ``"plane"`` (default), ``"paper"`` or ``"homography"``.
        fixed: parameter names held at ``init``'s values (default: none for ``"plane"`` and
            ``"homography"``, the pitch for ``"paper"``), in every start, and not bounded.
        init: the first start (a dict of any of the model's parameters, or a :class:`RoadFit`:
            another model's fit or dict gives the parameters they share, and one sharing none is
            a ValueError; the others at zero motion and the camera's roll and pitch); fixed
            parameters stay at it.
        starts: further start candidates, each a dict or fit whose parameters override ``init``'s,
            except the fixed ones (e.g. a fit to a network's flow, the previous frame's motion, a
            constant-velocity prediction). Each is solved at the coarsest level; the one with the
            lowest robust image cost, both ways (image 1's road into image 2 and image 2's back,
            :func:`~fsof_torch.estimation.starts.two_way_cost`) at the next finer level's
            intensities (each with its gain and offset, matched anew where the coarsest level
            compares a band of detail), goes on.
        forward_starts: further starts straight ahead, by these many camera heights per frame
            (z_d = k h; the other parameters as ``init``): from zero motion or a poor flow the fit
            can land on a wrong motion when the car moves a few heights a frame; these find fast
            driving (at 10 Hz and a 1.65 m high camera, 2 and 4 heights are 119 and 238 km/h).
            Not used where z_d (the homography: any parameter) is fixed; ``()``: none.
        turn_starts: where the fit from every start (and runner-up) fails or succeeds only weakly
            (below), the turn among these (degrees of yaw per frame, at one camera height ahead)
            whose motion best aligns the coarsest level's images (a screen: one batched cost, no
            fit) is solved from the coarsest level too; a failed frame takes it where it succeeds
            or its images correlate better, a weak success where it succeeds and correlates
            better. A sharp turn moves the whole image sideways, beyond the basin of the starts
            straight ahead, and often beyond what a network's flow finds. Costs nothing where
            the fit succeeds clearly; not used where the yaw (the homography: any parameter) is fixed; ``()``: none.
        reverse_starts: the last resort, where the fit still fails or succeeds only weakly after the
            turns and the retry without the prior (below): the steps straight backwards among these
            (camera heights per frame: z_d = -k h, no yaw) that best align the coarsest level's
            images, screened as the turns are; the best two are solved in turn (the census ranks large
            steps less surely: much of the near road leaves image 2's view), each taken as the turns
            are but as a success only where its detail correlates clearly (as the retry's), judged
            both ways: by the better of image 1's side and image 2's
            (:func:`~fsof_torch.estimation.confidence.backward_correlation`; a receding road's near
            detail in image 1 falls on image 2's far, smaller road, which holds less of it;
            ``extras["correlation"]`` is then the better one). The backward flow of forward driving
            (image 2 to image 1, as a forward-backward check computes it), or a car reversing, moves
            the road away from the camera, opposite to every start straight ahead; from zero motion
            the fit can land short of such a motion from about half a camera height a frame. Screened
            apart from the turns, and last: on real turning frames a step backwards could outrank the
            right turn, and on fast forward frames its fit, descending forwards, could pass a wrong
            motion as a success before the retry without the prior finds the right one. Costs nothing
            where the fit succeeds clearly; not used where z_d (the homography: any parameter) is fixed; ``()``: none.
        retry_starts: where the winning start's fit fails (below), or succeeds only weakly (its
            detail correlating below halfway from ``min_correlation`` to 1), up to this many
            runners-up, in the order of their two-way cost, are carried down the pyramid in
            turn. A runner-up overrules the coarse cost's ranking, so it counts as a success only
            where its detail correlates clearly (at least halfway); a failed frame keeps the
            first that does (else the one whose images correlate best), a weak success gives way
            to one that correlates better. The two-way cost at a coarse level can prefer a wrong
            motion (a predicted flow that lost the near road can point backwards; a jolt of the
            body can send a start far ahead, where a blurred level matches the few points in
            view); the tests at full resolution tell. Costs nothing where the winner succeeds
            clearly. 0: none.
        retry_without_prior: where the fit still fails or succeeds only weakly (and after the
            turns), the starts compete once more without the prior at the coarsest level (the
            finer levels keep it); a frame takes that fit where it succeeds with its detail
            correlating at least halfway from ``min_correlation`` to 1 (without the prior's guard
            a fit needs clearer evidence), and a failed frame also where its images correlate
            better. A jolt of the body (2° of pitch in a frame) lies beyond what the prior lets
            the coarsest level's few points reach; at speed the same prior keeps the coarse fits
            plausible, so it stays. Costs nothing where the fit succeeds clearly.
        prior: ``"calibration"`` (:func:`calibration_prior`, on the free parameters), None, or
            ``{name: (mean, sigma)}`` (a prior on a held parameter is a ValueError: it would be ignored).
        bounds: ``"physical"`` (:func:`physical_bounds`), None, or ``(lower, upper)`` (B, P) or (1, P):
            they hold the free parameters (a fixed one stays at ``init``'s value, even outside them); a fit
            with a free parameter within its standard deviation of a bound fails (the bound placed it).
        levels, min_size: pyramid levels (default: halve until the shorter side would drop below
            ``min_size``; fewer leave the coarsest level too fine for a start to reach a motion
            of tens of pixels there, and the fit can land far off: on the shared clip with two,
            40 px and more, its successes weak, ``python benchmarks/fit_confidence.py``; more than
            1 + ⌈log2 max(H, W)⌉, past a level of 1 × 1 pixel, is a ValueError);
            ``max_iter``, ``tol``: the solver's budget and tolerance per level;
            ``resolution``: a level also ends when a step moves the residuals by less than this
            fraction of their robust RMS (see :func:`~fsof_torch.estimation.solver.solve`); the
            coarser levels, which only have to land in the next one's basin, at 0.1 or more, and
            also where the next step is predicted to move them by less (the solver's ``predict``).
        smooth_sigma: Gaussian smoothing of the grey images (pixels) before the pyramid (0:
            none; a blur of fixed width does not commute with the road's magnification between
            the frames, and biases the fit at full resolution).
        highpass, band_levels: the ``band_levels`` finest levels compare each image minus its
            Gaussian blur of ``highpass`` pixels (of that level): the detail, not the lighting,
            which changes between real frames with exposure, vignetting and shade (None or 0: the
            intensities themselves; coarser levels always do, for a wide basin). A narrow band
            keeps the blur's mismatch under magnification small; docs/image-fit.md compares
            widths on real and synthetic frames.
        masked_band: each band's blur is the mean over the level's road mask only (normalised
            convolution, :func:`~fsof_torch.estimation.pyramid.band`), in both frames: a kerb or
            a verge beside the road does not enter the road's band, where it pulls the pitch and
            the vertical motion (docs/image-fit.md, "The band inside the mask"). Image 2's band
            uses image 1's mask, which misses the road that the motion moves out of it. False:
            the blur of every pixel.
        robust, scale: the kernel and its scale in grey levels on 0..255, whatever ``data_range``
            (default: 1.4826 × the median absolute residual at each level's start, at least 2).
        max_points, gradient_fraction: the points per frame and level that enter the
            iterations: the ``max_points`` road pixels with the strongest gradient among up to
            ``max_points / gradient_fraction`` evenly spread over the mask (on a level of fewer
            pixels than that, ``gradient_fraction`` of its pixel count instead of
            ``max_points``); all of a level's road pixels where it has no more than that many.
            ``max_points=None``: of all of each frame's road pixels, the ``gradient_fraction``
            share with the strongest gradient (slower; a frame's points do not depend on the
            rest of the batch). ``gradient_fraction=1``: up to ``max_points`` road pixels evenly
            spread, whatever their gradient.
        fine_points: at full resolution (the finest level) instead, up to this many road pixels
            evenly spread, whatever their gradient: the cost over more points has its minimum
            nearer the truth, and more points there cost less time than more at every level
            (docs/image-fit.md, "Points spread evenly"). None: as the coarser levels.
        affine: also fit a gain and an offset between the frames' brightness.
        inlier_threshold: |photometric residual| (grey levels on 0..255, as ``scale``) of an inlier
            at full resolution, image 2's intensities matched to image 1's by their own gain and offset.
        min_points, min_inlier_fraction: fewer inliers (or inliers on fewer than 3 rows or columns: a band that
            thin matches under many motions), or a smaller share of the mask's points that the model keeps
            inside image 2 (the others cannot be judged: at speed the road near the car leaves the frame), mark
            the frame as failed (as does a diverged or ill-conditioned fit, or one held by a bound).
        min_correlation: the frame also fails where the fitted motion aligns the images' detail
            (the finest level's band, or the intensities where ``highpass`` is None) with a
            correlation below this over the mask's points in view. A plain road's intensities
            match within ``inlier_threshold`` under almost any motion; its detail does not, unless
            it slides along itself (lane markings, a thin band of road: docs/image-fit.md). At
            0.5 the aligned images share as much of their detail's variance as they differ by.
        data_range: the images' range (255.0 or 1.0); the fit works on 0..255 either way.
        check_every: each level asks whether all samples converged (one host read) after this
            many iterations and then after every further one, so that no level runs on after
            its samples converged; the checks change no result. None: every level runs
            ``max_iter`` iterations, without a host read.

    Returns:
        :class:`~fsof_torch.estimation.flow_fit.RoadFit` of the model; ``residual`` and
        ``inliers`` refer to the photometric residual (grey levels on 0..255); ``extras`` holds
        ``gain`` and ``offset`` (B,) of the fit (of the finest level's band where it compares
        bands), ``inlier_fraction`` and ``correlation`` (B,), and ``converged`` (B,) bool: the
        full-resolution level converged (``success`` does not ask it: a fit that ran out of
        iterations is still judged by the image tests).
    """
    # (a 0-d tensor as its number: the levels' loops and the point budgets need Python numbers)
    (tol, resolution, smooth_sigma, highpass, scale, gradient_fraction, inlier_threshold, min_inlier_fraction,
     min_correlation, max_iter, max_points, min_points, levels, min_size, fine_points, band_levels, retry_starts,
     check_every) = (scalar(v, n) for n, v in dict(
        tol=tol, resolution=resolution, smooth_sigma=smooth_sigma, highpass=highpass, scale=scale,
        gradient_fraction=gradient_fraction, inlier_threshold=inlier_threshold,
        min_inlier_fraction=min_inlier_fraction, min_correlation=min_correlation, max_iter=max_iter,
        max_points=max_points, min_points=min_points, levels=levels, min_size=min_size, fine_points=fine_points,
        band_levels=band_levels, retry_starts=retry_starts, check_every=check_every).items())
    model, steps, turns, reverse, fixed, prior = checked_options(
        model=model, fixed=fixed, init=init, starts=starts, prior=prior, levels=levels,
        min_size=min_size, max_iter=max_iter, tol=tol, resolution=resolution, smooth_sigma=smooth_sigma,
        highpass=highpass, band_levels=band_levels, masked_band=masked_band, robust=robust, scale=scale,
        max_points=max_points, gradient_fraction=gradient_fraction, fine_points=fine_points, affine=affine,
        inlier_threshold=inlier_threshold,
        min_points=min_points, min_inlier_fraction=min_inlier_fraction, min_correlation=min_correlation,
        data_range=data_range, check_every=check_every, forward_starts=forward_starts, turn_starts=turn_starts,
        reverse_starts=reverse_starts, retry_starts=retry_starts, retry_without_prior=retry_without_prior)
    # (the frames and the mask on one device, named before torch's error from inside would come;
    # the camera and the starts follow image1's)
    check_same_device({n: t for n, t in (("image1", image1), ("image2", image2), ("mask", mask)) if isinstance(t, Tensor)})
    for name, t in (("image1", image1), ("image2", image2), ("mask", mask), ("camera", getattr(camera, "K", None))):
        check_has_values(t, name, "to fit (a fit is iterative and data dependent)")
    dims, mask = _check_images(image1, image2, mask, camera, data_range)
    check_bounds(bounds, model, dims["B"])
    B, H, W = dims["B"], dims["H"], dims["W"]
    out_dtype = result_dtype(image1, camera.K)
    dev = image1.device
    camera = camera.expand(B).to(device=dev)
    cam64 = camera.to(torch.float64)
    n_levels = pyramid_levels(H, W, levels, min_size)
    fixed_names = held_parameters(model, fixed, prior)
    P = len(model.params)
    # (None where every parameter is free: the solver then skips the fixed parameters' masking)
    free = (None if not fixed_names and affine else
            torch.tensor([n not in fixed_names for n in model.params] + [affine, affine], device=dev))

    with autocast_off(image1):
        work = torch.float64 if image1.dtype == torch.float64 else torch.float32
        # (both frames' grey written into one tensor: no copy of two; none at all where the frames
        # are already the two channels of one, as the refiner converts them)
        grey = _grey_pair(image1, image2, work)
        if grey is None:
            grey = image1.new_empty((B, 2, H, W), dtype=work)
            to_grey(image1.detach().to(work), out=grey[:, :1])
            to_grey(image2.detach().to(work), out=grey[:, 1:])
        if data_range != 255.0:  # (grey levels on 0..255: the residuals' and thresholds' unit)
            grey = grey * (255.0 / data_range)
        pyramid = image_pyramid(grey, n_levels, smooth_sigma)
        masks = mask_pyramid(mask, n_levels)

        _, default = pack_params(model, cam64, None)
        forward = starts_ahead(model, cam64, steps, fixed_names)
        candidates = start_list(model, cam64, init, list(starts) + forward, default)
        held = torch.tensor([n in fixed_names for n in model.params], device=dev)
        if fixed_names:  # (fixed parameters stay at init's value, else the default's, in every start)
            candidates = [torch.where(held, candidates[0], c) for c in candidates]
        S = len(candidates)
        ones, zeros = torch.ones(B, 1, dtype=torch.float64, device=dev), torch.zeros(B, 1, dtype=torch.float64, device=dev)
        params = torch.cat([torch.cat(candidates), ones.repeat(S, 1), zeros.repeat(S, 1)], dim=1)  # (S B, P + 2)
        prior_spec = ({n: v for n, v in calibration_prior(model, cam64).items() if n not in fixed_names}
                      if prior == "calibration" else prior)  # (a held parameter's prior has no effect)
        # each level weighs the prior by its residuals' noise: precision noise² / σ²
        prior_mean, inverse_variance = prior_arrays(model, prior_spec, B, dev)
        lo, hi = physical_bounds(model, cam64) if bounds == "physical" else (bounds or (None, None))
        # the bounds hold the free parameters: fixed ones (and the gain and offset) are not clamped
        unbounded = torch.cat([held, torch.ones(2, dtype=torch.bool, device=dev)])
        pad = torch.zeros(B, 2, dtype=torch.float64, device=dev)  # (the gain and offset: replaced)
        bound_lo = None if lo is None else torch.where(unbounded, -math.inf, torch.cat([lo.to(dev, torch.float64).expand(B, P), pad], 1))
        bound_hi = None if hi is None else torch.where(unbounded, math.inf, torch.cat([hi.to(dev, torch.float64).expand(B, P), pad], 1))

        checks = None if check_every is None else range(check_every, max_iter)
        # the mask's pixels (the tests at full resolution judge them all; the finest level's
        # points are drawn from them)
        points = sample_mask(mask, max_points)

        compared_levels: dict[int, Tensor] = {}

        def compared(level: int) -> Tensor:
            """The level's images as the fit compares them (the band of detail on the
            ``band_levels`` finest), once."""
            if level not in compared_levels:
                compared_levels[level] = band(pyramid[level], highpass if level < band_levels else None,
                                              masks[level] if masked_band else None)
            return compared_levels[level]

        def run(level: int, reps: int, params: Tensor, prior: bool = True) -> Solution:
            fine = level == 0 and fine_points is not None  # (the finest level's own points)
            problem = level_problem(model, level_camera(cam64, level), compared(level), masks[level],
                                     1.0 if fine else gradient_fraction, fine_points if fine else max_points, reps,
                                     points if level == 0 else None)
            rep = (lambda t: None if t is None else t.repeat(reps, 1))
            prior = prior and inverse_variance is not None
            precision = (lambda s: s.square().unsqueeze(-1) * rep(inverse_variance)) if prior else None
            return solve(problem, params, free=free, prior_mean=rep(prior_mean) if prior else None,
                         prior_precision=precision, lower=rep(bound_lo), upper=rep(bound_hi), kernel=robust,
                         scale=level_scale(scale, reps), max_iter=max_iter, tol=tol if level == 0 else max(tol, 1e-4),
                         # a coarse level only has to land in the next one's basin: it also ends
                         # where the next step is predicted not to matter
                         resolution=resolution if level == 0 else max(resolution, _COARSE_RESOLUTION),
                         check_every=checks, missing="mean", predict=level > 0)

        def descend(params: Tensor, top: int, prior: bool = True) -> tuple[Solution, Tensor, Tensor]:
            """From ``params`` (B, P + 2) down the pyramid from level ``top`` to full resolution (the
            prior at ``top`` with ``prior``, at the finer levels always)."""
            iterations = torch.zeros(B, dtype=torch.long, device=dev)
            sol = None
            for level in range(top, -1, -1):
                sol = run(level, 1, params, prior or level != top)
                params = sol.params
                iterations = iterations + sol.iterations
            return sol, params, iterations

        def judged(sol: Solution, params: Tensor, iterations: Tensor, both_ways: bool = False) -> dict[str, Tensor]:
            """The fit at full resolution and its tests (see ``success``); ``both_ways``: its
            detail correlates by the better of image 1's side and image 2's (a receding road)."""
            values, gain, offset = params[:, :P], params[:, P], params[:, P + 1]
            finite = torch.isfinite(params).all(-1)
            values = torch.where(finite.unsqueeze(-1), values, default)
            M = model.matrix(cam64, values)
            horizon = model.horizon_row(cam64, values)
            # (made outside inference mode, without autograd: a result the fit returns is then
            # not copied out of inference mode at its end; the same values)
            with torch.inference_mode(False), torch.no_grad():
                flow, valid = flow_from_map(M.to(out_dtype), horizon.to(out_dtype), (H, W))
            # the intensities and the compared band at every mask pixel in view
            band = compared(0)
            at1, at2, ok = warped_samples((grey[:, :1], band[:, :1]), (grey[:, 1:], band[:, 1:]), flow, valid,
                                          points)
            inliers, residual, fraction, n_in = photometric_inliers(at1[0], at2[0], ok, points, inlier_threshold,
                                                                    (H, W))
            correlation = detail_correlation(at1[1], at2[1], ok, points)
            if both_ways:
                correlation = torch.maximum(correlation, backward_correlation(band[:, :1], band[:, 1:], M, horizon,
                                                                              mask))
            A = sol.normal[:, :P, :P]
            d = A.diagonal(dim1=-2, dim2=-1).clamp_min(1e-300).sqrt()
            well_posed = positive_definite(A / (d.unsqueeze(-1) * d.unsqueeze(-2)), 1e-9)
            cov = sol.covariance(sol.scale)[:, :P, :P]
            # (one that ran out of iterations is still a fit: the refiner's gate judges it; extras["converged"] tells)
            success = (finite & well_posed & clear_of_bounds(values, cov, bound_lo, bound_hi) & (n_in >= min_points)
                       & spread_out(inliers) & (fraction >= min_inlier_fraction) & (correlation >= min_correlation))
            return {"values": values, "gain": gain, "offset": offset, "M": M, "flow": flow, "valid": valid,
                    "inliers": inliers, "residual": residual, "fraction": fraction, "correlation": correlation,
                    "success": success, "iterations": iterations, "covariance": cov,
                    "cost": sol.cost, "converged": sol.converged}

        coarse = n_levels - 1
        # a fit whose detail correlates at least halfway from the bar to 1 lines it up clearly;
        # a weaker success meets the runners-up, and one without the prior needs it (below)
        clear = 0.5 * (1.0 + min_correlation)

        def settled(fit: dict[str, Tensor]) -> bool:
            """Every frame's fit succeeded clearly (one host read): a weak success goes on too."""
            return bool((fit["success"] & (fit["correlation"] >= clear)).all())

        def clearly(fit: dict[str, Tensor]) -> dict[str, Tensor]:
            """``fit`` with only its clear successes counted as successes."""
            return {**fit, "success": fit["success"] & (fit["correlation"] >= clear)}

        def compete(prior: bool) -> dict[str, Tensor]:
            """The starts solved at the coarsest level (with its prior where ``prior``), the winner
            carried down, and runners-up where it fails or succeeds weakly."""
            if S == 1:
                return judged(*descend(params, coarse, prior))
            # the starts compete at the coarsest level, ranked by their two-way robust cost at the
            # next finer one's intensities (more points judge; one common kernel scale per frame;
            # gains and offsets fitted on a band of detail are matched to the intensities anew)
            sol = run(coarse, S, params, prior)
            judge = max(coarse - 1, 0)
            cost = two_way_cost(sol.params, model, level_camera(cam64, judge), pyramid[judge], masks[judge],
                                robust, max_points, S, match=compared(coarse) is not pyramid[coarse])
            order = cost.reshape(S, B).argsort(0)
            frames = torch.arange(B, device=dev)
            solved, moved = sol.params.reshape(S, B, -1), sol.iterations.reshape(S, B)
            # below the coarsest level; a single level solves once more on the winner
            top = coarse - 1 if coarse > 0 else 0

            def carried(rank: int) -> dict[str, Tensor]:
                pick = order[rank]
                sol, params, iterations = descend(solved[pick, frames], top, prior or coarse > 0)
                return judged(sol, params, iterations + moved[pick, frames])

            fit = carried(0)
            for rank in range(1, min(S, 1 + retry_starts)):
                if settled(fit):  # (one host read per runner-up)
                    break
                # a runner-up overrules the coarse cost's ranking: it succeeds only clearly
                fit = better_fit(fit, clearly(carried(rank)), clear)
            return fit

        def screened(moves: list[tuple[float, float]], fit: dict[str, Tensor], backwards: bool) -> dict[str, Tensor]:
            """``fit``, or where it failed (or succeeded weakly) the best of the screened ``moves``
            solved from the coarsest level, where that does better (:func:`better_fit`). Steps
            ``backwards``: the best two in turn, each judged both ways and taken only where it
            succeeds clearly."""
            for rank in range(_REVERSE_TRIES if backwards else 1):
                if rank and settled(fit):  # (one host read)
                    break
                start = screened_start(model, level_camera(cam64, coarse), candidates[0], pyramid[coarse],
                                       masks[coarse], moves, fixed_names, robust, max_points, rank=rank)
                if start is None:
                    return fit
                other = judged(*descend(torch.cat([start, ones, zeros], dim=1), coarse), both_ways=backwards)
                fit = better_fit(fit, clearly(other) if backwards else other, clear)
            return fit

        fit = compete(True)
        done = settled(fit)  # (one host read; once more after each way on that runs)
        turning, backwards = turn_moves(turns, fixed_names), reverse_moves(reverse, fixed_names)
        if turning and not done:
            # every start failed (or succeeded weakly) somewhere: the best turn of the screen
            fit = screened(turning, fit, False)
            done = settled(fit)
        if retry_without_prior and prior_mean is not None and not done:
            # still failed (or weak): the images alone choose the basin at the coarsest level;
            # without the prior's guard such a fit must line the detail up clearly
            fit = better_fit(fit, clearly(compete(False)), clear)
            if backwards:
                done = settled(fit)
        if backwards and not done:
            # the last resort: the best step backwards, which must line the detail up clearly
            # (from a step backwards a fast forward fit can descend to a wrong motion that
            # passes the bar)
            fit = screened(backwards, fit, True)
    values, gain, offset, M = fit["values"], fit["gain"], fit["offset"], fit["M"]
    named = {n: values[:, i].to(out_dtype) for i, n in enumerate(model.params)}
    # (detached copies: results are detached, and not the caller's storage nor a batch-1 camera's expansion)
    own = {n: getattr(camera, n).detach().to(out_dtype, copy=True) for n in ("K", "height", "roll", "pitch")}
    cam_fit = Camera._checked(own["K"], own["height"], named.get("roll", own["roll"]), named.get("pitch", own["pitch"]))
    return RoadFit(model=model.name, params=named, homography=M.to(out_dtype), flow=fit["flow"], valid=fit["valid"],
                   inliers=fit["inliers"], residual=fit["residual"].to(out_dtype), success=fit["success"],
                   camera=cam_fit, iterations=fit["iterations"], covariance=fit["covariance"].to(out_dtype),
                   cost=fit["cost"].to(out_dtype), extras={"gain": gain.to(out_dtype), "offset": offset.to(out_dtype),
                                                           "inlier_fraction": fit["fraction"].to(out_dtype),
                                                           "correlation": fit["correlation"].to(out_dtype),
                                                           "converged": fit["converged"]})


def check_image_fit_options(options: Mapping[str, Any], name: str = "options", reserved: Sequence[str] = ()) -> None:
    """Keyword arguments for :func:`fit_image` (its options, not the images, mask or camera),
    checked as it checks them, before any fit: a name it does not take, or one of ``reserved`` (set
    by the caller), is a TypeError naming ``name``; a bad value (a ``fixed`` or ``prior`` name the
    model lacks and a prior on a held parameter among them) the TypeError or ValueError that
    fit_image would raise (the bounds' batch size, the values of ``init`` and a prior's of one value
    per frame aside: they need the batch). For estimators and clip fits that forward
    options to it."""
    check_keywords(options, name, fit_image, ("image1", "image2", "mask", "camera", *reserved))
    given = {**_fit_image_defaults(), **options}
    bounds = given.pop("bounds")
    checked = checked_options(**given)
    check_bounds(bounds, checked.model)
    # (the names and priors that only the model tells apart: as the fit checks them)
    held_parameters(checked.model, checked.fixed, checked.prior)
    check_prior_values(checked.model, checked.prior)


def _fit_image_defaults() -> dict[str, Any]:
    """fit_image's keyword-only arguments and their defaults."""
    params = inspect.signature(fit_image).parameters.values()
    return {p.name: p.default for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY}


def fit_photometric(image1: Tensor, image2: Tensor, mask: Tensor, camera: Camera, *, init: Any = None,
                    fit_roll: bool = True, fit_pitch: bool = False, **options: Any) -> RoadFit:
    """Fit the paper's displacement model (x_d, z_d, yaw; roll / pitch where ``fit_roll`` /
    ``fit_pitch``) to two images: :func:`fit_image` with ``model="paper"``, no prior and no
    bounds, every road pixel (up to 40 000 per level), intensities at every level smoothed by σ = 1, pyramid levels
    down to 24 pixels and 20 iterations per level unless given. Other options as there.
    """
    check_fit_flags("fit_photometric", fit_roll, fit_pitch, options)
    fixed = tuple(n for n, on in (("roll", fit_roll), ("pitch", fit_pitch)) if not on)
    if isinstance(init, RoadFit) and init.model != "paper":
        raise ValueError(f"init: expected a fit of the 'paper' model, got one of {init.model!r}")
    for name, value in (("prior", None), ("bounds", None), ("max_points", 40000), ("gradient_fraction", 1.0),
                        ("min_size", 24), ("max_iter", 20), ("highpass", None), ("smooth_sigma", 1.0)):
        options.setdefault(name, value)
    return fit_image(image1, image2, mask, camera, model="paper", fixed=fixed, init=init, **options)
