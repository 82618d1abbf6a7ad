"""fsof_torch.io.images: checked decoding, RGB order, atomic writing with a failing encoder."""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from fsof_torch.io import read_image, read_image_array, write_image, write_image_array


def _ramp(h=24, w=40):
    g = torch.Generator().manual_seed(0)
    return (torch.rand(3, h, w, generator=g) * 255).round()


class TestSmoke:
    def test_png_round_trip_exact(self, tmp_path):
        image = _ramp()
        write_image(tmp_path / "a.png", image)
        back = read_image(tmp_path / "a.png")
        assert back.dtype == torch.float32 and back.shape == (3, 24, 40)
        torch.testing.assert_close(back, image)

    def test_rgb_order_is_rgb(self, tmp_path):
        bgr = np.zeros((4, 6, 3), np.uint8)
        bgr[..., 2] = 200  # red in OpenCV's order
        cv2.imwrite(str(tmp_path / "red.png"), bgr)
        image = read_image(tmp_path / "red.png")
        assert image[0].eq(200).all() and image[1:].eq(0).all()

    def test_grey_repeated_and_16bit_scaled(self, tmp_path):
        cv2.imwrite(str(tmp_path / "g.png"), np.full((5, 7), 100, np.uint8))
        cv2.imwrite(str(tmp_path / "g16.png"), np.full((5, 7, 3), 65535, np.uint16))
        assert read_image(tmp_path / "g.png").eq(100).all()
        torch.testing.assert_close(read_image(tmp_path / "g16.png"), torch.full((3, 5, 7), 255.0))

    def test_write_grey_and_uint8(self, tmp_path):
        write_image(tmp_path / "g.png", torch.full((5, 7), 17.2))
        write_image(tmp_path / "u.png", torch.full((1, 5, 7), 3, dtype=torch.uint8))
        assert read_image_array(tmp_path / "g.png").shape == (5, 7)
        assert read_image(tmp_path / "u.png").eq(3).all()
        assert read_image(tmp_path / "g.png").eq(17).all()


