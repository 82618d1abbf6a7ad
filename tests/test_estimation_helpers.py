"""The estimation package's helpers at their edges: a batch's homography decompositions each as if
alone, the pyramid's torch filters against OpenCV's at any image size, the CPU filters on any
layout and float dtype, the flow's planar start on broken pixels and wrong inputs, the robust
kernels' scale, and the turn screen's starts (fsof_torch.estimation: decompose, pyramid,
initial, robust, starts, confidence)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fsof_torch import Camera, decompose_homography, road_flow, road_homography
from fsof_torch.estimation import pyramid as P
from fsof_torch.estimation.confidence import backward_correlation, detail_correlation, matched_gain, warped_samples
from fsof_torch.estimation.initial import homography_dlt, planar_motion, planar_start
from fsof_torch.estimation.sampling import mask_pixels, pixel_coordinates, points_grid, reused_mask_pixels, sample_mask
from fsof_torch.estimation.robust import ROBUST_KERNELS, robust_cost, robust_weight
from fsof_torch.estimation.starts import screened_start, turn_moves
from fsof_torch.geometry.road_models import get_road_model, pack_params

K_KITTI = [[721.5, 0.0, 609.6], [0.0, 721.5, 172.9], [0.0, 0.0, 1.0]]


# -- decompose_homography ------------------------------------------------------------------------

def _two_cameras() -> Camera:
    K = torch.tensor(K_KITTI, dtype=torch.float64)
    K2 = K.clone()
    K2[0, 2], K2[1, 2] = 200.0, 100.0  # a crop: the principal point elsewhere, a smaller virtual image
    return Camera(torch.stack([K, K2]), torch.full((2,), 1.65, dtype=torch.float64),
                  torch.full((2,), 0.01, dtype=torch.float64), torch.full((2,), -0.02, dtype=torch.float64))


@pytest.mark.parametrize("perturb", [False, True], ids=["rigid", "out_of_reach"])
def test_decompose_homography_batch_gives_each_sample_its_own_result(perturb):
    cam = _two_cameras()
    H = road_homography(cam, {"z_d": 1.2, "pitch_change": 0.002, "y_d": 0.01, "yaw": 0.01}, model="plane")
    if perturb:
        # the motion of a plane about 17° from the first camera's attitude (OpenCV's decomposition),
        # out of its reach: its residual is in its own grid's pixels; 10° from the second's: found
        H = H.clone()
        H[:, 0, 1] += 0.02
        H[:, 2, 0] += 2e-4
    both = decompose_homography(H, cam)
    for i in range(2):
        alone = decompose_homography(H[i:i + 1], Camera(cam.K[i:i + 1], cam.height[i:i + 1],
                                                        cam.roll[i:i + 1], cam.pitch[i:i + 1]))
        for k, v in alone.params.items():
            torch.testing.assert_close(both.params[k][i:i + 1], v, atol=1e-9, rtol=1e-9)
        # the residual is in the sample's own grid pixels (not a grid shared with its batch-mates)
        torch.testing.assert_close(both.residual[i:i + 1], alone.residual, atol=1e-9, rtol=1e-9)
        torch.testing.assert_close(both.camera.K[i:i + 1], alone.camera.K, atol=0.0, rtol=0.0)
        h, w = alone.valid.shape[-2:]
        assert torch.equal(both.valid[i:i + 1, :, :h, :w], alone.valid)
        assert not bool(both.valid[i, :, h:].any()) and not bool(both.valid[i, :, :, w:].any())
        torch.testing.assert_close(both.flow[i:i + 1, :, :h, :w], alone.flow, atol=1e-9, rtol=0.0)
        assert float(both.flow[i, :, h:].abs().sum()) == 0.0 and float(both.flow[i, :, :, w:].abs().sum()) == 0.0
    if perturb:  # (measured alone: 1.79 grid pixels, and exact: its plane's homography is H)
        assert float(both.residual[0]) > 0.5 and float(both.residual[1]) < 1e-9 and bool(both.success[1])
        second = Camera(cam.K[1:], cam.height[1:], cam.roll[1:], cam.pitch[1:])
        H1 = road_homography(second, {k: v[1:] for k, v in both.params.items()}, model="plane")
        torch.testing.assert_close(H1 / H1[:, 2:, 2:], H[1:] / H[1:, 2:, 2:], atol=1e-9, rtol=0)
    else:
        assert float(both.residual.max()) < 1e-9
        assert both.params["z_d"].tolist() == pytest.approx([1.2, 1.2], abs=1e-9)
    # each grid's longer side is ``size``
    assert max(both.valid.shape[-2:]) == 192


def _rotation(axis: int, a: float) -> np.ndarray:
    """The road models' elementary rotations (roll about z, pitch about x, yaw about y)."""
    c, s = math.cos(a), math.sin(a)
    return {2: np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]), 0: np.array([[1, 0, 0], [0, c, s], [0, -s, c]]),
            1: np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])}[axis]


def _plane_homography(K: np.ndarray, h: float, p: dict) -> np.ndarray:
    """K (R + t nᵀ / h) K⁻¹ of a camera mounted at roll, pitch over the road plane nᵀX = h that
    turns by (roll_change, pitch_change, yaw) in the road's frame and moves by d = (x_d, y_d, z_d)
    there: X' = R X + t, written here without the library (DESIGN.md §10)."""
    Rc = _rotation(2, p["roll"]) @ _rotation(0, p["pitch"])
    Rv = _rotation(2, p["roll_change"]) @ _rotation(0, p["pitch_change"]) @ _rotation(1, p["yaw"])
    R, t = Rc @ Rv @ Rc.T, -Rc @ Rv @ np.array([p["x_d"], p["y_d"], p["z_d"]])
    n = Rc @ np.array([0.0, 1.0, 0.0])
    return K @ (R + np.outer(t, n) / h) @ np.linalg.inv(K)


@pytest.mark.parametrize("droll, dpitch", [(1.0, 0.0), (0.0, -3.0), (-3.0, 2.0), (2.0, 3.0), (5.0, 5.0),
                                           (-5.0, -5.0), (5.0, -5.0), (-5.0, 5.0)])
def test_decompose_homography_is_exact_for_a_road_tilted_from_the_camera(droll, dpitch):
    """The road's attitude degrees from the camera's (the roll and pitch the decomposition starts
    from): the decomposition is still exact. (Its grid was the pixels below the camera's horizon:
    those between that and the road's horizon cost as far outliers, and a road 1° off was fitted
    with a residual of 0.6 px, its roll left at the camera's.)"""
    K = np.array(K_KITTI)
    p = {"pitch_change": 0.002, "yaw": 0.01, "roll_change": 0.001, "x_d": 0.05, "y_d": 0.01, "z_d": 1.2,
         "roll": 0.01 + math.radians(droll), "pitch": -0.015 + math.radians(dpitch)}
    H = torch.from_numpy(_plane_homography(K, 1.65, p))[None]
    cam = Camera(torch.from_numpy(K), 1.65, roll=0.01, pitch=-0.015)
    fit = decompose_homography(2.5 * H, cam)
    assert bool(fit.success) and float(fit.residual) < 1e-10
    for k, v in p.items():
        assert float(fit.params[k]) == pytest.approx(v, abs=1e-8), k


