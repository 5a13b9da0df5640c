"""Articulated objects (seed 003): Tac-Man vs TacMan-Turbo on drawers, doors, cranks and Bezier tracks.

Rows: object x controller x arm inverse Jacobian, one part (one compiled
program) per object kind. Each row runs self-ID (Algorithm 1, the project's
own method) on the UR5e at its start configuration, returns there, grasps
the handle, and runs one closed-loop rollout (:mod:`selfid_jax.articulated.sim`)
with the true inverse Jacobian or the fixed self-identified estimate.
Metrics (seed Sec. 4.3): success (revolute/helical > 60 deg, prismatic >
250 mm, Bezier: 98 % of the track), time to success [s], action efficiency
[% of the path per control step, and per 1/60 s step as the paper's 60 Hz
simulation counts it], jerk [rad/s^3] and the paper's time-weighted base-joint
jerk [s^-3], path deviation (gripper to handle) [mm], mean and max contact
deviation [mm], steps with an invalid contact set (Eq. 11-12), slips and
non-finite states (counted, never NaN).

Objects: per-kind counts, or ``objects.paper: n`` in the seed's proportions
(Sec. 4.1: 1/4 drawers, 1/4 doors, 1/2 Bezier tracks of orders 2-5; the seed
has no cranks in simulation). Eq. 2 threshold: fixed (``pads.contact_eps``,
the default) or the seed's rule (``pads.contact_rule: paper``, Sec. 5.1:
exactly ``pads.contact_points`` markers in the first reading).

Grid axes besides object x controller x arm: ``grasp.k`` (the spring grasp's
stiffness, N/m) and ``resistance`` (a scale on every object's damping and
friction loss): the two quantities the paper leaves open
(``configs/articulated/articulated_plane.yaml`` sweeps them).

Size: about 530 lines, one experiment's contract (the config schema with the seed's physical checks on the
grasp spring, build, compute, tabulate, summarize, report); the figures are in ``experiments/figures``.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import BaseModel, Field, field_validator, model_validator

from selfid_jax.articulated import scenes, sim, tactile
from selfid_jax.identify import algorithm as selfid
from selfid_jax.runner import Experiment, Part, precision
from selfid_jax.runner.config import STRICT
from selfid_jax.runner.grids import grid_table, row_keys

from .common.lazy_figures import figures_plot
from .common.schema import SelfIdConfig, StudyConfig, add_m_a_columns, m_a_columns, m_a_summary

METRICS = ("time_s", "efficiency", "efficiency_60hz", "jerk", "jerk_tw", "path_dev_mm", "dev_mean_mm", "dev_max_mm")
RANGES = ("damping", "frictionloss", "radius", "crank", "pitch", "track")  # Population's (lo, hi) fields


class Objects(BaseModel):
    """How many objects of each kind, or ``paper: n`` objects in the seed's proportions (Sec. 4.1: 50 prismatic,
    50 revolute, 100 Bezier tracks of orders 2-5 in 200; :func:`selfid_jax.articulated.scenes.paper_counts`)."""

    model_config = STRICT
    paper: int = Field(0, ge=0, le=10**4, description="n objects in the seed's mix (1/4 drawers, 1/4 doors, 1/2 "
                       "Bezier tracks); excludes the per-kind counts")
    prismatic: int = Field(0, ge=0, le=10**4)
    revolute: int = Field(0, ge=0, le=10**4)
    helical: int = Field(0, ge=0, le=10**4, description="cranks (a hinge coupled to a slide): not in the seed's "
                         "simulated population")
    bezier: int = Field(0, ge=0, le=10**4)

    @model_validator(mode="after")
    def _paper_alone(self):
        if self.paper and any(getattr(self, k) for k in scenes.KINDS):
            raise ValueError(f"objects.paper ({self.paper}) sets every kind's count (the seed's mix); leave "
                             f"objects.{', objects.'.join(scenes.KINDS)} at 0 or set objects.paper to 0")
        return self

    def counts(self) -> dict[str, int]:
        """Objects per kind (``scenes.KINDS`` order)."""
        if self.paper:
            return scenes.paper_counts(self.paper)
        return {k: int(getattr(self, k)) for k in scenes.KINDS}


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

    @field_validator(*RANGES, mode="before")
    @classmethod
    def _range(cls, v, info):
        """A ``[lo, hi]`` list (YAML, ``--set population.damping=[0,0]``) is ``(lo, hi)``; ``0 <= lo <= hi``."""
        if isinstance(v, (list, tuple)):
            if len(v) != 2:
                raise ValueError(f"population.{info.field_name} needs two numbers [lo, hi], got {len(v)}")
            if all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
                v = (float(v[0]), float(v[1]))
                if not 0.0 <= v[0] <= v[1]:
                    raise ValueError(f"population.{info.field_name} = {list(v)}: needs 0 <= lo <= hi")
            else:
                v = tuple(v)
        return v


class Pads(BaseModel):
    model_config = STRICT
    rows: int = Field(8, ge=1, le=32)
    cols: int = Field(8, ge=1, le=32)
    pitch: float = Field(0.0025, gt=0, le=0.01, description="marker pitch [m]")
    marker_noise: float = Field(5e-6, ge=0, le=1e-3, description="marker reading noise sd [m]")
    contact_rule: Literal["fixed", "paper"] = Field("fixed", description="Eq. 2 threshold: 'fixed' (contact_eps) "
                                                    "or 'paper' (seed Sec. 5.1: the smallest threshold leaving exactly "
                                                    "contact_points markers in the first reading)")
    contact_eps: float = Field(3e-4, gt=0, le=1e-2, description="Eq. 2 threshold on normal deformation [m] "
                               "(contact_rule 'fixed')")
    contact_points: int = Field(9, ge=3, le=2048, description="contact_rule 'paper': markers in the initial contact "
                                "set (the seed: 9, one more than its longest line of markers)")

    @model_validator(mode="after")
    def _rule_applies(self):
        """The seed's rule needs ``contact_points`` below the markers touching the bar, and no tie at the boundary."""
        if self.contact_rule != "paper":
            return self
        d0 = tactile.pads(rows=self.rows, cols=self.cols, pitch=self.pitch).delta0
        n_touch = int(np.sum(d0 > 0))
        if not self.contact_points < n_touch:
            raise ValueError(f"pads.contact_points ({self.contact_points}) must be below the {n_touch} markers "
                             f"touching the handle at the grasp (pads.contact_rule 'paper')")
        if self.marker_noise == 0 and not (np.sort(d0)[::-1][self.contact_points - 1]
                                           > np.sort(d0)[::-1][self.contact_points]):
            raise ValueError(f"pads.contact_rule 'paper' finds no threshold leaving exactly pads.contact_points = "
                             f"{self.contact_points} markers: the pads' initial deformations tie "
                             f"({n_touch} markers at {1e3 * d0.max():.3f} mm) and pads.marker_noise is 0")
        return self


