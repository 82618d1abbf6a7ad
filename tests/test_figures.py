"""fsof_torch.evaluation.figures: every figure the refine job writes has a title, a legend or a
colour bar, and axes where they apply (checked on the matplotlib objects), and draws the road
as an outline that leaves the pixels under it as they are."""

from __future__ import annotations

import math
import re

import pytest
import torch


from fsof_torch.evaluation.figures import (  # noqa: E402
    PairFigure,
    clip_summary_figure,
    colour_wheel,
    pair_figure,
    road_outline,
    save_figure,
)
from fsof_torch.evaluation.visualize import flow_to_color  # noqa: E402

H, W = 30, 90


def _pair():
    g = torch.Generator().manual_seed(0)
    flow = torch.randn(2, H, W, generator=g) * 3
    road = torch.zeros(1, H, W, dtype=torch.bool)
    road[0, 18:, 10:80] = True
    images = tuple(torch.rand(3, H, W, generator=g) * 255 for _ in range(2))
    err = torch.rand(1, H, W, generator=g) * 8
    valid = torch.ones(1, H, W, dtype=torch.bool)
    valid[0, :3] = False
    return flow, road, images, err, valid


def _image_axes(fig):
    return [ax for ax in fig.axes if ax.get_images() and ax.get_label() != "colour wheel"
            and not hasattr(ax, "_colorbar")]


@pytest.fixture
def figure():
    flow, road, images, err, valid = _pair()
    fig = pair_figure(images=images, flows={"before": flow, "after, odometry 'fit'": flow * 0.5},
                      errors={"before": (err, valid), "after, odometry 'fit'": (err * 0.1, valid)},
                      road=road, max_flow=6.0, error_vmax=5.0, error_label="end-point error (px)",
                      title="pair 000000: before and after")
    yield fig
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_pair_figure_parts(figure):
    assert figure.get_suptitle() == "pair 000000: before and after"
    panels = _image_axes(figure)
    assert len(panels) == 6  # images, before, after; flow row and error row
    for ax in panels:
        assert ax.get_title()
        assert len(ax.get_xticks()) >= 2 and len(ax.get_yticks()) >= 2
    assert {ax.get_xlabel() for ax in panels} == {"u (px)", ""}
    assert {ax.get_ylabel() for ax in panels} == {"v (px)", ""}
    titles = [ax.get_title() for ax in panels]
    assert "flow, before" in titles and "end-point error, after, odometry 'fit'" in titles
    # the colour-wheel legend of the flow images, with the saturation
    (wheel,) = [ax for ax in figure.axes if ax.get_label() == "colour wheel"]
    assert "6 px" in wheel.get_title() and wheel.get_xlabel() == "u (px)" and wheel.get_ylabel() == "v (px)"
    # the error maps' colour bar: the unit, the saturation value, the arrow past it
    errors = [ax.get_images()[0] for ax in panels if ax.get_title().startswith("end-point error")]
    bars = {id(im.colorbar) for im in errors if im.colorbar is not None}
    assert len(bars) == 1
    bar = next(im.colorbar for im in errors if im.colorbar is not None)
    assert "end-point error (px)" in bar.ax.get_ylabel() and "saturates at 5" in bar.ax.get_ylabel()
    assert bar.extend == "max" and all(im.get_clim() == (0.0, 5.0) for im in errors)
    # the legend names the road outline and the pixels without a value
    (legend,) = figure.legends
    texts = [t.get_text() for t in legend.get_texts()]
    assert "road mask (outline)" in texts and any("no value" in t for t in texts)


def test_road_is_an_outline_not_a_tint(figure):
    """The image panels show the image's own pixels (no colour blended in); the road is a line."""
    from matplotlib.collections import LineCollection

    flow, road, images, _, _ = _pair()
    panels = _image_axes(figure)
    first = panels[0]
    assert first.get_title() == "image 1 (time t)"
    shown = torch.from_numpy(first.get_images()[0].get_array().copy())
    assert torch.equal(shown, images[0].round().to(torch.uint8).permute(1, 2, 0))
    flow_panel = next(ax for ax in panels if ax.get_title() == "flow, before")
    colours = torch.from_numpy(flow_panel.get_images()[0].get_array().copy())
    assert torch.equal(colours, flow_to_color(flow, 6.0)[0].permute(1, 2, 0))
    for ax in panels:
        lines = [c for c in ax.collections if isinstance(c, LineCollection)]
        assert len(lines) == 2  # a black line under a white dashed one
        assert all(len(c.get_facecolor()) == 0 or c.get_facecolor()[0][3] == 0 for c in lines)


def test_road_outline_traces_the_mask():
    """An L-shaped mask: the outline follows the notch (a bounding box would not)."""
    import cv2
    import numpy as np

    road = torch.zeros(1, 10, 12, dtype=torch.bool)
    road[0, 4:8, 2:9] = True
    road[0, 4:6, 6:9] = False  # the notch: its concave corner is at (u, v) = (5..6, 5..6)
    (poly,) = road_outline(road)
    assert poly.shape[1] == 2 and (poly[0] == poly[-1]).all()
    assert poly[:, 0].min() == 2 and poly[:, 0].max() == 8 and poly[:, 1].min() == 4 and poly[:, 1].max() == 7
    assert {(5.0, 4.0), (5.0, 5.0), (6.0, 6.0), (8.0, 6.0)} <= {tuple(p) for p in poly.tolist()}
    # the polygon through the boundary pixels' centres, filled, is the mask again
    filled = np.zeros((10, 12), np.uint8)
    cv2.fillPoly(filled, [poly.astype(np.int32)], 1)
    assert np.array_equal(filled.astype(bool), road[0].numpy())


def test_road_outline_takes_one_bool_mask_of_any_accepted_shape():
    road = torch.zeros(10, 12, dtype=torch.bool)
    road[4:8, 2:9] = True
    (want,) = road_outline(road)
    for shaped in (road[None], road[None, None]):
        (got,) = road_outline(shaped)
        assert (got == want).all()


@pytest.mark.parametrize("mask, error, match", [
    (torch.full((1, 10, 12), 0.7), TypeError, r"mask: expected a bool tensor, got dtype torch.float32"),
    (torch.ones(1, 10, 12, dtype=torch.uint8), TypeError, r"mask: expected a bool tensor, got dtype torch.uint8"),
    ([[True]], TypeError, r"mask: expected a bool tensor, got list"),
    (torch.ones(2, 1, 10, 12, dtype=torch.bool), ValueError,
     r"mask: expected shape \(H, W\), \(1, H, W\) or \(1, 1, H, W\), got \(2, 1, 10, 12\)"),
    (torch.ones(3, 10, 12, dtype=torch.bool), ValueError, r"mask: expected shape .* got \(3, 10, 12\)"),
    (torch.ones(12, dtype=torch.bool), ValueError, r"mask: expected shape .* got \(12,\)"),
])
def test_road_outline_refuses_other_masks(mask, error, match):
    """A float mask gave no outline at all, silently; a batch of masks a reshape error."""
    with pytest.raises(error, match=match):
        road_outline(mask)


