"""Tests of the freespace term's fitted target (odometry="fit"): its options checked by name and
value where they are given, and the target that of fit_road on the detached prediction."""

from __future__ import annotations

import pytest
import torch

from fsof_torch.estimation.flow_fit import fit_displacement, fit_road
from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.road_flow import displacement_flow
from fsof_torch.training.fitted_target import check_fit_options, fitted_target
from fsof_torch.training.losses import CompositeLoss, FreespaceFlowLoss, freespace_flow_loss

H, W = 48, 80
GIVEN = {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}


def _camera() -> Camera:
    K = torch.tensor([[60.0, 0.0, 40.0], [0.0, 60.0, 18.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Camera(K, 1.65)


def _bumped(seed: int = 0):
    """A prediction near the paper's model flow, its road mask (below the horizon) and camera."""
    cam = _camera()
    model, valid = displacement_flow(cam, 0.05, 1.0, 0.01, (H, W))
    road = valid.clone()
    road[..., : H // 2 + 4, :] = False
    g = torch.Generator().manual_seed(seed)
    return model + 0.2 + 0.3 * torch.randn(model.shape, generator=g, dtype=model.dtype), road, cam


@pytest.mark.parametrize("fit_options, error, match", [
    # values fit_road checks without a flow: each named as a key of fit_options
    ({"robust": "hubr"}, ValueError, r"^fit_options\['robust'\]: expected one of \('cauchy', "),
    ({"scale": -1.0}, ValueError, r"^fit_options\['scale'\]: expected a finite number > 0, got -1"),
    ({"max_iter": "ten"}, TypeError, r"^fit_options\['max_iter'\]: expected an int > 0, got 'ten'"),
    ({"tol": float("nan")}, ValueError, r"^fit_options\['tol'\]: "),
    ({"polish": 1}, TypeError, r"^fit_options\['polish'\]: expected True or False"),
    ({"bounds": "loose"}, ValueError, r"^fit_options\['bounds'\]: expected 'physical' or None"),
    ({"check_every": 0}, ValueError, r"^fit_options\['check_every'\]: expected 'auto', an int >= 1"),
    ({"model": "plane", "fixed": ["pitch_chnage"]}, ValueError,
     r"^fit_options\['fixed'\]: unknown parameters \['pitch_chnage'\] of model 'plane'"),
    ({"prior": {"z": (1.0, 0.1)}}, ValueError, r"^fit_options\['prior'\]: unknown parameter 'z' of model 'paper'"),
    # fit_displacement's flags, and its held pitch: a prior on it would be ignored by the fit
    ({"fit_roll": "yes"}, TypeError, r"^fit_options\['fit_roll'\]: expected True or False, got str 'yes'"),
    ({"prior": {"pitch": (0.0, 0.01)}}, ValueError, r"^fit_options\['prior'\]: 'pitch' is held at its start"),
])
def test_fit_option_values_are_refused_where_given_not_at_the_first_fit(fit_options, error, match):
    """A bad value passed the term's construction (and a call with a given odometry) and raised
    only at the first fit, in training, named as fit_road's own argument."""
    flow, road, cam = _bumped()
    with pytest.raises(error, match=match):
        FreespaceFlowLoss(odometry="fit", fit_options=fit_options)
    with pytest.raises(error, match=match):
        FreespaceFlowLoss(fit_options=fit_options)
    with pytest.raises(error, match=match):
        freespace_flow_loss(flow, road, cam, GIVEN, fit_options=fit_options)
    with pytest.raises(error, match=match):
        freespace_flow_loss(flow, road, cam, "fit", fit_options=fit_options)


@pytest.mark.parametrize("fit_options", [
    {}, {"fit_roll": False}, {"fit_pitch": True}, {"prior": {"roll": (0.0, 0.01)}}, {"robust": "huber", "scale": 2.0},
    {"max_iter": torch.tensor(20)}, {"check_every": (1, 2)}, {"bounds": None}, {"max_points": None},
    {"model": "plane", "prior": {"z_d": (1.0, 1.0)}}, {"model": "paper", "fixed": ()}, {"model": "homography"},
])
def test_valid_fit_options_give_fit_roads_target(fit_options):
    """The target is the flow of fit_road (fit_displacement without a model) on the detached
    prediction inside the road, where it is defined and the fit succeeded, compared here with the
    loss written out from that fit."""
    flow, road, cam = _bumped()
    assert check_fit_options(fit_options) == dict(fit_options)
    options = dict(fit_options)
    if "model" in options:
        fitted = fit_road(torch.where(road, flow, 0.0), road, cam, **options)
    else:
        fitted = fit_displacement(torch.where(road, flow, 0.0), road, cam, **options)
    target, counted = fitted_target(flow, road, cam, fit_options, flow.dtype)
    torch.testing.assert_close(target, fitted.flow, rtol=0, atol=0)
    assert torch.equal(counted, fitted.valid & fitted.success.reshape(-1, 1, 1, 1))
    counted = road & counted
    r = torch.where(counted, flow - fitted.flow, 0.0)
    expected = ((r.square() + 1).sqrt() - 1).sum() / counted.sum()
    value = FreespaceFlowLoss(odometry="fit", fit_options=fit_options)(flow, road, cam)
    assert value.item() == pytest.approx(expected.item(), rel=1e-9)
    # unused with a given odometry: the given odometry's target, as without fit_options
    assert freespace_flow_loss(flow, road, cam, GIVEN, fit_options=fit_options) == freespace_flow_loss(
        flow, road, cam, GIVEN)


def test_fit_mode_does_not_use_an_odometry_passed_to_it():
    """As documented: FreespaceFlowLoss(odometry="fit") fits the prediction whatever odometry it is
    given, so one batch dict with an odometry feeds it through CompositeLoss."""
    flow, road, cam = _bumped()
    term = FreespaceFlowLoss(odometry="fit")
    fitted = term(flow, road, cam)
    assert term(flow, road, cam, GIVEN) == fitted
    given = FreespaceFlowLoss()(flow, road, cam, GIVEN)
    assert given > 5 * fitted  # (the two targets differ: the test tells them apart)
    _, values = CompositeLoss({"f": (1.0, term)})(flow, {"road": road, "camera": cam, "odometry": GIVEN})
    assert values["f"] == fitted
