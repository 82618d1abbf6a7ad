"""FreespaceRefiner across execution backends: torch.compile, autocast (mixed precision) and the
meta device (shape inference), each against the plain float32 eager result."""

from __future__ import annotations

import warnings

import pytest
import torch

from fsof_torch.data.scene import render_pair
from fsof_torch.geometry.camera import Camera
from fsof_torch.refinement.fusion import FreespaceRefiner, refine_flow
from fsof_torch.refinement.wrapped import FreespaceRefined
from fsof_torch.training.testnet import TinyRAFT

SIZE = (64, 192)

pytestmark = pytest.mark.usefixtures("one_thread")


def scene(B: int = 2):
    """B rendered pairs (noise-free): images on 0..255, the true flow, the road, a prediction that
    is 40 % short near the bottom (where road flow is large) plus noise, and the odometry."""
    pairs = [render_pair("default", i, size=SIZE, noise=0.0) for i in range(B)]
    gt = torch.stack([p["flow"] for p in pairs])
    road = torch.stack([p["road"] for p in pairs])
    images = (torch.stack([p["image1"] for p in pairs]), torch.stack([p["image2"] for p in pairs]))
    g = torch.Generator().manual_seed(0)
    rows = torch.arange(SIZE[0]).reshape(1, 1, -1, 1)
    pred = (gt * torch.where(rows > 45, 0.6, 1.0) + 0.3 * torch.randn(gt.shape, generator=g)).float()
    odometry = {k: torch.tensor([p["odometry"][k] for p in pairs]) for k in ("x_d", "z_d", "yaw")}
    return pred, road, pairs[0]["camera"], images, odometry


# the four ways the road's motion is found: given, fitted to the flow, fitted to the images, both
CASES = {
    "odometry": lambda odo, images: dict(odometry=odo),
    "flow fit": lambda odo, images: dict(),
    "images": lambda odo, images: dict(images=images),
    "odometry+images": lambda odo, images: dict(odometry=odo, images=images),
}


def run(refiner, pred, road, cam, odometry=None, images=None):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return refiner(pred, road, cam, odometry, images=images)


# -- torch.compile ------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("case", ["flow fit", "images"])
# (the gate's OpenCV calls break the graph, as they are meant to: Dynamo says so once)
@pytest.mark.filterwarnings("ignore:Dynamo does not know how to trace the builtin:UserWarning")
def test_compiled_refiner_equals_eager(case):
    """torch.compile(FreespaceRefiner()) with B = 2 runs on the fit path, without images (the flow
    fit) and with them (the image estimator, OpenCV on the CPU, and the gate), and gives the eager
    result to 1e-4 px. (The fit path once raised IndexError inside AOTAutograd: an ``out=`` on a
    view; estimation now runs eagerly outside the graph.) The backend is ``aot_eager``: Dynamo's
    graphs through AOTAutograd, where that failure lay, without inductor's C++ code generation
    (about 40 s of a C++ compiler on a cold cache; inductor's code is checked on the road-flow
    modules, ``test_flow_model.py``, and timed on the refiner by ``bench_compile.py``)."""
    pred, road, cam, images, odo = scene(B=2)
    kw = CASES[case](odo, images)
    eager = run(FreespaceRefiner(), pred, road, cam, **kw)
    assert bool(eager.refined.all())  # the comparison covers refined flow, not the prediction
    compiled = run(torch.compile(FreespaceRefiner(), backend="aot_eager"), pred, road, cam, **kw)
    torch.testing.assert_close(compiled.flow, eager.flow, rtol=0, atol=1e-4)
    assert torch.equal(compiled.mask, eager.mask) and torch.equal(compiled.refined, eager.refined)
    for k, v in eager.odometry.items():
        torch.testing.assert_close(compiled.odometry[k], v, rtol=1e-6, atol=1e-9)


# -- autocast --------------------------------------------------------------------------------------

