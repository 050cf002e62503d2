"""The report's highway table: the interval coverage beside the proper scores."""

import numpy as np

from bayesdrive.reports.paper_report import highway_table
from bayesdrive.simulation.metrics import (
    Observed,
    distribution_samples,
    scenario_metrics,
    summarize,
)
from bayesdrive.simulation.rollout import Rollout


def test_the_position_coverage_is_shown_and_older_results_show_a_dash():
    # One vehicle, 4 rollouts ending 2 behind, 1 behind, 1 ahead and 3 ahead of the observation:
    # PIT 0.5, inside both central intervals.
    ends = np.array([-2.0, -1.0, 1.0, 3.0])
    x = np.zeros((4, 1, 3))
    x[:, 0, -1] = ends
    rollout = Rollout(
        x=x,
        v=np.full((4, 1, 3), 10.0),
        gap=np.full((4, 1, 3), 5.0),
        dx=np.diff(x, axis=-1),
        collision=np.zeros((4, 1, 2), bool),
        hard_braking=np.zeros((4, 1, 2), bool),
        off_road=np.zeros((4, 1, 2), bool),
    )
    observed = Observed(
        x=np.zeros((1, 3)), v=np.full((1, 3), 10.0), gap=np.full((1, 3), 5.0),
        step_mask=np.ones(2), dt=0.1,
    )  # fmt: skip
    summary = summarize(
        [scenario_metrics("s", rollout, observed)], [distribution_samples(rollout, observed)]
    )
    assert summary["calibration_position"]["coverage_50"] == 1.0
    older = {k: v for k, v in summary.items() if k != "calibration_position"}
    table = highway_table({"new": summary, "older": older}).set_index("model")
    column = "50% / 90% interval covers the position at 5 s"
    assert table.loc["new", column] == "1.00 / 1.00"
    assert table.loc["older", column] == "-"
