"""How well self-ID samples are explained: the forward map's leave-one-out error and each actuator's effect.

Self-ID samples ``(dtheta_k, V_k)`` of a robot that moves as commanded and is
tracked as it moves are explained by a linear forward map ``V = F dtheta``
near one configuration. :func:`held_out` fits it by least squares and
predicts each sample from the others: the error says how much to trust the
samples (a tracker latency beyond the settle time, an actuator that does not
act, a tracker that is not on the robot all show here). The live runner
checks it at convergence (:meth:`selfid_jax.robot.session.Session.check_quality`);
:func:`trust` turns it and a fit's estimate into the figures ``sj.fit`` and
``selfid-jax fit`` report (:class:`Trust`). :func:`trust_record` is what an
estimate file carries of them (``inverse_jacobian.npz``'s ``trust`` entry,
``.json``'s ``trust`` key), :func:`read_trust` reads it back and
:func:`record_flags` says why an estimate should not be followed unasked. numpy only.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["MAX_CONDITION", "MAX_HELDOUT_ERROR", "MAX_LEVER_M_PER_RAD", "MAX_MOVE_RAD", "MAX_REFUSED_FRACTION",
           "MIN_EFFECT_RATIO", "MIN_LEVER_M_PER_RAD", "MIN_MOTION_RATIO", "Quality", "TRUST_KEY", "Trust", "condition",
           "held_out", "read_trust", "record_flags", "record_lines", "trust", "trust_record", "unit_warnings"]


class Quality(NamedTuple):
    """How well a converged session's samples are explained (:func:`held_out`), checked before following."""

    heldout_error: float  # leave-one-out error of the tracked motion predicted from the measured actuator motion:
    #   sum_k |V_k - F_(-k) dtheta_k| / sum_k |V_k| with F_(-k) the least-squares forward map without sample k;
    #   NaN with no more samples than actuators
    effect: np.ndarray  # (n,) each actuator's task motion for a move of the given scale, |F[:, i]| scale [task units]
    samples: int
    motion: np.ndarray | None = None  # (n,) each actuator's largest |dtheta_k[i]| over the samples [actuator units]:
    #   an actuator that barely moved has an effect fitted to noise (its column of F is unidentified)


def held_out(D: np.ndarray, V: np.ndarray, scale: float) -> Quality:
    """:class:`Quality` of samples ``dtheta = D (k, n)``, ``V (k, m)``: the forward least-squares map
    ``V = F dtheta`` and its leave-one-out prediction error (the hat-matrix form, exact for least squares);
    ``effect`` is each actuator's ``|F[:, i]| scale`` (``scale``: a move's size in actuator units). float64 numpy."""
    D, V = np.asarray(D, np.float64), np.asarray(V, np.float64)
    k, n = D.shape
    motion = np.max(np.abs(D), axis=0, initial=0.0)
    if k <= n:
        return Quality(float("nan"), np.full(n, np.nan), k, motion)
    G = D.T @ D
    Ginv = np.linalg.pinv(G)
    F = (Ginv @ D.T @ V).T
    h = np.einsum("ki,ij,kj->k", D, Ginv, D)
    r = (V - D @ F.T) / np.maximum(1.0 - h, 1e-12)[:, None]
    err = float(np.linalg.norm(r, axis=1).sum() / max(float(np.linalg.norm(V, axis=1).sum()), 1e-300))
    return Quality(err, np.linalg.norm(F, axis=0) * float(scale), k, motion)


MAX_HELDOUT_ERROR = 0.5
"""The largest leave-one-out error; above it the samples are not explained by one linear map (the live runner
stops)."""
MAX_CONDITION = 1e3
"""The largest condition number of an estimate; above it some task direction is barely identified."""
MIN_EFFECT_RATIO = 1e-3
"""The smallest effect of an actuator relative to the strongest; below it the actuator barely moves the tracked
point."""
MAX_REFUSED_FRACTION = 0.25
"""The largest fraction of refused rows and samples; above it the log is mostly unusable."""
MIN_MOTION_RATIO = 1e-2
"""The least motion of an actuator (its largest sample step) relative to the most moved one's; below it the actuator
did not move in the samples (held, or jitter only) and its column of the estimate is fitted to noise: its effect
says nothing, and is left out of the effect ratio (else the noise's huge effect makes a moved actuator look weak)."""


