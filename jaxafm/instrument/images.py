"""AFM images, simulated or measured: one type, readers for instrument files, a file format.

``AFMImage``: heights ``z`` (rows, columns) nm, row 0 at the lowest y and
column 0 at the lowest x (files that do not say keep their stored order, noted in ``meta``), the pixel
size (x, y) nm, the position of pixel [0, 0]'s centre, and a ``meta`` dict
(source, direction, line rate, start time, unit conversions done).

Readers convert to nm and say so in ``meta``: the Nanosurf text export and binary
``.nid`` file, TIFF height maps (whose size the caller gives), and through AFMReader (the
``formats`` extra) Bruker .spm, Igor .ibw, JPK .jpk and TopoStats files, and
Gwyddion .gwy through gwyfile. What a file lacks (its size, height unit, row
order, fast axis, line rate, direction) the caller gives, as a config's
``ImageFile`` does.

Saved images (``save_image``/``load_image``) are ``.npz`` files holding ``z``
(float64, nm) and ``meta_json``, a JSON document ``{"format":
"jaxafm-image", "version": 1, "pixel_size_nm": [dx, dy], "origin_nm": [x0, y0],
"meta": {...}}``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import numpy as np

from ..config.names import LENGTH_TO_NM

if TYPE_CHECKING:
    from .afm import RasterScan

FORMAT, VERSION = "jaxafm-image", 1
#: A scan setting a config's pair gives (``angle_deg``, ...) -> the .nid header entry recording it
#: (section ``[DataSet\\DataSetInfos\\Scan]``)
NID_SCAN_ENTRIES = {
    "line_rate_hz": "Time/Line",
    "angle_deg": "Rotation",
    "overscan": "Overscan",
    "lines": "Scan direction",
}
#: A scan setting a config's pair gives -> the ``meta`` key a jaxafm image records it under
#: (:func:`from_scan`)
SAVED_SCAN_ENTRIES = {
    "line_rate_hz": "line_rate_hz",
    "angle_deg": "angle_deg",
    "overscan": "overscan",
    "lines": "scan_direction",
}
_NID_UNITS = {
    "Time/Line": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "\u00b5s": 1e-6},
    "Rotation": {"\u00b0": 1.0, "deg": 1.0, "Deg": 1.0},
    "Overscan": {"%": 1e-2},
}
#: Suffix -> AFMReader module and loader, with the channel it reads by default.
AFMREADER_FORMATS = {
    ".spm": ("spm", "load_spm", "Height"),
    ".ibw": ("ibw", "load_ibw", "HeightTracee"),
    ".jpk": ("jpk", "load_jpk", "height_trace"),
    ".topostats": ("topostats", None, "image"),
}
FORMATS = (".txt", ".nid", ".tif", ".tiff", ".gwy", ".npz") + tuple(AFMREADER_FORMATS)
#: A Nanosurf .nid file's frames by scan direction.
NID_FRAMES = {"trace": "Scan forward", "retrace": "Scan backward"}
#: A Nanosurf .nid file's height channels, the first the file holds read when none is named:
#: ``Z-Axis`` is the height in files of older Nanosurf software (easyScan 2), which has no
#: ``Topography``
NID_HEIGHTS = ("Topography", "Z-Axis")
#: How far (relative, per axis) a given scan size may lie from a file's own before it is refused.
SIZE_TOLERANCE = 0.01


@dataclasses.dataclass
class AFMImage:
    """Heights ``z`` (rows, cols) nm; ``pixel_size`` (dx, dy) nm; ``origin`` (x, y) nm of pixel [0, 0]."""

    z: np.ndarray
    pixel_size: tuple
    origin: tuple = (0.0, 0.0)
    meta: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        where = self.meta.get("source", "image")
        self.z = np.asarray(self.z, dtype=float)
        _check_shape(self.z, where)
        bad = ~np.isfinite(self.z)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise ValueError(
                f"{where}: {int(bad.sum())} of {self.z.size} pixels are NaN or inf (first at row "
                f"{r}, column {c}); fill or crop them before using the image"
            )
        self.pixel_size = tuple(float(p) for p in np.broadcast_to(self.pixel_size, (2,)))
        if not all(np.isfinite(self.pixel_size)) or min(self.pixel_size) <= 0:
            raise ValueError(f"{where}: pixel size must be > 0 nm on both axes, got {self.pixel_size}")
        self.origin = tuple(float(o) for o in self.origin)

    @property
    def shape(self) -> tuple:
        return self.z.shape

    @property
    def size(self) -> tuple:
        """Width and height, nm."""
        return (self.z.shape[1] * self.pixel_size[0], self.z.shape[0] * self.pixel_size[1])

    @property
    def x(self) -> np.ndarray:
        return self.origin[0] + self.pixel_size[0] * np.arange(self.z.shape[1])

    @property
    def y(self) -> np.ndarray:
        return self.origin[1] + self.pixel_size[1] * np.arange(self.z.shape[0])

    @property
    def extent(self) -> tuple:
        """(left, right, bottom, top) nm of the pixels' edges, for ``imshow(origin="lower")``."""
        (dx, dy), (x0, y0) = self.pixel_size, self.origin
        return (
            x0 - dx / 2,
            x0 + dx * (self.z.shape[1] - 0.5),
            y0 - dy / 2,
            y0 + dy * (self.z.shape[0] - 0.5),
        )

    def height_map(self):
        """The image as a sample (``samples.HeightMap``) to scan with the simulated AFM."""
        import jax.numpy as jnp

        from .samples import HeightMap

        return HeightMap(jnp.asarray(self.z), jnp.asarray(self.pixel_size), jnp.asarray(self.origin))


