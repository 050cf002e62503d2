"""Convergence checks that :func:`bayesdrive.inference.fit.fit` runs after every fit.

Each check applies where it means something, per vehicle and parameter (numbers from
:func:`~bayesdrive.inference.diagnostics.agreement.convergence_table`):

* ``rhat``: rank-normalised split R-hat above :data:`RHAT_MAX`, with two or more chains (NUTS
  chains, PMMH chains, hierarchical chains, SMC replicates);
* ``ess_bulk`` / ``ess_tail``: bulk or tail effective sample size below :data:`ESS_MIN`, for
  engines whose draws form Markov chains (:data:`MARKOV_ENGINES`); a filter's particles have no
  order along which autocorrelation would mean anything;
* ``autocorr``: an emcee run shorter than 50 integrated autocorrelation times of the parameter
  after burn-in (:data:`AUTOCORR_RELIABLE_FACTOR`);
* ``stuck_walkers``: an emcee vehicle whose kept draws hold walkers stuck far below the others'
  log posterior (the engine's ``stuck_walkers``; :mod:`bayesdrive.inference.engines.emcee`);
* ``replicate_spread``: with several SMC replicates, the ESS that the spread of their means
  implies (:func:`~bayesdrive.inference.diagnostics.agreement.mcse_mean`) below :data:`ESS_MIN`;
* ``spread``, for every engine: a parameter whose draws are all equal has collapsed onto one
  value (a particle set descended from one particle that never moved, a chain that never
  accepted), which no posterior of these models is.

Beyond ``spread``, one-replicate smc, pf and lm have nothing to check against:
:func:`check_convergence` says so in its ``unchecked`` note rather than passing them silently. For
one-replicate smc the note also names the vehicles whose closing moves ran to their cap with the
draws still correlated with their start: a sign, not a proof, that the draws still carry the
tempering path's excess mass (most such vehicles still agree with nuts).
"""

from __future__ import annotations

import logging
import math
from typing import Any, NamedTuple

import numpy as np
import xarray as xr

from bayesdrive.inference.core.kernels import decorrelation_threshold
from bayesdrive.inference.core.output import metadata
from bayesdrive.inference.diagnostics.agreement import convergence_table

__all__ = [
    "AUTOCORR_RELIABLE_FACTOR",
    "ESS_MIN",
    "EXTENSION_MIN_DRAWS",
    "MARKOV_ENGINES",
    "RHAT_MAX",
    "ConvergenceProblem",
    "ConvergenceReport",
    "chain_problems",
    "check_convergence",
    "log_problems",
    "next_step",
]

log = logging.getLogger(__name__)

RHAT_MAX = 1.01
ESS_MIN = 400.0
# The engines extend a failing run only when they keep at least this many draws: fewer, nearly
# independent, still fall short of ESS_MIN by chance too often for an extension to be worth it.
EXTENSION_MIN_DRAWS = int(2 * ESS_MIN)
# emcee's rule of thumb: an autocorrelation estimate needs a run of at least 50 tau.
AUTOCORR_RELIABLE_FACTOR = 50
MARKOV_ENGINES = ("nuts", "emcee", "hierarchical", "pmmh")
# At most this many vehicles are named in the unchecked note.
SHOWN_VEHICLES = 10
# Problems logged one by one; the rest are counted (all of them are in the metadata).
LOGGED_PROBLEMS = 10


class ConvergenceProblem(NamedTuple):
    """One failed check for one vehicle and parameter."""

    vehicle: str
    param: str
    check: str
    value: float
    limit: float

    def message(self) -> str:
        if self.check == "spread":
            return (
                f"vehicle {self.vehicle}, parameter {self.param}: every draw is the same value "
                "(the posterior collapsed onto one point)"
            )
        if self.check == "stuck_walkers":
            return (
                f"vehicle {self.vehicle}: {self.value:.0f} walker(s) stuck far below the others' "
                "log posterior in the kept steps"
            )
        relation = "above" if self.check == "rhat" else "below"
        what = {
            "rhat": "R-hat",
            "ess_bulk": "bulk ESS",
            "ess_tail": "tail ESS",
            "autocorr": "run length in autocorrelation times",
            "replicate_spread": "ESS implied by the spread of the SMC replicates",
        }[self.check]
        return (
            f"vehicle {self.vehicle}, parameter {self.param}: {what} {self.value:.4g} is "
            f"{relation} {self.limit:g}"
        )


