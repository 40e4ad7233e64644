"""A small PLY point reader (ASCII and binary), so loading points needs no open3d.

Reads the ``vertex`` element: x, y, z and, when present, red, green, blue. Elements before the
vertex element may only have scalar properties (true of every point-cloud PLY we meet).
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from edygs_ns.io.images import UINT8_MAX

#: PLY scalar type names (both spellings) and their numpy type codes.
PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
#: PLY format names and the numpy byte-order prefix (None for ASCII).
PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
#: Colour of points that carry none (mid grey, 8-bit).
DEFAULT_POINT_GREY = 128
#: Most header lines read before giving up (guards against non-PLY files).
MAX_HEADER_LINES = 1000


def _parse_header(handle, path: Path) -> Tuple[str, List[Tuple[str, int, List[Tuple[str, str]]]]]:
    """Read the header: (format, [(element name, count, [(property name, type code)])])."""
    if handle.readline().strip() != b"ply":
        raise ValueError(f"{path}: not a PLY file (first line is not 'ply')")
    fmt = None
    elements: List[Tuple[str, int, List[Tuple[str, str]]]] = []
    for _ in range(MAX_HEADER_LINES):
        line = handle.readline()
        if not line:
            break
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            if fmt is None:
                raise ValueError(f"{path}: PLY header has no 'format' line")
            return fmt, elements
        if words[0] == "format":
            if len(words) < 2 or words[1] not in PLY_FORMATS:
                raise ValueError(f"{path}: unsupported PLY format line {line!r}")
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise ValueError(f"{path}: PLY property before any element")
            if words[1] == "list":
                elements[-1][2].append((words[-1], "list"))
            elif words[1] in PLY_TYPES:
                elements[-1][2].append((words[2], PLY_TYPES[words[1]]))
            else:
                raise ValueError(f"{path}: unknown PLY property type {words[1]!r}")
    raise ValueError(f"{path}: PLY header has no 'end_header' line")


def read_ply_points(path: Path) -> Tuple[np.ndarray, np.ndarray]:
    """Read the points of a PLY file.

    Args:
        path: .ply file with a ``vertex`` element holding x, y, z (any scalar type) and
            optionally red, green, blue (uchar 0..255, or float 0..1).

    Returns:
        (xyz [P, 3] float32, rgb [P, 3] uint8); points without colour are grey.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a PLY file, no vertex element or no x/y/z, or a list property before the
            vertex element; the message names the file.
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: PLY file not found")
    with open(path, "rb") as handle:
        fmt, elements = _parse_header(handle, path)
        order = PLY_FORMATS[fmt]
        vertex: Optional[np.ndarray] = None
        for name, count, props in elements:
            if any(kind == "list" for _, kind in props):
                if name == "vertex":
                    raise ValueError(f"{path}: the vertex element has a list property, which is not supported")
                if vertex is None:
                    raise ValueError(f"{path}: element {name!r} with list properties precedes 'vertex'")
                break
            dtype = np.dtype([(prop, (order or "<") + code) for prop, code in props])
            if order is None:
                rows = [handle.readline().split() for _ in range(count)]
                table = np.zeros(count, dtype=dtype)
                if count:
                    values = np.asarray(rows, dtype=np.float64)
                    for col, (prop, _) in enumerate(props):
                        table[prop] = values[:, col]
            else:
                table = np.frombuffer(handle.read(dtype.itemsize * count), dtype=dtype, count=count)
            if name == "vertex":
                vertex = table
                break
    if vertex is None:
        raise ValueError(f"{path}: PLY file has no 'vertex' element")
    names = vertex.dtype.names or ()
    if not all(axis in names for axis in ("x", "y", "z")):
        raise ValueError(f"{path}: PLY vertex element lacks x, y, z (has {names})")
    xyz = np.stack([vertex[a].astype(np.float32) for a in ("x", "y", "z")], axis=-1)
    if all(c in names for c in ("red", "green", "blue")):
        rgb = np.stack([vertex[c] for c in ("red", "green", "blue")], axis=-1)
        if rgb.dtype.kind == "f":
            rgb = np.clip(np.round(rgb * UINT8_MAX), 0, UINT8_MAX)
        rgb = rgb.astype(np.uint8)
    else:
        rgb = np.full((len(xyz), 3), DEFAULT_POINT_GREY, dtype=np.uint8)
    return xyz, rgb


def write_ply_points(path: Path, xyz: np.ndarray, rgb: np.ndarray, binary: bool = True) -> None:
    """Write points [P, 3] float and colours [P, 3] uint8 as a PLY file (for fixtures and tools)."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    rgb = np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)
    if len(xyz) != len(rgb):
        raise ValueError(f"write_ply_points: {len(xyz)} positions but {len(rgb)} colours")
    fmt = "binary_little_endian" if binary else "ascii"
    header = (
        f"ply\nformat {fmt} 1.0\nelement vertex {len(xyz)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        if binary:
            table = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                              ("red", "u1"), ("green", "u1"), ("blue", "u1")])
            for col, axis in enumerate(("x", "y", "z")):
                table[axis] = xyz[:, col]
            for col, channel in enumerate(("red", "green", "blue")):
                table[channel] = rgb[:, col]
            handle.write(table.tobytes())
        else:
            for p, c in zip(xyz, rgb):
                handle.write(f"{p[0]:.7g} {p[1]:.7g} {p[2]:.7g} {c[0]} {c[1]} {c[2]}\n".encode("ascii"))
