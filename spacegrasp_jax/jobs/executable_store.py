"""Compiled programs kept on disk under the package's own program keys, so that a later
process skips tracing and lowering as well as compiling.

JAX's persistent cache (``spacegrasp_jax.jobs.compilation.use_compile_cache``) is keyed by the
lowered program: a later process finds a program there only after tracing and lowering it
again, which for the flight-like loop's batched programs takes longer than loading (about
6 s of a warm ``spacegrasp tune --realism flight`` of 15 s on 2 cores). Every program the package
compiles is also named by a key ([`compile_once()`][spacegrasp_jax.jobs.compilation.compile_once]:
its name, static settings and argument shapes). This store keeps the executable under that
key, in a folder ``executables`` inside JAX's cache folder, so that a process asking for the
same program loads it before tracing anything.

A key names a program only together with the code that builds it, so a stored program is
found only by a process with:

* the same source files of ``spacegrasp_jax`` (its ``tuning`` and ``benchmarks`` included),
  byte for byte;
* the same JAX and jaxlib versions, JAX options (``jax.config.values``), ``XLA_FLAGS``,
  devices and Python version.

A key is stored only if every object in it is described by its value: numbers, strings,
tuples, NumPy dtypes, JAX devices and shardings, the package's enums, frozen dataclasses and
module-level functions, and pytree structures made of these. A function or class defined
outside the package (a user's own law, say), a closure or anything else whose ``repr``
holds a memory address makes the program one that is compiled (and found in JAX's cache)
as before: its code is not in the fingerprint, so a stored copy could be stale. Nothing is
stored in a multi-process run.

A program that calls LAPACK (a custom call ``lapack_*``: a solve, a factorisation) is not
stored: JAX sets up its LAPACK kernels while it lowers a program that calls them, so a
process that loaded such a program untraced would crash at its first call.

The stored files are compressed pickles holding executables (0.2-1.2 MB each for the
package's programs): loading one runs its code. So a cache folder is used only if no other
user can have written it ([`unsafe_folder_reason()`][spacegrasp_jax.jobs.executable_store.unsafe_folder_reason],
the rule ssh applies to its keys): the folder is the user's own and writable by no one else,
and so is every folder above it (or it is the administrator's, or sticky like ``/tmp``).
Storing a program takes 0.1-0.3 s after its compile; loading one, 0.2-0.9 s.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import importlib.util
import os
import pickle
import stat
import sys
import types
import zlib
from pathlib import Path

import jax
import numpy as np

#: The folder, inside JAX's compilation cache folder, of the stored programs.
FOLDER = "executables"

#: The modules whose code the fingerprint covers: their functions, classes and enums may be
#: named in a stored key.
_PACKAGE_ROOT = "spacegrasp_jax"

#: The custom calls that a stored program may not hold: kernels that JAX sets up only while
#: it lowers a program calling them (module docstring).
_SET_UP_WHILE_LOWERING = 'custom_call_target="lapack_'

#: Modules of the libraries whose objects in a key are described by their ``repr``.
_LIBRARY_ROOTS = ("builtins", "numpy", "jax", "jaxlib")


class _NotDescribable(Exception):
    """An object of a key is not described by its value (its code is outside the package)."""


def _in_package(module: str | None) -> bool:
    return module is not None and (module == _PACKAGE_ROOT or module.startswith(_PACKAGE_ROOT + "."))


def _describe_type(kind: type) -> str:
    module = getattr(kind, "__module__", None)
    if "<locals>" in kind.__qualname__:
        raise _NotDescribable(kind)
    if _in_package(module) or (module or "").split(".")[0] in _LIBRARY_ROOTS:
        return f"{module}.{kind.__qualname__}"
    raise _NotDescribable(kind)


def _describe(value) -> str:
    """A text that names ``value`` the same in every process running the same code.

    Raises:
        _NotDescribable: ``value`` holds something whose meaning is not in its value.
    """
    if value is None or isinstance(value, (bool, int, float, complex, str, bytes)):
        return f"{type(value).__name__}:{value!r}"
    if isinstance(value, (tuple, list)):
        return f"{type(value).__name__}({','.join(_describe(item) for item in value)})"
    if isinstance(value, (frozenset, set)):
        return f"set({','.join(sorted(_describe(item) for item in value))})"
    if isinstance(value, dict):
        items = sorted(f"{_describe(k)}:{_describe(v)}" for k, v in value.items())
        return f"dict({','.join(items)})"
    if isinstance(value, np.dtype):
        return f"dtype:{value}"
    if isinstance(value, enum.Enum):
        return f"{_describe_type(type(value))}.{value.name}"
    if isinstance(value, type):
        return _describe_type(value)
    if isinstance(value, types.FunctionType):
        if not _in_package(value.__module__) or "<locals>" in value.__qualname__:
            raise _NotDescribable(value)
        return f"function:{value.__module__}.{value.__qualname__}"
    if isinstance(value, functools.partial):
        return f"partial({_describe(value.func)},{_describe(value.args)},{_describe(value.keywords)})"
    if isinstance(value, jax.tree_util.PyTreeDef):
        return _describe_structure(value)
    if dataclasses.is_dataclass(value):
        fields = ",".join(f"{f.name}={_describe(getattr(value, f.name))}" for f in dataclasses.fields(value))
        return f"{_describe_type(type(value))}({fields})"
    text = repr(value)
    if " at 0x" in text:
        raise _NotDescribable(value)
    return f"{_describe_type(type(value))}:{text}"


def _describe_structure(structure: jax.tree_util.PyTreeDef) -> str:
    """A pytree structure node by node: each node's type and static data, then its children."""
    if structure.num_nodes == 1 and structure.num_leaves == 1:
        return "*"
    node = structure.node_data()
    if node is None:  # None, or an empty container JAX does not name
        return f"leafless:{structure!r}"
    kind, static = node
    children = ",".join(_describe_structure(child) for child in structure.children())
    return f"{_describe_type(kind)}[{_describe(static)}]({children})"