@pytest.mark.parametrize("z_d", [8.0, 10.0, 15.0])
@pytest.mark.parametrize("yaw, x_d", [(0.0, 0.0), (0.1, 2.0), (0.3, 0.0)])
def test_decompose_homography_of_a_long_step_succeeds(z_d, yaw, x_d):
    """A forward step of several camera heights (frames far apart): only the road beyond the step is
    ahead of both cameras, and the grid's pixels just beyond it map arbitrarily far at t+1. Their flow
    left the exact decomposition ill-conditioned: from 8 m on a KITTI camera at 1.65 m the parameters
    were right to 1e-13 and success was False. The grid now keeps the pixels that H takes to within
    its own size beyond its edges. A homography without translation fixes no road attitude: no success."""
    K = np.array(K_KITTI)
    p = {"pitch_change": 0.002, "yaw": yaw, "roll_change": -0.001, "x_d": x_d, "y_d": 0.02, "z_d": z_d,
         "roll": 0.01, "pitch": -0.02}
    cam = Camera(torch.from_numpy(K), 1.65, roll=0.01, pitch=-0.02)
    fit = decompose_homography(torch.from_numpy(_plane_homography(K, 1.65, p))[None], cam)
    assert bool(fit.success) and float(fit.residual) < 1e-10
    for k, v in p.items():
        assert float(fit.params[k]) == pytest.approx(v, abs=1e-9), k
    still = {**p, "x_d": 0.0, "y_d": 0.0, "z_d": 0.0}
    assert not bool(decompose_homography(torch.from_numpy(_plane_homography(K, 1.65, still))[None], cam).success)


@pytest.mark.parametrize("roll, pitch, motion", [
    (0.0, -0.015, {"z_d": -8.0}),                           # reversing: pixel (0, 0)'s road point behind at t
    (0.0, 0.2, {"z_d": -4.0}),                              # looking up
    (0.3, 0.0, {"z_d": -3.5, "yaw": 0.05, "x_d": -0.3}),    # rolled
])
@pytest.mark.parametrize("sign", [1.0, -2.0])
def test_decompose_homography_where_h33_is_negative(roll, pitch, motion, sign):
    """H[2, 2] is q_z at pixel (0, 0): negative at H's physical scale when that pixel's road point
    (above the horizon: the plane behind the camera) comes in front of the camera at t+1. Dividing
    H by it flipped the sign of q_z everywhere: the grid (pixels with q_z > 0) was empty, and the
    closed form came back unrefined with success False and a residual of 0 over no pixel."""
    K = np.array(K_KITTI)
    p = {"pitch_change": 0.0, "yaw": 0.0, "roll_change": 0.0, "x_d": 0.0, "y_d": 0.0, "z_d": 0.0,
         "roll": roll, "pitch": pitch, **motion}
    H = _plane_homography(K, 1.65, p)
    assert H[2, 2] < 0
    cam = Camera(torch.from_numpy(K), 1.65, roll=roll, pitch=pitch)
    fit = decompose_homography(sign * torch.from_numpy(H)[None], cam)
    assert bool(fit.success) and float(fit.residual) < 1e-10 and int(fit.valid.sum()) > 500
    for k, v in p.items():
        assert float(fit.params[k]) == pytest.approx(v, abs=1e-8), k


def test_decompose_homography_takes_a_road_homography_with_h33_zero():
    """H[2, 2] = 0 (pixel (0, 0) on the line the road maps to infinity) is an invertible road
    homography like any other; it was refused (the decomposition divided by H[2, 2]). Reversing,
    that line lies above the horizon (the plane behind the camera): a camera padded at the top."""
    K = np.array(K_KITTI)
    p = {"pitch_change": 0.002, "yaw": 0.01, "roll_change": 0.0, "x_d": 0.05, "y_d": 0.0, "z_d": -4.0,
         "roll": 0.01, "pitch": -0.015}
    H = _plane_homography(K, 1.65, p)
    # the same road seen by a camera whose pixel (0, 0) lies on the line H[2] · p̃ = 0
    u0 = 0.0
    v0 = -(H[2, 0] * u0 + H[2, 2]) / H[2, 1]
    T = np.array([[1.0, 0.0, u0], [0.0, 1.0, v0], [0.0, 0.0, 1.0]])
    H0 = np.linalg.inv(T) @ H @ T
    assert abs(H0[2, 2]) < 1e-12
    H0[2, 2] = 0.0
    K0 = np.linalg.inv(T) @ K
    cam = Camera(torch.from_numpy(K0), 1.65, roll=0.01, pitch=-0.015)
    fit = decompose_homography(torch.from_numpy(H0)[None], cam)
    assert bool(fit.success) and float(fit.residual) < 1e-9
    for k, v in p.items():
        assert float(fit.params[k]) == pytest.approx(v, abs=1e-7), k


def test_decompose_homography_agrees_with_opencv_where_opencv_has_an_answer():
    """OpenCV's closed form (cv2.decomposeHomographyMat) on the same homographies: of its four
    solutions the physical one has the road's normal pointing down in the camera (n_y > 0) and
    is the one nearest the camera's attitude; its R, t h and n are the decomposition's."""
    import cv2
    K = np.array(K_KITTI)
    cases = [{"pitch_change": 0.02, "yaw": 0.3, "roll_change": -0.03, "x_d": 0.4, "y_d": 0.05, "z_d": 2.0,
              "roll": 0.02, "pitch": -0.03},
             {"pitch_change": 0.0, "yaw": -0.2, "roll_change": 0.0, "x_d": -0.5, "y_d": 0.0, "z_d": 0.8,
              "roll": 0.0, "pitch": -0.02}]
    for p in cases:
        H = _plane_homography(K, 1.65, p)
        _, Rs, ts, ns = cv2.decomposeHomographyMat(H, K)
        Rc = _rotation(2, p["roll"]) @ _rotation(0, p["pitch"])
        candidates = [(R, t[:, 0] * 1.65, n[:, 0]) for R, t, n in zip(Rs, ts, ns) if n[1, 0] > 0]
        R_cv, t_cv, n_cv = min(candidates, key=lambda c: np.abs(c[2] - Rc[:, 1]).max())
        assert np.isfinite(R_cv).all()
        fit = decompose_homography(torch.from_numpy(H)[None], Camera(torch.from_numpy(K), 1.65))
        q = {k: float(v) for k, v in fit.params.items()}
        Rc_fit = _rotation(2, q["roll"]) @ _rotation(0, q["pitch"])
        Rv = _rotation(2, q["roll_change"]) @ _rotation(0, q["pitch_change"]) @ _rotation(1, q["yaw"])
        d = np.array([q["x_d"], q["y_d"], q["z_d"]])
        np.testing.assert_allclose(Rc_fit @ Rv @ Rc_fit.T, R_cv, atol=1e-9)
        np.testing.assert_allclose(-Rc_fit @ Rv @ d, t_cv, atol=1e-8)
        np.testing.assert_allclose(Rc_fit[:, 1], n_cv, atol=1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16, torch.float64])
def test_decompose_homography_returns_the_inputs_dtype(dtype):
    """Values in H's dtype promoted with the camera's, float32 for half precision (the fit runs in
    float64: they were all float64)."""
    cam = Camera(torch.tensor(K_KITTI), 1.65, roll=0.01)
    H = road_homography(cam.to(torch.float64), {"z_d": 1.2, "yaw": 0.01, "roll": 0.01}, model="plane").to(dtype)
    fit = decompose_homography(H, cam)
    expected = torch.float64 if dtype == torch.float64 else torch.float32
    for t in (*fit.params.values(), fit.homography, fit.flow, fit.residual, fit.covariance, fit.cost, fit.camera.K,
              fit.camera.roll):
        assert t.dtype == expected
    assert bool(fit.success) and float(fit.z_d) == pytest.approx(1.2, abs=1e-2 if dtype.itemsize == 2 else 1e-5)


