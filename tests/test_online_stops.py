"""Stops that name their cause (issue 54): limits and reach tested before the estimate is blamed, the following
check's noise floor and rotation part, densely sampled paths, an actuator too narrow to self-identify, and the
resumed session's `moved` test in both phases. The fake arm of tests/helpers_online.py; the virtual UR5e for the
redundant and 6-D cases (slow)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from helpers_online import START, FakeArm, arm_pose, assert_in_envelope, opts  # tests/ is on the path

from selfid_jax.robot import live, options, safety
from selfid_jax.robot.journal import floats, read_journal
from selfid_jax.robot.session import NOISE_READS, STALL_MOVES

NAMES = ("yaw", "shoulder", "elbow")


def _records(run, e):
    return [r for r in read_journal(run / "session.jsonl").records if r["e"] == e]


# --------------------------------------------------------------------------- pure parts


def test_tracker_noise_is_the_pooled_sample_deviation():
    rng = np.random.default_rng(0)
    p, r = rng.normal(0.0, 2e-4, (400, 3)) + [0.3, 0.1, 0.2], rng.normal(0.0, 1e-3, (400, 3))
    sp, sr = safety.tracker_noise(p, r)
    np.testing.assert_allclose(sp, np.sqrt(np.mean(np.var(p, axis=0, ddof=1))), rtol=1e-12)
    np.testing.assert_allclose(sr, np.sqrt(np.mean(np.var(r, axis=0, ddof=1))), rtol=1e-12)
    assert abs(sp / 2e-4 - 1) < 0.1 and abs(sr / 1e-3 - 1) < 0.1


def test_linear_reach_names_the_first_waypoint_beyond_twice_the_room():
    Jinv = np.array([[2.0, 0.0], [0.0, -1.0], [1.0, 1.0]])  # (n=3, m=2)
    q, lo, hi = np.zeros(3), np.full(3, -1.0), np.array([1.0, 1.0, 0.3])
    offsets = np.array([[0.1, 0.1], [0.2, 0.2], [0.4, 0.3]])  # actuator 2 needs 0.2, 0.4 (> 2 x 0.3), 0.7
    assert safety.linear_reach(Jinv, offsets, q, lo, hi) == (2, 2, pytest.approx(0.7))
    assert safety.linear_reach(Jinv, offsets[:2], q, lo, hi) is None
    assert safety.linear_reach(Jinv, -offsets, q, lo, hi) is None  # 0.7 down, with 1.0 of room below


# --------------------------------------------------------------------------- item 2: what cannot be identified


def test_an_actuator_narrower_than_m_a_is_refused_before_any_motion(tmp_path):
    lower, upper = [-3.0, START[1] - 0.01, -3.0], [3.0, START[1] + 0.01, 3.0]
    fake = FakeArm(joint_names=NAMES)
    with pytest.raises(ValueError, match=r"joint 2 \(shoulder\) has a range of 0\.02 .* m_a = 0\.03"):
        live.run_online(fake, opts(lower=lower, upper=upper), tmp_path / "r")
    assert fake.moves == [] and fake.closed and not (tmp_path / "r").exists()
    fake = FakeArm(lower=lower, upper=upper)  # the driver's own limits: the same refusal, joints counted from 1
    with pytest.raises(ValueError, match=r"joint 2 has a range of 0\.02"):
        live.run_online(fake, opts(), tmp_path / "d")
    assert fake.moves == []
    fake = FakeArm(lower=lower, upper=upper)  # a range of exactly m_a is enough
    assert live.run_online(fake, opts(m_a=0.02), tmp_path / "ok").status == live.Stop.CONVERGED


def test_resumed_self_id_with_wander_none_and_the_arm_pushed_stops_as_moved(tmp_path):
    """wander None has no centre to test: the actuators against where the log left them (its last reading and
    the last target), by m_a; named by the driver's names, 1-based."""
    fake = FakeArm(fail_move_at=4)
    assert live.run_online(fake, opts(wander=None), tmp_path / "a").status == live.Stop.CONNECTION
    left = floats(_records(tmp_path / "a", "obs")[-1]["q"])
    np.testing.assert_array_equal(left, fake.q)
    pushed = FakeArm(q0=left + [0.0, 0.0, 0.6], joint_names=NAMES)
    res = live.run_online(pushed, opts(wander=None), tmp_path / "a", resume=True)
    assert res.status == live.Stop.MOVED and pushed.moves == [], res.detail
    assert f"joint 3 (elbow) is +0.6 from where the log left it (it was at {left[2]:.4g}" in res.detail
    there = FakeArm(q0=left + [0.0, 0.0, 0.02])  # within m_a of it: self-ID goes on
    assert live.run_online(there, opts(wander=None), tmp_path / "a", resume=True).status == live.Stop.CONVERGED


