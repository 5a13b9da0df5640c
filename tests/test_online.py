"""The online runner (selfid_jax.robot.live) against an in-process fake arm with injectable faults, its session
log (selfid_jax.robot.journal), and the ``selfid-jax online`` command."""

from __future__ import annotations

import json
import shutil
import sys
import textwrap
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from selfid_jax.math import geometry
from selfid_jax.robot import live, options, safety, session, steps
from selfid_jax.robot import offline as fit_mod
from selfid_jax.robot.journal import Journal, JournalError, floats, read_journal
from selfid_jax.robot.protocol import Observation, Robot, RobotConnectionError, RobotLimits

START = np.array([0.3, 0.6, -0.9])  # rad: yaw, shoulder, elbow; away from the arm's singularities
L1, L2, H = 0.4, 0.3, 0.1  # m
FAST = dict(settle_s=0.0, poll_s=0.001)


def arm_pose(q):
    """Position (3,) m and quaternion (w, x, y, z) of the tip of a yaw-pitch-pitch arm (numpy)."""
    a, b = q[1], q[1] + q[2]
    r = L1 * np.cos(a) + L2 * np.cos(b)
    p = np.array([r * np.cos(q[0]), r * np.sin(q[0]), H + L1 * np.sin(a) + L2 * np.sin(b)])
    cz, sz, cy, sy = np.cos(q[0] / 2), np.sin(q[0] / 2), np.cos(-b / 2), np.sin(-b / 2)
    return p, np.array([cz * cy, -sz * sy, cz * sy, sz * cy])  # Rz(q0) Ry(-b)


VENDOR_ERRORS = {"TimeoutError": TimeoutError, "ValueError": ValueError, "OSError": OSError}


class FakeArm:
    """A protocol driver around :func:`arm_pose`, with faults; records every command it is given.

    ``dropouts``: 1-based read numbers with no pose. ``freeze_at``: from this
    read on the tracker_t and pose stop advancing. ``fail_move_at``: 0-based move index raising
    RobotConnectionError (the move is not made); ``interrupt_at``: the same with KeyboardInterrupt.
    ``mirror``: the kinematics are mirrored about the start (the Jacobian's sign flips: a grasp that changed).
    ``fail_read_at`` / ``fail_move_with``: a vendor's own exception (not a RobotError) from that read / that move.
    ``valid_as``: ``valid`` reported as this (e.g. the string "False"). ``in_place``: read returns the same arrays
    every time, updated in place. ``frozen_pose_at``: from this read on the pose stays put while its stamp
    advances. ``tracker_clock``: the tracker's stamp as a function of the driver's time. ``stuck`` / ``slow``:
    an actuator that does not move / covers a tenth of each command. ``delay_at``: from this read on each reading
    arrives ``delay_s`` after it was stamped (a slow transport). ``pose_lag``: the tracker shows the arm one move
    late (its latency longer than the settle time).
    """

    def __init__(self, q0=START, *, lower=(-3.0, -3.0, -3.0), upper=(3.0, 3.0, 3.0), max_step=0.2, dropouts=(),
                 freeze_at=None, fail_move_at=None, interrupt_at=None, mirror=False, noise=1e-5, fail_move_with=None,
                 fail_read_at=None, fail_read_with="TimeoutError", valid_as=None, in_place=False,
                 frozen_pose_at=None, tracker_clock=None, stuck=None, slow=None, delay_at=None, delay_s=0.0,
                 pose_lag=False, no_quaternion=False, band=None):
        self.no_quaternion, self.band = no_quaternion, band
        self.pose_lag, self._q_before = pose_lag, None
        self.frozen_pose_at, self.tracker_clock, self.stuck, self.slow = frozen_pose_at, tracker_clock, stuck, slow
        self.delay_at, self.delay_s = delay_at, delay_s
        self.fail_move_with, self.fail_read_at, self.fail_read_with = fail_move_with, fail_read_at, fail_read_with
        self.valid_as, self.in_place = valid_as, in_place
        self._buffers = (np.zeros(3), np.zeros(3), np.zeros(4))  # in_place: one set of arrays, updated each read
        self.q = np.array(q0, np.float64)
        self.lim = RobotLimits(np.array(lower, np.float64), np.array(upper, np.float64), np.full(3, max_step))
        self.dropouts, self.freeze_at = set(dropouts), freeze_at
        self.fail_move_at, self.interrupt_at = fail_move_at, interrupt_at
        self.centre = self.q.copy() if mirror else None
        self.noise = noise
        self.moves: list[tuple[np.ndarray, np.ndarray]] = []  # (q before, target)
        self.reads = 0
        self.closed = self.closed_at = self.frozen_since = None
        self._t = self._tt = -np.inf
        self._pose = None
        self._lost = None

    def limits(self):
        return self.lim

    def read(self):
        obs = self._read()
        if self.delay_at is not None and self.reads >= self.delay_at:  # the reply is delayed in transport
            time.sleep(self.delay_s)
        if self.no_quaternion:  # a position-only tracker
            obs = obs._replace(quaternion=None)
        if self.valid_as is not None:  # a driver that reports validity as something other than a bool
            obs = obs._replace(valid=self.valid_as)
        if self.in_place:  # a driver that hands out its own arrays and updates them on the next read
            for buf, new in zip(self._buffers, (obs.q, obs.position, obs.quaternion)):
                buf[:] = new
            obs = obs._replace(q=self._buffers[0], position=self._buffers[1], quaternion=self._buffers[2])
        return obs

    def _read(self):
        self.reads += 1
        if self.reads == self.fail_read_at:
            raise VENDOR_ERRORS[self.fail_read_with]("fake: the vendor library failed")
        t = self._t = max(time.monotonic(), self._t + 1e-9)
        qk = self.q if self.centre is None else 2 * self.centre - self.q
        if self.pose_lag and self._q_before is not None:  # the tracker shows the arm as it was one move ago
            qk = self._q_before
        p, quat = arm_pose(qk)
        p = p + self.noise * np.sin(1e3 * self.q.sum() + np.arange(3))  # deterministic "noise": a function of q
        if self.freeze_at is not None and self.reads >= self.freeze_at:
            self.frozen_since = self.frozen_since or time.monotonic()
            return Observation(t, self.q.copy(), *self._pose, self._tt, True)
        if self.reads in self.dropouts:  # the marker was lost 1 ms before this read; tracker_t stays there
            self._lost = self._lost if self._lost is not None else t - 1e-3
            return Observation(t, self.q.copy(), np.full(3, np.nan), np.full(4, np.nan), self._lost, False)
        if self.frozen_pose_at is not None and self.reads >= self.frozen_pose_at:  # the pose freezes, stamps go on
            self._frozen = getattr(self, "_frozen", None) or self._pose or (p, quat)
            p, quat = self._frozen
        tt = t if self.tracker_clock is None else self.tracker_clock(t)
        self._tt, self._pose, self._lost = tt, (p, quat), None
        return Observation(t, self.q.copy(), p, quat, tt, True)

    def move(self, target):
        if len(self.moves) == self.fail_move_at:
            if self.fail_move_with is not None:
                raise VENDOR_ERRORS[self.fail_move_with]("fake: the vendor library refused the move")
            raise RobotConnectionError("fake: connection reset")
        if len(self.moves) == self.interrupt_at:
            raise KeyboardInterrupt
        self.moves.append((self.q.copy(), np.array(target, np.float64)))
        self._q_before = self.q.copy()
        q = np.array(target, np.float64)
        if self.stuck is not None:  # a joint that does not move, whatever it is told
            q[self.stuck] = self.q[self.stuck]
        if self.slow is not None:  # a joint that covers a tenth of each command before the reading
            q[self.slow] = self.q[self.slow] + 0.1 * (q[self.slow] - self.q[self.slow])
        if self.band is not None:  # a stick-slip band: a step under band[1] does not move joint band[0]
            i, width = self.band
            if abs(q[i] - self.q[i]) < width:
                q[i] = self.q[i]
        self.q = q

    def close(self):
        self.closed, self.closed_at = True, time.monotonic()


