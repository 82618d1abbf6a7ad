"""One place for input validation: typed errors that name the argument and quote what came (and
the modes the package's code runs in: tracing, autocast, inference mode; at the end).

Shape letters are bound across arguments: ``check_shape(flow, "flow", ("B", 2, "H", "W"), dims)``
followed by ``check_shape(mask, "mask", ("B", 1, "H", "W"), dims)`` requires the same B, H, W.
Value checks (finite, positive, in range) look at tensor values and are skipped while
``torch.compile`` or ``torch.export`` traces, where a data-dependent branch would break the graph,
and for tensors on the ``meta`` device, which have shapes but no values (torch's own value checks
skip them too, so shape inference runs through the library). The device checks
(:mod:`fsof_torch.devices`) are imported here, with the rest.
"""

from __future__ import annotations

import contextlib
import contextvars
import copy
import dataclasses
import functools
import math
import numbers
import os
from pathlib import Path
from collections.abc import Iterable, Mapping
from typing import Any, Callable, ContextManager, Sequence, TypeVar

import torch
from torch import Tensor

from .devices import check_device, check_has_values, check_same_device, to_device

__all__ = [
    "check_shape", "check_float_tensor", "check_mask", "all_finite", "known_finite", "known_images",
    "trust_image_range", "host_path", "device_paths", "check_finite", "check_all_finite", "check_positive",
    "check_size", "check_number", "check_bool", "check_int", "is_number", "option_error", "check_names",
    "check_mapping", "check_keywords", "check_fit_flags", "check_data_range", "check_image_range",
    "as_batch_param", "resolve_batch", "tracing", "skip_values", "result_dtype", "held_by", "as_path", "autocast_off",
    "batch_choices", "check_device", "check_has_values", "check_same_device", "to_device", "as_chw_flow", "inference",
    "ordinary", "same_mapping", "summary_repr",
]


def tracing() -> bool:
    """True while torch.compile / torch.export traces: skip value-dependent checks then."""
    return torch.compiler.is_compiling()


def skip_values(*tensors: object) -> bool:
    """True where value checks cannot run: while tracing, or when a tensor is on the meta device."""
    return tracing() or any(isinstance(t, Tensor) and t.device.type == "meta" for t in tensors)


def _fmt_shape(shape: Sequence[object]) -> str:
    inner = ", ".join(str(s) for s in shape)
    return f"({inner},)" if len(shape) == 1 else f"({inner})"


