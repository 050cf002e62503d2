"""The reproduction report: every experiment of the paper on held-out real data, as one HTML page.

Built from the results :mod:`bayesdrive.experiments.paper` saved; figures are drawn here into the
output folder and embedded in the page.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from bayesdrive.data.atomic import write_atomic
from bayesdrive.drivers.closed_loop import FILTERED, STATIONARY
from bayesdrive.drivers.registry import MODELS
from bayesdrive.inference.diagnostics.agreement import agreement_summary, agreement_table
from bayesdrive.reports.filter_plots import plot_convergence
from bayesdrive.reports.html import Report, Section
from bayesdrive.simulation.platoon import CONGESTED_SPEED
from bayesdrive.simulation.two_sample import BOOSTING

__all__ = ["build_report"]

LEFT_OUT_NOTE = "Left out of this run: `bayesdrive reproduce --full` runs it."
PAPER_NOTE = (
    "The paper's published code did not filter in its 'ours' column, picked seeds on test error, "
    "and scored a likelihood whose spread was off by a factor of 2; it reported a mean absolute "
    "error at the last step as 'RMSE'. Here every model is fitted on each vehicle's fitting window "
    "only, scored on its later held-out window, with seeds fixed in advance; the RMSE is the true "
    "root mean square over vehicles and rollouts, and the paper's variant is shown beside it."
)

PLATOON_NOTE = (
    "Realism columns give the simulation's value with the observed platoon's in brackets. "
    "Speed-variation amplification per vehicle (string stability): how much a follower's speed "
    "varies over the window against the vehicle ahead of it, pooled over consecutive pairs; above "
    "1, disturbances grow down the platoon. Wave speed: the speed at which a change of speed "
    "travels back, from Newell's shift between consecutive vehicles, on congested pairs only "
    f"(mean speed at most {CONGESTED_SPEED:g} m/s); '-' where no pair is congested and varies its "
    "speed."
)

# Every driver-model parameter's unit, for table headers and axis labels.
UNITS = {spec.name: spec.unit for model in MODELS.values() for spec in model.specs}
LEGEND_FONTSIZE = 9
# The agreement summary's columns (bayesdrive.inference.diagnostics.agreement) as a reader names them.
AGREEMENT_HEADERS = {
    "a": "engine",
    "b": "reference engine",
    "param": "parameter",
    "vehicles": "vehicles",
    "agree": "share of vehicles agreeing",
    "agree_mean": "share agreeing on the mean",
    "agree_sd": "share agreeing on the sd",
    "max_abs_mean_diff_sd": "largest mean difference (reference sds)",
    "median_sd_ratio": "median sd ratio (engine / reference)",
    "max_wasserstein_sd": "largest Wasserstein-1 distance (reference sds)",
}


def with_unit(param: str) -> str:
    """A parameter name with its unit, e.g. 'v_des (m/s)'; dimensionless ones without."""
    unit = UNITS.get(param, "--")
    return param if unit in ("--", "") else f"{param} ({unit})"


def _save(fig: Figure, path: Path) -> Path:
    write_atomic(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    return path


def _mean_sd(entry: dict[str, Any]) -> str:
    sd = entry.get("sd")
    return f"{entry['mean']:.2f}" + (f" ± {sd:.2f}" if sd is not None else "")


def highway_table(models: dict[str, Any]) -> pd.DataFrame:
    rows = []
    for name, result in models.items():
        paper = result["paper_mae_last_step"]
        rows.append(
            {
                "model": name,
                "start": result.get("start", STATIONARY),
                "RMSE position at 5 s (m)": _mean_sd(result["rmse_position_m"]),
                "RMSE speed at 5 s (m/s)": _mean_sd(result["rmse_speed_mps"]),
                "paper's MAE position, last step (m)": _mean_sd(paper["position_m"]),
                "collisions": result["collisions"]["total"],
                "colliding vehicle-rollouts": f"{result['collisions']['fraction']:.2%}",
                "hard braking per rollout (data)": f"{result['hard_braking']['per_rollout']:.1f}"
                + f" ({result['hard_braking']['data_total']})",
                "jerk RMS, m/s^3 (data)": _realism(result, "jerk_mps3", "rms", ".1f"),
                "min TTC < 1.5 s, share (data)": _realism(
                    result, "min_ttc", "share_critical", ".1%"
                ),
                "speed-variation amplification per vehicle (data)": _realism(
                    result, "string_stability", "amplification", ".2f"
                ),
                "wave speed upstream, m/s (data)": _realism(
                    result, "wave_speed_mps", "upstream", ".1f"
                ),
                "CRPS position at 5 s (m)": _scored(result, "crps_position_m"),
                "energy score of the (gap, speed) path (1 m, 1 m/s)": _scored(
                    result, "energy_score_path"
                ),
                "50% / 90% interval covers the position at 5 s": _coverage(result),
                "speed distribution: Wasserstein-1 to data (m/s)": f"{result['speed_distribution_mps']['wasserstein']:.2f}",
            }
        )
    return pd.DataFrame(rows)


def _realism(result: dict[str, Any], measure: str, name: str, spec: str) -> str:
    """A realism measure of the simulation with the data's beside it, "-" for results written
    before it was measured and for a value that could not be (no pair to measure it on)."""
    if measure not in result:
        return "-"
    entry = result[measure]

    def value(side: str) -> str:
        found = entry[f"{side}_{name}"]
        return "-" if found is None else f"{found:{spec}}"

    return f"{value('simulated')} ({value('observed')})"


def _scored(result: dict[str, Any], name: str) -> str:
    """A proper score's mean and sd, "-" for results written before the score was."""
    return _mean_sd(result[name]) if name in result else "-"


