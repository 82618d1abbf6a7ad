"""Road-motion results of one batch combined sample by sample: a fit of a coarser resolution
brought to the images' size, per sample one of two results (for example a second fit where it
succeeded, the first elsewhere), and some samples of a result (the starts of the samples that are
estimated), so that a sample in a batch gets what it would get alone."""

from __future__ import annotations

from dataclasses import fields, is_dataclass, replace
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.camera import Camera
from ..geometry.road_flow import flow_from_map
from ..geometry.road_models import get_road_model
from .flow_fit import RoadFit

__all__ = ["fit_at_size", "where_motion", "select_samples"]


def fit_at_size(fit: Any, camera: Camera, size: tuple[int, int]) -> Any:
    """A :class:`~fsof_torch.estimation.flow_fit.RoadFit` of another resolution (a coarser
    level's) as the same motion at ``size`` seen by ``camera`` (its homography, flow, validity,
    inliers and camera, with the fit's attitude); anything else as it is (a model's parameters do
    not depend on the resolution)."""
    if not isinstance(fit, RoadFit) or tuple(fit.flow.shape[-2:]) == tuple(size):
        return fit
    model = get_road_model(fit.model)
    dt = fit.homography.dtype
    cam = camera.to(dt).expand(fit.flow.shape[0])
    # (the fit's angles, as fitted: a failed fit's may be absurd, and are not validated again)
    cam = Camera._checked(cam.K, cam.height, *(a.to(cam.roll).expand_as(cam.roll)
                                               for a in (fit.camera.roll, fit.camera.pitch)))
    values = torch.stack([fit.params[n].to(dt) for n in model.params], dim=1)
    M = model.matrix(cam, values)
    flow, valid = flow_from_map(M.to(fit.flow.dtype), model.horizon_row(cam, values).to(fit.flow.dtype), size,
                                velocity=model.velocity)
    inliers = F.interpolate(fit.inliers.to(torch.uint8), size=size, mode="nearest").bool()
    return replace(fit, homography=M, flow=flow, valid=valid, inliers=inliers,
                   camera=cam.to(fit.camera.dtype))


def where_motion(take: Tensor, a: Any, b: Any) -> Any:
    """Per sample, motion ``a`` where ``take`` (B,) bool, else ``b``: two results of one estimator
    (a :class:`~fsof_torch.estimation.flow_fit.RoadFit`, a dict of parameters or a Camera; tensors
    with a batch dimension are chosen sample by sample, anything else must be the same in both)."""
    B = take.shape[0]
    if isinstance(a, Tensor) and isinstance(b, Tensor) and a.dim() >= 1 and a.shape == b.shape and a.shape[0] == B:
        return torch.where(take.reshape(B, *([1] * (a.dim() - 1))), a, b)
    if isinstance(a, dict) and isinstance(b, dict) and a.keys() == b.keys():
        return {k: where_motion(take, a[k], b[k]) for k in a}
    if isinstance(a, Camera) and isinstance(b, Camera):
        a, b = a.expand(B), b.expand(B)
        parts = ("K", "height", "roll", "pitch")
        return Camera._checked(*(where_motion(take, getattr(a, n), getattr(b, n)) for n in parts))
    if is_dataclass(a) and type(a) is type(b):
        return replace(a, **{f.name: where_motion(take, getattr(a, f.name), getattr(b, f.name)) for f in fields(a)})
    if a is None and b is None or isinstance(a, (str, int, float, bool)) and a == b:
        return a
    raise ValueError(f"estimator: its results of one batch cannot be combined sample by sample "
                     f"({type(a).__name__} and {type(b).__name__})")


def select_samples(x: Any, index: Tensor, B: int) -> Any:
    """The samples ``index`` of a motion, fit or start of batch ``B`` (tensors whose first
    dimension is ``B``, also inside dicts, cameras and dataclasses such as a
    :class:`~fsof_torch.estimation.flow_fit.RoadFit`); anything else (a value for the whole batch,
    a batch of 1 that is broadcast) as it is."""
    if isinstance(x, Tensor):
        return x[index] if x.dim() >= 1 and x.shape[0] == B else x
    if isinstance(x, dict):
        return {k: select_samples(v, index, B) for k, v in x.items()}
    if isinstance(x, tuple) and hasattr(x, "_fields"):  # a NamedTuple (an EgoMotion)
        return type(x)(*(select_samples(v, index, B) for v in x))
    if isinstance(x, Camera):
        x = x.expand(B)
        return Camera._checked(*(getattr(x, n)[index] for n in ("K", "height", "roll", "pitch")))
    if is_dataclass(x) and not isinstance(x, type):
        return replace(x, **{f.name: select_samples(getattr(x, f.name), index, B) for f in fields(x) if f.init})
    return x
