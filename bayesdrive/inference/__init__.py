"""Inference engines over driver-model parameters and their shared result layout.

Engines by name: :data:`bayesdrive.inference.fit.ENGINES`; the result layout:
:mod:`bayesdrive.inference.core.output`. Submodules are imported where used (nothing re-exported), so
importing one engine does not load the others.
"""

__all__: list[str] = []
