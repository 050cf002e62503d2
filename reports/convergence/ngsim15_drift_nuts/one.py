import sys
import time

import jax

from bayesdrive.data import registry
from bayesdrive.drivers.registry import get_model
from bayesdrive.inference.core.output import metadata, save_result
from bayesdrive.inference.fit import fit

vid, seed = sys.argv[1], int(sys.argv[2])
t = time.perf_counter()
tree = fit(
    jax.random.key(seed),
    registry.load("ngsim_i80_chains"),
    model=get_model("idm+drifting_parameters"),
    engine="nuts",
    seed=seed,
    vehicle_ids=[vid],
)
wall = time.perf_counter() - t
ss = tree["sample_stats"]
problems = metadata(tree)["convergence"]["problems"]
print(
    "vehicle",
    vid,
    "wall_s",
    round(wall),
    "problems",
    len(problems),
    "extension",
    ss["extension"].values.tolist() if "extension" in ss else None,
    "divergences",
    int(ss["diverging"].values.sum()),
    flush=True,
)
for p in problems[:10]:
    print("  ", p)
post = tree["posterior"]
print("means", {n: round(float(post[n].mean()), 4) for n in post.data_vars})
print("sds", {n: round(float(post[n].std()), 4) for n in post.data_vars})
save_result(tree, f"/work/runs/nutsdrift/nuts_{vid}.nc")
