"""Model criticism: what the simulation gets wrong, the cause, the extension that fixes it.

``criticize`` (:mod:`.criticize`) fits the base model, runs the checks (:mod:`.checks`), fits the
extensions the checks point to (:mod:`bayesdrive.drivers.extensions`) with the tempering sampler
(:mod:`bayesdrive.inference.tempering`), and names the cause whose held-out gain (:mod:`.gain`) is largest and
significant. :mod:`.generator` hides known effects in simulated NGSIM files for the tests and
the detection study; :mod:`bayesdrive.simulation.follower_rollout` simulates followers closed loop on held-out
windows.
"""

__all__: list[str] = []
