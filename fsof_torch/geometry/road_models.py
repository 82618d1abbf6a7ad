"""The road's motion models: named parameters -> the road's 3×3 map between two frames.

Every model is defined once, here, as a map from its parameters to a matrix per frame; the flow,
every fit, the refiner and the loss terms derive what they need from that definition. The
derivatives of the map by the parameters are written beside it (analytic: rotations differentiate
through their generators) and tested against finite differences.

Frames (DESIGN.md §2, §10): pixels (u, v), u right, v down, origin at the centre of the top-left
pixel. The road-aligned vehicle frame of time t has x right, y down along the road's normal,
z forward, origin at the camera; the road is the plane y = h (h the camera height, known: only
d / h is observable from images). The camera sees ``p_cam = R_c p_vehicle`` with the camera's
attitude relative to the road ``R_c = R_roll(θ) R_pitch(β)`` (:func:`~fsof_torch.geometry.camera.
mounting_matrix`). Rotations about the vehicle's axes:

    R_roll(γ)  = [[cos γ, sin γ, 0], [-sin γ, cos γ, 0], [0, 0, 1]]     (about z)
    R_pitch(α) = [[1, 0, 0], [0, cos α, sin α], [0, -sin α, cos α]]     (about x; > 0 looks up)
    R_yaw(φ)   = [[cos φ, 0, -sin φ], [0, 1, 0], [sin φ, 0, cos φ]]     (about y; > 0 turns right)

A static road point moves into the vehicle frame of t+1 as ``p' = R_v (p - d)`` with
``R_v = R_roll(γ) R_pitch(α) R_yaw(φ)`` and ``d = (x_d, y_d, z_d)`` in metres; the camera stays
rigidly mounted. Every road pixel then moves by the plane-induced homography

    H = K R_c R_v (I - d e_yᵀ / h) R_cᵀ K⁻¹ = K (R + t nᵀ / h) K⁻¹,
    R = R_c R_v R_cᵀ,  t = -R_c R_v d,  n = R_c e_y,

and the flow of a pixel p is π(H p̃) - p. The models:

- ``"paper"``: the paper's displacement model (eq. 13): (x_d, z_d, yaw) with the camera's roll
  and pitch (the mounting), i.e. ``"plane"`` with no pitch or roll change and y_d = 0.
- ``"plane"``: the rigid 6-DOF motion of the vehicle over the road (pitch_change, yaw,
  roll_change in radians; x_d, y_d, z_d in metres) and the camera's roll and pitch relative to the
  road at t: 8 parameters, as many as a homography has.
- ``"homography"``: a general road homography, the unconstrained reference: the 8 entries
  ``h11 … h32`` of ``K⁻¹ H K − I`` (the calibrated homography minus the identity, its last entry
  held at 1), unitless. :func:`fsof_torch.decompose_homography` turns one into ``"plane"``
  parameters.
- ``"velocity"``: the paper's velocity model (eq. 21), the time derivative of the homography at
  Δt = 0 for a forward speed (m/s) and a yaw rate (rad/s), with the camera's roll and pitch:
  ``G = K R_c (φ̇ E_y - v e_z e_yᵀ / h) R_cᵀ K⁻¹`` (1/s), flow = ``(g_x - u g_z, g_y - v g_z)`` for
  ``g = G p̃``, in pixels per second.

Example:
    >>> cam = Camera(torch.tensor([[700., 0, 600], [0, 700, 180], [0, 0, 1]]), 1.65)
    >>> H = road_homography(cam, {"x_d": 0.0, "z_d": 1.2, "yaw": 0.0}, model="paper")
    >>> H.shape
    torch.Size([1, 3, 3])
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

import torch
from torch import Tensor

from .._check import (autocast_off, as_batch_param, check_all_finite, check_float_tensor, check_shape, resolve_batch,
                      result_dtype, skip_values, tracing)
from .camera import Camera, check_camera
from .egomotion import as_pose_4x4, check_invertible, check_motion_step, scalable_map

__all__ = ["RoadModel", "ROAD_MODELS", "get_road_model", "road_homography", "road_motion", "is_planar_odometry",
           "homography_values", "pack_params", "unpack_params", "rotation_angles", "plane_from_pose",
           "plane_from_homography"]


# -- rotations about the vehicle's axes, as constant bases -------------------------------------

# R(angle) = E0 + cos(angle) Ec + sin(angle) Es for a rotation about one axis, and its derivative
# is Es R = R Es (the axis's generator). Rows: roll (z), pitch (x), yaw (y).
_E0 = ((0, 0, 0, 0, 0, 0, 0, 0, 1), (1, 0, 0, 0, 0, 0, 0, 0, 0), (0, 0, 0, 0, 1, 0, 0, 0, 0))
_EC = ((1, 0, 0, 0, 1, 0, 0, 0, 0), (0, 0, 0, 0, 1, 0, 0, 0, 1), (1, 0, 0, 0, 0, 0, 0, 0, 1))
_ES = ((0, 1, 0, -1, 0, 0, 0, 0, 0), (0, 0, 0, 0, 0, 1, 0, -1, 0), (0, 0, -1, 0, 0, 0, 1, 0, 0))
_ROLL, _PITCH, _YAW = 0, 1, 2
_CACHE: dict = {}


def _constant(key: tuple, build: Callable[[], object]) -> object:
    """The constant ``build()`` of the maps, cached per ``key`` (which holds its dtype and device)
    in eager mode; built afresh while tracing (a constant of the graph).

    Built outside inference mode and autograd: a constant first made under
    ``torch.inference_mode`` would be an inference tensor, and autograd refuses to save one for
    backward in every later differentiable call."""
    if tracing():
        return build()
    out = _CACHE.get(key)
    if out is None:
        with torch.inference_mode(False), torch.no_grad():
            out = _CACHE[key] = build()
    return out


def _bases(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """(E0, Ec, Es), each (3, 3, 3) indexed by axis (roll, pitch, yaw); cached."""
    return _constant(("bases", dtype, device), lambda: tuple(
        torch.tensor(b, dtype=dtype, device=device).reshape(3, 3, 3) for b in (_E0, _EC, _ES)))


def _rotations(angles: Tensor, axes: tuple[int, ...]) -> Tensor:
    """Rotation matrices (B, A, 3, 3) for angles (B, A) about the given axes (one per column)."""
    E0, Ec, Es = _axis_bases(axes, angles.dtype, angles.device)
    a = angles.reshape(*angles.shape, 1, 1)
    return torch.addcmul(torch.addcmul(E0, torch.cos(a), Ec), torch.sin(a), Es)


def _axis_bases(axes: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """The bases (E0, Ec, Es) of :func:`_bases` for the given axes, each (A, 3, 3); cached (the
    map is evaluated every solver iteration: indexing them each time showed)."""
    return _constant((axes, dtype, device), lambda: tuple(b[list(axes)] for b in _bases(dtype, device)))


# Products of small matrices go through torch.bmm on (B, n, m) operands: the ``@`` of batched 3×3
# matrices costs several times the product itself in dispatch (broadcasting checks, reshapes), and
# the fits evaluate these maps every solver iteration (python benchmarks/bench_fit.py).

def _mm(a: Tensor, b: Tensor) -> Tensor:
    """a @ b for a (B, n, k) and b (B, k, m)."""
    return torch.bmm(a, b)


def _sandwich_operator(L: Tensor, R: Tensor) -> Tensor:
    """T (B, 9, 9) with vec(L X R) = T vec(X) (row-major vec) for L, R (B, 3, 3): the sandwich
    as one linear map of X's nine entries (T[3a + b, 3i + j] = L[a, i] R[j, b])."""
    B = L.shape[0]
    return (L.reshape(B, 3, 1, 3, 1) * R.transpose(1, 2).reshape(B, 1, 3, 1, 3)).reshape(B, 9, 9)


