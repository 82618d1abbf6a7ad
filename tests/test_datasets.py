"""fsof_torch.data.datasets: pair datasets over the synthetic layout, KITTI layouts, the shared samples,
CARLA runs; collate with DataLoader."""

from __future__ import annotations

import math
import re
import shutil

import cv2
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from fsof_torch.geometry.camera import Camera
from fsof_torch.data.datasets import (
    ITEM_KEYS,
    CarlaRunDataset,
    ImageFolderDataset,
    KittiFlowDataset,
    KittiOdometryDataset,
    KittiSampleDataset,
    SceneDataset,
    SyntheticFlowDataset,
    check_item,
    collate,
    concat_cameras,
)
from fsof_torch.geometry.road_flow import displacement_flow
from fsof_torch.io import (
    write_carla_flow,
    write_image,
    write_kitti_calibration,
    write_kitti_flow,
    write_kitti_poses,
    write_synthetic_sequence,
)

SIZE = (24, 40)


def _plane_pair(i, size=SIZE):
    """Pair i: its own camera (focal length, height, roll) and odometry."""
    h, w = size
    f = 40.0 + 2.0 * i
    camera = Camera(torch.tensor([[f, 0, 19.5], [0, f, 6.0], [0, 0, 1]]), 1.6 + 0.1 * i, 0.02 + 0.01 * i, 0.0)
    odo = {"x_d": 0.01 * i, "z_d": 0.8, "yaw": 0.002 * i}
    flow, valid = displacement_flow(camera, odo["x_d"], odo["z_d"], odo["yaw"], size)
    g = torch.Generator().manual_seed(i)
    return {"image1": torch.rand(3, h, w, generator=g) * 255, "image2": torch.rand(3, h, w, generator=g) * 255,
            "flow": flow[0], "valid": valid[0], "road": valid[0].clone(), "camera": camera, "odometry": odo}


@pytest.fixture
def synthetic_root(tmp_path):
    pairs = [_plane_pair(i) for i in range(3)]
    write_synthetic_sequence(tmp_path / "seq", pairs)
    return tmp_path / "seq", pairs


def _colour_image(r, g, b, size=SIZE):
    """(3, H, W) integer values: channels r, g, b, each plus the column index (an RGB/BGR swap,
    a channel out of order, changes the values)."""
    x = torch.arange(size[1], dtype=torch.float32).expand(*size)
    return torch.stack([x + r, x + g, x + b])


def _uv_ramps(i, size=SIZE):
    """(2, H, W) flow of distinct u and v (u a ramp along x, v one along y; multiples of 1/64, as
    KITTI's PNG stores them): a u/v swap changes it."""
    h, w = size
    u = torch.arange(w, dtype=torch.float32).expand(h, w) * 0.25 - 3.0 + i
    v = torch.arange(h, dtype=torch.float32)[:, None].expand(h, w) * -0.5 + 1.0 + i
    return torch.stack([u, v])


@pytest.fixture
def kitti_root(tmp_path):
    """A KITTI 2015-like training folder with the paper's semantic hand labels (road = red)."""
    root = tmp_path / "kitti"
    for sub in ("image_2", "flow_noc", "calib_cam_to_cam", "semantic"):
        (root / sub).mkdir(parents=True)
    K = torch.tensor([[50.0, 0, 20.0], [0, 50.0, 8.0], [0, 0, 1]], dtype=torch.float64)
    for i in range(2):
        name = f"{i:06d}"
        write_image(root / "image_2" / f"{name}_10.png", _colour_image(10 * i, 80 + 10 * i, 160 + 10 * i))
        write_image(root / "image_2" / f"{name}_11.png", _colour_image(200, 20, 100))
        valid = torch.zeros(1, *SIZE, dtype=torch.bool)
        valid[:, 10:] = True
        write_kitti_flow(root / "flow_noc" / f"{name}_10.png", _uv_ramps(i), valid)
        write_kitti_calibration(root / "calib_cam_to_cam" / f"{name}.txt", K)
        sem = np.zeros((*SIZE, 3), np.uint8)
        sem[15:, :, 2] = 255  # red in BGR
        cv2.imwrite(str(root / "semantic" / f"{name}_10.png"), sem)
    return root, K


class TestSynthetic:
    def test_items(self, synthetic_root):
        root, pairs = synthetic_root
        ds = SyntheticFlowDataset(root)
        assert len(ds) == 3
        item = ds[1]
        assert item["image1"].shape == (3, *SIZE) and item["image1"].dtype == torch.float32
        assert torch.equal(item["valid"], pairs[1]["valid"])
        m = item["valid"].expand(2, -1, -1)
        assert float((item["flow"] - pairs[1]["flow"]).abs()[m].max()) <= 1 / 64
        assert item["odometry"] == pytest.approx(pairs[1]["odometry"])
        assert isinstance(item["camera"], Camera) and item["camera"].batch_size == 1
        assert ds[-1]["index"] == 2

    def test_dataloader_batches(self, synthetic_root):
        root, _ = synthetic_root
        ds = SyntheticFlowDataset(root)
        batch = next(iter(DataLoader(ds, batch_size=3, collate_fn=collate)))
        assert batch["image1"].shape == (3, 3, *SIZE) and batch["flow"].shape == (3, 2, *SIZE)
        assert batch["valid"].shape == (3, 1, *SIZE) and batch["valid"].dtype == torch.bool
        assert batch["camera"].batch_size == 3
        assert batch["odometry"]["z_d"].shape == (3,) and batch["odometry"]["x_d"].dtype == torch.float32
        assert batch["index"] == [0, 1, 2] and batch["name"] == ["000000", "000001", "000002"]
        # sample b of every key is item b's (each item its own odometry and camera)
        items = [ds[i] for i in range(3)]
        for key in ("x_d", "z_d", "yaw"):
            assert batch["odometry"][key].tolist() == [torch.tensor(it["odometry"][key], dtype=torch.float32).item()
                                                      for it in items], key
        assert batch["odometry"]["x_d"].unique().numel() == 3
        for b, it in enumerate(items):
            assert torch.equal(batch["image1"][b], it["image1"]) and torch.equal(batch["flow"][b], it["flow"])
            for field in ("K", "height", "roll", "pitch"):
                assert torch.equal(getattr(batch["camera"], field)[b], getattr(it["camera"], field)[0]), (b, field)
        assert batch["camera"].height.unique().numel() == 3

    @pytest.mark.parametrize("ground_truth", [True, False])
    def test_a_pair_file_lost_names_root(self, synthetic_root, ground_truth):
        """The reader's own argument, 'path', named a file of the folder the dataset was given as
        root ('path: no file at ...')."""
        root, _ = synthetic_root
        (root / "image_2" / "000001_11.png").unlink()
        (root / "params" / "000002.json").write_text("{")
        ds = SyntheticFlowDataset(root, ground_truth=ground_truth)
        assert ds[0]["index"] == 0
        with pytest.raises(FileNotFoundError, match=r"^root: no file at '.*000001_11\.png'$"):
            ds[1]
        with pytest.raises(ValueError, match=r"^root: '.*params/000002\.json' is not valid JSON"):
            ds[2]
        with pytest.raises(ValueError, match=r"^root: '.*params/000002\.json' is not valid JSON"):
            SyntheticFlowDataset(root, camera_dtype=torch.float64, ground_truth=ground_truth)[2]

    def test_float64_and_no_ground_truth(self, synthetic_root):
        root, _ = synthetic_root
        item = SyntheticFlowDataset(root, dtype=torch.float64, ground_truth=False)[0]
        assert item["flow"] is None and item["road"] is None and item["odometry"] is None
        assert item["image1"].dtype == torch.float64 and item["camera"].dtype == torch.float64


