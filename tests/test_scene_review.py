"""The scene renderer in every grad mode, and the configuration bounds that keep a scene's geometry
what its docs say: the ego vehicle in its lane, the kerb top below the camera, body frequencies and
the vertical curve's start within physical ranges."""

from __future__ import annotations

import math
import re
from dataclasses import replace

import numpy as np
import pytest
import torch

from fsof_torch.data.scene import PRESETS, SceneConfig, render_pair, scene_config
from fsof_torch.data.scene.config import MAX_BODY_HZ, MAX_GRADE_START, MIN_TURN_RADIUS, path_curvature
from fsof_torch.data.scene.objects import BUILDING_BOX, CAR_BODY
from fsof_torch.data.scene.world import Scene
from fsof_torch.geometry.camera import pitch_matrix, roll_matrix

TINY = (12, 40)

pytestmark = pytest.mark.usefixtures("one_thread")


def _tensors(pair: dict) -> dict:
    return {k: v for k, v in pair.items() if torch.is_tensor(v)}


def _equal(a: dict, b: dict) -> bool:
    ta, tb = _tensors(a), _tensors(b)
    return ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta) and a["plane"] == b["plane"]


# -- grad modes ----------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", [torch.no_grad, torch.inference_mode])
@pytest.mark.parametrize("preset", ["body-motion", "crest"])
def test_riding_scenes_render_alike_in_every_grad_mode(mode, preset):
    ref = render_pair(preset, 2, seed=4, size=TINY)
    render_pair("cvc-simple", 0, size=TINY)  # another scene: nothing kept for the next call
    with mode():
        pair = render_pair(preset, 2, seed=4, size=TINY)
    assert _equal(pair, ref)
    assert bool(ref["flow_velocity"].abs().amax() > 0)
    cfg = scene_config(preset, size=TINY)
    with torch.enable_grad():
        rates = Scene(cfg, 4, torch.float64).pose_rates(5)
    with mode():
        scene = Scene(cfg, 4, torch.float64)  # its tensors made in that mode too
        got = scene.pose_rates(5)
    assert all(torch.equal(g, r) for g, r in zip(got, rates))
    assert not any(g.requires_grad for g in got) and bool(rates[1].abs().amax() > 1.0)  # ~12 m/s forward


def test_a_frame_kept_under_inference_mode_is_not_handed_to_a_call_outside_it():
    ref = render_pair("body-motion", 1, seed=2, size=TINY)
    with torch.inference_mode():
        render_pair("body-motion", 0, seed=2, size=TINY)  # keeps its frame 1
    pair = render_pair("body-motion", 1, seed=2, size=TINY)
    assert _equal(pair, ref) and not any(v.is_inference() for v in _tensors(pair).values())
    pair["image1"] += 1.0  # a caller's own tensor: writable outside inference mode


# -- the ego vehicle keeps its lane --------------------------------------------------------------
@pytest.mark.parametrize("overrides, names", [
    (dict(steering=0.4), "steering, wheelbase, lane_width"),           # radius 6.4 m: the vehicle left its lane
    (dict(steering=-0.6, wheelbase=2.7), "steering, wheelbase, lane_width"),
    (dict(steering=-0.4, lane_width=16.0), "steering, wheelbase, lane_width"),   # was a ZeroDivisionError
    (dict(steering=-0.3, lane_width=20.0), "steering, wheelbase, lane_width"),   # the road bent the other way
    (dict(steering=0.3, lane_width=20.0), "steering, wheelbase, lane_width"),    # the lane across the centre
    (dict(x_d=2.0 * math.tan(0.25), z_d=2.0, yaw=0.5), "x_d, z_d, yaw, lane_width"),
])
def test_a_turn_that_leaves_the_lane_is_refused(overrides, names):
    with pytest.raises(ValueError, match=f"^{names}: expected a turn that keeps the ego vehicle in its lane"):
        scene_config("default", **overrides)
    with pytest.raises(ValueError, match=f"^{names}:"):
        render_pair("default", 0, size=TINY, **overrides)


@pytest.mark.parametrize("overrides", [dict(steering=0.325), dict(steering=-0.3, lane_width=15.0),
                                       dict(steering=0.3, speed=-5.0)])
