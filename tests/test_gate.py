"""ImageGate: the census it judges by, and its decisions on images whose true flow is known."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fsof_torch.refinement.gate import ImageGate, census_ring_distance

RING = [(0, -3), (1, -3), (2, -2), (3, -1), (3, 0), (3, 1), (2, 2), (1, 3),
        (0, 3), (-1, 3), (-2, 2), (-3, 1), (-3, 0), (-3, -1), (-2, -2), (-1, -3)]


def _texture(H=96, W=192, seed=0):
    g = torch.Generator().manual_seed(seed)
    noise = torch.rand(1, 1, H // 4, W // 4, generator=g) * 255
    return F.interpolate(noise, size=(H, W), mode="bicubic", align_corners=False).clamp(0, 255)


@pytest.mark.parametrize("threshold", [2.0, 0.0, 10.0])
def test_census_ring_distance_against_a_loop(threshold):
    # (image 2 is sampled bilinearly: at a whole pixel its value can differ from the pixel's in
    # the last bits, so a difference exactly at the threshold can fall either way; the textures'
    # continuous values make such ties improbable)
    g1, g2 = _texture(seed=1), _texture(seed=2)
    g = torch.Generator().manual_seed(3)
    x = torch.cat([torch.tensor([[10.0, 50.0, 90.0]]), torch.randint(5, 180, (1, 40), generator=g).float()], 1)
    y = torch.cat([torch.tensor([[20.0, 40.0, 60.0]]), torch.randint(5, 84, (1, 40), generator=g).float()], 1)
    flow = torch.randint(-2, 3, (1, 2, 43), generator=g).float()  # whole pixels: no interpolation
    flow[0, :, :3] = torch.tensor([[2.0, -3.0, 0.0], [1.0, 0.0, 4.0]])
    dist, n, ok = census_ring_distance(g1, g2, x, y, flow, threshold=threshold)
    a, b = g1[0, 0].numpy(), g2[0, 0].numpy()
    for i in range(x.shape[1]):
        u, v = int(x[0, i]), int(y[0, i])
        u2, v2 = u + int(flow[0, 0, i]), v + int(flow[0, 1, i])
        clear = differ = 0
        for dx, dy in RING:
            d1 = a[v + dy, u + dx] - a[v, u]
            d2 = b[v2 + dy, u2 + dx] - b[v2, u2]
            if abs(d1) > threshold:
                clear += 1
                t2 = np.sign(d2) if abs(d2) > threshold else 0.0
                differ += int(np.sign(d1) != t2)
        assert int(n[0, i]) == clear
        assert float(dist[0, i]) == pytest.approx(differ / max(clear, 1))
    assert bool(ok.all())




def test_census_ring_neighbour_not_finite_in_image_1_does_not_count():
    """A ring neighbour that is NaN in image 1 has no clear order: it counts neither as clear nor as
    kept (the distance is that of the finite neighbours), and the point is flagged."""
    g1, g2 = _texture(seed=1), _texture(seed=2)
    x, y, flow = torch.tensor([[50.0]]), torch.tensor([[40.0]]), torch.tensor([[[1.0], [-1.0]]])
    bad = g1.clone()
    bad[0, 0, 40 - 3, 50] = float("nan")  # the ring's first neighbour, (0, -3)
    dist, n, ok = census_ring_distance(bad, g2, x, y, flow)
    a, b = g1[0, 0].numpy(), g2[0, 0].numpy()
    clear = differ = 0
    for dx, dy in RING[1:]:
        d1, d2 = a[40 + dy, 50 + dx] - a[40, 50], b[39 + dy, 51 + dx] - b[39, 51]
        if abs(d1) > 2.0:
            clear += 1
            differ += int(np.sign(d1) != (np.sign(d2) if abs(d2) > 2.0 else 0.0))
    assert clear > 0 and int(n) == clear and float(dist) == pytest.approx(differ / clear)
    assert not bool(ok)


def test_census_ring_compares_image_2_in_its_own_dtype():
    """A float16 image 2 beside a float32 image 1: image 2's differences are compared with the
    threshold in float16 (the threshold rounded as they are), as the ternary census of image 2
    alone would: the reference samples image 2 on the same corner-aligned grid (in float32, its
    values rounded to float16) and orders its ring by sign and threshold in its dtype."""
    # (image 2 dim, 0 to 4 grey levels: its float16 differences fall on the threshold's own value)
    g1, g2 = _texture(seed=1), (_texture(seed=2) / 64).half()
    g = torch.Generator().manual_seed(4)
    x = torch.randint(5, 180, (1, 2000), generator=g).float()
    y = torch.randint(5, 84, (1, 2000), generator=g).float()
    flow = torch.rand(1, 2, 2000, generator=g) * 4 - 2
    threshold = 2.05  # (2.05078125 in float16)
    dist, n, _ = census_ring_distance(g1, g2, x, y, flow, threshold=threshold)
    dx, dy = (torch.tensor([0] + [d[k] for d in RING]) for k in (0, 1))
    v1 = g1[0, 0][(y.long() + dy.unsqueeze(-1)), (x.long() + dx.unsqueeze(-1))]  # (17, N)
    d1 = v1[1:] - v1[:1]
    sx, sy = 2.0 / (192 - 1), 2.0 / (96 - 1)
    centre = torch.stack([(x + flow[:, 0]) * sx - 1.0, (y + flow[:, 1]) * sy - 1.0], dim=-1)
    ring = torch.stack([dx * sx, dy * sy], dim=-1).float().unsqueeze(1)
    v2 = F.grid_sample(g2.float(), (centre.unsqueeze(1) + ring).reshape(1, 1, -1, 2), mode="bilinear",
                       padding_mode="border", align_corners=True).reshape(17, -1).half()
    d2 = v2[1:] - v2[:1]
    t2 = torch.where(d2.abs() > threshold, torch.sign(d2), 0.0)
    clear = d1.abs() > threshold
    want = ((torch.sign(d1) != t2) & clear).sum(0).float() / clear.sum(0).clamp_min(1)
    assert torch.equal(n[0], clear.sum(0))
    assert torch.equal(dist[0], want)
    # (the case is one where the dtype matters: compared in float32 some points would differ)
    t32 = torch.where(d2.float().abs() > threshold, torch.sign(d2.float()), 0.0)
    assert not torch.equal(((torch.sign(d1) != t32) & clear).sum(0).float() / clear.sum(0).clamp_min(1), want)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_census_ring_samples_a_half_precision_image_2_at_float32_positions(dtype):
    """Image 2 the same as image 1 (whole grey levels, exact in half precision) and zero flow: the
    distance is 0 at every point, also across a KITTI-wide image, where a normalised position in
    half precision is off by up to half a pixel."""
    H, W = 32, 1242
    g = torch.Generator().manual_seed(0)
    img = F.interpolate(torch.rand(1, 1, H // 2, W // 2, generator=g) * 255, size=(H, W), mode="bicubic",
                        align_corners=False).clamp(0, 255).round()
    ys, xs = torch.meshgrid(torch.arange(4, H - 4), torch.arange(4, W - 4), indexing="ij")
    x, y = xs.reshape(1, -1).float(), ys.reshape(1, -1).float()
    dist, n, ok = census_ring_distance(img, img.to(dtype), x, y, torch.zeros(1, 2, x.shape[1]))
    assert bool(ok.all()) and int((n >= 4).sum()) > 0.9 * x.shape[1]
    assert float(dist.float().abs().max()) == 0.0


def test_census_ring_end_points_of_integer_points_and_a_half_precision_flow_in_float32():
    """Integer coordinates plus a float16 flow: the end point is formed in float32 (was: float16,
    1001 + 0.25 rounded to 1001 on a wide image), the distance as with the flow in float32."""
    H, W = 16, 1100
    g = torch.Generator().manual_seed(3)
    img = F.interpolate(torch.rand(1, 1, H // 2, W // 4, generator=g) * 255, size=(H, W), mode="bicubic",
                        align_corners=False).clamp(0, 255).round()
    # image 2: image 1 resampled a quarter pixel over (sub-pixel detail for the end point to resolve)
    v, u = torch.meshgrid(torch.linspace(-1, 1, H), (torch.arange(W) + 0.25) * 2 / (W - 1) - 1, indexing="ij")
    shifted = F.grid_sample(img, torch.stack([u, v], -1)[None], align_corners=True, padding_mode="border")
    x, y = torch.tensor([[1001, 500]]), torch.tensor([[8, 8]])
    flow = torch.full((1, 2, 2), 0.25)
    flow[:, 1] = 0.0
    half = census_ring_distance(img, shifted, x, y, flow.half())
    single = census_ring_distance(img, shifted, x.float(), y.float(), flow)
    for a, b in zip(half, single):
        assert torch.equal(a.float(), b.float())


def test_census_ring_of_an_empty_batch_is_empty():
    """No samples (B = 0) gives empty results, as the warp and the photometric errors do (it was a
    RuntimeError from a reshape that could not infer a size); each sample of a batch is as alone."""
    g1, g2 = _texture(seed=1), _texture(seed=2)
    x, y = torch.tensor([[10.0, 50.0, 90.0]]), torch.tensor([[20.0, 40.0, 60.0]])
    flow = torch.tensor([[[1.25, -2.5, 0.0], [0.5, 3.0, -1.0]]])
    for got in census_ring_distance(g1[:0], g2[:0], x[:0], y[:0], flow[:0]):
        assert got.shape == (0, 3)
    both = census_ring_distance(torch.cat([g1, g2]), torch.cat([g2, g1]), x.repeat(2, 1), y.repeat(2, 1),
                                flow.repeat(2, 1, 1))
    for b, (one_image_1, one_image_2) in enumerate(((g1, g2), (g2, g1))):
        for got, want in zip(both, census_ring_distance(one_image_1, one_image_2, x, y, flow)):
            assert torch.equal(got[b:b + 1], want)


def test_census_ring_reads_image_1_at_whole_pixels():
    g1, g2 = _texture(seed=1), _texture(seed=2)
    x, y = torch.tensor([[10.0, 50.0]]), torch.tensor([[20.0, 40.0]])
    flow = torch.tensor([[[1.25, -2.5], [0.5, 3.0]]])
    whole = census_ring_distance(g1, g2, x, y, flow)
    # a fraction of the point is dropped for image 1; image 2 is still read at x + flow
    frac = census_ring_distance(g1, g2, x + 0.75, y + 0.5, flow - torch.tensor([0.75, 0.5]).reshape(1, 2, 1))
    for a, b in zip(whole, frac):
        assert torch.allclose(a.float(), b.float(), atol=1e-6)

def test_census_ring_points_count_only_with_all_samples_inside_both_images():
    g1, g2 = _texture(seed=1), _texture(seed=2)
    H, W = g1.shape[-2:]
    x = torch.tensor([[2.0, 3.0, W - 4.0, W - 3.0, 50.0, 50.0, 50.0, 50.0]])
    y = torch.tensor([[40.0, 40.0, 40.0, 40.0, 2.0, 3.0, H - 4.0, H - 3.0]])
    for fx, fy in ((0.0, 0.0), (1.5, -0.5), (-2.25, 1.0)):
        flow = torch.tensor([fx, fy]).reshape(1, 2, 1).expand(1, 2, x.shape[1])
        _, _, ok = census_ring_distance(g1, g2, x, y, flow)
        for i in range(x.shape[1]):
            u, v = float(x[0, i]), float(y[0, i])
            inside = all(0 <= u + dx <= W - 1 and 0 <= v + dy <= H - 1
                         and 0 <= u + dx + fx <= W - 1 and 0 <= v + dy + fy <= H - 1
                         for dx, dy in [(0, 0)] + list(RING))
            assert bool(ok[0, i]) == inside, (u, v, fx, fy)

def _smooth_noise(amplitude, seed=0, H=96, W=192):
    """A flow error that varies smoothly over the image, as a network's does (B, 2, H, W)."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 2, H // 16, W // 16, generator=g) * 2 - 1
    return amplitude * F.interpolate(coarse, size=(H, W), mode="bilinear", align_corners=False)


