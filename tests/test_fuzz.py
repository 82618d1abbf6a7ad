"""Property-based fuzzing of the public functions: every draw gives a finite, documented result or
a ValueError / TypeError whose message names an argument. Never a silent NaN, never an internal
error (RuntimeError, IndexError, ...), and either way every tensor argument is left as it came.

The suite is a table (:data:`TABLE`) of public functions, each with its arguments as roles
(an image, a flow, a mask, a camera, ...). A draw builds a valid call with random sizes
(H != W, B of 1 to 3), then mutates one argument or none:

- its rank, its batch size (one more), its last side (one less);
- its layout: non-contiguous, channels_last, expanded from batch 1: the result must then equal
  the result of the contiguous input (same values, other strides);
- its dtype: every float dtype, int32, int64, uint8, bool;
- one value: NaN, +inf, -inf, 1e20; a mask: empty, one pixel, one row;
- its type: None, a string, a list.

To add a function, add a row: ``Entry(name, call, {arg: role}, check=...)``; ``call`` takes the
arguments by name. ``check(result, args)`` replaces the default oracle (every float tensor in
the result finite) where the documentation promises something else.

Example counts are bounded (``FSOF_FUZZ_EXAMPLES``, default 25 per function) and the draws are
the same on every run (derandomised), so the file runs in seconds in CI. For a deeper search:
``FSOF_FUZZ_EXAMPLES=1000 FSOF_FUZZ_RANDOM=1 python -m pytest tests/test_fuzz.py``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import warnings
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fsof_torch.io as fio
from fsof_torch.evaluation import metrics as M
from fsof_torch.evaluation import photometric as P
from fsof_torch.evaluation import visualize as V
from fsof_torch.evaluation.warp import WarpBackward, normalize_coordinates, warp_backward
from fsof_torch.estimation.decompose import decompose_homography
from fsof_torch.estimation.flow_fit import fit_displacement, fit_road, fit_velocity
from fsof_torch.estimation.freespace import detect_freespace
from fsof_torch.estimation.image_fit import fit_image, fit_photometric
from fsof_torch.estimation.vflow import fit_vflow_curve, vflow_map
from fsof_torch.geometry import egomotion as E
from fsof_torch.geometry.camera import Camera, mounting_matrix, pitch_matrix, roll_matrix
from fsof_torch.geometry.road_flow import displacement_flow, road_flow, velocity_flow
from fsof_torch.geometry import road_flow as RF
from fsof_torch.geometry.road_models import plane_from_pose, road_homography
from fsof_torch.refinement.estimators import FlowMotionEstimator, ImageMotionEstimator
from fsof_torch.refinement.fusion import FreespaceRefiner, cauchy_weight, fuse_flow, refine_flow, resize_mask
from fsof_torch.refinement.wrapped import FreespaceRefined
from fsof_torch.refinement.gate import ImageGate
from fsof_torch.training import losses as L
from fsof_torch.training.testnet import TinyRAFT

settings.register_profile(
    "fuzz", max_examples=int(os.environ.get("FSOF_FUZZ_EXAMPLES", "25")), deadline=None,
    derandomize=not os.environ.get("FSOF_FUZZ_RANDOM"), database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FUZZ = settings.get_profile("fuzz")

DTYPES = [torch.float16, torch.bfloat16, torch.float32, torch.float64, torch.int32, torch.int64,
          torch.uint8, torch.bool]
LAYOUTS = ("noncontiguous", "channels_last", "expanded")
MUTATIONS = ("none", "none", "rank", "batch", "side", *LAYOUTS, "dtype", "nan", "inf", "-inf", "huge",
             "type")
MASK_PATTERNS = ("full", "empty", "pixel", "row", "random")


# -- the roles: how a valid argument is built ------------------------------------------------------

@dataclass
class Draw:
    """The random choices of one call: sizes, a generator, the mask pattern."""

    B: int
    H: int
    W: int
    g: torch.Generator
    pattern: str


def _mask(d: Draw) -> torch.Tensor:
    m = torch.zeros(d.B, 1, d.H, d.W, dtype=torch.bool)
    if d.pattern == "full":
        m[:] = True
    elif d.pattern == "pixel":
        m[:, :, d.H // 2, d.W // 2] = True
    elif d.pattern == "row":
        m[:, :, d.H - 1] = True
    elif d.pattern == "random":
        m = torch.rand(d.B, 1, d.H, d.W, generator=d.g) > 0.5
    return m


def _camera(d: Draw) -> Camera:
    f = 0.8 * max(d.W, d.H)
    K = torch.tensor([[f, 0.0, (d.W - 1) / 2], [0.0, f, d.H * 0.3], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Camera(K, 1.65, 0.01, -0.01)


def _poses(d: Draw) -> torch.Tensor:
    w = torch.randn(d.B, 3, generator=d.g, dtype=torch.float64) * 0.1
    skew = torch.zeros(d.B, 3, 3, dtype=torch.float64)
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    T = torch.eye(4, dtype=torch.float64).repeat(d.B, 1, 1)
    T[:, :3, :3] = torch.linalg.matrix_exp(skew - skew.transpose(1, 2))
    T[:, :3, 3] = torch.randn(d.B, 3, generator=d.g, dtype=torch.float64)
    return T


ROLES: dict[str, Callable[[Draw], Any]] = {
    "image": lambda d: torch.rand(d.B, 3, d.H, d.W, generator=d.g) * 255,
    "image1ch": lambda d: torch.rand(d.B, 1, d.H, d.W, generator=d.g) * 255,
    "flow": lambda d: torch.randn(d.B, 2, d.H, d.W, generator=d.g) * 2,
    "flows": lambda d: [torch.randn(d.B, 2, d.H, d.W, generator=d.g) * 2 for _ in range(2)],
    "error": lambda d: torch.rand(d.B, 1, d.H, d.W, generator=d.g) * 5,
    "mask": _mask,
    "camera": _camera,
    "odometry": lambda d: {"x_d": 0.02, "z_d": 1.0, "yaw": 0.01},
    "pose": _poses,
    "angles": lambda d: torch.randn(d.B, generator=d.g, dtype=torch.float64) * 0.1,
    "speed": lambda d: torch.rand(d.B, generator=d.g, dtype=torch.float64) * 20,
    "scale": lambda d: 2.0,
    "gamma": lambda d: 0.8,
    "coords": lambda d: torch.rand(d.H, d.W, generator=d.g) * d.W,
    "side": lambda d: d.W,
    "size": lambda d: (max(d.H // 2, 1), max(d.W // 2, 1)),
    "image_chw": lambda d: torch.rand(3, d.H, d.W, generator=d.g) * 255,
    "flow_chw": lambda d: torch.randn(2, d.H, d.W, generator=d.g) * 2,
    "mask_chw": lambda d: _mask(d)[0],
    "labels": lambda d: torch.randint(0, 300, (d.H, d.W), generator=d.g),
    "depth_chw": lambda d: torch.rand(1, d.H, d.W, generator=d.g) * 50,
    "poses_n44": _poses,
    "K33": lambda d: _camera(d).K[0],
    "polygons": lambda d: [[[0.0, 0.0], [d.W * 3.0, 1.0], [1.0, d.H * 3.0]]],
    "plane_motion": lambda d: {"z_d": 1.0, "x_d": 0.02, "pitch_change": 0.002, "y_d": 0.01},
    "homography": lambda d: road_homography(_camera(d), {"z_d": 0.5, "yaw": 0.01}).expand(d.B, 3, 3).clone(),
}


# -- mutations ---------------------------------------------------------------------------------------

def _mutate(value: Any, how: str, d: Draw, rng: np.random.Generator) -> Any:
    """``value`` changed by ``how``; returns the value unchanged where the mutation does not apply."""
    if how == "type":
        return [None, "x", [1.0, 2.0]][int(rng.integers(3))]
    if isinstance(value, Camera):
        if how == "batch":
            return Camera(value.K.expand(d.B + 1, 3, 3), value.height.expand(d.B + 1))
        if how == "dtype":
            return value.to(torch.float32)
        return value
    if isinstance(value, list) and value and isinstance(value[0], torch.Tensor):
        k = int(rng.integers(len(value)))
        return [(_mutate(v, how, d, rng) if i == k else v) for i, v in enumerate(value)]
    if isinstance(value, dict):
        if how in ("nan", "inf", "huge"):
            return {**value, "z_d": {"nan": math.nan, "inf": math.inf, "huge": 1e38}[how]}
        if how == "batch":
            return {**value, "z_d": torch.ones(d.B + 1)}
        if how == "rank":
            return {"x_d": 0.0, "yaw": 0.0}
        return value
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return {"nan": math.nan, "inf": math.inf, "-inf": -math.inf, "huge": 1e20, "dtype": "2",
                "rank": 0, "batch": -1}.get(how, value)
    if isinstance(value, tuple):
        return {"rank": value[:1], "side": (0, value[1]), "dtype": (2.5, value[1])}.get(how, value)
    if not isinstance(value, torch.Tensor):
        return value
    t = value
    if how == "rank":
        return t[0] if t.dim() > 1 and rng.integers(2) else t.unsqueeze(0)
    if how == "batch" and t.dim() >= 3:
        return torch.cat([t, t[:1]])
    if how == "side" and t.shape[-1] > 1:
        return t[..., :-1]
    if how == "noncontiguous" and t.dim() >= 2:
        return t.transpose(-1, -2).contiguous().transpose(-1, -2) if t.shape[-1] > 1 and t.shape[-2] > 1 else t
    if how == "channels_last" and t.dim() == 4:
        return t.contiguous(memory_format=torch.channels_last)
    if how == "expanded" and t.dim() >= 3:
        return t[:1].expand_as(t)
    if how == "dtype":
        return t.to(DTYPES[int(rng.integers(len(DTYPES)))])
    if how in ("nan", "inf", "-inf", "huge") and t.is_floating_point() and t.numel():
        t = t.clone()
        t.view(-1)[int(rng.integers(t.numel()))] = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf,
                                                    "huge": 1e20}[how]
        return t
    return t


# -- the oracle --------------------------------------------------------------------------------------

def _tensors(result: Any):
    if isinstance(result, torch.Tensor):
        yield result
    elif isinstance(result, dict):
        for v in result.values():
            yield from _tensors(v)
    elif isinstance(result, (list, tuple)):
        for v in result:
            yield from _tensors(v)
    elif isinstance(result, Camera):
        yield from (result.K, result.height, result.roll, result.pitch)
    elif dataclasses.is_dataclass(result) and not isinstance(result, type):
        for f in dataclasses.fields(result):
            value = getattr(result, f.name)
            if f.name == "covariance" and value is not None:
                # documented (docs/reliability.md): a frame whose data leave the parameters
                # undetermined (success False) has no covariance (NaN); the others are finite
                value = value[result.success]
            yield from _tensors(value)


def _finite(result: Any, args: dict) -> None:
    for t in _tensors(result):
        if t.is_floating_point():
            assert torch.isfinite(t).all(), f"non-finite values in the result: {t.flatten()[:6].tolist()}"
    if isinstance(result, (float, dict)):
        for v in (result.values() if isinstance(result, dict) else [result]):
            if isinstance(v, float):
                assert math.isfinite(v), f"non-finite number in the result: {result}"


def _same(a: Any, b: Any) -> None:
    ta, tb = list(_tensors(a)), list(_tensors(b))
    assert len(ta) == len(tb)
    for x, y in zip(ta, tb):
        assert x.shape == y.shape and x.dtype == y.dtype
        if x.is_floating_point():
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-4, equal_nan=True)
        else:
            assert torch.equal(x, y)
    if isinstance(a, dict):
        for k, v in a.items():
            if isinstance(v, (int, float)):
                assert v == pytest.approx(b[k], rel=1e-5, abs=1e-6), k


def _names_an_argument(message: str, names: list[str]) -> bool:
    return any(re.search(rf"(?<![A-Za-z_]){re.escape(n)}(?![A-Za-z_])", message) for n in names)


@dataclass
class Entry:
    name: str
    call: Callable[..., Any]
    args: dict[str, str]
    check: Callable[[Any, dict], None] = _finite
    min_side: int = 1
    also_named: tuple[str, ...] = ()
    layout_invariant: bool = True
    errors: tuple[type, ...] = (ValueError, TypeError)
    examples: int | None = None  # fewer draws for the slow ones (fits); default: the profile's


def _fuse_check(result: Any, args: dict) -> None:
    """Documented: outside the mask the prediction comes back as it was (NaN included)."""
    out, weight = result
    mask = args["mask"].expand_as(out)
    torch.testing.assert_close(out[~mask], args["flow_pred"].expand_as(out)[~mask].to(out.dtype), rtol=0, atol=0,
                               equal_nan=True)
    assert torch.isfinite(out[mask]).all() and torch.isfinite(weight).all()


def _refine_check(result: Any, args: dict) -> None:
    """Documented: the refined flow is finite wherever the prediction was, and where the model
    was applied; a non-finite prediction outside that comes back as it was. Every other output
    (weights, model flow, odometry, fit, gate) is finite."""
    preds = args["flows"] if "flows" in args else [args["flow"]]
    outs = result.flow if isinstance(result.flow, list) else [result.flow]
    for pred, out in zip(preds, outs):
        pred = pred.expand_as(out).to(out.dtype)
        assert (torch.isfinite(out) | ~torch.isfinite(pred)).all(), "a finite prediction came back non-finite"
        keep = ~torch.isfinite(out)
        assert torch.equal(torch.isnan(out[keep]), torch.isnan(pred[keep])), "non-finite values changed"
    finest = next(o for o in outs if o.shape[-2:] == result.mask.shape[-2:])
    assert torch.isfinite(finest[result.mask.expand_as(finest)]).all(), "non-finite where the model applied"
    _finite(result._replace(flow=None), args)


def _fit_check(result: Any, args: dict) -> None:
    """Documented: a fit's parameters, flow, residual and cost are finite, also where it failed
    (``success`` False); so is its covariance where it succeeded (see :func:`_tensors`)."""
    _finite(result, args)
    assert result.success.dtype == torch.bool


def _propagates(result: Any, args: dict) -> None:
    """Elementwise building blocks (rotation matrices, a coordinate map, a weight, the census
    filter) document NaN propagation, as ``torch.cos`` does: finite inputs give a finite result."""
    if all(torch.isfinite(t).all() for t in _tensors(list(args.values())) if t.is_floating_point()) and all(
            math.isfinite(v) for v in args.values() if isinstance(v, float)):
        _finite(result, args)


def _camera_check(cam: Camera, args: dict) -> None:
    """A camera that passes its checks has finite derived values and a finite road flow."""
    _finite(cam, args)
    assert torch.isfinite(cam.K_inv()).all() and torch.isfinite(cam.mounting()).all()
    flow, valid = displacement_flow(cam, 0.1, 1.0, 0.01, (7, 9))
    assert torch.isfinite(flow).all(), f"NaN road flow from a valid camera {cam}"


def _quiet(fn: Callable) -> Callable:
    def call(**kw):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # the documented warnings (excluded pixels, samples left unchanged)
            return fn(**kw)
    return call


# a road motion's errors name the parameter inside ``params`` (``z_d: expected finite values``)
_MOTION_NAMES = ("mismatched batch sizes", "x_d", "y_d", "z_d", "yaw", "pitch_change")
# and so do those of the odometry given to a refiner (``x_d, z_d, yaw, roll, pitch: the 'paper'
# road map overflows ...``)
_ODOMETRY_NAMES = ("x_d", "z_d", "yaw")

TABLE: list[Entry] = [
    # geometry/camera, geometry/egomotion (the road flow itself is fuzzed with the flow models)
    Entry("Camera.scaled", lambda sx, sy: _CAMERA.scaled(sx, sy), {"sx": "scale", "sy": "scale"}),
    Entry("roll_matrix", lambda roll: roll_matrix(roll), {"roll": "angles"}, check=_propagates),
    Entry("pitch_matrix", lambda pitch: pitch_matrix(pitch), {"pitch": "angles"}, check=_propagates),
    Entry("mounting_matrix", lambda roll, pitch: mounting_matrix(roll, pitch), {"roll": "angles", "pitch": "angles"},
          check=_propagates, also_named=("mismatched batch sizes",)),
    Entry("relative_pose", lambda pose0, pose1: E.relative_pose(pose0, pose1), {"pose0": "pose", "pose1": "pose"}),
    Entry("ego_motion_from_pose", lambda cam1_T_cam0, camera: E.ego_motion_from_pose(cam1_T_cam0, camera),
          {"cam1_T_cam0": "pose", "camera": "camera"}, also_named=("mismatched batch sizes",)),
    Entry("ego_motion_from_ackermann", lambda speed, steering: E.ego_motion_from_ackermann(speed, steering, 2.7, 0.1),
          {"speed": "speed", "steering": "angles"}, also_named=("mismatched batch sizes",)),
    # evaluation: warp, photometric error, metrics, figures
    Entry("warp_backward", lambda image, flow: warp_backward(image, flow), {"image": "image", "flow": "flow"}),
    Entry("WarpBackward", lambda image, flow: WarpBackward(mode="nearest")(image, flow), {"image": "image", "flow": "flow"}),
    Entry("normalize_coordinates", lambda coords, size: normalize_coordinates(coords, size, align_corners=False),
          {"coords": "coords", "size": "side"}, check=_propagates),
    *[Entry(f"photometric_error[{k}]", (lambda k: lambda image1, image2, flow, mask: P.photometric_error(
        image1, image2, flow, mask, kind=k, return_count=True))(k),
        {"image1": "image", "image2": "image", "flow": "flow", "mask": "mask"}) for k in ("l1", "ssim", "census")],
    Entry("photometric_error_map", lambda image1, image2, flow: P.photometric_error_map(image1, image2, flow, kind="soft_census"),
          {"image1": "image", "image2": "image", "flow": "flow"}),
    Entry("PhotometricError", lambda image1, image2, flow: P.PhotometricError(kind="ssim", window=3)(image1, image2, flow),
          {"image1": "image", "image2": "image", "flow": "flow"}),
    Entry("census_transform", lambda image: P.census_transform(image, radius=1), {"image": "image"},
          check=_propagates),
    *[Entry(f"metrics.{n}", (lambda n: lambda flow_est, flow_gt, mask, valid: getattr(M, n)(flow_est, flow_gt, mask, valid))(n),
            {"flow_est": "flow", "flow_gt": "flow", "mask": "mask", "valid": "mask"})
      for n in ("angular_error", "endpoint_error", "u_error", "v_error", "outlier_rate", "flow_metrics",
                "flow_metrics_per_sample", "flow_error_maps")],
    Entry("FlowMetricAccumulator.update", _quiet(lambda flow_est, flow_gt, valid: (
        lambda acc: (acc.update(flow_est, flow_gt, valid=valid), acc.compute("images")))(M.FlowMetricAccumulator())),
        {"flow_est": "flow", "flow_gt": "flow", "valid": "mask"}),  # (compute over nothing counted warns)
    Entry("flow_to_color", lambda flow, valid: V.flow_to_color(flow, valid=valid), {"flow": "flow", "valid": "mask"}),
    Entry("error_to_color", lambda error, vmax: V.error_to_color(error, vmax), {"error": "error", "vmax": "scale"}),
    Entry("overlay_mask", lambda image, mask: V.overlay_mask(image, mask), {"image": "image", "mask": "mask"}),
    # refinement: the fusion of two flows (refine_flow / FreespaceRefiner join with the estimation rows)
    Entry("fuse_flow", lambda flow_pred, flow_model, mask, scale: fuse_flow(flow_pred, flow_model, mask,
                                                                            mode="confidence", scale=scale),
          {"flow_pred": "flow", "flow_model": "flow", "mask": "mask", "scale": "scale"}, check=_fuse_check),
    Entry("cauchy_weight", lambda residual_sq, scale: cauchy_weight(residual_sq, scale),
          {"residual_sq": "error", "scale": "scale"}, check=_propagates),
    Entry("resize_mask", lambda mask, size: resize_mask(mask, size), {"mask": "mask", "size": "size"}),
    Entry("ImageGate", lambda image1, image2, prediction, model, mask: ImageGate(grid=(2, 3), points=64)(
        image1, image2, prediction, model, mask),
          {"image1": "image", "image2": "image", "prediction": "flow", "model": "flow", "mask": "mask"}),
    *[Entry(f"refine_flow[{name}]", (lambda kw: _quiet(lambda flow, mask, camera, odometry, image1, image2: refine_flow(
        flow, mask, camera, odometry, images=(image1, image2), **kw)))(kw),
        {"flow": "flow", "mask": "mask", "camera": "camera", "odometry": "odometry", "image1": "image",
         "image2": "image"}, check=_refine_check, also_named=("images", *_ODOMETRY_NAMES), examples=12)
      for name, kw in (("odometry+images", {"min_pixels": 1}), ("odometry+images,confidence", {"mode": "confidence"}))],
    Entry("refine_flow[odometry]", _quiet(lambda flows, mask, camera, odometry: refine_flow(
        flows, mask, camera, odometry, mode="confidence")),
          {"flows": "flows", "mask": "mask", "camera": "camera", "odometry": "odometry"}, check=_refine_check,
          also_named=("flow", *_ODOMETRY_NAMES)),  # refine_flow's argument is ``flow`` (here a list)
    Entry("refine_flow[fit]", _quiet(lambda flow, mask, camera: refine_flow(flow, mask, camera, min_pixels=3)),
          {"flow": "flow", "mask": "mask", "camera": "camera"}, check=_refine_check, examples=15),
    Entry("FreespaceRefiner[images]", _quiet(lambda flow, mask, camera, image1, image2: FreespaceRefiner(
        min_pixels=3)(flow, mask, camera, images=(image1, image2))),
          {"flow": "flow", "mask": "mask", "camera": "camera", "image1": "image", "image2": "image"},
          check=_refine_check, also_named=("images",), examples=12),
    Entry("FreespaceRefined", _quiet(lambda image1, image2, camera, mask, odometry: FreespaceRefined(
        _TINY, FreespaceRefiner(gate=None))(image1, image2, camera=camera, mask=mask, odometry=odometry)),
          {"image1": "image", "image2": "image", "camera": "camera", "mask": "mask", "odometry": "odometry"},
          also_named=_ODOMETRY_NAMES, min_side=4, layout_invariant=False, examples=10),
    # estimation: fits (flow, images, homographies), the V-flow, freespace
    Entry("fit_displacement", lambda flow, mask, camera: fit_displacement(flow, mask, camera, max_iter=5),
          {"flow": "flow", "mask": "mask", "camera": "camera"}, check=_fit_check, examples=15),
    Entry("fit_velocity", lambda flow, mask, camera, wheelbase: fit_velocity(flow, mask, camera, wheelbase, max_iter=5),
          {"flow": "flow", "mask": "mask", "camera": "camera", "wheelbase": "scale"}, check=_fit_check, examples=15),
    Entry("fit_road[plane]", lambda flow, mask, camera, valid: fit_road(flow, mask, camera, model="plane",
                                                                         valid=valid, max_iter=5),
          {"flow": "flow", "mask": "mask", "camera": "camera", "valid": "mask"}, check=_fit_check, examples=15),
    Entry("fit_image", lambda image1, image2, mask, camera: fit_image(image1, image2, mask, camera, max_iter=3),
          {"image1": "image", "image2": "image", "mask": "mask", "camera": "camera"}, check=_fit_check, examples=12),
    Entry("fit_photometric", lambda image1, image2, mask, camera: fit_photometric(image1, image2, mask, camera,
                                                                                  max_iter=3),
          {"image1": "image", "image2": "image", "mask": "mask", "camera": "camera"}, check=_fit_check, examples=10),
    Entry("decompose_homography", lambda H, camera: decompose_homography(H, camera, size=16),
          {"H": "homography", "camera": "camera"}, check=_fit_check, also_named=("mismatched batch sizes",),
          examples=15),
    Entry("FlowMotionEstimator", lambda flow, mask, camera: FlowMotionEstimator(max_iter=5)(flow, mask, camera),
          {"flow": "flow", "mask": "mask", "camera": "camera"}, check=_fit_check, examples=12),
    Entry("ImageMotionEstimator", lambda flow, mask, camera, image1, image2: ImageMotionEstimator(max_iter=3)(
        flow, mask, camera, images=(image1, image2)),
          {"flow": "flow", "mask": "mask", "camera": "camera", "image1": "image", "image2": "image"},
          check=_fit_check, also_named=("images",), examples=10),
    Entry("vflow_map", lambda flow, mask: vflow_map(flow, mask, bins=8), {"flow": "flow", "mask": "mask"}),
    Entry("fit_vflow_curve", lambda flow, mask: fit_vflow_curve(flow, mask, hypotheses=16, iterations=3),
          {"flow": "flow", "mask": "mask"}, check=_fit_check, examples=15),
    Entry("detect_freespace", lambda flow, camera, mask: detect_freespace(flow, camera, mask=mask, return_details=True),
          {"flow": "flow", "camera": "camera", "mask": "mask"}, examples=12),
    # geometry: the road's flow and homography of every model
    Entry("displacement_flow", lambda camera, x_d, z_d, yaw, size: displacement_flow(camera, x_d, z_d, yaw, size),
          {"camera": "camera", "x_d": "angles", "z_d": "speed", "yaw": "angles", "size": "size"},
          also_named=("mismatched batch sizes",)),
    Entry("velocity_flow", lambda camera, speed, steering, size: velocity_flow(camera, speed, steering, 2.7, size),
          {"camera": "camera", "speed": "speed", "steering": "angles", "size": "size"},
          also_named=("mismatched batch sizes",)),
    *[Entry(f"road_flow[{model}]", (lambda model: lambda camera, params, size: road_flow(
        camera, params, size, model=model))(model), {"camera": "camera", "params": role, "size": "size"},
        also_named=_MOTION_NAMES) for model, role in (("paper", "odometry"), ("plane", "plane_motion"))],
    Entry("road_homography", lambda camera, params: road_homography(camera, params, model="plane"),
          {"camera": "camera", "params": "plane_motion"}, also_named=_MOTION_NAMES),
    *[Entry(fn.__name__, (lambda fn: lambda camera, motion, size: fn(camera, motion, size))(fn),
            {"camera": "camera", "motion": "speed", "size": "size"}, also_named=("mismatched batch sizes", name))
      for fn, name in ((RF.displacement_flow_straight, "z_d"), (RF.displacement_flow_straight_level, "z_d"),
                       (RF.velocity_flow_straight, "speed"), (RF.velocity_flow_straight_level, "speed"))],
    Entry("road_velocity_matrix", lambda camera, speed, steering: RF.road_velocity_matrix(camera, speed, steering, 2.7),
          {"camera": "camera", "speed": "speed", "steering": "angles"}, also_named=("mismatched batch sizes",)),
    Entry("plane_from_pose", lambda cam1_T_cam0, camera: plane_from_pose(cam1_T_cam0, camera),
          {"cam1_T_cam0": "pose", "camera": "camera"}, also_named=("mismatched batch sizes",)),
    Entry("RoadFlow", lambda camera, params: RF.RoadFlow((5, 7), model="plane")(camera, params),
          {"camera": "camera", "params": "plane_motion"}, also_named=_MOTION_NAMES),
    # training: losses and the test net
    Entry("sequence_weights", lambda n, gamma: L.sequence_weights(n, gamma), {"n": "side", "gamma": "gamma"}),
    Entry("forward_backward_mask", lambda flow_forward, flow_backward: L.forward_backward_mask(flow_forward, flow_backward),
          {"flow_forward": "flow", "flow_backward": "flow"}),
    Entry("photometric_loss", lambda image1, image2, flow, mask: L.photometric_loss(
        image1, image2, flow, mask, census_weight=0.5, reduction="none"),
          {"image1": "image", "image2": "image", "flow": "flow", "mask": "mask"}),
    Entry("smoothness_loss", lambda flow, image: L.smoothness_loss(flow, image, order=1),
          {"flow": "flow", "image": "image"}),
    Entry("UnsupervisedFlowLoss", lambda flows, image1, image2, flows_backward: L.UnsupervisedFlowLoss(census_weight=0.1)(
        flows, image1, image2, flows_backward), {"flows": "flows", "image1": "image", "image2": "image",
                                                 "flows_backward": "flows"}),
    Entry("FreespaceFlowLoss", _quiet(lambda flows, road, camera, odometry, scale: L.FreespaceFlowLoss(
        penalty="cauchy", scale=scale)(flows, road, camera, odometry)),
          {"flows": "flows", "road": "mask", "camera": "camera", "odometry": "odometry", "scale": "scale"}),
    Entry("freespace_flow_loss", _quiet(lambda flows, road, camera, odometry: L.freespace_flow_loss(
        flows, road, camera, odometry, reduction="none")),
          {"flows": "flow", "road": "mask", "camera": "camera", "odometry": "odometry"}),
    Entry("CompositeLoss", lambda flows, image1, image2: L.CompositeLoss(
        {"u": (1.0, L.UnsupervisedFlowLoss(ssim_weight=0.0))})(flows, {"image1": image1, "image2": image2}),
          {"flows": "flows", "image1": "image", "image2": "image"}),
    Entry("TinyRAFT", lambda image1, image2: _TINY(image1, image2, iters=1), {"image1": "image", "image2": "image"},
          min_side=4, layout_invariant=False),
    # io: tensors to and from the formats (files are fuzzed by test_readers_on_corrupt_files)
    Entry("rasterize_polygons", lambda polygons, size: fio.rasterize_polygons(polygons, size),
          {"polygons": "polygons", "size": "size"}),
    Entry("mask_from_colors", lambda rgb: fio.mask_from_colors(rgb, [(0, 0, 0)]), {"rgb": "image_chw"}),
    Entry("vkitti2_camera_poses", lambda camera_T_world: fio.vkitti2_camera_poses(camera_T_world),
          {"camera_T_world": "poses_n44"}),
]
_TINY = TinyRAFT(iters=1).eval()
_CAMERA = Camera(torch.tensor([[50.0, 0.0, 20.0], [0.0, 50.0, 10.0], [0.0, 0.0, 1.0]]), 1.65)

WRITERS: list[Entry] = [
    Entry("write_flo", lambda path, flow: fio.write_flo(path / "f.flo", flow), {"flow": "flow_chw"}),
    Entry("write_flow[.npy]", lambda path, flow, valid: fio.write_flow(path / "f.npy", flow, valid),
          {"flow": "flow_chw", "valid": "mask_chw"}),
    Entry("write_kitti_flow", lambda path, flow, valid: fio.write_kitti_flow(path / "f.png", flow, valid),
          {"flow": "flow_chw", "valid": "mask_chw"}),
    Entry("write_vkitti2_flow", lambda path, flow, valid: fio.write_vkitti2_flow(path / "f.png", flow, valid),
          {"flow": "flow_chw", "valid": "mask_chw"}),
    Entry("write_carla_flow", lambda path, flow: fio.write_carla_flow(path / "f.tif", flow), {"flow": "flow_chw"}),
    Entry("write_image", lambda path, image: fio.write_image(path / "i.png", image), {"image": "image_chw"}),
    Entry("write_road_mask", lambda path, mask: fio.write_road_mask(path / "m.png", mask), {"mask": "mask_chw"}),
    Entry("write_label_map", lambda path, labels: fio.write_label_map(path / "l.png", labels), {"labels": "labels"}),
    Entry("write_depth_png", lambda path, depth: fio.write_depth_png(path / "d.png", depth), {"depth": "depth_chw"}),
    Entry("write_kitti_poses", lambda path, poses: fio.write_kitti_poses(path / "p.txt", poses), {"poses": "poses_n44"}),
    Entry("write_kitti_calibration", lambda path, K: fio.write_kitti_calibration(path / "c.txt", K), {"K": "K33"}),
    Entry("save_flow_png", lambda path, flow: V.save_flow_png(path / "f.png", flow), {"flow": "flow_chw"}),
    Entry("save_error_png", lambda path, error_map: V.save_error_png(path / "e.png", error_map, 3.0),
          {"error_map": "depth_chw"}),
]


# -- the properties ------------------------------------------------------------------------------------

@st.composite
def calls(draw, entry: Entry):
    B = draw(st.integers(1, 3))
    H = draw(st.sampled_from([1, 2, 3, 5, 8, 13]))
    W = draw(st.sampled_from([1, 2, 4, 7, 12]))
    d = Draw(B, max(H, entry.min_side), max(W, entry.min_side), torch.Generator().manual_seed(draw(st.integers(0, 2**16))),
             draw(st.sampled_from(MASK_PATTERNS)))
    args = {name: ROLES[role](d) for name, role in entry.args.items()}
    target = draw(st.sampled_from(sorted(args)))
    how = draw(st.sampled_from(MUTATIONS))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    mutated = dict(args, **{target: _mutate(args[target], how, d, rng)})
    return args, mutated, target, how


def _run(entry: Entry, args: dict, call: Callable[[], Any]) -> tuple[Any, BaseException | None]:
    names = [*entry.args, *entry.also_named]  # the entry's own: a generic name would let a wrong one pass
    try:
        return call(), None
    except entry.errors as err:
        assert _names_an_argument(str(err), names), f"{type(err).__name__} names no argument: {err}"
        return None, err


def _contiguous(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return value.contiguous()
    if isinstance(value, list):
        return [_contiguous(v) for v in value]
    return value


def _unchanged(args: dict, before: list[torch.Tensor]) -> None:
    """No function modifies a tensor it is given (docs/conventions.md), on its error paths too."""
    after = list(_tensors(args))
    assert len(after) == len(before)
    for old, new in zip(before, after):
        assert new.dtype == old.dtype and new.shape == old.shape
        if new.is_floating_point():  # (NaN where NaN was, every other value bit for bit)
            assert torch.equal(new.isnan(), old.isnan()), "an argument was modified"
            new, old = new.nan_to_num(0.0), old.nan_to_num(0.0)
        assert torch.equal(new, old), "an argument was modified"


def _property(entry: Entry, mutated: dict, target: str, how: str, invoke: Callable[[dict], Any]) -> None:
    before = [t.clone() for t in _tensors(mutated)]
    result, err = _run(entry, mutated, lambda: invoke(mutated))
    _unchanged(mutated, before)
    if err is None:
        entry.check(result, mutated)
        if how in LAYOUTS and entry.layout_invariant:
            # the same values in a plain contiguous tensor give the same result
            plain = dict(mutated, **{target: _contiguous(mutated[target])})
            reference, ref_err = _run(entry, plain, lambda: invoke(plain))
            assert ref_err is None, ref_err
            _same(result, reference)


def _budget(entry: Entry) -> settings:
    """The profile, with at most ``entry.examples`` draws (the fits are slower per call)."""
    if entry.examples is None:
        return FUZZ
    return settings(FUZZ, max_examples=min(FUZZ.max_examples, entry.examples)
                    if "FSOF_FUZZ_EXAMPLES" not in os.environ else FUZZ.max_examples)


@pytest.mark.parametrize("entry", TABLE, ids=[e.name for e in TABLE])
def test_public_function(entry: Entry):
    @_budget(entry)
    @given(calls(entry))
    def run(case):
        _, mutated, target, how = case
        _property(entry, mutated, target, how, lambda a: entry.call(**a))

    run()


@pytest.mark.parametrize("entry", WRITERS, ids=[e.name for e in WRITERS])
def test_writer(entry: Entry, tmp_path_factory):
    """A writer writes its file or raises a named error, and never leaves a temporary file behind."""
    @FUZZ
    @given(calls(entry))
    def run(case):
        args, mutated, _, how = case
        folder = tmp_path_factory.mktemp("w")
        before = [t.clone() for t in _tensors(mutated)]
        _, err = _run(entry, mutated, lambda: entry.call(folder, **mutated))
        _unchanged(mutated, before)
        left = [p.name for p in folder.iterdir()]
        assert len(left) <= 1 and not any(".tmp" in n for n in left), left
        assert (err is None) == (len(left) == 1), (err, left)

    run()


@FUZZ
@given(K=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=5, max_size=5),
       height=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([1e-320, 1e-39, 1e38, 1e300])),
       angles=st.tuples(st.floats(-10, 10), st.floats(-10, 10)),
       dtype=st.sampled_from([torch.float16, torch.bfloat16, torch.float32, torch.float64]),
       exponent=st.floats(-320, 308))
def test_camera_construction(K, height, angles, dtype, exponent):
    """Camera(K, height, roll, pitch): a camera whose derived values and road flow are finite, or a
    named error. Entries are drawn across every magnitude (also scaled by 10^exponent)."""
    fx, fy, cx, cy, skew = (k * 10.0 ** min(exponent, 300) if math.isfinite(k) else k for k in K)
    matrix = torch.tensor([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64).to(dtype)
    entry = Entry("Camera", Camera, {"K": "", "height": "", "roll": "", "pitch": ""}, check=_camera_check)
    result, err = _run(entry, {}, lambda: Camera(matrix, height, *angles))
    if err is None:
        _camera_check(result, {})


# -- files: every reader on corrupt and random bytes ------------------------------------------------------

def _valid_files(folder) -> dict[str, tuple[Callable, Any]]:
    """One valid file per reader (written by the library's writers)."""
    # seeded and within the Virtual KITTI 2 encoding's range at 5x7 (|u| <= 6, |v| <= 4 px): the
    # global generator's draw would depend on the tests that ran before; every file draws from g
    g = torch.Generator().manual_seed(0)
    flow = torch.randn(2, 5, 7, generator=g).clamp(-3.0, 3.0)
    return {
        "read_flo": (fio.read_flo, fio.write_flo(folder / "a.flo", flow)),
        "read_flow[.npy]": (fio.read_flow, fio.write_flow(folder / "a.npy", flow)),
        "read_kitti_flow": (fio.read_kitti_flow, fio.write_kitti_flow(folder / "k.png", flow)),
        "read_vkitti2_flow": (fio.read_vkitti2_flow, fio.write_vkitti2_flow(folder / "v.png", flow)),
        "read_carla_flow": (fio.read_carla_flow, fio.write_carla_flow(folder / "c.tif", flow)),
        "read_image": (fio.read_image, fio.write_image(folder / "i.png", torch.rand(3, 5, 7, generator=g) * 255)),
        "read_road_mask[.png]": (fio.read_road_mask, fio.write_road_mask(folder / "m.png", torch.rand(1, 5, 7, generator=g) > 0.5)),
        "read_road_mask[.json]": (fio.read_road_mask, fio.write_json(folder / "r.json", {
            "size": [5, 7], "road_polygon": [[0, 4], [6, 4], [3, 1]]})),
        "read_label_map": (fio.read_label_map, fio.write_label_map(folder / "l.png", torch.randint(0, 9, (5, 7), generator=g))),
        "read_depth_png": (fio.read_depth_png, fio.write_depth_png(folder / "d.png", torch.rand(1, 5, 7, generator=g) * 50)),
        "read_kitti_poses": (fio.read_kitti_poses, fio.write_kitti_poses(folder / "p.txt", torch.eye(4).repeat(2, 1, 1))),
        "read_kitti_calibration": (fio.read_kitti_calibration, fio.write_kitti_calibration(folder / "c.txt", torch.eye(3))),
        "read_vkitti2_intrinsics": (fio.read_vkitti2_intrinsics, fio.write_text(
            folder / "intrinsic.txt", "frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n0 0 725.0 725.0 620.5 187.0\n")),
        "read_vkitti2_extrinsics": (fio.read_vkitti2_extrinsics, fio.write_text(
            folder / "extrinsic.txt", "frame cameraID r1,1 r1,2 r1,3 t1 r2,1 r2,2 r2,3 t2 r3,1 r3,2 r3,3 t3 0 0 0 1\n"
            "0 0 1 0 0 0.5 0 1 0 -1 0 0 1 2.5 0 0 0 1\n")),
        "read_vkitti2_colors": (fio.read_vkitti2_colors, fio.write_text(
            folder / "colors.txt", "Category r g b\nTerrain 210 0 200\nRoad 100 60 100\n")),
        "read_synthetic_params": (_read_params_file, _params_file(folder)),
    }


def _params_file(folder) -> Any:
    """A pair's params JSON, as the synthetic layout writes it."""
    camera = Camera(torch.tensor([[50.0, 0.0, 20.0], [0.0, 50.0, 10.0], [0.0, 0.0, 1.0]]), 1.65)
    flow = torch.zeros(2, 5, 7)
    pair = {"image1": torch.zeros(3, 5, 7), "image2": torch.zeros(3, 5, 7), "flow": flow,
            "valid": torch.ones(1, 5, 7, dtype=torch.bool), "camera": camera,
            "odometry": {"x_d": 0.1, "z_d": 1.0, "yaw": 0.01}, "velocity": {"speed": 10.0, "steering": 0.0}}
    return fio.write_synthetic_pair(folder / "layout", 0, pair)["params"]


def _read_params_file(path) -> dict:
    """read_synthetic_params on a file anywhere: copied in as pair 0 of a layout beside it."""
    root = path.parent / "layout"
    (root / "params").mkdir(parents=True, exist_ok=True)
    (root / "params" / "000000.json").write_bytes(path.read_bytes())
    return fio.read_synthetic_params(root, 0)


READERS = ["read_flo", "read_flow[.npy]", "read_kitti_flow", "read_vkitti2_flow", "read_carla_flow", "read_image",
           "read_road_mask[.png]", "read_road_mask[.json]", "read_label_map", "read_depth_png", "read_kitti_poses",
           "read_kitti_calibration", "read_vkitti2_intrinsics", "read_vkitti2_extrinsics", "read_vkitti2_colors",
           "read_synthetic_params"]


@pytest.mark.parametrize("reader", READERS)
def test_readers_on_corrupt_files(reader, tmp_path_factory):
    """Truncated, bit-flipped and random files: a value, or a ValueError naming the path."""
    folder = tmp_path_factory.mktemp("valid")
    fn, path = _valid_files(folder)[reader]
    good = path.read_bytes()
    fn(path)  # the untouched file reads

    @FUZZ
    @given(how=st.sampled_from(["truncate", "flip", "random", "empty", "append"]),
           position=st.integers(0, 10**6), byte=st.integers(0, 255), data=st.binary(max_size=64))
    def run(how, position, byte, data):
        bad = bytearray(good)
        if how == "truncate":
            bad = bad[: position % max(len(good), 1)]
        elif how == "flip":
            bad[position % len(bad)] ^= max(byte, 1)
        elif how == "random":
            bad = bytearray(data)
        elif how == "empty":
            bad = bytearray()
        else:
            bad += data
        target = tmp_path_factory.mktemp("bad") / path.name
        target.write_bytes(bytes(bad))
        try:
            result = fn(target)
        except ValueError as err:
            assert "path" in str(err) or target.name in str(err), f"ValueError names no path: {err}"
            return
        if reader != "read_flo":  # (a raw .flo keeps unknown flow, NaN included, as stored)
            _finite(result, {})

    run()


@pytest.mark.parametrize("reader", [r for r in READERS if r != "read_synthetic_params"])  # (test_io_layout)
def test_readers_on_a_folder_or_a_broken_link(reader, tmp_path):
    """A folder where the file should be is an IsADirectoryError naming it, and a symbolic link to
    a missing file a FileNotFoundError that says so (data on a drive not mounted), for every
    reader: the Virtual KITTI 2 text readers said "no intrinsic.txt at" for both."""
    (tmp_path / "valid").mkdir()
    fn, path = _valid_files(tmp_path / "valid")[reader]
    folder = tmp_path / "bad" / path.name
    folder.mkdir(parents=True)
    with pytest.raises(IsADirectoryError, match=rf"^path: '.*/bad/{re.escape(path.name)}' is a folder; expected "):
        fn(folder)
    link = tmp_path / "link" / path.name
    link.parent.mkdir()
    link.symlink_to(tmp_path / "unmounted" / path.name)
    with pytest.raises(FileNotFoundError, match=rf"^path: '.*/link/{re.escape(path.name)}' is a symbolic link to "
                                                r"'.*/unmounted/.*', which does not exist"):
        fn(link)


# -- the meta device: shape inference through every table entry ---------------------------------------

# Entries that need values, with the documented error (they return Python numbers, go through
# NumPy, or are data dependent: fits, sampling the mask's pixels).
_FITS = "a tensor on the meta device has shapes but no values to fit"
NEEDS_VALUES = {
    "metrics.flow_metrics": "flow_metrics returns Python numbers",
    "FlowMetricAccumulator.update": "an accumulator sums values",
    "mask_from_colors": "rgb: a tensor on the meta device has shapes but no values",
    "ImageGate": "prediction: a tensor on the meta device has shapes but no values to judge by the images",
    "refine_flow[odometry+images]": "flow: a tensor on the meta device has shapes but no values to estimate",
    "refine_flow[odometry+images,confidence]": "flow: a tensor on the meta device has shapes but no values to estimate",
    "refine_flow[fit]": "flow: a tensor on the meta device has shapes but no values to estimate",
    "FreespaceRefiner[images]": "flow: a tensor on the meta device has shapes but no values to estimate",
    "FreespaceRefined": "flow: a tensor on the meta device has shapes but no values to estimate",
    **{name: _FITS for name in ("fit_displacement", "fit_velocity", "fit_road[plane]", "FlowMotionEstimator")},
    **{name: f"image1: {_FITS}" for name in ("fit_image", "fit_photometric", "ImageMotionEstimator")},
    "decompose_homography": "H: a tensor on the meta device has shapes but no values to decompose",
    "fit_vflow_curve": "flow: a tensor on the meta device has shapes but no values to fit the V-flow curve",
    "detect_freespace": "flow: a tensor on the meta device has shapes but no values to detect freespace",
}


def _to_meta(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return value.to("meta")
    if isinstance(value, Camera):
        return Camera(value.K.to("meta"), value.height.to("meta"), value.roll.to("meta"), value.pitch.to("meta"))
    if isinstance(value, list):
        return [_to_meta(v) for v in value]
    return value


@pytest.mark.parametrize("entry", TABLE, ids=[e.name for e in TABLE])
def test_meta_device(entry: Entry):
    """Every function runs on meta tensors (shapes out, no values), as torch's own functions do,
    or raises the documented ValueError where it must read values."""
    d = Draw(2, 6, 9, torch.Generator().manual_seed(0), "random")
    args = {name: _to_meta(ROLES[role](d)) for name, role in entry.args.items()}
    if entry.name in NEEDS_VALUES:
        with pytest.raises(ValueError, match=NEEDS_VALUES[entry.name]):
            entry.call(**args)
        return
    result = entry.call(**args)
    has_meta = any(t.device.type == "meta" for t in _tensors(args))
    assert not has_meta or all(t.device.type == "meta" for t in _tensors(result) if t.is_floating_point())


def _one_to_meta(value: Any) -> list[Any]:
    """The ways to put part of an argument on meta: the whole of it, or one tensor of a dict of
    tensors (an odometry's ``z_d``)."""
    if isinstance(value, dict):
        return [{**value, k: _to_meta(torch.as_tensor(v, dtype=torch.float32).reshape(1))}
                for k, v in value.items()][:1]
    return [_to_meta(value)] if isinstance(value, (torch.Tensor, Camera, list)) else []


@pytest.mark.parametrize("entry", TABLE, ids=[e.name for e in TABLE])
def test_one_argument_on_another_device(entry: Entry):
    """One argument on meta, the others on the CPU (as a CPU mask with CUDA flows): a named
    ValueError or TypeError, or a result wholly on meta where the function moves the other
    arguments to that one's device; never torch's error from inside, nor a CPU result computed
    from a tensor without values."""
    d = Draw(2, 6, 9, torch.Generator().manual_seed(0), "random")
    args = {name: ROLES[role](d) for name, role in entry.args.items()}
    for target in args:
        for value in _one_to_meta(args[target]):
            mixed = dict(args, **{target: value})
            result, err = _run(entry, mixed, lambda: _quiet(entry.call)(**mixed))
            if err is None:
                devices = {t.device.type for t in _tensors(result) if t.is_floating_point()}
                assert devices <= {"meta"}, f"{target} on meta gave a result on {devices}"