def test_an_accepted_turn_keeps_the_vehicle_in_the_centre_of_its_lane(overrides):
    cfg = scene_config("default", **overrides)
    kappa_v = math.tan(cfg.steering) / cfg.wheelbase
    assert 1 / abs(kappa_v) >= MIN_TURN_RADIUS and path_curvature(cfg) == kappa_v
    scene = Scene(cfg, 0, torch.float64)
    assert scene.road.kappa * kappa_v > 0  # the road bends the way the vehicle turns
    assert 1 / scene.road.kappa == pytest.approx(1 / kappa_v + cfg.lane_width / 2, rel=1e-12)
    for k in (0, 5, 20, 40):
        x, z, _ = scene.ego_pose(k)
        e = float(scene.road.lateral(torch.tensor(x, dtype=torch.float64), torch.tensor(z, dtype=torch.float64)))
        assert e == pytest.approx(cfg.lane_width / 2, abs=1e-9)


def test_every_preset_and_benchmark_turn_is_accepted():
    """Accepted as asked: the configuration is the preset with the overrides, nothing else changed."""
    for name in PRESETS:
        for factor in (1, 4):
            cfg = scene_config(name, speed_factor=factor)
            assert cfg.speed_factor == factor
            assert cfg == replace(PRESETS[name], speed_factor=factor)
    cfg = scene_config("default", steering=0.1)
    assert cfg.steering == 0.1 and cfg == replace(PRESETS["default"], steering=0.1)
    cfg = scene_config("carla-turning", steering=-0.15, roll=0.05)
    assert (cfg.steering, cfg.roll) == (-0.15, 0.05)
    assert cfg == replace(PRESETS["carla-turning"], steering=-0.15, roll=0.05)


# -- the kerb top below the camera ---------------------------------------------------------------
@pytest.mark.parametrize("overrides, bound", [
    (dict(kerb_height=2.0), 1.65),
    (dict(kerb_height=1.65), 1.65),
    (dict(kerb_height=1.0, body_height=0.8), 1.65 - 0.8),
    (dict(kerb_height=1.6, steering=0.0, grade_before=-0.2, grade_after=0.2),
     1.65 * 0.96 / math.sqrt(1.04)),
])
def test_a_kerb_reaching_the_camera_is_refused(overrides, bound):
    with pytest.raises(ValueError, match="^kerb_height: expected the kerb top below the camera") as info:
        scene_config("default", **overrides)
    assert f"= {bound!r} m, got {overrides['kerb_height']!r}" in str(info.value)


def test_the_highest_accepted_kerb_has_positive_depth_everywhere():
    kw = dict(kerb_height=0.84, body_height=0.8, body_height_hz=1.25)  # 1 cm under the camera at its lowest
    for k in range(0, 8):
        pair = render_pair("default", k, seed=3, size=(24, 80), dtype=torch.float64, **kw)
        depth, labels = pair["depth"][0], pair["labels"]
        assert bool((depth[labels != 0] > 0).all()) and bool((depth[labels == 0] == 0).all())


def test_the_camera_clearance_on_a_grade_is_at_least_the_bound():
    """Across a short, steep dip the road under the camera (not under the vehicle) comes closest;
    the bound (1 - G²) / sqrt(1 + G²) of the camera's height is met and nearly reached."""
    cfg = scene_config("default", steering=0.0, speed=1.0, dt=0.01, grade_before=-0.2, grade_after=0.2,
                       grade_start=1.0, grade_length=0.01, kerb_height=0.0)
    scene = Scene(cfg, 0, torch.float64)
    gaps = []
    for k in range(0, 250):
        c = scene.pose(k).c
        gaps.append(cfg.height - scene.grade.elevation_at(c[2]) - c[1])
    bound = cfg.height * 0.96 / math.sqrt(1.04)
    assert bound <= min(gaps) < 1.01 * bound and max(gaps) > cfg.height


# -- body frequencies and the vertical curve's start ---------------------------------------------
@pytest.mark.parametrize("name", ["body_pitch_hz", "body_roll_hz", "body_height_hz"])
def test_a_body_frequency_beyond_the_bound_is_refused(name):
    for value in (1e308, MAX_BODY_HZ * 1.001):
        with pytest.raises(ValueError, match=re.escape(f"{name}: expected a frequency <= 1000 Hz, got {value!r}")):
            render_pair("body-motion", 0, size=TINY, **{name: value})
    pair = render_pair("body-motion", 1, size=TINY, dtype=torch.float64, **{name: MAX_BODY_HZ})
    assert all(bool(torch.isfinite(v).all()) for v in _tensors(pair).values() if v.is_floating_point())
    assert all(math.isfinite(v) for v in pair["plane"].values()) and bool(pair["valid"].any())


