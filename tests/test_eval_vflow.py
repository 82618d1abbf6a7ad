"""Smoke tests of ``python -m eval vflow`` (in-process, tiny renders)."""

from __future__ import annotations

import json

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
