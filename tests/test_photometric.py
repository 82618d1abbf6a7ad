"""Tests of fsof_torch.evaluation.photometric: photometric error of a flow (l1, ssim, census)."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from fsof_torch.evaluation.photometric import (
    REPORTED_KINDS,
    PhotometricError,
    census_transform,
    photometric_error,
    photometric_error_map,
    photometric_error_maps,
    photometric_errors,
    to_grey,
)

KINDS = ["l1", "ssim", "census", "soft_census"]
# the differentiable kinds (the census distance counts bits)
SMOOTH_KINDS = ["l1", "ssim", "soft_census"]


def _smooth_image(B=1, H=32, W=48, seed=0, dtype=torch.float32):
    """A textured but smooth image in 0..255 (sums of random sinusoids)."""
    g = torch.Generator().manual_seed(seed)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                          indexing="ij")
    out = torch.zeros(B, 3, H, W, dtype=torch.float64)
    for _ in range(6):
        a = torch.rand(B, 3, 1, 1, generator=g, dtype=torch.float64)
        fu, fv, ph = (torch.rand(3, generator=g, dtype=torch.float64) * torch.tensor([0.5, 0.5, 6.0],
                                                                                     dtype=torch.float64))
        out = out + a * torch.sin(fu * u + fv * v + ph)
    out = (out - out.amin()) / (out.amax() - out.amin()) * 255.0
    return out.to(dtype)


def _shifted_pair(du=2, dv=1, **kw):
    """image2 is image1 moved by (du, dv): the true forward flow is the constant (du, dv)."""
    big = _smooth_image(H=32 + 8, W=48 + 8, **kw)
    image1 = big[..., 4:4 + 32, 4:4 + 48]
    image2 = big[..., 4 - dv:4 - dv + 32, 4 - du:4 - du + 48]
    flow = torch.zeros(image1.shape[0], 2, 32, 48, dtype=image1.dtype)
    flow[:, 0], flow[:, 1] = du, dv
    return image1.contiguous(), image2.contiguous(), flow


# --- smoke -------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
def test_smoke(kind, dtype):
    i1, i2, flow = _shifted_pair(dtype=dtype)
    err = photometric_error(i1, i2, flow, kind=kind)
    assert err.shape == (1,) and err.dtype == dtype and torch.isfinite(err).all()
    emap, valid = photometric_error_map(i1, i2, flow, kind=kind)
    assert emap.shape == (1, 1, 32, 48) and valid.shape == (1, 1, 32, 48) and valid.dtype == torch.bool


def test_public_names():
    import fsof_torch.evaluation.photometric as mod

    assert set(mod.__all__) >= {"photometric_error", "photometric_error_map", "census_transform",
                                "PhotometricError", "photometric_error_maps", "photometric_errors",
                                "REPORTED_KINDS"}
    import fsof_torch

    assert {"photometric_error_maps", "photometric_errors"} <= set(fsof_torch.__all__)



def _luma_reference(rgb: torch.Tensor) -> torch.Tensor:
    """ITU-R 601 luma written out: r w_r, then + g w_g, then + b w_b, each weight rounded to the
    image's dtype (kornia 0.9's order of rounding)."""
    w = [torch.tensor(v, dtype=rgb.dtype) for v in (0.299, 0.587, 0.114)]
    r, g, b = rgb[:, 0:1], rgb[:, 1:2], rgb[:, 2:3]
    return torch.addcmul(torch.addcmul(r * w[0], g, w[1]), b, w[2])


def _kornia_rounds_as_written() -> bool:
    """kornia >= 0.9 rounds r w_r + g w_g + b w_b as the reference does (0.8 adds three products)."""
    import kornia

    return tuple(int(p) for p in kornia.__version__.split(".")[:2]) >= (0, 9)


def test_to_grey_is_the_luma_for_rgb_and_the_image_itself_for_one_channel():
    from kornia.color import rgb_to_grayscale

    rgb = torch.rand(2, 3, 5, 7, generator=torch.Generator().manual_seed(0)) * 255
    assert torch.equal(to_grey(rgb), _luma_reference(rgb))
    weights = torch.tensor([0.299, 0.587, 0.114]).reshape(1, 3, 1, 1)
    assert torch.allclose(to_grey(rgb), (rgb * weights).sum(1, keepdim=True), atol=1e-4)
    # kornia's: bit for bit where it rounds in the same order, else to float32's rounding
    if _kornia_rounds_as_written():
        assert torch.equal(to_grey(rgb), rgb_to_grayscale(rgb))
    torch.testing.assert_close(to_grey(rgb), rgb_to_grayscale(rgb), rtol=1e-6, atol=1e-4)
    grey = rgb[:, :1]
    assert to_grey(grey) is grey
    assert torch.equal(to_grey(rgb[:, :2]), rgb[:, :2].mean(1, keepdim=True))


@pytest.mark.parametrize("channel", [0, 1, 2])
def test_to_grey_into_one_of_the_images_own_channels_reads_the_image_as_it_was(channel):
    """``out`` one of the image's own channels: the luma of the image as given (writing in place
    read the green or blue plane after overwriting it when writing into it), the other channels
    untouched."""
    rgb = torch.rand(2, 3, 9, 13, generator=torch.Generator().manual_seed(3))
    expected = _luma_reference(rgb)
    image = rgb.clone()
    grey = to_grey(image, out=image[:, channel:channel + 1])
    assert grey.data_ptr() == image[:, channel].data_ptr()
    assert torch.equal(grey, expected)
    others = [c for c in range(3) if c != channel]
    assert torch.equal(image[:, others], rgb[:, others])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16, torch.float16])
def test_to_grey_in_place_and_with_autograd_round_the_same(dtype):
    """The in-place conversion (no autograd) and the one with autograd give the written luma
    exactly, in every floating dtype and memory layout (whichever kornia is installed: kornia 0.8
    rounds otherwise, and refuses bfloat16), and ``out`` (one channel of a pair's tensor) is
    written without touching the rest."""
    rgb = (torch.rand(2, 3, 9, 13, generator=torch.Generator().manual_seed(1)) * 255).to(dtype)
    expected = _luma_reference(rgb)
    assert torch.equal(to_grey(rgb), expected)
    assert torch.equal(to_grey(rgb.to(memory_format=torch.channels_last)), expected)
    pair = torch.full((2, 2, 9, 13), 7.0, dtype=dtype)
    before = rgb.clone()
    assert to_grey(rgb, out=pair[:, 1:]).data_ptr() == pair[:, 1:].data_ptr()
    assert torch.equal(pair[:, 1:], expected) and bool((pair[:, 0] == 7).all())
    assert torch.equal(rgb, before)
    with_grad = rgb.clone().requires_grad_()
    grey = to_grey(with_grad)
    assert grey.requires_grad and grey.dtype == dtype and torch.equal(grey.detach(), expected)
    grey.sum().backward()  # d grey / d channel: the weights, as rounded
    w = torch.tensor([0.299, 0.587, 0.114], dtype=dtype).reshape(1, 3, 1, 1)
    assert torch.equal(with_grad.grad, w.expand_as(rgb))
    with pytest.raises(ValueError, match="out: not supported"):
        to_grey(with_grad, out=torch.empty(2, 1, 9, 13, dtype=dtype))
    if _kornia_rounds_as_written():
        from kornia.color import rgb_to_grayscale

        assert torch.equal(expected, rgb_to_grayscale(rgb))


def test_to_grey_of_uint8_rgb_is_opencvs_bit_for_bit():
    """A uint8 RGB image: cv2.cvtColor's COLOR_RGB2GRAY exactly (kornia 0.8 multiplied in uint8,
    which wraps: white came back as 1), also into ``out``; other integer images are refused."""
    import cv2

    gen = torch.Generator().manual_seed(2)
    rgb = torch.randint(0, 256, (2, 3, 11, 17), generator=gen, dtype=torch.uint8)
    rgb[0, :, 0, :8] = torch.tensor([[255, 0, 0, 0, 255, 128, 1, 254], [255, 255, 0, 0, 0, 128, 1, 254],
                                     [255, 0, 255, 0, 0, 128, 1, 254]], dtype=torch.uint8)
    expected = torch.stack([torch.from_numpy(cv2.cvtColor(np.ascontiguousarray(im.permute(1, 2, 0).numpy()),
                                                          cv2.COLOR_RGB2GRAY)) for im in rgb]).unsqueeze(1)
    grey = to_grey(rgb)
    assert grey.dtype == torch.uint8 and torch.equal(grey, expected)
    assert grey[0, 0, 0, :8].tolist() == [255, 150, 29, 0, 76, 128, 1, 254]  # white, green, blue, black, red
    out = torch.zeros(2, 1, 11, 17, dtype=torch.uint8)
    assert to_grey(rgb, out=out) is out and torch.equal(out, expected)
    assert to_grey(rgb[:, :1]) is not None and torch.equal(to_grey(rgb[:, :1]), rgb[:, :1])
    for bad in (rgb.to(torch.int16), rgb[:, :2], torch.zeros(1, 3, 4, 4, dtype=torch.bool)):
        with pytest.raises(TypeError, match=r"^image: expected a floating-point image, or a uint8 one of 1 or 3"):
            to_grey(bad)


def test_module_twin():
    i1, i2, flow = _shifted_pair()
    m = PhotometricError(kind="census")
    assert torch.equal(m(i1, i2, flow), photometric_error(i1, i2, flow, kind="census"))
    assert "census" in repr(m)
    # every option that changes the result is shown (window and census_radius were not)
    assert repr(PhotometricError(kind="ssim", data_range=1.0, window=11, census_radius=2)) == (
        "PhotometricError(kind='ssim', data_range=1, window=11, census_radius=2)")


# --- exceptions --------------------------------------------------------------------------------

def test_range_check_catches_wrong_data_range():
    i1, i2, flow = _shifted_pair()
    with pytest.raises(ValueError, match=r"image1: expected values in \[0, data_range=1\]"):
        photometric_error(i1, i2, flow, data_range=1.0)
    with pytest.raises(ValueError, match="image2: expected values in"):
        photometric_error(i1 / 255, i2, flow, data_range=1.0)
    with pytest.raises(ValueError, match="image1: expected values in"):
        photometric_error(i1 - 128, i2, flow)
    # 0..1 images with the default 0..255 range: refused, not judged as almost black frames
    for call in (lambda: photometric_error(i1 / 255, i2 / 255, flow),
                 lambda: photometric_errors(i1 / 255, i2 / 255, flow),
                 lambda: PhotometricError()(i1 / 255, i2 / 255, flow)):
        with pytest.raises(ValueError, match=r"image1: values in \[.*\] look like 0..1 images, expected 0..255: scale them by 255, or pass data_range=1.0"):
            call()


def test_bad_arguments():
    i1, i2, flow = _shifted_pair()
    with pytest.raises(ValueError, match="kind: expected one of"):
        photometric_error(i1, i2, flow, kind="l2")
    with pytest.raises(ValueError, match="mask: expected shape"):
        photometric_error(i1, i2, flow, torch.ones(1, 1, 32, 47, dtype=torch.bool))
    with pytest.raises(TypeError, match="mask: expected a bool tensor"):
        photometric_error(i1, i2, flow, torch.ones(1, 1, 32, 48))
    with pytest.raises(ValueError, match="image2: expected shape"):
        photometric_error(i1, i2[..., :40], flow)
    with pytest.raises(ValueError, match="window: expected an odd"):
        photometric_error(i1, i2, flow, kind="ssim", window=4)
    with pytest.raises(ValueError, match="data_range: expected a positive"):
        photometric_error(i1, i2, flow, data_range=0.0)
    with pytest.raises(ValueError, match="kind: expected one of"):
        PhotometricError(kind="l2")


# --- cardinality -------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("B", [1, 3])
def test_cardinality(kind, B):
    i1, i2, flow = _shifted_pair(B=B)
    flow = flow + torch.linspace(-1, 1, B).view(B, 1, 1, 1)
    err, count = photometric_error(i1, i2, flow, kind=kind, return_count=True)
    assert err.shape == (B,) and count.shape == (B,) and count.dtype == torch.int64
    for b in range(B):
        one = photometric_error(i1[b:b + 1], i2[b:b + 1], flow[b:b + 1], kind=kind)
        torch.testing.assert_close(one, err[b:b + 1])


# --- feature -----------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
def test_true_flow_gives_zero(kind):
    i1, i2, flow = _shifted_pair(du=3, dv=-2)
    err, count = photometric_error(i1, i2, flow, kind=kind, return_count=True)
    assert count > 0
    assert float(err) < 1e-4
    wrong = photometric_error(i1, i2, torch.zeros_like(flow), kind=kind)
    assert float(wrong) > 100 * max(float(err), 1e-6)


def test_l1_against_hand_computation(dtype):
    i1, i2, flow = _shifted_pair(dtype=dtype)
    flow = flow * 0.5 + 0.3   # non-integer: bilinear
    err, count = photometric_error(i1, i2, flow, return_count=True)
    # independent reference: numpy bilinear sampling, valid = sample point inside the image
    a, b, f = i1[0].double().numpy(), i2[0].double().numpy(), flow[0].double().numpy()
    H, W = a.shape[1:]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = u + f[0], v + f[1]
    ok = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    x0 = np.clip(np.floor(x).astype(int), 0, W - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, H - 2)
    fx, fy = x - x0, y - y0
    warped = (b[:, y0, x0] * (1 - fx) * (1 - fy) + b[:, y0, x0 + 1] * fx * (1 - fy)
              + b[:, y0 + 1, x0] * (1 - fx) * fy + b[:, y0 + 1, x0 + 1] * fx * fy)
    ref = np.abs(a - warped).mean(axis=0)[ok].mean()
    assert int(count) == int(ok.sum())
    tol = {torch.float32: 1e-3, torch.float64: 1e-9}[dtype]
    assert abs(float(err) - ref) < tol


def test_l1_scale_independent_of_data_range():
    i1, i2, flow = _shifted_pair()
    flow = flow * 0.5
    e255 = photometric_error(i1, i2, flow)
    e1 = photometric_error(i1 / 255, i2 / 255, flow, data_range=1.0)
    torch.testing.assert_close(e255, e1, rtol=1e-5, atol=1e-4)
    for kind in ("ssim", "census"):
        torch.testing.assert_close(photometric_error(i1, i2, flow, kind=kind),
                                   photometric_error(i1 / 255, i2 / 255, flow, kind=kind, data_range=1.0),
                                   rtol=1e-4, atol=1e-5)


def test_constant_offset_l1():
    i1 = torch.full((2, 3, 8, 8), 100.0)
    i2 = torch.full((2, 3, 8, 8), 110.0)
    torch.testing.assert_close(photometric_error(i1, i2, torch.zeros(2, 2, 8, 8)), torch.tensor([10.0, 10.0]))


def test_mask_restricts_pixels():
    i1, i2, flow = _shifted_pair()
    mask = torch.zeros(1, 1, 32, 48, dtype=torch.bool)
    mask[..., 10:20, 10:30] = True
    emap, valid = photometric_error_map(i1, i2, torch.zeros_like(flow), mask)
    err, count = photometric_error(i1, i2, torch.zeros_like(flow), mask, return_count=True)
    assert int(count) == 200 and torch.equal(valid, mask)
    torch.testing.assert_close(err, emap[mask].mean().reshape(1))
    assert (emap[~valid] == 0).all()


def test_ssim_against_kornia_on_interior():
    from kornia.metrics import ssim

    i1, i2, flow = _shifted_pair()
    zero = torch.zeros_like(flow)
    emap, valid = photometric_error_map(i1, i2, zero, kind="ssim", window=5)
    ref = ((1 - ssim(i1, i2, 5, max_val=255.0, eps=0.0)) / 2).clamp(0, 1).mean(1, keepdim=True)
    assert valid.all()
    torch.testing.assert_close(emap, ref)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_maps_of_a_crop_equal_those_of_its_copy(dtype):
    """A crop of larger images (a strided view, as the refine job passes) gives the maps of the
    same pixels copied into contiguous memory, bit for bit: every kind takes one path, whatever
    the images' memory layout."""
    g = torch.Generator().manual_seed(2)
    big1, big2 = ((torch.rand(1, 3, 40, 70, generator=g, dtype=torch.float64) * 255).to(dtype) for _ in range(2))
    flow = (torch.randn(1, 2, 30, 50, generator=g, dtype=torch.float64) * 2).to(dtype)
    crop1, crop2 = big1[..., 5:35, 10:60], big2[..., 5:35, 10:60]
    assert not crop1.is_contiguous()
    kinds = ("l1", "ssim", "census", "soft_census")
    views = photometric_error_maps(crop1, crop2, flow, kinds=kinds)
    copies = photometric_error_maps(crop1.contiguous(), crop2.contiguous(), flow, kinds=kinds)
    for kind in kinds:
        assert torch.equal(views[kind][0], copies[kind][0]) and torch.equal(views[kind][1], copies[kind][1]), kind


