# SPDX-License-Identifier: GPL-3.0-or-later
"""A small OpenEXR reader for the render passes the extension writes (tests, the demo, scripts).

Not part of the shipped extension (``tools/`` is left out of the zip): Blender
reads its own EXRs; this reads multilayer scanline files with NONE, RLE, ZIPS
or ZIP compression and FLOAT/HALF/UINT channels, so a test can check the
``Translucency`` AOV without Blender.  Written by hand because the formats
Blender writes need only this much, and the PyPI readers (OpenEXR,
OpenImageIO) would add a compiled dependency to the test environment.
"""

from __future__ import annotations

import struct
import zlib

AOV_NAME = "Translucency"

_PIXEL_TYPES = {0: ("<u4", 4), 1: ("<f2", 2), 2: ("<f4", 4)}
_LINES_PER_BLOCK = {0: 1, 1: 1, 2: 1, 3: 16}  # NONE, RLE, ZIPS, ZIP
_COMPRESSION_NAMES = {0: "NONE", 1: "RLE", 2: "ZIPS", 3: "ZIP", 4: "PIZ", 5: "PXR24",
                      6: "B44", 7: "B44A", 8: "DWAA", 9: "DWAB"}


def _undo_predictor(raw: bytes) -> bytes:
    import numpy as np

    t = np.frombuffer(raw, np.uint8).astype(np.int64)
    if t.size:
        t[1:] -= 128
        t = np.cumsum(t) & 0xFF  # t[i] = t[i-1] + t[i] - 128 (mod 256)
    t = t.astype(np.uint8)
    half = (t.size + 1) // 2
    out = np.empty_like(t)
    out[0::2] = t[:half]
    out[1::2] = t[half:]
    return out.tobytes()


