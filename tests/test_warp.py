"""Tests of fsof_torch.evaluation.warp: the one backward warp of the project."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fsof_torch.evaluation.warp import WarpBackward, normalize_coordinates, warp_backward


def _image(B=1, C=3, H=24, W=40, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(B, C, H, W, generator=g, dtype=torch.float64) * 255).to(dtype)


def _flow(B=1, H=24, W=40, scale=3.0, dtype=torch.float32, seed=1):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, 2, H, W, generator=g, dtype=torch.float64) * scale).to(dtype)


def _reference(image, flow):
    """Independent bilinear reference: torch grid_sample in float64 on a corner-aligned grid."""
    B, _, H, W = image.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                          indexing="ij")
    x = u + flow[:, 0].double()
    y = v + flow[:, 1].double()
    grid = torch.stack([x * 2 / (W - 1) - 1, y * 2 / (H - 1) - 1], dim=-1)
    return F.grid_sample(image.double(), grid, mode="bilinear", padding_mode="zeros", align_corners=True)


# --- smoke -------------------------------------------------------------------------------------

def test_smoke(dtype):
    image, flow = _image(dtype=dtype), _flow(dtype=dtype)
    warped, in_bounds = warp_backward(image, flow)
    assert warped.shape == image.shape and warped.dtype == dtype
    assert in_bounds.shape == (1, 1, 24, 40) and in_bounds.dtype == torch.bool
    assert torch.isfinite(warped).all()


def test_public_names():
    import fsof_torch.evaluation.warp as mod

    assert set(mod.__all__) >= {"warp_backward", "WarpBackward", "normalize_coordinates"}


def test_module_twin():
    image, flow = _image(), _flow()
    module = WarpBackward(align_corners=False, mode="nearest")
    got = module(image, flow)
    want = warp_backward(image, flow, align_corners=False, mode="nearest")
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    assert "nearest" in repr(module)


def test_does_not_modify_inputs():
    image, flow = _image(), _flow()
    image0, flow0 = image.clone(), flow.clone()
    warp_backward(image, flow)
    assert torch.equal(image, image0) and torch.equal(flow, flow0)


# --- exceptions --------------------------------------------------------------------------------

def test_bad_flow_shape():
    with pytest.raises(ValueError, match=r"flow: expected shape \(B, 2, H, W\)"):
        warp_backward(_image(), torch.zeros(1, 3, 24, 40))


def test_size_mismatch():
    with pytest.raises(ValueError, match=r"flow: expected shape .* with H=24"):
        warp_backward(_image(), torch.zeros(1, 2, 25, 40))


def test_batch_mismatch():
    with pytest.raises(ValueError, match=r"flow: expected shape .* with B=2"):
        warp_backward(_image(B=2), torch.zeros(3, 2, 24, 40))


def test_integer_image_rejected():
    with pytest.raises(TypeError, match="image: expected a floating-point tensor"):
        warp_backward(torch.zeros(1, 3, 4, 4, dtype=torch.uint8), torch.zeros(1, 2, 4, 4))


def test_bad_mode():
    with pytest.raises(ValueError, match="mode: expected one of"):
        warp_backward(_image(), _flow(), mode="bicubic")
    with pytest.raises(ValueError, match="padding_mode: expected one of"):
        warp_backward(_image(), _flow(), padding_mode="reflection")
    with pytest.raises(ValueError, match="mode: expected one of"):
        WarpBackward(mode="area")
    with pytest.raises(TypeError, match="^align_corners: expected True or False, got str 'x'$"):
        WarpBackward(align_corners="x")  # (when built, not at its first forward)
    # the function says what came as the module does: a NumPy bool was "expected a bool, got bool"
    with pytest.raises(TypeError, match=r"^align_corners: expected True or False, got bool np\.True_$"):
        warp_backward(_image(), _flow(), align_corners=np.True_)


def test_nan_flow_rejected():
    flow = _flow()
    flow[0, 0, 3, 3] = float("nan")
    with pytest.raises(ValueError, match="flow: expected finite values"):
        warp_backward(_image(), flow)


# --- cardinality -------------------------------------------------------------------------------

@pytest.mark.parametrize("B", [1, 3])
@pytest.mark.parametrize("size", [(16, 40), (33, 17)])
def test_cardinality(B, size):
    H, W = size
    image, flow = _image(B=B, C=2, H=H, W=W), _flow(B=B, H=H, W=W)
    warped, in_bounds = warp_backward(image, flow)
    assert warped.shape == (B, 2, H, W) and in_bounds.shape == (B, 1, H, W)
    # each sample of the batch is warped on its own
    for b in range(B):
        one, ok = warp_backward(image[b:b + 1], flow[b:b + 1])
        assert torch.equal(one, warped[b:b + 1]) and torch.equal(ok, in_bounds[b:b + 1])


def test_singleton_axis():
    image = _image(H=1, W=7)
    warped, in_bounds = warp_backward(image, torch.zeros(1, 2, 1, 7))
    assert torch.equal(warped, image) and in_bounds.all()


# --- feature -----------------------------------------------------------------------------------

@pytest.mark.parametrize("align_corners", [True, False])
@pytest.mark.parametrize("size", [(24, 40), (375, 1242)])
def test_identity_is_exact(align_corners, size):
    image = _image(C=1, H=size[0], W=size[1])
    warped, in_bounds = warp_backward(image, torch.zeros(1, 2, *size), align_corners=align_corners)
    assert torch.equal(warped, image)
    assert in_bounds.all()


@pytest.mark.parametrize("align_corners", [True, False])
@pytest.mark.parametrize("shift", [(1, 0), (0, -2), (3, 2), (-5, 4)])
def test_whole_pixel_shift_equals_roll(align_corners, shift, dtype):
    du, dv = shift
    H, W = 24, 40
    image = _image(H=H, W=W, dtype=dtype)
    flow = torch.zeros(1, 2, H, W, dtype=dtype)
    flow[:, 0], flow[:, 1] = du, dv
    warped, in_bounds = warp_backward(image, flow, align_corners=align_corners)
    # warped(v, u) = image(v + dv, u + du)  <=>  roll by (-dv, -du)
    rolled = torch.roll(image, shifts=(-dv, -du), dims=(2, 3))
    interior = (slice(None), slice(None), slice(5, H - 5), slice(5, W - 5))
    assert torch.equal(warped[interior], rolled[interior])
    # exactly the pixels whose source is inside the image are valid
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    expect = (u + du >= 0) & (u + du <= W - 1) & (v + dv >= 0) & (v + dv <= H - 1)
    assert torch.equal(in_bounds[0, 0], expect)
    assert torch.equal(warped[in_bounds.expand_as(warped)], rolled[in_bounds.expand_as(rolled)])


def test_out_of_image_invalid():
    H, W = 10, 12
    flow = torch.zeros(1, 2, H, W)
    flow[0, 0, 2, 3] = -3.01      # u = -0.01: just left of the first pixel centre
    flow[0, 0, 4, 5] = 6.0        # u = 11 = W-1: on the last pixel centre, still valid
    flow[0, 0, 4, 6] = 5.02       # u = 11.02
    flow[0, 1, 7, 1] = -7.5       # v = -0.5
    flow[0, 1, 8, 8] = 1.0        # v = 9 = H-1: valid
    _, in_bounds = warp_backward(_image(H=H, W=W), flow)
    invalid = {(2, 3), (4, 6), (7, 1)}
    for (r, c) in [(2, 3), (4, 5), (4, 6), (7, 1), (8, 8)]:
        assert bool(in_bounds[0, 0, r, c]) == ((r, c) not in invalid)
    assert int((~in_bounds).sum()) == 3


def test_matches_grid_sample_reference(dtype):
    image, flow = _image(B=2, dtype=dtype), _flow(B=2, dtype=dtype)
    warped, in_bounds = warp_backward(image, flow)
    ref = _reference(image, flow).to(dtype)
    tol = {torch.float32: 2e-3, torch.float64: 1e-9}[dtype]
    torch.testing.assert_close(warped, ref, atol=tol, rtol=0)


def _taps_reference(image, flow, padding_mode):
    """Independent exact reference: the four integer corners read by indexing (zeros or the
    nearest edge pixel outside the image), mixed with torch.lerp as the warp documents."""
    B, C, H, W = image.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=flow.dtype), torch.arange(W, dtype=flow.dtype), indexing="ij")
    x, y = u + flow[:, 0], v + flow[:, 1]
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = (x - x0).unsqueeze(1), (y - y0).unsqueeze(1)

    def tap(dx, dy):
        xi, yi = (x0 + dx).long(), (y0 + dy).long()
        inside = ((xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)).unsqueeze(1)
        xc, yc = xi.clamp(0, W - 1), yi.clamp(0, H - 1)
        b = torch.arange(B).view(B, 1, 1)
        picked = image.permute(0, 2, 3, 1)[b, yc, xc].permute(0, 3, 1, 2)
        return picked if padding_mode == "border" else torch.where(inside, picked, torch.zeros_like(picked))

    top = torch.lerp(tap(0, 0), tap(1, 0), fx)
    return torch.lerp(top, torch.lerp(tap(0, 1), tap(1, 1), fx), fy)


@pytest.mark.parametrize("padding_mode", ["zeros", "border"])
@pytest.mark.parametrize("align_corners", [True, False])
@pytest.mark.parametrize("size", [(24, 40), (2, 9), (7, 3), (375, 1242)])
def test_corner_taps_equal_indexing_reference(dtype, padding_mode, align_corners, size):
    """The four taps, sampled on one grid built from the first corner, are the image's own pixels
    (or the padding), bit for bit: flows reaching far outside the image, whole and fractional."""
    H, W = size
    image = _image(B=2, H=H, W=W, dtype=dtype)
    flow = _flow(B=2, H=H, W=W, scale=0.6 * max(H, W), dtype=dtype)
    flow[:, :, : H // 2] = flow[:, :, : H // 2].round()
    warped, _ = warp_backward(image, flow, align_corners=align_corners, padding_mode=padding_mode)
    assert torch.equal(warped, _taps_reference(image, flow, padding_mode))


@pytest.mark.parametrize("padding_mode", ["zeros", "border"])
@pytest.mark.parametrize("B, C, H, W", [(1, 3, 700, 1000), (3, 1, 257, 999)])
def test_large_warp_without_autograd_is_sampled_in_bands(monkeypatch, padding_mode, B, C, H, W):
    """Without autograd, a warp of more sample points than ``_BAND_POINTS`` samples a band of rows
    at a time (the corners' grid and taps of the whole frame, some 100 bytes a pixel of an RGB
    image, were held at once: about 1 GB for a 2160x3840 frame), with the values of the one-pass
    warp that autograd takes and of the indexing reference, bit for bit."""
    import fsof_torch.evaluation.warp as warp

    points = []
    sample = warp._sample_corners

    def spy(image, x0, y0, **kwargs):
        points.append(x0.numel())
        return sample(image, x0, y0, **kwargs)

    monkeypatch.setattr(warp, "_sample_corners", spy)
    image, flow = _image(B=B, C=C, H=H, W=W), _flow(B=B, H=H, W=W, scale=40.0)
    flow[:, 0, 5] = torch.arange(W - 1, -1, -1, dtype=flow.dtype)  # row 5: onto the last column exactly
    with torch.no_grad():
        banded, in_bounds = warp_backward(image, flow, padding_mode=padding_mode)
    assert len(points) > 1 and max(points) <= warp._BAND_POINTS and sum(points) == B * H * W
    points.clear()
    whole, whole_in_bounds = warp_backward(image, flow.clone().requires_grad_(), padding_mode=padding_mode)
    assert points == [B * H * W]
    assert torch.equal(banded, whole.detach()) and torch.equal(in_bounds, whole_in_bounds)
    assert torch.equal(banded, _taps_reference(image, flow, padding_mode))


@pytest.mark.parametrize("padding_mode", ["zeros", "border"])
@pytest.mark.parametrize("align_corners", [True, False])
@pytest.mark.parametrize("size", [(24, 40), (1, 9), (7, 1), (375, 1242)])
def test_corner_taps_equal_four_pixel_maps(dtype, padding_mode, align_corners, size):
    """The corners sampled from one normalised corner plus a pixel's step equal, bit for bit, the
    four corner pixel maps normalised one by one and sampled by kornia's remap (the warp's former
    path), also on 1-pixel axes and for corners far outside the image."""
    from fsof_torch.evaluation.warp import _sample_corners, _sample_nearest

    H, W = size
    B = 2
    image = _image(B=B, H=H, W=W, dtype=dtype)
    g = torch.Generator().manual_seed(3)
    x0 = torch.floor((torch.rand(B, H, W, generator=g, dtype=torch.float64) * 3 - 1) * W).to(dtype)
    y0 = torch.floor((torch.rand(B, H, W, generator=g, dtype=torch.float64) * 3 - 1) * H).to(dtype)
    x0[0, 0, 0], y0[0, 0, 0] = -1.0, -1.0  # the corners straddling the top-left edge
    corner = torch.tensor([[0, 1, 0, 1], [0, 0, 1, 1]], dtype=dtype)
    xs = (x0.unsqueeze(1) + corner[0].view(1, 4, 1, 1)).reshape(B, 4 * H, W)
    ys = (y0.unsqueeze(1) + corner[1].view(1, 4, 1, 1)).reshape(B, 4 * H, W)
    old = _sample_nearest(image, xs, ys, align_corners=align_corners, padding_mode=padding_mode)
    new = _sample_corners(image, x0, y0, align_corners=align_corners, padding_mode=padding_mode)
    assert torch.equal(new, old)


@pytest.mark.parametrize("padding_mode", ["zeros", "border"])
@pytest.mark.parametrize("mode", ["bilinear", "nearest"])
@pytest.mark.parametrize("size", [(1, 9), (7, 1), (1, 1)])
def test_one_pixel_axis_gives_the_same_result_for_both_align_corners(mode, padding_mode, size):
    """On a 1-pixel-high or -wide image both flags give one result, bit for bit: a tap outside
    reads the padding (with the corner-aligned scale, undefined on such an axis, it read the only
    pixel); the identity and whole-pixel shifts stay exact."""
    H, W = size
    image = _image(B=2, H=H, W=W, dtype=torch.float64)
    flow = _flow(B=2, H=H, W=W, scale=3.0, dtype=torch.float64)
    flow[:, :, :, : W // 2 + 1] = flow[:, :, :, : W // 2 + 1].round()
    a = warp_backward(image, flow, align_corners=True, mode=mode, padding_mode=padding_mode)
    b = warp_backward(image, flow, align_corners=False, mode=mode, padding_mode=padding_mode)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    if mode == "bilinear":
        assert torch.equal(a[0], _taps_reference(image, flow, padding_mode))
    # one row (column) down (right) of a 1-row (1-column) image: every tap outside, zeros padding reads 0
    step = torch.zeros(1, 2, H, W, dtype=torch.float64)
    step[:, 1 if H == 1 else 0] = 1.0
    for align_corners in (True, False):
        warped, ok = warp_backward(image[:1], step, align_corners=align_corners, mode=mode, padding_mode="zeros")
        assert not ok.any() and torch.equal(warped, torch.zeros_like(warped))
        warped, ok = warp_backward(image[:1], torch.zeros_like(step), align_corners=align_corners, mode=mode)
        assert ok.all() and torch.equal(warped, image[:1])


def test_align_corners_does_not_change_result():
    image, flow = _image(B=2), _flow(B=2)
    a = warp_backward(image, flow, align_corners=True)
    b = warp_backward(image, flow, align_corners=False)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_kornia_half_pixel_trap_is_real():
    """Documents why warp.py normalises by itself: kornia's remap with pixel maps and its
    default align_corners shifts an identity map by half a pixel (kornia #4504)."""
    from kornia.geometry.transform import remap

    image = _image(C=1)
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(40.0), indexing="ij")
    trap = remap(image, u[None], v[None])
    assert (trap - image).abs().max() > 1.0
    assert torch.equal(warp_backward(image, torch.zeros(1, 2, 24, 40))[0], image)


