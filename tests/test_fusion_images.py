"""The refiner with images (fsof_torch.refinement.fusion): odometry and images sample by sample,
gradients to a held odometry, starts of the estimated samples, the images' own checks, and the
odometry reported for samples left unrefined."""

from __future__ import annotations

import warnings

import pytest
import torch

from fsof_torch.data.scene import render_pair
from fsof_torch.refinement.fusion import FreespaceRefiner

pytestmark = pytest.mark.usefixtures("one_thread")

SIZE = (96, 320)


@pytest.fixture(scope="module")
def scene():
    p = render_pair("default", 1, size=SIZE)
    noise = 2.0 * torch.randn(p["flow"].shape, generator=torch.Generator().manual_seed(0))
    return {**p, "pred": (p["flow"] + noise)[None]}


def _two(scene, black_second: bool = True):
    """A batch of two copies of the scene; the second's image 2 black (nothing to estimate from)."""
    i1 = torch.stack([scene["image1"]] * 2)
    i2 = torch.stack([scene["image2"]] * 2)
    if black_second:
        i2[1] = 0.0
    return scene["pred"].expand(2, -1, -1, -1).clone(), torch.stack([scene["road"]] * 2), i1, i2


def _planar(scene, B: int, requires_grad: bool = False) -> dict:
    return {k: torch.full((B,), float(scene["odometry"][k]), requires_grad=requires_grad)
            for k in ("x_d", "z_d", "yaw")}


def _quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return fn(*args, **kwargs)


def test_planar_odometry_with_images_is_decided_sample_by_sample(scene):
    """Where the images give no estimate for one sample, that sample takes the planar odometry
    alone and the others keep their image estimate, each as it would alone."""
    pred, road, i1, i2 = _two(scene)
    refiner = FreespaceRefiner()
    both = _quiet(refiner, pred, road, scene["camera"], _planar(scene, 2), images=(i1, i2))
    for b in range(2):
        alone = _quiet(refiner, pred[b:b + 1], road[b:b + 1], scene["camera"], _planar(scene, 1),
                       images=(i1[b:b + 1], i2[b:b + 1]))
        torch.testing.assert_close(both.flow[b], alone.flow[0], rtol=0, atol=1e-3)
        assert bool(both.refined[b]) == bool(alone.refined[0])
    assert both.model == "plane" and both.fit is not None and both.fit.success.tolist() == [True, False]
    # the second sample's model flow is the planar odometry's, with the camera's attitude
    assert float(both.camera.roll[1]) == pytest.approx(float(scene["camera"].roll[0]))
    assert float(both.camera.pitch[1]) == pytest.approx(float(scene["camera"].pitch[0]))
    planar_only = FreespaceRefiner(gate=None)(pred[1:], road[1:], scene["camera"], _planar(scene, 1))
    assert planar_only.model == "paper"
    torch.testing.assert_close(both.flow_model[1], planar_only.flow_model[0], rtol=0, atol=1e-4)


def test_gradient_reaches_a_planar_odometry_held_with_images(scene):
    """The images estimate the rest of the motion; the planar odometry they hold is the caller's
    own tensors: the loss's gradient with respect to it is that of the same complete motion given
    directly (no estimate)."""
    road = scene["road"][None]
    images = (scene["image1"][None], scene["image2"][None])
    odo = _planar(scene, 1, requires_grad=True)
    out = FreespaceRefiner()(scene["pred"], road, scene["camera"], odo, images=images)
    assert out.model == "plane" and bool(out.refined[0])
    loss = (out.flow - scene["flow"][None]).abs().mean()
    loss.backward()
    direct = {k: v.detach().clone().requires_grad_(k in ("x_d", "z_d", "yaw")) for k, v in out.odometry.items()}
    again = FreespaceRefiner()(scene["pred"], road, out.camera, {"model": out.model, **direct}, images=images)
    (again.flow - scene["flow"][None]).abs().mean().backward()
    for k in ("x_d", "z_d", "yaw"):
        assert odo[k].grad is not None and bool(torch.isfinite(odo[k].grad).all()), k
        torch.testing.assert_close(odo[k].grad, direct[k].grad, rtol=1e-5, atol=1e-7)
    assert float(odo["z_d"].grad.abs()) > 0


