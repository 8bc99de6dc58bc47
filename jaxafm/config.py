"""YAML run configurations, validated by pydantic schemas before any work starts.

Errors name the file, the key and the value, and say what is allowed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional, Union

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .identify.calibration import MODEL_EFFECTS
from .identify.fit import SOLVERS
from .instrument.records import LENGTH_TO_NM, VOLTAGE_TO_V
from .model.effects import EFFECTS, check_effect_names

Solver = Literal[SOLVERS]  # type: ignore[valid-type]


class ConfigError(ValueError):
    """A configuration that cannot be run; the message names file, key and value."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RecordData(_Strict):
    """A measured time-series record (design.md, section 3); columns are 1-based or header names."""

    path: str = Field(description="file path, relative to the config file, or builtin:NAME")
    input_columns: Optional[list[Union[int, str]]] = None
    output_columns: Optional[list[Union[int, str]]] = None
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

    effects: list[str] = ["hysteresis", "asymmetry", "creep"]
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
    history_v: Optional[list[float]] = Field(
        None, min_length=1, description="inputs applied before t=0 (V); default: the plays start at u[0]"
    )
    settle_s: float = Field(0.0, ge=0, description="start-up transient left out of the training loss")
    train_fraction: float = Field(0.6, gt=0, lt=1)
    models: list[ModelSpec] = Field(min_length=1)
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
    withheld: list[str] = Field([], description="effects the simulated instrument does not have")
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
    sensitivity_nm_per_v: list[float] = Field(
        min_length=2, max_length=2, description="nominal x, y calibration"
    )
    u_max_v: float = Field(10.0, gt=0)
    line_rate_hz: float = Field(gt=0)
    history_v: Optional[list[list[float]]] = Field(
        None,
        description="drive turning points (x, y) V before the scan, e.g. the cycle [[-10, -10], [10, 10]]",
    )


class CalibrationModel(_Strict):
    """One scanner model to identify (an ablation lists several)."""

    name: str = Field(pattern=r"^[A-Za-z0-9_-]+$", description="names the model's output file")
    kind: Literal["pi", "gpi", "preisach"] = "gpi"
    operators: int = Field(16, ge=2, le=200)
    deadzones: int = Field(3, ge=1, le=20)
    levels: int = Field(20, ge=2, le=100)
    effects: list[str] = Field(
        ["asymmetry", "creep", "coupling", "bow", "feedback_lag"], description="effects besides hysteresis"
    )


class CalibrationSolver(_Strict):
    name: Solver = "optimistix.levenberg_marquardt"  # type: ignore[valid-type]
    max_steps: int = Field(100, ge=1, le=10_000, description="per stage")
    blur_px: list[float] = Field([2.0, 1.0], description="image stages, coarse to fine (px)")


class Compensation(_Strict):
    """Re-image the grating with compensated drives (simulated instrument only)."""

    scan_fraction: float = Field(
        0.85,
        gt=0,
        le=1.0,
        description="compensated scan size / calibration scan size: "
        "below 1, as the tip's true travel over the calibration image falls short "
        "of its nominal size",
    )
    overscan: float = Field(
        0.05, ge=0, le=0.5, description="over-scan of the compensated scans, fraction of the width each side"
    )
    inverses: list[Literal["analytic", "numerical"]] = ["analytic", "numerical"]
    paper_baseline: bool = Field(True, description="also the paper's polynomial + neural-network inverse")


class CalibrateConfig(_Strict):
    """Step A: identify the scanner from one grating image pair, invert it, compensate."""

    data: Optional[CalibrationImages] = None
    simulate: Optional[SimulatedCalibration] = None
    grating: Grating = Grating()
    models: list[CalibrationModel] = Field([CalibrationModel(name="gpi")], min_length=1)
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
                    raise ValueError(
                        f"model {m.name!r}: effect {e!r} cannot be fitted from grating images; "
                        f"choose from {', '.join(MODEL_EFFECTS)}"
                    )
        return self


