"""Tests of fsof_torch.estimation.image_fit: ego-motion from the images by direct photometric fitting."""

from __future__ import annotations

import math

import pytest
import torch

from fsof_torch.geometry.camera import Camera
from fsof_torch import FitResult, fit_displacement, fit_image, fit_photometric
from fsof_torch.geometry.road_flow import displacement_flow
from fsof_torch.evaluation.warp import warp_backward

SIZE = (96, 256)


pytestmark = pytest.mark.usefixtures("one_thread")


def small_camera(dtype=torch.float64, roll=0.0, pitch=0.0) -> Camera:
    K = torch.tensor([[200.0, 0.0, 128.0], [0.0, 200.0, 24.0], [0.0, 0.0, 1.0]], dtype=dtype)
    return Camera(K, 1.65, roll, pitch)


def texture(B: int, seed: int, size=SIZE) -> torch.Tensor:
    """Smooth random texture (B, 3, H, W) on 0..255: noise blurred at two scales."""
    from kornia.filters import gaussian_blur2d

    g = torch.Generator().manual_seed(seed)
    H, W = size
    noise = torch.rand(B, 1, H + 40, W + 40, generator=g, dtype=torch.float64)
    fine = gaussian_blur2d(noise, (9, 9), (1.5, 1.5))
    coarse = gaussian_blur2d(noise, (25, 25), (6.0, 6.0))
    img = (fine - fine.mean()) * 4.0 + (coarse - coarse.mean()) * 12.0
    img = (128 + 120 * img.clamp(-1, 1))[..., 20:-20, 20:-20]
    return img.expand(B, 3, H, W).contiguous()


def synthetic_pair(cam: Camera, x_d, z_d, yaw, B: int = 1, seed: int = 0):
    """image2 a texture; image1 = image2 warped back by the model flow (exact on the road)."""
    image2 = texture(B, seed)
    flow, valid = displacement_flow(cam, x_d, z_d, yaw, SIZE)
    image1, inb = warp_backward(image2, flow)
    mask = valid & inb
    mask[:, :, :34] = False  # stay away from the horizon and its tiny flows
    return image1.float(), image2.float(), mask, flow


# -- smoke / exceptions ------------------------------------------------------------------------

def test_smoke_result_type_and_shapes():
    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.3, 0.0)
    fit = fit_photometric(image1, image2, mask, cam.to(torch.float32), max_iter=5)
    assert isinstance(fit, FitResult)
    assert fit.flow.shape == (1, 2, *SIZE) and fit.inliers.shape == (1, 1, *SIZE)
    assert fit.z_d.shape == (1,) and fit.flow.dtype == torch.float32


def test_thresholds_and_results_are_grey_levels_on_0_255_for_any_data_range():
    """With data_range=1.0 the fit rescales the images to 0..255: the same inlier_threshold and
    scale give the fit on 0..255 images (its residual and offset in grey levels on 0..255 too),
    and thresholds rescaled to 0..1 are 255 times tighter (the docstring said only "grey levels")."""
    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.1, 0.8, 0.01)
    image2 = image2 * 0.9 + 12  # (an exposure change: a nonzero offset)
    options = dict(inlier_threshold=5.0, scale=3.0)
    grey = fit_image(image1, image2, mask, cam, **options)
    unit = fit_image(image1 / 255, image2 / 255, mask, cam, data_range=1.0, **options)
    assert bool(grey.success[0]) and bool(unit.success[0])
    for a, b in ((grey.params["z_d"], unit.params["z_d"]), (grey.residual, unit.residual),
                 (grey.extras["offset"], unit.extras["offset"])):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    tight = fit_image(image1 / 255, image2 / 255, mask, cam, data_range=1.0, inlier_threshold=5.0 / 255,
                      scale=3.0 / 255)
    assert float(tight.extras["inlier_fraction"][0]) < 0.5 * float(grey.extras["inlier_fraction"][0])


def test_result_camera_is_a_copy_of_the_callers():
    """fit.camera's K, height and held roll / pitch are the fit's own tensors: an in-place edit of
    them leaves the caller's camera alone (they shared its storage where the dtype matched) and
    works on a batch-1 camera broadcast to the images' batch (an expanded view refused it)."""
    cam = small_camera(roll=0.01, pitch=-0.02).to(torch.float32)
    image1, image2, mask, _ = (x.expand(2, -1, -1, -1) for x in synthetic_pair(small_camera(), 0.0, 0.3, 0.0))
    before = [t.clone() for t in (cam.K, cam.height, cam.roll, cam.pitch)]
    fit = fit_photometric(image1, image2, mask, cam, fit_roll=False, levels=1, max_iter=2)
    assert fit.camera.K.dtype == torch.float32 and fit.camera.batch_size == 2
    fit.camera.K.mul_(0.5)
    fit.camera.height.add_(1.0)
    fit.camera.roll.zero_()
    fit.camera.pitch.zero_()
    for was, now in zip(before, (cam.K, cam.height, cam.roll, cam.pitch)):
        assert torch.equal(was, now)


