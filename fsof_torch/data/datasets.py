"""Torch datasets of image pairs with optional ground truth, and a ``collate`` for DataLoader.

Every dataset's items follow one contract, written in :mod:`fsof_torch.data.items`: the keys
``image1``, ``image2`` ((3, H, W) float RGB 0..255), ``camera`` (a Camera of batch 1), ``flow``
((2, H, W) px), ``valid`` ((1, H, W) bool), ``road`` ((1, H, W) bool), ``odometry`` (dict
``x_d``, ``z_d``, ``yaw`` floats), ``relative_pose`` ((4, 4) float64 ``cam1_T_cam0``), ``index``
and ``name`` are always present, None where the data does not have them; some data sets add keys
of their own (``flow_velocity``, ``labels``, ``depth``, ``pose1``, ``pose2``, ``road_pose``,
``plane``, ``pose_residual``, ...).

========================  ============================================================================
:class:`SceneDataset`     the procedural scene rendered on demand (:func:`fsof_torch.scene.render_pair`)
SyntheticFlowDataset      a rendered sequence on disk (``python -m eval synth``)
ImageFolderDataset        a folder of frames with a KITTI calibration, poses, road masks and ground
                          truth matched by name (:mod:`fsof_torch.data.folders`)
KittiFlowDataset          KITTI flow 2012/2015 training folders, the paper's KITTI evaluation folder
KittiSampleDataset        the single-pair folder ``shared/data/kitti15_000000``
KittiOdometryDataset      a KITTI odometry clip with its poses (``shared/data/kitti_odometry_straight``)
CarlaRunDataset           one run of the paper's CARLA layout
========================  ============================================================================

:func:`collate` batches a list of items: tensors are stacked (leading B), cameras are concatenated
into one Camera of batch B, dicts of floats become dicts of (B,) tensors, a key None in every item
stays None, anything else (index, name) becomes a list. Images of different sizes cannot be
stacked: use ``batch_size=1`` for KITTI, whose frames differ by a pixel or two.
"""

from __future__ import annotations

import os
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from .._check import as_path, check_bool, check_int, check_size, tensor_from_array
from ..geometry.camera import Camera, check_camera_index, read_kitti_calibration
from ..io.carla import CarlaRun, carla_camera, read_carla_flow, read_carla_road
from ..io.images import check_no_broken_links, existing_folder, read_image, read_image_array
from ..io.kitti import read_kitti_flow, read_kitti_poses
from ..io.layout import camera_from_params, read_synthetic_pair, read_synthetic_params, synthetic_pair_indices
from ..io.masks import mask_from_colors, read_road_mask
from .folders import (KITTI_HEIGHT, FramePair, ImageFolderDataset, calibration_size, check_index, check_mounting,
                      kitti_flow_layout, principal_point_off_centre)
from .items import ITEM_KEYS, as_item, check_item, check_item_options, collate, concat_cameras, make_item

__all__ = [
    "ITEM_KEYS",
    "collate",
    "concat_cameras",
    "check_item",
    "make_item",
    "SceneDataset",
    "SyntheticFlowDataset",
    "ImageFolderDataset",
    "FramePair",
    "KittiFlowDataset",
    "KittiSampleDataset",
    "KittiOdometryDataset",
    "CarlaRunDataset",
    "KITTI_ROAD_COLOR",
]

# the paper's hand labels of KITTI (semantic/*.png): road painted pure red
KITTI_ROAD_COLOR = (255, 0, 0)


def _folder(root: str | os.PathLike, name: str = "root") -> Path:
    return existing_folder(as_path(root, name), name)


def _fits(x: Tensor, path: Path, size: tuple[int, int], image: Path, root: str) -> Tensor:
    """``x`` if its (H, W) is the pair's image size, else a ValueError that starts with ``root``
    (the dataset's argument) and names the file and the image."""
    if tuple(x.shape[-2:]) != tuple(size):
        raise ValueError(f"{root}: {str(path)!r} is {x.shape[-2]}x{x.shape[-1]}, but the pair's image "
                         f"{image.name} is {size[0]}x{size[1]}; every file of a pair needs its images' size")
    return x


