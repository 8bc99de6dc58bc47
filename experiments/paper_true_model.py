"""The main job with the true scanner as step A's model: what steps B, C and the push reach when
identification is perfect, to tell their errors from step A's.

    python experiments/paper_true_model.py

Writes ``experiments/results/paper_true_model/`` (the run's files; the model is the simulated
scanner itself without its drift and noise, which no model can know).
"""

from __future__ import annotations

from pathlib import Path

import yaml

import jaxafm
from jaxafm.cli import RUN_OUTPUTS, prepare_output
from jaxafm.config import RunConfig
from jaxafm.model.io import save_model
from jaxafm.position import strategy

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    out = ROOT / "experiments" / "results" / "paper_true_model"
    prepare_output(out, True, RUN_OUTPUTS + ("true_scanner.json",))
    model = out / "true_scanner.json"
    save_model(jaxafm.default_scanner().without("drift", "noise"), model)
    raw = yaml.safe_load((ROOT / "configs" / "paper.yaml").read_text())
    raw["calibration"]["model_file"] = str(model)
    strategy.run(RunConfig.model_validate(raw), ROOT / "configs" / "paper.yaml", out)


if __name__ == "__main__":
    main()