def _rle_decode(data: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(data):
        count = struct.unpack_from("b", data, i)[0]
        i += 1
        if count < 0:
            out += data[i:i - count]
            i -= count
        else:
            out += data[i:i + 1] * (count + 1)
            i += 1
    return bytes(out)


def _parse_header(data: bytes, pos: int):
    header = {}
    while data[pos] != 0:
        end = data.index(b"\0", pos)
        name = data[pos:end].decode()
        pos = end + 1
        end = data.index(b"\0", pos)
        kind = data[pos:end].decode()
        pos = end + 1
        size = struct.unpack_from("<i", data, pos)[0]
        pos += 4
        header[name] = (kind, data[pos:pos + size])
        pos += size
    return header, pos + 1


def _parse_channels(raw: bytes, path):
    channels = []
    i = 0
    while raw[i] != 0:
        end = raw.index(b"\0", i)
        name = raw[i:end].decode()
        pixel_type, _linear, xs, ys = struct.unpack_from("<iB3xii", raw, end + 1)
        if (xs, ys) != (1, 1):
            raise ValueError(f"{path}: subsampled channel {name!r} is not supported")
        channels.append((name, pixel_type))
        i = end + 1 + 16
    return channels


class _Part:
    def __init__(self, header, path):
        if header.get("type", ("", b"scanlineimage"))[1].rstrip(b"\0") != b"scanlineimage":
            raise ValueError(f"{path}: only scanline OpenEXR images are supported")
        self.channels = _parse_channels(header["channels"][1], path)
        self.compression = header["compression"][1][0]
        if self.compression not in _LINES_PER_BLOCK:
            raise ValueError(f"{path}: {_COMPRESSION_NAMES.get(self.compression, self.compression)} compression "
                             "is not supported (save with ZIP, ZIPS, RLE or no compression)")
        self.xmin, self.ymin, self.xmax, self.ymax = struct.unpack("<iiii", header["dataWindow"][1])
        self.width = self.xmax - self.xmin + 1
        self.height = self.ymax - self.ymin + 1
        self.lines = _LINES_PER_BLOCK[self.compression]
        if "chunkCount" in header:
            self.n_chunks = struct.unpack("<i", header["chunkCount"][1])[0]
        else:
            self.n_chunks = (self.height + self.lines - 1) // self.lines
        self.row_bytes = sum(_PIXEL_TYPES[t][1] for _n, t in self.channels) * self.width

    def decode(self, chunk: bytes, y: int, out: dict, path) -> None:
        import numpy as np

        n_lines = min(self.lines, self.ymax + 1 - y)
        expected = self.row_bytes * n_lines
        if len(chunk) != expected:  # stored raw when compression did not help
            if self.compression == 1:
                chunk = _undo_predictor(_rle_decode(chunk))
            elif self.compression in (2, 3):
                chunk = _undo_predictor(zlib.decompress(chunk))
        if len(chunk) != expected:
            raise ValueError(f"{path}: corrupt chunk at scanline {y}")
        at = 0
        for line in range(n_lines):
            row = y - self.ymin + line
            for name, pixel_type in self.channels:
                dtype, nbytes = _PIXEL_TYPES[pixel_type]
                out[name][row] = np.frombuffer(chunk, dtype, self.width, at).astype(np.float32)
                at += nbytes * self.width


def read_exr(path) -> dict:
    """Channels of a scanline OpenEXR file: ``{name: (height, width) float32}``.

    Single-part and multi-part files (Blender 5.0 writes a multilayer EXR as
    one part per pass, 4.x as one part).  Row 0 is the top of the image.
    Supports the NONE, RLE, ZIPS and ZIP codecs (Blender's default is ZIP)
    and raises ``ValueError`` for others.  Multilayer files name channels
    ``<view layer>.<pass>.<channel>``, e.g. ``ViewLayer.Translucency.R``.
    """
    import numpy as np

    with open(path, "rb") as fh:
        data = fh.read()
    if data[:4] != b"\x76\x2f\x31\x01":
        raise ValueError(f"{path}: not an OpenEXR file")
    flags = struct.unpack_from("<I", data, 4)[0]
    if flags & 0x200 or flags & 0x800:
        raise ValueError(f"{path}: tiled or deep OpenEXR files are not supported")
    multipart = bool(flags & 0x1000)
    pos = 8
    parts = []
    while True:
        header, pos = _parse_header(data, pos)
        parts.append(_Part(header, path))
        if not multipart or data[pos] == 0:
            break
    if multipart:
        pos += 1  # the empty header that ends the list
    offsets = []
    for part in parts:
        offsets.append(struct.unpack_from(f"<{part.n_chunks}Q", data, pos))
        pos += 8 * part.n_chunks

    out = {}
    for part in parts:
        for name, _t in part.channels:
            out[name] = np.zeros((part.height, part.width), np.float32)
    for index, part in enumerate(parts):
        for offset in offsets[index]:
            if multipart:
                number = struct.unpack_from("<i", data, offset)[0]
                if number != index:
                    raise ValueError(f"{path}: chunk of part {number} in the table of part {index}")
                offset += 4
            y, size = struct.unpack_from("<ii", data, offset)
            part.decode(data[offset + 8:offset + 8 + size], y, out, path)
    return out


def exr_pass(path, pass_name=AOV_NAME, view_layer=None):
    """One pass of a multilayer EXR as an (height, width, channels) array, top row first.

    Channels in R, G, B, A order (those present).  ``view_layer`` defaults to
    the only (or first) view layer that has the pass.
    """
    import numpy as np

    channels = read_exr(path)
    layers = []
    for name in channels:
        parts = name.rsplit(".", 2)
        if len(parts) == 3 and parts[1] == pass_name and parts[0] not in layers:
            layers.append(parts[0])
    if view_layer is None:
        if not layers:
            raise KeyError(f"{path}: no pass {pass_name!r}; channels: {sorted(channels)}")
        view_layer = layers[0]
    prefix = f"{view_layer}.{pass_name}."
    present = [c for c in "RGBA" if prefix + c in channels]
    if not present:
        present = sorted(name[len(prefix):] for name in channels if name.startswith(prefix))
        if not present:
            raise KeyError(f"{path}: no pass {pass_name!r} in view layer {view_layer!r}")
    return np.stack([channels[prefix + c] for c in present], axis=-1)
