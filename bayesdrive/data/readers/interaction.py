"""INTERACTION dataset tracks (``vehicle_tracks_XXX.csv``) on their lanelet2 map (``.osm``).

Units (:data:`UNITS`): ``x``, ``y``, ``length``, ``width`` in m, ``vx``, ``vy`` in m/s,
``timestamp_ms`` in ms, 10 Hz. Track columns: ``track_id, frame_id, timestamp_ms, agent_type, x,
y, vx, vy, psi_rad, length, width``; ``x``/``y`` is the vehicle CENTRE in the map's local metric
frame.

The map's nodes carry latitude/longitude; they are projected the way the INTERACTION tools do
(UTM of the zone containing the origin, minus the origin's UTM coordinates; origin (0, 0) by
default, as in the dataset's scripts). Nodes with ``local_x``/``local_y`` tags use those directly.

Lanes: every relation tagged ``type=lanelet`` with a ``left`` and ``right`` way. Its centreline is
the average of the two bounds resampled at equal arc-length fractions; its direction is the one
that puts the ``left`` bound on the left (lanelet2 allows bounds drawn against the direction of
travel). Each sample is projected onto the nearest centreline among the lanelets whose direction
agrees with the vehicle's heading (``psi_rad``), falling back to the nearest overall:
``lane_id`` = lanelet id, ``s`` = arc length along it. ``x = s + length/2`` (front bumper) so the
schema's gap identity holds. Leader = the nearest vehicle ahead on the same lanelet at the same
time; ``gap = (s_leader - length_leader/2) - (s + length/2)``. ``v = hypot(vx, vy)``; no
acceleration in the format (NaN).

Limitations (documented, not handled): lanelet successor/predecessor chains are not followed, so
a vehicle moving into the next lanelet restarts its ``x`` at that lanelet's start and sees no
leader beyond its lanelet's end; leaders in neighbouring or merging lanelets are not considered;
overlapping lanelets (intersections) are resolved only by heading and distance. One scene per
track file (scene id = file stem), vehicle ids ``"<stem>:<track_id>"``.
"""

from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from bayesdrive.data.errors import DataError
from bayesdrive.data.readers._common import (
    FileFormat,
    Notes,
    finish_parts,
    integer_ids,
    make_tracks,
    read_checked_table,
    require_regular_file,
    snap_to_grid,
    time_steps,
)
from bayesdrive.data.trajectories import Trajectories

__all__ = ["COLUMNS", "DT", "UNITS", "Lanelet", "read_interaction", "read_lanelets", "utm_xy"]

log = logging.getLogger(__name__)

FORMAT = "interaction"
DT = 0.1
UNITS = {"x/y/length/width": "m (vehicle centre)", "vx/vy": "m/s", "timestamp_ms": "ms"}
COLUMNS = [
    "track_id",
    "frame_id",
    "timestamp_ms",
    "agent_type",
    "x",
    "y",
    "vx",
    "vy",
    "psi_rad",
    "length",
    "width",
]
NUMERIC = ["frame_id", "timestamp_ms", "x", "y", "vx", "vy", "psi_rad", "length"]
SCHEMA_NAMES = {"vehicle_id": "track_id", "t": "timestamp_ms", "x": "x/y", "v": "vx/vy"}
FILE_FORMAT = FileFormat(FORMAT, DT, SCHEMA_NAMES)
# Centrelines are densified to this spacing for the nearest-point search, then refined exactly.
SEARCH_SPACING_M = 0.5
CANDIDATES = 16
# A sample this far from every centreline (over five lane widths) is on no lane of the map: the
# map or its projection origin is not the tracks'.
OFF_MAP_M = 20.0


@dataclass(frozen=True)
class Lanelet:
    """A lanelet's centreline (m, in the direction of travel) and its cumulative arc length."""

    id: int
    centreline: np.ndarray  # (n, 2)
    s: np.ndarray  # (n,)
    half_width: float


