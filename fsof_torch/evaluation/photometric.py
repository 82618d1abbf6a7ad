"""Photometric error of a flow: how well the second image, warped back by the flow, matches the first.

    error(p) = ρ( I_1(p), I_2(p + F(p)) ),   F the forward flow from I_1 to I_2 (pixels)

Four kinds of ρ (DESIGN.md §6):

- ``"l1"``: mean over channels of |I_1 − Î_1|, on the 0–255 scale whatever ``data_range`` the
  images come in (the paper's table of RAFT/ARFlow photometric errors).
- ``"ssim"``: the structural dissimilarity (1 − SSIM) / 2 in [0, 1], mean over channels, from
  ``kornia.metrics.ssim`` (Gaussian window of σ = 1.5, ``window`` taps, reflect padding).
- ``"census"``: the census distance (DESIGN.md §6): the census transform of the grey images (one
  bit per neighbour q of the (2r+1)² window: I(q) > I(p)), image 1 against image 2 warped by the
  flow, as the Hamming distance over the (2r+1)² − 1 neighbours (48 for r = 3). In [0, 1];
  indifferent to a gain and bias of brightness between the frames, and to any strictly increasing
  change of the grey image (not to one applied to each colour channel apart, such as a gamma per
  channel, which can reorder the luma). Not differentiable: the measure to judge a flow by on real
  images.
- ``"soft_census"``: the soft Hamming distance between soft census transforms, as in UFlow and
  ARFlow's ternary loss: per neighbour offset t = (I(q) − I(p)) / sqrt(0.81 + (I(q) − I(p))²) on
  the 0–255 scale, then mean over the (2r+1)² offsets of d² / (0.1 + d²) with d = t_1 − t_2. In
  [0, 1); differentiable (the training loss's census term).

Which pixels count. A pixel is valid when its sample point p + F(p) lies inside the second image
(:func:`fsof_torch.warp.warp_backward`'s ``in_bounds``) and the caller's ``mask`` is True there.
For ``"ssim"`` and the census kinds, whose value at p looks at a window around p, the in-bounds map
is first eroded by the window radius, so that no value mixes in the warp's padding (the image
border itself is padded by reflection or replication, not dropped).

Empty masks: a sample with no valid pixel gets the value 0.0 (never NaN) and a pixel count of 0;
pass ``return_count=True`` to get the counts, which are the flag to check. Nothing divides by a
zero count, so gradients stay finite as well.

Several kinds at once: :func:`photometric_error_maps` and :func:`photometric_errors` warp image 2
once and return one map (or mean) per kind; by default L1, SSIM and census (``REPORTED_KINDS``).

Photometric error can reward a wrong flow that matches brightness, and L1 on raw intensities
charges a correct flow for every exposure change between the frames: report census and SSIM beside
L1, and where ground truth exists the end-point error (:mod:`fsof_torch.metrics`) as well.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .._check import (
    autocast_off,
    check_bool,
    check_data_range,
    check_float_tensor,
    check_image_range,
    check_int,
    check_same_device,
    check_shape,
    result_dtype,
)
from .warp import warp_backward

__all__ = ["REPORTED_KINDS", "photometric_error", "photometric_error_map", "photometric_error_maps",
           "photometric_errors", "census_transform", "PhotometricError", "to_grey"]

_KINDS = ("l1", "ssim", "census", "soft_census")
#: the kinds to report side by side (DESIGN.md §6): L1 alone ranks wrong flows first on real images
REPORTED_KINDS = ("l1", "ssim", "census")
#: ITU-R BT.601 luma weights (R, G, B), kornia's ``rgb_to_grayscale``'s and OpenCV's
_LUMA = (0.299, 0.587, 0.114)


def to_grey(image: Tensor, *, out: Tensor | None = None) -> Tensor:
    """(B, C, H, W) -> (B, 1, H, W): ITU-R 601 luma for C = 3 (taken as RGB), the image itself
    for C = 1 (not a copy), the mean otherwise.

    A floating RGB image: ``r w_r + g w_g + b w_b``, rounded in that order (a product, then two
    ``addcmul``), as kornia's ``rgb_to_grayscale`` does since kornia 0.9: the same values bit for
    bit, with or without autograd, whichever kornia is installed (kornia 0.8 adds three products,
    which rounds differently, and refuses bfloat16). A uint8 RGB image: OpenCV's fixed-point
    ``COLOR_RGB2GRAY`` (the weights × 2¹⁵, rounded), as ``cv2.cvtColor`` and kornia 0.9 give it.
    Other integer images: a TypeError, but for one channel.

    ``out``: a (B, 1, H, W) tensor of the image's dtype to write the grey image into (such as
    one channel of a pair's tensor), returned; not with autograd. An ``out`` that shares the
    image's memory (one of its own channels) gets the grey image computed from the image as it
    was, then written.

    Without autograd the floating conversion runs in place, into one tensor (kornia's three
    steps each allocate a full-size one). Both frames of a KITTI-size pair, written into one
    tensor: 0.8–1.1 ms against 1.5–1.6 ms for kornia's and a concatenation
    (``python benchmarks/bench_image_fit.py``).
    """
    if not isinstance(image, Tensor):
        raise TypeError(f"image: expected a tensor, got {type(image).__name__}")
    dims = check_shape(image, "image", ("B", "C", "H", "W"), nonempty=("C", "H", "W"))  # (no channel: no grey)
    grad = torch.is_grad_enabled() and image.requires_grad
    if out is not None and grad:
        raise ValueError("out: not supported for an image that requires grad")
    if out is not None:
        # (a list failed in an AttributeError, a tensor on another device in torch's error of the
        # product written into it: neither named out)
        if not isinstance(out, Tensor):
            raise TypeError(f"out: expected a tensor (B, 1, H, W) or None, got {type(out).__name__}")
        if out.device != image.device:
            raise ValueError(f"out: expected the image's device ({image.device}), got {out.device}")
        # (written into, never resized: a caller's tensor of another shape would be reallocated)
        check_shape(out, "out", ("B", 1, "H", "W"), dims)
        if out.dtype != image.dtype:
            raise TypeError(f"out: expected the image's dtype {image.dtype}, got {out.dtype}")
    C = image.shape[1]
    if C == 1:
        grey = image
    elif C == 3 and image.dtype == torch.uint8:
        # OpenCV's fixed point: 0.299, 0.587 and 0.114 times 2**15, summing to 2**15 (a flat grey
        # maps to itself), accumulated in int32 and rounded back
        r, g, b = image.to(torch.int32).unbind(dim=1)
        grey = ((r * 9798 + g * 19235 + b * 3735 + 16384) >> 15).to(torch.uint8).unsqueeze(1)
    elif not image.is_floating_point():
        raise TypeError(f"image: expected a floating-point image, or a uint8 one of 1 or 3 channels, got dtype "
                        f"{image.dtype} with {C} channels")
    elif C == 3 and out is not None and out.untyped_storage().data_ptr() == image.untyped_storage().data_ptr():
        # (written in place, out=image[:, 1:2] or [:, 2:3] was read after being overwritten)
        grey = to_grey(image)
    elif C == 3:
        # the weights rounded to the image's dtype (0-dim CPU tensors, whatever the default device:
        # usable with an image on any device), and one order of rounding: r w_r, then + g w_g and
        # + b w_b (addcmul)
        w_r, w_g, w_b = torch.tensor(_LUMA, dtype=image.dtype, device="cpu").unbind()
        r, g, b = image.unbind(dim=1)
        if grad:
            return (r * w_r).addcmul(g, w_g).addcmul(b, w_b).unsqueeze(1)
        grey = torch.empty_like(r).unsqueeze(1) if out is None else out
        plane = grey[:, 0]
        torch.mul(r, w_r, out=plane)
        plane.addcmul_(g, w_g).addcmul_(b, w_b)
        return grey
    else:
        grey = image.mean(dim=1, keepdim=True)
    if out is None:
        return grey
    return out.copy_(grey)


def census_transform(image: Tensor, *, radius: int = 3, data_range: float = 255.0) -> Tensor:
    """Soft census transform (UFlow/ARFlow) of an image: one channel per neighbour offset.

    Args:
        image: (B, C, H, W) in [0, data_range]; C = 3 is converted to grey as RGB.
        radius: neighbourhood radius r; the transform has (2r+1)² channels.
        data_range: the images' range; intensities are compared on the 0-255 scale.

    Returns:
        (B, (2r+1)², H, W) in (-1, 1): t = δ / sqrt(0.81 + δ²), δ = I(q) - I(p) in grey levels,
        in at least float32 (also under ``torch.autocast``). The image border is replicated, so
        border offsets compare real pixels.
    """
    check_float_tensor(image, "image")
    check_shape(image, "image", ("B", "C", "H", "W"), nonempty=("C", "H", "W"))
    radius = check_int(radius, "radius", minimum=1)
    data_range = check_data_range(data_range)
    # At least float32, also under autocast: the comparisons of near-equal grey levels are the
    # whole signal, and bfloat16 keeps 3 significant digits of them.
    work = result_dtype(image)
    with autocast_off(image):
        grey = to_grey(image.to(work)) * (255.0 / data_range)
        k = 2 * radius + 1
        # One-hot kernels pick each neighbour: the census as a single convolution.
        eye = torch.eye(k * k, dtype=grey.dtype, device=grey.device).reshape(k * k, 1, k, k)
        padded = F.pad(grey, (radius, radius, radius, radius), mode="replicate")
        delta = F.conv2d(padded, eye) - grey
        return delta / torch.sqrt(0.81 + delta * delta)


def _erode(valid: Tensor, radius: int) -> Tensor:
    """Keep a pixel only if its whole (2r+1)² window is valid (outside the image counts valid).

    A separable AND over shifted views, rows then columns: 50 times faster than a max-pool of
    the (2r+1)² window on a KITTI frame."""
    if radius == 0:
        return valid
    out = valid
    for dim, pad in ((-1, (radius, radius, 0, 0)), (-2, (0, 0, radius, radius))):
        n = out.shape[dim]
        padded = F.pad(out, pad, value=True)
        acc = padded.narrow(dim, 0, n).clone()
        for shift in range(1, 2 * radius + 1):
            acc &= padded.narrow(dim, shift, n)
        out = acc
    return out


def _check_inputs(image1: Tensor, image2: Tensor, flow: Tensor, mask: Tensor | None, kinds: tuple[str, ...],
                  data_range: float, window: int, census_radius: int) -> tuple[float, int, int]:
    """Every argument check of the photometric functions; returns the checked ``data_range``,
    ``window`` and ``census_radius`` (as Python numbers: kornia refuses a NumPy integer window)."""
    check_float_tensor(image1, "image1")
    check_float_tensor(image2, "image2")
    check_float_tensor(flow, "flow")
    # (an image without channels has no value to compare: its L1 and soft census were NaN, its
    # census distance a perfect 0.0 over every pixel)
    dims = check_shape(image1, "image1", ("B", "C", "H", "W"), nonempty=("C", "H", "W"))
    check_shape(image2, "image2", ("B", "C", "H", "W"), dims)
    check_shape(flow, "flow", ("B", 2, "H", "W"), dims)
    if mask is not None:
        if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
            got = mask.dtype if isinstance(mask, Tensor) else type(mask).__name__
            raise TypeError(f"mask: expected a bool tensor, got {got}")
        check_shape(mask, "mask", ("B", 1, "H", "W"), dims)
    check_same_device({"image1": image1, "image2": image2, "flow": flow, "mask": mask})
    data_range = check_data_range(data_range)
    window, census_radius = _check_window_options(window, census_radius)
    if "ssim" in kinds and min(dims["H"], dims["W"]) <= window // 2:
        # kornia pads the SSIM window by reflection, which needs more pixels than the window radius
        raise ValueError(f"image1: kind='ssim' with window={window} needs H and W >= {window // 2 + 1}, "
                         f"got shape {tuple(image1.shape)} (pass a smaller odd window)")
    check_image_range(image1, "image1", data_range)
    check_image_range(image2, "image2", data_range)
    return data_range, window, census_radius


def _check_window_options(window: object, census_radius: object) -> tuple[int, int]:
    """``window``: an odd positive int; ``census_radius``: a positive int; both returned as
    Python ints (a NumPy integer accepted)."""
    window = check_int(window, "window", minimum=1)
    if window % 2 == 0:
        raise ValueError(f"window: expected an odd positive int, got {window!r}")
    return window, check_int(census_radius, "census_radius", minimum=1)


def _check_kind(kind: object) -> str:
    """``kind``: one of the known kinds (a string; a list of kinds is refused with a TypeError)."""
    if not isinstance(kind, str):
        raise TypeError(f"kind: expected a str, one of {_KINDS}, got {type(kind).__name__} {kind!r}")
    if kind not in _KINDS:
        raise ValueError(f"kind: expected one of {_KINDS}, got {kind!r}")
    return kind


def _check_kinds(kinds: object) -> tuple[str, ...]:
    """``kinds`` as a tuple of distinct known kinds (a single string is refused: it is iterable)."""
    if isinstance(kinds, str) or not isinstance(kinds, (tuple, list)):
        raise TypeError(f"kinds: expected a non-empty tuple or list of kinds from {_KINDS}, got {kinds!r}")
    if not kinds:
        raise ValueError(f"kinds: expected at least one kind from {_KINDS}, got {kinds!r}")
    bad = [k for k in kinds if k not in _KINDS]
    if bad:
        raise ValueError(f"kinds: expected kinds from {_KINDS}, got {bad[0]!r}")
    if len(set(kinds)) != len(kinds):
        raise ValueError(f"kinds: expected each kind once, got {tuple(kinds)!r}")
    return tuple(kinds)


def _census_distance(grey1: Tensor, grey2: Tensor, radius: int) -> Tensor:
    """Hamming distance of the census bits (I(q) > I(p) over the (2r+1)² window, the border
    replicated) of two (B, 1, H, W) grey images, divided by the (2r+1)² − 1 neighbours.

    The bits are compared one neighbour offset at a time on shifted views (a few operations per
    pixel and offset, counted in small integers): a tenth of the time of the one-hot convolution that
    :func:`census_transform` uses to build all offsets at once."""
    H, W = grey1.shape[-2:]
    pad = (radius, radius, radius, radius)
    p1, p2 = F.pad(grey1, pad, mode="replicate"), F.pad(grey2, pad, mode="replicate")
    k = 2 * radius + 1
    # the smallest integer type that holds the count of k² - 1 neighbours: uint8 up to radius 7,
    # int16 up to radius 90, int32 beyond (an int16 count wraps to negative distances there)
    n = k * k - 1
    dtype = torch.uint8 if n <= 255 else torch.int16 if n <= 32767 else torch.int32
    count = torch.zeros(grey1.shape, dtype=dtype, device=grey1.device)
    for dy in range(k):
        for dx in range(k):
            if dy == radius and dx == radius:
                continue
            count += (p1[..., dy:dy + H, dx:dx + W] > grey1) != (p2[..., dy:dy + H, dx:dx + W] > grey2)
    return count.to(grey1.dtype) / n


def photometric_error_maps(image1: Tensor, image2: Tensor, flow: Tensor, mask: Tensor | None = None,
                           *, kinds: tuple[str, ...] | list[str] = REPORTED_KINDS, data_range: float = 255.0,
                           window: int = 7, census_radius: int = 3,
                           align_corners: bool = True) -> dict[str, tuple[Tensor, Tensor]]:
    """Per-pixel photometric error of ``flow`` for several kinds at once (image 2 warped once).

    Args: as :func:`photometric_error_map`, with
        kinds: the kinds to compute, e.g. ``("l1", "ssim", "census")`` (the default: the three to
            report side by side, DESIGN.md §6).

    Returns:
        ``{kind: (error (B, 1, H, W), valid (B, 1, H, W) bool)}`` in the order of ``kinds``; each
        pair equals what :func:`photometric_error_map` returns for that kind.

    Example:
        >>> i1 = torch.arange(64.0).reshape(1, 1, 8, 8).repeat(1, 3, 1, 1) * 2
        >>> maps = photometric_error_maps(i1, i1 * 0.5 + 40, torch.zeros(1, 2, 8, 8))
        >>> [(k, tuple(e.shape), int(v.sum())) for k, (e, v) in maps.items()]
        [('l1', (1, 1, 8, 8), 64), ('ssim', (1, 1, 8, 8), 64), ('census', (1, 1, 8, 8), 64)]
    """
    kinds = _check_kinds(kinds)
    data_range, window, census_radius = _check_inputs(image1, image2, flow, mask, kinds, data_range, window,
                                                      census_radius)
    work = result_dtype(image1, image2, flow)
    out: dict[str, tuple[Tensor, Tensor]] = {}
    with autocast_off(image1):
        # contiguous: a crop of a larger image (a view, as the refine job passes) would send
        # kornia's SSIM down its NCHW path, slower than the channels-last one it takes for
        # contiguous float32 images (refine's boxed maps of a KITTI-sized pair: 86 ms against 112)
        im1 = image1.to(work).contiguous()
        warped, in_bounds = warp_backward(image2.to(work), flow.to(work), align_corners=align_corners)
        for kind in kinds:
            valid = in_bounds
            if kind == "l1":
                error = (im1 - warped).abs().mean(dim=1, keepdim=True) * (255.0 / data_range)
            elif kind == "ssim":
                error = _ssim_error(im1, warped, window, data_range)
                valid = _erode(in_bounds, window // 2)
            elif kind == "census":
                # the order of grey levels is all the census sees: no scaling to 0-255 needed
                error = _census_distance(to_grey(im1), to_grey(warped), census_radius)
                valid = _erode(in_bounds, census_radius)
            else:
                t1 = census_transform(im1, radius=census_radius, data_range=data_range)
                t2 = census_transform(warped, radius=census_radius, data_range=data_range)
                d2 = (t1 - t2) ** 2
                error = (d2 / (0.1 + d2)).mean(dim=1, keepdim=True)
                valid = _erode(in_bounds, census_radius)
            if mask is not None:
                valid = valid & mask
            out[kind] = (torch.where(valid, error, torch.zeros_like(error)), valid)
    return out


def _ssim_error(im1: Tensor, warped: Tensor, window: int, data_range: float) -> Tensor:
    """(1 − SSIM) / 2 per pixel, mean over channels, (B, 1, H, W)."""
    from kornia.metrics import ssim

    if im1.device.type == "meta":
        # kornia's ssim enters torch.autocast, which the meta device lacks; its map has the
        # images' shape, which is all shape inference needs.
        s = torch.empty_like(im1)
    else:
        # eps=0: kornia's default eps biases flat dark patches; c1, c2 > 0 keep it finite.
        s = ssim(im1, warped, window, max_val=float(data_range), eps=0.0)
    return ((1.0 - s) * 0.5).clamp(0.0, 1.0).mean(dim=1, keepdim=True)


def photometric_error_map(image1: Tensor, image2: Tensor, flow: Tensor, mask: Tensor | None = None,
                          *, kind: str = "l1", data_range: float = 255.0, window: int = 7,
                          census_radius: int = 3, align_corners: bool = True) -> tuple[Tensor, Tensor]:
    """Per-pixel photometric error of ``flow`` and the pixels where it is defined.

    Args:
        image1: (B, C, H, W) frame t, values in [0, data_range].
        image2: (B, C, H, W) frame t+1, same range.
        flow: (B, 2, H, W) forward flow t -> t+1 in pixels (channel 0 = u).
        mask: optional (B, 1, H, W) bool, the pixels to evaluate (e.g. the road).
        kind: ``"l1"`` (grey levels, 0-255 scale), ``"ssim"`` ((1 - SSIM)/2), ``"census"`` (the
            Hamming distance of census transforms / the neighbour count) or ``"soft_census"``.
        data_range: the images' range (255.0 or 1.0): a finite number > 0. Values outside
            [-0.01, 1.01] × data_range (1% either side, for rounding and resampling overshoot),
            NaN or inf pixels anywhere in either image, and with data_range > 1.5 an image whose
            brightest pixel lies in (0, 1] (a 0..1 image passed as 0..255), raise ValueError naming
            the image (a NaN pixel would spread through the warp's taps and the SSIM and census
            windows).
        window: odd SSIM window size (taps of the σ = 1.5 Gaussian); ``"ssim"`` needs H and W
            larger than ``window // 2`` (the reflection padding).
        census_radius: census neighbourhood radius r ((2r+1)² offsets).
        align_corners: passed to :func:`~fsof_torch.warp.warp_backward` (does not change results).

    Returns:
        error: (B, 1, H, W) in image1's promoted float dtype (at least float32), 0 where not valid.
        valid: (B, 1, H, W) bool: sample point inside image2 (eroded by the window for ssim and
            census) and inside ``mask``.
    """
    _check_kind(kind)
    return photometric_error_maps(image1, image2, flow, mask, kinds=(kind,), data_range=data_range,
                                  window=window, census_radius=census_radius,
                                  align_corners=align_corners)[kind]


def photometric_error(image1: Tensor, image2: Tensor, flow: Tensor, mask: Tensor | None = None,
                      *, kind: str = "l1", data_range: float = 255.0, window: int = 7,
                      census_radius: int = 3, align_corners: bool = True,
                      return_count: bool = False) -> Tensor | tuple[Tensor, Tensor]:
    """Mean photometric error per sample over the valid pixels inside ``mask``.

    Args: as :func:`photometric_error_map`, plus
        return_count: also return the number of pixels each mean is over.

    Returns:
        error: (B,) float; for ``"l1"`` the mean absolute difference in grey levels (0-255
            scale). A sample with no valid pixel gets 0.0, not NaN: check the count.
        count: (B,) int64, only with ``return_count=True``.

    Example:
        >>> i1 = torch.full((1, 3, 8, 8), 100.0); i2 = torch.full((1, 3, 8, 8), 110.0)
        >>> photometric_error(i1, i2, torch.zeros(1, 2, 8, 8)).tolist()
        [10.0]
    """
    check_bool(return_count, "return_count")
    error, valid = photometric_error_map(image1, image2, flow, mask, kind=kind,
                                         data_range=data_range, window=window,
                                         census_radius=census_radius, align_corners=align_corners)
    mean, count = _mean(error, valid)
    return (mean, count) if return_count else mean


def photometric_errors(image1: Tensor, image2: Tensor, flow: Tensor, mask: Tensor | None = None,
                       *, kinds: tuple[str, ...] | list[str] = REPORTED_KINDS, data_range: float = 255.0,
                       window: int = 7, census_radius: int = 3, align_corners: bool = True,
                       return_count: bool = False) -> dict[str, Tensor] | dict[str, tuple[Tensor, Tensor]]:
    """Mean photometric error per sample of several kinds at once (image 2 warped once).

    Args: as :func:`photometric_error_maps`, plus
        return_count: give ``(mean, count)`` per kind; the kinds with a window (ssim and the
            census kinds) count fewer pixels than ``"l1"`` within a window radius of any pixel
            whose sample point leaves image 2 (the border itself is padded, not dropped).

    Returns:
        ``{kind: (B,) mean}`` (``{kind: ((B,) mean, (B,) int64 count)}`` with ``return_count``);
        by default L1 (0-255 scale), SSIM ((1 − SSIM) / 2) and the census distance, the figures to
        report side by side (DESIGN.md §6). Empty selections give 0.0: check the count.

    Example: a change of exposure (image 2 = image 1 · 0.5 + 40, no motion) costs L1 and SSIM,
    not census:

        >>> i1 = torch.arange(64.0).reshape(1, 1, 8, 8).repeat(1, 3, 1, 1) * 2
        >>> errors = photometric_errors(i1, i1 * 0.5 + 40, torch.zeros(1, 2, 8, 8))
        >>> {k: round(v.item(), 3) for k, v in errors.items()}
        {'l1': 17.125, 'ssim': 0.115, 'census': 0.0}
    """
    check_bool(return_count, "return_count")
    maps = photometric_error_maps(image1, image2, flow, mask, kinds=kinds, data_range=data_range,
                                  window=window, census_radius=census_radius, align_corners=align_corners)
    out = {}
    for kind, (error, valid) in maps.items():
        mean, count = _mean(error, valid)
        out[kind] = (mean, count) if return_count else mean
    return out


def _mean(error: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Per-sample mean of ``error`` over ``valid`` (0 where nothing is valid) and the count."""
    count = valid.flatten(1).sum(dim=1)
    total = error.flatten(1).sum(dim=1)
    return total / count.clamp(min=1).to(total.dtype), count


