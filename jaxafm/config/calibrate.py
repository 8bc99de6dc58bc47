"""``jaxafm calibrate`` (step A): identify the scanner from a grating's trace/retrace images,
invert it and compensate. The grating, the simulated calibration scan, the model and the solver
are also step A of ``jaxafm run`` and ``jaxafm study``."""

from __future__ import annotations

import math
import numbers
from typing import Annotated, ClassVar, Literal, Optional, Union

from pydantic import Field, field_validator, model_validator

from .common import (
    HysteresisKind,
    HysteresisSpec,
    ImageFile,
    ImagePair,
    Length,
    ModelName,
    Operators,
    Seed,
    Solver,
    Strict,
)
from .names import KNOWABLE, MODEL_EFFECTS, check_effect_names


class CalibrationLattice(Strict):
    """The calibration lattice (the config's ``grating``): a square lattice of pillars (or pits)
    of known pitch, and its angle on the stage."""

    pitch_nm: float = Field(1000.0, gt=0, description="lattice pitch, nm (both axes)")
    pits: bool = Field(False, description="pits instead of pillars")
    rotation_deg: Union[Literal["fit"], Annotated[float, Field(ge=-45, le=45)]] = Field(
        "fit",
        description="the lattice's angle on the stage, degrees anticlockwise from the scanner's x "
        "axis, if known (e.g. 0 for a grating mounted square); fit: identified with the scanner, "
        "the x axis then being the direction the x piezo moves the tip (docs/step_a.md)",
    )
    off_line_chords_sd: Optional[float] = Field(
        None,
        gt=0,
        description="leave out every chord whose midpoint lies more than this many robust sds off "
        "its feature's line of midpoints (5: square features turned off the scan lines, whose "
        "chords by their corners meet a third side; docs/step_a.md); none: keep every chord",
    )

    @property
    def rotation_rad(self) -> Optional[float]:
        """The known angle (rad), or ``None`` to fit it."""
        return None if self.rotation_deg == "fit" else math.radians(self.rotation_deg)


LineRate = Annotated[float, Field(gt=0, le=50.0)]
#: the most scans one calibration may hold
MAX_SCANS = 8


class SimulatedCalibration(Strict):
    """Trace/retrace image pairs of the grating from the built-in simulated AFM
    (``default_afm()``), each taken after the initialisation cycle ``+-u_max``: one per scan angle
    and line rate."""

    pixels: int = Field(128, ge=32, le=1024, description="pixels per line = lines")
    size_nm: float = Field(8000.0, gt=0, le=9000.0, description="scan width = height, nm")
    line_rate_hz: Union[LineRate, list[LineRate]] = Field(
        1.0,
        description="lines per second, or several (a speed series: one image pair at each rate and "
        "angle, which separates the scanner's rate dependence from its loop)",
    )
    angles_deg: list[Annotated[float, Field(ge=-360, le=360)]] = Field(
        [0.0],
        min_length=1,
        max_length=4,
        description="scan angles, degrees: one image pair each, each after the initialisation "
        "cycle; [0, 90] makes both axes reverse in the data",
    )
    lattice_rotation_deg: float = Field(
        0.0, ge=-45, le=45, description="the simulated lattice's true angle on the stage, degrees"
    )
    withheld: list[str] = Field([], description="effects the simulated instrument does not have")
    seed: Seed = 0

    @model_validator(mode="after")
    def _known_effects(self):
        check_effect_names(self.withheld, "withheld")
        if len(set(self.angles_deg)) != len(self.angles_deg):
            raise ValueError(f"angles_deg: each scan angle once, got {self.angles_deg}")
        if len(set(self.line_rates_hz)) != len(self.line_rates_hz):
            raise ValueError(f"line_rate_hz: each line rate once, got {self.line_rate_hz}")
        if len(self.line_rates_hz) * len(self.angles_deg) > MAX_SCANS:
            raise ValueError(
                f"angles_deg x line_rate_hz: {len(self.angles_deg)} x {len(self.line_rates_hz)} scans, at most "
                f"{MAX_SCANS}"
            )
        return self

    @property
    def line_rates_hz(self) -> list:
        """The line rates (Hz), one or several."""
        return self.line_rate_hz if isinstance(self.line_rate_hz, list) else [self.line_rate_hz]

    @property
    def scans(self) -> list:
        """``(angle_deg, line_rate_hz)`` of each simulated scan, in the order taken: each angle at
        every rate."""
        return [(a, r) for a in self.angles_deg for r in self.line_rates_hz]


