"""The refine job with user networks (``--net module:callable``, ``--checkpoint``), through a stand-in
module written to tmp_path, and its runs on several processes under torchrun."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from refine.__main__ import main

SIZE = (45, 150)  # not divisible by 8: the torchvision contract needs the job's padding

MODULE = '''
"""A user's module of flow networks (stand-ins of ptlflow's and torchvision's RAFT)."""
import torch
from fsof_torch.training.standins import PtlflowRAFTStandIn, TorchvisionRAFTStandIn


def ptlflow_raft():
    return PtlflowRAFTStandIn(seed=0, iters=2)


def torchvision_raft():
    return TorchvisionRAFTStandIn(seed=0)


def not_a_module():
    return "raft"


class TwoImages(torch.nn.Module):
    """Two image arguments and no declared contract: the job cannot tell the value range."""

    def forward(self, image1, image2):
        return [torch.zeros(image1.shape[0], 2, *image1.shape[-2:])]


def two_images():
    return TwoImages()


class Zeros(torch.nn.Module):
    flow_contract = "raft"

    def forward(self, image1, image2):
        return [torch.zeros(image1.shape[0], 2, *image1.shape[-2:])]


class InPlace(Zeros):
    """Normalises its inputs in place, as some RAFT ports do."""

    def forward(self, image1, image2):
        image1.div_(255.0)
        image2.div_(255.0)
        return super().forward(image1, image2)


class AllNaN(Zeros):
    def forward(self, image1, image2):
        return [super().forward(image1, image2)[0] * float("nan")]