@functools.cache
def _source_digest() -> str:
    """SHA-256 of the package's source files (``tuning`` and ``benchmarks`` included,
    wherever they are installed)."""
    folders = []
    for name in (_PACKAGE_ROOT, f"{_PACKAGE_ROOT}.tuning", f"{_PACKAGE_ROOT}.benchmarks"):
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.origin and Path(spec.origin).parent not in folders:
            folders.append(Path(spec.origin).parent)
    digest = hashlib.sha256()
    for folder in folders:
        for path in sorted(folder.rglob("*.py")):
            digest.update(str(path.relative_to(folder)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def _environment() -> str:
    """What besides the key shapes a program: code, versions, options and devices."""
    import jaxlib

    options = sorted((name, repr(value)) for name, value in jax.config.values.items())
    devices = [(d.platform, d.device_kind, d.id, d.process_index) for d in jax.devices()]
    return repr(
        (
            _source_digest(),
            jax.__version__,
            jaxlib.__version__,
            sys.version,
            os.environ.get("XLA_FLAGS", ""),
            options,
            devices,
        )
    )


def _cache_folder() -> str | None:
    """JAX's compilation cache folder (``None`` where the cache is off)."""
    return jax.config.jax_compilation_cache_dir


def unsafe_folder_reason(folder: str | Path) -> str | None:
    """Why programs must not be loaded from, or stored in, ``folder``, or ``None`` where it
    is safe: the folder (if it exists) is owned by this process's user and writable by no one
    else, and every folder above it is owned by the user or the administrator (root) and
    writable by no one else, unless sticky (``/tmp``: others may add entries there, but not
    rename or remove this user's). A folder that does not exist yet is judged by those above
    it. The reason is one clause naming the folder and how to fix it."""
    user = os.getuid()
    folder = Path(os.path.abspath(folder))
    for level, path in enumerate([folder, *folder.parents]):
        try:
            status = path.stat()
        except FileNotFoundError:
            continue
        except OSError as error:
            return f"{path} cannot be inspected ({error.strerror})"
        owners = (user,) if level == 0 else (user, 0)
        if status.st_uid not in owners:
            whose = "" if level == 0 else "and it holds the cache: "
            return f"{path} is owned by another user (uid {status.st_uid}); {whose}use a folder of your own"
        writable_by_others = status.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
        if writable_by_others and not (level > 0 and status.st_mode & stat.S_ISVTX):
            return (
                f"{path} is writable by others (mode {stat.S_IMODE(status.st_mode):04o}), who could put programs "
                f"there that this process would run: make it yours alone (chmod go-w {path})"
            )
    return None


def path_for(key) -> Path | None:
    """Where the program of ``key`` is stored, or ``None`` where it is not stored: JAX's
    compilation cache is off, the run spans processes, the folder is writable by others
    ([`unsafe_folder_reason()`][spacegrasp_jax.jobs.executable_store.unsafe_folder_reason]), or the key
    holds something not described by its value (module docstring)."""
    folder = _cache_folder()
    if not folder or jax.process_count() > 1 or unsafe_folder_reason(folder) is not None:
        return None
    try:
        described = _describe(key)
    except _NotDescribable:
        return None
    name = hashlib.sha256((described + _environment()).encode()).hexdigest()[:32]
    return Path(folder) / FOLDER / f"{name}.pickle"


def load(path: Path):
    """The ``jax.stages.Compiled`` stored at ``path``, or ``None``: no such file, or one
    this process cannot load, which is removed (the program is then compiled, or loaded
    from JAX's cache, and stored again after a fresh compile)."""
    from jax.experimental import serialize_executable

    try:
        payload, in_tree, out_tree, device_ids = pickle.loads(zlib.decompress(path.read_bytes()))
        by_id = {device.id: device for device in jax.devices()}
        devices = [by_id[i] for i in device_ids]
        return serialize_executable.deserialize_and_load(payload, in_tree, out_tree, execution_devices=devices)
    except FileNotFoundError:
        return None
    except Exception:  # a partial, foreign or outdated file: compile instead
        path.unlink(missing_ok=True)
        return None


def save(path: Path, executable) -> bool:
    """Store ``executable`` (a ``jax.stages.Compiled``) at ``path``, atomically; ``False``
    where it cannot be serialised or written, or calls LAPACK (it is then only in JAX's
    cache)."""
    from jax.experimental import serialize_executable

    try:
        if _SET_UP_WHILE_LOWERING in (executable.as_text() or ""):
            return False
        payload, in_tree, out_tree = serialize_executable.serialize(executable)
        device_ids = [device.id for device in executable.runtime_executable().local_devices()]
        # zlib's fastest level: a fifth of the size for some 20 ms a program.
        data = zlib.compress(pickle.dumps((payload, in_tree, out_tree, device_ids)), 1)
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_name(f".{path.name}.{os.getpid()}")
        temporary.write_bytes(data)
        os.replace(temporary, path)
    except Exception:  # not serialisable (constants in the program), or the disk refused
        return False
    return True
