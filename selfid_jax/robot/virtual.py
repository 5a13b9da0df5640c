"""The virtual robot: a :class:`~selfid_jax.systems.System` stepped in real time with the real loop's non-idealities.

:class:`VirtualRobot` implements :class:`selfid_jax.robot.protocol.Robot` in
process; :mod:`selfid_jax.robot.transport` serves it (or any other driver) over
a socket, and ``selfid-jax robot-sim CONFIG`` (:mod:`selfid_jax.commands.robot_sim`)
runs it in a process of its own.

Model (the rule of :mod:`selfid_jax.control.realism`, evaluated in numpy on a
real-time clock): a thread ticks every ``period`` seconds (``time.monotonic``,
sleeping to the next tick; a tick that wakes late runs the missed ticks at once,
so simulated time stays wall time). At each tick ``k`` the actuators move
towards the last commanded target ``u``::

    q_i <- q_i                                   if |u_i - q_i| <= deadband_i
    q_i <- q_i + (u_i - q_i) (1 - exp(-period / servo_tau))   otherwise

(``servo_tau = 0``: ``q_i <- u_i``), so from rest at ``q0``, with no deadband,
``q_k = u + (q0 - u) exp(-k period / servo_tau)``, ``k`` ticks after the
command. The encoders are exact and current: :meth:`VirtualRobot.read` returns
``q`` of the latest tick ``k`` and ``t = k period``. The tracker reports the pose
``system.pose(q_{k - latency})`` of ``latency`` ticks earlier
(``tracker_t = (k - latency) period``), with Gaussian noise of ``noise_pos`` m per
axis on the position and a rotation vector of ``noise_rot`` rad per axis applied
in the world frame (``R <- exp(w) R``), and with probability ``dropout`` per
reading no pose (``valid`` False; the last pose reported and its ``tracker_t``
are repeated). A pose that is not finite (a hand outside its grasp) is a
dropout too. The pose is the system's own map, jitted once and evaluated in
float64 on each reading: MJCF kinematics for arms, the closed chain's Newton
solve for the hands.

Times are seconds on the simulator's clock, 0 at :meth:`VirtualRobot.start`;
the faults (:class:`Faults`) are scheduled on the same clock. Noise and
dropouts come from a numpy ``Generator`` seeded from ``seed`` (a stateful,
real-time process; not traced code).

The simulator is a safety net of its own: a move of the wrong length or with a
non-finite entry, outside the limits, or a step larger than ``max_step`` from
the actuators' position when the move arrives is refused (:class:`RobotError`,
naming the actuator) and nothing moves.
"""

from __future__ import annotations

import functools
import math
import threading
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.control.realism import Realism, check_realism
from selfid_jax.math.geometry import rotation_to_quaternion, so3_exp
from selfid_jax.robot.protocol import Observation, RobotError, RobotLimits, check_limits
from selfid_jax.systems import REGISTRY, System

UR5E_JOINT_NAMES = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
"""Universal Robots' names of the UR5e's joints, base to tool."""

__all__ = ["UR5E_JOINT_NAMES", "Faults", "LatencySpike", "TickStats", "VirtualRobot", "Window", "build_system",
           "default_q0", "servo_step", "system_limits", "tracked_reach"]


class Window(NamedTuple):
    """A time window ``[at_s, at_s + duration_s)`` on the simulator's clock (s)."""

    at_s: float  # s, start
    duration_s: float  # s, length

    def contains(self, t: float) -> bool:
        """Whether ``t`` (s) lies in the window."""
        return self.at_s <= t < self.at_s + self.duration_s


class LatencySpike(NamedTuple):
    """Requests that arrive in ``[at_s, at_s + duration_s)`` are answered ``extra_s`` seconds late."""

    at_s: float  # s, start on the simulator's clock
    duration_s: float  # s
    extra_s: float  # s, added to each reply in the window

    @property
    def window(self) -> Window:
        """The window of arrival times that are delayed."""
        return Window(self.at_s, self.duration_s)


