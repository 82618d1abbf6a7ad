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


def test_torchvision_network_is_padded(tmp_path, user_module, pair):
    from fsof_torch.training.standins import TorchvisionRAFTStandIn

    summary = _run(tmp_path, "--net", f"{user_module}:torchvision_raft")
    pad = (1, 1, 1, 2)  # 45x150 -> 48x152, RAFT's split of the padding
    x1, x2 = (F.pad(im[None] / 127.5 - 1, pad, mode="replicate") for im in (pair["image1"], pair["image2"]))
    with torch.no_grad():
        flow = TorchvisionRAFTStandIn(seed=0).eval()(x1, x2)[-1][0, :, 1:46, 1:151]
    assert summary["pairs"][0]["before"]["epe_road"] == pytest.approx(_epe_road(flow, pair), rel=1e-5)


def test_network_errors(tmp_path, user_module, capsys):
    base = ["--num-pairs", "1", "--no-figures", "--no-progress", "--size", f"{SIZE[0]}x{SIZE[1]}",
            "--out", str(tmp_path / "o")]

    def err(*extra) -> str:
        assert main([*base, *extra]) == 2
        return capsys.readouterr().err

    assert "--net: cannot import module 'no_such_module_xyz'" in err("--net", "no_such_module_xyz:make")
    assert f"--net: module '{user_module}' has no attribute 'missing'" in err("--net", f"{user_module}:missing")
    assert "--net: expected module:callable" in err("--net", user_module)
    assert "returned a str; expected a torch.nn.Module" in err("--net", f"{user_module}:not_a_module")
    assert "--net-contract: cannot tell how to call TwoImages" in err("--net", f"{user_module}:two_images")
    torch.save({"fnet.weight": torch.zeros(2)}, tmp_path / "wrong.pt")
    text = err("--net", f"{user_module}:ptlflow_raft", "--checkpoint", str(tmp_path / "wrong.pt"))
    assert "--checkpoint:" in text and "wrong.pt" in text and "does not fit PtlflowRAFTStandIn" in text
    assert "--checkpoint needs --net" in err("--checkpoint", str(tmp_path / "wrong.pt"))
    assert not (tmp_path / "o" / "run.json").exists()  # every check came before any work


def test_explicit_contract(tmp_path, user_module):
    """A two-image network with --net-contract raft runs (its flows are zero: refinement fixes the road)."""
    summary = _run(tmp_path, "--net", f"{user_module}:two_images", "--net-contract", "raft")
    (record,) = summary["pairs"]
    assert record["before"]["epe_road"] > 1.0 > 1e-3 > record["after"]["epe_road"]


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
