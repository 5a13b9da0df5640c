"""A fit from a recorded log written into a run directory: estimates, inverse Jacobian, summary, figure.

:func:`fit_to_run` is ``selfid-jax fit`` from Python: it runs
:func:`selfid_jax.robot.offline.fit` (``sj.fit``, same keywords, same
defaults) and writes, each file whole (:mod:`selfid_jax.runner.files`),
under the run directory's lock:

* ``estimates.npz``: ``estimates (T, n, m)`` after every sample, ``deltas (T,)``
  (``||J_t - J_{t-1}||_F``), ``thresholds (T,)``, ``accepted (T,)``, ``t (T,)``
  and ``row (T,)`` (the log row of each sample);
* ``inverse_jacobian.npz`` / ``.json`` (a converged fit only, and with
  ``strict`` one with no trust warning): the final refined estimate with
  ``n``, ``m``, the task axes, the convergence iteration, sample counts,
  units and its trust record (``trust``: the figures, the warnings and the
  report of how the log was read,
  :func:`selfid_jax.robot.quality.trust_record`), which ``selfid-jax online
  --estimate`` shows and checks;
* ``summary.json`` (:func:`summary`): options, counts, rejected rows by
  reason, the trust figures (:func:`selfid_jax.robot.quality.trust`), units,
  notes on how the log was read, and a camera tracker's frames, dropouts,
  tag edge and intrinsics;
* ``figures/convergence.png`` / ``.pdf`` (:func:`draw`), redrawn from the
  files alone by :func:`redraw` (``selfid-jax plot RUN``).

numpy, JAX and matplotlib are imported when a function runs, so the command
line that imports this module starts fast.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from selfid_jax.robot.log import Samples
    from selfid_jax.robot.offline import FitResult

__all__ = ["ESTIMATES_FILE", "FIGURE", "JINV_JSON", "JINV_NPZ", "SUMMARY_FILE", "UNITS", "default_run_dir", "draw",
           "draw_convergence", "estimate_units", "fit_to_run", "redraw", "report_lines", "summary", "withheld",
           "write_run"]

ESTIMATES_FILE = "estimates.npz"
JINV_NPZ = "inverse_jacobian.npz"
JINV_JSON = "inverse_jacobian.json"
SUMMARY_FILE = "summary.json"
FIGURE = "convergence"

UNITS = {"actuator": "rad (or m for a prismatic actuator)", "length": "m", "time": "s", "rotation": "rad"}
"""The units of a fit's outputs: every input is converted to these (--length, --time, --angle, a units row)."""


def default_run_dir(log: str | Path | Mapping[str, Any] | Samples) -> Path:
    """``runs/fit_<log stem>`` for a log file, ``runs/fit_table`` for a table given from Python."""
    return Path("runs") / (f"fit_{Path(log).stem}" if isinstance(log, (str, Path)) else "fit_table")


def fit_to_run(log: str | Path | Mapping[str, Any] | Samples, out: str | Path, *, strict: bool = False,
               **options: Any) -> tuple[FitResult, dict[str, Path]]:
    """Fit ``log`` (:func:`selfid_jax.robot.offline.fit` with ``options``) and write the run directory ``out``:
    ``(result, files)``, ``files`` mapping each written file's name (``figures/convergence.png``, ..) to its path.

    ``options``: ``sj.fit``'s keywords, the ``selfid-jax fit`` flags' (``task``,
    ``eps``, ``eps_rel``, ``method``, ``start``, ``latency``, ``joints``, ...).
    Nothing is written unless the log is read and fitted: bad options, an
    unusable log and a folder that holds a sweep's run directory are refused
    first. Only a converged fit writes ``inverse_jacobian.*`` (:func:`write_run`); with ``strict`` (``--strict``),
    only one with no trust warning.

    Raises:
      RunDirError: ``out`` holds a sweep's run directory (``config.yaml``), or is a file.
      RunDirBusy: another process writes into ``out``.
      LogError, ValueError: as :func:`selfid_jax.robot.offline.fit`.
    """
    from selfid_jax.robot.offline import fit
    from selfid_jax.runner import signals
    from selfid_jax.runner.errors import RunDirError
    from selfid_jax.runner.lock import hold

    out = Path(out)
    if (out / "config.yaml").exists():
        raise RunDirError(f"{out}: holds a sweep's run directory (config.yaml); choose another --out")
    signals.phase("fit")
    result = fit(log, **options)
    with hold(out):
        signals.phase("write")
        files = write_run(result, out, log=result.report.source, strict=strict)
    return result, files


