"""Smoke tests of ``python -m eval vflow`` (in-process, tiny renders)."""

from __future__ import annotations

import json

import pytest
import torch

from eval.__main__ import main


def test_vflow_preset(tmp_path, capsys):
    out = tmp_path / "v"
    rc = main(["vflow", "--preset", "cvc-complex", "--size", "64", "208", "--out", str(out), "--no-progress"])
    assert rc == 0
    data = json.loads((out / "vflow.json").read_text())
    assert {"source", "curve", "freespace", "files"} <= set(data)
    assert data["curve"]["success"] and abs(data["curve"]["z_d_m"] - data["curve"]["z_d_m_true"]) < 0.05
    assert data["freespace"]["iou"] >= 0.9  # (0.966 measured)
    for name in ("vflow_map.png", "fv_observed.png", "fv_fitted.png", "fv_error.png", "freespace.png"):
        assert (out / name).stat().st_size > 1000
    assert "V-flow curve" in capsys.readouterr().out


def test_vflow_velocity(tmp_path):
    out = tmp_path / "v"
    rc = main(["vflow", "--preset", "carla-straight", "--model", "velocity", "--size", "64", "208",
               "--out", str(out), "--json", str(tmp_path / "v.json"), "--no-progress"])
    assert rc == 0
    data = json.loads((tmp_path / "v.json").read_text())
    assert "speed_mps" in data["curve"] and "freespace" not in data


def test_vflow_flow_file(tmp_path):
    from fsof_torch.geometry.camera import Camera
    from fsof_torch.geometry.road_flow import displacement_flow
    from fsof_torch.io import write_flow

    cam = Camera(torch.tensor([[150.0, 0, 80], [0, 150.0, 15], [0, 0, 1]]), 1.5)
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, (48, 160))
    path = tmp_path / "f.npy"
    write_flow(path, flow[0], valid[0])
    out = tmp_path / "v"
    rc = main(["vflow", "--flow", str(path), "--out", str(out), "--no-progress"])
    assert rc == 0
    data = json.loads((out / "vflow.json").read_text())
    assert abs(data["curve"]["v0"] - 15.0) < 1e-3
    assert abs(data["curve"]["a"] * 1.5 * 150.0 - 1.0) < 1e-3


def test_vflow_bad_arguments(tmp_path, capsys):
    assert main(["vflow", "--flow", str(tmp_path / "missing.flo"), "--out", str(tmp_path)]) == 2
    assert "--flow" in capsys.readouterr().err
    assert main(["vflow", "--preset", "nope", "--out", str(tmp_path), "--no-progress"]) == 2
    assert "--preset: unknown preset 'nope'" in capsys.readouterr().err
    # a file that is not a flow, a mask that is not an image: exit 2 naming the option
    (tmp_path / "bad.flo").write_bytes(b"12345")
    assert main(["vflow", "--flow", str(tmp_path / "bad.flo"), "--out", str(tmp_path), "--no-progress"]) == 2
    assert "error: --flow:" in capsys.readouterr().err
    from fsof_torch.io import write_flow

    flow = tmp_path / "good.flo"
    write_flow(flow, torch.zeros(2, 32, 48))
    (tmp_path / "bad.png").write_bytes(b"not a png")
    rc = main(["vflow", "--flow", str(flow), "--mask", str(tmp_path / "bad.png"), "--out", str(tmp_path), "--no-progress"])
    assert rc == 2 and "error: --mask:" in capsys.readouterr().err


def _small_flow(tmp_path, rows=None):
    """A 32x48 road-plane flow file; ``rows``: keep only those rows valid (NaN elsewhere)."""
    from fsof_torch.geometry.camera import Camera
    from fsof_torch.geometry.road_flow import displacement_flow
    from fsof_torch.io import write_flow

    cam = Camera(torch.tensor([[60.0, 0, 24], [0, 60.0, 4], [0, 0, 1]]), 1.5)
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, (32, 48))
    valid = valid[0].clone()
    if rows is not None:
        keep = torch.zeros_like(valid)
        keep[:, rows] = True
        valid &= keep
    path = tmp_path / "f.npy"
    write_flow(path, flow[0], valid)
    return path


