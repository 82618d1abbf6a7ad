"""The refiner's road-motion estimators: what they do with a given odometry, and their detached results."""

import math
import warnings

import pytest
import torch

from fsof_torch import Camera, FlowMotionEstimator, FreespaceRefiner, ImageMotionEstimator, endpoint_error, render_pair

DEG = math.pi / 180
SIGMA = {"x_d": 0.05, "z_d": 0.05, "yaw": 0.2 * DEG}


@pytest.fixture(scope="module")
def body_pair():
    """A body-motion pair at half size and an odometry off as wheel odometry can be: the step 5 %
    long, the yaw 0.3° a frame too far left."""
    p = render_pair("body-motion", 1, size=(188, 621))
    odometry = dict(p["odometry"])
    odometry["z_d"] = odometry["z_d"] * 1.05
    odometry["yaw"] = odometry["yaw"] + 0.3 * DEG
    return p, odometry


def refined(p, odometry, estimator):
    road = p["road"][None]
    flow = torch.zeros(1, 2, *road.shape[-2:])
    out = FreespaceRefiner(estimator=estimator)(flow, road, p["camera"], odometry,
                                                images=(p["image1"][None], p["image2"][None]))
    assert bool(out.refined[0])
    epe = float(endpoint_error(out.flow, p["flow"][None], road, p["valid"][None])[0])
    return {k: float(v[0]) for k, v in out.fit.params.items()}, epe


def test_planar_odometry_held_by_default_and_moved_within_odometry_sigma(body_pair):
    p, odometry = body_pair
    truth = p["plane"]
    held, epe_held = refined(p, odometry, ImageMotionEstimator())
    for k in ("x_d", "z_d", "yaw"):
        assert held[k] == pytest.approx(odometry[k], abs=1e-6)

    moved, epe_moved = refined(p, odometry, ImageMotionEstimator(odometry_sigma=SIGMA))
    # the images take the yaw and the step back to the truth; the road flow follows
    assert abs(moved["yaw"] - truth["yaw"]) < 0.05 * DEG < abs(odometry["yaw"] - truth["yaw"])
    assert abs(moved["z_d"] / truth["z_d"] - 1) < 0.03 < abs(odometry["z_d"] / truth["z_d"] - 1)
    assert epe_moved < 0.5 < epe_held

    # only the yaw given a width: the step stays the odometry's
    yaw_only, _ = refined(p, odometry, ImageMotionEstimator(odometry_sigma={"yaw": 0.2 * DEG}))
    assert yaw_only["z_d"] == pytest.approx(odometry["z_d"], abs=1e-6)
    assert yaw_only["x_d"] == pytest.approx(odometry["x_d"], abs=1e-6)
    assert abs(yaw_only["yaw"] - odometry["yaw"]) > 0.05 * DEG


def test_a_prior_on_what_the_odometry_holds_names_the_odometry(body_pair):
    """The odometry holds x_d: a prior on it would be ignored; the error said "free it (fixed=
    without it)", which a caller of the estimator cannot do."""
    p, odometry = body_pair
    with pytest.raises(ValueError, match=r"^prior: 'x_d' is held at the odometry's value, .*odometry_sigma="):
        refined(p, odometry, ImageMotionEstimator(prior={"x_d": (1.0, 0.1)}))


def test_odometry_sigma_with_a_model_that_holds_a_parameter(body_pair):
    """The paper model holds the pitch: the calibration prior it is given leaves it out (fit_image
    refuses a prior on a held parameter)."""
    p, odometry = body_pair
    _, epe = refined(p, odometry, ImageMotionEstimator(model="paper", odometry_sigma={"yaw": 0.2 * DEG}))
    assert math.isfinite(epe)


def test_odometry_sigma_is_a_prior_on_top_of_the_calibration_prior(body_pair):
    """A width of a millionth of a degree is the odometry held; the calibration's prior on the
    attitude stays (the estimate equals the one with the yaw fixed)."""
    p, odometry = body_pair
    tight, _ = refined(p, odometry, ImageMotionEstimator(odometry_sigma={"yaw": 1e-6 * DEG}))
    held, _ = refined(p, odometry, ImageMotionEstimator())
    assert tight["yaw"] == pytest.approx(odometry["yaw"], abs=1e-7)
    for k in ("pitch", "roll", "pitch_change", "roll_change", "z_d"):
        assert tight[k] == pytest.approx(held[k], abs=2e-4)


def test_fit_image_options_checked_when_the_estimator_is_made():
    """A bad value among fit_image's options is an error when the estimator is built (as a torch
    module checks its arguments), not at the first refinement."""
    with pytest.raises(ValueError, match="^smooth_sigma: expected a number >= 0, got -1"):
        ImageMotionEstimator(smooth_sigma=-1)
    with pytest.raises(ValueError, match=r"^min_correlation: expected a number in \[-1, 1\], got 2"):
        ImageMotionEstimator(model="homography", min_correlation=2)
    with pytest.raises(TypeError, match=r"^options: options \['starts'\] of fit_image are set by"):
        ImageMotionEstimator(starts=[])
    assert ImageMotionEstimator(fine_points=20000, smooth_sigma=1.0).options == {"fine_points": 20000,
                                                                                 "smooth_sigma": 1.0}


