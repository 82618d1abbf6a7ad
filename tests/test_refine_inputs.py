"""``refine.inputs``: the job loads through the library's datasets. For the same files (written to
tmp_path by the library's writers) the job's pairs and the datasets' items are identical, both
follow the item contract, and both equal the data that was written (read back independently
where the format rounds: images to integers, KITTI flow PNGs to 1/64 px). A pair's resume
identity changes with its own files only."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
import torch

from fsof_torch import Camera
from fsof_torch.data.items import ITEM_KEYS, check_item
from fsof_torch.datasets import ImageFolderDataset, KittiOdometryDataset, KittiSampleDataset, SceneDataset

SIZE = (48, 160)
POLYGON = [[0, 47], [40, 36], [120, 36], [159, 47]]


@pytest.fixture(scope="module")
def scene():
    """Three consecutive rendered pairs (four frames)."""
    from fsof_torch.data.scene import render_pair

    return [render_pair("default", i, size=SIZE) for i in range(3)]


def _frames(scene) -> list[torch.Tensor]:
    return [scene[0]["image1"], *(p["image2"] for p in scene)]


def _mounting(camera: Camera) -> dict[str, float]:
    return {"height": float(camera.height[0]), "roll_deg": math.degrees(float(camera.roll[0])),
            "pitch_deg": math.degrees(float(camera.pitch[0]))}


@pytest.fixture
def user_folder(tmp_path, scene) -> Path:
    """A clip of four frames with calib.txt, poses.txt, road PNGs, ground truth and flows."""
    from fsof_torch.io import write_flow, write_image, write_kitti_calibration, write_kitti_poses, write_road_mask

    root = tmp_path / "user"
    for d in ("images", "road", "gt", "flows"):
        (root / d).mkdir(parents=True)
    for i, im in enumerate(_frames(scene)):
        write_image(root / "images" / f"{i:06d}.png", im)
    write_kitti_calibration(root / "calib.txt", scene[0]["camera"].K[0], cam=0, style="odometry")
    write_kitti_poses(root / "poses.txt", torch.stack([scene[0]["pose1"], *(p["pose2"] for p in scene)]))
    for i, (p, ext) in enumerate(zip(scene, (".flo", ".npy", ".png"))):
        write_road_mask(root / "road" / f"{i:06d}.png", p["road"])
        write_flow(root / "gt" / f"{i:06d}.png", p["flow"], p["valid"])
        write_flow(root / "flows" / f"{i:06d}{ext}", p["flow"] + 0.5)
    return root


@pytest.fixture
def kitti15_folder(tmp_path, scene) -> Path:
    """A folder in the layout of shared/data/kitti15_000000."""
    from fsof_torch.io import write_image, write_kitti_calibration, write_kitti_flow

    root = tmp_path / "kitti15_000000"
    root.mkdir()
    p = scene[0]
    write_image(root / "image_10.png", p["image1"])
    write_image(root / "image_11.png", p["image2"])
    write_kitti_calibration(root / "calib_cam_to_cam.txt", p["camera"].K[0], cam=2)
    with open(root / "calib_cam_to_cam.txt", "a") as f:
        f.write(f"S_rect_02: {SIZE[1]:.6e} {SIZE[0]:.6e}\n")
    write_kitti_flow(root / "flow_noc_10.png", p["flow"], p["valid"])
    (root / "road.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": POLYGON}))
    return root


@pytest.fixture
def odometry_folder(tmp_path, scene) -> Path:
    """A folder in the layout of shared/data/kitti_odometry_straight: image_l/, calib.txt (P0),
    poses.txt, road.json."""
    from fsof_torch.io import write_image, write_kitti_calibration, write_kitti_poses

    root = tmp_path / "clip"
    (root / "image_l").mkdir(parents=True)
    for i, im in enumerate(_frames(scene)):
        write_image(root / "image_l" / f"{i:06d}.png", im)
    write_kitti_calibration(root / "calib.txt", scene[0]["camera"].K[0], cam=0, style="odometry")
    write_kitti_poses(root / "poses.txt", torch.stack([scene[0]["pose1"], *(p["pose2"] for p in scene)]))
    (root / "road.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": POLYGON}))
    return root


def assert_same_item(a: dict, b: dict) -> None:
    """Two items hold the same keys and equal values: tensors bit for bit, cameras' parameters."""
    assert list(a) == list(b)
    for key in a:
        x, y = a[key], b[key]
        if isinstance(x, torch.Tensor):
            assert x.dtype == y.dtype and torch.equal(x, y), key
        elif isinstance(x, Camera):
            for name in ("K", "height", "roll", "pitch"):
                assert torch.equal(getattr(x, name), getattr(y, name)), (key, name)
        else:
            assert x == y, key


def _loaded(specs) -> list[dict]:
    return [s.load() for s in specs]


