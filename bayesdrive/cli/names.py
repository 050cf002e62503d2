"""Names and defaults the commands' options show in their help, without the libraries behind them.

The registries that define these import JAX, which takes seconds; ``--help`` must not. Each value
here is checked against its source by ``tests/cli/test_cli_startup.py``, so a new model, extension,
engine or baseline that is not added here fails a test rather than going missing from the help.
"""

__all__ = [
    "BASELINES",
    "CAUSES",
    "ENGINES",
    "FIT_CHUNK_SIZE",
    "IDM_PARAMS",
    "MODELS",
    "SCENARIO_CHUNK_SIZE",
]

# bayesdrive.drivers.registry.MODELS
MODELS = ("idm", "cidm", "gipps", "ovm")
# bayesdrive.drivers.extensions.CAUSES
CAUSES = (
    "reaction_delay",
    "autocorrelated_noise",
    "speed_dependent_noise",
    "second_leader_anticipation",
    "cut_in_overreaction",
    "leader_acceleration_anticipation",
    "state_correction",
    "drifting_parameters",
    "measurement_noise",
)
# bayesdrive.inference.fit.ENGINES
ENGINES = ("smc", "pf", "nuts", "emcee", "lm", "hierarchical", "pmmh")
# bayesdrive.simulation.baselines.BASELINES
BASELINES = ("idm-default", "idm-nls", "idm-lm", "cv", "ca", "blackbox", "cidm-c1", "idm-nomerge")
# bayesdrive.drivers.idm.IDM.param_names
IDM_PARAMS = ("v_des", "d_min", "tau", "a_max", "b_pref", "sigma")
# bayesdrive.inference.distributed.DEFAULT_CHUNK_SIZE
FIT_CHUNK_SIZE = 16
# bayesdrive.simulation.evaluation.DEFAULT_SCENARIO_CHUNK
SCENARIO_CHUNK_SIZE = 8
