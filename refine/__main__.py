"""``python -m refine``: refine optical flow with the freespace model inside the road mask.

With no arguments: render the default synthetic sequence (``fsof_torch.data.scene``, preset
"default"), predict flow with OpenCV DIS and with the test net (random weights), refine each with
the scene's odometry, with ego-motion fitted to the flow and with ego-motion fitted to the images,
and write refined flows, figures and a report (photometric error and end-point error, road and
overall, before and after).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DEFAULT_PAIRS = 4
DEFAULT_SIZE = (375, 1242)


def _size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW such as 375x1242, got {text!r}") from None
    if h < 16 or w < 16:
        raise argparse.ArgumentTypeError(f"expected sides of at least 16 pixels, got {text!r}")
    return h, w


def _list(choices: tuple[str, ...]):
    def parse(text: str) -> list[str]:
        items = [t.strip() for t in text.split(",") if t.strip()]
        bad = [t for t in items if t not in choices]
        if bad or not items:
            raise argparse.ArgumentTypeError(f"expected a comma-separated list of {', '.join(choices)}, got {text!r}")
        return items
    return parse


def build_parser() -> argparse.ArgumentParser:
    from .job import VARIANTS

    p = argparse.ArgumentParser(
        prog="python -m refine", description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        epilog="Exit status: 0 done, 2 bad or missing input (with a message). An interrupted run "
               "resumes: pairs whose outputs exist are skipped unless --overwrite.")
    g = p.add_argument_group("synthetic data (the default)")
    g.add_argument("--preset", default="default", help="scene preset (default: %(default)s)")
    g.add_argument("--num-pairs", type=int, default=DEFAULT_PAIRS, help="pairs to render (default: %(default)s)")
    g.add_argument("--size", type=_size, default=DEFAULT_SIZE, metavar="HxW",
                   help="image size (default: %(default)s, KITTI's)")
    g.add_argument("--seed", type=int, default=0, help="scene seed (default: %(default)s)")
    g.add_argument("--scene-noise", type=float, default=None, metavar="GREY",
                   help="sensor noise of the rendered images, grey levels at 375x1242 (default: the preset's)")

    g = p.add_argument_group("user data")
    g.add_argument("--images", type=Path, metavar="DIR", help="folder of images; consecutive pairs (KITTI *_10/*_11 by name)")
    g.add_argument("--calib", type=Path, metavar="FILE", help="KITTI calib_cam_to_cam.txt or odometry calib.txt")
    g.add_argument("--cam", type=int, default=None, help="camera index in --calib (default: 2 if present, else 0)")
    g.add_argument("--height", type=float, default=1.65, help="camera height above the road, m (default: %(default)s)")
    g.add_argument("--roll-deg", type=float, default=0.0, help="camera roll, degrees (default: 0)")
    g.add_argument("--pitch-deg", type=float, default=0.0, help="camera pitch, degrees (default: 0)")
    g.add_argument("--poses", type=Path, metavar="FILE", help="KITTI poses (camera-to-world, one row per image)")
    g.add_argument("--flows", type=Path, metavar="DIR", help="predicted flows from any network (KITTI .png, .flo, .npy)")
    g.add_argument("--road", metavar="DIR|FILE.json|auto", help="road masks: PNG folder, a polygon JSON, or auto (detect)")
    g.add_argument("--gt", type=Path, metavar="DIR", help="ground-truth flows (optional)")

    g = p.add_argument_group("shared KITTI samples")
    g.add_argument("--kitti15", type=Path, metavar="PATH", help="kitti15_000000 folder: DIS refined with fitted ego-motion vs ground truth")
    g.add_argument("--kitti-odometry", type=Path, metavar="PATH",
                   help="kitti_odometry_straight folder: DIS refined with the poses, and with a calibrated pitch")

    g = p.add_argument_group("refinement")
    g.add_argument("--source", type=_list(("dis", "testnet")), default=None,
                   help="flow sources, comma-separated (default: dis,testnet; with --flows: the files)")
    g.add_argument("--testnet-weights", type=Path, metavar="FILE", help="state_dict for the test net (default: random, seed 0)")
    g.add_argument("--odometry", type=_list(VARIANTS), default=None,
                   help=f"odometry variants, comma-separated from {', '.join(VARIANTS)} (default: "
                        "given,fit,photometric on synthetic data; given with --poses, else fit)")
    g.add_argument("--mode", choices=("replace", "confidence"), default="replace", help="fusion (default: %(default)s)")
    g.add_argument("--scale", type=float, default=2.0, help="Cauchy scale in px for --mode confidence (default: %(default)s)")
    g.add_argument("--fit-roll", action="store_true", help="also fit the camera roll")
    g.add_argument("--fit-pitch", action="store_true", help="also fit the camera pitch")
    g.add_argument("--calibrate-pitch", action="store_true",
                   help="with --poses: find the pitch minimising road photometric error over the clip (adds variant given_pitch)")

    g = p.add_argument_group("output")
    g.add_argument("--out", type=Path, default=Path("refine_out"), help="output folder (default: %(default)s)")
    g.add_argument("--json", type=Path, metavar="PATH", help="also write the report JSON here")
    g.add_argument("--overwrite", action="store_true", help="redo pairs whose outputs exist")
    g.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    return p


def _run(args: argparse.Namespace) -> int:
    import torch

    from .calibrate import calibrate_pitch
    from .inputs import JobError, kitti15_pairs, kitti_odometry_pairs, synthetic_pairs, user_pairs
    from .job import JobConfig, run_pairs, summarize, write_report

    if args.threads is not None:
        if args.threads < 1:
            raise JobError(f"--threads: expected >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)
    chosen = [n for n in ("images", "kitti15", "kitti_odometry") if getattr(args, n) is not None]
    if len(chosen) > 1:
        raise JobError(f"choose one input: got --{' and --'.join(c.replace('_', '-') for c in chosen)}")
    if args.flows is not None and args.images is None:
        raise JobError("--flows needs --images (the pairs the flows belong to)")
    if args.scale <= 0:
        raise JobError(f"--scale: expected > 0 px, got {args.scale}")
    notes: list[str] = []
    camera = None
    calibrate = args.calibrate_pitch
    if args.kitti15 is not None:
        specs = kitti15_pairs(args.kitti15, height=args.height)
        title = "refine: KITTI 2015 pair 000000 (DIS)"
        sources = args.source or ["dis"]
        variants = args.odometry or ["fit", "photometric"]
        notes.append("Road mask: the hand-drawn road.json; ground truth: flow_noc_10.png (sparse).")
    elif args.kitti_odometry is not None:
        specs, camera = kitti_odometry_pairs(args.kitti_odometry, height=args.height, pitch_deg=args.pitch_deg)
        title = "refine: KITTI odometry straight clip (DIS)"
        sources = args.source or ["dis"]
        calibrate = True
        variants = args.odometry or ["given", "given_pitch", "fit"]
        notes.append("Road mask: the hand-drawn road.json (ego lane); no ground-truth flow: photometric error only.")
    elif args.images is not None:
        if args.calib is None:
            raise JobError("--calib: user data needs a calibration file (KITTI format)")
        specs, camera = user_pairs(images=args.images, calib=args.calib, cam=args.cam, height=args.height,
                                   roll_deg=args.roll_deg, pitch_deg=args.pitch_deg, poses=args.poses,
                                   flows=args.flows, road=args.road, gt=args.gt)
        title = f"refine: {args.images}"
        sources = ["files"] if args.flows is not None else (args.source or ["dis"])
        if args.flows is not None and args.source:
            raise JobError("--source and --flows: give one of them")
        variants = args.odometry or (["given"] if args.poses is not None else ["fit"])
        if "given" in variants and args.poses is None:
            raise JobError("--odometry given: user data needs --poses (or use fit / photometric)")
    else:
        for opt in ("calib", "poses", "gt", "flows"):
            if getattr(args, opt) is not None:
                raise JobError(f"--{opt} needs --images")
        if args.road not in (None, "auto"):
            raise JobError("--road: synthetic scenes use their own road mask, or 'auto'")
        specs = synthetic_pairs(args.preset, args.num_pairs, seed=args.seed, size=args.size, road=args.road,
                                noise=args.scene_noise)
        title = f"refine: synthetic '{args.preset}' sequence, {args.num_pairs} pairs, {args.size[0]}x{args.size[1]}"
        sources = args.source or ["dis", "testnet"]
        variants = args.odometry or ["given", "fit", "photometric"]
        notes.append("Synthetic scene: odometry and flow ground truth are the scene's (exact); road mask: "
                     + ("detected on each prediction (--road auto)." if args.road == "auto" else "the scene's (exact)."))
    if "testnet" in sources and args.testnet_weights is None:
        notes.append("testnet: TinyRAFT with random weights (seed 0), not trained: its raw flow is meaningless; "
                     "it shows the wrapper on a RAFT-style output.")
    if "given_pitch" in variants and not calibrate:
        raise JobError("--odometry given_pitch needs --calibrate-pitch")
    if calibrate and "given_pitch" not in variants:
        variants = [*variants, "given_pitch"]
    cfg = JobConfig(out=args.out, sources=sources, variants=variants, mode=args.mode, scale=args.scale,
                    fit_roll=args.fit_roll, fit_pitch=args.fit_pitch, road_auto=args.road == "auto",
                    overwrite=args.overwrite, figures=not args.no_figures, progress=not args.no_progress,
                    title=title, testnet_weights=args.testnet_weights, notes=notes)
    args.out.mkdir(parents=True, exist_ok=True)
    if calibrate:
        if camera is None:
            raise JobError("--calibrate-pitch needs user data with --poses")
        pitch, scores = calibrate_pitch(specs, camera, progress=cfg.progress)
        cfg.calibrated_pitch_deg = pitch
        notes.append(f"Calibrated pitch: {pitch:.2f}° (minimum of the road photometric error of the "
                     f"pose-driven model flow over the clip; {len(scores)} candidates, "
                     f"error {min(s for _, s in scores):.3f} at the minimum, "
                     f"{dict(scores).get(0.0, float('nan')):.3f} at 0°).")
    records = run_pairs(specs, cfg)
    summary = summarize(records, cfg)
    if cfg.calibrated_pitch_deg is not None:
        summary["calibrated_pitch_deg"] = cfg.calibrated_pitch_deg
    table = write_report(summary, cfg, args.json)
    print(f"\n{title}\n\n{table}\n")
    for n in notes:
        print(f"- {n}")
    print(f"\nreport: {cfg.out / 'report.md'} and {cfg.out / 'report.json'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """The job's entry point; returns the exit status (0 done, 2 bad input)."""
    parser = build_parser()
    try:
        args = parser.parse_args(sys.argv[1:] if argv is None else list(argv))
    except SystemExit as exit_:  # argparse exits on --help and on bad options
        return int(exit_.code or 0)
    from .inputs import JobError

    try:
        return _run(args)
    except (JobError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except ValueError as err:  # a reader or the library rejected an input file or value
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
