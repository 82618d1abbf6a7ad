"""``benchmarks/auto_road.py``'s turned real pairs: the real street's texture in a turn of known
motion, through ``real_road.turned`` (tested in test_bench_real_road.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture
def bench(load_benchmark, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # (its sibling modules, as when run as a script)
    return load_benchmark("auto_road")


def test_turned_real_pairs_are_real_road_turned(bench, load_benchmark, shared_data):
    if not (shared_data / "kitti15_000000").is_dir():
        pytest.skip("kitti15_000000 is absent")
    name, im1, im2, camera, poly = next(bench.real_pairs(shared_data))
    name_t, t1, t2, camera_t, poly_t = next(bench.real_pairs(shared_data, (6.0, 0.5, -0.5)))
    assert name_t == name
    ref = load_benchmark("real_road").turned({"image1": im1[0], "image2": im2[0], "road": poly[0], "camera": camera},
                                             6.0, 0.5, -0.5)
    for got, want in ((t1, ref["image1"]), (t2, ref["image2"]), (poly_t, ref["road"])):
        assert got.shape == (1, *want.shape) and torch.equal(got[0], want)
    assert torch.equal(camera_t.K, ref["camera"].K)
    # cropped to where the turned image 2 is defined, and image 2 itself changed
    assert t1.shape[-1] < im1.shape[-1] and t1.shape[-2:] == t2.shape[-2:] == poly_t.shape[-2:]
    assert not torch.equal(t2, im2[..., :t2.shape[-2], :t2.shape[-1]])


def test_reversed_real_pairs_swap_the_frames_before_the_turn(bench, load_benchmark, shared_data):
    """``--reverse``: each real pair's frames swapped, the forward pair's polygon kept (as
    ``real_road.reversed_pair`` keeps it); with a turn, the swapped pair is turned."""
    if not (shared_data / "kitti15_000000").is_dir():
        pytest.skip("kitti15_000000 is absent")
    name, im1, im2, camera, poly = next(bench.real_pairs(shared_data))
    name_r, r1, r2, camera_r, poly_r = next(bench.real_pairs(shared_data, reverse=True))
    assert name_r == name and torch.equal(r1, im2) and torch.equal(r2, im1) and torch.equal(poly_r, poly)
    assert torch.equal(camera_r.K, camera.K)
    *_, t1, t2, _, poly_t = next(bench.real_pairs(shared_data, (6.0, 0.0, 0.0), reverse=True))
    ref = load_benchmark("real_road").turned({"image1": im2[0], "image2": im1[0], "road": poly[0], "camera": camera},
                                             6.0, 0.0, 0.0)
    assert torch.equal(t1[0], ref["image1"]) and torch.equal(t2[0], ref["image2"]) and torch.equal(poly_t[0], ref["road"])


TURN_OPTIONS = ("--yaw-deg", "--pitch-change-deg", "--roll-change-deg")


@pytest.mark.parametrize("option", TURN_OPTIONS)
@pytest.mark.parametrize("value", ["nan", "45"])
def test_turn_options_out_of_range_exit_2(bench, option, value, capsys):
    assert bench.main(["--no-synthetic", "--no-slow", option, value]) == 2
    # the error's line (the last) names the option that is wrong, and its value
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last == f"{option}: expected finite degrees within ±30, got {float(value)}", last


def test_a_grey_pair_turns_as_the_same_channel_of_a_colour_pair(load_benchmark):
    """The straight clip's frames are grey (one channel), which OpenCV's warp returns without its
    channel axis."""
    from fsof_torch.data.scene import render_pair

    rr = load_benchmark("real_road")
    pair = render_pair("default", 0, size=(96, 320))
    grey = {**pair, "image1": pair["image1"][:1], "image2": pair["image2"][:1]}
    colour, one = rr.turned(pair, 6.0, 1.0), rr.turned(grey, 6.0, 1.0)
    assert one["image2"].shape == (1, *colour["image2"].shape[-2:])
    assert torch.equal(one["image2"][0], colour["image2"][0]) and torch.equal(one["image1"][0], colour["image1"][0])


@pytest.mark.parametrize("bad", ["-1", "100000"])
def test_pair_indices_beyond_the_renderers_frames_exit_2(bench, capsys, bad):
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--no-slow", "--no-real", "--pairs", "5", bad])
    assert exit_.value.code == 2
    assert (f"argument --pairs: expected an integer from 0 to 99999 (the renderer's frames end at 100000), "
            f"got '{bad}'") in capsys.readouterr().err


def test_road_parts_split_the_true_road_by_what_image_2_shows(bench):
    """``road_parts``: seen in image 2 (``valid``) near the road's edge or inside it, occluded there
    (the flow lands inside image 2 but the point is hidden) or out of its view (the flow leaves
    image 2): disjoint, the whole road, each as defined, checked pixel by pixel against the
    rendered flow, validity and road in NumPy."""
    import numpy as np

    from fsof_torch.data.scene import render_pair

    pair = render_pair("default", 20, size=(96, 320))  # an oncoming car hides road in image 2
    parts = bench.road_parts(pair, edge_px=4)
    assert tuple(parts) == bench.PARTS
    road = pair["road"].bool().reshape(1, 1, 96, 320)
    near, inner, occluded, out = (parts[k] for k in bench.PARTS)
    union = torch.zeros_like(road)
    for k, part in parts.items():
        assert part.shape == road.shape and part.any(), k
        assert not (union & part).any(), k
        union |= part
    assert torch.equal(union, road)
    flow = pair["flow"].double().numpy()
    tx, ty = np.arange(320) + flow[0], np.arange(96)[:, None] + flow[1]
    outside = (tx < 0) | (tx > 319) | (ty < 0) | (ty > 95)
    valid = pair["valid"].reshape(96, 320).numpy()
    r = road[0, 0].numpy()
    assert np.array_equal(out[0, 0].numpy(), r & ~valid & outside)
    assert np.array_equal(occluded[0, 0].numpy(), r & ~valid & ~outside)
    # near the edge: a pixel not road, or road hidden in image 2, within 4 px (a 9 x 9 square)
    hidden = ~r | occluded[0, 0].numpy()
    ys, xs = np.nonzero(r & valid)
    close = np.array([hidden[max(y - 4, 0):y + 5, max(x - 4, 0):x + 5].any() for y, x in zip(ys, xs)])
    assert np.array_equal(near[0, 0].numpy()[ys, xs], close) and np.array_equal(inner[0, 0].numpy()[ys, xs], ~close)
    # driving forwards, the road nearest the vehicle leaves image 2 at its bottom
    assert r[-1].any() and np.array_equal(out[0, 0, -1].numpy(), r[-1]) and bool((ty[-1][r[-1]] > 95).all())


def test_edge_reach_is_step_5s_radius(bench):
    """The "near its edge" band of ``road_parts`` is how far the detection's step 5 reaches: 16 px
    at KITTI's size (working level 1), the figure docs/auto-road.md gives."""
    assert bench.edge_reach(1) == 16 and bench.edge_reach(0) == 8


