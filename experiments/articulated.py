"""Articulated objects (seed 003): Tac-Man vs TacMan-Turbo on drawers, doors, cranks and Bezier tracks.

Rows: object x controller x arm inverse Jacobian, one part (one compiled
program) per object kind. Each row runs self-ID (Algorithm 1, the project's
own method) on the UR5e at its start configuration, returns there, grasps
the handle, and runs one closed-loop rollout (:mod:`selfid_jax.articulated.sim`)
with the true inverse Jacobian or the fixed self-identified estimate.
Metrics (seed Sec. 4.3): success (revolute/helical > 60 deg, prismatic >
250 mm, Bezier: 98 % of the track), time to success [s], action efficiency
[% of the path per control step], jerk [rad/s^3], mean and max contact
deviation [mm], steps with an invalid contact set (Eq. 11-12), slips and
non-finite states (counted, never NaN).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import BaseModel, Field, model_validator

from selfid_jax.identify import algorithm as selfid
from selfid_jax.articulated import scenes, sim, tactile
from selfid_jax.experiments.common.schema import SelfIdConfig, StudyConfig, add_m_a_columns, m_a_summary
from selfid_jax.runner.config import STRICT
from selfid_jax.runner import Experiment, Part, precision
from selfid_jax.runner.figures import save_figure
from selfid_jax.runner.grids import grid_table, row_keys

METRICS = ("time_s", "efficiency", "jerk", "dev_mean_mm", "dev_max_mm")


class Objects(BaseModel):
    """How many objects of each kind (paper: 50 prismatic, 50 revolute, 100 Bezier)."""

    model_config = STRICT
    prismatic: int = Field(0, ge=0, le=10**4)
    revolute: int = Field(0, ge=0, le=10**4)
    helical: int = Field(0, ge=0, le=10**4)
    bezier: int = Field(0, ge=0, le=10**4)


class Population(BaseModel):
    """Ranges of the object generator (:func:`selfid_jax.articulated.scenes.population`)."""

    model_config = STRICT
    misalign_deg: float = Field(15.0, ge=0, le=60, description="max angle between u0 and the true initial direction")
    damping: tuple[float, float] = (2.0, 20.0)  # N s/m at the handle
    frictionloss: tuple[float, float] = (0.5, 3.0)  # N at the handle
    radius: tuple[float, float] = (0.25, 0.45)  # door radius [m]
    crank: tuple[float, float] = (0.1, 0.2)  # helical crank radius [m]
    pitch: tuple[float, float] = (0.005, 0.02)  # helical pitch [m/rad]
    track: tuple[float, float] = (0.25, 0.35)  # Bezier track length [m]
    amplitude: float = Field(0.06, ge=0, le=0.5, description="Bezier control-point lateral range [m]")


class Pads(BaseModel):
    model_config = STRICT
    rows: int = Field(8, ge=1, le=32)
    cols: int = Field(8, ge=1, le=32)
    pitch: float = Field(0.0025, gt=0, le=0.01, description="marker pitch [m]")
    marker_noise: float = Field(5e-6, ge=0, le=1e-3, description="marker reading noise sd [m]")
    contact_eps: float = Field(3e-4, gt=0, le=1e-2, description="Eq. 2 threshold on normal deformation [m]")


class TacManCfg(BaseModel):
    model_config = STRICT
    dev_high: float = Field(1e-3, gt=0, le=0.01, description="deviation ending an exploration stage [m]")
    dev_low: float = Field(2e-4, gt=0, le=0.01, description="deviation ending a recovery stage [m]")
    recovery_gain: float = Field(0.5, gt=0, le=1, description="fraction of the in-hand pose removed per recovery "
                                 "step")

    @model_validator(mode="after")
    def _order(self):
        if not self.dev_low < self.dev_high:
            raise ValueError(f"tacman.dev_low ({self.dev_low}) must be below tacman.dev_high ({self.dev_high})")
        return self


class TurboLeadCfg(BaseModel):
    """``turbo_lead`` (:func:`selfid_jax.articulated.tacman.lead_step`): integral lead and twist smoothing.

    ``lead_max`` 1 mm: Tac-Man's ``dev_high`` (the deviation it still calls
    safe), 5x below the 5 mm slip, and at ``gel_k`` 20 kN/m a 20 N pull, 5x
    the population's largest resistance; with a 15 deg misalignment its
    normal component (0.26 mm) stays below the 0.7 mm that lifts a pad off
    (squeeze 1 mm, ``contact_eps`` 0.3 mm). ``twist_tau`` 0.06 s: 3 control steps.
    """

    model_config = STRICT
    lead_max: float = Field(1e-3, ge=0, le=0.01, description="cap of the integral lead along the screw [m]")
    twist_tau: float = Field(0.06, ge=0, le=10, description="handle-twist smoothing time constant [s] (0: none)")


class ArticulatedConfig(StudyConfig, SelfIdConfig):
    """Tac-Man vs TacMan-Turbo over a seeded population of articulated objects, true vs self-ID arm."""

    experiment: Literal["articulated"] = "articulated"
    backend: Literal["native", "mjx"] = "native"
    objects: Objects
    population: Population = Population()
    controllers: Annotated[list[sim.ControllerLabel], Field(min_length=1)] = list(sim.CONTROLLERS)
    arms: Annotated[list[Literal["true", "selfid"]], Field(min_length=1)] = ["true", "selfid"]
    speed: float = Field(0.03, gt=0, le=0.5, description="|u0| [m/s] along the gripper x axis")
    control_dt: float = Field(0.02, gt=0, le=0.2, description="control interval [s]")
    substeps: int = Field(10, ge=1, le=200, description="physics steps per control step")
    max_time: float = Field(60.0, gt=0, le=3600, description="rollout budget [s]")
    trace_points: int = Field(200, ge=2, le=10**5, description="trajectory samples kept per rollout")
    qdot_max: float = Field(1.0, gt=0, le=10, description="arm joint-velocity limit [rad/s] (Eq. 25)")
    beta: float = Field(0.9, gt=0, le=1, description="Eq. 25 safety factor")
    slip: float = Field(5e-3, gt=0, le=0.05, description="in-hand translation declared a slip [m]")
    slip_rot: float = Field(0.3, gt=0, le=3, description="in-hand rotation declared a slip [rad]")
    pads: Pads = Pads()
    tacman: TacManCfg = TacManCfg()
    turbo_lead: TurboLeadCfg = TurboLeadCfg()
    gel_k: float = Field(20000.0, gt=0, le=1e7, description="gel shear/normal stiffness [N/m]")
    gel_kr: float = Field(5.0, gt=0, le=1e4, description="gel torsional stiffness [N m/rad]")
    selfid_iters: int = Field(30, ge=2, le=10**4)
    eps: float = Field(0.5, ge=0, le=1e6, description="self-ID Sec. IV-D threshold")

    @model_validator(mode="after")
    def _some_objects(self):
        if sum(self.objects.model_dump().values()) == 0:
            raise ValueError("objects: at least one kind needs a count > 0")
        if not self.control_dt / self.substeps >= 2e-4:
            raise ValueError(f"control_dt / substeps = {self.control_dt / self.substeps} s: the physics timestep "
                             "must be >= 2e-4 s")
        return self


class Static(NamedTuple):
    sim: sim.Static
    iters: int


class Params(NamedTuple):
    rollout: sim.RolloutParams
    sid_key: scenes.ParamArray  # (2,) uint32
    m_a: scenes.ParamArray  # (6,) self-ID magnitude per joint [rad]
    eps: scenes.ParamArray  # ()


def compute(static: Static, p: Params) -> sim.RolloutResult:
    """Self-ID at the start joints, then one rollout with the chosen inverse Jacobian."""
    st = static.sim
    sid = selfid.run(st.arm, jax.random.wrap_key_data(jnp.asarray(p.sid_key)), jnp.asarray(st.q0), iters=static.iters,
                     eps=p.eps, m_a=p.m_a)
    est = jnp.where(jnp.all(jnp.isfinite(sid.estimate)), sid.estimate, 0.0)
    return sim.rollout(st, p.rollout._replace(jinv_est=est.astype(p.rollout.jinv_est.dtype)))


def _arm():
    from selfid_jax.systems.ur5e import UR5E_HOME, ur5e

    arm = ur5e(task_dim=6)
    q0 = np.asarray(UR5E_HOME, float)
    p1, R1 = (np.asarray(a) for a in arm.pose(jnp.asarray(q0)))
    return arm, q0, p1, R1


def build(cfg: ArticulatedConfig) -> list[Part]:
    with precision(True):
        return [part._replace(x64=True) for part in _build(cfg)]


def _build(cfg: ArticulatedConfig) -> list[Part]:
    arm, q0, p1, R1 = _arm()
    m_a = cfg.magnitude(arm)
    settings = scenes.SceneSettings(timestep=cfg.control_dt / cfg.substeps, gel_k=cfg.gel_k, gel_kr=cfg.gel_kr)
    pads = tactile.pads(rows=cfg.pads.rows, cols=cfg.pads.cols, pitch=cfg.pads.pitch)
    if int(np.sum(pads.delta0 >= cfg.pads.contact_eps)) < 3:
        raise ValueError(f"pads.contact_eps ({cfg.pads.contact_eps}) leaves fewer than 3 markers in contact "
                         f"at the grasp (max deformation {pads.delta0.max():.2e} m)")
    steps = int(round(cfg.max_time / cfg.control_dt))
    stride = max(1, steps // cfg.trace_points)
    pop_kw = cfg.population.model_dump()
    parts = []
    for k_i, kind in enumerate(scenes.KINDS):
        n_obj = getattr(cfg.objects, kind)
        if n_obj == 0:
            continue
        mj, layout = scenes.compile_scene(kind, p1, R1, settings)
        static = Static(sim.make_static(cfg.backend, layout, mj, pads, arm, q0, steps=steps, substeps=cfg.substeps,
                                        stride=stride), cfg.selfid_iters)
        pop = scenes.population(kind, n_obj, cfg.seed, **pop_kw)
        meta = grid_table({"object": range(n_obj), "controller": cfg.controllers, "arm": cfg.arms})
        meta.insert(0, "kind", kind)
        o = meta["object"].to_numpy()
        meta["order"] = pop.order[o]
        meta["fit_error_mm"] = 1e3 * pop.fit_error[o]
        add_m_a_columns(meta, m_a)
        n = len(meta)
        full = lambda v, n=n: np.full((n,), float(v))  # noqa: E731
        rollout = sim.RolloutParams(
            obj=scenes.ObjectParams(*(np.asarray(a)[o] for a in pop)),
            controller=np.asarray([sim.Controller.parse(c) for c in meta["controller"]], np.int32),
            use_estimate=(meta["arm"] == "selfid").to_numpy(),
            jinv_est=np.zeros((n, 6, 6)),
            key=row_keys(cfg.seed + 1000 * k_i, n), speed=full(cfg.speed), marker_noise=full(cfg.pads.marker_noise),
            contact_eps=full(cfg.pads.contact_eps), qdot_max=np.full((n, 6), cfg.qdot_max), beta=full(cfg.beta),
            dev_high=full(cfg.tacman.dev_high), dev_low=full(cfg.tacman.dev_low),
            recovery_gain=full(cfg.tacman.recovery_gain), slip=full(cfg.slip), slip_rot=full(cfg.slip_rot),
            lead_max=full(cfg.turbo_lead.lead_max), twist_tau=full(cfg.turbo_lead.twist_tau))
        # one self-ID per object (the same estimate for every controller on it)
        params = Params(rollout, row_keys(cfg.seed + 7, o), np.repeat(m_a.value[None], n, axis=0), full(cfg.eps))
        parts.append(Part(kind, static, params, meta))
    return parts


def tabulate(wide: pd.DataFrame, part: Part, cfg: ArticulatedConfig) -> pd.DataFrame:
    df = wide.copy()
    dt = cfg.control_dt
    df["success"] = df["success"].astype(bool)
    df["failed"] = df["failed"].astype(bool)
    df["time_s"] = np.where(df["success"], df["steps_used"] * dt, np.nan)
    df["dev_mean_mm"] = 1e3 * df["dev_mean"]
    df["dev_max_mm"] = 1e3 * df["dev_max"]
    return df.drop(columns=["dev_mean", "dev_max"])


def _stats(g: pd.DataFrame) -> dict[str, Any]:
    ok = g[g["success"]]
    out: dict[str, Any] = {"n": int(len(g)), "success_rate": float(g["success"].mean()),
                           "slips": int(g["slipped"].sum()), "nonfinite": int(g["nonfinite"].sum()),
                           "invalid_contact_steps": int(g["invalid_steps"].sum()),
                           "alpha_min": float(g["alpha_min"].min())}
    for m in METRICS:  # over successful rollouts (the paper's convention for time); efficiency etc. likewise
        out[m] = {"mean": float(ok[m].mean()) if len(ok) else None, "sd": float(ok[m].std(ddof=0)) if len(ok) else None}
    return out


def summarize(table: pd.DataFrame, cfg: ArticulatedConfig) -> dict[str, Any]:
    """Per kind x arm x controller, and per arm x controller over all kinds: success rate, metrics mean +- sd."""
    kinds: dict[str, Any] = {}
    for (kind, arm, ctrl), g in table.groupby(["kind", "arm", "controller"], sort=False):
        kinds.setdefault(str(kind), {}).setdefault(str(arm), {})[str(ctrl)] = _stats(g)
    overall: dict[str, Any] = {}
    for (arm, ctrl), g in table.groupby(["arm", "controller"], sort=False):
        overall.setdefault(str(arm), {})[str(ctrl)] = _stats(g)
    return {"backend": cfg.backend, "speed": cfg.speed, "control_dt": cfg.control_dt, "max_time": cfg.max_time,
            "objects": cfg.objects.model_dump(),
            "self_id": {"iterations": cfg.selfid_iters, **m_a_summary(table), "eps": cfg.eps},
            "kinds": kinds, "overall": overall,
            "paper": {"turbo": {"time_s": "7.6 +- 2.3", "efficiency": "0.239 +- 0.063", "jerk": "109.82 +- 147.71"},
                      "tacman": {"time_s": "250.7 +- 194.4", "efficiency": "0.012 +- 0.011",
                                 "jerk": "4921.44 +- 3722.49"}, "success": "100% both"}}


def report(summary: dict) -> str:
    lines = [f"{'kind':10s} {'arm':7s} {'controller':10s} {'success':>8s} {'time s':>13s} {'eff %/step':>14s} "
             f"{'jerk':>16s} {'dev mean mm':>12s} {'dev max mm':>11s} {'slips':>5s}"]

    def ms(m, k, fmt):
        v = m[k]
        return "-" if v["mean"] is None else f"{v['mean']:{fmt}} +- {v['sd']:{fmt}}"

    rows = [(k, a, c, m) for k, arms in summary["kinds"].items() for a, cs in arms.items() for c, m in cs.items()]
    rows += [("ALL", a, c, m) for a, cs in summary["overall"].items() for c, m in cs.items()]
    for k, a, c, m in rows:
        lines.append(f"{k:10s} {a:7s} {c:10s} {100 * m['success_rate']:7.0f}% {ms(m, 'time_s', '.1f'):>13s} "
                     f"{ms(m, 'efficiency', '.3f'):>14s} {ms(m, 'jerk', '.0f'):>16s} "
                     f"{ms(m, 'dev_mean_mm', '.2f'):>12s} {(m['dev_max_mm']['mean'] or 0):11.2f} {m['slips']:5d}")
    return "\n".join(lines)


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """Handle and gripper trajectories per object kind (G1 frame, true arm), and metric distributions side by side."""
    from matplotlib.figure import Figure

    written: list[Path] = []
    kinds = list(dict.fromkeys(table["kind"]))
    ctrls = list(dict.fromkeys(table["controller"]))
    fig = Figure(figsize=(4 * len(ctrls), 3.4 * len(kinds)), layout="constrained")
    for i, kind in enumerate(kinds):
        for j, ctrl in enumerate(ctrls):
            ax = fig.add_subplot(len(kinds), len(ctrls), i * len(ctrls) + j + 1)
            g = table[(table["kind"] == kind) & (table["controller"] == ctrl) & (table["arm"] == table["arm"].iloc[0])]
            for n, (_, r) in enumerate(g.head(6).iterrows()):
                h = 1e3 * np.asarray(r["handle_trace"]).reshape(-1, 3)
                gr = 1e3 * np.asarray(r["gripper_trace"]).reshape(-1, 3)
                ax.plot(h[:, 0], h[:, 1], lw=1.2, color=f"C{n}")
                ax.plot(gr[:, 0], gr[:, 1], lw=0.6, ls="--", color=f"C{n}")
            ax.set_title(f"{kind}: {ctrl} (arm {table['arm'].iloc[0]})", fontsize=9)
            ax.set_xlabel("x_G1 [mm] (u0 direction)")
            ax.set_ylabel("y_G1 [mm]")
            ax.set_aspect("equal", adjustable="datalim")
    fig.suptitle("handle (solid) and gripper (dashed) paths, first objects", fontsize=9)
    written += save_figure(fig, out_dir, "articulated_trajectories")

    fig = Figure(figsize=(4 * len(METRICS), 3.6), layout="constrained")
    labels = [(k, c) for k in kinds for c in ctrls]
    for m_i, m in enumerate(METRICS):
        ax = fig.add_subplot(1, len(METRICS), m_i + 1)
        data = [table[(table["kind"] == k) & (table["controller"] == c) & table["success"]][m].dropna().to_numpy()
                for k, c in labels]
        pos = [i for i, d in enumerate(data) if len(d)]
        if pos:
            ax.boxplot([data[i] for i in pos], positions=pos)
        ax.set_xticks(range(len(labels)), [f"{k[:4]}\n{c}" for k, c in labels], fontsize=6)
        ax.set_title(m + (" (log)" if m in ("time_s", "jerk") else ""), fontsize=9)
        if m in ("time_s", "jerk") and pos:
            ax.set_yscale("log")
    fig.suptitle("successful rollouts, both arms; success rate: " + ", ".join(
        f"{k[:4]}/{c} {100 * table[(table['kind'] == k) & (table['controller'] == c)]['success'].mean():.0f}%"
        for k, c in labels), fontsize=7)
    written += save_figure(fig, out_dir, "articulated_metrics")
    return written


COLUMNS = {
    "kind": "object kind: prismatic, revolute, helical or bezier [label]",
    "object": "object index within its kind [id]",
    "controller": "controller: tacman, turbo, turbo_u0 or turbo_lead [label]",
    "arm": "arm inverse Jacobian: 'true' or 'selfid' (the fixed self-ID estimate) [label]",
    "order": "Bezier order of the track, 0 for other kinds [-]",
    "fit_error_mm": "Bezier: max distance of the track to its Bezier curve, 0 when exact [mm]",
    "m_a": "(n_act,) self-ID actuation magnitude per actuator [rad]",
    "m_a_source": "where m_a came from: 'system' (the system's own) or 'config' (the m_a key) [label]",
    "success": "reached the kind's success progress (revolute/helical > 60 deg, prismatic > 250 mm, Bezier 98 % "
               "of the track) [bool]",
    "failed": "slipped or non-finite [bool]",
    "slipped": "the handle slipped out of the grasp [bool]",
    "nonfinite": "the physics state went non-finite (rollout frozen there) [bool]",
    "steps_used": "control steps until success (or all) [steps]",
    "progress": "final normalised progress along the path, 1 = success threshold [-]",
    "efficiency": "action efficiency: 100 min(progress, level) / level / steps_used [% of the path per step]",
    "jerk": "mean ||d^3 q / dt^3|| over the steps used [rad/s^3]",
    "invalid_steps": "steps whose contact set failed Eq. 11-12 [steps]",
    "alpha_min": "smallest velocity scaling alpha applied (Eq. 25) [-]",
    "handle_trace": "(3 S,) handle positions in the G1 frame every stride-th step, row-major (S, 3) [m]",
    "gripper_trace": "(3 S,) gripper positions in the G1 frame every stride-th step, row-major (S, 3) [m]",
    "progress_trace": "(S,) normalised progress every stride-th step [-]",
    "dev_trace": "(S,) contact deviation every stride-th step [m]",
    "scene_id": "constant identifying the scene template [id]",
    "time_s": "time to success (steps_used * control_dt), NaN if not successful [s]",
    "dev_mean_mm": "mean contact deviation over the steps used [mm]",
    "dev_max_mm": "max contact deviation [mm]",
}
"""The results columns (``results.parquet``): one row per object, controller and arm."""


EXPERIMENT = Experiment(
    name="articulated",
    config=ArticulatedConfig,
    build=build,
    compute=compute,
    summarize=summarize,
    columns=COLUMNS,
    tabulate=tabulate,
    plot=plot,
    report=report,
    description="seed 003: Tac-Man vs TacMan-Turbo on articulated objects, true vs self-identified UR5e",
)