@pytest.fixture(scope="module")
def cut_following(tmp_path_factory, converged_run):
    """converged_run resumed with a star, the connection lost at the 4th following move."""
    run, ref_fake, _ = converged_run
    cut = tmp_path_factory.mktemp("stops") / "cut"
    shutil.copytree(run, cut)
    fake = FakeArm(q0=ref_fake.q, fail_move_at=3)
    res = live.run_online(fake, opts(path=options.FollowOptions(size=0.02)), cut, resume=True)
    assert res.status == live.Stop.CONNECTION and res.follow_steps == 4, res.detail
    return cut, fake


@pytest.mark.parametrize("push", [[0.05, 0.0, 0.0], [0.0, -0.04, 0.0]])
def test_resumed_following_with_the_arm_pushed_stops_as_moved(tmp_path, cut_following, push):
    """A push that keeps the point within diverge_dist (50 mm) of the path, but moves a joint by more than m_a
    from where the log left it: moved, no move; the hint names the estimate this run directory has."""
    cut, fake = cut_following
    shutil.copytree(cut, tmp_path / "r")
    q = fake.q + push
    assert np.linalg.norm(arm_pose(q)[0] - arm_pose(fake.q)[0]) < 0.05
    pushed = FakeArm(q0=q)
    res = live.run_online(pushed, opts(path=options.FollowOptions(size=0.02)), tmp_path / "r", resume=True)
    i = int(np.flatnonzero(push)[0])
    assert res.status == live.Stop.MOVED and pushed.moves == [], res.detail
    assert f"joint {i + 1} is {push[i]:+.4g} from where the log left it" in res.detail
    assert f"--estimate {tmp_path / 'r' / 'inverse_jacobian.npz'}" in res.detail
    back = FakeArm(q0=fake.q)  # where the log left it: following goes on to the end
    res = live.run_online(back, opts(path=options.FollowOptions(size=0.02)), tmp_path / "r", resume=True)
    assert res.status == live.Stop.COMPLETED, res.detail


def test_a_given_estimate_session_is_pointed_at_its_own_file(tmp_path, converged_run):
    """Following with --estimate FILE, cut, resumed with the arm moved: the hint names FILE, not a file the run
    directory does not have."""
    _, ref_fake, ref = converged_run
    est = tmp_path / "given.npz"
    np.savez(est, inverse_jacobian=ref.estimate, task_axes=np.array(["x", "y", "z"]))
    o = opts(path=options.FollowOptions(size=0.02), estimate=str(est))
    fake = FakeArm(q0=ref_fake.q, fail_move_at=3)
    assert live.run_online(fake, o, tmp_path / "g").status == live.Stop.CONNECTION
    pushed = FakeArm(q0=fake.q + [0.05, 0.0, 0.0])
    res = live.run_online(pushed, o, tmp_path / "g", resume=True)
    assert res.status == live.Stop.MOVED and pushed.moves == [], res.detail
    assert f"--estimate {est})" in res.detail and "g/inverse_jacobian.npz" not in res.detail


# --------------------------------------------------------------------------- item 1: stops that name their cause


def _tightest(ref, q, size=0.02):
    """The joint the star needs most (the estimate's linear step), its direction and how far it needs to go."""
    need = options.FollowOptions(size=size).offsets((0, 1, 2)) @ ref.estimate.T  # (W, n)
    w, i = np.unravel_index(np.argmax(np.abs(need)), need.shape)
    return int(i), bool(need[w, i] > 0), float(abs(need[w, i]))