@pytest.mark.parametrize("vmax, error, match", [
    (float("nan"), ValueError, "error_vmax: expected a finite number, got nan"),
    (float("inf"), ValueError, "error_vmax: expected a finite number, got inf"),
    (0.0, ValueError, r"error_vmax: expected a positive number \(> 0\), got 0.0"),
    (-1.0, ValueError, r"error_vmax: expected a positive number \(> 0\), got -1.0"),
    ("5", TypeError, "error_vmax: expected a number, got str '5'"),
    (None, TypeError, "error_vmax: expected a number, got NoneType None"),
])
def test_error_vmax_is_a_finite_positive_number(vmax, error, match):
    """NaN drew a colour bar 'saturates at nan' over a made-up scale; 0 and -1 saturated every
    error map white. pair_figure, PairFigure.layout_of and PairFigure refuse them by name."""
    import matplotlib.pyplot as plt

    flow, road, _, err, valid = _pair()
    content = dict(flows={"before": flow}, errors={"before": (err, valid)}, road=road, error_label="epe (px)")
    open_before = plt.get_fignums()
    with pytest.raises(error, match=match):
        pair_figure(**content, max_flow=2.0, error_vmax=vmax, title="t")
    with pytest.raises(error, match=match):
        PairFigure.layout_of(**content, images=None, error_vmax=vmax)
    with pytest.raises(error, match=match):
        PairFigure((H, W), (True,), False, vmax, "epe (px)")
    assert plt.get_fignums() == open_before  # refused before a figure is opened


def test_colour_wheel_is_the_flow_coding():
    wheel = colour_wheel(4.0, size=21)
    assert wheel.shape == (21, 21, 3) and wheel.dtype == torch.uint8
    # bottom centre: flow (0, 4) px, full saturation downwards, yellow in Middlebury colours
    down = flow_to_color(torch.tensor([[[0.0]], [[4.0]]], dtype=torch.float64), 4.0)[0, :, 0, 0].tolist()
    assert wheel[20, 10].tolist() == down and down[0] == 255 and down[2] == 0
    assert wheel[0, 0].tolist() == [255, 255, 255]  # outside the disc
    # its size is checked by name (0 was an error naming 'flow', 2.5 a TypeError from linspace)
    with pytest.raises(ValueError, match="size: expected an int >= 1, got 0"):
        colour_wheel(4.0, size=0)
    with pytest.raises(TypeError, match="size: expected an int, got float 2.5"):
        colour_wheel(4.0, size=2.5)


def _records():
    recs = []
    for i in range(3):
        for v, shift in (("given", 0.0), ("fit", 0.01)):
            recs.append({"pair": f"{i:06d}", "source": "dis", "variant": v,
                         # each variant's before is measured on its own pixels: they differ
                         "before": {"epe_road": 2.0 + i, "census_road": 0.3 + 2 * shift},
                         "after": {"epe_road": 0.1 * i + shift, "census_road": 0.2 + shift},
                         "odometry": {"x_d": 0.0 + shift, "z_d": 1.2 - shift, "yaw": 0.01, "y_d": 0.002 * i},
                         "roll": 0.01, "pitch": -0.02, "odometry_given": {"x_d": 0.0, "z_d": 1.2, "yaw": 0.01}})
    return recs


def test_clip_summary_parts():
    import matplotlib.pyplot as plt

    # one panel per error the records hold (no record has ssim_road: no panel for it)
    errors = {"epe_road": "end-point error (px), road", "census_road": "census distance (0-1), road",
              "ssim_road": "SSIM dissimilarity (0-1), road"}
    fig = clip_summary_figure(_records(), errors=errors, title="clip: dis")
    try:
        assert fig.get_suptitle() == "clip: dis"
        visible = [ax for ax in fig.axes if ax.get_visible()]
        titles = [ax.get_title() for ax in visible]
        # every odometry field of the records shows up, a new one (y_d) included, and the mounting
        assert len(visible) == 8
        assert titles[:2] == ["end-point error, road: before and after refinement",
                              "census distance, road: before and after refinement"]
        assert visible[1].get_ylabel() == "census distance (0-1), road"
        (census_fit,) = [ln for ln in visible[1].get_lines() if ln.get_label() == "after, fit"]
        assert list(census_fit.get_ydata()) == pytest.approx([0.21] * 3)
        assert any("vertical motion y_d" in t for t in titles)
        assert any("camera roll" in t for t in titles) and any("camera pitch" in t for t in titles)
        for ax in visible:
            assert ax.get_title() and ax.get_ylabel() and ax.get_legend() is not None
        assert "end-point error (px), road" == visible[0].get_ylabel()
        bottom = [ax for ax in visible if ax.get_xlabel()]
        assert bottom and all(ax.get_xlabel() == "pair" for ax in bottom)
        labels = [t.get_text() for t in visible[0].get_legend().get_texts()]
        assert labels == ["before, given", "after, given", "before, fit", "after, fit"]
        # each after against its own before: a dashed line in the variant's colour
        lines = {ln.get_label(): ln for ln in visible[1].get_lines()}
        assert list(lines["before, given"].get_ydata()) == pytest.approx([0.3] * 3)
        assert list(lines["before, fit"].get_ydata()) == pytest.approx([0.32] * 3)
        for v in ("given", "fit"):
            before, after = lines[f"before, {v}"], lines[f"after, {v}"]
            assert before.get_color() == after.get_color()
            assert before.get_linestyle() == "--" and after.get_linestyle() == "-"
        assert lines["after, given"].get_color() != lines["after, fit"].get_color()
        # yaw in degrees, with the given odometry as a reference line
        yaw = next(ax for ax in visible if "yaw" in ax.get_title())
        assert yaw.get_ylabel() == "yaw (deg)"
        (fit_line,) = [ln for ln in yaw.get_lines() if ln.get_label() == "fit"]
        assert fit_line.get_ydata()[0] == pytest.approx(0.01 * 180 / 3.141592653589793)
        assert "given (odometry / poses)" in [t.get_text() for t in yaw.get_legend().get_texts()]
    finally:
        plt.close(fig)


def test_save_figure_writes_png_and_closes(tmp_path, figure):
    import matplotlib.pyplot as plt

    path = save_figure(figure, tmp_path / "f.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not plt.fignum_exists(figure.number)


@pytest.mark.parametrize("name", ["f.pdf", "f.svg", "f.jpg", "f"])
def test_save_figure_refuses_a_path_that_is_not_png(tmp_path, figure, name):
    """save_figure(fig, "f.pdf") wrote PNG bytes under the .pdf name (viewers took it for a broken
    PDF) and closed the figure; now it is a ValueError naming path, nothing written, the figure
    still open to save under a .png name."""
    import matplotlib.pyplot as plt

    with pytest.raises(ValueError, match=r"^path: save_figure writes PNG, so expected a \.png path, got '.*f"):
        save_figure(figure, tmp_path / name)
    assert list(tmp_path.iterdir()) == []
    assert plt.fignum_exists(figure.number)
    assert save_figure(figure, tmp_path / "F.PNG").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(TypeError, match=r"^fig: expected a matplotlib Figure, got NoneType"):
        save_figure(None, tmp_path / "g.png")


def _pixels(fig):
    import numpy as np

    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba()).copy()


