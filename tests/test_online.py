"""The online runner (selfid_jax.robot.live) against an in-process fake arm with injectable faults
(tests/helpers_online.py): self-ID, its session log (selfid_jax.robot.journal) and resume, and following. The
``selfid-jax online`` command: tests/test_online_cli.py; progress, figures, given paths and estimates:
tests/test_online_lab.py."""

from __future__ import annotations

import shutil
import time

import jax
import numpy as np
import pytest
from helpers_online import (  # tests/ is on the path
    L1,
    L2,
    START,
    FakeArm,
    H,
    accepted_samples,
    arm_pose,
    assert_in_envelope,
    opts,
    states_equal,
)

from selfid_jax.robot import live, options, safety
from selfid_jax.robot import offline as fit_mod
from selfid_jax.robot.journal import Journal, JournalError, read_journal

# --------------------------------------------------------------------------- self-ID


@pytest.mark.slow
def test_selfid_with_dropouts_matches_offline_fit(tmp_path):
    lower = (START[0] - 0.01, -3.0, -3.0)  # joint 0 has 1 cm of room below: draws there are reflected
    fake = FakeArm(lower=lower, dropouts={3, 5})  # reads 3 and 5 follow moves 2 and 3
    result = live.run_online(fake, opts(), tmp_path)
    assert result.status == live.Stop.CONVERGED and fake.closed
    assert result.rejected == {"dropout": 2}
    # exactly converged_at + rejected random moves, none after convergence
    assert len(fake.moves) == result.moves == result.converged_at + 2 == result.samples + 2
    recs = read_journal(result.log).records
    kinds = [r["e"] for r in recs]
    assert "move" not in kinds[kinds.index("converged"):]
    assert_in_envelope(fake, np.array(lower), fake.lim.upper, 0.03)
    assert not any(t[0] == lower[0] for _, t in fake.moves)  # reflected, not clipped onto the limit
    # the same samples offline give the same convergence iteration and estimate
    dtheta, V = accepted_samples(result.log)
    trace = fit_mod.fit_samples(dtheta, V, 0.0, 0.05, min_samples=15)  # the live default, 5 per axis
    assert int(trace.converged_at) == result.converged_at > 2
    np.testing.assert_allclose(result.estimate, np.asarray(trace.estimate), rtol=1e-10, atol=1e-12)
    # the samples are the arm's own: q differences and tracker position differences
    q0, t0 = fake.moves[0]
    np.testing.assert_allclose(dtheta[0], t0 - q0, atol=1e-15)
    assert np.all(result.step_ms > 0) and result.step_ms.shape == (result.samples,)


def test_actuation_target_reflects_then_clips():
    lower, upper, m_a = np.array([0.0, 0.0]), np.array([1.0, 0.02]), np.array([0.1, 0.1])
    for k in range(200):
        q = np.array([0.05 if k % 2 else 0.97, 0.01])
        target = safety.actuation_target(7, k, q, m_a, lower, upper)
        assert np.all(target >= lower) and np.all(target <= upper)
        d = np.random.default_rng([7, k]).uniform(-1, 1, 2) * m_a
        assert np.isclose(abs(target[0] - q[0]), abs(d[0]))  # one side fits: reflected, magnitude kept
        assert abs(target[1] - q[1]) <= abs(d[1]) + 1e-15  # neither side fits: clipped
    np.testing.assert_array_equal(safety.actuation_target(7, 5, q, m_a, lower, upper),
                                  safety.actuation_target(7, 5, q, m_a, lower, upper))


@pytest.mark.slow
def test_stale_tracker_stops_within_stale_s(tmp_path):
    fake = FakeArm(freeze_at=4)  # read 4 follows move 3: from then on the tracker stops advancing
    result = live.run_online(fake, opts(stale_s=0.15), tmp_path)
    assert result.status == live.Stop.STALE, result.detail
    assert result.rejected == {"stale": 1}
    assert len(fake.moves) == 3  # nothing commanded once the tracker froze
    assert fake.closed_at - fake.frozen_since <= 0.15 + 0.0 + 0.1  # stale_s + settle_s + slack


@pytest.mark.slow
def test_box_stops_without_further_motion(tmp_path):
    p0, _ = arm_pose(START)
    fake = FakeArm(noise=0.0)
    result = live.run_online(fake, opts(box_low=p0 - 0.002, box_high=p0 + 0.002), tmp_path / "a")
    assert result.status == live.Stop.BOX and len(fake.moves) == 1 and "outside the box" in result.detail
    fake = FakeArm()
    result = live.run_online(fake, opts(box_low=p0 + 0.01, box_high=p0 + 0.1), tmp_path / "b")
    assert result.status == live.Stop.BOX and fake.moves == []  # the start is outside: no motion at all


