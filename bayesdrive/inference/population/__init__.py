"""Population estimators: the hierarchical model, the two-stage estimator and their summaries."""
