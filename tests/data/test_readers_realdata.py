"""Readers on the real data in ../shared/data (hand-checked figures) and ../shared/holdout (load
only: held-out data are for evaluation, so no numbers are asserted on them)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from bayesdrive.data.catalog import DATASETS, LAYOUTS
from bayesdrive.data.readers import read
from bayesdrive.data.readers.ngsim_chains import align_copies
from bayesdrive.data.readers.openacc import enu_consistency
from bayesdrive.data.trajectories import TRACK_COLUMNS, summary

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def chains(data_dir):
    return read(data_dir / "ngsim_i80_chains")


@pytest.fixture(scope="module")
def vicolungo(data_dir):
    return read(data_dir / "openacc_vicolungo")


# --- NGSIM I-80 chains -------------------------------------------------------------------------


def test_chains_summary(chains):
    info = summary(chains)
    assert info["format"] == "ngsim_chains"
    assert info["vehicles"] == 210
    assert info["scenes"] == 75
    assert info["dt_s"] == pytest.approx(0.1)
    assert set(chains.tracks["driver"]) == {"unknown"}
    assert chains.tracks["length"].eq(4.5).all()
    assert list(chains.tracks.columns) == list(TRACK_COLUMNS)


def same_t(times: pd.Series, t: float) -> np.ndarray:
    """Times equal to ``t`` (absolute tolerance: chain times run into the thousands of s)."""
    return np.abs(times.to_numpy() - t) < 1e-6


def at_sequence(rows: pd.DataFrame, speeds: list[float]) -> int:
    """Index (in ``rows``) where the speed sequence ``speeds`` starts; asserts it is unique."""
    v = rows["v"].to_numpy()
    hits = [i for i in range(len(v) - len(speeds) + 1) if np.allclose(v[i : i + 3], speeds)]
    assert len(hits) == 1
    return hits[0]


def test_chains_values_by_hand(chains):
    # 124_136_140_146_162_164.csv, first data row: 0.0,124,48.2567,7.3239,0.6303,136,34.5104,...
    # and 220 rows later (t1 = 22.0): 124 at v 3.424, a -0.1625.
    car124 = chains.vehicle("124").reset_index(drop=True)
    i = at_sequence(car124, [7.3239, 7.3866, 7.4512])
    start = car124.loc[i]
    assert start["a"] == pytest.approx(0.6303)
    end = car124[same_t(car124["t"], start["t"] + 22.0)].iloc[0]
    assert end["v"] == pytest.approx(3.424) and end["a"] == pytest.approx(-0.1625)
    assert end["x"] - start["x"] == pytest.approx(222.0899 - 48.2567, abs=2e-4)
    car136 = chains.vehicle("136")
    same_time = car136[same_t(car136["t"], start["t"])].iloc[0]
    assert same_time["v"] == pytest.approx(7.7673)
    assert same_time["leader_id"] == "124"
    # Bumper gap = front-to-front (48.2567 - 34.5104) minus the assumed 4.5 m.
    assert same_time["gap"] == pytest.approx(48.2567 - 34.5104 - 4.5, abs=2e-4)


def test_chain_copies_agree_after_alignment(data_dir):
    folder = data_dir / "ngsim_i80_chains"
    a = pd.read_csv(folder / "115_124_136_140_146_162.csv")
    b = pd.read_csv(folder / "124_136_140_146_162_164.csv")
    shifts = set()
    for slot_a, slot_b in ((2, 1), (3, 2), (4, 3), (5, 4), (6, 5)):
        assert a[f"ID{slot_a}"][0] == b[f"ID{slot_b}"][0]
        match = align_copies(
            a[f"v{slot_a}"].to_numpy(),
            a[f"Y{slot_a}"].to_numpy(),
            b[f"v{slot_b}"].to_numpy(),
            b[f"Y{slot_b}"].to_numpy(),
        )
        assert match is not None and match.overlap > 100
        assert match.y_residual < 1e-4  # Y is written with 4 decimals
        shifts.add(match.shift)
        lo, hi = max(0, match.shift), min(len(a), len(b) + match.shift)
        np.testing.assert_array_equal(
            a[f"v{slot_a}"][lo:hi].to_numpy(), b[f"v{slot_b}"][lo - match.shift : hi - match.shift]
        )
    assert len(shifts) == 1  # one time shift per pair of files


def test_chains_every_vehicle_once_and_components(chains):
    assert not chains.tracks.duplicated(["vehicle_id", "t"]).any()
    per_file = chains.scenes.groupby("scene_id")["component"].nunique()
    assert per_file.eq(1).all()
    assert chains.scenes["component"].nunique() == 25
    assert any("copies agree to max |dx| = 9.9e-05" in n for n in chains.notes)
    # Within a component every file's leader-follower gap uses one position axis.
    with_leader = chains.tracks[chains.tracks["leader_id"].notna()]
    leaders = chains.tracks.set_index(["vehicle_id", "t"])
    lead_x = leaders.loc[list(zip(with_leader["leader_id"], with_leader["t"], strict=True)), "x"]
    np.testing.assert_allclose(
        with_leader["gap"], lead_x.to_numpy() - with_leader["x"] - 4.5, atol=1e-9
    )


def test_chains_flag_the_three_known_negative_gap_chains(chains):
    flagged = chains.flags[chains.flags["kind"] == "negative_gap"]
    tracks = chains.tracks.set_index(["vehicle_id", "t"])
    pairs = {
        (v, tracks.loc[(v, t), "leader_id"])
        for v, t in zip(flagged["vehicle_id"], flagged["t"], strict=True)
    }
    # 124_136_140_146_162_164: 164 behind 162; 46_45_...: 45 behind 46; 202_210_..._234_252.
    assert pairs == {("164", "162"), ("45", "46"), ("252", "234")}
    # By hand, 46_45_53_68_72_81.csv row 2: 46 at v 9.2778, 45 at v 6.3481 and
    # Y1 - Y2 = 67.0979 - 63.3133, less than the assumed 4.5 m.
    car46 = chains.vehicle("46")
    start = car46[np.isclose(car46["v"], 9.2778) & np.isclose(car46["a"], -1.5344)]["t"].iloc[0]
    car45 = chains.vehicle("45")
    row = car45[same_t(car45["t"], start)].iloc[0]
    assert row["v"] == pytest.approx(6.3481) and row["leader_id"] == "46"
    assert row["gap"] == pytest.approx(67.0979 - 63.3133 - 4.5, abs=2e-4)
    assert ((flagged["vehicle_id"] == "45") & same_t(flagged["t"], start)).any()


def test_single_chain_file(data_dir):
    traj = read(data_dir / "ngsim_i80_chains" / "46_45_53_68_72_81.csv")
    assert traj.vehicle_ids == ["45", "46", "53", "68", "72", "81"]
    assert traj.vehicle("46")["t"].iloc[0] == 0.0


# --- OpenACC Vicolungo -------------------------------------------------------------------------


def test_openacc_vicolungo_figures(vicolungo):
    assert vicolungo.scene_ids == [
        "JRC-VC_260219_part3",
        "JRC-VC_280219_part2",
        "JRC-VC_280219_part3",
    ]
    for scene in vicolungo.scene_ids:
        assert len(vicolungo.scene_vehicles(scene)) == 5
    drivers = vicolungo.tracks.groupby("vehicle_id")["driver"].unique().map(list).to_dict()
    assert drivers["JRC-VC_260219_part3:1"] == ["human"]
    for i in (2, 3, 4, 5):
        assert drivers[f"JRC-VC_260219_part3:{i}"] == ["acc"]
    for part in ("JRC-VC_280219_part2", "JRC-VC_280219_part3"):
        for i in range(1, 6):
            assert drivers[f"{part}:{i}"] == ["human"]
    assert vicolungo.dt == pytest.approx(0.1)
    assert not vicolungo.flags["kind"].eq("negative_gap").any()


def test_openacc_gap_is_ivs_and_x_is_integrated_speed(vicolungo, data_dir):
    raw = pd.read_csv(data_dir / "openacc_vicolungo" / "JRC-VC_280219_part2.csv", skiprows=5)
    # By hand, first data row: Time 380201.5, Speed1 22.469999243982787, IVS1 27.52853932150435,
    # IVS2 30.219001588375395.
    assert raw["Speed1"][0] == pytest.approx(22.469999243982787)
    lead = vicolungo.vehicle("JRC-VC_280219_part2:1")
    assert lead["v"].iloc[0] == pytest.approx(22.469999243982787)
    assert vicolungo.vehicle("JRC-VC_280219_part2:2")["gap"].iloc[0] == pytest.approx(
        27.52853932150435
    )
    assert vicolungo.vehicle("JRC-VC_280219_part2:3")["gap"].iloc[0] == pytest.approx(
        30.219001588375395
    )
    for i in (1, 2, 3, 4):
        follower = vicolungo.vehicle(f"JRC-VC_280219_part2:{i + 1}")
        np.testing.assert_array_equal(follower["gap"].to_numpy(), raw[f"IVS{i}"].to_numpy())
    speed = raw["Speed1"].to_numpy()
    integrated = np.r_[0, np.cumsum(0.5 * (speed[1:] + speed[:-1]) * 0.1)]
    np.testing.assert_allclose(lead["x"] - lead["x"].iloc[0], integrated, atol=1e-6)
    assert lead["t"].iloc[-1] == pytest.approx(374.3)


def test_openacc_integrated_position_vs_enu_path(data_dir):
    folder = data_dir / "openacc_vicolungo"
    for name, worst in (
        ("JRC-VC_280219_part2.csv", 0.01),
        ("JRC-VC_280219_part3.csv", 0.01),
        # Car 5 of this file has a 62 m GNSS jump at t ~ 5 s (ENU and IVS4 jump together).
        ("JRC-VC_260219_part3.csv", 0.02),
    ):
        check = enu_consistency(folder / name)
        assert len(check) == 5
        relative = (check["difference_m"] / check["integrated_m"]).abs()
        assert relative.max() < worst
        assert relative.median() < 0.005


def test_openacc_gap_jump_is_flagged(vicolungo):
    jumps = vicolungo.flags[vicolungo.flags["kind"] == "gap_jump"]
    first = jumps[jumps["vehicle_id"] == "JRC-VC_260219_part3:5"]
    assert first["t"].between(4.0, 5.5).all() and len(first) > 0


# --- merge episodes and INTERACTION fixture --------------------------------------------------


def test_merge_episodes_by_hand(data_dir):
    traj = read(data_dir / "ngsim_merge_episodes")
    assert len(traj.scene_ids) == 98
    assert traj.dt == pytest.approx(0.1)
    # dataset_with_episode_ids.csv, first data row: episode 0, t 0.0, ego v 11.9315,
    # dist 211.0080, d_V1 -54.6118, dv_V1 -0.4637, d_V2 -29.1415, V3..V5 = sentinel.
    ego = traj.vehicle("ep0_ego").iloc[0]
    assert ego["x"] == pytest.approx(-211.008) and ego["v"] == pytest.approx(11.9315)
    assert ego["a"] == pytest.approx(0.1975) and ego["leader_id"] is None
    v1 = traj.vehicle("ep0_V1").iloc[0]
    assert v1["x"] == pytest.approx(-211.008 - 54.6118)
    assert v1["v"] == pytest.approx(11.9315 - 0.4637)
    assert v1["gap"] == pytest.approx(-29.1415 + 54.6118 - 4.5)
    assert "ep0_V3" not in traj.vehicle_ids and "ep0_V5" not in traj.vehicle_ids
    assert traj.vehicle("ep0_V2")["leader_id"].isna().all()  # V3 absent in episode 0
    npy = read(data_dir / "ngsim_merge_episodes" / "dataset.npy")
    assert len(npy.scene_ids) == 98 and len(npy.tracks) == len(traj.tracks)


def test_interaction_fixture(data_dir):
    traj = read(data_dir / "interaction_fixture")
    assert len(traj.vehicle_ids) == 2
    one, two = (traj.vehicle(f"vehicle_tracks_000:{i}") for i in (1, 2))
    assert one["lane_id"].eq(20).all() and two["lane_id"].eq(21).all()
    assert one["v"].eq(10.0).all() and two["v"].eq(10.0).all()
    # Track 1: centre x = 1..100 m on lanelet 20 starting at x = 1 m; front = s + 2 m.
    np.testing.assert_allclose(one["x"], one["t"] * 10.0 - 1.0 + 2.0, atol=1e-5)
    np.testing.assert_allclose(np.diff(two["x"]), 1.0, atol=1e-5)  # westbound, still forwards
    assert traj.tracks["leader_id"].isna().all()


# --- held-out folders: they load, nothing valid is rejected ------------------------------------


@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_holdout_folders_load(holdout_dir, name):
    traj = read(holdout_dir / name)
    assert len(traj.tracks) > 0 and len(traj.scene_ids) > 0
    assert traj.format == LAYOUTS[name].reader


# --- each data set's description against its data ---------------------------------------------


@pytest.mark.parametrize("name", sorted(DATASETS))
def test_documented_figures_match_the_data(request, data_dir, name):
    """The figures a description quotes from its source's documentation are what its reader finds
    (data sets for fitting only: nothing is measured on the held-out ones here)."""
    documented = DATASETS[name].documented
    assert documented, f"{name}: its description quotes no figure to check"
    # The two larger folders are already read by this module's fixtures.
    fixtures = {"ngsim_i80_chains": "chains", "openacc_vicolungo": "vicolungo"}
    if name in fixtures:
        traj = request.getfixturevalue(fixtures[name])
    else:
        traj = read(data_dir / name, format=DATASETS[name].format)
    info = summary(traj)
    assert {key: info[key] for key in documented} == pytest.approx(dict(documented))