class TestKittiLayout:
    def test_items(self, kitti_root):
        root, K = kitti_root
        ds = KittiFlowDataset(root)
        assert len(ds) == 2 and ds.names == ["000000", "000001"]
        item = ds[1]
        # channel by channel: image 1 in RGB order, u and v each in its own channel
        want = _colour_image(10, 90, 170)
        for c in range(3):
            assert torch.equal(item["image1"][c], want[c]), c
        assert torch.equal(item["image2"], _colour_image(200, 20, 100))
        assert torch.equal(item["valid"][0, 10:], torch.ones(SIZE[0] - 10, SIZE[1], dtype=torch.bool))
        assert not item["valid"][0, :10].any()
        want = _uv_ramps(1)
        for c in range(2):
            assert torch.equal(item["flow"][c, 10:], want[c, 10:]), "uv"[c]
        torch.testing.assert_close(item["camera"].K[0].double(), K)
        assert item["road"].shape == (1, *SIZE) and item["road"][0, 15:].all() and not item["road"][0, :15].any()
        batch = collate([ds[0], ds[1]])
        assert batch["flow"].shape == (2, 2, *SIZE) and batch["camera"].batch_size == 2

    def test_occ_missing_and_K_override(self, kitti_root):
        root, _ = kitti_root
        for p in (root / "calib_cam_to_cam").iterdir():
            p.unlink()
        K = torch.tensor([[30.0, 0, 18.0], [0, 30.0, 10.0], [0, 0, 1]])  # (the centre of these 24x40 images)
        # flow_noc/ alone, flow_occ/ asked for: named (a synthetic layout holds flow_occ/ alone, and
        # flow="noc" read no flow from it, silently)
        with pytest.raises(ValueError, match=r"^flow: .* has flow_noc/ but no flow_occ/; pass flow='noc'"):
            KittiFlowDataset(root, flow="occ")
        import shutil

        shutil.rmtree(root / "flow_noc")  # neither: a test folder, no ground-truth flow
        item = KittiFlowDataset(root, flow="occ", K=K, camera_height=1.7)[0]
        assert item["flow"] is None and item["valid"] is None and float(item["camera"].height) == pytest.approx(1.7)
        torch.testing.assert_close(item["camera"].K[0], K)
        assert KittiFlowDataset(root)[0]["camera"] is None

    def test_reads_the_synthetic_layout(self, synthetic_root):
        root, pairs = synthetic_root
        item = KittiFlowDataset(root, flow="occ")[0]
        torch.testing.assert_close(item["camera"].K[0], pairs[0]["camera"].K[0])
        assert torch.equal(item["road"], pairs[0]["road"]) and torch.equal(item["valid"], pairs[0]["valid"])
        with pytest.raises(ValueError, match=r"has flow_occ/ but no flow_noc/; pass flow='occ'"):
            KittiFlowDataset(root)

    def test_errors(self, tmp_path):
        with pytest.raises(ValueError, match="flow: expected 'noc' or 'occ'"):
            KittiFlowDataset(tmp_path, flow="all")
        with pytest.raises(FileNotFoundError, match="no image_2/ folder"):
            KittiFlowDataset(tmp_path)
        (tmp_path / "image_2").mkdir()
        with pytest.raises(ValueError, match="no NAME_10.png"):
            KittiFlowDataset(tmp_path)


class TestCarla:
    def test_run(self, tmp_path):
        run = tmp_path / "t10_s0_r-5"
        for sub in ("rgb", "optical_flow", "semantic"):
            (run / sub).mkdir(parents=True)
        for k in range(3):
            name = f"{k:08d}"
            write_image(run / "rgb" / f"{name}.png", _colour_image(5 * k, 100 + 5 * k, 200 - 5 * k, (12, 16)))
            write_carla_flow(run / "optical_flow" / f"{name}.tif", _uv_ramps(k, (12, 16)))
            sem = np.zeros((12, 16, 3), np.uint8)  # (cv2 writes BGR)
            sem[5] = (157, 234, 50)  # RGB (50, 234, 157): not road, the road line's colour reversed
            sem[6:9] = (128, 64, 128)  # road (the same in either order)
            sem[9:] = (50, 234, 157)  # RGB (157, 234, 50): road line
            cv2.imwrite(str(run / "semantic" / f"{name}.png"), sem)
        ds = CarlaRunDataset(run)
        assert len(ds) == 2
        item = ds[1]
        for c in range(3):  # channel by channel, in RGB order
            assert torch.equal(item["image1"][c], _colour_image(5, 105, 195, (12, 16))[c]), c
            assert torch.equal(item["image2"][c], _colour_image(10, 110, 190, (12, 16))[c]), c
        for c in range(2):  # frame 1's flow, u and v each in its own channel
            torch.testing.assert_close(item["flow_velocity"][c], _uv_ramps(1, (12, 16))[c], rtol=0, atol=1e-5)
        assert float(item["camera"].roll) == pytest.approx(math.radians(-5))
        road = torch.zeros(12, 16, dtype=torch.bool)
        road[6:] = True
        assert torch.equal(item["road"][0], road)