def _pair(shift=3):
    """image2 is image1 moved right by ``shift`` pixels: the true flow is (shift, 0)."""
    g1 = _texture()
    g2 = torch.roll(g1, shifts=shift, dims=-1)
    true = torch.zeros(1, 2, *g1.shape[-2:])
    true[:, 0] = shift
    return g1, g2, true


def test_the_gate_keeps_the_prediction_where_the_model_is_wrong():
    g1, g2, true = _pair()
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 10:-10, 10:-10] = True
    model = true.clone()
    model[..., 40:70, 100:150] += torch.tensor([4.0, -3.0]).reshape(1, 2, 1, 1)  # the model wrong here
    prediction = true + _smooth_noise(2.0)
    out = ImageGate(grid=(4, 8))(g1, g2, prediction, model, mask)
    assert bool(out.confirmed.all()) and bool(out.model_used.all())
    wrong = torch.zeros_like(mask)
    wrong[..., 40:70, 100:150] = True
    # the region where the model is wrong keeps the prediction; most of the rest takes the model
    assert not bool((out.use_model & wrong)[..., 45:65, 105:145].any())
    assert float(out.use_model[mask & ~wrong].float().mean()) > 0.8
    assert not bool(out.use_model[~mask].any())
    assert 0.0 < float(out.textured) <= 1.0


def test_images_without_evidence_leave_the_prediction():
    g1, _, true = _pair()
    mask = torch.ones(1, 1, 96, 192, dtype=torch.bool)
    # image 2 unrelated to image 1: no flow explains it, the census is noise for both
    noise = _texture(seed=7)
    out = ImageGate()(g1, noise, true, true.clone(), mask)
    assert not bool(out.informative.any()) and not bool(out.confirmed.any())
    assert not bool(out.model_used.any()) and not bool(out.use_model.any())
    loose = ImageGate(require_evidence=False)(g1, noise, true, true.clone(), mask)
    assert bool(loose.model_used.all()) and bool(loose.use_model.all())


def test_a_better_prediction_that_does_not_explain_the_images_does_not_keep_a_sample():
    """Over a sample's mask the prediction is kept only where it is significantly better AND
    explains the images itself (mean distance at most ``occlusion``): under heavy noise the right
    shift is far better than the zero model, yet its distance, about 0.46, is above 0.35; without
    ``require_evidence`` (which would hide the test: such a sample is not informative) the model's
    geometry stands. With ``occlusion`` above that distance the prediction is kept."""
    g = torch.Generator().manual_seed(0)
    H, W = 64, 96
    image1 = torch.rand(1, 1, H, W, generator=g) * 255
    image2 = (torch.roll(image1, 3, dims=-1) + 200.0 * torch.randn(1, 1, H, W, generator=g)).clamp(0, 255)
    pred, model = torch.zeros(1, 2, H, W), torch.zeros(1, 2, H, W)
    pred[:, 0] = 3.0
    mask = torch.zeros(1, 1, H, W, dtype=torch.bool)
    mask[..., 8:-8, 8:-8] = True
    out = ImageGate(objects=False, require_evidence=False)(image1, image2, pred, model, mask)
    assert 0.4 < float(out.cost_prediction[0]) < float(out.cost_model[0]) - 0.08
    assert bool(out.model_used[0]) and int(out.use_model.sum()) > 0.9 * int(mask.sum())
    loose = ImageGate(objects=False, require_evidence=False, occlusion=0.6)(image1, image2, pred, model, mask)
    assert not bool(loose.model_used[0]) and not bool(loose.use_model.any())


