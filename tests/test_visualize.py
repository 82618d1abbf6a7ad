"""Tests of fsof_torch.evaluation.visualize: flow colours, error maps, mask overlays and their PNG files."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from fsof_torch.evaluation.visualize import (
    error_to_color,
    flow_to_color,
    make_colorwheel,
    overlay_mask,
    save_error_png,
    save_flow_png,
    save_overlay_png,
)


def _reference_wheel():
    """The colour wheel of the Middlebury reference code (flow_vis, Baker et al.), as numpy."""
    RY, YG, GC, CB, BM, MR = 15, 6, 4, 11, 13, 6
    wheel = np.zeros((RY + YG + GC + CB + BM + MR, 3))
    col = 0
    wheel[0:RY, 0] = 255
    wheel[0:RY, 1] = np.floor(255 * np.arange(0, RY) / RY)
    col += RY
    wheel[col:col + YG, 0] = 255 - np.floor(255 * np.arange(0, YG) / YG)
    wheel[col:col + YG, 1] = 255
    col += YG
    wheel[col:col + GC, 1] = 255
    wheel[col:col + GC, 2] = np.floor(255 * np.arange(0, GC) / GC)
    col += GC
    wheel[col:col + CB, 1] = 255 - np.floor(255 * np.arange(CB) / CB)
    wheel[col:col + CB, 2] = 255
    col += CB
    wheel[col:col + BM, 2] = 255
    wheel[col:col + BM, 0] = np.floor(255 * np.arange(0, BM) / BM)
    col += BM
    wheel[col:col + MR, 2] = 255 - np.floor(255 * np.arange(MR) / MR)
    wheel[col:col + MR, 0] = 255
    return wheel


def _reference_colors(u, v):
    """flow_vis.flow_uv_to_colors after normalisation by the largest magnitude (+1e-5), RGB."""
    rad_max = np.sqrt(u ** 2 + v ** 2).max()
    u, v = u / (rad_max + 1e-5), v / (rad_max + 1e-5)
    wheel = _reference_wheel()
    ncols = wheel.shape[0]
    rad = np.sqrt(u ** 2 + v ** 2)
    a = np.arctan2(-v, -u) / np.pi
    fk = (a + 1) / 2 * (ncols - 1)
    k0 = np.floor(fk).astype(np.int32)
    k1 = k0 + 1
    k1[k1 == ncols] = 0
    f = fk - k0
    out = np.zeros(u.shape + (3,), np.uint8)
    for i in range(3):
        col0 = wheel[k0, i] / 255.0
        col1 = wheel[k1, i] / 255.0
        col = (1 - f) * col0 + f * col1
        idx = rad <= 1
        col[idx] = 1 - rad[idx] * (1 - col[idx])
        col[~idx] = col[~idx] * 0.75
        out[:, :, i] = np.floor(255 * col)
    return out


def _flow(B=1, H=20, W=30, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, 2, H, W, generator=g, dtype=torch.float64) * 4).to(dtype)


# --- smoke -------------------------------------------------------------------------------------

def test_smoke(dtype):
    rgb = flow_to_color(_flow(dtype=dtype))
    assert rgb.shape == (1, 3, 20, 30) and rgb.dtype == torch.uint8
    err = error_to_color(_flow(dtype=dtype)[:, :1].abs(), 5.0)
    assert err.shape == (1, 3, 20, 30) and err.dtype == torch.uint8
    ov = overlay_mask(torch.full((1, 3, 20, 30), 100.0, dtype=dtype), torch.ones(1, 1, 20, 30, dtype=torch.bool))
    assert ov.shape == (1, 3, 20, 30) and ov.dtype == torch.uint8


def test_public_names():
    import fsof_torch.evaluation.visualize as mod

    assert set(mod.__all__) >= {"flow_to_color", "error_to_color", "overlay_mask", "make_colorwheel",
                                "save_flow_png", "save_error_png", "save_overlay_png"}


# --- exceptions --------------------------------------------------------------------------------

def test_exceptions():
    with pytest.raises(ValueError, match=r"flow: expected shape \(2, H, W\) or \(B, 2, H, W\), got \(1, 3, 4, 4\)"):
        flow_to_color(torch.zeros(1, 3, 4, 4))
    with pytest.raises(ValueError, match="max_flow: expected a positive"):
        flow_to_color(_flow(), -1.0)
    with pytest.raises(TypeError, match="valid: expected a bool tensor"):
        flow_to_color(_flow(), valid=torch.ones(1, 1, 20, 30))
    with pytest.raises(ValueError, match="vmax: expected a positive"):
        error_to_color(torch.zeros(4, 4), 0.0)
    with pytest.raises(ValueError, match="colormap: expected an OpenCV colour map"):
        error_to_color(torch.zeros(4, 4), 1.0, colormap="nope")
    with pytest.raises(ValueError, match="mask: expected shape"):
        overlay_mask(torch.zeros(3, 4, 4), torch.ones(1, 4, 5, dtype=torch.bool))
    with pytest.raises(ValueError, match="alpha: expected a value in"):
        overlay_mask(torch.zeros(3, 4, 4), torch.ones(1, 4, 4, dtype=torch.bool), alpha=2.0)


@pytest.mark.parametrize("data_range, error, match", [
    (0, ValueError, "data_range: expected a positive finite number"),
    (-255.0, ValueError, "data_range: expected a positive finite number"),
    (float("nan"), ValueError, "data_range: expected a positive finite number"),
    ("255", TypeError, "data_range: expected a positive finite number"),
])
def test_overlay_checks_data_range(data_range, error, match):
    """Not a division by zero, nor a silently black image."""
    with pytest.raises(error, match=match):
        overlay_mask(torch.full((3, 4, 4), 9.0), torch.ones(1, 4, 4, dtype=torch.bool), data_range=data_range)


def test_overlay_refuses_non_finite_images():
    """A NaN pixel is no black pixel."""
    image = torch.full((3, 4, 4), 9.0)
    image[1, 2, 3] = float("nan")
    with pytest.raises(ValueError, match=r"image: expected finite values, got \[nan\]"):
        overlay_mask(image, torch.zeros(1, 4, 4, dtype=torch.bool))


@pytest.mark.parametrize("max_flow, match", [
    (torch.tensor(float("nan")), r"max_flow: expected finite values, got \[nan\]"),
    (torch.tensor(float("inf")), "max_flow: expected finite values"),
    (torch.tensor(-2.0), r"max_flow: expected values > 0, got \[-2.0\]"),
    (torch.tensor([1.0, 0.0, 2.0]), r"max_flow: expected values > 0, got \[0.0\]"),
    (torch.tensor([1.0, 2.0]), r"max_flow: expected a tensor of 1 or 3 elements \(one per sample\), got shape \(2,\)"),
])
def test_flow_to_color_checks_a_tensor_max_flow(max_flow, match):
    """Not an all-black (NaN) or all-white (negative) picture, nor a raw broadcasting error."""
    with pytest.raises(ValueError, match=match):
        flow_to_color(_flow(B=3), max_flow)
    with pytest.raises(TypeError, match="max_flow: expected a real tensor, got dtype torch.bool"):
        flow_to_color(_flow(B=3), torch.tensor(True))
    # one value or one per sample
    assert torch.equal(flow_to_color(_flow(B=3), torch.tensor(2.0)), flow_to_color(_flow(B=3), 2.0))
    assert flow_to_color(_flow(B=3), torch.tensor([1.0, 2.0, 3.0])).shape == (3, 3, 20, 30)


def test_save_refuses_meta_tensors(tmp_path):
    """A figure of a tensor on the meta device (shapes, no values) is a ValueError naming the
    argument, as the docs say of the file writers (was: torch's NotImplementedError)."""
    meta = "a tensor on the meta device has shapes but no values to write"
    with pytest.raises(ValueError, match=f"^flow: {meta}"):
        save_flow_png(tmp_path / "f.png", _flow().to("meta"), max_flow=1.0)
    with pytest.raises(ValueError, match=f"^error_map: {meta}"):
        save_error_png(tmp_path / "e.png", torch.zeros(8, 8, device="meta"), 1.0)
    with pytest.raises(ValueError, match=f"^image: {meta}"):
        save_overlay_png(tmp_path / "o.png", torch.zeros(3, 8, 8, device="meta"), torch.zeros(1, 8, 8, dtype=torch.bool,
                                                                                              device="meta"))
    assert not list(tmp_path.iterdir())


def test_save_rejects_batches(tmp_path):
    with pytest.raises(ValueError, match="expected a single image"):
        save_flow_png(tmp_path / "f.png", _flow(B=2))
    assert not list(tmp_path.iterdir())


# --- cardinality -------------------------------------------------------------------------------

@pytest.mark.parametrize("B", [1, 3])
def test_cardinality(B):
    flow = _flow(B=B, H=7, W=13)
    rgb = flow_to_color(flow)
    assert rgb.shape == (B, 3, 7, 13)
    for b in range(B):   # each sample normalised by its own largest magnitude
        assert torch.equal(flow_to_color(flow[b]), rgb[b:b + 1])
    assert error_to_color(flow[:, :1], 3.0).shape == (B, 3, 7, 13)
    assert overlay_mask(flow[:, :1].abs().clamp(max=255), flow[:, :1] > 0).shape == (B, 3, 7, 13)


# --- feature -----------------------------------------------------------------------------------

def test_colorwheel_matches_reference():
    np.testing.assert_array_equal(make_colorwheel(dtype=torch.float64).numpy(), _reference_wheel())


def test_colorwheel_dtype_holds_its_values_or_is_refused_naming_dtype():
    """An integer dtype that holds 0..255 gives the reference wheel exactly; dtype=torch.bool gave
    a wheel of True and False, torch.int8 wrapped 255 to -1, and a dtype's name ("float32") raised
    torch's TypeError about to(): each is a TypeError naming dtype now."""
    for dtype in (torch.uint8, torch.int16, torch.int64, torch.float32):
        wheel = make_colorwheel(dtype=dtype)
        assert wheel.dtype == dtype
        np.testing.assert_array_equal(wheel.numpy().astype(np.float64), _reference_wheel())
    for bad in (torch.bool, torch.int8, torch.complex64, "float32", np.float32, None):
        with pytest.raises(TypeError, match=r"^dtype: expected a floating-point torch\.dtype .* got "):
            make_colorwheel(dtype=bad)


def test_flow_to_color_matches_reference():
    flow = _flow(H=40, W=50, dtype=torch.float64)
    got = flow_to_color(flow)[0].permute(1, 2, 0).numpy().astype(int)
    want = _reference_colors(flow[0, 0].numpy(), flow[0, 1].numpy()).astype(int)
    assert np.abs(got - want).max() == 0


def test_flow_to_color_float32_within_one_level():
    flow = _flow(H=40, W=50)
    got = flow_to_color(flow)[0].permute(1, 2, 0).numpy().astype(int)
    want = _reference_colors(flow[0, 0].double().numpy(), flow[0, 1].double().numpy()).astype(int)
    assert np.abs(got - want).max() <= 1
    assert (got == want).mean() > 0.99


def test_directions_and_special_values():
    dirs = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]]).T.reshape(1, 2, 1, 4)
    rgb = flow_to_color(dirs)[0, :, 0].T.tolist()
    assert rgb == [[255, 0, 0], [255, 229, 0], [0, 209, 255], [88, 0, 255]]
    assert flow_to_color(torch.zeros(1, 2, 3, 3)).eq(255).all()     # no motion: white
    valid = torch.ones(1, 1, 1, 4, dtype=torch.bool)
    valid[..., 1] = False
    dirs_nan = dirs.clone()
    dirs_nan[0, 0, 0, 2] = float("nan")
    out = flow_to_color(dirs_nan, valid=valid)
    assert out[0, :, 0, 1].eq(0).all() and out[0, :, 0, 2].eq(0).all()     # invalid, NaN: black
    assert out[0, :, 0, 0].tolist() == [255, 0, 0]