def _cpu_autocast(dtype: torch.dtype) -> bool:
    """Whether CPU autocast takes ``dtype`` (it warns and stays off where it does not)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with torch.autocast("cpu", dtype=dtype):
            on = torch.is_autocast_enabled("cpu")
    return on and not caught


AMP = (torch.bfloat16, torch.float16)  # both taken by CPU autocast in the pinned torch (asserted)


@pytest.mark.parametrize("amp", AMP, ids=["bf16", "f16"])
@pytest.mark.parametrize("case", list(CASES))
def test_refined_flow_under_autocast_equals_float32(amp, case):
    """Under autocast the geometry, the estimation and the fusion run in float32 (at least): the
    refined flow of a float32 prediction is the float32 result to 1e-3 px, in float32. (In
    bfloat16 the paper's model flow was once 16 px off and the refiner with odometry 10 px.)"""
    pred, road, cam, images, odo = scene(B=2)
    kw = CASES[case](odo, images)
    reference = run(FreespaceRefiner(), pred, road, cam, **kw)
    assert bool(reference.refined.all())
    assert _cpu_autocast(amp)  # (otherwise this would compare float32 with itself)
    with torch.autocast("cpu", dtype=amp):
        got = run(FreespaceRefiner(), pred, road, cam, **kw)
    assert got.flow.dtype == torch.float32 and got.flow_model.dtype == torch.float32
    torch.testing.assert_close(got.flow, reference.flow, rtol=0, atol=1e-3)
    torch.testing.assert_close(got.flow_model, reference.flow_model, rtol=0, atol=1e-3)
    assert torch.equal(got.refined, reference.refined)


@pytest.mark.parametrize("amp", AMP, ids=["bf16", "f16"])
@pytest.mark.parametrize("case", ["odometry", "images"])
def test_half_precision_prediction_keeps_its_dtype(amp, case):
    """A network under autocast predicts in half precision: the refined flow comes back in that
    dtype, the float32 result rounded to it (the model flow itself stays float32)."""
    pred, road, cam, images, odo = scene(B=2)
    kw = CASES[case](odo, images)
    half = pred.to(amp)
    reference = run(FreespaceRefiner(), half.float(), road, cam, **kw)
    with torch.autocast("cpu", dtype=amp):
        got = run(FreespaceRefiner(), half, road, cam, **kw)
    assert got.flow.dtype == amp and got.flow_model.dtype == torch.float32
    assert torch.equal(got.flow, reference.flow.to(amp))
    outside = ~got.mask.expand_as(half)
    assert torch.equal(got.flow[outside], half[outside])


@pytest.mark.parametrize("half, amp", [(torch.float16, torch.bfloat16), (torch.bfloat16, torch.float16)],
                         ids=["f16-under-bf16", "bf16-under-f16"])
def test_half_images_under_autocast_of_the_other_half_dtype(half, amp):
    """Frames held in float16 under bfloat16 autocast (or the reverse) stopped the refiner with
    torch's RuntimeError "Unexpected floating ScalarType in at::autocast::prioritize" (the
    images' range check stacked their extremes, and autocast's stack refuses the half dtype it
    does not cast to): the refinement is the one without autocast."""
    pred, road, cam, images, odo = scene(B=2)
    images = tuple(image.to(half) for image in images)
    reference = run(FreespaceRefiner(), pred, road, cam, images=images)
    assert bool(reference.refined.all())
    with torch.autocast("cpu", dtype=amp):
        got = run(FreespaceRefiner(), pred, road, cam, images=images)
    assert got.flow.dtype == torch.float32
    assert torch.equal(got.flow, reference.flow) and torch.equal(got.refined, reference.refined)



@pytest.mark.parametrize("half, amp", [(torch.float16, torch.bfloat16), (torch.bfloat16, torch.float16)],
                         ids=["f16-under-bf16", "bf16-under-f16"])
def test_half_odometry_with_images_under_autocast_of_the_other_half_dtype(half, amp):
    """Planar odometry held in float16 beside images, under bfloat16 autocast (or the reverse),
    raised torch's RuntimeError "Unexpected floating ScalarType in at::autocast::prioritize"
    from the check of the step's length (a stack of the odometry's translations): the
    refinement is the one without autocast, and odometry in millimetres is still the
    ValueError naming it."""
    pred, road, cam, images, odo = scene(B=2)
    odo = {k: v.to(half) for k, v in odo.items()}
    reference = run(FreespaceRefiner(), pred, road, cam, odometry=odo, images=images)
    assert bool(reference.refined.all())
    with torch.autocast("cpu", dtype=amp):
        got = run(FreespaceRefiner(), pred, road, cam, odometry=odo, images=images)
        assert torch.equal(got.flow, reference.flow) and torch.equal(got.refined, reference.refined)
        millimetres = {**odo, "z_d": odo["z_d"] * 1000}
        with pytest.raises(ValueError, match=r"^odometry: sample 0 moves 1\d{3}(\.\d+)? m in a frame"):
            run(FreespaceRefiner(), pred, road, cam, odometry=millimetres, images=images)


# -- the meta device ----------------------------------------------------------------------------------

def _meta_camera(cam: Camera) -> Camera:
    return Camera(cam.K.to("meta"), cam.height.to("meta"), cam.roll.to("meta"), cam.pitch.to("meta"))


def test_meta_device_shape_inference_with_odometry():
    """With the motion given (planar odometry without images, or a model's full motion) the
    refiner is geometry and fusion only: on meta tensors it returns meta tensors of the right
    shapes, for every output structure."""
    pred, road, cam, images, odo = scene(B=2)
    meta_cam = _meta_camera(cam)
    pyramid = [pred[..., ::4, ::4].to("meta"), pred.to("meta")]
    out = refine_flow(pyramid, road.to("meta"), meta_cam, {k: v.to("meta") for k, v in odo.items()},
                      mode="confidence")
    assert [f.device.type for f in out.flow] == ["meta", "meta"]
    assert [tuple(f.shape) for f in out.flow] == [(2, 2, 16, 48), (2, 2, *SIZE)]
    assert out.weight.shape == (2, 1, *SIZE) and out.mask.shape == (2, 1, *SIZE) and out.refined.shape == (2,)
    full = {"model": "plane", "z_d": 1.0, "pitch_change": 0.001}
    out = refine_flow(pred.to("meta"), road.to("meta"), meta_cam, full, gate=None,
                      images=tuple(im.to("meta") for im in images))
    assert out.flow.device.type == "meta" and out.model == "plane"
    net = FreespaceRefined(TinyRAFT(iters=1).eval(), FreespaceRefiner(gate=None))
    flows = net(*(im.to("meta") for im in images), camera=meta_cam, mask=road.to("meta"), odometry=full)
    assert flows[-1].device.type == "meta" and flows[-1].shape == (2, 2, *SIZE)  # (the net's list of iterations)


def test_meta_device_estimation_is_data_dependent():
    """Estimating the motion (a fit) and judging it by the images (the gate samples the mask's
    pixels) need values: a named ValueError, not torch's "Tensor.item() cannot be called"."""
    pred, road, cam, images, odo = scene(B=2)
    meta = dict(flow=pred.to("meta"), mask=road.to("meta"), camera=_meta_camera(cam))
    meta_images = tuple(im.to("meta") for im in images)
    with pytest.raises(ValueError, match="flow: a tensor on the meta device has shapes but no values to estimate"):
        refine_flow(**meta)
    with pytest.raises(ValueError, match="flow: a tensor on the meta device has shapes but no values to estimate"):
        refine_flow(**meta, odometry=odo, images=meta_images)  # planar odometry + images: the rest is fitted
    with pytest.raises(ValueError, match="prediction: a tensor on the meta device has shapes but no values to judge"):
        refine_flow(**meta, odometry={"model": "plane", "z_d": 1.0}, images=meta_images)
    with pytest.raises(ValueError, match="camera: a camera on the meta device has shapes but no values to move"):
        refine_flow(pred, road, meta["camera"], odo)  # a meta camera beside real tensors
    for given in (meta_images, None):  # (the road found in the images, or in the flow without them)
        with pytest.raises(ValueError, match=r"flow: a tensor on the meta device .* to find the road in \(mask='auto'"):
            refine_flow(meta["flow"], "auto", meta["camera"], images=given)


# -- a GPU's paths, run on the CPU -------------------------------------------------------------------
# On the CPU the pyramid, the blurs, the masks' erosions and pixel searches, and the auto road's box
# filters go through OpenCV or NumPy; on any other device through torch ops. device_paths() sends
# CPU tensors down the other devices' paths, so the code a GPU runs is tested end to end here.

def _both_paths(fn):
    from fsof_torch._check import device_paths

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        host = fn()
        with device_paths():
            other = fn()
    return host, other


def _same_refinement(host, other, atol: float) -> None:
    torch.testing.assert_close(other.flow, host.flow, rtol=0, atol=atol)
    assert torch.equal(other.mask, host.mask) and torch.equal(other.refined, host.refined)
    for k, v in host.odometry.items():
        torch.testing.assert_close(other.odometry[k], v, rtol=0, atol=1e-5)


@pytest.mark.parametrize("case", ["images", "odometry+images"])
def test_other_devices_paths_give_the_cpus_refinement(case):
    """The image estimator and the gate down other devices' paths (torch filters instead of
    OpenCV's) refine a rendered pair as the CPU's paths do: the filters' rounding apart (float32
    sums in another order), the same road flow to 1e-3 px, the same pixels refined."""
    pred, road, cam, images, odo = scene(B=2)
    kw = CASES[case](odo, images)
    host, other = _both_paths(lambda: run(FreespaceRefiner(), pred, road, cam, **kw))
    assert bool(host.refined.all())
    _same_refinement(host, other, atol=1e-3)


def test_other_devices_paths_find_the_cpus_auto_road():
    """``road="auto"`` down other devices' paths (box filters by average pools, erosions by
    min-pools, blurs by convolutions) finds the road the CPU's paths find, and refines it alike."""
    pred, _, cam, images, _ = scene(B=2)
    host, other = _both_paths(lambda: refine_flow(pred, "auto", cam, images=images))
    assert bool(host.mask.any()) and host.road.flag == ["ok", "ok"]
    assert torch.equal(other.road.mask, host.road.mask)
    _same_refinement(host, other, atol=1e-3)


def test_other_devices_paths_on_the_kitti_pair(shared_data):
    """The shared KITTI pair, DIS's flow refined by the default refiner and with the auto road:
    other devices' paths give the CPU's flow to 1e-3 px (measured: 2.2e-4 at most), the same road and the
    same pixels refined."""
    from refine.sources import dis_flow

    from fsof_torch.io.images import read_image
    from fsof_torch.io.masks import read_road_mask

    root = shared_data / "kitti15_000000"
    im1, im2 = (read_image(root / f"image_1{i}.png") for i in (0, 1))
    cam = Camera.from_kitti(root / "calib_cam_to_cam.txt", cam=2, height=1.65)
    road = read_road_mask(root / "road.json", tuple(im1.shape[-2:])).bool().reshape(1, 1, *im1.shape[-2:])
    flow, images = dis_flow(im1, im2)[None], (im1[None], im2[None])
    for mask in (road, "auto"):
        host, other = _both_paths(lambda: refine_flow(flow, mask, cam, images=images))
        assert bool(host.refined.any())
        _same_refinement(host, other, atol=1e-3)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_compiled_refiner_with_images_compiles_once():
    """The gate's memo of mask pixels, keyed by a mask's address, stays out of the trace: read
    there, its keys were guarded, and every call recompiled (6-7 times the eager time in
    ``benchmarks/bench_compile.py``; a backend that only traces shows it)."""
    from torch._dynamo.utils import counters

    pred, road, cam, images, _ = scene()
    torch._dynamo.reset()
    counters.clear()
    compiled = torch.compile(FreespaceRefiner(), backend="eager")
    run(compiled, pred, road, cam, images=images)
    first = counters["stats"]["unique_graphs"]
    for _ in range(2):
        run(compiled, pred, road, cam, images=images)
    assert counters["stats"]["unique_graphs"] == first
    torch._dynamo.reset()
