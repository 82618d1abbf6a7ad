"""``FreespaceRefined``: a flow network wrapped with the refiner, taking the network's own inputs
and giving its own outputs (plain tensors, RAFT-style lists, ptlflow's and torchvision's
contracts; see :mod:`fsof_torch.refinement.contracts`)."""

from __future__ import annotations

import inspect
import math
import numbers
from dataclasses import replace
from typing import Any, Mapping

import torch
from torch import Tensor, nn

from .._check import (batch_choices, check_float_tensor, check_image_range, check_keywords, check_mapping,
                      check_mask, check_shape, scalar)
from ..estimation.flow_fit import RoadFit
from ..geometry.camera import Camera
from ..geometry.road_models import road_motion_batch
from .auto_refine import motion_complete, refine_with_auto_road
from .auto_road import ROAD_RESERVED, check_road_size, detect_road, road_level
from .contracts import InputPadder, Padding, collect_flows, finest_flow, images_from_ptlflow, is_ptlflow_inputs
from .fusion import FreespaceRefiner, RefineOutput, refine_flow
from .road_options import ROAD_VALUE_OPTIONS, check_road_values
from .options import select_estimator

__all__ = ["FreespaceRefined", "road_option_values", "check_road_options"]


def road_option_values(road_options: Mapping[str, Any], name: str = "road_options") -> dict[str, Any]:
    """``road_options``, keyword arguments for :func:`~fsof_torch.refinement.auto_road.detect_road`
    that a caller passes on (this wrapper, the refine job), checked as the detection checks them,
    before any detection: a name it does not take, or one the callers set themselves
    (:data:`~fsof_torch.refinement.auto_road.ROAD_RESERVED`), is a TypeError naming ``name``; a bad
    value the TypeError or ValueError that ``detect_road`` would raise
    (:func:`~fsof_torch.refinement.road_options.check_road_values`; what needs the images or the
    camera: :func:`check_road_options`). Returns every option of
    :data:`~fsof_torch.refinement.road_options.ROAD_VALUE_OPTIONS`, the given ones and
    ``detect_road``'s defaults for the rest, as ints, floats and bools."""
    check_keywords(road_options, name, detect_road, reserved=ROAD_RESERVED)
    defaults = inspect.signature(detect_road).parameters
    return check_road_values({n: road_options.get(n, defaults[n].default) for n in ROAD_VALUE_OPTIONS})


def check_road_options(road_options: Mapping[str, Any], shape: tuple[int, ...], camera: Camera,
                       estimated: bool) -> None:
    """``road_options`` (:func:`road_option_values`) against images of ``shape`` and ``camera`` as
    :func:`~fsof_torch.refinement.auto_road.detect_road` checks them
    (:func:`~fsof_torch.refinement.auto_road.check_road_size`; ``seed_level``'s where the detection
    will estimate the motion), with its errors."""
    options = road_option_values(road_options)
    if options["level"] is None:
        options["level"] = road_level(shape[-2:], options["window"], options["height_window"])
    check_road_size(shape, camera, options, estimated=estimated)


