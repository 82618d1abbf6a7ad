"""Accuracy of the road-motion models fitted by ``fit_road``: real KITTI ground truth, the
renderer's body motion, and a graded road (crest, dip).

1. KITTI (``--data``, the shared pair kitti15_000000): each model fitted to the ground-truth flow
   inside road.json (``fit_road`` defaults; the paper's model also with its pitch free), and a
   general homography fitted by SciPy (``least_squares``, soft-L1, scale 1 px, every valid road
   pixel) as an independent reference. Column e_E: mean end-point error against the ground truth
   over the valid road pixels; ms: one call after a warm-up, single thread.
2. ``body-motion`` (a level road; the body pitches, rolls and heaves): the plane model fitted to
   the ground-truth road flow of pairs rendered in float64, started from the calibrated mounting;
   its end-point error, and how far its parameters are from the pair's exported ``plane`` motion
   (angles in rad, translations as d / h: the fit reports d under the camera's 1.65 m, the export
   under the body's height at t).
3. ``crest`` and ``dip``: the same fit on a graded road, which no plane describes: the end-point
   error of the best plane per row band — near (the 60 lowest image rows), middle, far (the 30
   road rows nearest the horizon) — over the road pixels where the fitted plane is defined, and
   the number of road pixels beyond the fitted plane's horizon (a dip's rising road: the plane
   has no flow there).

    python benchmarks/fit_road_models.py [--pairs 0 30] [--size 375 1242] [--skip-kitti]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti15_000000"
NEED = ("calib_cam_to_cam.txt", "flow_noc_10.png", "road.json")


def kitti_table(folder: Path) -> None:
    from scipy.optimize import least_squares

    from fsof_torch import Camera, fit_road
    from fsof_torch.io import read_kitti_flow, read_road_mask

    cam = Camera.from_kitti(folder / "calib_cam_to_cam.txt", cam=2, height=1.65)
    gt, valid = read_kitti_flow(folder / "flow_noc_10.png")
    road = read_road_mask(folder / "road.json", size=tuple(gt.shape[-2:]))
    gt, valid, road = gt[None].double(), valid[None], road[None]
    use = (road & valid)[:, 0]

    def e_E(flow: torch.Tensor) -> float:
        return float((flow - gt).norm(dim=1)[use].mean())

    rows = []
    for label, model, options in (("paper (x_d, z_d, yaw, roll)", "paper", {}),
                                  ("paper, pitch free too", "paper", dict(fixed=())),
                                  ("plane (6-DOF motion + roll, pitch)", "plane", {}),
                                  ("homography (8 entries)", "homography", {})):
        fit_road(gt, road, cam, model=model, valid=valid, **options)  # warm-up (lazy imports, caches)
        t = time.perf_counter()
        fit = fit_road(gt, road, cam, model=model, valid=valid, **options)
        ms = (time.perf_counter() - t) * 1e3
        params = ", ".join(f"{k} {float(v):+.5f}" for k, v in fit.params.items())
        rows.append((f"fit_road {label}", e_E(fit.flow), ms, bool(fit.success), params))

    # the reference: a general homography, least squares with SciPy's soft-L1 on every valid road
    # pixel, in calibrated coordinates (K⁻¹ H K = G, g33 = 1), from the identity
    v, u = np.nonzero(use[0].numpy())
    target = gt[0].numpy()[:, v, u]
    K = cam.K[0].numpy()
    Kinv = np.linalg.inv(K)
    p = np.stack([u, v, np.ones_like(u)]).astype(np.float64)

    def residual(g: np.ndarray) -> np.ndarray:
        Hm = K @ np.append(g, 1.0).reshape(3, 3) @ Kinv
        q = Hm @ p
        return (q[:2] / q[2] - p[:2] - target).ravel()

    t = time.perf_counter()
    sol = least_squares(residual, np.eye(3).ravel()[:8], loss="soft_l1", f_scale=1.0)
    ms = (time.perf_counter() - t) * 1e3
    err = np.linalg.norm(residual(sol.x).reshape(2, -1), axis=0).mean()
    rows.append(("SciPy least_squares homography, soft_l1 (reference)", float(err), ms, bool(sol.success), ""))

    print(f"KITTI 2015 training pair 000000: ground truth inside road.json, {int(use.sum())} valid pixels")
    print("| method | e_E (px) | ms | success | parameters |")
    print("|---|---|---|---|---|")
    for name, e, ms, ok, params in rows:
        print(f"| {name} | {e:.4f} | {ms:.0f} | {ok} | {params} |")


def _bands(mask: np.ndarray) -> list[tuple[str, np.ndarray, str]]:
    """The road's far band (its first 30 rows), its near band (the frame's last 60 rows) and the
    rows between, row counts at 375 rows scaled to the frame's height."""
    H = mask.shape[0]
    n_far, n_near = max(1, round(30 * H / 375)), max(1, round(60 * H / 375))
    rows = np.nonzero(mask)[0]
    top = min(np.sort(np.unique(rows))[:n_far].max(), H - n_near - 1)
    rr = np.arange(H)[:, None].repeat(mask.shape[1], 1)
    return [("far", mask & (rr <= top), f"{int(rows.min())}-{int(top)}"),
            ("middle", mask & (rr > top) & (rr < H - n_near), f"{int(top) + 1}-{H - n_near - 1}"),
            ("near", mask & (rr >= H - n_near), f"{H - n_near}-{H - 1}")]