class TestExceptions:
    def test_truncated_png(self, tmp_path):
        write_image(tmp_path / "a.png", _ramp())
        data = (tmp_path / "a.png").read_bytes()
        (tmp_path / "t.png").write_bytes(data[: len(data) // 2])
        with pytest.raises(ValueError, match=r"t\.png.*truncated PNG"):
            read_image(tmp_path / "t.png")

    def test_not_a_png_and_empty(self, tmp_path):
        (tmp_path / "x.png").write_bytes(b"GIF89a....")
        (tmp_path / "e.png").write_bytes(b"")
        with pytest.raises(ValueError, match=r"x\.png.*not a PNG"):
            read_image(tmp_path / "x.png")
        with pytest.raises(ValueError, match=r"e\.png.*empty"):
            read_image(tmp_path / "e.png")

    def test_missing(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="no file"):
            read_image(tmp_path / "nope.png")

    @pytest.mark.parametrize("reader", ["read_image", "read_kitti_flow", "read_road_mask", "read_label_map"])
    def test_header_over_opencvs_pixel_limit(self, tmp_path, reader):
        """A 150-byte PNG whose IHDR states 60000 x 60000 pixels (over OpenCV's 2**30) made
        cv2.imdecode raise cv2.error, past every reader's ValueError."""
        import fsof_torch.io

        cv2.imwrite(str(tmp_path / "small.png"), np.zeros((2, 3), np.uint8))
        data = bytearray((tmp_path / "small.png").read_bytes())
        assert data[12:16] == b"IHDR"
        data[16:24] = struct.pack(">II", 60000, 60000)  # width, height
        data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])) & 0xFFFFFFFF)
        (tmp_path / "big.png").write_bytes(bytes(data))
        with pytest.raises(ValueError, match=rf"^path: {re.escape(repr(str(tmp_path / 'big.png')))}: OpenCV "
                                             r"refused to decode it"):
            getattr(fsof_torch.io, reader)(tmp_path / "big.png")

    def test_a_path_that_is_not_a_path_is_named(self):
        import fsof_torch as fs

        for read in (fs.read_image, fs.read_flow, fs.read_road_mask, fs.read_kitti_flow, fs.Camera.from_kitti):
            with pytest.raises(TypeError, match="path: expected a file path .str or os.PathLike., got NoneType"):
                read(None)
        with pytest.raises(TypeError, match="path: expected a file path .str or os.PathLike., got NoneType"):
            fs.write_flow(None, torch.zeros(2, 4, 4))  # the writers, through atomic_path

    def test_a_path_holding_a_nul_character_is_named(self, tmp_path):
        """The writers raised the system's bare "embedded null byte", naming no argument."""
        import fsof_torch as fs
        from fsof_torch.io import write_json, write_kitti_poses

        bad = str(tmp_path / "a\x00b.png")
        for write in (lambda: fs.write_image(bad, torch.zeros(3, 2, 2)), lambda: fs.write_flow(bad, torch.zeros(2, 2, 2)),
                      lambda: write_json(bad, {}), lambda: write_kitti_poses(bad, torch.eye(4)[None])):
            with pytest.raises(ValueError, match=r"^path: a file path holds no NUL character, got '.*a\\x00b\.png'$"):
                write()
        with pytest.raises(ValueError, match=r"^path: a file path holds no NUL character"):
            fs.read_image(bad)
        assert list(tmp_path.iterdir()) == []

    def test_write_checks(self, tmp_path):
        with pytest.raises(ValueError, match=r"0\.\.255 scale"):
            write_image(tmp_path / "a.png", torch.full((3, 4, 4), 300.0))
        with pytest.raises(ValueError, match="expected shape"):
            write_image(tmp_path / "a.png", torch.zeros(2, 4, 4))
        with pytest.raises(TypeError, match="torch.bool"):
            write_image(tmp_path / "a.png", torch.zeros(4, 4, dtype=torch.bool))

    def test_write_quotes_an_image_without_pixels_as_it_came(self, tmp_path):
        """A grey (H, W) image without rows was quoted unsqueezed, as (1, 0, 5)."""
        for shape in ((0, 5), (4, 0), (3, 0, 5), (1, 4, 0)):
            with pytest.raises(ValueError, match=rf"^image: expected H, W >= 1, got shape {re.escape(str(shape))}$"):
                write_image(tmp_path / "a.png", torch.zeros(shape))

    def test_write_refuses_a_0_1_float_image(self, tmp_path):
        """A float image on 0..1 was rounded to 0 and 1 and written near black, without a word;
        so was a float 0/1 mask (levels 0 and 1), as the library's image checks refuse it."""
        image = torch.linspace(0.0, 1.0, 3 * 4 * 5).reshape(3, 4, 5)
        mask = (image > 0.5).float()
        for x in (image, image.double(), image.half(), image.numpy(), image * 0.5, mask, mask[2], mask.numpy(),
                  torch.ones(3, 4, 5)):
            with pytest.raises(ValueError, match=r"^image: values in \[0?1?, (1|0\.5)\] look like a 0\.\.1 image or a 0/1 "
                                                 r"mask, expected the 0\.\.255 scale: scale it by 255 .*write a mask "
                                                 r"with write_road_mask, real grey levels 0 and 1 as uint8$"):
                write_image(tmp_path / "a.png", x)
        assert not (tmp_path / "a.png").exists()
        # black frames, uint8 images (grey levels 0 and 1 too) and 0..255 floats are written as they are
        for x in (torch.zeros(3, 4, 5), mask.to(torch.uint8), (image * 255).round().to(torch.uint8),
                  image * 255, mask * 255, torch.ones(4, 5, dtype=torch.uint8), torch.full((3, 4, 5), 2.0)):
            write_image(tmp_path / "b.png", x)
            assert torch.equal(read_image(tmp_path / "b.png"), x.expand(3, 4, 5).float().round())

    @pytest.mark.parametrize("name", ["x.xyz", "noext", "x.pgm", "x.pbm", "x.jp2", "x.hdr", "x.pfm"])
    def test_unknown_image_suffix(self, tmp_path, name):
        """write_image("x.xyz") once raised a cv2.error; .pgm, .pbm and .jp2 (OpenCV writers that
        refuse an RGB image) an OSError at encode time; .hdr and .pfm wrote float files that
        read_image refuses. All are refused up front, naming the suffix; nothing is left behind."""
        suffix = re.escape(repr(Path(name).suffix))
        with pytest.raises(ValueError, match=rf"path: no image writer for the suffix {suffix} of"):
            write_image(tmp_path / name, torch.zeros(3, 4, 4))
        assert list(tmp_path.iterdir()) == []

    @pytest.mark.parametrize("name", ["a.png", "a.PNG", "a.tif", "a.tiff", "a.jpg", "a.jpeg", "a.bmp", "a.webp"])
    def test_every_writable_suffix_reads_back(self, tmp_path, name):
        image = torch.zeros(3, 8, 8)
        image[0], image[1], image[2] = 200, 100, 10
        write_image(tmp_path / name, image)
        tol = 3.0 if name.endswith(("jpg", "jpeg")) else 0.0  # JPEG is lossy: fine for an image
        torch.testing.assert_close(read_image(tmp_path / name), image, atol=tol, rtol=0)