def test_synthetic_pairs_are_the_scene_dataset_and_the_rendered_pairs(scene):
    from refine.inputs import synthetic_pairs

    specs = synthetic_pairs("default", 3, seed=0, size=SIZE, road=None)
    dataset = SceneDataset("default", 3, size=SIZE, camera_dtype=torch.float64)
    assert [s.name for s in specs] == ["000000", "000001", "000002"]
    for i, (spec, p) in enumerate(zip(specs, scene)):
        item = spec.load()
        check_item(item)
        assert_same_item(item, dataset[i])
        # the rendered pair itself, under the contract's keys
        for key in ("image1", "image2", "flow", "valid", "road", "flow_velocity", "pose1", "pose2"):
            assert torch.equal(item[key], p[key]), key
        assert item["odometry"] == {k: p["odometry"][k] for k in ("x_d", "z_d", "yaw")}
        assert item["relative_pose"] is None and item["camera"].dtype == torch.float64
        # (the scene's float64 camera: the float32 render's K is rounded to float32)
        torch.testing.assert_close(item["camera"].K, p["camera"].K.double(), rtol=0, atol=1e-4)
        assert spec.identity() == {"index": i}


def test_user_pairs_are_the_image_folder_dataset(user_folder, scene):
    from refine.inputs import user_pairs

    m = _mounting(scene[0]["camera"])
    specs, camera = user_pairs(images=user_folder / "images", calib=user_folder / "calib.txt", cam=None,
                               height=m["height"], roll_deg=m["roll_deg"], pitch_deg=m["pitch_deg"],
                               poses=user_folder / "poses.txt", flows=user_folder / "flows",
                               road=str(user_folder / "road"), gt=user_folder / "gt")
    dataset = ImageFolderDataset(user_folder / "images", user_folder / "calib.txt", camera_height=m["height"],
                                 roll=math.radians(m["roll_deg"]), pitch=math.radians(m["pitch_deg"]),
                                 poses=user_folder / "poses.txt", road=user_folder / "road", gt=user_folder / "gt",
                                 camera_dtype=torch.float64)
    assert [s.name for s in specs] == ["000000", "000001", "000002"]
    assert [s.flow_files["files"].name for s in specs] == ["000000.flo", "000001.npy", "000002.png"]
    for i, (spec, p) in enumerate(zip(specs, scene)):
        item = spec.load()
        check_item(item)
        assert_same_item(item, dataset[i])
        # what was written, read back independently of the readers' code
        assert torch.equal(item["image1"], p["image1"].round()) and torch.equal(item["image2"], p["image2"].round())
        assert torch.equal(item["road"], p["road"]) and torch.equal(item["valid"], p["valid"])
        assert float((item["flow"] - p["flow"]).abs().amax(0)[p["valid"][0]].max()) <= 1 / 128
        torch.testing.assert_close(item["relative_pose"], torch.linalg.inv(p["pose2"]) @ p["pose1"],
                                   rtol=0, atol=1e-9)
        for k in ("x_d", "z_d", "yaw"):
            assert item["odometry"][k] == pytest.approx(p["odometry"][k], abs=1e-6)
        # (each item's own copy: editing one item's camera must not change the others')
        assert item["camera"] is not camera and torch.equal(item["camera"].K, camera.K)
    torch.testing.assert_close(camera.K, scene[0]["camera"].K.double(), rtol=0, atol=1e-4)


def test_user_pairs_of_a_kitti_flow_layout(tmp_path, user_folder, scene):
    """KITTI flow pairs NAME_10 / NAME_11 pair by name and are named NAME, in the job and the dataset."""
    from fsof_torch.io import write_image
    from refine.inputs import user_pairs

    folder = tmp_path / "pairs"
    folder.mkdir()
    for name, p in (("000007", scene[0]), ("000003", scene[2])):
        write_image(folder / f"{name}_10.png", p["image1"])
        write_image(folder / f"{name}_11.png", p["image2"])
    specs, _ = user_pairs(images=folder, calib=user_folder / "calib.txt", cam=0, height=1.65, roll_deg=0.0,
                          pitch_deg=0.0, poses=None, flows=None, road="auto", gt=None)
    dataset = ImageFolderDataset(folder, user_folder / "calib.txt", cam=0, camera_dtype=torch.float64)
    assert [s.name for s in specs] == [p.name for p in dataset.pairs] == ["000003", "000007"]
    for i, spec in enumerate(specs):
        item = spec.load()
        assert_same_item(item, dataset[i])
        assert item["road"] is None and item["flow"] is None and item["odometry"] is None
    assert torch.equal(specs[0].load()["image1"], scene[2]["image1"].round())


def test_kitti15_pairs_are_the_sample_dataset(kitti15_folder, scene):
    from refine.inputs import kitti15_pairs

    specs, camera = kitti15_pairs(kitti15_folder, height=1.65)
    dataset = KittiSampleDataset(kitti15_folder, camera_dtype=torch.float64)
    assert [s.name for s in specs] == ["kitti15_000000"] and len(dataset) == 1
    item = specs[0].load()
    check_item(item)
    assert_same_item(item, dataset[0])
    p = scene[0]
    assert torch.equal(item["image1"], p["image1"].round()) and torch.equal(item["valid"], p["valid"])
    assert float((item["flow"] - p["flow"]).abs().amax(0)[p["valid"][0]].max()) <= 1 / 128
    assert item["odometry"] is None and item["relative_pose"] is None
    from fsof_torch.io import rasterize_polygons

    assert torch.equal(item["road"], rasterize_polygons([POLYGON], SIZE).reshape(1, *SIZE))
    assert float(camera.height[0]) == 1.65 and float(camera.pitch[0]) == 0.0


