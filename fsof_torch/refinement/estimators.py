"""Road-motion estimators: the components a refiner asks for the road's motion between two frames.

Each is called as ``estimator(flow, mask, camera, *, images=None, odometry=None, starts=())`` and
returns a detached :class:`~fsof_torch.estimation.flow_fit.RoadFit` (its ``success`` says whether
to trust it):

- :class:`FlowMotionEstimator` fits a road model to the network's own flow inside the mask (the
  paper's approach; it inherits the flow's failures on weak road texture); given planar odometry,
  that is held fixed and the flow estimates the rest;
- :class:`ImageMotionEstimator` fits it to the two images directly
  (:func:`~fsof_torch.estimation.image_fit.fit_image`), the network's flow being one start among
  several; given the vehicle's planar odometry, that is held fixed (or, with ``odometry_sigma``,
  a prior) and the images estimate what odometry does not measure (the body's pitch and roll
  changes, its vertical motion, the camera's attitude over the road).
"""

from __future__ import annotations

import copy
import dataclasses
import inspect
from typing import Any, Mapping, Sequence

import torch
from torch import Tensor

from .._check import (all_finite, as_batch_param, batch_choices, check_batch, check_bool, check_float_tensor,
                      check_has_values, check_image_pair, check_keywords, check_mapping, check_mask, check_names,
                      check_number, check_same_device, check_shape, inference, skip_values)
from ..estimation.flow_fit import RoadFit, check_road_fit_options, fit_road, fixed_parameters
from ..estimation.image_fit import calibration_prior, check_image_fit_options, fit_image
from ..estimation.initial import planar_start
from ..estimation.sampling import reused_mask_pixels
from ..estimation.starts import planar_homography
from ..geometry.camera import Camera
from ..geometry.egomotion import check_motion_step
from ..geometry.road_models import get_road_model, road_motion
from ..warn import warn_user

__all__ = ["FlowMotionEstimator", "ImageMotionEstimator", "check_estimate", "check_estimator", "finite_estimate",
           "given_success", "planar_odometry", "planar_start", "unestimated_motion"]

_PLANAR = ("x_d", "z_d", "yaw")
_MOUNTING = ("roll", "pitch")  # (FlowMotionEstimator's default ``fixed``, this very object)
_FIT_ROAD_DEFAULTS = {n: p.default for n, p in inspect.signature(fit_road).parameters.items()
                      if p.default is not inspect.Parameter.empty}


def planar_odometry(odometry: object) -> dict[str, Any] | None:
    """The planar part (x_d, z_d, yaw) of an odometry in any form
    :func:`~fsof_torch.geometry.road_models.road_motion` takes, or None where it has none
    (a general homography)."""
    model, params = road_motion(odometry)
    if not all(k in model.params for k in _PLANAR):
        return None
    return {k: params.get(k, 0.0) for k in _PLANAR}


def _held(value: Any) -> Tensor:
    """``value`` as a tensor: a tensor where it is, anything else (bools, floats) on the CPU,
    whatever the default device (torch.as_tensor would move a tensor to that)."""
    return value if isinstance(value, Tensor) else torch.as_tensor(value, device="cpu")


def given_success(odometry: object, batch: int, device: torch.device | str) -> Tensor:
    """(batch,) bool: per sample, whether a given motion may be used. A fit result given as odometry
    is an estimate: its samples whose ``success`` is False are not refined with it, as the
    refiner's own failed estimates are not (and ``mask="auto"`` flags them ``no_motion``); a
    motion without ``success`` (a measurement: a dict, an EgoMotion) is used in every sample."""
    success = getattr(odometry, "success", None)
    if success is None:
        return torch.ones(batch, dtype=torch.bool, device=device)
    success = torch.as_tensor(success, device=device).reshape(-1)
    check_batch(success.numel(), "odometry.success", batch)
    return success.to(device=device, dtype=torch.bool).expand(batch)