def chain_problems(
    vehicle: str, names: tuple[str, ...], draws: np.ndarray, *, rhat: bool = True
) -> list[ConvergenceProblem]:
    """The R-hat (with ``rhat`` and two or more chains), bulk- and tail-ESS checks of
    :func:`check_convergence` on one vehicle's draws (chain, draw, parameter), with the same
    estimators and limits: what an engine that extends its own run must pass."""
    import arviz  # here, not at the top: a fit whose checks need no ArviZ does not import it

    dataset = xr.Dataset({"theta": (("chain", "draw", "param"), np.asarray(draws, np.float64))})
    checks = [("ess_bulk", arviz.ess(dataset, method="bulk"), ESS_MIN, False)]
    checks.append(("ess_tail", arviz.ess(dataset, method="tail"), ESS_MIN, False))
    if rhat and draws.shape[0] >= 2:
        checks.insert(0, ("rhat", arviz.rhat(dataset), RHAT_MAX, True))
    problems = []
    for check, values, limit, above in checks:
        for name, value in zip(names, np.asarray(values["theta"].values, float), strict=True):
            if math.isnan(value) or (value > limit if above else value < limit):
                problems.append(ConvergenceProblem(vehicle, name, check, float(value), limit))
    return problems


def next_step(engine: str | None, options: dict[str, Any]) -> str | None:
    """What to try after a run that failed its checks, from the run's own (extended) settings."""
    if engine == "nuts" and "num_samples" in options:
        cap = options.get("max_extension", 1)
        draws = options["num_samples"] * options["num_chains"]
        if cap == 1:
            return (
                f"rerun with --draws {max(2 * draws, 2 * EXTENSION_MIN_DRAWS)} --warmup "
                f"{2 * options['num_warmup']} (from {EXTENSION_MIN_DRAWS} draws on, the run "
                "also extends itself where it falls short)"
            )
        return (
            f"the run already extended itself up to {cap}x its warm-up and draws; rerun with "
            f"--draws {2 * cap * draws} --warmup {2 * cap * options['num_warmup']}, and look for "
            "a ridge or a second mode in the pair plot if that fails too"
        )
    steps = options.get("max_steps", options.get("num_steps"))
    if engine == "emcee" and steps is not None:
        return (
            f"the run already extended itself up to {steps} steps; rerun with --steps "
            f"{2 * steps}, or cross-check with --engine nuts"
        )
    if engine in MARKOV_ENGINES:
        return "rerun with more --draws and a longer --warmup"
    if engine == "smc":
        return "rerun with more --particles"
    return None


class ConvergenceReport(NamedTuple):
    """The checks that ran, what failed, and why some could not run (None: all applicable ran)."""

    checks: list[str]
    problems: list[ConvergenceProblem]
    unchecked: str | None
    next_step: str | None = None

    def as_metadata(self) -> dict[str, Any]:
        return {
            "checks": self.checks,
            "problems": [p._asdict() for p in self.problems],
            "unchecked": self.unchecked,
            "next_step": self.next_step if self.problems else None,
        }


