"""How the package asks XLA to compile its programs: :func:`jit` is ``jax.jit`` with
:func:`compiler_options`, and importing the package asks XLA:CPU to compile small loops
whole (:func:`request_loop_kernels`).

**Loops compiled whole.** XLA:CPU normally runs a loop body as a sequence of separately
compiled kernels, one launch each: some 430 per closed-loop step, whose launching cost
more than their arithmetic. A while loop whose body touches fewer bytes per iteration than
``xla_cpu_small_while_loop_byte_threshold`` and calls no library (no LAPACK, no custom
fusion) is instead compiled into one function, loop included ("small while loop
hoisting"). The threshold is a backend option that only ``XLA_FLAGS`` sets, read when XLA
first compiles, so importing ``spacegrasp_jax`` adds it to ``XLA_FLAGS`` (unless the user
already passes ``--xla_backend_extra_options``). It applies to every program of the process
on a CPU, other backends ignore it. Hence the package's loops call no library: the small
solves are unrolled (``spacegrasp_jax.linalg``), the 3x3 products are products and sums
(``spacegrasp_jax.spatial``), and :data:`CPU_OPTIONS` turns off XLA's YNNPACK fusions of
batched reductions (custom fusions). A 17 s rollout runs 2.4x faster, a gradient 3x; the
programs take 2-3x longer to compile (README, Performance).

**Compile options.** :data:`CPU_OPTIONS` also keeps the loop-fusion emitters that predate
XLA's MLIR-based "fusion emitters": half the compiler's peak memory on the closed loop's
many small kernels. They are read only by the CPU compiler. An XLA that no longer knows
them rejects them, so they are used only if a one-off probe compile accepts them.
"""

from __future__ import annotations

import functools
import os
import warnings
from typing import Any, Callable

import jax
import jax.numpy as jnp

#: Compile options for the closed-loop programs on a CPU (see the module docstring).
CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": ""}

#: Largest bytes a loop body may touch per iteration and still be compiled whole: far above
#: the closed loop's (a vmapped step of 128 samples touches a few MB), far below what would
#: make a loop over large arrays one kernel.
LOOP_KERNEL_BYTES = 100_000_000

_LOOP_FLAG = f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold={LOOP_KERNEL_BYTES}"


def request_loop_kernels() -> bool:
    """Add the loop-kernel threshold (:data:`LOOP_KERNEL_BYTES`) to ``XLA_FLAGS``, unless
    ``XLA_FLAGS`` already sets backend options (then the user's choice stands: set
    ``xla_cpu_small_while_loop_byte_threshold=0`` there to compile loops kernel by kernel).
    Takes effect if called before XLA first compiles; ``import spacegrasp_jax`` calls it.
    Returns whether it changed ``XLA_FLAGS``."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_extra_options" in flags:
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {_LOOP_FLAG}".strip()
    return True


@functools.cache
def loops_compile_whole() -> bool:
    """Whether XLA compiles a small loop into one kernel in this process (probed once, by
    compiling one; ``False`` on other backends than the CPU)."""
    if jax.default_backend() != "cpu":
        return False
    loop = jax.jit(lambda x: jax.lax.fori_loop(0, 3, lambda i, y: 2.0 * y + 1.0, x))
    return "xla_cpu_small_call" in loop.lower(jnp.zeros(3)).compile().as_text()


@functools.cache
def compiler_options() -> dict[str, Any]:
    """:data:`CPU_OPTIONS` if this XLA accepts them, else ``{}``. Probed on first use (the
    probe compiles a scalar program, so it initialises the JAX backend), together with
    :func:`loops_compile_whole`, which warns if loops run kernel by kernel on a CPU."""
    if jax.default_backend() == "cpu" and not loops_compile_whole():
        warnings.warn(
            "XLA compiles loops kernel by kernel in this process, so the closed loop runs about "
            "2.4x slower on a CPU: import spacegrasp_jax before JAX compiles anything, or pass "
            f"XLA_FLAGS={_LOOP_FLAG} (spacegrasp_jax.compilation)",
            RuntimeWarning,
            stacklevel=3,
        )
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