def _npz(**arrays) -> bytes:
    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def estimate_units(axis_names: Sequence[str]) -> list[str]:
    """The unit of each column of the estimate: ``rad/m`` for a position axis, ``rad/rad`` for a rotation axis."""
    return [f"rad/{'rad' if a.startswith('r') else 'm'}" for a in axis_names]


def summary(result: FitResult, *, log: Path | str) -> dict[str, Any]:
    """``summary.json`` of a fit: options, sample counts, rejected rows, convergence, the trust figures
    (``result.trust``), units and how the log was read (``result.report``)."""
    s = result.samples
    n, m = result.estimate.shape
    T = int(result.deltas.shape[0])
    return {
        "command": "fit",
        "log": str(log),
        "layout": s.layout,
        "rotation": s.rotation,
        "n": n,
        "m": m,
        "task_axes": list(s.axis_names),
        "eps": result.eps,
        "eps_rel": result.eps_rel,
        "refine": result.method,
        "rows": s.rows,
        "rows_used": s.used_rows,
        "rows_outside_window": s.outside_window,
        "max_gap_s": s.max_gap,
        "samples": T,
        "samples_accepted": int(result.accepted.sum()),
        "rejected": [{"reason": r.reason, "count": r.count, "first": r.first} for r in s.rejected],
        "converged_at": result.converged_at,
        "converged": result.converged,
        "converged_time_s": result.converged_time,
        "converged_row": int(s.row[result.converged_at - 1]) if result.converged else None,
        "final_delta": float(result.deltas[-1]),
        "final_threshold": float(result.thresholds[-1]),
        # how far to trust the fit (selfid_jax.robot.quality.trust): the forward map's leave-one-out error, the
        # estimate's condition number, each actuator's task motion for the largest sample step, the fraction of
        # rows and samples refused, and a warning per figure outside its bound
        **result.trust.figures(),
        "actuators": list(result.trust.actuators),  # how the warnings name each actuator (the log's names)
        "warnings": list(result.trust.warnings),
        "units": UNITS,
        "estimate_units": estimate_units(s.axis_names),
        "converted_from": dict(result.report.units),  # column -> the unit it was read in (converted to UNITS)
        "notes": list(result.report.notes),  # how the log was read (a bag, renamed columns, units, a stream)
        "camera": _camera(result),  # frames, dropouts by reason, the tag and its edge, the intrinsics; None without
    }


def _camera(result: FitResult) -> dict[str, Any] | None:
    """The camera's report (:class:`selfid_jax.robot.camera.sources.CameraReport`) as JSON: None without a camera."""
    camera = result.report.camera
    if camera is None:
        return None
    return {**camera._asdict(), "other_ids": {str(k): v for k, v in camera.other_ids.items()}}


def draw(result: FitResult):
    """Figure of ``||J_t - J_{t-1}||_F`` per sample (log scale) with the threshold and the convergence iteration."""
    return draw_convergence(result.deltas, result.thresholds, eps=result.eps, eps_rel=result.eps_rel,
                            converged_at=result.converged_at, accepted=result.accepted,
                            title=f"self-ID from {Path(result.samples.source).name}: n={result.estimate.shape[0]}, "
                            f"task {','.join(result.samples.axis_names)}")


