"""Tests of fsof_torch._check: the one validation helper module."""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import re

import numpy as np
import pytest
import torch

from fsof_torch._check import (
    all_finite,
    known_finite,
    known_images,
    trust_image_range,
    as_batch_param,
    as_chw_flow,
    autocast_off,
    check_bool,
    check_data_range,
    check_fit_flags,
    check_finite,
    check_float_tensor,
    check_has_values,
    check_same_device,
    check_image_range,
    check_int,
    check_keywords,
    check_mapping,
    check_names,
    check_number,
    check_positive,
    check_shape,
    check_size,
    resolve_batch,
    result_dtype,
    skip_values,
    tracing,
    to_device,
)


def test_check_shape_binds_letters_across_arguments():
    dims = check_shape(torch.zeros(4, 2, 8, 9), "flow", ("B", 2, "H", "W"))
    assert dims == {"B": 4, "H": 8, "W": 9}
    check_shape(torch.zeros(4, 1, 8, 9), "mask", ("B", 1, "H", "W"), dims)
    with pytest.raises(ValueError, match=r"mask: expected shape \(B, 1, H, W\) with H=8 \(from an earlier "
                                         r"argument\), got \(4, 1, 7, 9\)"):
        check_shape(torch.zeros(4, 1, 7, 9), "mask", ("B", 1, "H", "W"), dims)
    with pytest.raises(ValueError, match=r"flow: expected shape \(B, 2, H, W\), got \(4, 3, 64, 64\)"):
        check_shape(torch.zeros(4, 3, 64, 64), "flow", ("B", 2, "H", "W"))
    with pytest.raises(ValueError, match=r"x: expected shape \(B,\), got \(2, 2\)"):
        check_shape(torch.zeros(2, 2), "x", ("B",))


def test_check_float_tensor():
    x = torch.zeros(2)
    assert check_float_tensor(x, "x") is x
    with pytest.raises(TypeError, match="x: expected a torch.Tensor, got list"):
        check_float_tensor([1.0], "x")
    with pytest.raises(TypeError, match="x: expected a floating-point tensor, got dtype torch.int32"):
        check_float_tensor(torch.zeros(2, dtype=torch.int32), "x")


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_all_finite_agrees_with_isfinite(dtype, bad):
    """all_finite (minimum and maximum in one pass) gives torch.isfinite(x).all() wherever the bad
    value sits (first, last, middle, in the vectorised body and in the tail of a row), on
    contiguous tensors and on strided views, alone or beside another non-finite value."""
    g = torch.Generator().manual_seed(0)
    x = (torch.randn(3, 17, 33, generator=g) * 1e3).to(dtype)
    for view in (x, x[:, ::2, 1:], x.transpose(0, 2)):
        assert all_finite(view) is True and bool(torch.isfinite(view).all())
    for index in [(0, 0, 0), (2, 16, 32), (1, 5, 7), (1, 5, 31)]:
        y = x.clone()
        y[index] = bad
        for view in (y, y.transpose(0, 2), y[:, :, 1:]):
            assert all_finite(view) == bool(torch.isfinite(view).all())
        assert all_finite(y) is False
    for other in [float("nan"), float("inf"), float("-inf")]:
        y = x.clone()
        y[0, 0, 0], y[2, 16, 32] = bad, other
        assert all_finite(y) is False


def test_known_finite_answers_for_the_very_tensors_within_the_block():
    """Within ``known_finite(x)`` all_finite(x) is True without reading x (the caller's promise: a
    NaN there is not seen), for x itself only (not a copy, a view or another tensor), and only
    within the block (nested blocks add to the outer one's)."""
    x = torch.tensor([1.0, float("nan")])
    y = torch.tensor([float("inf")])
    assert all_finite(x) is False
    with known_finite(x):
        assert all_finite(x) is True
        assert all_finite(x.clone()) is False and all_finite(x[1:]) is False and all_finite(y) is False
        with known_finite(y):
            assert all_finite(x) is True and all_finite(y) is True
        assert all_finite(y) is False
    assert all_finite(x) is False


def test_known_images_pass_the_range_check_within_the_block_on_0_255_only():
    """Within ``known_images(x)`` check_image_range(x) on 0..255 passes without reading x (the
    caller checked what x comes from), for x itself only and only within the block; a check on
    another range still runs (x was vouched for on 0..255, not on that)."""
    dim = torch.full((1, 1, 4, 4), 0.9)  # (a frame whose brightest value is below 1 grey level)
    with pytest.raises(ValueError, match="look like 0..1 images"):
        check_image_range(dim, "image1", 255.0)
    with known_images(dim):
        check_image_range(dim, "image1", 255.0)
        with pytest.raises(ValueError, match="look like 0..1 images"):
            check_image_range(dim.clone(), "image1", 255.0)
        with pytest.raises(ValueError, match=r"expected values in \[0, data_range=0.5\]"):
            check_image_range(dim, "image1", 0.5)
    with pytest.raises(ValueError, match="look like 0..1 images"):
        check_image_range(dim, "image1", 255.0)