def test_kitti_odometry_pairs_are_the_odometry_dataset(odometry_folder, scene):
    from refine.inputs import kitti_odometry_pairs

    specs, camera = kitti_odometry_pairs(odometry_folder, height=1.65, pitch_deg=-1.0)
    dataset = KittiOdometryDataset(odometry_folder, pitch=math.radians(-1.0), camera_dtype=torch.float64)
    assert [s.name for s in specs] == ["000000", "000001", "000002"]
    assert float(camera.pitch[0]) == pytest.approx(math.radians(-1.0), abs=1e-15)
    for i, (spec, p) in enumerate(zip(specs, scene)):
        item = spec.load()
        check_item(item)
        assert_same_item(item, dataset[i])
        torch.testing.assert_close(item["relative_pose"], torch.linalg.inv(p["pose2"]) @ p["pose1"],
                                   rtol=0, atol=1e-9)
        assert set(item["pose_residual"]) == {"y_d", "rotation"}


def test_kitti_samples_without_road_json_need_road_auto(kitti15_folder, odometry_folder):
    """Another KITTI pair or clip in the samples' layouts may come without a road polygon: with
    --road auto (``road_auto``) it loads (the road left to the job's detection), otherwise the
    error names the missing file and the way out. Without flow_noc_10.png the pair has no ground
    truth, and it is named after its folder."""
    from refine.inputs import JobError, kitti15_pairs, kitti_odometry_pairs

    for folder in (kitti15_folder, odometry_folder):
        (folder / "road.json").unlink()
    with pytest.raises(JobError, match=r"^--kitti15: '.*' lacks \['road.json'\] \(or pass --road auto\)$"):
        kitti15_pairs(kitti15_folder, height=1.65)
    with pytest.raises(JobError, match=r"^--kitti-odometry: '.*' lacks road.json \(or pass --road auto\)$"):
        kitti_odometry_pairs(odometry_folder, height=1.65, pitch_deg=0.0)
    item = kitti_odometry_pairs(odometry_folder, height=1.65, pitch_deg=0.0, road_auto=True)[0][1].load()
    assert item["road"] is None and item["relative_pose"] is not None
    renamed = kitti15_folder.rename(kitti15_folder.parent / "kitti15_000042")
    (renamed / "flow_noc_10.png").unlink()
    specs, _ = kitti15_pairs(renamed, height=1.65, road_auto=True)
    item = specs[0].load()
    check_item(item)
    assert [s.name for s in specs] == ["kitti15_000042"]
    assert item["road"] is None and item["flow"] is None and item["valid"] is None
    (renamed / "image_11.png").unlink()
    with pytest.raises(JobError, match=r"lacks \['image_11.png'\]$"):  # no hint: road.json is not the problem
        kitti15_pairs(renamed, height=1.65, road_auto=True)



def test_a_folder_named_like_a_samples_file_is_named_not_taken(kitti15_folder, odometry_folder):
    """A folder road.json in an odometry clip's folder passed the check for the file, and the
    dataset, finding no road.json file, gave no road: the job detected it while the report said
    the road came from road.json; a folder poses.txt ended in a traceback (IsADirectoryError)."""
    from refine.inputs import JobError, kitti15_pairs, kitti_odometry_pairs

    for folder, name in ((odometry_folder, "road.json"), (odometry_folder, "poses.txt"),
                         (kitti15_folder, "road.json")):
        path = folder / name
        path.rename(folder / "moved")
        path.mkdir()
        with pytest.raises(JobError, match=rf"^--kitti(15|-odometry): '{re.escape(str(path))}' is a folder; "
                                           rf"expected a file$"):
            (kitti15_pairs(folder, height=1.65) if folder == kitti15_folder
             else kitti_odometry_pairs(folder, height=1.65, pitch_deg=0.0))
        path.rmdir()
        (folder / "moved").rename(path)
    (odometry_folder / "image_l").rename(odometry_folder / "moved")
    (odometry_folder / "image_l").write_bytes(b"")
    with pytest.raises(JobError, match=r"^--kitti-odometry: '.*image_l' is not a folder; expected the folder"):
        kitti_odometry_pairs(odometry_folder, height=1.65, pitch_deg=0.0)


def test_every_item_has_the_contract_keys_in_order(user_folder, kitti15_folder, odometry_folder):
    from refine.inputs import kitti15_pairs, kitti_odometry_pairs, synthetic_pairs, user_pairs

    loaded = [synthetic_pairs("default", 1, seed=0, size=SIZE, road="auto")[0].load(),
              kitti15_pairs(kitti15_folder, height=1.65)[0][0].load(),
              kitti_odometry_pairs(odometry_folder, height=1.65, pitch_deg=0.0)[0][0].load(),
              user_pairs(images=user_folder / "images", calib=user_folder / "calib.txt", cam=None, height=1.65,
                         roll_deg=0.0, pitch_deg=0.0, poses=None, flows=None, road="auto", gt=None)[0][0].load()]
    for item in loaded:
        assert tuple(item)[:len(ITEM_KEYS)] == ITEM_KEYS


