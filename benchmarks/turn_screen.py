"""The image fit's screens of turns and of steps backwards under exposure changes: the candidate
each ranks first against the motion applied, ranked by the census (the screens' measure) and by
raw intensities (gain 1, offset 0), for comparison.

Where every start of an image fit fails, ``fit_image`` screens turns of ±3 to ±12° a frame at the
coarsest pyramid level and solves the best (docs/image-fit.md, "Sharp turns"); where that and the
retry without the prior fail too, steps straight backwards of 1, 2 and 4 camera heights a frame
("Backward flow"). This script runs the screens alone
(``fsof_torch.estimation.starts.screened_start``, the fit's inputs to it) on:

- synthetic pairs (``default`` 0 and 10, ``body-motion`` 3, ``crest`` 5, ``dip`` 7; 188 × 621,
  driven straight), image 2 seen by a camera turned by ±5, ±8 and ±11° of yaw (``real_road.py``'s
  ``turned``, exact at every depth), each with image 2 as recorded and changed in exposure:
  gains 0.5, 0.6, 0.8, 1.5 and 2, offsets of ±30 and ±60 grey levels, gain 1.3 with +20 and 0.8
  with −20, clipped to 0..255 and rounded as an 8-bit camera records it;
- the shared KITTI clip's pairs (``../shared/data/kitti_odometry_straight``), turned by the
  yaw a frame (and pitched and rolled) of each row, also two or three frames apart, with image 2
  at the row's gain (``real_road.py``'s ``exposed``); and its pairs with their frames swapped
  (``real_road.py``'s ``reversed_pair``: the backward flow, 0.7, 1.4 and 2.2 camera heights a
  frame backwards at 1, 2 and 3 frames apart), screened for a step backwards.

Prints, per group, the cases and how many picks of each measure are the screened turn nearest
the applied yaw (5° → 6°, 8° → 9°, 11° → 12°), and how many lie within 3° of it (a step of the
screen: within the basin the fit is solved from, docs/image-fit.md); for the swapped frames, the
screened step nearest the poses' distance backwards, and one next to it.

    python benchmarks/turn_screen.py [--no-real] [--data DIR]

One thread. Without the clip (or with ``--no-real``) only the synthetic part runs.
"""

from __future__ import annotations

import argparse
import math
import warnings
from pathlib import Path
from typing import Callable

import torch

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CLIP = ("image_l", "calib.txt", "road.json", "poses.txt")
SYNTHETIC = (("default", 0), ("default", 10), ("body-motion", 3), ("crest", 5), ("dip", 7))
YAWS = (-11.0, -8.0, -5.0, 5.0, 8.0, 11.0)
EXPOSURES = ((1.0, 0.0), (0.5, 0.0), (0.6, 0.0), (0.8, 0.0), (1.5, 0.0), (2.0, 0.0), (1.0, 30.0), (1.0, -30.0),
             (1.0, 60.0), (1.0, -60.0), (1.3, 20.0), (0.8, -20.0))
#: (frames apart, yaw, pitch change, roll change in degrees a frame, image 2's gain)
REAL = ((1, 3, 0, 0, 1), (1, 6, 0, 0, 1), (1, -6, 0, 0, 1), (1, 9, 0, 0, 1), (1, -9, 0, 0, 1), (1, 12, 0, 0, 1),
        (1, -12, 0, 0, 1), (1, 6, 1, 1, 1), (1, -9, -1.5, 2, 1), (3, 6, 0, 0, 1), (2, -9, 0, 0, 1),
        (1, 9, 0, 0, 0.6), (1, -9, 0, 0, 1.5), (1, 12, 0, 0, 2), (1, -12, 0, 0, 0.5), (1, 6, 1, 1, 1.5),
        (1, -9, -1.5, 2, 0.7), (3, 6, 0, 0, 1.4), (2, -9, 0, 0, 0.6))