def check_float_tensor(x: object, name: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")
    return x


def check_mask(x: object, name: str) -> Tensor:
    """A mask: a bool tensor (a 0/1 or probability map must be thresholded by the caller)."""
    if not isinstance(x, Tensor) or x.dtype != torch.bool:
        got = f"dtype {x.dtype}" if isinstance(x, Tensor) else type(x).__name__
        raise TypeError(f"{name}: expected a bool tensor (B, 1, H, W), got {got}")
    return x


def check_shape(
    x: Tensor, name: str, pattern: Sequence[int | str], dims: dict[str, int] | None = None,
    *, nonempty: Sequence[str] = ("H", "W"),
) -> dict[str, int]:
    """Check ``x.shape`` against ``pattern`` (ints fixed, letters bound through ``dims``).

    The letters in ``nonempty`` (by default the image sides H and W) must be at least 1: an image
    without rows or columns has no pixel to warp, filter or evaluate."""
    dims = {} if dims is None else dims
    want = _fmt_shape(pattern)
    if x.dim() != len(pattern):
        raise ValueError(f"{name}: expected shape {want}, got {_fmt_shape(tuple(x.shape))}")
    for size, p in zip(x.shape, pattern):
        if isinstance(p, str) and p in nonempty and size < 1:
            raise ValueError(f"{name}: expected shape {want} with {p} >= 1, got {_fmt_shape(tuple(x.shape))}")
        if isinstance(p, int):
            if size != p:
                raise ValueError(f"{name}: expected shape {want}, got {_fmt_shape(tuple(x.shape))}")
        else:
            bound = dims.get(p)
            if bound is None:
                dims[p] = int(size)
            elif bound != size:
                raise ValueError(
                    f"{name}: expected shape {want} with {p}={bound} (from an earlier argument), "
                    f"got {_fmt_shape(tuple(x.shape))}"
                )
    return dims


def all_finite(x: Tensor) -> bool:
    """Whether every value of ``x`` is finite (a host read; see :func:`skip_values` for tracing).

    A float tensor is judged by its minimum and maximum, found in one pass: NaN propagates into
    both, and an inf is one of them. On the CPU that is about ten times faster than
    ``torch.isfinite(x).all()``, which writes a bool per value first (a 2 x 375 x 1242 float32
    flow: 0.18 ms against 2.4 ms), and this check runs at every public boundary."""
    if x.numel() == 0 or not (x.is_floating_point() or x.is_complex()):
        return True  # integers and bools are always finite
    if any(x is t for t in _KNOWN_FINITE.get()):
        return True  # (see known_finite)
    if x.is_complex():
        return bool(torch.isfinite(x).all())
    lo, hi = torch.aminmax(x.detach())
    return bool(torch.isfinite(lo) & torch.isfinite(hi))  # one host read


_KNOWN_FINITE: contextvars.ContextVar[tuple[Tensor, ...]] = contextvars.ContextVar("known_finite", default=())
_KNOWN_IMAGES: contextvars.ContextVar[tuple[Tensor, ...]] = contextvars.ContextVar("known_images", default=())
_TRUST_IMAGE_RANGE: contextvars.ContextVar[tuple[bool, ...]] = contextvars.ContextVar("trust_image_range", default=())


@contextlib.contextmanager
def _known(var: contextvars.ContextVar, tensors: tuple):
    """``tensors`` added to the promises of ``var`` for the block (and the thread or task)."""
    token = var.set(var.get() + tensors)
    try:
        yield
    finally:
        var.reset(token)


def known_finite(*tensors: Tensor):
    """Within the block, :func:`all_finite` of one of ``tensors`` (the very objects) is True
    without a pass over its values: for a caller that has just established it and hands the tensors
    on to code that checks again (the refiner's flow for its estimator: a planar start's test of the
    whole flow, a pass and a host read). Scoped to the block (and to the thread or task)."""
    return _known(_KNOWN_FINITE, tensors)


def known_images(*images: Tensor):
    """Within the block, :func:`check_image_range` of one of ``images`` (the very objects) on
    0..255 passes without a pass over its values: for a caller that checked the images they come
    from and hands them on to code that checks again (the refiner's frames for its estimator, which
    may be their grey levels: a weighted mean of colours that were finite and in range is too, while
    the "0..1" guess, which judges a frame by its brightest value, would take a dim frame's grey
    for a 0..1 image that its colours were not). Scoped to the block (and to the thread or task)."""
    return _known(_KNOWN_IMAGES, images)


def trust_image_range():
    """Within the block, images are taken to be on the range the caller states (``data_range``, ``image_range``,
    0..255 for the refiner) however dark: for a caller that knows it (8-bit files). Outside it, an image on 0..255
    whose values all lie in [0, 1] raises as a likely 0..1 image (each sample of a batch judged alone); a real
    frame can be that dark (a lens cap, a tunnel). Values out of range or not finite raise all the same."""
    return _known(_TRUST_IMAGE_RANGE, (True,))


def trusted_image_range() -> bool:
    return bool(_TRUST_IMAGE_RANGE.get())  # (within trust_image_range)


def host_path(x: Tensor) -> bool:
    """Whether work on ``x`` takes the CPU's path through NumPy or OpenCV (filters, erosions, a
    mask's pixels), which other devices do with torch ops: True for a CPU tensor, unless
    :func:`device_paths` is open."""
    return x.device.type == "cpu" and not _DEVICE_PATHS.get()


@contextlib.contextmanager
def device_paths():
    """Within the block, CPU tensors take the paths of other devices (torch ops where the CPU uses
    NumPy or OpenCV): how the tests run a GPU's code on a machine without one. Scoped to the block
    (and to the thread or task)."""
    token = _DEVICE_PATHS.set(True)
    try:
        yield
    finally:
        _DEVICE_PATHS.reset(token)


_DEVICE_PATHS: contextvars.ContextVar[bool] = contextvars.ContextVar("device_paths", default=False)

def check_finite(x: Tensor, name: str) -> None:
    if skip_values(x):
        return
    if not all_finite(x):
        bad = x[~torch.isfinite(x)].flatten()[:3].tolist()
        raise ValueError(f"{name}: expected finite values, got {bad} (NaN or inf)")


def check_positive(x: Tensor, name: str) -> None:
    if skip_values(x):
        return
    if not bool((x > 0).all()):
        bad = x[~(x > 0)].flatten()[:3].tolist()
        raise ValueError(f"{name}: expected values > 0, got {bad}")


def check_size(size: object, name: str = "size") -> tuple[int, int]:
    """``size = (H, W)`` with positive integer sides (a 0-d integer tensor read as its int, as by :func:`check_int`)."""
    if isinstance(size, torch.Size):
        size = tuple(size)
    if not isinstance(size, (tuple, list)) or len(size) != 2:
        raise TypeError(f"{name}: expected (H, W), got {size!r}")
    out, size = [], tuple(scalar(s, name) for s in size)  # (a 0-d tensor side was refused as not an integer)
    for s in size:
        if isinstance(s, bool) or not isinstance(s, numbers.Integral):
            raise TypeError(f"{name}: expected integer sides (H, W), got {size!r}")
        if s <= 0:
            raise ValueError(f"{name}: expected positive sides (H, W), got {tuple(size)!r}")
        out.append(int(s))
    return out[0], out[1]


def _float(x: numbers.Real, name: str) -> float:
    """``float(x)``; a number beyond float's range (``10**400``, where float raises OverflowError)
    is a ValueError naming ``name``."""
    try:
        return float(x)
    except OverflowError:
        raise ValueError(f"{name}: expected a finite number, got {_quote(x)}") from None


def _quote(x: object) -> str:
    """``repr(x)``, shortened where it is long (an int of 400 digits)."""
    r = repr(x)
    return r if len(r) <= 60 else f"{r[:20]}...{r[-8:]} ({len(r)} characters)"


def scalar(x: object, name: str) -> object:
    """A 0-d real tensor (not bool, not complex) read as the Python number it holds (float, or
    int for an integer dtype), so that every scalar parameter takes one wherever it takes a
    Python number; anything else returned as it came, for the caller's check to quote. A 0-d
    tensor on the meta device is a ValueError naming ``name`` (it holds no number)."""
    if isinstance(x, Tensor) and x.dim() == 0 and x.dtype != torch.bool and not x.is_complex():
        if skip_values(x):
            raise ValueError(f"{name}: expected a Python number, got a tensor on the meta device")
        return x.item()
    return x


def check_number(x: object, name: str, *, positive: bool = False, nonnegative: bool = False,
                 finite: bool = True) -> float:
    """A Python real (not a bool; a 0-d tensor is read) checked for finiteness and sign -> float.
    A number beyond float's range is a ValueError, also with ``finite=False``."""
    x = scalar(x, name)
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        raise TypeError(f"{name}: expected a number, got {type(x).__name__} {x!r}")
    value = _float(x, name)
    if finite and not math.isfinite(value):
        raise ValueError(f"{name}: expected a finite number, got {x!r}")
    if positive and not value > 0:
        raise ValueError(f"{name}: expected a positive number (> 0), got {x!r}")
    if nonnegative and not value >= 0:
        raise ValueError(f"{name}: expected a number >= 0, got {x!r}")
    return value


# -- options: plain Python values of keyword arguments ---------------------------------------------

def check_bool(x: object, name: str) -> bool:
    """A flag: True or False (not a truthy string or number, which would pass silently)."""
    if not isinstance(x, bool):
        raise TypeError(f"{name}: expected True or False, got {type(x).__name__} {x!r}")
    return x


def check_int(x: object, name: str, *, minimum: int | None = None, optional: bool = False) -> int | None:
    """An integer option (not a bool or a float), at least ``minimum``; None where ``optional``.
    A 0-d integer tensor is read as its int, as real options read a 0-d tensor (:func:`scalar`)."""
    if x is None and optional:
        return None
    x = scalar(x, name)
    if isinstance(x, bool) or not isinstance(x, numbers.Integral):
        what = "None or an int" if optional else "an int"
        raise TypeError(f"{name}: expected {what}, got {type(x).__name__} {x!r}")
    if minimum is not None and x < minimum:
        raise ValueError(f"{name}: expected an int >= {minimum}, got {x!r}")
    return int(x)


def is_number(x: object, *, integer: bool = False) -> bool:
    """Whether ``x`` is a Python or NumPy real number (an integer where ``integer``), not a bool."""
    return not isinstance(x, bool) and isinstance(x, numbers.Integral if integer else numbers.Real)


def option_error(value: object, message: str, *, integer: bool = False) -> Exception:
    """The error to raise, with ``message``, for an option ``value`` that failed its check: a
    TypeError where it is of the wrong type (not a number, or not an integer where ``integer``; a
    bool is neither), else a ValueError (a number out of range, or NaN)."""
    return (ValueError if is_number(value, integer=integer) else TypeError)(message)


def check_names(x: object, name: str) -> tuple[str, ...] | None:
    """Parameter names: None, one name, or a sequence of names -> a tuple (None kept)."""
    if x is None:
        return None
    if isinstance(x, str):
        return (x,)
    if isinstance(x, Iterable) and not isinstance(x, (Mapping, bytes, Tensor)):
        names = tuple(x)
        if all(isinstance(n, str) for n in names):
            return names
    raise TypeError(f"{name}: expected None, a name or a sequence of names, got {type(x).__name__} {x!r}")


def check_mapping(x: object, name: str) -> dict:
    """Keyword options or named values: None (empty) or a mapping with string keys -> a dict."""
    if x is None:
        return {}
    if not isinstance(x, Mapping) or not all(isinstance(k, str) for k in x):
        raise TypeError(f"{name}: expected None or a dict with string keys, got {type(x).__name__} {x!r}")
    return dict(x)


@functools.lru_cache(maxsize=64)
def _keyword_names(fn: object) -> frozenset[str] | None:
    """The names ``fn`` takes by keyword (None: it takes any, ``**kwargs``), looked up once per
    function (``inspect.signature`` costs about 0.1 ms, and the refiner checks its options at
    every call)."""
    import inspect

    params = inspect.signature(fn).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return None
    return frozenset(n for n, p in params.items() if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD))


