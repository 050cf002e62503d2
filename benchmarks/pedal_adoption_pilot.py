"""One round of ``criticize`` with 32 rollouts on ``trafficgen`` pedal noise of a given
correlation-time range, in CI's scenario: what it names, whether it adopts, and why.

A development pilot (reports/criticism/adoption_power_dev/README.md): seeds from the development
range, nothing chosen in the library by it.

    PYTHONPATH=. python benchmarks/pedal_adoption_pilot.py 2.0 4.0 900001 900002
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bayesdrive.criticism.criticize import DETECTION_CONFIG, criticize  # noqa: E402
from bayesdrive.data.readers import read  # noqa: E402
from trafficgen import DETECTION_SCENARIO, generate  # noqa: E402


def main(argv: list[str]) -> None:
    low, high = float(argv[0]), float(argv[1])
    config = DETECTION_CONFIG._replace(num_rollouts=32, max_rounds=1)
    for seed in map(int, argv[2:]):
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "pedal.csv"
            recording = generate(seed, path, {"pedal_noise": (low, high)}, **DETECTION_SCENARIO)
            report = criticize(read(path, format="ngsim_raw"), seed=seed, config=config).report
        first = report["rounds"][0]
        print(low, high, seed, recording.collisions, first["named"], first["adopted"])
        print("   ", first["adoption"], flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
