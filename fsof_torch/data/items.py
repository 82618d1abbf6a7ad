"""The dataset item contract: one dict of one image pair, the same keys for every data set.

Every dataset of :mod:`fsof_torch.datasets` (and the ``refine`` job, which loads through them)
returns items with these keys, always present; a value the data does not have is ``None``:

==================  ===============================================================================
``image1``          (3, H, W) float RGB, 0..255 (grey images repeated to 3 channels), frame t
``image2``          (3, H, W) the same for frame t+1
``camera``          :class:`fsof_torch.Camera` of batch 1, K at the images' resolution, with the
                    mounting (height m, roll and pitch rad); None without a calibration
``flow``            (2, H, W) px, ground-truth forward flow t -> t+1 (channel 0 = u); or None
``valid``           (1, H, W) bool, where the ground truth holds (for ``flow``, or for
                    ``flow_velocity`` where only that exists); None without ground truth
``road``            (1, H, W) bool road (freespace) mask; or None
``odometry``        dict ``x_d``, ``z_d`` (m), ``yaw`` (rad) of Python floats: the planar ego-motion
                    t -> t+1 of the displacement model (DESIGN.md §2); or None
``relative_pose``   (4, 4) float64 ``cam1_T_cam0``, a *given* relative pose (from a poses file:
                    camera-t coordinates -> camera-(t+1) coordinates); or None. ``odometry`` is
                    its planar part under ``camera``'s mounting. Synthetic scenes give their exact
                    motion as ``odometry`` (and ``plane``, ``pose1``, ``pose2``) instead.
``index``           int, the item's position in its dataset
``name``            str, the pair's name: its first frame's file stem (``000042``), ``NAME`` of a
                    KITTI ``NAME_10``/``NAME_11`` pair, the scene's ``000000``-style index
==================  ===============================================================================

Some data sets carry more (keys present only there):

==========================  =======================================================================
``flow_velocity``           (2, H, W) px/s, instantaneous flow (synthetic scenes, CARLA)
``labels``, ``depth``       (H, W) int64 classes, (1, H, W) m camera depth (synthetic scenes)
``moving``                  (1, H, W) bool pixels on moving cars (rendered scenes)
``velocity``                dict ``speed``, ``steering``, ``wheelbase``, ``dt`` (synthetic scenes)
``pose1``, ``pose2``        (4, 4) float64 camera-to-world poses (synthetic scenes)
``road_pose``, ``plane``    dicts of floats: the camera over the road at t and the rigid plane
                            motion t -> t+1 (synthetic scenes; :func:`fsof_torch.scene.render_pair`)
``pose_residual``           dict ``y_d`` (m), ``rotation`` (rad): what ``odometry`` drops of
                            ``relative_pose`` (data with poses)
==========================  =======================================================================

:func:`make_item` builds an item (:func:`as_item` from a dict with some of the keys),
:func:`check_item` checks one against the contract (for your own datasets), :func:`collate`
batches items for a ``DataLoader``.
"""

from __future__ import annotations

import functools
import math
import numbers
from typing import Any, Mapping, Sequence

import torch
from torch import Tensor

from .._check import autocast_off, check_bool
from ..geometry.camera import Camera

__all__ = ["ITEM_KEYS", "ODOMETRY_KEYS", "as_item", "make_item", "check_item", "check_item_options", "collate",
           "concat_cameras"]

def check_item_options(dtype: object, camera_dtype: object, ground_truth: object) -> torch.dtype:
    """The options every dataset takes: ``dtype`` and ``camera_dtype`` float32 or float64 (None:
    ``dtype``), ``ground_truth`` a bool (TypeError naming the argument). Returns the camera dtype."""
    camera_dtype = dtype if camera_dtype is None else camera_dtype
    for name, value in (("dtype", dtype), ("camera_dtype", camera_dtype)):
        if value not in (torch.float32, torch.float64):
            raise TypeError(f"{name}: expected torch.float32 or torch.float64, got {value!r}")
    check_bool(ground_truth, "ground_truth")  # a truthy string such as "no" would pass as True
    return camera_dtype


#: the keys of every item, in order
ITEM_KEYS = ("image1", "image2", "camera", "flow", "valid", "road", "odometry", "relative_pose", "index", "name")
#: the keys of ``odometry``
ODOMETRY_KEYS = ("x_d", "z_d", "yaw")