def opts(**kw):
    base = dict(task="x,y,z", m_a=0.03, eps=0.0, eps_rel=0.05, max_samples=60, seed=3, **FAST)
    return options.OnlineOptions(**{**base, **kw})


def assert_in_envelope(fake, env_lower, env_upper, max_step):
    for q, target in fake.moves:
        assert np.all(target >= env_lower) and np.all(target <= env_upper)
        assert np.all(np.abs(target - q) <= max_step + 1e-12)


def accepted_samples(log_path):
    recs = [r for r in read_journal(log_path).records if r["e"] == "sample" and r["accepted"]]
    return np.array([floats(r["dtheta"]) for r in recs]), np.array([floats(r["V"]) for r in recs])


def states_equal(a, b):
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


@pytest.fixture(scope="module")
def converged_run(tmp_path_factory):
    """One uninterrupted session to convergence (no path): the reference for resume and follow tests."""
    run = tmp_path_factory.mktemp("online") / "ref"
    fake = FakeArm()
    result = live.run_online(fake, opts(), run)
    assert result.status == live.Stop.CONVERGED, result.detail
    return run, fake, result


# --------------------------------------------------------------------------- self-ID


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


def test_stale_tracker_stops_within_stale_s(tmp_path):
    fake = FakeArm(freeze_at=4)  # read 4 follows move 3: from then on the tracker stops advancing
    result = live.run_online(fake, opts(stale_s=0.15), tmp_path)
    assert result.status == live.Stop.STALE, result.detail
    assert result.rejected == {"stale": 1}
    assert len(fake.moves) == 3  # nothing commanded once the tracker froze
    assert fake.closed_at - fake.frozen_since <= 0.15 + 0.0 + 0.1  # stale_s + settle_s + slack


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


def test_resume_with_the_robot_moved_stops_as_moved_before_any_move(tmp_path, converged_run):
    """Self-ID resumed with an actuator beyond (wander + 1) m_a of where self-ID started, and following resumed
    with the tracked point beyond diverge_dist of the logged path: a `moved` stop naming why, no command."""
    fake = FakeArm(fail_move_at=3)
    assert live.run_online(fake, opts(), tmp_path / "a").status == live.Stop.CONNECTION
    centre = np.array(read_journal(tmp_path / "a" / "session.jsonl").records[1]["q"])  # the centre record
    np.testing.assert_array_equal(centre, START)
    moved = FakeArm(q0=np.array(START) + [0.0, 0.061, 0.0])  # 2 m_a + 1 mm away in actuator 1
    res = live.run_online(moved, opts(), tmp_path / "a", resume=True)
    assert res.status == live.Stop.MOVED and "actuator 1 is +0.061 from where self-ID started" in res.detail
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
    assert res.status == live.Stop.ACTUATOR and f"actuator {i} moved" in res.detail, res.detail
    assert len(fake.moves) == 5 and not res.converged


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


# --------------------------------------------------------------------------- the command


DRIVER = '''
import numpy as np
CREATED = []

def make(**kw):
    from test_online import FakeArm
    arm = FakeArm(**{k: np.array(v) if isinstance(v, list) else v for k, v in kw.items()})
    CREATED.append(arm)
    return arm
'''


@pytest.fixture
def driver_module(tmp_path, monkeypatch):
    (tmp_path / "fake_driver.py").write_text(DRIVER)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    sys.modules.pop("fake_driver", None)
    import fake_driver

    yield fake_driver
    sys.modules.pop("fake_driver", None)


def _config(tmp_path, body):
    path = tmp_path / "online.yaml"
    path.write_text(textwrap.dedent(body))
    return path


