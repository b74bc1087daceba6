"""Fast lossless PNG encoding of 8-bit images for the data set (any PNG reader decodes them).

Pillow's PNG writer picks a filter per row by trying all five, which costs about twice the compression itself on
480×320 RGB frames. Here every row uses the *up* filter (the row minus the row above, computed by numpy in one
pass), then deflate at level 1 by ISA-L (`isal`, zlib-compatible streams, ~5× faster than zlib level 1 and a
little smaller; plain `zlib` if `isal` is not installed). `benchmarks/bench_generate.py` prints the figures of this
machine next to Pillow's encoder.

    data = png_bytes(image)           # (H, W) grey, (H, W, 3) RGB or (H, W, 4) RGBA uint8
    record = {"bytes": data, "path": None}   # a `datasets.Image` value
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

try:
    from isal.isal_zlib import compress as _deflate  # levels 0-3
except ImportError:  # the declared dependency is missing: the same PNG, slower
    from zlib import compress as _deflate

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
COLOR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}  # channels -> PNG colour type: grey, grey+alpha, RGB, RGBA
FILTER_UP = 2
MAX_LEVEL = 3 if _deflate.__module__.startswith("isal") else 9


def _chunk(tag: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + tag + payload + struct.pack(">I", zlib.crc32(tag + payload))


def png_bytes(image: np.ndarray, level: int = 1) -> bytes:
    """A PNG file (bytes) of an 8-bit image: (H, W) grey, or (H, W, C) with C = 1 (grey), 2, 3 (RGB) or 4 (RGBA).

    Args:
        image: uint8 pixels, rows top to bottom.
        level: deflate effort, 0 (fastest) to 9 (smallest); 1 is the fast default (ISA-L caps it at 3).

    Raises:
        ValueError: the array is not uint8, has another shape, is empty, or `level` is outside [0, 9].
    """
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"png_bytes: image dtype {image.dtype}: must be uint8")
    shape = image.shape
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[2] not in COLOR_TYPES or image.shape[0] < 1 or image.shape[1] < 1:
        raise ValueError(f"png_bytes: image shape {shape}: must be (H, W) or (H, W, 1|2|3|4) with H, W >= 1")
    if not 0 <= level <= 9:
        raise ValueError(f"png_bytes: level = {level}: must be in [0, 9]")
    h, w, channels = image.shape
    rows = image.reshape(h, w * channels)
    filtered = np.empty((h, w * channels + 1), np.uint8)  # each row: filter byte, then the filtered bytes
    filtered[:, 0] = FILTER_UP
    filtered[0, 1:] = rows[0]  # the row above the first is zeros
    np.subtract(rows[1:], rows[:-1], out=filtered[1:, 1:])  # uint8 arithmetic wraps modulo 256, as PNG wants
    header = struct.pack(">IIBBBBB", w, h, 8, COLOR_TYPES[channels], 0, 0, 0)
    return (
        PNG_SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", _deflate(filtered.data, min(level, MAX_LEVEL)))
        + _chunk(b"IEND", b"")
    )
