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


def test_train_job_smoke(tmp_path, capsys, keep_threads, check_environment):
    torch.set_num_threads(2)
    threads = torch.get_num_threads()
    out = tmp_path / "nets"
    rc = train.main(["--steps", "2", "--size", "32", "64", "--batch", "2", "--iters", "1",
                     "--train-pairs", "2", "--test-pairs", "1", "--threads", "1", "--no-progress",
                     "--json", str(tmp_path / "train.json"), "--out", str(out)])
    assert rc == 0
    assert torch.get_num_threads() == threads  # (the caller's count, given back; --threads 1 was set for the run)
    printed = capsys.readouterr().out
    assert "road EPE" in printed and "change with freespace" in printed
    report = json.loads((tmp_path / "train.json").read_text())
    assert set(report["metrics"]) == {"untrained", "unsupervised", "unsupervised+freespace"}
    check_environment(report["environment"], job="eval", command="python -m eval train", seed=0)
    assert report["environment"]["threads"]["torch"] == 1  # (the run's --threads, not the caller's 2)
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


def test_train_job_same_seed_writes_the_same_bytes(tmp_path, capsys, keep_threads):
    """Two runs with the same options write byte-identical state_dicts and first-step dumps (their
    archives named after the temporary file they were written to, a random name, they differed)."""
    files = []
    for run in ("a", "b"):
        argv = ["--steps", "1", "--size", "32", "64", "--batch", "2", "--iters", "1", "--train-pairs", "2",
                "--test-pairs", "1", "--threads", "1", "--no-progress", "--out", str(tmp_path / run / "nets"),
                "--dump-first-step", str(tmp_path / run / "first.pt")]
        assert train.main(argv) == 0
        files.append({p.relative_to(tmp_path / run): p.read_bytes() for p in sorted((tmp_path / run).rglob("*.pt"))})
    capsys.readouterr()
    assert len(files[0]) == 3 and files[0] == files[1]
    net = TinyRAFT(iters=1)
    net.load_state_dict(torch.load(tmp_path / "a" / "nets" / "tinyraft_unsupervised.pt"))
    assert torch.load(tmp_path / "a" / "first.pt")["world_size"] == 1


