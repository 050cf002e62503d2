"""Model cards: the short Markdown file beside every fitted posterior that ``bayesdrive`` writes
(``models/``, ``reproduce``, ``criticize --out``), stating what was fitted to what, how, by which
code, and the posterior in brief."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import xarray as xr

from bayesdrive.data.provenance import describe_code
from bayesdrive.inference.core.output import metadata
from bayesdrive.inference.fit import summary as fit_summary

__all__ = ["model_card", "posterior_lines"]


def posterior_lines(units: Sequence[dict], params: Sequence[str]) -> list[str]:
    """A model card's parameter lines: the spread of the posterior means across fitted units, or
    for a single (pooled) unit its posterior mean and sd."""
    if len(units) == 1:
        only = units[0]
        return [
            "Posterior mean / sd:",
            "",
            *(f"- {n}: {only[n]['mean']:.2f} / {only[n]['sd']:.2f}" for n in params),
        ]
    return [
        "Posterior means (mean / sd across fitted units):",
        "",
        *(
            f"- {n}: {np.mean([u[n]['mean'] for u in units]):.2f}"
            f" / {np.std([u[n]['mean'] for u in units]):.2f}"
            for n in params
        ),
    ]


def model_card(
    tree: xr.DataTree, *, title: str, description: str, label: str, lines: Sequence[str] = ()
) -> str:
    """The card of the fitted result ``tree``: ``description`` says what the model is, ``label``
    names the data, ``lines`` add what only the caller knows (settings, how to regenerate)."""
    meta = metadata(tree)
    units = list(fit_summary(tree)["vehicles"].values())
    stats = tree["sample_stats"].to_dataset()
    evidence = stats["log_evidence"].values if "log_evidence" in stats else np.array([np.nan])
    size = meta.get("num_particles", meta.get("num_draws"))
    return "\n".join(
        [
            f"# {title}",
            "",
            f"- model: {meta['model']} ({description}; parameters {', '.join(meta['params'])})",
            f"- data: {meta['data_source']} ({label}), window '{meta['window']}' of the split: "
            f"{meta.get('split_rule', '')}",
            f"- fitted units: {len(units)}; engine: {meta['engine']}, {size} draws, "
            f"seed {meta['seed']}",
            "- prior: independent uniform on the documented bounds (bayesdrive.drivers)",
            f"- diagnostics: median log-evidence per unit {np.nanmedian(evidence):.1f} nats; "
            f"wall time {meta.get('wall_time_s', float('nan')):.0f} s",
            f"- fitted by: {describe_code(meta.get('code'))}",
            *(f"- {line}" for line in lines),
            "- open with: `xarray.open_datatree(path, engine='h5netcdf')` or arviz; draws "
            "are (chain, draw, vehicle) per parameter",
            "",
            *posterior_lines(units, meta["params"]),
            "",
        ]
    )
