"""How realistic is the ``default`` scene preset? Road texture statistics and DIS road error,
real KITTI samples (``../shared/data`` or ``--data``) against rendered pairs.

Texture statistics on grey images (OpenCV RGB→grey, float) inside the road: the polygon of each
sample's road.json (real), the ``road`` label without paint (rendered), both eroded by 7×7 px.
Per row band (far 190–229, mid 230–299, near 300–369 at 375 rows): median grey; std after
subtracting each row's median (shading ramps are not texture); band-pass std of I − G1,
G1 − G2, G2 − G4 (Gaussian blurs of σ 1, 2, 4 px); median Sobel gradient magnitude. Stds are
robust: values within 4 robust σ (1.4826 MAD) of the median, so lane paint and specks do not
count. Real: the median over frames of each source (KITTI flow 000000 frames 10 and 11; odometry
frames 0, 10, 20, 30), and their mean. Rendered: the median over pairs 0, 3, 6, 9 (image1).

DIS (OpenCV PRESET_MEDIUM, grey) end-point error on road pixels with ground truth: KITTI flow
000000 inside road.json, rendered pairs 0–9 of ``render_sequence`` (the default, without its
noise, at the old speed, and the old default). Road photometric error (l1) of the DIS flow and of
the ground truth on pairs 0–3, without sensor noise (the default) and with SENSOR_NOISE.

    python benchmarks/scene_realism.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

BANDS = (("far", 190, 230), ("mid", 230, 300), ("near", 300, 370))
STATS = (("mean", "median grey"), ("std", "std, row-detrended"), ("b1", "band-pass I − G1"),
         ("b2", "band-pass G1 − G2"), ("b4", "band-pass G2 − G4"), ("grad", "median gradient magnitude"))
OLD_DEFAULT = dict(speed=8.0, asphalt=None, noise=0.0)  # the default preset before it was made realistic
DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data"
KITTI15 = ("kitti15_000000", ("image_10.png", "image_11.png", "road.json", "flow_noc_10.png"))
CLIP = ("kitti_odometry_straight", ("road.json", *(f"image_l/{i:06d}.png" for i in (0, 10, 20, 30))))


def _robust_std(x: np.ndarray) -> float:
    med = np.median(x)
    r = 1.4826 * np.median(np.abs(x - med))
    return float(np.std(x[np.abs(x - med) < 4 * max(r, 1e-6)]))


def road_statistics(grey: np.ndarray, mask: np.ndarray) -> dict:
    """Statistics per row band of a float grey image (H, W) inside a bool mask (H, W)."""
    import cv2

    grey = grey.astype(np.float64)
    mask = cv2.erode(mask.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    g1, g2, g4 = (cv2.GaussianBlur(grey, (0, 0), s) for s in (1.0, 2.0, 4.0))
    bands = {"b1": grey - g1, "b2": g1 - g2, "b4": g2 - g4}
    grad = np.hypot(cv2.Sobel(grey, cv2.CV_64F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_64F, 0, 1, ksize=3)) / 8
    out = {}
    for name, top, bottom in BANDS:
        m = mask.copy()
        m[:top] = False
        m[bottom:] = False
        if m.sum() < 200:
            continue
        rows = [grey[r, m[r]] - np.median(grey[r, m[r]]) for r in range(top, bottom) if m[r].sum() > 5]
        out[name] = {"mean": float(np.median(grey[m])), "std": _robust_std(np.concatenate(rows)),
                     **{k: _robust_std(v[m]) for k, v in bands.items()}, "grad": float(np.median(grad[m]))}
    return out


def _median(results: list[dict]) -> dict:
    return {b: {q: float(np.median([r[b][q] for r in results if b in r])) for q, _ in STATS} for b, _, _ in BANDS}


def _polygon(path: Path, shape: tuple) -> np.ndarray:
    """A road.json's mask (H, W) bool at the frame's ``shape``, as the library reads it (any of its
    polygon formats, drawn for the frame's size; the same pixels as the samples' own polygons filled
    by ``cv2.fillPoly``); a file it cannot read, or one drawn for another size, is a ValueError
    naming it."""
    from fsof_torch.io import read_road_mask

    return read_road_mask(path, size=tuple(shape))[0].numpy()


def _grey(image: torch.Tensor, *, uint8: bool = False) -> np.ndarray:
    import cv2

    rgb = np.ascontiguousarray(image.permute(1, 2, 0).numpy().clip(0, 255).round())
    return cv2.cvtColor(rgb.astype(np.uint8 if uint8 else np.float32), cv2.COLOR_RGB2GRAY)


def _dis(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(a, b, None)


def main(argv: list[str] | None = None) -> int:
    from cli import description, present, samples_folder

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="the folder that holds kitti15_000000/ and kitti_odometry_straight/, at least one "
                             "(default: ../shared/data beside the repository, where both may be absent)")
    args = parser.parse_args(argv)
    data = samples_folder(parser, args.data, DEFAULT, dict([KITTI15, CLIP]))
    torch.set_num_threads(1)
    import cv2

    cv2.setNumThreads(1)
    from fsof_torch.io import read_kitti_flow, read_road_mask
    from fsof_torch.data.scene import SENSOR_NOISE, render_pair, render_sequence

    k15, odo = data / KITTI15[0], data / CLIP[0]
    has_k15 = present(k15, KITTI15[1], f"KITTI pair {KITTI15[0]}")
    has_odo = present(odo, CLIP[1], f"KITTI clip {CLIP[0]}")
    columns = {}

    def read(path: Path, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
        image = cv2.imread(str(path), flags)
        if image is None:
            parser.error(f"--data: OpenCV cannot read {str(path)!r} as an image")
        return image

    try:  # (a road.json the library cannot read: exit 2 naming it, before the rendering)
        if has_k15:
            real15 = []
            for f in ("image_10.png", "image_11.png"):
                g = cv2.cvtColor(read(k15 / f).astype(np.float32), cv2.COLOR_BGR2GRAY)
                real15.append(road_statistics(g, _polygon(k15 / "road.json", g.shape)))
            columns["KITTI flow 000000"] = _median(real15)
        if has_odo:
            real_odo = []
            for i in (0, 10, 20, 30):
                g = read(odo / "image_l" / f"{i:06d}.png", cv2.IMREAD_GRAYSCALE).astype(np.float32)
                real_odo.append(road_statistics(g, _polygon(odo / "road.json", g.shape)))
            columns["KITTI odometry clip"] = _median(real_odo)
    except ValueError as err:
        parser.error(f"--data: {err}")
    if has_k15 and has_odo:
        both = (columns["KITTI flow 000000"], columns["KITTI odometry clip"])
        columns["real (mean of the two)"] = {b: {q: (both[0][b][q] + both[1][b][q]) / 2 for q, _ in STATS}
                                             for b, _, _ in BANDS}
    for name, kw in (("rendered default", {}), ("rendered default + sensor noise", dict(noise=SENSOR_NOISE)),
                     ("rendered old default", OLD_DEFAULT)):
        rendered = []
        for k in (0, 3, 6, 9):
            p = render_pair("default", k, **kw)
            rendered.append(road_statistics(_grey(p["image1"]), (p["labels"] == 1).numpy()))
        columns[name] = _median(rendered)
    print("| band (rows) | statistic | " + " | ".join(columns) + " |")
    print("|---" * (2 + len(columns)) + "|")
    for b, top, bottom in BANDS:
        for q, label in STATS:
            print(f"| {b} ({top}–{bottom - 1}) | {label} | " + " | ".join(f"{c[b][q]:.2f}" for c in columns.values()) + " |")

    print("\nDIS medium road end-point error\n| data | mean px | median px | mean road GT flow px |\n|---|---|---|---|")
    if has_k15:
        a, b = (cv2.cvtColor(cv2.imread(str(k15 / f)), cv2.COLOR_BGR2GRAY) for f in ("image_10.png", "image_11.png"))
        gt, valid = read_kitti_flow(k15 / "flow_noc_10.png")
        m = (valid & read_road_mask(k15 / "road.json", size=a.shape))[0].numpy()
        gt = gt.permute(1, 2, 0).numpy()
        e = np.linalg.norm(_dis(a, b) - gt, axis=2)[m]
        print(f"| KITTI flow 000000 | {e.mean():.2f} | {np.median(e):.2f} | {np.linalg.norm(gt, axis=2)[m].mean():.2f} |")
    cases = (("default, pairs 0–9", {}), (f"default with noise={SENSOR_NOISE}", dict(noise=SENSOR_NOISE)),
             ("default with speed=8.0", dict(speed=8.0)), ("old default, pairs 0–9", OLD_DEFAULT))
    for name, kw in cases:
        errs, mags = [], []
        for p in render_sequence("default", 10, **kw):
            g = p["flow"].permute(1, 2, 0).numpy()
            mm = (p["road"][0] & p["valid"][0]).numpy()
            errs.append(np.linalg.norm(_dis(_grey(p["image1"], uint8=True), _grey(p["image2"], uint8=True)) - g, axis=2)[mm])
            mags.append(np.linalg.norm(g, axis=2)[mm])
        e = np.concatenate(errs)
        print(f"| {name} | {e.mean():.2f} | {np.median(e):.2f} | {np.concatenate(mags).mean():.2f} |")

    # the noise floor of the photometric error: DIS and the ground truth warped, on the default
    # (noise-free) pairs and on the same pairs with sensor noise (DIS computed on each)
    from fsof_torch.evaluation.photometric import photometric_error

    rows = []
    for k in range(4):
        row = []
        for im in (render_pair("default", k), render_pair("default", k, noise=SENSOR_NOISE)):
            dis = torch.from_numpy(_dis(_grey(im["image1"], uint8=True), _grey(im["image2"], uint8=True))).permute(2, 0, 1)
            mask = (im["road"] & im["valid"])[None]
            row += [float(photometric_error(im["image1"][None], im["image2"][None], f[None], mask)[0])
                    for f in (dis, im["flow"])]
        rows.append(row)
    r = np.mean(rows, axis=0)
    print("\nroad photometric error (l1, 0..255), default pairs 0-3\n| images | DIS flow | GT flow | change |\n|---|---|---|---|")
    print(f"| default (no noise) | {r[0]:.3f} | {r[1]:.3f} | {100 * (r[1] / r[0] - 1):+.1f} % |")
    print(f"| same pairs, noise={SENSOR_NOISE} | {r[2]:.3f} | {r[3]:.3f} | {100 * (r[3] / r[2] - 1):+.1f} % |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