def test_bad_options_refused_before_any_motion(tmp_path):
    for bad, word in ((dict(m_a=0.3), "m_a"), (dict(m_a=[0.1, 0.1]), "m_a"), (dict(task="x,q"), "q"),
                      (dict(max_step=0.01), "m_a"), (dict(box_low=[0, 0], box_high=[1, 1, 1]), "box_low"),
                      (dict(method="slsqp"), "method"), (dict(stale_s=0.0), "stale_s"),
                      (dict(path=options.FollowOptions(plane="xz"), task="x,y"), "path.plane")):
        fake = FakeArm()
        with pytest.raises(ValueError, match=word):
            live.run_online(fake, opts(**bad), tmp_path / word)
        assert fake.moves == [] and fake.reads == 0 and fake.closed


@pytest.mark.slow
def test_interrupt_closes_and_keeps_the_log(tmp_path):
    fake = FakeArm(interrupt_at=2)
    result = live.run_online(fake, opts(), tmp_path / "kbd")
    assert result.status == live.Stop.INTERRUPTED and fake.closed and len(fake.moves) == 2
    assert read_journal(result.log).records[-1] == {"e": "stop", "reason": "interrupted",
                                                     "detail": "interrupted (KeyboardInterrupt)"}
    fake = FakeArm()
    result = live.run_online(fake, opts(), tmp_path / "req", stop_requested=lambda: len(fake.moves) >= 3)
    assert result.status == live.Stop.INTERRUPTED and len(fake.moves) == 3


# --------------------------------------------------------------------------- log and resume


@pytest.mark.slow
def test_connection_error_then_resume_equals_uninterrupted(tmp_path, converged_run):
    _, ref_fake, ref = converged_run
    assert ref.converged_at > 4
    fake = FakeArm(fail_move_at=3)
    cut = live.run_online(fake, opts(), tmp_path)
    assert cut.status == live.Stop.CONNECTION and fake.closed and cut.samples == 3
    contents = read_journal(cut.log)
    assert contents.records[-1]["reason"] == "connection" and contents.truncated == 0
    with open(cut.log, "ab") as f:  # a crash in the middle of the next line
        f.write(b'{"e":"obs","phase":"selfid","t":12.5,"q":[0.1,')
    again = FakeArm(q0=fake.q)
    result = live.run_online(again, opts(), tmp_path, resume=True)
    assert result.status == live.Stop.CONVERGED and result.truncated == 1 and result.replayed == 3
    assert states_equal(result.state, ref.state)
    assert result.converged_at == ref.converged_at
    assert result.moves == ref.moves + 1  # the command whose call raised is counted: it may have been sent
    assert len(again.moves) == len(ref_fake.moves) - 3
    np.testing.assert_array_equal(again.q, ref_fake.q)
    contents = read_journal(result.log)  # the cut line was removed before appending: the log reads cleanly
    assert contents.truncated == 0 and [r["e"] for r in contents.records].count("session") == 2


def test_resume_refuses_a_disagreeing_header(tmp_path, converged_run):
    run, _, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    for change, field in ((dict(m_a=0.02), "m_a"), (dict(seed=4), "seed"), (dict(task="x,y"), "m"),
                          (dict(eps_rel=0.1), "eps_rel")):
        fake = FakeArm()
        with pytest.raises(live.ResumeError, match=f"log's {field} is"):
            live.run_online(fake, opts(**change), tmp_path / "r", resume=True)
        assert fake.moves == [] and fake.closed
    with pytest.raises(live.ResumeError, match="already holds a session log"):
        live.run_online(FakeArm(), opts(), tmp_path / "r")
    with pytest.raises(live.ResumeError, match="no session log"):
        live.run_online(FakeArm(), opts(), tmp_path / "none", resume=True)


