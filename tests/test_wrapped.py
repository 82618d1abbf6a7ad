"""``FreespaceRefined``: road="auto" is refine_flow's "auto" path (the refiner's estimator, the
call's odometry, road_options), with and without padding; the net's output size and the images'
range checked, named; with padding, the RefineOutput's fit on the input's grid."""

from __future__ import annotations

import re
import warnings

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from fsof_torch import Camera, detect_road, render_pair
from fsof_torch.refinement.contracts import InputPadder, ptlflow_inputs
from fsof_torch.refinement.estimators import ImageMotionEstimator
from fsof_torch.refinement.fusion import FreespaceRefiner, refine_flow
from fsof_torch.refinement.road_options import ROAD_VALUE_OPTIONS
from fsof_torch.refinement.wrapped import FreespaceRefined
from fsof_torch.training.standins import PtlflowRAFTStandIn


def scene(size):
    p = render_pair("default", 0, size=size)
    noise = torch.randn(p["flow"][None].shape, generator=torch.Generator().manual_seed(0))
    odometry = {k: float(p["odometry"][k]) for k in ("x_d", "z_d", "yaw")}
    return dict(image1=p["image1"][None], image2=p["image2"][None], road=p["road"][None],
                camera=p["camera"].to(torch.float32), odometry=odometry, pred=p["flow"][None] + 1.5 * noise)


@pytest.fixture(scope="module")
def wide():
    return scene((120, 400))


