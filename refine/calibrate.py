"""The road motion of a clip from its images (:func:`fsof_torch.fit_sequence`): the camera's
mounting calibrated over the clip (its pitch and roll over the road; with poses, the height), each
pair's motion for the ``sequence`` variant.

The pairs must be consecutive frames of one clip (pair k's second image is pair k+1's first, and
where every frame is named by a number, or one text around a number, the numbers follow each
other: :func:`check_clip`); the road masks are the pairs' own, or detected on a DIS flow where the
road is ``auto``. Poses, where the pairs have them, give the metric scale (the images give the
translation over the height only). The clip is streamed: its memory is a few frames plus the
packed road masks, whatever its length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from fsof_torch import Camera, fit_sequence
from fsof_torch.io.images import frame_counts

from .inputs import JobError, PairSpec, options_of

STILL_M = 1e-6  # a pose step below this (metres) is no motion: the poses give the clip no scale


def clip_options(calibrate: bool, variants: Sequence[str]) -> str:
    """The options that make the job fit the clip, as its errors name them (e.g.
    ``--calibrate-pitch and --odometry sequence``); "" where none does."""
    needed = ["--calibrate-pitch"] if calibrate else []
    uses = [v for v in variants if v in ("sequence", "given_pitch")]
    if uses:
        needed.append(f"--odometry {','.join(uses)}")
    return " and ".join(needed)


def _separately(needed_by: str) -> str:
    return f"without {needed_by} the pairs are refined one by one (e.g. --odometry photometric)"


def check_clip(specs: Sequence[PairSpec], *, needed_by: str = "--odometry sequence",
               poses_option: str = "--poses") -> None:
    """What the clip's fit needs that is known without loading a pair, checked before any work:
    at least 2 pairs; where every frame is named by a number (or one text around a number,
    ``frame_9``, ``frame_10``; not a timestamp: :func:`fsof_torch.io.images.frame_counts`), no gap in the numbers
    (the fit carries each pair's motion to the next as a prior, so a dropped frame would be fitted
    as one step); where the pairs have poses, poses that move (they give the clip's scale). Errors name
    ``needed_by`` (the options that need the clip) or ``poses_option`` (where the poses come from)."""
    if len(specs) < 2:
        raise JobError(f"{needed_by}: the clip's fit needs a clip of at least 2 pairs (3 frames), got {len(specs)}")
    frames = [s.frames for s in specs]
    numbers = frame_counts(n for f in frames for n in f) if all(f is not None for f in frames) else None
    if numbers is not None:  # (frames named by a number: 000001, or one text around it: frame_1)
        for spec, (a, b), (i, j) in zip(specs, frames, zip(numbers[::2], numbers[1::2])):
            if j != i + 1:
                raise JobError(f"{needed_by}: pair {spec.name} goes from frame {a} to frame {b}, not to the next "
                               f"frame (a gap in the frame numbers, or frames out of order): the clip's fit needs "
                               f"every frame of one clip; {_separately(needed_by)}")
    if all(s.poses is not None for s in specs):
        steps = torch.stack([(s.poses[1, :3, 3] - s.poses[0, :3, 3]).norm() for s in specs])
        if not bool((steps > STILL_M).any()):
            raise JobError(f"{poses_option}: the poses do not move (no pair's step exceeds {STILL_M:g} m), so they "
                           f"give the clip's fit ({needed_by}) no scale: give poses that move with the camera")


@dataclass
class ClipFit:
    """The clip's road motion: ``motion[name]`` a ``"plane"`` motion dict per pair (floats),
    ``camera`` the calibrated camera, ``mounting`` {"roll_deg", "pitch_deg", "height_m" with
    poses}, ``success[name]`` whether the pair's fit succeeded (the fit redone with the calibrated
    mounting; the first, with the nominal one, where nothing is calibrated), ``fitted`` how many pairs' first fits
    the mounting was calibrated from (those that succeeded, move and show the attitude:
    :attr:`fsof_torch.SequenceFit.calibrated_from`); and the road masks the fit used (packed), with
    what ``road_for`` reported about each (:meth:`road`). Where there are none (``fitted`` 0) nothing
    is calibrated: ``camera`` and ``mounting`` are the nominal ones, and ``motion`` the one fitted
    with that camera (translations at its height, also with poses)."""

    motion: dict[str, dict[str, Any]]
    camera: Camera
    mounting: dict[str, float]
    success: dict[str, bool]
    masks: PackedMasks
    road_info: dict[str, tuple[int, dict[str, Any]]]
    fitted: int

    def road(self, name: str) -> tuple[Tensor, dict[str, Any]]:
        """Pair ``name``'s road mask (1, H, W) bool, as the clip's fit used it, and what was
        recorded about it (with ``--road auto``: the detection's flag, reason and coverage)."""
        k, info = self.road_info[name]
        return self.masks[k], info


class ClipFrames:
    """The clip's N + 1 frames, loaded from its N pairs on demand: frame k < N is pair k's first
    image, frame N the last pair's second. The last pair loaded is kept (and only its two
    images), so reading the frames in order, as :func:`fsof_torch.fit_sequence` does, loads each
    pair once."""

    def __init__(self, specs: Sequence[PairSpec]):
        self.specs = specs
        self._index: int | None = None
        self._images: tuple[Tensor, Tensor] | None = None

    def __len__(self) -> int:
        return len(self.specs) + 1

    def __getitem__(self, j: int) -> Tensor:
        if not 0 <= j <= len(self.specs):
            raise IndexError(f"frame {j} of a clip of {len(self)} frames")
        k = min(j, len(self.specs) - 1)
        if self._index != k:
            self._index, self._images = None, None  # freed before the next pair loads
            pair = self.specs[k].load()
            self._index, self._images = k, (pair["image1"], pair["image2"])
        return self._images[0 if j == k else 1]


class PackedMasks:
    """Road masks kept 8 pixels a byte (``numpy.packbits``): a 375×1242 mask takes 58 kB instead of
    466 kB as a bool tensor, so the masks of a clip of thousands of pairs fit in memory; each is
    unpacked to (1, H, W) bool when indexed (0.02 ms at that size). A mask equal to the one
    appended before it (one road polygon or mask file for every pair) shares its packed bytes:
    such a clip keeps one mask, whatever its length (:attr:`nbytes`)."""

    def __init__(self) -> None:
        self._packed: list[tuple[np.ndarray, tuple[int, ...]]] = []

    def append(self, mask: Tensor) -> None:
        m = mask.detach().to("cpu", torch.bool)
        bits, shape = np.packbits(m.numpy().reshape(-1)), tuple(m.shape)
        if self._packed and self._packed[-1][1] == shape and np.array_equal(self._packed[-1][0], bits):
            bits = self._packed[-1][0]  # (the previous mask's bytes, not a copy of them)
        self._packed.append((bits, shape))

    @property
    def nbytes(self) -> int:
        """The bytes of packed masks held (a mask shared by consecutive pairs counted once)."""
        return sum(bits.nbytes for bits in {id(bits): bits for bits, _ in self._packed}.values())

    def __len__(self) -> int:
        return len(self._packed)

    def __getitem__(self, k: int) -> Tensor:
        bits, shape = self._packed[k]
        return torch.from_numpy(np.unpackbits(bits, count=math.prod(shape)).view(np.bool_).reshape(shape))


def fit_clip(specs: list[PairSpec], camera: Camera, road_for: Callable[[dict], Tensor], *,
             progress: bool = True, needed_by: str = "--odometry sequence", poses_option: str = "--poses",
             **options: Any) -> ClipFit:
    """Fit the road motion of the clip made by ``specs`` (see the module docstring).

    The clip streams: one pass loads each pair to check that it follows the previous one and to
    find its road mask (``road_for`` is called once per pair; the masks are kept packed, see
    :class:`PackedMasks`), then each of :func:`fsof_torch.fit_sequence`'s two passes loads each
    pair once more (:class:`ClipFrames`). Memory stays at a few frames plus the masks and a few
    numbers per pair, whatever the clip's length.

    Args:
        specs: the clip's pairs, in order.
        camera: the nominal camera (batch 1): intrinsics, height, roll and pitch.
        road_for: a loaded pair -> its road mask (1, H, W) bool and what to record about it (a
            dict), kept with the masks (:meth:`ClipFit.road`).
        progress: progress bars.
        needed_by: the options that need the clip, which its errors name (:func:`clip_options`).
        poses_option: the option the poses come from, which the errors about them name.
        **options: further keyword arguments of :func:`fsof_torch.fit_sequence` (``--fit-options``:
            fit_image's).
    """
    from fsof_torch.io.progress import progress_bar

    check_clip(specs, needed_by=needed_by, poses_option=poses_option)
    masks = PackedMasks()
    road_info: dict[str, tuple[int, dict[str, Any]]] = {}
    relative_poses: list[Tensor | None] = []
    previous = None  # the previous pair's second image, which must be this pair's first
    with progress_bar(specs, enabled=progress, desc="clip: load", unit="pair") as bar:  # (closed before an error prints)
        for k, spec in enumerate(bar):
            pair = spec.load()
            if previous is not None and not torch.equal(previous, pair["image1"]):
                raise JobError(f"{needed_by}: pairs {specs[k - 1].name} and {spec.name} are not consecutive frames "
                               f"of one clip (the second image of one is not the first of the next); "
                               f"{_separately(needed_by)}")
            previous = pair["image2"]
            road, info = road_for(pair)
            masks.append(road.reshape(1, *pair["image1"].shape[-2:]).to(torch.bool))
            road_info[spec.name] = (k, info)
            pose = pair.get("relative_pose")
            relative_poses.append(None if pose is None else pose.to(torch.float64))
            del pair
    del previous
    poses = None
    if all(p is not None for p in relative_poses):
        # camera-to-world poses from the relative ones: P_{k+1} = P_k inverse(cam1_T_cam0)
        P = [torch.eye(4, dtype=torch.float64)]
        for pose in relative_poses:
            P.append(P[-1] @ torch.linalg.inv(pose))
        poses = torch.stack(P)
    cam = camera.to(torch.float64)
    with options_of({"poses": poses_option}):  # e.g. poses that move where the images do not
        seq = fit_sequence(ClipFrames(specs), masks, cam, poses=poses, keep_fits=False, progress=progress, **options)
    fitted = seq.calibrated_from
    # where nothing is calibrated the nominal camera stays, and the motion is the one fitted with it:
    # the first pass's (the only one run), not its translations rescaled to the poses' height, which
    # with the nominal height would scale the road's flow by the ratio of the two heights
    params = seq.params if fitted else seq.first_pass
    motion = {spec.name: {"model": "plane", **{k: float(v[i]) for k, v in params.items()}}
              for i, spec in enumerate(specs)}
    success = {spec.name: bool(seq.success[i]) for i, spec in enumerate(specs)}
    if not fitted:  # failed, still or creeping fits calibrate nothing: the nominal camera stays
        mounting = {"roll_deg": math.degrees(float(cam.roll[0])), "pitch_deg": math.degrees(float(cam.pitch[0]))}
        return ClipFit(motion, cam, mounting, success, masks, road_info, 0)
    mounting = {"roll_deg": math.degrees(seq.mounting["roll"]), "pitch_deg": math.degrees(seq.mounting["pitch"])}
    if "height" in seq.mounting:
        mounting["height_m"] = seq.mounting["height"]
    return ClipFit(motion, seq.camera, mounting, success, masks, road_info, fitted)