def _check_shape(z: np.ndarray, where) -> None:
    if z.ndim != 2 or min(z.shape) < 2:
        raise ValueError(f"{where}: an AFM image needs at least 2 x 2 pixels, got shape {z.shape}")


def from_scan(scan: RasterScan, raster, direction: str = "trace", meta: Optional[dict] = None) -> AFMImage:
    """The ``trace`` or ``retrace`` image of a ``raster_scan`` result, with the scan's metadata."""
    if direction not in ("trace", "retrace"):
        raise ValueError(f"direction must be 'trace' or 'retrace', got {direction!r}")
    info = {
        "source": "simulated",
        "direction": direction,
        "line_rate_hz": raster.line_rate,
        "scan_direction": raster.direction,
        "overscan": raster.overscan,
        "angle_deg": raster.angle_deg,
        "start_time_s": float(np.min(getattr(scan, f"t_{direction}"))),
        **(meta or {}),
    }
    return AFMImage(np.asarray(getattr(scan, direction)), raster.pixel_size, raster.origin, info)


@dataclasses.dataclass
class _Stored:
    """An image file as its reader found it: values ``z`` (rows, cols) in ``z_unit``, the size
    (width, height) nm of the stored columns and rows, the side ``first_row`` of the stored
    row 0 ("top" or "bottom"; ``first_row_said``: the header entry that records it, where the
    instrument wrote it rather than the format fixing it), the origin (x, y) nm, and the
    reader's ``meta``; None where the file does not say."""

    z: np.ndarray
    z_unit: Optional[str]
    size_nm: Optional[tuple]
    meta: dict
    first_row: Optional[str] = None
    origin: tuple = (0.0, 0.0)
    first_row_said: Optional[str] = None


