"""Tests of fsof_torch.warn: the library's warnings name the caller's file and line, whichever way
the library was reached (a function, its nn.Module twin, the refiner's mask="auto")."""

from __future__ import annotations

import math
import sys
import warnings

import pytest
import torch

from fsof_torch import Camera, FreespaceFlowLoss, FreespaceRefiner, refine_flow, road_flow
from fsof_torch.training.losses import freespace_flow_loss
from fsof_torch.warn import warn_user

pytestmark = pytest.mark.usefixtures("one_thread")


def caught(call) -> list[tuple[str, int, str]]:
    """``call()``'s warnings as (file, line, message), the line being the one that calls ``call``."""
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        call()
    return [(w.filename, w.lineno, str(w.message)) for w in got]


def here() -> int:
    """The line of the caller."""
    return sys._getframe(1).f_lineno


def test_warn_user_names_the_first_frame_outside_the_library():
    line = here() + 1
    got = caught(lambda: warn_user("a message"))
    assert got == [(__file__, line, "a message")]
    with pytest.warns(UserWarning, match="^another$"):
        warn_user("another", UserWarning)


@pytest.fixture(scope="module")
def pair():
    cam = Camera(torch.tensor([[130.0, 0.0, 80.0], [0.0, 130.0, 16.0], [0.0, 0.0, 1.0]]), 1.65)
    odo = {"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}
    flow = road_flow(cam, odo, (64, 160))[0].expand(2, -1, -1, -1).clone()
    flow[0, :, 50, 50] = math.nan
    road = torch.zeros(2, 1, 64, 160, dtype=torch.bool)
    road[:, :, 30:] = True
    return cam, odo, flow, road


def test_the_refiners_warnings_name_the_callers_line(pair):
    """refine_flow's warnings (a non-finite predicted pixel, a sample left unchanged) named the
    line above the caller's (or none, 'sys:1', from a script's top level), and through the module
    twin a line of torch's nn.Module.__call__."""
    cam, odo, flow, road = pair
    empty = road.clone()
    empty[1] = False
    expected = ["flow: 1 non-finite predicted pixels", "mask: samples [1] left unchanged"]
    for refine in (refine_flow, FreespaceRefiner()):
        line = here() + 1
        got = caught(lambda: refine(flow, empty, cam, odo))
        assert [(f, n) for f, n, _ in got] == [(__file__, line)] * 2, got
        assert [m[:len(e)] for (_, _, m), e in zip(got, expected)] == expected


def test_the_freespace_losss_warnings_name_the_callers_line(pair):
    """The freespace loss's warning through its module named the module's forward in losses.py."""
    cam, odo, flow, road = pair
    for loss in (freespace_flow_loss, FreespaceFlowLoss()):
        line = here() + 1
        got = caught(lambda: loss(flow, road, cam, odo))
        assert [(f, n) for f, n, _ in got] == [(__file__, line)], got
        assert got[0][2].startswith("flows: non-finite predicted pixels inside the road mask")


def test_the_road_detections_warnings_name_the_callers_line():
    """mask="auto" with images: the detection's warning (a sample whose road was not found) and
    the refinement's (its non-finite pixels), from the function and the module twin."""
    from fsof_torch.data.scene import render_pair

    p, q = render_pair("default", 10, size=(96, 320)), render_pair("default", 20, size=(96, 320))
    im1, im2 = torch.stack([p["image1"], q["image1"]]), torch.stack([p["image2"], q["image1"].clone()])
    pred = torch.stack([p["flow"], torch.zeros_like(q["flow"])])
    pred[0, :, 80:90, 150:170] = math.nan  # (on the road ahead)
    for refine in (refine_flow, FreespaceRefiner()):
        line = here() + 1
        got = caught(lambda: refine(pred, "auto", p["camera"], images=(im1, im2)))
        assert [(f, n) for f, n, _ in got] == [(__file__, line)] * 2, got
        assert got[0][2].startswith("mask: the road was not found in samples [1]")


def test_the_librarys_warnings_are_a_category_of_their_own(pair):
    """The library's warnings were plain RuntimeWarnings attributed to the caller's line: a filter
    on the module (``module="fsof_torch"``) silenced none of them, and one on the category silenced
    NumPy's and torch's as well. They are now FreespaceWarning, a RuntimeWarning that a filter can
    name alone."""
    import numpy as np

    import fsof_torch
    from fsof_torch import FlowMetricAccumulator, FreespaceWarning

    assert issubclass(FreespaceWarning, RuntimeWarning) and "FreespaceWarning" in fsof_torch.__all__
    cam, odo, flow, road = pair
    empty = road.clone()
    empty[1] = False
    calls = {"refine_flow": lambda: refine_flow(flow, empty, cam, odo),
             "FreespaceRefiner": lambda: FreespaceRefiner()(flow, empty, cam, odo),
             "freespace_flow_loss": lambda: freespace_flow_loss(flow, road, cam, odo),
             "FlowMetricAccumulator.compute": lambda: FlowMetricAccumulator().compute()}
    counts = {"refine_flow": 2, "FreespaceRefiner": 2, "freespace_flow_loss": 1, "FlowMetricAccumulator.compute": 1}
    for name, call in calls.items():
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            call()
        assert [w.category for w in got] == [FreespaceWarning] * counts[name], (name, got)
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            warnings.filterwarnings("ignore", category=FreespaceWarning)
            call()
            np.float64(1.0) / np.float64(0.0)  # (NumPy's RuntimeWarning: still shown)
        assert [(w.category, str(w.message)) for w in got] == [(RuntimeWarning, "divide by zero encountered in "
                                                                "scalar divide")], (name, got)