@pytest.mark.parametrize("polygon_json, message", [
    ('{"size": [32, 48], "polygons": 5}', "error: --mask: "),  # malformed
    ('{"size": [32, 48], "road_polygon": [[-9, -9], [-5, -9], [-5, -5]]}', "covers no pixel where"),  # outside
])
def test_vflow_bad_or_empty_mask_exits_2(tmp_path, capsys, polygon_json, message):
    flow = _small_flow(tmp_path)
    (tmp_path / "m.json").write_text(polygon_json)
    rc = main(["vflow", "--flow", str(flow), "--mask", str(tmp_path / "m.json"), "--out", str(tmp_path / "o"),
               "--no-progress"])
    assert rc == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_vflow_flow_without_valid_pixels_exits_2(tmp_path, capsys):
    from fsof_torch.io import write_flow

    write_flow(tmp_path / "nan.npy", torch.full((2, 32, 48), float("nan")))
    rc = main(["vflow", "--flow", str(tmp_path / "nan.npy"), "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "error: --flow: " in err and "has no valid flow pixel" in err


def test_vflow_failed_fit_exits_1(tmp_path, capsys):
    flow = _small_flow(tmp_path, rows=[30])  # one row: too few for the curve
    rc = main(["vflow", "--flow", str(flow), "--out", str(tmp_path / "o"), "--no-progress"])
    data = json.loads((tmp_path / "o" / "vflow.json").read_text())
    assert rc == 1 and data["curve"]["success"] is False
    assert (tmp_path / "o" / "vflow_map.png").is_file()
    assert "could not be fitted" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--inlier-threshold", "inf"], "--inlier-threshold: expected a finite number >= 0, got inf"),
    (["--inlier-threshold", "nan"], "--inlier-threshold: expected a finite number >= 0, got nan"),
    (["--relative-threshold", "inf"], "--relative-threshold: expected a finite number >= 0, got inf"),
    (["--preset", "cvc-simple", "--index", "-1"], "--index: expected a pair index >= 0, got -1"),
])
def test_vflow_bad_numbers_exit_2(tmp_path, capsys, argv, message):
    rc = main(["vflow", *argv, "--out", str(tmp_path / "o"), "--no-progress"])
    assert rc == 2 and f"error: {message}" in capsys.readouterr().err


def test_vflow_output_paths_checked_before_the_work(tmp_path, capsys):
    flow = _small_flow(tmp_path)
    (tmp_path / "afile").write_text("")
    for argv, message in ((["--json", str(tmp_path / "afile" / "v.json")], "--json: "),
                          (["--json", str(tmp_path)], "--json: "),
                          (["--out", str(tmp_path / "afile")], "--out: ")):
        out = ["--out", str(tmp_path / "o")] if argv[0] == "--json" else []
        rc = main(["vflow", "--flow", str(flow), *out, *argv, "--no-progress"])
        err = capsys.readouterr().err
        assert rc == 2 and f"error: {message}" in err, err
        assert not (tmp_path / "o").exists()
    (tmp_path / "o" / "vflow_map.png").mkdir(parents=True)
    rc = main(["vflow", "--flow", str(flow), "--out", str(tmp_path / "o"), "--no-progress"])
    assert rc == 2 and "vflow_map.png' is a folder" in capsys.readouterr().err
    # a --json in a folder not made yet: created
    rc = main(["vflow", "--flow", str(flow), "--out", str(tmp_path / "o2"), "--json", str(tmp_path / "new" / "v.json"),
               "--no-progress"])
    assert rc == 0 and (tmp_path / "new" / "v.json").is_file()


def test_vflow_figure_that_fails_to_save_leaves_no_file(tmp_path, monkeypatch):
    """A figure is written atomically: a write that fails part way leaves neither half a PNG
    nor a temporary file behind."""
    import matplotlib.figure

    from eval.vflow import _plot_image

    def half_then_fail(self, fname, *args, **kwargs):
        with open(fname, "wb") as f:
            f.write(b"\x89PNG half")
        raise OSError("disk full")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", half_then_fail)
    with pytest.raises(OSError, match="disk full"):
        _plot_image(torch.zeros(4, 6), torch.ones(4, 6, dtype=torch.bool), tmp_path / "fv.png", "t", "viridis")
    assert list(tmp_path.iterdir()) == []
