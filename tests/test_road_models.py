"""Tests of fsof_torch.geometry.road_models and road_flow for every road model.

Independent references, written here in NumPy float64:
- the plane-induced homography H = K (R + t nᵀ / h) K⁻¹ of a rigid camera motion over the road
  plane nᵀX = h, with R, t, n built from the model's definition (DESIGN.md §10);
- a ray cast: intersect each pixel's ray with the plane, move the point rigidly, project;
- the paper's λ formula (eq. 13) for the "paper" model.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fsof_torch import Camera, decompose_homography
from fsof_torch.geometry.road_flow import RoadFlow, displacement_flow, road_flow
from fsof_torch.geometry.road_models import (
    ROAD_MODELS,
    pack_params,
    homography_values,
    plane_from_homography,
    plane_from_pose,
    road_homography,
    road_motion,
    road_motion_batch,
    rotation_angles,
    unpack_params,
)

SIZE = (48, 120)
K_SMALL = [[90.0, 0.0, 60.0], [0.0, 95.0, 14.0], [0.0, 0.0, 1.0]]


def camera(roll=0.0, pitch=0.0, height=1.65, dtype=torch.float64) -> Camera:
    return Camera(torch.tensor(K_SMALL, dtype=dtype), height, roll, pitch)


# -- independent references ----------------------------------------------------------------------

def _rx(a):  # pitch: [[1, 0, 0], [0, c, s], [0, -s, c]]
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, s], [0, -s, c]])


def _ry(a):  # yaw: [[c, 0, -s], [0, 1, 0], [s, 0, c]]
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])


def _rz(a):  # roll: [[c, s, 0], [-s, c, 0], [0, 0, 1]]
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])


def rigid_motion(p: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, t, n) of the camera: X' = R X + t, road plane nᵀX = h, from plane parameters."""
    Rc = _rz(p.get("roll", 0.0)) @ _rx(p.get("pitch", 0.0))
    Rv = _rz(p.get("roll_change", 0.0)) @ _rx(p.get("pitch_change", 0.0)) @ _ry(p.get("yaw", 0.0))
    d = np.array([p.get("x_d", 0.0), p.get("y_d", 0.0), p.get("z_d", 0.0)])
    return Rc @ Rv @ Rc.T, -Rc @ Rv @ d, Rc @ np.array([0.0, 1.0, 0.0])


def flow_of_homography(Hm: np.ndarray, size) -> np.ndarray:
    H, W = size
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    q = np.einsum("ij,jhw->ihw", Hm, np.stack([u, v, np.ones_like(u)]))
    return np.stack([q[0] / q[2] - u, q[1] / q[2] - v])


