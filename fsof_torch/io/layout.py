"""A KITTI-like folder layout for rendered synthetic sequences: writer and reader.

One folder per sequence of N frame pairs; pair ``i`` is named ``{i:06d}`` and its two frames
``{i:06d}_10`` (time t) and ``{i:06d}_11`` (time t+1), as in KITTI flow::

    ROOT/
        meta.json                  what wrote the folder: format, version, preset, seed, size, N,
                                   and this file list; written last (a folder without it is
                                   incomplete); the reader takes pairs 0 .. N - 1 only
        image_2/000000_10.png      frame t, 8-bit RGB (rendered 0..255 values rounded)
        image_2/000000_11.png      frame t+1
        flow_occ/000000_10.png     forward flow t -> t+1, KITTI 16-bit flow PNG (1/64 px); its
                                   valid channel is the renderer's mask (occluded points and
                                   points leaving the view are not valid)
        flow_velocity/000000_10.flo  instantaneous flow in px/s (velocity model), Middlebury .flo,
                                   float32, exact; NaN where not valid
        road/000000_10.png         road (freespace) mask of frame t, 8-bit, 255 = road
        semantic/000000_10.png     label map of frame t, 8-bit (16-bit if a label exceeds 255)
        depth/000000_10.png        depth of frame t, KITTI depth PNG: uint16 = metres · 256,
                                   0 = no depth (sky, or from 255.998 m)
        calib/000000.txt           ``P_rect_02: K | 0`` (KITTI raw calibration style), the true
                                   intrinsics of the pair
        params/000000.json         the true camera (K, height, roll, pitch, in metres/radians) and
                                   odometry (x_d, z_d, yaw) of the pair, its velocity (speed,
                                   steering, wheelbase, dt), camera-to-world poses pose1, pose2
                                   (4×4), the camera over the road at t (road_pose: pitch, roll,
                                   height) and the rigid plane motion t -> t+1 (plane:
                                   pitch_change, yaw, roll_change, x_d, y_d, z_d, pitch, roll,
                                   height) when rendered with them, preset, seed, size
        poses.txt                  N + 1 rows, KITTI odometry format (camera-to-world 3×4):
                                   row i is the camera of ``{i:06d}_10``, row i + 1 the camera of
                                   ``{i:06d}_11``, so ``ego_motion_from_pose(P[i], camera,
                                   pose1=P[i+1])`` gives back the pair's odometry. They are the
                                   renderer's ``pose1``/``pose2`` (world = the renderer's level
                                   world frame: x right, y down, z along the road at its start, the
                                   road at s = 0 is y = h; the vehicle frame of frame 0 only on a
                                   level road without body motion) when every pair has them and
                                   consecutive pairs share a frame; the chain of each pair's true
                                   relative motion (world = camera of the first frame) when no
                                   pair has them. meta.json's poses_world says which. Pairs with
                                   poses that do not chain (not consecutive frames) get no
                                   poses.txt: meta.json's poses_missing says why.

Optional parts of a pair (velocity flow, labels, depth, velocity, poses, road pose, plane
motion) are written when the pair has them, and read back when the files have them (folders
written before road_pose and plane existed read as before). Every file is written atomically.
"""

from __future__ import annotations

import contextlib
import json
import math
import numbers
import os
import re
import signal
import threading
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np
import torch
from torch import Tensor

from .._check import as_chw_flow, check_bool, check_has_values, check_int, tensor_from_array
from ..geometry.camera import Camera
from .atomic import atomic_path, write_json
from .flo import read_flo, write_flo
from .images import (check_image_suffix, check_no_broken_links, read_image, read_image_array, write_image,
                     write_image_array)
from .kitti import (check_kitti_flow_range, check_rigid_poses, flow_valid_pixels, read_kitti_flow, write_kitti_calibration,
                    write_kitti_flow, write_kitti_poses)
from .masks import read_label_map, read_road_mask, write_label_map, write_road_mask

__all__ = [
    "SYNTHETIC_FORMAT",
    "pair_name",
    "relative_pose_from_odometry",
    "write_synthetic_pair",
    "write_synthetic_sequence",
    "read_synthetic_pair",
    "read_synthetic_params",
    "synthetic_pair_indices",
    "camera_from_params",
    "write_depth_png",
    "read_depth_png",
]

SYNTHETIC_FORMAT = "fsof-torch synthetic KITTI-like layout"
_VERSION = 1
_DEPTH_SCALE = 256.0
# meta.json's poses_world when poses.txt holds the renderer's poses: the scene's world frame
# (fsof_torch.data.scene.world), true of every preset; it is the camera of frame 0 only on a level
# road without body motion
_RENDERED_WORLD = ("renderer's level world frame (x right, y down along gravity, z along the road at its start; "
                   "origin the camera height above the road under the vehicle at frame 0)")

