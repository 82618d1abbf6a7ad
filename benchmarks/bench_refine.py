"""Speed of the refinement step at KITTI size (1242×375), one thread.

Times, as the median (and min) over rounds of repeats, each after a warm-up, and the minor page
faults per timed call (fresh memory from the system):

- model + fusion with odometry given (``FreespaceRefiner`` with ``odometry``);
- the full step without odometry: fit (``fit_displacement``) + model + fusion;
- the same in ``confidence`` mode;
- the parts alone: ``fit_displacement``, ``displacement_flow``, ``fuse_flow``;
- a RAFT-style output (12 iterations, refined level by level) with odometry;
- reference, in the same run: OpenCV DIS (PRESET_MEDIUM) on the same pair of grey images.

``--baseline REV`` (default 09d064e, the flat package before the road-model family and the one
solver; ``none`` to skip) adds a second table: the refinement step with odometry given and with
the fitted ego-motion (``FreespaceRefiner(fit="flow")``), that revision's (imported beside the
current package by ``baseline.py``) against the current one's, interleaved call by call over
the rounds so that both see the same load, with their ratio.

The flow is the model flow of a known motion plus 1 px Gaussian noise, and a box of the road
mask (rows 220–299, columns 700–999: 15 838 pixels, 12 % of the mask) replaced by an obstacle's
flow (outliers for the robust fit); the road mask holds 133 822 pixels. Run:
``python benchmarks/bench_refine.py [--repeats N] [--rounds R] [--json PATH] [--baseline REV]``.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time
from pathlib import Path

import torch


def _time_rounds(cases: dict, repeats: int, rounds: int = 3, warmup: int = 2) -> dict[str, dict[str, float]]:
    """Median and min per case over ``rounds`` × ``repeats`` timings: in each round every case
    runs ``warmup`` + ``repeats`` times in a row (its steady state, as in a pipeline that calls
    it frame after frame), the rounds spreading the shared machine's slow spells over all
    cases. (Taking turns call by call would charge each case the page faults of the previous
    one's buffers: the allocator hands large blocks back to the system between them.)"""
    samples: dict[str, list[float]] = {name: [] for name in cases}
    faults = dict.fromkeys(cases, 0)
    for _ in range(rounds):
        for name, fn in cases.items():
            for _ in range(warmup):
                fn()
            faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            for _ in range(repeats):
                t0 = time.perf_counter()
                fn()
                samples[name].append((time.perf_counter() - t0) * 1e3)
            faults[name] += resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0
    return {name: {"median_ms": statistics.median(x), "min_ms": min(x), "repeats": len(x),
                   "page_faults_per_call": faults[name] / len(x)} for name, x in samples.items()}


def _time_interleaved(pairs: dict, repeats: int, rounds: int, warmup: int = 2) -> dict[str, dict[str, float]]:
    """Median and min per case of ``pairs`` ({name: (baseline fn, current fn)}): within a round
    each case's two versions take turns call by call (``warmup`` turns untimed)."""
    samples: dict[str, list[float]] = {}
    for _ in range(rounds):
        for name, fns in pairs.items():
            for _ in range(warmup):
                for fn in fns:
                    fn()
            for _ in range(repeats):
                for label, fn in zip(("baseline", "current"), fns):
                    t0 = time.perf_counter()
                    fn()
                    samples.setdefault(f"{name}|{label}", []).append((time.perf_counter() - t0) * 1e3)
    return {key: {"median_ms": statistics.median(x), "min_ms": min(x), "repeats": len(x)}
            for key, x in samples.items()}


def baseline_table(rev: str, case: tuple, repeats: int, rounds: int) -> dict:
    """The refinement step of git revision ``rev`` against the current one (interleaved)."""
    from baseline import load_baseline

    from fsof_torch.refinement.fusion import FreespaceRefiner

    base = load_baseline(rev)
    camera, odo, flow, mask, _ = case
    base_camera = base.Camera(camera.K, camera.height, camera.roll, camera.pitch)
    current = FreespaceRefiner(fit="flow", warn=False)
    before = base.FreespaceRefiner(fit="flow", warn=False)
    pairs = {
        "refine, odometry given (model + fusion)": (lambda: before(flow, mask, base_camera, odo),
                                                    lambda: current(flow, mask, camera, odo)),
        "refine, fitted ego-motion (fit='flow')": (lambda: before(flow, mask, base_camera),
                                                   lambda: current(flow, mask, camera)),
    }
    with torch.no_grad():
        results = _time_interleaved(pairs, repeats, rounds)
        z_before = float(before(flow, mask, base_camera).odometry["z_d"][0])
        z_now = float(current(flow, mask, camera).odometry["z_d"][0])
    width = max(len(n) for n in pairs)
    print(f"\nagainst revision {rev} (interleaved call by call, median of {rounds} x {repeats} each)")
    print(f"{'case':<{width}}  baseline median / min ms  current median / min ms  ratio median / min")
    for name in pairs:
        a, b = results[f"{name}|baseline"], results[f"{name}|current"]
        print(f"{name:<{width}}  {a['median_ms']:14.2f} / {a['min_ms']:6.2f}  {b['median_ms']:13.2f} / "
              f"{b['min_ms']:6.2f}  {b['median_ms'] / a['median_ms']:11.3f} / {b['min_ms'] / a['min_ms']:.3f}")
    print(f"(fitted z_d: baseline {z_before:.6f} m, current {z_now:.6f} m)")
    return results


def build_case(dtype: torch.dtype = torch.float32):
    from fsof_torch.geometry.camera import Camera
    from fsof_torch.geometry.road_flow import displacement_flow

    H, W = 375, 1242
    K = torch.tensor([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]], dtype=torch.float64)
    camera = Camera(K, 1.65, roll=0.01, pitch=-0.015)
    odo = {"x_d": 0.02, "z_d": 1.0, "yaw": 0.01}
    gt, valid = displacement_flow(camera, odo["x_d"], odo["z_d"], odo["yaw"], (H, W))
    g = torch.Generator().manual_seed(0)
    flow = (gt + torch.randn(gt.shape, generator=g, dtype=gt.dtype)).to(dtype)
    rows = torch.arange(H).reshape(1, 1, H, 1)
    cols = torch.arange(W).reshape(1, 1, 1, W)
    # a trapezoid of road in front of the car, 133 822 pixels
    half = (rows - 190).clamp(min=0) * 3.3 + 60
    mask = valid & (rows >= 190) & ((cols - 610).abs() <= half)
    car = mask & (rows >= 220) & (rows < 300) & (cols >= 700) & (cols < 1000)
    flow = torch.where(car, flow + torch.tensor([12.0, -3.0], dtype=dtype).reshape(1, 2, 1, 1), flow)
    return camera, odo, flow, mask, (H, W)