def make_item(image1: Tensor, image2: Tensor, *, index: int, name: str, camera: Camera | None = None,
              flow: Tensor | None = None, valid: Tensor | None = None, road: Tensor | None = None,
              odometry: Mapping[str, float] | None = None, relative_pose: Tensor | None = None,
              **extras: Any) -> dict[str, Any]:
    """An item of the contract (see the module docstring): the keys of :data:`ITEM_KEYS` in order,
    then ``extras``.

    ``index`` must be an int (not a bool), ``name`` a str (TypeError otherwise); ``odometry`` a
    dict with exactly the keys ``x_d``, ``z_d``, ``yaw`` of finite real numbers (Python or NumPy
    scalars, 0-d tensors), stored as Python floats (a TypeError or ValueError naming ``odometry``
    otherwise).
    """
    if isinstance(index, bool) or not isinstance(index, numbers.Integral):
        raise TypeError(f"index: expected an int, got {type(index).__name__} {index!r}")
    if not isinstance(name, str):
        raise TypeError(f"name: expected a str, got {type(name).__name__} {name!r}")
    if odometry is not None:
        odometry = _odometry_floats(odometry)
    item = {"image1": image1, "image2": image2, "camera": camera, "flow": flow, "valid": valid, "road": road,
            "odometry": odometry, "relative_pose": relative_pose, "index": int(index), "name": name}
    item.update(extras)
    return item


def _odometry_floats(odometry: object) -> dict[str, float]:
    """``odometry`` checked (exactly the keys of :data:`ODOMETRY_KEYS`, finite real values) as floats."""
    if not isinstance(odometry, Mapping):
        raise TypeError(f"odometry: expected a dict with keys {list(ODOMETRY_KEYS)}, got {type(odometry).__name__} "
                        f"{odometry!r}")
    if set(odometry) != set(ODOMETRY_KEYS):
        raise ValueError(f"odometry: expected exactly the keys {list(ODOMETRY_KEYS)}, got {list(odometry)}")
    out = {}
    for k in ODOMETRY_KEYS:
        v = odometry[k]
        scalar_tensor = isinstance(v, Tensor) and v.dim() == 0 and v.dtype != torch.bool and not v.is_complex()
        if not scalar_tensor and (isinstance(v, bool) or not isinstance(v, numbers.Real)):
            raise TypeError(f"odometry: expected real numbers, got {type(v).__name__} {v!r} for {k!r}")
        out[k] = float(v)
        if not math.isfinite(out[k]):
            raise ValueError(f"odometry: expected finite values, got {out[k]!r} for {k!r}")
    return out


def as_item(sample: Mapping[str, Any], **changes: Any) -> dict[str, Any]:
    """An item of the contract from a dict that holds its keys where present (the output of
    :func:`fsof_torch.scene.render_pair` or :func:`fsof_torch.io.read_synthetic_pair`), with
    ``changes`` applied: absent keys of the contract become None, the others stay as extras.
    ``image1``, ``image2``, ``index`` and ``name`` must be given, in ``sample`` or ``changes``
    (a rendered pair holds no ``name``: ``as_item(pair, name="000000")``); a ValueError names
    the missing ones, and a ``sample`` that is no dict is a TypeError."""
    if not isinstance(sample, Mapping):
        raise TypeError(f"sample: expected a dict, got {type(sample).__name__} {sample!r:.60}")
    d = {**sample, **changes}
    missing = [k for k in ("image1", "image2", "index", "name") if k not in d]
    if missing:
        raise ValueError(f"sample: has no {', '.join(map(repr, missing))}; give "
                         f"{'them' if len(missing) > 1 else 'it'} in the dict or as keyword arguments "
                         f"(as_item(pair, name='000000'))")
    images = d.pop("image1"), d.pop("image2")
    index, name = d.pop("index"), d.pop("name")
    core = {k: d.pop(k, None) for k in ITEM_KEYS if k not in ("image1", "image2", "index", "name")}
    return make_item(*images, index=index, name=name, **core, **d)


