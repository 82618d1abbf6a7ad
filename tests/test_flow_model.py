"""Tests of fsof_torch.geometry.road_flow: the displacement (eq. 13) and velocity (eq. 21) road-flow models.

Independent references, all written here in NumPy float64:
- the paper's λ formula (eq. 13 / eq. 21, roll only: the paper has no pitch),
- the plain plane-induced homography H = K R_c R_φ (I - d nᵀ/h) R_cᵀ K⁻¹ applied pixel by pixel,
- a direct 3D ray cast: intersect the viewing ray with the road y = h in the vehicle frame, move the
  point with R_φ (p - d), project with K R_c (this one includes the pitch extension).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.egomotion import ego_motion_from_ackermann
from fsof_torch.geometry.road_flow import (
    DisplacementFlow,
    VelocityFlow,
    displacement_flow,
    displacement_flow_straight,
    displacement_flow_straight_level,
    flow_from_map,
    pixel_grid,
    road_velocity_matrix,
    velocity_flow,
    velocity_flow_straight,
    velocity_flow_straight_level,
    vflow_curve,
)
from fsof_torch.geometry.road_models import road_homography

KITTI = dict(fx=721.5377, fy=721.5377, cx=609.5593, cy=172.854)


def _K(fx, fy, cx, cy, skew=0.0, dtype=torch.float64):
    return torch.tensor([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)


def _camera(height=1.65, roll=0.0, pitch=0.0, dtype=torch.float64, **k):
    k = {**KITTI, **k}
    return Camera(_K(k["fx"], k["fy"], k["cx"], k["cy"], dtype=dtype), height, roll, pitch)


def _kitti_scaled(H, W, **kw):
    """A KITTI-like camera for a small (H, W) image: the same field of view, shrunk."""
    sx, sy = W / 1242.0, H / 375.0
    return _camera(fx=KITTI["fx"] * sx, fy=KITTI["fy"] * sy, cx=KITTI["cx"] * sx, cy=KITTI["cy"] * sy, **kw)


# --- independent references (NumPy float64) -------------------------------------------------------

def _grid(H, W):
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    return u, v


def paper_displacement(fx, fy, cx, cy, h, roll, x_d, z_d, yaw, H, W):
    """Paper eq. 13 written out: returns flow (2, H, W), valid (H, W), λ1, D."""
    u, v = _grid(H, W)
    st_, ct = math.sin(roll), math.cos(roll)
    lam1 = (u - cx) / fx * st_ + (v - cy) / fy * ct
    lam2 = (u - cx) / fx * ct - (v - cy) / fy * st_
    lam3 = lam2 * h - lam1 * x_d
    lam4 = h - lam1 * z_d
    sp, cp = math.sin(yaw), math.cos(yaw)
    D = lam3 * sp + lam4 * cp
    valid = (lam1 > 0) & (D > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (lam3 * cp - lam4 * sp) / D - lam2
        b = lam1 * h / D - lam1
    fu = fx * ct * a + fx * st_ * b
    fv = -fy * st_ * a + fy * ct * b
    flow = np.where(valid, np.stack([fu, fv]), 0.0)
    return flow, valid, lam1, D


def paper_velocity(fx, fy, cx, cy, h, roll, speed, steering, wheelbase, H, W):
    """Paper eq. 21 written out: returns flow (2, H, W) in px/s, valid (H, W), λ1."""
    u, v = _grid(H, W)
    st_, ct = math.sin(roll), math.cos(roll)
    lam1 = (u - cx) / fx * st_ + (v - cy) / fy * ct
    lam2 = (u - cx) / fx * ct - (v - cy) / fy * st_
    k = math.tan(steering) / wheelbase
    a = lam1 * lam2 - h * (1 + lam2 ** 2) * k
    b = lam1 ** 2 - lam1 * lam2 * h * k
    fu = speed / h * (fx * ct * a + fx * st_ * b)
    fv = speed / h * (-fy * st_ * a + fy * ct * b)
    valid = lam1 > 0
    return np.where(valid, np.stack([fu, fv]), 0.0), valid, lam1


def _rot_roll(t):
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]])


def _rot_pitch(b):
    c, s = math.cos(b), math.sin(b)
    return np.array([[1.0, 0, 0], [0, c, s], [0, -s, c]])


def _rot_yaw(p):
    c, s = math.cos(p), math.sin(p)
    return np.array([[c, 0, -s], [0, 1.0, 0], [s, 0, c]])


def homography_reference(K, h, roll, pitch, x_d, z_d, yaw, H, W):
    """H = K R_c R_φ (I - d nᵀ/h) R_cᵀ K⁻¹ applied to every pixel; validity from the ray and depth."""
    Rc = _rot_roll(roll) @ _rot_pitch(pitch)
    d = np.array([[x_d], [0.0], [z_d]])
    n = np.array([[0.0, 1.0, 0.0]])
    Hm = K @ Rc @ _rot_yaw(yaw) @ (np.eye(3) - d @ n / h) @ Rc.T @ np.linalg.inv(K)
    u, v = _grid(H, W)
    p = np.stack([u, v, np.ones_like(u)]).reshape(3, -1)
    q = Hm @ p
    ray_y = (Rc.T @ np.linalg.inv(K) @ p)[1]
    valid = (ray_y > 0) & (q[2] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        flow = q[:2] / q[2] - p[:2]
    flow = np.where(valid, flow, 0.0)
    return flow.reshape(2, H, W), valid.reshape(H, W), Hm


def raycast_reference(K, h, roll, pitch, x_d, z_d, yaw, H, W):
    """Direct 3D check: ray ∩ road y = h (vehicle frame), move with R_φ (p - d), project with K R_c."""
    Rc = _rot_roll(roll) @ _rot_pitch(pitch)
    u, v = _grid(H, W)
    p = np.stack([u, v, np.ones_like(u)]).reshape(3, -1)
    ray_v = Rc.T @ np.linalg.solve(K, p)            # vehicle-frame direction of each pixel's ray
    in_front = ray_v[1] > 0                          # the ray goes down: meets the road ahead
    # (a ray just below the horizon meets the road beyond float range: inf)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        t = np.where(in_front, h / np.where(in_front, ray_v[1], 1.0), np.nan)
        P = ray_v * t                                # road point, vehicle frame of time t (y = h)
        P1 = _rot_yaw(yaw) @ (P - np.array([[x_d], [0.0], [z_d]]))
        Pc1 = Rc @ P1                                # camera frame of time t+1
    valid = in_front & (Pc1[2] > 0)
    # (a road point beyond float range, just below the horizon, overflows its projection too)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        img = K @ Pc1
        flow = img[:2] / img[2] - p[:2]
    flow = np.where(valid, flow, 0.0)
    return flow.reshape(2, H, W), valid.reshape(H, W), ray_v[1].reshape(H, W), Pc1[2].reshape(H, W)


def _model(K, h, roll, pitch, x_d, z_d, yaw, H, W):
    cam = Camera(torch.as_tensor(K), h, roll, pitch)
    flow, valid = displacement_flow(cam, x_d, z_d, yaw, (H, W))
    return flow[0].numpy(), valid[0, 0].numpy()


def _assert_flow_close(got, want, valid, atol=1e-6, rtol=1e-9):
    """≤ atol px on valid pixels (plus rtol·|flow| for huge flows next to the D = 0 line)."""
    err = np.abs(got - want)[:, valid]
    bound = atol + rtol * np.abs(want)[:, valid]
    assert (err <= bound).all(), f"max error {err.max():.3g} px"


# --- smoke -----------------------------------------------------------------------------------------

def test_smoke_displacement(dtype):
    cam = _camera(dtype=dtype, roll=0.01, pitch=-0.01)
    flow, valid = displacement_flow(cam, 0.05, 1.2, 0.01, (375, 1242))
    assert flow.shape == (1, 2, 375, 1242) and flow.dtype == dtype
    assert valid.shape == (1, 1, 375, 1242) and valid.dtype == torch.bool
    assert torch.isfinite(flow).all()
    assert valid[0, 0, -1].all() and not valid[0, 0, 0].any()  # bottom row road, top row sky
    # forward motion: road flows down and away from the centre below the horizon
    assert flow[0, 1, -1, 600] > 0 and flow[0, 0, -1, 0] < 0 and flow[0, 0, -1, -1] > 0


def test_smoke_velocity(dtype):
    cam = _camera(dtype=dtype)
    flow, valid = velocity_flow(cam, 12.0, 0.02, 2.7, (375, 1242))
    assert flow.shape == (1, 2, 375, 1242) and flow.dtype == dtype and valid.dtype == torch.bool
    assert torch.isfinite(flow).all()
    assert valid[0, 0, -1].all() and not valid[0, 0, 0].any()


def test_docstring_example():
    cam = Camera(torch.tensor([[700.0, 0, 600], [0, 700, 180], [0, 0, 1]]), 1.65)
    flow, valid = displacement_flow(cam, 0.0, 1.2, 0.0, (370, 1226))
    assert flow.shape == (1, 2, 370, 1226) and bool(valid[0, 0, -1, 600])


def test_module_twins():
    cam = _kitti_scaled(12, 20, roll=0.02)
    torch.testing.assert_close(DisplacementFlow((12, 20))(cam, 0.1, 1.0, 0.02),
                               displacement_flow(cam, 0.1, 1.0, 0.02, (12, 20)), rtol=0, atol=0)
    torch.testing.assert_close(VelocityFlow((12, 20), wheelbase=2.5)(cam, 8.0, 0.05),
                               velocity_flow(cam, 8.0, 0.05, 2.5, (12, 20)), rtol=0, atol=0)
    assert "size=(12, 20)" in repr(DisplacementFlow((12, 20)))
    assert "wheelbase=2.5" in repr(VelocityFlow((12, 20), wheelbase=2.5))


def test_pixel_grid_checks_its_arguments():
    with pytest.raises(ValueError, match=r"^size: expected positive sides \(H, W\), got \(-2, 3\)"):
        pixel_grid((-2, 3), torch.float32)
    with pytest.raises(TypeError, match=r"^size: expected integer sides \(H, W\), got \(2.5, 3\)"):
        pixel_grid((2.5, 3), torch.float32)
    with pytest.raises(TypeError, match=r"^dtype: expected a floating-point torch.dtype, got torch.int64"):
        pixel_grid((2, 3), torch.int64)


def test_pixel_grid():
    g = pixel_grid((2, 3), torch.float32)
    assert g.shape == (3, 6)
    assert g[0].tolist() == [0, 1, 2, 0, 1, 2] and g[1].tolist() == [0, 0, 0, 1, 1, 1] and (g[2] == 1).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_pixel_grid_in_half_precision_is_float32_with_every_coordinate_exact(dtype):
    # (bfloat16 rounded columns 1237..1241 of a KITTI frame all to 1240, float16 4097 to 4096)
    H, W = 375, 4100
    g = pixel_grid((H, W), dtype)
    assert g.dtype == torch.float32
    u, v = torch.meshgrid(torch.arange(W, dtype=torch.float64), torch.arange(H, dtype=torch.float64), indexing="xy")
    assert torch.equal(g[0].double(), u.reshape(-1)) and torch.equal(g[1].double(), v.reshape(-1))


def test_does_not_modify_inputs():
    cam = _kitti_scaled(10, 16, roll=0.01)
    K0, h0 = cam.K.clone(), cam.height.clone()
    x = torch.tensor([0.1]); x0 = x.clone()
    displacement_flow(cam, x, 1.0, 0.0, (10, 16))
    velocity_flow(cam, x, 0.0, 2.7, (10, 16))
    assert torch.equal(cam.K, K0) and torch.equal(cam.height, h0) and torch.equal(x, x0)


def test_dtype_follows_inputs():
    cam = _kitti_scaled(8, 12, dtype=torch.float32)
    flow, _ = displacement_flow(cam, torch.tensor([0.0], dtype=torch.float64), 1.0, 0.0, (8, 12))
    assert flow.dtype == torch.float64
    flow, _ = displacement_flow(cam.to(torch.float16), 0.0, 1.0, 0.0, (8, 12))
    assert flow.dtype == torch.float32  # half precision is lifted for the geometry


# --- exceptions ------------------------------------------------------------------------------------

def test_exception_batch_mismatch():
    cam = _kitti_scaled(6, 9).expand(2)
    with pytest.raises(ValueError, match="mismatched batch sizes.*camera=2.*x_d=3"):
        displacement_flow(cam, torch.zeros(3), 1.0, 0.0, (6, 9))
    with pytest.raises(ValueError, match="mismatched batch sizes"):
        velocity_flow(_kitti_scaled(6, 9), torch.ones(2), torch.zeros(3), 2.7, (6, 9))


def test_exception_shapes():
    cam = _kitti_scaled(6, 9)
    with pytest.raises(ValueError, match=r"z_d: expected a scalar or shape \(B,\), got \(2, 2\)"):
        displacement_flow(cam, 0.0, torch.ones(2, 2), 0.0, (6, 9))
    with pytest.raises(ValueError, match=r"K: expected shape \(3, 3\) or \(B, 3, 3\), got \(3, 4\)"):
        Camera(torch.eye(3, 4), 1.65)


def test_exception_values():
    cam = _kitti_scaled(6, 9)
    with pytest.raises(ValueError, match="height: expected values > 0"):
        _kitti_scaled(6, 9, height=0.0)
    with pytest.raises(ValueError, match="height: expected values > 0"):
        _kitti_scaled(6, 9, height=-1.0)
    with pytest.raises(ValueError, match="K: expected focal lengths f_x, f_y > 0"):
        Camera(_K(-700.0, 700.0, 5, 3), 1.65)
    with pytest.raises(ValueError, match="K: expected focal lengths f_x, f_y > 0"):
        Camera(_K(700.0, 0.0, 5, 3), 1.65)
    with pytest.raises(ValueError, match="x_d: expected finite values"):
        displacement_flow(cam, float("nan"), 1.0, 0.0, (6, 9))
    with pytest.raises(ValueError, match="yaw: expected finite values"):
        displacement_flow(cam, 0.0, 1.0, torch.tensor([float("inf")]), (6, 9))
    with pytest.raises(ValueError, match="speed: expected finite values"):
        velocity_flow(cam, float("nan"), 0.0, 2.7, (6, 9))
    with pytest.raises(ValueError, match="roll: expected finite values"):
        _kitti_scaled(6, 9, roll=float("nan"))
    with pytest.raises(ValueError, match="K: expected finite values"):
        Camera(_K(700.0, 700.0, float("nan"), 3), 1.65)
    with pytest.raises(ValueError, match="wheelbase: expected values > 0"):
        velocity_flow(cam, 10.0, 0.0, 0.0, (6, 9))
    with pytest.raises(ValueError, match="steering: expected"):
        velocity_flow(cam, 10.0, 2.0, 2.7, (6, 9))
    with pytest.raises(ValueError, match="wheelbase: expected a positive number"):
        VelocityFlow((6, 9), wheelbase=-1.0)


def test_exception_types():
    cam = _kitti_scaled(6, 9)
    with pytest.raises(TypeError, match="x_d: expected a float tensor or a Python number, got dtype torch.int64"):
        displacement_flow(cam, torch.tensor([1]), 1.0, 0.0, (6, 9))
    with pytest.raises(TypeError, match="steering: expected a float tensor"):
        velocity_flow(cam, 1.0, torch.tensor([0], dtype=torch.int32), 2.7, (6, 9))
    with pytest.raises(TypeError, match="K: expected a floating-point tensor, got dtype torch.int64"):
        Camera(torch.eye(3, dtype=torch.int64), 1.65)
    with pytest.raises(TypeError, match="height: expected a float tensor"):
        Camera(torch.eye(3), torch.tensor([2]))
    with pytest.raises(TypeError, match="camera: expected a fsof_torch.Camera"):
        displacement_flow(torch.eye(3), 0.0, 1.0, 0.0, (6, 9))
    with pytest.raises(TypeError, match="z_d: expected a float"):
        displacement_flow(cam, 0.0, "1.0", 0.0, (6, 9))


@pytest.mark.parametrize("size, err", [((0, 9), ValueError), ((6, -1), ValueError), ((6,), TypeError),
                                       ((6.0, 9), TypeError), ("6x9", TypeError)])
def test_exception_size(size, err):
    cam = _kitti_scaled(6, 9)
    with pytest.raises(err, match="size: expected"):
        displacement_flow(cam, 0.0, 1.0, 0.0, size)
    with pytest.raises(err, match="size: expected"):
        velocity_flow(cam, 1.0, 0.0, 2.7, size)
    with pytest.raises(err, match="size: expected"):
        DisplacementFlow(size)


# --- cardinality -----------------------------------------------------------------------------------

@pytest.mark.parametrize("B", [1, 3])
def test_cardinality_per_item_parameters(B):
    H, W = 10, 17
    g = torch.Generator().manual_seed(B)
    rolls = (torch.rand(B, generator=g, dtype=torch.float64) - 0.5) * 0.1
    cam = Camera(_kitti_scaled(H, W).K.expand(B, 3, 3), 1.5 + torch.rand(B, generator=g, dtype=torch.float64),
                 rolls, -0.01)
    x_d = (torch.rand(B, generator=g, dtype=torch.float64) - 0.5) * 0.4
    z_d = torch.rand(B, generator=g, dtype=torch.float64) * 2
    yaw = (torch.rand(B, generator=g, dtype=torch.float64) - 0.5) * 0.1
    flow, valid = displacement_flow(cam, x_d, z_d, yaw, (H, W))
    vel, vvalid = velocity_flow(cam, z_d * 10, yaw, 2.7, (H, W))
    assert flow.shape == (B, 2, H, W) and valid.shape == (B, 1, H, W)
    assert vel.shape == (B, 2, H, W) and vvalid.shape == (B, 1, H, W)
    for b in range(B):  # each item equals the same call made alone
        cam_b = Camera(cam.K[b], cam.height[b:b + 1], cam.roll[b:b + 1], cam.pitch[b:b + 1])
        f_b, v_b = displacement_flow(cam_b, x_d[b:b + 1], z_d[b:b + 1], yaw[b:b + 1], (H, W))
        torch.testing.assert_close(flow[b:b + 1], f_b, rtol=1e-12, atol=1e-12)
        assert torch.equal(valid[b:b + 1], v_b)
        g_b, w_b = velocity_flow(cam_b, z_d[b:b + 1] * 10, yaw[b:b + 1], 2.7, (H, W))
        torch.testing.assert_close(vel[b:b + 1], g_b, rtol=1e-12, atol=1e-12)
        assert torch.equal(vvalid[b:b + 1], w_b)


def test_cardinality_broadcast_batch_one():
    cam = _kitti_scaled(7, 11)  # batch 1, parameters of batch 3
    flow, valid = displacement_flow(cam, torch.zeros(3, dtype=torch.float64), torch.tensor([0.5, 1.0, 1.5],
                                    dtype=torch.float64), 0.0, (7, 11))
    assert flow.shape == (3, 2, 7, 11)
    assert not torch.equal(flow[0], flow[2])
    # camera of batch 3, scalar parameters
    flow, valid = velocity_flow(cam.expand(3), 5.0, 0.0, 2.7, (7, 11))
    assert flow.shape == (3, 2, 7, 11) and torch.equal(flow[0], flow[2])


# --- feature: against the independent references ---------------------------------------------------

def test_feature_matches_paper_lambda_formula_kitti():
    H, W = 375, 1242
    for roll, x_d, z_d, yaw in [(0.0, 0.0, 1.2, 0.0), (0.02, 0.1, 1.0, 0.03), (-0.05, -0.3, 2.5, -0.06)]:
        want, want_valid, lam1, D = paper_displacement(*KITTI.values(), 1.65, roll, x_d, z_d, yaw, H, W)
        got, got_valid = _model(_K(*KITTI.values()), 1.65, roll, 0.0, x_d, z_d, yaw, H, W)
        clear = (np.abs(lam1) > 1e-9) & (np.abs(D) > 1e-9)  # away from the boundary lines
        assert (got_valid == want_valid)[clear].all()
        _assert_flow_close(got, want, want_valid & got_valid)
        assert (got[:, ~got_valid] == 0).all()


def test_feature_float32_close_to_paper():
    H, W = 375, 1242
    want, want_valid, _, _ = paper_displacement(*KITTI.values(), 1.65, 0.02, 0.1, 1.2, 0.02, H, W)
    cam = _camera(roll=0.02, dtype=torch.float32)
    got, valid = displacement_flow(cam, 0.1, 1.2, 0.02, (H, W))
    err = np.abs(got[0].double().numpy() - want)[:, want_valid & valid[0, 0].numpy()]
    assert err.max() < 2e-3  # float32 rounding of u ≈ 1000 px


def test_feature_velocity_matches_paper_formula():
    H, W = 375, 1242
    for roll, speed, steering in [(0.0, 10.0, 0.0), (0.03, 15.0, 0.1), (-0.02, 5.0, -0.3)]:
        want, want_valid, lam1 = paper_velocity(*KITTI.values(), 1.65, roll, speed, steering, 2.7, H, W)
        cam = _camera(roll=roll)
        got, got_valid = velocity_flow(cam, speed, steering, 2.7, (H, W))
        got, got_valid = got[0].numpy(), got_valid[0, 0].numpy()
        clear = np.abs(lam1) > 1e-9
        assert (got_valid == want_valid)[clear].all()
        _assert_flow_close(got, want, want_valid & got_valid, atol=1e-6, rtol=1e-12)
        assert (got[:, ~got_valid] == 0).all()


def test_feature_matches_homography_and_raycast_with_pitch():
    H, W = 120, 200
    K = _K(300.0, 320.0, 97.0, 40.0).numpy()
    args = (1.4, 0.07, -0.04, 0.3, 2.0, -0.05, H, W)
    got, got_valid = _model(K, *args)
    hom, hom_valid, Hm = homography_reference(K, *args)
    ray, ray_valid, ray_y, depth1 = raycast_reference(K, *args)
    clear = (np.abs(ray_y) > 1e-9) & (np.abs(depth1) > 1e-9)
    assert (got_valid == hom_valid)[clear].all() and (got_valid == ray_valid)[clear].all()
    assert got_valid.any() and (~got_valid).any()
    _assert_flow_close(got, hom, got_valid & hom_valid)
    _assert_flow_close(got, ray, got_valid & ray_valid)
    cam = Camera(torch.as_tensor(K), 1.4, 0.07, -0.04)
    Hm_model = road_homography(cam, {"x_d": 0.3, "z_d": 2.0, "yaw": -0.05})[0].numpy()
    np.testing.assert_allclose(Hm_model / Hm_model[2, 2], Hm / Hm[2, 2], rtol=1e-12, atol=1e-12)


def test_feature_pitch_zero_is_paper_and_pitch_moves_horizon():
    H, W = 60, 90
    K = _K(200.0, 200.0, 45.0, 20.0)
    flow0, _ = displacement_flow(Camera(K, 1.5, 0.03, 0.0), 0.1, 1.0, 0.01, (H, W))
    want, want_valid, _, _ = paper_displacement(200.0, 200.0, 45.0, 20.0, 1.5, 0.03, 0.1, 1.0, 0.01, H, W)
    _assert_flow_close(flow0[0].numpy(), want, want_valid)
    up = Camera(K, 1.5, 0.0, 0.05)  # β > 0: the camera looks up, the horizon moves below v_0
    assert float(up.horizon_row()) > 20.0
    assert float(Camera(K, 1.5, 0.0, -0.05).horizon_row()) < 20.0


def _geometry():
    return st.fixed_dictionaries(dict(
        roll=st.floats(-math.radians(10), math.radians(10)),
        pitch=st.floats(-math.radians(3), math.radians(3)),
        yaw=st.floats(-math.radians(5), math.radians(5)),
        x_d=st.floats(-0.5, 0.5),
        z_d=st.floats(0.0, 3.0),
        h=st.floats(1.0, 2.5),
        fx=st.floats(300.0, 1500.0),
        fy=st.floats(300.0, 1500.0),
        H=st.integers(8, 48),
        W=st.integers(8, 64),
        cx_frac=st.floats(0.0, 1.0),
        cy_frac=st.floats(0.0, 1.0),
    )).filter(lambda g: g["H"] != g["W"])


@settings(max_examples=40, deadline=None)
@given(_geometry())
def test_feature_hypothesis_random_geometry(g):
    H, W = g["H"], g["W"]
    cx, cy = g["cx_frac"] * (W - 1), g["cy_frac"] * (H - 1)
    # A small image with a real focal length sees a narrow cone: spread the pixel grid over the
    # scene by scaling the focal lengths with the image (about a 1242×375 field of view).
    fx, fy = g["fx"] * W / 1242.0, g["fy"] * H / 375.0
    K = _K(fx, fy, cx, cy).numpy()
    args = (g["h"], g["roll"], g["pitch"], g["x_d"], g["z_d"], g["yaw"], H, W)
    got, got_valid = _model(K, *args)
    ray, ray_valid, ray_y, depth1 = raycast_reference(K, *args)
    hom, hom_valid, _ = homography_reference(K, *args)
    clear = (np.abs(ray_y) > 1e-9) & (np.abs(depth1) > 1e-9)
    assert (got_valid == ray_valid)[clear].all()
    assert (got_valid == hom_valid)[clear].all()
    assert (got[:, ~got_valid] == 0).all() and np.isfinite(got).all()
    _assert_flow_close(got, ray, got_valid & ray_valid)
    _assert_flow_close(got, hom, got_valid & hom_valid)
    # β = 0: the paper's λ formula
    args0 = (g["h"], g["roll"], 0.0, g["x_d"], g["z_d"], g["yaw"], H, W)
    got0, valid0 = _model(K, *args0)
    want, want_valid, lam1, D = paper_displacement(fx, fy, cx, cy, g["h"], g["roll"], g["x_d"], g["z_d"],
                                                   g["yaw"], H, W)
    clear0 = (np.abs(lam1) > 1e-9) & (np.abs(D) > 1e-9)
    assert (valid0 == want_valid)[clear0].all()
    _assert_flow_close(got0, want, valid0 & want_valid)


def test_feature_velocity_is_limit_of_displacement():
    """f_v = lim f_d / Δt with the Ackermann-integrated ego-motion (central difference, O(Δt²))."""
    H, W = 40, 64
    cam = Camera(_K(250.0, 260.0, 30.0, 12.0), 1.6, 0.04, -0.02)
    speed, steering, wheelbase, dt = 12.0, 0.15, 2.7, 1e-4
    fv, valid = velocity_flow(cam, speed, steering, wheelbase, (H, W))
    e_plus = ego_motion_from_ackermann(speed, steering, wheelbase, dt)
    e_minus = ego_motion_from_ackermann(speed, steering, wheelbase, -dt)
    fd_plus, v_plus = displacement_flow(cam, e_plus.x_d.double(), e_plus.z_d.double(), e_plus.yaw.double(), (H, W))
    fd_minus, v_minus = displacement_flow(cam, e_minus.x_d.double(), e_minus.z_d.double(),
                                          e_minus.yaw.double(), (H, W))
    m = valid & v_plus & v_minus
    assert m.float().mean() > 0.3
    fd = (fd_plus - fd_minus) / (2 * dt)
    mm = m.expand_as(fv)
    rel = (fd[mm] - fv[mm]).abs().max() / fv[mm].abs().max()
    assert rel <= 1e-4
    # and the one-sided quotient f_d(Δt)/Δt converges too (O(Δt))
    rel1 = (fd_plus[mm] / dt - fv[mm]).abs().max() / fv[mm].abs().max()
    assert rel1 <= 1e-3


def test_feature_velocity_matrix_is_derivative_of_homography():
    cam = Camera(_K(250.0, 260.0, 30.0, 12.0), 1.6, 0.04, -0.02)
    speed, steering, l, dt = 9.0, -0.2, 2.9, 1e-6
    G = road_velocity_matrix(cam, speed, steering, l)
    yaw_rate = speed * math.tan(steering) / l
    Hp = road_homography(cam, {"x_d": 0.0, "z_d": speed * dt, "yaw": yaw_rate * dt})
    Hm = road_homography(cam, {"x_d": 0.0, "z_d": -speed * dt, "yaw": -yaw_rate * dt})
    torch.testing.assert_close((Hp - Hm) / (2 * dt), G, rtol=1e-6, atol=1e-6)


# --- feature: the special cases of eq. 22-24 ---------------------------------------------------------

def _assert_masks_agree(a, b, cam):
    """Equal valid masks, except on pixels lying on the horizon line itself (|λ1| < 1e-9), where
    the two forms may round to different signs."""
    H, W = a.shape[-2:]
    K = cam.K[0]
    _, _, lam1, _ = paper_displacement(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), 1.0,
                                       float(cam.roll[0]), 0.0, 0.0, 0.0, H, W)
    differ = (a != b)[0, 0].numpy()
    assert (np.abs(lam1[differ]) < 1e-9).all()
    assert differ.sum() <= W

def test_feature_special_case_straight_eq22():
    H, W = 50, 80
    cam = Camera(_K(200.0, 210.0, 41.0, 18.0), 1.7, 0.05, 0.0)  # roll, no pitch
    general, gv = displacement_flow(cam, 0.0, 1.3, 0.0, (H, W))
    special, sv = displacement_flow_straight(cam, 1.3, (H, W))
    _assert_masks_agree(gv, sv, cam)
    torch.testing.assert_close(special, general, rtol=1e-10, atol=1e-9)


def test_feature_special_case_velocity_straight_eq23():
    H, W = 50, 80
    cam = Camera(_K(200.0, 210.0, 41.0, 18.0), 1.7, -0.04, 0.0)
    general, gv = velocity_flow(cam, 11.0, 0.0, 2.7, (H, W))
    special, sv = velocity_flow_straight(cam, 11.0, (H, W))
    _assert_masks_agree(gv, sv, cam)
    torch.testing.assert_close(special, general, rtol=1e-10, atol=1e-9)


def test_feature_special_case_level_eq24():
    H, W = 50, 80
    cam = Camera(_K(200.0, 210.0, 41.0, 18.0), 1.7)  # no roll, no pitch
    general, gv = displacement_flow(cam, 0.0, 2.2, 0.0, (H, W))
    special, sv = displacement_flow_straight_level(cam, 2.2, (H, W))
    _assert_masks_agree(gv, sv, cam)
    torch.testing.assert_close(special, general, rtol=1e-10, atol=1e-9)
    vgeneral, vgv = velocity_flow(cam, 7.0, 0.0, 2.7, (H, W))
    vspecial, vsv = velocity_flow_straight_level(cam, 7.0, (H, W))
    _assert_masks_agree(vgv, vsv, cam)
    torch.testing.assert_close(vspecial, vgeneral, rtol=1e-10, atol=1e-9)
    # the vertical component depends on v alone and follows the V-flow curve
    v = torch.arange(H, dtype=torch.float64)
    curve = vflow_curve(v, 2.2, 1.7, 210.0, 18.0)
    rows = general[0, 1]
    torch.testing.assert_close(rows, curve.unsqueeze(1).expand(H, W), rtol=1e-10, atol=1e-9)


def test_vflow_curve_zero_outside_and_finite_gradient():
    # (rows to 800: the road points a step of 3 m takes behind the camera lie below row 569.7)
    v = torch.arange(0.0, 800.0, dtype=torch.float64)
    z_d = torch.tensor(3.0, dtype=torch.float64, requires_grad=True)
    out = vflow_curve(v, z_d, 1.65, 721.5, 172.9)
    above, behind = v <= 172.9, v - 172.9 >= 1.65 * 721.5 / 3.0  # road point behind the camera at t+1
    assert above.any() and behind.any()
    assert (out[above] == 0).all() and (out[behind] == 0).all()
    assert (out[~above & ~behind] > 0).all()
    out.sum().backward()
    assert torch.isfinite(z_d.grad)


# --- feature: the valid set -------------------------------------------------------------------------

def test_feature_valid_above_horizon_and_behind_camera():
    H, W = 60, 80
    cam = Camera(_K(60.0, 60.0, 40.0, 20.0), 1.5, 0.1, 0.0)
    # a 3 m step with a wide-angle camera: near road points pass behind the camera
    flow, valid = displacement_flow(cam, 0.0, 3.0, 0.0, (H, W))
    _, _, lam1, D = paper_displacement(60.0, 60.0, 40.0, 20.0, 1.5, 0.1, 0.0, 3.0, 0.0, H, W)
    valid = valid[0, 0].numpy()
    assert not valid[lam1 <= 0].any()                       # above the horizon
    assert ((lam1 > 0) & (D <= 0)).sum() > 50                # some road points behind the camera ...
    assert not valid[(lam1 > 0) & (D <= 0)].any()          # ... are not valid
    assert valid[(lam1 > 1e-9) & (D > 1e-9)].all()
    assert (flow[0][:, torch.from_numpy(~valid)] == 0).all()  # exactly 0, not NaN or inf
    assert torch.isfinite(flow).all()


def test_feature_valid_on_horizon_row():
    cam = Camera(_K(100.0, 100.0, 10.0, 5.0), 1.5)
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, (11, 21))
    assert not valid[0, 0, :6].any() and valid[0, 0, 6:].all()  # v = v_0 = 5 is the horizon itself
    vflow, vvalid = velocity_flow(cam, 1.0, 0.0, 2.7, (11, 21))
    assert torch.equal(valid, vvalid)


# --- gradcheck ---------------------------------------------------------------------------------------

def _params(cy):
    t = lambda x: torch.tensor([x], dtype=torch.float64, requires_grad=True)  # noqa: E731
    return dict(fx=t(12.0), fy=t(11.0), skew=t(0.3), cx=t(4.2), cy=t(cy), h=t(1.6), roll=t(0.05),
                pitch=t(-0.03), x_d=t(0.2), z_d=t(0.8), yaw=t(0.04), speed=t(7.0), steering=t(0.1))


def _camera_from(p):
    z, o = torch.zeros_like(p["fx"]), torch.ones_like(p["fx"])
    K = torch.stack([p["fx"], p["skew"], p["cx"], z, p["fy"], p["cy"], z, z, o], -1).reshape(1, 3, 3)
    return Camera(K, p["h"], p["roll"], p["pitch"])


@pytest.mark.parametrize("cy", [1.3, 4.6], ids=["mostly-road", "mostly-sky"])
def test_gradcheck_displacement(cy):
    p = _params(cy)
    names = ["fx", "fy", "skew", "cx", "cy", "h", "roll", "pitch", "x_d", "z_d", "yaw"]

    def f(*xs):
        q = dict(zip(names, xs))
        flow, _ = displacement_flow(_camera_from(q), q["x_d"], q["z_d"], q["yaw"], (6, 9))
        return flow

    with torch.no_grad():
        _, valid = displacement_flow(_camera_from(p), p["x_d"], p["z_d"], p["yaw"], (6, 9))
    assert (valid.float().mean() < 0.5) == (cy > 4) and valid.any()  # most pixels sky when cy > 4
    torch.autograd.gradcheck(f, [p[n] for n in names], eps=1e-6, atol=1e-6)
    flow = f(*[p[n] for n in names])
    flow.square().sum().backward()
    for n in names:
        assert torch.isfinite(p[n].grad).all(), n


@pytest.mark.parametrize("cy", [1.3, 4.6], ids=["mostly-road", "mostly-sky"])
def test_gradcheck_velocity(cy):
    p = _params(cy)
    names = ["fx", "fy", "skew", "cx", "cy", "h", "roll", "pitch", "speed", "steering"]

    def f(*xs):
        q = dict(zip(names, xs))
        flow, _ = velocity_flow(_camera_from(q), q["speed"], q["steering"], 2.7, (6, 9))
        return flow

    torch.autograd.gradcheck(f, [p[n] for n in names], eps=1e-6, atol=1e-6)
    flow = f(*[p[n] for n in names])
    flow.square().sum().backward()
    for n in names:
        assert torch.isfinite(p[n].grad).all(), n


def test_gradient_finite_when_mostly_above_horizon_and_behind_camera():
    """Most pixels invalid (sky, or behind the camera at t+1): no NaN in value or gradient."""
    p = _params(5.5)
    p["z_d"] = torch.tensor([40.0], dtype=torch.float64, requires_grad=True)  # passes most road points
    flow, valid = displacement_flow(_camera_from(p), p["x_d"], p["z_d"], p["yaw"], (6, 9))
    assert valid.float().mean() < 0.5
    assert torch.isfinite(flow).all() and (flow[valid.expand_as(flow).logical_not()] == 0).all()
    flow.sum().backward()
    for n in ["fx", "fy", "cx", "cy", "h", "roll", "pitch", "x_d", "z_d", "yaw"]:
        assert torch.isfinite(p[n].grad).all(), n


def test_gradient_through_module_and_batch():
    cam = Camera(_kitti_scaled(6, 9).K.expand(2, 3, 3), 1.65, torch.tensor([0.0, 0.02], dtype=torch.float64))
    z_d = torch.tensor([0.5, 1.0], dtype=torch.float64, requires_grad=True)
    flow, _ = DisplacementFlow((6, 9))(cam, 0.0, z_d, 0.0)
    flow.sum().backward()
    assert torch.isfinite(z_d.grad).all() and (z_d.grad != 0).all()


# --- torch.compile and torch.export ---------------------------------------------------------------------

def test_compile_fullgraph_modules():
    """Inductor's code for the paper's two modules gives their eager flow; the gradient through
    the compiled graph (AOTAutograd, ``aot_eager``: inductor's backward kernels would add tens of
    seconds of a C++ compiler on a cold cache) gives the eager one."""
    H, W = 6, 9
    cam = _kitti_scaled(H, W, roll=0.02, pitch=-0.01, dtype=torch.float32)
    args = (torch.tensor([0.1]), torch.tensor([1.0]), torch.tensor([0.02]))
    disp = DisplacementFlow((H, W))
    compiled = torch.compile(disp, fullgraph=True, backend="inductor")
    got, got_valid = compiled(cam, *args)
    want, want_valid = disp(cam, *args)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    assert got_valid.dtype == torch.bool and torch.equal(got_valid, want_valid)
    assert got_valid.any() and (~got_valid).any() and (got[~got_valid.expand_as(got)] == 0).all()
    z_d = torch.tensor([1.0], requires_grad=True)
    torch.compile(disp, fullgraph=True, backend="aot_eager")(cam, args[0], z_d, args[2])[0].sum().backward()
    z_ref = z_d.detach().clone().requires_grad_()
    disp(cam, args[0], z_ref, args[2])[0].sum().backward()
    torch.testing.assert_close(z_d.grad, z_ref.grad, rtol=1e-4, atol=1e-4)
    vel = VelocityFlow((H, W))
    got, got_valid = torch.compile(vel, fullgraph=True, backend="inductor")(cam, torch.tensor([9.0]),
                                                                           torch.tensor([0.05]))
    want, want_valid = vel(cam, torch.tensor([9.0]), torch.tensor([0.05]))
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-4)
    assert torch.equal(got_valid, want_valid)


def test_export_modules():
    H, W = 6, 9
    cam = _kitti_scaled(H, W, roll=0.02, pitch=-0.01, dtype=torch.float32)
    args = (cam, torch.tensor([0.1]), torch.tensor([1.0]), torch.tensor([0.02]))
    ep = torch.export.export(DisplacementFlow((H, W)), args)
    cam2 = cam.replace(roll=0.04)
    other = (cam2, torch.tensor([-0.1]), torch.tensor([1.5]), torch.tensor([0.0]))
    for a in (args, other):
        got, got_valid = ep.module()(*a)
        want, want_valid = displacement_flow(*a, (H, W))
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-5)
        assert torch.equal(got_valid, want_valid)
    ep = torch.export.export(VelocityFlow((H, W)), (cam, torch.tensor([9.0]), torch.tensor([0.05])))
    got, got_valid = ep.module()(cam2, torch.tensor([5.0]), torch.tensor([-0.05]))
    want, want_valid = velocity_flow(cam2, torch.tensor([5.0]), torch.tensor([-0.05]), 2.7, (H, W))
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-4)
    assert torch.equal(got_valid, want_valid)


def test_graphs_give_a_refused_motion_no_flow_and_no_validity():
    """docs/conventions.md: a graph checks no values, and a motion the eager call refuses gives a
    graph's flow of 0 with ``valid`` all False. The velocity model's validity depends on the
    horizon alone: exported or compiled, a NaN or inf speed gave a NaN flow marked valid on every
    road pixel (and the paper model's z_d = -1e38, an overflow the eager call names, NaN flow
    marked valid). Each frame of a batch is judged alone."""
    H, W = 6, 9
    cam = _kitti_scaled(H, W, roll=0.02, pitch=-0.01, dtype=torch.float32)
    vel = VelocityFlow((H, W))
    ep = torch.export.export(vel, (cam, torch.tensor([9.0, 5.0]), torch.tensor([0.05, 0.0])))
    compiled = torch.compile(DisplacementFlow((H, W)), fullgraph=True, backend="aot_eager")
    for bad in (math.nan, math.inf, -1e38):
        got, got_valid = ep.module()(cam, torch.tensor([bad, 9.0]), torch.tensor([0.05, 0.05]))
        want, want_valid = velocity_flow(cam, 9.0, 0.05, 2.7, (H, W))
        assert not got_valid[0].any() and torch.equal(got[0], torch.zeros(2, H, W))
        torch.testing.assert_close(got[1:], want, rtol=1e-6, atol=1e-4)
        assert torch.equal(got_valid[1:], want_valid) and want_valid.any()
        got, got_valid = compiled(cam, torch.zeros(2), torch.tensor([1.0, bad]), torch.tensor([0.01, 0.01]))
        want, want_valid = displacement_flow(cam, 0.0, 1.0, 0.01, (H, W))
        assert not got_valid[1].any() and torch.equal(got[1], torch.zeros(2, H, W))
        torch.testing.assert_close(got[:1], want, rtol=1e-5, atol=1e-5)
        assert torch.equal(got_valid[:1], want_valid)
    with pytest.raises(ValueError, match="overflows"):
        displacement_flow(cam, 0.0, -1e38, 0.0, (H, W))


@pytest.mark.parametrize("velocity", [False, True])
def test_autograd_and_inference_paths_agree(velocity):
    """Without autograd the evaluation works in place; with it, functionally: same numbers."""
    H, W = 40, 60
    cam = Camera(_K(30.0, 32.0, 28.0, 9.0), 1.6, 0.05, -0.02)
    p = torch.tensor([0.1, 2.5, 0.05], dtype=torch.float64)
    fn = (lambda c, a, b, d: velocity_flow(c, a * 20, d, 2.7, (H, W))) if velocity else \
        (lambda c, a, b, d: displacement_flow(c, a, b, d, (H, W)))
    plain, plain_valid = fn(cam, *p)
    q = p.clone().requires_grad_()
    graded, graded_valid = fn(cam, *q)
    assert graded.requires_grad and not plain.requires_grad
    assert torch.equal(plain_valid, graded_valid) and (~plain_valid).any() and plain_valid.any()
    torch.testing.assert_close(plain, graded.detach(), rtol=1e-14, atol=1e-12)
    with torch.no_grad():
        nograd, _ = fn(cam, *q)
    torch.testing.assert_close(plain, nograd, rtol=0, atol=0)


@settings(max_examples=40, deadline=None)
@given(a=st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6),
       m=st.lists(st.floats(-0.05, 0.05), min_size=18, max_size=18), velocity=st.booleans())
def test_inference_path_rows_match_the_general_path(a, m, velocity):
    """Without autograd on the CPU only a band of rows is computed (the rest zeroed): the same
    flow and validity as the general path for horizons of any tilt and side (valid rows at the
    bottom, at the top, none, all) and maps whose q_z changes sign in the image."""
    H, W = 23, 31
    horizon = torch.tensor(a, dtype=torch.float64).reshape(2, 1, 3) * torch.tensor([0.1, 0.1, 2.0], dtype=torch.float64)
    M = torch.eye(3, dtype=torch.float64) + torch.tensor(m, dtype=torch.float64).reshape(2, 3, 3)
    M[:, 2, :2] *= 0.2  # q_z = 1 + small terms, crossing 0 inside the image for some maps
    plain, plain_valid = flow_from_map(M, horizon, (H, W), velocity=velocity)
    graded, graded_valid = flow_from_map(M.clone().requires_grad_(), horizon, (H, W), velocity=velocity)
    assert torch.equal(plain_valid, graded_valid)
    torch.testing.assert_close(plain, graded.detach(), rtol=1e-12, atol=1e-12)
    assert not plain[~plain_valid.expand_as(plain)].any()


def test_inference_path_band_edge_cases():
    """The band of computed rows: none valid (a horizon below the image), all valid, and the
    valid side at the top (the road row's sign flipped) each match the general path."""
    H, W = 12, 17
    M = torch.eye(3, dtype=torch.float64).expand(3, 3, 3).clone()
    M[:, 0, 2], M[:, 1, 1] = 0.3, 1.02
    horizon = torch.tensor([[[0.0, 1.0, -100.0]], [[0.0, 1.0, 5.0]], [[0.01, -1.0, 6.5]]], dtype=torch.float64)
    plain, plain_valid = flow_from_map(M, horizon, (H, W))
    graded, graded_valid = flow_from_map(M.clone().requires_grad_(), horizon, (H, W))
    assert torch.equal(plain_valid, graded_valid)
    assert not plain_valid[0].any() and plain_valid[1].all() and plain_valid[2, 0, :6].any()
    assert not plain_valid[2, 0, 8:].any()
    torch.testing.assert_close(plain, graded.detach(), rtol=1e-12, atol=1e-12)


def test_vflow_curve_computes_half_precision_rows_in_float32():
    """Half precision rows are lifted to float32 (float16 arithmetic overflowed to inf in 151 of
    720 rows of a 720p camera); numbers and sequences are taken as tensors."""
    v = torch.arange(720.0)
    ref = vflow_curve(v.double(), 1.5, 1.5, 1000.0, 360.0)
    assert float(ref.max()) == pytest.approx(201.0624, abs=1e-4)
    for half in (torch.float16, torch.bfloat16):
        out = vflow_curve(v.to(half), 1.5, 1.5, 1000.0, 360.0)
        want = vflow_curve(v.to(half).double(), 1.5, 1.5, 1000.0, 360.0)  # the same rows, exactly
        assert out.dtype == torch.float32
        torch.testing.assert_close(out.double(), want, rtol=1e-6, atol=1e-5)
    assert vflow_curve(v.float(), 1.5, 1.5, 1000.0, 360.0).dtype == torch.float32
    # all numbers: the default dtype; a list of rows: a tensor of them
    assert float(vflow_curve(50.0, 1.0, 1.65, 150.0, 40.0)) == pytest.approx(100.0 / (247.5 - 10.0), rel=1e-6)
    torch.testing.assert_close(vflow_curve([39.0, 50.0], 1.0, 1.65, 150.0, 40.0),
                               torch.tensor([0.0, 100.0 / 237.5]))
    for bad in ("abc", None, True):
        with pytest.raises(TypeError, match="^z_d: expected a tensor or a number"):
            vflow_curve(v, bad, 1.65, 150.0, 40.0)


def test_vflow_curve_names_arguments_that_do_not_broadcast():
    """Rows and a batch of z_d that do not broadcast raised torch's RuntimeError from inside."""
    with pytest.raises(ValueError, match=r"^v, z_d, height, fy, cy: expected shapes that broadcast together, got "
                                         r"v \(5,\), z_d \(3,\), height \(\), fy \(\), cy \(\)$"):
        vflow_curve(torch.arange(5.0), torch.ones(3), 1.65, 500.0, 100.0)
    with pytest.raises(ValueError, match=r"got v \(2, 3\), z_d \(2,\), "):
        vflow_curve(torch.arange(6.0).reshape(2, 3), torch.ones(2), 1.65, 500.0, 100.0)
    # (rows (N, 1) against a batch (B,) broadcast to (N, B), as documented)
    assert vflow_curve(torch.arange(5.0)[:, None], torch.ones(3), 1.65, 500.0, 100.0).shape == (5, 3)


def test_velocity_flow_module_checks_its_wheelbase_when_built():
    """VelocityFlow takes the wheelbase velocity_flow takes (a float or a (B,) tensor) and checks
    it when built, naming it (a tensor of two once failed in float(), True was taken as 1 m, inf
    failed only at forward)."""
    cam = _kitti_scaled(12, 20, roll=0.02)
    wheelbase = torch.tensor([2.5, 3.0], dtype=torch.float64)
    module = VelocityFlow((12, 20), wheelbase=wheelbase)
    torch.testing.assert_close(module(cam, 8.0, 0.05), velocity_flow(cam, 8.0, 0.05, wheelbase, (12, 20)),
                               rtol=0, atol=0)
    assert "wheelbase" not in module.state_dict()
    for bad, error in ((True, TypeError), ("abc", TypeError), (None, TypeError), (float("inf"), ValueError),
                       (0.0, ValueError), (torch.tensor([2.5, 0.0]), ValueError), (torch.tensor([float("nan")]), ValueError)):
        with pytest.raises(error, match="^wheelbase: expected"):
            VelocityFlow((12, 20), wheelbase=bad)


@pytest.mark.parametrize("name, value, message", [
    ("height", -1.65, "height: expected values > 0"),
    ("height", 0.0, "height: expected values > 0"),
    ("fy", 0.0, "fy: expected values > 0"),
    ("z_d", float("nan"), "z_d: expected finite values"),
    ("cy", float("inf"), "cy: expected finite values"),
    ("v", torch.tensor([float("nan"), 200.0, 250.0]), "v: expected finite values"),
    ("height", torch.tensor([1.65, float("-inf")]), "height: expected finite values"),
])
def test_vflow_curve_refuses_values_without_a_curve(name, value, message):
    """NaN or inf arguments, a negative or zero height and a zero focal length once gave 0 (no road
    flow) without an error; the checks change nothing for valid arguments."""
    args = {"v": torch.tensor([180.0, 200.0, 250.0]), "z_d": 1.2, "height": 1.65, "fy": 721.5, "cy": 172.9}
    good = vflow_curve(**args)
    torch.testing.assert_close(good, torch.tensor([0.0511797, 0.7610766, 6.4968910]), rtol=1e-6, atol=0.0)
    with pytest.raises(ValueError, match=f"^{message}"):
        vflow_curve(**{**args, name: value})
    # not read where there are no values: shape inference on the meta device
    assert vflow_curve(torch.empty(3, device="meta"), -1.0, 1.65, 0.0, 0.0).shape == (3,)


def test_flow_from_map_checks_types_and_shapes_and_lifts_half_precision():
    """Half precision maps were evaluated in half precision (2.5 px off on a KITTI frame), and a
    map of (3, 3), a horizon of another batch or an empty size raised torch's own errors."""
    cam = _kitti_scaled(60, 200)
    from fsof_torch.geometry.road_models import ROAD_MODELS, pack_params
    c2, values = pack_params("paper", cam, {"z_d": 1.2, "yaw": 0.01})
    M = road_homography(cam, {"z_d": 1.2, "yaw": 0.01})
    horizon = ROAD_MODELS["paper"].horizon_row(c2, values)
    flow, valid = flow_from_map(M, horizon, (60, 200))
    for half in (torch.float16, torch.bfloat16):
        f16, v16 = flow_from_map(M.to(half), horizon.to(half), (60, 200))
        want, want_valid = flow_from_map(M.to(half).float(), horizon.to(half), (60, 200))  # the same map, float32
        assert f16.dtype == torch.float32 and torch.equal(f16, want) and torch.equal(v16, want_valid)
    f16, v16 = flow_from_map(M.half(), horizon.half(), (60, 200))
    common = (valid & v16).expand_as(flow)
    assert (f16.double() - flow)[common].abs().max() < 0.05  # the half map's own rounding, not its arithmetic
    # the accepted float32 and float64 inputs keep their results and dtypes
    assert flow.dtype == torch.float64 and flow_from_map(M.float(), horizon.float(), (60, 200))[0].dtype == torch.float32
    with pytest.raises(ValueError, match=r"^M: expected shape \(B, 3, 3\), got \(3, 3\)"):
        flow_from_map(M[0], horizon, (4, 5))
    with pytest.raises(TypeError, match="^M: expected a torch.Tensor, got list"):
        flow_from_map(M.tolist(), horizon, (4, 5))
    with pytest.raises(TypeError, match="^horizon: expected a floating-point tensor, got dtype torch.int64"):
        flow_from_map(M, horizon.long(), (4, 5))
    with pytest.raises(ValueError, match=r"^horizon: expected shape \(1, 1, 3\) beside M of batch 1, got \(2, 1, 3\)"):
        flow_from_map(M, horizon.expand(2, 1, 3), (4, 5))
    with pytest.raises(ValueError, match=r"^horizon: expected shape \(1 or 3, 1, 3\) beside M of batch 3, got \(1, 3\)"):
        flow_from_map(M.expand(3, 3, 3), horizon[0], (4, 5))
    for size in ((0, 5), (-2, 5)):
        with pytest.raises(ValueError, match=r"^size: expected positive sides"):
            flow_from_map(M, horizon, size)
    with pytest.raises(TypeError, match="^velocity: expected True or False"):
        flow_from_map(M, horizon, (4, 5), velocity=1)
    # a horizon of batch 1 beside maps of batch B is broadcast, as before
    f3, _ = flow_from_map(M.expand(3, 3, 3), horizon, (60, 200))
    assert torch.equal(f3, flow.expand(3, -1, -1, -1))


def test_flow_from_map_reads_nothing_from_the_host():
    """Its checks look at types and shapes only: the fits evaluate maps without host reads (the
    CPU inference path's one read of the valid rows' band aside, which the graded path skips)."""
    from torch.profiler import ProfilerActivity, profile

    cam = _kitti_scaled(60, 200)
    from fsof_torch.geometry.road_models import ROAD_MODELS, pack_params
    c2, values = pack_params("paper", cam, {"z_d": 1.2})
    M = road_homography(cam, {"z_d": 1.2}).requires_grad_()
    horizon = ROAD_MODELS["paper"].horizon_row(c2, values)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        flow_from_map(M, horizon, (60, 200))
    reads = [e.name for e in prof.events() if e.name in ("aten::_local_scalar_dense", "aten::nonzero", "aten::item")]
    assert reads == []


@pytest.mark.parametrize("cast", ["half", "bfloat16", "float16"])
def test_velocity_flow_module_cast_to_half_keeps_its_wheelbase(cast):
    """A VelocityFlow with a tensor wheelbase cast to half precision (a network's ``.half()``)
    rounded the wheelbase too, 2.7 m to 2.6992 (bfloat16: 2.7031): its flow moved by up to
    0.27 px/s at KITTI's size, where the geometry runs in at least float32."""
    cam = Camera(torch.tensor([[721.5, 0.0, 609.5], [0.0, 721.5, 172.8], [0.0, 0.0, 1.0]]), 1.65)
    for wheelbase in (torch.tensor([2.7]), torch.tensor([2.7, 3.1], dtype=torch.float64)):
        module = VelocityFlow((375, 1242), wheelbase=wheelbase)
        ref = module(cam, 10.0, 0.05)
        cast_module = module.to(torch.float16) if cast == "float16" else getattr(module, cast)()
        assert cast_module.wheelbase.dtype == wheelbase.dtype and torch.equal(cast_module.wheelbase, wheelbase)
        out = cast_module(cam, 10.0, 0.05)
        assert torch.equal(out[0], ref[0]) and torch.equal(out[1], ref[1])
        assert "wheelbase" not in cast_module.state_dict()
    # a wider cast and a move still apply
    module = VelocityFlow((4, 6), wheelbase=torch.tensor([2.7])).double()
    assert module.wheelbase.dtype == torch.float64
    assert VelocityFlow((4, 6), wheelbase=torch.tensor([2.7])).to("meta").wheelbase.device.type == "meta"
