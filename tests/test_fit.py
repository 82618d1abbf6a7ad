"""Tests of fsof_torch.estimation.flow_fit: robust fits of the displacement and velocity models to flow."""

from __future__ import annotations

import math

import pytest
import torch

import fsof_torch.estimation.flow_fit as fit_module
from fsof_torch.geometry.camera import Camera
from fsof_torch.estimation.decompose import decompose_homography
from fsof_torch.estimation.flow_fit import (
    ROBUST_KERNELS,
    FitResult,
    VelocityFitResult,
    fit_displacement,
    fit_road,
    fit_velocity,
    robust_weight,
)
from fsof_torch.estimation.sampling import sample_mask
from fsof_torch.geometry.road_flow import displacement_flow, road_flow, velocity_flow
from fsof_torch.geometry.road_models import road_homography

SIZE = (64, 160)


pytestmark = pytest.mark.usefixtures("one_thread")


def small_camera(dtype=torch.float64, roll=0.0, pitch=0.0) -> Camera:
    """A wide camera with the horizon near the top, so that most of a small image is road."""
    K = torch.tensor([[130.0, 0.0, 80.0], [0.0, 130.0, 16.0], [0.0, 0.0, 1.0]], dtype=dtype)
    return Camera(K, 1.65, roll, pitch)


def road_mask(valid: torch.Tensor, top: int = 24) -> torch.Tensor:
    mask = valid.clone()
    mask[:, :, :top] = False
    return mask


def epe_to(fit_flow: torch.Tensor, true_flow: torch.Tensor, mask: torch.Tensor) -> float:
    return float((fit_flow - true_flow).norm(dim=1)[mask[:, 0]].mean())


# -- smoke -------------------------------------------------------------------------------------

def test_smoke_fields_and_odometry():
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.02, 0.8, 0.01, SIZE)
    fit = fit_displacement(flow, road_mask(valid), cam)
    assert isinstance(fit, FitResult)
    for name in ("x_d", "z_d", "yaw", "roll", "pitch", "residual", "success"):
        assert getattr(fit, name).shape == (1,)
    assert fit.flow.shape == (1, 2, *SIZE) and fit.valid.shape == (1, 1, *SIZE)
    assert fit.inliers.dtype == torch.bool and fit.inliers.shape == (1, 1, *SIZE)
    assert set(fit.odometry()) == {"x_d", "z_d", "yaw"}
    assert isinstance(fit.camera, Camera) and fit.camera.batch_size == 1
    assert bool(fit.success)


def test_smoke_float32_input_float32_output():
    cam = small_camera(torch.float32)
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    fit = fit_displacement(flow, road_mask(valid), cam)
    assert fit.z_d.dtype == torch.float32 and fit.flow.dtype == torch.float32
    assert abs(float(fit.z_d) - 1.0) < 1e-4


# -- exceptions --------------------------------------------------------------------------------

def test_exceptions_shapes_and_types():
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    with pytest.raises(ValueError, match=r"flow: expected shape \(B, 2, H, W\)"):
        fit_displacement(flow[:, :1], valid, cam)
    with pytest.raises(ValueError, match="mask: expected shape"):
        fit_displacement(flow, valid[..., :10], cam)
    with pytest.raises(TypeError, match="mask: expected dtype torch.bool"):
        fit_displacement(flow, valid.float(), cam)
    with pytest.raises(TypeError, match="camera: expected a fsof_torch.Camera"):
        fit_displacement(flow, valid, "cam")
    with pytest.raises(TypeError, match="flow: expected a floating-point tensor"):
        fit_displacement(flow.long(), valid, cam)
    with pytest.raises(ValueError, match="robust: expected one of"):
        fit_displacement(flow, valid, cam, robust="bisquare")
    with pytest.raises(ValueError, match="scale: expected a finite number > 0"):
        fit_displacement(flow, valid, cam, scale=0.0)
    with pytest.raises(ValueError, match="camera: expected batch 1 or 2"):
        fit_displacement(flow.expand(2, -1, -1, -1), valid, cam.expand(3))
    with pytest.raises(ValueError, match=r"min_inlier_fraction: expected a number in \[0, 1\]"):
        fit_displacement(flow, valid, cam, min_inlier_fraction=2.0)
    with pytest.raises(ValueError, match="wheelbase: expected values > 0"):
        fit_velocity(flow, valid, cam, -1.0)


def test_exceptions_nan_inside_mask_raises_outside_is_ignored():
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    mask = road_mask(valid)
    bad = flow.clone()
    bad[0, 0, 40, 50] = float("nan")
    with pytest.raises(ValueError, match="flow: expected finite values inside mask"):
        fit_displacement(bad, mask, cam)
    # excluded through valid=, or outside the mask: no error, a correct fit
    keep = torch.ones_like(mask)
    keep[0, 0, 40, 50] = False
    fit = fit_displacement(bad, mask, cam, valid=keep)
    assert bool(fit.success) and abs(float(fit.z_d) - 1.0) < 1e-8
    bad2 = flow.clone()
    bad2[0, :, 2, 3] = float("nan")  # above the road mask
    assert bool(fit_displacement(bad2, mask, cam).success)


NAN = float("nan")


@pytest.mark.parametrize("options, error, message", [
    # once accepted silently (or failing far from the option without naming it)
    (dict(inlier_threshold=NAN), ValueError, "inlier_threshold: expected a finite number > 0, got nan"),
    (dict(inlier_threshold=-1), ValueError, "inlier_threshold: expected a finite number > 0, got -1"),
    (dict(min_points=-5), ValueError, "min_points: expected an int >= 1, got -5"),
    (dict(init="zero"), TypeError, "init: expected a RoadFit or a dict of .* got str 'zero'"),
    (dict(polish="yes"), TypeError, "polish: expected True or False, got str 'yes'"),
    (dict(check_every=0), ValueError, "check_every: expected 'auto', an int >= 1, a pair of them .*got 0"),
    (dict(check_every=2.5), TypeError, "check_every: expected 'auto', an int >= 1, .*got float 2.5"),
    (dict(check_every="always"), TypeError, "check_every: expected 'auto', an int >= 1, .*got str 'always'"),
    (dict(prior=5), TypeError, "prior: expected None or a dict with string keys, got int 5"),
    (dict(fit_roll="no"), TypeError, "fit_roll: expected True or False, got str 'no'"),
    (dict(fit_pitch=1), TypeError, "fit_pitch: expected True or False, got int 1"),
    (dict(model="plane"), TypeError, "model: fit_displacement sets the model and its fixed parameters itself"),
    (dict(fixed=("roll",)), TypeError, "fixed: fit_displacement sets the model"),
])
def test_exceptions_options_named_and_quoted(options, error, message):
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    with pytest.raises(error, match=message):
        fit_displacement(flow, valid, cam, **options)