def _apply(T: Tensor, X: Tensor) -> Tensor:
    """The sandwich T of :func:`_sandwich_operator` applied to matrices X (B, Q, 3, 3)."""
    B, Q = X.shape[:2]
    return _mm(X.reshape(B, Q, 9), T.transpose(1, 2)).reshape(B, Q, 3, 3)


def _commutators(like: Tensor) -> Tensor:
    """(9, 27): vec(X) (row-major, as a row) times this gives vec([G, X]) = vec(G X - X G) for
    the generators G of the three axes (roll, pitch, yaw, in :data:`_ES`'s order); cached."""
    def build() -> Tensor:
        _, _, Es = _bases(like.dtype, like.device)
        eye = torch.eye(3, dtype=like.dtype, device=like.device)
        # vec(G X) = (G ⊗ I) vec(X), vec(X G) = (I ⊗ Gᵀ) vec(X)
        return torch.cat([(torch.kron(G, eye) - torch.kron(eye, G.T.contiguous())).T for G in Es], dim=1)

    return _constant(("commutators", like.dtype, like.device), build)


# -- the definitions ------------------------------------------------------------------------------
#
# The rigid models and the velocity model are a vehicle-frame map X of the motion, seen through
# the camera's attitude over the road: H = K R_c X R_cᵀ K⁻¹. Each model defines X and its
# derivatives by its motion parameters; :func:`_mounted` does the rest, including the derivatives
# by the roll θ and pitch β (d(R_c X R_cᵀ)/dangle = [G, R_c X R_cᵀ] with the angle's generator G).

def _mounted(K: Tensor, K_inv: Tensor, Rt: Tensor, Rb: Tensor, stack: Tensor,
             jacobian: bool) -> tuple[Tensor, Tensor | None, Tensor]:
    """H = K R_c X R_cᵀ K⁻¹ (B, 3, 3) with R_c = Rt Rb (the camera's roll and pitch rotations,
    (B, 3, 3) each), and the horizon row (R_c e_y)ᵀ K⁻¹ (B, 1, 3), from ``stack`` (B, 1 + Q, 3, 3):
    X, then (with ``jacobian``) its derivatives by the Q motion parameters; with ``jacobian``
    also dH (B, Q + 2, 3, 3) by (motion..., roll, pitch), else None.

    By roll and pitch: d(R_c X R_cᵀ) = R_c [G̃, X] R_cᵀ with the angle's generator seen in the
    road frame, G̃ = R_cᵀ G R_c: Rbᵀ G_z Rb for the roll and G_x itself for the pitch (a rotation
    commutes with its own generator). So every derivative goes through the one sandwich.
    """
    B = stack.shape[0]
    Rc = _mm(Rt, Rb)
    R = _mm(Rc.transpose(1, 2), K_inv)
    T, horizon = _sandwich_operator(_mm(K, Rc), R), R[:, 1:2]
    if jacobian:
        # [G_x, X], [G_y, X], [G_z, X] at once; the roll's G̃ = Rbᵀ G_z Rb = cos β G_z - sin β G_y
        comm = torch.mm(stack[:, 0].reshape(B, 9), _commutators(stack)).reshape(B, 3, 3, 3)
        cos_b, sin_b = Rb[:, None, 2:3, 2:3], Rb[:, None, 1:2, 2:3]
        roll = comm[:, _ROLL:_ROLL + 1] * cos_b - comm[:, _YAW:_YAW + 1] * sin_b
        stack = torch.cat([stack, roll, comm[:, _PITCH:_PITCH + 1]], dim=1)
    HdH = _apply(T, stack)
    return HdH[:, 0], (HdH[:, 1:] if jacobian else None), horizon