class TestExceptions:
    def test_collate_errors(self, synthetic_root):
        root, _ = synthetic_root
        ds = SyntheticFlowDataset(root)
        a, b = ds[0], ds[1]
        del b["road"]
        with pytest.raises(ValueError, match=r"item 1 has different keys.*road"):
            collate([a, b])
        c = dict(ds[1])
        c["image1"] = c["image1"][:, :10]
        with pytest.raises(ValueError, match="'image1' has different shapes"):
            collate([ds[0], c])
        with pytest.raises(ValueError, match="non-empty"):
            collate([])

    def test_index_errors(self, synthetic_root):
        ds = SyntheticFlowDataset(synthetic_root[0])
        with pytest.raises(IndexError, match="out of range"):
            ds[3]
        with pytest.raises(TypeError, match="index: expected an int"):
            ds["0"]

    def test_concat_cameras(self):
        a = Camera(torch.eye(3), 1.5)
        b = Camera(torch.eye(3, dtype=torch.float64).expand(2, 3, 3), 1.6, 0.1)
        c = concat_cameras([a, b])
        assert c.batch_size == 3 and c.dtype == torch.float64 and c.roll.tolist() == [0.0, 0.1, 0.1]


    @pytest.mark.parametrize("kwargs, error, message", [
        ({"camera_height": "abc"}, TypeError, r"^camera_height: expected a number, got str 'abc'"),
        ({"camera_height": -1.0}, ValueError, r"^camera_height: expected a positive number \(> 0\), got -1\.0"),
        ({"camera_height": float("nan")}, ValueError, r"^camera_height: expected a finite number"),
        ({"cam": 7}, ValueError, r"^cam: expected 0\.\.3, got 7"),
        ({"image_dir": None}, TypeError, r"^image_dir: expected a file path .*got NoneType None"),
        # (once TypeError "new(): invalid data type 'str'" and a ValueError from torch, naming no argument)
        ({"K": "721"}, TypeError, r"^K: expected a \(3, 3\) tensor or array of numbers, got str '721'"),
        ({"K": [[1, 2], [3]]}, TypeError, r"^K: expected a \(3, 3\) tensor or array of numbers, got list "
                                          r"\[\[1, 2\], \[3\]\]"),
    ])
    def test_kitti_flow_arguments_checked_at_construction(self, kitti_root, kwargs, error, message):
        """Not at the first item (camera_height=-1 and cam=7 were accepted until then)."""
        with pytest.raises(error, match=message):
            KittiFlowDataset(kitti_root[0], **kwargs)

    @pytest.mark.parametrize("height, error, message", [
        ("abc", TypeError, r"^camera_height: expected a number, got str 'abc'"),
        (0.0, ValueError, r"^camera_height: expected a positive number \(> 0\), got 0\.0"),
    ])
    def test_carla_arguments_checked_at_construction(self, tmp_path, height, error, message):
        run = tmp_path / "t10_s0_r-5"
        (run / "rgb").mkdir(parents=True)
        for k in range(2):
            write_image(run / "rgb" / f"{k:08d}.png", _colour_image(0, 0, 0, (12, 16)))
        with pytest.raises(error, match=message):
            CarlaRunDataset(run, camera_height=height)
        with pytest.raises(TypeError, match=r"^run: expected a file path"):
            CarlaRunDataset(None)


    def test_carla_roll_from_the_folder_itself(self, tmp_path, monkeypatch):
        """'.' or 'run/rgb/..' named no run: the roll of 't10_s0_r-5' came out 0."""
        run = tmp_path / "t10_s0_r-5"
        (run / "rgb").mkdir(parents=True)
        for k in range(2):
            write_image(run / "rgb" / f"{k}.png", _colour_image(0, 0, 0, (12, 16)))
        monkeypatch.chdir(run)
        for given in (run, ".", run / "rgb" / ".."):
            ds = CarlaRunDataset(given)
            assert math.degrees(float(ds[0]["camera"].roll)) == pytest.approx(-5.0), given
            assert len(ds) == 1

    def test_a_carla_run_of_one_frame_is_refused(self, tmp_path):
        run = tmp_path / "t10_s0_r0"
        (run / "rgb").mkdir(parents=True)
        write_image(run / "rgb" / "0.png", _colour_image(0, 0, 0, (12, 16)))
        with pytest.raises(ValueError, match=r"^run: '.*t10_s0_r0' holds no pairs \(1 frame in rgb/\)"):
            CarlaRunDataset(run)  # was an empty dataset

    def test_a_bad_carla_run_names_run(self, tmp_path):
        """The errors of a run that is no run named 'root' (or 'name'), an argument CarlaRunDataset
        does not have; a missing folder said it had no rgb/ folder."""
        (tmp_path / "file.txt").write_text("x")
        (tmp_path / "empty").mkdir()
        (tmp_path / "nopng" / "rgb").mkdir(parents=True)
        bad_roll = tmp_path / "t10_r+5"
        (bad_roll / "rgb").mkdir(parents=True)
        for k in range(2):
            write_image(bad_roll / "rgb" / f"{k}.png", _colour_image(0, 0, 0, (12, 16)))
        (tmp_path / "linked").symlink_to(tmp_path / "unmounted")
        for given, error, message in [
                (tmp_path / "missing", FileNotFoundError, rf"^run: no folder at '{re.escape(str(tmp_path))}/missing'$"),
                (tmp_path / "file.txt", FileNotFoundError, r"^run: '.*file\.txt' is a file; expected a folder$"),
                (tmp_path / "linked", FileNotFoundError, r"^run: '.*linked' is a symbolic link to '.*unmounted', "
                                                         r"which does not exist"),
                (tmp_path / "empty", FileNotFoundError, r"^run: '.*empty' has no rgb/ folder"),
                (tmp_path / "nopng", ValueError, r"^run: '.*nopng/rgb' holds no PNG frames$"),
                (bad_roll, ValueError, r"^run: the run 't10_r\+5' has the part 'r\+5'; expected the roll as 'r'")]:
            with pytest.raises(error, match=message):
                CarlaRunDataset(given)

    @pytest.mark.parametrize("kwargs, message", [
        ({"roll": 1.6}, r"^roll: expected \|θ\| < π/2 rad"),
        ({"pitch": -1.6}, r"^pitch: expected \|β\| < π/2 rad"),
        ({"camera_height": 1e300}, r"^camera_height: expected a camera height in \[3.89e-62, 2.57e\+61\] m"),
        ({"camera_height": 1e10}, r"^camera_height: expected a camera height in \[2.98e-08, 3.36e\+07\] m "
                                  r"for a torch.float32 camera"),
    ])
    def test_a_bad_mounting_names_the_argument_not_calib(self, shared_data, kwargs, message):
        with pytest.raises(ValueError, match=message):
            KittiSampleDataset(shared_data / "kitti15_000000", **kwargs)
        with pytest.raises(ValueError, match=message):  # ("calib: '...' camera 2: roll: ..." before)
            KittiOdometryDataset(shared_data / "kitti_odometry_straight", **kwargs)
        if "camera_height" in kwargs:
            with pytest.raises(ValueError, match=message):
                KittiFlowDataset(shared_data / "kitti15_000000", **kwargs)