def utm_xy(lat: np.ndarray, lon: np.ndarray, origin: tuple[float, float]) -> np.ndarray:
    """Local metric x/y: UTM (WGS84, zone of the origin) minus the origin's UTM coordinates.

    Krüger's series for the transverse Mercator projection (sub-millimetre within a zone), as the
    INTERACTION tools do with pyproj.
    """
    lat0, lon0 = origin
    zone = math.floor((lon0 + 180.0) / 6.0) + 1
    central = math.radians((zone - 1) * 6 - 180 + 3)
    a, f, k0 = 6378137.0, 1 / 298.257223563, 0.9996
    n = f / (2 - f)
    big_a = a / (1 + n) * (1 + n**2 / 4 + n**4 / 64)
    alpha = (n / 2 - 2 * n**2 / 3 + 5 * n**3 / 16, 13 * n**2 / 48 - 3 * n**3 / 5, 61 * n**3 / 240)
    c = 2 * math.sqrt(n) / (1 + n)

    def forward(lat_deg, lon_deg):
        phi = np.radians(np.asarray(lat_deg, dtype=float))
        lam = np.radians(np.asarray(lon_deg, dtype=float)) - central
        t = np.sinh(np.arctanh(np.sin(phi)) - c * np.arctanh(c * np.sin(phi)))
        xi = np.arctan2(t, np.cos(lam))
        eta = np.arctanh(np.sin(lam) / np.sqrt(1 + t**2))
        east = eta + sum(
            al * np.cos(2 * j * xi) * np.sinh(2 * j * eta) for j, al in enumerate(alpha, 1)
        )
        north = xi + sum(
            al * np.sin(2 * j * xi) * np.cosh(2 * j * eta) for j, al in enumerate(alpha, 1)
        )
        return k0 * big_a * east, k0 * big_a * north

    e, nn = forward(lat, lon)
    e0, n0 = forward(lat0, lon0)
    return np.column_stack([e - e0, nn - n0])


def read_lanelets(path: str | Path, *, origin: tuple[float, float] = (0.0, 0.0)) -> list[Lanelet]:
    """Parse a lanelet2 ``.osm`` map into lanelet centrelines (see the module docstring)."""
    path = Path(path)
    require_regular_file(path)
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise DataError(f"{path}: cannot read the lanelet2 map ({exc})") from None
    ids, lats, lons, local = [], [], [], {}
    for node in root.iter("node"):
        tags = {t.get("k"): t.get("v") for t in node.iter("tag")}
        node_id = _map_number(path, node, "id", int)
        if "local_x" in tags and "local_y" in tags:
            local[node_id] = tuple(
                _map_number(path, node, key, float, tags[key]) for key in ("local_x", "local_y")
            )
        else:
            ids.append(node_id)
            lats.append(_map_number(path, node, "lat", float))
            lons.append(_map_number(path, node, "lon", float))
    points = dict(local)
    if ids:
        xy = utm_xy(np.array(lats), np.array(lons), origin)
        points.update(zip(ids, map(tuple, xy), strict=True))
    ways = {}
    for way in root.iter("way"):
        refs = [_map_number(path, nd, "ref", int) for nd in way.iter("nd")]
        unknown = [r for r in refs if r not in points]
        if unknown:
            raise DataError(
                f"{path}: way {way.get('id')} refers to node {unknown[0]}, which is not in the map"
            )
        if len(refs) < 2:
            raise DataError(f"{path}: way {way.get('id')} has {len(refs)} node(s); a bound needs 2")
        ways[_map_number(path, way, "id", int)] = np.array([points[r] for r in refs])
    lanelets = []
    for relation in root.iter("relation"):
        tags = {t.get("k"): t.get("v") for t in relation.iter("tag")}
        if tags.get("type") != "lanelet":
            continue
        roles = {m.get("role"): _map_number(path, m, "ref", int) for m in relation.iter("member")}
        if "left" not in roles or "right" not in roles:
            raise DataError(f"{path}: lanelet {relation.get('id')} lacks a left or right bound")
        try:
            left, right = ways[roles["left"]], ways[roles["right"]]
        except KeyError as exc:
            raise DataError(
                f"{path}: lanelet {relation.get('id')} names way {exc.args[0]}, not in the map"
            ) from None
        lanelets.append(_centreline(_map_number(path, relation, "id", int), left, right))
    if not lanelets:
        raise DataError(f"{path}: no lanelets (relations with type=lanelet) in the map")
    return lanelets