@pytest.mark.parametrize("value", [1e308, -1e308, 1.0001e5, -1e300])
def test_a_grade_start_beyond_the_bound_is_refused(value):
    message = f"grade_start: expected within ±100000 m of the start, got {value!r}"
    with pytest.raises(ValueError, match=re.escape(message)):
        render_pair("crest", 0, size=TINY, grade_start=value, grade_length=1e300)


@pytest.mark.parametrize("start, length", [(MAX_GRADE_START, 1e-300), (-MAX_GRADE_START, 1e-300),
                                           (-MAX_GRADE_START, 1e308), (MAX_GRADE_START, 60.0)])
def test_a_grade_start_at_the_bound_renders_finite(start, length):
    pair = render_pair("crest", 2, size=TINY, dtype=torch.float64, grade_start=start, grade_length=length)
    assert all(bool(torch.isfinite(v).all()) for v in _tensors(pair).values() if v.is_floating_point())
    assert all(math.isfinite(v) for v in pair["plane"].values()) and bool(pair["road"].any())
    # the vehicle pitches with the grade before the curve, or after a curve passed 100 km back
    # (still +3 % when the curve is 1e308 m long); the world-to-camera rotation is R_roll R_pitch
    slope = 0.03 if start > 0 or length > 1e300 else -0.03
    t = lambda x: torch.tensor([x], dtype=torch.float64)  # noqa: E731
    A = (roll_matrix(t(math.pi / 180)) @ pitch_matrix(t(-math.pi / 180 + math.atan(slope))))[0]
    assert torch.allclose(pair["pose1"][:3, :3], A.T, rtol=0, atol=1e-12)


# -- the configuration is immutable: a caller's list changed later changes nothing -----------------
def test_asphalt_is_held_as_a_tuple_of_floats():
    amps = [25, 24, 7, 3, 8, 22, 20.0]
    cfg = scene_config("default", asphalt=amps)
    assert isinstance(cfg.asphalt, tuple) and cfg.asphalt == (25.0, 24.0, 7.0, 3.0, 8.0, 22.0, 20.0)
    assert all(type(a) is float for a in cfg.asphalt)
    amps[0] = 80.0
    assert cfg.asphalt[0] == 25.0


def test_an_asphalt_list_changed_between_calls_does_not_reuse_the_old_frame():
    amps = [25.0, 24.0, 7.0, 3.0, 8.0, 22.0, 20.0]
    render_pair("default", 0, size=TINY, asphalt=amps)  # keeps frame 1, rendered with these amplitudes
    amps[:] = [80.0] * 7  # the caller reuses its list for another scene
    pair = render_pair("default", 1, size=TINY, asphalt=amps)
    render_pair("cvc-simple", 0, size=TINY)  # another scene: nothing kept for the next call
    fresh = render_pair("default", 1, size=TINY, asphalt=[80.0] * 7)
    assert torch.equal(pair["image1"], fresh["image1"]) and torch.equal(pair["image2"], fresh["image2"])


def test_size_and_base_size_are_held_as_tuples_of_ints():
    """A list (or NumPy ints) for ``size`` or ``base_size`` is held as a tuple of ints: the
    configuration is hashable, equals the one given tuples, and the caller's list changed after
    the call changes nothing."""
    size, base = [np.int64(40), 120], [375, 1242]
    cfg = scene_config("default", size=size, base_size=base)
    assert cfg.size == (40, 120) and cfg.base_size == (375, 1242)
    assert all(type(v) is int for v in (*cfg.size, *cfg.base_size))
    assert cfg == scene_config("default", size=(40, 120)) and hash(cfg) == hash(scene_config("default", size=(40, 120)))
    size[0], base[0] = 80, 300
    assert cfg.size == (40, 120) and cfg.base_size == (375, 1242)