def _content(seed, road_rows):
    g = torch.Generator().manual_seed(seed)
    flow = torch.randn(2, H, W, generator=g) * 3
    flow[:, 4, 7] = float("nan")
    road = torch.zeros(1, H, W, dtype=torch.bool)
    road[0, road_rows:, 5:85] = True
    err = torch.rand(1, H, W, generator=g) * 8
    valid = torch.rand(1, H, W, generator=g) > 0.1
    return dict(images=tuple(torch.rand(3, H, W, generator=g) * 255 for _ in range(2)),
                flows={f"before (s{seed})": flow, "after": flow * 0.5, "after, no error": flow},
                errors={f"before (s{seed})": (err, valid), "after": (err * 0.1, valid)},
                road=road, error_vmax=5.0, error_label="end-point error (px)")


def test_pair_figure_redrawn_equals_a_fresh_one(tmp_path):
    """A PairFigure drawn for one pair and updated for another shows exactly the pixels of a
    figure built afresh for the second pair (titles, outline, colour wheel, error maps all follow),
    and its PNG holds those pixels."""
    import matplotlib.pyplot as plt
    import numpy as np
    from PIL import Image

    first, second = _content(1, 12), _content(2, 20)
    fresh = pair_figure(**second, max_flow=9.0, title="second")
    reused = PairFigure(*PairFigure.layout_of(**first))
    try:
        reused.update(**{k: v for k, v in first.items() if not k.startswith("error_")}, max_flow=4.0, title="first")
        _pixels(reused.figure)
        content = {k: v for k, v in second.items() if not k.startswith("error_")}
        fig = reused.update(**content, max_flow=9.0, title="second")
        assert fig is reused.figure and fig.get_suptitle() == "second"
        expected = _pixels(fresh)
        assert (_pixels(fig) == expected).all()
        path = save_figure(fig, tmp_path / "a.png", close=False)
        assert plt.fignum_exists(fig.number)
        assert (np.asarray(Image.open(path).convert("RGBA")) == expected).all()  # PNG is lossless
        # another layout (no images column, an error panel fewer) is refused, naming what differs
        with pytest.raises(ValueError, match=r"flows: this pair's layout .* differs from the figure's"):
            reused.update(**{**content, "images": None}, max_flow=9.0, title="x")
        with pytest.raises(ValueError, match="layout"):
            reused.update(**{**content, "errors": {"after": content["errors"]["after"]}}, max_flow=9.0, title="x")
    finally:
        reused.close()
        plt.close(fresh)
    assert not plt.fignum_exists(reused.figure.number)



@pytest.mark.parametrize("variants", [1, 2, 4])
def test_pair_figure_title_stays_clear_of_the_legend(variants):
    """The job's title of a pair without ground truth (the census error's, the longer one), with one
    odometry variant (the job's default for a KITTI *_10/*_11 pair of --images): centred over the
    figure, it ran under the legend in the top-right corner. Now it stays left of the legend, in the
    figure, at 10 pt where it fits; a short title keeps 10 pt."""
    import matplotlib.pyplot as plt

    H, W = 375, 1242
    road = torch.zeros(1, H, W, dtype=torch.bool)
    road[0, 250:] = True
    names = ["before (files)"] + [f"after, odometry 'variant{k}' (left unrefined)" for k in range(variants)]
    flow, error = torch.ones(2, H, W), (torch.rand(1, H, W), torch.ones(1, H, W, dtype=torch.bool))
    long = ("pair 000000, flow source 'files': flow and error before and after refinement (mode 'replace'); "
            "error: census distance of I1 and I2 warped by the flow, 0–1")
    for title in (long, "pair 000000", long + "; " + long[:70]):
        fig = pair_figure(flows={n: flow for n in names}, errors={n: error for n in names}, road=road,
                          max_flow=1.0, error_vmax=0.5, error_label="census distance (0-1)", title=title,
                          images=(torch.zeros(3, H, W), torch.zeros(3, H, W)))
        try:
            (legend,) = fig.legends
            text, box = fig.get_suptitle(), fig._suptitle.get_window_extent()
            assert text == title
            assert box.x1 < legend.get_window_extent().x0 and box.x0 > 0, (box, legend.get_window_extent())
            if title != long + "; " + long[:70]:
                assert fig._suptitle.get_fontsize() == 10
        finally:
            plt.close(fig)


def test_pair_figure_draws_maps_that_carry_autograd():
    """A network's flow in training, its error map and images that carry autograd are drawn as
    their values: the pixels of the same figure drawn from detached copies (they raised
    "Can't call numpy() on Tensor that requires grad"). The caller's tensors keep their graph."""
    import matplotlib.pyplot as plt

    content = _content(4, 15)
    weight = torch.ones((), requires_grad=True)
    grad = {**content, "images": tuple(im * weight for im in content["images"]),
            "flows": {k: f * weight for k, f in content["flows"].items()},
            "errors": {k: (e * weight, v) for k, (e, v) in content["errors"].items()}}
    plain, drawn = pair_figure(**content, max_flow=6.0, title="t"), pair_figure(**grad, max_flow=6.0, title="t")
    try:
        assert (_pixels(drawn) == _pixels(plain)).all()
        assert all(f.requires_grad for f in grad["flows"].values())
    finally:
        plt.close(plain)
        plt.close(drawn)


@pytest.mark.parametrize("where", ["road", "flows['after']", "errors['after'][0]", "images[1]", "valid"])
def test_pair_figure_refuses_meta_tensors_naming_them(where):
    """A map or image on the meta device (shapes, no values) is a ValueError naming it, before a
    figure is opened (a NotImplementedError from inside the road's outline before)."""
    import matplotlib.pyplot as plt

    content = {k: v for k, v in _content(5, 15).items() if not k.startswith("error_")}
    content["valid"] = torch.ones(1, H, W, dtype=torch.bool)
    meta = lambda t: t.to("meta")  # noqa: E731
    if where == "road":
        content["road"] = meta(content["road"])
    elif where == "valid":
        content["valid"] = meta(content["valid"])
    elif where.startswith("flows"):
        content["flows"] = {**content["flows"], "after": meta(content["flows"]["after"])}
    elif where.startswith("errors"):
        e, v = content["errors"]["after"]
        content["errors"] = {**content["errors"], "after": (meta(e), v)}
    else:
        content["images"] = (content["images"][0], meta(content["images"][1]))
    open_before = plt.get_fignums()
    with pytest.raises(ValueError, match=re.escape(where) + ": a tensor on the meta device has shapes but no values to draw"):
        pair_figure(**content, max_flow=5.0, error_vmax=5.0, error_label="epe (px)", title="t")
    assert plt.get_fignums() == open_before

