"""The tracking experiment at small size on the 2-link arm: letters with the truth and the estimate, and its
per-axis error columns against an independent numpy distance to the path on the recorded trajectories."""

import numpy as np
import pytest

from selfid_jax import runner as experiment
from selfid_jax.control import paths
from selfid_jax.runner.errors import ConfigError

pytestmark = [pytest.mark.slow,  # an end-to-end experiment
              pytest.mark.xdist_group("tracking")]  # one worker builds the module's `result` once, not each worker

CONFIG = dict(system="two_link", path={"kind": "text", "text": "E", "height": 0.12},
              controller={"max_step": 0.005, "tol": 0.001, "steps": 300}, n_configs=3, iters=20, m_a=0.02, eps=0.05,
              pose_noise=[0.0, 0.0005], rot_noise=[0.0, 0.0])


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    exp = experiment.get("tracking")
    return experiment.run(exp, exp.config(**CONFIG), tmp_path_factory.mktemp("trk"))


def numpy_axis_errors(points, vertices, samples=4001):
    t = np.linspace(0.0, 1.0, samples)[:, None]
    dense = np.concatenate([a + t * (b - a) for a, b in zip(vertices[:-1], vertices[1:])])
    idx = np.argmin(((points[:, None, :] - dense[None]) ** 2).sum(-1), axis=1)
    return np.abs(points - dense[idx])


def test_truth_is_sub_tolerance_and_estimate_completes(result):
    table, summary = result
    truth = table[table.inverse == "analytical"]
    assert np.all(truth.completion == 1.0) and np.all(truth.waypoint_error_mm < 1.0)  # tol 1 mm
    est = table[table.inverse == "estimated"]
    assert est.completion.mean() >= 0.9 and np.all(est.converged_at > 0)
    clean = summary["systems"]["two_link"]["pose_noise_mm"]["0"]
    assert set(clean) == {"estimated", "analytical"}
    assert {"waypoint_error_mm", "error_x_mm", "error_y_mm", "error_z_mm", "completion", "converged_at"} <= set(
        clean["estimated"])


def test_axis_error_columns_equal_numpy_on_the_recorded_trajectories(result):
    table, _ = result
    offsets = np.asarray(paths.text("E", height=0.12, dim=2))
    for _, row in table.iloc[:4].iterrows():
        pos = np.asarray(row.positions).reshape(-1, 3)[: int(row.steps_used) + 1, :2]
        vertices = np.vstack([pos[0], pos[0] + offsets])  # the path starts where the rollout starts
        want = 1e3 * numpy_axis_errors(pos, vertices).mean(axis=0)
        np.testing.assert_allclose([row.error_x_mm, row.error_y_mm], want, atol=0.02)  # mm; sampling resolution
        assert row.error_z_mm == 0.0


def test_bad_configs_name_the_key():
    exp = experiment.get("tracking")
    with pytest.raises(ValueError, match="controller.tol"):
        exp.config(**{**CONFIG, "controller": {"max_step": 0.005, "tol": 0.02, "steps": 300}})
    with pytest.raises(ValueError, match="pose_noise and rot_noise"):
        exp.config(**{**CONFIG, "rot_noise": [0.0]})
    assert issubclass(ConfigError, ValueError)


def test_a_hand_writes_a_letter(tmp_path):
    """The Stewart Hand (float64 part) writes a small 'L': the truth is sub-tolerance, the estimate completes.

    50 control steps: both finish the letter in 25 (the loop scans the whole budget, each step a closed-chain
    solve, so a budget far above that only adds run time)."""
    exp = experiment.get("tracking")
    cfg = exp.config(system="stewart_hand", path={"kind": "letters", "text": "L", "height": 0.003},
                     controller={"max_step": 0.0002, "tol": 0.0001, "steps": 50, "max_rot_step": 0.01,
                                 "rot_tol": 0.005}, n_configs=1, iters=15, m_a=0.0005, eps=0.0, eps_rel=0.02)
    table, summary = experiment.run(exp, cfg, tmp_path)
    truth, est = (table[table.inverse == k].iloc[0] for k in ("analytical", "estimated"))
    assert truth.completion == 1.0 and truth.waypoint_error_mm < 0.1
    assert est.completion >= 0.9 and est.converged_at > 0
    assert "0:L" in summary["systems"]["stewart_hand"]["letters"]


def test_figures_are_drawn_from_the_saved_table(result, tmp_path):
    table, summary = result
    written = experiment.get("tracking").plot(table, summary, tmp_path)
    assert [p.name for p in written] == ["tracking_two_link.png", "tracking_two_link.pdf"]
    assert all(p.stat().st_size > 1000 for p in written)


def test_rotation_task_on_chosen_axes(tmp_path):
    """The UR5e rotates its flange 0.2 rad about world x and y on a rotation-only task ([rx, ry, rz]): the truth
    ends within rot_tol of the goal, the estimate completes, per-step traces are recorded and summarised per axis."""
    exp = experiment.get("tracking")
    cfg = exp.config(system="ur5e_6d", task_axes=["rx", "ry", "rz"],
                     path={"kind": "rotation", "angle": 0.2, "about": ["x", "y"], "rotation_steps": 4},
                     controller={"steps": 60, "max_rot_step": 0.02, "rot_tol": 0.004}, n_configs=1, iters=20,
                     m_a=0.03, eps=0.5)
    table, summary = experiment.run(exp, cfg, tmp_path)
    truth, est = table[table.inverse == "analytical"], table[table.inverse == "estimated"]
    assert np.all(truth.completion == 1.0) and np.all(truth.rot_final_deg <= np.degrees(0.004))
    assert np.all(est.completion >= 0.9)
    assert np.all(table[["error_x_mm", "error_y_mm", "error_z_mm"]].to_numpy() == 0.0)  # no position in the task
    for _, row in truth.iterrows():
        trace = np.asarray(row.rot_trace_deg)[: int(row.steps_used) + 1]
        assert trace[0] == pytest.approx(np.degrees(0.05), rel=1e-6)  # first waypoint: 0.2 / 4 rad away
        assert row.rot_step_deg == pytest.approx(trace.mean(), rel=1e-9)
    assert set(summary["systems"]["ur5e_6d"]["rotations"]) == {"0:rx", "1:ry"}
    with pytest.raises(ValueError, match="task_axes must include"):
        exp.config(**{**cfg.model_dump(), "task_axes": ["rz"]})
    with pytest.raises(ValueError, match="does not control"):
        exp.build(exp.config(system="two_link", path={"kind": "cube", "edge": 0.1}, n_configs=1, m_a=0.02))