def scene_tables(pairs: list[int], size: tuple[int, int]) -> None:
    from fsof_torch import fit_road, render_pair

    print(f"\nbody-motion: plane fit to the ground-truth road flow, {size[0]}x{size[1]}, float64")
    print("| pair | road pixels | mean / max EPE (px) | max angle error (rad) | max d/h error | ms |")
    print("|---|---|---|---|---|---|")
    for index in pairs:
        pair = render_pair("body-motion", index, size=size, dtype=torch.float64)
        flow, mask = pair["flow"][None], (pair["road"] & pair["valid"])[None]
        fit_road(flow, mask, pair["camera"], model="plane")  # warm-up (lazy imports, caches)
        t = time.perf_counter()
        fit = fit_road(flow, mask, pair["camera"], model="plane")
        ms = (time.perf_counter() - t) * 1e3
        err = (fit.flow - flow).norm(dim=1)[mask[:, 0]]
        truth = pair["plane"]
        angles = max(abs(float(fit.params[n]) - truth[n]) for n in ("pitch_change", "yaw", "roll_change", "roll", "pitch"))
        h = float(pair["camera"].height)
        moves = max(abs(float(fit.params[n]) / h - truth[n] / truth["height"]) for n in ("x_d", "y_d", "z_d"))
        print(f"| {index} | {int(mask.sum())} | {float(err.mean()):.2g} / {float(err.max()):.2g} | {angles:.2g} | "
              f"{moves:.2g} | {ms:.0f} |")

    print(f"\ncrest and dip: the best plane (fit_road model='plane') against the ground-truth road flow, "
          f"{size[0]}x{size[1]}, float64; bands of the road pixels where the fitted plane is defined")
    print("| preset | pair | band (rows) | road pixels | EPE mean / max (px) |")
    print("|---|---|---|---|---|")
    beyond = []
    for preset in ("crest", "dip"):
        for index in pairs:
            pair = render_pair(preset, index, size=size, dtype=torch.float64)
            flow, mask = pair["flow"][None], (pair["road"] & pair["valid"])[None]
            fit = fit_road(flow, mask, pair["camera"], model="plane")
            err = (fit.flow - flow).norm(dim=1)[0].numpy()
            m = mask[0, 0].numpy()
            defined = fit.valid[0, 0].numpy()
            beyond.append((preset, index, int((m & ~defined).sum()), int(m.sum()),
                           int(np.nonzero(m)[0].min()), int(np.nonzero(m & defined)[0].min())))
            for band, sel, span in _bands(m & defined):
                # (a band can hold no road pixel on small frames)
                errors = f"{err[sel].mean():.3g} / {err[sel].max():.3g}" if sel.any() else "–"
                print(f"| {preset} | {index} | {band} ({span}) | {int(sel.sum())} | {errors} |")
    for preset, index, n, total, top, top_defined in beyond:
        if n:
            print(f"{preset} pair {index}: {n} of {total} road pixels lie beyond the fitted plane's horizon "
                  f"(road from row {top}, the plane's flow from row {top_defined})")


def main(argv: list[str] | None = None) -> int:
    from cli import MIN_SIDE, data_folder, description, image_side, pair_index, present, readable_pair, reads_data

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="the KITTI 2015 pair's folder (default: ../shared/data/kitti15_000000)")
    parser.add_argument("--pairs", type=pair_index, nargs="+", default=[0, 30],
                        help="pair indices of the synthetic tables (default 0 30)")
    parser.add_argument("--size", type=image_side, nargs=2, default=[375, 1242], metavar=("H", "W"),
                        help=f"the synthetic pairs' size, each side {MIN_SIDE} to 16384 (default 375 1242)")
    parser.add_argument("--skip-kitti", action="store_true", help="leave out the KITTI table")
    args = parser.parse_args(argv)
    reads = reads_data(parser, args.data, args.skip_kitti, "--skip-kitti")
    data = data_folder(parser, args.data, DEFAULT, NEED) if reads else None
    torch.set_num_threads(1)
    if data is not None and present(data, NEED, "KITTI pair kitti15_000000 (the KITTI table)"):
        if all((data / f).is_file() for f in ("image_10.png", "image_11.png")):  # (the table reads no frames)
            readable_pair(parser, data)
        kitti_table(data)
    scene_tables(args.pairs, tuple(args.size))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
