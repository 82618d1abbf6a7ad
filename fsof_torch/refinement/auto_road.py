"""The road found from two images: the region in front of the vehicle that moves like the road plane.

The road's motion between two frames is a plane-induced homography (DESIGN.md §10). Warped by
it, image 2 lines up with image 1 on the road and only there: a kerb, a pavement or a grass
verge a few centimetres higher moves by a little more, a car or a wall by much more. The detection:

1. **Seed.** A conservative band of road in front of the vehicle, from the geometry alone: the
   ground points within ``seed_width_m / 2`` of the camera's axis and nearer than
   ``seed_depth_m``, seen below the horizon (:func:`road_seed`). Turning, where the motion found
   with it (steps 2 to 5) takes the vehicle's path out of that band within its depth, the
   detection is made again from the band along the path (:mod:`~fsof_torch.refinement.seed`), and
   kept per sample where it is ok and its seed agrees more with its motion.
2. **Motion.** The road's motion fitted to the images in the seed (an image estimator, the
   predicted flow one start; where that fails, on a seed twice as deep), or the caller's. With
   ``refit`` the motion is fitted again on the detected road (its boundary on the edges, step 5)
   and the road detected again: the seed alone pins the motion poorly far from it. Sample by
   sample: each keeps the fits it would get alone.
3. **Evidence**, per window, at a working resolution (``level``): image 2 is warped by the road
   flow, and the residual against image 1 is compared with what noise and the model's own misfit
   τ explain, both measured in the seed (nothing is tuned to particular frames). A window is off
   the road where its residual motion (*misalignment*: the residual energy above the noise over
   its gradient energy) is significantly (``z`` standard errors) larger than half the parallax of
   a surface ``min_height_m`` high and than ``3 τ``; where its *height* over the road plane (a
   Lucas–Kanade step along the parallax direction) differs significantly from the seed's by more
   than ``min_height_m / 2`` (a kerb, a pavement, a verge); or where, textured, its residual
   exceeds its own texture (nothing lines up). It is road evidence where it is not off the road
   and *testable* (a surface ``max_height_m`` high would move by at least ``3 τ``) with the texture
   to show it (such a step's residual significantly above the noise: flat windows are not). Where
   less than a tenth of the seed carries evidence (driving slowly), the step is doubled, up to
   ``slow_max_height_m``, until it does: lower kerbs then pass for road, cars and walls still show.
4. **Region** (:mod:`~fsof_torch.refinement.road_region`). The road evidence connected to the
   seed; pixels without evidence take the majority around them, the seed's assumption (road) or
   the decision along their line through the focus of expansion; small undecided holes filled.
5. **Edges** (``edges``), at full resolution: the windows that straddle a car's base or a kerb
   are off the road, so the region's boundary lies up to half a window from the edge where the
   road ends. Within half a height window of it (outward, one smoothing radius more: the windows
   see smoothed images) the boundary follows image 1's edges (a marker-controlled watershed,
   :func:`~fsof_torch.refinement.road_region.follow_edges`); the refit's road keeps half a window.
6. **Flags** (:data:`FLAGS`). A sample whose road cannot be trusted is flagged with the reason,
   never silently returned (docs/auto-road.md, "Flags").

Images are (B, 1 or 3, H, W) on 0..``data_range``; masks (B, 1, H, W) bool. Not differentiable
(a segmentation); the caller's tensors are never modified.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from .._check import (all_finite, autocast_off, batch_choices, check_bool, check_data_range, check_float_tensor,
                      check_has_values, check_image_pair, check_image_range, check_same_device, check_shape,
                      host_path, inference, is_number, scalar, skip_values, summary_repr)
from ..estimation.pyramid import gaussian_blur
from ..evaluation.photometric import to_grey
from ..evaluation.warp import warp_backward
from ..geometry.camera import Camera
from ..estimation.combine import fit_at_size, select_samples, where_motion
from ..geometry.road_flow import road_flow
from ..geometry.road_models import road_motion, road_motion_batch
from .estimators import ImageMotionEstimator, check_estimate, check_estimator, finite_estimate
from .road_options import SLOW_MAX_HEIGHT_M, check_road_values
from .road_region import erode_mask, focus_of_expansion, follow_edges, road_region, upsample_mask
from .seed import ground as _ground, path_curvature, plane_motion as _plane_motion, road_seed, seed_mask

__all__ = ["RoadDetection", "detect_road", "road_seed", "road_level", "check_road_size", "FLAGS", "ROAD_RESERVED"]

#: detect_road's arguments the refiner sets itself: refused in ``road_options``, by name
ROAD_RESERVED = ("image1", "image2", "camera", "flow", "motion", "estimator", "odometry", "starts", "data_range",
                 "warn")

#: the flags of :class:`RoadDetection`, in the order they are checked ("ok" when none applies; "empty" also
#: first, for a seed with no pixel in the image, and right after "no_motion", for a seed none of whose windows
#: is seen whole in image 2)
FLAGS = ("no_motion", "static", "textureless", "implausible", "empty", "small")

# windows count as independent pixels / this factor: the smoothing (σ = 1 px) correlates neighbours over 2 × 2
_CORRELATION = 4.0
# a residual motion of more than this many times the seed's typical one is never the road's
_MISFIT = 3.0
# below this share of the seed's windows with evidence, the seed cannot be judged (flag "textureless")
_MIN_EVIDENCE = 0.1
# the working resolution: the coarsest level of at least this many rows (the windows, the smoothing
# and the border margin are in its pixels)
_WORK_ROWS = 150
# the smoothing of the grey images at the working resolution (pixels)
_SIGMA = 1.0
# the least residual energy of 8-bit frames (grey levels², level 0): both frames' quantisation (1/12
# each), smoothed (Σ w² = 1 / 4πσ²); a level averages 4**level pixels
_QUANTISATION = 2 / 12 / (4 * math.pi * _SIGMA ** 2)


def _noise_gradient(sigma: float) -> float:
    """The gradient energy (TA) of white noise per its residual energy (E) through the smoothing of
    ``sigma`` and the central differences: Σ (g'_k)² / (2 Σ g_k²) of the 1-D kernel g (the blur's:
    sampled, normalised, ±3 σ), g' its central difference (0.158 at σ = 1)."""
    r = math.ceil(3 * sigma)
    g = torch.exp(-torch.arange(-r, r + 1, dtype=torch.float64, device="cpu").square() / (2 * sigma ** 2))
    g = g / g.sum()
    dg = 0.5 * (F.pad(g, (0, 2)) - F.pad(g, (2, 0)))  # (zero beyond the taps)
    return float(dg.square().sum() / (2 * g.square().sum()))