@pytest.mark.parametrize("model, options, error, message", [
    ("homography", {"fixed": ["pitch"]}, ValueError, r"^fixed: unknown parameters \['pitch'\] of model 'homography'"),
    ("plane", {"prior": {"pich": (0.0, 0.01)}}, ValueError, r"^prior: unknown parameter 'pich' of model 'plane'"),
    ("paper", {"prior": {"pitch": (0.0, 0.01)}}, ValueError, r"^prior: 'pitch' is held at its start \(fixed=\('pitch',\)\)"),
    ("plane", {"prior": {"pitch": (0.0,)}}, ValueError, r"^prior\['pitch'\]: expected \(mean, sigma\), got \(0.0,\)"),
    ("plane", {"prior": {"pitch": (0.0, -0.01)}}, ValueError, r"^prior\['pitch'\]: expected a finite mean and sigma > 0"),
    ("plane", {"prior": {"yaw": (float("nan"), 0.01)}}, ValueError, r"^prior\['yaw'\]: expected a finite mean and sigma"),
])
def test_model_names_and_priors_checked_when_the_estimator_is_made(model, options, error, message):
    """A fixed name or a prior the model refuses was an error at every call of the estimator (the
    first refinement), though its options are checked when it is made."""
    with pytest.raises(error, match=message):
        ImageMotionEstimator(model=model, **options)


def test_priors_of_several_values_are_left_to_the_call():
    """A prior of one value per frame is checked at the call, which knows the batch; the model's
    own free parameters take priors."""
    estimator = ImageMotionEstimator(prior={"pitch": (torch.zeros(3), torch.full((3,), 0.01))})
    assert set(estimator.options["prior"]) == {"pitch"}
    ImageMotionEstimator(model="paper", fixed=(), prior={"pitch": (torch.tensor(0.0), 0.01)})

def test_an_image_estimator_for_0_1_images_is_refused_where_it_gets_0_255():
    """The refiner and detect_road hand their estimator images on 0..255 (detect_road rescales
    the caller's): ImageMotionEstimator(data_range=1.0) was taken, and every call failed in the
    fit with "image1: expected values in [0, data_range=1]", which told a caller of detect_road
    with 0..1 images (data_range=1.0) to pass 255. It is refused where it is given, naming the
    estimator; called directly on 0..1 images it fits them."""
    from fsof_torch import detect_road

    p = render_pair("default", 0, size=(48, 160))
    images, road, cam = (p["image1"][None], p["image2"][None]), p["road"][None], p["camera"]
    message = r"^estimator: ImageMotionEstimator\(data_range=1.0\) is given images on 0..255 here"
    with pytest.raises(ValueError, match=message):
        FreespaceRefiner(estimator=ImageMotionEstimator(data_range=1.0))
    with pytest.raises(ValueError, match=message):
        detect_road(images[0] / 255, images[1] / 255, cam, estimator=ImageMotionEstimator(data_range=1.0),
                    data_range=1.0)
    with pytest.raises(TypeError, match=r"^photometric_options: options \['data_range'\] of fit_image are set by"):
        FreespaceRefiner(fit="photometric", photometric_options={"data_range": 1.0})
    FreespaceRefiner(estimator=ImageMotionEstimator(data_range=255.0))
    unit = ImageMotionEstimator(data_range=1.0)(None, road, cam, images=(images[0] / 255, images[1] / 255))
    grey = ImageMotionEstimator()(None, road, cam, images=images)
    torch.testing.assert_close(unit.params["z_d"], grey.params["z_d"], rtol=1e-5, atol=1e-6)

def test_odometry_sigma_checked():
    with pytest.raises(ValueError, match=r"odometry_sigma: expected some of \('x_d', 'z_d', 'yaw'\) \(the planar "
                                         r"odometry\), got 'pitch'"):
        ImageMotionEstimator(odometry_sigma={"pitch": 0.01})
    with pytest.raises(ValueError, match=r"odometry_sigma\['yaw'\]: expected a positive number \(> 0\), got -0.1"):
        ImageMotionEstimator(odometry_sigma={"yaw": -0.1})
    with pytest.raises(TypeError, match=r"odometry_sigma\['z_d'\]: expected a number, got str '5'"):
        ImageMotionEstimator(odometry_sigma={"z_d": "5"})
    with pytest.raises(TypeError, match="odometry_sigma: expected None or a dict with string keys, got float 0.1"):
        ImageMotionEstimator(odometry_sigma=0.1)
    with pytest.raises(ValueError, match=r"odometry_sigma\['yaw'\]: the parameter is also in fixed=\('yaw',\)"):
        ImageMotionEstimator(odometry_sigma={"yaw": 0.01}, fixed=("yaw",))
    # (the homography model has no planar motion: said so, not "expected some of x_d, z_d, yaw, got 'z_d'")
    with pytest.raises(ValueError, match=r"odometry_sigma: the 'homography' model has no planar motion \(x_d, z_d, "
                                         r"yaw\) to put a prior on; give odometry_sigma=None"):
        ImageMotionEstimator(model="homography", odometry_sigma={"z_d": 0.05})
    assert ImageMotionEstimator(model="homography", odometry_sigma={}).odometry_sigma == {}
    assert repr(ImageMotionEstimator(odometry_sigma={"yaw": 0.5})) == (
        "ImageMotionEstimator(model='plane', flow_start=True, odometry_sigma={'yaw': 0.5})")


def test_a_parameter_given_two_priors_is_refused(body_pair):
    p, odometry = body_pair
    estimator = ImageMotionEstimator(odometry_sigma={"yaw": 0.01}, prior={"yaw": (0.0, 0.1)})
    with pytest.raises(ValueError, match=r"prior: \['yaw'\] also given a prior by odometry_sigma"):
        refined(p, odometry, estimator)