def check_keywords(options: Mapping[str, object], name: str, fn: object,
                   reserved: Sequence[str] = ()) -> None:
    """``options`` are keyword arguments that will be forwarded to ``fn``: a name ``fn`` does not
    take, or one the caller sets itself (``reserved``), raises now rather than at the first call."""
    if not options:
        return
    taken = _keyword_names(fn)
    if taken is None:
        return
    unknown = sorted(set(options) - taken)
    if unknown:
        raise TypeError(f"{name}: unknown options {unknown} of {fn.__name__}; expected some of {sorted(taken - set(reserved))}")
    clash = sorted(set(options) & set(reserved))
    if clash:
        raise TypeError(f"{name}: options {clash} of {fn.__name__} are set by the function that forwards {name} "
                        f"to it, not through {name}")


def check_fit_flags(fn: str, fit_roll: object, fit_pitch: object, options: Mapping[str, object]) -> None:
    """The flags of a one-model fit (``fit_displacement``, ``fit_velocity``, ``fit_photometric``),
    which chooses the model and its fixed parameters itself: ``model`` or ``fixed`` among the
    forwarded ``options`` raise (Python would report a duplicate keyword deep inside)."""
    check_bool(fit_roll, "fit_roll")
    check_bool(fit_pitch, "fit_pitch")
    for key in ("model", "fixed"):
        if key in options:
            raise TypeError(f"{key}: {fn} sets the model and its fixed parameters itself (fit_roll, "
                            f"fit_pitch); use fit_road or fit_image for other choices")