@pytest.mark.slow
def test_resume_with_the_robot_moved_stops_as_moved_before_any_move(tmp_path, converged_run):
    """Self-ID resumed with an actuator beyond (wander + 1) m_a of where self-ID started, and following resumed
    with the tracked point beyond diverge_dist of the logged path: a `moved` stop naming why, no command."""
    fake = FakeArm(fail_move_at=3)
    assert live.run_online(fake, opts(), tmp_path / "a").status == live.Stop.CONNECTION
    centre = np.array(read_journal(tmp_path / "a" / "session.jsonl").records[1]["q"])  # the centre record
    np.testing.assert_array_equal(centre, START)
    moved = FakeArm(q0=np.array(START) + [0.0, 0.061, 0.0])  # 2 m_a + 1 mm away in actuator 1
    res = live.run_online(moved, opts(), tmp_path / "a", resume=True)
    assert res.status == live.Stop.MOVED and "joint 2 is +0.061 from where self-ID started" in res.detail
    assert moved.moves == [] and moved.closed
    near = FakeArm(q0=np.array(START) + [0.0, 0.059, 0.0])  # within reach: self-ID continues and converges
    assert live.run_online(near, opts(), tmp_path / "a", resume=True).status == live.Stop.CONVERGED

    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    fake = FakeArm(q0=ref_fake.q, fail_move_at=2)  # following starts, then the connection drops
    path = options.FollowOptions(size=0.02)
    assert live.run_online(fake, opts(path=path), tmp_path / "r", resume=True).status == live.Stop.CONNECTION
    away = FakeArm(q0=np.array(ref_fake.q) + [0.2, 0.0, 0.0])
    res = live.run_online(away, opts(path=path), tmp_path / "r", resume=True)
    assert res.status == live.Stop.MOVED and "from the log's path" in res.detail and "--estimate" in res.detail
    assert away.moves == [] and away.closed


@pytest.mark.slow
def test_self_id_stays_within_wander_of_its_start(tmp_path):
    """Every self-ID target within wander m_a of the first reading (reflected draws keep |dtheta| <= m_a); with
    wander None the same draws walk farther."""
    for wander, bound in ((1.0, 0.03), (2.0, 0.06)):
        fake = FakeArm()
        live.run_online(fake, opts(wander=wander, max_samples=40, eps_rel=1e-9), tmp_path / f"w{wander}")
        targets = np.array([t for _, t in fake.moves])
        assert len(targets) == 40 and np.max(np.abs(targets - START)) <= bound + 1e-12
        assert np.all(np.abs(targets - np.array([q for q, _ in fake.moves])) <= 0.03 + 1e-12)
    free = FakeArm()
    live.run_online(free, opts(wander=None, max_samples=40, eps_rel=1e-9), tmp_path / "free")
    assert np.max(np.abs(np.array([t for _, t in free.moves]) - START)) > 0.06


@pytest.mark.slow
def test_convergence_counts_from_min_samples(tmp_path):
    """The default floor is 5 samples per task axis (15 for x,y,z); the estimator's test is the paper's after it:
    the same samples offline with min_samples give the same iteration, and 0 gives the paper's earlier one."""
    res = live.run_online(FakeArm(), opts(), tmp_path / "d")
    dtheta, V = accepted_samples(res.log)
    paper = int(fit_mod.fit_samples(dtheta, V, 0.0, 0.05).converged_at)
    assert 1 < paper < 15 <= res.converged_at
    assert int(fit_mod.fit_samples(dtheta, V, 0.0, 0.05, min_samples=15).converged_at) == res.converged_at
    res0 = live.run_online(FakeArm(), opts(min_samples=0), tmp_path / "p")
    assert res0.converged_at == paper
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="min_samples: expected an integer"):
            live.run_online(FakeArm(), opts(min_samples=bad), tmp_path / "bad")
    with pytest.raises(ValueError, match="wander: must be a number >= 0.5"):
        live.run_online(FakeArm(), opts(wander=0.1), tmp_path / "bad")


@pytest.mark.slow
def test_resume_with_another_path_after_following_started_is_refused(tmp_path, converged_run):
    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    fake = FakeArm(q0=ref_fake.q, fail_move_at=2)  # following starts, then the connection drops
    res = live.run_online(fake, opts(path=options.FollowOptions(size=0.02)), tmp_path / "r", resume=True)
    assert res.status == live.Stop.CONNECTION and res.follow_steps == 3
    for other in (options.FollowOptions(size=0.03), options.FollowOptions(size=0.02, plane="xz")):
        fake = FakeArm(q0=fake.q)
        with pytest.raises(live.ResumeError, match="path differs"):
            live.run_online(fake, opts(path=other), tmp_path / "r", resume=True)
        assert fake.moves == [] and fake.closed
    fake = FakeArm(q0=fake.q)  # the logged path itself continues
    res = live.run_online(fake, opts(path=options.FollowOptions(size=0.02)), tmp_path / "r", resume=True)
    assert res.status == live.Stop.COMPLETED, res.detail