_NOISE_GRADIENT = _noise_gradient(_SIGMA)

# pixels of image 2's border whose smoothed values mix in its padding (3 σ of the blur, plus one)
_BORDER = 4


@dataclass(eq=False, repr=False)
class RoadDetection:
    """What :func:`detect_road` found, per sample (compared by identity, as a :class:`Camera` is).

    Attributes:
        mask: (B, 1, H, W) bool, the road. Flagged samples keep the mask found (possibly empty)
            for inspection; use :attr:`usable_mask` to apply only trusted ones.
        flag: per sample ``"ok"`` or one of :data:`FLAGS`.
        reason: per sample, a sentence saying why it was flagged (``""`` when ok).
        ok: (B,) bool, ``flag == "ok"``.
        motion: the road motion the mask was judged with (a fit result of any road model; one
            estimated here comes at the images' size, whichever fit each sample kept; a given one
            as it came, but for its tensors of batch 1, repeated for each sample of a larger batch).
        seed: (B, 1, H, W) bool, the geometric seed.
        coverage: (B,) the mask's share of the image below the horizon.
        seed_agreement: (B,) of the seed's windows with evidence, the share that is road evidence.
        evidence: (B, 1, h, w) int8 at the working resolution: 1 road, 0 off the road, -1 none.
        height: (B, 1, h, w) the windows' estimated height over the road plane (m; 0 where none: flat, or cut off).
        level: the working resolution is the images' / 2**level.
        stats: per sample (B,): ``tau_px`` (the road model's typical misfit, px at the working
            resolution), ``noise``, ``height_bias_m`` (the seed's height over the fitted plane),
            ``seed_evidence`` (the share of the seed's windows with evidence) and ``max_height_m``
            (the step evidence had to be able to show; see ``slow_max_height_m``).
    """

    mask: Tensor
    flag: list[str]
    reason: list[str]
    ok: Tensor
    motion: Any
    seed: Tensor
    coverage: Tensor
    seed_agreement: Tensor
    evidence: Tensor
    height: Tensor
    level: int
    stats: dict[str, Tensor] = field(default_factory=dict)
    __repr__ = summary_repr

    @property
    def usable_mask(self) -> Tensor:
        """(B, 1, H, W) bool: the mask where the sample is ok, empty elsewhere."""
        return self.mask & self.ok.reshape(-1, 1, 1, 1)


def _level_camera(camera: Camera, level: int) -> Camera:
    """The camera of images averaged over 2**level × 2**level blocks (pixel i there is the
    block of pixels 2**level i .. 2**level (i + 1) - 1)."""
    return camera if level == 0 else camera.scaled(0.5 ** level)


def _pool(x: Tensor, level: int) -> Tensor:
    return x if level == 0 else F.avg_pool2d(x, 2 ** level)


# -- image statistics ---------------------------------------------------------------------------

def _box(x: Tensor, k: int) -> Tensor:
    """Mean over k × k windows of (B, C, h, w), the border replicated (OpenCV on the CPU: a
    running sum; elsewhere two 1-D average pools)."""
    if host_path(x):
        import cv2
        import numpy as np

        B, C, h, w = x.shape
        planes = [cv2.boxFilter(p, -1, (k, k), borderType=cv2.BORDER_REPLICATE)
                  for p in x.detach().reshape(B * C, h, w).numpy()]
        return torch.from_numpy(np.stack(planes)).reshape(B, C, h, w)
    r = k // 2
    x = F.avg_pool2d(F.pad(x, (r, r, 0, 0), mode="replicate"), (1, k), stride=1)
    return F.avg_pool2d(F.pad(x, (0, 0, r, r), mode="replicate"), (k, 1), stride=1)


def _gradient(g: Tensor) -> tuple[Tensor, Tensor]:
    """Central differences of (B, 1, h, w), one-sided at the border."""
    p = F.pad(g, (1, 1, 1, 1), mode="replicate")
    return 0.5 * (p[..., 1:-1, 2:] - p[..., 1:-1, :-2]), 0.5 * (p[..., 2:, 1:-1] - p[..., :-2, 1:-1])


def _median(x: Tensor, fallback: float) -> Tensor:
    return x.median() if x.numel() else x.new_tensor(fallback)


@dataclass
class _Evidence:
    good: Tensor        # (B, 1, h, w) bool
    bad: Tensor
    misaligned: Tensor  # off the road by the residual alone (the height needs parallax: static is judged by this)
    ok: Tensor          # the warp is defined over the window
    testable: Tensor
    height: Tensor
    tau: Tensor         # (B,) the seed's typical residual motion (px at the level)
    noise: Tensor       # (B,) residual energy of textureless road (grey levels²)
    bias: Tensor        # (B,) the seed's height over the fitted plane (m)
    max_height: Tensor  # (B,) the step a window had to be able to show to count (m)


