"""The gradient estimators against independent definitions: SciPy's trimmed mean, NumPy's
median and mean, and the exact gradients of quadratic and linear functions, for which the
antithetic differences are exact and only the sampling noise is left."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from spacegrasp_jax.tuning import estimators


@pytest.fixture
def heavy_tailed():
    """(64, 5) samples around (1, -2, 0.5, 0, 3), one of them 100 times a typical norm."""
    rng = np.random.default_rng(7)
    samples = np.array([1.0, -2.0, 0.5, 0.0, 3.0]) + 0.3 * rng.standard_normal((64, 5))
    samples[11] *= 100.0
    return samples


def test_batch_estimators_match_their_definitions(heavy_tailed):
    samples = heavy_tailed
    np.testing.assert_allclose(estimators.aggregate(samples, "mean"), samples.mean(axis=0), rtol=1e-15)
    np.testing.assert_allclose(
        estimators.aggregate(samples, "trimmed", trim=0.1), stats.trim_mean(samples, 0.1, axis=0), rtol=1e-14
    )
    # median of means: one group is the mean, a group per sample the coordinate-wise median
    np.testing.assert_allclose(estimators.aggregate(samples, "median_of_means", groups=1), samples.mean(axis=0))
    np.testing.assert_allclose(
        estimators.aggregate(samples, "median_of_means", groups=64), np.median(samples, axis=0), rtol=1e-15
    )
    # clip: the outlier counts as a sample of 3 median norms along its own direction
    norms = np.linalg.norm(samples, axis=1)
    ceiling = 3.0 * np.median(norms)
    expected = samples.copy()
    expected[norms > ceiling] *= (ceiling / norms[norms > ceiling])[:, None]
    np.testing.assert_allclose(estimators.aggregate(samples, "clip"), expected.mean(axis=0), rtol=1e-14)
    assert np.sum(norms > ceiling) == 1
    # the robust ones stay near the centre; the mean does not
    centre = np.array([1.0, -2.0, 0.5, 0.0, 3.0])
    for method in ("clip", "trimmed", "median_of_means"):
        assert np.linalg.norm(estimators.aggregate(samples, method) - centre) < 0.3, method
    assert np.linalg.norm(estimators.aggregate(samples, "mean") - centre) > 3.0


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda s: estimators.aggregate(s, "mode"), "aggregate: expected one of"),
        (lambda s: estimators.aggregate(s[:0], "mean"), r"shape \(S, P\) with S >= 1"),
        (lambda s: estimators.aggregate(s, "trimmed", trim=0.5), r"trim: must be in \[0, 0.5\)"),
        (lambda s: estimators.aggregate(s, "median_of_means", groups=65), "groups: must be from 1 to the 64"),
        (lambda s: estimators.alpha_mix(s, s[:1]), "alpha_mix: needs at least 2 samples of each kind"),
    ],
)
def test_bad_settings_are_refused(heavy_tailed, call, message):
    with pytest.raises(ValueError, match=message):
        call(heavy_tailed)


def test_zeroth_order_samples_estimate_a_quadratics_gradient():
    """For ``L = theta^T A theta / 2 + b^T theta`` the antithetic difference is exactly
    ``eps^T (A theta + b)``, so the mean over M pairs is off the gradient by sampling noise
    alone: each coordinate's standard error is ``|grad| / sqrt(M)`` up to a factor near 1."""
    rng = np.random.default_rng(3)
    size, count, sigma = 6, 40_000, 0.07
    root = rng.standard_normal((size, size))
    A, b, theta = root @ root.T, rng.standard_normal(size), rng.standard_normal(size)
    loss = lambda x: 0.5 * np.einsum("...i,ij,...j->...", x, A, x) + x @ b
    directions = rng.standard_normal((count, size))
    samples = estimators.zeroth_order_samples(
        loss(theta + sigma * directions), loss(theta - sigma * directions), directions, sigma
    )
    gradient = A @ theta + b
    np.testing.assert_allclose(samples, directions * (directions @ gradient)[:, None], rtol=1e-9, atol=1e-9)
    error = samples.mean(axis=0) - gradient
    standard_error = samples.std(axis=0, ddof=1) / math.sqrt(count)
    assert np.all(np.abs(error) < 5.0 * standard_error), (error, standard_error)
    assert estimators.variance_of_mean(samples) == pytest.approx(np.sum(standard_error**2), rel=1e-12)


