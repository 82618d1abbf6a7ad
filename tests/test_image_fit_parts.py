"""The image fit's building blocks against formulas written here: the road mask's pyramid (a
3 × 3 min-pool at every second pixel), the image's central-difference gradient (replicated
border), on random masks and images of any size, and the points a level keeps."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from fsof_torch import Camera
from fsof_torch.estimation.image_fit import _grey_pair, gaussian_blur
from fsof_torch.estimation.image_problem import ImageProblem, level_problem, pixel_gradient, with_gradient
from fsof_torch.estimation.pyramid import mask_pyramid
from fsof_torch.geometry.road_models import get_road_model

sizes = st.tuples(st.integers(1, 3), st.integers(1, 40), st.integers(1, 40))


@settings(max_examples=40, deadline=None)
@given(sizes, st.floats(0.0, 1.0), st.integers(0, 2**31 - 1))
def test_mask_pyramid_is_a_min_pool_at_every_second_pixel(shape, density, seed):
    B, H, W = shape
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(B, 1, H, W, generator=g) < density
    levels = mask_pyramid(mask, 4)
    assert len(levels) == 4 and levels[0] is mask
    for fine, coarse in zip(levels, levels[1:]):
        h, w = fine.shape[-2:]
        assert coarse.dtype == torch.bool and coarse.shape == (B, 1, (h + 1) // 2, (w + 1) // 2)
        # pixel i of the coarser level: every pixel of the finer one within one of 2i (in the image)
        for i in range(coarse.shape[-2]):
            for j in range(coarse.shape[-1]):
                window = fine[:, 0, max(2 * i - 1, 0):2 * i + 2, max(2 * j - 1, 0):2 * j + 2]
                assert torch.equal(coarse[:, 0, i, j], window.flatten(1).all(1))


@settings(max_examples=40, deadline=None)
@given(sizes, st.integers(0, 2**31 - 1))
def test_image_gradient_is_the_central_difference_with_a_replicated_border(shape, seed):
    B, H, W = shape
    image = torch.rand(B, 1, H, W, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 255
    out = with_gradient(image)
    p = F.pad(image, (1, 1, 1, 1), mode="replicate")
    assert torch.equal(out[:, :1], image)
    assert torch.equal(out[:, 1:2], 0.5 * (p[..., 1:-1, 2:] - p[..., 1:-1, :-2]))
    assert torch.equal(out[:, 2:3], 0.5 * (p[..., 2:, 1:-1] - p[..., :-2, 1:-1]))
    before = image.clone()
    with_gradient(image)
    assert torch.equal(image, before)


def _points(problem, b):
    """The (u, v) of frame ``b``'s points of a level, sorted."""
    uv = problem.pts[b, :2, problem.sel[b]].T.tolist()
    return sorted(map(tuple, uv))


@settings(max_examples=30, deadline=None)
@given(st.integers(4, 30), st.integers(4, 40), st.floats(0.05, 1.0), st.sampled_from([0.3, 0.5, 0.7, 1.0]),
       st.sampled_from([None, 5, 40, 300]), st.integers(0, 2**31 - 1))
def test_level_points_follow_the_documented_rule_whatever_the_batch(H, W, density, fraction, max_points, seed):
    """A frame's points at a level: with ``max_points`` the k = round(fraction n) strongest
    gradients of n = min(ceil(max_points / fraction), H W) candidates (all of the road where it has
    no more than k pixels); with None the round(fraction × count) strongest of all its road
    pixels. Either way the same points alone as next to a frame with a larger road."""
    g = torch.Generator().manual_seed(seed)
    img = torch.rand(2, 2, H, W, generator=g, dtype=torch.float64) * 255
    mask = torch.rand(1, 1, H, W, generator=g) < density
    full = torch.ones_like(mask)
    cam = Camera(torch.tensor([[50.0, 0, W / 2], [0, 50.0, 1.0], [0, 0, 1]], dtype=torch.float64), 1.65)
    model = get_road_model("plane")
    alone = level_problem(model, cam, img[:1], mask, fraction, max_points, 1)
    both = level_problem(model, cam.expand(2), img, torch.cat([mask, full]), fraction, max_points, 1)
    assert _points(alone, 0) == _points(both, 0)
    count = int(mask.sum())
    if max_points is None:
        kept = max(1, round(fraction * count)) if fraction < 1 else count
    else:
        n = min(math.ceil(max_points / fraction), H * W)
        kept = min(count, max(1, round(fraction * n)) if fraction < 1 else n)
    assert int(alone.sel.sum()) == min(kept, count)
    # the kept points are the strongest gradients among the candidates (all the road when they
    # are all candidates)
    if count and fraction < 1 and (max_points is None or count <= min(math.ceil(max_points / fraction), H * W)):
        # (the gradient the selection ranks by: central differences, one-sided at the border)
        grad = pixel_gradient(img[:1, :1], torch.arange(H * W)[None])[1][0].abs().sum(0).reshape(H, W)
        chosen = {(int(u), int(v)) for u, v in _points(alone, 0)}
        inside = [(grad[v, u].item(), (u, v)) for v, u in mask[0, 0].nonzero().tolist()]
        weakest_kept = min(s for s, uv in inside if uv in chosen)
        strongest_left = max((s for s, uv in inside if uv not in chosen), default=-1.0)
        assert weakest_kept >= strongest_left


