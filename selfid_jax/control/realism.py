"""The real loop's non-idealities: control period, tracker latency, noise and dropouts, servo lag, deadband.

:class:`Realism` is one set of values, shared by the batched simulations (the
``realism`` config section of ``valid_region``, ``tracking`` and
``peg_in_hole``, traced so that one compiled program serves a sweep over them)
and by the virtual robot (:mod:`selfid_jax.robot.virtual`). :data:`IDEAL`
(every field at its default) reproduces the ideal kinematic loop exactly.

Model, per control step of ``period`` seconds, actuator targets ``u``:

* deadband: a commanded change ``|u_i - q_i| <= deadband_i`` produces no motion;
* servo lag: the actuators move ``q <- q + (u - q) (1 - exp(-period / servo_tau))``
  (first order; ``servo_tau = 0`` reaches the target within the step);
* the tracker reports the pose of ``latency`` whole control steps ago, with
  Gaussian noise of ``noise_pos`` metres and ``noise_rot`` radians per axis
  (rotation noise as a random rotation vector), and with probability
  ``dropout`` per reading no pose at all (the loop then holds its last good
  reading and counts the dropout).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

__all__ = ["Realism", "IDEAL", "check_realism"]


class Realism(NamedTuple):
    """Values of the non-idealities (scalars; any field may carry a batch axis under ``vmap`` where traced)."""

    period: Any = 0.0  # s, control period; 0: the ideal loop, where servo_tau has no effect
    latency: int = 0  # whole control steps between a pose and its tracker reading, >= 0 (static: it sizes a buffer)
    noise_pos: Any = 0.0  # m, standard deviation of the tracker position noise per axis
    noise_rot: Any = 0.0  # rad, standard deviation of the tracker rotation noise per axis
    dropout: Any = 0.0  # probability in [0, 1) that a tracker reading is missing
    servo_tau: Any = 0.0  # s, first-order servo time constant (0: no lag)
    deadband: Any = 0.0  # actuator units, commanded changes at most this large produce no motion


IDEAL = Realism()


def check_realism(r: Realism) -> Realism:
    """``r`` with concrete values checked (non-negative, finite, ``dropout < 1``, integer ``latency``).

    Raises ValueError naming the field and its value. Traced values are not checked.
    """
    for name in Realism._fields:
        value = getattr(r, name)
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError, Exception):  # traced (a jax Tracer) or not numeric
            if hasattr(value, "aval"):
                continue
            raise ValueError(f"realism.{name}: expected a number, got {value!r}") from None
        if not np.all(np.isfinite(arr)) or np.any(arr < 0):
            raise ValueError(f"realism.{name}: must be finite and >= 0, got {value!r}")
    if np.any(np.asarray(r.dropout, np.float64) >= 1):
        raise ValueError(f"realism.dropout: must be < 1, got {r.dropout!r}")
    if int(r.latency) != r.latency:
        raise ValueError(f"realism.latency: whole control steps, got {r.latency!r}")
    return r._replace(latency=int(r.latency))