MIN_LEVER_M_PER_RAD = 1e-3
"""The least tracked motion per radian of actuator motion a robot's log can show (m/rad: the median ``|V_xyz|`` over
the median ``|dtheta|`` of the moves): the tracked point sits on the moving arm, centimetres to metres from the
joint axes (a UR5e's tool ~0.1-1 m, a WidowX's ~0.05-0.5 m); every axis passing within 1 mm of it is no arm. A log
in metres read as mm shows 1000x less (~0.3 mm/rad for a UR5e). A warning, not a refusal: an actuator logged at a
geared motor's side moves the point less per radian. Not caught: a factor the range holds (m read as cm: ~3.5 mm/rad
for a UR5e)."""
MAX_LEVER_M_PER_RAD = 5.0
"""The most tracked motion per radian: the longest industrial arms reach ~3.5 m, so no tracked point lies 5 m from
every joint axis. Radians read as degrees show 57x more (~15 m/rad for a UR5e), mm read as m 1000x more."""
MAX_MOVE_RAD = 0.5
"""The largest median joint move (``|dtheta|``, rad) of a self-ID log: its moves are small (0.03 rad by default) so that
one linear map explains them; a median move of 29 degrees or more is no self-ID move in radians (degrees read as
radians show 57x: 0.03 rad logged in degrees is 1.7)."""


def unit_warnings(D: np.ndarray, V: np.ndarray, axes: tuple[int, ...] | None, units: dict[str, str] | None = None
                  ) -> tuple[str, ...]:
    """A line per implausible motion of samples ``dtheta = D (k, n)`` (rad), ``V (k, m)`` (m on position axes): a
    length or angle unit declared wrong. ``axes``: the task components of ``V`` (x, y, z = 0, 1, 2; None: unnamed,
    the tracked motion not checked); ``units``: column -> unit read in (``p_x``, ``q_0``), named in the advice.

    Checks: the median joint move against :data:`MAX_MOVE_RAD`, and the median tracked position motion per move
    over the median joint move against :data:`MIN_LEVER_M_PER_RAD` .. :data:`MAX_LEVER_M_PER_RAD`.
    """
    D, V = np.asarray(D, np.float64), np.asarray(V, np.float64)
    units = units or {}
    length, angle = units.get("p_x", "m"), units.get("q_0", units.get("dtheta_0", "rad"))
    if D.shape[0] == 0:
        return ()
    move = float(np.median(np.linalg.norm(D, axis=1)))
    out = []
    if move > MAX_MOVE_RAD:
        hint = ("is the angle unit deg, not rad? (--angle deg, or a units row)" if angle == "rad" else
                "are the joints moved this far per sample?")
        out.append(f"joint moves of {move:.3g} rad per sample (median; a self-ID move is below {MAX_MOVE_RAD:g}): "
                   f"{hint}")
    pos = [j for j, a in enumerate(axes or ()) if a < 3]
    if not (pos and move > 0):
        return tuple(out)
    motion = float(np.median(np.linalg.norm(V[:, pos], axis=1)))
    lever = motion / move
    said = f"tracked motion {_length(motion)} per {move:.3g} rad move ({_length(lever)}/rad"
    if lever < MIN_LEVER_M_PER_RAD:
        hint = {"mm": "is the length unit m (or cm), not mm?", "cm": "is the length unit m, not cm?"}.get(
            length, "is the tracker on the robot, and are the positions in metres?")
        out.append(f"{said}, below {_length(MIN_LEVER_M_PER_RAD)}/rad): {hint} (--length, or a units row)")
    elif lever > MAX_LEVER_M_PER_RAD:
        hint = ("is the angle unit rad, not deg?" if angle == "deg" else
                "is the length unit mm (or cm), not m?" if length == "m" else
                "are the length and angle units right?")
        out.append(f"{said}, above {MAX_LEVER_M_PER_RAD:g} m/rad): {hint} (--length, --angle, or a units row)")
    return tuple(out)


def _length(x: float) -> str:
    """A length for a message: ``12 µm``, ``3.4 mm``, ``0.25 m``."""
    if x < 1e-3:
        return f"{1e6 * x:.3g} µm"
    if x < 0.1:
        return f"{1e3 * x:.3g} mm"
    return f"{x:.3g} m"


