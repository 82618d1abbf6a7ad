"""fsof_torch.io.masks: road masks from PNG or polygon JSON, colour masks, label maps."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from fsof_torch.io import (
    mask_from_colors,
    rasterize_polygons,
    read_label_map,
    read_road_mask,
    write_label_map,
    write_road_mask,
)


def _write_json(path, obj):
    path.write_text(json.dumps(obj))
    return path


class TestSmoke:
    def test_png_round_trip(self, tmp_path):
        mask = torch.zeros(1, 5, 8, dtype=torch.bool)
        mask[0, 2:, 3:6] = True
        write_road_mask(tmp_path / "m.png", mask)
        back = read_road_mask(tmp_path / "m.png")
        assert back.dtype == torch.bool and torch.equal(back, mask)

    def test_colour_png_any_channel(self, tmp_path):
        bgr = np.zeros((3, 4, 3), np.uint8)
        bgr[1, 2, 1] = 7
        cv2.imwrite(str(tmp_path / "c.png"), bgr)
        mask = read_road_mask(tmp_path / "c.png")
        assert mask.shape == (1, 3, 4) and int(mask.sum()) == 1 and bool(mask[0, 1, 2])

    def test_png_resized_nearest(self, tmp_path):
        mask = torch.zeros(1, 4, 6, dtype=torch.bool)
        mask[0, 2:] = True
        write_road_mask(tmp_path / "m.png", mask)
        big = read_road_mask(tmp_path / "m.png", size=(8, 12))
        assert big.shape == (1, 8, 12) and big[0, 4:].all() and not big[0, :4].any()

    def test_label_map_round_trip_8_and_16_bit(self, tmp_path):
        small = torch.arange(12).reshape(3, 4)
        large = small * 1000
        write_label_map(tmp_path / "s.png", small)
        write_label_map(tmp_path / "l.png", large)
        assert torch.equal(read_label_map(tmp_path / "s.png"), small)
        assert torch.equal(read_label_map(tmp_path / "l.png"), large)
        assert cv2.imread(str(tmp_path / "s.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint8
        assert cv2.imread(str(tmp_path / "l.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16


class TestFeature:
    def test_polygon_rectangle_matches_pixel_centres(self, tmp_path):
        """A rectangle with vertices on pixel centres fills exactly the pixels from corner to corner."""
        path = _write_json(tmp_path / "r.json", {"size": [10, 12], "road_polygon": [[2, 3], [8, 3], [8, 7], [2, 7]]})
        mask = read_road_mask(path)
        expected = torch.zeros(1, 10, 12, dtype=torch.bool)
        expected[0, 3:8, 2:9] = True
        assert torch.equal(mask, expected)

    def test_triangle_pixel_count_close_to_geometry(self):
        """fillPoly includes the boundary: the pixel count is the area plus about half the perimeter."""
        mask = rasterize_polygons([[[0, 99], [199, 99], [0, 0]]], (100, 200))
        area = 0.5 * 199 * 99
        perimeter = 199 + 99 + (199**2 + 99**2) ** 0.5
        expected = area + perimeter / 2
        assert abs(int(mask.sum()) - expected) / expected < 0.005

    def test_polygon_scaled_to_size(self, tmp_path):
        path = _write_json(tmp_path / "r.json", {"size": [20, 40], "road_polygon": [[0, 10], [39, 10], [39, 19], [0, 19]]})
        full = read_road_mask(path)
        half = read_road_mask(path, size=(10, 20))
        assert half.shape == (1, 10, 20)
        assert abs(float(half.float().mean()) - float(full.float().mean())) < 0.06

    def test_several_polygons_and_size_argument(self, tmp_path):
        path = _write_json(tmp_path / "p.json", {"polygons": [[[0, 0], [2, 0], [2, 2]], [[5, 5], [7, 5], [7, 7]]]})
        mask = read_road_mask(path, size=(8, 8))
        assert bool(mask[0, 0, 2]) and bool(mask[0, 5, 7]) and not bool(mask[0, 7, 0])

    def test_mask_from_colors(self):
        rgb = torch.zeros(3, 2, 3)
        rgb[:, 0, 0] = torch.tensor([128.0, 64.0, 128.0])
        rgb[:, 1, 2] = torch.tensor([255.0, 0.0, 0.0])
        mask = mask_from_colors(rgb, [(128, 64, 128), (255, 0, 0)])
        assert mask.tolist() == [[[True, False, False], [False, False, True]]]


class TestExceptions:
    def test_json_errors(self, tmp_path):
        no_size = _write_json(tmp_path / "a.json", {"road_polygon": [[0, 0], [1, 0], [1, 1]]})
        with pytest.raises(ValueError, match="no 'size' entry"):
            read_road_mask(no_size)
        no_poly = _write_json(tmp_path / "b.json", {"size": [3, 3]})
        with pytest.raises(ValueError, match="no 'road_polygon'"):
            read_road_mask(no_poly)
        (tmp_path / "c.json").write_text("{not json")
        with pytest.raises(ValueError, match="not valid JSON"):
            read_road_mask(tmp_path / "c.json")
        bad = _write_json(tmp_path / "d.json", {"size": [3, 3], "road_polygon": [[0, 0], [1, 1]]})
        with pytest.raises(ValueError, match="at least three"):
            read_road_mask(bad)

    def test_writer_errors(self, tmp_path):
        with pytest.raises(TypeError, match="bool tensor"):
            write_road_mask(tmp_path / "m.png", torch.zeros(1, 2, 2))
        with pytest.raises(ValueError, match="0..65535"):
            write_label_map(tmp_path / "l.png", torch.tensor([[-1, 2]]))
        with pytest.raises(ValueError, match="single-channel"):
            cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((2, 2, 3), np.uint8))
            read_label_map(tmp_path / "rgb.png")


class TestShared:
    @pytest.mark.parametrize("folder,size,low,high", [("kitti15_000000", (375, 1242), 0.15, 0.25),
                                                      ("kitti_odometry_straight", (370, 1226), 0.05, 0.25)])
    def test_road_json(self, shared_data, folder, size, low, high):
        mask = read_road_mask(shared_data / folder / "road.json")
        assert mask.shape == (1, *size)
        assert low < float(mask.float().mean()) < high
        assert not mask[0, :150].any()  # the polygons lie below the horizon