def test_exceptions():
    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.3, 0.0)
    with pytest.raises(ValueError, match="image2: expected shape"):
        fit_photometric(image1, image2[..., :100], mask, cam)
    with pytest.raises(ValueError, match="expected 1 \\(grey\\) or 3 \\(RGB\\) channels"):
        fit_photometric(image1[:, :2], image2[:, :2], mask, cam)
    with pytest.raises(TypeError, match="mask: expected a bool tensor"):
        fit_photometric(image1, image2, mask.float(), cam)
    bad = image1.clone()
    bad[0, 0, 50, 50] = float("nan")
    with pytest.raises(ValueError, match="image1: expected finite pixel values"):
        fit_photometric(bad, image2, mask, cam)
    with pytest.raises(ValueError, match="robust: expected one of"):
        fit_photometric(image1, image2, mask, cam, robust="nope")


OPTION_ERRORS = [
    # once accepted silently, or failing far from the option (ZeroDivisionError, math domain error,
    # OpenCV's assertion, 'int' object is not iterable)
    (dict(inlier_threshold=float("nan")), ValueError, "inlier_threshold: expected a finite number > 0, got nan"),
    (dict(inlier_threshold=None), TypeError, r"^inlier_threshold: expected a finite number > 0 \(grey levels\), got None$"),
    (dict(min_points=-5), ValueError, "min_points: expected an int >= 1, got -5"),
    (dict(init="zero"), TypeError, "init: expected a RoadFit or a dict of .* got str 'zero'"),
    (dict(min_size=0), ValueError, "min_size: expected an int >= 2, got 0"),
    (dict(resolution=-1.0), ValueError, "resolution: expected a number >= 0, got -1.0"),
    (dict(smooth_sigma=float("nan")), ValueError, "smooth_sigma: expected a finite number, got nan"),
    (dict(highpass=-1.0), ValueError, "highpass: expected a number >= 0, got -1.0"),
    (dict(band_levels=1.5), TypeError, "band_levels: expected an int, got float 1.5"),
    (dict(gradient_fraction="x"), TypeError, "gradient_fraction: expected a number, got str 'x'"),
    (dict(fine_points=0), ValueError, "fine_points: expected an int >= 1, got 0"),
    (dict(fine_points=2.5), TypeError, "fine_points: expected None or an int, got float 2.5"),
    (dict(affine="x"), TypeError, "affine: expected True or False, got str 'x'"),
    (dict(starts=5), TypeError, "starts: expected a list of starts"),
    (dict(starts=["x"]), TypeError, "starts: expected dicts of parameters or fits, got an element str 'x'"),
    (dict(prior="loose"), ValueError, "prior: expected 'calibration', None or {name: \\(mean, sigma\\)}, got 'loose'"),
    (dict(prior=5), TypeError, "prior: expected None or a dict with string keys, got int 5"),
    (dict(bounds="wide"), TypeError, "bounds: expected 'physical', None or \\(lower, upper\\) tensors of shape \\(1, 8\\)"),
    (dict(bounds=(torch.zeros(1, 5), torch.ones(1, 5))), ValueError, r"bounds \(lower\): expected shape \(1, 8\)"),
    (dict(check_every=0), ValueError, "check_every: expected an int >= 1, got 0"),
    (dict(fixed=3), TypeError, "fixed: expected None, a name or a sequence of names, got int 3"),
    (dict(forward_starts=2.0), TypeError, "forward_starts: expected a list or tuple of numbers .* got float 2.0"),
    (dict(forward_starts=[1.0, float("nan")]), ValueError, "forward_starts: expected a finite number, got nan"),
    (dict(forward_starts=["fast"]), TypeError, "forward_starts: expected a number, got str 'fast'"),
    (dict(min_correlation=1.5), ValueError, r"min_correlation: expected a number in \[-1, 1\], got 1.5"),
    (dict(min_correlation="high"), TypeError, "min_correlation: expected a number, got str 'high'"),
    (dict(retry_starts=-1), ValueError, "retry_starts: expected an int >= 0, got -1"),
    (dict(masked_band=1), TypeError, "masked_band: expected True or False, got int 1"),
    # a prior's mean and sigma: numbers, of batch 1 or B (a raw torch error before; of one frame the
    # message said "batch 1 or 1")
    (dict(prior={"roll": ("a", 0.1)}), TypeError, r"prior\['roll'\]: expected numbers or tensors \(mean, sigma\)"),
    (dict(prior={"roll": (torch.zeros(3), 0.1)}), ValueError,
     r"prior\['roll'\]: expected a mean and a sigma of batch 1, got 3 and 1 values$"),
    (dict(prior={"roll": (0.0, 0.1), "pitch": (0.0, 0.0)}), ValueError,
     r"prior\['pitch'\]: expected a finite mean and sigma > 0, got \(0.0, 0.0\)"),
    # a prior on a held parameter was silently ignored (fit_road refuses it too)
    (dict(fixed=("roll",), prior={"roll": (0.0, 0.1)}), ValueError, r"^prior: 'roll' is held at its start"),
]


@pytest.mark.parametrize("options, error, message", OPTION_ERRORS + [
    # (checked against the images' size: at 96 x 256 the 9th level is 1 x 1 pixel; 10**20 levels
    # were built until memory ran out)
    (dict(levels=10**20), ValueError, r"^levels: expected at most 9 for 96x256 images"),
])
def test_exceptions_fit_image_options_named_and_quoted(options, error, message):
    from fsof_torch import fit_image

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.3, 0.0)
    with pytest.raises(error, match=message):
        fit_image(image1, image2, mask, cam, **options)