def check_data_range(data_range: object, name: str = "data_range") -> float:
    """The images' value range (1.0 for 0-1 images, 255.0 for 0-255): a finite number > 0."""
    if isinstance(data_range, Tensor) and data_range.dim() == 0 and not skip_values(data_range):
        data_range = data_range.item()
    if (isinstance(data_range, bool) or not isinstance(data_range, numbers.Real)
            or not (math.isfinite(_float(data_range, name)) and float(data_range) > 0)):
        wrong_type = isinstance(data_range, bool) or not isinstance(data_range, numbers.Real)
        raise (TypeError if wrong_type else ValueError)(
            f"{name}: expected a positive finite number (the images' maximum: 1.0 for 0-1 images, "
            f"255.0 for 0-255 images), got {data_range!r}")
    return float(data_range)


def sample_extremes(x: Tensor) -> tuple[list[float], list[float]]:
    """Each sample's minimum and maximum (x (B, ...); another rank: one sample), one pass, one host read
    (per sample: on the CPU, torch.aminmax(x.flatten(1), dim=1) takes 20 times as long as over all)."""
    with autocast_off(x):  # (autocast's stack refuses a half dtype other than its own; NaN propagates into both)
        return tuple(torch.stack([torch.stack(torch.aminmax(s)) for s in (x.unbind(0) if x.dim() == 4 else (x,))]).T.tolist())


