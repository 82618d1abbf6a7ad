"""What the job works on: image pairs with a camera, and optionally odometry, a road mask, ground
truth and flow files; and where they come from (a synthetic sequence, a folder, the shared KITTI
samples). Pairs load lazily, so a resumed run does not read or render finished pairs; everything
that can be checked without loading every pair is checked here, before any work.

Files are paired with image pairs by name only, never by position: the pair ``NAME`` (KITTI's
``NAME_10``/``NAME_11``, or consecutive frames ``NAME``, ``NEXT``) takes ``NAME.<ext>`` from
``--flows``, ``--road`` and ``--gt`` (``<ext>`` one of the folder's formats).

Image size against the calibration: a KITTI ``calib_cam_to_cam.txt`` states the rectified size
(``S_rect_0N``), ``--calib-size`` states it for other files; every image must have exactly that
size. Without either, every image must have the size of the first pair, and the principal point
must lie in the middle third of that image (|c_x − (W−1)/2| ≤ W/6, likewise for y): a calibration
made for images twice as large or half as large fails this test (its principal point lies a
quarter or a half of the image away from the centre), a camera's own offset (KITTI: 11 px of
1242) passes it.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor

from fsof_torch import Camera

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
    or None. ``identity()`` describes the pair's inputs (file contents, render parameters) for
    the resume fingerprint.
    """

    name: str
    load: Callable[[], dict[str, Any]]
    flow_files: dict[str, Path] = field(default_factory=dict)
    identity: Callable[[], dict[str, Any]] = dict


