"""Self-ID from recorded data: the estimator of Eq. 6-14 over a log's sample pairs, with the Sec. IV-D test.

:func:`fit_samples` is the pure core: one ``lax.scan`` of the per-sample
:func:`selfid_jax.identify.step.sample_step` (``estimator.update`` ->
``initial_guess`` (Eq. 13) -> ``refine`` (Eq. 14) -> ``record`` (Sec. IV-D))
over ``(dtheta (T, n), V (T, m))``, the same step Algorithm 1 takes after each random actuation
(:func:`selfid_jax.identify.algorithm.self_identify`), without the actuation.
``eps``, ``eps_rel`` and ``v_tol`` are traced, so one compilation serves
every threshold and every log of the same length, and it vmaps over a batch
of logs. Unlike Algorithm 1 it does not stop at convergence: a recorded log
has no more moves to save, so the final estimate uses every sample, and the
convergence iteration says how many would have sufficed.

:func:`fit` reads any log (:func:`selfid_jax.robot.read.read_log`: files, bags,
tables, continuous streams, units), runs it in float64 and says how far to
trust the result (:func:`selfid_jax.robot.quality.trust`); exported as
``sj.fit``, it does what ``selfid-jax fit`` does short of writing files, with
the same options and defaults.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from selfid_jax.identify import estimator
from selfid_jax.identify.refine import METHODS, needs_samples, refine
from selfid_jax.identify.step import sample_step
from selfid_jax.math.checks import check_array, float_dtype
from selfid_jax.robot.fit_options import FitOptions, ReadOptions
from selfid_jax.robot.log import Samples
from selfid_jax.robot.quality import Trust, held_out, trust, unit_warnings
from selfid_jax.robot.read import ReadReport, read_log

__all__ = ["FitResult", "FitTrace", "actuator_labels", "fit", "fit_samples"]

_READ, _FIT = ReadOptions(), FitOptions()  # the defaults of fit's keywords (and the command's flags): one source


class FitTrace(NamedTuple):
    """Output of :func:`fit_samples` (leading batch axes if vmapped)."""

    state: estimator.EstimatorState  # estimator after the last sample
    estimate: jax.Array  # (n, m) final refined inverse Jacobian (every sample)
    initial_guess: jax.Array  # (n, m) Eq. 13 guess after the last sample
    estimates: jax.Array  # (T, n, m) refined estimate after each sample
    deltas: jax.Array  # (T,) ||J_t - J_{t-1}||_F per sample
    thresholds: jax.Array  # (T,) eps + eps_rel ||J_t||_F per sample
    accepted: jax.Array  # (T,) bool: samples the estimator took
    converged_at: jax.Array  # () int32: first 1-based sample index meeting Sec. IV-D, -1 if never


class FitResult(NamedTuple):
    """Output of :func:`fit`: the trace as numpy, where its samples came from, how they were read and how far to
    trust the estimate."""

    estimate: np.ndarray  # (n, m) final refined inverse Jacobian (Eq. 14, every sample)
    initial_guess: np.ndarray  # (n, m) Eq. 13 guess from every sample
    estimates: np.ndarray  # (T, n, m) refined estimate after each sample
    deltas: np.ndarray  # (T,) ||J_t - J_{t-1}||_F per sample
    thresholds: np.ndarray  # (T,) eps + eps_rel ||J_t||_F per sample
    accepted: np.ndarray  # (T,) bool: samples the estimator took (the others: all-zero dtheta or V)
    converged_at: int  # first 1-based sample index meeting Sec. IV-D, -1 if never
    samples: Samples  # the sample pairs and the log's row screens (rejected rows, window, gap limit)
    eps: float
    eps_rel: float
    method: str
    state: estimator.EstimatorState  # final estimator state
    trust: Trust  # held-out error, condition number, actuator effect, refused fraction, and a warning per figure
    #   outside its bound (selfid_jax.robot.quality.trust)
    report: ReadReport  # how the log was read: notes, units, the bag's and the stream's figures

    @property
    def converged(self) -> bool:
        return self.converged_at > 0

    @property
    def warnings(self) -> tuple[str, ...]:
        """One line per trust figure outside its bound (``trust.warnings``); empty for a fit to trust."""
        return self.trust.warnings

    @property
    def notes(self) -> tuple[str, ...]:
        """How the log was read, one line each (``report.notes``)."""
        return self.report.notes

    @property
    def converged_time(self) -> float | None:
        """Log time (s) of the sample at which the test first held; None if never or the log has no time."""
        if self.converged_at < 1:
            return None
        t = float(self.samples.t[self.converged_at - 1])
        return t if np.isfinite(t) else None


@functools.partial(jax.jit, static_argnames=("method", "options", "capacity"))
def _scan(dtheta, V, eps, eps_rel, v_tol, min_count, *, method: str, options: tuple, capacity: int) -> FitTrace:
    n, m = dtheta.shape[-1], V.shape[-1]
    dtype = dtheta.dtype
    state0 = estimator.init(n, m, capacity=capacity, v_tol=v_tol, dtype=dtype)

    def body(state, sample):
        return sample_step(state, sample[0], sample[1], eps, eps_rel, method=method, options=options,
                           min_count=min_count)

    state, info = jax.lax.scan(body, state0, (dtheta, V))
    return FitTrace(state=state, estimate=state.estimate, initial_guess=estimator.initial_guess(state),
                    estimates=info.estimate, deltas=info.delta, thresholds=info.threshold, accepted=info.accepted,
                    converged_at=state.converged_at)


def fit_samples(dtheta: ArrayLike, V: ArrayLike, eps: ArrayLike = 0.0, eps_rel: ArrayLike = 0.05, *,
                method: str = "closed_form", refine_options: Mapping[str, Any] | None = None, v_tol: ArrayLike = 1e-9,
                dtype=None, min_samples: ArrayLike = 0) -> FitTrace:
    """Run the estimator over sample pairs ``dtheta (T, n)``, ``V (T, m)``: a :class:`FitTrace`.

    ``eps`` (inverse-Jacobian units) and ``eps_rel`` (relative to ``||J_t||_F``)
    are the Sec. IV-D thresholds of :func:`selfid_jax.identify.estimator.record`:
    converged at the first sample ``t`` where ``||J_s - J_{s-1}||_F <= eps +
    eps_rel ||J_s||_F`` for ``s = t - 1, t``, both after an accepted sample,
    and at least ``min_samples`` samples accepted (0: the paper's test; the
    live runner's default is 5 per task axis, ``selfid_jax.robot.options``).
    ``method`` names the refinement (:data:`selfid_jax.identify.refine.METHODS`):
    ``"closed_form"`` and ``"optax"`` run in the scan; ``"slsqp"`` (eager
    scipy, the paper's) refines only the final estimate, on every sample, while
    the per-sample estimates and the convergence test use ``"closed_form"``
    (the same L2 minimiser once ``V`` spans the task). Under ``jit``/``vmap``
    (``eps``, ``eps_rel``, ``v_tol``, the data may be traced; batch them with
    ``vmap``), ``"slsqp"`` is refused.
    """
    if method not in METHODS:
        raise ValueError(f"refine method: expected one of {METHODS}, got {method!r}")
    options = dict(refine_options or {})
    dtype = float_dtype() if dtype is None else dtype
    dtheta = jnp.asarray(dtheta, dtype)
    V = jnp.asarray(V, dtype)
    check_array("dtheta", dtheta, (None, None))
    check_array("V", V, (dtheta.shape[0], None))
    estimator.check_thresholds(eps, eps_rel)
    T = dtheta.shape[0]
    if T == 0:
        raise ValueError("no samples to fit")
    scan_method = "closed_form" if method == "slsqp" else method
    scan_options = {} if method == "slsqp" else options
    capacity = T if needs_samples(method, options.get("loss", "l2")) else 0
    trace = _scan(dtheta, V, jnp.asarray(eps, dtype), jnp.asarray(eps_rel, dtype), jnp.asarray(v_tol, dtype),
                  jnp.asarray(min_samples, jnp.int32),
                  method=scan_method, options=tuple(sorted(scan_options.items())), capacity=capacity)
    if method == "slsqp":
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(trace)):
            raise ValueError("method='slsqp' runs scipy eagerly and cannot be used under jit/vmap/grad")
        final = refine(trace.state, trace.initial_guess, method="slsqp", **options)
        trace = trace._replace(estimate=final)
    return trace


def fit(
    log: str | Path | Mapping[str, Any] | Samples,
    *,
    task: str | Sequence[str | int] | None = _READ.task,
    task_dim: int | None = _READ.task_dim,
    eps: float = _FIT.eps,
    eps_rel: float = _FIT.eps_rel,
    method: str = _FIT.method,
    refine_options: Mapping[str, Any] | None = None,
    start: float | None = _READ.start,
    stop: float | None = _READ.stop,
    max_gap: float | str | None = _READ.max_gap,
    columns: str | Path | Mapping[str, str] | None = _READ.columns,
    joint_names: str | Sequence[str] | None = _READ.joint_names,
    length: str = _READ.length,
    time: str = _READ.time,
    angle: str = _READ.angle,
    mode: str = _READ.mode,
    latency: str | float | None = _READ.latency,
    settle_speed: float | None = _READ.settle_speed,
    settle_time: float | None = _READ.settle_time,
    joints: str | None = _READ.joints,
    tracker: str | None = _READ.tracker,
    child_frame: str | None = _READ.child_frame,
    camera: str | None = _READ.camera,
    video: str | Path | None = _READ.video,
    frame_times: str | Path | None = _READ.frame_times,
    camera_info: str | Path | None = _READ.camera_info,
    tag: str | None = _READ.tag,
    v_tol: float = 1e-9,
    dtype=None,
) -> FitResult:
    """Self-identify an inverse Jacobian ``(n, m)`` from a recorded log: ``sj.fit("log.csv", task="x,y,z")``.

    ``log``: a CSV/Parquet/NPZ file, a ROS 1/2 bag or MCAP file (``joints``,
    ``tracker`` or ``camera``, ``child_frame``), a table of columns (dict, DataFrame), or
    :class:`~selfid_jax.robot.log.Samples` already read. It is read as
    ``selfid-jax fit`` reads it (:func:`selfid_jax.robot.read.read_log`): the
    reading keywords are :class:`~selfid_jax.robot.fit_options.ReadOptions`' (``task``,
    ``task_dim``, ``start``, ``stop``, ``max_gap``, ``columns``,
    ``joint_names``, ``length``, ``time``, ``angle``, ``mode``, ``latency``,
    ``settle_speed``, ``settle_time``, ``joints``, ``tracker``,
    ``child_frame``, ``camera``, ``video``, ``frame_times``, ``camera_info``,
    ``tag``; flag ``--x-y`` is keyword ``x_y``), with the command's
    defaults, so a continuous stream is reduced to settled moves and its
    tracker latency taken out here too. A camera is the tracker with ``tag``
    (``"tag36h11:ID:EDGE_M"``): a bag's image topic (``camera``, intrinsics from
    its ``camera_info`` topic or ``camera_info``), or beside a joint log a video
    or a folder of images (``video``) with ``frame_times`` and ``camera_info``
    (:mod:`selfid_jax.robot.camera.sources`). ``eps``, ``eps_rel``, ``method`` (the
    flag ``--refine``; defaults :class:`~selfid_jax.robot.fit_options.FitOptions`),
    ``refine_options``, ``v_tol`` as in :func:`fit_samples`.
    ``dtype``: default float64, whatever ``jax_enable_x64`` says (the fit runs
    with it on: a log is small).

    Returns a :class:`FitResult` with the trust figures (``result.trust``,
    ``result.warnings``) and how the log was read (``result.report``,
    ``result.notes``).

    Raises:
      LogError: the log cannot be used (one line naming file, column, row or topic).
      ValueError: an option out of range (naming the keyword), checked before the log is read, or no sample pair
        survives the screens.
    """
    if method not in METHODS:
        raise ValueError(f"refine method (method=, --refine): expected one of {METHODS}, got {method!r}")
    estimator.check_thresholds(eps, eps_rel)
    options = ReadOptions(task=task, task_dim=task_dim, start=start, stop=stop, max_gap=max_gap, columns=columns,
                          joint_names=joint_names, length=length, time=time, angle=angle, mode=mode, latency=latency,
                          settle_speed=settle_speed, settle_time=settle_time, joints=joints, tracker=tracker,
                          child_frame=child_frame, camera=camera, video=video, frame_times=frame_times,
                          camera_info=camera_info, tag=tag)
    if isinstance(log, Samples):
        given = [k for k, v in options._asdict().items() if v != _READ._field_defaults[k]]
        if given:
            raise ValueError(f"{log.source}: {given[0]}= reads a log; these Samples were read already (pass the log "
                             "or table instead)")
        samples, report = log, ReadReport(log.source, (), {}, None, None)
    else:
        samples, report = read_log(log, options)
    if samples.dtheta.shape[0] == 0:
        kinds = "; ".join(r.line() for r in samples.rejected) or "no rows in the time window"
        raise ValueError(f"{samples.source}: no usable sample pair ({kinds})")
    x64 = jax.dtypes.canonicalize_dtype(jnp.float64) == jnp.float64
    with contextlib.nullcontext() if x64 else jax.enable_x64(True):
        trace = fit_samples(samples.dtheta, samples.V, eps, eps_rel, method=method, refine_options=refine_options,
                            v_tol=v_tol, dtype=jnp.float64 if dtype is None else dtype)
        host = jax.device_get(trace)
    accepted = np.asarray(host.accepted)
    estimate = np.asarray(host.estimate)
    return FitResult(
        estimate=estimate, initial_guess=np.asarray(host.initial_guess),
        estimates=np.asarray(host.estimates), deltas=np.asarray(host.deltas), thresholds=np.asarray(host.thresholds),
        accepted=accepted, converged_at=int(host.converged_at), samples=samples,
        eps=float(eps), eps_rel=float(eps_rel), method=method, state=host.state,
        trust=_trust(samples, accepted, estimate, report.units,
                     None if isinstance(log, Samples) else
                     actuator_labels(estimate.shape[0], options, report, pairs=samples.layout == "pairs")),
        report=report,
    )


def actuator_labels(n: int, options: ReadOptions, report: ReadReport, *, pairs: bool = False) -> tuple[str, ...]:
    """How a fit's messages name actuator ``i`` (its column ``q_i``; ``dtheta_i`` in a log of sample ``pairs``): the
    log's own name beside the column, ``"wrist_3_joint (q_5)"``, where the log named it (a bag's JointState names,
    ``joint_names``, a ``columns`` mapping, columns numbered from 1), else the column, ``"q_5"``."""
    opts = options.check()
    col = "dtheta" if pairs else "q"
    names: list[str | None] = [None] * n
    if report.bag is not None:
        names[:] = [str(x) for x in report.bag.joint_names[:n]]
    elif opts.joint_names:
        names[:] = [str(x) for x in opts.joint_names[:n]]
    elif isinstance(opts.columns, Mapping):
        for old, new in opts.columns.items():
            k = new[len(col) + 1:]
            if new.startswith(f"{col}_") and k.isdigit() and int(k) < n:
                names[int(k)] = old
    elif any(note.startswith("joints numbered from 1") for note in report.notes):
        names[:] = [f"q_{i + 1}" for i in range(n)]  # the log's columns q_1 .. q_n
    names += [None] * (n - len(names))
    return tuple(f"{col}_{i}" if name in (None, f"{col}_{i}") else f"{name} ({col}_{i})"
                 for i, name in enumerate(names))


def _trust(samples: Samples, accepted: np.ndarray, estimate: np.ndarray, units: dict[str, str],
           names: tuple[str, ...] | None = None) -> Trust:
    """:func:`selfid_jax.robot.quality.trust` of a fit: the held-out error of the accepted samples (the largest
    actuator step of a sample as the move scale), the refused rows and samples against the log's rows, and the
    motion per move against the units read in (``units``: column -> unit;
    :func:`~selfid_jax.robot.quality.unit_warnings`); ``names``: :func:`actuator_labels` (default ``q_i``)."""
    ok = np.asarray(accepted, bool)
    D, V = np.asarray(samples.dtheta, np.float64)[ok], np.asarray(samples.V, np.float64)[ok]
    quality = held_out(D, V, float(np.max(np.abs(D), initial=0.0)))
    refused = sum(r.count for r in samples.rejected) + int((~ok).sum())
    labels = names if names is not None else tuple(f"q_{i}" for i in range(estimate.shape[0]))
    return trust(quality, estimate, refused, samples.rows, unit_warnings(D, V, samples.axes, units), labels)
