"""Argument checks of the scene renderer and the datasets: K, motion bounds, seeds, the dataset options,
and what each item owns (its camera) and holds (floats in ``velocity``)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

from fsof_torch.data.datasets import (CarlaRunDataset, KittiFlowDataset, KittiOdometryDataset, KittiSampleDataset,
                                      SceneDataset, SyntheticFlowDataset)
from fsof_torch.data.folders import ImageFolderDataset
from fsof_torch.data.scene.config import MAX_TRAVEL
from fsof_torch.io import write_image, write_kitti_calibration
from fsof_torch.scene import KITTI_K, PRESETS, render_pair, scene_config

TINY = (8, 24)


# -- K -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("make", [lambda: torch.tensor(KITTI_K, dtype=torch.float64), lambda: np.array(KITTI_K)],
                         ids=["tensor", "array"])
def test_K_as_tensor_or_array_renders_twice_like_the_tuple(make):
    ref = render_pair("cvc-simple", 1, size=TINY)
    first = render_pair("cvc-simple", 0, size=TINY, K=make())
    second = render_pair("cvc-simple", 1, size=TINY, K=make())  # takes the frame the first call kept
    assert torch.equal(second["image1"], ref["image1"]) and torch.equal(second["flow"], ref["flow"])
    assert torch.equal(first["image2"], second["image1"])
    assert scene_config("default", K=make()).K == KITTI_K


@pytest.mark.parametrize("K", [None, "abc", ((1, 2), (3, 4)), ((math.nan, 0, 600), (0, 700, 170), (0, 0, 1)),
                               ((True, 0, 0), (0, 1, 0), (0, 0, 1)), torch.ones(3, 4)])
def test_bad_K_names_K(K):
    with pytest.raises(ValueError, match="K: expected a 3×3 matrix of finite numbers"):
        scene_config("default", K=K)


@pytest.mark.parametrize("K, match", [
    (((0.0, 0, 609.0), (0, 721.0, 172.0), (0, 0, 1)), r"^K: expected focal lengths f_x, f_y > 0"),
    (((-721.0, 0, 609.0), (0, 721.0, 172.0), (0, 0, 1)), r"^K: expected focal lengths f_x, f_y > 0"),
    (((721.0, 0, 609.0), (0, 721.0, 172.0), (0, 0, 2.0)), r"^K: expected an upper-triangular intrinsic matrix"),
    (((721.0, 0, 609.0), (0, 721.0, 172.0), (0.001, 0, 1.0)), r"^K: expected an upper-triangular"),
    (((721.0, 0, 609.0), (5.0, 721.0, 172.0), (0, 0, 1.0)), r"^K: expected an upper-triangular"),
])
def test_a_K_no_camera_takes_is_refused_by_scene_config(K, match):
    """scene_config returned these as checked; the render then failed (or drew nothing)."""
    with pytest.raises(ValueError, match=match):
        scene_config("cvc-simple", K=K)


def test_a_camera_height_beyond_the_cameras_bounds_is_refused():
    with pytest.raises(ValueError, match=r"^height: expected a camera height in \[3.89e-62, 2.57e\+61\] m"):
        scene_config("cvc-simple", height=1e300)


@pytest.mark.parametrize("overrides", [dict(speed=np.float32(8.0)), dict(supersample=np.int64(2)),
                                       dict(height=np.float64(1.5), noise=np.float32(0.5)),
                                       dict(asphalt=np.array([25.0, 24, 7, 3, 8, 22, 20]))])
def test_numpy_numbers_are_taken_as_python_numbers(overrides):
    """np.float32 and np.int64 were refused: "speed: expected a finite number, got np.float32(8.0)"."""
    cfg = scene_config("cvc-simple", **overrides)
    for name, value in overrides.items():
        got = getattr(cfg, name)
        if name == "asphalt":
            assert got == tuple(value.tolist()) and all(type(a) is float for a in got)
        else:
            assert got == value and type(got) is (int if name == "supersample" else float)
    ref = render_pair("cvc-simple", 0, size=TINY, **{k: (v.tolist() if k == "asphalt" else v.item())
                                                     for k, v in overrides.items()})
    assert torch.equal(render_pair("cvc-simple", 0, size=TINY, **overrides)["image1"], ref["image1"])


@pytest.mark.parametrize("value, error", [(True, "bool True"), (torch.tensor(8.0), "Tensor tensor(8.)"),
                                          ("8", "str '8'")])
def test_what_is_no_number_is_named(value, error):
    """A wrong type is a TypeError (it was a ValueError), a wrong value a ValueError."""
    with pytest.raises(TypeError, match=re.escape(f"speed: expected a finite number, got {error}")):
        scene_config("cvc-simple", speed=value)
    with pytest.raises(ValueError, match=re.escape("speed: expected a finite number, got float nan")):
        scene_config("cvc-simple", speed=float("nan"))
    with pytest.raises(TypeError, match=r"^supersample: expected an integer in \[1, 16\], got 2.0"):
        scene_config("cvc-simple", supersample=2.0)


def test_supersample_is_bounded():
    scene_config("cvc-simple", supersample=16)
    with pytest.raises(ValueError, match=r"^supersample: expected an integer in \[1, 16\], got 17"):
        scene_config("cvc-simple", supersample=17)


# -- motion bounds -----------------------------------------------------------------------------
@pytest.mark.parametrize("overrides, match", [
    (dict(dt=1e9), "speed, speed_factor, dt: expected a travel"),
    (dict(speed_factor=1e12), "speed, speed_factor, dt: expected a travel"),
    (dict(speed=0.0, speed_factor=1e12), "speed, speed_factor, dt: expected the moving cars' base travel"),
    (dict(x_d=0.0, z_d=1.0, yaw=2 * math.pi), "yaw: expected |yaw| < π rad per frame"),
    (dict(x_d=0.0, z_d=1.0, yaw=-math.pi), "yaw: expected |yaw| < π rad per frame"),
    (dict(x_d=0.0, z_d=-1e3, yaw=0.0), "x_d, z_d: expected a travel"),
    (dict(x_d=0.0, z_d=1.0, yaw=0.0, speed_factor=1e6), "speed_factor, dt .with x_d, z_d.: expected the moving"),
])
def test_motion_beyond_the_per_frame_bound_is_refused(overrides, match):
    with pytest.raises(ValueError, match=match):
        scene_config("default", **overrides)


def test_every_preset_and_documented_speed_is_within_the_bound():
    for name in PRESETS:
        for factor in (1, 4):
            scene_config(name, speed_factor=factor)
    scene_config("default", speed=MAX_TRAVEL / 0.1, dt=0.1)  # exactly at the bound
    # the chord of an arc of radius 15 m turning by 3 rad: the ego vehicle keeps its lane
    chord = 2 * 15.0 * math.sin(1.5)
    scene_config("default", x_d=chord * math.sin(1.5), z_d=chord * math.cos(1.5), yaw=3.0)


# -- seeds -------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [-1, 2 ** 62, 2 ** 63, 2 ** 64])
def test_seed_out_of_range_names_seed(seed):
    with pytest.raises(ValueError, match=r"seed: expected an int in \[0, 2\*\*62\)"):
        render_pair("cvc-simple", 0, size=TINY, seed=seed)
    with pytest.raises(ValueError, match="seed: expected an int in"):
        SceneDataset("cvc-simple", 1, size=TINY, seed=seed)


def test_largest_seed_renders_and_differs_from_seed_zero():
    top = render_pair("cvc-simple", 0, size=TINY, seed=2 ** 62 - 1)
    assert not torch.equal(top["image1"], render_pair("cvc-simple", 0, size=TINY, seed=0)["image1"])
    with pytest.raises(TypeError, match="seed: expected an int"):
        render_pair("cvc-simple", 0, size=TINY, seed=1.5)


# -- dataset options ---------------------------------------------------------------------------
DATASETS = {
    "SyntheticFlowDataset": lambda p, **kw: SyntheticFlowDataset(p, **kw),
    "ImageFolderDataset": lambda p, **kw: ImageFolderDataset([p / "a.png", p / "b.png"], **kw),
    "KittiFlowDataset": lambda p, **kw: KittiFlowDataset(p, **kw),
    "KittiSampleDataset": lambda p, **kw: KittiSampleDataset(p, **kw),
    "KittiOdometryDataset": lambda p, **kw: KittiOdometryDataset(p, **kw),
    "CarlaRunDataset": lambda p, **kw: CarlaRunDataset(p, **kw),
    "SceneDataset": lambda p, **kw: SceneDataset("cvc-simple", 1, size=TINY, **kw),
}


@pytest.mark.parametrize("name", sorted(DATASETS))
@pytest.mark.parametrize("options, match", [
    (dict(dtype=torch.int64), "dtype: expected torch.float32 or torch.float64"),
    (dict(dtype="float32"), "dtype: expected torch.float32 or torch.float64"),
    (dict(camera_dtype=torch.float16), "camera_dtype: expected torch.float32 or torch.float64"),
    (dict(ground_truth="no"), "ground_truth: expected True or False"),
])
def test_every_dataset_checks_dtype_camera_dtype_ground_truth_first(tmp_path, name, options, match):
    with pytest.raises(TypeError, match=match):  # checked before any file is looked at (none exists here)
        DATASETS[name](tmp_path / "missing", **options)


# -- items own their camera --------------------------------------------------------------------
def test_image_folder_items_do_not_share_a_camera(tmp_path):
    for i in range(3):
        write_image(tmp_path / f"{i:06d}.png", torch.full((3, *TINY), 10.0 * i))
    K = torch.tensor([[30.0, 0.0, 11.5], [0.0, 30.0, 3.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    write_kitti_calibration(tmp_path / "calib.txt", K, cam=0, style="odometry")
    ds = ImageFolderDataset(sorted(tmp_path.glob("*.png")), tmp_path / "calib.txt")
    first = ds[0]
    first["camera"].K[0, 0, 0] = 999.0
    assert float(ds[1]["camera"].K[0, 0, 0]) == 30.0 and float(ds[0]["camera"].K[0, 0, 0]) == 30.0
    assert ds[0]["camera"].K is not ds[0]["camera"].K


# -- velocity holds floats ---------------------------------------------------------------------
@pytest.mark.parametrize("overrides", [dict(wheelbase=3, dt=1, speed=2, speed_factor=1, steering=0),
                                       dict(wheelbase=3, dt=1, x_d=0, z_d=1, yaw=0)])
def test_velocity_and_odometry_hold_floats(overrides):
    p = render_pair("cvc-simple", 0, size=TINY, **overrides)
    assert all(type(v) is float for v in p["velocity"].values()), p["velocity"]
    assert all(type(v) is float for v in p["odometry"].values()), p["odometry"]
