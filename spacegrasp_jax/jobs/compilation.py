"""How the package's programs are compiled, and the process settings they want.

Importing ``spacegrasp_jax`` changes nothing in the process: no environment variable, no
XLA flag, no JAX option. Three settings are the caller's to choose, each by one explicit
call, or all three at once by [`configure()`][spacegrasp_jax.jobs.compilation.configure] (what the ``spacegrasp`` command does):

* **float64** ([`enable_float64()`][spacegrasp_jax.core.precision.enable_float64]). The dynamics need double precision; JAX computes in
  float32 unless told otherwise. The constructors of robots, scenarios and gains raise
  [`Float64Required`][spacegrasp_jax.core.precision.Float64Required] when it is off, before anything compiles.
* **Loops compiled whole** ([`compile_loops_whole()`][spacegrasp_jax.jobs.compilation.compile_loops_whole]). XLA:CPU normally runs a loop body
  as a sequence of separately compiled kernels, one launch each: some 430 per closed-loop
  step, whose launching costs more than their arithmetic. A while loop whose body touches
  fewer bytes per iteration than ``xla_cpu_small_while_loop_byte_threshold`` and calls no
  library (no LAPACK, no custom fusion) can instead be compiled into one function, loop
  included. The threshold is a backend option that only ``XLA_FLAGS`` sets, and it applies
  to every program of the process on a CPU (other backends ignore it), which is why it is
  an opt-in. The package's loops are written to qualify: the small solves are unrolled
  (``spacegrasp_jax.core.linalg``), the 3x3 products are products and sums
  (``spacegrasp_jax.core.spatial``), and ``CPU_OPTIONS`` turns off XLA's YNNPACK fusions of
  batched reductions (custom fusions). Results are the same either way, to rounding.
* **A persistent compilation cache** ([`use_compile_cache()`][spacegrasp_jax.jobs.compilation.use_compile_cache]): compiled programs are
  kept on disk and loaded by later processes instead of compiled again.

**Compile options.** ``CPU_OPTIONS`` also keeps the loop-fusion emitters that predate
XLA's MLIR-based "fusion emitters": half the compiler's peak memory on the closed loop's
many small kernels. They are read only by the CPU compiler. An XLA that no longer knows
them rejects them, so they are used only if a one-off probe compile accepts them.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import re
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core.precision import enable_float64
from spacegrasp_jax.jobs import executable_store

#: Compile options for the closed-loop programs on a CPU (see the module docstring).
CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": ""}

#: Largest bytes a loop body may touch per iteration and still be compiled whole: far above
#: the closed loop's (a vmapped step of 128 samples touches a few MB), far below what would
#: make a loop over large arrays one kernel.
LOOP_KERNEL_BYTES = 100_000_000

LOOP_FLAG = f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold={LOOP_KERNEL_BYTES}"


def _backends_initialised() -> bool:
    try:
        from jax._src import xla_bridge

        return xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError):  # a JAX without the query: assume the worst
        return True


def compile_loops_whole() -> None:
    """Ask XLA:CPU to compile small loops into one function (module docstring) by adding
    ``LOOP_FLAG`` to ``XLA_FLAGS``, process-wide.

    If ``XLA_FLAGS`` already sets backend options, the user's choice stands (with
    ``xla_cpu_small_while_loop_byte_threshold=0`` there, loops run kernel by kernel). Best
    called before JAX first runs anything; if JAX has already started, a probe checks that
    the option took effect and warns (``RuntimeWarning``) if it did not."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_extra_options" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {LOOP_FLAG}".strip()
    if _backends_initialised():
        loops_compile_whole.cache_clear()
        if jax.default_backend() == "cpu" and not loops_compile_whole():
            warnings.warn(
                "spacegrasp_jax.compile_loops_whole() came too late for this process: XLA compiles "
                "loops kernel by kernel, so the closed loop runs about 2.4x slower on a CPU. Call it "
                f"before JAX runs anything, or start Python with XLA_FLAGS={LOOP_FLAG}",
                RuntimeWarning,
                stacklevel=2,
            )


