"""Reading points and point arrays from VTK XML files: `.vtu` (UnstructuredGrid), `.vtp` (PolyData)
and `.pvd` collections of them (one file per time step), as finite-element exporters write them.

The subset read (VTK file formats, "XML File Formats", https://docs.vtk.org/en/latest/design_documents/VTKFileFormats.html):

* `<VTKFile type="UnstructuredGrid|PolyData" byte_order="LittleEndian|BigEndian"
  header_type="UInt32|UInt64" compressor="vtkZLibDataCompressor|vtkLZMADataCompressor">`; every
  `<Piece>` (its points and point data concatenated in piece order);
* `<Points>` and `<PointData>` `<DataArray type=... NumberOfComponents=... format=...>` with
  `format="ascii"` (numbers in the text), `"binary"` (base64 in the text) or `"appended"` (at
  `offset` in `<AppendedData encoding="raw|base64">` after its `_` mark); types Int8 ... UInt64,
  Float32, Float64.
* Binary data is a header then the bytes. Uncompressed, the header is one integer: the byte count.
  Compressed, it is `[n_blocks, block_size, last_block_size, compressed_size_1 ... _n]` and each
  block is compressed on its own. With base64, the header and the data may be encoded as one
  stream or as two (VTK's own writer encodes them separately); both are read.

Not read, with a ConfigError saying so: legacy `.vtk` files, LZ4 compression (not in Python's
standard library: save with ZLib or no compression), other dataset types. A `.pvd` names its
files relative to itself: `<Collection><DataSet timestep="t" file="..."/></Collection>`.
"""

from __future__ import annotations

import base64
import binascii
import lzma
import math
import re
import zlib
from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree

import numpy as np

from vdo.core.errors import ConfigError

DATASETS = {".vtu": "UnstructuredGrid", ".vtp": "PolyData"}
_TYPES = {"Int8": "i1", "UInt8": "u1", "Int16": "i2", "UInt16": "u2", "Int32": "i4", "UInt32": "u4",
          "Int64": "i8", "UInt64": "u8", "Float32": "f4", "Float64": "f8"}
_DECOMPRESS = {"vtkZLibDataCompressor": zlib.decompress, "vtkLZMADataCompressor": lzma.decompress}


@dataclass(frozen=True, eq=False)
class PointData:
    """The points (N, 3) of a VTK dataset and its point arrays, each (N,) or (N, k), float64."""

    points: np.ndarray
    arrays: dict


@dataclass(frozen=True)
class _Format:
    """How a file stores binary arrays."""

    order: str            # "<" or ">"
    header: str           # numpy dtype of the header integers
    decompress: object    # None or bytes -> bytes


def _split_appended(raw: bytes, file: Path) -> tuple[bytes, bytes | None, str | None]:
    """(XML text without the appended block's content, the appended content after '_', its
    encoding). Raw appended data is not XML, so it is cut out before parsing."""
    start = raw.find(b"<AppendedData")
    if start < 0:
        return raw, None, None
    tag_end = raw.find(b">", start)
    mark = raw.find(b"_", tag_end)
    end = raw.rfind(b"</AppendedData>")
    if tag_end < 0 or mark < 0 or end < mark:
        raise ConfigError(file, "AppendedData", "is not closed, or has no '_' before its data")
    tag = raw[start:tag_end + 1].decode("latin-1")
    encoding = re.search(r'encoding\s*=\s*"([^"]*)"', tag)
    encoding = encoding.group(1) if encoding else "raw"
    xml = raw[:start] + b"<AppendedData/>" + raw[end + len(b"</AppendedData>"):]
    return xml, raw[mark + 1:end], encoding


def _ints(data: bytes, fmt: _Format, count: int) -> list[int]:
    return [int(v) for v in np.frombuffer(data, dtype=np.dtype(fmt.header).newbyteorder(fmt.order),
                                          count=count)]