def test_normalize_coordinates():
    x = torch.tensor([0.0, 4.0, 9.0])
    torch.testing.assert_close(normalize_coordinates(x, 10, align_corners=True),
                               torch.tensor([-1.0, -1.0 + 8 / 9, 1.0]))
    torch.testing.assert_close(normalize_coordinates(x, 10, align_corners=False),
                               torch.tensor([-0.9, -0.1, 0.9]))


@pytest.mark.parametrize("flag", ["False", "True", 0, 1, None])
def test_normalize_coordinates_refuses_a_flag_that_is_not_a_bool(flag):
    # (a truthy string "False" gave the corner-aligned coordinates, 0.1 off those asked for here)
    with pytest.raises(TypeError, match=f"align_corners: expected True or False, got {type(flag).__name__}"):
        normalize_coordinates(torch.tensor([0.0, 4.0, 9.0]), 10, align_corners=flag)


def test_nearest_mode():
    image, flow = _image(), _flow()
    warped, in_bounds = warp_backward(image, flow, mode="nearest")
    rounded = torch.round(flow)
    ref = _reference(image, rounded).float()
    assert torch.equal(warped[in_bounds.expand_as(warped)], ref[in_bounds.expand_as(ref)])


def test_border_padding_only_changes_invalid_pixels():
    image, flow = _image(), _flow(scale=8.0)
    zeros, ok = warp_backward(image, flow)
    border, ok2 = warp_backward(image, flow, padding_mode="border")
    assert torch.equal(ok, ok2) and not ok.all()
    m = ok.expand_as(zeros)
    assert torch.equal(zeros[m], border[m])
    assert not torch.equal(zeros[~m], border[~m])


