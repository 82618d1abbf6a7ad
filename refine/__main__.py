"""``python -m refine``: refine optical flow with the freespace model inside the road mask.

With no arguments: render the default synthetic sequence (``fsof_torch.data.scene``, preset
"default"), predict flow with OpenCV DIS and with the test net (random weights), refine each with
the scene's odometry, with ego-motion fitted to the flow and with ego-motion fitted to the images,
and write refined flows, figures and a report (census distance, SSIM and L1 photometric error, and
end-point error, road and overall, before and after) into ``refine_out/synthetic-default/``.

Options, inputs, outputs, resuming and distributed runs: ``docs/jobs.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
from pathlib import Path

DEFAULT_PAIRS = 4
DEFAULT_SIZE = (375, 1242)
DEFAULT_OUT = Path("refine_out")
DEFAULT_HEIGHT = 1.65  # m, KITTI's camera over the road
DEFAULT_SCALE = 2.0  # px, the Cauchy scale of --mode confidence
#: the defaults of the options that only some inputs use: the parser leaves them None (not given),
#: so that one given to an input that does not use it is refused even at its default value
#: (:func:`_refuse_unused`); :func:`_with_defaults` fills them in after that check
DEFAULTS = {"preset": "default", "num_pairs": DEFAULT_PAIRS, "size": DEFAULT_SIZE, "seed": 0,
            "height": DEFAULT_HEIGHT, "roll_deg": 0.0, "pitch_deg": 0.0}


def _size(text: str) -> tuple[int, int]:
    from fsof_torch.data.scene.render import MAX_SIDE  # (the renderer's bound, for --calib-size too)

    try:
        h, w = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW such as 375x1242, got {text!r}") from None
    if h < 16 or w < 16:
        raise argparse.ArgumentTypeError(f"expected sides of at least 16 pixels, got {text!r}")
    if max(h, w) > MAX_SIDE:  # (a larger render only fills memory)
        raise argparse.ArgumentTypeError(f"expected sides of at most {MAX_SIDE} pixels, got {text!r}")
    return h, w


def _road(text: str) -> str:
    """``--road``: a folder, a file or ``auto``; not an empty path (:func:`refine.resume.given_path`)."""
    from .resume import given_path

    given_path(text)
    return text


def _list(choices: tuple[str, ...]):
    def parse(text: str) -> list[str]:
        items = [t.strip() for t in text.split(",") if t.strip()]
        bad = [t for t in items if t not in choices]
        if bad or not items:
            raise argparse.ArgumentTypeError(f"expected a comma-separated list of {', '.join(choices)}, got {text!r}")
        return list(dict.fromkeys(items))
    return parse


def command_name() -> str:
    """The command the job was started by, as its usage names it: ``fsof-refine`` (the console
    script pyproject installs; its wrapper leaves that name in ``sys.argv[0]``) or ``python -m refine``."""
    return "fsof-refine" if sys.argv and Path(sys.argv[0] or ".").stem == "fsof-refine" else "python -m refine"


def build_parser(prog: str = "python -m refine") -> argparse.ArgumentParser:
    """The job's options; ``prog`` names the command in its usage and errors (:func:`command_name`)."""
    from fsof_torch.data.scene.render import MAX_FRAME, MAX_SIDE

    from .job import VARIANTS
    from .resume import file_path, given_path
    from .sources import CONTRACTS, SOURCES

    p = argparse.ArgumentParser(
        prog=prog, description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        epilog="Exit status: 0 done, 1 stdout closed by its reader (| head: the report is written) or the disk "
               "full (the pairs finished are kept), 2 bad "
               "or missing input (with a message naming the option), 130 interrupted (Ctrl-C). An "
               "interrupted run resumes: pairs finished by a run of the same inputs and options are "
               "reused; a folder holding a run of other inputs or options is refused unless --overwrite. "
               "Distributed: torchrun --nproc-per-node N -m refine ... (see docs/jobs.md).")
    g = p.add_argument_group("synthetic data (the default)")
    g.add_argument("--preset", metavar="NAME", help=f"scene preset (default: {DEFAULTS['preset']})")
    g.add_argument("--num-pairs", type=int, metavar="N",
                   help=f"pairs to render, 1 to {MAX_FRAME} (default: {DEFAULT_PAIRS})")
    g.add_argument("--size", type=_size, metavar="HxW", help=f"image size, each side 16 to {MAX_SIDE} (default: 375x1242, KITTI's)")
    g.add_argument("--seed", type=int, metavar="N", help="scene seed (default: 0)")
    g.add_argument("--scene-noise", type=float, default=None, metavar="GREY",
                   help="sensor noise of the rendered images, grey levels at 375x1242 (default: the preset's)")

    g = p.add_argument_group("user data")
    g.add_argument("--images", type=given_path, metavar="DIR", help="folder of images; consecutive pairs (KITTI *_10/*_11 by name)")
    g.add_argument("--calib", type=given_path, metavar="FILE", help="KITTI calib_cam_to_cam.txt or odometry calib.txt")
    g.add_argument("--calib-size", type=_size, default=None, metavar="HxW",
                   help=f"image size the calibration is for, each side 16 to {MAX_SIDE} (default: the file's S_rect row, "
                        "else checked loosely)")
    g.add_argument("--cam", type=int, default=None, metavar="N",
                   help="camera index in --calib (default: 2 if present, else 0)")
    g.add_argument("--height", type=float, metavar="M",
                   help=f"camera height above the road, m (default: {DEFAULT_HEIGHT})")
    g.add_argument("--roll-deg", type=float, metavar="D", help="camera roll, degrees (default: 0)")
    g.add_argument("--pitch-deg", type=float, metavar="D", help="camera pitch, degrees (default: 0)")
    g.add_argument("--poses", type=given_path, metavar="FILE", help="KITTI poses (camera-to-world, one row per image)")
    g.add_argument("--flows", type=given_path, metavar="DIR", help="predicted flows of any network, one per pair, "
                   "named like the pair (KITTI .png, .flo, .npy)")
    g.add_argument("--road", type=_road, metavar="DIR|FILE|auto", help="road masks: PNG folder (named like the pairs), "
                   "one PNG of the images' size or a polygon JSON for every pair, or auto (found in the images: docs/auto-road.md); required with --images; "
                   "synthetic scenes and the KITTI samples have their own, or take auto")
    g.add_argument("--gt", type=given_path, metavar="DIR", help="ground-truth flows, named like the pairs (optional)")

    g = p.add_argument_group("KITTI folders in the shared samples' layouts")
    g.add_argument("--kitti15", type=given_path, metavar="DIR",
                   help="a folder like kitti15_000000 (a KITTI 2015 pair): DIS refined with ego-motion fitted to "
                        "the flow and to the images, against its ground truth where present")
    g.add_argument("--kitti-odometry", type=given_path, metavar="DIR",
                   help="a folder like kitti_odometry_straight (a KITTI odometry clip with poses): DIS refined with "
                        "the poses, with the clip's fit and with the images; road.json optional with --road auto")

    g = p.add_argument_group("flow networks")
    g.add_argument("--source", type=_list(SOURCES), default=None, metavar="LIST",
                   help="flow sources, comma-separated from dis, testnet, net (default: dis,testnet on "
                        "synthetic data, dis on real data; with --net: net; with --flows: the files)")
    g.add_argument("--testnet-weights", type=given_path, metavar="FILE", help="state_dict for the test net (default: random, seed 0)")
    g.add_argument("--net", metavar="MODULE:CALLABLE",
                   help="your flow network: a factory returning an nn.Module (e.g. mypkg.models:make_raft)")
    g.add_argument("--net-contract", choices=CONTRACTS,
                   help="how --net is called: ptlflow (dict, BGR [0,1]), torchvision (RGB [-1,1], list), "
                        "raft (RGB 0..255, list); default: from the network (see docs/contracts.md)")
    g.add_argument("--checkpoint", type=given_path, metavar="FILE",
                   help="a local state_dict for --net (loaded with torch.load(weights_only=True))")

    g = p.add_argument_group("refinement")
    g.add_argument("--odometry", type=_list(VARIANTS), default=None, metavar="LIST",
                   help=f"odometry variants, comma-separated from {', '.join(VARIANTS)} (default: synthetic "
                        "data: given,fit,photometric; --images: sequence for a clip, photometric for "
                        "KITTI *_10/*_11 pairs or a single pair, plus given_images with --poses; "
                        "--kitti15: fit,photometric; --kitti-odometry: given,given_images,sequence,photometric)")
    g.add_argument("--odometry-sigma", type=float, nargs=3, metavar=("X_M", "Z_M", "YAW_DEG"), default=None,
                   help="variant given_images: let the images move the odometry's planar motion, within these "
                        "widths a frame (sideways and forward in metres, yaw in degrees; e.g. 0.05 0.05 0.2 "
                        "for wheel odometry); default: held fixed")
    g.add_argument("--fit-options", metavar="JSON", default=None,
                   help="fit_image keyword arguments for the road motion from the images (variants photometric, "
                        "given_images, and the clip's fit for sequence, given_pitch and --calibrate-pitch), a JSON "
                        "object, e.g. '{\"fine_points\": 20000, \"smooth_sigma\": 1.0}' (docs/real-roads.md, "
                        "\"Settings for a real camera\"); default: the library's")
    g.add_argument("--road-options", metavar="JSON", default=None,
                   help="detect_road keyword arguments for --road auto (the road found in the images), a JSON "
                        "object, e.g. '{\"seed_depth_m\": 40}' (docs/auto-road.md, \"Options\"); default: the "
                        "library's")
    g.add_argument("--mode", choices=("replace", "confidence"), default="replace", help="fusion (default: %(default)s)")
    g.add_argument("--scale", type=float, default=None, metavar="PX",
                   help=f"Cauchy scale in px, for --mode confidence only (default: {DEFAULT_SCALE:g})")
    g.add_argument("--fit-roll", action="store_true", help="variant fit: also fit the camera roll")
    g.add_argument("--fit-pitch", action="store_true", help="variant fit: also fit the camera pitch")
    g.add_argument("--calibrate-pitch", action="store_true",
                   help="calibrate the camera's pitch and roll over the road from the clip's images (with poses, "
                        "--poses or the odometry sample's, also its height) and refine every variant with it")

    g = p.add_argument_group("output")
    g.add_argument("--out", type=given_path, default=None, metavar="DIR",
                   help="output folder (default: refine_out/<input name>, e.g. refine_out/synthetic-default)")
    g.add_argument("--json", type=file_path, metavar="PATH",
                   help="also write the report JSON here (not an input, nor inside --out but OUT/report.json, "
                        "nor inside another run's output folder)")
    g.add_argument("--overwrite", action="store_true",
                   help="redo every pair; replace the results of another run in --out")
    g.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.add_argument("--threads", type=int, default=1, metavar="N",
                   help="intra-op threads per process for torch and OpenCV (default: 1; more helps only "
                        "on idle cores)")
    g.add_argument("--device", default="cpu", metavar="DEV", help="torch device for the networks and the refiner "
                   "(default: cpu; cuda uses the process's GPU)")
    return p


