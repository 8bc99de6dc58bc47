"""What every command's configuration shares: the strict schema base, the error type, the YAML
loader, data paths, the hysteresis-model spec, the measured-record spec and the image-file spec.

Units as everywhere in jaxafm (``docs/conventions.md``): nm, s, V; a key's unit is in its name.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, ClassVar, Literal, Optional, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .names import LENGTH_TO_NM, SOLVERS, VOLTAGE_TO_V

Solver = Literal[SOLVERS]  # type: ignore[valid-type]
HysteresisKind = Literal["pi", "gpi", "preisach"]
LengthUnit = Literal[tuple(LENGTH_TO_NM)]  # type: ignore[valid-type]
Length = Annotated[float, Field(gt=0)]

#: The limits of :class:`HysteresisSpec`, the same for every command (see its docstring).
MAX_OPERATORS = 200
MAX_DEADZONES = 20
MAX_LEVELS = 100

Operators = Annotated[int, Field(ge=2, le=MAX_OPERATORS, description="play operators (pi, gpi)")]
Deadzones = Annotated[int, Field(ge=1, le=MAX_DEADZONES, description="dead zones each side (gpi)")]
Levels = Annotated[int, Field(ge=2, le=MAX_LEVELS, description="Preisach plane levels")]
Seed = Annotated[int, Field(ge=0, lt=2**32, description="random seed, 0 <= seed < 2**32")]
ModelName = Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]+$", description="names the model's output file")]


class ConfigError(ValueError):
    """A configuration that cannot be run; the message names file, key and value."""


class Strict(BaseModel):
    """A schema that refuses unknown keys (a misspelt key is an error, not a silent default),
    NaN and infinite numbers (``.nan``, ``.inf``, ``"nan"``) at any depth, and whose values
    cannot change after validation."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class HysteresisSpec(Strict):
    """The hysteresis model of a fit, the same keys for every command (``fit``, ``calibrate``,
    ``run``, ``study``, ``diagnose``): its ``kind``, ``operators`` plays (pi, gpi; thresholds
    evenly over half the drive span), ``deadzones`` each side (gpi) and ``levels`` of a
    Preisach plane. Each command's schema names the kinds it can fit and its defaults.

    The limits are set by the cost of the fit: its Levenberg–Marquardt or BFGS step holds a
    dense (weights x weights) matrix in float64. A Preisach plane of L levels has L(L+1)/2
    weights: 100 levels are 5 050 weights, a 0.2 GB matrix (200 levels would be 20 100 weights
    and 3.2 GB). 200 plays resolve the play radii in steps of 1/400 of the drive span (50 mV
    over +-10 V), finer than the finest Preisach plane (1/200 of the span), with about ten
    times the plays or levels the shipped configs use (16 to 30).
    """

    kind: HysteresisKind = "gpi"
    operators: Operators = 20
    deadzones: Deadzones = 3
    levels: Levels = 20


class RecordData(Strict):
    """A measured time-series record (``docs/conventions.md``, records); columns are 1-based or
    header names."""

    path: str = Field(description="file path, relative to the config file, or builtin:NAME")
    input_columns: Optional[list[Union[int, str]]] = None
    output_columns: Optional[list[Union[int, str]]] = None
    time_column: Optional[Union[int, str]] = None
    sample_rate_hz: Optional[float] = Field(None, gt=0)
    input_unit: Literal[tuple(VOLTAGE_TO_V)] = "V"  # type: ignore[valid-type]
    output_unit: Optional[LengthUnit] = None
    delimiter: Optional[str] = None


class ImageFile(Strict):
    """An AFM image file a config names, with what its format may lack; a plain string is its
    ``path`` alone. Given metadata wins over the file's and is noted in the image's ``meta``,
    but a file's own size must agree within 1 % and its own height unit exactly
    (``jaxafm.instrument.images.read_image``; ``docs/instrument.md``)."""

    path: str = Field(description="image file, relative to the config file, or builtin:NAME")
    size_nm: Optional[Annotated[list[Length], Field(min_length=1, max_length=2)]] = Field(
        None,
        description="nm: [width along the scan lines (x), height across them (y)], or one number "
        "for a square scan; default: the file's (a TIFF has none)",
    )
    z_unit: Optional[LengthUnit] = Field(
        None, description="unit of the stored heights; default: the file's, nm for a TIFF"
    )
    line_rate_hz: Optional[float] = Field(
        None, gt=0, description="Hz: lines (trace + retrace) per second; default: the file's, if any"
    )
    fast_axis: Literal["x", "y"] = Field(
        "x",
        description="the image axis the scan lines run along; y: the stored columns, traced upward, "
        "turned a quarter turn clockwise into rows (the last column becomes row 0)",
    )
    first_row: Optional[Literal["bottom", "top"]] = Field(
        None,
        description="where the stored row 0 lies: bottom (the lowest y) or top (flipped); "
        "default: the file's (Gwyddion: top), else bottom",
    )
    direction: Optional[Literal["trace", "retrace"]] = Field(
        None,
        description="the scan direction the file holds; default: under a pair's trace or retrace key, "
        "that key's (a file recording the other is refused); else the file's, if any",
    )

    @model_validator(mode="before")
    @classmethod
    def _path_alone(cls, value):
        return {"path": value} if isinstance(value, str) else value

    @field_validator("size_nm", mode="before")
    @classmethod
    def _one_number(cls, value):
        return value if value is None or isinstance(value, (list, tuple)) else [value]