def test_census_of_constant_and_monotone_images():
    flat = torch.full((1, 1, 9, 9), 50.0)
    assert census_transform(flat, radius=2).abs().max() == 0
    ramp = torch.arange(9.0).repeat(9, 1)[None, None] * 10   # brighter to the right
    t = census_transform(ramp, radius=1)
    assert t.shape == (1, 9, 9, 9)
    # offset (dy, dx) = (0, +1) is channel 5 in row-major 3x3 order: +10 grey levels
    assert float(t[0, 5, 4, 4]) == pytest.approx(10 / np.sqrt(0.81 + 100), rel=1e-6)
    assert float(t[0, 3, 4, 4]) == pytest.approx(-10 / np.sqrt(0.81 + 100), rel=1e-6)



def _np_soft_census_distance(rgb1: np.ndarray, rgb2: np.ndarray, radius: int) -> np.ndarray:
    """UFlow's soft census distance of two RGB images on 0..255 ((3, H, W)), written out: BT.601
    grey levels; per offset of the (2r+1)² window (border replicated) t = δ / sqrt(0.81 + δ²);
    mean over the offsets of d² / (0.1 + d²), d = t1 − t2."""
    H, W = rgb1.shape[-2:]
    k = 2 * radius + 1
    greys = [0.299 * im[0] + 0.587 * im[1] + 0.114 * im[2] for im in (rgb1, rgb2)]
    pads = [np.pad(g, radius, mode="edge") for g in greys]
    total = np.zeros((H, W))
    for dy in range(k):
        for dx in range(k):
            t1, t2 = ((p[dy:dy + H, dx:dx + W] - g) / np.sqrt(0.81 + (p[dy:dy + H, dx:dx + W] - g) ** 2)
                      for p, g in zip(pads, greys))
            d2 = (t1 - t2) ** 2
            total += d2 / (0.1 + d2)
    return total / (k * k)


