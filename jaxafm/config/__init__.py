"""YAML run configurations, validated by pydantic schemas before any work starts.

One schema per command (``fit``, ``calibrate``, ``run``, ``study``, ``diagnose``, and ``predict``
and ``compensate`` in ``apply``), built from
shared parts: the strict base, the loader and data paths, one hysteresis-model spec
(:class:`HysteresisSpec`) and one image-file spec (:class:`ImageFile`, a path or a mapping with the
metadata a file format may lack) in ``common``; the names configs are checked against in ``names``.
Errors name the file, the key and the value, and say what is allowed.

This package imports no JAX: checking a YAML file is quick, and every layer's ``run(cfg, ...)``
job can take its config from here.
"""

from .apply import CompensateConfig, PredictConfig, RasterTrajectory, Trajectory, Triangle
from .calibrate import (
    CalibrateConfig,
    CalibrationImages,
    CalibrationLattice,
    CalibrationModel,
    CalibrationPair,
    CalibrationSolver,
    Compensation,
    SimulatedCalibration,
)
from .common import (
    ConfigError,
    HysteresisSpec,
    ImageFile,
    ImagePair,
    RecordData,
    Solver,
    load_config,
    resolve_data_path,
)
from .diagnose import (
    DiagnoseConfig,
    DiagnoseImage,
    DiagnoseNominal,
    DiagnoseScans,
    DiagnoseSimulation,
    ScanFiles,
    ScanSample,
    ScanSimulation,
)
from .fit import ActuatorFitConfig, ModelSpec, SimulatedData
from .names import EFFECTS, LENGTH_TO_NM, MODEL_EFFECTS, SOLVERS, VOLTAGE_TO_V, check_effect_names
from .run import (
    LandmarkSpec,
    LocalScanSpec,
    ParticleField,
    Positioning,
    PushSpec,
    RunConfig,
    StepA,
    Workspace,
    check_landmark_grid,
)
from .study import STUDY_PARAMETERS, Distribution, StudyConfig

#: ``jaxafm`` command -> its config schema (``jaxafm fit``'s first: :func:`load_config`'s default)
SCHEMAS = {
    "fit": ActuatorFitConfig,
    "calibrate": CalibrateConfig,
    "run": RunConfig,
    "study": StudyConfig,
    "diagnose": DiagnoseConfig,
    "predict": PredictConfig,
    "compensate": CompensateConfig,
}

__all__ = [
    "EFFECTS",
    "LENGTH_TO_NM",
    "MODEL_EFFECTS",
    "SCHEMAS",
    "SOLVERS",
    "STUDY_PARAMETERS",
    "VOLTAGE_TO_V",
    "ActuatorFitConfig",
    "CalibrateConfig",
    "CalibrationImages",
    "CalibrationPair",
    "CalibrationModel",
    "CalibrationSolver",
    "CompensateConfig",
    "Compensation",
    "ConfigError",
    "DiagnoseConfig",
    "DiagnoseImage",
    "DiagnoseNominal",
    "DiagnoseScans",
    "DiagnoseSimulation",
    "Distribution",
    "CalibrationLattice",
    "HysteresisSpec",
    "ImageFile",
    "ImagePair",
    "LandmarkSpec",
    "LocalScanSpec",
    "ModelSpec",
    "ParticleField",
    "Positioning",
    "PredictConfig",
    "PushSpec",
    "RasterTrajectory",
    "RecordData",
    "RunConfig",
    "ScanFiles",
    "ScanSample",
    "ScanSimulation",
    "SimulatedCalibration",
    "SimulatedData",
    "Solver",
    "StepA",
    "StudyConfig",
    "Trajectory",
    "Triangle",
    "Workspace",
    "check_effect_names",
    "check_landmark_grid",
    "load_config",
    "resolve_data_path",
]