def test_pair_figure_pixels_without_a_value_are_grey_not_an_error_of_zero():
    """Pixels without an error value were black, the colour of inferno's 0 (0, 0, 3), and a NaN
    error at a valid pixel was drawn as 0: both now show mid grey, a colour the error map and the
    flow wheel lack, in both rows, and the legend's swatch is that grey."""
    import matplotlib.pyplot as plt
    import numpy as np

    NO_VALUE_RGB = (128, 128, 128)  # fsof_torch.evaluation.visualize.NO_VALUE_RGB
    content = _content(3, 15)
    err, valid = content["errors"]["after"]
    err, valid = err.clone(), valid.clone()
    valid[:, :10] = False                 # rows 0-9: invalid
    valid[:, 20:] = True
    err[:, 20:, :5] = 0.0                 # valid, error 0
    err[:, 20:, 5:10] = float("nan")      # valid, but no finite error
    err[:, 20:, 10:15] = float("inf")
    fig = pair_figure(**{**content, "errors": {**content["errors"], "after": (err, valid)}}, max_flow=5.0, title="t")
    try:
        ax = next(ax for ax in _image_axes(fig) if ax.get_title() == "end-point error, after")
        shown = ax.get_images()[0]
        rgb = shown.to_rgba(shown.get_array(), bytes=True)[..., :3]
        assert (rgb[:10] == NO_VALUE_RGB).all()                    # invalid
        assert (rgb[20:, 5:15] == NO_VALUE_RGB).all()              # NaN or inf at a valid pixel
        zero = rgb[20:, :5].reshape(-1, 3)
        assert (zero == zero[0]).all() and np.abs(zero[0].astype(int) - NO_VALUE_RGB).max() > 60
        assert tuple(round(255 * c) for c in shown.cmap.get_bad()[:3]) == NO_VALUE_RGB
        # the flow row: its NaN pixel (4, 7) shows the same grey
        flow_ax = next(ax for ax in _image_axes(fig) if ax.get_title() == "flow, after")
        assert flow_ax.get_images()[0].get_array()[4, 7].tolist() == list(NO_VALUE_RGB)
        # the legend names it, with that colour
        (legend,) = fig.legends
        (handle,) = [h for h, t in zip(legend.legend_handles, legend.get_texts()) if "no value" in t.get_text()]
        assert tuple(round(255 * c) for c in handle.get_facecolor()[:3]) == NO_VALUE_RGB
        assert "not finite" in next(t.get_text() for t in legend.get_texts() if "no value" in t.get_text())
    finally:
        plt.close(fig)


def test_clip_summary_keeps_the_records_order_of_pairs():
    """Pair names were sorted as strings: frames numbered without zero padding went
    '10', '15', '5' along the time axis."""
    import matplotlib.pyplot as plt

    names = ["5", "10", "15"]
    records = [{"pair": n, "variant": "none", "before": {"epe_road": 1.0 + i}, "after": {"epe_road": 0.5 + i},
                "odometry": {"z_d": 0.1 * (i + 1)}} for i, n in enumerate(names)]
    fig = clip_summary_figure(records, errors={"epe_road": "end-point error (px), road"}, title="t")
    try:
        ax = fig.axes[0]
        assert [t.get_text() for t in ax.get_xticklabels()] == names
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        assert list(lines["before, none"].get_ydata()) == [1.0, 2.0, 3.0]
        assert list(lines["after, none"].get_xdata()) == [0, 1, 2]
        motion = next(a for a in fig.axes if "z_d" in a.get_title())
        assert list(motion.get_lines()[0].get_ydata()) == pytest.approx([0.1, 0.2, 0.3])
    finally:
        plt.close(fig)


def _shown_x(ax):
    """An axes' x label and its visible, non-empty x tick labels (after a draw)."""
    ax.figure.canvas.draw()
    return ax.get_xlabel(), [t.get_text() for t in ax.get_xticklabels() if t.get_visible() and t.get_text()]


def test_clip_summary_labels_the_lowest_panel_of_each_column():
    """With an odd number of panels the right column ends a row higher: its lowest panel had no
    tick labels and no "pair" (only the hidden axes below it had them)."""
    import matplotlib.pyplot as plt

    records = [{"pair": str(100 + i), "variant": "fit", "before": {"epe_road": 1.0}, "after": {"epe_road": 0.5},
                "odometry": {"x_d": 0.0, "z_d": 1.0}} for i in range(3)]
    fig = clip_summary_figure(records, errors={"epe_road": "end-point error (px), road"}, title="t")
    try:
        top_left, right, bottom_left = [ax for ax in fig.axes if ax.get_visible()]
        assert "x_d" in right.get_title() and "z_d" in bottom_left.get_title()
        for ax in (right, bottom_left):
            assert _shown_x(ax) == ("pair", ["100", "101", "102"]), ax.get_title()
        assert _shown_x(top_left) == ("", [])
    finally:
        plt.close(fig)


def test_clip_summary_of_many_pairs_ticks_whole_pairs_by_name():
    """Beyond 12 pairs no ticks were set: matplotlib's own read -2.5 ... 20.0 under "pair"."""
    import matplotlib.pyplot as plt

    names = [str(100 + i) for i in range(20)]
    records = [{"pair": n, "variant": "fit", "before": {"epe_road": 1.0}, "after": {"epe_road": 0.5},
                "odometry": {"z_d": 1.0}} for n in names]
    fig = clip_summary_figure(records, errors={"epe_road": "end-point error (px), road"}, title="t")
    try:
        for ax in fig.axes:
            label, ticks = _shown_x(ax)
            assert label == "pair" and 2 <= len(ticks) <= 13
            assert set(ticks) <= set(names), ticks
            assert [names.index(t) for t in ticks] == sorted(names.index(t) for t in ticks)
    finally:
        plt.close(fig)


@pytest.mark.parametrize("flows, errors, xlabelled, ylabelled", [
    # a flow column without an error panel is its column's lowest panel
    (("before", "after"), ("after",), ["flow, before", "end-point error, after"],
     ["flow, before", "end-point error, after"]),
    # no error panel at all: the flow row carries the x axis
    (("before",), (), ["flow, before"], ["flow, before"]),
    (("a", "b", "c"), ("b",), ["flow, a", "end-point error, b", "flow, c"], ["flow, a", "end-point error, b"]),
])
def test_pair_figure_labels_the_panels_that_exist(flows, errors, xlabelled, ylabelled):
    """Axis labels went by grid position: a flow panel with no error panel below had no x axis,
    an error panel with none to its left no "v (px)"."""
    import matplotlib.pyplot as plt

    flow, road, _, err, valid = _pair()
    fig = pair_figure(flows={n: flow for n in flows}, errors={n: (err, valid) for n in errors}, road=road,
                      max_flow=6.0, error_vmax=5.0, error_label="end-point error (px)", title="t")
    try:
        fig.canvas.draw()
        for ax in _image_axes(fig):
            x_ticks = [t.get_text() for t in ax.get_xticklabels() if t.get_visible() and t.get_text()]
            y_ticks = [t.get_text() for t in ax.get_yticklabels() if t.get_visible() and t.get_text()]
            has_x, has_y = ax.get_title() in xlabelled, ax.get_title() in ylabelled
            assert (ax.get_xlabel(), bool(x_ticks)) == (("u (px)", True) if has_x else ("", False)), ax.get_title()
            assert (ax.get_ylabel(), bool(y_ticks)) == (("v (px)", True) if has_y else ("", False)), ax.get_title()
    finally:
        plt.close(fig)


