"""Followers written here in numpy for tests, sharing no code with the models they test."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from bayesdrive.data.trajectories import Trajectories
from bayesdrive.data.validate import validate_tracks

DT = 0.1


def single_lane(t, vehicles, source: str) -> Trajectories:
    """One lane, one scene: ``vehicles`` are (id, x, v, leader id or None, leader's x or None)
    sampled at times ``t``; bumper gaps for vehicles 4.5 m long."""
    rows = [
        pd.DataFrame(
            {
                "vehicle_id": vid,
                "t": t,
                "x": x,
                "v": v,
                "a": np.nan,
                "lane_id": 1,
                "leader_id": leader,
                "gap": (lead_x - 4.5 - x) if leader else np.full_like(t, np.nan),
                "length": 4.5,
                "driver": "human",
            }
        )
        for vid, x, v, leader, lead_x in vehicles
    ]
    tracks = validate_tracks(pd.concat(rows, ignore_index=True), source=source, dt=DT)
    scenes = pd.DataFrame({"scene_id": "s", "vehicle_id": [vehicle[0] for vehicle in vehicles]})
    return Trajectories(tracks=tracks, scenes=scenes, dt=DT, format="test", source=source)


def corrected_follower(
    closing_coefficient: float, seed: int, steps: int = 3000, pairs: int = 1
) -> Trajectories:
    """``pairs`` leader-follower pairs (pair i from seed ``seed + i``, 10 km apart): the IDM
    (v_des 30, d_min 2, tau 1, a_max 3, b_pref 2, delta 4) behind a leader whose speed swings
    14 +- 3 m/s with a 20 s period, plus ``closing_coefficient`` times tanh((v - v_lead) / 2 m/s)
    and white noise of sd 0.3 m/s^2 per 0.1 s step. Exact kinematics per step."""
    v_des, d_min, tau, a_max, b_pref = 30.0, 2.0, 1.0, 3.0, 2.0
    t = np.round(np.arange(steps + 1) * DT, 6)
    v_lead = 14.0 + 3.0 * np.sin(2 * np.pi * t / 20.0)
    travelled = np.concatenate([[0.0], np.cumsum(0.5 * (v_lead[1:] + v_lead[:-1]) * DT)])
    vehicles = []
    for pair in range(pairs):
        rng = np.random.default_rng(seed + pair)
        start = 10_000.0 * pair
        x_lead = start + 60.0 + travelled
        x, v = np.full(steps + 1, start), np.full(steps + 1, 14.0)
        for k in range(steps):
            gap = x_lead[k] - 4.5 - x[k]
            closing = v[k] - v_lead[k]
            wanted = d_min + max(0.0, v[k] * tau + v[k] * closing / (2 * math.sqrt(a_max * b_pref)))
            acc = a_max * (1 - (v[k] / v_des) ** 4 - (wanted / gap) ** 2)
            acc += closing_coefficient * math.tanh(closing / 2.0) + 0.3 * rng.standard_normal()
            x[k + 1] = x[k] + v[k] * DT + 0.5 * acc * DT**2
            v[k + 1] = v[k] + acc * DT
        vehicles += [
            (f"L{pair}", x_lead, v_lead, None, None),
            (f"F{pair}", x, v, f"L{pair}", x_lead),
        ]
    return single_lane(t, tuple(vehicles), source="corrected")
