"""Full simulation-based calibration study of smc, nuts and emcee, with the sd-doubled power check.

For each engine: R replications (default 200) of T steps (default 100 = 10 s) behind a replayed
synthetic leader, four IDM parameters (d_min, tau, a_max, sigma) drawn from the prior box, L = 99
ranks in 20 bins, chi-square per parameter at 0.01 / 4 (Bonferroni), KS reported. Then the same
study with the same seed fitting the sd-doubled likelihood, which must be rejected. Writes to
``reports/sbc/`` (or ``--out``): per study the rank histograms (PNG), ranks (CSV) and digest
(JSON), and ``sbc_table.md`` with every p-value, coverage, the verdicts and the runtimes.

Run: ``python benchmarks/bench_sbc.py [--replications 200] [--engines smc,nuts,emcee]
[--model idm+autocorrelated_noise]``; with an extended model its own parameters are inferred too,
drawn from their prior box. A run of some engines and a model keeps the other studies from
``sbc_studies.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import numpy as np

from bayesdrive.cli.sbc_cmd import write_outcome
from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.diagnostics.sbc import run_sbc, sd_doubled
from bayesdrive.inference.fit import ENGINES

PARAMS = ("d_min", "tau", "a_max", "sigma")
# Each engine at the settings a user would run: ~1000 draws per replication.
ENGINE_OPTIONS = {
    "smc": {"num_particles": 1000},
    "nuts": {"num_particles": 1000, "num_chains": 4, "num_warmup": 500},
    "emcee": {"num_particles": 1000, "num_steps": 2000},
}


def table(digests: list[dict]) -> str:
    """The markdown table: one row per study and parameter (digests of SBCOutcome.summary)."""
    lines = [
        "| engine | fitted model | replications | param | chi2 p | KS p | 90% coverage | min ESS | "
        "verdict | study time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for study in digests:
        for name, test in study["parameters"].items():
            verdict = "reject" if test["chi2_pvalue"] < study["bonferroni_level"] else "pass"
            lines.append(
                f"| {study['engine']} | {study['fit_model']} | {study['replications']} | {name} | "
                f"{test['chi2_pvalue']:.3g} | {test['ks_pvalue']:.3g} | "
                f"{test['coverage']:.3f} | {test['min_ess']:.0f} | {verdict} | "
                f"{study['study_time_s']:.0f} |"
            )
    return "\n".join(lines) + "\n"


def kept_studies(path: Path, rerun: set[str], model: str) -> list[dict]:
    """Studies not rerun now (another engine or model), from an earlier run's digest file."""
    if not path.exists():
        return []
    return [
        s
        for s in json.loads(path.read_text())["studies"]
        if s["engine"] not in rerun or s["model"] != model
    ]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replications", type=int, default=200)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument("--engines", default="smc,nuts,emcee")
    parser.add_argument("--out", type=Path, default=Path("reports/sbc"))
    parser.add_argument("--model", default="idm", help="a model name (extensions too)")
    args = parser.parse_args(argv)

    model = get_model(args.model)
    params = PARAMS + tuple(n for n in model.param_names if n not in IDM.param_names)
    started = time.perf_counter()
    engines = args.engines.split(",")
    digests = kept_studies(args.out / "sbc_studies.json", set(engines), model.name)
    for engine in engines:
        for fit_model in (model, sd_doubled(model)):
            study_started = time.perf_counter()
            outcome = run_sbc(
                jax.random.key(args.seed),
                ENGINES[engine],
                engine_name=engine,
                model=model,
                params=params,
                fit_model=fit_model,
                num_replications=args.replications,
                num_steps=args.steps,
                engine_options=ENGINE_OPTIONS[engine],
                seed=args.seed,
            )
            seconds = time.perf_counter() - study_started
            stem = (
                f"sbc_{engine}"
                + ("" if model is IDM else "_" + model.name.replace("+", "_"))
                + ("" if fit_model is model else "_sd_doubled")
            )
            write_outcome(outcome, args.out, stem)
            digests.append({**outcome.summary(), "study_time_s": seconds})
            print(
                f"{engine} fitting {fit_model.name}: calibrated={outcome.calibrated}, "
                f"chi2 p={np.round(outcome.chi2_pvalue, 4).tolist()}, {seconds:.0f} s",
                flush=True,
            )
    total = time.perf_counter() - started
    header = (
        "# Simulation-based calibration (benchmarks/bench_sbc.py)\n\n"
        f"{args.replications} replications x {args.steps} steps (dt 0.1 s) per study, seed "
        f"{args.seed}, parameters {', '.join(PARAMS)} (and an extended model's own) from the "
        "uniform prior box, the rest at their defaults; a replayed synthetic leader per "
        "replication, the follower simulated by the fitted model's own step "
        "(bayesdrive.inference.diagnostics.synthetic_followers); L = 99 ranks. Verdict: chi-square per parameter at "
        "0.01 / the number of parameters (Bonferroni). The sd-doubled rows fit a likelihood "
        "with twice the execution-noise sd on the same simulated data (same seed): they must "
        "be rejected.\n\n"
        f"Engine settings: {json.dumps(ENGINE_OPTIONS)}.\n\n"
        f"Runtime of this run ({', '.join(engines)}): {total / 60:.1f} min on "
        f"{platform.machine()} ({jax.device_count()} JAX device(s), shared 2-core machine); "
        "studies of other engines are kept from the previous run (their times in the table).\n\n"
    )
    digests.sort(
        key=lambda s: (s["model"], list(ENGINE_OPTIONS).index(s["engine"]), s["fit_model"])
    )
    write_text_atomic(args.out / "sbc_table.md", header + table(digests))
    write_text_atomic(
        args.out / "sbc_studies.json",
        json.dumps({"total_time_s": total, "studies": digests}, indent=2) + "\n",
    )
    print(f"total {total / 60:.1f} min; written to {args.out}")


if __name__ == "__main__":
    main()
