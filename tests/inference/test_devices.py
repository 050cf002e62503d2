"""Vehicles split over JAX devices give the same bits as one device (issue 17, item 3).

A subprocess started with ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` (two CPU devices)
fits three simulated followers by smc, one after another, vectorised in batches of two, and one
after another with the paired independent moves; this process (one device) fits them the same three
ways, and vehicle a alone with one replicate (a chunk
of one vehicle, which XLA would otherwise compile into different float operations). Each way's
posterior draws must be bit-identical on one and two devices, and vehicle a's alone as in a
chunk. (Vectorising is a setting of its own: batches of two may differ from one at a time in the
last bits, as ``vmap`` compiles other float operations.) Negative control: another seed changes
the draws. In the ``extended`` tier (CI leaves it out for time, reports/ci_time.md).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

pytestmark = pytest.mark.extended

SEED = 7
FIT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    from bayesdrive.drivers.idm import IDM
    from bayesdrive.inference.engines import smc
    from bayesdrive.inference.diagnostics.synthetic_followers import simulate_following

    def followers():
        params = IDM.params_type(*(jnp.full(3, s.default) for s in IDM.specs))
        simulated = simulate_following(jax.random.key(11), IDM, params, num_steps=40)
        return simulated._replace(vehicle_ids=("a", "b", "c"))

    def fit(seed, arrays, chunk, batch, independent=False):
        result = smc.run(
            jax.random.key(seed), arrays, model=IDM, params=("v_des", "sigma"),
            num_particles=64, num_moves=1, temper_moves=2, final_moves=4, max_final_moves=8,
            vehicle_chunk=chunk, vehicle_batch=batch, independent=independent,
        )
        return np.stack([result.posterior["v_des"], result.posterior["sigma"]])
    """
)


def _in_subprocess(devices: int) -> dict:
    script = FIT + textwrap.dedent(
        f"""
        import json
        arrays = followers()
        print(json.dumps({{
            "devices": jax.device_count(),
            "plain": fit({SEED}, arrays, 2, 1).tolist(),
            "batched": fit({SEED}, arrays, 4, 2).tolist(),
            "paired": fit({SEED}, arrays, 2, 1, True).tolist(),
        }}))
        """
    )
    env = {**os.environ, "XLA_FLAGS": f"--xla_force_host_platform_device_count={devices}"}
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_sharded_fits_match_one_device_bit_for_bit():
    namespace: dict = {}
    exec(FIT, namespace)
    assert jax.device_count() == 1
    arrays = namespace["followers"]()
    here = {
        "plain": namespace["fit"](SEED, arrays, 2, 1),
        "batched": namespace["fit"](SEED, arrays, 4, 2),
        "paired": namespace["fit"](SEED, arrays, 2, 1, True),
    }
    alone = namespace["fit"](SEED, arrays.subset(np.asarray([0])), 1, 1)
    sharded = _in_subprocess(2)
    assert sharded["devices"] == 2
    for name, values in here.items():
        other = np.asarray(sharded[name], dtype=values.dtype)
        assert other.tobytes() == values.tobytes(), f"{name} fit on two devices differs"
    assert alone.tobytes() == here["plain"][..., :1].tobytes(), "vehicle a fitted alone differs"
    # Negative control: the seed reaches the draws.
    assert not np.array_equal(namespace["fit"](SEED + 1, arrays, 2, 1), here["plain"])
