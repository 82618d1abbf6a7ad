"""What the job works on: image pairs with a camera, and optionally odometry, a road mask, ground
truth and flow files; and where they come from (a synthetic sequence, a folder, the shared KITTI
samples). Pairs load lazily, so a resumed run does not read or render finished pairs."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor

from fsof_torch.geometry.camera import Camera

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff")
FLOW_SUFFIXES = (".png", ".flo", ".npy")


class JobError(Exception):
    """A problem with the job's inputs or options: reported as ``error: ...`` with exit code 2."""


@dataclass
class PairSpec:
    """One image pair of the job, loaded on demand.

    ``load()`` returns a dict: ``image1``, ``image2`` (3, H, W) float32 0..255; ``camera``
    (batch 1, K at the images' resolution); ``odometry`` (dict x_d, z_d, yaw floats) or None;
    ``road`` (1, H, W) bool or None (then detected); ``gt`` ``(flow (2, H, W), valid (1, H, W))``
    or None.
    """

    name: str
    load: Callable[[], dict[str, Any]]
    flow_files: dict[str, Path] = field(default_factory=dict)


# -- synthetic -----------------------------------------------------------------------------------

def synthetic_pairs(preset: str, num_pairs: int, *, seed: int, size: tuple[int, int] | None,
                    road: str | None, noise: float | None = None) -> list[PairSpec]:
    """Pairs of a rendered sequence (``fsof_torch.data.scene``), with the scene's exact ground truth,
    road mask and odometry. ``road="auto"`` leaves the mask to detection; ``noise`` overrides the
    preset's sensor noise (grey levels at 375×1242)."""
    from fsof_torch import scene

    if preset not in scene.PRESETS:
        raise JobError(f"--preset: unknown preset {preset!r}; choose from {', '.join(sorted(scene.PRESETS))}")
    if num_pairs < 1:
        raise JobError(f"--num-pairs: expected >= 1, got {num_pairs}")
    if noise is not None and not noise >= 0:
        raise JobError(f"--scene-noise: expected >= 0 grey levels, got {noise}")
    overrides = {} if noise is None else {"noise": float(noise)}

    def loader(index: int) -> Callable[[], dict[str, Any]]:
        def load() -> dict[str, Any]:
            p = scene.render_pair(preset, index, seed=seed, size=size, dtype=torch.float32, **overrides)
            odo = {k: float(v) for k, v in p["odometry"].items() if k in ("x_d", "z_d", "yaw")}
            return {"image1": p["image1"], "image2": p["image2"], "camera": p["camera"].to(torch.float64),
                    "odometry": odo, "road": None if road == "auto" else p["road"],
                    "gt": (p["flow"], p["valid"])}
        return load

    return [PairSpec(f"{index:06d}", loader(index)) for index in range(num_pairs)]


# -- user data -----------------------------------------------------------------------------------

def list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise JobError(f"--images: no folder at {str(folder)!r}")
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if len(images) < 2:
        raise JobError(f"--images: {str(folder)!r} holds {len(images)} image(s); a pair needs at least 2")
    return images


def image_pairs(images: list[Path]) -> list[tuple[str, Path, Path]]:
    """Consecutive pairs (i, i+1); KITTI flow layout (``NNNNNN_10`` / ``NNNNNN_11``) pairs by name."""
    stems = {p.stem: p for p in images}
    kitti = [s for s in stems if re.fullmatch(r".*_10", s)]
    if kitti and all(s[:-3] + "_11" in stems for s in kitti):
        return [(s[:-3], stems[s], stems[s[:-3] + "_11"]) for s in sorted(kitti)]
    return [(images[i].stem, images[i], images[i + 1]) for i in range(len(images) - 1)]


