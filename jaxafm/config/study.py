"""``jaxafm study``: Monte-Carlo positioning studies over drawn scanners, particles and pushes."""

from __future__ import annotations

from typing import Literal, Optional

import numpy as np
from pydantic import Field, model_validator

from .common import Strict
from .names import TRUTH_CLASSES, check_effect_names
from .run import Positioning, check_layout


class Distribution(Strict):
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
        """``n`` values drawn with ``rng``."""
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
    "rate_dependence": {"tau_s": ("rate_tau", (1e-5, 0.1), 2e-3)},
    "vibration": {
        "frequency_hz": ("vibration_hz", (1.0, 1e5), 150.0),
        "damping": ("vibration_damping", (1e-3, 0.99), 0.05),
    },
}

#: the effect whose parameters only scanners of a truth class hold (the others hold none of it)
CLASS_EFFECTS = {"rate_dependence": "rate_dependent", "vibration": "resonant"}


class Learning(Strict):
    """Step C's finds teach the A+B moves after them on the same scanner: a smooth offset field
    (a quadratic over the workspace, Bayesian ridge regression) learnt from every verified find
    so far, the trials run in rounds in their order (docs/study.md). With ``pushes``, the first
    pushes' checks teach the pushes after them too (the same prior and scatter); with
    ``min_push_odds``, a push whose odds from the scanner's earlier rounds are below it is
    withheld."""

    round_trials: int = Field(
        8, ge=1, le=100_000, description="trials per round; each learns from the rounds before"
    )
    prior_nm: float = Field(
        100.0, gt=0, description="prior standard deviation of each coefficient of the field, nm"
    )
    noise_nm: float = Field(5.0, gt=0, description="scatter of one find about the field, nm")
    pushes: bool = Field(
        False,
        description="the checked first pushes teach the pushes after them (needs the push and a check)",
    )
    min_push_odds: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="withhold a push whose predicted success (from the scanner's earlier pushes) is below "
        "this probability; 0: every push is made (needs the push)",
    )


class StudyConfig(Positioning):
    """A Monte-Carlo positioning study: ``trials`` independent trials, each a particle of radius
    drawn from ``particle_radius_nm`` at a random place in the landmark grid, on a scanner drawn
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
    truth_classes: list[Literal[TRUTH_CLASSES]] = Field(
        ["generalised_pi"],
        min_length=1,
        description="the true scanners' model classes, given in turn to scanner 0, 1, 2, ... (default_scanner's "
        "truth_class): the fitted model's own (generalised_pi) or one it cannot describe",
    )
    particle_radius_nm: Distribution = Distribution(uniform=[5.0, 50.0])
    learning: Optional[Learning] = Field(
        None, description="step C's finds teach the following A+B moves (needs A+B+C); null: they do not"
    )
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
            if effect in CLASS_EFFECTS and CLASS_EFFECTS[effect] not in self.truth_classes:
                raise ValueError(
                    f"scanner.{effect}: only scanners of the truth class {CLASS_EFFECTS[effect]!r} hold it; "
                    f"add it to truth_classes ({', '.join(self.truth_classes)}) or remove scanner.{effect}"
                )
        if len(set(self.truth_classes)) < len(self.truth_classes):
            raise ValueError(f"truth_classes: {self.truth_classes} names a class twice; name each once")
        _inside("particle_radius_nm", self.particle_radius_nm, 1.0, 200.0)
        check_layout(self)
        lm = self.landmarks
        cell = lm.step_px * self.workspace.size_nm / self.workspace.pixels
        if cell < 8 * self.particle_radius_nm.support[1]:
            raise ValueError(
                f"particle_radius_nm: radii up to {self.particle_radius_nm.support[1]:g} nm need "
                f"landmark cells of at least 8 R; they are {cell:.0f} nm: use a larger landmark step"
            )
        if self.learning is not None and "A+B+C" not in self.stages:
            raise ValueError(
                "learning: step C's finds teach the A+B moves; add 'A+B+C' to stages or remove learning"
            )
        if self.learning is not None and self.chunk % self.learning.round_trials:
            raise ValueError(
                f"chunk: {self.chunk} is not a whole number of learning.round_trials "
                f"({self.learning.round_trials}); a round may not span two chunks (the results would "
                "depend on the chunk size)"
            )
        if (
            self.learning is not None
            and self.learning.pushes
            and ("push" not in self.stages or self.push.corrections < 1)
        ):
            raise ValueError(
                "learning.pushes: the pushes learn from the checks after them; add 'push' to stages "
                "and set push.corrections >= 1, or set learning.pushes: false"
            )
        if self.learning is not None and self.learning.min_push_odds > 0 and "push" not in self.stages:
            raise ValueError(
                f"learning.min_push_odds: {self.learning.min_push_odds:g} gates the pushes; add 'push' to "
                "stages or set learning.min_push_odds: 0"
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