def test_autocast_bfloat16_keeps_geometry_float32():
    H, W = 16, 300
    image = _image(C=1, H=H, W=W)
    flow = torch.zeros(1, 2, H, W)
    flow[:, 0] = 0.25
    with torch.autocast(device_type="cpu", dtype=torch.bfloat16):
        warped, in_bounds = warp_backward(image, flow)
        warped_bf, _ = warp_backward(image.bfloat16(), flow.bfloat16())
    assert warped.dtype == torch.float32 and warped_bf.dtype == torch.bfloat16
    ref = _reference(image, flow).float()
    # a bfloat16 coordinate at u ~ 300 would be off by up to 1 px; float32 geometry is exact here
    torch.testing.assert_close(warped, ref, atol=1e-3, rtol=0)
    torch.testing.assert_close(warped_bf.float(), ref, atol=2.0, rtol=0.01)
    assert in_bounds[..., : W - 1].all() and not in_bounds[..., W - 1].any()


def test_autocast_backward_finite():
    image = _image(C=1).requires_grad_()
    flow = _flow().requires_grad_()
    with torch.autocast(device_type="cpu", dtype=torch.bfloat16):
        warped, ok = warp_backward(image, flow)
        loss = (warped * ok).mean()
    loss.backward()
    assert torch.isfinite(image.grad).all() and torch.isfinite(flow.grad).all()