def test_the_0_1_guess_judges_each_sample_alone():
    """A dim frame (brightest value 1 grey level) raises alone and raises in a batch beside a bright
    frame, naming its sample: its outcome does not depend on its batch (in a batch it passed, as
    the bright frame lifted the batch's maximum). A batch that is all 0..1 is named as a whole."""
    bright, dim = torch.full((1, 3, 4, 5), 200.0), torch.full((1, 3, 4, 5), 1.0)
    dim[..., 0, 0] = 0.0
    with pytest.raises(ValueError, match=r"^images\[0\]: values in \[0, 1\] look like 0..1 images"):
        check_image_range(dim, "images[0]", 255.0)
    with pytest.raises(ValueError, match=r"^images\[0\]\[1\]: values in \[0, 1\] look like 0..1 images, expected "
                                         r"0..255: .* fsof_torch.trust_image_range\(\)$"):
        check_image_range(torch.cat([bright, dim, bright]), "images[0]", 255.0)
    with pytest.raises(ValueError, match=r"^images\[0\]: values in \[0, 1\] look like 0..1 images"):
        check_image_range(torch.cat([dim, dim]), "images[0]", 255.0)
    check_image_range(torch.cat([bright, torch.zeros_like(dim)]), "images[0]", 255.0)  # (black is no 0..1 image)
    nan = bright.clone()
    nan[..., 1, 1] = float("nan")
    with pytest.raises(ValueError, match="expected finite pixel values"):  # (in any sample, not the first only)
        check_image_range(torch.cat([bright, nan]), "images[0]", 255.0)
    check_image_range(torch.cat([dim, bright]) / 255, "images[0]", 1.0)  # (on 0..1 there is nothing to guess)


def test_trust_image_range_turns_the_0_1_guess_off_within_the_block_only():
    """Within ``trust_image_range()`` a caller that knows its range (8-bit files) has a dim frame
    taken as it is, alone or batched; values out of range or not finite still raise; outside the
    block the guess is back."""
    import fsof_torch

    assert fsof_torch.trust_image_range is trust_image_range and "trust_image_range" in fsof_torch.__all__
    dim = torch.full((2, 1, 4, 4), 0.9)
    with trust_image_range():
        check_image_range(dim, "image1", 255.0)
        check_image_range(dim[:1], "image1", 255.0)
        with pytest.raises(ValueError, match=r"expected values in \[0, data_range=255\]"):
            check_image_range(dim * 300, "image1", 255.0)
        with pytest.raises(ValueError, match="expected finite pixel values"):
            check_image_range(dim.clone().fill_(float("nan")), "image1", 255.0)
    with pytest.raises(ValueError, match="look like 0..1 images"):
        check_image_range(dim, "image1", 255.0)


def test_all_finite_other_dtypes_and_edges():
    assert all_finite(torch.empty(0)) is True and all_finite(torch.empty(0, 3, dtype=torch.float64)) is True
    assert all_finite(torch.arange(5)) is True and all_finite(torch.ones(3, dtype=torch.bool)) is True
    assert all_finite(torch.tensor(2.5)) is True and all_finite(torch.tensor(float("nan"))) is False
    for z in [complex(float("nan"), 0.0), complex(0.0, float("inf")), complex(float("-inf"), 1.0)]:
        c = torch.tensor([1 + 2j, z])
        assert all_finite(c) is False and all_finite(c[:1]) is True
    for dtype in (torch.float16, torch.float32, torch.float64):
        info = torch.finfo(dtype)
        edge = torch.tensor([info.max, -info.max, info.tiny, -0.0], dtype=dtype)
        assert all_finite(edge) is True  # the largest finite values are finite (a sum would overflow)
    x = torch.randn(4, requires_grad=True, generator=torch.Generator().manual_seed(0))
    assert all_finite(x) is True and x.grad is None


def test_check_finite_and_positive():
    check_finite(torch.tensor([1.0, -2.0]), "x")
    with pytest.raises(ValueError, match=r"x: expected finite values, got \[nan\]"):
        check_finite(torch.tensor([1.0, float("nan")]), "x")
    with pytest.raises(ValueError, match=r"x: expected finite values, got \[-inf\]"):
        check_finite(torch.tensor([float("-inf")]), "x")
    check_positive(torch.tensor([1e-9]), "h")
    with pytest.raises(ValueError, match=r"h: expected values > 0, got \[0.0, -1.0\]"):
        check_positive(torch.tensor([1.0, 0.0, -1.0]), "h")
    with pytest.raises(ValueError, match="h: expected values > 0"):
        check_positive(torch.tensor([float("nan")]), "h")


@pytest.mark.parametrize("size, want", [((3, 4), (3, 4)), ([5, 6], (5, 6)), (torch.Size([7, 8]), (7, 8)),
                                        ((torch.tensor(3), np.int64(4)), (3, 4))])
