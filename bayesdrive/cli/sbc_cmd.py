"""``bayesdrive sbc``: simulation-based calibration of an engine on any registered driver model.

Draws parameters from the model's prior box, simulates one follower per replication behind a replayed
synthetic leader, fits all replications in one engine call and tests the ranks of the truths for
uniformity per parameter (chi-square, judged at alpha / K: Bonferroni; KS reported). See
:mod:`bayesdrive.inference.diagnostics.sbc`. ``--sd-doubled`` fits a deliberately wrong likelihood (twice the
noise sd): a study with power must reject it. Exit code 0 whether or not calibration holds: the
verdict is in the output.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from bayesdrive.cli.common import (
    ForceResults,
    JsonOut,
    console,
    emit_json,
    fail,
    optional_results,
    progress_bar,
    results_command,
)
from bayesdrive.cli.names import ENGINES as ENGINE_NAMES
from bayesdrive.data.atomic import write_text_atomic

if TYPE_CHECKING:
    from bayesdrive.inference.diagnostics.sbc import SBCOutcome

__all__ = ["sbc", "write_outcome"]

# Engines whose prior is not the uniform box SBC draws from.
POPULATION_ENGINES = ("hierarchical",)


def write_outcome(outcome: SBCOutcome, out: Path, stem: str) -> list[Path]:
    """Rank histograms (PNG), the ranks with their truths (CSV) and the digest (JSON) in ``out``."""
    from bayesdrive.reports.diagnostic_plots import plot_rank_ecdf

    header = ",".join(["replication", *(f"truth_{n}" for n in outcome.names)])
    header += "," + ",".join(f"rank_{n}" for n in outcome.names)
    lines = [header]
    for r in range(outcome.ranks.shape[0]):
        values = [str(r), *(repr(float(v)) for v in outcome.truth[r])]
        values += [str(int(v)) for v in outcome.ranks[r]]
        lines.append(",".join(values))
    ranks_path = out / f"{stem}_ranks.csv"
    summary_path = out / f"{stem}.json"
    write_text_atomic(ranks_path, "\n".join(lines) + "\n")
    write_text_atomic(summary_path, json.dumps(outcome.summary(), indent=2) + "\n")
    figure = plot_rank_ecdf(outcome, out / f"{stem}_ranks.png")
    return [figure, ranks_path, summary_path]


def _print(outcome: SBCOutcome) -> None:
    import numpy as np

    level = outcome.alpha / len(outcome.names)
    table = Table(
        title=escape(
            f"SBC of {outcome.engine} fitting {outcome.fit_model}: {outcome.ranks.shape[0]} "
            f"replications x {outcome.num_steps} steps, {outcome.num_ranks} ranks in "
            f"{outcome.bins} bins, seed {outcome.seed}"
        ),
        title_justify="left",
    )
    for column in ("param", "chi2 p", "KS p", f"{outcome.interval:.0%} coverage", "min ESS"):
        table.add_column(column, justify="left" if column == "param" else "right")
    for k, name in enumerate(outcome.names):
        flag = " [red](reject)[/red]" if outcome.chi2_pvalue[k] < level else ""
        table.add_row(
            name,
            f"{outcome.chi2_pvalue[k]:.3g}{flag}",
            f"{outcome.ks_pvalue[k]:.3g}",
            f"{outcome.coverage[k]:.2f}",
            f"{np.min(outcome.ess[:, k]):.0f}",
        )
    console.print(table)
    verdict = (
        "[green]no miscalibration found[/green]"
        if outcome.calibrated
        else "[red]miscalibrated[/red]"
    )
    console.print(
        f"{verdict} (chi-square at alpha={outcome.alpha} / {len(outcome.names)} parameters = "
        f"{level:.3g}, Bonferroni); compile {outcome.compile_time_s:.1f} s, "
        f"inference {outcome.wall_time_s:.1f} s"
    )


@results_command
def sbc(
    engine: str = typer.Option(
        ..., "--engine", help=f"Engine to calibrate: {', '.join(ENGINE_NAMES)}."
    ),
    replications: int = typer.Option(200, "--replications", min=10, help="Simulated vehicles."),
    seed: int = typer.Option(0, "--seed", help="Seed of prior draws, simulation and fits."),
    model_name: str = typer.Option(
        "idm",
        "--model",
        help="Driver model to simulate and fit: a base model, or one joined by '+' to extensions.",
    ),
    params: str | None = typer.Option(
        None, "--params", help="Comma-separated parameters to infer (default: all the model's)."
    ),
    steps: int = typer.Option(64, "--steps", min=2, help="Steps (0.1 s) per simulated vehicle."),
    ranks: int = typer.Option(
        99, "--ranks", min=9, help="Posterior draws each truth is ranked in."
    ),
    alpha: float = typer.Option(0.01, "--alpha", help="Family-wise level of the uniformity tests."),
    particles: int | None = typer.Option(
        None, "--particles", help="Draws per replication (the engine's num_particles)."
    ),
    sd_doubled_model: bool = typer.Option(
        False, "--sd-doubled", help="Fit the deliberately wrong 2-sigma likelihood (power check)."
    ),
    out: Annotated[
        Path | None, typer.Option("--out", help="Folder for histograms, ranks, digest.")
    ] = None,
    json_out: JsonOut = None,
    force: ForceResults = False,
) -> None:
    """Simulation-based calibration: are the engine's posteriors calibrated on the model?"""
    # Imported here so that `bayesdrive sbc --help` does not import JAX.
    import jax

    from bayesdrive.drivers.registry import get_model
    from bayesdrive.inference.diagnostics.sbc import run_sbc, sd_doubled
    from bayesdrive.inference.fit import ENGINES, check_engine_model

    if engine not in ENGINES:
        raise fail(f"unknown engine {engine!r}; choose one of {', '.join(ENGINES)}")
    if engine in POPULATION_ENGINES:
        raise fail(
            f"{engine} fits replications jointly under its own population prior; SBC simulates "
            "from the uniform prior box, so the ranks would test the prior, not the engine"
        )
    try:
        model = get_model(model_name)
        check_engine_model(engine, model)
        fit_model = sd_doubled(model) if sd_doubled_model else model
    except KeyError as error:  # an unknown or ill-composed model name
        raise fail(error.args[0]) from error
    except ValueError as error:
        raise fail(str(error)) from error
    names = None if params is None else [p.strip() for p in params.split(",") if p.strip()]
    options: dict[str, Any] = {} if particles is None else {"num_particles": particles}
    results = optional_results(out, "sbc", json_out=json_out, force=force)
    with progress_bar() as bar:
        task = bar.add_task(f"SBC {engine}: fitting replications", total=replications)
        try:
            outcome = run_sbc(
                jax.random.key(seed),
                ENGINES[engine],
                engine_name=engine,
                model=model,
                params=names,
                fit_model=fit_model,
                num_replications=replications,
                num_steps=steps,
                num_ranks=ranks,
                alpha=alpha,
                engine_options=options,
                seed=seed,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
            )
        except ValueError as error:
            raise fail(str(error)) from error
    result = outcome.summary()
    if results is not None:
        stem = f"sbc_{engine}" + ("_sd_doubled" if sd_doubled_model else "")
        written = write_outcome(outcome, results.path, stem)
        results.commit()
        result["files"] = [str(out / p.name) for p in written]
    if emit_json(result, json_out):
        return
    _print(outcome)
    if out is not None:
        console.print(f"histograms, ranks and digest written to {escape(str(out))}")
