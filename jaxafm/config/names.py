"""Names and unit tables that configs are checked against, kept free of JAX.

Each constant lives here once; the JAX modules that use them (``model.scanner``,
``instrument.afm``, ``instrument.images``, ``instrument.records``, ``identify.scan_model``,
``identify.fit``, ``diagnose.core``) import them from here, so
that validating a YAML file never imports JAX. Effect names and units: ``docs/conventions.md``.
"""

from __future__ import annotations

#: Every effect name the project knows (configs, the simulated instrument, diagnosis output).
#: The AFM layer (imaging) owns the last three.
EFFECTS = (
    "hysteresis",
    "asymmetry",
    "rate_dependence",
    "creep",
    "drift",
    "coupling",
    "bow",
    "vibration",
    "noise",
    "feedback_lag",
    "feedback_asymmetry",
    "tip",
)

#: The model classes the simulated scanner's truth can take (``default_scanner``'s
#: ``truth_class``): the fitted model's own, a Preisach plane, a lag after the hysteresis, a
#: mechanical mode after it.
TRUTH_CLASSES = ("generalised_pi", "preisach", "rate_dependent", "resonant")

#: The effects besides hysteresis that step A can fit from a grating's trace/retrace images.
MODEL_EFFECTS = ("asymmetry", "rate_dependence", "creep", "coupling", "bow", "drift", "feedback_lag")

#: the quantities of a scanner step A fits that a user may state as known beforehand (a
#: calibration model's ``known``; :func:`jaxafm.identify.quantities.quantities` defines each),
#: and the effect each needs among the model's effects (``None``: every model has it)
KNOWABLE = {
    "x_gain_nm_per_v": None,
    "y_gain_nm_per_v": None,
    "x_loop_pct_of_travel": None,
    "y_loop_pct_of_travel": None,
    "x_creep_per_decade": "creep",
    "y_creep_per_decade": "creep",
    "x_rate_lag_s": "rate_dependence",
    "y_rate_lag_s": "rate_dependence",
    "coupling_xy": "coupling",
    "coupling_yx": "coupling",
}

#: The solvers a fit can use: ``library.method``.
SOLVERS = (
    "optimistix.levenberg_marquardt",
    "optimistix.gauss_newton",
    "optimistix.dogleg",
    "optimistix.bfgs",
    "jaxopt.levenberg_marquardt",
    "jaxopt.gauss_newton",
    "jaxopt.lbfgs",
    "scipy.least_squares",
    "jaxafm.geodesic_levenberg_marquardt",
)

#: The solvers for operators whose output is linear in their weights (PI, Preisach): exact
#: non-negative least squares (:mod:`jaxafm.identify.linear`). Only ``jaxafm fit`` takes them.
LINEAR_SOLVERS = ("jaxafm.nnls",)

#: Length units a data file may use -> nm per unit (every length inside jaxafm is in nm).
LENGTH_TO_NM = {"pm": 1e-3, "Å": 0.1, "nm": 1.0, "um": 1e3, "µm": 1e3, "\u03bcm": 1e3, "mm": 1e6, "m": 1e9}

#: Voltage units a data file may use -> V per unit.
VOLTAGE_TO_V = {"V": 1.0, "mV": 1e-3}


def check_effect_names(names, where: str = "effects") -> None:
    """Raise for any name not in :data:`EFFECTS`.

    Arguments:
        names: effect names, e.g. from a config.
        where: the config key or argument they came from, named in the error.

    Raises:
        ValueError: naming the first unknown effect, ``where`` and the known effects.
    """
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect {unknown[0]!r} in {where}; known effects: {', '.join(EFFECTS)}")
