"""The benchmark scripts that take a KITTI 2015 pair's folder (``--data DIR``) read it as the
library's ``KittiSampleDataset`` does, before any work: frames the calibration is not for, or
ground truth of another size than the frames, a road polygon that covers no pixel of the frames,
exit 2 naming ``--data``, never a silent run or a traceback (``cli.readable_pair``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SIZE = (96, 320)
SCRIPTS = ("fit_kitti", "kitti_photometric", "fit_road_models")


@pytest.fixture
def scripts(load_benchmark, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # (their sibling modules, as when run as a script)
    return {name: load_benchmark(name) for name in SCRIPTS}


def _pair(folder: Path, calib_size: tuple[int, int] = SIZE, flow_size: tuple[int, int] = SIZE,
          polygon: list | None = None) -> Path:
    """A rendered pair in kitti15_000000's layout, its calibration for frames of ``calib_size``
    (``S_rect_02``), its ground truth of ``flow_size`` and its road ``polygon`` (default: on the
    road)."""
    from fsof_torch.data.scene import render_pair
    from fsof_torch.io import write_image, write_kitti_calibration, write_kitti_flow

    p = render_pair("default", 0, size=SIZE)
    folder.mkdir(parents=True)
    write_image(folder / "image_10.png", p["image1"])
    write_image(folder / "image_11.png", p["image2"])
    write_kitti_calibration(folder / "calib_cam_to_cam.txt", p["camera"].K[0], cam=2)
    with open(folder / "calib_cam_to_cam.txt", "a") as f:
        f.write(f"S_rect_02: {calib_size[1]} {calib_size[0]}\n")
    rows, cols = flow_size
    write_kitti_flow(folder / "flow_noc_10.png", p["flow"][:, :rows, :cols], p["valid"][:, :rows, :cols])
    polygon = [[60, 95], [150, 56], [195, 56], [205, 95]] if polygon is None else polygon
    (folder / "road.json").write_text(json.dumps({"size": list(SIZE), "road_polygon": polygon}))
    return folder


@pytest.mark.parametrize("name", SCRIPTS)
def test_a_pair_the_calibration_is_not_for_exits_2_naming_data(scripts, name, tmp_path, capsys, monkeypatch):
    bench = scripts[name]

    def no_work(*args, **kwargs):
        raise AssertionError("the script started its work")

    for work in ("load", "read_pair", "kitti_table"):  # (each script's first step on the pair)
        if hasattr(bench, work):
            monkeypatch.setattr(bench, work, no_work)
    cases = ((_pair(tmp_path / "taller", calib_size=(SIZE[0] + 4, SIZE[1])),
              f"--data: images: image_10.png is {SIZE[0]}x{SIZE[1]} but the calibration"),
             (_pair(tmp_path / "cut", flow_size=(SIZE[0] - 6, SIZE[1])),
              f"--data: gt: flow_noc_10.png is ({SIZE[0] - 6}, {SIZE[1]}), the images ({SIZE[0]}, {SIZE[1]})"),
             # a polygon beside the frames: every figure over the road a mean over no pixel
             (_pair(tmp_path / "off", polygon=[[400, 10], [450, 10], [450, 60]]),
              f"--data: road.json: its road polygon covers no pixel of the {SIZE[0]} x {SIZE[1]} frames"))
    for folder, message in cases:
        with pytest.raises(SystemExit) as exit_:
            bench.main(["--data", str(folder)] + (["--pairs", "0"] if name == "fit_road_models" else []))
        assert exit_.value.code == 2
        assert message in capsys.readouterr().err
    # a pair the library reads starts the work
    with pytest.raises(AssertionError, match="started its work"):
        bench.main(["--data", str(_pair(tmp_path / "fine"))])