@pytest.mark.parametrize("radius", [1, 3])
def test_soft_census_against_the_formula_written_out(radius):
    """kind="soft_census" (zero flow: every pixel valid) equals the soft census distance computed
    by hand, on 0..255 images and on the same images on 0..1 with data_range=1."""
    rng = np.random.default_rng(4)
    a = rng.uniform(0, 255, (3, 9, 12))
    b = np.clip(0.6 * a + 0.4 * rng.uniform(0, 255, (3, 9, 12)), 0, 255)
    want = _np_soft_census_distance(a, b, radius)
    assert 0.05 < want.mean() < 0.95
    i1, i2 = torch.from_numpy(a)[None], torch.from_numpy(b)[None]
    flow = torch.zeros(1, 2, 9, 12, dtype=torch.float64)
    for scale, data_range in ((1.0, 255.0), (1 / 255, 1.0)):
        emap, valid = photometric_error_map(i1 * scale, i2 * scale, flow, kind="soft_census",
                                            data_range=data_range, census_radius=radius)
        assert bool(valid.all())
        np.testing.assert_allclose(emap[0, 0].numpy(), want, rtol=1e-9, atol=1e-12)


def test_census_transform_compares_grey_levels_on_the_0_255_scale_for_any_data_range():
    """census_transform of 0..1 images with data_range=1 is that of the same images × 255 with
    data_range=255 (δ in grey levels of 0..255), not that of the 0..1 values."""
    g = torch.Generator().manual_seed(5)
    image = torch.rand(1, 3, 8, 10, generator=g, dtype=torch.float64)
    on_1 = census_transform(image, radius=2, data_range=1.0)
    on_255 = census_transform(image * 255, radius=2, data_range=255.0)
    torch.testing.assert_close(on_1, on_255, rtol=1e-12, atol=1e-12)
    grey = (0.299 * image[0, 0] + 0.587 * image[0, 1] + 0.114 * image[0, 2]) * 255
    delta = grey[3, 5] - grey[4, 4]  # offset (dy, dx) = (-1, +1): channel 1 * 5 + 3 = 8
    assert float(on_1[0, 8, 4, 4]) == pytest.approx(float(delta / torch.sqrt(0.81 + delta ** 2)), rel=1e-12)
    # on 0..1 images compared as they are, the differences would be 255 times smaller
    assert not torch.allclose(on_1, census_transform(image * 255, radius=2, data_range=255.0 * 255.0))

