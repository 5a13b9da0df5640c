"""The live progress of an online session: one line per self-ID sample, following move and the stop.

:class:`ProgressLine` is the ``progress`` callback of
:func:`selfid_jax.robot.live.run_online` (and of
:func:`selfid_jax.sessions.online_run.run_session`) that ``selfid-jax online``
shows: on a stream, one line per event; on a terminal, one line rewritten in
place (carriage return) per phase. Each event is the dict ``run_online``
documents; distances are printed in mm.
"""

from __future__ import annotations

from typing import Any

__all__ = ["ProgressLine"]


class ProgressLine:
    """The live progress of ``selfid-jax online``: one line per session event
    (:func:`selfid_jax.robot.live.run_online`'s ``progress``) on ``stream``, or on a terminal one line rewritten in
    place (carriage return) per phase."""

    def __init__(self, stream=None, tty: bool | None = None):
        """``stream``: where the lines go (default ``sys.stdout``); ``tty``: rewrite one line in place (default:
        whether ``stream`` is a terminal)."""
        import sys

        self.stream = sys.stdout if stream is None else stream
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)()) if tty is None else tty
        self.width = 0  # length of the line shown in place (tty)
        self.phase: str | None = None

    @staticmethod
    def line(event: dict[str, Any]) -> str:
        """The text of one event (a ``run_online`` progress dict): its phase, counts, ``|J_t - J_t-1|`` against
        Sec. IV-D's threshold, or the path distance [mm]."""
        phase = event["phase"]
        if phase == "selfid":
            head = f"self-ID  move {event['move']:4d}  sample {event['sample']:4d}"
            if not event["accepted"]:
                return f"{head}  rejected ({event['reason']})"
            conv = event.get("converged_at", -1)
            ok = "converged" if conv > 0 else ("below" if event["delta"] <= event["threshold"] else "above")
            return (f"{head}  |J_t - J_t-1| {event['delta']:.3e}  threshold {event['threshold']:.3e}  {ok}"
                    + ("" if event.get("estimator_accepted", True) else "  (refused by the estimator)"))
        if phase == "follow":
            return (f"follow   move {event['step']:4d}  waypoint {event['waypoint']}/{event['waypoints']}  "
                    f"path distance {1e3 * event['distance']:.3f} mm")
        return f"stop: {event['status']}: {event['detail']}"

    def __call__(self, event: dict[str, Any]) -> None:
        """Show one event: a line of its own, or on a terminal the phase's line rewritten in place."""
        text = self.line(event)
        if not self.tty:
            print(text, file=self.stream, flush=True)
            return
        if self.width and (event["phase"] != self.phase or event["phase"] == "stop"):
            self.stream.write("\n")  # keep the last line of the phase before
            self.width = 0
        self.phase = event["phase"]
        if event["phase"] == "stop":
            self.stream.write(text + "\n")
        else:
            self.stream.write("\r" + text.ljust(self.width))
            self.width = len(text)
        self.stream.flush()