@pytest.mark.parametrize("B, H, W", [(2, 7, 9), (1, 1, 6), (1, 5, 1), (1, 2, 2)])
def test_pixel_gradient_is_the_plain_central_difference(B, H, W):
    """Values and gradients at pixels (the border's too) equal the plain formula bit for bit: half
    the difference of the two neighbours, the difference with the one neighbour at the border,
    0 across a single pixel."""
    img = torch.rand(B, 1, H, W, generator=torch.Generator().manual_seed(0)) * 255
    pix = torch.randint(0, H * W, (B, 40), generator=torch.Generator().manual_seed(1))
    value, grad = pixel_gradient(img, pix)
    x = img[:, 0]
    right, left = torch.cat([x[..., 1:], x[..., -1:]], -1), torch.cat([x[..., :1], x[..., :-1]], -1)
    down, up = torch.cat([x[:, 1:], x[:, -1:]], 1), torch.cat([x[:, :1], x[:, :-1]], 1)
    steps = lambda n: torch.tensor([2.0] * n).index_fill_(0, torch.tensor([0, n - 1]), 1.0 if n > 1 else 0.0)  # noqa: E731
    gx = (right - left) / steps(W).clamp_min(1)
    gy = (down - up) / steps(H).clamp_min(1).unsqueeze(-1)
    at = lambda t: t.reshape(B, -1).gather(1, pix).double()  # noqa: E731
    assert torch.equal(value, at(x)) and torch.equal(grad, torch.stack([at(gx), at(gy)], 1))


@pytest.mark.parametrize("sigma, error, message", [
    (-1.0, ValueError, "sigma: expected a number >= 0, got -1.0"),  # (OpenCV's assertion before)
    (float("nan"), ValueError, "sigma: expected a finite number, got nan"),  # ('cannot convert float NaN')
    ("4", TypeError, "sigma: expected a number, got str '4'")])
def test_gaussian_blur_checks_its_sigma(sigma, error, message):
    x = torch.rand(1, 1, 8, 9, generator=torch.Generator().manual_seed(0))
    with pytest.raises(error, match=message):
        gaussian_blur(x, sigma)
    y = gaussian_blur(x, 0.0)  # (0: the images as they are, in a tensor of their own)
    assert torch.equal(y, x) and y.data_ptr() != x.data_ptr()


@pytest.mark.parametrize("B", [1, 2])
def test_grey_pair_is_taken_only_where_the_frames_are_one_tensors_channels(B):
    """Two grey frames that are the channels 0 and 1 of one (B, 2, H, W) tensor are that tensor
    (its memory, not a copy); frames in two tensors, in the other order, of another dtype, in
    colour, or channels of a wider tensor are not (the fit converts them into a tensor of its own)."""
    pair = torch.rand(B, 2, 5, 7)
    got = _grey_pair(pair[:, :1], pair[:, 1:], torch.float32)
    assert got is not None and got.data_ptr() == pair.data_ptr() and torch.equal(got, pair)
    assert _grey_pair(pair[:, 1:], pair[:, :1], torch.float32) is None
    assert _grey_pair(pair[:, :1].clone(), pair[:, 1:].clone(), torch.float32) is None
    assert _grey_pair(pair[:, :1], pair[:, 1:], torch.float64) is None
    wide = torch.rand(B, 3, 5, 7)
    assert _grey_pair(wide[:, :1], wide[:, 1:2], torch.float32) is None
    rgb = torch.rand(B, 6, 5, 7)
    assert _grey_pair(rgb[:, :3], rgb[:, 3:], torch.float32) is None


@pytest.mark.parametrize("options", [{}, {"smooth_sigma": 1.0}, {"highpass": None}, {"data_range": 1.0}])
def test_a_callers_stacked_grey_pair_is_read_not_written(options):
    """Frames that are the two channels of the caller's one tensor are fitted as they are (no
    copy) and left as they came, with the result of the same frames given apart."""
    from fsof_torch import fit_image, render_pair
    from fsof_torch.evaluation.photometric import to_grey

    p = render_pair("default", 0, size=(96, 320))
    scale = options.get("data_range", 255.0) / 255.0
    pair = torch.cat([to_grey(p["image1"][None]), to_grey(p["image2"][None])], dim=1) * scale
    before = pair.clone()
    stacked = fit_image(pair[:, :1], pair[:, 1:], p["road"][None], p["camera"], **options)
    assert torch.equal(pair, before)
    apart = fit_image(pair[:, :1].clone(), pair[:, 1:].clone(), p["road"][None], p["camera"], **options)
    for k in apart.params:
        assert torch.equal(stacked.params[k], apart.params[k]), k