def default_compile_cache() -> Path:
    """``$XDG_CACHE_HOME/spacegrasp-jax/xla`` (``~/.cache/spacegrasp-jax/xla`` without it)."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "spacegrasp-jax" / "xla"


#: The shortest compile, s, whose program the persistent cache keeps: every program. JAX's
#: default, 1 s, leaves out the small ones a command compiles on its way (building the robot
#: and the scenario, a log's summary: about a hundred, 3 s of a warm ``spacegrasp simulate``
#: of 2 s), which a later process then compiles again; reading one back takes milliseconds.
CACHE_MIN_COMPILE_TIME_S = 0.0

#: JAX's own default of ``jax_persistent_cache_min_compile_time_secs``: a value other than
#: this one was the user's choice and stands.
_JAX_MIN_COMPILE_TIME_S = 1.0


class CacheFolderError(ValueError):
    """A compilation cache folder that other users can write: loading programs from it would
    run their code ([`unsafe_folder_reason()`][spacegrasp_jax.jobs.executable_store.unsafe_folder_reason])."""


def _make_private_folder(folder: Path) -> None:
    """``folder`` and the folders above it that do not exist yet, each readable and writable by
    the user alone (whatever the umask), so that a new cache is safe by construction."""
    missing = [path for path in [folder, *folder.parents] if not path.exists()]
    for path in reversed(missing):
        try:
            path.mkdir(mode=0o700)
            path.chmod(0o700)  # mkdir's mode passes through the umask
        except FileExistsError:
            pass
        except OSError:
            return  # not creatable: JAX reports it when it writes


def use_compile_cache(folder: str | Path | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``folder`` and return the folder.

    ``None``: the folder the process already uses (``JAX_COMPILATION_CACHE_DIR``), else
    [`default_compile_cache()`][spacegrasp_jax.jobs.compilation.default_compile_cache]; ``"none"``: leave the cache as it is and return ``None``.
    Every compiled program is written there (``CACHE_MIN_COMPILE_TIME_S``, unless
    ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`` or ``jax_persistent_cache_min_compile_time_secs``
    says otherwise); a later process with the same program, JAX version and XLA flags loads
    it instead of compiling it. Takes effect for programs compiled after the first compile of
    the process only if called before it.

    A folder that does not exist is created readable and writable by the user alone. One that
    other users can write (or that lies under such a folder) is refused with
    [`CacheFolderError`][spacegrasp_jax.jobs.compilation.CacheFolderError] before anything is loaded
    from it: its programs could be theirs."""
    if folder == "none":
        return None
    if folder is None:
        folder = jax.config.jax_compilation_cache_dir or default_compile_cache()
    folder = Path(folder)
    reason = executable_store.unsafe_folder_reason(folder)
    if reason is not None:
        raise CacheFolderError(f"compilation cache {folder}: {reason}")
    _make_private_folder(folder)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    users_choice = "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" in os.environ or (
        jax.config.jax_persistent_cache_min_compile_time_secs != _JAX_MIN_COMPILE_TIME_S
    )
    if not users_choice:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_TIME_S)
    return folder


def configure(
    *, float64: bool = True, loops_whole: bool = True, compile_cache: str | Path | bool | None = True
) -> None:
    """The process settings the package is built for, in one call (module docstring):
    [`enable_float64()`][spacegrasp_jax.core.precision.enable_float64], [`compile_loops_whole()`][spacegrasp_jax.jobs.compilation.compile_loops_whole] and the persistent compilation
    cache ([`use_compile_cache()`][spacegrasp_jax.jobs.compilation.use_compile_cache]), on by default in the folder the process already uses
    (``JAX_COMPILATION_CACHE_DIR``) or the per-user [`default_compile_cache()`][spacegrasp_jax.jobs.compilation.default_compile_cache]. Call it
    once, at the top of a script or notebook, before JAX runs anything::

        import spacegrasp_jax as sg
        sg.configure()

    Args:
        compile_cache: ``True`` or ``None``: the default folder; a folder: that one;
            ``False`` or ``"none"``: leave the cache as it is (off unless JAX was told
            otherwise).
    """
    if compile_cache is False or compile_cache == "none":
        folder = "none"
    elif compile_cache is True or compile_cache is None:
        folder = None
    else:
        folder = compile_cache
    if float64:
        enable_float64()
    if loops_whole:
        compile_loops_whole()
    use_compile_cache(folder)


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
    """``CPU_OPTIONS`` if this XLA accepts them, else ``{}``. Probed on first use (the
    probe compiles a scalar program, so it initialises the JAX backend)."""
    try:
        jax.jit(lambda x: x + 1.0, compiler_options=CPU_OPTIONS).lower(0.0).compile()
    except (jax.errors.JaxRuntimeError, TypeError):  # unknown option; a jit without the argument
        return {}
    return dict(CPU_OPTIONS)


