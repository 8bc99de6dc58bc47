"""``jaxafm run``: the paper's full positioning strategy on the simulated AFM (steps A, B, C and
the push). Its step A, workspace, landmarks, local scan and push are also those of
``jaxafm study`` (:class:`Positioning`)."""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, model_validator

from .calibrate import (
    CalibrationLattice,
    CalibrationModel,
    CalibrationSolver,
    Compensation,
    SimulatedCalibration,
    check_coarsen,
    check_known,
    check_stage_steps,
)
from .common import Seed, Strict


class StepA(Strict):
    """Step A of a positioning run: the calibration scan of the simulated AFM and the model
    identified from it, or a scanner fitted earlier (``model_file``, a ``model_*.json``
    written by ``jaxafm calibrate`` from the same calibration scan)."""

    simulate: SimulatedCalibration = SimulatedCalibration()
    grating: CalibrationLattice = CalibrationLattice()
    model: CalibrationModel = CalibrationModel(name="gpi")
    solver: CalibrationSolver = CalibrationSolver()
    model_file: Optional[str] = Field(None, description="relative to the config file; skips identification")

    @model_validator(mode="after")
    def _full_instrument(self):
        if self.simulate.withheld:
            raise ValueError("simulate.withheld: a positioning run needs the full simulated instrument")
        check_coarsen(self.solver, self.simulate, self.grating)
        check_stage_steps(self.solver, len(self.simulate.scans))
        check_known(self.model, self.grating)
        return self


class Workspace(Strict):
    """The area of the task: re-scanned after the landmarks are pressed (step B)."""

    size_nm: float = Field(3000.0, gt=0, description="width = height, nm")
    centre_nm: list[float] = Field([0.0, 0.0], min_length=2, max_length=2)
    pixels: int = Field(256, ge=32, le=1024, description="pixels per line = lines (n of eq. 3)")
    line_rate_hz: float = Field(2.0, gt=0, le=50.0)


class ParticleField(Strict):
    """Nanoparticles in the cells of the landmark grid, ``per_cell`` x ``per_cell`` to a cell,
    each jittered by up to 1/8 of their spacing, radii uniform in ``radius_nm``; none sits on an
    indent."""

    radius_nm: list[float] = Field([5.0, 50.0], min_length=2, max_length=2, description="[min, max], nm")
    per_cell: int = Field(2, ge=1, le=10, description="particles per landmark cell, each way")
    seed: Seed = 1

    @model_validator(mode="after")
    def _sizes(self):
        lo, hi = self.radius_nm
        if not lo > 0:
            raise ValueError(f"radius_nm: a particle radius must be > 0 nm, got {lo}")
        if lo > hi:
            raise ValueError(f"radius_nm: [min, max] needs min <= max, got {self.radius_nm}")
        return self


class LandmarkSpec(Strict):
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
    approach_nm: float = Field(
        0.0,
        ge=0,
        le=5000,
        description="every press and every move to a target passes through target + (a, a) and "
        "target - (a, a) first, so that landmarks and targets are reached alike (0: straight, the paper's)",
    )


class LocalScanSpec(Strict):
    """Step C's local scan."""

    points: int = Field(192, ge=16, le=4096, description="samples per line")
    line_time_s: float = Field(0.5, gt=0, description="one direction of a line")
    margin_nm: float = Field(
        40.0,
        gt=0,
        description="how far beyond its expected place to search (keep a line clear of the neighbouring "
        "particles: its pulse is taken from the first to the last sample above half height)",
    )
    widenings: int = Field(
        0,
        ge=0,
        le=4,
        description="a search that finds nothing starts again with twice the margin, this many times "
        "at most (within max_lines): for a scanner whose model errs beyond the margin, on a sample "
        "whose particles lie further apart than the widest margin",
    )
    max_lines: int = Field(24, ge=3, le=1000)
    height_tolerance: float = Field(
        0.25,
        gt=0,
        description="a centred line's pulse rises within a factor 1 + this of 2R, either way: a check "
        "that the particle is the one sought (the z signal's, which no lateral frame distorts)",
    )
    centre_tolerance: float = Field(
        0.1, gt=0, le=1, description="a line is centred when its pulse's middle lies this close, in R"
    )
    centre_floor_nm: float = Field(
        1.0, ge=0, description="... or this close, nm, if more: the frame's repeatability from line to line"
    )
    condition_y: bool = Field(
        False,
        description="the first line along y through the estimate moves it but never confirms it: its trace "
        "passes where the move before the local scan turned y, and there sets plays moving whose weights "
        "the model may have wrong; a second line along y, below the first one's top, confirms",
    )


