"""Batches on the host, written once for Monte-Carlo campaigns, gain sweeps and tuning's
evaluations: chunk, pad, shard over the devices' mesh, compile once, gather, report progress.

A batched job is a pure function ``function(*replicated, block)`` whose last argument is a
pytree with a leading batch axis (sample indices, gain sets, scenarios) and whose outputs
all carry that axis. [`compile_chunk()`][spacegrasp_jax.jobs.batching.compile_chunk] compiles it for one chunk of ``chunk`` items, the
chunk's batch axis sharded over a 1-D mesh of ALL devices of ALL processes
([`batch_mesh()`][spacegrasp_jax.jobs.batching.batch_mesh]): one device on a plain CPU, every core with
[`use_all_cpu_cores()`][spacegrasp_jax.jobs.batching.use_all_cpu_cores], every GPU or host of a cluster with ``jax.distributed``; the code
path is the same. [`run_chunk()`][spacegrasp_jax.jobs.batching.run_chunk] runs a chunk and brings its outputs back to every host
as NumPy arrays; [`map_in_chunks()`][spacegrasp_jax.jobs.batching.map_in_chunks] runs a whole batch chunk by chunk, the last chunk
padded with copies of the last item (computed, then dropped).
"""

from __future__ import annotations

import functools
import math
import os
import sys
import time
from collections.abc import Callable, Hashable

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from spacegrasp_jax.jobs import compilation
from spacegrasp_jax.jobs.runfiles import end_progress, progress_bar, show_progress


class BatchingError(ValueError):
    """A chunk or batch that does not fit the devices; names the setting."""


def use_all_cpu_cores() -> int | None:
    """Expose one XLA CPU device per core (``jax_num_cpu_devices``), so that the batch axis
    shards across the cores: one CPU device runs a batch on about one core. It takes effect
    only if called before JAX initialises its backends (before the first array or device
    query). Returns the device count requested, or ``None`` if the user already chose one
    (``XLA_FLAGS`` with ``--xla_force_host_platform_device_count``, or
    ``JAX_NUM_CPU_DEVICES``). Harmless on GPU hosts, whose default devices are the GPUs."""
    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", "") or "JAX_NUM_CPU_DEVICES" in os.environ:
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        jax.config.update("jax_num_cpu_devices", cores)
    except (AttributeError, RuntimeError):  # an older jax, or backends already initialised
        return None
    return cores


def batch_mesh() -> Mesh:
    """A 1-D mesh (axis ``"batch"``) over every device of every process."""
    return Mesh(np.asarray(jax.devices()), ("batch",))


def chunk_size(requested: int, n: int) -> int:
    """``requested`` rounded up to a multiple of the device count, and no larger than ``n``
    items need."""
    devices = jax.device_count()
    return devices * math.ceil(min(requested, n) / devices)


def batch_size(batched) -> int:
    """The leading axis shared by every leaf of ``batched``."""
    sizes = {np.shape(leaf)[0] if np.ndim(leaf) else None for leaf in jax.tree.leaves(batched)}
    if len(sizes) != 1 or None in sizes:
        raise BatchingError(f"every leaf of a batch needs the same leading axis, got sizes {sorted(map(str, sizes))}")
    return sizes.pop()


def take(batched, rows):
    """Items ``rows`` (NumPy indices) of a batch, as NumPy arrays."""
    return jax.tree.map(lambda leaf: np.asarray(leaf)[rows], batched)


def program_settings(function: Callable) -> Hashable:
    """What, besides its arguments' shapes, identifies the program ``function`` makes: for a
    ``functools.partial``, the function and every argument it fixes (the static settings, such
    as the law object, the measure or the criteria: a setting added to the partial is in the
    key with nothing else to change); for any other function, the function object itself (a
    fresh closure is a new program).

    Raises:
        BatchingError: a fixed argument is not hashable (it could not tell programs apart).
    """
    if not isinstance(function, functools.partial):
        return function
    settings = (program_settings(function.func), function.args, tuple(sorted(function.keywords.items())))
    try:
        hash(settings)
    except TypeError as error:
        raise BatchingError(
            f"{function}: a fixed argument is not hashable ({error}); pass arrays as arguments"
        ) from None
    return settings