def match_files(folder: Path, names: list[str], what: str, suffixes=FLOW_SUFFIXES,
                stems_of: dict[str, list[str]] | None = None) -> dict[str, Path]:
    """One file per pair from ``folder``: by name (the pair's name or its first image's stem, any
    of ``suffixes``), else by sorted order when the counts agree."""
    if not folder.is_dir():
        raise JobError(f"{what}: no folder at {str(folder)!r}")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)
    by_stem: dict[str, Path] = {}
    for p in files:
        by_stem.setdefault(p.stem, p)
    out: dict[str, Path] = {}
    for name in names:
        for stem in [name, *(stems_of or {}).get(name, [])]:
            if stem in by_stem:
                out[name] = by_stem[stem]
                break
    if len(out) == len(names):
        return out
    if len(files) == len(names):
        return dict(zip(names, files))
    missing = [n for n in names if n not in out][:3]
    raise JobError(f"{what}: {str(folder)!r} has {len(files)} file(s) ({', '.join(suffixes)}) for "
                   f"{len(names)} pairs, and none named like pair(s) {missing}")


def read_camera(calib: Path, cam: int | None, height: float, roll_deg: float, pitch_deg: float) -> Camera:
    """A camera from a KITTI calibration file (``calib_cam_to_cam.txt`` or odometry ``calib.txt``).

    Without ``cam``: camera 2 (the left colour camera) when the file has it, else camera 0.
    """
    from fsof_torch.geometry.camera import read_kitti_calibration

    if not calib.is_file():
        raise JobError(f"--calib: no calibration file at {str(calib)!r}")
    for c in ([cam] if cam is not None else [2, 0]):
        try:
            P = read_kitti_calibration(calib, c)
            break
        except ValueError as err:
            last = err
    else:
        raise JobError(f"--calib: {last}")
    return Camera.from_projection(P, height, math.radians(roll_deg), math.radians(pitch_deg))


def odometry_from_pose(cam1_T_cam0: Tensor, camera: Camera) -> dict[str, float]:
    """The planar ego-motion (x_d, z_d, yaw) of a relative camera pose (4, 4), under the camera's
    mounting (its roll and pitch relate camera and vehicle frames)."""
    from fsof_torch.geometry.egomotion import ego_motion_from_pose

    ego = ego_motion_from_pose(cam1_T_cam0.to(torch.float64).unsqueeze(0), camera.to(torch.float64))
    return {"x_d": float(ego.x_d[0]), "z_d": float(ego.z_d[0]), "yaw": float(ego.yaw[0])}