def test_starts_follow_the_samples_that_are_estimated(scene):
    """A start of the whole batch (per-sample tensors, or the previous fit) is cut down with it
    where some samples have no road: the others are estimated as alone, each from its own start
    (not from the first samples' starts)."""
    import dataclasses

    from fsof_torch import ImageMotionEstimator

    pred, road, i1, i2 = _two(scene, black_second=False)
    road[0] = False  # the first sample has no road: the second is the one estimated
    # the given start is the estimator's only one, so the start that sample 1 takes shows in its result
    estimator = ImageMotionEstimator(flow_start=False, retry_starts=0, turn_starts=(), forward_starts=(),
                                     retry_without_prior=False)
    refiner = FreespaceRefiner(estimator=estimator)
    truth = {k: float(v) for k, v in scene["plane"].items() if k != "height"}
    # each sample its own start: the road-less first one far off (z_d 3 m), the second the truth
    start = {"model": "plane", **{k: torch.tensor([3.0 if k == "z_d" else 0.0, v]) for k, v in truth.items()}}
    fit = refiner(pred, torch.stack([scene["road"]] * 2), scene["camera"], images=(i1, i2)).fit
    previous = dataclasses.replace(fit, params={k: torch.stack([torch.tensor(3.0 if k == "z_d" else 0.0), v[1]])
                                                for k, v in fit.params.items()})
    for s in (start, previous):
        out = _quiet(refiner, pred, road, scene["camera"], images=(i1, i2), starts=(s,))
        assert out.refined.tolist() == [False, True]
        assert torch.equal(out.flow[0], pred[0])
        params = previous.params if s is previous else {k: v for k, v in s.items() if k != "model"}
        second = {"model": "plane", **{k: v[1:] for k, v in params.items()}}
        alone = refiner(pred[1:], road[1:], scene["camera"], images=(i1[1:], i2[1:]), starts=(second,))
        torch.testing.assert_close(out.flow[1], alone.flow[0], rtol=0, atol=1e-3)
        torch.testing.assert_close(out.odometry["z_d"][1], alone.odometry["z_d"][0], rtol=0, atol=1e-4)


def test_planar_odometry_follows_the_samples_that_are_estimated(scene):
    """The planar odometry of the whole batch is cut down with it as the starts are: the second
    sample (the first has no road) is estimated with its own odometry, as alone."""
    pred, road, i1, i2 = _two(scene, black_second=False)
    road[0] = False
    odo = _planar(scene, 2)
    odo["z_d"] = torch.tensor([3.0, float(scene["odometry"]["z_d"])])  # each sample its own
    refiner = FreespaceRefiner()
    out = _quiet(refiner, pred, road, scene["camera"], odo, images=(i1, i2))
    assert out.refined.tolist() == [False, True] and torch.equal(out.flow[0], pred[0])
    alone = _quiet(refiner, pred[1:], road[1:], scene["camera"], {k: v[1:] for k, v in odo.items()},
                   images=(i1[1:], i2[1:]))
    torch.testing.assert_close(out.flow[1], alone.flow[0], rtol=0, atol=1e-3)
    assert float(out.odometry["z_d"][1]) == pytest.approx(float(scene["odometry"]["z_d"]))


@pytest.mark.parametrize("how", ["0..1", "nan"])
def test_images_are_checked_without_an_estimate(scene, how):
    """With the complete motion given, nothing estimates from the images, yet the gate judges by
    them: they are checked all the same (finite, on 0..255)."""
    motion = {"model": "plane", **{k: v for k, v in scene["plane"].items() if k != "height"}}
    image1, image2 = scene["image1"][None].clone(), scene["image2"][None]
    if how == "0..1":
        image1, image2 = image1 / 255, image2 / 255
        match = r"^images\[0\]: values in .* look like 0..1 images, expected 0..255"
    else:
        image1[0, 0, 5, 5] = float("nan")
        match = r"^images\[0\]: expected finite pixel values"
    with pytest.raises(ValueError, match=match):
        FreespaceRefiner()(scene["pred"], scene["road"][None], scene["camera"], motion, images=(image1, image2))


