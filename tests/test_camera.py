"""Tests of fsof_torch.geometry.camera: the batched camera (intrinsics + mounting), KITTI calibration files."""

from __future__ import annotations

import math
import re

import pytest
import torch

from fsof_torch.geometry.camera import Camera, mounting_matrix, pitch_matrix, read_kitti_calibration, roll_matrix
from fsof_torch.geometry.road_flow import displacement_flow, velocity_flow

CAM_TO_CAM = """calib_time: 09-Jan-2012 13:57:47
corner_dist: 9.950000e-02
S_02: 1.392000e+03 5.120000e+02
K_02: 9.597910e+02 0.000000e+00 6.960217e+02 0.000000e+00 9.569251e+02 2.241806e+02 0.000000e+00 0.000000e+00 1.000000e+00
P_rect_00: 7.0e+02 0.0 6.0e+02 0.0 0.0 7.0e+02 1.8e+02 0.0 0.0 0.0 1.0 0.0
P_rect_02: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 1.728540e+02 2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03
"""

ODOMETRY_LABELLED = """P0: 7.070912e+02 0.0 6.018873e+02 0.0 0.0 7.070912e+02 1.831104e+02 0.0 0.0 0.0 1.0 0.0
P1: 7.070912e+02 0.0 6.018873e+02 -3.798145e+02 0.0 7.070912e+02 1.831104e+02 0.0 0.0 0.0 1.0 0.0
P2: 7.1e+02 0.0 6.1e+02 4.6e+01 0.0 7.1e+02 1.9e+02 -3.3e-01 0.0 0.0 1.0 3.0e-03
Tr: 4.276802e-04 -9.999672e-01 -8.084492e-03 -1.198459e-02 -7.210626e-03 8.081198e-03 -9.999413e-01 -5.403984e-02 9.999738e-01 4.859485e-04 -7.206933e-03 -2.921968e-01
"""

ODOMETRY_UNLABELLED = """7.070912e+02 0.0 6.018873e+02 0.0 0.0 7.070912e+02 1.831104e+02 0.0 0.0 0.0 1.0 0.0
7.070912e+02 0.0 6.018873e+02 -3.798145e+02 0.0 7.070912e+02 1.831104e+02 0.0 0.0 0.0 1.0 0.0
"""


def _K(fx=721.5377, fy=721.5377, cx=609.5593, cy=172.854, dtype=torch.float64):
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)


# --- smoke -----------------------------------------------------------------------------------------

def test_smoke(kitti_K, dtype):
    cam = Camera(kitti_K.to(dtype), 1.65)
    assert cam.batch_size == 1 and cam.dtype == dtype and cam.device == torch.device("cpu")
    assert cam.K.shape == (1, 3, 3) and cam.height.shape == (1,) and cam.roll.shape == (1,)
    assert cam.fx.tolist() == pytest.approx([721.5377]) and cam.cy.tolist() == pytest.approx([172.854])
    assert cam.fy.tolist() == pytest.approx([721.5377]) and cam.cx.tolist() == pytest.approx([609.5593])


def test_docstring_example():
    cam = Camera(torch.tensor([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]]), 1.65)
    assert cam.batch_size == 1 and cam.fx.tolist() == [721.5]


def test_dtype_promotion():
    cam = Camera(_K(dtype=torch.float32), torch.tensor([1.65], dtype=torch.float64))
    assert cam.dtype == torch.float64 and cam.height.dtype == torch.float64
    cam = Camera(_K(dtype=torch.float16), 1.65)
    assert cam.dtype == torch.float32  # half precision lifted


def test_rotation_matrices():
    t = torch.tensor([0.3], dtype=torch.float64)
    c, s = math.cos(0.3), math.sin(0.3)
    torch.testing.assert_close(roll_matrix(t)[0], torch.tensor([[c, s, 0], [-s, c, 0], [0, 0, 1.0]],
                                                               dtype=torch.float64))
    torch.testing.assert_close(pitch_matrix(t)[0], torch.tensor([[1.0, 0, 0], [0, c, s], [0, -s, c]],
                                                                dtype=torch.float64))
    torch.testing.assert_close(mounting_matrix(t, -t), roll_matrix(t) @ pitch_matrix(-t))
    cam = Camera(_K(), 1.65, 0.3, -0.3)
    torch.testing.assert_close(cam.mounting(), mounting_matrix(t, -t))


def test_K_inv(kitti_K):
    K = kitti_K.clone()
    K[0, 1] = 0.7  # skew
    cam = Camera(K, 1.65)
    torch.testing.assert_close(cam.K_inv()[0], torch.linalg.inv(K), rtol=1e-12, atol=1e-15)


def test_horizon_row_separates_valid_pixels():
    H, W = 40, 60
    cam = Camera(_K(50.0, 55.0, 30.0, 18.0), 1.5, 0.1, 0.02)
    _, valid = velocity_flow(cam, 1.0, 0.0, 2.7, (H, W))
    for u in (0, 29, 59):
        row = float(cam.horizon_row(torch.tensor([float(u)], dtype=torch.float64)))
        column = valid[0, 0, :, u]
        v = torch.arange(H, dtype=torch.float64)
        assert torch.equal(column, v > row)
    level = Camera(_K(50.0, 55.0, 30.0, 18.0), 1.5, 0.0, 0.02)  # pitch β > 0: horizon below v_0
    assert float(level.horizon_row()) == pytest.approx(18.0 + 55.0 * math.tan(0.02), abs=1e-9)