def read_image(
    path,
    channel: Optional[str] = None,
    size_nm=None,
    z_unit: Optional[str] = None,
    line_rate_hz: Optional[float] = None,
    fast_axis: Optional[str] = None,
    first_row: Optional[str] = None,
    direction: Optional[str] = None,
) -> AFMImage:
    """Read an AFM image file into nm and jaxafm's orientation, choosing the reader by the suffix.

    The arguments after ``channel`` say what the file lacks, and win over what it says (noted in
    ``meta["given"]``, with the file's replaced values in ``meta["file"]``), except that a
    file's own size must agree within :data:`SIZE_TOLERANCE`, its own height unit exactly, and
    ``first_row`` with the scan direction its instrument recorded (a .nid file's ``Up``).

    Arguments:
        path: the file.
        channel: the channel of multi-channel files (Gwyddion, AFMReader formats; a Nanosurf
            .nid file: the channel's name, default the first of :data:`NID_HEIGHTS` it holds,
            in the frame ``direction``
            picks, default the forward one).
        size_nm: (width, height) nm of the image as returned: along its rows (x) and across them
            (y); one number: a square scan (square pixels needed). Required for a TIFF, which
            carries no length calibration.
        z_unit: the unit of the stored heights (``LENGTH_TO_NM``); default nm for a TIFF.
        line_rate_hz: lines (trace + retrace) per second, Hz; into ``meta``.
        fast_axis: the image axis the scan lines run along: "x" (rows; the default) or "y"
            (the stored columns, traced upward: the image is turned a quarter turn clockwise,
            ``x' = y, y' = -x``, so that they are rows traced along +x in a right-handed frame;
            the stored image's last column becomes row 0, and a scan of its columns from left to
            right is ``lines: down``).
        first_row: where the stored row 0 lies: "bottom" (the lowest y: jaxafm's order, the
            default for files that do not say) or "top" (flipped).
        direction: "trace" or "retrace"; into ``meta``.

    Returns:
        The image: scan lines as rows along x, row 0 at the lowest y, heights in nm.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file and the value: not an image, a unit that is not a length, no
            size for a TIFF, a size or row order that disagrees with the file's, or a size that
            gives a square scan non-square pixels.
    """
    path = Path(path)
    names = ("size_nm", "z_unit", "line_rate_hz", "fast_axis", "first_row", "direction")
    values = (size_nm, z_unit, line_rate_hz, fast_axis, first_row, direction)
    given = {k: v for k, v in zip(names, values) if v is not None}
    _check_given(path, given)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    return _as_given(_read(path, channel, direction), path, given)


def _check_given(path: Path, given: dict) -> None:
    """Refuse a ``read_image`` argument outside its values, naming it."""
    choices = {
        "z_unit": tuple(LENGTH_TO_NM),
        "fast_axis": ("x", "y"),
        "first_row": ("bottom", "top"),
        "direction": ("trace", "retrace"),
    }
    for name, allowed in choices.items():
        if name in given and given[name] not in allowed:
            raise ValueError(f"{path}: {name}={given[name]!r} is not one of {', '.join(allowed)}")
    if "line_rate_hz" in given and not 0 < given["line_rate_hz"] < np.inf:
        raise ValueError(f"{path}: line_rate_hz={given['line_rate_hz']!r} must be a number > 0 Hz")
    if "size_nm" in given:
        size = np.ravel(np.asarray(given["size_nm"], dtype=float))
        if size.size not in (1, 2) or not np.all((size > 0) & (size < np.inf)):
            raise ValueError(
                f"{path}: size_nm={given['size_nm']!r} must be one number or [width, height], nm > 0"
            )


def _read(path: Path, channel: Optional[str], direction: Optional[str] = None) -> _Stored:
    """The file as stored, by the reader its suffix picks."""
    suffix = path.suffix.lower()
    if suffix == ".txt":
        return _read_nanosurf_text(path)
    if suffix == ".nid":
        return _read_nid(path, channel, direction)
    if suffix in (".tif", ".tiff"):
        return _read_tiff(path)
    if suffix == ".npz":
        image = load_image(path)
        scan = image.meta.get("scan") or _saved_scan(image.meta)
        return _Stored(
            image.z, "nm", image.size, image.meta | ({"scan": scan} if scan else {}), "bottom", image.origin
        )
    if suffix == ".gwy":
        return _read_gwy(path, channel)
    if suffix in AFMREADER_FORMATS:
        return _read_afmreader(path, channel)
    raise ValueError(f"{path}: unknown AFM image format {suffix!r}; known: {', '.join(FORMATS)}")