def test_a_handful_of_points_is_no_evidence():
    """A mask of a few points (fewer than ``min_points`` count) is not informative: a wrong model
    does not replace a right prediction there (was: with two or three points their standard
    error was so large that the model, worse on each, was used); with enough points it is found
    worse."""
    g1, g2, true = _pair()
    g2 = g2 + 8 * torch.randn(g2.shape, generator=torch.Generator().manual_seed(0))  # (sensor noise)
    model = true + torch.tensor([4.0, -3.0]).reshape(1, 2, 1, 1)
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 30:60, 40:150] = True
    for points, informative in ((2, False), (3, False), (11, False), (6000, True)):
        out = ImageGate(points=points)(g1, g2, true, model, mask)
        assert bool(out.informative[0]) == informative, points
        assert not bool(out.model_used[0]) and not bool(out.use_model.any())
        assert float(out.cost_model[0]) > float(out.cost_prediction[0])
    assert int(ImageGate(points=11)(g1, g2, true, model, mask).points[0]) == 11


def test_a_handful_of_points_does_not_confirm_the_model():
    """Image 2 unrelated to image 1 (no flow explains it) and a mask of two pixels: the model's
    census distance fell below the prediction's at both by chance in 14 of 40 draws, their
    standard error (two points) did not show it, and the images "confirmed" the model, which
    replaced the prediction. Fewer than ``min_points`` points confirm nothing, as they inform
    nothing; with enough points that confirm it, the model is confirmed (and used)."""
    g1, _, true = _pair()
    model = torch.zeros_like(true)
    for s in range(40):
        mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
        mask[..., 10 + s, 20 + 3 * s:22 + 3 * s] = True
        out = ImageGate()(g1, _texture(seed=100 + s), true, model, mask)
        assert int(out.points[0]) == 2, s
        assert not bool(out.confirmed[0]) and not bool(out.informative[0]), s
        assert not bool(out.model_used[0]) and not bool(out.use_model.any()), s
    # the images of a rigid shift: 12 points that confirm a right model over a wrong prediction
    g1, g2, true = _pair()
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 40, 20:180] = True
    wrong = true + torch.tensor([4.0, -3.0]).reshape(1, 2, 1, 1)
    for points, confirmed in ((11, False), (12, True)):
        out = ImageGate(points=points)(g1, g2, wrong, true, mask)
        assert int(out.points[0]) == points and float(out.cost_model[0]) == 0.0
        assert bool(out.confirmed[0]) == confirmed and bool(out.model_used[0]) == confirmed, points


def test_a_model_as_good_as_the_prediction_is_used():
    g1, g2, true = _pair()
    mask = torch.ones(1, 1, 96, 192, dtype=torch.bool)
    out = ImageGate()(g1, g2, true, true.clone(), mask)  # both explain the images
    assert bool(out.informative.all()) and not bool(out.confirmed.any())
    assert bool(out.model_used.all()) and bool(out.use_model.all())



def _wrong_at(true, pixels):
    """``true`` with the flow off by (4, -3) px at the given (row, column) pixels."""
    wrong = true.clone()
    for r, c in pixels:
        wrong[..., r, c] += torch.tensor([4.0, -3.0])
    return wrong


def _block_error(delta, x, y, block=16):
    """The standard error of the mean of ``delta`` (n,) at pixels (x, y) from the sums of its
    16 x 16 pixel blocks: sum_b (S_b - n_b mean)^2 / n^2 times G / (G - 1), G blocks holding
    points (0 for a single block)."""
    _, b = np.unique(np.stack([y // block, x // block]), axis=1, return_inverse=True)
    S = np.bincount(b.ravel(), weights=delta - delta.mean())
    G = S.size
    return np.sqrt((S ** 2).sum() / delta.size ** 2 * G / max(G - 1, 1))


def _mean_and_standard_error(g1, g2, mask, prediction, model):
    """The mean of d_model − d_pred (census_ring_distance) over the mask's points that count (in
    both images for both flows, at least 4 clear neighbours) and its standard error: the larger of
    std / sqrt(n) and the blocks' (:func:`_block_error`), with the costs of both flows."""
    W = g1.shape[-1]
    pix = mask.reshape(-1).nonzero().squeeze(1)
    x, y = (pix % W).float()[None], torch.div(pix, W, rounding_mode="floor").float()[None]
    d_pred, n, ok_pred = census_ring_distance(g1, g2, x, y, prediction.reshape(1, 2, -1)[:, :, pix])
    d_model, _, ok_model = census_ring_distance(g1, g2, x, y, model.reshape(1, 2, -1)[:, :, pix])
    count = (ok_pred & ok_model & (n >= 4))[0]
    delta = (d_model - d_pred)[0, count].double().numpy()
    se = max(delta.std() / np.sqrt(delta.size),
             _block_error(delta, x[0, count].long().numpy(), y[0, count].long().numpy()))
    return delta.mean(), se, float(d_model[0, count].mean()), float(d_pred[0, count].mean())


@pytest.mark.parametrize("bad, significant", [([(30, 50), (60, 120)], False),
                                              ([(30, 50), (60, 120), (50, 80), (40, 140), (70, 30), (20, 100)], True)])
def test_the_z_test_decides_whether_a_slightly_worse_model_is_used(bad, significant):
    """The model is worse than the prediction at a few pixels only: its mean census disadvantage
    is positive but, for two pixels, within z = 2 standard errors, so ImageGate(z=2) still uses
    it while ImageGate(z=0) keeps the prediction; at six pixels the disadvantage exceeds 2 standard
    errors and z=2 keeps the prediction as well. The mean and its standard error are computed here
    from census_ring_distance, at every mask pixel (``points`` above the mask's size)."""
    g1, g2, true = _pair()
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 10:-10, 10:-10] = True
    model = _wrong_at(true, bad)
    mean, se, cost_model, cost_pred = _mean_and_standard_error(g1, g2, mask, true, model)
    assert mean > 0 and (mean > 2 * se) == significant
    for z, used in ((2.0, not significant), (0.0, False)):
        out = ImageGate(z=z, objects=False, points=20000)(g1, g2, true, model, mask)
        assert float(out.cost_model) == pytest.approx(cost_model, rel=1e-5)
        assert float(out.cost_prediction) == pytest.approx(cost_pred, abs=1e-7)
        assert bool(out.informative.all()) and not bool(out.confirmed.any())
        assert bool(out.model_used.all()) == used, z
        assert bool(out.use_model[mask].all()) == used and not bool(out.use_model[~mask].any()), z


def test_the_z_test_decides_whether_a_slightly_better_model_is_confirmed():
    """The prediction is worse than the model at two pixels only: the model's advantage is within
    z = 2 standard errors (computed here), so ImageGate(z=2) does not confirm the model and
    ImageGate(z=0) does; both use it (the images are informative)."""
    g1, g2, true = _pair()
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 10:-10, 10:-10] = True
    prediction = _wrong_at(true, [(30, 50), (60, 120)])
    mean, se, _, _ = _mean_and_standard_error(g1, g2, mask, prediction, true)
    assert 0 < -mean < 2 * se
    for z, confirmed in ((2.0, False), (0.0, True)):
        out = ImageGate(z=z, objects=False, points=20000)(g1, g2, prediction, true, mask)
        assert bool(out.confirmed.all()) == confirmed, z
        assert bool(out.model_used.all()) and bool(out.use_model[mask].all())


def test_evidence_from_one_patch_counts_as_its_blocks_not_its_points():
    """The prediction is wrong in one patch of 16 x 32 pixels (two of the standard error's
    blocks) and exact elsewhere, as is the model. Its many points there would make the model's
    advantage significant at z = 2 as independent points (computed here), but neighbouring points
    share their census rings and image content: the blocks' error is the larger one, and at z = 2
    the model is not confirmed; at z = 1 it is (both from the reference here)."""
    g1, g2, true = _pair()
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 8:-8, 8:-8] = True
    prediction = true.clone()
    prediction[..., 32:48, 64:96] += torch.tensor([4.0, -3.0]).reshape(1, 2, 1, 1)
    mean, se, _, _ = _mean_and_standard_error(g1, g2, mask, prediction, true)
    pix = mask.reshape(-1).nonzero().squeeze(1)
    x, y = (pix % 192).float()[None], torch.div(pix, 192, rounding_mode="floor").float()[None]
    d_pred, n, ok_pred = census_ring_distance(g1, g2, x, y, prediction.reshape(1, 2, -1)[:, :, pix])
    d_model, _, ok_model = census_ring_distance(g1, g2, x, y, true.reshape(1, 2, -1)[:, :, pix])
    delta = (d_model - d_pred)[0, (ok_pred & ok_model & (n >= 4))[0]].double().numpy()
    assert -mean > 2 * delta.std() / np.sqrt(delta.size)  # significant as independent points
    assert -mean < 2 * se and -mean > 1 * se
    for z, confirmed in ((2.0, False), (1.0, True)):
        out = ImageGate(z=z, objects=False, points=20000)(g1, g2, prediction, true.clone(), mask)
        assert bool(out.confirmed.all()) == confirmed, z
        assert bool(out.informative.all()) and bool(out.model_used.all())