@pytest.mark.parametrize("options, error, message", [case for case in OPTION_ERRORS if not any(
    word in case[2] for word in ("bounds", "of batch"))])
def test_check_image_fit_options_raises_what_fit_image_raises(options, error, message):
    """The options alone, checked as fit_image checks them (what ImageMotionEstimator and
    fit_sequence do when given options): the same error, before any image is seen, also for a
    prior's names and values and a prior on a held parameter. The checks that need the batch (the
    bounds' shape, a prior's batch) come with the images."""
    from fsof_torch.estimation.image_fit import check_image_fit_options

    with pytest.raises(error, match=message):
        check_image_fit_options(options)


def test_check_image_fit_options_names_and_bounds_of_any_batch():
    from fsof_torch.estimation.image_fit import check_image_fit_options

    check_image_fit_options({"fine_points": 20000, "smooth_sigma": 1.0, "bounds": (torch.zeros(3, 8), torch.ones(3, 8))})
    with pytest.raises(TypeError, match=r"^opts: unknown options \['bogus'\] of fit_image"):
        check_image_fit_options({"bogus": 1}, "opts")
    with pytest.raises(TypeError, match=r"^opts: options \['camera'\] of fit_image are set by"):
        check_image_fit_options({"camera": None}, "opts")
    with pytest.raises(TypeError, match=r"^opts: options \['prior'\] of fit_image are set by"):
        check_image_fit_options({"prior": None}, "opts", reserved=("prior",))
    with pytest.raises(ValueError, match=r"bounds \(lower\): expected shape \(B, 8\)"):
        check_image_fit_options({"bounds": (torch.zeros(2, 5), torch.ones(2, 5))})
    with pytest.raises(ValueError, match=r"bounds: expected lower and upper of one shape"):
        check_image_fit_options({"bounds": (torch.zeros(2, 8), torch.ones(3, 8))})
    with pytest.raises(ValueError, match=r"bounds: expected lower <= upper"):
        check_image_fit_options({"bounds": (torch.ones(1, 8), torch.zeros(1, 8))})
    with pytest.raises(ValueError, match=r"^model: the image fit estimates a motion between two frames"):
        check_image_fit_options({"model": "velocity"})


def test_bounds_of_infinite_lower_or_negative_infinite_upper_are_named():
    """A lower bound of +inf (or an upper one of -inf) passed the checks and reached the solver,
    whose ValueError named its own "lower" / "upper" and quoted the gain's and offset's columns
    too; now the options' check names ``bounds`` and the parameter, also where an estimator is made.
    Bounds on the meta device are named too."""
    from fsof_torch import ImageMotionEstimator
    from fsof_torch.estimation.image_fit import check_image_fit_options

    lo, hi = torch.full((1, 8), -math.inf), torch.full((1, 8), math.inf)
    z = 5  # the plane model's z_d
    bad_lo = lo.clone()
    bad_lo[0, z] = math.inf
    bad_hi = hi.clone()
    bad_hi[0, z] = -math.inf
    with pytest.raises(ValueError, match=r"^bounds \(lower\): expected values below \+inf .* got inf for \['z_d'\]"):
        check_image_fit_options({"bounds": (bad_lo, hi)})
    with pytest.raises(ValueError, match=r"^bounds \(upper\): expected values above -inf .* got -inf for \['z_d'\]"):
        ImageMotionEstimator(bounds=(lo, bad_hi))
    check_image_fit_options({"bounds": (lo, hi)})  # (±inf on their own sides: no bounds)
    # bounds on the meta device (shapes, no values): torch's RuntimeError "Tensor.item() cannot be
    # called on meta tensors" from the check of lower <= upper
    for meta in ((lo.to("meta"), hi), (lo, hi.to("meta"))):
        with pytest.raises(ValueError, match=r"^bounds \((lower|upper)\): a tensor on the meta device has shapes but no "
                                             r"values to bound a fit"):
            check_image_fit_options({"bounds": meta})

def test_the_calibration_prior_leaves_held_parameters_out():
    """The calibration prior of the paper model (pitch held) and of a plane with its roll held: the
    held parameters' priors had no effect; now they are not given (and given ones are refused), and
    the fit is the same."""
    from fsof_torch import fit_image

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.3, 0.0)
    fit = fit_image(image1, image2, mask, cam, model="paper")
    assert bool(fit.success)
    held = fit_image(image1, image2, mask, cam, fixed=("roll",))
    assert bool(held.success) and float(held.params["roll"]) == float(cam.roll)


def test_priors_are_judged_in_one_host_read(monkeypatch):
    """Each prior entry's mean and sigma were read back on their own: ten host reads a fit for the
    calibration prior of the plane model, whose values come from the checked camera."""
    from fsof_torch.estimation.priors import calibration_prior, prior_arrays as _prior
    from fsof_torch.geometry.road_models import get_road_model

    plane = get_road_model("plane")
    spec = calibration_prior(plane, small_camera())
    reads = []
    for name in ("__bool__", "item", "tolist"):
        original = getattr(torch.Tensor, name)
        monkeypatch.setattr(torch.Tensor, name, lambda t, *a, _f=original, **k: reads.append(1) or _f(t, *a, **k))
    mean, inverse_variance = _prior(plane, spec, 1, torch.device("cpu"))
    monkeypatch.undo()
    assert len(reads) == 1
    assert (inverse_variance[0] > 0).tolist() == [n in spec for n in plane.params] + [False, False]


