"""Detection study: how often ``criticize`` names a hidden effect, per effect and size, and how
often it names one on data without any (the false-positive rate).

Every replication simulates the detection scenario (``DETECTION_SCENARIO``: platoons with cut-ins,
the base IDM plus one effect with per-driver sizes drawn uniformly from the size's range), writes it
as an NGSIM raw CSV, reads it back through the real reader and runs ``criticize`` with
``DETECTION_CONFIG`` -- exactly what the CI tests (tests/test_criticism_hidden.py) do for the
sizes this table shows detected in at least 95% of replications. Seeds are 1..N for every cell.

Results are appended to ``<out>/detection_runs.csv`` as they come (a rerun skips finished cells,
so the study can be stopped and resumed; with ``--first-seed`` a second process can work on the
upper seeds at the same time, appending to the same file); the table goes to
``<out>/detection.md`` with Wilson 95% intervals, and a picture to ``<out>/detection.png``.

    python benchmarks/bench_detection.py --seeds 20 --null-seeds 40 --out reports/criticism

Staged, so that a stop still leaves the cells CI needs: first the null and the CI size, then the
rest; ``--report-only`` redraws the table from the CSV.

    python benchmarks/bench_detection.py --sizes large --seeds 20 --null-seeds 20
    python benchmarks/bench_detection.py --sizes medium,small --seeds 10 --null-seeds 0
    python benchmarks/bench_detection.py --report-only
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import textwrap
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
    "sampler",
]


def sampler_label(config=DETECTION_CONFIG) -> str:
    """How many Metropolis-Hastings moves per tempering stage the run's sampler made."""
    if config.unmoved_tolerance > 0:
        return f">={config.num_moves} moves until unmoved<={config.unmoved_tolerance}"
    return f"{config.num_moves} moves"


# Cells are kept apart by sampler: a cell measured before a sampler change stays in the table,
# marked, until it is rerun; CI runs the current one (SAMPLER).
SAMPLER = sampler_label()


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion."""
    if n == 0:
        return float("nan"), float("nan")
    p = successes / n
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / (1 + z**2 / n)
    # Clipped: rounding can put an end a hair outside [0, 1] when p is 0 or 1.
    return max(centre - half, 0.0), min(centre + half, 1.0)


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
        "sampler": SAMPLER,
    }


# A cell backs a CI size only with at least this many replications (19 of 20 is 0.95).
CLAIM_REPLICATIONS = 20
SIZE_ORDER = ("none", "small", "medium", "large", "xlarge")


def cell_rates(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per (cause, size, sampler), in the order of DETECTION_SIZES and SIZE_ORDER:
    replications, hits, rate, Wilson interval and the other verdicts."""
    causes = [NO_CAUSE, *DETECTION_SIZES]
    rows = []
    for (cause, size, sampler), cell in runs.groupby(["cause", "size", "sampler"]):
        n, hits = len(cell), int(cell["detected"].sum())
        low, high = wilson(hits, n)
        rows.append(
            {
                "cause": cause,
                "size": size,
                "sampler": sampler,
                "effect": "-"
                if cause == NO_CAUSE
                else f"[{cell['low'].iloc[0]}, {cell['high'].iloc[0]}]",
                "n": n,
                "hits": hits,
                "rate": hits / n,
                "low": low,
                "high": high,
                "others": cell.loc[cell["verdict"] != cause, "verdict"].value_counts().to_dict(),
            }
        )
    out = pd.DataFrame(rows)
    order = {"cause": causes, "size": SIZE_ORDER, "sampler": [SAMPLER]}
    return out.sort_values(
        ["cause", "size", "sampler"],
        key=lambda col: col.map(lambda v: order[col.name].index(v) if v in order[col.name] else 99),
    ).reset_index(drop=True)


