"""Photometric error and end-point error on the shared KITTI 2015 pair 000000 (not a speed test).

Prints, for no motion, the ground truth (flow_noc_10.png), the ground truth with its holes filled
(each invalid pixel takes the flow of the nearest valid one: the truth is sparse, and a census or
SSIM window around a valid pixel otherwise warps its invalid neighbours by a flow of 0) and OpenCV
DIS (PRESET_MEDIUM on grey images from cv2.cvtColor), the photometric error of each kind (L1, SSIM, census distance, soft
census) over several pixel sets, with pixel counts (each kind's: the windowed kinds count fewer
pixels near the border and where the flow leaves the image), and DIS's end-point error against
the ground truth. The KITTI data is read from ../shared/data (not part of the repository).

Run: python benchmarks/kitti_photometric.py [--data ../shared/data/kitti15_000000]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from fsof_torch.evaluation.metrics import flow_metrics
from fsof_torch.evaluation.photometric import photometric_errors

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti15_000000"
NEED = ("flow_noc_10.png", "road.json", "image_10.png", "image_11.png")


def read_pair(folder: Path):
    from fsof_torch.io import read_image, read_kitti_flow, read_road_mask

    flow, valid = read_kitti_flow(folder / "flow_noc_10.png")
    road = read_road_mask(folder / "road.json", size=tuple(flow.shape[-2:]))
    image1, image2 = (read_image(folder / name)[None] for name in ("image_10.png", "image_11.png"))
    return image1, image2, flow[None], valid[None], road[None]


def filled(flow: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(1, 2, H, W) flow with every invalid pixel given the flow of its nearest valid pixel."""
    from scipy.ndimage import distance_transform_edt

    _, (iy, ix) = distance_transform_edt(~valid[0, 0].numpy(), return_indices=True)
    return flow[..., torch.from_numpy(iy), torch.from_numpy(ix)]


def dis_flow(folder: Path) -> torch.Tensor:
    import cv2

    g1 = cv2.cvtColor(cv2.imread(str(folder / "image_10.png")), cv2.COLOR_BGR2GRAY)
    g2 = cv2.cvtColor(cv2.imread(str(folder / "image_11.png")), cv2.COLOR_BGR2GRAY)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return torch.from_numpy(dis.calc(g1, g2, None)).permute(2, 0, 1)[None]


def main(argv=None) -> int:
    from cli import data_folder, description, present, readable_pair

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="the KITTI 2015 pair's folder (default: ../shared/data/kitti15_000000)")
    args = parser.parse_args(argv)
    args.data = data_folder(parser, args.data, DEFAULT, NEED)
    if not present(args.data, NEED, "KITTI pair kitti15_000000"):
        return 0
    readable_pair(parser, args.data)
    torch.set_num_threads(1)
    i1, i2, gt, valid, road = read_pair(args.data)
    flows = {"zero": torch.zeros_like(gt), "ground truth": gt, "truth, filled": filled(gt, valid),
             "DIS medium": dis_flow(args.data)}
    H, W = valid.shape[-2:]
    print(f"valid ground-truth pixels: {int(valid.sum())} of {H * W} ({float(valid.float().mean()):.2%}); "
          f"road polygon: {int(road.sum())} px, of which valid: {int((road & valid).sum())}")
    sets = {"all pixels": None, "valid": valid, "road": road, "road & valid": road & valid}
    kinds = ("l1", "ssim", "census", "soft_census")
    print(f"{'flow':>13} {'pixels':>13} {'l1 (0-255)':>11} {'ssim':>7} {'census':>7} {'soft census':>11} "
          f"{'l1 count':>8} {'census count':>12}")
    for fname, flow in flows.items():
        for sname, mask in sets.items():
            if fname in ("ground truth", "truth, filled") and sname in ("all pixels", "road"):
                continue   # the ground truth is defined on its valid pixels only
            e = photometric_errors(i1, i2, flow, mask, kinds=kinds, return_count=True)
            print(f"{fname:>13} {sname:>13} {float(e['l1'][0]):>11.3f} {float(e['ssim'][0]):>7.4f} "
                  f"{float(e['census'][0]):>7.4f} {float(e['soft_census'][0]):>11.4f} {int(e['l1'][1]):>8} "
                  f"{int(e['census'][1]):>12}")
    for sname, mask in (("valid", None), ("road & valid", road)):
        m = flow_metrics(flows["DIS medium"], gt, mask, valid)
        print(f"DIS vs ground truth, {sname}: e_E {m['e_E']:.2f} px, e_A {m['e_A']:.4f} rad, "
              f"e_U {m['e_U']:.2f}, e_V {m['e_V']:.2f}, Fl {m['Fl']:.2%}, n {m['n_pixels']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