def ray_cast_flow(K: np.ndarray, h: float, R, t, n, size) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flow by intersecting each pixel's ray with the plane nᵀX = h, moving it, projecting; where
    it is defined; and where that is clear of rounding (away from the horizon and the camera
    plane of t+1)."""
    H, W = size
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    rays = np.einsum("ij,jhw->ihw", np.linalg.inv(K), np.stack([u, v, np.ones_like(u)]))
    denom = np.einsum("i,ihw->hw", n, rays)
    ok = denom > 0
    with np.errstate(over="ignore", invalid="ignore"):  # rays grazing the horizon: not compared
        X = rays * np.where(ok, h / np.where(ok, denom, 1.0), 0.0)
        Xp = np.einsum("ij,jhw->ihw", R, X) + t[:, None, None]
    ok &= Xp[2] > 0
    clear = (np.abs(denom) > 1e-6) & (np.abs(Xp[2]) > 1e-6)
    q = np.einsum("ij,jhw->ihw", K, Xp)
    z = np.where(ok, q[2], 1.0)
    return np.stack([q[0] / z - u, q[1] / z - v]), ok, clear


plane_params = st.fixed_dictionaries({
    "pitch_change": st.floats(-0.02, 0.02), "yaw": st.floats(-0.1, 0.1), "roll_change": st.floats(-0.02, 0.02),
    "x_d": st.floats(-0.3, 0.3), "y_d": st.floats(-0.05, 0.05), "z_d": st.floats(-0.5, 2.5),
    "roll": st.floats(-0.1, 0.1), "pitch": st.floats(-0.1, 0.1)})


# -- feature: each model against the independent references --------------------------------------

@settings(max_examples=25, deadline=None)
@given(p=plane_params, height=st.floats(1.0, 2.5))
def test_plane_equals_plane_induced_homography_and_ray_cast(p, height):
    cam = camera(height=height)
    flow, valid = road_flow(cam, p, SIZE, model="plane")
    R, t, n = rigid_motion(p)
    K = np.asarray(K_SMALL)
    Hm = K @ (R + np.outer(t, n) / height) @ np.linalg.inv(K)
    ref = flow_of_homography(Hm, SIZE)
    cast, ok, clear = ray_cast_flow(K, height, R, t, n, SIZE)
    m = valid[0, 0].numpy()
    assert np.array_equal(m[clear], ok[clear])  # the same pixels are defined
    both = m & ok & clear
    np.testing.assert_allclose(flow[0].numpy()[:, both], ref[:, both], atol=1e-6)
    np.testing.assert_allclose(flow[0].numpy()[:, both], cast[:, both], atol=1e-6)


@settings(max_examples=20, deadline=None)
@given(p=plane_params)
def test_paper_is_plane_without_body_motion_and_matches_eq13(p):
    paper = {k: p[k] for k in ("x_d", "z_d", "yaw")}
    cam = camera(roll=p["roll"])  # eq. 13 has roll only
    flow, valid = road_flow(cam, paper, SIZE, model="paper")
    same, _ = road_flow(cam, {**paper, "roll": p["roll"]}, SIZE, model="plane")
    torch.testing.assert_close(flow, same, rtol=0, atol=1e-9)
    # the paper's λ form (eq. 13), written out here
    K = np.asarray(K_SMALL)
    fx, fy, u0, v0 = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    v, u = np.meshgrid(np.arange(SIZE[0], dtype=np.float64), np.arange(SIZE[1], dtype=np.float64), indexing="ij")
    th, h, phi = p["roll"], 1.65, p["yaw"]
    l1 = (u - u0) / fx * math.sin(th) + (v - v0) / fy * math.cos(th)
    l2 = (u - u0) / fx * math.cos(th) - (v - v0) / fy * math.sin(th)
    l3, l4 = l2 * h - l1 * p["x_d"], h - l1 * p["z_d"]
    D = l3 * math.sin(phi) + l4 * math.cos(phi)
    ok = (l1 > 1e-6) & (D > 1e-6)
    Ds = np.where(ok, D, 1.0)
    a = (l3 * math.cos(phi) - l4 * math.sin(phi)) / Ds - l2
    b = l1 * h / Ds - l1
    M = np.array([[fx * math.cos(th), fx * math.sin(th)], [-fy * math.sin(th), fy * math.cos(th)]])
    ref = np.einsum("ij,jhw->ihw", M, np.stack([a, b]))
    both = valid[0, 0].numpy() & ok
    np.testing.assert_allclose(flow[0].numpy()[:, both], ref[:, both], atol=1e-6)


def test_paper_equals_displacement_flow():
    cam = camera(roll=0.02, pitch=-0.015)
    a = road_flow(cam, {"x_d": 0.1, "z_d": 1.2, "yaw": 0.03}, SIZE, model="paper")
    b = displacement_flow(cam, 0.1, 1.2, 0.03, SIZE)
    torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_homography_model_is_its_matrix():
    cam = camera()
    h = {"h11": 0.01, "h12": -0.02, "h13": 0.03, "h21": 0.004, "h22": 0.02, "h23": -0.01, "h31": 0.001, "h32": -0.6}
    flow, valid = road_flow(cam, h, SIZE, model="homography")
    G = np.eye(3) + np.append(list(h.values()), 0.0).reshape(3, 3)
    K = np.asarray(K_SMALL)
    Hm = K @ G @ np.linalg.inv(K)
    ref = flow_of_homography(Hm, SIZE)
    m = valid[0, 0].numpy()
    assert m.sum() > 1000
    np.testing.assert_allclose(flow[0].numpy()[:, m], ref[:, m], atol=1e-9)
    torch.testing.assert_close(road_homography(cam, h, model="homography")[0], torch.from_numpy(Hm))


def test_velocity_model_is_the_derivative_of_the_plane_homography():
    cam = camera(roll=0.03, pitch=-0.02)
    speed, yaw_rate, dt = 8.0, 0.2, 1e-6
    G = road_homography(cam, {"speed": speed, "yaw_rate": yaw_rate}, model="velocity")
    Hp = road_homography(cam, {"z_d": speed * dt, "yaw": yaw_rate * dt}, model="plane")
    Hm = road_homography(cam, {"z_d": -speed * dt, "yaw": -yaw_rate * dt}, model="plane")
    torch.testing.assert_close(G, (Hp - Hm) / (2 * dt), rtol=1e-6, atol=1e-6)


# -- derivatives ------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(ROAD_MODELS))
def test_jacobian_matches_finite_differences(name):
    model = ROAD_MODELS[name]
    cam = Camera(torch.tensor(K_SMALL, dtype=torch.float64).expand(2, 3, 3), torch.tensor([1.6, 1.4], dtype=torch.float64),
                 torch.tensor([0.02, -0.01], dtype=torch.float64), torch.tensor([-0.015, 0.01], dtype=torch.float64))
    cam, values = pack_params(model, cam, None)
    values = values + 0.05 * torch.randn(values.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    M, dM = model.matrix_and_jacobian(cam, values)
    torch.testing.assert_close(M, model.matrix(cam, values))
    eps = 1e-6
    for k in range(values.shape[1]):
        e = torch.zeros_like(values)
        e[:, k] = eps
        fd = (model.matrix(cam, values + e) - model.matrix(cam, values - e)) / (2 * eps)
        torch.testing.assert_close(dM[:, k], fd, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("name", ["paper", "plane", "velocity"])
def test_evaluate_gives_the_horizon_row(name):
    """The horizon row that ``evaluate`` returns beside the map is :meth:`horizon_row`'s."""
    model = ROAD_MODELS[name]
    cam, values = pack_params(model, camera(roll=0.03, pitch=-0.02), None)
    values = values + 0.05
    M, _, horizon = model.evaluate(cam.K, cam.K_inv(), cam.height, values, True)
    torch.testing.assert_close(M, model.matrix(cam, values))
    torch.testing.assert_close(horizon, model.horizon_row(cam, values))