def test_max_flow_saturation():
    flow = torch.tensor([[2.0, 0.0]]).T.reshape(1, 2, 1, 1)
    half = flow_to_color(flow, 4.0)[0, :, 0, 0].tolist()       # half saturated red
    assert half == [255, 127, 127]
    over = flow_to_color(flow, 1.0)[0, :, 0, 0].tolist()       # beyond max_flow: darkened
    assert over == [191, 0, 0]


def test_error_to_color_uses_colormap_ends():
    import cv2

    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(256, 1), cv2.COLORMAP_INFERNO)[:, 0, ::-1]
    err = torch.tensor([[0.0, 5.0, 10.0, 50.0, float("nan")]])
    rgb = error_to_color(err, 10.0)[0, :, 0].T.numpy()
    np.testing.assert_array_equal(rgb[0], lut[0])
    np.testing.assert_array_equal(rgb[1], lut[128])     # round(5 / 10 * 255) = 128
    np.testing.assert_array_equal(rgb[2], lut[255])
    np.testing.assert_array_equal(rgb[3], lut[255])     # clipped at vmax
    np.testing.assert_array_equal(rgb[4], [128, 128, 128])    # non-finite: no value, mid grey


@pytest.mark.parametrize("vmax", [1e-50, 1e40])
def test_error_to_color_takes_any_finite_positive_vmax(vmax):
    """vmax is any finite number > 0, but a float32 error map failed outside float32's range: 1e40
    raised a RuntimeError from inside the clamp, 1e-50 (0 in float32) gave 0 / 0 = NaN and an
    IndexError from the colour table. Both now map 0 to the first colour and vmax to the last."""
    import cv2

    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(256, 1), cv2.COLORMAP_INFERNO)[:, 0, ::-1]
    # (float32 errors: 3e38 is 0.03 of 1e40, round(0.03 * 255) = 8; 1e-30 is far above 1e-50)
    err, top = (torch.tensor([[0.0, 3e38]]), 8) if vmax > 1 else (torch.tensor([[0.0, 1e-30]]), 255)
    rgb = error_to_color(err, vmax)[0, :, 0].T.numpy()
    np.testing.assert_array_equal(rgb, np.stack([lut[0], lut[top]]))