def test_journal_tolerates_only_a_cut_last_line(tmp_path):
    path = tmp_path / "log.jsonl"
    with Journal(path) as j:
        j.append({"e": "header", "n": 2, "x": np.float64(np.nan)})
        j.append({"e": "obs", "q": np.array([1.0, 1 / 3])})
    c = read_journal(path)
    assert c.truncated == 0 and c.header["x"] is None and c.records[0]["q"] == [1.0, 1 / 3]
    path.write_bytes(path.read_bytes() + b'{"e":"ob')
    c = read_journal(path)
    assert c.truncated == 1 and len(c.records) == 1
    with Journal(path, good_bytes=c.good_bytes) as j:
        j.append({"e": "stop"})
    assert [r["e"] for r in read_journal(path).records] == ["obs", "stop"]
    lines = path.read_bytes().split(b"\n")
    path.write_bytes(b"\n".join([lines[0], b"garbage", *lines[1:]]))
    with pytest.raises(JournalError, match="line 2"):
        read_journal(path)


def test_a_driver_that_updates_its_arrays_in_place_is_copied(tmp_path):
    """The runner copies every reading: a driver reusing its arrays gives the very session a copying one gives."""
    ref = live.run_online(FakeArm(noise=0.0), opts(), tmp_path / "copying")
    res = live.run_online(FakeArm(noise=0.0, in_place=True), opts(), tmp_path / "in_place")
    assert ref.status == res.status == live.Stop.CONVERGED and res.converged_at == ref.converged_at
    np.testing.assert_array_equal(res.estimate, ref.estimate)


@pytest.mark.parametrize("valid", ["False", float("nan")])
def test_valid_must_be_a_real_bool(tmp_path, valid):
    fake = FakeArm(valid_as=valid)
    res = live.run_online(fake, opts(), tmp_path)
    assert res.status == live.Stop.ROBOT_ERROR and "valid=" in res.detail, res.detail
    assert fake.moves == [] and res.samples == 0 and fake.closed


@pytest.mark.parametrize("kw, kind", [(dict(fail_read_at=6), "TimeoutError"),
                                      (dict(fail_read_at=6, fail_read_with="OSError"), "OSError"),
                                      (dict(fail_move_at=3, fail_move_with="ValueError"), "ValueError")])
def test_any_driver_exception_is_a_logged_stop_and_a_closed_robot(tmp_path, kw, kind):
    fake = FakeArm(**kw)
    res = live.run_online(fake, opts(), tmp_path)
    assert res.status == live.Stop.DRIVER_ERROR and kind in res.detail and fake.closed, res.detail
    last = read_journal(res.log).records[-1]
    assert last["e"] == "stop" and last["reason"] == "driver_error" and last["kind"] == kind


def test_a_tracker_frozen_while_the_arm_moves_stops_self_id(tmp_path):
    """A pose re-sent unchanged with advancing stamps: stopped within 3 m_a of actuator motion, not learned."""
    fake = FakeArm(frozen_pose_at=4)
    res = live.run_online(fake, opts(), tmp_path)
    assert res.status == live.Stop.TRACKER_FROZEN and "does not see the arm move" in res.detail, res.detail
    moved = sum(np.max(np.abs(t - q)) for q, t in fake.moves[2:])
    assert len(fake.moves) <= 12 and moved <= 3 * 0.03 + 0.03 and fake.closed


@pytest.mark.slow
def test_a_tracker_frozen_while_following_stops_within_frozen_dist(tmp_path, converged_run):
    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    fake = FakeArm(q0=ref_fake.q, frozen_pose_at=3)
    res = live.run_online(fake, opts(path=options.FollowOptions(size=0.05)), tmp_path / "r", resume=True)
    assert res.status == live.Stop.TRACKER_FROZEN, res.detail
    unseen = np.linalg.norm(arm_pose(fake.q)[0] - arm_pose(fake.moves[1][0])[0])  # since the last pose seen
    assert 2 <= len(fake.moves) <= 3 and unseen < 0.005 + 0.005 + 5e-4  # frozen_dist and the move that passed it


