"""Vehicle pose estimation from noisy freespace flow: the paper's experiment (§ "Vehicle Pose
Estimation"), with the robust least-squares fit of :mod:`fsof_torch.estimation.flow_fit` in place of the paper's
particle swarm optimisation.

A virtual road plane is seen by a calibrated camera; the pixels of a box below the horizon sample
it uniformly. The vehicle moves by a random displacement (x_d, z_d) and yaw φ (seeded); the
model flow of that motion (paper eq. 13) plus Gaussian noise of standard deviation σ pixels in
each component is the only input of the estimator, which recovers (x_d, z_d, φ) with
:func:`fsof_torch.estimation.flow_fit.fit_displacement` (camera height known, roll known unless ``fit_roll``).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

import torch
from torch import Tensor

from fsof_torch import Camera, displacement_flow

__all__ = ["PoseEstimationResult", "pose_estimation_experiment", "default_pose_camera", "MAX_SIGMA"]

#: The largest noise level σ (px) taken: noise wider than any image (10 000 px) leaves no flow to
#: fit, and far beyond it the noisy flow overflows (float32 near 1e38) and so does the fit.
MAX_SIGMA = 1e4

# The KITTI rectified left colour camera (P_rect_02 of drive 2011_09_26) at 375 × 1242, h = 1.65 m.
_KITTI_K = ((721.5377, 0.0, 609.5593), (0.0, 721.5377, 172.854), (0.0, 0.0, 1.0))
_KITTI_SIZE = (375, 1242)


def default_pose_camera(size: tuple[int, int] = _KITTI_SIZE, dtype: torch.dtype = torch.float64) -> Camera:
    """The KITTI colour camera (h = 1.65 m, level) resampled to ``size = (H, W)``, two ints >= 2."""
    H, W = _check_size(size)  # (a side of 0 was named as the camera's scale factor sx or sy)
    cam = Camera(torch.tensor(_KITTI_K, dtype=dtype), 1.65)
    if (H, W) == _KITTI_SIZE:
        return cam
    return cam.scaled(W / _KITTI_SIZE[1], H / _KITTI_SIZE[0])


@dataclass
class PoseEstimationResult:
    """Per-σ pose errors of :func:`pose_estimation_experiment`.

    Attributes:
        sigmas: the noise levels (pixels, standard deviation per flow component), (S,).
        translation_error: (S,) mean over trials of ‖(x̂_d, ẑ_d) - (x_d, z_d)‖ in metres.
        x_error, z_error: (S,) mean absolute errors of x_d and z_d in metres.
        yaw_error_deg: (S,) mean absolute yaw error in degrees.
        success_rate: (S,) fraction of trials whose fit reported success.
        true_pose: (T, 3) the drawn (x_d m, z_d m, yaw rad) of the T trials (shared by all σ).
        estimated_pose: (S, T, 3) the recovered poses.
        num_pixels: number of road pixels in the box (mean over trials).
    """

    sigmas: Tensor
    translation_error: Tensor
    x_error: Tensor
    z_error: Tensor
    yaw_error_deg: Tensor
    success_rate: Tensor
    true_pose: Tensor
    estimated_pose: Tensor
    num_pixels: float
    settings: dict = field(default_factory=dict)

    def rows(self) -> list[dict]:
        """One dict per σ (plain floats), for tables and JSON."""
        return [dict(sigma=float(s), translation_error_m=float(t), x_error_m=float(x),
                     z_error_m=float(z), yaw_error_deg=float(y), success_rate=float(r))
                for s, t, x, z, y, r in zip(self.sigmas, self.translation_error, self.x_error,
                                            self.z_error, self.yaw_error_deg, self.success_rate)]


def _is_int(value: object) -> bool:
    """A Python or NumPy integer, not a bool."""
    return not isinstance(value, bool) and isinstance(value, numbers.Integral)


def _check_size(size: object) -> tuple[int, int]:
    """``size`` as (H, W): two ints (Python or NumPy, as ``box`` takes them) >= 2."""
    if not isinstance(size, (tuple, list)) or len(size) != 2 or not all(_is_int(n) for n in size):
        raise TypeError(f"size: expected (H, W), two ints, got {size!r}")
    H, W = (int(n) for n in size)
    if min(H, W) < 2:
        raise ValueError(f"size: expected H, W >= 2, got {tuple(size)!r}")
    return H, W


def _check_range(value: object, name: str) -> tuple[float, float]:
    if (not isinstance(value, (tuple, list)) or len(value) != 2
            or any(isinstance(v, bool) or not isinstance(v, numbers.Real) for v in value)):
        raise TypeError(f"{name}: expected (low, high), two numbers, got {value!r}")
    lo, hi = (float(v) for v in value)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"{name}: expected finite low <= high, got {tuple(value)!r}")
    return lo, hi


def pose_estimation_experiment(sigmas: tuple[float, ...] | list[float] = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0),
                               *, trials: int = 32, camera: Camera | None = None,
                               size: tuple[int, int] = _KITTI_SIZE,
                               box: tuple[int, int, int, int] | None = None,
                               z_range: tuple[float, float] = (0.5, 2.5),
                               x_range: tuple[float, float] = (-0.2, 0.2),
                               yaw_range_deg: tuple[float, float] = (-3.0, 3.0),
                               fit_roll: bool = False, seed: int = 0, chunk: int = 8,
                               dtype: torch.dtype = torch.float32, progress: bool = False,
                               **fit_options) -> PoseEstimationResult:
    """Run the pose-from-noisy-flow experiment and return the per-σ mean absolute errors.

    Args:
        sigmas: noise levels σ in pixels (standard deviation of the Gaussian noise added to each
            flow component), each in [0, ``MAX_SIGMA``] (1e4): a list or tuple, or a 1-D NumPy
            array or tensor.
        trials: number of random poses (the same poses are used for every σ).
        camera: the camera (batch 1) at ``size``; default :func:`default_pose_camera`.
        size: ``(H, W)`` of the virtual image, two ints >= 2.
        box: ``(top, bottom, left, right)`` pixel box (rows top..bottom-1, columns
            left..right-1) sampling the road; default: rows from 15 % of the way between the
            horizon and the bottom, to the bottom; columns from 15 % to 85 % of the width.
            Only pixels where the model is defined are used; a box that leaves a trial none
            (above the horizon, say) raises ValueError.
        z_range, x_range: uniform ranges of the forward and lateral displacement in metres.
        yaw_range_deg: uniform range of the yaw change in degrees.
        fit_roll: also fit the roll (the paper's experiment knows the camera; default False).
        seed: an int in [-2**63, 2**64) (a ``torch.Generator``'s seeds); seeds the poses and the noise.
        chunk: trials fitted per batch (bounds memory; the results do not depend on it).
        dtype: dtype of the synthetic flow (the fit's normal equations are float64 anyway).
        progress: show a progress bar over σ and the trials (:func:`fsof_torch.io.progress.progress_bar`).
        **fit_options: passed to :func:`fsof_torch.estimation.flow_fit.fit_displacement`.

    Returns:
        :class:`PoseEstimationResult`.

    Example:
        >>> res = pose_estimation_experiment([0.0, 1.0], trials=4, size=(188, 621))
        >>> res.rows()[1]["yaw_error_deg"] < 0.05
        True
    """
    from fsof_torch import fit_displacement

    from fsof_torch.io.progress import progress_bar

    # a 1-D NumPy array or tensor (np.linspace, torch.logspace) is a list of σ (it was refused as
    # values outside [0, MAX_SIGMA], whatever they were)
    values = sigmas.tolist() if hasattr(sigmas, "tolist") and getattr(sigmas, "ndim", None) == 1 else sigmas
    if not isinstance(values, (tuple, list)) or any(isinstance(s, bool) or not isinstance(s, numbers.Real)
                                                    for s in values):
        # (a string, None or a nested list failed inside float(), unnamed; "0.5" was taken)
        raise TypeError(f"sigmas: expected a list of numbers (noise levels in px), got {sigmas!r}")
    sig = [float(s) for s in values]
    if not sig or not all(math.isfinite(s) and 0 <= s <= MAX_SIGMA for s in sig):
        raise ValueError(f"sigmas: expected a non-empty list of values in [0, {MAX_SIGMA:g}] px, got {sigmas!r}")
    H, W = _check_size(size)
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype: expected a floating-point torch.dtype, got {dtype!r}")
    for name, value in (("trials", trials), ("chunk", chunk), ("seed", seed)):
        if not _is_int(value):  # (a float seed was truncated, a string one failed inside int())
            raise TypeError(f"{name}: expected an integer{' >= 1' if name != 'seed' else ''}, got "
                            f"{type(value).__name__} {value!r}")
        if name != "seed" and value < 1:
            raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
    if not -2**63 <= seed < 2**64:  # (torch.Generator's range: beyond it an unnamed 'Overflow when unpacking')
        raise ValueError(f"seed: expected an integer in [-2**63, 2**64), got {seed!r}")
    z_lo, z_hi = _check_range(z_range, "z_range")
    x_lo, x_hi = _check_range(x_range, "x_range")
    y_lo, y_hi = _check_range(yaw_range_deg, "yaw_range_deg")
    if camera is None:
        camera = default_pose_camera((H, W), torch.float64)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    if camera.batch_size != 1:
        raise ValueError(f"camera: expected batch 1, got {camera.batch_size}")
    camera = camera.to(dtype)
    if box is None:
        horizon = float(camera.horizon_row().max())
        top = max(0, int(math.ceil(horizon + 0.15 * (H - horizon))))
        box = (top, H, int(0.15 * W), int(math.ceil(0.85 * W)))
    if not isinstance(box, (tuple, list)) or len(box) != 4 or not all(_is_int(b) for b in box):
        # (three numbers failed to unpack, a float was truncated, a string failed inside int())
        raise TypeError(f"box: expected (top, bottom, left, right), four ints, got {box!r}")
    top, bottom, left, right = (int(b) for b in box)
    if not (0 <= top < bottom <= H and 0 <= left < right <= W):
        raise ValueError(f"box: expected 0 <= top < bottom <= {H} and 0 <= left < right <= {W}, got {tuple(box)!r}")
    in_box = torch.zeros(1, 1, H, W, dtype=torch.bool, device=camera.device)
    in_box[..., top:bottom, left:right] = True

    gen = torch.Generator().manual_seed(int(seed))
    u = torch.rand(trials, 3, generator=gen, dtype=torch.float64)
    true = torch.stack([x_lo + (x_hi - x_lo) * u[:, 0], z_lo + (z_hi - z_lo) * u[:, 1],
                        torch.deg2rad(y_lo + (y_hi - y_lo) * u[:, 2])], dim=-1)

    estimated = torch.zeros(len(sig), trials, 3, dtype=torch.float64)
    success = torch.zeros(len(sig), trials, dtype=torch.bool)
    pixels = []
    # (closed before an error is raised, so that its message never prints on the bar's line)
    with progress_bar(total=len(sig) * trials, enabled=progress, desc="pose estimation", unit="trial") as bar:
        for k, s in enumerate(sig):
            for start in range(0, trials, chunk):
                pose = true[start:start + chunk]
                n = pose.shape[0]
                cam = camera.expand(n)
                p = pose.to(dtype=dtype, device=camera.device)
                flow, valid = displacement_flow(cam, p[:, 0], p[:, 1], p[:, 2], (H, W))
                mask = valid & in_box
                if k == 0:
                    counts = mask.sum(dim=(1, 2, 3))
                    if not bool(counts.all()):  # nothing to fit: its "errors" would be the fit's start
                        trial = start + int((counts == 0).nonzero()[0, 0])
                        raise ValueError(f"box: {(top, bottom, left, right)!r} holds no pixel where the model flow "
                                         f"is defined (below the horizon) for trial {trial}; expected a box on the road")
                    pixels.extend(counts.tolist())
                # Drawn on the CPU generator so that results do not depend on the device, and one
                # trial at a time so that they do not depend on ``chunk`` either (torch draws the
                # normal values of one call in blocks of 16: a call for a whole chunk gives other
                # values than a call per trial, where a trial's count is no multiple of 16)
                noise = torch.stack([torch.randn(flow.shape[1:], generator=gen, dtype=torch.float64)
                                     for _ in range(n)]).to(dtype=dtype, device=flow.device)
                noisy = torch.where(mask, flow + s * noise, torch.zeros_like(flow))
                fit = fit_displacement(noisy, mask, cam, fit_roll=fit_roll, fit_pitch=False, **fit_options)
                estimated[k, start:start + n] = torch.stack([fit.x_d, fit.z_d, fit.yaw], dim=-1).double().cpu()
                success[k, start:start + n] = fit.success.cpu()
                bar.update(n)

    diff = estimated - true.unsqueeze(0)
    return PoseEstimationResult(
        sigmas=torch.tensor(sig, dtype=torch.float64),
        translation_error=diff[..., :2].norm(dim=-1).mean(-1),
        x_error=diff[..., 0].abs().mean(-1),
        z_error=diff[..., 1].abs().mean(-1),
        yaw_error_deg=torch.rad2deg(diff[..., 2].abs()).mean(-1),
        success_rate=success.double().mean(-1),
        true_pose=true,
        estimated_pose=estimated,
        num_pixels=float(sum(pixels) / len(pixels)),
        settings=dict(trials=trials, size=[H, W], box=[top, bottom, left, right], z_range=[z_lo, z_hi],
                      x_range=[x_lo, x_hi], yaw_range_deg=[y_lo, y_hi], fit_roll=bool(fit_roll),
                      seed=int(seed), fx=float(camera.fx[0]), fy=float(camera.fy[0]),
                      cx=float(camera.cx[0]), cy=float(camera.cy[0]), height=float(camera.height[0])),
    )