def test_windowed_kinds_erode_out_of_bounds():
    i1, i2, flow = _shifted_pair()
    flow = torch.zeros_like(flow)
    flow[..., :, 40:] = 20.0   # the right columns sample outside the image
    _, v_l1 = photometric_error_map(i1, i2, flow, kind="l1")
    _, v_census = photometric_error_map(i1, i2, flow, kind="census", census_radius=3)
    _, v_ssim = photometric_error_map(i1, i2, flow, kind="ssim", window=7)
    assert (~v_l1).sum() > 0
    assert torch.equal(v_census, v_ssim)
    assert (v_census & ~v_l1).sum() == 0 and (~v_census).sum() > (~v_l1).sum()


# --- empty masks and gradients -----------------------------------------------------------------

@pytest.mark.parametrize("kind", SMOOTH_KINDS)
def test_empty_mask_is_zero_with_count_zero(kind):
    i1, i2, flow = _shifted_pair(B=2)
    flow = flow.clone().requires_grad_()
    mask = torch.ones(2, 1, 32, 48, dtype=torch.bool)
    mask[1] = False
    err, count = photometric_error(i1, i2, flow, mask, kind=kind, return_count=True)
    assert count[1] == 0 and err[1] == 0 and count[0] > 0
    err.sum().backward()
    assert torch.isfinite(flow.grad).all()


@pytest.mark.parametrize("kind", SMOOTH_KINDS)
def test_all_invalid_warp_has_finite_gradient(kind):
    i1, i2, flow = _shifted_pair()
    flow = torch.full_like(flow, 500.0).requires_grad_()
    err, count = photometric_error(i1, i2, flow, kind=kind, return_count=True)
    assert count == 0 and err == 0
    err.sum().backward()
    assert torch.isfinite(flow.grad).all()


@pytest.mark.parametrize("kind", SMOOTH_KINDS)
def test_gradcheck(kind):
    i1, i2, flow = _shifted_pair(dtype=torch.float64)
    i1, i2 = i1[..., :8, :9].contiguous(), i2[..., :8, :9].contiguous()
    flow = (flow[..., :8, :9] * 0.3 + 0.21).clone().requires_grad_()
    window = 3 if kind == "ssim" else 7
    # fast_mode checks a random projection of the Jacobian: the full one takes minutes here
    assert torch.autograd.gradcheck(
        lambda f: photometric_error(i1, i2, f, kind=kind, window=window, census_radius=1), (flow,),
        fast_mode=True)