def test_success_does_not_ask_convergence_and_the_docs_say_so():
    """An image fit that ran out of iterations still succeeds where the image tests pass; the
    docs said \"converged\" (RoadFit.success) and fit_image's Returns did not list ``converged``."""
    from fsof_torch import fit_image
    from fsof_torch.estimation.flow_fit import RoadFit

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.3, 0.0)
    fit = fit_image(image1, image2, mask, cam, model="paper", max_iter=1, levels=1, forward_starts=(), turn_starts=(),
                    retry_starts=0, retry_without_prior=False)
    assert bool(fit.success[0]) and not bool(fit.extras["converged"][0])
    assert "``converged`` (B,) bool" in fit_image.__doc__.split("Returns:")[1]
    assert "Image fits: finite, well posed" in " ".join(RoadFit.__doc__.split())


def test_exceptions_fit_photometric_flags_and_meta_device():
    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.3, 0.0)
    with pytest.raises(TypeError, match="fit_roll: expected True or False, got str 'x'"):
        fit_photometric(image1, image2, mask, cam, fit_roll="x")
    with pytest.raises(TypeError, match="model: fit_photometric sets the model"):
        fit_photometric(image1, image2, mask, cam, model="plane")
    with pytest.raises(ValueError, match="image1: a tensor on the meta device has shapes but no values to fit"):
        fit_photometric(image1.to("meta"), image2.to("meta"), mask.to("meta"), cam)


def test_exceptions_empty_mask_is_flagged():
    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.3, 0.0)
    fit = fit_photometric(image1, image2, torch.zeros_like(mask), cam, max_iter=3)
    assert not bool(fit.success)
    for name in ("x_d", "z_d", "yaw", "roll", "pitch", "residual"):
        assert bool(torch.isfinite(getattr(fit, name)).all()), name


# -- feature -----------------------------------------------------------------------------------

@pytest.mark.parametrize("B", [1, 2])
def test_feature_recovers_motion_from_zero_start(B):
    cam = small_camera()
    z_d = torch.tensor([0.8, 0.5][:B], dtype=torch.float64)
    x_d = torch.tensor([0.03, -0.02][:B], dtype=torch.float64)
    yaw = torch.tensor([0.01, -0.015][:B], dtype=torch.float64)
    image1, image2, mask, flow = synthetic_pair(cam, x_d, z_d, yaw, B=B)
    # a brightness change between the frames, absorbed by the gain and offset
    image2 = image2 * 0.95 + 4.0
    fit = fit_photometric(image1, image2, mask, cam.to(torch.float32), fit_roll=False)
    assert fit.success.all()
    epe = (fit.flow.double() - flow).norm(dim=1)[mask[:, 0]].mean()
    assert float(epe) < 0.05
    torch.testing.assert_close(fit.z_d.double(), z_d, atol=5e-3, rtol=0.0)


def _box_blur(image: torch.Tensor, k: int = 3) -> torch.Tensor:
    """A k × k box blur of (B, C, H, W) images, borders replicated (written here, not the library's)."""
    import torch.nn.functional as F

    B, C, H, W = image.shape
    padded = F.pad(image.reshape(B * C, 1, H, W), (k // 2,) * 4, mode="replicate")
    return F.avg_pool2d(padded, k, stride=1).reshape(B, C, H, W)


def test_feature_image2_blurred_still_succeeds():
    """Image 2 a little blurred (3 × 3 box): its band of detail loses amplitude, which the fit's
    gain absorbs; the inlier test compares the plain intensities with their own gain, so the
    fit still succeeds (the fit's band gain applied to the intensities failed every frame)."""
    from fsof_torch import fit_image

    cam = small_camera()
    image1, image2, mask, flow = synthetic_pair(cam, 0.02, 0.6, 0.01)
    fit = fit_image(image1, _box_blur(image2), mask, cam, model="paper")
    assert float(fit.extras["gain"]) > 1.05  # the band's amplitude: image 2's detail is weaker
    assert bool(fit.success)
    assert float(fit.extras["inlier_fraction"]) > 0.9 and float(fit.extras["correlation"]) > 0.8
    assert float((fit.flow.double() - flow).norm(dim=1)[mask[:, 0]].mean()) < 0.2


def test_feature_a_wrong_motion_fails_on_correlation():
    """Held at a wrong motion (every parameter fixed), the plain intensities of a smooth road
    still match within the inlier threshold almost everywhere, but the images' detail does not
    line up: the correlation test fails the frame. Held at the true motion, it succeeds."""
    from fsof_torch import fit_image

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.6, 0.0)
    names = ("x_d", "z_d", "yaw", "roll", "pitch")
    right = fit_image(image1, image2, mask, cam, model="paper", fixed=names, init={"z_d": 0.6})
    wrong = fit_image(image1, image2, mask, cam, model="paper", fixed=names, init={"z_d": 0.3})
    assert bool(right.success) and float(right.extras["correlation"]) > 0.85
    assert not bool(wrong.success) and float(wrong.extras["correlation"]) < 0.5
    assert float(wrong.extras["inlier_fraction"]) >= 0.25  # what the intensities alone would pass
    relaxed = fit_image(image1, image2, mask, cam, model="paper", fixed=names, init={"z_d": 0.3},
                        min_correlation=-1.0)
    assert bool(relaxed.success)


def test_feature_confidence_per_frame_of_a_batch():
    """A batch of two frames, one held at the true motion and one at a wrong one: each frame's
    correlation and inlier share are its own (those of the frame fitted alone)."""
    from fsof_torch import fit_image

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.6, 0.0)
    names = ("x_d", "z_d", "yaw", "roll", "pitch")
    z = torch.tensor([0.6, 0.3], dtype=torch.float64)
    batch = fit_image(image1.expand(2, -1, -1, -1), image2.expand(2, -1, -1, -1), mask.expand(2, -1, -1, -1),
                      cam, model="paper", fixed=names, init={"z_d": z})
    assert batch.success.tolist() == [True, False]
    for b in range(2):
        alone = fit_image(image1, image2, mask, cam, model="paper", fixed=names, init={"z_d": float(z[b])})
        for key in ("correlation", "inlier_fraction"):
            torch.testing.assert_close(batch.extras[key][b:b + 1], alone.extras[key], rtol=1e-9, atol=1e-12)