def _evidence(grey1: Tensor, grey2: Tensor, flow: Tensor, valid: Tensor, parallax: Tensor, seed: Tensor,
              gain: Tensor, *, window: int, height_window: int, min_height: float, max_heights: Sequence[float],
              trusted: Sequence[bool], z: float, min_misfit: float, noise_floor: float) -> _Evidence:
    """The window tests of the module docstring, at one resolution. ``parallax`` (B, 2, h, w): the
    flow of a surface ``min_height`` above the road minus the road's. ``noise_floor``: the least
    residual energy the images' quantisation leaves (grey levels²). ``max_heights``: the steps
    evidence must be able to show, tried in turn per sample until the seed carries evidence (the
    first, unless the parallax is too small for it: driving slowly); only the first where the
    sample's motion is not ``trusted`` (a failed estimate: no larger step makes it a road)."""
    B = grey1.shape[0]
    warped, _ = warp_backward(grey2, flow)
    # samples near image 2's border see the smoothing's reflected padding: not evidence
    h, w = grey1.shape[-2:]
    x = torch.arange(w, dtype=flow.dtype, device=flow.device) + flow[:, :1]
    y = torch.arange(h, dtype=flow.dtype, device=flow.device).reshape(h, 1) + flow[:, 1:]
    m = _BORDER
    defined = valid & (x >= m) & (x <= w - 1 - m) & (y >= m) & (y <= h - 1 - m)
    ok = erode_mask(defined, window)
    ok_h = erode_mask(defined, height_window)
    g = gain.reshape(-1).expand(B).reshape(B, 1, 1, 1).to(grey1.dtype)
    e = g * warped - grey1
    gx1, gy1 = _gradient(grey1)
    gx2, gy2 = _gradient(warped)
    # efficient second-order: the mean of both images' gradients
    gx, gy = 0.5 * (gx1 + g * gx2), 0.5 * (gy1 + g * gy2)

    # misalignment, per window: residual energy and gradient energy (offsets removed: exposure)
    k = window
    stack = torch.cat([e, e * e, gx, gx * gx, gy, gy * gy], dim=1)
    m = _box(stack, k)
    E = (m[:, 1:2] - m[:, 0:1] ** 2).clamp_min(0)
    TA = (m[:, 3:4] - m[:, 2:3] ** 2 + m[:, 5:6] - m[:, 4:5] ** 2).clamp_min(1e-12)

    # height, per (larger) window: one Lucas–Kanade step along the parallax direction
    P = torch.hypot(parallax[:, :1], parallax[:, 1:])
    direction = parallax / P.clamp_min(1e-9)
    gr = gx * direction[:, :1] + gy * direction[:, 1:]
    kh = height_window
    mh = _box(torch.cat([e, e * e, gr, gr * gr, gr * e, grey1, grey1 * grey1], dim=1), kh)
    Eh = (mh[:, 1:2] - mh[:, 0:1] ** 2).clamp_min(0)
    Vg = (mh[:, 3:4] - mh[:, 2:3] ** 2).clamp_min(1e-12)
    C = mh[:, 4:5] - mh[:, 2:3] * mh[:, 0:1]
    texture = (mh[:, 6:7] - mh[:, 5:6] ** 2).clamp_min(0)
    shift = -C / Vg                                   # px along the parallax direction
    left = (Eh - C * C / Vg).clamp_min(0)             # residual energy the shift leaves
    height = min_height * shift / P.clamp_min(1e-9)

    good, bad, misaligned, testable = (torch.zeros_like(ok) for _ in range(4))
    taus, noises, biases, heights = [], [], [], []
    n_k, n_kh = k * k / _CORRELATION, kh * kh / _CORRELATION
    for b in range(B):
        s = seed[b] & ok[b]
        E_s, T_s = E[b][s], TA[b][s]
        # the noise: residual energy of the seed's least textured windows, where misalignment
        # adds little; the model's misfit τ: what the rest of the seed adds, per gradient energy
        noise = _median(E_s[T_s <= torch.quantile(T_s, 0.25)], 0.0) if T_s.numel() > 3 else E.new_tensor(0.0)
        hi = T_s >= _median(T_s, 0.0)
        # (the floor as a tensor: a huge min_misfit_px is an infinite floor, no overflow error)
        tau = torch.maximum(_median(2 * (E_s[hi] - noise) / T_s[hi], 0.0), E.new_tensor(min_misfit * min_misfit)).sqrt()
        floor = _MISFIT * tau
        Pb = P[b]
        d2 = (E[b] - noise) / (0.5 * TA[b])
        se = torch.maximum(E[b], noise) * math.sqrt(2 / n_k) / (0.5 * TA[b])
        thr2 = torch.maximum(0.5 * Pb, floor) ** 2
        off_plane = d2 - z * se > thr2
        explained = d2 + z * se < thr2

        se_shift = (torch.maximum(left[b], noise) / (n_kh * Vg[b])).sqrt()
        se_h = min_height * se_shift / Pb.clamp_min(1e-9)
        informative = s & ok_h[b] & (se_h < min_height / 4)
        hs = height[b][informative]
        bias = _median(hs, 0.0)
        # the seed's scatter of the shift beyond the noise model: the model's misfit, in pixels
        rest = (shift[b] - bias / min_height * Pb)[informative]
        spread = 1.4826 * (rest - rest.median()).abs().median() if rest.numel() else rest.new_tensor(0.0)
        se_h = min_height * (se_shift ** 2 + spread ** 2).sqrt() / Pb.clamp_min(1e-9)
        raised = ((height[b] - bias).abs() - z * se_h > 0.5 * min_height)
        unexplained = (texture[b] > 4 * noise) & (Eh[b] > texture[b])
        misaligned[b] = ok[b] & off_plane | ok_h[b] & unexplained
        bad[b] = misaligned[b] | ok_h[b] & raised
        n_seed = max(int(s.sum()), 1)  # (the share below in float64, on the host: exact, whatever the device)
        for max_height in (max_heights if trusted[b] else max_heights[:1]):
            # testable: a surface max_height high would show (its parallax at least the floor); evidence
            # where, also, the residual energy its step would add (½ TA step²) is significant (flat: none)
            step = Pb * (max_height / min_height)
            testable[b] = test_b = 0.5 * step >= floor
            # (the gradient energy beyond what the noise itself has: flat frames' noise shows no step)
            signal = (TA[b] - _NOISE_GRADIENT * noise * (1 + z * math.sqrt(2 / n_k))).clamp_min(0)
            shows = 0.5 * signal * step ** 2 > z * noise.clamp_min(noise_floor) * math.sqrt(2 / n_k)
            good[b] = ok[b] & explained & test_b & shows & ~bad[b]
            if (s & test_b).any() and int((s & (good[b] | bad[b])).sum()) / n_seed >= _MIN_EVIDENCE:
                break
        taus.append(tau)
        noises.append(noise)
        biases.append(bias)
        heights.append(max_height)
    # (none where the height window leaves image 2, or has no gradient along the parallax)
    height = torch.where(ok_h & (Vg > 1e-12), height - torch.stack(biases).reshape(B, 1, 1, 1), 0.0)
    return _Evidence(good, bad, misaligned, ok, testable, height, torch.stack(taus), torch.stack(noises),
                     torch.stack(biases), torch.tensor(heights, dtype=torch.float64, device=height.device))


