"""Recorded self-ID logs -> sample pairs ``(dtheta (T, n), V (T, m))``, with bad rows rejected and counted.

Two layouts, told apart by their column names (other columns are ignored):

* **sample pairs**: ``dtheta_0 .. dtheta_{n-1}`` (actuator units) and
  ``V_0 .. V_{m-1}`` (task units), one pair per row, optionally a time ``t`` (s).
* **raw time series**: ``t`` (s), actuator positions ``q_0 .. q_{n-1}`` and
  the tracker pose: position ``p_x, p_y, p_z`` (length unit) and, when the
  task has a rotation axis, the orientation as a unit quaternion
  ``q_w, q_x, q_y, q_z`` or a rotation vector ``r_x, r_y, r_z`` (rad). Pairs
  are formed from consecutive kept rows: ``dtheta = q_t - q_{t-1}`` and
  ``V = [p_t - p_{t-1}, log(R_t R_{t-1}^T)]`` in the world (tracker) frame
  (:func:`selfid_jax.math.geometry.pose_difference`), restricted to the task
  axes.

Files: ``.csv`` (header row), ``.parquet`` and ``.npz`` (one 1-D array per
column); or, from Python, any mapping of column name -> 1-D array (a
``pandas.DataFrame`` too).

Bad rows are dropped and counted, one :class:`Rejection` per kind: a
non-finite entry in a used column, a zero quaternion, a timestamp equal to
(duplicated) or before (non-monotonic) the latest kept one, and, for the
time series, a pair spanning more than ``max_gap`` seconds. A log that cannot
be used at all (unreadable, a missing, misnumbered or duplicated column, text in
a number column, too few rows) raises :class:`LogError`, one line naming the file,
column and row.

These are the steps; :func:`selfid_jax.robot.read.read_log` runs them in
order on any log (with bags, units and continuous streams), as ``sj.fit``
and ``selfid-jax fit`` do.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from selfid_jax.systems.validation import AXIS_NAMES, TASK_DIMS, check_task_axes, default_axes

__all__ = ["LogError", "Rejection", "Samples", "prepare_table", "read_table", "read_table_units",
           "samples_from_table",
           "pairs_from_time_series", "parse_task", "DEFAULT_GAP_FACTOR"]

#: ``max_gap="auto"``: pairs spanning more than this many median time steps are dropped.
DEFAULT_GAP_FACTOR = 3.0

_INDEXED = re.compile(r"^(dtheta|V|q)_(\d+)$")
_POSITION = ("p_x", "p_y", "p_z")
_QUATERNION = ("q_w", "q_x", "q_y", "q_z")
_ROTVEC = ("r_x", "r_y", "r_z")
_FORMATS = (".csv", ".parquet", ".npz")


class LogError(ValueError):
    """A log that cannot be used at all; the one-line message names the file, column and row."""


class Rejection(NamedTuple):
    """One kind of rejected row (or pair) of a log."""

    reason: str  # what was wrong, e.g. "non-finite value"
    count: int  # type: ignore[assignment]  # shadows tuple.count: how many rows (pairs for "gap") were dropped
    first: str  # where the first one is, e.g. "line 12 (column q_3)"

    def line(self) -> str:
        """One line: ``3 rows rejected: non-finite value (first: line 12, column q_3)``."""
        unit = "pair" if self.reason.startswith("gap") else "row"
        return f"{self.count} {unit}{'s' if self.count != 1 else ''} rejected: {self.reason} (first: {self.first})"


class Samples(NamedTuple):
    """Sample pairs read from a log, with where each came from (numpy, float64)."""

    dtheta: np.ndarray  # (T, n) actuator changes, actuator units
    V: np.ndarray  # (T, m) pose changes, task units (length unit; rad for rotation axes)
    t: np.ndarray  # (T,) time of each sample (its later row), s; NaN without a time column
    row: np.ndarray  # (T,) int: 1-based data row (header not counted) of each sample's later row
    layout: str  # "pairs" or "time_series"
    rotation: str | None  # "quaternion", "rotation_vector" or None (position only / pairs)
    axes: tuple[int, ...] | None  # task components of V into (x, y, z, rx, ry, rz); None: unnamed V columns
    rows: int  # data rows in the log
    used_rows: int  # rows kept after the screens (and the time window)
    outside_window: int  # rows outside [start, stop] (not counted as rejected)
    max_gap: float | None  # gap limit applied (s), None where it does not apply
    rejected: tuple[Rejection, ...]  # one entry per kind of bad row, in screening order
    source: str  # the file (or "<table>")

    @property
    def axis_names(self) -> tuple[str, ...]:
        """Names of the task components, e.g. ``("x", "y", "z")``; ``V_j`` where unnamed."""
        if self.axes is None:
            return tuple(f"V_{j}" for j in range(self.V.shape[1]))
        return tuple(AXIS_NAMES[a] for a in self.axes)


def parse_task(task=None, task_dim=None) -> tuple[int, ...] | None:
    """Task axes from ``task`` (``"x,y,z"`` or a sequence of names/indices) or ``task_dim`` (2, 3, 6); None if both
    are None."""
    if task is not None and task_dim is not None:
        raise ValueError("give either a task (axis names) or a task dimension, not both")
    if task is not None:
        items = [s.strip() for s in task.split(",")] if isinstance(task, str) else list(task)
        return check_task_axes(items)
    if task_dim is not None:
        if isinstance(task_dim, bool) or not isinstance(task_dim, (int, np.integer)) or task_dim not in TASK_DIMS:
            raise ValueError(f"task dimension must be one of {TASK_DIMS}, got {task_dim!r}")
        return default_axes(int(task_dim))
    return None


def _where(source: str, i: int, column: str | None = None) -> str:
    """``line 12`` of a CSV (the header is line 1) or ``row 11`` elsewhere, with the column if given."""
    at = f"line {i + 2}" if source.lower().endswith(".csv") else f"row {i + 1}"
    return at if column is None else f"{at}, column {column}"


def read_table(path: str | Path) -> dict[str, np.ndarray]:
    """Columns of a CSV, Parquet or NPZ file as ``name -> 1-D array`` (unconverted); :class:`LogError` if unreadable."""
    return read_table_units(path)[0]


def read_table_units(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """:func:`read_table` and a CSV's units row as ``column -> unit`` ({} without one; :mod:`selfid_jax.robot.tables`:
    the delimiter and a decimal comma are detected)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _FORMATS:
        raise LogError(f"{path}: unknown log format {path.suffix or '(no suffix)'!r}; use one of {', '.join(_FORMATS)}")
    if not path.is_file():
        raise LogError(f"{path}: {'is a directory, not a log file' if path.is_dir() else 'no such file'}")
    try:
        if suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                _refuse_duplicates(str(path), z.files, "arrays")  # a zip may hold two members of one name
                return {k: z[k] for k in z.files}, {}
        import pandas as pd

        if suffix == ".csv":
            from selfid_jax.robot.tables import read_csv

            return read_csv(path, lambda names: _refuse_duplicates(str(path), names, "header columns"))
        else:
            df = pd.read_parquet(path)
            _refuse_duplicates(str(path), [str(c) for c in df.columns], "columns")
    except LogError:
        raise
    except Exception as err:  # noqa: BLE001 - pandas/pyarrow/numpy raise many types for a corrupt file
        detail = " ".join(str(err).split())[:200] or type(err).__name__
        raise LogError(f"{path}: cannot read as {suffix[1:]}: {detail}") from None
    return {str(k): df[k].to_numpy() for k in df.columns}, {}



