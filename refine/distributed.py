"""Running the job on several processes: ``torchrun --nproc-per-node N -m refine ...``.

torchrun starts N copies and sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK`` and the rendezvous
address; each copy joins one process group (gloo on CPU, nccl when the job runs on CUDA), takes
every N-th pair (``pairs[rank::N]``: each pair exactly once) and writes that pair's outputs.
Then the per-pair sums and pixel counts of the metrics are all-reduced and every record is
gathered to rank 0, which writes the one report. The sums are reduced per pair, in the pairs'
order, so the report equals the single-process one digit for digit.

Without torchrun (no ``WORLD_SIZE`` or ``WORLD_SIZE=1``) nothing here starts a process group.
Variables that are no whole number in their range, or a ``WORLD_SIZE`` above 1 without ``RANK``
(left in the shell, not set by torchrun), stop the job with a message naming the variable.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from typing import Any, Sequence, TypeVar

import torch

T = TypeVar("T")


@dataclass(frozen=True)
class World:
    """This process's place among the job's processes."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


#: How long a process waits for the others' pairs (torch.distributed's timeout).
WAIT_FOR_OTHERS = datetime.timedelta(days=7)


def init(device: str = "cpu") -> World:
    """Join the process group torchrun set up (gloo for ``device="cpu"``, nccl for CUDA), or
    return the single-process world."""
    world_size = environment_number("WORLD_SIZE", 1, minimum=1)
    if world_size == 1:
        return World()
    import torch.distributed as dist

    rank, local_rank = (environment_number("RANK", None, below=world_size),
                        environment_number("LOCAL_RANK", 0, below=world_size))
    backend = "nccl" if device.startswith("cuda") else "gloo"
    if backend == "nccl":
        torch.cuda.set_device(local_rank)
    if not dist.is_initialized():
        # A process that finished its pairs waits for the others' in the gather: as long as the
        # longest share takes, not the backends' default 10 to 30 minutes (a process that fails
        # ends the run through torchrun, so no process waits on a dead one).
        dist.init_process_group(backend=backend, timeout=WAIT_FOR_OTHERS)
    return World(rank=rank, world_size=world_size, local_rank=local_rank, backend=backend)


def environment_number(name: str, default: int | None, *, minimum: int = 0, below: int | None = None,
                       job: str = "refine") -> int:
    """The whole number in the environment variable ``name`` (``default`` where it is unset; None:
    it must be set), from ``minimum`` up and under ``below``; else a JobError naming the variable
    (and how to start ``python -m JOB`` with torchrun): a ``WORLD_SIZE`` left in the shell without
    torchrun's ``RANK`` stopped the job with a ``KeyError: 'RANK'`` traceback, a ``WORLD_SIZE``
    that is no number with int()'s message alone."""
    from .inputs import JobError

    text = os.environ.get(name)
    if text is None and default is not None:
        return default
    started = "torchrun sets it for each process it starts"
    if text is None:
        raise JobError(f"environment variable {name}: not set, while WORLD_SIZE is {os.environ['WORLD_SIZE']} "
                       f"({started}); start the job with torchrun --nproc-per-node N -m {job} ..., or unset "
                       f"WORLD_SIZE to run it in one process")
    try:
        value = int(text)
    except ValueError:
        value = None
    if value is None or value < minimum or (below is not None and value >= below):
        bound = f"from {minimum} up" if below is None else f"from {minimum} to {below - 1}"
        raise JobError(f"environment variable {name}: expected a whole number {bound} ({started}), got {text!r}")
    return value


def shard(items: Sequence[T], world: World) -> list[T]:
    """This process's share: every ``world_size``-th item from its rank (strided)."""
    return list(items[world.rank::world.world_size])


def all_reduce_sum(values: torch.Tensor, world: World) -> torch.Tensor:
    """The element-wise sum of ``values`` over the processes (a copy; ``values`` unchanged)."""
    if not world.distributed:
        return values.clone()
    import torch.distributed as dist

    device = torch.device("cuda", world.local_rank) if world.backend == "nccl" else torch.device("cpu")
    total = values.to(device=device, copy=True)
    dist.all_reduce(total, op=dist.ReduceOp.SUM)
    return total.to(values.device)


def gather_objects(obj: Any, world: World) -> list[Any]:
    """``obj`` of every process, in rank order (on every process)."""
    if not world.distributed:
        return [obj]
    import torch.distributed as dist

    out: list[Any] = [None] * world.world_size
    dist.all_gather_object(out, obj)
    return out


def broadcast_object(obj: Any, world: World) -> Any:
    """Rank 0's ``obj`` on every process."""
    if not world.distributed:
        return obj
    import torch.distributed as dist

    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def barrier(world: World) -> None:
    if world.distributed:
        import torch.distributed as dist

        dist.barrier()


def finish(world: World) -> None:
    """Leave the process group (if this process joined one)."""
    if world.distributed:
        import torch.distributed as dist

        if dist.is_initialized():
            dist.destroy_process_group()
