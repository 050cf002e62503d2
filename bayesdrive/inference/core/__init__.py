"""The shared kernels every engine is built from: the SMC step and adaptive tempering, the MCMC
moves, resampling, weights, the per-vehicle likelihood, the vehicle mapping and the result layout."""