def test_a_dim_colour_frame_is_judged_by_its_colours_not_its_grey(scene):
    """Frames on 0..255 whose brightest colour is a few grey levels while their grey stays below 1:
    the refiner checks the colours (they pass), and its image estimate, which fits their grey
    levels, does not take that grey for a 0..1 image (it raised "look like 0..1"). The fit on the
    colours takes them too; the grey alone, handed to the fit, is still questioned."""
    from fsof_torch import fit_image
    from fsof_torch.evaluation.photometric import to_grey

    image1, image2 = (torch.zeros_like(scene[k][None]) for k in ("image1", "image2"))
    image1[:, 0], image2[:, 0] = (3.0 * (scene[k][None, 0] > 128) for k in ("image1", "image2"))
    assert float(image1.amax()) == 3.0 and float(to_grey(image1).amax()) < 1.0
    out = _quiet(FreespaceRefiner(), scene["pred"], scene["road"][None], scene["camera"], images=(image1, image2))
    assert out.flow.shape == scene["pred"].shape and out.fit is not None
    fit_image(image1, image2, scene["road"][None], scene["camera"])
    with pytest.raises(ValueError, match="look like 0..1 images"):
        fit_image(to_grey(image1), to_grey(image2), scene["road"][None], scene["camera"])


def test_odometry_of_samples_left_unrefined_is_zero(scene):
    """RefineOutput.odometry holds 0 for the samples that were not refined, as documented."""
    pred, road, i1, i2 = _two(scene)
    out = _quiet(FreespaceRefiner(), pred, road, scene["camera"], images=(i1, i2))
    assert out.refined.tolist() == [True, False]
    assert all(float(v[1]) == 0.0 for v in out.odometry.values())
    assert float(out.odometry["z_d"][0]) > 0.5



@pytest.mark.parametrize("images", [True, False])
def test_a_sample_not_estimated_reports_the_same_motion_alone_as_in_a_batch(scene, images):
    """A sample with an empty mask reported the image estimator's "plane" model (eight zeros) or the
    flow fit's paper model with its roll and pitch (five) beside an estimated sample, but alone, or
    in a batch where no sample was estimated, the paper's x_d, z_d and yaw alone, under model
    "paper": out.odometry["y_d"] raised a KeyError on such a frame only. Alone it is now what the
    batch says of it, the same model, keys and zeros, and its model flow 0 as there."""
    pred, road, i1, i2 = _two(scene, black_second=False)
    road[1] = False
    kw = {"images": (i1, i2)} if images else {}
    both = _quiet(FreespaceRefiner(), pred, road, scene["camera"], **kw)
    alone = _quiet(FreespaceRefiner(), pred[1:], road[1:], scene["camera"],
                   **({"images": (i1[1:], i2[1:])} if images else {}))
    assert both.refined.tolist() == [True, False] and alone.refined.tolist() == [False]
    assert alone.model == both.model == ("plane" if images else "paper")
    assert list(alone.odometry) == list(both.odometry)
    assert all(float(v[1]) == 0.0 and float(alone.odometry[k]) == 0.0 for k, v in both.odometry.items())
    assert torch.equal(alone.flow_model, both.flow_model[1:]) and not bool(alone.flow_model.any())
    assert torch.equal(alone.flow, pred[1:])

def test_the_fit_covers_the_estimated_samples_not_the_refined_ones(scene):
    """RefineOutput.fit holds every estimated sample, a failed one too (the docstring once said
    that ``refined`` tells which samples it covers)."""
    pred, road, i1, i2 = _two(scene)  # (the second's image 2 black: its estimate fails)
    pred, road, i1, i2 = (torch.cat([t, t[:1]]) for t in (pred, road, i1, i2))
    road[2] = False  # (not estimated)
    out = _quiet(FreespaceRefiner(), pred, road, scene["camera"], images=(i1, i2))
    assert out.refined.tolist() == [True, False, False]
    assert out.fit.success.tolist() == [True, False]


@pytest.mark.parametrize("mode", ["replace", "confidence"])
def test_fuse_flow_weight_has_the_flows_batch(mode):
    """A mask of batch 1 is broadcast: the weight is (B, 1, H, W) in both modes, as documented."""
    from fsof_torch.refinement.fusion import fuse_flow

    pred = torch.randn(3, 2, 8, 10, generator=torch.Generator().manual_seed(0))
    mask = torch.zeros(1, 1, 8, 10, dtype=torch.bool)
    mask[..., 2:5, 3:7] = True
    out, weight = fuse_flow(pred, torch.zeros_like(pred), mask, mode=mode)
    assert tuple(weight.shape) == (3, 1, 8, 10) and tuple(out.shape) == (3, 2, 8, 10)
    assert bool((weight[:, :, ~mask[0, 0]] == 0).all())


