"""Detection study: how often ``criticize`` names a hidden effect, per effect and size, and how
often it names one on data without any (the false-positive rate).

Every replication simulates the detection scenario (``DETECTION_SCENARIO``: platoons with cut-ins,
the base IDM plus one effect with per-driver sizes drawn uniformly from the size's range), writes it
as an NGSIM raw CSV, reads it back through the real reader and runs ``criticize`` with
``DETECTION_CONFIG`` -- exactly what the CI tests (tests/test_criticism_hidden.py) do for the
sizes this table shows detected in at least 95% of replications. Seeds are 1..N for every cell.

Results are appended to ``<out>/detection_runs.csv`` as they come (a rerun skips finished cells,
so the study can be stopped and resumed); the table goes to ``<out>/detection.md`` with Wilson
95% intervals, and a picture to ``<out>/detection.png``.

    python benchmarks/bench_detection.py --seeds 20 --null-seeds 40 --out reports/criticism
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
import pandas as pd

from bayesdrive.criticism.criticize import DETECTION_CONFIG, criticize
from bayesdrive.criticism.generator import DETECTION_SCENARIO, DETECTION_SIZES, generate
from bayesdrive.data.atomic import write_text_atomic
from bayesdrive.data.readers import read
from bayesdrive.drivers.extensions import NO_CAUSE

FIELDS = [
    "cause",
    "size",
    "low",
    "high",
    "seed",
    "verdict",
    "detected",
    "true_gain",
    "true_se",
    "true_significant",
    "screened_in",
    "seconds",
]


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion."""
    if n == 0:
        return float("nan"), float("nan")
    p = successes / n
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / (1 + z**2 / n)
    return centre - half, centre + half


def run_one(cause: str, size: str, effect_range, seed: int, workdir: Path) -> dict:
    """One replication: simulate, write, read, criticize."""
    started = time.perf_counter()
    path = workdir / f"{cause}_{size}_{seed}.csv"
    generate(
        jax.random.key(seed),
        path,
        cause,
        effect_range=effect_range,
        **DETECTION_SCENARIO,
    )
    traj = read(path, format="ngsim_raw")
    report = criticize(traj, seed=seed, config=DETECTION_CONFIG).report
    path.unlink()
    entry = next((c for c in report["causes"] if c["name"] == cause), None)
    gain = entry["gain"] if entry else None
    return {
        "cause": cause,
        "size": size,
        "low": effect_range[0] if effect_range else "",
        "high": effect_range[1] if effect_range else "",
        "seed": seed,
        "verdict": report["verdict"],
        "detected": int(report["verdict"] == cause),
        "true_gain": gain["elpd"] if gain else "",
        "true_se": gain["se"] if gain else "",
        "true_significant": int(bool(gain and gain["significant"])),
        "screened_in": int(bool(entry and entry["screened_in"])),
        "seconds": round(time.perf_counter() - started, 1),
    }


def table(runs: pd.DataFrame) -> str:
    """The markdown detection table."""
    lines = [
        "| cause | size | effect range | replications | named correctly | rate | 95% interval "
        "| other verdicts |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (cause, size), cell in runs.groupby(["cause", "size"], sort=False):
        n, hits = len(cell), int(cell["detected"].sum())
        low, high = wilson(hits, n)
        others = cell.loc[cell["verdict"] != cause, "verdict"].value_counts().to_dict()
        effect = "-" if cause == NO_CAUSE else f"[{cell['low'].iloc[0]}, {cell['high'].iloc[0]}]"
        lines.append(
            f"| {cause} | {size} | {effect} | {n} | {hits} | {hits / n:.2f} | "
            f"[{low:.2f}, {high:.2f}] | {others or ''} |"
        )
    return "\n".join(lines)


def figure(runs: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = runs[runs["cause"] != NO_CAUSE].groupby(["cause", "size"], sort=False)["detected"]
    rates = cells.mean().unstack()
    order = [s for s in ("small", "medium", "large") if s in rates.columns]
    fig, ax = plt.subplots(figsize=(8, 3.8))
    rates[order].plot.bar(ax=ax, rot=15)
    null = runs[runs["cause"] == NO_CAUSE]
    if len(null):
        fp = 1 - null["detected"].mean()
        ax.set_title(f"Detection rate per effect and size; false positives on null data: {fp:.2f}")
    ax.axhline(0.95, color="k", ls="--", lw=1, label="95%")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("share named correctly")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20, help="replications per effect and size")
    parser.add_argument("--null-seeds", type=int, default=40, help="replications without effect")
    parser.add_argument(
        "--causes", default=",".join(DETECTION_SIZES), help="comma-separated causes"
    )
    parser.add_argument("--sizes", default="small,medium,large")
    parser.add_argument("--out", type=Path, default=Path("reports/criticism"))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    runs_path = args.out / "detection_runs.csv"
    done = set()
    if runs_path.exists():
        previous = pd.read_csv(runs_path)
        done = set(zip(previous["cause"], previous["size"], previous["seed"], strict=True))
    cells = [(NO_CAUSE, "none", None, s) for s in range(1, args.null_seeds + 1)]
    for seed in range(1, args.seeds + 1):
        for cause in args.causes.split(","):
            for size in args.sizes.split(","):
                cells.append((cause, size, DETECTION_SIZES[cause][size], seed))
    todo = [c for c in cells if (c[0], c[1], c[3]) not in done]
    todo.sort(key=lambda c: c[3])  # seed by seed, so a stopped study has every cell covered
    print(f"{len(cells) - len(todo)} replications done, {len(todo)} to go", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for i, (cause, size, effect_range, seed) in enumerate(todo, 1):
            try:
                row = run_one(cause, size, effect_range, seed, Path(tmp))
            except Exception as error:
                row = {field: "" for field in FIELDS}
                row.update(cause=cause, size=size, seed=seed, detected=0)
                row["verdict"] = f"error: {type(error).__name__}: {error}"[:200]
            new = not runs_path.exists()
            with runs_path.open("a", newline="") as handle:
                writer = csv.DictWriter(handle, fieldnames=FIELDS)
                if new:
                    writer.writeheader()
                writer.writerow(row)
            print(f"[{i}/{len(todo)}] {row}", flush=True)
    runs = pd.read_csv(runs_path)
    null = runs[runs["cause"] == NO_CAUSE]
    fp = int((null["verdict"] != NO_CAUSE).sum())
    fp_low, fp_high = wilson(fp, len(null))
    text = (
        "# Detection of hidden effects by `bayesdrive criticize`\n\n"
        f"Generated by `benchmarks/bench_detection.py`. Scenario: {DETECTION_SCENARIO} "
        f"(followers with per-driver effect sizes uniform on the range); settings: "
        f"{DETECTION_CONFIG._asdict()}. Seeds 1..N per cell. A replication counts as detected "
        "when the verdict names the hidden cause (a significant gain for another cause, or "
        "none, counts as a miss).\n\n"
        f"False positives on null data (verdict other than none): {fp} of {len(null)} "
        f"({fp / max(len(null), 1):.3f}, 95% interval [{fp_low:.3f}, {fp_high:.3f}]).\n\n"
        + table(runs)
        + "\n\nCI (tests/test_criticism_hidden.py) runs, per cause, a size whose detection rate "
        "here is at least 0.95.\n"
    )
    write_text_atomic(args.out / "detection.md", text)
    figure(runs, args.out / "detection.png")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
