"""fsof_torch.estimation.combine: road-motion results of one batch combined sample by sample."""

from __future__ import annotations

import pytest
import torch

from fsof_torch import Camera, fit_image, road_flow
from fsof_torch.estimation.combine import fit_at_size, where_motion
from fsof_torch.estimation.pyramid import image_pyramid, level_camera, mask_pyramid

pytestmark = pytest.mark.usefixtures("one_thread")


def test_where_motion_chooses_sample_by_sample(kitti_K):
    """Two results of one batch: tensors with the batch dimension chosen per sample (cameras'
    parameters too), the rest the same in both; results that differ otherwise are named."""
    take = torch.tensor([True, False])
    rolls = torch.tensor([0.1, 0.2], dtype=kitti_K.dtype)
    a = {"model": "plane", "z_d": torch.tensor([1.0, 2.0]), "camera": Camera(kitti_K, 1.65, roll=rolls)}
    b = {"model": "plane", "z_d": torch.tensor([3.0, 4.0]), "camera": Camera(kitti_K, 1.5, roll=0.3)}
    out = where_motion(take, a, b)
    assert out["model"] == "plane" and out["z_d"].tolist() == [1.0, 4.0]
    assert out["camera"].roll.tolist() == pytest.approx([0.1, 0.3])
    assert out["camera"].height.tolist() == pytest.approx([1.65, 1.5])
    assert a["z_d"].tolist() == [1.0, 2.0] and b["z_d"].tolist() == [3.0, 4.0]  # the inputs as they were
    with pytest.raises(ValueError, match=r"^estimator: .*combined sample by sample \(str and str\)$"):
        where_motion(take, {**a, "model": "plane"}, {**b, "model": "paper"})


def test_fit_at_size_is_the_same_motion_at_full_size():
    """A fit at half size, brought to full size: the flow is the road's flow of its parameters at
    full size (road_flow, written separately), with the fit's attitude; the rest as fitted."""
    from fsof_torch.data.scene import render_pair

    p = render_pair("default", 0, size=(96, 320))
    grey = torch.cat([p["image1"].mean(0, keepdim=True), p["image2"].mean(0, keepdim=True)])[None]
    half = image_pyramid(grey, 2)[1]
    fit = fit_image(half[:, :1], half[:, 1:], mask_pyramid(p["road"][None], 2)[1], level_camera(p["camera"], 1))
    full = fit_at_size(fit, p["camera"], (96, 320))
    assert tuple(full.flow.shape) == (1, 2, 96, 320) and tuple(full.inliers.shape) == (1, 1, 96, 320)
    expected, valid = road_flow(p["camera"].to(torch.float64), {k: v.double() for k, v in fit.params.items()},
                                (96, 320), model=fit.model)
    assert torch.equal(full.valid, valid)
    torch.testing.assert_close(full.flow[valid.expand_as(full.flow)].double(), expected[valid.expand_as(expected)],
                               rtol=0, atol=1e-4)
    assert full.params is fit.params and torch.equal(full.success, fit.success)
    assert torch.allclose(full.camera.K, p["camera"].K.to(full.camera.dtype))
    assert fit_at_size(full, p["camera"], (96, 320)) is full  # already at that size


def test_fit_at_size_of_a_velocity_fit_is_its_velocity_flow():
    """A velocity fit's map is the time derivative G (1/s), not a homography: brought to full size
    its flow is the velocity flow in px/s (it was evaluated as a homography: millions of px off)."""
    from fsof_torch import fit_velocity, velocity_flow

    K = torch.tensor([[700.0, 0, 320], [0, 700, 90], [0, 0, 1]], dtype=torch.float64)
    big = Camera(K, 1.65, roll=0.01)
    flow, valid = velocity_flow(big.scaled(0.5), 10.0, 0.05, 2.7, (96, 320))
    fit = fit_velocity(flow, valid, big.scaled(0.5), 2.7)
    assert bool(fit.success)
    full = fit_at_size(fit, big, (192, 640))
    expected, expected_valid = velocity_flow(big, 10.0, 0.05, 2.7, (192, 640))
    both = (full.valid & expected_valid).expand_as(expected)
    # (the pixels on the horizon itself may round either way)
    assert int((full.valid ^ expected_valid).sum()) <= 1 and int(both.sum()) > 0.4 * both.numel()
    torch.testing.assert_close(full.flow[both], expected[both], rtol=0, atol=1e-9)


def test_fit_at_size_keeps_a_failed_fits_absurd_attitude_as_fitted():
    """A failed flow fit's roll may drift beyond a quarter turn, which a user's Camera refuses:
    brought to another size, the fit keeps it as fitted (the camera's check raised here)."""
    from dataclasses import replace

    from fsof_torch import fit_road

    K = torch.tensor([[300.0, 0, 80], [0, 300, 24], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, 1.65)
    flow, valid = road_flow(cam.scaled(0.5), {"z_d": 1.0}, (24, 80), model="paper")
    fit = fit_road(flow, valid, cam.scaled(0.5), model="paper")
    drifted = Camera._checked(fit.camera.K, fit.camera.height, torch.tensor([-1.91], dtype=torch.float64),
                              fit.camera.pitch)
    full = fit_at_size(replace(fit, camera=drifted, success=torch.tensor([False])), cam, (48, 160))
    assert float(full.camera.roll) == -1.91 and tuple(full.flow.shape) == (1, 2, 48, 160)