def map_one_at_a_time(function: Callable, items):
    """``jax.lax.map(function, items)`` for a loop over whole runs (a device's samples, its
    sub-batches, the points of a search), which XLA:CPU never compiles whole.

    XLA:CPU compiles a loop whole when its body touches fewer bytes than the threshold
    (``LOOP_KERNEL_BYTES``), counting the inner loops' iterations, and a loop over runs of a
    short scenario stays under it. The program is then one function with every inner loop
    inside it, which takes LLVM up to three times as long (``spacegrasp gradients`` on a 0.2 s
    scenario: 89 s instead of 29 s), and the run gains nothing, as each iteration already
    lasts milliseconds or more. XLA:CPU never compiles a loop whole that sorts, so on a CPU
    each iteration also sorts the pair ``(i, -i)`` (``i`` the iteration) and returns
    ``function``'s outputs through a select on the pair being in order, which it always is:
    the outputs are ``function``'s exactly, and the sort's cost is nothing beside a run. (A
    library call would do the same, but a LAPACK call is set up by JAX while it traces, so a
    program holding one crashes when a later process loads it without tracing.) Other
    backends run ``jax.lax.map`` as it is.

    Args:
        function: one item in, a pytree of arrays out.
        items: a pytree of arrays with a leading axis (the items).

    Returns:
        ``function``'s outputs stacked along a leading axis, as ``jax.lax.map``.
    """
    if jax.default_backend() != "cpu":
        return jax.lax.map(function, items)
    count = jax.tree.leaves(items)[0].shape[0]

    def one(indexed):
        index, item = indexed
        outputs = function(item)
        pair = jnp.sort(jnp.stack([index, -index]))
        in_order = pair[0] <= pair[1]
        return jax.tree.map(lambda x: jnp.where(in_order, x, jnp.zeros_like(x)), outputs)

    return jax.lax.map(one, (jnp.arange(count), items))


def jit(fun: Callable, **jit_kwargs) -> Callable:
    """``jax.jit(fun, **jit_kwargs)`` compiled with [`compiler_options()`][spacegrasp_jax.jobs.compilation.compiler_options]. Call it when
    the program is about to be compiled, not at import: the options' probe initialises the
    JAX backend (``batching.use_all_cpu_cores`` must come before that)."""
    options = compiler_options()
    return jax.jit(fun, compiler_options=options, **jit_kwargs) if options else jax.jit(fun, **jit_kwargs)


def argument_signature(arguments) -> tuple:
    """What a compiled program depends on in its arguments: their tree structure and each
    leaf's shape, dtype and placement. Hashable.

    A NumPy array, a Python number and a ``jax.Array`` on the default device are placed
    alike (the same executable takes each), so they share a program; a leaf sharded over
    devices or on another device has its sharding in the signature."""
    leaves, structure = jax.tree.flatten(arguments)
    default = jax.devices()[0]

    def placement(leaf):
        sharding = getattr(leaf, "sharding", None)
        if isinstance(sharding, jax.sharding.SingleDeviceSharding) and sharding.device_set == {default}:
            return None
        return sharding

    specs = tuple(
        (np.shape(leaf), str(np.dtype(getattr(leaf, "dtype", np.asarray(leaf).dtype))), placement(leaf))
        for leaf in leaves
    )
    return structure, specs


_EXECUTABLES: dict = {}

#: Who hears of each compile that [`compile_once()`][spacegrasp_jax.jobs.compilation.compile_once] makes ([`listening()`][spacegrasp_jax.jobs.compilation.listening]); none by
#: default: the library compiles silently.
_LISTENERS: list = []


