"""fsof_torch.io.layout: the synthetic KITTI-like layout, written and read back."""

from __future__ import annotations

import json
import math

import pytest
import torch

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry.egomotion import ego_motion_from_pose
from fsof_torch.geometry.road_flow import displacement_flow
from fsof_torch.io import (
    read_depth_png,
    read_kitti_calibration,
    read_kitti_poses,
    read_synthetic_pair,
    relative_pose_from_odometry,
    synthetic_pair_indices,
    write_depth_png,
    write_synthetic_pair,
    write_synthetic_sequence,
)


def _pair(index=0, size=(24, 40), roll=0.03, pitch=-0.01, with_poses=False):
    """A pair with the road-plane flow of the model (a stand-in for the renderer)."""
    h, w = size
    K = torch.tensor([[40.0, 0, (w - 1) / 2], [0, 40.0, 6.0], [0, 0, 1]], dtype=torch.float64)
    camera = Camera(K, 1.6, roll, pitch)
    odo = {"x_d": 0.02 * (index + 1), "z_d": 0.9, "yaw": 0.004 * (index + 1)}
    flow, valid = displacement_flow(camera, odo["x_d"], odo["z_d"], odo["yaw"], size)
    g = torch.Generator().manual_seed(index)
    labels = torch.randint(0, 7, size, generator=g)
    pair = {
        "image1": torch.rand(3, h, w, generator=g) * 255, "image2": torch.rand(3, h, w, generator=g) * 255,
        "flow": flow[0].float(), "valid": valid[0], "flow_velocity": flow[0].float() * 10,
        "road": valid[0].clone(), "labels": labels, "depth": torch.rand(1, h, w, generator=g) * 80,
        "camera": camera.to(torch.float32), "odometry": odo,
        "velocity": {"speed": 9.0, "steering": 0.01, "wheelbase": 2.7, "dt": 0.1}, "index": index,
    }
    return pair


def _eye4(row, col, value):
    """A 4×4 identity list with one entry changed (a pose of a params JSON)."""
    matrix = torch.eye(4, dtype=torch.float64).tolist()
    matrix[row][col] = value
    return matrix


class TestSmoke:
    def test_pair_round_trip(self, tmp_path):
        pair = _pair()
        paths = write_synthetic_pair(tmp_path, 0, pair, extra={"preset": "test"})
        assert {"image1", "image2", "flow", "flow_velocity", "road", "labels", "depth", "calib", "params"} <= set(paths)
        assert (tmp_path / "image_2" / "000000_10.png").is_file() and (tmp_path / "flow_occ" / "000000_10.png").is_file()
        back = read_synthetic_pair(tmp_path, 0)
        assert torch.equal(back["valid"], pair["valid"])
        m = pair["valid"].expand(2, -1, -1)
        assert float((back["flow"] - pair["flow"]).abs()[m].max()) <= 1 / 128
        assert float((back["image1"] - pair["image1"]).abs().max()) <= 0.5
        assert torch.equal(back["road"], pair["road"]) and torch.equal(back["labels"], pair["labels"])
        assert torch.equal(back["flow_velocity"][m], pair["flow_velocity"][m])
        assert float((back["depth"] - pair["depth"]).abs().max()) <= 1 / 512 + 1e-6
        torch.testing.assert_close(back["camera"].K, pair["camera"].K)
        assert back["odometry"] == pair["odometry"] and back["velocity"] == pair["velocity"]
        params = json.loads((tmp_path / "params" / "000000.json").read_text())
        assert params["preset"] == "test" and params["size"] == [24, 40]
        P = read_kitti_calibration(tmp_path / "calib" / "000000.txt", 2)
        torch.testing.assert_close(P[:, :3], pair["camera"].K[0].double())

    def test_road_pose_and_plane_round_trip(self, tmp_path):
        pair = _pair()
        pair["road_pose"] = {"pitch": -0.021, "roll": 0.013, "height": 1.62}
        pair["plane"] = {"pitch_change": 1e-3, "yaw": 4e-3, "roll_change": -2e-3, "x_d": 0.02, "y_d": -0.004,
                         "z_d": 0.9, **pair["road_pose"]}
        write_synthetic_pair(tmp_path, 0, pair)
        back = read_synthetic_pair(tmp_path, 0)
        assert back["road_pose"] == pair["road_pose"] and back["plane"] == pair["plane"]
        # a folder written without them (older versions) reads without them
        write_synthetic_pair(tmp_path, 1, _pair(1))
        assert "road_pose" not in read_synthetic_pair(tmp_path, 1) and "plane" not in read_synthetic_pair(tmp_path, 1)

    def test_ground_truth_false(self, tmp_path):
        write_synthetic_pair(tmp_path, 3, _pair(3))
        back = read_synthetic_pair(tmp_path, 3, ground_truth=False)
        assert set(back) == {"image1", "image2", "camera", "index", "name"} and back["name"] == "000003"


