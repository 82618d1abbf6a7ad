"""Figures that read without the code: every figure the refine job writes is built here.

Each figure has a title; flow images carry a colour-wheel legend with the magnitude at full
saturation; error maps carry a colour bar with the unit and the value where the colours saturate;
pixels without a value are mid grey in flows and error maps alike (a colour neither the flow
wheel nor the error colour map holds: black would read as an error of 0), named in the legend;
a frame larger than its panel is drawn reduced (a KITTI frame by 4), each drawn pixel the mean of
the pixels with a value it covers, so sparse ground truth stays visible;
image panels have pixel axes; the road mask is drawn as a black-and-white dashed outline (no
fill, so nothing under it changes colour and it cannot be taken for an object); before and after
stand side by side. A clip gets a summary plot over its pairs: each error before and after, and
every estimated motion and mounting field the job's records hold.

Builders return a ``matplotlib.figure.Figure`` (so tests and notebooks can inspect or show it);
:func:`save_figure` writes one as PNG atomically and closes it. matplotlib is imported inside the
functions; where no backend has been chosen they select the non-interactive Agg backend
(headless-safe), and they never switch a backend the caller chose or pyplot runs. Colour coding
itself (Middlebury flow colours, colour maps) is :mod:`fsof_torch.evaluation.visualize`.
"""

from __future__ import annotations

import io
import math
import numbers
import os
import re
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch
from torch import Tensor

from .._check import check_float_tensor, check_has_values, check_image_range, check_int, check_number, check_shape
from .visualize import NO_VALUE_RGB, flow_to_color

__all__ = ["FIGURE_DPI", "PairFigure", "clip_summary_figure", "colour_wheel", "drawing_factor", "pair_figure",
           "place_reduced", "reduce_values", "road_outline", "save_figure"]

#: resolution of the written PNGs
FIGURE_DPI = 80

# road outline: a white dashed line over a black one, visible on any colour of the flow wheel
# and of the error maps, and never a filled area that could be read as an object
_OUTLINE = ({"color": "black", "linewidth": 2.0, "linestyle": "-"},
            {"color": "white", "linewidth": 1.0, "linestyle": (0, (4, 3))})

_UNITS = {"x_d": ("lateral motion x_d", "m", 1.0), "z_d": ("forward motion z_d", "m", 1.0),
          "y_d": ("vertical motion y_d", "m", 1.0), "yaw": ("yaw", "deg", 180 / math.pi),
          "roll": ("camera roll over the road", "deg", 180 / math.pi),
          "pitch": ("camera pitch over the road", "deg", 180 / math.pi),
          "roll_change": ("roll change", "deg", 180 / math.pi), "pitch_change": ("pitch change", "deg", 180 / math.pi),
          "speed": ("speed", "m/s", 1.0), "yaw_rate": ("yaw rate", "deg/s", 180 / math.pi)}
# the camera the refinement used (a record's own "roll" / "pitch", radians): its mounting
_MOUNTING = {"roll": "camera roll (the refinement's mounting)", "pitch": "camera pitch (the refinement's mounting)"}


def _pyplot():
    """pyplot, with the non-interactive Agg backend where nobody chose one: a backend the caller
    selected (``matplotlib.use``, ``MPLBACKEND``, a matplotlibrc, a notebook's inline backend) or
    that pyplot already runs is left as it is, and so are the caller's open figures."""
    import sys

    import matplotlib

    if "matplotlib.pyplot" not in sys.modules and _backend_unchosen(matplotlib):
        matplotlib.use("Agg")  # (headless-safe: no window, no display needed)
    import matplotlib.pyplot as plt

    return plt


def _backend_unchosen(matplotlib: Any) -> bool:
    """Whether matplotlib's backend is still its automatic choice (no one has selected one)."""
    from matplotlib import rcsetup

    sentinel = getattr(rcsetup, "_auto_backend_sentinel", None)
    return sentinel is not None and dict.__getitem__(matplotlib.rcParams, "backend") is sentinel


def _reduce(x: Tensor, factor: int, mode: str = "area") -> Tensor:
    """(C, H, W) reduced by an integer factor: area average, or 'any' for a bool mask."""
    if factor <= 1:
        return x
    import torch.nn.functional as F

    if x.dtype == torch.bool:
        return F.max_pool2d(x[None].to(torch.uint8), factor, ceil_mode=True)[0].to(torch.bool)
    dtype = torch.float64 if x.dtype == torch.float64 else torch.float32
    return F.avg_pool2d(x[None].to(dtype), factor, ceil_mode=True, count_include_pad=False)[0]


