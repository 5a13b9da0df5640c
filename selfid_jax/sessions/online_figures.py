"""The figures of a ``selfid-jax online`` run, drawn from its session log alone (``selfid-jax plot RUN`` redraws them).

* ``figures/convergence.png`` / ``.pdf``: ``||J_t - J_{t-1}||_F`` per accepted
  sample against the Sec. IV-D threshold, the convergence sample marked: the
  figure ``selfid-jax fit`` draws (:func:`selfid_jax.sessions.fit_run.draw_convergence`);
  none for a session that follows a given estimate (``--estimate``: no self-ID
  here; the summary gives its file's convergence).
* ``figures/path.png`` / ``.pdf`` (when the session started following): the
  tracked point's positions while following against the target waypoints, in
  the plane of the path's two widest position axes, and the path distance
  after each following move [m] with its mean and max; where a resumed
  session took up following is marked in both (:func:`resumed_at`).
* ``figures/estimate.png`` / ``.pdf`` (when the driver gave its model's
  Jacobian ``J``, a ``reference`` record: where self-ID started, or with a
  given estimate where following started, and the session converged or was
  given its estimate): ``J Ĵ`` and ``J Ĵ - I`` with its Frobenius norm
  (:func:`selfid_jax.runner.figures.right_inverse_panels`).

Everything comes from ``RUN/session.jsonl`` (:mod:`selfid_jax.robot.journal`):
the header (``eps``, ``eps_rel``, the axes), the accepted ``sample`` records
(``delta``, ``threshold``, ``converged_at``), the ``follow`` record (the
anchor pose and the waypoint offsets), the ``obs`` records of the following
phase and the ``track`` records (path distance per move).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["CONVERGENCE", "ESTIMATE", "PATH", "draw_estimate", "draw_path", "redraw", "resumed_at", "tracking",
           "write_figures"]

CONVERGENCE = "convergence"
PATH = "path"
ESTIMATE = "estimate"
LOG_FILE = "session.jsonl"  # selfid_jax.robot.live.LOG_FILE, without importing JAX to recognise a run directory


def tracking(records: list[dict[str, Any]]) -> dict[str, float | None]:
    """Mean and max path distance [m] over the log's following moves (``track`` records); None without any."""
    import numpy as np

    d = np.array([np.nan if r["distance"] is None else r["distance"] for r in records if r["e"] == "track"],
                 np.float64)
    if not d.size:
        return {"track_mean_m": None, "track_max_m": None, "track_moves": 0}
    return {"track_mean_m": float(np.nanmean(d)), "track_max_m": float(np.nanmax(d)), "track_moves": int(d.size)}


def _axis_names(axes) -> list[str]:
    from selfid_jax.systems.validation import AXIS_NAMES

    return [AXIS_NAMES[int(a)] for a in axes]