def file_digest(path: Path) -> str:
    """BLAKE2b of a file's bytes (hex, 32 characters): the file's identity for resuming."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


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

    # the scene and its options are in the run's fingerprint; a pair is its index
    return [PairSpec(f"{index:06d}", loader(index), identity=lambda i=index: {"index": i})
            for index in range(num_pairs)]


# -- user data -----------------------------------------------------------------------------------

def list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise JobError(f"--images: no folder at {str(folder)!r}")
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if len(images) < 2:
        raise JobError(f"--images: {str(folder)!r} holds {len(images)} image(s); a pair needs at least 2")
    return images


def kitti_flow_layout(images: list[Path]) -> bool:
    """Whether the images are KITTI flow pairs (``NNNNNN_10`` / ``NNNNNN_11``), not one clip."""
    stems = {p.stem for p in images}
    kitti = [s for s in stems if re.fullmatch(r".*_10", s)]
    return bool(kitti) and all(s[:-3] + "_11" in stems for s in kitti)


def image_pairs(images: list[Path]) -> list[tuple[str, Path, Path]]:
    """Consecutive pairs (i, i+1); KITTI flow layout (``NNNNNN_10`` / ``NNNNNN_11``) pairs by name."""
    stems = {p.stem: p for p in images}
    kitti = [s for s in stems if re.fullmatch(r".*_10", s)]
    if kitti_flow_layout(images):
        return [(s[:-3], stems[s], stems[s[:-3] + "_11"]) for s in sorted(kitti)]
    return [(images[i].stem, images[i], images[i + 1]) for i in range(len(images) - 1)]


def match_files(folder: Path, names: list[str], what: str, suffixes=FLOW_SUFFIXES,
                stems_of: dict[str, list[str]] | None = None) -> dict[str, Path]:
    """One file per pair from ``folder``, by name: the pair's name or its first image's stem,
    with any of ``suffixes``. A pair without such a file, or with two (``0001.png`` and
    ``0001.flo``), is an error naming the option and the file: files are never paired by
    position."""
    if not folder.is_dir():
        raise JobError(f"{what}: no folder at {str(folder)!r}")
    by_stem: dict[str, list[Path]] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in suffixes:
            by_stem.setdefault(p.stem, []).append(p)
    out: dict[str, Path] = {}
    for name in names:
        stems = list(dict.fromkeys([name, *(stems_of or {}).get(name, [])]))
        found = [p for s in stems for p in by_stem.get(s, [])]
        if len(found) > 1:
            raise JobError(f"{what}: pair {name} matches {len(found)} files in {str(folder)!r} "
                           f"({', '.join(p.name for p in found)}); keep one")
        if not found:
            near = sorted(by_stem)[:3]
            raise JobError(f"{what}: no file for pair {name} in {str(folder)!r}: expected "
                           f"{' or '.join(s + '.*' for s in stems)} ({', '.join(suffixes)}); "
                           f"the folder has {sum(len(v) for v in by_stem.values())} such file(s)"
                           + (f", e.g. {', '.join(near)}" if near else ""))
        out[name] = found[0]
    return out


def calibration_size(calib: Path, cam: int) -> tuple[int, int] | None:
    """The rectified image size (H, W) a KITTI ``calib_cam_to_cam.txt`` states for camera
    ``cam`` (``S_rect_0N: W H``), or None when the file has no such row (odometry ``calib.txt``)."""
    try:
        text = calib.read_text()
    except UnicodeDecodeError:
        return None  # read_camera reports the file
    for line in text.splitlines():
        key, sep, rest = line.partition(":")
        if sep and key.strip() == f"S_rect_0{cam}":
            try:
                w, h = (float(x) for x in rest.split())
            except ValueError:
                raise JobError(f"--calib: {str(calib)!r} has an S_rect_0{cam} row that is not 'W H': "
                               f"{line.strip()[:60]!r}") from None
            return int(round(h)), int(round(w))
    return None


def read_camera(calib: Path, cam: int | None, height: float, roll_deg: float,
                pitch_deg: float) -> tuple[Camera, int]:
    """A camera from a KITTI calibration file (``calib_cam_to_cam.txt`` or odometry ``calib.txt``)
    and the camera index used. Without ``cam``: camera 2 (the left colour camera) when the file
    has it, else camera 0."""
    from fsof_torch import read_kitti_calibration

    if not calib.is_file():
        raise JobError(f"--calib: no calibration file at {str(calib)!r}")
    if cam is not None and not 0 <= cam <= 3:
        raise JobError(f"--cam: expected 0..3, got {cam}")
    for c in ([cam] if cam is not None else [2, 0]):
        try:
            P = read_kitti_calibration(calib, c)
            break
        except UnicodeDecodeError:
            raise JobError(f"--calib: {str(calib)!r} is not a text file; expected a KITTI "
                           f"calib_cam_to_cam.txt or calib.txt") from None
        except ValueError as err:
            last = err
    else:
        raise JobError(f"--calib: {last}")
    for name, value in (("--height", height), ("--roll-deg", roll_deg), ("--pitch-deg", pitch_deg)):
        if not math.isfinite(value):
            raise JobError(f"{name}: expected a finite number, got {value}")
    if not height > 0:
        raise JobError(f"--height: expected > 0 m, got {height}")
    try:
        camera = Camera.from_projection(P, height, math.radians(roll_deg), math.radians(pitch_deg))
    except ValueError as err:
        raise JobError(f"--calib: {str(calib)!r} camera {c}: {err}") from None
    return camera, c


def check_image_size(size: tuple[int, int], image: Path, camera: Camera, calib: Path,
                     expected: tuple[int, int] | None) -> None:
    """An image of ``size`` (H, W) against the calibration (see the module docstring)."""
    if expected is not None:
        if tuple(size) != tuple(expected):
            raise JobError(f"--images: {image.name} is {size[0]}x{size[1]} but the calibration "
                           f"{str(calib)!r} is for {expected[0]}x{expected[1]} images; resize the images, "
                           f"or give the calibration of this size")
        return
    H, W = size
    cx, cy = float(camera.cx[0]), float(camera.cy[0])
    if abs(cx - (W - 1) / 2) > W / 6 or abs(cy - (H - 1) / 2) > H / 6:
        raise JobError(f"--images: {image.name} is {H}x{W}, but the principal point of {str(calib)!r} "
                       f"({cx:.1f}, {cy:.1f}) lies outside the middle third of such an image: the "
                       f"calibration belongs to another image size (give images of the calibrated size, "
                       f"or state the size with --calib-size HxW)")


def _rigid_poses(P: Tensor, poses: Path, rows: list[int]) -> None:
    """Each pose used must be a rigid transform: a rotation (orthonormal, determinant 1)."""
    R = P[:, :3, :3]
    eye = torch.eye(3, dtype=P.dtype)
    for i in rows:
        det = float(torch.linalg.det(R[i]))
        err = float((R[i] @ R[i].T - eye).abs().max())
        if not (abs(det - 1.0) < 1e-3 and err < 1e-3):
            raise JobError(f"--poses: pose {i + 1} (line {i + 1}) of {str(poses)!r} is not a rigid camera pose: "
                           f"its rotation has determinant {det:.4g} and deviates from orthonormal by {err:.3g}")


def odometry_from_pose(cam1_T_cam0: Tensor, camera: Camera) -> dict[str, float]:
    """The planar ego-motion (x_d, z_d, yaw) of a relative camera pose (4, 4), under the camera's
    mounting (its roll and pitch relate camera and vehicle frames)."""
    from fsof_torch import ego_motion_from_pose

    ego = ego_motion_from_pose(cam1_T_cam0.to(torch.float64).unsqueeze(0), camera.to(torch.float64))
    return {"x_d": float(ego.x_d[0]), "z_d": float(ego.z_d[0]), "yaw": float(ego.yaw[0])}


def _read_road(path: Path, size: tuple[int, int] | None) -> Tensor:
    """A road mask file through the library's reader; whatever it rejects names ``--road``."""
    from fsof_torch import read_road_mask

    try:
        return read_road_mask(path, size)
    except FileNotFoundError:
        raise JobError(f"--road: no file at {str(path)!r}") from None
    except (ValueError, TypeError, KeyError, IndexError, ZeroDivisionError, UnicodeDecodeError,
            AttributeError, OverflowError) as err:
        raise JobError(f"--road: {str(path)!r} is not a usable road mask ({type(err).__name__}: {err})") from None


