"""Smoke test of ``python -m eval train``: a handful of steps on a tiny size, in-process."""

from __future__ import annotations

import json

import pytest
import torch


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
    assert "road census" in printed and "road SSIM" in printed and "road L1" in printed
    for run in report["metrics"].values():
        for region in ("road", "non_road", "all"):
            assert run[region]["e_E"] >= 0 and run[region]["n_pixels"] > 0
            for kind in ("census", "ssim", "l1"):
                assert run[region][f"n_{kind}"] > 0 and run[region][kind] >= 0
            assert 0 <= run[region]["census"] <= 1 and 0 <= run[region]["ssim"] <= 1
    assert set(report["training"]["unsupervised+freespace"]["final_loss"]) == {"total", "unsupervised", "freespace"}
    net = TinyRAFT(iters=1)
    net.load_state_dict(torch.load(out / "tinyraft_unsupervised_freespace.pt"))


@pytest.mark.parametrize("argv, message", [
    (["--freespace-weight", "0"], "--freespace-weight: expected a finite number > 0, got 0.0"),
    (["--steps", "0"], "--steps: expected at least 1, got 0"),
    (["--test-pairs", "-1"], "--test-pairs: expected at least 1"),
    (["--size", "8", "64"], "--size: expected H, W >= 16"),
    (["--lr", "nan"], "--lr: expected a finite number > 0"),
    (["--preset", "nope"], "--preset: unknown preset 'nope'"),
    (["--device", "bogus"], "--device: not a torch device: 'bogus'"),
    (["--seed", "-1"], "--seed: expected an int in [0, 2**62), got -1"),
    # (the held-out scenes' seed, --seed + 1000, must be a scene seed too)
    (["--seed", str(2**62 - 1000)], f"--seed: expected at most 2**62 - 1001 (the held-out seed is --seed + 1000), "
                                    f"got {2**62 - 1000}"),
])
def test_train_job_rejects_bad_options(capsys, argv, message):
    """Exit 2 with a message naming the option, before anything is rendered or trained."""
    assert eval_main(["train", *argv, "--steps" if "--steps" not in argv else "--batch", "1"]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("option, where, message", [
    ("--out", "afile", "--out: '{tmp}/afile' is a file; expected a folder"),
    ("--json", "afile/t.json", "--json: '{tmp}/afile' is a file, so '{tmp}/afile/t.json' cannot be created"),
    ("--json", "folder", "--json: '{tmp}/folder' is a folder; expected a file path"),
    ("--dump-first-step", "folder", "--dump-first-step: '{tmp}/folder' is a folder"),
    ("--out", "nets", "--out: '{tmp}/nets/tinyraft_unsupervised.pt' is a folder, where the job writes a file"),
])
def test_train_job_checks_output_paths_first(tmp_path, capsys, monkeypatch, option, where, message):
    """An output that cannot be written: exit 2 naming the option, before anything is rendered."""
    (tmp_path / "afile").write_text("")
    (tmp_path / "folder").mkdir()
    (tmp_path / "nets" / "tinyraft_unsupervised.pt").mkdir(parents=True)
    monkeypatch.setattr(train, "render_pairs", lambda *a, **k: pytest.fail("rendered before the paths were checked"))
    assert eval_main(["train", "--steps", "1", option, str(tmp_path / where), "--no-progress"]) == 2
    assert message.format(tmp=tmp_path) in capsys.readouterr().err


def test_train_job_rejects_batch_larger_than_train_pairs(capsys, monkeypatch):
    """A batch is drawn from the training pairs without repeats: more than there are exits 2 before rendering."""
    monkeypatch.setattr(train, "render_pairs", lambda *a, **k: pytest.fail("rendered before --batch was checked"))
    assert eval_main(["train", "--steps", "1", "--batch", "5", "--train-pairs", "4", "--no-progress"]) == 2
    assert "error: --batch: expected at most --train-pairs (4), got 5" in capsys.readouterr().err


def test_dispatcher_help(capsys):
    with pytest.raises(SystemExit) as exc:
        eval_main(["train", "--help"])
    assert exc.value.code == 0
    assert "--freespace-weight" in capsys.readouterr().out


@pytest.mark.slow
def test_torchrun_ddp_first_step_equals_one_process(tmp_path, keep_threads):
    """torchrun with 2 gloo processes runs to the end; its first step's loss and gradients equal
    one process's on the same global batch (relative 1e-5)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    args = ["--steps", "2", "--size", "32", "64", "--batch", "4", "--iters", "1", "--train-pairs", "4",
            "--test-pairs", "1", "--threads", "1", "--no-progress"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                           "-m", "eval", "train", *args, "--json", str(tmp_path / "ddp.json"),
                           "--dump-first-step", str(tmp_path / "ddp.pt")],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads((tmp_path / "ddp.json").read_text())["world_size"] == 2
    assert train.main([*args, "--dump-first-step", str(tmp_path / "one.pt")]) == 0
    ddp, one = torch.load(tmp_path / "ddp.pt"), torch.load(tmp_path / "one.pt")
    assert (ddp["world_size"], one["world_size"]) == (2, 1)
    for run in ("unsupervised", "unsupervised+freespace"):
        assert ddp[run]["loss"] == pytest.approx(one[run]["loss"], rel=1e-5)
        g1, g2 = one[run]["grads"], ddp[run]["grads"]
        assert set(g1) == set(g2)
        flat = torch.cat([g.flatten() for g in g1.values()])
        diff = torch.cat([(g2[k] - g1[k]).flatten() for k in g1])
        assert float(diff.norm() / flat.norm()) < 1e-5
        # tensor by tensor, to 1e-5 of the gradient's scale (biases before instance norm have a
        # zero gradient, whose rounding noise has no relative size)
        scale = float(flat.abs().max())
        for k in g1:
            torch.testing.assert_close(g2[k], g1[k], rtol=1e-5, atol=1e-5 * scale, msg=k)


def test_evaluate_net_pools_photometric_errors_over_pixels(keep_threads):
    """The photometric figures of eval train pool over pixels (KITTI style): the count-weighted
    mean of the per-pair errors, road and overall, for census, SSIM and L1."""
    from fsof_torch.evaluation.photometric import photometric_error

    torch.set_num_threads(1)
    data = train.render_pairs("default", 2, seed=5, size=(32, 64))
    net = TinyRAFT(seed=0, iters=1).eval()
    metrics = train.evaluate_net(net, data)
    with torch.no_grad():
        flows = net(data["image1"], data["image2"])[-1]
    for region, mask in (("road", data["road"]), ("all", None)):
        for kind in ("census", "ssim", "l1"):
            mean, count = photometric_error(data["image1"], data["image2"], flows, mask, kind=kind, return_count=True)
            pooled = float((mean.double() * count).sum() / count.sum())
            assert metrics[region][kind] == pytest.approx(pooled, rel=1e-6)
            assert metrics[region][f"n_{kind}"] == int(count.sum())