def _decoded(text: bytes, n_bytes: int) -> tuple[bytes, int]:
    """The first `n_bytes` bytes of base64 `text` and the characters they took (a whole 4-char
    group per 3 bytes; '=' padding ends a stream)."""
    n_chars = 4 * math.ceil(n_bytes / 3)
    return base64.b64decode(text[:n_chars], validate=False)[:n_bytes], n_chars


def _binary_payload(data: bytes, fmt: _Format, base64_encoded: bool, file, name) -> bytes:
    """The array's bytes (decompressed) from `data`, which starts with the array's header."""
    size = np.dtype(fmt.header).itemsize
    try:
        if not base64_encoded:
            if fmt.decompress is None:
                (n,) = _ints(data[:size], fmt, 1)
                return data[size:size + n]
            (n_blocks,) = _ints(data[:size], fmt, 1)
            head = _ints(data[:(3 + n_blocks) * size], fmt, 3 + n_blocks)
            body, pos = [], (3 + n_blocks) * size
            for c in head[3:]:
                body.append(fmt.decompress(data[pos:pos + c]))
                pos += c
            return b"".join(body)
        text = re.sub(rb"\s+", b"", data)
        first, _ = _decoded(text, size)
        (n_words,) = _ints(first, fmt, 1)
        header_words = 1 if fmt.decompress is None else 3 + n_words
        header_bytes = header_words * size
        head_raw, head_chars = _decoded(text, header_bytes)
        head = _ints(head_raw, fmt, header_words)
        data_bytes = head[0] if fmt.decompress is None else sum(head[3:])
        if b"=" in text[:head_chars]:                 # two streams: header, then data
            body = base64.b64decode(text[head_chars:head_chars + 4 * math.ceil(data_bytes / 3)])
        else:                                         # one stream
            whole = base64.b64decode(text[:4 * math.ceil((header_bytes + data_bytes) / 3)])
            body = whole[header_bytes:]
        if fmt.decompress is None:
            return body[:data_bytes]
        out, pos = [], 0
        for c in head[3:]:
            out.append(fmt.decompress(body[pos:pos + c]))
            pos += c
        return b"".join(out)
    except (ValueError, binascii.Error, zlib.error, lzma.LZMAError) as exc:
        raise ConfigError(file, f"DataArray {name!r}", f"its binary data cannot be decoded ({exc})") from None


