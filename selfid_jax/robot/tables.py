"""A lab's log table -> the fit's layout: column names, units, time stamps, and CSV dialects.

:func:`selfid_jax.robot.read.read_log` reads a log through here
(:func:`selfid_jax.robot.log.prepare_table`) before it forms samples
(:func:`selfid_jax.robot.log.samples_from_table`):

* **CSV dialects** (:func:`read_csv`): the delimiter (``,``, ``;``, tab) is
  detected from the header, a decimal comma (``0,25`` with ``;``) too, and a
  **units row** right under the header (every entry a unit name, e.g. ``s``,
  ``rad``, ``mm``) is taken as the columns' units.
* **Column names** (:func:`normalise`): a map ``log name -> fit name``
  (``--columns``), named joints in a given order (``joint_names``: e.g. ROS's
  ``shoulder_pan_joint, ...`` become ``q_0, ...``), joints numbered from 1
  (``q_1 .. q_n`` with no ``q_0``) renumbered from 0, and the quaternion
  spelled ``qw, qx, qy, qz``.
* **Time stamps**: ISO 8601 strings (``2026-12-05T06:10:43.120Z``) become
  seconds since the first row.
* **Units** (:class:`Units`, :func:`apply_units`): positions in ``m``,
  ``cm`` or ``mm``; time in ``s``, ``ms``, ``us`` or ``ns``; angles (actuator
  positions and rotation vectors) in ``rad`` or ``deg``; each converted to
  m, s, rad before the fit. :func:`check_plausible` refuses magnitudes that
  the declared unit makes implausible (a tracked point 850 m from the origin,
  a time step of 1e7 s, a joint at 90 rad where no angle unit was stated: a
  multi-turn joint is read under a stated ``rad``) with a message naming the
  likely unit. The motion per move is checked against the units after the fit
  (:func:`selfid_jax.robot.quality.unit_warnings`).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

__all__ = ["ANGLE", "ANGLE_AUTO", "LENGTH", "TIME", "Units", "apply_units", "check_plausible", "normalise",
           "parse_columns", "read_csv"]

LENGTH = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
"""Length units the fit reads, in metres."""
TIME = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
"""Time units, in seconds."""
ANGLE = {"rad": 1.0, "deg": np.pi / 180.0}
"""Angle units (actuator positions of revolute joints, rotation vectors), in radians."""
ANGLE_AUTO = "auto"
"""The angle unit when none is stated: radians, and a joint beyond :data:`MAX_ANGLE_RAD` is refused as degrees
(stated ``rad``, multi-turn joints are read as they are)."""
UNIT_NAMES = {**LENGTH, **TIME, **ANGLE, "1": 1.0, "-": 1.0, "": 1.0}

# the plausibility bounds of check_plausible, in the converted units
MAX_POSITION_M = 10.0  # a tracked point farther than 10 m from the tracker's origin: the log is not in metres
MAX_STEP_S = 3600.0  # a median time step over an hour: the stamps are not in seconds
MAX_ANGLE_RAD = 4 * np.pi  # a revolute joint beyond two turns: the angles are not in radians
EPOCH_S = 1e8  # stamps beyond ~3 years are since the epoch: fine in s, ns as s would be ~1.7e18

_QUAT_ALIASES = {"qw": "q_w", "qx": "q_x", "qy": "q_y", "qz": "q_z"}


class Units(NamedTuple):
    """Declared units of a log's quantities (``--length``, ``--time``, ``--angle``)."""

    length: str = "m"  # tracker positions (p_*) and, in the sample-pair layout, the V position components
    time: str = "s"  # the t column
    angle: str = ANGLE_AUTO  # actuator positions q_* / dtheta_* and rotation vectors r_*: rad or deg as stated;
    #   "auto" (not stated): rad, positions beyond two turns refused as looking like degrees

    def check(self) -> Units:
        for name, table in (("length", LENGTH), ("time", TIME), ("angle", {ANGLE_AUTO: 1.0, **ANGLE})):
            if getattr(self, name) not in table:
                raise ValueError(f"--{name}: unknown unit {getattr(self, name)!r}; one of {', '.join(table)}")
        return self


