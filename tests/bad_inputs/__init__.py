"""Builders of small, physically consistent input files for every reader, and mutations of them.

Each builder writes into a folder and returns the path to read plus the figures it put in (so a
test compares what the reader returns with what was written, never with the reader's own output).
Speeds vary so that positions, speeds and gaps can be checked against each other; every file is
long enough (>= 10 steps, > 20 m of motion) for the validation layer's unit and rate checks.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

FT = 0.3048
NGSIM_COLUMNS = [
    "Vehicle_ID",
    "Frame_ID",
    "Total_Frames",
    "Global_Time",
    "Local_X",
    "Local_Y",
    "v_Length",
    "v_Width",
    "v_Class",
    "v_Vel",
    "v_Acc",
    "Lane_ID",
    "Preceding",
    "Following",
    "Space_Headway",
    "Time_Headway",
]


def speeds(n: int, base: float, amplitude: float, phase: float) -> np.ndarray:
    """A smooth speed profile (period ~2.5 s at 10 Hz), so leaders and followers close in and
    fall back."""
    return base + amplitude * np.sin(np.arange(n) / 4 - phase)


def integrate(v: np.ndarray, dt: float, start: float) -> np.ndarray:
    return start + np.r_[0.0, np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)]


# --- NGSIM raw (feet) ----------------------------------------------------------------------------


def ngsim_table(
    n: int = 100, *, ids=(1, 2), frame_step: int = 1, lengths=(15.0, 14.0), first_frame=100
) -> pd.DataFrame:
    """Cars in lane 2, each following the one before (feet, ft/s); Space_Headway is front to
    front, exactly the positions' difference."""
    rows = []
    fronts = []
    for index, vehicle in enumerate(ids):
        v = speeds(n, 45.0, 15.0, index)
        y = integrate(v, 0.1 * frame_step, 600.0 - 120.0 * index)
        fronts.append(y)
        for k in range(n):
            rows.append(
                {
                    "Vehicle_ID": vehicle,
                    "Frame_ID": first_frame + frame_step * k,
                    "Total_Frames": n,
                    "Global_Time": 1_113_433_135_300 + 100 * frame_step * k,
                    "Local_X": 18.0,
                    "Local_Y": y[k],
                    "v_Length": lengths[index % len(lengths)],
                    "v_Width": 6.0,
                    "v_Class": 2,
                    "v_Vel": v[k],
                    "v_Acc": 0.5,
                    "Lane_ID": 2,
                    "Preceding": ids[index - 1] if index else 0,
                    "Following": ids[index + 1] if index + 1 < len(ids) else 0,
                    "Space_Headway": fronts[index - 1][k] - y[k] if index else 0.0,
                    "Time_Headway": 1.0 if index else 0.0,
                }
            )
    return pd.DataFrame(rows, columns=NGSIM_COLUMNS)


def write_ngsim(folder, table: pd.DataFrame, name: str = "trajectories-0400-0415.csv", **kw):
    path = folder / name
    table.to_csv(path, index=False, float_format="%.10g", **kw)
    return path


# --- NGSIM chains (m) ------------------------------------------------------------------------------


def chain_table(
    n: int = 80, ids=(11, 12, 13), *, dt: float = 0.1, base: float = 12.0, amplitude: float = 3.0
):
    """A chain of cars in metres; t1 from 0; Y front positions, 15 m apart at the start."""
    table = {"t1": np.round(np.arange(n) * dt, 6)}
    for i, vehicle in enumerate(ids, start=1):
        v = speeds(n, base, amplitude, i)
        table[f"ID{i}"] = vehicle
        table[f"Y{i}"] = np.round(integrate(v, dt, 400.0 - 15.0 * i), 4)
        table[f"v{i}"] = np.round(v, 4)
        table[f"a{i}"] = 0.0
    return pd.DataFrame(table)


def write_chain(folder, table: pd.DataFrame, name: str = "11_12_13.csv", **kw):
    path = folder / name
    table.to_csv(path, index=False, **kw)
    return path


