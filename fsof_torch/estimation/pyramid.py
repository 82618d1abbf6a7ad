"""The image pyramids of the image fit: Gaussian levels of the grey images, the road mask's
levels, each level's camera and its band of detail. OpenCV filters on the CPU (measured in
``python benchmarks/bench_image_fit.py``), torch and kornia elsewhere."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from .._check import check_float_tensor, check_int, check_number, check_shape, host_path, is_number, option_error, scalar
from ..geometry.camera import Camera

__all__ = ["pyramid_levels", "image_pyramid", "mask_pyramid", "level_camera", "band", "gaussian_blur"]


def pyramid_levels(H: int, W: int, levels: int | None, min_size: int) -> int:
    """The number of levels: ``levels``, or floor(log2(min(H, W) / ``min_size``)) + 1 (at least
    1): the levels whose shorter side, halved exactly at each level (min(H, W) / 2^l), is at
    least ``min_size`` (an int >= 1). OpenCV's ``pyrDown`` rounds a side up ((s + 1) // 2), so a
    level can be a pixel or so larger than that, and a side just short of a power of two times
    ``min_size`` gets one level less than the rounded sides would allow (63 px with ``min_size``
    16: 2 levels, 63 and 32 px, though a third of 16 px would still reach it).

    A ``levels`` beyond the level at which both sides reach one pixel (1 + ⌈log2 max(H, W)⌉) is a
    ValueError: the levels past it would repeat that pixel, and a count such as 10**20 would build
    them until memory ran out."""
    min_size, levels = scalar(min_size, "min_size"), scalar(levels, "levels")  # (0-d integer tensors as their ints)
    if not is_number(min_size, integer=True):
        raise TypeError(f"min_size: expected an int >= 1, got {type(min_size).__name__} {min_size!r}")
    if min_size < 1:
        raise ValueError(f"min_size: expected an int >= 1, got {min_size!r}")
    if levels is None:
        levels = max(1, int(math.floor(math.log2(max(min(H, W), 1) / min_size))) + 1)
    if not is_number(levels, integer=True) or levels < 1:
        raise option_error(levels, f"levels: expected None or an int >= 1, got {levels!r}", integer=True)
    most = 1 + (max(H, W, 1) - 1).bit_length()  # (1 + ⌈log2 of the longer side⌉: each level rounds its sides up)
    if levels > most:
        raise ValueError(f"levels: expected at most {most} for {H}x{W} images (the level at which both sides reach "
                         f"1 pixel; more would repeat it), got {levels!r}")
    return int(levels)


def image_pyramid(images: Tensor, levels: int, smooth_sigma: float = 1.0) -> list[Tensor]:
    """A Gaussian pyramid of images (B, C, H, W): level 0 smoothed with ``smooth_sigma`` pixels,
    each next level the 5-tap binomial blur [1, 4, 6, 4, 1] / 16 of the one below, sampled at its
    even pixels (OpenCV's ``pyrDown``): pixel i of level l is pixel 2^l i of level 0. With
    ``smooth_sigma`` 0, level 0 is ``images`` itself, not a copy. Borders are reflected without
    repeating the edge (OpenCV's ``BORDER_REFLECT_101``) at any size, a level of one pixel too.

    On the CPU OpenCV does the filtering (python benchmarks/bench_image_fit.py: five levels of a
    KITTI frame in about 1 ms, some 70 times faster than the same convolutions in torch);
    elsewhere torch does the same arithmetic. On the CPU no filtered level carries a gradient:
    the coarser levels never, and level 0 neither where ``smooth_sigma`` > 0 (OpenCV's blur);
    only level 0 with ``smooth_sigma`` 0, which is ``images`` itself. Elsewhere every level is
    differentiable.
    """
    _check_images(images)
    levels = check_int(levels, "levels", minimum=1)
    smooth_sigma = check_number(smooth_sigma, "smooth_sigma", nonnegative=True)
    level = gaussian_blur(images, smooth_sigma) if smooth_sigma > 0 else images
    if host_path(images):
        return [level] + _pyramid_cv2(level, levels)
    return [level] + _pyramid_torch(level, levels)


def _pyramid_cv2(level: Tensor, levels: int) -> list[Tensor]:
    """Levels 1 to ``levels`` - 1 below ``level`` by OpenCV's ``pyrDown``, in ``level``'s dtype."""
    import cv2
    import numpy as np

    B, C, H, W = level.shape
    planes = _cv2_planes(level)
    out = [[x.numpy() for x in planes]]
    for _ in range(levels - 1):
        out.append([cv2.pyrDown(x) for x in out[-1]])
    return [torch.from_numpy(np.stack(p)).reshape(B, C, *p[0].shape).to(level.dtype) for p in out[1:]]


def _pyramid_torch(level: Tensor, levels: int) -> list[Tensor]:
    """:func:`_pyramid_cv2`'s levels by torch convolutions (any device)."""
    out = []
    taps = level.new_tensor([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0
    x = level
    for _ in range(levels - 1):
        x = _separable_reflect101(x, taps)[..., ::2, ::2].contiguous()
        out.append(x)
    return out


def _cv2_planes(images: Tensor) -> Tensor:
    """The planes (B C, H, W) of images as OpenCV takes them: detached, C-contiguous, float32
    for the 16-bit floats (which OpenCV and NumPy refuse)."""
    planes = images.detach().reshape(-1, *images.shape[-2:])
    if planes.dtype in (torch.float16, torch.bfloat16):
        planes = planes.to(torch.float32)
    return planes.contiguous()


def _reflect101(x: Tensor, dim: int, pad: int) -> Tensor:
    """``x`` padded by ``pad`` on both sides of ``dim``, reflected without repeating the edge
    (OpenCV's ``BORDER_REFLECT_101``), folded again and again where ``pad`` exceeds the side
    (``F.pad``'s reflection refuses a pad as long as the side)."""
    n = x.shape[dim]
    i = torch.arange(-pad, n + pad, device=x.device)
    if n == 1:
        i = torch.zeros_like(i)
    else:  # reflect-101 is periodic with period 2 (n - 1)
        period = 2 * (n - 1)
        i = i.remainder(period)
        i = torch.where(i < n, i, period - i)
    return x.index_select(dim, i)


def _separable_reflect101(x: Tensor, taps: Tensor) -> Tensor:
    """Images (B, C, H, W) filtered by the odd 1-D ``taps`` along rows, then along columns, with
    reflect-101 borders."""
    C, k = x.shape[1], taps.numel()
    x = F.conv2d(_reflect101(x, 3, k // 2), taps.reshape(1, 1, 1, k).expand(C, 1, 1, k), groups=C)
    return F.conv2d(_reflect101(x, 2, k // 2), taps.reshape(1, 1, k, 1).expand(C, 1, k, 1), groups=C)


def mask_pyramid(mask: Tensor, levels: int) -> list[Tensor]:
    """The masks (B, 1, H, W) bool of the pyramid's levels (:func:`image_pyramid`): a pixel of a
    coarser level, centred on pixel 2i of the finer one, is in the mask where the finer one's 3 × 3
    neighbourhood is (within the image). On the CPU OpenCV erodes: the same pixels as the min-pool
    used elsewhere, about 3 times faster (python benchmarks/bench_image_fit.py)."""
    out = [mask]
    if not host_path(mask):
        for _ in range(levels - 1):
            out.append(-F.max_pool2d(-out[-1].to(torch.float32), 3, stride=2, padding=1) > 0.5)
        return out
    import cv2
    import numpy as np

    kernel = np.ones((3, 3), np.uint8)
    B = mask.shape[0]
    for _ in range(levels - 1):
        # (a 3 x 3 erosion ignores the border, as the min-pool's padding does; the flags read
        # and written as bytes, 0 and 1, without converting them)
        planes = out[-1].reshape(B, *out[-1].shape[-2:]).view(torch.uint8).contiguous().numpy()
        eroded = np.stack([cv2.erode(x, kernel) for x in planes])[:, None, ::2, ::2]
        out.append(torch.from_numpy(eroded.copy()).view(torch.bool))
    return out


def level_camera(camera: Camera, level: int) -> Camera:
    """The camera of pyramid level ``level``: pixel i there is pixel 2^level i of level 0."""
    s = 0.5 ** level
    S = torch.tensor([[s, 0.0, 0.0], [0.0, s, 0.0], [0.0, 0.0, 1.0]], dtype=camera.dtype, device=camera.device)
    return Camera._checked(S @ camera.K, camera.height, camera.roll, camera.pitch)


#: :func:`band` inside a mask: below this share of the Gaussian's weight on the mask's pixels, a
#: pixel's mean would rest on the blur's tail alone, and the plain blur stands instead (1.6 σ or
#: more outside a straight edge of the mask)
MIN_MASK_SHARE = 0.05


def band(img: Tensor, sigma: float | None, mask: Tensor | None = None) -> Tensor:
    """Each level minus its Gaussian blur of ``sigma`` pixels (of that level): the level's band of
    detail, indifferent to smooth changes of lighting between the frames; None: the level itself.

    ``mask`` (B or 1, 1 or C, H, W) bool: the blur is the Gaussian-weighted mean over the mask's
    pixels only (normalised convolution: blur(img · mask) / blur(mask)), so that what lies outside
    it (a kerb standing above the road, a verge, a car) does not enter the band of the pixels
    inside; where the mask holds less than :data:`MIN_MASK_SHARE` of the Gaussian's weight, the
    plain blur."""
    if not sigma:
        return img
    if mask is not None:
        weight = mask.to(img.dtype)
        share = gaussian_blur(weight, sigma)
        inside = gaussian_blur(img * weight, sigma) / share.clamp_min(MIN_MASK_SHARE)
        return img - torch.where(share >= MIN_MASK_SHARE, inside, gaussian_blur(img, sigma))
    blurred = gaussian_blur(img, sigma)  # (a new tensor: the difference is written over it)
    if img.requires_grad or blurred.requires_grad:  # (out= does not record gradients)
        return img - blurred
    return torch.sub(img, blurred, out=blurred)


def gaussian_blur(images: Tensor, sigma: float) -> Tensor:
    """Gaussian blur of images (B, C, H, W), reflected at the border without repeating the edge
    (OpenCV's ``BORDER_REFLECT_101``, at any size; a kernel of ±3 σ): OpenCV on the CPU (python
    benchmarks/bench_image_fit.py: about 2.5x faster than kornia's at σ = 4; not differentiable),
    torch convolutions with kornia's kernel elsewhere. 16-bit floats are filtered in float32.
    ``sigma``: a number >= 0 (pixels; 0 leaves the images as they are, in a new tensor)."""
    _check_images(images)
    sigma = check_number(sigma, "sigma", nonnegative=True)
    if host_path(images):
        return _gaussian_blur_cv2(images, sigma)
    return _gaussian_blur_torch(images, sigma)


def _check_images(images: object) -> None:
    """``images``: a float tensor (B, C, H, W) with H, W >= 1 (else a TypeError / ValueError)."""
    check_shape(check_float_tensor(images, "images"), "images", ("B", "C", "H", "W"))


def _kernel_size(sigma: float) -> int:
    return 2 * int(math.ceil(3 * sigma)) + 1


def _gaussian_blur_cv2(images: Tensor, sigma: float) -> Tensor:
    import cv2

    k = _kernel_size(sigma)
    planes = _cv2_planes(images)
    out = torch.empty(planes.shape, dtype=planes.dtype, device="cpu")  # (C-contiguous, whatever the input's layout)
    for x, y in zip(planes.numpy(), out.numpy()):  # (each plane written in place, no stacking)
        cv2.GaussianBlur(x, (k, k), sigma, dst=y, borderType=cv2.BORDER_REFLECT_101)
    return out.reshape(images.shape).to(images.dtype)


def _gaussian_blur_torch(images: Tensor, sigma: float) -> Tensor:
    from kornia.filters import get_gaussian_kernel1d

    x = images.to(torch.float32) if images.dtype in (torch.float16, torch.bfloat16) else images
    taps = get_gaussian_kernel1d(_kernel_size(sigma), x.new_tensor([[sigma]])).reshape(-1)
    return _separable_reflect101(x, taps).to(images.dtype)
