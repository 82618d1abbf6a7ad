"""``python -m eval train``: does a freespace term help a flow network learn road flow?

The test net (:class:`fsof_torch.training.testnet.TinyRAFT`) is trained twice from the same seed on the
same synthetic driving pairs (:func:`fsof_torch.data.scene.render_sequence`, rendered once and kept in
memory), for the same number of steps with the same batches: once with the unsupervised loss
alone (:class:`~fsof_torch.training.losses.UnsupervisedFlowLoss`: photometric L1 + SSIM with a
forward-backward occlusion mask, edge-aware smoothness), once with
:class:`~fsof_torch.training.losses.FreespaceFlowLoss` added (the road flow of the freespace model from the
pairs' odometry, inside their road masks). Both nets, and the untrained one, are then evaluated on
held-out pairs of another seed against the exact ground truth: end-point error (and the others of
:func:`fsof_torch.evaluation.metrics.flow_metrics`) inside the road and outside it, and the
photometric error of each estimate (census distance and SSIM beside L1: the net is trained on L1
and SSIM, so census is the judge it was not trained on).

Prints a table, writes ``--json PATH``, and with ``--out DIR`` saves both nets' ``state_dict``.

Distributed: ``torchrun --nproc-per-node N -m eval train ...`` trains with DistributedDataParallel
(gloo on CPU, nccl with ``--device cuda``). Every process draws the same global batch of
``--batch`` pairs and takes every N-th of them; DDP averages the gradients, which equals the
gradient of the global batch's mean loss (the losses are means over samples, and every process
holds ``--batch / N`` of them). Rank 0 evaluates, prints and writes the outputs.
"""

from __future__ import annotations

import argparse
import io
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from fsof_torch.geometry.camera import Camera
from fsof_torch.io import write_json
from fsof_torch.io.atomic import write_bytes
from fsof_torch.training.losses import CompositeLoss, FreespaceFlowLoss, UnsupervisedFlowLoss
from fsof_torch.evaluation.metrics import flow_metrics
from fsof_torch.evaluation.photometric import photometric_error_maps
from fsof_torch.data.scene import collate, render_sequence
from fsof_torch.data.scene.config import MAX_SEED
from fsof_torch.training.testnet import TinyRAFT, count_parameters

from eval.paths import (bad_file, bad_folder, bad_json_target, bad_lookup, bad_size, file_path, first_bad, given_path,
                        make_parent, remove_outputs)
from eval.provenance import environment

__all__ = ["add_arguments", "run", "main", "render_pairs", "train_net", "evaluate_net", "one_cycle_lr",
           "TrainingDiverged"]

# the held-out scenes' seed: --seed + HELD_OUT
HELD_OUT = 1000
#: the largest learning rate taken: AdamW's first step, lr / (1 - 0.9) = 10 lr, is a float32 scalar
#: (at most 3.4e38; a rate within a rounding of that overflowed inside AdamW: a traceback)
MAX_LR = 1e37


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from fsof_torch.data.scene.render import MAX_FRAME, MAX_SIDE

    parser.add_argument("--steps", type=int, default=150, help="optimiser steps per run (default 150)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the net, the batches and the training scenes (held-out: seed + 1000; default 0)")
    parser.add_argument("--preset", default="default", help="synthetic scene preset (fsof_torch.data.scene.PRESETS; default: default)")
    parser.add_argument("--size", type=int, nargs=2, default=(64, 224), metavar=("H", "W"),
                        help=f"image size of the rendered pairs, each side 16 to {MAX_SIDE} (default 64 224)")
    parser.add_argument("--batch", type=int, default=4, help="pairs per step, at most --train-pairs (default 4)")
    parser.add_argument("--lr", type=float, default=1e-3, help="AdamW learning rate (default 1e-3)")
    parser.add_argument("--freespace-weight", type=float, default=0.1,
                        help="weight of the freespace term in the second run (default 0.1)")
    parser.add_argument("--odometry", choices=("given", "fit"), default="given",
                        help="freespace term from the pairs' odometry, or fitted to the prediction (default: given)")
    parser.add_argument("--iters", type=int, default=4, help="GRU iterations of the test net (default 4)")
    parser.add_argument("--train-pairs", type=int, default=24,
                        help=f"training pairs rendered, 1 to {MAX_FRAME} (default 24)")
    parser.add_argument("--test-pairs", type=int, default=6,
                        help=f"held-out pairs rendered, 1 to {MAX_FRAME} (default 6)")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch threads, at most the machine's CPUs (0: leave torch's default)")
    parser.add_argument("--json", type=file_path, default=None, metavar="PATH", help="write the results as JSON here")
    parser.add_argument("--out", type=given_path, default=None, metavar="DIR",
                        help="save both nets' state_dicts in this folder")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument("--device", default="cpu", help="torch device (default cpu; cuda: the process's GPU)")
    parser.add_argument("--dump-first-step", type=file_path, default=None, metavar="PATH",
                        help="save the first step's loss and gradients of each run here (torch.save), to "
                             "compare a distributed run with a single process")


