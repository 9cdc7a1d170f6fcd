"""Point-cloud files: .xyz/.asc/.txt tables, .pcd, .ply without faces, .npy and (through
`relicgpu.io.las`) .las/.laz, read into a checked `PointCloud`."""
from __future__ import annotations

import io as _stdio
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .fragment import FragmentError
from .las import LIDAR_SUFFIXES, read_las

POINT_SUFFIXES = {".xyz", ".asc", ".txt", ".pcd", ".npy"} | LIDAR_SUFFIXES

# A cloud of fewer points is no fragment.
MIN_POINTS = 20

@dataclass(frozen=True)
class PointCloud:
    """Scanned points with optional per-point normals (unit vectors)."""
    points: np.ndarray  # (N,3) float64
    normals: np.ndarray | None  # (N,3) float64 or None
    source: str
    notes: tuple[str, ...] = ()


# --- readers -------------------------------------------------------------

def read_point_cloud(path) -> PointCloud:
    """Read .xyz/.asc/.txt, .pcd, .ply (vertices only), .npy or .las/.laz (`io.read_las`) into a
    checked PointCloud."""
    p = Path(path)
    label = str(p)
    if not p.exists():
        raise FragmentError(f"{label}: no such file")
    if p.is_dir():
        raise FragmentError(f"{label}: is a directory, not a point-cloud file")
    suffix = p.suffix.lower()
    if suffix in (".xyz", ".asc", ".txt"):
        pts, nrm, notes = _read_text(p, label)
    elif suffix == ".pcd":
        pts, nrm, notes = _read_pcd(p, label)
    elif suffix == ".ply":
        pts, nrm, notes = _read_ply(p, label)
    elif suffix == ".npy":
        pts, nrm, notes = _read_npy(p, label)
    elif suffix in (".las", ".laz"):
        pts, nrm, notes = read_las(p, label)
    else:
        raise FragmentError(f"{label}: unknown point-cloud format {suffix or '(no extension)'!r}; "
                            "use .xyz, .asc, .txt, .pcd, .ply, .npy, .las or .laz")
    _check_points(pts, label)
    if nrm is not None and not np.isfinite(nrm).all():
        nrm = None
        notes.append(f"{label}: normals hold NaN or infinite values; ignored")
    if nrm is not None:
        nrm = _fill_zero_normals(pts, nrm, label, notes)
    return PointCloud(pts, nrm, label, tuple(notes))


def _fill_zero_normals(pts: np.ndarray, nrm: np.ndarray, label: str, notes: list) -> np.ndarray | None:
    """(N, 3) normals where points a scanner gave a zero normal take their nearest point's; None
    (with a note) where over half of them are zero: a cloud matched on its points uses them all."""
    zero = np.linalg.norm(nrm, axis=1) < 1e-12
    if not zero.any():
        return nrm
    if zero.mean() > 0.5:
        notes.append(f"{label}: {int(zero.sum())} of {len(zero)} normals are zero; normals ignored")
        return None
    from scipy.spatial import cKDTree

    nrm = nrm.copy()
    nrm[zero] = nrm[~zero][cKDTree(pts[~zero]).query(pts[zero])[1]]
    notes.append(f"{label}: {int(zero.sum())} points have a zero normal; each takes its nearest point's")
    return nrm


def _check_points(pts: np.ndarray, label: str, row_to_line=None) -> None:
    if len(pts) < MIN_POINTS:
        raise FragmentError(f"{label}: too few points ({len(pts)}); a fragment scan needs at least {MIN_POINTS}")
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        where = f"line {row_to_line(first)}" if row_to_line else f"point {first}"
        raise FragmentError(f"{label}: {int(bad.sum())} points have NaN or infinite coordinates (first at {where})")


def _split_normals(arr: np.ndarray, label: str, notes: list) -> tuple[np.ndarray, np.ndarray | None]:
    pts = np.ascontiguousarray(arr[:, :3], np.float64)
    if arr.shape[1] == 3:
        return pts, None
    nrm = np.asarray(arr[:, 3:6], np.float64)
    with np.errstate(invalid="ignore"):
        lengths = np.linalg.norm(nrm, axis=1)
    unit = np.abs(lengths - 1.0) < 0.05
    # a scanner's zero rows are missing normals (`_fill_zero_normals`), not colours
    if np.isfinite(lengths).all() and unit.any() and np.all(unit | (lengths < 1e-12)):
        return pts, np.ascontiguousarray(nrm)
    notes.append(f"{label}: columns 4 to 6 are not unit normals (colours?); ignored")
    return pts, None