def check_image_range(image: Tensor, name: str, data_range: float | tuple[float, float]) -> None:
    """Finite values in [0, data_range] up to 1% (catches 0-255 images passed as 0-1, 0-1 images
    passed as 0-255, and NaN pixels); ``data_range`` (low, high): images in the caller's range that
    the caller maps onto 0..255 (``FreespaceRefined``'s ``image_range``), judged as on 0..255.

    A NaN pixel would spread through bilinear taps and filter windows into its neighbours' values,
    so an image must be finite everywhere, not only where it is evaluated. The "0..1 image" guess
    (all values above 0 and within 1, or within the lowest 1/255 of (low, high)) judges each sample
    of a batch (B, C, H, W) alone, and is off on 0..1 and within :func:`trust_image_range`."""
    if skip_values(image) or image.numel() == 0:
        return
    if data_range == 255.0 and any(image is t for t in _KNOWN_IMAGES.get()):
        return  # (see known_images)
    pair = isinstance(data_range, tuple)
    low, high = data_range if pair else (0.0, data_range)
    span, given = high - low, f"image_range=({low:g}, {high:g})" if pair else f"[0, data_range={high:g}]"
    los, his = sample_extremes(d := image.detach())
    lo, hi = min(los), max(his)
    if not all(map(math.isfinite, los + his)):
        bad = d[~torch.isfinite(d)].flatten()[:3].tolist()
        raise ValueError(f"{name}: expected finite pixel values, got {bad} (NaN or inf); "
                         f"replace or mask them before warping or filtering")
    if hi > high + 0.01 * span or lo < low - 0.01 * span:
        raise ValueError(f"{name}: expected values in {given}, got values in [{lo:g}, {hi:g}] " + (
            "(pass image_range=(low, high) of the images: the net's convention, (0, 255) for RAFT, (-1, 1) for "
            "torchvision's transforms)" if pair else "(pass data_range=255.0 for 0-255 images, 1.0 for 0-1 images)"))
    top = low + span / 255.0 if pair else 1.0
    dim = [] if (span <= 1.5 and not pair) or trusted_image_range() else [b for b, h in enumerate(his) if low < h <= top]
    if dim:  # (a 0..255 frame whose brightest pixel is at most 1 grey level is no image to judge)
        where, (a, b) = (name, (lo, hi)) if len(dim) == len(his) else (f"{name}[{dim[0]}]", (los[dim[0]], his[dim[0]]))
        raise ValueError(f"{where}: values in [{a:g}, {b:g}] " + (
            f"fill at most 1/255 of {given} (0..1 images given for 0..255?): pass image_range=(0, 1) for 0..1 "
            f"images, or scale them" if pair else f"look like 0..1 images, expected 0..{high:g}: scale them by "
            f"{high:g}, or pass data_range=1.0 where the function takes it (the refiner and its gate take 0..255 "
            f"images)") + "; frames this dark (a lens cap): fsof_torch.trust_image_range()")


