"""Loading and checking images: every failure is an InputError that names the file; sizes are checked
from the header (max_pixels) before anything is decoded."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from edgecal.errors import InputError
from edgecal.fileio import permission_denied, read_input
from edgecal.imageheader import image_size

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
# The largest image read by default: 2^26 pixels (8192x8192, 64 MB grey / 192 MB BGR decoded), above
# room for the 65 MP machine-vision sensors; a bigger file is refused before it is decoded.
DEFAULT_MAX_PIXELS = 1 << 26


def as_grey(image: np.ndarray, name: str = "image") -> np.ndarray:
    """A contiguous uint8 grey view/copy of ``image`` (uint8 grey, BGR or BGRA).

    uint16 images are scaled to 8 bits by their actual range; any other dtype or shape is an error.
    """
    if not isinstance(image, np.ndarray):
        raise InputError(f"{name}: expected a numpy array, got {type(image).__name__}")
    if image.size == 0:
        raise InputError(f"{name}: the image is empty")
    if image.dtype == np.uint16:
        hi = int(image.max())
        shift = max(0, hi.bit_length() - 8)
        image = (image >> shift).astype(np.uint8)
    if image.dtype != np.uint8:
        raise InputError(f"{name}: expected a uint8 (or uint16) image, got dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    elif image.ndim != 2:
        raise InputError(f"{name}: expected a grey (H, W) or colour (H, W, 3) image, got shape {image.shape}")
    return np.ascontiguousarray(image)


def read_image(path: str | Path, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """An image file's pixels unchanged (grey, BGR or BGRA; uint8 or uint16).

    InputError naming the file if it is missing, not readable by this user ("permission denied"), not
    an image, or larger than ``max_pixels`` - the last read from the header, before anything is decoded
    (a small PNG can hold GBs of pixels). A format whose header edgecal does not read is checked after
    decoding (OpenCV's own limit, 2^30 pixels, still applies to it).
    """
    p = Path(path)
    data = read_input(p, "image file")
    if not data:
        raise InputError(f"{p}: the file is empty")
    size = image_size(data)
    if size is not None:
        _check_pixels(p, size, max_pixels)
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        image = None
    if image is None:
        raise InputError(f"{p}: not a readable image (PNG, JPEG, BMP, TIFF, PGM ...)")
    if size is None:
        _check_pixels(p, (image.shape[1], image.shape[0]), max_pixels)
    return image


def _check_pixels(path: Path, size: tuple[int, int], max_pixels: int) -> None:
    w, h = size
    if w * h > max_pixels:
        raise InputError(f"{path}: {w}x{h} is {w * h / 1e6:.3g} MP, more than max_pixels ({max_pixels / 1e6:.3g} MP); "
                         "refused before decoding (raise --max-pixels or the source's max_pixels to read it)")


def load_grey(path: str | Path, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Read an image file as uint8 grey (see :func:`read_image` for the errors)."""
    return as_grey(read_image(path, max_pixels), str(path))


_DIGITS = re.compile(r"(\d+)")


def natural_key(path: str | Path) -> tuple:
    """Sort key that orders numbers inside names by value: ``img2.png`` before ``img10.png``.

    Camera tools number files without leading zeros (left1 .. left14, Fisheye1_2 .. Fisheye1_10); a plain
    string sort would interleave them and pair the wrong stereo images.
    """
    parts = _DIGITS.split(str(path))
    return tuple((0, int(t), t) if i % 2 else (1, t.casefold(), t) for i, t in enumerate(parts))


def image_files(folder: Path) -> list[Path]:
    """The image files of ``folder`` in natural name order (2 before 10)."""
    try:
        names = list(folder.iterdir())
    except PermissionError:
        raise permission_denied(folder, "image folder") from None
    except OSError as exc:
        raise InputError(f"{folder}: cannot list the folder ({exc.strerror or exc})") from None
    return sorted((f for f in names if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)


def expand_image_args(paths: list[str]) -> list[Path]:
    """Expand folders into their image files (natural name order); files are kept in the order given."""
    out: list[Path] = []
    for item in paths:
        p = Path(item)
        if p.is_dir():
            files = image_files(p)
            if not files:
                raise InputError(f"{p}: the folder holds no images ({', '.join(IMAGE_SUFFIXES)})")
            out.extend(files)
        else:
            out.append(p)
    return out
