"""VTK XML PolyData (.vtp) writer for per-sample point fields, readable by ParaView.

One vertex cell per point; point arrays as raw little-endian binary appended data (base64 is not
needed: the format's `raw` encoding with a 4-byte header per array is what ParaView reads).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

_VTK_TYPES = {np.dtype("float32"): "Float32", np.dtype("float64"): "Float64",
              np.dtype("int32"): "Int32", np.dtype("int64"): "Int64", np.dtype("uint8"): "UInt8"}


def _as_vtk_array(values: np.ndarray) -> np.ndarray:
    values = np.asarray(values)
    if values.dtype == bool:
        values = values.astype(np.uint8)
    elif values.dtype.kind in "iu" and values.dtype not in _VTK_TYPES:
        values = values.astype(np.int64)
    elif values.dtype.kind == "f" and values.dtype not in _VTK_TYPES:
        values = values.astype(np.float64)
    return np.ascontiguousarray(values.astype(values.dtype.newbyteorder("<")))


def write_points(path, points: np.ndarray, arrays: dict[str, np.ndarray]) -> None:
    """Write `points` (N, 3) with point `arrays` (each (N,) or (N, k)) to a .vtp file."""
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    blocks, headers, offset = [], [], 0

    def add(data: np.ndarray, xml: str):
        nonlocal offset
        raw = data.tobytes()
        blocks.append(struct.pack("<I", len(raw)) + raw)
        headers.append(xml.format(offset=offset))
        offset += 4 + len(raw)

    add(_as_vtk_array(points), '<DataArray type="Float64" NumberOfComponents="3" '
                               'format="appended" offset="{offset}"/>')
    point_xml_start = len(headers)
    for name, values in arrays.items():
        data = _as_vtk_array(values)
        if data.shape[0] != n:
            raise ValueError(f"array {name!r} has {data.shape[0]} values for {n} points")
        comps = 1 if data.ndim == 1 else data.shape[1]
        add(data, f'<DataArray type="{_VTK_TYPES[data.dtype]}" Name="{name}" '
                  f'NumberOfComponents="{comps}" format="appended" offset="{{offset}}"/>')
    add(np.arange(n, dtype="<i8"), '<DataArray type="Int64" Name="connectivity" '
                                   'format="appended" offset="{offset}"/>')
    add(np.arange(1, n + 1, dtype="<i8"), '<DataArray type="Int64" Name="offsets" '
                                          'format="appended" offset="{offset}"/>')
    point_data = "\n".join(headers[point_xml_start:-2])
    xml = (
        '<?xml version="1.0"?>\n'
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt32">\n'
        "<PolyData>\n"
        f'<Piece NumberOfPoints="{n}" NumberOfVerts="{n}" NumberOfLines="0" NumberOfStrips="0" '
        'NumberOfPolys="0">\n'
        f"<PointData>\n{point_data}\n</PointData>\n"
        f"<Points>\n{headers[0]}\n</Points>\n"
        f"<Verts>\n{headers[-2]}\n{headers[-1]}\n</Verts>\n"
        "</Piece>\n</PolyData>\n"
        '<AppendedData encoding="raw">\n_'
    )
    with open(Path(path), "wb") as fh:
        fh.write(xml.encode())
        for block in blocks:
            fh.write(block)
        fh.write(b"\n</AppendedData>\n</VTKFile>\n")


_NUMPY_TYPES = {v: k for k, v in _VTK_TYPES.items()}


def read_points(path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read a .vtp file written by `write_points`: points (N, 3) and the point arrays by name.
    Raises ValueError when the file is not such a file (e.g. cut short by an interrupted run)."""
    import re

    data = Path(path).read_bytes()
    head, sep, body = data.partition(b'<AppendedData encoding="raw">\n_')
    if not sep:
        raise ValueError(f"{Path(path).name}: no appended raw data block")
    tags = re.findall(rb"<DataArray ([^>]*)/>", head)

    def block(offset: int, dtype: np.dtype) -> np.ndarray:
        if offset + 4 > len(body):
            raise ValueError(f"{Path(path).name}: truncated")
        (size,) = struct.unpack_from("<I", body, offset)
        if offset + 4 + size > len(body):
            raise ValueError(f"{Path(path).name}: truncated")
        return np.frombuffer(body, dtype=dtype.newbyteorder("<"), count=size // dtype.itemsize,
                             offset=offset + 4)

    points, arrays = None, {}
    for tag in tags:
        attrs = dict(re.findall(r'(\w+)="([^"]*)"', tag.decode()))
        values = block(int(attrs["offset"]), _NUMPY_TYPES[attrs["type"]])
        comps = int(attrs.get("NumberOfComponents", 1))
        values = values.reshape(-1, comps) if comps > 1 else values
        name = attrs.get("Name")
        if name is None:
            points = values
        elif name not in ("connectivity", "offsets"):
            arrays[name] = values
    if points is None:
        raise ValueError(f"{Path(path).name}: no points")
    return points, arrays
