"""Draw docs/images/overview.png, the README's picture: a flow before and after refinement.

A built-in synthetic pair (preset ``default``, pair 0, KITTI's 375 × 1242) with its exact flow,
road mask, camera and odometry; OpenCV DIS (PRESET_MEDIUM, grey images) predicts the flow; the
refiner replaces it inside the road by the road model's flow for the vehicle's odometry. The
figure is built by ``fsof_torch.evaluation.figures.pair_figure``, as the refine job's figures
are. Needs nothing but the installed package (a few seconds on one CPU thread):

    python docs/images/make_overview.py [--out docs/images/overview.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import torch

import fsof_torch as fs
from fsof_torch.evaluation.figures import pair_figure, save_figure
from refine.sources import dis_flow  # the refine job's DIS source (PRESET_MEDIUM, grey images)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "overview.png")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)

    pair = fs.render_pair("default", 0)
    image1, image2 = pair["image1"], pair["image2"]
    gt, valid, road = pair["flow"], pair["valid"], pair["road"]
    before = dis_flow(image1, image2)
    out = fs.FreespaceRefiner()(before[None], road[None], pair["camera"], pair["odometry"])
    after = out.flow[0]

    flows = {"before (OpenCV DIS)": before, "after (refined)": after}
    errors = {name: ((f - gt).norm(dim=0, keepdim=True), valid) for name, f in flows.items()}
    # colour saturation: the 99th percentile of the true flow's magnitude on the road
    magnitude = gt.norm(dim=0)[road[0] & valid[0]]
    max_flow = float(magnitude.kthvalue(max(1, int(0.99 * magnitude.numel()))).values)
    for name, f in flows.items():
        m = road & valid
        print(f"{name}: road end-point error {float((f - gt).norm(dim=0, keepdim=True)[m].mean()):.2f} px")
    fig = pair_figure(flows=flows, errors=errors, road=road, max_flow=max_flow, error_vmax=5.0,
                      error_label="end-point error (px)", images=(image1, image2),
                      title="A synthetic pair: OpenCV DIS flow before and after freespace refinement "
                            "(with the vehicle's odometry)\nerror = |flow − ground truth|")
    path = save_figure(fig, args.out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
