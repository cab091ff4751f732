"""Streaming checks of PLY and PCD files before Open3D reads them.

Open3D only logs a warning on a bad file and may return a partly filled cloud (a
truncated PLY gives the declared number of vertices with garbage after the cut; a bad
token in an ASCII PLY leaves the rest of the cloud as uninitialised memory). So the
header is parsed here and the body checked against it, reading the file line by line or
by its size, never whole into memory:

- binary bodies must hold exactly the bytes the header declares;
- ASCII bodies must hold exactly the declared number of data lines, each with the
  declared number of values, each value a number in the range of its property type.

Every problem raises :class:`~mvreg.errors.ScanFileError` naming the file (and the line).
:func:`declared_points` reads only the header, for the point-count limit.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from mvreg.errors import ScanFileError

MAX_HEADER_BYTES = 1 << 20
MAX_LINE_BYTES = 1 << 20
_BLOCK_BYTES = 1 << 22
_WHITESPACE = np.zeros(256, dtype=bool)
_WHITESPACE[[9, 10, 11, 12, 13, 32]] = True

_PLY_TYPES = {
    "char": ("i", 1), "int8": ("i", 1), "uchar": ("u", 1), "uint8": ("u", 1),
    "short": ("i", 2), "int16": ("i", 2), "ushort": ("u", 2), "uint16": ("u", 2),
    "int": ("i", 4), "int32": ("i", 4), "uint": ("u", 4), "uint32": ("u", 4),
    "float": ("f", 4), "float32": ("f", 4), "double": ("f", 8), "float64": ("f", 8),
}  # fmt: skip
_PCD_KINDS = {"F": "f", "I": "i", "U": "u"}


@dataclass
class Element:
    """One PLY element (or the PCD point record): its count and property types."""

    name: str
    count: int
    types: list[tuple[str, int]]  # (kind 'f'/'i'/'u', bytes) per value
    has_list: bool = False
    names: list[str] = field(default_factory=list)  # PLY property names (lists included)

    @property
    def row_bytes(self) -> int | None:
        return None if self.has_list else sum(size for _, size in self.types)


def _read_header(f: BinaryIO, path: Path, is_last) -> list[str]:
    lines, total = [], 0
    while True:
        raw = f.readline(MAX_HEADER_BYTES)
        total += len(raw)
        if not raw or total > MAX_HEADER_BYTES:
            raise ScanFileError(path, "corrupt header (no end of header found)")
        line = raw.decode("latin-1").rstrip("\r\n")
        lines.append(line)
        if is_last(line):
            return lines


def _ply_header(f: BinaryIO, path: Path) -> tuple[str, list[Element], int]:
    """(format, elements, number of header lines) of a PLY file open at its start."""
    if f.read(3) != b"ply":
        raise ScanFileError(path, "not a PLY file (bad magic number)")
    f.seek(0)
    header = _read_header(f, path, lambda s: s.strip() == "end_header")
    fmt, elements = None, []
    for line in header:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
            if len(tok) >= 3 and tok[2] not in ("1.0", "1"):
                raise ScanFileError(path, f"unsupported PLY version {tok[2]!r} (only 1.0)")
        elif tok[0] == "element" and len(tok) >= 3:
            try:
                count = int(tok[2])
            except ValueError:
                raise ScanFileError(path, f"corrupt PLY header line {line!r}") from None
            if count < 0:
                raise ScanFileError(path, f"corrupt PLY header line {line!r}")
            elements.append(Element(tok[1], count, []))
        elif tok[0] == "property" and elements and len(tok) >= 3:
            _add_property(path, elements[-1], tok)
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ScanFileError(path, f"unknown PLY format {fmt!r}")
    if not any(e.name == "vertex" for e in elements):
        raise ScanFileError(path, "PLY file has no vertex element")
    missing = [c for c in "xyz" if c not in _vertex(elements).names]
    if missing:
        raise ScanFileError(path, f"the PLY vertex element has no {'/'.join(missing)} property")
    return fmt, elements, len(header)


def _add_property(path: Path, element: Element, tok: list[str]) -> None:
    name = tok[-1]
    if name in element.names:
        raise ScanFileError(path, f"PLY property {name!r} of {element.name} declared twice")
    element.names.append(name)
    if tok[1] == "list":
        element.has_list = True
        return
    if tok[1] not in _PLY_TYPES:
        raise ScanFileError(path, f"unknown PLY property type {tok[1]!r}")
    element.types.append(_PLY_TYPES[tok[1]])


def _vertex(elements: list[Element]) -> Element:
    return next(e for e in elements if e.name == "vertex")


def declared_points(path: Path) -> int:
    """Number of points a PLY or PCD header declares (reads the header only)."""
    with path.open("rb") as f:
        if path.suffix.lower() == ".ply":
            return _vertex(_ply_header(f, path)[1]).count
        return _pcd_header(f, path)[0].count


def _line_blocks(
    path: Path, f: BinaryIO, first_line: int
) -> Iterator[tuple[np.ndarray, np.ndarray, list]]:
    """(line numbers, values per line, values) of the non-blank lines, block by block."""
    carry, line0 = b"", first_line
    while True:
        data = f.read(_BLOCK_BYTES)
        buf = carry + data
        cut = len(buf) if not data else buf.rfind(b"\n") + 1
        if data and cut == 0:
            if len(buf) > MAX_LINE_BYTES:  # binary garbage: never buffer the whole file
                raise ScanFileError(path, f"line {line0} is longer than {MAX_LINE_BYTES} bytes")
            carry = buf
            continue
        block, carry = buf[:cut], buf[cut:]
        if block:
            b = np.frombuffer(block, np.uint8)
            ws = _WHITESPACE[b]
            start = ~ws
            start[1:] &= ws[:-1]
            newlines = np.flatnonzero(b == 10)
            num_lines = len(newlines) + (not block.endswith(b"\n"))
            line_of = np.searchsorted(newlines, np.flatnonzero(start))
            counts = np.bincount(line_of, minlength=num_lines)
            keep = counts > 0
            yield line0 + np.flatnonzero(keep), counts[keep], block.split()
            line0 += num_lines
        if not data:
            return


def _remaining_lines(blocks) -> int:
    return sum(len(lines) for lines, _, _ in blocks)


def _bad_value(path: Path, line: int, tok: bytes, why: str) -> ScanFileError:
    return ScanFileError(path, f"line {line}: value {tok.decode('latin-1')!r} {why}")


def _check_values(path: Path, toks: list[bytes], lines: list[int], types) -> None:
    """Each token parses as a number in the range of its column's type."""
    n = len(types)
    try:
        vals = np.array(toks, dtype=bytes).astype(np.float64)
    except ValueError:
        for k, t in enumerate(toks):
            try:
                float(t)
            except ValueError:
                raise _bad_value(path, lines[k // n], t, "is not a number") from None
        raise  # pragma: no cover - numpy and float() disagree
    vals = vals.reshape(-1, n)
    for c, (kind, size) in enumerate(types):
        col = vals[:, c]
        if kind == "f":
            limit = np.finfo(np.float32 if size == 4 else np.float64).max
            bad = np.abs(col) > limit  # inf too: Open3D cannot read it (nan it can)
        else:
            lo = -(2 ** (8 * size - 1)) if kind == "i" else 0
            hi = 2 ** (8 * size - (kind == "i")) - 1
            with np.errstate(invalid="ignore"):
                bad = ~((col >= lo) & (col <= hi) & (col == np.round(col)))
        if np.any(bad):
            r = int(np.flatnonzero(bad)[0])
            what = "floating" if kind == "f" else "integer"
            raise _bad_value(path, lines[r], toks[r * n + c], f"is out of range of its {what} type")


def _check_ascii(path: Path, f: BinaryIO, first_line: int, elements: list[Element], what: str):
    """Stream an ASCII body: exact line counts, value counts and number ranges."""
    blocks = _line_blocks(path, f, first_line)
    todo = [e for e in elements if e.count > 0]
    el_i, seen = 0, 0
    for lines, counts, toks in blocks:
        pos = tpos = 0
        while pos < len(lines):
            if el_i == len(todo):
                extra = len(lines) - pos + _remaining_lines(blocks)
                last = elements[-1]
                raise ScanFileError(
                    path,
                    f"the header declares {last.count} {last.name} rows, the file holds "
                    f"{last.count + extra} (all data must be declared)",
                )
            el = todo[el_i]
            r = min(len(lines) - pos, el.count - seen)
            cnt = counts[pos : pos + r]
            ntok = int(cnt.sum())
            if not el.has_list:
                bad = np.flatnonzero(cnt != len(el.types))
                if bad.size:
                    k = pos + int(bad[0])
                    at_end = k == len(lines) - 1 and _remaining_lines(blocks) == 0
                    _wrong_width(
                        path, what, el, seen + int(bad[0]), int(lines[k]), counts[k], at_end
                    )
                if el.name in ("vertex", "point"):
                    _check_values(path, toks[tpos : tpos + ntok], lines[pos : pos + r], el.types)
            pos, tpos, seen = pos + r, tpos + ntok, seen + r
            if seen == el.count:
                el_i, seen = el_i + 1, 0
    if el_i < len(todo):
        el = todo[el_i]
        raise ScanFileError(
            path,
            f"truncated {what}: the header declares {el.count} {el.name} rows, the file "
            f"holds {seen}",
        )


def _wrong_width(path, what: str, el: Element, seen: int, line: int, num: int, at_end: bool):
    if at_end:
        raise ScanFileError(
            path,
            f"truncated {what}: the header declares {el.count} {el.name} rows, the "
            f"file holds {seen} (the last line, {line}, is incomplete)",
        )
    raise ScanFileError(
        path, f"line {line}: {num} values, the header declares {len(el.types)} per row"
    )


def _check_binary(path: Path, body: int, elements: list[Element], what: str) -> None:
    if any(e.row_bytes is None for e in elements):
        return  # list properties (faces): sizes not known without reading them
    need = sum(e.count * e.row_bytes for e in elements)
    if body == need:
        return
    last = elements[-1]
    held = max(0, body - need + last.count * last.row_bytes) // max(last.row_bytes, 1)
    raise ScanFileError(
        path,
        ("truncated " + what + ": " if body < need else "")
        + f"the header declares {last.count} {last.name} rows ({need} data bytes), the "
        f"file holds {body} data bytes ({held} rows)",
    )


def check_ply(path: Path) -> None:
    """Check a PLY file against its header (streaming). Raises ScanFileError."""
    with path.open("rb") as f:
        fmt, elements, num_header = _ply_header(f, path)
        n = _vertex(elements).count
        if n == 0:
            raise ScanFileError(path, "PLY header declares no vertices")
        if fmt == "ascii":
            _check_ascii(path, f, num_header + 1, elements, "PLY")
        else:
            _check_binary(path, path.stat().st_size - f.tell(), elements, "PLY")


def read_ply_vertices(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(points, normals or None, colors in [0, 1] or None) of a checked PLY file, read with
    NumPy by property name: Open3D's reader (RPly) aborts the process on a header line of
    about 1 KB and misreads vertices not declared x, y, z. The vertex element and those
    before it must have no list properties (their size is then known)."""
    with path.open("rb") as f:
        fmt, elements, num_header = _ply_header(f, path)
        body = f.tell()
    k = next(i for i, e in enumerate(elements) if e.name == "vertex")
    before, v = elements[:k], elements[k]
    if v.has_list or any(e.has_list for e in before):
        raise ScanFileError(
            path, "list properties in or before the vertex element are not supported"
        )
    if fmt == "ascii":
        skip = num_header + sum(e.count for e in before)
        data = np.loadtxt(path, skiprows=skip, max_rows=v.count, ndmin=2, dtype=np.float64)
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(f"c{i}", f"{order}{kd}{sz}") for i, (kd, sz) in enumerate(v.types)])
        offset = body + sum(e.count * e.row_bytes for e in before)
        rows = np.fromfile(path, dtype=dtype, count=v.count, offset=offset)
        data = np.column_stack([rows[f"c{i}"].astype(np.float64) for i in range(len(v.types))])
    col = {name: data[:, i] for i, name in enumerate(v.names)}
    points = np.column_stack([col["x"], col["y"], col["z"]])
    normals = np.column_stack([col[c] for c in ("nx", "ny", "nz")]) if "nz" in col else None
    colors = None
    if all(c in col for c in ("red", "green", "blue")):
        colors = np.column_stack([col[c] for c in ("red", "green", "blue")])
        colors = colors / 255.0 if colors.max(initial=0.0) > 1.0 else colors
    return points, normals, colors


def _pcd_header(f: BinaryIO, path: Path) -> tuple[Element, str, dict, int]:
    header = _read_header(f, path, lambda s: s.split()[:1] == ["DATA"])
    fields: dict[str, list[str]] = {}
    for line in header:
        tok = line.split()
        if tok and not tok[0].startswith("#"):
            fields[tok[0].upper()] = tok[1:]
    try:
        num = int(fields.get("POINTS", fields.get("WIDTH", ["0"]))[0])
        sizes = [int(s) for s in fields.get("SIZE", [])]
        counts = [int(c) for c in fields.get("COUNT", ["1"] * len(sizes))]
    except (ValueError, IndexError):
        raise ScanFileError(path, "corrupt PCD header") from None
    kinds = fields.get("TYPE", ["F"] * len(sizes))
    if num < 0 or len(counts) != len(sizes) or len(kinds) != len(sizes):
        raise ScanFileError(path, "corrupt PCD header (SIZE, TYPE and COUNT differ in length)")
    types = [
        (_PCD_KINDS.get(k.upper(), "f"), s)
        for k, s, c in zip(kinds, sizes, counts, strict=True)
        for _ in range(c)
    ]
    data = fields.get("DATA", [""])[0].lower()
    return Element("point", num, types), data, fields, len(header)


def check_pcd(path: Path) -> np.ndarray | None:
    """Check a PCD file (streaming); its sensor origin if VIEWPOINT is not the default."""
    with path.open("rb") as f:
        el, data, fields, num_header = _pcd_header(f, path)
        if el.count == 0:
            raise ScanFileError(path, "PCD header declares no points")
        if data == "binary" and el.types:
            _check_binary(path, path.stat().st_size - f.tell(), [el], "PCD")
        elif data == "ascii":
            _check_ascii(path, f, num_header + 1, [el], "PCD")
    vp = fields.get("VIEWPOINT")
    if vp is not None and len(vp) == 7:
        try:
            v = np.array([float(x) for x in vp])
        except ValueError:
            return None
        if not np.allclose(v, [0, 0, 0, 1, 0, 0, 0]):
            return v[:3]
    return None


def check_text(path: Path, min_values: int, counted: bool = False) -> None:
    """Check an XYZ-like text file (streaming): every non-blank line holds the same
    number (at least ``min_values``) of numbers in the float64 range (``nan`` allowed:
    such rows are dropped later, counted). With ``counted`` (PTS) the first line is the
    number of points, which must match the rows that follow. Raises ScanFileError."""
    with path.open("rb") as f:
        declared, first = None, 1
        if counted:
            head = f.readline(MAX_LINE_BYTES).split()
            if len(head) != 1 or not head[0].isdigit():
                shown = b" ".join(head).decode("latin-1")[:40]
                raise ScanFileError(path, f"line 1: {shown!r} is not a number of points")
            declared, first = int(head[0]), 2
        width, rows = None, 0
        for lines, counts, toks in _line_blocks(path, f, first):
            width = int(counts[0]) if width is None and len(counts) else width
            odd = np.flatnonzero(counts != width)
            if odd.size or (width is not None and width < min_values):
                k = int(odd[0]) if odd.size else 0
                raise ScanFileError(
                    path,
                    f"line {lines[k]}: {counts[k]} values, expected "
                    + (f"{width} like line {first}" if odd.size else f"at least {min_values}"),
                )
            _check_values(path, toks, list(lines), [("f", 8)] * (width or 0))
            rows += len(lines)
    if declared is not None and declared != rows:
        raise ScanFileError(path, f"line 1 declares {declared} points, the file holds {rows}")


def read_pcd_doubles(path: Path) -> tuple[np.ndarray, np.ndarray | None] | None:
    """(points, normals or None) of a checked binary or binary_compressed PCD file whose
    coordinates are 8-byte floats, which Open3D reads as zeros; None for any other PCD
    file (Open3D reads it)."""
    with path.open("rb") as f:
        el, data, fields, _ = _pcd_header(f, path)
        body = f.tell()
    counts = [int(c) for c in fields.get("COUNT", ["1"] * len(fields.get("SIZE", [])))]
    names = [
        n if c == 1 else f"{n}_{k}"
        for n, c in zip(fields.get("FIELDS", []), counts, strict=False)
        for k in range(c)
    ]
    if len(names) != len(el.types) or "x" not in names:
        return None
    if el.types[names.index("x")] != ("f", 8) or data == "ascii":
        return None
    if data == "binary":
        dtype = np.dtype([(f"c{i}", f"<{kd}{sz}") for i, (kd, sz) in enumerate(el.types)])
        rows = np.fromfile(path, dtype=dtype, count=el.count, offset=body)
        col = {n: rows[f"c{i}"].astype(np.float64) for i, n in enumerate(names)}
    elif data == "binary_compressed":
        col = dict(zip(names, _compressed_columns(path, body, el), strict=True))
    else:
        raise ScanFileError(path, f"unknown PCD DATA {data!r}")
    points = np.column_stack([col["x"], col["y"], col["z"]])
    keys = ("normal_x", "normal_y", "normal_z")
    normals = np.column_stack([col[k] for k in keys]) if all(k in col for k in keys) else None
    return points, normals


def _compressed_columns(path: Path, body: int, el: Element) -> list[np.ndarray]:
    """The columns (float64) of a binary_compressed PCD body: two uint32 sizes, then LZF
    data that decompresses to each field's values for all points, field after field."""
    from mvreg.io.loaders.lzf import lzf_decompress

    with path.open("rb") as f:
        f.seek(body)
        sizes = np.frombuffer(f.read(8), "<u4")
        if len(sizes) != 2:
            raise ScanFileError(path, "truncated PCD: no compressed sizes after the header")
        packed = f.read(int(sizes[0]))
    need = el.count * sum(size for _, size in el.types)
    try:
        if len(packed) != sizes[0] or sizes[1] != need:
            raise ValueError(f"sizes {sizes.tolist()} do not fit {el.count} points")
        raw = lzf_decompress(packed, int(sizes[1]))
    except ValueError as e:
        raise ScanFileError(path, f"corrupt binary_compressed PCD ({e})") from None
    cols, at = [], 0
    for kind, size in el.types:
        cols.append(np.frombuffer(raw, f"<{kind}{size}", el.count, at).astype(np.float64))
        at += el.count * size
    return cols


def count_lines(path: Path) -> int:
    """Non-blank lines of a text file (streaming): an upper bound of its points."""
    with path.open("rb") as f:
        return sum(1 for line in f if line.strip())
