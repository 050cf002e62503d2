"""The calibration step of ``bayesdrive reproduce`` on every held-out data set, run alone.

``bayesdrive reproduce --out results`` calibrates the predictive on the held-out windows as one
of its last steps (:func:`bayesdrive.experiments.paper.calibration_step`: the IDM and the final
model ``criticize`` chose on the training data set of the same kind, each fitted by smc with the
full run's settings and seeds to the held-out followers' fitting windows; coverage, PIT and the
point scores beside constant velocity, :mod:`bayesdrive.simulation.calibration`). A full run
takes hours on 2 cores; this runs that step alone, with the same settings, seeds and code, from
the final models of the committed full run (``models/``: the criticism's choice is the model of
each training label's extended posterior, read from its metadata).

Resumable: fits and each data set's result are kept in ``--out`` and reused. Writes
``reports/holdout/holdout_calibration.json`` and ``reports/holdout/calibration.html`` (the
report's own calibration section).

    PYTHONPATH=. python benchmarks/holdout_calibration.py --out results-calibration
"""

from __future__ import annotations

import argparse
import functools
import json
from pathlib import Path

from bayesdrive.data import registry
from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.drivers.idm import IDM
from bayesdrive.experiments.paper import FULL, calibration_step
from bayesdrive.inference.output import load_result, metadata
from bayesdrive.reports.html import Report
from bayesdrive.reports.paper_report import calibration_section

ROOT = Path(__file__).resolve().parents[1]
# The highway labels the criticism ran on, and the files of their models in models/.
TRAINING_LABELS = {
    "ngsim_i80_chains": "ngsim_i80_chains",
    "openacc_vicolungo:human": "openacc_vicolungo_human",
}


def committed_final_models(models: Path) -> dict[str, str]:
    """Each training label's final model: the extended model among its committed posteriors."""
    found = {}
    for label, stem in TRAINING_LABELS.items():
        for path in sorted(models.glob(f"{stem}_idm_*_smc.nc")):
            name = metadata(load_result(path))["model"]
            if name != IDM.name:
                found[label] = name
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="fits and per-set results")
    parser.add_argument("--models", type=Path, default=ROOT / "models")
    parser.add_argument("--report", type=Path, default=ROOT / "reports" / "holdout")
    args = parser.parse_args()
    final_models = committed_final_models(args.models)
    print(f"final models chosen on the training data: {final_models}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    result = calibration_step(
        args.out / "calibration",
        final_models,
        FULL,
        False,
        functools.cache(registry.load_holdout),
        evaluation_fits=args.out,
    )
    result["final_models"] = final_models
    args.report.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.report / "holdout_calibration.json", json.dumps(result, indent=2) + "\n")
    report = Report(
        "Calibration on the held-out data sets",
        "The calibration step of bayesdrive reproduce (full settings), run alone by "
        "benchmarks/holdout_calibration.py; its result holdout_calibration.json is beside this "
        "file.",
    )
    calibration_section(report.section("Calibration on held-out windows"), result, args.report)
    report.write(args.report / "calibration.html")
    print(f"wrote {args.report / 'calibration.html'}", flush=True)


if __name__ == "__main__":
    main()
