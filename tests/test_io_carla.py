"""fsof_torch.io.carla: the paper's CARLA layout (flow TIFF, semantic road, camera, run folders)."""

from __future__ import annotations

import math

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

    def test_run_checks(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="no rgb/"):
            CarlaRun(tmp_path)
        (tmp_path / "rgb").mkdir()
        with pytest.raises(ValueError, match="no PNG frames"):
            CarlaRun(tmp_path)