class TestWriteImageArray:
    """OpenCV converts what a format cannot hold to 8 bits, silently (float32 0.4, 300.7 -> 0, 255)."""

    @pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int32, np.int16, np.int64, np.bool_])
    def test_png_refuses_other_than_8_and_16_bit(self, tmp_path, dtype):
        with pytest.raises(ValueError, match=rf"array: a \.png file holds uint8/uint16 pixels, got {np.dtype(dtype).name}"):
            write_image_array(tmp_path / "a.png", np.ones((2, 3), dtype))
        assert list(tmp_path.iterdir()) == []

    @pytest.mark.parametrize("suffix", [".jpg", ".jpeg", ".bmp", ".webp"])
    def test_uint16_only_to_png_and_tif(self, tmp_path, suffix):
        with pytest.raises(ValueError, match=rf"array: a \{suffix} file holds uint8 pixels, got uint16"):
            write_image_array(tmp_path / f"a{suffix}", np.full((2, 3), 1000, np.uint16))
        assert list(tmp_path.iterdir()) == []

    @pytest.mark.parametrize("suffix, dtype", [(".png", np.uint16), (".tif", np.uint16), (".tiff", np.uint16),
                                               (".tif", np.float32), (".bmp", np.uint8), (".png", np.uint8)])
    @pytest.mark.parametrize("channels", [None, 3, 4])
    def test_exact_round_trip(self, tmp_path, suffix, dtype, channels):
        shape = (5, 7) if channels is None else (5, 7, channels)
        top = 255 if dtype == np.uint8 else 65535
        array = (np.random.default_rng(0).random(shape) * top).astype(dtype)
        write_image_array(tmp_path / f"a{suffix}", array)
        back = read_image_array(tmp_path / f"a{suffix}")
        assert back.dtype == array.dtype and np.array_equal(back, array)

    def test_shape_checked(self, tmp_path):
        """Two channels once raised a bare cv2.error from the encoder."""
        with pytest.raises(ValueError, match=r"array: expected shape \(H, W\) or \(H, W, C\) with C = 1, 3 or 4"):
            write_image_array(tmp_path / "a.png", np.zeros((4, 4, 2), np.uint8))
        with pytest.raises(TypeError, match="array: expected a NumPy array"):
            write_image_array(tmp_path / "a.png", torch.zeros(4, 4, dtype=torch.uint8))

    def test_encoder_failing_midway_leaves_no_file(self, tmp_path, monkeypatch):
        """A failing encoder, or a write that fails halfway (a full disk), leaves the old file or none."""
        write_image(tmp_path / "ref.png", _ramp())
        good = (tmp_path / "ref.png").read_bytes()
        write_image(tmp_path / "old.png", torch.zeros(3, 24, 40))
        before = (tmp_path / "old.png").read_bytes()

        def crash(*args):
            raise RuntimeError("encoder crashed")

        def half_then_crash(self, data):
            with open(self, "wb") as f:
                f.write(good[: len(good) // 2])
            raise OSError(28, "No space left on device")

        for patch, error in ((lambda: monkeypatch.setattr(cv2, "imencode", crash), RuntimeError),
                             (lambda: monkeypatch.setattr(Path, "write_bytes", half_then_crash), OSError)):
            patch()
            with pytest.raises(error):
                write_image(tmp_path / "new.png", _ramp())
            with pytest.raises(error):
                write_image(tmp_path / "old.png", _ramp())
            monkeypatch.undo()
            assert not (tmp_path / "new.png").exists()
            assert (tmp_path / "old.png").read_bytes() == before
            assert sorted(p.name for p in tmp_path.iterdir()) == ["old.png", "ref.png"]

    def test_path_that_is_not_utf8(self, tmp_path):
        """A file name that is not valid UTF-8 (a folder named in Latin-1, as Python lists it) is
        written and read back: OpenCV, given such a path, crashed the interpreter (a segmentation
        fault), so the writers give it the encoded bytes only (run in a child process, which a
        crash would kill instead of the test run)."""
        import subprocess
        import sys

        script = (
            "import os, sys, torch\n"
            "from fsof_torch.io import read_image, write_image, write_kitti_flow, read_kitti_flow\n"
            "folder = os.path.join(os.fsdecode(sys.argv[1].encode()), os.fsdecode(b'stra\\xdfe'))\n"
            "os.mkdir(folder)\n"
            "image = torch.arange(60.0).reshape(3, 4, 5)\n"
            "write_image(os.path.join(folder, os.fsdecode(b'\\xe9t\\xe9.png')), image)\n"
            "assert torch.equal(read_image(os.path.join(folder, os.fsdecode(b'\\xe9t\\xe9.png'))), image)\n"
            "flow = torch.full((2, 3, 4), -1.5)\n"
            "write_kitti_flow(os.path.join(folder, os.fsdecode(b'\\xff.png')), flow)\n"
            "assert torch.equal(read_kitti_flow(os.path.join(folder, os.fsdecode(b'\\xff.png')))[0], flow)\n"
            "print(sorted(os.listdir(os.fsencode(folder))))\n"
        )
        done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parents[1], timeout=120)
        assert done.returncode == 0, f"exit {done.returncode}: {done.stderr[-2000:]}"
        assert done.stdout.strip() == "[b'\\xe9t\\xe9.png', b'\\xff.png']"


class TestChannels:
    """What OpenCV reads back: a .jpg drops the alpha, a grey .webp comes back with 3 channels, a
    .webp with alpha loses the colour of its transparent pixels."""

    @pytest.mark.parametrize("suffix, channels", [(s, c) for s, cs in {
        ".png": (1, 3, 4), ".tif": (1, 3, 4), ".tiff": (1, 3, 4), ".bmp": (1, 3, 4), ".jpg": (1, 3), ".jpeg": (1, 3),
        ".webp": (3,)}.items() for c in cs])
    def test_allowed_channels_read_back(self, tmp_path, suffix, channels):
        from fsof_torch.io.images import WRITABLE_CHANNELS

        assert channels in WRITABLE_CHANNELS[suffix]
        shape = (6, 5) if channels == 1 else (6, 5, channels)
        array = (np.random.default_rng(0).random(shape) * 255).astype(np.uint8)
        write_image_array(tmp_path / f"a{suffix}", array)
        back = read_image_array(tmp_path / f"a{suffix}")
        assert back.shape == shape
        if suffix not in (".jpg", ".jpeg"):  # lossy in its values, not in its channels
            assert np.array_equal(back, array)

    @pytest.mark.parametrize("suffix", [".png", ".tif", ".bmp"])
    def test_colour_under_transparent_pixels_kept(self, tmp_path, suffix):
        array = (np.random.default_rng(0).random((16, 15, 4)) * 255).astype(np.uint8)
        array[::2, :, 3] = 0
        write_image_array(tmp_path / f"a{suffix}", array)
        assert np.array_equal(read_image_array(tmp_path / f"a{suffix}"), array)

    @pytest.mark.parametrize("suffix, shape", [(".jpg", (6, 5, 4)), (".jpeg", (6, 5, 4)), (".webp", (6, 5)),
                                               (".webp", (6, 5, 1)), (".webp", (6, 5, 4))])
    def test_other_channels_refused(self, tmp_path, suffix, shape):
        channels = 1 if len(shape) == 2 else shape[2]
        with pytest.raises(ValueError, match=rf"^array: a \{suffix} file keeps only .* channels .*, got {channels} "):
            write_image_array(tmp_path / f"a{suffix}", np.zeros(shape, np.uint8))
        assert list(tmp_path.iterdir()) == []

    def test_grey_image_to_webp(self, tmp_path):
        grey = _ramp()[:1]
        write_image(tmp_path / "g.webp", grey)
        assert read_image_array(tmp_path / "g.webp").shape == (24, 40, 3)
        torch.testing.assert_close(read_image(tmp_path / "g.webp"), grey.expand(3, -1, -1))


class TestArrays:
    def test_write_image_takes_views_and_byte_orders(self, tmp_path):
        """write_image called torch.from_numpy: an RGB view of a BGR array (negative strides) or a
        big-endian array raised torch's ValueError."""
        bgr = np.random.default_rng(0).integers(0, 256, (8, 10, 3)).astype(np.uint8)
        rgb = bgr[:, :, ::-1].transpose(2, 0, 1)
        write_image(tmp_path / "a.png", rgb)
        assert np.array_equal(read_image_array(tmp_path / "a.png"), bgr)
        big = rgb.astype(">f4")
        write_image(tmp_path / "b.png", big)
        assert np.array_equal(read_image_array(tmp_path / "b.png"), bgr)

    def test_folder_in_place_of_a_file(self, tmp_path):
        """A folder was 'no file at', as if nothing were there."""
        (tmp_path / "a.png").mkdir()
        with pytest.raises(IsADirectoryError, match=r"^path: '.*a\.png' is a folder; expected a file$"):
            read_image(tmp_path / "a.png")
        with pytest.raises(IsADirectoryError, match=r"^path: '.*a\.png' is a folder; expected a file path$"):
            write_image(tmp_path / "a.png", _ramp())
        with pytest.raises(FileNotFoundError, match="path: no file at"):
            read_image(tmp_path / "b.png")

    def test_folder_in_place_of_a_text_or_flow_file(self, tmp_path):
        """The poses, calibration and flow readers said "no file at" for a folder that is there."""
        from fsof_torch.io import read_flow, read_kitti_calibration, read_kitti_poses

        for name, read, what in (("poses.txt", read_kitti_poses, "poses file"),
                                 ("calib.txt", read_kitti_calibration, "calibration file"),
                                 ("f.flo", read_flow, "file"), ("f.npy", read_flow, "file")):
            (tmp_path / name).mkdir()
            with pytest.raises(IsADirectoryError, match=rf"^path: '.*{name}' is a folder; expected a {what}$"):
                read(tmp_path / name)


class TestCardinality:
    @pytest.mark.parametrize("size", [(1, 1), (7, 3), (3, 7)])
    def test_sizes(self, tmp_path, size):
        image = torch.full((3, *size), 9.0)
        write_image(tmp_path / "a.png", image)
        assert read_image(tmp_path / "a.png").shape == (3, *size)


class TestShared:
    def test_kitti_images(self, shared_data):
        image = read_image(shared_data / "kitti15_000000" / "image_10.png")
        assert image.shape == (3, 375, 1242) and 0 <= float(image.min()) and float(image.max()) <= 255
        grey = read_image(shared_data / "kitti_odometry_straight" / "image_l" / "000000.png")
        assert grey.shape == (3, 370, 1226) and torch.equal(grey[0], grey[2])


def test_frame_order_by_number_where_every_name_is_one():
    """The one rule of frame order, shared by image folders and CARLA runs."""
    from fsof_torch.io.images import in_frame_order

    assert [p.name for p in in_frame_order(["100.png", "98.png", "05.png", "5.png", "99.png"])] == [
        "05.png", "5.png", "98.png", "99.png", "100.png"]
    assert [p.name for p in in_frame_order(["b_2.png", "b_10.png", "a.png"])] == ["a.png", "b_10.png", "b_2.png"]
    assert [p.name for p in in_frame_order(["2.png", "10.png", "x1.png"])] == ["10.png", "2.png", "x1.png"]
    assert in_frame_order([]) == []


def test_frame_order_refuses_two_files_of_one_frame_name():
    """Two files of one frame name (a PNG and a JPEG export of one frame) would pair with each other."""
    from fsof_torch.io.images import in_frame_order

    with pytest.raises(ValueError, match=r"^images: 000000\.jpg and 000000\.png share the frame name 000000"):
        in_frame_order(["000001.png", "000000.png", "000000.jpg"])
    with pytest.raises(ValueError, match=r"^frames: 'a/5\.png' and 'b/5\.png' share the frame name 5"):
        in_frame_order(["b/5.png", "a/5.png"], name="frames")


def _exif_orientation(value: int) -> bytes:
    """A big-endian TIFF block (the payload of a PNG eXIf chunk and of a JPEG's APP1 Exif
    segment) holding one entry: the orientation tag 0x0112, a SHORT."""
    return b"MM\x00*" + struct.pack(">IHHHIHHI", 8, 1, 0x0112, 3, 1, value, 0, 0)


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_exif_orientation_is_not_applied(tmp_path, suffix):
    """An EXIF orientation tag (a phone's 'rotate 90°') leaves the pixels as stored, the grid a
    calibration of the stored frames describes, as PIL and torchvision read them (OpenCV's
    default imread would turn the image to 6×4)."""
    bgr = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3) * 3
    data = cv2.imencode(suffix, bgr, [cv2.IMWRITE_JPEG_QUALITY, 100] if suffix == ".jpg" else [])[1].tobytes()
    exif = _exif_orientation(6)
    if suffix == ".png":  # an eXIf chunk after IHDR (8-byte signature, 25-byte IHDR chunk)
        chunk = b"eXIf" + exif
        data = data[:33] + struct.pack(">I", len(exif)) + chunk + struct.pack(">I", zlib.crc32(chunk)) + data[33:]
    else:  # an APP1 Exif segment after SOI
        data = data[:2] + b"\xff\xe1" + struct.pack(">H", 2 + 6 + len(exif)) + b"Exif\x00\x00" + exif + data[2:]
    path = tmp_path / f"turned{suffix}"
    path.write_bytes(data)
    assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR).shape == (6, 4, 3)  # the tag is read
    stored = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert stored.shape == (4, 6, 3)
    image = read_image(path)
    assert image.shape == (3, 4, 6)
    assert torch.equal(image, torch.from_numpy(stored[:, :, ::-1].transpose(2, 0, 1).astype(np.float32)))
    if suffix == ".png":  # lossless: the very values written
        assert torch.equal(image, torch.from_numpy(bgr[:, :, ::-1].transpose(2, 0, 1).astype(np.float32)))


