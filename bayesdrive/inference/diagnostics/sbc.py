r"""Simulation-based calibration (Talts, Betancourt, Simpson, Vehtari & Gelman 2018, arXiv:1804.06788).

For replication r = 1..R: draw :math:`\theta_r` from the prior (the model's uniform box), simulate
one follower with the stochastic model (``model.transition_sample``, through
:func:`~bayesdrive.inference.diagnostics.synthetic_followers.simulate_following`: a replayed synthetic oscillating
leader), fit it with the engine under test, and take the rank of :math:`\theta_{r,k}` among
``num_ranks`` = L posterior draws of parameter k (the number of draws below it, 0..L). If the
engine returns the exact posterior, every rank is uniform on 0..L, whatever the model.

* **Near-independent draws.** The L draws are evenly spaced over all of a replication's draws
  (chains one after another), i.e. MCMC output thinned by (chains x draws) / L; the effective
  sample size of each replication's draws (``arviz.ess``, bulk) is recorded, so a thinning that is
  too light (ESS < L) shows.
* **Uniformity tests, per parameter.** A chi-square test on the ranks binned into ``bins`` equal
  bins (bins divide L + 1, at least ``MIN_EXPECTED`` expected per bin) and a Kolmogorov-Smirnov test
  of the randomised normalised ranks ``(rank + U) / (L + 1)``, U ~ Uniform(0, 1), which are exactly
  Uniform(0, 1) under calibration. The chi-square test decides; with K parameters it is judged at
  ``alpha / K`` (Bonferroni), so the whole study falsely rejects at most ``alpha``.
* **Coverage** of central ``interval`` posterior intervals is recorded too: averaged over the prior
  it equals the nominal level for an exact posterior.
* **Power.** :func:`sd_doubled` wraps a model so that its likelihood uses twice the execution-noise
  sd (the paper code's factor-2 bug); the same study with the same seed must reject it.

All replications are fitted by ONE engine call (they are the "vehicles" of one data set), so R
replications cost one compilation.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import arviz
import jax
import numpy as np
import scipy.stats
from jax import Array

from bayesdrive.drivers.base import DriverModel, fill_params
from bayesdrive.inference.core.likelihood import fixed_params, param_names
from bayesdrive.inference.core.output import EngineResult, thinned_draws
from bayesdrive.inference.diagnostics.synthetic_followers import simulate_following

__all__ = [
    "MIN_EXPECTED",
    "SBCOutcome",
    "choose_bins",
    "posterior_ranks",
    "run_sbc",
    "sd_doubled",
    "simulate_replications",
    "uniformity_tests",
]

# The chi-square approximation wants at least 5 expected counts per bin.
MIN_EXPECTED = 5


class SBCOutcome(NamedTuple):
    """One SBC study (module docstring). Arrays are numpy; k indexes ``names``.

    truth, ranks, ess: (R, K). counts: (K, bins). chi2, chi2_pvalue, ks_pvalue, coverage: (K,).
    calibrated: every chi-square p-value >= alpha / K (Bonferroni).
    """

    engine: str
    model: str
    fit_model: str
    names: tuple[str, ...]
    seed: int | None
    num_steps: int
    num_ranks: int
    bins: int
    alpha: float
    interval: float
    truth: np.ndarray
    ranks: np.ndarray
    ess: np.ndarray
    counts: np.ndarray
    chi2: np.ndarray
    chi2_pvalue: np.ndarray
    ks_pvalue: np.ndarray
    coverage: np.ndarray
    calibrated: bool
    compile_time_s: float
    wall_time_s: float
    engine_options: dict[str, Any]

    def summary(self) -> dict[str, Any]:
        """A JSON-ready digest: settings, per-parameter tests and the verdict."""
        return {
            "engine": self.engine,
            "model": self.model,
            "fit_model": self.fit_model,
            "seed": self.seed,
            "replications": int(self.ranks.shape[0]),
            "num_steps": self.num_steps,
            "num_ranks": self.num_ranks,
            "bins": self.bins,
            "alpha": self.alpha,
            "bonferroni_level": self.alpha / len(self.names),
            "calibrated": self.calibrated,
            "compile_time_s": self.compile_time_s,
            "wall_time_s": self.wall_time_s,
            "engine_options": self.engine_options,
            "parameters": {
                name: {
                    "chi2": float(self.chi2[k]),
                    "chi2_pvalue": float(self.chi2_pvalue[k]),
                    "ks_pvalue": float(self.ks_pvalue[k]),
                    "coverage": float(self.coverage[k]),
                    "min_ess": float(np.min(self.ess[:, k])),
                    "bin_counts": self.counts[k].tolist(),
                }
                for k, name in enumerate(self.names)
            },
        }


def sd_doubled(model: DriverModel) -> DriverModel:
    """A deliberately wrong model: its likelihood uses twice the execution-noise sd (the spec
    marked ``execution_noise``), its simulator the true one.

    Used to show that SBC has power: an engine fitting this model must fail calibration.
    """
    noise = model.execution_noise_param
    if noise is None:
        raise ValueError(f"model {model.name!r} marks no execution-noise sd to double")

    def doubled(params):
        return params._replace(**{noise: 2.0 * getattr(params, noise)})

    def transition_logpdf(params, state, next_state, inputs, **censoring):
        return model.transition_logpdf(doubled(params), state, next_state, inputs, **censoring)

    return model._replace(name=f"{model.name}-sd-doubled", transition_logpdf=transition_logpdf)


def simulate_replications(
    key: Array,
    model: DriverModel,
    names: Sequence[str],
    *,
    num_replications: int,
    num_steps: int,
    fixed: Mapping[str, float] | None = None,
    dt: float = 0.1,
) -> tuple[np.ndarray, Any]:
    """Prior draws (R, K) of the parameters ``names`` and one simulated follower for each.

    Parameters not in ``names`` take the ``fixed`` values (else the model's defaults).
    """
    key_prior, key_sim = jax.random.split(key)
    theta = model.prior(names).sample(key_prior, (num_replications,))
    base = fixed_params(model, fixed)
    params = jax.vmap(lambda th: fill_params(model, names, th, base))(theta)
    arrays = simulate_following(key_sim, model, params, num_steps=num_steps, dt=dt)
    return np.asarray(theta, dtype=np.float64), arrays


def posterior_ranks(
    posterior: Mapping[str, np.ndarray],
    names: Sequence[str],
    truth: np.ndarray,
    num_ranks: int,
) -> np.ndarray:
    """Ranks (R, K) of each truth among ``num_ranks`` evenly spaced draws of its replication.

    ``posterior`` maps each name to (chain, draw, replication); the draws of one replication are
    taken chain after chain, so MCMC output is thinned by (chains x draws) / num_ranks.
    """
    ranks = np.empty(truth.shape, dtype=np.int64)
    for k, name in enumerate(names):
        draws = np.asarray(posterior[name])
        flat = draws.reshape(-1, draws.shape[-1])  # (chain * draw, replication)
        if flat.shape[0] < num_ranks:
            raise ValueError(
                f"{name!r}: {flat.shape[0]} posterior draws per replication, fewer than the "
                f"{num_ranks} ranks requested"
            )
        chosen = flat[thinned_draws(flat.shape[0], num_ranks)]
        ranks[:, k] = np.sum(chosen < truth[None, :, k], axis=0)
    return ranks


def choose_bins(num_ranks: int, num_replications: int, max_bins: int = 20) -> int:
    """The most bins (<= max_bins) that divide the L + 1 ranks evenly and expect >= 5 per bin."""
    candidates = [
        b
        for b in range(2, max_bins + 1)
        if (num_ranks + 1) % b == 0 and num_replications / b >= MIN_EXPECTED
    ]
    if not candidates:
        raise ValueError(
            f"{num_replications} replications and {num_ranks} ranks allow no chi-square binning "
            f"with {MIN_EXPECTED} expected per bin; use more replications or L + 1 with small "
            "divisors (e.g. 99 ranks)"
        )
    return max(candidates)


def uniformity_tests(
    key: Array, ranks: np.ndarray, num_ranks: int, bins: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bin counts (K, bins), chi-square statistics and p-values (K,), KS p-values (K,).

    ``key`` draws the uniform jitter of the randomised normalised ranks for the KS test.
    """
    if (num_ranks + 1) % bins:
        raise ValueError(f"{bins} bins do not split the {num_ranks + 1} possible ranks evenly")
    width = (num_ranks + 1) // bins
    counts = np.stack(
        [np.bincount(ranks[:, k] // width, minlength=bins) for k in range(ranks.shape[1])]
    )
    chi2, chi2_pvalue = scipy.stats.chisquare(counts, axis=1)
    jitter = np.asarray(jax.random.uniform(key, ranks.shape), dtype=np.float64)
    normalised = (ranks + jitter) / (num_ranks + 1)
    ks_pvalue = np.array(
        [scipy.stats.kstest(normalised[:, k], "uniform").pvalue for k in range(ranks.shape[1])]
    )
    return counts, np.asarray(chi2), np.asarray(chi2_pvalue), ks_pvalue


def _ess(posterior: Mapping[str, np.ndarray], names: Sequence[str]) -> np.ndarray:
    """Bulk ESS (R, K) of every replication's draws (arviz; within-chain for single chains)."""
    return np.stack(
        [
            np.asarray(
                arviz.ess(
                    np.moveaxis(np.asarray(posterior[name]), -1, 0), chain_axis=1, draw_axis=2
                )
            )
            for name in names
        ],
        axis=1,
    )


def _coverage(
    posterior: Mapping[str, np.ndarray], names: Sequence[str], truth: np.ndarray, interval: float
) -> np.ndarray:
    """Fraction of replications whose central ``interval`` posterior interval holds the truth."""
    tail = (1.0 - interval) / 2.0
    covered = []
    for k, name in enumerate(names):
        draws = np.asarray(posterior[name])
        flat = draws.reshape(-1, draws.shape[-1])
        low, high = np.quantile(flat, [tail, 1.0 - tail], axis=0)
        covered.append(np.mean((low <= truth[:, k]) & (truth[:, k] <= high)))
    return np.asarray(covered)


def run_sbc(
    key: Array,
    engine: Callable[..., EngineResult],
    *,
    engine_name: str,
    model: DriverModel,
    params: Sequence[str] | None = None,
    fit_model: DriverModel | None = None,
    fixed: Mapping[str, float] | None = None,
    num_replications: int = 200,
    num_steps: int = 64,
    num_ranks: int = 99,
    bins: int | None = None,
    alpha: float = 0.01,
    interval: float = 0.9,
    engine_options: Mapping[str, Any] | None = None,
    seed: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SBCOutcome:
    """Simulate ``num_replications`` followers from ``model`` and fit them with ``engine``.

    ``fit_model`` (default ``model``) is what the engine fits: pass :func:`sd_doubled` of the model
    for a power check. ``seed`` is only recorded (the randomness comes from ``key``).
    """
    names = param_names(model, params)
    fit_model = model if fit_model is None else fit_model
    bins = choose_bins(num_ranks, num_replications) if bins is None else bins
    if not 0.0 < alpha < 1.0 or not 0.0 < interval < 1.0:
        raise ValueError(f"alpha and interval must be in (0, 1), got {alpha} and {interval}")
    key_sim, key_fit, key_jitter = jax.random.split(key, 3)
    truth, arrays = simulate_replications(
        key_sim,
        model,
        names,
        num_replications=num_replications,
        num_steps=num_steps,
        fixed=fixed,
    )
    options = dict(engine_options or {})
    result = engine(
        key_fit, arrays, model=fit_model, params=names, fixed=fixed, progress=progress, **options
    )
    ranks = posterior_ranks(result.posterior, names, truth, num_ranks)
    counts, chi2, chi2_pvalue, ks_pvalue = uniformity_tests(key_jitter, ranks, num_ranks, bins)
    return SBCOutcome(
        engine=engine_name,
        model=model.name,
        fit_model=fit_model.name,
        names=names,
        seed=seed,
        num_steps=num_steps,
        num_ranks=num_ranks,
        bins=bins,
        alpha=alpha,
        interval=interval,
        truth=truth,
        ranks=ranks,
        ess=_ess(result.posterior, names),
        counts=counts,
        chi2=chi2,
        chi2_pvalue=chi2_pvalue,
        ks_pvalue=ks_pvalue,
        coverage=_coverage(result.posterior, names, truth, interval),
        calibrated=bool(np.all(chi2_pvalue >= alpha / len(names))),
        compile_time_s=result.compile_time_s,
        wall_time_s=result.wall_time_s,
        engine_options={**options, **result.options},
    )
