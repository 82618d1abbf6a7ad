"""``python -m eval noise``: robustness of the model fit to flow noise, and pose estimation from
noisy flow (the paper's Fig. "noise robustness" and Fig. "vehicle pose estimation").

1. Noise robustness: Gaussian noise of standard deviation σ (pixels, each component) is added to
   the ground-truth flow of CVC12-like renders (cvc-simple / cvc-complex × speed ×1 / ×4); the
   displacement model is fitted inside the road mask; the fitted model flow is compared with the
   clean ground truth (e_E, e_A) and with the noisy flow it was fitted to.
2. Pose estimation (:func:`eval.pose.pose_estimation_experiment`): random displacement
   and yaw on a virtual road plane, the pose recovered from the noisy model flow alone.

Writes ``noise_robustness.png``, ``pose_errors.png``, ``pose_scatter.png`` (not with ``--no-plots``)
and ``noise.json`` into ``--out``, from which the files of an earlier run are removed first, once
the options are checked.

Example::

    python -m eval noise --out runs/noise
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

from fsof_torch.io.atomic import atomic_path

from .paths import MAX_SIDE, file_path, given_path

DEFAULT_SIGMAS = (0.0, 1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0, 2.0, 4.0)
DEFAULT_POSE_SIGMAS = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
#: the most random poses per noise level: each trial's true and estimated pose go into noise.json
#: (a count beyond memory ended in a traceback from the allocator, after the robustness fits)
MAX_TRIALS = 100_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=given_path, default=Path("runs/noise"), metavar="DIR",
                        help="output folder for the PNGs and noise.json (default runs/noise)")
    parser.add_argument("--json", type=file_path, default=None, metavar="PATH",
                        help="write the JSON here instead of DIR/noise.json")
    parser.add_argument("--size", type=int, nargs=2, default=None, metavar=("H", "W"),
                        help=f"render size of the CVC12-like scenes, each side 16 to {MAX_SIDE} "
                             "(default 375 1242; --quick: 96 320)")
    parser.add_argument("--sigmas", type=float, nargs="+", default=None, metavar="S",
                        help="noise levels for the fit-robustness curve, px, each at most 1e4 "
                             "(default 0, 1/64, ..., 4; --quick: 0, 1/32, 0.5, 2)")
    parser.add_argument("--pose-sigmas", type=float, nargs="+", default=None, metavar="S",
                        help="noise levels for the pose-estimation curves, px, each at most 1e4 "
                             "(default 0, 0.25, 0.5, 1, 2, 4, 8; --quick: 0, 1, 4)")
    parser.add_argument("--pose-size", type=int, nargs=2, default=None, metavar=("H", "W"),
                        help=f"virtual image size of the pose experiment, each side 16 to {MAX_SIDE} "
                             "(default 375 1242; --quick: 120 400)")
    parser.add_argument("--trials", type=int, default=None, metavar="N",
                        help=f"random poses per noise level, 1 to {MAX_TRIALS} (default 32; --quick: 3)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scenes, the noise and the poses (default 0)")
    parser.add_argument("--quick", action="store_true", help="small and fast: one scenario, few σ, small images")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def noise_robustness(size, sigmas, scenarios, seed: int, bar=None) -> list[dict]:
    """Fit errors versus σ; one row per (scenario, speed, σ)."""
    from fsof_torch.estimation.flow_fit import fit_displacement
    from fsof_torch.evaluation.metrics import flow_metrics
    from fsof_torch.data.scene import render_pair
    from fsof_torch.io.progress import print_above_bars

    rows = []
    gen = torch.Generator().manual_seed(seed)
    for scenario, speed in scenarios:
        pair = render_pair(f"cvc-{scenario}", 0, seed=seed, size=size, dtype=torch.float64, speed_factor=float(speed))
        flow, valid, road = pair["flow"][None], pair["valid"][None], pair["road"][None]
        mask = road & valid
        camera = pair["camera"]
        for sigma in sigmas:
            noise = torch.randn(flow.shape, generator=gen, dtype=torch.float64)
            noisy = flow + sigma * noise
            # The fit's robust scale follows the noise (1 px floor: its default).
            fit = fit_displacement(noisy, mask, camera, fit_roll=True, scale=max(1.0, 2.0 * sigma))
            clean = flow_metrics(fit.flow, flow, mask=road, valid=valid & fit.valid)
            observed = flow_metrics(fit.flow, noisy, mask=road, valid=valid & fit.valid)
            errors = {"e_E": clean["e_E"], "e_A": clean["e_A"], "e_E_vs_noisy": observed["e_E"],
                      "e_A_vs_noisy": observed["e_A"]}
            if not clean["n_pixels"]:  # over no pixel: None (printed '-'), not a 0 that reads as perfect
                print_above_bars(f"warning: {scenario} x{speed}, sigma {sigma:g}: the fitted model covers no road "
                                 "pixel; its errors are '-'")
                errors = dict.fromkeys(errors)
            rows.append({"scenario": scenario, "speed": f"x{speed}", "sigma": float(sigma), **errors,
                         "z_d_abs_error_m": abs(float(fit.z_d[0]) - pair["odometry"]["z_d"]),
                         "success": bool(fit.success.all()), "n_pixels": clean["n_pixels"]})
            if bar is not None:
                bar.update(1)
    return rows


def _plot_robustness(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    keys = sorted({(r["scenario"], r["speed"]) for r in rows})
    for scenario, speed in keys:
        # (in σ order: --sigmas given unsorted drew a curve that doubles back on itself)
        sel = sorted((r for r in rows if r["scenario"] == scenario and r["speed"] == speed),
                     key=lambda r: r["sigma"])
        s = [r["sigma"] for r in sel]
        for ax, key in zip(axes, ("e_E", "e_A")):  # (a row over no pixel: a gap in the curve)
            ax.plot(s, [math.nan if r[key] is None else r[key] for r in sel], marker="o", label=f"{scenario} {speed}")
    for ax, name in zip(axes, ("e_E of the fitted model vs clean GT (px)", "e_A vs clean GT (rad)")):
        ax.set_xscale("symlog", linthresh=1 / 64)
        ax.set_yscale("log")
        ax.set_xlabel("noise σ (px)")
        ax.set_title(name)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:  # (never half a figure)
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def _plot_pose(res, errors_path: Path, scatter_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = res.sigmas.tolist()
    order = sorted(range(len(s)), key=s.__getitem__)  # (the curves in σ order, as given or not)

    def curve(values: torch.Tensor) -> tuple[list[float], list[float]]:
        return [s[k] for k in order], [float(values[k]) for k in order]

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    axes[0].plot(*curve(res.translation_error), marker="o", label="‖d error‖")
    axes[0].plot(*curve(res.x_error), marker=".", label="|x_d error|")
    axes[0].plot(*curve(res.z_error), marker=".", label="|z_d error|")
    axes[0].axhline(0.07, color="grey", linestyle="--", label="paper bound 0.07 m")
    axes[0].set_ylabel("mean absolute error (m)")
    axes[1].plot(*curve(res.yaw_error_deg), marker="o", label="|yaw error|")
    axes[1].axhline(0.3, color="grey", linestyle="--", label="paper bound 0.3°")
    axes[1].set_ylabel("mean absolute error (deg)")
    for ax in axes:
        ax.set_xscale("symlog", linthresh=0.25)
        ax.set_yscale("log")
        ax.set_xlabel("noise σ (px)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle(f"pose from noisy flow ({res.settings['trials']} random poses per σ, "
                 f"{int(res.num_pixels)} road pixels)")
    fig.tight_layout()
    with atomic_path(errors_path) as tmp:  # (never half a figure)
        fig.savefig(tmp, dpi=110)
    plt.close(fig)

    # Per-trial errors against the size of the motion (the paper's "varying displacements, yaw").
    true = res.true_pose
    diff = res.estimated_pose - true.unsqueeze(0)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    d = true[:, :2].norm(dim=-1)
    yaw = torch.rad2deg(true[:, 2].abs())
    for k, sigma in enumerate(s):
        axes[0].scatter(d.tolist(), diff[k, :, :2].norm(dim=-1).tolist(), s=10, label=f"flow noise σ={sigma:g} px")
        axes[1].scatter(yaw.tolist(), torch.rad2deg(diff[k, :, 2].abs()).tolist(), s=10,
                        label=f"flow noise σ={sigma:g} px")
    axes[0].set_xlabel("‖d‖ (m)")
    axes[0].set_ylabel("‖d error‖ (m)")
    axes[0].set_title("translation error against the distance driven")
    axes[1].set_xlabel("|yaw| (deg)")
    axes[1].set_ylabel("|yaw error| (deg)")
    axes[1].set_title("yaw error against the yaw")
    for ax in axes:
        ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"pose from noisy flow, per random pose ({res.settings['trials']} per σ)")
    fig.tight_layout()
    with atomic_path(scatter_path) as tmp:  # (never half a figure)
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    from fsof_torch.io import write_json
    from eval.pose import MAX_SIGMA, pose_estimation_experiment

    from .paths import bad_file, bad_folder, bad_json_target, bad_size, first_bad, make_parent, remove_outputs
    from .provenance import environment
    from fsof_torch.io.progress import progress_bar
    from .tables import format_table

    quick = args.quick
    size = tuple(args.size) if args.size is not None else ((96, 320) if quick else (375, 1242))
    pose_size = tuple(args.pose_size) if args.pose_size is not None else ((120, 400) if quick else (375, 1242))
    sigmas = args.sigmas or ([0.0, 1 / 32, 0.5, 2.0] if quick else list(DEFAULT_SIGMAS))
    pose_sigmas = args.pose_sigmas or ([0.0, 1.0, 4.0] if quick else list(DEFAULT_POSE_SIGMAS))
    trials = args.trials if args.trials is not None else (3 if quick else 32)
    for name, values in (("--sigmas", sigmas), ("--pose-sigmas", pose_sigmas)):
        if any(not (math.isfinite(s) and 0 <= s <= MAX_SIGMA) for s in values):
            print(f"error: {name}: expected values in [0, {MAX_SIGMA:g}] px, got {values}", file=sys.stderr)
            return 2
    if not 1 <= trials <= MAX_TRIALS:
        print(f"error: --trials: expected 1 to {MAX_TRIALS}, got {trials}", file=sys.stderr)
        return 2
    for name, sz in (("--size", size), ("--pose-size", pose_size)):
        if min(sz) < 16:
            print(f"error: {name}: expected H, W >= 16, got {list(sz)}", file=sys.stderr)
            return 2
        bad = bad_size(sz, name)
        if bad is not None:
            print(f"error: {bad}", file=sys.stderr)
            return 2
    figures = ["noise_robustness.png", "pose_errors.png", "pose_scatter.png"]
    drawn = [] if args.no_plots else figures
    bad = first_bad(bad_folder(args.out, "--out", drawn + ([] if args.json else ["noise.json"])),
                    bad_file(args.json, "--json", args.out), bad_json_target(args.json, [args.out / f for f in drawn]))
    if bad is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    # an earlier run's files go (its plots with --no-plots, DIR/noise.json where this run writes
    # its JSON elsewhere), not to be read as this run's
    remove_outputs(args.out, figures + ["noise.json"])
    if args.json is not None:  # (and its JSON elsewhere: a run that stops would leave it as its own)
        remove_outputs(args.json.parent, [args.json.name])
    scenarios = [("complex", 1)] if quick else [("simple", 1), ("simple", 4), ("complex", 1), ("complex", 4)]

    with progress_bar(total=len(scenarios) * len(sigmas), enabled=not args.no_progress, desc="noise robustness",
                      unit="fit") as bar:
        robust_rows = noise_robustness(size, sigmas, scenarios, args.seed, bar)
    pose = pose_estimation_experiment(pose_sigmas, trials=trials, size=pose_size, seed=args.seed,
                                      progress=not args.no_progress)

    pose_rows = pose.rows()
    files = {}
    if not args.no_plots:  # (--out is created where the job writes into it: not with --no-plots and --json elsewhere)
        args.out.mkdir(parents=True, exist_ok=True)
        files["noise_robustness"] = args.out / "noise_robustness.png"
        files["pose_errors"] = args.out / "pose_errors.png"
        files["pose_scatter"] = args.out / "pose_scatter.png"
        _plot_robustness(robust_rows, files["noise_robustness"])
        _plot_pose(pose, files["pose_errors"], files["pose_scatter"])
    result = {"settings": {"size": list(size), "pose_size": list(pose_size), "sigmas": sigmas,
                           "pose_sigmas": pose_sigmas, "trials": trials, "seed": args.seed, "quick": bool(quick),
                           "pose": pose.settings},
              "noise_robustness": robust_rows, "pose": pose_rows,
              "pose_trials": {"true": pose.true_pose, "estimated": pose.estimated_pose},
              "files": {k: str(v) for k, v in files.items()},
              "environment": environment("noise", args, seed=args.seed)}
    json_path = args.json if args.json is not None else args.out / "noise.json"
    write_json(make_parent(json_path), result)
    # (printed after the files are written: a reader of stdout that goes away (| head) loses none)
    print("\nFit of the displacement model to noisy ground-truth flow (errors vs the clean GT)")
    # (σ as given, not rounded: 0.005 printed 0.01 and 0.001 printed 0.00, a noise-free row's label)
    print(format_table(robust_rows, [("scenario", "scenario", "s"), ("speed", "speed", "s"), ("sigma", "σ px", "g"),
                                     ("e_E", "e_E px", ".2e"), ("e_A", "e_A rad", ".2e"),
                                     ("e_E_vs_noisy", "e_E vs noisy", ".3g"), ("z_d_abs_error_m", "|z_d err| m", ".2e"),
                                     ("n_pixels", "pixels", "d")]))
    print(f"\nPose from noisy flow ({trials} random poses per σ, {int(pose.num_pixels)} road pixels, "
          f"{pose_size[0]}x{pose_size[1]}); the paper (PSO): < 0.07 m, < 0.3°")
    print(format_table(pose_rows, [("sigma", "σ px", "g"), ("translation_error_m", "‖d err‖ m", ".2e"),
                                   ("x_error_m", "|x_d err| m", ".2e"), ("z_error_m", "|z_d err| m", ".2e"),
                                   ("yaw_error_deg", "|yaw err| deg", ".2e"), ("success_rate", "success", ".2f")]))
    if any(r["success_rate"] < 1 for r in pose_rows):  # (a flag of the stated noise, not of the errors above)
        print("success: the share of fits flagged successful; these fits keep fit_displacement's default kernel "
              "scale, 1 px (inlier cut 3 px), which flags flow noisier than about 4 px whatever its motion "
              "(docs/fitting.md: pass a scale of about twice the noise)")

    print(f"\nwrote {json_path}" + "".join(f", {p}" for p in files.values()))
    return 0
