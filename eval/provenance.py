"""The ``environment`` block of the evaluation job's JSON outputs: :func:`fsof_torch.io.environment`
with the subcommand's command, its options and the code of this package."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def environment(subcommand: str, args: argparse.Namespace, *, seed: int | None = None,
                device: Any = "cpu") -> dict[str, Any]:
    """What produced a JSON output of ``subcommand`` run with ``args`` (its parsed options): the
    command, the options, ``seed`` (None where the results drew none), the library's version and
    the digest of its code with this package's, the dependencies' versions, the CPU, the thread
    counts, and ``device`` with the GPU's name."""
    from fsof_torch.io import environment as library_environment

    from .__main__ import command_name

    return library_environment(command=f"{command_name()} {subcommand}", options=vars(args), seed=seed,
                               device=device, packages=(Path(__file__).parent,))
