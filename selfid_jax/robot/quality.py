"""How well self-ID samples are explained: the forward map's leave-one-out error and each actuator's effect.

Self-ID samples ``(dtheta_k, V_k)`` of a robot that moves as commanded and is
tracked as it moves are explained by a linear forward map ``V = F dtheta``
near one configuration. :func:`held_out` fits it by least squares and
predicts each sample from the others: the error says how much to trust the
samples (a tracker latency beyond the settle time, an actuator that does not
act, a tracker that is not on the robot all show here). The live runner
checks it at convergence (:meth:`selfid_jax.robot.session.Session.check_quality`);
:func:`trust` turns it and a fit's estimate into the figures ``sj.fit`` and
``selfid-jax fit`` report (:class:`Trust`). numpy only.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["MAX_CONDITION", "MAX_HELDOUT_ERROR", "MAX_LEVER_M_PER_RAD", "MAX_MOVE_RAD", "MAX_REFUSED_FRACTION",
           "MIN_EFFECT_RATIO", "MIN_LEVER_M_PER_RAD", "Quality", "Trust", "condition", "held_out", "trust",
           "unit_warnings"]


class Quality(NamedTuple):
    """How well a converged session's samples are explained (:func:`held_out`), checked before following."""

    heldout_error: float  # leave-one-out error of the tracked motion predicted from the measured actuator motion:
    #   sum_k |V_k - F_(-k) dtheta_k| / sum_k |V_k| with F_(-k) the least-squares forward map without sample k;
    #   NaN with no more samples than actuators
    effect: np.ndarray  # (n,) each actuator's task motion for a move of the given scale, |F[:, i]| scale [task units]
    samples: int


def held_out(D: np.ndarray, V: np.ndarray, scale: float) -> Quality:
    """:class:`Quality` of samples ``dtheta = D (k, n)``, ``V (k, m)``: the forward least-squares map
    ``V = F dtheta`` and its leave-one-out prediction error (the hat-matrix form, exact for least squares);
    ``effect`` is each actuator's ``|F[:, i]| scale`` (``scale``: a move's size in actuator units). float64 numpy."""
    D, V = np.asarray(D, np.float64), np.asarray(V, np.float64)
    k, n = D.shape
    if k <= n:
        return Quality(float("nan"), np.full(n, np.nan), k)
    G = D.T @ D
    Ginv = np.linalg.pinv(G)
    F = (Ginv @ D.T @ V).T
    h = np.einsum("ki,ij,kj->k", D, Ginv, D)
    r = (V - D @ F.T) / np.maximum(1.0 - h, 1e-12)[:, None]
    err = float(np.linalg.norm(r, axis=1).sum() / max(float(np.linalg.norm(V, axis=1).sum()), 1e-300))
    return Quality(err, np.linalg.norm(F, axis=0) * float(scale), k)


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

    def figures(self) -> dict[str, float | list[float]]:
        """The four figures by name (``summary.json``'s keys)."""
        return {"heldout_error": self.heldout_error, "condition": self.condition,
                "actuator_effect": list(self.actuator_effect), "refused_fraction": self.refused_fraction}


def trust(quality: Quality, estimate: np.ndarray, refused: int, total: int, units: tuple[str, ...] = ()) -> Trust:
    """The figures that say how far to trust a fit, and a warning per figure outside its bound (:class:`Trust`).

    ``quality``: :func:`held_out` of the accepted samples; ``estimate (n,
    m)``; ``refused`` of ``total`` rows and samples were dropped (screens and
    the estimator). Bounds: :data:`MAX_HELDOUT_ERROR`, :data:`MAX_CONDITION`,
    :data:`MIN_EFFECT_RATIO`, :data:`MAX_REFUSED_FRACTION`. ``units``: the lines of :func:`unit_warnings`
    (a unit that looks swapped), first among the warnings.
    """
    cond = condition(estimate)
    effect = np.asarray(quality.effect, np.float64)
    top = float(np.nanmax(effect)) if effect.size and np.any(np.isfinite(effect)) else float("nan")
    ratio = effect / top if top > 0 else np.full(effect.shape, np.nan)
    fraction = refused / total if total else 0.0
    warnings = list(units)
    if quality.heldout_error > MAX_HELDOUT_ERROR:
        warnings.append(f"held-out error {quality.heldout_error:.3g} > {MAX_HELDOUT_ERROR:g}: the tracked motion is "
                        "not explained by the actuators' (a tracker latency, a continuous log paired row by row, "
                        "an actuator that does not act)")
    if cond > MAX_CONDITION:
        warnings.append(f"condition number {cond:.3g} > {MAX_CONDITION:g}: some task direction is barely identified")
    weak = np.flatnonzero(ratio < MIN_EFFECT_RATIO)
    if weak.size:
        warnings.append(f"actuator {int(weak[0])} moves the tracked point {ratio[weak[0]]:.2g} of the strongest "
                        f"(< {MIN_EFFECT_RATIO:g}): its column of the estimate is noise")
    if fraction > MAX_REFUSED_FRACTION:
        warnings.append(f"{100 * fraction:.0f}% of the rows and samples were refused (> "
                        f"{100 * MAX_REFUSED_FRACTION:.0f}%)")
    return Trust(float(quality.heldout_error), cond, tuple(float(x) for x in effect), float(fraction),
                 tuple(warnings))