def _hand_labelled_road(path: Path, size: tuple[int, int], image: Path) -> Tensor:
    """The road of the paper's hand labels ``semantic/NAME_10.png`` (road painted RGB (255, 0, 0)).
    A single-channel PNG holds class IDs, such as KITTI's own semantic segmentation ground truth,
    whose ``semantic/`` folder has the same names: it has no red, and read as colours it was an
    empty road; a ValueError naming ``root`` and the file."""
    array = read_image_array(path, what="semantic PNG (the paper's hand labels, road painted red)")
    if array.ndim == 2 or array.shape[2] == 1:
        raise ValueError(f"root: {str(path)!r} is a single-channel {array.dtype} image (class IDs, such as KITTI's "
                         f"semantic segmentation ground truth, whose semantic/ folder has these names); semantic/ "
                         f"is read as the paper's hand labels, road painted RGB {KITTI_ROAD_COLOR}: move the class "
                         f"IDs elsewhere, or give road masks in road/")
    colors = _fits(read_image(path), path, size, image, "root")
    return mask_from_colors(colors, [KITTI_ROAD_COLOR])


def _images_and_camera(sample: dict[str, Any]) -> dict[str, Any]:
    """``sample`` reduced to what ``ground_truth=False`` keeps: images, camera, index, name."""
    return {k: sample[k] for k in ("image1", "image2", "camera", "index", "name")}


class SceneDataset(Dataset):
    """Pairs 0 .. ``num_pairs`` − 1 of a procedural driving sequence, rendered when an item is
    read (:func:`fsof_torch.scene.render_pair`), with its exact ground truth: flow, valid, road,
    odometry, and the extras ``flow_velocity``, ``labels``, ``depth``, ``moving``, ``velocity``,
    ``pose1``, ``pose2``, ``road_pose``, ``plane``. ``relative_pose`` is None: the scene's motion
    is exact (``odometry``, ``plane``, ``pose1``, ``pose2``), not a given pose. Names are
    ``000000``, ``000001``, ...

    Args:
        preset: a name of :data:`fsof_torch.scene.PRESETS` or a ``SceneConfig``.
        num_pairs: the sequence's length in pairs.
        seed: the scene's seed (an int in [0, 2**62)); size: ``(H, W)`` (default: the preset's).
        dtype: float32 or float64 for the rendering; ``camera_dtype`` of the camera (default ``dtype``;
            cast from the scene's float64 camera, so float64 keeps its digits under a float32 render).
        ground_truth: False -> images, camera, index and name only.
        **overrides: fields of ``SceneConfig`` (``noise=0.5``, ``speed_factor=2``, ...).

    Every argument is checked here (a bad preset, override, size or dtype raises at construction,
    not at the first item); the items render the checked configuration ``config`` (a
    ``SceneConfig``), so an override the caller changes afterwards (an ``asphalt`` list) changes
    nothing.
    """

    def __init__(self, preset: Any = "default", num_pairs: int = 4, *, seed: int = 0,
                 size: tuple[int, int] | None = None, dtype: torch.dtype = torch.float32,
                 camera_dtype: torch.dtype | None = None, ground_truth: bool = True, **overrides: Any):
        from .scene import scene_config
        from .scene.config import check_overrides, check_seed
        from .scene.world import Scene

        from .scene.render import check_extent

        try:  # (a keyword neither SceneDataset's nor a SceneConfig field: named after render_pair there)
            check_overrides(overrides)
        except TypeError as err:
            raise TypeError(f"SceneDataset: {str(err).removeprefix('render_pair: ')} (or SceneDataset's own: "
                            f"preset, num_pairs, seed, size, dtype, camera_dtype, ground_truth)") from None
        self.num_pairs = check_int(num_pairs, "num_pairs", minimum=1)
        self.seed = check_seed(seed)
        size = None if size is None else check_size(size)
        check_extent(self.num_pairs, 0, size)  # (the renderer's bounds, checked here, not at an item)
        camera_dtype = check_item_options(dtype, camera_dtype, ground_truth)
        # a bad preset or override fails here, not at the first item; the items render this checked
        # configuration (immutable), not the caller's overrides, which the caller may change later
        self.config = scene_config(preset, **overrides, **({} if size is None else {"size": size}))
        # the calibrated camera is the same for every pair: cast from float64, not from a rounded copy
        self._camera64 = Scene(self.config, self.seed, torch.float64).camera64
        self.preset, self.size = preset, size
        self.dtype, self.camera_dtype, self.ground_truth = dtype, camera_dtype, ground_truth

    def __len__(self) -> int:
        return self.num_pairs

    def __getitem__(self, index: int) -> dict[str, Any]:
        from .scene import render_pair

        i = check_index(index, len(self))
        p = render_pair(self.config, i, seed=self.seed, dtype=self.dtype)
        p.update(index=i, name=f"{i:06d}", camera=self._camera64.to(self.camera_dtype, copy=True))
        return as_item(p if self.ground_truth else _images_and_camera(p))