@pytest.mark.parametrize("name", list(ROAD_MODELS))
def test_gradcheck_float64(name):
    model = ROAD_MODELS[name]
    # a 12 x 20 crop below the horizon (the full camera's horizon, row 14, lies below such a small
    # image's rows: its flow was 0 everywhere, and the gradcheck checked a constant)
    cam, values = pack_params(model, camera(roll=0.02, pitch=-0.01).cropped(50, 18), None)
    values = (values + 0.02).requires_grad_()

    def f(v):
        return road_flow(cam, dict(zip(model.params, v.unbind(-1))), (12, 20), model=name)[0]

    flow, valid = road_flow(cam, dict(zip(model.params, values.detach().unbind(-1))), (12, 20), model=name)
    assert bool(valid.all()) and float(flow.abs().min()) > 0
    assert torch.autograd.gradcheck(f, (values,), eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("name", list(ROAD_MODELS))
def test_module_twin_compiles_fullgraph_and_exports(name):
    """One graph (``fullgraph``) through AOTAutograd (``aot_eager``: inductor's C++ code, seconds
    of a compiler per model on a cold cache, is checked on the paper's modules in
    ``test_flow_model.py``), and an exported program, each giving the eager flow."""
    module = RoadFlow((24, 40), model=name)
    cam = camera(dtype=torch.float32)
    params = {n: torch.tensor([0.01]) for n in ROAD_MODELS[name].params if n not in ("roll", "pitch")}
    eager = module(cam, params)
    compiled = torch.compile(module, fullgraph=True, backend="aot_eager")(cam, params)
    torch.testing.assert_close(compiled[0], eager[0], rtol=1e-5, atol=1e-5)
    assert torch.equal(compiled[1], eager[1])
    exported = torch.export.export(module, (cam, params))
    out = exported.module()(cam, params)
    torch.testing.assert_close(out[0], eager[0], rtol=1e-5, atol=1e-5)


def test_geometry_in_float32_under_autocast():
    cam = Camera(torch.tensor([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]]), 1.65, 0.01, -0.01)
    ref, valid = road_flow(cam, {"z_d": 1.2, "yaw": 0.02, "pitch_change": 0.002}, (375, 1242), model="plane")
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out, valid2 = road_flow(cam, {"z_d": 1.2, "yaw": 0.02, "pitch_change": 0.002}, (375, 1242), model="plane")
    assert out.dtype == torch.float32
    assert torch.equal(valid, valid2)
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-3)


def test_pose_and_homography_conversions_in_float32_under_autocast():
    """plane_from_pose and plane_from_homography compute in float32 under a bfloat16 autocast (a
    bfloat16 pose put z_d 3 mm a metre off; det had no bfloat16 kernel)."""
    cam = Camera(torch.tensor([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]]), 1.65, 0.01, -0.01)
    T = torch.eye(4)
    T[2, 3], T[1, 3] = -1.2, 0.018
    H = road_homography(cam, {"z_d": 1.2, "yaw": 0.01}, model="plane")
    plain_pose, plain_h = plane_from_pose(T, cam), plane_from_homography(H, cam)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        pose, h = plane_from_pose(T, cam), plane_from_homography(H, cam)
    for got, ref in ((pose, plain_pose), (h, plain_h)):
        for k, v in ref.items():
            assert got[k].dtype == torch.float32 and torch.equal(got[k], v), k
    with pytest.raises(ValueError, match=r"^H: expected a float tensor of shape \(B, 3, 3\), got torch.float32"):
        plane_from_homography(H[0], cam)
    with pytest.raises(TypeError, match=r"^camera: expected a fsof_torch.Camera, got Tensor"):
        plane_from_homography(H, cam.K)


# -- conversions --------------------------------------------------------------------------------------

@settings(max_examples=20, deadline=None)
@given(p=plane_params)
def test_rotation_angles_invert_the_composition(p):
    R = _rz(p["roll_change"]) @ _rx(p["pitch_change"]) @ _ry(p["yaw"])
    a = rotation_angles(torch.from_numpy(R))
    np.testing.assert_allclose(a.numpy(), [p["pitch_change"], p["yaw"], p["roll_change"]], atol=1e-12)



