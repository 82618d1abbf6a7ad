"""``benchmarks/real_road.py``'s functions on a tiny synthetic pair (the full benchmark on the shared
KITTI data is not run here): the homography flow, ECC, poses as odometry, the road errors, the
summary, and ``main`` on a tiny clip in the shared data's layout."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

SIZE = (96, 320)
# inside the synthetic default scene's road at 96x320 (rows 48-95)
POLYGON = [[60, 95], [150, 56], [195, 56], [205, 95]]


@pytest.fixture(scope="module")
def rr(load_benchmark):
    with pytest.MonkeyPatch.context() as patch:
        # (main imports its sibling cli.py, as when run as a script)
        patch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "benchmarks"))
        yield load_benchmark("real_road")


@pytest.fixture(scope="module")
def scenes():
    from fsof_torch.data.scene import render_pair

    return [render_pair("default", i, size=SIZE) for i in range(2)]


@pytest.fixture(scope="module")
def pair(scenes):
    from fsof_torch.io import rasterize_polygons

    p = scenes[0]
    road = rasterize_polygons([POLYGON], SIZE).reshape(1, *SIZE)
    assert bool(road.any()) and not bool((road & ~p["road"]).any())  # the polygon lies on the road
    return {"image1": p["image1"], "image2": p["image2"], "camera": p["camera"], "road": road,
            "relative_pose": torch.linalg.inv(p["pose2"]) @ p["pose1"], "flow": p["flow"], "valid": p["valid"]}


@pytest.fixture(scope="module")
def results(rr, pair):
    return rr.run_pair(pair, rr.METHODS)


def test_homography_flow_against_hand_computation(rr):
    flow, valid = rr.homography_flow(np.eye(3), (4, 5))
    assert torch.equal(flow, torch.zeros(2, 4, 5)) and bool(valid.all())
    shift = np.array([[1.0, 0.0, 2.0], [0.0, 1.0, -1.5], [0.0, 0.0, 1.0]])
    flow, _ = rr.homography_flow(shift, (4, 5))
    assert torch.equal(flow[0], torch.full((4, 5), 2.0)) and torch.equal(flow[1], torch.full((4, 5), -1.5))
    H = np.array([[1.1, 0.02, 3.0], [0.01, 0.95, -2.0], [1e-3, 2e-3, 1.0]])
    flow, _ = rr.homography_flow(H, (4, 5))
    u, v = 3, 2  # pixel (u, v) -> (H p) / (H p)_z
    q = H @ np.array([u, v, 1.0])
    assert flow[:, v, u].tolist() == pytest.approx([q[0] / q[2] - u, q[1] / q[2] - v], abs=1e-5)
    behind = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 1.5]])  # z = 1.5 - v: behind from v = 2
    flow, valid = rr.homography_flow(behind, (4, 5))
    assert valid[0, :, 0].tolist() == [True, True, False, False] and bool((flow[:, 2:] == 0).all())


def test_ecc_recovers_a_known_homography_from_the_road_of_image_1(rr):
    """Image 2 is image 1 warped by a known homography H (image 2 (H p) = image 1 (p)); ECC from a
    start 1.8 px off recovers it. Image 1 outside the road shows other content, which must not
    count: the road is the template's mask (with the road as the input image's mask, as
    ``findTransformECC`` takes it, the same pair is 0.4 px off)."""
    import cv2

    size = (96, 320)
    gen = torch.Generator().manual_seed(0)

    def texture():
        coarse = torch.rand(1, 1, size[0] // 4, size[1] // 4, generator=gen)
        return (F.interpolate(coarse, size=size, mode="bicubic", align_corners=False)[0] * 255).clamp(0, 255)

    H = np.array([[1.05, 0.02, -3.0], [0.01, 1.04, 2.0], [1e-4, 2e-4, 1.0]])
    road = torch.zeros(1, *size, dtype=torch.bool)
    road[:, 20:80, 40:280] = True
    clean = texture()
    image1 = torch.where(road, clean, texture()).expand(3, -1, -1)
    image2 = torch.from_numpy(cv2.warpPerspective(clean[0].numpy(), H, size[::-1], flags=cv2.INTER_CUBIC))
    image2 = image2.clamp(0, 255).expand(3, -1, -1)
    flow, _ = rr.homography_flow(H, size)
    start = flow + torch.tensor([1.5, -1.0])[:, None, None]
    H_ecc, ok = rr.ecc_homography(image1, image2, road, start)
    flow_ecc, _ = rr.homography_flow(H_ecc, size)
    assert ok
    assert float((flow_ecc - flow)[:, road[0]].norm(dim=0).max()) < 0.1


def test_ecc_fits_the_road_plane_better_than_dis(results):
    """The synthetic road is a plane: ECC's homography matches the images better than DIS. (Its
    end-point error on this small pair, whose road reaches the image's bottom edge, depends on
    how the OpenCV version treats the border; the homography itself is checked above.)"""
    assert not results["ECC homography"]["ecc_failed"]
    assert results["ECC homography"]["census"] < results["DIS"]["census"]


def test_poses_as_odometry_give_the_true_road_flow(rr, pair):
    """inverse(P_{i+1}) @ P_i as the plane model's motion, or projected on the paper's planar
    motion (the scene's road has no body motion), maps the road as the ray-cast flow does."""
    from fsof_torch import road_homography

    road = pair["road"][0] & pair["valid"][0]
    cam = pair["camera"].to(torch.float64)
    plane = {k: v for k, v in rr.plane_odometry(pair).items() if k != "model"}
    ego = rr.paper_odometry(pair)
    for model, params in (("plane", plane), ("paper", {"x_d": ego.x_d, "z_d": ego.z_d, "yaw": ego.yaw})):
        H = road_homography(cam, params, model=model)[0]
        flow, _ = rr.homography_flow(H.numpy(), SIZE)
        assert float((flow - pair["flow"])[:, road].norm(dim=0).max()) < 0.05, model


def test_poses_as_odometry_never_worse_than_dis(results):
    """The gate keeps DIS where the images prefer it. On this small pair the exact road flow's
    census is close to DIS's (the rendered detail changes between the frames), so whether the
    gate takes the model can turn on DIS's last decimals: it is never worse, and the paper's
    planar motion, whose pitch and roll the images fit, is refined and better."""
    dis = results["DIS"]
    for name in ("refiner, poses ('plane')", "refiner, poses (paper's planar)"):
        r = results[name]
        assert r["census"] <= dis["census"] + 1e-6 and r["epe"] <= dis["epe"] + 1e-6, name
    r = results["refiner, poses (paper's planar)"]
    assert r["refined"] and r["epe"] < dis["epe"] and r["census"] < dis["census"]


def test_refiner_reports_the_model_flows_own_error_and_the_cells_kept(rr, pair, results):
    """The notes' figures: the gate's cells that kept DIS's flow, as the refiner's gate result
    counts them, and the model flow's own road error, from ``flow_model`` before the gate; where
    the gate keeps no cell and no sample, the refined road is the model's."""
    from fsof_torch import FreespaceRefiner, endpoint_error
    from refine.sources import dis_flow

    dis = dis_flow(pair["image1"], pair["image2"])
    out = FreespaceRefiner()(dis[None], pair["road"][None], pair["camera"], None,
                             images=(pair["image1"][None], pair["image2"][None]))
    r = results["refiner (no odometry)"]
    assert r["refined"] and r["cells_kept"] == int(out.gate.cells_kept[0])
    model = torch.where(pair["road"][None], out.flow_model, dis[None])
    expected = endpoint_error(model, pair["flow"][None], pair["road"][None], pair["valid"][None])
    assert r["epe_model"] == pytest.approx(float(expected[0]), rel=1e-5)
    if bool(out.gate.use_model[0][pair["road"]].all()):
        assert r["epe_model"] == pytest.approx(r["epe"], rel=1e-5)
    assert "model_flow" not in r  # the tensor is not kept in the results
    assert r["gate"] == {"census_model": float(out.gate.cost_model[0]),
                         "census_prediction": float(out.gate.cost_prediction[0]),
                         "confirmed": bool(out.gate.confirmed[0]), "informative": bool(out.gate.informative[0])}
    assert "epe_model" not in results["DIS"] and "epe_model" not in results["ECC homography"]


def test_road_errors_are_the_library_figures_of_the_combined_flow(rr, pair):
    """Inside the road the method's flow, DIS's elsewhere; census, SSIM and L1 as
    ``photometric_error`` gives them, EPE over road ∩ valid ground truth."""
    from fsof_torch import endpoint_error, photometric_error

    dis = torch.zeros(2, *SIZE)
    dis[0] = 0.5
    method = pair["flow"]
    errors = rr.road_errors(pair, method, dis)
    road = pair["road"][None]
    combined = torch.where(road, method[None], dis[None])
    for kind in ("census", "ssim", "l1"):
        expected = float(photometric_error(pair["image1"][None], pair["image2"][None], combined, road, kind=kind)[0])
        assert errors[kind] == pytest.approx(expected, rel=1e-6), kind
    assert errors["epe"] == pytest.approx(0.0, abs=1e-6) and errors["n_epe"] == int((road & pair["valid"]).sum())
    # outside the road the flow is DIS's: a different flow there changes nothing but the windows
    # of census and SSIM at the polygon's edge, and L1 not at all
    other = method.clone()
    other[:, ~pair["road"][0]] = 40.0
    assert rr.road_errors(pair, other, dis)["l1"] == errors["l1"]
    assert float(endpoint_error(combined, method[None], road)[0]) == 0.0


def test_summarize_counts_worse_pairs_and_the_difference_to_ecc(rr):
    def run(census):
        return {"census": census, "ssim": 0.1, "l1": 5.0, "seconds": 0.5}

    per_pair = [{"DIS": run(0.30), "ECC homography": run(0.20), "refiner (no odometry)": run(0.315)},
                {"DIS": run(0.30), "ECC homography": run(0.22), "refiner (no odometry)": run(0.305)},
                {"DIS": run(0.40), "refiner (no odometry)": run(0.10)}]  # ECC not run on this pair
    rows = {r["method"]: r for r in rr.summarize(per_pair)}
    ref = rows["refiner (no odometry)"]
    assert ref["pairs"] == 3 and ref["census"] == pytest.approx((0.315 + 0.305 + 0.10) / 3)
    assert ref["worse_than_dis"] == 1 and ref["max_worse_than_dis"] == pytest.approx(0.015)
    assert ref["minus_ecc"] == pytest.approx(((0.315 - 0.20) + (0.305 - 0.22)) / 2)
    assert rows["ECC homography"]["pairs"] == 2 and rows["ECC homography"]["minus_ecc"] == 0.0
    assert rows["DIS"]["worse_than_dis"] == 0
    text = rr.table(rr.summarize(per_pair))
    assert "| refiner (no odometry) | 3 | 0.2400 |" in text and "1 (max +0.015)" in text
    # the refiner's notes: pairs refined, the gate's cells kept over the pairs, the model's own EPE
    per_pair[0]["refiner (no odometry)"].update(refined=True, cells_kept=2, epe=0.5, epe_model=0.4)
    per_pair[1]["refiner (no odometry)"].update(refined=True, cells_kept=1)
    per_pair[2]["refiner (no odometry)"].update(refined=False)
    ref = {r["method"]: r for r in rr.summarize(per_pair)}["refiner (no odometry)"]
    assert ref["refined"] == 2 and ref["cells_kept"] == 3 and ref["epe_model"] == pytest.approx(0.4)
    assert "refined 2/3; the gate kept the prediction in 3 cell(s); model alone EPE 0.40 |" in rr.table([ref])


def _tiny_clip(scenes, tmp_path):
    """Three frames, two poses (the second pair has none, as the real clip's last), a polygon, in
    the shared data's layout under ``tmp_path / "data"``."""
    from fsof_torch.io import write_image, write_kitti_calibration, write_kitti_poses

    root = tmp_path / "data" / "kitti_odometry_straight"
    (root / "image_l").mkdir(parents=True)
    p0, p1 = scenes
    for i, im in enumerate([p0["image1"], p0["image2"], p1["image2"]]):
        write_image(root / "image_l" / f"{i:06d}.png", im)
    write_kitti_calibration(root / "calib.txt", p0["camera"].K[0], cam=0, style="odometry")
    write_kitti_poses(root / "poses.txt", torch.stack([p0["pose1"], p0["pose2"]]))
    (root / "road.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": POLYGON}))