def draw_convergence(deltas, thresholds, *, eps: float, eps_rel: float, converged_at: int, title: str,
                     accepted=None):
    """``||J_t - J_{t-1}||_F`` per sample ``deltas (T,)`` (log scale) against the Sec. IV-D threshold
    ``thresholds (T,)``, with the convergence iteration (1-based; < 1: none); ``fit``'s and ``online``'s figure.

    Samples the estimator refused (``accepted (T,)`` False) and zero or
    non-finite changes are not drawn as values but marked along the bottom;
    the axis spans the drawn values and the threshold, so neither a refused
    sample nor a zero change stretches it, and the threshold is always in view."""
    import numpy as np
    from matplotlib.figure import Figure

    deltas, thresholds = np.asarray(deltas, np.float64), np.asarray(thresholds, np.float64)
    T = deltas.shape[0]
    k = np.arange(1, T + 1)
    ok = np.ones(T, bool) if accepted is None else np.asarray(accepted, bool)
    shown = ok & np.isfinite(deltas) & (deltas > 0)
    thr = np.isfinite(thresholds) & (thresholds > 0)
    fig = Figure(figsize=(6.4, 3.6))
    ax = fig.subplots()
    ax.set_yscale("log")
    ax.plot(k[shown], deltas[shown], "o-", ms=3, lw=1, label=r"$\|J_t - J_{t-1}\|_F$")
    ax.plot(k[thr], thresholds[thr], "--", color="0.4", lw=1, gid="threshold",
            label=rf"$\epsilon + \epsilon_{{rel}} \|J_t\|_F$ ($\epsilon$={eps:g}, "
            rf"$\epsilon_{{rel}}$={eps_rel:g})")
    values = np.concatenate([deltas[shown], thresholds[thr]])
    lo, hi = (float(values.min()), float(values.max())) if values.size else (1e-3, 1.0)
    lo, hi = lo / 3.0, max(hi * 3.0, lo * 10.0)
    ax.set_ylim(lo, hi)
    marked = ~shown
    if marked.any():
        ax.plot(k[marked], np.full(int(marked.sum()), lo * 1.3), "x", color="C3", ms=4, gid="refused",
                label=f"refused or zero change ({int(marked.sum())})")
    if converged_at >= 1:
        ax.axvline(converged_at, color="C3", lw=1.2, label=f"converged at sample {converged_at}")
    ax.set_xlabel("sample")
    ax.set_ylabel(r"$\|J_t - J_{t-1}\|_F$")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    return fig