def unestimated_motion(estimator: Any, batch: int, dtype: torch.dtype,
                       device: torch.device | str) -> tuple[str, dict[str, Tensor]]:
    """``(model name, {parameter: (batch,) zeros})``: the motion the refiner reports for samples
    it did not estimate (too few mask pixels; frames of one row or column for the image estimator),
    every one of them. The same model and keys a batch reports for such a sample beside estimated
    ones: zeros of every parameter of the estimator's model (this module's estimators); the paper's
    ``x_d, z_d, yaw`` for another estimator, whose model is known only from its results."""
    if isinstance(estimator, (FlowMotionEstimator, ImageMotionEstimator)):
        model = get_road_model(estimator.model)
        return model.name, {k: torch.zeros(batch, dtype=dtype, device=device) for k in model.params}
    return "paper", {k: torch.zeros(batch, dtype=dtype, device=device) for k in _PLANAR}


def check_estimator(estimator: object, name: str = "estimator") -> Any:
    """``estimator`` checked (None, or a callable estimator object) and returned: a TypeError names
    ``name``, also for an estimator class given where an instance is due (it is callable, but a call
    with a flow would make an estimator, not estimate); an :class:`ImageMotionEstimator` with a
    ``data_range`` other than 255 is a ValueError (the refiner and detect_road, which check their
    estimator with this, give it images on 0..255)."""
    if isinstance(estimator, type):
        raise TypeError(f"{name}: expected a road-motion estimator object, got the class {estimator.__name__}; "
                        f"make one: {name}={estimator.__name__}()")
    if estimator is not None and not callable(estimator):
        raise TypeError(f"{name}: expected a callable road-motion estimator, got {type(estimator).__name__}")
    # (the refiner and detect_road hand their estimator images on 0..255, whatever the caller's range)
    given = estimator.options.get("data_range", 255.0) if isinstance(estimator, ImageMotionEstimator) else 255.0
    if float(given) != 255.0:
        raise ValueError(f"{name}: ImageMotionEstimator(data_range={given!r}) is given images on 0..255 here (the "
                         f"refiner takes them so, and detect_road rescales its images to them); leave data_range out "
                         f"of its options (detect_road takes the images' data_range itself)")
    return estimator


def check_estimate(result: Any, batch: int, name: str = "estimator") -> Any:
    """``result``, an estimator's answer for ``batch`` samples, checked and returned: it has
    ``model`` (a displacement model), ``params`` (a dict of that model's parameters, (batch,)
    tensors), ``success`` ((batch,) tensor) and ``camera`` (a :class:`Camera` of batch ``batch``);
    else a TypeError or ValueError names ``name`` and quotes what came (a motion in px/s, the
    ``"velocity"`` model's, would otherwise refine a flow in pixels per frame)."""
    missing = [a for a in ("model", "params", "success", "camera") if not hasattr(result, a)]
    if missing:
        raise TypeError(f"{name}: expected a result with model, params, success and camera (a RoadFit), got "
                        f"{type(result).__name__} without {', '.join(missing)}")
    model = get_road_model(result.model, f"{name}: result.model")
    if model.velocity:
        raise ValueError(f"{name}: returned a {model.name!r} motion, whose flow is in px/s; the refiner needs the "
                         f"motion over the frame interval, a displacement model ('paper', 'plane' or 'homography')")
    if not isinstance(result.params, Mapping):
        raise TypeError(f"{name}: expected result.params a dict of (B,) tensors, got {type(result.params).__name__}")
    if unknown := sorted(set(result.params) - set(model.params)):
        raise ValueError(f"{name}: result.params has unknown parameters {unknown} of model {model.name!r}; expected "
                         f"some of {model.params}")
    for key, value in [*((f"params[{k!r}]", v) for k, v in result.params.items()), ("success", result.success)]:
        if not isinstance(value, Tensor) or value.shape != (batch,):
            error = ValueError if isinstance(value, Tensor) else TypeError
            got = f"shape {tuple(value.shape)}" if isinstance(value, Tensor) else type(value).__name__
            raise error(f"{name}: expected result.{key} a tensor of shape ({batch},) (the samples it was given), "
                        f"got {got}")
    if not isinstance(result.camera, Camera):
        raise TypeError(f"{name}: expected result.camera a fsof_torch.Camera, got {type(result.camera).__name__}")
    if result.camera.batch_size != batch:
        raise ValueError(f"{name}: expected result.camera of batch {batch} (the samples it was given), got batch "
                         f"{result.camera.batch_size}")
    return result


