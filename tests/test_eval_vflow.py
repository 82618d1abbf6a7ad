"""Smoke tests of ``python -m eval vflow`` (in-process, tiny renders)."""

from __future__ import annotations

import json

import pytest
import torch

from eval.__main__ import main


def test_vflow_preset(tmp_path, capsys, check_environment):
    out = tmp_path / "v"
    rc = main(["vflow", "--preset", "cvc-complex", "--size", "64", "208", "--out", str(out), "--no-progress"])
    assert rc == 0
    data = json.loads((out / "vflow.json").read_text())
    assert {"source", "curve", "freespace", "files"} <= set(data)
    check_environment(data["environment"], job="eval", command="python -m eval vflow", seed=0)
    assert data["curve"]["success"] and abs(data["curve"]["z_d_m"] - data["curve"]["z_d_m_true"]) < 0.05
    assert data["freespace"]["iou"] >= 0.9  # (0.966 measured)
    assert data["freespace"]["success"] and abs(data["freespace"]["z_d_m"] - data["curve"]["z_d_m_true"]) < 0.01
    for name in ("vflow_map.png", "fv_observed.png", "fv_fitted.png", "fv_error.png", "freespace.png"):
        assert (out / name).stat().st_size > 1000
    assert "V-flow curve" in capsys.readouterr().out


def test_vflow_freespace_of_cvc_simple(tmp_path, capsys):
    """cvc-simple's pavements cover more of the upper rows than the road: the freespace's road
    model is the road's (z_d 0.5 m), not the pavements' (0.543), and the json says whether the
    detection succeeded (an empty freespace is a failure)."""
    out = tmp_path / "v"
    rc = main(["vflow", "--preset", "cvc-simple", "--size", "128", "416", "--out", str(out), "--no-progress"])
    assert rc == 0
    found = json.loads((out / "vflow.json").read_text())["freespace"]
    assert found["success"] and found["pixels"] > 0 and found["iou"] >= 0.7
    assert found["z_d_m"] == pytest.approx(0.5, abs=0.005)
    assert "freespace IoU with the road" in capsys.readouterr().out


def test_vflow_velocity(tmp_path):
    out = tmp_path / "v"
    rc = main(["vflow", "--preset", "carla-straight", "--model", "velocity", "--size", "64", "208",
               "--out", str(out), "--json", str(tmp_path / "v.json"), "--no-progress"])
    assert rc == 0
    data = json.loads((tmp_path / "v.json").read_text())
    assert "freespace" not in data
    curve = data["curve"]
    assert curve["success"] and curve["speed_mps_true"] == data["source"]["velocity"]["speed"] == 10.0
    assert abs(curve["speed_mps"] - 10.0) < 0.5  # 9.876 measured
    assert abs(curve["v0"] - curve["horizon_row_true"]) < 0.5  # 0.14 px measured


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


def test_vflow_rows_too_sparse_to_fit_are_not_counted_as_used(tmp_path):
    """Rows with fewer mask pixels than the fit uses (3) are neither used nor outliers: the
    exact curve's rows are all inliers of the used ones (the sparse rows counted as used read
    as "inlier rows 24/32" on an exact flow)."""
    from fsof_torch.geometry.camera import Camera
    from fsof_torch.geometry.road_flow import displacement_flow
    from fsof_torch.io import write_flow

    cam = Camera(torch.tensor([[150.0, 0, 80], [0, 150.0, 15], [0, 0, 1]]), 1.5)
    flow, valid = displacement_flow(cam, 0.0, 1.0, 0.0, (48, 160))
    valid = valid[0].clone()
    valid[0, 40:, 2:] = False  # the last 8 rows keep 2 pixels each
    write_flow(tmp_path / "f.npy", flow[0], valid)
    out = tmp_path / "v"
    assert main(["vflow", "--flow", str(tmp_path / "f.npy"), "--out", str(out), "--no-progress"]) == 0
    curve = json.loads((out / "vflow.json").read_text())["curve"]
    counts = valid[0].sum(-1)
    assert int((counts >= 3).sum()) == 24 and int(((counts > 0) & (counts < 3)).sum()) == 8
    assert curve["used_rows"] == curve["inlier_rows"] == 24
    assert abs(curve["v0"] - 15.0) < 1e-3


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


def test_vflow_mask_that_is_a_folder_exits_2(tmp_path, capsys):
    """A folder as --mask ended in a traceback (IsADirectoryError), with exit status 1, the
    status of a curve that could not be fitted."""
    flow = _small_flow(tmp_path)
    (tmp_path / "masks").mkdir()
    rc = main(["vflow", "--flow", str(flow), "--mask", str(tmp_path / "masks"), "--out", str(tmp_path / "o"),
               "--no-progress"])
    assert rc == 2
    assert f"error: --mask: {str(tmp_path / 'masks')!r} is a folder" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_vflow_png_mask_of_another_size_exits_2(tmp_path, capsys):
    """A PNG mask must have the flow's size (was: stretched to it, like another pair's mask would
    be); a polygon JSON is drawn at the flow's size (test_vflow_polygon_drawn_for_another_size_exits_2)."""
    from fsof_torch.io import write_image

    flow = _small_flow(tmp_path)
    write_image(tmp_path / "m.png", torch.full((1, 16, 24), 255, dtype=torch.uint8))
    rc = main(["vflow", "--flow", str(flow), "--mask", str(tmp_path / "m.png"), "--out", str(tmp_path / "o"),
               "--no-progress"])
    assert rc == 2 and "error: --mask: " in (err := capsys.readouterr().err) and "m.png' is a 16x24 mask, but size is 32x48" in err
    assert not (tmp_path / "o").exists()
    write_image(tmp_path / "m.png", torch.full((1, 32, 48), 255, dtype=torch.uint8))
    assert main(["vflow", "--flow", str(flow), "--mask", str(tmp_path / "m.png"), "--out", str(tmp_path / "o"),
                 "--no-progress"]) == 0