class SyntheticFlowDataset(Dataset):
    """Pairs of a synthetic KITTI-like layout folder (``python -m eval synth`` /
    :func:`fsof_torch.io.write_synthetic_sequence`), with their exact ground truth and the extras
    of :class:`SceneDataset` that were written (``flow_velocity``, ``labels``, ``depth``,
    ``velocity``, ``pose1``, ``pose2``, ``road_pose``, ``plane``).

    Args:
        root: the folder.
        dtype: float dtype of images, flows and depth; ``camera_dtype`` of the camera (default ``dtype``).
        ground_truth: False -> images, camera, index and name only.

    A pair whose file is missing or unreadable (an image, a flow, a params entry that is not
    valid) is an error naming ``root`` and the file when the pair loads.
    """

    def __init__(self, root: str | os.PathLike, *, dtype: torch.dtype = torch.float32,
                 camera_dtype: torch.dtype | None = None, ground_truth: bool = True):
        camera_dtype = check_item_options(dtype, camera_dtype, ground_truth)
        self.root = _folder(root)
        self.indices = synthetic_pair_indices(self.root)
        if not self.indices:
            raise ValueError(f"root: {str(self.root)!r} holds no pairs (params/*.json)")
        self.dtype, self.camera_dtype, self.ground_truth = dtype, camera_dtype, ground_truth

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index: int) -> dict[str, Any]:
        i = check_index(index, len(self))
        pair = self.indices[i]
        try:
            sample = read_synthetic_pair(self.root, pair, dtype=self.dtype, ground_truth=self.ground_truth)
            if self.camera_dtype not in (None, self.dtype):  # from the file's digits, not a rounded copy
                sample["camera"] = camera_from_params(read_synthetic_params(self.root, pair), self.camera_dtype)
        except (FileNotFoundError, IsADirectoryError, ValueError) as err:
            # the reader names its own argument (path) for a file of the folder: this dataset's is root
            message = str(err)
            if not message.startswith("path: "):
                raise
            raise type(err)("root: " + message.removeprefix("path: ")) from None
        return as_item(sample, index=i)


