"""Speed of the photometric error kinds at KITTI's size, against the warp they start from (reference).

Prints, single thread, warm-up, median of repeats, milliseconds: ``warp_backward`` alone, each kind
of ``photometric_error_map`` (the warp included), and ``photometric_error_maps`` with L1, SSIM and
census at once (one warp), each with its ratio to the warp. No gradient (evaluation).

Run: python benchmarks/bench_photometric.py
"""

from __future__ import annotations

import statistics
import time

import torch

from fsof_torch.evaluation.photometric import photometric_error_map, photometric_error_maps
from fsof_torch.evaluation.warp import warp_backward


def median_ms(fn, repeats=7, warmup=2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def main() -> int:
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    B, H, W = 1, 375, 1242
    image1 = torch.rand(B, 3, H, W, generator=g) * 255
    image2 = torch.rand(B, 3, H, W, generator=g) * 255
    flow = torch.randn(B, 2, H, W, generator=g) * 3
    with torch.no_grad():
        ref = median_ms(lambda: warp_backward(image2, flow))
        rows = [("warp_backward", ref)]
        for kind in ("l1", "ssim", "census", "soft_census"):
            rows.append((f"kind={kind!r}", median_ms(lambda: photometric_error_map(image1, image2, flow, kind=kind))))
        rows.append(("l1+ssim+census", median_ms(lambda: photometric_error_maps(image1, image2, flow))))
    print(f"{B}x3x{H}x{W}, one thread, no gradient")
    print(f"{'what':>22} {'ms':>9} {'/ warp':>7}")
    for name, ms in rows:
        print(f"{name:>22} {ms:>9.1f} {ms / ref:>7.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
