"""Detection study: how often ``criticize`` names a hidden effect in data made by the independent
generator (``trafficgen``: its own IDM on sub-steps, mechanisms that are not the extensions'
equations), per mechanism and size, on null data, and with two mechanisms at once.

Every replication simulates ``trafficgen.DETECTION_SCENARIO`` with the cell's mechanisms (per-driver
sizes uniform on the size's range), writes an NGSIM raw CSV, reads it back through the real reader
and runs ``criticize`` with ``DETECTION_CONFIG``, exactly as CI's hidden-effect tests
(tests/criticism/test_criticism_hidden.py) do, the loop included (``max_rounds`` of the config). With one
mechanism a replication is right when the verdict (the first round's cause) is one of the
mechanism's right verdicts (``trafficgen.right_verdicts``; null data: ``none``); with two, when
the final model holds a right verdict of each (:func:`names_every_mechanism`). The row records the
final model too, so causes added in later rounds on one-mechanism data (false positives of the
loop) are counted in the table.

**Adoption** (``--rollouts N``): the same replications with ``N`` rollouts per model, so each
round's named cause is also judged for adoption (its held-out 5 s forecast against the current
model's, module docstring of :mod:`bayesdrive.criticism.criticize`). Rows go to files of their own
(``detection_adoption_runs.csv``, ``detection_adoption.md``) with what was adopted and round 1's
adoption reason; the table puts each cell's adoption rate (null data: nothing adopted) beside its
naming rate. The first round names its cause as without rollouts.

**Seeds, fixed before the run.** Replication r (1, 2, ...) of every cell uses seed
``STUDY_SEEDS.start + r - 1``: 100001, 100002, ... . These were never used while developing the
generator or the detector; development and pilots use ``--dev``, which takes ``DEV_SEEDS``
(900001, ...) and writes to files of their own (``detection_dev_runs.csv``, ``detection_dev.md``).
CI's seeds (70001, ...) are a third range, fixed in the test. A rerun after a change to the
detector takes fresh seeds, fixed before it runs: ``--first-seed`` starts the study's range
elsewhere (the table names every row's seeds).

**Resumable.** Each finished replication is appended to ``<out>/detection_runs.csv`` as one line in
one ``write`` on a file opened for appending (so a stop never leaves half a row); a rerun skips the
(cell, size, seed) rows already there for the current sampler, generator and library
(fingerprints of trafficgen's and bayesdrive's sources), so the study, hours long, can be stopped and resumed, and rows made by
another generator version or sampler are neither reused nor reported. The table goes to
``<out>/detection.md`` with Wilson 95% intervals and the seeds used.

    PYTHONPATH=. python benchmarks/bench_detection.py                  # the study (hours)
    PYTHONPATH=. python benchmarks/bench_detection.py --dev --replications 2 --sizes large
    PYTHONPATH=. python benchmarks/bench_detection.py --report-only

**Many cores.** ``--shard K/N`` runs every N-th replication of the plan from the K-th (0-based), so
N processes, each pinned to a core, share one study; they may append to one runs file (each row is
one ``write`` on a file opened for appending). ``--jobs N`` starts those N processes itself, each
pinned to one of the cores this process may use, and writes the table when all have ended.
``--stop-at EPOCH`` starts no replication after that time, so a machine lent for a fixed time ends
with whole rows. Which replications a process runs changes no row: a replication's bits depend on
its cell, size and seed alone.

    PYTHONPATH=. python benchmarks/bench_detection.py --jobs 16 --stop-at $(( $(date +%s) + 400 ))
"""

from __future__ import annotations

import argparse
import ast
import csv
import functools
import hashlib
import io
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

# trafficgen is not installed with bayesdrive: it lives at the repository root beside it.
ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bayesdrive.criticism.criticize import (  # noqa: E402
    DETECTION_CONFIG,
    CriticizeConfig,
    criticize,
)
from bayesdrive.data.readers import read  # noqa: E402
from benchmarks.bench_crosscheck_convergence import write_keeping_findings  # noqa: E402
from trafficgen import (  # noqa: E402
    DETECTION_SCENARIO,
    MECHANISMS,
    NULL,
    SIZES,
    generate,
    right_verdicts,
)

