"""The camera: intrinsics and mounting (height above the road, roll, pitch), batched.

Convention (DESIGN.md §2): pixel (u, v) with u right, v down, origin at the centre of the
top-left pixel; vehicle frame x right, y down, z forward, the road is the plane y = h;
``p_cam = R_roll @ R_pitch @ p_vehicle`` with

    R_roll  = [[cos θ, sin θ, 0], [-sin θ, cos θ, 0], [0, 0, 1]]
    R_pitch = [[1, 0, 0], [0, cos β, sin β], [0, -sin β, cos β]]   (β > 0: camera looks up)

Angles in radians, heights in metres, focal lengths in pixels.
"""

from __future__ import annotations

import math
import numbers
import os
import re
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from .._check import (
    as_batch_param,
    autocast_off,
    existing_file,
    check_finite,
    check_float_tensor,
    check_int,
    check_same_device,
    check_positive,
    resolve_batch,
    option_error,
    result_dtype,
    scalar,
    skip_values,
    summary_repr,
)

__all__ = ["Camera", "check_camera", "roll_matrix", "pitch_matrix", "mounting_matrix", "read_kitti_calibration",
           "camera_value_bounds", "check_camera_index", "split_calibration_line"]


def roll_matrix(roll: Tensor) -> Tensor:
    """R_θ (B, 3, 3) of the paper for roll angles (B,) in radians, in the angles' dtype with half
    precision lifted to float32 (as the rest of the geometry: a half precision rotation is off
    by up to 1e-3, bfloat16 by 1e-2).

    Elementwise, as ``torch.cos``: a NaN or inf angle gives NaN entries (a :class:`Camera`
    rejects non-finite angles before they get here)."""
    check_float_tensor(roll, "roll")
    roll = roll.to(result_dtype(roll))
    c, s = torch.cos(roll), torch.sin(roll)
    z, o = torch.zeros_like(roll), torch.ones_like(roll)
    return torch.stack([c, s, z, -s, c, z, z, z, o], dim=-1).reshape(*roll.shape, 3, 3)


def pitch_matrix(pitch: Tensor) -> Tensor:
    """R_β (B, 3, 3) for pitch angles (B,) in radians (β > 0: the camera looks up); elementwise
    and in the angles' dtype (half precision lifted to float32) like :func:`roll_matrix`."""
    check_float_tensor(pitch, "pitch")
    pitch = pitch.to(result_dtype(pitch))
    c, s = torch.cos(pitch), torch.sin(pitch)
    z, o = torch.zeros_like(pitch), torch.ones_like(pitch)
    return torch.stack([o, z, z, z, c, s, z, -s, c], dim=-1).reshape(*pitch.shape, 3, 3)


def mounting_matrix(roll: Tensor, pitch: Tensor) -> Tensor:
    """R_c = R_θ R_β (B, 3, 3): rotates vehicle-frame vectors into the camera frame (roll and
    pitch of batch 1 or B, in their promoted dtype, half precision lifted to float32)."""
    Rr, Rp = roll_matrix(roll), pitch_matrix(pitch)
    check_same_device({"roll": roll, "pitch": pitch})
    if roll.dim() and pitch.dim():
        resolve_batch({"roll": roll.shape[0], "pitch": pitch.shape[0]})
    dtype = torch.promote_types(Rr.dtype, Rp.dtype)
    with autocast_off(Rr):  # (the angles' own precision, also under autocast)
        return Rr.to(dtype) @ Rp.to(dtype)


