"""What a synthetic scene is made of: labels, intrinsics, :class:`SceneConfig` and the presets.

Every field of :class:`SceneConfig` can be overridden by keyword in
:func:`fsof_torch.data.scene.render_pair`; :func:`scene_config` applies and checks overrides.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields, replace
from typing import Any

import torch

from ..._check import check_bool, check_int, check_number, check_size, is_number, option_error
from ...geometry.camera import Camera

__all__ = ["LABELS", "LABEL_COLORS", "KITTI_K", "KITTI_SIZE", "SENSOR_NOISE", "PRESETS", "SceneConfig",
           "scene_config", "ASPHALT_CELLS", "MAX_TRAVEL", "MAX_SEED", "MIN_TURN_RADIUS", "MAX_BODY_HZ",
           "MAX_GRADE_START", "MAX_CARS", "MAX_CONTRAST", "MAX_CRAB", "MAX_SUPERSAMPLE", "MAX_SIDE", "check_seed",
           "check_sides", "check_overrides", "arc_length", "path_curvature", "traffic_speed", "ego_speed"]

#: Semantic label ids of ``labels``.
LABELS: dict[str, int] = {"sky": 0, "road": 1, "marking": 2, "kerb": 3, "pavement": 4,
                          "building": 5, "car": 6}

#: A colour per label id (RGB 0..255), for visualisations.
LABEL_COLORS: dict[int, tuple[int, int, int]] = {
    0: (70, 130, 180), 1: (128, 64, 128), 2: (255, 255, 255), 3: (220, 220, 0),
    4: (244, 35, 232), 5: (70, 70, 70), 6: (0, 0, 142)}

#: KITTI-like intrinsics (pixels) at :data:`KITTI_SIZE` = (H, W).
KITTI_K = ((721.5377, 0.0, 609.5593), (0.0, 721.5377, 172.854), (0.0, 0.0, 1.0))
KITTI_SIZE = (375, 1242)

# the label ids by name, for the modules that cast, shade and label
SKY, ROAD, MARKING, KERB, PAVEMENT, BUILDING, CAR = (
    LABELS[k] for k in ("sky", "road", "marking", "kerb", "pavement", "building", "car"))

#: The most anything may move in one frame (m): the ego vehicle (its arc length) and the moving cars'
#: base speed (:func:`traffic_speed`) times dt. 100 m a frame is 1000 m/s at 10 Hz, 50× the fastest
#: scene of the paper's tables (CVC ×4: the ego vehicle and the cars' base speed 20 m/s); beyond it the
#: scene would generate objects along an unbounded stretch of road.
MAX_TRAVEL = 100.0

#: The most cars per 40 m block (``parked_cars`` per side, ``moving_cars`` over both lanes), as a
#: Poisson mean: far more than fit (parked cars 6 m apart, about 7 a side; moving cars 7 m apart in a
#: lane); beyond it every block would only draw cars that the spacing discards, at a cost per car.
MAX_CARS = 100.0

#: The most contrast of the procedural textures: ``texture`` (a multiplier of the built-in contrast)
#: and each ``asphalt`` amplitude (grey levels) are at most 1e4, far beyond any useful contrast on grey
#: levels 0..255; much larger values overflow the shading to inf (1e38 in float32), and inf · 0 to NaN.
MAX_CONTRAST = 1e4

#: The tightest turn a scene drives (m): the ego path's radius 1 / |κ| (:func:`path_curvature`) is at
#: least this, so the road (concentric with the path, the ego vehicle in its right lane) stays drivable.
MIN_TURN_RADIUS = 8.0

#: The most the chord (x_d, z_d) of explicit odometry may point off the circular arc's chord (rad):
#: |atan(x_d / z_d) − yaw / 2| (:func:`arc_length`). The ego vehicle drives a circular arc (Ackermann
#: motion without side slip), on which the chord points at half the turn; any other direction is a
#: sideways drift that takes the vehicle off its lane by that angle times the distance driven (the
#: planar odometry of the shared KITTI clip's first pair, 0.65° off its arc, crosses the centre line in
#: about 130 frames). 1e-6 rad admits the rounding of float32 odometry and drifts less than 1 m in 1000 km.
MAX_CRAB = 1e-6

#: The most rays per pixel side (``supersample``): ss² rays resolve an edge pixel's coverage in steps
#: of 1 / ss², 1 / 256 at 16, finer than one grey level of 0..255 between any two surfaces; beyond it
#: the cost grows as ss² (every pixel with ``adaptive=False``) and no 8-bit image changes.
MAX_SUPERSAMPLE = 16

#: The highest body-oscillation frequency (Hz): far above every mode of a car body (heave and pitch
#: about 1-2 Hz, wheel hop 10-15 Hz); beyond some 1e307 Hz the phase 2π f τ would overflow to NaN.
MAX_BODY_HZ = 1000.0

#: The farthest start of the vertical curve from the scene's start (m, either way): 100 km, a thousand
#: frames at :data:`MAX_TRAVEL`; the closed-form ray casting squares distances to it.
MAX_GRADE_START = 1e5

#: Pixels a side of ``size`` (and of the jobs' size options): beyond any camera's frame, a larger
#: render only fills memory.
MAX_SIDE = 16_384

#: Scene seeds are ints in [0, MAX_SEED): the generators are seeded with 2·seed + 1 and
#: seed·1 000 003 mod 2**63, so a larger or a negative seed would overflow or alias a valid one.
MAX_SEED = 2 ** 62


def check_seed(seed: object) -> int:
    """A scene seed: an int with 0 <= seed < :data:`MAX_SEED`, else TypeError / ValueError naming ``seed``."""
    seed = check_int(seed, "seed")
    if not 0 <= seed < MAX_SEED:
        raise ValueError(f"seed: expected an int in [0, 2**62), got {seed!r}")
    return seed


def check_sides(size: tuple[int, int]) -> None:
    """ValueError naming ``size`` (H, W, ints) where a side exceeds :data:`MAX_SIDE`."""
    if max(size) > MAX_SIDE:
        raise ValueError(f"size: expected sides of at most {MAX_SIDE} pixels, got {tuple(size)}")


def check_overrides(overrides: Any) -> None:
    """TypeError naming :func:`render_pair` unless every key of ``overrides`` is a :class:`SceneConfig`
    field (render_pair, render_sequence and :func:`scene_config` take the fields by keyword)."""
    known = {f.name for f in fields(SceneConfig)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise TypeError(f"render_pair: unknown overrides {unknown}; expected some of {sorted(known)}")


def traffic_speed(cfg: SceneConfig) -> float:
    """The moving cars' base speed (m/s): max(|v|, 5 m/s) · speed_factor, v the ego speed at
    speed_factor 1 (``speed``, or the arc through explicit odometry / dt), so that the cars' speed at
    factor k is k times their speed at factor 1 (:func:`.objects.block_objects`: cars in the ego
    vehicle's direction drive at 1.3 times it, oncoming cars at 0.8 times it)."""
    if cfg.x_d is not None:
        v = arc_length(float(cfg.x_d), float(cfg.z_d), float(cfg.yaw)) / cfg.dt
    else:
        v = float(cfg.speed)
    return max(abs(v), 5.0) * cfg.speed_factor


def ego_speed(cfg: SceneConfig) -> float:
    """The ego vehicle's signed speed (m/s, < 0 reversing): speed · speed_factor, or with explicit
    odometry the arc / dt (which ``speed_factor`` leaves as given)."""
    if cfg.x_d is not None:
        return arc_length(float(cfg.x_d), float(cfg.z_d), float(cfg.yaw)) / cfg.dt
    return float(cfg.speed) * cfg.speed_factor


def arc_length(x_d: float, z_d: float, yaw: float) -> float:
    """The signed length (m) of the circular arc with chord (x_d, z_d) (m) turning by ``yaw`` (rad,
    |yaw| < π): negative when z_d < 0 (backwards)."""
    chord = math.hypot(x_d, z_d)
    arc = chord * (yaw / 2) / math.sin(yaw / 2) if abs(yaw) > 1e-12 else chord
    return math.copysign(arc, z_d)


def path_curvature(cfg: SceneConfig) -> float:
    """The curvature κ (1/m, > 0 turning right) of the ego vehicle's path: tan(steering) / wheelbase, or
    with explicit odometry yaw / arc (0 without a turn; :func:`scene_config` refuses a turn along an
    arc under 1 mm, a turn on the spot). The road is concentric with this path (:class:`.road.Road`)."""
    if cfg.x_d is not None:
        # the arc as the Motion holds it: speed = arc / dt, times dt
        arc = arc_length(float(cfg.x_d), float(cfg.z_d), float(cfg.yaw)) / cfg.dt * float(cfg.dt)
        return float(cfg.yaw) / arc if cfg.yaw != 0.0 and arc != 0.0 else 0.0
    return math.tan(float(cfg.steering)) / float(cfg.wheelbase)


#: Cell sizes (m) of the seven asphalt noise octaves (:attr:`SceneConfig.asphalt`).
ASPHALT_CELLS = (0.02, 0.05, 0.12, 0.3, 0.75, 2.0, 5.0)


@dataclass(frozen=True)
class SceneConfig:
    """Everything a preset fixes; every field can be overridden by keyword in :func:`render_pair`.

    Motion: ``speed`` (m/s, rear axle = camera), ``steering`` (front-wheel angle, rad),
    ``wheelbase`` (m), ``dt`` (s between frames), ``speed_factor`` (multiplies the speed of the
    ego vehicle and of the moving cars: the paper's CVC ×1 / ×4; with explicit odometry, the moving
    cars' only: the odometry is the ego motion as given). Or explicit odometry per pair:
    ``x_d``, ``z_d`` (m) and ``yaw`` (rad), all three given: the chord of a circular arc (Ackermann
    motion), x_d = z_d tan(yaw / 2) within :data:`MAX_CRAB` = 1e-6 rad of direction, and an arc of
    at least 1 mm where yaw ≠ 0 (no turn on the spot); speed and steering are derived from the arc:
    speed = signed arc length / dt, steering = atan(l · yaw / arc length). A same-direction car in
    the ego lane drives at 1.3 times the traffic speed (:func:`traffic_speed`); where that is slower
    than the ego vehicle (explicit odometry with speed_factor < 1 / 1.3) the ego lane has none.
    The road is concentric with the ego path (:func:`path_curvature`), whose radius
    l / |tan(steering)| (or arc / |yaw|) must be at least :data:`MIN_TURN_RADIUS` = 8 m and more than
    lane_width / 2, so that the vehicle stays in the centre of its lane (|steering| up to
    atan(l / 8 m), about 0.325 rad at l = 2.7 m).

    Camera: ``height`` (m), ``roll``, ``pitch`` (rad), ``K`` (3×3 at ``base_size``), ``size``
    (rendered (H, W), each side at most :data:`MAX_SIDE` = 16 384; K is scaled to it; None renders at
    ``base_size``, then bounded alike; both held as tuples of ints); K, height, roll and pitch make a valid
    :class:`~fsof_torch.geometry.camera.Camera` (float64) at both sizes. Anti-aliasing:
    ``supersample`` (ss × ss rays per pixel, 1 <= ss <= :data:`MAX_SUPERSAMPLE` = 16) at geometric
    edges only when ``adaptive`` (textures and markings are band-limited analytically, so pixel
    centres suffice elsewhere), or at every pixel with ``adaptive=False``.

    Numbers may be any real numbers (not bools): a NumPy scalar is held as a Python float
    (``supersample`` as an int).

    Scene: ``lane_width``, ``parking_width`` (a parking strip on each side, 0 for none),
    ``pavement_width``, ``kerb_height`` (m; the kerb top stays below the camera: kerb_height <
    height - body_height on a level road, times (1 - G²) / sqrt(1 + G²) on a grade whose steepest
    grade is G); ``buildings`` (bool); ``parked_cars`` (mean number per 40 m and side, parked on
    the parking strip: 0 where ``parking_width`` is 0);
    ``moving_cars`` (mean number per 40 m, half oncoming), each at most :data:`MAX_CARS` = 100;
    ``texture`` (contrast multiplier of the procedural textures); ``asphalt`` (grey-level amplitude
    of each of the seven asphalt noise octaves, cells 2 cm, 5 cm, 12 cm, 30 cm, 75 cm, 2 m, 5 m; a
    sequence of numbers, held as a tuple of floats; None for the built-in
    (25, 25, 22, 18, 14, 13, 11)); ``texture`` and each amplitude at most :data:`MAX_CONTRAST` = 1e4.

    Camera sensor: ``noise`` (standard deviation, grey levels on 0..255, of independent Gaussian
    noise added to every pixel of every frame, the same on the three channels; seeded by the
    scene seed and the frame index, so a frame shared by two pairs has the same noise in both;
    0 for none). It is the noise at ``base_size``; at another ``size`` it is scaled by
    sqrt(H W / (H0 W0)), the noise of the base image area-averaged to that size.

    Vehicle body motion over the road (0 for none): ``body_pitch``, ``body_roll`` (rad) and
    ``body_height`` (m) are the amplitudes of a sinusoidal oscillation of the camera's pitch, roll
    and height relative to the road, at the frequencies ``body_pitch_hz``, ``body_roll_hz``,
    ``body_height_hz`` (Hz, at most :data:`MAX_BODY_HZ` = 1000) and phases drawn from the scene
    seed. With ±1°, ±1°, ±2 cm at
    dt = 0.1 s the default frequencies give mean per-frame changes of (4/π) a sin(π f dt) =
    0.084°, 0.092° and 0.97 cm, as measured on KITTI ground truth (0.085°, 0.09°, about 1 cm).

    Road grade (0 for a level road): the road's elevation g(s) along the arc length s rises by
    ``grade_before`` metres per metre up to ``grade_start`` (m), then the grade changes linearly
    to ``grade_after`` over ``grade_length`` metres (a parabolic vertical curve: a crest when the
    grade falls, a dip when it rises), g(0) = 0; |grade_start| <= :data:`MAX_GRADE_START` = 100 km.
    Needs a straight road (``steering=0``, or
    ``yaw=0`` with explicit odometry): ray casting is then closed-form.
    """

    speed: float = 8.0
    steering: float = 0.0
    wheelbase: float = 2.7
    dt: float = 0.1
    speed_factor: float = 1.0
    x_d: float | None = None
    z_d: float | None = None
    yaw: float | None = None
    height: float = 1.65
    roll: float = 0.0
    pitch: float = 0.0
    K: tuple = KITTI_K
    base_size: tuple = KITTI_SIZE
    size: tuple | None = None
    supersample: int = 2
    adaptive: bool = True
    lane_width: float = 3.5
    parking_width: float = 2.3
    pavement_width: float = 3.5
    kerb_height: float = 0.12
    buildings: bool = True
    parked_cars: float = 2.0
    moving_cars: float = 1.0
    texture: float = 1.0
    asphalt: tuple | None = None
    noise: float = 0.0
    body_pitch: float = 0.0
    body_roll: float = 0.0
    body_height: float = 0.0
    body_pitch_hz: float = 0.21
    body_roll_hz: float = 0.23
    body_height_hz: float = 1.25
    grade_before: float = 0.0
    grade_after: float = 0.0
    grade_start: float = 15.0
    grade_length: float = 60.0

    @property
    def has_grade(self) -> bool:
        """Whether the road has a grade (a non-level vertical profile)."""
        return self.grade_before != 0.0 or self.grade_after != 0.0

    @property
    def has_body_motion(self) -> bool:
        """Whether the camera's pitch, roll or height over the road oscillate."""
        return self.body_pitch != 0.0 or self.body_roll != 0.0 or self.body_height != 0.0


_DEG = math.pi / 180.0
# asphalt octave amplitudes of the default preset (cells 2 cm ... 5 m, see SceneConfig.asphalt):
# little contrast at 12-75 cm, where the built-in texture gave real KITTI road about twice its
# band-pass contrast, more at 2-5 m (patches), the 2-5 cm grain kept
_DEFAULT_ASPHALT = (25.0, 24.0, 7.0, 3.0, 8.0, 22.0, 20.0)

#: Sensor noise (grey levels at 375×1242) that, with the default asphalt, matches the fine-scale
#: (1 px band-pass) contrast measured on the real KITTI road (benchmarks/scene_realism.py).
SENSOR_NOISE = 3.8

#: Named scene presets (docs/synthetic-scenes.md). Overrides such as ``speed_factor=4`` or
#: ``roll=math.radians(5)`` apply on top.
PRESETS: dict[str, SceneConfig] = {
    # the refine job's default sequence, made like the real KITTI samples in ../shared/data:
    # 12 m/s at 10 Hz (the KITTI odometry clip moves 1.197 m per frame), asphalt whose grey-level
    # statistics per row band (row-detrended std, band-pass at 1, 2, 4 px, gradient) match those
    # measured inside the road polygons of the real images (README: "Realistic default"); a
    # gentle curve, cars in view, mild mounting. No sensor noise by default: independent noise per
    # frame is a floor under any photometric error that no flow can remove, and would hide what the
    # refiner changes; ``noise=SENSOR_NOISE`` adds the level measured on the real images.
    "default": SceneConfig(speed=12.0, steering=0.02, roll=1.0 * _DEG, pitch=-1.0 * _DEG,
                           parked_cars=2.5, moving_cars=1.5, asphalt=_DEFAULT_ASPHALT, noise=0.0),
    # CVC12-like straight urban road (the paper's displacement-model data): empty or busy
    "cvc-simple": SceneConfig(speed=5.0, dt=0.1, buildings=False, parked_cars=0.0, moving_cars=0.0,
                              parking_width=0.0, height=1.5),
    "cvc-complex": SceneConfig(speed=5.0, dt=0.1, parked_cars=3.0, moving_cars=1.5, height=1.5),
    # CARLA-like (the paper's velocity-model data), roll 0 by default; roll= overrides (±5°, ±10°)
    "carla-straight": SceneConfig(speed=10.0, dt=0.05, parked_cars=1.5, moving_cars=1.0,
                                  height=1.6, wheelbase=2.9),
    "carla-turning": SceneConfig(speed=6.0, dt=0.05, steering=0.18, parked_cars=1.0, moving_cars=0.5,
                                 height=1.6, wheelbase=2.9),
}
# Road motion beyond the paper's model (DESIGN.md §10), with exact ground truth (``road_pose``,
# ``plane``): the default scene with the body oscillating over a level road (±1° pitch and roll,
# ±2 cm height), and the default scene made straight with a crest or a dip 15-75 m ahead (the
# grade changes from +3 % to -3 % or back over 60 m).
PRESETS["body-motion"] = replace(PRESETS["default"], body_pitch=1.0 * _DEG, body_roll=1.0 * _DEG, body_height=0.02)
PRESETS["crest"] = replace(PRESETS["default"], steering=0.0, grade_before=0.03, grade_after=-0.03)
PRESETS["dip"] = replace(PRESETS["default"], steering=0.0, grade_before=-0.03, grade_after=0.03)


def scene_config(preset: str | SceneConfig = "default", **overrides: Any) -> SceneConfig:
    """The configuration of a preset (a name of :data:`PRESETS` or a :class:`SceneConfig`) with
    ``overrides`` applied; unknown names raise TypeError, bad values ValueError."""
    if isinstance(preset, SceneConfig):
        cfg = preset
    elif isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"preset: expected one of {sorted(PRESETS)}, got {preset!r}")
        cfg = PRESETS[preset]
    else:
        raise TypeError(f"preset: expected a preset name or a SceneConfig, got {type(preset).__name__}")
    check_overrides(overrides)
    cfg = replace(cfg, **overrides)
    # K as nested float tuples: a tensor or an array would not compare in the frame cache's key
    cfg = replace(cfg, K=_as_K(cfg.K), **_python_numbers(cfg))
    _validate(cfg)
    # tuples, not the caller's lists: a list changed after the call would change the configuration
    # that keyed the kept frame (render.py) and the SceneDataset's items
    if cfg.asphalt is not None:
        cfg = replace(cfg, asphalt=tuple(float(a) for a in cfg.asphalt))
    return replace(cfg, base_size=check_size(cfg.base_size, "base_size"),
                   size=None if cfg.size is None else check_size(cfg.size))


