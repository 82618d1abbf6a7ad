"""The road detection's seed along a curved path: its geometry against the arc sampled point by
point, and the detection in sharp turns (the seed bent where the motion found on the straight one
takes the path out of it)."""

from __future__ import annotations

import math

import pytest
import torch

from fsof_torch import Camera, ImageMotionEstimator, detect_road, render_pair, road_seed
from fsof_torch.refinement.seed import path_curvature

F, H, W, HEIGHT = 400.0, 120, 401, 1.5


def level_camera(batch: int = 1) -> Camera:
    """A level camera whose principal point is the image's centre column (left and right mirror)."""
    K = torch.tensor([[F, 0, (W - 1) / 2], [0, F, 40.0], [0, 0, 1]], dtype=torch.float64)
    return Camera(K.expand(batch, 3, 3), torch.full((batch,), HEIGHT, dtype=torch.float64))


def ground_points() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The road point (X, Z) of every pixel of :func:`level_camera`, written out for a level camera:
    Z = h f / (v - c_y), X = (u - c_x) Z / f; and whether the pixel sees the road."""
    v = torch.arange(H, dtype=torch.float64).reshape(-1, 1).expand(H, W)
    u = torch.arange(W, dtype=torch.float64).reshape(1, -1).expand(H, W)
    below = v > 40.0
    Z = HEIGHT * F / torch.where(below, v - 40.0, 1.0)
    return (u - (W - 1) / 2) * Z / F, Z, below


@pytest.mark.parametrize("curvature", [0.08, -0.03])
def test_a_curved_seed_is_the_band_along_the_arc(curvature):
    """The path turns by κ per metre: the arc from the camera, heading forward, through the points
    (1 − cos κs, sin κs) / κ. Sampled every 2 cm up to the seed's depth, a pixel whose road
    point lies nearer than half the width to a sample is in the seed, one farther from every sample
    is not (a margin of 3 cm either way: the samples' spacing, and the end of the arc, where the
    seed ends square and the samples' nearest distance rounds it)."""
    width, depth = 3.0, 15.0
    seed = road_seed(level_camera(), (H, W), width_m=width, depth_m=depth, curvature=curvature)[0, 0]
    X, Z, below = ground_points()
    s = torch.arange(0.0, depth + 1e-9, 0.02, dtype=torch.float64)
    ax, az = (1 - torch.cos(curvature * s)) / curvature, torch.sin(curvature * s) / curvature
    pts = torch.stack([X[below], Z[below]], -1)
    d2 = torch.full((pts.shape[0],), math.inf, dtype=torch.float64)
    nearest = torch.zeros(pts.shape[0], dtype=torch.float64)
    for chunk in torch.arange(s.numel()).split(256):
        dist = (pts[:, None, 0] - ax[chunk]) ** 2 + (pts[:, None, 1] - az[chunk]) ** 2
        best, at = dist.min(1)
        closer = best < d2
        d2, nearest = torch.where(closer, best, d2), torch.where(closer, s[chunk][at], nearest)
    dist = d2.sqrt()
    inside = (dist < width / 2 - 0.03) & (nearest < depth - 0.03)
    outside = dist > width / 2 + 0.03
    got = seed[below]
    assert bool(got[inside].all()) and not bool(got[outside].any())
    assert int(inside.sum()) > 500 and not bool(seed[~below].any())


def test_a_curved_seed_turns_towards_its_side_and_mirrors():
    """A left turn's seed is the right turn's mirrored (a camera centred on its middle column); a
    straight path (curvature 0, as a number or per sample) is the seed straight ahead."""
    right = road_seed(level_camera(), (H, W), curvature=0.05)[0, 0]
    left = road_seed(level_camera(), (H, W), curvature=-0.05)[0, 0]
    straight = road_seed(level_camera(), (H, W))[0, 0]
    assert torch.equal(left, right.flip(-1)) and not torch.equal(right, straight)
    columns = torch.arange(W, dtype=torch.float64)
    assert float(columns[right.any(0)].mean()) > float(columns[straight.any(0)].mean())  # (its far part: to the right)
    both = road_seed(level_camera(2), (H, W), curvature=torch.tensor([0.0, 0.05], dtype=torch.float64))
    assert torch.equal(both[0, 0], straight) and torch.equal(both[1, 0], right)
    assert torch.equal(road_seed(level_camera(), (H, W), curvature=torch.zeros(1))[0, 0], straight)


@pytest.mark.parametrize("curvature, error, match", [
    (float("nan"), ValueError, "curvature: expected a finite number"),
    ("0.1", TypeError, "curvature: expected a finite number"),
    (torch.tensor([0.1, 0.2, 0.3]), ValueError, r"curvature: expected a number or a 1-D tensor of 1 or 2 values"),
    (torch.tensor([0.1, float("inf")]), ValueError, "curvature: expected finite values"),
    (torch.tensor([1, 2]), TypeError, "curvature"),
])
def test_a_bad_curvature_is_refused_naming_it(curvature, error, match):
    with pytest.raises(error, match=match):
        road_seed(level_camera(2), (H, W), curvature=curvature)


def test_the_path_curvature_bends_only_what_leaves_the_straight_seed():
    """κ = yaw / z_d, where the arc's offset at the seed's depth (κ depth² / 2) exceeds its half width
    (|κ| > width / depth²: 0.01 /m for 4 m and 20 m); 0 below, for a motion that does not drive
    forwards, and for one that does not move sideways towards the turn by at least half its rear
    axle's chord, z_d yaw / 4 (a camera turned in place)."""
    rows = [  # (yaw rad, x_d m, z_d m, expected κ)
        (0.0, 0.0, 1.2, 0.0),
        (0.011, 0.0066, 1.2, 0.0),             # |κ| 0.0092 /m: the path stays in the straight seed
        (-0.013, -0.008, 1.2, -0.013 / 1.2),  # a left turn
        (0.05, 0.03, 1.0, 0.05),
        (0.05, 0.0126, 1.0, 0.05),            # just beyond a quarter of z_d yaw sideways
        (0.05, 0.0124, 1.0, 0.0),             # just short of it
        (0.05, 0.0, 1.0, 0.0),                # turned in place
        (0.05, -0.02, 1.0, 0.0),              # sideways away from the turn
        (0.05, 0.03, 0.0, 0.0),               # not moving
        (0.05, 0.03, -1.0, 0.0),              # backwards
    ]
    yaw, x_d, z_d, want = (torch.tensor(c, dtype=torch.float64) for c in zip(*rows))
    torch.testing.assert_close(path_curvature(yaw, x_d, z_d, 4.0, 20.0), want, rtol=1e-12, atol=0)


class CountingEstimator(ImageMotionEstimator):
    """The default image estimator, counting its calls."""

    def __init__(self):
        super().__init__()
        self.calls = 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return super().__call__(*args, **kwargs)


@pytest.fixture(scope="module")
def drives():
    """The default scene's pair 10 at half size in a turn of radius 27 m (steering -0.1 rad at
    12 m/s, 2.6° of yaw a frame) and driven straight, each detected alone (with the number of
    motion estimates it took)."""
    out = {}
    for name, steering in (("turn", {"steering": -0.1}), ("straight", {})):
        p = render_pair("default", 10, size=(188, 621), **steering)
        estimator = CountingEstimator()
        det = detect_road(p["image1"][None], p["image2"][None], p["camera"], estimator=estimator)
        out[name] = (p, det, estimator.calls)
    return out


def iou(mask, truth):
    return float((mask & truth).sum() / (mask | truth).sum())


def test_a_sharp_turn_is_found_along_the_path_and_a_straight_road_along_the_axis(drives):
    """In the turn the straight seed runs onto what the vehicle heads for, and the motion fitted
    on it is judged implausible; the seed along the path that motion turns on finds the road (two
    detections: four estimates). Driven straight, the path stays inside the straight seed: one
    detection (the seed's estimate and the refit)."""
    p, det, calls = drives["turn"]
    truth = p["road"][None]
    straight = detect_road(p["image1"][None], p["image2"][None], p["camera"], follow_path=False)
    assert det.flag == ["ok"] and straight.flag == ["implausible"] and calls == 4
    assert iou(det.mask, truth) > 0.6 and iou(det.mask, truth) > iou(straight.mask, truth) + 0.3
    assert not torch.equal(det.seed, straight.seed) and float(det.seed_agreement) > 0.9
    p, det, calls = drives["straight"]
    assert det.flag == ["ok"] and calls == 2


def test_in_a_batch_each_sample_keeps_its_own_seed(drives):
    """A turn and a straight drive in one batch: each sample's detection (seed, mask, flag, motion)
    is the one it gets alone, the turn's from the seed along its path, the other's from the
    straight seed."""
    (turn, _, _), (straight, _, _) = drives["turn"], drives["straight"]
    both = detect_road(torch.stack([turn["image1"], straight["image1"]]),
                       torch.stack([turn["image2"], straight["image2"]]), turn["camera"])
    for k, name in enumerate(("turn", "straight")):
        alone = drives[name][1]
        assert both.flag[k] == alone.flag[0] == "ok"
        for field in ("mask", "seed", "evidence", "height", "seed_agreement", "coverage"):
            assert torch.equal(getattr(both, field)[k], getattr(alone, field)[0]), field
        for param, value in alone.motion.params.items():
            torch.testing.assert_close(both.motion.params[param][k:k + 1], value, rtol=0, atol=1e-9)
    assert not torch.equal(both.seed[0], both.seed[1])  # (the turn's seed bends)
