"""The hidden mechanisms, their effect sizes, and the verdicts of ``bayesdrive criticize`` that
count as right for each (cause names of ``bayesdrive.drivers.extensions``; the table is in the
package docstring and in reports/criticism/generator.md).

Sizes are ranges of one parameter per mechanism, drawn uniformly per driver, so a platoon mixes
drivers with more and less of the effect.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["MECHANISMS", "NULL", "SIZES", "Mechanism", "right_verdicts"]

NULL = "none"
SIZES = ("small", "medium", "large")


class Mechanism(NamedTuple):
    """One way of making drivers differ from the plain IDM with white noise."""

    parameter: str  # the per-driver size parameter
    unit: str
    sizes: dict[str, tuple[float, float]]
    verdicts: tuple[str, ...]  # criticize verdicts that count as right; () = out of reach
    how: str  # the mechanism, in words (for the table)


MECHANISMS: dict[str, Mechanism] = {
    "perception_delay": Mechanism(
        "delay_s",
        "s",
        {"small": (0.1, 0.25), "medium": (0.25, 0.5), "large": (0.5, 0.9)},
        ("reaction_delay",),
        "gap and closing speed are perceived as they were delay_s ago (positions and speeds "
        "linearly interpolated between 0.01 s sub-steps; a cut-in is seen from its entry on); "
        "the own speed in the free-road and time-gap terms is current",
    ),
    "pedal_noise": Mechanism(
        "pedal_time_s",
        "s",
        {"small": (0.1, 0.25), "medium": (0.25, 0.5), "large": (0.5, 1.5)},
        ("autocorrelated_noise",),
        "the acceleration error is an Ornstein-Uhlenbeck process in continuous time (correlation "
        "time pedal_time_s, integrated on the sub-steps) instead of white noise per sample",
    ),
    "time_gap_drift": Mechanism(
        "drift_amplitude",
        "--",
        {"small": (0.1, 0.2), "medium": (0.2, 0.35), "large": (0.35, 0.5)},
        ("drifting_parameters",),
        "the time gap follows tau (1 + A sin(2 pi t / P + phase)), period P uniform on 15-40 s: "
        "a smooth drift of the parameter the extension lets wander",
    ),
    "time_gap_switch": Mechanism(
        "switch_factor",
        "--",
        {"small": (0.15, 0.3), "medium": (0.3, 0.5), "large": (0.5, 0.8)},
        ("drifting_parameters",),
        "a regime switch: at a random time in 40-80% of the record the time gap jumps to "
        "tau (1 + F); a random walk of tau reaches it, approximately",
    ),
    "acceleration_drift": Mechanism(
        "drift_amplitude",
        "--",
        {"small": (0.1, 0.2), "medium": (0.2, 0.35), "large": (0.35, 0.5)},
        (),
        "the maximum acceleration a_max follows a_max (1 + A sin(2 pi t / P + phase)): drift of a "
        "parameter the drifting_parameters extension keeps fixed (it lets only tau wander), so "
        "out of reach; measured to see what criticize says instead",
    ),
    "speed_power_noise": Mechanism(
        "noise_growth",
        "--",
        {"small": (0.2, 0.5), "medium": (0.5, 1.0), "large": (1.0, 2.0)},
        ("speed_dependent_noise",),
        "the noise sd is sigma (1 + c (v / 10 m/s)^p) with the power p uniform on 1.5-2.5 per "
        "driver (the extension's form is linear in v)",
    ),
    "video_position_noise": Mechanism(
        "position_noise_m",
        "m",
        {"small": (0.003, 0.01), "medium": (0.01, 0.03), "large": (0.03, 0.1)},
        ("measurement_noise",),
        "white noise on every recorded position, as video extraction has it; the written speeds "
        "are central differences of the noisy positions (floored at 0), accelerations differences "
        "of those speeds, headways differences of the noisy positions (the extension assumes exact "
        "speeds and gaps)",
    ),
    "two_leader_anticipation": Mechanism(
        "weight",
        "--",
        {"small": (0.1, 0.3), "medium": (0.3, 0.5), "large": (0.5, 0.8)},
        ("second_leader_anticipation",),
        "the approach term of the desired gap uses a weighted closing speed "
        "(1 - w)(v - v_1) + w (v - v_2) toward the leader and the vehicle two ahead (the "
        "extension blends two whole IDM accelerations instead)",
    ),
    "cut_in_relaxation": Mechanism(
        "relaxation",
        "--",
        {"small": (0.2, 0.4), "medium": (0.4, 0.7), "large": (0.7, 0.95)},
        ("cut_in_overreaction",),
        "after a vehicle cuts in, the driver accepts a shorter gap: time gap and jam distance "
        "scaled by 1 - eta exp(-t / t_r), t_r uniform on 4-10 s (relaxation, as in Schakel et "
        "al. 2012); the plain IDM over-reacts to the cut-in, the extension's cure is the "
        "constant-acceleration heuristic",
    ),
    "leader_acceleration_response": Mechanism(
        "gain",
        "--",
        {"small": (0.1, 0.25), "medium": (0.25, 0.5), "large": (0.5, 0.8)},
        ("leader_acceleration_anticipation",),
        "the driver adds gain times the leader's acceleration as it perceives it to the IDM "
        "acceleration: the leader's actual acceleration on the sub-steps through a first-order "
        "lag of time constant uniform on 0.2-0.5 s per driver (the extension adds the backward "
        "difference of the recorded leader speed over the last sample instead)",
    ),
    "position_smoothing": Mechanism(
        "smoothing_width_s",
        "s",
        {"small": (0.05, 0.1), "medium": (0.1, 0.2), "large": (0.2, 0.4)},
        (),
        "the recording, not the drivers: every vehicle's positions are smoothed by a symmetric "
        "exponential moving average of width T (weights exp(-|t' - t| / T), cut at 5 T; beyond "
        "the record's ends the positions are continued by reflection through the end point), as "
        "trajectory reconstructions smooth video positions; speeds are central differences of "
        "the smoothed positions (floored at 0), accelerations differences of those speeds, "
        "headways differences of the smoothed positions. A processing artefact, which no cause "
        "names: out of reach, measured to see whether criticize adopts a driver-behaviour "
        "extension on it",
    ),
    "approach_braking": Mechanism(
        "gain_per_s",
        "1/s",
        {"small": (0.1, 0.2), "medium": (0.2, 0.4), "large": (0.4, 0.8)},
        ("state_correction",),
        "while closing in on the leader faster than an onset speed (uniform on 0-1 m/s per "
        "driver), the driver brakes gain_per_s times the excess closing speed beyond the IDM "
        "acceleration: a one-sided ramp in the perceived closing speed, which the IDM's own "
        "approach term does not have; the state_correction extension approximates it with a "
        "tanh of the closing speed, two-sided, among other features (criticize screens it on "
        "request)",
    ),
}


def right_verdicts(mechanisms: tuple[str, ...]) -> tuple[str, ...]:
    """Verdicts that count as right for data with these mechanisms (any of theirs; none: none)."""
    if not mechanisms:
        return (NULL,)
    return tuple(v for m in mechanisms for v in MECHANISMS[m].verdicts)