# the keys write_synthetic_pair writes into a pair's params JSON, and write_synthetic_sequence into
# meta.json: `extra=` and `meta=` may not replace them
_PARAMS_KEYS = ("index", "name", "size", "camera", "odometry", "velocity", "road_pose", "plane", "pose1", "pose2")
_META_KEYS = ("format", "version", "num_pairs", "size", "poses_world", "poses_missing", "files", "layout")

FILES = {
    "image_2/{name}_10.png": "frame t, 8-bit RGB",
    "image_2/{name}_11.png": "frame t+1, 8-bit RGB",
    "flow_occ/{name}_10.png": "forward flow t->t+1, KITTI 16-bit flow PNG",
    "flow_velocity/{name}_10.flo": "instantaneous flow px/s, Middlebury .flo, NaN where not valid",
    "road/{name}_10.png": "road mask, 255 = road",
    "semantic/{name}_10.png": "label map",
    "depth/{name}_10.png": "depth, uint16 = metres * 256, 0 = none",
    "calib/{name}.txt": "P_rect_02: K | 0",
    "params/{name}.json": "true camera, odometry, velocity, poses, road pose, plane motion",
    "poses.txt": "N+1 camera-to-world poses (KITTI odometry format) of consecutive frames, when they chain",
}


def pair_name(index: int) -> str:
    """``000123`` for pair 123."""
    return f"{int(index):06d}"


def _float(x: Any) -> float:
    if isinstance(x, Tensor):
        if x.numel() != 1:
            raise ValueError(f"expected a single number, got a tensor of shape {tuple(x.shape)}")
        return float(x.detach().reshape(()).item())
    return float(x)


def _finite_entries(entries: Any, key: str, required: tuple[str, ...] = ()) -> dict[str, float]:
    """``pair[key]`` (a dict of numbers: the odometry, velocity, ...) as a dict of floats, each finite
    (else a ValueError naming ``pair[key][entry]``: JSON would hold a NaN as null, which
    :func:`read_synthetic_pair` refuses); where ``required`` is given, its entries only, each there."""
    if not isinstance(entries, Mapping):
        raise TypeError(f"pair[{key!r}]: expected a dict of numbers, got {type(entries).__name__}")
    missing = [k for k in required if k not in entries]
    if missing:
        raise ValueError(f"pair[{key!r}]: missing the entries {missing}; expected {list(required)}")
    out = {}
    for k in required or entries:
        v = entries[k]
        try:
            out[k] = _float(v)
        except (TypeError, ValueError):
            raise TypeError(f"pair[{key!r}][{k!r}]: expected a number, got {type(v).__name__} {v!r:.60}") from None
        if not math.isfinite(out[k]):
            raise ValueError(f"pair[{key!r}][{k!r}]: expected a finite number, got {out[k]!r} (the params JSON "
                             f"would hold null, which read_synthetic_pair refuses)")
    return out


def _camera_dict(camera: Camera) -> dict:
    if camera.batch_size != 1:
        raise ValueError(f"camera: expected a camera of batch 1 for one pair, got batch {camera.batch_size}")
    return {"K": camera.K[0].detach().cpu().double().tolist(), "height": _float(camera.height),
            "roll": _float(camera.roll), "pitch": _float(camera.pitch)}


def camera_from_params(params: Mapping, dtype: torch.dtype = torch.float64) -> Camera:
    """The Camera (batch 1) of a pair's ``params`` JSON (or its ``"camera"`` entry); ``dtype`` a
    floating-point torch dtype (else a TypeError naming it)."""
    _check_float_dtype(dtype)
    cam = params.get("camera", params)
    return Camera(torch.tensor(cam["K"], dtype=dtype, device="cpu"), float(cam["height"]), float(cam.get("roll", 0.0)),
                  float(cam.get("pitch", 0.0)))


def _check_float_dtype(dtype: object) -> None:
    """A TypeError naming ``dtype`` unless it is a floating-point torch dtype."""
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype: expected a floating-point torch dtype (torch.float32, torch.float64), got {dtype!r}")


def relative_pose_from_odometry(camera: Camera, x_d: float, z_d: float, yaw: float) -> Tensor:
    """``cam1_T_cam0`` (4, 4) float64 of the displacement model's motion for a mounted camera.

    Vehicle frame: ``p_v1 = R_φ (p_v0 - d)``; camera frame ``p_c = R_c p_v``, hence
    ``cam1_T_cam0 = [[R_c R_φ R_cᵀ, -R_c R_φ d], [0, 1]]`` (the inverse of what
    :func:`fsof_torch.egomotion.ego_motion_from_pose` projects).
    """
    check_has_values(camera.K, "camera")
    Rc = camera.to(device="cpu", dtype=torch.float64).mounting()[0].detach()
    c, s = math.cos(yaw), math.sin(yaw)
    R_phi = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]], dtype=torch.float64, device="cpu")
    d = torch.tensor([x_d, 0.0, z_d], dtype=torch.float64, device="cpu")
    T = torch.eye(4, dtype=torch.float64, device="cpu")
    T[:3, :3] = Rc @ R_phi @ Rc.T
    T[:3, 3] = -(Rc @ R_phi @ d)
    return T


