"""The evaluation's figures against implementations written out separately, in NumPy and OpenCV
only: the census distance by loops over its window, SSIM by Wang et al.'s formula with the
documented 7-tap Gaussian, the warp by bilinear taps written out, and EPE / Fl of the real KITTI
pair decoded as the devkit decodes its 16-bit PNG. ``kind="ssim"`` calls kornia, so comparing it
with kornia (tests/test_photometric.py) cannot catch a change of kornia's window or padding; these
can."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fsof_torch.evaluation.metrics import flow_metrics
from fsof_torch.evaluation.photometric import photometric_error_maps

H, W = 13, 17


def _pair(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two RGB images (H, W, 3) on 0..255 with many ties (whole grey levels) and a fractional
    flow (H, W, 2), float64."""
    rng = np.random.default_rng(seed)
    i1 = rng.integers(0, 256, (H, W, 3)).astype(np.float64)
    i2 = rng.integers(0, 256, (H, W, 3)).astype(np.float64)
    flow = rng.normal(0, 1.5, (H, W, 2))
    return i1, i2, flow


def _warp(image: np.ndarray, flow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """image(p + flow(p)) by four bilinear taps (zero outside), and whether p + flow(p) lies in
    [0, W - 1] x [0, H - 1]."""
    out = np.zeros_like(image)
    inside = np.zeros((H, W), dtype=bool)
    for y in range(H):
        for x in range(W):
            u, v = x + flow[y, x, 0], y + flow[y, x, 1]
            inside[y, x] = 0 <= u <= W - 1 and 0 <= v <= H - 1
            x0, y0 = int(np.floor(u)), int(np.floor(v))
            for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
                weight = (u - x0 if dx else 1 - (u - x0)) * (v - y0 if dy else 1 - (v - y0))
                if 0 <= x0 + dx < W and 0 <= y0 + dy < H:
                    out[y, x] += weight * image[y0 + dy, x0 + dx]
    return out, inside


def _eroded(inside: np.ndarray, r: int) -> np.ndarray:
    """A pixel whose whole (2r+1)^2 window (clipped to the image) is inside."""
    return np.array([[inside[max(y - r, 0):y + r + 1, max(x - r, 0):x + r + 1].all() for x in range(W)]
                     for y in range(H)])


def _census(g1: np.ndarray, g2: np.ndarray, r: int = 3) -> np.ndarray:
    """Census distance by loops: bits I(q) > I(p) over the (2r+1)^2 window, the border
    replicated, Hamming distance over the (2r+1)^2 - 1 neighbours."""
    out = np.zeros((H, W))
    for y in range(H):
        for x in range(W):
            differ = 0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    if dx or dy:
                        q = min(max(y + dy, 0), H - 1), min(max(x + dx, 0), W - 1)
                        differ += (g1[q] > g1[y, x]) != (g2[q] > g2[y, x])
            out[y, x] = differ / ((2 * r + 1) ** 2 - 1)
    return out


def _ssim(a: np.ndarray, b: np.ndarray, taps: int = 7, sigma: float = 1.5, top: float = 255.0) -> np.ndarray:
    """Wang et al.'s SSIM map of one channel: Gaussian-weighted means, variances and covariance
    over a window of ``taps`` (reflection padding without repeating the edge), C1 = (0.01 L)^2,
    C2 = (0.03 L)^2."""
    x = np.arange(taps) - taps // 2
    g = np.exp(-x ** 2 / (2 * sigma ** 2))
    kernel = np.outer(g, g) / g.sum() ** 2
    r = taps // 2

    def mean(img: np.ndarray) -> np.ndarray:
        p = np.pad(img, r, mode="reflect")
        return np.array([[(p[y:y + taps, x:x + taps] * kernel).sum() for x in range(W)] for y in range(H)])

    c1, c2 = (0.01 * top) ** 2, (0.03 * top) ** 2
    ma, mb = mean(a), mean(b)
    va, vb, cab = mean(a * a) - ma ** 2, mean(b * b) - mb ** 2, mean(a * b) - ma * mb
    return ((2 * ma * mb + c1) * (2 * cab + c2)) / ((ma ** 2 + mb ** 2 + c1) * (va + vb + c2))


@pytest.mark.parametrize("data_range", [255.0, 1.0])
def test_l1_ssim_and_census_against_the_formulas_written_out(data_range):
    """Every pixel of the maps (the border included) and every validity flag, with a fractional
    flow that sends some sample points out of image 2."""
    i1, i2, flow = _pair()
    warped, inside = _warp(i2, flow)
    grey = np.array([0.299, 0.587, 0.114])
    want = {
        "l1": (np.abs(i1 - warped).mean(axis=2), inside),
        "ssim": (np.mean([np.clip((1 - _ssim(i1[..., c], warped[..., c])) / 2, 0, 1) for c in range(3)], axis=0),
                 _eroded(inside, 3)),
        "census": (_census(i1 @ grey, warped @ grey), _eroded(inside, 3)),
    }
    scale = data_range / 255.0
    as_tensor = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None]  # noqa: E731
    maps = photometric_error_maps(as_tensor(i1) * scale, as_tensor(i2) * scale, as_tensor(flow),
                                  data_range=data_range)
    assert 0 < int(inside.sum()) < H * W
    for kind, (error, valid) in maps.items():
        ref_error, ref_valid = want[kind]
        assert np.array_equal(valid[0, 0].numpy(), ref_valid), kind
        np.testing.assert_allclose(error[0, 0].numpy()[ref_valid], ref_error[ref_valid], rtol=1e-9, atol=1e-9,
                                   err_msg=kind)


