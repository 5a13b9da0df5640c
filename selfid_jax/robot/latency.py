"""Tracker latency in a continuous log stream: how late the tracker is, and its columns moved back by that much.

A lab's tracker reports a pose a frame or more after the encoders report the
joints that make it. :func:`latency_estimate` finds that lag by
cross-correlating the joint speed with the tracker speed (a stream of moves
and rests); :func:`latency_fit` by the lag at which one linear map best
explains the tracker velocity from the joint velocity (continuous motion,
whose speed is too smooth to time);
:func:`shift_tracker` moves the tracker columns back by a latency (positions
interpolated componentwise, quaternions and rotation vectors as rotations).
:func:`selfid_jax.robot.streams.reduce_stream` uses both before it cuts a
stream into settled moves. Also here: the row screens and the numpy rotation
helpers both modules share. numpy only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

__all__ = ["LATENCY_MAX_S", "LATENCY_MIN_CORR", "LatencyEstimate", "estimate_latency", "latency_estimate",
           "latency_fit", "rotation_columns", "shift_tracker"]

LATENCY_MAX_S = 0.25
"""Largest tracker latency searched for by default (s, either sign); lab trackers lag 5-100 ms."""
LATENCY_MIN_CORR = 0.5
"""``latency="auto"`` shifts the tracker only where the speed correlation peak reaches this (else no shift, noted)."""
_QUATERNION = ("q_w", "q_x", "q_y", "q_z")
_ROTVEC = ("r_x", "r_y", "r_z")


class LatencyEstimate(NamedTuple):
    """How late the tracker is (:func:`latency_estimate`)."""

    seconds: float  # tracker lag behind the encoders (s); positive: the tracker reports a pose late
    correlation: float  # normalised correlation of joint speed and tracker speed at the peak (-1..1)
    grid_dt: float  # the uniform grid step the speeds were compared on (s)


# ------------------------------------------------------------------ row screens and rotations (streams' too)
def _usable(t: np.ndarray, *arrays: np.ndarray) -> np.ndarray:
    """Row mask: finite ``t`` and arrays, and ``t`` after every earlier kept row's (duplicates and
    non-monotonic stamps dropped, as the pairing's screens)."""
    keep = np.isfinite(t)
    for a in arrays:
        keep &= np.isfinite(a).all(axis=1) if a.ndim == 2 else np.isfinite(a)
    prev = np.maximum.accumulate(np.where(keep, t, -np.inf))
    prev = np.concatenate([[-np.inf], prev[:-1]])
    return keep & (t > prev)


def _as_2d(name: str, a: Any, rows: int | None = None) -> np.ndarray:
    a = np.asarray(a, np.float64)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or (rows is not None and a.shape[0] != rows):
        raise ValueError(f"{name}: expected shape ({rows if rows is not None else 'T'}, k), got {a.shape}")
    return a


def _time(t: Any) -> np.ndarray:
    t = np.asarray(t, np.float64)
    if t.ndim != 1:
        raise ValueError(f"t: expected shape (T,), got {t.shape}")
    return t


def _normalise(quat: np.ndarray) -> np.ndarray:
    return quat / np.linalg.norm(quat, axis=-1, keepdims=True)