def finite_estimate(result: Any, camera: Camera, *, samples: Sequence[int] | None = None, warn: bool = True) -> Any:
    """An estimator's ``result`` with every sample whose parameters, or roll and pitch, are not all
    finite marked failed: a custom estimator's NaN is a failed estimate, never a motion to refine with.

    Such a sample gets ``success`` False, parameters 0, the input ``camera``'s roll and pitch, and
    (where the result holds them) a zero model flow, nowhere valid, and the identity homography; a
    RuntimeWarning names the samples (``samples``: their indices in the caller's batch). ``result``
    itself comes back where every sample is finite, else a copy (the estimator's object is left as
    it is); so does a motion without ``success`` (a dict of parameters, which a detection takes as
    given and checks where it uses it).
    """
    if not all(hasattr(result, name) for name in ("success", "params", "camera")):
        return result
    success = _held(result.success).to(torch.bool).reshape(-1)
    values = [*result.params.values(), result.camera.roll, result.camera.pitch]
    finite = torch.ones_like(success)
    for v in values:
        finite = finite & torch.isfinite(_held(v).detach()).reshape(-1).to(finite.device)
    if bool(finite.all()):
        return result
    if warn:
        bad = [samples[i] if samples is not None else i for i in (~finite).nonzero().flatten().tolist()]
        warn_user(f"estimator: samples {bad} came back with non-finite parameters (NaN or inf; success "
                  f"{success[~finite].tolist()}): taken as failed estimates")

    def keep(t: Tensor, fill: Any) -> Tensor:  # (the sample's own values where finite, else fill)
        ok = finite.to(t.device).reshape(-1, *[1] * (t.dim() - 1))
        return torch.where(ok, t, fill)

    cam = result.camera
    changes: dict[str, Any] = {
        "success": success & finite, "params": {k: keep(_held(v), 0.0) for k, v in result.params.items()},
        "camera": cam.replace(roll=keep(cam.roll, camera.roll.to(cam.roll)),
                              pitch=keep(cam.pitch, camera.pitch.to(cam.pitch)))}
    for name, fill in (("flow", 0.0), ("valid", False), ("homography", None)):
        t = getattr(result, name, None)
        if isinstance(t, Tensor) and t.dim() >= 1 and t.shape[0] == finite.numel():
            changes[name] = keep(t, torch.eye(3, dtype=t.dtype, device=t.device) if fill is None else fill)
    if dataclasses.is_dataclass(result):
        return dataclasses.replace(result, **changes)
    out = copy.copy(result)
    for name, value in changes.items():
        setattr(out, name, value)
    return out


