"""The package computes in float64: the switch, and the check every constructor of a robot, a
scenario, a realism or a gain set makes before anything compiles."""

from __future__ import annotations

import jax


class Float64Required(RuntimeError):
    """JAX is in float32 (its default) where the package needs float64."""


def enable_float64() -> None:
    """Make JAX compute in float64 (``jax_enable_x64``), process-wide."""
    jax.config.update("jax_enable_x64", True)


def require_float64(what: str) -> None:
    """Raise [`Float64Required`][spacegrasp_jax.core.precision.Float64Required], naming ``what`` was being built, unless JAX is in
    float64 ([`enable_float64()`][spacegrasp_jax.core.precision.enable_float64], ``JAX_ENABLE_X64=1`` or ``jax_enable_x64``)."""
    if not jax.config.jax_enable_x64:
        raise Float64Required(
            f"{what}: spacegrasp_jax computes in float64, but JAX is in float32 (its default). "
            "Call spacegrasp_jax.configure() (or jax.config.update('jax_enable_x64', True)) first."
        )


__all__ = ["Float64Required", "enable_float64", "require_float64"]