def test_rotation_angles_and_homography_values_check_their_inputs():
    """An integer R once raised torch's "hypot_cpu not implemented for 'Long'", an R of shape
    (3, 2) an IndexError, and a 4×4 one gave angles silently; homography_values of an unbatched
    H raised an IndexError and of an integer H gave values. Each now names the argument."""
    R = torch.from_numpy(_rz(0.01) @ _rx(0.02) @ _ry(0.3))
    np.testing.assert_allclose(rotation_angles(R.expand(2, 3, 3)).numpy(), [[0.02, 0.3, 0.01]] * 2, atol=1e-12)
    with pytest.raises(TypeError, match=r"^R: expected a floating-point tensor, got dtype torch.int64"):
        rotation_angles(torch.eye(3, dtype=torch.int64))
    with pytest.raises(TypeError, match=r"^R: expected a torch.Tensor, got ndarray"):
        rotation_angles(R.numpy())
    for shape in ((3, 2), (4, 4), (3,)):
        with pytest.raises(ValueError, match=rf"^R: expected rotation matrices of shape \(\.\.\., 3, 3\), got "
                                             rf"{re.escape(str(shape))}"):
            rotation_angles(torch.zeros(shape, dtype=torch.float64))
    cam = camera()
    H = road_homography(cam, {"z_d": 1.2, "yaw": 0.02}, model="plane")
    # reference: K⁻¹ H K by NumPy, scaled to a last entry of 1, minus I
    G = np.linalg.inv(cam.K[0].numpy()) @ H[0].numpy() @ cam.K[0].numpy()
    want = (G / G[2, 2] - np.eye(3)).reshape(9)[:8]
    np.testing.assert_allclose(homography_values(H, cam.K, cam.K_inv())[0].numpy(), want, atol=1e-12)
    np.testing.assert_allclose(homography_values(H, cam.K.expand(3, 3, 3), cam.K_inv()).numpy(), [want] * 3, atol=1e-12)
    for args, error, message in (
            ((H[0], cam.K, cam.K_inv()), ValueError, r"^H: expected shape \(B, 3, 3\), got \(3, 3\)"),
            ((H, cam.K[0], cam.K_inv()), ValueError, r"^K: expected shape \(B, 3, 3\), got \(3, 3\)"),
            ((H, cam.K, cam.K_inv()[:, :2]), ValueError, r"^K_inv: expected shape \(B, 3, 3\), got \(1, 2, 3\)"),
            ((H.long(), cam.K, cam.K_inv()), TypeError, r"^H: expected a floating-point tensor, got dtype torch.int64"),
            ((H.expand(2, 3, 3), cam.K.expand(3, 3, 3), cam.K_inv()), ValueError, r"mismatched batch sizes: H=2, K=3")):
        with pytest.raises(error, match=message):
            homography_values(*args)


def test_homography_values_of_a_map_the_model_cannot_express_is_an_error():
    """A map whose K⁻¹ H K has a last entry of 0 (the model holds it at 1) gave inf and NaN values
    silently: a ValueError naming H and the sample. A tiny last entry that scales finitely is kept
    (values against NumPy), and NaN in H still gives NaN out."""
    cam = camera()
    K = cam.K[0].numpy()
    G = np.array([[1.0, 0.01, 0.02], [0.0, 1.0, 0.03], [0.001, 0.002, 0.0]])  # K G K⁻¹ and back: 0 up to rounding
    good = road_homography(cam, {"z_d": 1.2}, model="plane")
    H = torch.cat([good, torch.from_numpy(K @ G @ np.linalg.inv(K)).unsqueeze(0)])
    with pytest.raises(ValueError, match=r"^H: samples \[1\] have K⁻¹ H K with a last entry of .*cannot express"):
        homography_values(H, cam.K, cam.K_inv())
    with pytest.raises(ValueError, match=r"^H: samples \[0\] have K⁻¹ H K with a last entry of 0, "):
        homography_values(torch.diag(torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64))[None], cam.K, cam.K_inv())
    G[2, 2] = 1e-6
    H = torch.from_numpy(K @ G @ np.linalg.inv(K)).unsqueeze(0)
    want = (G / G[2, 2] - np.eye(3)).reshape(9)[:8]
    np.testing.assert_allclose(homography_values(H, cam.K, cam.K_inv())[0].numpy(), want, rtol=1e-6)
    assert homography_values(torch.full((1, 3, 3), float("nan"), dtype=torch.float64), cam.K, cam.K_inv()).isnan().all()


def test_unpack_params_refuses_values_of_another_width():
    """values with more columns than the model's parameters lost the extra ones silently, and
    fewer raised an IndexError: a ValueError naming values, with both counts."""
    values = torch.tensor([[0.1, 1.2, 0.01, 0.02, 0.03]], dtype=torch.float64)
    got = unpack_params("paper", values)
    assert list(got) == ["x_d", "z_d", "yaw", "roll", "pitch"]
    assert [float(v) for v in got.values()] == [0.1, 1.2, 0.01, 0.02, 0.03]
    for width in (3, 7, 8):
        with pytest.raises(ValueError, match=rf"^values: expected shape \(B, 5\), got \(1, {width}\)"):
            unpack_params("paper", torch.zeros(1, width))
    with pytest.raises(TypeError, match=r"^values: expected a \(B, 8\) tensor, got list"):
        unpack_params("plane", [[0.0] * 8])

