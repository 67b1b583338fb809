"""Point clouds as binary little-endian PLY files, with a scalar attribute per point.

The file holds one ``vertex`` element: ``double x, y, z`` (so positions round-trip bit for bit),
then one scalar property per attribute, its PLY type given by the array's dtype::

    float32 -> float    float64 -> double    int32 -> int     uint32 -> uint
    int16   -> short    uint16  -> ushort    int8  -> char    uint8  -> uchar

e.g. ``variance_z_m2`` (float32), ``kind`` (uint8), ``point_id`` (int32).
Open3D (``open3d.t.io.read_point_cloud``), CloudCompare and MeshLab read these files.

:func:`read_points_ply` also reads binary big-endian files, ``float`` x/y/z and files with other
elements (it reads the vertex element and skips the rest), but not ASCII PLY or list properties
in the vertex element.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from dem_graph.errors import DatasetError, DemGraphError

# PLY scalar type names (with their sized aliases) and numpy kinds
_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip
_WRITE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint", "f4": "float", "f8": "double"}
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_MAX_HEADER_BYTES = 1 << 20


def write_points_ply(path: str | Path, points_xyz, attributes: dict[str, np.ndarray] | None = None) -> None:
    """Write (N, 3) points and their per-point scalar attributes as a binary little-endian PLY.

    ``attributes`` maps a name (letters, digits, underscores; not x, y or z) to an (N,) array whose
    dtype is one of the eight PLY scalar types (see the module). Other dtypes (int64, bool, ...)
    are refused rather than silently converted: cast them first. N may be 0.

    Raises :class:`DemGraphError` for bad arguments, :class:`DatasetError` when the file cannot be written.
    """
    path = Path(path)
    attributes = {} if attributes is None else attributes
    points = np.asarray(points_xyz, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise DemGraphError(f"points must be an (N, 3) array, got shape {points.shape}")
    n = len(points)

    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    header = ["ply", "format binary_little_endian 1.0", "comment written by dem_graph", f"element vertex {n}"]
    header += [f"property double {c}" for c in "xyz"]
    columns = {}
    for name, values in attributes.items():
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise DemGraphError(f"point attribute name {name!r} is not a valid PLY property name (letters, digits, _)")
        if name in ("x", "y", "z"):
            raise DemGraphError(f"point attribute name {name!r} clashes with the positions")
        a = np.asarray(values)
        if a.shape != (n,):
            raise DemGraphError(f"point attribute {name!r} must have shape ({n},), got {a.shape}")
        code = f"{a.dtype.kind}{a.dtype.itemsize}"
        if code not in _WRITE_NAMES:
            raise DemGraphError(
                f"point attribute {name!r} has dtype {a.dtype}, which PLY cannot store; "
                "use float32, float64, int8/16/32 or uint8/16/32"
            )
        fields.append((name, "<" + code))
        header.append(f"property {_WRITE_NAMES[code]} {name}")
        columns[name] = a
    header.append("end_header")

    body = np.empty(n, dtype=np.dtype(fields))
    body["x"], body["y"], body["z"] = points[:, 0], points[:, 1], points[:, 2]
    for name, a in columns.items():
        body[name] = a
    try:
        with open(path, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(body.tobytes())
    except OSError as exc:
        raise DatasetError(path, f"cannot write ({exc.strerror or exc})") from None


def read_points_ply(path: str | Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read the vertex element of a binary PLY: ``(points_xyz (N, 3) float64, {name: (N,) array})``.

    Attributes keep their stored dtype (native byte order) and the file's property order.
    Raises :class:`DatasetError` naming the file when it is missing, not a PLY, uses an unsupported
    layout, lacks x, y or z, or is shorter than its header says.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "file not found" if not path.exists() else "not a regular file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(path, f"cannot read ({exc.strerror or exc})") from None

    if not data.startswith(b"ply\n") and not data.startswith(b"ply\r\n"):
        raise DatasetError(path, "not a PLY file (it does not start with 'ply')")
    header_lines: list[str] = []
    pos = 0
    while True:
        newline = data.find(b"\n", pos, _MAX_HEADER_BYTES)
        if newline < 0:
            raise DatasetError(path, "PLY header has no 'end_header' line")
        try:
            line = data[pos:newline].decode("ascii").rstrip("\r")
        except UnicodeDecodeError:
            raise DatasetError(path, "PLY header is not ASCII text") from None
        pos = newline + 1
        if line.strip() == "end_header":
            break
        header_lines.append(line)
    body_start = pos

    byte_order = None
    elements: list[tuple[str, int, list[tuple[str, str]], bool]] = []  # name, count, properties, has_list
    for line_no, line in enumerate(header_lines[1:], start=2):
        tokens = line.split()
        if not tokens or tokens[0] in ("comment", "obj_info"):
            continue
        keyword = tokens[0]
        if keyword == "format":
            if len(tokens) != 3:
                raise DatasetError(path, f"header line {line_no}: malformed format line {line!r}")
            if tokens[1] == "ascii":
                raise DatasetError(path, "ASCII PLY is not supported (binary only)")
            if tokens[1] not in ("binary_little_endian", "binary_big_endian"):
                raise DatasetError(path, f"header line {line_no}: unknown PLY format {tokens[1]!r}")
            byte_order = "<" if tokens[1] == "binary_little_endian" else ">"
        elif keyword == "element":
            if len(tokens) != 3 or not tokens[2].isdigit():
                raise DatasetError(path, f"header line {line_no}: malformed element line {line!r}")
            elements.append((tokens[1], int(tokens[2]), [], False))
        elif keyword == "property":
            if not elements:
                raise DatasetError(path, f"header line {line_no}: property before any element")
            name, count, props, has_list = elements[-1]
            if len(tokens) >= 2 and tokens[1] == "list":
                if len(tokens) != 5:
                    raise DatasetError(path, f"header line {line_no}: malformed list property {line!r}")
                elements[-1] = (name, count, props, True)
                continue
            if len(tokens) != 3 or tokens[1] not in _PLY_TYPES:
                raise DatasetError(path, f"header line {line_no}: malformed or unknown property {line!r}")
            if any(p == tokens[2] for p, _ in props):
                raise DatasetError(path, f"header line {line_no}: property {tokens[2]!r} appears twice")
            props.append((tokens[2], _PLY_TYPES[tokens[1]]))
        else:
            raise DatasetError(path, f"header line {line_no}: unknown keyword {keyword!r}")
    if byte_order is None:
        raise DatasetError(path, "PLY header has no format line")

    offset = body_start
    for name, count, props, has_list in elements:
        if name == "vertex":
            break
        if has_list:
            raise DatasetError(path, f"element {name!r} before the vertices has list properties; cannot skip it")
        offset += count * sum(np.dtype(code).itemsize for _, code in props)
    else:
        raise DatasetError(path, "PLY file has no vertex element")
    if has_list:
        raise DatasetError(path, "the vertex element has list properties, which are not supported")
    names = [p for p, _ in props]
    missing = [c for c in "xyz" if c not in names]
    if missing:
        raise DatasetError(path, f"the vertex element has no {', '.join(missing)} property")

    dtype = np.dtype([(p, byte_order + code) for p, code in props])
    needed = count * dtype.itemsize
    if len(data) - offset < needed:
        raise DatasetError(
            path, f"truncated: the header announces {count} vertices ({needed} bytes), the file holds {max(len(data) - offset, 0)}"
        )
    body = np.frombuffer(data, dtype=dtype, count=count, offset=offset) if count else np.empty(0, dtype=dtype)
    points = np.stack([body[c].astype(np.float64) for c in "xyz"], axis=1)
    attributes = {p: body[p].astype(np.dtype(code).newbyteorder("=")) for p, code in props if p not in ("x", "y", "z")}
    return points, attributes