@pytest.mark.parametrize("clock", [lambda t: t + 5.0, lambda t: time.time()])
def test_tracker_stamps_ahead_or_on_another_clock_stop_before_any_move(tmp_path, clock):
    fake = FakeArm(tracker_clock=clock)
    res = live.run_online(fake, opts(), tmp_path)
    assert res.status == live.Stop.CLOCK and "ahead of the driver's clock" in res.detail and fake.moves == []


def test_samples_whose_motion_is_not_explained_stop_before_following(tmp_path, converged_run):
    """A tracker one move late (latency beyond settle_s): the samples' held-out error stops the session at
    convergence, before any following move; the shipped fake arm's own samples pass the check."""
    _, _, ref = converged_run
    assert ref.quality is not None and ref.quality.heldout_error < 0.1 and np.all(ref.quality.effect > 0.005)
    fake = FakeArm(pose_lag=True)
    res = live.run_online(fake, opts(path=options.FollowOptions(size=0.02), max_samples=200), tmp_path)
    assert res.status == live.Stop.ESTIMATE and "held-out error" in res.detail, res.detail
    assert res.follow_steps == 0 and res.quality is not None and res.quality.heldout_error > 0.5


@pytest.mark.slow
def test_staleness_counts_the_transport_delay(tmp_path):
    """A reading stamped 0.6 s before it arrives is stale at stale_s 0.5, though its two stamps agree."""
    fake = FakeArm(delay_at=4, delay_s=0.6)
    res = live.run_online(fake, opts(stale_s=0.5), tmp_path)
    assert res.status == live.Stop.STALE and len(fake.moves) <= 3, res.detail


@pytest.mark.parametrize("kw", [dict(stuck=1), dict(slow=2)])
def test_an_actuator_that_does_not_follow_its_commands_stops_self_id(tmp_path, kw):
    """A stuck joint and a joint 10x slower: stopped naming the actuator, before Sec. IV-D could accept a wrong fit."""
    fake = FakeArm(**kw)
    res = live.run_online(fake, opts(), tmp_path)
    i = next(iter(kw.values()))
    assert res.status == live.Stop.ACTUATOR and f"joint {i + 1} moved" in res.detail, res.detail
    assert len(fake.moves) == 5 and not res.converged


@pytest.mark.slow
def test_a_stick_slip_band_that_swallows_small_commands_is_not_a_stuck_actuator(tmp_path, converged_run):
    """Joint 2 ignores steps under 1.5 mrad (a stick-slip band): following completes, as on franky-sim's FR3; the
    shortfall stays under half of m_a. A joint that ignores every command still stops (the test above)."""
    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    fake = FakeArm(q0=ref_fake.q, band=(2, 0.0015))
    path = options.FollowOptions(size=0.02, max_task_step=0.001, steps=400)
    res = live.run_online(fake, opts(path=path), tmp_path / "r", resume=True)
    assert res.status == live.Stop.COMPLETED, res.detail
    small = [abs(t[2] - q[2]) for q, t in fake.moves]
    assert sum(s < 0.0015 for s in small) >= 5  # the band did swallow commands


# --------------------------------------------------------------------------- following


@pytest.mark.slow
def test_follow_after_resume_completes_within_the_envelope(tmp_path, converged_run):
    run, ref_fake, ref = converged_run
    shutil.copytree(run, tmp_path / "r")
    fake = FakeArm(q0=ref_fake.q, max_step=0.05)
    path = options.FollowOptions(size=0.02, tol=0.001, max_task_step=0.004, gain=0.7, steps=400)
    result = live.run_online(fake, opts(path=path, max_step=0.03), tmp_path / "r", resume=True)
    assert result.status == live.Stop.COMPLETED, result.detail
    assert result.waypoints == result.waypoints_total == 10 and result.replayed == ref.samples
    assert result.moves == ref.moves and result.follow_steps == len(fake.moves) <= 400  # no random move
    assert_in_envelope(fake, fake.lim.lower, fake.lim.upper, 0.03)
    p_end, _ = arm_pose(fake.q)
    np.testing.assert_allclose(p_end, arm_pose(ref_fake.q)[0], atol=0.0015)  # the star closes where it began


def _arm_system():
    """The fake arm's tip position as a System (its pose map in JAX), limits as FakeArm's default."""
    import jax.numpy as jnp

    from selfid_jax.systems.system import from_pose_fn

    def pose(params, q):
        a, b = q[1], q[1] + q[2]
        r = L1 * jnp.cos(a) + L2 * jnp.cos(b)
        return jnp.stack([r * jnp.cos(q[0]), r * jnp.sin(q[0]), H + L1 * jnp.sin(a) + L2 * jnp.sin(b)])

    return from_pose_fn(pose, 3, task_dim=3, q_low=-3.0, q_high=3.0, dq_max=10.0, m_a=0.03, name="fake_arm")