class KittiFlowDataset(Dataset):
    """Pairs of a KITTI flow layout: KITTI 2012/2015 training folders, the paper's KITTI
    evaluation folder, or a synthetic layout folder read as KITTI.

    Reads, for each ``image_dir/NAME_10.png`` with a ``NAME_11.png`` beside it (named ``NAME``;
    hidden files, named ``.*`` such as macOS's ``._NAME_10.png``, are no frames; an image without
    its partner, a ``NAME_10.png`` without its ``NAME_11.png`` or the reverse, is a ValueError
    naming ``root``, the folder and the images when the dataset is made, never a pair left out):
    flow from ``flow_noc/`` or ``flow_occ/`` (``flow="noc"`` / ``"occ"``; both absent -> None, the
    other one alone a ValueError: a synthetic layout holds ``flow_occ/`` only, its valid pixels the
    non-occluded ones; a pair without its file in the folder a FileNotFoundError naming ``root``
    and the file, not a pair without ground truth);
    the camera from ``calib_cam_to_cam/NAME.txt`` (``P_rect_0{cam}``, KITTI 2015) or
    ``calib/NAME.txt`` (``P{cam}`` or ``P_rect_0{cam}``), else from ``K`` if given, else None
    (where one of those folders holds other pairs' files but no ``NAME.txt``, a
    FileNotFoundError naming ``root`` and the file when the pair loads);
    the road from ``road/NAME_10.png`` (nonzero = road) or the paper's hand labels
    ``semantic/NAME_10.png`` (road painted RGB (255, 0, 0); a single-channel PNG there, such as
    KITTI's semantic segmentation ground truth of class IDs, is a ValueError naming ``root``; a
    pair with neither file where one of the folders is there, a FileNotFoundError naming ``root``
    and the file when the pair loads). No odometry (KITTI flow has none).
    Every file of a pair (second image, flow, road) must have the size of its ``NAME_10.png``: one
    of another size is a ValueError naming ``root`` and the file, never resized; so is a
    calibration file whose ``S_rect_0{cam}`` row states another size, and one without that row
    (``calib/NAME.txt`` of KITTI 2012) or a ``K`` whose principal point lies outside the middle
    third of the pair's images (a calibration of images twice or half as large, as
    :class:`ImageFolderDataset` checks; a ValueError naming ``root`` and the file, or ``K``). A
    synthetic layout's ``calib/`` (``meta.json`` beside it: the renderer's cameras) is read as it is.

    Args:
        root: the folder (holding ``image_dir``).
        flow: ``"noc"`` or ``"occ"``.
        image_dir: ``"image_2"`` (colour; KITTI 2012 calls it ``colored_0``).
        cam: camera index of the calibration row.
        camera_height: metres (not in KITTI's files; nominal 1.65).
        K: (3, 3) intrinsics used where no calibration file is found (copied: each item's camera
            holds its own K; a (B, 3, 3) K of several cameras is a ValueError naming ``K``).
        dtype: float dtype of images and flow; ``camera_dtype`` of the camera (default ``dtype``).
        ground_truth: False -> no flow, valid, road.

    The arguments are checked here (``cam`` 0..3, ``camera_height`` a positive number within the
    camera's bounds, :func:`~fsof_torch.data.folders.check_mounting`; ``image_dir`` a folder name,
    ``K``), not at the first item; errors name the argument.
    """

    def __init__(self, root: str | os.PathLike, *, flow: str = "noc", image_dir: str = "image_2", cam: int = 2,
                 camera_height: float = KITTI_HEIGHT, K: Tensor | None = None, dtype: torch.dtype = torch.float32,
                 camera_dtype: torch.dtype | None = None, ground_truth: bool = True):
        if flow not in ("noc", "occ"):
            raise ValueError(f"flow: expected 'noc' or 'occ', got {flow!r}")
        camera_dtype = check_item_options(dtype, camera_dtype, ground_truth)
        cam = check_camera_index(cam)
        camera_height = check_mounting(camera_height, 0.0, 0.0, camera_dtype)[0]
        image_dir = str(as_path(image_dir, "image_dir"))
        self.root = _folder(root)
        images = self.root / image_dir
        if not images.is_dir():
            raise FileNotFoundError(f"root: {str(self.root)!r} has no {image_dir}/ folder")
        # regular, visible files only: a hidden one (macOS's ``._000000_10.png`` beside each frame,
        # a writer's temporary) is no frame, as in ImageFolderDataset and CarlaRun
        visible = [p for p in images.glob("*_1[01].png") if not p.name.startswith(".")]
        check_no_broken_links(visible, "root")  # (never a pair left out: a missing mount is an error)
        frames = sorted(p for p in visible if p.is_file())
        # every NAME_10 with its NAME_11 and back: an image without its partner (a file lost in a
        # copy) left its pair out of the data set without a word
        kitti_flow_layout(frames, "root")
        self.names = sorted(p.name[:-len("_10.png")] for p in frames if p.name.endswith("_10.png"))
        if not self.names:
            raise ValueError(f"root: {str(images)!r} holds no NAME_10.png / NAME_11.png pairs")
        self.image_dir, self.flow_dir = image_dir, f"flow_{flow}"
        other = "occ" if flow == "noc" else "noc"
        if ground_truth and not (self.root / self.flow_dir).is_dir() and (self.root / f"flow_{other}").is_dir():
            # (a test folder has neither; only the other one is another kind of ground truth, or a
            # synthetic layout, whose flow_occ/ marks occluded pixels invalid: not no flow at all)
            raise ValueError(f"flow: {str(self.root)!r} has flow_{other}/ but no flow_{flow}/; pass flow={other!r}")
        if K is not None:  # a copy, checked here: the caller's tensor is not shared with any item
            try:
                # (an array torch takes as it is, or copied first: a big-endian or reversed view)
                K = tensor_from_array(K) if isinstance(K, np.ndarray) else torch.as_tensor(K, device="cpu")
            except (TypeError, ValueError, RuntimeError):  # a str, a ragged list: as Camera.from_projection
                raise TypeError(f"K: expected a (3, 3) tensor or array of numbers, got "
                                f"{type(K).__name__} {K!r:.60}") from None
            K = K.detach().to("cpu", copy=True)
            Camera(K.to(camera_dtype), camera_height)
            if K.dim() == 3 and K.shape[0] != 1:  # (a camera of batch B: every item's camera B cameras)
                raise ValueError(f"K: expected one (3, 3) K for the pairs without a calibration file, got "
                                 f"{K.shape[0]} of them (shape {tuple(K.shape)})")
        self.cam, self.camera_height, self.K = cam, camera_height, K
        self.dtype, self.camera_dtype, self.ground_truth = dtype, camera_dtype, ground_truth

    def __len__(self) -> int:
        return len(self.names)

    def camera(self, name: str, size: tuple[int, int] | None = None) -> Camera | None:
        """The Camera (batch 1) of pair ``name``, or None when neither a file nor ``K`` gives one.
        ``size``: the pair's image size (H, W); a calibration file whose ``S_rect_0{cam}`` row
        states another size (the calibration of another sequence or camera) is a ValueError
        naming ``root``, the file and both sizes. A file without that row is taken as it is."""
        folders = ("calib_cam_to_cam", "calib")
        check_no_broken_links([self.root / f / f"{name}.txt" for f in folders], "root")  # (not "no file there")
        for folder in folders:
            path = self.root / folder / f"{name}.txt"
            if path.is_file():
                P = read_kitti_calibration(path, self.cam)
                stated = calibration_size(path, self.cam)
                if size is not None and stated is not None and stated != tuple(size):
                    raise ValueError(f"root: {str(path)!r} states S_rect_0{self.cam}: {stated[0]}x{stated[1]} (H x W), "
                                     f"but the pair's image {name}_10.png is {size[0]}x{size[1]}; its K is for "
                                     f"another image size (the calibration of another sequence or camera?)")
                camera = Camera.from_projection(P.to(self.camera_dtype), self.camera_height)
                # (a size stated in the file is checked above; a synthetic layout's calib/ holds the
                # renderer's camera of these very images, meta.json says so)
                if size is not None and stated is None and not (self.root / "meta.json").is_file():
                    self._check_principal_point(camera, size, name, f"root: {str(path)!r}",
                                                f"give images of the calibrated size, or, where the principal point "
                                                f"is right for these, add their size to the file as a row "
                                                f"'S_rect_0{self.cam}: W H'")
                return camera
        if self.K is not None:  # each item its own K: editing one changes no other, nor the caller's
            camera = Camera(self.K.to(self.camera_dtype, copy=True), self.camera_height)
            if size is not None:
                self._check_principal_point(camera, size, name, "K: the given K",
                                            "give the K of these images (Camera.scaled scales one)")
            return camera
        # a folder of other pairs' calibrations without this pair's: not a pair without a camera
        present = [f for f in folders if (self.root / f).is_dir() and any((self.root / f).glob("*.txt"))]
        if present:
            raise FileNotFoundError(f"root: {str(self.root)!r} has {present[0]}/ but no {name}.txt there for the "
                                    f"pair {name}; give every pair its calibration, or K= for those without")
        return None

    @staticmethod
    def _check_principal_point(camera: Camera, size: tuple[int, int], name: str, source: str, remedy: str) -> None:
        """A ValueError starting with ``source`` where the camera's principal point lies outside the
        middle third of the pair's images (:func:`~fsof_torch.data.folders.principal_point_off_centre`),
        as for :class:`ImageFolderDataset`: a calibration of images twice or half as large."""
        off = principal_point_off_centre(camera, size)
        if off is not None:
            raise ValueError(f"{source} has the principal point ({off[0]:.1f}, {off[1]:.1f}), outside the middle "
                             f"third of the pair's image {name}_10.png ({size[0]}x{size[1]}): a calibration of "
                             f"another image size (images resized since?); {remedy}")

    def __getitem__(self, index: int) -> dict[str, Any]:
        i = check_index(index, len(self))
        name = self.names[i]
        images = self.root / self.image_dir
        first = images / f"{name}_10.png"
        image1 = read_image(first).to(self.dtype)
        size = tuple(image1.shape[-2:])
        second = images / f"{name}_11.png"
        image2 = _fits(read_image(second), second, size, first, "root").to(self.dtype)
        truth: dict[str, Any] = {}
        if self.ground_truth:
            path = self.root / self.flow_dir / f"{name}_10.png"
            road = self.root / "road" / f"{name}_10.png"
            semantic = self.root / "semantic" / f"{name}_10.png"
            # (a drive not mounted, not a missing file; semantic/ where road/ has no file for the pair)
            check_no_broken_links([path, road] + ([] if road.is_file() else [semantic]), "root")
            if path.is_file() or (self.root / self.flow_dir).is_dir():
                # (a flow folder without the pair's file is an error, not a pair without ground truth)
                try:
                    flow, valid = read_kitti_flow(path)
                except FileNotFoundError:
                    raise FileNotFoundError(f"root: {str(self.root)!r} has {self.flow_dir}/ but no {path.name} there "
                                            f"for the pair {name}; every pair of a folder with ground truth needs "
                                            f"its flow") from None
                truth["flow"], truth["valid"] = _fits(flow, path, size, first, "root").to(self.dtype), valid
            if road.is_file():
                truth["road"] = _fits(read_road_mask(road), road, size, first, "root")
            elif semantic.is_file():
                truth["road"] = _hand_labelled_road(semantic, size, first)
            elif road.parent.is_dir() or semantic.parent.is_dir():  # (not a pair without road)
                raise FileNotFoundError(f"root: {str(self.root)!r} has {'road' if road.parent.is_dir() else 'semantic'}/"
                                        f" but no {road.name} there (nor in the other of road/, semantic/) for the "
                                        f"pair {name}; every pair of a folder with road masks needs its mask")
        return make_item(image1, image2, index=i, name=name, camera=self.camera(name, size), **truth)


