"""Tests of the procedural scene renderer: contract, errors, and its ground truth against
independent references (the paper's formula, rigid back-projection from depth, photometric
consistency, OpenCV DIS)."""

from __future__ import annotations

import math

import pytest
import torch

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.egomotion import ego_motion_from_ackermann
from fsof_torch.geometry.road_flow import displacement_flow, velocity_flow
from fsof_torch.data.scene import (KITTI_K, KITTI_SIZE, LABELS, PRESETS, SENSOR_NOISE, SceneConfig, collate, render_pair,
                              render_sequence, scene_config)

TINY = (40, 128)
SMALL = (64, 160)
MEDIUM = (96, 320)
KEYS = {"image1", "image2", "flow", "valid", "flow_velocity", "road", "labels", "depth", "moving",
        "camera", "odometry", "velocity", "pose1", "pose2", "road_pose", "plane", "index"}


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def default_pair64(one_thread) -> dict:
    return render_pair("default", 0, size=MEDIUM, dtype=torch.float64)


# -- smoke -------------------------------------------------------------------------------------------

def test_render_pair_contract(dtype):
    pair = render_pair("default", 0, size=SMALL, dtype=dtype)
    H, W = SMALL
    assert KEYS <= set(pair)
    for key, shape in (("image1", (3, H, W)), ("image2", (3, H, W)), ("flow", (2, H, W)),
                       ("flow_velocity", (2, H, W)), ("depth", (1, H, W))):
        assert pair[key].shape == shape and pair[key].dtype == dtype, key
    for key in ("valid", "road", "moving"):
        assert pair[key].shape == (1, H, W) and pair[key].dtype == torch.bool, key
    assert pair["labels"].shape == (H, W) and pair["labels"].dtype == torch.int64
    assert 0 <= float(pair["image1"].min()) and float(pair["image1"].max()) <= 255
    assert float(pair["image1"].std()) > 10  # not flat
    cam = pair["camera"]
    assert isinstance(cam, Camera) and cam.batch_size == 1 and cam.dtype == dtype
    assert set(pair["odometry"]) == {"x_d", "z_d", "yaw"}
    assert set(pair["velocity"]) == {"speed", "steering", "wheelbase", "dt"}
    assert all(isinstance(v, float) for v in [*pair["odometry"].values(), *pair["velocity"].values()])
    for key in ("flow", "flow_velocity", "depth", "image1", "image2"):
        assert torch.isfinite(pair[key]).all(), key
    assert pair["pose1"].shape == (4, 4) and pair["pose1"].dtype == torch.float64


def test_presets_exist_and_render():
    assert {"default", "cvc-simple", "cvc-complex", "carla-straight", "carla-turning"} <= set(PRESETS)
    for name in PRESETS:
        pair = render_pair(name, 0, size=TINY)
        assert pair["road"].any(), name
        assert pair["valid"].float().mean() > 0.3, name


def test_sequence_shares_frames_and_equals_pairs():
    seq = render_sequence("cvc-complex", 3, size=TINY, progress=True)
    assert len(seq) == 3 and [p["index"] for p in seq] == [0, 1, 2]
    for a, b in zip(seq, seq[1:]):
        torch.testing.assert_close(a["image2"], b["image1"], atol=0, rtol=0)
    single = render_pair("cvc-complex", 2, size=TINY)
    for key in ("image1", "image2", "flow", "valid", "labels"):
        torch.testing.assert_close(single[key], seq[2][key], atol=0, rtol=0)


def test_sequence_bar_ends_its_line_before_an_error(monkeypatch):
    """An error (or Ctrl-C) while a pair renders: its traceback began on the bar's line, after the
    bar's text, and the bar was drawn once more after the traceback when the process let go of
    it. Now the bar ends its line, at the pairs done, before the error leaves render_sequence."""
    import gc
    import io
    import sys

    from fsof_torch.data.scene import render

    real = render._Renderer.pair

    def pair(self, k):
        if k == 2:
            raise KeyboardInterrupt
        return real(self, k)

    monkeypatch.setattr(render._Renderer, "pair", pair)
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # (a log: not a terminal)
    try:
        render_sequence("cvc-complex", 4, size=TINY, progress=True)
    except KeyboardInterrupt:
        shown = sys.stderr.getvalue()  # (what the traceback follows)
    gc.collect()
    assert shown.endswith("]\n") and " 2/4 " in shown.rsplit("\r", 1)[1], shown
    assert sys.stderr.getvalue() == shown


