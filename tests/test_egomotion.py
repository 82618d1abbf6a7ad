"""Tests of fsof_torch.geometry.egomotion: poses -> (x_d, z_d, yaw) and the Ackermann integration."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.egomotion import (EgoMotion, check_pose_steps, ego_motion_from_ackermann, ego_motion_from_pose,
                                          relative_pose)
from fsof_torch.geometry.road_flow import displacement_flow


def _rot(axis, a):
    c, s = math.cos(a), math.sin(a)
    if axis == "x":
        return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _R_yaw(phi):
    """R_φ of the paper: p_v(t+1) = R_φ (p_v(t) - d)."""
    c, s = math.cos(phi), math.sin(phi)
    return np.array([[c, 0, -s], [0, 1.0, 0], [s, 0, c]])


def _mounting(roll, pitch):
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    R_roll = np.array([[cr, sr, 0], [-sr, cr, 0], [0, 0, 1.0]])
    R_pitch = np.array([[1.0, 0, 0], [0, cp, sp], [0, -sp, cp]])
    return R_roll @ R_pitch


def _synthetic_cam1_T_cam0(x_d, z_d, yaw, roll, pitch, y_d=0.0, body=None):
    """cam1_T_cam0 of a camera mounted with (roll, pitch) on a car that moves by d = (x_d, y_d, z_d)
    and turns by yaw (optionally with an extra body rotation, out of the model's plane)."""
    Rc = _mounting(roll, pitch)
    Rv = _R_yaw(yaw) if body is None else body @ _R_yaw(yaw)
    d = np.array([x_d, y_d, z_d])
    T = np.eye(4)
    T[:3, :3] = Rc @ Rv @ Rc.T
    T[:3, 3] = -Rc @ Rv @ d
    return torch.from_numpy(T)


# --- smoke / feature: poses ---------------------------------------------------------------------------

@pytest.mark.parametrize("x_d, z_d, yaw, roll, pitch", [
    (0.0, 1.2, 0.0, 0.0, 0.0),
    (0.1, 1.0, 0.03, 0.02, -0.015),
    (-0.4, 2.7, -0.08, -0.1, 0.05),
])
def test_pose_round_trip(x_d, z_d, yaw, roll, pitch):
    T = _synthetic_cam1_T_cam0(x_d, z_d, yaw, roll, pitch)
    cam = Camera(torch.eye(3, dtype=torch.float64), 1.65, roll, pitch)
    e = ego_motion_from_pose(T, cam)
    assert isinstance(e, EgoMotion)
    assert e.x_d.tolist() == pytest.approx([x_d], abs=1e-12)
    assert e.z_d.tolist() == pytest.approx([z_d], abs=1e-12)
    assert e.yaw.tolist() == pytest.approx([yaw], abs=1e-12)
    assert e.y_d.abs().max() < 1e-12 and e.rotation_residual.abs().max() < 1e-12


def test_pose_from_two_camera_to_world_poses():
    g = np.random.default_rng(0)
    P0 = np.eye(4)
    P0[:3, :3] = _rot("y", 0.7) @ _rot("x", 0.01)
    P0[:3, 3] = g.normal(size=3) * 10
    T = _synthetic_cam1_T_cam0(0.2, 1.4, 0.05, 0.03, -0.02).numpy()
    P1 = P0 @ np.linalg.inv(T)  # cam1_T_cam0 = inv(P1) @ P0
    cam = Camera(torch.eye(3, dtype=torch.float64), 1.65, 0.03, -0.02)
    e = ego_motion_from_pose(torch.from_numpy(P0), cam, pose1=torch.from_numpy(P1))
    assert e.x_d.item() == pytest.approx(0.2, abs=1e-9) and e.z_d.item() == pytest.approx(1.4, abs=1e-9)
    assert e.yaw.item() == pytest.approx(0.05, abs=1e-12)
    torch.testing.assert_close(relative_pose(torch.from_numpy(P0), torch.from_numpy(P1))[0],
                               torch.from_numpy(T), rtol=1e-9, atol=1e-9)
    # 3×4 rows (KITTI files) work as well
    e34 = ego_motion_from_pose(torch.from_numpy(P0[:3]), cam, pose1=torch.from_numpy(P1[:3]))
    torch.testing.assert_close(e34.z_d, e.z_d)


def test_pose_remainder_nonzero_out_of_plane():
    cam = Camera(torch.eye(3, dtype=torch.float64), 1.65, 0.01, -0.01)
    bump = _synthetic_cam1_T_cam0(0.0, 1.0, 0.02, 0.01, -0.01, y_d=0.05)
    e = ego_motion_from_pose(bump, cam)
    assert e.y_d.item() == pytest.approx(0.05, abs=1e-12)
    assert e.rotation_residual.abs().max() < 1e-12
    body_pitch = _synthetic_cam1_T_cam0(0.0, 1.0, 0.02, 0.01, -0.01, body=_rot("x", 0.01))
    e = ego_motion_from_pose(body_pitch, cam)
    assert e.rotation_residual.norm().item() == pytest.approx(0.01, rel=1e-3)
    assert e.yaw.item() == pytest.approx(0.02, abs=1e-3)
    # without the mounting, a mounted camera's motion looks partly out of plane
    T = _synthetic_cam1_T_cam0(0.0, 1.0, 0.05, 0.0, -0.1)
    e_wrong = ego_motion_from_pose(T)
    assert e_wrong.y_d.abs().item() > 0.05


def test_rotation_residual_is_the_axis_angle_of_the_coordinate_map():
    """EgoMotion's docstring: a body pitching up by α and rolling by γ (the "plane" model's
    pitch_change and roll_change, R_v = R_roll(γ) R_pitch(α) R_yaw(φ)) leaves about (−α, 0, −γ)."""
    from fsof_torch.geometry.camera import pitch_matrix, roll_matrix

    def angle(x: float) -> torch.Tensor:
        return torch.tensor([x], dtype=torch.float64)

    cam = Camera(torch.eye(3, dtype=torch.float64), 1.65, 0.01, -0.02)
    alpha, gamma, yaw = 0.01, 0.005, 0.03
    c, s = math.cos(yaw), math.sin(yaw)
    R_yaw = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]], dtype=torch.float64)
    Rv = (roll_matrix(angle(gamma)) @ pitch_matrix(angle(alpha)))[0] @ R_yaw
    Rc = cam.mounting()[0]
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = Rc @ Rv @ Rc.T
    T[:3, 3] = -Rc @ Rv @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    e = ego_motion_from_pose(T[None], cam)
    np.testing.assert_allclose(e.rotation_residual[0].numpy(), [-alpha, 0.0, -gamma], atol=2e-4)