class TrainingDiverged(ValueError):
    """Training produced a non-finite flow, loss or parameter: the run is stopped (message naming ``lr``)."""


@dataclass(frozen=True)
class Ranks:
    """This process's place among torchrun's processes (one process: rank 0 of 1)."""

    rank: int = 0
    world_size: int = 1

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def _bad_environment() -> str | None:
    """torchrun's variables, as the refine job checks them: a ``WORLD_SIZE`` left in the shell
    without ``RANK`` failed in torch's rendezvous with a traceback, one that is no number in
    int()'s."""
    from refine.distributed import environment_number
    from refine.inputs import JobError

    try:
        world_size = environment_number("WORLD_SIZE", 1, minimum=1, job="eval train")
        if world_size > 1:
            for name, default in (("RANK", None), ("LOCAL_RANK", 0)):
                environment_number(name, default, below=world_size, job="eval train")
    except JobError as err:
        return str(err)
    return None


def _join_process_group(device: torch.device) -> Ranks:
    """Join the process group torchrun set up (gloo on CPU, nccl on CUDA), if it set one up."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size <= 1:
        return Ranks()
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return Ranks(dist.get_rank(), dist.get_world_size())


def _to(data: dict, device: torch.device) -> dict:
    """A collated batch dict on ``device`` (tensors, the camera, the odometry dict)."""
    out = {}
    for k, v in data.items():
        if isinstance(v, torch.Tensor):
            out[k] = v.to(device)
        elif isinstance(v, Camera):
            out[k] = v.to(device=device)
        elif isinstance(v, dict):
            out[k] = {kk: vv.to(device) if isinstance(vv, torch.Tensor) else vv for kk, vv in v.items()}
        else:
            out[k] = v
    return out


def render_pairs(preset: str, num_pairs: int, *, seed: int, size: tuple[int, int],
                 progress: bool = False) -> dict:
    """``num_pairs`` consecutive pairs of a synthetic sequence, collated into one batch dict."""
    return collate(render_sequence(preset, num_pairs, seed=seed, size=tuple(size), progress=progress))


def _select(data: dict, idx: torch.Tensor) -> dict:
    """Rows ``idx`` of a collated batch: tensors, the camera and the odometry dict."""
    cam: Camera = data["camera"]
    return {
        "image1": data["image1"][idx], "image2": data["image2"][idx], "road": data["road"][idx],
        "camera": Camera(cam.K[idx], cam.height[idx], cam.roll[idx], cam.pitch[idx]),
        "odometry": {k: data["odometry"][k][idx] for k in ("x_d", "z_d", "yaw")},
    }


def build_loss(freespace_weight: float, odometry: str = "given") -> CompositeLoss:
    """The training loss: the unsupervised term, plus the freespace term if its weight is > 0."""
    terms = {"unsupervised": (1.0, UnsupervisedFlowLoss())}
    if freespace_weight > 0:
        terms["freespace"] = (freespace_weight, FreespaceFlowLoss(odometry=odometry))
    return CompositeLoss(terms)


def one_cycle_lr(step: int, steps: int, lr: float) -> float:
    """The learning rate of step ``step`` (0-based) of ``steps``: RAFT's one-cycle schedule in miniature.

    A linear warm-up from ``lr / 25`` over the first 5 % of the steps, then a linear decay to
    ``lr / 25 / 1e4`` at the last step: the values of torch's ``OneCycleLR(max_lr=lr,
    total_steps=steps, pct_start=0.05, anneal_strategy="linear")``, bit for bit, wherever that
    schedule is defined with a warm-up (more than 20 steps). With at most 20 steps the warm-up is
    shorter than a step, so there is none: the first step runs at ``lr`` (where ``OneCycleLR``
    divides by zero at 20 steps, and below 20 starts part-way down, a single step at ``lr / 25 /
    1e4``, which trains nothing).
    """
    start_lr, min_lr = lr / 25.0, lr / 25.0 / 1e4
    warm_end = max(float(0.05 * steps) - 1, 0.0)  # the step at which the warm-up reaches lr
    if step <= warm_end and warm_end > 0:
        return (lr - start_lr) * ((step - 0.0) / (warm_end - 0.0)) + start_lr
    last = steps - 1
    pct = (step - warm_end) / (last - warm_end) if last > warm_end else 0.0
    return (min_lr - lr) * pct + lr


def train_net(data: dict, *, steps: int, seed: int, batch: int, lr: float, freespace_weight: float,
              iters: int, odometry: str = "given", progress: bool = True, desc: str = "train",
              ranks: Ranks = Ranks(), device: torch.device | str = "cpu",
              first_step: dict | None = None) -> tuple[TinyRAFT, dict]:
    """Train a fresh ``TinyRAFT(seed=seed)`` on the collated pairs ``data``; the batches depend on ``seed`` only.

    Under torchrun (``ranks.distributed``) the net is wrapped in DistributedDataParallel and this
    process trains on every ``world_size``-th pair of each global batch of ``batch`` pairs.
    ``first_step``, when given, receives the first step's global mean loss and the gradients
    (averaged over the processes, before clipping).

    Returns the net (in eval mode) and a log: the last step's term values (global means) and the
    wall time.

    Raises:
        TrainingDiverged: a step's flow, loss, gradients' norm or updated parameters are not all
            finite (a learning rate too large for the run diverges so; the message names ``lr``, or
            ``freespace_weight`` where the first step's loss or gradients are not finite, before any
            update); every process raises at the same step.
    """
    from fsof_torch.io.progress import progress_bar, show_values

    device = torch.device(device)
    net = TinyRAFT(seed=seed, iters=iters).to(device)
    net.train()
    model: torch.nn.Module = net
    if ranks.distributed:
        from torch.nn.parallel import DistributedDataParallel

        model = DistributedDataParallel(net, device_ids=[device.index] if device.type == "cuda" else None)
    loss_fn = build_loss(freespace_weight, odometry)
    optimiser = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-5)
    gen = torch.Generator().manual_seed(seed)
    n = data["image1"].shape[0]
    values: dict[str, float] = {}
    start = time.perf_counter()
    bar = progress_bar(range(steps), enabled=progress, desc=desc, leave=False, dynamic_ncols=True)
    for step in bar:
        for group in optimiser.param_groups:
            group["lr"] = one_cycle_lr(step, steps, lr)
        idx = torch.randperm(n, generator=gen)[:batch]  # the global batch, the same on every process
        b = _to(_select(data, idx[ranks.rank::ranks.world_size]), device)
        local = b["image1"].shape[0]
        # Both directions in one pass: the backward flows feed the occlusion check.
        flows = model(torch.cat([b["image1"], b["image2"]]), torch.cat([b["image2"], b["image1"]]))
        if not _finite_everywhere(flows, ranks):
            raise _diverged(step, steps, lr, "the net's flow")
        fw = [f[:local] for f in flows]
        bw = [f[local:] for f in flows]
        total, terms = loss_fn(fw, b, flows_backward=bw)
        optimiser.zero_grad(set_to_none=True)
        total.backward()  # under DDP: gradients averaged over the processes
        reported = _mean_over_processes(torch.stack([total.detach(), *(v.detach() for v in terms.values())]), ranks)
        if not bool(torch.isfinite(reported).all()):  # (the global means: the same on every process)
            raise _diverged(step, steps, lr, "the loss", freespace_weight)
        if step == 0 and first_step is not None:
            first_step.update(loss=float(reported[0]), grads={k: p.grad.detach().cpu().clone()
                                                               for k, p in net.named_parameters() if p.grad is not None})
        # (a norm that overflows would scale every gradient to 0 or NaN: the net silently untrained)
        norm = torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        if not _finite_everywhere([norm], ranks):
            raise _diverged(step, steps, lr, "the gradients' norm", freespace_weight)
        optimiser.step()
        if not _finite_everywhere(list(net.parameters()), ranks):
            raise _diverged(step, steps, lr, "the net's parameters after the update")
        values = {"total": float(reported[0]), **{k: float(v) for k, v in zip(terms, reported[1:])}}
        show_values(bar, {k: f"{v:.3g}" for k, v in values.items()})
    net.eval()
    return net, {"final_loss": values, "seconds": time.perf_counter() - start}


def _finite_everywhere(tensors: list[torch.Tensor], ranks: Ranks) -> bool:
    """Whether every value of ``tensors`` is finite on every process (under DDP one all-reduce:
    the processes stop at the same step, none waits for the others in a collective)."""
    flag = torch.stack([torch.isfinite(t.detach()).all() for t in tensors]).all().to(torch.int32)
    if ranks.distributed:
        import torch.distributed as dist

        dist.all_reduce(flag, op=dist.ReduceOp.MIN)
    return bool(flag)


def _diverged(step: int, steps: int, lr: float, what: str, freespace_weight: float = 0.0) -> TrainingDiverged:
    """The error naming what is likely too large: the learning rate, or, where the first step's loss
    or gradients are not finite, before any update (which the learning rate plays no part in), the
    freespace term's weight."""
    if step == 0 and what != "the net's parameters after the update" and freespace_weight > 0:
        return TrainingDiverged(f"freespace_weight: training diverged at step 1 of {steps} ({what} not finite) "
                                f"before any update, which the learning rate plays no part in; the freespace "
                                f"weight {freespace_weight:g} is likely too large for this run: give a smaller one")
    return TrainingDiverged(f"lr: training diverged at step {step + 1} of {steps} ({what} not finite); the "
                            f"learning rate {lr:g} is likely too large for this run: give a smaller one")