def _mounting_rotations(values: Tensor, motion: tuple[int, ...], axes: tuple[int, ...],
                        roll: int) -> tuple[list[Tensor], Tensor, Tensor]:
    """The rotations of a model's motion angles (columns ``motion`` about ``axes``) and of the
    camera's roll and pitch (columns ``roll``, ``roll + 1``): one batch of rotation matrices."""
    cols = list(motion) + [roll, roll + 1]
    # (a slice where the columns follow each other: cheaper than gathering them; else a cached
    # index: indexing by a list builds one at every call)
    if cols == list(range(cols[0], cols[-1] + 1)):
        angles = values[:, cols[0]:cols[-1] + 1]
    else:
        index = _constant(("columns", tuple(cols), values.device),
                          lambda: torch.tensor(cols, dtype=torch.long, device=values.device))
        angles = values.index_select(1, index)
    Rs = _rotations(angles, axes + (_ROLL, _PITCH)).unbind(1)
    return list(Rs[:-2]), Rs[-2], Rs[-1]


def _unit_y(like: Tensor) -> Tensor:
    """e_y (3,) in ``like``'s dtype and device; cached."""
    return _constant(("e_y", like.dtype, like.device), lambda: _unit_matrix(1, 1, like)[1])


def _unit_matrix(i: int, j: int, like: Tensor) -> Tensor:
    """e_i e_jᵀ (3, 3) in ``like``'s dtype and device; cached."""
    def build() -> Tensor:
        out = torch.zeros(3, 3, dtype=like.dtype, device=like.device)
        out[i, j] = 1.0
        return out

    return _constant(("unit", i, j, like.dtype, like.device), build)


def _rigid(K: Tensor, K_inv: Tensor, h: Tensor, values: Tensor, jacobian: bool):
    """The ``"plane"`` map: values (B, 8) = (pitch_change α, yaw φ, roll_change γ, x_d, y_d, z_d,
    roll θ, pitch β); X = R_v (I - d e_yᵀ / h), R_v = R_roll(γ) R_pitch(α) R_yaw(φ)."""
    B = values.shape[0]
    (Rg, Ra, Rp), Rt, Rb = _mounting_rotations(values, (2, 0, 1), (_ROLL, _PITCH, _YAW), 6)
    Rga = _mm(Rg, Ra)
    Rv = _mm(Rga, Rp)
    # only the middle column changes, by -R_v d / h
    ey = _unit_y(values)
    shift = _mm(Rv, (values[:, 3:6] / h.unsqueeze(-1)).unsqueeze(-1))
    X = Rv - shift * ey
    stack = X.unsqueeze(1)
    if jacobian:
        # (the generators of pitch, yaw and roll, (B, 3, 3) each; cached per batch size)
        Gp, Gy, Gr = _constant(("generators", B, values.dtype, values.device), lambda: tuple(
            _bases(values.dtype, values.device)[2][i].expand(B, 3, 3) for i in (_PITCH, _YAW, _ROLL)))
        # d R_v / d angle = G_left R_v: roll outermost, pitch seen through the roll, yaw through both
        G_left = torch.stack([_mm(_mm(Rg, Gp), Rg.transpose(1, 2)), _mm(_mm(Rga, Gy), Rga.transpose(1, 2)), Gr], dim=1)
        dX_angles = _mm(G_left.reshape(B, 9, 3), X).reshape(B, 3, 3, 3)
        dX_d = -(Rv.transpose(1, 2) / h.reshape(B, 1, 1)).unsqueeze(-1) * ey  # column 1: -R_v e_k / h
        stack = torch.cat([stack, dX_angles, dX_d], dim=1)
    return _mounted(K, K_inv, Rt, Rb, stack, jacobian)


# The paper's X and its derivatives by (x_d, z_d, φ) are linear in nine monomials of its motion,
# (1, c, s, c a, c b, c / h, s a, s b, s / h) with c, s = cos φ, sin φ and a, b = x_d / h, z_d / h:
#
#   X       = [[c, -(c a - s b), -s], [0, 1, 0], [s, -(s a + c b), c]]
#   dX/dx_d = [[0, -c / h, 0], [0, 0, 0], [0, -s / h, 0]]
#   dX/dz_d = [[0, s / h, 0], [0, 0, 0], [0, -c / h, 0]]
#   dX/dφ   = G_y X = [[-s, s a + c b, -c], [0, 0, 0], [c, -(c a - s b), -s]]
#
# so the four maps are one product of the monomials with a constant basis (the fits evaluate them
# every solver iteration; python benchmarks/bench_fit.py: building them matrix by matrix took a
# third of the refinement step's fit).
_PAPER_MONOMIALS = ("1", "c", "s", "ca", "cb", "c/h", "sa", "sb", "s/h")
_PAPER_MAPS = (  # {entry (row-major) of [X, dX/dx_d, dX/dz_d, dX/dφ]: {monomial: coefficient}}
    {0: {"c": 1}, 1: {"ca": -1, "sb": 1}, 2: {"s": -1}, 4: {"1": 1}, 6: {"s": 1}, 7: {"sa": -1, "cb": -1},
     8: {"c": 1}},
    {1: {"c/h": -1}, 7: {"s/h": -1}},
    {1: {"s/h": 1}, 7: {"c/h": -1}},
    {0: {"s": -1}, 1: {"sa": 1, "cb": 1}, 2: {"c": -1}, 6: {"c": 1}, 7: {"ca": -1, "sb": 1}, 8: {"s": -1}},
)