def _coverage(result: dict[str, Any]) -> str:
    """The last-step position's interval coverage, "-" for results written before it was."""
    if "calibration_position" not in result:
        return "-"
    entry = result["calibration_position"]
    return f"{entry['coverage_50']:.2f} / {entry['coverage_90']:.2f}"


def _interval(paired: dict[str, Any]) -> str:
    return f"{paired['mean']:+.2f} [{paired['low']:+.2f}, {paired['high']:+.2f}]"


def _ci(result: dict[str, Any]) -> str:
    return f"{result['ci_low']:.2f}-{result['ci_high']:.2f}"


def turing_table(rows: dict[str, Any]) -> pd.DataFrame:
    """Both Turing classifiers' accuracies side by side, one row per model; results saved before
    the boosted classifier existed show "-" in its columns."""
    frame = []
    for name, result in rows.items():
        levels, boosted = result["levels_only"], result.get("boosted")
        frame.append(
            {
                "model": name,
                "accuracy, logistic": f"{result['accuracy']:.3f}",
                "95% CI (approx.)": _ci(result),
                "p (better than chance)": f"{result['p_value']:.3f}",
                "accuracy, logistic on levels only": f"{levels['accuracy']:.3f}",
                "95% CI, levels only": _ci(levels),
                "accuracy, boosted": _share(boosted and boosted["accuracy"]),
                "95% CI, boosted (approx.)": "-" if boosted is None else _ci(boosted),
                "p, boosted": _share(boosted and boosted["p_value"]),
            }
        )
    return pd.DataFrame(frame)


def holdout_table(entry: dict[str, Any]) -> pd.DataFrame:
    """One held-out data set's methods, with the paired difference of each learned model (the
    keys of ``entry["paired"]``: the per-vehicle fit and the population predictive) minus each
    method: per-scenario mean and 95% bootstrap interval."""
    learned = tuple(entry["paired"])
    rows = []
    for name, r in entry["models"].items():
        row = {
            "method": name,
            "scenarios": r["scenarios"],
            "RMSE position (m)": _mean_sd(r["rmse_position_m"]),
            "RMSE speed (m/s)": _mean_sd(r["rmse_speed_mps"]),
            "collisions": r["collisions"]["total"],
        }
        for model in learned:
            against = entry["paired"][model].get(name)
            for metric, label in (
                ("rmse_position_m", "position (m)"),
                ("rmse_speed_mps", "speed (m/s)"),
            ):
                row[f"{model} minus this, {label} [95%]"] = (
                    _interval(against[metric]) if against else "-"
                )
        rows.append(row)
    return pd.DataFrame(rows)


def forecast_table(forecast: dict[str, Any]) -> pd.DataFrame:
    """The final model's forecast comparison on one held-out data set: per method its start, the
    CRPS of the position at the horizon, the predictive mean's RMSE beside the RMSE over rollouts,
    collisions, and the final model minus the method: per-scenario mean and 95% bootstrap
    interval of the CRPS and of the predictive mean's squared error."""
    rows = []
    for name, r in forecast["models"].items():
        against = forecast["paired"].get(name)
        rows.append(
            {
                "method": name,
                "start": r["start"],
                "CRPS position (m)": _mean_sd(r["crps_position_m"]),
                "predictive-mean RMSE (m)": f"{r['predictive_mean_rmse_position_m']:.2f}",
                "RMSE over rollouts (m)": f"{r['rmse_position_m']:.2f}",
                "collisions": r["collisions"],
                "final minus this, CRPS [95%]": _interval(against["crps_position_m"])
                if against
                else "-",
                "final minus this, squared error of the mean (m^2) [95%]": _interval(
                    against["predictive_mean_sq_error_m2"]
                )
                if against
                else "-",
            }
        )
    return pd.DataFrame(rows)


