"""Pictures of flows, errors and masks, as uint8 tensors and as PNG files.

- :func:`flow_to_color`: the Middlebury colour coding of Baker et al. (IJCV 2011; the 55-colour
  wheel of ``flowToColor`` / ``flow_vis``): hue = direction, saturation = magnitude relative to
  ``max_flow``; zero flow is white. At full saturation flow to the right is red (255, 0, 0),
  down yellow (255, 229, 0), left light blue (0, 209, 255), up violet (88, 0, 255), as in the
  Middlebury and KITTI figures.
- :func:`error_to_color`: a scalar map (e.g. end-point or photometric error) through an OpenCV
  colour map, from 0 to ``vmax``; pixels without a value in mid grey (:data:`NO_VALUE_RGB`), a
  colour the default map lacks (black would read as inferno's 0).
- :func:`kitti_error_to_color`: the KITTI devkit's logarithmic flow error colours
  (``FlowImage::errorImage`` with ``log_colors``): blue below 3 px and 5 %, orange to red above.
- :func:`overlay_mask`: a mask blended in colour onto an image.

The ``save_*_png`` functions write single images atomically (a temporary file in the same folder,
then ``os.replace``). OpenCV is imported inside the functions that use it.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import Tensor

from .._check import (batch_choices, check_data_range, check_device, check_finite, check_float_tensor, check_has_values,
                      check_image_range, check_number, check_positive, check_same_device, check_shape, to_device)
from .metrics import pow2_scale

__all__ = [
    "NO_VALUE_RGB",
    "make_colorwheel",
    "flow_to_color",
    "error_to_color",
    "KITTI_LOG_COLORS",
    "kitti_error_to_color",
    "overlay_mask",
    "save_flow_png",
    "save_error_png",
    "save_overlay_png",
]

# Colour-wheel segment lengths of Baker et al.: chosen so that perceptually similar hues get
# similar numbers of entries (red-yellow, yellow-green, green-cyan, cyan-blue, blue-magenta,
# magenta-red).
_WHEEL = (15, 6, 4, 11, 13, 6)

#: the colour of an error map's pixels without a value (invalid or not finite): mid grey, which
#: the default "inferno" map lacks (its nearest colour is 68 levels away in some channel), while
#: its 0 is near black, as black is in most maps (avoid grey maps such as "bone" or "cividis")
NO_VALUE_RGB = (128, 128, 128)


def make_colorwheel(*, dtype: torch.dtype = torch.float32, device: torch.device | None = None) -> Tensor:
    """The Middlebury colour wheel: (55, 3) RGB in 0..255, in ``dtype`` (a floating-point dtype, or
    an integer one that holds 0..255 such as ``torch.uint8``; else a TypeError names it) on
    ``device`` (None: the default device; else a device torch can place tensors on, or a
    ValueError or TypeError names it)."""
    if not isinstance(dtype, torch.dtype) or not (dtype.is_floating_point or (
            not dtype.is_complex and dtype != torch.bool and torch.iinfo(dtype).max >= 255)):
        # (torch.bool made a wheel of True and False, torch.int8 wrapped 255 to -1)
        raise TypeError(f"dtype: expected a floating-point torch.dtype or an integer one that holds 0..255 "
                        f"(torch.uint8), got {dtype!r}")
    device = check_device(device)
    ry, yg, gc, cb, bm, mr = _WHEEL

    def ramp(n: int) -> Tensor:
        return torch.floor(255.0 * torch.arange(n, dtype=torch.float64, device=device) / n)

    def full(n: int) -> Tensor:
        return torch.full((n,), 255.0, dtype=torch.float64, device=device)

    def zero(n: int) -> Tensor:
        return torch.zeros(n, dtype=torch.float64, device=device)

    segments = [
        (full(ry), ramp(ry), zero(ry)),            # red -> yellow
        (255 - ramp(yg), full(yg), zero(yg)),      # yellow -> green
        (zero(gc), full(gc), ramp(gc)),            # green -> cyan
        (zero(cb), 255 - ramp(cb), full(cb)),      # cyan -> blue
        (ramp(bm), zero(bm), full(bm)),            # blue -> magenta
        (full(mr), zero(mr), 255 - ramp(mr)),      # magenta -> red
    ]
    wheel = torch.cat([torch.stack(s, dim=1) for s in segments])
    return wheel.to(dtype=dtype, device=device)


def _as_batch(x: Tensor, name: str, channels: int | None) -> Tensor:
    """Accept (C, H, W) or (B, C, H, W) (and (H, W) for one channel); return (B, C, H, W)."""
    c = channels if channels is not None else "C"
    batched = x[None, None] if x.dim() == 2 and channels == 1 else x[None] if x.dim() == 3 else x
    if batched.dim() != 4 or (channels is not None and batched.shape[1] != channels):
        # (the shape that came, not the one with a batch dimension added)
        raise ValueError(f"{name}: expected shape ({c}, H, W) or (B, {c}, H, W), got {tuple(x.shape)}")
    check_shape(batched, name, ("B", c, "H", "W"))
    return batched


def flow_to_color(flow: Tensor, max_flow: float | Tensor | None = None, *,
                  valid: Tensor | None = None) -> Tensor:
    """Middlebury colour coding of a flow field.

    Args:
        flow: (B, 2, H, W) or (2, H, W), pixels, channel 0 = u; any finite magnitude (the
            radius is formed without overflow, also above 1.8e19 px in float32).
        max_flow: the magnitude shown at full saturation (finite, > 0; exactly, also for small
            values: no absolute epsilon is added, unlike RAFT's ``flow_viz``, which adds 1e-5 px):
            a float, a tensor of one or B values, or None for each sample's own largest valid
            magnitude (per sample; torchvision's ``flow_to_image`` takes one maximum over the whole
            batch). Longer vectors are drawn darker (×0.75), as in the reference code.
        valid: optional (B, 1, H, W) bool; invalid (and non-finite) pixels are black.

    Returns:
        (B, 3, H, W) uint8 RGB (a batch dimension is added for a (2, H, W) input).
    """
    check_float_tensor(flow, "flow")
    flow = _as_batch(flow, "flow", 2)
    B, _, H, W = flow.shape
    ok = torch.isfinite(flow).all(dim=1, keepdim=True)
    if valid is not None:
        if not isinstance(valid, Tensor) or valid.dtype != torch.bool:
            got = getattr(valid, "dtype", type(valid).__name__)
            raise TypeError(f"valid: expected a bool tensor, got {got}")
        valid = _as_batch(valid, "valid", 1)
        check_shape(valid, "valid", (B, 1, H, W))
        check_same_device({"flow": flow, "valid": valid})
        ok = ok & valid
    work = torch.float64 if flow.dtype == torch.float64 else torch.float32
    f = torch.where(ok, flow.detach().to(work), torch.zeros((), dtype=work, device=flow.device))
    u, v = f[:, 0:1], f[:, 1:2]
    # |f| with u and v divided by a power of two t (to below 2) before squaring: exact, so the
    # plain formula's value wherever that does not overflow, and finite for any finite flow
    t = pow2_scale(u, v, at_least_one=False)
    ut, vt = u / t, v / t
    rad = torch.sqrt(ut * ut + vt * vt) * t
    if max_flow is None:
        scale = rad.flatten(1).amax(dim=1)
    elif isinstance(max_flow, Tensor):
        if max_flow.dtype == torch.bool or max_flow.is_complex():
            raise TypeError(f"max_flow: expected a real tensor, got dtype {max_flow.dtype}")
        if max_flow.numel() not in (1, B):
            raise ValueError(f"max_flow: expected a tensor of {batch_choices(B)} elements (one per sample), "
                             f"got shape {tuple(max_flow.shape)}")
        check_finite(max_flow, "max_flow")  # NaN would draw every pixel black, a negative one white
        check_positive(max_flow, "max_flow")
        scale = to_device(max_flow.detach(), "max_flow", flow.device).to(work).reshape(-1).expand(B)
    else:
        scale = torch.full((B,), check_number(max_flow, "max_flow", positive=True), dtype=work,
                           device=flow.device)
    # max_flow exactly, as Middlebury's flowToColor (maxrad + MATLAB's eps, 2.2e-16): RAFT's and
    # flow_vis' absolute 1e-5 px drew a max_flow of 1e-4 px at 0.91 of full saturation. A sample
    # without motion (largest magnitude 0) is white whatever it is divided by; the smallest
    # normal number keeps a max_flow below the work dtype's range from dividing by 0.
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    scale = scale.clamp(min=torch.finfo(work).tiny).view(B, 1, 1, 1)
    u, v, rad = u / scale, v / scale, rad / scale

    # (in levels 0..255, not RAFT's 0..1: the wheel's integers stay exact, so a colour on the
    # wheel, such as the 88 of flow straight up at full saturation, is not floored to 87 by the
    # rounding of a division by 255 and a multiplication back)
    wheel = make_colorwheel(dtype=work, device=flow.device)
    n = wheel.shape[0]
    angle = torch.atan2(-v, -u) / torch.pi                     # (-1, 1]
    fk = (angle + 1.0) / 2.0 * (n - 1)
    k0 = torch.floor(fk).long().clamp(0, n - 1)
    k1 = torch.where(k0 + 1 == n, torch.zeros_like(k0), k0 + 1)
    frac = (fk - k0.to(work))
    col0 = wheel[k0.squeeze(1)].permute(0, 3, 1, 2)             # (B, 3, H, W)
    col1 = wheel[k1.squeeze(1)].permute(0, 3, 1, 2)
    col = (1 - frac) * col0 + frac * col1
    col = torch.where(rad <= 1, 255.0 - rad * (255.0 - col), col * 0.75)
    rgb = torch.floor(col).clamp(0, 255).to(torch.uint8)
    return torch.where(ok, rgb, torch.zeros_like(rgb))


def _colormap_lut(colormap: str) -> Tensor:
    """The 256 RGB entries of an OpenCV colour map: (256, 3) uint8."""
    import cv2
    import numpy as np

    if not isinstance(colormap, str):
        raise TypeError(f"colormap: expected an OpenCV colour map name such as 'inferno', got "
                        f"{type(colormap).__name__} {colormap!r}")
    code = getattr(cv2, f"COLORMAP_{colormap.upper()}", None)
    if code is None:
        raise ValueError(f"colormap: expected an OpenCV colour map name such as 'inferno', got {colormap!r}")
    ramp = np.arange(256, dtype=np.uint8).reshape(256, 1)
    bgr = cv2.applyColorMap(ramp, code).reshape(256, 3)
    return torch.from_numpy(np.ascontiguousarray(bgr[:, ::-1]))


def error_to_color(error: Tensor, vmax: float, *, valid: Tensor | None = None,
                   colormap: str = "inferno") -> Tensor:
    """A scalar map in colour: 0 -> the map's first colour, ``vmax`` and above -> its last.

    Args:
        error: (B, 1, H, W), (1, H, W) or (H, W), any unit (px, grey levels).
        vmax: the value shown at the top of the colour map (> 0), same unit.
        valid: optional (B, 1, H, W) bool; invalid and non-finite pixels have no value and are
            drawn mid grey (:data:`NO_VALUE_RGB`), not black: black is inferno's 0.
        colormap: an OpenCV colour map name ("inferno", "jet", "turbo", "viridis", ...).

    Returns:
        (B, 3, H, W) uint8 RGB.
    """
    check_float_tensor(error, "error")
    error = _as_batch(error, "error", 1)
    vmax = check_number(vmax, "vmax", positive=True)
    ok = torch.isfinite(error)
    if valid is not None:
        if not isinstance(valid, Tensor) or valid.dtype != torch.bool:
            got = getattr(valid, "dtype", type(valid).__name__)
            raise TypeError(f"valid: expected a bool tensor, got {got}")
        valid = _as_batch(valid, "valid", 1)
        check_shape(valid, "valid", tuple(error.shape))
        check_same_device({"error": error, "valid": valid})
        ok = ok & valid
    # (in float64 where the device has it: in float32 a vmax beyond its range raised in the clamp,
    # and one below its smallest number divided 0 by 0 into a NaN index)
    work = torch.float32 if error.device.type == "mps" else torch.float64
    e = torch.where(ok, error.detach().to(work), torch.zeros((), dtype=work, device=error.device))
    index = torch.round(e.clamp(0, float(vmax)) / float(vmax) * 255.0).long()
    lut = _colormap_lut(colormap).to(error.device)
    rgb = lut[index.squeeze(1)].permute(0, 3, 1, 2)
    no_value = torch.tensor(NO_VALUE_RGB, dtype=torch.uint8, device=error.device).view(1, 3, 1, 1)
    return torch.where(ok, rgb, no_value)


#: the KITTI devkit's error colours (``LC`` in its C++ code): (lower, upper, R, G, B) for the
#: normalised error min(e / 3 px, 20 e / |F_gt|) in [lower, upper); 1 is Fl's outlier threshold
#: (3 px and 5 %), below it blues, above it oranges and reds
KITTI_LOG_COLORS = ((0.0, 0.0625, 49, 54, 149), (0.0625, 0.125, 69, 117, 180), (0.125, 0.25, 116, 173, 209),
                    (0.25, 0.5, 171, 217, 233), (0.5, 1.0, 224, 243, 248), (1.0, 2.0, 254, 224, 144),
                    (2.0, 4.0, 253, 174, 97), (4.0, 8.0, 244, 109, 67), (8.0, 16.0, 215, 48, 39),
                    (16.0, float("inf"), 165, 0, 38))


def kitti_error_to_color(flow_est: Tensor, flow_gt: Tensor, valid: Tensor, *,
                         valid_noc: Tensor | None = None) -> Tensor:
    """The KITTI devkit's error map of a flow in log colours (its ``errorImage`` with
    ``log_colors``, as on the KITTI flow benchmark's pages).

    Each valid pixel is coloured by n = min(e / 3, 20 e / |F_gt|), e its end-point error in px,
    through :data:`KITTI_LOG_COLORS` (n below 1, blue: within both of Fl's thresholds, 3 px and
    5 %); with ``valid_noc``, pixels valid in ``valid`` but not in it (occluded) have their colour
    halved, as the devkit does with its noc and occ ground truths. A zero ground-truth flow gives
    n = e / 3 (the devkit's min with 0 / 0 gives the same). Unlike the devkit, each pixel keeps
    its own colour (it draws each as a 3 x 3 block, the border rows and columns black), an n of
    1e9 and above is the last colour (the devkit leaves it black), and an estimate that is not
    finite at a valid pixel is the last colour (an infinite error; the devkit's NaN matched no
    colour and left it black, a good result's look). Invalid pixels are black, as in the devkit.

    Args:
        flow_est, flow_gt: (B, 2, H, W) or (2, H, W) px; ``flow_gt`` finite where ``valid``.
        valid: (B, 1, H, W) or (1, H, W) bool, the ground truth's valid pixels (KITTI's occ).
        valid_noc: optional, the same shape: the non-occluded ground truth's valid pixels.

    Returns:
        (B, 3, H, W) uint8 RGB.
    """
    check_float_tensor(flow_est, "flow_est")
    check_float_tensor(flow_gt, "flow_gt")
    est, gt = _as_batch(flow_est, "flow_est", 2), _as_batch(flow_gt, "flow_gt", 2)
    dims = check_shape(est, "flow_est", ("B", 2, "H", "W"))
    check_shape(gt, "flow_gt", ("B", 2, "H", "W"), dims)
    masks = {}
    for name, m in (("valid", valid), ("valid_noc", valid_noc)):
        if m is None and name == "valid_noc":  # (valid is required: a None is named below)
            continue
        if not isinstance(m, Tensor) or m.dtype != torch.bool:
            raise TypeError(f"{name}: expected a bool tensor, got {getattr(m, 'dtype', type(m).__name__)}")
        masks[name] = _as_batch(m, name, 1)
        check_shape(masks[name], name, ("B", 1, "H", "W"), dims)
    check_same_device({"flow_est": est, "flow_gt": gt, **masks})
    ok = masks["valid"]
    zero = torch.zeros((), dtype=torch.float64, device=est.device)
    g = torch.where(ok, gt.detach().to(torch.float64), zero)
    check_finite(g, "flow_gt")  # (at its valid pixels: g is 0 elsewhere)
    e_vec = est.detach().to(torch.float64) - g
    finite = torch.isfinite(e_vec).all(dim=1, keepdim=True)
    e_vec = torch.where(finite, e_vec, zero)
    t = pow2_scale(e_vec[:, :1], e_vec[:, 1:], at_least_one=False)
    e = torch.linalg.vector_norm(e_vec / t, dim=1, keepdim=True) * t
    mag = torch.linalg.vector_norm(g, dim=1, keepdim=True)
    n = torch.where(mag > 0, torch.minimum(e / 3.0, 20.0 * e / torch.where(mag > 0, mag, 1.0)), e / 3.0)
    n = torch.where(finite, n, torch.full_like(n, float("inf")))
    lower = torch.tensor([c[0] for c in KITTI_LOG_COLORS], dtype=torch.float64, device=est.device)
    table = torch.tensor([c[2:] for c in KITTI_LOG_COLORS], dtype=torch.uint8, device=est.device)
    index = (torch.bucketize(n, lower, right=True) - 1).clamp(0, len(KITTI_LOG_COLORS) - 1)
    rgb = table[index.squeeze(1)].permute(0, 3, 1, 2)
    if "valid_noc" in masks:
        rgb = torch.where(masks["valid_noc"], rgb, rgb // 2)  # (the devkit: uint8 *= 0.5, truncated)
    return torch.where(ok, rgb, torch.zeros_like(rgb))


def overlay_mask(image: Tensor, mask: Tensor, *, color: tuple[int, int, int] = (0, 255, 0),
                 alpha: float = 0.5, data_range: float = 255.0) -> Tensor:
    """Blend ``color`` into ``image`` where ``mask`` is True.

    Args:
        image: (B, C, H, W) or (C, H, W), C = 3 (RGB) or 1 (grey), finite values in [0, data_range]
            (up to 1 %; ValueError naming ``image`` otherwise, and for a 0..1 image passed with
            ``data_range=255``).
        data_range: the images' maximum (finite, > 0): 255.0 for 0-255 images, 1.0 for 0-1 images.
        mask: (B, 1, H, W) or (1, H, W) bool.
        color: RGB, three numbers in 0..255 (ValueError outside: not clamped).
        alpha: its weight inside the mask, a number in [0, 1].

    Returns:
        (B, 3, H, W) uint8 RGB: (1 - alpha) * image + alpha * color inside the mask, the image elsewhere.
    """
    check_float_tensor(image, "image")
    image = _as_batch(image, "image", None)
    if image.shape[1] not in (1, 3):
        raise ValueError(f"image: expected 1 or 3 channels, got shape {tuple(image.shape)}")
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise TypeError(f"mask: expected a bool tensor, got {getattr(mask, 'dtype', type(mask).__name__)}")
    mask = _as_batch(mask, "mask", 1)
    B, _, H, W = image.shape
    check_shape(mask, "mask", (B, 1, H, W))
    check_same_device({"image": image, "mask": mask})
    alpha = check_number(alpha, "alpha")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha: expected a value in [0, 1], got {alpha!r}")
    color = _check_color(color)
    data_range = check_data_range(data_range)
    check_finite(image, "image")  # a NaN pixel would be drawn as 0, black, as if it were one
    # a 0-255 image passed with data_range=1.0 was drawn white, a 0-1 one at 255 black
    check_image_range(image, "image", data_range)
    img = image.detach().float().expand(B, 3, H, W) * (255.0 / data_range)
    c = torch.tensor(color, device=image.device).view(1, 3, 1, 1)
    out = torch.where(mask, (1 - alpha) * img + alpha * c, img)
    return torch.round(out).clamp(0, 255).to(torch.uint8)


def _check_color(color: object) -> tuple[float, float, float]:
    """``color``: three numbers (R, G, B) in 0..255 (a value outside is refused, not clamped)."""
    if isinstance(color, (str, bytes)) or not hasattr(color, "__len__"):
        raise TypeError(f"color: expected an (R, G, B) triple of numbers in 0..255, got {type(color).__name__} {color!r}")
    if len(color) != 3:
        raise ValueError(f"color: expected an (R, G, B) triple, got {color!r}")
    rgb = tuple(check_number(x, "color") for x in color)
    if not all(0.0 <= x <= 255.0 for x in rgb):
        raise ValueError(f"color: expected values in 0..255, got {color!r}")
    return rgb


def _write_png(path: str | os.PathLike, rgb: Tensor, name: str) -> Path:
    """Write one (1, 3, H, W) or (3, H, W) uint8 RGB image as PNG, atomically; ``name`` is the
    argument the image came from (for the error of a batch above 1). A ``path`` whose suffix is not
    ``.png`` is a ValueError (PNG bytes in a file named ``.jpg``: tools that go by the suffix take
    it for a broken JPEG)."""
    import cv2

    from ..io.atomic import write_bytes

    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a str or os.PathLike, got {type(path).__name__}")
    if Path(path).suffix.lower() != ".png":
        raise ValueError(f"path: expected a .png file (this writes PNG), got {str(path)!r}; for another format "
                         f"write the colours with fsof_torch.write_image (e.g. write_image(path, flow_to_color(flow)[0]))")
    check_has_values(rgb, name, "to write")  # (the colours of a meta tensor are shapes only)
    if rgb.dim() == 4:
        if rgb.shape[0] != 1:
            raise ValueError(f"{name}: expected a single image (batch 1) to save, got batch {rgb.shape[0]}")
        rgb = rgb[0]
    bgr = rgb.permute(1, 2, 0).flip(-1).contiguous().cpu().numpy()
    ok, data = cv2.imencode(".png", bgr)
    if not ok:
        raise OSError(f"path: OpenCV could not encode a PNG for {str(path)!r}")
    return write_bytes(path, data.tobytes())


def save_flow_png(path: str | os.PathLike, flow: Tensor, *, max_flow: float | None = None,
                  valid: Tensor | None = None) -> Path:
    """Save one flow ((2, H, W) or (1, 2, H, W), pixels) in Middlebury colours as an RGB PNG.

    See :func:`flow_to_color` for ``max_flow`` and ``valid``. Returns the path.
    """
    return _write_png(path, flow_to_color(flow, max_flow, valid=valid), "flow")


def save_error_png(path: str | os.PathLike, error_map: Tensor, vmax: float, *,
                   valid: Tensor | None = None, colormap: str = "inferno") -> Path:
    """Save one scalar map ((H, W), (1, H, W) or (1, 1, H, W)) through a colour map as PNG.

    See :func:`error_to_color`. Returns the path.
    """
    check_float_tensor(error_map, "error_map")
    error_map = _as_batch(error_map, "error_map", 1)
    return _write_png(path, error_to_color(error_map, vmax, valid=valid, colormap=colormap), "error_map")


def save_overlay_png(path: str | os.PathLike, image: Tensor, mask: Tensor, *,
                     color: tuple[int, int, int] = (0, 255, 0), alpha: float = 0.5,
                     data_range: float = 255.0) -> Path:
    """Save one image ((C, H, W) or (1, C, H, W)) with ``mask`` blended in colour, as PNG.

    See :func:`overlay_mask`. Returns the path.
    """
    return _write_png(path, overlay_mask(image, mask, color=color, alpha=alpha, data_range=data_range), "image")