def test_feature_runners_up_per_frame_of_a_batch():
    """Where the winning start's fit fails (here every fit: the bar is out of reach), the
    runner-up start is carried down too and each frame keeps the fit whose images correlate
    best: a batch of two different pairs gives each pair's fit alone."""
    from fsof_torch import fit_image

    cam = small_camera()
    first = synthetic_pair(cam, 0.02, 0.6, 0.01, seed=0)
    second = synthetic_pair(cam, -0.03, 0.4, -0.01, seed=1)
    options = dict(model="paper", min_correlation=0.9999, starts=[{"z_d": 0.9}], forward_starts=())
    batch = fit_image(*(torch.cat([a, b]) for a, b in zip(first[:3], second[:3])), cam, **options)
    for b, pair in enumerate((first, second)):
        alone = fit_image(*pair[:3], cam, **options)
        assert not bool(alone.success)
        for name in ("x_d", "z_d", "yaw", "roll"):
            torch.testing.assert_close(batch.params[name][b:b + 1], alone.params[name], rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(batch.extras["correlation"][b:b + 1], alone.extras["correlation"], rtol=1e-6, atol=1e-9)
        assert int(batch.iterations[b]) == int(alone.iterations[0])


def test_feature_fixed_parameters_stay_at_init_in_every_start_and_beyond_the_bounds():
    """A start's value of a fixed parameter gives way to init's (the default's where init has
    none), and the bounds clamp only the free parameters: every parameter held at a motion
    beyond the physical bounds (z_d over 20 heights, pitch 17° off the calibration) stays there."""
    from fsof_torch import fit_image

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.02, 0.6, 0.01)
    # init turned far off (it loses), the start at the motion but at another attitude (it wins)
    options = dict(forward_starts=(), turn_starts=())
    paper = fit_image(image1, image2, mask, cam, model="paper", init={"pitch": 0.01, "yaw": 0.4},
                      starts=[{"z_d": 0.6, "yaw": 0.01, "pitch": 0.05}], **options)
    assert float(paper.params["pitch"]) == 0.01
    assert bool(paper.success) and abs(float(paper.params["yaw"]) - 0.01) < 1e-3
    plane = fit_image(image1, image2, mask, cam, fixed=("roll", "pitch"), init={"yaw": 0.4},
                      starts=[{"z_d": 0.6, "yaw": 0.01, "roll": 0.04, "pitch": 0.05}], **options)
    assert float(plane.params["roll"]) == 0.0 and float(plane.params["pitch"]) == 0.0
    assert bool(plane.success) and abs(float(plane.params["z_d"]) - 0.6) < 0.01
    names = ("x_d", "z_d", "yaw", "roll", "pitch")
    held = fit_image(image1, image2, mask, cam, model="paper", fixed=names, init={"z_d": 40.0, "pitch": -0.3})
    assert float(held.params["z_d"]) == 40.0 and float(held.params["pitch"]) == -0.3
    assert not bool(held.success)


def test_feature_bounds_of_batch_1_hold_every_frame():
    """Bounds of batch 1 (what ``physical_bounds`` gives for a camera of batch 1) hold every frame
    of a batch, as a prior of one value does (they were a ValueError asking for (2, 8)): a bound on
    z_d below the true 0.3 m holds both frames at it, as the same bounds given per frame do."""
    from fsof_torch import fit_image
    from fsof_torch.estimation.image_fit import physical_bounds
    from fsof_torch.geometry.road_models import get_road_model

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.3, 0.0)
    image1, image2, mask = (t.expand(2, -1, -1, -1) for t in (image1, image2, mask))
    model = get_road_model("plane")
    lo, hi = physical_bounds(model, cam)
    assert lo.shape == (1, 8)
    hi = hi.clone()
    hi[0, model.params.index("z_d")] = 0.2
    fit = fit_image(image1, image2, mask, cam, bounds=(lo, hi))
    assert fit.params["z_d"].tolist() == [0.2, 0.2]
    per_frame = fit_image(image1, image2, mask, cam, bounds=(lo.expand(2, -1), hi.expand(2, -1)))
    for name in model.params:
        assert torch.equal(fit.params[name], per_frame.params[name]), name
    with pytest.raises(ValueError, match=r"^bounds \(lower\): expected shape \(1 or 2, 8\)"):
        fit_image(image1, image2, mask, cam, bounds=(lo.expand(3, -1), hi.expand(3, -1)))