def _array(element, fmt: _Format, appended, encoding, file) -> np.ndarray:
    """One DataArray as float64, (n,) or (n, components)."""
    name = element.get("Name", "Points")
    kind = element.get("type")
    if kind not in _TYPES:
        raise ConfigError(file, f"DataArray {name!r}", f"type {kind!r} is not one of {', '.join(_TYPES)}")
    components = int(element.get("NumberOfComponents", "1"))
    form = element.get("format", "ascii")
    dtype = np.dtype(_TYPES[kind]).newbyteorder(fmt.order)
    if form == "ascii":
        try:
            values = np.array((element.text or "").split(), dtype=float)
        except ValueError as exc:
            raise ConfigError(file, f"DataArray {name!r}", f"ASCII data is not numbers ({exc})") from None
    elif form in ("binary", "appended"):
        if form == "binary":
            payload = _binary_payload((element.text or "").strip().encode("ascii"), fmt, True, file, name)
        else:
            if appended is None:
                raise ConfigError(file, f"DataArray {name!r}", "is 'appended' but the file has no AppendedData")
            if encoding not in ("raw", "base64"):
                raise ConfigError(file, "AppendedData", f"encoding {encoding!r} is not raw or base64")
            offset = int(element.get("offset", "0"))
            payload = _binary_payload(appended[offset:], fmt, encoding == "base64", file, name)
        values = np.frombuffer(payload[:len(payload) // dtype.itemsize * dtype.itemsize],
                               dtype=dtype).astype(float)
    else:
        raise ConfigError(file, f"DataArray {name!r}", f"format {form!r} is not ascii, binary or appended")
    if values.size % components:
        raise ConfigError(file, f"DataArray {name!r}", f"holds {values.size} values, not a multiple "
                                                       f"of its {components} components")
    return values.reshape(-1, components) if components > 1 else values


def read_points(file) -> PointData:
    """Points and point arrays of a `.vtu` or `.vtp` file (module docstring)."""
    file = Path(file)
    expected = DATASETS.get(file.suffix.lower())
    if expected is None:
        raise ConfigError(file, "", "is not a VTK XML .vtu or .vtp file (legacy .vtk files are not "
                                    "read: save as XML from ParaView)")
    try:
        raw = file.read_bytes()
    except OSError as exc:
        raise ConfigError(file, "", f"cannot be read ({exc})") from None
    xml, appended, encoding = _split_appended(raw, file)
    try:
        root = ElementTree.fromstring(xml)
    except ElementTree.ParseError as exc:
        raise ConfigError(file, "", f"is not a VTK XML file ({exc})") from None
    if root.tag != "VTKFile" or root.get("type") != expected:
        raise ConfigError(file, "VTKFile", f"expected a VTKFile of type {expected} for a "
                                           f"{file.suffix} file, got {root.tag} {root.get('type')!r}")
    compressor = root.get("compressor")
    if compressor and compressor not in _DECOMPRESS:
        raise ConfigError(file, "compressor", f"{compressor} is not supported: save with ZLib or no "
                                              "compression (ParaView: Save Data > Compressor)")
    header = root.get("header_type", "UInt32")
    if header not in ("UInt32", "UInt64"):
        raise ConfigError(file, "header_type", f"{header!r} is not UInt32 or UInt64")
    fmt = _Format(">" if root.get("byte_order") == "BigEndian" else "<", _TYPES[header],
                  _DECOMPRESS.get(compressor) if compressor else None)
    pieces = root.findall(f"{expected}/Piece")
    if not pieces:
        raise ConfigError(file, expected, "has no Piece")
    points, arrays = [], {}
    for k, piece in enumerate(pieces):
        n = int(piece.get("NumberOfPoints", "0"))
        element = piece.find("Points/DataArray")
        if element is None:
            raise ConfigError(file, f"Piece {k}", "has no Points")
        xyz = _array(element, fmt, appended, encoding, file)
        if xyz.shape != (n, 3):
            raise ConfigError(file, f"Piece {k}", f"Points hold {xyz.size} values; expected {n} x 3")
        points.append(xyz)
        for element in piece.findall("PointData/DataArray"):
            name = element.get("Name", "")
            values = _array(element, fmt, appended, encoding, file)
            if len(values) != n:
                raise ConfigError(file, f"point array {name!r}", f"has {len(values)} tuples for {n} points")
            arrays.setdefault(name, []).append(values)
    arrays = {name: np.concatenate(parts) for name, parts in arrays.items() if len(parts) == len(pieces)}
    return PointData(np.concatenate(points), arrays)


def collection(file) -> list[tuple[float, Path]]:
    """(timestep, file) of every DataSet of a `.pvd` collection, in the order of their timesteps
    (stable for equal ones); files relative to the collection."""
    file = Path(file)
    try:
        root = ElementTree.parse(file).getroot()
    except (OSError, ElementTree.ParseError) as exc:
        raise ConfigError(file, "", f"is not a readable .pvd collection ({exc})") from None
    sets = root.findall("Collection/DataSet")
    if root.tag != "VTKFile" or root.get("type") != "Collection" or not sets:
        raise ConfigError(file, "Collection", "expected <VTKFile type=\"Collection\"> with "
                                              "<Collection><DataSet timestep=... file=.../>")
    out = []
    for k, ds in enumerate(sets):
        try:
            t = float(ds.get("timestep", k))
        except ValueError:
            raise ConfigError(file, f"DataSet {k}", f"timestep {ds.get('timestep')!r} is not a number") from None
        if not ds.get("file"):
            raise ConfigError(file, f"DataSet {k}", "has no file attribute")
        out.append((t, file.parent / ds.get("file")))
    return sorted(out, key=lambda item: item[0])