#: the census screening the turns and the steps backwards at once, as the fit does not (a
#: comparison: the steps backwards can outrank the right turn)
TOGETHER = "census, turns and steps backwards together"
MEASURES = ("census", "intensities", TOGETHER)
#: the clip's pairs swapped (yaw None): the backward flow, driven 0.7, 1.4 and 2.2 camera heights
#: backwards a frame at 1, 2 and 3 frames apart
REVERSED = ((1, None, 0, 0, 1), (2, None, 0, 0, 1), (3, None, 0, 0, 1), (1, None, 0, 0, 0.6), (2, None, 0, 0, 1.5))


def screened(pair: dict, backwards: bool = False) -> dict[str, tuple[float, float]]:
    """The candidate the screen ranks first on ``pair`` (images, road, camera), by the census and by
    raw intensities, from the coarsest level ``fit_image`` would screen on: of the turns, or with
    ``backwards`` of the steps backwards; (degrees of yaw, camera heights ahead) per measure."""
    from fsof_torch.estimation.pyramid import image_pyramid, level_camera, mask_pyramid, pyramid_levels
    from fsof_torch.estimation.starts import REVERSE_STARTS, TURN_STARTS, reverse_moves, screened_start, turn_moves
    from fsof_torch.evaluation.photometric import to_grey
    from fsof_torch.geometry.road_models import get_road_model, pack_params

    grey = torch.cat([to_grey(pair["image1"][None].float()), to_grey(pair["image2"][None].float())], dim=1)
    n = pyramid_levels(*grey.shape[-2:], None, 16)
    level, mask = image_pyramid(grey, n, 0.0)[-1], mask_pyramid(pair["road"][None], n)[-1]
    camera = level_camera(pair["camera"].to(torch.float64), n - 1)
    plane = get_road_model("plane")
    _, base = pack_params(plane, camera, None)
    yaw, z_d = plane.params.index("yaw"), plane.params.index("z_d")
    moves = reverse_moves(REVERSE_STARTS, ()) if backwards else turn_moves(TURN_STARTS, ())
    # (and for comparison, on turns: the census over the turns and the steps backwards together)
    together = turn_moves(TURN_STARTS, ()) + reverse_moves(REVERSE_STARTS, ())
    picks = {}
    for name, census, screen in (("census", True, moves), ("intensities", False, moves), (TOGETHER, True, together)):
        pick = screened_start(plane, camera, base, level, mask, screen, (), "cauchy", 3000, census=census)[0]
        picks[name] = (math.degrees(float(pick[yaw])), float(pick[z_d] / camera.height[0]))
    return picks


def count(right: dict[str, list[int]], picks: dict[str, tuple[float, float]], yaw: float,
          back: float | None = None) -> None:
    """Add the picks to ``right`` ({measure: [nearest the applied motion, within a step of it]}): for a
    turn by ``yaw`` degrees, the screened turn nearest it and a turn within 3° of it; for a pair
    driven ``back`` camera heights backwards, the screened step backwards nearest it and one next
    to that."""
    from fsof_torch.estimation.starts import REVERSE_STARTS, TURN_STARTS

    for name, (picked, ahead) in picks.items():
        if back is None:
            nearest = min(TURN_STARTS, key=lambda t: abs(t - yaw))
            right[name][0] += ahead > 0 and abs(picked - nearest) < 1e-6  # (degrees through radians: not exact)
            right[name][1] += ahead > 0 and abs(picked - yaw) <= 3.0
        else:
            steps = [-k for k in REVERSE_STARTS]
            nearest = min(range(len(steps)), key=lambda i: abs(REVERSE_STARTS[i] - back))
            at = [i for i, k in enumerate(steps) if abs(ahead - k) < 1e-6]
            right[name][0] += at == [nearest]
            right[name][1] += bool(at) and abs(at[0] - nearest) <= 1


def synthetic_rows(rr, progress: Callable) -> list[tuple[str, int, dict[str, list[int]]]]:
    """(exposure, cases, right picks by measure) over the synthetic pairs and turns."""
    from fsof_torch.data.scene import render_pair

    right = {e: {m: [0, 0] for m in MEASURES} for e in EXPOSURES}
    cases = 0
    for preset, index in progress(SYNTHETIC):
        p = render_pair(preset, index, size=(188, 621), steering=0.0)
        for yaw in YAWS:
            t = rr.turned({k: p[k] for k in ("image1", "image2", "road", "camera", "flow", "valid")}, yaw)
            cases += 1
            for gain, offset in EXPOSURES:
                image2 = (t["image2"] * gain + offset).clamp(0, 255).round()
                count(right[(gain, offset)], screened({**t, "image2": image2}), yaw)
    return [(f"gain {g:g}, offset {o:+g}", cases, right[(g, o)]) for g, o in EXPOSURES]


