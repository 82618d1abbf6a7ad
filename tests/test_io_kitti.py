"""fsof_torch.io.kitti: KITTI flow PNG (1/64 px), poses, calibration; checks; the shared sample."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fsof_torch.geometry.camera import Camera
from fsof_torch.io import (
    KITTI_FLOW_MAX,
    KITTI_FLOW_MIN,
    read_kitti_calibration,
    read_kitti_flow,
    read_kitti_poses,
    write_kitti_calibration,
    write_kitti_flow,
    write_kitti_poses,
)

STEP = 1.0 / 64


def _flow(h, w, seed=0, scale=40.0):
    g = torch.Generator().manual_seed(seed)
    flow = torch.randn(2, h, w, generator=g, dtype=torch.float64) * scale
    valid = torch.rand(1, h, w, generator=g) > 0.3
    return flow, valid


class TestSmoke:
    def test_round_trip_to_one_64th(self, tmp_path):
        flow, valid = _flow(20, 33)
        write_kitti_flow(tmp_path / "f.png", flow, valid)
        back, back_valid = read_kitti_flow(tmp_path / "f.png")
        assert back.dtype == torch.float32 and back.shape == (2, 20, 33) and back_valid.shape == (1, 20, 33)
        assert torch.equal(back_valid, valid)
        err = (back.double() - flow).abs()[valid.expand(2, -1, -1)]
        assert float(err.max()) <= STEP / 2 + 1e-9
        assert back[~valid.expand(2, -1, -1)].eq(0).all()

    def test_values_on_the_grid_are_exact(self, tmp_path):
        flow = torch.randint(-512 * 64, 512 * 64, (2, 7, 5), generator=torch.Generator().manual_seed(0)).double() / 64
        write_kitti_flow(tmp_path / "f.png", flow)
        back, valid = read_kitti_flow(tmp_path / "f.png")
        assert valid.all() and torch.equal(back.double(), flow)

    def test_default_valid_is_finite(self, tmp_path):
        flow = torch.zeros(2, 3, 4)
        flow[0, 1, 2] = float("nan")
        write_kitti_flow(tmp_path / "f.png", flow)
        _, valid = read_kitti_flow(tmp_path / "f.png")
        assert int((~valid).sum()) == 1 and not bool(valid[0, 1, 2])


class TestFeature:
    def test_encoding_matches_design(self, tmp_path):
        """DESIGN.md §8, checked on the raw channels: B = valid, G = v·64 + 2^15, R = u·64 + 2^15."""
        flow = torch.tensor([[[1.5, -2.25]], [[-0.5, 100.0]]])
        write_kitti_flow(tmp_path / "f.png", flow, torch.tensor([[[True, False]]]))
        raw = cv2.imread(str(tmp_path / "f.png"), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (1, 2, 3)
        assert raw[0, 0].tolist() == [1, int(-0.5 * 64 + 2**15), int(1.5 * 64 + 2**15)]
        assert raw[0, 1, 0] == 0

    def test_decoding_of_raw_channels(self, tmp_path):
        """The reader on a PNG written here channel by channel: u = (R - 2^15) / 64, v = (G - 2^15) / 64,
        valid where B is non-zero (the devkit's min(B, 1): any non-zero value), flow 0 elsewhere."""
        raw = np.zeros((1, 3, 3), np.uint16)
        raw[0, 0] = [1, 2**15 + 96, 2**15 - 32]   # u = -0.5, v = 1.5
        raw[0, 1] = [7, 2**15 - 6400, 65535]      # u = 511.984375, v = -100
        raw[0, 2] = [0, 2**15 + 64, 2**15 + 64]   # not valid
        cv2.imwrite(str(tmp_path / "f.png"), raw)
        flow, valid = read_kitti_flow(tmp_path / "f.png")
        assert valid.tolist() == [[[True, True, False]]]
        assert flow[0, 0].tolist() == [-0.5, 511.984375, 0.0] and flow[1, 0].tolist() == [1.5, -100.0, 0.0]

    @settings(max_examples=15, deadline=None)
    @given(h=st.integers(1, 9), w=st.integers(1, 9), seed=st.integers(0, 10_000))
    def test_round_trip_any(self, tmp_path_factory, h, w, seed):
        path = tmp_path_factory.mktemp("k") / "f.png"
        flow, valid = _flow(h, w, seed, scale=100.0)
        flow = flow.clamp(-511, 511)
        write_kitti_flow(path, flow, valid)
        back, back_valid = read_kitti_flow(path)
        assert torch.equal(back_valid, valid)
        err = (back.double() - flow).abs()[valid.expand(2, -1, -1)]
        assert err.numel() == 0 or float(err.max()) <= STEP / 2 + 1e-9

    def test_poses_round_trip_and_relative_motion(self, tmp_path):
        from fsof_torch.geometry.egomotion import ego_motion_from_pose

        c, s = np.cos(0.01), np.sin(0.01)
        P0 = torch.eye(4, dtype=torch.float64)
        P1 = torch.tensor([[c, 0, s, 0.1], [0, 1, 0, 0], [-s, 0, c, 1.2], [0, 0, 0, 1]], dtype=torch.float64)
        write_kitti_poses(tmp_path / "poses.txt", torch.stack([P0, P1]))
        back = read_kitti_poses(tmp_path / "poses.txt")
        assert back.shape == (2, 4, 4) and back.dtype == torch.float64
        torch.testing.assert_close(back, torch.stack([P0, P1]), atol=1e-12, rtol=1e-11)
        ego = ego_motion_from_pose(back[:1], pose1=back[1:])
        # frame t is the world here: d is P1's translation, and p(t+1) = R_y(0.01)^T (p(t) - d) is
        # DESIGN.md's R_phi (p - d) with phi = 0.01
        assert float(ego.x_d) == pytest.approx(0.1, abs=1e-12)
        assert float(ego.z_d) == pytest.approx(1.2, abs=1e-12)
        assert float(ego.yaw) == pytest.approx(0.01, abs=1e-12)

    def test_poses_round_trip_bit_for_bit(self, tmp_path):
        """Poses were written to 13 significant digits (``%.12e``): a rendered sequence's poses.txt
        read back 5e-14 off the poses of its params files, and relative poses and odometry from it
        differed in their last digits from the pairs' own."""
        g = torch.Generator().manual_seed(3)
        angles = torch.rand(5, generator=g, dtype=torch.float64) * 0.3
        P = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
        P[:, 0, 0], P[:, 0, 2], P[:, 2, 0], P[:, 2, 2] = angles.cos(), angles.sin(), -angles.sin(), angles.cos()
        P[:, :3, 3] = torch.rand(5, 3, generator=g, dtype=torch.float64) * 100 - 50
        P[2, :3, 3] = torch.tensor([1e-300, -0.0, 123456789.123456789], dtype=torch.float64)
        write_kitti_poses(tmp_path / "poses.txt", P)
        back = read_kitti_poses(tmp_path / "poses.txt")
        assert torch.equal(back, P) and not torch.equal(back[2, 0, 3], torch.tensor(0.0, dtype=torch.float64))

    def test_poses_other_row_forms(self, tmp_path):
        T = torch.eye(4, dtype=torch.float64)
        T[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
        twelve = " ".join(map(str, T[:3].reshape(-1).tolist()))
        sixteen = " ".join(map(str, T.reshape(-1).tolist()))
        for rows in ([twelve] * 2, [f"0 {twelve}", f"1 {twelve}"], [sixteen] * 2, [f"0 {sixteen}", f"1.0 {sixteen}"]):
            (tmp_path / "p.txt").write_text(f"# comment\n{rows[0]}\n\n{rows[1]}\n")
            back = read_kitti_poses(tmp_path / "p.txt")
            assert back.shape == (2, 4, 4) and torch.equal(back, T.expand(2, 4, 4))

    @pytest.mark.parametrize("indices, line, why", [
        ((2, 0, 1), 1, "has the frame index '2'; expected 0"),
        ((0, 5, 10), 2, "has the frame index '5'; expected 1"),
        ((0, 0, 0), 2, "has the frame index '0'; expected 1"),
        ((0.5, 1, 2), 1, "has the frame index '0.5'; expected 0"),
        ((0, -3, 2), 2, "has the frame index '-3'; expected 1"),
        ((None, 1, None), 2, "has 13 numbers but line 1 has 12; expected rows of one length"),
        ((0, 1, "16"), 3, "has 17 numbers but line 1 has 13; expected rows of one length"),
    ])
    def test_poses_frame_index_counts_from_zero(self, tmp_path, indices, line, why):
        """The leading frame index was once dropped unread, so poses paired with frames by position
        whatever the indices said (out of order, gaps, repeats, fractions, rows with and without)."""
        rows = []
        for i, index in enumerate(indices):
            pose = f"1 0 0 0 0 1 0 0 0 0 1 {i}"
            rows.append(pose if index is None else f"{i} {pose} 0 0 0 1" if index == "16" else f"{index} {pose}")
        (tmp_path / "p.txt").write_text("\n".join(rows) + "\n")
        with pytest.raises(ValueError, match=rf"^path: line {line} of '.*p\.txt' {why}"):
            read_kitti_poses(tmp_path / "p.txt")

    def test_poses_with_a_byte_order_mark(self, tmp_path):
        """A UTF-8 byte-order mark (Windows editors) once made line 1 'not a row of numbers'."""
        (tmp_path / "p.txt").write_bytes("\ufeff0 1 0 0 0 0 1 0 0 0 0 1 5\n".encode("utf-8"))
        assert read_kitti_poses(tmp_path / "p.txt")[0, 2, 3] == 5

    @pytest.mark.parametrize("style,cam", [("cam_to_cam", 2), ("odometry", 0), ("odometry", 2)])
    def test_calibration_round_trip(self, tmp_path, kitti_K, style, cam):
        write_kitti_calibration(tmp_path / "c.txt", kitti_K, cam=cam, style=style)
        P = read_kitti_calibration(tmp_path / "c.txt", cam)
        torch.testing.assert_close(P[:, :3], kitti_K, atol=1e-9, rtol=1e-12)
        cam_obj = Camera.from_kitti(tmp_path / "c.txt", cam=cam)
        torch.testing.assert_close(cam_obj.K[0], kitti_K, atol=1e-9, rtol=1e-12)


class TestExceptions:
    def test_truncated_png(self, tmp_path):
        flow, valid = _flow(30, 40)
        write_kitti_flow(tmp_path / "f.png", flow, valid)
        data = (tmp_path / "f.png").read_bytes()
        (tmp_path / "cut.png").write_bytes(data[: len(data) - 40])
        with pytest.raises(ValueError, match=r"cut\.png.*truncated PNG"):
            read_kitti_flow(tmp_path / "cut.png")

    def test_8bit_png(self, tmp_path):
        cv2.imwrite(str(tmp_path / "eight.png"), np.zeros((4, 4, 3), np.uint8))
        with pytest.raises(ValueError, match=r"eight\.png.*uint8.*8-bit.*16-bit"):
            read_kitti_flow(tmp_path / "eight.png")

    @pytest.mark.parametrize("channels", [1, 4])
    def test_channel_count(self, tmp_path, channels):
        shape = (4, 4) if channels == 1 else (4, 4, channels)
        cv2.imwrite(str(tmp_path / "c.png"), np.zeros(shape, np.uint16))
        with pytest.raises(ValueError, match=rf"c\.png.*{channels} channel"):
            read_kitti_flow(tmp_path / "c.png")

    def test_write_checks(self, tmp_path):
        with pytest.raises(ValueError, match="holds"):
            write_kitti_flow(tmp_path / "f.png", torch.full((2, 2, 2), 600.0))
        with pytest.raises(ValueError, match="valid: expected shape"):
            write_kitti_flow(tmp_path / "f.png", torch.zeros(2, 2, 2), torch.ones(1, 3, 2, dtype=torch.bool))
        with pytest.raises(TypeError, match="valid: expected a bool"):
            write_kitti_flow(tmp_path / "f.png", torch.zeros(2, 2, 2), torch.ones(1, 2, 2))
        nan = torch.full((2, 2, 2), float("nan"))
        with pytest.raises(ValueError, match="finite values at valid pixels"):
            write_kitti_flow(tmp_path / "f.png", nan, torch.ones(1, 2, 2, dtype=torch.bool))
        assert not (tmp_path / "f.png").exists()

    @pytest.mark.parametrize("name", ["f.jpg", "f.tif", "f.bmp", "f"])
    def test_flow_only_to_png(self, tmp_path, name):
        """write_kitti_flow("f.jpg") once wrote an 8-bit JPEG that no reader takes as flow."""
        with pytest.raises(ValueError, match=r"path: a KITTI flow is written as \.png; got the suffix"):
            write_kitti_flow(tmp_path / name, torch.zeros(2, 4, 4))
        assert list(tmp_path.iterdir()) == []

    @pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
    def test_non_finite_only_matters_at_valid_pixels(self, tmp_path, bad):
        """A non-finite value at an invalid pixel is written as 0; the same value at a valid
        pixel raises, whichever channel holds it."""
        flow = torch.tensor([[[1.0, 2.0], [3.0, 4.0]], [[0.5, 0.25], [-1.0, 6.0]]])
        valid = torch.tensor([[[True, False], [True, True]]])
        flow[0, 0, 1] = bad
        write_kitti_flow(tmp_path / "f.png", flow, valid)
        back, back_valid = read_kitti_flow(tmp_path / "f.png")
        assert torch.equal(back_valid, valid) and back[:, 0, 1].eq(0).all()
        assert torch.equal(back[:, valid[0]], flow[:, valid[0]])
        for channel in (0, 1):
            worse = flow.clone()
            worse[channel, 1, 0] = bad
            with pytest.raises(ValueError, match="finite values at valid pixels"):
                write_kitti_flow(tmp_path / "g.png", worse, valid)

    @pytest.mark.parametrize("value, shown", [(512.0001, r"512\.0001"), (-512.00001, r"-512\.00001"),
                                              (511.99, r"511\.99")])
    def test_out_of_range_message_shows_the_value(self, tmp_path, value, shown):
        """The range is printed with enough digits to be outside the bound (not '[-512, 512]')."""
        flow = torch.zeros(2, 2, 2, dtype=torch.float64)
        flow[1, 0, 1] = value
        with pytest.raises(ValueError, match=rf"got the range \[.*{shown}.*\] at valid pixels"):
            write_kitti_flow(tmp_path / "f.png", flow)
        flow[1, 0, 1] = KITTI_FLOW_MAX if value > 0 else KITTI_FLOW_MIN  # the bounds themselves are accepted
        write_kitti_flow(tmp_path / "f.png", flow)

    def test_out_of_range_invalid_pixels_are_fine(self, tmp_path):
        flow = torch.full((2, 2, 2), 1e6)
        write_kitti_flow(tmp_path / "f.png", flow, torch.zeros(1, 2, 2, dtype=torch.bool))
        back, valid = read_kitti_flow(tmp_path / "f.png")
        assert not valid.any() and back.eq(0).all()

    def test_poses_errors(self, tmp_path):
        (tmp_path / "bad.txt").write_text("1 2 3\n")
        with pytest.raises(ValueError, match=r"line 1 .* 3 numbers"):
            read_kitti_poses(tmp_path / "bad.txt")
        (tmp_path / "word.txt").write_text("a b c\n")
        with pytest.raises(ValueError, match="not a row of numbers"):
            read_kitti_poses(tmp_path / "word.txt")
        (tmp_path / "empty.txt").write_text("\n")
        with pytest.raises(ValueError, match="holds no poses"):
            read_kitti_poses(tmp_path / "empty.txt")
        with pytest.raises(ValueError, match=r"expected shape \(N, 4, 4\)"):
            write_kitti_poses(tmp_path / "p.txt", torch.zeros(2, 2, 4, dtype=torch.float64))
        with pytest.raises(ValueError, match="style"):
            write_kitti_calibration(tmp_path / "c.txt", torch.eye(3), style="raw")

    def test_binary_poses_file(self, tmp_path):
        """Once a bare UnicodeDecodeError without the path."""
        (tmp_path / "poses.txt").write_bytes(bytes(range(256)))
        with pytest.raises(ValueError, match=r"path: '.*poses\.txt' is not a text poses file"):
            read_kitti_poses(tmp_path / "poses.txt")

    @pytest.mark.parametrize("rotation, why", [("0 0 0 0 0 0 0 0 0", "det 0"), ("2 0 0 0 2 0 0 0 2", "up to 3"),
                                               ("1 0 0 0 1 0 0 0 -1", "det -1")])
    def test_poses_whose_rotation_is_not_a_rotation(self, tmp_path, rotation, why):
        """An all-zero rotation was once accepted (singular: its relative poses are inf)."""
        r = rotation.split()
        good = "1 0 0 0 0 1 0 0 0 0 1 0"
        row = " ".join(r[0:3] + ["1"] + r[3:6] + ["2"] + r[6:9] + ["3"])
        (tmp_path / "p.txt").write_text(f"{good}\n# a comment\n{row}\n")
        with pytest.raises(ValueError, match=rf"path: line 3 of '.*p\.txt' is not a rigid pose: .*{why}"):
            read_kitti_poses(tmp_path / "p.txt")

    def test_write_no_poses(self, tmp_path):
        with pytest.raises(ValueError, match=r"poses: expected at least one pose, got shape \(0, 3, 4\)"):
            write_kitti_poses(tmp_path / "p.txt", torch.zeros(0, 3, 4))
        assert not list(tmp_path.iterdir())

    @pytest.mark.parametrize("text, row", [("P_rect_02: nan 0 600 0 0 720 180 0 0 0 1 0\n", "P_rect_02"),
                                           ("P2: 720 0 600 0 0 inf 180 0 0 0 1 0\n", "P2"),
                                           ("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2 + "720 0 600 0 0 720 -inf 0 0 0 1 0\n",
                                            "unlabelled row 3")])
    def test_calibration_non_finite(self, tmp_path, text, row):
        (tmp_path / "c.txt").write_text(text)
        with pytest.raises(ValueError, match=rf"path: the {row} row of '.*c\.txt' holds NaN or inf"):
            read_kitti_calibration(tmp_path / "c.txt")

    def test_calibration_writer_camera_index(self, tmp_path):
        # (a wrong type, "x" or 1.0, is a TypeError; a wrong index a ValueError)
        for cam, error in (("x", TypeError), (4, ValueError), (1.0, TypeError)):
            with pytest.raises(error, match=rf"cam: expected 0..3, got {cam!r}"):
                write_kitti_calibration(tmp_path / "c.txt", torch.eye(3), cam=cam)


class TestShared:
    def test_kitti15_sample_valid_fraction(self, shared_data):
        """The shared KITTI 2015 pair: about 16.2% of pixels carry ground truth (measured 16.200%)."""
        flow, valid = read_kitti_flow(shared_data / "kitti15_000000" / "flow_noc_10.png")
        assert flow.shape == (2, 375, 1242) and valid.shape == (1, 375, 1242)
        fraction = float(valid.float().mean())
        assert abs(fraction - 0.162) < 0.002
        moving = flow.norm(dim=0)[valid[0]]
        assert float(moving.max()) < 300 and float(moving.median()) > 0.5

    def test_odometry_poses_and_calibration(self, shared_data):
        folder = shared_data / "kitti_odometry_straight"
        poses = read_kitti_poses(folder / "poses.txt")
        assert poses.shape[1:] == (4, 4) and len(poses) >= 50
        assert torch.allclose(poses[0], torch.eye(4, dtype=torch.float64), atol=1e-9)
        step = (poses[1:, :3, 3] - poses[:-1, :3, 3]).norm(dim=1)
        assert 1.0 < float(step.mean()) < 1.4  # "about 1.2 m per frame"
        P0 = read_kitti_calibration(folder / "calib.txt", 0)
        assert abs(float(P0[0, 0]) - 707.0912) < 1e-6


class TestExactAndChecked:
    @pytest.mark.parametrize("style", ["cam_to_cam", "odometry"])
    def test_calibration_reads_back_exactly(self, tmp_path, style):
        """Every float64 survives the file (``%.12e`` once kept 13 digits: K of images resized by
        1/3 came back 3e-11 px off), for our reader and for a plain split-and-float reader."""
        K = Camera(torch.tensor([[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]],
                                dtype=torch.float64), 1.65).scaled(1 / 3, 1 / 3).K[0]
        P = torch.cat([K, torch.tensor([[1e-300], [-2.5e17], [1 / 7]], dtype=torch.float64)], dim=1)
        for written in (K, P):
            write_kitti_calibration(tmp_path / "c.txt", written, style=style)
            back = read_kitti_calibration(tmp_path / "c.txt", 2)
            assert torch.equal(back[:, :written.shape[1]], written)
            line = (tmp_path / "c.txt").read_text().splitlines()[-1]
            plain = np.array([float(x) for x in line.split(":", 1)[1].split()]).reshape(3, 4)
            assert np.array_equal(plain[:, :written.shape[1]], written.numpy())
        assert "721.5377" in (write_kitti_calibration(tmp_path / "d.txt", torch.tensor(
            [[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]], dtype=torch.float64))).read_text()
        with pytest.raises(ValueError, match=r"^K: expected finite values"):
            write_kitti_calibration(tmp_path / "e.txt", torch.tensor([[1.0, 0, float("nan")], [0, 1, 0], [0, 0, 1]]))
        assert not (tmp_path / "e.txt").exists()

    @pytest.mark.parametrize("style", ["cam_to_cam", "odometry"])
    @pytest.mark.parametrize("make, match", [
        (lambda K: K.t(), r"^K: expected an upper-triangular intrinsic matrix with K\[2, 2\] = 1, got .*609\.5593, "
                          r"172\.854, 1\.0"),
        (lambda K: K * torch.tensor([[1.0], [1.0], [2.0]], dtype=K.dtype), r"^K: expected an upper-triangular"),
        (lambda K: K * torch.tensor([[-1.0], [1.0], [1.0]], dtype=K.dtype), r"^K: expected focal lengths f_x, f_y > 0"),
        (lambda K: torch.cat([K.t(), torch.zeros(3, 1, dtype=K.dtype)], dim=1), r"^K: expected an upper-triangular"),
    ])
    def test_calibration_writer_refuses_a_K_no_camera_reads_back(self, tmp_path, style, make, match):
        """A transposed K (principal point in the last row, as a column-major copy gives it), a
        K[2, 2] of 2 or a negative focal length was written without a word; Camera.from_kitti and
        the datasets then refused the file (naming P and the file, not the call that wrote it). Now
        the writer refuses it, naming K, before anything is written; a valid K reads back as a
        camera with that K."""
        K = torch.tensor([[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]], dtype=torch.float64)
        with pytest.raises(ValueError, match=match) as err:
            write_kitti_calibration(tmp_path / "c.txt", make(K), style=style)
        assert "would not read back as a camera" in str(err.value)
        assert not (tmp_path / "c.txt").exists()
        write_kitti_calibration(tmp_path / "c.txt", K, style=style)
        assert torch.equal(Camera.from_kitti(tmp_path / "c.txt", 2).K[0], K)

    @pytest.mark.parametrize("edit, message", [
        (lambda P: P[1, :3, :3].mul_(2.0), r"poses: pose 1 is not a rigid pose: its 3×3 block is not a rotation"),
        (lambda P: P.__setitem__((1, 3, 0), 5.0), r"poses: pose 1 is not a rigid pose: its last row is 5 0 0 1"),
        (lambda P: P.__setitem__((2, 0, 3), float("inf")), r"poses: pose 2 holds NaN or inf"),
        (lambda P: (P[2, :3, :3].zero_(), P.__setitem__((1, 3, 3), 2.0)), r"poses: pose 1 is not a rigid pose: "
                                                                           r"its last row is 0 0 0 2"),
    ])
    def test_poses_writer_refuses_what_the_reader_refuses(self, tmp_path, edit, message):
        """The writer once wrote a non-rigid block (its reader refused the file) and dropped a last
        row that was not 0 0 0 1 without a word; now the first bad pose is named, nothing written."""
        P = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
        P[:, 2, 3] = torch.tensor([0.0, 1.0, 2.0])
        edit(P)
        with pytest.raises(ValueError, match=rf"^{message}"):
            write_kitti_poses(tmp_path / "p.txt", P)
        with pytest.raises(ValueError, match=rf"^{message}"):
            write_kitti_poses(tmp_path / "p.txt", P.float())
        assert not list(tmp_path.iterdir())

    def test_poses_reader_names_the_first_bad_line(self, tmp_path):
        good = "1 0 0 0 0 1 0 0 0 0 1 0"
        (tmp_path / "n.txt").write_text(f"{good}\n\n# comment\n1 0 0 nan 0 1 0 0 0 0 1 0\n{good}\n")
        with pytest.raises(ValueError, match=r"^path: line 4 of '.*n\.txt' holds NaN or inf"):
            read_kitti_poses(tmp_path / "n.txt")
        # the first bad line, whatever is wrong with it: a scaled block on line 2 before a NaN on line 3
        (tmp_path / "m.txt").write_text(f"{good}\n2 0 0 0 0 2 0 0 0 0 2 0\n1 0 0 inf 0 1 0 0 0 0 1 0\n")
        with pytest.raises(ValueError, match=r"^path: line 2 of '.*m\.txt' is not a rigid pose"):
            read_kitti_poses(tmp_path / "m.txt")
        (tmp_path / "r.txt").write_text(f"{good} 0 0 0 1\n{good} 0.5 0 0 1\n")
        with pytest.raises(ValueError, match=r"^path: line 2 of '.*r\.txt' is not a rigid pose: its last row is "
                                             r"0\.5 0 0 1, not 0 0 0 1"):
            read_kitti_poses(tmp_path / "r.txt")

    def test_writers_take_numpy_views_and_other_byte_orders(self, tmp_path):
        """A negative-stride view (``a[::-1]``) or a big-endian array once failed with torch's
        from_numpy error, which names no argument; the values are written as given."""
        big = np.eye(4)[None].astype(">f8")
        big[0, 2, 3] = 2.5
        back = read_kitti_poses(write_kitti_poses(tmp_path / "p.txt", big))
        assert back[0, 2, 3] == 2.5
        flipped = np.stack([np.eye(4)] * 2)[::-1].copy()
        flipped[0, 0, 3] = 1.0
        assert read_kitti_poses(write_kitti_poses(tmp_path / "q.txt", flipped[::-1]))[1, 0, 3] == 1.0
        K = np.array([[700.0, 0, 300], [0, 710, 200], [0, 0, 1]])
        for array in (K.astype(">f8"), K[::-1].copy()[::-1]):
            P = read_kitti_calibration(write_kitti_calibration(tmp_path / "c.txt", array), 2)
            assert np.array_equal(P[:, :3].numpy(), K)
        valid = np.zeros((3, 4), bool)
        valid[0] = True
        write_kitti_flow(tmp_path / "f.png", torch.zeros(2, 3, 4), valid[::-1])
        assert read_kitti_flow(tmp_path / "f.png")[1][0].tolist() == valid[::-1].tolist()
