"""Smoke tests of ``python -m refine`` in-process (``refine.__main__.main``) on tiny inputs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from refine.__main__ import main

SIZE = (48, 160)
TINY = ["--size", f"{SIZE[0]}x{SIZE[1]}", "--no-progress", "--threads", "1"]


@pytest.fixture(scope="module")
def scene_pairs():
    from fsof_torch.data.scene import render_pair

    return [render_pair("default", i, size=SIZE) for i in range(2)]


@pytest.fixture
def user_folder(tmp_path, scene_pairs) -> Path:
    """Three frames of the synthetic scene in a user layout: images, calib, poses, road PNGs,
    ground truth and predicted flows (ground truth + noise) in three file formats."""
    from fsof_torch.io import (write_flow, write_image, write_kitti_calibration, write_kitti_poses,
                               write_road_mask)

    root = tmp_path / "data"
    for d in ("images", "road", "gt", "flows"):
        (root / d).mkdir(parents=True)
    p0, p1 = scene_pairs
    for i, im in enumerate([p0["image1"], p0["image2"], p1["image2"]]):
        write_image(root / "images" / f"{i:06d}.png", im)
    write_kitti_calibration(root / "calib.txt", p0["camera"].K[0], cam=0, style="odometry")
    write_kitti_poses(root / "poses.txt", torch.stack([p0["pose1"], p0["pose2"], p1["pose2"]]))
    g = torch.Generator().manual_seed(0)
    for i, (p, ext) in enumerate([(p0, ".flo"), (p1, ".npy")]):
        write_road_mask(root / "road" / f"{i:06d}.png", p["road"])
        write_flow(root / "gt" / f"{i:06d}.png", p["flow"], p["valid"])
        noisy = p["flow"] + 1.5 * torch.randn(p["flow"].shape, generator=g)
        write_flow(root / "flows" / f"{i:06d}{ext}", noisy)
    return root


def _mounting(scene_pairs) -> list[str]:
    cam = scene_pairs[0]["camera"]
    return ["--roll-deg", str(math.degrees(float(cam.roll[0]))),
            "--pitch-deg", str(math.degrees(float(cam.pitch[0]))), "--height", str(float(cam.height[0]))]


def _rows(report: Path) -> dict[tuple[str, str], dict]:
    summary = json.loads(report.read_text())
    return {(r["source"], r["variant"]): r for r in summary["rows"]}


# -- smoke ----------------------------------------------------------------------------------------

def test_help_exits_zero(capsys):
    assert main(["--help"]) == 0
    assert "--kitti15" in capsys.readouterr().out


def test_synthetic_default_pipeline(tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["--num-pairs", "2", "--source", "dis", "--out", str(out), "--json", str(tmp_path / "r.json"), *TINY])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "EPE road before" in printed and "photo road before" in printed
    rows = _rows(out / "report.json")
    assert set(rows) == {("dis", "given"), ("dis", "fit"), ("dis", "photometric")}
    given = rows[("dis", "given")]
    assert given["pairs"] == 2 and given["refined"] == 2
    # the scene's odometry and road mask are exact: the refined road flow is the truth
    assert given["epe_road_after"] < 0.05 < given["epe_road_before"]
    assert "photo road noc before" in printed
    rec = json.loads((out / "dis" / "given" / "pairs" / "000000.json").read_text())
    assert 0 < rec["after"]["photo_road_noc_n"] <= rec["after"]["photo_road_n"]
    assert (tmp_path / "r.json").is_file() and (out / "report.md").is_file()
    from fsof_torch.io import read_kitti_flow

    flow, valid = read_kitti_flow(out / "dis" / "given" / "flow" / "000001.png")
    assert flow.shape == (2, *SIZE) and bool(valid.all())
    for f in ("before/000000_flow.png", "before/000000_error.png", "before/000000_road.png",
              "given/figures/000000_flow.png", "given/figures/000000_error.png"):
        assert (out / "dis" / f).is_file(), f
    assert not list(out.rglob("*.tmp*"))  # atomic writes leave no temporary files


def test_resume_skips_finished_pairs(tmp_path):
    out = tmp_path / "out"
    args = ["--num-pairs", "2", "--source", "dis", "--odometry", "given", "--no-figures", "--out", str(out), *TINY]
    assert main(args) == 0
    rec0 = out / "dis" / "given" / "pairs" / "000000.json"
    rec1 = out / "dis" / "given" / "pairs" / "000001.json"
    stamp0 = rec0.stat().st_mtime_ns
    text1 = rec1.read_text()
    rec1.unlink()  # as if the run had stopped before the second pair finished
    assert main(args) == 0
    assert rec0.stat().st_mtime_ns == stamp0  # finished pair not redone
    assert rec1.is_file() and json.loads(rec1.read_text()) == json.loads(text1)
    assert _rows(out / "report.json")[("dis", "given")]["pairs"] == 2
    assert main([*args, "--overwrite"]) == 0
    assert rec0.stat().st_mtime_ns != stamp0


def test_testnet_source_confidence_mode(tmp_path):
    out = tmp_path / "out"
    rc = main(["--num-pairs", "1", "--source", "testnet", "--odometry", "given", "--mode", "confidence",
               "--no-figures", "--out", str(out), *TINY])
    assert rc == 0
    summary = json.loads((out / "report.json").read_text())
    assert summary["mode"] == "confidence" and any("random weights" in n for n in summary["notes"])


def test_synthetic_road_auto(tmp_path):
    out = tmp_path / "out"
    rc = main(["--num-pairs", "1", "--source", "dis", "--odometry", "fit", "--road", "auto", "--no-figures",
               "--out", str(out), *TINY])
    assert rc == 0
    rec = json.loads((out / "dis" / "fit" / "pairs" / "000000.json").read_text())
    assert rec["road"] == "auto"
    if not rec["refined"]:  # nothing detected on so small a DIS flow: the prediction is kept
        assert rec["after"]["epe_all"] == rec["before"]["epe_all"]


def test_user_data_flow_files_poses_and_gt(tmp_path, user_folder, scene_pairs):
    out = tmp_path / "out"
    rc = main(["--images", str(user_folder / "images"), "--calib", str(user_folder / "calib.txt"),
               "--poses", str(user_folder / "poses.txt"), "--flows", str(user_folder / "flows"),
               "--road", str(user_folder / "road"), "--gt", str(user_folder / "gt"),
               "--odometry", "given,fit", "--out", str(out), "--no-progress", "--no-figures",
               *_mounting(scene_pairs)])
    assert rc == 0
    rows = _rows(out / "report.json")
    given, fit = rows[("files", "given")], rows[("files", "fit")]
    assert given["pairs"] == 2
    # poses -> odometry through the calibration file: the model matches the rendered road
    assert given["epe_road_after"] < 0.1 < 1.0 < given["epe_road_before"]
    assert fit["epe_road_after"] < 0.5 * fit["epe_road_before"]
    rec = json.loads((out / "files" / "given" / "pairs" / "000000.json").read_text())
    for k in ("x_d", "z_d", "yaw"):
        assert rec["odometry"][k] == pytest.approx(scene_pairs[0]["odometry"][k], abs=1e-6)


def test_user_data_polygon_json_road(tmp_path, user_folder, scene_pairs):
    poly = {"size": list(SIZE), "road_polygon": [[0, 47], [40, 36], [120, 36], [159, 47]]}
    (user_folder / "road.json").write_text(json.dumps(poly))
    out = tmp_path / "out"
    rc = main(["--images", str(user_folder / "images"), "--calib", str(user_folder / "calib.txt"),
               "--road", str(user_folder / "road.json"), "--source", "dis", "--out", str(out),
               "--no-progress", "--no-figures", *_mounting(scene_pairs)])
    assert rc == 0
    assert _rows(out / "report.json")[("dis", "fit")]["pairs"] == 2


# -- errors ---------------------------------------------------------------------------------------

def _err(capsys, argv) -> str:
    assert main(argv) == 2
    return capsys.readouterr().err


def test_missing_and_mismatched_inputs(tmp_path, user_folder, capsys):
    base = ["--images", str(user_folder / "images"), "--out", str(tmp_path / "o"), "--no-progress"]
    assert "--calib: user data needs" in _err(capsys, [*base, "--road", "auto"])
    calib = ["--calib", str(user_folder / "calib.txt")]
    assert "--road: user data needs road masks" in _err(capsys, [*base, *calib])
    assert "--images: no folder" in _err(capsys, ["--images", str(tmp_path / "nope"), *calib, "--road", "auto"])
    assert "--calib: no calibration file" in _err(capsys, [*base, "--calib", str(tmp_path / "x.txt"), "--road", "auto"])
    (user_folder / "flows" / "000001.npy").unlink()
    err = _err(capsys, [*base, *calib, "--road", "auto", "--flows", str(user_folder / "flows")])
    assert "--flows:" in err and "1 file(s)" in err
    short = tmp_path / "short.txt"
    short.write_text((user_folder / "poses.txt").read_text().splitlines()[0] + "\n")
    assert "--poses:" in _err(capsys, [*base, *calib, "--road", "auto", "--poses", str(short)])
    assert "user data needs --poses" in _err(capsys, [*base, *calib, "--road", "auto", "--odometry", "given"])
    assert "--flows needs --images" in _err(capsys, ["--flows", str(user_folder / "flows"), "--out", str(tmp_path / "o")])
    assert "unknown preset" in _err(capsys, ["--preset", "nope", "--out", str(tmp_path / "o")])
    assert main(["--mode", "blend"]) == 2  # argparse's own error


def test_mismatched_image_sizes(tmp_path, user_folder, capsys):
    from fsof_torch.io import write_image

    write_image(user_folder / "images" / "000002.png", torch.zeros(3, 40, 100))
    err = _err(capsys, ["--images", str(user_folder / "images"), "--calib", str(user_folder / "calib.txt"),
                        "--road", str(user_folder / "road"), "--out", str(tmp_path / "o"), "--no-progress"])
    assert "is (48, 160) but 000002.png is (40, 100)" in err


# -- the shared real data -------------------------------------------------------------------------

@pytest.mark.slow
def test_kitti15_dis_refined_with_photometric_odometry(shared_data, tmp_path):
    """DIS refined with ego-motion estimated from the images: road EPE vs ground truth <= 1 px."""
    root = shared_data / "kitti15_000000"
    if not root.is_dir():
        pytest.skip("kitti15_000000 absent")
    out = tmp_path / "out"
    rc = main(["--kitti15", str(root), "--odometry", "photometric", "--out", str(out), "--no-progress",
               "--no-figures"])
    assert rc == 0
    row = _rows(out / "report.json")[("dis", "photometric")]
    assert row["epe_road_before"] > 5.0
    assert row["epe_road_after"] <= 1.0


def test_scene_noise_option(tmp_path, capsys):
    """--scene-noise renders noisy images: the refined road flow (exact, with the scene's
    odometry) then has a higher photometric floor than on the noise-free sequence."""
    floors = []
    for noise in ("0", "3.8"):
        rc = main(["--num-pairs", "1", "--source", "dis", "--odometry", "given", "--scene-noise", noise,
                   "--no-figures", "--out", str(tmp_path / noise), "--json", str(tmp_path / f"{noise}.json"), *TINY])
        assert rc == 0
        (row,) = json.loads((tmp_path / f"{noise}.json").read_text())["rows"]
        assert row["epe_road_after"] < 1e-3
        floors.append(row["photo_road_after"])
    assert floors[1] > floors[0]  # (at 48x160 the noise is area-scaled to about 0.5 grey levels)
    assert "--scene-noise: expected >= 0" in _err(capsys, ["--scene-noise", "-1", "--out", str(tmp_path / "o")])


def test_evaluate_noc_leaves_out_occluded_pixels():
    """With ground truth, the 'noc' photometric error covers only its valid pixels: a pixel
    occluded in image 2 (invalid ground truth) whose brightness no flow can match is left out."""
    from refine.job import evaluate

    H, W = 6, 8
    image1 = torch.full((3, H, W), 100.0)
    image2 = image1.clone()
    image2[:, 2, 3] = 160.0  # an occluder in image 2 at one road pixel
    valid = torch.ones(1, H, W, dtype=torch.bool)
    valid[0, 2, 3] = False
    zero = torch.zeros(2, H, W)
    pair = {"image1": image1, "image2": image2, "gt": (zero, valid)}
    road = torch.zeros(1, H, W, dtype=torch.bool)
    road[0, 1:4, 1:6] = True
    before, after = evaluate(pair, zero, zero.clone(), road)
    for m in (before, after):
        assert m["photo_road_n"] == 15 and m["photo_road_noc_n"] == 14
        assert m["photo_road"] == pytest.approx(60.0 / 15)
        assert m["photo_road_noc"] == 0.0
        assert m["photo_all_noc_n"] == H * W - 1 and m["photo_all_noc"] == 0.0
    # without ground truth there is nothing to tell occlusion by
    before, _ = evaluate({"image1": image1, "image2": image2}, zero, zero, road)
    assert "photo_road_noc" not in before