def test_alpha_mix_weighs_by_variance_and_distrusts_a_biased_first_order_estimate():
    rng = np.random.default_rng(11)
    gradient = np.array([2.0, -1.0, 0.5, 1.5])
    first = gradient + 0.1 * rng.standard_normal((32, 4))  # precise
    zeroth = gradient + 3.0 * rng.standard_normal((32, 4))  # noisy
    mix = estimators.alpha_mix(first, zeroth, first="mean")
    var_first = np.sum(first.var(axis=0, ddof=1)) / 32
    var_zeroth = np.sum(zeroth.var(axis=0, ddof=1)) / 32
    assert mix.alpha == pytest.approx(var_zeroth / (var_first + var_zeroth), rel=1e-12)
    assert mix.alpha > 0.99
    np.testing.assert_allclose(
        mix.gradient, mix.alpha * first.mean(axis=0) + (1 - mix.alpha) * zeroth.mean(axis=0), rtol=1e-14
    )
    # a first-order estimate off by far more than the noise explains is trusted only as far
    # as the noise covers the bias it could bring
    biased = first + np.array([30.0, 30.0, -30.0, 30.0])
    mix = estimators.alpha_mix(biased, zeroth, first="mean")
    assert mix.disagreement > mix.noise
    assert mix.alpha * mix.disagreement == pytest.approx(mix.noise, rel=1e-12)
    assert mix.alpha < 0.1
    assert np.linalg.norm(mix.gradient - gradient) < np.linalg.norm(biased.mean(axis=0) - gradient) / 5


def test_guided_directions_have_the_guided_es_covariance_and_find_the_gradient():
    rng = np.random.default_rng(5)
    size, share = 8, 0.25
    guides = rng.standard_normal((2, size))
    directions = estimators.guided_directions(rng, guides, 200_000, share=share)
    basis, _ = np.linalg.qr(guides.T)
    covariance = share / size * np.eye(size) + (1 - share) / 2 * basis @ basis.T
    assert np.trace(covariance) == pytest.approx(1.0)
    np.testing.assert_allclose(np.cov(directions.T), covariance, atol=0.01 * np.abs(covariance).max())
    # a linear loss g^T theta: the estimate is P C g in expectation; with the guide along g,
    # nearly g's direction
    g = rng.standard_normal(size)
    directions = estimators.guided_directions(rng, g[None], 4_000, share=0.1)
    sigma, theta = 0.05, rng.standard_normal(size)
    estimate = estimators.guided_estimate(
        (theta + sigma * directions) @ g, (theta - sigma * directions) @ g, directions, sigma
    )
    assert estimators.cosine(estimate, g) > 0.99
    basis = g[:, None] / np.linalg.norm(g)
    expected = size * (0.1 / size * np.eye(size) + 0.9 * basis @ basis.T) @ g
    assert np.linalg.norm(estimate - expected) < 0.03 * np.linalg.norm(expected)
    with pytest.raises(ValueError, match="share: must be in"):
        estimators.guided_directions(rng, guides, 4, share=0.0)


def test_the_benchmark_compares_estimators_without_comparing_one_with_itself():
    """``benchmarks.estimators.compare_estimators`` on synthetic pools of a known gradient:
    first-order samples with heavy-tailed outliers, zeroth-order pairs of a linear loss. The
    robust aggregates agree with the references and with themselves; the plain mean's
    outliers pull it away; the zeroth-order estimates are unbiased but noisy."""
    from spacegrasp_jax.benchmarks.estimators import compare_estimators

    rng = np.random.default_rng(2)
    size, gradient = 8, np.linspace(1.0, -1.0, 8)
    first = gradient + 0.3 * rng.standard_normal((256, size))
    first[rng.choice(256, 12, replace=False)] *= rng.choice([-300.0, 300.0], size=(12, 1))  # chaotic captures
    directions = rng.standard_normal((1024, size))
    sigma = 0.05
    zeroth = estimators.zeroth_order_samples(
        (sigma * directions) @ gradient, -(sigma * directions) @ gradient, directions, sigma
    )
    guides = estimators.guided_directions(rng, gradient[None], 256)
    guided = ((sigma * guides) @ gradient, -(sigma * guides) @ gradient, guides)
    report = compare_estimators(first, zeroth, guided, batch=32, draws=50, seed=0, sigma=sigma)
    rows = report["estimators"]
    assert rows["first_order_trimmed"]["split_half_cosine"]["median"] > 0.95
    assert rows["first_order_trimmed"]["cosine_with_zeroth_order"]["median"] > 0.9
    trimmed_agreement = rows["first_order_trimmed"]["split_half_cosine"]["median"]
    assert rows["first_order_mean"]["split_half_cosine"]["median"] < trimmed_agreement - 0.2  # steered by outliers
    assert 0.5 < rows["zeroth_order_equal_cost"]["cosine_with_zeroth_order"]["median"] < 0.99
    assert rows["zeroth_order"]["cost_rollouts"] == 64 and rows["first_order_trimmed"]["cost_rollouts"] == 112
    assert rows["guided_es"]["cosine_with_zeroth_order"] > 0.9
    assert report["references"]["first_order_largest_norm_over_median"] > 100