def _as_K(K: Any) -> tuple:
    """K (nested sequences, a tensor or an array of 3×3 finite numbers) as a tuple of float tuples."""
    try:
        rows = [list(r.tolist() if hasattr(r, "tolist") else r) for r in (K.tolist() if hasattr(K, "tolist") else K)]
    except (TypeError, ValueError, RuntimeError, NotImplementedError):
        rows = None
    if (rows is None or len(rows) != 3 or any(len(r) != 3 for r in rows)
            or not all(isinstance(v, numbers.Real) and not isinstance(v, bool) and _finite(v)
                       for r in rows for v in r)):
        raise ValueError(f"K: expected a 3×3 matrix of finite numbers (nested sequences, a tensor or an array), "
                         f"got {K!r}")
    return tuple(tuple(float(v) for v in r) for r in rows)


def _finite(value: numbers.Real) -> bool:
    """Whether a real number is finite as a float (an int beyond float's range, 10**400, is not:
    math.isfinite raises OverflowError on it)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _python_numbers(cfg: SceneConfig) -> dict[str, Any]:
    """The fields that hold NumPy (or other) real scalars, as Python floats (``supersample`` an int),
    and an ``asphalt`` array as a list: what the computations and the frame cache's key expect."""
    out: dict[str, Any] = {}
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        if f.name == "supersample":
            if isinstance(value, numbers.Integral) and not isinstance(value, (bool, int)):
                out[f.name] = int(value)
        elif is_number(value) and type(value) not in (int, float):
            out[f.name] = float(value)
    if cfg.asphalt is not None and not isinstance(cfg.asphalt, (tuple, list, str)) and hasattr(cfg.asphalt, "tolist"):
        out["asphalt"] = cfg.asphalt.tolist()
    return out