def test_nan_predictions_in_a_sample_the_gate_leaves_unchanged(scene):
    """With the complete motion given and image 2 of the second sample black, the gate leaves that
    sample unchanged: its NaN predicted pixels inside the mask come back NaN, the first sample's
    get the model flow, and the warning counts both (it no longer claims all were replaced)."""
    pred, road, i1, i2 = _two(scene)
    ys, xs = road[0, 0].nonzero(as_tuple=True)
    pick = torch.arange(0, ys.numel(), 97)[:10]
    pred[:, :, ys[pick], xs[pick]] = float("nan")
    motion = {"model": "plane", **{k: v for k, v in scene["plane"].items() if k != "height"}}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = FreespaceRefiner()(pred, road, scene["camera"], motion, images=(i1, i2))
    assert out.refined.tolist() == [True, False]
    assert ("flow: 20 non-finite predicted pixels inside the mask, left out of the estimation; 10 replaced by "
            "the model flow; 10 left as they came") in "\n".join(str(w.message) for w in caught)
    torch.testing.assert_close(out.flow[0][:, ys[pick], xs[pick]], out.flow_model[0][:, ys[pick], xs[pick]],
                               rtol=0, atol=0)
    torch.testing.assert_close(out.flow[1], pred[1], rtol=0, atol=0, equal_nan=True)


def test_a_complete_paper_motion_is_used_as_it_is_with_images(scene):
    """A fit result of the paper's model, or a dict with "model": "paper", is a complete motion:
    used as it is (as the docs' table says), not taken for planar odometry to complete from the
    images (its roll and pitch were replaced and the model switched to "plane")."""
    from fsof_torch.estimation.flow_fit import fit_road

    pred, road, cam = scene["pred"], scene["road"][None], scene["camera"]
    images = (scene["image1"][None], scene["image2"][None])
    fit = fit_road(scene["flow"][None], road & scene["valid"][None], cam, model="paper")
    given = {"model": "paper", **{k: float(scene["odometry"][k]) for k in ("x_d", "z_d", "yaw")},
             "roll": 0.0175, "pitch": -0.0175}
    for motion in (fit, given):
        out = _quiet(FreespaceRefiner(gate=None), pred, road, cam, motion, images=images)
        assert out.model == "paper" and out.fit is None
        assert float(out.odometry["roll"]) == pytest.approx(float(torch.as_tensor(
            motion.params["roll"] if motion is fit else motion["roll"])))
    planar = {k: float(scene["odometry"][k]) for k in ("x_d", "z_d", "yaw")}
    assert _quiet(FreespaceRefiner(gate=None), pred, road, cam, planar, images=images).model == "plane"


def test_a_fit_result_given_is_used_where_it_succeeded(scene):
    """A fit result given as odometry is an estimate (the docs: judged by its success, so not checked
    for steps in mm): its failed samples were refined with the failed motion all the same (a mask
    tensor; mask="auto" flags them no_motion). They now come back unchanged, refined False, as the
    refiner's own failed estimates; the others as they would alone."""
    import dataclasses

    from fsof_torch.estimation.flow_fit import fit_road

    pred, road, cam = scene["pred"].expand(2, -1, -1, -1), scene["road"][None].expand(2, -1, -1, -1), scene["camera"]
    images = tuple(scene[k][None].expand(2, -1, -1, -1) for k in ("image1", "image2"))
    fit = fit_road(scene["flow"][None], road[:1] & scene["valid"][None], cam, model="paper")
    assert fit.success.tolist() == [True]
    half = dataclasses.replace(fit, params={k: v.expand(2) for k, v in fit.params.items()},
                               success=torch.tensor([True, False]))
    for these, gate in ((None, None), (images, None), (images, "auto")):
        out = _quiet(FreespaceRefiner(gate=gate), pred, road, cam, half, images=these)
        alone = _quiet(FreespaceRefiner(gate=gate), pred[:1], road[:1], cam, fit, images=None if these is None else
                       tuple(i[:1] for i in these))
        assert out.refined.tolist() == [True, False] and bool(alone.refined[0])
        assert torch.equal(out.flow[1], pred[1]) and torch.equal(out.flow[0], alone.flow[0])
        assert float(out.odometry["z_d"][1]) == 0.0 and not bool(out.mask[1].any())
    # a fit of batch 1 serves the batch, its success too
    out = _quiet(FreespaceRefiner(gate=None), pred, road, cam, dataclasses.replace(fit, success=torch.tensor([False])))
    assert out.refined.tolist() == [False, False] and torch.equal(out.flow, pred)


