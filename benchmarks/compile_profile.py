"""Where the test suite's time goes: how much of each test is JAX tracing, lowering and XLA
compiling, which programs compile longest, and how many compiles are small eager operations.

Runs the README's pytest command (two workers) with ``benchmarks/compile_log`` on ``PYTHONPATH``,
so every process, subprocesses and Dask workers included, logs its compile events with the test
that caused it and the line of bayesdrive that did; then joins them with pytest's
``--durations=0``. Writes ``<out>/summary.md``.

    PYTHONPATH=. python benchmarks/compile_profile.py --out compile-profile       # the suite
    PYTHONPATH=. python benchmarks/compile_profile.py --out p --tests tests/inference/test_lm.py
    PYTHONPATH=. python benchmarks/compile_profile.py --out compile-profile --summary-only

Compile events of subprocesses count toward the test that started them, so a test whose
subprocesses compile side by side can show more compile time than its duration.
"""

from __future__ import annotations

import argparse
import collections
import os
import re
import subprocess
import sys
from pathlib import Path

from bayesdrive.data.atomic import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]
EVENT = re.compile(
    r"Finished (tracing|jaxpr to MLIR module conversion|XLA compilation) (?:of )?(\S+).* in "
    r"([0-9.e-]+) sec"
)
KIND = {
    "tracing": "trace",
    "jaxpr to MLIR module conversion": "lower",
    "XLA compilation": "compile",
}
DURATION = re.compile(r"\s*([0-9.]+)s (?:setup|call|teardown)\s+(\S+)")
# A compile shorter than this is an eager operation's or a small helper's.
SMALL_S = 1.0


def run_suite(out: Path, tests: list[str]) -> None:
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    env = {
        **os.environ,
        "COMPILE_LOG_DIR": str(logs),
        "PYTHONPATH": os.pathsep.join(
            filter(None, [str(ROOT / "benchmarks" / "compile_log"), os.environ.get("PYTHONPATH")])
        ),
    }
    command = [sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist", "worksteal"]
    command += ["--durations=0", "-p", "no:cacheprovider", *tests]
    with open(out / "pytest.log", "w") as log:
        subprocess.run(
            command, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, check=False
        )


def ranked_table(
    title: str, preface: str, what: str, times: dict[str, list[float]], rows: int
) -> list[str]:
    """A section of the summary: ``times``'s keys ranked by their summed seconds."""
    lines = ["", title, "", f"{preface}| seconds | compiles | {what} |", "|---|---|---|"]
    ranked = sorted(times.items(), key=lambda item: -sum(item[1]))
    for name, seconds in ranked[:rows]:
        lines.append(f"| {sum(seconds):.1f} | {len(seconds)} | `{name}` |")
    return lines


def summarize(out: Path) -> str:
    per_test: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    per_program: dict[str, list[float]] = collections.defaultdict(list)
    small = collections.Counter()
    small_sites: dict[str, list[float]] = collections.defaultdict(list)
    hits = misses = 0
    for path in sorted((out / "logs").glob("*.log")):
        for line in path.read_text().splitlines():
            fields = line.split("\t", 3)
            # Logs written before the call site was recorded have three fields.
            test, site, message = (fields[1], "-", fields[2]) if len(fields) == 3 else fields[1:]
            test = test.split(" (")[0]
            if "cache hit" in message.lower():
                hits += 1
            elif "CACHE MISS" in message:
                misses += 1
            found = EVENT.search(message)
            if not found:
                continue
            kind, program, seconds = KIND[found[1]], found[2], float(found[3])
            per_test[test][kind] += seconds
            if kind == "compile":
                per_program[program].append(seconds)
                if seconds < SMALL_S:
                    small["count"] += 1
                    small["seconds"] += seconds
                    small_sites[site].append(seconds)
    pytest_lines = (out / "pytest.log").read_text().splitlines()
    durations = collections.Counter()
    for line in pytest_lines:
        found = DURATION.match(line)
        if found:
            durations[found[2]] += float(found[1])
    total = collections.Counter()
    for counts in per_test.values():
        total.update(counts)
    jax_time = {t: c["trace"] + c["lower"] + c["compile"] for t, c in per_test.items()}
    tail = [line for line in pytest_lines if " in " in line]
    lines = [
        "# Where the test suite's time goes",
        "",
        f"pytest: {tail[-1].strip('= ') if tail else 'no summary line'}",
        "",
        f"- Test durations add up to {sum(durations.values()):.0f} s.",
        f"- JAX, summed over every process: tracing {total['trace']:.0f} s, lowering "
        f"{total['lower']:.0f} s, XLA compiling {total['compile']:.0f} s.",
        f"- Compiles under {SMALL_S:.0f} s: {small['count']} of them, {small['seconds']:.0f} s.",
        f"- Persistent compilation cache: {hits} hits, {misses} misses.",
        "",
        "## Slowest tests",
        "",
        "| seconds | of which JAX (trace + lower + compile) | test |",
        "|---|---|---|",
    ]
    for test, seconds in durations.most_common(30):
        lines.append(f"| {seconds:.1f} | {jax_time.get(test, 0.0):.1f} | `{test}` |")
    lines += ranked_table("## Programs by compile time", "", "program", per_program, 25)
    lines += ranked_table(
        f"## Compiles under {SMALL_S:.0f} s by call site",
        "The innermost line of bayesdrive's code on the stack when JAX compiled (`-`: none, such "
        "as a test's own JAX call).\n\n",
        "call site",
        small_sites,
        40,
    )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--tests", nargs="*", default=[], help="pytest arguments (default: all)")
    parser.add_argument("--summary-only", action="store_true", help="summarise an earlier run")
    args = parser.parse_args()
    if not args.summary_only:
        if (args.out / "logs").exists():
            parser.error(f"{args.out / 'logs'} exists: give a new --out, or --summary-only")
        run_suite(args.out, args.tests)
    summary = summarize(args.out)
    write_text_atomic(args.out / "summary.md", summary)
    print(summary)


if __name__ == "__main__":
    main()