def _limited(q, i, up, room):
    lower, upper = np.full(3, -3.0), np.full(3, 3.0)
    (upper if up else lower)[i] = q[i] + (room if up else -room)
    return lower.tolist(), upper.tolist()


def _follow_with_room(tmp_path, converged_run, fraction):
    """Resume a copy of the converged run to follow a 20 mm star with the user's limit leaving the joint the star
    needs most ``fraction`` of the room it needs: ``(joint, up, lower, upper, arm, result)``."""
    run, ref_fake, ref = converged_run
    shutil.copytree(run, tmp_path / "r")
    i, up, need = _tightest(ref, ref_fake.q)
    lower, upper = _limited(ref_fake.q, i, up, fraction * need)
    fake = FakeArm(q0=ref_fake.q, joint_names=NAMES)
    res = live.run_online(fake, opts(path=options.FollowOptions(size=0.02), lower=lower, upper=upper),
                          tmp_path / "r", resume=True)
    return i, up, lower, upper, fake, res


def test_a_joint_held_at_the_users_limit_stops_as_unreachable_naming_it(tmp_path, converged_run):
    """The user's limit leaves the joint the star needs most 60 % of the way (within twice the room, so following
    starts): the joint is held there, the waypoint comes no nearer, and the session stops after STALL_MOVES such
    moves naming the joint and whose limit, every target inside the envelope."""
    i, up, lower, upper, fake, res = _follow_with_room(tmp_path, converged_run, 0.6)
    assert res.status == live.Stop.UNREACHABLE, res.detail
    side, value = ("upper", upper[i]) if up else ("lower", lower[i])
    assert f"{_label(i)} is held at its {side} limit {value:.4g} (the user's safety.limits_{side})" in res.detail
    assert STALL_MOVES < res.follow_steps < 80
    assert_in_envelope(fake, np.maximum(fake.lim.lower, lower), np.minimum(fake.lim.upper, upper), 0.2)
    targets = np.array([t for _, t in fake.moves])
    assert np.sum(targets[:, i] == value) >= STALL_MOVES  # held there, as the message says
    noise = _records(tmp_path / "r", "noise")
    assert len(noise) == 1 and noise[0]["reads"] == NOISE_READS


def _label(i):
    return f"joint {i + 1} ({NAMES[i]})"


def test_a_waypoint_far_beyond_the_limits_is_refused_before_following(tmp_path, converged_run):
    """The same joint with a fifth of the room it needs: refused before any following move, naming it."""
    i, up, _, _, fake, res = _follow_with_room(tmp_path, converged_run, 0.2)
    assert res.status == live.Stop.UNREACHABLE and fake.moves == [], res.detail
    side = "upper" if up else "lower"
    assert "No following move was made" in res.detail and f"estimate moves {_label(i)} from" in res.detail
    assert f"{side} limit" in res.detail and f"the user's safety.limits_{side}" in res.detail


@pytest.mark.parametrize("swap", [None, [0, 2, 1]])
def test_clipped_moves_are_samples_of_the_following_check(tmp_path, converged_run, swap):
    """A 20 mm waypoint followed with a given estimate, the user's limit leaving the joint it needs most 51 % of
    the room (so its moves are clipped from the third on): the correct estimate stops naming the limit; the
    estimate with its y and z columns swapped is blamed (estimate), from moves most of which were clipped (fewer
    than follow_min_moves were not: the clipped ones are counted as samples)."""
    _, ref_fake, ref = converged_run
    est = ref.estimate if swap is None else ref.estimate[:, swap]
    path = options.FollowOptions(kind="waypoints", waypoints=[[0.02, 0.0, 0.0]])
    need = est @ [0.02, 0.0, 0.0]  # (n,) the estimate's linear step to the waypoint
    i = int(np.argmax(np.abs(need)))
    lower, upper = _limited(ref_fake.q, i, bool(need[i] > 0), 0.51 * abs(need[i]))
    fake = FakeArm(q0=ref_fake.q, joint_names=NAMES)
    res = live.run_online(fake, opts(path=path, estimate=est, lower=lower, upper=upper), tmp_path / "r")
    limit = upper[i] if need[i] > 0 else lower[i]
    held = sum(1 for _, t in fake.moves if t[i] == limit)  # moves whose command the limit clipped
    assert held >= 3, (held, res.detail)
    assert_in_envelope(fake, np.maximum(fake.lim.lower, lower), np.minimum(fake.lim.upper, upper), 0.2)
    if swap is None:
        side = "upper" if need[i] > 0 else "lower"
        assert res.status == live.Stop.UNREACHABLE, res.detail
        assert f"{_label(i)} is held at its {side} limit {limit:.4g} (the user's safety.limits_{side})" in res.detail
    else:
        assert res.status == live.Stop.ESTIMATE, res.detail
        assert res.follow_steps - held < opts().follow_min_moves