class FlowMotionEstimator:
    """Fits a road model to the predicted flow inside the mask (:func:`~fsof_torch.fit_road`).

    Args (keyword-only):
        model: the road model (default the paper's).
        fixed: parameters held at the camera's / start values (default: the camera's roll and
            pitch, which a network's flow pins poorly; none for the ``"homography"``, which has
            no attitude); None: ``fit_road``'s default for the model. Names the model lacks
            raise a ValueError when the estimator is made.
        **options: further keyword arguments of :func:`~fsof_torch.fit_road` (not its inputs
            ``flow``, ``mask``, ``camera``, nor ``model``, ``fixed``, ``init``, which the
            estimator passes itself: a TypeError names them). Their values are checked here, as
            fit_road checks them: a bad one is an error when the estimator is made.

    Given the vehicle's planar odometry (x_d, z_d, yaw), that is held fixed at the odometry's values
    (the fit's start, and ``fixed`` extended by them; the model must have them: ``"paper"`` or
    ``"plane"``, else a ValueError) and the flow estimates the rest of the model's parameters (with
    the default ``model="paper"`` and ``fixed``, nothing: the fit only judges the odometry's model
    flow against the prediction, in ``success``). Pixels where the flow is NaN or inf are left out
    of the mask. Another odometry (a general homography) is the
    start where it is of the estimator's model. ``starts`` is not used: the fit has one start (the
    odometry's, or the planar motion of the back-projected mask pixels).
    """

    def __init__(self, *, model: str = "paper", fixed: Sequence[str] | None = _MOUNTING,
                 **options: Any) -> None:
        road_model = get_road_model(model)
        self.model = road_model.name
        if road_model.velocity:  # (its flow is in px/s: no model for a flow in pixels per frame)
            raise ValueError("model: the flow estimator needs a displacement model ('paper', 'plane' or "
                             "'homography'), not 'velocity' (its flow is in px/s)")
        # (the default holds the attitude the model has: the homography's none, not an error at the first call)
        fixed = tuple(n for n in _MOUNTING if n in road_model.params) if fixed is _MOUNTING else fixed
        self.fixed = check_names(fixed, "fixed")
        # (the inputs too: passed by the call, they would clash there as "multiple values")
        check_keywords(options, "options", fit_road, reserved=("flow", "mask", "camera", "model", "fixed", "init"))
        # (and their values, as fit_road checks them: a bad one is an error now, not at the first call
        # without odometry; the fixed names with them: a prior on a held parameter)
        given = {**_FIT_ROAD_DEFAULTS, **options, "fixed": self.fixed}
        check_road_fit_options(road_model, *(given[n] for n in inspect.signature(check_road_fit_options).parameters
                                             if n != "model"))
        self.options = dict(options)

    def __call__(self, flow: Tensor, mask: Tensor, camera: Camera, *, images: Any = None,
                 odometry: object = None, starts: Sequence[Any] = ()) -> RoadFit:
        if flow is None:
            raise ValueError("flow: FlowMotionEstimator needs the predicted flow, got None")
        fixed, init = self.fixed, None
        if odometry is not None:
            model, params = road_motion(odometry, displacement=True)  # (a rate, px/s: named, not left aside)
            init = params if model.name == self.model else None
            planar = planar_odometry(odometry)
            if planar is not None:
                # held at the odometry, as ImageMotionEstimator holds it: the fit estimates the rest
                road_model = get_road_model(self.model)
                if not all(k in road_model.params for k in _PLANAR):
                    raise ValueError(f"odometry: the {self.model!r} model has no planar motion (x_d, z_d, yaw) to "
                                     f"hold; fit the flow alone (odometry=None) or use model='paper' or 'plane'")
                init = {**(init or {}), **_finite_odometry(planar, check_float_tensor(flow, "flow").shape[0])}
                if held := [k for k in _PLANAR if k in (self.options.get("prior") or {})]:
                    raise ValueError(f"prior: {held[0]!r} is held at the odometry's value, so its prior would be "
                                     f"ignored; drop it, or call without odometry")
                fixed = fixed_parameters(road_model, fixed)
                fixed = fixed + tuple(k for k in _PLANAR if k not in fixed)
        check_float_tensor(flow, "flow")
        if isinstance(mask, Tensor):  # (named before the mask meets the flow below: torch's error from inside)
            check_same_device({"flow": flow, "mask": mask})
        if isinstance(mask, Tensor) and mask.dtype == torch.bool and not skip_values(flow) and not all_finite(flow):
            # a non-finite predicted pixel is no data: left out of the mask, as the refiner leaves it
            # out of the estimation (fit_road refuses one inside the mask)
            mask = mask & torch.isfinite(flow).all(1, keepdim=True)
        return fit_road(flow, mask, camera, model=self.model, fixed=fixed, init=init, **self.options)

    def __repr__(self) -> str:
        return f"FlowMotionEstimator(model={self.model!r}, fixed={self.fixed!r}{_options_repr(self.options)})"


