"""Flow sources of the job: OpenCV DIS, the test net (random weights unless a state_dict is
given), or flow files written by any network."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch
from torch import Tensor

from .inputs import JobError

SOURCES = ("dis", "testnet", "files")


def dis_flow(image1: Tensor, image2: Tensor, *, preset: str = "medium") -> Tensor:
    """OpenCV DIS optical flow (``PRESET_MEDIUM`` by default) on grey images.

    Args:
        image1, image2: (3, H, W) float 0..255 RGB.

    Returns:
        (2, H, W) float32 forward flow in pixels.
    """
    import cv2
    import numpy as np

    presets = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}

    def grey(image: Tensor) -> "np.ndarray":
        rgb = image.detach().to(torch.float32).clamp(0, 255).permute(1, 2, 0).cpu().numpy()
        return cv2.cvtColor(rgb.round().astype(np.uint8), cv2.COLOR_RGB2GRAY)

    dis = cv2.DISOpticalFlow_create(presets[preset])
    flow = dis.calc(grey(image1), grey(image2), None)
    return torch.from_numpy(np.ascontiguousarray(flow.transpose(2, 0, 1))).to(torch.float32)


def make_source(name: str, *, weights: Path | None = None) -> Callable[[dict, Path | None], Tensor]:
    """A callable ``(pair, flow_file) -> flow (2, H, W)`` for source ``name``."""
    if name == "dis":
        return lambda pair, _file: dis_flow(pair["image1"], pair["image2"])
    if name == "testnet":
        from fsof_torch.training.testnet import TinyRAFT

        net = TinyRAFT(seed=0)
        if weights is not None:
            if not weights.is_file():
                raise JobError(f"--testnet-weights: no file at {str(weights)!r}")
            net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
        net.eval()

        def run(pair: dict, _file: Path | None) -> Tensor:
            with torch.no_grad():
                flows = net(pair["image1"].unsqueeze(0), pair["image2"].unsqueeze(0))
            return flows[-1][0].to(torch.float32)
        return run
    if name == "files":
        from fsof_torch.io import read_flow

        def read(pair: dict, file: Path | None) -> Tensor:
            if file is None:
                raise JobError("--flows: no flow file for this pair")
            flow, valid = read_flow(file)
            size = tuple(pair["image1"].shape[-2:])
            if tuple(flow.shape[-2:]) != size:
                raise JobError(f"--flows: {file.name} is {tuple(flow.shape[-2:])}, the images {size}")
            # invalid pixels of a flow file carry no prediction: NaN keeps them out of the fit
            return torch.where(valid, flow, torch.full_like(flow, float("nan")))
        return read
    raise JobError(f"--source: unknown flow source {name!r}; choose from {', '.join(SOURCES[:2])} or give --flows")
