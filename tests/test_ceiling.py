"""What caps a campaign's success (``spacegrasp ceiling``, ``spacegrasp_jax.tuning.ceiling``):
each failed capture tuned alone.

The search's verdict is checked against the campaign's own (the margin of each tried capture
at the campaign's gains, sample for sample) and against a replay with the sample's full log
(``spacegrasp replay --gains``, a program of its own) of the gains it kept; the ceiling's
arithmetic against a Wilson interval worked by hand."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spacegrasp_jax import cli
from spacegrasp_jax.analysis.limit_state import capture_margin
from spacegrasp_jax.jobs import campaign
from spacegrasp_jax.tuning import ceiling

#: A 2 s approach: the flight-like campaign's failures come from its tight tolerance.
SHORT = "duration = 2.0\n[trajectory]\nduration = 2.0\n"
CAMPAIGN = ["--n", "8", "--chunk", "8", "--seed", "3", "--realism", "flight", "--controller", "admittance"]
CAMPAIGN += ["--tolerance-mm", "43", "--tolerance-deg", "3", "--compile-cache", "none"]


def test_the_ceiling_adds_the_fixed_share_of_the_failures():
    """70 of 100 captured, 5 of 10 tried failures fixed: the share 0.5 with Wilson's interval
    [0.2366, 0.7634] (``(p + z^2 / 2n +- z sqrt(p (1 - p) / n + z^2 / 4n^2)) / (1 + z^2 / n)``,
    z = 1.96), so the ceiling 0.70 + 0.30 x 0.5 = 0.85 in [0.771, 0.929]."""
    result = ceiling.ceiling_of(70, 100, 10, 5)
    assert result["ceiling"] == pytest.approx(0.85)
    assert result["low"] == pytest.approx(0.70 + 0.30 * 0.23659, abs=1e-4)
    assert result["high"] == pytest.approx(0.70 + 0.30 * 0.76341, abs=1e-4)
    assert ceiling.ceiling_of(70, 100, 0, 0)["ceiling"] == 0.70


def test_the_failures_tried_are_failed_captures_drawn_without_replacement():
    success = np.ones(100, bool)
    success[[3, 17, 40, 41, 99]] = False
    np.testing.assert_array_equal(ceiling.chosen_failures(success, 10, 0), [3, 17, 40, 41, 99])
    chosen = ceiling.chosen_failures(success, 3, 7)
    assert len(set(chosen)) == 3 and set(chosen) <= {3, 17, 40, 41, 99} and list(chosen) == sorted(chosen)
    np.testing.assert_array_equal(chosen, ceiling.chosen_failures(success, 3, 7))


@pytest.fixture(scope="module")
def short_campaign(tmp_path_factory):
    """A flight-like campaign of 8 captures of the 2 s approach with the paper's gains, some
    of them failed, and its samples."""
    folder = tmp_path_factory.mktemp("ceiling")
    scenario = folder / "short.toml"
    scenario.write_text(SHORT)
    out = folder / "campaign"
    assert cli.main(["montecarlo", *CAMPAIGN, "--scenario", str(scenario), "--out", str(out)]) == 0
    _, by_variant = campaign.load_samples(out / "samples.npz")
    return folder, out, by_variant["admittance/paper"]


@pytest.mark.slow
def test_each_failure_tuned_alone_is_judged_as_the_campaign_and_a_replay_judge_it(short_campaign, capsys):
    """``spacegrasp ceiling`` on its five failures, three steps each: each row's starting margin is
    the campaign's margin of that sample; the margin it ends with is at least that; the gains
    it kept, replayed with the sample's full log, give that margin (1e-9) and the verdict;
    ``--resume`` tunes nothing again, and refuses other settings before anything runs."""
    folder, out, samples = short_campaign
    failed = np.flatnonzero(~np.asarray(samples["success"], bool))
    assert failed.size >= 2, "the short campaign needs failures (its tolerance)"
    record, config = campaign.campaign_record(out)
    margins = np.asarray(capture_margin({k: np.asarray(samples[k], float) for k in NEEDED}, config.criteria))
    result = folder / "ceiling"
    argv = ["ceiling", str(out), "--failures", "5", "--steps", "3", "--compile-cache", "none", "--out", str(result)]
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    assert "ceiling: " in printed
    document = json.loads((result / "ceiling.json").read_text())
    assert document["failures_tried"] == 5 and document["failures"] == failed.size
    assert document["fixed"] == sum(row["fixed"] for row in document["rows"])
    for row in document["rows"]:
        index = row["sample"]
        assert index in failed
        np.testing.assert_allclose(row["margin_before"], margins[index], rtol=1e-9, atol=1e-12)
        assert row["margin_after"] >= row["margin_before"]
        assert row["fixed"] == (row["margin_after"] > 0.0)
        replayed = folder / f"replay_{index}"
        gains = str(result / row["gains_file"])
        replay = ["replay", str(out), "--sample", str(index), "--gains", gains, "--out", str(replayed)]
        assert cli.main([*replay, "--compile-cache", "none"]) == 0
        summary = json.loads((replayed / "summary.json").read_text())[f"admittance/sample_{index}"]
        replayed_margin = float(
            capture_margin({k: np.asarray(v, float) for k, v in summary.items() if k in NEEDED}, config.criteria)
        )
        np.testing.assert_allclose(replayed_margin, row["margin_after"], rtol=1e-9, atol=1e-12)
        assert summary["capture_success"] == row["fixed"]
    capsys.readouterr()
    rows = (result / "ceiling.jsonl").read_text()
    assert cli.main([*argv, "--resume"]) == 0
    assert (result / "ceiling.jsonl").read_text() == rows  # nothing tuned again
    changed = [*argv, "--resume"]
    changed[changed.index("--steps") + 1] = "4"
    assert cli.main(changed) == 2
    assert "rows of other settings" in capsys.readouterr().err


#: The summary fields the margin reads.
NEEDED = (
    "final_position_error_m",
    "final_orientation_error_rad",
    "largest_peak_torque_Nm",
    "max_range_excess_rad",
    "first_runaway_s",
    "first_nonfinite_s",
)


@pytest.mark.slow
def test_a_variant_the_campaign_does_not_hold_is_refused(short_campaign, tmp_path, capsys):
    _, out, _ = short_campaign
    argv = ["ceiling", str(out), "--variant", "admittance/flight", "--out", str(tmp_path / "a")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "--variant: " in err and "it has admittance/paper" in err
    assert not (tmp_path / "a").exists()  # refused before the folder is claimed