def _check_tensor(item: Mapping[str, Any], key: str, shape: tuple, *, boolean: bool = False,
                  dtype: torch.dtype | None = None) -> None:
    """``item[key]`` a tensor of ``shape``: bool where ``boolean``, of ``dtype`` where given, else float."""
    x = item[key]
    if not isinstance(x, Tensor):
        raise TypeError(f"item[{key!r}]: expected a tensor of shape {shape}, got {type(x).__name__}")
    if tuple(x.shape) != shape:
        raise ValueError(f"item[{key!r}]: expected shape {shape}, got {tuple(x.shape)}")
    if boolean and x.dtype != torch.bool:
        raise TypeError(f"item[{key!r}]: expected a bool tensor, got {x.dtype}")
    if dtype is not None and x.dtype != dtype:
        raise TypeError(f"item[{key!r}]: expected a {dtype} tensor, got {x.dtype}")
    if not boolean and dtype is None and not x.is_floating_point():
        raise TypeError(f"item[{key!r}]: expected a float tensor, got {x.dtype}")


def check_item(item: Mapping[str, Any]) -> None:
    """Check ``item`` against the contract: every key of :data:`ITEM_KEYS` present, tensors of
    the documented shapes and dtypes at the images' size (the extras ``flow_velocity``,
    ``moving``, ``labels``, ``depth``, ``pose1``, ``pose2`` too, where present), ``valid`` beside
    ground truth (``flow`` or ``flow_velocity``), ``camera`` of batch 1, ``odometry`` finite
    floats; a ValueError or TypeError names the key and quotes what came."""
    if not isinstance(item, Mapping):
        raise TypeError(f"item: expected a dict, got {type(item).__name__}")
    missing = [k for k in ITEM_KEYS if k not in item]
    if missing:
        raise ValueError(f"item: missing keys {missing} (every key of the contract is present, None where absent)")
    image1 = item["image1"]
    if not isinstance(image1, Tensor) or image1.dim() != 3 or image1.shape[0] != 3:
        got = tuple(image1.shape) if isinstance(image1, Tensor) else type(image1).__name__
        raise ValueError(f"item['image1']: expected a tensor of shape (3, H, W), got {got}")
    H, W = image1.shape[-2:]
    _check_tensor(item, "image1", (3, H, W))
    _check_tensor(item, "image2", (3, H, W))
    for key, channels, boolean in (("flow", 2, False), ("valid", 1, True), ("road", 1, True),
                                   ("flow_velocity", 2, False), ("moving", 1, True)):
        if item.get(key) is not None:
            _check_tensor(item, key, (channels, H, W), boolean=boolean)
    for key, shape, dtype in (("labels", (H, W), torch.int64), ("depth", (1, H, W), None),
                              ("pose1", (4, 4), torch.float64), ("pose2", (4, 4), torch.float64)):
        if item.get(key) is not None:
            _check_tensor(item, key, shape, dtype=dtype)
    for key in ("flow", "flow_velocity"):
        if item.get(key) is not None and item["valid"] is None:
            raise ValueError(f"item['valid']: None beside a ground-truth {key}; expected (1, H, W) bool")
    camera = item["camera"]
    if camera is not None and not (isinstance(camera, Camera) and camera.batch_size == 1):
        raise TypeError(f"item['camera']: expected a Camera of batch 1 or None, got {camera!r}")
    odometry = item["odometry"]
    if odometry is not None:
        if not isinstance(odometry, Mapping) or set(odometry) != set(ODOMETRY_KEYS):
            raise ValueError(f"item['odometry']: expected a dict with keys {list(ODOMETRY_KEYS)}, got {odometry!r}")
        if not all(isinstance(v, float) for v in odometry.values()):
            raise TypeError(f"item['odometry']: expected Python floats, got {odometry!r}")
        if not all(math.isfinite(v) for v in odometry.values()):
            raise ValueError(f"item['odometry']: expected finite values, got {odometry!r}")
    pose = item["relative_pose"]
    if pose is not None:
        if not isinstance(pose, Tensor) or tuple(pose.shape) != (4, 4) or pose.dtype != torch.float64:
            raise ValueError(f"item['relative_pose']: expected a (4, 4) float64 tensor or None, got "
                             f"{tuple(pose.shape) if isinstance(pose, Tensor) else type(pose).__name__}")
    if isinstance(item["index"], bool) or not isinstance(item["index"], numbers.Integral):
        raise TypeError(f"item['index']: expected an int, got {item['index']!r}")
    if not isinstance(item["name"], str):
        raise TypeError(f"item['name']: expected a str, got {item['name']!r}")