def _odometry_clip(root, names):
    """A KITTI odometry folder: image_l/NAME.png for each of ``names``, calib.txt, 4 poses."""
    (root / "image_l").mkdir(parents=True)
    for name in names:
        write_image(root / "image_l" / f"{name}.png", _colour_image(0, 0, 0, (6, 8)))
    poses = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    poses[:, 2, 3] = torch.arange(4.0)
    write_kitti_poses(root / "poses.txt", poses)
    write_kitti_calibration(root / "calib.txt", torch.tensor([[10.0, 0, 3.5], [0, 10, 2.5], [0, 0, 1]]), cam=0,
                            style="odometry")
    return root


class TestOdometryFrames:
    def test_two_files_of_one_frame_are_refused(self, tmp_path):
        """2.png beside 000002.png was paired with it (a pair of one frame, z_d 0)."""
        root = _odometry_clip(tmp_path / "odo", ["000000", "000001", "000002", "2", "000003"])
        with pytest.raises(ValueError, match=r"^folder: '.*odo/image_l' has two files of frame 2, 000002\.png "
                                             r"and 2\.png; keep one"):
            KittiOdometryDataset(root)

    def test_only_ascii_digit_names_are_frames(self, tmp_path):
        """'\u00b2.png' passed str.isdigit and then failed int() ('invalid literal for int()')."""
        root = _odometry_clip(tmp_path / "odo", ["000000", "000001", "000002", "000003", "\u00b2"])
        ds = KittiOdometryDataset(root)
        assert [(p.image1.name, p.image2.name) for p in ds.pairs] == [
            ("000000.png", "000001.png"), ("000001.png", "000002.png"), ("000002.png", "000003.png")]
        assert [ds[i]["odometry"]["z_d"] for i in range(3)] == pytest.approx([1.0, 1.0, 1.0])

    def test_image_dir_that_is_no_path_is_named(self, tmp_path):
        """image_dir=5 raised Python's "unsupported operand type(s) for /: 'PosixPath' and 'int'"."""
        root = _odometry_clip(tmp_path / "odo", ["000000", "000001"])
        with pytest.raises(TypeError, match=r"^image_dir: expected a file path \(str or os.PathLike\), got int 5$"):
            KittiOdometryDataset(root, image_dir=5)

    @pytest.mark.parametrize("names, others", [(["frame_000000", "frame_000001"], "frame_000000.png, frame_000001.png"),
                                               (["000000"], None), ([], None)])
    @pytest.mark.parametrize("ground_truth", [True, False])
    def test_a_clip_without_frames_says_so(self, tmp_path, names, others, ground_truth):
        """Frames not named by a number, JPEGs, one frame or none: 'has no frame pairs with poses',
        also with ground_truth=False (no poses read), sent the caller to poses.txt."""
        root = _odometry_clip(tmp_path / "odo", names)
        if not names:
            write_image(root / "image_l" / "000000.jpg", _colour_image(0, 0, 0, (6, 8)))
            others = "000000.jpg"
        shown = "" if others is None else rf"; other files there: {re.escape(others)}"
        with pytest.raises(ValueError, match=rf"^folder: '.*odo/image_l' holds {len(names) * (others is None)} "
                                             rf"frame\(s\), PNG files named by a number \(000000\.png, \.\.\.\), and a "
                                             rf"pair \(i, i \+ 1\) needs 2{shown}$"):
            KittiOdometryDataset(root, ground_truth=ground_truth)

    def test_frames_beyond_the_poses_name_the_poses(self, tmp_path):
        root = _odometry_clip(tmp_path / "odo", ["000003", "000004", "000005"])  # (4 poses: frames 0 .. 3)
        with pytest.raises(ValueError, match=r"^folder: '.*odo' has no frame pairs with poses \(step 1\): poses\.txt "
                                             r"holds 4 poses \(line n for frame n\), 1 of the frames 000003\.png \.\.\. "
                                             r"000005\.png have one$"):
            KittiOdometryDataset(root)


class TestShared:
    def test_kitti15_sample(self, shared_data):
        ds = KittiSampleDataset(shared_data / "kitti15_000000")
        assert len(ds) == 1
        item = ds[0]
        assert item["image1"].shape == (3, 375, 1242) and item["flow"].shape == (2, 375, 1242)
        assert abs(float(item["valid"].float().mean()) - 0.162) < 0.002
        assert float(item["camera"].fx) == pytest.approx(721.5377) and float(item["camera"].height) == pytest.approx(1.65)
        assert item["road"].shape == (1, 375, 1242) and 0.15 < float(item["road"].float().mean()) < 0.25
        assert item["odometry"] is None and item["relative_pose"] is None and item["name"] == "kitti15_000000"

    @pytest.mark.parametrize("file", ["calib_cam_to_cam.txt", "flow_noc_10.png", "road.json", "image_11.png"])
    def test_kitti_sample_file_linked_to_a_missing_file_is_an_error(self, shared_data, tmp_path, file):
        """A link to a missing calibration, flow or road.json read as a folder without it: the pair
        lost its camera, ground truth or road without a word (a missing image as 'has no')."""
        folder = tmp_path / "kitti15_000000"
        folder.mkdir()
        for name in ("image_10.png", "image_11.png", "calib_cam_to_cam.txt", "flow_noc_10.png", "road.json"):
            (folder / name).symlink_to(shared_data / "kitti15_000000" / name)
        assert KittiSampleDataset(folder)[0]["flow"] is not None
        (folder / file).unlink()
        (folder / file).symlink_to(tmp_path / "unmounted" / file)
        with pytest.raises(FileNotFoundError, match=rf"^folder: '.*kitti15_000000/{file}' is a symbolic link to "
                                                    r"'.*unmounted/.*', which does not exist"):
            KittiSampleDataset(folder)
        if file == "flow_noc_10.png":  # a file not read may be a broken link
            assert KittiSampleDataset(folder, ground_truth=False)[0]["flow"] is None
        if file == "road.json":
            assert KittiSampleDataset(folder, road_json=False)[0]["road"] is None

    @pytest.mark.parametrize("file", ["calib.txt", "poses.txt", "road.json"])
    def test_kitti_odometry_file_linked_to_a_missing_file_is_an_error(self, shared_data, tmp_path, file):
        """A link to a missing road.json read as a clip without road, without a word; a missing
        calibration or poses file as 'no file at'."""
        folder = tmp_path / "clip"
        folder.mkdir()
        for name in ("image_l", "calib.txt", "poses.txt", "road.json"):
            (folder / name).symlink_to(shared_data / "kitti_odometry_straight" / name)
        assert KittiOdometryDataset(folder, step=49)[0]["road"] is not None
        (folder / file).unlink()
        (folder / file).symlink_to(tmp_path / "unmounted" / file)
        with pytest.raises(FileNotFoundError, match=rf"^folder: '.*clip/{file}' is a symbolic link to "
                                                    r"'.*unmounted/.*', which does not exist"):
            KittiOdometryDataset(folder, step=49)
        if file == "road.json":  # a file not read may be a broken link
            assert KittiOdometryDataset(folder, step=49, road_json=False)[0]["road"] is None
        if file == "poses.txt":
            assert KittiOdometryDataset(folder, step=49, ground_truth=False)[0]["odometry"] is None

    def test_kitti_odometry_clip(self, shared_data):
        ds = KittiOdometryDataset(shared_data / "kitti_odometry_straight")
        assert len(ds) == 50
        item = ds[0]
        assert item["image1"].shape == (3, 370, 1226) and torch.equal(item["image1"][0], item["image1"][1])
        assert float(item["camera"].fx) == pytest.approx(707.0912)
        odo = item["odometry"]
        assert 1.1 < odo["z_d"] < 1.3 and abs(odo["x_d"]) < 0.05 and abs(odo["yaw"]) < 0.01
        assert abs(item["pose_residual"]["y_d"]) < 0.05 and item["relative_pose"].shape == (4, 4)
        assert item["road"].shape == (1, 370, 1226) and item["road"].any()
        batch = collate([ds[0], ds[10]])
        assert batch["odometry"]["z_d"].shape == (2,) and batch["camera"].batch_size == 2
        assert len(KittiOdometryDataset(shared_data / "kitti_odometry_straight", step=2)) == 49


