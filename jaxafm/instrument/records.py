"""Actuator time-series records (``docs/conventions.md``, records): read, convert to V / nm / s, split.

A record is a delimited text file with one row per sample. The reader is told
where time (a column, or a sample rate), input and output are, and the units;
a header row naming ``t, u, d`` (or ``t, ux, uy, x, y``) needs no mapping.
Every conversion made is written into ``Record.meta``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Optional, Union

import numpy as np

from ..config.names import LENGTH_TO_NM, VOLTAGE_TO_V

Column = Union[int, str]  # 1-based index or header name


@dataclasses.dataclass(frozen=True)
class Record:
    """Samples ``t`` (T,) s, input ``u`` (T,) or (T, k) V, output ``d`` (T,) or (T, k) nm (None:
    a drive without measured output, read with ``require_output=False``)."""

    t: np.ndarray
    u: np.ndarray
    d: Optional[np.ndarray]
    meta: dict

    def __len__(self) -> int:
        return len(self.t)

    def split(self, train_fraction: float) -> int:
        """Index of the first held-out sample when the first ``train_fraction`` trains."""
        if not 0 < train_fraction < 1:
            raise ValueError(f"train_fraction must be in (0, 1), got {train_fraction}")
        n = int(round(len(self) * train_fraction))
        if n < 10 or len(self) - n < 10:
            raise ValueError(
                f"record {self.meta.get('source', '')!r} has {len(self)} samples: too few to "
                f"split at train_fraction={train_fraction} into two parts of at least 10 samples"
            )
        return n


def _header(path: Path, delimiter: Optional[str]) -> Optional[list]:
    """Column names from a first line that is not numeric (a leading ``#`` is dropped)."""
    try:
        with open(path, encoding="utf-8") as f:
            first = f.readline().strip().lstrip("#").strip()
    except UnicodeDecodeError:
        raise ValueError(
            f"{path}: not a text file; a record is delimited numeric text (CSV, TXT, DAT)"
        ) from None
    if not first:
        raise ValueError(f"{path}: the first line is empty; the record needs data rows")
    names = first.split(delimiter) if delimiter else first.split()
    try:
        [float(x) for x in names]
        return None
    except ValueError:
        return [n.strip() for n in names]


def _column(spec: Column, header: Optional[list], path: Path, key: str) -> int:
    if isinstance(spec, str):
        if header is None or spec not in header:
            raise ValueError(f"{path}: {key}={spec!r} names no column; header is {header}")
        return header.index(spec)
    if spec < 1:
        raise ValueError(f"{path}: {key}={spec} must be a 1-based column number (>= 1)")
    return spec - 1


def _name(i: int, header: Optional[list]) -> str:
    """Column ``i`` (0-based) as the user knows it: its number, and its header name if any."""
    return f"{i + 1}" + (f" ({header[i]!r})" if header and i < len(header) else "")


def _check_distinct(path: Path, header: Optional[list], columns: dict) -> None:
    """No column is mapped twice (as input, output or time).

    Raises:
        ValueError: naming the column and the keys that map it.
    """
    seen = {}
    for key, cols in columns.items():
        for i in cols:
            if i in seen:
                raise ValueError(
                    f"{path}: column {_name(i, header)} is mapped twice ({seen[i]} and {key}); "
                    "input, output and time must be different columns"
                )
            seen[i] = key


def read_record(
    path: Union[str, Path],
    *,
    input_columns: Optional[Sequence[Column]] = None,
    output_columns: Optional[Sequence[Column]] = None,
    time_column: Optional[Column] = None,
    sample_rate_hz: Optional[float] = None,
    input_unit: str = "V",
    output_unit: Optional[str] = None,
    delimiter: Optional[str] = None,
    require_output: bool = True,
) -> Record:
    """Read a record, converting input to V, output to nm and time to s.

    Columns are 1-based numbers or header names. Without a mapping the header
    must name ``t, u, d`` or ``t, ux, uy, x, y``, values already in s, V, nm.
    With ``require_output=False`` a record of inputs alone (no ``output_columns``) is read,
    with ``d`` None.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: naming the file, and the key, column, row or value at fault.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"record file {path} does not exist")
    header = _header(path, delimiter)
    if input_columns is None and output_columns is None:
        input_columns, output_columns, time_column = _named_columns(path, header, sample_rate_hz)
        output_unit = output_unit or "nm"
    if not input_columns or (require_output and not output_columns):
        raise ValueError(f"{path}: give both input_columns and output_columns")
    output_columns = output_columns or []
    _check_units(path, bool(output_columns), input_unit, output_unit)
    if (time_column is None) == (sample_rate_hz is None):
        raise ValueError(f"{path}: give exactly one of time_column and sample_rate_hz")
    data = _rows(path, delimiter, header)
    columns = {"input_columns": input_columns, "output_columns": output_columns}
    columns["time_column"] = [] if time_column is None else [time_column]
    i_in, i_out, i_t = _indices(path, header, columns, data.shape[1])
    u = data[:, i_in] * VOLTAGE_TO_V[input_unit]
    d = data[:, i_out] * LENGTH_TO_NM.get(output_unit, 1.0)
    if sample_rate_hz is not None:
        if not 0 < sample_rate_hz < np.inf:
            raise ValueError(f"{path}: sample_rate_hz must be a finite rate > 0 Hz, got {sample_rate_hz}")
        t = np.arange(len(data)) / sample_rate_hz
    else:
        t = data[:, i_t[0]]
    _check_values(path, header, t, u, d, i_in, i_out)
    meta = {
        "source": str(path),
        "samples": len(t),
        "converted": f"input {input_unit} -> V (x{VOLTAGE_TO_V[input_unit]:g})"
        + (f", output {output_unit} -> nm (x{LENGTH_TO_NM[output_unit]:g})" if i_out else ", no output"),
        "time": f"sample rate {sample_rate_hz} Hz" if sample_rate_hz else f"column {time_column}",
    }
    squeeze = (lambda a: a[:, 0]) if len(i_in) == 1 else (lambda a: a)
    return Record(t, squeeze(u), None if not i_out else d[:, 0] if len(i_out) == 1 else d, meta)


def _indices(path: Path, header: Optional[list], columns: dict, count: int) -> list:
    """The 0-based indices of the columns each key maps (``input_columns``, ``output_columns``,
    ``time_column``), in the file of ``count`` columns.

    Raises:
        ValueError: a column that names none, lies beyond the file's, or is mapped twice.
    """
    indices = [[_column(c, header, path, key) for c in specs] for key, specs in columns.items()]
    for i in sum(indices, []):
        if i >= count:
            raise ValueError(f"{path}: column {i + 1} requested but the file has {count} columns")
    _check_distinct(path, header, dict(zip(columns, indices)))
    return indices


def _named_columns(path: Path, header: Optional[list], sample_rate_hz: Optional[float]) -> tuple:
    """Input, output and time columns from a header that names ``t, u, d`` or ``t, ux, uy, x, y``
    (time from the column ``t`` unless a sample rate is given).

    Raises:
        ValueError: the header names neither.
    """
    names = set(header or [])
    time_column = "t" if sample_rate_hz is None else None
    if {"t", "u", "d"} <= names:
        return ["u"], ["d"], time_column
    if {"t", "ux", "uy", "x", "y"} <= names:
        return ["ux", "uy"], ["x", "y"], time_column
    raise ValueError(
        f"{path}: no column mapping given and the header {header} does not name "
        "'t, u, d' or 't, ux, uy, x, y'; set input_columns, output_columns and "
        "time_column or sample_rate_hz"
    )


def _check_units(path: Path, outputs: bool, input_unit: str, output_unit: Optional[str]) -> None:
    """The input unit is a voltage's and, with ``outputs``, the output unit a length's.

    Raises:
        ValueError: naming the file, the key and what is allowed.
    """
    if outputs and output_unit is None:
        raise ValueError(f"{path}: output_unit is missing; one of {sorted(LENGTH_TO_NM)}")
    if outputs and output_unit not in LENGTH_TO_NM:
        raise ValueError(f"{path}: output_unit={output_unit!r} is not one of {sorted(LENGTH_TO_NM)}")
    if input_unit not in VOLTAGE_TO_V:
        raise ValueError(f"{path}: input_unit={input_unit!r} is not one of {sorted(VOLTAGE_TO_V)}")


def _rows(path: Path, delimiter: Optional[str], header: Optional[list]) -> np.ndarray:
    """The numeric rows (rows, columns) below the header; an empty field (a column a spreadsheet
    left blank) reads as NaN, and the columns used are checked later.

    Raises:
        ValueError: rows that are not numbers (with a hint to set the delimiter of a CSV
            file), or none at all.
    """
    try:
        blank = lambda s: float(s) if s.strip() else np.nan
        data = np.loadtxt(path, delimiter=delimiter, skiprows=1 if header else 0, ndmin=2, converters=blank)
    except ValueError as e:
        hint = (
            " (set delimiter: ',' for a CSV file)"
            if delimiter is None and "," in path.read_text()[:200]
            else ""
        )
        raise ValueError(f"{path}: not a numeric delimited record{hint} ({e})") from None
    if data.size == 0:
        raise ValueError(f"{path}: no data rows")
    return data


def _check_values(path: Path, header, t: np.ndarray, u: np.ndarray, d: np.ndarray, i_in: list, i_out: list):
    """Every value used is finite, time increases strictly, and no input or output column is
    constant.

    Raises:
        ValueError: naming the file, the column and the data row.
    """
    for name, a in (("input", u), ("output", d), ("time", t)):
        if not np.isfinite(a).all():
            row = int(np.argwhere(~np.isfinite(a))[0][0])
            raise ValueError(f"{path}: {name} column has a non-finite value at data row {row + 1}")
    if np.any(np.diff(t) <= 0):
        raise ValueError(f"{path}: time must increase strictly from row to row")
    for key, cols, a, unit in (("input_columns", i_in, u, "V"), ("output_columns", i_out, d, "nm")):
        for i, column in zip(cols, a.T):
            if np.ptp(column) == 0:
                raise ValueError(
                    f"{path}: {key}: column {_name(i, header)} is constant ({column[0]:g} {unit} in all "
                    f"{len(column)} rows); a record must drive and measure a moving axis"
                )


def write_columns(path: Union[str, Path], columns: dict) -> None:
    """A CSV file with a header of the column names (units in the names, e.g. ``t_s,u_v``) and
    one row per sample, 10 significant digits: what :func:`read_record` and a controller read.

    Arguments:
        path: the file to write.
        columns: name -> values (T,), all of one length.
    """
    names = list(columns)
    data = np.column_stack([np.asarray(columns[k], dtype=float) for k in names])
    np.savetxt(path, data, delimiter=",", header=",".join(names), comments="", fmt="%.10g")
