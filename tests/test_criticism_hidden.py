"""Hidden-effect tests: data with one known effect, written as NGSIM raw files and read back
through the real reader; ``criticize`` must name the effect, and on data without one say "none".

The effect sizes are those the detection study (benchmarks/bench_detection.py, table in
reports/criticism/detection.md: 20 replications per cell, seeds 1..20) names correctly in at least
95% of its replications at this scenario and these settings: "large" for every cause, each
measured with the current sampler (moves until every particle has likely moved): 20 of 20 for
every cause, and the null named no cause in 20 of 20. One seed, 2026, outside the study's seeds
and fixed in advance (not chosen by outcome).
"""

from __future__ import annotations

import jax
import pytest

from bayesdrive.criticism.criticize import DETECTION_CONFIG, criticize
from bayesdrive.criticism.generator import DETECTION_SCENARIO, DETECTION_SIZES, generate
from bayesdrive.data.readers import read
from bayesdrive.drivers.extensions import NO_CAUSE

SEED = 2026
# The size whose detection rate in reports/criticism/detection.md is at least 0.95, per cause.
CI_SIZE = {cause: "large" for cause in DETECTION_SIZES}


@pytest.mark.parametrize("cause", [*CI_SIZE, NO_CAUSE])
def test_criticize_names_the_hidden_cause(cause, tmp_path):
    path = tmp_path / f"{cause}.csv"
    truth = generate(
        jax.random.key(SEED),
        path,
        cause,
        effect_range=DETECTION_SIZES[cause][CI_SIZE[cause]] if cause != NO_CAUSE else None,
        **DETECTION_SCENARIO,
    )
    traj = read(path, format="ngsim_raw")
    result = criticize(traj, seed=SEED, config=DETECTION_CONFIG)
    report = result.report
    gains = {c["name"]: c["gain"] for c in report["causes"]}
    assert report["verdict"] == cause, (truth.cause, gains)
    if cause != NO_CAUSE:
        assert gains[cause]["significant"] and gains[cause]["elpd"] > 0