class ImagePair(Strict):
    """A trace/retrace pair of image files and how it was scanned: its line rate and the
    settings of :attr:`SCAN_DEFAULTS`. A setting left out is the one the files' own header
    records (a Nanosurf .nid file's), else its default (the line rate has none); one given must
    agree with the header's (``jaxafm.jobs.inputs.scan_settings``). An image's own ``direction``
    and ``line_rate_hz``, where given, must agree with the pair's."""

    #: the scan settings besides the line rate, with their defaults where the files do not say
    SCAN_DEFAULTS: ClassVar[dict] = {}

    trace: ImageFile = Field(description="the trace image: a path, relative to the config file, or a mapping")
    retrace: ImageFile = Field(
        description="the retrace image: a path, relative to the config file, or a mapping"
    )
    line_rate_hz: Optional[float] = Field(
        None, gt=0, description="lines (trace + retrace) per second; default: the files' header's"
    )

    @model_validator(mode="after")
    def _images_agree(self):
        for key in ("trace", "retrace"):
            image = getattr(self, key)
            if image.direction not in (None, key):
                raise ValueError(
                    f"{key}.direction is {image.direction!r}, but the {key} key holds the {key} "
                    f"image: remove {key}.direction or swap the files"
                )
        rates = self.given_line_rates
        if len(rates) > 1 and not all(math.isclose(r, next(iter(rates.values()))) for r in rates.values()):
            said = ", ".join(f"{k} = {r:g} Hz" for k, r in rates.items())
            raise ValueError(f"{said} disagree: give the pair's line rate once, as line_rate_hz")
        return self

    @property
    def given_line_rates(self) -> dict:
        """The line rates the config gives, by the key it gives each under (``line_rate_hz``, the
        pair's, first; ``trace.line_rate_hz``, ``retrace.line_rate_hz``)."""
        rates = {"line_rate_hz": self.line_rate_hz}
        rates |= {f"{k}.line_rate_hz": getattr(self, k).line_rate_hz for k in ("trace", "retrace")}
        return {k: r for k, r in rates.items() if r is not None}

    @property
    def given_line_rate_hz(self) -> Optional[float]:
        """The line rate the config gives: the pair's, else an image's, else None."""
        return next(iter(self.given_line_rates.values()), None)


def _key(loc: tuple) -> str:
    """A pydantic error's location as the key the user wrote, ``a.b.0.c``: without the names
    pydantic gives the members of a union (``constrained-int``, ``list[int]``, ``literal['auto']``)."""
    union = lambda p: isinstance(p, str) and (p in ("int", "float", "str", "bool") or not p.isidentifier())
    return ".".join(str(p) for p in loc if not union(p))


def _format(error: ValidationError, path: Path) -> str:
    """pydantic's errors as one line per key: ``key: what is wrong (got value)``."""
    lines = [f"{path}: invalid configuration"]
    for e in error.errors():
        key = _key(e["loc"])
        value = "" if e["type"] == "missing" or not key else f" (got {e.get('input')!r})"
        msg = e["msg"].replace(
            "Extra inputs are not permitted", "unknown key: remove it or check its spelling"
        )
        msg = msg.removeprefix("Value error, ")
        lines.append(f"  {key}: {msg}{value}" if key else f"  {msg}")
    return "\n".join(lines)


def load_config(path: Union[str, Path], schema: Optional[type] = None):
    """Read a YAML configuration and validate it against ``schema``.

    Arguments:
        path: the YAML file.
        schema: the command's schema, e.g. ``RunConfig``; default ``ActuatorFitConfig``
            (``jaxafm fit``): a file that fails it but passes another command's schema says which.

    Returns:
        The validated ``schema`` instance.

    Raises:
        ConfigError: naming the file, and for each wrong key the key, the value and what is allowed.
    """
    defaulted = schema is None
    if defaulted:
        from .fit import ActuatorFitConfig as schema
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} " + ("is a folder" if path.is_dir() else "does not exist"))
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file (a YAML config is UTF-8 text)") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from None
    if not isinstance(raw, dict):
        found = "an empty file" if raw is None else f"a {type(raw).__name__}"
        raise ConfigError(f"{path}: expected a mapping of keys at the top level, found {found}")
    try:
        return schema.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(_format(e, path) + (_schema_hint(raw) if defaulted else "")) from None


def _schema_hint(raw: dict) -> str:
    """For a config read without a schema (so as ``jaxafm fit``'s) that fails it: the commands whose
    schema it passes, and how to read it as theirs (empty where none does)."""
    from . import SCHEMAS

    fits = []
    for command, schema in list(SCHEMAS.items())[1:]:  # not fit's, which it failed
        try:
            schema.model_validate(raw)
        except ValidationError:
            continue
        fits.append(f"`jaxafm {command}` (load_config(path, {schema.__name__}))")
    if not fits:
        return ""
    return (
        "\n(read as a `jaxafm fit` config, the default; it is a valid config of " + " and ".join(fits) + ")"
    )


def resolve_data_path(spec: str, config_path: Path) -> Path:
    """Where a config's file lies.

    Arguments:
        spec: ``builtin:NAME`` (the copy shipped in ``jaxafm/data/real``), an absolute path, or a
            path relative to the config file.
        config_path: the config file.

    Returns:
        The file's path.
    """
    if spec.startswith("builtin:"):
        return Path(__file__).parents[1] / "data" / "real" / spec.removeprefix("builtin:")
    p = Path(spec)
    return p if p.is_absolute() else Path(config_path).parent / p