class CalibrationPair(ImagePair):
    """One measured trace/retrace pair of the calibration lattice and how it was scanned; a
    setting left out is the files' header's, else :attr:`SCAN_DEFAULTS`'."""

    SCAN_DEFAULTS: ClassVar[dict] = {"angle_deg": 0.0, "overscan": 0.1, "lines": "up"}

    angle_deg: Optional[float] = Field(
        None, ge=-360, le=360, description="scan angle, degrees anticlockwise; default: the header's, else 0"
    )
    overscan: Optional[float] = Field(
        None,
        ge=0,
        le=1,
        description="over-scan beyond the image at each end of a line, fraction of the width; "
        "default: the header's, else 0.1",
    )
    lines: Optional[Literal["up", "down"]] = Field(
        None,
        description="the order the lines were scanned: up (the image's row 0 first) or down; "
        "default: the header's, else up",
    )


class CalibrationImages(Strict):
    """Measured trace/retrace pairs of one lattice -- one pair as ``trace``, ``retrace``,
    ``line_rate_hz`` (and its ``angle_deg``, ``overscan``, ``lines``), or several as ``scans`` --
    and how the instrument drove them; each scan is centred on the scanner's zero. What the
    files cannot say -- the nominal sensitivity and the drive range -- has defaults
    (``docs/step_a.md``): ``u_max_v`` 10 V, and a sensitivity of ``scan_range_nm / (2 u_max_v)``
    or, without a stated range, such that the scans with their over-scan just span the drive."""

    trace: Optional[ImageFile] = Field(None, description="the trace image of a single scan")
    retrace: Optional[ImageFile] = Field(None, description="the retrace image of a single scan")
    line_rate_hz: Optional[float] = Field(
        None, gt=0, description="a single scan's lines per second; default: the files' header's"
    )
    angle_deg: Optional[float] = Field(
        None, ge=-360, le=360, description="a single scan's angle, degrees; default: the header's, else 0"
    )
    overscan: Optional[float] = Field(
        None,
        ge=0,
        le=1,
        description="a single scan's over-scan, fraction of the width; default: the header's, else 0.1",
    )
    lines: Optional[Literal["up", "down"]] = Field(
        None, description="a single scan's line order; default: the header's, else up"
    )
    scans: Optional[list[CalibrationPair]] = Field(
        None,
        min_length=1,
        max_length=8,
        description="several scans: at other angles (0 and 90 degrees make both axes reverse) and "
        "other line rates (a speed series), each pair of angle and rate once",
    )
    sensitivity_nm_per_v: Optional[list[Annotated[float, Field(gt=0)]]] = Field(
        None, min_length=2, max_length=2, description="nominal x, y calibration; default from the range"
    )
    scan_range_nm: Optional[Annotated[list[Length], Field(min_length=1, max_length=2)]] = Field(
        None, description="the instrument's stated scan range, nm (x, y or one number)"
    )
    u_max_v: float = Field(10.0, gt=0)
    history_v: Optional[list[Annotated[list[float], Field(min_length=2, max_length=2)]]] = Field(
        None,
        description="drive turning points (x, y) V before each scan, e.g. the cycle [[-10, -10], [10, 10]]",
    )

    @field_validator("scan_range_nm", mode="before")
    @classmethod
    def _one_number(cls, value):
        return value if value is None or isinstance(value, (list, tuple)) else [value]

    @model_validator(mode="after")
    def _one_form(self):
        single = {k: getattr(self, k) for k in SINGLE_SCAN_KEYS}
        given = [k for k, v in single.items() if v is not None]
        if self.scans is not None:
            if given:
                raise ValueError(
                    f"give one scan as trace/retrace/line_rate_hz or several as scans, not both ({given[0]})"
                )
            known = [(s.angle_deg, s.given_line_rate_hz) for s in self.scans]
            given = [i for i, k in enumerate(known) if None not in k]  # the files may say the rest
            each_scan_once([known[i] for i in given], [f"scans.{i}" for i in given])
        elif self.trace is None or self.retrace is None:
            missing = [k for k in ("trace", "retrace") if single[k] is None]
            raise ValueError(f"missing {', '.join(missing)}: a scan needs trace and retrace (or give scans)")
        else:
            CalibrationPair(**{k: v for k, v in single.items() if v is not None})  # the pair's own checks
        return self

    @property
    def pairs(self) -> list:
        """``(key, CalibrationPair)`` per scan, the key as the config wrote it (``data`` or
        ``data.scans.N``)."""
        if self.scans is not None:
            return [(f"data.scans.{i}", s) for i, s in enumerate(self.scans)]
        single = {k: getattr(self, k) for k in SINGLE_SCAN_KEYS}
        return [("data", CalibrationPair(**{k: v for k, v in single.items() if v is not None}))]


