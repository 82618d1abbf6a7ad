"""fsof_torch.io.vkitti: Virtual KITTI 2 flow PNG, intrinsics/extrinsics, class segmentation."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
import torch

from fsof_torch.geometry.egomotion import ego_motion_from_pose
from fsof_torch.io import (
    read_vkitti2_classes,
    read_vkitti2_colors,
    read_vkitti2_extrinsics,
    read_vkitti2_flow,
    read_vkitti2_intrinsics,
    vkitti2_camera_poses,
    write_vkitti2_flow,
)


def _flow(h=12, w=20):
    g = torch.Generator().manual_seed(3)
    flow = (torch.rand(2, h, w, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([w - 1, h - 1.0]).view(2, 1, 1)
    valid = torch.rand(1, h, w, generator=g) > 0.2
    return flow, valid


class TestFeature:
    def test_decoding_matches_vkitti2_formula(self, tmp_path):
        """Independent reference: the Virtual KITTI 2 README's decoder, on raw 16-bit channels."""
        h, w = 5, 9
        rng = np.random.default_rng(0)
        bgr = rng.integers(0, 65536, (h, w, 3), dtype=np.uint16)
        bgr[0, 0, 0] = 0  # one invalid pixel
        cv2.imwrite(str(tmp_path / "flow_00000.png"), bgr)
        ref = 2.0 / (2**16 - 1.0) * bgr[..., 2:0:-1].astype(np.float64) - 1
        ref[..., 0] *= w - 1
        ref[..., 1] *= h - 1
        flow, valid = read_vkitti2_flow(tmp_path / "flow_00000.png")
        assert flow.shape == (2, h, w) and not bool(valid[0, 0, 0]) and int(valid.sum()) == h * w - (bgr[..., 0] == 0).sum()
        m = valid[0].numpy()
        np.testing.assert_allclose(flow.numpy().transpose(1, 2, 0)[m], ref[m], atol=1e-4)
        assert flow[:, 0, 0].eq(0).all()

    def test_round_trip_to_code_step(self, tmp_path):
        flow, valid = _flow()
        write_vkitti2_flow(tmp_path / "f.png", flow, valid)
        back, back_valid = read_vkitti2_flow(tmp_path / "f.png")
        assert torch.equal(back_valid, valid)
        step = torch.tensor([19.0, 11.0]).view(2, 1, 1) / 65535  # half of 2 (W-1) / 65535
        err = (back.double() - flow).abs()
        assert bool((err <= step + 1e-5)[valid.expand(2, -1, -1)].all())

    def test_intrinsics_extrinsics_and_poses(self, tmp_path):
        (tmp_path / "intrinsic.txt").write_text(
            "frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n"
            "0 0 725.0087 725.0087 620.5 187\n0 1 725.0087 725.0087 620.5 187\n"
            "1 0 725.0087 725.0087 620.5 187\n1 1 725.0087 725.0087 620.5 187\n")
        # world-to-camera extrinsics: the camera moves 1 m forward (world z) between frames
        rows = ["frame cameraID r1,1 r1,2 r1,3 t1 r2,1 r2,2 r2,3 t2 r3,1 r3,2 r3,3 t3 0 0 0 1"]
        for frame in (0, 1):
            for cam, tx in ((0, 0.0), (1, -0.532725)):
                E = np.eye(4)
                E[:3, 3] = [tx, 1.5, -1.0 * frame]
                rows.append(f"{frame} {cam} " + " ".join(f"{x:g}" for x in E.reshape(-1)))
        (tmp_path / "extrinsic.txt").write_text("\n".join(rows) + "\n")
        frames, K = read_vkitti2_intrinsics(tmp_path / "intrinsic.txt", camera=0)
        assert frames.tolist() == [0, 1] and K.shape == (2, 3, 3) and float(K[0, 0, 2]) == 620.5 and float(K[0, 2, 2]) == 1
        frames, E = read_vkitti2_extrinsics(tmp_path / "extrinsic.txt", camera=0)
        assert frames.tolist() == [0, 1] and E.shape == (2, 4, 4)
        poses = vkitti2_camera_poses(E)
        ego = ego_motion_from_pose(poses[:1], pose1=poses[1:])
        torch.testing.assert_close(ego.z_d, torch.tensor([1.0], dtype=torch.float64))
        torch.testing.assert_close(ego.x_d, torch.tensor([0.0], dtype=torch.float64))

    def test_camera_poses_must_be_rigid(self):
        """A scaled, sheared or NaN extrinsic is refused (it inverted into a pose that is not one),
        naming the first bad matrix; a rigid one inverts to its pose."""
        E = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
        E[:, :3, 3] = torch.tensor([0.0, 1.5, -2.0])
        torch.testing.assert_close(vkitti2_camera_poses(E)[:, :3, 3], -E[:, :3, 3])
        for bad, match in ((lambda e: e[1, :3, :3].mul_(2.0), r"matrix 1 is not a rigid pose: its 3×3 block"),
                           (lambda e: e[2, 0, 1].fill_(0.5), r"matrix 2 is not a rigid pose: its 3×3 block"),
                           (lambda e: e[1, 3, 2].fill_(1.0), r"matrix 1 is not a rigid pose: its last row"),
                           (lambda e: e[0, 0, 0].fill_(float("nan")), r"matrix 0 holds NaN or inf")):
            wrong = E.clone()
            bad(wrong)
            with pytest.raises(ValueError, match=r"camera_T_world: " + match):
                vkitti2_camera_poses(wrong)

    def test_classes(self, tmp_path):
        (tmp_path / "colors.txt").write_text("Category r g b\nTerrain 210 0 200\nSky 90 200 255\nRoad 100 60 100\n")
        colors = read_vkitti2_colors(tmp_path / "colors.txt")
        assert list(colors) == ["Terrain", "Sky", "Road"] and colors["Road"] == (100, 60, 100)
        rgb = np.zeros((2, 3, 3), np.uint8)
        rgb[0, :] = (90, 200, 255)
        rgb[1, :2] = (100, 60, 100)
        cv2.imwrite(str(tmp_path / "classgt_00000.png"), rgb[..., ::-1])
        labels = read_vkitti2_classes(tmp_path / "classgt_00000.png", colors)
        assert labels.tolist() == [[1, 1, 1], [2, 2, -1]]