def redraw(run_dir: Path) -> list[Path] | None:
    """Redraw ``figures/convergence`` of a ``fit`` run directory from its ``estimates.npz`` and ``summary.json``
    (``selfid-jax plot RUN``); None when ``run_dir`` is not one (no ``fit`` summary)."""
    import json

    import numpy as np

    from selfid_jax.runner.errors import RunDirError
    from selfid_jax.runner.figures import save_figure
    from selfid_jax.runner.layout import FIGURES_DIR
    from selfid_jax.runner.lock import hold

    run_dir = Path(run_dir)
    try:
        info = json.loads((run_dir / SUMMARY_FILE).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(info, dict) or info.get("command") != "fit":
        return None
    with hold(run_dir):  # not while a fit writes it
        try:
            with np.load(run_dir / ESTIMATES_FILE) as z:
                deltas, thresholds, accepted = z["deltas"], z["thresholds"], z["accepted"]
        except (OSError, ValueError, KeyError) as err:
            raise RunDirError(f"{run_dir / ESTIMATES_FILE}: cannot be read ({err}); run selfid-jax fit again"
                              ) from None
        fig = draw_convergence(deltas, thresholds, eps=float(info["eps"]), eps_rel=float(info["eps_rel"]),
                               converged_at=int(info["converged_at"]), accepted=accepted,
                               title=f"self-ID from {Path(str(info.get('log', '?'))).name}: n={info.get('n')}, "
                               f"task {','.join(info.get('task_axes', []))}")
        return save_figure(fig, run_dir / FIGURES_DIR, FIGURE)


def withheld(result: FitResult, *, strict: bool = False) -> str | None:
    """Why a fit writes no estimate file (one line), or None when it writes one: it did not converge, or ``strict``
    and a trust figure is out of bounds (its warnings)."""
    if not result.converged:
        return "not converged"
    if strict and result.trust.warnings:
        return f"--strict and {len(result.trust.warnings)} trust warning(s)"
    return None


def report_lines(result: FitResult) -> list[str]:
    """How a fit's estimate was made, one line each (the estimate file's ``report``): the log, how it was read
    (``result.notes``), the rows refused and the samples the estimator refused."""
    s = result.samples
    lines = [f"{s.source}: {s.rows} rows, {s.layout.replace('_', ' ')}; {result.deltas.shape[0]} samples"]
    lines += list(result.notes) + [r.line() for r in s.rejected]
    if s.outside_window:
        lines.append(f"{s.outside_window} rows outside --start/--stop (ignored)")
    refused = int((~result.accepted).sum())
    if refused:
        lines.append(f"{refused} samples refused by the estimator (all-zero dtheta or V)")
    return lines


def write_run(result: FitResult, out: Path, *, log: Path | str, strict: bool = False) -> dict[str, Path]:
    """Write every output file of a fit into ``out`` (each atomically); returns name -> path.

    Only a converged fit writes ``inverse_jacobian.npz`` / ``.json``, and with
    ``strict`` only one with no trust warning (:func:`withheld`); one that
    does not removes those of an earlier fit there, so no file can be taken
    for its result, and ``summary.json`` then holds ``estimate_so_far`` and
    ``estimate_withheld`` (why). The estimate files carry the fit's
    :func:`~selfid_jax.robot.quality.trust_record` (``trust``; in the npz a
    JSON string)."""
    import json

    import numpy as np

    from selfid_jax.robot.quality import TRUST_KEY, trust_record
    from selfid_jax.runner.figures import save_figure
    from selfid_jax.runner.files import atomic_write_bytes, write_json
    from selfid_jax.runner.layout import FIGURES_DIR

    out = Path(out)
    s = result.samples
    info = summary(result, log=log)
    why = withheld(result, strict=strict)
    paths = {name: out / name for name in (ESTIMATES_FILE, SUMMARY_FILE)}
    atomic_write_bytes(paths[ESTIMATES_FILE], _npz(
        estimates=result.estimates, deltas=result.deltas, thresholds=result.thresholds, accepted=result.accepted,
        t=s.t, row=s.row, converged_at=np.int64(result.converged_at)))
    if why is None:
        paths.update({name: out / name for name in (JINV_NPZ, JINV_JSON)})
        meta = {k: info[k] for k in ("n", "m", "task_axes", "converged_at", "converged", "samples",
                                     "samples_accepted", "rows", "rows_used", "refine", "eps", "eps_rel")}
        record = trust_record(source="fit", log=str(log), converged=result.converged,
                              converged_at=result.converged_at, trust=result.trust, report=report_lines(result))
        atomic_write_bytes(paths[JINV_NPZ], _npz(
            inverse_jacobian=result.estimate, initial_guess=result.initial_guess,
            task_axes=np.array(info["task_axes"]), estimate_units=np.array(info["estimate_units"]),
            **{k: np.asarray(v) for k, v in meta.items() if k != "task_axes"},
            **{TRUST_KEY: np.array(json.dumps(record))}))
        write_json(paths[JINV_JSON], {"inverse_jacobian": result.estimate, "initial_guess": result.initial_guess,
                                      **meta, "units": UNITS, "estimate_units": info["estimate_units"],
                                      "log": str(log), TRUST_KEY: record})
    else:
        for name in (JINV_NPZ, JINV_JSON):
            (out / name).unlink(missing_ok=True)
        info["estimate_so_far"] = result.estimate
        info["estimate_withheld"] = why
    write_json(paths[SUMMARY_FILE], info)
    fig_paths = save_figure(draw(result), out / FIGURES_DIR, FIGURE)
    return {**{p.name: p for p in paths.values()}, **{f"figures/{p.name}": p for p in fig_paths}}