class TacManCfg(BaseModel):
    """Tac-Man's stage thresholds (``tacman``: the stop-and-go of its papers; ``tacman_reaim``: our departure).

    ``tacman`` defaults: ``dev_high`` 0.1 mm, below the 0.6 mm of one
    exploration step at 30 mm/s and 50 Hz, so every step ends an exploration
    (the papers' "step-by-step" cycles); ``dev_low`` 0.02 mm, 4x the marker
    noise sd. Neither TacMan-Turbo nor the material available here prints
    Tac-Man's own values; these are ours.
    """

    model_config = STRICT
    dev_high: float = Field(1e-4, gt=0, le=0.01, description="deviation ending an exploration stage [m]")
    dev_low: float = Field(2e-5, gt=0, le=0.01, description="deviation ending a recovery stage [m]")
    recovery_gain: float = Field(0.5, gt=0, le=1, description="fraction of the in-hand pose removed per recovery "
                                 "step")

    @model_validator(mode="after")
    def _order(self):
        if not self.dev_low < self.dev_high:
            raise ValueError(f"tacman.dev_low ({self.dev_low}) must be below tacman.dev_high ({self.dev_high})")
        return self


class Grasp(BaseModel):
    """The grasp model (:mod:`selfid_jax.articulated.scenes`): ``weld`` (gel joints and welds, about 7.3 kN/m
    effective at ``gel_k`` 20 kN/m) or ``spring`` (an explicit spring-damper of stiffness ``k``).

    Under ``spring``: ``k`` is a grid axis [N/m]; damping ``c = 2 damping_ratio
    sqrt(k mass)`` [N s/m]; torsion ``kr = k lever^2`` [N m/rad] with ``cr = 2
    damping_ratio sqrt(kr inertia)``. The explicit wrench needs the physics
    timestep of :func:`max_spring_timestep` on 0.3 kg, the lightest effective
    mass at a handle (a 0.45 m door or a 0.2 m crank: ``I / r^2`` plus the
    0.1 kg handle, 0.35 kg): 0.55 ms at ``k = 1e6`` N/m.
    """

    model_config = STRICT
    model: Literal["weld", "spring"] = "weld"
    k: Annotated[list[Annotated[float, Field(gt=0, le=1e8)]], Field(min_length=1)] = [20000.0]
    damping_ratio: float = Field(0.7, ge=0, le=10, description="spring: damping ratio on the reference mass")
    mass: float = Field(0.3, gt=0, le=100, description="spring: reference moving mass for the damping [kg] (the "
                        "lightest effective mass at a handle)")
    lever: float = Field(0.0158, gt=0, le=0.2, description="spring: kr = k lever^2 [m] (0.0158: the weld's gel "
                         "5 N m/rad at 20 kN/m)")
    inertia: float = Field(0.01, gt=0, le=10, description="spring: reference inertia for the torsional damping "
                           "[kg m^2]")

    @field_validator("k", mode="before")
    @classmethod
    def _floats(cls, v):
        return [float(x) if isinstance(x, int) and not isinstance(x, bool) else x for x in v] if isinstance(v, list) \
            else v

    def gains(self, k: float) -> np.ndarray:
        """``(4,) [k, c, kr, cr]`` of the spring grasp at stiffness ``k`` [N/m]."""
        kr = k * self.lever**2
        return np.array([k, 2 * self.damping_ratio * np.sqrt(k * self.mass), kr,
                         2 * self.damping_ratio * np.sqrt(kr * self.inertia)])