class TestExceptions:
    def test_flow_file_checks(self, tmp_path):
        cv2.imwrite(str(tmp_path / "eight.png"), np.zeros((3, 3, 3), np.uint8))
        with pytest.raises(ValueError, match=r"eight\.png.*16-bit"):
            read_vkitti2_flow(tmp_path / "eight.png")
        cv2.imwrite(str(tmp_path / "one.png"), np.zeros((3, 3), np.uint16))
        with pytest.raises(ValueError, match=r"one\.png.*1 channel"):
            read_vkitti2_flow(tmp_path / "one.png")
        with pytest.raises(ValueError, match="encoding holds"):
            write_vkitti2_flow(tmp_path / "big.png", torch.full((2, 3, 3), 10.0))

    @pytest.mark.parametrize("name", ["f.jpg", "f.bmp", "f.tif", "f"])
    def test_writer_takes_png_only(self, tmp_path, name):
        """A VKITTI2 flow is a 16-bit PNG: .jpg/.bmp raised naming `array`, no argument of the
        writer's, and .tif wrote a file of another format."""
        with pytest.raises(ValueError, match=r"^path: a Virtual KITTI 2 flow is written as \.png"):
            write_vkitti2_flow(tmp_path / name, torch.zeros(2, 3, 4))
        assert list(tmp_path.iterdir()) == []

    def test_table_checks(self, tmp_path):
        (tmp_path / "intrinsic.txt").write_text("frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n0 0 1 1 1\n")
        with pytest.raises(ValueError, match="5 columns"):
            read_vkitti2_intrinsics(tmp_path / "intrinsic.txt")
        (tmp_path / "i2.txt").write_text("0 1 1 1 1 1\n")
        with pytest.raises(ValueError, match="no rows for camera 0"):
            read_vkitti2_intrinsics(tmp_path / "i2.txt", camera=0)
        with pytest.raises(FileNotFoundError, match=r"path: no VKITTI2 extrinsic\.txt at '.*none\.txt'"):
            read_vkitti2_extrinsics(tmp_path / "none.txt")

    @pytest.mark.parametrize("camera", ["0", 0.0, True, None])
    @pytest.mark.parametrize("reader, columns", [(read_vkitti2_intrinsics, 6), (read_vkitti2_extrinsics, 18)])
    def test_camera_not_an_int(self, tmp_path, reader, columns, camera):
        """Not "has no rows for camera 0; it has cameras [0]" for the string '0'."""
        values = "1 1 1 1" if columns == 6 else "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"  # K, or a 4×4 identity
        (tmp_path / "t.txt").write_text(f"0 0 {values}\n")
        with pytest.raises(TypeError, match=rf"camera: expected an int, got {re.escape(repr(camera))}$"):
            reader(tmp_path / "t.txt", camera=camera)
        assert len(reader(tmp_path / "t.txt", camera=np.int64(0))[0]) == 1

    def test_writer_checks_valid_as_the_kitti_writer(self, tmp_path):
        flow = torch.zeros(2, 4, 5)
        with pytest.raises(TypeError, match=r"valid: expected a bool tensor of shape \(1, H, W\), got torch.uint8"):
            write_vkitti2_flow(tmp_path / "a.png", flow, torch.ones(1, 4, 5, dtype=torch.uint8))
        with pytest.raises(ValueError, match=r"valid: expected shape \(1, 4, 5\) to match flow, got \(1, 2, 10\)"):
            write_vkitti2_flow(tmp_path / "b.png", flow, torch.ones(1, 2, 10, dtype=torch.bool))
        flow[:, 1, 1] = float("nan")
        with pytest.raises(ValueError, match="flow: expected finite values at valid pixels"):
            write_vkitti2_flow(tmp_path / "c.png", flow, torch.ones(1, 4, 5, dtype=torch.bool))
        assert not list(tmp_path.iterdir())
        valid = torch.ones(1, 4, 5, dtype=torch.bool)
        valid[0, 1, 1] = False  # NaN where not valid is fine, and written as invalid
        _, back_valid = read_vkitti2_flow(write_vkitti2_flow(tmp_path / "d.png", flow, valid))
        assert torch.equal(back_valid, valid)

    @pytest.mark.parametrize("reader", [read_vkitti2_intrinsics, read_vkitti2_extrinsics, read_vkitti2_colors])
    def test_binary_text_files(self, tmp_path, reader):
        (tmp_path / "t.txt").write_bytes(b"\xff\xfe\x00\x01")
        with pytest.raises(ValueError, match=r"path: '.*t\.txt' is not a text file"):
            reader(tmp_path / "t.txt")

    def test_non_finite_table_values(self, tmp_path):
        (tmp_path / "intrinsic.txt").write_text("frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n0 0 nan 1 1 1\n")
        with pytest.raises(ValueError, match=r"line 2 of '.*intrinsic\.txt' holds NaN or inf"):
            read_vkitti2_intrinsics(tmp_path / "intrinsic.txt")


