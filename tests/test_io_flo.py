"""fsof_torch.io.flo: Middlebury .flo read/write, exact, and its checks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fsof_torch.io import FLO_MAGIC, read_flo, write_flo


def _flow(h, w, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(2, h, w, generator=g) * 30


class TestSmoke:
    def test_round_trip_exact(self, tmp_path):
        flow = _flow(6, 9)
        write_flo(tmp_path / "a.flo", flow)
        back = read_flo(tmp_path / "a.flo")
        assert back.dtype == torch.float32 and back.shape == (2, 6, 9)
        assert torch.equal(back, flow)

    def test_float64_and_numpy_inputs(self, tmp_path):
        flow = _flow(3, 4).double()
        write_flo(tmp_path / "a.flo", flow.numpy())
        assert torch.equal(read_flo(tmp_path / "a.flo"), flow.float())


class TestFeature:
    def test_layout_matches_middlebury(self, tmp_path):
        """Independent reference: the byte layout written by hand with NumPy."""
        flow = _flow(2, 3)
        hwc = flow.numpy().transpose(1, 2, 0)
        with open(tmp_path / "ref.flo", "wb") as f:
            np.array([FLO_MAGIC], "<f4").tofile(f)
            np.array([3, 2], "<i4").tofile(f)
            hwc.astype("<f4").tofile(f)
        assert torch.equal(read_flo(tmp_path / "ref.flo"), flow)
        write_flo(tmp_path / "ours.flo", flow)
        assert (tmp_path / "ours.flo").read_bytes() == (tmp_path / "ref.flo").read_bytes()
        assert (tmp_path / "ours.flo").read_bytes()[:4] == b"PIEH"

    @settings(max_examples=20, deadline=None)
    @given(h=st.integers(1, 8), w=st.integers(1, 8), seed=st.integers(0, 1000))
    def test_round_trip_any_size(self, tmp_path_factory, h, w, seed):
        path = tmp_path_factory.mktemp("flo") / "a.flo"
        flow = _flow(h, w, seed)
        write_flo(path, flow)
        assert torch.equal(read_flo(path), flow)


class TestExceptions:
    def test_wrong_magic(self, tmp_path):
        write_flo(tmp_path / "a.flo", _flow(2, 2))
        data = bytearray((tmp_path / "a.flo").read_bytes())
        data[:4] = np.array([1.0], "<f4").tobytes()
        (tmp_path / "bad.flo").write_bytes(bytes(data))
        with pytest.raises(ValueError, match=r"bad\.flo.*magic number 1\.0"):
            read_flo(tmp_path / "bad.flo")

    def test_size_does_not_match_length(self, tmp_path):
        write_flo(tmp_path / "a.flo", _flow(4, 5))
        data = (tmp_path / "a.flo").read_bytes()
        (tmp_path / "short.flo").write_bytes(data[:-8])
        (tmp_path / "long.flo").write_bytes(data + b"\x00" * 4)
        for name in ("short.flo", "long.flo"):
            with pytest.raises(ValueError, match=rf"{name}.*header declares 5x4"):
                read_flo(tmp_path / name)

    def test_too_short_and_bad_size(self, tmp_path):
        (tmp_path / "tiny.flo").write_bytes(b"PIEH")
        with pytest.raises(ValueError, match="too short"):
            read_flo(tmp_path / "tiny.flo")
        header = np.array([FLO_MAGIC], "<f4").tobytes() + np.array([-3, 2], "<i4").tobytes()
        (tmp_path / "neg.flo").write_bytes(header)
        with pytest.raises(ValueError, match="positive sides"):
            read_flo(tmp_path / "neg.flo")

    def test_missing_and_bad_input(self, tmp_path):
        with pytest.raises(FileNotFoundError, match=r"path: no file at '.*none\.flo'"):
            read_flo(tmp_path / "none.flo")
        with pytest.raises(ValueError, match=r"expected shape \(2, H, W\)"):
            write_flo(tmp_path / "x.flo", torch.zeros(3, 4, 4))
        with pytest.raises(TypeError, match="floating-point"):
            write_flo(tmp_path / "x.flo", torch.zeros(2, 4, 4, dtype=torch.int32))
        assert not (tmp_path / "x.flo").exists()

    def test_float64_beyond_float32_is_refused(self, tmp_path):
        # the cast stored 1e40 as inf (read back as invalid) without a word
        flow = torch.zeros(2, 1, 2, dtype=torch.float64)
        flow[0, 0, 0] = -1e40
        with pytest.raises(ValueError, match=r"flow: a \.flo file stores float32, which cannot hold -1e\+40"):
            write_flo(tmp_path / "x.flo", flow)
        assert not (tmp_path / "x.flo").exists()

    def test_non_finite_and_unknown_values_are_written_as_given(self, tmp_path):
        flow = torch.tensor([[[float("nan"), float("inf")]], [[2e9, 0.1]]], dtype=torch.float64)
        write_flo(tmp_path / "x.flo", flow)
        back = read_flo(tmp_path / "x.flo")
        assert torch.isnan(back[0, 0, 0]) and torch.isinf(back[0, 0, 1]) and back[1, 0, 0] == np.float32(2e9)
        assert back[1, 0, 1] == np.float32(0.1)  # rounded to float32


_HEADER_3X2 = np.array([FLO_MAGIC], "<f4").tobytes() + np.array([3, 2], "<i4").tobytes()


@pytest.mark.parametrize("header", [b"\x00" * 12, _HEADER_3X2], ids=["no-flo", "flo-header-of-3x2"])
def test_another_file_is_refused_without_reading_it(tmp_path, header):
    """A large file under a .flo name (a video, or a .flo whose header does not match its length)
    was read into memory whole before its 12-byte header was checked: the ValueError comes from the
    header and the file's length, with the data left unread."""
    import tracemalloc

    path = tmp_path / "big.flo"
    with open(path, "wb") as f:
        f.write(header)
        f.truncate(64 * 2**20)  # 64 MiB, sparse
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match=r"^path: '.*big\.flo' has (the magic number 0\.0|67108864 bytes, but its "
                                             r"header declares 3x2 flow \(60 bytes\))"):
            read_flo(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2**20, peak
