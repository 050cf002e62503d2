"""A vehicle's draws depend on the seed and its own id and data only (issue 17, item 1).

Three simulated followers a, b, c (b's series cut short, so pf's length sort and skipped steps
differ between the fits) are fitted together, as [c, a] and a alone by smc (two replicates),
nuts and pf at tiny settings: every array of the result that has a vehicle axis must be
bit-identical, for the shared vehicles, across the three fits. pf fits the three together in
chunks of two (its chunks are vectorised, the others' run one vehicle after another); smc and nuts
run one vehicle a chunk, so each compiles once (compilation is most of this test's time).
Negative control: another seed changes vehicle a's draws.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesdrive.drivers.idm import IDM
from bayesdrive.inference import fit
from bayesdrive.inference.core.output import EngineResult
from bayesdrive.inference.core.vehicles import vehicle_hash, vehicle_keys
from bayesdrive.inference.diagnostics.synthetic_followers import simulate_following
from bayesdrive.inference.engines import nuts, pf, smc

PARAMS = ("v_des", "sigma")
STEPS = 40
SEED = 5
ENGINES = {
    "smc": (
        smc.run,
        {
            "num_particles": 64,
            "num_moves": 1,
            "temper_moves": 2,
            "final_moves": 4,
            "max_final_moves": 8,
            "replicates": 2,
        },
    ),
    "nuts": (nuts.run, {"num_particles": 20, "num_chains": 2, "num_warmup": 10}),
    "pf": (pf.run, {"num_particles": 64}),
}


@pytest.fixture(scope="module")
def arrays():
    params = IDM.params_type(*(jnp.full(3, s.default) for s in IDM.specs))
    simulated = simulate_following(jax.random.key(11), IDM, params, num_steps=STEPS)
    mask = np.asarray(simulated.mask).copy()
    mask[1, STEPS // 2 :] = 0.0  # b is shorter
    return simulated._replace(vehicle_ids=("a", "b", "c"), mask=mask)


def _fit(engine: str, arrays, rows: list[int], chunk: int, seed: int = SEED) -> EngineResult:
    run, options = ENGINES[engine]
    subset = arrays.subset(np.asarray(rows))
    return run(
        jax.random.key(seed), subset, model=IDM, params=PARAMS, vehicle_chunk=chunk, **options
    )


def _vehicle_slices(result: EngineResult, column: int) -> dict[str, np.ndarray]:
    """Every output of one vehicle: posterior, log-likelihood and per-vehicle sample stats."""
    slices = {f"posterior.{k}": v[:, :, column] for k, v in result.posterior.items()}
    slices["log_likelihood"] = result.log_likelihood[:, :, column]
    for name, (dims, values) in result.sample_stats.items():
        if "vehicle" in dims:
            slices[f"sample_stats.{name}"] = np.take(
                np.asarray(values), column, axis=dims.index("vehicle")
            )
    return slices


def _assert_same_bits(first: dict[str, np.ndarray], second: dict[str, np.ndarray], what: str):
    assert first.keys() == second.keys()
    for name, values in first.items():
        other = second[name]
        assert values.dtype == other.dtype and values.shape == other.shape, (what, name)
        assert values.tobytes() == other.tobytes(), f"{name} of {what} differs"


# nuts' and pf's cases are in the extended tier (reports/ci_time.md): every engine maps vehicles
# alike, and CI keeps pf's chunking and order check (test_inference_pf.py).
@pytest.mark.parametrize(
    "engine",
    [
        pytest.param(name, marks=[pytest.mark.extended] if name in ("nuts", "pf") else [])
        for name in sorted(ENGINES)
    ],
)
def test_a_vehicles_draws_do_not_depend_on_the_other_vehicles(engine, arrays):
    together = _fit(engine, arrays, [0, 1, 2], chunk=2 if engine == "pf" else 1)
    swapped = _fit(engine, arrays, [2, 0], chunk=1)
    alone = _fit(engine, arrays, [0], chunk=1)
    a = _vehicle_slices(together, 0)
    _assert_same_bits(a, _vehicle_slices(swapped, 1), "vehicle a fitted as [c, a]")
    _assert_same_bits(a, _vehicle_slices(alone, 0), "vehicle a fitted alone")
    _assert_same_bits(
        _vehicle_slices(together, 2), _vehicle_slices(swapped, 0), "vehicle c fitted as [c, a]"
    )
    # Negative control: the seed reaches every vehicle's draws.
    other_seed = _fit(engine, arrays, [0], chunk=1, seed=SEED + 1)
    assert not np.array_equal(
        other_seed.posterior["v_des"][:, :, 0], together.posterior["v_des"][:, :, 0]
    )


def test_vehicle_keys_follow_the_id_not_the_position():
    key = jax.random.key(0)
    data = np.asarray(jax.random.key_data(vehicle_keys(key, ["a", "b", "c"])))
    again = np.asarray(jax.random.key_data(vehicle_keys(key, ["c", "a"])))
    np.testing.assert_array_equal(data[[2, 0]], again)
    assert len({row.tobytes() for row in data}) == 3
    replicated = np.asarray(jax.random.key_data(vehicle_keys(key, ["a", "b"], replicates=2)))
    assert replicated.shape[:2] == (2, 2)
    assert replicated[0, 0].tobytes() != replicated[1, 0].tobytes()
    # The hash is sha256's first 8 bytes of the UTF-8 id (stable across processes and versions).
    assert vehicle_hash("a") == (0xCA978112, 0xCA1BBDCA)


@pytest.mark.parametrize("engine", sorted(fit.ENGINES))
def test_every_engine_refuses_a_misspelt_or_missing_shared_input(engine, arrays):
    """The shared inputs travel as ``**inputs``: a misspelt one is a TypeError, as a misspelt
    keyword argument would be, not silently ignored; so is a missing model."""
    run = fit.ENGINES[engine]
    with pytest.raises(TypeError, match=r"unexpected keyword argument\(s\) \['num_particle'\]"):
        run(jax.random.key(0), arrays, model=IDM, num_particle=10)
    with pytest.raises(TypeError, match="missing the keyword argument 'model'"):
        run(jax.random.key(0), arrays, num_particles=10)
