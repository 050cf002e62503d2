"""Where the lagged-noise model puts its two times on smoothed recordings (issue 34, item 5).

A symmetric exponential moving average of width T, applied to white noise, gives exactly the
autocorrelation of an AR(2) with a double root exp(-dt / T) (the sum over the kernel's overlap,
checked below to 1e-12), which is the law of ``autocorrelated_noise``'s error when its correlation
time and its lag are equal. So on a recording smoothed that way, the model should read two short,
equal times; on a driver's persistent pedal error (an Ornstein-Uhlenbeck process), one long time
and no lag. This script fits ``idm+autocorrelated_noise`` with smc to the followers' fitting
windows of ``trafficgen`` recordings and prints, per follower, the posterior means of the two
times (``noise_time_s``, ``noise_lag_s``), sorted as (shorter, longer).

    PYTHONPATH=. python benchmarks/smoothing_roots.py --seeds 900065 900066 --out roots.csv
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import bayesdrive as bd  # noqa: E402
from bayesdrive.data.atomic import write_text_atomic  # noqa: E402
from trafficgen import DETECTION_SCENARIO, MECHANISMS, generate  # noqa: E402

CELLS = {
    "none": {},
    "pedal_noise large": {"pedal_noise": MECHANISMS["pedal_noise"].sizes["large"]},
    **{
        f"position_smoothing {size}": {
            "position_smoothing": MECHANISMS["position_smoothing"].sizes[size]
        }
        for size in ("small", "medium", "large")
    },
}
MODEL = "idm+autocorrelated_noise"


def smoothed_white_noise_acf(width_s: float, dt: float, lags: int) -> np.ndarray:
    """Autocorrelation of white noise smoothed by the exponential kernel (its self-overlap)."""
    reach = int(np.ceil(40 * width_s / dt))
    weights = np.exp(-np.abs(np.arange(-reach, reach + 1)) * dt / width_s)
    overlap = np.array([weights[: weights.size - h] @ weights[h:] for h in range(lags + 1)])
    return overlap / overlap[0]


def double_root_acf(root: float, lags: int) -> np.ndarray:
    """Autocorrelation of an AR(2) whose two roots both equal ``root``."""
    h = np.arange(lags + 1)
    return root**h * (1 + h * (1 - root**2) / (1 + root**2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", required=True)
    parser.add_argument("--particles", type=int, default=512)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    for width in (0.1, 0.2, 0.4):
        gap = np.abs(
            smoothed_white_noise_acf(width, 0.1, 10) - double_root_acf(np.exp(-0.1 / width), 10)
        )
        assert gap.max() < 1e-12, (width, gap.max())
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for seed in args.seeds:
            for cell, mechanisms in CELLS.items():
                path = Path(folder) / f"{cell.replace(' ', '_')}_{seed}.csv"
                recording = generate(seed, path, mechanisms, **DETECTION_SCENARIO)
                traj = bd.load(path, format="ngsim_raw")
                followers = [
                    f"{path.stem}:{vid}" for vid in recording.vehicle_id[recording.follower]
                ]
                result = bd.fit(
                    jax.random.key(seed),
                    traj.subset([v for v in followers if v in traj.vehicle_ids]),
                    model=MODEL,
                    particles=args.particles,
                    seed=seed,
                )
                post = result["posterior"]
                times = np.stack(
                    [
                        post["noise_time_s"].mean(("chain", "draw")),
                        post["noise_lag_s"].mean(("chain", "draw")),
                    ]
                )
                shorter, longer = np.sort(times, axis=0)
                for vehicle, lo, hi in zip(post["vehicle"].values, shorter, longer, strict=True):
                    rows.append(
                        {
                            "cell": cell,
                            "seed": seed,
                            "vehicle": str(vehicle),
                            "shorter_s": float(lo),
                            "longer_s": float(hi),
                        }
                    )
                print(
                    cell,
                    seed,
                    np.round(np.median(shorter), 3),
                    np.round(np.median(longer), 3),
                    flush=True,
                )
    frame = pd.DataFrame(rows)
    write_text_atomic(args.out, frame.to_csv(index=False))
    print(frame.groupby("cell")[["shorter_s", "longer_s"]].describe().round(3).to_string())


if __name__ == "__main__":
    main()