@pytest.mark.parametrize("argv, message", [
    (["--freespace-weight", "0"], "--freespace-weight: expected a finite number > 0, got 0.0"),
    (["--steps", "0"], "--steps: expected at least 1, got 0"),
    (["--test-pairs", "-1"], "--test-pairs: expected at least 1"),
    (["--size", "8", "64"], "--size: expected H, W >= 16"),
    (["--lr", "nan"], "--lr: expected a finite number > 0"),
    (["--lr", "0"], "--lr: expected a finite number > 0, got 0.0"),
    (["--lr", "-0.001"], "--lr: expected a finite number > 0, got -0.001"),
    # (AdamW's first step, 10 × lr, overflowed float32 inside the optimiser: a traceback)
    (["--lr", "1e300"], "--lr: expected at most 1e+37 (AdamW's first step is 10 × lr, which must fit the net's "
                        "float32), got 1e+300"),
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


def test_a_diverging_run_exits_2_naming_lr_and_writes_nothing(tmp_path, capsys, keep_threads):
    """A learning rate far too large drives the net to NaN within a few steps: the job stops with a
    message naming --lr (it used to end in a traceback from the loss), and writes no output."""
    out, report = tmp_path / "nets", tmp_path / "train.json"
    rc = train.main(["--lr", "1e6", "--steps", "5", "--size", "32", "64", "--batch", "2", "--iters", "1",
                     "--train-pairs", "2", "--test-pairs", "1", "--threads", "1", "--no-progress",
                     "--json", str(report), "--out", str(out), "--dump-first-step", str(tmp_path / "first.pt")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "error: --lr: training diverged at step" in err and "learning rate 1e+06 is likely too large" in err, err
    assert "run 'unsupervised'" in err and "Traceback" not in err
    assert not report.exists() and not out.exists() and not (tmp_path / "first.pt").exists()
    # an earlier run's outputs at these paths go: they would read as this run's
    out.mkdir()
    earlier = [out / "tinyraft_unsupervised.pt", out / "tinyraft_unsupervised_freespace.pt", report,
               tmp_path / "first.pt"]
    for path in earlier:
        path.write_bytes(b"an earlier run's")
    (out / "mine.pt").write_bytes(b"not the job's")
    rc = train.main(["--lr", "1e6", "--steps", "5", "--size", "32", "64", "--batch", "2", "--iters", "1",
                     "--train-pairs", "2", "--test-pairs", "1", "--threads", "1", "--no-progress",
                     "--json", str(report), "--out", str(out), "--dump-first-step", str(tmp_path / "first.pt")])
    assert rc == 2 and "error: --lr: training diverged" in capsys.readouterr().err
    assert [p for p in earlier if p.exists()] == [] and sorted(p.name for p in out.iterdir()) == ["mine.pt"]


@pytest.mark.parametrize("weight, what", [("1e300", "the loss"), ("1e20", "the gradients' norm")])
def test_a_freespace_weight_too_large_exits_2_naming_it(tmp_path, capsys, keep_threads, weight, what):
    """The first step's loss (1e300) or gradients' norm (1e20) not finite, before any update: the
    learning rate plays no part, so the message names --freespace-weight (it named --lr and its
    default 0.001); a norm that overflowed scaled every gradient to 0, and the untrained net was
    reported as the run with the freespace term."""
    report = tmp_path / "train.json"
    rc = train.main(["--freespace-weight", weight, "--steps", "2", "--size", "32", "64", "--batch", "2",
                     "--iters", "1", "--train-pairs", "2", "--test-pairs", "1", "--threads", "1", "--no-progress",
                     "--json", str(report)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert (f"error: --freespace-weight: training diverged at step 1 of 2 ({what} not finite) before any update"
            in err and f"the freespace weight {float(weight):g} is likely too large" in err), err
    assert "run 'unsupervised+freespace'" in err and "--lr" not in err and not report.exists()


def test_train_net_raises_on_non_finite_parameters(keep_threads):
    """An update that leaves a parameter non-finite stops training at once: no NaN net is returned."""
    torch.set_num_threads(1)
    data = train.render_pairs("default", 2, seed=0, size=(32, 64))
    with pytest.raises(train.TrainingDiverged, match=r"^lr: training diverged at step 1 of 1 \(the net's "
                                                     r"parameters after the update not finite\)"):
        train.train_net(data, steps=1, seed=0, batch=2, lr=float("inf"), freespace_weight=0.0, iters=1,
                        progress=False)


def test_dispatcher_help(capsys):
    assert eval_main(["train", "--help"]) == 0  # (returned, not raised: main(argv) -> int)
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


def _torch_one_cycle(steps: int, lr: float) -> list[float]:
    """The learning rates torch's OneCycleLR gives the job's settings, step by step."""
    param = torch.nn.Parameter(torch.zeros(1))
    optimiser = torch.optim.AdamW([param], lr=lr, weight_decay=1e-5)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, max_lr=lr, total_steps=steps, pct_start=0.05,
                                                   anneal_strategy="linear", cycle_momentum=False)
    rates = []
    for _ in range(steps):
        rates.append(optimiser.param_groups[0]["lr"])
        optimiser.step()
        schedule.step()
    return rates


@pytest.mark.parametrize("steps", [21, 39, 40, 150, 151, 400])
@pytest.mark.parametrize("lr", [1e-3, 3e-4])
def test_one_cycle_lr_is_torchs_schedule_bit_for_bit(steps, lr):
    """Where OneCycleLR has a warm-up (more than 20 steps; the default 150) the job's schedule is
    its values exactly, so results at those settings are unchanged."""
    assert [train.one_cycle_lr(step, steps, lr) for step in range(steps)] == _torch_one_cycle(steps, lr)


def test_one_cycle_lr_short_runs_start_at_the_full_rate():
    """At most 20 steps: no warm-up (shorter than a step); OneCycleLR divided by zero at 20 and,
    below, ran a single step at lr / 25 / 1e4, which trained nothing."""
    lr = 1e-3
    assert train.one_cycle_lr(0, 1, lr) == lr
    assert [train.one_cycle_lr(s, 2, lr) for s in range(2)] == [lr, pytest.approx(lr / 25 / 1e4)]
    rates = [train.one_cycle_lr(s, 20, lr) for s in range(20)]
    assert rates[0] == lr and rates[-1] == pytest.approx(lr / 25 / 1e4)
    assert all(a > b for a, b in zip(rates, rates[1:]))  # a linear decay
    assert rates[10] == pytest.approx(lr + (lr / 25 / 1e4 - lr) * 10 / 19)
    with pytest.raises(ZeroDivisionError):  # (what the job used to do at 20 steps)
        _torch_one_cycle(20, lr)


def test_train_net_single_step_trains(keep_threads):
    """--steps 1 moves the weights at the full learning rate (it used to run at 4e-9)."""
    torch.set_num_threads(1)
    data = train.render_pairs("default", 2, seed=0, size=(32, 64))
    net, _ = train.train_net(data, steps=1, seed=0, batch=2, lr=1e-3, freespace_weight=0.0, iters=1,
                             progress=False)
    start = TinyRAFT(seed=0, iters=1).state_dict()
    moved = max(float((p - start[k]).abs().max()) for k, p in net.state_dict().items() if p.is_floating_point())
    assert moved > 1e-4  # AdamW's first step moves a weight by about lr


def test_figures_over_no_pixel_are_none_and_print_a_dash(capsys):
    """A photometric error over no pixel (every sample point leaves image 2) and the flow metrics of
    a region without valid ground truth are None (JSON null), printed '-' with a warning: not 0,
    which reads as perfect."""
    data = train.render_pairs("default", 1, seed=5, size=(32, 64))
    data["valid"] = data["valid"] & ~data["road"]  # no ground truth on the road

    def far_away(image1, image2):  # every sample point 1e4 px off image 2
        return [torch.full((image1.shape[0], 2, *image1.shape[-2:]), 1e4)]

    metrics = train.evaluate_net(far_away, data)
    for region in ("road", "non_road", "all"):
        assert [metrics[region][k] for k in ("census", "ssim", "l1")] == [None] * 3
        assert [metrics[region][f"n_{k}"] for k in ("census", "ssim", "l1")] == [0] * 3
    assert metrics["road"]["n_pixels"] == 0 and metrics["road"]["e_E"] is None and metrics["road"]["Fl"] is None
    assert metrics["non_road"]["e_E"] > 1e3
    results = {"unsupervised": metrics}
    train._warn_no_pixels(results)
    err = capsys.readouterr().err
    assert "warning: unsupervised, road: no pixel with valid ground truth; its flow metrics are '-'" in err
    assert "warning: unsupervised, all: no pixel whose sample point (or window) stays inside image 2; " \
           "its census, ssim, l1 are '-'" in err
    assert train._photometric_row("x", metrics).split() == ["x", "-", "-", "-", "-", "-", "-"]
    row = train._row("x", metrics).split()
    assert row[1] == "-" and row[4] == "-" and float(row[2]) > 1e3
    filled = {**metrics, "road": {**metrics["road"], "e_E": 1.0, "Fl": 0.5}}  # '-' keeps the columns aligned
    assert len(train._row("x", metrics)) == len(train._row("x", filled))


@pytest.mark.parametrize("argv, message", [
    (["--size", "20000", "64"], "--size: expected H, W <= 16384, got [20000, 64]"),
    (["--device", "meta"], "--device: 'meta' holds no data (shapes only); give cpu or cuda"),
    (["--device", "mps"], "--device: cannot place a tensor on 'mps' ("),
    # (a huge thread count crashed torch's pool; pairs beyond the renderer's last frame ended in a
    # traceback after the work)
    (["--threads", "100000000"], "--threads: expected at most this machine's"),
    (["--train-pairs", "100001"], "--train-pairs: expected at most 100000, got 100001"),
    (["--test-pairs", "100001"], "--test-pairs: expected at most 100000, got 100001"),
])
def test_train_job_checks_size_and_device_before_the_work(capsys, monkeypatch, argv, message):
    """A huge --size, or a --device that cannot hold the nets, exits 2 naming it before anything is
    rendered (a device ended in a traceback after the rendering, exit 1)."""
    monkeypatch.setattr(train, "render_pairs", lambda *a, **k: pytest.fail("rendered before the check"))
    assert eval_main(["train", *argv, "--no-progress"]) == 2
    assert capsys.readouterr().err.startswith(f"error: {message}")


@pytest.mark.parametrize("json_name, dump_name", [
    ("x.pt", "x.pt"), ("o/tinyraft_unsupervised.pt", None), ("o/tinyraft_unsupervised_freespace.pt", None),
])
def test_train_job_json_naming_another_output_exits_2(tmp_path, capsys, monkeypatch, json_name, dump_name):
    """--json naming the --dump-first-step file or a state_dict the job writes into --out is
    refused before any work (the files written later replaced the JSON, or it them)."""
    monkeypatch.setattr(train, "render_pairs", lambda *a, **k: pytest.fail("rendered before the check"))
    target = tmp_path / json_name
    argv = ["train", "--out", str(tmp_path / "o"), "--json", str(target), "--no-progress"]
    if dump_name is not None:
        argv += ["--dump-first-step", str(tmp_path / dump_name)]
    assert eval_main(argv) == 2
    assert capsys.readouterr().err.startswith(f"error: --json: {str(target)!r} names {target.name}, a file the job "
                                              f"writes into ")
    assert eval_main(["train", "--out", str(tmp_path / "o"), "--dump-first-step", str(tmp_path / "o" / "tinyraft_"
                 "unsupervised.pt"), "--no-progress"]) == 2
    assert "error: --dump-first-step: " in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv, message", [
    (["--out", "{t}/o", "--json", "{t}/o"], "--json: '{t}/o' is --out '{t}/o' or a folder above it"),
    (["--out", "{t}/o/sub", "--json", "{t}/o"], "--json: '{t}/o' is --out '{t}/o/sub' or a folder above it"),
    (["--dump-first-step", "{t}/d", "--out", "{t}/d"], "--dump-first-step: '{t}/d' is --out '{t}/d' or a folder"),
    (["--dump-first-step", "{t}/d", "--json", "{t}/d/x.json"], "--json: '{t}/d/x.json' lies under --dump-first-step"),
    (["--json", "{t}/d", "--dump-first-step", "{t}/d/x.pt"], "--dump-first-step: '{t}/d/x.pt' lies under --json"),
])
def test_train_job_outputs_that_would_collide_with_out_exit_2(tmp_path, capsys, monkeypatch, argv, message):
    """An output file that is --out, a folder above it, or a path under the --dump-first-step file
    exits 2 before any work (was: the whole run, then a FileExistsError or NotADirectoryError)."""
    monkeypatch.setattr(train, "render_pairs", lambda *a, **k: pytest.fail("rendered before the check"))
    assert eval_main(["train", *(a.format(t=tmp_path) for a in argv), "--no-progress"]) == 2
    assert capsys.readouterr().err.startswith(f"error: {message.format(t=tmp_path)}")


def test_train_module_main_runs_the_eval_commands_checks(capsys):
    """``python -m eval.train`` (this module's main) checks as ``python -m eval train`` does, and
    returns argparse's status (was: a ValueError for a negative seed, SystemExit for --help)."""
    assert train.main(["--seed", "-1", "--no-progress"]) == 2
    assert "--seed" in capsys.readouterr().err
    assert train.main(["--help"]) == 0 and train.main(["--steps", "x"]) == 2


def test_training_bar_in_a_log_is_rate_limited(keep_threads, capsys):
    """With stderr not a terminal (a log, CI), the training bar is drawn when it opens and closes
    within fsof_torch.io.progress.LOG_INTERVAL, not at every step with its loss terms."""
    torch.set_num_threads(1)
    data = train.render_pairs("default", 2, seed=0, size=(32, 64))
    train.train_net(data, steps=4, seed=0, batch=1, lr=1e-3, freespace_weight=0.0, iters=1, progress=True)
    err = capsys.readouterr().err
    assert "train" in err and err.count("\r") <= 3, err


def test_train_in_a_distributed_environment_torchrun_did_not_set_exits_2(tmp_path, capsys, keep_threads,
                                                                         torchrun_environment):
    """As the refine job: a WORLD_SIZE left in the shell (no torchrun, so no RANK) failed in
    torch's env:// rendezvous with a traceback, one that is no number in int(): exit 2 naming the
    variable and how to start the job, before any process group is joined or any file written."""
    env, message, quoted = torchrun_environment
    out = tmp_path / "out"
    assert eval_main(["train", "--steps", "1", "--no-progress", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {message}") and quoted in err, err
    if "RANK: not set" in message:
        assert "torchrun --nproc-per-node N -m eval train" in err
    assert not out.exists()


@pytest.mark.parametrize("option, value, stated, refused", [
    ("--size", ["8", "48"], "image size of the rendered pairs, each side 16 to 16384 (default 64 224)",
     "--size: expected H, W >= 16, got [8, 48]"),
    ("--train-pairs", ["100001"], "training pairs rendered, 1 to 100000 (default 24)",
     "--train-pairs: expected at most 100000, got 100001"),
    ("--batch", ["25"], "pairs per step, at most --train-pairs (default 4)",
     "--batch: expected at most --train-pairs (24), got 25"),
])
def test_train_help_states_the_ranges_it_checks(capsys, option, value, stated, refused):
    """--help gave no range for these, which the job refuses beyond (exit 2): it states them now."""
    assert eval_main(["train", "--help"]) == 0
    assert stated in " ".join(capsys.readouterr().out.split())
    assert eval_main(["train", option, *value, "--no-progress"]) == 2
    assert capsys.readouterr().err == f"error: {refused}\n"
