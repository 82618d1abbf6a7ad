"""The default refiner on every synthetic preset: how general it is beyond the frames its settings
were chosen on.

For each preset of ``fsof_torch.data.scene.PRESETS`` and a few pairs of its sequence (375 × 1242,
exact flow and road mask), OpenCV DIS (MEDIUM) predicts the flow, and the default
``FreespaceRefiner()`` refines it with the two images and no odometry (the road motion estimated
from the images, then the gate). Prints, per preset, the road end-point error (px, over the valid
road pixels) of DIS, of the refined flow and of the model flow alone, pooled over the pairs, and
how many pairs were refined.

    python benchmarks/presets_refiner.py [--pairs 0 6 12] [--presets default carla-turning ...]
"""

from __future__ import annotations

import argparse
import warnings

import torch


def main() -> None:
    from fsof_torch.data.scene import PRESETS

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, nargs="+", default=[0, 6, 12])
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=list(PRESETS))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    import cv2

    import fsof_torch as fs
    from refine.sources import dis_flow

    cv2.setNumThreads(1)
    warnings.simplefilter("ignore")
    refiner = fs.FreespaceRefiner(warn=False)
    print(f"default refiner, DIS flow, pairs {args.pairs} of each preset (seed {args.seed}), road EPE in px "
          "pooled over the pairs' valid road pixels")
    print(f"{'preset':<16} {'DIS':>7} {'refined':>8} {'model':>7}  refined pairs")
    for preset in args.presets:
        sums = torch.zeros(3, dtype=torch.float64)
        count, refined = 0, 0
        for k in args.pairs:
            p = fs.render_pair(preset, k, seed=args.seed)
            im1, im2, road = p["image1"][None], p["image2"][None], p["road"][None]
            flow = dis_flow(p["image1"], p["image2"])[None]
            out = refiner(flow, road, p["camera"], images=(im1, im2))
            use = (p["road"] & p["valid"])[0]
            for i, f in enumerate((flow, out.flow, out.flow_model)):
                sums[i] += (f[0] - p["flow"]).norm(dim=0)[use].double().sum()
            count += int(use.sum())
            refined += int(out.refined.sum())
        dis, ref, model = (sums / max(count, 1)).tolist()
        print(f"{preset:<16} {dis:7.3f} {ref:8.3f} {model:7.3f}  {refined}/{len(args.pairs)}", flush=True)


if __name__ == "__main__":
    main()
