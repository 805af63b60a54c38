"""``spacegrasp benchmark --quick`` runs every part (ours, MuJoCo, the Pinocchio loop) so the
benchmark never rots. No assertion on time: only that every figure is there and sane, and
that the Pinocchio peer simulated the same closed loop as ours."""

from __future__ import annotations

import json
import math
import subprocess
import sys

from benchmarks.suite import KEYS


def test_quick_benchmark_writes_every_key(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "spacegrasp_jax.cli", "benchmark", "--quick", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=900,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((tmp_path / "benchmark.json").read_text())
    assert set(KEYS) <= set(report), set(KEYS) - set(report)
    assert set(report["rollout_s"]) == {"active", "cartesian"}
    assert set(report["batch_steps_per_s"]) == {"1", "4"}
    assert set(report["gradient_over_forward"]) == {"reverse", "forward"}
    numbers = [
        *report["rollout_s"].values(), *report["compile_s"].values(), *report["batch_steps_per_s"].values(),
        *report["gradient_over_forward"].values(), report["gradient_peak_mb"]["reverse"], report["flops_per_step"],
        report["pinocchio_loop_rollout_s"], report["mujoco_mj_step_17s_s"], report["mujoco_rollout_steps_per_s"],
    ]
    assert all(math.isfinite(x) and x > 0 for x in numbers), numbers
    assert report["pinocchio_loop_max_pose_difference"] < 1e-6
    assert "spacegrasp-jax" in result.stdout and "ratio" in result.stdout
    assert not any(tmp_path.glob("benchmark-*")), "intermediate files left behind"