_PIXEL_KEYS = ("image1", "image2", "flow", "valid", "flow_velocity", "road", "labels", "depth", "moving")


def _frames_rendered(monkeypatch) -> list[int]:
    """The frame indices the renderer casts pixel-centre rays for, in order (one per new frame)."""
    import fsof_torch.data.scene.render as render

    rendered: list[int] = []
    cast = render.cast_rays

    def counting(scene, k, *args, **kwargs):
        if kwargs.get("grid", True):
            rendered.append(k)
        return cast(scene, k, *args, **kwargs)

    monkeypatch.setattr(render, "cast_rays", counting)
    return rendered


def test_consecutive_calls_render_the_shared_frame_once(monkeypatch):
    """render_pair(k) then render_pair(k + 1) renders frame k + 1 once; any other call (the same
    pair again, a gap, another seed, size or dtype) renders both its frames."""
    render_pair("cvc-simple", 0, size=TINY, seed=7)
    rendered = _frames_rendered(monkeypatch)
    calls = [((1,), {}, [2]), ((2,), {}, [3]), ((2,), {}, [2, 3]), ((5,), {}, [5, 6]),
             ((6,), {"seed": 8}, [6, 7]), ((7,), {"dtype": torch.float64}, [7, 8]), ((8,), {}, [8, 9])]
    for args, kwargs, frames in calls:
        rendered.clear()
        render_pair("cvc-simple", *args, **{"size": TINY, "seed": 7, **kwargs})
        assert rendered == frames, (args, kwargs)
    rendered.clear()
    render_sequence("cvc-simple", 2, size=TINY, seed=7, start=10)
    render_sequence("cvc-simple", 2, size=TINY, seed=7, start=12)
    assert rendered == [10, 11, 12, 13, 14]


def test_kept_frame_gives_the_same_pixels_and_shares_no_tensor():
    """Pairs rendered one call at a time, in any order, equal a fresh sequence's bit for bit, and
    writing into every tensor of a returned pair (the camera's too) changes no later pair."""
    seq = render_sequence("cvc-complex", 4, size=TINY, seed=3, dtype=torch.float64)
    fresh = [{k: p[k].clone() for k in _PIXEL_KEYS} | {"K": p["camera"].K.clone()} for p in seq]
    for index in (0, 1, 2, 1, 2, 3, 0):
        pair = render_pair("cvc-complex", index, size=TINY, seed=3, dtype=torch.float64)
        for key in _PIXEL_KEYS:
            assert torch.equal(pair[key], fresh[index][key]), (index, key)
        assert torch.equal(pair["camera"].K, fresh[index]["K"])
        for key in _PIXEL_KEYS:  # a caller's in-place edits
            pair[key].logical_not_() if pair[key].dtype == torch.bool else pair[key].add_(1000)
        pair["camera"].K.mul_(2)
    other = render_pair("cvc-complex", 1, size=TINY, seed=4, dtype=torch.float64)  # its own frames
    assert not torch.equal(other["image1"], fresh[1]["image1"])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_pairs_of_one_sequence_do_not_share_a_camera(dtype):
    """In float64 every pair held the scene's own Camera: editing pair 0's K changed pair 1's."""
    seq = render_sequence("cvc-simple", 2, size=TINY, dtype=dtype)
    a, b = seq[0]["camera"], seq[1]["camera"]
    assert a is not b and a.K.data_ptr() != b.K.data_ptr() and a.dtype == dtype
    fx = float(b.K[0, 0, 0])
    a.K[0, 0, 0] = 1.0
    assert float(b.K[0, 0, 0]) == fx