def _real_data(root: Path, colour_clip: bool = False) -> Path:
    """A KITTI pair and a three-frame clip in the shared data's layout under ``root``, rendered
    at 96 × 320; the clip's frames grey (one channel, as KITTI's grey cameras) or colour."""
    import json

    from fsof_torch.data.scene import render_pair
    from fsof_torch.io import write_image, write_kitti_calibration

    size, polygon = (96, 320), [[60, 95], [150, 56], [195, 56], [205, 95]]
    p0, p1 = render_pair("default", 0, size=size), render_pair("default", 1, size=size)
    pair, clip = root / "kitti15_000000", root / "kitti_odometry_straight"
    (clip / "image_l").mkdir(parents=True)
    pair.mkdir()
    write_image(pair / "image_10.png", p0["image1"])
    write_image(pair / "image_11.png", p0["image2"])
    write_kitti_calibration(pair / "calib_cam_to_cam.txt", p0["camera"].K[0], cam=2)
    for i, im in enumerate((p0["image1"], p0["image2"], p1["image2"])):
        write_image(clip / "image_l" / f"{i:06d}.png", im if colour_clip else im.mean(0, keepdim=True).round())
    write_kitti_calibration(clip / "calib.txt", p0["camera"].K[0], cam=0, style="odometry")
    for folder in (pair, clip):
        (folder / "road.json").write_text(json.dumps({"size": list(size), "road_polygon": polygon}))
    return root