def reduce_values(x: Tensor, has: Tensor, bad: Tensor, factor: int) -> tuple[Tensor, Tensor]:
    """A map (C, H, W) reduced by an integer factor for drawing: each drawn pixel the mean over
    its pixels with a value (``has``, (1, H, W) bool), so that sparse ground truth (KITTI's laser
    lines: 39 % of a road's pixels, under 3 % of its 3 x 3 blocks entirely) stays visible; and
    whether it has a value: some pixel has one, and none is ``bad`` (a value that should be there
    but is not finite, shown as no value rather than hidden by its neighbours). Returns the
    reduced map (float64, 0 where no value) and that flag (1, h, w). ``factor``: an int >= 1, such
    as :func:`drawing_factor` gives for the panel."""
    factor = check_int(factor, "factor", minimum=1)  # (2.5 was avg_pool2d's kernel_size error, 0 read as 1)
    x = torch.where(has, x.to(torch.float64), torch.zeros((), dtype=torch.float64, device=x.device))
    if factor <= 1:
        return x, has & ~bad
    share = _reduce(has.to(torch.float64), factor)  # 0, or at least 1 / factor² (averaged alike)
    mean = _reduce(x, factor) / share.clamp(min=0.5 / (factor * factor))
    return mean, (share > 0) & ~_reduce(bad, factor)


def drawing_factor(size: tuple[int, int], panel: tuple[float, float]) -> int:
    """The least integer reduction that fits an image of ``size`` (H, W) into a panel of ``panel``
    (h, w) pixels, so that matplotlib enlarges the picture a little and never shrinks it: shrunk
    by its nearest-neighbour drawing, it drops whole rows and columns (a reduction of a KITTI
    frame by 3, 414 columns into a 316-pixel panel, lost a quarter of them, and sparse ground
    truth's lines with them)."""
    scale = max(size[0] / max(panel[0], 1.0), size[1] / max(panel[1], 1.0))
    return max(1, math.ceil(scale - 1e-9))