#: the keys of ``data`` that give a single scan (``CalibrationPair``'s)
SINGLE_SCAN_KEYS = ("trace", "retrace", "line_rate_hz", "angle_deg", "overscan", "lines")


def each_scan_once(seen: list, keys: list) -> None:
    """Refuse a calibration's scans whose ``(angle_deg, line_rate_hz)`` ``seen`` repeat; ``keys``
    name each scan as the config wrote it (``scans.0``).

    Raises:
        ValueError: naming the angle, the rate, how often and the scans.
    """
    twice = sorted({k for k in seen if seen.count(k) > 1})
    if twice:
        a, r = twice[0]
        named = " and ".join(k for k, s in zip(keys, seen) if s == twice[0])
        raise ValueError(
            f"scans: the scan at angle_deg {a:g} and line_rate_hz {r:g} is given "
            f"{seen.count(twice[0])} times ({named}): each pair of angle and line rate once (a speed "
            "series scans one angle at several rates)"
        )


#: the effects step A fits when a model names none (``asymmetry`` for a generalised PI only)
CALIBRATION_EFFECTS = ("asymmetry", "creep", "coupling", "bow", "feedback_lag")


class CalibrationModel(HysteresisSpec):
    """One scanner model to identify (an ablation lists several): the shared hysteresis spec
    and the effects besides hysteresis to fit from the images. ``asymmetry`` is the generalised
    PI's dead zones: a ``pi`` or ``preisach`` model leaves it out of its default effects and
    refuses it when named (a Preisach plane's branches take their own shapes without it)."""

    name: ModelName
    kind: HysteresisKind = "gpi"
    operators: Operators = 16
    effects: list[str] = Field(list(CALIBRATION_EFFECTS), description="effects besides hysteresis")
    creep_onset: bool = Field(
        False,
        description="creep as d0 (1 + gamma log10(1 + t / t0)) with its onset t0 (s) fitted too; "
        "otherwise a log law of fixed shape from 0.1 s",
    )
    known: dict[str, Annotated[list[float], Field(min_length=2, max_length=2)]] = Field(
        {},
        description="what you know of the scanner beforehand, each quantity as [value, sd] in its "
        "units (y_gain_nm_per_v: [1940, 40]): step A fits it under a Gaussian prior of that mean and sd",
    )

    @model_validator(mode="before")
    @classmethod
    def _asymmetry_with_gpi(cls, given):
        if not isinstance(given, dict) or given.get("kind", "gpi") == "gpi":
            return given
        if given.get("effects") is None:
            return given | {"effects": [e for e in CALIBRATION_EFFECTS if e != "asymmetry"]}
        if "asymmetry" in given["effects"]:
            raise ValueError(
                f"effect 'asymmetry' is the dead zones of a generalised PI (kind: gpi), and kind "
                f"{given['kind']!r} has none; leave it out of effects, or use kind: gpi"
            )
        return given

    @model_validator(mode="after")
    def _knowable(self):
        for key, (value, sd) in self.known.items():
            if key not in KNOWABLE:
                raise ValueError(
                    f"known: {key!r} is not a quantity step A fits; one of {', '.join(KNOWABLE)}"
                )
            if not (math.isfinite(value) and math.isfinite(sd) and sd > 0):
                raise ValueError(
                    f"known: {key}: [{value}, {sd}] needs a finite value and a finite sd > 0 (in the key's units)"
                )
            needs = KNOWABLE[key]
            if needs is not None and needs not in self.effects:
                raise ValueError(
                    f"known: {key} needs the effect {needs!r} among effects ({', '.join(self.effects)})"
                )
        return self

    @field_validator("effects")
    @classmethod
    def _fittable(cls, effects):
        for e in effects:
            if e not in MODEL_EFFECTS:
                raise ValueError(
                    f"effect {e!r} cannot be fitted from grating images; choose from {', '.join(MODEL_EFFECTS)}"
                )
        return effects