@pytest.mark.slow  # the follow step compiled for 400 waypoints: ~7 s on 2 loaded cores
def test_densely_sampled_path_is_followed_through_tracker_noise(tmp_path, converged_run):
    """400 waypoints 0.1 mm apart (40 mm) with 0.1 mm of tracker noise: waypoints already within tol are passed
    (each logged), moves are not single 0.1 mm steps lost in the noise, and the path completes at its end."""
    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    wps = [[0.0, 1e-4 * k, 0.0] for k in range(400)]
    fake = FakeArm(q0=ref_fake.q, jitter=1e-4)
    path = options.FollowOptions(kind="waypoints", waypoints=wps)
    res = live.run_online(fake, opts(path=path), tmp_path / "r", resume=True)
    assert res.status == live.Stop.COMPLETED and res.waypoints == 400, res.detail
    assert res.follow_steps < 100
    reached = [r["reached"] for r in _records(tmp_path / "r", "waypoint")]
    assert reached == list(range(400))
    (noise,) = _records(tmp_path / "r", "noise")
    assert 0.5e-4 < noise["position"] < 2e-4  # the jitter, measured at rest
    anchor = np.array(_records(tmp_path / "r", "follow")[0]["p"])
    assert np.linalg.norm(arm_pose(fake.q)[0] - (anchor + wps[-1])) < 0.002 + 5e-4


# --------------------------------------------------------------------------- the virtual UR5e


@pytest.mark.slow  # two self-IDs of the virtual UR5e in real time (6-D: 30 samples), ~30 s on 2 loaded cores
def test_ur5e_rotation_only_waypoint_and_pinned_redundant_joint(tmp_path):
    """On a redundant arm the estimate's pinv does not predict the motion of a clipped command: a joint held at
    the user's limit is not blamed on the estimate; a rotation-only waypoint on a 6-D task is followed."""
    from selfid_jax.control.realism import Realism
    from selfid_jax.robot.virtual import VirtualRobot, build_system
    from selfid_jax.systems.ur5e import UR5E_HOME

    real = Realism(period=0.002, noise_pos=1e-4, noise_rot=1e-4)
    fast = dict(settle_s=0.008, poll_s=0.001, seed=1, max_samples=150)
    robot = VirtualRobot(build_system("ur5e_6d"), realism=real, seed=1)
    path = options.FollowOptions(kind="waypoints", waypoints=[[0, 0, 0, 0, 0, 0.3]], steps=100)
    res = live.run_online(robot, opts(task="x,y,z,rx,ry,rz", path=path, **fast), tmp_path / "rot")
    assert res.status == live.Stop.COMPLETED and res.follow_steps < 40, res.detail
    # the same with the user's limits +-0.045 around the start and a 40 mm star: refused or stopped naming a limit
    home = np.array(UR5E_HOME)
    robot = VirtualRobot(build_system("ur5e"), realism=real, seed=1)
    res = live.run_online(robot, opts(path=options.FollowOptions(size=0.04), lower=(home - 0.045).tolist(),
                                      upper=(home + 0.045).tolist(), **fast), tmp_path / "lim")
    assert res.status == live.Stop.UNREACHABLE and "the user's safety.limits_" in res.detail, res.detail