def test_held_odometry_holds_over_a_previous_fit_given_as_start():
    """A previous pair's fit as a start (a RoadFit, not a dict) gets the held planar motion too:
    the fit returns the odometry's x_d, z_d, yaw, whatever the start says."""
    from fsof_torch import fit_image

    p = render_pair("default", 0, size=(96, 320))
    images, road = (p["image1"][None], p["image2"][None]), p["road"][None]
    previous = fit_image(images[0], images[1], road, p["camera"])
    odometry = {"x_d": 0.0, "z_d": 0.8, "yaw": 0.0}  # held, though the previous fit says about 1.08 m
    assert float(previous.params["z_d"][0]) > 1.0
    for start in (previous, dict(previous.params)):
        fit = ImageMotionEstimator()(None, road, p["camera"], images=images, odometry=odometry, starts=[start])
        assert {k: float(fit.params[k][0]) for k in odometry} == pytest.approx(odometry, abs=1e-6)


def test_odometry_errors_name_the_odometry():
    """A non-finite odometry, or one a homography cannot hold, is named as the odometry (not as the
    fit's init or fixed parameters it becomes)."""
    p = render_pair("default", 0, size=(96, 320))
    images, road = (p["image1"][None], p["image2"][None]), p["road"][None]
    with pytest.raises(ValueError, match=r"^odometry\['x_d'\]: expected finite values, got nan"):
        ImageMotionEstimator()(None, road, p["camera"], images=images,
                               odometry={"x_d": math.nan, "z_d": 1.0, "yaw": 0.0})
    with pytest.raises(ValueError, match=r"^odometry: the 'homography' model has no planar motion"):
        ImageMotionEstimator(model="homography")(None, road, p["camera"], images=images,
                                                 odometry={"x_d": 0.0, "z_d": 1.0, "yaw": 0.0})
    # an odometry of another batch than the frames': named as the odometry, not as the fit's init
    two = {"x_d": torch.zeros(2), "z_d": torch.ones(2), "yaw": torch.zeros(2)}
    with pytest.raises(ValueError, match=r"^odometry\['x_d'\]: expected batch 1, got 2 values"):
        ImageMotionEstimator()(None, road, p["camera"], images=images, odometry=two)
    with pytest.raises(ValueError, match=r"^odometry\['x_d'\]: expected batch 1, got 2 values"):
        FlowMotionEstimator()(p["flow"][None], road, p["camera"], odometry=two)


@pytest.fixture(scope="module")
def small_pair():
    p = render_pair("default", 0, size=(96, 320))
    return p, (p["image1"][None], p["image2"][None]), p["road"][None]


def _calls(monkeypatch, run=True):
    """What ImageMotionEstimator passes to fit_image (each call's keyword arguments); the fits run
    where ``run``."""
    import fsof_torch.refinement.estimators as estimators

    calls, fit_image = [], estimators.fit_image

    def spy(*args, **kwargs):
        calls.append(kwargs)
        return fit_image(*args, **kwargs) if run else None

    monkeypatch.setattr(estimators, "fit_image", spy)
    return calls


def test_held_odometry_takes_a_fixed_name_and_a_fit_as_init(small_pair, monkeypatch):
    """``fixed`` as one name (as fit_image takes it) and ``init`` as a previous fit (RoadFit) both
    combine with the held planar odometry: the name stays one parameter, the fit's parameters are
    the init under the odometry's."""
    p, images, road = small_pair
    calls = _calls(monkeypatch)
    odometry = {"x_d": 0.0, "z_d": 1.0, "yaw": 0.01}
    fit = ImageMotionEstimator(fixed="roll")(None, road, p["camera"], images=images, odometry=odometry)
    assert calls[-1]["fixed"] == ("roll", "x_d", "z_d", "yaw")
    assert float(fit.params["roll"][0]) == pytest.approx(float(p["camera"].roll[0]), abs=1e-7)
    assert {k: float(fit.params[k][0]) for k in odometry} == pytest.approx(odometry, abs=1e-6)

    previous = fit  # (a RoadFit, as a previous pair's)
    fit = ImageMotionEstimator(init=previous)(None, road, p["camera"], images=images, odometry=odometry)
    init = calls[-1]["init"]
    assert set(init) == set(previous.params)
    for k, v in init.items():
        assert float(torch.as_tensor(v).reshape(-1)[0]) == pytest.approx(
            odometry[k] if k in odometry else float(previous.params[k][0]))
    assert {k: float(fit.params[k][0]) for k in odometry} == pytest.approx(odometry, abs=1e-6)


def test_held_odometry_keeps_the_models_default_fixed(small_pair, monkeypatch):
    """Without ``fixed``, the model's own default stays held beside the odometry: the paper's
    model holds the camera's pitch, with odometry as without."""
    p, images, road = small_pair
    calls = _calls(monkeypatch)
    odometry = {"x_d": 0.0, "z_d": 1.0, "yaw": 0.01}
    fit = ImageMotionEstimator(model="paper")(None, road, p["camera"], images=images, odometry=odometry)
    assert calls[-1]["fixed"] == ("pitch", "x_d", "z_d", "yaw")
    assert float(fit.params["pitch"][0]) == pytest.approx(float(p["camera"].pitch[0]), abs=1e-7)
    ImageMotionEstimator()(None, road, p["camera"], images=images, odometry=odometry)
    assert calls[-1]["fixed"] == ("x_d", "z_d", "yaw")  # (the plane model holds nothing by default)


