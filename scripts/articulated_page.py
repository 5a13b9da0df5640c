"""The full-population tables of ``docs/results/articulated.md``, rendered from the run of
``configs/articulated/articulated_full.yaml`` (the paper's 200 objects) or from the data file written from it.

    python scripts/articulated_page.py [--run runs/articulated_full] [--json docs/results/data/articulated.json]
                                       [--page docs/results/articulated.md]
    python scripts/articulated_page.py --from-json docs/results/data/articulated.json \
        --page docs/results/articulated.md

``--json`` writes the numbers the tables are made of (the run's per arm x controller and per kind statistics, its
time ratios, its population and how long it ran); ``--from-json`` renders from such a file; ``--page`` rewrites the
page's generated blocks (between ``<!-- articulated:NAME -->`` and ``<!-- /articulated:NAME -->``), which
``tests/test_results_pages.py`` checks against the JSON: the page cannot drift from the JSON. The JSON
names its runs with their fingerprints (``"provenance"``); with ``--keep-rows`` the runs' rows are copied to
``docs/results/data/runs/`` and the test recomputes every number from them (``from_rows``). Success is over every
rollout; time, efficiency and jerk are mean +- sd over the successful ones, as the paper counts them.
"""

from __future__ import annotations

from pathlib import Path

import yaml
from page_blocks import ROWS, cli, provenance_block, run_summary  # scripts/page_blocks.py (python scripts/NAME.py)

CONFIG = "configs/articulated/articulated_full.yaml"
ARMS = {"true": "true", "selfid": "self-ID"}
CONTROLLERS = {"tacman": "`tacman`", "turbo": "`turbo` (literal)", "turbo_lead": "`turbo_lead` (ours)"}
KEEP = ("n", "success_rate", "slips", "alpha_min", "time_s", "efficiency_60hz", "jerk_tw")
PAPER_ROWS = (
    "| paper (Isaac Sim, Franka + RMPFlow, 200 objects) | Tac-Man | 100 % | 250.7 +- 194.4 | 0.012 +- 0.011 | "
    "4921.44 +- 3722.49 | - | 200 |",
    "| paper | TacMan-Turbo | 100 % | 7.6 +- 2.3 | 0.239 +- 0.063 | 109.82 +- 147.71 | - | 200 |",
)


NAME = "articulated_full"


def runs(where: Path) -> dict[str, tuple[Path, str]]:
    """The run behind the page: ``{name: (run directory, config)}``."""
    return {NAME: (where, CONFIG)}


def from_rows(rows: Path = ROWS) -> dict:
    """The numbers recomputed from the run's kept rows (``rows/articulated_full``), without provenance."""
    return extract(rows / NAME)


def extract(run: Path) -> dict:
    """The run's statistics per arm x controller (``overall``) and per kind, its time ratios and population."""
    if not (run / "results.parquet").exists():
        raise SystemExit(f"{run}: no results.parquet; run: selfid-jax sweep {CONFIG}")
    summary = run_summary(run)
    cfg = yaml.safe_load((run / "config.yaml").read_text())

    def keep(stats: dict) -> dict:
        return {k: stats[k] for k in KEEP if k in stats}

    return {"config": CONFIG, "objects": summary["objects"], "seed": cfg.get("seed"),
            "resistance": cfg.get("resistance"), "max_time": summary["max_time"],
            "contact_rule": summary["contact_rule"],
            "overall": {a: {c: keep(m) for c, m in cs.items()} for a, cs in summary["overall"].items()},
            "kinds": {k: {a: {c: keep(m) for c, m in cs.items()} for a, cs in arms.items()}
                      for k, arms in summary["kinds"].items()},
            "time_ratios": summary["time_ratios"]}


def _pct(rate: float) -> str:
    """A success rate in %, to a tenth where a whole number would round it (199 of 200 is 99.5 %, not 100 %)."""
    pct = 100 * rate
    return f"{pct:.0f} %" if abs(pct - round(pct)) < 1e-9 else f"{pct:.1f} %"


def _ms(m: dict, digits: int) -> str:
    return "-" if m.get("mean") is None else f"{m['mean']:.{digits}f} +- {m['sd']:.{digits}f}"