def _map_number(path: Path, element: ET.Element, key: str, kind, text: str | None = None):
    """``element``'s attribute ``key`` (or ``text``) as a number; a clear error when absent or bad."""
    text = element.get(key) if text is None else text
    try:
        return kind(text)
    except (TypeError, ValueError):
        what = "missing" if text is None else f"not a number: {text!r}"
        raise DataError(
            f"{path}: {element.tag} {element.get('id', '(no id)')}: {key} is {what}"
        ) from None


def _resample(line: np.ndarray, count: int) -> np.ndarray:
    steps = np.hypot(*np.diff(line, axis=0).T)
    s = np.r_[0.0, np.cumsum(steps)]
    wanted = np.linspace(0.0, s[-1], count)
    return np.column_stack([np.interp(wanted, s, line[:, 0]), np.interp(wanted, s, line[:, 1])])


def _centreline(lanelet_id: int, left: np.ndarray, right: np.ndarray) -> Lanelet:
    # Bounds drawn in opposite directions are first brought to the same direction.
    if np.dot(left[-1] - left[0], right[-1] - right[0]) < 0:
        right = right[::-1]
    length = max(
        np.hypot(*np.diff(left, axis=0).T).sum(), np.hypot(*np.diff(right, axis=0).T).sum()
    )
    count = max(len(left), len(right), int(np.ceil(length / SEARCH_SPACING_M)) + 1)
    left_r, right_r = _resample(left, count), _resample(right, count)
    centre = 0.5 * (left_r + right_r)
    heading = centre[-1] - centre[0]
    offset = (left_r - right_r).mean(axis=0)
    # Travel direction: the one that has the left bound on the left (positive cross product).
    if heading[0] * offset[1] - heading[1] * offset[0] < 0:
        centre = centre[::-1]
    s = np.r_[0.0, np.cumsum(np.hypot(*np.diff(centre, axis=0).T))]
    half_width = float(np.median(np.hypot(*(left_r - right_r).T)) / 2)
    return Lanelet(lanelet_id, centre, s, half_width)


def _project(lanelets: list[Lanelet], xy: np.ndarray, heading: np.ndarray):
    """Lanelet id, arc length and lateral distance of each point (see the module docstring)."""
    owner = np.concatenate([np.full(len(ll.s) - 1, k) for k, ll in enumerate(lanelets)])
    starts = np.concatenate([ll.centreline[:-1] for ll in lanelets])
    ends = np.concatenate([ll.centreline[1:] for ll in lanelets])
    s0 = np.concatenate([ll.s[:-1] for ll in lanelets])
    seg = ends - starts
    seg_len = np.hypot(*seg.T)
    direction = seg / np.where(seg_len > 0, seg_len, 1.0)[:, None]
    tree = cKDTree(0.5 * (starts + ends))
    k = min(CANDIDATES, len(starts))
    _, nearest = tree.query(xy, k=k)
    nearest = nearest.reshape(len(xy), k)
    rel = xy[:, None, :] - starts[nearest]
    along = np.clip(np.einsum("nkd,nkd->nk", rel, direction[nearest]), 0.0, seg_len[nearest])
    foot = starts[nearest] + along[..., None] * direction[nearest]
    dist = np.hypot(*(xy[:, None, :] - foot).transpose(2, 0, 1))
    agrees = (
        np.cos(heading)[:, None] * direction[nearest][..., 0]
        + np.sin(heading)[:, None] * direction[nearest][..., 1]
    ) >= 0
    penalised = np.where(agrees, dist, dist + 1e6)  # prefer lanelets in the heading's direction
    best = np.argmin(penalised, axis=1)
    rows = np.arange(len(xy))
    segment = nearest[rows, best]
    lane = np.array([lanelets[i].id for i in owner[segment]])
    s = s0[segment] + along[rows, best]
    lateral = dist[rows, best]
    half = np.array([lanelets[i].half_width for i in owner[segment]])
    return lane, s, lateral, half


