"""The refinement job's options checked and turned into a run: the pairs, the camera, the flow
sources, the odometry variants, the report's title and notes and the input's identity
(:func:`configure`), and the JSON and numeric option values parsed and checked before any work."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
from pathlib import Path

from .options import DEFAULT_HEIGHT, DEFAULTS


def _refuse_unused(args: argparse.Namespace, real: str | None) -> None:
    """Options that the chosen input does not use are refused when given, even at their default
    value, not silently ignored (``real``: the real-data input chosen, None for the synthetic
    scenes; ``args`` as parsed, before :func:`_with_defaults`)."""
    from .inputs import JobError

    if real is not None:
        for option in ("preset", "num_pairs", "size", "seed", "scene_noise"):
            if getattr(args, option) is not None:
                raise JobError(f"--{option.replace('_', '-')}: applies to the synthetic scenes, not to "
                               f"--{real.replace('_', '-')}")
    # (the road masks of a run without --road auto: --images's given, the others' own; a --road that
    # --images lacks or the others may not take is named by the checks of --road)
    if args.road_options is not None and args.road != "auto" and (args.road is not None) == (real == "images"):
        masks = (f"--road {args.road}" if real == "images" else "the synthetic scene's own road mask"
                 if real is None else "the folder's road.json")
        raise JobError(f"--road-options: applies to the road found in the images (--road auto), which this run "
                       f"does not use (its road masks: {masks})")
    if real == "images":
        return
    sample = f"--{(real or '').replace('_', '-')}"
    what = "the synthetic scenes have their own camera" if real is None else f"{sample} has its own calibration"
    own = {"--cam": args.cam is not None, "--roll-deg": args.roll_deg is not None,
           "--height": real is None and args.height is not None,
           "--pitch-deg": real != "kitti_odometry" and args.pitch_deg is not None}
    if real is not None:
        own.update({"--calib": args.calib is not None, "--calib-size": args.calib_size is not None,
                    "--poses": args.poses is not None, "--gt": args.gt is not None})
    # (the poses and ground truth of a sample are its own, or it has none: say which)
    why = {"--poses": f"{sample} has its own poses.txt" if real == "kitti_odometry" else
           "the KITTI 2015 pair has no poses",
           "--gt": "the KITTI 2015 pair has its own flow_noc_10.png" if real == "kitti15" else
           "the KITTI odometry clip has no ground-truth flow"}
    # the inputs each option applies to (the KITTI samples take --height, the clip --pitch-deg)
    where = {"--height": "--images, --kitti15 and --kitti-odometry", "--pitch-deg": "--images and --kitti-odometry"}
    for option, given in own.items():
        if given:
            raise JobError(f"{option}: applies to {where.get(option, '--images')} ({why.get(option, what)})")
    if real is not None and args.road not in (None, "auto"):
        raise JobError(f"--road: --{real.replace('_', '-')} uses its own road.json, or 'auto'")
    given = [v for v in args.odometry or () if v.startswith("given")]
    if real == "kitti15" and given:
        raise JobError(f"--odometry {given[0]}: the KITTI 2015 pair has no poses; use fit or photometric")


def _with_defaults(args: argparse.Namespace) -> argparse.Namespace:
    """A copy of ``args`` with the options of :data:`DEFAULTS` not given set to their defaults."""
    filled = {k: v for k, v in DEFAULTS.items() if getattr(args, k) is None}
    return argparse.Namespace(**{**vars(args), **filled})


def parse_odometry_sigma(widths: list[float] | None, variants: list[str]) -> dict[str, float] | None:
    """``--odometry-sigma X_M Z_M YAW_DEG`` -> ``ImageMotionEstimator``'s ``odometry_sigma``
    (radians for the yaw), checked; None where not given."""
    from .inputs import JobError

    if widths is None:
        return None
    if "given_images" not in variants:
        raise JobError(f"--odometry-sigma: applies to the variant given_images, which this run does not use "
                       f"(--odometry {','.join(variants)})")
    if not all(math.isfinite(w) and w > 0 for w in widths):
        raise JobError(f"--odometry-sigma: expected three finite widths > 0 (X_M Z_M YAW_DEG), got "
                       f"{' '.join(f'{w:g}' for w in widths)}")
    return {"x_d": widths[0], "z_d": widths[1], "yaw": math.radians(widths[2])}


#: fit_image options the job sets itself (besides the images, the road and the camera: the model,
#: the starts, the odometry's held parameters, the priors and the images' range), which
#: --fit-options may not give
_JOB_FIT_KEYS = ("model", "init", "starts", "fixed", "prior", "data_range")


def parse_fit_options(text: str | None, variants: list[str], calibrate: bool) -> dict | None:
    """``--fit-options JSON`` -> fit_image keyword arguments, checked (names and values) before any
    work; None where not given."""
    from fsof_torch.estimation.image_fit import check_image_fit_options

    from .calibrate import clip_options
    from .inputs import JobError
    from .job import WITH_IMAGES

    if text is None:
        return None
    options = _json_object(text, "--fit-options", "fit_image")
    if not set(WITH_IMAGES) & set(variants) and not clip_options(calibrate, variants):
        raise JobError(f"--fit-options: applies to the road motion from the images (variants photometric, "
                       f"given_images, sequence, given_pitch, or --calibrate-pitch), which this run does not use "
                       f"(--odometry {','.join(variants)})")
    with _named("--fit-options"):
        check_image_fit_options(options, "--fit-options", reserved=_JOB_FIT_KEYS)
    return options


def _json_object(text: str, option: str, function: str) -> dict:
    """``option``'s JSON ``text``, keyword arguments of ``function``: a JSON object, else a JobError
    naming the option and quoting what came."""
    from .inputs import JobError

    try:
        options = json.loads(text)
    except json.JSONDecodeError as err:
        raise JobError(f"{option}: expected a JSON object of {function} keyword arguments, got {text!r} ({err})") \
            from None
    if not isinstance(options, dict):
        raise JobError(f"{option}: expected a JSON object of {function} keyword arguments, got {text!r}")
    return options


@contextlib.contextmanager
def _named(option: str):
    """The library's TypeError or ValueError about an option's keyword arguments as a JobError
    naming the option."""
    from .inputs import JobError

    try:
        yield
    except (TypeError, ValueError) as err:
        message = str(err)
        raise JobError(message if message.startswith(option) else f"{option}: {message}") from None


def parse_road_options(text: str | None) -> dict | None:
    """``--road-options JSON`` -> detect_road keyword arguments, checked (names and values) before
    any work; None where not given. (Without ``--road auto`` refused first: :func:`_refuse_unused`.)"""
    from fsof_torch.refinement.wrapped import road_option_values

    if text is None:
        return None
    options = _json_object(text, "--road-options", "detect_road")
    with _named("--road-options"):
        road_option_values(options, "--road-options")
    return options


def _sample_road(road: str | None) -> str:
    """Where a KITTI sample's road mask comes from, for the report's notes."""
    return "found in the images of each pair (--road auto)" if road == "auto" else "the folder's hand-drawn road.json"


def poses_option(args: argparse.Namespace) -> str:
    """The option the pairs' poses come from, which errors about them name."""
    return "--kitti-odometry" if args.kitti_odometry is not None else "--poses" if args.images is not None \
        else "--preset"