class Inf(Zeros):
    """inf at one pixel (on the road, with valid ground truth), or everywhere."""

    def __init__(self, everywhere=False):
        super().__init__()
        self.everywhere = everywhere

    def forward(self, image1, image2):
        flow = super().forward(image1, image2)[0]
        if self.everywhere:
            flow[:] = float("inf")
        else:
            flow[:, :, -12, flow.shape[-1] // 2] = float("inf")
        return [flow]


def one_inf():
    return Inf()


def all_inf():
    return Inf(everywhere=True)


class Double(Zeros):
    """Float64 weights: the images must come in float64."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(6, 2, 3, padding=1).double()
        torch.nn.init.zeros_(self.conv.weight)
        torch.nn.init.zeros_(self.conv.bias)

    def forward(self, image1, image2):
        return [self.conv(torch.cat([image1, image2], 1))]


class Raises(Zeros):
    def forward(self, image1, image2):
        raise RuntimeError("boom inside forward")


class ReturnsDict(Zeros):
    def forward(self, image1, image2):
        return {"foo": 1}


def in_place():
    return InPlace()


def all_nan():
    return AllNaN()


def double():
    return Double()


def raises():
    return Raises()


def returns_dict():
    return ReturnsDict()


class TwoFlows(Zeros):
    """A flow of batch 2 for the job's one pair."""

    def forward(self, image1, image2):
        return [torch.zeros(2, 2, *image1.shape[-2:])]


class Meta(Zeros):
    def forward(self, image1, image2):
        return [torch.zeros(1, 2, *image1.shape[-2:], device="meta")]


class Needs32(Zeros):
    def forward(self, image1, image2):
        if image1.shape[-1] % 32 or image1.shape[-2] % 32:
            raise ValueError(f"H and W must be divisible by 32, got {tuple(image1.shape[-2:])}")
        return super().forward(image1, image2)


class Misspelt(TwoFlows):
    flow_contract = "RAFT"


def misspelt():
    return Misspelt()


class OnMeta(Double):
    """Built on the meta device (shapes only), to be filled from a checkpoint."""

    def __init__(self):
        super().__init__()
        self.to("meta")


def on_meta():
    return OnMeta()


class Concatenated(torch.nn.Module):
    """ARFlow's call: the pair concatenated, (B, 6, H, W); no declared contract."""

    def forward(self, x):
        return [torch.zeros(x.shape[0], 2, *x.shape[-2:])]


def concatenated():
    return Concatenated()


instance = Zeros()


def exits():
    raise SystemExit("no GPU")


class DisLike(torch.nn.Module):
    """OpenCV DIS through ptlflow's contract: exactly the job's DIS flow on integer images."""

    flow_contract = "ptlflow"

    def forward(self, inputs):
        from refine.sources import dis_flow

        rgb = (inputs["images"][0].flip(1) * 255.0).round()  # BGR [0, 1] -> the file's RGB 0..255
        return {"flows": dis_flow(rgb[0], rgb[1])[None, None]}


def dis_like():
    return DisLike()


class ExitsInForward(Zeros):
    def forward(self, image1, image2):
        raise SystemExit("out of memory")


def exits_in_forward():
    return ExitsInForward()


def two_flows():
    return TwoFlows()


def meta():
    return Meta()


def needs32():
    return Needs32()


INTERRUPTS = [2]  # the call (1-based) on which Interrupts raises, once


class Interrupts(Zeros):
    """Ctrl-C while the network runs on the second pair."""

    calls = 0

    def forward(self, image1, image2):
        Interrupts.calls += 1
        if INTERRUPTS and Interrupts.calls == INTERRUPTS[0]:
            INTERRUPTS.clear()
            raise KeyboardInterrupt
        return super().forward(image1, image2)


def interrupts():
    return Interrupts()


def data_parallel_raft():
    """RAFT's demo builds its network as nn.DataParallel(RAFT(args))."""
    from fsof_torch import TinyRAFT

    return torch.nn.DataParallel(TinyRAFT(seed=0))


def compiled_raft():
    from fsof_torch import TinyRAFT

    return torch.compile(TinyRAFT(seed=0))  # (lazy: nothing is compiled until it is called)
'''


@pytest.fixture
def user_module(tmp_path, monkeypatch) -> str:
    name = f"user_nets_{os.getpid()}"
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(MODULE))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield name
    sys.modules.pop(name, None)


@pytest.fixture(scope="module")
def pair():
    from fsof_torch.data.scene import render_pair

    return render_pair("default", 0, size=SIZE)


def _run(tmp_path, *extra) -> dict:
    out = tmp_path / "out"
    assert main(["--num-pairs", "1", "--odometry", "given", "--no-figures", "--no-progress",
                 "--size", f"{SIZE[0]}x{SIZE[1]}", "--out", str(out), *extra]) == 0
    return json.loads((out / "report.json").read_text())


def _epe_road(flow: torch.Tensor, pair: dict) -> float:
    """Mean end-point error over the road's valid ground-truth pixels, written out."""
    m = (pair["road"] & pair["valid"])[0]
    err = torch.sqrt(((flow - pair["flow"]) ** 2).sum(0))
    return float(err[m].double().mean())


def test_ptlflow_network(tmp_path, user_module, pair):
    from fsof_torch.refinement.contracts import ptlflow_inputs
    from fsof_torch.training.standins import PtlflowRAFTStandIn

    summary = _run(tmp_path, "--net", f"{user_module}:ptlflow_raft")
    (record,) = summary["pairs"]
    assert record["source"] == "net" and summary["identity"]["net"]["factory"] == f"{user_module}:ptlflow_raft"
    with torch.no_grad():
        out = PtlflowRAFTStandIn(seed=0, iters=2).eval()(ptlflow_inputs(pair["image1"][None], pair["image2"][None]))
    assert record["before"]["epe_road"] == pytest.approx(_epe_road(out["flows"][0, 0], pair), rel=1e-5)
    assert record["after"]["epe_road"] < 1e-3  # the scene's odometry: the road is exact after refinement


def test_checkpoint_is_loaded(tmp_path, user_module, pair):
    from fsof_torch.refinement.contracts import ptlflow_inputs
    from fsof_torch.training.standins import PtlflowRAFTStandIn

    other = PtlflowRAFTStandIn(seed=1, iters=2).eval()
    torch.save(other.state_dict(), tmp_path / "weights.pt")
    summary = _run(tmp_path, "--net", f"{user_module}:ptlflow_raft", "--checkpoint", str(tmp_path / "weights.pt"))
    with torch.no_grad():
        out = other(ptlflow_inputs(pair["image1"][None], pair["image2"][None]))
    assert summary["pairs"][0]["before"]["epe_road"] == pytest.approx(_epe_road(out["flows"][0, 0], pair), rel=1e-5)



def test_a_dataparallel_checkpoint_is_loaded_without_its_module_prefix(tmp_path, user_module, pair):
    """Weights saved from nn.DataParallel (RAFT's released checkpoints: every name starts with
    "module.") load into the bare network as the same weights saved without it; a file whose
    names are the network's own with "module." is not a prefix to strip when the network's own
    names start with it (a wrapper module called "module")."""
    from fsof_torch.training.standins import PtlflowRAFTStandIn

    other = PtlflowRAFTStandIn(seed=1, iters=2).eval()
    torch.save(other.state_dict(), tmp_path / "plain.pt")
    torch.save(torch.nn.DataParallel(other).state_dict(), tmp_path / "parallel.pt")
    assert all(k.startswith("module.") for k in torch.load(tmp_path / "parallel.pt", weights_only=True))
    runs = [_run(tmp_path / name, "--net", f"{user_module}:ptlflow_raft", "--checkpoint", str(tmp_path / f"{name}.pt"))
            for name in ("plain", "parallel")]
    assert runs[1]["pairs"][0]["before"] == runs[0]["pairs"][0]["before"]
    from refine.sources import load_state_dict

    # a training checkpoint: the weights under "model" (or "model_state_dict") beside the
    # optimiser's state and the step, with or without DataParallel's prefix
    optimiser = torch.optim.Adam(other.parameters()).state_dict()
    for key, state in (("model", other.state_dict()), ("model_state_dict", torch.nn.DataParallel(other).state_dict())):
        torch.save({key: state, "optimizer": optimiser, "step": 5}, tmp_path / f"{key}.pt")
        net = PtlflowRAFTStandIn(seed=0, iters=2)
        load_state_dict(net, tmp_path / f"{key}.pt", "--checkpoint")
        assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), other.state_dict().values()))
    wrapped = torch.nn.Sequential()
    wrapped.add_module("module", torch.nn.Linear(2, 2))
    state = wrapped.state_dict()
    torch.save(state, tmp_path / "own.pt")
    load_state_dict(wrapped, tmp_path / "own.pt", "--checkpoint")  # (its own names, kept)
    assert all(torch.equal(a, b) for a, b in zip(wrapped.state_dict().values(), state.values()))

def test_a_checkpoint_of_a_module_holding_the_network_loads_without_its_attribute_name(tmp_path, user_module, pair):
    """The state_dict of a module that kept the network as an attribute (a Lightning module's
    ``self.model``: every name starts with "model.") loads into the bare network as the same
    weights, through the job too; a file with a second network beside it, or whose names without
    the attribute are not the network's, is refused naming its keys, and a network whose own
    names all start with one attribute keeps them."""
    from refine.sources import JobError, load_state_dict
    from fsof_torch.training.standins import PtlflowRAFTStandIn

    other = PtlflowRAFTStandIn(seed=1, iters=2).eval()
    trainer = torch.nn.Module()
    trainer.model = other
    trainer.loss = torch.nn.L1Loss()  # (no weights: nothing in the state_dict)
    assert all(k.startswith("model.") for k in trainer.state_dict())
    torch.save({"state_dict": trainer.state_dict(), "epoch": 3}, tmp_path / "lightning.pt")
    torch.save(other.state_dict(), tmp_path / "plain.pt")
    runs = [_run(tmp_path / name, "--net", f"{user_module}:ptlflow_raft", "--checkpoint", str(tmp_path / f"{name}.pt"))
            for name in ("plain", "lightning")]
    assert runs[1]["pairs"][0]["before"] == runs[0]["pairs"][0]["before"]
    net = PtlflowRAFTStandIn(seed=0, iters=2)
    load_state_dict(net, tmp_path / "lightning.pt", "--checkpoint")
    assert net.state_dict().keys() == other.state_dict().keys()
    assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), other.state_dict().values()))
    trainer.teacher = torch.nn.Linear(2, 2)  # (two attributes: which one is the network is not guessed)
    torch.save(trainer.state_dict(), tmp_path / "two.pt")
    with pytest.raises(JobError, match=r"--checkpoint: .*two\.pt.* does not fit PtlflowRAFTStandIn: missing keys"):
        load_state_dict(PtlflowRAFTStandIn(seed=0, iters=2), tmp_path / "two.pt", "--checkpoint")
    torch.save({f"model.{k}": v for k, v in torch.nn.Linear(2, 2).state_dict().items()}, tmp_path / "linear.pt")
    with pytest.raises(JobError, match="does not fit PtlflowRAFTStandIn"):
        load_state_dict(PtlflowRAFTStandIn(seed=0, iters=2), tmp_path / "linear.pt", "--checkpoint")
    holder = torch.nn.Module()
    holder.model = torch.nn.Linear(2, 2)
    state = {k: v + 1 for k, v in holder.state_dict().items()}
    torch.save(state, tmp_path / "own.pt")
    load_state_dict(holder, tmp_path / "own.pt", "--checkpoint")  # (its own names, kept)
    assert all(torch.equal(a, b) for a, b in zip(holder.state_dict().values(), state.values()))


def test_a_compiled_networks_checkpoint_is_loaded_without_its_orig_mod_prefix(tmp_path):
    """The state_dict of a torch.compile'd network (every name starts with "_orig_mod."), also
    saved inside nn.DataParallel ("module._orig_mod."), loads into the bare network as the same
    weights; a network whose own names start with "_orig_mod." keeps them."""
    from refine.sources import load_state_dict
    from fsof_torch.training.standins import PtlflowRAFTStandIn

    other = PtlflowRAFTStandIn(seed=1, iters=2).eval()
    compiled = torch.compile(other)  # (lazy: nothing is compiled until it is called)
    for name, state in (("compiled", compiled.state_dict()),
                        ("parallel", torch.nn.DataParallel(compiled).state_dict())):
        assert all(k.startswith("_orig_mod." if name == "compiled" else "module._orig_mod.") for k in state)
        torch.save(state, tmp_path / f"{name}.pt")
        net = PtlflowRAFTStandIn(seed=0, iters=2)
        load_state_dict(net, tmp_path / f"{name}.pt", "--checkpoint")
        assert net.state_dict().keys() == other.state_dict().keys()
        assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), other.state_dict().values()))
    wrapped = torch.nn.Module()
    wrapped.add_module("_orig_mod", torch.nn.Linear(2, 2))
    state = {k: v + 1 for k, v in wrapped.state_dict().items()}
    torch.save(state, tmp_path / "own.pt")
    load_state_dict(wrapped, tmp_path / "own.pt", "--checkpoint")  # (its own names, kept)
    assert all(torch.equal(a, b) for a, b in zip(wrapped.state_dict().values(), state.values()))


def test_torchvision_network_is_padded(tmp_path, user_module, pair):
    from fsof_torch.training.standins import TorchvisionRAFTStandIn

    summary = _run(tmp_path, "--net", f"{user_module}:torchvision_raft")
    pad = (1, 1, 1, 2)  # 45x150 -> 48x152, RAFT's split of the padding
    x1, x2 = (F.pad(im[None] / 127.5 - 1, pad, mode="replicate") for im in (pair["image1"], pair["image2"]))
    with torch.no_grad():
        flow = TorchvisionRAFTStandIn(seed=0).eval()(x1, x2)[-1][0, :, 1:46, 1:151]
    assert summary["pairs"][0]["before"]["epe_road"] == pytest.approx(_epe_road(flow, pair), rel=1e-5)


def test_network_errors(tmp_path, user_module, capsys, monkeypatch):
    base = ["--num-pairs", "1", "--no-figures", "--no-progress", "--size", f"{SIZE[0]}x{SIZE[1]}",
            "--out", str(tmp_path / "o")]

    def err(*extra) -> str:
        assert main([*base, *extra]) == 2
        return capsys.readouterr().err

    assert "--net: cannot import module 'no_such_module_xyz'" in err("--net", "no_such_module_xyz:make")
    # a package whose __init__ raises, named through a submodule (finding the submodule runs it)
    (tmp_path / f"{user_module}_broken").mkdir()
    (tmp_path / f"{user_module}_broken" / "__init__.py").write_text("raise RuntimeError('broken package')\n")
    (tmp_path / f"{user_module}_broken" / "nets.py").write_text("def make():\n    pass\n")
    text = err("--net", f"{user_module}_broken.nets:make")
    assert text.startswith(f"error: --net: importing '{user_module}_broken.nets' failed: RuntimeError: broken "
                           f"package"), text
    assert f"--net: module '{user_module}' has no attribute 'missing'" in err("--net", f"{user_module}:missing")
    assert "--net: expected module:callable" in err("--net", user_module)
    assert "returned a str; expected a torch.nn.Module" in err("--net", f"{user_module}:not_a_module")
    # research code that parses the command line when imported, or exits in its factory
    (tmp_path / f"{user_module}_argv.py").write_text("import argparse\nargparse.ArgumentParser().parse_args()\n")
    # (the command line it parses is the job's, not the test runner's, which may hold no option)
    monkeypatch.setattr(sys, "argv", ["refine", *base, "--net", f"{user_module}_argv:make"])
    assert (f"--net: importing '{user_module}_argv' exited (SystemExit: 2); the job imports the module and calls its "
            f"factory: it may not parse the command line or exit") in err("--net", f"{user_module}_argv:make")
    sys.modules.pop(f"{user_module}_argv", None)
    (tmp_path / f"{user_module}_argv_pkg").mkdir()
    (tmp_path / f"{user_module}_argv_pkg" / "__init__.py").write_text("raise SystemExit(3)\n")
    assert f"--net: importing '{user_module}_argv_pkg.nets' exited (SystemExit: 3)" in err(
        "--net", f"{user_module}_argv_pkg.nets:make")
    assert f"--net: calling {user_module}:exits() exited (SystemExit: 'no GPU')" in err("--net", f"{user_module}:exits")
    assert (f"--net: '{user_module}:instance' is a network (a Zeros), not a factory; name a function or class that "
            f"returns it, e.g. {user_module}:Zeros") in err("--net", f"{user_module}:instance")
    assert "--net-contract: cannot tell how to call TwoImages" in err("--net", f"{user_module}:two_images")
    assert ("--net-contract: Misspelt.flow_contract is 'RAFT'; expected one of ptlflow, torchvision, raft (or give "
            "--net-contract)") in err("--net", f"{user_module}:misspelt")
    torch.save({"fnet.weight": torch.zeros(2)}, tmp_path / "wrong.pt")
    text = err("--net", f"{user_module}:ptlflow_raft", "--checkpoint", str(tmp_path / "wrong.pt"))
    assert "--checkpoint:" in text and "wrong.pt" in text and "does not fit PtlflowRAFTStandIn" in text
    # (the first four missing names, and how many more: four alone read as all of them)
    from fsof_torch.training.standins import PtlflowRAFTStandIn

    names = sorted(PtlflowRAFTStandIn(seed=0, iters=2).state_dict())
    assert len(names) > 4
    assert f"missing keys {names[:4]} and {len(names) - 4} more, unexpected keys ['fnet.weight']" in text, text
    assert "--checkpoint needs --net" in err("--checkpoint", str(tmp_path / "wrong.pt"))
    assert not (tmp_path / "o" / "run.json").exists()  # every check came before any work


def test_a_checkpoint_torch_load_refuses_is_named_with_its_reason(tmp_path, user_module, capsys):
    """A whole pickled network, a training checkpoint with objects beside its weights, bytes that
    are no checkpoint: exit 2 naming --checkpoint and the reason (the pickled class, the byte torch
    stopped at), without torch's advice to load with weights_only=False (which the job never does,
    and which cannot help bytes that are no checkpoint) or its terminal colour codes."""
    import argparse

    from fsof_torch.training.standins import PtlflowRAFTStandIn

    net = PtlflowRAFTStandIn(seed=0, iters=2)
    torch.save(net, tmp_path / "whole.pt")
    torch.save({"state_dict": net.state_dict(), "hyper_parameters": argparse.Namespace(lr=1e-4)},
               tmp_path / "lightning.ckpt")
    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint")
    base = ["--num-pairs", "1", "--no-figures", "--no-progress", "--size", f"{SIZE[0]}x{SIZE[1]}",
            "--out", str(tmp_path / "o"), "--net", f"{user_module}:ptlflow_raft", "--checkpoint"]
    for name, reason in (("whole.pt", "holds a pickled fsof_torch.training.standins.PtlflowRAFTStandIn, not only "
                                      "tensors"),
                         ("lightning.ckpt", "holds a pickled argparse.Namespace, not only tensors"),
                         ("garbage.pt", "can read (UnpicklingError: Unsupported operand")):
        assert main([*base, str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: --checkpoint: {str(tmp_path / name)!r} ") and reason in err, err
        assert "weights_only` set to `False`" not in err and "\x1b" not in err, err
    assert not (tmp_path / "o" / "run.json").exists()


def test_json_naming_the_network_source_is_refused_and_the_source_kept(tmp_path, user_module, capsys):
    """--json naming the file of --net's module, or a file inside its package's folder, is refused
    before any work: the job removes the --json file at its start."""
    source = tmp_path / f"{user_module}.py"
    before = source.read_bytes()
    package = tmp_path / f"{user_module}_pkg"
    package.mkdir()
    (package / "__init__.py").write_text("from " + user_module + " import ptlflow_raft  # noqa: F401\n")
    (package / "nets.py").write_text("X = 1\n")
    base = ["--num-pairs", "1", "--no-figures", "--no-progress", "--size", f"{SIZE[0]}x{SIZE[1]}",
            "--out", str(tmp_path / "o")]
    for factory, target, option_path in ((f"{user_module}:ptlflow_raft", source, source),
                                         (f"{user_module}_pkg:ptlflow_raft", package / "nets.py", package)):
        assert main([*base, "--net", factory, "--json", str(target)]) == 2
        err = capsys.readouterr().err
        wanted = ("is the input --net; give another path" if target == option_path else
                  f"is inside the input --net {str(option_path)!r}; give another path")
        assert err.startswith(f"error: --json: {str(target)!r} ") and wanted in err, err
    assert source.read_bytes() == before and (package / "nets.py").read_text() == "X = 1\n"
    assert not (tmp_path / "o").exists()
    sys.modules.pop(f"{user_module}_pkg", None)


def test_the_test_net_is_a_raft_contract_network(tmp_path, pair):
    """--net fsof_torch:TinyRAFT (e.g. with weights from eval train as --checkpoint) is called as
    RAFT: RGB on 0..255, padded by the job; its flow is the test net source's."""
    from fsof_torch import TinyRAFT

    torch.save(TinyRAFT(seed=3).state_dict(), tmp_path / "tiny.pt")
    net = _run(tmp_path / "net", "--net", "fsof_torch:TinyRAFT", "--checkpoint", str(tmp_path / "tiny.pt"))
    testnet = _run(tmp_path / "testnet", "--source", "testnet", "--testnet-weights", str(tmp_path / "tiny.pt"))
    assert net["pairs"][0]["before"] == testnet["pairs"][0]["before"]


def test_a_network_returned_wrapped_is_called_and_loaded_as_the_network_it_wraps(tmp_path, user_module, pair):
    """A factory that returns nn.DataParallel(net) (RAFT's demo) or torch.compile(net): its forward
    takes *args, so the contract could not be told ('forward takes 0 image arguments'), and a
    checkpoint of the bare network (or one saved from another wrapper) did not fit its
    'module.' or '_orig_mod.' names; both are now the wrapped network's."""
    from fsof_torch import TinyRAFT
    from refine.sources import NetSpec, build_user_net

    weights = TinyRAFT(seed=3).state_dict()
    torch.save(weights, tmp_path / "plain.pt")
    torch.save(torch.nn.DataParallel(TinyRAFT(seed=3)).state_dict(), tmp_path / "parallel.pt")
    reference = _run(tmp_path / "net", "--net", "fsof_torch:TinyRAFT", "--checkpoint", str(tmp_path / "plain.pt"))
    for name in ("plain", "parallel"):
        run = _run(tmp_path / name, "--net", f"{user_module}:data_parallel_raft", "--checkpoint",
                   str(tmp_path / f"{name}.pt"))
        assert run["pairs"][0]["before"] == reference["pairs"][0]["before"]
        for factory in ("data_parallel_raft", "compiled_raft"):
            net, contract, guessed = build_user_net(NetSpec(f"{user_module}:{factory}", "auto",
                                                            tmp_path / f"{name}.pt"))
            assert (contract, guessed) == ("raft", False)
            inner = net.module if factory == "data_parallel_raft" else net._orig_mod
            assert inner.state_dict().keys() == weights.keys()
            assert all(torch.equal(a, b) for a, b in zip(inner.state_dict().values(), weights.values()))


def test_a_network_built_on_the_meta_device_takes_the_checkpoints_tensors(tmp_path, user_module, capsys):
    """A network whose weights are on the meta device (shapes only) takes them from --checkpoint
    (load_state_dict(assign=True)) and runs as the same network built with values; without a
    checkpoint it exits 2 naming --net and the first such weight."""
    import importlib

    module = importlib.import_module(user_module)
    weights = module.Double().state_dict()
    weights["conv.weight"].normal_(generator=torch.Generator().manual_seed(0))
    torch.save(weights, tmp_path / "double.pt")
    built = [_run(tmp_path / name, "--net", f"{user_module}:{name}", "--checkpoint", str(tmp_path / "double.pt"))
             for name in ("double", "on_meta")]
    assert built[0]["pairs"][0]["before"] == built[1]["pairs"][0]["before"]
    assert main(["--num-pairs", "1", "--no-figures", "--no-progress", "--size", f"{SIZE[0]}x{SIZE[1]}",
                 "--out", str(tmp_path / "o"), "--net", f"{user_module}:on_meta"]) == 2
    assert capsys.readouterr().err == (f"error: --net: {user_module}:on_meta() returned a network whose 'conv.weight' "
                                       f"and 1 more on the device 'meta' hold no values (shapes only); give them in "
                                       f"--checkpoint\n")


def test_a_network_and_its_flows_saved_as_files_give_the_same_records(tmp_path, user_module, pair):
    """--source net with a network returning DIS's flow, and --flows with that flow saved: the
    same measures, refined flows and fits (the sources differ only in name and input files)."""
    from fsof_torch.io import read_image, write_flow, write_image, write_kitti_calibration, write_road_mask
    from refine.sources import dis_flow

    root = tmp_path / "data"
    for d in ("images", "road", "flows"):
        (root / d).mkdir(parents=True)
    write_image(root / "images" / "000000.png", pair["image1"])
    write_image(root / "images" / "000001.png", pair["image2"])
    write_kitti_calibration(root / "calib.txt", pair["camera"].K[0], cam=0, style="odometry")
    write_road_mask(root / "road" / "000000.png", pair["road"])
    images = [read_image(root / "images" / f"00000{i}.png") for i in (0, 1)]
    write_flow(root / "flows" / "000000.npy", dis_flow(*images))
    base = ["--images", str(root / "images"), "--calib", str(root / "calib.txt"), "--road", str(root / "road"),
            "--odometry", "fit,photometric", "--no-figures", "--no-progress"]
    runs = {}
    for name, source in (("net", ["--net", f"{user_module}:dis_like"]), ("files", ["--flows", str(root / "flows")])):
        assert main([*base, *source, "--out", str(tmp_path / name)]) == 0
        runs[name] = json.loads((tmp_path / name / "report.json").read_text())["pairs"]
    keep = ("before", "after", "odometry", "refined", "fit_success", "fit_residual_px", "flow_digest", "gate")
    assert [r["source"] for r in runs["net"]] == ["net", "net"] and [r["source"] for r in runs["files"]] == ["files"] * 2
    assert [{k: r.get(k) for k in keep} for r in runs["net"]] == [{k: r.get(k) for k in keep} for r in runs["files"]]
    assert any(r["refined"] for r in runs["net"])


def test_explicit_contract(tmp_path, user_module):
    """A two-image network with --net-contract raft runs (its flows are zero: refinement fixes the road)."""
    summary = _run(tmp_path, "--net", f"{user_module}:two_images", "--net-contract", "raft")
    (record,) = summary["pairs"]
    assert record["before"]["epe_road"] > 1.0 > 1e-3 > record["after"]["epe_road"]


def test_the_network_gets_copies_of_the_images(user_module, pair):
    """A network that normalises its inputs in place leaves the pair's images as they were."""
    import importlib

    from refine.sources import net_flow

    # a multiple of 8: no padding, which would hand the network a new tensor anyway
    image1, image2 = (pair[k][:, :40, :144].clone() for k in ("image1", "image2"))
    original = image1.clone(), image2.clone()
    flow = net_flow(importlib.import_module(user_module).in_place(), "raft", image1, image2)
    assert flow.shape == (2, 40, 144)
    assert torch.equal(image1, original[0]) and torch.equal(image2, original[1])


def test_a_float64_network_gets_float64_images(tmp_path, user_module):
    summary = _run(tmp_path, "--net", f"{user_module}:double")
    (record,) = summary["pairs"]
    assert record["prediction_finite"] == 1.0
    assert record["before"]["epe_road"] > 1.0 > 1e-3 > record["after"]["epe_road"]  # zero flow, then refined


def test_a_network_that_fails_on_a_pair_exits_2_naming_net(tmp_path, user_module, capsys):
    for name, message in (("raises", "--net: the network raised RuntimeError: boom inside forward (contract raft; "
                                     "the job padded the images from 45x150 to 48x152, a multiple of 8)"),
                          ("needs32", "--net: the network raised ValueError: H and W must be divisible by 32, got "
                                      "(48, 152) (contract raft; the job padded the images from 45x150 to 48x152"),
                          ("returns_dict", "--net: its output holds no flow"),
                          ("exits_in_forward", "--net: the network raised SystemExit: out of memory (contract raft"),
                          ("concatenated", "(contract ptlflow); the contract was guessed from its one-argument "
                                           "forward: give --net-contract, or call a network of another input "
                                           "(ARFlow's pair concatenated) through an adapter (docs/contracts.md)"),
                          ("two_flows", "--net: the network's finest flow has batch 2 (shape (2, 2, 45, 150)), the "
                                        "images 1 (one pair)"),
                          ("meta", "--net: the network returned its flow on the device 'meta' (shapes only, no "
                                   "values), the images on 'cpu'")):
        assert main(["--num-pairs", "1", "--no-figures", "--no-progress", "--size", f"{SIZE[0]}x{SIZE[1]}",
                     "--out", str(tmp_path / name), "--net", f"{user_module}:{name}"]) == 2
        assert message in capsys.readouterr().err


def test_a_network_whose_flow_is_nan_everywhere(tmp_path, user_module):
    """No pixel to measure: the records hold None, the report prints '–' rows and warns, naming
    the source."""
    out = tmp_path / "out"
    summary = _run(tmp_path, "--net", f"{user_module}:all_nan")
    (record,) = summary["pairs"]
    assert record["prediction_finite"] == 0.0
    assert record["before"]["census_all"] is None and record["before"]["census_all_n"] == 0
    (row,) = summary["rows"]
    assert row["census_road_before"] is None and row["epe_all_after"] is None
    report = (out / "report.md").read_text()
    assert "| net | given | 1/1 | census distance (0-1) | – | – | – | – | – | – |" in report
    assert "flow source 'net' gave no finite flow (NaN or inf at every pixel) on 1 of 1 pair(s) (000000)" in report
    assert "'–': measured over no pixel" in report


def test_a_network_whose_flow_is_inf_goes_on(tmp_path, user_module, pair):
    """inf at one pixel: that pixel is left out of the metrics (the run does not stop on its
    end-point error); inf everywhere: as NaN everywhere, '–' rows and a warning."""
    summary = _run(tmp_path / "one", "--net", f"{user_module}:one_inf")
    (record,) = summary["pairs"]
    H, W = SIZE
    assert record["prediction_finite"] == pytest.approx(1 - 1 / (H * W))
    assert bool(pair["valid"][0, -12, W // 2] and pair["road"][0, -12, W // 2])  # the pixel counts, when finite
    assert record["before"]["epe_road_n"] == int((pair["valid"] & pair["road"]).sum()) - 1
    assert record["before"]["epe_road"] > 1.0 > 1e-3 > record["after"]["epe_road"]  # zero flow, then refined
    summary = _run(tmp_path / "all", "--net", f"{user_module}:all_inf")
    (record,) = summary["pairs"]
    assert record["prediction_finite"] == 0.0 and record["before"]["epe_all"] is None
    report = (tmp_path / "all" / "out" / "report.md").read_text()
    assert "flow source 'net' gave no finite flow (NaN or inf at every pixel) on 1 of 1 pair(s)" in report


def test_threads_holds_for_a_network_whose_module_sets_its_own(tmp_path, user_module, monkeypatch):
    """A module that sets torch's and OpenCV's thread counts when imported (as some research code
    does) runs under --threads all the same: the job sets them again once the networks are built."""
    import cv2

    name = f"{user_module}_threads"
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(f'''
        import cv2
        import torch
        from {user_module} import Zeros

        torch.set_num_threads(2)
        cv2.setNumThreads(2)
        SEEN = []


        class Counts(Zeros):
            def forward(self, image1, image2):
                SEEN.append((torch.get_num_threads(), cv2.getNumThreads()))
                return super().forward(image1, image2)


        def make():
            return Counts()
        '''))
    monkeypatch.setattr(os, "cpu_count", lambda: 2)  # (--threads is bounded by the machine's CPUs)
    before = torch.get_num_threads(), cv2.getNumThreads()
    try:
        _run(tmp_path, "--net", f"{name}:make", "--threads", "1")
        assert sys.modules[name].SEEN == [(1, 1)]
    finally:
        torch.set_num_threads(before[0])
        cv2.setNumThreads(before[1])
        sys.modules.pop(name, None)


def test_ctrl_c_prints_one_line_exits_130_and_the_run_resumes(tmp_path, user_module, capsys):
    """A KeyboardInterrupt (Ctrl-C) while the network runs on the second pair: no traceback, one
    line on stderr and exit status 130; the --out lock is released and the finished pair kept,
    so the same command resumes."""
    args = ["--num-pairs", "2", "--odometry", "given", "--no-figures", "--no-progress", "--size",
            f"{SIZE[0]}x{SIZE[1]}", "--out", str(tmp_path / "out"), "--net", f"{user_module}:interrupts"]
    assert main(args) == 130
    err = capsys.readouterr().err
    assert err.startswith("refine: interrupted;") and err.count("\n") == 1 and "Traceback" not in err, err
    assert main(args) == 0
    summary = json.loads((tmp_path / "out" / "report.json").read_text())
    assert [r["pair"] for r in summary["pairs"]] == ["000000", "000001"]
    assert (summary["records_resumed"], summary["records_computed"]) == (1, 1)


# -- torchrun -------------------------------------------------------------------------------------

@pytest.mark.slow
def test_torchrun_two_processes_write_the_single_process_report(tmp_path):
    args = ["--num-pairs", "4", "--source", "dis", "--odometry", "given,fit", "--no-figures", "--no-progress",
            "--size", "48x160"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "refine", *args, "--out", str(tmp_path / "multi")]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert main([*args, "--out", str(tmp_path / "single")]) == 0
    multi = json.loads((tmp_path / "multi" / "report.json").read_text())
    single = json.loads((tmp_path / "single" / "report.json").read_text())
    assert multi["world_size"] == 2 and single["world_size"] == 1
    assert multi["rows"] == single["rows"]  # equal, not close: the sums are reduced pair by pair
    # every metric goes through the all-reduce: census and SSIM beside L1 and EPE
    for key in ("census_road", "census_all_noc", "ssim_road", "ssim_all", "photo_road", "epe_road"):
        assert all(f"{key}_before" in r and f"{key}_after" in r for r in multi["rows"]), key
    assert sorted({r["rank"] for r in multi["pairs"]}) == [0, 1]
    keys = [(r["pair"], r["variant"]) for r in multi["pairs"]]
    assert sorted(keys) == sorted((f"{i:06d}", v) for i in range(4) for v in ("given", "fit"))  # each once
    ranks = {r["pair"]: r["rank"] for r in multi["pairs"]}
    assert ranks == {"000000": 0, "000001": 1, "000002": 0, "000003": 1}  # strided
    strip = lambda rs: [{k: v for k, v in r.items() if k != "rank"} for r in rs]  # noqa: E731
    assert strip(multi["pairs"]) == strip(single["pairs"])


def test_processes_wait_for_the_others_longer_than_the_backend_default(monkeypatch):
    """A process that finished its pairs waits in the gather for the others' pairs: with the
    backend's default timeout (30 minutes for gloo) a long clip's uneven shares ended the run
    without its report."""
    import datetime

    import torch.distributed as dist

    from refine import distributed

    seen = {}
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setattr(dist, "is_initialized", lambda: False)
    monkeypatch.setattr(dist, "init_process_group", lambda **kwargs: seen.update(kwargs))
    world = distributed.init("cpu")
    assert world.rank == 1 and world.world_size == 2 and seen["backend"] == "gloo"
    assert seen["timeout"] == distributed.WAIT_FOR_OTHERS >= datetime.timedelta(days=1)


def test_a_distributed_environment_torchrun_did_not_set_exits_2_naming_the_variable(tmp_path, capsys,
                                                                                     torchrun_environment):
    """A WORLD_SIZE left in the shell (no torchrun, so no RANK) stopped the job with a traceback
    (KeyError: 'RANK'), one that is no number with int()'s message alone: exit 2 naming the
    variable, before any process group is joined or any file written."""
    from refine.__main__ import main

    env, message, quoted = torchrun_environment
    out = tmp_path / "out"
    assert main(["--num-pairs", "1", "--size", "48x160", "--source", "dis", "--odometry", "given", "--no-figures",
                 "--no-progress", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {message}") and quoted in err, err
    assert not out.exists()