def place_reduced(shown: Any, size: tuple[int, int], factor: int) -> None:
    """Place a picture (an ``AxesImage``) reduced by ``factor`` from an image of ``size`` (H, W)
    on axes set to the image's pixels: drawn pixel j over the pixels j f .. j f + f - 1 it is the
    mean of (:func:`reduce_values`; the last block, cut by the image's edge, reaches beyond the
    axes). Stretched over the image, ceil(W / f) drawn columns over W pixels drifted from it."""
    (H, W), f = size, check_int(factor, "factor", minimum=1)
    shown.set_extent((-0.5, -(-W // f) * f - 0.5, -(-H // f) * f - 0.5, -0.5))
    shown.axes.set_xlim(-0.5, W - 0.5)
    shown.axes.set_ylim(H - 0.5, -0.5)


def road_outline(mask: Tensor) -> list[Any]:
    """The outline of a bool road mask ((H, W), (1, H, W) or (1, 1, H, W)) as closed polygons of
    (u, v) pixel coordinates (NumPy (N, 2) arrays), from ``cv2.findContours``.

    A mask of another dtype (a float map gives no outline at all) or shape (a batch of masks)
    raises TypeError or ValueError naming ``mask``."""
    import cv2
    import numpy as np

    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        got = f"dtype {mask.dtype}" if isinstance(mask, Tensor) else type(mask).__name__
        raise TypeError(f"mask: expected a bool tensor, got {got} (threshold a soft mask first)")
    if not 2 <= mask.dim() <= 4 or any(n != 1 for n in mask.shape[:-2]):
        raise ValueError(f"mask: expected shape (H, W), (1, H, W) or (1, 1, H, W), got {tuple(mask.shape)}")
    m = mask.reshape(mask.shape[-2:]).detach().to(torch.uint8).cpu().numpy()
    contours, _ = cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in contours:
        pts = c[:, 0, :].astype(np.float64)
        if len(pts) >= 2:
            out.append(np.vstack([pts, pts[:1]]))  # closed
    return out


def _draw_outline(ax, polygons: list[Any]) -> None:
    from matplotlib.collections import LineCollection

    for style in _OUTLINE:
        ax.add_collection(LineCollection(polygons, **style))


def _outline_handle():
    import matplotlib.patheffects as pe
    from matplotlib.lines import Line2D

    return Line2D([], [], **_OUTLINE[1], label="road mask (outline)",
                  path_effects=[pe.Stroke(linewidth=2.0, foreground="black"), pe.Normal()])


def colour_wheel(max_flow: float, size: int = 101) -> Tensor:
    """The Middlebury colour coding of the disc of flows up to ``max_flow`` px: (size, size, 3)
    uint8 RGB, u to the right, v down (outside the disc white); ``size`` an int >= 1."""
    check_number(max_flow, "max_flow", positive=True)
    size = check_int(size, "size", minimum=1)  # (0 was named 'flow', 2.5 a TypeError from linspace)
    r = torch.linspace(-1.0, 1.0, size, dtype=torch.float64, device="cpu")  # (drawn by matplotlib)
    v, u = torch.meshgrid(r, r, indexing="ij")
    inside = (u * u + v * v) <= 1.0
    # the colours of flow / max_flow, which is the disc itself: drawn from it directly, as the
    # flow (u, v) * max_flow could come out a rounding error beyond max_flow at the rim and be
    # drawn darker there
    rgb = flow_to_color(torch.stack([u, v]), 1.0)[0]
    rgb = torch.where(inside[None], rgb, torch.full_like(rgb, 255))
    return rgb.permute(1, 2, 0)


def _wheel_axes(fig, rect: Sequence[float]) -> tuple[Any, Any]:
    """The colour-wheel legend's axes and image, to be filled by :func:`_show_wheel`."""
    ax = fig.add_axes(rect)
    shown = ax.imshow(colour_wheel(1.0).numpy(), extent=(-1.0, 1.0, 1.0, -1.0))
    ax.set_label("colour wheel")
    ax.set_xlabel("u (px)", fontsize=7, labelpad=1)
    ax.set_ylabel("v (px)", fontsize=7, labelpad=1)
    ax.tick_params(labelsize=6, length=2)
    ax.xaxis.set_major_formatter(_short_format())
    ax.yaxis.set_major_formatter(_short_format())
    return ax, shown


def _show_wheel(ax, shown, max_flow: float) -> None:
    """The colour wheel of flows up to ``max_flow`` px: picture, extent, ticks and title."""
    shown.set_data(colour_wheel(max_flow).numpy())
    shown.set_extent((-max_flow, max_flow, max_flow, -max_flow))
    ax.set_title(f"flow colour\nfull saturation {max_flow:.3g} px", fontsize=8)
    ax.set_xticks([-max_flow, 0, max_flow])
    ax.set_yticks([-max_flow, 0, max_flow])


def _short_format():
    from matplotlib.ticker import FuncFormatter

    return FuncFormatter(lambda x, _pos: f"{x:.3g}")


def _image_axes(ax, title: str, size: tuple[int, int], *, xlabel: bool, ylabel: bool) -> None:
    """Title and pixel axes of an image panel: three ticks a side (each tick is a costly object
    to draw), axis labels on the outer panels only."""
    H, W = size
    ax.set_title(title, fontsize=9)
    ax.set_xticks([0, _round(W / 2), _round(W - 1)])
    ax.set_yticks([0, _round(H / 2), _round(H - 1)])
    ax.tick_params(labelsize=6, length=2, labelbottom=xlabel, labelleft=ylabel)
    if xlabel:
        ax.set_xlabel("u (px)", fontsize=7, labelpad=1)
    if ylabel:
        ax.set_ylabel("v (px)", fontsize=7, labelpad=1)


def _round(x: float) -> int:
    """``x`` rounded to two significant digits (tick positions people read at a glance)."""
    if x < 10:
        return int(x)
    step = 10 ** (int(math.log10(x)) - 1)
    return int(x // step * step)


def pair_figure(*, flows: Mapping[str, Tensor], errors: Mapping[str, tuple[Tensor, Tensor]], road: Tensor,
                max_flow: float, error_vmax: float, error_label: str, title: str,
                images: tuple[Tensor, Tensor] | None = None, valid: Tensor | None = None) -> Any:
    """Flows and error maps of one pair, before and after refinement side by side.

    Args:
        flows: a dict of column title -> flow (2, H, W) px (e.g. ``{"before": ..., "after": ...}``);
            one column each, in order, at least one. Non-finite pixels have no value (mid grey).
        errors: column title -> ``(error map (1, H, W), valid (1, H, W) bool)`` for the second row
            (a title of ``flows`` missing here leaves that panel empty); invalid pixels, and
            valid ones whose error is not finite, have no value (mid grey).
        road: (1, H, W) bool road mask, drawn as an outline on every panel; every other map and
            image has its (H, W) (ValueError or TypeError naming the argument otherwise, e.g.
            ``flows['before']``).
        max_flow: flow magnitude at full colour saturation, px (one scale for all columns).
        error_vmax: error at the top of the colour bar, a finite number > 0 (ValueError naming
            it otherwise); larger errors saturate (the bar's arrow, drawn white in the maps).
        error_label: the error's name and unit for the colour bar, a str such as
            "end-point error (px)" (the error panels' titles are its name before " (").
        title: the figure's title.
        images: optional ``(image1, image2)`` (3, H, W) RGB 0..255, shown as a first column.
        valid: optional (1, H, W) bool for the flow row (e.g. a flow file's valid pixels).

        A frame larger than its panel is drawn reduced by an integer factor (4 for a KITTI
        frame): each drawn pixel shows the mean of the pixels with a value it covers, and has
        none where no pixel it covers is valid, or where a valid one is not finite.

        The maps and images may live on any device and carry autograd (a network's flow in
        training): their values are drawn. On the meta device (shapes only) a ValueError names
        the first one.

    Returns:
        the Figure: a row of flow panels with a colour-wheel legend, a row of error panels with
        a colour bar; every panel has the road outline, pixel axes and a title. (To draw many
        pairs, :class:`PairFigure` builds the figure once and redraws it.)
    """
    _check_pair(flows, errors, road, images, valid)  # (valid and max_flow too, before a figure is opened)
    check_number(max_flow, "max_flow", positive=True)
    figure = PairFigure(*PairFigure.layout_of(flows=flows, errors=errors, road=road, images=images,
                                              error_vmax=error_vmax, error_label=error_label))
    return figure.update(flows=flows, errors=errors, road=road, max_flow=max_flow, title=title,
                         images=images, valid=valid)


class PairFigure:
    """The figure of :func:`pair_figure`, built once and redrawn for each pair of one layout.

    Building a figure (its axes, ticks, colour bar and legend) costs matplotlib about as much as
    drawing it, so a job that writes a figure per pair builds one per layout, calls
    :meth:`update` for each pair and :func:`save_figure` with ``close=False``, and :meth:`close`
    at the end. :meth:`update` replaces everything that depends on the pair (pictures, road
    outline, titles, colour wheel): the figure drawn equals, pixel for pixel, one that
    :func:`pair_figure` builds afresh for that pair.

    Args (the layout, as :meth:`layout_of` returns it):
        size: (H, W) of the images.
        with_errors: per flow column, whether it has an error panel.
        images: whether the first column shows the two images.
        error_vmax, error_label: the error maps' colour bar (as in :func:`pair_figure`).
    """

    def __init__(self, size: tuple[int, int], with_errors: tuple[bool, ...], images: bool,
                 error_vmax: float, error_label: str) -> None:
        import numpy as np

        plt = _pyplot()
        error_vmax = _check_vmax(error_vmax, error_label)
        if not with_errors:
            raise ValueError(f"with_errors: expected one entry per flow column (at least one), got {with_errors!r}")
        self.layout = (tuple(size), tuple(with_errors), bool(images), error_vmax, error_label)
        H, W = size
        ncol = len(with_errors) + bool(images)
        panel_w = 4.2
        panel_h = panel_w * H / W
        fig_w, fig_h = panel_w * ncol + 1.8, 2 * panel_h + 1.5
        fig = self.figure = plt.figure(figsize=(fig_w, fig_h), dpi=FIGURE_DPI)
        self.title = fig.suptitle("", fontsize=10)
        right = 1.0 - 1.5 / (panel_w * ncol + 1.8)
        left, bottom, top = 0.45 / (panel_w * ncol + 1.8), 0.09, 0.84
        gap = 0.35 / (panel_w * ncol + 1.8)
        col_w = (right - left - gap * (ncol - 1)) / ncol
        row_h = (top - bottom - 0.11) / 2
        # (the picture, its aspect kept, is drawn at most as large as the panel's box)
        self.factor = drawing_factor((H, W), (row_h * fig_h * FIGURE_DPI, col_w * fig_w * FIGURE_DPI))
        rows = (bottom + row_h + 0.11, bottom)
        h, w = -(-H // self.factor), -(-W // self.factor)  # the reduced pictures' size
        blank_rgb, blank_error = np.zeros((h, w, 3), dtype=np.uint8), np.full((h, w), np.nan)
        # axis labels on the panels that exist: the lowest of each column, the left-most of each row
        lower = [True] * bool(images) + [bool(e) for e in with_errors]  # a column's second-row panel
        first_lower = lower.index(True) if any(lower) else None

        def panel(j: int, r: int, blank: Any, **kw: Any) -> tuple[Any, Any]:
            ax = fig.add_axes((left + j * (col_w + gap), rows[r], col_w, row_h))
            shown = ax.imshow(blank, interpolation="nearest", **kw)
            place_reduced(shown, (H, W), self.factor)  # (axes in pixels of the full image)
            _draw_outline(ax, [])
            _image_axes(ax, "", (H, W), xlabel=r == 1 or not lower[j], ylabel=j == (0 if r == 0 else first_lower))
            return ax, shown

        self.image_panels = [panel(0, r, blank_rgb) for r in range(2)] if images else []
        for (ax, _), name in zip(self.image_panels, ("image 1 (time t)", "image 2 (time t+1)")):
            ax.set_title(name, fontsize=9)
        cmap = _error_cmap()
        self.flow_panels, self.error_panels = [], []
        for j, has_error in enumerate(with_errors, start=int(bool(images))):
            self.flow_panels.append(panel(j, 0, blank_rgb))
            self.error_panels.append(panel(j, 1, blank_error, cmap=cmap, vmin=0.0, vmax=error_vmax)
                                     if has_error else None)
        self.wheel = _wheel_axes(fig, (right + 0.25 * (1 - right), rows[0] + row_h * 0.08, 0.55 * (1 - right),
                                       row_h * 0.75))
        shown = next((p[1] for p in self.error_panels if p is not None), None)
        if shown is not None:
            cax = fig.add_axes((right + 0.3 * (1 - right), bottom + row_h * 0.05, 0.08 * (1 - right), row_h * 0.9))
            bar = fig.colorbar(shown, cax=cax, extend="max")
            bar.set_label(f"{error_label}\nsaturates at {error_vmax:g}", fontsize=7)
            bar.ax.tick_params(labelsize=6)
        self.legend = fig.legend(handles=[_outline_handle(), _invalid_handle()], loc="upper right", fontsize=7,
                                 framealpha=0.9, bbox_to_anchor=(0.995, 0.995))

    def _fit_title(self) -> None:
        """The title centred in the width left of the legend, its font (10 pt) made smaller where
        the title is wider than that: a long one (a census error's, a long pair name) ran under it."""
        room = self.legend.get_window_extent().x0 - 8  # (px: the legend's left edge, less a margin; any backend)
        self.title.set(fontsize=10, x=room / 2 / self.figure.bbox.width)
        width = self.title.get_window_extent().width
        if width > room:
            self.title.set_fontsize(max(9.7 * room / width, 5))  # (a margin: widths do not scale exactly)

    @staticmethod
    def layout_of(*, flows: Mapping[str, Tensor], errors: Mapping[str, Any], road: Tensor,
                  images: Any, error_vmax: float, error_label: str) -> tuple:
        """The layout of a :func:`pair_figure` call, as :class:`PairFigure` takes it (hashable).
        The maps and images are checked as :func:`pair_figure` checks them."""
        _check_pair(flows, errors, road, images, None)
        return (tuple(road.shape[-2:]), tuple(name in errors for name in flows), images is not None,
                _check_vmax(error_vmax, error_label), error_label)

    def update(self, *, flows: Mapping[str, Tensor], errors: Mapping[str, tuple[Tensor, Tensor]], road: Tensor,
               max_flow: float, title: str, images: tuple[Tensor, Tensor] | None = None,
               valid: Tensor | None = None) -> Any:
        """Draw one pair (the arguments of :func:`pair_figure` but the layout's) into the figure
        and return the figure.

        Raises ValueError when the pair does not fit the layout (another size, columns with and
        without error panels, images or none): build another :class:`PairFigure` for it."""
        import numpy as np

        _check_pair(flows, errors, road, images, valid)
        # drawn from the host: maps that carry autograd (a network's flow in training) or live on
        # a GPU are taken as their values there
        host = lambda t: None if t is None else t.detach().cpu()  # noqa: E731
        flows = {k: host(f) for k, f in flows.items()}
        errors = {k: (host(e), host(v)) for k, (e, v) in errors.items()}
        road, valid = host(road), host(valid)
        images = None if images is None else tuple(host(im) for im in images)
        size, with_errors, has_images, _, label = self.layout
        got = (tuple(road.shape[-2:]), tuple(name in errors for name in flows), images is not None)
        if got != (size, with_errors, has_images):
            raise ValueError(f"flows: this pair's layout (size, error panels, images) {got} differs from the "
                             f"figure's {(size, with_errors, has_images)}; build a PairFigure for it")
        factor = self.factor
        outline = road_outline(road)
        self.title.set_text(title)
        self._fit_title()
        for (_, shown), im in zip(self.image_panels, images or ()):
            rgb = _reduce(im.float(), factor).clamp(0, 255).round().to(torch.uint8)
            shown.set_data(rgb.permute(1, 2, 0).numpy())
        for (ax, shown), error_panel, name in zip(self.flow_panels, self.error_panels, flows):
            f = flows[name]
            finite = torch.isfinite(f).all(dim=0, keepdim=True)
            has = finite if valid is None else finite & valid
            # a drawn pixel shows the mean of its pixels with a value (a sparse valid map stays
            # visible); no value where none has one, or where a valid pixel's flow is not finite
            mean, ok_r = reduce_values(f, has, ~finite if valid is None else valid & ~finite, factor)
            rgb = flow_to_color(mean, max_flow, valid=ok_r)[0]
            rgb = torch.where(ok_r, rgb, torch.tensor(NO_VALUE_RGB, dtype=torch.uint8, device=rgb.device).view(3, 1, 1))
            shown.set_data(rgb.permute(1, 2, 0).numpy())
            ax.set_title(f"flow, {name}", fontsize=9)
            if error_panel is None:
                continue
            err, ok_e = errors[name]
            # the mean of the valid pixels a drawn pixel covers (sparse ground truth stays
            # visible); a valid pixel whose error is not finite gives it no value (not an error of 0)
            finite = torch.isfinite(err)
            e, ok_r = reduce_values(err, ok_e & finite, ok_e & ~finite, factor)
            e, ok_r = e[0].numpy(), ok_r[0].numpy()
            # NaN where there is no value: drawn in the colour map's "bad" colour, as a masked
            # array would be (matplotlib masks NaN itself)
            error_panel[1].set_data(np.where(ok_r, e, np.nan))
            error_panel[0].set_title(f"{label.split(' (')[0]}, {name}", fontsize=9)
        for ax, _ in [*self.image_panels, *self.flow_panels, *(p for p in self.error_panels if p is not None)]:
            for lines in ax.collections:  # the two lines of the road outline
                lines.set_segments(outline)
        _show_wheel(*self.wheel, max_flow)
        return self.figure

    def close(self) -> None:
        """Close the figure (pyplot keeps it open until then)."""
        _pyplot().close(self.figure)


def _check_pair(flows: Mapping[str, Tensor], errors: Mapping[str, tuple[Tensor, Tensor]], road: Tensor,
                images: tuple[Tensor, Tensor] | None, valid: Tensor | None) -> None:
    """Every map and image of a pair figure at the road's (H, W), with its dtype and values: a
    flow of another size was stretched over the panel silently, a valid map of another size or
    dtype failed deep inside torch, a meta tensor in a NotImplementedError from the outline; no
    flow column at all divided by zero in the layout."""
    for name, value in (("flows", flows), ("errors", errors)):
        if not isinstance(value, Mapping):
            raise TypeError(f"{name}: expected a dict of column title -> "
                            f"{'flow' if name == 'flows' else '(error map, valid)'}, got {type(value).__name__}")
    if not flows:
        raise ValueError("flows: expected at least one flow column, got an empty dict")
    _check_bool(road, "road")
    dims = check_shape(road, "road", (1, "H", "W"))
    for name, flow in flows.items():
        check_float_tensor(flow, f"flows[{name!r}]")
        check_shape(flow, f"flows[{name!r}]", (2, "H", "W"), dims)
    for name, entry in errors.items():
        if name not in flows:
            raise ValueError(f"errors[{name!r}]: no flow column of that name; flows has {list(flows)}")
        if not isinstance(entry, (tuple, list)) or len(entry) != 2:
            got = f"{type(entry).__name__} of {len(entry)}" if isinstance(entry, (tuple, list)) else type(entry).__name__
            raise TypeError(f"errors[{name!r}]: expected (error map, valid), got {got}")
        check_float_tensor(entry[0], f"errors[{name!r}][0]")
        check_shape(entry[0], f"errors[{name!r}][0]", (1, "H", "W"), dims)
        _check_bool(entry[1], f"errors[{name!r}][1]")
        check_shape(entry[1], f"errors[{name!r}][1]", (1, "H", "W"), dims)
    if images is not None:
        if not isinstance(images, (tuple, list)) or len(images) != 2:
            raise TypeError(f"images: expected (image1, image2), got {type(images).__name__}")
        for k, image in enumerate(images):
            if not isinstance(image, Tensor) or image.dtype == torch.bool or image.is_complex():
                got = f"dtype {image.dtype}" if isinstance(image, Tensor) else type(image).__name__
                raise TypeError(f"images[{k}]: expected a real tensor (3, H, W) on 0..255, got {got}")
            check_shape(image, f"images[{k}]", (3, "H", "W"), dims)
            check_image_range(image.float(), f"images[{k}]", 255.0)
    if valid is not None:
        _check_bool(valid, "valid")
        check_shape(valid, "valid", (1, "H", "W"), dims)
    named = {"road": road, "valid": valid, **{f"flows[{k!r}]": f for k, f in flows.items()},
             **{f"errors[{k!r}][{i}]": t for k, entry in errors.items() for i, t in enumerate(entry)},
             **{f"images[{k}]": im for k, im in enumerate(images or ())}}
    for name, t in named.items():
        check_has_values(t, name, "to draw")  # (the meta device's tensors: shapes only)


def _check_bool(mask: object, name: str) -> None:
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        got = f"dtype {mask.dtype}" if isinstance(mask, Tensor) else type(mask).__name__
        raise TypeError(f"{name}: expected a bool tensor (1, H, W), got {got} (threshold a soft map first)")


def _check_vmax(error_vmax: object, error_label: object) -> float:
    """The error maps' saturation value: a finite number > 0 (NaN drew a bar "saturates at nan"
    over a made-up scale, 0 or a negative value maps saturated white everywhere); and their
    label, a str (the panels' titles are cut from it)."""
    if not isinstance(error_label, str):
        raise TypeError(f"error_label: expected a str such as 'end-point error (px)', got "
                        f"{type(error_label).__name__} {error_label!r}")
    return check_number(error_vmax, "error_vmax", positive=True)


def _invalid_handle():
    from matplotlib.patches import Patch

    return Patch(facecolor=_no_value_colour(), edgecolor="black", label="no value (invalid / out of view / not finite)")


def _no_value_colour() -> tuple[float, float, float]:
    """:data:`~fsof_torch.evaluation.visualize.NO_VALUE_RGB` as matplotlib's 0-1 RGB."""
    return tuple(c / 255.0 for c in NO_VALUE_RGB)


def _error_cmap():
    import matplotlib

    # no value: mid grey (inferno's 0 is near black); beyond the saturation value: white, so
    # both stand out of the map
    return matplotlib.colormaps["inferno"].with_extremes(bad=_no_value_colour(), over="white")


def clip_summary_figure(records: Sequence[Mapping[str, Any]], *, errors: Mapping[str, str], title: str) -> Any:
    """A clip's pairs over time: each error before (dashed) and after (solid) refinement per variant,
    in the variant's colour (each variant measures the prediction on its own pixels), and every
    estimated field of the records' ``odometry`` (angles in degrees; the given odometry as a
    reference line), and the records' own ``roll``, ``pitch`` (the camera the refinement used)
    where they are not the estimated attitude itself. A record with ``refined`` False (a pair
    left unrefined, which used no motion) is a gap in the lines of the motion and mounting panels.

    Args:
        records: the job's per-pair records of one flow source (``pair``, ``variant``,
            ``before``/``after`` metrics, ``odometry`` dict (a null field: no value), ``roll``,
            ``pitch``, optionally ``refined`` and ``odometry_given``), in time order: the pairs go along the x axis in the order they
            first appear (their names are not sorted: '10' would come before '5'), named under
            the lowest panel of each column (each pair up to 12, else about 12 of them). Fields are
            read as they come: a field new to the records shows up as a panel of its own.
        errors: the metrics plotted, one panel each, as record key -> name and unit, e.g.
            ``{"epe_road": "end-point error (px), road", "census_road": "census distance, road"}``
            (a key no record holds gets no panel).
        title: the figure's title.

    Values are numbers (Python, NumPy or one-element tensors) or None. Records that are not so (no
    ``pair`` or ``variant``, a metric that is not a number or None) raise a TypeError or ValueError
    naming the record, before a figure is opened.
    """
    _check_records(records, errors)
    # (NumPy and one-element tensor values as Python floats: a field of them had no panel at all)
    records = [{**r, **{k: _as_float(r[k]) for k in ("roll", "pitch") if k in r},
                **{p: {k: _as_float(v) for k, v in r[p].items()}
                   for p in ("before", "after", "odometry", "odometry_given") if p in r}} for r in records]
    plt = _pyplot()
    # the records' order, the job's time order (sorted names would put '10' before '5')
    pairs = list(dict.fromkeys(r["pair"] for r in records))
    index = {p: i for i, p in enumerate(pairs)}
    variants = list(dict.fromkeys(r["variant"] for r in records))
    # (in the records' key order; a field only null, as in the records of pairs left unrefined, has no panel)
    fields = [k for k in dict.fromkeys(k for r in records for k in r.get("odometry", {}))
              if any(isinstance(r.get("odometry", {}).get(k), (int, float)) for r in records)]
    # the mounting the refinement used, where it is not the estimated attitude itself
    mounting = [k for k in ("roll", "pitch") if any(isinstance(r.get(k), (int, float)) and r.get("refined") is not False
                                                    and r.get(k) != r.get("odometry", {}).get(k) for r in records)]
    error_keys = [k for k in errors if any(k in r.get("before", {}) for r in records)]
    panels = [*error_keys, *fields, *(("mounting", k) for k in mounting)]
    ncol = 2
    nrow = max(1, math.ceil(len(panels) / ncol))
    height = 2.6 * nrow + 1.1
    fig, axes = plt.subplots(nrow, ncol, figsize=(11, height), dpi=FIGURE_DPI, squeeze=False, sharex=True)
    # a fixed layout (tight_layout would draw the figure once more to measure its texts), in
    # inches from the edges: the title above the first row's panel titles
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.75 / height, top=1 - 0.85 / height,
                        wspace=0.25, hspace=0.45)
    fig.suptitle(title, fontsize=10, y=1 - 0.2 / height, va="top")
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    x_of = lambda rs: [index[r["pair"]] for r in rs]  # noqa: E731
    for k, panel in enumerate(panels):
        ax = axes[k // ncol][k % ncol]
        if panel in error_keys:
            # a before line per variant (dashed, hollow markers) in the colour of its after: each
            # variant measures the prediction on the pixels both its flows define, so the
            # befores of a pair differ between variants
            for c, v in enumerate(variants):
                colour = colours[c % len(colours)]
                for stage, style in (("before", {"linestyle": "--", "mfc": "none"}), ("after", {})):
                    rs = sorted((r for r in records if r["variant"] == v and panel in r.get(stage, {})),
                                key=lambda r: index[r["pair"]])
                    ax.plot(x_of(rs), [r[stage][panel] for r in rs], color=colour, marker="o", ms=3,
                            label=f"{stage}, {v}", **style)
            ax.set_ylabel(errors[panel], fontsize=8)
            name = re.sub(r" \([^)]*\)", "", errors[panel])  # the unit is on the y axis
            ax.set_title(f"{name}: before and after refinement", fontsize=9)
        else:
            own = isinstance(panel, tuple)  # ("mounting", key): the record's own camera
            key = panel[1] if own else panel
            name, unit, scale = _UNITS.get(key, (key, "", 1.0))
            if own:
                name = _MOUNTING[key]

            def value(r: Mapping[str, Any]) -> Any:
                # (the mounting panel: only where the camera used is not the variant's own estimate;
                # a pair left unrefined, ``refined`` False, used neither)
                if r.get("refined") is False:
                    return None
                estimate = r.get("odometry", {}).get(key)
                return (r.get(key) if r.get(key) != estimate else None) if own else estimate

            for c, v in enumerate(variants):
                rs = sorted((r for r in records if r["variant"] == v), key=lambda r: index[r["pair"]])
                # (a pair without a value is a gap in the line, not bridged as if it had one between)
                ys = [scale * value(r) if isinstance(value(r), (int, float)) else math.nan for r in rs]
                if not all(map(math.isnan, ys)):  # (the colour stays the variant's on every panel)
                    ax.plot(x_of(rs), ys, color=colours[c % len(colours)], marker="o", ms=3, label=v)
            given = {r["pair"]: r["odometry_given"][key] for r in records
                     if not own and isinstance(r.get("odometry_given"), Mapping) and key in r["odometry_given"]}
            if given:
                xs = sorted(given, key=index.get)
                ax.plot([index[p] for p in xs], [scale * given[p] for p in xs], color="black", linestyle="--",
                        marker="x", ms=4, label="given (odometry / poses)")
            # (the mounting's name has its own brackets: the unit goes into them, not a second pair)
            label = f"{name[:-1]}, {unit})" if unit and name.endswith(")") else f"{name} ({unit})" if unit else name
            ax.set_ylabel(label, fontsize=8)
            ax.set_title(("" if own else "estimated motion: ") + name, fontsize=9)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7, loc="best")
    for k in range(len(panels), nrow * ncol):
        axes[k // ncol][k % ncol].set_visible(False)
    # the pair axis under the lowest visible panel of each column (with an odd number of panels
    # the right column ends a row higher); the axes share it, so one locator serves all
    for c in range(min(ncol, len(panels))):
        ax = axes[(len(panels) - 1 - c) // ncol][c]
        ax.set_xlabel("pair", fontsize=8)
        if len(pairs) <= 12:
            ax.set_xticks(range(len(pairs)))
            ax.set_xticklabels(pairs, rotation=30, fontsize=6)
        else:  # whole positions only, named by their pair
            from matplotlib.ticker import FuncFormatter, MaxNLocator

            ax.xaxis.set_major_locator(MaxNLocator(nbins=12, integer=True))
            ax.xaxis.set_major_formatter(FuncFormatter(
                lambda x, _pos: pairs[round(x)] if x == round(x) and 0 <= x < len(pairs) else ""))
            ax.tick_params(axis="x", labelrotation=30, labelsize=6)
        ax.tick_params(labelbottom=True)
    return fig


def _check_records(records: object, errors: object) -> None:
    """The records and errors of :func:`clip_summary_figure` (a record without a variant was a
    KeyError, a metric given as text a panel of text categories)."""
    if not isinstance(errors, Mapping) or not all(isinstance(v, str) for v in errors.values()):
        raise TypeError(f"errors: expected a dict of record key -> name and unit (str), got {errors!r:.80}")
    if isinstance(records, (str, bytes, Mapping)) or not isinstance(records, Sequence):
        raise TypeError(f"records: expected a list of per-pair record dicts, got {type(records).__name__}")
    for i, r in enumerate(records):
        if not isinstance(r, Mapping):
            raise TypeError(f"records[{i}]: expected a dict, got {type(r).__name__}")
        missing = [k for k in ("pair", "variant") if k not in r]
        if missing:
            raise ValueError(f"records[{i}]: missing {missing}; expected a record with 'pair' and 'variant', "
                             f"got keys {sorted(map(str, r))}")
        for part in ("before", "after", "odometry", "odometry_given"):
            if part in r and not isinstance(r[part], Mapping):
                raise TypeError(f"records[{i}][{part!r}]: expected a dict, got {type(r[part]).__name__}")
        for part, k in ((part, k) for part in ("before", "after") for k in errors):
            v = r.get(part, {}).get(k)
            if v is not None and (isinstance(v, bool) or not isinstance(_as_float(v), (int, float))):
                raise TypeError(f"records[{i}][{part!r}][{k!r}]: expected a number or None, got "
                                f"{type(v).__name__} {v!r:.40}")


def _as_float(v: object) -> object:
    """A NumPy real or a one-element real tensor as a Python float; anything else as it is."""
    if isinstance(v, Tensor) and v.numel() == 1 and v.dtype != torch.bool and not v.is_complex():
        return float(v)
    return float(v) if isinstance(v, numbers.Real) and not isinstance(v, (bool, int, float)) else v


def save_figure(fig: Any, path: str | os.PathLike, *, close: bool = True) -> Path:
    """Write a Figure as PNG atomically (:func:`fsof_torch.io.write_bytes`) and close it
    (``close=False`` keeps it open, e.g. a :class:`PairFigure` to redraw).

    ``path`` must end in ``.png`` (any case): another suffix (``.pdf``, ``.svg``, ``.jpg``) is a
    ValueError naming ``path``, and ``fig`` without a ``savefig`` method a TypeError naming ``fig``,
    both before anything is written or closed. (For another format call ``fig.savefig`` itself.)"""
    from ..io.atomic import write_bytes

    if not callable(getattr(fig, "savefig", None)):
        raise TypeError(f"fig: expected a matplotlib Figure, got {type(fig).__name__}")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a str or os.PathLike, got {type(path).__name__}")
    if Path(path).suffix.lower() != ".png":
        # (PNG bytes under a .pdf or .jpg name: viewers that go by the suffix take the file for a broken one)
        raise ValueError(f"path: save_figure writes PNG, so expected a .png path, got {str(path)!r}; for "
                         f"another format call fig.savefig(path) itself")
    plt = _pyplot()
    buf = io.BytesIO()
    try:
        # zlib level 3 rather than PIL's default 6: the same pixels, half the time to encode
        # (a job figure: 29 ms against 64 ms), the file about 9 % larger
        fig.savefig(buf, format="png", dpi=fig.dpi, pil_kwargs={"compress_level": 3})
    finally:
        if close:
            plt.close(fig)
    return write_bytes(path, buf.getvalue())
