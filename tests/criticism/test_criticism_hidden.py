"""Hidden-effect tests on data bayesdrive did not make: the independent generator (``trafficgen``:
its own sub-stepped IDM, mechanisms that are not the extensions' equations) writes NGSIM raw
files, the real reader reads them, and ``criticize`` must give a right verdict (trafficgen's table,
reports/criticism/generator.md); on data without a mechanism it must say "none".

Cells: those the detection study (benchmarks/bench_detection.py, seeds 100001 on, fixed before
it ran; reports/criticism/detection.md) named right in 20 of 20 replications at library
65ad89982e02: null data (said none 20 of 20); an Ornstein-Uhlenbeck pedal error, a smooth drift
of the time gap and video-style measurement noise (noisy positions, speeds and headways
differenced from them), each at "large", and video-style noise at "small", 3-10 mm, each 20 of
20. Speed-dependent noise of a power form (large) is right 17 of 20 there, so it stays out of CI.
Two mechanisms at once are left to the study: no pair is named right 20 times in 20. These cells
were rerun on fresh seeds 130001-130020 (library 7e2a5195645e) and again, after the drift cause's
filtered forecast start, on 150001-150020 (library f1435fca9d52;
reports/criticism/detection_adoption.md): each time every mechanism cell was named right 20 of
20, and null data said none 18 of 20 (the other two flag a misfit no cause explains). The
table there holds every rerun since, one per change of the detector; the latest, at library
d0222453dc69 (seeds 200001-200020), names as the one before it in every replication.
Each test runs one round (a one-mechanism verdict is the first round's; the loop's later rounds
cost CI time and are measured in the study). One seed per cell, fixed before any of these tests
ran, outside the study's seed range (not chosen by outcome). Cells the study has not backed run
in the extended tier, as expected failures where the detector is known to name another cause.
"""

from __future__ import annotations

import pytest

from bayesdrive.criticism.criticize import DETECTION_CONFIG, criticize
from bayesdrive.data.readers import read
from trafficgen import DETECTION_SCENARIO, MECHANISMS, NULL, generate, right_verdicts

# "mechanism[ size]" -> (size, seed); seeds fixed in advance, one per cell.
CI_CELLS = {
    NULL: (NULL, 70001),
    "pedal_noise": ("large", 70003),
    "video_position_noise": ("large", 70008),
    "time_gap_drift": ("large", 70007),
    "video_position_noise small": ("small", 70010),
}
# Cells the study has not backed (no 20 of 20 at the current library), in the extended tier,
# with why each fails where it does (a strict xfail: a detector that comes to name it fails the
# test, so the cell moves up).
EXTENDED_CELLS = {
    "leader_acceleration_response": (
        "large",
        70012,
        "names drifting_parameters: its Kalman-filtered time gap gains more held-out than "
        "leader_acceleration_anticipation, both significant; so on development seeds 900001-2",
    )
}


@pytest.mark.slow
@pytest.mark.parametrize(
    "cell",
    [
        *CI_CELLS,
        *(
            pytest.param(
                cell, marks=[pytest.mark.extended, pytest.mark.xfail(strict=True, reason=why)]
            )
            for cell, (_, _, why) in EXTENDED_CELLS.items()
        ),
    ],
)
def test_criticize_names_the_hidden_mechanism(cell, tmp_path):
    size, seed = (CI_CELLS | EXTENDED_CELLS)[cell][:2]
    name = cell.split()[0]
    mechanisms = {} if name == NULL else {name: MECHANISMS[name].sizes[size]}
    path = tmp_path / f"{cell}.csv"
    recording = generate(seed, path, mechanisms, **DETECTION_SCENARIO)
    assert recording.collisions == 0
    config = DETECTION_CONFIG._replace(max_rounds=1)
    report = criticize(read(path, format="ngsim_raw"), seed=seed, config=config).report
    gains = {c["name"]: c["gain"] for c in report["causes"]}
    right = right_verdicts(tuple(mechanisms))
    assert report["verdict"] in right, (cell, gains)
    if cell != NULL:
        assert gains[report["verdict"]]["significant"] and gains[report["verdict"]]["elpd"] > 0
