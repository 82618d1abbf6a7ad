"""Stand-ins for the flow networks users bring: the I/O contracts of ptlflow's RAFT and of
torchvision's RAFT, reproduced exactly (shapes, colour order, value range, padding), around the
test net :class:`~fsof_torch.training.testnet.TinyRAFT`, in eval and in training mode. Two
defaults differ: the torchvision stand-in's ``num_flow_updates`` is 4, torchvision's
``RAFT.forward`` 12 (kept small so the tests and jobs that run it stay quick); pass
``num_flow_updates=12`` for torchvision's count; likewise the ptlflow stand-in's ``iters`` is 4,
ptlflow's RAFT runs 12 (the length of its ``"flow_preds"`` in training mode).

They exist to test code that wraps such networks (:class:`fsof_torch.FreespaceRefined`, the
refine job's ``--net``) without installing ptlflow or torchvision or downloading weights. Their
flows are TinyRAFT's (random weights unless a state_dict is loaded): meaningless as estimates,
exact as contracts. See :mod:`fsof_torch.refinement.contracts` for the contracts themselves.
"""

from __future__ import annotations

from typing import Any, Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .._check import check_float_tensor, check_int, check_shape, skip_values
from ..refinement.contracts import InputPadder
from .testnet import TinyRAFT

__all__ = ["PtlflowRAFTStandIn", "TorchvisionRAFTStandIn", "ptlflow_raft", "torchvision_raft"]


class PtlflowRAFTStandIn(nn.Module):
    """ptlflow's RAFT contract, in eval and in training mode.

    ``forward(inputs)`` with ``inputs["images"]`` (B, 2, 3, H, W), BGR in [0, 1], any B, H and
    W >= 1 (an empty batch or side raises ValueError naming ``inputs['images']``; the range is not
    read on the meta device, which has no values).
    Like ptlflow's RAFT it pads the images to a multiple of 8 (replicating the border, split
    between both sides), converts BGR to RGB and returns

    - ``"flows"``: (B, 1, 2, H, W), the estimate at the input size (the padding cropped off);
    - in eval mode ``"flow_small"``: (B, 2, Hp/8, Wp/8), the estimate at 1/8 of the *padded*
      size, in pixels of that grid (here: the full-resolution estimate averaged over 8×8 blocks,
      divided by 8);
    - in training mode, instead of ``"flow_small"``, ``"flow_preds"``: a list of every
      iteration's flow (B, 2, H, W) at the input size, the last the estimate (``iters`` of them;
      ptlflow's RAFT runs 12).

    Args:
        net: the TinyRAFT inside (default: ``TinyRAFT(seed=seed, iters=iters)``).
    """

    flow_contract = "ptlflow"  # read by the refine job's --net (see docs/jobs.md)
    output_stride = 8

    def __init__(self, net: TinyRAFT | None = None, *, seed: int = 0, iters: int = 4) -> None:
        super().__init__()
        self.net = net if net is not None else TinyRAFT(seed=seed, iters=iters)
        self.padder = InputPadder(self.output_stride, mode="sintel")

    def forward(self, inputs: Mapping[str, Any]) -> dict[str, Tensor]:
        if not isinstance(inputs, Mapping) or "images" not in inputs:
            raise TypeError(f"inputs: expected ptlflow's dict {{'images': (B, 2, 3, H, W)}}, got {type(inputs).__name__}")
        images = inputs["images"]
        check_float_tensor(images, "inputs['images']")
        check_shape(images, "inputs['images']", ("B", 2, 3, "H", "W"), nonempty=("B", "H", "W"))
        if not skip_values(images):  # (no values while tracing, nor on the meta device)
            lo, hi = _value_range(images)
            if not (lo >= 0.0 and hi <= 1.0):  # (false for NaN, which the range then shows)
                raise ValueError(f"inputs['images']: expected BGR values in [0, 1], got [{lo:.4g}, {hi:.4g}]")
        H, W = images.shape[-2:]
        padding = self.padder.padding((H, W))
        rgb = padding.pad(images).flip(2) * 255.0      # BGR [0, 1] -> RGB 0..255, padded
        if self.training:  # (ptlflow's RAFT: every iteration's flow, cropped, and no flow_small)
            preds = [padding.unpad(f) for f in self.net(rgb[:, 0], rgb[:, 1])]
            return {"flows": preds[-1][:, None], "flow_preds": preds}
        up = self.net(rgb[:, 0], rgb[:, 1])[-1]        # (B, 2, Hp, Wp): divisible, TinyRAFT pads nothing
        small = F.avg_pool2d(up, self.output_stride) / self.output_stride
        return {"flows": padding.unpad(up)[:, None], "flow_small": small}