def main(argv: list[str] | None = None) -> int:
    from baseline import DEFAULT_BASELINE
    from cli import baseline_revision, description, json_path, positive_int, write_json

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--repeats", type=positive_int, default=15, help="timed calls per case and round (default 15)")
    parser.add_argument("--rounds", type=positive_int, default=3, help="rounds over all cases (default 3)")
    parser.add_argument("--json", type=Path, default=None, metavar="PATH",
                        help="write the results as JSON here (an earlier file there is removed at the start)")
    parser.add_argument("--baseline", type=str, default=None, metavar="REV",
                        help="a git revision to time against the current version (interleaved; default "
                             f"{DEFAULT_BASELINE}, left out where git or it is unavailable); 'none' to skip")
    args = parser.parse_args(argv)
    args.baseline = baseline_revision(parser, args.baseline, DEFAULT_BASELINE)
    args.json = json_path(parser, args.json)
    torch.set_num_threads(1)

    import cv2
    import numpy as np

    from fsof_torch.estimation.flow_fit import fit_displacement
    from fsof_torch.geometry.road_flow import displacement_flow
    from fsof_torch.refinement.fusion import FreespaceRefiner, fuse_flow

    cv2.setNumThreads(1)
    camera, odo, flow, mask, size = build_case()
    camera32 = camera.to(torch.float32)  # the refiner computes in the prediction's dtype
    refiner = FreespaceRefiner(warn=False)
    confidence = FreespaceRefiner(mode="confidence", warn=False)
    model, mvalid = displacement_flow(camera, odo["x_d"], odo["z_d"], odo["yaw"], size)
    raft = [flow] * 12
    g = np.random.default_rng(0)
    grey1 = (g.random(size) * 255).astype(np.uint8)
    grey1 = cv2.GaussianBlur(grey1, (0, 0), 2.0)
    grey2 = np.roll(grey1, 3, axis=1)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)

    cases = {
        "refine, odometry given (model + fusion)": lambda: refiner(flow, mask, camera, odo),
        "refine, fitted odometry (fit + model + fusion)": lambda: refiner(flow, mask, camera),
        "refine confidence, fitted odometry": lambda: confidence(flow, mask, camera),
        "  fit_displacement alone (float32, as in the refiner)": lambda: fit_displacement(flow, mask, camera32,
                                                                                          fit_roll=False),
        "  displacement_flow alone": lambda: displacement_flow(camera, odo["x_d"], odo["z_d"], odo["yaw"], size),
        "  fuse_flow alone (replace)": lambda: fuse_flow(flow, model, mask & mvalid),
        "refine RAFT list of 12, odometry given": lambda: refiner(raft, mask, camera, odo),
        "reference: OpenCV DIS medium (same size)": lambda: dis.calc(grey1, grey2, None),
    }
    with torch.no_grad():
        results = _time_rounds(cases, args.repeats, args.rounds)
    fitted = refiner(flow, mask, camera)
    width = max(len(n) for n in results)
    print(f"refinement step at {size[1]}x{size[0]}, {int(mask.sum())} road pixels, 1 thread, "
          f"median of {args.rounds} x {args.repeats} (torch {torch.__version__})")
    print(f"{'case':<{width}}  median ms  min ms  page faults/call")
    for name, r in results.items():
        print(f"{name:<{width}}  {r['median_ms']:9.2f}  {r['min_ms']:6.2f}  {r['page_faults_per_call']:16.0f}")
    print(f"(fitted z_d {float(fitted.odometry['z_d'][0]):.4f} m for a true {odo['z_d']}; target for the full "
          f"step: <= 15 ms)")
    report = {"size": list(size), "road_pixels": int(mask.sum()), "threads": 1, "torch": torch.__version__,
              "results": results, "baseline": args.baseline or "none", "against_baseline": None}
    if args.json is not None:  # (before the baseline's table, which may fail to import that revision)
        write_json(args.json, report)
    if args.baseline is not None:
        report["against_baseline"] = baseline_table(args.baseline, (camera, odo, flow, mask, size), args.repeats,
                                                    args.rounds)
        if args.json is not None:
            write_json(args.json, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