class StepA(_Strict):
    """Step A of a positioning run: the calibration scan of the simulated AFM and the model
    identified from it, or a scanner fitted earlier (``model_file``, a ``model_*.json``
    written by ``jaxafm calibrate`` from the same calibration scan)."""

    simulate: SimulatedCalibration = SimulatedCalibration()
    grating: Grating = Grating()
    model: CalibrationModel = CalibrationModel(name="gpi")
    solver: CalibrationSolver = CalibrationSolver()
    model_file: Optional[str] = Field(None, description="relative to the config file; skips identification")

    @model_validator(mode="after")
    def _fittable(self):
        if self.simulate.withheld:
            raise ValueError("simulate.withheld: a positioning run needs the full simulated instrument")
        for e in self.model.effects:
            if e not in MODEL_EFFECTS:
                raise ValueError(
                    f"model.effects: {e!r} cannot be fitted from grating images; "
                    f"choose from {', '.join(MODEL_EFFECTS)}"
                )
        return self


class Workspace(_Strict):
    """The area of the task: re-scanned after the landmarks are pressed (step B)."""

    size_nm: float = Field(3000.0, gt=0, description="width = height, nm")
    centre_nm: list[float] = Field([0.0, 0.0], min_length=2, max_length=2)
    pixels: int = Field(256, ge=32, le=1024, description="pixels per line = lines (n of eq. 3)")
    line_rate_hz: float = Field(2.0, gt=0, le=50.0)


class ParticleField(_Strict):
    """Nanoparticles in the cells of the landmark grid, ``per_cell`` x ``per_cell`` to a cell,
    each jittered by up to 1/8 of their spacing, radii uniform in ``radius_nm``; none sits on an
    indent."""

    radius_nm: list[float] = Field([5.0, 50.0], min_length=2, max_length=2, description="[min, max], nm")
    per_cell: int = Field(2, ge=1, le=10, description="particles per landmark cell, each way")
    seed: int = 1

    @model_validator(mode="after")
    def _sizes(self):
        lo, hi = self.radius_nm
        if not lo > 0:
            raise ValueError(f"radius_nm: a particle radius must be > 0 nm, got {lo}")
        if lo > hi:
            raise ValueError(f"radius_nm: [min, max] needs min <= max, got {self.radius_nm}")
        return self


class LandmarkSpec(_Strict):
    """Step B's indent grid (paper eq. 3, in pixels of the workspace image) and interpolation."""

    n: int = Field(5, ge=2, description="N x N indents")
    start_px: float = Field(16.0, ge=0, description="P")
    step_px: float = Field(56.0, gt=0, description="S")
    depth_nm: float = Field(50.0, gt=0, description="deep enough that the pit spans a few pixels")
    interpolation: list[Literal["polynomial", "pairwise"]] = Field(
        ["polynomial", "pairwise"],
        min_length=1,
        description="compared; the first one drives step C and the push",
    )
    m: int = Field(4, ge=2, description="nearest landmarks in the pairwise interpolation")
    degree: int = Field(3, ge=1, le=6, description="polynomial surface degree")


class LocalScanSpec(_Strict):
    """Step C's local scan."""

    points: int = Field(192, ge=16, le=4096, description="samples per line")
    line_time_s: float = Field(0.5, gt=0, description="one direction of a line")
    margin_nm: float = Field(40.0, gt=0, description="how far beyond its expected place to search")
    max_lines: int = Field(24, ge=3, le=1000)
    width_tolerance: float = Field(0.1, gt=0, lt=1, description="accepted pulse-width mismatch, fraction")


class PushSpec(_Strict):
    """The pushing task: each particle pushed by a distance uniform in ``distance_nm`` in a
    random direction; success when it ends within ``tolerance_radii`` x R of the goal."""

    distance_nm: list[float] = Field([100.0, 300.0], min_length=2, max_length=2)
    speed_nm_per_s: float = Field(200.0, gt=0)
    tolerance_radii: float = Field(1.0, gt=0)

    @model_validator(mode="after")
    def _range(self):
        lo, hi = self.distance_nm
        if not 0 < lo <= hi:
            raise ValueError(f"distance_nm: [min, max] needs 0 < min <= max, got {self.distance_nm}")
        return self