def test_a_base_size_list_changed_between_calls_does_not_reuse_the_old_frame():
    """The kept frame was keyed by a configuration holding the caller's list: changed in place
    between two calls, the second call took the frame rendered with the old intrinsics (pair 1's
    image1 seen by another camera than its flow)."""
    base = [375, 1242]
    render_pair("default", 0, size=TINY, base_size=base)  # keeps frame 1, K scaled from 375x1242
    base[:] = [300, 1000]
    pair = render_pair("default", 1, size=TINY, base_size=base)
    render_pair("cvc-simple", 0, size=TINY)  # another scene: nothing kept for the next call
    fresh = render_pair("default", 1, size=TINY, base_size=(300, 1000))
    assert torch.equal(pair["image1"], fresh["image1"]) and torch.equal(pair["flow"], fresh["flow"])


def test_a_configurations_size_list_changed_between_calls_renders_the_new_size():
    size = [16, 48]
    cfg = SceneConfig(size=size, supersample=1)
    render_pair(cfg, 0)
    size[:] = [8, 24]  # used to crash: the kept 16x48 frame read as an 8x24 one
    pair = render_pair(cfg, 1)
    assert pair["image1"].shape == pair["image2"].shape == (3, 8, 24) and pair["flow"].shape == (2, 8, 24)


# -- car densities and texture contrast within physical ranges -----------------------------------
@pytest.mark.parametrize("name", ["parked_cars", "moving_cars"])
def test_a_car_density_beyond_the_bound_is_refused(name):
    for value in (1e9, 100.5):  # 1e9 used to generate cars for minutes
        message = f"{name}: expected a mean number of cars per 40 m <= 100, got {value!r}"
        with pytest.raises(ValueError, match=re.escape(message)):
            render_pair("default", 0, size=TINY, **{name: value})
    pair = render_pair("default", 0, size=TINY, **{name: 100.0})
    assert bool(torch.isfinite(pair["image1"]).all()) and bool((pair["labels"] == 6).any())


def test_parked_cars_without_a_parking_strip_are_refused():
    """Parked cars stand on the parking strip: asked for with parking_width=0 they were silently
    left out (a scene without them); now a ValueError names both. Without cars, or with a strip,
    the scene renders (its parked cars in view)."""
    message = ("parked_cars, parking_width: parked cars need a parking strip, got parked_cars=2.0 with "
               "parking_width=0.0; give parking_width > 0 or parked_cars=0")
    with pytest.raises(ValueError, match=re.escape(message)):
        scene_config("cvc-simple", parked_cars=2.0)
    with pytest.raises(ValueError, match=r"^parked_cars, parking_width: parked cars need a parking strip"):
        render_pair("default", 0, size=TINY, parking_width=0.0)  # (the preset's 2.5 parked cars)
    assert scene_config("default", parking_width=0.0, parked_cars=0.0).parking_width == 0.0
    pair = render_pair("cvc-simple", 0, size=(48, 160), parking_width=2.3, parked_cars=100.0)
    assert bool((pair["labels"] == 6).any())  # (a car: the scene has no moving cars)


