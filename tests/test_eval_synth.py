"""``python -m eval synth``: render a tiny sequence to tmp_path in-process and read it back."""

from __future__ import annotations

import json
import math

import pytest
import torch

from eval.__main__ import main
from fsof_torch.data.datasets import SyntheticFlowDataset, collate
from fsof_torch.geometry.egomotion import ego_motion_from_pose
from fsof_torch.io import read_kitti_poses, read_synthetic_pair

import fsof_torch.data.scene as scene


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "seq"
    report = out.parent / "report.json"
    rc = main(["synth", "--preset", "default", "--pairs", "2", "--out", str(out), "--size", "48", "160",
               "--seed", "3", "--json", str(report), "--no-progress"])
    return rc, out, report


def test_writes_the_layout(written, capsys, check_environment):
    rc, out, report = written
    assert rc == 0
    for rel in ("image_2/000000_10.png", "image_2/000001_11.png", "flow_occ/000001_10.png", "road/000000_10.png",
                "semantic/000000_10.png", "calib/000001.txt", "params/000001.json", "poses.txt", "meta.json"):
        assert (out / rel).is_file(), rel
    meta = json.loads((out / "meta.json").read_text())
    assert meta["preset"] == "default" and meta["seed"] == 3 and meta["num_pairs"] == 2 and meta["size"] == [48, 160]
    check_environment(meta["environment"], job="eval", command="python -m eval synth", seed=3)
    summary = json.loads(report.read_text())
    assert summary["environment"] == meta["environment"]
    assert "environment" not in json.loads((out / "params" / "000000.json").read_text())
    assert summary["num_pairs"] == 2 and len(summary["pairs"]) == 2 and summary["bytes"] > 0
    assert set(summary["pairs"][0]["road_pose"]) == {"pitch", "roll", "height"}
    for row in summary["pairs"]:  # (yaw_deg was converted in float32: 0.5093637704849243 for 0.5093637348698544)
        odometry = json.loads((out / "params" / f"{row['index']:06d}.json").read_text())["odometry"]
        assert row["yaw_deg"] == math.degrees(odometry["yaw"]) and row["z_d"] == odometry["z_d"]


def test_dataset_reads_back_the_render(written):
    _, out, _ = written
    ds = SyntheticFlowDataset(out)
    assert len(ds) == 2
    for i in range(2):
        item = ds[i]
        truth = scene.render_pair("default", i, seed=3, size=(48, 160))
        assert torch.equal(item["valid"], truth["valid"])
        m = truth["valid"].expand(2, -1, -1)
        assert float((item["flow"] - truth["flow"]).abs()[m].max()) <= 1 / 64
        assert float((item["image1"] - truth["image1"]).abs().max()) <= 0.5 + 1e-4
        assert torch.equal(item["road"], truth["road"]) and torch.equal(item["labels"], truth["labels"])
        torch.testing.assert_close(item["camera"].K, truth["camera"].K)
        assert item["odometry"] == pytest.approx(truth["odometry"])
    batch = collate([ds[0], ds[1]])
    assert batch["flow"].shape == (2, 2, 48, 160) and batch["camera"].batch_size == 2


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_reads_back_bit_for_bit_where_the_format_allows(written, dtype):
    """The files hold what their formats can hold exactly: the float64 camera (the params held the
    float32 render's camera, 4e-6 px off in K from SceneDataset(camera_dtype=torch.float64)),
    masks, labels, motion and poses (poses.txt was 5e-14 off); flow to 1/64 px, images to 8 bits."""
    from fsof_torch.data.datasets import KittiFlowDataset, SceneDataset

    _, out, _ = written
    ds = SyntheticFlowDataset(out, dtype=dtype, camera_dtype=torch.float64)
    # (written from a float32 render: its ground truth is the float32 render's, read as dtype)
    truth = SceneDataset("default", 2, seed=3, size=(48, 160), camera_dtype=torch.float64)
    rendered = SceneDataset("default", 2, seed=3, size=(48, 160), dtype=dtype)  # (the camera in dtype)
    poses = read_kitti_poses(out / "poses.txt")
    for i in range(2):
        item, want = ds[i], truth[i]
        for field in ("K", "height", "roll", "pitch"):
            assert torch.equal(getattr(item["camera"], field), getattr(want["camera"], field)), field
            got = getattr(SyntheticFlowDataset(out, dtype=dtype)[i]["camera"], field)
            assert torch.equal(got, getattr(rendered[i]["camera"], field)), field
        assert torch.equal(KittiFlowDataset(out, flow="occ", camera_dtype=torch.float64)[i]["camera"].K,
                           want["camera"].K)
        for key in ("valid", "road", "labels", "pose1", "pose2"):
            assert torch.equal(item[key], want[key]), key
        for key in ("odometry", "velocity", "road_pose", "plane"):
            assert item[key] == want[key], key
        assert torch.equal(poses[i], want["pose1"]) and torch.equal(poses[i + 1], want["pose2"])
        m = want["valid"].expand(2, -1, -1)
        assert float((item["flow"] - want["flow"].to(dtype))[m].abs().max()) <= 1 / 128
        assert torch.equal(item["flow_velocity"][m], want["flow_velocity"].to(dtype)[m])
        for key in ("image1", "image2"):
            assert torch.equal(item[key], want[key].round().to(dtype)), key