class RunConfig(_Strict):
    """The paper's full strategy on the simulated AFM: step A, then an ablation of open loop,
    A, B, A+B and A+B+C over every particle of the workspace, and the push."""

    calibration: StepA = StepA()
    drift_nm_per_min: list[float] = Field([3.0, -1.8], min_length=2, max_length=2)
    workspace: Workspace = Workspace()
    particles: ParticleField = ParticleField()
    landmarks: LandmarkSpec = LandmarkSpec()
    local_scan: LocalScanSpec = LocalScanSpec()
    push: PushSpec = PushSpec()
    stages: list[Literal["open_loop", "A", "B", "A+B"]] = Field(
        ["open_loop", "A", "B", "A+B"], min_length=1, description="A+B goes on to step C and the push"
    )
    seed: int = 0
    output: str = "runs/paper"

    @property
    def particle_spacing_nm(self) -> float:
        """Distance between neighbouring particle sites: a landmark cell over ``per_cell``."""
        ws = self.workspace
        return self.landmarks.step_px * ws.size_nm / ws.pixels / self.particles.per_cell

    @model_validator(mode="after")
    def _fits(self):
        _check_layout(self)
        spacing = self.particle_spacing_nm
        if spacing < 4 * self.particles.radius_nm[1]:
            raise ValueError(
                f"particles.per_cell = {self.particles.per_cell} puts particles {spacing:.0f} nm apart, "
                f"too close for radii up to {self.particles.radius_nm[1]:g} nm: at least 4 x the "
                "largest radius is needed; use fewer per cell or a larger landmark step"
            )
        return self


def _check_layout(cfg) -> None:
    """The landmark grid fits the workspace image (eq. 3), and the workspace lies where step A's
    calibration scan covers the scanner reliably."""
    from .position.landmarks import LandmarkGrid

    lm = cfg.landmarks
    try:
        LandmarkGrid(lm.n, lm.start_px, lm.step_px, cfg.workspace.pixels)
    except ValueError as e:
        raise ValueError(f"landmarks: {e}") from None
    if lm.m > lm.n**2:
        raise ValueError(f"landmarks.m = {lm.m} exceeds the {lm.n**2} landmarks")
    reach = max(abs(c) for c in cfg.workspace.centre_nm) + cfg.workspace.size_nm / 2
    calibrated = Compensation().scan_fraction * cfg.calibration.simulate.size_nm / 2
    if reach > calibrated:
        raise ValueError(
            f"workspace: it reaches {reach:.0f} nm from the scanner's centre, beyond the "
            f"{calibrated:.0f} nm that step A's calibration scan covers reliably "
            f"({Compensation().scan_fraction:g} x half its size): make the workspace "
            "smaller, move it inward, or calibrate over a larger scan"
        )


def _format(error: ValidationError, path: Path) -> str:
    lines = [f"{path}: invalid configuration"]
    for e in error.errors():
        key = ".".join(str(p) for p in e["loc"])
        value = "" if e["type"] == "missing" or not key else f" (got {e.get('input')!r})"
        msg = e["msg"].replace(
            "Extra inputs are not permitted", "unknown key: remove it or check its spelling"
        )
        msg = msg.removeprefix("Value error, ")
        lines.append(f"  {key}: {msg}{value}" if key else f"  {msg}")
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


class DiagnoseNominal(_Strict):
    """The nominal model ``jaxafm diagnose`` starts from: its hysteresis and its other effects."""

    kind: Literal["pi", "gpi", "preisach"] = Field("pi", description="pi: the classical symmetric PI model")
    effects: list[str] = Field(["hysteresis"], description="effects the nominal model has")
    operators: int = Field(20, ge=2, le=200, description="play operators (pi, gpi)")
    deadzones: int = Field(3, ge=1, le=20, description="dead zones each side (gpi)")
    levels: int = Field(20, ge=2, le=100, description="Preisach plane levels")

    @model_validator(mode="after")
    def _known_effects(self):
        check_effect_names(self.effects, "nominal.effects")
        if "hysteresis" not in self.effects:
            raise ValueError(f"nominal.effects must include 'hysteresis', got {self.effects}")
        return self