def test_pose_batch():
    Ts = torch.stack([_synthetic_cam1_T_cam0(0.1 * i, 1.0 + i, 0.01 * i, 0.02, 0.0) for i in range(3)])
    cam = Camera(torch.eye(3, dtype=torch.float64), 1.65, 0.02)
    e = ego_motion_from_pose(Ts, cam)
    assert e.x_d.shape == (3,) and e.rotation_residual.shape == (3, 3)
    torch.testing.assert_close(e.z_d, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="mismatched batch sizes"):
        ego_motion_from_pose(Ts, cam.expand(2))


def test_pose_empty_batch_refused_with_or_without_a_camera():
    """Without a camera an empty batch of poses gave an empty EgoMotion, where relative_pose,
    plane_from_pose and the same call with a camera raise."""
    cam = Camera(torch.eye(3, dtype=torch.float64), 1.65, 0.02)
    for args in ((), (cam,)):
        with pytest.raises(ValueError, match=r"^cam1_T_cam0: expected a batch of at least 1, got 0$"):
            ego_motion_from_pose(torch.eye(4, dtype=torch.float64).expand(0, 4, 4), *args)


def test_pose_and_flow_agree():
    """The flow of the decomposed planar motion equals the projection of road points moved by the pose."""
    H, W = 30, 50
    K = torch.tensor([[40.0, 0, 25.0], [0, 40.0, 10.0], [0, 0, 1]], dtype=torch.float64)
    roll, pitch, h = 0.03, -0.02, 1.6
    T = _synthetic_cam1_T_cam0(0.15, 1.3, 0.04, roll, pitch).numpy()
    cam = Camera(K, h, roll, pitch)
    e = ego_motion_from_pose(torch.from_numpy(T), cam)
    flow, valid = displacement_flow(cam, e.x_d, e.z_d, e.yaw, (H, W))
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    p = np.stack([u, v, np.ones_like(u)]).reshape(3, -1)
    Kn = K.numpy()
    Rc = _mounting(roll, pitch)
    ray_c = np.linalg.solve(Kn, p)
    ray_y = (Rc.T @ ray_c)[1]
    ok = ray_y > 1e-6
    X0 = ray_c * (h / np.where(ok, ray_y, 1.0))       # road points in camera-0 coordinates
    X1 = T[:3, :3] @ X0 + T[:3, 3:4]
    proj = Kn @ X1
    ok &= X1[2] > 1e-6
    want = (proj[:2] / np.where(ok, proj[2], 1.0) - p[:2]).reshape(2, H, W)
    ok = ok.reshape(H, W)
    assert (valid[0, 0].numpy() == ok).all()
    np.testing.assert_allclose(flow[0].numpy()[:, ok], want[:, ok], atol=1e-9, rtol=1e-9)