def test_error_to_color_draws_no_value_apart_from_zero():
    """Invalid and non-finite pixels were black, which reads as inferno's 0 (0, 0, 3): they are
    mid grey (NO_VALUE_RGB), a colour the map lacks, whatever the error under them."""
    import cv2

    grey = (128, 128, 128)
    err = torch.tensor([[0.0, 0.0, 3.0, float("nan"), float("inf"), float("-inf")]])
    valid = torch.tensor([[True, False, False, True, True, True]])
    rgb = error_to_color(err, 5.0, valid=valid)[0, :, 0].T.numpy()
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(256, 1), cv2.COLORMAP_INFERNO)[:, 0, ::-1]
    np.testing.assert_array_equal(rgb[0], lut[0])                      # a valid 0
    np.testing.assert_array_equal(rgb[1:], np.tile(grey, (5, 1)))  # no value
    assert np.abs(lut.astype(int) - grey).max(axis=1).min() > 60  # not in the map
    from fsof_torch.evaluation.visualize import NO_VALUE_RGB

    assert NO_VALUE_RGB == grey


def test_overlay_blends_inside_mask_only():
    image = torch.full((3, 2, 2), 100.0)
    mask = torch.tensor([[True, False], [False, False]])[None]
    out = overlay_mask(image, mask, color=(0, 255, 0), alpha=0.5)
    assert out[0, :, 0, 0].tolist() == [50, 178, 50]   # round(50 + 127.5) = 178 (half to even)
    assert out[0, :, 1, 1].tolist() == [100, 100, 100]
    grey01 = overlay_mask(torch.full((1, 2, 2), 0.4), mask, data_range=1.0, alpha=0.0)
    assert grey01.eq(102).all()


