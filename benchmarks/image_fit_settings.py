"""The image fit's photometric settings on real and synthetic frames: the band-pass width and the
pre-smoothing, compared by road end-point error where the truth is known.

For each setting (``fit_image`` keyword arguments, JSON), the ``"plane"`` fit of:

- the shared KITTI 2015 pair 000000 (road.json; EPE over the road pixels with ground truth);
- three pairs of the shared straight KITTI odometry clip (0, 4, 8; road census distance of the
  fitted road flow, image 1 against image 2 warped, 7×7 census / 48);
- the synthetic ``default`` scene (pairs 0 and 2), ``body-motion`` preset (pairs 0–2), and the
  ``default`` scene in a sharp turn (``steering=0.1``: 2.6° of yaw per frame, 26°/s at 10 Hz;
  pairs 0 and 2), road EPE over the valid road pixels.

    python benchmarks/image_fit_settings.py                       # the settings below
    python benchmarks/image_fit_settings.py '{"highpass": 3.0}' '{"highpass": null}'

Without ``../shared`` the real columns are skipped. One thread.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SETTINGS = ['{}', '{"highpass": null}', '{"highpass": null, "smooth_sigma": 1.0}', '{"highpass": 5.0, "smooth_sigma": 1.0}',
            '{"highpass": 3.0}', '{"highpass": 3.0, "smooth_sigma": 1.0}', '{"highpass": 10.0}']


def main(argv: list[str]) -> None:
    from fsof_torch import Camera, fit_image, photometric_error, read_image, read_kitti_flow, read_road_mask
    from fsof_torch.data.scene import render_pair, render_sequence

    torch.set_num_threads(1)
    settings = [json.loads(a) for a in (argv or SETTINGS)]
    synthetic = {"default": [render_pair("default", i, seed=0) for i in (0, 2)],
                 "body-motion": render_sequence("body-motion", 3, seed=0),
                 "turning": [render_pair("default", i, seed=0, steering=0.1) for i in (0, 2)]}
    real = {}
    k15 = SHARED / "kitti15_000000"
    if k15.is_dir():
        im1, im2 = read_image(k15 / "image_10.png"), read_image(k15 / "image_11.png")
        gt, valid = read_kitti_flow(k15 / "flow_noc_10.png")
        road = read_road_mask(k15 / "road.json", size=tuple(im1.shape[-2:]))
        real["kitti"] = (Camera.from_kitti(k15 / "calib_cam_to_cam.txt", cam=2, height=1.65), im1, im2, road, gt, valid)
    clip = SHARED / "kitti_odometry_straight"
    if clip.is_dir():
        files = sorted((clip / "image_l").glob("*.png"))
        cam = Camera.from_kitti(clip / "calib.txt", cam=0, height=1.65)
        road = read_road_mask(clip / "road.json", size=tuple(read_image(files[0]).shape[-2:]))
        real["clip"] = [(cam, read_image(files[i]), read_image(files[i + 1]), road) for i in (0, 4, 8)]

    def epe(flow, gt, mask):
        return float((flow - gt).norm(dim=0)[mask].mean())

    print("| setting | KITTI pair EPE (px) | clip census | default EPE (px) | body-motion EPE (px) | turning EPE (px) |")
    print("|---|---|---|---|---|---|")
    for kw in settings:
        cols = []
        if "kitti" in real:
            cam, im1, im2, road, gt, valid = real["kitti"]
            fit = fit_image(im1[None], im2[None], road[None], cam, **kw)
            cols.append(f"{epe(fit.flow[0], gt, road[0] & valid.reshape(road.shape[-2:]).bool()):.3f}")
        else:
            cols.append("–")
        if "clip" in real:
            c = []
            for cam, im1, im2, road in real["clip"]:
                fit = fit_image(im1[None], im2[None], road[None], cam, **kw)
                c.append(float(photometric_error(im1[None], im2[None], fit.flow.float(), road[None], kind="census")[0]))
            cols.append(f"{np.mean(c):.4f}")
        else:
            cols.append("–")
        for pairs in synthetic.values():
            e = [epe(fit_image(p["image1"][None], p["image2"][None], p["road"][None], p["camera"], **kw).flow[0],
                     p["flow"], (p["road"] & p["valid"])[0]) for p in pairs]
            cols.append(f"{np.mean(e):.3f}")
        print(f"| `{json.dumps(kw)}` | " + " | ".join(cols) + " |", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