class ImageMotionEstimator:
    """Fits a road model to the two images (:func:`~fsof_torch.estimation.image_fit.fit_image`):
    coarse to fine, robust to exposure changes and to cars in the mask, with MAP priors from the
    calibration and physical bounds.

    Args (keyword-only):
        model: ``"plane"`` (default: the 6-DOF motion over the road and the camera's attitude
            over it), ``"paper"`` or ``"homography"``.
        flow_start: also start from the planar motion of the predicted flow (when one is given,
            :func:`planar_start`; for ``"homography"``, that motion's map at the camera's roll and
            pitch); the start with the lowest robust image cost wins at the coarsest level.
        odometry_sigma: how far the images may move a given planar odometry. None (default):
            not at all, x_d, z_d and yaw are held at the odometry. A dict of standard deviations
            for some of ``"x_d"``, ``"z_d"`` (metres a frame) and ``"yaw"`` (radians a frame):
            those become Gaussian priors centred on the odometry (added to ``prior``), the fit
            starts from the odometry alone (no starts straight ahead, unless ``forward_starts``
            is given), and the others stay fixed. Real odometry is off by a few tenths of a
            degree of yaw or a percent of the step, and the camera's height over the road
            changes as the body moves: held fixed, such errors bend the rest of the fit
            (docs/real-roads.md measures it on KITTI's poses).
        **options: further keyword arguments of ``fit_image`` (``prior``, ``bounds``,
            ``max_points``, ``levels``, ...; not its inputs ``image1``, ``image2``, ``mask``,
            ``camera``, nor ``model``, ``starts``, which the estimator passes itself: a
            TypeError names them). Their values are checked here, as fit_image checks them
            (the bounds' batch size, ``init``'s values and a prior's of one value per frame
            aside): a bad one is an error when the estimator is made.

    Given the vehicle's planar odometry (x_d, z_d, yaw from poses or wheel odometry), that is held
    fixed (or, with ``odometry_sigma``, a prior) and the images estimate the rest of the model's
    parameters: every start (``init`` and ``starts``, fits among them) takes the odometry's x_d, z_d
    and yaw, and ``fixed`` (None: the model's default, as ``fit_image`` holds it) is extended by
    those held. An odometry without a planar motion (a
    general homography) holds nothing: it is one more start where it is of the estimator's own
    model, and the predicted flow's start is used as without odometry.
    """

    def __init__(self, *, model: str = "plane", flow_start: bool = True,
                 odometry_sigma: Mapping[str, float] | None = None, **options: Any) -> None:
        self.model = get_road_model(model).name
        if get_road_model(model).velocity:
            raise ValueError("model: the image estimator needs a displacement model, not 'velocity'")
        self.flow_start = check_bool(flow_start, "flow_start")
        if options:  # (the values too: a bad one is an error here, not at the first fit)
            check_image_fit_options({"model": self.model, **options}, "options", reserved=("starts",))
        self.odometry_sigma = _odometry_sigma(odometry_sigma, self.model, options.get("fixed"))
        self.options = dict(options)

    def __call__(self, flow: Tensor | None, mask: Tensor, camera: Camera, *,
                 images: tuple[Tensor, Tensor] | None = None, odometry: object = None,
                 starts: Sequence[Any] = ()) -> RoadFit:
        if images is None:
            raise ValueError("images: ImageMotionEstimator needs images=(image1, image2), got None")
        if not isinstance(images, (tuple, list)) or len(images) != 2:
            raise TypeError(f"images: expected a pair (image1, image2), got {type(images).__name__}"
                            + (f" of {len(images)}" if isinstance(images, (tuple, list)) else ""))
        image1, image2 = images
        # (the images first: a flow of another size is named, not the frames)
        dims = check_image_pair(image1, image2)
        # (the frames, the mask and the flow on one device: named before torch's error from inside)
        check_same_device({n: t for n, t in (("image1", image1), ("image2", image2), ("mask", mask), ("flow", flow))
                           if isinstance(t, Tensor)})
        check_has_values(image1, "image1", "to fit (a fit is iterative and data dependent)")
        if not isinstance(camera, Camera):
            raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
        if camera.batch_size not in (1, dims["B"]):
            raise ValueError(f"camera: expected batch {batch_choices(dims['B'])} (the images' B), got {camera.batch_size}")
        check_mask(mask, "mask")
        for name, t in (("image2", image2), ("mask", mask), ("camera", camera.K), ("flow", flow)):
            check_has_values(t, name, "to fit (a fit is iterative and data dependent)")  # (with image1 on a device)
        if flow is not None:  # (the flow is only a start: fit_image checks the rest)
            check_shape(check_float_tensor(flow, "flow"), "flow", ("B", 2, "H", "W"), dims)
            if mask.dim() != 4 or mask.shape[0] not in (1, dims["B"]) or tuple(mask.shape[1:]) != (1, dims["H"], dims["W"]):
                raise ValueError(f"mask: expected shape ({dims['B']}, 1, {dims['H']}, {dims['W']}) (the flow's; batch 1 "
                                 f"is broadcast), got {tuple(mask.shape)}")
        if not isinstance(starts, (list, tuple)):
            raise TypeError(f"starts: expected a list or tuple of start candidates, got {type(starts).__name__}")
        options = dict(self.options)
        starts = list(starts)
        fixed = check_names(options.pop("fixed", None), "fixed")
        init = options.pop("init", None)
        planar = None
        if odometry is not None:
            odometry_model, odometry_params = road_motion(odometry, displacement=True)  # (a rate: named)
            planar = planar_odometry(odometry)
            if planar is None and odometry_model.name == self.model:
                # a general motion of the estimator's own model (a homography): nothing to hold,
                # one more start (as FlowMotionEstimator starts from it)
                starts.insert(0, _finite_odometry(odometry_params, dims["B"]))
        if planar is not None:
            if not all(k in get_road_model(self.model).params for k in _PLANAR):
                raise ValueError(f"odometry: the {self.model!r} model has no planar motion (x_d, z_d, yaw) to "
                                 f"hold; estimate it from the images alone (odometry=None) or use model='plane'")
            _finite_odometry(planar, dims["B"])  # (named here: below they become the fit's init)
            # the odometry fixes the planar motion (or centres priors on it); the images add
            # what it does not measure, from every start (a previous fit's too)
            init = {**(init.params if isinstance(init, RoadFit) else (init or {})), **planar}
            starts = [s.motion() if isinstance(s, RoadFit) else s for s in starts]
            starts = [{**s, **planar} if isinstance(s, Mapping) else s for s in starts]
            held = tuple(k for k in _PLANAR if k not in self.odometry_sigma)
            given = options.get("prior")
            if isinstance(given, Mapping) and (on_held := [k for k in held if k in given]):
                raise ValueError(f"prior: {on_held[0]!r} is held at the odometry's value, so its prior would be "
                                 f"ignored; drop it, or give odometry_sigma={{{on_held[0]!r}: sigma}} instead")
            fixed = fixed_parameters(get_road_model(self.model), fixed)  # (None: the model's default)
            fixed = fixed + tuple(k for k in held if k not in fixed)
            if self.odometry_sigma:
                options["prior"] = _with_odometry_prior(options.get("prior", "calibration"), self.model, camera,
                                                        planar, self.odometry_sigma, fixed)
                options.setdefault("forward_starts", ())
        # (the flow's start and the fit sample the same mask: its pixels found once)
        with reused_mask_pixels():
            if planar is None and self.flow_start and flow is not None:
                # (planar_start leaves a frame's non-finite pixels out: each frame's start is its own;
                # in inference mode, as the fit that takes it runs: a start is no result of the call)
                start = inference(planar_start)(flow, mask, camera)
                if self.model == "homography":  # (x_d, z_d, yaw are no parameters of it: their map's are)
                    start = inference(planar_homography)(camera, start)
                starts.append(start)
            # (on the camera's values: fit_image's result keeps its K and height, and results are detached)
            camera = Camera._checked(camera.K.detach(), camera.height.detach(), camera.roll.detach(),
                                     camera.pitch.detach())
            return fit_image(image1, image2, mask, camera, model=self.model, fixed=fixed, init=init, starts=starts,
                             **options)

    def __repr__(self) -> str:
        sigma = f", odometry_sigma={self.odometry_sigma!r}" if self.odometry_sigma else ""
        options = _options_repr(self.options)
        return f"ImageMotionEstimator(model={self.model!r}, flow_start={self.flow_start}{sigma}{options})"


