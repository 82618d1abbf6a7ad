"""Speed of ``smooth_attitude`` (the attitude track of a clip of N pairs) against the dense solve
of the same normal equations, one thread.

``smooth_attitude`` solves its tridiagonal (N + 1) × (N + 1) system in O(N) (an LDLᵀ sweep, the
covariance's diagonal by a backward recursion). The reference, timed in the same run on the same
inputs, builds the matrix densely and inverts it with ``torch.linalg.inv`` (O(N³) time, O(N²)
memory: 800 MB for the matrix alone at N = 10 000). Prints the median time of each (a single run
of the dense solve where it takes over a second), their ratio, the dense matrix's size and the
largest differences between the two results.

    python benchmarks/bench_smooth_attitude.py [--sizes 100 1000 10000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch


def dense_smooth(attitude, change, attitude_sigma, change_sigma):
    """The same weighted least squares, its normal equations built densely and inverted."""
    N = attitude.shape[0]
    dt = torch.float64
    wa = 1.0 / attitude_sigma.to(dt).square()
    wc = 1.0 / change_sigma.to(dt).square()
    A = torch.zeros(N + 1, N + 1, dtype=dt)
    b = torch.zeros(N + 1, dtype=dt)
    idx = torch.arange(N)
    A[idx, idx] += wa
    b[idx] += wa * attitude
    A[idx, idx] += wc
    A[idx + 1, idx + 1] += wc
    A[idx, idx + 1] -= wc
    A[idx + 1, idx] -= wc
    b[idx] -= wc * change
    b[idx + 1] += wc * change
    cov = torch.linalg.inv(A + 1e-12 * torch.eye(N + 1, dtype=dt))
    return cov @ b, cov.diagonal().sqrt()


def timed(fn, repeats: int) -> tuple[float, object]:
    """Median seconds over ``repeats`` calls (one call if the first takes over a second)."""
    times, out = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
        if times[0] > 1.0:
            break
    return statistics.median(times), out


def main(argv: list[str] | None = None) -> int:
    from cli import description, positive_int, thread_count

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--sizes", type=positive_int, nargs="+", default=[100, 1000, 10000],
                        help="clip lengths N in pairs (default 100 1000 10000)")
    parser.add_argument("--repeats", type=positive_int, default=5, help="timed calls per solve (default 5)")
    parser.add_argument("--threads", type=thread_count, default=1,
                        help="torch threads, at most this machine's CPUs (default 1)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    from fsof_torch.estimation.sequence import smooth_attitude

    deg = torch.pi / 180
    print(f"smooth_attitude vs a dense inverse, {args.threads} thread(s)")
    print(f"{'N':>6} {'dense ms':>10} {'O(N) ms':>9} {'ratio':>8} {'dense MB':>9} {'max |Δtrack|':>13} {'max rel Δσ':>11}")
    for N in args.sizes:
        g = torch.Generator().manual_seed(N)
        f64 = dict(dtype=torch.float64)
        attitude = deg * torch.randn(N, generator=g, **f64)
        change = 0.1 * deg * torch.randn(N, generator=g, **f64)
        # as fit_sequence's track: failed pairs' attitudes do not count (1 in 10 here)
        sa = torch.where(torch.rand(N, generator=g) < 0.1, torch.inf, 1.0 * deg).to(torch.float64)
        if not bool(torch.isfinite(sa).any()):  # (at least one attitude counts, as smooth_attitude needs)
            sa[0] = 1.0 * deg
        sc = torch.full((N,), 0.03 * deg, **f64)
        t_fast, (track, sigma) = timed(lambda: smooth_attitude(attitude, change, sa, sc), args.repeats)
        t_dense, (track_d, sigma_d) = timed(lambda: dense_smooth(attitude, change, sa, sc), args.repeats)
        dtrack = float((track - track_d).abs().max())
        dsigma = float(((sigma - sigma_d) / sigma_d).abs().max())
        print(f"{N:6d} {1e3 * t_dense:10.2f} {1e3 * t_fast:9.2f} {t_dense / t_fast:8.1f} "
              f"{(N + 1) ** 2 * 8 / 1e6:9.1f} {dtrack:13.2e} {dsigma:11.2e}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
