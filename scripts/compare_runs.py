"""Compare two run directories of the same config: are their figures the same up to float32 round-off?

Run one sweep on two backends (a GPU and the CPU, or the CPU under two XLA
settings) and compare what each wrote:

* ``summary.json``: every leaf; strings, booleans and integers must be equal,
  floats are reported by their largest relative difference;
* ``results.parquet``: per column, the rows that differ (integer, boolean and
  string columns: any difference; float columns: beyond ``--rtol`` relative,
  with ``--atol`` absolute below that scale).

A float32 program compiled for another backend (or by another XLA emitter)
sums in another order; a closed-loop rollout of hundreds of steps can carry
that round-off far on rows near the edge of a valid region, so the report
counts rows rather than asserting every bit.

    python scripts/compare_runs.py RUN_A RUN_B [--rtol 1e-3] [--atol 1e-6] [--max-rows 0.01] [--json out.json]

Exit status 0 when both runs have the same rows, every discrete figure of
the summary and every boolean or string column agree, and at most
``--max-rows`` (default 1 %) of the rows differ in any column; 1 otherwise;
2 when a run directory is not a finished run. The differences are printed
either way.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd


def _leaves(tree, path=""):
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from _leaves(v, f"{path}.{k}" if path else str(k))
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            yield from _leaves(v, f"{path}[{i}]")
    else:
        yield path, tree


def compare_summaries(a: dict, b: dict) -> dict:
    """``{"discrete": [paths that differ], "missing": [paths in one only], "float_max_rel": x, "float_worst": path}``
    over the leaves of two summaries."""
    la, lb = dict(_leaves(a)), dict(_leaves(b))
    out: dict = {"discrete": [], "missing": sorted(set(la) ^ set(lb)), "float_max_rel": 0.0, "float_worst": None}
    for key in sorted(set(la) & set(lb)):
        x, y = la[key], lb[key]
        if isinstance(x, float) and isinstance(y, float | int) and not isinstance(y, bool):
            if math.isnan(x) and math.isnan(float(y)):
                continue
            rel = abs(x - y) / max(abs(x), abs(y), 1e-30)
            if rel > out["float_max_rel"]:
                out["float_max_rel"], out["float_worst"] = rel, key
        elif x != y:
            out["discrete"].append(key)
    return out


def compare_tables(a: pd.DataFrame, b: pd.DataFrame, rtol: float = 1e-3, atol: float = 1e-6) -> dict:
    """Per column of two results tables (same rows in the same order): ``{"rows": n, "columns": {name: {"kind",
    "differ": rows beyond tolerance, "max_abs", "max_rel"}}, "rows_differ": rows with any column beyond it,
    "discrete": boolean, string and object columns with any difference}``; raises ValueError if the tables' shapes or
    column names differ."""
    if list(a.columns) != list(b.columns) or len(a) != len(b):
        raise ValueError(f"the tables differ in shape: {len(a)} rows {list(a.columns)} against {len(b)} rows "
                         f"{list(b.columns)}")
    cols = {}
    for c in a.columns:
        x, y = a[c].to_numpy(), b[c].to_numpy()
        if x.dtype == object and len(x) and isinstance(x[0], np.ndarray | list):  # a vector per row
            try:
                x, y = np.stack(x).astype(np.float64), np.stack(y).astype(np.float64)
            except (ValueError, TypeError):
                diff = np.array([not np.array_equal(u, v) for u, v in zip(x, y, strict=True)])
                cols[c] = {"kind": "O", "differ": int(diff.sum()), "rows_differ": diff}
                continue
            x, y = x.reshape(len(x), -1), y.reshape(len(y), -1)
        if x.dtype.kind == "f":
            x, y = x.astype(np.float64), y.astype(np.float64)
            both_nan = np.isnan(x) & np.isnan(y)
            d = np.where(both_nan, 0.0, np.abs(x - y))
            d = np.where(np.isnan(d), np.inf, d)
            scale = np.maximum(np.abs(x), np.abs(y))
            bad = d > atol + rtol * np.where(np.isnan(scale), 0.0, scale)
            bad = bad.reshape(len(bad), -1).any(axis=1)
            rel = d / np.maximum(np.where(np.isnan(scale), 1.0, scale), atol)
            cols[c] = {"kind": "float", "differ": int(bad.sum()), "max_abs": float(d.max(initial=0.0)),
                       "max_rel": float(rel.max(initial=0.0)), "rows_differ": bad}
        else:
            cols[c] = {"kind": str(x.dtype.kind), "differ": int((x != y).sum()), "rows_differ": x != y}
    any_row = np.zeros(len(a), bool)
    for c in cols.values():
        any_row |= c.pop("rows_differ")
    discrete = [c for c, v in cols.items() if v["kind"] in ("b", "O", "U", "S", "T") and v["differ"]]
    return {"rows": len(a), "columns": cols, "rows_differ": int(any_row.sum()), "discrete": discrete}


def compare(run_a, run_b, rtol: float = 1e-3, atol: float = 1e-6, max_rows: float = 0.01) -> dict:
    """Both comparisons of two run directories, and ``ok``: the summaries' discrete figures and the tables'
    boolean and string columns equal, and at most a fraction ``max_rows`` of rows differing in any column (a float
    beyond ``rtol``, an integer such as a step count)."""
    run_a, run_b = Path(run_a), Path(run_b)
    for d in (run_a, run_b):
        for f in ("summary.json", "results.parquet"):
            if not (d / f).is_file():
                raise FileNotFoundError(f"{d / f}: missing (is {d} a finished run directory?)")
    s = compare_summaries(json.loads((run_a / "summary.json").read_text()),
                          json.loads((run_b / "summary.json").read_text()))
    t = compare_tables(pd.read_parquet(run_a / "results.parquet"), pd.read_parquet(run_b / "results.parquet"),
                       rtol, atol)
    ok = not s["discrete"] and not s["missing"] and not t["discrete"] and t["rows_differ"] <= max_rows * t["rows"]
    return {"summary": s, "table": t, "rtol": rtol, "atol": atol, "max_rows": max_rows, "ok": ok}


def report(res: dict, a="A", b="B") -> str:
    s, t = res["summary"], res["table"]
    lines = [f"{a} against {b}: {t['rows']} rows"]
    lines.append(f"summary.json: {len(s['discrete'])} discrete figures differ"
                 + (f" ({', '.join(s['discrete'][:8])})" if s["discrete"] else "")
                 + (f", {len(s['missing'])} in one run only" if s["missing"] else "")
                 + f"; floats within {s['float_max_rel']:.1e} relative"
                 + (f" (worst {s['float_worst']})" if s["float_worst"] else ""))
    for name, c in t["columns"].items():
        if c["kind"] == "float":
            lines.append(f"  {name:24s} float: {c['differ']:6d} rows beyond rtol {res['rtol']:g} "
                         f"({100 * c['differ'] / max(t['rows'], 1):.2f} %); max abs {c['max_abs']:.2e}, "
                         f"max rel {c['max_rel']:.2e}")
        else:
            lines.append(f"  {name:24s} {c['kind']}: {c['differ']:6d} rows differ")
    lines.append(f"rows differing in any column: {t['rows_differ']} ({100 * t['rows_differ'] / max(t['rows'], 1):.2f} "
                 f"%, at most {100 * res['max_rows']:g} % allowed); discrete columns differing: "
                 f"{', '.join(t['discrete']) or 'none'}")
    lines.append("agree within float32 round-off" if res["ok"] else "DIFFER")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_a")
    ap.add_argument("run_b")
    ap.add_argument("--rtol", type=float, default=1e-3)
    ap.add_argument("--atol", type=float, default=1e-6)
    ap.add_argument("--max-rows", type=float, default=0.01, help="fraction of rows allowed to differ")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    try:
        res = compare(args.run_a, args.run_b, args.rtol, args.atol, args.max_rows)
    except (FileNotFoundError, ValueError) as err:
        print(f"compare_runs: {err}", file=sys.stderr)
        return 2
    print(report(res, args.run_a, args.run_b))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2))
    return 0 if res["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
