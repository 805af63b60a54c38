"""How tightly a stored result may be checked here: bit for bit (1e-12) only on a machine
that reproduced it so, across machines at the tolerance their variation was measured to need.

XLA:CPU compiles for the processor it runs on (its vector width, fused multiply-adds), so a
17 s closed loop of 17,000 steps magnifies a change of rounding between two x86-64 machines:
the first 16 flight-like captures of seed 20261202 differed by up to 5.8e-9 relative
(3.4e-11 m) between a 2-core Intel Xeon VM and a 2-core AMD EPYC VM, with the same verdicts.
A folder of stored results lists, in ``machines.json``, the machines (``fingerprint()``) on
which they were reproduced to 1e-12; elsewhere they are checked to ``CROSS_MACHINE_RTOL``.
"""

from __future__ import annotations

import json
from pathlib import Path

import jaxlib

#: Same machine: the stored values again, to rounding.
SAME_MACHINE_RTOL = 1e-12

#: Another x86-64 machine: 17 times the largest difference measured between two (5.8e-9).
CROSS_MACHINE_RTOL = 1e-7

#: The processor features that change what XLA:CPU generates.
_ISA_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl", "avx512_bf16", "amx_tile")


def fingerprint() -> str:
    """This machine as far as XLA's rounding is concerned: the processor's model, the vector
    features XLA:CPU compiles for, and jaxlib's version."""
    model, flags = "unknown processor", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and model == "unknown processor":
                model = value.strip()
            elif key.strip() == "flags" and not flags:
                flags = set(value.split())
    except OSError:
        pass
    features = ",".join(flag for flag in _ISA_FLAGS if flag in flags)
    return f"{model} [{features}] jaxlib {jaxlib.__version__}"


def tolerance(folder: Path) -> tuple[float, str]:
    """The relative tolerance to which ``folder``'s stored results are checked on this machine,
    and which kind of check that is (``"same machine"`` or ``"across machines"``)."""
    listed = folder / "machines.json"
    machines = json.loads(listed.read_text())["reproduced_to_1e-12_on"] if listed.exists() else []
    if fingerprint() in machines:
        return SAME_MACHINE_RTOL, "same machine"
    return CROSS_MACHINE_RTOL, "across machines"
