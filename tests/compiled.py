"""The per-step density compiled as one program per model and shape, for tests that call it
outside a compiled program: there each of its many small operations would compile on its own.
The engines call ``bayesdrive``'s own inside their programs, where it is inlined."""

from __future__ import annotations

import jax

from bayesdrive.inference.core import likelihood

step_logpdfs = jax.jit(likelihood.step_logpdfs, static_argnames=("model", "may_be_censored"))