def real_rows(rr, clip: Path, progress: Callable) -> list[tuple[str, int, dict[str, list[int]]]]:
    """(turn and exposure, pairs, right picks by measure) over the clip's pairs, turned; then
    swapped (the backward flow), the steps backwards judged against the poses' distance."""
    from fsof_torch import plane_from_pose

    rows = []
    for step, yaw, pitch, roll, gain in progress(REAL + REVERSED):
        right, cases = {m: [0, 0] for m in MEASURES}, 0
        for _, load in rr.odometry_clip(clip, 1.65, 0.0, step):
            pair = load()
            back = None
            if yaw is None:  # (swapped: the distance driven backwards, in camera heights)
                pair = rr.reversed_pair(pair)
                camera = pair["camera"].to(torch.float64)
                back = -float(plane_from_pose(pair["relative_pose"][None], camera)["z_d"][0] / camera.height[0])
            t = rr.turned(pair, yaw, pitch, roll) if yaw else pair
            if gain != 1:
                t = rr.exposed(t, gain)
            cases += 1
            count(right, screened(t, back is not None), yaw or 0.0, back)
        motion = ("frames swapped" if yaw is None else f"yaw {yaw:+g}°"
                  + (f", pitch {pitch:+g}°, roll {roll:+g}°" if pitch or roll else ""))
        rows.append((f"{'' if step == 1 else f'{step} frames apart, '}{motion}, gain {gain:g}", cases, right))
    return rows


def table(title: str, rows: list[tuple[str, int, dict[str, list[int]]]]) -> None:
    print(f"\n{title}\n")
    print("| case | cases | " + " | ".join(f"{m}: nearest | within a step" for m in MEASURES) + " |")
    print("|---|---|" + "---|---|" * len(MEASURES))
    for label, cases, right in rows + [("all", sum(c for _, c, _ in rows),
                                        {m: [sum(r[m][k] for *_, r in rows) for k in (0, 1)] for m in MEASURES})]:
        print(f"| {label} | {cases} | " + " | ".join(f"{right[m][0]} | {right[m][1]}" for m in MEASURES) + " |")


def main(argv: list[str] | None = None) -> int:
    from cli import data_folder, description, readable_clip, reads_data

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--no-real", action="store_true", help="leave out the shared KITTI clip")
    parser.add_argument("--data", metavar="DIR", type=Path, default=None,
                        help="the folder holding kitti_odometry_straight/ (default: ../shared/data beside the "
                             "repository; without the clip there, the synthetic part only)")
    args = parser.parse_args(argv)
    reads = reads_data(parser, args.data, args.no_real, "--no-real")
    data = data_folder(parser, args.data, DATA, tuple(f"kitti_odometry_straight/{n}" for n in CLIP)) if reads else None
    if args.data is not None:  # (a file it cannot read raised a traceback after the synthetic part)
        readable_clip(parser, data / "kitti_odometry_straight", poses=True)
    import cv2
    import real_road as rr

    from fsof_torch.io.progress import progress_bar

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    warnings.simplefilter("ignore")
    table("Synthetic pairs (5 scenes × 6 turns), by image 2's exposure:",
          synthetic_rows(rr, lambda items: progress_bar(items, desc="synthetic", unit="scene", leave=False)))
    if data is not None:
        clip = data / "kitti_odometry_straight"
        if all((clip / n).exists() for n in CLIP):
            table("The shared KITTI clip's pairs, turned, and with their frames swapped:",
                  real_rows(rr, clip, lambda rows: progress_bar(rows, desc="clip", unit="row", leave=False)))
        else:
            print(f"\nThe KITTI clip absent: skipped ({clip} lacks some of {', '.join(CLIP)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