def test_cli_runs_resumes_and_writes_the_estimate(tmp_path, driver_module, capsys):
    from selfid_jax.cli import main

    cfg = _config(tmp_path, """
        robot: {driver: "fake_driver:make", args: {noise: 0.0}}
        selfid: {task: "x,y,z", m_a: 0.03, eps_rel: 0.05, max_samples: 40, seed: 3, settle_s: 0.0, poll_s: 0.001}
        safety: {stale_s: 1.0, max_step: 0.1}
    """)
    out = tmp_path / "run"
    assert main(["online", str(cfg), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "converged" and summary["converged_at"] > 2
    assert summary["moves"] == len(driver_module.CREATED[0].moves)
    with np.load(out / "inverse_jacobian.npz") as z:
        assert z["inverse_jacobian"].shape == (3, 3) and int(z["converged_at"]) == summary["converged_at"]
    assert json.loads((out / "inverse_jacobian.json").read_text())["task_axes"] == ["x", "y", "z"]
    assert main(["online", str(cfg), "--out", str(out)]) == 2  # a log is there: --resume or another --out
    assert "--resume" in capsys.readouterr().err
    assert main(["online", str(cfg), "--out", str(out), "--resume"]) == 0
    assert driver_module.CREATED[-1].moves == []  # converged already: no random move on resume
    assert main(["online", str(cfg), "--out", str(out), "--resume", "--set", "selfid.seed=5"]) == 2
    assert "seed" in capsys.readouterr().err


def test_cli_driver_exception_exits_3_and_writes_no_estimate(tmp_path, driver_module, capsys):
    """A vendor's ValueError mid-session: exit 3 (the robot's class, not 2), a summary, no estimate file."""
    from selfid_jax.cli import main

    cfg = _config(tmp_path, """
        robot: {driver: "fake_driver:make", args: {fail_move_at: 3, fail_move_with: ValueError}}
        selfid: {task: "x,y,z", m_a: 0.03, eps_rel: 0.05, max_samples: 40, seed: 3, settle_s: 0.0, poll_s: 0.001}
    """)
    out = tmp_path / "run"
    assert main(["online", str(cfg), "--out", str(out)]) == 3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "driver_error" and not summary["converged"] and summary["samples"] == 3
    assert np.shape(summary["estimate_so_far"]) == (3, 3)
    assert not (out / "inverse_jacobian.npz").exists() and not (out / "inverse_jacobian.json").exists()
    assert "not converged: no inverse Jacobian written" in capsys.readouterr().out
    assert driver_module.CREATED[-1].closed


@pytest.mark.parametrize("body, key", [
    ("robot: {driver: 'fake_driver:make'}\nselfid: {m_a: 0.03, bogus: 1}\n", "selfid.bogus"),
    ("robot: {driver: 'fake_driver:make'}\nsafety: {stale_s: -1}\n", "safety.stale_s"),
    ("robot: {driver: 'fake_driver:make', host: h, port: 1}\n", "robot"),
    ("selfid: {m_a: 0.03}\n", "robot"),
    ("robot: {driver: 'fake_driver:make'}\nselfid: {task: 'x,w'}\n", "selfid.task"),
    ("robot: {driver: 'fake_driver:make'}\nselfid: {task: 'x,y'}\npath: {plane: xz}\n", "path.plane"),
    ("robot: {driver: 'fake_driver:make'}\nsafety: {limits_lower: [0, 0]}\n", "safety.limits_lower"),
    ("robot: {driver: 'no_such_module:make'}\n", "robot.driver"),
])
def test_cli_bad_config_exits_2_naming_the_key(tmp_path, driver_module, capsys, body, key):
    from selfid_jax.cli import main

    assert main(["online", str(_config(tmp_path, body)), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert key in err, err
    assert all(arm.moves == [] for arm in driver_module.CREATED)
    if key != "safety.limits_lower":  # that one needs the robot's n: checked after connecting, before motion
        assert driver_module.CREATED == []


def test_robot_protocol_fake_is_a_robot():
    assert isinstance(FakeArm(), Robot)


def test_example_config_validates():
    from selfid_jax.commands.online import OnlineConfig, options
    from selfid_jax.runner.config import read_config, validate

    path = Path(__file__).resolve().parents[1] / "configs" / "robot" / "online_ur5e.yaml"
    cfg = validate(OnlineConfig, read_config(path)[0], path)
    opts = options(cfg)
    assert cfg.robot.host == "127.0.0.1" and opts.path is not None and opts.path.size == 0.02
    assert opts.path.offsets((0, 1, 2)).shape == (10, 3)


def test_task_difference_is_the_pose_change_with_rotation():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    r0, w = Rotation.from_rotvec(rng.normal(size=3)), rng.normal(scale=0.1, size=3)
    r1 = Rotation.from_rotvec(w) * r0  # log(R1 R0^T) = w, world frame
    wxyz = [np.roll(r.as_quat(), 1) for r in (r0, r1)]
    p0, p1 = rng.normal(size=3), rng.normal(size=3)
    a = Observation(0.0, np.zeros(1), p0, wxyz[0], 0.0, True)
    b = Observation(1.0, np.zeros(1), p1, -wxyz[1], 1.0, True)  # the quaternion's sign does not matter
    np.testing.assert_allclose(steps.task_difference(b, a, (0, 2, 3, 5)), [*(p1 - p0)[[0, 2]], w[0], w[2]],
                               atol=1e-12)
    with jax.enable_x64(True):
        R1 = np.asarray(geometry.quaternion_to_rotation(np.asarray(-wxyz[1])))
    np.testing.assert_allclose(R1, r1.as_matrix(), atol=1e-12)


def _start_online(console, cfg, out, driver_dir, record: bytes, count: int):
    """``selfid-jax online CFG --out OUT`` in a process of its own (the fake driver importable from ``driver_dir``),
    returned once its session log holds ``count`` lines with ``record`` (or it ended, or 60 s passed)."""
    import os
    import subprocess

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(driver_dir), str(Path(__file__).parent),
                                                        os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([*console, "online", str(cfg), "--out", str(out)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    log = out / live.LOG_FILE
    deadline = time.monotonic() + 60
    while proc.poll() is None and time.monotonic() < deadline and \
            not (log.exists() and log.read_bytes().count(record) >= count):
        time.sleep(0.02)
    return proc, log


@pytest.mark.slow
@pytest.mark.parametrize("signame", ["SIGTERM", "SIGINT"])
def test_cli_sigterm_or_ctrl_c_stops_cleanly_and_resumes(tmp_path, driver_module, console, signame):
    """A first SIGTERM or Ctrl-C stops after the move in flight, closes the robot and keeps the log (not os._exit)."""
    import signal

    cfg = _config(tmp_path, """
        robot: {driver: "fake_driver:make"}
        selfid: {m_a: 0.03, eps_rel: 1.0e-15, max_samples: 100000, settle_s: 0.01, poll_s: 0.001}
    """)  # a threshold below float64 round-off: never converges, so only the signal ends it
    out = tmp_path / "run"
    proc, log = _start_online(console, cfg, out, tmp_path, b'"e":"sample"', 5)
    proc.send_signal(getattr(signal, signame))
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    last = read_journal(log).records[-1]
    assert last == {"e": "stop", "reason": "interrupted", "detail": "stop requested"}
    assert json.loads((out / "summary.json").read_text())["status"] == "interrupted"
    assert "stopped: interrupted" in stdout
    # the session continues in-process from its log: 3 more random moves, then max_samples
    from selfid_jax.cli import main

    done = sum(1 for r in read_journal(log).records if r["e"] == "sample")
    assert main(["online", str(cfg), "--out", str(out), "--resume", "--set", f"selfid.max_samples={done + 3}"]) == 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "max_samples" and summary["replayed"] == summary["samples"] - 3 >= 5
    assert len(driver_module.CREATED[-1].moves) == 3


@pytest.mark.slow
def test_cli_two_sigterms_50_ms_apart_still_leave_a_stop_record(tmp_path, driver_module, console):
    """The second signal ends the process at once (143); the log still ends with a stop record (killed)."""
    import signal

    cfg = _config(tmp_path, """
        robot: {driver: "fake_driver:make"}
        selfid: {m_a: 0.03, eps_rel: 1.0e-15, max_samples: 100000, settle_s: 0.4, poll_s: 0.001}
    """)  # a long settle: the first signal's stop is seen only after it, so the second one ends the process
    out = tmp_path / "run"
    proc, log = _start_online(console, cfg, out, tmp_path, b'"e":"move"', 2)
    proc.send_signal(signal.SIGTERM)
    time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=60)
    assert proc.returncode == 143
    last = read_journal(log).records[-1]
    assert last["e"] == "stop" and last["reason"] == "killed", last


def test_the_step_compiles_once_per_shape(tmp_path, converged_run):
    before = steps._step._cache_size()
    for i, (eps, eps_rel) in enumerate(((0.0, 0.2), (1e-3, 0.0), (0.1, 0.3))):
        result = live.run_online(FakeArm(), opts(eps=eps, eps_rel=eps_rel, max_samples=4), tmp_path / str(i))
        assert result.samples >= 2
    assert steps._step._cache_size() == before  # new thresholds, same (n, m, method, dtype): no retrace


def test_cli_and_api_give_the_same_defaults_for_every_online_option():
    """`selfid-jax online` with an empty config section runs exactly run_online's defaults (one source each)."""
    import inspect

    from selfid_jax.commands.online import OnlineConfig
    from selfid_jax.commands.online import options as cli_options

    cfg = OnlineConfig(robot={"host": "127.0.0.1", "port": 50007}, path={})
    assert cli_options(cfg) == options.OnlineOptions(path=options.FollowOptions())
    for name, p in inspect.signature(safety.envelope).parameters.items():
        if p.default is not inspect.Parameter.empty and name in options.OnlineOptions._fields:
            assert p.default == options.OnlineOptions._field_defaults[name], name


def test_a_position_only_tracker_serves_a_position_task_and_is_refused_for_rotation(tmp_path):
    res = live.run_online(FakeArm(no_quaternion=True), opts(), tmp_path / "p")
    assert res.status == live.Stop.CONVERGED, res.detail
    fake = FakeArm(no_quaternion=True)
    res = live.run_online(fake, opts(task="x,y,rz"), tmp_path / "r")
    assert res.status == live.Stop.ROBOT_ERROR and "quaternion None" in res.detail and fake.moves == []


def test_scalar_limits_broadcast_beside_a_vector_and_are_refused_alone():
    from selfid_jax.robot.protocol import check_limits

    lim = check_limits(RobotLimits(np.full(3, -3.0), 3.0, 0.2))
    assert [x.shape for x in lim] == [(3,)] * 3 and np.all(lim.upper == 3.0) and np.all(lim.max_step == 0.2)
    with pytest.raises(ValueError, match="all single numbers"):
        check_limits(RobotLimits(-3.0, 3.0, 0.2))
    with pytest.raises(ValueError, match="different lengths"):
        check_limits(RobotLimits(np.full(3, -3.0), np.full(2, 3.0), 0.2))


@pytest.mark.parametrize("where", ["config_folder", "cwd"])
def test_a_driver_module_beside_the_config_or_in_the_current_directory_is_found(tmp_path, monkeypatch, where):
    from selfid_jax.cli import main

    monkeypatch.syspath_prepend(str(Path(__file__).parent))  # the driver wraps this file's FakeArm
    name = f"lab_driver_{where}"
    folder = tmp_path / "lab"
    folder.mkdir()
    (folder / f"{name}.py").write_text("from test_online import FakeArm\n\ndef make(**kw):\n    return FakeArm(**kw)\n")
    cfg_dir = folder if where == "config_folder" else tmp_path / "configs"
    cfg_dir.mkdir(exist_ok=True)
    if where == "cwd":
        monkeypatch.chdir(folder)
    cfg = cfg_dir / "online.yaml"
    cfg.write_text(f"robot: {{driver: '{name}:make'}}\n"
                   "selfid: {m_a: 0.03, max_samples: 40, seed: 3, settle_s: 0.0, poll_s: 0.001}\n")
    monkeypatch.delitem(sys.modules, name, raising=False)
    assert main(["online", str(cfg), "--out", str(tmp_path / "run")]) == 0
    assert name not in " ".join(sys.path)  # looked there for the import only


# --------------------------------------------------------------------------- a loop a lab can watch (issue 42, item 3)


def test_progress_events_arrive_in_order_and_match_the_log(tmp_path):
    events = []
    fake = FakeArm(dropouts=(6,))
    path = options.FollowOptions(size=0.02, tol=0.001, max_task_step=0.004, gain=0.7, steps=400)
    result = live.run_online(fake, opts(path=path, max_step=0.03, m_a=0.02), tmp_path / "run", progress=events.append)
    assert result.status == live.Stop.COMPLETED, result.detail
    phases = [e["phase"] for e in events]
    n_sel, n_fol = phases.count("selfid"), phases.count("follow")
    assert phases == ["selfid"] * n_sel + ["follow"] * n_fol + ["stop"]  # in order, one stop, last
    sel, fol = events[:n_sel], events[n_sel:-1]
    assert n_sel == result.moves and [e["move"] for e in sel] == list(range(1, n_sel + 1))
    accepted = [e for e in sel if e["accepted"]]
    assert len(accepted) == result.samples and [e["sample"] for e in accepted] == list(range(1, result.samples + 1))
    assert [e["reason"] for e in sel if not e["accepted"]] == ["dropout"] * result.rejected["dropout"]
    logged = [r for r in read_journal(result.log).records if r["e"] == "sample" and r["accepted"]]
    assert [e["delta"] for e in accepted] == [r["delta"] for r in logged]
    assert [e["threshold"] for e in accepted] == [r["threshold"] for r in logged]
    assert accepted[-1]["converged_at"] == result.converged_at and accepted[-2]["converged_at"] < 1
    assert [e["step"] for e in fol] == list(range(1, result.follow_steps + 1))
    assert all(e["waypoints"] == 10 for e in fol) and fol[-1]["waypoint"] == 10
    assert [e["waypoint"] for e in fol] == sorted(e["waypoint"] for e in fol)
    assert events[-1] == {"phase": "stop", "status": "completed", "detail": result.detail}
    # the tracking error and wall times of the result: the events' path distances, each logged
    d = np.array([e["distance"] for e in fol])
    np.testing.assert_array_equal(result.track, d)
    assert [r["distance"] for r in read_journal(result.log).records if r["e"] == "track"] == d.tolist()
    assert 0 < d.max() < 0.01 and result.selfid_s > 0 and result.follow_s > 0


def test_tracking_error_and_wall_times_add_up_over_a_resume(tmp_path, converged_run):
    run, ref_fake, ref = converged_run
    shutil.copytree(run, tmp_path / "r")
    path = options.FollowOptions(size=0.02, tol=0.001, max_task_step=0.004, gain=0.7, steps=400)
    fake = FakeArm(q0=ref_fake.q, max_step=0.05, fail_move_at=5)
    first = live.run_online(fake, opts(path=path, max_step=0.03), tmp_path / "r", resume=True)
    assert first.status == live.Stop.CONNECTION and first.track.size == 5
    stops = [r for r in read_journal(first.log).records if r["e"] == "times"]  # one per session, before its stop
    assert len(stops) == 2 and all("selfid_s" in r and "follow_s" in r for r in stops)
    fake = FakeArm(q0=fake.q, max_step=0.05)
    second = live.run_online(fake, opts(path=path, max_step=0.03), tmp_path / "r", resume=True)
    assert second.status == live.Stop.COMPLETED, second.detail
    # one distance per move read back: the move the connection lost has none
    assert second.track.size == second.follow_steps - 1 and np.array_equal(second.track[:5], first.track)
    assert second.selfid_s == pytest.approx(sum(r["selfid_s"] for r in stops), rel=0.5)  # no self-ID since
    assert second.follow_s > first.follow_s


def _follow_config(tmp_path):
    return _config(tmp_path, """
        robot: {driver: "fake_driver:make", args: {noise: 0.0}}
        selfid: {task: "x,y,z", m_a: 0.02, eps_rel: 0.05, max_samples: 60, seed: 3, settle_s: 0.0, poll_s: 0.001}
        safety: {stale_s: 1.0, max_step: 0.03}
        path: {size: 0.02, tol: 0.001, max_task_step: 0.004, gain: 0.7, steps: 400}
    """)


def test_cli_prints_progress_and_quiet_prints_only_the_report(tmp_path, driver_module, capsys):
    from selfid_jax.cli import main

    cfg = _follow_config(tmp_path)
    assert main(["online", str(cfg), "--out", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out.splitlines()
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    sel = [ln for ln in out if ln.startswith("self-ID  move")]
    fol = [ln for ln in out if ln.startswith("follow   move")]
    assert len(sel) == summary["moves"] and len(fol) == summary["follow_steps"]  # one line per event, not a tty
    assert "threshold" in sel[0] and sel[-1].endswith("converged") and "waypoint 10/10" in fol[-1]
    assert "path distance" in fol[0] and out.index(sel[-1]) < out.index(fol[0])
    assert any(ln.startswith("stop: completed") for ln in out) and any(ln.startswith("tracking error") for ln in out)
    # the summary: tracking error and wall times
    assert 0 < summary["track_mean_m"] <= summary["track_max_m"] < 0.01
    assert summary["selfid_s"] > 0 and summary["follow_s"] > 0
    assert main(["online", str(cfg), "--out", str(tmp_path / "b"), "--quiet"]) == 0
    quiet = capsys.readouterr().out
    assert "self-ID  move" not in quiet and "follow   move" not in quiet and "stop: completed" not in quiet
    assert "follow: 10/10 waypoints" in quiet and "stopped: completed" in quiet and "tracking error" in quiet


def test_progress_line_on_a_terminal_rewrites_one_line_per_phase():
    import io

    from selfid_jax.commands.online import ProgressLine

    buf = io.StringIO()
    show = ProgressLine(buf, tty=True)
    show({"phase": "selfid", "move": 1, "sample": 1, "accepted": True, "delta": 1.0, "threshold": 0.1,
          "converged_at": -1})
    show({"phase": "selfid", "move": 2, "sample": 1, "accepted": False, "reason": "dropout"})
    show({"phase": "follow", "step": 1, "waypoint": 0, "waypoints": 10, "distance": 1e-4})
    show({"phase": "stop", "status": "completed", "detail": "done"})
    text = buf.getvalue()
    assert text.count("\n") == 3 and text.count("\r") == 3 and text.endswith("stop: completed: done\n")
    assert "rejected (dropout)" in text and "0.100 mm" in text


def test_online_run_writes_figures_and_plot_redraws_them(tmp_path, driver_module, capsys):
    from selfid_jax.cli import main

    run = tmp_path / "run"
    assert main(["online", str(_follow_config(tmp_path)), "--out", str(run), "--quiet"]) == 0
    figures = {f"{name}.{ext}" for name in ("convergence", "path") for ext in ("png", "pdf")}
    assert {p.name for p in (run / "figures").iterdir()} == figures
    assert "figure: " in capsys.readouterr().out
    for name in figures:
        (run / "figures" / name).unlink()
    assert main(["plot", str(run)]) == 0
    assert {p.name for p in (run / "figures").iterdir()} == figures
    assert all((run / "figures" / n).stat().st_size > 1000 for n in figures)
    assert "figure: " in capsys.readouterr().out


def test_online_run_without_a_path_has_only_the_convergence_figure(tmp_path, converged_run, capsys):
    from selfid_jax.cli import main

    run, _, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    assert main(["plot", str(tmp_path / "r")]) == 0
    assert sorted(p.name for p in (tmp_path / "r" / "figures").iterdir()) == ["convergence.pdf", "convergence.png"]


def test_path_figure_titles_say_tracked_point(converged_run, tmp_path):
    from selfid_jax.commands import online_figures

    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    path = options.FollowOptions(size=0.02, tol=0.001, max_task_step=0.004, gain=0.7, steps=400)
    live.run_online(FakeArm(q0=ref_fake.q, max_step=0.05), opts(path=path, max_step=0.03), tmp_path / "r",
                    resume=True)
    log = read_journal(tmp_path / "r" / "session.jsonl")
    fig = online_figures.draw_path(log.records, [0, 1, 2], "t")
    titles = " ".join(ax.get_title() for ax in fig.axes)
    assert "tracked point" in titles and "POM" not in titles
    assert online_figures.tracking(log.records)["track_moves"] > 0


def test_plot_refuses_an_unknown_directory_clearly(tmp_path, capsys):
    from selfid_jax.cli import main

    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("x")
    assert main(["plot", str(tmp_path / "junk")]) == 2
    err = capsys.readouterr().err
    assert "not a run directory" in err and "config.yaml" in err and "online" in err and "fit" in err
    assert sorted(p.name for p in (tmp_path / "junk").iterdir()) == ["notes.txt"]  # nothing written there
    assert main(["plot", str(tmp_path / "missing")]) == 2
    assert "not found" in capsys.readouterr().err


# --------------------------------------------------------------------------- paths and estimates a lab can reuse


SQUARE = [[0.01, 0.0, 0.0], [0.01, 0.01, 0.0], [0.0, 0.01, 0.005], [0.0, 0.0, 0.0]]  # m, x y z offsets
FOLLOW = dict(tol=0.001, max_task_step=0.004, gain=0.7, steps=400)


def _write_estimate(path, estimate, axes=("x", "y", "z")):
    np.savez(path, inverse_jacobian=np.asarray(estimate), task_axes=np.array(list(axes)))
    return path


@pytest.mark.parametrize("kind", ["waypoints", "csv"])
def test_waypoints_and_csv_paths_are_followed_to_completion(tmp_path, converged_run, kind):
    run, ref_fake, ref = converged_run
    shutil.copytree(run, tmp_path / "r")
    if kind == "waypoints":
        path = options.FollowOptions(kind="waypoints", waypoints=SQUARE, **FOLLOW)
    else:  # columns in another order than the task's: matched by the header's names
        rows = "\n".join(f"{z},{x},{y}" for x, y, z in SQUARE)
        (tmp_path / "square.csv").write_text(f"# a square with a step up, m\nz, x, y\n{rows}\n")
        path = options.FollowOptions(kind="csv", file=str(tmp_path / "square.csv"), **FOLLOW)
    np.testing.assert_array_equal(path.offsets((0, 1, 2)), SQUARE)
    fake = FakeArm(q0=ref_fake.q, max_step=0.05)
    p0, _ = arm_pose(fake.q)
    result = live.run_online(fake, opts(path=path, max_step=0.03), tmp_path / "r", resume=True)
    assert result.status == live.Stop.COMPLETED, result.detail
    assert result.waypoints == result.waypoints_total == 4 and result.moves == ref.moves  # no random move
    follow = [r for r in read_journal(tmp_path / "r" / live.LOG_FILE).records if r["e"] == "follow"]
    np.testing.assert_array_equal([floats(o) for o in follow[0]["offsets"]], SQUARE)
    np.testing.assert_allclose(arm_pose(fake.q)[0], p0, atol=0.0015)  # the last waypoint is the start
    # resumed again with the same path: nothing left to do; with another path: refused, naming the path keys
    again = live.run_online(FakeArm(q0=fake.q), opts(path=path), tmp_path / "r", resume=True)
    assert again.status == live.Stop.COMPLETED and again.follow_steps == result.follow_steps
    other = options.FollowOptions(kind="waypoints", waypoints=SQUARE[:3], **FOLLOW)
    with pytest.raises(session.ResumeError, match="path.waypoints"):
        live.run_online(FakeArm(q0=fake.q), opts(path=other), tmp_path / "r", resume=True)


def _bad_csv(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    return dict(kind="csv", file=str(tmp_path / name))


@pytest.mark.parametrize("case, key, match", [
    ("columns", "path.waypoints", "has 2 values; the task has 3 axes"),
    ("nan", "path.waypoints", "not finite"),
    ("empty", "path.waypoints", "at least 1"),
    ("none", "path.waypoints", "needs it"),
    ("missing_file", "path.file", "no such file"),
    ("header", "path.file", "does not name the task axes x,y,z"),
    ("csv_columns", "path.file", "waypoint 2 has 2 values"),
    ("csv_inf", "path.file", "not finite"),
    ("csv_empty", "path.file", "at least 1"),
    ("file_with_star", "path.file", "only used with path.kind 'csv'"),
])
def test_bad_paths_are_refused_before_any_move(tmp_path, case, key, match):
    kw = {"columns": dict(kind="waypoints", waypoints=[[0.01, 0.0, 0.0], [0.01, 0.0]]),
          "nan": dict(kind="waypoints", waypoints=[[0.01, float("nan"), 0.0]]),
          "empty": dict(kind="waypoints", waypoints=[]),
          "none": dict(kind="waypoints"),
          "missing_file": dict(kind="csv", file=str(tmp_path / "nope.csv")),
          "header": _bad_csv(tmp_path, "header.csv", "x,y,rz\n0.01,0,0\n"),
          "csv_columns": _bad_csv(tmp_path, "csv_columns.csv", "x,y,z\n0.01,0,0\n0.01,0\n"),
          "csv_inf": _bad_csv(tmp_path, "csv_inf.csv", "x,y,z\n0.01,inf,0\n"),
          "csv_empty": _bad_csv(tmp_path, "csv_empty.csv", "x,y,z\n"),
          "file_with_star": dict(file="square.csv")}[case]
    fake = FakeArm()
    with pytest.raises(ValueError, match=key) as err:
        live.run_online(fake, opts(path=options.FollowOptions(**kw)), tmp_path / "r")
    assert match in str(err.value)
    assert fake.moves == [] and fake.closed and not (tmp_path / "r").exists()


def test_the_box_check_uses_the_given_waypoints(tmp_path, converged_run):
    run, ref_fake, _ = converged_run
    shutil.copytree(run, tmp_path / "r")
    fake = FakeArm(q0=ref_fake.q)
    p0, _ = arm_pose(fake.q)
    path = options.FollowOptions(kind="waypoints", waypoints=[[0.01, 0.0, 0.0], [0.0, 0.0, 0.03]], **FOLLOW)
    result = live.run_online(fake, opts(path=path, box_low=(p0 - 0.02).tolist(), box_high=(p0 + 0.02).tolist()),
                             tmp_path / "r", resume=True)
    assert result.status == live.Stop.BOX and "waypoint 2 of 2" in result.detail, result.detail
    assert fake.moves == []


def test_a_given_estimate_follows_without_any_random_move_and_resumes(tmp_path, converged_run):
    _, ref_fake, ref = converged_run
    npz = _write_estimate(tmp_path / "inverse_jacobian.npz", ref.estimate)
    path = options.FollowOptions(kind="waypoints", waypoints=SQUARE, **FOLLOW)
    fake = FakeArm(q0=ref_fake.q, max_step=0.05, interrupt_at=3)
    first = live.run_online(fake, opts(path=path, max_step=0.03, estimate=str(npz)), tmp_path / "r")
    assert first.status == live.Stop.INTERRUPTED and first.moves == first.samples == 0
    recs = read_journal(tmp_path / "r" / live.LOG_FILE).records
    est = [r for r in recs if r["e"] == "estimate"]
    assert len(est) == 1 and est[0]["source"] == str(npz)
    assert {r["phase"] for r in recs if r["e"] == "move"} == {"follow"}  # no self-ID move at all
    # resumed without the file: the log's estimate; with it: the same; the path is completed
    fake2 = FakeArm(q0=fake.q, max_step=0.05)
    second = live.run_online(fake2, opts(path=path, max_step=0.03), tmp_path / "r", resume=True)
    assert second.status == live.Stop.COMPLETED, second.detail
    assert second.moves == 0 and second.estimate_source == str(npz) and second.waypoints == 4
    np.testing.assert_array_equal(second.estimate, ref.estimate)
    # a different estimate on resume is refused naming both sources
    other = _write_estimate(tmp_path / "other.npz", 2 * ref.estimate)
    with pytest.raises(session.ResumeError, match="other.npz differs"):
        live.run_online(FakeArm(q0=fake2.q), opts(path=path, estimate=str(other)), tmp_path / "r", resume=True)


def test_a_given_estimate_is_refused_on_a_self_identified_log(tmp_path, converged_run):
    run, ref_fake, ref = converged_run
    shutil.copytree(run, tmp_path / "r")
    npz = _write_estimate(tmp_path / "e.npz", ref.estimate)
    fake = FakeArm(q0=ref_fake.q)
    path = options.FollowOptions(kind="waypoints", waypoints=SQUARE, **FOLLOW)
    with pytest.raises(session.ResumeError, match="self-identified"):
        live.run_online(fake, opts(path=path, estimate=str(npz)), tmp_path / "r", resume=True)
    assert fake.moves == []


@pytest.mark.parametrize("shape, axes, task, match", [
    ((3, 2), ("x", "y"), "x,y,z", "task axes are x,y, the task is x,y,z"),
    ((2, 3), ("x", "y", "z"), "x,y,z", r"is \(2, 3\), expected \(3, 3\)"),
    ((3, 3), ("x", "y", "z"), "x,y,rz", "task axes are x,y,z, the task is x,y,rz"),
    (None, None, "x,y,z", "no such file"),
])
def test_an_estimate_of_the_wrong_shape_or_axes_is_refused_before_any_move(tmp_path, shape, axes, task, match):
    npz = tmp_path / "e.npz"
    if shape is not None:
        _write_estimate(npz, np.ones(shape), axes)
    fake = FakeArm()
    path = options.FollowOptions(kind="waypoints", waypoints=[[0.01] * len(task.split(","))], **FOLLOW)
    with pytest.raises(ValueError, match=match) as err:
        live.run_online(fake, opts(task=task, path=path, estimate=str(npz)), tmp_path / "r")
    assert str(npz) in str(err.value)
    assert fake.moves == [] and fake.closed


def test_cli_follows_a_csv_beside_the_config_with_the_estimate_of_an_earlier_session(tmp_path, driver_module, capsys):
    from selfid_jax.cli import main

    assert main(["online", str(_follow_config(tmp_path)), "--out", str(tmp_path / "a"), "--quiet"]) == 0
    npz = tmp_path / "a" / "inverse_jacobian.npz"
    rows = "\n".join(",".join(map(str, r)) for r in SQUARE)
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "square.csv").write_text(f"x,y,z\n{rows}\n")
    cfg = _config(tmp_path / "cfg", """
        robot: {driver: "fake_driver:make", args: {noise: 0.0}}
        selfid: {task: "x,y,z", settle_s: 0.0, poll_s: 0.001}
        safety: {stale_s: 1.0, max_step: 0.03}
        path: {kind: csv, file: square.csv, tol: 0.001, max_task_step: 0.004, gain: 0.7, steps: 400}
    """)
    capsys.readouterr()
    assert main(["online", str(cfg), "--out", str(tmp_path / "b"), "--estimate", str(npz), "--quiet"]) == 0
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["moves"] == 0 and summary["samples"] == 0
    assert summary["waypoints"] == 4 and summary["estimate_source"] == str(npz)
    assert "no self-ID" in capsys.readouterr().out
    assert not (tmp_path / "b" / "inverse_jacobian.npz").exists()  # not this session's result
    # the self-identified run resumed with an estimate: refused (exit 2), naming the cause
    assert main(["online", str(_follow_config(tmp_path)), "--out", str(tmp_path / "a"), "--resume",
                 "--estimate", str(npz)]) == 2
    assert "self-identified" in capsys.readouterr().err
    # wrong axes in the file: exit 2 naming the file, no move
    bad = _write_estimate(tmp_path / "xy.npz", np.ones((3, 2)), ("x", "y"))
    assert main(["online", str(cfg), "--out", str(tmp_path / "c"), "--estimate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "xy.npz" in err and "task axes" in err
    assert all(arm.moves == [] for arm in driver_module.CREATED[2:])
    # a header that does not match the task: exit 2 naming path.file, before connecting
    (tmp_path / "cfg" / "square.csv").write_text(f"x,y\n{rows}\n")
    n_arms = len(driver_module.CREATED)
    assert main(["online", str(cfg), "--out", str(tmp_path / "d"), "--estimate", str(npz)]) == 2
    assert "path.file" in capsys.readouterr().err and len(driver_module.CREATED) == n_arms


class ModelArm(FakeArm):
    """FakeArm with a model: jacobian(q) by central differences of arm_pose (position rows; rotation rows zero,
    the task has none), or a broken one."""

    def __init__(self, *a, broken=False, **kw):
        super().__init__(*a, **kw)
        self.broken, self.asked = broken, []

    def jacobian(self, q):
        self.asked.append(np.array(q))
        if self.broken:
            return np.zeros((3, 3))
        h = 1e-6
        cols = [(arm_pose(q + h * e)[0] - arm_pose(q - h * e)[0]) / (2 * h) for e in np.eye(3)]
        return np.vstack([np.array(cols).T, np.zeros((3, 3))])


def test_a_driver_model_jacobian_is_the_estimate_s_reference(tmp_path):
    """jacobian() is asked once, at the first reading; summary-level reference_error equals numpy's ||J Ĵ - I||_F
    (a few % here: the estimate averages J over the moves around the start) and figures/estimate is drawn from
    the log; a malformed one stops before any move; a driver without one has no reference."""
    from selfid_jax.commands import online_figures

    arm = ModelArm()
    res = live.run_online(arm, opts(), tmp_path / "a")
    assert res.converged and len(arm.asked) == 1 and np.array_equal(arm.asked[0], START)
    h = 1e-6
    J = np.array([(arm_pose(START + h * e)[0] - arm_pose(START - h * e)[0]) / (2 * h) for e in np.eye(3)]).T
    want = np.linalg.norm(J @ res.estimate - np.eye(3))
    assert res.reference_error == pytest.approx(want, rel=1e-6) and 0 < want < 0.15
    paths = online_figures.write_figures(tmp_path / "a")
    assert any(p.name == "estimate.png" for p in paths)
    resumed = live.run_online(ModelArm(q0=arm.q), opts(), tmp_path / "a", resume=True)
    assert resumed.reference_error == pytest.approx(want, rel=1e-6)  # from the log
    bad = ModelArm(broken=True)
    res = live.run_online(bad, opts(), tmp_path / "b")
    assert res.status == live.Stop.DRIVER_ERROR and "jacobian() raised ValueError" in res.detail, res.detail
    assert bad.moves == []
    assert live.run_online(FakeArm(), opts(), tmp_path / "c").reference_error is None