@pytest.mark.parametrize("colour", [False, True])
def test_a_colour_clip_is_judged_in_colour_a_grey_one_in_its_channel(bench, tmp_path, colour):
    """The clip's frames as read: a grey camera's one channel (``read_image`` repeats it), a colour
    camera's three (as the KITTI pair's), never its red channel alone."""
    from fsof_torch.io import read_image

    root = _real_data(tmp_path, colour_clip=colour)
    clip = list(bench.real_pairs(root, kitti15=False))
    assert [c[0] for c in clip] == ["straight clip 00", "straight clip 01"]
    want = read_image(root / "kitti_odometry_straight" / "image_l" / "000001.png")
    assert not colour or not torch.equal(want[0], want[1])
    _, im1, im2, _, _ = clip[1]
    assert im1.shape == (1, 3 if colour else 1, 96, 320) and torch.equal(im1[0], want[:im1.shape[1]])


def test_data_the_library_cannot_read_exits_2_before_any_work(bench, tmp_path, capsys, monkeypatch):
    """A --data folder whose samples the library cannot read (a pair's frames of another size than
    its calibration's S_rect, a clip's calibration without P0, a clip frame of another size) exits
    2 naming --data and what is wrong, before the synthetic table; a readable one passes."""
    from fsof_torch.io import write_image

    def no_work(*args, **kwargs):
        raise AssertionError("the synthetic table ran")

    monkeypatch.setattr(bench, "synthetic_table", no_work)
    root = _real_data(tmp_path / "data")
    pair, clip = root / "kitti15_000000", root / "kitti_odometry_straight"
    calib = (pair / "calib_cam_to_cam.txt").read_text()
    (pair / "calib_cam_to_cam.txt").write_text(calib + "S_rect_02: 320 100\n")  # (4 rows taller)
    calib_clip = (clip / "calib.txt").read_text()
    (clip / "calib.txt").write_text("P_rect_02: 101.0 1.0 1.0 0.0 1.0 101.0 1.0 0.0 1.0 1.0 101.0 0.0\n")  # no camera's K
    cut = torch.zeros(1, 90, 320)
    for wrong, message in (("pair", "--data: images: image_10.png is 96x320 but the calibration"),
                           ("calib", "--data: calib: "),
                           ("frame", "--data: images: 000002.png is 90x320 but 000000.png is 96x320")):
        if wrong == "calib":
            (pair / "calib_cam_to_cam.txt").write_text(calib)
        if wrong == "frame":
            (clip / "calib.txt").write_text(calib_clip)
            write_image(clip / "image_l" / "000002.png", cut)
        with pytest.raises(SystemExit) as exit_:
            bench.main(["--data", str(root), "--no-slow"])
        assert exit_.value.code == 2
        assert message in capsys.readouterr().err
    readable = _real_data(tmp_path / "readable")
    assert bench.unreadable(readable, True, True) is None
    # a polygon beside the frames: the tables' shares of the polygon would be of no pixel
    (readable / "kitti_odometry_straight" / "road.json").write_text('{"size": [96, 320], "road_polygon": '
                                                                   '[[400, 10], [450, 10], [450, 60]]}')
    assert bench.unreadable(readable, True, False) is None
    assert bench.unreadable(readable, True, True) == "road.json: its road polygon covers no pixel of the 96 x 320 frames"