STUDY_SEEDS = range(100_001, 200_001)
DEV_SEEDS = range(900_001, 1_000_001)
# Two mechanisms at once whose right verdicts compose into one model (bayesdrive.drivers.extensions:
# one extension of each kind), so the loop can name both.
PAIRS = (
    ("perception_delay", "video_position_noise"),
    ("pedal_noise", "perception_delay"),
    ("pedal_noise", "two_leader_anticipation"),
)
FIELDS = [
    "cell",
    "size",
    "ranges",
    "seed",
    "verdict",
    "model",
    "right",
    "right_verdicts",
    "best_right_gain",
    "best_right_se",
    "screened_in",
    "collisions",
    "seconds",
    "sampler",
    "generator",
    "code",
]
# With --rollouts: what was adopted (causes joined by "+"), whether that is right (a right cause of
# the mechanism adopted; null data: nothing adopted), and round 1's adoption reason.
ADOPTION_FIELDS = [*FIELDS, "adopted", "adopted_right", "adoption"]
# A cell backs CI only with at least this many replications, all right.
CLAIM_REPLICATIONS = 20


def generator_fingerprint() -> str:
    """First 12 hex digits of the sha256 of trafficgen's source: rows of another version differ."""
    digest = hashlib.sha256()
    for source in sorted((ROOT / "trafficgen").glob("*.py")):
        digest.update(source.read_bytes())
    return digest.hexdigest()[:12]


def code_without_docstrings(source: str) -> str:
    """``source`` without docstrings, comments or layout (Python's own rendering of its syntax
    tree, so compare rows made on one Python minor version): what the code computes, so rewording
    a docstring or reflowing a line keeps a study's rows valid."""
    tree = ast.parse(source)
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
            and ast.get_docstring(node, clean=False) is not None
        ):
            node.body = node.body[1:] or [ast.Pass()]
    return ast.unparse(tree)


def library_fingerprint() -> str:
    """First 12 hex digits of the sha256 of the detector's code: every bayesdrive module loaded
    once criticize and the readers are imported (none of them imports lazily), without docstrings
    and comments (:func:`code_without_docstrings`; rows made before this rule carry the hash of
    the whole source), so rows made by another version of the detector are told apart while
    changes elsewhere in the library (the CLI, the reports, other engines) leave finished
    replications valid."""
    package = ROOT / "bayesdrive"
    sources = sorted(
        Path(module.__file__)
        for name, module in list(sys.modules.items())
        if name.split(".")[0] == "bayesdrive" and getattr(module, "__file__", None)
    )
    digest = hashlib.sha256()
    for source in sources:
        digest.update(str(source.relative_to(package)).encode())
        digest.update(code_without_docstrings(source.read_text()).encode())
    return digest.hexdigest()[:12]


# Taken once, at start: the rows of a run carry the versions it imported.
GENERATOR = generator_fingerprint()
CODE = library_fingerprint()
# Earlier generator version -> the next one, whose data are byte-identical for every cell the
# earlier could make (checked when the next was made): its rows stand for the next one's, and so
# on down the chain. 9694aaba4aea -> aa0aedd5461c added position_smoothing; 92 CSVs of the other
# cells were compared (reports/criticism/smoothing/README.md). aa0aedd5461c -> d3093b9b024b added
# approach_braking; 100 CSVs of the other cells (reports/state_correction/README.md).
# d3093b9b024b -> 18351af3c27e rewrapped a description's string (the same text, the same CSVs).
# 18351af3c27e -> 296ef49af316 made state_correction approach_braking's right verdict and rewrapped
# two strings (100 CSVs of the other cells and 4 of approach_braking byte-identical, stop 56).
SAME_DATA_GENERATORS = {
    "9694aaba4aea": "aa0aedd5461c",
    "aa0aedd5461c": "d3093b9b024b",
    "d3093b9b024b": "18351af3c27e",
    "18351af3c27e": "296ef49af316",
}


def same_data_generators(generator: str) -> set[str]:
    """``generator`` and every earlier version whose chain in :data:`SAME_DATA_GENERATORS`
    reaches it."""
    found = {generator}
    while more := {e for e, later in SAME_DATA_GENERATORS.items() if later in found} - found:
        found |= more
    return found