def check_known(model: CalibrationModel, grating: CalibrationLattice) -> None:
    """Refuse a stated ``coupling_yx`` where the lattice's angle is fitted: step A then holds the
    coupling of y from x at 0 (the lattice's angle and it move the images alike), so there is
    nothing to state it of."""
    if "coupling_yx" in model.known and grating.rotation_deg == "fit":
        raise ValueError(
            f"models {model.name}: known: coupling_yx cannot be stated while grating.rotation_deg is 'fit': "
            "step A then holds the coupling of y from x at 0 and fits the lattice's angle; give the "
            "lattice's angle (grating.rotation_deg) or leave coupling_yx out"
        )


StepLimit = Annotated[int, Field(ge=1, le=10_000)]

#: step A's image stages on the simulated AFM unless ``solver.blur_px`` says otherwise; on measured
#: images none (on a 3 x 3 pit lattice of the independent generator at four line rates, 256 px,
#: both took longer than the chord stages and both were rejected: docs/step_a.md)
SIMULATED_BLURS_PX = (2.0, 1.0)


class CalibrationSolver(Strict):
    """The solver of step A's staged image fit."""

    name: Solver = "jaxafm.geodesic_levenberg_marquardt"  # type: ignore[valid-type]
    max_steps: Union[StepLimit, list[StepLimit]] = Field(
        100,
        description="per stage: one number for every stage, or a list, one per stage in order (the "
        "chord stages, then each blur)",
    )
    blur_px: Optional[list[Annotated[float, Field(ge=0, le=64)]]] = Field(
        None,
        description="image stages, coarse to fine: Gaussian sigma (px), 0 for none; default "
        "[2, 1] on the simulated AFM, none on measured images (the chords alone: a real image's "
        "background and feature shapes are the sample's, docs/step_a.md)",
    )
    coarsen: Union[Annotated[int, Field(ge=1, le=64)], Literal["auto"]] = Field(
        1,
        description="the chord stages fit the scans with this many pixels of a line "
        "averaged into one, a power of two (a cheaper start); the image stages fit them whole; 1: "
        "none; auto: the largest leaving 8 px per pitch",
    )
    hold_out: bool = Field(
        True,
        description="hold out half the lattice sites (a checkerboard) to validate the fit and to "
        "refuse an image stage that worsens them; false: the training features judge the image stages",
    )
    select: bool = Field(
        True,
        description="climb a ladder of models from straight axes towards the configured model and "
        "keep the one the data support (docs/step_a.md); false: fit the configured model as it is",
    )
    wide_loop: bool = Field(
        False,
        description="the scanner's loop may hold the retrace more than a pitch behind the trace at the "
        "line reversal (loops over about 18 % of the range at 10 % overscan): every scan's retrace is "
        "also tried indexed a pitch further back, kept where it fits more than twice as well as the "
        "first matching once both fits have gone on to converge, up to four step limits (docs/step_a.md)",
    )
    chord_lengths: bool = Field(
        False,
        description="fit each chord's length as well as its midpoint: every feature has one shape, "
        "so the path may not run fast across one feature and slow across the next (on a 3 x 3 pit "
        "lattice of the independent generator the tip path 3.7 times closer to the truth; on the "
        "shipped Nanosurf lattices the held-out features 6-13 nm further off, docs/step_a.md)",
    )
    path_tolerance_nm: Optional[Annotated[float, Field(gt=0)]] = Field(
        None,
        description="how open (nm, sd rms over the images) the fitted tip path may be: the fit is "
        "refused when the parameters the scans do not fix move the path by more than this and more "
        "than a held-out feature's predicted error; default a tenth of the scans' finest pixel "
        "(docs/step_a.md)",
    )

    def image_blurs(self, measured: bool) -> tuple:
        """The image stages' blurs (px): ``blur_px`` as given, else :data:`SIMULATED_BLURS_PX` on
        the simulated AFM and none on ``measured`` images."""
        if self.blur_px is not None:
            return tuple(self.blur_px)
        return () if measured else SIMULATED_BLURS_PX


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