def test_threads_rendering_pairs_in_order_get_the_same_pixels():
    """Threads that render pairs 0, 1, 2 of one scene at the same time (each taking or keeping the
    shared frame) get exactly the pixels of one sequence."""
    from concurrent.futures import ThreadPoolExecutor

    seq = render_sequence("cvc-simple", 3, size=TINY, seed=11)

    def run(_):
        return [render_pair("cvc-simple", i, size=TINY, seed=11) for i in range(3)]

    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(run, range(4)))
    for pairs in results:
        for pair, ref in zip(pairs, seq):
            for key in _PIXEL_KEYS:
                assert torch.equal(pair[key], ref[key]), key


def test_same_seed_same_pixels_other_seed_other_scene():
    a = render_pair("default", 1, seed=3, size=TINY)
    b = render_pair("default", 1, seed=3, size=TINY)
    c = render_pair("default", 1, seed=4, size=TINY)
    for key in ("image1", "image2", "flow", "valid", "labels", "depth"):
        torch.testing.assert_close(a[key], b[key], atol=0, rtol=0)
    assert not torch.equal(a["image1"], c["image1"])


def test_scene_config_overrides():
    cfg = scene_config("cvc-simple", speed_factor=4, roll=0.1)
    assert isinstance(cfg, SceneConfig) and cfg.speed_factor == 4 and cfg.roll == 0.1
    assert PRESETS["cvc-simple"].speed_factor == 1  # presets are not modified


# -- exceptions ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, error, match", [
    (dict(preset="nope"), ValueError, "preset: expected one of"),
    (dict(preset=3), TypeError, "preset: expected a preset name"),
    (dict(colour="red"), TypeError, "unknown overrides"),
    (dict(dtype=torch.float16), TypeError, "dtype: expected torch.float32 or torch.float64"),
    (dict(index=-1), ValueError, "index: expected an int >= 0, got -1"),
    (dict(index=1.5), TypeError, "index: expected an int, got float 1.5"),
    (dict(size=(0, 10)), ValueError, "size: expected positive sides"),
    (dict(size=(10.5, 10)), TypeError, "size: expected integer sides"),
    (dict(supersample=0), ValueError, r"supersample: expected an integer in \[1, 16\]"),
    (dict(x_d=0.1), ValueError, "x_d, z_d, yaw: give all three or none"),
    (dict(steering=2.0), ValueError, "steering: expected"),
    (dict(height=-1.0), ValueError, "height: expected > 0"),
    (dict(speed=float("nan")), ValueError, "speed: expected a finite number"),
    (dict(noise=-1.0), ValueError, "noise: expected >= 0"),
    (dict(asphalt=(1.0, 2.0)), ValueError, r"asphalt: expected 7 amplitudes in \[0, 10000\] grey levels"),
    (dict(roll=1.0), ValueError, "roll, pitch: expected"),
    (dict(adaptive="False"), TypeError, "adaptive: expected True or False, got str 'False'"),
    (dict(buildings=1), TypeError, "buildings: expected True or False, got int 1"),
    # (a frame's poses and objects are built from frame 0 on: an index of 10**9 filled memory)
    (dict(index=100_000), ValueError, "index: expected at most 99999, got 100000"),
    (dict(size=(16, 16385)), ValueError, r"size: expected sides of at most 16384 pixels, got \(16, 16385\)"),
    # an int beyond float's range was an OverflowError from math.isfinite (a traceback, no option named)
    (dict(speed=10**400), ValueError, r"^speed: expected a finite number, got 1000.*\(401 characters\)$"),
    (dict(x_d=10**400, z_d=1.0, yaw=0.0), ValueError, r"^x_d: expected a finite number"),
    (dict(grade_start=-10**400), ValueError, r"^grade_start: expected a finite number"),
    (dict(K=((10**400, 0, 600), (0, 700, 170), (0, 0, 1))), ValueError, r"^K: expected a 3×3 matrix of finite numbers"),
])
def test_render_pair_errors(kwargs, error, match):
    kwargs = {"preset": "default", "size": TINY, **kwargs}
    with pytest.raises(error, match=match):
        render_pair(**kwargs)