def test_kitti_odometry_poses(shared_data):
    rows = np.loadtxt(shared_data / "kitti_odometry_straight" / "poses.txt").reshape(-1, 3, 4)
    P = torch.from_numpy(rows)
    e = ego_motion_from_pose(P[:-1], pose1=P[1:])
    assert e.z_d.shape == (len(rows) - 1,)
    assert e.z_d.mean().item() == pytest.approx(1.2, abs=0.15)
    assert (e.z_d > 1.0).all() and (e.z_d < 1.4).all()
    assert e.x_d.abs().max() < 0.05 and e.yaw.abs().max() < 0.01
    assert e.y_d.abs().max() < 0.05 and e.rotation_residual.norm(dim=-1).max() < 0.01


def test_pose_exceptions():
    with pytest.raises(TypeError, match="cam1_T_cam0: expected a float tensor"):
        ego_motion_from_pose(np.eye(4))
    with pytest.raises(TypeError, match="cam1_T_cam0: expected a float tensor"):
        ego_motion_from_pose(torch.eye(4, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"cam1_T_cam0: expected shape \(B, 4, 4\) or \(B, 3, 4\), got \(4, 3\)"):
        ego_motion_from_pose(torch.eye(4)[:, :3])
    bad = torch.eye(4)
    bad[0, 3] = float("nan")
    with pytest.raises(ValueError, match="cam1_T_cam0: expected finite values"):
        ego_motion_from_pose(bad)
    with pytest.raises(ValueError, match=r"pose1: expected shape"):
        relative_pose(torch.eye(4), torch.eye(5))


# --- Ackermann ------------------------------------------------------------------------------------------

def _integrate(speed, steering, wheelbase, dt, steps=20000):
    """RK4 on φ̇ = v tan δ / l, ẋ = v sin φ, ż = v cos φ (x right, z forward in the frame of time t)."""
    k = speed * math.tan(steering) / wheelbase

    def f(s):
        return np.array([k, speed * math.sin(s[0]), speed * math.cos(s[0])])

    s = np.zeros(3)
    h = dt / steps
    for _ in range(steps):
        a = f(s); b = f(s + h / 2 * a); c = f(s + h / 2 * b); d = f(s + h * c)
        s = s + h / 6 * (a + 2 * b + 2 * c + d)
    return s  # yaw, x, z


@pytest.mark.parametrize("speed, steering, dt", [(10.0, 0.1, 0.1), (5.0, -0.5, 1.0), (20.0, 0.02, 0.5)])
def test_ackermann_exact_integration(speed, steering, dt):
    e = ego_motion_from_ackermann(torch.tensor([speed], dtype=torch.float64), steering, 2.7, dt)
    yaw, x, z = _integrate(speed, steering, 2.7, dt, steps=2000)
    assert e.yaw.item() == pytest.approx(yaw, abs=1e-12)
    assert e.x_d.item() == pytest.approx(x, abs=1e-9)
    assert e.z_d.item() == pytest.approx(z, abs=1e-9)
    assert e.y_d.tolist() == [0.0] and e.rotation_residual.abs().max() == 0


@pytest.mark.parametrize("offset", [1.5, -0.8])
@pytest.mark.parametrize("speed, steering, dt", [(10.0, 0.1, 0.1), (-5.0, -0.5, 1.0)])
def test_ackermann_camera_ahead_of_the_rear_axle(speed, steering, dt, offset):
    """The displacement model's d is the camera's (the vehicle frame's origin is the camera
    centre); the Ackermann arc is the rear axle's. Independent reference: the axle's pose from
    the numerical integration, the camera ``offset`` metres ahead of it along the heading, and a
    road point's coordinates in the camera frame of t+1 by rigid transforms, against the
    displacement model's ``R_φ (p - d)``. Before ``camera_offset`` the axle's arc was returned for
    every camera: a camera 1.5 m ahead, turning 2° a frame, lies 5 cm further to the side."""
    e = ego_motion_from_ackermann(torch.tensor([speed], dtype=torch.float64), steering, 2.7, dt,
                                  camera_offset=offset)
    yaw, x, z = _integrate(speed, steering, 2.7, dt, steps=2000)
    forward, right = np.array([math.sin(yaw), 0.0, math.cos(yaw)]), np.array([math.cos(yaw), 0.0, -math.sin(yaw)])
    camera1 = np.array([0.0, 0.0, -offset]) + np.array([x, 0.0, z]) + offset * forward  # in camera-t coordinates
    assert e.yaw.item() == pytest.approx(yaw, abs=1e-12)
    assert [e.x_d.item(), e.z_d.item()] == pytest.approx([camera1[0], camera1[2]], abs=1e-9)
    point = np.array([2.0, 1.65, 9.0])
    seen = np.array([right @ (point - camera1), point[1] - camera1[1], forward @ (point - camera1)])
    c, s_ = math.cos(e.yaw.item()), math.sin(e.yaw.item())
    d = np.array([e.x_d.item(), 0.0, e.z_d.item()])
    model = np.array([[c, 0.0, -s_], [0.0, 1.0, 0.0], [s_, 0.0, c]]) @ (point - d)
    np.testing.assert_allclose(model, seen, atol=1e-9)
    axle = ego_motion_from_ackermann(torch.tensor([speed], dtype=torch.float64), steering, 2.7, dt)
    assert abs(e.x_d.item() - axle.x_d.item()) > 0.01  # (the offset matters at these turns)


def test_ackermann_camera_offset_batch_gradient_and_default():
    v = torch.tensor([12.0, 12.0], dtype=torch.float64)
    e = ego_motion_from_ackermann(v, 0.05, 2.7, 0.1, camera_offset=torch.tensor([0.0, 1.5], dtype=torch.float64))
    base = ego_motion_from_ackermann(v, 0.05, 2.7, 0.1)
    assert e.x_d[0] == base.x_d[0] and e.z_d[0] == base.z_d[0] and e.x_d[1] > base.x_d[1]
    assert torch.equal(e.yaw, base.yaw)
    for steering in (0.0, 0.2):  # smooth through straight motion
        torch.autograd.gradcheck(
            lambda s, a: torch.cat(ego_motion_from_ackermann(12.0, s, 2.7, 0.1, camera_offset=a)[:3]),
            (torch.tensor([steering], dtype=torch.float64, requires_grad=True),
             torch.tensor([1.5], dtype=torch.float64, requires_grad=True)))
    with pytest.raises(ValueError, match="camera_offset: expected finite values"):
        ego_motion_from_ackermann(10.0, 0.0, 2.7, 0.1, camera_offset=float("inf"))
    with pytest.raises(ValueError, match="mismatched batch sizes"):
        ego_motion_from_ackermann(torch.ones(2), 0.0, 2.7, 0.1, camera_offset=torch.ones(3))


def test_ackermann_straight_limit():
    e = ego_motion_from_ackermann(torch.tensor([12.0], dtype=torch.float64), 0.0, 2.7, 0.1)
    assert e.x_d.item() == 0.0 and e.yaw.item() == 0.0 and e.z_d.item() == pytest.approx(1.2, abs=1e-15)
    small = ego_motion_from_ackermann(torch.tensor([12.0], dtype=torch.float64), 1e-9, 2.7, 0.1)
    assert small.z_d.item() == pytest.approx(1.2, abs=1e-12) and abs(small.x_d.item()) < 1e-9
    # the curvature κ -> 0 limit is smooth: finite gradients at δ = 0
    steering = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    speed = torch.tensor([12.0], dtype=torch.float64, requires_grad=True)
    torch.autograd.gradcheck(lambda s, v: torch.cat(ego_motion_from_ackermann(v, s, 2.7, 0.1)[:3]),
                             (steering, speed))
    torch.autograd.gradcheck(lambda s, v: torch.cat(ego_motion_from_ackermann(v, s, 2.7, 0.1)[:3]),
                             (steering.detach().clone().fill_(0.2).requires_grad_(), speed))


def test_ackermann_batch_and_dtype():
    e = ego_motion_from_ackermann(torch.tensor([5.0, 10.0, 15.0]), torch.tensor([0.0, 0.1, -0.1]), 2.7, 0.1)
    assert e.x_d.shape == (3,) and e.x_d.dtype == torch.float32
    assert e.x_d[1] > 0 and e.x_d[2] < 0 and e.yaw[1] > 0  # steering right turns toward +x
    e = ego_motion_from_ackermann(10.0, 0.0, 2.7, 0.1)
    assert e.z_d.shape == (1,)


def test_ackermann_exceptions():
    with pytest.raises(ValueError, match="wheelbase: expected values > 0"):
        ego_motion_from_ackermann(10.0, 0.0, 0.0, 0.1)
    with pytest.raises(ValueError, match="mismatched batch sizes"):
        ego_motion_from_ackermann(torch.ones(2), torch.zeros(3), 2.7, 0.1)
    with pytest.raises(TypeError, match="speed: expected a float tensor"):
        ego_motion_from_ackermann(torch.tensor([10]), 0.0, 2.7, 0.1)
    with pytest.raises(ValueError, match="dt: expected finite values"):
        ego_motion_from_ackermann(10.0, 0.0, 2.7, float("nan"))


def test_ackermann_on_the_meta_device_follows_its_tensors():
    """Python numbers once became CPU tensors beside meta ones (a device mismatch)."""
    speed = torch.empty(3, device="meta")
    out = ego_motion_from_ackermann(speed, 0.1, 2.7, 0.1)
    assert out.x_d.device.type == "meta" and out.x_d.shape == (3,)


@pytest.mark.parametrize("steering", [math.pi / 2, -2.0, float("nan")])
def test_ackermann_refuses_steering_across_the_car(steering):
    """|δ_f| ≥ π/2 has no Ackermann motion (velocity_flow refuses it too); before, a yaw of
    millions of radians came back."""
    with pytest.raises(ValueError, match=r"^steering: "):
        ego_motion_from_ackermann(10.0, steering, 2.7, 0.1)


def test_relative_pose_names_a_singular_pose1():
    """A finite but singular pose1 once raised torch's _LinAlgError, naming no argument (now the
    rigid check names it: a singular pose has no rotation block)."""

    pose0 = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    pose1 = pose0.clone()
    pose1[0, 2, 3] = 1.5
    pose1[1, :3, :3] = 0.0
    with pytest.raises(ValueError, match=r"^pose1: expected rigid transforms .*, got sample 1: its 3×3 block is not "
                                         r"a rotation: \|RᵀR − I\| up to 1, det R = 0"):
        relative_pose(pose0, pose1)
    with pytest.raises(ValueError, match=r"^pose1: expected rigid transforms"):
        ego_motion_from_pose(pose0, pose1=pose1)
    T = relative_pose(pose0[:1], pose1[:1])
    assert T[0, 2, 3].item() == -1.5 and float(ego_motion_from_pose(pose0[:1], pose1=pose1[:1]).z_d) == 1.5


def _turn_pose(dtype=torch.float64):
    T = torch.tensor(np.eye(4), dtype=dtype)
    T[:3, :3] = torch.tensor(_R_yaw(0.05), dtype=dtype)
    T[:3, 3] = torch.tensor([0.05, 0.0, -1.2], dtype=dtype)
    return T


def test_poses_that_are_not_rigid_are_refused():
    """A transposed pose, a scaled or reflected rotation block and an all-zero block once gave
    plausible numbers (a transposed pose: z_d = 0 and yaw of the wrong sign, without an error)."""
    from fsof_torch import plane_from_pose

    T = _turn_pose()
    cam = Camera(torch.tensor([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]], dtype=torch.float64), 1.65)
    with pytest.raises(ValueError, match=r"^cam1_T_cam0: expected rigid transforms .*, got sample 0: its bottom row is "
                                         r"\[0.05, 0.0, -1.2, 1.0\], not 0 0 0 1 \(a transposed pose"):
        ego_motion_from_pose(T.T)
    with pytest.raises(ValueError, match=r"^cam1_T_cam0: expected rigid transforms .*its bottom row"):
        plane_from_pose(T.T, cam)
    scaled = T.clone()
    scaled[:3, :3] *= 3.0
    reflected = T.clone()
    reflected[:3, :3] *= -1.0
    for bad, what in ((scaled, r"\|RᵀR − I\| up to 8, det R = 27"), (reflected, "det R = -1"),
                      (torch.zeros(3, 4, dtype=torch.float64), "det R = 0")):
        with pytest.raises(ValueError, match=rf"^cam1_T_cam0: expected rigid transforms .*its 3×3 block is not a "
                                             rf"rotation: .*{what}"):
            ego_motion_from_pose(bad)
    # the first bad sample of a batch is named; pose0 and pose1 by their names
    with pytest.raises(ValueError, match="^cam1_T_cam0: expected rigid transforms .*, got sample 2:"):
        ego_motion_from_pose(torch.stack([T, T, scaled, T]))
    with pytest.raises(ValueError, match="^pose1: expected rigid transforms"):
        relative_pose(T, 2 * T)
    with pytest.raises(ValueError, match="^pose0: expected rigid transforms"):
        relative_pose(scaled, T)


