"""fsof_torch.data.folders: ImageFolderDataset over a folder of frames written by the library's
writers (pairs, files matched by name, poses, one road file for all pairs, the size checks) and
the errors that name the argument and the file."""

from __future__ import annotations

import json
import math
import os
import re

import numpy as np
import pytest
import torch

from fsof_torch.data.folders import (ImageFolderDataset, calibration_size, check_index, frame_pairs,
                                    kitti_flow_layout, match_files)
from fsof_torch.data.items import check_item
from fsof_torch.io import (read_kitti_poses, write_flow, write_image, write_kitti_calibration, write_kitti_poses,
                           write_road_mask)

SIZE = (24, 40)
K = torch.tensor([[30.0, 0.0, 19.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _motion(yaw: float) -> torch.Tensor:
    """Camera i in the coordinates of camera i - 1: 1 m forward, then turned by ``yaw`` about y
    (the displacement model's d = (0, 0, 1), φ = yaw)."""
    c, s = torch.cos(torch.tensor(yaw, dtype=torch.float64)), torch.sin(torch.tensor(yaw, dtype=torch.float64))
    M = torch.eye(4, dtype=torch.float64)
    M[0, 0], M[0, 2], M[2, 0], M[2, 2], M[2, 3] = c, s, -s, c, 1.0
    return M


def _frame(i: int) -> torch.Tensor:
    """Frame i: channels 10 i, 60 + 10 i, 120 + 10 i, each plus the column index (an RGB/BGR swap
    changes it)."""
    x = torch.arange(SIZE[1], dtype=torch.float32).expand(*SIZE)
    return torch.stack([x + 10.0 * i, x + 60.0 + 10.0 * i, x + 120.0 + 10.0 * i])


def _flow(i: int) -> torch.Tensor:
    """Pair i's flow: u a ramp along x, v one along y, distinct (a u/v swap changes it)."""
    u = torch.arange(SIZE[1], dtype=torch.float32).expand(*SIZE) * 0.5 + i
    v = torch.arange(SIZE[0], dtype=torch.float32)[:, None].expand(*SIZE) * -0.25 - i
    return torch.stack([u, v])


@pytest.fixture
def clip(tmp_path):
    """Four frames (:func:`_frame`), calib.txt, poses, road PNGs and flows (:func:`_flow`) per pair."""
    root = tmp_path / "clip"
    for d in ("images", "road", "gt"):
        (root / d).mkdir(parents=True)
    for i in range(4):
        write_image(root / "images" / f"{i:06d}.png", _frame(i))
    write_kitti_calibration(root / "calib.txt", K, cam=0, style="odometry")
    poses = [torch.eye(4, dtype=torch.float64)]
    for i in range(1, 4):  # camera-to-world: P_i = P_{i-1} M_i, turning by 0.01 i
        poses.append(poses[-1] @ _motion(0.01 * i))
    poses = torch.stack(poses)
    write_kitti_poses(root / "poses.txt", poses)
    for i in range(3):
        road = torch.zeros(1, *SIZE, dtype=torch.bool)
        road[:, 12 + i:] = True
        write_road_mask(root / "road" / f"{i:06d}.png", road)
        write_flow(root / "gt" / f"{i:06d}.flo", _flow(i))
    return root, poses


def test_consecutive_pairs_with_poses_road_and_ground_truth(clip):
    root, poses = clip
    ds = ImageFolderDataset(root / "images", root / "calib.txt", camera_height=1.5, poses=root / "poses.txt",
                            road=root / "road", gt=root / "gt")
    assert len(ds) == 3 and [p.name for p in ds.pairs] == ["000000", "000001", "000002"]
    item = ds[1]
    check_item(item)
    assert item["name"] == "000001"
    for c in range(3):  # channel by channel, in RGB order
        assert torch.equal(item["image1"][c], _frame(1)[c]) and torch.equal(item["image2"][c], _frame(2)[c]), c
    assert int(item["road"].sum()) == (SIZE[0] - 13) * SIZE[1]
    for c in range(2):  # u and v each in its own channel
        assert torch.equal(item["flow"][c], _flow(1)[c]), "uv"[c]
    assert item["valid"].all()
    torch.testing.assert_close(item["relative_pose"], torch.linalg.inv(poses[2]) @ poses[1], rtol=0, atol=1e-12)
    # forward by 1 m, turning by 0.02 rad, a level camera: the odometry by construction
    assert item["odometry"]["yaw"] == pytest.approx(0.02, abs=1e-12)
    assert item["odometry"]["z_d"] == pytest.approx(1.0, abs=1e-12) and abs(item["odometry"]["x_d"]) < 1e-12
    assert item["camera"].dtype == torch.float32 and float(item["camera"].height) == 1.5
    torch.testing.assert_close(item["camera"].K[0].double(), K)


def test_step_frame_list_poses_tensor_and_no_calibration(clip):
    root, poses = clip
    frames = sorted((root / "images").iterdir())
    ds = ImageFolderDataset(frames, poses=poses, step=2)
    assert [(p.name, p.frame1, p.frame2) for p in ds.pairs] == [("000000", 0, 2), ("000001", 1, 3)]
    with pytest.raises(TypeError, match=r"^poses: expected an \(N, 4, 4\) float tensor, got dtype torch.int64$"):
        ImageFolderDataset(frames, poses=poses.round().long(), step=2)
    # poses in millimetres: named with the two frames, not left to the refiner's generic warning
    mm = poses.clone()
    mm[:, :3, 3] *= 1000
    with pytest.raises(ValueError, match=r"^poses: the pose of 000000.png and the pose of 000001.png lie 1000 m apart, "
                                         r"farther than a road vehicle travels .*millimetres"):
        ImageFolderDataset(frames, poses=mm)
    write_kitti_poses(root / "poses_mm.txt", mm)
    with pytest.raises(ValueError, match=r"^poses: the pose of 000000.png and the pose of 000001.png lie 1000 m"):
        ImageFolderDataset(root / "images", poses=root / "poses_mm.txt")
    # frames 0 and 3 (1 and 2 missing): 270 m is within a road vehicle's travel over three frames (300 m)
    far = poses[[0, 3]].clone()
    far[1, :3, 3] *= 90
    assert ImageFolderDataset([frames[0], frames[3]], poses=far).poses.shape == (2, 4, 4)
    item = ds[1]
    assert item["camera"] is None and item["road"] is None and item["flow"] is None
    torch.testing.assert_close(item["relative_pose"], torch.linalg.inv(poses[3]) @ poses[1], rtol=0, atol=1e-12)
    assert item["odometry"]["yaw"] == pytest.approx(0.02 + 0.03, abs=1e-12)  # two turns
    torch.testing.assert_close(torch.as_tensor(ImageFolderDataset(frames, poses=root / "poses.txt").poses), poses,
                               rtol=0, atol=1e-12)


def test_a_poses_file_has_exactly_one_line_per_image(clip, tmp_path):
    """A poses file is read by position (line i: image i), so one with more lines than images, such as
    a KITTI poses file (line n for frame n) for frames cut from a longer sequence, is refused: read
    by position, the pair of frames 2 and 3 would take the motion of lines 0 and 1. A tensor (the
    KITTI odometry dataset's poses, already selected for its frames) may be longer."""
    root, poses = clip
    frames = sorted((root / "images").iterdir())
    longer = torch.cat([poses, poses[-1:] @ _motion(0.05)])
    write_kitti_poses(tmp_path / "poses.txt", longer)
    with pytest.raises(ValueError, match=r"^poses: .*poses\.txt' has 5 poses for 4 images: one line per image, "
                                         r"line i for image i in sorted order.*must be cut to these frames"):
        ImageFolderDataset(root / "images", poses=tmp_path / "poses.txt")
    with pytest.raises(ValueError, match=r"has 4 poses for 2 images"):  # frames 000002, 000003 of the clip
        ImageFolderDataset(frames[2:], poses=root / "poses.txt")
    write_kitti_poses(tmp_path / "cut.txt", poses[2:])  # cut to those frames: line i is image i
    item = ImageFolderDataset(frames[2:], poses=tmp_path / "cut.txt")[0]
    torch.testing.assert_close(item["relative_pose"], torch.linalg.inv(poses[3]) @ poses[2], rtol=0, atol=1e-12)
    ds = ImageFolderDataset(frames, poses=longer)
    torch.testing.assert_close(ds[2]["relative_pose"], torch.linalg.inv(poses[3]) @ poses[2], rtol=0, atol=1e-12)


def test_one_road_file_for_every_pair(clip, tmp_path):
    root, _ = clip
    (tmp_path / "road.json").write_text(json.dumps({"size": list(SIZE),
                                                    "road_polygon": [[0, 23], [0, 12], [39, 12], [39, 23]]}))
    ds = ImageFolderDataset(root / "images", road=tmp_path / "road.json")
    a, b = ds[0]["road"], ds[2]["road"]
    assert torch.equal(a, b) and a.shape == (1, *SIZE) and a[:, 12:].all() and not a[:, :12].any()
    a[:] = False  # an item's mask is its own
    assert ds[0]["road"].any()
    road = torch.zeros(1, *SIZE, dtype=torch.bool)
    road[:, :, :5] = True
    write_road_mask(tmp_path / "road.png", road)
    assert torch.equal(ImageFolderDataset(root / "images", road=tmp_path / "road.png")[1]["road"], road)


def test_kitti_flow_pairs_pair_by_name(tmp_path):
    for name in ("000004", "000002"):
        for t, v in (("10", 1), ("11", 2)):
            write_image(tmp_path / f"{name}_{t}.png", torch.full((3, *SIZE), v, dtype=torch.uint8))
    files = sorted(tmp_path.iterdir())
    assert kitti_flow_layout(files)
    assert frame_pairs(files) == [("000002", 0, 1), ("000004", 2, 3)]
    ds = ImageFolderDataset(tmp_path)
    assert [p.name for p in ds.pairs] == ["000002", "000004"] and ds[1]["image2"].eq(2.0).all()
    with pytest.raises(ValueError, match="step: KITTI flow pairs"):
        ImageFolderDataset(tmp_path, step=2)
    assert not kitti_flow_layout([tmp_path / "000002.png", tmp_path / "000010.png"])  # frames of a clip


@pytest.mark.parametrize("extra, orphans", [
    (["000009_10"], "000009_10.png"),  # a _10 without its _11
    (["000009_11"], "000009_11.png"),  # a _11 without its _10
    (["000003"], "000003.png"),  # a clip's frame beside the pairs
    (["000009_11", "000010_10"], "000009_11.png, 000010_10.png"),  # as one clip: 000009_11 -> 000010_10
])
def test_kitti_flow_pairs_must_be_complete(tmp_path, extra, orphans):
    """A folder of KITTI flow pairs (here complete pairs under two names) pairs by name: an image
    without its partner stops the dataset, naming the folder and every such image, never paired
    across scenes nor dropped."""
    for name in ("000002", "000004"):
        for t in ("10", "11"):
            write_image(tmp_path / f"{name}_{t}.png", torch.zeros(3, *SIZE))
    for name in extra:
        write_image(tmp_path / f"{name}.png", torch.zeros(3, *SIZE))
    message = (rf"^images: '{re.escape(str(tmp_path))}' holds KITTI flow pairs \(NAME_10 / NAME_11, paired by name\), but "
               rf"{len(extra)} image\(s\) have no partner: {orphans}; ")
    with pytest.raises(ValueError, match=message):
        ImageFolderDataset(tmp_path)
    with pytest.raises(ValueError, match=message):
        frame_pairs(sorted(tmp_path.iterdir()))


def test_a_clip_with_a_frame_named_like_kitti_stays_a_clip(tmp_path):
    """frame_00 ... frame_10: one name ends in _10, but no pair is complete and not every name is
    a KITTI pair's: a clip of 10 pairs, as it always was."""
    for n in range(11):
        write_image(tmp_path / f"frame_{n:02d}.png", torch.full((3, *SIZE), n, dtype=torch.uint8))
    images = sorted(tmp_path.iterdir())
    assert not kitti_flow_layout(images)
    ds = ImageFolderDataset(tmp_path)
    assert [p.name for p in ds.pairs] == [f"frame_{n:02d}" for n in range(10)]
    assert float(ds[9]["image2"][0, 0, 0]) == 10.0


@pytest.mark.parametrize("names, orphans", [
    (["000009_11", "000010_10"], "000009_11.png, 000010_10.png"),  # only KITTI names, no pair
    (["000002_09", "000002_10", "000002_11", "000002_12", "000003_09", "000003_10", "000003_11"],
     "000002_09.png, 000002_12.png, 000003_09.png"),  # KITTI multiview frames of two scenes
])
def test_kitti_names_without_complete_pairs_or_beside_them_are_refused(tmp_path, names, orphans):
    """Every name a KITTI pair's, or complete pairs under two names beside other frames (KITTI's
    multiview folders): KITTI pairs, and the images without a partner are named (never paired
    across scenes, never dropped)."""
    for name in names:
        write_image(tmp_path / f"{name}.png", torch.zeros(3, *SIZE))
    with pytest.raises(ValueError, match=rf"have no partner: {orphans}; "):
        ImageFolderDataset(tmp_path)


@pytest.mark.parametrize("frames", [12, 21])
def test_a_clip_of_one_name_through_10_and_11_stays_a_clip(tmp_path, frames):
    """frame_00 ... frame_11 (or ... frame_20): frame_10 and frame_11 form a complete pair, but
    every frame shares one name: a clip of frames - 1 pairs, not KITTI flow pairs whose other
    frames are refused as orphans."""
    for n in range(frames):
        write_image(tmp_path / f"frame_{n:02d}.png", torch.full((3, *SIZE), n, dtype=torch.uint8))
    images = sorted(tmp_path.iterdir())
    assert not kitti_flow_layout(images)
    ds = ImageFolderDataset(tmp_path)
    assert [p.name for p in ds.pairs] == [f"frame_{n:02d}" for n in range(frames - 1)]
    assert [(float(ds[i]["image1"][0, 0, 0]), float(ds[i]["image2"][0, 0, 0])) for i in (9, 10)] == [
        (9.0, 10.0), (10.0, 11.0)]
    # a second name with its complete pair makes it KITTI's multiview layout: the clip's frames are refused
    for t in ("10", "11"):
        write_image(tmp_path / f"other_{t}.png", torch.zeros(3, *SIZE))
    with pytest.raises(ValueError, match=rf"holds KITTI flow pairs .* {frames - 2} image\(s\) have no partner: "
                                         rf"frame_00\.png, "):
        ImageFolderDataset(tmp_path)


def test_frames_numbered_without_padding_pair_by_number(tmp_path):
    """Frames named 0, 5, 10, 15, 20 are a clip in that order (not the names' order 0, 10, 15, 20,
    5); names that are not all numbers keep the names' order."""
    from fsof_torch.data.folders import list_images

    for n in (0, 5, 10, 15, 20):
        write_image(tmp_path / f"{n}.png", torch.full((3, *SIZE), n, dtype=torch.uint8))
    assert [p.stem for p in list_images(tmp_path)] == ["0", "5", "10", "15", "20"]
    ds = ImageFolderDataset(tmp_path)
    assert [p.name for p in ds.pairs] == ["0", "5", "10", "15"]
    assert [(float(ds[i]["image1"][0, 0, 0]), float(ds[i]["image2"][0, 0, 0])) for i in range(4)] == [
        (0.0, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 20.0)]
    write_image(tmp_path / "a.png", torch.zeros(3, *SIZE))
    from fsof_torch.io.images import in_frame_order
    assert [p.stem for p in in_frame_order(tmp_path.iterdir())] == ["0", "10", "15", "20", "5", "a"]
    # (a folder so named would pair 20 with 5 and 5 with a: test_clip_beside_other_images_is_refused)
    with pytest.raises(ValueError, match="named by a number beside images named otherwise"):
        list_images(tmp_path)


def test_frames_named_one_text_around_a_number_pair_by_number(tmp_path):
    """Frames frame_0 ... frame_11 (numbers without padding after a common prefix) are a clip in
    the order of their numbers: by name, frame_1 paired with frame_10, frame_11 with frame_2, and
    each pair took the flow file named after its first frame (frame_1.flo for frame_1 -> frame_10)."""
    from fsof_torch.data.folders import list_images

    for n in range(12):
        write_image(tmp_path / f"frame_{n}.png", torch.full((3, *SIZE), n, dtype=torch.uint8))
    assert [p.stem for p in list_images(tmp_path)] == [f"frame_{n}" for n in range(12)]
    ds = ImageFolderDataset(tmp_path)
    assert [p.name for p in ds.pairs] == [f"frame_{n}" for n in range(11)]
    assert [(float(ds[i]["image1"][0, 0, 0]), float(ds[i]["image2"][0, 0, 0])) for i in (1, 9, 10)] == [
        (1.0, 2.0), (9.0, 10.0), (10.0, 11.0)]
    from fsof_torch.io.images import frame_numbers

    # one text around the last number, prefix and suffix shared by every name
    assert frame_numbers(["cam0_9_rect", "cam0_10_rect"]) == [9, 10]
    assert frame_numbers(["9_cam0", "10_cam0"]) == [9, 10]  # the number that differs, not the last
    # other texts, a name without a number, and the decimals of a timestamp keep the names' order
    assert frame_numbers(["left_9", "right_10"]) is None
    assert frame_numbers(["frame_9", "frame_10", "notes"]) is None
    assert frame_numbers(["1541234567.15", "1541234567.2"]) is None  # .15 s before .2 s, as named
    assert frame_numbers(["000000_10", "000000_11", "000001_10"]) is None  # numbers differ in two places


def test_frames_of_every_suffix_write_image_writes_are_frames(tmp_path):
    """A .webp frame (written by write_image, read by read_image) was no frame: a folder of them
    held "0 image(s)", and one beside .png frames was left out, pairing its neighbours."""
    from fsof_torch.data.folders import list_images
    from fsof_torch.io.images import WRITABLE_DTYPES

    for k, suffix in enumerate(sorted(WRITABLE_DTYPES)):
        write_image(tmp_path / f"{k}{suffix}", torch.full((3, *SIZE), k, dtype=torch.uint8))
    assert [p.name for p in list_images(tmp_path)] == [f"{k}{s}" for k, s in enumerate(sorted(WRITABLE_DTYPES))]
    ds = ImageFolderDataset(tmp_path)
    assert [p.name for p in ds.pairs] == [str(k) for k in range(len(WRITABLE_DTYPES) - 1)]
    for k in range(len(ds)):  # frame k holds the value k (a .jpg within its rounding)
        item = ds[k]
        assert abs(float(item["image1"].mean()) - k) <= 1 and abs(float(item["image2"].mean()) - k - 1) <= 1, k


def test_hidden_files_are_no_frames(tmp_path):
    """macOS's ``._N.png`` beside each frame (or a writer's hidden temporary) was a frame: the
    names were then not all numbers, and the clip paired 0 -> 10 -> 5."""
    from fsof_torch.data.folders import list_images

    for n in (0, 5, 10):
        write_image(tmp_path / f"{n}.png", torch.full((3, *SIZE), n, dtype=torch.uint8))
    (tmp_path / "._5.png").write_bytes(b"\x00\x05")
    assert [p.name for p in list_images(tmp_path)] == ["0.png", "5.png", "10.png"]
    assert [p.name for p in ImageFolderDataset(tmp_path).pairs] == ["0", "5"]


def test_a_broken_link_is_no_missing_file(clip):
    """A frame, flow, road or ground-truth file that is a symbolic link to nothing (storage not mounted, a
    moved target) was left out silently: the clip one frame shorter, or paired across the gap. It
    is an error naming the argument, the link and its target."""
    root, _ = clip
    (root / "images" / "000004.png").symlink_to(root / "gone" / "000004.png")
    with pytest.raises(FileNotFoundError, match=r"^images: '.*000004\.png' is a symbolic link to '.*gone.*', which does not exist"):
        ImageFolderDataset(root / "images")
    (root / "images" / "000004.png").unlink()
    (root / "gt" / "000001.flo").unlink()
    (root / "gt" / "000001.flo").symlink_to(root / "gone.flo")
    with pytest.raises(FileNotFoundError, match=r"^gt: '.*000001\.flo' is a symbolic link to '.*gone\.flo', which does not exist"):
        ImageFolderDataset(root / "images", gt=root / "gt")
    (root / "road" / "000002.png").unlink()
    (root / "road" / "000002.png").symlink_to("nowhere.png")
    with pytest.raises(FileNotFoundError, match=r"^road: '.*000002\.png' is a symbolic link to 'nowhere\.png'"):
        ImageFolderDataset(root / "images", road=root / "road")


def test_a_folder_argument_that_is_a_file_or_a_broken_link_says_so(clip, tmp_path):
    """A folder argument given a file, or a symbolic link to a folder that is not there (a drive
    not mounted), said "no folder at" the path, which is there: the message now says what is."""
    from fsof_torch.datasets import SyntheticFlowDataset

    root, _ = clip
    frame = root / "images" / "000000.png"
    with pytest.raises(FileNotFoundError, match=r"^images: '.*000000\.png' is a file; expected a folder$"):
        ImageFolderDataset(frame)
    for what in ("gt", "road"):
        with pytest.raises(FileNotFoundError, match=rf"^{what}: '.*000000\.png' is a file; expected a folder$"):
            match_files(frame, ["000000"], what=what)
    link = tmp_path / "mounted"
    link.symlink_to(tmp_path / "drive" / "clip")
    with pytest.raises(FileNotFoundError, match=r"^images: '.*mounted' is a symbolic link to '.*drive/clip', "
                                                r"which does not exist"):
        ImageFolderDataset(link)
    with pytest.raises(FileNotFoundError, match=r"^gt: '.*mounted' is a symbolic link"):
        ImageFolderDataset(root / "images", gt=link)
    with pytest.raises(FileNotFoundError, match=r"^root: '.*000000\.png' is a file; expected a folder$"):
        SyntheticFlowDataset(frame)
    with pytest.raises(FileNotFoundError, match=r"^images: no folder at '.*nothing'$"):  # (nothing there)
        ImageFolderDataset(tmp_path / "nothing")


def test_frame_linked_to_a_missing_file_is_an_error(tmp_path):
    """A frame that is a symbolic link to a missing file (data on a drive not mounted) was left out
    silently: its neighbours made a pair two frames apart, named as one frame apart."""
    clip, store = tmp_path / "clip", tmp_path / "store"
    clip.mkdir()
    store.mkdir()
    for n in (0, 1, 3):
        write_image(clip / f"{n:06d}.png", torch.full((3, *SIZE), n, dtype=torch.uint8))
    write_image(store / "elsewhere.png", torch.zeros(3, *SIZE, dtype=torch.uint8))
    (clip / "000002.png").symlink_to(store / "elsewhere.png")  # a link that works is a frame
    assert [(p.image1.name, p.image2.name) for p in ImageFolderDataset(clip).pairs] == [
        ("000000.png", "000001.png"), ("000001.png", "000002.png"), ("000002.png", "000003.png")]
    (store / "elsewhere.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"images: '.*000002\.png' is a symbolic link to '.*elsewhere\.png', "
                                                r"which does not exist"):
        ImageFolderDataset(clip)


def test_files_match_by_name_never_by_position(clip):
    root, _ = clip
    (root / "gt" / "000001.flo").rename(root / "gt" / "000007.flo")
    with pytest.raises(ValueError, match=r"^gt: no file for pair 000001 in .*expected 000001\.\* \(\.png, \.flo, \.npy\)"):
        ImageFolderDataset(root / "images", gt=root / "gt")
    write_flow(root / "gt" / "000000.npy", torch.zeros(2, *SIZE))
    with pytest.raises(ValueError, match=r"gt: pair 000000 matches 2 files .*\(000000\.flo, 000000\.npy\); keep one"):
        match_files(root / "gt", ["000000"], what="gt")
    with pytest.raises(FileNotFoundError, match=r"^road: no folder at"):
        ImageFolderDataset(root / "images", road=root / "nothing")
    with pytest.raises(FileNotFoundError, match=r"^road: no file at .*none\.json"):
        ImageFolderDataset(root / "images", road=root / "none.json")
    with pytest.raises(FileNotFoundError, match=r"^road: no file at .*none\.png"):  # (not 'no folder at')
        ImageFolderDataset(root / "images", road=root / "none.png")


def test_sizes_against_the_first_pair_and_the_calibration(clip, tmp_path):
    root, _ = clip
    write_image(root / "images" / "000003.png", torch.zeros(3, 20, 40))
    ds = ImageFolderDataset(root / "images", root / "calib.txt")  # the first pair is fine
    ds[1]
    with pytest.raises(ValueError, match=r"^images: 000003\.png is 20x40 but 000000\.png is 24x40; all images need one size"):
        ds[2]
    with pytest.raises(ValueError, match=r"^images: 000000\.png is 24x40 but the calibration .* is for 48x80 images"):
        ImageFolderDataset(root / "images", root / "calib.txt", calib_size=(48, 80))
    cam2cam = tmp_path / "calib_cam_to_cam.txt"
    write_kitti_calibration(cam2cam, K, cam=2)
    cam2cam.write_text(cam2cam.read_text() + "S_rect_02: 8.000000e+01 4.800000e+01\n")
    with pytest.raises(ValueError, match=r"is for 48x80 images"):
        ImageFolderDataset(root / "images", cam2cam)
    # a stated size that is not the file's own: the calibration of 48x80 images was taken for 24x40
    with pytest.raises(ValueError, match=r"^calib_size: 24x40 is not the size .*calib_cam_to_cam\.txt' states for "
                                         r"camera 2 \(S_rect_02: 48x80\); leave it out"):
        ImageFolderDataset(root / "images", cam2cam, calib_size=SIZE)
    with pytest.raises(ValueError, match=r"is for 48x80 images"):  # the file's own size, stated again
        ImageFolderDataset(root / "images", cam2cam, calib_size=(48, 80))
    # a calibration for images twice as large: the principal point is a quarter image off centre
    write_kitti_calibration(tmp_path / "double.txt", K * torch.tensor([[2.0], [2.0], [1.0]], dtype=torch.float64),
                            cam=0, style="odometry")
    with pytest.raises(ValueError, match=r"^images: 000000\.png is 24x40, but the principal point .*middle third"):
        ImageFolderDataset(root / "images", tmp_path / "double.txt")
    # frames cropped after calibration (the top rows cut away, the crop's K): a camera's own principal
    # point that far off centre; the message says how such a camera passes, and it does
    crop = K.clone()
    crop[1, 2] = 17.0  # (more than H / 6 = 4 px below the middle row of 24, 11.5)
    write_kitti_calibration(tmp_path / "crop.txt", crop, cam=0, style="odometry")
    with pytest.raises(ValueError, match=r"middle third of such an image, as a calibration of another image size puts "
                                         r"it \(give images of the calibrated size\); a camera whose principal point "
                                         r"lies that far off centre \(frames cropped after calibration, the crop's K\) "
                                         r"states the size with calib_size=\(H, W\)$"):
        ImageFolderDataset(root / "images", tmp_path / "crop.txt")
    cropped = ImageFolderDataset(root / "images", tmp_path / "crop.txt", calib_size=SIZE)
    assert torch.equal(cropped[0]["camera"].K[0].to(torch.float64), crop.to(torch.float64))


@pytest.mark.parametrize("row", ["nan 48", "80 inf", "-80 48", "0 48", "80 0.2"])
def test_size_row_not_two_sizes_names_calib(clip, tmp_path, row):
    """NaN / inf in S_rect once raised from int(round(...)) (cannot convert float NaN to integer)."""
    root, _ = clip
    cam2cam = tmp_path / "calib_cam_to_cam.txt"
    write_kitti_calibration(cam2cam, K, cam=2)
    cam2cam.write_text(cam2cam.read_text() + f"S_rect_02: {row}\n")
    with pytest.raises(ValueError, match=rf"^calib: '.*calib_cam_to_cam\.txt' has an S_rect_02 row that is not "
                                         rf"'W H' \(two sizes of at least one pixel\): 'S_rect_02: {row}'"):
        calibration_size(cam2cam, 2)
    with pytest.raises(ValueError, match=r"^calib: .* has an S_rect_02 row that is not 'W H'"):
        ImageFolderDataset(root / "images", cam2cam)


def test_size_row_after_a_byte_order_mark(clip, tmp_path):
    """A BOM before S_rect_02 once hid the row (read_text kept the BOM), so the size went unchecked."""
    root, _ = clip
    cam2cam = tmp_path / "calib_cam_to_cam.txt"
    write_kitti_calibration(cam2cam, K, cam=2)
    cam2cam.write_bytes(b"\xef\xbb\xbfS_rect_02: 8.000000e+01 4.800000e+01\n" + cam2cam.read_bytes())
    assert calibration_size(cam2cam, 2) == (48, 80)
    with pytest.raises(ValueError, match=r"is for 48x80 images"):
        ImageFolderDataset(root / "images", cam2cam)


def test_errors_name_the_argument_and_the_file(clip, tmp_path):
    root, _ = clip
    with pytest.raises(FileNotFoundError, match=r"^images: no folder at"):
        ImageFolderDataset(tmp_path / "none")
    with pytest.raises(ValueError, match=r"^images: 1 image\(s\) given; a pair needs at least 2"):
        ImageFolderDataset([root / "images" / "000000.png"])
    with pytest.raises(ValueError, match=r"^images: 4 frames make no pair \(i, i \+ step\) with step 4"):
        ImageFolderDataset(root / "images", step=4)
    with pytest.raises(ValueError, match=r"^images: 000000\.png is 24x40 but calib_size is for 12x40 images"):
        ImageFolderDataset(root / "images", calib_size=(12, 40))
    with pytest.raises(FileNotFoundError, match=r"^calib: no calibration file at"):
        ImageFolderDataset(root / "images", tmp_path / "calib.txt")
    # a folder, or a link to a missing file (a drive not mounted), is named as such, not as missing
    (tmp_path / "calib_dir.txt").mkdir()
    with pytest.raises(IsADirectoryError, match=r"^calib: '.*calib_dir\.txt' is a folder; expected a calibration file"):
        ImageFolderDataset(root / "images", tmp_path / "calib_dir.txt")
    (tmp_path / "calib_link.txt").symlink_to(tmp_path / "unmounted" / "calib.txt")
    with pytest.raises(FileNotFoundError, match=r"^calib: '.*calib_link\.txt' is a symbolic link to .*unmounted"):
        ImageFolderDataset(root / "images", tmp_path / "calib_link.txt")
    (tmp_path / "calib.bin").write_bytes(bytes(range(256)))
    with pytest.raises(ValueError, match=r"^calib: .*calib\.bin"):
        ImageFolderDataset(root / "images", tmp_path / "calib.bin")
    with pytest.raises(ValueError, match=r"^cam: expected 0\.\.3, got 4"):
        ImageFolderDataset(root / "images", root / "calib.txt", cam=4)
    # without calib too: a bad cam was taken without a word, where the same call with calib refused it
    with pytest.raises(ValueError, match=r"^cam: expected 0\.\.3, got 4"):
        ImageFolderDataset(root / "images", cam=4)
    with pytest.raises(TypeError, match=r"^cam: expected None or an int, got str '2'"):
        ImageFolderDataset(root / "images", cam="2")
    assert ImageFolderDataset(root / "images", cam=2)[0]["camera"] is None
    with pytest.raises(ValueError, match=r"^camera_height: expected a positive number"):
        ImageFolderDataset(root / "images", root / "calib.txt", camera_height=0.0)
    short = tmp_path / "poses.txt"
    write_kitti_poses(short, read_kitti_poses(root / "poses.txt")[:2])
    with pytest.raises(ValueError, match=r"^poses: .*poses\.txt' has 2 poses for 4 images"):
        ImageFolderDataset(root / "images", poses=short)
    rows = (root / "poses.txt").read_text().splitlines()
    rows[2] = " ".join(["0"] * 12)
    short.write_text("\n".join(rows) + "\n")
    with pytest.raises(ValueError, match=r"^poses: .*line 3 .*not a rigid pose"):
        ImageFolderDataset(root / "images", poses=short)
    (tmp_path / "road.json").write_text("5")
    with pytest.raises(ValueError, match=r"^road: '.*road\.json': expected a JSON object .* got int 5$"):
        ImageFolderDataset(root / "images", road=tmp_path / "road.json")
    # a polygon drawn for other images (twice the size) was stretched over these: now refused
    (tmp_path / "road.json").write_text(json.dumps({"size": [2 * SIZE[0], 2 * SIZE[1]],
                                                    "road_polygon": [[0, 47], [0, 24], [79, 24], [79, 47]]}))
    with pytest.raises(ValueError, match=r"^road: '.*road\.json' is a polygon drawn for 48x80 images \(its 'size'\), "
                                         r"but size is 24x40; "):
        ImageFolderDataset(root / "images", road=tmp_path / "road.json")
    write_road_mask(root / "road" / "000001.png", torch.ones(1, 10, 10, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"^road: 000001\.png is \(10, 10\), the images \(24, 40\)"):
        ImageFolderDataset(root / "images", road=root / "road")[1]
    # files removed after the dataset was made: named with the argument when the pair loads
    ds = ImageFolderDataset(root / "images", gt=root / "gt")
    (root / "gt" / "000002.flo").unlink()
    with pytest.raises(FileNotFoundError, match=r"^gt: no file at '.*000002\.flo'"):
        ds[2]


@pytest.mark.parametrize("kwargs, message", [
    ({"roll": 1.6}, r"^roll: expected \|θ\| < π/2 rad"),
    ({"pitch": -1.6}, r"^pitch: expected \|β\| < π/2 rad"),
    ({"camera_height": 1e10}, r"^camera_height: expected a camera height in \[2.98e-08, 3.36e\+07\] m"),
])
@pytest.mark.parametrize("with_calib", [True, False])
def test_a_bad_mounting_names_the_argument(clip, kwargs, message, with_calib):
    """The camera's errors came prefixed "calib: '...' camera 0:" (and without calib, unchecked)."""
    root, _ = clip
    with pytest.raises(ValueError, match=message):
        ImageFolderDataset(root / "images", root / "calib.txt" if with_calib else None, **kwargs)


@pytest.mark.parametrize("index, error, message", [
    (True, TypeError, r"^index: expected an int, got bool True"),
    (1.0, TypeError, r"^index: expected an int, got float 1\.0"),
    ("0", TypeError, r"^index: expected an int, got str '0'"),
    (3, IndexError, r"^index: 3 out of range for a dataset of 3 pairs"),
])
def test_check_index_refuses_a_bool_and_quotes_the_value(index, error, message):
    with pytest.raises(error, match=message):
        check_index(index, 3)
    assert check_index(-1, 3) == 2 and check_index(np.int64(1), 3) == 1


@pytest.mark.parametrize("index, error", [
    (torch.tensor(True), TypeError), (torch.tensor(1.0), TypeError), (torch.tensor([1]), TypeError),
    (np.array(1.0), TypeError), (torch.tensor(3), IndexError)])
def test_a_0d_integer_tensor_is_an_index_as_in_a_list(clip, index, error):
    """A 0-d integer tensor or array indexes a dataset as it indexes a list (Subset(ds,
    torch.randperm(n)) hands such indices over); a bool, float or 1-element tensor does not."""
    from torch.utils.data import DataLoader, Subset

    from fsof_torch.data.items import collate

    root, _ = clip
    ds = ImageFolderDataset(root / "images")
    assert check_index(torch.tensor(-1), 3) == 2 and check_index(np.array(1, dtype=np.int32), 3) == 1
    batch = next(iter(DataLoader(Subset(ds, torch.tensor([2, 0])), batch_size=2, collate_fn=collate)))
    assert batch["index"] == [2, 0] and batch["name"] == ["000002", "000000"]
    with pytest.raises(error, match=r"^index: "):
        ds[index]


@pytest.mark.parametrize("pose, edit, message", [
    (1, lambda P: P.__setitem__((1, 0, 3), float("nan")), r"pose 1 of the tensor holds NaN or inf"),
    (1, lambda P: P[1, :3, :3].mul_(3.0), r"pose 1 of the tensor is not a rigid pose: its 3×3 block is not a "
                                           r"rotation \(\|RᵀR − I\| up to 8, det 27"),
    (2, lambda P: P[2, :3, :3].zero_(), r"pose 2 of the tensor is not a rigid pose: .*det 0"),
    (0, lambda P: P.__setitem__((0, 3, 0), 5.0), r"pose 0 of the tensor is not a rigid pose: its last row is "
                                                  r"5 0 0 1, not 0 0 0 1"),
])
def test_a_poses_tensor_is_checked_as_a_poses_file_is(clip, pose, edit, message):
    """A poses tensor gets the checks of a poses file (finite, last row 0 0 0 1, a rotation block):
    a 3x scaled block was once accepted and gave a wrong odometry (z_d 1/3), NaN and an all-zero
    block stopped only at the item, under another name."""
    root, poses = clip
    bad = poses.clone()
    edit(bad)
    with pytest.raises(ValueError, match=rf"^poses: {message}"):
        ImageFolderDataset(root / "images", root / "calib.txt", poses=bad)
    given = poses.clone()
    ds = ImageFolderDataset(root / "images", root / "calib.txt", poses=given)
    given[1, 2, 3] += 10.0  # the dataset holds its own copy
    torch.testing.assert_close(ds[0]["relative_pose"], torch.linalg.inv(poses[1]) @ poses[0], rtol=0, atol=1e-12)


def test_two_files_of_one_frame_name_are_refused(clip, tmp_path):
    """000000.png beside 000000.jpg was paired with its own copy, and two pairs shared one name
    (and so one road and gt file); in a KITTI layout the last file of a name silently won."""
    root, _ = clip
    write_image(root / "images" / "000000.jpg", _frame(0))
    message = r"^images: 000000\.jpg and 000000\.png share the frame name 000000"
    with pytest.raises(ValueError, match=message):
        ImageFolderDataset(root / "images")
    frames = [root / "images" / n for n in ("000000.png", "000001.png", "000000.jpg")]
    with pytest.raises(ValueError, match=r"^images: 000000\.png and 000000\.jpg share the frame name 000000"):
        ImageFolderDataset(frames)
    kitti = [tmp_path / n for n in ("a_10.png", "a_11.png", "a_11.jpg", "b_10.png", "b_11.png")]
    with pytest.raises(ValueError, match=r"^images: a_11\.png and a_11\.jpg share the frame name a_11"):
        frame_pairs(kitti)
    assert frame_pairs([tmp_path / "a" / "0.png", tmp_path / "b" / "1.png"]) == [("0", 0, 1)]


def test_a_malformed_camera_2_row_raises_not_falls_back_to_camera_0(clip, tmp_path):
    """Without ``cam``, camera 0 is used only where the file has no camera-2 row: an 11-number
    or NaN P_rect_02 once gave camera 0's intrinsics silently."""
    root, _ = clip
    p0 = "P_rect_00: 30 0 19.5 0 0 30 11.5 0 0 0 1 0\n"
    calib = tmp_path / "cc.txt"
    calib.write_text(p0 + "P_rect_02: 40 0 19.5 0 0 40 11.5 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"^calib: .*camera 2 in .*cc\.txt' has 11 numbers, expected 12"):
        ImageFolderDataset(root / "images", calib)
    calib.write_text(p0 + "P_rect_02: 40 0 19.5 0 0 40 nan 0 0 0 1 0\n")
    with pytest.raises(ValueError, match=r"^calib: .*P_rect_02 row of .*cc\.txt' holds NaN or inf"):
        ImageFolderDataset(root / "images", calib)
    calib.write_text(p0)  # no camera-2 row: camera 0
    assert float(ImageFolderDataset(root / "images", calib).camera.K[0, 0, 0]) == 30.0
    calib.write_text(p0 + "P_rect_02: 40 0 19.5 0 0 40 11.5 0 0 0 1 0\n")
    assert float(ImageFolderDataset(root / "images", calib).camera.K[0, 0, 0]) == 40.0
    # an unlabelled row beside labelled P rows is not camera 2's: camera 0 (as the reader sees it)
    calib.write_text(p0 + "1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    assert float(ImageFolderDataset(root / "images", calib).camera.K[0, 0, 0]) == 30.0


def test_one_road_png_of_another_size_is_refused(clip, tmp_path):
    """A single road PNG for every pair must have the images' size, as a folder's PNGs must (it
    was resized silently); a polygon JSON is still drawn at the images' size."""
    root, _ = clip
    write_road_mask(tmp_path / "big.png", torch.ones(1, 2 * SIZE[0], 2 * SIZE[1], dtype=torch.bool))
    with pytest.raises(ValueError, match=r"^road: big\.png is \(48, 80\), the images \(24, 40\)"):
        ImageFolderDataset(root / "images", road=tmp_path / "big.png")


def test_odometry_without_a_calibration_takes_the_given_mounting(clip):
    """``roll`` and ``pitch`` are the camera's mounting with ``calib=None`` too: the odometry is the
    poses' planar part under them, as with a calibration (K plays no part), not a level camera's."""
    root, poses = clip
    mounting = {"roll": 0.05, "pitch": 0.1}
    with_calib = ImageFolderDataset(root / "images", root / "calib.txt", poses=poses, **mounting)[1]
    without = ImageFolderDataset(root / "images", poses=poses, **mounting)[1]
    level = ImageFolderDataset(root / "images", poses=poses)[1]
    assert without["camera"] is None
    for key in ("odometry", "pose_residual"):
        for name, value in with_calib[key].items():
            assert without[key][name] == pytest.approx(value, rel=1e-12, abs=1e-15), (key, name)
    # the mounting matters: a pitched camera sees the 1 m forward motion partly as y_d
    assert abs(level["pose_residual"]["y_d"]) < 1e-12
    assert abs(without["pose_residual"]["y_d"]) == pytest.approx(math.sin(0.1), rel=0.05)


def _pairs_in_time_order(tmp_path, names):
    """Frames ``names`` (in time order; frame k holds the value k) in a folder and a CARLA run:
    both list them in that order, and the folder's pairs are (k, k + 1)."""
    from fsof_torch.data.folders import list_images
    from fsof_torch.io.carla import CarlaRun

    for k, name in enumerate(names):
        write_image(tmp_path / f"{name}.png", torch.full((3, *SIZE), k, dtype=torch.uint8))
    assert [p.stem for p in list_images(tmp_path)] == names
    ds = ImageFolderDataset(tmp_path)
    assert [p.name for p in ds.pairs] == names[:-1]
    assert [(float(ds[i]["image1"][0, 0, 0]), float(ds[i]["image2"][0, 0, 0])) for i in range(len(ds))] == [
        (float(k), float(k + 1)) for k in range(len(names) - 1)]
    run = tmp_path / "run"
    (run / "rgb").mkdir(parents=True)
    for name in names:
        write_image(run / "rgb" / f"{name}.png", torch.zeros(3, 4, 4))
    assert CarlaRun(run).frames == names


def test_frames_named_by_decimal_timestamps_pair_in_time_order(tmp_path):
    """Frames named by their time in seconds (``9.967.png``, ``10.000.png``): by name 10.000 came
    before 9.900, so the clip paired 10.033 -> 9.900 (backwards in time, across the whole clip)."""
    _pairs_in_time_order(tmp_path, ["9.900", "9.933", "9.967", "10.000", "10.033"])
    # timestamps of one width keep the names' order, which is their time order
    from fsof_torch.io.images import in_frame_order

    stamps = ["1541234567.15", "1541234567.2", "1541234568.05"]
    assert [p.stem for p in in_frame_order(f"{s}.png" for s in reversed(stamps))] == stamps


@pytest.mark.parametrize("pattern", ["left_{}", "{}_cam0", "cam0_{}_rect", "t{}"])
def test_frames_named_by_timestamps_within_a_text_pair_in_time_order(tmp_path, pattern):
    """Timestamps with a text around them (``left_9.967.png``, ``9.967_cam0.png``) sorted by name:
    left_10.000 came before left_9.900, so the clip paired left_10.033 -> left_9.900 (backwards in
    time, across the whole clip), as bare timestamps once did."""
    from fsof_torch.io.images import decimal_times

    _pairs_in_time_order(tmp_path, [pattern.format(t) for t in ["9.900", "9.933", "9.967", "10.000", "10.033"]])
    # the text is the same in every name: digits it shares with the numbers are the numbers'
    assert decimal_times(["t_10.0", "t_10.25", "t_9.5"]) == [10.0, 10.25, 9.5]
    assert decimal_times(["left_9.5", "right_10.0"]) is None  # other texts: by name
    assert decimal_times(["a_1.5_b", "a_2.5_c"]) is None


def test_a_frame_list_with_a_missing_file_or_a_folder_is_refused_when_made(clip):
    """A list of frames was read only when a pair loaded: a missing third frame raised at item 1 of
    a DataLoader run, a folder in the list an IsADirectoryError that named no argument."""
    root, _ = clip
    frames = sorted((root / "images").iterdir())
    with pytest.raises(FileNotFoundError, match=r"^images: no file at '.*nope\.png'$"):
        ImageFolderDataset([*frames[:2], root / "images" / "nope.png"])
    with pytest.raises(IsADirectoryError, match=r"^images: '.*images' is a folder; expected an image file$"):
        ImageFolderDataset([*frames[:2], root / "images"])
    ds = ImageFolderDataset(frames)
    frames[2].unlink()
    frames[2].mkdir()  # (replaced by a folder since the dataset was made)
    with pytest.raises(IsADirectoryError, match=r"^images: '.*000002\.png' is a folder"):
        ds[1]


@pytest.mark.parametrize("what, file", [("calib", "calib.txt"), ("poses", "poses.txt"), ("road", "road.json")])
def test_a_file_argument_linked_to_a_missing_file_says_so(clip, tmp_path, what, file):
    """calib=, poses= or road= a link to a missing file (a drive not mounted) read as 'no file at'."""
    root, _ = clip
    link = tmp_path / file
    link.symlink_to(tmp_path / "unmounted" / file)
    with pytest.raises(FileNotFoundError, match=rf"^{what}: '.*{file}' is a symbolic link to '.*unmounted/{file}', "
                                                r"which does not exist"):
        ImageFolderDataset(root / "images", **{what: link})


@pytest.mark.parametrize("kwargs, error", [
    ({"images": None}, r"^images: expected a folder or a list of image files, got NoneType None$"),
    ({"images": 7}, r"^images: expected a folder or a list of image files, got int 7$"),
    ({"images": b"clip/images"}, r"^images: expected a folder or a list of image files, got bytes b'clip/images'$"),
    ({"images": [0, 1]}, r"^images: expected a file path \(str or os.PathLike\), got int 0$"),
    ({"calib": 3}, r"^calib: expected a file path \(str or os.PathLike\), got int 3$"),
    ({"road": ["a.png"]}, r"^road: expected a file path \(str or os.PathLike\), got list \['a.png'\]$"),
    ({"gt": 1.5}, r"^gt: expected a file path \(str or os.PathLike\), got float 1.5$"),
    ({"poses": [[1.0] * 12]}, r"^poses: expected a poses file or an \(N, 4, 4\) float tensor, got list "),
    ({"poses": True}, r"^poses: expected a poses file or an \(N, 4, 4\) float tensor, got bool True$"),
])
def test_arguments_that_are_no_paths_are_named(clip, kwargs, error):
    """An argument of another type than documented raised Python's own TypeError from Path() or
    iteration ("'NoneType' object is not iterable", "expected str, bytes or os.PathLike object,
    not int"), naming no argument."""
    root, _ = clip
    kwargs = {"images": root / "images", **kwargs}
    with pytest.raises(TypeError, match=error):
        ImageFolderDataset(**kwargs)


def test_poses_as_a_numpy_array(clip):
    """(N, 4, 4) poses as a NumPy array (np.loadtxt(...).reshape) raised a bare TypeError from
    Path(); they read as the same poses as a tensor, copied."""
    root, poses = clip
    array = poses.numpy().copy()
    ds = ImageFolderDataset(root / "images", poses=array)
    reference = ImageFolderDataset(root / "images", poses=poses)
    for i in range(len(ds)):
        assert torch.equal(ds[i]["relative_pose"], reference[i]["relative_pose"])
        assert ds[i]["odometry"] == reference[i]["odometry"]
    # the expected relative pose of pair 1, by hand: inverse(P_2) @ P_1 = inverse(M_2)
    torch.testing.assert_close(ds[1]["relative_pose"], torch.linalg.inv(_motion(0.02)), rtol=0, atol=1e-12)
    array[:, 0, 3] += 5.0  # the dataset holds its own copy
    assert torch.equal(ds[1]["relative_pose"], reference[1]["relative_pose"])
    with pytest.raises(TypeError, match=r"^poses: expected an \(N, 4, 4\) float tensor, got dtype torch.int64$"):
        ImageFolderDataset(root / "images", poses=np.round(array).astype(np.int64))


def test_clip_beside_other_images_is_refused(tmp_path):
    """A clip named by numbers beside an image named otherwise (a preview.png), or two cameras'
    clips in one folder (left_*, right_*), sorted by name paired the clip's last frame with the
    other image (000002 -> preview, left_000002 -> right_000000): a ValueError naming `images`,
    the folder and the names. One clip, names without numbers and KITTI pairs keep working."""
    from fsof_torch.data.folders import list_images

    clip = tmp_path / "clip"
    clip.mkdir()
    for n in range(3):
        write_image(clip / f"{n:06d}.png", torch.full((3, *SIZE), n, dtype=torch.uint8))
    assert [p.name for p in ImageFolderDataset(clip).pairs] == ["000000", "000001"]
    write_image(clip / "preview.png", torch.zeros(3, *SIZE))
    message = (rf"^images: '{re.escape(str(clip))}' holds frames named by a number beside images named otherwise "
               rf"\(000000.png ... 000002.png \(3\); preview.png\);")
    with pytest.raises(ValueError, match=message):
        ImageFolderDataset(clip)
    with pytest.raises(ValueError, match=message):
        list_images(clip)

    cams = tmp_path / "cams"
    cams.mkdir()
    for side in ("left", "right"):
        for n in range(3):
            write_image(cams / f"{side}_{n:06d}.png", torch.zeros(3, *SIZE))
    with pytest.raises(ValueError, match=r"\(left_000000.png ... left_000002.png \(3\); right_000000.png ... "
                                         r"right_000002.png \(3\)\)"):
        ImageFolderDataset(cams)

    plain = tmp_path / "plain"  # no numbers: the names' order, as before
    plain.mkdir()
    for stem in ("a", "b", "c"):
        write_image(plain / f"{stem}.png", torch.zeros(3, *SIZE))
    assert [p.name for p in ImageFolderDataset(plain).pairs] == ["a", "b"]
    pairs = tmp_path / "pairs"  # KITTI road's names: pairs by name under two texts
    pairs.mkdir()
    for stem in ("um_000000", "uu_000003"):
        for t in ("10", "11"):
            write_image(pairs / f"{stem}_{t}.png", torch.zeros(3, *SIZE))
    assert [p.name for p in ImageFolderDataset(pairs).pairs] == ["um_000000", "uu_000003"]


def test_series_told_apart_by_one_number_are_refused(tmp_path):
    """Two cameras' frames named alike but for a number (cam0_000000 ..., cam1_000000 ...), or a
    stereo rig's (000000_0, 000000_1, ...), were sorted by name into one clip: cam0's last frame
    paired with cam1's first, or each left frame with its right one. A ValueError naming
    `images`, the folder and the series. A frame counter beside a timestamp (both numbers vary,
    each unique) stays one clip."""
    from fsof_torch.data.folders import list_images

    cams = tmp_path / "cams"
    cams.mkdir()
    for cam in (0, 1):
        for n in range(3):
            write_image(cams / f"cam{cam}_{n:06d}.png", torch.zeros(3, *SIZE))
    folder = re.escape(repr(str(cams)))
    with pytest.raises(ValueError, match=rf"^images: {folder} holds 2 series of frames named alike but for one number "
                                         r"\(cam0_000000.png ... cam0_000002.png \(3\); cam1_000000.png ... "
                                         r"cam1_000002.png \(3\)\)"):
        list_images(cams)
    with pytest.raises(ValueError, match="holds 2 series"):
        ImageFolderDataset(cams)
    stereo = tmp_path / "stereo"
    stereo.mkdir()
    for n in range(3):
        for side in (0, 1):
            write_image(stereo / f"{n:06d}_{side}.png", torch.zeros(3, *SIZE))
    with pytest.raises(ValueError, match=r"holds 2 series .*\(000000_0.png ... 000002_0.png \(3\); "
                                         r"000000_1.png ... 000002_1.png \(3\)\)"):
        list_images(stereo)
    timed = tmp_path / "timed"
    timed.mkdir()
    for n, t in enumerate((1000, 1100, 1205)):
        write_image(timed / f"{n:06d}_{t}.png", torch.zeros(3, *SIZE))
    assert [p.name for p in list_images(timed)] == ["000000_1000.png", "000001_1100.png", "000002_1205.png"]


def test_folder_of_camera_folders_names_where_the_frames_are(tmp_path):
    """A KITTI raw camera folder (image_02/, its frames in data/) or an odometry sequence
    (sequences/00/, frames in image_0/ and image_2/) given for the frames: 'holds 0 image(s)'
    said nothing of where they are; the error now names the sub-folders that hold images."""
    from fsof_torch.data.folders import list_images

    camera = tmp_path / "image_02"
    (camera / "data").mkdir(parents=True)
    (camera / "timestamps.txt").write_text("2011-09-26 13:02:25.964389445\n")
    for n in range(3):
        write_image(camera / "data" / f"{n:010d}.png", torch.zeros(3, *SIZE))
    data = re.escape(repr(str(camera / "data")))
    with pytest.raises(ValueError, match=rf"^images: .* holds 0 image\(s\); a pair needs at least 2; its sub-folder "
                                         rf"{data} \(3 images\) holds images: give the folder of one camera's frames$"):
        ImageFolderDataset(camera)
    assert [p.name for p in ImageFolderDataset(camera / "data").pairs] == ["0000000000", "0000000001"]
    sequence = tmp_path / "00"
    for sub, count in (("image_0", 2), ("image_2", 1)):
        (sequence / sub).mkdir(parents=True)
        for n in range(count):
            write_image(sequence / sub / f"{n:06d}.png", torch.zeros(3, *SIZE))
    (sequence / "empty").mkdir()
    with pytest.raises(ValueError, match=r"its sub-folders '.*image_0' \(2 images\), '.*image_2' \(1 image\) hold "
                                         r"images: give"):
        list_images(sequence)
    with pytest.raises(ValueError, match=r"holds 0 image\(s\); a pair needs at least 2$"):  # (nothing below)
        list_images(sequence / "empty")


def test_road_or_gt_given_the_images_is_an_error(tmp_path):
    """road= pointed at the images' folder (a slip of the shell's completion) or at one of the
    frames read each pair's own colour image as its mask: every nonzero pixel road, here all of
    them, silently. A ValueError names road (or gt) and the frame; real masks still read."""
    images = tmp_path / "images"
    images.mkdir()
    for n in range(3):
        write_image(images / f"{n:06d}.png", (_frame(n) + 1).to(torch.uint8))
    with pytest.raises(ValueError, match=r"^road: '.*000000\.png' is one of the images \(the frame 000000\.png\), "
                                         r"not a road mask"):
        ImageFolderDataset(images, road=images)
    with pytest.raises(ValueError, match=r"^road: '.*000002\.png' is one of the images"):
        ImageFolderDataset(images, road=images / ".." / "images" / "000002.png")
    with pytest.raises(ValueError, match=r"^gt: '.*000000\.png' is one of the images .*, not a flow"):
        ImageFolderDataset(images, gt=images)
    os.link(images / "000001.png", tmp_path / "road.png")  # (a hard link: the frame's file under another name)
    with pytest.raises(ValueError, match=r"^road: '.*road\.png' is one of the images \(the frame 000001\.png\)"):
        ImageFolderDataset(images, road=tmp_path / "road.png")
    masks = tmp_path / "road"
    masks.mkdir()
    mask = torch.zeros(1, *SIZE, dtype=torch.bool)
    mask[:, SIZE[0] // 2:] = True
    for n in range(2):
        write_road_mask(masks / f"{n:06d}.png", mask)
    assert torch.equal(ImageFolderDataset(images, road=masks)[1]["road"], mask)


def test_errors_of_the_files_read_name_the_datasets_argument_alone(tmp_path):
    """A poses or calibration file the reader refuses was named twice, as the dataset's argument
    and the reader's ('poses: path: line 1 of ...'): the dataset's argument alone now."""
    clip = tmp_path / "clip"
    clip.mkdir()
    for n in range(2):
        write_image(clip / f"{n:06d}.png", torch.zeros(3, *SIZE))
    (tmp_path / "poses.txt").write_text("1 2 3\n")
    (tmp_path / "calib.txt").write_text("P0: 1 2\n")
    with pytest.raises(ValueError, match=rf"^poses: line 1 of {re.escape(repr(str(tmp_path / 'poses.txt')))} has 3 "
                                         r"numbers; expected 12"):
        ImageFolderDataset(clip, poses=tmp_path / "poses.txt")
    with pytest.raises(ValueError, match=r"^calib: the projection row of camera 0 in .*calib\.txt' has 2 numbers"):
        ImageFolderDataset(clip, calib=tmp_path / "calib.txt")
