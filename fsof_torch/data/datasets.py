"""Torch datasets of image pairs with optional ground truth, and a ``collate`` for DataLoader.

Each item is a dict with the key names of :func:`fsof_torch.scene.render_pair` where they
overlap:

========================  =====================================================================
``image1``, ``image2``    (3, H, W) float RGB 0..255 (grey images repeated to 3 channels)
``flow``, ``valid``       (2, H, W) px forward flow t -> t+1, (1, H, W) bool
``flow_velocity``         (2, H, W) px/s (synthetic and CARLA data)
``road``                  (1, H, W) bool road (freespace) mask
``labels``, ``depth``     (H, W) int64, (1, H, W) metres (synthetic data)
``camera``                :class:`fsof_torch.camera.Camera` of batch 1 (K at the image size)
``odometry``              dict ``x_d, z_d, yaw`` of Python floats (metres, radians)
``velocity``              dict ``speed, steering, wheelbase, dt`` (synthetic data)
``pose1``, ``pose2``      (4, 4) float64 camera-to-world poses (synthetic data)
``road_pose``, ``plane``  dicts of floats: the camera over the road at t and the rigid plane
                          motion t -> t+1 (synthetic data; :func:`fsof_torch.scene.render_pair`)
``cam1_T_cam0``           (4, 4) float64 relative pose (odometry data)
``index``, ``name``       int, str
========================  =====================================================================

Keys are present only when the data has them (``ground_truth=False`` leaves out flow, valid and
odometry). :func:`collate` batches a list of items: tensors are stacked (leading B), cameras are
concatenated into one Camera of batch B, dicts of floats become dicts of (B,) tensors, anything
else (index, name) a list, as :func:`fsof_torch.scene.collate` does for rendered pairs. Images of different sizes cannot be stacked: use
``batch_size=1`` for KITTI, whose frames differ by a pixel or two.
"""

from __future__ import annotations

import numbers
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch
from torch import Tensor
from torch.utils.data import Dataset

from ..geometry.camera import Camera
from ..geometry.egomotion import ego_motion_from_pose, relative_pose
from ..io.carla import CarlaRun, carla_camera, read_carla_flow, read_carla_road
from ..io.images import read_image
from ..io.kitti import read_kitti_calibration, read_kitti_flow, read_kitti_poses
from ..io.layout import read_synthetic_pair, synthetic_pair_indices
from ..io.masks import mask_from_colors, read_road_mask

__all__ = [
    "collate",
    "concat_cameras",
    "SyntheticFlowDataset",
    "KittiFlowDataset",
    "KittiSampleDataset",
    "KittiOdometryDataset",
    "CarlaRunDataset",
    "KITTI_ROAD_COLOR",
]

# the paper's hand labels of KITTI (semantic/*.png): road painted pure red
KITTI_ROAD_COLOR = (255, 0, 0)
_KITTI_HEIGHT = 1.65


def concat_cameras(cameras: Sequence[Camera]) -> Camera:
    """One Camera of batch sum(B_i) from several (dtype promoted, device of the first)."""
    if not cameras:
        raise ValueError("cameras: expected at least one Camera")
    dtype = cameras[0].dtype
    for cam in cameras[1:]:
        dtype = torch.promote_types(dtype, cam.dtype)
    device = cameras[0].device
    parts = [c.to(device=device, dtype=dtype) for c in cameras]
    return Camera(torch.cat([c.K for c in parts]), torch.cat([c.height for c in parts]),
                  torch.cat([c.roll for c in parts]), torch.cat([c.pitch for c in parts]))