def test_the_race_pairs_each_method_with_cmaes_at_the_same_mark_and_refuses_bad_settings(tmp_path):
    from spacegrasp_jax.benchmarks import race

    flags = {
        "paper": [1, 0, 0, 0, 1, 0],
        "shipped_flight": [1, 1, 1, 0, 1, 0],
        "cmaes_5min": [1, 1, 0, 0, 0, 0],
        "gradient_fresh_5min": [1, 1, 1, 1, 1, 0],
    }
    np.savez(tmp_path / "samples.npz", **{f"admittance/{key}/success": np.array(v, bool) for key, v in flags.items()})
    table = race.summarise(tmp_path / "samples.npz", ["cmaes", "gradient_fresh"])
    assert table["gradient_fresh_5min"]["success"]["successes"] == 5
    versus = table["gradient_fresh_5min"]["vs_cmaes_same_mark"]
    assert (versus["only_candidate"], versus["only_reference"], versus["both"]) == (3, 0, 2)
    assert table["cmaes_5min"]["vs_shipped"]["only_reference"] == 2 and "vs_cmaes_same_mark" not in table["cmaes_5min"]
    # A method raced later, on the same captures: paired with the first race's gain sets.
    added = {"shipped_flight": flags["shipped_flight"], "gradient_fresh_truncated_5min": [0, 1, 1, 1, 1, 1]}
    (tmp_path / "added").mkdir()
    np.savez(
        tmp_path / "added" / "samples.npz", **{f"admittance/{k}/success": np.array(v, bool) for k, v in added.items()}
    )
    table = race.summarise(tmp_path / "added" / "samples.npz", ["gradient_fresh_truncated"], tmp_path / "samples.npz")
    row = table["gradient_fresh_truncated_5min"]
    assert (row["vs_cmaes_same_mark"]["only_candidate"], row["vs_cmaes_same_mark"]["only_reference"]) == (4, 1)
    assert (
        row["vs_gradient_fresh_same_mark"]["only_candidate"],
        row["vs_gradient_fresh_same_mark"]["only_reference"],
    ) == (
        1,
        1,
    )
    added["shipped_flight"] = [0, 1, 1, 0, 1, 0]  # other captures
    np.savez(
        tmp_path / "added" / "samples.npz", **{f"admittance/{k}/success": np.array(v, bool) for k, v in added.items()}
    )
    with pytest.raises(ValueError, match="not the same captures"):
        race.summarise(tmp_path / "added" / "samples.npz", ["gradient_fresh_truncated"], tmp_path / "samples.npz")
    for argv in (
        ["--methods", "nope"],
        ["--minutes", "15", "--marks", "20"],
        ["--marks", "x"],
        ["--heldout", "0"],
        ["--against", str(tmp_path / "nowhere")],
    ):
        with pytest.raises(SystemExit) as refused:
            race.main([*argv, "--out", str(tmp_path / "race")])
        assert refused.value.code == 2, argv
    assert not (tmp_path / "race").exists()