def calibration_table(entry: dict[str, Any]) -> pd.DataFrame:
    """One held-out data set's forecast scores: per model, start and lead time, the windows, the
    proper scores (CRPS of gap, position and speed; energy score of the (gap, speed) path), the
    predictive mean's RMSE beside the RMSE over rollouts, the coverage of the central 50% and 90%
    predictive intervals, the PIT histogram's chi-square p-value and constant velocity on the same
    windows; a start the model cannot take shows why."""
    rows = []
    for model, result in entry["models"].items():
        for start, scored in result["starts"].items():
            if "error" in scored:
                rows.append({"model": model, "start": start, "windows": scored["error"][:120]})
                continue
            for lead_time, h in scored["horizons"].items():
                rows.append(
                    {
                        "model": model,
                        "start": start,
                        "lead time (s)": lead_time,
                        "windows": h["windows"],
                        "CRPS gap (m)": _share(h["crps_gap_m"], "{:.2f}"),
                        "CRPS position (m)": _share(h["crps_m"], "{:.2f}"),
                        "CRPS speed (m/s)": _share(h["crps_speed_mps"], "{:.2f}"),
                        "energy score (gap/1 m, speed/1 m/s)": _share(h["energy_score"], "{:.2f}"),
                        "RMSE of the mean (m)": _share(h["rmse_mean_m"], "{:.2f}"),
                        "RMSE over rollouts (m)": _share(h["rmse_rollouts_m"], "{:.2f}"),
                        "50% interval covers": _share(h["coverage_50"]),
                        "90% interval covers": _share(h["coverage_90"]),
                        "PIT uniform: chi-square p": _share(h["pit_chi2_p"], "{:.2g}"),
                        "constant velocity RMSE (m)": _share(
                            h["constant_velocity_rmse_m"], "{:.2f}"
                        ),
                        "CRPS minus constant velocity's absolute error (m) [95%, by driver]": (
                            _by_driver(h["minus_constant_velocity"]["crps_minus_abs_error_m"])
                        ),
                    }
                )
    return pd.DataFrame(rows)


def _by_driver(difference: dict[str, Any]) -> str:
    if difference["mean"] is None:
        return "-"
    if difference["low"] is None:
        return f"{difference['mean']:+.2f} (1 driver)"
    return _interval(difference)


def _share(value: float | None, form: str = "{:.3f}") -> str:
    return "-" if value is None else form.format(value)


def plot_pit_histograms(data_sets: dict[str, Any], path: Path) -> Path:
    """PIT histograms of the ``filtered`` forecasts: one row per held-out data set, one column per
    lead time, one line per model (density; a calibrated predictive lies on 1)."""
    shown = {name: entry for name, entry in data_sets.items() if "error" not in entry}

    def filtered(result: dict[str, Any]) -> dict[str, Any]:
        return result["starts"].get(FILTERED, {}).get("horizons", {})

    horizons = sorted(
        {h for e in shown.values() for m in e["models"].values() for h in filtered(m)}, key=float
    )
    # One colour per model in every panel, and every model in the legend: a set where only the
    # IDM was fitted would otherwise leave the others out of a legend read from one panel.
    models = list(dict.fromkeys(m for e in shown.values() for m in e["models"]))
    colours = {model: f"C{i}" for i, model in enumerate(models)}
    fig = Figure(figsize=(4.2 * len(horizons), 2.2 * len(shown) + 0.6), layout="constrained")
    axes = np.atleast_2d(fig.subplots(len(shown), len(horizons), squeeze=False))
    for row, (name, entry) in enumerate(shown.items()):
        for col, horizon in enumerate(horizons):
            ax = axes[row, col]
            for model, result in entry["models"].items():
                h = filtered(result).get(horizon)
                if not h or not h["windows"]:
                    continue
                counts = np.asarray(h["pit_counts"], float)
                density = counts / counts.sum() * len(counts)
                edges = np.linspace(0.0, 1.0, len(counts) + 1)
                ax.stairs(density, edges, color=colours[model], lw=1.5)
            ax.axhline(1.0, color="grey", lw=0.8, ls="--")
            ax.set_title(f"{name}, {horizon} s ahead ({FILTERED})", fontsize=9)
            ax.set(xlabel="PIT of the observed position", ylabel="density")
    # Below the panels: inside one it hides the histogram's bars at its edges.
    handles = [Line2D([], [], color=colours[model], lw=1.5) for model in models]
    fig.legend(
        handles,
        models,
        loc="outside lower center",
        ncols=len(models),
        fontsize=LEGEND_FONTSIZE,
        title="model",
    )
    return _save(fig, path)


