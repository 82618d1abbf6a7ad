"""The image pyramids of the image fit: Gaussian levels of the grey images, the road mask's
levels, each level's camera and its band of detail. OpenCV filters on the CPU (measured in
``python benchmarks/bench_image_fit.py``), torch and kornia elsewhere."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.camera import Camera

__all__ = ["pyramid_levels", "image_pyramid", "mask_pyramid", "level_camera", "band", "gaussian_blur"]


def pyramid_levels(H: int, W: int, levels: int | None, min_size: int) -> int:
    """The number of levels: ``levels``, or halving until the shorter side would drop below
    ``min_size``."""
    if levels is None:
        levels = max(1, int(math.floor(math.log2(max(min(H, W), 1) / min_size))) + 1)
    if isinstance(levels, bool) or not isinstance(levels, int) or levels < 1:
        raise ValueError(f"levels: expected None or an int >= 1, got {levels!r}")
    return levels


def image_pyramid(images: Tensor, levels: int, smooth_sigma: float = 1.0) -> list[Tensor]:
    """A Gaussian pyramid of images (B, C, H, W): level 0 smoothed with ``smooth_sigma`` pixels,
    each next level the 5-tap binomial blur [1, 4, 6, 4, 1] / 16 of the one below, sampled at its
    even pixels (OpenCV's ``pyrDown``): pixel i of level l is pixel 2^l i of level 0. With
    ``smooth_sigma`` 0, level 0 is ``images`` itself, not a copy.

    On the CPU OpenCV does the filtering (python benchmarks/bench_image_fit.py: five levels of a
    KITTI frame in about 1 ms, some 70 times faster than the same convolutions in torch);
    elsewhere torch does the same arithmetic.
    """
    if images.device.type == "cpu":
        import cv2
        import numpy as np

        B, C = images.shape[:2]
        level = gaussian_blur(images, smooth_sigma) if smooth_sigma > 0 else images
        out = [[x.numpy() for x in level.reshape(B * C, *level.shape[-2:])]]
        for _ in range(levels - 1):
            out.append([cv2.pyrDown(x) for x in out[-1]])
        return [level] + [torch.from_numpy(np.stack(planes)).reshape(B, C, *planes[0].shape) for planes in out[1:]]
    level = gaussian_blur(images, smooth_sigma) if smooth_sigma > 0 else images
    out = [level]
    taps = images.new_tensor([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0
    for _ in range(levels - 1):
        x = out[-1]
        C = x.shape[1]
        x = F.pad(x, (2, 2, 2, 2), mode="reflect")
        x = F.conv2d(x, taps.reshape(1, 1, 1, 5).expand(C, 1, 1, 5), groups=C)
        x = F.conv2d(x, taps.reshape(1, 1, 5, 1).expand(C, 1, 5, 1), groups=C)
        out.append(x[..., ::2, ::2].contiguous())
    return out


def mask_pyramid(mask: Tensor, levels: int) -> list[Tensor]:
    """The masks (B, 1, H, W) bool of the pyramid's levels (:func:`image_pyramid`): a pixel of a
    coarser level, centred on pixel 2i of the finer one, is in the mask where the finer one's 3 × 3
    neighbourhood is (within the image). On the CPU OpenCV erodes: the same pixels as the min-pool
    used elsewhere, about 3 times faster (python benchmarks/bench_image_fit.py)."""
    out = [mask]
    if mask.device.type != "cpu":
        for _ in range(levels - 1):
            out.append(-F.max_pool2d(-out[-1].to(torch.float32), 3, stride=2, padding=1) > 0.5)
        return out
    import cv2
    import numpy as np

    kernel = np.ones((3, 3), np.uint8)
    B = mask.shape[0]
    for _ in range(levels - 1):
        # (a 3 x 3 erosion ignores the border, as the min-pool's padding does)
        planes = out[-1].reshape(B, *out[-1].shape[-2:]).to(torch.uint8).numpy()
        eroded = np.stack([cv2.erode(x, kernel) for x in planes])[:, None, ::2, ::2]
        out.append(torch.from_numpy(eroded.copy()).to(torch.bool))
    return out


def level_camera(camera: Camera, level: int) -> Camera:
    """The camera of pyramid level ``level``: pixel i there is pixel 2^level i of level 0."""
    s = 0.5 ** level
    S = torch.tensor([[s, 0.0, 0.0], [0.0, s, 0.0], [0.0, 0.0, 1.0]], dtype=camera.dtype, device=camera.device)
    return Camera._checked(S @ camera.K, camera.height, camera.roll, camera.pitch)


def band(img: Tensor, sigma: float | None) -> Tensor:
    """Each level minus its Gaussian blur of ``sigma`` pixels (of that level): the level's band of
    detail, indifferent to smooth changes of lighting between the frames; None: the level itself."""
    if not sigma:
        return img
    blurred = gaussian_blur(img, sigma)  # (a new tensor: the difference is written over it)
    return torch.sub(img, blurred, out=blurred)


def gaussian_blur(images: Tensor, sigma: float) -> Tensor:
    """Gaussian blur of images (B, C, H, W), reflected at the border (a kernel of ±3 σ): OpenCV
    on the CPU (python benchmarks/bench_image_fit.py: about 6x faster than kornia's at σ = 4),
    kornia elsewhere."""
    k = 2 * int(math.ceil(3 * sigma)) + 1
    if images.device.type == "cpu":
        import cv2

        B, C, H, W = images.shape
        planes = images.detach().reshape(B * C, H, W)
        out = torch.empty_like(planes)
        for x, y in zip(planes.numpy(), out.numpy()):  # (each plane written in place, no stacking)
            cv2.GaussianBlur(x, (k, k), sigma, dst=y, borderType=cv2.BORDER_REFLECT_101)
        return out.reshape(B, C, H, W)
    from kornia.filters import gaussian_blur2d

    return gaussian_blur2d(images, (k, k), (sigma, sigma), border_type="reflect")