def test_the_papers_dict_with_its_roll_or_pitch_is_a_complete_motion_with_images(scene):
    """{x_d, z_d, yaw, roll} (no "model" key) is the paper's motion at that roll: without images the
    refiner used the roll given, with images it was taken for planar odometry and the image estimate
    replaced the roll and pitch given, silently (and the flow estimator held them: the estimators
    disagreed). It is now used as it is, as with "model": "paper", also with images."""
    pred, road, cam = scene["pred"], scene["road"][None], scene["camera"]
    images = (scene["image1"][None], scene["image2"][None])
    planar = {k: float(scene["odometry"][k]) for k in ("x_d", "z_d", "yaw")}
    for extra in ({"roll": 0.03}, {"pitch": -0.03}, {"roll": 0.0, "pitch": 0.0}):
        given = {**planar, **extra}
        reference = _quiet(FreespaceRefiner(gate=None), pred, road, cam, {"model": "paper", **given}, images=images)
        for these in (images, None):
            out = _quiet(FreespaceRefiner(gate=None), pred, road, cam, given, images=these)
            assert out.model == "paper" and out.fit is None
            for k, v in extra.items():
                assert float(out.odometry[k]) == pytest.approx(v)
            torch.testing.assert_close(out.flow, reference.flow, rtol=0, atol=0)
    # the planar odometry alone is completed from the images
    out = _quiet(FreespaceRefiner(gate=None), pred, road, cam, planar, images=images)
    assert out.model == "plane" and out.fit is not None


def test_an_estimator_result_without_a_flow_of_this_size(scene):
    """The docs ask an estimator's result for model, params, success and camera: one without a
    ``flow`` raised AttributeError, one with a flow of another size a size mismatch; the model
    flow is then computed, as for a given motion."""
    from types import SimpleNamespace

    from fsof_torch.estimation.flow_fit import fit_road

    pred, road, cam = scene["pred"], scene["road"][None], scene["camera"]
    exact = fit_road(scene["flow"][None], road & scene["valid"][None], cam, model="paper")

    def minimal(flow, mask, camera, **_):
        return SimpleNamespace(model="paper", params=exact.params, success=exact.success, camera=exact.camera)

    def half_size(flow, mask, camera, **_):  # every second pixel: u' = u / 2, flow halved
        K = cam.K * torch.tensor([[0.5], [0.5], [1.0]], dtype=cam.K.dtype)
        return fit_road(0.5 * scene["flow"][None, :, ::2, ::2], (road & scene["valid"][None])[..., ::2, ::2],
                        cam.replace(K=K), model="paper")

    reference = FreespaceRefiner(gate=None)(pred, road, cam, exact)
    for estimator in (minimal, half_size):
        out = _quiet(FreespaceRefiner(estimator=estimator, gate=None), pred, road, cam)
        assert bool(out.refined.all())
        torch.testing.assert_close(out.flow, reference.flow, atol=2e-3, rtol=0)


def test_a_custom_estimators_flow_field_is_not_taken_for_the_model_flow(scene):
    """A result that is no RoadFit, with a full-size ``flow`` and ``valid`` of its own meaning (here
    the flow and mask it was given), once replaced the model flow: the prediction came back as the
    'refined' flow. Only a RoadFit's flow is its model flow; another result's motion is evaluated."""
    from types import SimpleNamespace

    from fsof_torch.estimation.flow_fit import fit_road

    pred, road, cam = scene["pred"], scene["road"][None], scene["camera"]
    exact = fit_road(scene["flow"][None], road & scene["valid"][None], cam, model="paper")

    def echoing(flow, mask, camera, **_):
        return SimpleNamespace(model="paper", params=exact.params, success=exact.success, camera=exact.camera,
                               flow=flow.clone(), valid=mask.clone())

    reference = FreespaceRefiner(gate=None)(pred, road, cam, exact)
    out = _quiet(FreespaceRefiner(estimator=echoing, gate=None), pred, road, cam)
    assert bool(out.refined.all()) and not torch.equal(out.flow, pred)
    torch.testing.assert_close(out.flow, reference.flow, atol=2e-3, rtol=0)
    torch.testing.assert_close(out.flow_model, reference.flow_model, atol=2e-3, rtol=0)