def as_batch_param(x: object, name: str, dtype: torch.dtype | None = None,
                   device: torch.device | None = None, *, finite: bool = True) -> Tensor:
    """A per-frame scalar as a 1-D tensor: a Python number -> (1,) on ``device`` (else the CPU, not
    the default device), a 0-d or (B,) tensor kept. ``finite=False`` leaves the finiteness check to
    the caller (see :func:`check_all_finite`)."""
    if isinstance(x, Tensor):
        if not x.is_floating_point():
            raise TypeError(f"{name}: expected a float tensor or a Python number, got dtype {x.dtype}")
        if x.dim() == 0:
            x = x.reshape(1)
        elif x.dim() != 1:
            raise ValueError(f"{name}: expected a scalar or shape (B,), got {_fmt_shape(tuple(x.shape))}")
        if dtype is not None or device is not None:
            x = to_device(x, name, device or x.device).to(dtype or x.dtype)
    elif isinstance(x, numbers.Real) and not isinstance(x, bool):
        x = torch.tensor([_float(x, name)], dtype=dtype or torch.get_default_dtype(), device=device or "cpu")
    else:
        raise TypeError(f"{name}: expected a float, or a tensor of shape (B,), got {type(x).__name__}")
    if finite:
        check_finite(x, name)
    return x


def check_all_finite(named: dict[str, Tensor]) -> None:
    """:func:`check_finite` for several small tensors of one dtype with one reduction (the
    common case costs one check, not one per argument); the error names the first bad one."""
    values = list(named.values())
    if not values or skip_values(*values):
        return
    flat = torch.cat([t.reshape(-1) for t in values]) if len(values) > 1 else values[0]
    if not all_finite(flat):
        for name, t in named.items():
            check_finite(t, name)


def as_path(path: object, name: str = "path") -> Path:
    """``path`` as a ``pathlib.Path``: a str or an os.PathLike, else a TypeError naming it (a
    ValueError for one holding a NUL character, which no file system takes)."""
    if isinstance(path, bool) or not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{name}: expected a file path (str or os.PathLike), got {type(path).__name__} {path!r:.60}")
    path = Path(path)
    if "\x00" in str(path):  # (the system refuses it: os.open's "embedded null byte" named nothing)
        raise ValueError(f"{name}: a file path holds no NUL character, got {str(path)!r}")
    return path


def existing_file(path: object, what: str = "file") -> Path:
    """``path`` as a Path where a file is there: a FileNotFoundError where nothing is ("no
    {what} at"; a symbolic link to a missing file says so), an IsADirectoryError where a folder
    is, each naming ``path``."""
    path = as_path(path)
    if path.is_dir():
        raise IsADirectoryError(f"path: {str(path)!r} is a folder; expected a {what}")
    if not path.is_file():
        if path.is_symlink():  # (a drive not mounted: "no file" would send the user to the wrong place)
            raise FileNotFoundError(f"path: {str(path)!r} is a symbolic link to {os.readlink(path)!r}, which does "
                                    f"not exist; mount or copy the data it points to, or remove the link")
        raise FileNotFoundError(f"path: no {what} at {str(path)!r}")
    return path


def batch_choices(B: int) -> str:
    """The batch sizes an argument may have beside a batch of B, for messages: ``"1 or B"``
    (``"1"`` where B is 1)."""
    return "1" if B == 1 else f"1 or {B}"


def check_batch(count: int, name: str, B: int) -> None:
    """An argument of ``count`` values beside a batch of B has 1 or B of them (else a ValueError
    naming it)."""
    if count not in (1, B):
        raise ValueError(f"{name}: expected batch {batch_choices(B)}, got {count} values")


def resolve_batch(named: dict[str, int]) -> int:
    """The common batch size of arguments whose sizes are 1 or B; raise on a mismatch or an empty
    batch (nothing to compute: the geometry of no frame)."""
    empty = [n for n, b in named.items() if b < 1]
    if empty:
        raise ValueError(f"{empty[0]}: expected a batch of at least 1, got {named[empty[0]]}")
    sizes = {n: b for n, b in named.items() if b != 1}
    if len(set(sizes.values())) > 1:
        listing = ", ".join(f"{n}={b}" for n, b in sizes.items())
        raise ValueError(f"mismatched batch sizes: {listing} (each must be 1 or the same B)")
    return next(iter(sizes.values()), 1)


def result_dtype(*tensors: Tensor) -> torch.dtype:
    """The float dtype to compute in: the promoted dtype, half precision lifted to float32."""
    dt = tensors[0].dtype
    for t in tensors[1:]:
        dt = torch.promote_types(dt, t.dtype)
    if dt in (torch.float16, torch.bfloat16):
        dt = torch.float32
    return dt