class Faults(NamedTuple):
    """Injected faults (each None: absent), on the simulator's clock (s since :meth:`VirtualRobot.start`)."""

    latency_spike: LatencySpike | None = None  # read/move/limits answered late
    dropout_burst: Window | None = None  # every tracker reading in the window is a dropout (valid False)
    freeze_tracker_at_s: float | None = None  # from then on the tracker repeats one reading, valid, tracker_t frozen


class TickStats(NamedTuple):
    """How well the tick thread kept its real-time rate (see :meth:`VirtualRobot.stats`)."""

    period: float  # s, configured control period
    elapsed: float  # s since start
    ticks: int  # ticks simulated (= floor(elapsed / period): missed ticks are caught up)
    wakeups: int  # times the thread woke to tick (ticks - wakeups ticks ran late, in a catch-up)
    late_p50: float  # s, median lateness of a wake-up after its tick's due time
    late_p99: float  # s, 99th percentile of that lateness
    late_max: float  # s, largest lateness
    caught_up: int  # ticks run more than one period late (in a catch-up)


def build_system(name: str | None = None, *, mjcf: str | None = None, site: str | None = None,
                 body: str | None = None, offset: Any = None, actuators: Any = None, task_dim: int = 3,
                 dq_max: float = 0.1) -> System:
    """A built-in system by name (:data:`selfid_jax.systems.REGISTRY`) or a user's MJCF or URDF (``.urdf``) with
    its POM at a ``site``, or at ``offset (3,)`` [m] in ``body``'s frame, driven by its actuators or the named
    ``actuators`` (``"joints"``: every hinge and slide joint); built in float64.

    Raises ValueError naming the unknown system or the MJCF problem.
    """
    if (name is None) == (mjcf is None):
        raise ValueError("give a built-in system name or an MJCF path (one of them)")
    with jax.enable_x64(True):
        if name is not None:
            if name not in REGISTRY:
                raise ValueError(f"unknown system {name!r}; built-in: {', '.join(REGISTRY)}")
            return REGISTRY[name].factory()
        from selfid_jax.systems import from_mjcf

        if bool(site) == bool(body):
            raise ValueError("an MJCF or URDF system needs the point to track: a site, or a body (and an offset)")
        pom: dict[str, Any] = {} if body is None else {"body": body,
                                                        "offset": (0.0, 0.0, 0.0) if offset is None else offset}
        if actuators is not None:
            pom["actuators"] = actuators
        # m_a is the runner's business; the System only requires a positive value
        return from_mjcf(mjcf, site, task_dim=task_dim, m_a=dq_max, dq_max=dq_max, **pom)


def default_q0(system: System) -> np.ndarray:
    """The start position ``(n,)``: the robot's home where it has one (UR5e, Model O, Stewart Hand), else the
    centre of its sampling box (for an MJCF: its home, unless the box was clipped at a limit)."""
    name = system.name
    if name.startswith("ur5e"):
        from selfid_jax.systems.ur5e import UR5E_HOME

        return np.asarray(UR5E_HOME, np.float64)
    if name.startswith("model_o"):
        from selfid_jax.systems.hands import model_o_home

        return np.asarray(model_o_home(), np.float64)
    if name.startswith("stewart"):
        from selfid_jax.systems.hands import stewart_home

        return np.asarray(stewart_home(), np.float64)
    return 0.5 * (np.asarray(system.sample_low, np.float64) + np.asarray(system.sample_high, np.float64))