def _coefficients(monomials: tuple[str, ...], maps: tuple[dict, ...]) -> list[list[float]]:
    """(monomials, 9 · maps) coefficients of :data:`_PAPER_MAPS`-like tables, as nested lists."""
    table = [[0.0] * (9 * len(maps)) for _ in monomials]
    for k, entries in enumerate(maps):
        for entry, coefficients in entries.items():
            for monomial, c in coefficients.items():
                table[monomials.index(monomial)][9 * k + entry] = float(c)
    return table


_PAPER_BASIS = _coefficients(_PAPER_MONOMIALS, _PAPER_MAPS)


def _paper_basis(dtype: torch.dtype, device: torch.device) -> Tensor:
    """(9, 36): the maps [X, dX/dx_d, dX/dz_d, dX/dφ] (row-major) from the monomials above; cached."""
    return _constant(("paper", dtype, device), lambda: torch.tensor(_PAPER_BASIS, dtype=dtype, device=device))


def _paper(K: Tensor, K_inv: Tensor, h: Tensor, values: Tensor, jacobian: bool):
    """The ``"paper"`` map: values (B, 5) = (x_d, z_d, yaw, roll, pitch); X = R_yaw(φ) (I - d e_yᵀ / h)
    with d = (x_d, 0, z_d): the ``"plane"`` map with no pitch or roll change and y_d = 0."""
    B = values.shape[0]
    _, Rt, Rb = _mounting_rotations(values, (), (), 3)
    yaw = values[:, 2:3]
    one = torch.ones_like(yaw)
    cs = torch.cat([torch.cos(yaw), torch.sin(yaw)], dim=-1)                   # (c, s)
    lin = torch.cat([values[:, :2], one], dim=-1) / h.unsqueeze(-1)             # (a, b, 1 / h)
    monomials = torch.cat([one, cs, (cs.unsqueeze(-1) * lin.unsqueeze(1)).reshape(B, 6)], dim=-1)
    basis = _paper_basis(values.dtype, values.device)
    stack = torch.mm(monomials, basis if jacobian else basis[:, :9]).reshape(B, -1, 3, 3)
    return _mounted(K, K_inv, Rt, Rb, stack, jacobian)


def _velocity(K: Tensor, K_inv: Tensor, h: Tensor, values: Tensor, jacobian: bool):
    """The ``"velocity"`` map G (1/s): values (B, 4) = (speed, yaw_rate, roll, pitch);
    X = d/dt [R_yaw(φ̇ t) (I - (0, 0, v t) e_yᵀ / h)] at t = 0 = φ̇ G_y - v e_z e_yᵀ / h."""
    B = values.shape[0]
    _, Rt, Rb = _mounting_rotations(values, (), (), 2)
    _, _, Es = _bases(values.dtype, values.device)
    # d X / d speed = -e_z e_yᵀ / h, d X / d yaw_rate = G_y: constant in the motion
    dX_speed = _unit_matrix(2, 1, values) * (-1.0 / h).reshape(B, 1, 1)
    Gy = Es[_YAW].expand(B, 3, 3)
    X = values[:, 0].reshape(B, 1, 1) * dX_speed + values[:, 1].reshape(B, 1, 1) * Gy
    stack = torch.stack([X, dX_speed, Gy], dim=1) if jacobian else X.unsqueeze(1)
    return _mounted(K, K_inv, Rt, Rb, stack, jacobian)


def _homography(K: Tensor, K_inv: Tensor, h: Tensor, values: Tensor, jacobian: bool):
    """The ``"homography"`` map: values (B, 8), the entries of K⁻¹ H K − I (its last entry 0)."""
    B = values.shape[0]
    G = torch.eye(3, dtype=values.dtype, device=values.device) + torch.cat(
        [values, torch.zeros_like(values[:, :1])], dim=-1).reshape(B, 3, 3)
    T = _sandwich_operator(K, K_inv)
    H = _apply(T, G.unsqueeze(1))[:, 0]
    if not jacobian:
        return H, None, None
    # H is linear in the values: its derivatives are T's first eight columns
    return H, T[:, :, :8].transpose(1, 2).reshape(B, 8, 3, 3), None


