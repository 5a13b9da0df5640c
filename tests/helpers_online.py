"""The fake arm and helpers the online runner's tests share (tests/test_online.py, test_online_cli.py,
test_online_lab.py, test_online_session.py; tests/conftest.py's ``driver_module`` and ``converged_run`` fixtures):
a yaw-pitch-pitch arm with injectable faults behind the robot protocol, the runner's options for it, and the
checks on what it was commanded."""

from __future__ import annotations

import textwrap
import time

import jax
import numpy as np

from selfid_jax.robot import options
from selfid_jax.robot.journal import floats, read_journal
from selfid_jax.robot.protocol import Observation, RobotConnectionError, RobotLimits

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
    late (its latency longer than the settle time). ``jitter``: Gaussian tracker noise [m per axis], new at every
    read (seeded), so readings at rest differ. ``joint_names``: the driver's names of its joints (messages use them).
    """

    def __init__(self, q0=START, *, lower=(-3.0, -3.0, -3.0), upper=(3.0, 3.0, 3.0), max_step=0.2, dropouts=(),
                 freeze_at=None, fail_move_at=None, interrupt_at=None, mirror=False, noise=1e-5, fail_move_with=None,
                 fail_read_at=None, fail_read_with="TimeoutError", valid_as=None, in_place=False,
                 frozen_pose_at=None, tracker_clock=None, stuck=None, slow=None, delay_at=None, delay_s=0.0,
                 pose_lag=False, no_quaternion=False, band=None, jitter=0.0, joint_names=None):
        self.jitter, self._rng = jitter, np.random.default_rng(7)
        if joint_names is not None:
            self.joint_names = joint_names
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
        if self.jitter:
            p = p + self._rng.normal(0.0, self.jitter, 3)
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


# the fake arm's driver module (tests/conftest.py's driver_module writes it beside a test's config)
DRIVER = '''
import numpy as np
CREATED = []

def make(**kw):
    from helpers_online import FakeArm
    arm = FakeArm(**{k: np.array(v) if isinstance(v, list) else v for k, v in kw.items()})
    CREATED.append(arm)
    return arm
'''


def write_config(tmp_path, body):
    path = tmp_path / "online.yaml"
    path.write_text(textwrap.dedent(body))
    return path
