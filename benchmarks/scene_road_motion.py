"""Road motion of the synthetic scenes beyond the paper's model: body-motion statistics per frame,
and how far the road flow of a crest or a dip is from a single homography.

1. Body motion (preset ``body-motion``): per-frame changes of the camera's pitch, roll and height
   over the road (``road_pose`` of consecutive pairs), over ``--frames`` frames of ``--seeds``
   seeds, beside the closed-form mean of a sampled sinusoid, (4/π) a sin(π f dt), and the KITTI
   odometry figures of DESIGN.md §10.
2. Crest and dip (presets ``crest``, ``dip``; the body-motion preset as a control): on the valid
   road pixels of pairs rendered at 375 × 1242 in float64, the end-point error (px) of
   (a) the homography of the exported ``plane`` motion (the tangent plane under the vehicle at t:
   K (R + t nᵀ / h) K⁻¹) and (b) the best homography through the ground-truth correspondences
   p -> p + flow (OpenCV ``findHomography``, method 0: least squares on all points), per row band:
   near (the 60 lowest image rows), middle, far (the 30 road rows nearest the horizon).

    python benchmarks/scene_road_motion.py [--frames 100] [--seeds 5] [--pairs 0 30]
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

KITTI = {"pitch": "0.085 (max 0.28)", "roll": "0.09", "height": "about 1"}


def body_motion_statistics(frames: int, seeds: int) -> None:
    from fsof_torch.data.scene import render_sequence, scene_config

    cfg = scene_config("body-motion")
    changes = {"pitch": [], "roll": [], "height": []}
    ranges = {"pitch": [], "roll": [], "height": []}
    for seed in range(seeds):
        # road_pose does not depend on the image size: render tiny images
        pairs = render_sequence("body-motion", frames, seed=seed, size=(8, 24))
        for key in changes:
            x = np.array([p["road_pose"][key] for p in pairs])
            changes[key].append(np.abs(np.diff(x)))
            ranges[key].append(x)
    scale = {"pitch": 180 / math.pi, "roll": 180 / math.pi, "height": 100.0}
    unit = {"pitch": "deg", "roll": "deg", "height": "cm"}
    amp = {"pitch": cfg.body_pitch, "roll": cfg.body_roll, "height": cfg.body_height}
    hz = {"pitch": cfg.body_pitch_hz, "roll": cfg.body_roll_hz, "height": cfg.body_height_hz}
    mount = {"pitch": cfg.pitch, "roll": cfg.roll, "height": cfg.height}
    print(f"body motion, preset 'body-motion', dt = {cfg.dt} s, {seeds} seeds x {frames} frames")
    print("| quantity | amplitude | frequency (Hz) | range over the clips | mean per-frame change "
          "| max per-frame change | (4/π) a sin(π f dt) | KITTI (DESIGN.md §10) |")
    print("|---|---|---|---|---|---|---|---|")
    for key in changes:
        d = np.concatenate(changes[key]) * scale[key]
        x = (np.concatenate(ranges[key]) - mount[key]) * scale[key]
        expected = 4 / math.pi * amp[key] * math.sin(math.pi * hz[key] * cfg.dt) * scale[key]
        print(f"| {key} ({unit[key]}) | ±{amp[key] * scale[key]:.3g} | {hz[key]} | {x.min():+.3f} .. {x.max():+.3f} "
              f"| {d.mean():.4f} | {d.max():.4f} | {expected:.4f} | {KITTI[key]} |")


def _grid(H: int, W: int) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.stack([u, v], axis=-1)


def _apply_homography(Hm: np.ndarray, pts: np.ndarray) -> np.ndarray:
    q = np.concatenate([pts, np.ones((len(pts), 1))], axis=1) @ Hm.T
    return q[:, :2] / q[:, 2:]


def plane_homography(pair: dict) -> np.ndarray:
    """K (R + t nᵀ / h) K⁻¹ from the exported ``plane`` values (DESIGN.md §10)."""
    from fsof_torch.geometry.camera import pitch_matrix, roll_matrix

    pl = pair["plane"]

    def rot(fn, angle):
        return fn(torch.tensor([angle], dtype=torch.float64))[0].numpy()

    c, s = math.cos(pl["yaw"]), math.sin(pl["yaw"])
    R_yaw = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
    Rc = rot(roll_matrix, pl["roll"]) @ rot(pitch_matrix, pl["pitch"])
    Rv = rot(roll_matrix, pl["roll_change"]) @ rot(pitch_matrix, pl["pitch_change"]) @ R_yaw
    d = np.array([pl["x_d"], pl["y_d"], pl["z_d"]])
    R, t = Rc @ Rv @ Rc.T, -Rc @ Rv @ d
    n = Rc @ np.array([0.0, 1.0, 0.0])
    K = pair["camera"].K[0].double().numpy()
    return K @ (R + np.outer(t, n) / pl["height"]) @ np.linalg.inv(K)


def homography_mismatch(presets: list[str], indices: list[int]) -> None:
    import cv2

    from fsof_torch.data.scene import KITTI_SIZE, render_pair

    H, W = KITTI_SIZE
    print(f"\nroad flow against homographies, {H}x{W}, float64, end-point error in px (mean / max) per row band")
    print("| preset | pair | band (rows) | road pixels | depth (m) | exported plane at t | best homography (cv2, method 0) |")
    print("|---|---|---|---|---|---|---|")
    for name in presets:
        for index in indices:
            pair = render_pair(name, index, size=(H, W), dtype=torch.float64)
            mask = (pair["road"] & pair["valid"])[0].numpy()
            flow = pair["flow"].permute(1, 2, 0).numpy()
            pix = _grid(H, W)
            src, dst = pix[mask], (pix + flow)[mask]
            best, _ = cv2.findHomography(src, dst, 0)
            err_plane = np.linalg.norm(_apply_homography(plane_homography(pair), src) - dst, axis=1)
            err_best = np.linalg.norm(_apply_homography(best, src) - dst, axis=1)
            rows = pix[mask][:, 1]
            depth = pair["depth"][0].numpy()[mask]
            top = np.sort(np.unique(rows))[:30].max()
            bands = (("far", rows <= top, f"{int(rows.min())}-{int(top)}"),
                     ("middle", (rows > top) & (rows < H - 60), f"{int(top) + 1}-{H - 61}"),
                     ("near", rows >= H - 60, f"{H - 60}-{H - 1}"))
            for band, sel, span in bands:
                if not sel.any():
                    continue
                print(f"| {name} | {index} | {band} ({span}) | {int(sel.sum())} | {depth[sel].min():.1f}-{depth[sel].max():.1f} "
                      f"| {err_plane[sel].mean():.3g} / {err_plane[sel].max():.3g} "
                      f"| {err_best[sel].mean():.3g} / {err_best[sel].max():.3g} |")


def main(argv: list[str] | None = None) -> int:
    from cli import description, pair_count, pair_index, positive_int

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--frames", type=pair_count(2), default=100,
                        help="frames per seed for the body-motion statistics (default 100; at least 2)")
    parser.add_argument("--seeds", type=positive_int, default=5,
                        help="seeds for the body-motion statistics (default 5)")
    parser.add_argument("--pairs", type=pair_index, nargs="+", default=[0, 30],
                        help="pair indices of the crest and dip")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    body_motion_statistics(args.frames, args.seeds)
    homography_mismatch(["crest", "dip", "body-motion"], args.pairs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