def calibration_section(section: Section, calibration: dict[str, Any], figures: Path) -> None:
    """Calibration of the predictive on the held-out windows (protocol point 6)."""
    section.text(
        "The IDM and the final model the criticism chose on the training data set of the same "
        "kind, each fitted by smc (defaults) to the held-out followers' fitting windows, forecast "
        "1, 2, 3 and 5 s ahead from the start of every 5 s held-out window, behind the replayed "
        "leader, from two starts: filtered (the model's state, such as an autocorrelated "
        "residual or a delay's past, taken from the window's observed history; the forecast) and "
        "stationary (the same without that history). Proper scores (scoringrules): the CRPS of "
        "gap, position and speed (with the leader replayed, the gap's and the position's agree) "
        "and the energy score of the joint (gap, speed) path up to the lead time, in units of "
        "1 m and 1 m/s (fixed, not from the data); lower is better. Beside them the predictive "
        "mean's RMSE and the RMSE over rollouts (what the closed-loop tables report: the mean's "
        "error and the rollouts' spread in quadrature, so it penalises a calibrated spread and "
        "decides nothing). A calibrated predictive covers the observation by its central 50% and "
        "90% intervals at those rates and gives uniform PITs (the chi-square p-value is "
        "descriptive: windows of one driver are dependent). The CRPS equals the absolute error "
        "for a point forecast, so it is compared with constant velocity's from each window's "
        "observed first speed (mean over drivers of each driver's mean difference, 95% t "
        "interval across drivers; negative: the model is closer)."
    )
    for name, entry in calibration["data_sets"].items():
        if "error" in entry:
            section.note(f"{name}: not evaluated: {entry['error'][:160]}")
            continue
        section.table(
            calibration_table(entry),
            caption=f"{name}: final model chosen on {entry['training_data']}",
        )
    section.figure(
        plot_pit_histograms(calibration["data_sets"], figures / "holdout_pit.png"),
        "PIT histograms on the held-out windows",
    )


def criticism_folder(out: Path, label: str) -> Path:
    """Where a reproduction's criticism of highway data set ``label`` keeps its JSON and figures."""
    return out / "criticism" / label.replace(":", "_")


def figure_paths(recorded: list[str], folder: Path) -> list[Path]:
    """A step's figures in ``folder``: a step records them by name (as it records its fits), so a
    results folder may move or be staged elsewhere and renamed into place; results written
    before recorded whole paths, whose names are the same."""
    return [folder / Path(name).name for name in recorded]


def holdout_section(section: Section, holdout: dict[str, Any]) -> None:
    """The held-out section: the protocol, then one table per data set (why a set was not
    evaluated, where it was not) with its training population and who drives."""
    section.text(holdout["protocol"])
    section.note(
        "A negative paired difference means the learned model (idm-smc, fitted per vehicle, or "
        "idm-population, the population predictive for a driver with no data) is closer to the "
        "data than the method of its row. The row idm-smc-pooled-ngsim is what this section reported "
        "before: the pooled NGSIM I-80 posterior applied to every driver of every data set."
    )
    if holdout.get("left_out_by_settings"):
        section.note(
            f"Not evaluated in this run, whose settings take only "
            f"{', '.join(holdout['data_sets'])}: {', '.join(holdout['left_out_by_settings'])}."
        )
    for name, entry in holdout["data_sets"].items():
        if "error" in entry:
            section.note(f"{name}: not evaluated: {entry['error'][:160]}")
            continue
        drivers = f"; {entry['acc']}" if entry["acc"] else ""
        divergences = entry["population_divergences"]
        diverged = f", {divergences} divergent transition(s)" if divergences else ""
        section.table(
            holdout_table(entry),
            caption=f"{name}: population from {entry['training_data']} "
            f"({entry['population_vehicles']} drivers, two-stage; smallest importance ESS of a "
            f"vehicle {entry['population_min_importance_ess']:.0f}{diverged}){drivers}",
        )
        forecast = entry.get("final_model")
        if forecast is None:
            continue
        if "error" in forecast:
            section.note(
                f"{name}: the final model's forecast was not compared: {forecast['error']}"
            )
            continue
        section.table(
            forecast_table(forecast),
            caption=f"{name}: the final model chosen on {entry['training_data']} "
            f"({forecast['label']}) against the per-vehicle IDM and the baselines, "
            f"{forecast['scenarios']} scenario(s) with the observed history the filtered start "
            f"reads ({forecast['left_out_without_history']} without it left out); negative: the "
            "final model is closer",
        )


