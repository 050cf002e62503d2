"""Does the state correction (``idm+state_correction``) forecast held-out steps better than the IDM
where the independent generator hides a state-dependent effect, and not where it hides none?

Per seed, trafficgen's detection scenario (``--duration-s`` long) twice: with ``approach_braking``
at ``--size`` and without a mechanism (the same seed, so the same traffic). Per recording, the
held-out evidence fits that ``criticize`` uses (``fit_model``: tempering on each follower's
fitting window, then on to its held-out window; the criticism's settings) of the IDM and of the
IDM with the state correction, started from the IDM's fit. Per follower: the held-out one-step
log predictive density gain of the correction, and where its three coefficients' 90% intervals
lie. Writes ``<out>/runs.csv`` and ``<out>/README.md`` (keeping the findings written below its
marker). Seeds are fixed before a run.

    PYTHONPATH=. python benchmarks/bench_state_correction.py --seeds 250001-250020 --out DIR

With ``--real``, on the training data sets instead, the criticism's data of the README's main job
(``criticism_data``: NGSIM I-80 scenes 9-40, OpenACC's human recordings, their first 120 s): the
gain of the correction over the IDM and over the model the criticism adopted
(``idm+autocorrelated_noise``), each extended model started from its base's fit. Writes
``<out>/real.csv`` and ``<out>/real.md``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bayesdrive.criticism.criticize import (  # noqa: E402
    DETECTION_CONFIG,
    criticized_series,
    fit_config,
)
from bayesdrive.data.atomic import write_text_atomic  # noqa: E402
from bayesdrive.data.readers import read  # noqa: E402
from bayesdrive.drivers.extensions import as_extended, extend  # noqa: E402
from bayesdrive.drivers.extensions.state_correction import STATE_CORRECTION_SPECS  # noqa: E402
from bayesdrive.drivers.idm import IDM  # noqa: E402
from bayesdrive.experiments.paper import Settings, criticism_data, highway_data  # noqa: E402
from bayesdrive.inference.engines.heldout_evidence import fit_model  # noqa: E402
from benchmarks.bench_crosscheck_convergence import markdown, write_keeping_findings  # noqa: E402
from benchmarks.bench_detection import CODE, GENERATOR  # noqa: E402
from trafficgen import DETECTION_SCENARIO, MECHANISMS, NULL, generate  # noqa: E402

MECHANISM = "approach_braking"
COEFFICIENTS = tuple(spec.name for spec in STATE_CORRECTION_SPECS)


def seed_range(text: str) -> list[int]:
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


CRITICISM_FIT = fit_config(DETECTION_CONFIG)
REAL_DATA = ("ngsim_i80_chains", "openacc_vicolungo:human")
# Each base the correction is added to: the plain IDM, and the model the criticism adopted.
REAL_PAIRS = ((), ("autocorrelated_noise",))


def coefficient_columns(fitted) -> dict[str, np.ndarray]:
    """Per vehicle, each coefficient's posterior mean and where its 90% interval lies."""
    columns = {}
    for name in COEFFICIENTS:
        draws = fitted.theta[:, :, fitted.names.index(name)]
        low, high = np.quantile(draws, [0.05, 0.95], axis=1)
        columns[f"{name}_mean"] = draws.mean(axis=1)
        columns[f"{name}_sign"] = np.where(high < 0, "-", np.where(low > 0, "+", "0"))
    return columns


def correction_gain(key: jax.Array, fold: int, series, present: tuple[str, ...]) -> dict:
    """Fit the base (the IDM with ``present``) with the key's ``fold``-th part, then the base with
    the correction, started from it, with the next; per follower the held-out gain and the
    coefficients (:func:`coefficient_columns`)."""
    base_model = extend(present[0], IDM) if present else as_extended(IDM)
    base = fit_model(jax.random.fold_in(key, fold), series, base_model, config=CRITICISM_FIT)
    corrected = fit_model(
        jax.random.fold_in(key, fold + 1),
        series,
        extend("state_correction", IDM, present),
        config=CRITICISM_FIT,
        start=base,
    )
    return {
        "base": base_model.model.name,
        "vehicle": list(series.vehicle_ids),
        "gain_nats": corrected.log_z_held - base.log_z_held,
        **coefficient_columns(corrected),
    }


def run_real(label: str, seed: int) -> pd.DataFrame:
    """The correction against each base of :data:`REAL_PAIRS` on one training data set."""
    traj = highway_data(label.split(":")[0])[label]
    series = criticized_series(criticism_data(label, traj, Settings()))
    key = jax.random.key(seed)
    frames = [
        pd.DataFrame({"data": label, **correction_gain(key, 2 * number, series, present)})
        for number, present in enumerate(REAL_PAIRS)
    ]
    return pd.concat(frames, ignore_index=True)