LIGHTEST_KG = 0.3  # the lightest effective mass at a handle (a 0.45 m door, a 0.2 m crank: I / r^2 + 0.1 kg = 0.35)


def spring_stable(grasp: Grasp, k: float, h: float, mass: float = LIGHTEST_KG) -> bool:
    """Whether MuJoCo's semi-implicit Euler keeps the spring grasp ``k`` [N/m] (damping from ``grasp``) stable on
    ``mass`` [kg] at timestep ``h`` [s], accurately: ``omega h <= 1`` and the one-step map's spectral radius < 1.

    The map of ``(x, h v)`` under ``v' = v - h (omega^2 x + 2 zeta omega v)``, ``x' = x + h v'`` is
    ``[[1 - a^2, 1 - b], [-a^2, 1 - b]]`` with ``a = omega h``, ``b = c h / mass``.
    """
    c = grasp.gains(k)[1]
    a, b = np.sqrt(k / mass) * h, c * h / mass
    M = np.array([[1 - a * a, 1 - b], [-a * a, 1 - b]])
    return bool(a <= 1.0 and np.max(np.abs(np.linalg.eigvals(M))) < 1.0)


def max_spring_timestep(grasp: Grasp, k: float, mass: float = LIGHTEST_KG) -> float:
    """The largest timestep [s] (to 1 %) at which :func:`spring_stable` holds."""
    h = 1.0 / np.sqrt(k / mass)
    while not spring_stable(grasp, k, h, mass):
        h *= 0.99
    return float(h)