def _options_repr(options: Mapping[str, Any]) -> str:
    """An estimator's further options as they end its repr, each on one line: ``", max_iter=5"``."""
    return "".join(f", {k}={' '.join(repr(v).split())}" for k, v in options.items())


def _finite_odometry(values: Mapping[str, Any], B: int) -> Mapping[str, Any]:
    """``values`` (an odometry's parameters), checked finite and of 1 or ``B`` values (the
    frames'): a ValueError names the odometry's key (the fit would name its ``init``); and a step
    beyond a road vehicle's between two frames (100 m: odometry in millimetres) names the odometry."""
    steps = {}
    for k, v in values.items():
        # (a float or a (B,) float tensor, as the refiner takes it: a str, a bool, a list or an int tensor named here)
        t = as_batch_param(v, f"odometry[{k!r}]", finite=False)
        check_has_values(t, f"odometry[{k!r}]", "to fit (a fit is iterative and data dependent)")
        if not all_finite(t):
            raise ValueError(f"odometry[{k!r}]: expected finite values, got {v!r}")
        check_batch(t.numel(), f"odometry[{k!r}]", B)
        steps[k] = t.reshape(-1)
    check_motion_step(steps, "odometry")
    return values


def _odometry_sigma(sigma: object, model: str, fixed: object) -> dict[str, float]:
    """``odometry_sigma`` checked: {name: sigma > 0} of some of the model's planar parameters."""
    if sigma is None:
        return {}
    sigma = check_mapping(sigma, "odometry_sigma")
    if sigma and not all(k in get_road_model(model).params for k in _PLANAR):
        raise ValueError(f"odometry_sigma: the {model!r} model has no planar motion (x_d, z_d, yaw) to put a prior "
                         f"on; give odometry_sigma=None, or use model='plane' or 'paper'")
    for name, value in sigma.items():
        if name not in _PLANAR:
            raise ValueError(f"odometry_sigma: expected some of {_PLANAR} (the planar odometry), got {name!r}")
        check_number(value, f"odometry_sigma[{name!r}]", positive=True)
        if name in (check_names(fixed, "fixed") or ()):
            raise ValueError(f"odometry_sigma[{name!r}]: the parameter is also in fixed={fixed!r}")
    return {k: float(v) for k, v in sigma.items()}


def _with_odometry_prior(prior: object, model: str, camera: Camera, planar: Mapping[str, Any],
                         sigma: Mapping[str, float], held: Sequence[str] = ()) -> dict[str, tuple[Any, Any]]:
    """``fit_image``'s ``prior`` (``"calibration"``, None or a dict) with Gaussian priors of
    widths ``sigma`` centred on the planar odometry added (the calibration's on the ``held``
    parameters left out: they would have no effect, and fit_image refuses them)."""
    if prior == "calibration":
        base = {n: v for n, v in calibration_prior(model, camera.to(torch.float64)).items() if n not in held}
    elif prior is None:
        base = {}
    elif isinstance(prior, Mapping):
        base = dict(prior)
    else:  # (fit_image names a bad value)
        return prior
    both = sorted(set(base) & set(sigma))
    if both:
        raise ValueError(f"prior: {both} also given a prior by odometry_sigma; give each parameter one prior")
    return {**base, **{k: (planar[k], sigma[k]) for k in sigma}}
