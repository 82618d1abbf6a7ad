"""Images on disk: checked decoding of PNG/JPEG files with OpenCV, RGB tensors, atomic writing.

Convention: images are returned as (3, H, W) float32 RGB on the 0..255 scale (OpenCV's BGR order
is undone here, once). PNG files are checked before decoding: the signature and the closing
``IEND`` chunk must be there, so a truncated file raises instead of decoding to a partial image.

Writing takes the formats in :data:`WRITABLE_DTYPES` only, each with the pixel types it stores
exactly: OpenCV would otherwise convert what a format cannot hold to 8 bits (clipping labels
above 255, rounding float data) or write a file the readers here refuse (.hdr, .pfm: float).
"""

from __future__ import annotations

import os
import re
from decimal import Decimal
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import torch
from torch import Tensor

from .._check import as_path, check_has_values, existing_file, tensor_from_array
from .atomic import atomic_path, file_target

__all__ = ["read_image", "write_image", "read_image_array", "write_image_array"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk type and its fixed CRC


def _read_bytes(path: str | os.PathLike) -> tuple[Path, bytes]:
    path = existing_file(path)
    return path, path.read_bytes()


def check_frame_names(paths: Iterable[str | os.PathLike], name: str = "images") -> None:
    """Raise a ValueError naming ``name`` where two frame files share a frame name (stem), such as
    ``000000.png`` and ``000000.jpg``: a frame's name names its pair and finds the pair's files by
    name, so two frames of one name would pair with each other and share those files."""
    seen: dict[str, Path] = {}
    for p in map(Path, paths):
        first = seen.get(p.stem)
        if first is not None:
            both = f"{first.name} and {p.name}" if first.parent == p.parent else f"{str(first)!r} and {str(p)!r}"
            raise ValueError(f"{name}: {both} share the frame name {p.stem}; keep one file per frame")
        seen[p.stem] = p


def check_no_broken_links(paths: Iterable[str | os.PathLike], name: str) -> None:
    """Raise a FileNotFoundError naming ``name`` where one of ``paths`` is a symbolic link whose
    target is missing (a data set linked from a drive that is not mounted): the listers of frames
    keep regular files only, so such a frame would be left out silently and its neighbours paired
    with each other, a pair two frames apart under a name that says one."""
    for p in map(Path, paths):
        if p.is_symlink() and not p.exists():
            raise FileNotFoundError(f"{name}: {str(p)!r} is a symbolic link to {os.readlink(p)!r}, which does not "
                                    f"exist; mount or copy the data it points to, or remove the link")


def existing_folder(folder: str | os.PathLike, name: str) -> Path:
    """``folder`` as a Path where a folder is there; else a FileNotFoundError (no folder found)
    naming ``name`` and the path, and what is there: a file ("is a file; expected a folder"), a
    symbolic link to a missing folder (a drive not mounted), or nothing ("no folder at")."""
    folder = Path(folder)
    if folder.is_dir():
        return folder
    check_no_broken_links([folder], name)
    if folder.exists():
        raise FileNotFoundError(f"{name}: {str(folder)!r} is a file; expected a folder")
    raise FileNotFoundError(f"{name}: no folder at {str(folder)!r}")


def frame_numbers(stems: Iterable[str]) -> list[int] | None:
    """The frame numbers of frame names (stems) that are one text around a number: every name a
    number (``0``, ``5``, ``10``), or the same text and the same other numbers around one number
    (``frame_9``, ``frame_10``; ``cam0_9_rect``, ``cam0_10_rect``; ``9_cam0``, ``10_cam0``; where
    no number differs, the last). None where the names are not (other texts, no number, numbers
    that differ in two places, or the decimals of a fraction, ``1541234567.15``, whose digits do
    not count as a number)."""
    parts = [re.split(r"([0-9]+)", s) for s in stems]  # text, number, text, ..., number, text
    if not parts or any(len(p) < 3 or len(p) != len(parts[0]) for p in parts):
        return None
    first = parts[0]
    if any(p[k] != first[k] for p in parts for k in range(0, len(first), 2)):
        return None  # other texts
    varying = [k for k in range(1, len(first), 2) if any(p[k] != first[k] for p in parts)]
    if len(varying) > 1:
        return None
    k = varying[0] if varying else len(first) - 2
    if k >= 3 and first[k - 1] == ".":  # the decimals of a number
        return None
    return [int(p[k]) for p in parts]


#: a frame name's number from here up is a timestamp (Unix time in seconds since 2001, or in ms,
#: µs, ns: ``1541234567150000000.png``), not a frame counter: its steps count no frames
TIMESTAMP_MIN = 10**9


def frame_counts(stems: Iterable[str]) -> list[int] | None:
    """The frame numbers of frame names (:func:`frame_numbers`) where they count frames, so that
    frames i and j lie j − i frames apart; None where the names have no frame numbers, or where
    their numbers are timestamps (one from :data:`TIMESTAMP_MIN` up: a camera's frames named by
    the time they were taken, 100 ms or 100 000 000 ns apart, are consecutive frames)."""
    numbers = frame_numbers(stems)
    return None if numbers is None or max(numbers) >= TIMESTAMP_MIN else numbers


_DECIMAL = re.compile(r"[0-9]+(\.[0-9]+)?")  # a frame's time as its name: 9.967, 1541234567.15


def decimal_times(stems: Iterable[str]) -> list[Decimal] | None:
    """The times of frame names (stems) that are decimal numbers (``9.967``, ``10.000``), or one
    text around one, the same text for every name (``left_9.967``, ``left_10.000``;
    ``9.967_cam0``), as exact Decimals (1541234567.15 and 1541234567.150 are one time); None
    where the names are not."""
    stems = list(stems)
    if not stems:
        return None
    digits = "0123456789."
    # the text common to every name, up to the number (a digit or point it ends in is the number's)
    before = os.path.commonprefix(stems).rstrip(digits)
    after = os.path.commonprefix([s[::-1] for s in stems])[::-1].lstrip(digits)
    middles = [s[len(before):len(s) - len(after)] for s in stems]
    if not all(_DECIMAL.fullmatch(m) for m in middles):
        return None
    return [Decimal(m) for m in middles]


def in_frame_order(paths: Iterable[str | os.PathLike], name: str = "images") -> list[Path]:
    """Frame files in frame order: by number where every file's stem is one text around a number
    (:func:`frame_numbers`: ``0.png``, ``5.png``, ``10.png``, ``100.png``, or ``frame_9.png``
    before ``frame_10.png``: frames numbered without zero padding), or by value where every stem
    is a decimal number or one text around one (:func:`decimal_times`: timestamps ``9.967.png``
    before ``10.000.png``, ``left_9.967.png`` before ``left_10.000.png``; by name they came after
    it), else by name. Equal numbers (``5`` and ``05``) stay in the order of their names. Two
    files of one frame name (``000000.png`` and ``000000.jpg``) are a ValueError naming ``name``
    (:func:`check_frame_names`)."""
    paths = sorted(Path(p) for p in paths)
    check_frame_names(paths, name)
    numbers: list[Any] | None = frame_numbers(p.stem for p in paths)
    if numbers is None:
        numbers = decimal_times(p.stem for p in paths)
    if numbers is not None:
        order = sorted(range(len(paths)), key=numbers.__getitem__)  # (stable: equal numbers by name)
        paths = [paths[i] for i in order]
    return paths


def _a(what: str) -> str:
    """``what`` with its indefinite article ("an image", "a KITTI flow PNG")."""
    return f"{'an' if what[:1].lower() in 'aeiou' else 'a'} {what}"


def read_image_array(path: str | os.PathLike, *, what: str = "image") -> np.ndarray:
    """Decode an image file exactly as stored (``cv2.IMREAD_UNCHANGED``): (H, W) or (H, W, C)
    uint8/uint16/float32, channels in OpenCV's BGR(A) order.

    Raises ValueError naming the path for an empty, truncated or undecodable file (also one whose
    header states more pixels than OpenCV decodes, 2**30 by default), FileNotFoundError for a
    missing one, IsADirectoryError for a folder. ``what`` says in the message what the file was
    expected to be ("KITTI flow PNG", ...).
    """
    import cv2

    path, data = _read_bytes(path)
    if not data:
        raise ValueError(f"path: {str(path)!r} is empty, expected {_a(what)}")
    if data.startswith(_PNG_SIGNATURE):
        if data.rfind(_PNG_END) < 0:
            raise ValueError(f"path: {str(path)!r} is a truncated PNG (no IEND chunk, {len(data)} bytes); "
                             f"expected a complete {what}")
    elif path.suffix.lower() == ".png":
        raise ValueError(f"path: {str(path)!r} is not a PNG file (bad signature {data[:8]!r}); expected {_a(what)}")
    try:
        array = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as err:  # OpenCV raises (rather than returns None) for a header over its pixel limit
        reason = (err.err or str(err)).strip()
        raise ValueError(f"path: {str(path)!r}: OpenCV refused to decode it as {_a(what)} ({reason}: a header "
                         f"stating more pixels than OpenCV decodes, or a corrupt one)") from None
    if array is None:
        raise ValueError(f"path: OpenCV could not decode {str(path)!r} as {_a(what)} (corrupt or unsupported file)")
    return array


#: the suffixes :func:`write_image_array` writes, and the pixel types each stores exactly and reads
#: back as such (.jpg is lossy in its values, not in its type: for images, never for data)
WRITABLE_DTYPES: dict[str, tuple[type, ...]] = {
    ".png": (np.uint8, np.uint16),
    ".tif": (np.uint8, np.uint16, np.float32),
    ".tiff": (np.uint8, np.uint16, np.float32),
    ".jpg": (np.uint8,),
    ".jpeg": (np.uint8,),
    ".bmp": (np.uint8,),
    ".webp": (np.uint8,),
}

#: the channel counts each suffix of :data:`WRITABLE_DTYPES` reads back as written (1: (H, W) or
#: (H, W, 1), read back as (H, W)); OpenCV drops the alpha of a .jpg, makes a grey .webp BGR, and
#: WebP drops the colour of transparent pixels (alpha 0)
WRITABLE_CHANNELS: dict[str, tuple[int, ...]] = {
    ".png": (1, 3, 4),
    ".tif": (1, 3, 4),
    ".tiff": (1, 3, 4),
    ".jpg": (1, 3),
    ".jpeg": (1, 3),
    ".bmp": (1, 3, 4),
    ".webp": (3,),
}


def check_image_suffix(path: str | os.PathLike, suffixes: tuple[str, ...], what: str) -> Path:
    """``path`` as a Path if its suffix (any case) is one of ``suffixes``, else a ValueError naming
    it; ``what`` says what the file holds ("label map", ...). Shared by the writers of data
    images (masks, labels, flow), which must not go to a lossy or 8-bit-only format."""
    path = file_target(path)
    if path.suffix.lower() not in suffixes:
        raise ValueError(f"path: {_a(what)} is written as {' or '.join(suffixes)}; got the suffix "
                         f"{path.suffix!r} of {str(path)!r}")
    return path


def write_image_array(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Encode ``array`` (OpenCV layout: (H, W) or (H, W, C), C = 1, 3 or 4, in BGR(A) order) to
    ``path`` atomically; the format comes from the suffix.

    Only pixel types the format stores exactly are written (:data:`WRITABLE_DTYPES`): uint8 to
    .png, .tif/.tiff, .jpg/.jpeg, .bmp, .webp; uint16 to .png and .tif/.tiff; float32 to
    .tif/.tiff. Only channel counts the format reads back are written (:data:`WRITABLE_CHANNELS`):
    1, 3 or 4 to .png, .tif/.tiff, .bmp; 1 or 3 to .jpg/.jpeg (no alpha); 3 to .webp (no grey,
    and no alpha: WebP drops the colour of transparent pixels). Anything else is a ValueError
    naming ``array`` and the suffix, raised before a file is written (OpenCV would silently
    convert it to 8 bits, drop the alpha or add channels). Another suffix is a ValueError naming
    ``path``.
    """
    import cv2

    path = file_target(path)
    suffix = path.suffix.lower()
    # OpenCV is given the suffix and the encoded bytes, never the path: it crashes the interpreter
    # (a segmentation fault) on a path that is not valid UTF-8, such as a folder named in Latin-1
    if suffix not in WRITABLE_DTYPES or not cv2.haveImageWriter("x" + suffix):
        known = ", ".join(s for s in WRITABLE_DTYPES if cv2.haveImageWriter("x" + s))
        raise ValueError(f"path: no image writer for the suffix {path.suffix!r} of {str(path)!r} "
                         f"(the formats written and read back here: {known})")
    if not isinstance(array, np.ndarray):
        raise TypeError(f"array: expected a NumPy array (H, W) or (H, W, C), got {type(array).__name__}")
    if not (array.ndim == 2 or (array.ndim == 3 and array.shape[2] in (1, 3, 4))) or min(array.shape[:2]) < 1:
        raise ValueError(f"array: expected shape (H, W) or (H, W, C) with C = 1, 3 or 4 and H, W >= 1, "
                         f"got {array.shape}")
    allowed = WRITABLE_DTYPES[suffix]
    if array.dtype not in allowed:
        raise ValueError(f"array: a {suffix} file holds {'/'.join(np.dtype(d).name for d in allowed)} pixels, "
                         f"got {array.dtype} for {str(path)!r} (OpenCV would convert it to 8 bits); "
                         f"uint16 goes to .png or .tif, float32 to .tif")
    channels = 1 if array.ndim == 2 else array.shape[2]
    if channels not in WRITABLE_CHANNELS[suffix]:
        allowed = " or ".join(map(str, WRITABLE_CHANNELS[suffix]))
        raise ValueError(f"array: a {suffix} file keeps only {allowed} channels (others read back changed), "
                         f"got {channels} (shape {array.shape}) for {str(path)!r}; any of 1, 3, 4 goes to "
                         f".png, .tif or .bmp")
    ok, encoded = cv2.imencode(suffix, array)
    if not ok:
        raise OSError(f"path: OpenCV could not encode {str(path)!r} (dtype {array.dtype}, shape {array.shape})")
    with atomic_path(path) as tmp:
        tmp.write_bytes(encoded.tobytes())
    return path


def read_image(path: str | os.PathLike) -> Tensor:
    """An image file as a (3, H, W) float32 RGB tensor on the 0..255 scale.

    Grey images are repeated to three channels, an alpha channel is dropped, 16-bit images are
    divided by 257 (65535 -> 255). An EXIF orientation tag is not applied: the pixels come as
    stored (as PIL and torchvision read them; ``cv2.imread``'s default would turn the image), the
    grid that a calibration of the stored frames describes. A PGM or PPM file states its white
    (maxval): its values are scaled by 255 / maxval (10-bit data, maxval 1023, to 0..255).
    """
    array = read_image_array(path, what="image")
    maxval = _netpbm_maxval(path)  # (OpenCV gives most PGM/PPM values as stored, whatever their white)
    if maxval is not None and maxval not in (255, 65535) and array.dtype in (np.uint8, np.uint16):
        array = (array.astype(np.float64) * (255.0 / maxval)).astype(np.float32)
    elif array.dtype == np.uint16:
        array = array.astype(np.float32) / 257.0
    elif array.dtype == np.uint8:
        array = array.astype(np.float32)
    else:
        raise ValueError(f"path: {str(path)!r} holds {array.dtype} pixels; expected an 8- or 16-bit image")
    if array.ndim == 2:
        array = np.repeat(array[:, :, None], 3, axis=2)
    elif array.shape[2] == 4:
        array = array[:, :, :3]
    elif array.shape[2] != 3:
        raise ValueError(f"path: {str(path)!r} has {array.shape[2]} channels; expected 1, 3 or 4")
    rgb = np.ascontiguousarray(array[:, :, ::-1].transpose(2, 0, 1))
    return torch.from_numpy(rgb)


def _netpbm_maxval(path: str | os.PathLike) -> int | None:
    """The value of white in OpenCV's decoding of a PGM or PPM file (``P2``, ``P3``, ``P5``,
    ``P6``: the magic, then width, height and maxval, with ``#`` comments between): its maxval,
    or 255 for a plain-text (``P2``, ``P3``) file of maxval < 256, whose values OpenCV scales
    itself; None for another file."""
    with open(path, "rb") as f:
        head = f.read(4096)
    if head[:2] not in (b"P2", b"P3", b"P5", b"P6"):
        return None
    tokens = re.sub(rb"#[^\n\r]*", b" ", head[2:]).split()  # (past maxval the data may hold anything)
    if len(tokens) < 3 or not tokens[2].isdigit() or not 1 <= int(tokens[2][:6]) <= 65535:
        return None
    return 255 if head[:2] in (b"P2", b"P3") and int(tokens[2]) < 256 else int(tokens[2])


def write_image(path: str | os.PathLike, image: Tensor | np.ndarray) -> Path:
    """Write an image atomically as 8-bit, in a format :func:`read_image` reads back (by suffix:
    .png, .tif/.tiff, .jpg/.jpeg, .bmp, .webp; another suffix is a ValueError naming ``path``).

    Args:
        image: (3, H, W) RGB, or (1, H, W) / (H, W) grey (written as three equal channels to
            .webp, which stores no grey), float on the 0..255 scale (rounded to the nearest
            integer) or uint8; a tensor or a NumPy array (any strides and byte order). Values may
            exceed 0..255 by at most 0.5 (rounding). A float image whose brightest value is in
            (0, 1] is a ValueError naming ``image``, as in the library's image checks: it is a 0..1
            image or a 0/1 float mask, which would be written near black (levels 0 and 1); scale
            it by 255, write a mask with :func:`~fsof_torch.io.write_road_mask`, or pass uint8 for
            an image of real grey levels 0 and 1. An all-zero float image is written black.
    """
    if isinstance(image, np.ndarray):
        image = tensor_from_array(image)
    if not isinstance(image, Tensor):
        raise TypeError(f"image: expected a tensor of shape (3, H, W), (1, H, W) or (H, W), got {type(image).__name__}")
    given = tuple(image.shape)  # (quoted as it came, not as unsqueezed)
    if image.dim() == 3 and image.shape[0] in (1, 3):
        pass
    elif image.dim() == 2:
        image = image.unsqueeze(0)
    else:
        raise ValueError(f"image: expected shape (3, H, W), (1, H, W) or (H, W), got {given}")
    if min(image.shape[-2:]) < 1:
        raise ValueError(f"image: expected H, W >= 1, got shape {given}")
    check_has_values(image, "image")
    image = image.detach().cpu()
    if image.dtype == torch.uint8:
        array = image.numpy()
    else:
        if image.dtype == torch.bool:
            raise TypeError("image: expected a float or uint8 tensor, got dtype torch.bool (use write_road_mask)")
        values = image.double()
        if not bool(torch.isfinite(values).all()):
            raise ValueError("image: expected finite values, got NaN or inf")
        lo, hi = float(values.min()), float(values.max())
        if lo < -0.5 or hi > 255.5:
            raise ValueError(f"image: expected values on the 0..255 scale, got the range [{lo:.4g}, {hi:.4g}]")
        if 0.0 < hi <= 1.0:
            # (a float 0/1 mask too: far likelier than a float image of grey levels 0 and 1, which uint8 writes)
            raise ValueError(f"image: values in [{lo:.4g}, {hi:.4g}] look like a 0..1 image or a 0/1 mask, expected "
                             f"the 0..255 scale: scale it by 255 (rounded, its values would be 0 and 1: near "
                             f"black); write a mask with write_road_mask, real grey levels 0 and 1 as uint8")
        array = values.round().clamp(0, 255).to(torch.uint8).numpy()
    array = array.transpose(1, 2, 0)
    if array.shape[2] == 1 and 1 not in WRITABLE_CHANNELS.get(as_path(path).suffix.lower(), (1,)):
        array = np.repeat(array, 3, axis=2)  # .webp stores no grey; read_image repeats grey to 3 channels anyway
    array = array[:, :, 0] if array.shape[2] == 1 else array[:, :, ::-1]
    return write_image_array(path, np.ascontiguousarray(array))