def _refuse_duplicates(source: str, names: Sequence[str], what: str = "columns") -> None:
    """:class:`LogError` naming the first column name that ``names`` holds more than once (where they are)."""
    seen: dict[str, list[int]] = {}
    for i, name in enumerate(names):
        seen.setdefault(name, []).append(i + 1)
    for name, where in seen.items():
        if len(where) > 1 and name != "":  # an unnamed CSV column is not a name pandas would merge
            at = ", ".join(map(str, where[:-1])) + f" and {where[-1]}"
            raise LogError(f"{source}: column {name} appears {len(where)} times ({what} {at}); which one is meant "
                           "is ambiguous: give every column its own name")


def _numeric(source: str, name: str, values: Any, rows: int) -> np.ndarray:
    """Column ``name`` as float64 ``(rows,)``; :class:`LogError` naming the first entry that is not a number."""
    arr = np.asarray(values)
    if arr.ndim != 1 or arr.shape[0] != rows:
        raise LogError(f"{source}: column {name} has shape {arr.shape}, expected ({rows},) like the other columns")
    if arr.dtype.kind in "fiub":
        return arr.astype(np.float64)
    out = np.empty(rows, np.float64)
    for i, v in enumerate(arr):
        if v is None or (isinstance(v, str) and v.strip().lower() in ("", "nan")):
            out[i] = np.nan
            continue
        try:
            out[i] = float(v)
        except (TypeError, ValueError):
            raise LogError(f"{source}: {_where(source, i, name)}: {str(v)[:40]!r} is not a number") from None
    return out