@pytest.mark.parametrize("fn", ["fit_road", "fit_velocity"])
def test_exceptions_options_of_fit_road_and_fit_velocity(fn):
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    call = (lambda **kw: fit_road(flow, valid, cam, **kw)) if fn == "fit_road" else (
        lambda **kw: fit_velocity(flow, valid, cam, 2.7, **kw))
    for options, error, message in [
            (dict(inlier_threshold=NAN), ValueError, "inlier_threshold: expected a finite number > 0, got nan"),
            (dict(min_points=-5), ValueError, "min_points: expected an int >= 1, got -5"),
            (dict(init="zero"), TypeError, "init: expected a RoadFit or a dict .* got str 'zero'"),
            (dict(max_points=3), ValueError, "max_points: expected an int > 15, got 3"),
            (dict(polish=None), TypeError, "polish: expected True or False, got NoneType None")]:
        with pytest.raises(error, match=message):
            call(**options)
    if fn == "fit_road":
        with pytest.raises(TypeError, match="fixed: expected None, a name or a sequence of names, got int 5"):
            call(fixed=5)
        with pytest.raises(ValueError, match="fixed: unknown parameters"):
            call(fixed=("speed",))


def test_numpy_numbers_are_options_like_python_numbers():
    """NumPy integers and floats were refused with messages that read as false ("expected an int
    >= 1, got 5"); a bool is not a number."""
    import numpy as np

    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    plain = fit_road(flow, valid, cam, min_points=5, min_inlier_fraction=0.5, max_iter=20, check_every=(2, 1))
    numpy = fit_road(flow, valid, cam, min_points=np.int64(5), min_inlier_fraction=np.float64(0.5),
                     max_iter=np.int64(20), check_every=(np.int64(2), np.int32(1)))
    for name, value in plain.params.items():
        assert torch.equal(numpy.params[name], value), name
    speed = fit_velocity(flow, valid, cam, np.float64(2.7)).extras["wheelbase"]
    assert torch.equal(speed, torch.tensor([2.7], dtype=torch.float64))
    with pytest.raises(TypeError, match="min_inlier_fraction: expected a number in \\[0, 1\\], got True"):
        fit_road(flow, valid, cam, min_inlier_fraction=True)


def test_exceptions_meta_device_fits_need_values():
    """Fitting is iterative and data dependent: on the meta device a named error, not .item()'s."""
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    meta_cam = Camera(cam.K.to("meta"), cam.height.to("meta"))
    for call in (lambda: fit_displacement(flow.to("meta"), valid.to("meta"), meta_cam),
                 lambda: fit_road(flow.to("meta"), valid.to("meta"), meta_cam, model="plane"),
                 lambda: fit_velocity(flow.to("meta"), valid.to("meta"), meta_cam, 2.7)):
        with pytest.raises(ValueError, match="flow: a tensor on the meta device has shapes but no values to fit"):
            call()
    with pytest.raises(ValueError, match="camera: a tensor on the meta device has shapes but no values to fit"):
        fit_displacement(flow, valid, meta_cam)


def test_a_mask_on_another_device_than_the_flow_is_named():
    """fit_road checked no device of the mask: a CUDA mask with a CPU flow went on to torch's own
    device error from inside the sampling (a tensor on meta, the one device a CPU test has besides
    the CPU, was named only for having no values). Now "mask: expected the device of flow (cpu),
    got meta" before any value is read, through every fit on it; ``valid``, the camera and the
    starts still follow the flow's device (a CPU ``valid`` with a CPU flow and mask fits as ever)."""
    from fsof_torch import FlowMotionEstimator

    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    fits = (lambda f, m: fit_road(f, m, cam, model="plane"), lambda f, m: fit_displacement(f, m, cam),
            lambda f, m: fit_velocity(f, m, cam, 2.7), lambda f, m: FlowMotionEstimator()(f, m, cam))
    for call in fits:
        with pytest.raises(ValueError, match=r"^mask: expected the device of flow \(cpu\), got meta$"):
            call(flow, valid.to("meta"))
        with pytest.raises(ValueError, match=r"^mask: expected the device of flow \(meta\), got cpu$"):
            call(flow.to("meta"), valid)
    fit = fit_road(flow, valid, cam, model="plane", valid=valid.clone())
    assert bool(fit.success.all()) and abs(float(fit.z_d) - 1.0) < 1e-6


def test_a_wheelbase_on_the_meta_device_is_named():
    """fit_velocity read a wheelbase tensor's values (> 0) with no check of its device: one on meta
    raised torch's "Tensor.item() cannot be called on meta tensors". Now a ValueError names it."""
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    wheelbase = torch.tensor([2.7], device="meta")
    with pytest.raises(ValueError, match=r"^wheelbase: a tensor on the meta device has shapes but no values"):
        fit_velocity(flow, valid, cam, wheelbase)
    with pytest.raises(ValueError, match=r"^init\['wheelbase'\]: a tensor on the meta device has shapes but no"):
        fit_velocity(flow, valid, cam, 2.7, init={"steering": 0.1, "speed": 10.0, "wheelbase": wheelbase})


def test_exceptions_decompose_homography():
    cam = small_camera()
    Hm = road_homography(cam, {"z_d": 1.0})
    with pytest.raises(TypeError, match="H: expected a floating-point tensor, got dtype torch.int64"):
        decompose_homography(torch.eye(3, dtype=torch.int64)[None], cam)
    with pytest.raises(ValueError, match=r"H: expected shape \(B, 3, 3\), got \(3, 3\)"):
        decompose_homography(Hm[0], cam)
    for bad in (torch.zeros(1, 3, 3), torch.full((1, 3, 3), NAN)):  # once a LinAlgError from the SVD
        with pytest.raises(ValueError, match=r"H: expected finite, invertible homographies, got samples"):
            decompose_homography(bad.double(), cam)
    with pytest.raises(ValueError, match="size: expected an int >= 8, got 0"):
        decompose_homography(Hm, cam, size=0)
    with pytest.raises(ValueError, match="H: a tensor on the meta device has shapes but no values to decompose"):
        decompose_homography(Hm.to("meta"), cam)


@pytest.mark.parametrize("case", ["empty", "tiny", "one_row", "above_horizon", "no_motion", "noise"])
def test_exceptions_degenerate_inputs_flagged(case):
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.02, 1.0, 0.01, SIZE)
    mask = torch.zeros_like(valid)
    if case == "empty":
        pass
    elif case == "tiny":
        mask[0, 0, 50:53, 70:73] = True
    elif case == "one_row":
        mask[0, 0, 50, 10:150] = True
    elif case == "above_horizon":  # a mask where the road cannot be: the model is undefined there
        mask[0, 0, :10] = True
        flow = torch.randn(flow.shape, generator=torch.Generator().manual_seed(0), dtype=flow.dtype)
    elif case == "no_motion":  # zero flow: the roll is not observable
        mask = road_mask(valid)
        flow = torch.zeros_like(flow)
    elif case == "noise":  # flow that is no road motion at all: few inliers
        mask = road_mask(valid)
        flow = 20.0 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(0), dtype=flow.dtype)
    fit = fit_displacement(flow, mask, cam)
    assert not bool(fit.success)
    for name in ("x_d", "z_d", "yaw", "roll", "pitch", "residual"):
        assert bool(torch.isfinite(getattr(fit, name)).all()), name
    assert bool(torch.isfinite(fit.flow).all())