# --- OpenACC (SI) ----------------------------------------------------------------------------------

OPENACC_META = [
    "Date,5,3,2019",
    "Vehicle_order,Ford(S-Max),KIA(Niro)",
    "Number_of_vehicles,2",
    "ACC,1",
    "Distance_setting,min",
]


def openacc_table(n: int = 300, *, dt: float = 0.1, speed_factor: float = 1.0) -> pd.DataFrame:
    """Two cars; IVS1 is the bumper gap, changing exactly by the integrated relative speed."""
    v1 = speeds(n, 25.0, 3.0, 0.0)
    v2 = speeds(n, 25.0, 3.0, 0.5)
    gap = integrate(v1 - v2, dt, 30.0)
    return pd.DataFrame(
        {
            "Time": 4000.0 + np.arange(n) * dt,
            "Speed1": v1 * speed_factor,
            "E1": integrate(v1, dt, 0.0),
            "N1": 0.0,
            "Speed2": v2 * speed_factor,
            "E2": integrate(v2, dt, -34.5),
            "N2": 0.0,
            "IVS1": gap,
            "Driver1": "Human",
            "Driver2": "ACC",
        }
    )


def write_openacc(path, table: pd.DataFrame, *, meta=OPENACC_META, newline="\n", bom=False):
    text = "\n".join(meta) + ("\n" if meta else "") + table.to_csv(index=False)
    text = text.replace("\n", newline)
    path.write_bytes(("\ufeff" if bom else "").encode() + text.encode())
    return path


# --- highD (SI, 25 Hz) -----------------------------------------------------------------------------


def highd_tables(n: int = 50, *, ids=(1, 2), width=(4.0, 5.0)):
    """Two cars driving rightwards, car 2 behind car 1; x is the box's left edge."""
    rows = []
    for index, car in enumerate(ids):
        v = speeds(n, 30.0, 3.0, index)
        x = integrate(v, 1 / 25, 100.0 - 40.0 * index)
        for k in range(n):
            rows.append(
                {
                    "frame": k + 1,
                    "id": car,
                    "x": x[k],
                    "y": 10.0,
                    "width": width[index],
                    "height": 1.9,
                    "xVelocity": v[k],
                    "xAcceleration": 0.0,
                    "precedingId": ids[index - 1] if index else 0,
                    "laneId": 5,
                }
            )
    tracks = pd.DataFrame(rows)
    meta = pd.DataFrame({"id": list(ids), "width": list(width), "drivingDirection": 2})
    recording = pd.DataFrame({"id": [7], "frameRate": [25]})
    return tracks, meta, recording


def write_highd(folder, tracks, meta, recording, prefix: str = "07"):
    tracks.to_csv(folder / f"{prefix}_tracks.csv", index=False)
    meta.to_csv(folder / f"{prefix}_tracksMeta.csv", index=False)
    recording.to_csv(folder / f"{prefix}_recordingMeta.csv", index=False)
    return folder / f"{prefix}_tracks.csv"


# --- INTERACTION ---------------------------------------------------------------------------------

OSM_NODES = [
    (1, 0, 0),
    (2, 400, 0),
    (3, 0, 3.5),
    (4, 400, 3.5),
]


def osm_text(*, nodes=None, extra_way_ref: int | None = None, drop_lat: int | None = None) -> str:
    """A one-lanelet map (eastbound, 400 m) in lat/lon-free local coordinates."""
    lines = ['<?xml version="1.0"?>', '<osm version="0.6">']
    for node_id, x, y in nodes or OSM_NODES:
        lat = "" if node_id == drop_lat else ' lat="0"'
        tags = (
            "" if node_id == drop_lat else f'<tag k="local_x" v="{x}"/><tag k="local_y" v="{y}"/>'
        )
        lines.append(f'  <node id="{node_id}"{lat} lon="0">{tags}</node>')
    lines.append('  <way id="10"><nd ref="1"/><nd ref="2"/></way>')
    extra = f'<nd ref="{extra_way_ref}"/>' if extra_way_ref is not None else ""
    lines.append(f'  <way id="11"><nd ref="3"/><nd ref="4"/>{extra}</way>')
    lines.append(
        '  <relation id="20"><member type="way" ref="11" role="left"/>'
        '<member type="way" ref="10" role="right"/><tag k="type" v="lanelet"/></relation>'
    )
    lines.append("</osm>")
    return "\n".join(lines) + "\n"