@contextlib.contextmanager
def listening(listener):
    """Within the block, ``listener.before(label, key)`` is called before each compile that
    [`compile_once()`][spacegrasp_jax.jobs.compilation.compile_once] makes and ``listener.after(label, key, seconds)`` after it (the
    command line prints a line naming each program and its expected duration)."""
    _LISTENERS.append(listener)
    try:
        yield listener
    finally:
        _LISTENERS.remove(listener)


#: The memory address in an object's default ``repr``: `` at 0x7f3676f0d760``.
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def documented_build_s(program: str) -> tuple[float, float]:
    """The documented range of cold builds (s) of ``program`` (``CompileAnnouncer.program()``'s
    name) on a quiet 2-core VM, or of any program of the package where that one has none
    (``data/compile_times.json``): the estimate the first time a machine builds it."""
    table = json.loads((Path(__file__).resolve().parents[1] / "data" / "compile_times.json").read_text())
    low, high = table["range_s"].get(program, table["any_program_s"])
    return float(low), float(high)


class CompileAnnouncer:
    """A [`listening()`][spacegrasp_jax.jobs.compilation.listening] listener that writes one line before each compile, naming the
    program and, when the same program was compiled before on this machine, how long that
    took (XLA's own slow-compile banner says nothing of what is compiling).

    The estimate follows the machine as it is now: each program keeps its last
    ``HISTORY_LENGTH`` compile times, and once a compile of this process has taken longer or
    shorter than its history said (a loaded machine, another one), the next estimates are
    scaled by how far this process's compiles are from their histories (the median ratio).

    Args:
        stream: where the lines go (the command line: stderr).
        history: a JSON file of each program's recent compile times (s), read and updated
            (the command line keeps it beside the compile cache); ``None``: no history.
    """

    #: How many compile times a program's history keeps.
    HISTORY_LENGTH = 5
    #: How far this process's pace must be from 1 before an estimate is scaled by it.
    PACE_TOLERANCE = 0.25

    def __init__(self, stream, history: Path | None = None):
        self.stream = stream
        self.history_path = None if history is None else Path(history)
        self.history = {}
        self.ratios: list[float] = []  # this process's compile times over their histories'
        self._expected: dict[str, float] = {}
        if self.history_path is not None:
            try:
                self.history = dict(json.loads(self.history_path.read_text()))
            except (OSError, ValueError, TypeError):
                self.history = {}

    @staticmethod
    def digest(key) -> str:
        """A name for ``key`` that stays the same from one process to the next: its
        ``repr`` without the memory addresses that name a function or another object
        (``<function f at 0x7f...>``), which change with every process."""
        stable = _ADDRESS.sub("", repr(key))
        return hashlib.sha256(stable.encode()).hexdigest()[:20]

    @staticmethod
    def program(key) -> str:
        """The kind of program ``key`` names, whatever its settings and shapes (its first
        entry; for [`batching.compile_chunk()`][spacegrasp_jax.jobs.batching.compile_chunk]'s keys, the job's name)."""
        parts = key if isinstance(key, tuple) else (key,)
        return f"program:{parts[1] if parts[0] == 'batch' and len(parts) > 1 else parts[0]}"

    def times(self, name: str) -> list[float]:
        """The recorded compile times (s) of ``name`` (a digest or a program), oldest first (a
        history of an older version holds one number)."""
        value = self.history.get(name)
        values = value if isinstance(value, list) else [value]
        return [float(item) for item in values if isinstance(item, (int, float)) and not isinstance(item, bool)]

    def pace(self) -> float | None:
        """How long this process's compiles take against their histories (the median ratio),
        or ``None`` before any compile with a history."""
        return float(np.median(self.ratios)) if self.ratios else None

    def before(self, label: str, key) -> None:
        times, similar = self.times(self.digest(key)), self.times(self.program(key))
        pace = self.pace()
        scaled = pace is not None and abs(pace - 1.0) > self.PACE_TOLERANCE
        if times:
            typical = float(np.median(times))
            self._expected[self.digest(key)] = typical
            if scaled:
                expected = (
                    f" (about {typical * pace:.1f} s: {typical:.1f} s before on this machine, and this run's "
                    f"compiles take {pace:.1f}x their usual time)"
                )
            elif len(times) > 1 and max(times) > (1.0 + self.PACE_TOLERANCE) * min(times):
                expected = f" ({min(times):.1f} to {max(times):.1f} s the last {len(times)} times on this machine)"
            else:
                expected = f" (last time {times[-1]:.1f} s on this machine)"
        elif similar:
            typical = float(np.median(similar)) * (pace if scaled else 1.0)
            expected = f" (first time for these settings, about {typical:.0f} s)"
        elif self.history_path is not None:
            low, high = documented_build_s(self.program(key))
            expected = (
                f" (first time on this machine: {low:.0f} to {high:.0f} s on a quiet 2-core VM, longer on a busy one)"
            )
        else:
            expected = ""
        print(f"compiling {label}{expected}...", file=self.stream, flush=True)

    def after(self, label: str, key, seconds: float) -> None:
        digest = self.digest(key)
        typical = self._expected.pop(digest, None)
        if typical:
            self.ratios.append(seconds / typical)
        for name in (digest, self.program(key)):
            self.history[name] = [*self.times(name), round(seconds, 2)][-self.HISTORY_LENGTH :]
        if self.history_path is None:
            return
        try:
            self.history_path.parent.mkdir(parents=True, exist_ok=True)
            temporary = self.history_path.with_name(f".{self.history_path.name}.{os.getpid()}")
            temporary.write_text(json.dumps(self.history, indent=0, sort_keys=True))
            os.replace(temporary, self.history_path)
        except OSError:
            pass  # a history that cannot be written only loses the next run's estimate


