"""YAML run configurations, validated by pydantic schemas before any work starts.

Errors name the file, the key and the value, and say what is allowed.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Literal, Optional, Union

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .calibration import MODEL_EFFECTS
from .effects import EFFECTS, check_effect_names
from .fit import SOLVERS
from .records import LENGTH_TO_NM, VOLTAGE_TO_V

Solver = Literal[SOLVERS]  # type: ignore[valid-type]


class ConfigError(ValueError):
    """A configuration that cannot be run; the message names file, key and value."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RecordData(_Strict):
    """A measured time-series record (design.md, section 3); columns are 1-based or header names."""

    path: str = Field(description="file path, relative to the config file, or builtin:NAME")
    input_columns: Optional[List[Union[int, str]]] = None
    output_columns: Optional[List[Union[int, str]]] = None
    time_column: Optional[Union[int, str]] = None
    sample_rate_hz: Optional[float] = Field(None, gt=0)
    input_unit: Literal[tuple(VOLTAGE_TO_V)] = "V"  # type: ignore[valid-type]
    output_unit: Optional[Literal[tuple(LENGTH_TO_NM)]] = None  # type: ignore[valid-type]
    delimiter: Optional[str] = None


class SimulatedData(_Strict):
    """A record from one axis of the built-in simulated scanner (``default_scanner().x``).

    Drive: ``u = amplitude_v * (0.55 + 0.45 cos(2 pi t / period)) * sin(2 pi f t)``,
    an amplitude-modulated sine whose shrinking and growing cycles make minor loops.
    """

    effects: List[str] = ["hysteresis", "asymmetry", "creep"]
    amplitude_v: float = Field(10.0, gt=0, le=10.0)
    frequency_hz: float = Field(1.0, gt=0)
    modulation_period_s: float = Field(10.0, gt=0)
    duration_s: float = Field(40.0, gt=0)
    sample_rate_hz: float = Field(200.0, gt=0)
    noise_nm: float = Field(2.0, ge=0)
    seed: int = 0

    @model_validator(mode="after")
    def _known_effects(self):
        axis_effects = ("hysteresis", "asymmetry", "creep")  # what default_scanner's axes have
        for e in self.effects:
            if e not in EFFECTS:
                raise ValueError(f"unknown effect {e!r}; known effects: {', '.join(EFFECTS)}")
            if e not in axis_effects:
                raise ValueError(f"effect {e!r} is not one of the simulated axis's effects {axis_effects}")
        return self


class ModelSpec(_Strict):
    """One model to fit: its kind, size, optional creep stage and solver."""

    name: str = Field(pattern=r"^[A-Za-z0-9_-]+$", description="names the model's output file")
    kind: Literal["linear", "pi", "gpi", "preisach"]
    operators: int = Field(20, ge=2, le=500, description="play operators (pi, gpi)")
    deadzones: int = Field(3, ge=1, le=20, description="dead zones each side (gpi)")
    levels: int = Field(20, ge=2, le=200, description="Preisach plane levels")
    creep: bool = Field(False, description="add a logarithmic creep stage (0.1 s to 100 s)")
    rate_dependence: bool = Field(False, description="add a first-order lag after hysteresis")
    solver: Optional[Solver] = Field(None, description="default: LM, or BFGS for preisach")
    max_steps: int = Field(2000, ge=1, le=100_000)

    @property
    def solver_name(self) -> str:
        if self.solver:
            return self.solver
        return "optimistix.bfgs" if self.kind == "preisach" else "optimistix.levenberg_marquardt"


class ActuatorFitConfig(_Strict):
    """Fit hysteresis models to one actuator record; train on the start, validate on the rest."""

    data: Optional[RecordData] = None
    simulate: Optional[SimulatedData] = None
    history_v: Optional[List[float]] = Field(
        None, min_length=1, description="inputs applied before t=0 (V); default: the plays start at u[0]")
    settle_s: float = Field(0.0, ge=0, description="start-up transient left out of the training loss")
    train_fraction: float = Field(0.6, gt=0, lt=1)
    models: List[ModelSpec] = Field(min_length=1)
    output: str = "runs/actuator_fit"

    @model_validator(mode="after")
    def _one_source(self):
        if self.history_v is not None and not all(np.isfinite(self.history_v)):
            raise ValueError(f"history_v must hold finite voltages, got {self.history_v}")
        if (self.data is None) == (self.simulate is None):
            raise ValueError("give exactly one of 'data' (a measured record) and 'simulate'")
        names = [m.name for m in self.models]
        if len(set(names)) != len(names):
            raise ValueError(f"model names must be unique, got {names}")
        return self


class Grating(_Strict):
    """The calibration grating: a square lattice of pillars (or pits) of known pitch."""

    pitch_nm: float = Field(1000.0, gt=0, description="lattice pitch, nm (both axes)")
    pits: bool = Field(False, description="pits instead of pillars")