def write_depth_png(path: str | os.PathLike, depth: Tensor | np.ndarray) -> Path:
    """Write (1, H, W) or (H, W) float depth in metres (a tensor or a NumPy array) as a KITTI depth
    PNG (uint16 = m · 256, rounded; 0 = none).

    Depth that is not finite, not positive, at most 1/512 m (it rounds to 0) or at least
    65535.5/256 = 255.998 m (it rounds beyond the largest code, 65535 = 255.996 m) is written as
    none (sky). ``path`` must end in .png (another suffix: a ValueError naming it)."""
    path = check_image_suffix(path, (".png",), "depth map")
    if isinstance(depth, np.ndarray):
        depth = tensor_from_array(depth)
    if not isinstance(depth, Tensor) or not depth.is_floating_point():
        got = f"dtype {depth.dtype}" if isinstance(depth, Tensor) else type(depth).__name__
        raise TypeError(f"depth: expected a float tensor or array of shape (1, H, W), got {got}")
    if depth.dim() not in (2, 3) or (depth.dim() == 3 and depth.shape[0] != 1) or min(depth.shape[-2:]) < 1:
        raise ValueError(f"depth: expected shape (1, H, W) or (H, W), got {tuple(depth.shape)}")
    check_has_values(depth, "depth")
    d = depth.detach().cpu().double().reshape(depth.shape[-2:])
    coded = torch.where(torch.isfinite(d) & (d > 0), (d * _DEPTH_SCALE).round(), torch.zeros_like(d))
    coded = torch.where(coded > 65535, torch.zeros_like(coded), coded)
    return write_image_array(path, coded.to(torch.int32).numpy().astype(np.uint16))


def read_depth_png(path: str | os.PathLike) -> tuple[Tensor, Tensor]:
    """A KITTI depth PNG → ``(depth (1, H, W) float32 metres, valid (1, H, W) bool)``; 0 where not valid."""
    array = read_image_array(path, what="depth PNG (16-bit, 1 channel)")
    if array.dtype != np.uint16 or array.ndim != 2:
        raise ValueError(f"path: {str(path)!r} is {array.dtype} with shape {array.shape}; a depth PNG is 16-bit, 1 channel")
    valid = array > 0
    return torch.from_numpy(array.astype(np.float32) / _DEPTH_SCALE).unsqueeze(0), torch.from_numpy(valid).unsqueeze(0)