def test_decompose_homography_gives_the_homography_of_its_scaled_camera():
    """As its docstring says: fit.homography is the plane's homography for fit.camera (the grid's
    scaled camera), not H: S⁻¹ fit.homography S is H up to scale, S = fit.camera.K camera.K⁻¹."""
    cam = _two_cameras()
    H = road_homography(cam, {"z_d": 1.2, "yaw": 0.01, "x_d": 0.05}, model="plane")
    fit = decompose_homography(H, cam)
    S = fit.camera.K @ torch.linalg.inv(cam.K)
    back = torch.linalg.inv(S) @ fit.homography @ S
    torch.testing.assert_close(back / back[:, 2:, 2:], H / H[:, 2:, 2:], rtol=0, atol=1e-9)
    assert float((fit.homography / fit.homography[:, 2:, 2:] - H / H[:, 2:, 2:]).abs().max()) > 1.0


# -- the pyramid's torch path (what a GPU tensor takes) against OpenCV's -------------------------

@pytest.mark.parametrize("n", [1, 2, 3, 4, 6])
def test_reflect101_padding_is_numpys_reflect_at_any_pad(n):
    x = torch.arange(float(n)).reshape(1, 1, 1, n)
    for pad in (0, 1, 2, n - 1, n, n + 1, 3 * n + 2):
        want = np.pad(np.arange(float(n)), pad, mode="reflect")  # (reflect-101: the edge not repeated)
        assert P._reflect101(x, 3, pad).flatten().tolist() == want.tolist(), (n, pad)
        assert P._reflect101(x.transpose(2, 3), 2, pad).flatten().tolist() == want.tolist(), (n, pad)


@pytest.mark.parametrize("size", [(1, 1), (1, 7), (2, 2), (3, 5), (5, 3), (8, 8), (12, 40), (13, 2)])
def test_torch_path_matches_opencv_on_tiny_images(size):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, *size, generator=g)
    for sigma in (0.5, 1.0, 4.0):  # (σ = 4: a kernel of 25 taps, a pad of 12 >= either side)
        torch.testing.assert_close(P._gaussian_blur_torch(x, sigma), P._gaussian_blur_cv2(x, sigma),
                                   atol=2e-6, rtol=0.0)
    cv, th = P._pyramid_cv2(x, 5), P._pyramid_torch(x, 5)  # (down to levels of one pixel)
    assert [t.shape for t in th] == [t.shape for t in cv]
    assert th[-1].shape[-2:] == ((size[0] + 15) // 16, (size[1] + 15) // 16)
    for a, b in zip(th, cv):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=0.0)
    # the public functions take the OpenCV path on the CPU
    assert torch.equal(P.gaussian_blur(x, 4.0), P._gaussian_blur_cv2(x, 4.0))
    assert all(torch.equal(a, b) for a, b in zip(P.image_pyramid(x, 5, 0.0)[1:], cv))



@pytest.mark.parametrize("size", [(1, 1), (2, 3), (7, 5), (30, 41)])
def test_other_devices_paths_of_the_masks_and_filters_are_the_cpus(size):
    """Under ``device_paths`` (what a GPU tensor takes, run on the CPU) each part gives what the
    CPU's OpenCV or NumPy path gives, at the borders too: the mask pyramid's erosion (a min-pool),
    the search of a mask's pixels (``nonzero``), the auto road's box means (two average pools,
    the border replicated) and its erosion (a min-pool), and the road flow without the CPU's scan
    of the rows that hold no valid pixel."""
    from fsof_torch._check import device_paths
    from fsof_torch.refinement.auto_road import _box
    from fsof_torch.refinement.road_region import erode_mask

    g = torch.Generator().manual_seed(size[0] * 100 + size[1])
    mask = torch.rand(2, 1, *size, generator=g) > 0.3
    x = torch.rand(2, 3, *size, generator=g)
    cam = Camera(torch.tensor([[70.0, 0, 40], [0, 70, 20], [0, 0, 1]]), 1.65)  # (the horizon at row 20)
    params = {"x_d": torch.tensor([0.1]), "z_d": torch.tensor([1.2]), "yaw": torch.tensor([0.01])}

    def parts():
        return (P.mask_pyramid(mask, 4), mask_pixels(mask), _box(x, 5), _box(x, 1), erode_mask(mask, 3),
                erode_mask(mask, 5), road_flow(cam, params, (60, 80), model="paper")[0])

    host = parts()
    with device_paths():
        other = parts()
    for a, b in zip(host[0], other[0]):
        assert torch.equal(a, b)
    assert torch.equal(host[1], other[1])
    for a, b in zip(host[2:4], other[2:4]):
        torch.testing.assert_close(b, a, atol=2e-6, rtol=0.0)
    assert torch.equal(host[4], other[4]) and torch.equal(host[5], other[5])
    torch.testing.assert_close(other[6], host[6], atol=0.0, rtol=0.0, equal_nan=True)
    # and the paths differ: outside the block the CPU's run, inside it the others'
    with device_paths():
        assert torch.equal(P.gaussian_blur(x, 4.0), P._gaussian_blur_torch(x, 4.0))
    assert torch.equal(P.gaussian_blur(x, 4.0), P._gaussian_blur_cv2(x, 4.0))

