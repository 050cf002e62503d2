"""The paper's experiments as one pipeline (``bayesdrive reproduce``): fit, simulate, criticise and
score on the real data, then hand the results to :mod:`bayesdrive.reports` to draw. It sits between
the criticism and the CLI: it uses every library layer and the report's drawing functions, and
nothing but the CLI uses it."""
