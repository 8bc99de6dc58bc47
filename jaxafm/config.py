"""YAML run configurations, validated by pydantic schemas before any work starts.

Errors name the file, the key and the value, and say what is allowed.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Literal, Optional, Union

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .effects import EFFECTS
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


def _format(error: ValidationError, path: Path) -> str:
    lines = [f"{path}: invalid configuration"]
    for e in error.errors():
        key = ".".join(str(p) for p in e["loc"]) or "(top level)"
        value = "" if e["type"] == "missing" else f" (got {e.get('input')!r})"
        msg = e["msg"].replace("Extra inputs are not permitted", "unknown key: remove it or check its spelling")
        lines.append(f"  {key}: {msg}{value}")
    return "\n".join(lines)


def load_config(path: Union[str, Path]) -> ActuatorFitConfig:
    """Read and validate a YAML configuration; raise :class:`ConfigError` naming what is wrong."""
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
        return ActuatorFitConfig.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(_format(e, path)) from None


def resolve_data_path(spec: str, config_path: Path) -> Path:
    """``builtin:NAME`` -> the copy shipped in ``jaxafm/data/real``; else relative to the config."""
    if spec.startswith("builtin:"):
        return Path(__file__).parent / "data" / "real" / spec.removeprefix("builtin:")
    p = Path(spec)
    return p if p.is_absolute() else config_path.parent / p
