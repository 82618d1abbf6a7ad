"""fsof_torch.io.atomic: temp file in the same folder + os.replace; a failure leaves no half file."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fsof_torch.io import atomic_path, to_jsonable, write_bytes, write_json, write_text


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if ".tmp" in p.name)


class TestSmoke:
    def test_write_text_and_bytes(self, tmp_path):
        write_text(tmp_path / "a.txt", "hello")
        write_bytes(tmp_path / "b.bin", b"\x00\x01")
        assert (tmp_path / "a.txt").read_text() == "hello"
        assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"
        assert _leftovers(tmp_path) == []

    def test_temp_file_beside_target_keeps_suffix(self, tmp_path):
        with atomic_path(tmp_path / "x.png") as tmp:
            assert tmp.parent == tmp_path and tmp.suffix == ".png" and tmp != tmp_path / "x.png"
            tmp.write_bytes(b"data")
        assert (tmp_path / "x.png").read_bytes() == b"data"

    def test_write_json_converts_tensors_and_arrays(self, tmp_path):
        obj = {"t": torch.tensor([1.5, 2.0]), "a": np.arange(3), "s": np.float32(0.5), "n": None, "p": tmp_path}
        write_json(tmp_path / "x.json", obj)
        back = json.loads((tmp_path / "x.json").read_text())
        assert back == {"t": [1.5, 2.0], "a": [0, 1, 2], "s": 0.5, "n": None, "p": str(tmp_path)}


class TestExceptions:
    def test_failure_midway_leaves_no_file(self, tmp_path):
        with pytest.raises(RuntimeError, match="boom"):
            with atomic_path(tmp_path / "out.txt") as tmp:
                tmp.write_bytes(b"half of")
                raise RuntimeError("boom")
        assert not (tmp_path / "out.txt").exists()
        assert _leftovers(tmp_path) == []

    def test_failure_keeps_old_file(self, tmp_path):
        write_text(tmp_path / "out.txt", "old")
        with pytest.raises(RuntimeError):
            with atomic_path(tmp_path / "out.txt") as tmp:
                tmp.write_text("new, half")
                raise RuntimeError("crash")
        assert (tmp_path / "out.txt").read_text() == "old"
        assert _leftovers(tmp_path) == []

    def test_nothing_written_is_an_error(self, tmp_path):
        with pytest.raises(OSError, match="nothing was written"):
            with atomic_path(tmp_path / "empty.txt"):
                pass
        assert not (tmp_path / "empty.txt").exists()
        assert _leftovers(tmp_path) == []

    def test_missing_folder(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="does not exist"):
            write_text(tmp_path / "no" / "x.txt", "a")

    def test_json_rejects_unknown_objects(self, tmp_path):
        with pytest.raises(TypeError, match="cannot write a object"):
            to_jsonable(object())

    def test_json_non_finite_becomes_null(self, tmp_path):
        write_json(tmp_path / "nan.json", {"x": float("nan"), "t": torch.tensor([1.0, float("inf")])})
        assert json.loads((tmp_path / "nan.json").read_text()) == {"x": None, "t": [1.0, None]}
