"""Speed of the procedural scene renderer: one KITTI-sized (375 × 1242) pair with all ground truth.

Single thread, warm-up then repeats, median milliseconds of wall-clock and of process CPU time. The reference rows, measured in the same
run, are the closed-form road flow (``displacement_flow``) at the same size and OpenCV DIS
(PRESET_MEDIUM) on the rendered pair; ``x DIS`` is each row's CPU time over DIS's.

    python benchmarks/bench_scene.py [--repeats 5] [--size 375 1242]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch


def _median_ms(fn, repeats: int, warmup: int = 1) -> tuple[float, float]:
    """Median wall-clock and process-CPU milliseconds (on a shared machine the CPU time is the
    better estimate of the unloaded wall time of this single-threaded work)."""
    for _ in range(warmup):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append((time.perf_counter() - start) * 1e3)
        cpu.append((time.process_time() - start_cpu) * 1e3)
    return statistics.median(wall), statistics.median(cpu)


def main(argv: list[str] | None = None) -> int:
    from cli import MIN_SIDE, description, image_side, positive_int

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--repeats", type=positive_int, default=5, help="timed calls per row (default 5)")
    parser.add_argument("--size", type=image_side, nargs=2, default=(375, 1242), metavar=("H", "W"),
                        help=f"image size, each side {MIN_SIDE} to 16384 (default 375 1242)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    import numpy as np
    import cv2

    from fsof_torch.geometry.road_flow import displacement_flow
    from fsof_torch.data.scene import SENSOR_NOISE, render_pair

    size = tuple(args.size)
    rows = []
    cases = [
        ("render_pair default, float32, supersample 2 at edges (default)", dict(dtype=torch.float32)),
        ("render_pair default, float32, no supersampling", dict(dtype=torch.float32, supersample=1)),
        ("render_pair default, float64, supersample 2 at edges", dict(dtype=torch.float64)),
        ("render_pair cvc-simple, float32, supersample 2 at edges", dict(dtype=torch.float32, preset="cvc-simple")),
        ("render_pair body-motion, float32, supersample 2 at edges", dict(dtype=torch.float32, preset="body-motion")),
        ("render_pair crest, float32, supersample 2 at edges", dict(dtype=torch.float32, preset="crest")),
        ("render_pair dip, float32, supersample 2 at edges", dict(dtype=torch.float32, preset="dip")),
        ("render_pair default, float32, supersample 2 at every pixel", dict(dtype=torch.float32, adaptive=False)),
    ]
    for name, kw in cases:
        kw = dict(kw)
        preset = kw.pop("preset", "default")
        repeats = max(1, args.repeats // 2) if kw.get("adaptive") is False else args.repeats
        rows.append((name, _median_ms(lambda: render_pair(preset, 0, size=size, **kw), repeats)))

    pair = render_pair("default", 0, size=size)
    cam, odo = pair["camera"], pair["odometry"]
    rows.append(("reference: displacement_flow (closed form), float32",
                 _median_ms(lambda: displacement_flow(cam, odo["x_d"], odo["z_d"], odo["yaw"], size), args.repeats)))
    grey = [cv2.cvtColor(pair[k].permute(1, 2, 0).numpy().astype(np.uint8), cv2.COLOR_RGB2GRAY)
            for k in ("image1", "image2")]
    cv2.setNumThreads(1)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    rows.append(("reference: OpenCV DIS medium on the pair", _median_ms(lambda: dis.calc(grey[0], grey[1], None), args.repeats)))

    # quality of the default pair: photometric consistency of the ground truth and trackability
    from fsof_torch.evaluation.warp import warp_backward

    mask = (pair["road"] & pair["valid"])[0]

    def warp_mae(p: dict) -> tuple[float, float]:
        warped, _ = warp_backward(p["image2"][None], p["flow"][None], align_corners=True)
        return (float((warped[0] - p["image1"]).abs().mean(0)[mask].mean()),
                float((p["image2"] - p["image1"]).abs().mean(0)[mask].mean()))

    mae, mae_id = warp_mae(pair)
    # with sensor noise, independent per frame, that no flow warps away
    mae_noisy, mae_id_noisy = warp_mae(render_pair("default", 0, size=size, noise=SENSOR_NOISE))
    flow_dis = torch.from_numpy(dis.calc(grey[0], grey[1], None)).permute(2, 0, 1)
    epe = (flow_dis - pair["flow"]).norm(dim=0)
    valid = pair["valid"][0]

    width = max(len(r[0]) for r in rows)
    print(f"scene renderer, {size[0]}x{size[1]}, 1 thread, median of {args.repeats} (torch {torch.__version__})")
    dis_cpu = max(rows[-1][1][1], 1e-6)  # (DIS's CPU ms, the last row)
    print(f"{'case'.ljust(width)}  wall ms   cpu ms    x DIS")
    for name, (wall, cpu) in rows:
        print(f"{name.ljust(width)}  {wall:7.1f}  {cpu:7.1f}  {cpu / dis_cpu:7.2f}")
    print(f"\ndefault pair 0 (seed 0): road pixels valid {int(mask.sum())}, mean |GT flow| on them "
          f"{float(pair['flow'].norm(dim=0)[mask].mean()):.2f} px")
    print(f"  mean |I1 - warp(I2, GT flow)| on valid road pixels: {mae:.3f} (no warp: {mae_id:.3f}); "
          f"with sensor noise (noise={SENSOR_NOISE}): {mae_noisy:.3f} (no warp: {mae_id_noisy:.3f})")
    print(f"  OpenCV DIS medium end-point error: road {float(epe[mask].mean()):.3f} px "
          f"(median {float(epe[mask].median()):.3f}), all valid pixels {float(epe[valid].mean()):.3f} px, "
          f"finite: {bool(torch.isfinite(flow_dis).all())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