def test_vflow_polygon_drawn_for_another_size_exits_2(tmp_path, capsys):
    """A polygon JSON whose 'size' is not the flow's was drawn for another image (KITTI frames are
    375x1242, 370x1226, 374x1238, ...) and was stretched over the flow (exit 0, the road shifted by
    up to 16 px at the right edge): exit 2 naming --mask and both sizes. Without a size it is
    drawn at the flow's size."""
    flow = _small_flow(tmp_path)
    polygon = '"road_polygon": [[0, 20], [47, 20], [47, 31], [0, 31]]'
    (tmp_path / "m.json").write_text('{"size": [30, 46], ' + polygon + '}')
    rc = main(["vflow", "--flow", str(flow), "--mask", str(tmp_path / "m.json"), "--out", str(tmp_path / "o"),
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and (f"error: --mask: {str(tmp_path / 'm.json')!r} is a polygon drawn for 30x46 images (its "
                        f"'size'), but size is 32x48") in err, err
    assert not (tmp_path / "o").exists()
    for own in ('{"size": [32, 48], ', "{"):
        (tmp_path / "m.json").write_text(own + polygon + '}')
        assert main(["vflow", "--flow", str(flow), "--mask", str(tmp_path / "m.json"), "--out", str(tmp_path / "o"),
                     "--no-progress"]) in (0, 1)
        assert json.loads((tmp_path / "o" / "vflow.json").read_text())["source"]["mask"] == str(tmp_path / "m.json")


def test_vflow_flow_without_valid_pixels_exits_2(tmp_path, capsys):
    from fsof_torch.io import write_flow

    write_flow(tmp_path / "nan.npy", torch.full((2, 32, 48), float("nan")))
    rc = main(["vflow", "--flow", str(tmp_path / "nan.npy"), "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "error: --flow: " in err and "has no valid flow pixel" in err


def test_vflow_noise_is_no_curve_and_says_why(tmp_path, capsys):
    """Noise gathers a few rows on some curve; the job reports its false alarms and exits 1."""
    from fsof_torch.io import write_flow

    noise = 2 * torch.rand(2, 96, 320, generator=torch.Generator().manual_seed(1)) - 1
    write_flow(tmp_path / "noise.npy", 5 * noise)
    rc = main(["vflow", "--flow", str(tmp_path / "noise.npy"), "--out", str(tmp_path / "o"), "--no-progress"])
    data = json.loads((tmp_path / "o" / "vflow.json").read_text())
    err = capsys.readouterr().err
    assert rc == 1 and data["curve"]["success"] is False and data["curve"]["nfa"] >= 1
    assert f"no more than chance gives ({data['curve']['nfa']:.2g} false alarms)" in err


def test_vflow_failed_fit_exits_1(tmp_path, capsys):
    flow = _small_flow(tmp_path, rows=[30])  # one row: too few for the curve
    rc = main(["vflow", "--flow", str(flow), "--out", str(tmp_path / "o"), "--no-progress"])
    data = json.loads((tmp_path / "o" / "vflow.json").read_text())
    assert rc == 1 and data["curve"]["success"] is False
    assert (tmp_path / "o" / "vflow_map.png").is_file()
    assert "could not be fitted" in capsys.readouterr().err


def test_vflow_failed_fit_is_not_reported_as_a_fit_of_zero(tmp_path, capsys, monkeypatch):
    """A failed fit has no curve (a = v0 = 0 by the library's contract). The job printed
    "z_d_m: fitted 0.0000 ...; horizon row: fitted 0.000" and "its road model's z_d 0.0000 m", and
    the map's legend named an "eq. 24 fit: a=0.000e+00" and its "inlier rows" (those of the curve
    the chance test rejected). It now says that nothing was fitted, and names those rows as the
    rejected curve's."""
    import matplotlib.pyplot as plt

    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # (kept open to look at)
    rc = main(["vflow", "--preset", "carla-turning", "--size", "16", "48", "--out", str(tmp_path), "--no-progress"])
    data = json.loads((tmp_path / "vflow.json").read_text())
    out = capsys.readouterr().out
    assert rc == 1 and data["curve"]["success"] is False and data["freespace"]["success"] is False
    assert data["curve"]["inlier_rows"] > 0  # (rows near the curve the chance test rejected)
    assert f"  z_d_m: not fitted, true 0.3000; horizon row: true {data['curve']['horizon_row_true']:.3f}\n" in out
    assert f"rows near the rejected curve {data['curve']['inlier_rows']}/{data['curve']['used_rows']}" in out
    assert "fitted 0.0" not in out and "z_d 0.0" not in out and "inlier rows" not in out
    assert "freespace IoU with the road: 0.0000, the detection failed: no freespace\n" in out
    try:
        labels = [t.get_text() for t in figures[0].axes[0].get_legend().get_texts()]
        assert labels == ["dominant F_v, other rows", "dominant F_v, rows near the rejected curve",
                          f"eq. 24 fit failed ({data['curve']['nfa']:.2g} false alarms): no curve"]
    finally:
        monkeypatch.undo()
        for fig in figures:
            plt.close(fig)


@pytest.mark.parametrize("argv, message", [
    (["--inlier-threshold", "inf"], "--inlier-threshold: expected a finite number >= 0, got inf"),
    (["--inlier-threshold", "nan"], "--inlier-threshold: expected a finite number >= 0, got nan"),
    (["--relative-threshold", "inf"], "--relative-threshold: expected a finite number >= 0, got inf"),
    (["--preset", "cvc-simple", "--index", "-1"], "--index: expected a pair index in [0, 10000], got -1"),
    # (the scene is laid out up to the pair asked for: 1e9 ran out of memory)
    (["--preset", "cvc-simple", "--index", "10001"], "--index: expected a pair index in [0, 10000], got 10001"),
    (["--index", "1000000000"], "--index: expected a pair index in [0, 10000], got 1000000000"),
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
        _plot_image(torch.zeros(4, 6), torch.ones(4, 6, dtype=torch.bool), tmp_path / "fv.png", "t", "viridis",
                    0.0, 1.0, "F_v (px)")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, message", [
    (["--road-only"], "--road-only: applies to a rendered --preset, not to --flow"),
    (["--index", "0"], "--index: applies to a rendered --preset, not to --flow"),  # (its default, given)
    (["--index", "3"], "--index: applies to a rendered --preset, not to --flow"),
    (["--seed", "0"], "--seed: applies to a rendered --preset, not to --flow"),
    (["--size", "32", "48"], "--size: applies to a rendered --preset, not to --flow"),
])
def test_vflow_preset_options_with_flow_exit_2(tmp_path, capsys, argv, message):
    """An option of the rendered scene given with --flow is refused, not silently ignored."""
    flow = _small_flow(tmp_path)
    rc = main(["vflow", "--flow", str(flow), *argv, "--out", str(tmp_path / "o"), "--no-progress"])
    assert rc == 2 and f"error: {message}" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("preset", [["--preset", "cvc-simple"], []])
def test_vflow_mask_with_a_preset_exits_2(tmp_path, capsys, monkeypatch, preset):
    """--mask with a rendered preset (given or the default one) is refused before rendering: the
    preset's own road mask would be used."""
    import fsof_torch.data.scene as scene

    monkeypatch.setattr(scene, "render_pair", lambda *a, **k: pytest.fail("rendered before --mask was refused"))
    (tmp_path / "m.json").write_text('{"size": [32, 48], "road_polygon": [[0, 20], [47, 20], [47, 31]]}')
    rc = main(["vflow", *preset, "--mask", str(tmp_path / "m.json"), "--out", str(tmp_path / "o"), "--no-progress"])
    assert rc == 2 and "error: --mask: applies to --flow" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_vflow_observed_map_shows_negative_flow(tmp_path, monkeypatch):
    """fv_observed.png's colours cover every observed F_v, the negative values above the horizon
    too (a range from 0 drew them as 0); the fitted map shares the scale, and a colour bar has an
    arrow at an end where its values are clipped; units in the labels."""
    import eval.vflow as vflow

    calls = {}
    plot = vflow._plot_image

    def record(img, valid, path, title, cmap, vmin, vmax, label):
        calls[path.name] = (img[valid], vmin, vmax, label, vflow._extend(img[valid], vmin, vmax))
        plot(img, valid, path, title, cmap, vmin, vmax, label)

    monkeypatch.setattr(vflow, "_plot_image", record)
    assert main(["vflow", "--preset", "cvc-complex", "--size", "64", "200", "--out", str(tmp_path), "--no-progress"]) == 0
    shown, vmin, vmax, label, extend = calls["fv_observed.png"]
    assert float(shown.min()) < -1.0  # the pixels above the horizon (-1.4 px at this size)
    assert vmin <= float(shown.min()) and float(shown.max()) <= vmax and extend == "neither"
    assert vmin == -vmax and label.startswith("F_v (px")
    assert calls["fv_fitted.png"][1:3] == (vmin, vmax)
    error, _, error_max, error_label, error_extend = calls["fv_error.png"]
    assert float(error.max()) > error_max and error_extend == "max" and error_label == "|F_v error| (px)"
    assert vflow._extend(torch.tensor([-2.0, 0.5]), -1.0, 1.0) == "min"
    assert vflow._extend(torch.tensor([-2.0, 3.0]), -1.0, 1.0) == "both"


@pytest.mark.parametrize("size", [(375, 1242), (370, 1226), (188, 621)])
def test_vflow_map_figures_draw_sparse_flow_no_larger_than_their_panel(tmp_path, monkeypatch, size):
    """An F_v map larger than its panel was shrunk by matplotlib's nearest-neighbour drawing, which
    drops whole rows and columns: of a KITTI-sized map of sparse flow, one row in 12 valid (laser
    lines), 22 of 31 lines were drawn. The picture is now reduced to fit its panel, each drawn
    pixel the mean of the valid pixels it covers (no value where none is)."""
    import matplotlib.pyplot as plt
    import numpy as np

    import eval.vflow as vflow

    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # (kept open to look at)
    H, W = size
    img = torch.arange(H * W, dtype=torch.float64).reshape(H, W) / (H * W)
    valid = torch.zeros(H, W, dtype=torch.bool)
    valid[6::12] = True
    vflow._plot_image(img, valid, tmp_path / "map.png", "t", "inferno", 0.0, 1.0, "F_v (px)")
    fig = figures[0]
    try:
        ax = next(a for a in fig.axes if a.get_images())
        picture = ax.get_images()[0]
        shown = np.ma.filled(picture.get_array().astype(np.float64), np.nan)
        fig.canvas.draw()
        box = picture.get_window_extent()
        assert shown.shape[0] <= box.height and shown.shape[1] <= box.width
        k = -(-H // shown.shape[0])  # the reduction
        assert shown.shape == (-(-H // k), -(-W // k))
        rows = sorted({r // k for r in range(6, H, 12)})
        has = ~np.isnan(shown)
        assert has[rows].all() and not np.delete(has, rows, axis=0).any()  # every line, and nothing else
        r = rows[1]
        block = img[r * k:(r + 1) * k, :k]
        assert shown[r, 0] == pytest.approx(float(block[valid[r * k:(r + 1) * k, :k]].mean()), rel=1e-12)
    finally:
        monkeypatch.undo()
        plt.close(fig)


@pytest.mark.parametrize("size", [(373, 1241), (375, 1242), (1201, 601)])
def test_vflow_map_figures_place_each_reduced_pixel_over_the_pixels_it_averages(tmp_path, monkeypatch, size):
    """An F_v map drawn reduced by f was stretched over the full image, its ceil(W / f) drawn
    columns over W pixels: drawn column j stood at j W / ceil(W / f) instead of j f, so a map of
    373 x 1241 px (reduced by 2) drew an edge at column 1232 at 1231.0. Drawn pixel j now covers
    the pixels j f .. j f + f - 1 it is the mean of, on axes of the image's pixels."""
    import matplotlib.pyplot as plt

    import eval.vflow as vflow

    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # (kept open to look at)
    H, W = size
    img = torch.zeros(H, W, dtype=torch.float64)
    col, row = W - 5 - (W - 5) % 4, H - 5 - (H - 5) % 4  # edges near the far sides, on block boundaries
    img[:, col:] += 1.0
    img[row:, :] += 2.0
    vflow._plot_image(img, torch.ones(H, W, dtype=torch.bool), tmp_path / "map.png", "t", "inferno", 0.0, 3.0, "F_v (px)")
    fig = figures[0]
    try:
        ax = next(a for a in fig.axes if a.get_images())
        picture = ax.get_images()[0]
        shown = picture.get_array()
        h, w = shown.shape
        f = -(-W // w)
        assert f > 1 and (h, w) == (-(-H // f), -(-W // f))
        left, right, bottom, top = picture.get_extent()
        assert (left, right, bottom, top) == (-0.5, w * f - 0.5, h * f - 0.5, -0.5)
        first_col = next(j for j in range(w) if shown[0, j] != shown[0, 0])
        first_row = next(i for i in range(h) if shown[i, 0] != shown[0, 0])
        assert left + first_col * (right - left) / w == col - 0.5  # drawn where it is in the image
        assert top + first_row * (bottom - top) / h == row - 0.5
        assert tuple(ax.get_xlim()) == (-0.5, W - 0.5) and tuple(ax.get_ylim()) == (H - 0.5, -0.5)
    finally:
        monkeypatch.undo()
        plt.close(fig)


@pytest.mark.parametrize("rows, bins", [(100, 4096), (1200, 256), (375, 1024)])
def test_vflow_map_figure_draws_every_row_and_bin(tmp_path, monkeypatch, rows, bins):
    """A V-flow map of more rows or bins than its panel has pixels was shrunk by matplotlib's
    nearest-neighbour drawing, which drops whole rows and columns: of a map with one count per
    row, 12 of 100 rows' counts were drawn at 4096 bins, 410 of 1200 at 256 bins. It is now drawn
    reduced, each drawn pixel the largest count it covers, placed over the rows and bins it covers."""
    import matplotlib.pyplot as plt
    import numpy as np

    import eval.vflow as vflow
    from fsof_torch import fit_vflow_curve, vflow_map

    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # (kept open to look at)
    col = (torch.arange(rows) * 37) % bins  # each row's one bin
    flow = torch.zeros(1, 2, rows, 3, dtype=torch.float64)
    flow[0, 1] = (10.0 * (col + 0.5) / bins).reshape(rows, 1)
    hist, edges = vflow_map(flow, bins=bins, min_flow=0.0, max_flow=10.0)
    assert torch.equal(hist[0].argmax(-1), col)
    curve = fit_vflow_curve(flow, bins=bins)
    vflow._plot_map(hist[0], edges, curve, tmp_path / "map.png", "px")
    fig = figures[0]
    try:
        ax = fig.axes[0]
        picture = ax.get_images()[0]
        shown = np.asarray(picture.get_array())
        box = ax.get_window_extent()
        assert shown.shape[0] <= box.height and shown.shape[1] <= box.width
        fr, fc = -(-rows // shown.shape[0]), -(-bins // shown.shape[1])
        assert fr * fc > 1 and shown.shape == (-(-rows // fr), -(-bins // fc))
        counts = hist[0].numpy()
        for i, j in [(0, 0), (shown.shape[0] // 2, shown.shape[1] // 3), (shown.shape[0] - 1, shown.shape[1] - 1)]:
            assert shown[i, j] == np.log1p(counts[i * fr:(i + 1) * fr, j * fc:(j + 1) * fc].max())
        left, right, bottom, top = picture.get_extent()
        assert (left, top, bottom) == (0.0, -0.5, shown.shape[0] * fr - 0.5)
        assert right == pytest.approx(shown.shape[1] * fc * 10.0 / bins, rel=1e-12)
        assert tuple(ax.get_xlim()) == (0.0, 10.0) and tuple(ax.get_ylim()) == (rows - 0.5, -0.5)
        # every row's count is drawn where it is: lit at its bin's centre
        ax.get_legend().remove()
        for points in ax.collections:
            points.remove()
        fig.canvas.draw()
        rgb = np.asarray(fig.canvas.buffer_rgba())[:, :, :3].astype(int)
        x, y = ax.transData.transform(np.stack([(col.numpy() + 0.5) * 10.0 / bins, np.arange(rows)], 1)).T
        x, y = x.astype(int), (rgb.shape[0] - y).astype(int)
        lit = [(rgb[b - 1:b + 2, a - 1:a + 2].sum(-1) > 60).any() for a, b in zip(x, y)]
        # (matplotlib 3.10, the newest for Python 3.10, places a drawn pixel or two of hundreds a
        # little off the data's pixel grid; without the reduction 12 to 41 % of the rows were lit)
        assert np.mean(lit) >= 0.98 and (all(lit) or _older_matplotlib())
    finally:
        monkeypatch.undo()
        plt.close(fig)


def _older_matplotlib() -> bool:
    """matplotlib older than 3.11 (3.10 is the newest for Python 3.10): it places some drawn pixels
    a pixel off the data's grid."""
    import matplotlib

    return tuple(int(p) for p in matplotlib.__version__.split(".")[:2]) < (3, 11)


def test_vflow_freespace_figure_draws_every_strip_of_a_class(tmp_path, monkeypatch):
    """The freespace figure of a 375 x 1242 frame, larger than its panel, was shrunk by dropping
    whole rows and columns: of strips of freespace off the road one pixel wide, 92 of 138 were
    drawn, of road missed 63 of 95. It is now drawn reduced, each drawn pixel tinted by the class
    of any pixel it covers (a miss over a find), placed over the pixels it covers."""
    import matplotlib.pyplot as plt
    import numpy as np

    import eval.vflow as vflow

    figures = []
    monkeypatch.setattr(plt, "close", figures.append)  # (kept open to look at)
    H, W = 375, 1242
    road = torch.zeros(1, H, W, dtype=torch.bool)
    road[0, 200:] = True
    free = road.clone()
    off, missed = list(range(3, W - 3, 9)), list(range(5, W - 5, 13))
    free[0, 250:300, off] = True
    road[0, 250:300, off] = False
    free[0, 320:, missed] = False
    vflow._plot_freespace(torch.full((3, H, W), 128.0), free, road, tmp_path / "free.png", 0.9)
    fig = figures[0]
    try:
        ax = fig.axes[0]
        picture = ax.get_images()[0]
        shown = picture.get_array()
        box = ax.get_window_extent()
        f = -(-W // shown.shape[1])
        assert f > 1 and shown.shape[:2] == (-(-H // f), -(-W // f)) and shown.shape[1] <= box.width
        assert picture.get_extent() == [-0.5, shown.shape[1] * f - 0.5, shown.shape[0] * f - 0.5, -0.5]
        assert tuple(ax.get_xlim()) == (-0.5, W - 0.5) and tuple(ax.get_ylim()) == (H - 0.5, -0.5)
        grey = 128 / 255
        magenta, red, green = (0.5 * grey + 0.5 * np.array(c) for c in ((1, 0, 1), (1, 0, 0), (0, 1, 0)))
        np.testing.assert_allclose(shown[275 // f, [c // f for c in off]], np.broadcast_to(magenta, (len(off), 3)))
        np.testing.assert_allclose(shown[340 // f, [c // f for c in missed]], np.broadcast_to(red, (len(missed), 3)))
        np.testing.assert_allclose(shown[340 // f, 9 // f], green)  # (a block of freespace on the road only)
        np.testing.assert_allclose(shown[100 // f, 100 // f], [grey] * 3)
        # and as written: every strip drawn in its colour, at the middle of its block
        fig.canvas.draw()
        rgb = np.asarray(fig.canvas.buffer_rgba())[:, :, :3].astype(int)
        for columns, row, colour in ((off, 275, magenta), (missed, 340, red)):
            middle = [c // f * f + (f - 1) / 2 for c in columns]
            x, y = ax.transData.transform(np.column_stack([middle, [row // f * f + (f - 1) / 2] * len(columns)])).T
            drawn = rgb[(rgb.shape[0] - y).astype(int), x.astype(int)]
            # (matplotlib 3.10, the newest for Python 3.10, places some blocks a pixel off the data's
            # grid, so there the drawn array above is what is checked)
            assert (np.abs(drawn - 255 * colour).max(-1) <= 2).all() or _older_matplotlib()
    finally:
        monkeypatch.undo()
        plt.close(fig)


def test_vflow_road_figure_needs_a_road(tmp_path, capsys):
    """--flow without --mask has no road: the road figure is null in the JSON and not printed as
    "on the road" (it was the figure over every valid pixel); the figure over the fit's pixels is
    printed as such. With --mask (the road) both figures are the mask's."""
    flow = _small_flow(tmp_path)
    assert main(["vflow", "--flow", str(flow), "--out", str(tmp_path / "o"), "--no-progress"]) == 0
    curve = json.loads((tmp_path / "o" / "vflow.json").read_text())["curve"]
    assert curve["mean_abs_fv_error_road"] is None and curve["mean_abs_fv_error_mask"] is not None
    out = capsys.readouterr().out
    assert "on the road" not in out
    assert "mean |F_v - fitted| over the flow's valid pixels where the curve is defined (no road mask): " in out
    (tmp_path / "m.json").write_text('{"size": [32, 48], "road_polygon": [[0, 10], [47, 10], [47, 31], [0, 31]]}')
    assert main(["vflow", "--flow", str(flow), "--mask", str(tmp_path / "m.json"), "--out", str(tmp_path / "m"),
                 "--no-progress"]) == 0
    curve = json.loads((tmp_path / "m" / "vflow.json").read_text())["curve"]
    assert curve["mean_abs_fv_error_road"] == curve["mean_abs_fv_error_mask"] is not None
    assert "on the road" in capsys.readouterr().out


@pytest.mark.parametrize("argv, name", [
    (["--flow", "{flow}"], "fv_error.png"),
    (["--preset", "cvc-simple", "--size", "32", "96"], "freespace.png"),
    (["--preset", "cvc-simple", "--size", "32", "96"], "vflow_map.png"),
])
def test_vflow_json_naming_an_output_exits_2(tmp_path, capsys, argv, name):
    """A --json naming a figure the job writes is refused (the JSON, written last, replaced it)."""
    flow = _small_flow(tmp_path)
    argv = [a.format(flow=flow) for a in argv]
    target = tmp_path / "o" / ".." / "o" / name
    rc = main(["vflow", *argv, "--out", str(tmp_path / "o"), "--json", str(target), "--no-progress"])
    assert rc == 2
    assert f"error: --json: {str(target)!r} names {name}, a file the job writes into " in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_vflow_json_naming_its_input_exits_2(tmp_path, capsys):
    """A --json naming the input --flow is refused, and the flow file is left as it was."""
    flow = _small_flow(tmp_path)
    before = flow.read_bytes()
    rc = main(["vflow", "--flow", str(flow), "--out", str(tmp_path / "o"), "--json", str(flow), "--no-progress"])
    assert rc == 2
    assert f"error: --json: {str(flow)!r} is the input --flow; give another path" in capsys.readouterr().err
    assert flow.read_bytes() == before and not (tmp_path / "o").exists()


@pytest.mark.parametrize("option, name", [("--flow", "fv_error.png"), ("--mask", "freespace.png")])
def test_vflow_out_holding_its_input_as_an_output_exits_2(tmp_path, capsys, option, name):
    """An --out that holds --flow or --mask under the name of a file the job writes (or removes
    there as an earlier run's) is refused, and the input kept: the flow was deleted and replaced
    by a figure."""
    from fsof_torch.io import read_flow, write_flow, write_road_mask

    flow = _small_flow(tmp_path)
    out = tmp_path / "o"
    out.mkdir()
    given = out / name
    if option == "--flow":
        write_flow(given, *read_flow(flow))  # a KITTI flow PNG
        argv = ["--flow", str(given)]
    else:
        write_road_mask(given, read_flow(flow)[1])
        argv = ["--flow", str(flow), "--mask", str(given)]
    before = given.read_bytes()
    rc = main(["vflow", *argv, "--out", str(out), "--no-progress"])
    assert rc == 2
    assert (f"error: --out: {str(out)!r} holds the input {option} {str(given)!r} as {name}, a file the job removes "
            f"and writes there; give another --out") in capsys.readouterr().err
    assert given.read_bytes() == before and sorted(p.name for p in out.iterdir()) == [name]


def test_vflow_json_may_name_a_figure_the_run_does_not_write(tmp_path):
    """freespace.png is written for a preset's displacement flow only: with --flow the name is free."""
    flow = _small_flow(tmp_path)
    rc = main(["vflow", "--flow", str(flow), "--out", str(tmp_path / "o"), "--json",
               str(tmp_path / "o" / "freespace.png"), "--no-progress"])
    assert rc == 0 and "curve" in json.loads((tmp_path / "o" / "freespace.png").read_text())


@pytest.mark.parametrize("argv, message", [
    (["--bins", "65537"], "--bins: expected 2 to 65536, got 65537"),
    (["--bins", "1000000000000"], "--bins: expected 2 to 65536, got 1000000000000"),
    (["--bins", "1"], "--bins: expected 2 to 65536, got 1"),
    (["--size", "16385", "64"], "--size: expected H, W <= 16384, got [16385, 64]"),
    (["--size", "64", "10000000"], "--size: expected H, W <= 16384, got [64, 10000000]"),
])
def test_vflow_bins_and_size_bounded(tmp_path, capsys, monkeypatch, argv, message):
    """--bins and --size have maxima: a huge value exits 2 naming it, before any work (it raised
    a MemoryError or RuntimeError traceback)."""
    import fsof_torch.data.scene as scene

    monkeypatch.setattr(scene, "render_pair", lambda *a, **k: pytest.fail("rendered before the check"))
    rc = main(["vflow", *argv, "--out", str(tmp_path / "o"), "--no-progress"])
    assert rc == 2 and f"error: {message}" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_vflow_bins_at_the_maximum(tmp_path):
    flow = _small_flow(tmp_path)
    rc = main(["vflow", "--flow", str(flow), "--bins", "65536", "--out", str(tmp_path / "o"), "--no-progress"])
    assert rc == 0 and json.loads((tmp_path / "o" / "vflow.json").read_text())["curve"]["success"]


def test_vflow_input_errors_print_before_the_progress_bar(tmp_path, capsys):
    """The input checks come before the progress bar opens: an error line is never printed inside
    the bar's line."""
    flow = _small_flow(tmp_path)
    (tmp_path / "m.json").write_text('{"size": [32, 48], "road_polygon": [[-9, -9], [-5, -9], [-5, -5]]}')
    for argv in (["--flow", str(flow), "--mask", str(tmp_path / "m.json")],  # empty mask
                 ["--flow", str(tmp_path / "missing.flo")], ["--flow", str(tmp_path / "m.json")],
                 ["--preset", "nope"]):
        rc = main(["vflow", *argv, "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith("error: ") and "vflow:" not in err, err


def test_vflow_flow_and_mask_errors_quote_the_file_without_the_readers_argument(tmp_path, capsys):
    """A reader's own argument ("path: ...") inside the message means nothing to the user: the
    message reads "--flow: '<file>' ...", as the refine job's do."""
    (tmp_path / "bad.flo").write_bytes(b"12345")
    assert main(["vflow", "--flow", str(tmp_path / "bad.flo"), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --flow: {str(tmp_path / 'bad.flo')!r} "), err
    flow = _small_flow(tmp_path)
    (tmp_path / "bad.png").write_bytes(b"not a png")
    assert main(["vflow", "--flow", str(flow), "--mask", str(tmp_path / "bad.png"), "--out", str(tmp_path / "o"),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --mask: {str(tmp_path / 'bad.png')!r} "), err


def test_vflow_rerun_leaves_no_file_of_the_run_before(tmp_path):
    """A rerun into the same folder removes the earlier run's files that it does not write again:
    freespace.png (a velocity run draws none), DIR/vflow.json (its JSON written elsewhere)."""
    out = tmp_path / "o"
    base = ["vflow", "--preset", "cvc-complex", "--size", "48", "160", "--out", str(out), "--no-progress"]
    main(base)
    assert {"freespace.png", "vflow.json"} <= {p.name for p in out.iterdir()}
    main([*base, "--model", "velocity", "--json", str(tmp_path / "v.json")])
    assert sorted(p.name for p in out.iterdir()) == ["fv_error.png", "fv_fitted.png", "fv_observed.png",
                                                    "vflow_map.png"]
    assert json.loads((tmp_path / "v.json").read_text())["curve"]["model"] == "velocity"


def test_vflow_bar_in_a_log_is_rate_limited(tmp_path, capsys):
    """With stderr not a terminal (a log, CI), the bar is drawn when it opens and closes within
    fsof_torch.io.progress.LOG_INTERVAL, not at every step."""
    assert main(["vflow", "--flow", str(_small_flow(tmp_path)), "--out", str(tmp_path / "o")]) == 0
    err = capsys.readouterr().err
    assert "vflow" in err and err.count("\r") <= 3, err


def test_vflow_a_run_that_stops_leaves_no_earlier_json(tmp_path, interrupted):
    """An earlier run's --json (elsewhere than --out) goes once the inputs are checked, as
    DIR/vflow.json does: a run stopped during the curve fit left it to be read as its own."""
    import fsof_torch

    path = tmp_path / "v.json"
    path.write_text('{"curve": "an earlier run"}')

    flow = _small_flow(tmp_path)
    interrupted(fsof_torch, "fit_vflow_curve", lambda: main(["vflow", "--flow", str(flow), "--out", str(tmp_path / "o"),
                                                           "--json", str(path), "--no-progress"]))
    assert not path.exists()


def test_vflow_error_colour_range_of_a_large_flow():
    """The error map's colour bar tops at max(1, 95th percentile): torch.quantile refused more than
    2**24 values (a 6000x4000 flow ended in a traceback, without vflow.json); the same value as
    torch's for fewer."""
    from eval.vflow import error_vmax

    small = torch.linspace(0.0, 4.0, 1001, dtype=torch.float64)
    assert error_vmax(small) == pytest.approx(float(small.quantile(0.95)), rel=1e-12)
    assert error_vmax(small / 100) == 1.0 and error_vmax(small[:0]) == 1.0
    large = torch.zeros(2**24 + 1)
    large[-(2**20):] = 3.0  # the top 6.25 %: the 95th percentile is 3
    assert error_vmax(large) == 3.0


@pytest.mark.parametrize("reverse", [False, True])
def test_vflow_figures_have_legends_that_hide_no_curve(tmp_path, monkeypatch, reverse):
    """freespace.png tells freespace on the road, road missed and freespace off the road apart in
    a legend (green alone drew freespace off the road as road found); the map's legend gives the
    fit's units and covers none of the curve, which runs into the lower right corner of a forward
    motion's map (lower left reversing), where the legend was."""
    import matplotlib.figure
    import numpy as np

    import eval.vflow as vflow

    figures = {}
    save = matplotlib.figure.Figure.savefig

    def record(fig, path, *args, **kwargs):
        figures[len(figures)] = fig
        return save(fig, path, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", record)
    if not reverse:
        assert main(["vflow", "--preset", "cvc-complex", "--size", "64", "200", "--out", str(tmp_path),
                     "--no-progress"]) == 0
        labels = [t.get_text() for t in figures[4].axes[0].get_legend().get_texts()]
        assert [label.split(" (")[0] for label in labels] == [
            "freespace on the road", "road missed", "freespace off the road"]
    else:
        from fsof_torch import Camera, displacement_flow

        cam = Camera(torch.tensor([[150.0, 0, 100], [0, 150, 10], [0, 0, 1]], dtype=torch.float64), 1.5)
        flow, valid = displacement_flow(cam, 0.0, -1.5, 0.0, (64, 200))
        path = tmp_path / "reverse.npy"
        np.save(path, torch.where(valid, flow, torch.nan)[0].permute(1, 2, 0).numpy())
        assert main(["vflow", "--flow", str(path), "--out", str(tmp_path / "o"), "--no-progress"]) == 0
    fig = figures[0]
    ax = fig.axes[0]
    fig.canvas.draw()
    legend = ax.get_legend()
    assert any("1/px" in t.get_text() and "v0=" in t.get_text() and t.get_text().endswith(" px")
               for t in legend.get_texts())
    box = legend.get_window_extent()
    curve = [line for line in ax.get_lines() if line.get_label().startswith("eq. 24 fit")][0]
    points = ax.transData.transform(np.column_stack(curve.get_data()))
    assert len(points) > 10
    inside = (points[:, 0] >= box.x0) & (points[:, 0] <= box.x1) & (points[:, 1] >= box.y0) & (points[:, 1] <= box.y1)
    assert not inside.any()


@pytest.mark.parametrize("cmap", ["RdBu_r", "inferno"])
def test_vflow_maps_draw_no_value_grey_not_as_a_value(tmp_path, cmap):
    """fv_observed / fv_fitted / fv_error left pixels outside the mask transparent: the figure's
    white, which on the diverging F_v map is the colour of F_v = 0 (a road mask's surroundings,
    the rows above the fitted horizon read as zero flow). They are mid grey (NO_VALUE_RGB, as in
    the job's pair figures), a colour neither map holds, and the colour bar names it."""
    import numpy as np
    from PIL import Image

    from eval.vflow import _plot_image
    from fsof_torch.evaluation.visualize import NO_VALUE_RGB

    img = torch.zeros(40, 60)  # every value 0: RdBu_r's near-white
    valid = torch.zeros(40, 60, dtype=torch.bool)
    valid[:, 30:] = True
    _plot_image(img, valid, tmp_path / "fv.png", "t", cmap, -1.0, 1.0, "F_v (px)")
    rgb = np.asarray(Image.open(tmp_path / "fv.png").convert("RGB")).reshape(-1, 3).astype(int)
    colours, counts = np.unique(rgb, axis=0, return_counts=True)
    # the two halves of the picture: the masked one grey, the other the map's colour of 0
    top = {tuple(c) for c in colours[np.argsort(counts)[::-1][:3]]}
    assert tuple(NO_VALUE_RGB) in top
    import matplotlib

    zero = tuple(int(round(255 * x)) for x in matplotlib.colormaps[cmap](0.5)[:3])
    assert any(max(abs(a - b) for a, b in zip(c, zero)) <= 2 for c in top)


def test_vflow_interrupted_ends_the_bars_line_before_its_own(tmp_path, interrupted, capsys):
    """Ctrl-C during the curve fit: the job's line "interrupted" followed the bar on the bar's line,
    and the bar was drawn once more after it, as the last line of the log, when the process let go
    of the bar. Now the bar ends its line first and nothing follows the job's line."""
    import gc

    import fsof_torch

    flow = _small_flow(tmp_path)
    interrupted(fsof_torch, "fit_vflow_curve", lambda: main(["vflow", "--flow", str(flow), "--out", str(tmp_path / "o")]))
    gc.collect()
    err = capsys.readouterr().err
    bar, line, rest = err.partition("eval vflow: interrupted; the files written so far are kept, each one whole\n")
    assert line and rest == "", err
    assert bar.startswith("\rvflow:") and bar.endswith("/s]\n") and " 2/4 " in bar.rsplit("\r", 1)[1], err