def test_torch_blur_is_kornias_where_kornia_can_pad():
    from kornia.filters import gaussian_blur2d

    x = torch.rand(2, 1, 30, 40, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    for sigma in (1.0, 4.0):
        k = 2 * math.ceil(3 * sigma) + 1
        torch.testing.assert_close(P._gaussian_blur_torch(x, sigma),
                                   gaussian_blur2d(x, (k, k), (sigma, sigma), border_type="reflect"),
                                   atol=1e-12, rtol=0.0)


# -- the CPU path on any layout, float dtype and autograd state ------------------------------------

def _layouts(x):
    return {
        "channels_last": x.contiguous(memory_format=torch.channels_last),
        "transposed": x.transpose(-1, -2).contiguous().transpose(-1, -2),  # dense, not contiguous
        "strided": torch.stack([x, x], dim=-1)[..., 0],
    }


def test_cpu_filters_take_any_dense_or_strided_layout():
    x = torch.rand(2, 3, 20, 30, generator=torch.Generator().manual_seed(2)) * 255
    blur, pyr, bnd = P.gaussian_blur(x, 2.0), P.image_pyramid(x, 3, 1.0), P.band(x, 4.0)
    for name, y in _layouts(x).items():
        assert torch.equal(P.gaussian_blur(y, 2.0), blur), name
        assert all(torch.equal(a, b) for a, b in zip(P.image_pyramid(y, 3, 1.0), pyr)), name
        assert all(torch.equal(a, b) for a, b in zip(P.image_pyramid(y, 3, 0.0)[1:], P.image_pyramid(x, 3, 0.0)[1:]))
        assert torch.equal(P.band(y, 4.0), bnd), name
        assert torch.equal(y, _layouts(x)[name])  # the caller's tensor is not written


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_cpu_filters_take_16_bit_floats(dtype):
    x = torch.rand(1, 2, 20, 30, generator=torch.Generator().manual_seed(3))
    y = x.to(dtype)
    ref = y.to(torch.float32)  # the same values, filtered in float32, rounded back
    tol = dict(atol=0.0, rtol=0.0)
    torch.testing.assert_close(P.gaussian_blur(y, 2.0), P.gaussian_blur(ref, 2.0).to(dtype), **tol)
    for smooth in (0.0, 1.0):
        got = P.image_pyramid(y, 3, smooth)
        assert [t.dtype for t in got] == [dtype] * 3
        assert [t.shape[-2:] for t in got] == [(20, 30), (10, 15), (5, 8)]
        assert got[0] is y if smooth == 0 else torch.equal(got[0], P.gaussian_blur(ref, smooth).to(dtype))
        # the coarser levels from level 0 in float32, each rounded back
        for a, b in zip(got[1:], P.image_pyramid(got[0].to(torch.float32), 3, 0.0)[1:]):
            torch.testing.assert_close(a, b.to(dtype), **tol)
    torch.testing.assert_close(P.band(y, 4.0), P.band(y, 4.0).to(torch.float32).to(dtype), **tol)
    assert P.band(y, 4.0).dtype == dtype


def test_cpu_filters_take_a_tensor_requiring_grad():
    x = torch.rand(1, 1, 20, 30, generator=torch.Generator().manual_seed(4))
    xg = x.clone().requires_grad_()
    torch.testing.assert_close(P.gaussian_blur(xg, 2.0), P.gaussian_blur(x, 2.0), atol=0.0, rtol=0.0)
    for smooth in (0.0, 1.0):
        for a, b in zip(P.image_pyramid(xg, 3, smooth), P.image_pyramid(x, 3, smooth)):
            torch.testing.assert_close(a.detach(), b, atol=0.0, rtol=0.0)
    assert P.image_pyramid(xg, 3, 0.0)[0] is xg  # level 0 is the images themselves
    b = P.band(xg, 4.0)
    torch.testing.assert_close(b.detach(), P.band(x, 4.0), atol=0.0, rtol=0.0)
    b.sum().backward()  # (the blur is a constant on the CPU: d band / d img = 1)
    assert torch.equal(xg.grad, torch.ones_like(x))


# -- band inside a mask ----------------------------------------------------------------------------

def _masked_band_reference(img: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """The band inside ``mask`` written out: at each pixel, the image minus the Gaussian-weighted
    mean of the mask's pixels around it (weights g(dy) g(dx) over ±⌈3σ⌉, reflected at the border
    without repeating the edge), or minus the plain weighted mean where the mask's share of the
    weights is below 0.05. ``img`` and ``mask`` (H, W)."""
    r = math.ceil(3 * sigma)
    g = np.exp(-np.arange(-r, r + 1) ** 2 / (2 * sigma ** 2))
    g /= g.sum()
    im, m = np.pad(img, r, mode="reflect"), np.pad(mask.astype(np.float64), r, mode="reflect")
    H, W = img.shape
    out = np.empty_like(img)
    w = np.outer(g, g)
    for y in range(H):
        for x in range(W):
            wm = w * m[y:y + 2 * r + 1, x:x + 2 * r + 1]
            patch = im[y:y + 2 * r + 1, x:x + 2 * r + 1]
            mean = (wm * patch).sum() / wm.sum() if wm.sum() >= 0.05 else (w * patch).sum()
            out[y, x] = img[y, x] - mean
    return out


@pytest.mark.parametrize("host", [True, False], ids=["opencv", "torch"])
def test_band_inside_a_mask_is_the_normalised_convolution(monkeypatch, host):
    """``band(img, sigma, mask)`` against the weighted means written out per pixel, for a mask per
    channel (two frames, each its own) and one broadcast over the channels and the batch, on
    OpenCV's path and on torch's."""
    if not host:
        monkeypatch.setattr(P, "host_path", lambda t: False)
    g = torch.Generator().manual_seed(11)
    img = torch.rand(2, 2, 14, 17, generator=g, dtype=torch.float64) * 255
    own = torch.rand(2, 2, 14, 17, generator=g) > 0.4
    own[0, 0, :, 9:] = False  # (pixels more than 1.6 σ from the mask: the plain mean there)
    shared = own[:1, :1]
    for mask in (own, shared):
        got = P.band(img, 1.5, mask)
        assert got.shape == img.shape and got.dtype == img.dtype
        if mask is own:
            torch.testing.assert_close(got[0, 0, :, -1], P.band(img, 1.5)[0, 0, :, -1], rtol=0, atol=1e-9)
        for b in range(2):
            for c in range(2):
                m = mask[min(b, mask.shape[0] - 1), min(c, mask.shape[1] - 1)].numpy()
                np.testing.assert_allclose(got[b, c].numpy(), _masked_band_reference(img[b, c].numpy(), m, 1.5),
                                           rtol=0, atol=1e-9)


def test_band_inside_a_mask_ignores_what_lies_outside_it():
    """Whatever lies outside the mask (a kerb, a wall, a car beside the road) leaves the band of
    the pixels inside as it was; a mask of every pixel gives the plain band; the caller's tensors
    are not written."""
    g = torch.Generator().manual_seed(12)
    img = torch.rand(1, 2, 40, 60, generator=g, dtype=torch.float64) * 255
    mask = torch.zeros(1, 1, 40, 60, dtype=torch.bool)
    mask[..., 15:, 10:45] = True
    other = torch.where(mask, img, torch.rand(img.shape, generator=g, dtype=torch.float64) * 255)
    before = (img.clone(), mask.clone())
    a, b = P.band(img, 4.0, mask), P.band(other, 4.0, mask)
    inside = mask.expand_as(img)
    torch.testing.assert_close(a[inside], b[inside], rtol=0, atol=1e-9)
    assert not torch.allclose(P.band(img, 4.0)[inside], P.band(other, 4.0)[inside])  # (the plain band takes it in)
    torch.testing.assert_close(P.band(img, 4.0, torch.ones_like(mask)), P.band(img, 4.0), rtol=0, atol=1e-9)
    assert torch.equal(img, before[0]) and torch.equal(mask, before[1])


# -- planar_start --------------------------------------------------------------------------------

SIZE = (60, 160)


def _small_flow():
    cam = Camera(torch.tensor(K_KITTI, dtype=torch.float64), 1.65, roll=0.01, pitch=-0.02).scaled(0.125)
    truth = {"x_d": 0.05, "z_d": 1.1, "yaw": 0.01}
    flow, valid = road_flow(cam, truth, SIZE, model="paper")
    return flow.to(torch.float32), valid, cam, truth


def test_planar_start_leaves_out_non_finite_flow():
    flow, mask, cam, truth = _small_flow()
    clean = planar_start(flow, mask, cam)
    assert [float(clean[k]) for k in truth] == pytest.approx(list(truth.values()), abs=1e-4)
    pixels = mask[0, 0].nonzero()
    (y0, x0), (y1, x1) = pixels[0].tolist(), pixels[len(pixels) // 2].tolist()
    broken = flow.clone()
    broken[0, :, y0, x0] = float("nan")
    broken[0, 1, y1, x1] = float("inf")  # (one component is enough to spoil the pixel)
    without = mask.clone()
    without[0, 0, y0, x0] = without[0, 0, y1, x1] = False
    for points in (2048, 100):  # (all the mask's pixels; an even subsample of them)
        got, want = planar_start(broken, mask, cam, points), planar_start(flow, without, cam, points)
        for k in truth:
            torch.testing.assert_close(got[k], want[k], atol=1e-12, rtol=0.0)
            assert float(got[k]) == pytest.approx(truth[k], abs=1e-3)
    assert torch.isnan(broken[0, 0, y0, x0])  # the caller's flow is not repaired in place


def test_planar_start_carries_the_cameras_gradient():
    # (the flow is detached, the camera is not: z_d = (z_d / h) h)
    flow, mask, cam, truth = _small_flow()
    height = torch.tensor([1.65], dtype=torch.float64, requires_grad=True)
    got = planar_start(flow, mask, Camera(cam.K, height, cam.roll, cam.pitch))
    got["z_d"].sum().backward()
    assert float(height.grad) == pytest.approx(float(got["z_d"].detach()) / 1.65, rel=1e-12)


def test_planar_start_batch_and_broadcast_mask():
    flow, mask, cam, truth = _small_flow()
    got = planar_start(torch.cat([flow, flow]), mask, cam.expand(2))  # (mask batch 1: broadcast)
    for k in truth:
        assert got[k].shape == (2,)
        assert got[k].tolist() == pytest.approx([truth[k]] * 2, abs=1e-4)
    # a non-finite pixel in the second frame only: left out of that frame's mask, not the first's
    y0, x0 = mask[0, 0].nonzero()[0].tolist()
    broken = torch.cat([flow, flow])
    broken[1, 0, y0, x0] = float("nan")
    without = mask.clone()
    without[0, 0, y0, x0] = False
    got = planar_start(broken, mask, cam.expand(2), 100)
    first, second = planar_start(flow, mask, cam, 100), planar_start(flow, without, cam, 100)
    for k in truth:
        assert got[k].tolist() == pytest.approx([float(first[k]), float(second[k])], abs=1e-12, rel=0)
        assert float(got[k][1]) == pytest.approx(truth[k], abs=1e-3)


def test_planar_start_names_wrong_inputs():
    flow, mask, cam, _ = _small_flow()
    H, W = SIZE
    with pytest.raises(ValueError, match=rf"mask: expected shape \(1, 1, {H}, {W}\).*got \(1, 1, {H - 10}, {W}\)"):
        planar_start(flow, mask[..., 10:, :], cam)  # (it was a silently wrong motion)
    with pytest.raises(ValueError, match=rf"mask: expected shape \(1, 1, {H}, {W - 1}\)"):
        planar_start(flow[..., :-1], mask, cam)
    with pytest.raises(ValueError, match=r"mask: expected shape \(2, 1"):
        planar_start(torch.cat([flow, flow]), torch.cat([mask, mask, mask]), cam)
    with pytest.raises(ValueError, match=r"mask: expected shape .*got \(1, 60, 160\)"):
        planar_start(flow, mask[0], cam)
    with pytest.raises(TypeError, match="mask: expected a bool tensor"):
        planar_start(flow, mask.float(), cam)
    with pytest.raises(ValueError, match=r"flow: expected shape \(B, 2, H, W\), got \(2, 60, 160\)"):
        planar_start(flow[0], mask, cam)
    with pytest.raises(TypeError, match="flow: expected a floating-point tensor, got dtype torch.int64"):
        planar_start(flow.long(), mask, cam)
    with pytest.raises(TypeError, match="flow: expected a torch.Tensor, got ndarray"):
        planar_start(flow.numpy(), mask, cam)
    with pytest.raises(TypeError, match="camera: expected a fsof_torch.Camera, got NoneType"):
        planar_start(flow, mask, None)
    with pytest.raises(ValueError, match="camera: expected batch 1 or 2 .*got 3"):
        planar_start(torch.cat([flow, flow]), mask, cam.expand(3))
    with pytest.raises(ValueError, match="points: expected an int >= 1, got 0"):
        planar_start(flow, mask, cam, 0)
    with pytest.raises(ValueError, match=r"flow: expected a non-empty batch, got shape \(0, 2, 60, 160\)"):
        planar_start(flow[:0], mask, cam)


# -- planar_motion, homography_dlt: points that are not real -------------------------------------

def test_linear_starts_ignore_whatever_the_points_that_are_not_real_hold():
    """A NaN at a point marked not real (sel False: a frame's padding) does not reach the sums:
    the result is that of the same points padded with zeros (it was the identity / zero motion,
    the frame marked degenerate)."""
    flow, mask, cam, truth = _small_flow()
    flow = torch.cat([flow, flow]).to(torch.float64)
    mask = torch.cat([mask, mask])
    mask[1, :, :40] = False  # (fewer pixels in frame 1: its points end in padding)
    points = sample_mask(mask, None)  # (every pixel: frame 1's run padded to frame 0's length)
    assert bool(points.sel[0].all()) and not bool(points.sel[1].all())
    pts = pixel_coordinates(points.pix, SIZE[1])
    real = points.sel.unsqueeze(1)
    zeros = torch.where(real, torch.gather(flow.flatten(2), 2, points.pix.unsqueeze(1).expand(-1, 2, -1)), 0.0)
    nan_pts, nan_flow = torch.where(real, pts, float("nan")), torch.where(real, zeros, float("nan"))
    c = cam.expand(2)
    want, want_good = planar_motion(c.K, c.K_inv(), c.roll, c.pitch, pts, zeros, points.sel)
    got, good = planar_motion(c.K, c.K_inv(), c.roll, c.pitch, nan_pts, nan_flow, points.sel)
    assert bool(want_good.all()) and torch.equal(good, want_good) and torch.equal(got, want)
    assert (want[:, 1] * 1.65).tolist() == pytest.approx([truth["z_d"]] * 2, abs=1e-6)
    want = homography_dlt(c.K, c.K_inv(), pts, zeros, points.sel)
    assert torch.equal(homography_dlt(c.K, c.K_inv(), nan_pts, nan_flow, points.sel), want)
    assert not torch.equal(want[1], torch.eye(3, dtype=want.dtype))


# -- warped_samples: one host read --------------------------------------------------------------

def test_warped_samples_reads_the_frames_bounds_once():
    """The frames' runs of points are read from the device once (one tolist), not twice per frame
    (int(bounds[b]) was a host sync per read on a GPU)."""
    from torch.overrides import TorchFunctionMode

    class HostReads(TorchFunctionMode):
        def __init__(self):
            super().__init__()
            self.reads = []

        def __torch_function__(self, func, types, args=(), kwargs=None):
            name = getattr(func, "__name__", "")
            if name in ("__int__", "__index__", "__float__", "__bool__", "item", "tolist"):
                self.reads.append(name)
            return func(*args, **(kwargs or {}))

    g = torch.Generator().manual_seed(0)
    B, H, W = 3, 16, 20
    image1, image2 = torch.rand(B, 1, H, W, generator=g), torch.rand(B, 2, H, W, generator=g)
    flow = torch.randn(B, 2, H, W, generator=g)
    points = sample_mask(torch.rand(B, 1, H, W, generator=g) > 0.3, None)
    valid = torch.ones(B, 1, H, W, dtype=torch.bool)
    with HostReads() as mode:
        I1, I2, ok = warped_samples((image1,), (image2,), flow, valid, points)
    assert mode.reads == ["tolist"]
    # (the first point of frame 2's run: its own pixel of frame 2)
    n = int(points.bounds[2])
    v, u = divmod(int(points.every[n]) % (H * W), W)
    assert torch.equal(I1[:, n], image1[2, :, v, u].double()) and I2.shape == (2, points.every.numel())


# -- the image fit's tests at every mask pixel: written in place, the plain formulas bit for bit ---

def test_pixel_coordinates_and_points_grid_are_the_plain_formulas():
    g = torch.Generator().manual_seed(0)
    pix = torch.randint(0, 37 * 53, (2, 500), generator=g)
    for dtype in (torch.float64, torch.float32):
        plain = torch.stack([pix % 53, torch.div(pix, 53, rounding_mode="floor"), torch.ones_like(pix)], 1)
        assert torch.equal(pixel_coordinates(pix, 53, dtype), plain.to(dtype))
    # the first and last pixel of rows far down images of any width (the row found by a float
    # division: exact, not one row off at a row's end)
    for width in (1, 2, 53, 1242, 2**20 + 7, 2**31 - 1):
        rows = torch.tensor([0, 1, 374, 2**20 - 1, 2**40 // width])
        pix = torch.cat([rows * width, rows * width + width - 1]).unsqueeze(0)
        plain = torch.stack([pix % width, torch.div(pix, width, rounding_mode="floor"), torch.ones_like(pix)], 1)
        assert torch.equal(pixel_coordinates(pix, width), plain.double()), width
    xy = torch.rand(2, 2, 500, generator=g, dtype=torch.float64) * 60 - 5
    plain = torch.stack([xy[:, 0] * (2.0 / 52) - 1.0, xy[:, 1] * (2.0 / 36) - 1.0], dim=-1).unsqueeze(1)
    for dtype, grid_dtype in ((torch.float64, torch.float64), (torch.float32, torch.float32),
                              (torch.float16, torch.float32)):
        grid, inb = points_grid(xy, (37, 53), dtype)
        assert torch.equal(grid, plain.to(grid_dtype))
        assert torch.equal(inb, (xy[:, 0] >= -1e-6) & (xy[:, 0] <= 52 + 1e-6) & (xy[:, 1] >= -1e-6)
                           & (xy[:, 1] <= 36 + 1e-6))


@pytest.mark.parametrize("B", [1, 3])
def test_matched_gain_and_detail_correlation_are_the_plain_formulas(B):
    g = torch.Generator().manual_seed(1)
    points = sample_mask(torch.rand(B, 1, 30, 40, generator=g) > 0.4, None)
    M = points.every.numel()
    I1 = torch.rand(M, generator=g, dtype=torch.float64) * 200
    I2 = 0.8 * I1 + 20 + torch.randn(M, generator=g, dtype=torch.float64) * torch.rand(M, generator=g) * 30
    ok = torch.rand(M, generator=g) > 0.2
    kept = (I1.clone(), I2.clone())
    w = usable = ok.to(torch.float64)
    for _ in range(3):  # (matched_gain's defining passes, as plain tensor expressions)
        n = points.per_frame(w).clamp_min(1e-12)
        m1, m2 = points.per_frame(w * I1) / n, points.per_frame(w * I2) / n
        s1 = points.per_frame(w * (I1 - points.per_pixel(m1)).abs()) / n
        s2 = points.per_frame(w * (I2 - points.per_pixel(m2)).abs()) / n
        gain = torch.where(s2 > 0, s1 / s2.clamp_min(1e-12), 1.0)
        offset = m1 - gain * m2
        w = usable / (1.0 + ((points.per_pixel(gain) * I2 + points.per_pixel(offset) - I1) / 10.0).square())
    got = matched_gain(I1, I2, ok, points, 10.0)
    assert torch.equal(got[0], gain) and torch.equal(got[1], offset)
    w = ok.to(torch.float64)
    n = points.per_frame(w).clamp_min(1.0)
    x = I1 - points.per_pixel(points.per_frame(w * I1) / n)
    y = I2 - points.per_pixel(points.per_frame(w * I2) / n)
    sxy, sxx, syy = points.per_frame(w * x * y), points.per_frame(w * x * x), points.per_frame(w * y * y)
    den = (sxx * syy).sqrt()
    assert torch.equal(detail_correlation(I1, I2, ok, points), torch.where(den > 0, sxy / den.clamp_min(1e-300), 0.0))
    assert torch.equal(I1, kept[0]) and torch.equal(I2, kept[1])  # (the caller's values untouched)


# -- robust_weight / robust_cost: the scale ------------------------------------------------------

@pytest.mark.parametrize("kind", ROBUST_KERNELS)
def test_robust_kernels_check_the_scale(kind):
    r2 = torch.tensor([0.0, 1.0, 4.0], dtype=torch.float64)
    for fn in (robust_weight, robust_cost):
        with pytest.raises(ValueError, match=r"scale: expected a positive number \(> 0\), got 0.0"):
            fn(r2, 0.0, kind)
        with pytest.raises(ValueError, match=r"scale: expected a positive number \(> 0\), got -2"):
            fn(r2, -2, kind)  # (it was the kernel of scale 2)
        with pytest.raises(ValueError, match="scale: expected a finite number, got nan"):
            fn(r2, float("nan"), kind)
        with pytest.raises(ValueError, match="scale: expected a finite number, got inf"):
            fn(r2, float("inf"), kind)
        with pytest.raises(TypeError, match="scale: expected a number, got str '2'"):
            fn(r2, "2", kind)
        with pytest.raises(TypeError, match="scale: expected a number, got bool True"):
            fn(r2, True, kind)
        with pytest.raises(ValueError, match=r"scale: expected finite values > 0, got \[0.0, nan\]"):
            fn(r2, torch.tensor([[2.0], [0.0], [float("nan")]], dtype=torch.float64), kind)
        with pytest.raises(TypeError, match="scale: expected a number or a real tensor, got dtype torch.bool"):
            fn(r2, torch.tensor(True), kind)
        if kind == "l2":  # (no scale in least squares: checked all the same)
            continue
        # a tensor of scales broadcasts, each row its own scale's kernel
        scales = torch.tensor([[1.5], [3.0]], dtype=torch.float64)
        got = fn(r2, scales, kind)
        assert got.shape == (2, 3)
        for i, c in enumerate((1.5, 3.0)):
            torch.testing.assert_close(got[i], fn(r2, c, kind), atol=0.0, rtol=0.0)


def test_robust_kernel_values_at_a_checked_scale():
    r2 = torch.tensor([0.0, 1.0, 4.0, 16.0], dtype=torch.float64)
    torch.testing.assert_close(robust_weight(r2, 2, "cauchy"), 1 / (1 + r2 / 4))
    torch.testing.assert_close(robust_cost(r2, torch.tensor(2.0, dtype=torch.float64), "cauchy"),
                               4 * torch.log1p(r2 / 4))


# -- screened_start: what its starts are made of ----------------------------------------------------

def test_screened_start_takes_base_for_yaw_models_and_the_camera_for_the_homography():
    cam = Camera(torch.tensor(K_KITTI, dtype=torch.float64), 1.65, roll=0.01, pitch=-0.02).scaled(0.125)
    flow, valid = road_flow(cam, {"x_d": 0.0, "z_d": 1.0, "yaw": math.radians(3.0)}, SIZE, model="paper")
    g = torch.Generator().manual_seed(5)
    img = torch.rand(1, 2, *SIZE, generator=g, dtype=torch.float64)
    turns = (-3.0, 3.0)
    for name in ("paper", "homography"):
        model = get_road_model(name)
        _, base = pack_params(model, cam, None)
        moved = base.clone()
        moved[:, 0] += 0.05
        a = screened_start(model, cam, base, img, valid, turn_moves(turns, ()), (), "cauchy", 500)
        b = screened_start(model, cam, moved, img, valid, turn_moves(turns, ()), (), "cauchy", 500)
        if name == "homography":  # the camera's turn and step alone: base's values play no part
            assert torch.equal(a, b)
            assert not torch.equal(a, base)
        else:  # base with the turn's yaw and step's z_d; the rest, roll and pitch too, base's
            i_yaw, i_z = model.params.index("yaw"), model.params.index("z_d")
            assert abs(abs(float(a[0, i_yaw])) - math.radians(3.0)) < 1e-12
            assert float(a[0, i_z]) == pytest.approx(1.65, abs=1e-12)
            keep = [i for i in range(len(model.params)) if i not in (i_yaw, i_z)]
            assert torch.equal(a[0, keep], base[0, keep]) and torch.equal(b[0, keep], moved[0, keep])


# -- robust_weight / robust_cost: r2 and the dtype -------------------------------------------------

@pytest.mark.parametrize("fn", [robust_weight, robust_cost])
def test_robust_kernels_check_r2(fn):
    with pytest.raises(TypeError, match="r2: expected a torch.Tensor, got float"):
        fn(4.0, 1.0, "cauchy")
    with pytest.raises(TypeError, match="r2: expected a torch.Tensor, got list"):
        fn([4.0], 1.0, "cauchy")
    with pytest.raises(TypeError, match="r2: expected a floating-point tensor, got dtype torch.bool"):
        fn(torch.tensor([True]), 1.0, "huber")
    with pytest.raises(ValueError, match=r"r2: expected finite squared norms >= 0, got \[nan\]"):
        fn(torch.tensor([1.0, float("nan")]), 1.0, "cauchy")
    with pytest.raises(ValueError, match=r"r2: expected finite squared norms >= 0, got \[-3.0\]"):
        fn(torch.tensor([-3.0]), 1.0, "tukey")  # (its weight was 16)
    with pytest.raises(ValueError, match=r"r2: expected finite squared norms >= 0, got \[inf\]"):
        fn(torch.tensor([float("inf")]), 1.0, "l2")


@pytest.mark.parametrize("kind", ROBUST_KERNELS)
def test_robust_kernels_name_the_kind_argument(kind):
    for fn in (robust_weight, robust_cost):
        with pytest.raises(ValueError, match=r"^kind: expected one of \('cauchy'"):
            fn(torch.ones(2), 1.0, kind="gauss")
        fn(torch.ones(2), 1.0, kind=kind)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("kind", ROBUST_KERNELS)
def test_robust_kernels_lift_16_bit_to_float32(dtype, kind):
    """r² / c² overflowed float16 (a cost of inf, a weight of 0, at 30 scales out): the kernels
    compute, and answer, in float32."""
    r2 = torch.tensor([0.0, 0.5, 10.0, 1000.0], dtype=dtype)
    for scale in (0.01, torch.tensor(0.01, dtype=dtype)):
        for fn in (robust_weight, robust_cost):
            got = fn(r2, scale, kind)
            assert got.dtype == torch.float32, fn
            want = fn(r2.to(torch.float32), scale if isinstance(scale, float) else scale.to(torch.float32), kind)
            torch.testing.assert_close(got, want, rtol=0, atol=0)
            assert bool(torch.isfinite(got).all())


# -- pyramid_levels and image_pyramid: what they do -----------------------------------------------

def test_pyramid_levels_rule_and_min_size():
    """The rule the docstring states: floor(log2(min(H, W) / min_size)) + 1, at least 1 (halving
    exactly; pyrDown's rounded-up sides may leave room for one more, as at 63 px)."""
    for side, ms, n in [(375, 16, 5), (375, 24, 4), (63, 16, 2), (64, 16, 3), (127, 16, 3), (15, 16, 1), (1, 1, 1)]:
        assert P.pyramid_levels(side, 2 * side, None, ms) == n, (side, ms)
        assert P.pyramid_levels(2 * side, side, None, ms) == n, (side, ms)
    assert P.pyramid_levels(375, 1242, 3, 16) == 3
    # at most the level at which both sides, rounded up at each halving, reach 1 pixel: 375 x 1242
    # halves to 1 x 1 at its 12th level; beyond it every level repeats that pixel (10**20 of them
    # were built until memory ran out)
    sizes = [(375, 1242)]
    while sizes[-1] != (1, 1):
        sizes.append(tuple((s + 1) // 2 for s in sizes[-1]))
    assert len(sizes) == 12 and P.pyramid_levels(375, 1242, 12, 16) == 12
    for side, most in [(1, 1), (2, 2), (3, 3), (4, 3), (5, 4), (256, 9), (257, 10)]:
        assert P.pyramid_levels(1, side, most, 1) == most
        with pytest.raises(ValueError, match=rf"^levels: expected at most {most} for 1x{side} images .*got {most + 1}$"):
            P.pyramid_levels(1, side, most + 1, 1)
    with pytest.raises(ValueError, match=r"^levels: expected at most 12 for 375x1242 images \(the level at which both "
                                         r"sides reach 1 pixel; more would repeat it\), got 100000000000000000000$"):
        P.pyramid_levels(375, 1242, 10**20, 16)
    for bad in (0, -4):
        with pytest.raises(ValueError, match=f"min_size: expected an int >= 1, got {bad}"):
            P.pyramid_levels(64, 64, None, bad)
    with pytest.raises(TypeError, match="min_size: expected an int >= 1, got float 16.0"):
        P.pyramid_levels(64, 64, None, 16.0)


@pytest.mark.parametrize("level", [1, 2])
def test_level_camera_projects_where_the_pyramid_samples(level):
    """Pixel i of level l is pixel 2^l i of level 0: a linear ramp's pyramid (the binomial blur
    leaves a ramp alone away from the borders) holds at level l, pixel (i, j), the ramp at
    (2^l i, 2^l j); and a point that level 0's camera projects to pixel p, level_camera projects to
    p / 2^l (both written here; not camera.scaled's convention of pixel centres)."""
    s = 2 ** level
    H, W = 48, 64
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ramp = (3.0 * u + 5.0 * v).reshape(1, 1, H, W)
    coarse = P.image_pyramid(ramp, level + 1, 0.0)[level][0, 0]
    i = torch.arange(2, coarse.shape[1] - 2, dtype=torch.float64)  # (away from the reflected borders)
    j = torch.arange(2, coarse.shape[0] - 2, dtype=torch.float64).unsqueeze(1)
    torch.testing.assert_close(coarse[2:-2, 2:-2], 3.0 * s * i + 5.0 * s * j)
    K = torch.tensor([[100.0, 0.4, 31.3], [0.0, 90.0, 22.7], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cam = Camera(K, 1.5)
    X = torch.tensor([[0.7, -0.3, 1.0], [-2.0, 1.1, 1.0]], dtype=torch.float64).T  # (3, 2): rays, z = 1
    p0 = (K @ X)[:2]
    p = (P.level_camera(cam, level).K[0] @ X)[:2]
    torch.testing.assert_close(p, p0 / s)


def test_image_pyramid_gradients_on_the_cpu():
    """As its docstring says: on the CPU only an unsmoothed level 0 (``images`` itself) carries a
    gradient; OpenCV's filters do not, level 0 smoothed included."""
    x = torch.rand(1, 1, 32, 32, generator=torch.Generator().manual_seed(5), requires_grad=True)
    assert [t.requires_grad for t in P.image_pyramid(x, 3, 0.0)] == [True, False, False]
    assert [t.requires_grad for t in P.image_pyramid(x, 3, 1.0)] == [False, False, False]


@pytest.mark.parametrize("call, error, match", [
    (lambda x: P.image_pyramid(x, 0), ValueError, r"^levels: expected an int >= 1, got 0"),
    (lambda x: P.image_pyramid(x, 2.5), TypeError, r"^levels: expected an int, got float 2.5"),
    (lambda x: P.image_pyramid(x, 2, -1.0), ValueError, r"^smooth_sigma: expected a number >= 0, got -1.0"),
    (lambda x: P.image_pyramid(x, 2, math.nan), ValueError, r"^smooth_sigma: expected a finite number, got nan"),
    (lambda x: P.image_pyramid(x[0], 2), ValueError, r"^images: expected shape \(B, C, H, W\), got \(1, 16, 20\)"),
    (lambda x: P.image_pyramid(x.long(), 2), TypeError, r"^images: expected a floating-point tensor, got dtype torch.int64"),
    (lambda x: P.gaussian_blur(x > 0.5, 1.0), TypeError, r"^images: expected a floating-point tensor, got dtype torch.bool"),
    (lambda x: P.gaussian_blur(x[..., :0, :], 1.0), ValueError, r"^images: expected shape \(B, C, H, W\) with H >= 1"),
])
def test_pyramid_and_blur_check_their_arguments(call, error, match):
    """The public pyramid and blur name a bad argument (not OpenCV's or a reshape's error, nor a
    pyramid of one level for ``levels`` 0, nor level 0 left unsmoothed for a negative sigma)."""
    x = torch.rand(1, 1, 16, 20, generator=torch.Generator().manual_seed(0))
    with pytest.raises(error, match=match):
        call(x)


@pytest.mark.parametrize("speed", [1.0, 2.0])
def test_backward_correlation_is_the_correlation_on_image_2s_side_by_opencvs_warp(speed):
    """The detail correlation judged from image 2's side, against OpenCV: image 1's band warped into
    image 2 by the road map (``cv2.warpPerspective``, bilinear), correlated with image 2's band at
    image 2's pixels whose pre-image (rounded) is a road pixel of image 1 inside the frame. The
    default scene's frames swapped (the road recedes) with their true road map, and the same map
    at half the distance (the correlation drops)."""
    import cv2

    from fsof_torch.data.scene import render_pair

    p = render_pair("default", 0, size=(188, 621), speed_factor=speed)
    road = render_pair("default", 1, size=(188, 621), speed_factor=speed)["road"][None]  # image 1 is frame 1
    camera = p["camera"].to(torch.float64)
    motion = {k: torch.tensor([v], dtype=torch.float64) for k, v in p["odometry"].items()}
    grey = lambda im: (0.299 * im[0] + 0.587 * im[1] + 0.114 * im[2]).double()[None, None]  # noqa: E731
    b1, b2 = P.band(grey(p["image2"]), 4.0), P.band(grey(p["image1"]), 4.0)
    horizon = get_road_model("plane").horizon_row(camera, pack_params(get_road_model("plane"), camera, {})[1])
    H, W = road.shape[-2:]
    found = []
    for scale in (1.0, 0.5):
        M = torch.linalg.inv(road_homography(camera, {**motion, "z_d": motion["z_d"] * scale}, model="paper"))
        got = float(backward_correlation(b1, b2, M, horizon, road)[0])
        Mn = M[0].numpy()
        warped = cv2.warpPerspective(b1[0, 0].numpy(), Mn, (W, H), flags=cv2.INTER_LINEAR)
        v, u = np.mgrid[0:H, 0:W]
        q = np.linalg.inv(Mn) @ np.stack([u.ravel(), v.ravel(), np.ones(H * W)])
        x, y = q[0] / q[2], q[1] / q[2]
        ok = (q[2] > 0) & (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
        ui, vi = np.clip(np.round(x), 0, W - 1).astype(int), np.clip(np.round(y), 0, H - 1).astype(int)
        ok &= road[0, 0].numpy()[vi, ui]
        want = np.corrcoef(b2[0, 0].numpy().ravel()[ok], warped.ravel()[ok])[0, 1]
        assert ok.sum() > 10_000 and got == pytest.approx(want, abs=0.01)
        found.append(got)
    assert found[0] > 0.7 and found[1] < found[0] - 0.1
    # a singular map judges no pixel
    singular = torch.zeros(1, 3, 3, dtype=torch.float64)
    assert float(backward_correlation(b1, b2, singular, horizon, road)[0]) == 0.0


def test_reused_mask_pixels_serves_the_same_mask_once_and_only_it():
    """Within ``reused_mask_pixels`` a mask searched once (or a view of the same memory, shape and
    strides) gets the pixels found then; another mask, another view of it, a mask written in place
    since, and any mask outside the block are searched anew; the samples equal the plain ones."""
    g = torch.Generator().manual_seed(0)
    mask = torch.rand(2, 1, 30, 40, generator=g) > 0.6
    plain = sample_mask(mask, 50)
    with reused_mask_pixels():
        first = mask_pixels(mask)
        assert mask_pixels(mask) is first and mask_pixels(mask.expand(2, 1, 30, 40)) is first
        with reused_mask_pixels():  # (nested: the outer memo serves)
            assert mask_pixels(mask) is first
        assert mask_pixels(mask[:1]) is not first and torch.equal(mask_pixels(mask[:1]), first[first < 1200])
        other = mask.clone()
        assert mask_pixels(other) is not first and torch.equal(mask_pixels(other), first)
        again = sample_mask(mask, 50)
        for name in ("pix", "sel", "count", "every", "bounds"):
            assert torch.equal(getattr(again, name), getattr(plain, name)), name
        mask[0, 0, 0, 0] = not bool(mask[0, 0, 0, 0])  # (written: searched anew)
        changed = mask_pixels(mask)
        assert changed is not first and torch.equal(changed, mask.reshape(-1).nonzero().squeeze(1))
    assert mask_pixels(mask) is not changed
    memo = {}  # (kept beyond a block: a later block given it reuses what the first found)
    with reused_mask_pixels(memo):
        kept = mask_pixels(mask)
    assert mask_pixels(mask) is not kept
    with reused_mask_pixels(memo):
        assert mask_pixels(mask) is kept


def test_the_image_estimator_searches_its_mask_once(monkeypatch):
    """The flow's planar start and the image fit sample the same mask: its pixels are found once
    (one search of a full-size mask), the fit as without the reuse."""
    import fsof_torch.estimation.sampling as sampling
    from fsof_torch import ImageMotionEstimator, fit_image, render_pair

    p = render_pair("default", 0, size=(96, 320))
    images, road, flow = (p["image1"][None], p["image2"][None]), p["road"][None], p["flow"][None].float()
    sizes, flatnonzero = [], sampling.np.flatnonzero
    monkeypatch.setattr(sampling.np, "flatnonzero", lambda a: sizes.append(a.size) or flatnonzero(a))
    fit = ImageMotionEstimator()(flow, road, p["camera"], images=images)
    assert sizes.count(road.numel()) == 1
    monkeypatch.setattr(sampling.np, "flatnonzero", flatnonzero)
    alone = fit_image(*images, road, p["camera"], starts=[planar_start(flow, road, p["camera"])])
    for k in fit.params:
        assert torch.equal(fit.params[k], alone.params[k]), k