def test_collate_keeps_each_item_with_its_own_values(written, tmp_path):
    """Items of two sequences (other cameras, other odometry): sample b of the batch is item b."""
    _, out, _ = written
    rc = main(["synth", "--preset", "carla-turning", "--pairs", "1", "--out", str(tmp_path / "t"), "--size", "48",
               "160", "--no-progress"])
    assert rc == 0
    ds, other = SyntheticFlowDataset(out), SyntheticFlowDataset(tmp_path / "t")
    items = [other[0], ds[0], ds[1]]  # (the default preset's two pairs share their camera and odometry)
    assert items[0]["odometry"] != items[2]["odometry"] and float(items[0]["camera"].height) != float(
        items[2]["camera"].height)
    batch = collate(items)
    for key in ("x_d", "z_d", "yaw"):
        want = torch.tensor([it["odometry"][key] for it in items], dtype=batch["odometry"][key].dtype)
        assert torch.equal(batch["odometry"][key], want), key
    for b, it in enumerate(items):
        assert torch.equal(batch["image1"][b], it["image1"]) and torch.equal(batch["flow"][b], it["flow"]), b
        for field in ("K", "height", "roll", "pitch"):
            assert torch.equal(getattr(batch["camera"], field)[b], getattr(it["camera"], field)[0]), (b, field)
    assert batch["name"] == [it["name"] for it in items]


def test_poses_give_back_the_odometry(written):
    _, out, _ = written
    poses = read_kitti_poses(out / "poses.txt")
    assert poses.shape == (3, 4, 4)
    ds = SyntheticFlowDataset(out, dtype=torch.float64)
    for i in range(2):
        item = ds[i]
        ego = ego_motion_from_pose(poses[i:i + 1], item["camera"], pose1=poses[i + 1:i + 2])
        for key in ("x_d", "z_d", "yaw"):
            assert float(getattr(ego, key)) == pytest.approx(item["odometry"][key], abs=1e-6)


def test_stores_the_road_pose_and_plane_motion(tmp_path):
    rc = main(["synth", "--preset", "body-motion", "--pairs", "2", "--out", str(tmp_path / "b"), "--size", "24", "64",
               "--no-progress"])
    assert rc == 0
    ds = SyntheticFlowDataset(tmp_path / "b", dtype=torch.float64)
    for i in range(2):
        truth = scene.render_pair("body-motion", i, size=(24, 64))
        assert ds[i]["road_pose"] == truth["road_pose"] and ds[i]["plane"] == truth["plane"]
    batch = collate([ds[0], ds[1]])
    assert batch["plane"]["pitch_change"].shape == (2,)
    for key in ("pitch_change", "roll_change", "pitch", "height"):  # in the items' order (they differ)
        assert batch["plane"][key].tolist() == [ds[0]["plane"][key], ds[1]["plane"][key]], key
        assert ds[0]["plane"][key] != ds[1]["plane"][key], key


def test_prints_a_table(tmp_path, capsys):
    rc = main(["synth", "--preset", "cvc-simple", "--pairs", "1", "--out", str(tmp_path / "s"), "--size", "32", "96",
               "--no-progress"])
    printed = capsys.readouterr().out
    assert rc == 0 and "wrote 1 pairs of preset 'cvc-simple'" in printed and "valid %" in printed


