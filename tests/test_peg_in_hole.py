"""Peg-in-hole (Table III) at the smallest size: one layout, noise-free. The truth inserts within tolerance, the
self-ID estimates do too, the reported position error equals the distance recomputed from the recorded
positions and the last waypoint error equals it; bad layouts are rejected before any compute."""

import numpy as np
import pytest

from selfid_jax import runner as experiment

pytestmark = pytest.mark.slow  # compiles the UR5e + Model O pipeline (float64)

CONFIG = dict(
    layouts=[{"yaw": 0.1, "grasp": [0.03, 0.0, -0.03], "hole": [0.05, 0.02]}],
    arm={"iters": 20, "m_a": 0.03, "eps": 0.5, "controller": {"steps": 150}},
    hand={"iters": 12, "m_a": 0.0003, "eps_rel": 0.05,
          "controller": {"max_step": 0.0001, "tol": 0.00005, "steps": 60, "max_rot_step": 0.01, "rot_tol": 0.005}},
    rotation={"angle": 0.1, "about": "y", "steps": 5},
)


def test_inserts_and_reports_table_iii(tmp_path):
    exp = experiment.get("peg_in_hole")
    table, summary = experiment.run(exp, exp.config(**CONFIG), tmp_path)
    assert len(table) == 2 and not table.failed.any()
    truth, est = (table[table.inverse == k].iloc[0] for k in ("analytical", "estimated"))
    assert truth.inserted and truth.arm_pos_mm < 0.5 and truth.hand_rot_deg < np.degrees(0.005)
    assert est.inserted and est.arm_converged_at > 0 and est.hand_converged_at > 0
    for row in (truth, est):
        grasp, _, end = np.asarray(row.positions).reshape(3, 3)
        target = grasp + np.array([0.05, 0.02, 0.0])
        assert row.arm_pos_mm == pytest.approx(1e3 * np.linalg.norm(end - target), abs=1e-9)
        # noise-free, every waypoint is reached within the arm's 0.5 mm tolerance and the loop stops at the last
        wp = np.asarray(row.arm_wp_mm)
        assert wp.shape == (4,) and np.all((wp >= 0) & (wp < 0.5))
        assert wp[3] == pytest.approx(row.arm_pos_mm, abs=1e-9)
    assert ({"arm_pos_mm", "arm_wp_mm", "arm_rot_deg", "hand_rot_deg", "inserted"}
            <= set(summary["pose_noise_mm"]["0"]["estimated"]["all"]))
    pooled = summary["pose_noise_mm"]["0"]["estimated"]["all"]["arm_wp_mm"]
    assert pooled["mean"] == pytest.approx(np.mean(est.arm_wp_mm))
    assert pooled["sd"] == pytest.approx(np.std(est.arm_wp_mm))
    written = exp.plot(table, summary, tmp_path)
    assert [p.name for p in written] == ["peg_in_hole.png", "peg_in_hole.pdf"]


def test_bad_layouts_are_rejected():
    exp = experiment.get("peg_in_hole")
    with pytest.raises(ValueError, match="grasp"):
        exp.config(**{**CONFIG, "layouts": [{"yaw": 0.0, "grasp": [0.0, 0.0], "hole": [0.0, 0.0]}]})
    with pytest.raises(ValueError, match="insert_tol"):
        exp.config(**{**CONFIG, "insert_tol": 0.0004})
    with pytest.raises(ValueError, match="angle"):
        exp.config(**{**CONFIG, "rotation": {"angle": 0.5}})
