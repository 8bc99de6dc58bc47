"""``jaxafm calibrate`` (step A): identify the scanner from a grating's trace/retrace images,
invert it and compensate. The grating, the simulated calibration scan, the model and the solver
are also step A of ``jaxafm run`` and ``jaxafm study``."""

from __future__ import annotations

from typing import Annotated, Literal, Optional

from pydantic import Field, field_validator, model_validator

from .common import (
    HysteresisKind,
    HysteresisSpec,
    ImagePair,
    ModelName,
    Operators,
    Seed,
    Solver,
    Strict,
)
from .names import MODEL_EFFECTS, check_effect_names


class Grating(Strict):
    """The calibration grating: a square lattice of pillars (or pits) of known pitch."""

    pitch_nm: float = Field(1000.0, gt=0, description="lattice pitch, nm (both axes)")
    pits: bool = Field(False, description="pits instead of pillars")


class SimulatedCalibration(Strict):
    """A trace/retrace image pair of the grating from the built-in simulated AFM
    (``default_afm()``), taken after the initialisation cycle ``+-u_max``."""

    pixels: int = Field(128, ge=32, le=1024, description="pixels per line = lines")
    size_nm: float = Field(8000.0, gt=0, le=9000.0, description="scan width = height, nm")
    line_rate_hz: float = Field(1.0, gt=0, le=50.0)
    withheld: list[str] = Field([], description="effects the simulated instrument does not have")
    seed: Seed = 0

    @model_validator(mode="after")
    def _known_effects(self):
        check_effect_names(self.withheld, "withheld")
        return self


class CalibrationImages(ImagePair):
    """A measured trace/retrace pair (``ImageFile``s: any format
    ``jaxafm.instrument.images.read_image`` reads), its line rate and how the instrument drove
    it; the scan is centred on the scanner's zero."""

    sensitivity_nm_per_v: list[Annotated[float, Field(gt=0)]] = Field(
        min_length=2, max_length=2, description="nominal x, y calibration"
    )
    u_max_v: float = Field(10.0, gt=0)
    history_v: Optional[list[Annotated[list[float], Field(min_length=2, max_length=2)]]] = Field(
        None,
        description="drive turning points (x, y) V before the scan, e.g. the cycle [[-10, -10], [10, 10]]",
    )


class CalibrationModel(HysteresisSpec):
    """One scanner model to identify (an ablation lists several): the shared hysteresis spec
    and the effects besides hysteresis to fit from the images."""

    name: ModelName
    kind: HysteresisKind = "gpi"
    operators: Operators = 16
    effects: list[str] = Field(
        ["asymmetry", "creep", "coupling", "bow", "feedback_lag"], description="effects besides hysteresis"
    )

    @field_validator("effects")
    @classmethod
    def _fittable(cls, effects):
        for e in effects:
            if e not in MODEL_EFFECTS:
                raise ValueError(
                    f"effect {e!r} cannot be fitted from grating images; choose from {', '.join(MODEL_EFFECTS)}"
                )
        return effects


class CalibrationSolver(Strict):
    """The solver of step A's staged image fit."""

    name: Solver = "optimistix.levenberg_marquardt"  # type: ignore[valid-type]
    max_steps: int = Field(100, ge=1, le=10_000, description="per stage")
    blur_px: list[Annotated[float, Field(ge=0, le=64)]] = Field(
        [2.0, 1.0], description="image stages, coarse to fine: Gaussian sigma (px), 0 for none"
    )


class Compensation(Strict):
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


class CalibrateConfig(Strict):
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
        return self
