"""How well self-ID samples are explained: the forward map's leave-one-out error and each actuator's effect.

Self-ID samples ``(dtheta_k, V_k)`` of a robot that moves as commanded and is
tracked as it moves are explained by a linear forward map ``V = F dtheta``
near one configuration. :func:`held_out` fits it by least squares and
predicts each sample from the others: the error says how much to trust the
samples (a tracker latency beyond the settle time, an actuator that does not
act, a tracker that is not on the robot all show here). The live runner
checks it at convergence (:meth:`selfid_jax.robot.session.Session.check_quality`)
and ``selfid-jax fit`` reports it. numpy only.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["Quality", "held_out"]


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
