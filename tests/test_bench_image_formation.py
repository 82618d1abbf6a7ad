"""``benchmarks/image_formation.py``'s warped frames on a tiny synthetic pair: image 2 made from
image 1 by the pair's true road motion (its exported ``plane`` values) is the rendered road's
ground truth, so the benchmark's "warped" rows isolate the geometry; and its "matched" frames'
blur by the road's magnification."""

from __future__ import annotations


import numpy as np
import pytest
import torch

SIZE = (96, 320)


@pytest.fixture(scope="module")
def bench(load_benchmark):
    return load_benchmark("image_formation")


@pytest.mark.parametrize("preset, overrides", [("body-motion", {}), ("default", {"steering": 0.1})])
def test_true_homography_moves_the_road_pixels_by_their_ground_truth_flow(bench, preset, overrides):
    from fsof_torch.data.scene import render_pair

    pair = render_pair(preset, 3, size=SIZE, dtype=torch.float64, **overrides)
    M = bench.true_homography(pair)
    road = (pair["road"] & pair["valid"])[0].numpy()
    v, u = np.nonzero(road)
    q = M @ np.stack([u, v, np.ones_like(u)]).astype(np.float64)
    moved = q[:2] / q[2] - np.stack([u, v])
    flow = pair["flow"].numpy()[:, v, u]
    assert road.sum() > 1000
    np.testing.assert_allclose(moved, flow, atol=1e-6)


def test_warped_image_2_is_image_1_moved_by_the_road_flow(bench, monkeypatch):
    from fsof_torch.data.scene import render_pair
    from fsof_torch.estimation.sampling import sample_points

    pair = render_pair("body-motion", 3, size=SIZE)
    image2 = bench.warped(pair)
    assert image2.shape == pair["image1"].shape and image2.dtype == torch.float32
    assert image2.min() >= 0 and image2.max() <= 255
    # image 1 at p is image 2 at p + flow (up to interpolation: away from the frame's border)
    road = (pair["road"] & pair["valid"])[0].numpy()
    flow = pair["flow"].numpy()
    H, W = SIZE
    v, u = np.nonzero(road)
    x, y = u + flow[0, v, u], v + flow[1, v, u]
    inside = (x > 2) & (x < W - 3) & (y > 2) & (y < H - 3)
    assert inside.sum() > 1000
    xy = torch.from_numpy(np.stack([x, y])[:, inside]).unsqueeze(0)
    at1 = pair["image1"].double()[:, v[inside], u[inside]]

    def error(image2: torch.Tensor) -> float:
        """Mean |image 2 at p + flow - image 1 at p| (bilinear samples of image 2)."""
        at2, inb = sample_points(image2[None].double(), xy)
        return float((at2[0] - at1).abs()[:, inb[0]].mean())

    # a fraction of the texture's contrast (0.566 measured, 0.1 std is 1.19; a homography 0.25 px
    # off gives 0.64, 0.5 px off 0.82)
    err = error(image2)
    assert err < 0.7, err
    # and the best alignment: the same warp with its homography 0.25 px off in u or v is worse
    true_homography = bench.true_homography
    for du, dv in ((0.25, 0), (-0.25, 0), (0, 0.25), (0, -0.25)):
        shift = np.array([[1.0, 0.0, du], [0.0, 1.0, dv], [0.0, 0.0, 1.0]])
        monkeypatch.setattr(bench, "true_homography", lambda p, shift=shift: shift @ true_homography(p))
        off = error(bench.warped(pair))
        assert off > err, (du, dv, off, err)


def test_from_truth_fits_stay_at_the_truth_where_image_2_is_image_1_moved(bench, capsys):
    """``--from-truth``: fits started at the true motion at full resolution, one row per choice of
    points; where image 2 is image 1 moved by the true road motion, every row stays within 0.2 px,
    0.15° and 0.03 camera heights of the truth at this small size (one row's mask without the road
    beside the kerb). The three rows whose bands are filtered inside the road mask filter image 2
    inside image 1's mask, which the motion moves off the road it covers: at this size (a blur of
    4 px spans twice the road it does at full size) that costs up to 0.26° of roll (0.3 allowed);
    at full size on four pairs they lie as near as the others (docs/image-fit.md)."""
    from fsof_torch.data.scene import render_pair

    pair = render_pair("body-motion", 3, size=(188, 621))  # (the attitude needs the rows)
    moved = {**pair, "image2": bench.warped(pair)}
    bench.from_truth([moved])
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert [r.split(" | ")[0][2:] for r in rows] == list(bench.FROM_TRUTH)
    for r in rows:
        e, pitch, roll, z = (float(c) for c in r.strip("| ").split(" | ")[1:])
        assert e < 0.2 and pitch < 0.15 and roll < (0.3 if "inside the mask" in r else 0.15) and abs(z) < 0.03, r