def read_interaction(
    path: str | Path,
    *,
    map_path: str | Path | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
) -> Trajectories:
    """Read ``vehicle_tracks_*.csv`` (a file, or a folder with them) on a lanelet2 map.

    ``map_path`` defaults to the only ``.osm`` file in the tracks' folder.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    folder = path if path.is_dir() else path.parent
    if not path.is_dir():
        require_regular_file(path)
    files = (
        [path]
        if not path.is_dir()
        else sorted(f for f in folder.glob("vehicle_tracks_*.csv") if f.is_file())
    )
    if not files:
        raise DataError(f"{path}: no INTERACTION track files (vehicle_tracks_*.csv)")
    if map_path is None:
        maps = sorted(f for f in folder.glob("*.osm") if f.is_file())
        if len(maps) != 1:
            raise DataError(
                f"{folder}: need exactly one lanelet2 .osm map next to the tracks (found "
                f"{len(maps)}); pass map_path="
            )
        map_path = maps[0]
    lanelets = read_lanelets(map_path, origin=origin)
    notes = Notes(log)
    notes.assume(
        f"INTERACTION: positions are arc lengths along lanelet centrelines of {Path(map_path).name} "
        f"({len(lanelets)} lanelets, UTM projection about origin {origin}); x = front bumper; "
        "lanelet successors not followed (x restarts in each lanelet); no acceleration in format"
    )
    parts = [_read_file(f, lanelets, Path(map_path), notes) for f in files]
    return finish_parts(
        parts,
        FILE_FORMAT,
        path,
        notes,
        extra_inputs=[Path(map_path)],
    )


def _read_file(path: Path, lanelets: list[Lanelet], map_path: Path, notes: Notes):
    frame = read_checked_table(
        path,
        COLUMNS,
        NUMERIC,
        fmt="INTERACTION vehicle_tracks",
        notes=notes,
        text_columns=["track_id"],
    )
    steps = snap_to_grid(frame["timestamp_ms"] / 1000.0, DT, frame, column="timestamp_ms")
    xy = frame[["x", "y"]].to_numpy()
    lane, s, lateral, half = _project(lanelets, xy, frame["psi_rad"].to_numpy())
    off_map = lateral > OFF_MAP_M
    if off_map.any():
        first = int(np.argmax(off_map))
        raise DataError(
            f"{path}, row {frame['_row'].iloc[first]}, columns 'x', 'y': track "
            f"{frame['track_id'].iloc[first]} lies {lateral[first]:.0f} m from every lanelet of "
            f"{map_path.name} (more than {OFF_MAP_M:g} m: on no lane of it; "
            f"{int(off_map.sum())} such row(s)); is it the map of these tracks, with the right "
            "origin?"
        )
    outside = lateral > half + 0.5
    if outside.any():
        notes.assume(
            f"{path.name}: {int(outside.sum())} sample(s) lie outside every lanelet (more than "
            "half a lane width from any centreline); assigned to the nearest lanelet",
            warn=True,
        )
    length = frame["length"].to_numpy()
    ids = path.stem + ":" + pd.Series(integer_ids(frame, "track_id"))
    work = pd.DataFrame(
        {"vehicle_id": ids, "k": steps, "lane": lane, "s": s, "length": length}
    ).reset_index()
    work = work.sort_values(["k", "lane", "s"], kind="stable")
    same = (work["k"].shift(-1) == work["k"]) & (work["lane"].shift(-1) == work["lane"])
    leader = work["vehicle_id"].shift(-1).where(same)
    gap = (work["s"].shift(-1) - work["length"].shift(-1) / 2) - (work["s"] + work["length"] / 2)
    work["leader"] = leader
    work["gap"] = gap.where(same)
    work = work.sort_values("index")
    tracks = make_tracks(
        vehicle_id=ids.to_numpy(),
        t=time_steps(steps, DT),
        x=s + length / 2,
        v=np.hypot(frame["vx"].to_numpy(), frame["vy"].to_numpy()),
        lane_id=lane,
        leader_id=work["leader"].to_numpy(),
        gap=work["gap"].to_numpy(),
        length=length,
        row=frame["_row"].to_numpy(),
        file=str(path),
    )
    scenes = pd.DataFrame({"scene_id": path.stem, "vehicle_id": pd.unique(tracks["vehicle_id"])})
    return tracks, scenes
