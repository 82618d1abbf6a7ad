"""Smoke test of ``python -m eval noise`` (in-process, tiny renders)."""

from __future__ import annotations

import json
import re

import pytest

from eval.__main__ import main


def test_noise_quick(tmp_path, capsys, check_environment):
    out = tmp_path / "noise"
    rc = main(["noise", "--quick", "--size", "48", "160", "--pose-size", "60", "200", "--sigmas", "0", "0.5",
               "--pose-sigmas", "0", "1", "--trials", "2", "--out", str(out), "--no-progress"])
    assert rc == 0
    data = json.loads((out / "noise.json").read_text())
    assert {"settings", "noise_robustness", "pose", "pose_trials", "files"} <= set(data)
    check_environment(data["environment"], job="eval", command="python -m eval noise", seed=0)
    assert [r["sigma"] for r in data["noise_robustness"]] == [0.0, 0.5]
    assert data["noise_robustness"][0]["e_E"] < 1e-6
    assert {"sigma", "translation_error_m", "yaw_error_deg"} <= set(data["pose"][0])
    for name in ("noise_robustness.png", "pose_errors.png", "pose_scatter.png"):
        assert (out / name).stat().st_size > 1000
    assert "Pose from noisy flow" in capsys.readouterr().out


def test_noise_json_path_no_plots(tmp_path):
    path = tmp_path / "n.json"
    rc = main(["noise", "--quick", "--size", "48", "160", "--pose-size", "60", "200", "--sigmas", "0.1",
               "--pose-sigmas", "0.5", "--trials", "1", "--out", str(tmp_path / "o"), "--json", str(path),
               "--no-plots", "--no-progress"])
    assert rc == 0
    data = json.loads(path.read_text())
    assert data["files"] == {}
    assert not (tmp_path / "o").exists()  # nothing is written there: the folder is not created


def test_noise_bad_arguments(tmp_path, capsys):
    assert main(["noise", "--sigmas", "-1", "--out", str(tmp_path)]) == 2
    assert "--sigmas" in capsys.readouterr().err