def _main_on_tiny_clip(rr, scenes, tmp_path, capsys, *options):
    """``main`` on the tiny clip with ``options`` (no ECC, no progress): what it printed and its
    JSON report."""
    _tiny_clip(scenes, tmp_path)
    out = tmp_path / "report.json"
    assert rr.main(["--data", str(tmp_path / "data"), *options, "--no-ecc", "--no-progress", "--json", str(out)]) == 0
    return capsys.readouterr().out, json.loads(out.read_text())


def test_main_on_a_tiny_clip_in_the_shared_layout(rr, scenes, tmp_path, capsys):
    _tiny_clip(scenes, tmp_path)
    out = tmp_path / "real_road.json"
    assert rr.main(["--data", str(tmp_path / "data"), "--json", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr()
    assert "kitti15_000000 not found, skipped" in printed.err
    assert "| DIS | 2 |" in printed.out and "| refiner, poses ('plane') | 1 |" in printed.out
    report = json.loads(out.read_text())
    rows = {r["method"]: r for r in report["clip"]["rows"]}
    assert set(rows) == {"DIS", "ECC homography", "refiner (no odometry)", "refiner, poses ('plane')",
                         "refiner, poses (paper's planar)", "refiner, poses (paper's planar) as priors",
                         "refiner, clip motion (fit_sequence)"}
    for r in rows.values():
        assert 0 <= r["census"] <= 1 and r["seconds"] >= 0 and "epe" not in r
    assert [p["pair"] for p in report["clip"]["pairs"]] == ["000000", "000001"]
    # the mounting fit_sequence printed, and the run's options
    pitch, roll = (float(v) for v in re.search(r"calibrated the mounting at pitch (\S+) deg, roll (\S+) deg",
                                                printed.out).groups())
    mounting = report["clip"]["mounting"]
    assert round(mounting["pitch_deg"], 3) == pitch and round(mounting["roll_deg"], 3) == roll
    assert report["options"] == {**report["options"], "data": str(tmp_path / "data"), "pairs": None, "height": 1.65,
                                 "pitch_deg": 0.0, "no_ecc": False, "pair": None, "clip": None, "json": str(out)}
    assert rr.main(["--data", str(tmp_path / "data"), "--pairs", "1", "--no-ecc", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "| DIS | 1 |" in printed and "| ECC homography |" not in printed
    # frames two apart: one pair (0, 2), and frame 2 has no pose
    assert rr.main(["--data", str(tmp_path / "data"), "--step", "2", "--no-ecc", "--no-sequence", "--no-progress",
                    "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "1 pair(s), frames 2 apart" in printed and "| DIS | 1 |" in printed and "poses" not in printed
    report = json.loads(out.read_text())
    assert report["step"] == 2 and [p["pair"] for p in report["clip"]["pairs"]] == ["000000"]
    with pytest.raises(SystemExit) as exit_:
        rr.main(["--data", str(tmp_path / "data"), "--step", "0"])
    assert exit_.value.code == 2 and "--step: expected >= 1, got 0" in capsys.readouterr().err


def test_main_checks_the_step_and_the_json_path_before_any_work(rr, scenes, tmp_path, capsys, monkeypatch):
    """--step must leave a pair in the clip; --json must name a file that can be written, and the file an
    earlier run left there is removed once the options are checked: a run that fails later leaves none."""
    _tiny_clip(scenes, tmp_path)
    data = ["--data", str(tmp_path / "data"), "--no-ecc", "--no-progress"]
    with pytest.raises(SystemExit) as exit_:
        rr.main([*data, "--step", "3"])
    assert exit_.value.code == 2
    assert "--step: expected at most 2 (the clip" in capsys.readouterr().err
    for bad, message in ((tmp_path, "is a folder"), (tmp_path / "data" / "x.json", "is inside the input --data")):
        with pytest.raises(SystemExit) as exit_:
            rr.main([*data, "--json", str(bad)])
        assert exit_.value.code == 2 and f"--json: {str(bad)!r} {message}" in capsys.readouterr().err
    earlier = tmp_path / "report.json"
    earlier.write_text('{"from": "an earlier run"}')
    with pytest.raises(SystemExit):  # (refused: nothing ran, nothing removed)
        rr.main([*data, "--step", "0", "--json", str(earlier)])
    assert earlier.is_file()

    def fails(*args, **kwargs):
        raise RuntimeError("the run failed")

    monkeypatch.setattr(rr, "measure", fails)
    with pytest.raises(RuntimeError, match="the run failed"):
        rr.main([*data, "--json", str(earlier)])
    assert not earlier.exists()


def test_main_on_other_kitti_folders(rr, scenes, tmp_path, capsys):
    """--pair and --clip name other folders in the samples' layouts, run instead of --data's: a
    pair without ground truth (no EPE) and a clip without poses (no pose methods) are judged by
    their images; each is titled by its folder. A folder without road.json exits 2 naming it."""
    from fsof_torch.io import write_image, write_kitti_calibration

    _tiny_clip(scenes, tmp_path)
    clip = tmp_path / "data" / "kitti_odometry_straight"
    (clip / "poses.txt").unlink()
    pair = tmp_path / "another_pair"
    pair.mkdir()
    write_image(pair / "image_10.png", scenes[1]["image1"])
    write_image(pair / "image_11.png", scenes[1]["image2"])
    write_kitti_calibration(pair / "calib_cam_to_cam.txt", scenes[1]["camera"].K[0], cam=2)
    (pair / "road.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": POLYGON}))
    out = tmp_path / "report.json"
    assert rr.main(["--pair", str(pair), "--clip", str(clip), "--no-ecc", "--no-progress", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "KITTI 2015 pair another_pair (no ground-truth flow): 1 pair(s)" in printed
    assert "KITTI odometry clip kitti_odometry_straight (no poses, no ground-truth flow): 2 pair(s)" in printed
    report = json.loads(out.read_text())
    assert [p["pair"] for p in report["kitti15"]["pairs"]] == ["another_pair"]
    for key in ("kitti15", "clip"):
        methods = {r["method"] for r in report[key]["rows"]}
        assert "refiner (no odometry)" in methods and not any("poses" in m for m in methods)
        assert all("epe" not in r for r in report[key]["rows"])
    # only what is named runs: the clip alone
    assert rr.main(["--clip", str(clip), "--no-ecc", "--no-sequence", "--no-progress", "--json", str(out)]) == 0
    assert set(json.loads(out.read_text())) >= {"clip"} and "kitti15" not in json.loads(out.read_text())
    capsys.readouterr()
    (pair / "road.json").unlink()
    assert rr.main(["--pair", str(pair), "--no-progress"]) == 2
    assert f"--pair: {str(pair)!r} lacks road.json" in capsys.readouterr().err


def test_clip_poses_are_matched_to_frames_by_name(rr, scenes, tmp_path):
    """Line n of poses.txt is frame NNNNNN = n: a clip whose frames start later (or skip one) takes
    each pair's poses by its frames' names, never by the pair's position."""
    from fsof_torch.io import write_kitti_poses

    _tiny_clip(scenes, tmp_path)
    clip = tmp_path / "data" / "kitti_odometry_straight"
    for old, new in ((2, 7), (1, 5), (0, 4)):  # frames 4, 5, 7
        (clip / "image_l" / f"{old:06d}.png").rename(clip / "image_l" / f"{new:06d}.png")
    angles = torch.arange(8, dtype=torch.float64) * 0.01
    poses = torch.eye(4, dtype=torch.float64).repeat(8, 1, 1)
    c, s = angles.cos(), angles.sin()
    poses[:, 0, 0], poses[:, 0, 2], poses[:, 2, 0], poses[:, 2, 2] = c, s, -s, c
    poses[:, 2, 3] = torch.arange(8, dtype=torch.float64) ** 2  # every step different
    write_kitti_poses(clip / "poses.txt", poses)
    pairs = rr.odometry_clip(clip, 1.65, 0.0)
    assert [name for name, _ in pairs] == ["000004", "000005"]
    for (name, load), (a, b) in zip(pairs, ((4, 5), (5, 7))):
        torch.testing.assert_close(load()["relative_pose"], torch.linalg.inv(poses[b]) @ poses[a], rtol=0, atol=1e-9)
    write_kitti_poses(clip / "poses.txt", poses[:6])  # frame 7 has no pose
    assert rr.odometry_clip(clip, 1.65, 0.0)[1][1]()["relative_pose"] is None


def test_main_without_data_exits_2(rr, tmp_path, capsys):
    assert rr.main(["--data", str(tmp_path), "--no-progress"]) == 2
    assert "--data: no kitti15_000000/ or kitti_odometry_straight/" in capsys.readouterr().err
    (tmp_path / "kitti15_000000").mkdir()  # (a sample's folder without its files)
    (tmp_path / "kitti15_000000" / "road.json").write_text("{}")
    assert rr.main(["--data", str(tmp_path), "--no-progress"]) == 2
    assert (f"--data: {str(tmp_path / 'kitti15_000000')!r} lacks image_10.png, image_11.png, calib_cam_to_cam.txt"
            in capsys.readouterr().err)


def test_turned_pair_is_the_scene_seen_by_a_camera_turned_about_the_road_normal(rr, scenes):
    """Written separately: the road's normal in the camera R_c e_y, the turn by Rodrigues' formula,
    image 2's pixels mapped by H = K Rᵀ K⁻¹; the window's offset read off the cropped camera."""
    import torch.nn.functional as F

    from fsof_torch import plane_from_pose
    from fsof_torch.geometry.camera import mounting_matrix

    p = scenes[0]
    pair = {k: p[k] for k in ("image1", "image2", "road", "camera", "flow", "valid")}
    pair["relative_pose"] = torch.linalg.inv(p["pose2"]) @ p["pose1"]
    yaw = 6.0
    t = rr.turned(pair, yaw)
    cam = p["camera"].to(torch.float64)
    K = cam.K[0]
    c0, r0 = (K[:2, 2] - t["camera"].to(torch.float64).K[0, :2, 2]).round().long().tolist()
    h, w = t["image1"].shape[-2:]
    assert torch.equal(t["image1"], p["image1"][..., r0:r0 + h, c0:c0 + w])
    assert torch.equal(t["road"], p["road"][..., r0:r0 + h, c0:c0 + w]) and w > SIZE[1] // 2
    n = mounting_matrix(cam.roll, cam.pitch)[0] @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    N = torch.tensor([[0.0, -n[2], n[1]], [n[2], 0.0, -n[0]], [-n[1], n[0], 0.0]], dtype=torch.float64)
    a = math.radians(yaw)
    R = torch.eye(3, dtype=torch.float64) + math.sin(a) * N + (1 - math.cos(a)) * N @ N
    H = K @ R.T @ torch.linalg.inv(K)
    # the flow: π(H (p + f(p))) − p at every pixel of the window
    v, u = torch.meshgrid(torch.arange(r0, r0 + h, dtype=torch.float64), torch.arange(c0, c0 + w, dtype=torch.float64),
                          indexing="ij")
    f = p["flow"][..., r0:r0 + h, c0:c0 + w].to(torch.float64)
    q = torch.einsum("ij,jhw->ihw", H, torch.stack([u + f[0], v + f[1], torch.ones_like(u)]))
    ref = torch.stack([q[0] / q[2] - u, q[1] / q[2] - v])
    assert torch.allclose(t["flow"].to(torch.float64), ref, atol=1e-3)
    # image 2: the original sampled at H⁻¹ y (Lanczos there, bicubic here: close, not equal),
    # within 0..255, and as sharp as the original (bilinear weights would blur it)
    s = torch.einsum("ij,jhw->ihw", torch.linalg.inv(H), torch.stack([u, v, torch.ones_like(u)]))
    grid = torch.stack([s[0] / s[2] / (SIZE[1] - 1), s[1] / s[2] / (SIZE[0] - 1)], dim=-1) * 2 - 1
    original = p["image2"][None].to(torch.float64)
    sampled = F.grid_sample(original, grid[None], mode="bicubic", align_corners=True)[0].clamp(0, 255)
    diff = (t["image2"].to(torch.float64) - sampled).abs()
    assert float(diff.mean()) < 1.0 and float(diff.max()) < 16.0
    assert 0 <= float(t["image2"].min()) <= float(t["image2"].max()) <= 255

    def detail(x: torch.Tensor) -> float:  # mean absolute difference of neighbouring columns
        return float((x[..., 1:] - x[..., :-1]).abs().mean())

    bilinear = F.grid_sample(original, grid[None], mode="bilinear", align_corners=True)[0]
    assert detail(t["image2"].double()) > 0.95 * detail(original[0, :, r0:r0 + h, c0:c0 + w]) > detail(bilinear)
    # the pose turns by the same yaw, and the plane motion's other parameters stay
    before = plane_from_pose(pair["relative_pose"][None].double(), cam)
    after = plane_from_pose(t["relative_pose"][None].double(), t["camera"].to(torch.float64))
    assert float(after["yaw"] - before["yaw"]) == pytest.approx(a, abs=1e-9)
    for k in ("x_d", "z_d", "pitch_change", "roll_change"):
        assert float(after[k]) == pytest.approx(float(before[k]), abs=1e-9)
    # pitched and rolled too: the "plane" model's yaw, pitch_change and roll_change add exactly
    t = rr.turned(pair, yaw, 1.5, -1.0)
    after = plane_from_pose(t["relative_pose"][None].double(), t["camera"].to(torch.float64))
    for k, added in (("yaw", yaw), ("pitch_change", 1.5), ("roll_change", -1.0)):
        assert float(after[k] - before[k]) == pytest.approx(math.radians(added), abs=1e-9)
    for k in ("x_d", "y_d", "z_d"):
        assert float(after[k]) == pytest.approx(float(before[k]), abs=1e-9)
    # no turn: the whole frame, the pair itself
    same = rr.turned(pair, 0.0)
    assert torch.equal(same["image1"], pair["image1"]) and torch.equal(same["road"], pair["road"])
    assert torch.allclose(same["flow"], pair["flow"], atol=1e-4)
    assert float((same["image2"] - pair["image2"]).abs().max()) < 1e-3


def test_slalom_turns_each_frame_once_by_its_place_in_the_clip(rr, pair):
    """``slalomed``: frame k turned to A sin(2π k / P) about the road's normal, both frames of a pair
    cut to one window. A frame at a heading 0 is the frame itself, cut; a turned one is what
    ``turned`` makes of it; the frame two pairs share is the same in both (a clip still); the pose
    turns by the difference of the two headings, keeping the step's length and the other motion."""
    from fsof_torch import plane_from_pose

    A, P = 6.0, 8.0
    window = rr.slalom_window(pair["camera"], SIZE, 3, A, P)
    r0, r1, c0, c1 = window
    assert 0 < r1 - r0 <= SIZE[0] and 32 <= c1 - c0 < SIZE[1]
    first = rr.slalomed({**pair, "positions": (0, 1)}, A, P, window)
    assert math.isclose(rr.slalom_yaw(1, A, P), A * math.sin(math.pi / 4)) and rr.slalom_yaw(0, A, P) == 0.0
    assert float((first["image1"] - pair["image1"][..., r0:r1, c0:c1]).abs().max()) < 1e-3
    assert torch.equal(first["road"], pair["road"][..., r0:r1, c0:c1])
    by_turned = rr.turned(pair, rr.slalom_yaw(1, A, P), window=window)
    assert torch.equal(first["image2"], by_turned["image2"]) and first["camera"].K.tolist() == by_turned["camera"].K.tolist()
    torch.testing.assert_close(first["relative_pose"], by_turned["relative_pose"], rtol=0, atol=1e-12)
    assert first["flow"] is None and first["valid"] is None  # (no ground truth is composed)
    # the next pair starts with the frame the first ended with, turned alike
    second = rr.slalomed({**pair, "image1": pair["image2"], "image2": pair["image1"], "positions": (1, 2)}, A, P, window)
    assert torch.equal(second["image1"], first["image2"])
    # its pose: turned by the headings' difference; the step's length, y_d and the attitude changes kept
    cam = pair["camera"].to(torch.float64)
    before = plane_from_pose(pair["relative_pose"][None].double(), cam)
    after = plane_from_pose(second["relative_pose"][None].double(), second["camera"].to(torch.float64))
    turn = math.radians(rr.slalom_yaw(2, A, P) - rr.slalom_yaw(1, A, P))
    assert float(after["yaw"] - before["yaw"]) == pytest.approx(turn, abs=1e-9)
    assert float(after["x_d"].hypot(after["z_d"])) == pytest.approx(float(before["x_d"].hypot(before["z_d"])), abs=1e-9)
    for k in ("y_d", "pitch_change", "roll_change"):
        assert float(after[k]) == pytest.approx(float(before[k]), abs=1e-9)
    # turns that leave no window: named
    with pytest.raises(rr.UnfitOption, match="--slalom"):
        rr.slalom_window(pair["camera"], (96, 64), 9, 20.0, 8.0)


def test_clip_steps_take_the_frames_these_many_apart_in_turn(rr, scenes, tmp_path):
    """``steps``: pairs (0, 1), (1, 1) (a frame repeated: a stop) and (1, 2) of the tiny clip, its
    frames as written, each pair's poses by its frames (identity where it repeats one), and its
    places in the clip; frames beyond the clip are refused, naming ``steps``."""
    from fsof_torch import read_image

    _tiny_clip(scenes, tmp_path)
    clip = tmp_path / "data" / "kitti_odometry_straight"
    frames = [read_image(clip / "image_l" / f"{i:06d}.png") for i in range(3)]
    pairs = rr.odometry_clip(clip, 1.65, 0.0, steps=[1, 0, 1])
    assert [name for name, _ in pairs] == ["0:000000-000001", "1:000001-000001", "2:000001-000002"]
    p0, p1 = scenes
    for (_, load), (a, b) in zip(pairs, ((0, 1), (1, 1), (1, 2))):
        pair = load()
        assert torch.equal(pair["image1"], frames[a]) and torch.equal(pair["image2"], frames[b])
        assert pair["positions"] == (a, b)
        if b < 2:  # (frame 2 has no pose)
            poses = (p0["pose1"], p0["pose2"])
            expected = torch.linalg.inv(poses[b]) @ poses[a]
            torch.testing.assert_close(pair["relative_pose"].double(), expected.double(), rtol=0, atol=1e-9)
        else:
            assert pair["relative_pose"] is None
    with pytest.raises(ValueError, match="steps"):
        rr.odometry_clip(clip, 1.65, 0.0, steps=[1, 2])


def test_main_steps_names_them_and_fits_the_clip(rr, scenes, tmp_path, capsys):
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--steps", "1,0,1")
    assert "3 pair(s), frames 1,0,1 apart in turn" in printed
    assert report["steps"] == [1, 0, 1]
    assert "refiner, clip motion (fit_sequence)" in {r["method"] for r in report["clip"]["rows"]}
    assert [p["pair"] for p in report["clip"]["pairs"]] == ["0:000000-000001", "1:000001-000001", "2:000001-000002"]
    with pytest.raises(SystemExit) as exit_:  # (frames beyond the clip's three)
        rr.main(["--data", str(tmp_path / "data"), "--steps", "2,1", "--no-progress"])
    assert exit_.value.code == 2 and "--steps: expected frames at most 2 apart" in capsys.readouterr().err


def test_main_slalom_keeps_the_clip_fit(rr, scenes, tmp_path, capsys):
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--slalom", "4", "6")
    assert "2 pair(s), the camera yawing back and forth by 4° over 6 frames" in printed
    assert report["slalom"] == [4.0, 6.0]
    assert "refiner, clip motion (fit_sequence)" in {r["method"] for r in report["clip"]["rows"]}


def test_main_turned_with_and_without_the_screen_of_turns(rr, scenes, tmp_path, capsys):
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--yaw-deg", "4", "--no-turn-screen")
    assert "2 pair(s), turned by 4° of yaw" in printed
    assert report["yaw_deg"] == 4.0
    # turned, image 2 of a pair is not image 1 of the next: no clip fit
    assert {r["method"] for r in report["clip"]["rows"]} == {"DIS", "refiner (no odometry)", *rr.TURN_ROWS,
                                                            "refiner, poses ('plane')", "refiner, poses (paper's planar)",
                                                            "refiner, poses (paper's planar) as priors"}
    assert rr.main(["--data", str(tmp_path / "data"), "--pitch-change-deg", "1", "--roll-change-deg", "-0.5",
                    "--no-ecc", "--no-progress", "--pairs", "1", "--no-prior-retry"]) == 0
    printed = capsys.readouterr().out
    assert "1 pair(s), turned by 1° of pitch, -0.5° of roll" in printed
    assert "| refiner, retry_without_prior=False | 1 |" in printed
    # a pitch change that leaves no window of image 2 defined (at most a fifth of the rows cut at the
    # top and at the bottom; 4 degrees leave one at this camera): exit 2 before any work, no traceback
    assert rr.main(["--data", str(tmp_path / "data"), "--pitch-change-deg", "6", "--no-ecc", "--no-progress"]) == 2
    said = capsys.readouterr()
    assert "error: --yaw-deg, --pitch-change-deg, --roll-change-deg: the turn (0.0°, 6.0°, 0.0°) leaves no window " \
           "of image 2 defined" in said.err and "| DIS |" not in said.out
    for flag, value in (("--yaw-deg", "50"), ("--pitch-change-deg", "nan"), ("--roll-change-deg", "-45")):
        with pytest.raises(SystemExit) as exit_:
            rr.main(["--data", str(tmp_path / "data"), flag, value])
        assert exit_.value.code == 2 and f"{flag}: expected a number of degrees within (-45, 45), got" in \
            capsys.readouterr().err


def test_reversed_pair_swaps_the_frames_inverts_the_pose_and_drops_the_forward_truth(rr, pair):
    before = {k: pair[k].clone() for k in ("image1", "image2", "relative_pose")}
    out = rr.reversed_pair(pair)
    assert out["image1"] is pair["image2"] and out["image2"] is pair["image1"]
    assert out["flow"] is None and out["valid"] is None and out["road"] is pair["road"]
    assert torch.allclose(out["relative_pose"] @ pair["relative_pose"].double(), torch.eye(4, dtype=torch.float64),
                          atol=1e-12)
    for k, v in before.items():
        assert torch.equal(pair[k], v)  # the caller's pair is left as it was
    assert rr.reversed_pair({**pair, "relative_pose": None})["relative_pose"] is None


def test_mirrored_pair_is_the_street_seen_from_its_other_side(rr, pair):
    """Mirrored, the pair's ground truth is the mirrored camera's road flow under the mirrored
    pose (as the original's is the original camera's), its pose's lateral step, yaw and roll
    change turn over, and mirroring twice gives the pair back; the caller's pair is left alone."""
    from fsof_torch import plane_from_pose, road_flow

    before = {k: pair[k].clone() for k in ("image1", "image2", "road", "flow", "valid", "relative_pose")}
    out = rr.mirrored(pair)
    for k, v in before.items():
        assert torch.equal(pair[k], v), k
    W = pair["image1"].shape[-1]
    assert torch.equal(out["image1"], pair["image1"].flip(-1)) and torch.equal(out["road"], pair["road"].flip(-1))
    assert torch.equal(out["flow"][0], -pair["flow"][0].flip(-1)) and torch.equal(out["flow"][1], pair["flow"][1].flip(-1))
    assert float(out["camera"].K[0, 0, 2]) == (W - 1) - float(pair["camera"].K[0, 0, 2])
    assert float(out["camera"].roll[0]) == -float(pair["camera"].roll[0])
    cams = [p["camera"].to(torch.float64) for p in (pair, out)]
    motions = [plane_from_pose(p["relative_pose"][None].double(), c) for p, c in zip((pair, out), cams)]
    for k, v in motions[0].items():
        sign = -1.0 if k in ("yaw", "roll_change", "x_d", "roll") else 1.0
        assert abs(float(motions[1][k]) - sign * float(v)) < 1e-12, k
    # the model flow of each pose through each camera matches each pair's ground truth alike
    errors = []
    for p, c, m in zip((pair, out), cams, motions):
        flow, valid = road_flow(c, m, tuple(p["image1"].shape[-2:]), model="plane")
        on = p["road"] & p["valid"] & valid[0]
        errors.append((flow[0] - p["flow"]).norm(dim=0)[on[0]])
    assert float(errors[0].mean()) < 0.05
    assert torch.allclose(errors[0].sort().values, errors[1].sort().values, atol=1e-4)
    twice = rr.mirrored(out)
    for k in before:
        assert torch.allclose(twice[k].double(), pair[k].double(), atol=1e-12), k
    assert torch.equal(twice["camera"].K, pair["camera"].K) and torch.equal(twice["camera"].roll, pair["camera"].roll)
    assert rr.mirrored({**pair, "flow": None, "valid": None, "relative_pose": None})["flow"] is None


def test_main_mirrored_says_so_and_records_it(rr, scenes, tmp_path, capsys, monkeypatch):
    seen = []
    mirrored = rr.mirrored
    monkeypatch.setattr(rr, "mirrored", lambda pair: seen.append(pair["image1"].shape) or mirrored(pair))
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--mirror")
    assert "2 pair(s), mirrored left to right" in printed and report["mirror"] is True
    assert len(seen) >= 2  # (every pair loaded through it)


def test_grown_gives_the_methods_a_looser_or_tighter_mask_and_the_figures_stay_on_the_road(rr, pair):
    """``grown`` adds a ``mask`` (the polygon dilated or eroded by a disc), leaves the road polygon
    and the caller's pair alone; the methods get it, the road figures stay over the polygon, and
    the census (and EPE) in the mask beyond the road are reported."""
    road = pair["road"].clone()
    wide, narrow = rr.grown(pair, 4), rr.grown(pair, -2)
    assert torch.equal(pair["road"], road) and "mask" not in pair and "mask" not in rr.grown(pair, 0)
    assert torch.equal(wide["road"], road) and bool((wide["mask"] >= road).all()) and bool((wide["mask"] & ~road).any())
    assert bool((narrow["mask"] <= road).all()) and bool((road & ~narrow["mask"]).any())
    assert rr.given_mask(wide) is wide["mask"] and rr.given_mask(pair) is pair["road"]
    with pytest.raises(rr.EmptyMask, match=r"^--mask-grow: a road polygon shrunk by 200 px is empty"):
        rr.grown(pair, -200)
    dis = pair["flow"] + 1.0
    errors = rr.road_errors(wide, pair["flow"], dis)
    on_road = rr.road_errors(pair, pair["flow"], dis)
    # (the census windows at the polygon's edge see the flow beyond it: here the true one, not DIS's)
    assert errors["epe"] == on_road["epe"] and errors["census"] <= on_road["census"]
    assert errors["ring_epe"] == pytest.approx(0.0, abs=1e-6) and 0.0 <= errors["ring_census"] <= 1.0
    assert "ring_census" not in on_road
    # no ground truth beyond the road: no EPE there (not an empty mean of 0)
    only_road = rr.road_errors({**wide, "valid": pair["valid"] & road}, pair["flow"], dis)
    assert "ring_epe" not in only_road and "ring_census" in only_road
    # shrunk, the road outside the mask keeps DIS's flow (1.41 px off)
    assert rr.road_errors(narrow, pair["flow"], dis)["epe"] > on_road["epe"] + 0.1


def test_main_with_a_grown_mask_says_so_and_reports_beyond_the_road(rr, scenes, tmp_path, capsys):
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--mask-grow", "6", "--no-sequence")
    assert "2 pair(s), the methods given the polygon grown by 6 px" in printed and report["mask_grow"] == 6
    assert "in the mask beyond the road: census" in printed
    assert all("ring_census" in r for r in report["clip"]["rows"] if r["method"] != "DIS")
    # grown last, from the polygon as resized (or turned)
    assert rr.main(["--data", str(tmp_path / "data"), "--mask-grow", "3", "--resize", "0.5", "--yaw-deg", "2",
                    "--no-ecc", "--no-progress"]) == 0
    assert "grown by 3 px, turned by 2° of yaw, resized by 0.5" in capsys.readouterr().out
    # a polygon shrunk to nothing is refused before any work
    assert rr.main(["--data", str(tmp_path / "data"), "--mask-grow", "-100", "--no-ecc", "--no-progress"]) == 2
    said = capsys.readouterr()
    assert "error: --mask-grow: a road polygon shrunk by 100 px is empty" in said.err and "| DIS |" not in said.out
    with pytest.raises(SystemExit) as exit_:
        rr.main(["--data", str(tmp_path / "data"), "--mask-grow", "101"])
    assert exit_.value.code == 2 and "--mask-grow: expected at most 100 pixels either way, got 101" in \
        capsys.readouterr().err


def test_the_roll_given_reaches_both_data_sets_cameras(rr, scenes, tmp_path, capsys, monkeypatch):
    """``--roll-deg`` is the camera roll the refiner is given, on the clip (and the KITTI pair,
    through the same dataset option); out of (-45, 45) it is refused before any work."""
    given = []
    clip = rr.odometry_clip
    monkeypatch.setattr(rr, "odometry_clip", lambda *a, **k: given.append(a[4:] or k["roll_deg"]) or clip(*a, **k))
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--roll-deg", "1.5", "--no-sequence")
    assert given == [(1.5,)]  # (main hands the roll to the clip's loader)
    pairs = rr.odometry_clip(tmp_path / "data" / "kitti_odometry_straight", 1.65, 0.5, roll_deg=-2.0)
    cam = pairs[0][1]()["camera"]
    assert float(cam.roll[0]) == pytest.approx(math.radians(-2.0)) and float(cam.pitch[0]) == pytest.approx(
        math.radians(0.5))
    assert report["options"]["roll_deg"] == 1.5 and "| refiner (no odometry) | 2 |" in printed
    for bad in ("45", "nan"):
        with pytest.raises(SystemExit) as exit_:
            rr.main(["--data", str(tmp_path / "data"), "--roll-deg", bad])
        assert exit_.value.code == 2 and "--roll-deg: expected a number of degrees within (-45, 45), got" in \
            capsys.readouterr().err


def test_the_roll_given_reaches_the_kitti_pairs_camera(rr, shared_data):
    pair = rr.kitti15(shared_data / "kitti15_000000", 1.4, roll_deg=2.5)[0][1]()
    assert float(pair["camera"].roll[0]) == pytest.approx(math.radians(2.5))
    assert float(pair["camera"].height[0]) == pytest.approx(1.4)


def test_cropped_pair_is_the_same_motion_seen_through_a_window(rr, pair):
    """``cropped``: frames, road, ground truth sliced, the principal point moved; the true road
    motion through the cropped camera still gives the cropped ground truth; a crop leaving nothing
    is refused, naming the option; the caller's pair is left alone."""
    from fsof_torch import plane_from_pose, road_flow

    before = pair["image1"].clone()
    out = rr.cropped(pair, 10, 6, 20, 4)
    H, W = SIZE
    assert torch.equal(pair["image1"], before)
    for key in ("image1", "image2", "road", "flow", "valid"):
        assert torch.equal(out[key], pair[key][..., 10:H - 6, 20:W - 4]), key
    K, K0 = out["camera"].K[0], pair["camera"].K[0]
    assert float(K[0, 2]) == float(K0[0, 2]) - 20 and float(K[1, 2]) == float(K0[1, 2]) - 10
    cam = out["camera"].to(torch.float64)
    flow, valid = road_flow(cam, plane_from_pose(out["relative_pose"][None].double(), cam), (H - 16, W - 24),
                            model="plane")
    on = (out["road"] & out["valid"] & valid[0])[0]
    assert float((flow[0] - out["flow"]).norm(dim=0)[on].mean()) < 0.05
    with pytest.raises(rr.UnfitOption, match=r"^--crop: 50 \+ 46 rows or 0 \+ 0 columns leave nothing"):
        rr.cropped(pair, 50, 46, 0, 0)
    # a window beside the polygon (columns 60 to 205): every figure over the road would read 0
    with pytest.raises(rr.UnfitOption, match=r"^--crop: the window of rows 0 to 95 and columns 210 to 319 of a "
                                             r"96 x 320 frame holds none of the road polygon"):
        rr.cropped(pair, 0, 0, 210, 0)
    assert bool(rr.cropped(pair, 0, 0, 200, 0)["road"].any())  # (the polygon's last columns kept)


def test_main_with_a_crop_says_so_and_refuses_one_leaving_nothing(rr, scenes, tmp_path, capsys):
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--crop", "8", "4", "0", "10", "--no-sequence")
    assert "2 pair(s), cut by 8 / 4 / 0 / 10 px at the top / bottom / left / right" in printed
    assert report["crop"] == [8, 4, 0, 10]
    assert rr.main(["--data", str(tmp_path / "data"), "--crop", "60", "40", "0", "0", "--no-ecc", "--no-progress"]) == 2
    said = capsys.readouterr()
    assert "error: --crop: 60 + 40 rows or 0 + 0 columns leave nothing of a 96 x 320 frame" in said.err
    assert "| DIS |" not in said.out
    assert rr.main(["--data", str(tmp_path / "data"), "--crop", "0", "0", "210", "0", "--no-ecc", "--no-progress"]) == 2
    said = capsys.readouterr()
    assert "error: --crop: the window of rows 0 to 95 and columns 210 to 319 of a 96 x 320 frame holds none of " \
           "the road polygon" in said.err and "| DIS |" not in said.out
    with pytest.raises(SystemExit) as exit_:
        rr.main(["--data", str(tmp_path / "data"), "--crop", "0", "-1", "0", "0"])
    assert exit_.value.code == 2 and "--crop: expected pixels >= 0 at each side, got 0 -1 0 0" in \
        capsys.readouterr().err


def test_compressed_pair_is_the_frames_through_a_jpeg_encoder(rr, pair):
    """``compressed``: both frames through OpenCV's JPEG encoder and decoder (RGB and grey), the
    rest of the pair as it was; lower quality strays further from the frames; the caller's pair
    is left alone."""
    import cv2

    before = pair["image1"].clone()
    fine, coarse = rr.compressed(pair, 95), rr.compressed(pair, 20)
    assert torch.equal(pair["image1"], before) and fine["flow"] is pair["flow"] and fine["road"] is pair["road"]
    for out in (fine, coarse):
        assert out["image1"].shape == pair["image1"].shape and out["image1"].dtype == pair["image1"].dtype
    error = lambda out: float((out["image2"] - pair["image2"].round()).abs().mean())  # noqa: E731
    assert 0 < error(fine) < error(coarse)
    # the same bytes as OpenCV's own round trip (BGR order on the way)
    a = pair["image1"].round().to(torch.uint8).permute(1, 2, 0).numpy()[..., ::-1]
    _, data = cv2.imencode(".jpg", np.ascontiguousarray(a), [cv2.IMWRITE_JPEG_QUALITY, 20])
    ref = torch.from_numpy(np.ascontiguousarray(cv2.imdecode(data, cv2.IMREAD_UNCHANGED)[..., ::-1])).permute(2, 0, 1)
    assert torch.equal(coarse["image1"], ref.to(pair["image1"].dtype))
    grey = rr.compressed({**pair, "image1": pair["image1"][:1], "image2": pair["image2"][:1]}, 50)
    assert grey["image1"].shape == (1, *SIZE)


def test_main_with_jpeg_frames_says_so_and_checks_the_quality(rr, scenes, tmp_path, capsys):
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--jpeg", "60", "--no-sequence")
    assert "2 pair(s), stored as JPEG at quality 60" in printed and report["jpeg"] == 60
    for bad in ("0", "101"):
        with pytest.raises(SystemExit) as exit_:
            rr.main(["--data", str(tmp_path / "data"), "--jpeg", bad])
        assert exit_.value.code == 2 and f"--jpeg: expected a quality within [1, 100], got {bad}" in \
            capsys.readouterr().err


def test_the_model_flows_own_error_is_reported_wherever_the_estimate_succeeded(rr, pair):
    """A method whose estimate succeeded but whose flow the gate turned down everywhere still
    reports its model flow's own road error; one whose estimate failed does not."""
    truth = pair["flow"].clone()

    def method(estimated):
        return (None, lambda p, dis: (dis, {"refined": False, "estimated": estimated, "model_flow": truth}))

    results = rr.run_pair(pair, {"kept": method(True), "failed": method(False)})
    assert results["kept"]["epe_model"] == pytest.approx(0.0, abs=1e-6) and "epe_model" not in results["failed"]
    assert "estimated" not in results["kept"] and "model_flow" not in results["kept"]


def test_main_reversed_runs_the_clip_last_to_first(rr, scenes, tmp_path, capsys):
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--reverse", "--no-reverse-screen")
    assert "2 pair(s), frames swapped (the backward flow)" in printed
    assert report["reverse"] is True
    # last to first: image 2 of a pair is image 1 of the next, so the clip's fit runs
    assert [p["pair"] for p in report["clip"]["pairs"]] == ["000001", "000000"]
    methods = {r["method"] for r in report["clip"]["rows"]}
    assert {"refiner, reverse_starts=()", "refiner, clip motion (fit_sequence)"} <= methods
    assert all("epe" not in r for r in report["clip"]["rows"])


def test_exposed_scales_image_2_as_an_8_bit_camera_records_it(rr, pair):
    out = rr.exposed(pair, 1.5)
    expected = torch.clamp(pair["image2"].to(torch.float64) * 1.5, 0, 255).round()
    assert torch.equal(out["image2"].to(torch.float64), expected) and out["image2"].dtype == pair["image2"].dtype
    assert out["image1"] is pair["image1"] and out["flow"] is pair["flow"]
    assert float(out["image2"].max()) == 255.0  # bright texture saturates
    before = pair["image2"].clone()
    rr.exposed(pair, 0.5)
    assert torch.equal(pair["image2"], before)  # the caller's pair is left as it was


def test_resized_pair_averages_the_ground_truth_over_each_new_pixel(rr, pair):
    """--resize: a linear flow field's mean over a 2 x 2 block is its value at the block's centre,
    which is the new pixel's centre; a block with fewer than half of its pixels valid is not
    valid, one with half averages those only."""
    rows, cols = SIZE
    v, u = torch.meshgrid(torch.arange(rows, dtype=torch.float64), torch.arange(cols, dtype=torch.float64),
                          indexing="ij")
    flow = torch.stack([0.5 + 0.02 * u - 0.01 * v, -1.0 + 0.03 * v + 0.005 * u]).to(torch.float32)
    valid = torch.ones(1, rows, cols, dtype=torch.bool)
    valid[0, 10, 20] = valid[0, 10, 21] = valid[0, 11, 20] = False  # block (5, 10): 1 of 4 valid
    valid[0, 20, 40] = valid[0, 21, 41] = False  # block (10, 20): 2 of 4, (20, 41) and (21, 40)
    flow[:, 20, 40] = flow[:, 21, 41] = 1e4  # (what invalid pixels hold must not count)
    given = {**pair, "flow": flow, "valid": valid}
    before = {k: given[k].clone() for k in ("image1", "image2", "road", "flow", "valid")}
    out = rr.resized(given, 0.5)
    for k, t in before.items():
        assert torch.equal(given[k], t)  # the caller's pair is left as it was
    h, w = rows // 2, cols // 2
    assert out["image1"].shape == (3, h, w) and out["road"].shape == (1, h, w) and out["flow"].shape == (2, h, w)
    vv, uu = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    uc, vc = 2 * uu + 0.5, 2 * vv + 0.5  # the new pixel's centre in the old pixels
    expected = 0.5 * torch.stack([0.5 + 0.02 * uc - 0.01 * vc, -1.0 + 0.03 * vc + 0.005 * uc])
    ok = out["valid"][0]
    assert not bool(ok[5, 10]) and bool(ok[10, 20]) and int((~ok).sum()) == 1
    assert torch.allclose(out["flow"].to(torch.float64)[:, ok], expected[:, ok], atol=1e-4)
    old = flow.to(torch.float64)[:, [20, 21], [41, 40]].mean(1)  # the two valid pixels of block (10, 20)
    assert torch.allclose(out["flow"][:, 10, 20].to(torch.float64), 0.5 * old, atol=1e-4)
    # the frames: block means rounded to 8 bits, the dtype kept; the road where half a block is
    im = pair["image1"].to(torch.float64).reshape(3, h, 2, w, 2).mean((2, 4))
    assert (out["image1"].to(torch.float64) - im).abs().max() <= 0.5 + 1e-4 and out["image1"].dtype == pair["image1"].dtype
    assert torch.equal(out["image1"], out["image1"].round())
    share = pair["road"].to(torch.float64).reshape(1, h, 2, w, 2).mean((2, 4))
    assert torch.equal(out["road"], share >= 0.5)
    # the camera as Camera.scaled gives it (its own tests check the convention)
    assert torch.equal(out["camera"].K, pair["camera"].scaled(0.5).K)
    without = rr.resized({k: x for k, x in pair.items() if k not in ("flow", "valid")}, 0.5)
    assert "flow" not in without and without["image2"].shape == (3, h, w)


def test_main_resized(rr, scenes, tmp_path, capsys):
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--resize", "0.75")
    assert "2 pair(s), resized by 0.75 (EPE in its pixels)" in printed
    assert report["resize"] == 0.75
    # resized alike, the frames still make a clip
    assert "refiner, clip motion (fit_sequence)" in {r["method"] for r in report["clip"]["rows"]}
    for value in ("0", "nan", "1.5"):
        with pytest.raises(SystemExit) as exit_:
            rr.main(["--data", str(tmp_path / "data"), "--resize", value])
        assert exit_.value.code == 2 and "--resize: expected a factor within [0.1, 1], got" in capsys.readouterr().err


def test_odometry_error_scales_the_translation_and_shifts_the_yaw(rr, pair):
    """--odometry-error SCALE YAW_DEG: both forms of the poses' odometry, translation SCALE times as
    long and yaw YAW_DEG degrees more, the rest as measured."""
    wrong = {**pair, "odometry_error": (1.03, -0.2)}
    plane, plane_wrong = rr.plane_odometry(pair), rr.plane_odometry(wrong)
    for k in ("x_d", "y_d", "z_d"):
        assert float(plane_wrong[k]) == pytest.approx(1.03 * float(plane[k]), rel=1e-12)
    assert float(plane_wrong["yaw"] - plane["yaw"]) == pytest.approx(math.radians(-0.2), abs=1e-12)
    for k in ("pitch_change", "roll_change", "pitch", "roll"):
        assert torch.equal(plane_wrong[k], plane[k])
    ego, ego_wrong = rr.paper_odometry(pair), rr.paper_odometry(wrong)
    assert float(ego_wrong.z_d) == pytest.approx(1.03 * float(ego.z_d), rel=1e-12)
    assert float(ego_wrong.x_d) == pytest.approx(1.03 * float(ego.x_d), rel=1e-12)
    assert float(ego_wrong.yaw - ego.yaw) == pytest.approx(math.radians(-0.2), abs=1e-12)


def test_images_against_poses_over_the_pairs_both_refined(rr):
    images, poses = "refiner (no odometry)", "refiner, poses (paper's planar)"

    def pair(z_images, yaw_images, z_poses, yaw_poses, refined=True):
        return {images: {"refined": True, "motion": {"z_d": z_images, "yaw_deg": yaw_images}},
                poses: {"refined": refined, "motion": {"z_d": z_poses, "yaw_deg": yaw_poses}}}

    per_pair = [pair(1.2, 0.1, 1.0, 0.0), pair(0.9, -0.2, 1.0, 0.1), pair(3.0, 5.0, 1.0, 0.0, refined=False),
                {images: {"refined": True, "motion": {"z_d": 1.0, "yaw_deg": 0.0}}}]
    assert rr.images_against_poses(per_pair) == (
        "The images against the poses (2 pairs): forward step x 0.900 to 1.200 (median 1.050); yaw -0.300° to "
        "+0.100° a frame (median |difference| 0.200°)")
    assert rr.images_against_poses(per_pair[2:]) is None


def test_main_with_wrong_odometry(rr, scenes, tmp_path, capsys):
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--odometry-error", "1.05", "0.3",
                                         "--no-sequence")
    assert "odometry's steps 1.05 times as long and its yaw +0.3° a frame off" in printed
    assert report["odometry_error"] == [1.05, 0.3]
    rows = {r["method"]: r for r in report["clip"]["rows"]}
    assert rows["refiner, poses (paper's planar) as priors"]["pairs"] == 1
    for value in (["0.4", "0"], ["1", "nan"], ["1", "50"]):
        with pytest.raises(SystemExit) as exit_:
            rr.main(["--data", str(tmp_path / "data"), "--odometry-error", *value])
        assert exit_.value.code == 2 and "--odometry-error: expected a scale within [0.5, 2]" in capsys.readouterr().err


def test_main_with_an_exposure_change(rr, scenes, tmp_path, capsys):
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--exposure-gain", "0.6")
    assert "2 pair(s), image 2 0.6 times as bright" in printed
    assert report["exposure_gain"] == 0.6
    # image 2 of a pair is not image 1 of the next: no clip fit
    assert "refiner, clip motion (fit_sequence)" not in {r["method"] for r in report["clip"]["rows"]}
    refined = [p["refiner (no odometry)"]["refined"] for p in report["clip"]["pairs"]]
    assert all(refined)  # census and the fit's gain do not mind the darker image 2
    for value in ("0", "nan", "11"):
        with pytest.raises(SystemExit) as exit_:
            rr.main(["--data", str(tmp_path / "data"), "--exposure-gain", value])
        assert exit_.value.code == 2 and "--exposure-gain: expected a factor within [0.1, 10], got" in \
            capsys.readouterr().err


def test_a_false_fit_success_is_caught_by_the_gate(rr, shared_data):
    """Frame 32 of the clip with image 2 pitched by -2° (a hard jolt), cut to rows 0-334 and
    columns 5-1221, from the planar motion of DIS's flow there (8 m ahead; written out): with the
    fit's ways on from a weak success switched off, the image fit reports success at a motion far
    ahead of the true 1.2 m, its detail correlating only weakly (above the bar of 0.5, far below a
    right fit's 0.95). The gate finds that the model explains the road's census worse than DIS and
    keeps DIS: the refined road is no worse than DIS's. The default refiner finds the motion (its
    runners-up) and refines the road clearly."""
    from fsof_torch import ImageMotionEstimator, refine_flow
    from refine.sources import dis_flow

    folder = shared_data / "kitti_odometry_straight"
    if not folder.is_dir():
        pytest.skip("kitti_odometry_straight is absent")
    pair = dict(rr.odometry_clip(folder, 1.65, 0.0, 1))["000032"]()
    t = rr.turned(pair, 0.0, -2.0, 0.0, window=(0, 334, 5, 1221))
    dis = dis_flow(t["image1"], t["image2"])[None]
    start = {"model": "paper", "x_d": 0.16943574931974922, "z_d": 8.034197668891988, "yaw": -0.004506969879176324}
    args = (dis, t["road"][None], t["camera"])
    images = (t["image1"][None], t["image2"][None])
    alone = ImageMotionEstimator(flow_start=False, retry_starts=0, turn_starts=(), reverse_starts=(),
                                 retry_without_prior=False)
    with pytest.warns(RuntimeWarning, match="left unchanged"):
        kept = refine_flow(*args, images=images, estimator=alone, starts=(start,))
    assert bool(kept.fit.success[0]) and float(kept.fit.params["z_d"][0]) > 10.0  # the false success
    assert not bool(kept.refined[0]) and torch.equal(kept.flow, dis)
    refined = refine_flow(*args, images=images, estimator=ImageMotionEstimator(flow_start=False), starts=(start,))
    assert bool(refined.refined[0])
    census = {name: rr.road_errors(t, out.flow[0], dis[0])["census"] for name, out in (("dis", kept), ("refined", refined))}
    assert census["refined"] < census["dis"] - 0.05


def _brute_window(defined):
    """The largest window of full columns over every cut of up to a fifth of the rows, top and
    bottom (the first found of equal areas), written as a plain search."""
    rows, cols = defined.shape
    best = (0, 0, 0, 0, 0)
    for top in range(rows // 5 + 1):
        for bottom in range(rows // 5 + 1):
            full = defined[top:rows - bottom].all(0).tolist()
            for c0 in range(cols):
                c1 = c0
                while c1 < cols and full[c1]:
                    c1 += 1
                if (rows - top - bottom) * (c1 - c0) > best[0]:
                    best = ((rows - top - bottom) * (c1 - c0), top, rows - bottom, c0, c1)
    return best[1:]


@pytest.mark.parametrize("turn", [(0.001, 0.0, 0.0), (6.0, 0.0, 0.0), (-9.0, -1.5, 2.0), (0.0, 2.0, 0.0)])
def test_turned_window_is_the_largest_defined_one_cut_row_by_row(rr, pair, turn):
    """A turn bends the top and bottom rows by fractions of a pixel: the window cuts the rows that
    need it, one by one (a turn of 0.001° costs a row at each end, not a twentieth of the frame)."""
    from fsof_torch.geometry.camera import mounting_matrix

    cam = pair["camera"].to(torch.float64)
    K = cam.K.reshape(-1, 3, 3)[0]
    axes = mounting_matrix(cam.roll.reshape(-1)[:1], cam.pitch.reshape(-1)[:1])[0].T

    def rodrigues(axis: torch.Tensor, degrees: float) -> torch.Tensor:  # about a unit axis
        N = torch.tensor([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]],
                         dtype=torch.float64)
        a = math.radians(degrees)
        return torch.eye(3, dtype=torch.float64) + math.sin(a) * N + (1 - math.cos(a)) * N @ N

    Rs = [rodrigues(axes[i], turn[j]) for i, j in ((0, 1), (1, 0), (2, 2))]
    H = K @ (Rs[1] @ Rs[0] @ Rs[2]).T @ torch.linalg.inv(K)
    rows, cols = SIZE
    v, u = torch.meshgrid(torch.arange(rows, dtype=torch.float64), torch.arange(cols, dtype=torch.float64),
                          indexing="ij")
    src = torch.einsum("ij,jhw->ihw", torch.linalg.inv(H), torch.stack([u, v, torch.ones_like(u)]))
    x, y = src[0] / src[2], src[1] / src[2]
    defined = (src[2] > 0) & (x >= -1e-6) & (x <= cols - 1 + 1e-6) & (y >= -1e-6) & (y <= rows - 1 + 1e-6)
    window = rr.defined_window(defined)
    assert window == _brute_window(defined)
    r0, r1, c0, c1 = window
    assert bool(defined[r0:r1, c0:c1].all())
    t = rr.turned(pair, *turn)
    assert t["image1"].shape[-2:] == (r1 - r0, c1 - c0)
    if turn == (0.001, 0.0, 0.0):
        assert r0 <= 1 and r1 >= rows - 1


def test_turned_to_a_given_window(rr, pair):
    t = rr.turned(pair, 6.0, window=(10, 80, 0, 250))
    assert t["image1"].shape[-2:] == t["image2"].shape[-2:] == t["road"].shape[-2:] == (70, 250)
    assert torch.equal(t["image1"], pair["image1"][..., 10:80, 0:250])
    with pytest.raises(ValueError, match="window"):
        rr.turned(pair, 6.0, window=(0, 96, 0, 320))  # (its right columns are not defined)


def test_turned_window_of_nothing_defined_is_empty(rr):
    assert rr.defined_window(torch.zeros(20, 30, dtype=torch.bool)) == (0, 0, 0, 0)
    defined = torch.ones(20, 30, dtype=torch.bool)
    defined[:, 10] = False  # (a column undefined in the middle rows too)
    defined[0, :] = False
    assert rr.defined_window(defined) == _brute_window(defined) == (1, 20, 11, 30)


def test_main_adds_a_row_per_estimator_given(rr, scenes, tmp_path, capsys, monkeypatch):
    """``--estimator OPTIONS``: a row more each, the refiner with ``ImageMotionEstimator(**OPTIONS)``;
    with no options the row is the default refiner's."""
    given = []
    refiner_flow = rr.refiner_flow
    monkeypatch.setattr(rr, "refiner_flow", lambda pair, dis, odometry=None, **options:
                        given.append(options) or refiner_flow(pair, dis, odometry, **options))
    printed, report = _main_on_tiny_clip(rr, scenes, tmp_path, capsys, "--no-sequence", "--estimator", "{}",
                                         "--estimator", '{"smooth_sigma": 1.0}')
    rows = {r["method"]: r for r in report["clip"]["rows"]}
    assert '| refiner, {"smooth_sigma": 1.0} | 2 |' in printed
    assert rows["refiner, {}"]["census"] == rows["refiner (no odometry)"]["census"]
    assert {"smooth_sigma": 1.0} in given and report["options"]["estimator"] == [{}, {"smooth_sigma": 1.0}]


def test_main_refuses_folders_the_library_cannot_read(rr, scenes, tmp_path, capsys):
    """A folder the library cannot read exits 2 with the option that named it and the library's
    message, never a traceback: a clip's calibration without P0, a pair's frames of another size
    than its calibration's S_rect, a clip whose later frame has another size (found as it runs),
    a poses.txt with no line for any of the clip's frames, a road polygon that covers no pixel of
    the frames."""
    from fsof_torch.io import write_image, write_kitti_calibration

    _tiny_clip(scenes, tmp_path)
    clip = tmp_path / "data" / "kitti_odometry_straight"
    run = ["--no-ecc", "--no-sequence", "--no-progress"]
    calib = (clip / "calib.txt").read_text()
    write_kitti_calibration(clip / "calib.txt", scenes[0]["camera"].K[0], cam=2, style="cam_to_cam")
    assert rr.main(["--clip", str(clip), *run]) == 2
    assert f"error: --clip: calib: {str(clip / 'calib.txt')!r} has no P_rect_00 or P0 row" in capsys.readouterr().err
    (clip / "calib.txt").write_text(calib)
    pair = tmp_path / "pair"
    pair.mkdir()
    write_image(pair / "image_10.png", scenes[1]["image1"])
    write_image(pair / "image_11.png", scenes[1]["image2"])
    write_kitti_calibration(pair / "calib_cam_to_cam.txt", scenes[1]["camera"].K[0], cam=2)
    with open(pair / "calib_cam_to_cam.txt", "a") as f:  # (the calibration of frames 4 rows taller)
        f.write(f"S_rect_02: {SIZE[1]} {SIZE[0] + 4}\n")
    (pair / "road.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": POLYGON}))
    assert rr.main(["--pair", str(pair), *run]) == 2
    assert f"error: --pair: images: image_10.png is {SIZE[0]}x{SIZE[1]} but the calibration" in capsys.readouterr().err
    # the second pair's frame cut: the first pair loads, the run stops at the second
    write_image(clip / "image_l" / "000002.png", scenes[1]["image2"][..., :-8, :])
    assert rr.main(["--clip", str(clip), *run]) == 2
    printed = capsys.readouterr()
    assert f"error: --clip: images: 000002.png is {SIZE[0] - 8}x{SIZE[1]} but 000000.png" in printed.err
    assert "Traceback" not in printed.err and "| DIS |" not in printed.out
    # a road polygon that covers no pixel of the frames (drawn for other frames): every figure over
    # the road would read 0 (census 0.0000, EPE 0.00 px, over no pixel)
    write_image(clip / "image_l" / "000002.png", scenes[1]["image2"])
    (clip / "road.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": [[400, 10], [450, 10], [450, 60]]}))
    assert rr.main(["--clip", str(clip), *run]) == 2
    printed = capsys.readouterr()
    assert f"error: --clip: road.json: its road polygon covers no pixel of the {SIZE[0]} x {SIZE[1]} frames" in \
        printed.err and "| DIS |" not in printed.out


def test_main_refuses_poses_that_have_no_line_for_the_clips_frames(rr, scenes, tmp_path, capsys):
    """Frames numbered from their place in a sequence with poses.txt cut to the clip: no frame has
    its line, and the methods that need poses would be left out unsaid; exits 2 naming poses.txt."""
    _tiny_clip(scenes, tmp_path)
    clip = tmp_path / "data" / "kitti_odometry_straight"
    for old in (2, 1, 0):
        (clip / "image_l" / f"{old:06d}.png").rename(clip / "image_l" / f"{old + 100:06d}.png")
    with pytest.raises(ValueError, match=r"^poses: .* has 2 poses \(line n for frame NNNNNN = n\), none for the "
                                         r"clip's frames 000100.png to 000102.png"):
        rr.odometry_clip(clip, 1.65, 0.0)
    assert rr.main(["--clip", str(clip), "--no-ecc", "--no-sequence", "--no-progress"]) == 2
    assert f"error: --clip: poses: {str(clip / 'poses.txt')!r} has 2 poses" in capsys.readouterr().err
    (clip / "image_l" / "000100.png").rename(clip / "image_l" / "000001.png")  # (frame 1 has a pose: runs)
    assert len(rr.odometry_clip(clip, 1.65, 0.0)) == 2