CURRENT_GENERATORS = same_data_generators(GENERATOR)


def study_config(
    rollouts: int, causes: tuple[str, ...] = DETECTION_CONFIG.causes
) -> CriticizeConfig:
    """CI's detection settings, with ``rollouts`` rollouts per model (0: naming only), screening
    ``causes`` (CI's: the criticism's default family)."""
    return DETECTION_CONFIG._replace(num_rollouts=rollouts, causes=causes)


def sampler_label(config: CriticizeConfig) -> str:
    """How many Metropolis-Hastings moves per tempering stage the run's sampler made, how many
    rounds the criticism's loop may run and, when adoption is judged, how many rollouts (rows of
    another setting are not reused)."""
    rounds = f", up to {config.max_rounds} rounds"
    if config.num_rollouts:
        rounds += f", {config.num_rollouts} rollouts"
    if config.causes != DETECTION_CONFIG.causes:
        rounds += f", causes {'+'.join(config.causes)}"
    if config.unmoved_tolerance > 0:
        return f">={config.num_moves} moves until unmoved<={config.unmoved_tolerance}{rounds}"
    return f"{config.num_moves} moves{rounds}"


def cell_mechanisms(cell: str, size: str) -> dict[str, tuple[float, float]]:
    """The mechanisms (name -> size range) of a cell named ``a`` or ``a+b`` (or none)."""
    if cell == NULL:
        return {}
    return {name: MECHANISMS[name].sizes[size] for name in cell.split("+")}


def names_every_mechanism(model: str, mechanisms: tuple[str, ...]) -> bool:
    """Whether the final model ``model`` (a composite name) holds a right verdict of every one of
    ``mechanisms`` (none: the base model alone)."""
    causes = set(model.split("+")[1:])
    if not mechanisms:
        return not causes
    return all(causes & set(MECHANISMS[m].verdicts) for m in mechanisms)


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion."""
    if n == 0:
        return float("nan"), float("nan")
    p = successes / n
    centre = (p + z**2 / (2 * n)) / (1 + z**2 / n)
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / (1 + z**2 / n)
    # Clipped: rounding can put an end a hair outside [0, 1] when p is 0 or 1.
    return max(centre - half, 0.0), min(centre + half, 1.0)


def runs_file(out: Path, *, dev: bool, rollouts: int) -> Path:
    """Where a study's rows go: development and adoption rows each in a file of their own."""
    return out / f"detection{'_dev' if dev else ''}{'_adoption' if rollouts else ''}_runs.csv"


def run_one(
    cell: str, size: str, seed: int, workdir: Path, config: CriticizeConfig, scenario: dict
) -> dict:
    """One replication of ``scenario`` (trafficgen's keyword arguments): simulate, write, read,
    criticize."""
    started = time.perf_counter()
    mechanisms = cell_mechanisms(cell, size)
    path = workdir / f"{cell.replace('+', '_')}_{size}_{seed}.csv"
    recording = generate(seed, path, mechanisms, **scenario)
    report = criticize(read(path, format="ngsim_raw"), seed=seed, config=config).report
    path.unlink()
    right = right_verdicts(tuple(mechanisms))
    found = (
        names_every_mechanism(report["model"], tuple(mechanisms))
        if len(mechanisms) > 1
        else report["verdict"] in right
    )
    gains = [c["gain"] for c in report["causes"] if c["name"] in right and c["gain"]]
    best = max(gains, key=lambda g: g["elpd"] if g["elpd"] is not None else -np.inf, default=None)
    row = {
        "cell": cell,
        "size": size,
        "ranges": ";".join(f"{k}={v[0]}-{v[1]}" for k, v in mechanisms.items()),
        "seed": seed,
        "verdict": report["verdict"],
        "model": report["model"],
        "right": int(found),
        "right_verdicts": "|".join(right) or "(out of reach)",
        "best_right_gain": "" if best is None else best["elpd"],
        "best_right_se": "" if best is None else best["se"],
        "screened_in": int(any(c["screened_in"] for c in report["causes"] if c["name"] in right)),
        "collisions": recording.collisions,
        "seconds": round(time.perf_counter() - started, 1),
        "sampler": sampler_label(config),
        "generator": GENERATOR,
        "code": CODE,
    }
    if config.num_rollouts:
        adopted = report["adopted"]
        row["adopted"] = "+".join(adopted)
        row["adopted_right"] = int(bool(set(adopted) & set(right)) if mechanisms else not adopted)
        row["adoption"] = report["rounds"][0]["adoption"] if report["rounds"] else ""
    return row


