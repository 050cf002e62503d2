import sys

import jax

from bayesdrive.data import registry
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.output import load_result
from bayesdrive.inference.diagnostics.agreement import agreement_table
from bayesdrive.inference.fit import fit

for vid in sys.argv[1:]:
    smc = fit(
        jax.random.key(20261219),
        registry.load("ngsim_i80_chains"),
        model=get_model("idm+drifting_parameters"),
        engine="smc",
        seed=20261219,
        vehicle_ids=[vid],
    )
    table = agreement_table(
        {"smc": smc, "nuts": load_result(f"/work/runs/nutsdrift/nuts_{vid}.nc")}
    )
    cols = [
        c
        for c in table.columns
        if c in ("param", "agree", "mean_a", "mean_b", "sd_a", "sd_b", "abs_mean_diff_sd")
    ]
    print("vehicle", vid, "agree", int(table["agree"].sum()), "of", len(table), flush=True)
    print(table[cols].round(4).to_string())
