"""How far the image fit's covariance can be trusted, measured.

``fit_image`` reports ``covariance``: the Gauss–Newton posterior of its parameters, from the
residuals' spread at the fitted motion. This script compares it with the fits' actual errors,
in units of the standard deviation it reports (z = error / σ: for a covariance that tells the
truth, half of the |z| lie below 0.67, 68 % below 1 and 95 % below 2):

1. synthetic presets (``default``, ``body-motion``, ``crest``, ``dip``; pairs 0, 10, 20 and 30
   of each at 375 × 1242, the scene's road): every parameter against the scene's true motion;
2. the shared straight clip (all pairs, road.json's polygon, the nominal camera 1.65 m high):
   the rotations between the frames (yaw, pitch change, roll change) against the ground-truth
   poses (``plane_from_pose``); the translations are left out, as the poses' scale over the
   images' is the camera's unknown true height.

    python benchmarks/fit_covariance.py [--data DIR] [--pairs 0 10 20 30]

One thread. Part 2 needs the clip (``../shared/data/kitti_odometry_straight``, or ``--data``
naming it) and is skipped without it.
"""

from __future__ import annotations

import argparse
import math
import statistics
import warnings
from pathlib import Path

import cv2
import torch

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_odometry_straight"
CLIP = ("calib.txt", "image_l", "road.json", "poses.txt")
PRESETS = ("default", "body-motion", "crest", "dip")
#: the parameters shown in degrees (the rest in millimetres)
ANGLES = ("pitch_change", "yaw", "roll_change", "pitch", "roll")


def z_scores(fit, truth: dict[str, float], names: list[str]) -> dict[str, tuple[float, float]]:
    """Per parameter of ``names``: (error, reported σ) of a batch-1 fit against ``truth``."""
    sd = fit.covariance[0].diagonal().sqrt()
    order = list(fit.params)
    return {n: (fit.params[n].item() - truth[n], sd[order.index(n)].item()) for n in names}


def summary(rows: list[dict[str, tuple[float, float]]], names: list[str]) -> list[str]:
    """Markdown rows: per parameter, the fits, median |error|, median σ, median |z| and the
    shares of |z| within 1 and 2."""
    out = []
    for n in names:
        err = [abs(r[n][0]) for r in rows]
        sd = [r[n][1] for r in rows]
        z = [e / s if s > 0 else math.inf for e, s in zip(err, sd)]
        unit, k = ("°", math.degrees(1.0)) if n in ANGLES else ("mm", 1000.0)
        out.append(f"| {n} | {len(rows)} | {statistics.median(err) * k:.3g} {unit} | "
                   f"{statistics.median(sd) * k:.3g} {unit} | {statistics.median(z):.2f} | "
                   f"{sum(v <= 1 for v in z) / len(z):.2f} | {sum(v <= 2 for v in z) / len(z):.2f} |")
    return out


HEADER = ["| parameter | fits | median \\|error\\| | median σ reported | median \\|z\\| | \\|z\\| ≤ 1 | \\|z\\| ≤ 2 |",
          "|---|---|---|---|---|---|---|"]


def synthetic(pairs: list[int], progress: bool) -> list[str]:
    import fsof_torch as fs
    from fsof_torch.io.progress import progress_bar

    rows, names = [], None
    jobs = [(p, i) for p in PRESETS for i in pairs]
    for preset, i in progress_bar(jobs, enabled=progress, desc="synthetic fits", unit="pair"):
        s = fs.render_pair(preset, i)
        fit = fs.fit_image(s["image1"][None], s["image2"][None], s["road"][None], s["camera"])
        names = names or list(fit.params)
        rows.append(z_scores(fit, s["plane"], names))
    return [f"Synthetic presets {', '.join(PRESETS)}, pairs {', '.join(map(str, pairs))} "
            f"(375 × 1242), every parameter against the scene's motion:", "", *HEADER, *summary(rows, names)]


def real_clip(root: Path, progress: bool) -> list[str]:
    import fsof_torch as fs
    from fsof_torch.datasets import ImageFolderDataset
    from fsof_torch.io.progress import progress_bar

    dataset = ImageFolderDataset(root / "image_l", root / "calib.txt", cam=0, camera_height=1.65,
                                 road=root / "road.json", camera_dtype=torch.float64)
    poses = fs.read_kitti_poses(root / "poses.txt")
    names = ["yaw", "pitch_change", "roll_change"]
    rows = []
    for i in progress_bar(range(len(dataset)), enabled=progress, desc="clip fits", unit="pair"):
        pair, files = dataset[i], dataset.pairs[i]
        a, b = int(files.image1.stem), int(files.image2.stem)  # (poses by the frames' numbers)
        truth = fs.plane_from_pose((torch.linalg.inv(poses[b]) @ poses[a])[None].to(torch.float64), pair["camera"])
        fit = fs.fit_image(pair["image1"][None], pair["image2"][None], pair["road"][None], pair["camera"])
        if bool(fit.success[0]):
            rows.append(z_scores(fit, {n: truth[n].item() for n in names}, names))
    return [f"The shared straight clip ({len(rows)} of {len(dataset)} pairs fitted with success), the rotations "
            f"against the ground-truth poses:", "", *HEADER, *summary(rows, names)]


def main(argv: list[str] | None = None) -> int:
    from cli import data_folder, description, pair_index, present, readable_clip

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="the straight clip's folder (default: ../shared/data/kitti_odometry_straight)")
    parser.add_argument("--pairs", type=pair_index, nargs="+", default=[0, 10, 20, 30],
                        help="the synthetic presets' pairs (default: 0 10 20 30)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    clip = data_folder(parser, args.data, DEFAULT, CLIP)
    if args.data is not None:  # (a file it cannot read would raise a traceback after part 1)
        readable_clip(parser, clip, poses=True)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    warnings.simplefilter("ignore")
    print("\n".join(synthetic(args.pairs, not args.no_progress)))
    print()
    if present(clip, CLIP, "KITTI clip (part 2)"):
        print("\n".join(real_clip(clip, not args.no_progress)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