def test_the_race_over_seeds_pairs_each_run_with_the_reference_on_its_seed_and_refuses_bad_settings(tmp_path):
    from spacegrasp_jax.benchmarks import race_seeds
    from spacegrasp_jax.envelope import statistics

    flags = {"shipped_flight": [1, 1, 1, 0, 1, 0]}
    for seed, (ours, theirs) in enumerate(
        [([1, 1, 1, 1, 1, 0], [1, 0, 0, 0, 1, 0]), ([1, 1, 0, 1, 1, 1], [1, 1, 0, 1, 1, 0])]
    ):
        flags[f"gradient_fresh_seed{seed}_10min"] = ours
        flags[f"cmaes_fresh_seed{seed}_10min"] = theirs
    np.savez(tmp_path / "samples.npz", **{f"admittance/{key}/success": np.array(v, bool) for key, v in flags.items()})
    summary = race_seeds.summarise(
        tmp_path / "samples.npz", ["gradient_fresh", "cmaes_fresh"], [0, 1], [10.0], "gradient_fresh"
    )
    versus = summary["runs"]["cmaes_fresh_seed0_10min"]["vs_gradient_fresh"]
    assert (versus["only_reference"], versus["only_candidate"]) == (3, 0)
    assert "vs_gradient_fresh" not in summary["runs"]["gradient_fresh_seed1_10min"]
    entry = summary["methods"]["cmaes_fresh"]["10"]
    assert entry["success"]["values"] == [2 / 6, 4 / 6]
    # paired by seed: cmaes - gradient = -3/6 on seed 0, -1/6 on seed 1
    np.testing.assert_allclose(entry["difference_to_gradient_fresh"]["values"], [-3 / 6, -1 / 6])
    assert entry["difference_to_gradient_fresh"]["iqm"] == statistics.interquartile_mean([-3 / 6, -1 / 6])
    assert summary["shipped_flight"]["successes"] == 4
    for argv in (
        ["--methods", "nope"],
        ["--methods", "cmaes_fresh", "--reference", "gradient_fresh"],
        ["--seeds", "0,0"],
        ["--seeds", "x"],
        ["--minutes", "15", "--marks", "20"],
        ["--range", "lar_position_m"],
        ["--gradient-steps-per-minute", "0"],
    ):
        with pytest.raises(SystemExit) as refused:
            race_seeds.main([*argv, "--out", str(tmp_path / "race")])
        assert refused.value.code == 2, argv
    assert not (tmp_path / "race").exists()