def configure(args: argparse.Namespace):
    """Options -> (pair specs, camera, config parts, input identity), checked before any work."""
    from .inputs import JobError, kitti15_pairs, kitti_odometry_pairs, synthetic_pairs, user_pairs

    chosen = [n for n in ("images", "kitti15", "kitti_odometry") if getattr(args, n) is not None]
    if len(chosen) > 1:
        raise JobError(f"choose one input: got --{' and --'.join(c.replace('_', '-') for c in chosen)}")
    if args.flows is not None and args.images is None:
        raise JobError("--flows needs --images (the pairs the flows belong to)")
    if args.scale is not None:
        if args.mode != "confidence":
            raise JobError(f"--scale: applies to --mode confidence, not to --mode {args.mode} (which uses no scale)")
        if not (args.scale > 0 and math.isfinite(args.scale)):
            raise JobError(f"--scale: expected a finite value > 0 px, got {args.scale}")
    if args.checkpoint is not None and args.net is None:
        raise JobError("--checkpoint needs --net (the network the state_dict is for)")
    if args.net_contract is not None and args.net is None:
        raise JobError("--net-contract needs --net")
    if args.net is not None and args.flows is not None:
        raise JobError("--net and --flows: give one of them (the flows are another network's predictions)")
    _refuse_unused(args, chosen[0] if chosen else None)
    height_given = args.height is not None
    args = _with_defaults(args)
    notes: list[str] = []
    camera = None
    calibrate = args.calibrate_pitch
    default_sources = ["net"] if args.net is not None else None
    if args.kitti15 is not None:
        specs, camera = kitti15_pairs(args.kitti15, height=args.height, road_auto=args.road == "auto")
        title = f"refine: KITTI 2015 pair {specs[0].name}"
        sources = args.source or default_sources or ["dis"]
        variants = args.odometry or ["fit", "photometric"]
        truth = "flow_noc_10.png (sparse)" if (args.kitti15 / "flow_noc_10.png").is_file() else \
            "none (no flow_noc_10.png): image errors only"
        notes.append(f"Road mask: {_sample_road(args.road)}; ground truth: {truth}.")
        identity = {"kind": "kitti15", "root": str(args.kitti15.resolve()), "height": args.height}
    elif args.kitti_odometry is not None:
        specs, camera = kitti_odometry_pairs(args.kitti_odometry, height=args.height, pitch_deg=args.pitch_deg,
                                             road_auto=args.road == "auto")
        title = f"refine: KITTI odometry clip {args.kitti_odometry.resolve().name}"
        sources = args.source or default_sources or ["dis"]
        variants = args.odometry or ["given", "given_images", "sequence", "photometric"]
        notes.append(f"Road mask: {_sample_road(args.road)}; no ground-truth flow: image errors only.")
        identity = {"kind": "kitti_odometry", "root": str(args.kitti_odometry.resolve()), "height": args.height,
                    "pitch_deg": args.pitch_deg}
    elif args.images is not None:
        from .inputs import file_digest

        if args.calib is None:
            raise JobError("--calib: user data needs a calibration file (KITTI format)")
        if args.flows is not None and args.source:
            raise JobError("--source and --flows: give one of them")
        specs, camera = user_pairs(images=args.images, calib=args.calib, cam=args.cam, height=args.height,
                                   roll_deg=args.roll_deg, pitch_deg=args.pitch_deg, poses=args.poses,
                                   flows=args.flows, road=args.road, gt=args.gt, calib_size=args.calib_size)
        title = f"refine: {args.images}"
        sources = ["files"] if args.flows is not None else (args.source or default_sources or ["dis"])
        from .inputs import kitti_flow_layout, list_images

        clip = len(specs) > 1 and not kitti_flow_layout(list_images(args.images))
        variants = args.odometry or (["sequence" if clip else "photometric"]
                                     + (["given_images"] if args.poses is not None else []))
        for v in ("given", "given_images", "given_pitch"):
            if v in variants and args.poses is None:
                raise JobError(f"--odometry {v}: user data needs --poses (or use photometric / sequence / fit)")
        if not height_given and not calibrate and (metric := [v for v in ("given", "given_images") if v in variants]):
            notes.append(_default_height_note(metric))
        road = args.road
        if road not in (None, "auto") and Path(road).is_file():
            road = {"file": str(Path(road).resolve()), "digest": file_digest(Path(road))}
        elif road not in (None, "auto"):
            road = str(Path(road).resolve())
        identity = {"kind": "images", "images": str(args.images.resolve()), "calib": file_digest(args.calib),
                    "calib_size": args.calib_size, "cam": args.cam, "height": args.height,
                    "roll_deg": args.roll_deg, "pitch_deg": args.pitch_deg,
                    "poses": file_digest(args.poses) if args.poses is not None else None,
                    "flows": str(args.flows.resolve()) if args.flows is not None else None, "road": road,
                    "gt": str(args.gt.resolve()) if args.gt is not None else None}
    else:
        for opt in ("calib", "poses", "gt", "flows", "calib_size"):
            if getattr(args, opt) is not None:
                raise JobError(f"--{opt.replace('_', '-')} needs --images")
        if args.road not in (None, "auto"):
            raise JobError("--road: synthetic scenes use their own road mask, or 'auto'")
        specs = synthetic_pairs(args.preset, args.num_pairs, seed=args.seed, size=args.size, road=args.road,
                                noise=args.scene_noise)
        title = (f"refine: synthetic '{args.preset}' sequence, {args.num_pairs} pair{'' if args.num_pairs == 1 else 's'}, "
                 f"{args.size[0]}x{args.size[1]}")
        sources = args.source or default_sources or ["dis", "testnet"]
        variants = args.odometry or ["given", "fit", "photometric"]
        notes.append("Synthetic scene: odometry and flow ground truth are the scene's (exact); road mask: "
                     + ("found in the images of each pair (--road auto)." if args.road == "auto" else "the scene's (exact)."))
        identity = {"kind": "synthetic", "preset": args.preset, "seed": args.seed, "size": list(args.size),
                    "noise": args.scene_noise}
    if "net" in sources and args.net is None:
        raise JobError("--source net needs --net module:callable")
    if "net" not in sources:  # (--checkpoint and --net-contract without --net are refused above)
        given = [o for o, v in (("--net", args.net is not None), ("--checkpoint", args.checkpoint is not None),
                                ("--net-contract", args.net_contract is not None)) if v]
        if given:
            raise JobError(f"{' and '.join(given)}: the run has no net source (sources: {','.join(sources)}); "
                           f"add net to --source")
    if args.testnet_weights is not None and "testnet" not in sources:
        raise JobError(f"--testnet-weights: the run has no testnet source (sources: {','.join(sources)})")
    for flag in ("fit_roll", "fit_pitch"):
        if getattr(args, flag) and "fit" not in variants:
            raise JobError(f"--{flag.replace('_', '-')}: applies to the variant fit, which this run does not do "
                           f"(--odometry {','.join(variants)})")
    if "testnet" in sources and args.testnet_weights is None:
        notes.append("testnet: TinyRAFT with random weights (seed 0), not trained: its raw flow is meaningless; "
                     "it shows the wrapper on a RAFT-style output.")
    from .calibrate import check_clip, clip_options

    needed_by = clip_options(calibrate, variants)
    if needed_by:
        check_clip(specs, needed_by=needed_by, poses_option=poses_option(args))
    return specs, camera, title, sources, variants, calibrate, notes, identity


def _default_height_note(variants: list[str]) -> str:
    """The report's note where user data refines with the poses' odometry (``variants``: of given and
    given_images) at a height nobody gave: the default, KITTI's camera. The poses' translation is in
    metres and the road's flow scales with translation / height, so another camera's height scales
    that flow (a camera 2.8 m high, refined at 1.65 m: 1.7 times its road flow)."""
    return (f"Camera height not given (--height): {DEFAULT_HEIGHT} m, KITTI's camera, is assumed; the road flow of the "
            f"odometry from --poses (variant{'s' if len(variants) > 1 else ''} {' / '.join(variants)}) scales with "
            f"1 / height: give the camera's height above the road, or --calibrate-pitch (with poses it calibrates "
            f"the height over the clip).")