def _object_pair():
    """The textured pair with an object of 20 x 24 pixels moving by (-2, 0), image2 showing it
    there; the prediction has the object's flow and a smooth error elsewhere."""
    g1, g2, true = _pair()
    obj = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    obj[..., 50:70, 60:84] = True
    g2 = g2.clone()
    g2[..., 50:70, 58:82] = g1[..., 50:70, 60:84]
    prediction = torch.where(obj, torch.tensor([-2.0, 0.0]).reshape(1, 2, 1, 1), true + _smooth_noise(2.0))
    return g1, g2, true, obj, prediction


def test_a_small_object_keeps_its_flow():
    g1, g2, true, obj, prediction = _object_pair()
    mask = torch.ones_like(obj)
    out = ImageGate(grid=(2, 4))(g1, g2, prediction, true.clone(), mask)
    # the object keeps the prediction although its cell is mostly background
    assert not bool((out.use_model & obj)[..., 53:67, 63:81].any())
    coarse = ImageGate(grid=(2, 4), objects=False)(g1, g2, prediction, true.clone(), mask)
    assert bool((coarse.use_model & obj).any())



@pytest.mark.parametrize("rows, cols", [((0, 70), (0, 84)), ((50, 96), (60, 192))])
def test_an_object_at_the_corner_of_the_masks_box_keeps_its_flow(rows, cols):
    # (the object's last row and column are the mask's last, or its first ones the mask's first:
    # the regions are found over the mask's bounding box, which must take them in whole)
    g1, g2, true, obj, prediction = _object_pair()
    mask = torch.zeros_like(obj)
    mask[..., rows[0]:rows[1], cols[0]:cols[1]] = True
    # (one cell, mostly background: the cell alone uses the model on the object)
    out = ImageGate(grid=(1, 1))(g1, g2, prediction, true.clone(), mask)
    assert bool(ImageGate(grid=(1, 1), objects=False)(g1, g2, prediction, true.clone(), mask).use_model[obj].all())
    assert not bool((out.use_model & obj).any())  # (all of it, its first and last rows and columns too)


def test_a_small_object_keeps_its_flow_in_a_mask_over_part_of_a_batch():
    g1, g2, true, obj, prediction = _object_pair()
    # frame 0: a mask around the object; frame 1: the same images without the object in its mask
    mask = torch.zeros(2, 1, 96, 192, dtype=torch.bool)
    mask[0, :, 30:90, 40:150] = True
    mask[1, :, 5:45, 100:190] = True
    out = ImageGate(grid=(2, 4))(g1.expand(2, -1, -1, -1), g2.expand(2, -1, -1, -1),
                                 prediction.expand(2, -1, -1, -1), true.expand(2, -1, -1, -1).clone(), mask)
    assert not bool((out.use_model[:1] & obj)[..., 53:67, 63:81].any())
    assert not bool((out.use_model & ~mask).any())
    alone = ImageGate(grid=(2, 4))(g1, g2, prediction, true.clone(), mask[:1])
    assert torch.equal(out.use_model[:1], alone.use_model)
    assert bool(out.use_model[1, :, 5:45, 100:190].float().mean() > 0.9)

def _cells_without_the_model(out, grid):
    """(B, rows, columns) bool: the cells where the model is used at no pixel."""
    B, _, H, W = out.use_model.shape
    rows, cols = grid
    ch, cw = -(-H // rows), -(-W // cols)
    used = F.pad(out.use_model.to(torch.uint8), (0, cols * cw - W, 0, rows * ch - H))
    return used.reshape(B, rows, ch, cols, cw).amax(dim=(2, 4)) == 0


def test_an_object_region_does_not_overrule_the_evidence_of_its_parts():
    """One connected region where the flows differ by 1.5 px over the whole mask: left of column
    100 the model is wrong (the prediction exact), right of it the prediction is wrong. The
    prediction wins on the region's average, yet the cells on the right, whose own points favour
    the model by far, use the model (once the region kept the prediction everywhere); on the left
    the prediction is kept; cells_kept counts the cells without a pixel of the model."""
    g1, g2, true = _pair()
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 12:84, 12:180] = True  # cells 1 to 6 of 8 rows, 1 to 14 of 16 columns, whole
    prediction, model = true.clone(), true.clone()
    model[:, 0, :, :100] += 1.5
    prediction[:, 0, :, 100:] += 1.5
    columns = torch.arange(192)
    right, left = mask & (columns >= 108), mask & (columns < 96)
    out = ImageGate()(g1, g2, prediction, model, mask)
    assert bool(out.model_used.all()) and int(out.cells) == 6 * 14
    assert bool(out.use_model[right].all())
    assert not bool(out.use_model[left].any())
    kept = _cells_without_the_model(out, (8, 16))[:, 1:7, 1:15]
    assert int(out.cells_kept) == int(kept.sum()) >= 6 * 7  # (the 7 columns of cells left of column 96)


def test_the_cells_kept_count_the_cells_an_object_region_keeps_whole():
    """Image 2 noisy and few points: the model, 0.6 px wrong on the left half, is not shown worse
    in most of the left cells alone, but the left half, an object region, keeps the prediction
    as a whole. The cells it keeps whole are counted in cells_kept (once only the cells' own
    decisions were, and cells_kept said 3 while the model was used in none of the 16 left cells)."""
    g1, g2, true = _pair()
    g2 = g2 + 15 * torch.randn(g2.shape, generator=torch.Generator().manual_seed(1))
    mask = torch.ones(1, 1, 96, 192, dtype=torch.bool)
    prediction, model = true.clone(), true.clone()
    model[:, 0, :, :96] += 0.6
    prediction[:, 0, :, 96:] += 0.45  # (below object_px: the left half is a region of its own)
    left = mask & (torch.arange(192) < 96)
    options = dict(grid=(4, 8), object_px=0.5, points=500)
    cells = ImageGate(objects=False, **options)(g1, g2, prediction, model, mask)
    out = ImageGate(**options)(g1, g2, prediction, model, mask)
    assert bool(out.model_used.all()) and float(cells.use_model[left].float().mean()) > 0.5
    assert not bool(out.use_model[left].any())
    without = int(_cells_without_the_model(out, (4, 8)).sum())
    # every cell with enough points and no pixel of the model; (32 - cells) cells have too few
    assert without - (32 - int(out.cells)) <= int(out.cells_kept) <= without
    assert int(out.cells_kept) >= int(cells.cells_kept) + 10