def test_ssim_with_the_papers_11_taps():
    """``window=11`` is Wang et al.'s window (11 taps of sigma 1.5), as docs/evaluation.md says."""
    i1, i2, _ = _pair(seed=3)
    as_tensor = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None]  # noqa: E731
    error, valid = photometric_error_maps(as_tensor(i1), as_tensor(i2), torch.zeros(1, 2, H, W, dtype=torch.float64),
                                          kinds=("ssim",), window=11)["ssim"]
    want = np.mean([np.clip((1 - _ssim(i1[..., c], i2[..., c], taps=11)) / 2, 0, 1) for c in range(3)], axis=0)
    assert valid.all()
    np.testing.assert_allclose(error[0, 0].numpy(), want, rtol=1e-9, atol=1e-9)


def test_epe_and_fl_of_the_kitti_pair_as_the_devkit_computes_them(shared_data):
    """The ground truth decoded as the devkit decodes it ((value - 2^15) / 64, valid in the third
    channel), a perturbed estimate, and the devkit's error and outlier test (e > 3 px and
    e / |F| > 5 %), pooled over the valid pixels."""
    import cv2

    from fsof_torch.io import read_kitti_flow

    path = shared_data / "kitti15_000000" / "flow_noc_10.png"
    png = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float64)  # BGR -> (u, v, valid)
    gt = (png[..., :2] - 2 ** 15) / 64.0
    valid = png[..., 2] > 0
    rng = np.random.default_rng(1)
    est = gt + rng.normal(0, 3.0, gt.shape) * rng.integers(0, 2, gt.shape[:2])[..., None]
    err = np.linalg.norm(est - gt, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):  # (the devkit divides by |F| = 0 as well)
        outlier = (err > 3.0) & (err / np.linalg.norm(gt, axis=2) > 0.05)

    flow, ok = read_kitti_flow(path)
    assert np.array_equal(ok[0].numpy(), valid) and np.array_equal(flow.permute(1, 2, 0).numpy()[valid], gt[valid])
    m = flow_metrics(torch.from_numpy(est).permute(2, 0, 1)[None], flow[None].double(), valid=ok[None])
    assert m["n_pixels"] == int(valid.sum())
    assert m["epe"] == pytest.approx(err[valid].mean(), rel=1e-12)
    assert m["Fl"] == pytest.approx(outlier[valid].mean(), rel=1e-12) and 0.05 < m["Fl"] < 0.5


def _bilinear_at(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """image (H, W, C) at the points (x, y) (h, w) by four bilinear taps, zero outside: float64."""
    h, w = image.shape[:2]
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    out = np.zeros(x.shape + image.shape[2:])
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        weight = (x - x0 if dx else 1 - (x - x0)) * (y - y0 if dy else 1 - (y - y0))
        xi, yi = x0 + dx, y0 + dy
        inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
        tap = image[np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)].astype(np.float64)
        out += np.where(inside, weight, 0.0)[..., None] * tap
    return out


def test_opencv_remap_beside_the_warp_as_evaluation_md_states(shared_data):
    """evaluation.md, beside OpenCV: ``cv2.remap(INTER_LINEAR)`` of a float image rounds its sample
    positions, hence its weights, to 1/32 of a pixel in OpenCV 4, which puts it up to 4.6 grey
    levels (0.13 on average) off ``warp_backward`` on the KITTI frame 000000_10 under random
    flows of up to ±5 px; OpenCV 5 weights exactly and agrees to float32 rounding. (The page said
    1/32 weights and a difference of up to about 2e-4 grey levels, which cannot both hold.)"""
    import cv2

    from fsof_torch.evaluation.warp import warp_backward

    image = np.ascontiguousarray(cv2.imread(str(shared_data / "kitti15_000000" / "image_10.png"))[:, :, ::-1])
    image = image.astype(np.float32)
    h, w = image.shape[:2]
    flow = (torch.rand(1, 2, h, w, generator=torch.Generator().manual_seed(0)) - 0.5) * 10
    warped, inside = warp_backward(torch.from_numpy(image).permute(2, 0, 1)[None], flow)
    x = (np.arange(w)[None] + flow[0, 0].numpy()).astype(np.float32)
    y = (np.arange(h)[:, None] + flow[0, 1].numpy()).astype(np.float32)
    remapped = cv2.remap(image, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    inside = inside[0, 0].numpy()
    diff = np.abs(remapped - warped[0].permute(1, 2, 0).numpy())[inside]
    if int(cv2.__version__.split(".")[0]) >= 5:
        assert diff.max() < 1e-5
        return
    # OpenCV 4: exactly bilinear at the positions rounded to 1/32 px (to float32 rounding) ...
    x32, y32 = np.round(x.astype(np.float64) * 32) / 32, np.round(y.astype(np.float64) * 32) / 32
    np.testing.assert_allclose(remapped[inside], _bilinear_at(image, x32, y32)[inside], atol=1e-3)
    # ... so grey levels off the exact weights
    assert 4.5 < diff.max() < 4.7 and 0.12 < diff.mean() < 0.13, (diff.max(), diff.mean())
