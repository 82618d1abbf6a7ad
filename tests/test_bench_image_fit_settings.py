"""``benchmarks/image_fit_settings.py``'s crops: each window is the same scene and motion seen
through a smaller frame, so the true road motion under the window's camera moves its pixels by
the window's slice of the ground-truth flow."""

from __future__ import annotations

import numpy as np
import pytest
import torch

SIZE = (96, 320)


@pytest.fixture(scope="module")
def bench(load_benchmark):
    return load_benchmark("image_fit_settings")


def test_crops_slice_the_frame_and_move_the_principal_point(bench):
    from fsof_torch.data.scene import render_pair

    pair = render_pair("default", 2, size=SIZE, dtype=torch.float64)
    windows = bench.crops(pair, shift=3)
    assert len(windows) == 9
    H, W = SIZE
    offsets = [(t, l) for t in range(3) for l in range(3)]
    for (top, left), window in zip(offsets, windows):
        for name in ("image1", "image2", "flow", "road", "valid"):
            assert window[name].shape[-2:] == (H - 3, W - 3)
            assert torch.equal(window[name], pair[name][..., top:top + H - 3, left:left + W - 3])
        K, K0 = window["camera"].K[0], pair["camera"].K[0]
        assert float(K[0, 2]) == float(K0[0, 2]) - left and float(K[1, 2]) == float(K0[1, 2]) - top
        assert torch.equal(K[:2, :2], K0[:2, :2])
        assert window["plane"] is pair["plane"]  # (what is not an image passes through)


def test_true_road_motion_under_a_window_camera_gives_the_window_ground_truth(bench):
    from fsof_torch.data.scene import render_pair
    from fsof_torch.geometry.road_models import get_road_model

    pair = render_pair("body-motion", 1, size=SIZE, dtype=torch.float64)
    model = get_road_model("plane")
    values = torch.tensor([[pair["plane"][n] for n in model.params]], dtype=torch.float64)
    for window in bench.crops(pair)[5::5]:
        # (the plane's translation is in units of its own height, which the body's heave moves)
        camera = window["camera"].replace(height=pair["plane"]["height"])
        M = model.matrix(camera, values)[0].numpy()
        road = (window["road"] & window["valid"])[0].numpy()
        v, u = np.nonzero(road)
        q = M @ np.stack([u, v, np.ones_like(u)]).astype(np.float64)
        assert road.sum() > 1000
        np.testing.assert_allclose(q[:2] / q[2] - np.stack([u, v]), window["flow"].numpy()[:, v, u], atol=1e-6)


def test_road_epe_is_the_mean_error_over_road_pixels_with_ground_truth(bench):
    flow = torch.zeros(2, 4, 5)
    truth = torch.zeros(2, 4, 5)
    truth[0, 1, 1], truth[1, 2, 3] = 3.0, 4.0
    road = torch.zeros(1, 4, 5, dtype=torch.bool)
    road[0, 1:3, 1:4] = True
    valid = torch.ones(1, 4, 5, dtype=torch.bool)
    valid[0, 2, 1] = False
    sample = {"flow": truth, "road": road, "valid": valid}
    assert bench.road_epe(flow, sample) == pytest.approx((3.0 + 4.0) / 5)


def test_mirrored_samples_mirror_the_real_frames_and_their_cameras(bench, monkeypatch):
    """``--mirror``: the KITTI sample and each clip pair mirrored left to right, the cameras'
    principal points mirrored with them; the samples given are left as they were."""
    from pathlib import Path

    from fsof_torch.data.scene import render_pair

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "benchmarks"))  # (real_road)
    p = render_pair("default", 2, size=SIZE)
    sample = {k: p[k] for k in ("camera", "image1", "image2", "road", "flow", "valid")}
    real = {"kitti": sample, "clip": [(p["camera"], p["image1"], p["image2"], p["road"])] * 2}
    out = bench.mirrored_samples(real)
    assert real["kitti"] is sample and real["clip"][0][1] is p["image1"]
    assert torch.equal(out["kitti"]["image1"], p["image1"].flip(-1))
    assert torch.equal(out["kitti"]["flow"][0], -p["flow"][0].flip(-1))
    W = SIZE[1]
    for cam, im1, im2, road in out["clip"]:
        assert torch.equal(im1, p["image1"].flip(-1)) and torch.equal(im2, p["image2"].flip(-1))
        assert torch.equal(road, p["road"].flip(-1))
        assert float(cam.K[0, 0, 2]) == (W - 1) - float(p["camera"].K[0, 0, 2])
    assert bench.mirrored_samples({}) == {}