_EXTRINSIC_HEADER = "frame cameraID r1,1 r1,2 r1,3 t1 r2,1 r2,2 r2,3 t2 r3,1 r3,2 r3,3 t3 0 0 0 1\n"
_IDENTITY = "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"


class TestMalformedRows:
    """Rows once accepted without a word: a frame number truncated (2.7 -> 2), a (frame, camera)
    row kept twice, a scaled 'rotation' inverted into a wrong pose, focal lengths -1 and 0."""

    @pytest.mark.parametrize("rows, line, message", [
        (f"0 0 {_IDENTITY}\n2.7 0 {_IDENTITY}\n", 3,
         r"starts with frame '2\.7', cameraID '0'; expected whole numbers >= 0"),
        (f"-1 0 {_IDENTITY}\n", 2, r"starts with frame '-1', cameraID '0'; expected whole numbers >= 0"),
        (f"0 0.5 {_IDENTITY}\n", 2, r"starts with frame '0', cameraID '0\.5'; expected whole numbers >= 0"),
        (f"0 0 {_IDENTITY}\n0 1 {_IDENTITY}\n0 0 {_IDENTITY}\n", 4, r"repeats frame 0 of camera 0 \(line 2\)"),
        (f"0 0 {_IDENTITY}\n1 0 2 0 0 0 0 2 0 0 0 0 2 5 0 0 0 1\n", 3,
         r"is not a rigid pose: its 3×3 block is not a rotation \(\|RᵀR − I\| up to 3, det 8"),
        (f"0 0 {_IDENTITY}\n1 0 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0.5 1\n", 3,
         r"is not a rigid pose: its last row is 0 0 0\.5 1"),
    ])
    def test_extrinsics(self, tmp_path, rows, line, message):
        (tmp_path / "extrinsic.txt").write_text(_EXTRINSIC_HEADER + rows)
        with pytest.raises(ValueError, match=rf"^path: line {line} of '.*extrinsic\.txt' {message}"):
            read_vkitti2_extrinsics(tmp_path / "extrinsic.txt")

    @pytest.mark.parametrize("row, fx, fy", [("0 0 -1 725 620 187", -1, 725), ("0 0 725 0 620 187", 725, 0)])
    def test_focal_lengths(self, tmp_path, row, fx, fy):
        header = "frame cameraID K[0,0] K[1,1] K[0,2] K[1,2]\n"
        (tmp_path / "intrinsic.txt").write_text(f"{header}1 0 725 725 620 187\n{row}\n")
        with pytest.raises(ValueError, match=rf"^path: line 3 of '.*intrinsic\.txt' has the focal lengths "
                                             rf"K\[0,0\] = {fx}, K\[1,1\] = {fy}; expected both > 0"):
            read_vkitti2_intrinsics(tmp_path / "intrinsic.txt")

    def test_a_class_named_twice(self, tmp_path):
        """The second 'Road' once took Sky's colour at Road's place in the dict."""
        (tmp_path / "colors.txt").write_text("Category r g b\nRoad 100 60 100\nSky 90 200 255\nRoad 90 200 255\n")
        with pytest.raises(ValueError, match=r"^path: line 4 of '.*colors\.txt' repeats the class 'Road' of line 2"):
            read_vkitti2_colors(tmp_path / "colors.txt")

    def test_byte_order_mark(self, tmp_path):
        """A UTF-8 byte-order mark once turned colors.txt's header into a class row."""
        (tmp_path / "colors.txt").write_bytes("\ufeffCategory r g b\nRoad 100 60 100\n".encode("utf-8"))
        assert read_vkitti2_colors(tmp_path / "colors.txt") == {"Road": (100, 60, 100)}
        (tmp_path / "intrinsic.txt").write_bytes("\ufeff0 0 725 725 620 187\n".encode("utf-8"))
        assert read_vkitti2_intrinsics(tmp_path / "intrinsic.txt")[1][0, 0, 0] == 725