def _as_given(stored: _Stored, path: Path, given: dict) -> AFMImage:
    """The stored image in nm and jaxafm's orientation, with the ``given`` metadata over the
    file's; ``meta["file"]``: the file's values it replaced."""
    _check_shape(stored.z, path)
    meta = stored.meta | ({"given": given} if given else {})
    said = {k: meta.get(k) for k in ("line_rate_hz", "direction")} | {"first_row": stored.first_row}
    meta |= {k: given[k] for k in ("line_rate_hz", "direction") if k in given}
    z = stored.z * LENGTH_TO_NM[_z_unit(stored, path, given.get("z_unit"), meta)]
    size, origin = stored.size_nm, stored.origin
    _check_first_row(stored, path, given)
    if given.get("first_row", stored.first_row) == "top":
        z = z[::-1]
        meta["row_order"] = "flipped: row 0 is the bottom line"
    turned = given.get("fast_axis") == "y"
    if turned:  # x' = y, y' = -x: a rotation, so the frame stays right-handed (a transpose mirrors it)
        z = np.rot90(z)
        size = None if size is None else size[::-1]
        meta["fast_axis"] = (
            "y: turned a quarter turn clockwise, the stored columns (traced upward) are the rows"
        )
    pixel = _pixel_size(path, z.shape, given.get("size_nm"), size)
    if turned:  # where the stored image's last column, now row 0, lies
        origin = (origin[1], -(origin[0] + (z.shape[0] - 1) * pixel[1]))
    if size is not None:
        said["size_nm"] = [float(v) for v in size]
    wanted = given | ({"size_nm": list(_size(given["size_nm"]))} if "size_nm" in given else {})
    file = {k: v for k, v in said.items() if k in given and v is not None and v != wanted[k]}
    return AFMImage(z, pixel, origin, meta | ({"file": file} if file else {}))


def _check_first_row(stored: _Stored, path: Path, given: dict) -> None:
    """Refuse a given ``first_row`` that contradicts the row order the instrument recorded in the
    file's header (a scan direction), as a contradicting height unit or size is refused."""
    if "first_row" not in given or stored.first_row_said is None:
        return
    if given["first_row"] != stored.first_row:
        raise ValueError(
            f"{path}: first_row = {given['first_row']!r} disagrees with the file's own header "
            f"({stored.first_row_said}: row 0 is the {stored.first_row} line, scanned first): remove "
            "first_row or correct it"
        )


def _z_unit(stored: _Stored, path: Path, given: Optional[str], meta: dict) -> str:
    """The unit of the stored heights: the file's (``given`` must name the same), else ``given``
    (default nm), noted in ``meta``."""
    if stored.z_unit is None:
        unit = given or "nm"
        meta["converted"] = f"z from {unit} to nm" + ("" if given else " (assumed: the file does not say)")
        return unit
    if given is not None and LENGTH_TO_NM[given] != LENGTH_TO_NM[stored.z_unit]:
        raise ValueError(
            f"{path}: z_unit = {given!r} disagrees with the file's own height unit {stored.z_unit!r}: "
            "remove z_unit or correct it"
        )
    return stored.z_unit


def _size(size_nm) -> np.ndarray:
    """A given size as (width, height) nm."""
    return np.broadcast_to(np.asarray(size_nm, dtype=float).ravel(), (2,))


def _pixel_size(path: Path, shape: tuple, given, own: Optional[tuple]) -> tuple:
    """(dx, dy) nm of an image of ``shape`` (rows, cols): from the ``given`` size, checked
    against the file's ``own`` (width, height) nm, else from the file's."""
    rows, cols = shape
    if given is None:
        if own is None:
            raise ValueError(
                f"{path}: the file does not carry its length calibration (a TIFF never does): give "
                "size_nm, [width, height] nm or one number for a square scan, and z_unit if its "
                "heights are not in nm"
            )
        return (own[0] / cols, own[1] / rows)
    if np.size(given) == 1 and rows != cols:
        s = float(np.ravel(given)[0])
        raise ValueError(
            f"{path}: size_nm = {s:g} nm gives this {cols} x {rows} px image non-square pixels "
            f"({s / cols:g} x {s / rows:g} nm): give size_nm: [{s:g}, {s * rows / cols:g}] if {s:g} nm "
            f"is its width, [{s * cols / rows:g}, {s:g}] if it is its height"
        )
    w, h = _size(given)
    if own is not None and np.any(np.abs(np.array([w, h]) / own - 1) > SIZE_TOLERANCE):
        raise ValueError(
            f"{path}: size_nm = [{w:g}, {h:g}] nm disagrees with the file's own size "
            f"[{own[0]:g}, {own[1]:g}] nm by more than {SIZE_TOLERANCE:.0%}: correct size_nm, or "
            "remove it to use the file's"
        )
    return (w / cols, h / rows)