def plot_rmse_curves(models: dict[str, Any], path: Path, title: str, dt: float) -> Path:
    """Position and speed RMSE, and the share of vehicle-rollouts with an undesirable event
    (collision, hard braking, off road) so far, over the horizon; means across scenarios."""
    fig = Figure(figsize=(16, 3.8), layout="constrained")
    ax_x, ax_v, ax_e = fig.subplots(1, 3)
    panels = (
        (ax_x, "rmse_position_m"),
        (ax_v, "rmse_speed_mps"),
        (ax_e, "undesirable_events"),
    )
    # A colour of its own for each of up to 20 models (the default cycle repeats after 10), and
    # the legend beside the panels, where it hides no curve.
    colours = matplotlib.colormaps["tab20"].colors
    for i, (name, result) in enumerate(models.items()):
        for ax, key in panels:
            mean = np.array(result[key]["by_step"]["mean"], dtype=float)
            steps = np.arange(len(mean)) * dt
            style = {"color": colours[i % len(colours)], "lw": 2 if "smc" in name else 1}
            ax.plot(steps, mean, label=name, **style)
    ax_x.set(xlabel="horizon (s)", ylabel="position RMSE (m)")
    ax_v.set(xlabel="horizon (s)", ylabel="speed RMSE (m/s)")
    ax_e.set(xlabel="horizon (s)", ylabel="share with an undesirable event so far")
    fig.legend(
        *ax_x.get_legend_handles_labels(),
        loc="outside right upper",
        fontsize=LEGEND_FONTSIZE,
        title="model",
    )
    fig.suptitle(title)
    return _save(fig, path)


def plot_speed_densities(models: dict[str, Any], path: Path, title: str) -> Path:
    """Speed densities of every model's rollouts against the data's on the same steps."""
    fig = Figure(figsize=(6.5, 3.8), layout="tight")
    ax = fig.subplots()
    first = next(iter(models.values()))["speed_density"]
    ax.plot(first["grid_mps"], first["observed"], color="k", lw=2.5, label="data")
    for name, result in models.items():
        density = result["speed_density"]
        ax.plot(density["grid_mps"], density["simulated"], lw=1.2, label=name)
    ax.set(xlabel="speed (m/s)", ylabel="density", title=title)
    ax.legend(fontsize=LEGEND_FONTSIZE)
    return _save(fig, path)


def plot_cooperation(draws: list[float], path: Path) -> Path:
    """The learned cooperation c of the C-IDM against its uniform prior."""
    fig = Figure(figsize=(5, 3.2), layout="tight")
    ax = fig.subplots()
    ax.hist(draws, bins=40, range=(0.0, 1.0), density=True, alpha=0.7, label="posterior (smc)")
    ax.axhline(1.0, color="k", lw=1, ls="--", label="prior (uniform)")
    ax.set(xlabel="cooperation c", ylabel="density", title="C-IDM cooperation, merge episodes")
    ax.legend(fontsize=LEGEND_FONTSIZE)
    return _save(fig, path)


def _short(label: str) -> str:
    """A tick label: 'NGSIM', 'OpenACC human', 'OpenACC ACC'."""
    name, _, part = label.partition(":")
    short = {"ngsim_i80_chains": "NGSIM", "openacc_vicolungo": "OpenACC"}.get(name, name)
    return f"{short}\n{part.replace('-contrast', '')}" if part else short


def plot_parameters(table: pd.DataFrame, path: Path) -> Path:
    """Per-vehicle posterior means, one box per data set and parameter (NGSIM vs free flow)."""
    params = [c for c in table.columns if c not in ("data", "vehicle")]
    fig = Figure(figsize=(12, 3.5), layout="tight")
    axes = fig.subplots(1, len(params))
    labels = list(pd.unique(table["data"]))
    # Data-set names are too long for six narrow panels: letters on the axis, the key above.
    letters = [chr(ord("A") + i) for i in range(len(labels))]
    for ax, name in zip(axes, params, strict=True):
        ax.boxplot([table.loc[table["data"] == lab, name] for lab in labels], widths=0.6)
        ax.set_xticks(range(1, len(labels) + 1), letters)
        ax.set_title(with_unit(name))
        ax.set_xlabel("data set")
    key = ", ".join(f"{letter}: {lab}" for letter, lab in zip(letters, labels, strict=True))
    fig.suptitle(f"posterior mean per vehicle (smc), by data set ({key})", fontsize=10)
    return _save(fig, path)


def turing_section(turing: Section, turing_results: dict[str, Any]) -> None:
    """The Turing test's texts and its classifiers' tables."""
    turing.text(
        "Two classifiers try to tell real held-out vehicle segments from simulated ones; 50% "
        "accuracy means indistinguishable. p-values by label permutation with the same folds. "
        "The first, a logistic regression, reads six summaries of a segment: speed mean and sd, "
        "gap mean and minimum (the levels), acceleration sd and jerk sd. Its second accuracy uses "
        "the levels only: where it is much lower, the classifier tells real from simulated by "
        "smoothness, i.e. by the execution noise, which the model draws independently at every "
        "step while the processed data are smooth (compare the criticism section's verdicts). "
        "The second, gradient-boosted trees, reads the within-segment quantiles of speed, gap, "
        "acceleration, jerk, relative speed and time headway and the acceleration's "
        "autocorrelation, sign changes and correlation with the closing speed; its folds are "
        "grouped by vehicle (no vehicle is tested by a classifier trained on it) and its interval "
        "counts a vehicle's segments, which are not independent, as fewer trials. A linear "
        "boundary on six summaries can call a model indistinguishable that the trees still tell "
        "apart. A fold that trains on fewer than "
        f"{2 * BOOSTING['min_samples_leaf']} segments (a quick run) cannot split a tree: there "
        "the boosted accuracy is chance by construction and says nothing."
    )
    # The folder's name, not its absolute path: the clips travel with the report.
    turing.text(
        f"For human judges: {turing_results['pairs']} pairs of clips (real and idm-smc, order "
        f"drawn from a seeded generator) in the folder {Path(turing_results['clips']).name}/ "
        "beside this report. Which clip of each pair is real is kept outside that folder, in "
        f"{Path(turing_results.get('answer_sheet', 'turing_answer_sheet.json')).name} beside "
        "this report, so the folder can be handed to judges as it is."
    )
    for label, rows in turing_results["classifier"].items():
        turing.table(turing_table(rows), caption=label)