class FreespaceRefined(nn.Module):
    """A flow network with freespace refinement attached: a drop-in replacement for ``net``.

    Args:
        net: a flow network, called as it expects to be called (see
            :mod:`fsof_torch.refinement.contracts`): ``net(image1, image2, **kw)`` (RAFT,
            torchvision's RAFT, TinyRAFT) or ``net(inputs, **kw)`` with ptlflow's input dict
            (ARFlow's PWC-Lite, which takes the pair concatenated, ``net(torch.cat([image1,
            image2], 1))`` on 0..1, needs a two-image adapter: docs/contracts.md). It may return any structure :func:`refine_flow` accepts whose finest flow has the
            (padded) input's size, batch and device: a net that returns only a coarser flow
            (PWC-Net's 1/4) or a larger one (its own padding left on), another batch than the
            images' or another device, raises a ValueError naming ``net`` after it ran;
            upsample its flow to the input's size first (crop a padded one, or give ``pad``). It gets images of its own (copies, or
            the padded images): one that changes its inputs in place leaves the caller's images,
            which the refiner reads, as they were.
        refiner: a :class:`FreespaceRefiner` (default: ``FreespaceRefiner()``).
        road: None (the caller passes ``mask``) or ``"auto"`` (no mask: the road found in the two
            images, as ``refine_flow(flow, "auto", ...)`` finds it with the refiner's options: its
            estimator, and the call's ``odometry``).
        road_options: keyword arguments for :func:`~fsof_torch.refinement.auto_road.detect_road`
            (a mapping with string keys, or None), as ``refine_flow``'s ``road_options``, with
            ``road="auto"`` only: given with ``road=None`` they raise a ValueError. Their names and
            values are checked when the wrapper is made, with ``detect_road``'s errors, and
            against the images' size and the camera's height at a call, before the network runs
            (``seed_level``'s too where the detection will estimate the motion). A call that
            passes ``mask=`` detects nothing, and leaves them unused.
        pad: an :class:`~fsof_torch.refinement.contracts.InputPadder` for networks that need
            sizes divisible by a stride (torchvision's RAFT: ``InputPadder(8)``; ptlflow's RAFT,
            so that its ``flow_small`` is refined on its true grid). The images are padded before
            the net, the mask (with False) and the camera (:meth:`Camera.padded`) the same way;
            the output is refined on the padded grid, so a coarse level such as ``flow_small``
            (1/8 of the padded size) gets the padded camera scaled to it; then every output tensor
            of the padded full size is cropped back to the input size. Coarser levels stay on
            their padded grid, as the network returned them. With ``road="auto"`` the road is found
            in the images as they came (a replicated border is not road) and padded like a mask.
        image_range: ``(low, high)`` of the images passed as two tensors (the net's convention:
            (0, 255) for RAFT and TinyRAFT, (-1, 1) for torchvision's weights' transforms); the
            refiner's photometric fit reads them as 0..255. They are checked against it before
            the net runs (finite, within it up to 1 % of its width, and not all within its lowest
            1/255, as 0..1 images given for 0..255 are). ptlflow dicts are BGR in [0, 1].

    Forward: ``model(image1, image2, *, camera, mask=None, odometry=None, return_info=False, **kw)``
    or ``model(inputs, *, camera, ...)`` with a ptlflow dict. Returns the net's output with its
    forward flows refined (same structure), or ``(output, RefineOutput)`` with
    ``return_info=True``. The mask (B, 1, H, W) bool (batch 1 broadcasts) and the camera refer to
    the input images' size; both are checked against the images as they came, before the network
    runs (errors quote the caller's shapes, not the padded ones), as are ``odometry`` and
    ``image2``'s shape, dtype and device (``image1``'s). With ``pad`` the RefineOutput's
    maps (also the gate's and the found road's masks) are cropped to the input size and its camera
    is the input's (the padding undone); so is a :class:`~fsof_torch.estimation.flow_fit.RoadFit`
    in ``fit``: its maps (``flow``, ``valid``, ``inliers``) cropped, its camera the input's, its
    ``homography`` mapping the input's pixels (another estimator's result comes as it gave it,
    on the padded grid).
    """

    def __init__(self, net: nn.Module, refiner: FreespaceRefiner | None = None, *,
                 road: str | None = None, road_options: Mapping[str, Any] | None = None,
                 pad: InputPadder | None = None, image_range: tuple[float, float] = (0.0, 255.0)) -> None:
        super().__init__()
        for name, given in (("net", net), ("refiner", refiner), ("pad", pad)):
            if isinstance(given, type):  # (a class is callable: the first call would build one from the images)
                raise TypeError(f"{name}: expected an instance, got the class {given.__name__}; make one: "
                                f"{name}={given.__name__}(...)")
        if not callable(net):
            raise TypeError(f"net: expected a callable flow network, got {type(net).__name__}")
        if refiner is not None and not isinstance(refiner, FreespaceRefiner):
            raise TypeError(f"refiner: expected a FreespaceRefiner, got {type(refiner).__name__}")
        if road not in (None, "auto"):
            raise ValueError(f"road: expected None or 'auto', got {road!r}")
        if pad is not None and not isinstance(pad, InputPadder):
            raise TypeError(f"pad: expected an InputPadder or None, got {type(pad).__name__}")
        given = image_range
        if isinstance(image_range, (tuple, list)):
            image_range = tuple(scalar(v, "image_range") for v in image_range)
        if (not isinstance(image_range, tuple) or len(image_range) != 2
                or any(isinstance(v, bool) or not isinstance(v, numbers.Real) for v in image_range)):
            raise TypeError(f"image_range: expected (low, high), two numbers, got {given!r}")
        lo, hi = (float(v) for v in image_range)
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise ValueError(f"image_range: expected finite (low, high) with high > low, got {image_range!r}")
        # (named now, not at the first call after the network has run)
        road_options = check_mapping(road_options, "road_options")
        if road_options and road != "auto":
            raise ValueError(f"road_options: apply to the road detection of road='auto'; with road={road!r} "
                             f"nothing is detected, got road_options={road_options!r}")
        if road_options:  # (their names and values, as detect_road checks them)
            road_option_values(road_options)
        self.net = net
        self.refiner = refiner if refiner is not None else FreespaceRefiner()
        self.road = road
        self.road_options = road_options
        self.pad = pad
        self.image_range = (lo, hi)

    def forward(self, *inputs: Any, camera: Camera, mask: Tensor | None = None, odometry: object = None,
                return_info: bool = False, **kw: Any):
        """The network's output for ``image1, image2`` (B, 3, H, W), its forward flows refined (see the class)."""
        ptlflow = len(inputs) == 1 and is_ptlflow_inputs(inputs[0])
        if ptlflow:
            net_inputs = dict(inputs[0])
            image1, image2 = images_from_ptlflow(net_inputs)  # (validates the dict)
        elif len(inputs) == 2:
            image1, image2 = inputs
            for name, im in (("image1", image1), ("image2", image2)):
                check_float_tensor(im, name)
                check_shape(im, name, ("B", "C", "H", "W"), nonempty=("B", "H", "W"))  # (as ptlflow's dict)
                if im.shape[1] not in (1, 3):  # (the refiner's estimator and gate read grey or RGB)
                    raise ValueError(f"{name}: expected 1 (grey) or 3 (RGB) channels, got shape {tuple(im.shape)}")
            if image2.shape != image1.shape:
                raise ValueError(f"image2: expected the shape of image1 {tuple(image1.shape)}, got {tuple(image2.shape)}")
            # (one pair for the net: torch's own error from its first layer, or the refiner's after it ran)
            if image2.dtype != image1.dtype:
                raise TypeError(f"image2: expected the dtype of image1 ({image1.dtype}), got {image2.dtype}")
            if image2.device != image1.device:
                raise ValueError(f"image2: expected the device of image1 ({image1.device}), got {image2.device}")
        else:
            raise TypeError(f"inputs: expected (image1, image2) or one ptlflow dict {{'images': ...}}, "
                            f"got {len(inputs)} positional argument(s)")
        # the caller's camera and mask against the images as they came: before the padding moves
        # them, and before the network runs
        B, size = image1.shape[0], tuple(image1.shape[-2:])
        if not isinstance(camera, Camera):
            raise TypeError(f"camera: expected a fsof_torch.Camera, got {type(camera).__name__}")
        if camera.batch_size not in (1, B):
            raise ValueError(f"camera: expected batch {batch_choices(B)} (the images' batch), got {camera.batch_size}")
        if mask is None and self.road != "auto":
            raise ValueError("mask: expected a road mask (B, 1, H, W) bool, got None "
                             "(pass mask=..., or build FreespaceRefined(..., road='auto'))")
        if mask is not None:
            check_mask(mask, "mask")
            if mask.dim() != 4 or mask.shape[1] != 1 or mask.shape[0] not in (1, B) or tuple(mask.shape[-2:]) != size:
                raise ValueError(f"mask: expected shape ({B}, 1, {size[0]}, {size[1]}) (the images' batch and size; "
                                 f"batch 1 is broadcast), got {tuple(mask.shape)}")
        if not ptlflow:  # (ptlflow's dict was checked above: BGR in [0, 1])
            for name, im in (("image1", image1), ("image2", image2)):
                check_image_range(im, name, self.image_range)  # (in the caller's units)
        if odometry is not None:  # (its form, batch and values, as the refiner will check them)
            road_motion_batch(odometry, B, torch.float64, image1.device, batch_of="the images' batch",
                              displacement=True)
        if mask is None:  # road="auto": its options against these images and the camera, as the detection will
            # (it estimates the motion unless given a complete one: as refine_flow's mask="auto" decides)
            estimated = not motion_complete(odometry, self.refiner.fit)
            check_road_options(self.road_options or {}, tuple(image1.shape), camera, estimated=estimated)
        padding = self.pad.padding(size) if self.pad is not None else None

        def own(x: Tensor) -> Tensor:
            """The net's own tensor: a net that normalises its inputs in place (some RAFT ports do)
            leaves the caller's images, which the refiner reads after it, as they were. (A padded
            image is new already; a zero padding returns the image itself.)"""
            y = padding.pad(x, mode=self.pad.pad_mode) if padding is not None else x
            return y.clone() if y is x else y

        if ptlflow:
            net_inputs["images"] = own(net_inputs["images"])
            output = self.net(net_inputs, **kw)
        else:
            output = self.net(own(image1), own(image2), **kw)
            lo, hi = self.image_range
            if (lo, hi) != (0.0, 255.0):
                image1, image2 = ((im - lo) * (255.0 / (hi - lo)) for im in (image1, image2))
        padded_size = size if padding is None else padding.padded_size(size)
        flow_keys = self.refiner.flow_keys
        flows = collect_flows(output, "flow", flow_keys)
        if not flows:  # (as refine_flow says it)
            raise ValueError(f"flow: no flow found in the {type(output).__name__}; expected a value under "
                             f"one of the keys {flow_keys} (set flow_keys)")
        finest = finest_flow(flows)[1]
        if finest.shape[0] != B:  # (before the refiner, which would blame the caller's mask or images)
            raise ValueError(f"net: its finest flow has batch {finest.shape[0]} (shape {tuple(finest.shape)}), the "
                             f"input images batch {B}: the wrapper needs one flow per image pair")
        if finest.device != image1.device:  # (the refiner would blame the caller's images)
            raise ValueError(f"net: its finest flow is on {finest.device}, the input images on {image1.device}: "
                             f"return the flow on the images' device")
        if tuple(finest.shape[-2:]) != padded_size:
            given = f"{size[0]} x {size[1]}" + ("" if padded_size == size else
                                               f" (padded to {padded_size[0]} x {padded_size[1]})")
            larger = finest.shape[-2] > padded_size[0] or finest.shape[-1] > padded_size[1]
            fix = ("; crop off the padding the net added (RAFT's padder.unpad), or give pad=InputPadder(stride) so "
                   "that it gets sizes it need not pad" if larger else
                   "; upsample it (a PWC-style net's 1/4 flow: its size and its values by 4)")
            raise ValueError(f"net: its finest flow is {finest.shape[-2]} x {finest.shape[-1]}, the input "
                             f"{given}: the wrapper needs full-size output{fix}")
        if padding is not None and padding.is_zero:
            padding = None
        if mask is None:
            info = self._refine_auto(output, finest, camera, odometry, (image1, image2), padding)
        elif padding is None:
            info = self.refiner(output, mask, camera, odometry, images=(image1, image2))
        else:
            images = tuple(padding.pad(im, mode=self.pad.pad_mode) for im in (image1, image2))
            info = self.refiner(output, padding.pad(mask), padding.camera(camera), odometry, images=images)
        if padding is None:
            return (info.flow, info) if return_info else info.flow
        flow = padding.unpad_output(info.flow, padded_size)
        if not return_info:
            return flow
        gate = info.gate
        if gate is not None:  # its maps at the input size too (its per-sample counts as they are)
            gate = gate._replace(use_model=padding.unpad(gate.use_model), evidence=padding.unpad(gate.evidence))
        # (the found road, and the motion found with it, are of the images as they came)
        fit = info.fit if info.road is not None else _unpadded_fit(info.fit, padding)
        info = info._replace(flow=flow, weight=padding.unpad(info.weight), mask=padding.unpad(info.mask),
                             flow_model=padding.unpad(info.flow_model), gate=gate, fit=fit,
                             camera=info.camera.cropped(padding.left, padding.top, padding.right, padding.bottom))
        return flow, info

    def extra_repr(self) -> str:
        options = f", road_options={self.road_options!r}" if self.road_options else ""
        return f"road={self.road!r}{options}, pad={self.pad!r}, image_range={self.image_range!r}"

    def _refine_auto(self, output: Any, finest: Tensor, camera: Camera, odometry: object,
                     images: tuple[Tensor, Tensor], padding: Padding | None) -> RefineOutput:
        """``refine_flow(output, "auto", camera, odometry, images=images)`` with the refiner's
        options (:meth:`FreespaceRefiner.refine_options`) and ``road_options``
        (:meth:`FreespaceRefiner.forward` takes no ``road_options``).
        With ``padding`` the same steps (:func:`refine_with_auto_road`), the road found in the
        images as they came and the output refined on the padded grid."""
        r = self.refiner
        options = r.refine_options()
        if padding is None:
            return refine_flow(output, "auto", camera, odometry, images=images, road_options=self.road_options,
                               **options)
        padded = tuple(padding.pad(im, mode=self.pad.pad_mode) for im in images)

        def refine_padded(_: Tensor, mask: Tensor, camera: Camera, motion: object, *, images: Any,
                          **kw: Any) -> RefineOutput:  # (the output itself, on the padded grid)
            return refine_flow(output, padding.pad(mask), padding.camera(camera), motion, images=padded, **kw)

        images = tuple(im.detach() for im in images)  # (as refine_flow passes them on)
        # (the estimator refine_flow's "auto" path gives the detection)
        road_estimator = select_estimator(r.estimator, r.fit, images, r.fit_roll, r.fit_pitch, r.fit_options,
                                          r.photometric_options)
        return refine_with_auto_road(refine_padded, padding.unpad(finest), "auto", camera, odometry, images=images,
                                     road_estimator=road_estimator, road_options=self.road_options, **options)


def _unpadded_fit(fit: Any, padding: Padding) -> Any:
    """A :class:`RoadFit` of the padded grid on the input's: its maps cropped, its camera the
    input's, its homography (pixels t -> t+1) conjugated by the padding's shift; another result as it is."""
    if not isinstance(fit, RoadFit):
        return fit
    shift = torch.eye(3, dtype=fit.homography.dtype, device=fit.homography.device)
    shift[0, 2], shift[1, 2] = padding.left, padding.top  # (an input pixel p is p + shift on the padded grid)
    unshift = shift.clone()
    unshift[:2, 2] = -shift[:2, 2]
    return replace(fit, flow=padding.unpad(fit.flow), valid=padding.unpad(fit.valid),
                   inliers=padding.unpad(fit.inliers), homography=unshift @ fit.homography @ shift,
                   camera=fit.camera.cropped(padding.left, padding.top, padding.right, padding.bottom))