def _mean_over_processes(values: torch.Tensor, ranks: Ranks) -> torch.Tensor:
    """The mean of per-process means over the processes: the global batch's mean (equal shares)."""
    if not ranks.distributed:
        return values
    import torch.distributed as dist

    values = values.clone()
    dist.all_reduce(values, op=dist.ReduceOp.SUM)
    return values / ranks.world_size


@torch.no_grad()
def evaluate_net(net: TinyRAFT, data: dict, *, chunk: int = 4) -> dict:
    """Metrics of the net's last estimate on ``data``, road, non-road and all pixels: KITTI-style
    flow metrics over the valid ground-truth pixels (``e_E``, ``Fl``, ...), and the photometric
    error of image 1 against image 2 warped by the estimate (``census``, ``ssim``, ``l1``, pooled
    over every pixel whose sample point, and window, falls inside image 2, with ``n_photometric``
    per kind): a net trained on a photometric loss of L1 and SSIM is judged by census too.

    A figure over no pixel is None (JSON null, printed '-'), not 0, which would read as perfect:
    the flow metrics of a region with no valid ground truth, a photometric error where every
    estimate's sample point (or window) leaves image 2."""
    flows = torch.cat([net(data["image1"][i:i + chunk], data["image2"][i:i + chunk])[-1]
                       for i in range(0, data["image1"].shape[0], chunk)])
    road, valid, gt = data["road"], data["valid"], data["flow"]
    photo = photometric_error_maps(data["image1"], data["image2"], flows)
    out = {}
    for region, mask in (("road", road), ("non_road", ~road), ("all", None)):
        metrics = flow_metrics(flows, gt, mask, valid)
        out[region] = metrics if metrics["n_pixels"] else {k: None for k in metrics} | {"n_pixels": 0}
        for kind, (error, ok) in photo.items():
            counted = ok if mask is None else ok & mask
            n = int(counted.sum())
            total = torch.where(counted, error, torch.zeros_like(error)).sum(dtype=torch.float64)
            out[region][kind] = float(total) / n if n else None
            out[region][f"n_{kind}"] = n
    return out


