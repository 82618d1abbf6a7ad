"""Speed and size of the test net (fsof_torch.training.testnet.TinyRAFT) on the CPU, one thread.

    python benchmarks/bench_testnet.py [--repeats 5] [--iters 6]

Prints the parameter count and, per image size, the median forward time (no gradient) over
``--repeats`` runs after one warm-up: wall-clock and CPU time of this process (on a shared,
loaded machine the CPU time is the steadier figure), and the CPU time with ``final_only=True``
(only the last iteration upsampled, as the refine job runs it). Reference in the same run: one
3x3 convolution 3 -> 64 channels at full resolution (a fixed unit of work to compare machines by),
and the forward pass's wall time in units of it (``x ref conv``).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from fsof_torch.training.testnet import TinyRAFT, count_parameters

SIZES = [(128, 416), (375, 1242)]


def _median_times(fn, repeats: int) -> tuple[float, float]:
    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return 1e3 * statistics.median(wall), 1e3 * statistics.median(cpu)


def main(argv: list[str] | None = None) -> int:
    from cli import description, positive_int

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--repeats", type=positive_int, default=5, help="timed forward passes per row (default 5)")
    parser.add_argument("--iters", type=positive_int, default=6, help="GRU iterations (TinyRAFT's default: 6)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    net = TinyRAFT(seed=0, iters=args.iters).eval()
    print(f"TinyRAFT: {count_parameters(net)} parameters, {args.iters} iterations, torch {torch.__version__}, "
          f"1 thread")
    print(f"{'input':<16} {'forward wall ms':>16} {'forward CPU ms':>15} {'final_only CPU ms':>18} "
          f"{'ref conv wall ms':>17} {'x ref conv':>11}")
    g = torch.Generator().manual_seed(0)
    for H, W in SIZES:
        image1 = torch.rand(1, 3, H, W, generator=g) * 255
        image2 = torch.rand(1, 3, H, W, generator=g) * 255
        conv = torch.nn.Conv2d(3, 64, 3, padding=1)
        with torch.no_grad():
            wall, cpu = _median_times(lambda: net(image1, image2), args.repeats)
            _, cpu_final = _median_times(lambda: net(image1, image2, final_only=True), args.repeats)
            ref, _ = _median_times(lambda: conv(image1), args.repeats)
        print(f"1x3x{H}x{W:<8} {wall:>16.1f} {cpu:>15.1f} {cpu_final:>18.1f} {ref:>17.1f} {wall / ref:>11.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
