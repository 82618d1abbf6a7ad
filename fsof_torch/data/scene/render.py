"""Rendering: frames (images, labels, depth) cached per scene, pairs with all ground truth, and
the public :func:`render_pair`, :func:`render_sequence` and :func:`collate`."""

from __future__ import annotations

import math
import threading
from typing import Any

import torch
from torch import Tensor

from ..._check import autocast_off, check_bool, check_int, check_size
from .config import MAX_SIDE  # noqa: F401 (the jobs' size options take the renderer's bound from here)
from .config import MARKING, ROAD, SKY, SceneConfig, check_overrides, check_seed, check_sides, scene_config
from .ground_truth import ground_truth, road_motion
from .raycast import Hits, cast_rays, sample_grid
from .shading import sensor_noise, shade
from .world import Scene, on_host

__all__ = ["render_pair", "render_sequence", "collate"]


class _Renderer:
    """Frame cache for one scene: images and pixel-centre casts per frame index (``frames``: frames
    rendered earlier, e.g. the one :func:`render_sequence` kept)."""

    def __init__(self, scene: Scene, frames: dict[int, dict[str, Any]] | None = None) -> None:
        self.scene = scene
        self.H, self.W = scene.size
        self._frames: dict[int, dict[str, Any]] = dict(frames or {})

    def frame(self, k: int) -> dict[str, Any]:
        if k in self._frames:
            return self._frames[k]
        scene = self.scene
        ss = scene.cfg.supersample
        dtype = scene.dtype
        uc, vc = sample_grid((self.H, self.W), 1, dtype)
        centre = cast_rays(scene, k, uc, vc)
        centre_rgb, labels = shade(scene, centre, labels=True)
        if ss > 1 and not scene.cfg.adaptive:
            us, vs = sample_grid((self.H, self.W), ss, dtype)
            rgb = shade(scene, cast_rays(scene, k, us, vs))
            image = rgb.reshape(3, self.H, ss, self.W, ss).mean(dim=(2, 4))
        else:
            image = centre_rgb
            if ss > 1:
                image = self._supersample_edges(k, centre, image)
        if scene.cfg.noise > 0:
            # noise is given at base_size; another size is that image area-averaged:
            # the per-pixel noise scales with the square root of the pixel area, as the
            # band-limited textures do, so a small render is the same camera binned
            H0, W0 = scene.cfg.base_size
            sigma = scene.cfg.noise * math.sqrt(self.H * self.W / (H0 * W0))
            image = sensor_noise(image, sigma, scene.seed, k)
        depth = torch.where(centre.label == SKY, torch.zeros_like(centre.t), centre.t)
        inv_depth = torch.where(centre.label == SKY, torch.zeros_like(centre.t), 1.0 / centre.t)
        out = {"image": image, "centre": centre, "labels": labels, "depth": depth, "inv_depth": inv_depth}
        self._frames = {kk: vv for kk, vv in self._frames.items() if kk >= k - 1}
        self._frames[k] = out
        return out

    def _supersample_edges(self, k: int, centre: Hits, image: Tensor) -> Tensor:
        """Replace the colour of pixels at geometric edges (a different surface or object next to
        them) by the mean of ss × ss sub-pixel rays. Textures and markings are band-limited
        analytically, so elsewhere the pixel-centre sample is already anti-aliased."""
        ss = self.scene.cfg.supersample
        key = centre.label * 100003 + centre.obj
        edge = torch.zeros_like(key, dtype=torch.bool)
        dh = key[:, 1:] != key[:, :-1]
        dv = key[1:, :] != key[:-1, :]
        edge[:, 1:] |= dh
        edge[:, :-1] |= dh
        edge[1:, :] |= dv
        edge[:-1, :] |= dv
        ie, je = edge.nonzero(as_tuple=True)
        if ie.numel() == 0:
            return image
        dtype = self.scene.dtype
        offsets = (torch.arange(ss, dtype=torch.float64) + 0.5) / ss - 0.5
        ov, ou = torch.meshgrid(offsets, offsets, indexing="ij")
        u = (je.to(torch.float64).unsqueeze(1) + ou.reshape(1, -1)).reshape(-1).to(dtype)
        v = (ie.to(torch.float64).unsqueeze(1) + ov.reshape(1, -1)).reshape(-1).to(dtype)
        v, order = torch.sort(v, stable=True)
        rgb = torch.empty(3, v.numel(), dtype=dtype)
        rgb[:, order] = shade(self.scene, cast_rays(self.scene, k, u[order], v, grid=False))
        mean = rgb.reshape(3, -1, ss * ss).mean(dim=2)
        image = image.clone()
        image[:, ie, je] = mean
        return image

    def pair(self, k: int) -> dict[str, Any]:
        f0, f1 = self.frame(k), self.frame(k + 1)
        scene = self.scene
        centre = f0["centre"]
        gt = ground_truth(scene, k, centre, f1["inv_depth"])
        labels = f0["labels"]
        is_moving = torch.tensor([o.vs != 0.0 for o in centre.objects] + [False], dtype=torch.bool)
        moving = is_moving[torch.where(centre.obj >= 0, centre.obj, len(centre.objects))]
        mot = scene.motion
        cam0 = scene.world_to_camera(k)
        cam1 = scene.world_to_camera(k + 1)
        road_pose, plane = road_motion(scene, k)
        return {
            "image1": f0["image"],
            "image2": f1["image"].clone(),  # the next pair's image1 (or the kept frame's): no aliasing
            "flow": gt["flow"],
            "valid": gt["valid"],
            "flow_velocity": gt["flow_velocity"],
            "road": ((labels == ROAD) | (labels == MARKING)).unsqueeze(0),
            "labels": labels,
            "depth": f0["depth"].unsqueeze(0),
            "moving": moving.unsqueeze(0),
            "camera": scene.camera(),
            "odometry": {"x_d": mot.x_d, "z_d": mot.z_d, "yaw": mot.yaw},
            "velocity": {"speed": mot.speed, "steering": mot.steering, "wheelbase": mot.wheelbase,
                         "dt": mot.dt},
            "pose1": _camera_to_world(*cam0),
            "pose2": _camera_to_world(*cam1),
            "road_pose": road_pose,
            "plane": plane,
            "index": k,
        }