@pytest.mark.parametrize("magic, maxval", [("P5", 1023), ("P5", 4095), ("P5", 100), ("P6", 1023), ("P6", 15),
                                           ("P2", 1023), ("P3", 4095), ("P2", 100), ("P5", 255), ("P6", 65535)])
def test_pgm_and_ppm_scaled_by_their_maxval(tmp_path, magic, maxval):
    """A PGM/PPM states the value of white (maxval): 10-bit data (maxval 1023) read as 0..3.98, a
    near black image, since OpenCV gives binary files' values as stored (and 16-bit ones were
    divided by 257). Now white is 255 whatever the maxval; the expected values are the samples
    scaled by 255 / maxval (OpenCV itself scales plain-text files of maxval < 256, to whole
    levels)."""
    colour = magic in ("P3", "P6")
    shape = (3, 5, 3) if colour else (3, 5)
    samples = np.random.default_rng(maxval).integers(0, maxval + 1, shape)
    samples.flat[0], samples.flat[1] = 0, maxval  # black and white are there
    header = f"{magic}\n# 10-bit sensor\n5 3\n{maxval}\n".encode()
    if magic in ("P2", "P3"):
        body = " ".join(map(str, samples.ravel())).encode() + b"\n"
    else:
        body = samples.astype(">u2" if maxval > 255 else np.uint8).tobytes()
    (tmp_path / "a.pnm").write_bytes(header + body)
    rgb = samples.transpose(2, 0, 1) if colour else np.repeat(samples[None], 3, axis=0)
    expected = rgb * 255.0 / maxval
    if magic in ("P2", "P3") and maxval < 256:
        expected = np.floor(expected)  # (OpenCV's own scaling, to whole levels)
    image = read_image(tmp_path / "a.pnm")
    assert image.dtype == torch.float32 and image.shape == (3, 3, 5)
    np.testing.assert_allclose(image.numpy(), expected, rtol=0, atol=1e-4)
    assert float(image.max()) == 255.0