@pytest.mark.slow
def test_simulated_follow_commands_what_the_live_runner_commands(tmp_path, converged_run):
    """One follow law: control.follow on a model of the arm, with FollowOptions.controller(envelope), moves the arm
    to the very targets the live runner commands the (noise-free) fake arm, step by step, to float64 round-off;
    the per-actuator cap binds on some steps (it is part of the law, in both)."""
    from selfid_jax import control

    run, ref_fake, ref = converged_run
    shutil.copytree(run, tmp_path / "r")
    fake = FakeArm(q0=ref_fake.q, noise=0.0, max_step=0.05)
    path = options.FollowOptions(size=0.03, tol=0.001, max_task_step=0.015, gain=0.9, steps=400)
    result = live.run_online(fake, opts(path=path, max_step=0.03), tmp_path / "r", resume=True)
    assert result.status == live.Stop.COMPLETED, result.detail
    env = safety.envelope(fake.lim, max_step=0.03)
    targets = np.array([t for _, t in fake.moves])
    capped = np.max(np.abs(np.diff(np.vstack([ref_fake.q, targets]), axis=0)) / env.max_step, axis=1)
    assert np.sum(capped > 1 - 1e-9) >= 3  # the cap scaled some steps down
    system = _arm_system()
    with jax.enable_x64(True):
        sim = control.follow(system, control.fixed(np.asarray(result.estimate, np.float64)), path.offsets((0, 1, 2)),
                             np.asarray(ref_fake.q, np.float64), path.controller(env), steps=path.steps,
                             return_trajectory=True)
        sim = jax.device_get(sim)
    k = len(fake.moves)
    assert int(sim.steps_used) == k == result.follow_steps and float(sim.completion) == 1.0 and not sim.failed
    np.testing.assert_allclose(sim.final_q, targets[-1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(sim.positions[1:k + 1], np.array([arm_pose(t)[0] for t in targets]), rtol=0,
                               atol=1e-12)
    # each waypoint reached at the same step: live, the number of following moves made before its log record
    moves, live_steps = 0, []
    for rec in read_journal(result.log).records:
        moves += rec["e"] == "move" and rec["phase"] == "follow"
        if rec["e"] == "waypoint":
            live_steps.append(moves)
    sim_steps = [int(np.argmax(sim.targets > w)) for w in range(len(live_steps))]
    assert live_steps == sim_steps and len(live_steps) == 10


@pytest.mark.slow
def test_an_estimate_that_no_longer_predicts_the_motion_stops_following(tmp_path, converged_run):
    """Each following move is a held-out sample: with the Jacobian flipped after self-ID (a changed grasp) the
    predicted motion misses the tracked one and the session stops at the 5th move, before any divergence stop."""
    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "e")
    fake = FakeArm(q0=ref_fake.q, mirror=True)
    res = live.run_online(fake, opts(path=options.FollowOptions(size=0.05), diverge_dist=0.5), tmp_path / "e",
                          resume=True)
    assert res.status == live.Stop.ESTIMATE and "no longer moves as it was self-identified" in res.detail, res.detail
    assert len(fake.moves) == 5


@pytest.mark.slow
def test_follow_divergence_and_box_stop(tmp_path, converged_run):
    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "d")
    fake = FakeArm(q0=ref_fake.q, mirror=True)  # the arm's Jacobian flipped after self-ID: the estimate is wrong
    result = live.run_online(fake, opts(path=options.FollowOptions(size=0.05), diverge_dist=0.01),
                               tmp_path / "d", resume=True)
    assert result.status == live.Stop.DIVERGENCE and 0 < len(fake.moves) < 20, result.detail
    recs = read_journal(result.log).records
    assert recs[-1]["reason"] == "divergence"
    shutil.copytree(run, tmp_path / "b")
    p, _ = arm_pose(ref_fake.q)
    fake = FakeArm(q0=ref_fake.q)
    result = live.run_online(fake, opts(path=options.FollowOptions(size=0.05), box_low=p - [1, 0.05, 1],
                                          box_high=p + 1), tmp_path / "b", resume=True)
    assert result.status == live.Stop.BOX and "path leaves the box" in result.detail and fake.moves == []