class PhotometricError(nn.Module):
    """``nn.Module`` twin of :func:`photometric_error`:
    ``forward(image1, image2, flow, mask=None, *, return_count=False)``.

    The options are checked at construction (the image-size rule of ``"ssim"`` at each call).
    ``return_count=True`` gives ``(mean, count)``, as the function does: a sample with no
    counted pixel (an empty mask, or a flow that sends every pixel out of image 2) has the mean
    0.0 and the count 0, the flag to check.
    """

    def __init__(self, *, kind: str = "l1", data_range: float = 255.0, window: int = 7,
                 census_radius: int = 3, align_corners: bool = True) -> None:
        super().__init__()
        _check_kind(kind)
        data_range = check_data_range(data_range)
        window, census_radius = _check_window_options(window, census_radius)
        check_bool(align_corners, "align_corners")
        self.kind = kind
        self.data_range = data_range
        self.window = window
        self.census_radius = census_radius
        self.align_corners = align_corners

    def forward(self, image1: Tensor, image2: Tensor, flow: Tensor, mask: Tensor | None = None,
                *, return_count: bool = False) -> Tensor | tuple[Tensor, Tensor]:
        """(B,) mean error of image 2 warped by ``flow`` (B, 2, H, W) px against image 1 (B, C, H, W): :func:`photometric_error`."""
        return photometric_error(image1, image2, flow, mask, kind=self.kind,
                                 data_range=self.data_range, window=self.window,
                                 census_radius=self.census_radius, align_corners=self.align_corners,
                                 return_count=return_count)

    def extra_repr(self) -> str:
        # (every option that changes the result: the window and the census radius were left out,
        # so a module with window=11 printed as one with the default 7)
        return (f"kind={self.kind!r}, data_range={self.data_range:g}, window={self.window}, "
                f"census_radius={self.census_radius}")
