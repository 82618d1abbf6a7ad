"""Fitting a road-motion model to a flow field inside a road mask, robustly.

Only d / h is observable from flow (DESIGN.md §5): the camera height h is taken from the camera
and translations are reported in metres under it. Any model of
:mod:`fsof_torch.geometry.road_models` can be fitted (:func:`fit_road`); :func:`fit_displacement`
(the paper's model) and :func:`fit_velocity` (flow in px/s) are the paper's two.

Method: an even subsample of the mask's pixels (:mod:`~fsof_torch.estimation.sampling`); a start
from the planar motion of back-projected points (:mod:`~fsof_torch.estimation.initial`); the
robust Levenberg–Marquardt of :mod:`~fsof_torch.estimation.solver` on the end-point residuals,
with the Cauchy kernel's scale annealed from the spread of the start's residuals; then a polish
with Tukey's biweight cut at the inlier threshold, so that far outliers (other vehicles) stop
pulling on the estimate. The residual depends on the parameters only through the 3×3 map of the
model, so the normal equations are sums over the pixels' moments (:class:`FlowProblem`), and the
model's own derivatives do the rest.

Fitting is iterative and data dependent: not differentiable (it runs in ``torch.inference_mode``).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Any, Mapping

import torch
from torch import Tensor

from .._check import (autocast_off, batch_choices, check_batch, check_bool, check_fit_flags, check_float_tensor,
                      check_has_values, check_mapping, check_names, check_shape, inference, result_dtype, scalar,
                      check_same_device, summary_repr, to_device)
from ..geometry.camera import Camera
from ..geometry.egomotion import scalable_map
from ..geometry.road_flow import flow_from_map
from ..geometry.road_models import (ROAD_MODELS, RoadModel, get_road_model, homography_values, pack_params,
                                    plane_from_homography)
from .confidence import agreement
from .initial import homography_dlt, planar_motion
from .priors import within_bounds
from .robust import ROBUST_KERNELS, check_fit_options, robust_weight
from .sampling import gather_pixels, pixel_coordinates, sample_mask
from .solver import Evaluation, positive_definite, solve

__all__ = ["RoadFit", "FitResult", "VelocityFitResult", "FlowProblem", "fit_road", "fit_displacement",
           "fit_velocity", "robust_weight", "ROBUST_KERNELS", "DEFAULT_FIXED"]

#: The parameters each model holds at their start unless told otherwise: a flow field pins the
#: camera's roll well (with motion), its pitch poorly (it trades against z_d near the horizon).
DEFAULT_FIXED = {"paper": ("pitch",), "plane": (), "homography": (), "velocity": ("pitch",)}


@dataclass(eq=False, repr=False)
class RoadFit:
    """A road-motion model fitted to B frames (compared by identity, as a :class:`Camera` is).

    Attributes:
        model: the model's name.
        params: ``{name: (B,)}``, the fitted parameters (see the model's units); they are also
            attributes (``fit.z_d``).
        homography: (B, 3, 3) the fitted map (pixels t -> t+1; the velocity model: G in 1/s).
        flow: (B, 2, H, W) the model flow at full resolution (0 where not defined).
        valid: (B, 1, H, W) bool, where the model is defined.
        inliers: (B, 1, H, W) bool: mask pixels where the model is defined and within the inlier
            threshold (flow fits: end-point residual in px; image fits: photometric residual).
        residual: (B,) mean residual over the inliers (0 when none).
        success: (B,) bool; where False the parameters are finite but not to be trusted. Flow
            fits: converged (a polish that does not converge returns the robust stage's
            parameters, covariance and cost), on enough well-spread inliers making up at least the
            minimum share of the mask, well conditioned, within ``bounds`` (:func:`fit_road`). Image
            fits: finite, well posed, each free parameter more than its standard deviation inside
            ``bounds`` (which hold it), and passing ``fit_image``'s image tests (not convergence:
            ``extras["converged"]``).
        camera: a copy of the input camera with the fit's roll and pitch (fitted or held).
        iterations: (B,) int64 solver iterations.
        covariance: (B, P, P) the posterior covariance, any prior at its own weight (model order; 0 for fixed ones; where
            the fit is singular, as on an empty or one-pixel mask, +inf on the free parameters'
            diagonal and 0 elsewhere, never NaN).
        cost: (B,) the robust cost per point at the end.
        extras: further per-frame values of a fit (e.g. the velocity model's steering angle).
    """

    model: str
    params: dict[str, Tensor]
    homography: Tensor
    flow: Tensor
    valid: Tensor
    inliers: Tensor
    residual: Tensor
    success: Tensor
    camera: Camera
    iterations: Tensor
    covariance: Tensor | None = None
    cost: Tensor | None = None
    extras: dict[str, Tensor] = field(default_factory=dict)
    __repr__ = summary_repr

    def __getattr__(self, name: str) -> Tensor:
        for store in ("params", "extras"):
            values = self.__dict__.get(store) or {}
            if name in values:
                return values[name]
        raise AttributeError(f"{type(self).__name__} of model {self.__dict__.get('model')!r} has no {name!r}")

    def odometry(self) -> dict[str, Tensor]:
        """``dict(x_d=, z_d=, yaw=)`` of (B,) tensors (the paper's and the plane model; else ValueError)."""
        if not all(k in self.params for k in ("x_d", "z_d", "yaw")):
            raise ValueError(f"odometry: a {self.model!r} fit has no x_d, z_d, yaw: {tuple(self.params)}")
        return {k: self.params[k] for k in ("x_d", "z_d", "yaw")}

    def velocity(self) -> dict[str, Tensor]:
        """``dict(speed=, steering=, wheelbase=)`` of (B,) tensors (a :func:`fit_velocity` result; else ValueError)."""
        if not all(k in self.extras for k in ("steering", "wheelbase")):  # (was: AttributeError "... no 'steering'")
            raise ValueError(f"velocity: a {self.model!r} fit has no steering and wheelbase: fit_velocity (given the "
                             f"wheelbase) turns the velocity model's yaw rate into a steering angle, fit_road does not")
        return {k: getattr(self, k) for k in ("speed", "steering", "wheelbase")}

    def motion(self) -> dict[str, Any]:
        """``{"model": name, **params}``: what the refiner and the loss terms take as odometry."""
        return {"model": self.model, **self.params}


#: :func:`fit_displacement`'s result (a :class:`RoadFit` of the ``"paper"`` model).
FitResult = RoadFit
#: :func:`fit_velocity`'s result (a :class:`RoadFit` of the ``"velocity"`` model).
VelocityFitResult = RoadFit


class FlowProblem:
    """End-point residuals of a road model's flow at sampled pixels, for the solver.

    The residual depends on the parameters only through the 3×3 map M: per pixel
    ∂r/∂M = (1/q_z) [[p̃ᵀ, 0, −x′ p̃ᵀ], [0, p̃ᵀ, −y′ p̃ᵀ]] with (x′, y′) the projected point
    (velocity model: q_z = 1 and (x′, y′) the pixel itself). So Jᵀ W J in M's 9 entries is made of
    four weighted sums of p̃ p̃ᵀ (weights w/q_z² × 1, x′, y′, x′²+y′²) and Jᵀ W r of three weighted
    sums of p̃: seven weights summed against the pixels' six moments by one skinny matmul,
    instead of a (P, 2, N) Jacobian, then the chain rule through dM/dp (B, P, 3, 3) on 9×9
    matrices. (python benchmarks/bench_fit.py: the per-pixel work of an iteration.)
    """

    def __init__(self, model: RoadModel, camera: Camera, pts: Tensor, flow: Tensor, sel: Tensor,
                 K_inv: Tensor | None = None) -> None:
        self.model, self.camera, self.pts, self.sel = model, camera, pts, sel
        self.K, self.height = camera.K, camera.height
        self.K_inv = camera.K_inv() if K_inv is None else K_inv
        self.count = sel.sum(1)
        self.target = flow if model.velocity else pts[:, :2] + flow
        u, v, one = pts.unbind(1)
        # p̃ p̃ᵀ's six entries and p̃ (last), point-major for the sums against the weights
        self.moments = torch.stack([u * u, u * v, v * v, u, v, one], dim=-1)
        # the points below the horizon, for a model without mounting parameters: once
        self._below = None
        self.domain = None  # (the parameters that move the horizon, where the solver is to slide along it)
        if not model.mounting:
            self._below = sel & (torch.bmm(model.horizon_row(camera, torch.zeros_like(camera.height)[:, None]), pts)[:, 0] > 0)

    def evaluate(self, params: Tensor) -> Evaluation:
        M, dM, horizon = self.model.evaluate(self.K, self.K_inv, self.height, params, True)
        if self._below is None:
            q = torch.bmm(torch.cat([M, horizon], dim=1), self.pts)
            below = self.sel & (q[:, 3] > 0)
        else:
            q, below = torch.bmm(M, self.pts), self._below
        qz = q[:, 2]
        pxy = self.pts[:, :2]
        if self.model.velocity:
            use = below
            inv_z, proj = None, pxy
            r = torch.addcmul(q[:, :2], pxy, qz.unsqueeze(1), value=-1.0).sub_(self.target)
        else:
            use = below & (qz > 1e-9)
            # in place on the fresh product q (each per-point temporary costs a pass over memory);
            # a point that does not count keeps a finite (if huge) residual
            inv_z = qz.clamp_min(1e-9).reciprocal_()
            proj = q[:, :2].mul_(inv_z.unsqueeze(1))
            r = proj - self.target
        # (points not in ``use`` keep a finite residual: every sum over the points masks them)
        rx, ry = r.unbind(1)
        return Evaluation(torch.mul(rx, rx).addcmul_(ry, ry), use, r, (dM, proj, inv_z))

    def normal_equations(self, ev: Evaluation, w: Tensor) -> tuple[Tensor, Tensor]:
        dM, proj, inv_z = ev.state
        r = ev.residual
        B, P = dM.shape[:2]
        # the seven weights written into one buffer (per-point temporaries and a stack would
        # each cost a pass over memory): a, a x′, a y′, a (x′² + y′²), w/q_z r, -w/q_z (x′ r_x + y′ r_y)
        wts = torch.empty(B, 7, w.shape[-1], dtype=w.dtype, device=w.device)
        a, ax, ay, app, brx, bry, gz = wts.unbind(1)
        x, y = proj.unbind(1)
        if inv_z is None:
            a.copy_(w)
            torch.mul(r, w.unsqueeze(1), out=wts[:, 4:6])
        else:
            wi = w * inv_z
            torch.mul(wi, inv_z, out=a)
            torch.mul(r, wi.unsqueeze(1), out=wts[:, 4:6])
        torch.mul(proj, a.unsqueeze(1), out=wts[:, 1:3])
        torch.mul(x, ax, out=app).addcmul_(y, ay)
        torch.mul(x, brx, out=gz).neg_().addcmul_(y, bry, value=-1.0)
        S = torch.bmm(wts, self.moments)  # (B, 7, 6)
        AH = torch.mm(S[:, :4].reshape(B, 24), _moment_basis(w.dtype, w.device)).reshape(B, 9, 9)
        gH = S[:, 4:, 3:].reshape(B, 9, 1)  # rows x, y, z of M against p̃
        D = dM.reshape(B, P, 9)
        return torch.bmm(torch.bmm(D, AH), D.transpose(1, 2)), torch.bmm(D, gH).squeeze(-1)


_BASIS: dict = {}


def _moment_basis(dtype: torch.dtype, device: torch.device) -> Tensor:
    """(24, 81): Jᵀ W J in M's entries (9 × 9) from the four moment sums (4 × 6): blocks
    [[S0, 0, −S1], [0, S0, −S2], [−S1, −S2, S3]], each S_k symmetric from (uu, uv, vv, u, v, 1)."""
    if (key := (dtype, device)) not in _BASIS:
        sym = ((0, 1, 3), (1, 2, 4), (3, 4, 5))
        blocks = {(0, 0): (0, 1.0), (1, 1): (0, 1.0), (0, 2): (1, -1.0), (2, 0): (1, -1.0),
                  (1, 2): (2, -1.0), (2, 1): (2, -1.0), (2, 2): (3, 1.0)}
        with torch.inference_mode(False):  # (the fits run in inference mode; a cached constant must not)
            ah = torch.zeros(24, 81, dtype=dtype, device="cpu")  # (filled on the host, whatever the default device)
            for (bi, bj), (k, sign) in blocks.items():
                for i in range(3):
                    for j in range(3):
                        ah[6 * k + sym[i][j], (3 * bi + i) * 9 + 3 * bj + j] = sign
            _BASIS[key] = ah.to(device)
    return _BASIS[key]


# -- input handling ------------------------------------------------------------------------------

def check_flow_inputs(flow: Tensor, mask: Tensor, camera: Camera, valid: Tensor | None) -> tuple[dict, Camera, Tensor]:
    """Validate a flow fit's inputs; return dims, the camera (batch B, on the flow's device) and
    the mask (batch B, ANDed with ``valid``)."""
    check_float_tensor(flow, "flow")
    dims = check_shape(flow, "flow", ("B", 2, "H", "W"))
    if not isinstance(mask, Tensor):
        raise TypeError(f"mask: expected a bool tensor of shape (B, 1, H, W), got {type(mask).__name__}")
    one = mask.dim() == 4 and mask.shape[0] == 1  # (batch 1 broadcasts: checked as it came, for the message)
    check_shape(mask, "mask", ("B", 1, "H", "W"), {**dims, "B": 1} if one else dims)
    mask = mask.expand(dims["B"], -1, -1, -1) if one else mask
    if mask.dtype != torch.bool:
        raise TypeError(f"mask: expected dtype torch.bool, got {mask.dtype}")
    if valid is not None:
        if not isinstance(valid, Tensor) or valid.dtype != torch.bool:
            raise TypeError(f"valid: expected a bool tensor of shape (B, 1, H, W), got "
                            f"{valid.dtype if isinstance(valid, Tensor) else type(valid).__name__}")
        one = valid.dim() == 4 and valid.shape[0] == 1  # (batch 1 broadcasts, as the mask's does)
        check_shape(valid, "valid", ("B", 1, "H", "W"), {**dims, "B": 1} if one else dims)
        mask = mask & to_device(valid, "valid", mask.device)
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
    if camera.batch_size not in (1, dims["B"]):
        raise ValueError(f"camera: expected batch {batch_choices(dims['B'])} (the flow's B), got {camera.batch_size}")
    if dims["B"] == 0 or dims["H"] == 0 or dims["W"] == 0:
        raise ValueError(f"flow: expected a non-empty batch and image, got shape {tuple(flow.shape)}")
    camera = camera.expand(dims["B"]).to(device=flow.device)
    # one reduction settles the common case (a NaN or inf anywhere makes the sum non-finite)
    if not bool(torch.isfinite(flow.detach().sum())):
        n = int((~torch.isfinite(flow.detach()) & mask).sum())
        if n:
            raise ValueError(f"flow: expected finite values inside mask, got {n} NaN/inf values there "
                             f"(exclude them with valid=)")
    return dims, camera, mask


def start_values(model: RoadModel, init: object, camera: Camera, default: Tensor,
                 what: str = "init") -> tuple[Tensor, list[bool]]:
    """Start values (B, P) float64: ``init``'s (a :class:`RoadFit` or a dict of any of the model's
    parameters) over ``default``; and (P,) flags of the names given. Another road model's
    parameters (a fit of another model as a start) are left aside; a name of no road model (a
    typo), or a fit, motion or dict that shares no parameter, is an error naming ``what``."""
    B, P = default.shape
    given = [False] * P
    if init is None:
        return default, given
    values = init.params if isinstance(init, RoadFit) else init
    if not isinstance(values, Mapping):
        raise TypeError(f"{what}: expected a RoadFit or a dict of {model.params}, got {type(init).__name__}")
    kind, named = ("fit", init.model) if isinstance(init, RoadFit) else ("motion", values.get("model"))  # (motion())
    known = {"model"} | {n for m in ROAD_MODELS.values() for n in m.params}  # (a road motion's own form)
    unknown = sorted(str(n) for n in values if n not in known)
    if unknown:
        raise ValueError(f"{what}: unknown parameters {unknown}; expected some of the {model.name!r} model's "
                         f"{model.params}")
    if values and named != model.name and not set(values) & set(model.params):  # (else ignored: a silent default)
        kind = f"{named!r} {kind}" if named else f"{kind} of {sorted(map(str, values))}"  # (a dict: its names)
        raise ValueError(f"{what}: a {kind} shares no parameter with the {model.name!r} model's {model.params}")
    out = default.clone()
    for i, name in enumerate(model.params):
        value = values.get(name)
        if value is None:
            continue
        check_has_values(value, f"{what}[{name!r}]", "to start a fit from")  # (was: "expected a number or a tensor")
        try:
            t = torch.as_tensor(value, dtype=torch.float64, device=default.device).detach().reshape(-1)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"{what}: expected a number or a tensor for {name}, got {type(value).__name__} "
                            f"{value!r:.40}") from None
        check_batch(t.numel(), f"{what}[{name!r}]", B)
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{what}: expected a finite {name}, got {t.tolist()}")
        out[:, i] = t.expand(B)
        given[i] = True
    return out, given


def fixed_parameters(model: RoadModel, fixed: object) -> tuple[str, ...]:
    """The names held fixed: ``fixed`` (a name or names), or the model's default."""
    names = DEFAULT_FIXED[model.name] if fixed is None else ((fixed,) if isinstance(fixed, str) else tuple(fixed))
    unknown = sorted(set(names) - set(model.params))
    if unknown:
        raise ValueError(f"fixed: unknown parameters {unknown} of model {model.name!r}; expected some of {model.params}")
    return names


def prior_terms(model: RoadModel, prior: Mapping[str, tuple[float, float]] | None, noise: float,
                B: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """A Gaussian prior ``{name: (mean, sigma)}`` as (mean, precision) (B, P) for the solver:
    precision noise² / σ² (residuals of std ``noise`` against parameters of std σ)."""
    mean = torch.zeros(B, len(model.params), dtype=dtype, device=device)
    precision = torch.zeros_like(mean)
    for name, spec in (prior or {}).items():
        if name not in model.params:
            raise ValueError(f"prior: unknown parameter {name!r} of model {model.name!r}")
        for v in spec if isinstance(spec, (tuple, list)) else ():  # (was: torch's "Cannot copy out of meta tensor")
            check_has_values(v, f"prior[{name!r}]", "for a prior")
        try:
            mu, sigma = spec
            sigma = torch.as_tensor(sigma, dtype=dtype, device=device).reshape(-1)
            mu = torch.as_tensor(mu, dtype=dtype, device=device).reshape(-1)
        except (TypeError, ValueError):
            raise ValueError(f"prior[{name!r}]: expected (mean, sigma), got {spec!r}") from None
        for what, t in (("mean", mu), ("sigma", sigma)):
            check_batch(t.numel(), f"prior[{name!r}] {what}", B)
        if not bool(torch.isfinite(mu).all()) or not bool((sigma > 0).all()):
            raise ValueError(f"prior[{name!r}]: expected a finite mean and sigma > 0, got {spec!r}")
        i = model.params.index(name)
        mean[:, i] = mu
        precision[:, i] = noise * noise / sigma.square()
    return mean, precision


# -- the fit ---------------------------------------------------------------------------------------

# the robust stage before the polish runs on an even stride of about this many of the points: it
# only has to land in the polish's basin (its statistical error stays far below the polish's cut)
_ROBUST_STAGE_POINTS = 2048
# Resolution tolerance: an accepted step that moves the model flow by at most this fraction of the
# robust RMS residual ends a stage. The estimate's own uncertainty is of the order of that RMS
# times sqrt(parameters / points) (3 and 8192: 2 %), so steps below 1 % change nothing the data
# resolve; the robust stage before a polish only has to land in the polish's basin (10 %).
_RESOLUTION = 0.01
_ROBUST_STAGE_RESOLUTION = 0.1


def _robust_points(pts: Tensor, obs: Tensor, sel: Tensor, count: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """The start's and the robust stage's points: an even stride of about ``_ROBUST_STAGE_POINTS``
    of the sampled points (B, ·, N). ``count`` None: N is the sampled number (``max_points``), one
    stride for all; else (N the largest mask's count, the others padded) each frame's stride from
    its own count (one host read), so that a frame's points do not depend on its batch-mates."""
    N = pts.shape[-1]
    k = max(1, N // _ROBUST_STAGE_POINTS)
    if count is not None:
        counts = count.tolist()
        ks = [max(1, n // _ROBUST_STAGE_POINTS) for n in counts]
        if len(set(ks)) > 1:  # (one stride for all: the slices below, as for a frame alone)
            kept = [-(-n // kb) for n, kb in zip(counts, ks)]
            j = torch.arange(max(kept), device=pts.device)
            idx = (j * torch.tensor(ks, device=pts.device).unsqueeze(1)).clamp_max(N - 1)
            at = idx.unsqueeze(1)
            return (pts.gather(2, at.expand(-1, pts.shape[1], -1)), obs.gather(2, at.expand(-1, obs.shape[1], -1)),
                    sel.gather(1, idx) & (j < torch.tensor(kept, device=pts.device).unsqueeze(1)))
        k = ks[0]
    return pts[..., ::k], obs[..., ::k], sel[..., ::k]


def _initial(model: RoadModel, camera: Camera, K_inv: Tensor, values: Tensor, pts: Tensor, flow: Tensor,
             sel: Tensor) -> Tensor:
    """Values (B, P) float64 of a start without a prior, from the robust stage's points
    (:func:`_robust_points`): the paper's model from the planar motion of back-projected points,
    the plane and the homography from a robust DLT homography (the plane decomposed with the
    road's normal from the camera's roll and pitch), the velocity model from rest (it is linear)."""
    if model.velocity:
        return values
    if model.name == "paper":
        roll, pitch = values[:, model.index("roll")], values[:, model.index("pitch")]
        # (one robust step after least squares: the robust stage anneals from there)
        lin, _ = planar_motion(camera.K, K_inv, roll, pitch, pts, flow, sel, iterations=1)
        h = camera.height
        return torch.stack([lin[:, 0] * h, lin[:, 1] * h, lin[:, 2], roll, pitch], dim=-1)
    # the plane's robust stage anneals from the decomposed start: its DLT needs only to land in
    # the basin (2 robust iterations); the homography's starts at the DLT itself (4)
    H = homography_dlt(camera.K, K_inv, pts, flow, sel, iterations=2 if model.name == "plane" else 4)
    if model.name == "plane":
        cam = camera
        if model.mounting:  # the attitude to decompose with: the start's
            cam = Camera._checked(camera.K, camera.height, values[:, model.index("roll")],
                                  values[:, model.index("pitch")])
        # a frame whose DLT is degenerate (not finite, or singular: plane_from_homography refuses
        # it) keeps its start; the others are decomposed as they would be alone
        usable = torch.isfinite(H).all(dim=(-2, -1)) & (torch.linalg.det(H) != 0)
        eye = torch.eye(3, dtype=H.dtype, device=H.device)
        plane = plane_from_homography(torch.where(usable.reshape(-1, 1, 1), H, eye), cam)
        out = torch.stack([plane[n] for n in model.params], dim=-1)
        return torch.where(torch.isfinite(out) & usable.unsqueeze(-1), out, values)
    # a frame whose DLT the model cannot express (K⁻¹ H K's last entry 0 up to rounding, which
    # homography_values refuses: a flow of 1e15 px or more) keeps its start, as the plane's does
    usable = scalable_map(K_inv @ H @ camera.K)
    eye = torch.eye(3, dtype=H.dtype, device=H.device)
    out = homography_values(torch.where(usable.reshape(-1, 1, 1), H, eye), camera.K, K_inv)
    return torch.where(usable.unsqueeze(-1), out, values)


def check_road_fit_options(model: RoadModel, fixed: object, prior: object, robust: object, scale: object,
                           max_iter: object, tol: object, max_points: object, inlier_threshold: object,
                           min_points: object, min_inlier_fraction: object, polish: object, check_every: object,
                           bounds: object) -> tuple:
    """:func:`fit_road`'s options checked without a flow (named errors, 0-d tensors read), as the
    estimator and the refiner that forward them check them when made. Returns the fixed names,
    the prior, ``scale``, ``tol``, ``inlier_threshold``, ``min_inlier_fraction``, ``max_iter``,
    ``max_points``, ``min_points`` and the two stages' ``check_every``."""
    max_iter, max_points, min_points = (scalar(v, n) for n, v in (("max_iter", max_iter), ("max_points", max_points),
                                                                  ("min_points", min_points)))
    check_every = tuple(scalar(k, "check_every") for k in check_every) if isinstance(check_every, tuple) else \
        scalar(check_every, "check_every")
    numbers_ = check_fit_options(robust, scale, max_iter, tol, max_points, inlier_threshold, min_points,
                                 min_inlier_fraction)
    check_bool(polish, "polish")
    if bounds not in ("physical", None):
        raise (ValueError if isinstance(bounds, str) else TypeError)(f"bounds: expected 'physical' or None, got {bounds!r}")
    fixed_names, prior = fixed_parameters(model, check_names(fixed, "fixed")), check_mapping(prior, "prior")
    if unknown := sorted(str(n) for n in (prior or {}) if n not in model.params):
        raise ValueError(f"prior: unknown parameter {unknown[0]!r} of model {model.name!r}")
    if held := [n for n in model.params if n in fixed_names and n in (prior or {})]:
        raise ValueError(f"prior: {held[0]!r} is held at its start (fixed={fixed_names!r}), so its prior would "
                         f"be ignored; free it (fixed= without it, or fit_roll= / fit_pitch=True) or drop its prior")
    checks = (2, 1) if check_every == "auto" else check_every if isinstance(check_every, tuple) else (check_every,) * 2
    expected = "'auto', an int >= 1, a pair of them (robust stage, polish) or None"
    if len(checks) != 2 or any(isinstance(k, bool) or not isinstance(k, (numbers.Integral, type(None))) for k in checks):
        raise TypeError(f"check_every: expected {expected}, got {type(check_every).__name__} {check_every!r}")
    if any(k is not None and k < 1 for k in checks):
        raise ValueError(f"check_every: expected {expected}, got {check_every!r}")
    return (fixed_names, prior, *numbers_, max_iter, max_points, min_points, checks)


@inference
def fit_road(flow: Tensor, mask: Tensor, camera: Camera, *, model: str | RoadModel = "paper",
             fixed: object = None, init: object = None,
             prior: Mapping[str, tuple[float, float]] | None = None, valid: Tensor | None = None,
             robust: str = "cauchy", scale: float = 1.0, max_iter: int = 50, tol: float = 1e-6,
             max_points: int | None = 8192, inlier_threshold: float | None = None,
             min_points: int = 30, min_inlier_fraction: float = 0.25, polish: bool = True,
             check_every: int | tuple[int, int] | str | None = "auto", bounds: str | None = "physical") -> RoadFit:
    """Fit a road-motion model to a flow field inside a road mask.

    Args:
        flow: forward flow (B, 2, H, W) in pixels (px/s for ``model="velocity"``), any float dtype.
        mask: road pixels to fit (B, 1, H, W) bool (batch 1 broadcasts).
        camera: intrinsics at the flow's resolution, the height (known: only d/h is observable),
            and the roll / pitch: the start where ``init`` gives none (so, held where not fitted).
        model: ``"paper"``, ``"plane"``, ``"homography"`` or ``"velocity"``
            (:data:`~fsof_torch.geometry.road_models.ROAD_MODELS`).
        fixed: names held at their start (``init``'s value where it gives one, else the default
            start: the camera's roll / pitch, and 0 for a motion parameter, not the data's guess);
            default :data:`DEFAULT_FIXED` (the pitch of the paper's and the velocity model).
        init: a start: a :class:`RoadFit` of the same model or a dict of any of its parameters;
            default: the planar motion of back-projected points (the velocity model: rest).
        prior: ``{name: (mean, sigma)}`` Gaussian priors (the parameters' units), weighed
            against the residuals at the kernel's scale; on fitted parameters only (ValueError).
        valid: optional (B, 1, H, W) bool validity of the flow (e.g. KITTI's; batch 1
            broadcasts; moved to the flow's device); ANDed with mask (which must be on the flow's
            device: else a ValueError names it).
        robust: the kernel (:data:`ROBUST_KERNELS`); ``scale``: its scale in pixels (px/s).
        max_iter, tol: the solver's budget and tolerance per stage.
        max_points: mask pixels per frame that enter the iterations (an even stride over the
            mask); None: all. The model flow, inliers and residual cover every mask pixel.
        inlier_threshold: end-point residual below which a mask pixel is an inlier (default
            3 × scale); also the polish's Tukey cut.
        min_points, min_inlier_fraction: fewer inliers (or inliers on fewer than 3 rows or
            columns), or an inlier share of the mask below the fraction, mark the frame as failed.
        polish: after the robust fit, iterate with Tukey's biweight cut at the inlier threshold
            (where it does not converge: the robust fit's parameters, ``success=False``). Not
            after ``robust="l2"`` (least squares asked for) or ``"tukey"`` (its one stage is
            Tukey's, cut at ``scale``): ignored there. Without it a mask up to the horizon is fitted
            along the horizon's edge with ``bounds``; Huber's and soft-L1's can still end there
            short of their minimum (docs/fitting.md, step 4).
        check_every: each solver stage's first early-stop check (one host read; then after 1,
            1, 2, 4, ... more iterations): ``(robust stage, polish)`` or one number for both.
            ``"auto"``: (2, 1). A stage ends where the next step, predicted from the normal
            equations, would move the residuals by less than they resolve (the solver's
            ``predict``): the robust stage, annealing its kernel from the start, usually after
            two iterations, the polish, which starts at the robust answer, after one. The checks
            change no result (converged samples stop moving): they only end the loops. None:
            run the fixed budgets (no host read inside the loops).
        bounds: ``"physical"``: a frame has failed whose free parameters leave ``physical_bounds``
            (:mod:`~fsof_torch.estimation.priors`) or are not determined to half their width (1 σ).

    Returns:
        :class:`RoadFit`; parameters in float64 for float64 flow, else the camera's dtype
        promoted with the flow's.

    Raises:
        TypeError, ValueError: a wrong type (TypeError); wrong shapes, NaN/inf flow inside the
        mask, a bad option value. A frame whose mask is empty, tiny, on one row, or whose geometry
        leaves the parameters undetermined gets ``success=False`` (its parameters stay finite).

    Example:
        >>> cam = Camera(torch.tensor([[700., 0, 320], [0, 700, 90], [0, 0, 1]], dtype=torch.float64), 1.65)
        >>> from fsof_torch.geometry.road_flow import road_flow
        >>> truth = {"z_d": 1.0, "pitch_change": 0.003, "y_d": 0.01}
        >>> flow, valid = road_flow(cam, truth, (192, 640), model="plane")
        >>> fit = fit_road(flow, valid, cam, model="plane")
        >>> round(float(fit.z_d), 6), round(float(fit.pitch_change), 6)
        (1.0, 0.003)
    """
    model = get_road_model(model)
    (fixed_names, prior, scale, tol, inlier_threshold, min_inlier_fraction, max_iter, max_points, min_points,
     checks) = check_road_fit_options(model, fixed, prior, robust, scale, max_iter, tol, max_points, inlier_threshold,
                                      min_points, min_inlier_fraction, polish, check_every, bounds)
    if init is not None and not isinstance(init, (Mapping, RoadFit)):
        raise TypeError(f"init: expected a RoadFit or a dict of {model.params}, got {type(init).__name__} {init!r}")
    # (the flow and the mask on one device, named before torch's error from inside would come;
    # valid, the camera, the starts and the priors follow the flow's)
    check_same_device({n: t for n, t in (("flow", flow), ("mask", mask)) if isinstance(t, Tensor)})
    for name, t in (("flow", flow), ("mask", mask), ("camera", getattr(camera, "K", None))):
        check_has_values(t, name, "to fit (a fit is iterative and data dependent)")
    dims, camera, mask = check_flow_inputs(flow, mask, camera, valid)
    B, H, W = dims["B"], dims["H"], dims["W"]
    out_dtype = result_dtype(flow, camera.K)
    cam64 = camera.to(torch.float64)
    K_inv = cam64.K_inv()
    thr = 3.0 * scale if inlier_threshold is None else float(inlier_threshold)
    free = torch.tensor([n not in fixed_names for n in model.params], device=flow.device)

    with autocast_off(flow):
        points = sample_mask(mask, max_points)
        pix, sel, count = points.pix, points.sel, points.count
        pts = pixel_coordinates(pix, W)
        obs = gather_pixels(flow.detach(), pix).to(torch.float64)
        obs = torch.where(sel.unsqueeze(1), obs, 0.0)
        _, default = pack_params(model, cam64, None)
        start, given = start_values(model, init, cam64, default)
        coarse = _robust_points(pts, obs, sel, count if max_points is None else None)
        if not all(kept := [g or n in fixed_names for g, n in zip(given, model.params)]):  # (held: init's or default)
            guess = _initial(model, cam64, K_inv, start, *coarse)
            start = torch.where(torch.tensor(kept, device=flow.device), start, guess)
        mean, precision = prior_terms(model, prior, scale, B, torch.float64, flow.device) if prior else (None, None)
        stages = [(robust, float(scale), init is None, _RESOLUTION, checks[0])]
        if polish and robust not in ("tukey", "l2"):
            stages = [(robust, float(scale), init is None, _ROBUST_STAGE_RESOLUTION, checks[0]),
                      ("tukey", thr, False, _RESOLUTION, checks[1])]
        params = start
        iterations = torch.zeros(B, dtype=torch.long, device=flow.device)
        for i, (kernel, s, anneal, resolution, first_check) in enumerate(stages):
            last = i + 1 == len(stages)
            points_used = (pts, obs, sel) if last else coarse
            problem = FlowProblem(model, cam64, *(x.contiguous() for x in points_used), K_inv)
            if last and kernel != "tukey" and bounds is not None and model.mounting:  # (docs/fitting.md, step 4)
                problem.domain = torch.tensor([n in model.mounting for n in model.params], device=flow.device)
            sol = solve(problem, params, free=free, prior_mean=mean,
                        prior_precision=None if precision is None else precision * (s / scale) ** 2,
                        kernel=kernel, scale=s, anneal=anneal, max_iter=max_iter,
                        tol=tol if last else max(tol, 1e-4), resolution=resolution,
                        check_every=first_check, predict=True)
            well_posed, covariance, cost = _well_posed(sol, free), sol.covariance(sol.scale), sol.cost
            if i == 0:
                params, converged, first = sol.params, sol.converged, (well_posed, covariance, cost)
            else:
                # the polish is kept where it converged to a finite answer; elsewhere the robust
                # stage's answer, with its own tests, covariance and cost, and no success
                converged = sol.converged & torch.isfinite(sol.params).all(-1)
                params = torch.where(converged.unsqueeze(-1), sol.params, params)
                well_posed, cost = torch.where(converged, well_posed, first[0]), torch.where(converged, cost, first[2])
                covariance = torch.where(converged.reshape(B, 1, 1), covariance, first[1])
            iterations = iterations + sol.iterations
        finite = torch.isfinite(params).all(-1)
        params = torch.where(finite.unsqueeze(-1), params, start)
        M, _, horizon = model.evaluate(cam64.K, K_inv, cam64.height, params, False)
        if horizon is None:
            horizon = model.horizon_row(cam64, params)
        model_flow, model_valid = flow_from_map(M.to(out_dtype), horizon.to(out_dtype), (H, W), velocity=model.velocity)
        inliers, residual, spread, fraction, n_in = agreement(flow.detach(), model_flow, model_valid, points, thr)
    success = finite & converged & spread & well_posed & (n_in >= min_points) & (fraction >= min_inlier_fraction)
    success = success if bounds is None else success & within_bounds(model, cam64, params, covariance, free)
    return _result(model, camera, params, M, model_flow, model_valid, inliers, residual, success, iterations,
                   covariance, cost, out_dtype)


def _well_posed(sol: Any, free: Tensor) -> Tensor:
    """A conditioning test of the final normal equations: the smallest eigenvalue of the
    scaled normal matrix (collinear parameters) above 1e-9, and of the unscaled one per unit
    weight (a parameter the flow barely depends on: (px per unit of parameter)²) above 1e-6."""
    A = sol.normal
    B = A.shape[0]
    wsum = sol.weights.sum(1).clamp_min(1e-300)
    fixed = ~free
    eye_fixed = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device) * fixed
    Ab = torch.where(fixed.unsqueeze(-1) | fixed.unsqueeze(-2), eye_fixed, A / wsum.reshape(B, 1, 1))
    return sol.well_conditioned(1e-9) & positive_definite(Ab, 1e-6)


def _result(model: RoadModel, camera: Camera, params: Tensor, M: Tensor, flow: Tensor, valid: Tensor,
            inliers: Tensor, residual: Tensor, success: Tensor, iterations: Tensor, covariance: Tensor,
            cost: Tensor, dtype: torch.dtype) -> RoadFit:
    named = {n: params[:, i].to(dtype) for i, n in enumerate(model.params)}
    # (detached copies: results are detached, and not the caller's storage nor a batch-1 camera's expansion)
    own = {n: getattr(camera, n).detach().to(dtype, copy=True) for n in ("K", "height", "roll", "pitch")}
    cam_fit = Camera._checked(own["K"], own["height"], named.get("roll", own["roll"]), named.get("pitch", own["pitch"]))
    return RoadFit(model=model.name, params=named, homography=M.to(dtype), flow=flow, valid=valid,
                   inliers=inliers, residual=residual, success=success, camera=cam_fit, iterations=iterations,
                   covariance=covariance.to(dtype), cost=cost.to(dtype))


def fit_displacement(flow: Tensor, mask: Tensor, camera: Camera, *, fit_roll: bool = True,
                     fit_pitch: bool = False, init: object = None, **options: Any) -> RoadFit:
    """Fit the displacement model (paper eq. 13) to a flow field inside a road mask.

    :func:`fit_road` with ``model="paper"``: x_d, z_d (metres), yaw (radians), and the camera's
    roll / pitch where ``fit_roll`` / ``fit_pitch``. Other options as there.

    Example:
        >>> cam = Camera(torch.tensor([[700., 0, 320], [0, 700, 90], [0, 0, 1]], dtype=torch.float64), 1.65)
        >>> from fsof_torch.geometry.road_flow import displacement_flow
        >>> flow, valid = displacement_flow(cam, 0.05, 1.0, 0.01, (192, 640))
        >>> fit = fit_displacement(flow, valid, cam)
        >>> round(float(fit.z_d), 6), bool(fit.success)
        (1.0, True)
    """
    check_fit_flags("fit_displacement", fit_roll, fit_pitch, options)
    fixed = tuple(n for n, on in (("roll", fit_roll), ("pitch", fit_pitch)) if not on)
    if isinstance(init, RoadFit) and init.model != "paper":
        raise ValueError(f"init: expected a fit of the 'paper' model, got one of {init.model!r}")
    return fit_road(flow, mask, camera, model="paper", fixed=fixed, init=init, **options)


def fit_velocity(flow: Tensor, mask: Tensor, camera: Camera, wheelbase: Tensor | float, *,
                 fit_roll: bool = True, fit_pitch: bool = False, init: object = None,
                 scale: float = 10.0, **options: Any) -> RoadFit:
    """Fit the velocity model (paper eq. 21) to a flow field in pixels per second.

    :func:`fit_road` with ``model="velocity"`` (speed m/s, yaw_rate rad/s, roll, pitch); the wheelbase l (m, > 0,
    float or (B,)) only turns the yaw rate into ``fit.steering`` δ_f = atan(φ̇ l / v_r) (0 at rest: a speed within
    3 σ of 0). ``init`` may give a steering angle instead of a yaw rate (not both: ValueError), and its wheelbase
    (``fit.velocity()``; default ``wheelbase``). ``scale``: the kernel's scale in px/s (default 10 px/s: 1 px at 10 Hz)."""
    check_fit_flags("fit_velocity", fit_roll, fit_pitch, options)
    wb = init_wb = _wheelbase(wheelbase, flow)
    if isinstance(init, Mapping) and "wheelbase" in init:  # (an earlier fit's velocity(): its steering's)
        init_wb, init = _wheelbase(init["wheelbase"], flow, "init['wheelbase']"), {k: v for k, v in init.items()
                                                                                   if k != "wheelbase"}
    given = {}
    if isinstance(init, Mapping) and "steering" in init:  # (a steering of None is not given, as any init entry)
        init = dict(init)
        given = {"steering": init.pop("steering"), "speed": init.get("speed", 0.0)}
    if given.get("steering") is not None:
        if init.get("yaw_rate") is not None:  # (it raised "init: unknown parameters ['steering']")
            raise ValueError(f"init: expected a steering angle or a yaw rate, not both (either gives the start's yaw rate), got "
                             f"steering={given['steering']!r} and yaw_rate={init['yaw_rate']!r}; drop one")
        try:
            steer, speed = (torch.as_tensor(v, dtype=torch.float64, device="cpu").reshape(-1) for v in given.values())
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"init: expected numbers or tensors for steering and speed, got {given!r}") from None
        B = flow.shape[0] if isinstance(flow, Tensor) and flow.dim() == 4 else max(steer.numel(), speed.numel())
        for key, t in (("steering", steer), ("speed", speed)):
            check_batch(t.numel(), f"init[{key!r}]", B)
        if not bool(torch.isfinite(steer).all()) or not bool((steer.abs() < math.pi / 2).all()):
            raise ValueError(f"init: expected a finite steering with |δ_f| < π/2 rad, got {steer.tolist()}")
        init["yaw_rate"] = speed * torch.tan(steer) / init_wb.to(torch.float64).cpu()
    fixed = tuple(n for n, on in (("roll", fit_roll), ("pitch", fit_pitch)) if not on)
    fit = fit_road(flow, mask, camera, model="velocity", fixed=fixed, init=init, scale=scale, **options)
    i = get_road_model(fit.model).index("speed")  # (the covariance is in the model's parameter order)
    speed, yaw_rate, sd = fit.params["speed"], fit.params["yaw_rate"], fit.covariance[:, i, i].clamp_min(0).sqrt()
    moving = speed.abs() > (3 * sd).clamp_min(1e-12)  # (a speed told from rest: beyond 3 σ, else no steering)
    wb = wb.to(speed).expand_as(speed).clone()  # (the fit's own: not the caller's tensor, nor a stride-0 view)
    steering = torch.where(moving, torch.atan(yaw_rate * wb / torch.where(moving, speed, 1.0)), 0.0)
    fit.extras.update(steering=steering, wheelbase=wb)
    return fit


def _wheelbase(wheelbase: Tensor | float, flow: Tensor, name: str = "wheelbase") -> Tensor:
    if isinstance(wheelbase, Tensor):
        check_float_tensor(wheelbase, name)
        check_has_values(wheelbase, name, "to turn the yaw rate into a steering angle")
        wb = wheelbase.detach().reshape(-1)
    elif isinstance(wheelbase, numbers.Real) and not isinstance(wheelbase, bool):
        wb = torch.tensor([float(wheelbase)], dtype=torch.float64, device="cpu")
    else:
        raise TypeError(f"{name}: expected a float or a (B,) tensor, got {type(wheelbase).__name__}")
    if isinstance(flow, Tensor) and flow.dim() == 4:
        check_batch(wb.numel(), name, flow.shape[0])
    if not bool((torch.isfinite(wb) & (wb > 0)).all()):
        raise ValueError(f"{name}: expected values > 0, got {wb.tolist()}")
    return wb