def test_clip_summary_shows_each_angle_once_in_degrees():
    """A plane-model record carries its attitude over the road in ``odometry`` and the camera
    the refinement used beside it: one panel each, titled apart, where they differ; the same
    value is one panel. Angle changes are in degrees."""
    import matplotlib.pyplot as plt

    recs = []
    for i, v in ((0, "sequence"), (1, "sequence"), (0, "photometric"), (1, "photometric")):
        own = 0.0144 if v == "sequence" else 0.02 + 0.001 * i  # photometric: its camera is its estimate
        recs.append({"pair": f"{i:06d}", "variant": v, "before": {"census_road": 0.3}, "after": {"census_road": 0.2},
                     "odometry": {"z_d": 1.2, "pitch_change": 0.001, "roll": 0.02 + 0.001 * i, "pitch": -0.02},
                     "roll": own, "pitch": -0.02})
    fig = clip_summary_figure(recs, errors={"census_road": "census distance (0-1), road"}, title="clip")
    try:
        titles = [ax.get_title() for ax in fig.axes if ax.get_visible()]
        assert len(titles) == len(set(titles))
        assert "estimated motion: camera roll over the road" in titles
        assert "camera roll (the refinement's mounting)" in titles  # the sequence's calibrated camera
        assert "camera pitch (the refinement's mounting)" not in titles  # the same as the estimate
        mount = next(ax for ax in fig.axes if ax.get_title() == "camera roll (the refinement's mounting)")
        assert [ln.get_label() for ln in mount.get_lines()] == ["sequence"]  # photometric's is its estimate
        assert mount.get_ylabel() == "camera roll (the refinement's mounting, deg)"  # (one pair of brackets)
        change = next(ax for ax in fig.axes if ax.get_title() == "estimated motion: pitch change")
        assert change.get_ylabel() == "pitch change (deg)"
        assert change.get_lines()[0].get_ydata()[0] == pytest.approx(0.001 * 180 / 3.141592653589793)
    finally:
        plt.close(fig)