class TestRanges:
    @pytest.mark.parametrize("shape, channel, name", [((3, 1), 0, "u"), ((1, 4), 1, "v")])
    def test_a_one_pixel_side_stores_zero_flow_only(self, tmp_path, shape, channel, name):
        """The reader scales by W - 1 (H - 1), 0 on a 1-pixel side: u = 0.75 there was once
        written and read back as 0."""
        flow = torch.zeros(2, *shape, dtype=torch.float64)
        flow[1 - channel] = 0.5  # the other component stays in range (its side is 3 or 4 pixels)
        back, valid = read_vkitti2_flow(write_vkitti2_flow(tmp_path / "ok.png", flow))
        assert valid.all() and back[channel].eq(0).all()
        assert float((back[1 - channel].double() - 0.5).abs().max()) <= (max(shape) - 1) / 65535
        flow[channel, 0, 0] = 0.75
        with pytest.raises(ValueError, match=rf"^flow: the Virtual KITTI 2 encoding holds \|u\| <= {shape[1] - 1}, "
                                             rf"\|v\| <= {shape[0] - 1} px .*got \|{name}\| = 0\.75 at a valid pixel"):
            write_vkitti2_flow(tmp_path / "bad.png", flow)
        assert not (tmp_path / "bad.png").exists()
        valid = torch.ones(1, *shape, dtype=torch.bool)
        valid[0, 0, 0] = False  # where not valid, any value is fine (written as 0)
        write_vkitti2_flow(tmp_path / "masked.png", flow, valid)

    @pytest.mark.parametrize("row", ["Road 0 256 0", "Road -1 0 0", "Road 100 60 1000"])
    def test_colour_components_beyond_a_byte_are_refused(self, tmp_path, row):
        """(0, 256, 0) once packed to the code of (1, 0, 0): such a pixel was labelled Road."""
        (tmp_path / "colors.txt").write_text(f"Category r g b\nTerrain 210 0 200\n{row}\n")
        with pytest.raises(ValueError, match=rf"^path: line 3 of '.*colors\.txt' has a colour component outside "
                                             rf"0\.\.255: '{row}'"):
            read_vkitti2_colors(tmp_path / "colors.txt")
        cv2.imwrite(str(tmp_path / "classgt_00000.png"), np.array([[[0, 0, 1], [0, 255, 0]]], np.uint8))
        colors = {"Terrain": (210, 0, 200), "Road": tuple(int(x) for x in row.split()[1:])}
        with pytest.raises(ValueError, match=rf"^colors\['Road'\]: expected three integers in 0\.\.255, got "
                                             rf"\({', '.join(row.split()[1:])}\)"):
            read_vkitti2_classes(tmp_path / "classgt_00000.png", colors)
        labels = read_vkitti2_classes(tmp_path / "classgt_00000.png", {"Terrain": (210, 0, 200), "Road": (0, 255, 0)})
        assert labels.tolist() == [[-1, 1]]  # RGB (1, 0, 0) is no class