def condition(estimate: np.ndarray) -> float:
    """The estimate's condition number ``s_max / s_min`` of ``(n, m)`` (inf when rank-deficient)."""
    s = np.linalg.svd(np.asarray(estimate, np.float64), compute_uv=False)
    return float(s[0] / s[-1]) if s.size and s[-1] > 0 else float("inf")


class Trust(NamedTuple):
    """How far to trust a fit (:func:`trust`): four figures and a warning per figure outside its bound."""

    heldout_error: float  # Quality.heldout_error of the accepted samples (bound MAX_HELDOUT_ERROR); NaN: too few
    condition: float  # the estimate's s_max / s_min (bound MAX_CONDITION); inf when rank-deficient
    actuator_effect: tuple[float, ...]  # (n,) each actuator's task motion for the largest sample step [task units]
    #   (an actuator below MIN_EFFECT_RATIO of the strongest is noise in the estimate)
    refused_fraction: float  # rows and samples refused (screens and the estimator) / rows (bound MAX_REFUSED_FRACTION)
    warnings: tuple[str, ...]  # one line per figure outside its bound
    actuators: tuple[str, ...] = ()  # (n,) how the warnings name each actuator (the log's or the driver's names)
    actuator_motion: tuple[float, ...] = ()  # (n,) each actuator's largest sample step [actuator units]
    #   (one below MIN_MOTION_RATIO of the most moved did not move: its column is not identified)

    def figures(self) -> dict[str, float | list[float]]:
        """The figures by name (``summary.json``'s keys; the warnings and the actuators' labels apart)."""
        return {"heldout_error": self.heldout_error, "condition": self.condition,
                "actuator_effect": list(self.actuator_effect), "refused_fraction": self.refused_fraction,
                "actuator_motion": list(self.actuator_motion)}


def trust(quality: Quality, estimate: np.ndarray, refused: int, total: int, units: tuple[str, ...] = (),
          names: tuple[str, ...] | list[str] | None = None) -> Trust:
    """The figures that say how far to trust a fit, and a warning per figure outside its bound (:class:`Trust`).

    ``quality``: :func:`held_out` of the accepted samples; ``estimate (n,
    m)``; ``refused`` of ``total`` rows and samples were dropped (screens and
    the estimator). Bounds: :data:`MAX_HELDOUT_ERROR`, :data:`MAX_CONDITION`,
    :data:`MIN_MOTION_RATIO`, :data:`MIN_EFFECT_RATIO`, :data:`MAX_REFUSED_FRACTION`. ``units``: the lines of
    :func:`unit_warnings` (a unit that looks swapped), first among the warnings. ``names``: how the warnings name
    actuator ``i`` (``n`` labels: the log's joint names, the driver's); default ``actuator i``.

    An actuator that did not move (``quality.motion`` below :data:`MIN_MOTION_RATIO` of the most moved one's) is
    named as such and left out of the effect ratio: its fitted effect is noise divided by noise, often the largest,
    which would make every moved actuator look weak.
    """
    cond = condition(estimate)
    effect = np.asarray(quality.effect, np.float64)
    n = effect.shape[0]
    labels = tuple(str(x) for x in names) if names is not None and len(names) == n else \
        tuple(f"actuator {i}" for i in range(n))
    motion = np.full(n, np.nan) if quality.motion is None else np.asarray(quality.motion, np.float64)
    most = float(np.max(motion)) if motion.size and np.all(np.isfinite(motion)) else float("nan")
    still = motion < MIN_MOTION_RATIO * most if most > 0 else np.zeros(n, bool)
    moved_effect = np.where(still, np.nan, effect)
    top = float(np.nanmax(moved_effect)) if np.any(np.isfinite(moved_effect)) else float("nan")
    ratio = moved_effect / top if top > 0 else np.full(effect.shape, np.nan)
    fraction = refused / total if total else 0.0
    warnings = list(units)
    if quality.heldout_error > MAX_HELDOUT_ERROR:
        warnings.append(f"held-out error {quality.heldout_error:.3g} > {MAX_HELDOUT_ERROR:g}: the tracked motion is "
                        "not explained by the actuators' (a tracker latency, a continuous log paired row by row, "
                        "an actuator that does not act)")
    if cond > MAX_CONDITION:
        warnings.append(f"condition number {cond:.3g} > {MAX_CONDITION:g}: some task direction is barely identified")
    for i in np.flatnonzero(still):
        warnings.append(f"{labels[i]} did not move in the samples (largest step {motion[i]:.3g}, "
                        f"{motion[i] / most:.2g} of the most moved actuator's, < {MIN_MOTION_RATIO:g}): its column "
                        "of the estimate is not identified")
    for i in np.flatnonzero(ratio < MIN_EFFECT_RATIO):
        warnings.append(f"{labels[i]} moves the tracked point {ratio[i]:.2g} of the strongest moved actuator "
                        f"(< {MIN_EFFECT_RATIO:g}): its column of the estimate is noise")
    if fraction > MAX_REFUSED_FRACTION:
        warnings.append(f"{100 * fraction:.0f}% of the rows and samples were refused (> "
                        f"{100 * MAX_REFUSED_FRACTION:.0f}%)")
    return Trust(float(quality.heldout_error), cond, tuple(float(x) for x in effect), float(fraction),
                 tuple(warnings), labels, tuple(float(x) for x in motion))