def test_a_homography_fit_of_a_flow_beyond_its_model_fails_instead_of_naming_h():
    """fit_road(model="homography") turned its DLT start into values with homography_values, which
    raised "H: ... a last entry of 1, which the 'homography' model cannot express" for a finite
    flow of ~1e15 px and more (its K⁻¹ H K too large for the last entry to count): an argument
    the caller never gave. Now that frame starts from its default, as the plane's degenerate DLT
    does, and fails (success False, finite parameters); a good frame beside it fits as alone
    (up to the batch's rounding)."""
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.02, 1.0, 0.01, SIZE)
    mask = road_mask(valid)
    H, W = SIZE
    x = torch.arange(W, dtype=flow.dtype).expand(H, W)
    huge = torch.stack([x * 1e15, torch.zeros_like(x)])[None]  # (finite: the flow check lets it in)
    for bad in (huge, flow * 1e18):
        fit = fit_road(torch.cat([flow, bad]), mask.expand(2, -1, -1, -1), cam, model="homography")
        assert fit.success.tolist() == [True, False]
        assert all(bool(torch.isfinite(v).all()) for v in fit.params.values())
        alone = fit_road(flow, mask, cam, model="homography")
        for name, v in alone.params.items():
            torch.testing.assert_close(fit.params[name][:1], v, rtol=0, atol=1e-9)
        truth = road_homography(cam, {"x_d": 0.02, "z_d": 1.0, "yaw": 0.01})
        torch.testing.assert_close(fit.homography[0] / fit.homography[0, 2, 2], truth[0] / truth[0, 2, 2],
                                   rtol=0, atol=1e-3)


def test_no_motion_is_fine_with_the_mounting_fixed():
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 0.0, 0.0, SIZE)
    fit = fit_displacement(flow, road_mask(valid), cam, fit_roll=False)
    assert bool(fit.success)
    assert float(fit.z_d.abs()) < 1e-9 and float(fit.residual) < 1e-9


def test_no_motion_with_a_prior_on_the_attitude_leaves_it_to_the_prior():
    """At rest the flow says nothing of the roll: with a prior on it the fit reports it known to
    the prior's sigma and succeeds, on exact flow as on noisy flow. On exact flow (a flow of 0) it
    reported +inf variances and failed: the prior's weight in the normal matrix, rounded, swamped
    the data's, and the posterior's matrix came out indefinite."""
    cam = small_camera(roll=0.01)
    flow, valid = displacement_flow(cam, 0.0, 0.0, 0.0, SIZE)
    noise = 0.3 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(0), dtype=flow.dtype)
    i = fit_module.ROAD_MODELS["paper"].index("roll")
    for f in (flow, flow + noise):
        fit = fit_displacement(f, road_mask(valid), cam, prior={"roll": (0.01, 0.001)})
        assert bool(fit.success)
        assert float(fit.covariance[0, i, i].sqrt()) == pytest.approx(0.001, rel=1e-3)


# -- cardinality -------------------------------------------------------------------------------

@pytest.mark.parametrize("B", [1, 3])
def test_cardinality_batch(B):
    cam = small_camera()
    x_d = torch.tensor([0.03, -0.05, 0.0][:B], dtype=torch.float64)
    z_d = torch.tensor([0.9, 1.3, 0.5][:B], dtype=torch.float64)
    yaw = torch.tensor([0.01, -0.02, 0.0][:B], dtype=torch.float64)
    flow, valid = displacement_flow(cam, x_d, z_d, yaw, SIZE)
    fit = fit_displacement(flow, road_mask(valid), cam)  # camera and mask broadcast from batch 1
    assert fit.x_d.shape == (B,) and fit.flow.shape == (B, 2, *SIZE)
    assert fit.camera.batch_size == B and fit.success.all()
    torch.testing.assert_close(fit.z_d, z_d, atol=1e-8, rtol=0)
    torch.testing.assert_close(fit.yaw, yaw, atol=1e-9, rtol=0)


def test_cardinality_batch_is_per_frame():
    """One failing frame does not disturb the others."""
    cam = small_camera()
    zero = torch.zeros(2, dtype=torch.float64)
    flow, valid = displacement_flow(cam, zero, torch.tensor([1.0, 0.7], dtype=torch.float64), zero, SIZE)
    mask = road_mask(valid).clone()
    mask[1] = False
    fit = fit_displacement(flow, mask, cam)
    assert fit.success.tolist() == [True, False]
    assert abs(float(fit.z_d[0]) - 1.0) < 1e-9


def test_cardinality_valid_of_batch_1_broadcasts_like_the_mask():
    """``valid`` of batch 1 for a batch of 3 serves every frame, as a mask of batch 1 does (it
    was a ValueError naming valid while the mask broadcast)."""
    cam = small_camera()
    z_d = torch.tensor([0.9, 1.3, 0.5], dtype=torch.float64)
    zero = torch.zeros(3, dtype=torch.float64)
    flow, valid = displacement_flow(cam, zero, z_d, zero, SIZE)
    flow = flow.clone()
    flow[:, :, 40:, :30] = float("nan")  # (a hole in the ground truth: valid excludes it)
    valid1 = torch.ones(1, 1, *SIZE, dtype=torch.bool)
    valid1[:, :, 40:, :30] = False
    mask = road_mask(valid)
    fit = fit_road(flow, mask, cam, model="plane", valid=valid1)
    torch.testing.assert_close(fit.z_d, z_d, atol=1e-8, rtol=0)
    per_frame = fit_road(flow, mask, cam, model="plane", valid=valid1.expand(3, -1, -1, -1))
    assert torch.equal(fit.z_d, per_frame.z_d) and torch.equal(fit.inliers, per_frame.inliers)
    with pytest.raises(ValueError, match=r"^valid: expected shape \(B, 1, H, W\) with B=3"):
        fit_road(flow, mask, cam, model="plane", valid=valid1.expand(2, -1, -1, -1))


# -- feature -----------------------------------------------------------------------------------