def test_check_size(size, want):
    got = check_size(size)
    assert got == want and all(type(s) is int for s in got)


def test_a_size_of_0_d_integer_tensors_is_read_as_ints_as_whole_number_options_are():
    """docs/reliability.md: a whole-number option takes a 0-d integer tensor as its int (the refiner's
    min_pixels, Camera.padded, ImageGate's grid); a size (H, W) of two, as ``tuple(sizes[i])`` of a
    batch's (B, 2) sizes gives it, was refused as 'expected integer sides' by every function."""
    import fsof_torch as fs

    H, W = torch.tensor(12), torch.tensor(40)
    camera = fs.Camera(torch.tensor([[50.0, 0.0, 20.0], [0.0, 50.0, 4.0], [0.0, 0.0, 1.0]]), 1.65)
    flow, valid = fs.displacement_flow(camera, 0.0, 1.0, 0.0, (H, W))
    want = fs.displacement_flow(camera, 0.0, 1.0, 0.0, (12, 40))
    assert torch.equal(flow, want[0]) and torch.equal(valid, want[1]) and flow.shape == (1, 2, 12, 40)
    assert fs.DisplacementFlow((H, W)).size == (12, 40) and repr(fs.RoadFlow((H, W))) == "RoadFlow(size=(12, 40), model='paper')"
    assert torch.equal(fs.road_seed(camera, (H, W)), fs.road_seed(camera, (12, 40)))
    assert fs.InputPadder(8).padding((torch.tensor(375), torch.tensor(1242))) == fs.InputPadder(8).padding((375, 1242))
    for bad, err, msg in (((torch.tensor(3.0), 4), TypeError, r"expected integer sides \(H, W\), got \(3.0, 4\)"),
                          ((torch.tensor(True), 4), TypeError, "expected integer sides"),
                          ((torch.tensor([3]), 4), TypeError, "expected integer sides"),
                          ((torch.tensor(0), 4), ValueError, r"expected positive sides \(H, W\), got \(0, 4\)"),
                          ((torch.tensor(3, device="meta"), 4), ValueError, "size: expected a Python number, got a tensor on the meta")):
        with pytest.raises(err, match=msg):
            check_size(bad)


@pytest.mark.parametrize("size, err, msg", [
    ((0, 4), ValueError, r"size: expected positive sides \(H, W\), got \(0, 4\)"),
    ((3, -1), ValueError, "size: expected positive sides"),
    ((3,), TypeError, r"size: expected \(H, W\), got \(3,\)"),
    ((3, 4, 5), TypeError, r"size: expected \(H, W\)"),
    ((3.0, 4), TypeError, "size: expected integer sides"),
    ((True, 4), TypeError, "size: expected integer sides"),
    (34, TypeError, r"size: expected \(H, W\), got 34"),
])
def test_check_size_errors(size, err, msg):
    with pytest.raises(err, match=msg):
        check_size(size)


def test_as_batch_param():
    x = as_batch_param(1.5, "x")
    assert x.shape == (1,) and x.dtype == torch.get_default_dtype()
    assert as_batch_param(1.5, "x", torch.float64).dtype == torch.float64
    assert as_batch_param(torch.tensor(2.0), "x").shape == (1,)
    t = torch.tensor([1.0, 2.0])
    assert as_batch_param(t, "x") is t
    assert as_batch_param(t, "x", torch.float64).dtype == torch.float64
    with pytest.raises(TypeError, match="x: expected a float tensor or a Python number, got dtype torch.int64"):
        as_batch_param(torch.tensor([1]), "x")
    with pytest.raises(ValueError, match=r"x: expected a scalar or shape \(B,\), got \(2, 1\)"):
        as_batch_param(torch.zeros(2, 1), "x")
    with pytest.raises(TypeError, match="x: expected a float, or a tensor of shape"):
        as_batch_param("1.0", "x")
    with pytest.raises(TypeError, match="x: expected a float, or a tensor of shape"):
        as_batch_param(True, "x")
    with pytest.raises(ValueError, match="x: expected finite values"):
        as_batch_param(float("nan"), "x")
    # a shapes-only tensor cannot be moved to a real device (once torch's "Cannot copy out of meta
    # tensor", naming nothing), and stays where the computation is on meta too
    meta = torch.ones(2, device="meta")
    with pytest.raises(ValueError, match="x: a tensor on the meta device has no values to move to cpu"):
        as_batch_param(meta, "x", device=torch.device("cpu"))
    assert as_batch_param(meta, "x", torch.float64, torch.device("meta"), finite=False).device.type == "meta"


def test_resolve_batch():
    assert resolve_batch({"a": 1, "b": 1}) == 1
    assert resolve_batch({"a": 1, "b": 4, "c": 4}) == 4
    with pytest.raises(ValueError, match="mismatched batch sizes: b=4, c=3"):
        resolve_batch({"a": 1, "b": 4, "c": 3})