def test_the_refiners_grey_frames_reach_the_fit_without_a_copy(monkeypatch):
    """The refiner converts both frames to grey into one tensor; its image fit takes that tensor
    as its pair of frames (no conversion, no copy) and fits what it fits from separate greys."""
    import warnings

    import fsof_torch.estimation.image_fit as image_fit
    import fsof_torch.refinement.estimators as estimators
    from fsof_torch import FreespaceRefiner, fit_image, render_pair
    from fsof_torch.evaluation.photometric import to_grey

    p = render_pair("default", 0, size=(96, 320))
    images, road, flow = (p["image1"][None], p["image2"][None]), p["road"][None], p["flow"][None].float()
    fits, conversions, real = [], [], image_fit.to_grey
    monkeypatch.setattr(image_fit, "to_grey", lambda *a, **k: conversions.append(1) or real(*a, **k))
    monkeypatch.setattr(estimators, "fit_image", lambda *a, **k: fits.append((a, k)) or fit_image(*a, **k))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = FreespaceRefiner()(flow, road, p["camera"], images=images)
    assert len(fits) == 1 and conversions == []
    (image1, image2, *_), options = fits[0]
    assert image2.data_ptr() == image1.data_ptr() + image1[0, 0].numel() * image1.element_size()
    alone = fit_image(to_grey(images[0]), to_grey(images[1]), *fits[0][0][2:], **options)
    for k in alone.params:
        assert torch.equal(out.fit.params[k], alone.params[k].to(out.fit.params[k].dtype)), k


def test_the_fits_flow_is_returned_as_it_was_made(monkeypatch):
    """The fit's model flow and its mask are made outside inference mode: returned as they were made
    (ordinary tensors, not copies made at the end), the values those made inside it."""
    import fsof_torch.estimation.image_fit as image_fit
    from fsof_torch import fit_image, render_pair

    p = render_pair("default", 0, size=(96, 320))
    made, real = [], image_fit.flow_from_map
    monkeypatch.setattr(image_fit, "flow_from_map", lambda *a, **k: made.append((a, real(*a, **k))) or made[-1][1])
    fit = fit_image(p["image1"][None], p["image2"][None], p["road"][None], p["camera"])
    (args, (flow, valid)), = [m for m in made if m[1][0].data_ptr() == fit.flow.data_ptr()]
    assert valid.data_ptr() == fit.valid.data_ptr() and not fit.flow.is_inference() and not fit.valid.is_inference()
    with torch.inference_mode():
        inside = real(*args)
    assert torch.equal(inside[0], fit.flow) and torch.equal(inside[1], fit.valid)


def test_image_residuals_count_only_points_below_the_horizon():
    """The photometric residuals count a point only where its ray meets the road in front of the
    camera: the ray K⁻¹ p̃ turned into the vehicle frame (R_c = R_roll R_pitch, written here) points
    down (y > 0). With no motion every point maps onto itself, inside image 2: only the horizon
    decides."""

    roll, pitch = 0.05, -0.03
    K = torch.tensor([[100.0, 0.0, 40.0], [0.0, 100.0, 20.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cam = Camera(K, 1.5, roll, pitch)
    H, W = 40, 80
    v, u = torch.meshgrid(torch.arange(0.0, H, 3, dtype=torch.float64), torch.arange(0.0, W, 7, dtype=torch.float64),
                          indexing="ij")
    pts = torch.stack([u.flatten(), v.flatten(), torch.ones(u.numel(), dtype=torch.float64)]).unsqueeze(0)
    c, s = math.cos(roll), math.sin(roll)
    R_roll = torch.tensor([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    c, s = math.cos(pitch), math.sin(pitch)
    R_pitch = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]], dtype=torch.float64)
    down = ((R_roll @ R_pitch).T @ torch.linalg.inv(K) @ pts[0])[1] > 0
    assert down.any() and (~down).any()
    image = torch.rand(1, 1, H, W, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 255
    N = pts.shape[-1]
    model = get_road_model("plane")
    problem = ImageProblem(model, cam, pts, torch.zeros(1, N, dtype=torch.float64),
                           torch.zeros(1, 2, N, dtype=torch.float64), with_gradient(image),
                           torch.ones(1, N, dtype=torch.bool))
    params = torch.zeros(1, len(model.params) + 2, dtype=torch.float64)
    params[0, model.params.index("roll")], params[0, model.params.index("pitch")] = roll, pitch
    params[0, len(model.params)] = 1.0  # (the gain)
    assert torch.equal(problem.evaluate(params).use[0], down)