def compile_chunk(
    name: str,
    function: Callable,
    replicated: tuple,
    chunk_example,
    *,
    device_batch: int | None = None,
) -> tuple[Callable, float]:
    """Compile ``function(*replicated, block)`` for chunks shaped like ``chunk_example``,
    once per process ([`compile_once()`][spacegrasp_jax.jobs.compilation.compile_once]).

    Args:
        name: the job's name (the compile line's).
        function: pure, batch in and batch out (e.g. a ``vmap``); with the arguments'
            shapes, [`program_settings()`][spacegrasp_jax.jobs.batching.program_settings] of it
            identifies the program, so a fresh ``functools.partial`` with the same settings
            reuses it.
        replicated: arguments every device receives whole.
        chunk_example: a chunk (pytree, leading axis ``chunk``, a multiple of the device
            count); only its shapes matter.
        device_batch: items each device computes at once (``None``: its whole share). A
            share larger than this is run in sub-batches of it, one after another
            (``compilation.map_one_at_a_time``), if it divides the share; on a CPU, 128 keeps
            a sub-batch's states in cache.

    Returns:
        ``(executable, compile_s)``.
    """
    chunk = batch_size(chunk_example)
    devices = jax.device_count()
    if chunk % devices:
        raise BatchingError(
            f"chunk: {chunk} is not a multiple of the {devices} devices; use a multiple such as {devices * max(1, round(chunk / devices))}"
        )
    share = chunk // devices
    sub_batch = device_batch if device_batch and share > device_batch and share % device_batch == 0 else None
    mesh = batch_mesh()
    batched_sharding = NamedSharding(mesh, PartitionSpec("batch"))

    def on_one_device(*arguments):
        *fixed, block = arguments
        if sub_batch is None:
            return function(*fixed, block)
        blocks = jax.tree.map(lambda x: x.reshape((-1, sub_batch, *x.shape[1:])), block)
        outputs = compilation.map_one_at_a_time(lambda b: function(*fixed, b), blocks)
        return jax.tree.map(lambda x: x.reshape((-1, *x.shape[2:])), outputs)

    def lower():
        specs = (PartitionSpec(),) * len(replicated) + (PartitionSpec("batch"),)
        sharded = jax.shard_map(
            on_one_device, mesh=mesh, in_specs=specs, out_specs=PartitionSpec("batch"), check_vma=False
        )
        placeholder = jax.tree.map(
            lambda x: jax.ShapeDtypeStruct(np.shape(x), np.asarray(x).dtype, sharding=batched_sharding), chunk_example
        )
        return compilation.jit(sharded).lower(*replicated, placeholder)

    signature = compilation.argument_signature((replicated, take(chunk_example, slice(0, 0))))
    return compilation.compile_once(
        ("batch", name, program_settings(function), chunk, sub_batch, tuple(jax.devices()), signature),
        lower,
        label=f"{name} ({chunk} items a call)",
    )


def run_chunk(executable: Callable, replicated: tuple, block) -> object:
    """Run one compiled chunk on ``block`` (NumPy, leading axis the chunk) and return its
    outputs on every host as NumPy arrays (gathered across processes)."""
    batched_sharding = NamedSharding(batch_mesh(), PartitionSpec("batch"))
    sharded = jax.tree.map(
        lambda x: jax.make_array_from_callback(np.shape(x), batched_sharding, lambda where, x=x: np.asarray(x)[where]),
        block,
    )
    outputs = executable(*replicated, sharded)
    return jax.tree.map(np.asarray, multihost_utils.process_allgather(outputs, tiled=True))


def map_in_chunks(
    name: str,
    function: Callable,
    replicated: tuple,
    batched,
    *,
    chunk: int = 64,
    device_batch: int | None = None,
    progress=sys.stderr,
    label: str = "items",
):
    """``function(*replicated, batched)`` over a whole batch of N items, ``chunk`` items per
    call of one compiled program ([`compile_chunk()`][spacegrasp_jax.jobs.batching.compile_chunk]; ``chunk`` rounded by
    [`chunk_size()`][spacegrasp_jax.jobs.batching.chunk_size]). ``progress``: stream for one progress line per chunk (``None``:
    silent). Returns the outputs as NumPy arrays with leading axis N."""
    if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
        raise BatchingError(f"chunk: expected a positive integer, got {chunk!r}")
    n = batch_size(batched)
    chunk = chunk_size(chunk, n)
    executable, _ = compile_chunk(
        name,
        function,
        replicated,
        take(batched, np.minimum(np.arange(chunk), n - 1)),
        device_batch=device_batch,
    )
    pieces = []
    for first in range(0, n, chunk):
        start = time.perf_counter()
        outputs = run_chunk(executable, replicated, take(batched, np.minimum(np.arange(first, first + chunk), n - 1)))
        pieces.append(jax.tree.map(lambda x: x[: min(chunk, n - first)], outputs))
        if progress is not None:
            done = min(first + chunk, n)
            show_progress(
                progress,
                progress_bar(done, n, f"{label} {done}/{n} ({time.perf_counter() - start:.1f} s for the last chunk)"),
            )
            if done == n:
                end_progress(progress)
    return jax.tree.map(lambda *parts: np.concatenate(parts), *pieces)


__all__ = [
    "BatchingError",
    "batch_mesh",
    "batch_size",
    "chunk_size",
    "compile_chunk",
    "program_settings",
    "map_in_chunks",
    "run_chunk",
    "take",
    "use_all_cpu_cores",
]