def test_result_dtype():
    f16, f32, f64 = (torch.zeros(1, dtype=d) for d in (torch.float16, torch.float32, torch.float64))
    assert result_dtype(f32) == torch.float32
    assert result_dtype(f32, f64) == torch.float64
    assert result_dtype(f16) == torch.float32
    assert result_dtype(torch.zeros(1, dtype=torch.bfloat16), f16) == torch.float32


def test_tracing_flag():
    assert tracing() is False

    def f(x):
        return x + (1.0 if tracing() else 0.0)

    assert f(torch.zeros(1)).item() == 0.0
    assert torch.compile(f, backend="eager", fullgraph=True)(torch.zeros(1)).item() == 1.0


def test_check_shape_rejects_empty_images():
    with pytest.raises(ValueError, match=r"flow: expected shape \(B, 2, H, W\) with H >= 1, got \(1, 2, 0, 5\)"):
        check_shape(torch.zeros(1, 2, 0, 5), "flow", ("B", 2, "H", "W"))
    assert check_shape(torch.zeros(0, 2, 3, 5), "flow", ("B", 2, "H", "W")) == {"B": 0, "H": 3, "W": 5}
    assert check_shape(torch.zeros(1, 0), "x", ("B", "N"), nonempty=()) == {"B": 1, "N": 0}


def test_resolve_batch_refuses_an_empty_batch():
    from fsof_torch._check import resolve_batch

    assert resolve_batch({"K": 1, "x_d": 3}) == 3
    with pytest.raises(ValueError, match="x_d: expected a batch of at least 1, got 0"):
        resolve_batch({"K": 1, "x_d": 0})


def test_value_checks_skip_meta_tensors():
    meta = torch.full((3,), float("nan"), device="meta")
    assert skip_values(meta) and not skip_values(torch.zeros(1))
    check_finite(meta, "x")
    check_positive(meta, "x")
    check_image_range(meta, "image", 1.0)
    with autocast_off(meta):  # autocast does not exist on meta: a no-op
        pass
    with pytest.raises(ValueError, match="x: a tensor on the meta device has shapes but no values"):
        check_has_values(meta, "x")


def test_check_number_and_data_range():
    assert check_number(2, "n", positive=True) == 2.0
    assert check_number(torch.tensor(0.5), "n") == 0.5
    with pytest.raises(TypeError, match="n: expected a number, got str '1'"):
        check_number("1", "n")
    with pytest.raises(TypeError, match="n: expected a number, got bool"):
        check_number(True, "n")
    with pytest.raises(ValueError, match="n: expected a finite number, got nan"):
        check_number(float("nan"), "n")
    with pytest.raises(ValueError, match="n: expected a number >= 0, got -1"):
        check_number(-1, "n", nonnegative=True)
    assert check_data_range(255) == 255.0
    for bad in (0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="data_range: expected a positive finite number"):
            check_data_range(bad)


def test_check_image_range():
    check_image_range(torch.tensor([0.0, 1.0]), "image", 1.0)
    with pytest.raises(ValueError, match=r"image: expected values in \[0, data_range=1\], got values in \[0, 255\]"):
        check_image_range(torch.tensor([0.0, 255.0]), "image", 1.0)
    with pytest.raises(ValueError, match=r"image: expected finite pixel values, got \[nan\]"):
        check_image_range(torch.tensor([0.0, float("nan")]), "image", 255.0)
    with pytest.raises(ValueError, match=r"image: expected finite pixel values, got \[-inf\]"):
        check_image_range(torch.tensor([-float("inf"), 3.0]), "image", 255.0)


def test_check_image_range_on_a_range_low_high():
    """(low, high): images the caller maps onto 0..255 (FreespaceRefined's image_range), judged as
    on 0..255 in the caller's units: within 1 % of the width, and not all within its lowest 1/255."""
    grey = torch.tensor([[0.0, 40.0, 200.0]]).reshape(1, 1, 1, 3)
    for low, high in ((0.0, 255.0), (-1.0, 1.0), (0.0, 1.0)):
        scaled = low + grey * ((high - low) / 255.0)
        check_image_range(scaled, "image1", (low, high))
        check_image_range(low + (high - low) * 1.009 * torch.ones(1, 1, 1, 1), "image1", (low, high))
        with pytest.raises(ValueError, match=rf"^image1: expected values in image_range=\({low:g}, {high:g}\), got "):
            check_image_range(scaled + 0.25 * (high - low), "image1", (low, high))
        with pytest.raises(ValueError, match=rf"^image1: values in .* fill at most 1/255 of image_range=\({low:g}, "
                                             rf"{high:g}\) .* fsof_torch.trust_image_range\(\)$"):
            check_image_range(low + (scaled - low) / 255.0, "image1", (low, high))
        with trust_image_range():
            check_image_range(low + (scaled - low) / 255.0, "image1", (low, high))
    # on (0, 255) it is the 0..255 check's verdict
    dim = grey / 255.0
    for rng in (255.0, (0.0, 255.0)):
        with pytest.raises(ValueError, match=r"^image1: values in \[0, 0\.78\d*\] "):
            check_image_range(dim, "image1", rng)