# --- files -------------------------------------------------------------------------------------

def test_save_pngs_roundtrip(tmp_path):
    import cv2

    flow = _flow()
    p = save_flow_png(tmp_path / "flow.png", flow[0])
    back = cv2.imread(str(p), cv2.IMREAD_COLOR)[:, :, ::-1]
    np.testing.assert_array_equal(back, flow_to_color(flow)[0].permute(1, 2, 0).numpy())

    err = flow[:, :1].abs()
    p = save_error_png(tmp_path / "err.png", err[0, 0], 5.0)
    back = cv2.imread(str(p), cv2.IMREAD_COLOR)[:, :, ::-1]
    np.testing.assert_array_equal(back, error_to_color(err, 5.0)[0].permute(1, 2, 0).numpy())

    image = torch.rand(3, 20, 30, generator=torch.Generator().manual_seed(0)) * 255
    mask = flow[0, :1] > 0
    p = save_overlay_png(tmp_path / "ov.png", image, mask)
    back = cv2.imread(str(p), cv2.IMREAD_COLOR)[:, :, ::-1]
    np.testing.assert_array_equal(back, overlay_mask(image, mask)[0].permute(1, 2, 0).numpy())
    # atomic writes leave no temporary files behind
    assert sorted(os.listdir(tmp_path)) == ["err.png", "flow.png", "ov.png"]