def compile_once(key, lower: Callable[[], Any], label: str | None = None) -> tuple[Any, float]:
    """The executable of ``lower().compile()``, compiled the first time ``key`` is asked for
    in this process and reused after: the package's one cache of compiled programs (JAX's
    persistent cache, [`use_compile_cache()`][spacegrasp_jax.jobs.compilation.use_compile_cache], keeps them across processes).

    Args:
        key: hashable; everything that shapes the program (its name, static settings and
            [`argument_signature()`][spacegrasp_jax.jobs.compilation.argument_signature] of its arguments).
        lower: builds the program's ``jax.stages.Lowered`` (called on a miss only).
        label: the program's name for people ([`listening()`][spacegrasp_jax.jobs.compilation.listening]); default ``str(key[0])``.

    A program compiled in an earlier process is loaded from the
    [`executable_store`][spacegrasp_jax.jobs.executable_store] when the key and the code allow
    it (no tracing, lowering or compiling, and no announcement), else compiled (and loaded
    from JAX's persistent cache where that has it).

    Returns:
        ``(executable, seconds)``: the time of the original compile or load (s).
    """
    if key in _EXECUTABLES:
        return _EXECUTABLES[key]
    stored = executable_store.path_for(key)
    start = time.perf_counter()
    executable = None if stored is None else executable_store.load(stored)
    if executable is not None:
        _EXECUTABLES[key] = (executable, time.perf_counter() - start)
        return _EXECUTABLES[key]
    label = label if label is not None else str(key[0] if isinstance(key, tuple) else key)
    for listener in _LISTENERS:
        listener.before(label, key)
    start = time.perf_counter()
    with _jax_cache_hits() as hits:
        executable = lower().compile()
    _EXECUTABLES[key] = (executable, time.perf_counter() - start)
    for listener in _LISTENERS:
        listener.after(label, key, _EXECUTABLES[key][1])
    if stored is not None and not hits:
        # An executable JAX read from its own cache serialises without its compiled
        # functions: only a fresh compile is stored.
        executable_store.save(stored, executable)
    return _EXECUTABLES[key]


@contextlib.contextmanager
def _jax_cache_hits():
    """The programs JAX's persistent cache served within the block (a list of its events)."""
    hits = []

    def heard(event: str, **_):
        if event == "/jax/compilation_cache/cache_hits":
            hits.append(event)

    jax.monitoring.register_event_listener(heard)
    try:
        yield hits
    finally:
        jax.monitoring.unregister_event_listener(heard)