def collate(samples: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Batch a list of dataset items (for ``DataLoader(..., collate_fn=collate)``).

    Tensors -> stacked (B, ...); Camera -> one Camera of batch B; dicts of numbers (odometry,
    velocity) -> dicts of (B,) tensors (the cameras' dtype, else float64); anything else (index,
    name) -> a list. The same rules as :func:`fsof_torch.scene.collate`, so rendered pairs and
    items read from disk batch alike. Every item must have the same keys.
    """
    if not samples:
        raise ValueError("samples: expected a non-empty list of dicts")
    keys = list(samples[0].keys())
    for i, s in enumerate(samples[1:], 1):
        if set(s.keys()) != set(keys):
            diff = sorted(set(s.keys()) ^ set(keys))
            raise ValueError(f"samples: item {i} has different keys from item 0 (differing: {diff})")
    cams = [s[k] for s in samples for k in keys if isinstance(s[k], Camera)]
    float_dtype = cams[0].dtype if cams else torch.float64
    batch: dict[str, Any] = {}
    for key in keys:
        values = [s[key] for s in samples]
        first = values[0]
        if isinstance(first, Tensor):
            shapes = {tuple(v.shape) for v in values}
            if len(shapes) > 1:
                raise ValueError(f"samples: {key!r} has different shapes {sorted(shapes)}; use batch_size=1 "
                                 f"or images of one size")
            batch[key] = torch.stack(values)
        elif isinstance(first, Camera):
            batch[key] = concat_cameras(values)
        elif isinstance(first, Mapping) and all(isinstance(x, numbers.Number) for x in first.values()):
            batch[key] = {k: torch.tensor([float(v[k]) for v in values], dtype=float_dtype) for k in first}
        else:
            batch[key] = list(values)
    return batch


def _check_index(index: int, length: int) -> int:
    if not isinstance(index, numbers.Integral):
        raise TypeError(f"index: expected an int, got {type(index).__name__}")
    if not -length <= index < length:
        raise IndexError(f"index: {index} out of range for a dataset of {length} pairs")
    return int(index) % length


def _folder(root: str | os.PathLike, name: str = "root") -> Path:
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{name}: no folder at {str(root)!r}")
    return root


class SyntheticFlowDataset(Dataset):
    """Pairs of a synthetic KITTI-like layout folder (``python -m eval synth`` /
    :func:`fsof_torch.io.write_synthetic_sequence`), with their exact ground truth.

    Args:
        root: the folder.
        dtype: float dtype of images, flows, depth and camera.
        ground_truth: False -> images, camera, index and name only.
    """

    def __init__(self, root: str | os.PathLike, *, dtype: torch.dtype = torch.float32, ground_truth: bool = True):
        self.root = _folder(root)
        self.indices = synthetic_pair_indices(self.root)
        if not self.indices:
            raise ValueError(f"root: {str(self.root)!r} holds no pairs (params/*.json)")
        self.dtype = dtype
        self.ground_truth = ground_truth

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index: int) -> dict[str, Any]:
        i = self.indices[_check_index(index, len(self))]
        return read_synthetic_pair(self.root, i, dtype=self.dtype, ground_truth=self.ground_truth)


class KittiFlowDataset(Dataset):
    """Pairs of a KITTI flow layout: KITTI 2012/2015 training folders, the paper's KITTI
    evaluation folder, or a synthetic layout folder read as KITTI.

    Reads, for each ``image_dir/NAME_10.png`` with a ``NAME_11.png`` beside it:
    flow from ``flow_noc/`` or ``flow_occ/`` (``flow="noc"`` / ``"occ"``; absent -> no flow
    keys); the camera from ``calib_cam_to_cam/NAME.txt`` (``P_rect_0{cam}``, KITTI 2015) or
    ``calib/NAME.txt`` (``P{cam}`` or ``P_rect_0{cam}``), else from ``K`` if given, else none;
    the road from ``road/NAME_10.png`` (nonzero = road) or the paper's hand labels
    ``semantic/NAME_10.png`` (road painted RGB (255, 0, 0)).

    Args:
        root: the folder (holding ``image_dir``).
        flow: ``"noc"`` or ``"occ"``.
        image_dir: ``"image_2"`` (colour; KITTI 2012 calls it ``colored_0``).
        cam: camera index of the calibration row.
        camera_height: metres (not in KITTI's files; nominal 1.65).
        K: (3, 3) intrinsics used where no calibration file is found.
        dtype: float dtype of images, flow and camera.
        ground_truth: False -> no flow, valid, road.
    """

    def __init__(self, root: str | os.PathLike, *, flow: str = "noc", image_dir: str = "image_2", cam: int = 2,
                 camera_height: float = _KITTI_HEIGHT, K: Tensor | None = None, dtype: torch.dtype = torch.float32,
                 ground_truth: bool = True):
        if flow not in ("noc", "occ"):
            raise ValueError(f"flow: expected 'noc' or 'occ', got {flow!r}")
        self.root = _folder(root)
        images = self.root / image_dir
        if not images.is_dir():
            raise FileNotFoundError(f"root: {str(self.root)!r} has no {image_dir}/ folder")
        self.names = sorted(p.name[:-len("_10.png")] for p in images.glob("*_10.png")
                            if (images / p.name.replace("_10.png", "_11.png")).is_file())
        if not self.names:
            raise ValueError(f"root: {str(images)!r} holds no NAME_10.png / NAME_11.png pairs")
        self.image_dir, self.flow_dir = image_dir, f"flow_{flow}"
        self.cam, self.camera_height, self.K = cam, float(camera_height), K
        self.dtype, self.ground_truth = dtype, ground_truth

    def __len__(self) -> int:
        return len(self.names)

    def camera(self, name: str) -> Camera | None:
        """The Camera (batch 1) of pair ``name``, or None when neither a file nor ``K`` gives one."""
        for folder in ("calib_cam_to_cam", "calib"):
            path = self.root / folder / f"{name}.txt"
            if path.is_file():
                P = read_kitti_calibration(path, self.cam)
                return Camera.from_projection(P.to(self.dtype), self.camera_height)
        if self.K is not None:
            return Camera(torch.as_tensor(self.K).to(self.dtype), self.camera_height)
        return None

    def __getitem__(self, index: int) -> dict[str, Any]:
        i = _check_index(index, len(self))
        name = self.names[i]
        images = self.root / self.image_dir
        sample: dict[str, Any] = {
            "image1": read_image(images / f"{name}_10.png").to(self.dtype),
            "image2": read_image(images / f"{name}_11.png").to(self.dtype),
        }
        camera = self.camera(name)
        if camera is not None:
            sample["camera"] = camera
        if self.ground_truth:
            path = self.root / self.flow_dir / f"{name}_10.png"
            if path.is_file():
                flow, valid = read_kitti_flow(path)
                sample["flow"], sample["valid"] = flow.to(self.dtype), valid
            road = self.root / "road" / f"{name}_10.png"
            semantic = self.root / "semantic" / f"{name}_10.png"
            if road.is_file():
                sample["road"] = read_road_mask(road, size=tuple(sample["image1"].shape[-2:]))
            elif semantic.is_file():
                sample["road"] = mask_from_colors(read_image(semantic), [KITTI_ROAD_COLOR])
        sample["index"], sample["name"] = i, name
        return sample


class KittiSampleDataset(Dataset):
    """The single-pair folder ``shared/data/kitti15_000000`` (or one like it): ``image_10.png``,
    ``image_11.png``, ``flow_noc_10.png``, ``road.json``, ``calib_cam_to_cam.txt``.

    No odometry (KITTI flow does not publish it). ``camera_height`` in metres.
    """

    def __init__(self, folder: str | os.PathLike, *, cam: int = 2, camera_height: float = _KITTI_HEIGHT,
                 dtype: torch.dtype = torch.float32, ground_truth: bool = True):
        self.folder = _folder(folder, "folder")
        for file in ("image_10.png", "image_11.png"):
            if not (self.folder / file).is_file():
                raise FileNotFoundError(f"folder: {str(self.folder)!r} has no {file}")
        self.cam, self.camera_height, self.dtype, self.ground_truth = cam, float(camera_height), dtype, ground_truth

    def __len__(self) -> int:
        return 1

    def __getitem__(self, index: int) -> dict[str, Any]:
        _check_index(index, 1)
        f = self.folder
        sample: dict[str, Any] = {
            "image1": read_image(f / "image_10.png").to(self.dtype),
            "image2": read_image(f / "image_11.png").to(self.dtype),
        }
        size = tuple(sample["image1"].shape[-2:])
        if (f / "calib_cam_to_cam.txt").is_file():
            P = read_kitti_calibration(f / "calib_cam_to_cam.txt", self.cam)
            sample["camera"] = Camera.from_projection(P.to(self.dtype), self.camera_height)
        if self.ground_truth:
            if (f / "flow_noc_10.png").is_file():
                flow, valid = read_kitti_flow(f / "flow_noc_10.png")
                sample["flow"], sample["valid"] = flow.to(self.dtype), valid
            if (f / "road.json").is_file():
                sample["road"] = read_road_mask(f / "road.json", size=size)
        sample["index"], sample["name"] = 0, f.name
        return sample


class KittiOdometryDataset(Dataset):
    """Consecutive frames of a KITTI odometry clip (like ``shared/data/kitti_odometry_straight``)
    with the odometry from its ground-truth poses.

    Folder: ``image_dir/NNNNNN.png`` frames, ``calib.txt`` (``P{cam}``), ``poses.txt``
    (camera-to-world, one row per frame), optionally ``road.json`` (one polygon for the clip).
    Pair ``i`` = frames ``(i, i + step)``; only frames with a pose and an image are used.
    ``odometry`` = :func:`fsof_torch.egomotion.ego_motion_from_pose` of the two poses for the
    camera (its roll/pitch, default 0); ``cam1_T_cam0`` the full relative pose; ``pose_residual``
    what the planar model drops (``y_d`` in metres, rotation residual angle in radians).
    """

    def __init__(self, folder: str | os.PathLike, *, image_dir: str = "image_l", cam: int = 0, step: int = 1,
                 camera_height: float = _KITTI_HEIGHT, roll: float = 0.0, pitch: float = 0.0,
                 dtype: torch.dtype = torch.float32, ground_truth: bool = True):
        self.folder = _folder(folder, "folder")
        if not isinstance(step, numbers.Integral) or step < 1:
            raise ValueError(f"step: expected an int >= 1, got {step!r}")
        images = self.folder / image_dir
        if not images.is_dir():
            raise FileNotFoundError(f"folder: {str(self.folder)!r} has no {image_dir}/ folder")
        frames = sorted(p.stem for p in images.glob("*.png") if p.stem.isdigit())
        poses_path = self.folder / "poses.txt"
        self.poses = read_kitti_poses(poses_path) if ground_truth or poses_path.is_file() else None
        limit = len(self.poses) if self.poses is not None else float("inf")
        have = {int(s): s for s in frames if int(s) < limit}
        self.pairs = [(have[i], have[i + step]) for i in sorted(have) if i + step in have]
        if not self.pairs:
            raise ValueError(f"folder: {str(self.folder)!r} has no frame pairs with poses (step {step})")
        P = read_kitti_calibration(self.folder / "calib.txt", cam)
        self.camera_ = Camera.from_projection(P.to(torch.float64), float(camera_height), float(roll), float(pitch))
        self.image_dir, self.dtype, self.ground_truth = image_dir, dtype, ground_truth
        self.road_path = self.folder / "road.json"

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict[str, Any]:
        i = _check_index(index, len(self))
        a, b = self.pairs[i]
        images = self.folder / self.image_dir
        sample: dict[str, Any] = {
            "image1": read_image(images / f"{a}.png").to(self.dtype),
            "image2": read_image(images / f"{b}.png").to(self.dtype),
            "camera": self.camera_.to(self.dtype),
        }
        if self.ground_truth:
            pose0, pose1 = self.poses[int(a)], self.poses[int(b)]
            ego = ego_motion_from_pose(pose0.unsqueeze(0), self.camera_, pose1=pose1.unsqueeze(0))
            sample["odometry"] = {"x_d": float(ego.x_d[0]), "z_d": float(ego.z_d[0]), "yaw": float(ego.yaw[0])}
            sample["pose_residual"] = {"y_d": float(ego.y_d[0]),
                                       "rotation": float(ego.rotation_residual[0].norm())}
            sample["cam1_T_cam0"] = relative_pose(pose0.unsqueeze(0), pose1.unsqueeze(0))[0]
            if self.road_path.is_file():
                sample["road"] = read_road_mask(self.road_path, size=tuple(sample["image1"].shape[-2:]))
        sample["index"], sample["name"] = i, f"{a}-{b}"
        return sample


class CarlaRunDataset(Dataset):
    """Frame pairs (k, k+1) of one run of the paper's CARLA layout (see :mod:`fsof_torch.io.carla`).

    ``flow_velocity`` is the run's flow of frame k (the paper: instantaneous, px/s); ``road`` from
    the semantic PNG; ``camera`` from :func:`fsof_torch.io.carla_camera` with the roll of the run
    name (``r`` in degrees). No displacement ``flow`` (CARLA gives velocities).
    """

    def __init__(self, run: str | os.PathLike, *, camera_height: float = 2.4, dtype: torch.dtype = torch.float32,
                 ground_truth: bool = True):
        self.run = CarlaRun(run)
        self.camera_height, self.dtype, self.ground_truth = float(camera_height), dtype, ground_truth

    def __len__(self) -> int:
        return max(len(self.run) - 1, 0)

    def __getitem__(self, index: int) -> dict[str, Any]:
        i = _check_index(index, len(self))
        a, b = self.run.frames[i], self.run.frames[i + 1]
        image1 = read_image(self.run.path("rgb", a)).to(self.dtype)
        sample: dict[str, Any] = {
            "image1": image1,
            "image2": read_image(self.run.path("rgb", b)).to(self.dtype),
            "camera": carla_camera(tuple(image1.shape[-2:]), height=self.camera_height,
                                   roll=self.run.params.get("roll", 0.0), dtype=self.dtype),
        }
        if self.ground_truth:
            path = self.run.path("optical_flow", a)
            if path.is_file():
                flow, valid = read_carla_flow(path)
                sample["flow_velocity"], sample["valid"] = flow.to(self.dtype), valid
            path = self.run.path("semantic", a)
            if path.is_file():
                sample["road"] = read_carla_road(path)
        sample["index"], sample["name"] = i, a
        return sample
