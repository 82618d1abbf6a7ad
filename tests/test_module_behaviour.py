"""The library's modules and stateful objects as training and deployment code uses them: copied,
pickled, in DataLoader workers, saved and loaded, cast, wrapped in DistributedDataParallel and
called from several threads at once (docs/refinement.md#in-training-and-deployment-code)."""

from __future__ import annotations

import copy
import io
import pickle
import warnings
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

import fsof_torch as fs
from fsof_torch.refinement.gate import ImageGate


@pytest.fixture(scope="module")
def pairs():
    return [fs.render_pair("default", k, size=(96, 320)) for k in (1, 5)]


def _inputs(pair, seed):
    gt = pair["flow"][None]
    pred = gt + seed * torch.randn(gt.shape, generator=torch.Generator().manual_seed(seed))
    return pred, pair["road"][None], pair["camera"], pair["odometry"], (pair["image1"][None], pair["image2"][None])


def _equal(a, b):
    """Refiner outputs (tensors, containers, cameras, fits) equal bit for bit."""
    if isinstance(a, torch.Tensor):
        return a.dtype == b.dtype and a.shape == b.shape and torch.equal(a.nan_to_num(), b.nan_to_num())
    if isinstance(a, fs.Camera):
        return all(_equal(getattr(a, k), getattr(b, k)) for k in ("K", "height", "roll", "pitch"))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return a == b if isinstance(a, (str, int, float, bool, type(None))) else True


# -- repr -----------------------------------------------------------------------------------------

def test_refiner_repr_shows_the_options_that_are_not_the_defaults():
    assert repr(fs.FreespaceRefiner()) == "FreespaceRefiner(mode='replace', estimator=None, gate='auto')"
    assert repr(fs.FreespaceRefiner(mode="confidence", fit="flow")) == (
        "FreespaceRefiner(mode='confidence', scale=2.0, fit='flow', gate='auto')")
    text = repr(fs.FreespaceRefiner(min_pixels=10, warn=False, flow_keys="flow_up", fit="flow", fit_pitch=True,
                                    fit_options={"max_iter": 5}))
    assert text == ("FreespaceRefiner(mode='replace', fit='flow', gate='auto', min_pixels=10, flow_keys=('flow_up',), "
                    "warn=False, fit_pitch=True, fit_options={'max_iter': 5})")


def test_wrapper_repr_shows_its_own_options():
    net = fs.TinyRAFT(seed=0, iters=1)
    first = repr(fs.FreespaceRefined(net)).splitlines()[:2]
    assert first == ["FreespaceRefined(", "  road=None, pad=None, image_range=(0.0, 255.0)"]
    text = repr(fs.FreespaceRefined(net, road="auto", road_options={"z": 3.0}, pad=fs.InputPadder(8),
                                    image_range=(-1, 1)))
    assert text.splitlines()[1] == ("  road='auto', road_options={'z': 3.0}, pad=InputPadder(8, mode='sintel', "
                                    "pad_mode='replicate'), image_range=(-1.0, 1.0)")