class KittiSampleDataset(ImageFolderDataset):
    """The single-pair folder ``shared/data/kitti15_000000`` (or one like it): ``image_10.png``,
    ``image_11.png``, and where present ``calib_cam_to_cam.txt`` (camera ``cam``, with its
    ``S_rect`` size checked), ``flow_noc_10.png`` (ground truth), ``road.json``. The pair is named
    after the folder. No odometry (KITTI flow does not publish it). ``camera_height`` in metres,
    ``roll`` and ``pitch`` in radians; ``road_json=False``: the folder's ``road.json`` is not read
    (items without ``road``, for a caller that finds the road itself); the other arguments as in
    :class:`ImageFolderDataset`.
    """

    def __init__(self, folder: str | os.PathLike, *, cam: int = 2, camera_height: float = KITTI_HEIGHT,
                 roll: float = 0.0, pitch: float = 0.0, dtype: torch.dtype = torch.float32,
                 camera_dtype: torch.dtype | None = None, ground_truth: bool = True, road_json: bool = True):
        check_item_options(dtype, camera_dtype, ground_truth)  # before the files, as every dataset does
        road_json = check_bool(road_json, "road_json")
        self.folder = f = _folder(folder, "folder")
        # (a link to a missing file is no absent part: read as one, the pair lost its camera, flow or road)
        read = ["image_10.png", "image_11.png", "calib_cam_to_cam.txt"] + ["flow_noc_10.png"] * ground_truth
        check_no_broken_links([f / name for name in read + ["road.json"] * road_json], "folder")
        for file in ("image_10.png", "image_11.png"):
            if not (f / file).is_file():
                raise FileNotFoundError(f"folder: {str(f)!r} has no {file}")
        calib, road, gt = f / "calib_cam_to_cam.txt", f / "road.json", f / "flow_noc_10.png"
        super().__init__([f / "image_10.png", f / "image_11.png"], calib if calib.is_file() else None, cam=cam,
                         camera_height=camera_height, roll=roll, pitch=pitch,
                         road=road if road_json and road.is_file() else None, dtype=dtype,
                         camera_dtype=camera_dtype, ground_truth=ground_truth)
        # (named after the folder itself: ``.`` or ``sub/..`` has no name of its own)
        self.pairs = [replace(self.pairs[0], name=f.resolve().name or "kitti15", gt=gt if gt.is_file() else None)]