# The last frame of the last render_sequence call (render_pair is one): a caller that renders
# pair k, then pair k + 1 (SceneDataset, the refine job) renders the frame they share once (5
# frames for 4 pairs, not 8). Frames are deterministic, so the pixels do not depend on whether the
# frame came from here. A call takes the frame out under the lock (no two threads share one) and
# puts its own last frame back at its end. That frame's tensors were never handed to a caller (a
# pair's image2 is a copy), and the call that takes it hands them to its caller and keeps none, so
# no caller's tensor aliases a kept one; each call builds its own Scene, and each pair gets its own
# copy of the camera. Holds one frame (about 39 MB at 375x1242 in float32, 60 MB in float64) until a call on
# another scene replaces it.
_KEPT: dict[str, Any] = {}
_KEPT_LOCK = threading.Lock()


def _take_kept(key: tuple, index: int) -> dict[str, Any] | None:
    """The kept frame when it is frame ``index`` of the scene ``key`` (then no longer kept)."""
    with _KEPT_LOCK:
        if _KEPT.get("key") != (key, index):
            return None
        frame = _KEPT["frame"]
        _KEPT.clear()
        return frame


def _keep(key: tuple, index: int, frame: dict[str, Any]) -> None:
    with _KEPT_LOCK:
        _KEPT.clear()
        _KEPT.update(key=(key, index), frame=frame)


def _camera_to_world(A: list[list[float]], c: list[float]) -> Tensor:
    """KITTI-style camera-to-world pose (4, 4) float64 from p_cam = A (p_world - c)."""
    T = torch.eye(4, dtype=torch.float64)
    At = torch.tensor(A, dtype=torch.float64)
    T[:3, :3] = At.T
    T[:3, 3] = torch.tensor(c, dtype=torch.float64)
    return T


def _check_dtype(dtype: torch.dtype) -> None:
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")


#: frames beyond this are refused: a frame's poses and objects are built from frame 0 on (time and
#: memory grow with the index), and float32 geometry loses precision with the distance driven
MAX_FRAME = 100_000


def check_extent(num_pairs: int, start: int = 0, size: tuple[int, int] | None = None) -> None:
    """Frames ``start`` .. ``start + num_pairs`` within :data:`MAX_FRAME` and ``size``'s sides
    within :data:`MAX_SIDE` (ValueErrors naming ``num_pairs`` and ``size``); the ints already
    checked."""
    if start + num_pairs > MAX_FRAME:
        raise ValueError(f"num_pairs: expected start + num_pairs (the last frame) at most {MAX_FRAME}, got "
                         f"{start} + {num_pairs}")
    if size is not None:
        check_sides(size)