def _validate(cfg: SceneConfig) -> None:
    def real(name: str) -> float:
        value = getattr(cfg, name)
        try:
            finite = is_number(value) and math.isfinite(value)
        except OverflowError:  # an int beyond float's range (10**400): check_number's ValueError, shortened
            check_number(value, name)
            raise
        if not finite:
            raise option_error(value, f"{name}: expected a finite number, got {type(value).__name__} {value!r}")
        return float(value)

    for name in ("speed", "steering", "roll", "pitch", "speed_factor", "texture", "noise", "parked_cars",
                 "moving_cars", "lane_width", "parking_width", "pavement_width", "kerb_height"):
        real(name)
    for name in ("wheelbase", "dt", "height", "lane_width"):
        if real(name) <= 0:
            raise ValueError(f"{name}: expected > 0, got {getattr(cfg, name)!r}")
    for name in ("speed_factor", "parked_cars", "moving_cars", "parking_width", "pavement_width",
                 "kerb_height", "texture", "noise"):
        if real(name) < 0:
            raise ValueError(f"{name}: expected >= 0, got {getattr(cfg, name)!r}")
    if cfg.parked_cars > 0 and cfg.parking_width == 0:  # (the cars park on the strip: none would appear)
        raise ValueError(f"parked_cars, parking_width: parked cars need a parking strip, got parked_cars="
                         f"{cfg.parked_cars!r} with parking_width={cfg.parking_width!r}; give parking_width > 0 or parked_cars=0")
    for name in ("parked_cars", "moving_cars"):
        if not real(name) <= MAX_CARS:
            raise ValueError(f"{name}: expected a mean number of cars per 40 m <= {MAX_CARS:g}, "
                             f"got {getattr(cfg, name)!r}")
    if not real("texture") <= MAX_CONTRAST:
        raise ValueError(f"texture: expected a contrast multiplier <= {MAX_CONTRAST:g}, got {cfg.texture!r}")
    if not abs(cfg.steering) < math.pi / 2:
        raise ValueError(f"steering: expected |δ_f| < π/2 rad, got {cfg.steering!r}")
    if not (abs(cfg.roll) < math.pi / 4 and abs(cfg.pitch) < math.pi / 4):
        raise ValueError(f"roll, pitch: expected |angle| < π/4 rad, got roll={cfg.roll!r}, pitch={cfg.pitch!r}")
    explicit = [getattr(cfg, n) is not None for n in ("x_d", "z_d", "yaw")]
    if any(explicit) and not all(explicit):
        raise ValueError(f"x_d, z_d, yaw: give all three or none, got x_d={cfg.x_d!r}, z_d={cfg.z_d!r}, yaw={cfg.yaw!r}")
    if all(explicit):
        for n in ("x_d", "z_d", "yaw"):
            real(n)
    _validate_travel(cfg)
    _validate_arc(cfg)
    _validate_lane(cfg)
    if cfg.asphalt is not None:
        amps = cfg.asphalt
        if (not isinstance(amps, (tuple, list)) or len(amps) != len(ASPHALT_CELLS)
                or not all(is_number(a) and 0 <= a <= MAX_CONTRAST for a in amps)):
            raise ValueError(f"asphalt: expected {len(ASPHALT_CELLS)} amplitudes in [0, {MAX_CONTRAST:g}] grey "
                             f"levels (one per octave), got {amps!r}")
    whole = isinstance(cfg.supersample, numbers.Integral) and not isinstance(cfg.supersample, bool)
    if not (whole and 1 <= cfg.supersample <= MAX_SUPERSAMPLE):
        raise (ValueError if whole else TypeError)(
            f"supersample: expected an integer in [1, {MAX_SUPERSAMPLE}], got {cfg.supersample!r}")
    for name in ("adaptive", "buildings"):
        check_bool(getattr(cfg, name), name)  # a truthy string such as "False" would pass as True
    if cfg.size is not None:
        check_sides(check_size(cfg.size))  # (a SceneConfig's own size as well as the size argument)
    base_size = check_size(cfg.base_size, "base_size")
    if cfg.size is None and max(base_size) > MAX_SIDE:  # without a size, the images are base_size's
        raise ValueError(f"base_size: expected sides of at most {MAX_SIDE} pixels where no size is given (the "
                         f"images are rendered at base_size), got {base_size}; give a size")
    _validate_camera(cfg)
    _validate_road_motion(cfg, real)