def test_rigid_poses_pass_in_every_dtype_and_keep_their_results():
    """The check accepts poses rounded as files and dtypes round them, and changes no result."""
    T = _turn_pose()
    want = ego_motion_from_pose(T)
    assert float(want.z_d) == pytest.approx(1.2010, abs=1e-4) and float(want.yaw) == pytest.approx(0.05)
    for dtype in (torch.float16, torch.bfloat16, torch.float32):
        got = ego_motion_from_pose(T.to(dtype))
        assert got.z_d.dtype == torch.float32
        assert float(got.yaw) == pytest.approx(0.05, abs=5e-3)
    # rounded to 4 digits (|RᵀR − I| about 1e-4): still a pose
    rounded = ego_motion_from_pose(torch.round(T, decimals=4))
    assert float(rounded.yaw) == pytest.approx(0.05, abs=1e-3)
    plain = ego_motion_from_pose(T.float())
    with torch.autocast("cpu", dtype=torch.bfloat16):  # the check's products in float32 too (bfloat16: 1e-2 off)
        auto = ego_motion_from_pose(T.float())
    assert torch.equal(auto.z_d, plain.z_d) and torch.equal(auto.yaw, plain.yaw)
    # unchecked where there are no values (shape inference) or while tracing
    assert ego_motion_from_pose((3 * T).to("meta")).z_d.shape == (1,)


