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
import os
import sys
from pathlib import Path

from .configure import configure, parse_fit_options, parse_odometry_sigma, parse_road_options, poses_option
from .options import DEFAULT_SCALE, build_parser, command_name, default_out


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
    specs, camera, title, sources, variants, calibrate, notes, input_identity = configure(args)
    resume.check_inputs_outside(out, sources, inputs)
    odometry_sigma = parse_odometry_sigma(args.odometry_sigma, variants)
    if odometry_sigma is not None:
        x, z, yaw = args.odometry_sigma
        notes.append(f"Variant given_images: the images may move the odometry's planar motion within {x:g} m "
                     f"sideways, {z:g} m forward and {yaw:g}° of yaw a frame (Gaussian priors).")
    fit_options = parse_fit_options(args.fit_options, variants, calibrate)
    if fit_options is not None:
        notes.append(f"The road motion from the images with fit_image's options {json.dumps(fit_options)} "
                     f"(--fit-options).")
    road_options = parse_road_options(args.road_options)
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
        cfg.clip = _fit_clip(specs, camera, cfg, built, device, needed_by=needed_by, poses_option=poses_option(args))
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