class DiagnoseSimulation(_Strict):
    """A two-axis record of the simulated PI scanner with one effect the nominal model lacks
    (``jaxafm.withheld.simulate_record``; ``magnitude`` in ``withheld.RECORD_UNITS``)."""

    withheld: Optional[str] = Field(None, description="the effect switched on; none: a control")
    magnitude: float = 0.0
    duration_s: float = Field(20.0, gt=0)
    sample_rate_hz: float = Field(100.0, gt=0)
    noise_nm: float = Field(2.0, ge=0)
    seed: int = 0

    @model_validator(mode="after")
    def _known_effect(self):
        if self.withheld is not None:
            check_effect_names([self.withheld], "simulate.withheld")
        return self


class DiagnoseImage(_Strict):
    """One image of a 1-D grating (any format ``jaxafm.images.read_image`` reads), lines along
    the slow axis; rows are taken in scan order (row 0 first)."""

    path: str = Field(description="image file, relative to the config file, or builtin:NAME")


class ScanGrating(_Strict):
    """The calibration grating a scan set images (its datasheet) and the tip's cone."""

    pitch_nm: float = Field(gt=0)
    edge_width_nm: float = Field(gt=0, description="width of an edge's linear ramp (nm)")
    tip_half_angle_deg: float = Field(20.0, gt=0, lt=90)


class ScanFiles(_Strict):
    """One trace/retrace pair (any format ``jaxafm.images.read_image`` reads), both left to right,
    row 0 scanned first, and how fast it was scanned."""

    trace: str = Field(description="image file, relative to the config file")
    retrace: str = Field(description="image file, relative to the config file")
    line_rate_hz: float = Field(gt=0, description="lines (trace + retrace) per second")
    overscan: float = Field(0.0, ge=0, le=1, description="fraction of the width scanned beyond each end")


class ScanSimulation(_Strict):
    """Trace/retrace pairs of the simulated AFM (``jaxafm.withheld.simulate_scans``)."""

    withheld: Optional[Literal["feedback_lag", "tip", "rate_dependence"]] = Field(
        None, description="the effect switched on; none: a control"
    )
    magnitude: float = Field(0.0, ge=0, description="units: jaxafm.withheld.SCAN_UNITS")
    line_rates_hz: list[float] = Field([1.0, 4.0], min_length=2)
    lines: int = Field(24, ge=8, le=4096)
    pixels: int = Field(512, ge=64, le=8192)
    noise_nm: float = Field(0.5, ge=0)
    seed: int = 0

    @model_validator(mode="after")
    def _valid(self):
        if min(self.line_rates_hz) <= 0 or len(set(self.line_rates_hz)) < 2:
            raise ValueError(
                f"line_rates_hz needs two or more different rates > 0 Hz, got {self.line_rates_hz}"
            )
        if self.withheld is not None and not self.magnitude > 0:
            raise ValueError(f"magnitude must be > 0 for withheld {self.withheld!r}, got {self.magnitude}")
        return self


class DiagnoseScans(_Strict):
    """Trace/retrace images of a 1-D grating at two or more scan speeds (``jaxafm.diagnose_scans``):
    ``pairs`` from files, or ``simulate``; ``grating`` is required with files."""

    grating: Optional[ScanGrating] = None
    pairs: Optional[list[ScanFiles]] = Field(None, min_length=2)
    simulate: Optional[ScanSimulation] = None

    @model_validator(mode="after")
    def _one_source(self):
        if (self.pairs is None) == (self.simulate is None):
            raise ValueError("scans: give exactly one of 'pairs' (files) and 'simulate'")
        if self.pairs is not None and self.grating is None:
            raise ValueError(
                "scans.grating is required with scans.pairs: the grating's pitch_nm and edge_width_nm "
                "from its datasheet"
            )
        return self