class TestScene:
    def test_items_are_the_rendered_pairs(self):
        from fsof_torch.data.scene import render_pair

        ds = SceneDataset("default", 2, seed=1, size=SIZE, camera_dtype=torch.float64, noise=0.0)
        assert len(ds) == 2
        item, p = ds[-1], render_pair("default", 1, seed=1, size=SIZE, noise=0.0)
        assert item["index"] == 1 and item["name"] == "000001" and item["relative_pose"] is None
        for key in ("image1", "image2", "flow", "valid", "road", "labels", "depth", "pose2"):
            assert torch.equal(item[key], p[key]), key
        assert item["odometry"] == p["odometry"] and item["plane"] == p["plane"]
        # the float64 camera of a float32 render is the scene's own, not its float32 copy cast back
        k64 = render_pair("default", 1, seed=1, size=SIZE, noise=0.0, dtype=torch.float64)["camera"].K
        assert item["camera"].dtype == torch.float64 and torch.equal(item["camera"].K, k64)
        assert not torch.equal(k64, p["camera"].K.double())  # float32 rounds this K
        assert ds[0]["camera"].K is not ds[1]["camera"].K  # every item its own tensors
        bare = SceneDataset("default", 1, size=SIZE, ground_truth=False)[0]
        assert set(bare) == set(ITEM_KEYS) and bare["flow"] is None and bare["road"] is None

    def test_items_do_not_follow_the_callers_overrides_changed_later(self):
        from fsof_torch.data.scene import render_pair

        amps = [25.0, 24.0, 7.0, 3.0, 8.0, 22.0, 20.0]
        ds = SceneDataset("default", 1, size=SIZE, asphalt=amps)
        ref = render_pair("default", 0, size=SIZE, asphalt=list(amps))
        amps[:] = [80.0] * 7  # the caller reuses its list
        item = ds[0]
        assert torch.equal(item["image1"], ref["image1"]) and torch.equal(item["image2"], ref["image2"])
        assert ds.config.asphalt == (25.0, 24.0, 7.0, 3.0, 8.0, 22.0, 20.0)

    def test_errors(self):
        with pytest.raises(ValueError, match="preset: expected one of"):
            SceneDataset("nope")
        # (named render_pair, which the caller did not call; a misspelt argument of SceneDataset too)
        for given in (dict(wobble=3), dict(sed=1, wobble=3)):
            with pytest.raises(TypeError, match=re.escape(f"SceneDataset: unknown overrides {sorted(given)}; expected "
                                                          f"some of ['K', ")):
                SceneDataset("default", 1, **given)
        with pytest.raises(TypeError, match=r"\(or SceneDataset's own: preset, num_pairs, seed, size, dtype, "
                                            r"camera_dtype, ground_truth\)$"):
            SceneDataset("default", 1, camera_type=torch.float64)
        with pytest.raises(ValueError, match="num_pairs: expected an int >= 1"):
            SceneDataset("default", 0)
        with pytest.raises(IndexError, match="out of range"):
            SceneDataset("default", 2, size=SIZE)[2]
        # the arguments every item would use are checked at construction, not at the first item
        with pytest.raises(TypeError, match=r"size: expected \(H, W\), got \(48,\)"):
            SceneDataset("default", 1, size=(48,))
        with pytest.raises(ValueError, match="size: expected positive sides"):
            SceneDataset("default", 1, size=(0, 16))
        with pytest.raises(TypeError, match="dtype: expected torch.float32 or torch.float64, got torch.float16"):
            SceneDataset("default", 1, size=SIZE, dtype=torch.float16)
        with pytest.raises(TypeError, match="camera_dtype: expected torch.float32 or torch.float64, got 'f64'"):
            SceneDataset("default", 1, size=SIZE, camera_dtype="f64")
        with pytest.raises(TypeError, match="ground_truth: expected True or False"):
            SceneDataset("default", 1, size=SIZE, ground_truth="no")