def user_pairs(*, images: Path, calib: Path, cam: int | None, height: float, roll_deg: float,
               pitch_deg: float, poses: Path | None, flows: Path | None, road: str | None,
               gt: Path | None, calib_size: tuple[int, int] | None = None,
               image_list: list[Path] | None = None) -> tuple[list[PairSpec], Camera]:
    """Pairs of consecutive images of a folder (or of ``image_list``) with the options' inputs,
    checked before any work: files matched by name, poses rigid, the road file readable, the
    first pair's size against the calibration (the others when they load)."""
    from fsof_torch import read_flow, read_image, read_kitti_poses

    files = image_list if image_list is not None else list_images(images)
    pairs = image_pairs(files)
    names = [n for n, _, _ in pairs]
    stems = {n: [a.stem] for n, a, _ in pairs}
    camera, cam_used = read_camera(calib, cam, height, roll_deg, pitch_deg)
    expected = calib_size or calibration_size(calib, cam_used)

    relative: list[Tensor | None] = [None] * len(pairs)
    pose_rows: list[list[float] | None] = [None] * len(pairs)
    if poses is not None:
        if not poses.is_file():
            raise JobError(f"--poses: no file at {str(poses)!r}")
        try:
            P = read_kitti_poses(poses).to(torch.float64)
        except UnicodeDecodeError:
            raise JobError(f"--poses: {str(poses)!r} is not a text file; expected KITTI poses "
                           f"(12 numbers a line)") from None
        except ValueError as err:
            raise JobError(f"--poses: {err}") from None
        index = {p: i for i, p in enumerate(files)}
        need = max(index[b] for _, _, b in pairs) + 1
        if P.shape[0] < need:
            raise JobError(f"--poses: {str(poses)!r} has {P.shape[0]} poses for {need} images")
        _rigid_poses(P, poses, sorted({index[x] for _, a, b in pairs for x in (a, b)}))
        # cam1_T_cam0 = inverse(P1) @ P0 for camera-to-world poses
        relative = [torch.linalg.inv(P[index[b]]) @ P[index[a]] for _, a, b in pairs]
        pose_rows = [torch.cat([P[index[a]].flatten(), P[index[b]].flatten()]).tolist() for _, a, b in pairs]

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

    # the first pair, before any work: its size fixes the job's size (or meets the calibration's)
    first = read_image(pairs[0][1])
    size = tuple(first.shape[-2:])
    check_image_size(size, pairs[0][1], camera, calib, expected)
    if road_json is not None:
        _read_road(road_json, size)

    def loader(i: int, name: str, a: Path, b: Path) -> Callable[[], dict[str, Any]]:
        def load() -> dict[str, Any]:
            im1, im2 = read_image(a), read_image(b)
            for path, im in ((a, im1), (b, im2)):
                if tuple(im.shape[-2:]) != size:
                    raise JobError(f"--images: {path.name} is {im.shape[-2]}x{im.shape[-1]} but "
                                   f"{pairs[0][1].name} is {size[0]}x{size[1]}; all images need one size "
                                   f"(the calibration's)")
            mask = None
            if road_json is not None:
                mask = _read_road(road_json, size)
            elif name in road_files:
                mask = _read_road(road_files[name], None)
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

    def identity(i: int, name: str, a: Path, b: Path) -> Callable[[], dict[str, Any]]:
        def describe() -> dict[str, Any]:
            files_ = {"image1": a, "image2": b, "flow": flow_files.get(name), "gt": gt_files.get(name),
                      "road": road_files.get(name)}
            return {"files": {k: file_digest(p) for k, p in files_.items() if p is not None},
                    "poses": pose_rows[i]}
        return describe

    specs = [PairSpec(name, loader(i, name, a, b),
                      {"files": flow_files[name]} if name in flow_files else {}, identity(i, name, a, b))
             for i, (name, a, b) in enumerate(pairs)]
    return specs, camera


# -- the shared KITTI samples --------------------------------------------------------------------

def kitti15_pairs(root: Path, *, height: float) -> tuple[list[PairSpec], Camera]:
    """``kitti15_000000``: image_10/image_11, calib_cam_to_cam.txt (P_rect_02), flow_noc_10.png
    (ground truth), road.json."""
    need = ["image_10.png", "image_11.png", "calib_cam_to_cam.txt", "flow_noc_10.png", "road.json"]
    missing = [n for n in need if not (root / n).is_file()]
    if missing:
        raise JobError(f"--kitti15: {str(root)!r} lacks {missing}")
    specs, camera = user_pairs(images=root, calib=root / "calib_cam_to_cam.txt", cam=2, height=height,
                               roll_deg=0.0, pitch_deg=0.0, poses=None, flows=None,
                               road=str(root / "road.json"), gt=None,
                               image_list=[root / "image_10.png", root / "image_11.png"])
    from fsof_torch import read_flow

    spec = specs[0]
    inner, inner_id = spec.load, spec.identity

    def load() -> dict[str, Any]:
        d = inner()
        d["gt"] = read_flow(root / "flow_noc_10.png")
        return d

    def identity() -> dict[str, Any]:
        return {**inner_id(), "gt": file_digest(root / "flow_noc_10.png")}

    return [PairSpec("kitti15_000000", load, spec.flow_files, identity)], camera


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