def test_autocast_bfloat16():
    i1, i2, flow = _shifted_pair()
    ref = photometric_error(i1, i2, flow * 0.5)
    with torch.autocast(device_type="cpu", dtype=torch.bfloat16):
        got = photometric_error(i1, i2, (flow * 0.5))
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, ref)


@pytest.mark.parametrize("half, amp", [(torch.float16, torch.bfloat16), (torch.bfloat16, torch.float16)],
                         ids=["f16-under-bf16", "bf16-under-f16"])
def test_half_images_under_autocast_of_the_other_half_dtype(half, amp):
    """float16 images under bfloat16 autocast (or the reverse) raised torch's RuntimeError
    "Unexpected floating ScalarType in at::autocast::prioritize" from the images' range check
    (autocast's stack refuses the half dtype it does not cast to). Each kind now gives the error
    of the images lifted to float32, as without autocast."""
    i1, i2, flow = _shifted_pair()
    i1, i2 = i1.to(half), i2.to(half)
    for kind in ("l1", "ssim", "census"):
        ref = photometric_error(i1.float(), i2.float(), flow * 0.5, kind=kind)
        with torch.autocast(device_type="cpu", dtype=amp):
            got = photometric_error(i1, i2, flow * 0.5, kind=kind)
        assert got.dtype == torch.float32
        torch.testing.assert_close(got, ref, rtol=0, atol=0)


# --- real data (KITTI 2015 pair 000000) --------------------------------------------------------

def _read_kitti(shared_data):
    from fsof_torch.io import read_image, read_kitti_flow, read_road_mask

    folder = shared_data / "kitti15_000000"
    flow, valid = read_kitti_flow(folder / "flow_noc_10.png")
    road = read_road_mask(folder / "road.json", size=tuple(flow.shape[-2:]))
    image1, image2 = (read_image(folder / name)[None] for name in ("image_10.png", "image_11.png"))
    return image1, image2, flow[None], valid[None], road[None]


def test_kitti_ground_truth_lowers_photometric_error(shared_data):
    i1, i2, flow, valid, road = _read_kitti(shared_data)
    assert i1.shape == (1, 3, 375, 1242)
    assert abs(float(valid.float().mean()) - 0.1620) < 5e-4        # 75 453 valid pixels
    zero, n_zero = photometric_error(i1, i2, torch.zeros_like(flow), valid, return_count=True)
    gt, n_gt = photometric_error(i1, i2, flow, valid, return_count=True)
    # measured: 41.118 over 75 453 px without motion, 16.396 over 75 156 px warped by the truth
    assert int(n_zero) == 75453 and abs(int(n_gt) - 75156) <= 5
    assert abs(float(zero) - 41.12) < 0.05
    assert abs(float(gt) - 16.40) < 0.05
    # on the road polygon the ground truth does better still: 8.54 over 31 053 px
    road_gt, n_road = photometric_error(i1, i2, flow, valid & road, return_count=True)
    assert abs(float(road_gt) - 8.54) < 0.05 and abs(int(n_road) - 31053) <= 5


def test_kitti_dis_photometric_and_endpoint(shared_data):
    """OpenCV DIS (medium preset, grey images): lower photometric error than the ground truth on
    the road, yet 14 px end-point error there: photometric error alone can reward a wrong flow."""
    import cv2

    from fsof_torch.evaluation.metrics import endpoint_error

    i1, i2, flow, valid, road = _read_kitti(shared_data)
    folder = shared_data / "kitti15_000000"
    # cv2.cvtColor, not IMREAD_GRAYSCALE: the two greys differ by 1 level on 44% of the pixels,
    # and DIS's road photometric error moves from 8.35 to 8.85 with it.
    g1 = cv2.cvtColor(cv2.imread(str(folder / "image_10.png")), cv2.COLOR_BGR2GRAY)
    g2 = cv2.cvtColor(cv2.imread(str(folder / "image_11.png")), cv2.COLOR_BGR2GRAY)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow_dis = torch.from_numpy(dis.calc(g1, g2, None)).permute(2, 0, 1)[None]
    road_dis, n_dis = photometric_error(i1, i2, flow_dis, road, return_count=True)
    road_gt = photometric_error(i1, i2, flow, valid & road)
    epe_road = endpoint_error(flow_dis, flow, road, valid)
    # measured (OpenCV 5): DIS 8.353 over 77 952 road px vs the ground truth's 8.541 over 31 053
    # valid road px; DIS's end-point error on the valid road pixels is 14.08 px. The tolerances
    # leave room for other OpenCV versions; the point stays: about the truth's photometric error,
    # yet more than 10 px away from it.
    assert abs(float(road_dis) - 8.35) < 0.6 and abs(int(n_dis) - 77952) < 2000
    assert float(road_dis) < 1.1 * float(road_gt)
    assert abs(float(epe_road) - 14.08) < 2.0


# --- non-finite pixels, data_range, small images ----------------------------------------------