def test_render_sequence_errors():
    with pytest.raises(ValueError, match="num_pairs: expected an int >= 1"):
        render_sequence("default", 0, size=SMALL)
    with pytest.raises(ValueError, match="start: expected an int >= 0, got -1"):
        render_sequence("default", 1, start=-1, size=SMALL)
    with pytest.raises(TypeError, match="start: expected an int, got float 1.5"):
        render_sequence("default", 1, start=1.5, size=SMALL)
    with pytest.raises(TypeError, match="num_pairs: expected an int"):
        render_sequence("default", 1.5, size=SMALL)
    with pytest.raises(ValueError, match="pairs: expected a non-empty list"):
        collate([])
    with pytest.raises(ValueError, match=r"num_pairs: expected start \+ num_pairs \(the last frame\) at most 100000, "
                                         r"got 99990 \+ 11"):
        render_sequence("default", 11, start=99_990, size=SMALL)
    with pytest.raises(TypeError, match="progress: expected True or False, got str 'False'"):
        render_sequence("default", 1, size=SMALL, progress="False")
    from fsof_torch.datasets import SceneDataset

    with pytest.raises(ValueError, match=r"num_pairs: expected start \+ num_pairs \(the last frame\) at most 100000, "
                                         r"got 0 \+ 1000000000000"):
        SceneDataset("default", 10**12)


def test_rendering_under_autocast_is_rendering_without():
    """Under CPU autocast the scene renders as without it (was: the moving cars' flow in bfloat16,
    off by up to 0.18 px, and their validity changed on the cars' edges)."""
    plain = render_pair("cvc-complex", 0, size=SMALL)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        under = render_pair("cvc-complex", 0, size=SMALL)
    assert bool(plain["moving"].any())
    for key in ("image1", "image2", "flow", "valid", "flow_velocity", "depth"):
        assert torch.equal(under[key], plain[key]), key


# -- cardinality ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("batch", [1, 3])
def test_collate(batch):
    pairs = render_sequence("cvc-simple", batch, size=(48, 80))
    out = collate(pairs)
    assert out["image1"].shape == (batch, 3, 48, 80)
    assert out["valid"].shape == (batch, 1, 48, 80) and out["labels"].shape == (batch, 48, 80)
    assert out["camera"].batch_size == batch and out["camera"].K.shape == (batch, 3, 3)
    assert out["odometry"]["z_d"].shape == (batch,) and out["velocity"]["dt"].shape == (batch,)
    assert out["odometry"]["z_d"].dtype == out["camera"].dtype
    assert out["index"] == list(range(batch))


def test_collate_errors_name_its_argument_pairs():
    """fs.collate's errors named ``samples``, the argument of the items' collate it calls; a
    string or number was a ValueError."""
    a, b = render_sequence("cvc-simple", 2, size=(48, 80))
    with pytest.raises(ValueError, match=r"^pairs: item 1 has different keys from item 0 \(differing: \['depth'\]\)$"):
        collate([a, {k: v for k, v in b.items() if k != "depth"}])
    with pytest.raises(ValueError, match=r"^pairs: 'image1' has different shapes"):
        collate([a, {**b, "image1": b["image1"][:, :24]}])
    with pytest.raises(TypeError, match=r"^pairs: expected a non-empty list of dicts, got str$"):
        collate("pairs")
    with pytest.raises(TypeError, match=r"^pairs: item 1 is a int, expected a dict$"):
        collate([a, 3])


def test_size_scales_intrinsics():
    pair = render_pair("cvc-simple", 0, size=(75, 414))
    ref = Camera(torch.tensor(KITTI_K, dtype=torch.float64), 1.5).scaled(414 / KITTI_SIZE[1], 75 / KITTI_SIZE[0])
    torch.testing.assert_close(pair["camera"].K, ref.K.float())
    assert pair["image1"].shape == (3, 75, 414)


# -- feature: the formula against the renderer's geometry ------------------------------------------------

