"""``benchmarks/image_formation.py``'s warped frames on a tiny synthetic pair: image 2 made from
image 1 by the pair's true road motion (its exported ``plane`` values) is the rendered road's
ground truth, so the benchmark's "warped" rows isolate the geometry."""

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


def test_warped_image_2_is_image_1_moved_by_the_road_flow(bench):
    from fsof_torch.data.scene import render_pair

    pair = render_pair("body-motion", 3, size=SIZE)
    image2 = bench.warped(pair)
    assert image2.shape == pair["image1"].shape and image2.dtype == torch.float32
    # image 1 at p is image 2 at p + flow (up to interpolation: away from the frame's border)
    road = (pair["road"] & pair["valid"])[0].numpy()
    flow = pair["flow"].numpy()
    H, W = SIZE
    v, u = np.nonzero(road)
    x, y = u + flow[0, v, u], v + flow[1, v, u]
    assert image2.min() >= 0 and image2.max() <= 255
    inside = (x > 2) & (x < W - 3) & (y > 2) & (y < H - 3)
    # bilinear samples of image 2 at p + flow match image 1 to a fraction of its texture's contrast
    from fsof_torch.estimation.sampling import sample_points

    xy = torch.from_numpy(np.stack([x, y])[:, inside]).unsqueeze(0)
    at2, inb = sample_points(image2[None].double(), xy)
    at1 = pair["image1"].double()[:, v[inside], u[inside]]
    err = (at2[0] - at1).abs()[:, inb[0]]
    assert inside.sum() > 1000
    assert float(err.mean()) < 0.1 * float(at1.std()), (float(err.mean()), float(at1.std()))
