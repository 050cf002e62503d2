"""Model criticism: what the simulation gets wrong, the cause, the extension that fixes it.

``criticize`` (:mod:`.criticize`) fits the base model, runs the checks (:mod:`.checks`), fits the
extensions the checks point to (:mod:`bayesdrive.drivers.extensions`) with the tempering sampler
(:mod:`bayesdrive.inference.engines.heldout_evidence`), and names the cause whose held-out gain (:mod:`.gain`)
is largest and significant; :mod:`bayesdrive.simulation.follower_rollout` simulates followers
closed loop on held-out windows. The data with known hidden effects that test it come from
``trafficgen`` at the repository root, a generator that shares no code with bayesdrive.
"""

__all__: list[str] = []