def _validate_camera(cfg: SceneConfig) -> None:
    """K, height, roll and pitch as the scene builds its camera (:class:`.world.Scene`): a float64
    :class:`Camera` at ``base_size`` and scaled to ``size``, whose errors name the field."""
    camera = Camera(torch.tensor(cfg.K, dtype=torch.float64), float(cfg.height), float(cfg.roll), float(cfg.pitch))
    size = tuple(cfg.size) if cfg.size is not None else tuple(cfg.base_size)
    if size != tuple(cfg.base_size):
        try:
            camera.scaled(size[1] / cfg.base_size[1], size[0] / cfg.base_size[0])
        except ValueError as err:
            raise ValueError(f"size, base_size: K scaled from base_size {tuple(cfg.base_size)} to size {size}: "
                             f"{err}") from None


def _validate_travel(cfg: SceneConfig) -> None:
    """At most :data:`MAX_TRAVEL` metres a frame for the ego vehicle and for the moving cars, whose base
    speed is max(|v|, 5 m/s) · speed_factor (:func:`traffic_speed`), v the ego speed at speed_factor 1."""
    if cfg.x_d is not None:
        if not abs(cfg.yaw) < math.pi:
            raise ValueError(f"yaw: expected |yaw| < π rad per frame, got {cfg.yaw!r}")
        travel = abs(arc_length(float(cfg.x_d), float(cfg.z_d), float(cfg.yaw)))
        if not travel <= MAX_TRAVEL:
            raise ValueError(f"x_d, z_d: expected a travel (arc length) <= {MAX_TRAVEL:g} m per frame, got "
                             f"{travel!r} m from x_d={cfg.x_d!r}, z_d={cfg.z_d!r}, yaw={cfg.yaw!r}")
        names = "speed_factor, dt (with x_d, z_d)"
    else:
        speed = abs(cfg.speed * cfg.speed_factor)
        if not speed * cfg.dt <= MAX_TRAVEL:
            raise ValueError(f"speed, speed_factor, dt: expected a travel |speed · speed_factor · dt| <= "
                             f"{MAX_TRAVEL:g} m per frame, got {speed * cfg.dt!r} m from speed={cfg.speed!r}, "
                             f"speed_factor={cfg.speed_factor!r}, dt={cfg.dt!r}")
        names = "speed, speed_factor, dt"
    traffic = traffic_speed(cfg) * cfg.dt
    if not traffic <= MAX_TRAVEL:
        raise ValueError(f"{names}: expected the moving cars' base travel max(|v|, 5 m/s) · speed_factor · dt <= "
                         f"{MAX_TRAVEL:g} m per frame (v the ego speed at speed_factor 1), got {traffic!r} m from "
                         f"speed_factor={cfg.speed_factor!r}, dt={cfg.dt!r}")