@pytest.mark.parametrize("params", [
    dict(x_d=0.05, z_d=1.1, yaw=0.02, roll=0.03, pitch=-0.02),
    dict(x_d=-0.2, z_d=0.6, yaw=-0.08, roll=-0.05, pitch=0.015),
    dict(x_d=0.0, z_d=-0.7, yaw=0.0, roll=0.0, pitch=0.0),  # reversing
])
def test_feature_noise_free_recovery(params):
    """float64, no noise, no prior: every parameter to 1e-6 relative (start: camera level)."""
    true_cam = small_camera(roll=params["roll"], pitch=params["pitch"])
    flow, valid = displacement_flow(true_cam, params["x_d"], params["z_d"], params["yaw"], SIZE)
    fit = fit_displacement(flow, road_mask(valid), small_camera(), fit_roll=True, fit_pitch=True)
    assert bool(fit.success)
    scale = {"x_d": abs(params["z_d"]), "z_d": abs(params["z_d"]), "yaw": 1.0, "roll": 1.0, "pitch": 1.0}
    for name, value in params.items():
        got = float(getattr(fit, name))
        assert abs(got - value) <= 1e-6 * max(abs(value), 1e-3 * scale[name]), (name, got, value)
    assert float(fit.residual) < 1e-6
    torch.testing.assert_close(fit.camera.roll, torch.tensor([params["roll"]], dtype=torch.float64))


def test_feature_fitted_homography_is_the_flow_models():
    """The fit's homography is the road homography of its parameters, and its flow the model's."""
    cam = small_camera(roll=0.02, pitch=-0.01)
    flow, valid = displacement_flow(cam, 0.1, 1.2, 0.03, SIZE)
    fit = fit_displacement(flow, road_mask(valid), cam, fit_pitch=True)
    torch.testing.assert_close(fit.homography, road_homography(fit.camera, fit.odometry(), model="paper"))
    model, _ = displacement_flow(fit.camera, fit.x_d, fit.z_d, fit.yaw, SIZE)
    torch.testing.assert_close(fit.flow, model)


def _outlier_scene(seed: int):
    cam = small_camera(roll=0.02, pitch=-0.01)
    flow, valid = displacement_flow(cam, 0.04, 1.2, 0.015, SIZE)
    mask = road_mask(valid)
    # "cars": vertical bands of the mask carrying the flow of other motions, 30% of the mask
    cars = flow.clone()
    covered = torch.zeros_like(mask)
    for (a, b), motion in zip([(6, 22), (62, 78), (124, 140)],
                              [(0.0, 0.3, 0.0), (-0.3, 2.0, -0.05), (0.2, -0.5, 0.03)]):
        other, _ = displacement_flow(cam, *motion, SIZE)
        cars[..., a:b] = other[..., a:b]
        covered[..., a:b] = True
    frac = float((covered & mask).sum() / mask.sum())
    noise = 0.5 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(seed), dtype=flow.dtype)
    return cam, flow, mask, flow + noise, cars + noise, frac


@pytest.mark.parametrize("seed", [0, 1])
def test_feature_outliers_within_twice_the_noise_error(seed):
    cam, truth, mask, clean, with_cars, frac = _outlier_scene(seed)
    assert 0.28 <= frac <= 0.32
    start = small_camera()
    fit0 = fit_displacement(clean, mask, start, fit_pitch=True)
    fit1 = fit_displacement(with_cars, mask, start, fit_pitch=True)
    assert bool(fit0.success) and bool(fit1.success)
    err0, err1 = epe_to(fit0.flow, truth, mask), epe_to(fit1.flow, truth, mask)
    assert err1 <= 2.0 * err0, (err0, err1)
    assert err0 < 0.05
    # the cars whose motion differs by more than the inlier threshold are recognised as outliers
    cars = torch.zeros_like(mask)
    cars[..., 62:78] = True
    cars[..., 124:140] = True
    cars &= mask & ((with_cars - clean).norm(dim=1, keepdim=True) > 3.0)
    assert float(fit1.inliers[cars].float().mean()) < 0.05


def test_feature_resolution_stop_saves_iterations_not_accuracy(monkeypatch):
    """Steps that move the model flow by under 1 % of the robust RMS residual end the fit: on
    noisy flow that saves iterations, and the estimate moves far less than its own error."""
    cam, truth, mask, _, with_cars, _ = _outlier_scene(0)
    start = small_camera()
    fast = fit_displacement(with_cars, mask, start, max_points=None)
    monkeypatch.setattr(fit_module, "_RESOLUTION", 0.0)
    monkeypatch.setattr(fit_module, "_ROBUST_STAGE_RESOLUTION", 0.0)
    tight = fit_displacement(with_cars, mask, start, max_points=None)
    assert bool(fast.success) and bool(tight.success)
    assert int(fast.iterations) < int(tight.iterations)
    moved = epe_to(fast.flow, tight.flow, mask)
    assert moved < 0.2 * epe_to(tight.flow, truth, mask), (moved, epe_to(tight.flow, truth, mask))


def test_feature_robust_kernels_all_fit_clean_data():
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.02, 0.8, 0.01, SIZE)
    for kind in ROBUST_KERNELS:
        fit = fit_displacement(flow, road_mask(valid), cam, robust=kind)
        assert bool(fit.success), kind
        assert abs(float(fit.z_d) - 0.8) < 1e-8, kind


def test_feature_robust_weight_values():
    r2 = torch.tensor([0.0, 1.0, 4.0, 16.0], dtype=torch.float64)
    torch.testing.assert_close(robust_weight(r2, 2.0, "cauchy"), 1 / (1 + r2 / 4))
    torch.testing.assert_close(robust_weight(r2, 2.0, "soft_l1"), (1 + r2 / 4) ** -0.5)
    torch.testing.assert_close(robust_weight(r2, 2.0, "huber"), torch.tensor([1.0, 1.0, 1.0, 0.5], dtype=torch.float64))
    torch.testing.assert_close(robust_weight(r2, 2.0, "tukey"), torch.tensor([1.0, 0.5625, 0.0, 0.0], dtype=torch.float64))


def test_feature_subsampling_is_deterministic_and_close():
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.02, 1.0, 0.01, SIZE)
    noisy = flow + 0.3 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(3), dtype=flow.dtype)
    mask = road_mask(valid)
    a = fit_displacement(noisy, mask, cam, max_points=500)
    b = fit_displacement(noisy, mask, cam, max_points=500)
    full = fit_displacement(noisy, mask, cam, max_points=None)
    assert torch.equal(a.z_d, b.z_d)
    # 500 of the mask's 6400 pixels give z_d within 6e-4 of all of them (the first 500 pixels in
    # raster order, four rows under the horizon, 0.011 off)
    assert abs(float(a.z_d - full.z_d)) < 0.003
    # the kept pixels stride over the whole mask: its first row to its last
    kept = sample_mask(mask, 500).pix[0] // SIZE[1]
    rows = mask[0, 0].any(1).nonzero().squeeze(1)
    assert int(kept.min()) == int(rows.min()) and int(kept.max()) == int(rows.max())