DEG = math.pi / 180
CROSS_CHECK = [
    ("default", {}),
    ("cvc-simple", {}), ("cvc-simple", {"speed_factor": 4}),
    ("cvc-complex", {}), ("cvc-complex", {"speed_factor": 4}),
    ("carla-straight", {}), ("carla-straight", {"roll": 5 * DEG}), ("carla-straight", {"roll": -10 * DEG}),
    ("carla-turning", {}), ("carla-turning", {"roll": -5 * DEG}), ("carla-turning", {"roll": 10 * DEG}),
    ("carla-turning", {"roll": 3 * DEG, "pitch": -2 * DEG, "steering": -0.15}),
    ("default", {"x_d": 1.2 * math.tan(0.01), "z_d": 1.2, "yaw": 0.02}),  # the chord of an arc: x_d = z_d tan(yaw / 2)
    ("cvc-complex", {"x_d": -0.7 * math.tan(-0.005), "z_d": -0.7, "yaw": -0.01}),  # reversing
    ("default", {"speed": 0.0}),
    # a skewed K (the renderer's rays and its ground truth take K's skew as the road model does)
    ("carla-turning", {"K": ((721.5377, 60.0, 609.5593), (0.0, 721.5377, 172.854), (0.0, 0.0, 1.0))}),
]


@pytest.mark.parametrize("preset, overrides", CROSS_CHECK)
def test_road_flow_equals_formula(preset, overrides):
    pair = render_pair(preset, 1, size=SMALL, dtype=torch.float64, **overrides)
    cam, odo, vel = pair["camera"], pair["odometry"], pair["velocity"]
    flow_d, valid_d = displacement_flow(cam, odo["x_d"], odo["z_d"], odo["yaw"], SMALL)
    flow_v, valid_v = velocity_flow(cam, vel["speed"], vel["steering"], vel["wheelbase"], SMALL)
    road = pair["road"]
    assert int(road.sum()) > 500
    assert bool(valid_d[0][road].all()) and bool(valid_v[0][road].all())  # road is below the horizon
    err_d = (pair["flow"] - flow_d[0]).norm(dim=0)[road[0]]
    err_v = (pair["flow_velocity"] - flow_v[0]).norm(dim=0)[road[0]]
    assert float(err_d.mean()) <= 0.01 and float(err_d.max()) < 1e-6
    assert float(err_v.mean()) <= 0.01 and float(err_v.max()) < 1e-6
    if "z_d" in overrides:
        assert odo == pytest.approx({k: overrides[k] for k in ("x_d", "z_d", "yaw")})
        assert math.copysign(1.0, vel["speed"]) == math.copysign(1.0, overrides["z_d"])
    if "roll" in overrides:
        assert float(cam.roll[0]) == pytest.approx(overrides["roll"])


def test_float32_matches_float64():
    a = render_pair("carla-turning", 0, size=SMALL, dtype=torch.float32, roll=5 * DEG)
    b = render_pair("carla-turning", 0, size=SMALL, dtype=torch.float64, roll=5 * DEG)
    both = a["valid"][0] & b["valid"][0]
    assert float((a["flow"].double() - b["flow"]).norm(dim=0)[both].max()) < 0.02
    assert float((a["image1"].double() - b["image1"]).abs().mean()) < 0.5
    assert float((a["valid"] != b["valid"]).float().mean()) < 0.01


def test_odometry_and_velocity_are_ackermann():
    pair = render_pair("carla-turning", 0, size=SMALL)
    vel, odo = pair["velocity"], pair["odometry"]
    ego = ego_motion_from_ackermann(torch.tensor([vel["speed"]], dtype=torch.float64), vel["steering"],
                                    vel["wheelbase"], vel["dt"])
    assert odo["x_d"] == pytest.approx(float(ego.x_d[0]), abs=1e-12)
    assert odo["z_d"] == pytest.approx(float(ego.z_d[0]), abs=1e-12)
    assert odo["yaw"] == pytest.approx(float(ego.yaw[0]), abs=1e-12) and odo["yaw"] > 0
    fast = render_pair("cvc-simple", 0, size=SMALL, speed_factor=4)
    slow = render_pair("cvc-simple", 0, size=SMALL)
    assert fast["odometry"]["z_d"] == pytest.approx(4 * slow["odometry"]["z_d"])
    # the relative camera pose agrees with the odometry: p_v(t+1) = R_φ (p_v(t) - d)
    rel = torch.linalg.inv(pair["pose2"]) @ pair["pose1"]
    assert float(rel[:3, 3].norm()) == pytest.approx(math.hypot(odo["x_d"], odo["z_d"]), rel=1e-9)