def test_flow_start_is_each_frames_own(small_pair, monkeypatch):
    """A frame's flow start is the same alone or next to a frame whose flow has a NaN pixel (that
    frame's start leaves the pixel out)."""
    from fsof_torch.refinement.estimators import planar_start

    p, images, road = small_pair
    flow = p["flow"][None].float()
    bad = flow.clone()
    bad[0, :, 0, 0] = math.nan
    calls = _calls(monkeypatch, run=False)
    ImageMotionEstimator()(torch.cat([flow, bad]), road, p["camera"], images=tuple(torch.cat([x, x]) for x in images))
    (start,) = calls[-1]["starts"]
    alone = planar_start(flow, road, p["camera"])
    for k in ("x_d", "z_d", "yaw"):
        assert float(start[k][0]) == pytest.approx(float(alone[k][0]), rel=1e-9, abs=1e-12), k
        assert float(start[k][1]) == pytest.approx(float(alone[k][0]), rel=1e-3, abs=1e-6), k
    assert float(alone["z_d"][0]) == pytest.approx(p["odometry"]["z_d"], rel=0.05)


def test_the_refiners_flow_start_is_the_public_one(small_pair, monkeypatch):
    """In the refiner the estimator's flow is known finite (no second pass over it) and its planar
    start runs in inference mode (as the fit: fewer costs per operation): the start the fit gets is planar_start's own, bit for bit, an
    ordinary tensor; with a NaN in the flow the refiner's zeroed copy starts it."""
    import fsof_torch._check as _check
    import fsof_torch.estimation.initial as initial
    from fsof_torch._check import all_finite
    from fsof_torch.refinement.estimators import planar_start

    p, images, road = small_pair
    flow = p["flow"][None].float()
    seen = []

    def finite(f):  # (whether planar_start's test is of a flow known finite: answered without a pass)
        seen.append((any(f is t for t in _check._KNOWN_FINITE.get()) and all_finite(f),
                     torch.is_inference_mode_enabled()))
        return all_finite(f)

    monkeypatch.setattr(initial, "all_finite", finite)
    for holed in (False, True):
        f = flow.clone()
        if holed:
            f[0, :, 60, 100] = math.nan
        calls = _calls(monkeypatch, run=False)
        seen.clear()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with pytest.raises(TypeError, match="^estimator: expected a result"):  # (the spy returns no fit)
                FreespaceRefiner()(f, road, p["camera"], images=images)
        assert seen == [(True, True)]
        (start,) = calls[-1]["starts"]
        usable = road & torch.isfinite(f).all(1, keepdim=True)
        # (the refiner's geometry in the flow's dtype)
        expected = planar_start(torch.where(usable, f, 0.0), usable, p["camera"].to(torch.float32))
        for k in ("x_d", "z_d", "yaw"):
            assert torch.equal(start[k], expected[k]) and not start[k].is_inference(), k


def test_homography_odometry_is_a_start_and_keeps_the_flow_start(small_pair, monkeypatch):
    """An odometry without planar motion (a homography) holds nothing: for a homography estimator
    it is one more start; the flow's start stays, as without odometry."""
    from fsof_torch import road_homography
    from fsof_torch.geometry.road_models import get_road_model, homography_values
    from fsof_torch.refinement.estimators import planar_start

    p, images, road = small_pair
    flow = p["flow"][None].float()
    odometry = {"model": "homography", **{n: 0.01 * i for i, n in enumerate(get_road_model("homography").params)}}
    calls = _calls(monkeypatch, run=False)
    for model in ("homography", "plane"):
        ImageMotionEstimator(model=model)(flow, road, p["camera"], images=images, odometry=odometry)
        kw = calls[-1]
        assert kw["fixed"] is None and kw["init"] is None
        starts = kw["starts"]
        assert len(starts) == (2 if model == "homography" else 1)
        if model == "homography":
            assert starts[0] == {k: v for k, v in odometry.items() if k != "model"}
            # the flow's start as the homography's parameters: the map of its planar motion
            planar = planar_start(flow, road, p["camera"])
            H = road_homography(p["camera"], planar, model="plane").to(torch.float64)
            K = p["camera"].K.to(torch.float64)
            values = homography_values(H, K, torch.linalg.inv(K))[0]
            assert sorted(starts[-1]) == sorted(get_road_model("homography").params)
            torch.testing.assert_close(torch.stack([starts[-1][n][0] for n in get_road_model("homography").params]),
                                       values, rtol=0, atol=1e-9)
        else:
            assert float(starts[-1]["z_d"][0]) == pytest.approx(p["odometry"]["z_d"], rel=0.05)  # the flow's


def test_flow_start_of_a_homography_estimator_is_used():
    """flow_start with model="homography": the flow's planar start was passed to the fit as x_d,
    z_d and yaw, names the homography lacks, and the fit left it aside (at three times the default
    speed it started from zero motion alone and landed 15 px off, as without the flow). Now it
    starts from that motion's homography, and the flow finds the motion as it does for the plane."""
    p = render_pair("default", 0, size=(96, 320), speed_factor=3)
    images, road, flow = (p["image1"][None], p["image2"][None]), p["road"][None], p["flow"][None]
    few = dict(forward_starts=(), turn_starts=(), reverse_starts=(), retry_starts=0, retry_without_prior=False)
    errors = {}
    for model in ("plane", "homography"):
        for flow_start in (True, False):
            fit = ImageMotionEstimator(model=model, flow_start=flow_start, **few)(flow, road, p["camera"],
                                                                                  images=images)
            errors[model, flow_start] = float(endpoint_error(fit.flow, p["flow"][None], road, p["valid"][None])[0])
    assert errors["plane", True] < 2.0 and errors["homography", True] < 2.0
    assert errors["plane", False] > 10.0 and errors["homography", False] > 10.0


# -- FlowMotionEstimator with planar odometry; detached results ------------------------------------------