class TestContract:
    """Every dataset's items have the contract's keys first, in order, and pass check_item."""

    def test_every_dataset(self, synthetic_root, kitti_root, tmp_path):
        run = tmp_path / "t10_s0_r0"
        for sub in ("rgb", "optical_flow", "semantic"):
            (run / sub).mkdir(parents=True)
        for k in range(2):
            write_image(run / "rgb" / f"{k:08d}.png", torch.full((3, 12, 16), 5.0 * k))
            write_carla_flow(run / "optical_flow" / f"{k:08d}.tif", torch.full((2, 12, 16), 3.0))
            cv2.imwrite(str(run / "semantic" / f"{k:08d}.png"), np.zeros((12, 16, 3), np.uint8))
        datasets = [SceneDataset("default", 1, size=SIZE), SyntheticFlowDataset(synthetic_root[0]),
                    KittiFlowDataset(kitti_root[0]), CarlaRunDataset(run),
                    ImageFolderDataset(kitti_root[0] / "image_2")]
        for ds in datasets:
            for ground_truth in (True, False):
                ds.ground_truth = ground_truth
                item = ds[0]
                check_item(item)
                assert tuple(item)[:len(ITEM_KEYS)] == ITEM_KEYS, type(ds).__name__
                if not ground_truth:
                    assert set(item) == set(ITEM_KEYS), type(ds).__name__
        carla = CarlaRunDataset(run)[0]
        assert carla["flow"] is None and carla["valid"].shape == (1, 12, 16) and carla["name"] == "00000000"


class TestPairChecks:
    """KITTI and CARLA items: each holds its own camera, and every file of a pair has the size of
    its first image (a file of another size was once returned as it was, breaking the contract)."""

    @pytest.mark.parametrize("view", ["big-endian", "reversed"])
    def test_kitti_K_as_any_numpy_array(self, kitti_root, view):
        """A (3, 3) K array in big-endian byte order, or a reversed view, which torch.as_tensor
        refuses, was a TypeError saying "expected a (3, 3) tensor or array of numbers": untrue."""
        root, _ = kitti_root
        K = np.array([[30.0, 0.0, 19.5], [0.0, 31.0, 11.5], [0.0, 0.0, 1.0]])
        given = K.astype(">f8") if view == "big-endian" else np.ascontiguousarray(K[::-1])[::-1]
        for f in (root / "calib_cam_to_cam").iterdir():  # the pairs without a calibration take K
            f.unlink()
        ds = KittiFlowDataset(root, K=given, camera_dtype=torch.float64)
        assert torch.equal(ds[0]["camera"].K[0], torch.from_numpy(K))
        with pytest.raises(TypeError, match=r"^K: expected a \(3, 3\) tensor or array of numbers, got ndarray"):
            KittiFlowDataset(root, K=np.array([["a"] * 3] * 3))

    def test_kitti_items_do_not_share_the_given_K(self, kitti_root):
        root, _ = kitti_root
        for p in (root / "calib_cam_to_cam").iterdir():
            p.unlink()
        K = torch.tensor([[30.0, 0, 18.0], [0, 30.0, 10.0], [0, 0, 1]])  # (the centre of these 24x40 images)
        ds = KittiFlowDataset(root, K=K)
        ds[0]["camera"].K[0, 0, 0] += 100.0  # editing one item's camera changes no other, nor K
        assert float(ds[1]["camera"].K[0, 0, 0]) == 30.0 and float(K[0, 0]) == 30.0
        K[0, 0] = 7.0  # nor does the caller's later edit change the items
        assert float(ds[0]["camera"].K[0, 0, 0]) == 30.0
        with pytest.raises(ValueError, match=r"^K: "):  # checked when the dataset is made
            KittiFlowDataset(root, K=torch.eye(4))

    @pytest.mark.parametrize("count", [2, 3])
    def test_kitti_K_of_several_cameras_is_refused(self, kitti_root, count):
        """A (B, 3, 3) K gave every item a Camera of batch B (the contract's is 1): collate then
        refused the items, naming 'camera', not K."""
        root, _ = kitti_root
        for p in (root / "calib_cam_to_cam").iterdir():
            p.unlink()
        K = torch.tensor([[30.0, 0, 18.0], [0, 30.0, 10.0], [0, 0, 1]])
        with pytest.raises(ValueError, match=rf"^K: expected one \(3, 3\) K .*got {count} of them "
                                             rf"\(shape \({count}, 3, 3\)\)"):
            KittiFlowDataset(root, K=K.expand(count, 3, 3))
        with pytest.raises(ValueError, match=r"^K: expected one \(3, 3\) K"):
            KittiFlowDataset(root, K=K.expand(count, 3, 3).numpy().tolist())
        item = KittiFlowDataset(root, K=K[None])[0]  # (1, 3, 3): one camera, as Camera takes it
        check_item(item)
        assert item["camera"].batch_size == 1 and torch.equal(item["camera"].K[0], K)

    @pytest.mark.parametrize("folder, file", [("image_2", "000001_11.png"), ("flow_noc", "000001_10.png"),
                                              ("semantic", "000001_10.png"), ("road", "000001_10.png")])
    def test_kitti_files_of_another_size_are_refused(self, kitti_root, folder, file):
        root, _ = kitti_root
        (root / folder).mkdir(exist_ok=True)
        bigger = (SIZE[0] + 2, SIZE[1] + 3)
        if folder == "flow_noc":
            write_kitti_flow(root / folder / file, torch.ones(2, *bigger))
        else:  # an image, a semantic label image, a road mask (nonzero = road)
            write_image(root / folder / file, torch.full((3, *bigger), 255.0))
        ds = KittiFlowDataset(root)
        check_item(ds[0])
        with pytest.raises(ValueError, match=rf"^root: '.*{folder}/{file}' is 26x43, but the pair's image "
                                             rf"000001_10\.png is 24x40; every file of a pair needs its images' size"):
            ds[1]

    def test_kitti_road_pngs_of_the_image_size(self, kitti_root):
        root, _ = kitti_root
        (root / "road").mkdir()
        road = torch.zeros(1, *SIZE, dtype=torch.bool)
        road[:, 20:] = True
        from fsof_torch.io import write_road_mask

        write_road_mask(root / "road" / "000001_10.png", road)
        assert torch.equal(KittiFlowDataset(root)[1]["road"], road)  # road/ before semantic/

    @pytest.mark.parametrize("bad", ["rgb/00000001.png", "optical_flow/00000000.tif", "semantic/00000000.png"])
    def test_carla_files_of_another_size_are_refused(self, tmp_path, bad):
        run = tmp_path / "t10_s0_r0"
        for sub in ("rgb", "optical_flow", "semantic"):
            (run / sub).mkdir(parents=True)

        def write(file, h):
            if file.startswith("rgb"):
                write_image(run / file, torch.zeros(3, h, 16))
            elif file.startswith("optical_flow"):
                write_carla_flow(run / file, torch.zeros(2, h, 16))
            else:
                cv2.imwrite(str(run / file), np.zeros((h, 16, 3), np.uint8))

        for k in range(2):
            for file in (f"rgb/{k:08d}.png", f"optical_flow/{k:08d}.tif", f"semantic/{k:08d}.png"):
                write(file, 12)
        check_item(CarlaRunDataset(run)[0])
        write(bad, 14)
        with pytest.raises(ValueError, match=rf"^run: '.*{bad}' is 14x16, but the pair's image 00000000\.png "
                                             rf"is 12x16"):
            CarlaRunDataset(run)[0]

    @pytest.mark.parametrize("missing", ["optical_flow/00000001.tif", "semantic/00000001.png"])
    def test_carla_pair_missing_its_ground_truth_is_an_error(self, tmp_path, missing):
        """A run's optical_flow/ or semantic/ without one pair's file (not copied) gave that item
        no flow_velocity or road, without a word, as KITTI's flow folder once did."""
        run = tmp_path / "t10_s0_r0"
        for sub in ("rgb", "optical_flow", "semantic"):
            (run / sub).mkdir(parents=True)
        for k in range(3):
            write_image(run / "rgb" / f"{k:08d}.png", torch.zeros(3, 12, 16))
            write_carla_flow(run / "optical_flow" / f"{k:08d}.tif", torch.zeros(2, 12, 16))
            cv2.imwrite(str(run / "semantic" / f"{k:08d}.png"), np.zeros((12, 16, 3), np.uint8))
        (run / missing).unlink()
        ds = CarlaRunDataset(run)
        assert ds[0]["flow_velocity"] is not None and ds[0]["road"] is not None
        folder, name = missing.split("/")
        with pytest.raises(FileNotFoundError, match=rf"^run: '.*t10_s0_r0' has {folder}/ but no {name} there for "
                                                    rf"the pair 00000001"):
            ds[1]
        (run / missing).symlink_to(tmp_path / "unmounted" / "x")  # (it said the same of a broken link)
        with pytest.raises(FileNotFoundError, match=rf"^run: '.*t10_s0_r0/{missing}' is a symbolic link to "
                                                    r"'.*unmounted/x', which does not exist"):
            ds[1]
        (run / missing).unlink()
        ds.ground_truth = False
        check_item(ds[1])
        shutil.rmtree(run / folder)  # a run without the folder has no such ground truth
        ds.ground_truth = True
        item = ds[1]
        assert ("flow_velocity" not in item) if folder == "optical_flow" else item["road"] is None

    def test_carla_frames_numbered_without_padding_pair_in_order(self, tmp_path):
        """Frames 98, 99, 100: pairs (98, 99) and (99, 100), not the names' order 100, 98, 99."""
        run = tmp_path / "t10_s0_r0"
        (run / "rgb").mkdir(parents=True)
        for k in (98, 99, 100):
            write_image(run / "rgb" / f"{k}.png", torch.full((3, 4, 6), float(k)))
        ds = CarlaRunDataset(run)
        assert [(ds[i]["name"], float(ds[i]["image1"][0, 0, 0]), float(ds[i]["image2"][0, 0, 0]))
                for i in range(len(ds))] == [("98", 98.0, 99.0), ("99", 99.0, 100.0)]