def test_a_fit_held_by_a_bound_fails():
    """The solver clamps the parameters into the bounds, so a motion beyond one ended on it and
    was reported a success: a bound on z_d at 0.2 m or 0.29 m (true: 0.3 m) gave z_d exactly at it
    with success True. Now a free parameter within its standard deviation of a bound fails the fit;
    a bound the fit stays clear of changes nothing."""
    from fsof_torch.estimation.priors import clear_of_bounds, physical_bounds
    from fsof_torch.geometry.road_models import get_road_model

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.3, 0.0)
    model = get_road_model("plane")
    lo, hi = physical_bounds(model, cam)
    z = model.params.index("z_d")
    free = fit_image(image1, image2, mask, cam)
    assert bool(free.success) and abs(float(free.z_d) - 0.3) < 0.005
    for bound in (0.2, 0.29):
        held = hi.clone()
        held[0, z] = bound
        fit = fit_image(image1, image2, mask, cam, bounds=(lo, held))
        assert float(fit.z_d) == pytest.approx(bound, abs=1e-9) and not bool(fit.success), bound
    clear = hi.clone()
    clear[0, z] = 0.4
    fit = fit_image(image1, image2, mask, cam, bounds=(lo, clear))
    assert bool(fit.success) and float(fit.z_d) == float(free.z_d)
    # the test itself, against the values: a parameter clear by more than its sd, by less, or beyond
    params = torch.tensor([[0.0, 1.0], [0.0, 1.95], [0.0, 2.5]], dtype=torch.float64)
    cov = torch.diag_embed(torch.tensor([[1.0, 0.01], [1.0, 0.01], [1.0, 0.01]], dtype=torch.float64))
    lower = torch.tensor([[-math.inf, 0.5]], dtype=torch.float64)
    upper = torch.tensor([[math.inf, 2.0]], dtype=torch.float64)
    assert clear_of_bounds(params, cov, lower, upper).tolist() == [True, False, False]
    assert clear_of_bounds(params, cov, None, None).tolist() == [True, True, True]


@pytest.mark.parametrize("masked_band", [False, True])
def test_feature_all_road_pixels_a_frames_fit_is_its_own(masked_band):
    """With max_points=None (every road pixel a candidate) a frame's fit is the same alone as
    next to a frame with a larger road; with the band inside the mask too (each frame's band
    inside its own mask)."""
    from fsof_torch import fit_image

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.02, 0.6, 0.01)
    small = mask.clone()
    small[..., :, :128] = False
    options = dict(model="paper", max_points=None, forward_starts=(), turn_starts=(), masked_band=masked_band)
    alone = fit_image(image1, image2, small, cam, **options)
    both = fit_image(image1.expand(2, -1, -1, -1), image2.expand(2, -1, -1, -1), torch.cat([mask, small]), cam,
                     **options)
    for name in ("x_d", "z_d", "yaw", "roll"):
        torch.testing.assert_close(both.params[name][1:], alone.params[name], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("preset, index", [("default", 0), ("body-motion", 0), ("crest", 10)])
def test_feature_identical_frames_of_a_batch_get_identical_fits(preset, index):
    """Copies of one pair in a batch: the zero-motion start maps the road's bottom row onto the
    image's last row to within rounding, which batched products round differently per frame;
    with an exact in-bounds test some copies kept those points and others not, and their fits
    ended up to 5 px apart (188 x 621 frames)."""
    from fsof_torch import fit_image
    from fsof_torch.data.scene import render_pair

    p = render_pair(preset, index, size=(188, 621))
    I1, I2, M = (p[k][None].expand(4, *p[k].shape).contiguous() for k in ("image1", "image2", "road"))
    fit = fit_image(I1, I2, M, p["camera"])
    assert bool(fit.success.all())
    torch.testing.assert_close(fit.flow, fit.flow[:1].expand_as(fit.flow), rtol=0, atol=1e-6, equal_nan=True)
    for name, value in fit.params.items():
        torch.testing.assert_close(value, value[:1].expand_as(value), rtol=0, atol=1e-9)


def test_feature_init_from_flow_fit_is_used():
    cam = small_camera()
    image1, image2, mask, flow = synthetic_pair(cam, 0.02, 0.7, 0.01)
    start = fit_displacement(flow, mask, cam)
    fit = fit_photometric(image1, image2, mask, cam, init=start, levels=1, fit_roll=False)
    cold = fit_photometric(image1, image2, mask, cam, levels=1, fit_roll=False)
    assert bool(fit.success) and int(fit.iterations) < int(cold.iterations)  # (5 against 15)
    assert abs(float(fit.z_d) - 0.7) < 5e-3
    # one step from each start: from the flow fit's it is there, from zero motion far off
    one = {"levels": 1, "fit_roll": False, "max_iter": 1}
    assert abs(float(fit_photometric(image1, image2, mask, cam, init=start, **one).z_d) - 0.7) < 5e-3
    assert abs(float(fit_photometric(image1, image2, mask, cam, **one).z_d) - 0.7) > 0.3


def test_early_stop_checks_change_no_result_and_read_the_host_at_most_once_per_iteration():
    """Converged samples stop moving, so the checks only decide when a level's loop ends: the
    fit with the default checks equals the fixed budgets (``check_every=None``), parameters and
    iteration counts alike, and reads the host at most once per iteration more."""
    from torch.profiler import ProfilerActivity, profile

    from fsof_torch.estimation.image_fit import fit_image

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, torch.tensor([0.02, -0.01]), torch.tensor([0.7, 0.5]),
                                             torch.tensor([0.01, 0.0]), B=2)
    fits, reads = {}, {}
    for checks in ("default", None):
        options = {} if checks == "default" else {"check_every": checks}
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            fits[checks] = fit_image(image1, image2, mask, cam, max_iter=8, **options)
        reads[checks] = sum(e.name == "aten::_local_scalar_dense" for e in prof.events())
    checked, fixed = fits["default"], fits[None]
    for name in checked.params:
        assert torch.equal(checked.params[name], fixed.params[name]), name
    assert torch.equal(checked.iterations, fixed.iterations)
    assert bool(checked.success.all())
    assert int(checked.iterations.max()) < 8 * 3  # some of the 3 levels (96, 48, 24 rows) stopped early
    assert 0 < reads["default"] - reads[None] <= int(checked.iterations.max()), reads