def _warn_no_pixels(results: dict) -> None:
    """A warning on stderr for every figure over no pixel (None: printed '-')."""
    for run, metrics in results.items():
        for region, m in metrics.items():
            if m["n_pixels"] == 0:
                print(f"warning: {run}, {region}: no pixel with valid ground truth; its flow metrics are '-'",
                      file=sys.stderr)
            empty = [kind for kind in ("census", "ssim", "l1") if m[kind] is None]
            if empty:
                print(f"warning: {run}, {region}: no pixel whose sample point (or window) stays inside image 2; "
                      f"its {', '.join(empty)} are '-'", file=sys.stderr)


def _cell(value: float | None, spec: str, scale: float = 1.0) -> str:
    """``value * scale`` formatted with ``spec`` (a width and a format), or '-' right-aligned when None."""
    width = spec.split(".")[0].lstrip(">+")
    return f"{'-':>{width}}" if value is None else format(scale * value, spec)


def _row(name: str, m: dict) -> str:
    return (f"{name:<22} {_cell(m['road']['e_E'], '>9.3f')} {_cell(m['non_road']['e_E'], '>13.3f')} "
            f"{_cell(m['all']['e_E'], '>8.3f')} {_cell(m['road']['Fl'], '>9.1f', 100)} "
            f"{_cell(m['non_road']['Fl'], '>13.1f', 100)}")