# -- the detection ------------------------------------------------------------------------------

def road_level(size: tuple[int, int], window: object, height_window: object) -> int:
    """``detect_road``'s default ``level`` for images of ``size`` (H, W): the coarsest at least
    ``_WORK_ROWS`` rows high and 16 and ``window + 8``, ``height_window + 8`` pixels either way."""
    rows, side = size[0], min(size)  # (16 pixels either way, room for the windows)
    least = max([16] + [k + 2 * _BORDER for k in (scalar(window, "window"), scalar(height_window, "height_window"))
                        if is_number(k, integer=True)])  # (a 0-d tensor as its number, as the options take it)
    return max(0, min(math.floor(math.log2(max(rows, 1) / _WORK_ROWS)), math.floor(math.log2(max(side, 1) / least))))


def check_road_size(shape: tuple[int, ...], camera: Camera, options: dict[str, Any], estimated: bool) -> None:
    """``detect_road``'s checks of its options (their values checked,
    :func:`~fsof_torch.refinement.road_options.check_road_values`, and ``level`` chosen) against
    images of ``shape`` (B, C, H, W) and ``camera``'s height, with its errors; ``seed_level``'s
    only where the motion is ``estimated``."""
    H, W = shape[-2:]
    if min(H, W) < 16:
        raise ValueError(f"image1: expected images of at least 16x16 pixels (the evidence's windows), got shape "
                         f"{shape}")
    for name in ("level", "seed_level"):
        v = options[name]
        if min(H, W) >> v < 16 and (name == "level" or estimated):
            raise ValueError(f"{name}: {v} leaves fewer than 16 pixels of the {H}x{W} images " + (
                f"(at most {(min(H, W) // 16).bit_length() - 1} here)" if name == "level" else
                "(with the default seed_level=1, an estimate needs images of at least 32x32 pixels)"))
    side = min(H, W) >> options["level"]
    for name in ("window", "height_window"):
        v = options[name]
        if v > side - 2 * _BORDER:  # (never seen whole: its test would be off everywhere)
            raise ValueError(f"{name}: expected at most {side - 2 * _BORDER} (the working image's side, {side} px: "
                             f"the {H}x{W} images at level {options['level']}, less {_BORDER} at "
                             f"either border, where image 2's smoothing sees its padding), got {v!r}")
    if not skip_values(camera.height) and not bool((camera.height > options["min_height_m"]).all()):
        # (the raised surface tested lies below the camera)
        raise ValueError(f"min_height_m: expected below the camera's height {camera.height.tolist()} m, "
                         f"got {options['min_height_m']!r}")


def _check_inputs(image1: Tensor, image2: Tensor, camera: Camera, flow: Tensor | None, data_range: float,
                  options: dict[str, Any], estimated: bool) -> dict[str, int]:
    dims = check_image_pair(image1, image2)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    if camera.batch_size not in (1, dims["B"]):
        raise ValueError(f"camera: expected batch {batch_choices(dims['B'])} (the images' B), got {camera.batch_size}")
    if flow is not None:
        check_float_tensor(flow, "flow")
        check_shape(flow, "flow", ("B", 2, "H", "W"), dims)
    check_same_device({"image1": image1, "image2": image2, "flow": flow})  # (torch's error would name neither)
    data_range = check_data_range(data_range)
    for name, t in (("image1", image1), ("image2", image2)):  # (the road is found in their values)
        check_has_values(t, name, "to find the road in (the detection reads the images, also with a motion given)")
        check_image_range(t, name, data_range)
    options.update(check_road_values(options))  # (their values, as int / float; then what the images allow)
    check_road_size(tuple(image1.shape), camera, options, estimated)
    return dims


