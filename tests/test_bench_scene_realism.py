"""``benchmarks/scene_realism.py`` on real samples of the user's own (``--data``): road.json read
as the library reads it, and a sample it cannot read refused before the rendering."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
POLYGON = [[10, 95], [150, 56.5], [195, 56], [300, 95]]


@pytest.fixture
def bench(load_benchmark, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # (its sibling modules, as when run as a script)
    return load_benchmark("scene_realism")


def test_road_json_in_any_of_the_librarys_formats(bench, tmp_path):
    """A road.json in another of the library's polygon formats is the mask the library reads (the
    refine job, real_road.py), not a KeyError; one drawn for another size is the library's
    ValueError naming it, not a polygon stretched over the frame."""
    from fsof_torch.io import read_road_mask

    size = (96, 320)
    single = tmp_path / "single.json"
    single.write_text(json.dumps({"size": list(size), "road_polygon": POLYGON}))
    listed = tmp_path / "listed.json"
    listed.write_text(json.dumps({"size": list(size), "polygons": [POLYGON]}))
    larger = tmp_path / "larger.json"
    larger.write_text(json.dumps({"size": [192, 640], "road_polygon": [[2 * u, 2 * v] for u, v in POLYGON]}))
    want = read_road_mask(single, size=size)[0].numpy()
    assert want.any() and not want.all()
    for path in (single, listed):
        got = bench._polygon(path, size)
        assert got.dtype == bool and np.array_equal(got, want)
    with pytest.raises(ValueError, match=r"larger\.json' is a polygon drawn for 192x640 images \(its 'size'\), "
                                         r"but size is 96x320"):
        bench._polygon(larger, size)


def test_a_sample_the_library_cannot_read_exits_2_naming_data(bench, tmp_path, capsys):
    """A pair whose road.json is not JSON, or whose frame OpenCV cannot read, exits 2 naming --data
    and the file, before the rendering, not a traceback."""
    from fsof_torch.data.scene import render_pair
    from fsof_torch.io import write_image, write_kitti_flow

    p = render_pair("default", 0, size=(96, 320))
    pair = tmp_path / "data" / "kitti15_000000"
    pair.mkdir(parents=True)
    write_image(pair / "image_10.png", p["image1"])
    write_image(pair / "image_11.png", p["image2"])
    write_kitti_flow(pair / "flow_noc_10.png", p["flow"], p["valid"])
    (pair / "road.json").write_text("{not json")
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--data", str(tmp_path / "data")])
    assert exit_.value.code == 2
    assert f"--data: path: {str(pair / 'road.json')!r} is not valid JSON" in capsys.readouterr().err
    (pair / "road.json").write_text(json.dumps({"size": [96, 320], "road_polygon": POLYGON}))
    (pair / "image_11.png").write_bytes(b"not a png")
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--data", str(tmp_path / "data")])
    assert exit_.value.code == 2
    assert f"--data: OpenCV cannot read {str(pair / 'image_11.png')!r} as an image" in capsys.readouterr().err