@settings(max_examples=20, deadline=None)
@given(p=plane_params)
def test_plane_from_pose_and_decomposition_recover_the_parameters(p):
    cam = camera(roll=p["roll"], pitch=p["pitch"])
    R, t, _ = rigid_motion(p)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3], T[:3, 3] = torch.from_numpy(R), torch.from_numpy(t)
    got = plane_from_pose(T, cam)
    for k, v in p.items():
        assert abs(float(got[k]) - v) < 1e-10, k
    if abs(p["z_d"]) + abs(p["x_d"]) > 0.05:  # a homography of (almost) no translation has no plane
        H = road_homography(cam, p, model="plane")
        dec = decompose_homography(3.0 * H, cam)  # any scale
        for k, v in p.items():
            assert abs(float(dec.params[k]) - v) < 1e-6, k


def test_road_motion_forms_and_errors():
    assert road_motion({"x_d": 0.0, "z_d": 1.0, "yaw": 0.0})[0].name == "paper"
    model, params = road_motion({"model": "plane", "z_d": 1.0})
    assert model.name == "plane" and params == {"z_d": 1.0}
    with pytest.raises(ValueError, match="odometry: missing keys"):
        road_motion({"z_d": 1.0})
    with pytest.raises(ValueError, match="unknown parameters"):
        road_motion({"model": "plane", "speed": 1.0})
    # (the error names the motion's entry, not a ``model`` argument of the caller's: the refiner's
    # and the loss's odometry come with options of their own)
    with pytest.raises(ValueError, match=r"odometry\['model'\]: expected one of .*got 'bicycle'"):
        road_motion({"model": "bicycle"})
    with pytest.raises(TypeError, match=r"motion\['model'\]: expected one of .*got None"):
        road_motion({"model": None}, "motion")
    with pytest.raises(TypeError, match="odometry: expected a dict"):
        road_motion(3.0)
    # a batch of 1 allows one shape, and the message says so (once "(1,) or (1,)")
    with pytest.raises(ValueError, match=r"odometry\['z_d'\]: expected a float or a tensor of shape \(1,\) \(the "
                                         r"flow's batch\), got shape \(3,\)"):
        road_motion_batch({"model": "plane", "z_d": torch.ones(3)}, 1, torch.float32, "cpu")


def test_bad_inputs_name_the_argument():
    cam = camera()
    with pytest.raises(ValueError, match="params: unknown names"):
        road_flow(cam, {"speed": 1.0}, SIZE, model="paper")
    with pytest.raises(ValueError, match="mismatched batch sizes"):
        road_flow(cam.expand(2), {"z_d": torch.ones(3, dtype=torch.float64)}, SIZE)
    with pytest.raises(ValueError, match="z_d: expected finite"):
        road_flow(cam, {"z_d": float("nan")}, SIZE)
    with pytest.raises(ValueError, match="z_d: a tensor on the meta device has no values to move to cpu"):
        road_flow(cam, {"z_d": torch.ones(1, dtype=torch.float64, device="meta")}, SIZE)
    with pytest.raises(ValueError, match="overflows"):
        road_flow(Camera(torch.tensor(K_SMALL), 1.65), {"x_d": 1e37}, SIZE)
    with pytest.raises(TypeError, match="camera: expected a fsof_torch.Camera"):
        road_flow("cam", {"z_d": 1.0}, SIZE)
    with pytest.raises(TypeError, match="camera: expected a fsof_torch.Camera, got list"):
        plane_from_pose(torch.eye(4, dtype=torch.float64)[None], [1.0, 2.0])  # once an AttributeError


# -- constants, autocast, devices ---------------------------------------------------------------------

def test_constants_first_built_under_inference_mode_serve_autograd(monkeypatch):
    """The maps' cached constants are built outside inference mode: a first call under
    torch.inference_mode once cached inference tensors, and every later differentiable call
    failed ("Inference tensors cannot be saved for backward")."""
    import fsof_torch.geometry.road_models as road_models

    cam = Camera(torch.tensor(K_SMALL), 1.65, 0.01)
    cases = [("paper", {"z_d": 1.0, "yaw": 0.02}), ("plane", {"z_d": 1.0, "pitch_change": 0.01}),
             ("velocity", {"speed": 1.0, "yaw_rate": 0.1})]

    def grads():
        out = []
        for model, p in cases:
            roll = torch.tensor([0.02], requires_grad=True)
            road_flow(cam, {**p, "roll": roll}, SIZE, model=model)[0].sum().backward()
            out.append(roll.grad)
        return out

    want = grads()
    monkeypatch.setattr(road_models, "_CACHE", {})
    with torch.inference_mode():
        for model, p in cases:
            road_flow(cam, p, SIZE, model=model)
            ROAD_MODELS[model].matrix_and_jacobian(*pack_params(model, cam, p))
    assert road_models._CACHE and not any(t.is_inference() for v in road_models._CACHE.values()
                                          for t in (v if isinstance(v, tuple) else (v,)))
    for got, ref in zip(grads(), want):
        assert torch.equal(got, ref) and float(ref.abs()) > 0


