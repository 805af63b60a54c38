"""The tuner's code may change, not what it computes: four short runs at fixed seeds (the
gradient method and CMA-ES, the ideal and the flight-like loop) give the stored reference's
steps, tuned gains and held-out parts, to 1e-12 on a machine that reproduced them so and to
the measured cross-machine tolerance elsewhere (``tests/stored_results.py``); a part that is
the difference of two others (``DIFFERENCES``) to that tolerance of the larger. The reference
was written by ``tests/tuner_reference.py`` with the version before the tuner's methods
shared one driver."""

from __future__ import annotations

import numpy as np
import pytest
import stored_results
import tuner_reference

#: Parts that are a difference of two others: ``part`` -> the larger of its terms.
DIFFERENCES = {"peak_torque_gap": "peak_torque_smooth"}


def renamed(key: str) -> str:
    """A stored array's key with today's names of the objective's parts (the reference was
    written before the final errors took the campaign's names: a name, not a result)."""
    from spacegrasp_jax.tuning.objective import OLDER_PART_NAMES

    group, _, name = key.partition("/")
    prefix = next((p for p in ("start_", "tuned_") if group == "holdout" and name.startswith(p)), "")
    name = name[len(prefix) :]
    return f"{group}/{prefix}{OLDER_PART_NAMES.get(name, name)}"


@pytest.mark.slow
@pytest.mark.parametrize("name", list(tuner_reference.RUNS))
def test_a_tuning_run_gives_the_stored_reference(tmp_path, name):
    rtol, kind = stored_results.tolerance(tuner_reference.FOLDER)
    got = tuner_reference.run(name, tmp_path)
    with np.load(tuner_reference.FOLDER / f"{name}.npz") as stored:
        expected = {renamed(key): stored[key] for key in stored.files}
    assert set(expected) <= set(got), sorted(set(expected) - set(got))  # new columns may come, none may go
    for key, value in expected.items():
        # a difference of two near-equal parts carries their rounding: it is checked to the
        # tolerance of the larger part (the ideal loop's held-out program now runs each
        # sample's robot as a batched argument, which moves the last bits of both terms)
        term = next((key.replace(part, of) for part, of in DIFFERENCES.items() if key.endswith(part)), None)
        atol = rtol * np.max(np.abs(got[term])) if term else 1e-300
        np.testing.assert_allclose(got[key], value, rtol=rtol, atol=atol, err_msg=f"{name}: {key} ({kind})")