def test_horizon_row_checks_u_as_a_per_frame_scalar():
    """Once a raw RuntimeError (u of another batch), a raw TypeError ('left') and a silent NaN."""
    cam = Camera(_K(50.0, 55.0, 30.0, 18.0), 1.5, 0.1, 0.02).expand(2)
    with pytest.raises(ValueError, match=r"^u: expected a float or a tensor of shape \(1,\) or \(2,\) \(the "
                                         r"camera's batch\), got shape \(3,\)$"):
        cam.horizon_row(torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64))
    with pytest.raises(TypeError, match="^u: expected a float, or a tensor of shape .B,., got str"):
        cam.horizon_row("left")
    with pytest.raises(TypeError, match="^u: expected a float tensor or a Python number, got dtype torch.int64"):
        cam.horizon_row(torch.tensor([1, 2]))
    with pytest.raises(ValueError, match="^u: expected finite values"):
        cam.horizon_row(float("nan"))
    with pytest.raises(ValueError, match="^u: expected a scalar or shape .B,."):
        cam.horizon_row(torch.zeros(2, 1, dtype=torch.float64))
    # accepted forms give the values they gave: a float, 0-d, (1,) and (B,) tensors; a camera of
    # batch 1 takes a u of any batch
    want = cam.horizon_row(torch.tensor([7.0, 7.0], dtype=torch.float64))
    for u in (7.0, 7, torch.tensor(7.0, dtype=torch.float64), torch.tensor([7.0], dtype=torch.float64)):
        torch.testing.assert_close(cam.horizon_row(u), want, rtol=0.0, atol=0.0)
    one = Camera(_K(50.0, 55.0, 30.0, 18.0), 1.5, 0.1, 0.02)
    assert one.horizon_row(torch.tensor([0.0, 30.0, 59.0], dtype=torch.float64)).shape == (3,)


def test_to_expand_replace():
    cam = Camera(_K(), 1.65, 0.01)
    c32 = cam.to(torch.float32)
    assert c32.dtype == torch.float32 and c32.height.dtype == torch.float32
    c3 = cam.expand(3)
    assert c3.batch_size == 3 and c3.K.shape == (3, 3, 3) and c3.roll.tolist() == [0.01] * 3
    r = cam.replace(roll=0.05, height=torch.tensor([1.2, 1.3], dtype=torch.float64))
    assert r.batch_size == 2 and r.roll.tolist() == [0.05, 0.05] and torch.equal(r.K[0], cam.K[0])
    assert cam.roll.tolist() == [0.01]  # the original is unchanged
    with pytest.raises(ValueError, match="batch_size: cannot expand a camera of batch 2 to 3"):
        r.expand(3)
    with pytest.raises(TypeError, match="replace: unknown fields"):
        cam.replace(focal=3.0)


def test_repeat_orders_the_copies_as_tensor_repeat():
    cam = Camera(_K(), torch.tensor([1.5, 1.7], dtype=torch.float64), roll=torch.tensor([0.01, 0.02], dtype=torch.float64))
    r = cam.repeat(3)
    assert r.batch_size == 6 and r.K.shape == (6, 3, 3)
    assert r.height.tolist() == [1.5, 1.7] * 3 and r.roll.tolist() == [0.01, 0.02] * 3
    assert cam.repeat(1) is cam


def test_to_and_expand_without_change_return_the_camera_itself():
    """Like Tensor.to: no change, no copy (and no re-validation in the refiner's hot path)."""
    cam = Camera(_K(), 1.65, 0.01)
    assert cam.to(torch.float64) is cam and cam.to("cpu") is cam and cam.expand(1) is cam
    c32 = cam.to(torch.float32)
    assert c32 is not cam and c32.to(torch.float32) is c32
    torch.testing.assert_close(c32.K_inv().double(), cam.K_inv(), rtol=1e-6, atol=1e-9)
    c2 = cam.expand(2)
    assert c2.expand(2) is c2 and c2.K.shape == (2, 3, 3)
    with pytest.raises(TypeError, match="K: expected a floating-point tensor"):
        cam.to(torch.int64)


def test_pytree_round_trip():
    cam = Camera(_K(), 1.65, 0.01, -0.02)
    leaves, spec = torch.utils._pytree.tree_flatten(cam)
    assert len(leaves) == 4
    back = torch.utils._pytree.tree_unflatten(leaves, spec)
    assert isinstance(back, Camera)
    for name in ("K", "height", "roll", "pitch"):
        assert torch.equal(getattr(back, name), getattr(cam, name))
    doubled = torch.utils._pytree.tree_map(lambda t: t * 2, cam)
    assert isinstance(doubled, Camera) and doubled.height.tolist() == [3.3]


# --- KITTI calibration --------------------------------------------------------------------------------

def test_kitti_cam_to_cam_shared(shared_data):
    cam = Camera.from_kitti(shared_data / "kitti15_000000" / "calib_cam_to_cam.txt", cam=2)
    assert cam.dtype == torch.float64 and cam.height.tolist() == [1.65]
    assert cam.fx.tolist() == [721.5377] and cam.fy.tolist() == [721.5377]
    assert cam.cx.tolist() == [609.5593] and cam.cy.tolist() == [172.854]


def test_kitti_odometry_shared(shared_data):
    path = shared_data / "kitti_odometry_straight" / "calib.txt"
    cam = Camera.from_kitti(path, cam=0, height=1.7, roll=0.01, pitch=-0.01)
    assert cam.fx.tolist() == [707.0912] and cam.cx.tolist() == [601.8873] and cam.cy.tolist() == [183.1104]
    assert cam.height.tolist() == [1.7] and cam.roll.tolist() == [0.01] and cam.pitch.tolist() == [-0.01]
    P1 = read_kitti_calibration(path, 1)
    assert P1[0, 3] == pytest.approx(-379.8145)