_COMMENTS = ("#", "//")


def _data_lines(lines, first_line_no: int = 1):
    """(line number, fields) of each non-empty, non-comment line."""
    for no, raw in enumerate(lines, first_line_no):
        line = raw.strip()
        if not line or line.startswith(_COMMENTS):
            continue
        for c in _COMMENTS:
            line = line.split(c, 1)[0]
        yield no, line.replace(",", " ").split()


def _diagnose_table(lines, label: str, first_line_no: int, allowed: tuple[int, ...], what: str) -> FragmentError:
    """The first fault of a numeric table, named with its line number."""
    expected = None
    for no, fields in _data_lines(lines, first_line_no):
        if expected is None:
            if len(fields) not in allowed:
                return FragmentError(f"{label}: line {no} has {len(fields)} columns; expected {what}")
            expected = len(fields)
        elif len(fields) != expected:
            return FragmentError(f"{label}: line {no} has {len(fields)} columns, earlier lines have {expected}")
        for i, tok in enumerate(fields, 1):
            try:
                float(tok)
            except ValueError:
                return FragmentError(f"{label}: line {no}, column {i}: {tok[:40]!r} is not a number")
    return FragmentError(f"{label}: unreadable numeric table")


def _row_to_line(lines, first_line_no: int):
    def find(row: int) -> int:
        for k, (no, _) in enumerate(_data_lines(lines, first_line_no)):
            if k == row:
                return no
        return -1
    return find


def _parse_table(text: str, label: str, first_line_no: int, allowed: tuple[int, ...], what: str) -> np.ndarray:
    """Parse whitespace- or comma-separated numbers; fast path numpy, slow path for the error message."""
    first = next(_data_lines(text.splitlines()[:10000], first_line_no), None)
    if first is None:
        raise FragmentError(f"{label}: no points (the file has no data lines)")
    # numpy counts only data rows; on any fault re-scan the lines to name the real line.
    delimiter = "," if "," in text[: 1 << 16] else None
    try:
        arr = np.loadtxt(_stdio.StringIO(text), comments=_COMMENTS, delimiter=delimiter, ndmin=2, dtype=np.float64)
    except ValueError:
        raise _diagnose_table(text.splitlines(), label, first_line_no, allowed, what) from None
    if arr.shape[1] not in allowed:
        raise _diagnose_table(text.splitlines(), label, first_line_no, allowed, what)
    return arr


def _read_text(p: Path, label: str):
    text = p.read_bytes().decode("latin-1")
    arr = _parse_table(text, label, 1, (3, 6), "3 (x y z) or 6 (x y z nx ny nz)")
    notes: list[str] = []
    pts, nrm = _split_normals(arr, label, notes)
    if not np.isfinite(pts).all():
        _check_points(pts, label, _row_to_line(text.splitlines(), 1))
    return pts, nrm, notes


# PCD: https://pointclouds.org/documentation/tutorials/pcd_file_format.html
def _binary_records(raw: bytes, dtypes, n_points: int, offset: int, fault: str, items: str) -> np.ndarray:
    """n_points records of the structured dtype from raw[offset:]; `fault` raised (FragmentError)
    when the file holds fewer bytes than that."""
    dt = np.dtype(dtypes)
    need = n_points * dt.itemsize
    have = len(raw) - offset
    if have < need:
        raise FragmentError(f"{fault}: header declares {n_points} {items} of "
                            f"{dt.itemsize} bytes ({need} bytes), the file holds {have} bytes of data")
    return np.frombuffer(raw, dt, count=n_points, offset=offset)


