"""fsof_torch.io.carla: the paper's CARLA layout (flow TIFF, semantic road, camera, run folders)."""

from __future__ import annotations

import math
import re

import cv2
import numpy as np
import pytest
import torch

from fsof_torch.io import (
    CarlaRun,
    carla_camera,
    parse_carla_run_name,
    read_carla_flow,
    read_carla_road,
    write_carla_flow,
)


def _flow(h=6, w=8):
    g = torch.Generator().manual_seed(5)
    return torch.randn(2, h, w, generator=g) * 20


class TestFeature:
    def test_reads_like_the_official_code(self, tmp_path):
        """The official script: reshape the TIFF to (H, W, 2), u = x·W, v = -y·H."""
        h, w = 4, 6
        raw = np.random.default_rng(1).normal(size=(h, 2 * w)).astype(np.float32)
        cv2.imwrite(str(tmp_path / "00000001.tif"), raw)
        flow, valid = read_carla_flow(tmp_path / "00000001.tif")
        ref = raw.reshape(h, w, 2)
        np.testing.assert_allclose(flow[0].numpy(), ref[..., 0] * w, rtol=1e-6)
        np.testing.assert_allclose(flow[1].numpy(), -ref[..., 1] * h, rtol=1e-6)
        assert valid.all()

    def test_round_trip(self, tmp_path):
        flow = _flow()
        write_carla_flow(tmp_path / "f.tif", flow)
        back, valid = read_carla_flow(tmp_path / "f.tif")
        assert valid.all()
        torch.testing.assert_close(back, flow, atol=1e-4, rtol=1e-6)

    def test_road_from_semantic(self, tmp_path):
        rgb = np.zeros((2, 3, 3), np.uint8)
        rgb[0, 0] = (128, 64, 128)
        rgb[1, 1] = (157, 234, 50)
        rgb[1, 2] = (244, 35, 232)  # sidewalk
        cv2.imwrite(str(tmp_path / "s.png"), rgb[..., ::-1])
        assert read_carla_road(tmp_path / "s.png").tolist() == [[[True, False, False], [False, True, False]]]

    def test_camera_and_run_name(self):
        cam = carla_camera((480, 640), roll=math.radians(-5))
        assert float(cam.fx) == pytest.approx(320.0) and float(cam.cx) == 320 and float(cam.cy) == 240
        assert float(cam.height) == pytest.approx(2.4)
        params = parse_carla_run_name("t10_s0_r-5")
        assert params["t"] == 10 and params["s"] == 0 and params["r"] == -5
        assert params["roll"] == pytest.approx(math.radians(-5))

    def test_run_folder(self, tmp_path):
        run = tmp_path / "t10_s0_r5"
        for sub in ("rgb", "optical_flow", "semantic"):
            (run / sub).mkdir(parents=True)
        for k in (1, 2):
            cv2.imwrite(str(run / "rgb" / f"{k:08d}.png"), np.zeros((4, 6, 3), np.uint8))
        r = CarlaRun(run)
        assert r.frames == ["00000001", "00000002"] and len(r) == 2
        assert r.path("optical_flow", "00000001").name == "00000001.tif"
        assert r.params["roll"] == pytest.approx(math.radians(5))