def table(rates: pd.DataFrame) -> str:
    """The markdown detection table."""
    lines = [
        "| cause | size | effect range | sampler | replications | named correctly | rate "
        "| 95% interval | other verdicts |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rates.itertuples():
        lines.append(
            f"| {r.cause} | {r.size} | {r.effect} | {r.sampler} | {r.n} | {r.hits} | "
            f"{r.rate:.2f} | [{r.low:.2f}, {r.high:.2f}] | {r.others or ''} |"
        )
    return "\n".join(lines)


def figure(rates: pd.DataFrame, false_positive: str, path: Path) -> None:
    """Detection rate per effect (groups) and size (bars) with Wilson intervals; where a cell was
    measured with several samplers, the current one's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    effects = rates[rates["cause"] != NO_CAUSE]
    effects = effects[
        (effects["sampler"] == SAMPLER)
        | ~effects.set_index(["cause", "size"]).index.isin(
            effects[effects["sampler"] == SAMPLER].set_index(["cause", "size"]).index
        )
    ]
    causes = list(dict.fromkeys(effects["cause"]))
    sizes = [s for s in SIZE_ORDER if s in set(effects["size"])]
    width = 0.8 / max(len(sizes), 1)
    fig, ax = plt.subplots(figsize=(9, 4.2))
    handles = []
    for k, size in enumerate(sizes):
        cell = effects[effects["size"] == size].set_index("cause").reindex(causes)
        x = np.arange(len(causes)) + (k - (len(sizes) - 1) / 2) * width
        bars = ax.bar(x, cell["rate"], width)
        # Legend from a plain patch: a hatched first bar would hatch the size's legend entry.
        handles.append(Patch(facecolor=bars.patches[0].get_facecolor(), label=size))
        for bar, sampler in zip(bars, cell["sampler"], strict=True):
            if isinstance(sampler, str) and sampler != SAMPLER:
                bar.set_hatch("//")  # measured with an older sampler only
        ax.bar_label(
            bars,
            ["" if pd.isna(n) else f"{n:.0f}" for n in cell["n"]],
            fontsize=7,
            label_type="center",
        )
        ax.errorbar(
            x,
            cell["rate"],
            yerr=[cell["rate"] - cell["low"], cell["high"] - cell["rate"]],
            fmt="none",
            ecolor="k",
            lw=0.8,
            capsize=2,
        )
    labels = ["\n".join(textwrap.wrap(c.replace("_", " "), 14)) for c in causes]
    ax.set_xticks(np.arange(len(causes)), labels, fontsize=8)
    ax.set_title(
        f"Named correctly, per effect and size (whiskers: Wilson 95%, in the bar: replications)\n"
        f"null data: {false_positive}; hatched: older sampler only",
        fontsize=9,
    )
    handles.append(ax.axhline(0.95, color="k", ls="--", lw=1, label="0.95"))
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("share of replications")
    ax.legend(handles=handles, fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def misses(runs: pd.DataFrame) -> str:
    """The missed replications with the hidden cause's gain: was it screened in, how large?"""
    missed = runs[(runs["cause"] != NO_CAUSE) & (runs["detected"] == 0)]
    if missed.empty:
        return "No effect was missed.\n"
    lines = [
        "Missed replications (gain of the hidden cause's extension: summed held-out elpd, its se "
        "across vehicles; screened in: whether the checks pointed to it):",
        "",
        "| cause | size | sampler | seed | verdict | gain | se | screened in |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in missed.sort_values(["cause", "size", "sampler", "seed"]).itertuples():
        lines.append(
            f"| {r.cause} | {r.size} | {r.sampler} | {r.seed} | {r.verdict} | "
            f"{r.true_gain:.1f} | {r.true_se:.1f} | {'yes' if r.screened_in else 'no'} |"
        )
    return "\n".join(lines) + "\n"


def write_report(runs_path: Path, out: Path) -> None:
    """detection.md (the table, false positives, the sizes at or above 0.95) and detection.png."""
    runs = pd.read_csv(runs_path)
    rates = cell_rates(runs)
    # The false-positive rate of the current sampler (older null runs are in the table).
    null = runs[(runs["cause"] == NO_CAUSE) & (runs["sampler"] == SAMPLER)]
    fp = int((null["verdict"] != NO_CAUSE).sum())
    fp_low, fp_high = wilson(fp, len(null))
    false_positive = (
        f"{fp} of {len(null)} ({fp / max(len(null), 1):.3f}, 95% interval "
        f"[{fp_low:.3f}, {fp_high:.3f}])"
    )
    reliable = rates[
        (rates["cause"] != NO_CAUSE) & (rates["rate"] >= 0.95) & (rates["n"] >= CLAIM_REPLICATIONS)
    ]
    by_cause = reliable.groupby("cause", sort=False).apply(
        lambda cell: ", ".join(f"{r.size} ({r.sampler})" for r in cell.itertuples()),
        include_groups=False,
    )
    unbacked = [c for c in DETECTION_SIZES if c not in by_cause.index]
    now = rates[rates["sampler"] == SAMPLER]
    current = set(zip(now["cause"], now["size"], strict=True))
    older = {
        f"{r.cause} {r.size}" for r in reliable.itertuples() if (r.cause, r.size) not in current
    }
    text = (
        "# Detection of hidden effects by `bayesdrive criticize`\n\n"
        f"Generated by `benchmarks/bench_detection.py`. Scenario: {DETECTION_SCENARIO} "
        f"(followers with per-driver effect sizes uniform on the range); settings: "
        f"{DETECTION_CONFIG._asdict()}. Seeds 1..N per cell (N = replications). A replication "
        "counts as detected when the verdict names the hidden cause (a significant gain for "
        "another cause, or none, counts as a miss). Intervals: Wilson 95%. Sampler: the "
        "Metropolis-Hastings moves per tempering stage the run used; the current settings "
        f'make "{SAMPLER}" (bayesdrive.inference.tempering, "How many moves"); cells '
        "measured with an older sampler stay in the table, marked, until rerun.\n\n"
        f"False positives on null data with the current sampler (verdict other than none): "
        f"{false_positive}.\n\n"
        + table(rates)
        + f"\n\nSizes named correctly in at least 95% of at least {CLAIM_REPLICATIONS} "
        "replications: "
        + ("; ".join(f"{c}: {s}" for c, s in by_cause.items()) or "none")
        + ". CI (tests/test_criticism_hidden.py) runs, per cause, one of these sizes"
        + (f"; it skips {', '.join(unbacked)}, which no measured size backs" if unbacked else "")
        + ".\n\n"
        + (
            "CI runs the current sampler; these backing cells were measured only with an older "
            f"one and not rerun since: {', '.join(sorted(older))}.\n\n"
            if older
            else ""
        )
        + misses(runs)
    )
    write_text_atomic(out / "detection.md", text)
    figure(rates, f"{fp} of {len(null)} named a cause", out / "detection.png")
    print(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20, help="replications per effect and size")
    parser.add_argument("--null-seeds", type=int, default=40, help="replications without effect")
    parser.add_argument(
        "--first-seed",
        type=int,
        default=1,
        help="start at this seed (a second process can take the upper seeds; same CSV)",
    )
    parser.add_argument(
        "--causes", default=",".join(DETECTION_SIZES), help="comma-separated causes"
    )
    parser.add_argument("--sizes", default="small,medium,large")
    parser.add_argument("--out", type=Path, default=Path("reports/criticism"))
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="rewrite detection.md and detection.png from the CSV without running anything "
        "(e.g. after several processes shared the study)",
    )
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    runs_path = args.out / "detection_runs.csv"
    if args.report_only:
        write_report(runs_path, args.out)
        return 0
    done = set()
    if runs_path.exists():
        previous = pd.read_csv(runs_path)
        current = previous[previous["sampler"] == SAMPLER]
        done = set(zip(current["cause"], current["size"], current["seed"], strict=True))
    cells = [(NO_CAUSE, "none", None, s) for s in range(args.first_seed, args.null_seeds + 1)]
    for seed in range(args.first_seed, args.seeds + 1):
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
    write_report(runs_path, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
