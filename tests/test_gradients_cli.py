"""``spacegrasp gradients`` at toy size (0.4 s, three perturbed samples): every key of
``gradients.json`` present and finite at the paper's gains, central differences agreeing
with the gradient, and gains that make every loop diverge reported as non-finite, not
hidden. Both runs share one compiled program (the gains are an argument of it)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from spacegrasp_jax import cli
from spacegrasp_jax.tuning.parameters import GROUPS as TUNED_GROUPS

pytestmark = pytest.mark.slow  # the gradients command's program: reverse mode over a batch

N = 3
SCENARIO = "duration = 0.4\n[trajectory]\nduration = 0.4\n"
GROUPS = TUNED_GROUPS["admittance"]  # what the report covers: the tuned groups


def _run(tmp_path, name, *extra):
    out = tmp_path / name
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(SCENARIO)
    argv = ["gradients", "--n", str(N), "--scenario", str(scenario), "--out", str(out), "--chunk", "4"]
    code = cli.main([*argv, "--fd-samples", "2", "--compile-cache", "none", *extra])
    return code, out


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gradients")
    (folder / "wild.json").write_text(json.dumps({"kp": [1e7] * 7}))
    healthy = _run(folder, "paper")
    diverging = _run(folder, "wild", "--gains", str(folder / "wild.json"), "--fill-from", "paper")
    return healthy, diverging


def _all_finite(value) -> bool:
    if isinstance(value, dict):
        return all(_all_finite(item) for key, item in value.items() if key != "settings")
    if isinstance(value, list):
        return all(_all_finite(item) for item in value)
    return value is not None and (not isinstance(value, float) or math.isfinite(value))


def test_every_key_present_and_finite_at_the_papers_gains(reports):
    (code, out), _ = reports
    assert code == 0
    document = json.loads((out / "gradients.json").read_text())
    for key in (
        "samples",
        "horizons_s",
        "nominal",
        "nonfinite",
        "groups",
        "norm_over_nominal",
        "cosine_with_nominal",
        "outliers",
        "per_sample",
        "horizon_growth",
        "central_differences",
        "settings",
    ):
        assert key in document, key
    outliers = document["outliers"]
    if outliers["count"] == 0:  # no outlier: no median loss of the outliers (null, by the files' convention)
        assert outliers.pop("median_loss") is None
    assert _all_finite(document), document
    assert document["samples"] == N and document["nonfinite"]["count"] == 0 and document["nominal"]["finite"]
    assert set(document["groups"]) == set(GROUPS)
    for name, group in document["groups"].items():
        for statistic in ("nominal", "mean", "median", "std", "iqr", "sign_agreement"):
            assert len(group[statistic]) == len(group["nominal"]), (name, statistic)
        assert all(0.0 <= value <= 1.0 for value in group["sign_agreement"])
    assert document["horizons_s"] == pytest.approx([0.05, 0.1, 0.2, 0.4])
    assert len(document["per_sample"]["norm_over_nominal"]) == N
    # the gradient against central differences of the same loss (independent of the tape)
    assert len(document["central_differences"]) == 2
    for check in document["central_differences"]:
        assert check["relative_error"] < 1e-5, check
    # the nominal gradient in gradients.npz is the one the report describes
    arrays = np.load(out / "gradients.npz")
    nominal = np.concatenate([arrays[f"gradient.{name}"][0, -1] for name in document["groups"]])
    assert np.linalg.norm(nominal) == pytest.approx(document["nominal"]["gradient_norm"], rel=1e-12)
    assert (out / "gradients.png").stat().st_size > 0
    # the run's record: what it ran, read back
    from spacegrasp_jax.jobs.records import RunRecord

    record = RunRecord.from_dict(document["settings"]["record"])
    assert [variant.key for variant in record.variants] == ["admittance/paper"]
    assert record.scenario.contact_law == "smooth" and record.command[:2] == ("spacegrasp", "gradients")


def test_a_diverging_envelope_is_reported_not_hidden(reports, capsys):
    _, (code, out) = reports
    assert code == 0
    document = json.loads((out / "gradients.json").read_text())
    assert document["nonfinite"]["count"] == N and not document["nominal"]["finite"]
    listed = document["nonfinite"]["samples"]
    assert [row["sample"] for row in listed] == list(range(1, N + 1))
    assert all("dq_init" in row["perturbation"] for row in listed)
    assert document["central_differences"] == []  # no finite sample to check