@pytest.fixture(scope="module")
def noisy_pair():
    p = render_pair("default", 0, size=(53, 94))
    noise = torch.randn(p["flow"][None].shape, generator=torch.Generator().manual_seed(0))
    return p, p["camera"].to(torch.float32), p["flow"][None] + 2.0 * noise


def test_flow_estimator_holds_planar_odometry_and_the_refiner_keeps_its_graph(noisy_pair):
    """With planar odometry and images the refiner asks the estimator for the rest of the motion:
    FlowMotionEstimator re-fitted x_d, z_d and yaw to the prediction, so the caller's odometry was
    replaced and got no gradient."""
    p, cam, pred = noisy_pair
    road = p["road"][None]
    odometry = {k: torch.tensor([float(p["odometry"][k])], requires_grad=True) for k in ("x_d", "z_d", "yaw")}
    fit = FlowMotionEstimator(model="plane")(pred, road, cam, odometry=odometry)
    for k, v in odometry.items():
        assert torch.equal(fit.params[k], v.detach()), k
    assert not any(v.requires_grad for v in fit.params.values())
    out = FreespaceRefiner(estimator=FlowMotionEstimator(), gate=None)(pred, road, cam, odometry,
                                                                        images=(p["image1"][None], p["image2"][None]))
    assert out.fit is not None and bool(out.refined.all())
    for k, v in odometry.items():
        assert torch.equal(out.odometry[k].detach(), v.detach()), k
    out.flow.sum().backward()
    assert all(float(v.grad.abs().sum()) > 0 for v in odometry.values())


def test_flow_estimator_planar_odometry_needs_a_planar_model(noisy_pair):
    p, cam, pred = noisy_pair
    with pytest.raises(ValueError, match=r"^odometry: the 'homography' model has no planar motion \(x_d, z_d, yaw\) "
                                         r"to hold; fit the flow alone \(odometry=None\)"):
        FlowMotionEstimator(model="homography")(pred, p["road"][None], cam, odometry=p["odometry"])
    with pytest.raises(ValueError, match=r"^odometry\['yaw'\]: expected finite values, got nan"):
        FlowMotionEstimator()(pred, p["road"][None], cam, odometry={**p["odometry"], "yaw": float("nan")})


def test_flow_estimator_refuses_a_prior_on_what_the_odometry_holds(noisy_pair):
    """A prior on x_d, z_d or yaw cannot act where planar odometry holds them: refused in the
    estimator's words (it was silently ignored); without odometry it is a prior as before."""
    p, cam, pred = noisy_pair
    estimator = FlowMotionEstimator(model="plane", prior={"z_d": (1.0, 0.01)})
    with pytest.raises(ValueError, match=r"^prior: 'z_d' is held at the odometry's value, so its prior would be "
                                         r"ignored; drop it, or call without odometry$"):
        estimator(pred, p["road"][None], cam, odometry=p["odometry"])
    assert float(estimator(pred, p["road"][None], cam).z_d) == pytest.approx(1.0, abs=0.05)


def test_image_estimator_returns_a_detached_camera(noisy_pair):
    """fit.camera.K kept the caller's graph (FlowMotionEstimator's fit is detached)."""
    p, cam, pred = noisy_pair
    K = cam.K.clone().requires_grad_(True)
    camera = Camera(K, cam.height)
    images = (p["image1"][None], p["image2"][None])
    for odometry in (None, p["odometry"]):
        fit = ImageMotionEstimator()(pred, p["road"][None], camera, images=images, odometry=odometry)
        c = fit.camera
        assert not any(t.requires_grad for t in (c.K, c.height, c.roll, c.pitch))
        torch.testing.assert_close(c.K, K.detach(), rtol=0, atol=0)


def test_image_estimator_names_what_came_for_images(small_pair):
    """Not a pair: the message says what came (a tuple of 1 or 3 read as only "got tuple")."""
    p, (im1, im2), road = small_pair
    for images, shown in (((im1,), "tuple of 1"), ((im1, im2, im2), "tuple of 3"), (im1, "Tensor")):
        with pytest.raises(TypeError, match=rf"^images: expected a pair \(image1, image2\), got {shown}$"):
            ImageMotionEstimator()(None, road, p["camera"], images=images)


def test_flow_estimator_leaves_non_finite_pixels_out_of_the_mask():
    """A NaN or inf predicted pixel is no data: the flow fit leaves it out of the mask (as the
    refiner does before it calls an estimator), the fit equal to one on the mask without it."""
    p = render_pair("default", 0, size=(96, 320))
    flow, road, cam = p["flow"][None].clone(), p["road"][None], p["camera"]
    v, u = road[0, 0].nonzero()[100].tolist()
    flow[0, 0, v, u], flow[0, 1, v + 1, u] = math.nan, math.inf
    without = road.clone()
    without[0, 0, v, u] = without[0, 0, v + 1, u] = False
    fit = FlowMotionEstimator()(flow, road, cam)
    reference = FlowMotionEstimator()(flow, without, cam)
    assert bool(fit.success.all())
    for name in ("x_d", "z_d", "yaw"):
        assert torch.equal(fit.params[name], reference.params[name])
    assert not bool(fit.inliers[0, 0, v, u]) and bool(road[0, 0, v, u])  # (the caller's mask kept)


class _NaNFirst:
    """A custom estimator with a bug: the first sample's first parameter (and its model flow) NaN,
    reported as a success."""

    def __init__(self, inner):
        self.inner = inner

    def __call__(self, *args, **kwargs):
        import dataclasses

        fit = self.inner(*args, **kwargs)
        params = {k: v.clone() for k, v in fit.params.items()}
        params[next(iter(params))][0] = math.nan
        flow = fit.flow.clone()
        flow[0] = math.nan
        return dataclasses.replace(fit, params=params, flow=flow, success=torch.ones_like(fit.success))