def _length_nm(path: Path, key: str, text: str) -> float:
    m = re.fullmatch(r"\s*([-+0-9.eE]+)\s*(\S+)\s*", text)
    if not m or m.group(2) not in LENGTH_TO_NM:
        raise ValueError(
            f"{path}: header {key!r} = {text!r} is not a length with a unit of {', '.join(LENGTH_TO_NM)}"
        )
    return float(m.group(1)) * LENGTH_TO_NM[m.group(2)]


def _read_nanosurf_text(path: Path) -> _Stored:
    """Nanosurf text export: ``Key : value`` header lines, then the heights row by row."""
    header, values = {}, []
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            if ":" in line and not values and not line.lstrip()[:1].isdigit():
                key, _, value = line.partition(":")
                header[key.strip()] = value.strip()
            elif line.strip():
                values.append(line)
    needed = ("Image Width", "Image Height", "Real Width", "Real Height", "Z Unit")
    missing = [k for k in needed if k not in header]
    if missing:
        raise ValueError(
            f"{path} is not a Nanosurf text export: header line(s) {missing} missing "
            f"(found {sorted(header) or 'no header'})"
        )
    try:
        cols, rows = int(header["Image Width"]), int(header["Image Height"])
    except ValueError:
        raise ValueError(
            f"{path}: 'Image Width' = {header['Image Width']!r} and 'Image Height' = "
            f"{header['Image Height']!r} must be whole numbers of pixels"
        ) from None
    try:
        z = np.array(" ".join(values).split(), dtype=float)
    except ValueError as e:
        raise ValueError(f"{path}: the height values are not all numbers ({e})") from None
    if z.size != rows * cols:
        raise ValueError(f"{path}: the header says {cols} x {rows} pixels but {z.size} values follow")
    z_unit = header["Z Unit"]
    if z_unit not in LENGTH_TO_NM:
        raise ValueError(f"{path}: 'Z Unit' = {z_unit!r} is not a length unit ({', '.join(LENGTH_TO_NM)})")
    width = _length_nm(path, "Real Width", header["Real Width"])
    height = _length_nm(path, "Real Height", header["Real Height"])
    name = header.get("Name", "")
    direction = "retrace" if "Bwd" in name else "trace" if "Fwd" in name else "unknown"
    meta = {
        "source": str(path),
        "reader": "nanosurf-text",
        "channel": name,
        "direction": direction,
        "converted": f"x, y from {header['Real Width'].split()[-1]} and z from {z_unit} to nm",
        "row_order": "as stored (row 0 first in the file)",
    }
    return _Stored(z.reshape(rows, cols), z_unit, (width, height), meta)


def _read_tiff(path: Path) -> _Stored:
    """A TIFF height map: one numeric channel, with no length calibration or height unit."""
    import tifffile

    try:
        z = tifffile.imread(path)
    except Exception as e:  # tifffile raises several types for a file that is not a TIFF
        raise ValueError(f"{path} is not a readable TIFF image ({e})") from None
    z = np.squeeze(z)
    if z.ndim != 2 or not np.issubdtype(z.dtype, np.number):
        raise ValueError(
            f"{path}: a TIFF height map must be one numeric 2-D channel, got shape {z.shape}, dtype {z.dtype}"
        )
    meta = {"source": str(path), "reader": "tiff", "row_order": "as stored"}
    return _Stored(z.astype(float), None, None, meta)


def _optional(module: str, path: Path):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ImportError(
            f"{path}: reading {path.suffix} files needs {module.split('.')[0]}: pip install 'jaxafm[formats]'"
        ) from None