def test_off_kerb_leaves_out_the_road_beside_kerb_and_pavement_only(bench):
    """The off-kerb ``--from-truth`` row's mask: the road less the pixels within r px (a square
    window) of the kerb and the pavement, every one of them; the rest of the road stays."""
    from fsof_torch.data.scene import render_pair
    from fsof_torch.data.scene.config import KERB, PAVEMENT

    pair = render_pair("body-motion", 3, size=SIZE)
    r = 4
    mask = bench.off_kerb(pair, r)
    road = pair["road"][0]
    assert bool((mask[0] <= road).all()) and int(road.sum()) - int(mask[0].sum()) > 50
    raised = torch.nonzero((pair["labels"] == KERB) | (pair["labels"] == PAVEMENT))
    for v, u in torch.nonzero(road & ~mask[0]).tolist():
        assert bool(((raised[:, 0] - v).abs().le(r) & (raised[:, 1] - u).abs().le(r)).any())
    near = torch.zeros_like(road)
    for v, u in raised.tolist():
        near[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1] = True
    assert torch.equal(mask[0], road & ~near)


def test_magnification_blur_of_a_zoom_and_of_no_motion(bench):
    """A zoom by m about any point widens image 1's footprint by m along both axes: σ = s √(m² − 1)
    at every pixel; no motion, or a shrinking zoom, needs no blur."""
    m, s, c = 1.3, 0.8, (70.0, 20.0)
    zoom = lambda m: np.array([[m, 0.0, (1 - m) * c[0]], [0.0, m, (1 - m) * c[1]], [0.0, 0.0, 1.0]])
    sigma = bench.magnification_blur(zoom(m), (40, 90), s)
    assert sigma.shape == (2, 40, 90)
    np.testing.assert_allclose(sigma, s * np.sqrt(m * m - 1), rtol=1e-12)
    assert not bench.magnification_blur(np.eye(3), (40, 90), s).any()
    assert not bench.magnification_blur(zoom(0.8), (40, 90), s).any()


def test_magnification_blur_against_finite_differences_of_the_road_homography(bench):
    """On a pair's true road homography (a magnifying, shearing map), σ² / s² + 1 along each axis
    is the squared length of the Jacobian's row, the Jacobian by central differences of the map at
    each pixel's preimage (written out here)."""
    from fsof_torch.data.scene import render_pair

    pair = render_pair("body-motion", 3, size=SIZE)
    M = bench.true_homography(pair)
    s = 1.0
    sigma = bench.magnification_blur(M, SIZE, s)

    def apply(H, x):  # (2, N) pixels through H
        q = H @ np.vstack([x, np.ones(x.shape[1])])
        return q[:2] / q[2]

    rng = np.random.default_rng(0)
    v = rng.integers(SIZE[0] // 2 + 5, SIZE[0], 200)  # (below the horizon: road in both frames)
    u = rng.integers(0, SIZE[1], 200)
    x1 = apply(np.linalg.inv(M), np.stack([u, v]).astype(np.float64))
    h = 1e-4
    J = np.stack([(apply(M, x1 + h * e[:, None]) - apply(M, x1 - h * e[:, None])) / (2 * h)
                  for e in np.eye(2)], axis=1)  # (2, 2, N): ∂x2_i / ∂x1_j
    expected = s * np.sqrt(np.clip((J ** 2).sum(1) - 1, 0, None))
    np.testing.assert_allclose(sigma[:, v, u], expected, atol=1e-6)
    assert (expected > 0.3).mean() > 0.5  # (the near road is magnified)


def test_blur_along_matches_opencv_at_its_steps_and_lies_between_them(bench):
    """A constant σ that is one of the steps gives OpenCV's Gaussian blur along that axis; σ
    halfway between two steps gives the mean of the two; σ = 0 leaves the image."""
    import cv2

    rng = np.random.default_rng(1)
    image = rng.uniform(0, 255, (30, 50, 3)).astype(np.float32)
    ones = np.ones((30, 50))
    for axis, ksize in ((0, (7, 1)), (1, (1, 7))):
        out = bench.blur_along(image, ones, axis)
        ref = cv2.GaussianBlur(image, ksize, 1.0 if axis == 0 else 0, sigmaY=1.0 if axis == 1 else 1e-9)
        np.testing.assert_allclose(out, ref, atol=1e-4)
        half = bench.blur_along(image, 1.25 * ones, axis)
        wide = cv2.GaussianBlur(image, (11, 1) if axis == 0 else (1, 11), 1.5 if axis == 0 else 0,
                                sigmaY=1.5 if axis == 1 else 1e-9)
        np.testing.assert_allclose(half, 0.5 * (ref + wide), atol=1e-4)
    np.testing.assert_array_equal(bench.blur_along(image, 0 * ones, 0), image)