def held_by(mask: Tensor, flow: Tensor, dtype: torch.dtype) -> Tensor:
    """``mask`` (B, 1, H, W) where ``flow`` (B, 2, H, W) is finite in ``dtype``: for float16, whose
    largest value is 65 504 (a road model's flow near the horizon or under a fast camera exceeds
    it, and cast to float16 would be inf); ``mask`` itself for the dtypes of float32's range."""
    if dtype != torch.float16:
        return mask
    return mask & torch.isfinite(flow.to(dtype)).all(dim=1, keepdim=True)


def autocast_off(x: Tensor) -> ContextManager:
    """``torch.autocast(enabled=False)`` for ``x``'s device type: the caller casts to its working
    dtype (:func:`result_dtype`) itself. A no-op where autocast is off already or does not exist
    (the meta device): the road models' maps enter it at every solver iteration."""
    device_type = x.device.type
    if not (torch.amp.is_autocast_available(device_type) and torch.is_autocast_enabled(device_type)):
        return contextlib.nullcontext()
    return torch.autocast(device_type=device_type, enabled=False)


def tensor_from_array(array: Any) -> Tensor:
    """``torch.from_numpy`` of any NumPy array: one with negative strides (such as ``a[::-1]``, a
    BGR-to-RGB view) or in a non-native byte order is copied first, values kept (torch takes
    neither); others share their memory, as with ``from_numpy``."""
    import numpy as np

    if any(stride < 0 for stride in array.strides):
        array = np.ascontiguousarray(array)
    if not array.dtype.isnative:
        array = array.astype(array.dtype.newbyteorder("="))
    return torch.from_numpy(array)


def as_chw_flow(flow: object, name: str) -> Tensor:
    """A flow as a (2, H, W) float tensor (from a tensor or array of that shape; an array with
    negative strides, such as ``a[::-1]``, or in a non-native byte order is copied, values kept)."""
    import numpy as np

    if isinstance(flow, np.ndarray):
        if flow.dtype.kind != "f" or flow.dtype.itemsize > 8:  # (object, str, longdouble: torch's own TypeError)
            raise TypeError(f"{name}: expected a floating-point array (float16/32/64), got dtype {flow.dtype}")
        flow = tensor_from_array(flow)
    if not isinstance(flow, Tensor):
        raise TypeError(f"{name}: expected a tensor of shape (2, H, W), got {type(flow).__name__}")
    check_has_values(flow, name)
    if not flow.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {flow.dtype}")
    if flow.dim() != 3 or flow.shape[0] != 2 or flow.shape[1] == 0 or flow.shape[2] == 0:
        raise ValueError(f"{name}: expected shape (2, H, W), got {tuple(flow.shape)}")
    return flow


def check_image_pair(image1: object, image2: object) -> dict[str, int]:
    """Two frames (B, C, H, W) float of one shape, grey (C = 1) or RGB (C = 3), B, H and W at least
    1: their dims."""
    for name, img in (("image1", image1), ("image2", image2)):
        check_float_tensor(img, name)
    dims = check_shape(image1, "image1", ("B", "C", "H", "W"), nonempty=("B", "H", "W"))
    check_shape(image2, "image2", ("B", "C", "H", "W"), dims, nonempty=("B", "H", "W"))
    if dims["C"] not in (1, 3):
        raise ValueError(f"image1: expected 1 (grey) or 3 (RGB) channels, got shape {tuple(image1.shape)}")
    return dims


# -- estimation without autograd's bookkeeping ------------------------------------------------------
#
# The estimators run hundreds of small tensor operations per call and are not differentiable (their
# results are detached). ``torch.inference_mode`` runs such code with less overhead per operation
# than ``torch.no_grad`` (no version counters, no view tracking; python
# benchmarks/bench_image_fit.py times fit_image both ways). Its tensors, however, cannot be
# saved for backward or changed in place outside inference mode, so results leave
# :func:`inference` as ordinary tensors.

_F = TypeVar("_F", bound=Callable[..., Any])