def run_cell(seed: int, cell: str, size: str, duration_s: float, folder: Path) -> pd.DataFrame:
    """Both fits on one recording; one row per follower."""
    mechanisms = {} if cell == NULL else {cell: MECHANISMS[cell].sizes[size]}
    path = folder / f"{cell}_{seed}.csv"
    generate(seed, path, mechanisms, **{**DETECTION_SCENARIO, "duration_s": duration_s})
    series = criticized_series(read(path, format="ngsim_raw"))
    gain = correction_gain(jax.random.key(seed), 0, series, ())
    del gain["base"]  # always the IDM here
    return pd.DataFrame({"seed": seed, "cell": cell, "size": size if cell != NULL else "-", **gain})


def summary(runs: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    """Per group of ``by``: followers, the held-out gain (sum, its SE over followers, the median,
    the share above 0) and, per coefficient, the followers whose 90% interval lies below or above
    0."""
    out = []
    for keys, group in runs.groupby(by, sort=False):
        gain = group["gain_nats"].to_numpy()
        row = {
            **dict(zip(by, keys, strict=True)),
            "followers": len(group),
            "gain_sum_nats": gain.sum(),
            "gain_se_nats": gain.std(ddof=1) * np.sqrt(len(gain)),
            "gain_median_nats": np.median(gain),
            "followers_gaining": int((gain > 0).sum()),
        }
        for name in COEFFICIENTS:
            signs = group[f"{name}_sign"]
            row[f"{name} below / above 0"] = f"{(signs == '-').sum()} / {(signs == '+').sum()}"
        out.append(row)
    return pd.DataFrame(out)


def write_study(
    out: Path, report: str, runs: pd.DataFrame, table: pd.DataFrame, header: str, csv: str = ""
) -> None:
    """``<csv or report>.csv`` (the rows) and ``<report>.md`` (the header and the table, keeping
    the findings written below its marker), both atomically; the report is printed too."""
    out.mkdir(parents=True, exist_ok=True)
    rows = runs.to_csv(index=False, float_format="%.6g")
    write_text_atomic(out / f"{csv or report}.csv", rows)
    write_keeping_findings(out / f"{report}.md", header + markdown(table) + "\n")
    print(header + markdown(table))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", required=True, help="e.g. 250001-250004")
    parser.add_argument("--size", default="large", choices=list(MECHANISMS[MECHANISM].sizes))
    parser.add_argument("--duration-s", type=float, default=120.0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--real", action="store_true", help="the training data sets (see above)")
    args = parser.parse_args()
    started = time.perf_counter()
    if args.real:
        seed = seed_range(args.seeds)[0]
        runs = pd.concat([run_real(label, seed) for label in REAL_DATA], ignore_index=True)
        header = (
            "# The state correction on the training data sets\n\n"
            f"Generated by `benchmarks/bench_state_correction.py --real --seeds {seed} --out "
            f"{args.out}` (library {CODE}; {time.perf_counter() - started:.0f} s). The criticism's "
            "data of the README's main job and its held-out evidence fits. Gain: the held-out "
            "one-step log predictive density of the base with `state_correction` added, minus "
            "the base's, per follower (`real.csv`); `gain_se_nats` is the standard error of the "
            "sum.\n\n"
        )
        write_study(args.out, "real", runs, summary(runs, ["data", "base"]), header)
        return
    frames = []
    with tempfile.TemporaryDirectory() as folder:
        for seed in seed_range(args.seeds):
            for cell in (MECHANISM, NULL):
                frames.append(run_cell(seed, cell, args.size, args.duration_s, Path(folder)))
                print(f"seed {seed} {cell}: done at {time.perf_counter() - started:.0f} s")
    runs = pd.concat(frames, ignore_index=True)
    header = (
        f"# The state correction on trafficgen's `{MECHANISM}` and on null data\n\n"
        f"Generated by `benchmarks/bench_state_correction.py --seeds {args.seeds} --size "
        f"{args.size} --duration-s {args.duration_s:g}` (library {CODE}, generator {GENERATOR}; "
        f"{time.perf_counter() - started:.0f} s). The detection scenario "
        f"({DETECTION_SCENARIO['platoons']} platoons of {DETECTION_SCENARIO['followers']} "
        f"followers) {args.duration_s:g} s long; the criticism's held-out evidence fits. Gain: "
        "the held-out one-step log predictive density of `idm+state_correction` minus the IDM's, "
        "per follower (`runs.csv`).\n\n"
    )
    write_study(args.out, "README", runs, summary(runs, ["cell", "size"]), header, "runs")


if __name__ == "__main__":
    main()