@pytest.mark.parametrize("name", ["flow.jpg", "flow", "flow.png.tmp"])
def test_save_to_a_path_that_is_no_png_is_named_and_writes_nothing(tmp_path, name):
    """The save_*_png functions write PNG bytes: a path of another suffix (a PNG named .jpg, which
    tools that go by the suffix take for a broken JPEG) is a ValueError naming path, before
    anything is written; an upper-case .PNG is a PNG."""
    flow = _flow()
    calls = (lambda p: save_flow_png(p, flow[0]), lambda p: save_error_png(p, flow[0, 0].abs(), 5.0),
             lambda p: save_overlay_png(p, torch.full((3, 20, 30), 100.0), flow[0, :1] > 0))
    for call in calls:
        with pytest.raises(ValueError, match=r"path: expected a \.png file .*write_image"):
            call(tmp_path / name)
    assert os.listdir(tmp_path) == []
    assert save_flow_png(tmp_path / "FLOW.PNG", flow[0]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(TypeError, match="path: expected a str or os.PathLike, got int"):
        save_flow_png(3, flow[0])


def test_save_into_missing_folder_fails_cleanly(tmp_path):
    """A missing folder is named and not created; nothing is written."""
    with pytest.raises(FileNotFoundError, match=r"path: the folder of '.*missing/flow\.png' does not exist"):
        save_flow_png(tmp_path / "missing" / "flow.png", _flow()[0])
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("image, data_range, match", [
    # a 0-255 image said to be 0-1: drawn white everywhere before
    (torch.full((3, 4, 4), 100.0), 1.0, r"image: expected values in \[0, data_range=1\], got values in \[100, 100\]"),
    (torch.full((3, 4, 4), -20.0), 255.0, r"image: expected values in \[0, data_range=255\]"),
    # a 0-1 image said to be 0-255: drawn black
    (torch.full((3, 4, 4), 0.4), 255.0, r"image: values in \[0.4, 0.4\] look like 0..1 images"),
])
def test_overlay_checks_the_image_range(image, data_range, match):
    with pytest.raises(ValueError, match=match):
        overlay_mask(image, torch.zeros(1, 4, 4, dtype=torch.bool), data_range=data_range)
    # the documented range is taken, up to 1 %
    assert overlay_mask(torch.full((3, 4, 4), 1.005), torch.zeros(1, 4, 4, dtype=torch.bool),
                        data_range=1.0).eq(255).all()


@pytest.mark.parametrize("kwargs, error, match", [
    ({"alpha": "half"}, TypeError, "alpha: expected a number, got str 'half'"),
    ({"alpha": float("nan")}, ValueError, "alpha: expected a finite number"),
    ({"color": (300, -40, 0)}, ValueError, r"color: expected values in 0..255, got \(300, -40, 0\)"),
    ({"color": (0, 0, 255.5)}, ValueError, "color: expected values in 0..255"),
    ({"color": (0, 255)}, ValueError, r"color: expected an \(R, G, B\) triple"),
    ({"color": ("r", 0, 0)}, TypeError, "color: expected a number, got str 'r'"),
    ({"color": 255}, TypeError, r"color: expected an \(R, G, B\) triple of numbers in 0..255, got int 255"),
])
def test_overlay_refuses_bad_alpha_and_color(kwargs, error, match):
    """A colour outside 0..255 is refused, not clamped into another colour."""
    with pytest.raises(error, match=match):
        overlay_mask(torch.full((3, 4, 4), 9.0), torch.ones(1, 4, 4, dtype=torch.bool), **kwargs)


def test_overlay_accepts_colour_lists_and_number_types():
    image, mask = torch.full((1, 3, 2, 2), 100.0), torch.ones(1, 1, 2, 2, dtype=torch.bool)
    out = overlay_mask(image, mask, color=[0, 255.0, torch.tensor(50)], alpha=torch.tensor(0.5))
    assert out[0, :, 0, 0].tolist() == [50, 178, 75]


def test_flow_to_color_of_huge_float32_flows():
    """|f|² overflows float32 above about 1.8e19 px: the radius is formed after scaling by a
    power of two, so the colours are the float64 ones (right = red at full saturation, a tiny
    vector beside it white), not NaN cast to uint8."""
    f = torch.zeros(2, 2, 1, 2)
    f[0, 0, 0, 0] = 1e20
    f[0, 0, 0, 1] = 1.0
    f[1, 1, 0, 0] = -3e38  # up, near float32's largest value
    f[1, 0, 0, 1] = 1e10
    got = flow_to_color(f)
    # float32 rounding may move a level by one, as for ordinary flows
    assert (got.int() - flow_to_color(f.double()).int()).abs().max() <= 1
    assert got[0, :, 0, 0].tolist() == [255, 0, 0] and got[0, :, 0, 1].tolist() == [255, 255, 255]
    assert got[1, :, 0, 1].tolist() == [255, 255, 255]
    assert (got[1, :, 0, 0].int() - torch.tensor([88, 0, 255])).abs().max() <= 1


def test_colormap_and_shape_errors_name_what_came():
    """A colour map that is not a name raised AttributeError ('int' object has no attribute
    'upper'); a shape error quoted the shape with the batch dimension the function had added."""
    error = torch.rand(1, 1, 4, 4)
    for colormap in (3, None):
        with pytest.raises(TypeError, match=f"^colormap: expected an OpenCV colour map name such as 'inferno', "
                                            f"got {type(colormap).__name__} {colormap!r}$"):
            error_to_color(error, 1.0, colormap=colormap)
    with pytest.raises(ValueError, match=r"^flow: expected shape \(2, H, W\) or \(B, 2, H, W\), got \(3, 4, 4\)$"):
        flow_to_color(torch.rand(3, 4, 4))
    assert flow_to_color(torch.rand(2, 4, 4)).shape == (1, 3, 4, 4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("m", [1e-2, 1e-4, 1e-6, 1e-30])
def test_max_flow_is_full_saturation_for_small_flows(m, dtype):
    """The scale had RAFT's absolute 1e-5 px added, so a small max_flow was not full saturation:
    a flow of max_flow = 1e-4 px to the right was drawn (255, 23, 23), of 1e-5 px half saturated.
    Now max_flow (and, with None, each sample's largest magnitude) is exactly full saturation,
    as in Middlebury's flowToColor (maxrad + MATLAB's eps 2.2e-16); zero flow stays white."""
    flow = torch.zeros(2, 2, 1, 2, dtype=dtype)
    flow[:, 0, 0, 0] = m
    flow[1, 0, 0, 1] = m / 2
    for max_flow in (m, None):
        rgb = flow_to_color(flow, max_flow)
        assert rgb[0, :, 0, 0].tolist() == [255, 0, 0]          # full saturation, right: red
        assert rgb[0, :, 0, 1].tolist() == [255, 255, 255]      # no motion: white
    assert flow_to_color(flow, m)[1, :, 0, 1].tolist() == [255, 127, 127]  # half of max_flow
    assert flow_to_color(flow * 0, None).eq(255).all()          # all zero, max_flow None: white


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_flow_inside_max_flow_keeps_a_full_channel(dtype):
    """Every colour of the wheel, and every mix of two neighbours, has a channel at 255, which the
    desaturation towards white keeps: inside max_flow each pixel has a channel at 255. Without
    RAFT's 1e-5 (the test above), colours computed in 0..1 as RAFT does are floored one level low
    where the exact value is an integer: flow straight up at full saturation was (87, 0, 255),
    not the 88 of the wheel (RAFT's flow_viz itself draws 254 for a few per cent of the channels at
    255: (1 - f) * 1 + f * 1 falls below 1). In levels 0..255 the wheel's integers stay exact."""
    g = torch.Generator().manual_seed(3)
    flow = (torch.randn(2, 2, 60, 80, generator=g, dtype=torch.float64) * 4).to(dtype)
    for max_flow in (None, float(torch.linalg.vector_norm(flow, dim=1).max()) * 1.01):
        rgb = flow_to_color(flow, max_flow)
        assert rgb.amax(dim=1).eq(255).all()
    up = torch.tensor([0.0, -1.0], dtype=dtype).view(2, 1, 1)
    assert flow_to_color(up, 1.0)[0, :, 0, 0].tolist() == [88, 0, 255]


_DEVKIT_LC = [(0, 0.0625, 49, 54, 149), (0.0625, 0.125, 69, 117, 180), (0.125, 0.25, 116, 173, 209),
              (0.25, 0.5, 171, 217, 233), (0.5, 1, 224, 243, 248), (1, 2, 254, 224, 144), (2, 4, 253, 174, 97),
              (4, 8, 244, 109, 67), (8, 16, 215, 48, 39), (16, 1e9, 165, 0, 38)]


def _devkit_error_image(est, gt, occ, noc):
    """The KITTI devkit's FlowImage::errorImage(F_noc, F_occ, log_colors=true), pixel by pixel
    (without its 3 x 3 blocks): est, gt (H, W, 2), occ, noc (H, W) bool; RGB (H, W, 3) uint8."""
    H, W = occ.shape
    out = np.zeros((H, W, 3), np.uint8)
    for y in range(H):
        for x in range(W):
            if not occ[y, x]:
                continue
            dfu, dfv = est[y, x] - gt[y, x]
            f_err = np.sqrt(dfu * dfu + dfv * dfv)
            f_mag = np.sqrt(gt[y, x, 0] ** 2 + gt[y, x, 1] ** 2)
            with np.errstate(divide="ignore", invalid="ignore"):
                rel = 20.0 * f_err / f_mag
            n_err = f_err / 3.0 if not rel < f_err / 3.0 else rel  # std::min(a, b): b < a ? b : a
            val = [0, 0, 0]
            for lo, hi, r, g, b in _DEVKIT_LC:
                if lo <= n_err < hi:
                    val = [r, g, b]
            if not noc[y, x]:
                val = [int(c * 0.5) for c in val]
            out[y, x] = val
    return out


def test_kitti_error_to_color_matches_the_devkit():
    from fsof_torch.evaluation.visualize import kitti_error_to_color

    g = torch.Generator().manual_seed(5)
    H, W = 24, 40
    gt = torch.randn(2, H, W, generator=g, dtype=torch.float64) * 20
    gt[:, 0, :5] = 0.0  # zero ground truth: n = e / 3
    # errors from 0.01 px to 100 px, log-uniform, in random directions
    e = 10 ** (torch.rand(1, H, W, generator=g, dtype=torch.float64) * 4 - 2)
    angle = torch.rand(1, H, W, generator=g, dtype=torch.float64) * 2 * torch.pi
    est = gt + e * torch.cat([torch.cos(angle), torch.sin(angle)])
    est[:, 1, 0] = gt[:, 1, 0] + torch.tensor([3.0, 0.0], dtype=torch.float64)  # e = 3 px: n = 1 where |F| >= 60
    occ = torch.rand(1, H, W, generator=g) > 0.2
    noc = occ & (torch.rand(1, H, W, generator=g) > 0.3)
    got = kitti_error_to_color(est, gt, occ, valid_noc=noc)[0].permute(1, 2, 0).numpy()
    want = _devkit_error_image(est.permute(1, 2, 0).numpy(), gt.permute(1, 2, 0).numpy(), occ[0].numpy(), noc[0].numpy())
    np.testing.assert_array_equal(got, want)
    assert len({tuple(c) for c in got.reshape(-1, 3)}) >= 15  # the test reaches most colours, halved or not
    # without valid_noc no colour is halved; a (2, H, W) input gets a batch dimension
    full = kitti_error_to_color(est, gt, occ)
    want_full = _devkit_error_image(est.permute(1, 2, 0).numpy(), gt.permute(1, 2, 0).numpy(), occ[0].numpy(),
                                    occ[0].numpy())
    assert full.shape == (1, 3, H, W) and full.dtype == torch.uint8
    np.testing.assert_array_equal(full[0].permute(1, 2, 0).numpy(), want_full)


def test_kitti_error_to_color_draws_a_non_finite_estimate_as_the_worst_error():
    """The devkit's NaN error matches no colour and stays black, as an invalid pixel: here a
    non-finite estimate at a valid pixel is an infinite error, the last colour; huge errors too."""
    from fsof_torch.evaluation.visualize import KITTI_LOG_COLORS, kitti_error_to_color

    gt = torch.ones(1, 2, 1, 4)
    est = torch.tensor([float("nan"), float("inf"), 1e30, 1.0]).view(1, 1, 1, 4).expand(1, 2, 1, 4).clone()
    valid = torch.ones(1, 1, 1, 4, dtype=torch.bool)
    rgb = kitti_error_to_color(est, gt, valid)[0, :, 0].T.tolist()
    worst, best = list(KITTI_LOG_COLORS[-1][2:]), list(KITTI_LOG_COLORS[0][2:])
    assert rgb == [worst, worst, worst, best]
    valid[..., 0] = False
    assert kitti_error_to_color(est, gt, valid)[0, :, 0, 0].tolist() == [0, 0, 0]  # invalid: black
    with pytest.raises(ValueError, match="flow_gt"):
        kitti_error_to_color(est, torch.full_like(gt, float("nan")), valid)
    with pytest.raises(TypeError, match="valid_noc"):
        kitti_error_to_color(est, gt, valid, valid_noc=valid.float())
    with pytest.raises(TypeError, match="valid: expected a bool tensor, got NoneType"):
        kitti_error_to_color(est, gt, None)  # (required: it was a KeyError 'valid')
    with pytest.raises(ValueError, match="flow_gt"):
        kitti_error_to_color(est, gt[..., :3], valid)
