"""fsof_torch.data.items: the one item contract of the datasets and the job, written once in the
docs and in the module; make_item, as_item, check_item, collate with absent (None) values."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from fsof_torch.data import items
from fsof_torch.data.items import ITEM_KEYS, as_item, check_item, collate, make_item
from fsof_torch.geometry.camera import Camera

DOCS = Path(__file__).resolve().parents[1] / "docs" / "data-formats.md"
H, W = 6, 10


def _documented_keys(text: str, heading: str, table: int) -> list[str]:
    """The backticked names in the first column of table ``table`` (0-based) under ``heading``."""
    section = text.split(heading, 1)[1].split("\n## ", 1)[0]
    tables, rows = [], []
    for line in section.splitlines():
        if line.startswith("|"):
            rows.append(line)
        elif rows:
            tables.append(rows)
            rows = []
    if rows:
        tables.append(rows)
    first = [row.split("|")[1] for row in tables[table][2:]]
    return [name for cell in first for name in re.findall(r"`([a-z_0-9]+)`", cell)]


def test_the_docs_list_the_contracts_keys_in_order():
    text = DOCS.read_text()
    assert tuple(_documented_keys(text, "## Datasets and their items", 0)) == ITEM_KEYS
    extras = _documented_keys(text, "## Datasets and their items", 1)
    assert extras == ["flow_velocity", "labels", "depth", "moving", "velocity", "pose1", "pose2", "road_pose",
                      "plane", "pose_residual"]
    # the module's docstring lists the same keys, each in its first column
    for key in (*ITEM_KEYS, *extras):
        assert re.search(rf"^``{key}``|, ``{key}``", items.__doc__, re.M), key


def _item(**changes):
    g = torch.Generator().manual_seed(0)
    base = dict(image1=torch.rand(3, H, W, generator=g) * 255, image2=torch.rand(3, H, W, generator=g) * 255,
                index=3, name="000003", camera=Camera(torch.eye(3), 1.5))
    return make_item(**{**base, **changes})


def test_make_item_has_every_key_in_order_and_floats():
    item = _item(odometry={"x_d": torch.tensor(0.1), "z_d": 1, "yaw": np.float32(0.0)}, note="x")
    assert tuple(item) == (*ITEM_KEYS, "note")
    assert item["odometry"] == {"x_d": pytest.approx(0.1), "z_d": 1.0, "yaw": 0.0}
    assert all(type(v) is float for v in item["odometry"].values())
    assert item["flow"] is None and item["road"] is None and item["relative_pose"] is None
    check_item(item)


@pytest.mark.parametrize("change, error, match", [
    ({"index": 2.9}, TypeError, r"index: expected an int, got float 2\.9"),
    ({"index": True}, TypeError, r"index: expected an int, got bool True"),
    ({"name": None}, TypeError, r"name: expected a str, got NoneType None"),
    ({"odometry": [1, 2, 3]}, TypeError, r"odometry: expected a dict with keys \['x_d', 'z_d', 'yaw'\], got list"),
    ({"odometry": {"x_d": 1.0, "z_d": 2.0}}, ValueError,
     r"odometry: expected exactly the keys \['x_d', 'z_d', 'yaw'\], got \['x_d', 'z_d'\]"),
    ({"odometry": {"x_d": 1.0, "z_d": 2.0, "yaw": 0.0, "extra": 5.0}}, ValueError, r"odometry: expected exactly"),
    ({"odometry": {"x_d": "a", "z_d": 1, "yaw": 0}}, TypeError, r"odometry: expected real numbers, got str 'a' for 'x_d'"),
    ({"odometry": {"x_d": 0.0, "z_d": True, "yaw": 0}}, TypeError, r"odometry: expected real numbers, got bool True"),
    ({"odometry": {"x_d": 0.0, "z_d": 1.0, "yaw": float("nan")}}, ValueError,
     r"odometry: expected finite values, got nan for 'yaw'"),
])
def test_make_item_refuses_what_it_would_have_converted(change, error, match):
    # index=2.9 became 2, name=None became 'None', and bad odometry a bare KeyError / ValueError
    with pytest.raises(error, match=match):
        _item(**change)


def test_make_item_takes_integer_indices_of_numpy():
    item = _item(index=np.int64(4))
    assert item["index"] == 4 and type(item["index"]) is int


def test_as_item_fills_the_absent_keys_and_keeps_extras():
    from fsof_torch.data.scene import render_pair

    p = render_pair("default", 0, size=(24, 80))
    item = as_item(p, name="000000")
    assert tuple(item)[:len(ITEM_KEYS)] == ITEM_KEYS
    assert item["relative_pose"] is None and torch.equal(item["flow"], p["flow"]) and item["index"] == 0
    assert {"flow_velocity", "labels", "depth", "moving", "velocity", "pose1", "pose2", "road_pose", "plane"} \
        <= set(item)
    check_item(item)
    bare = as_item({"image1": p["image1"], "image2": p["image2"], "index": 1, "name": "x"})
    assert all(bare[k] is None for k in ITEM_KEYS if k not in ("image1", "image2", "index", "name"))


def test_as_item_names_what_the_sample_lacks():
    """A rendered pair, which the docstring offers as a sample, holds no name: as_item raised
    KeyError: 'name'; a sample that is no dict a TypeError of the ** unpacking."""
    from fsof_torch.data.scene import render_pair

    p = render_pair("default", 0, size=(24, 80))
    with pytest.raises(ValueError, match=r"^sample: has no 'name'; give it in the dict or as keyword arguments"):
        as_item(p)
    with pytest.raises(ValueError, match=r"^sample: has no 'image2', 'index', 'name'; give them"):
        as_item({"image1": p["image1"]})
    with pytest.raises(TypeError, match=r"^sample: expected a dict, got list"):
        as_item([p])
    assert as_item(p, name="000000")["name"] == "000000"  # (given as a change)


@pytest.mark.parametrize("given, error, message", [
    (lambda cam: cam, TypeError, r"^cameras: expected a list of Cameras, got Camera$"),
    (lambda cam: [cam, None], TypeError, r"^cameras: item 1 is a NoneType, expected a Camera$"),
    (lambda cam: (cam.K, cam), TypeError, r"^cameras: item 0 is a Tensor, expected a Camera$"),
    (lambda cam: [], ValueError, r"^cameras: expected at least one Camera$"),
])
def test_concat_cameras_names_what_is_no_camera(given, error, message):
    """A Camera itself, a None or a K among them were a bare TypeError or AttributeError."""
    cam = Camera(torch.eye(3), 1.5)
    with pytest.raises(error, match=message):
        items.concat_cameras(given(cam))
    assert items.concat_cameras((cam, cam)).batch_size == 2


@pytest.mark.parametrize("change, error, match", [
    ({"flow": torch.zeros(2, H, W + 1), "valid": torch.ones(1, H, W, dtype=torch.bool)}, ValueError,
     r"item\['flow'\]: expected shape \(2, 6, 10\), got \(2, 6, 11\)"),
    ({"flow": torch.zeros(2, H, W)}, ValueError, r"item\['valid'\]: None beside a ground-truth flow"),
    ({"road": torch.ones(1, H, W)}, TypeError, r"item\['road'\]: expected a bool tensor, got torch.float32"),
    ({"image2": torch.zeros(3, H + 1, W)}, ValueError, r"item\['image2'\]: expected shape \(3, 6, 10\)"),
    ({"image1": torch.zeros(1, H, W)}, ValueError, r"item\['image1'\]: expected a tensor of shape \(3, H, W\)"),
    ({"relative_pose": torch.eye(4)}, ValueError, r"item\['relative_pose'\]: expected a \(4, 4\) float64"),
    ({"camera": Camera(torch.eye(3).expand(2, 3, 3), 1.5)}, TypeError, r"item\['camera'\]: expected a Camera of batch 1"),
    # the extras of the contract, where present (each passed before)
    ({"flow_velocity": torch.zeros(2, H, W)}, ValueError, r"item\['valid'\]: None beside a ground-truth flow_velocity"),
    ({"labels": torch.zeros(7, 7, dtype=torch.int64)}, ValueError,
     r"item\['labels'\]: expected shape \(6, 10\), got \(7, 7\)"),
    ({"labels": torch.zeros(H, W)}, TypeError, r"item\['labels'\]: expected a torch.int64 tensor, got torch.float32"),
    ({"depth": torch.zeros(2, 9, 9)}, ValueError, r"item\['depth'\]: expected shape \(1, 6, 10\), got \(2, 9, 9\)"),
    ({"depth": torch.zeros(1, H, W, dtype=torch.int32)}, TypeError, r"item\['depth'\]: expected a float tensor"),
    ({"pose1": "not a pose"}, TypeError, r"item\['pose1'\]: expected a tensor of shape \(4, 4\), got str"),
    ({"pose2": torch.eye(4)}, TypeError, r"item\['pose2'\]: expected a torch.float64 tensor, got torch.float32"),
])
def test_check_item_names_the_key(change, error, match):
    item = _item()
    item.update(change)
    with pytest.raises(error, match=match):
        check_item(item)


def test_check_item_wants_every_key_and_float_odometry():
    item = _item()
    del item["road"]
    with pytest.raises(ValueError, match=r"item: missing keys \['road'\]"):
        check_item(item)
    item = _item()
    item["odometry"] = {"x_d": 0.0, "z_d": 1.0}
    with pytest.raises(ValueError, match=r"item\['odometry'\]: expected a dict with keys"):
        check_item(item)
    item["odometry"] = {"x_d": 0.0, "z_d": torch.tensor(1.0), "yaw": 0.0}
    with pytest.raises(TypeError, match=r"item\['odometry'\]: expected Python floats"):
        check_item(item)
    item["odometry"] = {"x_d": 0.0, "z_d": float("nan"), "yaw": 0.0}  # (a NaN passed, then batched)
    with pytest.raises(ValueError, match=r"item\['odometry'\]: expected finite values, got .*nan"):
        check_item(item)


def test_collate_keeps_keys_absent_in_every_item_and_refuses_a_mix():
    a, b = _item(index=0, name="a"), _item(index=1, name="b")
    batch = collate([a, b])
    assert batch["flow"] is None and batch["odometry"] is None and batch["relative_pose"] is None
    assert batch["image1"].shape == (2, 3, H, W) and batch["camera"].batch_size == 2
    assert batch["index"] == [0, 1] and batch["name"] == ["a", "b"]
    b["road"] = torch.ones(1, H, W, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"samples: 'road' is None in item 0 \(pair 'a'\) but not in item 1 \(pair 'b'\)"):
        collate([a, b])


@pytest.mark.parametrize("order", [(torch.float32, torch.float64), (torch.float64, torch.float32)])
def test_collate_gives_the_odometry_the_cameras_promoted_dtype(order):
    odo = {"x_d": 0.1, "z_d": 1.0, "yaw": 0.01}
    batch = collate([_item(camera=Camera(torch.eye(3, dtype=dt), 1.5), odometry=odo) for dt in order])
    assert batch["camera"].dtype == torch.float64
    assert all(v.dtype == torch.float64 for v in batch["odometry"].values())


def test_collate_refuses_a_camera_of_another_batch_than_1():
    # concat_cameras took it: two items gave a camera of batch 3 beside images of batch 2
    two = Camera(torch.eye(3).expand(2, 3, 3), 1.5)
    for items_ in ([_item(camera=two), _item()], [_item(), _item(camera=two)]):
        i = 0 if items_[0]["camera"] is two else 1
        with pytest.raises(ValueError, match=rf"samples: 'camera' of item {i} is a Camera of batch 2; expected batch 1"):
            collate(items_)


def test_collate_errors_name_the_pairs_of_the_items():
    """A batch of a DataLoader is items 0 .. B-1 of shuffled pairs: an error naming the item's
    position alone did not say which pair had another size or lacked ground truth."""
    a = _item(index=3, name="000003", flow=torch.zeros(2, H, W), valid=torch.ones(1, H, W, dtype=torch.bool))
    b = {**_item(index=8, name="000008"), "flow": torch.zeros(2, H, W + 1), "valid": torch.ones(1, H, W + 1, dtype=torch.bool)}
    with pytest.raises(ValueError, match=rf"^samples: 'flow' has different shapes: \(2, {H}, {W}\) in item 0 "
                                         rf"\(pair '000003'\) but \(2, {H}, {W + 1}\) in item 1 \(pair '000008'\); "
                                         r"use batch_size=1"):
        collate([a, b])
    c = {**_item(index=5, name="000005"), "image1": torch.zeros(3, H + 2, W)}
    with pytest.raises(ValueError, match=r"'image1' has different shapes: .* in item 0 \(pair '000003'\) but "
                                         rf"\(3, {H + 2}, {W}\) in item 2 \(pair '000005'\)"):
        collate([a, {**a, "index": 4, "name": "000004"}, c])
    d = _item(index=9, name="000009")  # no ground truth
    with pytest.raises(ValueError, match=r"'flow' is None in item 1 \(pair '000009'\) but not in item 0 "
                                         r"\(pair '000003'\)"):
        collate([a, d])
    e = {**a, "name": 7}  # (a name that is not a str: the position alone)
    with pytest.raises(ValueError, match=r"'flow' is None in item 0 but not in item 1;"):
        collate([{**d, "name": 7}, e])


@pytest.mark.parametrize("key, cast, match", [
    ("valid", lambda v: v.to(torch.uint8), r"samples: 'valid' has dtype torch.bool in item 0 .* but torch.uint8 in item 1"),
    ("flow", lambda v: v.to(torch.int64), r"samples: 'flow' has dtype torch.float32 in item 0 .* but torch.int64 in item 1"),
    ("image1", lambda v: v.double(), r"samples: 'image1' has dtype torch.float32 in item 0 .* but torch.float64 in item 1"),
    ("flow", lambda v: v.to("meta"), r"samples: 'flow' has device cpu in item 0 .* but meta in item 1"),
])
def test_collate_refuses_tensors_of_different_dtypes_or_devices(key, cast, match):
    # torch.stack promoted the dtypes without a word (a bool and a uint8 mask gave a uint8 one)
    a = _item(flow=torch.zeros(2, H, W), valid=torch.ones(1, H, W, dtype=torch.bool))
    b = {**a, key: cast(a[key])}
    with pytest.raises(ValueError, match=match):
        collate([a, b])


@pytest.mark.parametrize("half, amp", [(torch.float16, torch.bfloat16), (torch.bfloat16, torch.float16)],
                         ids=["f16-under-bf16", "bf16-under-f16"])
def test_collate_stacks_half_tensors_under_autocast_of_the_other_half_dtype(half, amp):
    """Items holding float16 tensors collated under bfloat16 autocast (or the reverse) raised
    torch's RuntimeError "Unexpected floating ScalarType in at::autocast::prioritize" (autocast's
    stack refuses the half dtype it does not cast to): they are stacked in their own dtype."""
    g = torch.Generator().manual_seed(0)
    a, b = (_item(flow=torch.randn(2, H, W, generator=g).to(half), valid=torch.ones(1, H, W, dtype=torch.bool))
            for _ in range(2))
    with torch.autocast("cpu", dtype=amp):
        batch = collate([a, b])
    assert batch["flow"].dtype == half and torch.equal(batch["flow"], torch.stack([a["flow"], b["flow"]]))
    assert batch["image1"].dtype == a["image1"].dtype


def test_collate_judges_every_items_dict_alike():
    odo = {"x_d": 0.1, "z_d": 1.0, "yaw": 0.0}
    tensors = {k: torch.tensor(v) for k, v in odo.items()}
    # tensors in item 0 and floats in item 1 gave a list of dicts; the other order raised
    for first, second, bad in ((tensors, odo, 0), (odo, tensors, 1)):
        a, b = _item(index=0), _item(index=1)
        a["odometry"], b["odometry"] = first, second
        with pytest.raises(TypeError, match=rf"samples: 'odometry' of item {bad} has values that are not numbers .*, "
                                            rf"but numbers only in item {1 - bad}"):
            collate([a, b])
    # the same kind in every item: dicts of numbers become (B,) tensors, other dicts a list
    a, b = _item(index=0), _item(index=1)
    a["odometry"], b["odometry"] = dict(tensors), dict(tensors)
    assert isinstance(collate([a, b])["odometry"], list)
    assert collate([_item(odometry=odo), _item(odometry=odo)])["odometry"]["x_d"].shape == (2,)


def test_collate_names_the_key_and_the_item():
    a = _item(odometry={"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}, flow=torch.zeros(2, H, W),
              valid=torch.ones(1, H, W, dtype=torch.bool))
    with pytest.raises(TypeError, match="samples: expected a non-empty list of dicts, got dict"):
        collate(a)
    with pytest.raises(ValueError, match="samples: expected a non-empty list of dicts"):
        collate([])
    with pytest.raises(TypeError, match="samples: item 0 is a NoneType, expected a dict"):
        collate([None])
    with pytest.raises(TypeError, match="samples: item 1 is a str, expected a dict"):
        collate([a, "b"])
    b = {**a, "odometry": {"x_d": 0.0, "z_d": 1.0}}
    with pytest.raises(ValueError, match=r"samples: 'odometry' of item 1 has keys \['x_d', 'z_d'\], "
                                         r"but \['x_d', 'yaw', 'z_d'\] in item 0"):
        collate([a, b])
    b = {**a, "odometry": {"x_d": 0.0, "z_d": "1", "yaw": 0.0}}
    with pytest.raises(TypeError, match="samples: 'odometry' of item 1 has values that are not numbers"):
        collate([a, b])
    b = {**a, "flow": a["flow"].numpy()}
    with pytest.raises(TypeError, match="samples: 'flow' of item 1 is a ndarray, but a Tensor in item 0"):
        collate([a, b])
    b = {**a, "camera": torch.eye(3)}
    with pytest.raises(TypeError, match="samples: 'camera' of item 1 is a Tensor, but a Camera in item 0"):
        collate([a, b])