class TorchvisionRAFTStandIn(nn.Module):
    """torchvision's RAFT contract.

    ``forward(image1, image2, num_flow_updates=4)`` with (B, 3, H, W) RGB in [-1, 1] (what the
    transforms of ``Raft_Large_Weights`` produce), B >= 1 and H, W >= 1 divisible by 8 (else a
    ValueError, as torchvision raises for sides not divisible by 8); returns a list of
    ``num_flow_updates`` flows (B, 2, H, W), the last the estimate (``num_flow_updates``: an int
    >= 1, checked under its own name; values beyond [-1, 1] by more than 1 % of its width (0.02:
    a resize's overshoot, which ``FreespaceRefined(image_range=(-1, 1))`` lets through and
    torchvision's RAFT runs on) or NaN raise ValueError quoting the range that came; not read on
    the meta device). The default of 4 updates is not torchvision's
    (``RAFT.forward`` defaults to ``num_flow_updates=12``): it keeps the tests quick; pass 12
    explicitly for torchvision's list length.
    """

    flow_contract = "torchvision"  # read by the refine job's --net (see docs/jobs.md)

    def __init__(self, net: TinyRAFT | None = None, *, seed: int = 0) -> None:
        super().__init__()
        self.net = net if net is not None else TinyRAFT(seed=seed)

    def forward(self, image1: Tensor, image2: Tensor, num_flow_updates: int = 4) -> list[Tensor]:
        for name, im in (("image1", image1), ("image2", image2)):
            check_float_tensor(im, name)
            check_shape(im, name, ("B", 3, "H", "W"), nonempty=("B", "H", "W"))
        if image1.shape != image2.shape:
            raise ValueError(f"input images should have the same shape, instead got ({tuple(image1.shape)}) "
                             f"!= ({tuple(image2.shape)})")
        h, w = image1.shape[-2:]
        if h % 8 or w % 8:
            raise ValueError(f"input image H and W should be divisible by 8, instead got {h} (h) and {w} (w)")
        num_flow_updates = check_int(num_flow_updates, "num_flow_updates", minimum=1)
        if not skip_values(image1, image2):
            lo, hi = _value_range(image1, image2)
            if not (lo >= -1.02 and hi <= 1.02):  # (false for NaN, which the range then shows)
                raise ValueError(f"image1, image2: expected RGB values in [-1, 1], got [{lo:.4g}, {hi:.4g}]")
        # (an overshoot let through is clipped for TinyRAFT, which takes 0..255 exactly)
        return self.net(*((im.clamp(-1.0, 1.0) + 1.0) * 127.5 for im in (image1, image2)), iters=num_flow_updates)


def _value_range(*images: Tensor) -> tuple[float, float]:
    """The smallest and largest value of the images, NaN where any value is NaN (Python's min and
    max would drop a NaN depending on the order of their arguments)."""
    lo = torch.tensor([float(im.detach().amin()) for im in images], dtype=torch.float64, device="cpu").amin()
    hi = torch.tensor([float(im.detach().amax()) for im in images], dtype=torch.float64, device="cpu").amax()
    return float(lo), float(hi)


def ptlflow_raft(seed: int = 0) -> PtlflowRAFTStandIn:
    """Factory for the refine job's ``--net fsof_torch.training.standins:ptlflow_raft``."""
    return PtlflowRAFTStandIn(seed=seed).eval()


def torchvision_raft(seed: int = 0) -> TorchvisionRAFTStandIn:
    """Factory for the refine job's ``--net fsof_torch.training.standins:torchvision_raft``."""
    return TorchvisionRAFTStandIn(seed=seed).eval()