def concat_cameras(cameras: Sequence[Camera]) -> Camera:
    """One Camera of batch sum(B_i) from several (dtype promoted, device of the first).
    ``cameras`` must be a non-empty list or tuple of Cameras (a TypeError naming ``cameras`` and
    the odd one otherwise, such as a Camera itself or a None among them)."""
    if not isinstance(cameras, (list, tuple)):
        raise TypeError(f"cameras: expected a list of Cameras, got {type(cameras).__name__}")
    if not cameras:
        raise ValueError("cameras: expected at least one Camera")
    odd = next((i for i, c in enumerate(cameras) if not isinstance(c, Camera)), None)
    if odd is not None:
        raise TypeError(f"cameras: item {odd} is a {type(cameras[odd]).__name__}, expected a Camera")
    dtype = cameras[0].dtype
    for cam in cameras[1:]:
        dtype = torch.promote_types(dtype, cam.dtype)
    device = cameras[0].device
    parts = [c.to(device=device, dtype=dtype) for c in cameras]
    return Camera(torch.cat([c.K for c in parts]), torch.cat([c.height for c in parts]),
                  torch.cat([c.roll for c in parts]), torch.cat([c.pitch for c in parts]))


def _kind(value: Any) -> str:
    """What :func:`collate` does with a value, in words: every item must give a key the same kind."""
    if isinstance(value, Tensor):
        return "a tensor"
    if isinstance(value, Camera):
        return "a Camera"
    if isinstance(value, Mapping):
        return "a dict of numbers" if _holds_numbers(value) else "a dict"
    return "not a tensor, Camera or dict"


def _holds_numbers(d: Mapping[str, Any]) -> bool:
    """Whether :func:`collate` batches the dict ``d`` into (B,) tensors: every value a real number."""
    return all(isinstance(x, numbers.Real) for x in d.values())


def _which(samples: Sequence[Mapping[str, Any]], i: int) -> str:
    """``item i``, with the pair's name where the item holds one (``item 1 (pair '000007')``): the
    position in a DataLoader's batch alone does not say which pair of the dataset it was."""
    pair = samples[i].get("name")
    return f"item {i}" + (f" (pair {pair!r})" if isinstance(pair, str) else "")


def _check_samples(samples: object, name: str) -> list[str]:
    """``samples`` a non-empty list or tuple of dicts with the same keys, each key of the same kind
    (a dict of numbers in every item or in none, with the same keys) in every item where it is not
    None, every Camera of batch 1: the keys."""
    if not isinstance(samples, (list, tuple)):
        raise TypeError(f"{name}: expected a non-empty list of dicts, got {type(samples).__name__}")
    if not samples:
        raise ValueError(f"{name}: expected a non-empty list of dicts, got an empty one")
    for i, s in enumerate(samples):
        if not isinstance(s, Mapping):
            raise TypeError(f"{name}: item {i} is a {type(s).__name__}, expected a dict")
    keys = list(samples[0].keys())
    for i, s in enumerate(samples[1:], 1):
        if set(s.keys()) != set(keys):
            diff = sorted(set(s.keys()) ^ set(keys))
            raise ValueError(f"{name}: item {i} has different keys from item 0 (differing: {diff})")
    for key in keys:
        given = [(i, s[key]) for i, s in enumerate(samples) if s[key] is not None]
        if not given:
            continue
        i0, first = given[0]
        for i, v in given:
            if isinstance(v, Camera) and v.batch_size != 1:
                raise ValueError(f"{name}: {key!r} of item {i} is a Camera of batch {v.batch_size}; expected batch 1 "
                                 f"(an item holds one pair)")
        for i, v in given[1:]:
            if isinstance(v, Mapping) and isinstance(first, Mapping):
                if set(v) != set(first):
                    raise ValueError(f"{name}: {key!r} of item {i} has keys {sorted(v)}, but {sorted(first)} "
                                     f"in item {i0}")
                if _holds_numbers(v) != _holds_numbers(first):
                    # each item's dict is judged alike: item 0 alone must not decide how the others batch
                    (j, other), (k, _) = ((i, v), (i0, first)) if _holds_numbers(first) else ((i0, first), (i, v))
                    bad = {name: x for name, x in other.items() if not isinstance(x, numbers.Real)}
                    raise TypeError(f"{name}: {key!r} of item {j} has values that are not numbers {bad!r}, but "
                                    f"numbers only in item {k} (a dict of numbers in every item becomes (B,) "
                                    f"tensors, another dict in every item a list)")
            elif _kind(v) != _kind(first):
                raise TypeError(f"{name}: {key!r} of item {i} is a {type(v).__name__}, but a {type(first).__name__} "
                                f"in item {i0} (a key holds tensors, Cameras, dicts or other values in every item)")
    return keys