def test_kitti_hidden_files_are_no_pairs(kitti_root):
    """macOS's AppleDouble files (``._NAME_10.png`` beside each frame, not PNGs) are no frames, as
    in ImageFolderDataset and CarlaRun: they made pairs named ``._NAME`` that failed to load."""
    root, _ = kitti_root
    for p in list((root / "image_2").iterdir()):
        (root / "image_2" / f"._{p.name}").write_bytes(b"\x00\x05\x16\x07" + bytes(60))
    (root / "image_2" / "dir_10.png").mkdir()  # a folder named like a frame is no frame either
    (root / "image_2" / "dir_11.png").mkdir()
    ds = KittiFlowDataset(root)
    assert ds.names == ["000000", "000001"]
    for i, name in enumerate(ds.names):
        item = ds[i]
        check_item(item)
        assert item["name"] == name and item["flow"] is not None


@pytest.mark.parametrize("frame", ["000001_10.png", "000001_11.png"])
def test_kitti_frame_linked_to_a_missing_file_is_an_error(kitti_root, frame):
    """A frame linked to a missing file (a drive not mounted) left its pair out of the dataset silently."""
    root, _ = kitti_root
    (root / "image_2" / frame).unlink()
    (root / "image_2" / frame).symlink_to(root / "gone.png")
    with pytest.raises(FileNotFoundError, match=rf"root: '.*{frame}' is a symbolic link to '.*gone\.png', which "
                                                r"does not exist"):
        KittiFlowDataset(root)


def test_kitti_semantic_class_ids_are_no_hand_labels(kitti_root):
    """KITTI's semantic segmentation ground truth (single-channel class IDs, road = 7) has the flow
    data set's names and folder (training/semantic/NAME_10.png): unzipped beside the flow, it was
    read as the paper's red hand labels, a road mask empty without a word."""
    root, _ = kitti_root
    ids = np.full(SIZE, 21, np.uint8)  # vegetation
    ids[15:] = 7  # road
    cv2.imwrite(str(root / "semantic" / "000001_10.png"), ids)
    assert KittiFlowDataset(root)[0]["road"].any()  # the hand labels of the other pair still read
    with pytest.raises(ValueError, match=r"root: '.*semantic/000001_10\.png' is a single-channel uint8 image \(class "
                                         r"IDs, such as KITTI's semantic segmentation ground truth"):
        KittiFlowDataset(root)[1]


@pytest.mark.parametrize("missing", ["calib_cam_to_cam/000001.txt", "semantic/000001_10.png"])
def test_kitti_pair_missing_its_calibration_or_road_is_an_error(kitti_root, missing):
    """A calibration or road folder without one pair's file (not copied) gave that item no camera
    or no road, without a word; K= still fills a missing calibration, and a folder without files
    (or none) is no calibration."""
    root, K = kitti_root
    (root / missing).unlink()
    ds = KittiFlowDataset(root)
    assert ds[0]["camera"] is not None and ds[0]["road"] is not None
    folder, name = missing.split("/")
    with pytest.raises(FileNotFoundError, match=rf"^root: '.*kitti' has {folder}/ but no {name} there"):
        ds[1]
    if folder == "calib_cam_to_cam":
        torch.testing.assert_close(KittiFlowDataset(root, K=K)[1]["camera"].K[0], K.float())
    else:
        from fsof_torch.io import write_road_mask

        (root / "road").mkdir()
        write_road_mask(root / "road" / "000001_10.png", torch.ones(1, *SIZE, dtype=torch.bool))
        assert KittiFlowDataset(root)[1]["road"].all()  # road/ has it: the pair has its mask


