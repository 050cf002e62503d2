"""A reference that does not depend on any Markov chain mixing: importance sampling.

For each ``--vehicles`` id of ``ngsim_i80_chains`` (fitting window, all six IDM parameters, the
uniform prior box: the target of ``bench_agreement`` and ``bench_reference``), a short nuts pilot
gives a mean and covariance; ``--draws`` proposals from a multivariate t around them (two
proposals: 5 degrees of freedom with the covariance doubled, 3 with it tripled, both heavier-tailed
than the posterior) are weighted by prior x likelihood / proposal density. The weighted moments are
consistent whatever the pilot got wrong, so long as the proposal covers the posterior; the
effective sample size of the weights and the agreement of the two proposals say whether it does.
Monte Carlo standard errors come from the spread over ``--batches`` equal batches.

In a posterior whose sd rests on rare visits to a tail (vehicle 124's b_pref), a Markov chain's
sd estimate varies far more between seeds than its own MCSE suggests; independent proposals
visit the tail in proportion to its mass every time.

Writes ``reports/agreement/importance.md`` (or ``--out``). Runs in float64. Run:
``python benchmarks/bench_importance.py --vehicles 124,140``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.registry import load
from bayesdrive.data.views import follower_arrays
from bayesdrive.drivers.idm import IDM
from bayesdrive.inference.fit import fit
from bayesdrive.inference.likelihood import fixed_params, series_loglik, step_inputs

DATA = "ngsim_i80_chains"
PILOT = {"num_particles": 8000, "num_chains": 4, "num_warmup": 1000}
PROPOSALS = ((5, 2.0), (3, 3.0))  # (degrees of freedom, covariance inflation)


def t_draws(key: jax.Array, mean: np.ndarray, shape: np.ndarray, df: int, size: int) -> np.ndarray:
    """``size`` draws of a multivariate t (normal scaled by sqrt(df / chi-square(df)))."""
    key_normal, key_gamma = jax.random.split(key)
    normal = jax.random.normal(key_normal, (size, mean.size)) @ jnp.linalg.cholesky(shape).T
    chi2 = 2.0 * jax.random.gamma(key_gamma, df / 2.0, (size,))
    return np.asarray(mean + normal * jnp.sqrt(df / chi2)[:, None])


def weighted_moments(theta: np.ndarray, log_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Self-normalised weighted mean and sd of each column."""
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    mean = w @ theta
    return mean, np.sqrt(w @ (theta - mean) ** 2)


def importance(key, arrays, pilot_draws, df, inflation, draws, batches):
    """Mean, sd, their batch standard errors, the ESS and the largest normalised weight."""
    names = IDM.param_names
    box = IDM.prior(names)
    lower, upper = np.asarray(box.lower), np.asarray(box.upper)
    series = jax.tree.map(lambda a: a[0], step_inputs(arrays))
    fixed = fixed_params(IDM, None)
    log_lik = jax.jit(jax.vmap(lambda theta: series_loglik(IDM, names, fixed, theta, series).sum()))
    mean, shape = pilot_draws.mean(0), inflation * np.cov(pilot_draws.T)
    proposal = stats.multivariate_t(loc=mean, shape=shape, df=df)
    thetas, log_ws = [], []
    for batch_key in jax.random.split(key, batches):
        theta = t_draws(batch_key, mean, shape, df, draws // batches)
        inside = np.all((theta > lower) & (theta < upper), axis=1)
        log_w = np.full(len(theta), -np.inf)  # outside the prior box the posterior is 0
        log_w[inside] = np.asarray(log_lik(jnp.asarray(theta[inside]))) - proposal.logpdf(
            theta[inside]
        )
        thetas.append(theta)
        log_ws.append(log_w)
    theta, log_w = np.concatenate(thetas), np.concatenate(log_ws)
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    per_batch = np.array([weighted_moments(t, lw) for t, lw in zip(thetas, log_ws, strict=True)])
    se = per_batch.std(axis=0, ddof=1) / np.sqrt(batches)
    m, sd = weighted_moments(theta, log_w)
    return m, sd, se[0], se[1], 1.0 / np.sum(w**2), w.max()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", default="124,140")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--draws", type=int, default=2_000_000)
    parser.add_argument("--batches", type=int, default=20)
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--out", type=Path, default=Path("reports/agreement"))
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)  # before anything is traced

    traj = load(DATA, data_dir=args.data_dir)
    lines = [
        "# Importance-sampling references (benchmarks/bench_importance.py)",
        "",
        f"{DATA}, fitting windows, all six IDM parameters, uniform prior box, float64, seed "
        f"{args.seed}. Pilot: nuts {PILOT}; {args.draws} proposals per proposal family from a "
        "multivariate t around the pilot's mean with its covariance inflated; se: spread over "
        f"{args.batches} batches. ESS: effective sample size of the normalised weights.",
        "",
        "| vehicle | proposal | ESS | max weight | param | mean | se | sd | se of sd | time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    key = jax.random.key(args.seed)
    for vehicle in args.vehicles.split(","):
        key, key_pilot, key_is = jax.random.split(key, 3)
        arrays = follower_arrays(traj, window="fit", vehicle_ids=[vehicle])
        pilot = fit(key_pilot, arrays, model=IDM, engine="nuts", seed=args.seed, **PILOT)
        pilot_draws = np.stack([pilot["posterior"][n].values.ravel() for n in IDM.param_names], 1)
        for (df, inflation), proposal_key in zip(
            PROPOSALS, jax.random.split(key_is, len(PROPOSALS)), strict=True
        ):
            started = time.perf_counter()
            mean, sd, se_mean, se_sd, ess, max_w = importance(
                proposal_key, arrays, pilot_draws, df, inflation, args.draws, args.batches
            )
            seconds = time.perf_counter() - started
            for i, name in enumerate(IDM.param_names):
                lines.append(
                    f"| {vehicle} | t{df}, {inflation:g} x cov | {ess:.0f} | {max_w:.1e} | "
                    f"{name} | {mean[i]:.4g} | {se_mean[i]:.2g} | {sd[i]:.4g} | {se_sd[i]:.2g} | "
                    f"{seconds:.0f} |"
                )
            print(f"{vehicle} t{df}: ESS {ess:.0f}, {seconds:.0f} s", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out / "importance.md", "\n".join(lines) + "\n")
    print(f"written to {args.out / 'importance.md'}")


if __name__ == "__main__":
    main()