def write_synthetic_pair(root: str | os.PathLike, index: int, pair: Mapping[str, Any], *,
                         extra: Mapping[str, Any] | None = None) -> dict[str, Path]:
    """Write one rendered pair (the dict of :func:`fsof_torch.scene.render_pair`) into ``root``.

    Required keys: ``image1``, ``image2`` (3, H, W) 0..255, ``flow`` (2, H, W), ``valid``
    (1, H, W) bool, ``camera`` (batch 1), ``odometry`` (x_d, z_d, yaw). Optional: ``road``,
    ``labels``, ``depth``, ``flow_velocity``, ``velocity``, ``pose1``, ``pose2``, ``road_pose``,
    ``plane``. ``extra`` goes into the params JSON (preset, seed, ...). Returns the written paths
    by kind.

    Checked before anything is written, as :func:`read_synthetic_pair` and
    :func:`synthetic_pair_indices` require: ``index`` is an int >= 0 (TypeError, ValueError naming
    it); every image, flow, mask, label and depth tensor has the size (H, W) of ``image1``;
    the flow at the valid pixels lies within the KITTI flow PNG's [-512, 511.98] px;
    ``flow_velocity`` is finite (within float32) at the valid pixels, where it is stored (NaN
    elsewhere: a NaN there would read back as 0 at a valid pixel); ``pose1`` and ``pose2`` are
    rigid poses; ``odometry`` holds ``x_d``, ``z_d``, ``yaw`` and it, ``velocity``, ``road_pose``
    and ``plane`` hold finite numbers (a NaN would be written as JSON null, which the reader
    refuses); ``extra`` holds none of the params' own keys (each a ValueError or TypeError naming
    the argument and the entry). The files are written all or none: one that fails (a road mask
    that is not bool, a 0..1 image) leaves no file of the pair, and a pair written over keeps its
    old files, rather than a mix of old and new. A Ctrl-C while the files are put in place is
    held until the pair is whole (then raised); a rename that fails there leaves no file of the pair.
    """
    root = Path(root)
    if isinstance(index, bool) or not isinstance(index, numbers.Integral):
        raise TypeError(f"index: expected an int >= 0, got {type(index).__name__} {index!r:.60}")
    if index < 0:
        raise ValueError(f"index: expected an int >= 0 (the pair's file names), got {index}")
    missing = [k for k in ("image1", "image2", "flow", "valid", "camera", "odometry") if k not in pair]
    if missing:
        raise ValueError(f"pair: missing keys {missing}; expected the dict of fsof_torch.scene.render_pair")
    size = tuple(getattr(pair["image1"], "shape", ())[-2:])
    for key in ("image2", "flow", "valid", "flow_velocity", "road", "labels", "depth"):
        shape = tuple(getattr(pair.get(key), "shape", ()))
        if len(size) == 2 and len(shape) >= 2 and shape[-2:] != size:
            raise ValueError(f"pair[{key!r}]: expected the size {size[0]}x{size[1]} of pair['image1'], "
                             f"got shape {shape}")
    clash = sorted(set(extra or {}) & set(_PARAMS_KEYS))
    if clash:
        raise ValueError(f"extra: {clash} are keys the params JSON holds itself; give other names")
    # the flow PNG's range, before the images are written: a pair half written is no pair
    flow = as_chw_flow(pair["flow"], "pair['flow']").detach().cpu().double()
    held = flow_valid_pixels(flow, pair["valid"])  # (H, W) bool
    check_kitti_flow_range(flow, held, "pair['flow']")
    velocity = None
    if pair.get("flow_velocity") is not None:  # NaN off the valid pixels; read back as 0 there
        given = as_chw_flow(pair["flow_velocity"], "pair['flow_velocity']").detach().cpu()
        velocity = torch.where(held, given.float(), torch.tensor(float("nan"), device="cpu"))
        if not bool(torch.isfinite(velocity[:, held]).all()):  # (a NaN would read back as 0 at a valid pixel)
            raise ValueError("pair['flow_velocity']: expected finite values within float32's range at the valid "
                             "pixels (pair['valid']), got NaN, inf or a value beyond 3.4e38")
    poses = {}
    for key in ("pose1", "pose2"):  # checked before any file is written, as the reader checks them
        if pair.get(key) is not None:
            pose = torch.as_tensor(pair[key], device="cpu").detach().to(torch.float64)
            if pose.numel() != 16:
                raise ValueError(f"pair[{key!r}]: expected a 4×4 pose, got shape {tuple(pose.shape)}")
            check_rigid_poses(pose.reshape(1, 4, 4), lambda _: f"pair[{key!r}]")
            poses[key] = pose.reshape(4, 4).tolist()
    name = pair_name(index)
    camera: Camera = pair["camera"]
    params = {  # keys: _PARAMS_KEYS
        "index": int(index),
        "name": name,
        "size": list(pair["flow"].shape[-2:]),
        "camera": _camera_dict(camera),
        "odometry": _finite_entries(pair["odometry"], "odometry", ("x_d", "z_d", "yaw")),
    }
    for key in ("velocity", "road_pose", "plane"):
        if pair.get(key) is not None:
            params[key] = _finite_entries(pair[key], key)
    params.update(poses)
    if extra:
        params.update(dict(extra))
    # (kind, folder, file, writer of a path): written all or none (_write_all), params last
    jobs: list[tuple[str, str, str, Callable[[Path], Path]]] = [
        ("image1", "image_2", f"{name}_10.png", lambda p: write_image(p, pair["image1"])),
        ("image2", "image_2", f"{name}_11.png", lambda p: write_image(p, pair["image2"])),
        ("flow", "flow_occ", f"{name}_10.png", lambda p: write_kitti_flow(p, pair["flow"], pair["valid"])),
    ]
    if velocity is not None:
        jobs.append(("flow_velocity", "flow_velocity", f"{name}_10.flo", lambda p: write_flo(p, velocity)))
    if pair.get("road") is not None:
        jobs.append(("road", "road", f"{name}_10.png", lambda p: write_road_mask(p, pair["road"])))
    if pair.get("labels") is not None:
        jobs.append(("labels", "semantic", f"{name}_10.png", lambda p: write_label_map(p, pair["labels"])))
    if pair.get("depth") is not None:
        jobs.append(("depth", "depth", f"{name}_10.png", lambda p: write_depth_png(p, pair["depth"])))
    jobs.append(("calib", "calib", f"{name}.txt",
                 lambda p: write_kitti_calibration(p, camera.K[0].detach().cpu().double())))
    jobs.append(("params", "params", f"{name}.json", lambda p: write_json(p, params)))
    return _write_all(root, jobs)