def test_finite_estimate_marks_non_finite_samples_failed(noisy_pair):
    """A sample whose parameters are not all finite is a failed estimate: success False, its
    parameters 0, the input camera's attitude, a zero model flow nowhere valid and the identity
    homography; the other samples and the estimator's own result stay as they are."""
    from fsof_torch.refinement.estimators import finite_estimate

    p, cam, flow = noisy_pair
    flow, road = flow.expand(2, -1, -1, -1).clone(), p["road"][None].expand(2, -1, -1, -1)
    cam = cam.expand(2)
    good = FlowMotionEstimator()(flow, road, cam)
    assert finite_estimate(good, cam) is good  # (all finite: the result itself)
    bad = _NaNFirst(FlowMotionEstimator())(flow, road, cam)
    with pytest.warns(RuntimeWarning, match=r"estimator: samples \[5\] came back with non-finite parameters "
                                            r"\(NaN or inf; success \[True\]\): taken as failed estimates"):
        out = finite_estimate(bad, cam, samples=[5, 6])
    assert out.success.tolist() == [False, True] and bad.success.tolist() == [True, True]
    assert math.isnan(float(bad.params["x_d"][0]))  # (the estimator's result left as it was)
    for k, v in out.params.items():
        assert float(v[0]) == 0.0 and torch.equal(v[1], good.params[k][1])
    assert float(out.camera.roll[0]) == float(cam.roll[0]) and float(out.camera.pitch[0]) == float(cam.pitch[0])
    assert not bool(out.flow[0].any()) and not bool(out.valid[0].any()) and torch.equal(out.flow[1], good.flow[1])
    assert torch.equal(out.homography[0], torch.eye(3, dtype=out.homography.dtype))


@pytest.mark.parametrize("with_images", [False, True])
def test_refiner_takes_non_finite_estimated_parameters_as_a_failed_estimate(noisy_pair, with_images):
    """A custom estimator's NaN parameters with success True: the sample keeps its prediction, is
    reported unrefined, and a warning names it; no NaN reaches the flow, the odometry or the model
    flow (it did: the odometry came back NaN, refined True). The other sample is refined as with the
    estimator without the bug."""
    p, cam, flow = noisy_pair
    flow = flow.expand(2, -1, -1, -1).clone()
    road = p["road"][None].expand(2, -1, -1, -1)
    images = (torch.stack([p["image1"]] * 2), torch.stack([p["image2"]] * 2)) if with_images else None
    inner = ImageMotionEstimator() if with_images else FlowMotionEstimator()
    flows = [flow[..., ::2, ::2] / 2, flow]  # (a coarser level: its model flow computed from the parameters)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = FreespaceRefiner(estimator=_NaNFirst(inner))(flows, road, cam, images=images)
    said = [str(w.message) for w in caught]
    assert any(m.startswith("estimator: samples [0] came back with non-finite parameters") for m in said), said
    assert any(m.startswith("mask: samples [0] left unchanged") for m in said), said
    reference = FreespaceRefiner(estimator=inner)(flows, road, cam, images=images)
    assert out.refined.tolist() == [False, True] and reference.refined.tolist() == [True, True]
    for level, (f, ref) in enumerate(zip(out.flow, reference.flow)):
        assert torch.equal(f[0], flows[level][0])
        torch.testing.assert_close(f[1], ref[1], rtol=0, atol=1e-4)
    assert all(bool(torch.isfinite(v).all()) for v in out.odometry.values())
    assert bool(torch.isfinite(out.flow_model).all()) and not bool(out.mask[0].any())


@pytest.mark.parametrize("value, error, message", [
    ("1.2", TypeError, r"expected a float, or a tensor of shape \(B,\), got str"),
    (True, TypeError, r"expected a float, or a tensor of shape \(B,\), got bool"),
    ([1.2], TypeError, r"expected a float, or a tensor of shape \(B,\), got list"),
    (torch.tensor([1]), TypeError, r"expected a float tensor or a Python number, got dtype torch.int64"),
    (torch.ones(1, 1), ValueError, r"expected a scalar or shape \(B,\), got \(1, 1\)")], ids=["str", "bool", "list", "int", "2d"])
def test_an_odometry_value_of_another_type_is_named_as_the_refiner_names_it(value, error, message):
    """The estimators and detect_road took an odometry's value as torch.as_tensor takes it: a str
    raised torch's 'new(): invalid data type' naming nothing, and True, a list, an int tensor or a
    (B, 1) tensor were taken as a step (True as 1 m) where refine_flow refuses them. They are now
    refused as refine_flow refuses them, naming the odometry's key."""
    from fsof_torch import detect_road, refine_flow

    p = render_pair("default", 0, size=(48, 160))
    flow, road, camera = p["flow"][None].nan_to_num(), p["road"][None], p["camera"]
    images = (p["image1"][None], p["image2"][None])
    odometry = {"x_d": 0.0, "z_d": value, "yaw": 0.0}
    calls = {"refine_flow": lambda: refine_flow(flow, road, camera, odometry, images=images),
             "FlowMotionEstimator": lambda: FlowMotionEstimator()(flow, road, camera, odometry=odometry),
             "ImageMotionEstimator": lambda: ImageMotionEstimator()(flow, road, camera, images=images, odometry=odometry),
             "detect_road": lambda: detect_road(*images, camera, odometry=odometry)}
    for name, call in calls.items():
        with pytest.raises(error, match=r"^odometry\['z_d'\]: " + message):
            call()


