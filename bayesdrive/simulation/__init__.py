"""Closed-loop simulation: scenarios from held-out data, rollouts, baselines and metrics."""