def _write_all(root: Path, jobs: list[tuple[str, str, str, Callable[[Path], Path]]]) -> dict[str, Path]:
    """Write the files of ``jobs`` ((kind, folder, file, writer of a path)) under ``root``, all or
    none: each writer writes a temporary beside its target (:func:`atomic_path`), and only once
    every one has been written are they renamed onto their targets, in order. A writer that
    raises (a road mask that is not bool, a 0..1 image) leaves no file of the pair, and a pair
    written over keeps its old files rather than a mix of old and new; the folders this call
    created are removed again. SIGINT is held while the files are renamed (:func:`_interrupt_deferred`),
    and a rename or fsync that fails there removes every target: no pair rather than a mix.
    Returns the targets by kind."""
    targets = [root / folder / file for _, folder, file, _ in jobs]
    created = sorted({p for t in targets for p in (t.parent, *t.parent.parents) if not p.exists()},
                     key=lambda p: len(p.parts), reverse=True)
    placing = False
    try:
        for folder in reversed(created):
            folder.mkdir(exist_ok=True)
        with contextlib.ExitStack() as stack:
            # entered last to first, so that they leave (rename) first to last: params/ last
            temporaries = [stack.enter_context(atomic_path(t)) for t in reversed(targets)][::-1]
            for (*_, write), tmp in zip(jobs, temporaries):
                write(tmp)
            renames = stack.pop_all()
        # every file is written: put them in place with Ctrl-C held until all are, so that an
        # interrupt leaves the whole pair, never some new files beside the old params/ file
        placing = True
        with _interrupt_deferred():  # (delivered on leaving it, once the pair is whole)
            with renames:
                pass
            placing = False
    except BaseException:
        if placing:  # (a rename or fsync that failed): no pair at all rather than a mix
            for target in targets:
                with contextlib.suppress(OSError):
                    target.unlink()
        for folder in created:
            with contextlib.suppress(OSError):  # (only where empty)
                folder.rmdir()
        raise
    return {kind: target for (kind, *_), target in zip(jobs, targets)}