def _validate_arc(cfg: SceneConfig) -> None:
    """Explicit odometry that the ego vehicle drives as a circular arc (the road follows that arc):
    a turn along at least 1 mm (a turn on the spot has no path, and no speed for the velocity
    model), the chord pointing at yaw / 2 within :data:`MAX_CRAB` (forwards or backwards)."""
    if cfg.x_d is None:
        return
    x_d, z_d, yaw = float(cfg.x_d), float(cfg.z_d), float(cfg.yaw)
    given = f"x_d={cfg.x_d!r}, z_d={cfg.z_d!r}, yaw={cfg.yaw!r}"
    arc = arc_length(x_d, z_d, yaw)
    if yaw != 0.0 and not abs(arc) >= 1e-3:
        raise ValueError(f"x_d, z_d, yaw: expected a turn along an arc of at least 1 mm (no turn on the spot), got "
                         f"an arc of {arc!r} m from {given}")
    direction = math.atan2(x_d, z_d) if z_d >= 0 else math.atan2(-x_d, -z_d)
    if not abs(direction - yaw / 2) <= MAX_CRAB:
        raise ValueError(f"x_d, z_d, yaw: expected the chord of a circular arc, x_d = z_d tan(yaw / 2) = "
                         f"{z_d * math.tan(yaw / 2)!r} m (atan(x_d / z_d) = yaw / 2 within {MAX_CRAB:g} rad), got "
                         f"{direction - yaw / 2!r} rad off from {given}: a sideways drift would take the ego "
                         f"vehicle off its lane")


