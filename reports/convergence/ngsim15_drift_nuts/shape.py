# Per vehicle: nuts' extension factor, each chain's adapted step size and median tree depth, and
# the mean number of leapfrog steps per draw (what a draw costs).
import sys

import numpy as np

from bayesdrive.inference.core.output import load_result

for vid in sys.argv[1:]:
    stats = load_result(f"/work/runs/nutsdrift/nuts_{vid}.nc")["sample_stats"]
    step = np.asarray(stats["step_size"].values, dtype=np.float64).ravel()
    depth = np.asarray(stats["tree_depth"].values)
    depth = depth.reshape(depth.shape[0], -1)
    print(
        vid,
        "extension",
        np.asarray(stats["extension"].values).ravel().tolist(),
        "step sizes",
        np.round(step, 4).tolist(),
        "median depth per chain",
        np.median(depth, axis=1).tolist(),
        "mean leapfrogs per draw",
        round(float(np.asarray(stats["n_steps"].values).mean())),
        "divergences",
        int(np.asarray(stats["diverging"].values).sum()),
    )
