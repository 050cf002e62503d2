"""Hidden-effect tests: data with one known effect, written as NGSIM raw files and read back
through the real reader; ``criticize`` must name the effect, and on data without one say "none".

The effect sizes are those the detection study (benchmarks/bench_detection.py, table in
reports/criticism/detection.md: 20 replications per cell, seeds 1..20) names correctly in at least
95% of its replications at this scenario and these settings: "large" for every cause it backs. On
null data the study named no cause in 20 of 20 replications. The speed-dependent noise has no
such size (large 16/20, xlarge 18/20: one vehicle whose extension loses heavily on held-out data
sinks the test across 8 vehicles), so its case is skipped, visibly, until the criticism detects it
reliably. One seed, 2026, outside the study's seeds and fixed in advance (not chosen by outcome).
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
UNBACKED = "speed_dependent_noise"  # no size reaches 0.95 there (module docstring)
CI_SIZE = {cause: "large" for cause in DETECTION_SIZES if cause != UNBACKED}
SKIP_UNBACKED = pytest.mark.skip(
    reason="no size reaches 0.95 in reports/criticism/detection.md (large 0.80, xlarge 0.90)"
)


@pytest.mark.parametrize("cause", [*CI_SIZE, NO_CAUSE, pytest.param(UNBACKED, marks=SKIP_UNBACKED)])
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