@pytest.mark.parametrize("estimator", [FlowMotionEstimator(), ImageMotionEstimator()], ids=["flow", "image"])
def test_an_odometry_on_the_meta_device_is_named(estimator):
    """A meta odometry with real flow and images: a ValueError naming its key (was torch's
    'Tensor.item() cannot be called on meta tensors'); on meta throughout it is named too."""
    p = render_pair("default", 0, size=(24, 80))
    flow, road, images = p["flow"][None], p["road"][None], (p["image1"][None], p["image2"][None])
    odometry = {"x_d": 0.0, "z_d": torch.tensor([1.0], device="meta"), "yaw": 0.0}
    with pytest.raises(ValueError, match=r"^odometry\['z_d'\]: a tensor on the meta device has shapes but no values"):
        estimator(flow, road, p["camera"], images=images, odometry=odometry)
    meta = Camera(p["camera"].K.to("meta"), p["camera"].height.to("meta"))
    with pytest.raises(ValueError, match="a tensor on the meta device has shapes but no values"):
        estimator(flow.to("meta"), road.to("meta"), meta, images=tuple(im.to("meta") for im in images),
                  odometry=odometry)


@pytest.mark.parametrize("estimator", [FlowMotionEstimator(), ImageMotionEstimator()], ids=["flow", "image"])
def test_a_velocity_odometry_is_named_not_left_aside(estimator):
    """A "velocity" motion (a rate, px/s) as the estimators' odometry was left aside without a word
    (neither planar odometry to hold nor a start of their model): the estimate ran as if no odometry
    had come, also through detect_road(odometry=). Named now, as the refiner names it."""
    from fsof_torch import detect_road

    p = render_pair("default", 0, size=(48, 120))
    flow, road, images = p["flow"][None], p["road"][None], (p["image1"][None], p["image2"][None])
    message = r"^odometry: the 'velocity' model gives flow in px/s, not the pixels per frame this needs"
    for odometry in ({"model": "velocity", "speed": 10.0}, {"model": "velocity", "speed": 10.0, "yaw_rate": 0.1}):
        with pytest.raises(ValueError, match=message):
            estimator(flow, road, p["camera"], images=images, odometry=odometry)
        with pytest.raises(ValueError, match=message):
            detect_road(*images, p["camera"], flow=flow, estimator=estimator, odometry=odometry)


def test_the_image_fit_names_a_frame_mask_or_flow_on_another_device():
    """fit_image and ImageMotionEstimator named no argument on another device than image1: a
    CUDA mask or frame with CPU ones came to torch's own error from inside the fit (a tensor on
    meta, the one device a CPU test has besides the CPU, was named only for having no values).
    Now, as the rest of the library: "<name>: expected the device of image1 (cpu), got meta"."""
    from fsof_torch import fit_image

    p = render_pair("default", 0, size=(24, 80))
    flow, road, cam = p["flow"][None], p["road"][None], p["camera"]
    args = {"image1": p["image1"][None], "image2": p["image2"][None], "mask": road}
    for name in ("image2", "mask"):
        mixed = dict(args, **{name: args[name].to("meta")})
        with pytest.raises(ValueError, match=rf"^{name}: expected the device of image1 \(cpu\), got meta$"):
            fit_image(mixed["image1"], mixed["image2"], mixed["mask"], cam)
        with pytest.raises(ValueError, match=rf"^{name}: expected the device of image1 \(cpu\), got meta$"):
            ImageMotionEstimator()(flow, mixed["mask"], cam, images=(mixed["image1"], mixed["image2"]))
    with pytest.raises(ValueError, match=r"^flow: expected the device of image1 \(cpu\), got meta$"):
        ImageMotionEstimator()(flow.to("meta"), road, cam, images=(args["image1"], args["image2"]))
    with pytest.raises(ValueError, match=r"^image2: expected the device of image1 \(meta\), got cpu$"):
        fit_image(args["image1"].to("meta"), args["image2"], road, cam)


def test_the_flow_estimator_names_a_mask_on_another_device_with_a_non_finite_flow():
    """FlowMotionEstimator leaves a flow's non-finite pixels out of the mask before fit_road, which
    names a mask on another device: with a NaN in the flow that mask met the flow first, and a CUDA
    mask with a CPU flow came to torch's own device error there (meta: "Tensor on device cpu is
    not on the expected device meta!"). Now the same ValueError as fit_road's, first; the NaN
    pixel is still left out on one device."""
    p = render_pair("default", 0, size=(96, 320))
    flow, road = p["flow"][None].clone(), p["road"][None]
    flow[0, :, 80, 160] = math.nan
    assert bool(road[0, 0, 80, 160])
    with pytest.raises(ValueError, match=r"^mask: expected the device of flow \(cpu\), got meta$"):
        FlowMotionEstimator()(flow, road.to("meta"), p["camera"])
    fit = FlowMotionEstimator()(flow, road, p["camera"])
    assert bool(fit.success.all()) and abs(float(fit.z_d) - p["plane"]["z_d"]) < 1e-4