def test_feature_init_from_a_previous_result():
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.02, 1.0, 0.01, SIZE)
    first = fit_displacement(flow, road_mask(valid), cam)
    again = fit_displacement(flow, road_mask(valid), cam, init=first)
    assert bool(again.success) and int(again.iterations) <= 3
    again2 = fit_displacement(flow, road_mask(valid), cam, init=dict(z_d=0.5))
    assert abs(float(again2.z_d) - 1.0) < 1e-8
    # the start is the init: one step from z_d = 0.5 has not arrived (the default start, from the
    # flow itself, is exact here), one step from the previous result stays there
    one_step = fit_displacement(flow, road_mask(valid), cam, init=dict(z_d=0.5), max_iter=1)
    assert abs(float(one_step.z_d) - 1.0) > 0.01
    assert abs(float(fit_displacement(flow, road_mask(valid), cam, init=first, max_iter=1).z_d) - 1.0) < 1e-8


def test_feature_velocity_noise_free_recovery():
    cam = small_camera(roll=0.02, pitch=-0.015)
    flow, valid = velocity_flow(cam, 12.0, 0.05, 2.7, SIZE)
    fit = fit_velocity(flow, road_mask(valid), small_camera(), 2.7, fit_pitch=True)
    assert isinstance(fit, VelocityFitResult) and bool(fit.success)
    for name, value in dict(speed=12.0, steering=0.05, roll=0.02, pitch=-0.015).items():
        assert abs(float(getattr(fit, name)) - value) <= 1e-6 * abs(value), name
    assert set(fit.velocity()) == {"speed", "steering", "wheelbase"}


def test_velocity_steering_reads_the_speed_variance_by_name(monkeypatch):
    """fit_velocity told a moving car from one at rest by the covariance at [0, 0], the speed's
    only while the velocity model lists speed first: it reads the speed's entry by its name."""
    import dataclasses

    from fsof_torch.geometry.road_models import ROAD_MODELS

    cam = small_camera()
    flow, valid = velocity_flow(cam, 12.0, 0.05, 2.7, SIZE)
    real = fit_velocity(flow, road_mask(valid), cam, 2.7)
    # the same fit as a model listing yaw_rate first would give it: a yaw rate known to ±1000 rad/s,
    # the speed exactly (a speed told from rest, so a steering angle)
    swapped = dataclasses.replace(ROAD_MODELS["velocity"], params=("yaw_rate", "speed", "roll", "pitch"))
    cov = torch.zeros(1, 4, 4, dtype=torch.float64)
    cov[0, 0, 0] = 1e6
    monkeypatch.setitem(ROAD_MODELS, "velocity", swapped)
    monkeypatch.setattr(fit_module, "fit_road", lambda *a, **k: dataclasses.replace(real, covariance=cov, extras={}))
    fit = fit_velocity(flow, road_mask(valid), cam, 2.7)
    assert abs(float(fit.steering) - 0.05) <= 1e-6


def test_feature_velocity_batch_and_outliers():
    cam = small_camera()
    speed = torch.tensor([8.0, 15.0, 3.0], dtype=torch.float64)
    steer = torch.tensor([0.0, -0.04, 0.1], dtype=torch.float64)
    flow, valid = velocity_flow(cam, speed, steer, 2.7, SIZE)
    noisy = flow + 2.0 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(0), dtype=flow.dtype)
    noisy[..., 60:80] += 200.0  # a car: far outliers in px/s
    fit = fit_velocity(noisy, road_mask(valid), cam, 2.7)
    assert fit.success.all()
    torch.testing.assert_close(fit.speed, speed, atol=0.05, rtol=0.0)
    torch.testing.assert_close(fit.steering, steer, atol=2e-3, rtol=0.0)


# -- real data ---------------------------------------------------------------------------------

def test_real_kitti_ground_truth_fit(kitti15_ground_truth):
    cam, flow, valid, road = kitti15_ground_truth
    use = road & valid
    fit = fit_displacement(flow, road, cam, valid=valid)
    assert bool(fit.success)
    e_E = epe_to(fit.flow, flow, use)
    assert e_E <= 0.40, e_E
    fit_p = fit_displacement(flow, road, cam, valid=valid, fit_pitch=True)
    assert bool(fit_p.success)
    assert epe_to(fit_p.flow, flow, use) <= e_E + 1e-6
    # plausible ego-motion of a car at ~50 km/h and 10 Hz
    assert 1.0 < float(fit.z_d) < 1.8 and abs(float(fit.roll)) < 0.02