def same_mapping(obj: Mapping, items: dict) -> Mapping:
    """A new mapping of ``obj``'s type holding ``items``. A dict subclass is copied and refilled:
    its constructor may take other arguments (``defaultdict(factory, items)``), and a copy keeps
    its type and state; another Mapping is built from the items where its constructor takes them,
    else a plain dict comes back."""
    if isinstance(obj, dict):
        try:
            out = copy.copy(obj)  # (shallow: the values are the caller's objects until replaced)
            out.clear()
            out.update(items)
            return out
        except (TypeError, AttributeError, NotImplementedError):  # a subclass that refuses it
            pass
    try:
        return type(obj)(items)
    except TypeError:  # a Mapping type without a dict constructor
        return items


def ordinary(x: Any) -> Any:
    """``x`` with every inference tensor in it cloned into an ordinary one (outside inference
    mode): a tensor, or the tensors held by dicts (subclasses such as a ``defaultdict`` keep their
    type and state), lists, tuples (named ones too) and dataclass instances (with ``slots=True``
    too), recursively. What holds no inference tensor stays itself (an input passed through,
    a camera, which compares by identity); a container that holds one is rebuilt around the
    clones (the input is not changed)."""
    if isinstance(x, Tensor):
        return x.clone() if x.is_inference() else x
    if isinstance(x, dict):
        items = {k: ordinary(v) for k, v in x.items()}
        if _same(x.values(), items.values()):
            return x
        return same_mapping(x, items)
    if isinstance(x, (tuple, list)):
        items = [ordinary(v) for v in x]
        if _same(x, items):
            return x
        return type(x)(*items) if hasattr(x, "_fields") else type(x)(items)
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        # (a dataclass with slots=True has no __dict__: its fields are read one by one)
        before = (x.__dict__ if hasattr(x, "__dict__")
                  else {f.name: getattr(x, f.name) for f in dataclasses.fields(x)})
        items = {k: ordinary(v) for k, v in before.items()}
        if _same(before.values(), items.values()):
            return x
        # (not through __init__ or dataclasses.replace: its checks ran when the instance was made)
        if hasattr(x, "__dict__"):
            out = object.__new__(type(x))
            out.__dict__.update(items)
            return out
        out = copy.copy(x)
        for k, v in items.items():
            object.__setattr__(out, k, v)  # (a frozen one too)
        return out
    return x


def _same(before: Iterable[Any], after: Iterable[Any]) -> bool:
    return all(a is b for a, b in zip(before, after))


def inference(fn: _F) -> _F:
    """Decorator: run ``fn`` under ``torch.inference_mode`` and return :func:`ordinary` results.

    Inside inference mode already, ``fn`` runs as it is (the caller wants inference tensors, or
    converts them itself); while ``torch.compile`` traces, under ``torch.no_grad`` instead."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if torch.is_inference_mode_enabled():
            return fn(*args, **kwargs)
        if tracing():
            with torch.no_grad():
                return fn(*args, **kwargs)
        with torch.inference_mode():
            out = fn(*args, **kwargs)
        return ordinary(out)

    return wrapper  # type: ignore[return-value]


def summary_repr(obj: Any) -> str:
    """A dataclass's or NamedTuple's repr on one line, tensors of more than 9 values (or on meta) as
    their shape and dtype, lists cut at 4 items: torch's repr of a result's flows runs to pages."""
    items = obj._asdict() if isinstance(obj, tuple) else {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj) if f.repr}
    return f"{type(obj).__name__}(" + ", ".join(f"{k}={_short(v)}" for k, v in items.items()) + ")"


def _short(v: Any) -> str:
    if isinstance(v, Tensor) and (v.numel() > 9 or v.device.type == "meta"):
        return f"tensor(shape={tuple(v.shape)}, dtype={v.dtype}" + ("" if v.is_cpu else f", device='{v.device}'") + ")"
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{k!r}: {_short(x)}" for k, x in v.items()) + "}"
    if type(v) in (list, tuple):
        inner = ", ".join([_short(x) for x in v[:4]] + ([f"... ({len(v)} items)"] if len(v) > 4 else []))
        return f"({inner}{',' * (len(v) == 1)})" if type(v) is tuple else f"[{inner}]"
    return " ".join(repr(v.detach() if isinstance(v, Tensor) else v).split())