def _continuous_signs(quat: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(K, 4)`` with signs flipped so consecutive ones lie in one hemisphere (q and -q are one
    rotation), so componentwise interpolation follows the short way."""
    quat = _normalise(quat)
    if quat.shape[0] < 2:
        return quat
    flip = np.concatenate([[False], np.einsum("ij,ij->i", quat[1:], quat[:-1]) < 0])
    sign = np.where(np.logical_xor.accumulate(flip), -1.0, 1.0)
    return quat * sign[:, None]


def _rotvec_to_quat(r: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * theta
    scale = np.where(theta > 1e-8, np.sin(half) / np.where(theta > 1e-8, theta, 1.0), 0.5 - theta**2 / 48.0)
    return np.concatenate([np.cos(half), scale * r], axis=-1)


def _quat_to_rotvec(quat: np.ndarray) -> np.ndarray:
    quat = _normalise(quat)
    quat = np.where(quat[..., :1] < 0, -quat, quat)  # w >= 0: angle in [0, pi]
    w, v = quat[..., :1], quat[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    theta = 2.0 * np.arctan2(s, w)
    scale = np.where(s > 1e-8, theta / np.where(s > 1e-8, s, 1.0), 2.0 / np.maximum(w, 1e-300))
    return scale * v


# ------------------------------------------------------------------ latency
def _uniform(t: np.ndarray, x: np.ndarray, grid: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(grid, t, x[:, j]) for j in range(x.shape[1])], axis=1)


def latency_estimate(t: Any, q: Any, p: Any, *, max_lag_s: float = LATENCY_MAX_S) -> LatencyEstimate:
    """How many seconds the tracker ``p (T, d)`` lags the encoders ``q (T, n)``, both at times ``t (T,)``.

    Both are resampled (linear interpolation) onto a uniform grid of the
    median row interval, so jittered stamps are fine; the joint speed norm
    ``|dq/dt|`` and the tracker speed norm ``|dp/dt|`` (each minus its mean)
    are cross-correlated (normalised over the overlap) at integer lags within
    ``+-max_lag_s`` (at most a quarter of the log), and the peak is refined to a
    fraction of a step by the parabola through it and its neighbours. Positive:
    the tracker reports a pose later than the encoders report the joints that
    make it. Where the motion is a series of moves with the same shape, the
    correlation is symmetric about the true lag, so the parabola is unbiased.

    Raises:
      ValueError: too few rows, joints or tracker that never move, or a peak at
        the edge of the search (the lag may exceed ``max_lag_s``).
    """
    q_rate, p_rate, dt = _grid_rates(t, q, p)
    if not (np.isfinite(max_lag_s) and max_lag_s > 0):
        raise ValueError(f"max_lag_s must be a positive number of seconds, got {max_lag_s!r}")
    a = np.linalg.norm(q_rate, axis=1)
    b = np.linalg.norm(p_rate, axis=1)
    a, b = a - a.mean(), b - b.mean()
    if not (np.abs(a).max() > 0):
        raise ValueError("latency: the joints never move (constant speed), nothing to correlate")
    if not (np.abs(b).max() > 0):
        raise ValueError("latency: the tracker never moves (constant speed), nothing to correlate")
    N = a.shape[0]
    K = max(1, min(int(round(max_lag_s / dt)), N // 4))
    lags = np.arange(-K, K + 1)
    c = _correlation(a, b, K)
    i = int(np.argmax(c))
    if i in (0, lags.shape[0] - 1):
        raise ValueError(f"latency: the speed correlation peaks at the edge of the search ({lags[i] * dt:+.3g} s, "
                         f"max_lag_s={max_lag_s:.3g}); the tracker may lag more: give a larger max_lag_s or the "
                         f"latency itself")
    den = c[i - 1] - 2.0 * c[i] + c[i + 1]
    frac = 0.5 * (c[i - 1] - c[i + 1]) / den if den < 0 else 0.0
    frac = float(np.clip(frac, -0.5, 0.5))
    return LatencyEstimate(float((lags[i] + frac) * dt), float(c[i]), dt)


def _grid_rates(t: Any, q: Any, p: Any) -> tuple[np.ndarray, np.ndarray, float]:
    """Joint and tracker rates ``(N, n)``, ``(N, d)`` (per s) on a uniform grid of the median row interval (linear
    interpolation of the usable rows), and that interval."""
    t = _time(t)
    q = _as_2d("q", q, t.shape[0])
    p = _as_2d("p", p, t.shape[0])
    keep = _usable(t, q, p)
    t, q, p = t[keep], q[keep], p[keep]
    if t.shape[0] < 8:
        raise ValueError(f"latency: {t.shape[0]} usable rows; need at least 8")
    dt = float(np.median(np.diff(t)))
    n = int(np.floor((t[-1] - t[0]) / dt + 1e-9)) + 1
    grid = t[0] + dt * np.arange(n)
    uniform = np.abs(np.diff(t) - dt).max() <= 1e-6 * dt
    qg, pg = (q, p) if uniform and n == t.shape[0] else (_uniform(t, q, grid), _uniform(t, p, grid))
    return np.diff(qg, axis=0) / dt, np.diff(pg, axis=0) / dt, dt


def latency_fit(t: Any, q: Any, p: Any, *, max_lag_s: float = LATENCY_MAX_S) -> LatencyEstimate:
    """How many seconds the tracker ``p (T, d)`` lags the encoders ``q (T, n)``, both at times ``t (T,)``: the lag at
    which one linear map best explains the tracker velocity from the joint velocity.

    Both are resampled onto a uniform grid of the median row interval; with
    rates ``a_i = dq/dt (n,)`` and ``b_i = dp/dt (d,)``, each integer lag ``k``
    within ``+-max_lag_s`` (at most a quarter of the log) gets the least-squares
    map ``F_k`` of ``b_{i+k} ~ F_k a_i`` over the overlap and its residual
    fraction ``f_k = sum |b_{i+k} - F_k a_i|^2 / sum |b_{i+k}|^2``. The lag of
    the least ``f_k`` (refined by the parabola through it and its neighbours)
    is the latency; ``correlation`` is ``sqrt(1 - f_k)`` there (the multiple
    correlation, 1 for a tracker explained exactly). The sums over every lag
    come from prefix sums and ``n d`` FFT cross-correlations, so a search over
    a quarter of an hour-long log is cheap. Unlike the speed correlation of
    :func:`latency_estimate`, it uses the direction of the motion, not only its
    speed: a smooth continuous motion's speed changes too slowly to time a lag
    (on the sum-of-sines test motion the speed correlation was off by -15 to
    +50 ms, this by under a frame). The map is one over the whole log, so the
    motion should stay near one configuration (as self-ID's does).

    Raises:
      ValueError: too few rows, joints or tracker that never move, or a least
        residual at the edge of the search (the lag may exceed ``max_lag_s``).
    """
    if not (np.isfinite(max_lag_s) and max_lag_s > 0):
        raise ValueError(f"max_lag_s must be a positive number of seconds, got {max_lag_s!r}")
    a, b, dt = _grid_rates(t, q, p)
    if not (np.abs(a).max() > 0):
        raise ValueError("latency: the joints never move, nothing to time")
    if not (np.abs(b).max() > 0):
        raise ValueError("latency: the tracker never moves, nothing to time")
    N, n = a.shape
    K = max(1, min(int(round(max_lag_s / dt)), N // 4))
    lags = np.arange(-K, K + 1)
    k = np.abs(lags)
    pos = lags >= 0
    # pairs (a_i, b_{i+k}): k >= 0: i in [0, N - k); k < 0: i in [k, N) (k = |lag|)
    ca = np.concatenate([np.zeros((1, n, n)), np.cumsum(a[:, :, None] * a[:, None, :], axis=0)])
    A = np.where(pos[:, None, None], ca[N - k], ca[N] - ca[k])
    cb = np.concatenate([[0.0], np.cumsum((b * b).sum(axis=1))])
    C = np.where(pos, cb[N] - cb[k], cb[N - k])
    size = 1 << int(np.ceil(np.log2(2 * N)))
    fa, fb = np.fft.rfft(a, size, axis=0), np.fft.rfft(b, size, axis=0)
    r = np.fft.irfft(np.conj(fa)[:, :, None] * fb[:, None, :], size, axis=0)  # r[k mod size, j, l] = sum a_ij b_i+k,l
    B = r[lags % size]  # (2K + 1, n, d)
    ridge = 1e-12 * np.trace(A, axis1=1, axis2=2)[:, None, None] * np.eye(n) + 1e-300 * np.eye(n)
    X = np.linalg.solve(A + ridge, B)
    explained = np.einsum("kjl,kjl->k", B, X)
    f = np.where(C > 0, np.clip(1.0 - explained / np.where(C > 0, C, 1.0), 0.0, 1.0), 1.0)
    i = int(np.argmin(f))
    if i in (0, lags.shape[0] - 1):
        raise ValueError(f"latency: the tracker velocity is best explained at the edge of the search "
                         f"({lags[i] * dt:+.3g} s, max_lag_s={max_lag_s:.3g}); the tracker may lag more: give a larger "
                         "max_lag_s or the latency itself")
    den = f[i - 1] - 2.0 * f[i] + f[i + 1]
    frac = float(np.clip(-0.5 * (f[i + 1] - f[i - 1]) / den, -0.5, 0.5)) if den > 0 else 0.0
    return LatencyEstimate(float((lags[i] + frac) * dt), float(np.sqrt(1.0 - f[i])), dt)


def _correlation(a: np.ndarray, b: np.ndarray, K: int) -> np.ndarray:
    """``c (2K + 1,)``: ``c[K + k] = corr(a[i], b[i + k])`` normalised over the overlap, lags ``-K..K`` (``K < N``),
    by FFT (a search over a quarter of an hour-long 100 Hz log is 90,000 lags)."""
    N = a.shape[0]
    n = 1 << int(np.ceil(np.log2(2 * N)))
    r = np.fft.irfft(np.conj(np.fft.rfft(a, n)) * np.fft.rfft(b, n), n)  # r[k mod n] = sum_i a[i] b[i + k]
    lags = np.arange(-K, K + 1)
    raw = r[lags % n]
    ca, cb = np.concatenate([[0.0], np.cumsum(a * a)]), np.concatenate([[0.0], np.cumsum(b * b)])
    pos = lags >= 0
    k = np.abs(lags)
    # overlap: k >= 0: a[:N - k], b[k:]; k < 0: a[k:], b[:N - k] (k = |lag|)
    ea = np.where(pos, ca[N - k], ca[N] - ca[k])
    eb = np.where(pos, cb[N] - cb[k], cb[N - k])
    den = np.sqrt(ea * eb)
    return np.where(den > 0, raw / np.where(den > 0, den, 1.0), 0.0)


def estimate_latency(t: Any, q: Any, p: Any, *, max_lag_s: float = LATENCY_MAX_S) -> float:
    """Seconds the tracker ``p (T, d)`` lags the encoders ``q (T, n)`` (:func:`latency_estimate`'s ``seconds``)."""
    return latency_estimate(t, q, p, max_lag_s=max_lag_s).seconds


def _shift_positions(t: np.ndarray, x: np.ndarray, latency: float) -> np.ndarray:
    return _uniform(t, x, t + latency)


def shift_tracker(t: Any, pose: Mapping[str, Any], latency: float, *, quat_cols: Sequence[str] | None = None,
                  rotvec_cols: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """The tracker columns ``pose`` (name -> ``(T,)``) at ``t + latency``: undo a tracker that reports ``latency``
    seconds late (the pose it logs at ``t + latency`` is the one at ``t``).

    Linear interpolation between rows (``t`` increasing, values finite);
    beyond the last row (or before the first, for a negative latency) the end
    value is held. Quaternion columns (``quat_cols``, ``w, x, y, z`` order;
    default ``q_w, q_x, q_y, q_z`` when all present) are sign-aligned,
    interpolated and renormalised; rotation-vector columns (``rotvec_cols``,
    default ``r_x, r_y, r_z``) go through quaternions. Other columns are
    interpolated one by one.
    """
    t = _time(t)
    if not np.isfinite(latency):
        raise ValueError(f"latency must be a finite number of seconds, got {latency!r}")
    names = list(pose.keys())
    quat_cols, rotvec_cols = rotation_columns(names, quat_cols, rotvec_cols)
    values = {c: np.asarray(pose[c], np.float64) for c in names}
    out: dict[str, np.ndarray] = {}
    if quat_cols:
        quat = _continuous_signs(np.stack([values[c] for c in quat_cols], axis=1))
        shifted = _normalise(_shift_positions(t, quat, latency))
        out.update({c: shifted[:, k] for k, c in enumerate(quat_cols)})
    if rotvec_cols:
        quat = _continuous_signs(_rotvec_to_quat(np.stack([values[c] for c in rotvec_cols], axis=1)))
        shifted = _quat_to_rotvec(_shift_positions(t, quat, latency))
        out.update({c: shifted[:, k] for k, c in enumerate(rotvec_cols)})
    for c in names:
        if c not in out:
            out[c] = np.interp(t + latency, t, values[c])
    return {c: out[c] for c in names}


def rotation_columns(names: Sequence[str], quat_cols: Sequence[str] | None, rotvec_cols: Sequence[str] | None
                      ) -> tuple[list[str], list[str]]:
    """The quaternion and rotation-vector columns among ``names`` (defaults by name); ValueError if misgiven."""
    if quat_cols is None:
        quat_cols = list(_QUATERNION) if all(c in names for c in _QUATERNION) else []
    if rotvec_cols is None:
        rotvec_cols = list(_ROTVEC) if all(c in names for c in _ROTVEC) else []
    quat_cols, rotvec_cols = list(quat_cols), list(rotvec_cols)
    if quat_cols and len(quat_cols) != 4:
        raise ValueError(f"quat_cols: need 4 columns (w, x, y, z), got {quat_cols}")
    if rotvec_cols and len(rotvec_cols) != 3:
        raise ValueError(f"rotvec_cols: need 3 columns (x, y, z), got {rotvec_cols}")
    for c in quat_cols + rotvec_cols:
        if c not in names:
            raise ValueError(f"rotation column {c} is not among the pose columns ({', '.join(names)})")
    if set(quat_cols) & set(rotvec_cols):
        raise ValueError("a column cannot be both a quaternion and a rotation-vector component")
    return quat_cols, rotvec_cols