def default_out(args: argparse.Namespace) -> Path:
    """``refine_out/<input name>``: one folder per input, so runs on other inputs do not meet. A
    folder of images is named with the folder it is in (``my_clip/images`` -> ``my_clip-images``):
    the layout of the docs gives every clip an ``images`` folder."""
    if args.images is not None:
        images = args.images.resolve()
        name = "-".join(n for n in (images.parent.name, images.name) if n) or "images"
    elif args.kitti15 is not None:
        name = args.kitti15.resolve().name
    elif args.kitti_odometry is not None:
        name = args.kitti_odometry.resolve().name
    else:
        name = f"synthetic-{args.preset or DEFAULTS['preset']}"
        if args.seed:
            name += f"-seed{args.seed}"
        if args.size is not None and tuple(args.size) != DEFAULT_SIZE:
            name += f"-{args.size[0]}x{args.size[1]}"
        if args.scene_noise is not None:
            name += f"-noise{args.scene_noise:g}"
    return DEFAULT_OUT / name


def _input_paths(args: argparse.Namespace, net: bool = True) -> dict[str, Path | None]:
    """The files and folders the run reads, by option (None where not given): --json may name
    none of them, nor a file inside one of the folders (``net``: with --net's module, which finding
    may import its package)."""
    road = Path(args.road) if args.road not in (None, "auto") else None
    return {"--images": args.images, "--calib": args.calib, "--poses": args.poses, "--flows": args.flows,
            "--road": road, "--gt": args.gt, "--kitti15": args.kitti15, "--kitti-odometry": args.kitti_odometry,
            "--testnet-weights": args.testnet_weights, "--checkpoint": args.checkpoint,
            "--net": _net_source(args.net) if net else None}