def system_limits(system: System, max_step: Any = None) -> RobotLimits:
    """The robot's limits from the system's: ``q_low``/``q_high`` ``(n,)``, the sampling box where those are
    infinite, and ``max_step`` (scalar or ``(n,)``, default the system's ``dq_max``)."""
    lo, hi = (np.asarray(x, np.float64) for x in (system.q_low, system.q_high))
    lo = np.where(np.isfinite(lo), lo, np.asarray(system.sample_low, np.float64))
    hi = np.where(np.isfinite(hi), hi, np.asarray(system.sample_high, np.float64))
    step = np.asarray(system.dq_max if max_step is None else max_step, np.float64)
    return check_limits(RobotLimits(lo, hi, np.broadcast_to(step, lo.shape).copy()), system.n_act)


REACH_BATCH = 4096
"""Actuator positions per evaluation of the tracked position in :func:`tracked_reach` (one compilation)."""
REACH_MARGIN = 0.02
""":func:`tracked_reach` adds this fraction: what a search from samples may still miss of the farthest position."""


def tracked_reach(system: System, lower: np.ndarray, upper: np.ndarray, *, batches: int = 8,
                  seed: int = 0) -> float | None:
    """The radius [m] of a ball fixed in the world that holds every position of the system's tracked point with the
    actuators ``(n,)`` within ``[lower, upper]``: so any two of them are at most twice this apart.

    From ``batches`` x :data:`REACH_BATCH` uniform actuator positions: the ball's centre is the smallest enclosing
    ball's of their tracked positions (Badoiu-Clarkson's iteration), its radius the farthest of them from it after
    six rounds of local search around the 16 farthest (steps 0.2 to 0.005 in actuator units), plus
    :data:`REACH_MARGIN`. A search, not a proof: the margin covers what it misses. Positions that are not finite
    are left out; None where none is.
    """
    lo, hi = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
    rng = np.random.default_rng(seed)
    with jax.enable_x64(True):
        position = jax.jit(jax.vmap(lambda q: system.pose(q)[0]))
        Q = lo + (hi - lo) * rng.uniform(size=(batches * REACH_BATCH, lo.shape[0]))
        P = np.concatenate([np.asarray(position(x)) for x in np.split(Q, batches)])
        ok = np.all(np.isfinite(P), axis=1)
        if not ok.any():
            return None
        Q, P = Q[ok], P[ok]
        centre = P[0].copy()
        for k in range(1, 1000):
            centre += (P[np.argmax(np.sum((P - centre) ** 2, axis=1))] - centre) / (k + 1)
        d = np.linalg.norm(P - centre, axis=1)
        top = np.argsort(d)[-16:]
        Q, d = Q[top], d[top]
        for step in (0.2, 0.1, 0.05, 0.02, 0.01, 0.005):
            near = np.clip(np.repeat(Q, REACH_BATCH // 16, axis=0) + step * rng.normal(size=(REACH_BATCH, lo.shape[0])),
                           lo, hi)
            dn = np.linalg.norm(np.asarray(position(near)) - centre, axis=1)
            dn = np.where(np.isfinite(dn), dn, -np.inf)
            allq, alld = np.concatenate([Q, near]), np.concatenate([d, dn])
            top = np.argsort(alld)[-16:]
            Q, d = allq[top], alld[top]
    return float(d.max()) * (1.0 + REACH_MARGIN)


def servo_step(q: np.ndarray, u: np.ndarray, gain: float, deadband: np.ndarray) -> np.ndarray:
    """One tick of the actuators ``(n,)`` towards targets ``u (n,)``: deadband, then first-order lag of ``gain``
    (``1 - exp(-period / servo_tau)``; 1: reach ``u``). Actuator units."""
    moved = u if gain >= 1.0 else q + gain * (u - q)
    return np.where(np.abs(u - q) <= deadband, q, moved)


def _tracker_fn(system: System) -> Callable:
    """``(q (n,), dp (3,), dw (3,)) -> (position (3,), quaternion (4,))``: the pose, noise added, w >= 0."""

    def tracker(q, dp, dw):
        p, R = system.pose(q)
        quat = rotation_to_quaternion(so3_exp(dw) @ R)
        return p + dp, jnp.where(quat[0] < 0, -quat, quat)

    return jax.jit(tracker)


class _Reading(NamedTuple):
    position: np.ndarray  # (3,) m
    quaternion: np.ndarray  # (4,) (w, x, y, z)
    tracker_t: float  # s


class VirtualRobot:
    """A :class:`~selfid_jax.systems.System` stepped in real time behind the :class:`~selfid_jax.robot.protocol.Robot`
    protocol (see the module docstring for the model).

    Args:
      system: the robot (built in float64, e.g. :func:`build_system`).
      realism: the non-idealities; ``period > 0`` (s) is the tick of the simulation.
      q0: ``(n,)`` start position (default :func:`default_q0`), inside the limits.
      faults: injected faults (:class:`Faults`).
      seed: seed of the tracker's noise and dropouts.
      max_step: largest accepted step, scalar or ``(n,)`` (default the system's ``dq_max``).
      start: start ticking now (else call :meth:`start`); the pose is compiled before either.
    """

    def __init__(self, system: System, *, realism: Realism, q0: Any = None, faults: Faults = Faults(),
                 seed: int = 0, max_step: Any = None, start: bool = True):
        r = check_realism(realism)
        if not float(r.period) > 0:
            raise ValueError(f"realism.period: the virtual robot ticks in real time, needs a period > 0 s, "
                             f"got {r.period!r}")
        self.system, self.realism, self.faults = system, r, faults
        # the vendor's joint names where the system is a known arm (the runner's messages name joints by them)
        self.joint_names = UR5E_JOINT_NAMES if system.name.startswith("ur5e") else None
        self.n = int(system.n_act)
        self.period = float(r.period)
        self.latency = int(r.latency)
        tau = float(r.servo_tau)
        self._gain = 1.0 if tau == 0 else -math.expm1(-self.period / tau)
        self._deadband = np.broadcast_to(np.asarray(r.deadband, np.float64), (self.n,)).copy()
        self._limits = system_limits(system, max_step)
        q = default_q0(system) if q0 is None else np.asarray(q0, np.float64).reshape(-1)
        if q.shape != (self.n,) or not np.all(np.isfinite(q)):
            raise ValueError(f"q0: expected {self.n} finite actuator positions, got {q.tolist()}")
        outside = np.flatnonzero((q < self._limits.lower) | (q > self._limits.upper))
        if outside.size:
            i = outside[0]
            raise ValueError(f"q0[{i}] = {q[i]:g} is outside the limits [{self._limits.lower[i]:g}, "
                             f"{self._limits.upper[i]:g}]")
        self._rng = np.random.default_rng(seed)
        self._tracker = _tracker_fn(system)
        zero = np.zeros(3)
        p, quat = self._pose(q, zero, zero)  # compiles here, before the clock starts
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(quat))):
            raise ValueError(f"q0: the system has no pose at {q.tolist()} (NaN)")
        self._q0 = q.copy()  # (n,) the start position (reset)
        self._q = q.copy()  # (n,) actuator positions at tick self._k
        self._u = q.copy()  # (n,) commanded target
        self._k = 0  # latest tick simulated
        self._hist = np.tile(q, (self.latency + 1, 1))  # (latency + 1, n) ring buffer: row k % (L + 1) is q_k
        self._last = _Reading(p, quat, -self.latency * self.period)  # the last pose the tracker reported
        self._frozen_q: np.ndarray | None = None  # (n,) the actuators' position the frozen tracker last saw
        self._frozen_k = 0  # the tick of that position
        self._frozen: _Reading | None = None  # the reading a frozen tracker repeats
        freeze = faults.freeze_tracker_at_s
        if freeze is not None and freeze <= 0:  # frozen at tick 0 already, not from the tick thread's first tick
            self._frozen_q, self._frozen_k = q.copy(), -self.latency
        self._lock = threading.Lock()  # the state above, between the tick thread and the callers
        self._read_lock = threading.Lock()  # the generator and the last reading, between callers
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = math.nan
        self._lateness = np.zeros(100_000)  # s, ring buffer of wake-up lateness
        self._wakeups = 0
        self._caught_up = 0
        self._closed = False
        if start:
            self.start()

    # ------------------------------------------------------------------ clock
    def start(self) -> None:
        """Start the clock (t = 0) and the tick thread; once."""
        if self._thread is not None:
            raise RuntimeError("the virtual robot is already started")
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="virtual-robot-ticks", daemon=True)
        self._thread.start()

    def now(self) -> float:
        """Seconds on the simulator's clock (0 at :meth:`start`; NaN before)."""
        return time.monotonic() - self._t0

    def _run(self) -> None:
        period, t0, n_lat = self.period, self._t0, self.latency + 1
        k = 0
        while not self._stop.is_set():
            due = t0 + (k + 1) * period
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            now = time.monotonic()
            self._lateness[self._wakeups % self._lateness.shape[0]] = now - due
            self._wakeups += 1
            k_now = max(k + 1, int((now - t0) / period))
            self._caught_up += k_now - k - 1
            with self._lock:
                q, u, hist = self._q, self._u, self._hist
                for j in range(k + 1, k_now + 1):
                    q = servo_step(q, u, self._gain, self._deadband)
                    hist[j % n_lat] = q
                self._q, self._k = q, k_now
                freeze = self.faults.freeze_tracker_at_s
                if freeze is not None and self._frozen_q is None and k_now * period >= freeze:
                    self._frozen_q = hist[(k_now - self.latency) % n_lat].copy()
                    self._frozen_k = k_now - self.latency
            k = k_now

    def reset(self) -> None:
        """Put the actuators back at rest at the start position ``q0`` at once (a simulator's reset; the clock runs
        on). The tracker, ``latency`` periods behind, sees the arm there from now on."""
        with self._lock:
            self._q, self._u = self._q0.copy(), self._q0.copy()
            self._hist[:] = self._q0

    def stats(self) -> TickStats:
        """Tick timing since :meth:`start`: ticks, wake-ups, and lateness of a wake-up (p50, p99, max, s)."""
        w = min(self._wakeups, self._lateness.shape[0])
        late = self._lateness[:w] if w else np.zeros(1)
        return TickStats(self.period, self.now(), self._k, self._wakeups, float(np.percentile(late, 50)),
                         float(np.percentile(late, 99)), float(late.max()), self._caught_up)

    @functools.cached_property
    def reach(self) -> float | None:
        """[m] The farthest the tracked point gets from a point fixed in the world, within the limits
        (:func:`tracked_reach` of the model, computed once): the runner refuses a waypoint farther than twice this
        from where following starts (the protocol's optional ``reach``)."""
        return tracked_reach(self.system, self._limits.lower, self._limits.upper)

    tool_offset = 0.0
    """[m] :attr:`reach` is the tracked point's own: no tool beyond it (the protocol's optional ``tool_offset``)."""

    def info(self) -> dict[str, Any]:
        """What a client may want to know (plain values): name, n, period, latency, the clock."""
        return {"name": self.system.name, "n": self.n, "period": self.period, "latency": self.latency,
                "servo_tau": float(self.realism.servo_tau), "t": self.now(), "clock": "s since the simulator started"}

    # ------------------------------------------------------------------ the protocol
    def _pose(self, q, dp, dw) -> tuple[np.ndarray, np.ndarray]:
        with jax.enable_x64(True):  # thread-local: the callers' threads each need it
            p, quat = self._tracker(np.asarray(q, np.float64), dp, dw)
            return np.asarray(p, np.float64), np.asarray(quat, np.float64)

    def _fault_delay(self) -> None:
        spike = self.faults.latency_spike
        if spike is not None and spike.window.contains(self.now()):
            time.sleep(spike.extra_s)

    def _check_open(self) -> None:
        if self._closed:
            raise RobotError("the virtual robot is closed")

    def limits(self) -> RobotLimits:
        """The actuator limits ``(n,)`` (constant)."""
        self._check_open()
        self._fault_delay()
        return RobotLimits(*(x.copy() for x in self._limits))

    def position(self) -> np.ndarray:
        """The actuators' positions ``(n,)`` at the latest tick, without a tracker reading (no random draw, no
        injected delay): what a server checks a move's ``max_step`` against."""
        with self._lock:
            return self._q.copy()

    def read(self) -> Observation:
        """Actuator positions of the latest tick and the tracker's reading (module docstring)."""
        self._check_open()
        self._fault_delay()
        with self._read_lock:
            with self._lock:
                k, q = self._k, self._q.copy()
                q_seen = self._hist[(k - self.latency) % (self.latency + 1)].copy()
                frozen_q = self._frozen_q
            t, tracker_t = k * self.period, (k - self.latency) * self.period
            burst = self.faults.dropout_burst
            r = self.realism
            dp = float(r.noise_pos) * self._rng.standard_normal(3)
            dw = float(r.noise_rot) * self._rng.standard_normal(3)
            lost = bool(self._rng.random() < float(r.dropout)) or (burst is not None and burst.contains(t))
            if frozen_q is not None:
                if self._frozen is None:
                    p, quat = self._pose(frozen_q, dp, dw)
                    self._frozen = _Reading(p, quat, self._frozen_k * self.period)
                f = self._frozen
                return Observation(t, q, f.position.copy(), f.quaternion.copy(), f.tracker_t, True)
            if not lost:
                p, quat = self._pose(q_seen, dp, dw)
                if np.all(np.isfinite(p)) and np.all(np.isfinite(quat)):
                    self._last = _Reading(p, quat, tracker_t)
                    return Observation(t, q, p.copy(), quat.copy(), tracker_t, True)
            last = self._last
            return Observation(t, q, last.position.copy(), last.quaternion.copy(), last.tracker_t, False)

    def move(self, target: Any) -> None:
        """Command the absolute target ``(n,)``; refused (RobotError naming the actuator, no motion) if it is
        malformed, outside the limits, or more than ``max_step`` from the actuators' current position."""
        self._check_open()
        self._fault_delay()
        try:
            u = np.asarray(target, np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise RobotError(f"move refused: target is not a vector of numbers: {target!r}") from None
        if u.shape != (self.n,):
            raise RobotError(f"move refused: target has {u.shape[0]} entries, the robot has {self.n} actuators")
        bad = np.flatnonzero(~np.isfinite(u))
        if bad.size:
            raise RobotError(f"move refused: target[{bad[0]}] is {u[bad[0]]}")
        lim = self._limits
        bad = np.flatnonzero((u < lim.lower) | (u > lim.upper))
        if bad.size:
            i = bad[0]
            raise RobotError(f"move refused: target[{i}] = {u[i]:.6g} is outside the limits "
                             f"[{lim.lower[i]:.6g}, {lim.upper[i]:.6g}]")
        with self._lock:
            step = np.abs(u - self._q)
            bad = np.flatnonzero(step > lim.max_step * (1 + 1e-9) + 1e-12)
            if bad.size:
                i = bad[0]
                raise RobotError(f"move refused: actuator {i} would step {step[i]:.6g} from {self._q[i]:.6g}, "
                                 f"more than max_step {lim.max_step[i]:.6g}")
            self._u = u

    def hold(self) -> None:
        """Stop where the actuators are now (target := current position)."""
        with self._lock:
            self._u = self._q.copy()

    def close(self) -> None:
        """Stop where it is and stop the clock (idempotent); later calls raise RobotError."""
        if self._closed:
            return
        self.hold()
        self._closed = True
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5 * self.period + 1.0)
