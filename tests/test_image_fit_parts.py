"""The image fit's building blocks against formulas written here: the road mask's pyramid (a
3 × 3 min-pool at every second pixel) and the image's central-difference gradient (replicated
border), on random masks and images of any size."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from fsof_torch.estimation.image_fit import _with_gradient
from fsof_torch.estimation.pyramid import mask_pyramid

sizes = st.tuples(st.integers(1, 3), st.integers(1, 40), st.integers(1, 40))


@settings(max_examples=40, deadline=None)
@given(sizes, st.floats(0.0, 1.0), st.integers(0, 2**31 - 1))
def test_mask_pyramid_is_a_min_pool_at_every_second_pixel(shape, density, seed):
    B, H, W = shape
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(B, 1, H, W, generator=g) < density
    levels = mask_pyramid(mask, 4)
    assert len(levels) == 4 and levels[0] is mask
    for fine, coarse in zip(levels, levels[1:]):
        h, w = fine.shape[-2:]
        assert coarse.dtype == torch.bool and coarse.shape == (B, 1, (h + 1) // 2, (w + 1) // 2)
        # pixel i of the coarser level: every pixel of the finer one within one of 2i (in the image)
        for i in range(coarse.shape[-2]):
            for j in range(coarse.shape[-1]):
                window = fine[:, 0, max(2 * i - 1, 0):2 * i + 2, max(2 * j - 1, 0):2 * j + 2]
                assert torch.equal(coarse[:, 0, i, j], window.flatten(1).all(1))


@settings(max_examples=40, deadline=None)
@given(sizes, st.integers(0, 2**31 - 1))
def test_image_gradient_is_the_central_difference_with_a_replicated_border(shape, seed):
    B, H, W = shape
    image = torch.rand(B, 1, H, W, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 255
    out = _with_gradient(image)
    p = F.pad(image, (1, 1, 1, 1), mode="replicate")
    assert torch.equal(out[:, :1], image)
    assert torch.equal(out[:, 1:2], 0.5 * (p[..., 1:-1, 2:] - p[..., 1:-1, :-2]))
    assert torch.equal(out[:, 2:3], 0.5 * (p[..., 2:, 1:-1] - p[..., :-2, 1:-1]))
    before = image.clone()
    _with_gradient(image)
    assert torch.equal(image, before)