def _validate_lane(cfg: SceneConfig) -> None:
    """A turn the ego vehicle drives in the centre of its lane: the path's radius 1 / |κ|
    (:func:`path_curvature`) at least :data:`MIN_TURN_RADIUS` and more than lane_width / 2, so that the
    lane (centre line to lane line) lies on one side of the turn's centre and the road, concentric with
    the path, bends the way the vehicle turns."""
    kappa = path_curvature(cfg)
    if abs(kappa) < 1e-9:  # a straight road (Road's threshold)
        return
    radius = 1.0 / abs(kappa)
    if abs(kappa) <= 1.0 / MIN_TURN_RADIUS and radius > cfg.lane_width / 2:
        return
    if cfg.x_d is None:
        names, what = "steering, wheelbase", f"wheelbase / |tan(steering)| from steering={cfg.steering!r}, " \
                                             f"wheelbase={cfg.wheelbase!r}"
    else:
        names, what = "x_d, z_d, yaw", f"arc / |yaw| from x_d={cfg.x_d!r}, z_d={cfg.z_d!r}, yaw={cfg.yaw!r}"
    raise ValueError(f"{names}, lane_width: expected a turn that keeps the ego vehicle in its lane, a path radius "
                     f">= {MIN_TURN_RADIUS:g} m and > lane_width / 2 = {cfg.lane_width / 2!r} m, got {radius!r} m "
                     f"({what})")