def _net_source(factory: str | None) -> Path | None:
    """The file, or for a package the folder, that ``--net``'s module is read from."""
    from .sources import net_module_file

    source = net_module_file(factory) if factory is not None else None
    return source.parent if source is not None and source.name == "__init__.py" else source


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


def _odometry_sigma(widths: list[float] | None, variants: list[str]) -> dict[str, float] | None:
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


def _fit_options(text: str | None, variants: list[str], calibrate: bool) -> dict | None:
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


def _road_options(text: str | None) -> dict | None:
    """``--road-options JSON`` -> detect_road keyword arguments, checked (names and values) before
    any work; None where not given. (Without ``--road auto`` refused first: :func:`_refuse_unused`.)"""
    from fsof_torch.refinement.auto_road import road_option_values

    if text is None:
        return None
    options = _json_object(text, "--road-options", "detect_road")
    with _named("--road-options"):
        road_option_values(options, "--road-options")
    return options


def _sample_road(road: str | None) -> str:
    """Where a KITTI sample's road mask comes from, for the report's notes."""
    return "found in the images of each pair (--road auto)" if road == "auto" else "the folder's hand-drawn road.json"


def _poses_option(args: argparse.Namespace) -> str:
    """The option the pairs' poses come from, which errors about them name."""
    return "--kitti-odometry" if args.kitti_odometry is not None else "--poses" if args.images is not None \
        else "--preset"