def test_a_prediction_that_cannot_be_judged_loses_to_a_model_that_explains_the_images():
    """A prediction that is NaN, or whose end points leave image 2, where the model explains the
    images: the model wins there (the points counted only where both flows could be judged:
    none, so the images were not informative and the sample kept its prediction)."""
    g1, g2, true = _pair()
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 8:-8, 8:-8] = True
    plain = ImageGate()(g1, g2, true, true.clone(), mask)
    # (also just past the last pixel centre, half a pixel beyond column W - 1 or row H - 1: outside
    # the image's samples, which span the pixel centres 0..W - 1 and 0..H - 1)
    u, v = torch.arange(192.0).expand(96, 192), torch.arange(96.0).unsqueeze(1).expand(96, 192)
    just_right = torch.stack([191.5 - u, torch.zeros_like(u)]).unsqueeze(0)
    just_below = torch.stack([torch.zeros_like(v), 95.5 - v]).unsqueeze(0)
    for bad in (torch.full_like(true, float("nan")), true + torch.tensor([5000.0, 0.0]).reshape(1, 2, 1, 1),
                true - torch.tensor([0.0, 200.0]).reshape(1, 2, 1, 1), just_right, just_below):
        prediction = torch.where(mask, bad, true)
        out = ImageGate()(g1, g2, prediction, true.clone(), mask)
        assert int(out.points) == int(plain.points) > 0
        assert float(out.cost_model) == 0.0 and float(out.cost_prediction) == pytest.approx(0.35)
        assert bool(out.informative.all()) and bool(out.confirmed.all()) and bool(out.model_used.all())
        assert bool(out.use_model[mask].all()) and int(out.cells_kept) == 0
    # half of the mask lost, the other half judged by both flows (both exact there): the model
    half = torch.where(mask & (torch.arange(192) < 96), float("nan"), true)
    out = ImageGate()(g1, g2, half, true.clone(), mask)
    assert 0.15 < float(out.cost_prediction) < 0.2 and float(out.cost_model) == 0.0
    assert bool(out.use_model[mask].all())


def test_a_prediction_lost_everywhere_leaves_it_to_the_model_whether_the_images_inform():
    """A finite prediction whose end points leave image 2 at every point (5000 px off) counts each
    point at ``occlusion`` exactly, so it "explained" the images by construction: on image 2
    unrelated to image 1 (no flow explains them) the sample was reported informative, and with a
    margin that keeps the model from being shown worse the model replaced the prediction on its own
    word. Where the prediction is lost everywhere, the model alone says whether the images inform:
    here they do not, and the prediction stays; beside a model that explains them, they do."""
    g1, g2, true = _pair()
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 8:-8, 8:-8] = True
    lost = true + torch.tensor([5000.0, 0.0]).reshape(1, 2, 1, 1)
    unrelated = _texture(seed=7)
    out = ImageGate(margin=0.3)(g1, unrelated, lost, true.clone(), mask)
    assert int(out.points) > 1000 and float(out.cost_prediction) == pytest.approx(0.35)
    assert float(out.cost_model) > 0.45  # (the model explains nothing either)
    assert not bool(out.informative.any()) and not bool(out.confirmed.any())
    assert not bool(out.model_used.any()) and not bool(out.use_model.any())
    # the same prediction beside a model that explains the images: informative, and the model is used
    out = ImageGate(margin=0.3)(g1, g2, lost, true.clone(), mask)
    assert float(out.cost_model) == 0.0
    assert bool(out.informative.all()) and bool(out.model_used.all()) and bool(out.use_model[mask].all())


def test_a_non_finite_prediction_never_wins_its_points_on_images_the_exact_flow_explains_poorly():
    """Dim, noisy frames (texture and noise of 20 grey levels): even the exact flow's census
    distance is above ``occlusion``, as on real road (the shared KITTI pair's ground truth: 0.43).
    Half the prediction NaN, the rest 1 px off, the model exact: a NaN point took the distance
    ``occlusion``, below the exact model's, so the NaN half spoke for the prediction and the model
    was refused over the whole sample (the refiner then returned the NaN inside the road). A
    non-finite prediction never explains a point better than the model: the model is used."""
    H, W = 96, 192
    g = torch.Generator().manual_seed(6)
    big = _texture(H, W + 4, seed=5) * (20 / 255)
    image1 = big[..., 2:W + 2] + torch.randn(1, 1, H, W, generator=g) * 20
    image2 = big[..., :W] + torch.randn(1, 1, H, W, generator=g) * 20
    model = torch.zeros(1, 2, H, W)
    model[:, 0] = 2.0  # exact: image 1's x is image 2's x + 2
    prediction = model.clone()
    prediction[:, 0] += 1.0
    prediction[..., : W // 2] = float("nan")
    mask = torch.ones(1, 1, H, W, dtype=torch.bool)
    out = ImageGate()(image1, image2, prediction, model, mask)
    assert float(out.cost_model) > 0.4  # (the exact flow does not explain these images by the threshold)
    assert float(out.cost_prediction) > float(out.cost_model)
    assert bool(out.model_used.all()) and bool(out.confirmed.all())
    assert bool(out.use_model[..., : W // 2].all())


def test_a_prediction_nan_in_part_on_the_real_pair_is_refined_not_returned(shared_data, kitti15_ground_truth):
    """The shared KITTI pair, the ground truth as the prediction with a block of the road (rows
    250 on, columns 400 to 700: two fifths of the mask) NaN, as a network's invalid region: the
    road's census distance there is above ``occlusion`` for any flow (0.47 for the model), so
    the NaN block, taken at ``occlusion``, spoke for the prediction; the sample was left
    unchanged with the NaN inside the road. The model now replaces it."""
    import warnings

    from fsof_torch import refine_flow
    from fsof_torch.io import read_image

    camera, flow, _, road = kitti15_ground_truth
    images = tuple(read_image(shared_data / "kitti15_000000" / n)[None] for n in ("image_10.png", "image_11.png"))
    prediction = flow.float()
    prediction[..., 250:, 400:700] = float("nan")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = refine_flow(prediction, road, camera, images=images)
    assert bool(out.refined.all()) and bool(out.gate.model_used.all())
    assert bool(torch.isfinite(out.flow)[road.expand(-1, 2, -1, -1)].all())


def test_a_right_prediction_leaving_the_frame_is_not_overruled_by_a_wrong_model_inside():
    """Near the border a right flow leaves image 2 while a wrong model stays inside and explains
    nothing there: the unjudgeable prediction counts as just explaining its points (the
    occlusion threshold), so the wrong model does not win them."""
    g1, g2, true = _pair(shift=24)
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 8:-8, 192 - 24:-1] = True  # every true end point leaves image 2
    model = torch.zeros_like(true)  # wrong by 24 px, inside the image
    out = ImageGate()(g1, g2, true, model, mask)
    assert int(out.points) > 0 and float(out.cost_model) > 0.35
    assert float(out.cost_prediction) == pytest.approx(0.35)
    assert not bool(out.use_model.any())


@pytest.mark.parametrize("judge, options, strips", [
    # (the strip alone: the prediction lost everywhere, the model explaining nothing, the images do
    # not inform; without require_evidence the cell decides)
    ("cell", dict(objects=False, require_evidence=False), [(185, 19)]),
    ("region", dict(min_points=10 ** 6, require_evidence=False), [(168, 40), (175, 60), (180, 80), (185, 30)]),
    ("sample", dict(min_points=10 ** 6, require_evidence=False, objects=False),
     [(175, 20), (180, 30), (185, 56), (185, 65)])])
def test_a_prediction_leaving_the_frame_everywhere_just_explains_its_points_whatever_their_number(judge, options,
                                                                                                  strips):
    """A right prediction whose end points all leave image 2 (each point's distance taken as
    ``occlusion``) in a strip at the right edge (columns from the first number to 190, rows 8 to
    the second), a model wrong by 24 px inside it: whether the prediction explains a cell, an
    object region or the sample's mask is its mean distance at most ``occlusion``, and the mean
    of n equal distances rounds above that value for some n in float32 (44 points: 0.35000002).
    These strips took the wrong model: the cell's (one cell over the mask), the region's (beside
    a block where the model is right and the prediction 2 px off, which the sample and its cell
    take; ``min_points`` beyond reach leaves the cell to follow the sample), the sample's (the
    strip alone, no cells). The prediction's distances are now compared as their summed excess
    over ``occlusion``, 0 exactly where it is lost."""
    g1, g2, true = _pair(shift=24)
    model, prediction = torch.zeros_like(true), true.clone()
    block = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    if judge == "region":
        model[..., :150] = true[..., :150]
        prediction[:, 0, :, :100] += 2.0
        block[..., 8:88, 8:100] = True
    for left, bottom in strips:
        strip = torch.zeros_like(block)
        strip[..., 8:bottom, left:191] = True  # every true end point leaves image 2
        out = ImageGate(grid=(1, 1), **options)(g1, g2, prediction, model, block | strip)
        assert int((strip & ~block).sum()) >= 44 and float(out.cost_model[0]) > 0
        assert not bool(out.use_model[strip].any()), (left, bottom)
        assert bool(out.model_used[0]) == (judge != "sample") and int(out.cells_kept[0]) == (judge == "cell")
        assert bool(out.use_model[block].all())


def test_a_cell_whose_model_leaves_image_2_keeps_the_prediction_only_where_it_explains_it():
    """The right cell's true end points mostly leave image 2 (a frame cut at its edge), and the
    prediction there is wrong (no motion) but inside. On the few points whose model end point
    stays inside, the prediction is right and the model 1 px off: judged there alone, the
    prediction explained the cell, and the cell kept it whole. Whether the prediction explains
    the cell itself counts every point it is judged at: it does not, and the cell takes the
    model. The sample's evidence counts only the points both flows are judged at, as before."""
    g1, g2, true = _pair(shift=40)
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 8:-8, 8:] = True
    model, prediction = true.clone(), torch.zeros_like(true)  # no motion: wrong everywhere ...
    right = torch.arange(192) >= 144  # the right cell of a (1, 4) grid
    model[:, 0, :, right] += 1.0
    prediction[:, 0, :, 144:149] = 40.0  # ... but where the model stays inside the right cell
    gate = ImageGate(grid=(1, 4), objects=False)
    out = gate(g1, g2, prediction, model, mask)
    assert bool(out.confirmed.all()) and bool(out.model_used.all())
    assert bool(out.use_model[mask & ~right].all())
    # the right cell takes the model (1 px off there, the prediction 40 px off on most of it)
    assert bool(out.use_model[mask & right].all()) and int(out.cells_kept) == 0
    # the object test alike
    assert bool(ImageGate(grid=(1, 4))(g1, g2, prediction, model, mask).use_model[mask & right].all())
    # the sample's evidence: only the points both flows are judged at, as before
    assert float(out.cost_prediction) > 0.35 and float(out.cost_model) < 0.1


def test_an_object_region_whose_model_leaves_image_2_keeps_the_prediction_only_where_it_explains_it():
    """The object test alone (cells too small to decide: every cell follows its sample): a
    region near the right edge where the flows differ, whose true end points mostly leave image 2,
    the prediction right on the few points whose model end point stays inside (the model 1.5 px
    off) and wrong (no motion) on the rest. Whether the prediction explains the region itself
    counts every point it is judged at there: it does not, and the region takes the model."""
    g1, g2, true = _pair(shift=40)
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 8:-8, 8:] = True
    columns = torch.arange(192)
    model, prediction = true.clone(), torch.zeros_like(true)  # no motion: wrong on the left ...
    prediction[:, 0, :, 96:148] = 40.0  # ... right from the middle to where the model leaves
    strip = columns >= 141
    model[:, 0, :, strip] += 1.5
    out = ImageGate(grid=(48, 96))(g1, g2, prediction, model, mask)
    assert bool(out.confirmed.all()) and bool(out.model_used.all()) and int(out.cells) == 0
    assert bool(out.use_model[mask & (columns < 96)].all())
    assert bool(out.use_model[mask & strip].all())