def render_pair(preset: str | SceneConfig = "default", index: int = 0, *, seed: int = 0,
                size: tuple[int, int] | None = None, dtype: torch.dtype = torch.float32,
                **overrides: Any) -> dict[str, Any]:
    """Render frames ``index`` and ``index + 1`` of a procedural sequence with all ground truth.

    Args:
        preset: a name of :data:`PRESETS` or a :class:`SceneConfig`.
        index: the pair's position in the sequence (frame t = index), below :data:`MAX_FRAME`
            (100 000; long sequences are rendered best in float64: float32 geometry loses
            precision with the distance driven).
        seed: scene seed (object layout, colours, textures), an int in [0, 2**62); same seed, same
            pixels.
        size: ``(H, W)`` of the images, each side at most 16 384; K is scaled from the KITTI-like
            375×1242 (default).
        dtype: float32 or float64 for every tensor (geometry is exact either way up to rounding;
            under ``torch.autocast`` the scene is rendered with autocast off).
        **overrides: fields of :class:`SceneConfig` (``speed_factor=4``, ``roll=math.radians(5)``,
            ``supersample=3``, ``x_d=, z_d=, yaw=`` …); any other name (``start``, ``num_pairs``,
            ``progress`` of :func:`render_sequence` as well) is a TypeError "render_pair: unknown
            overrides".

    Returns:
        dict with ``image1``, ``image2`` (3, H, W) RGB 0..255; ``flow`` (2, H, W) px, forward;
        ``valid`` (1, H, W) bool; ``flow_velocity`` (2, H, W) px/s; ``road`` (1, H, W) bool;
        ``labels`` (H, W) int64 (:data:`LABELS`); ``depth`` (1, H, W) m (camera z, 0 on the sky);
        ``moving`` (1, H, W) bool (pixels on moving cars);
        ``camera`` (:class:`Camera`, batch 1: the calibrated mounting, without body motion);
        ``odometry`` dict(x_d, z_d, yaw) floats (m, rad) of the planar ego motion; ``velocity``
        dict(speed m/s, steering rad, wheelbase m, dt s) floats; ``pose1``, ``pose2`` (4, 4)
        float64 camera-to-world poses (KITTI convention; world = the vehicle frame of frame 0 on a
        level road without body motion, in general the level frame x right, y down, z along the
        road's start, in which the road at s = 0 is y = h); ``road_pose`` dict(pitch, roll rad,
        height m) of the camera relative to the road's tangent plane under the vehicle at t;
        ``plane`` dict(pitch_change, yaw, roll_change rad, x_d, y_d, z_d m, pitch, roll, height)
        of the rigid motion t -> t+1 over that plane (:func:`.ground_truth.road_motion`, DESIGN.md
        §10); ``index`` int.
    """
    index = check_int(index, "index", minimum=0)  # checked here, so that the error names this function's argument
    if index >= MAX_FRAME:
        raise ValueError(f"index: expected at most {MAX_FRAME - 1}, got {index}")
    check_overrides(overrides)  # render_sequence's own keywords are not overrides either
    return render_sequence(preset, 1, seed=seed, size=size, dtype=dtype, start=index, **overrides)[0]


def render_sequence(preset: str | SceneConfig = "default", num_pairs: int = 1, *, seed: int = 0,
                    size: tuple[int, int] | None = None, dtype: torch.dtype = torch.float32,
                    progress: bool = False, start: int = 0, **overrides: Any) -> list[dict[str, Any]]:
    """Render ``num_pairs`` consecutive pairs (frames start..start+num_pairs) of one sequence.

    Consecutive pairs share frames (frame t+1 of pair i is frame t of pair i+1); each pair equals
    ``render_pair(preset, start + i, ...)``. So do consecutive calls: the last frame of a call is
    kept (one frame of one scene, about 39 MB at 375×1242 in float32, 60 MB in float64, for any
    thread) and is the first frame of a call on the same scene that starts there, so rendering pair 0, then pair 1, ... one call
    at a time renders each frame once (a frame kept under ``torch.inference_mode()`` serves only calls
    under it, and one kept outside only calls outside). No returned tensor is shared with another
    call's. Any grad mode renders the same pixels and ground truth.
    ``progress=True`` shows a tqdm bar (rate-limited where stderr is a log). The last frame,
    ``start + num_pairs``, is at most :data:`MAX_FRAME`. Other arguments as in :func:`render_pair`.
    """
    _check_dtype(dtype)
    num_pairs = check_int(num_pairs, "num_pairs", minimum=1)
    start = check_int(start, "start", minimum=0)
    progress = check_bool(progress, "progress")
    seed = check_seed(seed)
    if size is not None:
        size = check_size(size)
        overrides["size"] = size
    check_extent(num_pairs, start, size)
    cfg = scene_config(preset, **overrides)
    # a frame kept under torch.inference_mode() holds inference tensors, which a caller outside
    # it could neither write into nor use in autograd: kept frames serve calls in the same mode
    key = (cfg, seed, dtype, torch.is_inference_mode_enabled())
    kept = _take_kept(key, start)
    renderer = _Renderer(Scene(cfg, seed, dtype), None if kept is None else {start: kept})
    indices = range(start, start + num_pairs)
    if progress:
        from ...io.progress import progress_bar
        indices = progress_bar(indices, desc=f"render {preset if isinstance(preset, str) else 'scene'}", unit="pair")
    # (the ground truth's products in the render dtype, not autocast's; on the CPU, whatever the default device)
    pairs = []
    with autocast_off(torch.empty(0, device="cpu")), on_host():
        # a loop, not a list comprehension, whose frame an error's traceback (Ctrl-C's) holds, and the bar's
        # iterator with it: the bar ends its line, at the pairs done, before the traceback, not after it at exit
        for k in indices:
            pairs.append(renderer.pair(k))
        last = start + num_pairs
        _keep(key, last, renderer.frame(last))  # rendered by the last pair: no new work
    return pairs


def collate(pairs: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack rendered pairs into a batch: tensors get a leading B, cameras are concatenated,
    ``odometry`` / ``velocity`` floats become (B,) tensors (of the cameras' promoted dtype), ints a list.

    The rules of :func:`fsof_torch.datasets.collate`, so rendered pairs and pairs read from disk
    batch alike.
    """
    from ..items import collate as collate_items

    return collate_items(pairs, name="pairs")  # (its errors name this argument)