class TestExceptions:
    def test_flow_checks(self, tmp_path):
        cv2.imwrite(str(tmp_path / "odd.tif"), np.zeros((3, 5), np.float32))
        with pytest.raises(ValueError, match=r"odd\.tif.*even width"):
            read_carla_flow(tmp_path / "odd.tif")
        cv2.imwrite(str(tmp_path / "u8.png"), np.zeros((3, 4), np.uint8))
        with pytest.raises(ValueError, match=r"u8\.png.*uint8"):
            read_carla_flow(tmp_path / "u8.png")

    def test_writer_takes_a_tiff_path_only(self, tmp_path):
        # a .png failed with an error naming `array`, not an argument of write_carla_flow
        for name in ("w.png", "w.flo", "w"):
            with pytest.raises(ValueError, match=rf"^path: a CARLA flow file is a float32 TIFF; expected a \.tif or "
                                                 rf"\.tiff path, got '.*{name}'$"):
                write_carla_flow(tmp_path / name, _flow())
        assert list(tmp_path.iterdir()) == []
        write_carla_flow(tmp_path / "w.TIFF", _flow())
        assert torch.allclose(read_carla_flow(tmp_path / "w.TIFF")[0], _flow(), atol=1e-5)

    def test_writer_refuses_values_beyond_float32(self, tmp_path):
        """A finite float64 value beyond float32's range was written as inf and read back as an
        invalid pixel, silently: a ValueError naming flow, nothing written. The largest float32
        value and NaN / inf (invalid pixels) are written as before."""
        flow = _flow().double()
        flow[0, 2, 3] = 1e39
        with pytest.raises(ValueError, match=r"^flow: a CARLA flow TIFF stores float32, which cannot hold 1e\+39"):
            write_carla_flow(tmp_path / "f.tif", flow)
        assert list(tmp_path.iterdir()) == []
        big = torch.finfo(torch.float32).max
        flow[0, 2, 3], flow[1, 0, 0] = big, float("nan")
        back, valid = read_carla_flow(write_carla_flow(tmp_path / "f.tif", flow))
        assert float(back[0, 2, 3]) == pytest.approx(big, rel=1e-6) and valid[0, 2, 3]
        assert not valid[0, 0, 0] and int(valid.sum()) == flow[0].numel() - 1

    def test_run_checks(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="no rgb/"):
            CarlaRun(tmp_path)
        with pytest.raises(TypeError, match="^root: expected a file path .str or os.PathLike., got NoneType None$"):
            CarlaRun(None)
        (tmp_path / "rgb").mkdir()
        with pytest.raises(ValueError, match="no PNG frames"):
            CarlaRun(tmp_path)


    @pytest.mark.parametrize("name, part", [("t10_s0_r+5", "r+5"), ("t10_s0_R-5", "R-5"), ("t10_s0_r-2.5e0", "r-2.5e0"),
                                            ("t10_s0_r.5", "r.5"), ("t10_s0_r-5deg", "r-5deg"), ("t10_r", "r")])
    def test_a_roll_that_does_not_parse(self, tmp_path, name, part):
        """Such a part was once dropped without a word, and CarlaRunDataset used roll 0."""
        with pytest.raises(ValueError, match=rf"^name: the run '{re.escape(name)}' has the part '{re.escape(part)}'; "
                                             rf"expected the roll as 'r' and a number of degrees"):
            parse_carla_run_name(name)
        (tmp_path / name / "rgb").mkdir(parents=True)
        cv2.imwrite(str(tmp_path / name / "rgb" / "1.png"), np.zeros((2, 3, 3), np.uint8))
        with pytest.raises(ValueError, match=rf"the run '{re.escape(name)}'"):
            CarlaRun(tmp_path / name)

    def test_a_roll_given_twice(self):
        """'t10_s0_r-5_r5' once used the last one (5°)."""
        with pytest.raises(ValueError, match=r"^name: the run 't10_s0_r-5_r5' gives the roll twice \('r-5', 'r5'\)"):
            parse_carla_run_name("t10_s0_r-5_r5")
        assert parse_carla_run_name("rain2_t1_r2.5") == {"rain": 2.0, "t": 1.0, "r": 2.5, "roll": math.radians(2.5)}

    @pytest.mark.parametrize("kwargs, err, match", [
        ({"fov_deg": 0}, ValueError, r"^fov_deg: expected a field of view in \(0, 180\) degrees, got 0$"),
        ({"fov_deg": 180.0}, ValueError, r"^fov_deg: expected a field of view in \(0, 180\) degrees, got 180\.0"),
        ({"fov_deg": 200}, ValueError, r"^fov_deg: expected a field of view in \(0, 180\) degrees"),
        ({"fov_deg": float("nan")}, ValueError, r"^fov_deg: expected a finite number"),
        ({"fov_deg": "90"}, TypeError, r"^fov_deg: expected a number, got str '90'"),
        ({"size": (0, 640)}, ValueError, r"^size: expected an int >= 1, got 0"),
        ({"size": (480.5, 640)}, TypeError, r"^size: expected an int, got float 480\.5"),
        ({"size": 640}, TypeError, r"^size: expected \(H, W\), two ints, got int 640"),
        ({"size": (1, 480, 640)}, TypeError, r"^size: expected \(H, W\), two ints, got tuple"),
        ({"dtype": torch.int64}, TypeError, r"^dtype: expected a floating-point torch dtype, got torch\.int64"),
    ])
    def test_camera_arguments(self, kwargs, err, match):
        """fov_deg=0 raised ZeroDivisionError, 180 gave a camera of focal length 2e-14 px, a size of
        (480.5, 640) was truncated, and a zero side or an integer dtype was blamed on K."""
        call = {"size": (480, 640), **kwargs}
        with pytest.raises(err, match=match):
            carla_camera(call.pop("size"), **call)
        cam = carla_camera(np.array([480, 640]), fov_deg=torch.tensor(60.0))
        assert float(cam.fx) == pytest.approx(320.0 / math.tan(math.radians(30.0)))
        assert (float(cam.cx), float(cam.cy)) == (320.0, 240.0)

    def test_grey_semantic_png(self, tmp_path):
        """A single-channel PNG (CARLA's raw class IDs, road = 7) once gave an empty road mask."""
        ids = np.full((3, 4), 7, np.uint8)
        cv2.imwrite(str(tmp_path / "grey.png"), ids)
        with pytest.raises(ValueError, match=r"^path: '.*grey\.png' has 1 channel\(s\); a CARLA semantic PNG is a "
                                             r"colour image \(3 or 4 channels"):
            read_carla_road(tmp_path / "grey.png")
        rgba = np.zeros((3, 4, 4), np.uint8)
        rgba[1:, :, :3] = (128, 64, 128)  # (BGR order: the road colour reads the same)
        cv2.imwrite(str(tmp_path / "rgba.png"), rgba)
        assert int(read_carla_road(tmp_path / "rgba.png").sum()) == 8