def draw_path(records: list[dict[str, Any]], axes, title: str):
    """The path figure of a log's records (see the module docstring); None if the log never started following."""
    import numpy as np
    from matplotlib.figure import Figure

    from selfid_jax.robot.journal import floats

    start = next((i for i, r in enumerate(records) if r["e"] == "follow"), None)
    if start is None:
        return None
    follow = records[start]
    anchor = floats(follow["p"])
    offsets = np.array([floats(o) for o in follow["offsets"]]).reshape(len(follow["offsets"]), -1)
    targets = np.repeat(anchor[None], offsets.shape[0], axis=0)
    for j, a in enumerate(axes):
        if a < 3:
            targets[:, a] += offsets[:, j]
    seen = [floats(r["p"]) for r in records[start:] if r["e"] == "obs" and r["phase"] == "follow" and r["valid"]]
    tracked = np.array(seen).reshape(-1, 3)
    resumes = resumed_at(records, start)
    both = np.vstack([targets, tracked, anchor[None]])
    plane = sorted(np.argsort(-np.ptp(both, axis=0), kind="stable")[:2].tolist())
    i, j = plane
    dist = np.array([np.nan if r["distance"] is None else r["distance"] for r in records[start:] if r["e"] == "track"],
                    np.float64)
    reached = max([int(r["reached"]) + 1 for r in records[start:] if r["e"] == "waypoint"], default=0)

    fig = Figure(figsize=(10.0, 4.2), layout="constrained")
    ax, ax_d = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.0, 1.3]})
    mm = 1e3
    loop = np.vstack([anchor[None], targets])
    ax.plot(mm * (loop[:, i] - anchor[i]), mm * (loop[:, j] - anchor[j]), "--", color="0.5", lw=1,
            label="target path")
    ax.plot(mm * (targets[:, i] - anchor[i]), mm * (targets[:, j] - anchor[j]), "s", color="0.3", ms=5,
            mfc="none", label=f"waypoints ({reached}/{targets.shape[0]} reached)")
    if tracked.size:
        ax.plot(mm * (tracked[:, i] - anchor[i]), mm * (tracked[:, j] - anchor[j]), "o-", color="C0", ms=2.5, lw=1,
                label="tracked point")
    ax.plot([0], [0], "k+", ms=10, label="start (anchor)")
    if resumes:
        at = np.array([p for _, p in resumes if p is not None]).reshape(-1, 3)
        ax.plot(mm * (at[:, i] - anchor[i]), mm * (at[:, j] - anchor[j]), "D", color="C1", ms=6, mfc="none",
                gid="resumed", label=f"resumed here ({len(resumes)})")
    names = "xyz"
    ax.set_xlabel(f"{names[i]} - start [mm]")
    ax.set_ylabel(f"{names[j]} - start [mm]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(f"tracked point against the target, {names[i]}{names[j]} plane", fontsize=10)
    if dist.size:
        k = np.arange(1, dist.size + 1)
        ax_d.plot(k, mm * dist, "o-", ms=2.5, lw=1, color="C0", label="path distance")
        ax_d.axhline(mm * np.nanmean(dist), color="C2", lw=1, ls="--", label=f"mean {mm * np.nanmean(dist):.3g} mm")
        ax_d.axhline(mm * np.nanmax(dist), color="C3", lw=1, ls=":", label=f"max {mm * np.nanmax(dist):.3g} mm")
        for r, (moves, _) in enumerate(resumes):
            ax_d.axvline(moves + 0.5, color="C1", lw=1, gid="resumed",
                         label="a resumed session started" if r == 0 else None)
        ax_d.legend(fontsize=7)
    ax_d.set_xlabel("following move")
    ax_d.set_ylabel("distance of the tracked point from the path [mm]")
    ax_d.grid(True, alpha=0.3)
    ax_d.set_title("tracking error", fontsize=10)
    fig.suptitle(title, fontsize=10)
    return fig


def resumed_at(records: list[dict[str, Any]], start: int) -> list[tuple[int, Any]]:
    """Where each resumed session of a log took up following (``session`` records with ``resume`` after the
    ``follow`` record at index ``start``): ``(following moves before it, the tracked position (3,) m it first read,
    or None)`` each."""
    from selfid_jax.robot.journal import floats

    out: list[tuple[int, Any]] = []
    moves = 0
    for k in range(start, len(records)):
        r = records[k]
        if r["e"] == "track":
            moves += 1
        elif r["e"] == "session" and r.get("resume"):
            first = next((floats(o["p"]) for o in records[k + 1:] if o["e"] == "obs" and o["phase"] == "follow"
                          and o["valid"]), None)
            out.append((moves, first))
    return out


def draw_estimate(records: list[dict[str, Any]], axes, title: str):
    """The converged estimate against the driver's reference Jacobian (``J Ĵ``, ``J Ĵ - I``); None without both."""
    import numpy as np
    from matplotlib.figure import Figure

    from selfid_jax.runner.figures import right_inverse_panels

    ref = next((r for r in records if r["e"] == "reference"), None)
    conv = next((r for r in records if r["e"] in ("converged", "estimate")), None)  # self-ID's, or a given one
    if ref is None or conv is None:
        return None
    J = np.array(ref["jacobian"], np.float64)[list(axes)]
    est = np.array(conv["estimate"], np.float64).reshape(J.shape[1], J.shape[0])
    fig = Figure(figsize=(8.5, 3.8), layout="constrained")
    panels = fig.subplots(1, 2)
    im = right_inverse_panels(panels, J, est, _axis_names(axes), "")
    fig.colorbar(im, ax=list(panels), shrink=0.8, label="task unit per task unit")
    fig.suptitle(title, fontsize=10)
    return fig


def write_figures(run_dir: str | Path) -> list[Path]:
    """Draw the run's figures from ``RUN/session.jsonl`` into ``RUN/figures``; returns the files written."""
    import numpy as np

    from selfid_jax.robot.journal import read_journal
    from selfid_jax.runner.figures import save_figure
    from selfid_jax.runner.layout import FIGURES_DIR
    from selfid_jax.sessions.fit_run import draw_convergence

    run_dir = Path(run_dir)
    log = read_journal(run_dir / LOG_FILE)
    header, records = log.header, log.records
    axes = [int(a) for a in header.get("axes", [])]
    what = f"n={header.get('n')}, task {','.join(_axis_names(axes))}"
    samples = [r for r in records if r["e"] == "sample" and r["accepted"]]
    deltas = np.array([np.nan if r["delta"] is None else r["delta"] for r in samples], np.float64)
    thresholds = np.array([np.nan if r["threshold"] is None else r["threshold"] for r in samples], np.float64)
    conv = max([int(r["converged_at"]) for r in samples], default=-1)
    out = run_dir / FIGURES_DIR
    paths: list[Path] = []
    if any(r["e"] == "estimate" for r in records):  # followed with a given estimate: no self-ID here to draw
        for f in out.glob(f"{CONVERGENCE}.*"):  # nor a figure of one left from before
            f.unlink()
    else:
        paths += save_figure(draw_convergence(deltas, thresholds, eps=float(header["eps"]),
                                              eps_rel=float(header["eps_rel"]), converged_at=conv,
                                              accepted=[bool(r.get("estimator_accepted", True)) for r in samples],
                                              title=f"online self-ID of the tracked point ({run_dir.name}): {what}"),
                             out, CONVERGENCE)
    fig = draw_path(records, axes, f"following with the estimate ({run_dir.name}): {what}")
    if fig is not None:
        paths += save_figure(fig, out, PATH)
    at = next((r.get("at", "selfid") for r in records if r["e"] == "reference"), "selfid")
    fig = draw_estimate(records, axes, f"the estimate against the driver's model Jacobian J where "
                                       f"{'following' if at == 'follow' else 'self-ID'} started ({run_dir.name}): "
                                       f"{what}")
    if fig is not None:
        paths += save_figure(fig, out, ESTIMATE)
    return paths


def redraw(run_dir: Path) -> list[Path] | None:
    """``selfid-jax plot RUN`` for an online run directory (one with ``session.jsonl``); None for any other."""
    from selfid_jax.robot.journal import JournalError
    from selfid_jax.runner.errors import RunDirError
    from selfid_jax.runner.lock import hold

    run_dir = Path(run_dir)
    if not (run_dir / LOG_FILE).is_file():
        return None
    with hold(run_dir):  # not while a session appends to it
        try:
            return write_figures(run_dir)
        except JournalError as err:
            raise RunDirError(f"{err}") from None