def test_kitti_pair_missing_its_flow_file_is_an_error(kitti_root):
    """A flow folder without one pair's file (deleted, not copied) raises naming it when the pair
    loads: that pair's item had flow None, silently, beside pairs with ground truth."""
    root, _ = kitti_root
    ds = KittiFlowDataset(root)
    (root / "flow_noc" / "000001_10.png").unlink()
    assert ds[0]["flow"] is not None
    with pytest.raises(FileNotFoundError, match=r"^root: '.*kitti' has flow_noc/ but no 000001_10\.png there "
                                                r"for the pair 000001"):
        ds[1]
    assert KittiFlowDataset(root, ground_truth=False)[1]["flow"] is None  # no ground truth asked for


@pytest.mark.parametrize("file", ["calib_cam_to_cam/000001.txt", "semantic/000001_10.png", "flow_noc/000001_10.png",
                                  "road/000001_10.png"])
def test_kitti_pair_file_linked_to_a_missing_file_says_so(kitti_root, tmp_path, file):
    """A pair's calibration, flow or road linked from a drive that is not mounted read as a file
    missing from its folder ('has flow_noc/ but no 000001_10.png there'); a broken road/ link fell
    back to semantic/'s hand labels without a word."""
    root, _ = kitti_root
    (root / file).parent.mkdir(exist_ok=True)
    (root / file).unlink(missing_ok=True)
    (root / file).symlink_to(tmp_path / "unmounted" / "x")
    ds = KittiFlowDataset(root)
    with pytest.raises(FileNotFoundError, match=rf"^root: '.*kitti/{file}' is a symbolic link to '.*unmounted/x', "
                                                r"which does not exist"):
        ds[1]
    if file.startswith("semantic/"):  # a pair whose road/ has its mask needs no semantic/ file
        from fsof_torch.io import write_road_mask

        (root / "road").mkdir()
        write_road_mask(root / "road" / "000001_10.png", torch.ones(1, *SIZE, dtype=torch.bool))
        assert ds[1]["road"].all()


def test_kitti_calibration_of_another_image_size_is_an_error(kitti_root):
    """A calibration file whose S_rect_02 states another size than the pair's images (the file of
    another sequence or camera) gave that size's K silently: a ValueError naming root, the file
    and both sizes. The file's own size, or no S_rect row, reads the K as written."""
    root, K = kitti_root
    calib = root / "calib_cam_to_cam" / "000001.txt"
    text = calib.read_text()
    calib.write_text(text + "S_rect_02: 1.242000e+03 3.750000e+02\n")
    ds = KittiFlowDataset(root)
    with pytest.raises(ValueError, match=r"^root: .*000001\.txt' states S_rect_02: 375x1242 .* image "
                                         r"000001_10\.png is 24x40"):
        ds[1]
    torch.testing.assert_close(ds[0]["camera"].K[0].double(), K)  # no S_rect row: read as it is
    calib.write_text(text + f"S_rect_02: {SIZE[1]:.6e} {SIZE[0]:.6e}\n")  # its own size
    torch.testing.assert_close(ds[1]["camera"].K[0].double(), K)
    calib.write_text(text + "S_rect_03: 1.242000e+03 3.750000e+02\n")  # another camera's row
    torch.testing.assert_close(ds[1]["camera"].K[0].double(), K)


@pytest.mark.parametrize("add, remove, shown", [
    (["000009_10"], [], "000009_10.png"),  # a NAME_10 without its NAME_11
    (["000009_11"], [], "000009_11.png"),  # a NAME_11 without its NAME_10
    (["000009_10"], ["000001_11"], "000001_10.png, 000009_10.png"),  # a file lost in a copy, and another
])
def test_kitti_image_without_its_partner_is_an_error(kitti_root, add, remove, shown):
    """A NAME_10 without its NAME_11 (or the reverse: a file lost in a copy) left its pair out of
    the data set without a word, one pair fewer in every evaluation over it; as ImageFolderDataset
    does, a ValueError naming root, the folder and every such image, when the dataset is made."""
    root, _ = kitti_root
    for stem in add:
        write_image(root / "image_2" / f"{stem}.png", torch.zeros(3, *SIZE))
    for stem in remove:
        (root / "image_2" / f"{stem}.png").unlink()
    count = len(shown.split(", "))
    with pytest.raises(ValueError, match=rf"^root: '{re.escape(str(root / 'image_2'))}' holds KITTI flow pairs "
                                         rf"\(NAME_10 / NAME_11, paired by name\), but {count} image\(s\) have no "
                                         rf"partner: {re.escape(shown)}; give each NAME_10 its NAME_11$"):
        KittiFlowDataset(root)


def test_kitti_calibration_of_resized_images_is_an_error(kitti_root):
    """A calibration without a stated size (KITTI 2012's calib/NAME.txt, rows P0..P3) or a K= made
    for images twice as large gave the pair that K silently: its principal point (40, 16) in the
    corner of these 24x40 images. As ImageFolderDataset does, a principal point outside the
    images' middle third is a ValueError naming the file (or K) and the pair; the file's own
    S_rect row states a size where the point is right, and K's true size passes."""
    root, K = kitti_root
    shutil.rmtree(root / "calib_cam_to_cam")
    (root / "calib").mkdir()
    K2 = K.clone()
    K2[:2] *= 2  # the calibration of 48x80 images
    for name in ("000000", "000001"):
        write_kitti_calibration(root / "calib" / f"{name}.txt", K2 if name == "000001" else K, style="odometry")
    ds = KittiFlowDataset(root)
    torch.testing.assert_close(ds[0]["camera"].K[0].double(), K)
    with pytest.raises(ValueError, match=r"^root: '.*calib/000001\.txt' has the principal point \(40\.0, 16\.0\), "
                                         r"outside the middle third of the pair's image 000001_10\.png \(24x40\)"):
        ds[1]
    calib = root / "calib" / "000001.txt"
    calib.write_text(calib.read_text() + f"S_rect_02: {SIZE[1]} {SIZE[0]}\n")  # stated: taken as it is
    torch.testing.assert_close(ds[1]["camera"].K[0].double(), K2)
    shutil.rmtree(root / "calib")
    with pytest.raises(ValueError, match=r"^K: the given K has the principal point \(40\.0, 16\.0\), outside the "
                                         r"middle third of the pair's image 000000_10\.png \(24x40\)"):
        KittiFlowDataset(root, K=K2)[0]
    torch.testing.assert_close(KittiFlowDataset(root, K=K)[0]["camera"].K[0].double(), K)
