r"""Followers driven by the Optimal Velocity Model, behind one varied head vehicle.

**Driver.** The Optimal Velocity Model written from Bando, Hasebe, Nakayama, Shibata & Sugiyama
(Phys. Rev. E 51, 1035, 1995), :math:`\dot v = \kappa\,[V(s) - v]`, with their optimal velocity
:math:`\tanh(b - 2) + \tanh 2` put in physical units by a gap scale :math:`s_c` and a speed scale
:math:`v_{max}/2`:

.. math::

    V(s) = \frac{v_{max}}{2}\Big[\tanh\Big(\frac{s}{s_c} - \beta\Big) + \tanh\beta\Big],
    \qquad \beta = 2,

:math:`s` the bumper gap, plus an acceleration error of sd :math:`\sigma`, one normal draw held for
each 0.1 s sample. As in :mod:`trafficgen.simulate`, the equations are integrated on ``SUBSTEPS``
sub-steps per sample (speed clipped at 0, positions by the trapezoid of the speeds), so the
recorded steps are not the one-step Euler map a fitted model uses. ``inflection`` changes
:math:`\beta` (a different optimal-velocity law, for negative controls).

**Platoon.** One head vehicle replayed from the random profile of :mod:`trafficgen.simulate`
(segments of constant acceleration towards random target speeds, some hard braking), and
``len(kappa)`` followers in a line, each following the one ahead; every follower starts at the
head's speed and at the gap where its optimal velocity equals it.

Randomness: one integer seed; the head, the lengths and the noise draw from their own streams.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from trafficgen.simulate import DT, HEAD_START_SPEED, LENGTH_M, SUBSTEPS, _head_accelerations

__all__ = ["OVMPlatoon", "optimal_velocity", "ovm_platoon"]

BANDO_INFLECTION = 2.0


class OVMPlatoon(NamedTuple):
    """x: front-bumper positions (m), v: speeds (m/s), both (vehicle, sample) with the head first;
    length: (vehicle,) lengths (m), so follower k's bumper gap is x[k-1] - length[k-1] - x[k];
    dt: the sampling interval (s)."""

    x: np.ndarray
    v: np.ndarray
    length: np.ndarray
    dt: float


def optimal_velocity(gap, v_max, s_c, inflection=BANDO_INFLECTION):
    """V(s) of the module docstring."""
    return 0.5 * v_max * (np.tanh(gap / s_c - inflection) + np.tanh(inflection))


def _equilibrium_gap(v, v_max, s_c, inflection):
    """The gap s with V(s) = v (v below the free-road speed)."""
    level = np.clip(2.0 * v / v_max - np.tanh(inflection), -0.999999, 0.999999)
    return s_c * (inflection + np.arctanh(level))


def ovm_platoon(
    seed: int,
    *,
    kappa,
    v_max,
    s_c,
    sigma,
    duration_s: float,
    inflection: float = BANDO_INFLECTION,
) -> OVMPlatoon:
    """One platoon (module docstring); ``kappa`` (1/s), ``v_max`` (m/s), ``s_c`` (m) and ``sigma``
    (m/s^2) are per-follower sequences of equal length."""
    kappa, v_max, s_c, sigma = (np.asarray(p, dtype=np.float64) for p in (kappa, v_max, s_c, sigma))
    followers = kappa.shape[0]
    if not all(p.shape == (followers,) for p in (v_max, s_c, sigma)):
        raise ValueError("kappa, v_max, s_c and sigma must be 1-d and of one length")
    heads, lengths, noise = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3)
    )
    samples = round(duration_s / DT)
    start = heads.uniform(*HEAD_START_SPEED, size=1)
    head_acc = _head_accelerations(heads, start, samples)[0]
    length = lengths.uniform(*LENGTH_M, size=followers + 1)

    n = followers + 1
    x, v = np.zeros((n, samples + 1)), np.zeros((n, samples + 1))
    v[:, 0] = start[0]
    gaps = _equilibrium_gap(start[0], v_max, s_c, inflection)
    x[1:, 0] = -np.cumsum(gaps + length[:-1])
    h = DT / SUBSTEPS
    for t in range(samples):
        error = sigma * noise.standard_normal(followers)
        xs, vs = x[:, t].copy(), v[:, t].copy()
        for _ in range(SUBSTEPS):
            gap = xs[:-1] - length[:-1] - xs[1:]
            acc = np.concatenate(
                [[head_acc[t]], kappa * (optimal_velocity(gap, v_max, s_c, inflection) - vs[1:])]
            )
            acc[1:] += error
            new_v = np.maximum(0.0, vs + acc * h)
            xs += 0.5 * (vs + new_v) * h
            vs = new_v
        x[:, t + 1], v[:, t + 1] = xs, vs
    return OVMPlatoon(x=x, v=v, length=length, dt=DT)
