"""The camera's conventions against references written without the library: OpenCV's and torch's
resizing (where a blob's centre lands), cropping and padding, KITTI's projection matrices, and the
road's flow from kornia's projection of the moved road point."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fsof_torch import Camera, read_kitti_calibration, road_flow

# a camera with skew and non-square pixels, its principal point off the image centre
K_ODD = [[300.0, 2.0, 161.3], [0.0, 280.0, 97.7], [0.0, 0.0, 1.0]]


def _project(K: torch.Tensor, X: torch.Tensor) -> np.ndarray:
    x = K @ X
    return (x[:2] / x[2]).numpy()


def _centroid(image: np.ndarray) -> np.ndarray:
    v, u = np.mgrid[0:image.shape[0], 0:image.shape[1]]
    return np.array([(image * u).sum(), (image * v).sum()]) / image.sum()


def _blob(K: torch.Tensor, X: torch.Tensor, H: int, W: int) -> np.ndarray:
    """An (H, W) image of a Gaussian blob (σ 6 px) drawn where K projects the point X."""
    u0, v0 = _project(K, X)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.exp(-((u - u0) ** 2 + (v - v0) ** 2) / (2 * 6.0 ** 2))


@pytest.mark.parametrize("size", [(100, 160), (50, 80), (100, 320), (300, 480)])
def test_scaled_puts_a_point_where_resizing_moves_it(size):
    """A Gaussian blob drawn where a 3-D point projects, resized by OpenCV (INTER_AREA down,
    INTER_LINEAR up) and by torch (bilinear, align_corners=False, antialias): its centre lands
    where the scaled camera projects the point (the box filter keeps a blob's centroid under the
    pixel-centre map u' + 0.5 = s (u + 0.5))."""
    import cv2
    H, W = 200, 320
    K = torch.tensor(K_ODD, dtype=torch.float64)
    X = torch.tensor([0.3, 0.2, 5.0], dtype=torch.float64)
    image = _blob(K, X, H, W)
    h, w = size
    cam = Camera(K, 1.5).scaled(w / W, h / H)
    expected = _project(cam.K[0], X)
    inter = cv2.INTER_AREA if w < W else cv2.INTER_LINEAR
    np.testing.assert_allclose(_centroid(cv2.resize(image, (w, h), interpolation=inter)), expected, atol=2e-3)
    resized = F.interpolate(torch.from_numpy(image)[None, None], size=(h, w), mode="bilinear", align_corners=False,
                            antialias=True)[0, 0].numpy()
    np.testing.assert_allclose(_centroid(resized), expected, atol=2e-3)


@pytest.mark.parametrize("k", [2, 3, 4])
def test_nearest_resizing_is_off_the_scaled_cameras_map_as_documented(k):
    """Camera.scaled's docstring: cv2.INTER_NEAREST and F.interpolate(mode="nearest") take source
    pixel floor(u' / sx), (k - 1) / 2 source pixels short of the centre map u = (u' + 0.5) k - 0.5
    when shrunk by k; INTER_NEAREST_EXACT and "nearest-exact" round that map. An image whose
    value is its source column shows which pixel each one took."""
    import cv2
    W = 12 * k
    image = np.tile(np.arange(W, dtype=np.float32), (3, 1))
    cam = Camera(torch.tensor(K_ODD, dtype=torch.float64), 1.5).scaled(1 / k)
    # the scaled camera's map: u' = f_x' x + ..., so u = (u' - c_x') / s + c_x with the same ray
    target = np.arange(W // k, dtype=np.float64)
    centre = (target - float(cam.cx[0])) * k + K_ODD[0][2]
    np.testing.assert_allclose(centre, (target + 0.5) * k - 0.5, atol=1e-12)
    torch_image = torch.from_numpy(image)[None, None]
    floor = cv2.resize(image, (W // k, 3), interpolation=cv2.INTER_NEAREST)[0]
    np.testing.assert_array_equal(floor, F.interpolate(torch_image, size=(3, W // k), mode="nearest")[0, 0, 0])
    np.testing.assert_allclose(centre - floor, (k - 1) / 2, atol=1e-12)
    for exact in (cv2.resize(image, (W // k, 3), interpolation=cv2.INTER_NEAREST_EXACT)[0],
                  F.interpolate(torch_image, size=(3, W // k), mode="nearest-exact")[0, 0, 0].numpy()):
        assert np.abs(centre - exact).max() <= 0.5


@pytest.mark.parametrize("s", [0.5, 1 / 3])
def test_scaled_by_the_factor_of_a_resize_by_a_factor(s):
    """Camera.scaled's docstring: a resize by a factor (F.interpolate(scale_factor=s),
    cv2.resize(fx=s)) maps coordinates by s itself while its output size is rounded (torch down,
    OpenCV to the nearest), so on an image whose size is no multiple of 1 / s the blob lands where
    ``scaled(s)`` projects the point, not where the ratio of the sizes would put it."""
    import cv2
    H, W = 377, 322  # (377 / 3 = 125.7: 125 rows by torch, 126 by OpenCV)
    K = torch.tensor(K_ODD, dtype=torch.float64)
    X = torch.tensor([0.3, 0.9, 5.0], dtype=torch.float64)
    image = _blob(K, X, H, W)
    expected = _project(Camera(K, 1.5).scaled(s).K[0], X)
    by_torch = F.interpolate(torch.from_numpy(image)[None, None], scale_factor=s, mode="bilinear",
                             align_corners=False, antialias=True)[0, 0].numpy()
    by_cv2 = cv2.resize(image, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    assert by_torch.shape == (math.floor(H * s), math.floor(W * s))
    assert by_cv2.shape == (round(H * s), round(W * s))
    for resized in (by_torch, by_cv2):
        h, w = resized.shape
        np.testing.assert_allclose(_centroid(resized), expected, atol=2e-3)
        # the ratio of the sizes (not s: they were rounded) is another camera, off by more than that
        by_ratio = _project(Camera(K, 1.5).scaled(w / W, h / H).K[0], X)
        assert np.abs(by_ratio - expected).max() > 0.05


def test_crop_pad_and_scale_move_the_principal_point_as_the_pixels_move():
    """Cropping by (l, t) moves every pixel by (-l, -t), padding by (+l, +t); cropping then
    scaling by s is scaling then cropping by (s l, s t) when those are whole pixels (an image of
    2x2 blocks averaged, cropped at even offsets); several cameras at once."""
    K = torch.tensor(K_ODD, dtype=torch.float64)
    cams = Camera(torch.stack([K, K * torch.tensor([[2.0, 2.0, 2.0], [1.0, 2.0, 2.0], [1.0, 1.0, 1.0]])]),
                  torch.tensor([1.5, 1.2], dtype=torch.float64))
    X = torch.tensor([-0.4, 0.3, 7.0], dtype=torch.float64)
    for b in range(2):
        p = _project(cams.K[b], X)
        np.testing.assert_allclose(_project(cams.cropped(10, 7, 3, 2).K[b], X), p - [10, 7], atol=1e-12)
        np.testing.assert_allclose(_project(cams.padded(3, 1, 3, 1).K[b], X), p + [3, 1], atol=1e-12)
    for s, (left, top) in ((0.5, (20, 10)), (0.25, (40, 16)), (2.0, (3, 5))):
        a = cams.cropped(left, top).scaled(s)
        b = cams.scaled(s).cropped(int(s * left), int(s * top))
        torch.testing.assert_close(a.K, b.K, rtol=0, atol=1e-12)
    # non-square: sx and sy each act on their own axis
    a = cams.cropped(20, 9).scaled(0.5, 1 / 3)
    b = cams.scaled(0.5, 1 / 3).cropped(10, 3)
    torch.testing.assert_close(a.K, b.K, rtol=0, atol=1e-12)


def test_K_inv_with_skew_is_the_inverse():
    K = torch.tensor(K_ODD, dtype=torch.float64)
    K2 = torch.tensor([[510.0, -3.0, 20.0], [0.0, 640.0, -15.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cams = Camera(torch.stack([K, K2]), 1.6)
    torch.testing.assert_close(cams.K_inv(), torch.linalg.inv(cams.K), rtol=0, atol=1e-15)


def test_kitti_projection_matrix_gives_K_and_the_camera_offset(shared_data):
    """P_rect_02 = K [I | t]: K its first three columns, and camera 2's centre -K⁻¹ P[:, 3] lies
    6 cm to the left of camera 0 (KITTI's rig), camera 3's 48 cm to the right of it."""
    path = shared_data / "kitti15_000000" / "calib_cam_to_cam.txt"
    for cam, centre_x in ((2, -0.0598), (3, 0.4729)):
        P = read_kitti_calibration(path, cam)
        camera = Camera.from_kitti(path, cam=cam)
        torch.testing.assert_close(camera.K[0], P[:, :3], rtol=0, atol=0)
        centre = -torch.linalg.solve(P[:, :3], P[:, 3])
        assert float(centre[0]) == pytest.approx(centre_x, abs=1e-4)
        assert float(centre[1:].abs().max()) < 5e-3


def _rotation(axis: int, a: float) -> torch.Tensor:
    c, s = math.cos(a), math.sin(a)
    R = {2: [[c, s, 0], [-s, c, 0], [0, 0, 1]], 0: [[1, 0, 0], [0, c, s], [0, -s, c]],
         1: [[c, 0, -s], [0, 1, 0], [s, 0, c]]}[axis]
    return torch.tensor(R, dtype=torch.float64)


@pytest.mark.parametrize("motion", [
    {"pitch_change": 0.02, "yaw": 0.3, "roll_change": -0.03, "x_d": 0.4, "y_d": 0.05, "z_d": 2.0},
    {"yaw": -0.6, "x_d": -1.0, "z_d": 0.5},
    {"pitch_change": -0.1, "roll_change": 0.1, "y_d": -0.2, "z_d": -1.5},
])
def test_road_flow_is_kornias_projection_of_the_moved_road_point(motion):
    """Each pixel's ray (kornia's unprojection) meets the road y = h of the vehicle frame (camera =
    R_roll R_pitch vehicle); the point moves as p' = R_v (p - d) and kornia projects it: the flow
    is that displacement, and valid exactly where the point is in front of both cameras. (kornia's
    projection reads f_x, f_y, c_x, c_y and ignores a skew: the camera here has none. Its
    ``project_points`` is taken apart to divide by z exactly, ``eps=0``: kornia 0.8 divides by
    z + 1e-8, 2e-5 px off here.)"""
    import kornia.geometry.camera as kornia_camera
    from kornia.geometry.conversions import convert_points_from_homogeneous, denormalize_points_with_intrinsics
    K = torch.tensor([[300.0, 0.0, 161.3], [0.0, 280.0, 97.7], [0.0, 0.0, 1.0]], dtype=torch.float64)
    h, roll, pitch = 1.4, 0.05, -0.08
    cam = Camera(K, h, roll, pitch)
    H, W = 190, 330
    flow, valid = road_flow(cam, motion, (H, W), model="plane")
    Rc = _rotation(2, roll) @ _rotation(0, pitch)
    Rv = _rotation(2, motion.get("roll_change", 0.0)) @ _rotation(0, motion.get("pitch_change", 0.0)) @ _rotation(
        1, motion.get("yaw", 0.0))
    d = torch.tensor([motion.get(k, 0.0) for k in ("x_d", "y_d", "z_d")], dtype=torch.float64)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    pixels = torch.stack([u, v], dim=-1).reshape(-1, 2)
    rays = kornia_camera.unproject_points(pixels, torch.ones(len(pixels), 1, dtype=torch.float64), K)  # z = 1
    rays_v = rays @ Rc  # (Rcᵀ r)ᵀ = rᵀ Rc
    below = rays_v[:, 1] > 0
    points = rays_v * (h / torch.where(below, rays_v[:, 1], 1.0)).unsqueeze(-1)
    moved = ((points - d) @ Rv.T) @ Rc.T
    front = below & (moved[:, 2] > 0)
    projected = denormalize_points_with_intrinsics(
        convert_points_from_homogeneous(torch.where(front.unsqueeze(-1), moved, 1.0), eps=0.0), K)
    expected = (projected - pixels).T.reshape(2, H, W)
    assert torch.equal(valid[0, 0], front.reshape(H, W))
    assert int(front.sum()) > 1000
    ok = valid[0, 0]
    torch.testing.assert_close(flow[0][:, ok], expected[:, ok], rtol=1e-9, atol=1e-7)
    assert float(flow[0][:, ~ok].abs().max()) == 0.0


# KITTI's P_rect_02 and P_rect_03 (drive 2011_09_26): P_N = K [I | t_N] maps camera 0's rectified
# coordinates to camera N's pixels
KITTI_P = {
    2: [[721.5377, 0.0, 609.5593, 44.85728], [0.0, 721.5377, 172.854, 0.2163791], [0.0, 0.0, 1.0, 0.002745884]],
    3: [[721.5377, 0.0, 609.5593, -339.5242], [0.0, 721.5377, 172.854, 2.199936], [0.0, 0.0, 1.0, 0.002729905]],
}


@pytest.mark.parametrize("cam", [2, 3])
def test_kitti_camera_n_poses_give_the_flow_its_projection_matrix_sees(cam):
    """KITTI's poses are camera 0's (camera-to-world). The reference: each pixel of camera N at t,
    back-projected through P_N (its centre is P_N's null vector), meets the world's road y = 1.35;
    P_N projects that point from camera 0's pose at t+1. The library's recipe
    (docs/data-formats.md): camera N's poses are pose @ [[I, c], [0, 1]], c = -K⁻¹ P_N[:, 3]; the
    camera's height and attitude over the road at t from its pose; plane_from_pose of the relative
    pose, road_flow of the plane model. They agree to rounding; camera 0's poses as they are miss
    camera 3's road by pixels (its 47 cm offset turned by the yaw)."""
    from fsof_torch import plane_from_pose, relative_pose

    P = np.array(KITTI_P[cam])
    K = P[:, :3]
    centre = np.append(-np.linalg.solve(K, P[:, 3]), 1.0)  # P @ centre = 0
    assert float(centre[0]) == pytest.approx(-0.0598 if cam == 2 else 0.4729, abs=1e-4)
    pose0 = np.eye(4)
    pose0[:3, :3] = (_rotation(2, 0.02) @ _rotation(0, -0.015)).numpy().T  # camera 0 rolled and pitched
    pose0[:3, 3] = [1.0, -0.3, 5.0]
    step = np.eye(4)
    step[:3, :3] = (_rotation(1, 0.06).T @ _rotation(0, 0.004)).numpy()  # a turn and a body pitch
    step[:3, 3] = [0.1, 0.01, 1.3]
    pose1 = pose0 @ step
    road_y = 1.35
    H, W = 375, 1242
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    pixels = np.stack([u.ravel(), v.ravel(), np.ones(H * W)])
    # reference: rays of P_N in the world, the road point, projected by P_N from camera 0's pose at t+1
    origin = (pose0 @ centre)[:3]
    rays = pose0[:3, :3] @ np.linalg.solve(K, pixels)
    front = rays[1] > 0
    world = origin[:, None] + rays * ((road_y - origin[1]) / np.where(front, rays[1], 1.0))
    q = P @ (np.linalg.inv(pose1) @ np.vstack([world, np.ones(H * W)]))
    front &= q[2] > 0
    expected = (q[:2] / np.where(front, q[2], 1.0) - pixels[:2]).reshape(2, H, W)
    # the library's recipe
    offset = np.eye(4)
    offset[:3, 3] = centre[:3]
    own0, own1 = pose0 @ offset, pose1 @ offset
    normal = own0[:3, :3].T @ np.array([0.0, 1.0, 0.0])  # the road's normal in camera N's frame, R_c e_y
    camera = Camera(torch.from_numpy(K.copy()), road_y - own0[1, 3], math.atan2(normal[0], normal[1]),
                    -math.asin(normal[2]))
    for poses, exact in (((own0, own1), True), ((pose0, pose1), False)):
        T = relative_pose(*(torch.from_numpy(p)[None] for p in poses))
        flow, valid = road_flow(camera, plane_from_pose(T, camera), (H, W), model="plane")
        ok = valid[0, 0].numpy()
        error = np.abs(flow[0].numpy()[:, ok] - expected[:, ok]).max()
        if exact:
            assert (ok == front.reshape(H, W)).all() and ok.sum() > 0.4 * H * W
            assert error < 1e-9
        else:
            assert error > (0.3 if cam == 2 else 3.0)
