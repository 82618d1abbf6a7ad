"""The fitting figures on the shared real KITTI pair (kitti15_000000), printed as a table.

Rows: the displacement model fitted to the ground-truth flow inside road.json (paper model, and
with pitch); OpenCV DIS flow (PRESET_MEDIUM, grey images) and a robust fit to it; the direct
photometric fit started from zero motion and from the DIS fit (no ground truth used). Column
e_E: mean end-point error against the ground truth over the valid pixels of road.json.

Usage: ``python benchmarks/fit_kitti.py [--data ../shared/data/kitti15_000000] [--json out.json]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from fsof_torch.geometry.camera import Camera
from fsof_torch import fit_displacement, fit_photometric

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti15_000000"
NEED = ("calib_cam_to_cam.txt", "flow_noc_10.png", "road.json", "image_10.png", "image_11.png")


def load(folder: Path):
    import cv2

    from fsof_torch.io import read_image, read_kitti_flow, read_road_mask

    cam = Camera.from_kitti(folder / "calib_cam_to_cam.txt", cam=2, height=1.65)
    gt, valid = read_kitti_flow(folder / "flow_noc_10.png")
    road = read_road_mask(folder / "road.json", size=tuple(gt.shape[-2:]))
    rgb = [read_image(folder / f"image_1{i}.png")[None] for i in (0, 1)]
    grey = [cv2.cvtColor(im[0].permute(1, 2, 0).numpy().astype(np.uint8), cv2.COLOR_RGB2GRAY) for im in rgb]
    return cam, gt[None].double(), valid[None], road[None], rgb, grey


def main(argv: list[str] | None = None) -> int:
    from cli import data_folder, description, json_path, present, readable_pair, write_json

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="the KITTI 2015 pair's folder (default: ../shared/data/kitti15_000000)")
    parser.add_argument("--json", type=str, default=None, metavar="PATH",
                        help="also write the rows as JSON here (an earlier file there is removed at the start)")
    args = parser.parse_args(argv)
    args.data = data_folder(parser, args.data, DEFAULT, NEED)
    args.json = json_path(parser, args.json, {"--data": args.data})
    if not present(args.data, NEED, "KITTI pair kitti15_000000"):
        return 0
    readable_pair(parser, args.data)
    import cv2

    torch.set_num_threads(1)
    cv2.setNumThreads(1)  # (DIS and the photometric fit's image operations: the ms column is one thread's)
    cam, gt, valid, road, (image1, image2), (g1, g2) = load(args.data)
    use = (road & valid)[:, 0]

    def e_E(flow: torch.Tensor) -> float:
        return float((flow.double() - gt).norm(dim=1)[use].mean())

    rows = []

    def add(name, fn):
        t = time.perf_counter()
        out = fn()
        ms = (time.perf_counter() - t) * 1e3
        flow = out if isinstance(out, torch.Tensor) else out.flow
        row = dict(name=name, e_E=round(e_E(flow), 3), ms=round(ms, 1))
        if not isinstance(out, torch.Tensor):
            row.update(x_d=round(float(out.x_d), 4), z_d=round(float(out.z_d), 4),
                       yaw=round(float(out.yaw), 5), roll=round(float(out.roll), 4),
                       pitch=round(float(out.pitch), 4), success=bool(out.success))
        rows.append(row)
        return out

    add("fit_displacement to GT (paper model: x_d, z_d, yaw, roll)",
        lambda: fit_displacement(gt, road, cam, valid=valid))
    add("fit_displacement to GT, with pitch",
        lambda: fit_displacement(gt, road, cam, valid=valid, fit_pitch=True))
    dis = add("OpenCV DIS (PRESET_MEDIUM, grey)", lambda: torch.from_numpy(
        cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(g1, g2, None)).permute(2, 0, 1)[None].double())
    add("fit_displacement to DIS", lambda: fit_displacement(dis, road, cam))
    start = add("fit_displacement to DIS, roll fixed at 0", lambda: fit_displacement(dis, road, cam, fit_roll=False))
    add("fit_photometric from zero motion", lambda: fit_photometric(image1, image2, road, cam))
    add("fit_photometric from the DIS fit (roll fixed)", lambda: fit_photometric(image1, image2, road, cam, init=start))
    add("fit_photometric from zero motion, roll fixed at 0",
        lambda: fit_photometric(image1, image2, road, cam, fit_roll=False))

    print(f"KITTI 2015 training pair 000000, {int(use.sum())} valid GT pixels inside road.json, 1 thread")
    header = f"{'method':<58} {'e_E px':>7} {'ms':>8}  parameters"
    print(header)
    print("-" * len(header))
    for r in rows:
        extra = {k: v for k, v in r.items() if k not in ("name", "e_E", "ms")}
        print(f"{r['name']:<58} {r['e_E']:>7.3f} {r['ms']:>8.1f}  {extra if extra else ''}")
    if args.json is not None:
        write_json(args.json, dict(rows=rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
