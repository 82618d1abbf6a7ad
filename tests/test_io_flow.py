"""fsof_torch.io.flow: read_flow / write_flow dispatch by suffix (.png, .flo, .npy)."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import torch

from fsof_torch.io import read_flow, write_flow


def _flow(h=6, w=9):
    g = torch.Generator().manual_seed(1)
    flow = torch.randn(2, h, w, generator=g) * 10
    valid = torch.rand(1, h, w, generator=g) > 0.25
    return flow, valid


class TestSmoke:
    @pytest.mark.parametrize("suffix", [".png", ".flo", ".npy"])
    def test_round_trip_keeps_valid(self, tmp_path, suffix):
        flow, valid = _flow()
        write_flow(tmp_path / f"f{suffix}", flow, valid)
        back, back_valid = read_flow(tmp_path / f"f{suffix}")
        assert back.shape == (2, 6, 9) and back.dtype == torch.float32
        assert torch.equal(back_valid, valid)
        m = valid.expand(2, -1, -1)
        tol = 1 / 128 if suffix == ".png" else 0.0
        assert float((back - flow).abs()[m].max()) <= tol
        assert back[~m].eq(0).all()

    @pytest.mark.parametrize("suffix", [".flo", ".npy"])
    def test_exact_without_valid(self, tmp_path, suffix):
        flow, _ = _flow()
        write_flow(tmp_path / f"f{suffix}", flow)
        back, valid = read_flow(tmp_path / f"f{suffix}")
        assert valid.all() and torch.equal(back, flow)

    def test_npy_hwc_layout(self, tmp_path):
        flow, _ = _flow(4, 5)
        np.save(tmp_path / "hwc.npy", flow.numpy().transpose(1, 2, 0))
        back, _ = read_flow(tmp_path / "hwc.npy")
        assert torch.equal(back, flow)

    def test_npy_float64_beyond_float32_is_invalid_without_a_numpy_warning(self, tmp_path):
        """A float64 .npy value beyond float32's range is flow 'above 1e9' (not valid), as
        documented; its cast to float32 let NumPy's 'overflow encountered in cast'
        RuntimeWarning through, an error under -W error."""
        flow, _ = _flow(3, 4)
        array = flow.double().numpy()
        array[:, 1, 2] = (1e300, -1e39)
        np.save(tmp_path / "big.npy", array)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            back, valid = read_flow(tmp_path / "big.npy")
        assert not bool(valid[0, 1, 2]) and int(valid.sum()) == 11 and back[:, 1, 2].eq(0).all()
        assert torch.equal(back[:, valid[0]], flow[:, valid[0]])

    def test_middlebury_unknown_marker(self, tmp_path):
        """A Middlebury file's 1e10 reads as unknown flow; write_flow stores unknown flow through
        ``valid`` (NaN), and a 1e10 it would take for a valid pixel is refused, not written."""
        from fsof_torch.io import write_flo

        flow, _ = _flow(3, 3)
        flow[:, 0, 0] = 1e10
        write_flo(tmp_path / "f.flo", flow)
        _, valid = read_flow(tmp_path / "f.flo")
        assert not bool(valid[0, 0, 0]) and int(valid.sum()) == 8
        for suffix in (".flo", ".npy"):
            write_flow(tmp_path / f"g{suffix}", flow, valid)
            back, back_valid = read_flow(tmp_path / f"g{suffix}")
            assert torch.equal(back_valid, valid) and torch.equal(back[:, valid[0]], flow[:, valid[0]])

    @pytest.mark.parametrize("suffix", [".flo", ".npy"])
    @pytest.mark.parametrize("value, dtype", [(2e9, torch.float32), (-1e9, torch.float32), (1e39, torch.float64)])
    def test_unstorable_flow_without_valid_is_refused(self, tmp_path, suffix, value, dtype):
        """Without ``valid`` every finite pixel is valid: |flow| >= 1e9 px (or float64 beyond
        float32's range) there was once written and read back as not valid, silently."""
        flow = torch.zeros(2, 2, 3, dtype=dtype)
        flow[0, 1, 2] = value
        with pytest.raises(ValueError, match=r"^flow: expected \|flow\| < 1e\+09 px at valid pixels after the "
                                             r"float32 cast .*got " + re.escape(f"{abs(value):.4g}")):
            write_flow(tmp_path / f"f{suffix}", flow)
        assert list(tmp_path.iterdir()) == []
        flow[0, 1, 2] = float("nan")  # non-finite pixels are the invalid ones
        write_flow(tmp_path / f"f{suffix}", flow)
        back, valid = read_flow(tmp_path / f"f{suffix}")
        assert int(valid.sum()) == 5 and not bool(valid[0, 1, 2]) and back.eq(0).all()


class TestExceptions:
    @pytest.mark.parametrize("suffix", [".flo", ".npy", ".png"])
    def test_an_array_torch_cannot_take_is_a_type_error_naming_flow_or_valid(self, tmp_path, suffix):
        """An object, string or long-double array as the flow (or an object array as valid) raised
        torch's TypeError ("can't convert np.ndarray of type numpy.object_"), naming neither;
        nothing is written."""
        from fsof_torch.io import write_flo

        good = np.zeros((2, 4, 5), dtype=np.float32)
        writers = [write_flow] + ([write_flo] if suffix == ".flo" else [])
        for writer in writers:
            for dtype in (object, "U3", np.longdouble):
                with pytest.raises(TypeError, match=rf"^flow: expected a floating-point array \(float16/32/64\), "
                                                    rf"got dtype {re.escape(str(np.dtype(dtype)))}$"):
                    writer(tmp_path / f"f{suffix}", good.astype(dtype))
        with pytest.raises(TypeError, match=r"^valid: expected a bool tensor of shape \(1, H, W\), got a NumPy "
                                            r"array of dtype object$"):
            write_flow(tmp_path / f"f{suffix}", good, np.ones((4, 5), dtype=object))
        assert not any(tmp_path.iterdir())
        write_flow(tmp_path / f"f{suffix}", good, np.ones((4, 5), dtype=bool))  # (a bool array is taken)
        assert torch.equal(read_flow(tmp_path / f"f{suffix}")[0], torch.zeros(2, 4, 5))

    def test_unknown_suffix(self, tmp_path):
        with pytest.raises(ValueError, match=r"suffix '\.txt'"):
            read_flow(tmp_path / "f.txt")
        with pytest.raises(ValueError, match=r"suffix '\.bmp'"):
            write_flow(tmp_path / "f.bmp", torch.zeros(2, 2, 2))

    @pytest.mark.parametrize("suffix", [".flo", ".npy"])
    @pytest.mark.parametrize("bad", [float("nan"), float("inf"), -1e9, 2e9])
    def test_unstorable_flow_at_valid_pixels(self, tmp_path, suffix, bad):
        """NaN, inf or |flow| >= 1e9 at a valid pixel was once written, and read back as invalid
        (the .png writer raised)."""
        flow, valid = _flow(3, 4)
        valid[0, 1, 2] = True
        flow[1, 1, 2] = bad
        with pytest.raises(ValueError, match=r"flow: expected (finite values|\|flow\| < 1e\+09 px) at valid pixels"):
            write_flow(tmp_path / f"f{suffix}", flow, valid)
        assert list(tmp_path.iterdir()) == []
        valid[0, 1, 2] = False  # at an invalid pixel it is fine
        write_flow(tmp_path / f"f{suffix}", flow, valid)
        assert torch.equal(read_flow(tmp_path / f"f{suffix}")[1], valid)

    def test_float64_beyond_float32_at_a_valid_pixel(self, tmp_path):
        """1e39 is finite in float64 but inf once stored as float32."""
        flow = torch.full((2, 2, 2), 1e39, dtype=torch.float64)
        with pytest.raises(ValueError, match=r"flow: expected \|flow\| < 1e\+09 px at valid pixels after the "
                                             r"float32 cast .*got 1e\+39"):
            write_flow(tmp_path / "f.flo", flow, torch.ones(1, 2, 2, dtype=torch.bool))

    def test_bad_npy(self, tmp_path):
        np.save(tmp_path / "s.npy", np.zeros((3, 4, 5), np.float32))
        np.save(tmp_path / "i.npy", np.zeros((2, 4, 5), np.int32))
        with pytest.raises(ValueError, match=r"s\.npy.*shape"):
            read_flow(tmp_path / "s.npy")
        with pytest.raises(ValueError, match=r"i\.npy.*int32"):
            read_flow(tmp_path / "i.npy")
        with pytest.raises(FileNotFoundError, match=r"path: no file at '.*none\.npy'"):
            read_flow(tmp_path / "none.npy")
        np.save(tmp_path / "e.npy", np.zeros((2, 0, 5), np.float32))  # as .flo: no empty flow
        with pytest.raises(ValueError, match=r"e\.npy' holds an empty flow of shape \(2, 0, 5\)"):
            read_flow(tmp_path / "e.npy")
        # an empty (H, W, 2) array: the shape in the file, not the transposed (2, 0, 4)
        np.save(tmp_path / "e.npy", np.zeros((0, 4, 2), np.float32))
        with pytest.raises(ValueError, match=r"e\.npy' holds an empty flow of shape \(0, 4, 2\)"):
            read_flow(tmp_path / "e.npy")

    def test_zero_byte_and_npz_npy(self, tmp_path):
        """A zero-byte .npy once raised a bare EOFError."""
        (tmp_path / "z.npy").write_bytes(b"")
        with pytest.raises(ValueError, match=r"path: '.*z\.npy' is not a readable \.npy array \(EOFError"):
            read_flow(tmp_path / "z.npy")
        np.savez(tmp_path / "a.npz", flow=np.zeros((2, 3, 3), np.float32))
        (tmp_path / "a.npz").rename(tmp_path / "a.npy")
        with pytest.raises(ValueError, match=r"a\.npy' is not a single \.npy array"):
            read_flow(tmp_path / "a.npy")