@pytest.mark.parametrize("overrides, message", [
    (dict(texture=1e38), "texture: expected a contrast multiplier <= 10000, got 1e+38"),
    (dict(texture=10000.5), "texture: expected a contrast multiplier <= 10000, got 10000.5"),
    (dict(asphalt=(1e39,) * 7), "asphalt: expected 7 amplitudes in [0, 10000] grey levels (one per octave), got "),
    (dict(asphalt=(25.0,) * 6 + (1e300,)), "asphalt: expected 7 amplitudes in [0, 10000] grey levels"),
    (dict(asphalt=(25.0,) * 6 + (-1.0,)), "asphalt: expected 7 amplitudes in [0, 10000] grey levels"),
])
def test_a_texture_contrast_beyond_the_bound_is_refused(overrides, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        render_pair("default", 0, size=TINY, **overrides)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_highest_texture_contrast_renders_finite_grey_levels(dtype):
    pair = render_pair("default", 0, size=TINY, dtype=dtype, texture=1e4, asphalt=(1e4,) * 7)
    for key in ("image1", "image2"):
        assert bool(((pair[key] >= 0) & (pair[key] <= 255)).all())  # False for NaN


# -- speed_factor multiplies the cars' speed once ------------------------------------------------
@pytest.mark.parametrize("preset", ["cvc-complex", "default"])
def test_speed_factor_multiplies_the_moving_cars_speed_as_the_ego_speed(preset):
    speeds, ego = {}, {}
    for factor in (1.0, 2.0, 4.0):
        scene = Scene(scene_config(preset, speed_factor=factor), 0, torch.float64)
        speeds[factor] = [o.vs for b in range(4) for o in scene.blocks(b) if o.vs != 0.0]
        ego[factor] = scene.motion.speed
    assert speeds[1.0]
    for factor in (2.0, 4.0):
        assert ego[factor] == pytest.approx(factor * ego[1.0])
        assert speeds[factor] == pytest.approx([factor * v for v in speeds[1.0]], rel=1e-12)


def test_the_travel_bound_counts_speed_factor_once():
    # 12 m/s at 10 Hz times 50: 60 m a frame for the ego vehicle and the cars' base speed
    scene_config("default", speed_factor=50.0)
    with pytest.raises(ValueError, match=re.escape("speed, speed_factor, dt: expected the moving cars' base travel")):
        scene_config("default", speed=0.0, speed_factor=201.0)  # 5 m/s · 201 · 0.1 s > 100 m
    scene_config("default", speed=0.0, speed_factor=200.0)


# -- render_pair's overrides are SceneConfig fields only -----------------------------------------
@pytest.mark.parametrize("overrides", [dict(start=3), dict(num_pairs=2), dict(progress=True), dict(wobble=1),
                                       dict(progress=False, start=0)])
def test_render_pair_refuses_what_is_not_a_scene_field(overrides):
    with pytest.raises(TypeError, match=re.escape(f"render_pair: unknown overrides {sorted(overrides)}; expected")):
        render_pair("default", 0, size=TINY, **overrides)


# -- a turning road is a full circle: the objects do not jump at half a lap ------------------------
@pytest.mark.parametrize("preset, overrides", [("default", dict(steering=0.1)), ("carla-turning", {}),
                                               ("default", dict(steering=-0.1, speed=-8.0))])
def test_the_objects_stay_the_same_across_the_half_lap(preset, overrides):
    """The ego arc length came from an angle that jumps from +πR to -πR after half a lap: the pair
    across the jump got another set of objects at t+1 (the default preset's pair 353)."""
    scene = Scene(scene_config(preset, **overrides), 0, torch.float64)
    lap = 2 * math.pi / abs(scene.road.kappa)
    frames = math.ceil(0.75 * lap / abs(scene.motion.speed * scene.motion.dt))  # past the half lap
    for k in range(frames):
        before, after = {id(o) for o in scene.objects(k)}, {id(o) for o in scene.objects(k + 1)}
        assert len(before & after) >= 0.8 * len(before), k  # a few leave or enter at the window's ends


def test_frames_before_the_half_lap_see_the_objects_they_saw():
    scene = Scene(scene_config("default"), 0, torch.float64)
    for k in (0, 40, 352):
        x, z, _ = scene.ego_pose(k)
        plain = scene.road.R * math.atan2(z, -scene.road.sigma * (x - scene.road.cx))
        assert scene.road.s_of(x, z, near=scene.ego_pose(k)[2] / scene.road.kappa) == plain


# -- buildings stay behind the kerb on every accepted bend ---------------------------------------
def _building_footprints(scene: Scene, blocks: range):
    """(object, its lateral e, the lateral e of its footprint's four corners) of every building block."""
    lateral = lambda x, z: float(scene.road.lateral(torch.tensor(x, dtype=torch.float64),  # noqa: E731
                                                    torch.tensor(z, dtype=torch.float64)))
    for b in blocks:
        for o in scene.blocks(b):
            if o.kind != BUILDING_BOX:
                continue
            (x, _, z), psi = scene.object_pose(o, 0)
            c, s = math.cos(psi), math.sin(psi)
            corners = [lateral(x + a * c + d * s, z - a * s + d * c)
                       for a in (-o.half[0], o.half[0]) for d in (-o.half[2], o.half[2])]
            yield o, lateral(x, z), corners


@pytest.mark.parametrize("preset, overrides", [
    ("carla-turning", {}), ("default", dict(steering=0.25)), ("default", dict(steering=-0.3)),
    ("default", dict(steering=math.atan(2.7 / MIN_TURN_RADIUS) - 1e-6, pavement_width=10.0)),
    ("default", dict(steering=0.2, pavement_width=0.0, parking_width=0.0, parked_cars=0.0)),
])
def test_buildings_stay_behind_the_kerb_on_a_bend(preset, overrides):
    """Straight blocks up to 22 m long reached from inside a bend into the road, and a block whose
    offset exceeded the bend's radius stood mirrored through its centre (in the lane)."""
    cfg = scene_config(preset, **overrides)
    scene = Scene(cfg, 0, torch.float64)
    kerb = cfg.lane_width + cfg.parking_width
    found = 0
    for o, e, corners in _building_footprints(scene, range(-2, 4)):
        found += 1
        assert e == pytest.approx(o.e, abs=1e-9)  # where it was placed: not through the bend's centre
        assert all(abs(c) >= kerb + cfg.pavement_width - 1e-9 for c in corners[::2] + corners[1::2]
                   if math.copysign(1.0, c) != math.copysign(1.0, scene.road.kappa * o.e)), corners
        assert all(math.copysign(1.0, c) == math.copysign(1.0, o.e) and abs(c) >= kerb - 1e-9 for c in corners)
    assert found > 5


def test_every_accepted_bend_renders_the_road_ahead_clear():
    for steering in (0.25, 0.3, math.atan(2.7 / MIN_TURN_RADIUS) - 1e-6):
        pair = render_pair("default", 0, size=(24, 80), steering=steering, parked_cars=0.0, moving_cars=0.0)
        assert float((pair["labels"][12:] == 5).double().mean()) < 0.15  # once 57 % building at 0.25


# -- explicit odometry is an arc the vehicle can drive -------------------------------------------
@pytest.mark.parametrize("odometry, message", [
    (dict(x_d=1.0, z_d=1.0, yaw=0.0),
     re.escape("expected the chord of a circular arc, x_d = z_d tan(yaw / 2) = 0.0 m")),
    (dict(x_d=0.05, z_d=1.2, yaw=0.02), "expected the chord of a circular arc"),  # a 1.8° crab
    (dict(x_d=0.5, z_d=0.0, yaw=0.0), "expected the chord of a circular arc"),  # sideways
    (dict(x_d=-0.013997265434895748, z_d=1.1990016053038177, yaw=-0.0006870412325024073),
     "expected the chord of a circular arc"),  # the KITTI clip's pair 0: crossed the centre line by frame 130
    (dict(x_d=0.0, z_d=0.0, yaw=0.05), "expected a turn along an arc of at least 1 mm .no turn on the spot., "
                                       "got an arc of 0.0 m"),
    (dict(x_d=0.0, z_d=0.0005, yaw=0.05), "expected a turn along an arc of at least 1 mm"),
])
def test_odometry_that_is_no_arc_is_refused(odometry, message):
    """A sideways part of (x_d, z_d) made the vehicle drift across the road; a turn on the spot kept a
    straight road and gave a flow_velocity of 0 beside a flow of 11 px."""
    with pytest.raises(ValueError, match="^x_d, z_d, yaw: " + message):
        scene_config("cvc-simple", **odometry)


@pytest.mark.parametrize("preset, index", [("carla-turning", 0), ("default", 3), ("cvc-simple", 0)])
def test_a_pairs_own_odometry_renders_the_same_motion(preset, index):
    """Ackermann odometry (forwards and reversing) is an arc: accepted, and the vehicle keeps its lane."""
    for sign in (1.0, -1.0):
        odo = render_pair(preset, index, size=TINY, speed=sign * 6.0)["odometry"]
        cfg = scene_config(preset, **odo)
        scene = Scene(cfg, 0, torch.float64)
        for k in (0, 50, 200):
            x, z, _ = scene.ego_pose(k)
            e = float(scene.road.lateral(torch.tensor(x, dtype=torch.float64), torch.tensor(z, dtype=torch.float64)))
            assert e == pytest.approx(cfg.lane_width / 2, abs=1e-6)
    scene_config(preset, x_d=0.0, z_d=0.0, yaw=0.0)  # standing still


# -- cars in the ego lane are faster than the ego vehicle -----------------------------------------
@pytest.mark.parametrize("speed_factor", [1.0, 0.5, 0.0])
def test_no_slower_car_in_the_ego_lane_with_explicit_odometry(speed_factor):
    """Explicit odometry keeps the ego speed at any speed_factor: with speed_factor < 1 / 1.3 the cars
    ahead in its lane were slower, and the ego vehicle drove through them."""
    cfg = scene_config("cvc-simple", x_d=0.0, z_d=1.2, yaw=0.0, speed_factor=speed_factor, moving_cars=3.0)
    scene = Scene(cfg, 0, torch.float64)
    cars = [o for b in range(-1, 12) for o in scene.blocks(b) if o.kind == CAR_BODY]
    ahead = [o for o in cars if o.e > 0]
    assert all(o.vs >= scene.motion.speed for o in ahead)
    assert (len(ahead) > 3) == (speed_factor == 1.0) and len(cars) > 10
    for k in range(0, 300, 3):  # the camera never over a car's footprint
        cx, _, cz = scene.pose(k).c
        for o in scene.objects(k):
            if o.kind == CAR_BODY:
                (x, _, z), _ = scene.object_pose(o, k)
                assert abs(x - cx) > o.half[0] or abs(z - cz) > o.half[2], k


def test_the_presets_lane_cars_are_kept():
    for name in PRESETS:
        cfg = scene_config(name, moving_cars=3.0)
        scene = Scene(cfg, 0, torch.float64)
        assert any(o.vs > 0 and o.e > 0 for b in range(1, 8) for o in scene.blocks(b)), name


def test_a_configurations_own_size_is_bounded_as_the_size_argument():
    """A SceneConfig's size (or scene_config's size override) went round MAX_SIDE: render_pair and
    SceneDataset rendered a (16385, 1) frame (a (20000, 20000) one would fill 100 GB); now the same
    ValueError as the size argument's, before any rendering."""
    from fsof_torch.data.datasets import SceneDataset

    message = r"^size: expected sides of at most 16384 pixels, got \(16385, 1\)$"
    tall = replace(PRESETS["cvc-simple"], size=(16385, 1))
    for call in (lambda: render_pair(tall, 0), lambda: SceneDataset(tall, 1),
                 lambda: scene_config("cvc-simple", size=(16385, 1))):
        with pytest.raises(ValueError, match=message):
            call()
    assert render_pair(replace(tall, size=(16384, 1)), 0)["image1"].shape == (3, 16384, 1)


@pytest.mark.parametrize("dtype, megabytes", [(torch.float32, 39.3), (torch.float64, 59.8)])
def test_the_kept_frame_is_the_size_the_docs_state(dtype, megabytes):
    """docs/synthetic-scenes.md and render.py: the frame kept for the next call is about 39 MB at
    375 x 1242 in float32 and 60 MB in float64 (its tensors' storages, each counted once)."""
    import dataclasses

    from fsof_torch.data.scene import render as render_module

    def stored(x, seen: set) -> int:
        if isinstance(x, torch.Tensor):
            ptr = x.untyped_storage().data_ptr()
            return 0 if ptr in seen or seen.add(ptr) else x.untyped_storage().nbytes()
        if isinstance(x, dict):
            return sum(stored(v, seen) for v in x.values())
        if isinstance(x, (list, tuple)):
            return sum(stored(v, seen) for v in x)
        if dataclasses.is_dataclass(x) or hasattr(x, "__dict__"):
            return sum(stored(v, seen) for v in vars(x).values())
        return 0

    render_pair("default", 0, dtype=dtype)  # (at the default 375 x 1242)
    frame = render_module._KEPT["frame"]
    assert stored(frame, set()) / 1e6 == pytest.approx(megabytes, abs=0.5)


def test_base_size_is_bounded_where_it_is_the_rendered_size():
    """Without a size the images are rendered at base_size, which went round MAX_SIDE: a
    base_size of (16385, 1) rendered a (16385, 1) frame (and (20000, 20000) would fill 100 GB); now
    a ValueError naming base_size, before any rendering. With a size, base_size only sets the frame
    of K and may be larger."""
    from fsof_torch.data.datasets import SceneDataset

    message = r"^base_size: expected sides of at most 16384 pixels where no size is given .*got \(16385, 1\)"
    for call in (lambda: render_pair("cvc-simple", 0, base_size=(16385, 1)),
                 lambda: SceneDataset("cvc-simple", 1, base_size=(16385, 1)),
                 lambda: scene_config("cvc-simple", base_size=(16385, 1))):
        with pytest.raises(ValueError, match=message):
            call()
    pair = render_pair("cvc-simple", 0, base_size=(16385, 1), size=(8, 1))
    assert pair["image1"].shape == (3, 8, 1)
    assert render_pair("cvc-simple", 0, base_size=(16384, 1))["image1"].shape == (3, 16384, 1)