def _nid_header(path: Path, text: str) -> dict:
    """A .nid header's ``[section]`` s of ``key=value`` lines, as dicts."""
    sections, current = {}, None
    for line in text.splitlines():
        if line.startswith("[") and line.rstrip().endswith("]"):
            current = sections.setdefault(line.strip()[1:-1], {})
        elif current is not None and "=" in line:
            key, _, value = line.partition("=")
            current[key] = value.strip()
    if "DataSet" not in sections:
        raise ValueError(f"{path} is not a Nanosurf .nid file (no [DataSet] section in its header)")
    return sections


def _read_nid(path: Path, channel: Optional[str], direction: Optional[str]) -> _Stored:
    """A Nanosurf .nid file: a text header, ``#!``, then each channel's lines of little-endian
    signed integers, in the order the header's ``[DataSet]`` lists them (``Gr<g>-Ch<c>`` naming a
    section with ``Frame``, ``Points``, ``Lines``, ``SaveBits``, the size ``Dim0Range`` x
    ``Dim1Range`` and the heights ``Dim2Min``, ``Dim2Range``, ``Dim2Unit``). The data are the
    file's last bytes, and a value is ``Dim2Min + (raw + 2^(bits - 1)) / 2^bits * Dim2Range``, as
    the vendor's reader (NSFopen) has it. The frame ``Scan forward`` is the trace, ``Scan
    backward`` the retrace, stored in the same column order; ``Scan direction`` ``Up`` puts the
    first line, row 0, at the bottom."""
    raw = path.read_bytes()
    cut = raw.find(b"\n#!")
    if cut < 0:
        raise ValueError(f"{path} is not a Nanosurf .nid file (no '#!' line between header and data)")
    head = _nid_header(path, raw[:cut].decode("utf-8", errors="replace"))
    blocks = _nid_channels(path, head)
    frame = NID_FRAMES[direction or "trace"]
    names = [f"{h.get('Dim2Name')} ({h.get('Frame')})" for h, *_ in blocks]
    held = {h.get("Dim2Name") for h, *_ in blocks}
    channel = channel or next((c for c in NID_HEIGHTS if c in held), NID_HEIGHTS[0])
    pick = [i for i, (h, *_) in enumerate(blocks) if h.get("Dim2Name") == channel and h.get("Frame") == frame]
    if not pick:
        raise ValueError(
            f"{path}: no channel {channel!r} in the frame {frame!r} (direction {direction or 'trace'}); "
            f"channels: {', '.join(names)}"
        )
    sizes = [lines * points * bits // 8 for _, lines, points, bits in blocks]
    start = len(raw) - sum(sizes) + sum(sizes[: pick[0]])
    h, lines, points, bits = blocks[pick[0]]
    if bits not in (16, 32):
        raise ValueError(f"{path}: SaveBits={bits} in channel {names[pick[0]]!r}; jaxafm reads 16 or 32")
    if start <= cut:
        raise ValueError(f"{path}: {len(raw)} bytes, fewer than its header's channels need")
    stored = np.frombuffer(raw, f"<i{bits // 8}", lines * points, start).astype(float)
    z = float(h["Dim2Min"]) + (stored + 2.0 ** (bits - 1)) / 2.0**bits * float(h["Dim2Range"])
    units = {"xy": h.get("Dim0Unit", "m"), "z": h.get("Dim2Unit")}
    if units["xy"] not in LENGTH_TO_NM or units["z"] not in LENGTH_TO_NM:
        raise ValueError(
            f"{path}: channel {names[pick[0]]!r} has units {units}, not lengths ({', '.join(LENGTH_TO_NM)})"
        )
    scan = head.get("DataSet\\DataSetInfos\\Scan", head.get("DataSet-Info", {}))
    up = scan.get("Scan direction")
    meta = {
        "source": str(path),
        "reader": "nanosurf-nid",
        "channel": names[pick[0]],
        "direction": "trace" if frame == NID_FRAMES["trace"] else "retrace",
        "converted": f"x, y from {units['xy']} and z from {units['z']} to nm",
        "instrument": {k: scan[k] for k in NID_SCAN_ENTRIES.values() if k in scan},
        "scan": _nid_scan(scan),
    }
    size = tuple(float(h[f"Dim{k}Range"]) * LENGTH_TO_NM[units["xy"]] for k in (0, 1))
    first_row = {"Up": "bottom"}.get(up)  # Down: the file does not say where its row 0 lies
    said = None if first_row is None else f"Scan direction={up}"
    return _Stored(z.reshape(lines, points), units["z"], size, meta, first_row, first_row_said=said)


def _nid_scan(scan: dict) -> dict:
    """The scan settings a .nid header records, as a config pair's keys
    (:data:`NID_SCAN_ENTRIES`), each ``{"value": ..., "header": "Rotation=-45 \u00b0"}``:
    ``line_rate_hz`` = 1 / ``Time/Line`` (a line: its trace and its retrace), ``angle_deg`` =
    ``Rotation`` (degrees anticlockwise), ``overscan`` = ``Overscan`` / 100 (of the width, at each
    end of a line), ``lines`` = ``Scan direction`` (``Up``: the bottom line first). An entry the
    header lacks is left out; one whose value or unit is not one of these is kept as
    ``{"unread": ..., "header": ...}`` (``jaxafm.jobs.inputs.scan_settings`` refuses it unless
    the config gives the setting)."""
    recorded = {}
    for key, entry in NID_SCAN_ENTRIES.items():
        text = scan.get(entry, "").strip()
        if entry == "Scan direction":
            value = {"Up": "up", "Down": "down"}.get(text)
        else:
            m = re.fullmatch(r"([-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\s*(\S*)", text)
            scale = _NID_UNITS[entry].get(m.group(2)) if m else None
            value = None if scale is None else float(m.group(1)) * scale
            if key == "line_rate_hz" and value is not None:
                value = 1.0 / value if value > 0 else None
        if value is not None:
            recorded[key] = {"value": value, "header": f"{entry}={text}"}
        elif entry in scan:
            recorded[key] = {"unread": text, "header": f"{entry}={text}"}
    return recorded


def _saved_scan(meta: dict) -> dict:
    """The scan settings a jaxafm image records in its ``meta`` (:data:`SAVED_SCAN_ENTRIES`), as
    :func:`_nid_scan` gives a .nid header's: ``{"value": ..., "header": "meta overscan=0.1"}``."""
    return {
        key: {"value": meta[entry], "header": f"meta {entry}={meta[entry]!r}"}
        for key, entry in SAVED_SCAN_ENTRIES.items()
        if meta.get(entry) is not None
    }


def _nid_channels(path: Path, head: dict) -> list:
    """The channels of a .nid header in the order their data are stored: ``(section, lines,
    points, bits)`` each.

    Raises:
        ValueError: a channel's section lacks or garbles a key.
    """
    groups = head["DataSet"]
    order = [
        groups[f"Gr{g}-Ch{c}"]
        for g in range(int(groups.get("GroupCount", 0)))
        for c in range(int(groups.get(f"Gr{g}-Count", 0)))
        if f"Gr{g}-Ch{c}" in groups
    ]
    try:
        blocks = [
            (head[k], int(head[k]["Lines"]), int(head[k]["Points"]), int(head[k]["SaveBits"])) for k in order
        ]
        for h, *_ in blocks:
            float(h["Dim0Range"]), float(h["Dim1Range"]), float(h["Dim2Min"]), float(h["Dim2Range"])
    except (KeyError, ValueError) as e:
        raise ValueError(f"{path}: a channel section of the .nid header lacks or garbles {e}") from None
    return blocks


def _read_gwy(path: Path, channel: Optional[str]) -> _Stored:
    """A Gwyddion file: the data field titled ``channel`` (default: the first one)."""
    gwyfile = _optional("gwyfile", path)
    try:
        container = gwyfile.load(str(path))
    except Exception as e:  # gwyfile raises several types for a file that is not a .gwy
        raise ValueError(f"{path} is not a readable Gwyddion file ({e})") from None
    titles = {container[k]: k[: -len("/title")] for k in container if re.fullmatch(r"/\d+/data/title", k)}
    if not titles:
        raise ValueError(f"{path}: the Gwyddion file holds no image channel")
    channel = channel or next(iter(titles))
    if channel not in titles:
        raise ValueError(f"{path}: no channel {channel!r}; channels: {sorted(titles)}")
    field = container[titles[channel]]
    units = {
        "xy": field.si_unit_xy.unitstr if field.si_unit_xy else "m",
        "z": field.si_unit_z.unitstr if field.si_unit_z else "m",
    }
    for axis, unit in units.items():
        if unit not in LENGTH_TO_NM:
            raise ValueError(
                f"{path}: channel {channel!r} has {axis} unit {unit!r}, not a length "
                f"({', '.join(LENGTH_TO_NM)})"
            )
    scale = LENGTH_TO_NM[units["xy"]]
    meta = {
        "source": str(path),
        "reader": "gwyfile",
        "channel": channel,
        "converted": f"x, y from {units['xy']} and z from {units['z']} to nm",
    }
    size = (field.xreal * scale, field.yreal * scale)
    first_row = "top"  # Gwyddion's row 0 is the top line
    return _Stored(np.asarray(field.data, dtype=float), units["z"], size, meta, first_row)


def _read_afmreader(path: Path, channel: Optional[str]) -> _Stored:
    module, loader, default = AFMREADER_FORMATS[path.suffix.lower()]
    reader = _optional(f"AFMReader.{module}", path)
    from loguru import logger  # AFMReader logs every step at DEBUG level

    logger.disable("AFMReader")
    channel = channel or default
    try:
        if loader is None:  # .topostats: a dict of arrays
            d = reader.load_topostats(path)
            z, px = d[channel], d["pixel_to_nm_scaling"]
        else:
            z, px = getattr(reader, loader)(path, channel)[:2]
    except (KeyError, ValueError, OSError) as e:
        raise ValueError(f"{path}: cannot read channel {channel!r} ({e}); pass channel=...") from None
    meta = {
        "source": str(path),
        "reader": f"AFMReader.{module}",
        "channel": channel,
        "converted": "to nm by AFMReader",
        "row_order": "as AFMReader returns it",
    }
    z = np.asarray(z, dtype=float)
    _check_shape(z, path)
    return _Stored(z, "nm", (float(px) * z.shape[1], float(px) * z.shape[0]), meta)


def _json_number(value):
    """NumPy and JAX numbers in ``meta`` as plain JSON numbers; anything else is refused."""
    a = np.asarray(value)
    if a.dtype.kind not in "biuf":
        raise TypeError(
            f"image meta value {value!r} is not a number, string, list or dict; convert it before saving"
        )
    return a.tolist()


def save_image(image: AFMImage, path, overwrite: bool = False) -> Path:
    """Write ``image`` as a ``.npz`` in the jaxafm image format; never overwrites unless asked."""
    path = Path(path)
    if path.suffix != ".npz":
        raise ValueError(f"{path}: jaxafm images are saved as .npz files")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "pixel_size_nm": list(image.pixel_size),
        "origin_nm": list(image.origin),
        "meta": image.meta,
    }
    text = json.dumps(doc, default=_json_number)
    partial = path.with_name(path.name + ".partial")
    with open(partial, "wb") as f:
        np.savez_compressed(f, z=image.z, meta_json=np.asarray(text))
    os.replace(partial, path)  # a failed write never leaves a damaged file at ``path``
    return path


def load_image(path) -> AFMImage:
    """Read an image written by :func:`save_image`."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as f:
            z, doc = f["z"], json.loads(str(f["meta_json"]))
        fmt, version = doc.get("format"), doc.get("version")
    except (OSError, ValueError, KeyError, EOFError, AttributeError) as e:
        raise ValueError(f"{path} is not a jaxafm image file ({type(e).__name__}: {e})") from None
    if fmt != FORMAT:
        raise ValueError(f"{path} is not a jaxafm image file (format {fmt!r})")
    if version != VERSION:
        raise ValueError(f"{path}: image format version {version} is not supported ({VERSION} is)")
    try:
        pixel_size, origin, meta = tuple(doc["pixel_size_nm"]), tuple(doc["origin_nm"]), doc["meta"]
    except KeyError as e:
        raise ValueError(f"{path}: the image's meta_json lacks the key {e}") from None
    image = AFMImage(z, pixel_size, origin, {"source": str(path)})  # a bad pixel or size: this file named
    image.meta = meta  # the saved metadata, with the source the image was made from
    return image
