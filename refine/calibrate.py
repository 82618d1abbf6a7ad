"""Calibrating the camera pitch over a clip with known poses: the pitch whose road model flow
(from the poses) minimises the road photometric error over the clip.

The paper's model has no pitch; real mountings have one (KITTI: about −1°), and with poses the
model flow is fixed by the pitch alone, so a one-dimensional search is enough: a coarse grid,
then a fine grid around the best value.
"""

from __future__ import annotations

import math
import sys

import torch

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.road_flow import displacement_flow
from fsof_torch.evaluation.photometric import photometric_error

from .inputs import JobError, PairSpec, odometry_from_pose


def calibrate_pitch(specs: list[PairSpec], camera: Camera, *, max_pairs: int = 24,
                    coarse_deg: tuple[float, float, float] = (-3.0, 1.0, 0.25),
                    fine_step_deg: float = 0.05, progress: bool = True) -> tuple[float, list[tuple[float, float]]]:
    """The pitch (degrees) minimising the mean road photometric error of the pose-driven model flow.

    Args:
        specs: pairs whose ``load()`` gives ``relative_pose`` and a ``road`` mask.
        camera: the camera (its pitch is replaced by the candidates).
        max_pairs: at most this many pairs, evenly spread over the clip, enter the search.
        coarse_deg: (start, stop, step) of the coarse grid, degrees.
        fine_step_deg: the step of the fine grid around the coarse optimum (± one coarse step).

    Returns:
        ``(best_pitch_deg, [(pitch_deg, mean_road_photometric_error), ...])`` over every candidate.
    """
    from tqdm import tqdm

    if not specs:
        raise JobError("--calibrate-pitch: no pairs")
    step = max(1, math.ceil(len(specs) / max_pairs))
    data = []
    for spec in tqdm(specs[::step], desc="calibrate pitch: load", disable=not progress, file=sys.stderr):
        pair = spec.load()
        if pair.get("relative_pose") is None or pair.get("road") is None:
            raise JobError("--calibrate-pitch: needs --poses and a road mask (not 'auto')")
        # grey is enough for the L1 error and a third of the memory
        grey = lambda im: im.mean(dim=0, keepdim=True)[None]  # noqa: E731
        data.append((grey(pair["image1"]), grey(pair["image2"]), pair["road"][None], pair["relative_pose"]))
    size = tuple(data[0][0].shape[-2:])
    cam64 = camera.to(torch.float64)
    scores: dict[float, float] = {}

    def score(pitch_deg: float) -> float:
        key = round(pitch_deg, 6)
        if key not in scores:
            cam = cam64.replace(pitch=math.radians(pitch_deg))
            num = den = 0.0
            for im1, im2, road, rel in data:
                odo = odometry_from_pose(rel, cam)
                flow, valid = displacement_flow(cam, odo["x_d"], odo["z_d"], odo["yaw"], size)
                pe, n = photometric_error(im1, im2, flow.to(im1.dtype), road & valid, return_count=True)
                num += float(pe[0]) * int(n[0])
                den += int(n[0])
            scores[key] = num / den if den else float("inf")
        return scores[key]

    start, stop, coarse = coarse_deg
    grid = [start + i * coarse for i in range(int(round((stop - start) / coarse)) + 1)]
    for p in tqdm(grid, desc="calibrate pitch: coarse", disable=not progress, file=sys.stderr):
        score(p)
    best = min(scores, key=scores.get)
    n_fine = int(round(coarse / fine_step_deg))
    fine = [best + i * fine_step_deg for i in range(-n_fine, n_fine + 1)]
    for p in tqdm(fine, desc="calibrate pitch: fine", disable=not progress, file=sys.stderr):
        score(p)
    best = min(scores, key=scores.get)
    return best, sorted(scores.items())