def _kind(column: str) -> str | None:
    """Which unit a fit column is in: "time", "length", "angle" or None (quaternions, unitless)."""
    if column == "t":
        return "time"
    if column in ("p_x", "p_y", "p_z"):
        return "length"
    if re.fullmatch(r"(q|dtheta)_\d+|r_[xyz]", column):
        return "angle"
    return None


def parse_columns(spec: str | Path | Mapping[str, str] | None) -> dict[str, str]:
    """A column map ``log name -> fit name`` from ``"a=q_0,b=q_1"``, a YAML/JSON file of that mapping, or a dict."""
    if spec is None:
        return {}
    if isinstance(spec, Mapping):
        return {str(k): str(v) for k, v in spec.items()}
    text = str(spec)
    path = Path(text)
    if path.suffix.lower() in (".yaml", ".yml", ".json") or path.is_file():
        if not path.is_file():
            raise ValueError(f"--columns: no such file {text!r}")
        import yaml

        data = yaml.safe_load(path.read_text())
        if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
            raise ValueError(f"--columns {text}: expected a mapping of log column -> fit column (q_0, p_x, t, ...)")
        return {str(k): v for k, v in data.items()}
    out = {}
    for part in filter(None, (x.strip() for x in text.split(","))):
        if "=" not in part:
            raise ValueError(f"--columns: expected LOG_NAME=FIT_NAME pairs separated by commas, got {part!r}")
        k, v = (x.strip() for x in part.split("=", 1))
        out[k] = v
    return out