class PushSpec(Strict):
    """The pushing task: each particle pushed by a distance uniform in ``distance_nm`` in a
    random direction clear of the other particles (``jaxafm run``); success when it ends within
    ``tolerance_radii`` x R of the goal."""

    distance_nm: list[float] = Field([100.0, 300.0], min_length=2, max_length=2)
    speed_nm_per_s: float = Field(200.0, gt=0)
    lead_in_nm: float = Field(
        0.0,
        ge=0,
        le=5000,
        description="the push's start reached through this far beyond it and this far before it along "
        "the push, so the push goes on the way the tip came, far from its last reversal (0: straight "
        "from the particle, the push starting at the reversal)",
    )
    tolerance_radii: float = Field(1.0, gt=0)
    corrections: int = Field(
        1,
        ge=0,
        le=4,
        description="local scans at the goal after a push, each followed by a corrective push when the "
        "particle lies over a quarter of its radius from the goal (0: the single push)",
    )

    @model_validator(mode="after")
    def _range(self):
        lo, hi = self.distance_nm
        if not 0 < lo <= hi:
            raise ValueError(f"distance_nm: [min, max] needs 0 < min <= max, got {self.distance_nm}")
        return self


class Positioning(Strict):
    """What a positioning run and a study share: step A, the workspace, step B's landmarks,
    step C's local scan, the push and the seed."""

    calibration: StepA = StepA()
    workspace: Workspace = Workspace()
    landmarks: LandmarkSpec = LandmarkSpec()
    local_scan: LocalScanSpec = LocalScanSpec()
    push: PushSpec = PushSpec()
    seed: Seed = 0


class RunConfig(Positioning):
    """The paper's full strategy on the simulated AFM: step A, then an ablation of open loop,
    A, B, A+B and A+B+C over every particle of the workspace, and the push."""

    drift_nm_per_min: list[float] = Field([3.0, -1.8], min_length=2, max_length=2)
    particles: ParticleField = ParticleField()
    stages: list[Literal["open_loop", "A", "B", "A+B"]] = Field(
        ["open_loop", "A", "B", "A+B"], min_length=1, description="A+B goes on to step C and the push"
    )
    output: str = "runs/paper"

    @property
    def particle_spacing_nm(self) -> float:
        """Distance between neighbouring particle sites: a landmark cell over ``per_cell``."""
        ws = self.workspace
        return self.landmarks.step_px * ws.size_nm / ws.pixels / self.particles.per_cell

    @model_validator(mode="after")
    def _fits(self):
        check_layout(self)
        spacing = self.particle_spacing_nm
        if spacing < 4 * self.particles.radius_nm[1]:
            raise ValueError(
                f"particles.per_cell = {self.particles.per_cell} puts particles {spacing:.0f} nm apart, "
                f"too close for radii up to {self.particles.radius_nm[1]:g} nm: at least 4 x the "
                "largest radius is needed; use fewer per cell or a larger landmark step"
            )
        return self


def check_landmark_grid(n: int, start_px: float, step_px: float, image_px: int) -> None:
    """An ``n`` x ``n`` indent grid, first indent at pixel ``start_px`` then every ``step_px``
    pixels, fits an ``image_px``-pixel image: paper eq. 3, ``P + S(N-1) < n``.

    Raises:
        ValueError: naming the rule, the values and what to change.
    """
    if n != int(n) or n < 2:
        raise ValueError(f"the landmark grid needs N >= 2 indents per side, got N = {n}")
    if not start_px >= 0 or not step_px > 0:
        raise ValueError(
            f"landmark grid start P must be >= 0 px and step S > 0 px, got P = {start_px}, S = {step_px}"
        )
    last = start_px + step_px * (n - 1)
    if not last < image_px:
        raise ValueError(
            f"the landmark grid does not fit the image (paper eq. 3, P + S(N-1) < n): "
            f"{start_px:g} + {step_px:g} x {n - 1} = {last:g} px, but the image has "
            f"n = {image_px} px: reduce N, P or S, or scan more pixels"
        )


def check_layout(cfg: Positioning) -> None:
    """The landmark grid fits the workspace image (eq. 3), its pairwise interpolation has the
    landmarks it needs, and the workspace lies where step A's calibration scan covers the
    scanner reliably (``Compensation().scan_fraction`` of half the scan).

    Raises:
        ValueError: naming the key, the values and what to change.
    """
    lm = cfg.landmarks
    try:
        check_landmark_grid(lm.n, lm.start_px, lm.step_px, cfg.workspace.pixels)
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
