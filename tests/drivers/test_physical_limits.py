"""The execution noise within the vehicle's physical limits and collision-free by construction
(drivers/execution_noise.py): the sampler and the censored density describe one law, and the
noise never collides where the deterministic IDM does not."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from bayesdrive.drivers.base import CarFollowingInputs, EgoState
from bayesdrive.drivers.closed_loop import STATIONARY, platoon_scene, rollout_scenes
from bayesdrive.drivers.execution_noise import (
    LIMIT_TOLERANCE,
    MAX_ACCELERATION,
    MAX_BRAKING,
    acceleration_ceiling,
    implied_acceleration,
    noisy_step,
    step_logpdf,
)
from bayesdrive.drivers.extensions import autocorrelated_noise
from bayesdrive.drivers.idm import IDM
from bayesdrive.drivers.registry import get_model

DT = 0.1
DRAWS = 4000


def step_law(v: float, mean: float, sigma: float, inputs: CarFollowingInputs):
    """The censored one-step law as the density states it, from ``step_logpdf`` alone: the class
    masses (stop, floor, ceiling; each read off one observation in its class) with the implied
    acceleration at which each sits, and the interior density of the implied acceleration on a
    fine grid (the density of the position increment times its Jacobian dt^2 / 2)."""
    state = EgoState(jnp.float32(0.0), jnp.float32(v))
    ceiling = float(acceleration_ceiling(state.v, inputs))

    def logp(acc):
        next_v = jnp.maximum(0.0, v + acc * DT)
        next_state = EgoState(0.5 * (v + next_v) * DT, next_v)
        return step_logpdf(state, next_state, mean, sigma, DT, ceiling)

    stop_at = -v / DT  # where a stopped step's implied acceleration lies
    atoms = {"stop": stop_at, "floor": -MAX_BRAKING, "ceiling": ceiling}
    masses = {name: float(np.exp(logp(jnp.float32(at)))) for name, at in atoms.items()}
    low = max(-MAX_BRAKING, stop_at) + LIMIT_TOLERANCE
    if stop_at > -MAX_BRAKING:  # a step braking at the floor would stop: no moving floor class
        masses["floor"] = 0.0
    if stop_at < -MAX_BRAKING:  # no stop in one step from this speed
        masses["stop"] = 0.0
    grid = np.linspace(low + 1e-4, ceiling - LIMIT_TOLERANCE - 1e-4, 6001)
    density = np.exp(np.asarray(jax.vmap(logp)(jnp.asarray(grid, jnp.float32)))) * DT**2 / 2
    cumulative = np.concatenate(
        [[0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(grid))]
    )
    return atoms, masses, grid, cumulative


def randomized_pit(samples, atoms, masses, grid, cumulative) -> np.ndarray:
    """PIT values of the implied accelerations under the law: inside, its CDF; in a class with a
    mass, uniform within the mass (the randomized PIT of a law with atoms, uniform under it)."""
    order = sorted(atoms, key=atoms.get)
    below = {}
    interior_start = max(atoms["stop"], atoms["floor"])
    running = 0.0
    for name in order:
        if atoms[name] <= interior_start:
            below[name] = running
            running += masses[name]
    start = running
    below["ceiling"] = start + cumulative[-1]
    u = np.random.default_rng(0).uniform(size=samples.shape)
    pit = start + np.interp(samples, grid, cumulative)
    for name in order:
        at_atom = np.abs(samples - atoms[name]) <= LIMIT_TOLERANCE
        pit = np.where(at_atom, below[name] + u * masses[name], pit)
    return pit


# (speed, mean, sigma, gap, leader speed, has leader), the classes it exercises: a fast car near
# its leader, where the floor and the ceiling each take about a sixth of the draws, and a crawling
# car on free road, which stops about half the time.
SCENES = {
    "floor and ceiling": ((12.0, -7.0, 2.0, 3.32, 6.0, 1.0), ("floor", "ceiling")),
    "stop": ((0.5, -5.0, 2.0, 50.0, 0.0, 0.0), ("stop",)),
}


@pytest.mark.parametrize("scene", list(SCENES))
def test_bounded_noise_sampler_matches_its_censored_density(scene):
    """4000 one-step draws of ``noisy_step`` (key 0), their implied accelerations against the law
    ``step_logpdf`` states: the class masses and interior density sum to 1 within 1e-3, the
    randomized PIT is uniform (KS p > 1e-3), and the same draws reject the unbounded Gaussian
    (p < 1e-6), the negative control."""
    (v, mean, sigma, gap, lead_v, has_leader), exercised = SCENES[scene]
    inputs = CarFollowingInputs(
        jnp.float32(gap), jnp.float32(lead_v), jnp.float32(has_leader), jnp.float32(DT)
    )
    atoms, masses, grid, cumulative = step_law(v, mean, sigma, inputs)
    assert abs(sum(masses.values()) + cumulative[-1] - 1.0) < 1e-3
    assert min(masses[name] for name in exercised) > 0.1
    state = EgoState(jnp.float32(0.0), jnp.float32(v))
    ceiling = acceleration_ceiling(state.v, inputs)
    keys = jax.random.split(jax.random.key(0), DRAWS)
    moved = jax.vmap(lambda k: noisy_step(k, state, mean, sigma, DT, ceiling))(keys)
    samples = np.asarray(implied_acceleration(v, moved.x, DT), np.float64)
    assert samples.min() >= -MAX_BRAKING - 1e-3 and samples.max() <= float(ceiling) + 1e-3
    pit = randomized_pit(samples, atoms, masses, grid, cumulative)
    assert stats.kstest(pit, "uniform").pvalue > 1e-3
    assert stats.kstest(samples, stats.norm(mean, sigma).cdf).pvalue < 1e-6


def test_the_ceiling_keeps_a_safe_distance_to_a_leader_braking_at_the_limit():
    """Constructed inputs (10 m/s behind a leader at 6 m/s, 5 m gap), stepped here with numpy: a
    step at the ceiling, then braking at the limit, stops at least the safety gap (0.1 m) behind a
    leader that brakes at the limit to a stop from now on, and within 0.7 m of it (the ceiling is
    not needlessly low: the bound of the discrete stop is loose by up to v' dt / 2); 6 m/s^2
    above the ceiling the gap closes below 0.1 m (the negative control). Without a leader the ceiling is the physical maximum."""
    v, lead_v, gap = 10.0, 6.0, 5.0
    inputs = CarFollowingInputs(*(jnp.float32(x) for x in (gap, lead_v, 1.0, DT)))
    ceiling = float(acceleration_ceiling(jnp.float32(v), inputs))
    assert -MAX_BRAKING < ceiling < 0.0

    def closest(first_acc: float) -> float:
        ego_v, leader_v, between = v, lead_v, gap
        acc, smallest = first_acc, gap
        while ego_v > 0 or leader_v > 0:
            ego_next = max(0.0, ego_v + acc * DT)
            leader_next = max(0.0, leader_v - MAX_BRAKING * DT)
            between += 0.5 * (leader_v + leader_next) * DT - 0.5 * (ego_v + ego_next) * DT
            ego_v, leader_v, acc = ego_next, leader_next, -MAX_BRAKING
            smallest = min(smallest, between)
        return smallest

    assert 0.1 - 1e-4 <= closest(ceiling) <= 0.7
    assert closest(ceiling + 6.0) < 0.1
    free = inputs._replace(has_leader=jnp.float32(0.0))
    assert float(acceleration_ceiling(jnp.float32(v), free)) == MAX_ACCELERATION


def hard_braking_scenes(seed: int, count: int, steps: int):
    """Random platoon scenes (numpy, ``seed``), stacked: a head cruising at 8-30 m/s that brakes
    at 3-9 m/s^2 (9: the physical limit) to a random speed or a stop, once or twice, holds, and
    speeds up again; four followers at its speed, 0.5-1.5 s apart."""
    rng = np.random.default_rng(seed)
    scenes = []
    for _ in range(count):
        speed = rng.uniform(8.0, 30.0)
        head = np.full(steps + 1, speed)
        for start in np.sort(rng.integers(20, steps - 100, size=rng.integers(1, 3))):
            target = rng.choice([0.0, rng.uniform(0.0, speed)])
            braking, hold = rng.uniform(3.0, MAX_BRAKING), rng.integers(10, 60)
            down = np.maximum(head[start] - braking * DT * np.arange(steps + 1 - start), target)
            head[start:] = np.minimum(head[start:], down)
            restart = start + int(np.argmax(down <= target)) + hold
            if restart < steps:
                up = head[restart] + rng.uniform(1.0, 2.5) * DT * np.arange(steps + 1 - restart)
                head[restart:] = np.minimum(up, speed)
        headways = rng.uniform(0.5, 1.5, 4)
        x0 = -np.cumsum(2.0 + 4.5 + headways * speed)
        scenes.append(platoon_scene(head, x0, np.full(4, speed), length=4.5, dt=DT))
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *scenes)


SCENES_COUNT, ROLLOUTS = 8, 8


def collisions(model, values: dict, scenes) -> int:
    """Collisions over 8 rollouts of every scene (key 1) of ``model`` with ``values`` (the others
    its defaults)."""
    params = model.defaults()._replace(**{k: jnp.float32(v) for k, v in values.items()})
    shape = (SCENES_COUNT, ROLLOUTS, 4)
    per_vehicle = jax.tree.map(lambda a: jnp.full(shape, a, jnp.float32), params)
    keys = jax.random.split(jax.random.key(1), SCENES_COUNT)
    rolled = rollout_scenes(
        keys, model, per_vehicle, scenes, num_rollouts=ROLLOUTS, start=STATIONARY, dt=DT
    )
    return int(np.asarray(rolled.collision).sum())


def test_execution_noise_never_collides(monkeypatch):
    """8 random hard-braking scenes (seed 5), 30 s each, 4 followers, 8 rollouts (key 1): the
    deterministic IDM (sigma 1e-6) never collides, and neither does the IDM with the prior's
    largest execution noise (sigma 2 m/s^2), nor a driver reacting 1.5 s late with that noise
    persistent (correlation time 5 s, the prior's bounds), which without the ceiling (the floor
    kept) collides: the negative control."""
    scenes = hard_braking_scenes(5, SCENES_COUNT, 300)
    assert collisions(IDM, {"sigma": 1e-6}, scenes) == 0
    assert collisions(IDM, {"sigma": 2.0}, scenes) == 0
    late = get_model("idm+reaction_delay+autocorrelated_noise")
    late_and_persistent = {"sigma": 2.0, "reaction_time": 1.5, "noise_time_s": 5.0}
    assert collisions(late, late_and_persistent, scenes) == 0
    # The control lifts the ceiling to the physical maximum; a renamed model is traced afresh.
    monkeypatch.setattr(
        autocorrelated_noise,
        "acceleration_ceiling",
        lambda v, inputs: jnp.full_like(v, MAX_ACCELERATION),
    )
    uncapped = late._replace(name="idm+reaction_delay+autocorrelated_noise without ceiling")
    assert collisions(uncapped, late_and_persistent, scenes) > 0
