"""The road motion of a clip from its images (:func:`fsof_torch.fit_sequence`): the camera's
mounting calibrated over the clip (its pitch and roll over the road; with poses, the height), each
pair's motion for the ``sequence`` variant.

The pairs must be consecutive frames of one clip (pair k's second image is pair k+1's first); the
road masks are the pairs' own, or detected on a DIS flow where the road is ``auto``. Poses, where
the pairs have them, give the metric scale (the images give the translation over the height only).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Any, Callable

import torch
from torch import Tensor

from fsof_torch import Camera, fit_sequence

from .inputs import JobError, PairSpec


@dataclass
class ClipFit:
    """The clip's road motion: ``motion[name]`` a ``"plane"`` motion dict per pair (floats),
    ``camera`` the calibrated camera, ``mounting`` {"roll", "pitch" (degrees), "height" (m) with
    poses}, ``success[name]`` whether the pair's fit succeeded."""

    motion: dict[str, dict[str, Any]]
    camera: Camera
    mounting: dict[str, float]
    success: dict[str, bool]


def fit_clip(specs: list[PairSpec], camera: Camera, road_for: Callable[[dict], Tensor], *,
             progress: bool = True) -> ClipFit:
    """Fit the road motion of the clip made by ``specs`` (see the module docstring).

    Args:
        specs: the clip's pairs, in order.
        camera: the nominal camera (batch 1): intrinsics, height, roll and pitch.
        road_for: a loaded pair -> its road mask (1, H, W) bool.
        progress: progress bars.
    """
    from tqdm import tqdm

    if len(specs) < 2:
        raise JobError("sequence: a clip needs at least 2 pairs (3 frames)")
    pairs = [spec.load() for spec in tqdm(specs, desc="clip: load", disable=not progress, file=sys.stderr)]
    for k in range(len(pairs) - 1):
        if not torch.equal(pairs[k]["image2"], pairs[k + 1]["image1"]):
            raise JobError(f"sequence: pairs {specs[k].name} and {specs[k + 1].name} are not consecutive frames "
                           f"of one clip (the second image of one is not the first of the next); use "
                           f"--odometry photometric for separate pairs")
    frames = [p["image1"] for p in pairs] + [pairs[-1]["image2"]]
    masks = [road_for(p).reshape(1, *frames[0].shape[-2:]).to(torch.bool) for p in pairs]
    poses = None
    if all(p.get("relative_pose") is not None for p in pairs):
        # camera-to-world poses from the relative ones: P_{k+1} = P_k inverse(cam1_T_cam0)
        P = [torch.eye(4, dtype=torch.float64)]
        for p in pairs:
            P.append(P[-1] @ torch.linalg.inv(p["relative_pose"].to(torch.float64)))
        poses = torch.stack(P)
    cam = camera.to(torch.float64)
    seq = fit_sequence(frames, masks, cam, poses=poses, progress=progress)
    motion = {spec.name: {"model": "plane", **{k: float(v[i]) for k, v in seq.params.items()}}
              for i, spec in enumerate(specs)}
    mounting = {"roll_deg": math.degrees(seq.mounting["roll"]), "pitch_deg": math.degrees(seq.mounting["pitch"])}
    if "height" in seq.mounting:
        mounting["height_m"] = seq.mounting["height"]
    success = {spec.name: bool(f.success.all()) for spec, f in zip(specs, seq.fits)}
    return ClipFit(motion, seq.camera, mounting, success)