@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("which", ["image1", "image2"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nonfinite_pixels_raise(kind, which, bad):
    """A NaN pixel at a counted pixel once gave a NaN error (all three kinds)."""
    image1, image2, flow = _shifted_pair()
    images = {"image1": image1.clone(), "image2": image2.clone()}
    images[which][0, 1, 10, 20] = bad
    with pytest.raises(ValueError, match=rf"{which}: expected finite pixel values, got \[{bad}\]"):
        photometric_error(images["image1"], images["image2"], flow, kind=kind)


@pytest.mark.parametrize("data_range", [float("nan"), 0.0, -1.0, float("inf"), "255", True])
def test_data_range_must_be_a_positive_finite_number(data_range):
    image1, image2, flow = _shifted_pair()
    err = TypeError if isinstance(data_range, (str, bool)) else ValueError  # (a bool is no number here)
    with pytest.raises(err, match=r"data_range: expected a positive finite number \(the images' maximum"):
        photometric_error(image1, image2, flow, data_range=data_range)
    with pytest.raises(err, match="data_range: expected a positive finite number"):
        PhotometricError(data_range=data_range)
    with pytest.raises(err, match="data_range: expected a positive finite number"):
        census_transform(image1, data_range=data_range)


@pytest.mark.parametrize("size", [(3, 16), (16, 3), (1, 1)])
def test_ssim_on_images_smaller_than_its_window(size):
    """kind='ssim' with H or W < 4 once failed inside kornia's padding."""
    image = _smooth_image(H=16, W=16)[..., : size[0], : size[1]].contiguous()
    flow = torch.zeros(1, 2, *size)
    with pytest.raises(ValueError, match=rf"image1: kind='ssim' with window=7 needs H and W >= 4, "
                                         rf"got shape \(1, 3, {size[0]}, {size[1]}\)"):
        photometric_error(image, image, flow, kind="ssim")
    if min(size) >= 2:  # a window that fits works: identical images have no error
        assert photometric_error(image, image, flow, kind="ssim", window=3).item() == pytest.approx(0.0, abs=1e-6)
    for kind in ("l1", "census"):  # no window padding by reflection: any size
        assert photometric_error(image, image, flow, kind=kind).item() == 0.0


def test_census_distance_is_the_hamming_distance_of_census_bits():
    """Against a census written out here: bits I(q) > I(p) over the 7x7 window, image 1 against
    image 2 warped by the flow, Hamming distance / 48, on pixels whose window stays in bounds."""
    g = torch.Generator().manual_seed(3)
    i1 = torch.rand(1, 1, 20, 24, generator=g, dtype=torch.float64) * 255
    i2 = torch.roll(i1, shifts=2, dims=-1) * 0.8 + 10  # shifted right by 2 px, darker
    flow = torch.zeros(1, 2, 20, 24, dtype=torch.float64)
    flow[:, 0] = 2.0
    err, valid = photometric_error_map(i1, i2, flow, kind="census")
    a = i1[0, 0].numpy()
    w = torch.roll(i2, shifts=-2, dims=-1)[0, 0].numpy()  # image 2 warped back (exact on the interior)

    def bits(x):
        p = np.pad(x, 3, mode="edge")
        return np.stack([p[3 + dy:23 + dy, 3 + dx:27 + dx] > x
                         for dy in range(-3, 4) for dx in range(-3, 4) if (dy, dx) != (0, 0)])

    ref = (bits(a) != bits(w)).sum(0) / 48.0
    v = valid[0, 0].numpy()
    assert v.sum() > 50 and not v[:, -5:].any()  # the window's samples must stay inside image 2
    np.testing.assert_allclose(err[0, 0].numpy()[v], ref[v])
    assert float(err[0, 0][valid[0, 0]].max()) == 0.0  # a monotonic brightness change costs nothing


@pytest.mark.parametrize("radius", [7, 8, 10])
def test_census_distance_of_wide_windows(radius):
    """More than 255 neighbours (radius 8 and up) are counted without overflow: the inverted image
    flips every bit that differs, against a count written out here."""
    g = torch.Generator().manual_seed(5)
    i1 = torch.rand(1, 1, 30, 34, generator=g, dtype=torch.float64) * 255
    i2 = 255 - i1
    err, valid = photometric_error_map(i1, i2, torch.zeros(1, 2, 30, 34, dtype=torch.float64), kind="census",
                                       census_radius=radius)
    a, b = i1[0, 0].numpy(), i2[0, 0].numpy()
    k = 2 * radius + 1

    def bits(x):
        p = np.pad(x, radius, mode="edge")
        return np.stack([p[dy:dy + 30, dx:dx + 34] > x for dy in range(k) for dx in range(k)
                         if (dy, dx) != (radius, radius)])

    ref = (bits(a) != bits(b)).sum(0) / (k * k - 1)
    v = valid[0, 0].numpy()
    assert v.any() and ref[v].mean() > 0.9
    np.testing.assert_allclose(err[0, 0].numpy()[v], ref[v])


def test_census_bits_are_strict_at_ties():
    """A census bit is I(q) > I(p), strictly (the census distance's docstring): on a flat image every
    bit is 0, so a single brighter pixel in image 2 flips one bit of each of the 48 pixels whose
    7 x 7 window holds it (1/48 there) and none of its own (its neighbours are all darker: 0 in
    both). A bit of I(q) >= I(p) would make the flat image all ones, and the bright pixel would
    flip nothing."""
    i1 = torch.full((1, 1, 15, 17), 80.0, dtype=torch.float64)
    i2 = i1.clone()
    i2[..., 7, 8] = 120.0
    err, valid = photometric_error_map(i1, i2, torch.zeros(1, 2, 15, 17, dtype=torch.float64), kind="census")
    ref = torch.zeros(15, 17, dtype=torch.float64)
    ref[4:11, 5:12] = 1 / 48
    ref[7, 8] = 0.0
    v = valid[0, 0]
    assert bool(v[4:11, 5:12].all())
    torch.testing.assert_close(err[0, 0][v], ref[v])


def test_census_distance_beyond_the_int16_count():
    """Radius 91 has 183² - 1 = 33488 neighbours, more than int16 holds (radius 90: 32760): a
    pixel whose every neighbour bit flips has the distance 1.0, not a wrapped-around negative
    count (it was -0.957)."""
    i1 = torch.full((1, 1, 200, 200), 100.0)
    i2 = i1.clone()
    i1[..., 100, 100], i2[..., 100, 100] = 0.0, 255.0  # darkest, then brightest of its window
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # 33488 small shifted comparisons: 3 s on one thread, 30 s on two contending ones
    try:
        err, valid = photometric_error_map(i1, i2, torch.zeros(1, 2, 200, 200), kind="census", census_radius=91)
    finally:
        torch.set_num_threads(threads)
    assert bool(valid[0, 0, 100, 100]) and err[0, 0, 100, 100].item() == 1.0
    assert err[0, 0][valid[0, 0]].min().item() >= 0.0


# --- several kinds at once ---------------------------------------------------------------------

def test_several_kinds_equal_one_kind_at_a_time():
    """One warp for all kinds: each map, validity and mean is what the one-kind call gives."""
    i1, i2, flow = _shifted_pair(B=2)
    flow = flow * 0.7 + 0.3  # not the true flow: errors everywhere
    mask = torch.zeros(2, 1, 32, 48, dtype=torch.bool)
    mask[:, :, 8:30, 5:40] = True
    maps = photometric_error_maps(i1, i2, flow, mask, kinds=KINDS)
    assert list(maps) == KINDS
    errors = photometric_errors(i1, i2, flow, mask, kinds=KINDS, return_count=True)
    for kind in KINDS:
        error, valid = photometric_error_map(i1, i2, flow, mask, kind=kind)
        assert torch.equal(maps[kind][0], error) and torch.equal(maps[kind][1], valid), kind
        mean, count = photometric_error(i1, i2, flow, mask, kind=kind, return_count=True)
        assert torch.equal(errors[kind][0], mean) and torch.equal(errors[kind][1], count), kind
    assert REPORTED_KINDS == ("l1", "ssim", "census")
    assert list(photometric_errors(i1, i2, flow)) == ["l1", "ssim", "census"]


def test_exposure_change_costs_l1_and_ssim_not_census():
    """Image 2 = a gain and bias of image 1, no motion: the census distance is 0 (it sees only the
    order of grey levels), L1 is the mean of |I - (0.6 I + 30)| computed by hand."""
    i1 = _smooth_image(H=24, W=32)
    i2 = i1 * 0.6 + 30.0
    zero = torch.zeros(1, 2, 24, 32)
    errors = photometric_errors(i1, i2, zero)
    assert float(errors["census"]) == 0.0
    assert float(errors["l1"]) == pytest.approx(float((0.4 * i1 - 30.0).abs().mean()), rel=1e-5)
    assert float(errors["ssim"]) > 0.0


def test_kinds_argument_is_checked():
    i1, i2, flow = _shifted_pair()
    with pytest.raises(TypeError, match=r"kinds: expected a non-empty tuple or list of kinds .*got 'census'"):
        photometric_error_maps(i1, i2, flow, kinds="census")
    with pytest.raises(ValueError, match=r"kinds: expected at least one kind from .*, got \(\)"):
        photometric_errors(i1, i2, flow, kinds=())
    with pytest.raises(ValueError, match=r"kinds: expected kinds from .*, got 'l2'"):
        photometric_errors(i1, i2, flow, kinds=("l1", "l2"))
    with pytest.raises(ValueError, match=r"kinds: expected each kind once, got \('l1', 'l1'\)"):
        photometric_errors(i1, i2, flow, kinds=["l1", "l1"])


@pytest.mark.parametrize("radius", [1, 3])
def test_windowed_validity_is_the_in_bounds_map_eroded_by_the_window(radius):
    """A windowed kind counts a pixel only if every sample point of its (2r+1)² window falls in
    image 2; pixels outside the image count as in bounds (the border is padded, not dropped).
    Reference: a max-pool of the out-of-bounds map."""
    import torch.nn.functional as F

    from fsof_torch import warp_backward

    g = torch.Generator().manual_seed(radius)
    i1, i2, _ = _shifted_pair()
    flow = torch.randn(1, 2, 32, 48, generator=g)
    flow[..., 10:14, 20:23] = 60.0  # a patch whose sample points leave the image, and the border
    _, in_bounds = warp_backward(i2, flow)
    ref = F.max_pool2d((~in_bounds).float(), 2 * radius + 1, stride=1, padding=radius) == 0
    _, valid = photometric_error_map(i1, i2, flow, kind="census", census_radius=radius)
    assert 0 < int(valid.sum()) < int(in_bounds.sum())
    assert torch.equal(valid, ref)


@pytest.mark.parametrize("kind", ["l1", "census"])
def test_module_returns_the_count_like_the_function(kind):
    """PhotometricError(..., return_count=True) gives (mean, count); a flow that sends every
    pixel out of image 2 gives the mean 0.0 with the count 0, the flag to check."""
    i1, i2, flow = _shifted_pair(B=2)
    module = PhotometricError(kind=kind)
    mean, count = module(i1, i2, flow, return_count=True)
    ref_mean, ref_count = photometric_error(i1, i2, flow, kind=kind, return_count=True)
    assert torch.equal(mean, ref_mean) and torch.equal(count, ref_count)
    assert count.dtype == torch.int64 and (count > 0).all()
    assert torch.equal(module(i1, i2, flow), ref_mean)  # the default is unchanged: the mean alone
    away = torch.full_like(flow, 100.0)
    mean, count = module(i1, i2, away, return_count=True)
    assert mean.tolist() == [0.0, 0.0] and count.tolist() == [0, 0]


@pytest.mark.parametrize("call, error, match", [
    (lambda i, f: photometric_errors(i, i, f, window=7.0), TypeError, "window: expected an int, got float 7.0"),
    (lambda i, f: photometric_error(i, i, f, kind="ssim", window=True), TypeError, "window: expected an int"),
    (lambda i, f: photometric_errors(i, i, f, census_radius="3"), TypeError, "census_radius: expected an int, got str '3'"),
    (lambda i, f: photometric_error(i, i, f, census_radius=0), ValueError, "census_radius: expected an int >= 1"),
    (lambda i, f: photometric_error(i, i, f, kind=["l1"]), TypeError, r"kind: expected a str, .* got list \['l1'\]"),
    (lambda i, f: photometric_error_map(i, i, f, kind=None), TypeError, "kind: expected a str"),
    (lambda i, f: photometric_errors(i, i, f, kinds=[]), ValueError, r"kinds: expected at least one kind .*got \[\]"),
    (lambda i, f: photometric_errors(i, i, f, return_count="no"), TypeError, "return_count: expected True or False, got str 'no'"),
    (lambda i, f: photometric_error(i, i, f, return_count=1), TypeError, "return_count: expected True or False, got int 1"),
    (lambda i, f: PhotometricError()(i, i, f, return_count="yes"), TypeError, "return_count: expected True or False"),
])
def test_option_types_and_values_are_checked(call, error, match):
    i1, _, flow = _shifted_pair()
    with pytest.raises(error, match=match):
        call(i1, flow)


@pytest.mark.parametrize("options, error, match", [
    ({"kind": "ssim", "window": 8}, ValueError, "window: expected an odd positive int, got 8"),
    ({"window": 7.0}, TypeError, "window: expected an int, got float 7.0"),
    ({"census_radius": 0}, ValueError, "census_radius: expected an int >= 1, got 0"),
    ({"census_radius": "3"}, TypeError, "census_radius: expected an int"),
    ({"kind": ["l1"]}, TypeError, "kind: expected a str"),
    ({"align_corners": "yes"}, TypeError, "align_corners: expected True or False"),
])
def test_module_checks_its_options_at_construction(options, error, match):
    with pytest.raises(error, match=match):
        PhotometricError(**options)


def test_to_grey_and_census_check_their_arguments():
    """to_grey took an unbatched (3, H, W) image as (B=3, C=8) rows and silently averaged them,
    and resized a caller's ``out`` of another shape; census_transform's radius 2.0 was a
    ValueError where every other option of a wrong type is a TypeError."""
    from fsof_torch.evaluation.photometric import to_grey

    image = torch.rand(1, 3, 8, 8) * 255
    with pytest.raises(ValueError, match=r"^image: expected shape \(B, C, H, W\), got \(3, 8, 8\)$"):
        to_grey(image[0])
    with pytest.raises(TypeError, match="^image: expected a tensor, got ndarray$"):
        to_grey(image.numpy())
    out = torch.zeros(1, 1, 4, 4)
    with pytest.raises(ValueError, match=r"^out: expected shape \(B, 1, H, W\) with H=8"):
        to_grey(image, out=out)
    assert out.shape == (1, 1, 4, 4) and not out.any()
    with pytest.raises(TypeError, match="^out: expected the image's dtype torch.float32, got torch.float64$"):
        to_grey(image, out=torch.zeros(1, 1, 8, 8, dtype=torch.float64))
    into = torch.zeros(1, 2, 8, 8)
    assert to_grey(image, out=into[:, :1]).data_ptr() == into.data_ptr()
    # a list failed in an AttributeError, a tensor on another device in torch's error of the
    # product (three channels) or was copied into without a word (one channel)
    with pytest.raises(TypeError, match=r"^out: expected a tensor \(B, 1, H, W\) or None, got list$"):
        to_grey(image, out=[0.0])
    for source in (image, image[:, :1]):
        with pytest.raises(ValueError, match=r"^out: expected the image's device \(cpu\), got meta$"):
            to_grey(source, out=torch.empty(1, 1, 8, 8, device="meta"))
    for radius, error in ((2.0, TypeError), (True, TypeError), (0, ValueError)):
        with pytest.raises(error, match="^radius: expected an int"):
            census_transform(image, radius=radius)


def test_numpy_integer_window_and_radius_work_as_ints():
    """check_int's result was discarded: a NumPy integer window passed the check and failed
    inside kornia ("'numpy.int64' object is not iterable"), in the function and the module."""
    i1, i2, flow = _shifted_pair()
    for kind, options in (("ssim", {"window": 5}), ("census", {"census_radius": 2}),
                          ("soft_census", {"census_radius": 2})):
        want = photometric_error(i1, i2, flow, kind=kind, **options)
        numpy_options = {k: np.int64(v) for k, v in options.items()}
        assert torch.equal(photometric_error(i1, i2, flow, kind=kind, **numpy_options), want), kind
        module = PhotometricError(kind=kind, **numpy_options)
        assert all(type(getattr(module, k)) is int for k in options)
        assert torch.equal(module(i1, i2, flow), want), kind
    maps = photometric_error_maps(i1, i2, flow, kinds=("ssim", "census"), window=np.int32(5),
                                  census_radius=np.int16(2))
    assert torch.equal(maps["ssim"][0], photometric_error_map(i1, i2, flow, kind="ssim", window=5)[0])


def test_census_ignores_gain_bias_and_increasing_grey_changes_not_per_channel_ones():
    """The module docstring's claim, as stated: a gain and bias of a colour image and any
    strictly increasing change of a grey image cost no census distance; a gamma applied to each
    colour channel apart can reorder the luma and does cost (it is not "any monotonic change")."""
    import fsof_torch.evaluation.photometric as module

    g = torch.Generator().manual_seed(5)
    rgb = torch.rand(1, 3, 32, 32, generator=g) * 255
    zero = torch.zeros(1, 2, 32, 32)
    gamma = lambda x: 255 * (x / 255) ** 0.5  # noqa: E731  (strictly increasing)
    assert float(photometric_error(rgb, rgb * 0.5 + 40, zero, kind="census")) == 0.0
    grey = rgb[:, :1].contiguous()
    assert float(photometric_error(grey, gamma(grey), zero, kind="census")) == 0.0
    assert float(photometric_error(rgb, gamma(rgb), zero, kind="census")) > 0.01
    doc = " ".join(module.__doc__.split())
    assert "any monotonic change of brightness" not in doc
    assert "gain and bias" in doc and "strictly increasing change of the grey image" in doc


@pytest.mark.parametrize("kind", KINDS)
def test_images_without_channels_are_refused_not_scored(kind):
    """Images of shape (B, 0, H, W) have nothing to compare: the L1 and soft census errors were
    NaN, the census distance a perfect 0.0 over every pixel and SSIM a RuntimeError from inside
    torch; each now raises a ValueError naming image1, as to_grey and census_transform do."""
    empty, flow = torch.zeros(1, 0, 8, 8), torch.zeros(1, 2, 8, 8)
    with pytest.raises(ValueError, match=r"image1: expected shape \(B, C, H, W\) with C >= 1, got \(1, 0, 8, 8\)"):
        photometric_error(empty, empty, flow, kind=kind)
    with pytest.raises(ValueError, match=r"image: expected shape \(B, C, H, W\) with C >= 1"):
        to_grey(empty)
    with pytest.raises(ValueError, match=r"image: expected shape \(B, C, H, W\) with C >= 1"):
        census_transform(empty)