def coarsen_fits(factor, pixels: list, per_pitch: float) -> bool:
    """Whether ``factor`` can top step A's pyramid: a power of two (the stages halve it) that
    divides every scan's ``pixels`` per line and leaves 2 of the ``per_pitch`` pixels per pitch
    along a line (fewer cannot show a lattice)."""
    whole = isinstance(factor, numbers.Integral) and not isinstance(factor, bool)
    power = whole and factor >= 1 and not factor & (factor - 1)
    return power and not any(p % factor for p in pixels) and per_pitch / factor >= 2


def check_stage_steps(solver: CalibrationSolver, scans: int, measured: bool = False) -> None:
    """Refuse a list ``solver.max_steps`` that does not give one step limit per stage of step A
    on ``scans`` scans (``measured`` images or simulated ones): one feature stage (two for
    several scans), then one per blur."""
    if isinstance(solver.max_steps, int):
        return
    stages = ["chords"] + (["chords, all scans"] if scans > 1 else [])
    stages += [f"images, blur {b:g} px" for b in solver.image_blurs(measured)]
    if len(solver.max_steps) != len(stages):
        raise ValueError(
            f"solver.max_steps: {solver.max_steps} gives {len(solver.max_steps)} step limits, but step A "
            f"has {len(stages)} stages here ({'; '.join(stages)}): give one number or one per stage"
        )


def check_coarsen(
    solver: CalibrationSolver, simulate: SimulatedCalibration, grating: CalibrationLattice
) -> None:
    """Refuse a ``solver.coarsen`` that does not fit the simulated scan (:func:`coarsen_fits`)
    before anything is simulated."""
    f = solver.coarsen
    if f == "auto":
        return
    per_pitch = grating.pitch_nm * simulate.pixels / simulate.size_nm
    if not coarsen_fits(f, [simulate.pixels], per_pitch):
        raise ValueError(
            f"solver.coarsen: {f} must be a power of two that divides simulate.pixels ({simulate.pixels}) "
            f"and leaves 2 px per pitch along a line ({per_pitch:.3g} px per pitch at full resolution)"
        )


class CalibrateConfig(Strict):
    """Step A: identify the scanner from one grating image pair, invert it, compensate."""

    data: Optional[CalibrationImages] = None
    simulate: Optional[SimulatedCalibration] = None
    grating: CalibrationLattice = CalibrationLattice()
    models: list[CalibrationModel] = Field([CalibrationModel(name="gpi")], min_length=1)
    solver: CalibrationSolver = CalibrationSolver()
    compensate: Optional[Compensation] = Compensation()
    output: str = "runs/calibrate"

    @model_validator(mode="after")
    def _one_source(self):
        if (self.data is None) == (self.simulate is None):
            raise ValueError("give exactly one of 'data' (measured trace/retrace images) and 'simulate'")
        if self.data is not None and "pitch_nm" not in self.grating.model_fields_set:
            raise ValueError(
                "grating.pitch_nm: measured images need their lattice's pitch in nm (from its datasheet; "
                "the default, 1000 nm, is the simulated lattice's); give it, e.g. grating: {pitch_nm: 10000}"
            )
        names = [m.name for m in self.models]
        if len(set(names)) != len(names):
            raise ValueError(f"model names must be unique, got {names}")
        for model in self.models:
            check_known(model, self.grating)
        if self.simulate is not None:
            check_coarsen(self.solver, self.simulate, self.grating)
        check_stage_steps(
            self.solver,
            len(self.simulate.angles_deg if self.data is None else self.data.pairs),
            measured=self.data is not None,
        )
        return self