class DiagnoseConfig(_Strict):
    """Sim-to-real gap diagnosis: fit the nominal model, then nominal + each candidate effect on the
    training part; compare the gaps on the held-out part (``jaxafm.diagnose``)."""

    data: Optional[RecordData] = None
    simulate: Optional[DiagnoseSimulation] = None
    image: Optional[DiagnoseImage] = None
    scans: Optional[DiagnoseScans] = None
    nominal: DiagnoseNominal = DiagnoseNominal()
    candidates: list[str] = Field(
        ["asymmetry", "rate_dependence", "creep", "drift", "coupling", "bow", "feedback_lag", "tip"],
        min_length=1,
    )
    history_v: Optional[list[float]] = Field(
        None, min_length=1, description="inputs applied before t=0 (V); default: the plays start at u[0]"
    )
    settle_s: float = Field(0.0, ge=0, description="start-up transient left out of the training loss")
    train_fraction: float = Field(
        0.6, gt=0, lt=1, description="records: first part of the time; images: of the rows"
    )
    min_shrink_pct: float = Field(
        5.0, ge=0, description="held-out gap shrink a significant candidate needs, %"
    )
    min_delta_bic: float = Field(10.0, ge=0, description="training BIC drop a significant candidate needs")
    max_steps: int = Field(300, ge=1, le=100_000, description="Levenberg-Marquardt steps per fit")
    output: str = "runs/diagnose"

    @model_validator(mode="after")
    def _one_source(self):
        if sum(s is not None for s in (self.data, self.simulate, self.image, self.scans)) != 1:
            raise ValueError(
                "give exactly one of 'data' (an actuator record), 'simulate', 'image' and 'scans'"
            )
        check_effect_names(self.candidates, "candidates")
        if self.history_v is not None and not all(np.isfinite(self.history_v)):
            raise ValueError(f"history_v must hold finite voltages, got {self.history_v}")
        return self


# ---------------------------------------------------------------------------------------------
# Monte-Carlo positioning studies (`jaxafm study`)