def test_a_turn_that_leaves_no_window_exits_2_before_any_work(bench, tmp_path, capsys, monkeypatch):
    """A turn within ±30° that leaves no window of image 2 defined (a pitch change of 6° at this
    camera: at most a fifth of the rows may be cut at the top and at the bottom; 4° leave one)
    exits 2 naming the turn options before the synthetic table, not with a traceback after it; on
    the clip alone too."""
    def no_work(*args, **kwargs):
        raise AssertionError("the synthetic table ran")

    monkeypatch.setattr(bench, "synthetic_table", no_work)
    root = _real_data(tmp_path / "data")
    for only_clip in (False, True):
        if only_clip:
            for f in (root / "kitti15_000000").iterdir():
                f.unlink()
            (root / "kitti15_000000").rmdir()
        with pytest.raises(SystemExit) as exit_:
            bench.main(["--data", str(root), "--no-slow", "--pitch-change-deg", "6"])
        assert exit_.value.code == 2
        assert "--yaw-deg, --pitch-change-deg, --roll-change-deg: the turn (0.0°, 6.0°, 0.0°) leaves no window of " \
               "image 2 defined" in capsys.readouterr().err
    assert next(bench.real_pairs(root, (0.0, 4.0, 0.0), kitti15=False))[1].shape[-2] < 96  # (4°: a window)


def test_a_flow_based_detection_that_finds_nothing_is_flagged(bench, monkeypatch, capsys):
    """The real-data table's flow-based rows count the frames whose detect_freespace failed (an
    empty freespace is a failure; the column printed '-' and the empty results passed unflagged)."""
    from types import SimpleNamespace

    import fsof_torch
    from fsof_torch import Camera

    K = torch.tensor([[200.0, 0, 80.0], [0, 200.0, 18.0], [0, 0, 1]], dtype=torch.float64)
    size = (64, 160)
    image = torch.zeros(1, 3, *size)
    poly = torch.zeros(1, 1, *size, dtype=torch.bool)
    poly[..., 40:, 40:120] = True
    monkeypatch.setattr(bench, "real_pairs", lambda root, *a, **k: iter(
        [(f"straight clip {i:02d}", image, image, Camera(K, 1.5), poly) for i in range(2)]))
    monkeypatch.setattr(bench, "dis", lambda im1, im2: torch.zeros(1, 2, *size))   # a standing car: no road model
    monkeypatch.setattr(fsof_torch, "detect_road", lambda *a, **k: SimpleNamespace(mask=poly, flag=["ok"]))
    bench.real_table(Path("."), kitti15=False)
    row = next(line for line in capsys.readouterr().out.splitlines() if "flow-based" in line)
    assert row.split()[-2:] == ["2", "2"]   # empty 2, flagged 2


def test_the_turns_table_prints_both_seeds(bench, capsys):
    """``--turns``: per turn, the detection and the same with the seed straight ahead only
    (``follow_path=False``): a flag, an IoU, the seed's agreement and a time each; the mean IoUs."""
    from fsof_torch.refinement.auto_road import FLAGS

    bench.turns_table(((-0.1, 10),), size=(188, 621))
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == "Sharp turns, (188, 621)" and "follow_path=False" in lines[1]
    row, mean = lines[2].split(), lines[3].split()
    assert row[:2] == ["-0.10,", "10"] and len(row) == 10 and len(mean) == 4
    for flag, iou, agreement, ms in (row[2:6], row[6:10]):
        assert flag in ("ok", *FLAGS) and 0 <= float(iou) <= 1 and 0 <= float(agreement) <= 1 and float(ms) > 0
    assert [float(mean[2]), float(mean[3])] == [float(row[3]), float(row[7])]
