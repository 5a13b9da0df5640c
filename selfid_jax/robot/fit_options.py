"""The options of a fit from a log: plain values with their defaults, read by ``sj.fit`` and ``selfid-jax fit``.

:class:`ReadOptions` (how a log is read: layout, units, a continuous stream,
a bag's topics; :func:`selfid_jax.robot.read.read_log`) and :class:`FitOptions`
(the estimator's thresholds and refinement; :func:`selfid_jax.robot.offline.fit`)
are the one place each default of an offline fit is written: ``sj.fit``'s
keywords and the ``selfid-jax fit`` flags (keyword ``x_y`` is flag ``--x-y``)
take theirs from here. Importing this module loads neither numpy nor JAX
(the command line builds its flags from it).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

__all__ = ["LATENCY_CHOICES", "MODES", "FitOptions", "ReadOptions"]

MODES = ("auto", "stream", "moves")
"""How a raw time series is read (:func:`selfid_jax.robot.streams.reduce_stream`)."""
LATENCY_CHOICES = ("auto", "none")
"""The tracker latency's named settings besides a number of seconds."""


def _flag(name: str) -> str:
    """``latency (--latency)``: a keyword and the command's flag, for messages."""
    return f"{name} (--{name.replace('_', '-')})"


class ReadOptions(NamedTuple):
    """How to read a log: the options of ``sj.fit`` and ``selfid-jax fit`` (keyword ``x_y`` = flag ``--x-y``).

    The defaults here are the command's. :meth:`check` validates them (one
    message naming the keyword and flag) and returns them normalised.
    """

    task: str | Sequence[str | int] | None = None  # task axes, e.g. "x,y,z" or ("z", "rx"); None: the layout's default
    task_dim: int | None = None  # or the task dimension 2, 3 or 6 (not both)
    start: float | None = None  # ignore rows before this time (s, after unit conversion)
    stop: float | None = None  # ignore rows after this time (s)
    max_gap: float | str | None = "auto"  # time series: drop pairs of rows more than this many s apart;
    #   "auto": 3 median time steps; None or inf: no limit
    columns: str | Path | Mapping[str, str] | None = None  # log name -> fit name: a dict, "a=q_0,b=p_x" or a file
    joint_names: str | Sequence[str] | None = None  # these columns (in a bag: JointState names) are q_0.. in order
    length: str = "m"  # unit of the tracked positions: m, cm, mm
    time: str = "s"  # unit of t: s, ms, us, ns
    angle: str = "rad"  # unit of the actuator positions and rotation vectors: rad, deg
    mode: str = "auto"  # a raw time series: "auto" (detect a stream), "stream" (reduce it), "moves" (as it is)
    latency: str | float | None = "auto"  # a stream's tracker latency (s): "auto" (estimated), a number, None
    settle_speed: float | None = None  # a stream: joint speed below which the arm rests (actuator units / s)
    settle_time: float | None = None  # a stream: shortest rest that counts as settled (s)
    joints: str | None = None  # a bag: the sensor_msgs/JointState topic
    tracker: str | None = None  # a bag: the PoseStamped / TransformStamped / TFMessage topic
    child_frame: str | None = None  # a bag: on a tf topic, the tracked frame (child_frame_id)

    def check(self) -> ReadOptions:
        """These options validated and normalised: ``columns`` a dict, ``joint_names`` a tuple (None if empty),
        ``latency`` ``"auto"``, seconds or None, ``max_gap`` ``"auto"``, seconds or None.

        Raises:
          ValueError: an option out of range or of the wrong kind; the message names the keyword and the flag.
        """
        from selfid_jax.robot.log import parse_task
        from selfid_jax.robot.tables import Units, parse_columns

        try:
            parse_task(self.task, self.task_dim)
        except ValueError as err:
            raise ValueError(f"{_flag('task')} / {_flag('task_dim')}: {err}") from None
        for name in ("start", "stop"):
            value = getattr(self, name)
            if value is not None and not (_is_number(value) and not math.isnan(value)):
                raise ValueError(f"{_flag(name)}: expected a number of seconds, got {value!r}")
        if self.start is not None and self.stop is not None and self.stop < self.start:
            raise ValueError(f"--stop {self.stop:g} is before --start {self.start:g} (stop < start)")
        max_gap = self.max_gap
        if isinstance(max_gap, str) and max_gap.strip().lower() != "auto":
            max_gap = _seconds("max_gap", max_gap)
        if isinstance(max_gap, str):
            max_gap = "auto"
        elif max_gap is not None:
            if not (_is_number(max_gap) and max_gap > 0):
                raise ValueError(f"{_flag('max_gap')} must be positive seconds (or auto, inf), got {max_gap!r}")
            max_gap = None if math.isinf(max_gap) else float(max_gap)
        Units(self.length, self.time, self.angle).check()
        if self.mode not in MODES:
            raise ValueError(f"{_flag('mode')}: expected one of {', '.join(MODES)}, got {self.mode!r}")
        latency: str | float | None
        if self.latency is None or (isinstance(self.latency, str) and self.latency.strip().lower() == "none"):
            latency = None
        elif isinstance(self.latency, str) and self.latency.strip().lower() == "auto":
            latency = "auto"
        else:
            latency = _seconds("latency", self.latency, "auto, none or")
            if not math.isfinite(latency):
                raise ValueError(f"{_flag('latency')}: expected auto, none or a finite number of seconds, "
                                 f"got {self.latency!r}")
        if self.settle_speed is not None and not (_is_number(self.settle_speed) and math.isfinite(self.settle_speed)
                                                  and self.settle_speed > 0):
            raise ValueError(f"{_flag('settle_speed')} must be a positive number (actuator units / s), got "
                             f"{self.settle_speed!r}")
        if self.settle_time is not None and not (_is_number(self.settle_time) and math.isfinite(self.settle_time)
                                                 and self.settle_time >= 0):
            raise ValueError(f"{_flag('settle_time')} must be a non-negative number of seconds, got "
                             f"{self.settle_time!r}")
        for name in ("joints", "tracker", "child_frame"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, str) and value.strip()):
                raise ValueError(f"{_flag(name)}: expected a topic or frame name, got {value!r}")
        names = self.joint_names
        if isinstance(names, str):
            names = [x.strip() for x in names.split(",") if x.strip()]
        elif names is not None:
            names = list(names)
            if not all(isinstance(x, str) for x in names):
                raise ValueError(f"{_flag('joint_names')}: expected names (strings), got {self.joint_names!r}")
        return self._replace(columns=parse_columns(self.columns) or None, joint_names=tuple(names) if names else None,
                             latency=latency, max_gap=max_gap)


def _is_number(value: Any) -> bool:
    """A real number (numpy's too), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _seconds(name: str, value: Any, named: str = "") -> float:
    """``value`` (a number or its text) as float seconds; ValueError naming the keyword and flag."""
    if _is_number(value):
        return float(value)
    try:
        out = float(str(value).strip())
    except ValueError:
        raise ValueError(f"{_flag(name)}: expected {named + ' ' if named else ''}a number of seconds, "
                         f"got {value!r}") from None
    if math.isnan(out):
        raise ValueError(f"{_flag(name)}: expected a number of seconds, got nan")
    return out


class FitOptions(NamedTuple):
    """The estimator's options of an offline fit (:func:`selfid_jax.robot.offline.fit_samples`); the defaults are
    ``sj.fit``'s and ``selfid-jax fit``'s."""

    eps: float = 0.0  # Sec. IV-D absolute threshold on ||J_t - J_{t-1}||_F (inverse-Jacobian units)
    eps_rel: float = 0.05  # relative threshold, times ||J_t||_F; converged when the change is at most
    #   eps + eps_rel ||J_t||_F twice in a row
    method: str = "closed_form"  # Eq. 14 refinement (selfid_jax.identify.refine.METHODS; flag --refine)