class Distribution(_Strict):
    """One parameter's spread across a study: exactly one of ``uniform: [min, max]``,
    ``loguniform: [min, max]`` (min > 0), ``normal: [mean, std]`` or ``fixed: value``;
    a bare number in the YAML is ``fixed``."""

    uniform: Optional[list[float]] = Field(None, min_length=2, max_length=2)
    loguniform: Optional[list[float]] = Field(None, min_length=2, max_length=2)
    normal: Optional[list[float]] = Field(None, min_length=2, max_length=2)
    fixed: Optional[float] = None

    @model_validator(mode="before")
    @classmethod
    def _number_is_fixed(cls, raw):
        return {"fixed": raw} if isinstance(raw, (int, float)) and not isinstance(raw, bool) else raw

    @model_validator(mode="after")
    def _valid(self):
        given = [k for k in ("uniform", "loguniform", "normal", "fixed") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of uniform, loguniform, normal, fixed; got {given or 'none'}")
        a, b = (self.fixed, self.fixed) if self.fixed is not None else getattr(self, given[0])
        if given[0] in ("uniform", "loguniform") and a > b:
            raise ValueError(f"{given[0]}: [min, max] needs min <= max, got [{a}, {b}]")
        if given[0] == "loguniform" and not a > 0:
            raise ValueError(f"loguniform: needs min > 0, got {a}")
        if given[0] == "normal" and b < 0:
            raise ValueError(f"normal: [mean, std] needs std >= 0, got {b}")
        return self

    @property
    def support(self) -> tuple:
        """The smallest and largest value it can draw."""
        if self.fixed is not None:
            return self.fixed, self.fixed
        if self.normal is not None:
            mean, std = self.normal
            return (mean, mean) if std == 0 else (-np.inf, np.inf)
        return tuple(self.uniform or self.loguniform)

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        if self.fixed is not None:
            return np.full(n, float(self.fixed))
        if self.uniform is not None:
            return rng.uniform(*self.uniform, n)
        if self.loguniform is not None:
            return np.exp(rng.uniform(*np.log(self.loguniform), n))
        return rng.normal(*self.normal, n)


#: What a study can vary, per effect: parameter -> (``default_afm`` argument, allowed range, default).
STUDY_PARAMETERS = {
    "hysteresis": {"loop_width": ("loop_width", (0.0, 0.45), 0.15)},
    "creep": {"gamma": ("creep_gamma", (0.0, 0.1), 0.01)},
    "coupling": {"strength": ("coupling", (-0.2, 0.2), 0.02)},
    "bow": {"per_nm": ("bow", (-2e-5, 2e-5), 2e-6)},
    "drift": {
        "x_nm_per_min": ("drift_x", (-np.inf, np.inf), 3.0),
        "y_nm_per_min": ("drift_y", (-np.inf, np.inf), -1.8),
        "wander_nm_per_sqrt_s": ("drift_sigma", (0.0, 10.0), 0.05),
    },
    "noise": {"std_nm": ("noise_std", (0.0, 20.0), 0.2)},
    "feedback_lag": {"tau_s": ("feedback_tau", (0.0, 0.05), 1e-3)},
    "tip": {"radius_nm": ("tip_radius", (0.5, 100.0), 10.0)},
}


class StudyConfig(_Strict):
    """A Monte-Carlo positioning study: ``trials`` independent trials, each a particle of radius
    drawn from ``particles.radius_nm`` at a random place in the landmark grid, on a scanner drawn
    from ``scanner`` (shared by ``trials_per_scanner`` consecutive trials: step A and the surveys
    run once per scanner; 1 runs them per trial), through the ``stages``."""

    trials: int = Field(256, ge=1, le=10_000_000)
    trials_per_scanner: int = Field(256, ge=1, description="1: step A per trial")
    chunk: int = Field(256, ge=1, le=1_000_000, description="trials per batch and per results file")
    stages: list[Literal["open_loop", "A", "B", "A+B", "A+B+C", "push"]] = Field(
        ["open_loop", "A", "A+B", "A+B+C", "push"], min_length=1
    )
    scanner: dict[str, dict[str, Distribution]] = Field(
        default_factory=dict, description="effect -> parameter -> distribution (see STUDY_PARAMETERS)"
    )
    particle_radius_nm: Distribution = Distribution(uniform=[5.0, 50.0])
    calibration: StepA = StepA()
    workspace: Workspace = Workspace()
    landmarks: LandmarkSpec = LandmarkSpec()
    local_scan: LocalScanSpec = LocalScanSpec()
    push: PushSpec = PushSpec()
    seed: int = 0
    output: str = "runs/study"

    @model_validator(mode="after")
    def _possible(self):
        for effect, params in self.scanner.items():
            check_effect_names([effect], "scanner")
            if effect not in STUDY_PARAMETERS:
                raise ValueError(
                    f"scanner.{effect}: a study cannot vary this effect; vary {', '.join(STUDY_PARAMETERS)}"
                )
            for name, dist in params.items():
                if name not in STUDY_PARAMETERS[effect]:
                    raise ValueError(
                        f"scanner.{effect}.{name}: unknown parameter; {effect} has "
                        f"{', '.join(STUDY_PARAMETERS[effect])}"
                    )
                _inside(f"scanner.{effect}.{name}", dist, *STUDY_PARAMETERS[effect][name][1])
        _inside("particle_radius_nm", self.particle_radius_nm, 1.0, 200.0)
        _check_layout(self)
        lm = self.landmarks
        cell = lm.step_px * self.workspace.size_nm / self.workspace.pixels
        if cell < 8 * self.particle_radius_nm.support[1]:
            raise ValueError(
                f"particle_radius_nm: radii up to {self.particle_radius_nm.support[1]:g} nm need "
                f"landmark cells of at least 8 R; they are {cell:.0f} nm: use a larger landmark step"
            )
        needs = {"A+B+C": "A+B", "push": "A+B+C"}
        for stage, before in needs.items():
            if stage in self.stages and before not in self.stages:
                raise ValueError(f"stages: {stage!r} goes on from {before!r}; add {before!r}")
        return self

    @property
    def scanners(self) -> int:
        """How many scanners the study draws."""
        return -(-self.trials // self.trials_per_scanner)


def _inside(key: str, dist: Distribution, lo: float, hi: float) -> None:
    a, b = dist.support
    if a < lo or b > hi:
        raise ValueError(
            f"{key}: the distribution reaches [{a:g}, {b:g}], outside the allowed [{lo:g}, {hi:g}]"
            + ("; a normal distribution is unbounded: use uniform" if np.isinf([a, b]).any() else "")
        )
