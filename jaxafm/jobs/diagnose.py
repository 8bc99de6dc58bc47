"""``jaxafm diagnose CONFIG``: read the configured data, diagnose it, write the report.

One of four sources (``jaxafm.config.DiagnoseConfig``): a measured actuator record
(``data``), a simulated one (``simulate``), one grating image (``image``) or trace/retrace
scan pairs (``scans``, from files or simulated). Everything is read and checked before the
output folder is prepared; the report is :func:`jaxafm.diagnose.report.write`'s, and
``metrics.json`` holds the metrics it returns.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..config import DiagnoseConfig, DiagnoseScans, ImageFile, resolve_data_path
from ..diagnose import withheld
from ..diagnose.core import Diagnosis, Rules
from ..diagnose.image import diagnose_image, lattice_vectors
from ..diagnose.record import ActuatorRecord, auto_settle, diagnose_record
from ..diagnose.report import write
from ..diagnose.scans import ScanPair, diagnose_scans
from ..instrument.records import read_record
from .folder import Output
from .inputs import read_image_file, read_image_pair, scan_settings, settings_line


def run(cfg: DiagnoseConfig, config_path: Path, out: Output, log=print) -> dict:
    """Diagnose the configured record, image or scan set into ``out``.

    Arguments:
        cfg: a validated ``DiagnoseConfig``.
        config_path: the config file (data paths are relative to it; errors name it).
        out: the output folder: ``diagnosis.json``, ``metrics.json``, ``residuals.png``,
            ``report.md``; prepared once the data are read and diagnosed, before anything is written.
        log: called with each line of the human summary.

    Returns:
        The metrics.

    Raises:
        ValueError: for data that cannot be read or split, naming the config key to change.
    """
    rules = Rules(cfg.min_shrink_pct, cfg.min_delta_bic, cfg.max_steps)
    config_path = Path(config_path)
    if cfg.image is not None:
        diagnosis = _image(cfg, config_path, rules, log)
    elif cfg.scans is not None:
        diagnosis = _scans(cfg, config_path, rules, log)
    else:
        diagnosis = _record(cfg, config_path, rules, log)
    out.prepare()
    return out.write_metrics(write(diagnosis, out.write, log))


def _record(cfg: DiagnoseConfig, config_path: Path, rules: Rules, log) -> Diagnosis:
    record = _load(cfg, config_path)
    blocks = cfg.blocks if cfg.split == "blocked" else 0
    try:
        data = ActuatorRecord.split_off(
            record, cfg.nominal, cfg.train_fraction, 0, None, rules.max_steps, blocks
        )
    except ValueError as e:
        key = "blocks" if blocks else "train_fraction"
        raise ValueError(f"{e}: give a longer record, or change {key} in {config_path}") from None
    history = None if cfg.history_v is None else np.asarray(cfg.history_v, dtype=float)
    if cfg.settle_s == "auto":
        settle = auto_settle(record, cfg.train_fraction, history, blocks)
    else:
        settle = int(round(cfg.settle_s / np.median(np.diff(record.t))))
    if int(data.train[settle:].sum()) < 10:
        raise ValueError(
            f"settle_s={cfg.settle_s} s leaves {int(data.train[settle:].sum())} training samples: lower "
            f"settle_s or raise train_fraction in {config_path}"
        )
    if "creep" in cfg.nominal.effects and (reason := data.cannot("creep")):
        raise ValueError(f"nominal.effects in {config_path}: 'creep' cannot be fitted: {reason}")
    outputs = np.asarray(record.d).reshape(len(record), -1).shape[1]
    log(
        f"record: {record.meta['source']} - {len(record)} samples x {outputs} output(s); train "
        f"{int(data.train[settle:].sum())} (from {record.t[settle] - record.t[0]:.3g} s on), hold out "
        f"{int(data.heldout.sum())}" + (f" ({blocks} alternating blocks)" if blocks else "")
    )
    return diagnose_record(
        record, cfg.nominal, cfg.candidates, cfg.train_fraction, settle, history, rules, log, blocks
    )


def _load(cfg: DiagnoseConfig, config_path: Path):
    """The configured record: simulated, or read (the output unit must be named)."""
    if cfg.data is None:
        s = cfg.simulate
        return withheld.simulate_record(
            s.withheld, s.magnitude, s.seed, s.duration_s, s.sample_rate_hz, s.noise_nm
        )
    spec = cfg.data.model_dump(exclude={"path"})
    path = resolve_data_path(cfg.data.path, config_path)
    if spec["output_unit"] is None and spec["output_columns"] is not None:
        raise ValueError(
            f"{path}: the record's output unit is missing: set data.output_unit in {config_path} "
            "(e.g. output_unit: um)"
        )
    record = read_record(path, **spec)
    return dataclasses.replace(record, meta=record.meta | {"source": cfg.data.path})  # as the config gives it


def _image(cfg: DiagnoseConfig, config_path: Path, rules: Rules, log) -> Diagnosis:
    im = cfg.image
    spec = ImageFile.model_validate(im.model_dump(exclude={"kind", "pitch_nm"}, exclude_unset=True))
    image = read_image_file(spec, config_path, "image")
    pitch = None if im.pitch_nm is None else im.pitch_nm[0]
    if im.kind == "lattice" and pitch is not None:
        try:  # the features repeat at the stated pitch, as step A's calibration checks
            lattice_vectors(image, pitch)
        except ValueError as e:
            raise ValueError(f"{config_path}: image: {e}") from None
    log(
        f"image: {image.meta.get('source')} - {image.shape[0]} x {image.shape[1]} px"
        f"{' of a 2-D lattice' if im.kind == 'lattice' else ''}; nominal: hysteresis-only scanner "
        "(fast-axis nonlinearity)"
    )
    return diagnose_image(image, cfg.candidates, cfg.train_fraction, rules, log, im.kind, pitch)


def _scans(cfg: DiagnoseConfig, config_path: Path, rules: Rules, log) -> Diagnosis:
    sc = cfg.scans
    sim = {"lines": withheld.SIM_GRATING, "lattice": withheld.SIM_LATTICE}
    grating = sim[sc.simulate.sample] if sc.grating is None else sc.grating
    pairs = _scan_pairs(sc, config_path, log)
    return diagnose_scans(pairs, grating, cfg.candidates, cfg.train_fraction, rules, log)


def _scan_pairs(sc: DiagnoseScans, config_path: Path, log) -> list:
    """The configured trace/retrace pairs: simulated, or read from files."""
    if sc.simulate is not None:
        s = sc.simulate
        what = (
            f" with {s.withheld} {s.magnitude:g} {withheld.SCAN_UNITS[s.withheld]}"
            if s.withheld
            else " (a control)"
        )
        log(f"simulating trace/retrace pairs at {', '.join(f'{r:g}' for r in s.line_rates_hz)} Hz{what}")
        return withheld.simulate_scans(
            s.withheld,
            s.magnitude,
            s.seed,
            s.line_rates_hz,
            s.lines,
            s.pixels,
            noise_nm=s.noise_nm,
            sample=s.sample,
        )
    pairs, said = [], []
    for i, p in enumerate(sc.pairs):
        tr, re = read_image_pair(p, config_path, f"scans.pairs[{i}]")
        how, source = scan_settings(p, (tr, re), config_path, f"scans.pairs[{i}]")
        said.append(settings_line(f"scans.pairs[{i}]", how, source))
        if tr.shape != re.shape:
            raise ValueError(
                f"{config_path}: scans.pairs[{i}]: the trace ({tr.shape}) and retrace ({re.shape}) "
                "images differ in size"
            )
        dt = 1.0 / (2 * how["line_rate_hz"] * tr.shape[1] * (1 + 2 * how["overscan"]))  # s between two pixels
        pairs.append(ScanPair(np.asarray(tr.z), np.asarray(re.z), tuple(tr.pixel_size), dt, p.trace.path))
    for line in said:  # once every pair has passed: a refusal is the run's first line
        log(line)
    return pairs