@dataclass(frozen=True)
class RoadModel:
    """A road-motion model: its parameter names and units, and its map.

    Attributes:
        name: ``"paper"``, ``"plane"``, ``"homography"`` or ``"velocity"``.
        params: the parameter names, in the order of the columns of a (B, P) value tensor.
        units: the unit of each parameter (``"m"``, ``"rad"``, ``"m/s"``, ``"rad/s"``, ``"1"``).
        mounting: the parameters that are the camera's roll and pitch relative to the road
            (taken from the :class:`Camera` when not given).
        velocity: True when the map is a time derivative G (flow = (g_x - u g_z, g_y - v g_z) in
            px/s), False for a homography (flow = π(H p̃) - p in px).
    """

    name: str
    params: tuple[str, ...]
    units: tuple[str, ...]
    mounting: tuple[str, ...]
    velocity: bool
    _fn: object = field(repr=False)

    def matrix(self, camera: Camera, values: Tensor) -> Tensor:
        """The map (B, 3, 3) for values (B, P) (columns in ``params`` order; camera and values of
        batch 1 or B), in their promoted dtype, half precision lifted to float32. Types and shapes
        are checked, not the values (the fits' loops must not wait for host reads): NaN in, NaN out."""
        return self.evaluate(*self._inputs(camera, values), False)[0]

    def matrix_and_jacobian(self, camera: Camera, values: Tensor) -> tuple[Tensor, Tensor]:
        """The map (B, 3, 3) and its derivatives by the parameters (B, P, 3, 3), as :meth:`matrix`."""
        return self.evaluate(*self._inputs(camera, values), True)[:2]

    def _inputs(self, camera: Camera, values: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """K, K⁻¹, height and values (B, P) of one batch and float dtype (no value read)."""
        check_camera(camera)
        check_shape(check_float_tensor(values, "values"), "values", ("B", len(self.params)))
        B = resolve_batch({"camera": camera.batch_size, "values": values.shape[0]})
        dtype = result_dtype(camera.K, values)
        camera = (camera.to(dtype) if camera.dtype != dtype else camera).expand(B)  # (a cast: nothing read)
        return camera.K, camera.K_inv(), camera.height, values.to(dtype).expand(B, -1)

    def evaluate(self, K: Tensor, K_inv: Tensor, height: Tensor, values: Tensor,
                 jacobian: bool) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """The map, its derivatives (with ``jacobian``) and the horizon row (:meth:`horizon_row`;
        None for a model without a mounting) from the camera's K (B, 3, 3), K⁻¹ and height (B,),
        for loops that evaluate the map many times with one camera.

        In the dtype of the values and the camera (as :meth:`matrix` and
        :meth:`matrix_and_jacobian`), also under ``torch.autocast``."""
        with autocast_off(values):
            return self._fn(K, K_inv, height, values, jacobian)

    def horizon_row(self, camera: Camera, values: Tensor) -> Tensor:
        """The row a (B, 1, 3) with ``a · p̃ > 0`` for pixels whose ray meets the road in front of
        the camera at t: ``a = (R_c e_y)ᵀ K⁻¹`` with the camera's roll and pitch relative to the
        road (the model's own where it has them, else the camera's)."""
        if self.mounting:
            i, j = (self.params.index(n) for n in self.mounting)
            roll, pitch = values[:, i], values[:, j]
        else:
            roll, pitch = camera.roll.to(values), camera.pitch.to(values)
        with autocast_off(values):
            Rt, Rb = _rotations(torch.stack([roll, pitch], dim=-1), (_ROLL, _PITCH)).unbind(1)
            n = (Rt @ Rb)[:, :, 1:2]  # the road's normal in the camera frame (pointing down)
            return n.transpose(-1, -2) @ camera.K_inv().to(values)

    def index(self, name: str) -> int:
        """The column of parameter ``name`` in a (B, P) value tensor (ValueError for another name)."""
        return self.params.index(name)


ROAD_MODELS: dict[str, RoadModel] = {
    "paper": RoadModel("paper", ("x_d", "z_d", "yaw", "roll", "pitch"), ("m", "m", "rad", "rad", "rad"),
                       ("roll", "pitch"), False, _paper),
    "plane": RoadModel("plane", ("pitch_change", "yaw", "roll_change", "x_d", "y_d", "z_d", "roll", "pitch"),
                       ("rad", "rad", "rad", "m", "m", "m", "rad", "rad"), ("roll", "pitch"), False, _rigid),
    "homography": RoadModel("homography", ("h11", "h12", "h13", "h21", "h22", "h23", "h31", "h32"),
                            ("1",) * 8, (), False, _homography),
    "velocity": RoadModel("velocity", ("speed", "yaw_rate", "roll", "pitch"), ("m/s", "rad/s", "rad", "rad"),
                          ("roll", "pitch"), True, _velocity),
}


def get_road_model(model: str | RoadModel, name: str = "model") -> RoadModel:
    """The :class:`RoadModel` of a name in :data:`ROAD_MODELS` (or the model itself); the error names ``name``."""
    if isinstance(model, RoadModel):
        return model
    if not isinstance(model, str) or model not in ROAD_MODELS:
        raise (ValueError if isinstance(model, str) else TypeError)(
            f"{name}: expected one of {tuple(ROAD_MODELS)}, got {model!r}")
    return ROAD_MODELS[model]


# -- named parameters <-> value tensors ------------------------------------------------------------

def pack_params(model: str | RoadModel, camera: Camera, params: Mapping[str, Tensor | float] | None,
                ) -> tuple[Camera, Tensor]:
    """Named parameters -> ``(camera, values (B, P))`` in one float dtype (half lifted to float32).

    Missing motion parameters are 0 (no motion); missing mounting parameters are the camera's
    roll and pitch. Python floats and (B,) tensors broadcast against the camera's batch; the
    camera comes back cast and expanded to the common dtype and batch.
    """
    model = get_road_model(model)
    check_camera(camera)
    params = {} if params is None else params
    if not isinstance(params, Mapping):
        raise TypeError(f"params: expected a dict of {model.params}, got {type(params).__name__}")
    unknown = sorted(set(params) - set(model.params))
    if unknown:
        raise ValueError(f"params: unknown names {unknown} for model {model.name!r}; expected some of {model.params}")
    tensors = [as_batch_param(v, n, finite=False) for n, v in params.items() if isinstance(v, Tensor)]
    dtype = result_dtype(camera.K, *tensors)
    # Python floats go straight to the common dtype (no float32 round trip)
    given = {n: as_batch_param(v, n, dtype, camera.device, finite=False) for n, v in params.items()}
    check_all_finite(given)
    B = resolve_batch({"camera": camera.batch_size, **{n: t.shape[0] for n, t in given.items()}})
    camera = camera.to(dtype).expand(B) if camera.dtype != dtype else camera.expand(B)
    mount = {"roll": camera.roll, "pitch": camera.pitch}
    cols = []
    for name in model.params:
        if name in given:
            cols.append(given[name].expand(B))
        elif name in model.mounting:
            cols.append(mount[name])
        else:
            cols.append(torch.zeros(B, dtype=dtype, device=camera.device))
    return camera, torch.stack(cols, dim=-1)


def unpack_params(model: str | RoadModel, values: Tensor) -> dict[str, Tensor]:
    """Values (B, P) -> ``{name: (B,)}``; values of another P are a ValueError naming ``values``."""
    model = get_road_model(model)
    if not isinstance(values, Tensor):
        raise TypeError(f"values: expected a (B, {len(model.params)}) tensor, got {type(values).__name__}")
    check_shape(values, "values", ("B", len(model.params)))  # (not a column dropped or an IndexError)
    return {n: values[:, i] for i, n in enumerate(model.params)}


def road_homography(camera: Camera, params: Mapping[str, Tensor | float] | None = None, *,
                    model: str | RoadModel = "paper") -> Tensor:
    """The road's map (B, 3, 3) under a model's named parameters: pixels of t -> t+1.

    Args:
        camera: intrinsics (K at the flow's resolution), height and mounting; batch 1 or B.
        params: the model's parameters (floats or (B,) tensors; see :data:`ROAD_MODELS` for names
            and units); missing motion parameters are 0, missing roll / pitch the camera's.
        model: ``"paper"``, ``"plane"``, ``"homography"`` or ``"velocity"`` (whose map is the time
            derivative G, in 1/s).

    Returns:
        (B, 3, 3) in the common dtype of the camera and the parameters (at least float32).
    """
    model = get_road_model(model)
    check_camera(camera)
    with autocast_off(camera.K):
        camera, values = pack_params(model, camera, params)
        return model.matrix(camera, values)


# -- from other descriptions of the motion ---------------------------------------------------------

def road_motion(odometry: object, name: str = "odometry", *,
                displacement: bool = False) -> tuple[RoadModel, dict[str, object]]:
    """``(model, params)`` of a road motion given in any of the forms the library takes:

    - a dict of the paper's ``x_d``, ``z_d`` (metres) and ``yaw`` (radians);
    - a dict with a ``"model"`` key and that model's parameters (``{"model": "plane", "z_d":
      1.2, "pitch_change": 0.002}``; missing ones are 0, missing roll / pitch the camera's);
    - a fit result or anything with ``model`` and ``params`` attributes
      (:class:`~fsof_torch.estimation.flow_fit.RoadFit`);
    - an object with ``x_d``, ``z_d`` and ``yaw`` attributes (:class:`~fsof_torch.geometry.egomotion.EgoMotion`).

    With ``displacement`` (a caller whose flow is pixels per frame: the freespace loss, the
    refiner) the ``"velocity"`` model, whose flow is in px/s, raises a ValueError naming ``name``.
    """
    if isinstance(odometry, Mapping):
        if "model" in odometry:
            model = get_road_model(odometry["model"], f"{name}['model']")
            params = {k: v for k, v in odometry.items() if k != "model"}
        else:
            model = ROAD_MODELS["paper"]
            missing = [k for k in ("x_d", "z_d", "yaw") if k not in odometry]
            if missing:
                rate = "; a speed and a yaw rate are a rate: integrate them over the frame interval " \
                    "(fs.ego_motion_from_ackermann)" if set(odometry) & {"speed", "yaw_rate", "steering"} else ""
                raise ValueError(f"{name}: missing keys {missing}; expected a dict with x_d, z_d (metres) and yaw "
                                 f"(radians), or a 'model' key and that model's parameters; got keys {sorted(odometry)}{rate}")
            params = dict(odometry)
    elif hasattr(odometry, "model") and hasattr(odometry, "params"):
        model, params = get_road_model(odometry.model, f"{name}.model"), dict(odometry.params)
    elif all(hasattr(odometry, k) for k in ("x_d", "z_d", "yaw")):
        model = ROAD_MODELS["paper"]
        params = {k: getattr(odometry, k) for k in ("x_d", "z_d", "yaw")}
    else:
        raise TypeError(f"{name}: expected a dict of x_d, z_d, yaw (or with a 'model' key), a fit result or an "
                        f"EgoMotion, got {type(odometry).__name__}")
    if displacement and model.velocity:
        raise ValueError(f"{name}: the {model.name!r} model gives flow in px/s, not the pixels per frame this "
                         f"needs; give the motion over the frame interval in a displacement model ('paper', 'plane' "
                         f"or 'homography')")
    unknown = sorted(set(params) - set(model.params))
    if unknown:
        raise ValueError(f"{name}: unknown parameters {unknown} of model {model.name!r}; expected some of {model.params}")
    return model, params


def is_planar_odometry(odometry: object) -> bool:
    """Whether ``odometry`` is planar odometry, the paper's ``x_d``, ``z_d`` and ``yaw`` alone (a dict
    of those keys, or an :class:`~fsof_torch.geometry.egomotion.EgoMotion`), which the refiner with
    images completes from them, rather than a complete road model's motion (a dict with ``"model"``,
    also ``"paper"``; the paper's dict with its ``roll`` or ``pitch``; a fit result), used as it is."""
    if isinstance(odometry, Mapping):
        return "model" not in odometry and not {"roll", "pitch"} & set(odometry)
    return not (hasattr(odometry, "model") and hasattr(odometry, "params"))


def road_motion_batch(odometry: object, batch: int, dtype: torch.dtype, device: torch.device | str, *,
                      name: str = "odometry", batch_of: str = "the flow's batch",
                      displacement: bool = False) -> tuple[RoadModel, dict[str, Tensor]]:
    """:func:`road_motion`'s ``(model, params)`` with every parameter a tensor of shape
    (``batch``,) of ``dtype`` on ``device`` (a float or a batch of 1 broadcast); ``batch_of`` names
    the batch in the error a wrong batch size raises; ``displacement`` as in :func:`road_motion`,
    and a translation longer than 100 m a frame (odometry in millimetres) or a yaw of half a turn
    (degrees) a ValueError naming ``name`` (:func:`~fsof_torch.geometry.egomotion.check_motion_step`),
    except in a fit result (an estimate, whose ``success`` judges it, not a measurement in other units)."""
    model, params = road_motion(odometry, name, displacement=displacement)
    out = {}
    for key, value in params.items():
        t = as_batch_param(value, f"{name}[{key!r}]", dtype, device, finite=False)  # (a float: exact in dtype)
        if t.shape[0] not in (1, batch):
            shapes = "(1,)" if batch == 1 else f"(1,) or ({batch},)"
            raise ValueError(f"{name}[{key!r}]: expected a float or a tensor of shape {shapes} ({batch_of}), got "
                             f"shape {tuple(t.shape)}")
        out[key] = t.expand(batch)
    # one finiteness check for all (in the dtype they are used in: a value it cannot hold fails)
    check_all_finite({f"{name}[{key!r}]": t for key, t in out.items()})
    if displacement and not hasattr(odometry, "params"):  # (a measurement in mm or degrees, not a fit's estimate)
        check_motion_step(out, name)
    return model, out


def rotation_angles(R: Tensor) -> Tensor:
    """(pitch_change α, yaw φ, roll_change γ) (..., 3), in R's dtype, of rotations R (..., 3, 3),
    float (else a TypeError or ValueError names ``R``), R = R_roll(γ) R_pitch(α) R_yaw(φ). The row
    z of that product is (cos α sin φ, -sin α, cos α cos φ) and its column y is (sin γ cos α,
    cos γ cos α, -sin α): the angles follow with atan2 (|α| < π/2)."""
    if check_float_tensor(R, "R").dim() < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R: expected rotation matrices of shape (..., 3, 3), got {tuple(R.shape)}")
    alpha = torch.atan2(-R[..., 2, 1], torch.hypot(R[..., 2, 0], R[..., 2, 2]))
    phi = torch.atan2(R[..., 2, 0], R[..., 2, 2])
    gamma = torch.atan2(R[..., 0, 1], R[..., 1, 1])
    return torch.stack([alpha, phi, gamma], dim=-1)


def plane_from_pose(cam1_T_cam0: Tensor, camera: Camera) -> dict[str, Tensor]:
    """The ``"plane"`` parameters of a relative camera pose, with the camera's roll and pitch
    relative to the road (and its height) taken from ``camera``.

    Args:
        cam1_T_cam0: (B, 4, 4) or (B, 3, 4): camera-t coordinates to camera-(t+1) coordinates
            (KITTI: ``inverse(P_{t+1}) @ P_t`` for camera-to-world poses), metres.
        camera: the camera's attitude over the road at t (roll, pitch) and its height.

    Returns:
        ``{"pitch_change", "yaw", "roll_change", "x_d", "y_d", "z_d", "roll", "pitch"}`` of (B,):
        R_v = R_cᵀ R R_c and d = -R_vᵀ R_cᵀ t (DESIGN.md §10).
    """
    check_camera(camera)
    T = as_pose_4x4(cam1_T_cam0, "cam1_T_cam0")
    B = resolve_batch({"cam1_T_cam0": T.shape[0], "camera": camera.batch_size})
    with autocast_off(T):  # (geometry in at least float32, also under autocast)
        T = T.expand(B, 4, 4).to(result_dtype(T))
        cam = camera.to(device=T.device, dtype=T.dtype).expand(B)  # (the camera follows the pose)
        Rc = _rotations(torch.stack([cam.roll, cam.pitch], dim=-1), (_ROLL, _PITCH))
        Rc = Rc[:, 0] @ Rc[:, 1]
        return _plane_params(T[:, :3, :3], T[:, :3, 3:], Rc, cam)


def _plane_params(R: Tensor, t: Tensor, Rc: Tensor, cam: Camera) -> dict[str, Tensor]:
    """``"plane"`` parameters of X' = R X + t (B, 3, 3), (B, 3, 1) seen from ``cam``'s attitude R_c
    (R_v = R_cᵀ R R_c, d = -R_vᵀ R_cᵀ t); its roll and pitch copied, not the caller's tensors."""
    Rv = Rc.transpose(-1, -2) @ R @ Rc
    a, d = rotation_angles(Rv), -(Rv.transpose(-1, -2) @ Rc.transpose(-1, -2) @ t).squeeze(-1)
    return {"pitch_change": a[:, 0], "yaw": a[:, 1], "roll_change": a[:, 2], "x_d": d[:, 0], "y_d": d[:, 1],
            "z_d": d[:, 2], "roll": cam.roll.clone(), "pitch": cam.pitch.clone()}


def homography_values(H: Tensor, K: Tensor, K_inv: Tensor) -> Tensor:
    """The ``"homography"`` model's values (B, 8) of road maps H (B, 3, 3), the inverse of its map:
    the entries of K⁻¹ H K, scaled to a last entry of 1, minus the identity (in the promoted dtype
    of the three, half precision lifted to float32, also under ``torch.autocast``). H, K, K⁻¹ are
    float (B, 3, 3), batch 1 or B each (else a TypeError or ValueError names the argument). A
    finite map whose K⁻¹ H K has a last entry of 0 (up to rounding, or too small to scale to 1 in
    the dtype), which the model cannot express, is a ValueError naming ``H`` (one host read)."""
    resolve_batch({n: check_shape(check_float_tensor(M, n), n, ("B", 3, 3))["B"]
                   for n, M in (("H", H), ("K", K), ("K_inv", K_inv))})
    dtype = result_dtype(H, K, K_inv)
    with autocast_off(H):
        G = K_inv.to(dtype) @ H.to(dtype) @ K.to(dtype)
        out = (G / G[:, 2:3, 2:3] - torch.eye(3, dtype=G.dtype, device=G.device)).reshape(-1, 9)[:, :8]
    if not skip_values(out):
        bad = torch.isfinite(G).flatten(1).all(1) & ~scalable_map(G)  # (NaN in: NaN out, as before)
        if bool(bad.any()):
            i = bad.nonzero().flatten().tolist()
            raise ValueError(f"H: samples {i} have K⁻¹ H K with a last entry of {float(G[i[0], 2, 2]):.3g}, "
                             f"which the 'homography' model (that entry scaled to 1) cannot express; "
                             f"K⁻¹ H K = {G[i[0]].tolist()}")
    return out


def plane_from_homography(H: Tensor, camera: Camera) -> dict[str, Tensor]:
    """``"plane"`` parameters of road homographies (B, 3, 3) with the road's normal taken from the
    camera's roll and pitch: exact when that is the true attitude, a close start otherwise.

    With n known, ``G = K⁻¹ H K = λ (R + t nᵀ / h)`` maps the two directions m ⟂ n by λ R alone:
    λ is their stretch (its sign that of det G), R the rotation closest to what it does to them
    (Procrustes, by :func:`_nearest_rotation`), and t = h (G n / λ − R n).
    :func:`fsof_torch.decompose_homography` refines this start by a fit that frees the normal too.

    H may have any scale and sign but must be invertible (a ValueError names the samples that
    are not, or are too close to singular for the dtype). The result is differentiable in H and in the camera's tensors, and on H's device
    (the camera's tensors are moved there).
    """
    check_camera(camera)
    if not isinstance(H, Tensor) or not H.is_floating_point() or H.dim() != 3 or tuple(H.shape[1:]) != (3, 3):
        got = f"{H.dtype} {tuple(H.shape)}" if isinstance(H, Tensor) else type(H).__name__
        raise ValueError(f"H: expected a float tensor of shape (B, 3, 3), got {got}")
    check_all_finite({"H": H})
    B = resolve_batch({"H": H.shape[0], "camera": camera.batch_size})
    check_invertible(H, "H")
    with autocast_off(H):  # (geometry in at least float32, also under autocast; det has no bfloat16)
        out = _plane_from_homography(H.to(result_dtype(H)), camera, B)
    if not skip_values(H):
        finite = torch.isfinite(torch.stack(list(out.values()), dim=-1)).all(-1)
        if not bool(finite.all()):
            bad = (~finite).nonzero().flatten().tolist()
            raise ValueError(f"H: samples {bad} are too close to singular to decompose in {out['z_d'].dtype}, "
                             f"e.g. {H[bad[0]].tolist()}")
    return out


def _nearest_rotation(M: Tensor) -> Tensor:
    """The rotation closest to M (B, 3, 3) with det M > 0 (Frobenius norm; M's polar factor),
    by the scaled Newton iteration X <- (γ X + (γ X)⁻ᵀ) / 2 (Higham, *Functions of Matrices*,
    §8.6): quadratic near a rotation, which an exact road homography gives at once.

    Differentiable throughout (unlike an SVD, whose backward divides by differences of the
    singular values: NaN for M a rotation, where all three are 1, and inaccurate near one). The
    inverse transpose is the cofactor matrix over the determinant (cross products of columns).
    A fixed count of iterations, with no host read, in float64 whatever M's dtype (the result in
    M's): 12 agree with the SVD's polar factor to 1e-12 for condition numbers up to 1e8 (tested),
    far beyond the near-rotations road homographies give; towards 1e12 the cofactors lose the
    small singular directions."""
    X = M.to(torch.float64)
    for _ in range(12):
        c0, c1, c2 = X.unbind(-1)
        cof = torch.stack([torch.linalg.cross(c1, c2, dim=-1), torch.linalg.cross(c2, c0, dim=-1),
                           torch.linalg.cross(c0, c1, dim=-1)], dim=-1)
        det = (c0 * cof[..., 0]).sum(-1).reshape(-1, 1, 1)
        inv_t = cof / det
        gamma = (inv_t.square().sum((-2, -1), keepdim=True) / X.square().sum((-2, -1), keepdim=True)).sqrt().sqrt()
        X = 0.5 * (gamma * X + inv_t / gamma)
    return X.to(M.dtype)


def _plane_from_homography(H: Tensor, camera: Camera, B: int) -> dict[str, Tensor]:
    cam = camera.to(device=H.device, dtype=H.dtype).expand(B)  # (the camera follows H)
    H = H / H.abs().amax(dim=(-2, -1), keepdim=True)  # (any scale: det G must not underflow)
    G = cam.K_inv() @ H.expand(B, 3, 3) @ cam.K
    Rt, Rb = _rotations(torch.stack([cam.roll, cam.pitch], dim=-1), (_ROLL, _PITCH)).unbind(1)
    Rc = Rt @ Rb
    m1, n, m2 = Rc[:, :, 0:1], Rc[:, :, 1:2], Rc[:, :, 2:3]
    a1, a2 = G @ m1, G @ m2
    lam = 0.5 * (a1.norm(dim=1) + a2.norm(dim=1)) * torch.sign(torch.linalg.det(G)).unsqueeze(-1)  # (B, 1)
    r1, r2 = a1 / lam.unsqueeze(-1), a2 / lam.unsqueeze(-1)
    # R R_c maps (m1, n, m2), the columns of R_c (m2 × m1 = n), to (r1, r2 × r1, r2); that target
    # has det |r1|² |r2|² - (r1 · r2)² > 0 (r1, r2 independent for an invertible G)
    target = torch.cat([r1, torch.linalg.cross(r2, r1, dim=1), r2], dim=2)
    R = _nearest_rotation(target @ Rc.transpose(-1, -2))
    t = cam.height.reshape(B, 1, 1) * ((G @ n) / lam.unsqueeze(-1) - R @ n)
    return _plane_params(R, t, Rc, cam)