def collate(samples: Sequence[Mapping[str, Any]], *, name: str = "samples") -> dict[str, Any]:
    """Batch a list of dataset items (for ``DataLoader(..., collate_fn=collate)``).

    Tensors -> stacked (B, ...); Camera -> one Camera of batch B (dtype promoted, as
    :func:`concat_cameras`); dicts of numbers (odometry, velocity) -> dicts of (B,) tensors (the
    cameras' promoted dtype, else float64); a key that is None in every item -> None; anything else
    (index, name) -> a list. The same rules serve :func:`fsof_torch.scene.collate`, so rendered pairs
    and items read from disk batch alike. ``samples`` must be a non-empty list or tuple of dicts with
    the same keys; a key None in one item must be None in all, and a key must hold the same kind of
    value in every item: tensors of one shape, dtype and device (no promotion), Cameras of batch 1,
    dicts with the same keys that hold only numbers in every item or in none, or other values (a
    ValueError or TypeError naming the key and the item otherwise: its position and, where it has
    a str ``name``, its pair's name). The errors start with ``name``,
    the argument's name where a wrapper takes the items (:func:`fsof_torch.scene.collate`: ``pairs``).
    """
    keys = _check_samples(samples, name)
    cams = [s[k] for s in samples for k in keys if isinstance(s[k], Camera)]
    float_dtype = functools.reduce(torch.promote_types, [c.dtype for c in cams]) if cams else torch.float64
    batch: dict[str, Any] = {}
    for key in keys:
        values = [s[key] for s in samples]
        absent = [v is None for v in values]
        if all(absent):
            batch[key] = None
            continue
        if any(absent):
            raise ValueError(f"{name}: {key!r} is None in {_which(samples, absent.index(True))} but not in "
                             f"{_which(samples, absent.index(False))}; batch items that have the same data")
        first = values[0]
        if isinstance(first, Tensor):
            odd = next((i for i, v in enumerate(values) if v.shape != first.shape), None)
            if odd is not None:  # (naming the pairs: which file of the dataset has another size)
                raise ValueError(f"{name}: {key!r} has different shapes: {tuple(first.shape)} in "
                                 f"{_which(samples, 0)} but {tuple(values[odd].shape)} in {_which(samples, odd)}; "
                                 f"use batch_size=1 or images of one size")
            # torch.stack would promote dtypes (a bool mask beside a uint8 one becomes uint8) without a word
            for what in ("dtype", "device"):
                odd = next((i for i, v in enumerate(values) if getattr(v, what) != getattr(first, what)), None)
                if odd is not None:
                    raise ValueError(f"{name}: {key!r} has {what} {getattr(first, what)} in {_which(samples, 0)} "
                                     f"but {getattr(values[odd], what)} in {_which(samples, odd)}; batch items of "
                                     f"one {what}")
            with autocast_off(first):  # (autocast's stack refuses a half dtype other than its own)
                batch[key] = torch.stack(values)
        elif isinstance(first, Camera):
            batch[key] = concat_cameras(values)
        elif isinstance(first, Mapping) and _holds_numbers(first):  # then in every item (_check_samples)
            # (on the CPU, as the numbers were, not on torch's default device)
            batch[key] = {k: torch.tensor([float(v[k]) for v in values], dtype=float_dtype, device="cpu") for k in first}
        else:
            batch[key] = list(values)
    return batch