class TestFeature:
    def test_poses_reproduce_odometry(self, tmp_path):
        pairs = [_pair(i) for i in range(3)]
        summary = write_synthetic_sequence(tmp_path, iter(pairs), meta={"preset": "test", "seed": 1})
        assert summary["num_pairs"] == 3 and summary["size"] == [24, 40] and summary["files"]["image_2"] == 6
        assert synthetic_pair_indices(tmp_path) == [0, 1, 2]
        poses = read_kitti_poses(tmp_path / "poses.txt")
        assert poses.shape == (4, 4, 4)
        for i, pair in enumerate(pairs):
            ego = ego_motion_from_pose(poses[i:i + 1], pair["camera"].to(torch.float64), pose1=poses[i + 1:i + 2])
            for key in ("x_d", "z_d", "yaw"):
                assert float(getattr(ego, key)) == pytest.approx(pair["odometry"][key], abs=1e-9)
        meta = json.loads((tmp_path / "meta.json").read_text())
        assert meta["num_pairs"] == 3 and meta["preset"] == "test" and meta["poses_world"] == "camera of the first frame"

    def test_renderer_poses_used_when_they_chain(self, tmp_path):
        pairs = [_pair(i, roll=0.0, pitch=0.0) for i in range(2)]
        chain = [torch.eye(4, dtype=torch.float64)]
        for p in pairs:
            T = relative_pose_from_odometry(p["camera"], **p["odometry"])
            chain.append(chain[-1] @ torch.linalg.inv(T))
        offset = torch.eye(4, dtype=torch.float64)
        offset[:3, 3] = torch.tensor([5.0, 0.0, 2.0])
        for i, p in enumerate(pairs):
            p["pose1"], p["pose2"] = offset @ chain[i], offset @ chain[i + 1]
        write_synthetic_sequence(tmp_path, pairs)
        poses = read_kitti_poses(tmp_path / "poses.txt")
        torch.testing.assert_close(poses, offset @ torch.stack(chain), atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(read_synthetic_pair(tmp_path, 1)["pose2"], pairs[1]["pose2"])

    @pytest.mark.parametrize("preset", ["default", "crest", "body-motion"])
    def test_rendered_poses_world_is_the_level_world_frame(self, tmp_path, preset):
        from fsof_torch.data.scene import render_sequence

        pairs = render_sequence(preset, 2, size=(12, 40))
        write_synthetic_sequence(tmp_path, pairs, meta={"preset": preset, "seed": 0})
        meta = json.loads((tmp_path / "meta.json").read_text())
        # on a grade or with body motion the frame-0 camera is not at the world's origin: the label
        # must hold for every preset
        assert meta["poses_world"].startswith("renderer's level world frame")
        assert "vehicle frame of frame 0" not in meta["poses_world"]
        poses = read_kitti_poses(tmp_path / "poses.txt")
        torch.testing.assert_close(poses[0], pairs[0]["pose1"], rtol=0, atol=1e-12)

    def test_flow_velocity_reads_back_0_off_the_valid_pixels_as_documented(self, tmp_path):
        from fsof_torch.data.scene import render_pair

        pair = render_pair("crest", 0, size=(12, 40))
        write_synthetic_pair(tmp_path, 0, pair)
        back = read_synthetic_pair(tmp_path, 0)
        valid = pair["valid"][0]
        assert bool((~valid).any()) and bool((pair["flow_velocity"][:, ~valid] != 0).any())
        assert bool((back["flow_velocity"][:, ~valid] == 0).all())
        assert torch.equal(back["flow_velocity"][:, valid], pair["flow_velocity"][:, valid])
        doc = " ".join(read_synthetic_pair.__doc__.split())
        assert "(0 off the valid pixels, where the file holds NaN;" in doc

    def test_relative_pose_inverts_ego_motion(self):
        camera = Camera(torch.eye(3, dtype=torch.float64), 1.5, 0.1, -0.05)
        T = relative_pose_from_odometry(camera, 0.3, 1.1, math.radians(4))
        ego = ego_motion_from_pose(T.unsqueeze(0), camera)
        assert float(ego.x_d) == pytest.approx(0.3) and float(ego.z_d) == pytest.approx(1.1)
        assert float(ego.yaw) == pytest.approx(math.radians(4)) and abs(float(ego.y_d)) < 1e-12

    def test_depth_png(self, tmp_path):
        depth = torch.tensor([[[0.0, 1.5, 300.0, float("inf")]]])
        write_depth_png(tmp_path / "d.png", depth)
        back, valid = read_depth_png(tmp_path / "d.png")
        assert valid.tolist() == [[[False, True, False, False]]] and float(back[0, 0, 1]) == 1.5

    def test_depth_png_codes_and_a_numpy_array(self, tmp_path):
        """A NumPy depth map was a TypeError saying 'expected a float tensor of shape (1, H, W)',
        which it was, save for being an array (every other writer here takes one)."""
        import cv2
        import numpy as np

        # (reversed: any strides and byte order) 10 m, at and just beyond 65535.5 / 256 m, just below
        # it, 0.003 m (code 0.77 -> 1), 1/512 m (code 0.5 -> 0), 1 m
        depth = np.array([[1.0, 1 / 512, 0.003, 255.998, 255.9981, 65535.5 / 256, 10.0]], dtype=">f8")[:, ::-1]
        write_depth_png(tmp_path / "d.png", depth)
        codes = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
        assert codes.dtype == np.uint16 and codes.tolist() == [[2560, 0, 0, 65535, 1, 0, 256]]  # round(d * 256)
        back, valid = read_depth_png(tmp_path / "d.png")
        assert back.dtype == torch.float32 and back[0].tolist() == [[10.0, 0.0, 0.0, 65535 / 256, 1 / 256, 0.0, 1.0]]
        assert valid[0].tolist() == [[True, False, False, True, True, False, True]]
        with pytest.raises(TypeError, match=r"^depth: expected a float tensor or array of shape \(1, H, W\), got "
                                             r"dtype torch\.int64"):
            write_depth_png(tmp_path / "e.png", np.ones((1, 2, 2), dtype=np.int64))
        with pytest.raises(TypeError, match=r"^depth: expected a float tensor or array .*got list"):
            write_depth_png(tmp_path / "e.png", [[1.0]])
        assert not (tmp_path / "e.png").exists()

    @pytest.mark.parametrize("name", ["d.jpg", "d.bmp", "d.tif"])
    def test_depth_png_only(self, tmp_path, name):
        """.jpg/.bmp raised naming `array`, no argument of the writer's; .tif wrote another format."""
        with pytest.raises(ValueError, match=r"^path: a depth map is written as \.png"):
            write_depth_png(tmp_path / name, torch.ones(1, 3, 4))
        assert list(tmp_path.iterdir()) == []


class TestExceptions:
    def test_missing_keys(self, tmp_path):
        pair = _pair()
        del pair["flow"]
        with pytest.raises(ValueError, match=r"missing keys \['flow'\]"):
            write_synthetic_pair(tmp_path, 0, pair)

    def test_not_a_layout(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="no params/ folder"):
            synthetic_pair_indices(tmp_path)
        (tmp_path / "params").mkdir()
        with pytest.raises(FileNotFoundError, match="no params file"):
            read_synthetic_pair(tmp_path, 0)

    def test_empty_sequence(self, tmp_path):
        with pytest.raises(ValueError, match="no pairs"):
            write_synthetic_sequence(tmp_path, [])

    def test_batched_camera_rejected(self, tmp_path):
        pair = _pair()
        pair["camera"] = pair["camera"].expand(2)
        with pytest.raises(ValueError, match="batch 1"):
            write_synthetic_pair(tmp_path, 0, pair)

    def test_files_of_another_size_than_the_images(self, tmp_path):
        from fsof_torch.io import write_kitti_flow, write_road_mask

        write_synthetic_sequence(tmp_path / "a", [_pair(0)])
        write_road_mask(tmp_path / "a" / "road" / "000000_10.png", torch.ones(1, 20, 20, dtype=torch.bool))
        with pytest.raises(ValueError, match=r"path: '.*road/000000_10\.png' is 20x20; .* is 24x40"):
            read_synthetic_pair(tmp_path / "a", 0)
        write_synthetic_sequence(tmp_path / "b", [_pair(0)])
        write_kitti_flow(tmp_path / "b" / "flow_occ" / "000000_10.png", torch.zeros(2, 24, 41))
        with pytest.raises(ValueError, match=r"path: '.*flow_occ/000000_10\.png' is 24x41"):
            read_synthetic_pair(tmp_path / "b", 0)
        write_synthetic_sequence(tmp_path / "c", [_pair(0)])
        write_depth_png(tmp_path / "c" / "depth" / "000000_10.png", torch.ones(1, 23, 40))
        with pytest.raises(ValueError, match=r"path: '.*depth/000000_10\.png' is 23x40"):
            read_synthetic_pair(tmp_path / "c", 0)

    @pytest.mark.parametrize("edit, message", [
        (lambda p: p.pop("odometry"), r"has no entry \['odometry'\]"),
        (lambda p: p["odometry"].pop("z_d"), r"has no entry \['odometry'\]\['z_d'\]"),
        (lambda p: p["camera"].pop("height"), r"has no entry \['camera'\]\['height'\]"),
        (lambda p: p["camera"].update(K=[[1, 0], [0, 1]]), r"\['camera'\]\['K'\] is not a 3×3 list"),
        (lambda p: p["odometry"].update(yaw="left"), r"\['odometry'\]\['yaw'\] is not a finite number: 'left'"),
        (lambda p: p.update(velocity=[1, 2]), r"\['velocity'\] is not an object of numbers"),
        (lambda p: p.update(pose1=[[1, 2]]), r"\['pose1'\] is not a 4×4 list of numbers"),
        (lambda p: p.update(pose1=_eye4(0, 3, float("nan"))), r"\['pose1'\] holds NaN or inf"),
        (lambda p: p.update(pose2=_eye4(0, 0, 5.0)), r"\['pose2'\] is not a rigid pose: its 3×3 block"),
        (lambda p: p.update(pose2=_eye4(3, 3, 2.0)), r"\['pose2'\] is not a rigid pose: its last row"),
    ])
    def test_params_without_what_a_pair_has(self, tmp_path, edit, message):
        from fsof_torch.io import read_synthetic_params

        write_synthetic_sequence(tmp_path, [_pair(0, with_poses=True)])
        path = tmp_path / "params" / "000000.json"
        params = json.loads(path.read_text())
        edit(params)
        path.write_text(json.dumps(params))
        with pytest.raises(ValueError, match=r"path: '.*000000\.json'" + ".*" + message):
            read_synthetic_pair(tmp_path, 0)
        if "velocity" not in message and "pose" not in message:
            with pytest.raises(ValueError, match=message):
                read_synthetic_params(tmp_path, 0)

    def test_binary_params_file(self, tmp_path):
        from fsof_torch.io import read_synthetic_params

        write_synthetic_sequence(tmp_path, [_pair(0)])
        (tmp_path / "params" / "000000.json").write_bytes(b"\xff\xfe\x00")
        with pytest.raises(ValueError, match=r"path: '.*000000\.json' is not a text \(UTF-8\) JSON file"):
            read_synthetic_params(tmp_path, 0)


class TestStalePairs:
    def test_meta_num_pairs_bounds_the_pairs(self, tmp_path):
        """Pairs beside a sequence (as an older, longer run left them): meta.json's count, not the files."""
        from fsof_torch.data.datasets import SyntheticFlowDataset

        write_synthetic_sequence(tmp_path, [_pair(5)])
        for index in (1, 2):
            write_synthetic_pair(tmp_path, index, _pair(index))
        assert synthetic_pair_indices(tmp_path) == [0]
        assert len(SyntheticFlowDataset(tmp_path)) == 1
        (tmp_path / "meta.json").unlink()  # without it, every params file counts
        assert synthetic_pair_indices(tmp_path) == [0, 1, 2]

    def test_a_pair_without_its_params_file_is_an_error_not_left_out(self, tmp_path):
        """params/000001.json lost from a sequence of three: the dataset had two pairs, its item 1
        the pair 000002."""
        from fsof_torch.data.datasets import SyntheticFlowDataset

        write_synthetic_sequence(tmp_path, [_pair(i) for i in range(3)])
        (tmp_path / "params" / "000001.json").unlink()
        match = r"^root: '.*' has meta\.json for 3 pairs but params/ lacks 1 of them \(000001\.json\)"
        with pytest.raises(FileNotFoundError, match=match):
            synthetic_pair_indices(tmp_path)
        with pytest.raises(FileNotFoundError, match=match):
            SyntheticFlowDataset(tmp_path)
        (tmp_path / "meta.json").unlink()  # without it, the params files there are the pairs
        assert synthetic_pair_indices(tmp_path) == [0, 2]

    @pytest.mark.parametrize("file, key", [("flow_velocity/000001_10.flo", "flow_velocity"),
                                           ("road/000001_10.png", "road"), ("semantic/000001_10.png", "labels"),
                                           ("depth/000001_10.png", "depth")])
    def test_a_lost_optional_file_is_an_error_not_a_pair_without_it(self, tmp_path, file, key):
        """A pair's road mask lost from a sequence written with road masks read as a pair without
        road (None), its depth as an item without the key."""
        write_synthetic_sequence(tmp_path, [_pair(i) for i in range(3)])
        (tmp_path / file).unlink()
        assert read_synthetic_pair(tmp_path, 0)[key] is not None
        with pytest.raises(FileNotFoundError, match=rf"^root: '.*' has no {file} for the pair 000001, but its "
                                                    r"meta\.json says every pair was written with one"):
            read_synthetic_pair(tmp_path, 1)
        assert read_synthetic_pair(tmp_path, 1, ground_truth=False)["name"] == "000001"

    def test_pairs_written_without_a_part_read_without_it(self, tmp_path):
        """Pairs written with and without an optional part (write_synthetic_sequence takes them)
        read back as written."""
        pairs = [_pair(i) for i in range(3)]
        del pairs[1]["depth"], pairs[2]["flow_velocity"]
        write_synthetic_sequence(tmp_path, pairs)
        back = [read_synthetic_pair(tmp_path, i) for i in range(3)]
        assert "depth" not in back[1] and "flow_velocity" not in back[2]
        assert "depth" in back[0] and "depth" in back[2] and "flow_velocity" in back[1]

    def test_a_folder_that_holds_files_is_refused(self, tmp_path):
        """Another run's optional files (road, depth, ...) or meta.json would be read as this run's."""
        write_synthetic_sequence(tmp_path / "seq", [_pair(i) for i in range(3)])
        rendered = []

        def pairs():
            for i in range(2):
                rendered.append(i)
                yield {k: v for k, v in _pair(i).items() if k not in ("road", "depth", "labels", "flow_velocity")}

        with pytest.raises(ValueError, match=r"root: '.*seq' already holds files \(calib, depth, flow_occ, "
                                             r"flow_velocity, \.\.\.\); give a new or empty folder"):
            write_synthetic_sequence(tmp_path / "seq", pairs())
        assert rendered == []  # refused before rendering anything
        assert synthetic_pair_indices(tmp_path / "seq") == [0, 1, 2]
        (tmp_path / "empty").mkdir()
        assert write_synthetic_sequence(tmp_path / "empty", pairs())["num_pairs"] == 2
        back = read_synthetic_pair(tmp_path / "empty", 0)
        assert not {"road", "depth", "labels", "flow_velocity"} & set(back)

    def test_only_ascii_digit_names_are_pairs(self, tmp_path):
        """'².json' is not a pair (str.isdigit accepts it, int() does not)."""
        write_synthetic_sequence(tmp_path, [_pair(0)])
        for name in ("².json", "٣.json", "1a.json"):
            (tmp_path / "params" / name).write_text("{}")
        (tmp_path / "meta.json").unlink()
        assert synthetic_pair_indices(tmp_path) == [0]

    @pytest.mark.parametrize("text", ['{"num_pairs": "2"}', '{"format": "x"}', "[1]", "{"])
    def test_bad_meta(self, tmp_path, text):
        write_synthetic_sequence(tmp_path, [_pair(0)])
        (tmp_path / "meta.json").write_text(text)
        with pytest.raises(ValueError, match=r"path: '.*meta\.json'"):
            synthetic_pair_indices(tmp_path)


@pytest.mark.parametrize("key, pose, match", [
    ("pose1", torch.full((4, 4), float("nan"), dtype=torch.float64), "holds NaN or inf"),
    ("pose2", 2 * torch.eye(4, dtype=torch.float64), "not a rigid pose"),
    ("pose1", torch.eye(3, dtype=torch.float64), r"expected a 4×4 pose, got shape \(3, 3\)"),
])
def test_writer_refuses_poses_its_reader_refuses(tmp_path, key, pose, match):
    """write_synthetic_pair wrote a pose that read_synthetic_pair then refused; now it refuses it
    first, before any file is written."""
    pair = dict(_pair(), **{key: pose})
    with pytest.raises(ValueError, match=rf"^pair\[{key!r}\]"):
        write_synthetic_pair(tmp_path / "out", 0, pair)
    with pytest.raises(ValueError, match=match):
        write_synthetic_pair(tmp_path / "out", 0, pair)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value", [600.0, -512.5])
def test_writer_refuses_a_flow_beyond_the_png_range_before_writing(tmp_path, value):
    """A valid flow beyond what flow_occ/'s KITTI PNG holds raised only after the pair's images were
    written (a half-written pair, no params); now nothing is written. Beyond it but invalid: kept."""
    pair = _pair()
    pair["flow"] = pair["flow"].clone()
    pair["flow"][1, 5, 7] = value
    pair["valid"] = pair["valid"].clone()
    pair["valid"][0, 5, 7] = True
    with pytest.raises(ValueError, match=r"^pair\['flow'\]: a KITTI flow PNG holds \[-512\.0, 511\.984375\] px, got "
                                         r"the range \[.*\] at valid pixels") as err:
        write_synthetic_pair(tmp_path / "out", 0, pair)
    assert repr(value) in str(err.value)
    assert not (tmp_path / "out").exists()
    pair["valid"][0, 5, 7] = False
    write_synthetic_pair(tmp_path / "out", 0, pair)
    assert not bool(read_synthetic_pair(tmp_path / "out", 0)["valid"][0, 5, 7])


@pytest.mark.parametrize("key, bad, err", [
    ("image2", lambda t: t / 255, ValueError),            # a 0..1 image: refused by write_image
    ("road", lambda t: t.to(torch.uint8), TypeError),     # a 0/1 uint8 mask: refused by write_road_mask
    ("labels", lambda t: t.float(), TypeError),           # float labels: refused by write_label_map
])
def test_a_pair_is_written_all_or_none(tmp_path, key, bad, err):
    """A value refused by its file's writer (the pair's second image, road mask, labels) raised
    after the files before it were written: a new folder kept image_2/, flow_occ/, ... without
    params/, and pair 0 written over an earlier pair 0 mixed the new images and flow with the old
    road, labels, depth and params, which read_synthetic_pair then read as one pair. Now nothing
    is written, and the earlier pair reads back as it was, file for file."""
    pair = dict(_pair(), **{key: bad(_pair()[key])})
    with pytest.raises(err):
        write_synthetic_pair(tmp_path / "new", 0, pair)
    assert not (tmp_path / "new").exists()

    root = tmp_path / "old"
    write_synthetic_pair(root, 0, _pair(index=3))
    before = {p.relative_to(root): p.read_bytes() for p in root.rglob("*") if p.is_file()}
    with pytest.raises(err):
        write_synthetic_pair(root, 0, pair)
    assert {p.relative_to(root): p.read_bytes() for p in root.rglob("*") if p.is_file()} == before
    assert read_synthetic_pair(root, 0)["odometry"]["x_d"] == pytest.approx(0.08)   # pair 3's x_d


def _files(root):
    return {p.relative_to(root): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def test_ctrl_c_while_a_pair_is_put_in_place_leaves_the_whole_pair(tmp_path, monkeypatch):
    """A Ctrl-C (SIGINT) that came while the written files were renamed onto their targets stopped
    the renames: eval synth left a pair's images and flow without its params/ file, and a pair
    written over read back as the new images and flow with the old params (odometry, poses,
    camera). Now the interrupt is held until every file is in place and raised after: the new
    pair reads back whole."""
    import os
    import signal

    from fsof_torch.io import atomic

    real_replace = os.replace

    def replace_then_interrupt(src, dst):
        real_replace(src, dst)
        if str(dst).endswith(os.path.join("image_2", "000000_10.png")):  # the first target of the pair
            signal.raise_signal(signal.SIGINT)

    root = tmp_path / "old"
    write_synthetic_pair(root, 0, _pair(index=3))
    monkeypatch.setattr(atomic.os, "replace", replace_then_interrupt)
    # Python's own Ctrl-C handler, whatever this process inherited (a shell's background job
    # starts with SIGINT ignored); and ignored, as such a process must go on ignoring it
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            write_synthetic_pair(root, 0, _pair(index=1))
        with pytest.raises(KeyboardInterrupt):
            write_synthetic_pair(tmp_path / "new", 0, _pair(index=1))
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        write_synthetic_pair(tmp_path / "ignored", 0, _pair(index=1))
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, inherited)
    monkeypatch.undo()
    write_synthetic_pair(tmp_path / "reference", 0, _pair(index=1))
    assert _files(root) == _files(tmp_path / "new") == _files(tmp_path / "ignored") == _files(tmp_path / "reference")


def test_a_pair_whose_files_fail_to_be_put_in_place_is_not_read_as_a_mix(tmp_path, monkeypatch):
    """A rename (or its fsync) that failed after the first files of a pair were in place left them
    there: new images and flow beside the old params/ file, read back as one pair. Now none of
    the pair's files stay, and the error propagates."""
    import os

    from fsof_torch.io import atomic

    real_replace = os.replace

    def replace_but_params(src, dst):
        if str(dst).endswith(os.path.join("params", "000000.json")):
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    root = tmp_path / "old"
    write_synthetic_pair(root, 0, _pair(index=3))
    write_synthetic_pair(root, 1, _pair(index=2))
    monkeypatch.setattr(atomic.os, "replace", replace_but_params)
    for folder in (root, tmp_path / "new"):
        with pytest.raises(OSError, match="No space left"):
            write_synthetic_pair(folder, 0, _pair(index=1))
    monkeypatch.undo()
    assert not (tmp_path / "new").exists()
    assert not [p for p in root.rglob("*") if p.is_file() and p.name.startswith("000000")]
    assert synthetic_pair_indices(root) == [1]
    assert read_synthetic_pair(root, 1)["odometry"]["x_d"] == pytest.approx(0.06)   # pair 1 untouched


class TestWriterChecks:
    """write_synthetic_pair once wrote what its readers cannot use, and meta= replaced the layout's
    own entries of meta.json."""

    @pytest.mark.parametrize("index, err, match", [(-1, ValueError, r"index: expected an int >= 0 .*got -1"),
                                                   (2.7, TypeError, r"index: expected an int >= 0, got float 2\.7"),
                                                   (True, TypeError, r"index: expected an int >= 0, got bool True")])
    def test_index_is_an_int_from_0(self, tmp_path, index, err, match):
        """-1 wrote '-00001.*' files no reader finds; 2.7 was written as pair 2."""
        with pytest.raises(err, match=match):
            write_synthetic_pair(tmp_path / "out", index, _pair())
        assert not (tmp_path / "out").exists()
        import numpy as np

        write_synthetic_pair(tmp_path / "ok", np.int64(2), _pair())
        assert synthetic_pair_indices(tmp_path / "ok") == [2]

    @pytest.mark.parametrize("key", ["image2", "flow", "valid", "flow_velocity", "road", "labels", "depth"])
    def test_every_tensor_has_the_size_of_the_images(self, tmp_path, key):
        """A flow of 12x20 beside 24x40 images was written and refused only when read back."""
        pair = _pair()
        pair[key] = pair[key][..., :12, :20]
        with pytest.raises(ValueError, match=rf"^pair\['{key}'\]: expected the size 24x40 of pair\['image1'\], got"):
            write_synthetic_pair(tmp_path / "out", 0, pair)
        assert not (tmp_path / "out").exists()

    @pytest.mark.parametrize("key, entry, value, err, match", [
        ("odometry", "x_d", float("nan"), ValueError, r"^pair\['odometry'\]\['x_d'\]: expected a finite number, got nan"),
        ("odometry", "yaw", float("inf"), ValueError, r"^pair\['odometry'\]\['yaw'\]: expected a finite number, got inf"),
        ("odometry", "z_d", None, ValueError, r"^pair\['odometry'\]: missing the entries \['z_d'\]"),
        ("odometry", "x_d", "abc", TypeError, r"^pair\['odometry'\]\['x_d'\]: expected a number, got str 'abc'"),
        ("velocity", "speed", float("nan"), ValueError, r"^pair\['velocity'\]\['speed'\]: expected a finite number"),
        ("velocity", "dt", torch.tensor(float("inf")), ValueError, r"^pair\['velocity'\]\['dt'\]: expected a finite"),
    ])
    def test_the_params_numbers_are_finite(self, tmp_path, key, entry, value, err, match):
        """A NaN odometry or velocity was written as JSON null: the pair was written whole, and
        read_synthetic_pair then refused its params file ('is not a finite number: None')."""
        pair = _pair()
        pair[key] = dict(pair[key])
        if value is None:
            del pair[key][entry]
        else:
            pair[key][entry] = value
        with pytest.raises(err, match=match):
            write_synthetic_pair(tmp_path / "out", 0, pair)
        assert not (tmp_path / "out").exists()
        pair[key][entry] = torch.tensor(0.25, dtype=torch.float64)  # (a 0-d tensor is a number)
        write_synthetic_pair(tmp_path / "ok", 0, pair)
        assert read_synthetic_pair(tmp_path / "ok", 0)[key][entry] == 0.25

    @pytest.mark.parametrize("value", [float("nan"), float("inf"), 1e39])
    def test_flow_velocity_is_finite_at_the_valid_pixels(self, tmp_path, value):
        """A NaN velocity at a valid pixel was written as NaN and read back as 0 at a pixel that
        read_synthetic_pair calls valid; 1e39 px/s (float64) was cast to inf, read back as 3.4e38."""
        pair = _pair()
        ys, xs = pair["valid"][0].nonzero()[0].tolist()
        pair["flow_velocity"] = pair["flow_velocity"].double()
        pair["flow_velocity"][1, ys, xs] = value
        with pytest.raises(ValueError, match=r"^pair\['flow_velocity'\]: expected finite values within float32's "
                                             r"range at the valid pixels \(pair\['valid'\]\)"):
            write_synthetic_pair(tmp_path / "out", 0, pair)
        assert not (tmp_path / "out").exists()
        pair["flow_velocity"][1, ys, xs] = 2.5
        off = (~pair["valid"][0]).nonzero()[0].tolist()  # (not stored off the valid pixels: any value goes)
        pair["flow_velocity"][:, off[0], off[1]] = float("inf")
        write_synthetic_pair(tmp_path / "ok", 0, pair)
        back = read_synthetic_pair(tmp_path / "ok", 0)
        assert float(back["flow_velocity"][1, ys, xs]) == 2.5 and back["flow_velocity"][:, off[0], off[1]].tolist() == [0, 0]

    def test_numpy_arrays_in_a_pair(self, tmp_path):
        """The checks took NumPy arrays for valid, flow_velocity and the poses, and writing them
        then failed with AttributeError ('numpy.ndarray' object has no attribute 'cpu' / 'detach')."""
        pair = _pair()
        pose = torch.eye(4, dtype=torch.float64)
        pair.update(pose1=pose, pose2=pose)
        arrays = dict(pair, **{k: pair[k].numpy() for k in ("valid", "flow_velocity", "pose1", "pose2")})
        write_synthetic_pair(tmp_path / "a", 0, pair)
        write_synthetic_pair(tmp_path / "b", 0, arrays)
        for part in ("flow_velocity/000000_10.flo", "flow_occ/000000_10.png", "params/000000.json"):
            assert (tmp_path / "a" / part).read_bytes() == (tmp_path / "b" / part).read_bytes(), part

    def test_extra_cannot_replace_the_params(self, tmp_path):
        with pytest.raises(ValueError, match=r"^extra: \['camera', 'size'\] are keys the params JSON holds itself"):
            write_synthetic_pair(tmp_path / "out", 0, _pair(), extra={"size": [1, 1], "camera": None, "preset": "x"})
        assert not (tmp_path / "out").exists()

    def test_meta_cannot_replace_the_layouts_entries(self, tmp_path):
        """meta={'num_pairs': 1} once made a 3-pair sequence read back as 1 pair."""
        rendered = []

        def pairs():
            for i in range(3):
                rendered.append(i)
                yield _pair(i)

        with pytest.raises(ValueError, match=r"^meta: \['format', 'num_pairs'\] are entries meta\.json holds itself"):
            write_synthetic_sequence(tmp_path / "seq", pairs(), meta={"num_pairs": 1, "format": "mine", "seed": 1})
        assert rendered == [] and not (tmp_path / "seq").exists()


class TestPosesChain:
    """poses.txt's row i is the camera of pair i's first frame: true only of consecutive frames."""

    def _posed_pairs(self, breaks):
        pairs = [_pair(i, roll=0.0, pitch=0.0) for i in range(3)]
        pose = torch.eye(4, dtype=torch.float64)
        for i, p in enumerate(pairs):
            if i == breaks:  # a gap: this pair starts 6 m further on
                pose = pose.clone()
                pose[2, 3] += 6.0
            p["pose1"] = pose
            pose = pose @ torch.linalg.inv(relative_pose_from_odometry(p["camera"], **p["odometry"]))
            p["pose2"] = pose
        return pairs

    def test_pairs_that_are_not_consecutive_frames_get_no_poses_file(self, tmp_path):
        """A broken chain was written as the chain of the pairs' relative motions, so row 2 was the
        camera of 000001_11, 6 m off the camera of 000002_10."""
        pairs = self._posed_pairs(breaks=2)
        write_synthetic_sequence(tmp_path, pairs)
        assert not (tmp_path / "poses.txt").exists()
        meta = json.loads((tmp_path / "meta.json").read_text())
        assert meta["poses_world"] is None
        assert meta["poses_missing"].startswith("pair 2's pose1 is not pair 1's pose2: the pairs are not consecutive")
        torch.testing.assert_close(read_synthetic_pair(tmp_path, 2)["pose1"], pairs[2]["pose1"])

    def test_a_pair_without_poses_among_posed_ones(self, tmp_path):
        pairs = self._posed_pairs(breaks=None)
        del pairs[1]["pose1"], pairs[1]["pose2"]
        write_synthetic_sequence(tmp_path, pairs)
        assert not (tmp_path / "poses.txt").exists()
        assert json.loads((tmp_path / "meta.json").read_text())["poses_missing"].startswith("pair 1 has no pose1/pose2")

    def test_consecutive_pairs_keep_their_poses(self, tmp_path):
        pairs = self._posed_pairs(breaks=None)
        write_synthetic_sequence(tmp_path, pairs)
        poses = read_kitti_poses(tmp_path / "poses.txt")
        torch.testing.assert_close(poses, torch.stack([pairs[0]["pose1"]] + [p["pose2"] for p in pairs]))
        assert "poses_missing" not in json.loads((tmp_path / "meta.json").read_text())


class TestReaderChecks:
    def test_each_pair_counts_once(self, tmp_path):
        """'1.json' and '0000001.json' beside '000001.json' once made pair 1 count three times."""
        write_synthetic_sequence(tmp_path, [_pair(i) for i in range(3)])
        for name in ("1.json", "0000001.json", "00000.json"):
            (tmp_path / "params" / name).write_bytes((tmp_path / "params" / "000001.json").read_bytes())
        assert synthetic_pair_indices(tmp_path) == [0, 1, 2]
        (tmp_path / "meta.json").unlink()
        assert synthetic_pair_indices(tmp_path) == [0, 1, 2]
        write_synthetic_pair(tmp_path, 1234567, _pair())  # beyond six digits, pair_name's own name
        assert synthetic_pair_indices(tmp_path) == [0, 1, 2, 1234567]

    @pytest.mark.parametrize("entry", ["height", "K", "roll", "pitch", "x_d", "pose1"])
    def test_integers_beyond_float64(self, tmp_path, entry):
        """JSON takes any integer: 10**400 raised OverflowError rather than the ValueError naming
        the file and the entry."""
        from fsof_torch.io import read_synthetic_params

        write_synthetic_sequence(tmp_path, [_pair(0)])
        path = tmp_path / "params" / "000000.json"
        params = json.loads(path.read_text())
        huge = 10 ** 400
        if entry == "K":
            params["camera"]["K"][0][0] = huge
        elif entry == "x_d":
            params["odometry"]["x_d"] = huge
        elif entry == "pose1":
            params["pose1"] = _eye4(0, 3, huge)
        else:
            params["camera"][entry] = huge
        path.write_text(json.dumps(params))
        where = {"K": r"\['camera'\]\['K'\] is not a 3×3 list of finite numbers", "x_d": r"\['odometry'\]\['x_d'\]",
                 "pose1": r"\['pose1'\] is not a 4×4 list of numbers"}.get(entry, rf"\['camera'\]\['{entry}'\]")
        with pytest.raises(ValueError, match=rf"^path: '.*000000\.json'{where}"):
            read_synthetic_pair(tmp_path, 0)
        if entry != "pose1":
            with pytest.raises(ValueError, match=where):
                read_synthetic_params(tmp_path, 0)
        path.write_text('{"camera": {"height": ' + "1" * 5000 + "}}")
        with pytest.raises(ValueError, match=r"^path: '.*000000\.json' is not valid JSON"):
            read_synthetic_params(tmp_path, 0)

    @pytest.mark.parametrize("kwargs, err, match", [
        ({"index": 0.5}, TypeError, r"^index: expected an int, got float 0\.5"),
        ({"index": -1}, ValueError, r"^index: expected an int >= 0, got -1"),
        ({"index": True}, TypeError, r"^index: expected an int, got bool True"),
        ({"dtype": torch.int64}, TypeError, r"^dtype: expected a floating-point torch dtype .*got torch\.int64"),
        ({"dtype": "float32"}, TypeError, r"^dtype: expected a floating-point torch dtype .*got 'float32'"),
        ({"ground_truth": "no"}, TypeError, r"^ground_truth: expected True or False, got str 'no'"),
    ])
    def test_arguments_are_checked(self, tmp_path, kwargs, err, match):
        """index=0.5 read pair 0, ground_truth='no' read the ground truth, and dtype=torch.int64 or
        'float32' was blamed on the file ("path: '.../000000.json' holds a camera that is not valid")."""
        from fsof_torch.io import camera_from_params, read_synthetic_params

        write_synthetic_sequence(tmp_path, [_pair(0)])
        call = {"index": 0, **kwargs}
        index = call.pop("index")
        with pytest.raises(err, match=match):
            read_synthetic_pair(tmp_path, index, **call)
        if "index" in kwargs:
            with pytest.raises(err, match=match):
                read_synthetic_params(tmp_path, index)
        if "dtype" in kwargs:
            with pytest.raises(err, match=match):
                camera_from_params(read_synthetic_params(tmp_path, 0), kwargs["dtype"])
        back = read_synthetic_pair(tmp_path, torch.tensor(0), dtype=torch.float64, ground_truth=False)
        assert back["index"] == 0 and back["image1"].dtype == torch.float64 and "flow" not in back

    def test_folders_in_place_of_files(self, tmp_path):
        """A folder was 'no params file', or skipped as a missing optional part."""
        write_synthetic_sequence(tmp_path / "a", [_pair(0)])
        (tmp_path / "a" / "road" / "000000_10.png").unlink()
        (tmp_path / "a" / "road" / "000000_10.png").mkdir()
        with pytest.raises(IsADirectoryError, match=r"^path: '.*road/000000_10\.png' is a folder"):
            read_synthetic_pair(tmp_path / "a", 0)
        (tmp_path / "b" / "params" / "000000.json").mkdir(parents=True)
        with pytest.raises(IsADirectoryError, match=r"^path: '.*params/000000\.json' is a folder"):
            read_synthetic_pair(tmp_path / "b", 0)
        (tmp_path / "b" / "meta.json").mkdir()
        with pytest.raises(IsADirectoryError, match=r"^path: '.*meta\.json' is a folder"):
            synthetic_pair_indices(tmp_path / "b")


@pytest.mark.parametrize("file", ["image_2/000001_11.png", "flow_occ/000001_10.png", "road/000001_10.png",
                                  "depth/000001_10.png", "params/000001.json"])
def test_a_link_to_a_missing_file_says_so(tmp_path, file):
    """A pair's file linked from a drive that is not mounted read as 'no file at' (or, for an
    optional part, as a file lost in a copy), sending the user to look for a file that is there."""
    write_synthetic_sequence(tmp_path / "seq", [_pair(i) for i in range(2)])
    (tmp_path / "seq" / file).unlink()
    (tmp_path / "seq" / file).symlink_to(tmp_path / "unmounted" / "x")
    with pytest.raises(FileNotFoundError, match=rf"^path: '.*seq/{file}' is a symbolic link to '.*unmounted/x', "
                                                r"which does not exist; mount or copy the data"):
        read_synthetic_pair(tmp_path / "seq", 1)