def read_csv(path: str | Path, check_names: Callable[[list[str]], None] | None = None
             ) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Columns of a CSV (``name -> 1-D array``: float64 where pandas reads numbers, else text) and the units row's
    ``name -> unit`` ({} if none).

    The delimiter is the one of ``,``, ``;`` and tab that splits the header
    most; with ``;`` or tab, a number written ``0,25`` is read as 0.25. A
    first data row whose every non-empty entry is a unit name is the units row.
    ``check_names`` is called on the header's names as written, before pandas
    reads the file (pandas renames a repeated name: the second ``q_0`` becomes
    ``q_0.1``).
    """
    import pandas as pd

    path = Path(path)
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        header, second = f.readline(), f.readline()
    sep = max((",", ";", "\t"), key=header.count)
    decimal = "," if sep != "," else "."
    names = [v.strip() for v in header.rstrip("\r\n").split(sep)] if header else []
    if check_names is not None:
        check_names(names)
    first = [v.strip() for v in second.rstrip("\r\n").split(sep)] if second.strip() else []
    units: dict[str, str] = {}
    if first and any(first) and all(v.lower() in UNIT_NAMES for v in first) and \
            not all(_is_number(v, decimal) for v in first if v):
        units = {n: v.lower() for n, v in zip(names, first) if v}
    df = pd.read_csv(path, sep=sep, decimal=decimal, skiprows=[1] if units else None, skipinitialspace=True,
                     encoding="utf-8-sig")
    return {str(k).strip(): df[k].to_numpy() for k in df.columns}, units


def _is_number(text: str, decimal: str) -> bool:
    try:
        float(text.replace(",", ".") if decimal == "," else text)
    except ValueError:
        return False
    return True


def normalise(table: Mapping[str, Any], *, columns: Mapping[str, str] | None = None,
              joint_names: Sequence[str] | None = None, source: str = "<table>"
              ) -> tuple[dict[str, Any], list[str]]:
    """The table with the fit's column names and ``t`` in numbers, and a note per change made.

    ``columns``: ``log name -> fit name`` (a name not in the log is refused,
    naming the log's columns). ``joint_names``: these columns, in this order,
    become ``q_0 ..`` (``dtheta_0 ..`` is not renamed). Then, when the log
    has no ``q_0``: ``q_1 .. q_n`` become ``q_0 .. q_{n-1}``; ``qw, qx, qy, qz``
    become ``q_w ..``; a ``t`` of ISO 8601 strings becomes seconds since its
    first row. Raises ValueError (a LogError in :mod:`selfid_jax.robot.log`).
    """
    out = dict(table)
    notes: list[str] = []
    names = list(out)
    for old, new in (columns or {}).items():
        if old not in out:
            raise ValueError(f"{source}: --columns names {old!r}, which is not a column (have {', '.join(names)})")
        if new in out and new not in (columns or {}):
            raise ValueError(f"{source}: --columns maps {old!r} to {new!r}, which the log already has")
    if columns:
        out = {columns.get(k, k): v for k, v in out.items()}
        notes.append("columns renamed: " + ", ".join(f"{k} -> {v}" for k, v in columns.items()))
    if joint_names:
        missing = [j for j in joint_names if j not in out]
        if missing:
            raise ValueError(f"{source}: joint {missing[0]!r} is not a column (have {', '.join(out)})")
        if any(re.fullmatch(r"q_\d+", k) for k in out if k not in joint_names):
            raise ValueError(f"{source}: has q_* columns and --joint-names; give one of them")
        renamed = {j: f"q_{i}" for i, j in enumerate(joint_names)}
        out = {renamed.get(k, k): v for k, v in out.items()}
        notes.append(f"joints {', '.join(joint_names)} -> q_0..q_{len(joint_names) - 1}")
    numbered = sorted(int(k[2:]) for k in out if re.fullmatch(r"q_\d+", k))
    if numbered and numbered[0] == 1 and numbered == list(range(1, len(numbered) + 1)):
        out = {(f"q_{int(k[2:]) - 1}" if re.fullmatch(r"q_\d+", k) else k): v for k, v in out.items()}
        notes.append(f"joints numbered from 1: q_1..q_{len(numbered)} -> q_0..q_{len(numbered) - 1}")
    if any(k in out for k in _QUAT_ALIASES) and not any(v in out for v in _QUAT_ALIASES.values()):
        out = {_QUAT_ALIASES.get(k, k): v for k, v in out.items()}
        notes.append("quaternion qw, qx, qy, qz -> q_w, q_x, q_y, q_z")
    if "t" in out:
        t = np.asarray(out["t"])
        if t.dtype.kind in "OUS" and t.size and not _numeric_strings(t):
            import pandas as pd

            try:
                stamps = pd.to_datetime(pd.Series(t), utc=True, format="ISO8601")
            except (ValueError, TypeError) as err:
                raise ValueError(f"{source}: column t is neither numbers nor ISO 8601 times ({str(t[0])[:40]!r}: "
                                 f"{' '.join(str(err).split())[:120]})") from None
            ns = stamps.astype("int64").to_numpy()
            out["t"] = (ns - ns[0]) * 1e-9
            notes.append(f"t from ISO 8601 times: seconds since {stamps.iloc[0].isoformat()}")
    return out, notes


def _numeric_strings(values: np.ndarray) -> bool:
    """True when the (string) entries read as numbers (the first non-empty few)."""
    seen = 0
    for v in values:
        s = str(v).strip()
        if not s or s.lower() == "nan":
            continue
        try:
            float(s)
        except ValueError:
            return False
        seen += 1
        if seen >= 5:
            break
    return True


def apply_units(table: Mapping[str, Any], units: Units, row_units: Mapping[str, str] | None = None,
                *, source: str = "<table>") -> tuple[dict[str, Any], dict[str, str]]:
    """Convert the fit's columns to m, s, rad; returns the table and each converted column's unit of origin.

    A column's unit is its units-row entry where there is one (a conflict with
    a declared unit other than the default is refused), else the declared
    ``units`` of its kind. Columns are converted to float64 only when scaled.
    """
    units = units.check()
    out = dict(table)
    used: dict[str, str] = {}
    for name in list(out):
        kind = _kind(name)
        if kind is None:
            continue
        unit = getattr(units, kind)
        if unit == ANGLE_AUTO:
            unit = "rad"
        if row_units and name in row_units:
            given = row_units[name]
            table_of = {"length": LENGTH, "time": TIME, "angle": ANGLE}[kind]
            if given not in table_of:
                raise ValueError(f"{source}: the units row gives column {name} the unit {given!r}; a {kind} column "
                                 f"takes one of {', '.join(table_of)}")
            if getattr(units, kind) not in (Units._field_defaults[kind], given):
                raise ValueError(f"{source}: column {name} is in {given} by the units row but --{kind} {unit}")
            unit = given
        used[name] = unit
        scale = {**LENGTH, **TIME, **ANGLE}[unit]
        if scale != 1.0:
            out[name] = _floats(out[name]) * scale
    return out, used


def _floats(values: Any) -> np.ndarray:
    arr = np.asarray(values)
    if arr.dtype.kind in "fiub":
        return arr.astype(np.float64)
    return np.array([np.nan if (v is None or str(v).strip() in ("", "nan")) else float(v) for v in arr], np.float64)


def check_plausible(table: Mapping[str, Any], used: Mapping[str, str], *, source: str = "<table>",
                    stated: frozenset[str] = frozenset()) -> None:
    """ValueError naming the likely unit when converted magnitudes are implausible (see the module docstring).

    ``stated``: the columns whose unit was stated (a declared ``--angle`` or a units row); a joint stated in rad may
    turn many times (a multi-turn joint), one whose unit was not stated is refused beyond :data:`MAX_ANGLE_RAD`."""

    def finite(name):
        try:
            v = _floats(table[name])
        except (TypeError, ValueError):
            return np.zeros(0)  # text: the layout's own check names it
        return v[np.isfinite(v)]

    pos = [finite(c) for c in ("p_x", "p_y", "p_z") if c in table]
    if pos and sum(x.size for x in pos):
        big = float(max(np.abs(x).max(initial=0.0) for x in pos))
        if big > MAX_POSITION_M:
            unit = used.get("p_x", "m")
            guess = "mm" if big < MAX_POSITION_M * 1000 else "a smaller unit"
            raise ValueError(f"{source}: the tracked positions reach {big:.4g} {unit} after conversion to m "
                             f"(limit {MAX_POSITION_M:g} m): they look like {guess}; declare it (--length mm, or a "
                             "units row) or convert the log")
    if "t" in table:
        t = finite("t")
        if t.size >= 2:
            step = float(np.median(np.abs(np.diff(t))))
            unit = used.get("t", "s")
            if step > MAX_STEP_S:
                guess = "ns" if step > 1e6 else "ms"
                raise ValueError(f"{source}: the median time step is {step:.4g} s after reading t in {unit} (limit "
                                 f"{MAX_STEP_S:g} s): the stamps look like {guess}; declare it (--time {guess}, or "
                                 "a units row)")
    qs = [c for c in table if re.fullmatch(r"q_\d+", c)]
    if qs:
        big = max(float(np.abs(finite(c)).max(initial=0.0)) for c in qs)
        if big > MAX_ANGLE_RAD and all(used.get(c, "rad") == "rad" and c not in stated for c in qs):
            raise ValueError(f"{source}: an actuator position reaches {big:.4g} rad (more than two turns, "
                             f"{MAX_ANGLE_RAD:.4g} rad) and no angle unit was stated: the joints look like degrees, "
                             "or a joint turns many times; state it: --angle deg (or a units row) if the joints are in "
                             "degrees, --angle rad if a joint turns more than twice (a multi-turn joint); a wrong one "
                             "scales the estimate by 57")