def test_model_maps_stay_float32_under_autocast():
    """RoadModel.matrix, matrix_and_jacobian, evaluate, horizon_row and homography_values keep
    their inputs' precision under a bfloat16 autocast (bfloat16 moved the flow 3.9 px)."""
    from fsof_torch.geometry.road_models import homography_values

    cam = Camera(torch.tensor([[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]]), 1.65, 0.01, -0.015)
    for name, p in [("paper", {"x_d": 0.05, "z_d": 1.2, "yaw": 0.01}), ("plane", {"z_d": 1.2, "y_d": 0.01}),
                    ("velocity", {"speed": 9.0, "yaw_rate": 0.1})]:
        model = ROAD_MODELS[name]
        c, values = pack_params(model, cam, p)

        def compute():
            M, J = model.matrix_and_jacobian(c, values)
            return {"matrix": model.matrix(c, values), "M": M, "J": J,
                    "evaluate": model.evaluate(c.K, c.K_inv(), c.height, values, True)[1],
                    "horizon": model.horizon_row(c, values),
                    "values": homography_values(M, c.K, c.K_inv())}

        plain = compute()
        with torch.autocast("cpu", dtype=torch.bfloat16):
            cast = compute()
        for key, ref in plain.items():
            assert cast[key].dtype == torch.float32 and torch.equal(cast[key], ref), (name, key)
    # homography_values in the promoted dtype, half precision lifted (mixed dtypes once raised
    # torch's "expected scalar type Double but found Float")
    M = ROAD_MODELS["plane"].matrix(*pack_params(ROAD_MODELS["plane"], cam, {"z_d": 1.2}))
    ref = homography_values(M.double(), cam.K.double(), cam.K_inv().double())
    mixed = homography_values(M, cam.K.double(), cam.K_inv())
    assert mixed.dtype == torch.float64 and torch.allclose(mixed, ref, atol=1e-6)
    half = homography_values(M.half(), cam.K, cam.K_inv())
    assert half.dtype == torch.float32 and torch.allclose(half, ref.float(), atol=2e-2)


def test_pose_conversions_follow_the_inputs_device():
    """The camera follows the pose or homography to its device (the meta device stands in for
    a GPU here: a CPU camera beside them once raised inside torch)."""
    from fsof_torch import ego_motion_from_pose

    cam = camera(roll=0.01, pitch=0.02)
    T = torch.eye(4, dtype=torch.float64, device="meta")[None]
    H = torch.eye(3, dtype=torch.float64, device="meta")[None]
    for out in (plane_from_pose(T, cam), plane_from_homography(H, cam), ego_motion_from_pose(T, cam)._asdict()):
        assert all(v.device.type == "meta" for v in out.values() if v is not None)
    meta_cam = Camera(cam.K.to("meta"), 1.65)
    with pytest.raises(ValueError, match="^camera: a camera on the meta device has shapes but no values"):
        plane_from_homography(torch.eye(3, dtype=torch.float64)[None], meta_cam)



def test_pose_conversions_return_the_attitude_as_their_own_tensors():
    """plane_from_pose and plane_from_homography returned the camera's own roll and pitch tensors
    (or, for a camera of batch 1 beside a batch, a stride-0 expansion of them): a result edited
    in place changed the caller's camera, or raised torch's 'more than one element of the
    written-to tensor refers to a single memory location'. They are copies now, still
    differentiable in the camera."""
    for B, cam_batch in ((1, 1), (2, 2), (2, 1)):
        roll = torch.full((cam_batch,), 0.01, dtype=torch.float64, requires_grad=True)
        cam = Camera(torch.tensor(K_SMALL, dtype=torch.float64), 1.65, roll, torch.full((cam_batch,), -0.015,
                                                                                          dtype=torch.float64))
        T = torch.eye(4, dtype=torch.float64).repeat(B, 1, 1)
        T[:, 2, 3] = -1.2
        H = road_homography(cam.expand(B), {"z_d": 1.2}, model="plane").detach()
        for out in (plane_from_pose(T, cam), plane_from_homography(H, cam)):
            assert out["roll"].shape == out["pitch"].shape == (B,)
            sum(out[n].sum() for n in ("roll", "pitch", "z_d")).backward()
            assert torch.isfinite(roll.grad).all() and float(roll.grad.abs().min()) > 0
            roll.grad = None
            with torch.no_grad():
                out["roll"].add_(0.5)
                out["pitch"].mul_(2.0)
            assert cam.roll.tolist() == [0.01] * cam_batch and cam.pitch.tolist() == [-0.015] * cam_batch

# -- plane_from_homography: singular homographies, gradients ------------------------------------------

