"""Continuous log streams -> one settled row per move, before pairing (``selfid-jax fit`` on a stream).

:func:`selfid_jax.robot.log.samples_from_table` pairs consecutive rows of a
raw time series, which is right for a log with one *settled* row per random
move. A lab's log is often a continuous stream instead: encoders and tracker
logged at a fixed rate (e.g. 100 Hz) while the arm moves, the servo lagging
its command, the tracker a frame or more late. Consecutive rows of such a log
pair into tiny samples made mostly of tracker noise and of the lag between
encoders and tracker, and the fit is wrong. This module, numpy only:

* :func:`stream_stats` / :func:`is_continuous`: tell a stream from a per-move
  log by the joint steps between consecutive rows (thresholds below).
* :func:`settled_intervals`: the runs of rows where the arm rests (joint speed
  below ``v_tol`` for at least ``min_settle_s``).
* the tracker's latency (:mod:`selfid_jax.robot.latency`, whose names are
  importable from here too): :func:`latency_estimate` / :func:`estimate_latency`
  cross-correlate the joint speed with the tracker speed; :func:`shift_tracker`
  moves the tracker columns back by a latency.
* :func:`motion_windows`: a stream without rests (the arm moving
  continuously) cut into short windows of one time length, chosen from the
  motion so that a window moves the joints about as far as a self-ID move
  (:data:`WINDOW_MOVE`); each window's joint and tracker displacement is one
  sample, about a nearly constant Jacobian.
* :func:`reduce_stream`: the entry point. A per-move log comes back unchanged;
  a stream comes back as one representative row per settled interval (or, with
  no rests, one row per window edge), so that consecutive rows pair into one
  sample per move (per window), with a :class:`StreamInfo`.

Columns are named by the caller (``t_col``, ``q_cols``, ``pose_cols``), so any
layout works. Quaternion columns (``q_w, q_x, q_y, q_z`` by default, when all
four are among ``pose_cols``) and rotation-vector columns (``r_x, r_y, r_z``)
are interpolated and averaged as rotations (sign-aligned, renormalised), the
other pose columns componentwise.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from selfid_jax.robot.fit_options import MODES as _MODES
from selfid_jax.robot.latency import (  # the latency's public names, re-exported; the shared row and rotation helpers
    LATENCY_MAX_S,
    LATENCY_MIN_CORR,
    LatencyEstimate,
    _as_2d,
    _normalise,
    _quat_to_rotvec,
    _rotvec_to_quat,
    _time,
    _usable,
    estimate_latency,
    latency_estimate,
    latency_fit,
    rotation_columns,
    shift_tracker,
)

__all__ = ["CONTINUOUS_COHERENCE", "CONTINUOUS_STILL_FRACTION", "GAP_FACTOR", "LATENCY_MAX_S", "LATENCY_MIN_CORR",
           "LATENCY_SEARCH_FRACTION",
           "NO_RESTS_ADVICE",
           "MIN_COHERENCE_PAIRS", "MIN_SETTLE_RUN_FRACTION", "MIN_SETTLE_STEPS", "MIN_STREAM_ROWS", "REF_SKIP",
           "REF_TOP_FRACTION", "SETTLE_SPEED_RATIO", "STILL_STEP_RATIO", "LatencyEstimate", "Segmentation",
           "MIN_WINDOW_STEPS", "MIN_WINDOWS", "WINDOW_EDGE_FRACTION", "WINDOW_MOVE", "NoRestsError", "Windows",
           "StreamInfo", "StreamStats", "estimate_latency", "is_continuous", "latency_estimate", "motion_windows",
           "reduce_stream", "reference", "settled_intervals", "shift_tracker", "stream_stats"]

# ------------------------------------------------------------------ detection thresholds
REF_TOP_FRACTION = 0.005
"""The reference value of a series (a full move's joint step, a move's peak speed): its largest value once the top
``REF_TOP_FRACTION`` (0.5 %) of the rows, and at least :data:`REF_SKIP` rows, are left out (:func:`reference`).
Leaving out a few rows ignores glitches; leaving out no more keeps the reference among the moving rows of a stream
that rests up to ~98 % of its rows (a move every 2 s at 100 Hz rests 96 %; below ~0.5 % moving rows the reference
falls to the noise floor: give the mode and thresholds explicitly)."""
REF_SKIP = 2
"""At least this many of the largest values are left out of the reference (two glitch rows in a short log)."""
STILL_STEP_RATIO = 0.1
"""A row step ``max_j |q_{i+1,j} - q_{i,j}|`` below this fraction of the reference step is *still* (the arm rests,
or creeps to a stop)."""
CONTINUOUS_STILL_FRACTION = 0.3
"""A log with at least this fraction of still steps is a stream. A per-move log moves every row by a full random
move: with ``dtheta ~ uniform(-m_a, m_a)`` the largest joint step of a row is below 0.1 x the reference with
probability about 0.09 for one actuator (30-row logs: 0.21 at the 99th percentile), 0.01 for two, ~1e-6 for six
(0.0 in the shipped example log, whose one zero step, a row logged twice, is screened as a duplicated stamp). The
100 Hz streams of the tests (20 ms servo) have 0.88 (a move every 0.5 s), 0.71 (every 0.2 s), 0.97 (every 2 s):
the arm rests most rows."""
CONTINUOUS_COHERENCE = 0.5
"""... or a mean cosine between consecutive non-still joint steps of at least this: a stream's steps follow one
smooth motion (a first-order servo keeps the direction of a move, cosine 1), a per-move log's are independent random
moves (mean cosine about 0, standard error ``<= 1 / sqrt(pairs)``: 0.0 in the shipped example; one-actuator logs of
30 random moves reach 0.5 about 1 % of the time). This catches a stream that rarely rests. Needs
:data:`MIN_COHERENCE_PAIRS` pairs."""
MIN_COHERENCE_PAIRS = 20
"""Fewer pairs of consecutive non-still steps than this: the coherence is not used (reported as 0)."""
MIN_STREAM_ROWS = 8
"""Fewer usable rows than this: never called a stream (too few to tell)."""
LATENCY_SEARCH_FRACTION = 0.25
"""``latency="auto"`` searches lags up to this fraction of the log's span (at least ``max_lag_s``): the speeds still
overlap over three quarters of the log there. A narrower search is fooled by a regular schedule of moves: with a
move every 0.5 s a 400 ms lag correlates at -100 ms nearly as well (0.92 against 0.95), and a lag beyond the search
was taken for its alias inside it. A peak at the edge is refused (the latency must be given)."""

# ------------------------------------------------------------------ segmentation defaults
GAP_FACTOR = 3.0
"""A step longer than this many median row intervals is a gap in the log: it never counts as rest (the arm may
have moved unseen) and is left out of the speed reference (as ``max_gap="auto"`` of the pairing)."""
SETTLE_SPEED_RATIO = 0.05
"""Default ``v_tol`` = this x the reference speed (:func:`reference` of the row speeds ``max_j |dq_j / dt|``,
actuator units / s: about a typical move's peak speed). For a first-order servo (time constant tau) the speed decays as
``exp(-t / tau)``: 5 % of the peak is reached about 3 tau after the command (the arm then lies within 5 % of the
move from its target), well above encoder noise (~1e-5 rad / 10 ms = 1e-3 rad/s vs ~0.05 rad/s for 0.03 rad moves
with tau = 20 ms)."""
MIN_SETTLE_STEPS = 4
"""Default ``min_settle_s`` is at least this many median row intervals (5 rows): a dip of one or two rows in the
speed of a moving arm is not a rest."""
MIN_SETTLE_RUN_FRACTION = 0.25
"""... and at least this fraction of the median duration of the candidate rests (runs of rows below ``v_tol``): the
real rests dominate the runs of a stream, short dips are dropped. For the test stream (0.5 s per move, 100 Hz):
``max(0.04, 0.25 x ~0.43) ~ 0.11 s``."""



# ------------------------------------------------------------------ windows (a stream without rests)
WINDOW_MOVE = 0.03
"""A stream without rests is cut into windows whose typical joint displacement (the median over windows of
``max_j |q_j(end) - q_j(start)|``, actuator units: rad, or m for a prismatic joint) is this: the online runner's
default self-ID magnitude ``m_a``, so a window is a sample like a rest-to-rest self-ID move, small enough that the
Jacobian is nearly constant over it and large enough that the tracker's noise is small beside its tracked motion
(0.1 mm against ~10 mm on a UR5e)."""
MIN_WINDOW_STEPS = 4
"""A window spans at least this many median row intervals (a faster arm gets windows of more than ``WINDOW_MOVE``)."""
MIN_WINDOWS = 2
"""A stream gives at least this many windows, or it is refused (too short, or it never moves)."""
WINDOW_EDGE_FRACTION = 0.2
"""Each window edge is the average of the rows within +- this fraction of a window of it, ``q`` and the pose over the
same rows: the tracker noise divided by the square root of their number, the two consistent to second order in the
motion (the Jacobian's change over 0.4 of a window). Consecutive edges' rows never overlap."""

NO_RESTS_ADVICE = ("A stream is read from the arm's rests between moves or, without rests, from short windows of its "
                   "motion (--mode windows); either needs the arm to move over many rows: record the moves with a rest "
                   "after each (the arm still for a few tenths of a second, as the online runner's moves are), or give "
                   "a larger settle speed (--settle-speed) or a shorter settle time (--settle-time) if it does rest. "
                   "--mode moves would pair the rows of the motion as settled moves: a wrong estimate")
"""What a stream that gives no samples can do (the messages of :func:`reduce_stream`): never ``--mode moves``, which
pairs a continuous stream's rows as if each were a settled move (on the test stream without rests:
||J Jhat - I||_F 0.45-0.78, where its windows give 0.05)."""


class NoRestsError(ValueError):
    """A stream with fewer than two settled intervals (:func:`settled_intervals`, :func:`reduce_stream`): it is read
    by windows (:func:`motion_windows`) instead where that is allowed."""


class Windows(NamedTuple):
    """A stream without rests cut into windows of one length (:func:`motion_windows`)."""

    edges: np.ndarray  # (K + 1,) times (s) of the window edges, K windows of window_s each
    window_s: float  # the window length (s)
    move: float  # the target joint displacement per window (actuator units; WINDOW_MOVE)
    median_move: float  # the median over the windows of max_j |q_j(end) - q_j(start)| (actuator units)


class StreamStats(NamedTuple):
    """The figures :func:`is_continuous` decides on (:func:`stream_stats`)."""

    rows: int  # usable rows (finite t and q, increasing t)
    still_fraction: float  # fraction of row steps below STILL_STEP_RATIO x the reference step
    coherence: float  # mean cosine of consecutive non-still joint steps (0 with fewer than MIN_COHERENCE_PAIRS)
    pairs: int  # consecutive non-still step pairs behind the coherence
    continuous: bool  # the decision


class Segmentation(NamedTuple):
    """Settled intervals of a stream (:func:`settled_intervals`); row indices into the arrays given."""

    start: np.ndarray  # (K,) int: first row of each interval
    stop: np.ndarray  # (K,) int: last row of each interval (inclusive)
    v_tol: float  # speed threshold used (actuator units / s)
    min_settle_s: float  # minimum rest duration used (s)
    v_ref: float  # the stream's reference speed (reference() of the row speeds)



class StreamInfo(NamedTuple):
    """What :func:`reduce_stream` did to a log."""

    continuous: bool  # True: reduced as a stream (one row per settled interval or window edge); False: unchanged
    mode: str  # "auto", "stream", "windows" or "moves", as asked
    detected: bool | None  # is_continuous of the log (None for mode "moves": not checked)
    rows_in: int  # rows of the table given
    rows_out: int  # rows of the table returned
    rows_dropped: int  # rows dropped before reducing (non-finite, zero quaternion, t not increasing); 0 if unchanged
    segments: int  # settled intervals found, or windows cut (rows_out, or rows_out - 1 for windows; 0 unchanged)
    still_fraction: float | None  # detection figures (StreamStats); None for mode "moves"
    coherence: float | None
    v_tol: float | None  # joint speed threshold used (actuator units / s); None if unchanged
    min_settle_s: float | None  # minimum rest duration used (s); None if unchanged
    latency_s: float | None  # tracker shift applied (s); None: none applied
    latency_estimate_s: float | None  # the estimated tracker latency (s), latency="auto" only
    latency_correlation: float | None  # its speed correlation peak
    intervals: np.ndarray  # (segments, 2) start and stop time (s) of each settled interval (or window)
    notes: tuple[str, ...]  # one line each: what was not done and why
    reading: str = "rests"  # a stream: "rests" (one row per settled interval) or "windows" (one row per window edge)
    window_s: float | None = None  # windows: their length (s), chosen from the motion (motion_windows)
    window_move: float | None = None  # windows: the median joint displacement of a window (actuator units)

    def line(self) -> str:
        """One line for the fit's report, e.g. ``a continuous stream: 2050 rows -> 41 settled rows (...)`` or
        ``a continuous stream without rests: 4030 rows -> 58 windows of 0.69 s (...)``."""
        if not self.continuous:
            why = ("as asked" if self.mode == "moves" else "not checked" if self.still_fraction is None
                   else f"still fraction {self.still_fraction:.2f} < {CONTINUOUS_STILL_FRACTION}")
            return f"per-move log ({why}): {self.rows_in} rows used as they are"
        estimate = self.latency_estimate_s
        if self.latency_s is not None:
            how = "given" if estimate is None else "estimated"
            lat = f", tracker latency {1e3 * self.latency_s:.1f} ms ({how}) taken out"
        elif estimate is not None:
            lat = (f", tracker latency estimated {1e3 * estimate:.1f} ms (corr "
                   f"{self.latency_correlation:.2f}), not taken out")
        else:
            lat = ", no tracker shift"
        if self.reading == "windows":
            return (f"a continuous stream without rests: {self.rows_in} rows -> {self.segments} windows of "
                    f"{self.window_s:.3g} s (the length at which a window moves the joints {WINDOW_MOVE:g}, a self-ID "
                    f"move m_a: median {self.window_move:.3g}), each window's joint and tracker displacement one "
                    f"sample{lat}; {self.rows_dropped} bad rows dropped first")
        return (f"a continuous stream: {self.rows_in} rows -> {self.segments} settled rows (one per rest of >= "
                f"{self.min_settle_s:.3g} s below {self.v_tol:.3g}/s){lat}; {self.rows_dropped} bad rows dropped "
                "first")


# ------------------------------------------------------------------ helpers
def reference(x: Any) -> float:
    """The largest of ``x (K,)`` once its top :data:`REF_TOP_FRACTION` (at least :data:`REF_SKIP` values, never all)
    are left out: a typical move's size or peak speed that a few glitch rows do not move. 0 for an empty ``x``."""
    x = np.sort(np.asarray(x, np.float64).ravel())[::-1]
    if x.size == 0:
        return 0.0
    return float(x[min(max(REF_SKIP, int(np.ceil(REF_TOP_FRACTION * x.size))), x.size - 1)])


# ------------------------------------------------------------------ detection
def stream_stats(t: Any, q: Any) -> StreamStats:
    """The detection figures of a log's actuator positions ``q (T, n)`` at times ``t (T,)``.

    Over the usable rows (finite, increasing ``t``), each row step's size is
    ``s_i = max_j |q_{i+1,j} - q_{i,j}|`` (independent of the log rate and of
    stamp jitter). With ``s_ref = reference(s)`` (about a full move's step;
    :data:`REF_TOP_FRACTION`), a step is still if ``s_i < STILL_STEP_RATIO s_ref``:

    * ``still_fraction``: the fraction of still steps;
    * ``coherence``: the mean cosine between consecutive non-still step vectors.

    The log is continuous iff it has at least :data:`MIN_STREAM_ROWS` rows and
    ``still_fraction >= CONTINUOUS_STILL_FRACTION`` (0.3) or (with at least
    :data:`MIN_COHERENCE_PAIRS` pairs) ``coherence >= CONTINUOUS_COHERENCE``
    (0.5); see those constants for the numbers behind them. A log whose joints
    never move is not continuous.
    """
    t = _time(t)
    q = _as_2d("q", q, t.shape[0])
    keep = _usable(t, q)
    q = q[keep]
    rows = int(q.shape[0])
    if rows < 2:
        return StreamStats(rows, 0.0, 0.0, 0, False)
    dq = np.diff(q, axis=0)
    s = np.abs(dq).max(axis=1)
    s_ref = reference(s)
    if not s_ref > 0:
        return StreamStats(rows, 1.0, 0.0, 0, False)
    still = s < STILL_STEP_RATIO * s_ref
    still_fraction = float(still.mean())
    both = ~still[1:] & ~still[:-1]
    pairs = int(both.sum())
    coherence = 0.0
    if pairs >= MIN_COHERENCE_PAIRS:
        a, b = dq[:-1][both], dq[1:][both]
        cos = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        coherence = float(cos.mean())
    continuous = rows >= MIN_STREAM_ROWS and (still_fraction >= CONTINUOUS_STILL_FRACTION
                                              or (pairs >= MIN_COHERENCE_PAIRS and coherence >= CONTINUOUS_COHERENCE))
    return StreamStats(rows, still_fraction, coherence, pairs, bool(continuous))


def is_continuous(t: Any, q: Any) -> bool:
    """Whether ``q (T, n)`` at times ``t (T,)`` is a continuous stream (many still rows, or smoothly consecutive
    steps) rather than one settled row per move; thresholds in :func:`stream_stats`."""
    return stream_stats(t, q).continuous


# ------------------------------------------------------------------ segmentation
def settled_intervals(t: Any, q: Any, *, v_tol: float | None = None, min_settle_s: float | None = None
                      ) -> Segmentation:
    """The runs of rows where the arm rests, from actuator positions ``q (T, n)`` at increasing times ``t (T,)``.

    The joint speed of the step from row ``i`` to ``i + 1`` is
    ``max_j |q_{i+1,j} - q_{i,j}| / (t_{i+1} - t_i)`` (actuator units / s). A
    settled interval is a maximal run of rows ``a..b`` whose every step is
    slower than ``v_tol`` and no longer than :data:`GAP_FACTOR` median row
    intervals, lasting ``t_b - t_a >= min_settle_s``. Its last row ``b`` is the
    last one before the arm moves again.

    Defaults (from the data): ``v_tol = SETTLE_SPEED_RATIO (0.05) x v_ref``,
    ``v_ref = reference(speeds)`` (:data:`REF_TOP_FRACTION`: the largest speed
    once the top 0.5 % of the rows are left out, about a typical move's peak
    speed); ``min_settle_s = max(MIN_SETTLE_STEPS (4) x median row interval,
    MIN_SETTLE_RUN_FRACTION (0.25) x median duration of the runs below v_tol)``.

    Raises:
      NoRestsError: no settled interval (the message gives the figures to change).
      ValueError: rows not finite or not increasing, joints that never move.
    """
    t = _time(t)
    q = _as_2d("q", q, t.shape[0])
    if t.shape[0] < 3:
        raise ValueError(f"a stream needs at least 3 rows to find settled intervals, got {t.shape[0]}")
    if not (np.isfinite(t).all() and np.isfinite(q).all()):
        raise ValueError("settled_intervals: t and q must be finite (screen the rows first)")
    dt = np.diff(t)
    if not (dt > 0).all():
        raise ValueError(f"settled_intervals: t must increase (row {int(np.argmin(dt > 0)) + 1} does not)")
    dt_med = float(np.median(dt))
    speed = np.abs(np.diff(q, axis=0)).max(axis=1) / dt
    ok = dt <= GAP_FACTOR * dt_med
    v_ref = reference(speed[ok]) if ok.any() else 0.0
    if v_tol is None:
        if not v_ref > 0:
            raise ValueError("no settled interval can be told from the moves: the joints never move (every joint "
                             "speed is 0); is this a stream of a robot making moves?")
        v_tol = SETTLE_SPEED_RATIO * v_ref
    elif not (np.isfinite(v_tol) and v_tol > 0):
        raise ValueError(f"v_tol (settle speed) must be a positive number (actuator units / s), got {v_tol!r}")
    rest = (speed < v_tol) & ok
    # runs of rest steps [a, b) -> rows a..b
    edges = np.diff(np.concatenate([[0], rest.astype(np.int8), [0]]))
    run_a, run_b = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    durations = t[run_b] - t[run_a]
    if min_settle_s is None:
        min_settle_s = MIN_SETTLE_STEPS * dt_med
        if durations.size:
            min_settle_s = max(min_settle_s, MIN_SETTLE_RUN_FRACTION * float(np.median(durations)))
    elif not (np.isfinite(min_settle_s) and min_settle_s >= 0):
        raise ValueError(f"min_settle_s (settle time) must be a non-negative number of seconds, got {min_settle_s!r}")
    long = durations >= min_settle_s * (1 - 1e-9)
    if not long.any():
        longest = f"{float(durations.max()):.3g} s" if durations.size else "none"
        raise NoRestsError(
            f"no settled interval found: the joint speed (max over joints of |dq/dt|) never stays below "
            f"v_tol={v_tol:.3g}/s for min_settle_s={min_settle_s:.3g} s (lowest speed {float(speed[ok].min()):.3g}/s, "
            f"typical move speed {v_ref:.3g}/s, longest rest {longest}); does the arm rest between moves? "
            f"{NO_RESTS_ADVICE}")
    return Segmentation(run_a[long].astype(np.int64), run_b[long].astype(np.int64), float(v_tol),
                        float(min_settle_s), v_ref)


def _window_move(t: np.ndarray, q: np.ndarray, lo: float, window_s: float, count: int) -> np.ndarray:
    """``(count,)``: ``max_j |q_j(lo + (k + 1) w) - q_j(lo + k w)|`` of windows ``k`` (``q`` interpolated)."""
    edges = lo + window_s * np.arange(count + 1)
    qe = np.stack([np.interp(edges, t, q[:, j]) for j in range(q.shape[1])], axis=1)
    return np.abs(np.diff(qe, axis=0)).max(axis=1)


def motion_windows(t: Any, q: Any, *, move: float = WINDOW_MOVE, lo: float | None = None, hi: float | None = None
                   ) -> Windows:
    """A stream's time span ``[lo, hi]`` (default: all of ``t``) cut into windows of one length, chosen so that a
    window moves the joints ``q (T, n)`` (at increasing times ``t (T,)``, s) about ``move`` (actuator units).

    A window's move is ``max_j |q_j(end) - q_j(start)|`` (``q`` interpolated
    linearly at the edges). The length ``w`` starts at ``move`` over the mean
    joint speed (``max_j |dq_j/dt|`` over the steps that are no gap,
    :data:`GAP_FACTOR`) and is rescaled by ``move / median move`` until the
    median move of the windows is within 5 % of ``move`` (at most 8 rounds, at
    most 4x per round: a random walk's move grows as ``sqrt(w)``, a straight
    motion's as ``w``); ``w`` is kept within ``MIN_WINDOW_STEPS`` (4) median
    row intervals and a :data:`MIN_WINDOWS` th of the span. The edges are
    ``lo + k w``, ``k = 0..K`` with ``K = floor((hi - lo) / w)``.

    Raises:
      NoRestsError: fewer than :data:`MIN_WINDOWS` windows fit in the span, or the joints never move in it.
    """
    t = _time(t)
    q = _as_2d("q", q, t.shape[0])
    if not (np.isfinite(move) and move > 0):
        raise ValueError(f"move (a window's joint displacement) must be a positive number, got {move!r}")
    lo = float(t[0]) if lo is None else float(lo)
    hi = float(t[-1]) if hi is None else float(hi)
    dt = np.diff(t)
    span = hi - lo
    dt_med = float(np.median(dt)) if dt.size else 0.0
    speed = np.abs(np.diff(q, axis=0)).max(axis=1) / np.where(dt > 0, dt, np.inf)
    inside = (t[:-1] >= lo) & (t[1:] <= hi) & (dt <= GAP_FACTOR * dt_med)
    mean_speed = float(speed[inside].mean()) if inside.any() else 0.0
    shortest = MIN_WINDOW_STEPS * dt_med
    if not (dt_med > 0 and span >= MIN_WINDOWS * shortest and mean_speed > 0):
        raise NoRestsError(f"no windows of its motion can be cut: {span:.3g} s of the stream "
                           f"({int(inside.sum())} row steps) with a mean joint speed of {mean_speed:.3g}/s, where "
                           f"{MIN_WINDOWS} windows of at least {MIN_WINDOW_STEPS} rows of motion are needed")
    longest = span / MIN_WINDOWS
    w = float(np.clip(move / mean_speed, shortest, longest))
    median = 0.0
    for _ in range(8):
        median = float(np.median(_window_move(t, q, lo, w, int(np.floor(span / w + 1e-9)))))
        if not median > 0:
            break
        scale = float(np.clip(move / median, 0.25, 4.0))
        new = float(np.clip(w * scale, shortest, longest))
        if abs(median / move - 1.0) <= 0.05 or new == w:
            break
        w = new
    count = int(np.floor(span / w + 1e-9))
    median = float(np.median(_window_move(t, q, lo, w, count)))
    if not median > 0:
        raise NoRestsError(f"no windows of its motion can be cut: the joints do not move between {lo:.3f} and "
                           f"{hi:.3f} s")
    return Windows(lo + w * np.arange(count + 1), w, float(move), median)


def _average(q: np.ndarray, pose: np.ndarray, qi: Sequence[int], ri: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """The mean of rows ``q (k, n)`` and ``pose (k, d)``; the pose's quaternion columns ``qi`` (w, x, y, z) and
    rotation-vector columns ``ri`` averaged as rotations (sign-aligned to the last row's, renormalised)."""
    q_mean, pose_mean = q.mean(axis=0), pose.mean(axis=0)
    for cols, to_q, back in ((qi, _normalise, _normalise), (ri, _rotvec_to_quat, _quat_to_rotvec)):
        if cols:
            quats = to_q(pose[:, list(cols)])
            quats = np.where((quats @ quats[-1] < 0)[:, None], -quats, quats)
            pose_mean[list(cols)] = back(_normalise(quats.mean(axis=0)))
    return q_mean, pose_mean


# ------------------------------------------------------------------ the entry point
def _column(table: Mapping[str, Any], name: str, rows: int) -> np.ndarray:
    if name not in table.keys():
        raise ValueError(f"column {name} is missing (have {', '.join(map(str, list(table.keys())[:12]))})")
    raw = np.asarray(table[name])
    if raw.ndim != 1 or raw.shape[0] != rows:
        raise ValueError(f"column {name} has shape {raw.shape}, expected ({rows},) like the other columns")
    try:
        return raw.astype(np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"column {name} holds entries that are not numbers") from None


def reduce_stream(
    table: Mapping[str, Any],
    q_cols: Sequence[str],
    pose_cols: Sequence[str],
    *,
    t_col: str = "t",
    mode: str = "auto",
    latency: str | float | None = "auto",
    v_tol: float | None = None,
    min_settle_s: float | None = None,
    quat_cols: Sequence[str] | None = None,
    rotvec_cols: Sequence[str] | None = None,
    max_lag_s: float = LATENCY_MAX_S,
) -> tuple[dict[str, np.ndarray], StreamInfo]:
    """A raw time series as the pairing wants it: one settled row per move (or per window edge). Returns
    ``(table, info)``.

    ``mode``: ``"auto"`` reduces the log if :func:`is_continuous` (on ``t_col``
    and ``q_cols``) says it is a stream and returns it unchanged otherwise;
    ``"stream"`` always reduces; ``"windows"`` always reduces, by windows
    (step 5) even where the arm rests; ``"moves"`` never reduces (the table
    comes back as it is, columns as numpy arrays, its bad rows left to the
    pairing's screens).

    Reducing a stream:

    1. Rows with a non-finite ``t``/``q``/pose entry, a zero quaternion or a
       time not after the previous kept row's are dropped (``rows_dropped``).
    2. ``latency``: ``"auto"`` estimates the tracker latency
       (:func:`latency_estimate` for a stream with rests, :func:`latency_fit`
       for one read by windows; over ``+-max(max_lag_s, LATENCY_SEARCH_FRACTION x the log's span)``, on the
       position columns or, without any, all pose columns) and shifts the
       pose columns by it (:func:`shift_tracker`) when the correlation peak
       reaches :data:`LATENCY_MIN_CORR`; a number shifts by that many seconds;
       None shifts nothing.
    3. :func:`settled_intervals` with ``v_tol`` (actuator units / s) and
       ``min_settle_s`` (s), defaults from the data (see there).
    4. Each interval gives one row: ``t`` of its last row (the arm's settled
       time before the next move), and ``q`` and the pose averaged over the
       interval's second half (rows at ``t >= (t_start + t_stop) / 2``). The
       second half keeps clear of the end of the previous move and of a
       tracker still catching up, and averaging ``k`` rows divides the tracker
       noise by ``sqrt(k)`` (20 rows: 4.5x less than the last row alone);
       ``q`` and the pose are averaged over the same rows, so a pair stays
       consistent even if the arm still creeps. Quaternions are sign-aligned to
       the interval's last row, averaged and renormalised (rotation vectors via
       quaternions). Any other column takes its value at the interval's last row.
       Only rows the latency shift leaves a pose for are averaged (the
       shifted pose is held past the log's end): a rest with none gives no row
       (noted).
    5. A stream with fewer than two settled intervals (the arm moving without
       rests; a forced ``"stream"`` on a log that does not look like one is
       refused instead) is cut into windows of one length
       (:func:`motion_windows`: a window moves the joints about
       :data:`WINDOW_MOVE`, a self-ID move), within the rows the latency shift
       left defined. Each window edge gives one row: ``q`` and the (shifted)
       pose averaged over the rows within ``WINDOW_EDGE_FRACTION`` (0.2) of a
       window of it, ``t`` their mean time, other columns at the row nearest
       the edge. Consecutive rows then pair into one sample per window: its
       joint and tracker displacement, about a nearly constant Jacobian.

    Consecutive returned rows then pair into one sample per move
    (:func:`selfid_jax.robot.log.samples_from_table`).

    Raises:
      NoRestsError: (reducing) a stream too short or too still for two windows.
      ValueError: an unknown mode or option, a missing or non-numeric column,
        an estimated latency at the edge of the search; one line that says
        which figure to change.
    """
    if mode not in _MODES:
        raise ValueError(f"stream mode must be one of {', '.join(_MODES)}, got {mode!r}")
    if not (latency is None or latency == "auto" or (isinstance(latency, (int, float, np.floating))
                                                      and not isinstance(latency, bool) and np.isfinite(latency))):
        raise ValueError(f"latency must be 'auto', a number of seconds or None, got {latency!r}")
    names = [str(c) for c in table.keys()]
    rows = int(np.shape(table[names[0]])[0]) if names and np.ndim(table[names[0]]) >= 1 else 0
    unchanged = {c: np.asarray(table[c]) for c in names}
    empty = np.zeros((0, 2))
    if mode == "moves":
        return unchanged, StreamInfo(False, mode, None, rows, rows, 0, 0, None, None, None, None, None, None, None,
                                     empty, ())
    q_cols, pose_cols = [str(c) for c in q_cols], [str(c) for c in pose_cols]
    if not q_cols:
        raise ValueError("reduce_stream: no actuator (q) columns given")
    if not pose_cols:
        raise ValueError("reduce_stream: no pose columns given")
    try:
        if rows <= 0:
            raise ValueError("reduce_stream: the table has no rows")
        t = _column(table, t_col, rows)
        q = np.stack([_column(table, c, rows) for c in q_cols], axis=1)
    except ValueError as err:
        if mode in ("stream", "windows"):
            raise
        # auto: a log that cannot be checked is left to the pairing's screens, whose messages name file and line
        return unchanged, StreamInfo(False, mode, None, rows, rows, 0, 0, None, None, None, None, None, None, None,
                                     empty, (f"not checked for a stream: {err}",))
    stats = stream_stats(t, q)
    if mode == "auto" and not stats.continuous:
        return unchanged, StreamInfo(False, mode, False, rows, rows, 0, 0, stats.still_fraction, stats.coherence,
                                     None, None, None, None, None, empty, ())

    # ---- reduce
    quat_c, rotvec_c = rotation_columns(pose_cols, quat_cols, rotvec_cols)
    pose = np.stack([_column(table, c, rows) for c in pose_cols], axis=1)
    screened = pose
    if quat_c:  # a zero quaternion is a bad row, as a non-finite entry
        qi = [pose_cols.index(c) for c in quat_c]
        zero = np.linalg.norm(np.where(np.isfinite(pose[:, qi]), pose[:, qi], 0.0), axis=1) <= 1e-6
        screened = np.where(zero[:, None], np.nan, pose)
    idx = np.flatnonzero(_usable(t, q, screened))
    if idx.size < 3:
        raise ValueError(f"reduce_stream: {idx.size} usable rows (finite, increasing {t_col}); a stream needs many")
    t_k, q_k, pose_k = t[idx], q[idx], pose[idx]
    notes: list[str] = []

    seg: Segmentation | None = None
    if mode != "windows":
        try:
            seg = settled_intervals(t_k, q_k, v_tol=v_tol, min_settle_s=min_settle_s)
            if seg.start.shape[0] < 2:
                raise NoRestsError(
                    f"only one settled interval found (t = {t_k[seg.start[0]]:.3f} to {t_k[seg.stop[0]]:.3f} s, joint "
                    f"speed below v_tol={seg.v_tol:.3g}/s for >= {seg.min_settle_s:.3g} s); a sample needs two")
        except NoRestsError as err:
            if mode == "stream" and not stats.continuous:  # forced: the log may be one settled row per move
                raise ValueError(f"{err} (--mode stream was asked, but the log does not look like a stream: if it "
                                 "holds one settled row per move, read it with --mode auto)") from None
            given = ", ".join(f"{name} {value:g}{unit}" for name, value, unit in
                              (("--settle-speed", v_tol, "/s"), ("--settle-time", min_settle_s, " s"))
                              if value is not None)
            notes.append(f"fewer than two rests{' at ' + given if given else ''}: read by windows of its motion")
            seg = None
        except ValueError as err:
            if mode == "stream" and not stats.continuous:
                raise ValueError(f"{err} (--mode stream was asked, but the log does not look like a stream: if it "
                                 "holds one settled row per move, read it with --mode auto)") from None
            raise

    if seg is None:  # too short or too still for windows: refused before the latency is looked for
        try:
            motion_windows(t_k, q_k)
        except NoRestsError as err:
            raise NoRestsError(f"{err}. {NO_RESTS_ADVICE}") from None
    latency_s: float | None = None
    est: LatencyEstimate | None = None
    if latency == "auto":
        rot = set(quat_c) | set(rotvec_c)
        pos = [j for j, c in enumerate(pose_cols) if c not in rot] or list(range(len(pose_cols)))
        # the search covers what the log can show: lags up to a quarter of it (three quarters overlap), not only
        # max_lag_s; a periodic schedule of moves makes a lag beyond a narrower search look like one inside it
        search = max(float(max_lag_s), LATENCY_SEARCH_FRACTION * float(t_k[-1] - t_k[0]))
        try:
            how = latency_estimate if seg is not None else latency_fit  # no rests: the speed is too smooth to time
            est = how(t_k, q_k, pose_k[:, pos], max_lag_s=search)
        except ValueError as err:
            if "edge of the search" in str(err):
                raise ValueError(f"the tracker latency is beyond what the log can show (its best match lies at the "
                                 f"edge of a +-{search:.3g} s search, a quarter of the log): give it, "
                                 f"--latency S (latency=S, seconds), or --latency none; {err}") from None
            notes.append(f"tracker latency not estimated ({err}); no shift applied")
        else:
            if est.correlation >= LATENCY_MIN_CORR:
                latency_s = est.seconds
            else:
                what = "speed correlation" if seg is not None else "velocity fit's correlation"
                notes.append(f"tracker latency estimate {1e3 * est.seconds:.1f} ms not used: {what} "
                             f"{est.correlation:.2f} < {LATENCY_MIN_CORR}; no shift applied")
    elif latency is not None:
        latency_s = float(latency)  # checked above: a number
    if latency_s is not None and latency_s != 0.0:
        shifted = shift_tracker(t_k, {c: pose_k[:, j] for j, c in enumerate(pose_cols)}, latency_s,
                                quat_cols=quat_c, rotvec_cols=rotvec_c)
        pose_k = np.stack([shifted[c] for c in pose_cols], axis=1)

    qi = [pose_cols.index(c) for c in quat_c]
    ri = [pose_cols.index(c) for c in rotvec_c]
    rows_used: list[tuple[int, int]] = []  # (first, last + 1) row of t_k averaged into each output row
    pick: list[int] = []  # the row of t_k whose other columns each output row takes
    windows: Windows | None = None
    shift = 0.0 if latency_s is None else latency_s
    lo, hi = float(t_k[0]) + max(0.0, -shift), float(t_k[-1]) - max(0.0, shift)  # a shifted pose is held beyond
    if seg is not None:
        inside = []
        for a, b in zip(seg.start, seg.stop):
            first = int(a + np.searchsorted(t_k[a:b + 1], max(0.5 * (t_k[a] + t_k[b]), lo), side="left"))
            end = int(a + np.searchsorted(t_k[a:b + 1], hi, side="right"))
            if end > first:  # a rest whose second half the latency shift left undefined gives no row
                rows_used.append((first, end))
                pick.append(int(b))
                inside.append(True)
            else:
                inside.append(False)
        keep_seg = np.asarray(inside)
        if not keep_seg.all():
            notes.append(f"{int((~keep_seg).sum())} rests beyond the rows the tracker latency "
                         f"({1e3 * shift:.0f} ms) leaves a pose for: not used")
        if keep_seg.sum() < 2:
            raise NoRestsError(f"only {int(keep_seg.sum())} rests within the rows the tracker latency "
                               f"({1e3 * shift:.0f} ms) leaves a pose for; a sample needs two. {NO_RESTS_ADVICE}")
        intervals = np.stack([t_k[seg.start], t_k[seg.stop]], axis=1)[keep_seg]
    else:
        try:
            windows = motion_windows(t_k, q_k, lo=lo, hi=hi)
        except NoRestsError as err:
            raise NoRestsError(f"{err}. {NO_RESTS_ADVICE}") from None
        h = WINDOW_EDGE_FRACTION * windows.window_s
        kept = []
        for e in windows.edges:
            a = int(np.searchsorted(t_k, max(e - h, lo), side="left"))
            b = int(np.searchsorted(t_k, min(e + h, hi), side="right"))
            if b > a:  # no row near this edge (a gap): its two windows pair as one
                rows_used.append((a, b))
                pick.append(int(a + np.argmin(np.abs(t_k[a:b] - e))))
                kept.append(e)
        edges = np.asarray(kept)
        intervals = np.stack([edges[:-1], edges[1:]], axis=1) if edges.size >= 2 else np.zeros((0, 2))
        if len(rows_used) < MIN_WINDOWS + 1:
            raise NoRestsError(f"only {len(rows_used)} window edges have rows near them; {NO_RESTS_ADVICE}")
    K = len(rows_used)
    q_out = np.empty((K, q_k.shape[1]))
    pose_out = np.empty((K, pose_k.shape[1]))
    t_out = np.empty(K)
    for k, (a, b) in enumerate(rows_used):
        q_out[k], pose_out[k] = _average(q_k[a:b], pose_k[a:b], qi, ri)
        t_out[k] = t_k[pick[k]] if windows is None else float(t_k[a:b].mean())
    last = idx[np.asarray(pick, np.int64)]
    out: dict[str, np.ndarray] = {}
    for c in names:
        if c == t_col:
            out[c] = t_out
        elif c in q_cols:
            out[c] = q_out[:, q_cols.index(c)]
        elif c in pose_cols:
            out[c] = pose_out[:, pose_cols.index(c)]
        else:
            out[c] = unchanged[c][last]
    info = StreamInfo(
        continuous=True, mode=mode, detected=stats.continuous, rows_in=rows, rows_out=K,
        rows_dropped=int(rows - idx.size), segments=K if windows is None else K - 1,
        still_fraction=stats.still_fraction, coherence=stats.coherence,
        v_tol=None if seg is None else seg.v_tol, min_settle_s=None if seg is None else seg.min_settle_s,
        latency_s=latency_s, latency_estimate_s=None if est is None else est.seconds,
        latency_correlation=None if est is None else est.correlation,
        intervals=intervals, notes=tuple(notes), reading="rests" if windows is None else "windows",
        window_s=None if windows is None else windows.window_s,
        window_move=None if windows is None else windows.median_move)
    return out, info
