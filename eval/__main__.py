"""``python -m eval SUBCOMMAND``: the evaluation job. Each subcommand lives in its own module of
this package, exposing ``add_arguments(parser)`` and ``run(args) -> int``; it is imported only
when chosen, so ``--help`` stays fast."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    # name: (module, one-line help)
    "synth": ("eval.synth", "render a synthetic driving sequence with exact ground truth to disk"),
    "train": ("eval.train", "train the test net unsupervised, without and with the freespace term"),
    "tables": ("eval.tables", "the paper's fitting tables (CVC12-like, CARLA-like, real KITTI)"),
    "noise": ("eval.noise", "noise robustness and pose estimation from noisy flow (plots)"),
    "vflow": ("eval.vflow", "V-flow map, fitted curve and fitted F_v map of a flow (PNGs)"),
}


def command_name() -> str:
    """The command the job was started by, as its usages name it: ``fsof-eval`` (the console
    script pyproject installs; its wrapper leaves that name in ``sys.argv[0]``) or ``python -m eval``."""
    return "fsof-eval" if sys.argv and Path(sys.argv[0] or ".").stem == "fsof-eval" else "python -m eval"


def build_parser(prog: str = "python -m eval") -> argparse.ArgumentParser:
    """The job's subcommands; ``prog`` names the command in its usage and errors (:func:`command_name`)."""
    parser = argparse.ArgumentParser(prog=prog, description="the evaluation job: the paper's "
                                     "experiments and the test net's training, one subcommand each")
    sub = parser.add_subparsers(dest="command", metavar="SUBCOMMAND")
    for name, (_, help_text) in SUBCOMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    return parser


#: the exit status of a run stopped by Ctrl-C (KeyboardInterrupt): 128 + SIGINT, as a shell reports it
INTERRUPTED = 130
#: the exit status of a run whose stdout's reader went away (``| head``): Python's own on EPIPE
STDOUT_CLOSED = 1
#: the exit status of a run that met a full disk (or a spent quota) writing its outputs
WRITE_FAILED = 1


def main(argv: list[str] | None = None) -> int:
    """The job's entry point; returns the exit status (0 done, 2 bad input, 1 where a subcommand
    says so, stdout was closed by its reader or the disk is full, 130 interrupted), also for ``--help`` and for the errors argparse reports, rather
    than exiting."""
    from fsof_torch.io.progress import tolerant_stdout, warnings_above_bars

    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        # (the tables' σ, Δ and ° where stdout writes cp1252 or ASCII; a warning during training, such as
        # the freespace loss's, on lines of its own rather than on the bar's)
        with tolerant_stdout(), warnings_above_bars():
            return _main(argv)
    except KeyboardInterrupt:
        # (each output file is written whole or not at all, through a temporary file)
        name = f"eval {argv[0]}" if argv and argv[0] in SUBCOMMANDS else "eval"
        print(f"{name}: interrupted; the files written so far are kept, each one whole", file=sys.stderr)
        return INTERRUPTED
    except BrokenPipeError:
        # (each subcommand prints its results after writing its files)
        from fsof_torch.io.progress import silence_stdout

        silence_stdout()
        name = f"eval {argv[0]}" if argv and argv[0] in SUBCOMMANDS else "eval"
        print(f"{name}: stdout was closed by its reader (a broken pipe); the files written so far are kept, "
              f"each one whole", file=sys.stderr)
        return STDOUT_CLOSED
    except OSError as err:
        from fsof_torch.io.atomic import NO_SPACE

        if err.errno not in NO_SPACE:
            raise
        name = f"eval {argv[0]}" if argv and argv[0] in SUBCOMMANDS else "eval"
        print(f"{name}: {err.strerror.removeprefix('path: ')}; the files written so far are kept, each one whole",
              file=sys.stderr)
        return WRITE_FAILED


def _main(argv: list[str]) -> int:
    try:
        if not argv or argv[0] not in SUBCOMMANDS:
            parser = build_parser(command_name())
            if not argv:
                parser.error(f"missing SUBCOMMAND; choose from {', '.join(SUBCOMMANDS)}")
            if argv[0] not in ("-h", "--help"):
                parser.error(f"unknown subcommand {argv[0]!r}; choose from {', '.join(SUBCOMMANDS)}")
            parser.print_help()
            return 0
        name = argv[0]
        module = importlib.import_module(SUBCOMMANDS[name][0])
        parser = argparse.ArgumentParser(prog=f"{command_name()} {name}", description=SUBCOMMANDS[name][1])
        module.add_arguments(parser)
        args = parser.parse_args(argv[1:])
    except SystemExit as exit_:  # argparse exits on --help and on bad options
        return int(exit_.code or 0)
    if getattr(args, "seed", None) is not None:
        # (the scenes' seed range, checked before any work: exit 2 naming the option)
        from fsof_torch.data.scene.config import check_seed

        try:
            check_seed(args.seed)
        except ValueError as err:
            print(f"error: --{err}", file=sys.stderr)
            return 2
    try:
        return int(module.run(args) or 0)
    except PermissionError as err:  # an input the process may not read, an output it may not write
        from refine.inputs import permission_message

        paths = {f"--{k.replace('_', '-')}": v for k, v in vars(args).items() if isinstance(v, Path)}
        outputs = tuple(o for o in paths if o in ("--out", "--json", "--dump-first-step"))
        print(f"error: {permission_message(err, paths, outputs)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