def test_autocast_off_restores_float32_arithmetic():
    a = torch.randn(4, 4, generator=torch.Generator().manual_seed(0))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert (a @ a).dtype == torch.bfloat16
        with autocast_off(a):
            assert (a @ a).dtype == torch.float32
        assert (a @ a).dtype == torch.bfloat16  # (restored on leaving)
    # with autocast off already, nothing to switch off: no context entered
    assert isinstance(autocast_off(a), contextlib.nullcontext)


def test_option_checks_name_the_option_and_quote_the_value():
    assert check_bool(True, "flag") is True
    with pytest.raises(TypeError, match="flag: expected True or False, got int 1"):
        check_bool(1, "flag")
    assert check_int(3, "n", minimum=1) == 3 and check_int(None, "n", optional=True) is None
    with pytest.raises(TypeError, match="n: expected an int, got float 2.0"):
        check_int(2.0, "n")
    with pytest.raises(TypeError, match="n: expected an int, got bool True"):
        check_int(True, "n")
    with pytest.raises(ValueError, match="n: expected an int >= 1, got -5"):
        check_int(-5, "n", minimum=1)
    assert check_names("roll", "fixed") == ("roll",) and check_names(["a", "b"], "fixed") == ("a", "b")
    assert check_names(None, "fixed") is None and check_names({"a": 1}.keys(), "keys") == ("a",)
    for bad in (5, [1], {"a": 1}):
        with pytest.raises(TypeError, match="fixed: expected None, a name or a sequence of names"):
            check_names(bad, "fixed")
    assert check_mapping(None, "options") == {}
    with pytest.raises(TypeError, match="options: expected None or a dict with string keys, got list"):
        check_mapping([1], "options")


def test_check_keywords_against_the_receiving_function():
    def fit(flow, *, scale=1.0, model="paper"):
        return flow

    check_keywords({"scale": 2.0}, "options", fit)
    with pytest.raises(TypeError, match=r"options: unknown options \['bogus'\] of fit; expected some of"):
        check_keywords({"bogus": 1}, "options", fit)
    with pytest.raises(TypeError, match=r"options: options \['model'\] of \w+ are set by the function that forwards"):
        check_keywords({"model": "plane"}, "options", fit, reserved=("model",))
    check_fit_flags("fit_x", True, False, {"scale": 1.0})
    with pytest.raises(TypeError, match="fixed: fit_x sets the model and its fixed parameters itself"):
        check_fit_flags("fit_x", True, False, {"fixed": ()})


# -- inference mode -------------------------------------------------------------------------------

def test_ordinary_clones_inference_tensors_in_containers_and_keeps_the_rest():
    import dataclasses
    from typing import NamedTuple

    from fsof_torch._check import ordinary

    class Pair(NamedTuple):
        a: torch.Tensor
        b: object

    @dataclasses.dataclass
    class Box:
        t: torch.Tensor
        items: dict

    given = torch.arange(3.0)
    with torch.inference_mode():
        made = torch.arange(3.0) * 2
    x = {"made": made, "given": given, "list": [made, "text"], "pair": Pair(made, 7), "box": Box(made, {"g": given})}
    out = ordinary(x)
    for t in (out["made"], out["list"][0], out["pair"].a, out["box"].t):
        assert not t.is_inference() and torch.equal(t, made)
    assert out["given"] is given and out["box"].items["g"] is given  # (inputs passed through stay themselves)
    assert isinstance(out["pair"], Pair) and out["pair"].b == 7 and out["list"][1] == "text"
    assert isinstance(out["box"], Box) and out["box"] is not x["box"] and x["box"].t is made  # (the input unchanged)
    # what holds no inference tensor is returned itself, containers and dataclasses too (a camera
    # compares by identity)
    kept = Box(given, {"g": given})
    assert ordinary(kept) is kept and ordinary(x)["box"].items is x["box"].items
    plain = {"a": [given, (given, 1)], "b": kept}
    assert ordinary(plain) is plain


@dataclasses.dataclass(slots=True)
class _Slotted:
    t: torch.Tensor
    n: int = 3


@dataclasses.dataclass(frozen=True, slots=True)
class _FrozenSlotted:
    t: torch.Tensor


def test_ordinary_keeps_dict_subclasses_and_reads_slotted_dataclasses():
    """A defaultdict raised 'first argument must be callable or None' (its constructor takes the
    factory first); a slots=True dataclass (no __dict__) came back with its inference tensor."""
    from fsof_torch._check import ordinary

    with torch.inference_mode():
        made = torch.arange(3.0) * 2
    d = collections.defaultdict(list, {"a": made, "b": 1})
    out = ordinary(d)
    assert type(out) is collections.defaultdict and out.default_factory is list and out is not d
    assert not out["a"].is_inference() and torch.equal(out["a"], made) and out["b"] == 1
    assert d["a"] is made  # (the input unchanged)
    o = ordinary(collections.OrderedDict([("b", made), ("a", 2)]))
    assert type(o) is collections.OrderedDict and list(o) == ["b", "a"] and not o["b"].is_inference()
    for cls in (_Slotted, _FrozenSlotted):
        x = cls(made)
        y = ordinary(x)
        assert type(y) is cls and y is not x and not y.t.is_inference() and torch.equal(y.t, made)
        assert x.t is made
    assert ordinary(_Slotted(made, 5)).n == 5
    kept = _Slotted(torch.zeros(2))
    assert ordinary(kept) is kept