def _indexed(source: str, columns: Sequence[str], prefix: str) -> list[str]:
    """``prefix_0 .. prefix_{k-1}`` as present; :class:`LogError` if the numbering has a hole or a repeat."""
    found = sorted(int(m.group(2)) for c in columns if (m := _INDEXED.match(c)) and m.group(1) == prefix)
    if not found:
        return []
    expected = list(range(len(found)))
    if found != expected:
        missing = sorted(set(range(max(found) + 1)) - set(found))
        what = f"column {prefix}_{missing[0]} is missing" if missing else f"column {prefix}_* numbered {found}"
        raise LogError(f"{source}: {what} (have {', '.join(f'{prefix}_{k}' for k in found)}); "
                       f"number them {prefix}_0 .. {prefix}_{len(found) - 1}")
    return [f"{prefix}_{k}" for k in expected]


def _need(source: str, columns: Sequence[str], names: Sequence[str], what: str) -> None:
    missing = [c for c in names if c not in columns]
    if missing:
        raise LogError(f"{source}: column {missing[0]} is missing ({what} needs {', '.join(names)})")


def pairs_from_time_series(q, p, R, axes: Sequence[int]):
    """Sample pairs of consecutive rows of a time series: ``(dtheta (T-1, n), V (T-1, m))``.

    ``q (T, n)`` actuator positions, ``p (T, 3)`` positions, ``R (T, 3, 3)``
    orientations (world frame; None for a position-only task); ``dtheta_t =
    q_t - q_{t-1}``, ``V_t = [p_t - p_{t-1}, log(R_t R_{t-1}^T)][axes]``
    (:func:`selfid_jax.math.geometry.pose_difference`). numpy in, numpy out.
    """
    q, p = np.asarray(q, np.float64), np.asarray(p, np.float64)
    axes = list(axes)
    dtheta = np.diff(q, axis=0)
    if R is None or all(a < 3 for a in axes):
        return dtheta, np.diff(p, axis=0)[:, axes]
    import jax

    from selfid_jax.math import geometry

    with jax.enable_x64(True):  # the pose math in float64 whatever the global setting (data, not traced code)
        R = jax.numpy.asarray(np.asarray(R, np.float64))
        full = geometry.pose_difference(p[1:], R[1:], p[:-1], R[:-1])
        full = np.asarray(full, np.float64)
    return dtheta, full[:, axes]


