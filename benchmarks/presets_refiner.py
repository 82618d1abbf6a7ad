"""The default refiner on every synthetic preset: how general it is beyond the frames its settings
were chosen on.

For each preset of ``fsof_torch.data.scene.PRESETS`` and a few pairs of its sequence (375 × 1242,
exact flow and road mask), OpenCV DIS (MEDIUM) predicts the flow, and the default
``FreespaceRefiner()`` refines it with the two images and no odometry (the road motion estimated
from the images, then the gate). Prints, per preset, the road end-point error (px, over the valid
road pixels) of DIS, of the refined flow and of the model flow alone, pooled over the pairs, and
how many pairs were refined.

With ``--odometry-error SCALE YAW_DEG`` the refiner is also given the scene's planar odometry, its
translation SCALE times as long and its yaw YAW_DEG degrees a frame off (``1 0``: exact), held fixed
(the default) and as priors the images may move it from (``ImageMotionEstimator(odometry_sigma=
ODOMETRY_SIGMA)``, as in ``real_road.py``): two more columns of road end-point error.

    python benchmarks/presets_refiner.py [--pairs 0 6 12] [--presets default carla-turning ...] [--odometry-error SCALE YAW_DEG]
"""

from __future__ import annotations

import argparse
import math
import warnings

import torch


def main(argv: list[str] | None = None) -> int:
    from cli import description, finite_float, odometry_error, pair_index, scene_seed
    from fsof_torch.data.scene import PRESETS

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--pairs", type=pair_index, nargs="+", default=[0, 6, 12],
                        help="pair indices of each preset's sequence (default 0 6 12)")
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=list(PRESETS),
                        help="the synthetic presets (default: all)")
    parser.add_argument("--seed", type=scene_seed, default=0, help="the scenes' seed, in [0, 2**62) (default 0)")
    parser.add_argument("--odometry-error", type=finite_float, nargs=2, metavar=("SCALE", "YAW_DEG"), default=None,
                        help="also refine with the scene's odometry made this wrong, held and as priors "
                             "(SCALE within [0.5, 2], YAW_DEG within (-45, 45))")
    args = parser.parse_args(argv)
    args.odometry_error = odometry_error(parser, args.odometry_error)
    torch.set_num_threads(1)
    import cv2

    import fsof_torch as fs
    from refine.sources import dis_flow

    cv2.setNumThreads(1)
    warnings.simplefilter("ignore")
    refiner = fs.FreespaceRefiner(warn=False)
    with_odometry = args.odometry_error is not None
    if with_odometry:
        from real_road import ODOMETRY_SIGMA

        scale, yaw_error = args.odometry_error
        priors = fs.FreespaceRefiner(warn=False, estimator=fs.ImageMotionEstimator(odometry_sigma=ODOMETRY_SIGMA))
    print(f"default refiner, DIS flow, pairs {args.pairs} of each preset (seed {args.seed}), road EPE in px "
          "pooled over the pairs' valid road pixels")
    if with_odometry:
        print(f"odometry: the scene's, translation {scale:g} times as long, yaw {yaw_error:+g}° a frame off; "
              "refined with it held fixed and as priors")
    print(f"{'preset':<16} {'DIS':>7} {'refined':>8} {'model':>7}  refined pairs"
          + (f" {'held':>7} {'priors':>7}" if with_odometry else ""))
    for preset in args.presets:
        sums = torch.zeros(5, dtype=torch.float64)
        count, refined = 0, 0
        for k in args.pairs:
            p = fs.render_pair(preset, k, seed=args.seed)
            im1, im2, road = p["image1"][None], p["image2"][None], p["road"][None]
            flow = dis_flow(p["image1"], p["image2"])[None]
            out = refiner(flow, road, p["camera"], images=(im1, im2))
            flows = [flow, out.flow, out.flow_model]
            if with_odometry:
                odometry = {"x_d": p["odometry"]["x_d"] * scale, "z_d": p["odometry"]["z_d"] * scale,
                            "yaw": p["odometry"]["yaw"] + math.radians(yaw_error)}
                flows += [r(flow, road, p["camera"], odometry, images=(im1, im2)).flow for r in (refiner, priors)]
            use = (p["road"] & p["valid"])[0]
            for i, f in enumerate(flows):
                sums[i] += (f[0] - p["flow"]).norm(dim=0)[use].double().sum()
            count += int(use.sum())
            refined += int(out.refined.sum())
        dis, ref, model, held, prior = (sums / max(count, 1)).tolist()
        print(f"{preset:<16} {dis:7.3f} {ref:8.3f} {model:7.3f}  {refined}/{len(args.pairs)}"
              + (f"{'':>12}{held:7.3f} {prior:7.3f}" if with_odometry else ""), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