def test_numbers_beyond_float_range_are_named():
    """float(10**400) raised an OverflowError naming nothing."""
    big = 10 ** 400
    short = r"10000000000000000000\.\.\.00000000 \(401 characters\)$"
    for finite in (True, False):
        with pytest.raises(ValueError, match=rf"^x: expected a finite number, got {short}"):
            check_number(big, "x", finite=finite)
    with pytest.raises(ValueError, match=r"^x: expected a finite number, got -1000000000000000000\.\.\.00000000 "
                                         r"\(402 characters\)$"):
        check_number(-big, "x", nonnegative=True)
    with pytest.raises(ValueError, match=rf"^data_range: expected a finite number, got {short}"):
        check_data_range(big)
    with pytest.raises(ValueError, match=rf"^height: expected a finite number, got {short}"):
        as_batch_param(big, "height")
    assert check_number(10 ** 300, "x") == 1e300 and check_data_range(255) == 255.0


def test_as_chw_flow_takes_flipped_and_big_endian_arrays():
    """torch.from_numpy refuses negative strides and a non-native byte order: its unnamed
    ValueError came out of the flow writers. The values are kept."""
    hw2 = np.arange(40, dtype=np.float32).reshape(4, 5, 2)
    flipped = hw2.transpose(2, 0, 1)[::-1]  # (2, H, W), v and u swapped: a negative stride
    assert torch.equal(as_chw_flow(flipped, "flow"), torch.from_numpy(flipped.copy()))
    big = hw2.transpose(2, 0, 1).astype(">f4")
    out = as_chw_flow(big, "flow")
    assert out.dtype == torch.float32 and torch.equal(out, torch.from_numpy(hw2.transpose(2, 0, 1).copy()))
    native = np.zeros((2, 4, 5), np.float32)
    as_chw_flow(native, "flow").add_(1)  # (a native array is still read without a copy)
    assert native[0, 0, 0] == 1.0


def test_inference_results_work_in_place_and_under_autograd():
    from fsof_torch._check import inference

    @inference
    def scaled(x: torch.Tensor) -> dict:
        assert torch.is_inference_mode_enabled()
        return {"y": x * 2, "x": x}

    x = torch.ones(3, requires_grad=True)
    out = scaled(x)
    assert out["x"] is x and not out["y"].is_inference() and not out["y"].requires_grad
    out["y"].add_(1)  # (an inference tensor refuses this outside inference mode)
    w = torch.ones(3, requires_grad=True)
    (w * out["y"]).sum().backward()  # (and refuses to be saved for backward)
    assert w.grad.tolist() == [3.0, 3.0, 3.0]
    with torch.inference_mode():
        assert scaled(x)["y"].is_inference()  # (inside inference mode: left as it is)


def test_option_error_tells_a_wrong_type_from_a_wrong_value():
    from fsof_torch._check import is_number, option_error

    assert is_number(np.float32(0.5)) and is_number(np.int64(3), integer=True) and not is_number(True)
    assert not is_number(2.0, integer=True) and not is_number("1") and not is_number(torch.tensor(1.0))
    for value, integer, error in ((-1, True, ValueError), (float("nan"), False, ValueError),
                                  (np.int64(0), True, ValueError), ("1", False, TypeError),
                                  (True, False, TypeError), (2.5, True, TypeError)):
        err = option_error(value, "x: expected ...", integer=integer)
        assert type(err) is error and str(err) == "x: expected ..."