def _rigid_flow(pair: dict) -> torch.Tensor:
    """Flow of static points from depth, the camera and the odometry (an independent reference)."""
    cam, odo = pair["camera"], pair["odometry"]
    _, H, W = pair["depth"].shape
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)]).reshape(3, -1)
    pc = (cam.K_inv()[0] @ pix) * pair["depth"].reshape(1, -1)
    Rc = cam.mounting()[0]
    pv = Rc.T @ pc
    c, s = math.cos(odo["yaw"]), math.sin(odo["yaw"])
    R_phi = torch.tensor([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=torch.float64)
    d = torch.tensor([[odo["x_d"]], [0.0], [odo["z_d"]]], dtype=torch.float64)
    q = cam.K[0] @ Rc @ R_phi @ (pv - d)
    return (q[:2] / q[2:] - pix[:2]).reshape(2, H, W)


def test_static_structure_and_moving_cars():
    pair = render_pair("cvc-complex", 0, size=MEDIUM, dtype=torch.float64, moving_cars=4.0)
    labels = pair["labels"]
    ref = _rigid_flow(pair)
    static = (labels != LABELS["sky"]) & ~pair["moving"][0]
    err = (pair["flow"] - ref).norm(dim=0)
    assert float(err[static].max()) < 1e-6
    moving = pair["moving"][0]
    assert int(moving.sum()) > 20
    assert float(err[moving].mean()) > 0.5  # moving cars do not move like the static world
    assert bool((labels[moving] == LABELS["car"]).all())


@pytest.mark.parametrize("preset, overrides", [
    ("carla-turning", {"roll": 0.05, "pitch": -0.02}),
    # body motion and a grade: the rates of the camera's attitude and height are in the px/s truth
    ("body-motion", {}), ("crest", {"body_pitch": DEG, "body_roll": DEG, "body_height": 0.02}), ("dip", {}),
])
def test_velocity_flow_is_the_limit_of_displacement_flow(preset, overrides):
    # every pixel, moving cars included: flow / dt -> flow_velocity as dt -> 0, linearly in dt
    errors = {}
    for dt in (1e-2, 1e-3):
        pair = render_pair(preset, 0, size=SMALL, dtype=torch.float64, dt=dt, moving_cars=4.0, **overrides)
        for name, mask in (("static", ~pair["moving"][0]), ("moving", pair["moving"][0])):
            mask = mask & pair["valid"][0]
            assert int(mask.sum()) > 20, name
            diff = (pair["flow"] / dt - pair["flow_velocity"]).norm(dim=0)[mask].mean()
            errors[name, dt] = float(diff / pair["flow_velocity"].norm(dim=0)[mask].mean())
    for name in ("static", "moving"):
        assert errors[name, 1e-3] < 0.01
        assert errors[name, 1e-3] < 0.2 * errors[name, 1e-2]


def test_off_road_flow_is_not_plane_flow(default_pair64):
    pair = default_pair64
    cam, odo = pair["camera"], pair["odometry"]
    flow_d, valid_d = displacement_flow(cam, odo["x_d"], odo["z_d"], odo["yaw"], MEDIUM)
    labels = pair["labels"]
    for name in ("car", "building"):
        mask = (labels == LABELS[name]) & valid_d[0, 0]
        assert int(mask.sum()) > 50, name
        diff = (pair["flow"] - flow_d[0]).norm(dim=0)[mask]
        assert float(diff.mean()) > 1.0, name


def test_depth_on_level_road():
    pair = render_pair("cvc-simple", 0, size=SMALL, dtype=torch.float64)
    cam = pair["camera"]
    v = torch.arange(SMALL[0], dtype=torch.float64).reshape(-1, 1).expand(SMALL)
    expected = cam.height[0] * cam.fy[0] / (v - cam.cy[0])
    road = pair["road"][0]
    torch.testing.assert_close(pair["depth"][0][road], expected[road], atol=1e-9, rtol=1e-9)
    assert bool((pair["depth"][0][pair["labels"] == LABELS["sky"]] == 0).all())


def test_labels_and_masks(default_pair64):
    pair = default_pair64
    labels = pair["labels"]
    assert set(labels.unique().tolist()) <= set(LABELS.values())
    assert {LABELS["road"], LABELS["marking"], LABELS["car"], LABELS["building"], LABELS["pavement"]} <= set(labels.unique().tolist())
    road = (labels == LABELS["road"]) | (labels == LABELS["marking"])
    assert torch.equal(pair["road"][0], road)
    assert not bool(pair["valid"][0][labels == LABELS["sky"]].any())
    # leaving the view is invalid
    H, W = MEDIUM
    u = torch.arange(W, dtype=torch.float64) + pair["flow"][0]
    v = torch.arange(H, dtype=torch.float64).reshape(-1, 1) + pair["flow"][1]
    outside = (u < 0) | (u > W - 1) | (v < 0) | (v > H - 1)
    outside &= pair["flow"].abs().amax(0) > 1e-3  # (a point within 1e-3 px of its pixel is in view)
    assert int(outside.sum()) > 0 and not bool(pair["valid"][0][outside].any())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_camera_standing_still_keeps_its_border_pixels_valid(dtype):
    """A static point seen by a camera that does not move stays in view, on the border too; the
    projection rounded about half of the border pixels a hair outside (flow -1.4e-14 px at pixel
    (0, 0) in float64) and marked them invalid."""
    pair = render_pair("default", 1, size=SMALL, dtype=dtype, speed=0.0, moving_cars=0.0)
    H, W = SMALL
    border = torch.ones(H, W, dtype=torch.bool)
    border[1:-1, 1:-1] = False
    static = (pair["labels"] != LABELS["sky"]) & ~pair["moving"][0]
    assert int((border & static).sum()) > H
    assert float(pair["flow"].abs().amax(0)[static].max()) < 1e-3
    assert bool(pair["valid"][0][static].all())


def test_occluded_points_are_invalid():
    """Parked cars ahead: a point of frame t that lands inside frame t+1 is invalid where a nearer
    surface covers it there. Checked against frame t+1 rendered on its own: the point carried by
    depth and the poses lies behind the nearest of the four pixels around where it lands; a valid
    one is not behind all four."""
    seq = render_sequence("cvc-complex", 2, size=MEDIUM, dtype=torch.float64, parked_cars=6.0, start=2)
    pair, after = seq
    assert torch.equal(pair["pose2"], after["pose1"])
    H, W = MEDIUM
    cam = pair["camera"]
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)]).reshape(3, -1)
    rel = torch.linalg.inv(pair["pose2"]) @ pair["pose1"]  # camera t -> camera t+1
    q = rel[:3, :3] @ ((cam.K_inv()[0] @ pix) * pair["depth"].reshape(1, -1)) + rel[:3, 3:]
    z1 = q[2].reshape(H, W)
    p1 = cam.K[0] @ q
    u1, v1 = (p1[0] / p1[2]).reshape(H, W), (p1[1] / p1[2]).reshape(H, W)
    static = (pair["labels"] != LABELS["sky"]) & ~pair["moving"][0]
    assert float((u1 - u - pair["flow"][0])[static].abs().max()) < 1e-9  # the same landing point
    inside = (u1 >= 0) & (u1 <= W - 1) & (v1 >= 0) & (v1 <= H - 1) & static & (z1 > 0)
    x0, y0 = u1.floor().clamp(0, W - 1).long(), v1.floor().clamp(0, H - 1).long()
    x1, y1 = (x0 + 1).clamp(max=W - 1), (y0 + 1).clamp(max=H - 1)
    d1 = after["depth"][0]
    around = torch.stack([d1[y0, x0], d1[y0, x1], d1[y1, x0], d1[y1, x1]])
    occluded, seen = inside & ~pair["valid"][0], inside & pair["valid"][0]
    assert int(occluded.sum()) > 500 and int(seen.sum()) > 0.5 * H * W
    behind_nearest = z1 > 1.003 * around.min(0).values
    behind_all = z1 > 1.003 * around.max(0).values
    assert float(behind_nearest[occluded].double().mean()) > 0.99
    assert float(behind_all[seen].double().mean()) < 0.01


