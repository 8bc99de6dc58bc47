"""``jaxafm diagnose``: the sim-to-real gap of a record, an image or a set of scans."""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar, Literal, Optional, Union

from pydantic import Field, model_validator

from .common import HysteresisKind, HysteresisSpec, ImageFile, ImagePair, RecordData, Seed, Strict
from .names import EFFECTS, check_effect_names


class DiagnoseNominal(HysteresisSpec):
    """The nominal model ``jaxafm diagnose`` starts from: the shared hysteresis spec and its
    other effects."""

    kind: HysteresisKind = Field("pi", description="pi: the classical symmetric PI model")
    effects: list[str] = Field(["hysteresis"], description="effects the nominal model has")

    @model_validator(mode="after")
    def _known_effects(self):
        check_effect_names(self.effects, "nominal.effects")
        if "hysteresis" not in self.effects:
            raise ValueError(f"nominal.effects must include 'hysteresis', got {self.effects}")
        return self


class DiagnoseSimulation(Strict):
    """A two-axis record of the simulated PI scanner with one effect the nominal model lacks
    (``jaxafm.diagnose.withheld.simulate_record``; ``magnitude`` in its ``RECORD_UNITS``)."""

    withheld: Optional[str] = Field(None, description="the effect switched on; none: a control")
    magnitude: float = 0.0
    duration_s: float = Field(20.0, gt=0)
    sample_rate_hz: float = Field(100.0, gt=0)
    noise_nm: float = Field(2.0, ge=0)
    seed: Seed = 0

    @model_validator(mode="after")
    def _known_effect(self):
        if self.withheld is not None:
            check_effect_names([self.withheld], "simulate.withheld")
        if self.withheld in ("asymmetry", "rate_dependence", "creep") and self.magnitude < 0:
            raise ValueError(
                f"magnitude: {self.withheld} has no sign (a dead-zone scale, a time constant, a creep "
                f"rate), so it must be >= 0, got {self.magnitude}"
            )
        return self


SampleKind = Literal["lines", "lattice"]
_PITCH_ALLOWED = "a length > 0 nm, or [x, y] nm for a lattice whose pitches differ"


def _pitch(value, kind: str, where: str):
    """``value`` as a pitch (nm, one number or [x, y]), or a ValueError naming ``where``, the
    value and what is allowed; ``None`` stays ``None`` for a 1-D image (its pitch is fitted)."""
    bad = lambda why: ValueError(f"{where}: {why}, got {value!r}; allowed: {_PITCH_ALLOWED}")
    if value is None:
        return None
    items = list(value) if isinstance(value, (list, tuple)) else [value]
    if not 1 <= len(items) <= 2 or (kind == "lines" and len(items) != 1):
        raise bad(f"a {'1-D grating has one pitch' if kind == 'lines' else 'lattice has one or two pitches'}")
    out = []
    for v in items:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise bad("the pitch must be a number of nm")
        if not (math.isfinite(v) and v > 0):
            raise bad("the pitch must be finite and > 0 nm")
        out.append(float(v))
    return out


class DiagnoseImage(ImageFile):
    """One image of a 1-D grating (``kind: lines``, lines along the slow axis) or of a 2-D
    lattice of pits or pillars (``kind: lattice``, whose ``pitch_nm`` is required), an
    ``ImageFile``: any format ``jaxafm.instrument.images.read_image`` reads; rows are taken in
    scan order (row 0 first)."""

    kind: SampleKind = Field("lines", description="lines: a 1-D grating; lattice: pits or pillars")
    pitch_nm: Any = Field(
        None,
        description="nm: the pitch along x (or [x, y]); required for a lattice, fitted for lines",
    )

    @model_validator(mode="after")
    def _lattice_pitch(self):
        object.__setattr__(self, "pitch_nm", _pitch(self.pitch_nm, self.kind, "image.pitch_nm"))
        if self.kind == "lattice" and self.pitch_nm is None:
            raise ValueError(
                f"image.pitch_nm: a lattice needs its pitch (from its datasheet) to tell its rows' "
                f"features apart, got None; allowed: {_PITCH_ALLOWED}"
            )
        return self


class ScanSample(Strict):
    """The calibration sample a scan set images (its datasheet) and the tip's cone: a 1-D
    grating (``kind: lines``) or a 2-D lattice of pits or pillars (``kind: lattice``); the
    pitch along the fast axis x (``pitch_nm``: one number, or [x, y] for a lattice)."""

    kind: SampleKind = Field("lines", description="lines: a 1-D grating; lattice: pits or pillars")
    pitch_nm: Any = Field(None, description=f"nm: {_PITCH_ALLOWED}")
    edge_width_nm: float = Field(gt=0, description="width of an edge's linear ramp (nm)")
    tip_half_angle_deg: float = Field(20.0, gt=0, lt=90)

    @model_validator(mode="after")
    def _known_pitch(self):
        pitch = _pitch(self.pitch_nm, self.kind, "scans.grating.pitch_nm")
        if pitch is None:
            raise ValueError(
                f"scans.grating.pitch_nm: a {'lattice' if self.kind == 'lattice' else '1-D grating'} "
                f"needs its pitch (from its datasheet), got None; allowed: {_PITCH_ALLOWED}"
            )
        object.__setattr__(self, "pitch_nm", pitch[0] if len(pitch) == 1 else pitch)
        return self

    @property
    def pitch_x_nm(self) -> float:
        """The pitch along the fast axis x (nm)."""
        return float(self.pitch_nm[0] if isinstance(self.pitch_nm, list) else self.pitch_nm)