def build_report(results: dict[str, Any], out: Path, command: list[str]) -> Path:
    """Write ``out/report.html`` from the results of :func:`experiments.run_all`."""
    figures = out / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    settings = results["settings"]
    left_out = results.get("steps_left_out", {})
    scope = (
        f" Left out of this run: {'; '.join(left_out.values())}. "
        "`bayesdrive reproduce --full` runs them (over this folder, only them)."
        if left_out
        else ""
    )
    report = Report(
        "bayesdrive: the paper's experiments on real data",
        intro=(
            f"Run '{settings['name']}': {settings['smc_particles']} smc particles, "
            f"{settings['rollouts']} rollouts per scenario, seeds {results['seeds']}.{scope}"
        ),
    )

    data = report.section("Data")
    rows = [
        {
            "data set": name,
            "format": info["format"],
            "scenes": info["scenes"],
            "vehicles": info["vehicles"],
            "recorded (s)": round(info["duration_s"], 1),
            "leader-follower pairs": info["leader_follower_pairs"],
            "median speed (m/s)": round(info["speed_mps"]["median"], 2),
            "flagged samples": sum(info["flags"].values()),
        }
        for name, info in results["data"].items()
    ]
    data.table(pd.DataFrame(rows), caption="Data sets (bayesdrive data info)")

    highway = report.section("Highway experiment (the paper's table of RMSE and collisions)")
    highway.note(PAPER_NOTE)
    highway.note(PLATOON_NOTE)
    for label, experiment in results["highway"].items():
        scenes = experiment["scenario_set"]
        highway.text(
            f"{label}: {scenes.get('scenarios', len(experiment['models']))} scenarios of "
            f"{scenes.get('vehicles_per_scenario')} simulated vehicles over 5 s, "
            f"{experiment['rollouts']} rollouts each, seed {experiment['seed']}; "
            f"{experiment['scenarios_dropped_without_posterior']} scenario(s) dropped because a "
            "vehicle had no usable fitting window. Selection: "
            f"{scenes.get('selection_rule', '')}"
        )
        highway.table(highway_table(experiment["models"]), caption=label)
        path = figures / f"rmse_{label.replace(':', '_')}.png"
        plot_rmse_curves(experiment["models"], path, f"RMSE over the horizon: {label}", 0.1)
        highway.figure(
            path, f"RMSE and undesirable events over the horizon, mean across scenarios: {label}"
        )
        if "acc-contrast" in label:
            highway.note(
                "Contrast: these followers drive on adaptive cruise control, not human drivers."
            )

    merge = report.section("Merging experiment")
    experiment = results["merge"]
    merge.note(
        "The slot layout of the merge episodes is inferred, not documented: the main-lane car "
        "just behind the merging car (V2) is taken as the driver who cooperates or not, its "
        "leader is V3, the merge point is the end of the acceleration lane, and episodes are cut "
        "at slot re-assignment jumps. The episodes carry no vehicle ids, so held-out cooperating "
        "drivers have no fitting window of their own, and one stay behind a merging car lasts "
        "about 3 s (median), too short to identify a driver. The learned models (C-IDM by smc, "
        "c included; IDM by Levenberg-Marquardt) therefore share one parameter set over all "
        f"{experiment['fitting_stays']} V2 stays of the fitting episodes "
        f"({experiment['fitting_steps']} steps, complete pooling), fitted with seed "
        f"{experiment['fit_seed']}, and are scored on the held-out episodes (split by episode)."
    )
    merge.table(highway_table(experiment["models"]), caption="Held-out merge episodes")
    path = plot_rmse_curves(
        experiment["models"], figures / "rmse_merge.png", "Merging: over the horizon", 0.1
    )
    merge.figure(path, "RMSE and undesirable events over the horizon, held-out merge episodes")
    merge.figure(
        plot_speed_densities(
            experiment["models"], figures / "merge_speeds.png", "Merging: speed distribution"
        ),
        "Speeds of the cooperating car in rollouts against the data, held-out merge episodes",
    )
    posterior = pd.DataFrame(experiment["cidm_posterior"]).T.round(3)
    posterior.index = [with_unit(name) for name in posterior.index]
    posterior = posterior.rename(columns={"q05": "5% quantile", "q95": "95% quantile"})
    merge.table(
        posterior.reset_index(names="parameter"),
        caption="C-IDM posterior (smc), pooled over the fitting episodes' V2 stays",
    )
    merge.figure(
        plot_cooperation(experiment["cooperation_draws"], figures / "cooperation.png"),
        "The learned cooperation c against its prior",
    )
    merge.note(
        "The C-IDM's likelihood is piecewise constant in c (the yield decision is a threshold), "
        "so the data can only rule ranges of c in or out: a posterior flat up to a cut-off says "
        "that yielding more often than that cut-off allows would have explained the fitting "
        "episodes worse, and nothing distinguishes the values below it."
    )

    params = report.section("Per-vehicle parameters and filter convergence")
    table = pd.DataFrame(results["parameters"])
    summary = table.drop(columns="vehicle").groupby("data").agg(["mean", "std"]).round(2)
    summary.columns = [
        f"{with_unit(a)}: {'mean' if b == 'mean' else 'sd'}" for a, b in summary.columns
    ]
    params.table(
        summary.reset_index(names="data set"),
        caption="Mean and sd across vehicles of the posterior means",
    )
    params.figure(plot_parameters(table, figures / "parameters.png"), "Posterior means per vehicle")
    for label, tree in results["trees"]["pf"].items():
        path = figures / f"convergence_{label.replace(':', '_')}.png"
        params.figure(plot_convergence(tree, path), f"The paper's filter: convergence, {label}")

    departure = report.section("The paper's filter against the exact posterior")
    for label in results["trees"]["smc"]:
        trees = {"smc": results["trees"]["smc"][label], "pf": results["trees"]["pf"][label]}
        agreement = agreement_table(trees)
        departure.table(
            agreement_summary(agreement).rename(columns=AGREEMENT_HEADERS),
            caption=f"{label}: pf against smc, per parameter",
        )

    turing = report.section("Turing test (automated: classifier two-sample test)")
    if "turing" in results:
        turing_section(turing, results["turing"])
    else:
        turing.note(LEFT_OUT_NOTE)

    scenes = report.section("Scene generation")
    scenes.note(
        "The paper's tables are reproduced as printed; a b_pref of 9 m/s^2 and a free-flow tau of "
        "5 s are odd for an IDM. Our own presets pool the exact posteriors."
    )
    presets = pd.DataFrame(results["scenes"]["presets"])
    scenes.table(
        presets.rename(columns={c: with_unit(c) for c in presets.columns}),
        caption="The paper's parameter tables (mean ± sd, independent normals), as printed",
    )
    scenes.table(
        pd.DataFrame(results["scenes"]["table"]).rename(
            columns={
                "speed_mean_mps": "mean speed (m/s)",
                "gap_median_m": "median bumper gap (m)",
                "collisions": "colliding vehicles",
                "hard_braking_steps": "hard-braking steps",
            }
        ),
        caption="Generated scenes",
    )
    recorded = results["scenes"]["figures"] + results["scenes"]["sweeps"]
    for path in figure_paths(recorded, out / "scenes"):
        scenes.figure(path, path.stem.replace("_", " "))

    generalisation = report.section("Generalisation to held-out data sets")
    if "holdout" in results:
        holdout_section(generalisation, results["holdout"])
    else:
        generalisation.note(LEFT_OUT_NOTE)
    if "holdout_calibration" in results:
        calibration_section(
            report.section("Calibration on held-out windows"),
            results["holdout_calibration"],
            figures,
        )

    prior = report.section("Prior sensitivity")
    frame = pd.DataFrame(results["prior_sensitivity"]["rows"])
    by_param = frame.groupby("param")[["shift_in_sd", "sd_ratio"]].agg(["median", "max"]).round(2)
    readable = {
        "shift_in_sd": "shift of the posterior mean (posterior sds)",
        "sd_ratio": "sd ratio (wide prior / box prior)",
    }
    by_param.columns = [f"{readable[a]}, {b} over vehicles" for a, b in by_param.columns]
    by_param.index = [with_unit(name) for name in by_param.index]
    prior.table(
        by_param.reset_index(names="parameter"),
        caption="Posterior shift under a prior twice as wide",
    )

    criticism = report.section("Model criticism: what the stochastic IDM gets wrong on real data")
    criticism.text(
        "bayesdrive criticize fits the base IDM, checks its held-out residuals and predictions, "
        "fits the extensions the checks point to, and names the cause whose extension gains most "
        "held-out log predictive density (leave-future-out), when significant after Holm's "
        "correction over every cause considered; standard errors are across vehicles. A misfit "
        "the checks find that no cause explains is named as such ('unexplained: <check>'). A "
        "cause extends the model only if it simulates better: its held-out forecast (the "
        "energy score of the 5 s gap and speed path from the filtered state) is better by a "
        "paired test across vehicles, its predictive mean is not worse and it adds no "
        "collisions. The named cause is judged first; where it fails, the other causes of "
        "significant gain in the order of their gain. Then it asks again, round after round, "
        "until a round adopts nothing. "
        "The final model joins the highway "
        "tables, the Turing test and models/ beside the IDM, fitted by smc on the fitting windows "
        "and scored on the held-out windows. It was chosen on the held-out windows of the "
        "criticised vehicles (scenes of the same data set, named below), so its held-out scores "
        "here are not wholly independent of the choice; the held-out data sets are. The merge "
        "episodes are not criticised: the criticism reads car-following series, and the "
        "Cooperative IDM's merge scene is not among them."
    )
    if results.get("criticism_left_out_by_settings"):
        criticism.note(
            "Not criticised in this run, whose settings criticise only "
            f"{', '.join(results['criticism'])}: "
            f"{', '.join(results['criticism_left_out_by_settings'])}."
        )
    first_scenes = dict(map(tuple, results["settings"].get("criticism_first_scene", ())))
    for label, found in results.get("criticism", {}).items():
        artefact = found.get("verdict_is_possible_processing_artefact")
        sampler = found["settings"]
        moves = (
            f"moves until a particle stays put with probability at most "
            f"{sampler['unmoved_tolerance']:g}"
            if sampler.get("unmoved_tolerance")
            else f"{sampler['num_moves']} moves"
        )
        criticism.text(
            f"{label} ({found['data']['vehicles']} vehicles of {found['scenes']} scenes from its "
            f"scene {first_scenes.get(label, 0) + 1}, the first {found['seconds_per_scene']:.0f} s "
            f"of each; {sampler['num_particles']} "
            f"particles per vehicle and model, {moves} per tempering stage): verdict "
            f"'{found['verdict']}', final model '{found.get('model', 'idm')}'."
        )
        if artefact:
            criticism.note(f"The verdict may be a processing artefact: {artefact}")
        # Results written before the loop have one round, under "causes".
        rounds = found.get("rounds") or [{"round": 1, "model": "idm", "causes": found["causes"]}]
        for found_round in rounds:
            criticism.table(
                causes_table(found_round["causes"]),
                caption=f"{label}, round {found_round['round']}: what extends "
                f"{found_round['model']}, causes by gain",
            )
            if "adoption" in found_round:
                misfit = ", ".join(m["check"] for m in found_round["misfit"]) or "none found"
                criticism.text(
                    f"{label}, round {found_round['round']}: misfit {misfit}; verdict "
                    f"'{found_round['verdict']}'; {found_round['adoption']}; "
                    f"{found_round['outcome']}."
                )
        criticism.table(
            pd.DataFrame(
                [
                    {
                        "check": c["title"],
                        "p-value": c["p_value"],
                        "points to": ", ".join(c["points_to"]),
                    }
                    for c in found["checks"]
                ]
            ),
            caption=f"{label}: checks on the held-out windows",
        )
        for path in figure_paths(found.get("figures", []), criticism_folder(out, label)):
            criticism.figure(path, f"{label}: {path.stem.replace('_', ' ')}")

    if "step_times" in results:
        report.section("Steps and their times").table(
            pd.DataFrame(results["step_times"]),
            caption="Wall seconds of each step in the invocation that finished this folder (a step "
            "reused from an earlier invocation shows about 0 s); the last row is the total",
        )
    return report.write(out / "report.html", command=command)


def causes_table(causes: list[dict[str, Any]]) -> pd.DataFrame:
    rows = []
    for cause in causes:
        gain = cause.get("gain") or {}
        scored = cause.get("forecast") or {}
        rows.append(
            {
                "cause": cause["name"],
                "fitted": "yes" if gain else "no (screened out)",
                "held-out elpd gain (nats)": gain.get("elpd"),
                "se of the gain (nats)": gain.get("se"),
                "p (one-sided)": gain.get("p_value"),
                "significant (Holm)": gain.get("significant"),
                "RMSE position change (m)": gain.get("rmse_position_change"),
                "energy score gain": scored.get("energy_score_gain"),
                "its se": scored.get("energy_score_gain_se"),
                "p (paired)": scored.get("p_value"),
                "forecasts better (Holm)": scored.get("significant"),
                "predictive-mean RMSE change (m)": scored.get("rmse_mean_position_change_m"),
                "collisions (rollouts)": scored.get("collisions"),
                "possible artefact": "yes" if cause.get("possible_processing_artefact") else "",
            }
        )
    return pd.DataFrame(rows)