def camera_value_bounds(dtype: torch.dtype) -> tuple[float, float]:
    """The magnitudes ``(lo, hi)`` a camera of ``dtype`` may hold: focal lengths and the height
    in [lo, hi], |principal point| and |skew| at most hi.

    Why the fifth root of the dtype's range: the road geometry multiplies up to about five
    camera-scale quantities before a division brings the result back to pixels. The velocity
    model's terms are f · ((u - c) / f)² · (v / h)-like products, the fit's Jacobians square
    normalised coordinates (u - c) / f, and the homography K R K⁻¹ applied to a pixel multiplies
    c by c / f by u. With every factor (a focal length, a principal point, a pixel coordinate, a
    height) within [max^(-1/5), max^(1/5)], any product of five lies within [1/max, max]: it
    neither overflows to inf nor underflows to 0, so a camera that passes cannot make the flow
    NaN through its own scale. The bounds are the powers of two just inside those roots (exact
    in every dtype): float32 [2^-25, 2^25] = [3.0e-8, 3.4e7]; float64 [2^-204, 2^204] =
    [3.9e-62, 2.6e61] (half precision cameras are stored in float32). Real cameras sit far
    inside both ranges.
    """
    k = math.floor(math.log2(torch.finfo(dtype).max) / 5)
    return 2.0 ** -k, 2.0 ** k


def _check_camera_values(K: Tensor, height: Tensor) -> None:
    """Reject values whose geometry overflows or underflows in K's dtype (see camera_value_bounds)."""
    if skip_values(K, height):
        return
    lo, hi = camera_value_bounds(K.dtype)
    f = torch.stack([K[:, 0, 0], K[:, 1, 1]], dim=-1)
    offsets = torch.stack([K[:, 0, 1], K[:, 0, 2], K[:, 1, 2]], dim=-1).abs()
    if not bool(((f >= lo) & (f <= hi)).all()):
        raise ValueError(f"K: expected focal lengths in [{lo:.3g}, {hi:.3g}] px for a {K.dtype} camera "
                         f"(beyond them the road geometry overflows), got f_x={K[:, 0, 0].tolist()}, "
                         f"f_y={K[:, 1, 1].tolist()}")
    if not bool((offsets <= hi).all()):
        raise ValueError(f"K: expected |principal point| and |skew| <= {hi:.3g} px for a {K.dtype} camera "
                         f"(beyond it the road geometry overflows), got c_x={K[:, 0, 2].tolist()}, "
                         f"c_y={K[:, 1, 2].tolist()}, skew={K[:, 0, 1].tolist()}")
    if not bool(((height >= lo) & (height <= hi)).all()):
        raise ValueError(f"height: expected a camera height in [{lo:.3g}, {hi:.3g}] m for a {K.dtype} camera "
                         f"(beyond it the road geometry overflows or underflows), got {height.tolist()}")


def _check_angles(roll: Tensor, pitch: Tensor) -> None:
    """Finite roll and pitch within a quarter turn, |angle| < π/2 (one host read when they are)."""
    if skip_values(roll, pitch):
        return
    if bool((roll.abs() < math.pi / 2).all() & (pitch.abs() < math.pi / 2).all()):  # False for NaN too
        return
    for name, t, symbol in (("roll", roll, "θ"), ("pitch", pitch, "β")):
        check_finite(t, name)
        bad = t[~(t.abs() < math.pi / 2)]
        if bad.numel():
            raise ValueError(f"{name}: expected |{symbol}| < π/2 rad (a camera upright and facing the road), got "
                             f"{bad[:3].tolist()}")


