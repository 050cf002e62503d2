"""The held-out steps of ``bayesdrive reproduce`` on every held-out data set, run alone.

``bayesdrive reproduce --full --out results`` ends with two steps on the held-out data sets
(:mod:`bayesdrive.experiments.holdout`): the evaluation (:func:`~bayesdrive.experiments.paper.holdout_step`:
per-vehicle smc fits, the population predictive of the training data set of the same kind,
baselines, paired intervals) and the calibration (:func:`~bayesdrive.experiments.paper.calibration_step`:
the IDM and the final model ``criticize`` chose on the training data, each fitted by smc to the
held-out followers' fitting windows; coverage, PIT and the point scores beside constant velocity).
A full run takes hours on 2 cores; this runs those two steps alone, with the full run's settings,
seeds and code, on the training results of the committed full run in ``models/``: its
per-vehicle smc posteriors (the populations' drivers, and the pooled NGSIM row) and its final
models (each training label's extended posterior names the criticism's choice).

Resumable: fits and each data set's results are kept in ``--out`` and reused (both steps share
the per-vehicle IDM fits); ``--sets`` runs some data sets only (the long ACC platoon's fits take
the longest); ``--calibration-only`` and ``--evaluation-only`` run one step. Writes
``holdout_evaluation.json``, ``holdout_calibration.json`` and
``holdout.html`` (the report's own held-out and calibration sections) to ``--report``.

    PYTHONPATH=. python benchmarks/holdout_steps.py --out results-holdout
"""

from __future__ import annotations

import argparse
import functools
import json
from pathlib import Path

from bayesdrive.data import registry
from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.experiments.paper import FULL, calibration_step, holdout_step
from bayesdrive.inference.core.output import load_result, metadata
from bayesdrive.reports.html import Report
from bayesdrive.reports.paper_report import calibration_section, holdout_section

ROOT = Path(__file__).resolve().parents[1]
# The highway labels of the full run and the stems of their files in models/ (the ACC contrast
# recordings were not criticised: they have no extended model).
TRAINING_LABELS = {
    "ngsim_i80_chains": "ngsim_i80_chains",
    "openacc_vicolungo:human": "openacc_vicolungo_human",
    "openacc_vicolungo:acc-contrast": "openacc_vicolungo_acc-contrast",
}


def committed_final_models(models: Path) -> dict[str, str]:
    """Each training label's final model: the extended model among its committed posteriors."""
    found = {}
    for label, stem in TRAINING_LABELS.items():
        # "_idm_*_smc" matches the extended models' files only, not the IDM's own.
        for path in sorted(models.glob(f"{stem}_idm_*_smc.nc")):
            found[label] = metadata(load_result(path))["model"]
    return found


def committed_smc_fits(models: Path) -> dict:
    """Each highway label's per-vehicle smc posterior of the IDM, as the full run saved it."""
    return {
        label: load_result(models / f"{stem}_idm_smc.nc") for label, stem in TRAINING_LABELS.items()
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="fits and per-set results")
    parser.add_argument("--models", type=Path, default=ROOT / "models")
    parser.add_argument("--report", type=Path, default=ROOT / "reports" / "holdout")
    parser.add_argument(
        "--sets", default=None, help="comma-separated held-out data sets (default: every one)"
    )
    only = parser.add_mutually_exclusive_group()
    only.add_argument("--calibration-only", action="store_true", help="the calibration step alone")
    only.add_argument("--evaluation-only", action="store_true", help="the evaluation step alone")
    args = parser.parse_args()
    final_models = committed_final_models(args.models)
    print(f"final models chosen on the training data: {final_models}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    load = functools.cache(registry.load_holdout)
    names = None if args.sets is None else args.sets.split(",")
    results = {}
    if not args.evaluation_only:
        calibration = calibration_step(
            args.out / "calibration", final_models, FULL, False, load, args.out, names
        )
        calibration["final_models"] = final_models
        results["calibration"] = calibration
    if not args.calibration_only:
        fits = committed_smc_fits(args.models)
        results["evaluation"] = holdout_step(
            args.out, fits, FULL, False, load, names, final_models=final_models
        )
    args.report.mkdir(parents=True, exist_ok=True)
    for name, result in results.items():
        path = args.report / f"holdout_{name}.json"
        write_text_atomic(path, json.dumps(result, indent=2) + "\n")
    report = Report(
        "Held-out data sets: new drivers, new roads",
        "The held-out steps of bayesdrive reproduce (full settings), run alone by "
        "benchmarks/holdout_steps.py on the committed full run's training results "
        f"(models/); their results ({', '.join(f'holdout_{name}.json' for name in results)}) "
        "are beside this file.",
    )
    if "evaluation" in results:
        section = report.section("Generalisation to held-out data sets")
        holdout_section(section, results["evaluation"])
    if "calibration" in results:
        section = report.section("Calibration on held-out windows")
        calibration_section(section, results["calibration"], args.report)
    report.write(args.report / "holdout.html")
    print(f"wrote {args.report / 'holdout.html'}", flush=True)


if __name__ == "__main__":
    main()