def _photometric_row(name: str, m: dict) -> str:
    return (f"{name:<22} {_cell(m['road']['census'], '>11.4f')} {_cell(m['road']['ssim'], '>9.4f')} "
            f"{_cell(m['road']['l1'], '>8.2f')} {_cell(m['all']['census'], '>11.4f')} "
            f"{_cell(m['all']['ssim'], '>9.4f')} {_cell(m['all']['l1'], '>8.2f')}")


RUNS = ("unsupervised", "unsupervised+freespace")


def _save(obj: object, path: Path) -> None:
    """``torch.save(obj)`` written to ``path`` atomically. Saved to memory first: ``torch.save`` to
    a path names the records of its archive after that file, here the atomic write's temporary,
    whose name is random, so that two runs with the same options wrote files of other bytes."""
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_bytes(path, buffer.getvalue())


def _net_file(run: str) -> str:
    """The file name of a run's state_dict in ``--out``."""
    return f"tinyraft_{run.replace('+', '_')}.pt"


def _bad_input(args: argparse.Namespace) -> str | None:
    """The first bad option as a message naming it, or None."""
    from fsof_torch.data.scene import PRESETS

    from fsof_torch.data.scene.render import MAX_FRAME

    for option in ("steps", "batch", "train_pairs", "test_pairs", "iters"):
        if getattr(args, option) < 1:
            return f"--{option.replace('_', '-')}: expected at least 1, got {getattr(args, option)}"
    for option in ("train_pairs", "test_pairs"):  # (the scenes' frames end at MAX_FRAME)
        if getattr(args, option) > MAX_FRAME:
            return f"--{option.replace('_', '-')}: expected at most {MAX_FRAME}, got {getattr(args, option)}"
    if args.batch > args.train_pairs:  # a global batch is drawn from the training pairs without repeats
        return f"--batch: expected at most --train-pairs ({args.train_pairs}), got {args.batch}"
    if min(args.size) < 16:
        return f"--size: expected H, W >= 16, got {list(args.size)}"
    bad = bad_size(args.size, "--size")
    if bad is not None:
        return bad
    for option in ("lr", "freespace_weight"):
        if not (math.isfinite(getattr(args, option)) and getattr(args, option) > 0):
            return f"--{option.replace('_', '-')}: expected a finite number > 0, got {getattr(args, option)}"
    if args.lr > MAX_LR:
        return (f"--lr: expected at most {MAX_LR:g} (AdamW's first step is 10 × lr, which must fit the net's "
                f"float32), got {args.lr:g}")
    if args.threads < 0:
        return f"--threads: expected >= 0 (0: torch's default), got {args.threads}"
    if args.threads > (os.cpu_count() or 1):  # (a huge count crashes torch's thread pool)
        return f"--threads: expected at most this machine's {os.cpu_count() or 1} CPUs, got {args.threads}"
    if args.seed < 0:  # (also where this module's main runs the job, without the eval command's check)
        return f"--seed: expected an int in [0, 2**62), got {args.seed}"
    if args.seed + HELD_OUT >= MAX_SEED:  # (the held-out scenes' seed is in the scenes' range too)
        return f"--seed: expected at most 2**62 - {HELD_OUT + 1} (the held-out seed is --seed + {HELD_OUT}), got {args.seed}"
    if args.preset not in PRESETS:
        return f"--preset: unknown preset {args.preset!r}; choose from {', '.join(sorted(PRESETS))}"
    bad = _bad_device(args.device)
    if bad is not None:
        return bad
    # the outputs, before the rendering and the training: none may be another (the last written
    # would replace the others)
    dump = args.dump_first_step
    # (paths the system cannot look up first: the comparisons below resolve them)
    bad = first_bad(bad_lookup(args.out, "--out"), bad_lookup(args.json, "--json"), bad_lookup(dump, "--dump-first-step"))
    if bad is not None:
        return bad
    nets = [args.out / _net_file(name) for name in RUNS] if args.out is not None else []
    if dump is not None and any(dump.resolve() == net.resolve() for net in nets):
        return f"--dump-first-step: {str(dump)!r} is a state_dict the job writes into --out; give another path"
    if dump is not None and args.json is not None and args.json.resolve() != dump.resolve():
        # (one a path under the other: the first written makes the other's folder a file, or its file a folder)
        if args.json.resolve().is_relative_to(dump.resolve()):
            return f"--json: {str(args.json)!r} lies under --dump-first-step {str(dump)!r}, a file; give another path"
        if dump.resolve().is_relative_to(args.json.resolve()):
            return f"--dump-first-step: {str(dump)!r} lies under --json {str(args.json)!r}, a file; give another path"
    return first_bad(bad_folder(args.out, "--out", [_net_file(name) for name in RUNS]),
                     bad_file(args.json, "--json", args.out), bad_file(dump, "--dump-first-step", args.out),
                     bad_json_target(args.json, nets + ([dump] if dump is not None else [])))