def test_images_of_another_channel_count_and_a_ptlflow_dict_are_named(scene):
    """RGB beside grey failed inside the estimator as 'image2'; a ptlflow dict given as images= was
    named 'inputs'."""
    pred, road, cam = scene["pred"], scene["road"][None], scene["camera"]
    i1 = scene["image1"][None]
    with pytest.raises(ValueError, match=r"^images\[1\]: expected 1 \(grey\) or 3 \(RGB\) channels, as images\[0\] has"):
        FreespaceRefiner()(pred, road, cam, images=(i1, i1.mean(1, keepdim=True)))
    # a first image of another count (RGBA) is named without a comparison with itself
    rgba = torch.cat([i1, torch.full_like(i1[:, :1], 255.0)], 1)
    with pytest.raises(ValueError, match=r"^images\[0\]: expected 1 \(grey\) or 3 \(RGB\) channels, got shape "
                                         r"\(1, 4, \d+, \d+\)$"):
        FreespaceRefiner()(pred, road, cam, images=(rgba, rgba))
    ptl = {"images": torch.stack([i1, i1], 1)}  # on 0..255, not ptlflow's 0..1
    with pytest.raises(ValueError, match=r"^images\['images'\]: expected BGR values in \[0, 1\]"):
        FreespaceRefiner()(pred, road, cam, images=ptl)


def test_images_of_batch_1_serve_every_sample(scene):
    """Images of batch 1 judge every sample of a batch of predictions (B predictions of one pair),
    as the images repeated would; a batch that is neither 1 nor the flow's is named with both."""
    pred, road, cam = scene["pred"], scene["road"][None], scene["camera"]
    preds = torch.cat([pred, pred + 0.5])
    i1, i2 = scene["image1"][None], scene["image2"][None]
    one = _quiet(FreespaceRefiner(), preds, road, cam, images=(i1, i2))
    two = _quiet(FreespaceRefiner(), preds, road, cam, images=(i1.expand(2, -1, -1, -1), i2.expand(2, -1, -1, -1)))
    assert torch.equal(one.flow, two.flow) and torch.equal(one.refined, two.refined)
    H, W = SIZE
    with pytest.raises(ValueError, match=rf"^images\[0\]: expected shape \(1 or 2, C, {H}, {W}\) \(the finest flow's size\), "
                                         rf"got \(3, 3, {H}, {W}\)"):
        FreespaceRefiner()(preds, road, cam, images=(torch.cat([i1] * 3), torch.cat([i2] * 3)))


def test_fuse_flow_takes_a_numpy_scale_as_the_refiner_does(scene):
    import numpy as np

    from fsof_torch.refinement.fusion import fuse_flow

    pred, road = scene["pred"], scene["road"][None]
    model = scene["flow"][None]
    a = fuse_flow(pred, model, road, mode="confidence", scale=np.float32(2.0))
    b = fuse_flow(pred, model, road, mode="confidence", scale=2.0)
    torch.testing.assert_close(a, b)


def test_a_backward_flow_is_refined_with_the_frames_swapped():
    """ARFlow-style backward flows (image 2 to image 1, a pyramid list) refined by a call of their
    own with the frames swapped and image 2's road (docs/contracts.md): the default scene at 2.4 m
    a frame, the road receding from the camera. Against the true backward road flow (the inverse
    of the forward road map) the road's error drops from DIS's 36 px to under two."""
    from fsof_torch import road_homography
    from refine.sources import dis_flow

    size = (188, 621)
    p = render_pair("default", 0, size=size, speed_factor=2.0)
    road2 = render_pair("default", 1, size=size, speed_factor=2.0)["road"][None]
    camera = p["camera"].to(torch.float64)
    forward = road_homography(camera, {k: torch.tensor([v], dtype=torch.float64) for k, v in p["odometry"].items()},
                              model="paper")[0]
    v, u = torch.meshgrid(torch.arange(size[0], dtype=torch.float64), torch.arange(size[1], dtype=torch.float64),
                          indexing="ij")
    x = torch.stack([u, v, torch.ones_like(u)]).reshape(3, -1)
    y = torch.linalg.inv(forward) @ x
    truth = (y[:2] / y[2:] - x[:2]).reshape(2, *size)
    backward = dis_flow(p["image2"], p["image1"])[None]
    flows_bw = [torch.nn.functional.avg_pool2d(backward, 2) / 2, backward]  # (a coarse level and the finest)
    out = FreespaceRefiner()(flows_bw, road2, p["camera"], images=(p["image2"][None], p["image1"][None]))
    assert isinstance(out.flow, list) and bool(out.refined[0])
    on_road = road2[0, 0]
    before = float((backward[0].double() - truth).norm(dim=0)[on_road].mean())
    after = float((out.flow[1][0].double() - truth).norm(dim=0)[on_road].mean())
    assert after < 2.0 < before