# -- real data ---------------------------------------------------------------------------------

def _kitti(shared_data, kitti15_ground_truth):
    """The KITTI pair's ground truth (the conftest fixture) with its RGB images and their greys."""
    import cv2
    import numpy as np

    from fsof_torch.io import read_image

    cam, gt, valid, road = kitti15_ground_truth
    folder = shared_data / "kitti15_000000"
    rgb = [read_image(folder / f"image_1{i}.png")[None] for i in (0, 1)]
    grey = [cv2.cvtColor(im[0].permute(1, 2, 0).numpy().astype(np.uint8), cv2.COLOR_RGB2GRAY) for im in rgb]
    return cam, gt, valid, road, rgb, grey


def test_real_kitti_dis_then_photometric(shared_data, kitti15_ground_truth):
    """No ground truth used: DIS flow, a flow fit, then the photometric fit; EPE vs GT ≤ 1 px."""
    import cv2
    cam, gt, valid, road, (image1, image2), (g1, g2) = _kitti(shared_data, kitti15_ground_truth)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(g1, g2, None)
    flow_dis = torch.from_numpy(dis).permute(2, 0, 1)[None].double()
    use = (road & valid)[:, 0]
    e_dis = float((flow_dis - gt).norm(dim=1)[use].mean())
    start = fit_displacement(flow_dis, road, cam, fit_roll=False)
    assert not bool(start.success)  # too few inliers: DIS is wrong on most of the road
    fit = fit_photometric(image1, image2, road, cam, init=start)
    e_fit = float((fit.flow.double() - gt).norm(dim=1)[use].mean())
    assert bool(fit.success)
    assert e_fit <= 1.0, (e_dis, e_fit)
    assert e_dis > 5.0  # DIS itself is far off on this road (about 14 px)


def test_calibration_prior_and_physical_bounds_check_their_arguments():
    from fsof_torch.estimation.image_fit import calibration_prior, physical_bounds

    cam = small_camera()
    with pytest.raises(ValueError, match=r"^mounting_deg: expected a positive number \(> 0\), got -1.0"):
        calibration_prior("plane", cam, mounting_deg=-1.0)
    with pytest.raises(TypeError, match=r"^vertical_m: expected a number, got str 'a'"):
        calibration_prior("plane", cam, vertical_m="a")
    for fn in (calibration_prior, physical_bounds):
        with pytest.raises(TypeError, match=r"^camera: expected a fsof_torch.Camera, got NoneType"):
            fn("plane", None)
    # the prior's means are copies: editing one leaves the camera as it was
    prior = calibration_prior("plane", cam)
    roll = cam.roll.clone()
    prior["roll"][0].add_(1.0)
    assert torch.equal(cam.roll, roll) and prior["roll"][0].data_ptr() != cam.roll.data_ptr()


def test_a_band_of_one_or_two_rows_is_no_success():
    """Inliers on fewer than 3 rows (or columns) fail the image fit, as they fail fit_road: on a
    band of one or two rows of the default scene's road, the motion lands backwards (z_d < 0 for
    a true 1.2 m) with its detail correlating above the bar (was: a success)."""
    from fsof_torch import fit_image, render_pair

    p = render_pair("default", 0, size=(94, 310))
    im1, im2, road, cam = p["image1"][None], p["image2"][None], p["road"][None], p["camera"]
    rows = torch.arange(94).reshape(1, 1, -1, 1)
    for last in (80, 81):
        fit = fit_image(im1, im2, road & (rows >= 80) & (rows <= last), cam)
        assert int(fit.inliers[0, 0].any(1).sum()) == last - 79 and int(fit.inliers.sum()) >= 100
        assert float(fit.extras["correlation"][0]) > 0.5 and float(fit.params["z_d"][0]) < 0
        assert not bool(fit.success[0])
    whole = fit_image(im1, im2, road, cam)
    assert bool(whole.success[0]) and abs(float(whole.params["z_d"][0]) - p["odometry"]["z_d"]) < 0.15