def test_kitti_text_poses_pass_the_rigid_check(shared_data):
    """The shared KITTI odometry excerpt (poses printed to 7 digits, orthonormal to 2e-7): its
    poses and their relative poses pass, in float64 and float32."""
    path = shared_data / "kitti_odometry_straight" / "poses.txt"
    if not path.is_file():
        pytest.skip("no shared KITTI odometry poses")
    P = torch.tensor(np.loadtxt(path).reshape(-1, 3, 4), dtype=torch.float64)
    for dtype in (torch.float64, torch.float32):
        Pd = P.to(dtype)
        rel = relative_pose(Pd[:-1], Pd[1:])
        ego = ego_motion_from_pose(rel)
        assert torch.isfinite(ego.z_d).all() and (ego.z_d > 0.5).all()


def _poses_along_z(steps_m) -> torch.Tensor:
    P = torch.eye(4, dtype=torch.float64).repeat(len(steps_m) + 1, 1, 1)
    P[1:, 2, 3] = torch.tensor(steps_m, dtype=torch.float64).cumsum(0)
    return P


def test_pose_steps_beyond_a_road_vehicle_are_named(shared_data):
    """Poses in millimetres gave motions of a kilometre a frame, which the refiner left unchanged
    with its generic warning: a step beyond 100 m (100 m/s for 1 s) names the poses and the frames."""
    from fsof_torch.io import read_kitti_poses

    P = read_kitti_poses(shared_data / "kitti_odometry_straight" / "poses.txt")
    check_pose_steps(P)  # metres: about 1.2 m a frame
    mm = P.clone()
    mm[:, :3, 3] *= 1000
    with pytest.raises(ValueError, match=r"^poses: pose 0 and pose 1 lie 1199 m apart, farther than a road vehicle "
                                         r"travels between them \(100 m: 100 m/s for 1 s.*millimetres"):
        check_pose_steps(mm)
    check_pose_steps(_poses_along_z([1.0, 99.0, 2.0]))  # (fast, but a road vehicle's)
    with pytest.raises(ValueError, match=r"^clip: b and c lie 150 m apart"):
        check_pose_steps(_poses_along_z([1.0, 150.0]), "clip", labels=["a", "b", "c"])
    # frames missing between two poses: as many frames' travel
    check_pose_steps(_poses_along_z([1.0, 150.0]), frames_apart=[1, 2])
    with pytest.raises(ValueError, match=r"^poses: pose 1 and pose 2 lie 250 m apart, .* \(200 m: 100 m/s for 2 s"):
        check_pose_steps(_poses_along_z([1.0, 250.0]), frames_apart=[1, 2])
