"""The timing tables of ``benchmarks/bench_testnet.py`` and ``benchmarks/bench_scene.py`` give each
row's ratio to the reference timed in the same run (docs/benchmarks.md: read the ratios, not the
milliseconds), on tiny sizes so that the scripts run in seconds."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture
def threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)  # (the scripts set one thread)


def _table(text: str, header_word: str) -> tuple[list[str], list[list[str]]]:
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if header_word in line)
    rows = []
    for line in lines[start + 1:]:
        if not line.strip():
            break
        rows.append(line.split())
    return lines[start], rows


def test_testnet_rows_give_their_ratio_to_the_reference_convolution(load_benchmark, monkeypatch, capsys, threads):
    monkeypatch.syspath_prepend(str(BENCHMARKS))  # (cli, as when run as a script)
    bench = load_benchmark("bench_testnet")
    monkeypatch.setattr(bench, "SIZES", [(32, 64)])
    assert bench.main(["--repeats", "1", "--iters", "1"]) == 0
    header, rows = _table(capsys.readouterr().out, "forward wall ms")
    assert "x ref conv" in header
    (row,) = rows
    wall, ref, ratio = float(row[1]), float(row[4]), float(row[5])
    # (the ms are printed to 0.1, the ratio to 0.1)
    assert ratio > 0
    if ref > 0.05:
        assert (wall - 0.05) / (ref + 0.05) - 0.05 <= ratio <= (wall + 0.05) / (ref - 0.05) + 0.05


def test_scene_rows_give_their_ratio_to_dis(load_benchmark, monkeypatch, capsys, threads):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    bench = load_benchmark("bench_scene")
    assert bench.main(["--repeats", "1", "--size", "16", "48"]) == 0
    header, rows = _table(capsys.readouterr().out, "wall ms")
    assert header.split()[-1] == "DIS"  # "x DIS"
    assert len(rows) == 10
    dis = rows[-1]
    assert " ".join(dis[:5]) == "reference: OpenCV DIS medium on" and float(dis[-1]) == 1.0
    for row in rows:
        assert float(row[-1]) > 0


def test_fit_kitti_runs_opencv_on_one_thread_too(load_benchmark, monkeypatch, capsys, threads, shared_data, tmp_path):
    """Its ms column (DIS, the photometric fits) is documented as single-thread: OpenCV's too."""
    import cv2

    if not (shared_data / "kitti15_000000").is_dir():
        pytest.skip("kitti15_000000 is absent")
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    bench = load_benchmark("fit_kitti")
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        assert bench.main(["--data", str(shared_data / "kitti15_000000"), "--json", str(tmp_path / "k.json")]) == 0
        assert cv2.getNumThreads() == 1
    finally:
        cv2.setNumThreads(before)
    assert "OpenCV DIS" in capsys.readouterr().out


def test_compile_bench_runs_opencv_on_one_thread_and_cold_removes_its_cache(load_benchmark, monkeypatch, tmp_path,
                                                                           capsys, threads):
    """The refiner with images runs OpenCV (blur, pyramids): the script's "single thread" holds
    for it too, not for torch alone. And ``--cold`` compiles into a fresh cache folder, removed
    when the run ends (each run left one of tens of MB in the temporary folder). One run checks
    both (the script compiles every case: tens of seconds)."""
    import tempfile

    import cv2

    monkeypatch.syspath_prepend(str(BENCHMARKS))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    bench = load_benchmark("bench_compile")
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        assert bench.main(["--cold", "--backend", "eager", "--repeats", "1"]) == 0
        assert cv2.getNumThreads() == 1
    finally:
        cv2.setNumThreads(before)
    out = capsys.readouterr().out
    assert "odometry+images" in out and "cold cache" in out
    assert list(tmp_path.glob("fsof_inductor_*")) == []