def _validate_road_motion(cfg: SceneConfig, real) -> None:
    """The body-motion and grade fields (``real`` reads a field as a finite float)."""
    for name in ("body_pitch", "body_roll", "body_height", "body_pitch_hz", "body_roll_hz", "body_height_hz"):
        if real(name) < 0:
            raise ValueError(f"{name}: expected >= 0, got {getattr(cfg, name)!r}")
    for name in ("body_pitch_hz", "body_roll_hz", "body_height_hz"):
        if not real(name) <= MAX_BODY_HZ:
            raise ValueError(f"{name}: expected a frequency <= {MAX_BODY_HZ:g} Hz, got {getattr(cfg, name)!r}")
    for name in ("body_pitch", "body_roll"):
        if not real(name) < math.pi / 8:
            raise ValueError(f"{name}: expected an amplitude < π/8 rad, got {getattr(cfg, name)!r}")
    if not (abs(cfg.roll) + cfg.body_roll < math.pi / 4 and abs(cfg.pitch) + cfg.body_pitch < math.pi / 4):
        raise ValueError(f"body_roll, body_pitch: expected |roll| + body_roll and |pitch| + body_pitch < π/4 rad, "
                         f"got {abs(cfg.roll) + cfg.body_roll!r} and {abs(cfg.pitch) + cfg.body_pitch!r}")
    if not cfg.body_height < 0.5 * cfg.height:
        raise ValueError(f"body_height: expected an amplitude < height / 2 = {0.5 * cfg.height!r} m, "
                         f"got {cfg.body_height!r}")
    for name in ("grade_before", "grade_after"):
        if not abs(real(name)) <= 0.2:
            raise ValueError(f"{name}: expected a grade within ±0.2 m per m, got {getattr(cfg, name)!r}")
    if not abs(real("grade_start")) <= MAX_GRADE_START:
        raise ValueError(f"grade_start: expected within ±{MAX_GRADE_START:g} m of the start, got {cfg.grade_start!r}")
    if real("grade_length") <= 0:
        raise ValueError(f"grade_length: expected > 0, got {cfg.grade_length!r}")
    _validate_kerb(cfg)
    if cfg.has_grade:
        turning = cfg.yaw != 0.0 if cfg.x_d is not None else cfg.steering != 0.0
        if turning:
            raise ValueError(f"grade_before, grade_after: a grade needs a straight road (steering=0, or yaw=0 with "
                             f"explicit odometry), got steering={cfg.steering!r}, yaw={cfg.yaw!r}")


def _validate_kerb(cfg: SceneConfig) -> None:
    """The kerb top below the camera at every heave (the ray casting meets the pavement from above).
    The camera is H >= height - body_height over the road along its normal; on a grade the road under
    the camera is at least H (1 - G²) / sqrt(1 + G²) below it (G the steepest grade; the slope under
    the vehicle and under the camera may differ across the vertical curve), on a level road H."""
    steep = max(abs(cfg.grade_before), abs(cfg.grade_after))
    clearance = (cfg.height - cfg.body_height) * (1 - steep * steep) / math.sqrt(1 + steep * steep)
    if not cfg.kerb_height < clearance:
        bound = "height - body_height" if steep == 0 else \
            f"(height - body_height) (1 - G²) / sqrt(1 + G²), G = {steep!r} the steepest grade,"
        raise ValueError(f"kerb_height: expected the kerb top below the camera at its lowest, kerb_height < {bound} "
                         f"= {clearance!r} m, got {cfg.kerb_height!r} (height={cfg.height!r}, "
                         f"body_height={cfg.body_height!r})")