def test_decompose_a_camera_cropped_past_its_principal_point():
    """A crop that leaves the principal point above and left of the image (Camera.cropped allows
    it) is decomposed as any other (it raised about a scale the caller never gave)."""
    K = torch.tensor([[300.0, 0, 80], [0, 300, 20], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, 1.5).cropped(100, 30)
    assert float(cam.cx[0]) < 0 and float(cam.cy[0]) < 0
    H = road_homography(cam, {"z_d": 1.0, "yaw": 0.01}, model="plane")
    dec = decompose_homography(H, cam)
    assert float(dec.params["z_d"][0]) == pytest.approx(1.0, abs=1e-6)
    assert float(dec.params["yaw"][0]) == pytest.approx(0.01, abs=1e-8)


@pytest.mark.parametrize("droll, dpitch", [(0.0, 0.0), (0.02, 0.03)], ids=["camera_attitude", "road_tilted"])
def test_decompose_a_camera_whose_horizon_lies_below_its_image(droll, dpitch):
    """A camera pitched up 0.4 rad sees its horizon 275 px below the principal point, beyond the
    virtual image around it (2 c_y + 1 rows): the grid moves below the horizon, and the
    decomposition is as exact as for any camera. (Its grid held no pixel: the closed form came back
    with a residual of 0 over no pixel, y_d 0.059 for 0.01 on a road tilted 2 degrees.)"""
    K = torch.tensor([[700.0, 0, 600], [0, 650, 180], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, 1.5, roll=0.0, pitch=0.4)
    p = {"pitch_change": 0.004, "yaw": 0.03, "roll_change": -0.003, "x_d": 0.1, "y_d": 0.01, "z_d": 1.2,
         "roll": droll, "pitch": 0.4 + dpitch}
    H = road_homography(cam, p, model="plane")
    dec = decompose_homography(H, cam)
    assert bool(dec.success) and int(dec.valid.sum()) > 1000 and float(dec.residual) < 1e-9
    for k, v in p.items():
        assert float(dec.params[k]) == pytest.approx(v, abs=1e-8), k
    S = dec.camera.K @ torch.linalg.inv(cam.K)  # (as the docstring says: H in the grid's pixels)
    back = torch.linalg.inv(S) @ dec.homography @ S
    torch.testing.assert_close(back / back[:, 2:, 2:], H / H[:, 2:, 2:], rtol=0, atol=1e-9)


@pytest.mark.parametrize("steering, error, match", [
    ("x", TypeError, r"^init: expected numbers or tensors for steering and speed"),
    (float("nan"), ValueError, r"^init: expected a finite steering"),
    (math.pi / 2, ValueError, r"^init: expected a finite steering with \|δ_f\| < π/2"),
])
def test_fit_velocity_init_steering_is_named(steering, error, match):
    K = torch.tensor([[300.0, 0, 80], [0, 300, 20], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, 1.5)
    flow, valid = velocity_flow(cam, 10.0, 0.05, 2.7, (48, 160))
    with pytest.raises(error, match=match):
        fit_velocity(flow, valid, cam, 2.7, init={"steering": steering, "speed": 12.0})


def test_fit_velocity_takes_an_earlier_fits_velocity_as_its_start(monkeypatch):
    """``fit.velocity()`` (speed, steering, wheelbase) is a start for the next fit (it raised
    ``init: unknown parameters ['wheelbase']``); its steering becomes the start's yaw rate with its
    own wheelbase, not the new fit's; the caller's dict is left as it was."""
    import fsof_torch.estimation.flow_fit as flow_fit

    K = torch.tensor([[300.0, 0, 80], [0, 300, 20], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, 1.5)
    flow, valid = velocity_flow(cam, 10.0, 0.05, 2.7, (48, 160))
    first = fit_velocity(flow, valid, cam, 2.7)
    start = first.velocity()
    again = fit_velocity(flow, valid, cam, 2.7, init=start)
    assert bool(again.success) and float(again.steering) == pytest.approx(0.05, abs=1e-9)
    assert set(start) == {"speed", "steering", "wheelbase"}
    seen = []
    fit_road = flow_fit.fit_road
    monkeypatch.setattr(flow_fit, "fit_road", lambda *a, init=None, **k: seen.append(init) or fit_road(*a, init=init, **k))
    fit_velocity(flow, valid, cam, 3.5, init=start)  # (another car's wheelbase for this fit's steering)
    assert float(seen[0]["yaw_rate"]) == pytest.approx(float(first.yaw_rate), rel=1e-12)
    assert "wheelbase" not in seen[0] and "steering" not in seen[0]
    with pytest.raises(ValueError, match=r"^init\['wheelbase'\]: expected values > 0"):
        fit_velocity(flow, valid, cam, 2.7, init={**start, "wheelbase": -1.0})


def test_fit_velocity_steering_of_a_vehicle_at_rest_is_0():
    """At rest the yaw rate is about 0 and so is the speed: their ratio, the steering, is noise
    (one such fit of 0.2 px/s noise gave -3° with ``success`` True: the roll held, nothing else is
    undetermined). A speed within 3 σ of 0 is rest: steering 0, as the docstring says; moving at
    1 m/s the same noise leaves the steering within 0.01 rad of the truth."""
    K = torch.tensor([[300.0, 0, 160], [0, 300, 40], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, 1.5, 0.01, -0.01)
    noise = 0.2 * torch.randn(1, 2, 96, 320, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    for speed, expected in ((0.0, 0.0), (1.0, 0.05)):
        flow, valid = velocity_flow(cam, speed, 0.05, 2.7, (96, 320))
        valid[..., :50, :] = False
        fit = fit_velocity(flow + noise, valid, cam, 2.7, fit_roll=False)
        assert bool(fit.success)
        assert float(fit.steering) == pytest.approx(expected, abs=0.01 if speed else 0.0), float(fit.speed)


def test_a_prior_on_a_held_parameter_is_refused():
    """A prior on a parameter the fit holds (the pitch by default, or one in ``fixed``) would be
    ignored: a ValueError that says so (it was silently dropped, success True); freed, it acts."""
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    with pytest.raises(ValueError, match=r"^prior: 'pitch' is held at its start \(fixed=\('pitch',\)\), so its "
                                         r"prior would be ignored; free it"):
        fit_displacement(flow, valid, cam, prior={"pitch": (-0.017, 0.002)})
    with pytest.raises(ValueError, match=r"^prior: 'roll' is held at its start"):
        fit_road(flow, valid, cam, model="plane", fixed=("roll", "pitch"), prior={"roll": (0.01, 0.01)})
    fit = fit_displacement(flow, valid, cam, fit_pitch=True, prior={"pitch": (0.0, 0.002)})
    assert bool(fit.success) and float(fit.z_d) == pytest.approx(1.0, abs=1e-6)


def test_road_points_behind_the_camera_at_t1_do_not_count():
    """The fit's residuals count only the points whose road point is in front of the camera at t+1:
    a level camera sees the road at row v at depth Z = h f_y / (v − c_y), which a forward step z_d
    takes behind the camera where Z < z_d (the homography's projection there is meaningless)."""
    cam = small_camera()
    H, W = SIZE
    v = torch.arange(20, H, dtype=torch.float64)
    pts = torch.stack([torch.full_like(v, 80.0), v, torch.ones_like(v)]).unsqueeze(0)  # (1, 3, N)
    depth = 1.65 * 130.0 / (v - 16.0)
    z_d = 8.0
    assert (depth < z_d).any() and (depth > z_d).any() and bool(((depth - z_d).abs() > 0.05).all())
    from fsof_torch.geometry.road_models import get_road_model

    model = get_road_model("paper")
    problem = fit_module.FlowProblem(model, cam, pts, torch.zeros(1, 2, v.numel(), dtype=torch.float64),
                                     torch.ones(1, v.numel(), dtype=torch.bool))
    ev = problem.evaluate(torch.tensor([[0.0, z_d, 0.0, 0.0, 0.0]], dtype=torch.float64))
    assert torch.equal(ev.use[0], depth > z_d)


def test_a_prior_weighs_against_the_flow_at_the_kernels_scale():
    """A prior (μ, σ) is weighed against the residuals at the kernel's scale c: with the l2 kernel
    the fit minimises Σ |r|² + (c / σ)² (z_d − μ)². The minimiser is found here by a golden-section
    search over that energy, evaluated with displacement_flow; for two scales with the same c / σ
    (the same answer, halfway between the flow's z_d and the prior's mean)."""
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    mask = road_mask(valid)
    f_step, _ = displacement_flow(cam, 0.0, 1.001, 0.0, SIZE)
    curvature = float(((f_step - flow) / 0.001).square().sum(1, keepdim=True)[mask].sum())  # Σ |dr/dz_d|²
    lam = curvature  # the prior's precision in residual² per m²: as strong as the flow's

    def energy(z):
        f, _ = displacement_flow(cam, 0.0, z, 0.0, SIZE)
        return float((f - flow).square().sum(1, keepdim=True)[mask].sum()) + lam * (z - 1.5) ** 2

    lo, hi, g = 1.0, 1.5, (math.sqrt(5) - 1) / 2
    for _ in range(40):
        m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
        lo, hi = (lo, m2) if energy(m1) < energy(m2) else (m1, hi)
    z_ref = (lo + hi) / 2
    assert 1.2 < z_ref < 1.3
    for scale in (0.5, 2.0):
        fit = fit_road(flow, mask, cam, robust="l2", scale=scale, fixed=("x_d", "yaw", "roll", "pitch"),
                       max_points=None, prior={"z_d": (1.5, scale / math.sqrt(lam))})
        assert bool(fit.success)
        # (to the fit's resolution: it stops when a step moves the residuals by 1 % of their RMS)
        assert float(fit.z_d) == pytest.approx(z_ref, abs=3e-3), scale


def test_detect_freespace_keeps_a_roll_prior_for_the_hypothesis_that_fits_the_roll():
    """detect_freespace's second hypothesis holds the camera's roll and pitch: a caller's prior on
    them belongs to the first, which fits them (passing it to both would be refused)."""
    from fsof_torch import detect_freespace

    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    road = valid & torch.isfinite(flow).all(1, keepdim=True)  # (a road everywhere below the horizon)
    with_prior = detect_freespace(flow, cam, fit_options={"prior": {"roll": (0.0, 0.01)}})
    assert float((with_prior & road).sum() / (with_prior | road).sum()) > 0.9


def test_exceptions_batch_of_priors_and_velocity_init_named():
    """A prior or a velocity start of the wrong batch is a ValueError naming its key (it was
    torch's RuntimeError about expanding or broadcasting)."""
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    flow3, valid3 = flow.expand(3, -1, -1, -1), valid.expand(3, -1, -1, -1)
    two = torch.tensor([1.0, 1.0], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^prior\['z_d'\] mean: expected batch 1 or 3, got 2 values$"):
        fit_road(flow3, valid3, cam, prior={"z_d": (two, 0.1)})
    with pytest.raises(ValueError, match=r"^prior\['z_d'\] sigma: expected batch 1 or 3, got 2 values$"):
        fit_road(flow3, valid3, cam, prior={"z_d": (1.0, 0.1 * two)})
    with pytest.raises(ValueError, match=r"^prior\['yaw'\] mean: expected batch 1, got 2 values$"):
        fit_road(flow, valid, cam, prior={"yaw": (two, 0.1)})
    vflow, vvalid = velocity_flow(cam.expand(3), 10.0, 0.05, 2.7, SIZE)
    with pytest.raises(ValueError, match=r"^init\['speed'\]: expected batch 1 or 3, got 2 values$"):
        fit_velocity(vflow, vvalid, cam, 2.7, init={"steering": [0.05] * 3, "speed": [10.0, 10.0]})
    with pytest.raises(ValueError, match=r"^init\['steering'\]: expected batch 1 or 3, got 2 values$"):
        fit_velocity(vflow, vvalid, cam, 2.7, init={"steering": [0.05] * 2, "speed": 10.0})
    # a prior and a start per frame, or one for all, as before
    per_frame = fit_road(flow3, valid3, cam, prior={"z_d": (torch.ones(3, dtype=torch.float64), 0.1)})
    assert per_frame.z_d.tolist() == pytest.approx([1.0] * 3, abs=1e-6)
    fit = fit_velocity(vflow, vvalid, cam, 2.7, init={"steering": [0.05] * 3, "speed": 10.0})
    assert fit.speed.tolist() == pytest.approx([10.0] * 3, abs=1e-6)


def test_exceptions_odometry_of_a_model_without_it():
    """RoadFit.odometry() of a fit whose model has no (x_d, z_d, yaw): a ValueError naming the
    model (not a bare KeyError)."""
    cam = small_camera()
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, SIZE)
    fit = fit_road(flow, valid, cam, model="homography")
    with pytest.raises(ValueError, match=r"^odometry: a 'homography' fit has no x_d, z_d, yaw: \('h11',"):
        fit.odometry()
    assert fit_road(flow, valid, cam, model="plane").odometry()["z_d"].tolist() == pytest.approx([1.0], abs=1e-6)


def test_exceptions_a_batch_1_mask_is_quoted_as_passed():
    """A batch-1 mask of the wrong size is quoted with the shape that came (the message quoted it
    broadcast to the flow's batch, a shape the caller never passed)."""
    cam = small_camera()
    flow = torch.zeros(3, 2, 96, 320, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^mask: expected shape \(B, 1, H, W\) with H=96 \(from an earlier "
                                         r"argument\), got \(1, 1, 50, 320\)$"):
        fit_road(flow, torch.ones(1, 1, 50, 320, dtype=torch.bool), cam)
    with pytest.raises(ValueError, match=r"^mask: expected shape \(B, 1, H, W\) with B=3 .*got \(2, 1, 96, 320\)$"):
        fit_road(flow, torch.ones(2, 1, 96, 320, dtype=torch.bool), cam)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("B", [1, 2])
def test_result_camera_is_a_copy_of_the_callers(dtype, B):
    """fit.camera's K, height and held roll / pitch are the fit's own tensors: editing them in place
    leaves the caller's camera alone (they shared its storage where the dtype matched) and works
    for a batch-1 camera broadcast to the flow's batch (an expanded view refused the edit)."""
    K = torch.tensor([[130.0, 0.0, 80.0], [0.0, 130.0, 16.0], [0.0, 0.0, 1.0]], dtype=dtype)
    cam = Camera(K, 1.65, 0.01, -0.02)
    flow, valid = displacement_flow(cam, 0.02, 0.8, 0.01, SIZE)
    flow, valid = flow.to(dtype).expand(B, -1, -1, -1), road_mask(valid).expand(B, -1, -1, -1)
    before = [t.clone() for t in (K, cam.K, cam.height, cam.roll, cam.pitch)]
    fits = [fit_displacement(flow, valid, cam, fit_roll=False),
            fit_road(flow, valid, cam, model="homography")]  # (no roll / pitch of its own)
    for fit in fits:
        assert fit.camera.K.dtype == dtype and fit.camera.batch_size == B
        fit.camera.K.mul_(0.5)
        fit.camera.height.add_(1.0)
        fit.camera.roll.zero_()
        fit.camera.pitch.zero_()
    for was, now in zip(before, (K, cam.K, cam.height, cam.roll, cam.pitch)):
        assert torch.equal(was, now)


def test_velocity_wheelbase_is_the_fits_own():
    """fit.wheelbase is a (B,) tensor of the fit's own: not the caller's tensor (an edit of the
    result changed it), nor a stride-0 view of a float wheelbase (which refused an in-place edit)."""
    cam = small_camera()
    flow, valid = velocity_flow(cam, 10.0, 0.05, 2.7, SIZE)
    wheelbase = torch.tensor([2.7], dtype=torch.float64)
    fit = fit_velocity(flow, road_mask(valid), cam, wheelbase)
    fit.wheelbase.mul_(2.0)
    assert wheelbase.tolist() == [2.7]
    fit = fit_velocity(flow.expand(2, -1, -1, -1), road_mask(valid), cam, 2.7)
    assert fit.wheelbase.shape == (2,) and fit.wheelbase.stride() == (1,)
    fit.wheelbase[0] = 3.0
    assert fit.wheelbase.tolist() == [3.0, 2.7]


def test_held_roll_and_pitch_start_at_init_else_at_the_camera():
    """A held roll / pitch is held at its start: init's value where init gives one, else the
    camera's (as the docstring and docs/fitting.md say; they named the camera's alone)."""
    from pathlib import Path

    cam = small_camera(roll=0.005, pitch=0.003)
    flow, valid = displacement_flow(small_camera(roll=0.02), 0.02, 0.8, 0.01, SIZE)
    mask = road_mask(valid)
    plain = fit_displacement(flow, mask, cam, fit_roll=False)
    assert (float(plain.roll), float(plain.pitch)) == (0.005, 0.003)
    started = fit_displacement(flow, mask, cam, fit_roll=False, init={"roll": 0.05})
    assert (float(started.roll), float(started.pitch)) == (0.05, 0.003)
    assert float(started.camera.roll) == 0.05
    previous = fit_displacement(flow, mask, small_camera(roll=0.04), fit_roll=False)
    assert float(fit_displacement(flow, mask, cam, fit_roll=False, init=previous).roll) == 0.04
    for model in ("plane", "velocity"):
        fit = fit_road(flow, mask, cam, model=model, fixed=("roll", "pitch"), init={"pitch": -0.01})
        assert (float(fit.roll), float(fit.pitch)) == (0.005, -0.01), model
    doc = " ".join(fit_road.__doc__.split())
    assert "held at their start (``init``'s value where it gives one, else the default start: the camera's " \
           "roll / pitch, and 0 for a motion parameter" in doc
    text = " ".join((Path(__file__).resolve().parents[1] / "docs" / "fitting.md").read_text().split())
    assert "held at their start: `init`'s value where `init` gives one, else the default start (for the roll " \
           "and pitch, the camera's; for a motion parameter 0, no motion" in text


def test_held_motion_parameters_are_held_at_no_motion_not_at_the_start_guess():
    """A motion parameter in ``fixed`` without a value in ``init`` is held at the default start, no
    motion (0), as the roll and pitch are held at the camera's: it was held at the data-driven start
    (the planar motion or the DLT's decomposition) instead, a value from the flow itself, so that
    holding it changed nothing (a held y_d came back as the flow's own 0.02 m)."""
    cam = small_camera(roll=0.01, pitch=-0.015)
    truth = {"z_d": 1.0, "x_d": 0.03, "yaw": 0.01, "pitch_change": 0.003, "y_d": 0.02}
    flow, valid = road_flow(cam, truth, SIZE, model="plane")
    mask = road_mask(valid)
    cases = [("plane", ("y_d",)), ("plane", ("pitch_change", "roll_change", "y_d")), ("paper", ("yaw", "pitch")),
             ("paper", ("x_d", "pitch")), ("homography", ("h31", "h32"))]
    for model, fixed in cases:
        fit = fit_road(flow, mask, cam, model=model, fixed=fixed)
        for name in fixed:
            expected = {"roll": 0.01, "pitch": -0.015}.get(name, 0.0)
            assert float(fit.params[name]) == expected, (model, name)
    # the others are fitted with the held value: the plane's flow without vertical motion, exactly
    flat = {**truth, "y_d": 0.0}
    flow, valid = road_flow(cam, flat, SIZE, model="plane")
    fit = fit_road(flow, road_mask(valid), cam, model="plane", fixed=("y_d",))
    assert bool(fit.success) and float(fit.y_d) == 0.0
    for name, value in flat.items():
        assert abs(float(fit.params[name]) - value) < 1e-8, name
    # a value given in init is held there, as before
    fit = fit_road(flow, road_mask(valid), cam, model="plane", fixed=("y_d",), init={"y_d": 0.005})
    assert float(fit.y_d) == 0.005


def test_fit_velocity_init_with_a_steering_and_a_yaw_rate_is_refused_by_name():
    """A start giving both a steering angle and a yaw rate (``{**fit.params, **fit.extras}``) is a
    ValueError naming both, not ``init: unknown parameters ['steering']`` (steering alone is
    accepted); a steering of None is not given, as any other entry of None."""
    K = torch.tensor([[300.0, 0, 80], [0, 300, 20], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, 1.5)
    flow, valid = velocity_flow(cam, 10.0, 0.05, 2.7, (48, 160))
    fit = fit_velocity(flow, valid, cam, 2.7)
    for init in ({"speed": 10.0, "steering": 0.05, "yaw_rate": 0.2}, {**fit.params, **fit.extras}):
        with pytest.raises(ValueError, match=r"^init: expected a steering angle or a yaw rate, not both .*"
                                             r"got steering=.* and yaw_rate=.*; drop one$"):
            fit_velocity(flow, valid, cam, 2.7, init=init)
    again = fit_velocity(flow, valid, cam, 2.7, init={"speed": 10.0, "steering": None, "yaw_rate": 0.2})
    assert bool(again.success) and float(again.yaw_rate) == pytest.approx(10.0 * math.tan(0.05) / 2.7, rel=1e-9)


@pytest.mark.parametrize("robust", ["l2", "tukey"])
def test_robust_l2_and_tukey_run_no_polish(robust):
    """As the docstring says: ``robust="l2"`` and ``"tukey"`` run one stage, ``polish`` ignored
    (the same fit bit for bit); another kernel's polish changes it."""
    cam = small_camera()
    flow, valid = road_flow(cam, {"x_d": 0.05, "z_d": 1.1, "yaw": 0.01}, (48, 160), model="paper")
    noisy = flow + 0.5 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(0), dtype=flow.dtype)
    mask = road_mask(valid)
    on, off = (fit_road(noisy, mask, cam, robust=robust, polish=p) for p in (True, False))
    assert all(torch.equal(on.params[k], off.params[k]) for k in on.params) and torch.equal(on.iterations, off.iterations)
    cauchy = [fit_road(noisy, mask, cam, polish=p) for p in (True, False)]
    assert not torch.equal(cauchy[0].params["z_d"], cauchy[1].params["z_d"])


def test_velocity_of_a_fit_without_a_steering_is_a_named_error():
    """``fit.velocity()`` of a fit without a steering angle (``fit_road(model="velocity")``, which
    has no wheelbase, or another model's fit) is a ValueError saying so, as ``odometry()`` of a fit
    without x_d, z_d, yaw (it raised AttributeError "... has no 'steering'")."""
    K = torch.tensor([[300.0, 0, 80], [0, 300, 20], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, 1.5)
    flow, valid = velocity_flow(cam, 10.0, 0.05, 2.7, (48, 160))
    fit = fit_road(flow, valid, cam, model="velocity")
    with pytest.raises(ValueError, match=r"^velocity: a 'velocity' fit has no steering and wheelbase: fit_velocity"):
        fit.velocity()
    paper = fit_road(*displacement_flow(cam, 0.0, 1.0, 0.0, (48, 160)), cam)
    with pytest.raises(ValueError, match=r"^velocity: a 'paper' fit has no steering and wheelbase"):
        paper.velocity()
    steered = fit_velocity(flow, valid, cam, 2.7).velocity()
    assert float(steered["steering"]) == pytest.approx(0.05, abs=1e-9) and float(steered["wheelbase"]) == 2.7