def _bad_pair_cases():
    flow, road, images, err, valid = _pair()
    small = torch.zeros(1, H // 2, W // 2)
    return [
        # a flow of another size was stretched over the panel silently
        ({"flows": {"before": torch.zeros(2, H // 2, W // 2), "after": flow}}, ValueError,
         rf"flows\['before'\]: expected shape \(2, H, W\) with H={H} \(from an earlier argument\), got \(2, 15, 45\)"),
        ({"flows": {"before": flow[None], "after": flow}}, ValueError, r"flows\['before'\]: expected shape \(2, H, W\)"),
        ({"flows": {"before": torch.zeros(3, H, W), "after": flow}}, ValueError, r"flows\['before'\]: expected shape"),
        ({"flows": {"before": flow.long(), "after": flow}}, TypeError, r"flows\['before'\]: expected a floating-point"),
        ({"errors": {"before": (small, valid), "after": (err, valid)}}, ValueError, r"errors\['before'\]\[0\]: expected shape"),
        # a float validity map, or one of another size: a raw RuntimeError deep inside torch before
        ({"errors": {"before": (err, valid.float()), "after": (err, valid)}}, TypeError,
         r"errors\['before'\]\[1\]: expected a bool tensor \(1, H, W\), got dtype torch.float32"),
        ({"errors": {"before": (err, small.bool()), "after": (err, valid)}}, ValueError, r"errors\['before'\]\[1\]: expected shape"),
        ({"errors": {"other": (err, valid)}}, ValueError, r"errors\['other'\]: no flow column of that name"),
        # no column at all divided by zero in the layout; a list of columns raised AttributeError
        ({"flows": {}, "errors": {}}, ValueError, "flows: expected at least one flow column, got an empty dict"),
        ({"flows": [flow, flow]}, TypeError, "flows: expected a dict of column title -> flow, got list"),
        ({"errors": [(err, valid)]}, TypeError, r"errors: expected a dict of column title -> \(error map, valid\), got list"),
        ({"errors": {"before": (err, valid, valid)}}, TypeError, r"errors\['before'\]: expected \(error map, valid\), got tuple of 3"),
        ({"valid": torch.ones(1, H // 2, W // 2, dtype=torch.bool)}, ValueError, r"valid: expected shape \(1, H, W\) with H=30"),
        ({"valid": valid.float()}, TypeError, r"valid: expected a bool tensor \(1, H, W\), got dtype torch.float32"),
        ({"road": road.float()}, TypeError, r"road: expected a bool tensor \(1, H, W\), got dtype torch.float32"),
        ({"road": road[0]}, ValueError, r"road: expected shape \(1, H, W\), got \(30, 90\)"),
        ({"images": (images[0], torch.rand(3, H // 2, W // 2) * 255)}, ValueError, r"images\[1\]: expected shape \(3, H, W\) with H=30"),
        ({"images": (images[0] / 255, images[1] / 255)}, ValueError, r"images\[0\]: values in .* look like 0..1 images"),
        ({"images": (images[0], images[1].bool())}, TypeError, r"images\[1\]: expected a real tensor \(3, H, W\) on 0..255"),
    ]


@pytest.mark.parametrize("case", range(len(_bad_pair_cases())))
def test_pair_figure_checks_every_map_against_the_road(case):
    """Every flow, error map, validity map and image must have the road's (H, W) and its dtype:
    pair_figure, PairFigure.layout_of and PairFigure.update refuse one that does not, naming it,
    before a figure is opened."""
    import matplotlib.pyplot as plt

    change, error, match = _bad_pair_cases()[case]
    flow, road, images, err, valid = _pair()
    content = dict(flows={"before": flow, "after": flow}, errors={"before": (err, valid), "after": (err, valid)},
                   road=road, images=images)
    content.update(change)
    open_before = plt.get_fignums()
    with pytest.raises(error, match=match):
        pair_figure(**content, max_flow=5.0, error_vmax=5.0, error_label="epe (px)", title="t")
    assert plt.get_fignums() == open_before
    if "valid" not in change:  # (layout_of takes no valid)
        with pytest.raises(error, match=match):
            PairFigure.layout_of(**content, error_vmax=5.0, error_label="epe (px)")
    good = dict(flows={"before": flow, "after": flow}, errors={"before": (err, valid), "after": (err, valid)},
                road=road, images=images)
    figure = PairFigure(*PairFigure.layout_of(**good, error_vmax=5.0, error_label="epe (px)"))
    try:
        with pytest.raises(error, match=match):
            figure.update(**content, max_flow=5.0, title="t")
    finally:
        figure.close()


def test_pair_figure_checks_error_label_and_the_layout_before_a_figure_is_opened():
    """An error_label that is no str failed while drawing ('NoneType' object has no attribute
    'split', a figure left open); a PairFigure of no flow column divided by zero."""
    import matplotlib.pyplot as plt

    flow, road, _, err, valid = _pair()
    open_before = plt.get_fignums()
    with pytest.raises(TypeError, match="error_label: expected a str such as 'end-point error \\(px\\)', got NoneType"):
        pair_figure(flows={"before": flow}, errors={"before": (err, valid)}, road=road, max_flow=2.0,
                    error_vmax=1.0, error_label=None, title="t")
    with pytest.raises(TypeError, match="error_label: expected a str"):
        PairFigure.layout_of(flows={"before": flow}, errors={}, road=road, images=None, error_vmax=1.0,
                             error_label=b"epe")
    with pytest.raises(ValueError, match=r"with_errors: expected one entry per flow column \(at least one\), got \(\)"):
        PairFigure((H, W), (), True, 1.0, "epe (px)")
    assert plt.get_fignums() == open_before


@pytest.mark.parametrize("max_flow, error, match", [
    (float("nan"), ValueError, "max_flow: expected a finite number, got nan"),
    (0.0, ValueError, r"max_flow: expected a positive number \(> 0\), got 0.0"),
    ("2", TypeError, "max_flow: expected a number, got str '2'"),
])
def test_pair_figure_checks_max_flow_before_a_figure_is_opened(max_flow, error, match):
    """max_flow was checked only while drawing, after pair_figure had opened its figure (left open)."""
    import matplotlib.pyplot as plt

    flow, road, _, err, valid = _pair()
    open_before = plt.get_fignums()
    with pytest.raises(error, match=match):
        pair_figure(flows={"before": flow}, errors={"before": (err, valid)}, road=road, max_flow=max_flow,
                    error_vmax=1.0, error_label="epe (px)", title="t")
    assert plt.get_fignums() == open_before


def test_pair_figure_draws_sparse_ground_truth_reduced_not_hidden():
    """A wide frame is drawn reduced (this one by 3, a KITTI frame by 4): a drawn pixel had no value when any
    pixel it covers had none, so sparse ground truth (KITTI's laser lines: 39 % of a road's pixels
    valid, under 3 % of its 3 x 3 blocks entirely) came out almost all grey. A drawn pixel now
    shows the mean of the valid pixels it covers, in the error row and in the flow row (a valid
    map given); it has no value where none is valid, or where a valid pixel's value is not finite."""
    import matplotlib.pyplot as plt
    import numpy as np

    Hk, Wk = 12, 960  # reduced by 3 (a panel is about 320 px wide)
    g = torch.Generator().manual_seed(1)
    flow = torch.randn(2, Hk, Wk, generator=g) * 2
    err = torch.rand(1, Hk, Wk, generator=g) * 4
    valid = torch.zeros(1, Hk, Wk, dtype=torch.bool)
    valid[0, ::3] = True                 # every third row valid: no 3 x 3 block entirely
    valid[0, :, 600:] = False            # none valid here
    err[0, 3, 0], flow[0, 3, 3] = float("nan"), float("inf")  # valid pixels without a value
    err[0, 1, 300] = float("nan")        # invalid: ignored
    road = torch.zeros(1, Hk, Wk, dtype=torch.bool)
    road[0, 6:, 100:800] = True
    fig = pair_figure(flows={"f": flow}, errors={"f": (err, valid)}, road=road, max_flow=4.0, error_vmax=5.0,
                      error_label="end-point error (px)", title="t", valid=valid)
    try:
        flow_ax, error_ax = (next(ax for ax in _image_axes(fig) if ax.get_title() == t)
                             for t in ("flow, f", "end-point error, f"))
        shown = np.ma.filled(error_ax.get_images()[0].get_array(), np.nan)
        assert shown.shape == (4, 320)
        has = ~np.isnan(shown)
        assert has[:, 1:200].all() and not has[:, 200:].any() and not has[1, 0] and has[0, 0]
        # the mean of the valid pixels of a 3 x 3 block: row 0 of the block
        block = err[0, 3:6, 30:33]
        assert shown[1, 10] == pytest.approx(float(block[0].double().mean()), rel=1e-9)
        assert shown[0, 100] == pytest.approx(float(err[0, 0, 300:303].double().mean()), rel=1e-9)
        rgb = flow_ax.get_images()[0].get_array()
        grey = (rgb == np.array([128, 128, 128], dtype=np.uint8)).all(axis=-1)
        assert grey[:, 200:].all() and grey[1, 1] and not grey[1, 0] and not grey[:, 2:200].any()
        mean = flow[:, 3:6, 30:33][:, 0].double().mean(dim=1).view(2, 1, 1)
        assert rgb[1, 10].tolist() == flow_to_color(mean, 4.0)[0, :, 0, 0].tolist()
    finally:
        plt.close(fig)


@pytest.mark.parametrize("size, columns, factor", [
    ((375, 1242), 1, 4), ((375, 1242), 3, 4), ((370, 1226), 2, 4), ((600, 600), 1, 3), ((200, 640), 1, 2),
    ((40, 120), 2, 1),
])
def test_pair_figure_draws_its_pictures_no_larger_than_their_panels(size, columns, factor):
    """matplotlib draws a picture larger than its panel with its nearest-neighbour drawing, which
    drops whole rows and columns: the reduction was the width over about 320 px rounded down, so a
    KITTI frame (by 3: 414 columns into a 324-pixel panel) lost a quarter of its drawn rows and
    columns, sparse ground truth's lines with them (24 of 31 lines one row in 12 apart were drawn),
    and a square 600 px frame (not reduced, into a 253-pixel panel) more than half. The reduction
    now fits the picture into the panel's box, both sides."""
    import matplotlib.pyplot as plt

    H, W = size
    flows = {f"c{k}": torch.zeros(2, H, W) for k in range(columns)}
    errors = {name: (torch.ones(1, H, W), torch.ones(1, H, W, dtype=torch.bool)) for name in flows}
    fig = pair_figure(flows=flows, errors=errors, road=torch.zeros(1, H, W, dtype=torch.bool), max_flow=1.0,
                      error_vmax=1.0, error_label="epe (px)", title="t")
    try:
        fig.canvas.draw()
        for ax in _image_axes(fig):
            picture = ax.get_images()[0]
            h, w = picture.get_array().shape[:2]
            assert (h, w) == (-(-H // factor), -(-W // factor))
            box = picture.get_window_extent()
            assert h <= box.height + 1e-6 and w <= box.width + 1e-6
    finally:
        plt.close(fig)


def test_clip_summary_leaves_out_the_motion_of_pairs_left_unrefined():
    """A pair left unrefined used no road motion: its record's ``odometry`` is null (the job), or
    ``refined`` is False beside the refiner's placeholder zeros; neither is drawn as an estimate
    (a forward motion of 0 m) nor as the mounting the refinement used. The motion fields keep the
    records' order where the first record's are null."""
    import matplotlib.pyplot as plt

    recs = []
    for i in range(3):
        ok = i != 1
        recs.append({"pair": f"{i:06d}", "variant": "fit", "refined": ok,
                     "before": {"census_road": 0.3}, "after": {"census_road": 0.2 if ok else 0.3},
                     "odometry": {k: (v if ok else None) for k, v in (("x_d", 0.01), ("z_d", 1.2), ("yaw", 0.01),
                                                                      ("roll", 0.01), ("pitch", -0.01))},
                     "roll": 0.01 if ok else 0.0, "pitch": -0.01 if ok else 0.0})  # (the fit's own attitude)
    recs.insert(0, {**recs.pop(1)})  # the unrefined record first
    recs.append({"pair": "000003", "variant": "fit", "refined": False, "before": {"census_road": 0.3},
                 "after": {"census_road": 0.3}, "odometry": {"x_d": 0.0, "z_d": 0.0, "yaw": 0.0, "roll": 0.0,
                                                              "pitch": 0.0},
                 "roll": 0.0, "pitch": 0.0})
    fig = clip_summary_figure(recs, errors={"census_road": "census distance (0-1), road"}, title="clip")
    try:
        titles = [ax.get_title() for ax in fig.axes if ax.get_visible()]
        assert titles[1:4] == ["estimated motion: lateral motion x_d", "estimated motion: forward motion z_d",
                               "estimated motion: yaw"]
        assert not any("mounting" in t for t in titles)
        z_d = next(ax for ax in fig.axes if ax.get_title() == "estimated motion: forward motion z_d")
        (line,) = z_d.get_lines()
        # the pairs in the records' order (000001 first): those left unrefined are gaps, not points
        assert list(line.get_xdata()) == [0, 1, 2, 3]
        assert list(line.get_ydata()) == pytest.approx([math.nan, 1.2, 1.2, math.nan], nan_ok=True)
        census = next(ax for ax in fig.axes if ax.get_title().startswith("census"))
        (after,) = [ln for ln in census.get_lines() if ln.get_label() == "after, fit"]
        assert len(after.get_ydata()) == 4  # its errors are still drawn
    finally:
        plt.close(fig)


def test_clip_summary_leaves_a_gap_where_a_pair_between_others_has_no_motion():
    """A pair left unrefined between two refined ones breaks the motion's line there: a line
    drawn straight from the pair before to the pair after showed a motion for a pair that had none
    (as the job's KITTI clip drew given_images over the pairs its gate kept as predicted)."""
    import matplotlib.pyplot as plt

    recs = [{"pair": f"{i:06d}", "variant": "photometric", "refined": i != 2, "before": {"census_road": 0.3},
             "after": {"census_road": 0.2}, "odometry": {"z_d": 1.0 + i if i != 2 else None},
             "roll": 0.0, "pitch": 0.0} for i in range(5)]
    fig = clip_summary_figure(recs, errors={"census_road": "census distance (0-1), road"}, title="clip")
    try:
        z_d = next(ax for ax in fig.axes if ax.get_title() == "estimated motion: forward motion z_d")
        (line,) = z_d.get_lines()
        assert list(line.get_xdata()) == [0, 1, 2, 3, 4]
        assert list(line.get_ydata()) == pytest.approx([1.0, 2.0, math.nan, 4.0, 5.0], nan_ok=True)
        # no segment of the drawn path spans pair 2: matplotlib draws none across a NaN
        path = line.get_path()
        segments = [v for v, code in path.iter_segments(simplify=False)]
        assert [float(v[0]) for v in segments] == [0.0, 1.0, 3.0, 4.0]
        assert [code for _v, code in path.iter_segments(simplify=False)] == [1, 2, 1, 2]  # MOVETO, LINETO
    finally:
        plt.close(fig)


_BACKEND_DRIVER = r"""
import sys
import matplotlib
if sys.argv[1] != "auto":
    matplotlib.use(sys.argv[1])
    import matplotlib.pyplot as plt
    mine = plt.figure()
import torch
from fsof_torch.evaluation.figures import clip_summary_figure, pair_figure, save_figure
H, W = 12, 20
road = torch.zeros(1, H, W, dtype=torch.bool)
road[0, 6:] = True
fig = pair_figure(flows={"a": torch.ones(2, H, W)}, errors={}, road=road, max_flow=2.0, error_vmax=1.0,
                  error_label="e (px)", title="t")
save_figure(fig, sys.argv[2] + "/pair.png")
rec = {"pair": "0", "variant": "v", "before": {"e": 1.0}, "after": {"e": 0.5}, "odometry": {}}
save_figure(clip_summary_figure([rec], errors={"e": "e (px)"}, title="t"), sys.argv[2] + "/clip.png")
import matplotlib.pyplot as plt
print(matplotlib.get_backend().lower(), sys.argv[1] == "auto" or plt.fignum_exists(mine.number))
"""


@pytest.mark.parametrize("chosen, want", [("svg", "svg"), ("pdf", "pdf"), ("auto", "agg")])
def test_figures_keep_the_callers_backend(tmp_path, chosen, want):
    """The figures selected Agg with matplotlib.use, which switched a backend the caller had
    chosen (a notebook's inline backend, a GUI one: later plots no longer showed). Now they take
    Agg only where nobody chose a backend, and leave the caller's figures open."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {k: v for k, v in os.environ.items() if k != "MPLBACKEND"}
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    done = subprocess.run([sys.executable, "-c", _BACKEND_DRIVER, chosen, str(tmp_path)], capture_output=True,
                          text=True, env=env, cwd=root, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [want, "True"]
    assert (tmp_path / "pair.png").stat().st_size > 0 and (tmp_path / "clip.png").stat().st_size > 0


@pytest.mark.parametrize("max_flow", [3.7, 104.0, 0.37])
def test_colour_wheel_rim_is_not_drawn_beyond_max_flow(max_flow):
    """The legend drew the flow (u, v) * max_flow, whose magnitude at the rim came out a rounding
    error above max_flow for some max_flow (3.7: 8 pixels), drawn darker as flow beyond the
    scale. Inside the disc every colour is one of the wheel's (a channel at 255)."""
    wheel = colour_wheel(max_flow).int()
    assert wheel.amax(dim=-1).eq(255).all()
    assert torch.equal(wheel, colour_wheel(1.0).int())  # the colours do not depend on the scale


@pytest.mark.parametrize("size", [(375, 1242), (373, 1241), (90, 330)])
def test_pair_figure_draws_each_reduced_pixel_over_the_pixels_it_averages(size):
    """A frame drawn reduced by f (a KITTI frame by 4) was stretched over the full image, its
    ceil(W / f) drawn columns over W pixels: drawn column j stood at j W / ceil(W / f) instead
    of j f, so the picture drifted from the road outline (drawn in the image's pixels) towards the
    right and bottom edges, a flow edge at column 1236 of a KITTI frame drawn 2 px left of it.
    Drawn pixel j now covers the pixels j f .. j f + f - 1 it is the mean of, and the axes show the
    image's pixels, -0.5 .. W - 0.5 (the last block, cut by the image's edge, ends beyond them)."""
    import matplotlib.pyplot as plt
    import numpy as np

    Hs, Ws = size
    step = Ws - 6  # a flow edge near the right edge, on a block boundary of the reduction
    u = torch.arange(Ws, dtype=torch.float32).expand(Hs, Ws)
    flow = torch.stack([torch.where(u >= step - step % 4, 5.0, 0.0), torch.zeros(Hs, Ws)])
    road = torch.zeros(1, Hs, Ws, dtype=torch.bool)
    road[0, Hs // 2:, :] = True
    fig = pair_figure(flows={"f": flow}, errors={}, road=road, max_flow=5.0, error_vmax=1.0,
                      error_label="epe (px)", title="t")
    try:
        ax = next(a for a in _image_axes(fig) if a.get_title() == "flow, f")
        picture = ax.get_images()[0]
        rgb = picture.get_array()
        h, w = rgb.shape[:2]
        f = -(-Ws // w)
        assert f > 1 and h == -(-Hs // f)
        left, right, bottom, top = picture.get_extent()
        # drawn column j spans [left + j (right - left) / w, ...] in image pixels: j f - 0.5
        for j in (0, 1, w // 2, w - 1):
            assert left + j * (right - left) / w == pytest.approx(j * f - 0.5, abs=1e-9)
        for i in (0, h // 2, h - 1):
            assert top + i * (bottom - top) / h == pytest.approx(i * f - 0.5, abs=1e-9)
        # the flow edge is drawn where it is in the image (the first column of a block)
        first = next(j for j in range(w) if (rgb[0, j] != rgb[0, 0]).any())
        edge = step - step % 4
        assert edge % f == 0 and left + first * (right - left) / w == pytest.approx(edge - 0.5, abs=1e-9)
        # the axes are the image's pixels, where the road outline is drawn
        assert tuple(ax.get_xlim()) == (-0.5, Ws - 0.5) and tuple(ax.get_ylim()) == (Hs - 0.5, -0.5)
        outline = np.concatenate(ax.collections[0].get_segments())
        assert outline[:, 0].max() == Ws - 1 and outline[:, 1].min() == Hs // 2
    finally:
        plt.close(fig)


def _without(record, key):
    return {k: v for k, v in record.items() if k != key}


@pytest.mark.parametrize("records, errors, error, match", [
    # a record without its variant or pair was a bare KeyError('variant')
    ([_without(_records()[0], "variant")], None, ValueError, r"records\[0\]: missing \['variant'\]"),
    ([_records()[0], _without(_records()[1], "pair")], None, ValueError, r"records\[1\]: missing \['pair'\]"),
    # one record rather than a list of them: "string indices must be integers"
    (_records()[0], None, TypeError, "records: expected a list of per-pair record dicts, got dict"),
    ([("000000", "given")], None, TypeError, r"records\[0\]: expected a dict, got tuple"),
    ([{**_records()[0], "before": [2.0]}], None, TypeError, r"records\[0\]\['before'\]: expected a dict"),
    # a metric written as text was drawn as a panel of text categories, without a word
    ([{**_records()[0], "after": {"epe_road": "0.5"}}], None, TypeError,
     r"records\[0\]\['after'\]\['epe_road'\]: expected a number or None, got str '0.5'"),
    # the errors as a list of keys: "list indices must be integers or slices, not str"
    (_records(), ["epe_road"], TypeError, r"errors: expected a dict of record key -> name and unit"),
    (_records(), {"epe_road": None}, TypeError, r"errors: expected a dict of record key -> name and unit"),
])
def test_clip_summary_refuses_records_it_cannot_draw_naming_them(records, errors, error, match):
    import matplotlib.pyplot as plt

    open_before = plt.get_fignums()
    with pytest.raises(error, match=match):
        clip_summary_figure(records, errors=errors or {"epe_road": "end-point error (px), road"}, title="t")
    assert plt.get_fignums() == open_before  # (checked before a figure is opened)


def test_clip_summary_draws_metrics_of_any_real_number_type_and_none():
    """NumPy and 0-d tensor metrics are numbers too (and None, a metric over no pixel, a gap)."""
    import matplotlib.pyplot as plt
    import numpy as np

    records = _records()[:4]
    records[0]["after"]["epe_road"] = np.float32(0.25)
    records[1]["after"]["epe_road"] = torch.tensor(0.5)
    records[2]["after"]["epe_road"] = None
    fig = clip_summary_figure(records, errors={"epe_road": "end-point error (px), road"}, title="t")
    try:
        lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
        # records 0 and 2 are pairs 0 and 1 of "given", 1 and 3 of "fit"
        given = [np.nan if y is None else float(y) for y in lines["after, given"].get_ydata()]
        assert given[0] == 0.25 and np.isnan(given[1])
        assert [float(y) for y in lines["after, fit"].get_ydata()] == pytest.approx([0.5, 0.11])
    finally:
        plt.close(fig)


def test_clip_summary_draws_motion_fields_given_as_numpy_or_tensor_values():
    """A field of NumPy float32 or one-element tensor values (a fit's parameters put in the records
    as they come) was no int or float to the summary: it had no panel at all, without a word."""
    import matplotlib.pyplot as plt
    import numpy as np

    records = [{"pair": str(i), "variant": "fit", "before": {"epe_road": 1.0}, "after": {"epe_road": 0.5},
                "odometry": {"x_d": 0.1, "z_d": np.float32(1.25), "yaw": torch.tensor([0.01 * i])},
                "roll": np.float32(0.02), "pitch": -0.02,
                "odometry_given": {"z_d": torch.tensor(1.2, dtype=torch.float64)}} for i in range(3)]
    fig = clip_summary_figure(records, errors={"epe_road": "end-point error (px), road"}, title="t")
    try:
        panels = {ax.get_title(): ax for ax in fig.axes if ax.get_visible()}
        z_d = {ln.get_label(): list(ln.get_ydata()) for ln in panels["estimated motion: forward motion z_d"].get_lines()}
        assert z_d == {"fit": [1.25] * 3, "given (odometry / poses)": pytest.approx([1.2] * 3)}
        (yaw,) = panels["estimated motion: yaw"].get_lines()
        assert list(yaw.get_ydata()) == pytest.approx([0.0, 0.01 * 180 / np.pi, 0.02 * 180 / np.pi])
        (roll,) = panels["camera roll (the refinement's mounting)"].get_lines()
        assert list(roll.get_ydata()) == pytest.approx([float(np.float32(0.02)) * 180 / np.pi] * 3)
    finally:
        plt.close(fig)


@pytest.mark.parametrize("factor, error, match", [
    (2.5, TypeError, "factor: expected an int, got float 2.5"),  # was avg_pool2d's "kernel_size" error
    (0, ValueError, "factor: expected an int >= 1, got 0"),      # was read as 1
    (-3, ValueError, "factor: expected an int >= 1, got -3"),
])
def test_reduce_values_takes_a_whole_factor_of_at_least_one(factor, error, match):
    import numpy as np

    from fsof_torch.evaluation.figures import reduce_values

    x, has = torch.ones(2, 6, 6), torch.ones(1, 6, 6, dtype=torch.bool)
    with pytest.raises(error, match=match):
        reduce_values(x, has, ~has, factor)
    mean, ok = reduce_values(x, has, ~has, np.int64(3))  # (a NumPy int is a whole number)
    assert mean.shape == (2, 2, 2) and bool(ok.all())