def _bad_device(text: str) -> str | None:
    """``--device`` names a device that can hold the nets' tensors (as the refine job checks its
    own), else the message naming it: a device torch does not know, CUDA where there is none,
    ``meta`` (shapes without data), one that cannot place a tensor (``mps`` off a Mac, a GPU
    index beyond the machine's)."""
    try:
        device = torch.device(text)
    except RuntimeError:
        return f"--device: not a torch device: {text!r}"
    if device.type == "cuda" and not torch.cuda.is_available():
        return f"--device: {text!r} requested but CUDA is not available"
    if device.type == "meta":
        return f"--device: {text!r} holds no data (shapes only); give cpu or cuda"
    if device.type != "cuda" or device.index is not None:  # (bare cuda: the process's GPU, set later)
        try:
            torch.empty(0, device=device)
        except Exception as err:  # torch raises RuntimeError, AssertionError, NotImplementedError, ...
            first = str(err).splitlines()[0].split(". ")[0] if str(err) else ""
            return f"--device: cannot place a tensor on {text!r} ({type(err).__name__}: {first})"
    return None


def run(args: argparse.Namespace) -> int:
    bad = first_bad(_bad_input(args), _bad_environment())
    if bad is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    threads = torch.get_num_threads()  # (a main() called in-process gives its caller's count back)
    try:
        if args.threads:
            torch.set_num_threads(args.threads)
        return _train_in_group(args, torch.device(args.device))
    finally:
        torch.set_num_threads(threads)


def _train_in_group(args: argparse.Namespace, device: torch.device) -> int:
    ranks = _join_process_group(device)
    try:
        status = _train_and_report(args, device, ranks)
        if ranks.distributed:  # (the others wait for rank 0's evaluation and report: a process group
            import torch.distributed as dist  # torn down while a peer still holds it aborted a rank)

            dist.barrier()
        return status
    finally:
        if ranks.distributed:
            import torch.distributed as dist

            dist.destroy_process_group()