class Net(nn.Module):
    """Returns ``[flow / 2, flow]`` of a fixed prediction, replicated to the size it is given
    (the padded size with ``pad``); counts its calls."""

    def __init__(self, pred: torch.Tensor) -> None:
        super().__init__()
        self.pred, self.calls = pred, 0

    def forward(self, image1, image2):
        self.calls += 1
        dh, dw = image1.shape[-2] - self.pred.shape[-2], image1.shape[-1] - self.pred.shape[-1]
        flow = F.pad(self.pred, (dw // 2, dw - dw // 2, dh // 2, dh - dh // 2), mode="replicate")
        return [flow / 2, flow]


class Counting(ImageMotionEstimator):
    def __init__(self, **kw) -> None:
        super().__init__(**kw)
        self.calls = 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return super().__call__(*args, **kwargs)


# -- road="auto" is refine_flow(flow, "auto", ...) -------------------------------------------------------

@pytest.mark.parametrize("road_options", [None, {"window": 5}])
def test_auto_road_is_refine_flow_auto_with_the_refiners_estimator_and_odometry(wide, road_options):
    """The wrapper called detect_road without the estimator and the odometry, then refined with the
    detection's motion: the refiner's estimator was never called and planar odometry ignored."""
    s = wide
    net = Net(s["pred"])
    images = (s["image1"], s["image2"])
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for odometry in (None, s["odometry"]):
            estimator = Counting(model="paper")
            model = FreespaceRefined(net, FreespaceRefiner(estimator=estimator), road="auto",
                                     road_options=road_options)
            flows, info = model(*images, camera=s["camera"], odometry=odometry, return_info=True)
            assert estimator.calls > 0 and info.model == "paper"
            expected = refine_flow(net(*images), "auto", s["camera"], odometry, images=images,
                                   estimator=Counting(model="paper"), road_options=road_options)
            assert torch.equal(info.road.mask, expected.road.mask)
            assert torch.equal(flows[-1], expected.flow[-1]) and torch.equal(flows[0], expected.flow[0])
            for k, v in expected.odometry.items():
                assert torch.equal(info.odometry[k], v), k
            if odometry is not None:  # held, as the refiner holds it
                for k, v in odometry.items():
                    assert float(info.odometry[k]) == pytest.approx(v, abs=1e-6), k


@pytest.mark.parametrize("given", [False, True])
def test_auto_road_with_pad_uses_the_estimator_and_the_odometry(wide, given):
    s = wide
    odometry = s["odometry"] if given else None
    estimator = Counting(model="paper")
    model = FreespaceRefined(Net(s["pred"][..., :117, :397]), FreespaceRefiner(estimator=estimator), road="auto",
                             pad=InputPadder(8))
    image1, image2 = s["image1"][..., :117, :397], s["image2"][..., :117, :397]
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        flows, info = model(image1, image2, camera=s["camera"], odometry=odometry, return_info=True)
    assert estimator.calls > 0 and info.model == "paper"
    assert tuple(flows[-1].shape[-2:]) == (117, 397) and tuple(info.road.mask.shape[-2:]) == (117, 397)
    assert bool(info.refined.all()) and bool(info.mask.any())
    for k, v in (odometry or {}).items():
        assert float(info.odometry[k]) == pytest.approx(v, abs=1e-6), k


def test_auto_road_without_a_flow_key_says_so():
    """road='auto' said 'flow: expected at least one flow, got none'."""
    s = scene((53, 94))

    class DictNet(nn.Module):
        def forward(self, a, b):
            return {"flow_fw": [s["pred"]]}

    for road, kw in (("auto", {}), (None, {"mask": s["road"]})):
        with pytest.raises(ValueError, match=r"^flow: no flow found in the dict; expected a value under one of the "
                                             r"keys \('flow', .*\) \(set flow_keys\)$"):
            FreespaceRefined(DictNet(), road=road)(s["image1"], s["image2"], camera=s["camera"], **kw)


# -- the net's output at the input's size ------------------------------------------------------------------

@pytest.mark.parametrize("road, pad, given", [(None, None, "64 x 96"), ("auto", None, "64 x 96"),
                                              (None, InputPadder(16), "60 x 90 (padded to 64 x 96)")])
def test_a_net_with_only_a_coarse_flow_is_named(road, pad, given):
    """A PWC-style net (the flow at 1/4) got contradictory mask-size errors."""
    s = scene((60, 90) if pad is not None else (64, 96))

    class QuarterNet(nn.Module):
        def forward(self, a, b):
            return torch.zeros(a.shape[0], 2, a.shape[-2] // 4, a.shape[-1] // 4)

    mask = None if road == "auto" else s["road"]
    message = rf"^net: its finest flow is 16 x 24, the input {re.escape(given)}: the wrapper needs full-size output"
    with pytest.raises(ValueError, match=message + "; upsample it"):
        FreespaceRefined(QuarterNet(), road=road, pad=pad)(s["image1"], s["image2"], camera=s["camera"], mask=mask)


@pytest.mark.parametrize("pad, given", [(None, "53 x 94"), (InputPadder(8), "53 x 94 (padded to 56 x 96)")])
def test_a_net_that_leaves_its_own_padding_on_is_told_to_crop_it(pad, given):
    """A net that pads to a multiple of 32 itself and returns the padded flow (RAFT's code without
    ``padder.unpad``): the flow is larger than the input, and the error said to upsample it."""
    s = scene((53, 94))

    class PadsItself(nn.Module):
        def forward(self, a, b):
            return [torch.zeros(a.shape[0], 2, -(-a.shape[-2] // 32) * 32, -(-a.shape[-1] // 32) * 32)]

    message = (rf"^net: its finest flow is 64 x 96, the input {re.escape(given)}: the wrapper needs full-size output; "
               r"crop off the padding the net added \(RAFT's padder.unpad\), or give pad=InputPadder\(stride\)")
    with pytest.raises(ValueError, match=message):
        FreespaceRefined(PadsItself(), pad=pad)(s["image1"], s["image2"], camera=s["camera"], mask=s["road"])


def test_a_class_given_for_the_net_refiner_or_pad_is_named_when_built():
    """A network class given for the network (FreespaceRefined(RAFT)) passed the callable check: the
    first call built one from the two images (a TypeError from its __init__, or a module taken as
    the flow); a FreespaceRefiner or InputPadder class was 'got type'."""
    s = scene((48, 96))

    class TwoArgs(nn.Module):  # (its class called with the two images builds a module)
        def __init__(self, a=None, b=None):
            super().__init__()

        def forward(self, a, b):
            return [torch.zeros(a.shape[0], 2, *a.shape[-2:])]

    for kw, name, cls in ((dict(net=TwoArgs), "net", "TwoArgs"),
                          (dict(net=PtlflowRAFTStandIn), "net", "PtlflowRAFTStandIn"),
                          (dict(net=TwoArgs(), refiner=FreespaceRefiner), "refiner", "FreespaceRefiner"),
                          (dict(net=TwoArgs(), pad=InputPadder), "pad", "InputPadder")):
        with pytest.raises(TypeError, match=rf"^{name}: expected an instance, got the class {cls}; make one: "
                                            rf"{name}={cls}\(\.\.\.\)$"):
            FreespaceRefined(**kw)
    out = FreespaceRefined(TwoArgs())(s["image1"], s["image2"], camera=s["camera"], mask=s["road"],
                                      odometry=s["odometry"])
    assert isinstance(out, list) and out[0].shape == (1, 2, 48, 96)


@pytest.mark.parametrize("options", [
    {"window": 8}, {"height_window": 1}, {"window": "7"}, {"level": -1}, {"seed_level": 1.5}, {"z": -1.0},
    {"min_misfit_px": float("nan")}, {"seed_width_m": float("inf")}, {"min_height_m": 0.0},
    {"max_height_m": 0.05}, {"max_height_m": 2.0}, {"slow_max_height_m": 0.2}, {"slow_max_height_m": True},
    {"min_coverage": 1.5}, {"min_coverage": None}, {"window": torch.tensor(4)},
    {"edges": "yes"}, {"refit": 1}, {"edges": torch.tensor(True)}, {"refit": None}])
def test_road_option_values_are_checked_when_built_with_detect_roads_errors(wide, options):
    """A bad value of road="auto"'s road_options raised only at the first call, from detect_road,
    after the network had run (only the names were checked when made); now when made, with the
    error detect_road gives for it (its defaults for the options not given). The flags (edges,
    refit) too: they were left to the first call after the others were checked when made."""
    with pytest.raises((TypeError, ValueError)) as expected:
        detect_road(wide["image1"], wide["image2"], wide["camera"], **options)
    net = Net(wide["pred"])
    with pytest.raises(expected.type) as made:
        FreespaceRefined(net, road="auto", road_options=options)
    assert str(made.value) == str(expected.value) and str(made.value).split(":")[0] in ROAD_VALUE_OPTIONS
    assert net.calls == 0


@pytest.mark.parametrize("options, height", [
    ({"level": 4}, None), ({"height_window": 115}, None), ({"window": 25, "level": 2}, None),
    ({"min_height_m": 2.0, "max_height_m": 2.0, "slow_max_height_m": None}, None), ({}, 0.05)])
def test_road_options_against_the_images_and_camera_before_the_net(wide, options, height):
    """What only the images' size or the camera's height rules out (a level or window too large for
    them, a min_height_m above the camera) raised after the network had run; now before it, with
    detect_road's error."""
    camera = wide["camera"] if height is None else Camera(wide["camera"].K, height)
    with pytest.raises(ValueError) as expected:
        detect_road(wide["image1"], wide["image2"], camera, **options)
    net = Net(wide["pred"])
    with pytest.raises(ValueError) as called:
        FreespaceRefined(net, road="auto", road_options=options)(wide["image1"], wide["image2"], camera=camera)
    assert str(called.value) == str(expected.value) and str(called.value).split(":")[0] in ROAD_VALUE_OPTIONS
    assert net.calls == 0


def test_a_seed_level_too_deep_for_the_images_is_named_before_the_net(wide):
    """seed_level 3 leaves 15 rows of 120: where the detection estimates the motion (no odometry,
    or planar odometry alone) that raised detect_road's error only after the network had run; now
    before it. A complete motion (planar odometry with the refiner's fit, a model's dict) estimates
    nothing, and the option is unused: the call runs, as detect_road's does."""
    options = {"seed_level": 3}
    with pytest.raises(ValueError, match=r"^seed_level: 3 leaves fewer than 16 pixels of the 120x400 images") as expected:
        detect_road(wide["image1"], wide["image2"], wide["camera"], **options)
    for odometry in (None, wide["odometry"]):
        net = Net(wide["pred"])
        with pytest.raises(ValueError) as called:
            FreespaceRefined(net, road="auto", road_options=options)(wide["image1"], wide["image2"],
                                                                     camera=wide["camera"], odometry=odometry)
        assert str(called.value) == str(expected.value) and net.calls == 0
    net = Net(wide["pred"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (the road's verdicts: not what this test is about)
        model = FreespaceRefined(net, FreespaceRefiner(fit="flow"), road="auto", road_options=options)
        _, info = model(wide["image1"], wide["image2"], camera=wide["camera"], odometry=wide["odometry"],
                        return_info=True)
    assert net.calls == 1 and info.road is not None


def test_good_road_option_values_build_and_are_kept_as_given(wide):
    """Values detect_road takes build (a 0-d tensor, a max_height_m above the slow default with
    slow_max_height_m None, a level chosen from the images), and are passed on as given."""
    options = {"window": torch.tensor(5), "max_height_m": 2.0, "slow_max_height_m": None, "level": None}
    model = FreespaceRefined(Net(wide["pred"]), road="auto", road_options=options)
    assert model.road_options == options and model.road_options["window"] is options["window"]


@pytest.mark.parametrize("mask_batch", [1, 2])
def test_a_net_that_returns_another_batch_is_named(mask_batch):
    """A net that returns batch 1 for a batch of 2: the error names the net's output and quotes
    both batches (once it blamed the caller's images[0] or mask)."""
    s = scene((48, 96))
    image1, image2 = s["image1"].expand(2, -1, -1, -1), s["image2"].expand(2, -1, -1, -1)

    class OneFlowNet(nn.Module):
        def forward(self, a, b):
            return [torch.zeros(1, 2, *a.shape[-2:])]

    mask = s["road"].expand(mask_batch, -1, -1, -1)
    with pytest.raises(ValueError, match=r"^net: its finest flow has batch 1 \(shape \(1, 2, 48, 96\)\), the input "
                                         r"images batch 2"):
        FreespaceRefined(OneFlowNet())(image1, image2, camera=s["camera"], mask=mask, odometry=s["odometry"])


def test_a_net_that_returns_its_flow_on_another_device_is_named():
    """A flow on another device than the images' (here 'meta', on a machine with only a CPU): the
    error names the net and both devices (it blamed the caller's images[0])."""
    s = scene((48, 96))

    class MetaNet(nn.Module):
        def forward(self, a, b):
            return [torch.zeros(a.shape[0], 2, *a.shape[-2:], device="meta")]

    with pytest.raises(ValueError, match=r"^net: its finest flow is on meta, the input images on cpu: return the "
                                         r"flow on the images' device"):
        FreespaceRefined(MetaNet())(s["image1"], s["image2"], camera=s["camera"], mask=s["road"],
                                    odometry=s["odometry"])


# -- the images' range, before the net runs ------------------------------------------------------------------

@pytest.mark.parametrize("image_range, scale, message", [
    ((0, 255), 1 / 255, r"^image1: values in \[0\.05\d*, 0\.9\d*\] fill at most 1/255 of image_range=\(0, 255\) "
                        r"\(0\.\.1 images given for 0\.\.255\?\): pass image_range=\(0, 1\)"),
    ((0, 1), 1.0, r"^image1: expected values in image_range=\(0, 1\), got values in \[13\.\d*, 232\.\d*\] \(pass "
                  r"image_range=\(low, high\) of the images"),
])
def test_images_checked_against_image_range_before_the_net(image_range, scale, message):
    """The refiner found these after the net had run, named images[0], quoted converted values and
    advised data_range=, which the wrapper does not take."""
    s = scene((53, 94))
    net = Net(s["pred"])
    model = FreespaceRefined(net, FreespaceRefiner(), image_range=image_range)
    with pytest.raises(ValueError, match=message):
        model(s["image1"] * scale, s["image2"] * scale, camera=s["camera"], mask=s["road"])
    bad = s["image2"].clone()
    bad[..., 3, 4] = float("nan")
    with pytest.raises(ValueError, match=r"^image2: expected finite pixel values, got \[nan, nan, nan\] "
                                         r"\(NaN or inf\); replace or mask them"):
        FreespaceRefined(net)(s["image1"], bad, camera=s["camera"], mask=s["road"])
    assert net.calls == 0
    # images on the range stated run, as before
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        FreespaceRefined(net, image_range=(-1, 1))(s["image1"] / 127.5 - 1, s["image2"] / 127.5 - 1,
                                                   camera=s["camera"], mask=s["road"])
    assert net.calls == 1


def test_a_dim_sample_is_named_in_any_batch_and_taken_within_trust_image_range():
    """A frame whose brightest value is 1 grey level of 255 is refused as a likely 0..1 image alone
    and beside a bright frame alike (in a batch it ran, as the bright frame lifted the batch's
    maximum); a caller that knows its range (8-bit files) has it taken within trust_image_range(),
    where the refiner leaves that sample unrefined and refines the other."""
    import fsof_torch

    s = scene((53, 94))
    dim1, dim2 = ((s[k] > 128).float() for k in ("image1", "image2"))
    i1, i2 = torch.cat([s["image1"], dim1]), torch.cat([s["image2"], dim2])
    net = Net(torch.cat([s["pred"], s["pred"]]))
    for a, b in ((dim1, dim2), (i1, i2)):
        with pytest.raises(ValueError, match=r"^image1(\[1\])?: values in \[0, 1\] fill at most 1/255 of "
                                             r"image_range=\(0, 255\) .* fsof_torch.trust_image_range\(\)$"):
            FreespaceRefined(net)(a, b, camera=s["camera"], mask=s["road"])
    assert net.calls == 0
    with fsof_torch.trust_image_range(), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out = FreespaceRefined(net)(i1, i2, camera=s["camera"], mask=torch.cat([s["road"], s["road"]]),
                                    return_info=True)
    assert out[1].refined.tolist() == [True, False]


def test_images_of_another_channel_count_are_named_before_the_net():
    """RGBA frames ran the net, then the refiner named them images[0] ('as images[0] has')."""
    s = scene((53, 94))
    net = Net(s["pred"])
    rgba = [torch.cat([im, torch.full_like(im[:, :1], 255.0)], 1) for im in (s["image1"], s["image2"])]
    with pytest.raises(ValueError, match=r"^image1: expected 1 \(grey\) or 3 \(RGB\) channels, got shape "
                                         r"\(1, 4, 53, 94\)$"):
        FreespaceRefined(net)(rgba[0], rgba[1], camera=s["camera"], mask=s["road"])
    assert net.calls == 0


@pytest.mark.parametrize("pad", [None, InputPadder(8)])
@pytest.mark.parametrize("index", [0, 2, 3])
def test_images_without_samples_or_pixels_are_named_before_the_net(pad, index):
    """An empty batch ran the net, then the refiner named its flow (flow[0], at the padded size);
    an image without rows or columns was named size, by the padder."""
    s = scene((53, 94))
    net = Net(s["pred"])
    image1, image2, road = (x.narrow(index, 0, 0) for x in (s["image1"], s["image2"], s["road"]))
    shape = re.escape(str(tuple(image1.shape)))
    with pytest.raises(ValueError, match=rf"^image1: expected shape \(B, C, H, W\) with {'BCHW'[index]} >= 1, got {shape}$"):
        FreespaceRefined(net, pad=pad)(image1, image2, camera=s["camera"], mask=road)
    assert net.calls == 0


def test_reflect_padding_larger_than_the_image_is_named_before_the_net():
    """torch's own RuntimeError came from F.pad."""
    s = scene((53, 94))
    net = Net(s["pred"])
    image1, image2 = s["image1"][..., :3, :20], s["image2"][..., :3, :20]
    with pytest.raises(ValueError, match=r"^x: mode='reflect' pads a side by less than the image's size there, "
                                         r"got \(H, W\) = \(3, 20\) and Padding\(left=2, right=2, top=2, bottom=3\)"):
        FreespaceRefined(net, pad=InputPadder(8, pad_mode="reflect"))(image1, image2, camera=s["camera"],
                                                                      mask=s["road"][..., :3, :20])
    assert net.calls == 0
    # (a side padded by the size - 1 is what reflection can do)
    x = torch.arange(6.0).reshape(1, 1, 3, 2)
    assert torch.equal(InputPadder(4, pad_mode="reflect").padding((3, 2)).pad(x, mode="reflect"),
                       F.pad(x, (1, 1, 0, 1), mode="reflect"))


# -- with pad, the RefineOutput's fit on the input's grid -------------------------------------------------------

def test_pad_gives_the_fit_on_the_input_grid():
    """fit kept the padded grid's maps, camera and homography."""
    s = scene((53, 94))
    model = FreespaceRefined(PtlflowRAFTStandIn(seed=0).eval(), FreespaceRefiner(), pad=InputPadder(8))
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        _, info = model(ptlflow_inputs(s["image1"], s["image2"]), camera=s["camera"], mask=s["road"],
                        return_info=True)
    fit = info.fit
    for name in ("flow", "valid", "inliers"):
        assert tuple(getattr(fit, name).shape[-2:]) == (53, 94), name
    torch.testing.assert_close(fit.camera.K, s["camera"].K.reshape(fit.camera.K.shape), rtol=0, atol=0)
    torch.testing.assert_close(fit.camera.K, info.camera.K, rtol=0, atol=0)
    # its homography maps the input's pixels as the model flow moves them
    v, u = torch.meshgrid(torch.arange(53.0), torch.arange(94.0), indexing="ij")
    p = torch.stack([u, v, torch.ones_like(u)]).reshape(3, -1).double()
    q = fit.homography[0].double() @ p
    moved = (q[:2] / q[2] - p[:2]).reshape(2, 53, 94)
    m = info.mask[0, 0]
    assert bool(m.any())
    torch.testing.assert_close(moved[:, m].float(), info.flow_model[0][:, m], rtol=0, atol=1e-3)
    torch.testing.assert_close(fit.flow[0][:, m], info.flow_model[0][:, m], rtol=0, atol=1e-4)


class PWCLiteLike(nn.Module):
    """ARFlow's PWC-Lite contract: ``model(torch.cat([image1, image2], 1), with_bk=False)`` on 0..1,
    sides divisible by 64; ``{"flows_fw": [finest, ...]}`` (and ``"flows_bw"`` with ``with_bk``)."""

    def __init__(self, pred: torch.Tensor) -> None:
        super().__init__()
        self.pred = pred

    def forward(self, x, with_bk=False):
        assert x.shape[1] == 6 and x.shape[-2] % 64 == x.shape[-1] % 64 == 0 and 0 <= x.min() <= x.max() <= 1
        dh, dw = x.shape[-2] - self.pred.shape[-2], x.shape[-1] - self.pred.shape[-1]
        flow = F.pad(self.pred, (dw // 2, dw - dw // 2, dh // 2, dh - dh // 2), mode="replicate")
        out = {"flows_fw": [flow, F.avg_pool2d(flow, 2) / 2]}
        if with_bk:
            out["flows_bw"] = [-flow]
        return out


class TwoFrames(nn.Module):  # (the adapter of docs/contracts.md)
    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, image1, image2, **kw):
        return self.net(torch.cat([image1, image2], 1) / 255.0, **kw)


def test_arflows_call_needs_the_two_frame_adapter_the_docs_give(wide):
    """The wrapper calls net(image1, image2): ARFlow's PWC-Lite takes the pair as one tensor on
    0..1 (the docstring once listed it among the nets called with two images)."""
    net = PWCLiteLike(wide["pred"])
    args = (wide["image1"], wide["image2"])
    kw = dict(camera=wide["camera"], mask=wide["road"], odometry=wide["odometry"])
    with pytest.raises(AssertionError):  # (two images, 0..255: not its call)
        FreespaceRefined(net, pad=InputPadder(64))(*args, **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out, info = FreespaceRefined(TwoFrames(net), pad=InputPadder(64))(*args, with_bk=True, return_info=True, **kw)
    assert info.refined.tolist() == [True]
    fw, bw = out["flows_fw"][0], out["flows_bw"][0]
    assert fw.shape == bw.shape == wide["pred"].shape and out["flows_fw"][1].shape[-2:] == (64, 224)
    outside = ~info.mask.expand_as(fw)
    assert torch.equal(fw[outside], wide["pred"][outside]) and not torch.equal(fw, wide["pred"])
    assert torch.equal(bw, -wide["pred"])  # (backward flows come back as the network's)


@pytest.mark.parametrize("odometry, message", [
    ({"model": "velocity", "speed": 12.0}, "odometry: the 'velocity' model gives flow in px/s"),
    ({"x_d": 0.0, "z_d": 1.2}, r"odometry: missing keys \['yaw'\]"),
    ({"x_d": 0.0, "z_d": 1200.0, "yaw": 0.0}, r"odometry: sample 0 moves 1200 m in a frame .*in millimetres\?"),
    ({"x_d": 0.0, "z_d": float("nan"), "yaw": 0.0}, r"odometry\['z_d'\]: expected finite"),
    ({"x_d": 0.0, "z_d": torch.ones(3), "yaw": 0.0}, r"odometry\['z_d'\]: expected a float or a tensor of shape .*"
                                                     r"\(the images' batch\), got shape \(3,\)"),
])
def test_a_bad_odometry_is_named_before_the_network_runs(wide, odometry, message):
    """As the mask and the camera: a network's forward pass (seconds at KITTI size) once ran before
    the refiner refused the odometry."""
    net = Net(wide["pred"])
    model = FreespaceRefined(net, pad=InputPadder(8))
    with pytest.raises(ValueError, match=message):
        model(wide["image1"], wide["image2"], camera=wide["camera"], mask=wide["road"], odometry=odometry)
    assert net.calls == 0


class EitherCall(Net):
    """Net, called with two images or with ptlflow's dict (its flow all the same)."""

    def forward(self, *images):
        return super().forward(*(images[0]["images"].unbind(1) if len(images) == 1 else images))


class InPlace(EitherCall):
    """Changes its inputs in place, as some RAFT ports normalise theirs (RGB 0..255 -> [-1, 1])."""

    def forward(self, *images):
        for im in ([images[0]["images"]] if len(images) == 1 else images):
            im.div_(127.5).sub_(1.0)
        return super().forward(*images)


@pytest.mark.parametrize("ptlflow", [False, True])
@pytest.mark.parametrize("pad", [None, InputPadder(8)])
def test_a_net_that_changes_its_inputs_in_place_leaves_the_callers_images(wide, pad, ptlflow):
    """The net gets tensors of its own (also where the padding is zero, 120 x 400 with
    InputPadder(8)): the caller's images stay as they were, and the refiner reads them, not the
    net's normalised copies, so the output is the one of a net that leaves its inputs alone."""
    s = wide
    inputs = ((ptlflow_inputs(s["image1"], s["image2"]),) if ptlflow else
              (s["image1"].clone(), s["image2"].clone()))
    callers = [inputs[0]["images"]] if ptlflow else list(inputs)
    kept = [x.clone() for x in callers]
    call = dict(mask=s["road"], camera=s["camera"], odometry=s["odometry"])
    got = FreespaceRefined(InPlace(s["pred"]), pad=pad)(*inputs, **call)
    assert all(torch.equal(a, b) for a, b in zip(callers, kept))
    want = FreespaceRefined(EitherCall(s["pred"]), pad=pad)(*inputs, **call)
    assert all(torch.equal(a, b) for a, b in zip(got, want))


@pytest.mark.parametrize("change, error, message", [
    (lambda im: im.double(), TypeError, r"^image2: expected the dtype of image1 \(torch.float32\), got torch.float64$"),
    (lambda im: im.to("meta"), ValueError, r"^image2: expected the device of image1 \(cpu\), got meta$"),
])
def test_images_of_another_dtype_or_device_are_named_before_the_net(change, error, message):
    """A float64 image2 beside a float32 image1 reached the net (torch's 'Input type (double) and bias
    type (float) should be the same' from its first layer); one on another device was named
    images[1], the refiner's name, after the net had run."""
    s = scene((53, 94))
    net = Net(s["pred"])
    with pytest.raises(error, match=message):
        FreespaceRefined(net)(s["image1"], change(s["image2"]), camera=s["camera"], mask=s["road"])
    assert net.calls == 0
