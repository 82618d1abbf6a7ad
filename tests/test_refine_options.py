"""The refiner's options and the network contracts at their edges: options checked whatever the
call estimates, flow_keys read once, padding sizes and modes, forwarded options that name the
fits' inputs, road_options, dict subclasses, the wrapper's checks before the network runs, and
ptlflow's input range."""

from __future__ import annotations

import collections
import math
import warnings

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.egomotion import EgoMotion
from fsof_torch.geometry.road_flow import displacement_flow
from fsof_torch.refinement.contracts import (
    InputPadder,
    Padding,
    collect_flows,
    map_flows,
    ptlflow_inputs,
)
from fsof_torch.refinement.estimators import FlowMotionEstimator, ImageMotionEstimator
from fsof_torch.refinement.fusion import FreespaceRefiner, refine_flow
from fsof_torch.refinement.wrapped import FreespaceRefined

H, W = 48, 120
ODO = {"x_d": 0.05, "z_d": 1.0, "yaw": 0.01}


def make_case(B: int = 1):
    """A camera, the model flow of ODO, a noisy prediction, the road mask (below row 24) and two
    0..255 images."""
    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[90.0, 0, 60.0], [0, 90.0, 14.0], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K.expand(B, 3, 3), 1.65)
    gt, valid = displacement_flow(Camera(K, 1.65), ODO["x_d"], ODO["z_d"], ODO["yaw"], (H, W))
    gt, valid = gt.expand(B, 2, H, W), valid.expand(B, 1, H, W)
    pred = (gt + torch.randn(gt.shape, generator=g, dtype=gt.dtype)).float()
    mask = valid.clone()
    mask[..., : H // 2, :] = False
    image = torch.rand(B, 3, H, W, generator=g) * 255
    return pred, mask, cam, (image, image.roll(1, dims=-1))


class Spy:
    """A road-motion estimator that counts its calls (the flow fit inside)."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        return FlowMotionEstimator()(*args, **kwargs)


# -- the estimator's options are checked whether or not odometry leaves anything to estimate ---------

@pytest.mark.parametrize("odometry, images, options, message", [
    # planar odometry, no images: the flow fit would run, which takes no photometric_options
    ("planar", False, dict(photometric_options={"max_iter": 3}),
     "photometric_options: applies with fit='photometric'; here fit='flow'"),
    # a complete motion, images: the default image estimator would run, which takes no fit_roll
    ("complete", True, dict(fit_roll=True),
     "fit_roll: applies with fit='flow' or 'photometric'; here the default image estimator runs"),
    # planar odometry with fit= set: nothing is estimated, but fit='flow' takes no photometric_options
    ("planar", True, dict(fit="flow", photometric_options={"max_iter": 3}),
     "photometric_options: applies with fit='photometric'; here fit='flow'"),
    # an estimator given, with odometry: its options are its own
    ("planar", False, dict(estimator=FlowMotionEstimator(), fit_options={"max_iter": 3}),
     "fit_options: applies with fit='flow'; here an estimator is given"),
])
def test_inconsistent_estimator_options_raise_also_with_odometry(odometry, images, options, message):
    """Once these passed silently whenever the odometry made estimation unnecessary."""
    pred, mask, cam, pair = make_case()
    odo = {"model": "plane", **ODO} if odometry == "complete" else ODO
    with pytest.raises(ValueError, match=message):
        refine_flow(pred, mask, cam, odo, images=pair if images else None, **options)
    with pytest.raises(ValueError, match=message):
        FreespaceRefiner(**options)(pred, mask, cam, odo, images=pair if images else None)


@pytest.mark.parametrize("options, message", [
    (dict(estimator=FlowMotionEstimator(), fit_roll=True),
     "fit_roll: applies with fit='flow' or 'photometric'; here an estimator is given"),
    (dict(estimator=FlowMotionEstimator(), fit_options={"max_iter": 3}), "fit_options: applies with fit='flow'; here an "
                                                                          "estimator is given"),
    (dict(fit="flow", photometric_options={"max_iter": 3}), "photometric_options: applies with fit='photometric'; "
                                                            "here fit='flow'"),
    (dict(fit="photometric", fit_options={"max_iter": 3}), "fit_options: applies with fit='flow'; here "
                                                           "fit='photometric'"),
])
def test_options_that_fit_no_call_are_refused_when_the_refiner_is_made(options, message):
    """Where the estimator does not depend on the call's images (one given, or fit= set), a
    combination that raises on every call was taken when the refiner was made: a training script
    learnt of it at its first batch. Those the images decide (fit=None) are judged at the call."""
    with pytest.raises(ValueError, match=f"^{message}"):
        FreespaceRefiner(**options)
    pred, mask, cam, _ = make_case()
    refiner = FreespaceRefiner(fit_roll=True, fit_options={"max_iter": 3}, gate=None, warn=False)
    assert bool(refiner(pred, mask, cam).refined.all())  # (no images: the flow fit takes them)
    FreespaceRefiner(fit="photometric", fit_pitch=True, photometric_options={"max_iter": 3})


def test_an_estimator_with_odometry_is_left_unused_not_refused():
    """A refiner configured with an estimator may be given odometry on some batches: then the
    estimator is not called, and nothing raises."""
    pred, mask, cam, _ = make_case()
    spy = Spy()
    refiner = FreespaceRefiner(estimator=spy, gate=None, warn=False)
    out = refiner(pred, mask, cam, ODO)
    assert spy.calls == 0 and out.fit is None and bool(out.refined.all())
    out = refiner(pred, mask, cam)
    assert spy.calls == 1 and out.fit is not None


def test_options_checked_before_the_road_is_detected():
    pred, mask, cam, _ = make_case()
    with pytest.raises(ValueError, match="photometric_options: applies with fit='photometric'; here fit='flow'"):
        refine_flow(pred, "auto", cam, ODO, photometric_options={"max_iter": 3})


# -- flow_keys ------------------------------------------------------------------------------------------

def test_flow_keys_none_is_refused_by_name():
    """Once a raw ``TypeError: 'NoneType' object is not iterable`` from inside contracts.py."""
    pred, mask, cam, _ = make_case()
    message = r"^flow_keys: expected a key or a sequence of keys \(str\) .*, got NoneType None$"
    with pytest.raises(TypeError, match=message):
        refine_flow(pred, mask, cam, ODO, flow_keys=None)
    with pytest.raises(TypeError, match=message):
        FreespaceRefiner(flow_keys=None)
    with pytest.raises(TypeError, match=message):
        collect_flows({"flow": pred}, "flow", None)
    with pytest.raises(TypeError, match=message):
        map_flows({"flow": pred}, lambda f: f, None)
    with pytest.raises(TypeError, match=r"^flow_keys: .*got tuple \('flows', 3\)$"):
        refine_flow(pred, mask, cam, ODO, flow_keys=["flows", 3])


def test_flow_keys_generator_is_read_once():
    """A generator was consumed by the option check, and then no flow was found."""
    pred, mask, cam, _ = make_case()
    output = {"flows": pred[:, None], "other": pred[:, None]}
    expected = refine_flow(output, mask, cam, ODO, flow_keys=("flows",))
    out = refine_flow(output, mask, cam, ODO, flow_keys=(k for k in ["flows"]))
    assert torch.equal(out.flow["flows"], expected.flow["flows"])
    assert not torch.equal(out.flow["flows"], pred[:, None]) and out.flow["other"] is output["other"]
    refiner = FreespaceRefiner(flow_keys=(k for k in ["flows"]))
    assert refiner.flow_keys == ("flows",)
    assert torch.equal(refiner(output, mask, cam, ODO).flow["flows"], expected.flow["flows"])


# -- forwarded options that name the fits' own inputs -----------------------------------------------------

@pytest.mark.parametrize("name", ["flow", "mask", "camera"])
def test_fit_options_naming_the_fits_inputs_are_refused(name):
    """Once accepted, then "fit_road() got multiple values for argument" at the first call."""
    pred, mask, cam, _ = make_case()
    message = rf"fit_options: options \['{name}'\] of \w+ are set by .*, not through fit_options"
    with pytest.raises(TypeError, match=message):
        FreespaceRefiner(fit_options={name: None})
    with pytest.raises(TypeError, match=message):
        refine_flow(pred, mask, cam, fit_options={name: None})
    with pytest.raises(TypeError, match=rf"options: options \['{name}'\] of \w+ are set by the function that forwards"):
        FlowMotionEstimator(**{name: None})


@pytest.mark.parametrize("options, error, match", [
    ({"max_iter": -1}, ValueError, r"^max_iter: expected an int > 0, got -1"),
    ({"robust": "bogus"}, ValueError, r"^robust: expected one of"),
    ({"scale": 0.0}, ValueError, r"^scale: expected a finite number > 0, got 0.0"),
    ({"polish": "yes"}, TypeError, r"^polish: expected True or False, got str 'yes'"),
    ({"bounds": "x"}, ValueError, r"^bounds: expected 'physical' or None, got 'x'"),
    ({"check_every": 0}, ValueError, r"^check_every: expected 'auto', an int >= 1"),
    ({"prior": {"bogus": (0.0, 1.0)}}, ValueError, r"^prior: unknown parameter 'bogus' of model 'paper'"),
    ({"prior": {"roll": (0.0, 0.01)}}, ValueError, r"^prior: 'roll' is held at its start"),
])
def test_fit_options_values_are_checked_when_made(options, error, match):
    """The flow fit's option values were checked only by the first fit: a refiner (or flow estimator)
    with a bad one ran on without a word while odometry was given, and failed at the first call
    without it. Now when made, and at every call, with odometry too (as the image estimator's)."""
    pred, mask, cam, _ = make_case()
    with pytest.raises(error, match=match):
        FlowMotionEstimator(**options)
    # the refiner's errors name the option as a key of the mapping it came in, not a refiner argument
    (key,) = options
    keyed = match.replace(f"^{key}:", f"^fit_options\\['{key}'\\]:")
    with pytest.raises(error, match=keyed):
        FreespaceRefiner(fit="flow", fit_options=options)
    with pytest.raises(error, match=keyed):
        refine_flow(pred, mask, cam, ODO, fit="flow", fit_options=options)
    if set(options) <= {"max_iter", "robust", "scale"}:  # (options the image fit shares, checked alike)
        with pytest.raises(error, match=keyed.replace("fit_options", "photometric_options")):
            FreespaceRefiner(fit="photometric", photometric_options=options)
    # a prior on a parameter the flags free is taken
    FreespaceRefiner(fit="flow", fit_roll=True, fit_options={"prior": {"roll": (0.0, 0.01)}})


def test_a_forwarded_option_is_not_named_as_the_refiners_own_argument():
    """``fit_options={"scale": -1.0}`` beside the refiner's own ``scale=2.0`` raised "scale: expected a
    finite number > 0, got -1.0", naming the refiner's own argument, which was valid. The message
    names the mapping and its key, for ``photometric_options`` too."""
    pred, mask, cam, pair = make_case()
    with pytest.raises(ValueError, match=r"^fit_options\['scale'\]: expected a finite number > 0, got -1.0$"):
        FreespaceRefiner(mode="confidence", scale=2.0, fit="flow", fit_options={"scale": -1.0})
    with pytest.raises(ValueError, match=r"^photometric_options\['levels'\]: expected an int >= 1, got -1$"):
        refine_flow(pred, mask, cam, images=pair, fit="photometric", photometric_options={"levels": -1})
    # the refiner's own scale keeps its name
    with pytest.raises(ValueError, match=r"^scale: expected a positive number \(> 0\), got -1.0$"):
        FreespaceRefiner(mode="confidence", scale=-1.0, fit="flow", fit_options={"scale": 2.0})


@pytest.mark.parametrize("name", ["image1", "image2", "mask", "camera"])
def test_photometric_options_naming_the_fits_inputs_are_refused(name):
    pred, mask, cam, pair = make_case()
    message = rf"photometric_options: options \['{name}'\] of \w+ are set by the function that forwards"
    with pytest.raises(TypeError, match=message):
        FreespaceRefiner(fit="photometric", photometric_options={name: None})
    with pytest.raises(TypeError, match=message):
        refine_flow(pred, mask, cam, images=pair, fit="photometric", photometric_options={name: None})
    with pytest.raises(TypeError, match=rf"options: options \['{name}'\] of \w+ are set by the function that forwards"):
        ImageMotionEstimator(**{name: None})


# -- road_options --------------------------------------------------------------------------------------

def test_road_options_with_a_mask_tensor_are_refused():
    """Once silently ignored: a mask tensor detects nothing."""
    pred, mask, cam, _ = make_case()
    with pytest.raises(ValueError, match=r"^road_options: apply to the road detection of mask='auto'; with a mask "
                                         r"tensor nothing is detected, got road_options=\{'window': 5\}$"):
        refine_flow(pred, mask, cam, ODO, road_options={"window": 5})
    # none given, or an empty mapping: nothing to leave aside
    for empty in (None, {}):
        assert bool(refine_flow(pred, mask, cam, ODO, road_options=empty).refined.all())


@pytest.mark.parametrize("bad, shown", [(5, "int 5"), ([("window", 5)], r"list \[\('window', 5\)\]")])
def test_road_options_not_a_mapping_named(bad, shown):
    """Once a raw TypeError from inside auto_road.py."""
    pred, mask, cam, pair = make_case()
    message = rf"^road_options: expected None or a dict with string keys, got {shown}$"
    with pytest.raises(TypeError, match=message):
        refine_flow(pred, "auto", cam, ODO, images=pair, road_options=bad)
    with pytest.raises(TypeError, match=message):
        FreespaceRefined(Net(), road="auto", road_options=bad)


def test_wrapper_road_options_need_road_auto():
    with pytest.raises(ValueError, match=r"^road_options: apply to the road detection of road='auto'; with "
                                         r"road=None nothing is detected, got road_options=\{'window': 5\}$"):
        FreespaceRefined(Net(), road=None, road_options={"window": 5})
    assert FreespaceRefined(Net(), road="auto", road_options={"window": 5}).road_options == {"window": 5}


def test_wrapper_road_options_data_range_refused_when_built():
    """Once accepted here, and refused by refine_flow only after the network had run."""
    message = r"^road_options: options \['data_range'\] of \w+ are set by .*, not through road_options$"
    with pytest.raises(TypeError, match=message):
        FreespaceRefined(Net(), road="auto", road_options={"data_range": 1.0})
    pred, _, cam, pair = make_case()
    with pytest.raises(TypeError, match=message):
        refine_flow(pred, "auto", cam, images=pair, road_options={"data_range": 1.0})


# -- dict subclasses keep their type --------------------------------------------------------------------

def test_map_flows_keeps_a_defaultdict_and_its_factory():
    """A defaultdict came back as a plain dict (its constructor takes the factory first)."""
    flow, occ = torch.zeros(1, 2, 4, 6), torch.zeros(1, 1, 4, 6)
    output = collections.defaultdict(list, {"flows": flow[:, None], "occ": occ})
    mapped = map_flows(output, lambda f: f + 1)
    assert type(mapped) is collections.defaultdict and mapped.default_factory is list
    assert mapped is not output and output["flows"] is not mapped["flows"]
    assert torch.equal(mapped["flows"], flow[:, None] + 1) and mapped["occ"] is occ
    assert torch.equal(output["flows"], flow[:, None])  # the caller's dict as it was
    assert mapped["missing"] == []  # the factory works

    ordered = collections.OrderedDict([("occ", occ), ("flow_up", flow), ("flow_low", flow[..., ::2, ::2])])
    mapped = map_flows(ordered, lambda f: f + 1)
    assert type(mapped) is collections.OrderedDict and list(mapped) == ["occ", "flow_up", "flow_low"]
    assert float(mapped["flow_low"].min()) == 1.0 and mapped["occ"] is occ


def test_refiner_and_padding_keep_a_defaultdict():
    pred, mask, cam, _ = make_case()
    out = refine_flow(collections.defaultdict(list, {"flows": pred[:, None]}), mask, cam, ODO)
    assert type(out.flow) is collections.defaultdict and out.flow.default_factory is list
    padded = Padding(1, 1, 0, 0)
    cropped = padded.unpad_output(collections.defaultdict(int, {"flows": torch.zeros(1, 1, 2, 4, 8)}), (4, 8))
    assert type(cropped) is collections.defaultdict and cropped.default_factory is int
    assert cropped["flows"].shape == (1, 1, 2, 4, 6)


# -- InputPadder.padding and Padding.pad ------------------------------------------------------------------

def test_padding_size_is_a_pair_of_positive_ints():
    padder = InputPadder(8)
    assert padder.padding(torch.Size([61, 122])) == padder.padding((61, 122)) == Padding(3, 3, 1, 2)
    assert padder.padding(torch.zeros(1, 3, 61, 122).shape[-2:]) == Padding(3, 3, 1, 2)
    # RAFT's InputPadder takes the whole shape; read as (H, W) it would pad by B and C
    with pytest.raises(TypeError, match=r"^size: expected \(H, W\), got \(1, 3, 64, 100\); for an image's shape "
                                        r"pass image.shape\[-2:\]$"):
        padder.padding(torch.Size([1, 3, 64, 100]))
    with pytest.raises(ValueError, match=r"^size: expected positive sides \(H, W\), got \(0, -3\)$"):
        padder.padding((0, -3))
    with pytest.raises(TypeError, match=r"^size: expected integer sides \(H, W\), got \(61.5, 122\)$"):
        padder.padding((61.5, 122))
    with pytest.raises(TypeError, match=r"^size: expected \(H, W\), got 61$"):
        padder.padding(61)


@pytest.mark.parametrize("mode", ["replicate", "reflect", "constant"])
def test_pad_a_2d_tensor(mode):
    """Once a raw NotImplementedError from F.pad in replicate and reflect modes."""
    x = torch.arange(30, dtype=torch.float32).reshape(5, 6)
    p = Padding(1, 2, 3, 4)
    y = p.pad(x, mode=mode)
    assert y.shape == (12, 9)
    assert torch.equal(y, F.pad(x[None, None], (1, 2, 3, 4), mode=mode)[0, 0])
    assert torch.equal(p.unpad(y), x)


def test_pad_mode_and_dims_checked():
    x = torch.zeros(1, 3, 5, 6)
    for p in (Padding(1, 2, 3, 4), Padding()):  # (also where nothing is padded)
        with pytest.raises(ValueError, match=r"^mode: expected one of \('replicate', 'reflect', 'constant'\), "
                                             r"got 'zeros'$"):
            p.pad(x, mode="zeros")
    with pytest.raises(ValueError, match=r"^x: expected at least 2 dimensions \(..., H, W\), got shape \(6,\)$"):
        Padding(1, 1, 1, 1).pad(torch.zeros(6))


# -- the wrapper checks the caller's mask and camera before the network runs ------------------------------

class Net(nn.Module):
    """Zero flow at the input size; counts its calls."""

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def forward(self, image1, image2):
        self.calls += 1
        return [torch.zeros(image1.shape[0], 2, *image1.shape[-2:])]


SMALL = (45, 118)  # padded by InputPadder(8) to (48, 120)


@pytest.mark.parametrize("kw, error, message", [
    (dict(camera=None), TypeError, r"^camera: expected a fsof_torch.Camera, got NoneType$"),
    (dict(mask=None), ValueError, r"^mask: expected a road mask \(B, 1, H, W\) bool, got None"),
    (dict(mask="uint8"), TypeError, r"^mask: expected a bool tensor \(B, 1, H, W\), got dtype torch.uint8$"),
    # the caller's shapes, never the padded (48, 120)
    (dict(mask="short"), ValueError, r"^mask: expected shape \(1, 1, 45, 118\) \(the images' batch and size; "
                                     r"batch 1 is broadcast\), got \(1, 1, 44, 118\)$"),
    (dict(mask="3d"), ValueError, r"^mask: expected shape \(1, 1, 45, 118\) .*, got \(1, 45, 118\)$"),
    (dict(camera="batch 3"), ValueError, r"^camera: expected batch 1 \(the images' batch\), got 3$"),
])
@pytest.mark.parametrize("contract", ["two images", "ptlflow"])
def test_wrapper_checks_before_the_network_runs(kw, error, message, contract):
    """These were found after the network had run, and with ``pad`` a wrong mask was reported
    with the padded size."""
    _, mask, cam, (image1, image2) = make_case()
    image1, image2 = image1[..., :SMALL[0], :SMALL[1]], image2[..., :SMALL[0], :SMALL[1]]
    mask = mask[..., :SMALL[0], :SMALL[1]]
    given = {"mask": mask, "camera": cam, **kw}
    given["mask"] = {"uint8": mask.to(torch.uint8), "short": mask[..., 1:, :], "3d": mask[:, 0]}.get(
        given["mask"], given["mask"])
    given["camera"] = cam.expand(3) if given["camera"] == "batch 3" else given["camera"]
    net = Net()
    model = FreespaceRefined(net, FreespaceRefiner(gate=None, warn=False), pad=InputPadder(8))
    inputs = (ptlflow_inputs(image1, image2),) if contract == "ptlflow" else (image1, image2)
    if contract == "ptlflow":
        model.net = PtlflowNet(net)
    with pytest.raises(error, match=message):
        model(*inputs, odometry=ODO, **given)
    assert net.calls == 0
    # and the same wrapper with the right arguments runs the network once
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        model(*inputs, odometry=ODO, mask=mask, camera=cam)
    assert net.calls == 1


class PtlflowNet(nn.Module):
    def __init__(self, net: Net) -> None:
        super().__init__()
        self.net = net

    def forward(self, inputs):
        images = inputs["images"]
        return {"flows": self.net(images[:, 0], images[:, 1])[0][:, None]}


def test_wrapper_images_of_two_shapes_named_before_the_network_runs():
    _, _, cam, (image1, image2) = make_case()
    net = Net()
    with pytest.raises(ValueError, match=r"^image2: expected the shape of image1 \(1, 3, 48, 120\), "
                                         r"got \(1, 3, 47, 120\)$"):
        FreespaceRefined(net)(image1, image2[..., 1:, :], camera=cam, mask=torch.ones(1, 1, H, W, dtype=torch.bool))
    assert net.calls == 0


# -- ptlflow_inputs checks the images' range ---------------------------------------------------------------

def test_ptlflow_inputs_checks_range_and_finiteness():
    """0..1 images once became near-black ptlflow inputs, and NaN passed."""
    _, _, _, (image1, image2) = make_case()
    with pytest.raises(ValueError, match=r"^image1: values in \[.*\] look like 0..1 images, expected 0..255"):
        ptlflow_inputs(image1 / 255, image2 / 255)
    torch.testing.assert_close(ptlflow_inputs(image1 / 255, image2 / 255, data_range=1.0)["images"],
                               ptlflow_inputs(image1, image2)["images"])
    bad = image2.clone()
    bad[0, 1, 3, 4] = float("nan")
    with pytest.raises(ValueError, match=r"^image2: expected finite pixel values, got \[nan\]"):
        ptlflow_inputs(image1, bad)
    with pytest.raises(ValueError, match=r"^image1: expected values in \[0, data_range=255\], got values in"):
        ptlflow_inputs(image1 * 2, image2)
    with pytest.raises(ValueError, match=r"^data_range: expected a positive finite number .*, got 0"):
        ptlflow_inputs(image1, image2, data_range=0)
    with pytest.raises(TypeError, match=r"^data_range: expected a positive finite number .*, got '255'"):
        ptlflow_inputs(image1, image2, data_range="255")


# -- a velocity motion is not a per-frame target ---------------------------------------------------------

@pytest.mark.parametrize("mask_kind", ["tensor", "auto"])
def test_velocity_odometry_is_refused_by_name(mask_kind):
    """The "velocity" model's flow is px/s: once it replaced a per-frame prediction by it silently
    (the road set to 10x its displacement at 10 Hz). With mask="auto" it raises before the road is
    detected."""
    pred, mask, cam, pair = make_case()
    road = mask if mask_kind == "tensor" else "auto"
    message = r"^odometry: the 'velocity' model gives flow in px/s, not the pixels per frame this needs"
    for odo in ({"model": "velocity", "speed": 10.0}, {"model": "velocity", "speed": 10.0, "yaw_rate": 0.1}):
        with pytest.raises(ValueError, match=message):
            refine_flow(pred, road, cam, odo, images=pair)
        with pytest.raises(ValueError, match=message):
            FreespaceRefiner()(pred, road, cam, odo, images=pair if mask_kind == "auto" else None)
    # the same motion over the frame interval, as a displacement model, is taken
    out = refine_flow(pred, mask, cam, {"model": "paper", **ODO}, gate=None, warn=False)
    assert bool(out.refined.all())


def test_a_velocity_estimator_is_refused_by_name():
    """A flow estimator of the "velocity" model refined with a rate's flow, in px/s (taken, as
    odometry of that model is not): refused when made, as the image estimator refuses it."""
    with pytest.raises(ValueError, match=r"^model: the flow estimator needs a displacement model \('paper', 'plane' "
                                         r"or 'homography'\), not 'velocity'"):
        FlowMotionEstimator(model="velocity")
    with pytest.raises(ValueError, match=r"^model: the image estimator needs a displacement model"):
        ImageMotionEstimator(model="velocity")
    pred, mask, cam, _ = make_case()
    # every displacement model with the default fixed (the homography's: nothing; it has no attitude
    # to hold, and raised "fixed: unknown parameters ['pitch', 'roll']" at the first call)
    for model in ("paper", "plane", "homography"):
        out = refine_flow(pred, mask, cam, estimator=FlowMotionEstimator(model=model), gate=None, warn=False)
        assert out.model == model and bool(out.refined.all())
    assert FlowMotionEstimator(model="homography").fixed == () and FlowMotionEstimator().fixed == ("roll", "pitch")
    with pytest.raises(ValueError, match=r"^fixed: unknown parameters \['roll'\] of model 'homography'"):
        FlowMotionEstimator(model="homography", fixed=("roll",))  # (when made, not at the first call)


# -- odometry beyond a road vehicle's step is named ----------------------------------------------------

@pytest.mark.parametrize("mask_kind", ["tensor", "auto"])
def test_odometry_in_millimetres_is_refused_by_name(mask_kind):
    """Odometry a kilometre a frame (millimetres for metres) once left every sample unchanged
    with only the generic "left unchanged" warning; a step beyond 100 m (100 m/s for 1 s, as the
    poses' check) names the odometry and the sample, in every form, with or without images (with
    mask="auto" before the road is detected); a long step within it is taken."""
    pred, mask, cam, pair = make_case(B=2)
    road = mask if mask_kind == "tensor" else "auto"
    z_d = torch.tensor([1.0, 1200.0])
    forms = [{"x_d": 0.0, "z_d": z_d, "yaw": 0.0}, EgoMotion(torch.zeros(2), z_d, torch.zeros(2)),
             {"model": "paper", "z_d": z_d}, {"model": "plane", "z_d": z_d}]
    message = (r"^odometry: sample 1 moves 1200 m in a frame \(.*z_d 1200\), farther than a road vehicle travels "
               r"between two frames \(100 m: 100 m/s for 1 s\); in millimetres\?")
    for odo in forms:
        for images in (None, pair):
            with pytest.raises(ValueError, match=message):
                refine_flow(pred, road, cam, odo, images=images if mask_kind == "tensor" else pair)
        with pytest.raises(ValueError, match=message):
            FreespaceRefiner()(pred, road, cam, odo, images=pair)
    with pytest.raises(ValueError, match=r"^odometry: sample 0 moves 150 m in a frame \(x_d 90, y_d 0, z_d 120\)"):
        refine_flow(pred, road, cam, {"model": "plane", "x_d": 90.0, "y_d": 0.0, "z_d": 120.0}, images=pair)
    # a fit result is an estimate, judged by its success, not a measurement in other units: a diverged
    # sample of it is refined as before (left unchanged where its model is undefined), not refused
    import dataclasses

    from fsof_torch import fit_road

    fit = fit_road(pred, mask, cam, model="plane")
    diverged = dataclasses.replace(fit, params={**fit.params, "z_d": torch.tensor([1.0, 1200.0])},
                                   success=torch.tensor([True, False]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert refine_flow(pred, mask, cam, diverged, gate=None).refined.tolist() == [True, False]
    # 60 m a frame (600 m/s at 10 Hz) is absurd for a car, but within the bound: taken, as before
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        refine_flow(pred, mask, cam, {"x_d": 0.0, "z_d": 60.0, "yaw": 0.0}, gate=None)
    out = refine_flow(pred, mask, cam, ODO, gate=None, warn=False)
    assert bool(out.refined.all())


def test_a_yaw_of_half_a_turn_and_a_rate_are_named():
    """A yaw in degrees (30 "rad" a frame, taken and refined with a wrapped turn) and wheel
    odometry given as a rate (speed, yaw_rate; named only as missing keys) say what they are."""
    pred, mask, cam, pair = make_case(B=2)
    message = r"^odometry: sample 1 turns by -30 rad in a frame, half a turn or more \(\|yaw\| >= π\); in degrees\?"
    for odo in ({"x_d": 0.0, "z_d": 1.0, "yaw": torch.tensor([0.01, -30.0])},
                {"model": "plane", "z_d": 1.0, "yaw": torch.tensor([0.01, -30.0])}):
        for images in (None, pair):
            with pytest.raises(ValueError, match=message):
                refine_flow(pred, mask, cam, odo, images=images)
    with pytest.raises(ValueError, match=r"^odometry: sample 0 turns by 3.142 rad"):
        refine_flow(pred, mask, cam, {"x_d": 0.0, "z_d": 1.0, "yaw": math.pi})
    with warnings.catch_warnings():  # (a sharp turn, but less than half a turn: taken)
        warnings.simplefilter("ignore")
        refine_flow(pred, mask, cam, {"x_d": 0.0, "z_d": 1.0, "yaw": 3.0}, gate=None)
    with pytest.raises(ValueError, match=r"^odometry: missing keys \['x_d', 'z_d', 'yaw'\]; .*got keys \['speed', "
                                         r"'yaw_rate'\]; a speed and a yaw rate are a rate: integrate them over the "
                                         r"frame interval \(fs.ego_motion_from_ackermann\)"):
        refine_flow(pred, mask, cam, {"speed": 10.0, "yaw_rate": 0.1})


# -- an estimator class given for an estimator, and what an estimator returns -------------------------

@pytest.mark.parametrize("cls", [FlowMotionEstimator, ImageMotionEstimator])
def test_an_estimator_class_is_refused_by_name(cls):
    """``estimator=ImageMotionEstimator`` (the class, callable) passed the check: given odometry and
    no images the refiner ran on, and at a call that estimates, the class was called with the flow
    ("__init__() takes 1 positional argument but 4 were given"). Refused when the refiner is made,
    as by refine_flow and detect_road."""
    from fsof_torch.refinement.auto_road import detect_road

    pred, mask, cam, images = make_case()
    message = rf"^estimator: expected a road-motion estimator object, got the class {cls.__name__}; make one: " \
              rf"estimator={cls.__name__}\(\)$"
    with pytest.raises(TypeError, match=message):
        FreespaceRefiner(estimator=cls)
    for odometry in (None, ODO):
        with pytest.raises(TypeError, match=message):
            refine_flow(pred, mask, cam, odometry, estimator=cls)
    with pytest.raises(TypeError, match=message):
        detect_road(*images, cam, estimator=cls)
    assert bool(refine_flow(pred, mask, cam, estimator=FlowMotionEstimator(), gate=None, warn=False).refined.all())


def _returning(**fields):
    """An estimator whose result is the flow fit's with ``fields`` replaced (a field None: left out)."""
    from types import SimpleNamespace

    def estimator(flow, mask, camera, **kw):
        fit = FlowMotionEstimator()(flow, mask, camera, **kw)
        given = {k: getattr(fit, k) for k in ("model", "params", "success", "camera")}
        return SimpleNamespace(**{k: v for k, v in {**given, **fields}.items() if v is not None})
    return estimator


def test_an_estimators_result_is_checked_by_name():
    """A custom estimator's result is model, params ((n,) tensors), success ((n,)) and camera (batch
    n). A "velocity" motion (flow in px/s, refused as odometry) was used as pixels per frame: the
    flow came back refined with a rate's flow; a result without success, params of one motion for
    the batch or a camera of batch 1 raised AttributeError or IndexError from inside the refiner."""
    pred, mask, cam, _ = make_case(B=2)
    ok = refine_flow(pred, mask, cam, estimator=_returning(), gate=None, warn=False)
    assert bool(ok.refined.all())
    one = {k: v[:1] for k, v in FlowMotionEstimator()(pred, mask, cam).params.items()}
    cases = [
        (_returning(model="velocity", params={}), ValueError,
         r"^estimator: returned a 'velocity' motion, whose flow is in px/s; the refiner needs the motion over the "
         r"frame interval, a displacement model \('paper', 'plane' or 'homography'\)$"),
        (_returning(model="paper", success=None), TypeError,
         r"^estimator: expected a result with model, params, success and camera \(a RoadFit\), got SimpleNamespace "
         r"without success$"),
        (lambda *a, **k: None, TypeError, r"^estimator: expected a result .* got NoneType without model, params, "
                                          r"success, camera$"),
        (_returning(params=one), ValueError, r"^estimator: expected result.params\['x_d'\] a tensor of shape \(2,\) "
                                             r"\(the samples it was given\), got shape \(1,\)$"),
        (_returning(params=dict(ODO)), TypeError, r"^estimator: expected result.params\['x_d'\] a tensor of shape "
                                                  r"\(2,\) \(the samples it was given\), got float$"),
        (_returning(success=True), TypeError, r"^estimator: expected result.success a tensor of shape \(2,\)"),
        (_returning(params={"x_d": torch.zeros(2), "speed": torch.zeros(2)}), ValueError,
         r"^estimator: result.params has unknown parameters \['speed'\] of model 'paper'"),
        (_returning(camera=Camera(cam.K[:1], 1.65)), ValueError, r"^estimator: expected result.camera of batch 2 \(the samples it "
                                                 r"was given\), got batch 1$"),
        (_returning(camera=cam.K), TypeError, r"^estimator: expected result.camera a fsof_torch.Camera, got Tensor$"),
    ]
    for estimator, error, message in cases:
        with pytest.raises(error, match=message):
            refine_flow(pred, mask, cam, estimator=estimator, gate=None, warn=False)
    # with images and planar odometry (the estimate completes it), and for a subset of the batch: n = 1
    few = mask.clone()
    few[1] = False
    with pytest.raises(ValueError, match=r"^estimator: returned a 'velocity' motion"):
        refine_flow(pred, mask, cam, ODO, estimator=_returning(model="velocity", params={}), gate=None,
                    images=make_case(B=2)[3], warn=False)
    with pytest.raises(ValueError, match=r"^estimator: expected result.camera of batch 1 \(the samples it was given\), "
                                         r"got batch 2$"):
        refine_flow(pred, few, cam, estimator=_returning(camera=cam), gate=None, warn=False)