# --- gradients ---------------------------------------------------------------------------------

def test_gradcheck():
    image = _image(B=2, C=2, H=5, W=6, dtype=torch.float64).div(255).requires_grad_()
    # keep sample points off the integer lattice, where bilinear is not differentiable
    flow = (_flow(B=2, H=5, W=6, scale=1.3, dtype=torch.float64) + 0.37).requires_grad_()
    assert torch.autograd.gradcheck(lambda i, f: warp_backward(i, f)[0], (image, flow))


def test_gradients_finite_out_of_bounds():
    image = _image(C=1, dtype=torch.float64).requires_grad_()
    flow = (_flow(scale=50.0, dtype=torch.float64)).requires_grad_()
    warped, ok = warp_backward(image, flow)
    assert not ok.all()
    warped.sum().backward()
    assert torch.isfinite(image.grad).all() and torch.isfinite(flow.grad).all()


def test_nearest_has_zero_flow_gradient():
    image = _image(C=1).requires_grad_()
    flow = _flow().requires_grad_()
    warp_backward(image, flow, mode="nearest")[0].sum().backward()
    assert flow.grad is None or torch.count_nonzero(flow.grad) == 0
    assert image.grad.abs().sum() > 0


def test_nonfinite_image_rejected():
    """A NaN pixel once reached every output pixel whose bilinear taps touched it."""
    image = _image()
    image[0, 2, 5, 7] = float("nan")
    with pytest.raises(ValueError, match=r"image: expected finite values, got \[nan\]"):
        warp_backward(image, _flow())