def test_a_refiner_carries_nothing_from_one_call_to_the_next(scene):
    """A refiner (and its default estimator and gate) holds no state between calls: pair B after
    pair A gives, bit for bit, what a fresh refiner gives for B, and the same call twice gives the
    same result. Pair A is another scene (with body motion), so its motion or its model flow carried
    over into the call on B would show."""
    other = render_pair("body-motion", 3, size=SIZE)
    noise = 2.0 * torch.randn(other["flow"].shape, generator=torch.Generator().manual_seed(1))
    a = ((other["flow"] + noise)[None], other["road"][None], other["camera"],
         {"images": (other["image1"][None], other["image2"][None])})
    b = (scene["pred"], scene["road"][None], scene["camera"], {"images": (scene["image1"][None], scene["image2"][None])})

    def outputs(out):
        fit = out.fit
        return [out.flow, out.weight, out.mask, out.refined, out.flow_model, *out.odometry.values(),
                out.gate.use_model, out.gate.evidence, fit.homography, *fit.params.values()]

    for options in ({}, {"mode": "confidence"}):
        used = FreespaceRefiner(**options)
        _quiet(used, *a[:3], **a[3])
        after_a = outputs(_quiet(used, *b[:3], **b[3]))
        fresh = outputs(_quiet(FreespaceRefiner(**options), *b[:3], **b[3]))
        again = outputs(_quiet(used, *b[:3], **b[3]))
        for x, y, z in zip(after_a, fresh, again):
            assert torch.equal(x, y) and torch.equal(x, z), options


def test_the_image_estimator_and_the_gate_compare_the_frames_grey_converted_once(scene, monkeypatch):
    """The image estimator and the gate both compare grey levels: where the images share the flow's
    precision the refiner converts them once and hands both the grey frames (bit for bit the
    result of RGB frames); another estimator, a subclass of the image estimator (which may read
    the colours), or images in another precision, get them as they came."""
    from fsof_torch.evaluation.photometric import to_grey
    from fsof_torch.refinement.estimators import ImageMotionEstimator

    seen = []
    call = ImageMotionEstimator.__call__

    def spy(self, flow, mask, camera, *, images=None, **kw):
        seen.append(tuple(images[0].shape) + (images[0].dtype,))
        return call(self, flow, mask, camera, images=images, **kw)

    monkeypatch.setattr(ImageMotionEstimator, "__call__", spy)
    i1, i2 = scene["image1"][None], scene["image2"][None]
    args = (scene["pred"], scene["road"][None], scene["camera"])
    rgb = _quiet(FreespaceRefiner(), *args, images=(i1, i2))
    grey = _quiet(FreespaceRefiner(), *args, images=(to_grey(i1), to_grey(i2)))
    assert seen[0] == (1, 1, *SIZE, torch.float32)
    assert bool(rgb.refined.all()) and torch.equal(rgb.flow, grey.flow) and torch.equal(rgb.weight, grey.weight)
    _quiet(FreespaceRefiner(), *args, images=(i1.double(), i2.double()))
    assert seen[2] == (1, 3, *SIZE, torch.float64)  # (the gate works in the float32 flow's precision)

    class Sub(ImageMotionEstimator):
        pass

    _quiet(FreespaceRefiner(estimator=Sub()), *args, images=(i1, i2))
    assert seen[3] == (1, 3, *SIZE, torch.float32)

    class Other:
        def __call__(self, flow, mask, camera, *, images=None, **kw):
            seen.append(tuple(images[0].shape))
            return ImageMotionEstimator()(flow, mask, camera, images=images, **kw)

    _quiet(FreespaceRefiner(estimator=Other()), *args, images=(i1, i2))
    assert seen[4] == (1, 3, *SIZE)


@pytest.mark.parametrize("rows, cols", [(slice(60, 61), slice(0, 320)), (slice(40, 96), slice(100, 101)),
                                        (slice(60, 61), slice(100, 101))])