def check_convergence(tree: xr.DataTree) -> ConvergenceReport:
    """Run every check that applies to ``tree`` (module docstring); nothing is logged here."""
    meta = metadata(tree)
    engine = meta.get("engine")
    replicates = (meta.get("engine_options") or {}).get("replicates", 1)
    multi_chain = tree["posterior"].sizes["chain"] >= 2
    replicated_smc = engine == "smc" and replicates > 1
    # Only the spread check applies to one-chain filters: no ESS or MCSE is estimated for them.
    table = convergence_table(
        tree, statistics=multi_chain or engine in MARKOV_ENGINES or replicated_smc
    )
    checks: list[str] = []
    problems: list[ConvergenceProblem] = [
        ConvergenceProblem(row.vehicle, row.param, "spread", float(row.sd), 0.0)
        for row in table.itertuples()
        if not row.sd > 0.0
    ]

    def flag(check: str, column: str, limit: float, above: bool) -> None:
        checks.append(check)
        for row in table.itertuples():
            value = float(getattr(row, column))
            if math.isnan(value) or (value > limit if above else value < limit):
                problems.append(ConvergenceProblem(row.vehicle, row.param, check, value, limit))

    if multi_chain:
        flag("rhat", "rhat", RHAT_MAX, above=True)
    if engine in MARKOV_ENGINES:
        flag("ess_bulk", "ess_bulk", ESS_MIN, above=False)
        flag("ess_tail", "ess_tail", ESS_MIN, above=False)
    if "autocorr_time" in table:
        stats = tree["sample_stats"].to_dataset()
        if "num_steps" in stats:  # per vehicle: the run may have extended itself
            kept = stats["num_steps"] - stats["num_burn"]
            sampled = table["vehicle"].map(
                dict(zip(map(str, kept["vehicle"].values), kept.values, strict=True))
            )
        else:
            options = meta.get("engine_options") or {}
            sampled = options["num_steps"] - options["num_burn"]
        table["run_over_tau"] = sampled / table["autocorr_time"]
        flag("autocorr", "run_over_tau", AUTOCORR_RELIABLE_FACTOR, above=False)
    stats = tree["sample_stats"]
    if "stuck_walkers" in stats:
        checks.append("stuck_walkers")
        stuck = stats["stuck_walkers"]
        problems += [
            ConvergenceProblem(str(vehicle), "all", "stuck_walkers", float(count), 0.0)
            for vehicle, count in zip(stuck["vehicle"].values, stuck.values, strict=True)
            if count > 0
        ]
    if replicated_smc:
        flag("replicate_spread", "ess_mean", ESS_MIN, above=False)
    unchecked = None
    if not checks:
        unchecked = (
            f"{engine} with one chain of independent-looking draws: no R-hat, ESS or replicate "
            "check applies (smc: use replicates > 1)"
        )
        undecorrelated = _closing_at_cap(stats, meta.get("engine_options") or {})
        if undecorrelated:
            unchecked += (
                f"; the closing moves of {len(undecorrelated)} vehicle(s) ended at their cap with "
                "draws still correlated with the tempering's, so these may be off: "
                f"{', '.join(undecorrelated[:SHOWN_VEHICLES])}"
                f"{' ...' if len(undecorrelated) > SHOWN_VEHICLES else ''} (rerun them with "
                "more --particles, or with replicates > 1 to measure their spread)"
            )
    advice = next_step(engine, meta.get("engine_options") or {})
    return ConvergenceReport(["spread", *checks], problems, unchecked, advice)


def _closing_at_cap(stats: xr.DataTree, options: dict[str, Any]) -> list[str]:
    """The vehicles whose smc closing moves (in any replicate) ran to ``max_final_moves`` with the
    draws still correlated with their start above the engine's criterion: there the draws may
    still carry the tempering path's excess mass (``reports/convergence/extensions_ngsim15.md``,
    vehicle 109)."""
    needed = ("max_final_moves", "decorrelation", "num_particles")
    if "final_moves" not in stats or not all(k in options for k in needed):
        return []
    criterion = float(decorrelation_threshold(options["decorrelation"], options["num_particles"]))
    moves, correlation = stats["final_moves"], stats["final_correlation"]
    flagged = (moves >= options["max_final_moves"]) & ~(correlation <= criterion)
    flagged = flagged.any([d for d in flagged.dims if d != "vehicle"])
    return [str(v) for v in flagged["vehicle"].values[flagged.values]]


def log_problems(report: ConvergenceReport) -> None:
    """One warning per problem (the first :data:`LOGGED_PROBLEMS`), each with the next step to
    take, then how many more."""
    advice = f"; next: {report.next_step}" if report.next_step else ""
    for problem in report.problems[:LOGGED_PROBLEMS]:
        log.warning("not converged: %s%s", problem.message(), advice)
    hidden = len(report.problems) - LOGGED_PROBLEMS
    if hidden > 0:
        log.warning("... and %d more convergence problem(s), listed in the metadata", hidden)
