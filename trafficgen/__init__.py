"""An independent generator of car-following data with hidden effects, for testing
``bayesdrive criticize`` on data it did not make.

It imports nothing from ``bayesdrive`` (numpy only) and is not part of the bayesdrive wheel: the
tests import it from the repository root (``pythonpath`` in pyproject.toml's pytest settings), the
detection benchmark puts the root on ``sys.path``. Its own IDM, written from the equations and
integrated on ten sub-steps per 0.1 s sample (:mod:`.simulate`), drives platoons behind varied
head vehicles with cut-ins; each mechanism (:mod:`.mechanisms`) is a way drivers or recordings
differ from the plain IDM with white noise that is *not* the equation of any bayesdrive extension;
:mod:`.ngsim` writes the result as a US DOT NGSIM raw CSV, so ``criticize`` reads it through the
real reader.

Which verdicts count as right (cause names of ``bayesdrive.drivers.extensions``; two mechanisms at
once: a verdict right for either; no mechanism: ``none``):

============================  ================================  ====================================
mechanism                     right verdicts                    how (:data:`.mechanisms.MECHANISMS`)
============================  ================================  ====================================
perception_delay              reaction_delay                    gap and closing speed perceived
                                                                delay_s late, interpolated between
                                                                sub-steps
pedal_noise                   autocorrelated_noise              Ornstein-Uhlenbeck acceleration
                                                                error in continuous time
time_gap_drift                drifting_parameters               smooth sinusoidal drift of the time
                                                                gap
time_gap_switch               drifting_parameters               regime switch of the time gap (a
                                                                random walk of tau reaches it only
                                                                approximately)
acceleration_drift            out of reach                      drift of a_max: the extension lets
                                                                only tau wander
speed_power_noise             speed_dependent_noise             noise sd sigma (1 + c (v/10)^p), p
                                                                in 1.5-2.5
video_position_noise          measurement_noise                 noisy positions; speeds,
                                                                accelerations and headways
                                                                differenced from them
two_leader_anticipation       second_leader_anticipation        closing speed weighted over two
                                                                leaders
cut_in_relaxation             cut_in_overreaction               shorter accepted gap after a cut-in,
                                                                relaxing back over seconds
leader_acceleration_response  leader_acceleration_anticipation  the leader's acceleration through a
                                                                first-order lag, times a gain, added
position_smoothing            out of reach (a processing        the recording smooths positions by
                              artefact, which no cause names)   a symmetric exponential moving
                                                                average; speeds differenced from
                                                                them
approach_braking              state_correction (screened on     extra braking in proportion to the
                              request; a tanh basis             closing speed beyond an onset
                              approximating the ramp)
(none)                        none                              IDM with white noise per sample
============================  ================================  ====================================
"""

from __future__ import annotations

from pathlib import Path

from trafficgen.mechanisms import MECHANISMS, NULL, SIZES, Mechanism, right_verdicts
from trafficgen.ngsim import write_ngsim_raw
from trafficgen.simulate import Recording, simulate

__all__ = [
    "DETECTION_SCENARIO",
    "MECHANISMS",
    "NULL",
    "SIZES",
    "Mechanism",
    "Recording",
    "generate",
    "right_verdicts",
    "simulate",
    "write_ngsim_raw",
]

# The scenario of the detection study and of the CI tests it backs (same in both, so the table
# applies): two platoons of four followers, 40 s, eight cut-ins attempted per platoon.
DETECTION_SCENARIO = {"platoons": 2, "followers": 4, "duration_s": 40.0, "cut_ins": 8}


def generate(
    seed: int,
    path: str | Path,
    mechanisms: dict[str, tuple[float, float]] | None = None,
    **scenario,
) -> Recording:
    """Simulate (:func:`.simulate.simulate`) and write the NGSIM file; returns the recording."""
    recording = simulate(seed, mechanisms, **scenario)
    write_ngsim_raw(recording, path)
    return recording