def check_motion(motion: Any, B: int, device: torch.device, name: str) -> None:
    """A given road motion checked (displacement model, batch 1 or B, finite), errors naming ``name``."""
    model, params = road_motion(motion, name)
    if model.velocity:
        raise ValueError(f"{name}: expected a displacement model ('paper', 'plane' or 'homography'), got {model.name!r}")
    shapes = {k: tuple(getattr(v, "shape", ())) for k, v in params.items()}
    if any(math.prod(shape) not in (1, B) for shape in shapes.values()):
        raise ValueError(f"{name}: expected parameters of batch {batch_choices(B)} (the images' B), got shapes {shapes}")
    road_motion_batch(motion, B, torch.float64, device, name=name, batch_of="the images' B", displacement=True)


@inference
def detect_road(image1: Tensor, image2: Tensor, camera: Camera, *, flow: Tensor | None = None,
                motion: Any = None, estimator: Any = None, odometry: object = None, starts: Sequence[Any] = (),
                refit: bool = True, data_range: float = 255.0, level: int | None = None, seed_level: int = 1,
                seed_width_m: float = 4.0, seed_depth_m: float = 20.0, min_height_m: float = 0.1,
                max_height_m: float = 0.3, slow_max_height_m: float | None = SLOW_MAX_HEIGHT_M, z: float = 2.0, window: int = 7,
                height_window: int = 15, min_misfit_px: float = 0.5, min_coverage: float = 0.01,
                edges: bool = True, follow_path: bool = True, warn: bool = True) -> RoadDetection:
    """The road in image 1: the region connected to the road in front of the vehicle that moves like
    the road plane (see the module for the method).

    Args:
        image1, image2: frames t and t+1, (B, 3, H, W) RGB or (B, 1, H, W) grey, on 0..``data_range``.
        camera: intrinsics at the images' resolution, height, calibrated roll and pitch (batch 1 or B).
        flow: (B, 2, H, W) a predicted flow (pixels, t -> t+1), passed to the estimator (one start;
            its NaN or inf pixels left out of the estimator's masks, as the refiner leaves them out).
        motion: the road motion to judge with (a fit result, or a dict with a ``"model"`` key and
            its parameters; batch 1 or B; a ``"homography"`` is judged with its own flow, the plane
            it decomposes into giving the parallax); default: estimated on the seed. Given, ``flow``,
            ``estimator``, ``odometry`` and ``starts`` (an estimate's inputs) are refused.
        estimator: the road-motion estimator (the refiner's protocol, default
            :class:`~fsof_torch.refinement.estimators.ImageMotionEstimator`); ``odometry`` and
            ``starts`` (a sequence of start candidates: fit results or dicts of parameters) go to it.
            Its results are checked, errors naming ``estimator``: a fit result as the refiner checks
            it (of the samples it was given: :func:`~fsof_torch.refinement.estimators.check_estimate`),
            a motion in another form (a dict of parameters) as ``motion`` is.
        refit: after the first detection, estimate the motion again on the detected road (started
            from the first; with ``edges``, its boundary on the edges) and detect again. Only where
            the motion was estimated here.
        level: the evidence is judged on images averaged over 2**level pixels; default: the
            coarsest level at least ``_WORK_ROWS`` rows high (1 for KITTI's 375 rows) and 16 and
            ``height_window + 8`` pixels (23) either way. The windows are in pixels of that level.
        seed_level: the first estimate, on the seed, runs on images averaged over 2**seed_level
            pixels (the motion's parameters do not depend on the resolution).
        seed_width_m, seed_depth_m: the seed (:func:`road_seed`); in a turn also along the path
            (the module's step 1).
        min_height_m: the smallest step the road must not take in (a kerb); surfaces more than half
            of it above or below the road plane are off the road.
        max_height_m: evidence counts where a surface this high would show (see the module).
        slow_max_height_m: driving slowly, the parallax of a ``max_height_m`` step can sink below
            what the images show over most of the seed (at KITTI's 10 Hz, below about 5 m/s). The
            step is then doubled, up to this height, until a tenth of the seed carries evidence:
            a kerb lower than the step used then passes for road, a car or a wall still shows. A
            motion whose estimate failed keeps ``max_height_m``.
            ``stats["max_height_m"]`` reports the step used per sample. None: never (flagged).
        z: significance of every test, in standard errors.
        min_misfit_px: the least residual motion (pixels of the images) the road model is trusted
            to: a fitted road motion is not more accurate than about half a pixel on real images
            (DESIGN.md §5), even where the seed, which it was fitted to, says less.
        window, height_window: window sides at the working resolution for the misalignment and
            the height tests (the height needs more pixels); at most the working image's side less
            8 (a ValueError otherwise: a window never seen whole, 4 pixels from either border, tests nothing).
        min_coverage: a road smaller than this share of the image below the horizon is flagged
            ``"small"``.
        edges: within half a height window of the boundary the windows found (in pixels of the
            images; outward, one pixel of the working resolution more), the boundary follows
            image 1's edges (a marker-controlled watershed,
            :func:`~fsof_torch.refinement.road_region.follow_edges`). False: the windows' boundary.
        follow_path: turning, where the motion found takes the vehicle's path out of the straight
            seed within its depth, detect again from the seed along the path and keep that
            detection where it is ok and its seed agrees more with its motion (the module's step
            1). False: the seed straight ahead only.
        warn: an estimated motion whose parameters are not all finite is a failed estimate (flagged
            ``"no_motion"``) with a ``RuntimeWarning`` naming the samples; False: without it.

    Returns:
        :class:`RoadDetection`.

    Raises:
        TypeError, ValueError: bad input, naming the argument.
    """
    if level is None and isinstance(image1, Tensor) and image1.dim() == 4:
        level = road_level(tuple(image1.shape[-2:]), window, height_window)
    options = dict(level=level, seed_level=seed_level, window=window, height_window=height_window,
                   seed_width_m=seed_width_m, seed_depth_m=seed_depth_m, min_height_m=min_height_m,
                   max_height_m=max_height_m, slow_max_height_m=slow_max_height_m, z=z, min_misfit_px=min_misfit_px,
                   min_coverage=min_coverage, refit=refit, edges=edges, follow_path=follow_path)
    dims = _check_inputs(image1, image2, camera, flow, data_range, options, estimated=motion is None)
    (level, seed_level, window, height_window, seed_width_m, seed_depth_m, min_height_m, max_height_m, slow_max_height_m,
     z, min_misfit_px, min_coverage, refit, edges, follow_path) = options.values()  # (as int / float / bool)
    warn = check_bool(warn, "warn")
    check_estimator(estimator)
    if isinstance(starts, (str, bytes, Mapping)) or not isinstance(starts, Iterable):
        raise TypeError(f"starts: expected a sequence of start candidates, got {type(starts).__name__} {starts!r:.60}")
    starts = tuple(starts)  # (read once: an iterator would leave the refit none)
    B, H, W, device = dims["B"], dims["H"], dims["W"], image1.device
    if motion is not None:
        check_motion(motion, B, device, "motion")
        unused = [n for n, v in (("flow", flow), ("estimator", estimator), ("odometry", odometry)) if v is not None]
        if unused or starts:  # (what only an estimate takes: given with the motion, it would be ignored)
            raise ValueError(f"{(unused or ['starts'])[0]}: not used with motion given (the motion is judged, not "
                             f"estimated); give one or the other")
        if B > 1:  # (det.motion per sample, as an estimated one: a fit of batch 1 came back as it was)
            motion = select_samples(motion, torch.zeros(B, dtype=torch.long), 1)
    work = torch.float64 if image1.dtype == torch.float64 else torch.float32
    camera = camera.to(device=device).expand(B)
    # images on 0..255 (the estimators' scale), detached copies: the caller's tensors stay as they are
    scale = 255.0 / float(data_range)
    im1, im2 = (im.detach().to(work) * scale for im in (image1, image2))
    estimator = estimator if estimator is not None else ImageMotionEstimator()

    def estimate(f: Tensor | None, m: Tensor, cam: Camera, **kw: Any) -> Any:  # (non-finite parameters: failed)
        result = estimator(f, m, cam, **kw)
        if hasattr(result, "success"):  # (a fit result, as the refiner checks it; else a motion, as a given one)
            check_estimate(result, B)
        else:
            check_motion(result, B, device, "estimator")
        return finite_estimate(result, cam, warn=warn)
    # the geometry at the working resolution (the seed and the region live there)
    cam_l = _level_camera(camera, level)
    h, w = H >> level, W >> level
    X, Z, below_l = _ground(cam_l, (h, w))

    estimated = motion is None
    # a non-finite predicted pixel is no data: 0 in the estimator's flow and out of its masks (as
    # the refiner leaves it out of the estimation), in its own sample only
    flow = None if flow is None else flow.detach().to(work)
    finite = None if flow is None or all_finite(flow) else torch.isfinite(flow).all(1, keepdim=True)
    if finite is not None:
        flow = torch.where(finite, flow, 0.0)
    if estimated:
        cam_s = _level_camera(camera, seed_level)
        hs, ws = H >> seed_level, W >> seed_level
        flow_s = None if flow is None else _pool(flow, seed_level)[..., :hs, :ws] / 2 ** seed_level
        finite_s = None if finite is None else _pool(finite.to(work), seed_level)[..., :hs, :ws] == 1
        usable = (lambda m: m if finite_s is None else m & finite_s)  # noqa: E731
        images_s = tuple(_pool(im, seed_level)[..., :hs, :ws] for im in (im1, im2))
    with autocast_off(im1):  # (the smoothing in the working dtype; the tests' ops keep their inputs' dtype)
        grey = gaussian_blur(_pool(torch.cat([to_grey(im1), to_grey(im2)], dim=1), level)[..., :h, :w], _SIGMA)
    # the steps the evidence must be able to show: max_height_m, doubled up to slow_max_height_m
    heights = [max_height_m]
    while slow_max_height_m is not None and heights[-1] < slow_max_height_m:
        heights.append(min(2 * heights[-1], slow_max_height_m))
    below = upsample_mask(below_l, level, (H, W))
    if edges:  # (image 1 as 8-bit RGB and the horizon on the host, once)
        rgb = (im1.expand(-1, 3, -1, -1) if im1.shape[1] == 1 else im1).clamp(0, 255).round().to(torch.uint8)
        rgb = rgb.permute(0, 2, 3, 1).cpu().numpy()
        below_np = below[:, 0].cpu().numpy()
        radius = (height_window // 2 + 1) * 2 ** level
        # the result's edge may lie one smoothing radius farther out: what the windows see is smoothed
        reach = (height_window // 2 + 1 + math.ceil(_SIGMA)) * 2 ** level

    def detect(motion: Any, curvature: Tensor | None) -> RoadDetection:
        """The detection from the seed along a path of ``curvature`` (B,) 1/m (None: straight ahead)."""
        seed_l = seed_mask(X, Z, below_l, seed_width_m, seed_depth_m, curvature)
        bend = 0.0 if curvature is None else curvature
        if estimated:
            seed_s = (seed_l if seed_level == level else
                      road_seed(cam_s, (hs, ws), width_m=seed_width_m, depth_m=seed_depth_m, curvature=bend))
            motion = estimate(flow_s, usable(seed_s), cam_s, images=images_s, odometry=odometry, starts=starts)
            failed = ~torch.tensor(_succeeded(motion, B), device="cpu")
            if bool(failed.any()):
                # driving fast, most of the seed leaves image 2: the motion from a seed twice as deep,
                # per sample where the first failed and this one succeeds (the others keep their own)
                deeper = road_seed(cam_s, (hs, ws), width_m=seed_width_m, depth_m=2 * seed_depth_m, curvature=bend)
                again = estimate(flow_s, usable(deeper), cam_s, images=images_s, odometry=odometry, starts=starts)
                take = failed & torch.tensor(_succeeded(again, B), device="cpu")
                if bool(take.any()):
                    motion = again if bool(take.all()) else where_motion(take.to(device), again, motion)
            # the fit at the images' size (its homography, flow and camera; its parameters are the same)
            motion = fit_at_size(motion, camera, (H, W))

        def judge(motion: Any) -> tuple[_Evidence, Tensor]:
            model, params = _plane_motion(motion, camera)
            params = {k: torch.as_tensor(v, dtype=torch.float64, device=device) for k, v in params.items()}
            f, valid = road_flow(cam_l.to(torch.float64), params, (h, w), model=model)
            raised, _ = road_flow(cam_l.to(torch.float64).replace(height=cam_l.height.to(torch.float64) - min_height_m),
                                  params, (h, w), model=model)
            parallax = raised - f
            own, own_params = road_motion(motion, "motion")
            if own.name == "homography":  # (its own flow: the plane, with the camera's normal, only approximates it)
                own_params = {k: torch.as_tensor(v, dtype=torch.float64, device=device) for k, v in own_params.items()}
                f, own_valid = road_flow(cam_l.to(torch.float64), own_params, (h, w), model=own)
                valid = valid & own_valid
            gain = getattr(motion, "extras", {}).get("gain") if hasattr(motion, "extras") else None
            gain = torch.ones(B, dtype=work, device=device) if gain is None else gain.to(device=device, dtype=work)
            ev = _evidence(grey[:, :1], grey[:, 1:], f.to(work), valid, parallax.to(work), seed_l, gain,
                           window=window, height_window=height_window, min_height=min_height_m, max_heights=heights,
                           trusted=_succeeded(motion, B), z=z, min_misfit=min_misfit_px / 2 ** level,
                           noise_floor=_QUANTISATION / 4 ** level)
            focus = focus_of_expansion(model, params, cam_l)
            roads = []
            for b in range(B):
                fz = focus[b]
                fo = (float(fz[0] / fz[2]), float(fz[1] / fz[2])) if abs(float(fz[2])) > 1e-9 * float(fz.abs().max()) else None
                arrays = [t[b, 0].cpu().numpy() for t in (ev.good, ev.bad, ev.ok, ev.testable, below_l, seed_l)]
                roads.append(torch.from_numpy(road_region(*arrays, fo, window, max(1, (h * w) // 500))))
            return ev, torch.stack(roads).unsqueeze(1).to(device)

        seed = upsample_mask(seed_l, level, (H, W))
        seed_np = seed[:, 0].cpu().numpy() if edges else None

        def full_size(road_l: Tensor, outward: int | None = None) -> Tensor:
            """The road at the images' size; with ``edges``, its boundary on image 1's edges (up to
            ``outward`` pixels beyond the windows' boundary, default ``radius``)."""
            mask = upsample_mask(road_l, level, (H, W))
            if not edges:
                return mask
            m = mask[:, 0].cpu().numpy()
            return torch.stack([torch.from_numpy(follow_edges(m[b], rgb[b], below_np[b], seed_np[b], radius, outward))
                                for b in range(B)]).unsqueeze(1).to(device)

        ev, road_l = judge(motion)
        if estimated and refit and bool(road_l.any()):
            mask = full_size(road_l)  # (the fit: the road within half a window of the windows' boundary)
            again = estimate(flow, mask if finite is None else mask & finite, camera, images=(im1, im2),
                             odometry=odometry, starts=(motion, *starts))
            # per sample: a road found and fitted again (a sample without road keeps its seed fit,
            # as it would alone)
            ok_again = torch.tensor(_succeeded(again, B), device="cpu") & road_l.flatten(1).any(1).cpu()
            if bool(ok_again.any()):
                motion = again if bool(ok_again.all()) else where_motion(ok_again.to(device), again, motion)
                ev, road_l = judge(motion)
        return _report(full_size(road_l, reach if edges else None), motion, seed, below, ev, seed_l, level,
                       min_coverage)

    found = detect(motion, None)
    if not follow_path:
        return found
    # turning: where the motion takes the vehicle's path out of the straight seed within its depth
    # (seed.path_curvature), the seed along that path is judged too, and kept per sample where it is
    # ok and its evidence agrees more, or the straight seed's detection is flagged
    _, params = _plane_motion(found.motion, camera)
    yaw, x_d, z_d = (torch.as_tensor(params.get(n, 0.0), dtype=torch.float64, device=device) for n in ("yaw", "x_d", "z_d"))
    curvature = path_curvature(yaw, x_d, z_d, seed_width_m, seed_depth_m).expand(B)
    moved = torch.tensor([f != "no_motion" for f in found.flag], device=curvature.device)
    curvature = torch.where(moved, curvature, 0.0).to(device)
    if bool((curvature != 0).any()):
        bent = detect(motion, curvature)
        take = ((curvature != 0) & bent.ok & (~found.ok | (bent.seed_agreement > found.seed_agreement))).cpu()
        if bool(take.any()):
            found = _per_sample(take, bent, found)
    return found


def _succeeded(motion: Any, B: int) -> list[bool]:
    """Per sample, whether the motion was estimated successfully (a given motion without a
    ``success`` field counts as such)."""
    success = getattr(motion, "success", None)
    if success is None:
        return [True] * B
    return torch.as_tensor(success, device="cpu").reshape(-1).expand(B).tolist()


def _per_sample(take: Tensor, a: RoadDetection, b: RoadDetection) -> RoadDetection:
    """``a``'s detection where ``take`` (B,) bool, ``b``'s elsewhere."""
    if bool(take.all()):
        return a
    t = take.to(a.mask.device)

    def pick(x: Tensor, y: Tensor) -> Tensor:
        return torch.where(t.reshape(-1, *([1] * (x.dim() - 1))), x, y)

    flags = [(a if bool(k) else b).flag[i] for i, k in enumerate(take)]
    reasons = [(a if bool(k) else b).reason[i] for i, k in enumerate(take)]
    motion = a.motion if a.motion is b.motion else where_motion(t, a.motion, b.motion)
    return RoadDetection(mask=pick(a.mask, b.mask), flag=flags, reason=reasons, ok=pick(a.ok, b.ok), motion=motion,
                         seed=pick(a.seed, b.seed), coverage=pick(a.coverage, b.coverage),
                         seed_agreement=pick(a.seed_agreement, b.seed_agreement), evidence=pick(a.evidence, b.evidence),
                         height=pick(a.height, b.height), level=a.level,
                         stats={k: pick(a.stats[k], b.stats[k]) for k in a.stats})


def _report(mask: Tensor, motion: Any, seed: Tensor, below: Tensor, ev: _Evidence, seed_l: Tensor,
            level: int, min_coverage: float) -> RoadDetection:
    """Coverage, the seed's agreement and the flags (step 6 of the module)."""
    B = mask.shape[0]
    success = _succeeded(motion, B)
    pixels = mask.flatten(1).sum(1).cpu()
    coverage = pixels.double() / below.flatten(1).sum(1).cpu().clamp_min(1)  # (counts: float64, not torch's default dtype)
    s = seed_l & ev.ok
    n_judged = s.flatten(1).sum(1).cpu()
    n_seed = n_judged.clamp_min(1)
    n_good = (s & ev.good).flatten(1).sum(1).cpu()
    n_bad = (s & ev.bad).flatten(1).sum(1).cpu()
    n_test = (s & ev.testable).flatten(1).sum(1).cpu()
    n_moved = (s & ev.misaligned).flatten(1).sum(1).cpu()
    agreement = n_good.double() / (n_good + n_bad).clamp_min(1)
    evidence_share = (n_good + n_bad).double() / n_seed
    flags, reasons = [], []
    in_view = seed_l.flatten(1).any(1).cpu()
    for b in range(B):
        if not bool(in_view[b]):
            flag, why = "empty", ("the seed (the road ahead within seed_width_m and seed_depth_m) has no pixel in the "
                                  "image: check the camera's height and pitch, or a deeper seed_depth_m")
        elif not bool(success[b]):
            flag, why = "no_motion", "the road's motion could not be estimated from the images"
        elif int(n_judged[b]) == 0:
            flag, why = "empty", ("no window of the seed is seen whole in image 2 under the motion (frames too far "
                                  "apart for the seed, a wrong motion, or windows larger than the seed's view): "
                                  "nothing to judge the road ahead by; check the motion, or a deeper seed_depth_m")
        elif int(n_test[b]) == 0 and int(n_moved[b]) == 0:
            flag, why = "static", ("no parallax anywhere (a stopped vehicle, or one moving too little between the frames "
                                   "for their resolution; identical frames; or a camera whose pitch or height is far off)")
        elif float(evidence_share[b]) < _MIN_EVIDENCE:
            flag, why = "textureless", (f"only {100 * float(evidence_share[b]):.1f} % of the road ahead carries "
                                        f"evidence (dark or textureless frames)")
        elif float(agreement[b]) < 0.5:
            flag, why = "implausible", (f"the road ahead does not move like a road plane ({100 * float(agreement[b]):.0f} % "
                                        f"of its evidence agrees): an obstacle close ahead, or a wrong motion")
        elif int(pixels[b]) == 0:
            flag, why = "empty", "no road found"
        elif float(coverage[b]) < min_coverage:
            flag, why = "small", (f"the road covers {100 * float(coverage[b]):.2f} % of the image below the horizon "
                                  f"(fewer than {100 * min_coverage:g} %)")
        else:
            flag, why = "ok", ""
        flags.append(flag)
        reasons.append(why)
    evidence = torch.where(ev.good, 1, torch.where(ev.bad, 0, -1)).to(torch.int8)
    ok = torch.tensor([f == "ok" for f in flags], dtype=torch.bool, device=mask.device)
    on = mask.device  # (the per-sample numbers, read above on the host, follow the masks' device, as ok does)
    return RoadDetection(mask=mask, flag=flags, reason=reasons, ok=ok, motion=motion, seed=seed,
                         coverage=coverage.to(on), seed_agreement=agreement.to(on), evidence=evidence, height=ev.height,
                         level=level, stats={"tau_px": ev.tau.to(on), "noise": ev.noise.to(on), "height_bias_m": ev.bias.to(on),
                                             "seed_evidence": evidence_share.to(on), "max_height_m": ev.max_height.to(on)})