# -- feature: photometric consistency and trackability --------------------------------------------------

def _warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """``image`` (C, H, W) sampled at x + flow(x), bilinear (written here with grid_sample, apart
    from the library's warp)."""
    import torch.nn.functional as F

    _, H, W = image.shape
    u = torch.arange(W, dtype=flow.dtype) + flow[0]
    v = torch.arange(H, dtype=flow.dtype).reshape(-1, 1) + flow[1]
    grid = torch.stack([2 * u / (W - 1) - 1, 2 * v / (H - 1) - 1], dim=-1)
    return F.grid_sample(image[None].to(flow.dtype), grid[None], align_corners=True)[0]


def test_warp_by_ground_truth_is_photometrically_consistent(default_pair64):
    pair = default_pair64
    warped = _warp(pair["image2"], pair["flow"])
    mask = (pair["road"] & pair["valid"])[0]
    mae = (warped - pair["image1"]).abs().mean(0)[mask].mean()
    unwarped = (pair["image2"] - pair["image1"]).abs().mean(0)[mask].mean()
    assert float(mae) <= 2.0
    assert float(unwarped) > 2 * float(mae)


def test_sensor_noise_is_seeded_gaussian_and_per_frame(default_pair64):
    assert PRESETS["default"].noise == 0.0
    noisy = render_pair("default", 0, size=MEDIUM, dtype=torch.float64, noise=SENSOR_NOISE)
    assert torch.equal(noisy["flow"], default_pair64["flow"])  # noise changes the images only
    # given at 375 x 1242; a smaller render is that image area-averaged: sigma scales with sqrt(area)
    sigma = SENSOR_NOISE * math.sqrt(MEDIUM[0] * MEDIUM[1] / (KITTI_SIZE[0] * KITTI_SIZE[1]))
    clean = default_pair64
    for key in ("image1", "image2"):
        diff = noisy[key] - clean[key]
        inside = ((clean[key] > 5 * sigma) & (clean[key] < 255 - 5 * sigma)).all(0)  # away from the clamp
        d = diff[:, inside]
        assert torch.allclose(d[0], d[1], atol=1e-9) and torch.allclose(d[0], d[2], atol=1e-9)  # luminance noise
        assert float(d[0].mean()) == pytest.approx(0.0, abs=0.05 * sigma)
        assert float(d[0].std()) == pytest.approx(sigma, rel=0.05)
    # the two frames have independent noise; frame 1 of pair 0 is frame 0 of pair 1
    n1 = (noisy["image1"] - clean["image1"])[0]
    n2 = (noisy["image2"] - clean["image2"])[0]
    assert abs(float(torch.corrcoef(torch.stack([n1.flatten(), n2.flatten()]))[0, 1])) < 0.05
    nxt = render_pair("default", 1, size=MEDIUM, dtype=torch.float64, noise=SENSOR_NOISE)
    assert torch.equal(nxt["image1"], noisy["image2"])


def test_opencv_dis_tracks_the_road(default_pair64):
    import cv2
    import numpy as np
    pair = default_pair64
    grey = [cv2.cvtColor(pair[k].permute(1, 2, 0).numpy().astype(np.uint8), cv2.COLOR_RGB2GRAY)
            for k in ("image1", "image2")]
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = torch.from_numpy(dis.calc(grey[0], grey[1], None)).permute(2, 0, 1).double()
    assert bool(torch.isfinite(flow).all())
    mask = (pair["road"] & pair["valid"])[0]
    epe = (flow - pair["flow"]).norm(dim=0)[mask].mean()
    zero = pair["flow"].norm(dim=0)[mask].mean()
    assert float(epe) < 0.5 * float(zero)  # far better than no motion at all