def append_rows(path: Path, rows: list[dict], fields: list[str]) -> None:
    """Append CSV lines in one write (header first on a new file): a crash never leaves half a
    replication."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fields)
    if not path.exists():
        writer.writeheader()
    writer.writerows(rows)
    handle = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(handle, buffer.getvalue().encode())
        os.fsync(handle)
    finally:
        os.close(handle)


def planned_cells(cells: list[str], sizes: list[str]) -> list[tuple[str, str]]:
    """(cell, size) pairs: null once, every mechanism and pair at every size."""
    return [
        (c, NULL) if c == NULL else (c, s) for c in cells for s in ([NULL] if c == NULL else sizes)
    ]


def cell_rates(runs: pd.DataFrame) -> pd.DataFrame:
    """One row per (cell, size, generator): replications, right, rate, Wilson interval, other
    verdicts, seeds."""
    order = [NULL, *MECHANISMS, *("+".join(p) for p in PAIRS)]
    rows = []
    for (cell, size, generator, code), group in runs.groupby(["cell", "size", "generator", "code"]):
        n, hits = len(group), int(group["right"].sum())
        low, high = wilson(hits, n)
        seeds = sorted(group["seed"].astype(int))
        adoption = {}
        if "adopted_right" in group:
            adopted = int(group["adopted_right"].sum())
            adoption = dict(
                zip(
                    ["adopted", "adopted_low", "adopted_high"],
                    [adopted, *wilson(adopted, n)],
                    strict=True,
                )
            )
        rows.append(
            adoption
            | {
                "cell": cell,
                "size": size,
                "generator": generator,
                "code": code,
                "ranges": group["ranges"].iloc[0]
                if isinstance(group["ranges"].iloc[0], str)
                else "-",
                "right_verdicts": group["right_verdicts"].iloc[0],
                "n": n,
                "hits": hits,
                "rate": hits / n,
                "low": low,
                "high": high,
                "others": group.loc[group["right"] == 0, "verdict"].value_counts().to_dict(),
                "models": group["model"].value_counts().to_dict(),
                "seeds": _ranges(seeds),
            }
        )
    if not rows:  # no replication of the current generator and sampler yet
        return pd.DataFrame(columns=["cell", "size", "generator", "code", "n", "hits"])
    out = pd.DataFrame(rows)
    size_order = [NULL, *SIZES]
    return out.sort_values(
        ["cell", "size"],
        key=lambda col: col.map((order if col.name == "cell" else size_order).index),
    ).reset_index(drop=True)


def _ranges(seeds: list[int]) -> str:
    """1,2,3,5 -> '1-3, 5'."""
    parts, start = [], None
    for i, s in enumerate(seeds):
        if start is None:
            start = s
        if i + 1 == len(seeds) or seeds[i + 1] != s + 1:
            parts.append(str(start) if start == s else f"{start}-{s}")
            start = None
    return ", ".join(parts)


# What a replication found: a rerun of the same cell, size and seed must give the same values.
RESULT_COLUMNS = ["verdict", "model", "right", "best_right_gain", "best_right_se", "screened_in"]


def reruns(runs: pd.DataFrame) -> list[str]:
    """Per other library version: how many of its replications the current one ran again (same
    cell, size and seed) and how many of those found exactly the same (:data:`RESULT_COLUMNS`).
    A change that moved no verdict shows here as every rerun identical; the rows still back
    nothing until the current version has its own."""
    key = ["cell", "size", "seed"]
    current = runs[runs["code"] == CODE]
    lines = []
    for code, rows in runs[runs["code"] != CODE].groupby("code"):
        both = current.merge(rows, on=key, suffixes=("", "_before"))
        if both.empty:
            continue
        same = np.ones(len(both), bool)
        for column in RESULT_COLUMNS:
            now, before = both[column], both[f"{column}_before"]
            same &= ((now == before) | (now.isna() & before.isna())).to_numpy()
        # Differing reruns per cell, with how many were right then and now (seeds would be a
        # wall of numbers when a change moves every draw).
        differing = [
            f"{cell} {size}: {len(group)} (right {int(group['right_before'].sum())} before, "
            f"{int(group['right'].sum())} now)"
            for (cell, size), group in both.loc[~same].groupby(["cell", "size"], sort=False)
        ]
        lines.append(
            f"- {code}: {len(both)} replication(s) rerun, {int(same.sum())} identical"
            + (f"; differing: {'; '.join(differing)}" if differing else "")
        )
    return lines


def write_report(
    runs_path: Path, out: Path, *, dev: bool, config: CriticizeConfig, scenario: dict
) -> str:
    """The markdown table of the current sampler's rows: for the study, of the current generator
    only (or one whose data it repeats, :data:`SAME_DATA_GENERATORS`); for the development pilot,
    of every generator version it ran (marked). With rollouts, each cell's adoption rate stands
    beside its naming rate."""
    runs = pd.read_csv(runs_path, dtype={"generator": str, "code": str})
    runs = runs[runs["sampler"] == sampler_label(config)]
    if not dev:
        runs = runs[runs["generator"].isin(CURRENT_GENERATORS)]
    rates = cell_rates(runs)
    judged = bool(config.num_rollouts)
    lines = [
        "| cell | size | generator | library | size ranges | right verdicts | replications | "
        "right | rate | 95% interval | "
        + ("adopted right | adoption rate | 95% interval | " if judged else "")
        + "other verdicts | final models | seeds |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|"
        + ("---|---|---|" if judged else ""),
    ]
    for r in rates.itertuples():
        adoption = (
            f"{r.adopted} | {r.adopted / r.n:.2f} | [{r.adopted_low:.2f}, {r.adopted_high:.2f}] | "
            if judged
            else ""
        )
        lines.append(
            f"| {r.cell} | {r.size} | {r.generator} | {r.code} | {r.ranges} | {r.right_verdicts.replace('|', ', ')} "
            f"| {r.n} | "
            f"{r.hits} | "
            f"{r.rate:.2f} | [{r.low:.2f}, {r.high:.2f}] | {adoption}{r.others or ''} | {r.models} | "
            f"{r.seeds} |"
        )
    reliable = rates[
        (rates["n"] >= CLAIM_REPLICATIONS)
        & (rates["hits"] == rates["n"])
        & (rates["generator"].isin(CURRENT_GENERATORS))
        & (rates["code"] == CODE)
    ]
    kind = (
        "**Development pilot** (development seeds, never evidence for CI: it chose what to measure)"
        if dev
        else "Study (seeds fixed before the run, never used in development)"
    )
    text = (
        "# Detection of hidden effects by `bayesdrive criticize` on independent data\n\n"
        f"{kind}. Generated by `benchmarks/bench_detection.py` from `{runs_path.name}`; "
        f"current generator trafficgen {GENERATOR} and library bayesdrive {CODE} (sha256 "
        "prefixes of trafficgen's source and of the detector's code without docstrings or "
        "comments; rows of other library versions are listed apart and back no claim), scenario "
        f"{scenario}; criticize settings {config._asdict()}; sampler "
        f'"{sampler_label(config)}". A replication is right when the verdict (first round) is one of '
        "the right verdicts (trafficgen's table, reports/criticism/generator.md); with two "
        "mechanisms, when the final model holds a right verdict of each. Out-of-reach mechanisms "
        "have none, and their row shows what criticize said instead; 'final models' counts the "
        "models the loop ended with (a cause beyond the right ones is a false positive of a "
        "later round). Intervals: Wilson 95%. Seeds: replication r of every cell uses the r-th seed of "
        f"the range ({'development' if dev else 'study'} seeds from "
        f"{(DEV_SEEDS if dev else STUDY_SEEDS).start}, or where a rerun's --first-seed put "
        "them; each row names its seeds)."
        + (
            " With rollouts, 'adopted right' counts the replications whose loop adopted a right "
            "cause of the mechanism (null data: adopted nothing), by criticize's adoption rule "
            "(the 5 s energy score from the filtered start better by a paired test with Holm over "
            "the round's causes, the predictive mean not worse, no added collisions)."
            if judged
            else ""
        )
        + "\n\n"
        + "\n".join(lines)
        + f"\n\nCells right in all of at least {CLAIM_REPLICATIONS} replications: "
        + (", ".join(f"{r.cell} {r.size}" for r in reliable.itertuples()) or "none yet")
        + ".\n"
    )
    rerun = reruns(runs)
    if rerun:
        text += (
            f"\nReplications of other library versions rerun at {CODE} (same cell, size and "
            "seed; identical = the same verdict, final model, rightness, best right gain and its "
            "SE, and screening):\n\n" + "\n".join(rerun) + "\n"
        )
    # detection[_dev][_adoption].md, its hand-written reading kept
    write_keeping_findings(out / runs_path.name.replace("_runs.csv", ".md"), text)
    return text


def run_shards(args: argparse.Namespace) -> int:
    """Run shards 0/N..N-1/N of this study as N processes, each pinned to one of this process's
    cores (XLA's threads then stay on it); return how many ended with an error."""
    cores = sorted(os.sched_getaffinity(0))
    common = [sys.executable, str(Path(__file__).resolve()), "--out", str(args.out)]
    common += ["--cells", args.cells, "--sizes", args.sizes]
    common += ["--replications", str(args.replications)]
    common += ["--null-replications", str(args.null_replications)]
    common += ["--dev"] if args.dev else []
    common += ["--first-seed", str(args.first_seed), "--rollouts", str(args.rollouts)]
    common += ["--platoons", str(args.platoons), "--duration-s", str(args.duration_s)]
    common += ["--causes", args.causes]
    common += ["--stop-at", str(args.stop_at)] if args.stop_at is not None else []
    shards = []
    for k in range(args.jobs):
        core = cores[k % len(cores)]
        shards.append(
            subprocess.Popen(
                [*common, "--shard", f"{k}/{args.jobs}"],
                preexec_fn=functools.partial(os.sched_setaffinity, 0, {core}),
            )
        )
    return sum(shard.wait() != 0 for shard in shards)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replications", type=int, default=20, help="per mechanism and size")
    parser.add_argument("--null-replications", type=int, default=40)
    parser.add_argument(
        "--cells",
        default=",".join([NULL, *MECHANISMS, *("+".join(p) for p in PAIRS)]),
        help="comma-separated: none, mechanisms, pairs a+b",
    )
    parser.add_argument("--sizes", default=",".join(SIZES))
    parser.add_argument("--dev", action="store_true", help="development seeds and files")
    parser.add_argument(
        "--first-seed",
        type=int,
        default=STUDY_SEEDS.start,
        help="the study's first seed (fresh seeds for a rerun, fixed before it runs)",
    )
    parser.add_argument(
        "--rollouts", type=int, default=0, help="rollouts per model: >0 also judges adoption"
    )
    parser.add_argument(
        "--platoons",
        type=int,
        default=DETECTION_SCENARIO["platoons"],
        help="platoons per replication (CI's scenario by default); another size needs its own --out",
    )
    parser.add_argument(
        "--duration-s",
        type=float,
        default=DETECTION_SCENARIO["duration_s"],
        help="seconds recorded per replication (CI's scenario by default); another length needs "
        "its own --out",
    )
    parser.add_argument(
        "--causes",
        default=",".join(DETECTION_CONFIG.causes),
        help="comma-separated: the family criticize screens (CI's by default); another family "
        "needs its own --out",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "reports" / "criticism")
    parser.add_argument("--report-only", action="store_true", help="redraw the table from the CSV")
    parser.add_argument("--shard", default="0/1", help="K/N: every N-th replication from the K-th")
    parser.add_argument(
        "--stop-at", type=float, default=None, help="start no replication after this Unix time"
    )
    parser.add_argument(
        "--jobs", type=int, default=1, help="N: run shards 0/N..N-1/N at once, one per core"
    )
    args = parser.parse_args(argv)
    # The rows do not record the scenario: rows of another size must not join CI's study.
    scenario = {**DETECTION_SCENARIO, "platoons": args.platoons, "duration_s": args.duration_s}
    if scenario != DETECTION_SCENARIO and args.out == parser.get_default("out"):
        parser.error(f"{scenario} is not CI's scenario: give it its own --out")
    causes = tuple(args.causes.split(","))
    if causes != DETECTION_CONFIG.causes and args.out == parser.get_default("out"):
        parser.error(f"causes {causes} are not CI's family: give them their own --out")
    args.out.mkdir(parents=True, exist_ok=True)
    config = study_config(args.rollouts, causes)
    fields = ADOPTION_FIELDS if args.rollouts else FIELDS
    runs_path = runs_file(args.out, dev=args.dev, rollouts=args.rollouts)
    if args.report_only:
        print(write_report(runs_path, args.out, dev=args.dev, config=config, scenario=scenario))
        return 0
    if args.jobs > 1:
        if args.shard != "0/1":
            parser.error("--jobs runs every shard itself; give --shard or --jobs, not both")
        failed = run_shards(args)
        if runs_path.exists():
            print(write_report(runs_path, args.out, dev=args.dev, config=config, scenario=scenario))
        return 1 if failed else 0
    seeds = DEV_SEEDS if args.dev else range(args.first_seed, args.first_seed + len(STUDY_SEEDS))
    unknown = [
        c for c in args.cells.split(",") for m in c.split("+") if m not in (NULL, *MECHANISMS)
    ]
    if unknown:
        parser.error(f"unknown cell(s) {unknown}; known: {[NULL, *MECHANISMS]} and pairs a+b")
    done = set()
    if runs_path.exists():
        header = runs_path.read_text().splitlines()[0].split(",")
        if header != fields:
            parser.error(
                f"{runs_path} has the columns of another version of this study ({header}); "
                "move it aside to start a new one"
            )
        previous = pd.read_csv(runs_path)
        current = previous[
            (previous["sampler"] == sampler_label(config))
            & (previous["generator"].isin(CURRENT_GENERATORS))
            & (previous["code"] == CODE)
        ]
        done = set(zip(current["cell"], current["size"], current["seed"], strict=True))
    try:
        shard, shards = (int(part) for part in args.shard.split("/"))
    except ValueError:
        parser.error(f"--shard {args.shard!r}: give K/N, two integers")
    if not 0 <= shard < shards:
        parser.error(f"--shard {args.shard}: K must be in 0..N-1")
    plan = [
        (cell, size, seeds[r])
        for r in range(max(args.replications, args.null_replications))
        for cell, size in planned_cells(args.cells.split(","), args.sizes.split(","))
        if r < (args.null_replications if cell == NULL else args.replications)
    ]
    # Sliced before the finished rows are dropped, so a shard's share never depends on when it
    # started or on what the others have finished.
    todo = [item for item in plan[shard::shards] if item not in done]
    print(f"{len(done)} replications done, {len(todo)} to go in shard {args.shard}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for i, (cell, size, seed) in enumerate(todo, 1):
            if args.stop_at is not None and time.time() > args.stop_at:
                print(f"stopped at --stop-at with {len(todo) - i + 1} to go", flush=True)
                break
            try:
                row = run_one(cell, size, seed, Path(tmp), config, scenario)
            except Exception as error:  # a crash on independent data is a miss, kept on record
                row = dict.fromkeys(fields, "")
                row.update(cell=cell, size=size, seed=seed, right=0, sampler=sampler_label(config))
                row.update(generator=GENERATOR, code=CODE)
                row["verdict"] = f"error: {type(error).__name__}: {error}"[:200]
            append_rows(runs_path, [row], fields)
            print(f"[{i}/{len(todo)}] {row}", flush=True)
    if runs_path.exists():  # a shard stopped before its first row has nothing to report
        print(write_report(runs_path, args.out, dev=args.dev, config=config, scenario=scenario))
    return 0


if __name__ == "__main__":
    sys.exit(main())
