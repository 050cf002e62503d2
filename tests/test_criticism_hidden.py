"""Hidden-effect tests: data with one known effect, written as NGSIM raw files and read back
through the real reader; ``criticize`` must name the effect, and on data without one say "none".

The effect sizes are those the detection study (benchmarks/bench_detection.py, table in
reports/criticism/detection.md) detects in at least 95% of its replications at this scenario and
these settings, so a correct implementation passes these fixed-seed cases; one seed per cause,
fixed in advance (not chosen by outcome).
"""

from __future__ import annotations

import jax
import pytest

from bayesdrive.criticism.criticize import DETECTION_CONFIG, criticize
from bayesdrive.criticism.generator import DETECTION_SCENARIO, generate
from bayesdrive.data.readers import read
from bayesdrive.drivers.extensions import NO_CAUSE

SEED = 2026
# Effect sizes (the extension parameter's range) detected >= 95% in the detection study.
CI_SIZES = {
    "reaction_delay": (0.6, 0.9),
    "autocorrelated_noise": (0.6, 0.9),
    "speed_dependent_noise": (0.1, 0.2),
    "second_leader_anticipation": (0.5, 0.8),
    "cut_in_overreaction": (0.9, 1.0),
}


@pytest.mark.parametrize("cause", [*CI_SIZES, NO_CAUSE])
def test_criticize_names_the_hidden_cause(cause, tmp_path):
    path = tmp_path / f"{cause}.csv"
    truth = generate(
        jax.random.key(SEED), path, cause, effect_range=CI_SIZES.get(cause), **DETECTION_SCENARIO
    )
    traj = read(path, format="ngsim_raw")
    result = criticize(traj, seed=SEED, config=DETECTION_CONFIG)
    report = result.report
    gains = {c["name"]: c["gain"] for c in report["causes"]}
    assert report["verdict"] == cause, (truth.cause, gains)
    if cause != NO_CAUSE:
        assert gains[cause]["significant"] and gains[cause]["elpd"] > 0