def test_the_race_report_gives_a_race_over_seeds_run_by_run_and_across_seeds(tmp_path, capsys):
    import json

    from spacegrasp_jax.benchmarks import race_seeds, tuning

    folder = tmp_path / "races" / "race_seeds_constant"
    (folder / "heldout").mkdir(parents=True)
    flags = {"shipped_flight": [1, 1, 1, 0, 1, 0, 1, 1]}
    runs = {}
    for seed, (ours, theirs) in enumerate(
        [([1, 1, 1, 1, 1, 0, 1, 1], [1, 0, 0, 0, 1, 0, 1, 1]), ([1, 1, 0, 1, 1, 1, 1, 1], [1, 1, 0, 1, 1, 0, 0, 1])]
    ):
        for method, hits in (("gradient_fresh", ours), ("cmaes_fresh", theirs)):
            flags[f"{method}_seed{seed}_15min"] = hits
            used = {"gradients": 32 * 90} if method == "gradient_fresh" else {"rollouts": 16 * 32 * 60}
            runs[f"{method}_seed{seed}"] = {"snapshots": {"15": {"path": "x", "steps": 90, **used}}}
    samples = folder / "heldout" / "samples.npz"
    np.savez(samples, **{f"admittance/{key}/success": np.array(v, bool) for key, v in flags.items()})
    summary = race_seeds.summarise(samples, ["gradient_fresh", "cmaes_fresh"], [0, 1], [15.0], "gradient_fresh")
    settings = {"schedule": None, "ranges": ["lar_position_m=0.01"], "heldout_seed": 730001}
    (folder / "race.json").write_text(json.dumps({"settings": settings, "runs": runs, "summary": summary}))
    assert tuning.main(["--races", str(tmp_path / "races"), "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "races.json").read_text())
    row = next(r for r in report["rows"] if r["method"] == "cmaes_fresh" and r["training_seed"] == 0)
    assert row["problem"] == "constant gains, lar_position_m=0.01" and row["success"]["successes"] == 4
    assert (row["versus"]["only_reference"], row["versus"]["only_candidate"]) == (3, 0)
    across = next(r for r in report["across_seeds"] if r["method"] == "cmaes_fresh")
    np.testing.assert_allclose(across["difference_to_reference"]["values"], [-3 / 8, -2 / 8])
    printed = capsys.readouterr().out
    assert "| constant gains, lar_position_m=0.01 | 15 | cmaes_fresh | 56.2% [50.0, 62.5] | 2 |" in printed
    assert "-31.2 points [-37.5, -25.0] against gradient_fresh |" in printed


def test_the_race_report_reads_each_mark_off_the_committed_campaigns_and_the_runs(tmp_path, capsys):
    """``benchmarks.tuning --races``: every row's success and McNemar counts recounted from the
    held-out campaign's per-sample flags, its steps from the run's history."""
    import csv
    import json
    from pathlib import Path

    from spacegrasp_jax.benchmarks import tuning
    from spacegrasp_jax.jobs.campaign import load_samples

    data = Path(__file__).parent.parent / "notebooks" / "data"
    assert tuning.main(["--races", str(data), "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "races.json").read_text())
    assert {row["race"] for row in report["rows"]} >= {"race", "race_seed1", "race_seed2", "race_schedule_time"}
    for row in report["rows"]:
        _, by_variant = load_samples(data / row["race"] / "heldout" / "samples.npz")
        flags = {key.split("/", 1)[1]: np.asarray(value["success"], bool) for key, value in by_variant.items()}
        if "versus" in row:  # a race over seeds: each run named by its seed, paired with the reference's
            mark = f"seed{row['training_seed']}_{row['minutes']:g}min"
            hits = flags[f"{row['method']}_{mark}"]
            assert (row["success"]["successes"], row["success"]["samples"]) == (hits.sum(), hits.size)
            if row["versus"] is not None:
                reference = flags[f"{row['versus']['method']}_{mark}"]
                assert (row["versus"]["only_candidate"], row["versus"]["only_reference"]) == (
                    (hits & ~reference).sum(),
                    (reference & ~hits).sum(),
                )
            counted = row["gradients"] if row["method"].startswith("gradient") else row["rollouts"]
            assert counted % 32 == 0
            history = data / row["race"] / f"seed{row['training_seed']}" / row["method"] / "history.csv"
            with open(history, newline="") as file:
                assert 0 < row["steps"] <= len(list(csv.DictReader(file))) - 1
            continue
        hits = flags[f"{row['method']}_{row['minutes']:g}min"]
        assert (row["success"]["successes"], row["success"]["samples"]) == (hits.sum(), hits.size)
        if row["paired_with"] is not None:  # a method raced later on the same captures
            _, by_variant = load_samples(data / row["paired_with"] / "heldout" / "samples.npz")
            flags |= {key.split("/", 1)[1]: np.asarray(value["success"], bool) for key, value in by_variant.items()}
        if row["method"] != "cmaes":
            cmaes = flags[f"cmaes_{row['minutes']:g}min"]
            versus = row["vs_cmaes_same_mark"]
            assert (versus["only_candidate"], versus["only_reference"]) == (
                (hits & ~cmaes).sum(),
                (cmaes & ~hits).sum(),
            )
            assert row["gradients"] % 32 == 0 and row["rollouts"] is None
        with open(data / row["race"] / row["method"] / "history.csv", newline="") as file:
            steps_run = len(list(csv.DictReader(file))) - 1
        assert 0 < row["steps"] <= steps_run
    seed0 = {(row["method"], row["minutes"]): row for row in report["rows"] if row["race"] == "race"}
    assert seed0[("gradient_fresh", 15.0)]["steps"] == 75  # the run's whole schedule, done by 15 minutes
    verdict = next(v for v in report["verdicts"] if v["problem"] == "constant gains" and v["minutes"] == 10.0)
    assert verdict["seeds"] == [0, 1, 2] and verdict["won_on"] == [0, 1, 2]
    assert "| constant gains | 1 | 10 | gradient_fresh | 94.8% [93.2, 96.0] |" in capsys.readouterr().out
    with pytest.raises(SystemExit) as refused:
        tuning.main(["--races", str(tmp_path / "none"), "--out", str(tmp_path)])
    assert refused.value.code == 2