def test_frames_of_one_row_or_column_give_the_image_fit_nothing(scene, rows, cols):
    """Once a ValueError quoting a grey 'image1' the caller never gave (the image fit's 2 x 2
    minimum), and only where the image estimator ran: with odometry, or with 100 mask pixels or
    more. The estimate fails instead: the odometry alone, or the sample left unchanged."""
    box = (..., rows, cols)
    pred = scene["pred"][box].contiguous()
    images = tuple(scene[k][None][box].contiguous() for k in ("image1", "image2"))
    camera = scene["camera"].cropped(cols.start, rows.start)
    mask = torch.ones(1, 1, *pred.shape[-2:], dtype=torch.bool)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        alone = FreespaceRefiner(gate=None)(pred, mask, camera, scene["odometry"])
        held = FreespaceRefiner(gate=None)(pred, mask, camera, scene["odometry"], images=images)
        estimated = FreespaceRefiner()(pred, mask, camera, images=images)
        gated = FreespaceRefiner()(pred, mask, camera, scene["odometry"], images=images)
    assert held.refined.tolist() == [True] and held.fit is None and torch.equal(held.flow, alone.flow)
    assert estimated.refined.tolist() == [False] and torch.equal(estimated.flow, pred)
    assert gated.refined.tolist() == [False] and torch.equal(gated.flow, pred)  # (no evidence in such frames)


@pytest.mark.parametrize("dtypes", [(torch.float32, torch.float64), (torch.float64, torch.float32),
                                    (torch.float32, torch.float16)])
def test_frames_of_two_dtypes_are_refined_as_they_came(scene, dtypes):
    """Where image 1 shared the flow's precision and image 2 did not, the refiner's one grey
    conversion wrote image 2 into a tensor of image 1's dtype: a TypeError naming ``out``, an
    argument of no public function. Frames of two dtypes reach the estimator as they came."""
    i1, i2 = scene["image1"][None], scene["image2"][None]
    args = (scene["pred"].to(dtypes[0]), scene["road"][None], scene["camera"])
    out = _quiet(FreespaceRefiner(), *args, images=(i1.to(dtypes[0]), i2.to(dtypes[1])))
    ref = _quiet(FreespaceRefiner(), *args, images=(i1.to(dtypes[0]), i2.to(dtypes[1]).to(dtypes[0])))
    assert bool(out.refined.all()) and out.flow.dtype == dtypes[0]
    # (image 2 in another precision, the same road motion: within a half precision image's rounding)
    torch.testing.assert_close(out.flow, ref.flow, rtol=0, atol=0.05 if torch.float16 in dtypes else 1e-4)


def test_confidence_weight_adds_the_gates_evidence(scene):
    """In confidence mode the model's weight is the Cauchy weight of the two flows' disagreement
    raised by the images' evidence for the model: w = w_c + (1 − w_c) e, with w_c = 1 / (1 + r² / c²)
    and e the gate's per-cell evidence (written out here)."""
    pred, road = scene["pred"], scene["road"][None]
    motion = {"model": "plane", **{k: v for k, v in scene["plane"].items() if k != "height"}}
    scale = 2.0
    out = _quiet(FreespaceRefiner(mode="confidence", scale=scale), pred, road, scene["camera"], motion,
                 images=(scene["image1"][None], scene["image2"][None]))
    m = out.mask[0, 0]
    evidence = out.gate.evidence[0, 0][m]
    assert m.sum() > 100 and bool(((evidence > 0.05) & (evidence < 0.95)).any())
    r2 = (pred - out.flow_model).square().sum(1)[0][m]
    w_c = 1.0 / (1.0 + r2 / scale**2)
    torch.testing.assert_close(out.weight[0, 0][m], w_c + (1.0 - w_c) * evidence, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("case", ["images", "planar odometry and images", "flow fit"])
def test_a_samples_model_flow_does_not_depend_on_the_others_estimates(scene, case):
    """A sample refined beside one that is not estimated (an empty mask) or whose estimate fails
    (a black frame) gets the model flow it gets alone: the fit's own flow, not a second evaluation
    in the prediction's dtype, which differed from it by up to 1e-4 px and so moved the gate's
    points at the border of image 2."""
    pred, road, i1, i2 = _two(scene, black_second=case == "planar odometry and images")
    if case != "planar odometry and images":
        road[1] = False
    odometry = _planar(scene, 2) if case == "planar odometry and images" else None
    images = None if case == "flow fit" else (i1, i2)
    both = _quiet(FreespaceRefiner(), pred, road, scene["camera"], odometry, images=images)
    alone = _quiet(FreespaceRefiner(), pred[:1], road[:1], scene["camera"], None if odometry is None else
                   _planar(scene, 1), images=None if images is None else (i1[:1], i2[:1]))
    assert both.refined.tolist() == [True, False] and alone.refined.tolist() == [True]
    torch.testing.assert_close(both.flow_model[:1], alone.flow_model, rtol=0, atol=1e-6)
    torch.testing.assert_close(both.flow[:1], alone.flow, rtol=0, atol=1e-6)