def _two_channel_float_tiff(path, array):
    """A minimal baseline little-endian TIFF of (H, W, 2) float32, chunky, one strip (OpenCV
    cannot write one)."""
    import struct

    h, w, _ = array.shape
    data = np.ascontiguousarray(array, "<f4").tobytes()
    entries = []

    def entry(tag, kind, count, value, raw=None):
        entries.append(struct.pack("<HHI", tag, kind, count) + (raw if raw is not None else struct.pack("<I", value)))

    data_offset = 8 + 2 + 12 * 11 + 4 + 8
    entry(256, 4, 1, w)
    entry(257, 4, 1, h)
    entry(258, 3, 2, 0, struct.pack("<HH", 32, 32))  # bits per sample
    entry(259, 3, 1, 1)  # no compression
    entry(262, 3, 1, 1)  # black is zero
    entry(273, 4, 1, data_offset)
    entry(277, 3, 1, 2)  # samples per pixel
    entry(278, 4, 1, h)
    entry(279, 4, 1, len(data))
    entry(284, 3, 1, 1)  # chunky
    entry(339, 3, 2, 0, struct.pack("<HH", 3, 3))  # IEEE float samples
    path.write_bytes(b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 11) + b"".join(entries)
                     + struct.pack("<I", 0) + b"\x00" * 8 + data)


class TestLayoutLimits:
    def test_a_two_channel_float_tiff_is_refused_by_name(self, tmp_path):
        """The docstring once promised (H, W, 2) float32 TIFFs, which OpenCV does not decode."""
        _two_channel_float_tiff(tmp_path / "two.tif", np.ones((3, 4, 2), np.float32))
        with pytest.raises(ValueError, match=r"^path: OpenCV could not decode '.*two\.tif' as a CARLA flow TIFF "
                                             r"\(single-channel float32 \(H, 2W\), x and y interleaved; OpenCV "
                                             r"decodes no two-channel float32 TIFF\)"):
            read_carla_flow(tmp_path / "two.tif")
        cv2.imwrite(str(tmp_path / "three.tif"), np.ones((3, 4, 3), np.float32))
        with pytest.raises(ValueError, match=r"^path: '.*three\.tif' has 3 channels; a CARLA flow TIFF is a "
                                             r"single-channel \(H, 2W\) image"):
            read_carla_flow(tmp_path / "three.tif")

    def test_run_frames_in_number_order(self, tmp_path):
        """Frames named without zero padding are in the order of their numbers (98, 99, 100), as
        an image folder's; other names in the order of the names."""
        (tmp_path / "rgb").mkdir()
        for k in (100, 98, 99, 5):
            cv2.imwrite(str(tmp_path / "rgb" / f"{k}.png"), np.zeros((2, 3, 3), np.uint8))
        assert CarlaRun(tmp_path).frames == ["5", "98", "99", "100"]
        cv2.imwrite(str(tmp_path / "rgb" / "a.png"), np.zeros((2, 3, 3), np.uint8))
        assert CarlaRun(tmp_path).frames == ["100", "5", "98", "99", "a"]

    def test_run_frame_linked_to_a_missing_file_is_an_error(self, tmp_path):
        """A frame linked to a missing file was left out: frames 98 and 100 made a pair."""
        (tmp_path / "rgb").mkdir()
        for k in (98, 100):
            cv2.imwrite(str(tmp_path / "rgb" / f"{k}.png"), np.zeros((2, 3, 3), np.uint8))
        (tmp_path / "rgb" / "99.png").symlink_to(tmp_path / "gone.png")
        with pytest.raises(FileNotFoundError, match=r"root: '.*99\.png' is a symbolic link to '.*gone\.png', which "
                                                    r"does not exist"):
            CarlaRun(tmp_path)

    def test_run_frames_skip_hidden_files_and_folders(self, tmp_path):
        """A macOS '._99.png', an atomic writer's temporary or a folder named like a frame was once
        a frame: the order fell back to names (100, 5, 98, 99) and frames were paired wrongly."""
        (tmp_path / "rgb").mkdir()
        for k in (100, 98, 99, 5):
            cv2.imwrite(str(tmp_path / "rgb" / f"{k}.png"), np.zeros((2, 3, 3), np.uint8))
        (tmp_path / "rgb" / "._99.png").write_bytes(b"\x00\x05\x16\x07" + b"\x00" * 80)
        (tmp_path / "rgb" / ".99.png.0123456789abcdef.tmp.png").write_bytes(b"")
        (tmp_path / "rgb" / "101.png").mkdir()
        assert CarlaRun(tmp_path).frames == ["5", "98", "99", "100"]