@pytest.mark.parametrize("require_evidence", [True, False])
def test_a_sample_with_an_empty_mask_does_not_use_the_model(require_evidence):
    """A batch whose second mask is empty (as the refiner hands a sample left unchanged before the
    gate): with ``require_evidence=False`` that sample reported ``model_used`` True, though the
    model is used at none of its pixels (and the docs say False). It is False either way; the
    other sample is judged as alone."""
    g1, g2, true = _pair()
    mask = torch.zeros(2, 1, 96, 192, dtype=torch.bool)
    mask[0, :, 8:-8, 8:-8] = True
    images = (g1.expand(2, -1, -1, -1), g2.expand(2, -1, -1, -1))
    prediction = (true + _smooth_noise(2.0)).expand(2, -1, -1, -1)
    gate = ImageGate(require_evidence=require_evidence)
    out = gate(*images, prediction, true.expand(2, -1, -1, -1).clone(), mask)
    alone = gate(g1, g2, prediction[:1], true.clone(), mask[:1])
    assert out.points.tolist() == [int(alone.points), 0] and out.cells.tolist() == [int(alone.cells), 0]
    assert out.model_used.tolist() == [True, False] and bool(alone.model_used.all())
    assert not bool(out.use_model[1].any()) and not bool(out.evidence[1].any())
    assert torch.equal(out.use_model[:1], alone.use_model)


def test_the_gate_leaves_its_inputs_alone():
    g1, g2, true = _pair()
    args = [g1, g2, true, true + 1.0, torch.ones(1, 1, 96, 192, dtype=torch.bool)]
    before = [a.clone() for a in args]
    ImageGate()(*args)
    assert all(torch.equal(a, b) for a, b in zip(args, before))


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(grid=(0, 4)), ValueError, r"^grid: expected an int >= 1, got 0"),
    (dict(grid=3), TypeError, r"^grid: expected \(rows, columns\) of positive integers, got 3"),
    (dict(grid=(2.0, 4)), TypeError, r"^grid: expected an int, got float 2.0"),
    (dict(points=0), ValueError, r"^points: expected an int >= 1, got 0"),
    (dict(points=2.0), TypeError, r"^points: expected an int, got float 2.0"),
    (dict(z=-1.0), ValueError, r"^z: expected a number >= 0, got -1.0"),
    (dict(z=None), TypeError, r"^z: expected a number, got NoneType None"),
    (dict(margin=True), TypeError, r"^margin: expected a number, got bool True"),
    (dict(object_px=0.0), ValueError, r"^object_px: expected a positive number \(> 0\), got 0.0"),
    (dict(object_px=1e200), ValueError, r"^object_px: expected at most 1e\+06 pixels, got 1e\+200"),
    (dict(temperature=0.0), ValueError, r"^temperature: expected a positive number \(> 0\), got 0.0"),
    (dict(contrast=float("inf")), ValueError, r"^contrast: expected a finite number, got inf"),
    (dict(min_points_fine=0), ValueError, r"^min_points_fine: expected an int >= 1, got 0"),
    (dict(min_neighbours=2.5), TypeError, r"^min_neighbours: expected an int, got float 2.5"),
    (dict(min_neighbours=True), TypeError, r"^min_neighbours: expected an int, got bool True"),
    (dict(min_neighbours=17), ValueError, r"^min_neighbours: expected at most 16 \(the ring's neighbours\)"),
])
def test_gate_options_are_checked(kwargs, error, match):
    with pytest.raises(error, match=match):
        ImageGate(**kwargs)


@pytest.mark.parametrize("kwargs, match", [(dict(objects=1), "objects: expected a bool, got 1"),
                                           (dict(require_evidence="yes"), "require_evidence: expected a bool, got 'yes'")])
def test_gate_flags_are_checked(kwargs, match):
    with pytest.raises(TypeError, match=match):
        ImageGate(**kwargs)


def test_gate_inputs_are_checked_images_first():
    """The frames fix the size: a flow or mask of another size is the one named; an empty batch
    is refused; bfloat16 flows are judged like float32 ones (the object test's host copy)."""
    from fsof_torch import render_pair

    p = render_pair("default", 0, size=(48, 160))
    im1, im2, flow, road = p["image1"][None], p["image2"][None], p["flow"][None].float(), p["road"][None]
    gate = ImageGate()
    with pytest.raises(ValueError, match=r"prediction: expected shape \(B, 2, H, W\) with H=48"):
        gate(im1, im2, flow[..., :40, :], flow, road)
    with pytest.raises(ValueError, match=r"model: expected shape \(B, 2, H, W\) with W=160"):
        gate(im1, im2, flow, flow[..., :100], road)
    with pytest.raises(ValueError, match=r"image1: expected shape \(B, C, H, W\) with B >= 1"):
        gate(im1[:0], im2[:0], flow[:0], flow[:0], road[:0])
    # a prediction 1.5 px off and the true flow as the model: the model is used where the road is
    prediction = flow + 1.5
    plain = gate(im1, im2, prediction, flow, road)
    half = gate(im1.bfloat16(), im2.bfloat16(), prediction.bfloat16(), flow.bfloat16(), road)
    assert bool(plain.use_model.any()) and bool(plain.model_used.all())
    assert torch.equal(half.use_model, plain.use_model) and half.cost_model.dtype == torch.float32
    torch.testing.assert_close(half.cost_model, plain.cost_model, rtol=0.02, atol=0)
    torch.testing.assert_close(half.cost_prediction, plain.cost_prediction, rtol=0.02, atol=0)