@pytest.mark.parametrize("trials", ["0", "100001", str(10**11)])
def test_noise_trials_out_of_range_exit_2_before_any_work(tmp_path, capsys, trials):
    """10**11 trials ended in a traceback from the allocator, after the robustness fits."""
    assert main(["noise", "--quick", "--trials", trials, "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert f"error: --trials: expected 1 to 100000, got {trials}" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_noise_non_finite_sigmas_exit_2(tmp_path, capsys):
    for option in ("--sigmas", "--pose-sigmas"):
        assert main(["noise", option, "0", "inf", "--out", str(tmp_path / "o"), "--no-progress"]) == 2
        assert f"error: {option}: expected values in [0, 10000] px" in capsys.readouterr().err
    assert main(["noise", "--sigmas", "nan", "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert not (tmp_path / "o").exists()


def test_noise_sigmas_above_the_bound_exit_2(tmp_path, capsys, monkeypatch):
    """A huge finite σ (the fit's kernel scale 2σ overflowed to inf at 1e308; the pose experiment's
    float32 flow at 1e39) exits 2 naming the option, before any work; the bound itself is taken."""
    import eval.noise as noise

    for option, value in (("--sigmas", "1e308"), ("--pose-sigmas", "1e39"), ("--sigmas", "10000.5")):
        assert main(["noise", option, "0", value, "--out", str(tmp_path / "o"), "--no-progress"]) == 2
        assert f"error: {option}: expected values in [0, 10000] px, got [0.0, {float(value)}]" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()

    class Reached(Exception):
        pass

    def stop(size, sigmas, *args, **kwargs):
        raise Reached(sigmas)

    monkeypatch.setattr(noise, "noise_robustness", stop)
    with pytest.raises(Reached, match=r"\[10000.0\]"):
        main(["noise", "--sigmas", "1e4", "--pose-sigmas", "1e4", "--out", str(tmp_path / "o"), "--no-progress"])


def test_noise_output_paths_checked_before_the_work(tmp_path, capsys):
    (tmp_path / "afile").write_text("")
    assert main(["noise", "--quick", "--out", str(tmp_path / "afile"), "--no-progress"]) == 2
    assert "error: --out: " in capsys.readouterr().err
    assert main(["noise", "--quick", "--out", str(tmp_path / "o"), "--json", str(tmp_path / "afile" / "n.json"),
                 "--no-progress"]) == 2
    assert "error: --json: " in capsys.readouterr().err
    (tmp_path / "o" / "pose_errors.png").mkdir(parents=True)
    assert main(["noise", "--quick", "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert "pose_errors.png' is a folder" in capsys.readouterr().err


def test_noise_row_over_no_pixel_is_none_with_a_warning(capsys):
    """A fit that covers no road pixel (σ at the bound here) reports its errors as None, printed
    '-', with a warning: not the 0.0 of flow_metrics over no pixel, which reads as a perfect fit."""
    from eval.noise import noise_robustness
    from eval.tables import format_table

    clean, lost = noise_robustness((48, 160), [0.0, 1e4], [("complex", 1)], 0)
    assert clean["n_pixels"] > 0 and clean["e_E"] < 1e-6
    assert lost["n_pixels"] == 0
    assert [lost[k] for k in ("e_E", "e_A", "e_E_vs_noisy", "e_A_vs_noisy")] == [None] * 4
    assert "warning: complex x1, sigma 10000: the fitted model covers no road pixel" in capsys.readouterr().err
    assert format_table([lost], [("e_E", "e_E px", ".2e")]).splitlines()[-1].strip() == "-"


@pytest.mark.parametrize("plots, name, refused", [
    ([], "pose_errors.png", True), ([], "noise_robustness.png", True), ([], "sub/../pose_scatter.png", True),
    (["--no-plots"], "pose_errors.png", False),  # (not written without the plots)
])
def test_noise_json_naming_a_figure(tmp_path, capsys, monkeypatch, plots, name, refused):
    """--json naming a figure the run writes is refused before any work (the JSON replaced it)."""
    import eval.noise as noise

    class Reached(Exception):
        pass

    def stop(*args, **kwargs):
        raise Reached

    monkeypatch.setattr(noise, "noise_robustness", stop)
    argv = ["noise", "--quick", *plots, "--out", str(tmp_path / "o"), "--json", str(tmp_path / "o" / name),
            "--no-progress"]
    if not refused:
        with pytest.raises(Reached):
            main(argv)
        return
    assert main(argv) == 2
    expected = f"error: --json: {str(tmp_path / 'o' / name)!r} names {name.split('/')[-1]}, a file the job writes into "
    assert expected in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("option, size", [("--size", ["16385", "64"]), ("--pose-size", ["64", "100000000"])])
def test_noise_sizes_bounded(tmp_path, capsys, monkeypatch, option, size):
    import eval.noise as noise

    monkeypatch.setattr(noise, "noise_robustness", lambda *a, **k: pytest.fail("rendered before the check"))
    assert main(["noise", option, *size, "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert f"error: {option}: expected H, W <= 16384, got [{size[0]}, {size[1]}]" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("box", [(0, 1, 0, 1), (0, 10, 0, 120)])
def test_pose_experiment_box_without_model_pixels_raises(box):
    """A box above the horizon leaves no pixel to fit: ValueError naming box, not "errors" of a
    fit over nothing (num_pixels 0 with finite errors)."""
    from eval.pose import pose_estimation_experiment

    with pytest.raises(ValueError, match=rf"^box: {re.escape(repr(box))} holds no pixel where the model flow is defined"):
        pose_estimation_experiment([0.0], trials=2, size=(40, 120), box=box)
    res = pose_estimation_experiment([0.0], trials=2, size=(40, 120), box=(30, 40, 0, 120))
    assert res.num_pixels > 0


def test_noise_rerun_without_plots_leaves_no_plot_of_the_run_before(tmp_path):
    """A rerun with --no-plots into the same folder removes the earlier run's PNGs, which would
    read as this run's beside its noise.json; one with --json elsewhere removes DIR/noise.json."""
    out = tmp_path / "o"
    base = ["noise", "--quick", "--size", "32", "96", "--pose-size", "32", "96", "--trials", "1", "--sigmas", "0",
            "--pose-sigmas", "0", "--out", str(out), "--no-progress"]
    assert main(base) == 0
    assert sorted(p.name for p in out.iterdir()) == ["noise.json", "noise_robustness.png", "pose_errors.png",
                                                    "pose_scatter.png"]
    assert main([*base, "--no-plots", "--seed", "5"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["noise.json"]
    assert json.loads((out / "noise.json").read_text())["settings"]["seed"] == 5
    assert main([*base, "--no-plots", "--json", str(tmp_path / "n.json")]) == 0
    assert list(out.iterdir()) == [] and (tmp_path / "n.json").is_file()


def test_noise_a_run_that_stops_leaves_no_earlier_json(tmp_path, interrupted):
    """An earlier run's --json (elsewhere than --out) goes once the options are checked, as
    DIR/noise.json does: a run stopped during the fits left it to be read as its own."""
    from eval import noise

    path = tmp_path / "n.json"
    path.write_text('{"settings": "an earlier run"}')

    interrupted(noise, "noise_robustness", lambda: main(["noise", "--quick", "--trials", "1", "--out", str(tmp_path / "o"),
                                                         "--json", str(path), "--no-progress"]))
    assert not path.exists()


def test_noise_explains_a_pose_success_rate_below_one(tmp_path, capsys):
    """σ = 4 px at the default kernel scale: the pose fits are flagged (fewer than a quarter of the
    pixels within 3 px) while their errors stay small; the job says why under the table, and only
    where a rate is below 1."""
    args = ["noise", "--sigmas", "0", "--size", "48", "160", "--pose-size", "120", "400", "--trials", "3",
            "--no-plots", "--no-progress", "--out", str(tmp_path / "noise")]
    assert main(args + ["--pose-sigmas", "0", "4"]) == 0
    out = capsys.readouterr().out
    pose = json.loads((tmp_path / "noise" / "noise.json").read_text())["pose"]
    assert [r["success_rate"] for r in pose] == [1.0, 0.0]
    assert pose[1]["translation_error_m"] < 0.05
    assert "flags flow noisier than about 4 px whatever its motion" in out
    assert main(args + ["--pose-sigmas", "0", "1"]) == 0
    assert "whatever its motion" not in capsys.readouterr().out


def test_noise_curves_are_drawn_in_sigma_order(tmp_path, monkeypatch):
    """--sigmas / --pose-sigmas given unsorted: each curve runs through its points in σ order
    (in the order given it doubled back on itself), each σ still with its own value."""
    import matplotlib

    matplotlib.use("Agg")
    import torch
    from matplotlib.axes import Axes

    import eval.noise as noise
    from eval.pose import PoseEstimationResult

    drawn = []
    plot = Axes.plot

    def record(self, *args, **kwargs):
        if len(args) >= 2:
            drawn.append((kwargs.get("label"), list(args[0]), list(args[1])))
        return plot(self, *args, **kwargs)

    monkeypatch.setattr(Axes, "plot", record)
    sigmas = [2.0, 0.0, 0.5]
    rows = [{"scenario": "complex", "speed": "x1", "sigma": s, "e_E": 1.0 + s, "e_A": 2.0 + s} for s in sigmas]
    noise._plot_robustness(rows, tmp_path / "r.png")
    assert [d[1:] for d in drawn] == [([0.0, 0.5, 2.0], [1.0, 1.5, 3.0]), ([0.0, 0.5, 2.0], [2.0, 2.5, 4.0])]
    drawn.clear()
    t = torch.tensor(sigmas, dtype=torch.float64)
    res = PoseEstimationResult(sigmas=t, translation_error=t + 1, x_error=t + 2, z_error=t + 3,
                               yaw_error_deg=t + 4, success_rate=torch.ones(3), true_pose=torch.ones(2, 3),
                               estimated_pose=torch.full((3, 2, 3), 1.5), num_pixels=10.0, settings={"trials": 2})
    noise._plot_pose(res, tmp_path / "e.png", tmp_path / "s.png")
    assert [d for d in drawn if d[0] != "paper bound"] == [
        ("‖d error‖", [0.0, 0.5, 2.0], [1.0, 1.5, 3.0]), ("|x_d error|", [0.0, 0.5, 2.0], [2.0, 2.5, 4.0]),
        ("|z_d error|", [0.0, 0.5, 2.0], [3.0, 3.5, 5.0]), ("|yaw error|", [0.0, 0.5, 2.0], [4.0, 4.5, 6.0])]


def test_noise_tables_print_each_sigma_as_given(tmp_path, capsys):
    """The σ column names the noise of its row: 0.005 printed 0.01 and 0.001 printed 0.00, the label
    of a noise-free row, and 1e-5 printed 0.0000; the noisy flow's distance, 1.2e-05 px at σ = 1e-5,
    printed 0.000."""
    sigmas, pose_sigmas = ["0", "1e-05", "0.125"], ["0", "0.001", "0.005", "0.125"]
    assert main(["noise", "--quick", "--size", "32", "96", "--pose-size", "40", "120", "--trials", "1",
                 "--sigmas", *sigmas, "--pose-sigmas", *pose_sigmas, "--no-plots", "--no-progress",
                 "--out", str(tmp_path / "noise")]) == 0
    out = capsys.readouterr().out
    data = json.loads((tmp_path / "noise" / "noise.json").read_text())
    robust, pose = out.split("Pose from noisy flow")
    robust_rows = [line.split() for line in robust.splitlines() if line.startswith(" complex")]
    pose_rows = [line.split() for line in pose.splitlines()[3:3 + len(pose_sigmas)]]
    assert [float(r[2]) for r in robust_rows] == [float(s) for s in sigmas]
    assert [float(r[0]) for r in pose_rows] == [float(s) for s in pose_sigmas]
    noisy = [r["e_E_vs_noisy"] for r in data["noise_robustness"]]
    assert noisy[1] > 1e-6  # (the noise itself: about 1.25 σ)
    assert [float(r[5]) for r in robust_rows] == pytest.approx(noisy, rel=5e-3)


def test_noise_warning_during_the_bar_starts_a_line_of_its_own(capsys):
    """The warning of a row over no pixel followed the bar's text on the bar's line (``noise
    robustness:   0%|... 0/2 [00:00<?, ?fit/s]warning: complex x1, ...``); now the bar is cleared,
    the warning printed from the start of a line, and the bar drawn again below it."""
    import re

    from eval.noise import noise_robustness
    from fsof_torch.io.progress import progress_bar

    with progress_bar(total=2, desc="noise robustness", unit="fit") as bar:
        noise_robustness((48, 160), [0.0, 1e4], [("complex", 1)], 0, bar=bar)
    err = capsys.readouterr().err
    warning = "warning: complex x1, sigma 10000: the fitted model covers no road pixel; its errors are '-'\n"
    before, found, after = err.partition(warning)
    assert found and before.endswith("\r") and "noise robustness:" not in re.split("[\r\n]", before)[-1], err
    assert after.startswith("\rnoise robustness:") and "2/2" in after, err