def test_fine_points_take_the_finest_levels_points_evenly_spread(monkeypatch):
    """``fine_points``: the finest level's problems are built from that many evenly spread road
    pixels (``gradient_fraction`` 1), every coarser level's as before; None builds every level
    alike, and the fit is then the default's bit for bit."""
    from fsof_torch import fit_image
    from fsof_torch.estimation import image_fit

    cam = small_camera()
    image1, image2, mask, _ = synthetic_pair(cam, 0.0, 0.3, 0.0)
    built = []
    level_problem = image_fit.level_problem

    def spy(model, camera, img, m, fraction, max_points, *rest):
        built.append((img.shape[-2:] == image1.shape[-2:], fraction, max_points))
        return level_problem(model, camera, img, m, fraction, max_points, *rest)

    monkeypatch.setattr(image_fit, "level_problem", spy)
    plain = fit_image(image1, image2, mask, cam, max_points=500)
    assert built and {b[1:] for b in built} == {(0.5, 500)}
    built.clear()
    fine = fit_image(image1, image2, mask, cam, max_points=500, fine_points=2000)
    assert {b[1:] for b in built if b[0]} == {(1.0, 2000)} and {b[1:] for b in built if not b[0]} == {(0.5, 500)}
    assert plain.success.all() and fine.success.all()
    same = fit_image(image1, image2, mask, cam, max_points=500, fine_points=None)
    assert all(torch.equal(same.params[k], plain.params[k]) for k in plain.params)


def test_masked_band_takes_each_levels_mask(monkeypatch):
    """``masked_band=True``: every band level's images are filtered inside that level's road mask
    (the mask pyramid's level, of the images' size), the coarser levels not at all; by default no
    mask enters. Either way the fit succeeds on a pair whose left side, outside the mask, is a
    static wall the same in both frames."""
    from fsof_torch import fit_image
    from fsof_torch.estimation import image_fit
    from fsof_torch.estimation.pyramid import mask_pyramid

    cam = small_camera()
    image1, image2, mask, flow = synthetic_pair(cam, 0.02, 0.3, 0.0)
    wall = torch.zeros_like(mask)
    wall[..., :70] = True
    stripes = torch.rand(1, 1, *SIZE, generator=torch.Generator().manual_seed(5)).expand_as(image1) * 255
    image1, image2 = (torch.where(wall, stripes, im) for im in (image1, image2))
    road = mask & ~wall
    levels = mask_pyramid(road, 2)
    calls = []
    band = image_fit.band

    def spy(img, sigma, m=None):
        calls.append((tuple(img.shape[-2:]), sigma, None if m is None else m.clone()))
        return band(img, sigma, m)

    monkeypatch.setattr(image_fit, "band", spy)
    for masked in (False, True):
        calls.clear()
        fit = fit_image(image1, image2, road, cam, masked_band=masked)
        assert bool(fit.success[0])
        assert float((fit.flow - flow).norm(dim=1)[road[:, 0]].mean()) < 0.05
        banded = {shape: m for shape, sigma, m in calls if sigma}
        assert sorted(banded) == [(48, 128), (96, 256)]  # (the two finest levels, once each)
        for level, shape in enumerate([(96, 256), (48, 128)]):
            assert torch.equal(banded[shape], levels[level]) if masked else banded[shape] is None


def test_masked_band_leaves_the_kerbs_pull_out_of_the_pitch():
    """docs/image-fit.md, "Where the cost's minimum lies": on rendered frames the kerb and the
    pavement, 12 cm above the road, enter the band of the road beside them and pull the fitted
    pitch. Started at the true motion and solved at full resolution with every road pixel, the
    fit's pitch ends several times nearer the truth with the band taken inside the road mask
    (body-motion pair 3 at half size: 0.36° off without it, 0.05° with it)."""
    import math

    from fsof_torch import fit_image, render_pair
    from fsof_torch.geometry.road_models import get_road_model

    p = render_pair("body-motion", 3, size=(188, 621))
    camera = p["camera"].to(torch.float64).replace(height=p["plane"]["height"])
    truth = {n: p["plane"][n] for n in get_road_model("plane").params}
    off = {}
    for masked in (False, True):
        fit = fit_image(p["image1"][None].double(), p["image2"][None].double(), p["road"][None], camera, init=truth,
                        levels=1, prior=None, bounds=None, forward_starts=(), turn_starts=(), reverse_starts=(),
                        retry_starts=0, retry_without_prior=False, max_points=None, gradient_fraction=1.0,
                        masked_band=masked)
        off[masked] = abs(math.degrees(float(fit.params["pitch"][0]) - truth["pitch"]))
    assert off[True] < 0.1 and off[True] < off[False] / 3, off