def _configure(args: argparse.Namespace):
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
        check_clip(specs, needed_by=needed_by, poses_option=_poses_option(args))
    return specs, camera, title, sources, variants, calibrate, notes, identity


def _run(args: argparse.Namespace, stack: contextlib.ExitStack) -> int:
    import torch

    from fsof_torch import __version__
    from fsof_torch.io import environment
    from fsof_torch.io.atomic import lookup_error

    from . import distributed, resume
    from .inputs import JobError, file_digest, special_input
    from .job import JobConfig
    from .measure import PHOTO
    from .report import auto_road_lines, pair_table, summarize, write_clip_summaries, write_report
    from .sources import NetSpec, make_source, net_identity

    if args.threads < 1:
        raise JobError(f"--threads: expected >= 1, got {args.threads}")
    if args.threads > (os.cpu_count() or 1):  # (a huge count crashes torch's thread pool)
        raise JobError(f"--threads: expected at most this machine's {os.cpu_count() or 1} CPUs, got {args.threads}")
    import cv2

    # (a main() called in-process gives its caller's thread counts back when it returns)
    stack.callback(torch.set_num_threads, torch.get_num_threads())
    stack.callback(cv2.setNumThreads, cv2.getNumThreads())
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    try:
        device = torch.device(args.device)
    except RuntimeError:
        raise JobError(f"--device: not a torch device: {args.device!r}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise JobError(f"--device: {args.device!r} requested but CUDA is not available")
    if device.type == "meta":
        raise JobError(f"--device: {args.device!r} holds no data (shapes only); give cpu or cuda")
    if device.type != "cuda" or device.index is not None:  # (bare cuda: the process's GPU, set below)
        try:
            torch.empty(0, device=device)
        except Exception as err:  # torch raises RuntimeError, AssertionError, NotImplementedError, ...
            first = str(err).splitlines()[0].split(". ")[0] if str(err) else ""
            raise JobError(f"--device: cannot place a tensor on {args.device!r} ({type(err).__name__}: {first})") \
                from None
    world = distributed.init(device.type)
    stack.callback(distributed.finish, world)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", world.local_rank)

    inputs = _input_paths(args)  # (the files and folders the run reads, by option: checked three ways below)
    for option, path in (*inputs.items(), ("--out", args.out), ("--json", args.json)):
        if option != "--net" and (bad := lookup_error(path, option)) is not None:
            raise JobError(bad)  # (Python's own look-ups of such a path raise: before any of them)
    for option, path in inputs.items():  # (a FIFO: "no file at", or a read that waits for a writer)
        if (bad := special_input(path, option)) is not None:
            raise JobError(bad)
    out = args.out if args.out is not None else default_out(args)
    resume.check_out_path(out)
    resume.check_json_path(args.json, out, inputs)
    if not args.no_figures:
        import importlib.util

        if importlib.util.find_spec("matplotlib") is None:
            raise JobError("figures need matplotlib (pip install matplotlib), or give --no-figures")
    specs, camera, title, sources, variants, calibrate, notes, input_identity = _configure(args)
    resume.check_inputs_outside(out, sources, inputs)
    odometry_sigma = _odometry_sigma(args.odometry_sigma, variants)
    if odometry_sigma is not None:
        x, z, yaw = args.odometry_sigma
        notes.append(f"Variant given_images: the images may move the odometry's planar motion within {x:g} m "
                     f"sideways, {z:g} m forward and {yaw:g}° of yaw a frame (Gaussian priors).")
    fit_options = _fit_options(args.fit_options, variants, calibrate)
    if fit_options is not None:
        notes.append(f"The road motion from the images with fit_image's options {json.dumps(fit_options)} "
                     f"(--fit-options).")
    road_options = _road_options(args.road_options)
    if road_options is not None:
        notes.append(f"The road found in the images with detect_road's options {json.dumps(road_options)} "
                     f"(--road-options).")
    net_spec = NetSpec(args.net, args.net_contract or "auto", args.checkpoint) if args.net is not None else None
    built = {s: make_source(s, weights=args.testnet_weights, net=net_spec, device=device) for s in sources}
    # again: --net's module may set its own counts when imported (research code often does)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)

    # replace uses no scale: the default's in the identity, as for a confidence run without --scale
    scale = DEFAULT_SCALE if args.scale is None else args.scale
    identity = {"version": __version__, "library_code": resume.code_digest(),
                "dependencies": dict(resume.dependency_versions()), "input": input_identity,
                "sources": sources, "variants": variants,
                "mode": args.mode, "scale": scale, "fit_roll": args.fit_roll, "fit_pitch": args.fit_pitch,
                # a road folder or file by its resolved path and contents in "input", however spelled
                "road": args.road if args.road in (None, "auto") else "given",
                "calibrate_pitch": calibrate, "odometry_sigma": odometry_sigma,
                "testnet_weights": file_digest(args.testnet_weights) if args.testnet_weights is not None
                and "testnet" in sources else None,
                "net": net_identity(net_spec) if "net" in sources else None, "outputs": sources,
                "photometric": [kind for _, kind, _ in PHOTO]}
    if fit_options is not None:  # (no key without it: a run without the option has the identity it had)
        identity["fit_options"] = fit_options
    if road_options is not None:  # (as fit_options)
        identity["road_options"] = road_options
    if device.type != "cpu":
        # a GPU's kernels round otherwise (and a network's convolutions may run in TF32): its
        # records are not the CPU's. (No key on the CPU: a CPU run's identity is as before.)
        identity["device"] = device.type
    error = None
    if world.is_main:
        try:
            stack.enter_context(resume.locked(out))
            identity = _earlier_road_spelling(out, identity)
            resume.prepare(out, identity, overwrite=args.overwrite)
            if args.json is not None:  # (an earlier run's, written again last; through a link, as written)
                Path(os.path.realpath(args.json)).unlink(missing_ok=True)
        except JobError as err:
            error = str(err)
    error, identity = distributed.broadcast_object((error, identity), world)
    if error is not None:
        raise JobError(error)
    fp = resume.fingerprint(identity)
    cfg = JobConfig(out=out, sources=sources, variants=variants, mode=args.mode, scale=scale,
                    fit_roll=args.fit_roll, fit_pitch=args.fit_pitch, road_auto=args.road == "auto", calibrate=calibrate,
                    odometry_sigma=odometry_sigma, fit_options=fit_options or {},
                    road_options=road_options or {}, overwrite=args.overwrite,
                    figures=not args.no_figures,
                    progress=not args.no_progress and world.is_main, title=title, notes=notes,
                    fingerprint=fp, device=str(device))
    from .calibrate import clip_options

    needed_by = clip_options(calibrate, variants)
    if needed_by:
        from .job import clip_fingerprint

        # (digested before the fit reads them: a frame saved anew meanwhile leaves its old digest, redone)
        cfg.clip_fingerprint = clip_fingerprint(specs, progress=cfg.progress)
        cfg.clip = _fit_clip(specs, camera, cfg, built, device, needed_by=needed_by, poses_option=_poses_option(args))
        notes.append(_mounting_note(cfg.clip, calibrate, len(specs), variants))
    if world.distributed:
        notes.append(f"Run on {world.world_size} processes ({world.backend}); pairs strided over the ranks.")
    records = _run_shard(specs, cfg, built, world, paths={**inputs, "--out": out, "--json": args.json})
    if records is None:
        return 2  # another process stopped on its pairs' input, and rank 0 reports it
    names = [s.name for s in specs]
    metrics, extra = pair_table(records, names, cfg)
    metrics, extra = distributed.all_reduce_sum(metrics, world), distributed.all_reduce_sum(extra, world)
    gathered = distributed.gather_objects(records, world)
    if not world.is_main:
        return 0
    order = {n: i for i, n in enumerate(names)}
    key = {(s, v): j for j, (s, v) in enumerate((s, v) for s in sources for v in variants)}
    records = sorted((r for rs in gathered for r in rs), key=lambda r: (order[r["pair"]], key[(r["source"], r["variant"])]))
    summary = summarize(metrics, extra, records, cfg, world_size=world.world_size, identity=identity)
    if cfg.clip is not None:  # (None where no pair's fit succeeded: the nominal mounting was kept)
        summary["calibrated_mounting"] = cfg.clip.mounting if cfg.clip.fitted else None
    # what produced the report (the same library_code and dependencies as the identity; beside them
    # the command's options, the CPU, GPU and thread counts, which the identity leaves out)
    summary["environment"] = environment(command=command_name(), options=vars(args), seed=input_identity.get("seed"),
                                         device=device, packages=(Path(resume.__file__).parent,))
    if cfg.figures:
        write_clip_summaries(summary, cfg)
    table = write_report(summary, cfg, args.json)
    print(f"\n{title}\n\n{table}\n")
    for n in summary["notes"]:
        print(f"- {n}")
    for line in auto_road_lines(summary):  # --road auto: the flagged pairs and why, as in report.md
        print(line)
    print(f"\nreport: {out / 'report.md'} and {out / 'report.json'}")
    return 0


def _earlier_road_spelling(out: Path, identity: dict) -> dict:
    """The identity of the run in ``out`` where it differs from ``identity`` only in ``road``
    holding --road as it was typed, as earlier runs recorded it (e.g. ``"d/road"`` for
    ``"given"``): the same road, whose resolved path and contents ``input`` pins, so that run's
    records are reused. Else ``identity``."""
    import json

    from .resume import MANIFEST, fingerprint

    try:
        old = json.loads((out / MANIFEST).read_text()).get("identity")
    except (OSError, ValueError, AttributeError):
        return identity
    typed = old.get("road") if isinstance(old, dict) else None
    if (identity["road"] == "given" and isinstance(typed, str) and typed not in ("auto", "given")
            and fingerprint({**old, "road": "given"}) == fingerprint(identity)):
        return {**identity, "road": typed}
    return identity


def _default_height_note(variants: list[str]) -> str:
    """The report's note where user data refines with the poses' odometry (``variants``: of given and
    given_images) at a height nobody gave: the default, KITTI's camera. The poses' translation is in
    metres and the road's flow scales with translation / height, so another camera's height scales
    that flow (a camera 2.8 m high, refined at 1.65 m: 1.7 times its road flow)."""
    return (f"Camera height not given (--height): {DEFAULT_HEIGHT} m, KITTI's camera, is assumed; the road flow of the "
            f"odometry from --poses (variant{'s' if len(variants) > 1 else ''} {' / '.join(variants)}) scales with "
            f"1 / height: give the camera's height above the road, or --calibrate-pitch (with poses it calibrates "
            f"the height over the clip).")


def _mounting_note(clip, calibrate: bool, pairs: int, variants=("sequence", "given_pitch")) -> str:
    """The report's note on the clip's calibrated mounting, or on its absence where no pair's fit
    over the clip succeeded, or none of those that did moves enough to show it (the nominal mounting is kept,
    ``refine.calibrate.fit_clip``). A calibrated mounting comes from the clip's first fits (with the
    nominal mounting); the note also says on how many pairs the fit redone with it succeeded (the
    records' ``clip_fit_success``). ``variants``: those of the run."""
    m = clip.mounting
    uses = [v for v in ("sequence", "given_pitch") if v in variants]
    users = "every variant" if calibrate else f"variant{'s' if len(uses) > 1 else ''} {' / '.join(uses)}"
    if not clip.fitted:
        succeeded = sum(bool(s) for s in clip.success.values())
        why = (f"no pair's fit over the clip succeeded (0 of {pairs})" if not succeeded else
               f"the {succeeded} of {pairs} pairs whose fits succeeded do not move, or too little for their "
               f"images to show it (still frames, or a vehicle creeping by millimetres, measure no mounting)")
        return (f"Mounting not calibrated: {why}; {users} "
                f"use{'s' if calibrate or len(uses) == 1 else ''} the nominal mounting (pitch {m['pitch_deg']:.2f}°, roll "
                f"{m['roll_deg']:.2f}°)" + (", so --calibrate-pitch changed nothing." if calibrate else "."))
    confirmed = sum(bool(s) for s in clip.success.values())  # (the second pass's)
    return (f"Mounting calibrated over the clip from its images (the fits of {clip.fitted} of {pairs} pairs): pitch "
            f"{m['pitch_deg']:.2f}°, roll {m['roll_deg']:.2f}°"
            + (f", height {m['height_m']:.3f} m (scale from the poses)" if "height_m" in m else "")
            + f"; {users} use{'s' if calibrate or len(uses) == 1 else ''} it. The clip's fit, redone with it, "
            f"succeeded on {confirmed} of {pairs} pairs"
            + (": no pair confirms the mounting (a road mask that holds more than the road, such as one covering "
               "the whole image, misleads the fit)." if not confirmed else "."))


def _run_shard(specs, cfg, built: dict, world, paths: dict[str, Path | None] | None = None) -> list[dict] | None:
    """Run this process's share of the pairs (``refine.job.run_pairs``). Under torchrun, an input
    error on one process's pairs (a corrupt file, a file it may not read, say) stops every process
    before the collectives the others would otherwise wait in: the processes exchange their
    errors, the one that failed raises its own (a JobError), rank 0 the first one (naming its
    rank), the others return None. ``paths``: the run's path options, which a file the process
    may not read or write is named under (:func:`refine.inputs.permission_message`)."""
    from . import distributed
    from .inputs import JobError, permission_message
    from .job import run_pairs

    error = None
    try:
        records = run_pairs(distributed.shard(specs, world), cfg, built, rank=world.rank)
    except (JobError, FileNotFoundError, IsADirectoryError, ValueError, PermissionError) as err:
        if not world.distributed:
            raise
        error = permission_message(err, paths or {}, ("--out", "--json")) if isinstance(err, PermissionError) \
            else str(err)
        records = None
    if world.distributed:
        failed = [(rank, e) for rank, e in enumerate(distributed.gather_objects(error, world)) if e is not None]
        if error is not None:
            raise JobError(error)
        if failed and world.is_main:
            rank, first = failed[0]
            raise JobError(f"{first} (on rank {rank})")
        if failed:
            return None
    return records


def _fit_clip(specs, camera, cfg, built: dict, device, *, needed_by: str, poses_option: str):
    """The clip's road motion and calibrated camera (refine.calibrate); road masks the pairs' own,
    or detected on DIS's flow where the road is auto (the refinement of every source then uses
    those detections: each pair's road is detected once)."""
    import torch

    from .calibrate import fit_clip
    from .job import road_mask
    from .sources import make_source

    dis = built.get("dis") or make_source("dis", weights=None, net=None, device=device)

    def road_for(pair: dict) -> tuple[torch.Tensor, dict]:
        if pair.get("road") is not None and not cfg.road_auto:
            return pair["road"], {}
        cam = (camera if camera is not None else pair["camera"]).to(torch.float64)
        road, _, info = road_mask(pair, dis(pair, None), cam, cfg)
        return road, info

    cam = camera if camera is not None else specs[0].load()["camera"]
    return fit_clip(specs, cam, road_for, progress=cfg.progress, needed_by=needed_by, poses_option=poses_option,
                    **cfg.fit_options)


#: the exit status of a run stopped by Ctrl-C (KeyboardInterrupt): 128 + SIGINT, as a shell reports it
INTERRUPTED = 130


#: the exit status of a run whose stdout's reader went away (``| head``): Python's own on EPIPE
STDOUT_CLOSED = 1
#: the exit status of a run that met a full disk (or a spent quota) writing its outputs
WRITE_FAILED = 1


def main(argv: list[str] | None = None) -> int:
    """The job's entry point; returns the exit status (0 done, 1 stdout closed by its reader or the
    disk full, 2 bad input, 130 interrupted)."""
    from fsof_torch.io.progress import tolerant_stdout, warnings_above_bars

    try:
        # (the tables' Δ and ° where stdout writes cp1252 or ASCII; a warning on lines of its own, not the bar's)
        with tolerant_stdout(), warnings_above_bars():
            return _main(argv)
    except KeyboardInterrupt:
        # (after the run's ExitStack closed: the --out lock released, the process group finished)
        print("refine: interrupted; the pairs finished so far are kept: run the command again "
              "(without --overwrite) to resume", file=sys.stderr)
        return INTERRUPTED
    except BrokenPipeError:
        # (the summary printed last, after report.md and report.json were written)
        from fsof_torch.io.progress import silence_stdout

        silence_stdout()
        print("refine: stdout was closed by its reader (a broken pipe); the pairs finished and the "
              "report written so far are kept", file=sys.stderr)
        return STDOUT_CLOSED
    except OSError as err:
        from fsof_torch.io.atomic import NO_SPACE

        if err.errno not in NO_SPACE:
            raise
        # (each file is written whole or not at all: the one that did not fit is not there)
        print(f"refine: {err.strerror.removeprefix('path: ')}; the pairs finished so far are kept: make room and "
              f"run the command again (without --overwrite) to resume", file=sys.stderr)
        return WRITE_FAILED


def _main(argv: list[str] | None) -> int:
    parser = build_parser(command_name())
    try:
        args = parser.parse_args(sys.argv[1:] if argv is None else list(argv))
    except SystemExit as exit_:  # argparse exits on --help and on bad options
        return int(exit_.code or 0)
    from fsof_torch import trust_image_range

    from .inputs import JobError

    # the job reads its frames from 8- and 16-bit files (or renders them) on 0..255 and vouches
    # for that range: a frame dark enough to pass for a 0..1 image (a lens cap, a tunnel) is
    # judged like any frame, its pair refined or flagged, rather than stopping the job
    with contextlib.ExitStack() as stack, trust_image_range():
        try:
            return _run(args, stack)
        except (JobError, FileNotFoundError, IsADirectoryError, ValueError) as err:
            # JobError: an option or input file the job rejected; FileNotFoundError /
            # IsADirectoryError / ValueError: a reader or the library rejected an input file or
            # value (their messages name it)
            print(f"error: {err}", file=sys.stderr)
            return 2
        except PermissionError as err:  # an input the process may not read, an output it may not write
            from .inputs import permission_message

            out = args.out if args.out is not None else default_out(args)
            paths = {**_input_paths(args, net=False), "--out": out, "--json": args.json}
            print(f"error: {permission_message(err, paths, outputs=('--out', '--json'))}", file=sys.stderr)
            return 2


if __name__ == "__main__":
    sys.exit(main())
