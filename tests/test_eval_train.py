"""Smoke test of ``python -m eval train``: a handful of steps on a tiny size, in-process."""

from __future__ import annotations

import json

import pytest
import torch

pytest.importorskip("fsof_torch.data.scene")

from eval import train  # noqa: E402
from eval.__main__ import main as eval_main  # noqa: E402
from fsof_torch.training.testnet import TinyRAFT  # noqa: E402


@pytest.fixture
def keep_threads():
    """The job sets torch's thread count for the process; give the rest of the suite its own back."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_train_job_smoke(tmp_path, capsys, keep_threads):
    out = tmp_path / "nets"
    rc = train.main(["--steps", "2", "--size", "32", "64", "--batch", "2", "--iters", "1",
                     "--train-pairs", "2", "--test-pairs", "1", "--threads", "1", "--no-progress",
                     "--json", str(tmp_path / "train.json"), "--out", str(out)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "road EPE" in printed and "change with freespace" in printed
    report = json.loads((tmp_path / "train.json").read_text())
    assert set(report["metrics"]) == {"untrained", "unsupervised", "unsupervised+freespace"}
    for run in report["metrics"].values():
        for region in ("road", "non_road", "all"):
            assert run[region]["e_E"] >= 0 and run[region]["n_pixels"] > 0
    assert set(report["training"]["unsupervised+freespace"]["final_loss"]) == {"total", "unsupervised", "freespace"}
    net = TinyRAFT(iters=1)
    net.load_state_dict(torch.load(out / "tinyraft_unsupervised_freespace.pt"))


def test_train_job_rejects_bad_options():
    with pytest.raises(SystemExit, match="--freespace-weight must be > 0"):
        train.main(["--freespace-weight", "0", "--steps", "1"])


def test_dispatcher_help(capsys):
    with pytest.raises(SystemExit) as exc:
        eval_main(["train", "--help"])
    assert exc.value.code == 0
    assert "--freespace-weight" in capsys.readouterr().out