class ScanFiles(ImagePair):
    """One trace/retrace pair (``ImageFile``s: any format ``jaxafm.instrument.images.read_image``
    reads), both left to right, row 0 scanned first, and how fast it was scanned."""

    SCAN_DEFAULTS: ClassVar[dict] = {"overscan": 0.0}

    overscan: Optional[float] = Field(
        None,
        ge=0,
        le=1,
        description="fraction of the width scanned beyond each end; default: the header's, else 0",
    )


class ScanSimulation(Strict):
    """Trace/retrace pairs of the simulated AFM (``jaxafm.diagnose.withheld.simulate_scans``)."""

    withheld: Optional[Literal["feedback_lag", "feedback_asymmetry", "tip", "rate_dependence"]] = Field(
        None, description="the effect switched on; none: a control"
    )
    magnitude: float = Field(0.0, ge=0, description="units: jaxafm.diagnose.withheld.SCAN_UNITS")
    sample: SampleKind = Field(
        "lines", description="lines: the 1-D grating; lattice: the 2-D pit lattice (withheld.SIM_LATTICE)"
    )
    line_rates_hz: list[float] = Field([1.0, 4.0], min_length=2)
    lines: int = Field(24, ge=8, le=4096)
    pixels: int = Field(512, ge=64, le=8192)
    noise_nm: float = Field(0.5, ge=0)
    seed: Seed = 0

    @model_validator(mode="after")
    def _valid(self):
        if min(self.line_rates_hz) <= 0 or len(set(self.line_rates_hz)) < 2:
            raise ValueError(
                f"line_rates_hz needs two or more different rates > 0 Hz, got {self.line_rates_hz}"
            )
        if self.withheld is not None and not self.magnitude > 0:
            raise ValueError(f"magnitude must be > 0 for withheld {self.withheld!r}, got {self.magnitude}")
        return self


class DiagnoseScans(Strict):
    """Trace/retrace images of a 1-D grating or a 2-D lattice at two or more scan speeds (``jaxafm.diagnose``):
    ``pairs`` from files, or ``simulate``; ``grating`` is required with files."""

    grating: Optional[ScanSample] = None
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


class DiagnoseConfig(Strict):
    """Sim-to-real gap diagnosis: fit the nominal model, then nominal + each candidate effect on the
    training part; compare the gaps on the held-out part (``jaxafm.diagnose``)."""

    data: Optional[RecordData] = None
    simulate: Optional[DiagnoseSimulation] = None
    image: Optional[DiagnoseImage] = None
    scans: Optional[DiagnoseScans] = None
    nominal: DiagnoseNominal = DiagnoseNominal()
    candidates: list[str] = Field(
        [e for e in EFFECTS if e not in ("hysteresis", "noise")],
        min_length=1,
    )
    history_v: Optional[list[float]] = Field(
        None, min_length=1, description="inputs applied before t=0 (V); default: the plays start at u[0]"
    )
    settle_s: Union[Literal["auto"], Annotated[float, Field(ge=0)]] = Field(
        "auto",
        description="s of start-up transient left out of the training loss; auto: 0 where the drive "
        "starts at rest or history_v is given, else until every drive has reversed once "
        "(jaxafm.diagnose.record.auto_settle)",
    )
    train_fraction: float = Field(
        0.6, gt=0, lt=1, description="records: first part of the time; images: of the rows"
    )
    split: Literal["later", "blocked"] = Field(
        "later",
        description="records: hold out the part after train_fraction (later), or every other of "
        "'blocks' equal blocks in time (blocked; train_fraction unused); with later, drift is judged "
        "on 11 alternating blocks, or the nearest count whose training blocks reach every held-out "
        "input (jaxafm.diagnose.record.JUDGED_ON_BLOCKS, JUDGE_BLOCKS)",
    )
    blocks: int = Field(5, ge=3, description="records, split: blocked: an odd number of blocks")
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
        if self.split == "blocked" and self.blocks % 2 == 0:
            raise ValueError(
                f"blocks: {self.blocks}; a blocked split needs an odd number (>= 3) of blocks, so that "
                "training blocks sit at both ends"
            )
        if self.split == "blocked" and self.data is None and self.simulate is None:
            raise ValueError("split: blocked applies to records (data or simulate), not to images or scans")
        return self