class KittiOdometryDataset(ImageFolderDataset):
    """Consecutive frames of a KITTI odometry clip (like ``shared/data/kitti_odometry_straight``)
    with the odometry from its ground-truth poses.

    Folder: ``image_dir/NNNNNN.png`` frames, ``calib.txt`` (``P{cam}``), ``poses.txt``
    (camera-to-world, line n for frame n), optionally ``road.json`` (one polygon for the clip).
    Frames are the files whose name is a number (ASCII digits); two files of one number
    (``2.png`` and ``000002.png``) are a ValueError naming the folder and both. Only frames with a
    pose are used; pair ``i`` is frames (i, i + step) of those, named after its first frame.
    ``odometry`` is :func:`fsof_torch.egomotion.ego_motion_from_pose` of the pair's
    ``relative_pose`` under the camera's mounting (``roll``, ``pitch`` in radians, default 0);
    ``pose_residual`` what the planar model drops (``y_d`` in metres, rotation residual angle in
    radians). ``road_json=False``: ``road.json`` is not read (items without ``road``, for a caller
    that finds the road itself). The other arguments as in :class:`ImageFolderDataset`.
    """

    def __init__(self, folder: str | os.PathLike, *, image_dir: str = "image_l", cam: int = 0, step: int = 1,
                 camera_height: float = KITTI_HEIGHT, roll: float = 0.0, pitch: float = 0.0,
                 dtype: torch.dtype = torch.float32, camera_dtype: torch.dtype | None = None,
                 ground_truth: bool = True, road_json: bool = True):
        check_item_options(dtype, camera_dtype, ground_truth)  # ground_truth decides below whether poses are needed
        road_json = check_bool(road_json, "road_json")
        self.folder = _folder(folder, "folder")
        # (a link to a missing file is no absent part: read as one, the clip lost its road)
        read = ["calib.txt"] + ["poses.txt"] * ground_truth + ["road.json"] * road_json
        check_no_broken_links([self.folder / name for name in read], "folder")
        step = check_int(step, "step", minimum=1)
        images = self.folder / as_path(image_dir, "image_dir")
        if not images.is_dir():
            raise FileNotFoundError(f"folder: {str(self.folder)!r} has no {image_dir}/ folder")
        # ASCII digits only: str.isdigit takes '²', which int() refuses
        frames = sorted((p for p in images.glob("*.png") if re.fullmatch(r"[0-9]+", p.stem)),
                        key=lambda p: (int(p.stem), p.name))
        for a, b in zip(frames, frames[1:]):
            if int(a.stem) == int(b.stem):  # 2.png and 000002.png: which one is frame 2 is a guess
                raise ValueError(f"folder: {str(images)!r} has two files of frame {int(a.stem)}, {a.name} and "
                                 f"{b.name}; keep one")
        if len(frames) <= step:  # (not "no pairs with poses": the frames are not there, or not named so)
            others = sorted(p.name for p in images.iterdir() if p.is_file() and not p.name.startswith(".")
                            and p not in frames)
            shown = f"; other files there: {', '.join(others[:3])}{', ...' if len(others) > 3 else ''}" if others else ""
            raise ValueError(f"folder: {str(images)!r} holds {len(frames)} frame(s), PNG files named by a number "
                             f"(000000.png, ...), and a pair (i, i + {step}) needs {step + 1}{shown}")
        path, poses = self.folder / "poses.txt", None
        if ground_truth or path.is_file():
            try:
                P = read_kitti_poses(path)
            except FileNotFoundError:
                raise FileNotFoundError(f"poses: no file at {str(path)!r}") from None
            except ValueError as err:
                raise ValueError(f"poses: {str(err).removeprefix('path: ')}") from None
            with_pose = [p for p in frames if int(p.stem) < len(P)]
            if len(with_pose) <= step:
                raise ValueError(f"folder: {str(self.folder)!r} has no frame pairs with poses (step {step}): "
                                 f"{path.name} holds {len(P)} poses (line n for frame n), {len(with_pose)} of the "
                                 f"frames {frames[0].name} ... {frames[-1].name} have one")
            frames, poses = with_pose, P[[int(p.stem) for p in with_pose]]
        road = self.folder / "road.json"
        super().__init__(frames, self.folder / "calib.txt", cam=cam, camera_height=camera_height, roll=roll,
                         pitch=pitch, poses=poses, road=road if road_json and road.is_file() else None, step=step,
                         dtype=dtype, camera_dtype=camera_dtype, ground_truth=ground_truth)