def _option_call(function: str, **option):
    """``function`` called with tiny valid inputs and one option (its checks run before any work)."""
    import fsof_torch as fs
    from fsof_torch.estimation.pyramid import pyramid_levels
    from fsof_torch.estimation.solver import ResidualProblem, solve
    from fsof_torch.evaluation.warp import normalize_coordinates

    cam = fs.Camera(torch.tensor([[130.0, 0.0, 80.0], [0.0, 130.0, 16.0], [0.0, 0.0, 1.0]], dtype=torch.float64), 1.65)
    flow, valid = torch.zeros(1, 2, 32, 48), torch.ones(1, 1, 32, 48, dtype=torch.bool)
    image = torch.full((1, 1, 32, 48), 100.0)
    calls = {
        "fit_road": lambda: fs.fit_road(flow, valid, cam, **option),
        "fit_image": lambda: fs.fit_image(image, image, valid, cam, **option),
        "detect_road": lambda: fs.detect_road(image, image, cam, **option),
        "road_seed": lambda: fs.road_seed(cam, (32, 48), **option),
        "vflow_map": lambda: fs.vflow_map(flow, valid, **option),
        "fit_vflow_curve": lambda: fs.fit_vflow_curve(flow, valid, **option),
        "fit_sequence": lambda: fs.fit_sequence([image] * 3, valid, cam, **option),
        "solve": lambda: solve(ResidualProblem(lambda p: p[:, :, None], torch.ones(1)), torch.zeros(1, 2), **option),
        "pyramid_levels": lambda: pyramid_levels(32, 48, min_size=4, **option),
        "normalize_coordinates": lambda: normalize_coordinates(torch.zeros(3), align_corners=True, **option),
        "fuse_flow": lambda: fs.fuse_flow(flow, flow + 1, valid, mode="confidence", **option),
        "Camera.scaled": lambda: cam.scaled(**option),
        "FreespaceRefined": lambda: fs.FreespaceRefined(lambda a, b: a, **option).image_range,
        "refine_flow": lambda: fs.refine_flow(flow, valid, cam, gate=None, warn=False, **option).flow,
        "FreespaceRefiner": lambda: fs.FreespaceRefiner(gate=None, warn=False, **option).min_pixels,
        "Camera.padded": lambda: cam.padded(**{"top": 0, **option}),
    }
    return calls[function]()


# (function, option, a value of the wrong type, a number out of range): docs/reliability.md's promise
@pytest.mark.parametrize("function, option, wrong_type, wrong_value", [
    ("fit_road", "scale", "1", -1.0),
    ("fit_road", "max_iter", 5.0, 0),
    ("fit_road", "tol", True, float("nan")),
    ("fit_road", "min_points", 1.5, 0),
    ("fit_road", "min_inlier_fraction", "0.5", 1.5),
    ("fit_image", "max_points", 100.5, 10),
    ("detect_road", "z", "2", -2.0),
    ("detect_road", "level", 1.5, -1),
    ("detect_road", "window", 7.0, 4),
    ("detect_road", "slow_max_height_m", "1.2", 0.1),
    ("detect_road", "min_coverage", True, 1.0),
    ("road_seed", "width_m", "4", float("inf")),
    ("vflow_map", "bins", 1.5, 1),
    ("vflow_map", "max_flow", "3", float("inf")),
    ("fit_vflow_curve", "hypotheses", 2.5, 0),
    ("fit_vflow_curve", "max_false_alarms", True, 0.0),
    ("fit_sequence", "passes", True, 3),
    ("fit_sequence", "attitude_deg", "1", 0.0),
    ("fit_sequence", "body_rotation_deg", None, -0.3),
    ("solve", "scale", True, float("nan")),
    ("solve", "check_every", 2.5, 0),
    ("pyramid_levels", "levels", 2.5, 0),
    ("normalize_coordinates", "size", 4.0, 0),
])
def test_options_raise_type_error_for_a_wrong_type_and_value_error_for_a_wrong_value(
        function, option, wrong_type, wrong_value):
    with pytest.raises(TypeError, match=f"^{option}: expected .*, got {re.escape(repr(wrong_type))}$"):
        _option_call(function, **{option: wrong_type})
    with pytest.raises(ValueError, match=f"^{option}: expected .*, got {re.escape(repr(wrong_value))}$"):
        _option_call(function, **{option: wrong_value})


def test_devices_are_checked_and_moved_with_the_argument_named():
    """The meta device stands in for another one: the first tensor fixes the device, None is left
    out; a tensor with no values to move (meta) is named, one with values moves."""
    x, m = torch.zeros(2), torch.zeros(2, device="meta")
    check_same_device({"a": x, "b": None, "c": x.clone()})
    with pytest.raises(ValueError, match=r"^c: expected the device of a \(cpu\), got meta$"):
        check_same_device({"a": x, "b": None, "c": m})
    with pytest.raises(ValueError, match=r"^mask: a tensor on the meta device has no values to move to cpu"):
        to_device(m, "mask", "cpu")
    assert to_device(x, "x", "meta").device.type == "meta" and to_device(x, "x", x.device) is x
    with pytest.raises(ValueError, match=r"^z_d: a tensor on the meta device has no values to move to cpu"):
        as_batch_param(m, "z_d", torch.float64, torch.device("cpu"))