TRUST_KEY = "trust"
"""The entry of ``inverse_jacobian.npz`` (a JSON string) and the key of ``inverse_jacobian.json`` that hold the
estimate's :func:`trust_record`."""


def trust_record(*, source: str, log: str, converged: bool, converged_at: int, trust: Trust | None,
                 reference_error: float | None = None, report: tuple[str, ...] | list[str] = ()) -> dict:
    """What an estimate file carries of how far to trust it (JSON values; NaN/inf as None).

    ``source``: ``"fit"`` or ``"online"`` (what wrote it); ``log``: the log it
    was identified from; ``converged``, ``converged_at``: Sec. IV-D's test;
    ``trust``: the figures and warnings (:func:`trust`; None: none computed, e.g.
    too few samples); ``reference_error``: ``||J Ĵ - I||_F`` against a driver's
    model where known; ``report``: the lines that say how the estimate was made
    (how the log was read, rows refused, the session's stop).
    """
    from selfid_jax.strict_json import jsonable

    figures = {} if trust is None else {**trust.figures(), "actuators": list(trust.actuators)}
    return jsonable({"source": source, "log": log, "converged": bool(converged), "converged_at": int(converged_at),
                     **figures, "warnings": [] if trust is None else list(trust.warnings),
                     "reference_error": reference_error, "report": list(report)})


def read_trust(files: dict) -> dict | None:
    """The :func:`trust_record` an estimate file carries: ``files`` maps its entries to arrays (an open ``npz``); None
    for a file written before estimates carried one. ValueError where the entry is there but unreadable."""
    import json

    if TRUST_KEY not in files:
        return None
    try:
        record = json.loads(str(np.asarray(files[TRUST_KEY]).item()))
    except (ValueError, TypeError) as err:
        raise ValueError(f"its {TRUST_KEY!r} entry is not a trust record ({err})") from None
    if not isinstance(record, dict):
        raise ValueError(f"its {TRUST_KEY!r} entry is not a trust record (a {type(record).__name__})")
    return record


def record_flags(record: dict) -> list[str]:
    """Why an estimate with this :func:`trust_record` should not be followed unasked: its warnings, and a line when it
    did not converge; empty for an estimate to trust."""
    flags = [str(w) for w in record.get("warnings") or []]
    if not record.get("converged", False):
        flags.insert(0, "it did not converge (Sec. IV-D)")
    return flags


def record_lines(record: dict) -> list[str]:
    """The trust figures of a :func:`trust_record` as lines to print: convergence, held-out error, condition number,
    the reference error where known, then its warnings."""
    def num(key: str) -> str:
        v = record.get(key)
        return "n/a" if v is None else f"{float(v):.3g}"

    conv = (f"converged at sample {record.get('converged_at')}" if record.get("converged") else "not converged")
    head = f"{conv}, held-out error {num('heldout_error')}, condition number {num('condition')}"
    if record.get("reference_error") is not None:
        head += f", ||J Ĵ - I||_F {num('reference_error')} against the driver's model"
    return [head, *(f"warning: {w}" for w in record.get("warnings") or [])]