class TurboLeadCfg(BaseModel):
    """``turbo_lead`` (:func:`selfid_jax.articulated.tacman.lead_step`): integral lead and twist smoothing.

    ``lead_max`` 1 mm: ``tacman_reaim``'s ``dev_high`` (the deviation it still calls
    safe), 5x below the 5 mm slip, and at the weld grasp's 7.3 kN/m a 7 N pull, 2x
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
    tacman_reaim: TacManCfg = TacManCfg(dev_high=1e-3, dev_low=2e-4)
    grasp: Grasp = Grasp()
    resistance: Annotated[list[Annotated[float, Field(ge=0, le=100)]], Field(min_length=1)] = Field(
        [1.0], description="grid axis: scale on every object's damping and friction loss")
    turbo_lead: TurboLeadCfg = TurboLeadCfg()
    gel_k: float = Field(20000.0, gt=0, le=1e7, description="weld grasp: gel shear/normal joint stiffness [N/m] (in "
                         "series with the weld: about 7.3 kN/m effective at 20 kN/m)")
    gel_kr: float = Field(5.0, gt=0, le=1e4, description="gel torsional stiffness [N m/rad]")
    selfid_iters: int = Field(30, ge=2, le=10**4)
    eps: float = Field(0.5, ge=0, le=1e6, description="self-ID Sec. IV-D threshold")

    @model_validator(mode="after")
    def _some_objects(self):
        if sum(self.objects.model_dump().values()) == 0:
            raise ValueError("objects: at least one kind needs a count > 0")
        h = self.control_dt / self.substeps
        if not h >= 2e-4:
            raise ValueError(f"control_dt / substeps = {h} s: the physics timestep must be >= 2e-4 s")
        if self.grasp.model == "weld" and len(self.grasp.k) > 1:
            raise ValueError("grasp.k lists several stiffnesses but grasp.model is 'weld' (its stiffness is gel_k); "
                             "set grasp.model: spring")
        if self.grasp.model == "spring":
            if self.backend != "native":
                raise ValueError("grasp.model 'spring' runs on the native backend only; set backend: native")
            k = max(self.grasp.k)
            if not spring_stable(self.grasp, k, h):
                h_ok = max_spring_timestep(self.grasp, k)
                raise ValueError(f"grasp.k up to {k:g} N/m needs a physics timestep <= {h_ok:.2e} s for the explicit "
                                 f"spring on the lightest object ({LIGHTEST_KG} kg); control_dt / substeps = {h:.2e} s:"
                                 f" raise substeps to >= {int(np.ceil(self.control_dt / h_ok))}")
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
    settings = scenes.SceneSettings(timestep=cfg.control_dt / cfg.substeps, gel_k=cfg.gel_k, gel_kr=cfg.gel_kr,
                                    grasp=cfg.grasp.model)
    pads = tactile.pads(rows=cfg.pads.rows, cols=cfg.pads.cols, pitch=cfg.pads.pitch)
    paper_rule = cfg.pads.contact_rule == "paper"
    if not paper_rule and int(np.sum(pads.delta0 >= cfg.pads.contact_eps)) < 3:
        raise ValueError(f"pads.contact_eps ({cfg.pads.contact_eps}) leaves fewer than 3 markers in contact "
                         f"at the grasp (max deformation {pads.delta0.max():.2e} m)")
    steps = int(round(cfg.max_time / cfg.control_dt))
    stride = max(1, steps // cfg.trace_points)
    pop_kw = cfg.population.model_dump()
    parts = []
    counts = cfg.objects.counts()
    for k_i, kind in enumerate(scenes.KINDS):
        n_obj = counts[kind]
        if n_obj == 0:
            continue
        mj, layout = scenes.compile_scene(kind, p1, R1, settings)
        static = Static(sim.make_static(cfg.backend, layout, mj, pads, arm, q0, steps=steps, substeps=cfg.substeps,
                                        stride=stride), cfg.selfid_iters)
        pop = scenes.population(kind, n_obj, cfg.seed, **pop_kw)
        meta = grid_table({"object": range(n_obj), "controller": cfg.controllers, "arm": cfg.arms,
                           "grasp_k": cfg.grasp.k, "resistance": cfg.resistance})
        meta.insert(0, "kind", kind)
        meta["grasp"] = cfg.grasp.model
        o = meta["object"].to_numpy()
        meta["order"] = pop.order[o]
        meta["fit_error_mm"] = 1e3 * pop.fit_error[o]
        add_m_a_columns(meta, m_a)
        n = len(meta)
        full = lambda v, n=n: np.full((n,), float(v))
        res = meta["resistance"].to_numpy(float)
        obj = scenes.ObjectParams(*(np.asarray(a)[o] for a in pop))
        obj = obj._replace(damping=obj.damping * res, frictionloss=obj.frictionloss * res)
        reaim = (meta["controller"] == "tacman_reaim").to_numpy()
        tac = lambda name, r=reaim: np.where(r, getattr(cfg.tacman_reaim, name), getattr(cfg.tacman, name))
        rollout = sim.RolloutParams(
            obj=obj,
            controller=np.asarray([sim.Controller.parse(c) for c in meta["controller"]], np.int32),
            use_estimate=(meta["arm"] == "selfid").to_numpy(),
            jinv_est=np.zeros((n, 6, 6)),
            key=row_keys(cfg.seed + 1000 * k_i, n), speed=full(cfg.speed), marker_noise=full(cfg.pads.marker_noise),
            contact_eps=full(cfg.pads.contact_eps),
            contact_points=np.full((n,), cfg.pads.contact_points if paper_rule else 0, np.int32),
            qdot_max=np.full((n, 6), cfg.qdot_max), beta=full(cfg.beta),
            dev_high=tac("dev_high"), dev_low=tac("dev_low"),
            recovery_gain=tac("recovery_gain"), slip=full(cfg.slip), slip_rot=full(cfg.slip_rot),
            lead_max=full(cfg.turbo_lead.lead_max), twist_tau=full(cfg.turbo_lead.twist_tau),
            grasp=np.stack([cfg.grasp.gains(k) for k in meta["grasp_k"].to_numpy(float)]))
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
    df["path_dev_mm"] = 1e3 * df["path_dev"]
    df["contact_eps_mm"] = 1e3 * df["contact_eps"]
    return df.drop(columns=["dev_mean", "dev_max", "path_dev", "contact_eps"])


def _stats(g: pd.DataFrame) -> dict[str, Any]:
    ok = g[g["success"]]
    out: dict[str, Any] = {"n": int(len(g)), "success_rate": float(g["success"].mean()),
                           "slips": int(g["slipped"].sum()), "nonfinite": int(g["nonfinite"].sum()),
                           "invalid_contact_steps": int(g["invalid_steps"].sum()),
                           "invalid_share": float((g["invalid_steps"] / g["steps_used"].clip(lower=1)).mean()),
                           "alpha_min": float(g["alpha_min"].min()),
                           "recovery_share": float((g["recovery_steps"] / g["steps_used"].clip(lower=1)).mean())}
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
    plane: list[dict[str, Any]] = []  # grasp stiffness x resistance x controller, over all kinds and arms
    for (k, res, ctrl), g in table.groupby(["grasp_k", "resistance", "controller"], sort=False):
        plane.append({"grasp_k": float(k), "resistance": float(res), "controller": str(ctrl), **_stats(g)})
    ratios: dict[str, Any] = {}  # Tac-Man's mean time over each Turbo's (the paper: 250.7 / 7.6 = 33x)
    for arm, cs in overall.items():
        for tm in ("tacman", "tacman_reaim"):
            for tb in ("turbo", "turbo_u0", "turbo_lead"):
                a, b = cs.get(tm, {}).get("time_s", {}).get("mean"), cs.get(tb, {}).get("time_s", {}).get("mean")
                if tm in cs and tb in cs:
                    ratios.setdefault(str(arm), {})[f"{tm}/{tb}"] = None if a is None or b is None else a / b
    return {"backend": cfg.backend, "speed": cfg.speed, "control_dt": cfg.control_dt, "max_time": cfg.max_time,
            "objects": cfg.objects.counts(), "paper_mix": cfg.objects.paper > 0,
            "contact_rule": cfg.pads.contact_rule,
            "self_id": {"iterations": cfg.selfid_iters, **m_a_summary(table), "eps": cfg.eps},
            "grasp": cfg.grasp.model, "kinds": kinds, "overall": overall, "plane": plane, "time_ratios": ratios,
            "paper": {"turbo": {"time_s": "7.6 +- 2.3", "efficiency": "0.239 +- 0.063", "jerk": "109.82 +- 147.71"},
                      "tacman": {"time_s": "250.7 +- 194.4", "efficiency": "0.012 +- 0.011",
                                 "jerk": "4921.44 +- 3722.49"}, "success": "100% both", "time_ratio": 250.7 / 7.6,
                      "note": "efficiency in % per 60 Hz step (compare efficiency_60hz), jerk time-weighted in s^-3 "
                              "(compare jerk_tw)"}}


def report(summary: dict) -> str:
    """The summary as text: per kind x arm x controller (the paper's metrics beside ours), the time ratios, and the
    stiffness x resistance plane when it has more than one cell."""
    lines = [f"{'kind':10s} {'arm':7s} {'controller':12s} {'success':>8s} {'time s':>13s} {'eff %/step':>14s} "
             f"{'eff %/60Hz':>14s} {'jerk':>16s} {'jerk_tw s^-3':>16s} {'path mm':>12s} {'dev mean mm':>12s} "
             f"{'slips':>5s}"]

    def ms(m, k, fmt):
        v = m[k]
        return "-" if v["mean"] is None else f"{v['mean']:{fmt}} +- {v['sd']:{fmt}}"

    rows = [(k, a, c, m) for k, arms in summary["kinds"].items() for a, cs in arms.items() for c, m in cs.items()]
    rows += [("ALL", a, c, m) for a, cs in summary["overall"].items() for c, m in cs.items()]
    for k, a, c, m in rows:
        lines.append(f"{k:10s} {a:7s} {c:12s} {100 * m['success_rate']:7.0f}% {ms(m, 'time_s', '.1f'):>13s} "
                     f"{ms(m, 'efficiency', '.3f'):>14s} {ms(m, 'efficiency_60hz', '.3f'):>14s} "
                     f"{ms(m, 'jerk', '.0f'):>16s} {ms(m, 'jerk_tw', '.1f'):>16s} {ms(m, 'path_dev_mm', '.2f'):>12s} "
                     f"{ms(m, 'dev_mean_mm', '.2f'):>12s} {m['slips']:5d}")
    for arm, rs in summary.get("time_ratios", {}).items():
        lines.append(f"time ratios (arm {arm}; paper tacman/turbo 33x): " + ", ".join(
            f"{k} {'-' if v is None else f'{v:.1f}x'}" for k, v in rs.items()))
    plane = summary.get("plane", [])
    if len({(r["grasp_k"], r["resistance"]) for r in plane}) > 1:
        lines.append(f"{'grasp k N/m':>12s} {'resistance':>10s} {'controller':12s} {'success':>8s} {'time s':>13s}")
        for r in plane:
            lines.append(f"{r['grasp_k']:12.3g} {r['resistance']:10.3g} {r['controller']:12s} "
                         f"{100 * r['success_rate']:7.0f}% {ms(r, 'time_s', '.1f'):>13s}")
    return "\n".join(lines)


plot = figures_plot("articulated")  # experiments/figures/articulated.py, imported (with matplotlib) when called


COLUMNS = {
    "kind": "object kind: prismatic, revolute, helical or bezier [label]",
    "object": "object index within its kind [id]",
    "controller": "controller: tacman (stop-and-go, as its papers), tacman_reaim (our departure), turbo (literal "
                  "Eq. 14-21), turbo_u0 or turbo_lead (our departures) [label]",
    "grasp_k": "spring grasp stiffness (grid axis; unused by the weld grasp) [N/m]",
    "resistance": "scale on the object's damping and friction loss (grid axis) [-]",
    "grasp": "grasp model: 'weld' or 'spring' [label]",
    "arm": "arm inverse Jacobian: 'true' or 'selfid' (the fixed self-ID estimate) [label]",
    "order": "Bezier order of the track, 0 for other kinds [-]",
    "fit_error_mm": "Bezier: max distance of the track to its Bezier curve, 0 when exact [mm]",
    **m_a_columns(),
    "success": "reached the kind's success progress (revolute/helical > 60 deg, prismatic > 250 mm, Bezier 98 % "
               "of the track) [bool]",
    "failed": "slipped or non-finite [bool]",
    "slipped": "the handle slipped out of the grasp [bool]",
    "nonfinite": "the physics state went non-finite (rollout frozen there) [bool]",
    "steps_used": "control steps until success (or all) [steps]",
    "progress": "final normalised progress along the path, 1 = success threshold [-]",
    "efficiency": "action efficiency: 100 min(progress, level) / level / steps_used [% of the path per step]",
    "efficiency_60hz": "action efficiency per 1/60 s, the paper's step: 100 min(progress, level) / level / (60 "
                       "steps_used control_dt) [% of the path per 60 Hz step]",
    "jerk": "mean ||d^3 q / dt^3|| over the steps used [rad/s^3]",
    "jerk_tw": "time-weighted jerk: time average of the base joint's |d^3 q_1 / dt^3| over the task "
               "(sim.time_weighted_jerk) [s^-3]",
    "invalid_steps": "steps whose contact set failed Eq. 11-12 [steps]",
    "alpha_min": "smallest velocity scaling alpha applied (Eq. 25) [-]",
    "recovery_steps": "Tac-Man control steps spent in recovery, the object not driven (0 for Turbo) [steps]",
    "contact_eps_mm": "Eq. 2 threshold used: pads.contact_eps, or set by the seed's rule (pads.contact_rule "
                      "'paper') on the first reading [mm]",
    "contact_n": "markers in the initial contact set C_1 [count]",
    "contact_ok": "the seed's rule found a threshold with exactly pads.contact_points markers (True under the "
                  "fixed threshold) [bool]",
    "recovery_trace": "(S,) the step was a Tac-Man recovery, every stride-th step [bool]",
    "handle_trace": "(3 S,) handle positions in the G1 frame every stride-th step, row-major (S, 3) [m]",
    "gripper_trace": "(3 S,) gripper positions in the G1 frame every stride-th step, row-major (S, 3) [m]",
    "progress_trace": "(S,) normalised progress every stride-th step [-]",
    "dev_trace": "(S,) contact deviation every stride-th step [m]",
    "scene_id": "constant identifying the scene template [id]",
    "time_s": "time to success (steps_used * control_dt), NaN if not successful [s]",
    "dev_mean_mm": "mean contact deviation over the steps used [mm]",
    "dev_max_mm": "max contact deviation [mm]",
    "path_dev_mm": "path deviation: mean distance from the gripper (the arm's pose) to the handle [mm]",
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