_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
              ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def _read_pcd(p: Path, label: str):
    raw = p.read_bytes()
    header: dict[str, list[str]] = {}
    pos = 0
    line_no = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise FragmentError(f"{label}: PCD header has no DATA line")
        line_no += 1
        line = raw[pos:end].decode("latin-1").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            break
        if line_no > 100:
            raise FragmentError(f"{label}: not a PCD file (no DATA line in the first 100 lines)")
    for key in ("FIELDS", "SIZE", "TYPE"):
        if key not in header:
            raise FragmentError(f"{label}: PCD header lacks the {key} line")
    fields, sizes, types = header["FIELDS"], header["SIZE"], header["TYPE"]
    counts = header.get("COUNT", ["1"] * len(fields))
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise FragmentError(f"{label}: PCD header lists {len(fields)} FIELDS but {len(sizes)} SIZE, "
                            f"{len(types)} TYPE and {len(counts)} COUNT entries")
    for axis in "xyz":
        if axis not in fields:
            raise FragmentError(f"{label}: PCD has no {axis!r} field (fields: {' '.join(fields)})")
    try:
        sizes_i = [int(s) for s in sizes]
        counts_i = [int(c) for c in counts]
        width = int(header.get("WIDTH", ["0"])[0])
        height = int(header.get("HEIGHT", ["1"])[0])
        n_points = int(header.get("POINTS", [str(width * height)])[0])
    except ValueError as exc:
        raise FragmentError(f"{label}: PCD header has a non-integer SIZE/COUNT/WIDTH/HEIGHT/POINTS ({exc})") from None
    dtypes = []
    for name, t, s, c in zip(fields, types, sizes_i, counts_i):
        code = _PCD_TYPES.get((t.upper(), s))
        if code is None:
            raise FragmentError(f"{label}: PCD field {name!r} has unsupported TYPE {t} with SIZE {s}")
        dtypes.append((name, "<" + code, (c,)) if c != 1 else (name, "<" + code))
    mode = (header["DATA"] or [""])[0].lower()
    organised = height > 1
    notes: list[str] = []
    if mode == "ascii":
        text = raw[pos:].decode("latin-1")
        ncols = sum(counts_i)
        arr = _parse_table(text, label, line_no + 1, (ncols,), f"{ncols} (the PCD FIELDS with their COUNT)")
        if len(arr) != n_points:
            notes.append(f"{label}: header declares {n_points} points, data holds {len(arr)}")
        offsets = np.cumsum([0] + counts_i)
        col = {name: offsets[i] for i, name in enumerate(fields)}
        table = arr
        row_to_line = _row_to_line(text.splitlines(), line_no + 1)
    elif mode == "binary":
        rec = _binary_records(raw, dtypes, n_points, pos, f"{label}: truncated binary PCD", "points")
        table = np.column_stack([rec[a].astype(np.float64) for a in ("x", "y", "z")]
                                + ([rec[a].astype(np.float64) for a in ("normal_x", "normal_y", "normal_z")]
                                   if all(a in fields for a in ("normal_x", "normal_y", "normal_z")) else []))
        col = {name: i for i, name in enumerate(["x", "y", "z", "normal_x", "normal_y", "normal_z"])}
        row_to_line = None
    elif mode == "binary_compressed":
        raise FragmentError(f"{label}: PCD 'DATA binary_compressed' is unsupported; "
                            "save the cloud as binary or ascii PCD (e.g. pcl_convert_pcd_ascii_binary)")
    else:
        raise FragmentError(f"{label}: unknown PCD DATA mode {mode!r}; expected ascii or binary")
    pts = np.column_stack([table[:, col[a]] for a in "xyz"]).astype(np.float64)
    nrm = None
    if all(a in col and a in fields for a in ("normal_x", "normal_y", "normal_z")):
        nrm = np.column_stack([table[:, col[a]] for a in ("normal_x", "normal_y", "normal_z")]).astype(np.float64)
    bad = ~np.isfinite(pts).all(axis=1)
    if organised and bad.any():
        # An organised cloud marks pixels without a return with NaN (PCL's is_dense=false).
        notes.append(f"{label}: dropped {int(bad.sum())} NaN points of the organised {width}x{height} cloud")
        pts = pts[~bad]
        nrm = nrm[~bad] if nrm is not None else None
    elif bad.any():
        _check_points(pts, label, row_to_line)
    return pts, nrm, notes


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _read_ply(p: Path, label: str):
    raw = p.read_bytes()
    if not raw.startswith(b"ply"):
        raise FragmentError(f"{label}: not a PLY file (no 'ply' magic line)")
    end = raw.find(b"end_header")
    if end < 0:
        raise FragmentError(f"{label}: PLY header has no end_header line")
    body = raw.find(b"\n", end) + 1
    header_lines = raw[:body].decode("latin-1").splitlines()
    fmt = None
    elements: list[tuple[str, int, list]] = []
    for line in header_lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1] if len(parts) > 1 else ""
        elif parts[0] == "element" and len(parts) == 3:
            try:
                elements.append((parts[1], int(parts[2]), []))
            except ValueError:
                raise FragmentError(f"{label}: PLY element {parts[1]!r} has a non-integer count {parts[2]!r}") from None
        elif parts[0] == "property" and elements:
            elements[-1][2].append(parts[1:])
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise FragmentError(f"{label}: unknown PLY format {fmt!r}")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise FragmentError(f"{label}: PLY has no vertex element")
    vi = names.index("vertex")
    if any(count > 0 for _, count, _ in elements[:vi]):
        raise FragmentError(f"{label}: unsupported PLY layout (elements with data before 'vertex')")
    _, n_points, props = elements[vi]
    prop_names = []
    dtypes = []
    endian = "<" if fmt == "binary_little_endian" else ">"
    for prop in props:
        if prop[0] == "list":
            raise FragmentError(f"{label}: unsupported PLY vertex property list {prop[-1]!r}")
        if len(prop) != 2 or prop[0] not in _PLY_TYPES:
            raise FragmentError(f"{label}: PLY vertex property {' '.join(prop)!r} has an unknown type")
        prop_names.append(prop[1])
        dtypes.append((prop[1], endian + _PLY_TYPES[prop[0]]))
    for axis in "xyz":
        if axis not in prop_names:
            raise FragmentError(f"{label}: PLY vertices have no {axis!r} property")
    has_normals = all(a in prop_names for a in ("nx", "ny", "nz"))
    if fmt == "ascii":
        text = raw[body:].decode("latin-1")
        lines = text.splitlines()[:n_points]
        if len(lines) < n_points:
            raise FragmentError(f"{label}: truncated PLY: header declares {n_points} vertices, the file has {len(lines)} lines after the header")
        ncols = len(prop_names)
        arr = _parse_table("\n".join(lines), label, len(header_lines) + 1, (ncols,), f"{ncols} (the PLY vertex properties)")
        if len(arr) < n_points:
            raise FragmentError(f"{label}: truncated PLY: header declares {n_points} vertices, found {len(arr)}")
        table = {name: arr[:, i] for i, name in enumerate(prop_names)}
        row_to_line = _row_to_line(lines, len(header_lines) + 1)
    else:
        rec = _binary_records(raw, dtypes, n_points, body, f"{label}: truncated binary PLY", "vertices")
        table = {name: rec[name] for name in prop_names}
        row_to_line = None
    pts = np.column_stack([table[a] for a in "xyz"]).astype(np.float64)
    nrm = np.column_stack([table[a] for a in ("nx", "ny", "nz")]).astype(np.float64) if has_normals else None
    notes: list[str] = []
    if any(name == "face" and count > 0 for name, count, _ in elements):
        notes.append(f"{label}: the PLY's faces were ignored; its vertices were triangulated afresh")
    if not np.isfinite(pts).all():
        _check_points(pts, label, row_to_line)
    return pts, nrm, notes


def _read_npy(p: Path, label: str):
    try:
        arr = np.load(p, allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:
        raise FragmentError(f"{label}: unreadable or truncated .npy file ({exc})") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiu":
        raise FragmentError(f"{label}: .npy must hold a numeric array, got dtype {getattr(arr, 'dtype', type(arr))}")
    if arr.ndim != 2 or arr.shape[1] not in (3, 6):
        raise FragmentError(f"{label}: .npy array has shape {arr.shape}; expected (N, 3) points or (N, 6) points with normals")
    notes: list[str] = []
    pts, nrm = _split_normals(arr, label, notes)
    return pts, nrm, notes
