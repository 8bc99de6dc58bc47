"""The main job with the true scanner as step A's model: what steps B, C and the push reach when
identification is perfect, to tell their errors from step A's.

    python experiments/paper_true_model.py [--config configs/paper.yaml]

Writes ``experiments/results/paper_true_model/`` (the run's files; the model is the simulated
scanner itself without its drift and noise, which no model can know).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import yaml

import jaxafm
from jaxafm.config import RunConfig
from jaxafm.jobs import run as run_job
from jaxafm.jobs import run_folder
from jaxafm.model.io import save_model

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "paper.yaml", help="the run's config")
    config = ap.parse_args().config.resolve()
    out = ROOT / "experiments" / "results" / "paper_true_model"
    model = out / "true_scanner.json"
    raw = yaml.safe_load(config.read_text())
    raw["calibration"]["model_file"] = str(model)
    cfg = RunConfig.model_validate(raw)
    with run_folder(out, "run", config, cfg, overwrite=True) as folder:
        folder.prepare()  # the true model is one of the run's files
        truth = jaxafm.default_scanner().without("drift", "noise")
        folder.output.write(model.name, lambda path: save_model(truth, path))
        run_job.run(cfg, config, folder.output)


if __name__ == "__main__":
    main()