def interaction_table(n: int = 40, *, ids=(1, 2), lengths=(4.0, 5.0)) -> pd.DataFrame:
    rows = []
    for index, track in enumerate(ids):
        v = speeds(n, 10.0, 2.0, index)
        x = integrate(v, 0.1, 80.0 - 20.0 * index)
        for k in range(n):
            rows.append(
                {
                    "track_id": track,
                    "frame_id": k + 1,
                    "timestamp_ms": 100 * (k + 1),
                    "agent_type": "car",
                    "x": x[k],
                    "y": 1.75,
                    "vx": v[k],
                    "vy": 0.0,
                    "psi_rad": 0.0,
                    "length": lengths[index],
                    "width": 1.8,
                }
            )
    return pd.DataFrame(rows)


def write_interaction(folder, table: pd.DataFrame, osm: str | None = None):
    (folder / "map.osm").write_text(osm if osm is not None else osm_text())
    path = folder / "vehicle_tracks_001.csv"
    table.to_csv(path, index=False)
    return path


# --- merge episodes (m) ----------------------------------------------------------------------------


def merge_table(n: int = 60, episodes=(4,)) -> pd.DataFrame:
    """Ego slowing from 12 m/s towards the lane end; V5 ahead on the ramp, V3 ahead on the main
    lane; other slots absent (sentinel)."""
    parts = []
    for episode in episodes:
        ego_v = speeds(n, 12.0, 2.0, 0.0)
        lead_v = speeds(n, 12.0, 2.0, 1.0)
        dist = 300.0 - integrate(ego_v, 0.1, 0.0)
        lead_d = integrate(lead_v - ego_v, 0.1, 25.0)
        table = {
            "episode": episode,
            "t_s": np.round(np.arange(n) * 0.1, 1),
            "ego_v_mps": ego_v,
            "ego_a_mps2": 0.0,
            "ego_dist_to_accel_lane_end_m": dist,
        }
        for i in (1, 2, 3, 4, 5):
            table[f"d_V{i}_m"] = lead_d if i in (3, 5) else 100.0
            table[f"dv_V{i}_mps"] = (lead_v - ego_v) if i in (3, 5) else 30.0
        table["action"] = 1
        parts.append(pd.DataFrame(table))
    return pd.concat(parts, ignore_index=True)


def write_merge(folder, table: pd.DataFrame, **kw):
    path = folder / "dataset_with_episode_ids.csv"
    table.to_csv(path, index=False, **kw)
    return path


# --- column-mapped vehicles (declared units) ---------------------------------------------------

VEHICLE_MAP = {"vehicle_id": "car", "t": "time", "x": "pos", "v": "speed", "leader_id": "lead"}


def vehicles_table(n: int = 100, *, ids=("a", "b"), dt: float = 0.1, with_length=True):
    """Cars in metres, ``b`` following ``a`` 20 m behind (front positions)."""
    rows = []
    for index, car in enumerate(ids):
        v = speeds(n, 15.0, 3.0, index)
        x = integrate(v, dt, 200.0 - 20.0 * index)
        for k in range(n):
            row = {
                "car": car,
                "time": round(k * dt, 6),
                "pos": x[k],
                "speed": v[k],
                "lead": ids[index - 1] if index else "",
            }
            if with_length:
                row["len"] = 4.5
            rows.append(row)
    return pd.DataFrame(rows)


def write_vehicles(folder, table: pd.DataFrame, name: str = "cars.csv", **kw):
    path = folder / name
    table.to_csv(path, index=False, **kw)
    return path