def test_kitti_files_in_tmp_path(tmp_path):
    (tmp_path / "calib_cam_to_cam.txt").write_text(CAM_TO_CAM)
    (tmp_path / "calib.txt").write_text(ODOMETRY_LABELLED)
    (tmp_path / "calib_unlabelled.txt").write_text(ODOMETRY_UNLABELLED)
    P = read_kitti_calibration(tmp_path / "calib_cam_to_cam.txt", 2)
    assert P.shape == (3, 4) and P.dtype == torch.float64 and P[0, 3] == pytest.approx(44.85728)
    assert Camera.from_kitti(tmp_path / "calib_cam_to_cam.txt", cam=0).fx.tolist() == [700.0]
    assert Camera.from_kitti(tmp_path / "calib.txt", cam=0).fx.tolist() == [707.0912]
    assert Camera.from_kitti(tmp_path / "calib.txt", cam=2).cy.tolist() == [190.0]
    cam = Camera.from_kitti(tmp_path / "calib_unlabelled.txt", cam=1, dtype=torch.float32)
    assert cam.dtype == torch.float32 and cam.fx.tolist() == pytest.approx([707.0912])
    for half in (torch.float16, torch.bfloat16):  # a float32 camera, its values not rounded to half
        cam = Camera.from_kitti(tmp_path / "calib.txt", cam=0, dtype=half)
        assert cam.dtype == torch.float32 and cam.fx.tolist() == [pytest.approx(707.0912, abs=1e-4)]
    cam = Camera.from_projection(P, 1.5)
    assert cam.cx.tolist() == [609.5593] and cam.height.tolist() == [1.5]