def test_plane_from_homography_rejects_singular_homographies():
    """A singular H once raised torch's _LinAlgError from the SVD, naming no argument."""
    cam = camera(roll=0.02, pitch=-0.03)
    good = road_homography(cam, {"z_d": 1.3, "yaw": 0.02}, model="plane")
    rank2 = torch.tensor([[[1.0, 0, 0], [0, 1, 0], [0, 0, 0]]], dtype=torch.float64)
    for H, bad in ((torch.zeros(1, 3, 3, dtype=torch.float64), [0]), (rank2, [0]),
                   (torch.cat([good, rank2]), [1])):
        with pytest.raises(ValueError, match=rf"^H: expected invertible matrices, got samples \{bad}"):
            plane_from_homography(H, cam)
    # any scale and sign of an invertible one is fine, also one whose determinant underflows
    for scale in (-2.5, 1e-120):
        assert float(plane_from_homography(scale * good, cam)["z_d"]) == pytest.approx(1.3, abs=1e-12)


def test_plane_from_homography_gradients():
    """Gradients through the decomposition are finite and right: straight motion, where the
    rotation step's SVD had three equal singular values, gave NaN; a turn gave gradients a few
    percent off."""
    K = torch.tensor([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(K, 1.65, 0.01, -0.02)

    def motion(H):
        return tuple(v for k, v in plane_from_homography(H, cam).items() if k not in ("roll", "pitch"))

    for p in ({"z_d": 1.2}, {"z_d": 1.2, "yaw": 0.02, "pitch_change": 0.003, "x_d": 0.1}):
        H = road_homography(cam, p, model="plane").requires_grad_()
        assert torch.autograd.gradcheck(motion, (H,), atol=1e-6, rtol=1e-4, fast_mode=False)
        sum(v.sum() for v in motion(H)).backward()
        assert torch.isfinite(H.grad).all() and float(H.grad.abs().max()) > 0


def test_nearest_rotation_is_the_polar_factor():
    """The rotation step against an SVD's U Vᵀ, for matrices near and far from a rotation."""
    from fsof_torch.geometry.road_models import _nearest_rotation

    g = torch.Generator().manual_seed(0)
    for spread in (1e-3, 0.5, 1e3, 1e8):
        Q1 = torch.linalg.qr(torch.randn(20, 3, 3, generator=g, dtype=torch.float64))[0]
        Q2 = torch.linalg.qr(torch.randn(20, 3, 3, generator=g, dtype=torch.float64))[0]
        s = 1.0 + spread * torch.rand(20, 3, generator=g, dtype=torch.float64)
        M = Q1 @ torch.diag_embed(s) @ Q2
        M = M * torch.sign(torch.linalg.det(M)).reshape(-1, 1, 1)
        U, _, Vh = torch.linalg.svd(M)
        torch.testing.assert_close(_nearest_rotation(M), U @ Vh, rtol=0, atol=1e-12)
        # float32 is iterated in float64 (in float32 a condition number of 1e6 gave a wrong rotation)
        R32 = _nearest_rotation(M.float())
        assert R32.dtype == torch.float32
        torch.testing.assert_close(R32.double(), torch.linalg.svd(M.float().double())[0] @
                                   torch.linalg.svd(M.float().double())[2], rtol=0, atol=1e-6)


def test_road_motion_displacement_refuses_the_velocity_model():
    """Callers comparing with flow per frame ask for a displacement motion; others still take
    the velocity model's."""
    velocity = {"model": "velocity", "speed": 12.0, "yaw_rate": 0.1}
    assert road_motion(velocity)[0].name == "velocity"
    assert road_motion_batch(velocity, 2, torch.float64, "cpu")[0].name == "velocity"
    message = r"^motion: the 'velocity' model gives flow in px/s, not the pixels per frame this needs"
    with pytest.raises(ValueError, match=message):
        road_motion(velocity, "motion", displacement=True)
    with pytest.raises(ValueError, match=message):
        road_motion_batch(velocity, 2, torch.float64, "cpu", name="motion", displacement=True)
    for odometry in ({"x_d": 0.0, "z_d": 1.0, "yaw": 0.0}, {"model": "plane", "z_d": 1.0},
                     {"model": "homography", "h11": 0.0}):
        assert not road_motion(odometry, displacement=True)[0].velocity


def test_matrix_checks_types_and_shapes_and_promotes_dtypes():
    """matrix / matrix_and_jacobian once raised torch's own errors for values of another dtype
    (float64 beside a float32 camera, float16), of the wrong width or rank, or of another batch."""
    cam32 = camera(dtype=torch.float32)
    m = ROAD_MODELS["paper"]
    v64 = torch.tensor([[0.05, 1.2, 0.01, 0.02, -0.01]], dtype=torch.float64)
    want = m.matrix(camera(dtype=torch.float64), v64)
    got = m.matrix(cam32, v64)  # the camera lifted to the values' dtype
    assert got.dtype == torch.float64
    torch.testing.assert_close(got, m.matrix(cam32.to(torch.float64), v64), rtol=0.0, atol=0.0)
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
    for half in (torch.float16, torch.bfloat16):  # half precision values computed in float32
        M, J = m.matrix_and_jacobian(cam32, v64.to(half))
        M_ref, J_ref = m.matrix_and_jacobian(cam32, v64.to(half).float())
        assert M.dtype == J.dtype == torch.float32 and torch.equal(M, M_ref) and torch.equal(J, J_ref)
    # a camera of batch 1 beside values of batch B (and values of batch 1 beside a camera of B)
    v3 = v64.expand(3, 5) * torch.tensor([[1.0], [0.5], [2.0]], dtype=torch.float64)
    cam = camera()
    torch.testing.assert_close(m.matrix(cam, v3), m.matrix(cam.expand(3), v3), rtol=0.0, atol=0.0)
    torch.testing.assert_close(m.matrix(cam.expand(3), v64), m.matrix(cam, v64).expand(3, 3, 3), rtol=0.0, atol=0.0)
    with pytest.raises(ValueError, match=r"^values: expected shape \(B, 5\), got \(1, 3\)"):
        m.matrix(cam, v64[:, :3])
    with pytest.raises(ValueError, match=r"^values: expected shape \(B, 8\).*got \(8,\)"):
        ROAD_MODELS["plane"].matrix_and_jacobian(cam, torch.zeros(8, dtype=torch.float64))
    with pytest.raises(ValueError, match="^mismatched batch sizes: camera=2, values=3"):
        m.matrix(cam.expand(2), v3)
    with pytest.raises(TypeError, match="^values: expected a floating-point tensor, got dtype torch.int64"):
        m.matrix(cam, torch.zeros(1, 5, dtype=torch.int64))
    with pytest.raises(TypeError, match="^camera: expected a fsof_torch.Camera, got Tensor"):
        m.matrix(cam.K, v64)
    # the values are the caller's: no check reads them (a NaN gives a NaN map, without a host read)
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        nan = m.matrix_and_jacobian(cam32, torch.full((1, 5), float("nan"), dtype=torch.float64))[0]
    assert torch.isnan(nan).all()
    assert not [e.name for e in prof.events() if e.name in ("aten::_local_scalar_dense", "aten::nonzero", "aten::item")]


# -- symmetry: the street seen from its other side ------------------------------------------------

# the parameters whose sign a left-right reflection of the world (the camera's x axis) turns over
# (the homography's values, the entries of K⁻¹ H K − I, turn over where exactly one index is x's)
MIRRORED = {"paper": ("x_d", "yaw", "roll"), "plane": ("yaw", "roll_change", "x_d", "roll"),
            "velocity": ("yaw_rate", "roll"), "homography": ("h12", "h13", "h21", "h31")}


@settings(max_examples=20, deadline=None)
@given(p=plane_params, height=st.floats(1.0, 2.5), model=st.sampled_from(sorted(MIRRORED)))
def test_mirrored_camera_and_motion_give_the_mirrored_road_flow(p, height, model):
    """Mirrored left to right (the principal point to W - 1 - c_x, the lateral motion, yaw and
    roll negated), every model's road flow is the original's, mirrored with its horizontal
    component negated: the models favour neither side of the road (DESIGN.md §10's signs)."""
    names = ROAD_MODELS[model].params
    # (a principal point off the pixel grid: no pixel lies exactly on the horizon, where rounding
    # would decide its validity differently on the two sides)
    K = torch.tensor([[90.0, 0.0, 60.3], [0.0, 95.0, 14.2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cam = Camera(K, height)
    values = {"speed": 12.0, "yaw_rate": 10 * p["yaw"], **p}
    if model == "homography":  # (the plane's map as a general homography)
        H = road_homography(cam.replace(roll=p["roll"], pitch=p["pitch"]), p, model="plane")
        values = dict(zip(names, homography_values(H, cam.K, cam.K_inv())[0].tolist()))
    params = {n: values[n] for n in names}
    mirror_cam = cam.replace(K=K.clone().index_put_((torch.tensor(0), torch.tensor(2)),
                                                    torch.tensor((SIZE[1] - 1) - 60.3, dtype=torch.float64)))
    mirror_params = {n: -v if n in MIRRORED[model] else v for n, v in params.items()}
    flow, valid = road_flow(cam, params, SIZE, model=model)
    got, got_valid = road_flow(mirror_cam, mirror_params, SIZE, model=model)
    assert torch.equal(got_valid, valid.flip(-1))
    expected = flow.flip(-1) * torch.tensor([-1.0, 1.0], dtype=flow.dtype).reshape(1, 2, 1, 1)
    assert torch.allclose(got[got_valid.expand_as(got)], expected[got_valid.expand_as(got)], atol=1e-9, rtol=1e-9)


def test_get_road_model_tells_a_wrong_type_from_a_wrong_name():
    """A model that is no string (3, None) raised the ValueError of an unknown name."""
    from fsof_torch.geometry.road_models import get_road_model

    for bad in (3, None, ["plane"]):
        with pytest.raises(TypeError, match=rf"^model: expected one of \('paper', 'plane', .*\), got {re.escape(repr(bad))}$"):
            get_road_model(bad)
    with pytest.raises(ValueError, match=r"^model: expected one of .*, got 'planar'$"):
        get_road_model("planar")
    assert get_road_model("plane") is get_road_model(get_road_model("plane"))
