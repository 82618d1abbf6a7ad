"""What flow networks take and return, written once: the output structures the refiner walks,
the input conventions of ptlflow and torchvision, and RAFT-style padding.

**Output structures.** Whatever a network returns is refined level by level at its own
resolution, and comes back in the same containers:

- a tensor (B, 2, H, W);
- a list, tuple or NamedTuple of flows: RAFT's per-iteration flows, a ``(flow_low, flow_up)``
  pair, an ARFlow/PWC-Lite pyramid (levels may differ in size);
- a dict: the values under ``flow_keys`` (:data:`DEFAULT_FLOW_KEYS`) are forward flows (tensors,
  ptlflow's 5-D stacks (B, N, 2, H, W) with N ≥ 1, lists); every other value (backward flows,
  occlusions, features) passes through as the same object.

**Input contracts** (what a network is called with):

- *ptlflow*: ``model(inputs)`` with ``inputs = {"images": (B, 2, 3, H, W)}``, BGR (OpenCV's
  order) in [0, 1]; it returns ``{"flows": (B, 1, 2, H, W), ...}`` at the input size. Its RAFT
  models pad the images internally to a multiple of 8 (replicating the border, on both sides)
  and add ``"flow_small"`` (B, 2, Hp/8, Wp/8): the flow at 1/8 of the *padded* size, in pixels
  of that grid (in eval mode; in training mode ``"flow_preds"`` instead, every iteration's flow
  at the input size). :func:`ptlflow_inputs` and :func:`images_from_ptlflow` convert (one pair: the
  flows of a multi-frame input, N > 2, are of the pair its model picks, so it is refused).
- *torchvision*: ``raft_large()(image1, image2)`` with (B, 3, H, W) RGB in [-1, 1] and H, W
  divisible by 8; it returns a list of (B, 2, H, W), one per update, the last the estimate.
- *RAFT* (the authors' code) and :class:`fsof_torch.TinyRAFT`: (B, 3, H, W) RGB on 0..255; a
  list of flows (RAFT's ``test_mode``: ``(flow_low, flow_up)``).

**Padding** (RAFT's ``InputPadder``): H and W are padded up to a multiple of the stride; the
``"sintel"`` rule splits the padding between both sides (ptlflow's ``pad_two_side=True``), the
``"kitti"`` rule puts the rows at the bottom: 375×1242 becomes 376×1248 with (left, right, top,
bottom) = (3, 3, 0, 1). A pixel (u, v) of the image is (u + left, v + top) of the padded one, so
the camera's principal point moves by (left, top) (:meth:`fsof_torch.Camera.padded`), and a
level at 1/8 of the padded size has the K of the padded camera scaled by 1/8.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import torch
import torch.nn.functional as F
from torch import Tensor

from .._check import (autocast_off, batch_choices, check_data_range, check_float_tensor, check_image_range, check_int,
                      check_same_device, check_shape, check_size, same_mapping, tracing)
from ..geometry.camera import Camera

__all__ = [
    "DEFAULT_FLOW_KEYS",
    "InputPadder",
    "PAD_MODES",
    "Padding",
    "check_flow_keys",
    "check_levels",
    "collect_flows",
    "finest_flow",
    "images_from_ptlflow",
    "is_ptlflow_inputs",
    "map_flows",
    "ptlflow_inputs",
    "refiner_images",
]

#: dict keys refined by default: the forward flows of ARFlow/PWC-Lite, ptlflow, RAFT wrappers.
#: Backward flows (``flows_bw``, ``flows_21``) are left alone: the forward model does not apply.
DEFAULT_FLOW_KEYS = ("flow", "flows", "flows_fw", "flows_12", "flow_12", "flow_preds",
                     "flow_up", "flow_low", "flow_small", "flow_final", "flow_init")


# -- output structures ------------------------------------------------------------------------

def check_flow_keys(flow_keys: object, name: str = "flow_keys") -> tuple[str, ...]:
    """The dict keys of forward flows: one key or a sequence of keys -> a tuple of str, read once
    (a generator is consumed here, not seen empty later). None is an error, not the default:
    pass :data:`DEFAULT_FLOW_KEYS`, or leave the argument out."""
    if isinstance(flow_keys, str):
        return (flow_keys,)
    if flow_keys is not None and isinstance(flow_keys, Iterable) and not isinstance(flow_keys, (Mapping, bytes, Tensor)):
        keys = tuple(flow_keys)
        if all(isinstance(k, str) for k in keys):
            return keys
        flow_keys = keys
    raise TypeError(f"{name}: expected a key or a sequence of keys (str) of the forward flows "
                    f"(default DEFAULT_FLOW_KEYS), got {type(flow_keys).__name__} {flow_keys!r}")


def _check_flow(x: Tensor, name: str) -> None:
    stack = x.dim() == 5
    if not ((x.dim() == 4 and x.shape[1] == 2) or (stack and x.shape[2] == 2)):
        raise ValueError(f"{name}: expected a flow of shape (B, 2, H, W) or (B, N, 2, H, W), "
                         f"got {tuple(x.shape)}")
    check_float_tensor(x, name)
    if stack and x.shape[1] == 0:
        raise ValueError(f"{name}: expected at least one prediction in the (B, N, 2, H, W) stack, "
                         f"got N = 0 (shape {tuple(x.shape)})")
    if x.shape[0] == 0 or x.shape[-1] == 0 or x.shape[-2] == 0:
        raise ValueError(f"{name}: expected B, H and W of at least 1, got shape {tuple(x.shape)}")


def collect_flows(output: Any, name: str = "flow",
                  flow_keys: tuple[str, ...] = DEFAULT_FLOW_KEYS) -> list[tuple[str, Tensor]]:
    """Every forward flow of a network's output, in order, as ``(name, flow)`` pairs.

    ``name`` locates the flow for messages (``flow['flows']``, ``flow[2]``). Shapes are
    validated: each flow is (B, 2, H, W) or a stack (B, N, 2, H, W) with N ≥ 1, float, with
    no empty dimension. A dict contributes only its ``flow_keys`` values.
    """
    out: list[tuple[str, Tensor]] = []
    _collect(output, name, check_flow_keys(flow_keys), out)
    return out


def _collect(obj: Any, name: str, flow_keys: tuple[str, ...], out: list[tuple[str, Tensor]]) -> None:
    if isinstance(obj, Tensor):
        _check_flow(obj, name)
        out.append((name, obj))
    elif isinstance(obj, (list, tuple)):
        if len(obj) == 0:
            raise ValueError(f"{name}: expected a non-empty list of flows, got an empty {type(obj).__name__}")
        for i, item in enumerate(obj):
            _collect(item, f"{name}[{i}]", flow_keys, out)
    elif isinstance(obj, Mapping):
        for key, value in obj.items():
            if key in flow_keys:
                _collect(value, f"{name}[{key!r}]", flow_keys, out)
    else:
        raise TypeError(f"{name}: expected a flow tensor (B, 2, H, W), a list/tuple of them or a dict, "
                        f"got {type(obj).__name__}")


def map_flows(output: Any, fn: Callable[[Tensor], Tensor],
              flow_keys: tuple[str, ...] = DEFAULT_FLOW_KEYS) -> Any:
    """The structure with every flow ``f`` replaced by ``fn(f)`` ((B, 2, H, W) in and out).

    Containers keep their type (list, tuple, NamedTuple, dict subclass with its state, such as a
    ``defaultdict``'s ``default_factory``); a 5-D stack is mapped prediction by prediction; dict
    values outside ``flow_keys`` are the same objects. Anything else where a flow is expected
    raises TypeError naming its place (``output``, ``output['flows']``, ``output[1]``).
    """
    return _map_flows(output, fn, check_flow_keys(flow_keys), "output")


def _map_flows(output: Any, fn: Callable[[Tensor], Tensor], flow_keys: tuple[str, ...], name: str) -> Any:
    if isinstance(output, Tensor):
        if output.dim() == 5:  # ptlflow stack (B, N, 2, H, W): each prediction on its own
            flows = [fn(output[:, n]) for n in range(output.shape[1])]
            with autocast_off(output):  # (autocast's stack refuses a half dtype other than its own)
                return torch.stack(flows, dim=1)
        return fn(output)
    if isinstance(output, tuple) and hasattr(output, "_fields"):  # a NamedTuple
        return type(output)(*(_map_flows(v, fn, flow_keys, f"{name}[{i}]") for i, v in enumerate(output)))
    if isinstance(output, (list, tuple)):
        return type(output)(_map_flows(v, fn, flow_keys, f"{name}[{i}]") for i, v in enumerate(output))
    if isinstance(output, Mapping):
        return same_mapping(output, {k: (_map_flows(v, fn, flow_keys, f"{name}[{k!r}]") if k in flow_keys else v)
                                      for k, v in output.items()})
    raise TypeError(f"{name}: expected a flow tensor (B, 2, H, W), a list/tuple of them or a dict, "
                    f"got {type(output).__name__}")


#: dict keys of a start or a coarse estimate, not the network's answer (RAFT's ``flow_init`` is
#: its warm start): a flow of the same size under another key is the one to fit.
_SECONDARY_KEYS = ("flow_init", "flow_low", "flow_small")


def finest_flow(flows: list[tuple[str, Tensor]]) -> tuple[str, Tensor]:
    """The flow to fit, from :func:`collect_flows`'s pairs: the largest resolution; among equals
    one not under a dict's ``flow_init``, ``flow_low`` or ``flow_small`` (a warm start, a coarse
    estimate), then the last (RAFT's final iterate: a list's last, a dict's last in its order);
    of a stack (B, N, 2, H, W) its last prediction. Returns ``(name, (B, 2, H, W))``."""
    best = None
    for name, f in flows:
        f4 = f[:, -1] if f.dim() == 5 else f
        # (the dict keys are in the names collect_flows gives: flow['flow_init'], flow['flows'][0])
        rank = (f4.shape[-2] * f4.shape[-1], not any(f"[{k!r}]" in name for k in _SECONDARY_KEYS))
        if best is None or rank >= best[0]:
            best = (rank, name, f4)
    if best is None:
        raise ValueError("flow: expected at least one flow, got none")
    return best[1], best[2]


def check_levels(flows: list[tuple[str, Tensor]], finest_name: str, finest: Tensor) -> None:
    """Every flow of :func:`collect_flows`'s pairs against the finest (:func:`finest_flow`'s
    ``finest_name, finest``): its batch and its device, as each level is refined with the finest's
    road motion, on its device. A ValueError names the level that differs."""
    for name, f in flows:
        if f.shape[0] != finest.shape[0]:
            raise ValueError(f"{name}: expected batch {finest.shape[0]} (as the finest flow), got shape {tuple(f.shape)}")
        if f.device != finest.device:
            raise ValueError(f"{name}: expected the device of the finest flow {finest_name} ({finest.device}), "
                             f"got {f.device}")


def _map_tensors(obj: Any, fn: Callable[[Tensor], Tensor]) -> Any:
    """Every tensor of a nested structure through ``fn`` (containers keep their type)."""
    if isinstance(obj, Tensor):
        return fn(obj)
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):
        return type(obj)(*(_map_tensors(v, fn) for v in obj))
    if isinstance(obj, (list, tuple)):
        return type(obj)(_map_tensors(v, fn) for v in obj)
    if isinstance(obj, Mapping):
        return same_mapping(obj, {k: _map_tensors(v, fn) for k, v in obj.items()})
    return obj


# -- ptlflow's inputs ---------------------------------------------------------------------------

def is_ptlflow_inputs(obj: object) -> bool:
    """True for a ptlflow input dict (a mapping with an ``"images"`` entry)."""
    return isinstance(obj, Mapping) and "images" in obj


def _ptlflow_images(inputs: Mapping[str, Any], name: str = "inputs") -> Tensor:
    if not isinstance(inputs, Mapping):
        raise TypeError(f"{name}: expected ptlflow's dict {{'images': (B, 2, 3, H, W)}}, got {type(inputs).__name__}")
    if "images" not in inputs:
        raise TypeError(f"{name}: expected ptlflow's dict {{'images': (B, 2, 3, H, W)}}, got a "
                        f"{type(inputs).__name__} without 'images' (keys {list(inputs)!r})")
    images = inputs["images"]
    check_float_tensor(images, f"{name}['images']")
    if images.dim() != 5 or images.shape[1] != 2 or images.shape[2] != 3:
        # (a multi-frame input's flows are of the pair its model picks: ptlflow's VideoFlow takes 3
        # frames and returns the flow of the middle one to the last, not of the first two)
        several = images.dim() == 5 and images.shape[1] > 2 and images.shape[2] == 3
        raise ValueError(f"{name}['images']: expected shape (B, 2, 3, H, W) (two BGR images in [0, 1]), "
                         f"got {tuple(images.shape)}" + (
                             f": the pair of a {images.shape[1]}-frame input is the model's choice (VideoFlow's "
                             f"flows are of its middle frame to the next); refine its output with "
                             f"refine_flow(..., images=(image1, image2)), the two frames of its flow" if several else ""))
    if images.shape[0] == 0 or images.shape[-1] == 0 or images.shape[-2] == 0:
        raise ValueError(f"{name}['images']: expected B, H and W of at least 1, got {tuple(images.shape)}")
    if not tracing() and images.device.type != "meta":
        lo, hi = float(images.min()), float(images.max())
        if not (lo >= 0.0 and hi <= 1.0):
            raise ValueError(f"{name}['images']: expected BGR values in [0, 1] (ptlflow's convention), "
                             f"got the range [{lo:.4g}, {hi:.4g}]")
    return images


def ptlflow_inputs(image1: Tensor, image2: Tensor, *, data_range: float = 255.0) -> dict[str, Tensor]:
    """ptlflow's input dict from two RGB images: ``{"images": (B, 2, 3, H, W)}``, BGR in [0, 1].

    Args:
        image1, image2: (B, 3, H, W) RGB on 0..``data_range``, of one shape and on one device
            (else a ValueError naming ``image2``), B, H and W at least 1 (finite;
            checked as the refiner checks its images: 0..1 images with the default
            ``data_range=255.0`` are an error, not near-black input). Values the check lets
            through beyond the range (up to 1 % of it, a resize's overshoot) are clipped to
            [0, 1], ptlflow's range, which :func:`images_from_ptlflow` and the refiner check.
        data_range: the images' maximum, 255.0 for 0..255 images, 1.0 for 0..1.
    """
    data_range = check_data_range(data_range)
    for name, im in (("image1", image1), ("image2", image2)):
        check_float_tensor(im, name)
        check_shape(im, name, ("B", 3, "H", "W"), nonempty=("B", "H", "W"))
    if image1.shape != image2.shape:
        raise ValueError(f"image2: expected the shape of image1 {tuple(image1.shape)}, got {tuple(image2.shape)}")
    check_same_device({"image1": image1, "image2": image2})  # (torch.stack's error names neither)
    for name, im in (("image1", image1), ("image2", image2)):
        check_image_range(im, name, data_range)
    with autocast_off(image1):  # (autocast's stack refuses a half dtype other than its own)
        pair = (torch.stack([image1, image2], dim=1) / float(data_range)).clamp(0.0, 1.0)
    return {"images": pair.flip(2)}  # RGB -> BGR along the channel axis


def images_from_ptlflow(inputs: Mapping[str, Any], name: str = "inputs") -> tuple[Tensor, Tensor]:
    """The two images of a ptlflow input dict as (B, 3, H, W) RGB on 0..255 (the range
    the refiner's photometric fit and freespace detection read); ``name``: the argument the
    errors name."""
    images = _ptlflow_images(inputs, name)
    rgb = images[:, :2].flip(2) * 255.0
    return rgb[:, 0], rgb[:, 1]


def refiner_images(images: Any, finest: Tensor) -> tuple[Tensor, Tensor] | None:
    """The refiner's ``images``: a pair (image1, image2) (B or 1, 1 or 3, H, W) on 0..255, or
    ptlflow's input dict, checked against its finest flow ``finest`` (B, 2, H, W) (their device,
    size and range), detached and expanded to its batch; None stays None."""
    if images is None:
        return None
    if is_ptlflow_inputs(images):
        images = images_from_ptlflow(images, "images")
    if not isinstance(images, (tuple, list)) or len(images) != 2:
        raise TypeError(f"images: expected a pair (image1, image2), got {type(images).__name__}"
                        + (f" of {len(images)}" if isinstance(images, (tuple, list)) else ""))
    B, _, H, W = finest.shape
    for i, im in enumerate(images):
        check_float_tensor(im, f"images[{i}]")
        if im.device != finest.device:
            raise ValueError(f"images[{i}]: expected the device of the flow ({finest.device}), got {im.device}")
        if im.dim() != 4 or im.shape[0] not in (1, B) or tuple(im.shape[-2:]) != (H, W):
            raise ValueError(f"images[{i}]: expected shape ({batch_choices(B)}, C, {H}, {W}) (the finest flow's size), "
                             f"got {tuple(im.shape)}")
        if im.shape[1] not in (1, 3) or im.shape[1] != images[0].shape[1]:
            raise ValueError(f"images[{i}]: expected 1 (grey) or 3 (RGB) channels"
                             + ("" if i == 0 else ", as images[0] has") + f", got shape {tuple(im.shape)}"
                             + ("" if i == 0 else f" (images[0]: {tuple(images[0].shape)})"))
        check_image_range(im, f"images[{i}]", 255.0)
    return tuple(im.detach().expand(B, -1, -1, -1) for im in images)


# -- padding ------------------------------------------------------------------------------------

#: How :meth:`Padding.pad` extends an image (``F.pad``'s modes).
PAD_MODES = ("replicate", "reflect", "constant")


@dataclass(frozen=True)
class Padding:
    """Whole pixels added at each side of an image (``F.pad``'s (left, right, top, bottom)).

    A pixel (u, v) of the image is (u + left, v + top) of the padded image. Each side is an int
    >= 0 (a NumPy integer too; a bool or a float raises TypeError).
    """

    left: int = 0
    right: int = 0
    top: int = 0
    bottom: int = 0

    def __post_init__(self) -> None:
        for name in ("left", "right", "top", "bottom"):  # (NumPy integers too, stored as int)
            object.__setattr__(self, name, check_int(getattr(self, name), name, minimum=0))

    @property
    def is_zero(self) -> bool:
        return self.left == self.right == self.top == self.bottom == 0

    def padded_size(self, size: tuple[int, int]) -> tuple[int, int]:
        """(H, W) of the image -> (H, W) of the padded image."""
        return size[0] + self.top + self.bottom, size[1] + self.left + self.right

    def pad(self, x: Tensor, *, mode: str = "replicate") -> Tensor:
        """Pad the last two dimensions of ``x`` (H, W) with any leading dimensions: none, (C, H, W),
        (B, C, H, W), ptlflow's (B, 2, 3, H, W). ``mode``: ``"replicate"`` (RAFT's, for images),
        ``"reflect"`` (a side padded by less than the image's size there, else a ValueError) or
        ``"constant"`` (zeros); a bool mask is always padded with False. An image without rows or
        columns (H or W 0) is a ValueError naming ``x``."""
        if mode not in PAD_MODES:
            raise ValueError(f"mode: expected one of {PAD_MODES}, got {mode!r}")
        if not isinstance(x, Tensor):
            raise TypeError(f"x: expected a tensor (..., H, W), got {type(x).__name__}")
        if x.dim() < 2:
            raise ValueError(f"x: expected at least 2 dimensions (..., H, W), got shape {tuple(x.shape)}")
        if min(x.shape[-2:]) < 1:  # (no pixel to replicate or reflect, nor an image to pad with zeros)
            raise ValueError(f"x: expected an image with H, W >= 1, got shape {tuple(x.shape)}")
        if self.is_zero:
            return x
        pads = (self.left, self.right, self.top, self.bottom)
        if mode == "constant" or x.dtype == torch.bool:
            return F.pad(x, pads)
        H, W = x.shape[-2:]
        if mode == "reflect" and (max(self.left, self.right) >= W or max(self.top, self.bottom) >= H):
            # (F.pad's reflection does not repeat the edge: it has H - 1 rows and W - 1 columns to mirror)
            raise ValueError(f"x: mode='reflect' pads a side by less than the image's size there, got (H, W) = "
                             f"({H}, {W}) and {self}; use mode='replicate' or 'constant'")
        # (F.pad's replicate and reflect pad H and W of a (C, H, W) or (B, C, H, W) tensor only)
        if x.dim() == 2:
            return F.pad(x[None], pads, mode=mode)[0]
        lead = x.shape[:-3] if x.dim() > 4 else None
        y = x.reshape(-1, *x.shape[-3:]) if lead is not None else x
        y = F.pad(y, pads, mode=mode)
        return y.reshape(*lead, *y.shape[-3:]) if lead is not None else y

    def unpad(self, x: Tensor) -> Tensor:
        """Crop the padding off the last two dimensions of ``x`` (a view). ``x`` is a tensor
        (..., H, W) larger than the padding (H > top + bottom, W > left + right), else a
        ValueError naming ``x`` (not an empty crop)."""
        if not isinstance(x, Tensor):
            raise TypeError(f"x: expected a tensor (..., H, W), got {type(x).__name__}")
        if x.dim() < 2:
            raise ValueError(f"x: expected at least 2 dimensions (..., H, W), got shape {tuple(x.shape)}")
        H, W = x.shape[-2:]
        if H <= self.top + self.bottom or W <= self.left + self.right:
            raise ValueError(f"x: expected a padded image larger than the padding {self}, got (H, W) = ({H}, {W})")
        return x[..., self.top:H - self.bottom, self.left:W - self.right]

    def camera(self, camera: Camera) -> Camera:
        """The camera of the padded image (:meth:`fsof_torch.Camera.padded`)."""
        return camera.padded(self.left, self.top, self.right, self.bottom)

    def unpad_output(self, output: Any, padded_size: tuple[int, int]) -> Any:
        """Crop every tensor of a network's output whose last two dimensions are the padded size
        (flows, occlusions, confidences); coarser tensors (``flow_small``) stay on their grid."""
        if self.is_zero:
            return output
        return _map_tensors(output, lambda t: self.unpad(t) if tuple(t.shape[-2:]) == tuple(padded_size) else t)


class InputPadder:
    """RAFT's padding rule: pad H and W up to a multiple of ``stride``.

    Args:
        stride: the multiple, an int >= 1 (8 for RAFT and torchvision's RAFT; some ptlflow models
            need 32 or 64).
        mode: ``"sintel"`` (the padding split between both sides, the larger half right/bottom;
            ptlflow's ``pad_two_side=True``) or ``"kitti"`` (columns split, all rows at the bottom).
        pad_mode: how images are extended, ``"replicate"`` (RAFT's), ``"reflect"`` (images
            larger than the padding on each side) or ``"constant"`` (zeros).

    Example:
        >>> InputPadder(8, mode="kitti").padding((375, 1242))
        Padding(left=3, right=3, top=0, bottom=1)
    """

    def __init__(self, stride: int = 8, *, mode: str = "sintel", pad_mode: str = "replicate") -> None:
        stride = check_int(stride, "stride", minimum=1)  # (NumPy integers too; not a bool)
        if mode not in ("sintel", "kitti"):
            raise ValueError(f"mode: expected 'sintel' or 'kitti', got {mode!r}")
        if pad_mode not in PAD_MODES:
            raise ValueError(f"pad_mode: expected 'replicate', 'constant' or 'reflect', got {pad_mode!r}")
        self.stride = stride
        self.mode = mode
        self.pad_mode = pad_mode

    def padding(self, size: tuple[int, int]) -> Padding:
        """The :class:`Padding` of an image of ``size = (H, W)``: two ints >= 1 (a tuple, a list
        or a ``torch.Size`` of two). Unlike RAFT's ``InputPadder(dims)``, which takes the whole
        shape, an image's shape is refused: pass ``image.shape[-2:]`` (a (B, C, H, W) shape read as
        (H, W) would pad by B and C)."""
        if isinstance(size, (tuple, list, torch.Size)) and len(size) > 2:
            raise TypeError(f"size: expected (H, W), got {tuple(size)!r}; for an image's shape pass "
                            f"image.shape[-2:]")
        H, W = check_size(size, "size")
        ph, pw = (-H) % self.stride, (-W) % self.stride
        if self.mode == "sintel":
            return Padding(pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)
        return Padding(pw // 2, pw - pw // 2, 0, ph)

    def __repr__(self) -> str:
        return f"InputPadder({self.stride}, mode={self.mode!r}, pad_mode={self.pad_mode!r})"