# (function, option, a value taken, one out of range): a 0-d tensor wherever a Python number goes
@pytest.mark.parametrize("function, option, good, wrong_value", [
    ("fit_road", "scale", 2.0, -1.0),
    ("fit_road", "tol", 1e-4, float("nan")),
    ("fit_road", "inlier_threshold", 2.0, 0.0),
    ("fit_road", "min_inlier_fraction", 0.5, 1.5),
    ("fit_image", "gradient_fraction", 0.25, 1.5),
    ("fit_image", "min_correlation", 0.2, 2.0),
    ("detect_road", "z", 3.0, -2.0),
    ("detect_road", "seed_width_m", 3.0, float("inf")),
    ("detect_road", "min_coverage", 0.1, 1.0),
    ("road_seed", "width_m", 3.0, float("inf")),
    ("road_seed", "depth_m", 10.0, 0.0),
    ("vflow_map", "max_flow", 3.0, float("inf")),
    ("fit_vflow_curve", "inlier_threshold", 0.25, -1.0),
    ("fit_vflow_curve", "max_false_alarms", 2.0, 0.0),
    ("fit_sequence", "attitude_deg", 2.0, 0.0),
    ("fuse_flow", "scale", 3.0, -1.0),
    ("Camera.scaled", "sx", 0.5, 0.0),
])
def test_scalar_options_take_a_0d_tensor_as_its_number(function, option, good, wrong_value):
    """Camera.scaled, fuse_flow, the fits' and the road detection's real options refused a 0-d
    tensor (TypeError) that refine_flow(scale=...) and the losses took; fit_image passed the
    check and then failed in round()."""
    with pytest.raises(ValueError, match=f"^{option}: expected .*, got {re.escape(repr(wrong_value))}"):
        _option_call(function, **{option: torch.tensor(wrong_value, dtype=torch.float64)})
    if function == "fit_sequence":
        return  # (a clip fit: its check is the point; the fits themselves are fit_image's)
    as_tensor, as_number = (_option_call(function, **{option: v}) for v in (torch.tensor(good), good))
    pairs = [(a, b) for a, b in zip(*(dataclasses.astuple(r) if dataclasses.is_dataclass(r) else (r.K,) if hasattr(r, "K")
                                      else r if isinstance(r, tuple) else (r,) for r in (as_tensor, as_number)))
             if isinstance(a, torch.Tensor)]
    assert pairs and all(torch.equal(a, b) for a, b in pairs)


def test_image_range_takes_0d_tensors():
    assert _option_call("FreespaceRefined", image_range=(torch.tensor(0.0), torch.tensor(1.0))) == (0.0, 1.0)
    with pytest.raises(ValueError, match=r"^image_range: expected finite \(low, high\) with high > low"):
        _option_call("FreespaceRefined", image_range=(torch.tensor(1.0), torch.tensor(0.0)))


# (function, option, a value taken, one out of range): a 0-d integer tensor wherever an int goes
@pytest.mark.parametrize("function, option, good, wrong_value", [
    ("fit_road", "max_iter", 5, 0),
    ("fit_road", "max_points", 200, 10),
    ("fit_road", "min_points", 3, 0),
    ("fit_image", "max_iter", 3, 0),
    ("fit_image", "levels", 2, 0),
    ("fit_image", "min_size", 8, 1),
    ("fit_image", "fine_points", 300, 0),
    ("fit_image", "band_levels", 0, -1),
    ("fit_image", "retry_starts", 0, -1),
    ("detect_road", "level", 0, -1),
    ("detect_road", "window", 5, 4),
    ("vflow_map", "bins", 8, 1),
    ("fit_vflow_curve", "hypotheses", 8, 0),
    ("fit_vflow_curve", "iterations", 2, -1),
    ("fit_sequence", "passes", 1, 3),
    ("refine_flow", "min_pixels", 10, 0),
    ("FreespaceRefiner", "min_pixels", 10, 0),
    ("solve", "max_iter", 3, -1),
    ("pyramid_levels", "levels", 2, 0),
    ("normalize_coordinates", "size", 5, 0),
    ("Camera.padded", "left", 2, -1),
])
def test_whole_number_options_take_a_0d_integer_tensor_as_its_int(function, option, good, wrong_value):
    """Whole-number options refused a 0-d integer tensor (TypeError) where the real options took a
    0-d tensor as its number: now both read it (an int dtype as an int; a float or bool 0-d tensor
    stays refused, as 2.0 and True are)."""
    with pytest.raises(ValueError, match=f"^{option}: expected .*, got {re.escape(repr(wrong_value))}"):
        _option_call(function, **{option: torch.tensor(wrong_value)})
    for wrong_type in (torch.tensor(float(good)), torch.tensor(True)):
        with pytest.raises(TypeError, match=f"^{option}: expected"):
            _option_call(function, **{option: wrong_type})
    if function in ("fit_sequence", "solve"):
        return  # (a clip fit, a solver without a problem here: the check is the point)
    as_tensor, as_number = (_option_call(function, **{option: v}) for v in (torch.tensor(good), good))
    if isinstance(as_tensor, (int, list)):
        assert as_tensor == as_number and type(as_tensor) is type(as_number)
        return
    pairs = [(a, b) for a, b in zip(*(dataclasses.astuple(r) if dataclasses.is_dataclass(r) else (r.K,) if hasattr(r, "K")
                                      else r if isinstance(r, tuple) else (r,) for r in (as_tensor, as_number)))
             if isinstance(a, torch.Tensor)]
    assert pairs and all(torch.equal(a, b) for a, b in pairs)
