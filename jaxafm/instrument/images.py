"""AFM images, simulated or measured: one type, readers for instrument files, a file format.

``AFMImage``: heights ``z`` (rows, columns) nm, row 0 at the lowest y and
column 0 at the lowest x (files that do not say keep their stored order, noted in ``meta``), the pixel
size (x, y) nm, the position of pixel [0, 0]'s centre, and a ``meta`` dict
(source, direction, line rate, start time, unit conversions done).

Readers convert to nm and say so in ``meta``: the Nanosurf text export, TIFF
height maps (whose size the caller gives), and through AFMReader (the
``formats`` extra) Bruker .spm, Igor .ibw, JPK .jpk and TopoStats files, and
Gwyddion .gwy through gwyfile.

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
#: Suffix -> AFMReader module and loader, with the channel it reads by default.
AFMREADER_FORMATS = {
    ".spm": ("spm", "load_spm", "Height"),
    ".ibw": ("ibw", "load_ibw", "HeightTracee"),
    ".jpk": ("jpk", "load_jpk", "height_trace"),
    ".topostats": ("topostats", None, "image"),
}
FORMATS = (".txt", ".tif", ".tiff", ".gwy", ".npz") + tuple(AFMREADER_FORMATS)


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
        if self.z.ndim != 2 or min(self.z.shape) < 2:
            raise ValueError(f"{where}: an AFM image needs at least 2 x 2 pixels, got shape {self.z.shape}")
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
        "start_time_s": float(np.min(getattr(scan, f"t_{direction}"))),
        **(meta or {}),
    }
    return AFMImage(np.asarray(getattr(scan, direction)), raster.pixel_size, raster.origin, info)


def read_image(
    path, channel: Optional[str] = None, size_nm: Optional[tuple] = None, z_unit: str = "nm"
) -> AFMImage:
    """Read an AFM image file into nm, choosing the reader by the file's suffix.

    ``channel`` picks the channel of multi-channel files (AFMReader formats);
    ``size_nm`` (width, height) and ``z_unit`` say what a TIFF cannot.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".txt":
        return _read_nanosurf_text(path)
    if suffix in (".tif", ".tiff"):
        return _read_tiff(path, size_nm, z_unit)
    if suffix == ".npz":
        return load_image(path)
    if suffix == ".gwy":
        return _read_gwy(path, channel)
    if suffix in AFMREADER_FORMATS:
        return _read_afmreader(path, channel)
    raise ValueError(f"{path}: unknown AFM image format {suffix!r}; known: {', '.join(FORMATS)}")


def _length_nm(path: Path, key: str, text: str) -> float:
    m = re.fullmatch(r"\s*([-+0-9.eE]+)\s*(\S+)\s*", text)
    if not m or m.group(2) not in LENGTH_TO_NM:
        raise ValueError(
            f"{path}: header {key!r} = {text!r} is not a length with a unit of {', '.join(LENGTH_TO_NM)}"
        )
    return float(m.group(1)) * LENGTH_TO_NM[m.group(2)]


def _read_nanosurf_text(path: Path) -> AFMImage:
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
    return AFMImage(
        z.reshape(rows, cols) * LENGTH_TO_NM[z_unit], (width / cols, height / rows), (0.0, 0.0), meta
    )


def _read_tiff(path: Path, size_nm, z_unit: str) -> AFMImage:
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
    if size_nm is None:
        raise ValueError(
            f"{path}: a TIFF does not carry its length calibration; pass "
            "size_nm=(width, height) in nm, and z_unit if heights are not in nm"
        )
    if z_unit not in LENGTH_TO_NM:
        raise ValueError(f"{path}: z_unit={z_unit!r} is not one of {', '.join(LENGTH_TO_NM)}")
    w, h = np.broadcast_to(np.asarray(size_nm, dtype=float), (2,))
    meta = {
        "source": str(path),
        "reader": "tiff",
        "converted": f"z from {z_unit} to nm",
        "size_nm_given": [float(w), float(h)],
        "row_order": "as stored",
    }
    return AFMImage(
        z.astype(float) * LENGTH_TO_NM[z_unit], (w / z.shape[1], h / z.shape[0]), (0.0, 0.0), meta
    )


def _optional(module: str, path: Path):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ImportError(
            f"{path}: reading {path.suffix} files needs {module.split('.')[0]}: pip install 'jaxafm[formats]'"
        ) from None


def _read_gwy(path: Path, channel: Optional[str]) -> AFMImage:
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
    z = np.flipud(np.asarray(field.data, dtype=float)) * LENGTH_TO_NM[units["z"]]  # Gwyddion: row 0 on top
    rows, cols = z.shape
    scale = LENGTH_TO_NM[units["xy"]]
    meta = {
        "source": str(path),
        "reader": "gwyfile",
        "channel": channel,
        "converted": f"x, y from {units['xy']} and z from {units['z']} to nm",
        "row_order": "flipped: row 0 is the bottom line",
    }
    return AFMImage(z, (field.xreal * scale / cols, field.yreal * scale / rows), (0.0, 0.0), meta)


def _read_afmreader(path: Path, channel: Optional[str]) -> AFMImage:
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
    return AFMImage(np.asarray(z, dtype=float), (float(px), float(px)), (0.0, 0.0), meta)


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
        return AFMImage(z, tuple(doc["pixel_size_nm"]), tuple(doc["origin_nm"]), doc["meta"])
    except KeyError as e:
        raise ValueError(f"{path}: the image's meta_json lacks the key {e}") from None
