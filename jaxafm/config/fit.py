"""``jaxafm fit``: hysteresis models fitted to one actuator record."""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, model_validator

from .common import HysteresisSpec, ModelName, RecordData, Seed, Strict
from .names import EFFECTS, LINEAR_SOLVERS, SOLVERS


class SimulatedData(Strict):
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
    seed: Seed = 0

    @model_validator(mode="after")
    def _known_effects(self):
        axis_effects = ("hysteresis", "asymmetry", "creep")  # what default_scanner's axes have
        for e in self.effects:
            if e not in EFFECTS:
                raise ValueError(f"unknown effect {e!r}; known effects: {', '.join(EFFECTS)}")
            if e not in axis_effects:
                raise ValueError(f"effect {e!r} is not one of the simulated axis's effects {axis_effects}")
        return self


class ModelSpec(HysteresisSpec):
    """One model to fit: the shared hysteresis spec (a straight line with ``kind: linear``), an
    optional creep stage and rate-dependent lag, and the solver."""

    name: ModelName
    kind: Literal["linear", "pi", "gpi", "preisach"]
    creep: bool = Field(False, description="add a logarithmic creep stage (0.1 s to 100 s)")
    rate_dependence: bool = Field(False, description="add a first-order lag after hysteresis")
    solver: Optional[Literal[SOLVERS + LINEAR_SOLVERS]] = Field(  # type: ignore[valid-type]
        None,
        description="default: jaxafm.nnls for preisach alone, BFGS for preisach with creep or a lag, "
        "else LM; jaxafm.nnls fits pi and preisach alone",
    )
    max_steps: int = Field(2000, ge=1, le=100_000)

    @model_validator(mode="after")
    def _linear_solver_fits_weights(self):
        extras = [e for e in ("creep", "rate_dependence") if getattr(self, e)]
        if self.solver in LINEAR_SOLVERS and (self.kind not in ("pi", "preisach") or extras):
            raise ValueError(
                f"model {self.name!r}: solver {self.solver!r} fits the weights of kind pi or preisach "
                f"alone (outputs linear in them), not kind {self.kind!r}"
                + "".join(f" with {e}: true" for e in extras)
                + "; use a gradient solver"
            )
        return self

    @property
    def solver_name(self) -> str:
        """The configured solver, or the default for the model's kind."""
        if self.solver:
            return self.solver
        if self.kind == "preisach":
            return "optimistix.bfgs" if self.creep or self.rate_dependence else LINEAR_SOLVERS[0]
        return "optimistix.levenberg_marquardt"


class ActuatorFitConfig(Strict):
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
        if (self.data is None) == (self.simulate is None):
            raise ValueError("give exactly one of 'data' (a measured record) and 'simulate'")
        names = [m.name for m in self.models]
        if len(set(names)) != len(names):
            raise ValueError(f"model names must be unique, got {names}")
        return self
