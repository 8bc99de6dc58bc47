"""``jaxafm predict`` and ``jaxafm compensate``: a saved model applied to a new record, and
inverted into the drive that makes it follow a wanted trajectory."""

from __future__ import annotations

from typing import Annotated, Literal, Optional

from pydantic import Field, model_validator

from .common import RecordData, Strict


class PredictConfig(Strict):
    """Apply a saved model (``model_*.json``) to a record's input; score it where the record
    has measured output."""

    model: str = Field(description="model file, relative to the config file")
    data: RecordData
    history_v: Optional[list[float]] = Field(
        None, min_length=1, description="inputs before t=0 (V); default: the model file's history_v"
    )
    evaluate_from: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="score the record from this fraction of its samples on (a fit's train_fraction: "
        "its held-out part); the model always runs over the whole record",
    )
    estimate_offset: bool = Field(
        False,
        description="re-estimate one constant sensor offset (nm) per axis on the samples before "
        "evaluate_from (the whole record if 0), and report it",
    )
    level: Optional[float] = Field(
        None,
        gt=0,
        lt=1,
        description="the probability of the prediction band (0.9: 90 %); default 0.9 where the model "
        "file holds an uncertainty (models from `jaxafm fit`), none otherwise; set for a model "
        "without one, an error",
    )
    output: str = "runs/predict"


class Triangle(Strict):
    """A triangle wave about ``centre_nm``: one period per amplitude in ``amplitudes_nm`` (e.g.
    decreasing, for minor loops), sampled at ``sample_rate_hz``."""

    amplitudes_nm: list[Annotated[float, Field(gt=0)]] = Field(min_length=1)
    centre_nm: Optional[float] = Field(
        None, description="default: the middle of the model's fitted output range"
    )
    period_s: float = Field(1.0, gt=0)
    sample_rate_hz: float = Field(200.0, gt=0, le=1e6)


class RasterTrajectory(Strict):
    """A raster scan of a two-axis scanner (``jaxafm.instrument.afm.Raster``): ``lines`` lines of
    ``pixels`` samples, each a trace then a retrace along x, over ``size_nm`` (width, height)."""

    size_nm: list[Annotated[float, Field(gt=0)]] = Field(min_length=2, max_length=2)
    pixels: int = Field(128, ge=2, le=4096)
    lines: int = Field(128, ge=1, le=4096)
    line_rate_hz: float = Field(1.0, gt=0, le=1000)
    centre_nm: Optional[list[float]] = Field(
        None, min_length=2, max_length=2, description="default: the middle of the fitted output range"
    )
    overscan: float = Field(0.05, ge=0, le=0.5, description="fraction of the width added at each end")


class Trajectory(Strict):
    """The wanted output: a CSV file with a header ``t_s,x_nm`` (two axes: ``t_s,x_nm,y_nm``;
    other length units as ``x_um``), a ``triangle`` (on every axis) or a ``raster`` (two axes)."""

    path: Optional[str] = Field(None, description="CSV file, relative to the config file")
    triangle: Optional[Triangle] = None
    raster: Optional[RasterTrajectory] = None

    @model_validator(mode="after")
    def _one_source(self):
        if sum(v is not None for v in (self.path, self.triangle, self.raster)) != 1:
            raise ValueError("give exactly one of 'path' (a CSV file), 'triangle' and 'raster'")
        return self


class CompensateConfig(Strict):
    """The drive voltages that make a saved model (one axis or a two-axis scanner) follow a
    wanted trajectory, after the initialisation cycle ``{u2, u1}`` over its fitted input range."""

    model: str = Field(description="model file, relative to the config file")
    trajectory: Trajectory
    method: Literal["auto", "analytic", "numerical"] = Field(
        "auto", description="auto: the analytic inverse where the model has one, else numerical"
    )
    cycle_s: float = Field(
        2.0, gt=0, description="duration of the initialisation cycle prepended to the drive"
    )
    check_models: list[str] = Field(
        [],
        description="other model files (e.g. a richer fit of the same data) to run the drive through: "
        "their tracking error tells what the compensation is worth beyond the model it inverts",
    )
    output: str = "runs/compensate"