def test_the_largest_object_threshold_runs():
    """object_px is bounded where it is set: the largest allowed one judges (its squared
    thresholds are finite), a larger one is refused there rather than overflowing in the call."""
    g1, g2, true = _pair()
    mask = torch.ones(1, 1, 96, 192, dtype=torch.bool)
    out = ImageGate(object_px=1e6)(g1, g2, true + 1.0, true.clone(), mask)
    assert bool(out.model_used.all()) and bool(out.use_model.all())


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_image_pixels_are_no_evidence(bad):
    """Both flows true: wherever the images are finite they explain them exactly (distance 0).
    Points that read a NaN or inf pixel in either image do not count; they neither raise the
    cost nor throw the model away, even with 45 % of image 2 not finite."""
    g1, g2, true = _pair()
    mask = torch.ones(1, 1, 96, 192, dtype=torch.bool)
    gate = ImageGate(objects=False)
    clean = gate(g1, g2, true, true.clone(), mask)
    assert float(clean.cost_model) == 0.0 and float(clean.cost_prediction) == 0.0
    for which in (0, 1):
        images = [g1.clone(), g2.clone()]
        images[which][..., 20:60, 40:120] = bad
        out = gate(*images, true, true.clone(), mask)
        assert float(out.cost_model) == 0.0 and float(out.cost_prediction) == 0.0, which
        assert 0 < int(out.points) < int(clean.points)
        assert bool(out.informative.all()) and bool(out.model_used.all())
    g2_bad = g2.clone()
    g2_bad[..., :, :86] = bad
    out = ImageGate()(g1, g2_bad, true, true.clone(), mask)
    assert float(out.cost_model) == 0.0 and bool(out.model_used.all()) and bool(out.use_model.all())
    # census_ring_distance flags the points themselves: the first one's ring at its end point reads the patch
    x, y = torch.tensor([[30.0, 30.0]]), torch.tensor([[18.0, 10.0]])
    images = [g1.clone(), g2.clone()]
    images[1][..., 20:60, 40:120] = bad
    _, _, ok = census_ring_distance(*images, x, y, torch.tensor([[[12.0, 12.0], [0.0, 0.0]]]))
    assert ok.tolist() == [[False, True]]


def test_gate_arguments_on_another_device_are_named():
    """Every argument is checked against the prediction's device (the meta device stands in for
    another one): each is named, instead of torch's device error deep inside."""
    g1, g2, true = _pair()
    mask = torch.ones(1, 1, 96, 192, dtype=torch.bool)
    args = {"image1": g1, "image2": g2, "prediction": true, "model": true.clone(), "mask": mask}
    for name in ("image1", "image2", "model", "mask"):
        moved = {**args, name: args[name].to("meta")}
        with pytest.raises(ValueError, match=f"^{name}: a tensor on the meta device has shapes but no values"):
            ImageGate()(*moved.values())


@pytest.mark.parametrize("which, bad, error, match", [
    ("grey1", lambda g: g.expand(1, 3, -1, -1), ValueError, r"^grey1: expected shape \(B, 1, H, W\), got \(1, 3, 96, 192\)"),
    ("grey2", lambda g: g[..., :90, :], ValueError, r"^grey2: expected shape \(B, 1, H, W\) with H=96"),
    ("grey1", lambda g: g.to(torch.uint8), TypeError, r"^grey1: expected a floating-point tensor, got dtype torch.uint8"),
    ("x", lambda x: x[0], ValueError, r"^x: expected shape \(B, N\), got \(3,\)"),
    ("x", lambda x: x > 0, TypeError, r"^x: expected float or integer pixel coordinates, got dtype torch.bool"),
    ("y", lambda y: y[:, :2], ValueError, r"^y: expected shape \(B, N\) with N=3"),
    ("y", lambda y: y.tolist(), TypeError, r"^y: expected a tensor \(B, N\) of pixel coordinates, got list"),
    ("flow", lambda f: f.transpose(1, 2), ValueError, r"^flow: expected shape \(B, 2, N\), got \(1, 3, 2\)"),
    ("flow", lambda f: f.expand(2, -1, -1), ValueError, r"^flow: expected shape \(B, 2, N\) with B=1"),
    ("flow", lambda f: f.to("meta"), ValueError, r"^flow: expected the device of grey1 \(cpu\), got meta"),
    ("threshold", lambda t: -1.0, ValueError, r"^threshold: expected a number >= 0, got -1.0"),
])
def test_census_ring_distance_checks_its_arguments(which, bad, error, match):
    g1, g2 = _texture(seed=1), _texture(seed=2)
    args = {"grey1": g1, "grey2": g2, "x": torch.tensor([[10.0, 50.0, 90.0]]), "y": torch.tensor([[20.0, 40.0, 60.0]]),
            "flow": torch.tensor([[[2.0, -3.0, 0.0], [1.0, 0.0, 4.0]]]), "threshold": 2.0}
    args[which] = bad(args[which])
    with pytest.raises(error, match=match):
        census_ring_distance(**args)


def test_census_ring_distance_takes_integer_coordinates():
    """Integer coordinates are whole pixels: the same as float ones."""
    g1, g2 = _texture(seed=1), _texture(seed=2)
    ints = census_ring_distance(g1, g2, torch.tensor([[10, 50, 90]]), torch.tensor([[20, 40, 60]]),
                                torch.tensor([[[2.0, -3.0, 0.0], [1.0, 0.0, 4.0]]]))
    floats = census_ring_distance(g1, g2, torch.tensor([[10.0, 50.0, 90.0]]), torch.tensor([[20.0, 40.0, 60.0]]),
                                  torch.tensor([[[2.0, -3.0, 0.0], [1.0, 0.0, 4.0]]]))
    assert all(torch.equal(a, b) for a, b in zip(ints, floats))


def test_gate_and_estimates_return_ordinary_tensors():
    """The estimators run in inference mode; what they return is usable in place and in autograd."""
    from fsof_torch import detect_road, fit_image, fit_road, render_pair
    from fsof_torch.estimation.initial import planar_start

    p = render_pair("default", 0, size=(48, 160))
    I1, I2, road, cam = p["image1"][None], p["image2"][None], p["road"][None], p["camera"]
    flow = p["flow"][None]
    results = {"gate": ImageGate()(I1, I2, flow, flow, road), "fit_image": fit_image(I1, I2, road, cam),
               "fit_road": fit_road(flow, road, cam), "planar_start": planar_start(flow, road, cam),
               "detect_road": detect_road(I1, I2, cam, refit=False)}

    def tensors(x):
        if isinstance(x, torch.Tensor):
            yield x
        elif isinstance(x, dict):
            for v in x.values():
                yield from tensors(v)
        elif isinstance(x, (list, tuple)):
            for v in x:
                yield from tensors(v)
        elif hasattr(x, "__dict__"):
            yield from tensors(vars(x))

    for name, result in results.items():
        found = list(tensors(result))
        assert len(found) >= 3, name
        assert not any(t.is_inference() for t in found), name
        for t in found:  # (a view made in inference mode would refuse this too)
            t.copy_(t.clone())
    # (objects passed in come back themselves: a camera compares by identity)
    assert detect_road(I1, I2, cam, motion=results["fit_image"]).motion is results["fit_image"]
    fit = results["fit_image"]
    w = torch.ones((), requires_grad=True)
    (w * fit.flow).sum().backward()
    assert w.grad is not None