@dataclass(eq=False, repr=False)
class Camera:
    """Intrinsics and mounting of a road-facing camera, for B frames.

    Args:
        K: intrinsics (3, 3) or (B, 3, 3), pixels, at the resolution of the flow.
        height: camera height above the road in metres, a float or (B,) tensor, > 0.
        roll: roll θ about the optical axis in radians, |θ| < π/2, a float or (B,).
        pitch: pitch β in radians, |β| < π/2 (an extension of the paper; 0 reproduces it), a float
            or (B,).

    The angles stay within a quarter turn: beyond it the camera is upside down or looks away from
    the road, and "below the horizon" (:meth:`horizon_row`) no longer means "on the road".

    All four are stored as tensors of one float dtype and device (the promoted dtype of the
    tensors given; Python floats follow it): ``K`` (B, 3, 3), the others (B,), with B the common
    batch size (arguments of batch 1 are broadcast). A tensor given at its field's shape, dtype
    and device is stored as it is, the same object (so a camera of learnable leaf tensors can be
    deep-copied, as ``copy.deepcopy`` copies only graph leaves).

    Cameras are compared by identity, as ``nn.Module`` s are (``a == b`` only for the same
    object; hashable, so usable as a dict key): compare values with ``torch.equal`` on the fields.

    Example:
        >>> cam = Camera(torch.tensor([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]]), 1.65)
        >>> cam.batch_size, cam.fx.tolist()
        (1, [721.5])
    """

    K: Tensor
    height: Tensor | float
    roll: Tensor | float = 0.0
    pitch: Tensor | float = 0.0
    __repr__ = summary_repr  # (one line: K of a large batch as its shape)

    def __post_init__(self) -> None:
        K = self.K
        if not isinstance(K, Tensor):
            raise TypeError(f"K: expected a torch.Tensor of shape (3, 3) or (B, 3, 3), got {type(K).__name__}")
        if not K.is_floating_point():
            raise TypeError(f"K: expected a floating-point tensor, got dtype {K.dtype}")
        if K.dim() not in (2, 3) or K.shape[-2:] != (3, 3):
            raise ValueError(f"K: expected shape (3, 3) or (B, 3, 3), got {tuple(K.shape)}")
        if K.dim() == 2:
            K = K.unsqueeze(0)
        tensors = [K] + [t for t in (self.height, self.roll, self.pitch) if isinstance(t, Tensor)]
        for name in ("height", "roll", "pitch"):
            t = getattr(self, name)
            if isinstance(t, Tensor) and not t.is_floating_point():
                raise TypeError(f"{name}: expected a float tensor or a Python number, got dtype {t.dtype}")
        dtype = result_dtype(*tensors)
        device = K.device
        K = K.to(dtype)
        height = as_batch_param(self.height, "height", dtype, device)
        roll = as_batch_param(self.roll, "roll", dtype, device, finite=False)
        pitch = as_batch_param(self.pitch, "pitch", dtype, device, finite=False)
        _check_angles(roll, pitch)
        B = resolve_batch({"K": K.shape[0], "height": height.shape[0], "roll": roll.shape[0],
                           "pitch": pitch.shape[0]})
        check_finite(K, "K")
        check_positive(height, "height")
        if not skip_values(K):
            fx, fy = K[:, 0, 0], K[:, 1, 1]
            if not bool(((fx > 0) & (fy > 0)).all()):
                raise ValueError(f"K: expected focal lengths f_x, f_y > 0, got f_x={fx.tolist()}, f_y={fy.tolist()}")
            lower = torch.stack([K[:, 1, 0], K[:, 2, 0], K[:, 2, 1]], dim=-1)
            if not bool((lower == 0).all()) or not bool((K[:, 2, 2] == 1).all()):
                raise ValueError(f"K: expected an upper-triangular intrinsic matrix with K[2, 2] = 1, got {K.tolist()}")
        _check_camera_values(K, height)
        # (a field already of batch B kept as given: a view of a leaf that requires grad is no
        # leaf, and copy.deepcopy refuses those)
        self.K = K if K.shape[0] == B else K.expand(B, 3, 3)
        self.height, self.roll, self.pitch = (t if t.shape[0] == B else t.expand(B) for t in (height, roll, pitch))

    # -- derived quantities -------------------------------------------------------------
    @property
    def batch_size(self) -> int:
        """B, the number of frames."""
        return self.K.shape[0]

    @property
    def dtype(self) -> torch.dtype:
        """The float dtype of all four fields."""
        return self.K.dtype

    @property
    def device(self) -> torch.device:
        """The device of all four fields."""
        return self.K.device

    @property
    def fx(self) -> Tensor:
        """(B,) the horizontal focal length f_x, pixels."""
        return self.K[:, 0, 0]

    @property
    def fy(self) -> Tensor:
        """(B,) the vertical focal length f_y, pixels."""
        return self.K[:, 1, 1]

    @property
    def cx(self) -> Tensor:
        """(B,) the principal point's column c_x, pixels."""
        return self.K[:, 0, 2]

    @property
    def cy(self) -> Tensor:
        """(B,) the principal point's row c_y, pixels."""
        return self.K[:, 1, 2]

    def K_inv(self) -> Tensor:
        """Analytic inverse of the upper-triangular K, (B, 3, 3)."""
        K = self.K
        fx, s, cx = K[:, 0, 0], K[:, 0, 1], K[:, 0, 2]
        fy, cy = K[:, 1, 1], K[:, 1, 2]
        z, o = torch.zeros_like(fx), torch.ones_like(fx)
        rows = [1 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy), z, 1 / fy, -cy / fy, z, z, o]
        return torch.stack(rows, dim=-1).reshape(-1, 3, 3)

    def mounting(self) -> Tensor:
        """R_c (B, 3, 3): vehicle-frame vectors to camera-frame vectors."""
        return mounting_matrix(self.roll, self.pitch)

    def horizon_row(self, u: float | Tensor | None = None) -> Tensor:
        """Row v of the horizon at column u (default: the principal point column), (B,).

        Pixels strictly below this row (larger v) see the road in front of the camera: so for
        every camera built with |roll| and |pitch| < π/2, which the constructor requires (a
        camera turned further would see the road above this row, or not at all), and a skew s
        with cos θ − sin θ · s / f_x > 0 (θ the roll; any real camera's skew of about 0).

        Args:
            u: the column, pixels: a finite float or a float tensor of shape (1,) or (B,), B the
                camera's batch (a camera of batch 1 takes any B); None for c_x.
        """
        if u is not None:
            # (a per-frame scalar like the camera's own, checked and named as they are)
            dtype = torch.promote_types(self.dtype, u.dtype) if isinstance(u, Tensor) else self.dtype
            u = as_batch_param(u, "u", dtype, self.device)
            if self.batch_size not in (1, u.shape[0]) and u.shape[0] != 1:
                raise ValueError(f"u: expected a float or a tensor of shape (1,) or ({self.batch_size},) (the "
                                 f"camera's batch), got shape {tuple(u.shape)}")
        with autocast_off(self.K):
            A = self.mounting().transpose(-1, -2) @ self.K_inv()  # rows: vehicle-frame ray of p̃
        u = self.cx if u is None else u
        # ray_y = A[1,0] u + A[1,1] v + A[1,2] = 0
        return -(A[:, 1, 0] * u + A[:, 1, 2]) / A[:, 1, 1]

    # -- constructors and transforms ----------------------------------------------------
    def to(self, *args, **kwargs) -> "Camera":
        """A copy moved / cast like ``Tensor.to`` (``self`` when nothing changes, as there).

        A half precision dtype gives a float32 camera, as the constructor does (the values are
        not rounded to half precision on the way); a cast to a narrower dtype checks the values
        against that dtype's bounds (:func:`camera_value_bounds`)."""
        # (the arguments as nn.Module.to reads them, Tensor.to's copy aside: the target dtype is
        # known before any cast)
        copy = kwargs.pop("copy", False)
        device, dtype, non_blocking, _ = torch._C._nn._parse_to(*args, **kwargs)
        if dtype in (torch.float16, torch.bfloat16):
            dtype = torch.float32
        fields_ = (self.K, self.height, self.roll, self.pitch)
        try:
            moved = [t.to(device=device or t.device, dtype=dtype or t.dtype, non_blocking=non_blocking, copy=copy)
                     for t in fields_]
        except NotImplementedError:  # torch: "Cannot copy out of meta tensor; no data!"
            if self.device.type != "meta":
                raise
            raise ValueError("camera: a camera on the meta device has shapes but no values to move to another "
                             "device; build it there (or keep every input on meta)") from None
        if all(a is b for a, b in zip(moved, fields_)):
            return self
        # a cast to a non-float dtype goes through the checks (and fails there)
        if not moved[0].is_floating_point():
            return Camera(*moved)
        if torch.finfo(moved[0].dtype).max < torch.finfo(self.dtype).max:
            # a narrower dtype has narrower bounds (a float64 focal of 1e10 px is out of float32's)
            _check_camera_values(moved[0], moved[1])
        return Camera._checked(*moved)

    def expand(self, batch_size: int) -> "Camera":
        """The same camera for ``batch_size`` frames (an int >= 1, a NumPy integer too; from a
        batch of 1; ``self`` if it has that batch already)."""
        batch_size = check_int(batch_size, "batch_size", minimum=1)
        if self.batch_size == batch_size:
            return self
        if self.batch_size != 1:
            raise ValueError(f"batch_size: cannot expand a camera of batch {self.batch_size} to {batch_size}")
        return Camera._checked(self.K.expand(batch_size, 3, 3), self.height.expand(batch_size),
                               self.roll.expand(batch_size), self.pitch.expand(batch_size))

    def repeat(self, times: int) -> "Camera":
        """The batch repeated ``times`` times (an int >= 1), as ``Tensor.repeat`` does (frame b of
        copy k is frame k B + b; ``self`` for 1)."""
        times = check_int(times, "times", minimum=1)
        if times == 1:
            return self
        return Camera._checked(self.K.repeat(times, 1, 1), self.height.repeat(times), self.roll.repeat(times),
                               self.pitch.repeat(times))

    @classmethod
    def _checked(cls, K: Tensor, height: Tensor, roll: Tensor, pitch: Tensor) -> "Camera":
        """A camera from values that already passed the checks of ``__post_init__`` (K (B, 3, 3),
        the others (B,), one dtype and device): a cast, move or expansion of a valid camera, or
        a valid camera's K and height with fitted, finite angles (not checked against π/2 either).
        Skips the validation, which costs more than the fitting loop's iterations (it syncs to
        test the values)."""
        cam = object.__new__(cls)
        cam.K, cam.height, cam.roll, cam.pitch = K, height, roll, pitch
        return cam

    def replace(self, **changes: Tensor | float) -> "Camera":
        """A copy with some of ``K, height, roll, pitch`` replaced."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        unknown = set(changes) - set(values)
        if unknown:
            raise TypeError(f"replace: unknown fields {sorted(unknown)}; expected K, height, roll, pitch")
        values.update(changes)
        return Camera(**values)

    def scaled(self, sx: float, sy: float | None = None) -> "Camera":
        """The camera for an image resized by ``sx`` horizontally and ``sy`` vertically.

        Pixel centres map as ``u' + 0.5 = sx (u + 0.5)`` (the convention of
        ``F.interpolate(..., align_corners=False)`` and ``cv2.resize``), so
        ``f_x' = sx f_x`` and ``c_x' = sx (c_x + 0.5) - 0.5``; likewise for y. ``sx`` is the
        factor the resize maps coordinates by: the ratio of the sizes ``w / W`` for a resize to
        a size (``F.interpolate(size=...)``, ``cv2.resize(image, (w, h))``), but the factor
        itself for a resize by a factor (``F.interpolate(scale_factor=s)``, ``cv2.resize(image,
        None, fx=s, fy=s)``), whose output size is rounded (by torch down, by OpenCV to the
        nearest): KITTI's 375 rows at ``scale_factor=0.5`` are 187, and their camera is
        ``scaled(0.5)``, not ``scaled(621 / 1242, 187 / 375)`` (the road flow of z_d = 1.2 m,
        yaw = 0.01 rad 0.18 px off on average, 0.54 px at most). Nearest-neighbour
        resizing does not follow it: ``cv2.INTER_NEAREST`` and ``F.interpolate(mode="nearest")``
        take source pixel ``floor(u' / sx)``: shrunk by a whole factor k (``sx = 1 / k``), that is
        (k - 1) / 2 source pixels short of the centre map (0.5 at half size);
        ``cv2.INTER_NEAREST_EXACT`` and ``"nearest-exact"`` round the centre map instead.
        """
        sx = scalar(sx, "sx")
        sy = sx if sy is None else scalar(sy, "sy")
        for name, s in (("sx", sx), ("sy", sy)):
            if isinstance(s, bool) or not isinstance(s, numbers.Real):
                raise TypeError(f"{name}: expected a number (the resize factor), got {type(s).__name__} {s!r}")
            if not (float(s) > 0 and float(s) < float("inf")):
                raise ValueError(f"{name}: expected a finite scale > 0, got {s!r}")
        S = torch.tensor([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]],
                         dtype=self.dtype, device=self.device)
        try:
            with autocast_off(self.K):
                return self.replace(K=S @ self.K)
        except ValueError as err:
            raise ValueError(f"sx, sy: the camera resized by ({sx!r}, {sy!r}) is out of range: {err}") from None

    def padded(self, left: int, top: int, right: int = 0, bottom: int = 0) -> "Camera":
        """The camera for the image padded by ``left`` columns on the left and ``top`` rows on top
        (``right`` and ``bottom`` at the other sides), as ``F.pad(image, (left, right, top,
        bottom))`` or RAFT's ``InputPadder`` do.

        Convention: the pixel (u, v) of the image is the pixel (u + left, v + top) of the padded
        one, so the principal point moves by the padding on the left and top,
        ``c_x' = c_x + left``, ``c_y' = c_y + top``; focal lengths stay. Padding on the right or
        bottom changes the image size, not K (a camera does not store the size; the arguments
        are accepted so that a padder's four numbers can be passed as they are). Example: RAFT's
        KITTI padder takes 375×1242 to 376×1248 with (left, right, top, bottom) = (3, 3, 0, 1):
        ``camera.padded(3, 0, 3, 1)`` moves c_x by 3 px.
        """
        amounts = _pixel_amounts("padded", left=left, top=top, right=right, bottom=bottom)
        return self._shifted(amounts["left"], amounts["top"], "padded")

    def cropped(self, left: int, top: int, right: int = 0, bottom: int = 0) -> "Camera":
        """The camera for the image with ``left`` columns and ``top`` rows cut away at the left and
        top (``right``, ``bottom`` at the other sides), as ``image[..., top:H-bottom, left:W-right]``.

        The inverse of :meth:`padded`: ``c_x' = c_x - left``, ``c_y' = c_y - top``; the principal
        point may fall outside the crop (an off-centre crop), which is valid.
        """
        amounts = _pixel_amounts("cropped", left=left, top=top, right=right, bottom=bottom)
        return self._shifted(-amounts["left"], -amounts["top"], "cropped")

    def _shifted(self, du: int, dv: int, method: str) -> "Camera":
        if du == 0 and dv == 0:
            return self
        T = torch.tensor([[1.0, 0.0, float(du)], [0.0, 1.0, float(dv)], [0.0, 0.0, 1.0]],
                         dtype=self.dtype, device=self.device)
        with autocast_off(self.K):
            K = T @ self.K
        # the moved principal point must stay within the dtype's bounds (a shift of 1e39 px is
        # inf in float32, and K's product would hold NaN)
        try:
            check_finite(K, "K")
            _check_camera_values(K, self.height)
        except ValueError as err:
            raise ValueError(f"left, top: the camera {method} by ({abs(du)}, {abs(dv)}) px is out of range: "
                             f"{err}") from None
        return Camera._checked(K, self.height, self.roll, self.pitch)

    @classmethod
    def from_projection(cls, P: Tensor, height: Tensor | float, roll: Tensor | float = 0.0,
                        pitch: Tensor | float = 0.0) -> "Camera":
        """From a rectified 3×4 projection matrix (KITTI ``P_rect_0N`` / ``P0``): K = P[:, :3].

        A P whose first three columns are no valid K raises the constructor's error naming ``P``."""
        if not isinstance(P, Tensor):
            try:
                P = torch.as_tensor(P, dtype=torch.float64, device="cpu")  # (as a file's: not on the default device)
            except (TypeError, ValueError, RuntimeError):
                raise TypeError(f"P: expected a (3, 4) or (B, 3, 4) tensor or array of numbers, got "
                                f"{type(P).__name__} {P!r:.60}") from None
        if P.dim() not in (2, 3) or P.shape[-2:] != (3, 4):
            raise ValueError(f"P: expected shape (3, 4) or (B, 3, 4), got {tuple(P.shape)}")
        if not P.is_floating_point():
            raise TypeError(f"P: expected a floating-point tensor, got dtype {P.dtype}")
        try:
            return cls(P[..., :3].clone(), height, roll, pitch)
        except ValueError as err:
            if not str(err).startswith("K: "):
                raise
            raise ValueError(f"P: its first three columns are K, {str(err)[3:]}") from None

    @classmethod
    def from_kitti(cls, path: str | os.PathLike, cam: int = 2, height: float = 1.65,
                   roll: float = 0.0, pitch: float = 0.0, dtype: torch.dtype = torch.float64) -> "Camera":
        """From a KITTI calibration file: raw ``calib_cam_to_cam.txt`` (``P_rect_0{cam}``) or
        odometry ``calib.txt`` (``P{cam}``). The height is not in the file (KITTI: about 1.65 m).
        A half precision ``dtype`` gives a float32 camera, as the constructor does (the file's
        values are not rounded to half precision on the way); None is float64."""
        if dtype is not None and not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise TypeError(f"dtype: expected a floating-point torch.dtype (torch.float64, torch.float32), "
                            f"got {type(dtype).__name__} {dtype!r}")
        P = read_kitti_calibration(path, cam)
        if dtype in (torch.float16, torch.bfloat16):
            dtype = torch.float32
        return cls.from_projection(P if dtype is None else P.to(dtype), height, roll, pitch)


def check_camera(camera: object, name: str = "camera") -> "Camera":
    """``camera`` itself if it is a :class:`Camera`, else a TypeError naming the argument."""
    if not isinstance(camera, Camera):
        raise TypeError(f"{name}: expected a fsof_torch.Camera, got {type(camera).__name__}")
    return camera


def _pixel_amounts(method: str, **amounts: object) -> dict[str, int]:
    """Padding or cropping amounts as non-negative ints (a whole number of pixels)."""
    out = {}
    for name, value in amounts.items():
        value = scalar(value, name)  # (a 0-d integer tensor as its int, as Camera.scaled reads a 0-d tensor)
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise TypeError(f"{name}: expected a whole number of pixels (int) for Camera.{method}, "
                            f"got {type(value).__name__} {value!r}")
        value = int(value)
        if value < 0:
            raise ValueError(f"{name}: expected >= 0 pixels for Camera.{method}, got {value}")
        out[name] = value
    return out


_CALIBRATION_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_PROJECTION_KEY = re.compile(r"P(_rect_)?[0-9]+")  # the rows read_kitti_calibration reads


def split_calibration_line(line: str) -> tuple[str | None, str]:
    """``(key, values)`` of a KITTI calibration line, or ``(None, line)`` for an unlabelled row.

    Keys end in a colon (``P2: ...``, ``P_rect_02: ...``, ``calib_time: 09-Jan-2012 ...``), or,
    in KITTI tracking's ``calib/NNNN.txt``, a space (``R_rect 9.99e-01 ...``, ``Tr_velo_cam ...``):
    a first word that is a name, not a number. The line is stripped."""
    line = line.strip()
    key, sep, rest = line.partition(":")
    if sep:
        return key.strip(), rest
    first, *rest = line.split(None, 1)
    if _CALIBRATION_KEY.fullmatch(first) and first.lower() not in ("nan", "inf", "infinity"):
        return first, rest[0] if rest else ""
    return None, line


def read_kitti_calibration(path: str | os.PathLike, cam: int = 2) -> "torch.Tensor":
    """The 3×4 rectified projection matrix of camera ``cam`` from a KITTI calibration file.

    Reads ``calib_cam_to_cam.txt`` (key ``P_rect_0{cam}``) or the odometry ``calib.txt``
    (key ``P{cam}``, or, in a file without labelled ``P`` rows, unlabelled rows in order), and
    KITTI tracking's and object detection's ``calib`` files (``P{cam}:``; their other rows,
    ``R_rect`` / ``Tr_velo_cam`` keyed by a space rather than a colon, are not read:
    :func:`split_calibration_line`). Only the projection rows (``P_rect_0N``, ``PN``) are read:
    any other keyed row (``calib_time``, ``S_rect_02``, ``Tr``, a note of your own) is skipped,
    whatever it holds and however often it comes. A UTF-8 byte-order mark is skipped. Raises
    ValueError naming the path (and the row) for a missing or malformed projection row, one
    holding NaN or inf, one given twice, or both ``P_rect_0{cam}`` and ``P{cam}`` with different
    values (naming both lines).
    """
    path = existing_file(path, "calibration file")
    cam = check_camera_index(cam)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as err:
        raise ValueError(f"path: {str(path)!r} is not a text calibration file (undecodable byte at "
                         f"offset {err.start})") from None
    rows: dict[str, list[float]] = {}  # the projection rows, P_rect_0N or PN
    key_lines: dict[str, int] = {}
    unlabelled: list[list[float]] = []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line:
            continue
        key, rest = split_calibration_line(line)
        if key is not None and not _PROJECTION_KEY.fullmatch(key):
            continue  # another row (calib_time, R_rect_02, Tr, a note): not read, however often it comes
        if key in key_lines:  # which of the two rows would be the calibration?
            raise ValueError(f"path: line {n} of {str(path)!r} repeats the key {key!r} of line {key_lines[key]}; "
                             f"expected each projection row once")
        try:
            if key is not None:
                key_lines[key] = n
                rows[key] = [float(x) for x in rest.split()]
            else:
                unlabelled.append([float(x) for x in line.split()])
        except ValueError as err:
            raise ValueError(f"path: line {n} of {str(path)!r} is not a calibration row: {line[:60]!r}") from err
    labelled = bool(rows)
    rect, plain = f"P_rect_0{cam}", f"P{cam}"
    if rect in rows and plain in rows and rows[rect] != rows[plain]:  # which is the calibration?
        raise ValueError(f"path: {str(path)!r} gives camera {cam} twice, {rect} (line {key_lines[rect]}) and "
                         f"{plain} (line {key_lines[plain]}), with different values; expected one of them, "
                         f"or both the same")
    for key in (rect, plain):
        if key in rows:
            values = rows[key]
            row = key
            break
    else:
        # unlabelled rows count as P0, P1, ... only in a file that labels none of its P rows
        if cam < len(unlabelled) and not labelled:
            values = unlabelled[cam]
            row = f"unlabelled row {cam + 1}"
        else:
            count = len(unlabelled)
            raise ValueError(f"path: {str(path)!r} has no P_rect_0{cam} or P{cam} row"
                             + (" (its unlabelled rows are not counted: the file labels its P rows)"
                                if labelled and unlabelled else
                                f" (its {count} unlabelled row(s) are cameras 0 to {count - 1}, in order)"
                                if unlabelled else ""))
    if len(values) != 12:
        raise ValueError(f"path: the projection row of camera {cam} in {str(path)!r} has {len(values)} numbers, expected 12")
    if not all(math.isfinite(x) for x in values):
        raise ValueError(f"path: the {row} row of {str(path)!r} holds NaN or inf: {values}")
    return torch.tensor(values, dtype=torch.float64, device="cpu").reshape(3, 4)


def check_camera_index(cam: object, name: str = "cam") -> int:
    """A KITTI camera index: an int 0..3 (0/1 grey, 2/3 colour); a 0-d integer tensor is read as
    its int, as every whole-number option reads one (docs/reliability.md)."""
    cam = scalar(cam, name)
    if isinstance(cam, bool) or not isinstance(cam, numbers.Integral) or not 0 <= int(cam) <= 3:
        raise option_error(cam, f"{name}: expected 0..3, got {cam!r} (the KITTI camera index)", integer=True)
    return int(cam)


def _camera_flatten(cam: Camera):
    return [cam.K, cam.height, cam.roll, cam.pitch], None


def _camera_unflatten(values, _context) -> Camera:
    # Rebuild without validation: the leaves come from a Camera that was validated, and while
    # torch.export builds its inputs they are fake tensors whose values cannot be checked.
    cam = object.__new__(Camera)
    cam.K, cam.height, cam.roll, cam.pitch = values
    return cam


try:  # let torch.compile / torch.export see a Camera as a container of tensors
    torch.utils._pytree.register_pytree_node(
        Camera, _camera_flatten, _camera_unflatten,
        serialized_type_name="fsof_torch.camera.Camera",
        flatten_with_keys_fn=lambda cam: (
            [(torch.utils._pytree.GetAttrKey(k), getattr(cam, k)) for k in ("K", "height", "roll", "pitch")],
            None,
        ),
    )
except (ValueError, TypeError):  # pragma: no cover - already registered (module reloaded)
    pass