def rotations(kind: str, values: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)`` rotations (float64) of ``(K, 4)`` quaternions ``(w, x, y, z)`` (normalised here;
    ``kind="quaternion"``) or ``(K, 3)`` rotation vectors (``kind="rotation_vector"``)."""
    import jax

    from selfid_jax.math import geometry

    with jax.enable_x64(True):  # the pose math in float64 whatever the global setting (data, not traced code)
        v = jax.numpy.asarray(values, jax.numpy.float64)
        R = geometry.quaternion_to_rotation(v) if kind == "quaternion" else geometry.so3_exp(v)
        return np.asarray(R, np.float64)


def samples_from_table(
    table: Mapping[str, Any],
    *,
    task=None,
    task_dim=None,
    start: float | None = None,
    stop: float | None = None,
    max_gap: float | str | None = "auto",
    source: str = "<table>",
) -> Samples:
    """Sample pairs from a table of columns (see the module docstring); the screens and their counts in
    ``rejected``.

    Args:
      table: column name -> 1-D array (a ``dict``, an ``np.load`` result, a ``pandas.DataFrame``).
      task, task_dim: the task axes (``"x,y,z"``, ``("z", "rx")``, or 2/3/6 for
        the first components of ``[x, y, z, rx, ry, rz]``). Time series:
        default 3 (position). Sample pairs: must match the ``V_*`` columns (default: their count
        names the axes if it is 2, 3 or 6, else they stay unnamed).
      start, stop: keep rows with ``start <= t <= stop`` (s); need a ``t`` column.
      max_gap: time series only: drop pairs whose rows are more than this
        many seconds apart; ``"auto"``: :data:`DEFAULT_GAP_FACTOR` median
        time steps; None or ``inf``: no limit.
      source: the file name used in messages.
    """
    columns = [str(c) for c in table.keys()]
    _refuse_duplicates(source, columns)  # a DataFrame may hold two columns of one name
    rows = -1
    for c in columns:
        rows = int(np.shape(table[c])[0]) if np.ndim(table[c]) >= 1 else 0
        break
    if not columns or rows <= 0:
        raise LogError(f"{source}: no data rows")
    axes = parse_task(task, task_dim)
    dth, vv, qq = (_indexed(source, columns, k) for k in ("dtheta", "V", "q"))
    if (dth or vv) and qq:
        raise LogError(f"{source}: has both sample-pair columns ({(dth or vv)[0]}) and time-series columns "
                       f"({qq[0]}); keep one layout")
    has_t = "t" in columns
    if not has_t and (start is not None or stop is not None):
        raise LogError(f"{source}: --start/--stop need a time column 't'")

    def col(name):
        return _numeric(source, name, table[name], rows)

    rotation: str | None = None
    if dth or vv:
        layout = "pairs"
        if not dth:
            raise LogError(f"{source}: column dtheta_0 is missing (sample pairs need dtheta_0.. and V_0..)")
        if not vv:
            raise LogError(f"{source}: column V_0 is missing (sample pairs need dtheta_0.. and V_0..)")
        m = len(vv)
        if axes is None:
            axes = default_axes(m) if m in TASK_DIMS else None
        elif len(axes) != m:
            raise LogError(f"{source}: the task has {len(axes)} axes ({','.join(AXIS_NAMES[a] for a in axes)}) but "
                           f"the log has {m} V columns (V_0..V_{m - 1})")
        used = dth + vv
    elif qq:
        layout = "time_series"
        if not has_t:
            raise LogError(f"{source}: column t is missing (a time series needs t, q_0.., p_x, p_y, p_z)")
        axes = default_axes(3) if axes is None else axes
        _need(source, columns, _POSITION, "the tracker position")
        used = qq + list(_POSITION)
        if any(a >= 3 for a in axes):
            quat, rv = [c in columns for c in _QUATERNION], [c in columns for c in _ROTVEC]
            if all(quat) and any(rv) or all(rv) and any(quat):
                raise LogError(f"{source}: has both quaternion (q_w..) and rotation-vector (r_x..) columns; keep one")
            if any(quat):
                _need(source, columns, _QUATERNION, "a quaternion orientation")
                rotation = "quaternion"
            elif any(rv):
                _need(source, columns, _ROTVEC, "a rotation-vector orientation")
                rotation = "rotation_vector"
            else:
                names = ",".join(AXIS_NAMES[a] for a in axes)
                raise LogError(f"{source}: column q_w is missing: the task ({names}) has a rotation axis, which needs "
                               "q_w, q_x, q_y, q_z (unit quaternion) or r_x, r_y, r_z (rotation vector)")
            used += list(_QUATERNION if rotation == "quaternion" else _ROTVEC)
    else:
        raise LogError(f"{source}: no dtheta_0/V_0 (sample pairs) or q_0 (time series) column; found "
                       f"{', '.join(columns[:8])}{', ...' if len(columns) > 8 else ''}")
    if has_t:
        used = ["t", *used]
    data = {c: col(c) for c in used}

    keep = np.ones(rows, bool)
    rejected: list[Rejection] = []

    def reject(mask: Any, reason: str, first_column=None):
        nonlocal keep
        mask = mask & keep
        if mask.any():
            i = int(np.argmax(mask))
            rejected.append(Rejection(reason, int(mask.sum()), _where(source, i, first_column(i) if first_column
                                                                     else None)))
            keep = keep & ~mask

    finite = np.stack([np.isfinite(data[c]) for c in used], axis=1)
    reject(~finite.all(axis=1), "non-finite value", lambda i: used[int(np.argmin(finite[i]))])
    if rotation == "quaternion":
        wxyz = np.stack([data[c] for c in _QUATERNION], axis=1)
        norm = np.linalg.norm(np.where(finite[:, -4:], wxyz, 0.0), axis=1)
        reject(norm < 1e-6, "zero quaternion")
    outside = 0
    if has_t:
        t = data["t"]
        window = np.ones(rows, bool)
        if start is not None:
            window &= t >= start
        if stop is not None:
            window &= t <= stop
        outside = int((keep & ~window).sum())
        keep &= window
        # a row is kept iff its time is after every earlier kept row's (= the running max of kept times)
        prev = np.maximum.accumulate(np.where(keep, t, -np.inf))
        prev = np.concatenate([[-np.inf], prev[:-1]])
        reject(t == prev, "duplicated timestamp")
        reject(t < prev, "non-monotonic timestamp (earlier than a previous row)")
    idx = np.flatnonzero(keep)
    used_rows = int(idx.size)
    gap_limit: float | None = None
    if layout == "pairs":
        dtheta = np.stack([data[c][idx] for c in dth], axis=1)
        V = np.stack([data[c][idx] for c in vv], axis=1)
        t_s = data["t"][idx] if has_t else np.full(idx.size, np.nan)
        row = idx + 1
    else:
        assert axes is not None
        if idx.size < 2:
            raise LogError(f"{source}: {idx.size} usable row(s) after the screens; a time series needs at least 2")
        t_k = data["t"][idx]
        q = np.stack([data[c][idx] for c in qq], axis=1)
        p = np.stack([data[c][idx] for c in _POSITION], axis=1)
        R = None
        if rotation is not None:
            rot_columns = _QUATERNION if rotation == "quaternion" else _ROTVEC
            R = rotations(rotation, np.stack([data[c][idx] for c in rot_columns], axis=1))
        dtheta, V = pairs_from_time_series(q, p, R, axes)
        dt = np.diff(t_k)
        if max_gap == "auto":
            gap_limit = float(DEFAULT_GAP_FACTOR * np.median(dt))
        elif max_gap is not None and np.isfinite(float(max_gap)):
            gap_limit = float(max_gap)
            if not gap_limit > 0:
                raise ValueError(f"max_gap must be positive (s), got {max_gap!r}")
        ok = np.ones(dt.size, bool) if gap_limit is None else dt <= gap_limit
        if not ok.all():
            i = int(idx[1:][np.argmin(ok)])
            rejected.append(Rejection(f"gap longer than {gap_limit:.6g} s", int((~ok).sum()), _where(source, i)))
        dtheta, V = dtheta[ok], V[ok]
        t_s, row = t_k[1:][ok], idx[1:][ok] + 1
    return Samples(dtheta=dtheta, V=V, t=t_s, row=row.astype(np.int64), layout=layout, rotation=rotation, axes=axes,
                   rows=rows, used_rows=used_rows, outside_window=outside, max_gap=gap_limit,
                   rejected=tuple(rejected), source=source)


def prepare_table(table: Mapping[str, Any], *, columns=None, joint_names=None, units=None,
                  row_units: Mapping[str, str] | None = None, source: str = "<table>"
                  ) -> tuple[dict[str, Any], list[str], dict[str, str]]:
    """A lab's table in the fit's layout and units (:mod:`selfid_jax.robot.tables`): ``(table, notes, units used)``.

    ``columns``: a map ``log name -> fit name`` (or its ``"a=b,c=d"`` / file
    form); ``joint_names``: columns that become ``q_0 ..`` in this order;
    ``units``: a :class:`~selfid_jax.robot.tables.Units`; ``row_units``: a
    units row's ``column -> unit``. Raises :class:`LogError` naming the file
    (and a column name the table holds twice, before a dict could merge them).
    """
    from selfid_jax.robot import tables

    _refuse_duplicates(source, [str(c) for c in table.keys()])
    try:
        out, notes = tables.normalise(table, columns=tables.parse_columns(columns), joint_names=joint_names,
                                      source=source)
        units = (units or tables.Units()).check()
        out, used = tables.apply_units(out, units, row_units, source=source)
        stated = {c for c in used if c in (row_units or {}) or (tables.ANGLE_AUTO != units.angle
                                                                and used[c] in tables.ANGLE)}
        tables.check_plausible(out, used, source=source, stated=frozenset(stated))
    except LogError:
        raise
    except ValueError as err:
        raise LogError(str(err)) from None
    return out, notes, used