class SimulatedCalibration(_Strict):
    """A trace/retrace image pair of the grating from the built-in simulated AFM
    (``default_afm()``), taken after the initialisation cycle ``+-u_max``."""

    pixels: int = Field(128, ge=32, le=1024, description="pixels per line = lines")
    size_nm: float = Field(8000.0, gt=0, le=9000.0, description="scan width = height, nm")
    line_rate_hz: float = Field(1.0, gt=0, le=50.0)
    withheld: List[str] = Field([], description="effects the simulated instrument does not have")
    seed: int = 0

    @model_validator(mode="after")
    def _known_effects(self):
        check_effect_names(self.withheld, "withheld")
        return self


class CalibrationImages(_Strict):
    """A measured trace/retrace pair (any format ``jaxafm.images.read_image`` reads) and
    how the instrument drove it; the scan is centred on the scanner's zero."""

    trace: str = Field(description="image file, relative to the config file")
    retrace: str = Field(description="image file, relative to the config file")
    sensitivity_nm_per_v: List[float] = Field(min_length=2, max_length=2, description="nominal x, y calibration")
    u_max_v: float = Field(10.0, gt=0)
    line_rate_hz: float = Field(gt=0)
    history_v: Optional[List[List[float]]] = Field(
        None, description="drive turning points (x, y) V before the scan, e.g. the cycle [[-10, -10], [10, 10]]")


class CalibrationModel(_Strict):
    """One scanner model to identify (an ablation lists several)."""

    name: str = Field(pattern=r"^[A-Za-z0-9_-]+$", description="names the model's output file")
    kind: Literal["pi", "gpi", "preisach"] = "gpi"
    operators: int = Field(16, ge=2, le=200)
    deadzones: int = Field(3, ge=1, le=20)
    levels: int = Field(20, ge=2, le=100)
    effects: List[str] = Field(["asymmetry", "creep", "coupling", "bow", "feedback_lag"],
                               description="effects besides hysteresis")


class CalibrationSolver(_Strict):
    name: Solver = "optimistix.levenberg_marquardt"  # type: ignore[valid-type]
    max_steps: int = Field(100, ge=1, le=10_000, description="per stage")
    blur_px: List[float] = Field([2.0, 1.0], description="image stages, coarse to fine (px)")


class Compensation(_Strict):
    """Re-image the grating with compensated drives (simulated instrument only)."""

    scan_fraction: float = Field(0.85, gt=0, le=1.0, description="compensated scan size / calibration scan size: "
                               "below 1, as the tip's true travel over the calibration image falls short "
                               "of its nominal size")
    overscan: float = Field(0.05, ge=0, le=0.5, description="over-scan of the compensated scans, fraction of "
                            "the width each side")
    inverses: List[Literal["analytic", "numerical"]] = ["analytic", "numerical"]
    paper_baseline: bool = Field(True, description="also the paper's polynomial + neural-network inverse")


class CalibrateConfig(_Strict):
    """Step A: identify the scanner from one grating image pair, invert it, compensate."""

    data: Optional[CalibrationImages] = None
    simulate: Optional[SimulatedCalibration] = None
    grating: Grating = Grating()
    models: List[CalibrationModel] = Field([CalibrationModel(name="gpi")], min_length=1)
    solver: CalibrationSolver = CalibrationSolver()
    compensate: Optional[Compensation] = Compensation()
    output: str = "runs/calibrate"

    @model_validator(mode="after")
    def _one_source(self):
        if (self.data is None) == (self.simulate is None):
            raise ValueError("give exactly one of 'data' (measured trace/retrace images) and 'simulate'")
        names = [m.name for m in self.models]
        if len(set(names)) != len(names):
            raise ValueError(f"model names must be unique, got {names}")
        for m in self.models:
            for e in m.effects:
                if e not in MODEL_EFFECTS:
                    raise ValueError(f"model {m.name!r}: effect {e!r} cannot be fitted from grating images; "
                                     f"choose from {', '.join(MODEL_EFFECTS)}")
        return self


def _format(error: ValidationError, path: Path) -> str:
    lines = [f"{path}: invalid configuration"]
    for e in error.errors():
        key = ".".join(str(p) for p in e["loc"]) or "(top level)"
        value = "" if e["type"] == "missing" else f" (got {e.get('input')!r})"
        msg = e["msg"].replace("Extra inputs are not permitted", "unknown key: remove it or check its spelling")
        lines.append(f"  {key}: {msg}{value}")
    return "\n".join(lines)


def load_config(path: Union[str, Path], schema: type = ActuatorFitConfig):
    """Read a YAML configuration and validate it against ``schema``; raise
    :class:`ConfigError` naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping of keys at the top level")
    try:
        return schema.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(_format(e, path)) from None


def resolve_data_path(spec: str, config_path: Path) -> Path:
    """``builtin:NAME`` -> the copy shipped in ``jaxafm/data/real``; else relative to the config."""
    if spec.startswith("builtin:"):
        return Path(__file__).parent / "data" / "real" / spec.removeprefix("builtin:")
    p = Path(spec)
    return p if p.is_absolute() else config_path.parent / p