def test_planar_start_takes_the_camera_to_the_flows_device_and_names_a_mask_on_another():
    """planar_start (ImageMotionEstimator's start from a flow) used the camera where it came: a CPU
    camera (as read from a calibration file) with a CUDA flow and images met torch's own device
    error from inside (a meta camera with a CPU flow: "Tensor on device meta is not on the
    expected device cpu!"), and a mask on another device than the flow torch's error from its
    sampling (meta: nonzero's NotImplementedError). Now the camera follows the flow's device, as
    in the fits, and a mask elsewhere is named; a CPU call gives the same start as ever."""
    from fsof_torch.refinement.estimators import planar_start

    p = render_pair("default", 0, size=(96, 320))
    flow, road, cam = p["flow"][None], p["road"][None], p["camera"]
    start = planar_start(flow, road, cam)
    for k in ("x_d", "z_d", "yaw"):  # (the scene's own motion, from its rendered flow)
        assert abs(float(start[k]) - p["plane"][k]) < 1e-3, (k, float(start[k]), p["plane"][k])
    with pytest.raises(ValueError, match=r"^camera: a camera on the meta device has shapes but no values to move"):
        planar_start(flow, road, cam.to("meta"))
    with pytest.raises(ValueError, match=r"^mask: expected the device of flow \(cpu\), got meta$"):
        planar_start(flow, road.to("meta"), cam)
    with pytest.raises(ValueError, match=r"^mask: expected the device of flow \(meta\), got cpu$"):
        planar_start(flow.to("meta"), road, cam)


def test_starts_and_priors_on_the_meta_device_are_named():
    """A start or a prior on the meta device with real data: a ValueError naming its key (was a
    TypeError "expected a number or a tensor", a tensor it was, or torch's "Cannot copy out of
    meta tensor"), in the fits and through the refiner."""
    from fsof_torch import fit_image, fit_road, refine_flow

    p = render_pair("default", 0, size=(24, 80))
    flow, road, cam = p["flow"][None], p["road"][None], p["camera"]
    images = (p["image1"][None], p["image2"][None])
    meta = torch.tensor([1.0], device="meta")
    start = r"a tensor on the meta device has shapes but no values to start a fit from; move it to a real device"
    prior = r"^prior\['z_d'\]: a tensor on the meta device has shapes but no values for a prior"
    with pytest.raises(ValueError, match=rf"^init\['z_d'\]: {start}"):
        fit_road(flow, road, cam, init={"z_d": meta})
    with pytest.raises(ValueError, match=rf"^init\['z_d'\]: {start}"):
        fit_image(*images, road, cam, init={"z_d": meta})
    with pytest.raises(ValueError, match=rf"^starts\[0\]\['z_d'\]: {start}"):
        fit_image(*images, road, cam, starts=[{"z_d": meta}])
    with pytest.raises(ValueError, match=rf"^starts\[0\]\['z_d'\]: {start}"):
        refine_flow(flow, road, cam, images=images, starts=[{"z_d": meta}])
    for spec in ((meta, 1.0), (1.0, meta)):
        with pytest.raises(ValueError, match=prior):
            fit_road(flow, road, cam, prior={"z_d": spec})
        with pytest.raises(ValueError, match=prior):
            fit_image(*images, road, cam, prior={"z_d": spec})
    with pytest.raises(TypeError, match=r"^init: expected a number or a tensor for z_d, got str 'a'"):
        fit_road(flow, road, cam, init={"z_d": "a"})  # (what the message is for)
    from fsof_torch.estimation.sequence import smooth_attitude

    with pytest.raises(ValueError, match=r"^change_sigma: a tensor on the meta device has shapes but no values"):
        smooth_attitude(torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), 0.01, meta)


def _tensors(obj, prefix="out"):
    """Every tensor in a refiner's output (its fit's and gate's too), by name."""
    import dataclasses

    if isinstance(obj, torch.Tensor):
        return {prefix: obj}
    if isinstance(obj, Camera):
        return {f"{prefix}.{n}": getattr(obj, n) for n in ("K", "height", "roll", "pitch")}
    if hasattr(obj, "_fields"):
        items = {k: getattr(obj, k) for k in obj._fields}
    elif dataclasses.is_dataclass(obj):
        items = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    elif isinstance(obj, dict):
        items = obj
    else:
        return {}
    return {k: v for name, item in items.items() for k, v in _tensors(item, f"{prefix}.{name}").items()}


@pytest.mark.parametrize("above_horizon", [False, True])
def test_the_refiner_searches_its_mask_once_for_the_estimate_and_the_gate(small_pair, monkeypatch, above_horizon):
    """The planar start, the fit and the gate sample one mask: where the gate judges the very pixels
    the estimate used, they are found once, else (a mask reaching above the horizon, where the
    model is undefined: the gate judges fewer) twice; the output is the same bit for bit as with
    every search made anew."""
    import contextlib

    import fsof_torch.estimation.sampling as sampling
    import fsof_torch.refinement.estimators as estimators
    import fsof_torch.refinement.fusion as fusion

    p, images, road = small_pair
    if above_horizon:
        road = road.clone()
        road[..., :3, 100:200] = True
    flow = p["flow"][None].float()
    sizes, flatnonzero = [], sampling.np.flatnonzero
    monkeypatch.setattr(sampling.np, "flatnonzero", lambda a: sizes.append(a.size) or flatnonzero(a))
    out = FreespaceRefiner()(flow, road, p["camera"], images=images)
    assert out.gate is not None and sizes.count(road.numel()) == (2 if above_horizon else 1)
    sizes.clear()
    for module in (fusion, estimators):  # (every search made anew)
        monkeypatch.setattr(module, "reused_mask_pixels", lambda memo=None: contextlib.nullcontext())
    plain = FreespaceRefiner()(flow, road, p["camera"], images=images)
    assert sizes.count(road.numel()) == 3
    got, expected = _tensors(out), _tensors(plain)
    assert got.keys() == expected.keys() and len(got) > 30
    for name, t in expected.items():
        assert torch.equal(got[name], t), name