def test_mean_and_error_from_blocks_against_numpy():
    """Per frame of a batch, over the points of weight 1 only: the mean and the larger of the
    points' and the blocks' standard errors (:func:`_block_error`, written apart); a frame whose
    points all lie in one block has the points' error."""
    from fsof_torch.refinement.gate import _mean_and_error

    g = torch.Generator().manual_seed(5)
    B, N, cols = 3, 400, 12
    v = torch.rand(B, N, generator=g, dtype=torch.float64)
    w = (torch.rand(B, N, generator=g) < 0.8).double()
    x, y = torch.randint(0, cols * 16, (B, N), generator=g), torch.randint(0, 64, (B, N), generator=g)
    x[2], y[2] = x[2] % 16, y[2] % 16  # frame 2: one block
    v[1] += (x[1] // 16 % 2) * 0.5  # frame 1: blocks of two levels (their error is the larger)
    block = (y // 16) * cols + x // 16
    mean, se = _mean_and_error(v, w, block, 4 * cols)
    for b in range(B):
        keep = w[b].bool().numpy()
        d, xb, yb = v[b].numpy()[keep], x[b].numpy()[keep], y[b].numpy()[keep]
        points = d.std() / np.sqrt(d.size)
        assert float(mean[b]) == pytest.approx(d.mean(), rel=1e-12)
        assert float(se[b]) == pytest.approx(max(points, _block_error(d, xb, yb)), rel=1e-9)
    assert float(se[1]) > 1.5 * float(v[1][w[1].bool()].std() / np.sqrt(float(w[1].sum())))
    assert float(se[2]) == pytest.approx(float(_mean_and_error(v, w)[1][2]), rel=1e-12)


def test_the_gate_takes_each_points_block_by_row_and_column(monkeypatch):
    """The standard error the gate uses over a sample's mask is the reference's (the larger of
    the points' and the 16 x 16 px blocks' errors, :func:`_block_error`) on a frame of 53 x 77
    pixels (neither side a multiple of 16, more block columns than rows, the masks reaching the
    first and last columns of blocks) whose mask leaves a column of blocks empty; each frame of a
    batch of two (different masks) alone."""
    from fsof_torch.refinement import gate as gate_module

    H, W = 53, 77
    g1 = _texture(H, W, seed=3)
    g2 = torch.roll(g1, shifts=3, dims=-1)
    true = torch.zeros(1, 2, H, W)
    true[:, 0] = 3.0
    prediction = true + _smooth_noise(2.0, seed=4, H=H, W=W)
    masks = torch.zeros(2, 1, H, W, dtype=torch.bool)
    masks[0, :, 5:50] = True
    masks[0, :, :, 32:48] = False  # (the third column of blocks empty)
    masks[1, :, 10:53, 0:70] = True
    seen = []
    blocked = gate_module._mean_and_error

    def spy(v, w, *blocks):
        mean, se = blocked(v, w, *blocks)
        seen.append((mean, se))
        return mean, se

    monkeypatch.setattr(gate_module, "_mean_and_error", spy)
    ImageGate(objects=False, points=20000)(g1.expand(2, -1, -1, -1), g2.expand(2, -1, -1, -1),
                                           prediction.expand(2, -1, -1, -1), true.expand(2, -1, -1, -1), masks)
    (mean, se), = seen
    for b in range(2):
        ref_mean, ref_se, _, _ = _mean_and_standard_error(g1, g2, masks[b:b + 1], prediction, true)
        assert float(mean[b]) == pytest.approx(ref_mean, rel=1e-5)
        assert float(se[b]) == pytest.approx(ref_se, rel=1e-4)


def test_the_gates_evidence_map_is_returned_as_made():
    """The full-size evidence map is made outside inference mode: an ordinary tensor returned as
    made, not a copy of an inference tensor (no full-size float clone in the call)."""
    from torch.profiler import ProfilerActivity, profile

    from fsof_torch import render_pair

    p = render_pair("default", 0, size=(96, 320))
    image1, image2, road = p["image1"][None], p["image2"][None], p["road"][None]
    flow = p["flow"][None].float()
    ImageGate()(image1, image2, flow, flow, road)  # (warm-up)
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        result = ImageGate()(image1, image2, flow + 0.5, flow, road)
    clones = [e for e in prof.events() if e.name == "aten::clone" and e.input_shapes
              and list(e.input_shapes[0]) == [1, 1, 96, 320]]
    assert len(clones) <= 1  # (the decision map's bool copy at most)
    assert not result.evidence.is_inference() and result.evidence.shape == (1, 1, 96, 320)


def test_census_ring_distance_under_exposure_changes_on_a_real_road(shared_data, kitti15_ground_truth):
    """What the census module says of exposure: an offset or a brightening gain leaves the distance
    of the exact (here: zero) flow at 0 (up to rounding), but a darkening gain g < 1 does not, as the threshold
    applies in image 2 too: differences in (2, 2 / g] grey levels of image 1 fall to 2 or below.
    On the road of the real KITTI frame 000000_10 (grey from RGB, every 7th road pixel) the
    distance at g = 0.8 is 0.1 or more, at g = 0.5 a third or more."""
    from fsof_torch.evaluation.photometric import to_grey
    from fsof_torch.io import read_image

    _, _, _, road = kitti15_ground_truth
    grey = to_grey(read_image(shared_data / "kitti15_000000" / "image_10.png")[None])
    y, x = road[0, 0].nonzero().T[:, ::7].double()
    flow = torch.zeros(1, 2, x.numel())

    def distance(image2):
        d, _, ok = census_ring_distance(grey, image2, x[None], y[None], flow)
        return float(d[ok].mean())

    # (not exactly 0: image 2's samples at float32 grid positions move a difference just above
    # the threshold to it now and then, 1e-4 of the neighbours)
    assert max(distance(grey), distance(grey + 30.0), distance(grey * 1.3)) < 1e-3
    assert 0.1 <= distance(grey * 0.8) <= 0.2 and distance(grey * 0.5) >= 0.33


@pytest.mark.parametrize("objects", [True, False])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_model_flow_not_finite_inside_the_mask_is_never_used(bad, objects):
    """The model NaN or inf in a patch of the mask, exact elsewhere: the patch's points give no
    evidence, and its pixels keep the prediction (they were marked as using the model, a mask
    that fuse_flow then refused: "flow_model: expected finite values inside the mask"). The rest
    of the mask is decided as before; fuse_flow takes the gate's use_model as its mask."""
    from fsof_torch import fuse_flow

    g1, g2, true = _pair()
    mask = torch.zeros(1, 1, 96, 192, dtype=torch.bool)
    mask[..., 8:-8, 8:-8] = True
    prediction = true + _smooth_noise(2.0)
    gate = ImageGate(grid=(4, 8), objects=objects)
    clean = gate(g1, g2, prediction, true.clone(), mask)
    model = true.clone()
    model[:, 1, 24:48, 48:96] = bad  # (the v channel only: either channel makes the pixel unusable)
    patch = torch.zeros_like(mask)
    patch[..., 24:48, 48:96] = True  # (cells of 24 x 24 pixels: two whole ones)
    out = gate(g1, g2, prediction, model, mask)
    assert bool(out.model_used.all()) and bool(out.confirmed.all())
    assert not bool(out.use_model[patch].any())
    assert torch.equal(out.use_model[~patch], clean.use_model[~patch]) and bool(out.use_model[mask & ~patch].all())
    # (the two cells the patch covers whole have no point that counts: too few to be counted)
    assert int(out.cells) == int(clean.cells) - 2 and int(out.cells_kept) == int(clean.cells_kept)
    fused, weight = fuse_flow(prediction, model, out.use_model)
    assert torch.equal(fused[patch.expand_as(fused)], prediction[patch.expand_as(fused)])
    assert torch.equal(fused[(mask & ~patch).expand_as(fused)], true[(mask & ~patch).expand_as(fused)])