class CarlaRunDataset(Dataset):
    """Frame pairs (k, k+1) of one run of the paper's CARLA layout (see :mod:`fsof_torch.io.carla`).

    ``flow_velocity`` (an extra key) is the run's flow of frame k (the paper: instantaneous, px/s)
    and ``valid`` its validity; ``flow`` is None (CARLA gives velocities). ``road`` from the
    semantic PNG; ``camera`` from :func:`fsof_torch.io.carla_camera` with the roll of the run name
    (``r`` in degrees). Pairs are named after frame k. Every file of a pair (frame k + 1, flow,
    semantic PNG) must have the size of frame k: one of another size is a ValueError naming ``run``
    and the file; a run with an ``optical_flow/`` or ``semantic/`` folder that lacks a pair's file is
    a FileNotFoundError naming ``run`` and the file when the pair loads (never an item without that
    ground truth). ``camera_height`` (metres, default 2.4) must be a positive number within the
    camera's bounds (checked here, not at the first item). The run's name is that of the folder itself (``.`` or ``run/rgb/..``
    is made absolute first); a run of fewer than two frames, or a roll part of its name that does
    not read as one, is a ValueError naming ``run``; a ``run`` that is no folder, or has no
    ``rgb/``, a FileNotFoundError naming ``run``.
    """

    def __init__(self, run: str | os.PathLike, *, camera_height: float = 2.4, dtype: torch.dtype = torch.float32,
                 camera_dtype: torch.dtype | None = None, ground_truth: bool = True):
        self.camera_dtype = check_item_options(dtype, camera_dtype, ground_truth)
        self.camera_height = check_mounting(camera_height, 0.0, 0.0, self.camera_dtype)[0]
        # absolute, '..' collapsed, symbolic links kept: the roll comes from the folder's own name
        path = existing_folder(Path(os.path.abspath(as_path(run, "run"))), "run")
        try:
            self.run = CarlaRun(path)
        except (FileNotFoundError, ValueError) as err:  # (CarlaRun's errors name its own argument, root)
            message = str(err)
            prefix = next((p for p in ("root: ", "name: ") if message.startswith(p)), None)
            if prefix is None:
                raise
            raise type(err)("run: " + message[len(prefix):]) from None
        if len(self.run) < 2:
            raise ValueError(f"run: {str(self.run.root)!r} holds no pairs ({len(self.run)} frame in rgb/)")
        self.dtype, self.ground_truth = dtype, ground_truth

    def __len__(self) -> int:
        return len(self.run) - 1

    def __getitem__(self, index: int) -> dict[str, Any]:
        i = check_index(index, len(self))
        a, b = self.run.frames[i], self.run.frames[i + 1]
        first, second = self.run.path("rgb", a), self.run.path("rgb", b)
        image1 = read_image(first).to(self.dtype)
        size = tuple(image1.shape[-2:])
        image2 = _fits(read_image(second), second, size, first, "run").to(self.dtype)
        camera = carla_camera(size, height=self.camera_height, roll=self.run.params.get("roll", 0.0),
                              dtype=self.camera_dtype)
        truth: dict[str, Any] = {}
        if self.ground_truth:
            path = self._truth_file("optical_flow", a)
            if path is not None:
                flow, valid = read_carla_flow(path)
                truth["flow_velocity"], truth["valid"] = _fits(flow, path, size, first, "run").to(self.dtype), valid
            path = self._truth_file("semantic", a)
            if path is not None:
                truth["road"] = _fits(read_carla_road(path), path, size, first, "run")
        return make_item(image1, image2, index=i, name=a, camera=camera, **truth)

    def _truth_file(self, kind: str, frame: str) -> Path | None:
        """The frame's file of ``kind`` (``optical_flow``, ``semantic``); None where the run has no
        such folder. A folder without the frame's file is a FileNotFoundError naming ``run`` and the
        file, never an item without that ground truth."""
        path = self.run.path(kind, frame)
        check_no_broken_links([path], "run")  # (a drive not mounted, not a file missing from the folder)
        if path.is_file() or not path.parent.is_dir():
            return path if path.is_file() else None
        raise FileNotFoundError(f"run: {str(self.run.root)!r} has {kind}/ but no {path.name} there for the pair "
                                f"{frame}; every pair of a run with ground truth needs its file")