def user_pairs(*, images: Path, calib: Path, cam: int | None, height: float, roll_deg: float,
               pitch_deg: float, poses: Path | None, flows: Path | None, road: str | None,
               gt: Path | None, image_list: list[Path] | None = None) -> tuple[list[PairSpec], Camera]:
    """Pairs of consecutive images of a folder (or of ``image_list``) with the options' inputs."""
    from fsof_torch.io import read_flow, read_image, read_kitti_poses, read_road_mask

    files = image_list if image_list is not None else list_images(images)
    pairs = image_pairs(files)
    names = [n for n, _, _ in pairs]
    stems = {n: [a.stem] for n, a, _ in pairs}
    camera = read_camera(calib, cam, height, roll_deg, pitch_deg)

    relative: list[Tensor | None] = [None] * len(pairs)
    if poses is not None:
        if not poses.is_file():
            raise JobError(f"--poses: no file at {str(poses)!r}")
        P = read_kitti_poses(poses).to(torch.float64)
        index = {p: i for i, p in enumerate(files)}
        need = max(index[b] for _, _, b in pairs) + 1
        if P.shape[0] < need:
            raise JobError(f"--poses: {str(poses)!r} has {P.shape[0]} poses for {need} images")
        # cam1_T_cam0 = inverse(P1) @ P0 for camera-to-world poses
        relative = [torch.linalg.inv(P[index[b]]) @ P[index[a]] for _, a, b in pairs]

    flow_files = match_files(flows, names, "--flows", stems_of=stems) if flows is not None else {}
    gt_files = match_files(gt, names, "--gt", stems_of=stems) if gt is not None else {}
    road_files: dict[str, Path] = {}
    road_json: Path | None = None
    if road not in (None, "auto"):
        rp = Path(road)
        if rp.suffix.lower() == ".json" or rp.is_file():
            if not rp.is_file():
                raise JobError(f"--road: no file at {str(rp)!r}")
            road_json = rp
        else:
            road_files = match_files(rp, names, "--road", suffixes=IMAGE_SUFFIXES, stems_of=stems)
    elif road is None:
        raise JobError("--road: user data needs road masks: a folder of PNGs, a polygon JSON, or 'auto'")

    def loader(i: int, name: str, a: Path, b: Path) -> Callable[[], dict[str, Any]]:
        def load() -> dict[str, Any]:
            im1, im2 = read_image(a), read_image(b)
            if im1.shape != im2.shape:
                raise JobError(f"--images: {a.name} is {tuple(im1.shape[-2:])} but {b.name} is {tuple(im2.shape[-2:])}")
            size = tuple(im1.shape[-2:])
            mask = None
            if road_json is not None:
                mask = read_road_mask(road_json, size)
            elif name in road_files:
                mask = read_road_mask(road_files[name])
                if tuple(mask.shape[-2:]) != size:
                    raise JobError(f"--road: {road_files[name].name} is {tuple(mask.shape[-2:])}, the images {size}")
            gt_pair = None
            if name in gt_files:
                gt_pair = read_flow(gt_files[name])
                if tuple(gt_pair[0].shape[-2:]) != size:
                    raise JobError(f"--gt: {gt_files[name].name} is {tuple(gt_pair[0].shape[-2:])}, the images {size}")
            odo = None
            if relative[i] is not None:
                odo = odometry_from_pose(relative[i], camera)
            return {"image1": im1, "image2": im2, "camera": camera, "odometry": odo,
                    "relative_pose": relative[i], "road": mask, "gt": gt_pair}
        return load

    specs = [PairSpec(name, loader(i, name, a, b),
                      {"files": flow_files[name]} if name in flow_files else {})
             for i, (name, a, b) in enumerate(pairs)]
    return specs, camera


# -- the shared KITTI samples --------------------------------------------------------------------

def kitti15_pairs(root: Path, *, height: float, flows: Path | None = None) -> list[PairSpec]:
    """``kitti15_000000``: image_10/image_11, calib_cam_to_cam.txt (P_rect_02), flow_noc_10.png
    (ground truth), road.json."""
    need = ["image_10.png", "image_11.png", "calib_cam_to_cam.txt", "flow_noc_10.png", "road.json"]
    missing = [n for n in need if not (root / n).is_file()]
    if missing:
        raise JobError(f"--kitti15: {str(root)!r} lacks {missing}")
    specs, _ = user_pairs(images=root, calib=root / "calib_cam_to_cam.txt", cam=2, height=height,
                          roll_deg=0.0, pitch_deg=0.0, poses=None, flows=flows,
                          road=str(root / "road.json"), gt=None,
                          image_list=[root / "image_10.png", root / "image_11.png"])
    from fsof_torch.io import read_flow

    spec = specs[0]
    inner = spec.load

    def load() -> dict[str, Any]:
        d = inner()
        d["gt"] = read_flow(root / "flow_noc_10.png")
        return d

    return [PairSpec("kitti15_000000", load, spec.flow_files)]


def kitti_odometry_pairs(root: Path, *, height: float, pitch_deg: float) -> tuple[list[PairSpec], Camera]:
    """``kitti_odometry_straight``: image_l/ (cam 0), calib.txt (P0), poses.txt, road.json."""
    for n in ("image_l", "calib.txt", "poses.txt", "road.json"):
        if not (root / n).exists():
            raise JobError(f"--kitti-odometry: {str(root)!r} lacks {n}")
    images = list_images(root / "image_l")
    # The clip has one image more than poses: pair only the images that have a pose.
    poses_n = sum(1 for line in (root / "poses.txt").read_text().splitlines() if line.strip())
    return user_pairs(images=root / "image_l", calib=root / "calib.txt", cam=0, height=height,
                      roll_deg=0.0, pitch_deg=pitch_deg, poses=root / "poses.txt", flows=None,
                      road=str(root / "road.json"), gt=None, image_list=images[:poses_n])
