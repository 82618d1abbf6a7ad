"""Properties of the never-worse gate and the auto road, on small synthetic frames (hypothesis):
the prediction is returned bit for bit outside the mask, and where the refinement leaves it; an
exact prediction is never made worse where the model is visibly wrong; a road that cannot be
trusted is flagged, never applied."""

import functools
import warnings

import torch
import torch.nn.functional as F
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fsof_torch as fs
from fsof_torch.refinement.gate import ImageGate

_SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])


@functools.lru_cache(maxsize=None)
def _scene(preset: str = "default", index: int = 0):
    return fs.render_pair(preset, index, size=(64, 208))


def _texture(H, W, seed):
    g = torch.Generator().manual_seed(seed)
    noise = torch.rand(1, 1, H // 4, W // 4, generator=g) * 255
    return F.interpolate(noise, size=(H, W), mode="bicubic", align_corners=False).clamp(0, 255)


def _same(a, b):
    """(B, 1, H, W) bool: bit for bit the same (NaN where both are NaN)."""
    return ((a == b) | (a.isnan() & b.isnan())).all(1, keepdim=True)


@st.composite
def _masks(draw, B, H, W):
    """Per sample: a rectangle (possibly touching the borders, above the horizon, or empty)."""
    masks = torch.zeros(B, 1, H, W, dtype=torch.bool)
    for b in range(B):
        top, left = draw(st.integers(0, H - 1)), draw(st.integers(0, W - 1))
        bottom, right = draw(st.integers(top, H)), draw(st.integers(left, W))
        masks[b, 0, top:bottom, left:right] = True
    return masks


@settings(max_examples=12, **_SETTINGS)
@given(data=st.data(), nan_rows=st.integers(0, 64), garbage=st.floats(-40, 40), preset=st.sampled_from(["default", "cvc-complex"]))
def test_the_refined_flow_is_the_prediction_wherever_the_output_says_so(data, nan_rows, garbage, preset):
    """Outside the mask, outside ``out.mask`` (replace mode) and in samples not ``refined``, the
    output is the prediction bit for bit; inside ``out.mask`` it is the model flow; a refined
    sample has no non-finite pixel left in ``out.mask``."""
    p = _scene(preset)
    B, (H, W) = 2, p["flow"].shape[-2:]
    mask = data.draw(_masks(B, H, W))
    mask[0] |= p["road"]  # (one sample with its road: refined where the images allow)
    prediction = p["flow"].expand(B, -1, -1, -1).clone()
    prediction[1] += garbage
    prediction[0, :, H - nan_rows:, : W // 2] = float("nan")
    images = tuple(p[k].expand(B, -1, -1, -1) for k in ("image1", "image2"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = fs.refine_flow(prediction, mask, p["camera"], images=images)
    same = _same(out.flow, prediction)
    assert bool(same[~mask].all())
    assert bool(same[~out.mask].all())
    assert not bool((out.mask & ~mask).any())
    for b in range(B):
        if not bool(out.refined[b]):
            assert bool(same[b].all()) and not bool(out.mask[b].any())
    assert bool((out.flow == out.flow_model.to(out.flow.dtype)).all(1, keepdim=True)[out.mask].all())
    if out.gate is not None:
        # cells_kept: cells that keep the prediction, of those with enough points
        assert bool((out.gate.cells_kept <= out.gate.cells).all())


@settings(max_examples=20, **_SETTINGS)
@given(seed=st.integers(0, 10_000), shift=st.integers(1, 6), du=st.floats(-6, 6), dv=st.floats(-6, 6))
def test_an_exact_prediction_is_kept_where_the_model_is_visibly_wrong(seed, shift, du, dv):
    """The exact flow as prediction, a model off by (du, dv) of at least 2 px over the whole mask,
    textured frames: the gate keeps the prediction everywhere (the refined EPE stays 0)."""
    if du * du + dv * dv < 4:
        dv = 2.0 if dv >= 0 else -2.0
    g1 = _texture(64, 128, seed)
    g2 = torch.roll(g1, shifts=shift, dims=-1)
    exact = torch.zeros(1, 2, 64, 128)
    exact[:, 0] = shift
    model = exact + torch.tensor([du, dv]).reshape(1, 2, 1, 1)
    mask = torch.zeros(1, 1, 64, 128, dtype=torch.bool)
    mask[..., 8:-8, 8:-8] = True
    out = ImageGate()(g1, g2, exact, model, mask)
    assert not bool(out.use_model.any())


@settings(max_examples=10, **_SETTINGS)
@given(how=st.sampled_from(["static", "black", "shuffled", "pitched", "occluded"]), seed=st.integers(0, 1000))
def test_a_road_that_cannot_be_trusted_is_flagged_and_left_unrefined(how, seed):
    """Frames whose road cannot be found (identical frames, black frames, image 2 unrelated to
    image 1, a camera pitched to look at the sky, a wall covering the view): a sample flagged ok
    has a road of at least ``min_coverage``; an empty road is flagged; a flagged sample comes back
    unchanged."""
    p = _scene()
    image1, image2, camera = p["image1"][None], p["image2"][None], p["camera"]
    if how == "static":
        image2 = image1.clone()
    elif how == "black":
        image1, image2 = image1 * 0, image2 * 0
    elif how == "shuffled":
        g = torch.Generator().manual_seed(seed)
        image2 = image2.flatten(2)[..., torch.randperm(image2[0, 0].numel(), generator=g)].reshape(image2.shape)
    elif how == "pitched":
        camera = camera.replace(pitch=camera.pitch + 0.6)
    else:
        image1, image2 = image1.clone(), image2.clone()
        image1[..., 20:, :], image2[..., 20:, :] = 40.0, 40.0
    prediction = p["flow"][None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = fs.refine_flow(prediction, "auto", camera, images=(image1, image2))
    det = out.road
    assert det.flag[0] in ("static", "no_motion", "empty", "textureless", "implausible", "small")
    for b in range(det.mask.shape[0]):
        if det.flag[b] == "ok":
            assert bool(det.mask[b].any()) and float(det.coverage[b]) >= 0.01
        else:
            assert det.reason[b] and not bool(out.refined[b])
            assert bool(_same(out.flow, prediction)[b].all())
        if not bool(det.mask[b].any()):
            assert det.flag[b] != "ok"
