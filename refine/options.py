"""The command line of the refinement job (``python -m refine``, ``fsof-refine``): its parser,
the options' defaults and value types, and the output folder named after the input."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DEFAULT_PAIRS = 4
DEFAULT_SIZE = (375, 1242)
DEFAULT_OUT = Path("refine_out")
DEFAULT_HEIGHT = 1.65  # m, KITTI's camera over the road
DEFAULT_SCALE = 2.0  # px, the Cauchy scale of --mode confidence
#: the one-line description of the command, in its --help
DESCRIPTION = "refine optical flow with the freespace model inside the road mask."
#: the defaults of the options that only some inputs use: the parser leaves them None (not given),
#: so that one given to an input that does not use it is refused even at its default value
#: (:func:`refine.configure._refuse_unused`); :func:`refine.configure._with_defaults` fills them in after
#: that check
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
        prog=prog, description=DESCRIPTION,
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