def test_a_changed_file_changes_only_its_pairs_identity(user_folder, scene):
    """The resume fingerprint's input: the contents of a pair's own files and its poses."""
    from fsof_torch.io import write_flow, write_image
    from refine.inputs import user_pairs

    def identities():
        specs, _ = user_pairs(images=user_folder / "images", calib=user_folder / "calib.txt", cam=None,
                              height=1.65, roll_deg=0.0, pitch_deg=0.0, poses=user_folder / "poses.txt",
                              flows=user_folder / "flows", road=str(user_folder / "road"), gt=user_folder / "gt")
        return [s.identity() for s in specs]

    first = identities()
    assert set(first[0]["files"]) == {"image1", "image2", "flow", "gt", "road", "calib"}
    assert len(first[0]["poses"]) == 32
    assert identities() == first  # the same files, the same identities
    write_image(user_folder / "images" / "000003.png", scene[2]["image2"].flip(-1))  # pair 000002's second frame
    second = identities()
    assert second[:2] == first[:2] and second[2]["files"]["image2"] != first[2]["files"]["image2"]
    write_flow(user_folder / "flows" / "000000.flo", scene[0]["flow"])  # pair 000000's prediction
    third = identities()
    assert third[1:] == second[1:] and third[0]["files"]["flow"] != second[0]["files"]["flow"]


def test_kitti_samples_identity_follows_their_polygon_and_calibration(kitti15_folder, odometry_folder):
    """The samples keep one road polygon and one calibration for all pairs: a changed road.json or
    calibration file changes every pair's identity (a resumed run redoes them)."""
    from refine.inputs import kitti15_pairs, kitti_odometry_pairs

    def identities():
        return ([s.identity() for s in kitti15_pairs(kitti15_folder, height=1.65)[0]]
                + [s.identity() for s in kitti_odometry_pairs(odometry_folder, height=1.65, pitch_deg=0.0)[0]])

    first = identities()
    assert all({"road", "calib"} <= set(i["files"]) for i in first)
    for folder in (kitti15_folder, odometry_folder):
        (folder / "road.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": POLYGON[:3]}))
    second = identities()
    assert all(a["files"]["road"] != b["files"]["road"] and a["files"]["calib"] == b["files"]["calib"]
               for a, b in zip(first, second))
    for calib in (kitti15_folder / "calib_cam_to_cam.txt", odometry_folder / "calib.txt"):
        calib.write_text(calib.read_text() + "\n")
    third = identities()
    assert all(a["files"]["calib"] != b["files"]["calib"] for a, b in zip(second, third))


def test_kitti15_pair_of_the_working_folder_is_named_after_it(kitti15_folder, monkeypatch):
    """``--kitti15 .`` names the pair after the folder itself, not after the empty name of ``.``."""
    from refine.inputs import kitti15_pairs

    monkeypatch.chdir(kitti15_folder)
    specs, _ = kitti15_pairs(Path("."), height=1.65)
    assert [s.name for s in specs] == ["kitti15_000000"]
    assert KittiSampleDataset(Path(".")).pairs[0].name == "kitti15_000000"


def test_dataset_errors_name_the_option(user_folder, tmp_path):
    """The datasets' errors name their argument; the job's name the option that gave it."""
    from refine.inputs import JobError, user_pairs

    args = dict(images=user_folder / "images", calib=user_folder / "calib.txt", cam=None, height=1.65,
                roll_deg=0.0, pitch_deg=0.0, poses=None, flows=None, road="auto", gt=None)
    (user_folder / "gt" / "000001.png").unlink()
    with pytest.raises(ValueError, match=r"^gt: no file for pair 000001 in "):
        ImageFolderDataset(user_folder / "images", user_folder / "calib.txt", gt=user_folder / "gt")
    with pytest.raises(JobError, match=r"^--gt: no file for pair 000001 in "):
        user_pairs(**{**args, "gt": user_folder / "gt"})
    with pytest.raises(JobError, match=r"^--cam: expected 0..3, got 7"):
        user_pairs(**{**args, "cam": 7})
    with pytest.raises(JobError, match=r"^--calib-size: .*positive"):
        user_pairs(**{**args, "calib_size": (0, 160)})
    with pytest.raises(JobError, match=r"--calib-size HxW"):  # the hint names the option, not the argument
        user_pairs(**{**args, "images": _resized(user_folder, tmp_path, 2.0)})