@pytest.mark.parametrize("shape", [(1, 3, 0, 4), (1, 3, 4, 0), (2, 1, 0, 0)])
def test_empty_image_rejected(shape):
    """H = 0 once raised an internal error from the sampler."""
    B, _, Hs, Ws = shape
    side = "H" if Hs == 0 else "W"
    with pytest.raises(ValueError, match=rf"image: expected shape \(B, C, H, W\) with {side} >= 1"):
        warp_backward(torch.zeros(shape), torch.zeros(B, 2, Hs, Ws))


@pytest.mark.parametrize("padding_mode", ["zeros", "border"])
def test_in_bounds_gradient_on_the_last_column_and_row_does_not_read_the_padding(padding_mode, dtype):
    """A sample point exactly on the last column (row) is in bounds: its flow gradient is the
    one-sided difference to the pixel before it, whatever the padding (before, it was
    padding - I(W-1): -I(W-1) with zeros, 0 with border)."""
    image = _image(C=2, H=4, W=5, dtype=dtype)
    flow = torch.zeros(1, 2, 4, 5, dtype=dtype, requires_grad=True)
    warped, in_bounds = warp_backward(image, flow, padding_mode=padding_mode)
    assert in_bounds.all()
    assert torch.equal(warped, image)  # the value is unchanged, bit for bit
    (warped * in_bounds).sum().backward()
    du_last = (image[0, :, :, 4] - image[0, :, :, 3]).sum(0)
    dv_last = (image[0, :, 3, :] - image[0, :, 2, :]).sum(0)
    torch.testing.assert_close(flow.grad[0, 0, :, 4], du_last, rtol=0, atol=1e-4)
    torch.testing.assert_close(flow.grad[0, 1, 3, :], dv_last, rtol=0, atol=1e-4)
    # inside, the forward difference as before
    torch.testing.assert_close(flow.grad[0, 0, :, 1], (image[0, :, :, 2] - image[0, :, :, 1]).sum(0),
                               rtol=0, atol=1e-4)