def overall_table(data: dict) -> str:
    """Per arm x controller over the whole population, below the paper's two rows. Markdown."""
    lines = ["| arm | controller | success | time [s] | efficiency [% per 60 Hz step] | time-weighted jerk [s^-3] | "
             "slips | n |", "|---|---|---|---|---|---|---|---|", *PAPER_ROWS]
    for arm, arm_label in ARMS.items():
        for ctrl, ctrl_label in CONTROLLERS.items():
            m = data["overall"].get(arm, {}).get(ctrl)
            if m is None:
                continue
            lines.append(f"| {arm_label} | {ctrl_label} | {_pct(m['success_rate'])} | {_ms(m['time_s'], 1)} | "
                         f"{_ms(m['efficiency_60hz'], 3)} | {_ms(m['jerk_tw'], 1)} | {m['slips']} | {m['n']} |")
    return "\n".join(lines)


def kinds_table(data: dict) -> str:
    """Success and time per kind, arm and controller, and the Tac-Man / Turbo time ratios. Markdown."""
    ctrls = [c for c in CONTROLLERS if any(c in cs for arms in data["kinds"].values() for cs in arms.values())]
    lines = ["| kind | arm | " + " | ".join(CONTROLLERS[c] for c in ctrls) + " |",
             "|---|---|" + "---|" * len(ctrls)]
    for kind, arms in data["kinds"].items():
        for arm, arm_label in ARMS.items():
            cs = arms.get(arm, {})
            cells = [f"{_pct(cs[c]['success_rate'])}, {_ms(cs[c]['time_s'], 1)} s (n {cs[c]['n']})"
                     if c in cs else "-" for c in ctrls]
            lines.append(f"| {kind} | {arm_label} | " + " | ".join(cells) + " |")
    lines += ["", ratios_text(data)]
    return "\n".join(lines)


def _successes(m: dict) -> int:
    return round(m["success_rate"] * m["n"])


def ratios_text(data: dict) -> str:
    """Tac-Man's time over each Turbo's, saying what each ratio divides and how many successes each mean rests on,
    overall and (like for like, against ``turbo_lead``) per kind. Markdown."""
    ratios = []
    for arm, rs in data["time_ratios"].items():
        for pair in ("tacman/turbo", "tacman/turbo_lead"):
            if pair not in rs:
                continue
            v = rs[pair]
            num, den = (data["overall"][arm][c] for c in pair.split("/"))
            ratios.append(f"{ARMS.get(arm, arm)} arm {pair}: " + ("-" if v is None else (
                f"{v:.1f}x ({num['time_s']['mean']:.1f} s over {_successes(num)} successes / "
                f"{den['time_s']['mean']:.1f} s over {_successes(den)})")))
    per_kind = []
    for kind, arms in data["kinds"].items():
        cells = []
        for arm in ARMS:
            cs = arms.get(arm, {})
            if "tacman" in cs and "turbo_lead" in cs and cs["turbo_lead"]["time_s"].get("mean"):
                cells.append(f"{cs['tacman']['time_s']['mean'] / cs['turbo_lead']['time_s']['mean']:.1f}x")
        if cells:
            per_kind.append(f"{kind} {' / '.join(cells)}")
    text = ("Time ratios: Tac-Man's mean time to success over the other controller's, each over its own successful "
            f"rollouts of the {sum(data['objects'].values())} objects (the paper's Tac-Man / TacMan-Turbo: 250.7 s / "
            "7.6 s = 33x, both over all 200 objects): " + "; ".join(ratios) + ".")
    if per_kind:
        text += (" Like for like, `tacman` / `turbo_lead` per kind (" + " / ".join(ARMS.values()) + " arm): "
                 + ", ".join(per_kind) + ".")
    turbo = [_successes(cs["turbo"]) for cs in data["overall"].values() if "turbo" in cs]
    if turbo:
        text += (f" The literal `turbo`'s ratios rest on its {' and '.join(map(str, turbo))} successes "
                 f"({' and '.join(ARMS.get(a, a) for a in data['overall'] if 'turbo' in data['overall'][a])} arm).")
    return text


def blocks(data: dict) -> dict[str, str]:
    """The generated blocks of the page: ``{"full": ..., "kinds": ..., "provenance": ...}``."""
    return {"full": overall_table(data), "kinds": kinds_table(data),
            "provenance": provenance_block(data.get("provenance", []))}


def main():
    cli(__doc__, "articulated", extract, blocks, run_flag="--run", run_default="runs/articulated_full",
        runs=runs, from_rows=from_rows)


if __name__ == "__main__":
    main()