def test_bad_arguments(tmp_path, capsys):
    assert main(["synth", "--preset", "nope", "--pairs", "1", "--out", str(tmp_path / "x")]) == 2
    assert "unknown preset 'nope'" in capsys.readouterr().err
    assert main(["synth", "--pairs", "0", "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()
    capsys.readouterr()
    # beyond the renderer's last frame (was: a traceback at frame 100 000, a half-written folder)
    assert main(["synth", "--pairs", "100001", "--out", str(tmp_path / "x")]) == 2
    assert "error: --pairs: expected 1 to 100000, got 100001" in capsys.readouterr().err
    # --json as a folder above --out (was: the whole render, then an IsADirectoryError)
    assert main(["synth", "--pairs", "1", "--out", str(tmp_path / "j" / "out"), "--json", str(tmp_path / "j")]) == 2
    assert f"error: --json: {str(tmp_path / 'j')!r} is --out" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "j").exists()


def test_a_flow_beyond_the_flow_png_stops_with_a_message(tmp_path, capsys):
    """A --size the renderer takes, whose flow a KITTI flow PNG cannot hold (the default preset at 4000
    px wide: 501 px at pair 0, 622 px at pair 1): was a traceback after pair 1's images were written;
    now exit 2 naming --size, pair 0 whole, nothing of pair 1."""
    out = tmp_path / "wide"
    rc = main(["synth", "--pairs", "3", "--out", str(out), "--size", "16", "4000", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: --size: pair 1's ground-truth flow: a KITTI flow PNG holds "
                                      "[-512.0, 511.984375] px, got the range [")
    assert "give a smaller --size (pairs 0 to 0 are written to" in err and "without meta.json" in err
    assert sorted(p.name for p in (out / "image_2").iterdir()) == ["000000_10.png", "000000_11.png"]
    assert not (out / "meta.json").exists() and sorted(p.name for p in (out / "params").iterdir()) == ["000000.json"]
    pair = read_synthetic_pair(out, 0)
    assert float(pair["flow"][pair["valid"].expand(2, -1, -1)].abs().max()) <= 511.984375
    rc = main(["synth", "--pairs", "1", "--out", str(tmp_path / "first"), "--size", "16", "5000", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "pair 0's ground-truth flow" in err and err.endswith("give a smaller --size (nothing was written)\n")
    assert not any((tmp_path / "first").rglob("*.*"))


def test_refuses_a_folder_holding_files(written, capsys):
    """A second run into a used folder would leave the first run's extra pairs beside its own."""
    _, out, _ = written
    before = (out / "meta.json").read_text()
    rc = main(["synth", "--preset", "cvc-simple", "--pairs", "1", "--out", str(out), "--size", "32", "96",
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and f"error: --out: {str(out)!r} already holds files" in err and "new or empty folder" in err
    assert (out / "meta.json").read_text() == before and len(SyntheticFlowDataset(out)) == 2


def test_output_paths_checked_first(tmp_path, capsys):
    (tmp_path / "afile").write_text("")
    (tmp_path / "empty").mkdir()
    assert main(["synth", "--pairs", "1", "--out", str(tmp_path / "afile"), "--no-progress"]) == 2
    assert "error: --out: " in capsys.readouterr().err
    rc = main(["synth", "--pairs", "1", "--out", str(tmp_path / "s"), "--json", str(tmp_path / "empty"),
               "--no-progress"])
    assert rc == 2 and "error: --json: " in capsys.readouterr().err
    assert not (tmp_path / "s").exists()
    # an empty folder is fine, and a --json in a folder not made yet is created
    rc = main(["synth", "--pairs", "1", "--size", "24", "64", "--out", str(tmp_path / "empty"),
               "--json", str(tmp_path / "new" / "s.json"), "--no-progress"])
    assert rc == 0 and (tmp_path / "new" / "s.json").is_file() and len(SyntheticFlowDataset(tmp_path / "empty")) == 1


@pytest.mark.parametrize("inside", ["poses.txt", "meta.json", "extra/s.json", "../seq/s.json"])
def test_refuses_a_json_inside_out(tmp_path, capsys, monkeypatch, inside):
    """--json inside --out is refused before any work: the layout's files would replace it, or it
    one of them (--json DIR/poses.txt destroyed the poses)."""
    monkeypatch.setattr(scene, "render_pair", lambda *a, **k: pytest.fail("rendered before --json was checked"))
    out = tmp_path / "seq"
    rc = main(["synth", "--pairs", "1", "--out", str(out), "--json", str(out / inside), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and f"error: --json: {str(out / inside)!r} is inside --out {str(out)!r}" in err, err
    assert not out.exists()


@pytest.mark.parametrize("size", [["16385", "64"], ["10000000", "10000000"]])
def test_refuses_a_size_above_the_maximum(tmp_path, capsys, monkeypatch, size):
    """Each --size side is at most 16384: beyond, exit 2 naming it before any folder is made (a
    MemoryError traceback left an empty --out)."""
    monkeypatch.setattr(scene, "render_pair", lambda *a, **k: pytest.fail("rendered before --size was checked"))
    rc = main(["synth", "--pairs", "1", "--out", str(tmp_path / "s"), "--size", *size, "--no-progress"])
    assert rc == 2 and f"error: --size: expected H, W <= 16384, got [{size[0]}, {size[1]}]" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_jobs_doc_lists_what_synth_writes(written):
    """docs/jobs.md's row for synth names every folder and file the job writes (params/ was left out)."""
    from pathlib import Path

    _, out, _ = written
    doc = (Path(__file__).resolve().parents[1] / "docs" / "jobs.md").read_text()
    row = next(line for line in doc.splitlines() if line.startswith("| `synth` |"))
    written_names = sorted(p.name + ("/" if p.is_dir() else "") for p in out.iterdir())
    assert "params/" in written_names
    assert [n for n in written_names if f"`{n}" not in row] == []


def test_a_run_that_stops_leaves_no_earlier_json(tmp_path, interrupted):
    """An earlier run's --json goes once the options are checked: a run stopped while rendering
    (an interrupt, an error) left it beside its own partial sequence, read as this run's summary."""
    path = tmp_path / "synth.json"
    path.write_text('{"preset": "an earlier run"}')

    interrupted(scene, "render_pair",
                lambda: main(["synth", "--pairs", "1", "--out", str(tmp_path / "s"), "--json", str(path), "--no-progress"]))
    assert not path.exists()