def test_kitti_exceptions(tmp_path):
    with pytest.raises(FileNotFoundError, match="path: no calibration file"):
        read_kitti_calibration(tmp_path / "missing.txt")
    (tmp_path / "a.txt").write_text(CAM_TO_CAM)
    with pytest.raises(ValueError, match="cam: expected 0..3, got 7"):
        read_kitti_calibration(tmp_path / "a.txt", 7)
    with pytest.raises(ValueError, match="has no P_rect_01 or P1 row"):
        read_kitti_calibration(tmp_path / "a.txt", 1)
    (tmp_path / "b.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(ValueError, match="has 3 numbers, expected 12"):
        read_kitti_calibration(tmp_path / "b.txt", 0)
    (tmp_path / "c.txt").write_text("P0: 1 2 x 4 5 6 7 8 9 10 11 12\n")
    with pytest.raises(ValueError, match="line 1 .* is not a calibration row"):
        read_kitti_calibration(tmp_path / "c.txt", 0)
    with pytest.raises(ValueError, match=r"P: expected shape \(3, 4\)"):
        Camera.from_projection(torch.zeros(3, 3), 1.65)


# KITTI tracking's calib/NNNN.txt: P rows keyed with a colon, the others with a space
TRACKING = (
    "P0: 7.215377e+02 0 6.095593e+02 0 0 7.215377e+02 1.72854e+02 0 0 0 1 0\n"
    "P1: 7.215377e+02 0 6.095593e+02 -3.875744e+02 0 7.215377e+02 1.72854e+02 0 0 0 1 0\n"
    "P2: 7.215377e+02 0 6.095593e+02 4.485728e+01 0 7.215377e+02 1.72854e+02 2.163791e-01 0 0 1 2.745884e-03\n"
    "P3: 7.215377e+02 0 6.095593e+02 -3.395242e+02 0 7.215377e+02 1.72854e+02 2.199936e+00 0 0 1 2.729905e-03\n"
    "R_rect 9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 7.402527e-03 "
    "4.351614e-03 9.999631e-01\n"
    "Tr_velo_cam\t7.533745e-03 -9.999714e-01 -6.166020e-04 -4.069766e-03 1.480249e-02 7.280733e-04 -9.998902e-01 "
    "-7.631618e-02 9.998621e-01 7.523790e-03 1.480755e-02 -2.717806e-01\n"
)


def test_kitti_tracking_calibration(tmp_path):
    """KITTI tracking keys its R_rect and Tr_velo_cam rows with a space, not a colon: the reader
    took them for unlabelled rows of numbers and refused the file ('R_rect' is no number), so no
    KITTI tracking sequence could be read. The dataset picks camera 2 there, as for a labelled file."""
    (tmp_path / "0000.txt").write_text(TRACKING)
    P = read_kitti_calibration(tmp_path / "0000.txt", 2)
    assert P[0, 3] == pytest.approx(44.85728) and P[2, 3] == pytest.approx(2.745884e-3)
    assert read_kitti_calibration(tmp_path / "0000.txt", 1)[0, 3] == pytest.approx(-387.5744)
    from fsof_torch.data.folders import ImageFolderDataset
    from fsof_torch.io import write_image

    (tmp_path / "frames").mkdir()
    for k in range(2):
        write_image(tmp_path / "frames" / f"{k:06d}.png", torch.zeros(3, 375, 1242))
    camera = ImageFolderDataset(tmp_path / "frames", tmp_path / "0000.txt").camera
    assert float(camera.cx[0]) == pytest.approx(609.5593)
    # a row of numbers keyed by a name without a colon is still a key, not an unlabelled row
    (tmp_path / "spaced.txt").write_text("P0 1 0 2 0 0 1 3 0 0 0 1 0\n")
    assert read_kitti_calibration(tmp_path / "spaced.txt", 0)[1, 2] == 3.0


@pytest.mark.parametrize("text, cam, message", [
    (CAM_TO_CAM + CAM_TO_CAM.splitlines()[5] + "\n", 2, r"line 7 of '.*' repeats the key 'P_rect_02' of line 6"),
    (ODOMETRY_LABELLED + "P2: 1 0 1 0 0 1 1 0 0 0 1 0\n", 2, r"line 5 of '.*' repeats the key 'P2' of line 3"),
    (ODOMETRY_LABELLED + "P2: 1 0 1 0 0 1 1 0 0 0 1 0\n", 0, r"line 5 of '.*' repeats the key 'P2' of line 3"),
    ("".join(ODOMETRY_LABELLED.splitlines(True)[:2]) + ODOMETRY_UNLABELLED * 2, 2,
     r"'.*' has no P_rect_02 or P2 row \(its unlabelled rows are not counted: the file labels its P rows\)"),
    ("".join(ODOMETRY_UNLABELLED.splitlines(True)[:2]), 2,
     r"'.*' has no P_rect_02 or P2 row \(its 2 unlabelled row\(s\) are cameras 0 to 1, in order\)$"),
    (CAM_TO_CAM + ODOMETRY_LABELLED, 2, r"'.*' gives camera 2 twice, P_rect_02 \(line 6\) and P2 \(line 9\), with "
                                        r"different values; expected one of them, or both the same$"),
])
def test_kitti_calibration_repeated_or_mixed_rows(tmp_path, text, cam, message):
    """A repeated key once took the last row, and unlabelled rows were counted by position even
    beside labelled P rows (P0:, P1:, then rows taken as P2, P3)."""
    (tmp_path / "calib.txt").write_text(text)
    with pytest.raises(ValueError, match=rf"^path: {message}"):
        read_kitti_calibration(tmp_path / "calib.txt", cam)


def test_kitti_calibration_with_both_spellings_of_a_camera(tmp_path):
    """P_rect_0N and PN for one camera: the same values are one calibration; different ones were
    silently resolved to P_rect_0N (now an error, above). Other cameras' rows are not compared."""
    same = CAM_TO_CAM + "P2: " + CAM_TO_CAM.splitlines()[5].partition(":")[2].strip() + "\n"
    (tmp_path / "calib.txt").write_text(same)
    assert read_kitti_calibration(tmp_path / "calib.txt", 2)[0, 3] == pytest.approx(44.85728)
    (tmp_path / "other.txt").write_text(CAM_TO_CAM + ODOMETRY_LABELLED)
    # (P_rect_00 and P0, P_rect_02 and P2 differ there; camera 1 has only P1)
    assert read_kitti_calibration(tmp_path / "other.txt", 1)[0, 3] == pytest.approx(-379.8145)
    with pytest.raises(ValueError, match=r"gives camera 0 twice, P_rect_00 \(line 5\) and P0 \(line 7\)"):
        read_kitti_calibration(tmp_path / "other.txt", 0)


def test_kitti_calibration_with_a_byte_order_mark(tmp_path):
    """A UTF-8 byte-order mark once hid the key of the first row (P0 'missing')."""
    (tmp_path / "calib.txt").write_bytes(("\ufeff" + ODOMETRY_LABELLED).encode("utf-8"))
    assert read_kitti_calibration(tmp_path / "calib.txt", 0)[0, 0] == pytest.approx(707.0912)
    (tmp_path / "unlabelled.txt").write_bytes(("\ufeff" + ODOMETRY_UNLABELLED).encode("utf-8"))
    assert read_kitti_calibration(tmp_path / "unlabelled.txt", 0)[0, 0] == pytest.approx(707.0912)


def test_kitti_calibration_skips_every_row_that_is_no_projection(tmp_path):
    """Rows other than P_rect_0N / PN are not read: a note keyed 'Program' once failed the file
    ('is not a calibration row': a key starting with P was parsed as numbers), and KITTI raw's
    calib_cam_to_cam.txt and calib_velo_to_cam.txt concatenated failed on the second calib_time
    ('repeats the key'). Windows line endings and trailing blanks read the same."""
    P2 = [721.5377, 0.0, 609.5593, 44.85728, 0.0, 721.5377, 172.854, 0.2163791, 0.0, 0.0, 1.0, 0.002745884]
    velo_to_cam = "calib_time: 15-Mar-2012 11:37:16\nR: 1 0 0 0 1 0 0 0 1\nT: -0.004 -0.076 -0.27\n"
    text = ("Program: stereo calibrator v1.2\r\nPose_source: GPS/IMU\t \r\n" + CAM_TO_CAM.replace("\n", "  \r\n")
            + velo_to_cam)
    (tmp_path / "calib.txt").write_bytes(text.encode())
    assert read_kitti_calibration(tmp_path / "calib.txt", 2).flatten().tolist() == P2
    assert Camera.from_kitti(tmp_path / "calib.txt", cam=0).fx.tolist() == [700.0]
    # a projection row is still read as one: malformed or given twice, it raises
    (tmp_path / "bad.txt").write_text(CAM_TO_CAM.replace("P_rect_00: 7", "P_rect_00: x"))
    with pytest.raises(ValueError, match=r"line \d+ of '.*' is not a calibration row: 'P_rect_00: x"):
        read_kitti_calibration(tmp_path / "bad.txt", 2)
    (tmp_path / "twice.txt").write_text(CAM_TO_CAM + "P_rect_00: 1 0 1 0 0 1 1 0 0 0 1 0\n")
    with pytest.raises(ValueError, match="repeats the key 'P_rect_00' of line 5"):
        read_kitti_calibration(tmp_path / "twice.txt", 2)


# --- scaled: rendering geometry ----------------------------------------------------------------------

@pytest.mark.parametrize("sx, sy", [(3, 3), (3, 5), (5, 3)])
def test_scaled_matches_resized_rendering(sx, sy):
    """Pixel centres map as u' + 0.5 = s (u + 0.5): with odd integer s, pixel (u, v) of the original
    image is pixel (s u + (s-1)/2, s v + (s-1)/2) of the resized one, where the flow is s times larger."""
    H, W = 12, 20
    cam = Camera(_K(15.0, 16.0, 9.3, 4.1), 1.6, 0.03, -0.02)
    flow, valid = displacement_flow(cam, 0.1, 1.1, 0.02, (H, W))
    big = cam.scaled(sx, sy)
    flow_big, valid_big = displacement_flow(big, 0.1, 1.1, 0.02, (H * sy, W * sx))
    iu, iv = (sx - 1) // 2, (sy - 1) // 2
    sub = flow_big[:, :, iv::sy, iu::sx]
    assert sub.shape == flow.shape
    assert torch.equal(valid_big[:, :, iv::sy, iu::sx], valid)
    torch.testing.assert_close(sub[:, 0], sx * flow[:, 0], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(sub[:, 1], sy * flow[:, 1], rtol=1e-10, atol=1e-10)
    # and back down: scaling by 1/s recovers the original intrinsics
    torch.testing.assert_close(big.scaled(1 / sx, 1 / sy).K, cam.K, rtol=1e-12, atol=1e-12)


def test_scaled_values():
    cam = Camera(_K(700.0, 710.0, 600.0, 180.0), 1.65)
    half = cam.scaled(0.5)
    assert half.fx.tolist() == [350.0] and half.fy.tolist() == [355.0]
    assert half.cx.tolist() == [0.5 * 600.5 - 0.5] and half.cy.tolist() == [0.5 * 180.5 - 0.5]
    assert half.height.tolist() == [1.65]
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="sx: expected a finite scale > 0"):
            cam.scaled(bad, 1.0)
    with pytest.raises(ValueError, match="sy: expected a finite scale > 0"):
        cam.scaled(1.0, 0.0)


# --- exceptions ------------------------------------------------------------------------------------

def test_exceptions():
    with pytest.raises(TypeError, match="K: expected a torch.Tensor"):
        Camera([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]], 1.65)
    with pytest.raises(TypeError, match="K: expected a floating-point tensor, got dtype torch.int64"):
        Camera(torch.eye(3, dtype=torch.int64), 1.65)
    with pytest.raises(ValueError, match=r"K: expected shape \(3, 3\) or \(B, 3, 3\), got \(2, 2\)"):
        Camera(torch.eye(2), 1.65)
    with pytest.raises(ValueError, match=r"K: expected shape \(3, 3\) or \(B, 3, 3\), got \(1, 1, 3, 3\)"):
        Camera(torch.eye(3).reshape(1, 1, 3, 3), 1.65)
    with pytest.raises(ValueError, match="K: expected focal lengths f_x, f_y > 0"):
        Camera(_K(fx=0.0), 1.65)
    with pytest.raises(ValueError, match="K: expected focal lengths f_x, f_y > 0"):
        Camera(_K(fy=-5.0), 1.65)
    bad = _K()
    bad[1, 0] = 0.1
    with pytest.raises(ValueError, match="K: expected an upper-triangular intrinsic matrix"):
        Camera(bad, 1.65)
    bad = _K()
    bad[2, 2] = 2.0
    with pytest.raises(ValueError, match="K: expected an upper-triangular intrinsic matrix"):
        Camera(bad, 1.65)
    bad = _K()
    bad[0, 2] = float("nan")
    with pytest.raises(ValueError, match="K: expected finite values"):
        Camera(bad, 1.65)
    with pytest.raises(ValueError, match="height: expected values > 0, got \\[0.0\\]"):
        Camera(_K(), 0.0)
    with pytest.raises(ValueError, match="height: expected values > 0"):
        Camera(_K(), torch.tensor([1.6, -1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="height: expected finite values"):
        Camera(_K(), float("inf"))
    with pytest.raises(ValueError, match="pitch: expected finite values"):
        Camera(_K(), 1.65, 0.0, float("nan"))
    with pytest.raises(TypeError, match="roll: expected a float tensor or a Python number"):
        Camera(_K(), 1.65, torch.tensor([1]))
    with pytest.raises(TypeError, match="height: expected a float, or a tensor of shape"):
        Camera(_K(), "1.65")
    with pytest.raises(ValueError, match=r"roll: expected a scalar or shape \(B,\)"):
        Camera(_K(), 1.65, torch.zeros(2, 2))
    with pytest.raises(ValueError, match="mismatched batch sizes: K=2, height=3"):
        Camera(_K().expand(2, 3, 3), torch.ones(3, dtype=torch.float64))


# --- cardinality -----------------------------------------------------------------------------------

@pytest.mark.parametrize("B", [1, 3])
def test_cardinality(B):
    K = _K().expand(B, 3, 3)
    cam = Camera(K, torch.linspace(1.4, 1.8, B, dtype=torch.float64), 0.01, torch.zeros(B, dtype=torch.float64))
    assert cam.batch_size == B and cam.roll.shape == (B,) and cam.pitch.shape == (B,)
    assert cam.mounting().shape == (B, 3, 3) and cam.K_inv().shape == (B, 3, 3)
    assert cam.horizon_row().shape == (B,)
    assert cam.scaled(0.5).K.shape == (B, 3, 3)
    cam = Camera(_K(), torch.ones(B, dtype=torch.float64))  # K of batch 1 broadcast
    assert cam.K.shape == (B, 3, 3)


def test_gradient_through_camera():
    fx = torch.tensor(700.0, dtype=torch.float64, requires_grad=True)
    h = torch.tensor([1.6], dtype=torch.float64, requires_grad=True)
    z = torch.zeros((), dtype=torch.float64)
    K = torch.stack([fx, z, z + 600, z, fx, z + 180, z, z, z + 1]).reshape(3, 3)
    cam = Camera(K, h, 0.01)
    (cam.scaled(0.5).fx.sum() + cam.height.sum()).backward()
    assert fx.grad.item() == pytest.approx(0.5) and h.grad.tolist() == [1.0]


def test_a_camera_of_learnable_values_is_deep_copied():
    """A camera built from leaf tensors that require grad (a learnable height, as a training
    model holds one) kept views of them, which copy.deepcopy refuses: deep-copying the model or
    batch that held it raised a RuntimeError."""
    import copy

    class Model(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.height = torch.nn.Parameter(torch.tensor([1.6, 1.7], dtype=torch.float64))
            self.camera = Camera(_K().expand(2, 3, 3), self.height, torch.zeros(2, dtype=torch.float64))

    model = Model()
    assert model.camera.height is model.height
    copied = copy.deepcopy(model)
    assert copied.camera.height is copied.height and copied.height is not model.height
    assert copied.camera.height.requires_grad and torch.equal(copied.camera.height, model.height)
    assert torch.equal(copied.camera.K, model.camera.K) and copied.camera.batch_size == 2
    # a field broadcast to the batch is a view of what was given (of which torch keeps the graph)
    assert Camera(_K(), torch.tensor([1.6], requires_grad=True), torch.zeros(3)).height.shape == (3,)


# --- values whose geometry overflows or underflows in the camera's dtype ---------------------------

from fsof_torch.geometry.camera import camera_value_bounds  # noqa: E402


@pytest.mark.parametrize("dtype, field, value", [
    (torch.float32, "cx", 1e21), (torch.float32, "cy", -1e21), (torch.float32, "height", 1e-38),
    (torch.float32, "fx", 1e38), (torch.float64, "fx", 1e-171), (torch.float64, "height", 1e-300),
    (torch.float64, "fy", 1e200)])
def test_values_that_break_the_geometry_are_rejected(dtype, field, value):
    """Each once passed the checks and gave NaN flow at pixels marked valid."""
    K = _K(dtype=dtype)
    height = 1.65
    if field == "height":
        height = value
    else:
        i, j = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}[field]
        K[i, j] = value
    name = "height" if field == "height" else "K"
    with pytest.raises(ValueError, match=rf"{name}: expected .* for a {dtype} camera"):
        Camera(K, height)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bounds_follow_the_dtype_and_the_geometry_stays_finite_inside_them(dtype):
    lo, hi = camera_value_bounds(dtype)
    finfo = torch.finfo(dtype)
    # no product of five factors overflows or leaves the normal range
    assert hi ** 5 <= finfo.max and lo ** 5 >= finfo.tiny
    assert lo == 1 / hi and finfo.max ** 0.2 / 2 < hi <= finfo.max ** 0.2
    inside = {"fx": [hi, lo], "cx": [hi, -hi], "height": [hi, lo]}
    for field, values in inside.items():
        for value in values:
            K, height = _K(dtype=dtype), 1.65
            if field == "height":
                height = value
            else:
                K[(0, 0) if field == "fx" else (0, 2)] = value
                if field == "fx":
                    K[1, 1] = value
            cam = Camera(K, height)
            flow, valid = displacement_flow(cam, 0.1, 1.0, 0.01, (24, 40))
            vel, _ = velocity_flow(cam, 10.0, 0.01, 2.7, (24, 40))
            assert torch.isfinite(flow).all() and torch.isfinite(vel).all(), (field, value)
            # just outside: rejected
            outside = value * 1.01 if value in (hi, -hi) else value / 1.01
            if field == "height":
                height = outside
            else:
                K[(0, 0) if field == "fx" else (0, 2)] = outside
            with pytest.raises(ValueError, match="for a .* camera"):
                Camera(K, height)


def test_cast_to_a_narrower_dtype_checks_its_bounds():
    cam = Camera(_K(fx=1e10), 1.65)
    assert cam.to(torch.float64) is cam
    with pytest.raises(ValueError, match="K: expected focal lengths in .* for a torch.float32 camera"):
        cam.to(torch.float32)
    assert Camera(_K(), 1.65).to(torch.bfloat16).dtype == torch.float32  # as the constructor does


def test_scaled_needs_numbers():
    """cam.scaled("2") was accepted silently (float("2") == 2)."""
    cam = Camera(_K(), 1.65)
    with pytest.raises(TypeError, match="sx: expected a number \\(the resize factor\\), got str '2'"):
        cam.scaled("2")
    with pytest.raises(TypeError, match="sy: expected a number"):
        cam.scaled(2.0, True)


def test_kitti_calibration_bad_camera_index_and_binary_file(tmp_path):
    (tmp_path / "a.txt").write_text(CAM_TO_CAM)
    # Camera.from_kitti(cam=2.0) raised a ValueError: a float, str or bool index is a TypeError
    for cam, error in (("x", TypeError), (2.0, TypeError), (True, TypeError), (-1, ValueError)):
        with pytest.raises(error, match=rf"cam: expected 0..3, got {cam!r}"):
            read_kitti_calibration(tmp_path / "a.txt", cam)
        with pytest.raises(error, match=rf"cam: expected 0..3, got {cam!r}"):
            Camera.from_kitti(tmp_path / "a.txt", cam=cam)
    # a 0-d integer tensor is its int, as for every whole-number option (docs/reliability.md;
    # it was a TypeError "got tensor(2)"); a 0-d float or bool tensor stays a TypeError
    assert torch.equal(read_kitti_calibration(tmp_path / "a.txt", torch.tensor(2)),
                       read_kitti_calibration(tmp_path / "a.txt", 2))
    assert Camera.from_kitti(tmp_path / "a.txt", cam=torch.tensor(0)).fx.tolist() == [700.0]
    for cam, error, quoted in ((torch.tensor(5), ValueError, "5"), (torch.tensor(2.0), TypeError, "2.0"),
                               (torch.tensor(True), TypeError, "tensor(True)")):
        with pytest.raises(error, match=rf"cam: expected 0..3, got {re.escape(quoted)}"):
            Camera.from_kitti(tmp_path / "a.txt", cam=cam)
    (tmp_path / "b.txt").write_bytes(bytes(range(256)))
    with pytest.raises(ValueError, match=r"path: '.*b.txt' is not a text calibration file"):
        read_kitti_calibration(tmp_path / "b.txt")
    with pytest.raises(ValueError, match=r"path: '.*b.txt' is not a text calibration file"):
        Camera.from_kitti(tmp_path / "b.txt")


def test_meta_device_shape_inference():
    """Value checks once called .item() on meta tensors; torch skips them there, and so does Camera."""
    cam = Camera(_K(dtype=torch.float32).to("meta"), torch.ones(2, device="meta"))
    assert cam.device.type == "meta" and cam.batch_size == 2
    assert cam.scaled(0.5).K.shape == (2, 3, 3) and cam.horizon_row().shape == (2,)
    assert cam.to(torch.float64).dtype == torch.float64


def test_meta_camera_cannot_move_to_a_real_device():
    """A meta camera beside real tensors once failed inside torch ("Cannot copy out of meta tensor")."""
    cam = Camera(_K(dtype=torch.float32).to("meta"), 1.65)
    with pytest.raises(ValueError, match="camera: a camera on the meta device has shapes but no values to move to another device"):
        cam.to("cpu")
    assert cam.to(torch.float64).device.type == "meta"


def test_camera_geometry_keeps_its_precision_under_autocast():
    """Under a bfloat16 autocast the camera's transforms, its mounting and what is built on them
    give what they give without it: geometry never runs in half precision."""
    from fsof_torch import ego_motion_from_pose, mounting_matrix, road_flow

    cam = Camera(torch.tensor([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]]), 1.65,
                 0.013, -0.021)
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([0.03, -0.01, -1.2])
    odometry = {"x_d": 0.05, "z_d": 1.2, "yaw": 0.01}

    def compute():
        return {"scaled": cam.scaled(0.5).K, "cropped": cam.cropped(3, 5).K, "padded": cam.padded(3, 0, 3, 1).K,
                "mounting": cam.mounting(), "matrix": mounting_matrix(cam.roll, cam.pitch),
                "horizon": cam.horizon_row(), "pose": torch.stack(ego_motion_from_pose(T[None], cam)[:3]),
                "flow": road_flow(cam.scaled(0.5), odometry, (188, 621))[0]}

    plain = compute()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        cast = compute()
    for name, value in plain.items():
        assert cast[name].dtype == value.dtype == torch.float32, name
        assert torch.equal(cast[name], value), name


def test_an_empty_camera_batch_is_refused():
    """A batch of no cameras, or an expansion to none, is an error naming it (not a crash later
    in the geometry)."""
    from fsof_torch import road_flow

    cam = Camera(torch.tensor([[700.0, 0, 320], [0, 700.0, 120], [0, 0, 1]]), 1.65)
    with pytest.raises(ValueError, match="K: expected a batch of at least 1, got 0"):
        Camera(cam.K.expand(0, 3, 3), 1.65)
    for size in (0, -1):
        with pytest.raises(ValueError, match=f"batch_size: expected an int >= 1, got {size!r}"):
            cam.expand(size)
    with pytest.raises(ValueError, match="x_d: expected a batch of at least 1, got 0"):
        road_flow(cam, {k: torch.zeros(0) for k in ("x_d", "z_d", "yaw")}, (48, 160))


def test_from_projection_names_a_bad_matrix():
    with pytest.raises(TypeError, match="P: expected a .3, 4. or .B, 3, 4. tensor or array of numbers, got str 'abc'"):
        Camera.from_projection("abc", 1.65)
    with pytest.raises(ValueError, match=r"P: expected shape \(3, 4\) or \(B, 3, 4\), got \(4,\)"):
        Camera.from_projection(torch.zeros(4), 1.65)


def test_cameras_compare_by_identity_and_hash():
    """Cameras hold tensors: ``==`` compares identity (as nn.Module does) instead of raising on a
    tensor's truth value, and a camera can key a dict."""
    a, b = Camera(_K(), 1.65), Camera(_K(), 1.65)
    assert a == a and a != b and not (a == b)
    assert {a: 1, b: 2}[b] == 2 and len({a, b, a}) == 2
    assert a in [b, a] and b not in [a]
    assert all(torch.equal(getattr(a, n), getattr(b, n)) for n in ("K", "height", "roll", "pitch"))


def test_cast_to_half_precision_keeps_the_values():
    """A half precision target gives a float32 camera without rounding through half precision
    (bfloat16 once turned f_x 721.54 into 720)."""
    cam = Camera(_K(), 1.65, 0.0123, -0.021)
    for half in (torch.float16, torch.bfloat16):
        c = cam.to(half)
        assert c.dtype == torch.float32
        for name in ("K", "height", "roll", "pitch"):
            assert torch.equal(getattr(c, name), getattr(cam, name).float()), name
        c32 = cam.to(torch.float32)
        assert c32.to(half) is c32 and c32.to(dtype=half, device="cpu") is c32
    assert cam.to(torch.zeros(1, dtype=torch.bfloat16)).K[0, 0, 0].item() == pytest.approx(721.5377, abs=1e-4)
    copied = cam.to(cam.dtype, copy=True)  # as Tensor.to: a copy even without a change
    assert copied is not cam and torch.equal(copied.K, cam.K) and copied.K.data_ptr() != cam.K.data_ptr()


def test_repeat_needs_a_positive_int():
    cam = Camera(_K(), 1.65)
    for times in (0, -1):
        with pytest.raises(ValueError, match=f"^times: expected an int >= 1, got {times}"):
            cam.repeat(times)
    for times in (2.0, True, "2"):
        with pytest.raises(TypeError, match="^times: expected an int, got"):
            cam.repeat(times)
    assert cam.repeat(2).batch_size == 2


def test_padded_and_cropped_check_the_new_principal_point():
    """A shift beyond the dtype's bounds once stored NaN in K (padded(10**39, 0) in float32)."""
    cam = Camera(_K(dtype=torch.float32), 1.65)
    with pytest.raises(ValueError, match=r"^left, top: the camera padded by \(10{39}, 0\) px is out of range: "
                                         r"K: expected finite values"):
        cam.padded(10 ** 39, 0)
    with pytest.raises(ValueError, match=r"^left, top: the camera cropped by \(0, 67108864\) px is out of range: "
                                         r"K: expected \|principal point\|"):
        cam.cropped(0, 2 ** 26)
    assert cam.padded(2 ** 20, 3).cx.item() == pytest.approx(609.5593 + 2 ** 20)


def test_expand_takes_numpy_integers_and_refuses_bools_and_floats():
    """Once expand(np.int64(3)) was refused while repeat took it, and expand(True) was a ValueError."""
    import numpy as np

    cam = Camera(_K(), 1.65)
    assert cam.expand(np.int64(3)).batch_size == 3 and cam.expand(np.int32(1)) is cam
    for size in (1.5, 2.0, True, "2"):
        with pytest.raises(TypeError, match="^batch_size: expected an int, got"):
            cam.expand(size)


@pytest.mark.parametrize("name", ["roll", "pitch"])
@pytest.mark.parametrize("value", [math.pi / 2, -math.pi / 2, 3.0, -1.7, 10.0])
def test_angles_beyond_a_quarter_turn_are_refused(name, value):
    """horizon_row says pixels below it see the road; with |roll| or |pitch| >= π/2 that was false
    (roll 3: 2117 valid road pixels against 2683 below the row; pitch 1.7: none against all)."""
    symbol = {"roll": "θ", "pitch": "β"}[name]
    with pytest.raises(ValueError, match=rf"^{name}: expected \|{symbol}\| < π/2 rad .*, got \[{value!r}\]$"):
        Camera(_K(), 1.65, **{name: value})
    with pytest.raises(ValueError, match=f"^{name}: expected"):
        Camera(_K(dtype=torch.float32), 1.65, **{name: torch.tensor([0.1, value], dtype=torch.float32)})
    with pytest.raises(ValueError, match=f"^{name}: expected"):
        Camera(_K(), 1.65).replace(**{name: value})
    with pytest.raises(ValueError, match=f"^{name}: expected finite values"):  # NaN: its own message
        Camera(_K(), 1.65, **{name: float("nan")})


@pytest.mark.parametrize("roll, pitch", [(1.4, 0.0), (-1.3, 0.0), (0.0, 1.2), (0.0, -1.4), (0.7, -0.8)])
def test_horizon_row_separates_the_road_for_every_accepted_angle(roll, pitch):
    """Within the accepted quarter turn the horizon row's promise holds: the road flow's valid
    pixels are exactly those strictly below it, column by column."""
    K = _K(72.15, 72.15, 60.9, 17.3)
    cam = Camera(K, 1.65, roll=roll, pitch=pitch)
    size = (40, 120)
    _, valid = displacement_flow(cam, 0.0, 0.01, 0.0, size)
    rows = cam.horizon_row(torch.arange(size[1], dtype=torch.float64))
    below = torch.arange(size[0], dtype=torch.float64)[:, None] > rows[None, :]
    assert torch.equal(valid[0, 0], below)


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_rotation_matrices_of_half_precision_angles_are_computed_in_float32(half):
    """Once a float16 angle gave a float16 rotation (orthonormal to 1e-3; bfloat16 6e-3)."""
    roll, pitch = torch.tensor([0.3, 1.0], dtype=half), torch.tensor([0.05, -0.2], dtype=half)
    for got, want in ((roll_matrix(roll), roll_matrix(roll.float())), (pitch_matrix(pitch), pitch_matrix(pitch.float())),
                      (mounting_matrix(roll, pitch), mounting_matrix(roll.float(), pitch.float()))):
        assert got.dtype == torch.float32
        assert torch.equal(got, want)
    M = mounting_matrix(roll, pitch).double()
    assert (M @ M.transpose(-1, -2) - torch.eye(3, dtype=torch.float64)).abs().max() < 1e-6
    # float32 and float64 angles keep their dtype (and values)
    t = torch.tensor([0.3], dtype=torch.float64)
    assert roll_matrix(t).dtype == torch.float64 and roll_matrix(t.float()).dtype == torch.float32


def test_from_projection_and_from_kitti_name_their_own_arguments(tmp_path):
    """A bad projection's errors named K (the constructor's argument), and from_kitti(dtype="float32")
    raised torch's own TypeError naming as_tensor."""
    bad = torch.tensor([[1.0, 0, 2, 0], [0, -1.0, 3, 0], [0, 0, 1.0, 0]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^P: its first three columns are K, expected focal lengths f_x, f_y > 0"):
        Camera.from_projection(bad, 1.65)
    with pytest.raises(TypeError, match="^P: expected a floating-point tensor, got dtype torch.int64"):
        Camera.from_projection(torch.zeros(3, 4, dtype=torch.int64), 1.65)
    with pytest.raises(ValueError, match=r"^P: expected shape \(3, 4\) or \(B, 3, 4\), got \(1, 2, 3, 4\)"):
        Camera.from_projection(torch.zeros(1, 2, 3, 4), 1.65)
    with pytest.raises(ValueError, match="^height: expected values > 0"):  # the other arguments keep their names
        Camera.from_projection(torch.eye(3, 4, dtype=torch.float64), 0.0)
    path = tmp_path / "calib.txt"
    path.write_text(ODOMETRY_LABELLED)
    for dtype in ("float32", torch.int32, 32):
        with pytest.raises(TypeError, match=f"^dtype: expected a floating-point torch.dtype .*, got .*{dtype!s}"):
            Camera.from_kitti(path, dtype=dtype)
    assert Camera.from_kitti(path, dtype=torch.float32).dtype == torch.float32
    assert Camera.from_kitti(path, dtype=None).dtype == torch.float64