def _train_and_report(args: argparse.Namespace, device: torch.device, ranks: Ranks) -> int:
    if args.batch % ranks.world_size:
        print(f"error: --batch: {args.batch} pairs cannot be shared evenly by {ranks.world_size} processes",
              file=sys.stderr)
        return 2
    if device.type == "cuda" and device.index is None and ranks.distributed:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    if ranks.rank == 0:  # an earlier run's files where this run writes go, not to be read as its own
        if args.out is not None:  # (should this run stop, a diverged one say, it leaves none)
            remove_outputs(args.out, [_net_file(name) for name in RUNS])
        for path in (args.json, args.dump_first_step):
            if path is not None:
                remove_outputs(path.parent, [path.name])
    progress = not args.no_progress and ranks.rank == 0
    size = tuple(args.size)
    t0 = time.perf_counter()
    train = render_pairs(args.preset, args.train_pairs, seed=args.seed, size=size, progress=progress)
    test = render_pairs(args.preset, args.test_pairs, seed=args.seed + HELD_OUT, size=size, progress=progress)
    render_s = time.perf_counter() - t0

    common = dict(steps=args.steps, seed=args.seed, batch=args.batch, lr=args.lr, iters=args.iters,
                  progress=progress, ranks=ranks, device=device)
    logs: dict[str, dict] = {}
    nets = {}
    first_steps: dict[str, dict] = {}
    for name, weight in zip(RUNS, (0.0, args.freespace_weight)):
        first_steps[name] = {}
        try:
            net, log = train_net(train, freespace_weight=weight, odometry=args.odometry, desc=name,
                                 first_step=first_steps[name], **common)
        except TrainingDiverged as err:  # (before any output is written: nothing of this run is kept)
            if ranks.rank == 0:  # (the message names train_net's argument: lr or freespace_weight)
                option, _, rest = str(err).partition(": ")
                print(f"error: --{option.replace('_', '-')}: {rest} (run {name!r}; nothing written)", file=sys.stderr)
            return 2
        logs[name] = log
        nets[name] = net.cpu()
    if ranks.rank != 0:
        return 0
    if args.dump_first_step is not None:
        _save({"world_size": ranks.world_size, **first_steps}, make_parent(args.dump_first_step))
    results: dict[str, dict] = {"untrained": evaluate_net(TinyRAFT(seed=args.seed, iters=args.iters).eval(), test)}
    for name, net in nets.items():
        results[name] = evaluate_net(net, test)

    _warn_no_pixels(results)
    base, free = results["unsupervised"], results["unsupervised+freespace"]
    change = {region: None if None in (base[region]["e_E"], free[region]["e_E"])
              else (free[region]["e_E"] - base[region]["e_E"]) / max(base[region]["e_E"], 1e-12)
              for region in ("road", "non_road", "all")}
    report = {
        "options": {k: (list(v) if isinstance(v, tuple) else str(v) if isinstance(v, Path) else v)
                    for k, v in vars(args).items()},
        "world_size": ranks.world_size,
        "parameters": count_parameters(nets["unsupervised"]),
        "metrics": results,
        "relative_change_with_freespace": change,
        "training": logs,
        "render_seconds": render_s,
        "environment": environment("train", args, seed=args.seed, device=device),
    }
    if args.json is not None:
        write_json(make_parent(args.json), report)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        for name, net in nets.items():
            _save(net.state_dict(), args.out / _net_file(name))
    # (printed after the files are written: a reader of stdout that goes away (| head) loses none)
    print(f"TinyRAFT ({count_parameters(nets['unsupervised'])} parameters, {args.iters} iterations), "
          f"{args.steps} steps of batch {args.batch} on {args.train_pairs} '{args.preset}' pairs of "
          f"{size[0]}x{size[1]}; held-out: {args.test_pairs} pairs (seed {args.seed + HELD_OUT})"
          + (f"; {ranks.world_size} processes (DDP)" if ranks.distributed else ""))
    print(f"{'run':<22} {'road EPE':>9} {'non-road EPE':>13} {'all EPE':>8} {'road Fl%':>9} {'non-road Fl%':>13}")
    for name, m in results.items():
        print(_row(name, m))
    percent = {region: _cell(value, spec, 100) + ("%" if value is not None else " ")
               for (region, value), spec in zip(change.items(), (">+8.1f", ">+12.1f", ">+7.1f"))}
    print(f"{'change with freespace':<22} {percent['road']} {percent['non_road']} {percent['all']}")
    print("photometric error of image 1 against image 2 warped by the estimate (census distance, "
          "SSIM dissimilarity, L1 on 0-255; lower is better; L1 alone rewards a flow bent to match brightness):")
    print(f"{'run':<22} {'road census':>11} {'road SSIM':>9} {'road L1':>8} {'all census':>11} {'all SSIM':>9} {'all L1':>8}")
    for name, m in results.items():
        print(_photometric_row(name, m))
    print(f"render {render_s:.1f} s; training " + ", ".join(f"{k} {v['seconds']:.1f} s" for k, v in logs.items()))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the job in-process: ``main(["--steps", "10", ...])``, as ``python -m eval train`` runs
    it (its checks, and its status returned for ``--help`` and argparse's errors too)."""
    from eval.__main__ import main as eval_main

    return eval_main(["train", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
