"""emcee on vehicle 140 of ngsim_i80_chains with idm+drifting_parameters, without extension.

    python probe.py <seed> <steps> '<emcee options as JSON>'

The box scale is the engine as it is; the logit scale needs ``emcee_logit.patch`` applied to
480c0b8 (``git apply``), which the study tried and did not keep (``../ngsim15_drifting_parameters.md``,
"Stop 58")."""

import json
import sys
import time

import jax
import numpy as np

from bayesdrive.data import registry
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.fit import fit

seed, steps = int(sys.argv[1]), int(sys.argv[2])
options = json.loads(sys.argv[3]) if len(sys.argv) > 3 else {}
started = time.perf_counter()
tree = fit(
    jax.random.key(seed),
    registry.load("ngsim_i80_chains"),
    model=get_model("idm+drifting_parameters"),
    engine="emcee",
    seed=seed,
    vehicle_ids=["140"],
    num_steps=steps,
    max_steps=steps,
    **options,
)
posterior = tree["posterior"]
names = list(posterior.data_vars)
tau = tree["sample_stats"]["autocorr_time"].values[0]
print("wall", round(time.perf_counter() - started, 1), "steps", steps, "options", options)
print("tau", dict(zip(names, np.round(tau, 1).tolist(), strict=True)))
print("run/tau", round(steps / 2 / float(np.max(tau)), 1))
print("means", {n: round(float(posterior[n].mean()), 4) for n in names})
print("sds", {n: round(float(posterior[n].std()), 4) for n in names})
