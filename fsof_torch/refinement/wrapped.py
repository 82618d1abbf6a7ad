"""``FreespaceRefined``: a flow network wrapped with the refiner, taking the network's own inputs
and giving its own outputs (plain tensors, RAFT-style lists, ptlflow's and torchvision's
contracts; see :mod:`fsof_torch.refinement.contracts`)."""

from __future__ import annotations

import math
import numbers
from typing import Any, Mapping

from torch import Tensor, nn

from .._check import batch_choices, check_float_tensor, check_keywords, check_mapping, check_mask
from ..geometry.camera import Camera
from .auto_road import detect_road
from .contracts import InputPadder, collect_flows, finest_flow, images_from_ptlflow, is_ptlflow_inputs
from .fusion import FreespaceRefiner

__all__ = ["FreespaceRefined"]


class FreespaceRefined(nn.Module):
    """A flow network with freespace refinement attached: a drop-in replacement for ``net``.

    Args:
        net: a flow network, called as it expects to be called (see
            :mod:`fsof_torch.refinement.contracts`): ``net(image1, image2, **kw)`` (RAFT,
            torchvision's RAFT, TinyRAFT, ARFlow) or ``net(inputs, **kw)`` with ptlflow's input
            dict. It may return any structure :func:`refine_flow` accepts.
        refiner: a :class:`FreespaceRefiner` (default: ``FreespaceRefiner()``).
        road: None (the caller passes ``mask``) or ``"auto"`` (no mask: the road found in the two images).
        road_options: keyword arguments for :func:`~fsof_torch.refinement.auto_road.detect_road`
            (a mapping with string keys, or None), with ``road="auto"`` only: given with
            ``road=None`` they raise a ValueError. A call that passes ``mask=`` detects nothing,
            and leaves them unused.
        pad: an :class:`~fsof_torch.refinement.contracts.InputPadder` for networks that need
            sizes divisible by a stride (torchvision's RAFT: ``InputPadder(8)``; ptlflow's RAFT,
            so that its ``flow_small`` is refined on its true grid). The images are padded before
            the net, the mask (with False) and the camera (:meth:`Camera.padded`) the same way;
            the output is refined on the padded grid, so a coarse level such as ``flow_small``
            (1/8 of the padded size) gets the padded camera scaled to it; then every output tensor
            of the padded full size is cropped back to the input size. Coarser levels stay on
            their padded grid, as the network returned them.
        image_range: ``(low, high)`` of the images passed as two tensors (the net's convention:
            (0, 255) for RAFT and TinyRAFT, (-1, 1) for torchvision's weights' transforms); the
            refiner's photometric fit reads them as 0..255. ptlflow dicts are BGR in [0, 1].

    Forward: ``model(image1, image2, *, camera, mask=None, odometry=None, return_info=False, **kw)``
    or ``model(inputs, *, camera, ...)`` with a ptlflow dict. Returns the net's output with its
    forward flows refined (same structure), or ``(output, RefineOutput)`` with
    ``return_info=True``. The mask (B, 1, H, W) bool (batch 1 broadcasts) and the camera refer to
    the input images' size; both are checked against the images as they came, before the network
    runs (errors quote the caller's shapes, not the padded ones). With ``pad`` the RefineOutput's
    maps (also the gate's and the found road's masks) are cropped to the input size and its camera
    is the input's (the padding undone).
    """

    def __init__(self, net: nn.Module, refiner: FreespaceRefiner | None = None, *,
                 road: str | None = None, road_options: Mapping[str, Any] | None = None,
                 pad: InputPadder | None = None, image_range: tuple[float, float] = (0.0, 255.0)) -> None:
        super().__init__()
        if not callable(net):
            raise TypeError(f"net: expected a callable flow network, got {type(net).__name__}")
        if refiner is not None and not isinstance(refiner, FreespaceRefiner):
            raise TypeError(f"refiner: expected a FreespaceRefiner, got {type(refiner).__name__}")
        if road not in (None, "auto"):
            raise ValueError(f"road: expected None or 'auto', got {road!r}")
        if pad is not None and not isinstance(pad, InputPadder):
            raise TypeError(f"pad: expected an InputPadder or None, got {type(pad).__name__}")
        if (not isinstance(image_range, (tuple, list)) or len(image_range) != 2
                or any(isinstance(v, bool) or not isinstance(v, numbers.Real) for v in image_range)):
            raise TypeError(f"image_range: expected (low, high), two numbers, got {image_range!r}")
        lo, hi = (float(v) for v in image_range)
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise ValueError(f"image_range: expected finite (low, high) with high > low, got {image_range!r}")
        # (named now, not at the first call after the network has run)
        road_options = check_mapping(road_options, "road_options")
        if road_options and road != "auto":
            raise ValueError(f"road_options: apply to the road detection of road='auto'; with road={road!r} "
                             f"nothing is detected, got road_options={road_options!r}")
        check_keywords(road_options, "road_options", detect_road, reserved=("image1", "image2", "camera", "flow"))
        self.net = net
        self.refiner = refiner if refiner is not None else FreespaceRefiner()
        self.road = road
        self.road_options = road_options
        self.pad = pad
        self.image_range = (lo, hi)

    def forward(self, *inputs: Any, camera: Camera, mask: Tensor | None = None, odometry: object = None,
                return_info: bool = False, **kw: Any):
        ptlflow = len(inputs) == 1 and is_ptlflow_inputs(inputs[0])
        if ptlflow:
            net_inputs = dict(inputs[0])
            image1, image2 = images_from_ptlflow(net_inputs)  # (validates the dict)
        elif len(inputs) == 2:
            image1, image2 = inputs
            for name, im in (("image1", image1), ("image2", image2)):
                check_float_tensor(im, name)
                if im.dim() != 4:
                    raise ValueError(f"{name}: expected shape (B, C, H, W), got {tuple(im.shape)}")
            if image2.shape != image1.shape:
                raise ValueError(f"image2: expected the shape of image1 {tuple(image1.shape)}, got {tuple(image2.shape)}")
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
        padding = self.pad.padding(size) if self.pad is not None else None
        if ptlflow:
            if padding is not None:
                net_inputs["images"] = padding.pad(net_inputs["images"], mode=self.pad.pad_mode)
            output = self.net(net_inputs, **kw)
        else:
            if padding is not None:
                output = self.net(padding.pad(image1, mode=self.pad.pad_mode),
                                  padding.pad(image2, mode=self.pad.pad_mode), **kw)
            else:
                output = self.net(image1, image2, **kw)
            lo, hi = self.image_range
            if (lo, hi) != (0.0, 255.0):
                image1, image2 = ((im - lo) * (255.0 / (hi - lo)) for im in (image1, image2))
        if padding is not None and padding.is_zero:
            padding = None
        road = None
        if mask is None:  # found in the images as they came (a replicated border is not road)
            finest = finest_flow(collect_flows(output, "output", self.refiner.flow_keys))[1].detach()
            road = detect_road(image1, image2, camera, flow=finest if padding is None else padding.unpad(finest),
                               **self.road_options)
            # its mask, and its motion unless the caller's odometry is given
            mask, odometry = road.usable_mask, road.motion if odometry is None else odometry
        if padding is not None:
            camera = padding.camera(camera)
            image1, image2 = (padding.pad(im, mode=self.pad.pad_mode) for im in (image1, image2))
            mask = padding.pad(mask)
        info = self.refiner(output, mask, camera, odometry, images=(image1, image2))._replace(road=road)
        if padding is None:
            return (info.flow, info) if return_info else info.flow
        padded_size = padding.padded_size(size)
        flow = padding.unpad_output(info.flow, padded_size)
        if not return_info:
            return flow
        gate = info.gate
        if gate is not None:  # its maps at the input size too (its per-sample counts as they are)
            gate = gate._replace(use_model=padding.unpad(gate.use_model), evidence=padding.unpad(gate.evidence))
        info = info._replace(flow=flow, weight=padding.unpad(info.weight), mask=padding.unpad(info.mask),
                             flow_model=padding.unpad(info.flow_model), gate=gate,
                             camera=info.camera.cropped(padding.left, padding.top, padding.right, padding.bottom))
        return flow, info
