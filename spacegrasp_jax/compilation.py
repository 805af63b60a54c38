"""How the package asks XLA to compile its programs: :func:`jit` is ``jax.jit`` with
:func:`compiler_options`.

The closed loop compiles to a few hundred small kernels per step (none over 64 numbers).
On XLA's CPU backend, the loop-fusion emitters that predate XLA's MLIR-based "fusion
emitters" compile these kernels with half the peak memory, and run them as fast or faster
(a reverse-mode gradient 1.2x faster; README, Performance, has the same-run numbers).

The option is read only by the CPU compiler (other backends ignore it). An XLA that no
longer knows it rejects it, so it is used only if a one-off probe compile accepts it.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import jax

#: Compile options for the closed-loop programs on a CPU (see the module docstring).
CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False}


@functools.cache
def compiler_options() -> dict[str, Any]:
    """:data:`CPU_OPTIONS` if this XLA accepts them, else ``{}``. Probed on first use (the
    probe compiles a scalar program, so it initialises the JAX backend)."""
    try:
        jax.jit(lambda x: x + 1.0, compiler_options=CPU_OPTIONS).lower(0.0).compile()
    except (jax.errors.JaxRuntimeError, TypeError):  # unknown option; a jit without the argument
        return {}
    return dict(CPU_OPTIONS)


def jit(fun: Callable, **jit_kwargs) -> Callable:
    """``jax.jit(fun, **jit_kwargs)`` compiled with :func:`compiler_options`. Call it when
    the program is about to be compiled, not at import: the options' probe initialises the
    JAX backend (``campaign.use_all_cpu_cores`` must come before that)."""
    options = compiler_options()
    return jax.jit(fun, compiler_options=options, **jit_kwargs) if options else jax.jit(fun, **jit_kwargs)