def test_a_calib_size_that_is_not_the_files_own_exits_2(tmp_path, user_folder, scene, capsys):
    """--calib-size that contradicts the calibration file's S_rect row was taken over it: the
    projection of a 96x320 camera refined 48x160 images, without a word (the principal point check
    is skipped where a size is stated). Now exit 2 naming --calib-size and both sizes."""
    from fsof_torch.io import write_kitti_calibration
    from refine.__main__ import main

    cam2cam = tmp_path / "calib_cam_to_cam.txt"
    write_kitti_calibration(cam2cam, scene[0]["camera"].K[0] * torch.tensor([[2.0], [2.0], [1.0]]), cam=2)
    cam2cam.write_text(cam2cam.read_text() + f"S_rect_02: {2 * SIZE[1]} {2 * SIZE[0]}\n")
    out = tmp_path / "out"
    assert main(["--images", str(user_folder / "images"), "--calib", str(cam2cam), "--calib-size",
                 f"{SIZE[0]}x{SIZE[1]}", "--road", "auto", "--out", str(out), "--no-progress", "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --calib-size: {SIZE[0]}x{SIZE[1]} is not the size {str(cam2cam)!r} states for "
                          f"camera 2 (S_rect_02: {2 * SIZE[0]}x{2 * SIZE[1]}); leave it out"), err
    assert not out.exists()


def _resized(user_folder: Path, tmp_path: Path, factor: float) -> Path:
    import torch.nn.functional as F

    from fsof_torch.io import read_image, write_image

    out = tmp_path / f"resized{factor:g}"
    out.mkdir()
    for p in sorted((user_folder / "images").iterdir()):
        write_image(out / p.name, F.interpolate(read_image(p)[None], scale_factor=factor, mode="bilinear")[0])
    return out


def test_the_sequence_variant_refuses_pairs_that_are_not_one_clip(tmp_path, user_folder, scene, capsys):
    """Two KITTI flow pairs loaded through the dataset are separate pairs: the clip's fit finds
    that the second image of one is not the first of the next, and the job exits 2."""
    from fsof_torch.io import write_image
    from refine.__main__ import main

    folder = tmp_path / "pairs"
    folder.mkdir()
    for name, p in (("000000", scene[0]), ("000001", scene[2])):
        write_image(folder / f"{name}_10.png", p["image1"])
        write_image(folder / f"{name}_11.png", p["image2"])
    rc = main(["--images", str(folder), "--calib", str(user_folder / "calib.txt"), "--road", "auto",
               "--odometry", "sequence", "--source", "dis", "--no-figures", "--no-progress",
               "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "sequence: pairs 000000 and 000001 are not consecutive frames" in err


def test_poses_errors_name_the_option_and_not_the_readers_argument(user_folder, tmp_path):
    """A poses file with more lines than images stops the job under --poses; a reader's own
    argument (``path``) inside the dataset's error is dropped when the job renames it."""
    from fsof_torch.io import read_kitti_poses, write_kitti_poses
    from refine.inputs import JobError, options_of, user_pairs

    args = dict(images=user_folder / "images", calib=user_folder / "calib.txt", cam=None, height=1.65,
                roll_deg=0.0, pitch_deg=0.0, flows=None, road="auto", gt=None)
    P = read_kitti_poses(user_folder / "poses.txt")
    write_kitti_poses(tmp_path / "kitti.txt", torch.cat([P[:1], P]))  # line n for frame n, one frame before
    with pytest.raises(JobError, match=r"^--poses: '.*kitti\.txt' has 5 poses for 4 images: one line per image"):
        user_pairs(**args, poses=tmp_path / "kitti.txt")
    rows = (user_folder / "poses.txt").read_text().splitlines()
    rows[1] = "1 2 3"
    (tmp_path / "bad.txt").write_text("\n".join(rows) + "\n")
    with pytest.raises(JobError, match=r"^--poses: line 2 of '.*bad\.txt' has 3 numbers") as err:
        user_pairs(**args, poses=tmp_path / "bad.txt")
    assert "path" not in str(err.value)
    with pytest.raises(JobError, match=r"^--kitti-odometry: poses: line 2 of 'x'$"):
        with options_of("--kitti-odometry"):
            raise ValueError("poses: path: line 2 of 'x'")


def test_the_clip_refuses_a_gap_in_the_frame_numbers_before_any_work(tmp_path, user_folder, capsys):
    """Frames 0, 1, 3, 4 (frame 2 dropped): the clip's fit would carry the motion across the gap
    as a prior and fit that pair as one step, so the variants that fit the clip stop, naming the
    pair and the option, before any work."""
    from refine.calibrate import check_clip
    from refine.inputs import JobError, user_pairs
    from refine.__main__ import main

    images = user_folder / "images"
    for i in (3, 2):  # 000002 -> 000003, 000003 -> 000004
        (images / f"{i:06d}.png").rename(images / f"{i + 1:06d}.png")
    args = dict(images=images, calib=user_folder / "calib.txt", cam=None, height=1.65, roll_deg=0.0,
                pitch_deg=0.0, poses=user_folder / "poses.txt", flows=None, road="auto", gt=None)
    specs, _ = user_pairs(**args)
    assert [s.frames for s in specs] == [("000000", "000001"), ("000001", "000003"), ("000003", "000004")]
    with pytest.raises(JobError, match=r"^--odometry sequence: pair 000001 goes from frame 000001 to frame "
                                       r"000003, not to the next frame \(a gap in the frame numbers"):
        check_clip(specs)
    base = ["--images", str(images), "--calib", str(user_folder / "calib.txt"), "--road", "auto",
            "--poses", str(user_folder / "poses.txt"), "--no-figures", "--no-progress"]
    for extra, option in ((["--odometry", "given,given_pitch"], "--odometry given_pitch"),
                          (["--odometry", "given", "--calibrate-pitch"], "--calibrate-pitch"),
                          ([], "--odometry sequence")):
        out = tmp_path / f"out{len(extra)}"
        assert main([*base, *extra, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {option}: pair 000001 goes from frame 000001 to frame 000003"), err
        assert f"without {option} the pairs are refined one by one" in err
        assert not (out / "run.json").exists()


def test_the_clip_of_frames_named_around_a_number_is_in_number_order_and_refuses_a_gap(user_folder):
    """Frames frame_0, frame_1, ... (no padding): the clip is in the order of the numbers, not of
    the names (frame_1 -> frame_10), and a dropped frame stops the clip's fit as it does for frames
    named by a number alone."""
    from refine.calibrate import check_clip
    from refine.inputs import JobError, user_pairs

    images = user_folder / "images"
    frames = sorted(images.iterdir())
    for i, f in enumerate(frames):
        f.rename(images / f"frame_{i * 5}.png")  # frame_0, frame_5, frame_10, frame_15
    args = dict(images=images, calib=user_folder / "calib.txt", cam=None, height=1.65, roll_deg=0.0,
                pitch_deg=0.0, poses=None, flows=None, road="auto", gt=None)
    specs, _ = user_pairs(**args)
    assert [s.frames for s in specs] == [("frame_0", "frame_5"), ("frame_5", "frame_10"), ("frame_10", "frame_15")]
    with pytest.raises(JobError, match=r"^--odometry sequence: pair frame_0 goes from frame frame_0 to frame "
                                       r"frame_5, not to the next frame"):
        check_clip(specs)
    for i in range(len(frames)):
        (images / f"frame_{i * 5}.png").rename(images / f"frame_{i + 8}.png")  # frame_8 ... frame_11
    specs, _ = user_pairs(**args)
    assert [s.frames for s in specs] == [("frame_8", "frame_9"), ("frame_9", "frame_10"), ("frame_10", "frame_11")]
    check_clip(specs)


def test_frames_named_by_timestamps_are_one_clip_and_their_poses_steps_are_one_frame(tmp_path, user_folder):
    """Frames named by the time they were taken (ns, as ROS exports them; µs after a text, as
    nuScenes' CAM_FRONT__1532402927612460.jpg): their numbers were taken for frame numbers, so
    the clip's fit (the default variant sequence) refused every such clip as "a gap in the frame
    numbers", and a pose step was allowed 100 m per nanosecond between them (poses in
    millimetres passed the check). A timestamp (from 1e9 up) now counts one frame a step."""
    from fsof_torch.io import read_kitti_poses, write_kitti_poses
    from fsof_torch.io.images import frame_counts
    from refine.calibrate import check_clip
    from refine.inputs import JobError, user_pairs

    assert frame_counts(["000000", "000001", "000003"]) == [0, 1, 3]
    assert frame_counts(["cam_999999999", "cam_1000000000"]) is None
    images = user_folder / "images"
    for n, f in enumerate(sorted(images.iterdir())):
        f.rename(images / f"{1541234567150000000 + n * 100_000_000}.png")
    args = dict(images=images, calib=user_folder / "calib.txt", cam=None, height=1.65, roll_deg=0.0,
                pitch_deg=0.0, poses=user_folder / "poses.txt", flows=None, road="auto", gt=None)
    specs, _ = user_pairs(**args)
    assert [s.frames[1] for s in specs] == ["1541234567250000000", "1541234567350000000", "1541234567450000000"]
    check_clip(specs)  # (was: pair 1541234567150000000 goes from frame ... not to the next frame)
    for n, f in enumerate(sorted(images.iterdir())):
        f.rename(images / f"n015-2018-07-24-11-22-45+0800__CAM_FRONT__{1532402927612460 + n * 100_000}.png")
    check_clip(user_pairs(**args)[0])
    poses = read_kitti_poses(user_folder / "poses.txt")
    poses[:, :3, 3] *= 1000  # millimetres
    write_kitti_poses(tmp_path / "poses_mm.txt", poses)
    with pytest.raises(JobError, match=r"^--poses: the pose of .*__1532402927612460\.png and the pose of "
                                       r".*__1532402927712460\.png lie \d+ m apart, farther than a road vehicle "
                                       r"travels between them \(100 m: .* in millimetres"):
        user_pairs(**{**args, "poses": tmp_path / "poses_mm.txt"})


def test_an_error_in_the_clips_fit_names_its_option_and_leaves_the_folder_for_the_corrected_run(
        tmp_path, user_folder, scene, capsys):
    """KITTI flow pairs with --calibrate-pitch: the clip's fit finds they are not one clip and names
    --calibrate-pitch (the run is already photometric); the corrected run into the same folder is
    not refused as another run's, since the failed one left no record."""
    from fsof_torch.io import write_image
    from refine.__main__ import main

    folder = tmp_path / "pairs"
    folder.mkdir()
    for name, p in (("000000", scene[0]), ("000001", scene[2])):
        write_image(folder / f"{name}_10.png", p["image1"])
        write_image(folder / f"{name}_11.png", p["image2"])
    out = tmp_path / "out"
    base = ["--images", str(folder), "--calib", str(user_folder / "calib.txt"), "--road", "auto",
            "--source", "dis", "--no-figures", "--no-progress", "--out", str(out)]
    assert main([*base, "--calibrate-pitch"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --calibrate-pitch: pairs 000000 and 000001 are not consecutive frames"), err
    assert "use --odometry photometric" not in err and "without --calibrate-pitch" in err
    assert main(base) == 0, capsys.readouterr().err
    assert json.loads((out / "report.json").read_text())["rows"][0]["pairs"] == 2


def test_a_kitti_odometry_clip_whose_poses_do_not_move_stops_under_its_option(tmp_path, odometry_folder, capsys):
    """The odometry clip's poses give the clip's fit its scale: poses that stand still stop the job
    under --kitti-odometry (where they come from) before any work."""
    from fsof_torch.io import read_kitti_poses, write_kitti_poses
    from refine.__main__ import main

    P = read_kitti_poses(odometry_folder / "poses.txt")
    write_kitti_poses(odometry_folder / "poses.txt", P[[0] * len(P)])
    out = tmp_path / "out"
    assert main(["--kitti-odometry", str(odometry_folder), "--source", "dis", "--no-figures", "--no-progress",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --kitti-odometry: the poses do not move"), err
    assert "(--odometry sequence)" in err and not (out / "run.json").exists()


def test_kitti_flow_pairs_with_a_missing_partner_stop_under_images(tmp_path, user_folder, scene, capsys):
    """KITTI flow pairs pair by name: a folder where one pair lacks its _11 is refused under
    --images, naming the image, not read as one clip (000000_11 -> 000001_10, across scenes)."""
    from fsof_torch.io import write_image
    from refine.__main__ import main

    folder = tmp_path / "pairs"
    folder.mkdir()
    write_image(folder / "000000_10.png", scene[0]["image1"])
    write_image(folder / "000000_11.png", scene[0]["image2"])
    write_image(folder / "000001_10.png", scene[2]["image1"])
    out = tmp_path / "out"
    assert main(["--images", str(folder), "--calib", str(user_folder / "calib.txt"), "--road", "auto",
                 "--no-figures", "--no-progress", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --images: {str(folder)!r} holds KITTI flow pairs (NAME_10 / NAME_11, paired "
                          f"by name), but 1 image(s) have no partner: 000001_10.png; "), err
    assert not out.exists()


def test_images_too_small_for_the_job_stop_under_their_option(tmp_path, user_folder):
    """Images of 6x8 pixels (DIS needs 12, --size asks 16): refused before any work, naming the
    option, the file and its size, for a folder and for the KITTI samples' layouts."""
    from fsof_torch.io import write_image, write_kitti_calibration
    from refine.inputs import JobError, kitti15_pairs, kitti_odometry_pairs, user_pairs

    K = torch.tensor([[8.0, 0.0, 3.5], [0.0, 8.0, 2.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    images = tmp_path / "tiny"
    images.mkdir()
    for i in range(3):
        write_image(images / f"{i:06d}.png", torch.full((3, 6, 8), 40.0 * i))
    write_kitti_calibration(tmp_path / "calib.txt", K, cam=0, style="odometry")
    with pytest.raises(JobError, match=r"^--images: '.*000000\.png' is 6x8; the job needs images with sides of "
                                       r"at least 16 pixels$"):
        user_pairs(images=images, calib=tmp_path / "calib.txt", cam=None, height=1.65, roll_deg=0.0,
                   pitch_deg=0.0, poses=None, flows=None, road="auto", gt=None)
    k15 = tmp_path / "k15"
    k15.mkdir()
    for t in ("10", "11"):
        write_image(k15 / f"image_{t}.png", torch.zeros(3, 15, 40))
    write_kitti_calibration(k15 / "calib_cam_to_cam.txt", K * torch.tensor([[5.0], [3.0], [1.0]], dtype=K.dtype),
                            cam=2)
    with pytest.raises(JobError, match=r"^--kitti15: '.*image_10\.png' is 15x40; "):
        kitti15_pairs(k15, height=1.65, road_auto=True)
    odo = tmp_path / "odo"
    (odo / "image_l").mkdir(parents=True)
    for p in images.iterdir():
        (odo / "image_l" / p.name).write_bytes(p.read_bytes())
    (odo / "calib.txt").write_bytes((tmp_path / "calib.txt").read_bytes())
    (odo / "poses.txt").write_bytes((user_folder / "poses.txt").read_bytes())
    with pytest.raises(JobError, match=r"^--kitti-odometry: '.*000000\.png' is 6x8; "):
        kitti_odometry_pairs(odo, height=1.65, pitch_deg=0.0, road_auto=True)
    # 16 pixels pass with a given road (--road auto needs 32: its first estimate works at half size)
    for i in range(3):
        write_image(images / f"{i:06d}.png", torch.full((3, 16, 16), 40.0 * i))
    write_kitti_calibration(tmp_path / "calib.txt", torch.tensor([[8.0, 0, 7.5], [0, 8.0, 7.5], [0, 0, 1]],
                                                                 dtype=torch.float64), cam=0, style="odometry")
    (tmp_path / "road.json").write_text('{"size": [16, 16], "road_polygon": [[0, 15], [15, 15], [8, 9]]}')
    specs, _ = user_pairs(images=images, calib=tmp_path / "calib.txt", cam=None, height=1.65, roll_deg=0.0,
                          pitch_deg=0.0, poses=None, flows=None, road=str(tmp_path / "road.json"), gt=None)
    assert tuple(specs[0].load()["image1"].shape) == (3, 16, 16)
    with pytest.raises(JobError, match=r"^--road: auto finds the road on images with sides of at least 32 pixels"):
        user_pairs(images=images, calib=tmp_path / "calib.txt", cam=None, height=1.65, roll_deg=0.0,
                   pitch_deg=0.0, poses=None, flows=None, road="auto", gt=None)


def test_with_road_auto_the_samples_road_json_is_not_read(kitti15_folder, odometry_folder):
    """--road auto: a broken road.json in a KITTI sample's folder is not read (the road is found in
    the images), nor part of the pairs' identity; without it, the broken file stops the job."""
    from refine.inputs import JobError, kitti15_pairs, kitti_odometry_pairs

    for folder in (kitti15_folder, odometry_folder):
        (folder / "road.json").write_text("{bad")
    with pytest.raises(JobError, match=r"^--kitti15: road: '.*road\.json' is not valid JSON"):
        kitti15_pairs(kitti15_folder, height=1.65)
    with pytest.raises(JobError, match=r"^--kitti-odometry: road: '.*road\.json' is not valid JSON"):
        kitti_odometry_pairs(odometry_folder, height=1.65, pitch_deg=0.0)
    for specs in (kitti15_pairs(kitti15_folder, height=1.65, road_auto=True)[0],
                  kitti_odometry_pairs(odometry_folder, height=1.65, pitch_deg=0.0, road_auto=True)[0]):
        item = specs[0].load()
        assert item["road"] is None and item["image1"].shape[-2:] == SIZE
        assert "road" not in specs[0].identity()["files"] and "calib" in specs[0].identity()["files"]
    # the datasets' own switch, checked as a flag
    assert KittiSampleDataset(kitti15_folder, road_json=False)[0]["road"] is None
    assert KittiOdometryDataset(odometry_folder, road_json=False)[1]["road"] is None
    with pytest.raises(TypeError, match=r"^road_json: expected True or False, got str 'no'"):
        KittiOdometryDataset(odometry_folder, road_json="no")


def test_a_given_road_without_a_road_pixel_stops_under_road(user_folder, tmp_path):
    """A polygon wholly outside the images, one all-zero mask for every pair or a folder of them:
    every pair would go unrefined, so the job stops before any work naming --road. A folder where
    only some masks are empty is taken (the report names those pairs); --road auto flags its own."""
    from fsof_torch.io import write_road_mask
    from refine.inputs import JobError, user_pairs

    args = dict(images=user_folder / "images", calib=user_folder / "calib.txt", cam=None, height=1.65,
                roll_deg=0.0, pitch_deg=0.0, poses=None, flows=None, gt=None)
    (tmp_path / "out.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": [[500, 500], [600, 500],
                                                                                       [600, 600]]}))
    with pytest.raises(JobError, match=r"^--road: '.*out\.json' holds no road pixel inside the 48x160 images, "
                                       r"so no pair could be refined; .* or --road auto$"):
        user_pairs(**args, road=str(tmp_path / "out.json"))
    zero = torch.zeros(1, *SIZE, dtype=torch.bool)
    write_road_mask(tmp_path / "zero.png", zero)
    with pytest.raises(JobError, match=r"^--road: '.*zero\.png' holds no road pixel inside the 48x160 images,"):
        user_pairs(**args, road=str(tmp_path / "zero.png"))
    masks = sorted((user_folder / "road").iterdir())
    write_road_mask(masks[1], zero)
    assert len(user_pairs(**args, road=str(user_folder / "road"))[0]) == 3  # one empty mask of three: taken
    for m in masks:
        write_road_mask(m, zero)
    with pytest.raises(JobError, match=r"^--road: '.*road' holds no road pixel inside the 48x160 images \(the "
                                       r"masks of all 3 pairs are empty\), so no pair could be refined"):
        user_pairs(**args, road=str(user_folder / "road"))
    assert len(user_pairs(**args, road="auto")[0]) == 3


def test_a_polygon_drawn_for_another_size_stops_under_road(user_folder, tmp_path):
    """A polygon JSON whose 'size' is not the images' was stretched over them (a wrong road given
    silently): the job stops before any work naming --road, the file and both sizes."""
    from refine.inputs import JobError, user_pairs

    args = dict(images=user_folder / "images", calib=user_folder / "calib.txt", cam=None, height=1.65,
                roll_deg=0.0, pitch_deg=0.0, poses=None, flows=None, gt=None)
    polygon = [[0, 47], [40, 36], [120, 36], [159, 47]]
    (tmp_path / "other.json").write_text(json.dumps({"size": [2 * SIZE[0], 2 * SIZE[1]], "road_polygon": polygon}))
    with pytest.raises(JobError, match=r"^--road: '.*other\.json' is a polygon drawn for 96x320 images \(its "
                                       r"'size'\), but size is 48x160; "):
        user_pairs(**args, road=str(tmp_path / "other.json"))
    (tmp_path / "own.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": polygon}))
    assert len(user_pairs(**args, road=str(tmp_path / "own.json"))[0]) == 3