@pytest.mark.parametrize("padding_mode", ["zeros", "border"])
def test_samples_landing_on_the_last_column_take_its_values_and_no_padding_gradient(padding_mode):
    """Flows that send every pixel to the last column and the last row: the values are that
    pixel's, and the image gradient goes to it alone."""
    H, W = 6, 7
    image = _image(C=1, H=H, W=W).requires_grad_()
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32),
                          indexing="ij")
    flow = torch.stack([(W - 1) - u, (H - 1) - v])[None].requires_grad_()
    warped, ok = warp_backward(image, flow, padding_mode=padding_mode)
    assert ok.all() and torch.equal(warped, image[..., H - 1:, W - 1:].expand_as(warped))
    warped.sum().backward()
    expected = torch.zeros_like(image)
    expected[..., H - 1, W - 1] = H * W
    assert torch.equal(image.grad, expected)
    d = image.detach()[0, 0]
    assert torch.allclose(flow.grad[0, 0], (d[H - 1, W - 1] - d[H - 1, W - 2]).expand(H, W))
    assert torch.allclose(flow.grad[0, 1], (d[H - 1, W - 1] - d[H - 2, W - 1]).expand(H, W))


@pytest.mark.parametrize("padding_mode", ["zeros", "border"])
def test_one_pixel_axis_gives_in_bounds_points_no_padding_gradient(padding_mode):
    """On a one-pixel-high image the only in-bounds row is 0, with no neighbour: d/dv is 0."""
    image = _image(C=1, H=1, W=5)
    flow = torch.zeros(1, 2, 1, 5, requires_grad=True)
    warped, ok = warp_backward(image, flow, padding_mode=padding_mode)
    assert ok.all() and torch.equal(warped, image)
    warped.sum().backward()
    assert torch.equal(flow.grad[0, 1], torch.zeros(1, 5))