@contextlib.contextmanager
def _interrupt_deferred():
    """Hold SIGINT (Ctrl-C) while the body runs and deliver it after (main thread only: elsewhere
    the signal reaches the main thread, not this one)."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous is None:
        yield
        return
    caught: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            signal.raise_signal(signal.SIGINT)


def write_synthetic_sequence(root: str | os.PathLike, pairs: Iterable[Mapping[str, Any]], *,
                             meta: Mapping[str, Any] | None = None, progress: bool = False,
                             total: int | None = None) -> dict[str, Any]:
    """Write rendered pairs 0, 1, ... into ``root`` (created), then ``poses.txt`` and ``meta.json``.

    ``pairs`` may be a generator (rendering lazily, so that the progress bar, on stderr when
    ``progress``, counts rendering too). ``root`` must be new or empty (ValueError otherwise,
    before any pair is rendered, as ``python -m eval synth`` does): files of an earlier run there
    (a road mask, depth, ``meta.json``) would be read back as part of this one. ``meta`` adds
    entries to ``meta.json`` (``preset`` and ``seed`` also go into every params JSON); a key of
    the layout's own (``format``, ``version``, ``num_pairs``, ``size``, ``poses_world``,
    ``poses_missing``, ``files``, ``layout``) is a ValueError naming ``meta``, raised first.

    ``poses.txt`` holds the renderer's ``pose1``/``pose2`` where every pair has them and each
    pair's ``pose1`` is the previous pair's ``pose2`` (consecutive frames); the chain of the
    pairs' relative motions (world = camera of the first frame) where no pair has poses (the
    pairs are taken as consecutive frames). Where some pairs have poses and the chain breaks
    (pairs that are not consecutive frames, or a pair without poses), no ``poses.txt`` is
    written and ``meta.json``'s ``poses_missing`` says why (``poses_world`` is null).

    Returns a summary: ``root``, ``num_pairs``, ``size``, ``files`` (count per folder), ``bytes``.
    """
    from .progress import progress_bar

    root = Path(root)
    clash = sorted(set(meta or {}) & set(_META_KEYS))
    if clash:
        raise ValueError(f"meta: {clash} are entries meta.json holds itself; give other names")
    if root.is_dir() and any(root.iterdir()):
        held = sorted(p.name for p in root.iterdir())
        listed = ", ".join(held[:4]) + (", ..." if len(held) > 4 else "")
        raise ValueError(f"root: {str(root)!r} already holds files ({listed}); give a new or empty folder")
    root.mkdir(parents=True, exist_ok=True)
    extra = dict(meta or {})
    chained = [torch.eye(4, dtype=torch.float64, device="cpu")]
    rendered: list[tuple[Tensor, Tensor] | None] = []
    size = None
    count = 0
    iterator = progress_bar(pairs, enabled=progress, total=total, desc=f"synth {root.name}", unit="pair")
    for index, pair in enumerate(iterator):
        write_synthetic_pair(root, index, pair, extra={k: v for k, v in extra.items() if k in ("preset", "seed")})
        odo = pair["odometry"]
        T = relative_pose_from_odometry(pair["camera"], _float(odo["x_d"]), _float(odo["z_d"]), _float(odo["yaw"]))
        chained.append(chained[-1] @ torch.linalg.inv(T))
        has_poses = pair.get("pose1") is not None and pair.get("pose2") is not None
        rendered.append(tuple(pair[k].detach().cpu().double().reshape(4, 4) for k in ("pose1", "pose2"))
                        if has_poses else None)
        size = list(pair["flow"].shape[-2:])
        count += 1
    if count == 0:
        raise ValueError("pairs: got no pairs to write")
    poses, note = _sequence_poses(rendered, chained)
    if poses is not None:
        write_kitti_poses(root / "poses.txt", poses)
        extra["poses_world"] = note
    else:
        extra["poses_world"], extra["poses_missing"] = None, note
    files = {folder: len(list((root / folder).glob("*"))) for folder in
             ("image_2", "flow_occ", "flow_velocity", "road", "semantic", "depth", "calib", "params")
             if (root / folder).is_dir()}
    summary = {"format": SYNTHETIC_FORMAT, "version": _VERSION, "num_pairs": count, "size": size,
               **extra, "files": files, "layout": FILES}
    write_json(root / "meta.json", summary)
    total_bytes = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    return {"root": str(root), "num_pairs": count, "size": size, "files": files, "bytes": total_bytes}


def _sequence_poses(rendered: list[tuple[Tensor, Tensor] | None],
                    chained: list[Tensor]) -> tuple[Tensor | None, str]:
    """The (N + 1, 4, 4) poses of ``poses.txt`` and their world frame, or None and why there are
    none: the renderer's poses where they chain, the chained relative motions where no pair has
    poses (nothing to check the pairs' order against)."""
    if all(p is None for p in rendered):
        return torch.stack(chained), "camera of the first frame"
    for i, p in enumerate(rendered):
        if p is None:
            return None, f"pair {i} has no pose1/pose2 while others have: the chain of cameras is not known"
        # row i is the camera of pair i's first frame: only consecutive frames chain
        if i and not torch.allclose(rendered[i - 1][1], p[0], atol=1e-9, rtol=0):
            return None, (f"pair {i}'s pose1 is not pair {i - 1}'s pose2: the pairs are not consecutive "
                          f"frames, so no row can be the camera of both")
    return torch.stack([rendered[0][0]] + [p[1] for p in rendered]), _RENDERED_WORLD


def synthetic_pair_indices(root: str | os.PathLike) -> list[int]:
    """Indices of the pairs in a synthetic layout folder (from ``params/*.json``), sorted.

    A file counts where its name is the one :func:`pair_name` gives (``000001.json``; not
    ``1.json`` nor ``0000001.json``, which the readers would not open: each pair counts once).
    Where ``meta.json`` exists, only the pairs ``0 .. num_pairs - 1`` it lists count: files of
    pairs beyond them (left by an older, longer run) are not pairs of this sequence, and a pair
    among them without its params file is a FileNotFoundError naming ``root`` and the file (never
    a pair left out, which would shift the later pairs' indices). A folder named ``meta.json`` is
    an IsADirectoryError.
    """
    root = Path(root)
    if not (root / "params").is_dir():
        raise FileNotFoundError(f"root: {str(root)!r} has no params/ folder (not a synthetic layout written by "
                                f"write_synthetic_sequence / python -m eval synth)")
    indices = sorted(int(p.stem) for p in (root / "params").glob("*.json")
                     if re.fullmatch("[0-9]+", p.stem) and p.stem == pair_name(int(p.stem)))
    meta = root / "meta.json"
    if meta.is_dir():
        raise IsADirectoryError(f"path: {str(meta)!r} is a folder; expected the layout's meta.json file")
    if meta.is_file():
        count = _read_json_file(meta).get("num_pairs")
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise ValueError(f"path: {str(meta)!r} has no 'num_pairs' entry holding a whole number >= 0, got {count!r}")
        indices = [i for i in indices if i < count]
        missing = sorted(set(range(count)) - set(indices))
        if missing:  # (a pair left out would shift every later pair's index)
            shown = ", ".join(f"{pair_name(i)}.json" for i in missing[:4]) + (", ..." if len(missing) > 4 else "")
            raise FileNotFoundError(f"root: {str(root)!r} has meta.json for {count} pairs but params/ lacks "
                                    f"{len(missing)} of them ({shown}); copy the folder again")
    return indices


def _complete_parts(root: Path, index: int) -> set[str]:
    """The folders that ``meta.json`` lists with a file for each of its ``num_pairs`` pairs (none
    without meta.json, which :func:`synthetic_pair_indices` checks, nor for a pair ``index``
    beyond them)."""
    meta = root / "meta.json"
    if not meta.is_file():
        return set()
    obj = _read_json_file(meta)
    count, files = obj.get("num_pairs"), obj.get("files")
    if isinstance(count, bool) or not isinstance(count, int) or not isinstance(files, dict) or index >= count:
        return set()
    return {folder for folder, n in files.items()
            if isinstance(n, int) and not isinstance(n, bool) and n >= count > 0}


def _read_json_file(path: Path) -> dict:
    """A JSON object from a UTF-8 file, or ValueError naming the path."""
    try:
        obj = json.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as err:
        raise ValueError(f"path: {str(path)!r} is not a text (UTF-8) JSON file (undecodable byte at offset "
                         f"{err.start})") from None
    except (ValueError, RecursionError) as err:  # JSONDecodeError, or an integer of over 4300 digits
        raise ValueError(f"path: {str(path)!r} is not valid JSON: {err}") from None
    if not isinstance(obj, dict):
        raise ValueError(f"path: {str(path)!r} holds a JSON {type(obj).__name__}; expected an object")
    return obj


def _number(params: dict, path: Path, *keys: str) -> float:
    """The finite number at ``params[keys[0]][keys[1]]...``, or ValueError naming the path and the entry."""
    value: Any = params
    for depth, key in enumerate(keys):
        if not isinstance(value, dict) or key not in value:
            entry = "".join(f"[{k!r}]" for k in keys[:depth + 1])
            raise ValueError(f"path: {str(path)!r} has no entry {entry}")
        value = value[key]
    entry = "".join(f"[{k!r}]" for k in keys)
    if not _is_finite_number(value):
        raise ValueError(f"path: {str(path)!r}{entry} is not a finite number: {value!r:.60}")
    return float(value)


def _is_finite_number(value: Any) -> bool:
    """A JSON number that is a finite float64 (not a bool; not an integer beyond float64's range,
    which JSON allows)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def read_synthetic_params(root: str | os.PathLike, index: int) -> dict:
    """The params JSON of pair ``index``.

    Raises ValueError naming the path for a file that is not UTF-8 JSON, or that lacks an entry
    every pair has (``camera``: ``K`` 3×3 and ``height``; ``odometry``: ``x_d``, ``z_d``, ``yaw``),
    or holds there (or in ``camera``'s ``roll``, ``pitch``) something other than finite numbers
    (an integer beyond float64's range included); FileNotFoundError for a missing file,
    IsADirectoryError for a folder in its place. ``index`` must be an int >= 0 (a TypeError or
    ValueError naming it: 1.7 is no pair, rather than pair 1).
    """
    index = check_int(index, "index", minimum=0)
    path = Path(root) / "params" / f"{pair_name(index)}.json"
    if path.is_dir():
        raise IsADirectoryError(f"path: {str(path)!r} is a folder; expected the params JSON of pair {index}")
    check_no_broken_links([path], "path")  # (a drive not mounted, not a pair without params)
    if not path.is_file():
        raise FileNotFoundError(f"index: no params file {str(path)!r}")
    params = _read_json_file(path)
    _number(params, path, "camera", "height")
    K = params["camera"].get("K")
    rows = isinstance(K, list) and len(K) == 3 and all(isinstance(r, list) and len(r) == 3 for r in K)
    if not rows or not all(_is_finite_number(v) for r in K for v in r):
        raise ValueError(f"path: {str(path)!r}['camera']['K'] is not a 3×3 list of finite numbers: {K!r:.200}")
    for key in ("roll", "pitch"):  # optional: folders of older versions may lack them
        if key in params["camera"]:
            _number(params, path, "camera", key)
    for key in ("x_d", "z_d", "yaw"):
        _number(params, path, "odometry", key)
    return params


def read_synthetic_pair(root: str | os.PathLike, index: int, *, dtype: torch.dtype = torch.float32,
                        ground_truth: bool = True) -> dict[str, Any]:
    """Read pair ``index`` of a synthetic layout folder as the dict :func:`fsof_torch.scene.render_pair`
    gives (keys where present on disk): ``image1``, ``image2`` (3, H, W) ``dtype`` 0..255,
    ``flow`` (2, H, W) px, ``valid`` (1, H, W) bool, ``flow_velocity`` (2, H, W) px/s (0 off the
    valid pixels, where the file holds NaN; render_pair's values there, which are not ground truth,
    are not written), ``road``
    (1, H, W) bool, ``labels`` (H, W) int64, ``depth`` (1, H, W) m, ``camera`` (Camera, batch 1,
    ``dtype``), ``odometry``, ``velocity``, ``road_pose`` and ``plane`` (dicts of floats), ``pose1``,
    ``pose2`` (4, 4) float64, plus ``index`` and ``name``.
    ``ground_truth=False`` reads only the images and the camera. A params entry that is not
    finite numbers, or a ``pose1``/``pose2`` that is not a rigid pose (checked as
    :func:`~fsof_torch.io.kitti.read_kitti_poses` checks a file's), is a ValueError naming the
    path and the entry. An optional part (``flow_velocity/``, ``road/``, ``semantic/``,
    ``depth/``) the pair lacks although ``meta.json`` says every pair was written with it is a
    FileNotFoundError naming ``root`` and the file (a lost file, never a pair without that part).
    ``index`` (an int >= 0), ``dtype`` (a floating-point torch dtype) and ``ground_truth`` (a
    bool: a truthy string such as ``"no"`` is not False) are checked first, a TypeError or
    ValueError naming the argument.
    """
    index = check_int(index, "index", minimum=0)
    _check_float_dtype(dtype)
    ground_truth = check_bool(ground_truth, "ground_truth")
    root = Path(root)
    name = pair_name(index)
    params = read_synthetic_params(root, index)
    params_path = root / "params" / f"{name}.json"
    path = root / "image_2" / f"{name}_10.png"
    image1 = read_image(path)
    size = tuple(image1.shape[-2:])

    def same_size(tensor: Tensor, path: Path) -> Tensor:
        if tuple(tensor.shape[-2:]) != size:
            raise ValueError(f"path: {str(path)!r} is {tensor.shape[-2]}x{tensor.shape[-1]}; the pair's frame "
                             f"image_2/{name}_10.png is {size[0]}x{size[1]}")
        return tensor

    path = root / "image_2" / f"{name}_11.png"
    try:
        camera = camera_from_params(params, dtype)
    except (ValueError, TypeError) as err:
        raise ValueError(f"path: {str(params_path)!r} holds a camera that is not valid: {err}") from None
    sample: dict[str, Any] = {
        "image1": image1.to(dtype),
        "image2": same_size(read_image(path), path).to(dtype),
        "camera": camera,
        "index": int(index),
        "name": name,
    }
    if not ground_truth:
        return sample
    path = root / "flow_occ" / f"{name}_10.png"
    flow, valid = read_kitti_flow(path)
    sample["flow"], sample["valid"] = same_size(flow, path).to(dtype), valid
    complete = _complete_parts(root, int(index))

    def part(folder: str, file: str) -> Path | None:
        """The pair's file of an optional part, or None where the pair has none; an error where
        meta.json says every pair was written with that part (a file lost since, which would
        make a pair without ground truth it has)."""
        path = root / folder / file
        if path.exists() or path.is_symlink():  # (a folder or a broken link there: the reader's error)
            return path
        if folder in complete:
            raise FileNotFoundError(f"root: {str(root)!r} has no {folder}/{file} for the pair {name}, but its "
                                    f"meta.json says every pair was written with one; copy the folder again")
        return None

    path = part("flow_velocity", f"{name}_10.flo")
    if path is not None:
        fv = same_size(read_flo(path), path)
        sample["flow_velocity"] = torch.nan_to_num(fv, nan=0.0).to(dtype)
    path = part("road", f"{name}_10.png")
    if path is not None:
        sample["road"] = same_size(read_road_mask(path), path)
    path = part("semantic", f"{name}_10.png")
    if path is not None:
        sample["labels"] = same_size(read_label_map(path), path)
    path = part("depth", f"{name}_10.png")
    if path is not None:
        sample["depth"] = same_size(read_depth_png(path)[0], path).to(dtype)
    sample["odometry"] = {k: float(params["odometry"][k]) for k in ("x_d", "z_d", "yaw")}
    for key in ("velocity", "road_pose", "plane"):
        if key in params:
            if not isinstance(params[key], dict):
                raise ValueError(f"path: {str(params_path)!r}[{key!r}] is not an object of numbers")
            sample[key] = {k: _number(params, params_path, key, k) for k in params[key]}
    for key in ("pose1", "pose2"):
        if key in params:
            try:
                sample[key] = torch.tensor(params[key], dtype=torch.float64, device="cpu").reshape(4, 4)
            except (ValueError, TypeError, RuntimeError, OverflowError):
                raise ValueError(f"path: {str(params_path)!r}[{key!r}] is not a 4×4 list of numbers") from None
            check_rigid_poses(sample[key].unsqueeze(0), lambda _: f"path: {str(params_path)!r}[{key!r}]")
    return sample
