"""Closed-loop simulation: scenarios from held-out data, rollouts, baselines and metrics.

The simulator itself is :func:`bayesdrive.simulation.rollout.rollout` (not re-exported here: the
name would hide its module).
"""

from bayesdrive.simulation.baselines import BASELINES, Policy, baseline_policy
from bayesdrive.simulation.metrics import evaluate_policy
from bayesdrive.simulation.rollout import scene_arrays
from bayesdrive.simulation.scenarios import merge_scenarios, platoon_scenarios

__all__ = [
    "BASELINES",
    "Policy",
    "baseline_policy",
    "evaluate_policy",
    "merge_scenarios",
    "platoon_scenarios",
    "scene_arrays",
]
