"""Self-ID design experiment (``selfid_jax.design``): the self-ID magnitude ``m_a`` to use at a tracker's noise.

For each system and tracker-noise level (one row of the sweep), one compiled
program (:func:`selfid_jax.design.optimize`) evaluates the design loss (mean
over start configurations and trials of ``log`` of the mean squared distance
to the path, failures saturated) on a log-spaced grid of scalar magnitudes,
refines the grid's best point by Adam on ``log m_a`` with the gradient through
self-ID, the closed-form estimate and the rollout, and then refines one
magnitude per actuator from the scalar optimum. Every evaluation uses the same
training trials (common random numbers); the designs (the system's own safe
``m_a``, the grid's best, the refined scalar, the per-actuator one) are then
compared on held-out trials (a second key, ``eval_trials`` per start).
Wherever the fraction of failed rollouts exceeds ``refine.max_failed`` the
gradient is flagged unreliable and not followed (see :mod:`selfid_jax.design`).

Why a row is a whole (system, noise level) problem
    The refinement starts where the grid is lowest, so it depends on the grid
    of the same noise level; the experiment contract builds every part's
    parameters from the config before any compute, so a second part could not
    start from the first part's results, and running the refinement in
    ``summarize`` would put compute (and gradients) where only saved results
    should be read. Instead each row's pure ``compute`` runs grid, scalar
    refinement and per-actuator refinement in one scan (one copy of the
    differentiated rollout in the program: it compiles about 3x faster than a
    vmapped grid plus two refinements), then the held-out evaluation of the
    four designs (one vmapped forward pass). A row costs
    ``(G + 2 K) x n_configs x n_trials`` differentiated rollouts. An interrupted
    sweep resumes per finished row (``chunk_size: 1`` in the shipped configs:
    one noise level per chunk), and ``tabulate`` stores every evaluated point
    (grid curve, both gradient paths, the held-out comparison) in the tidy
    table, so ``selfid-jax plot`` redraws the figures and ``summarize`` the
    optima from the saved table alone.

The tidy table has one row per evaluated point, ``stage`` one of ``grid``,
``scalar``, ``per_actuator`` (the points in evaluation order, ``index``) and
``eval`` (``design``: ``default``, ``grid``, ``scalar``, ``per_actuator`` if refined):
``m_a`` (geometric mean over actuators), ``m_a_vec`` (per actuator), ``loss``
[log m^2], ``gm_error_mm`` (``1e3 exp(loss / 2)``), ``rms_error_mm`` (over the
rollouts that did not fail), ``failed_fraction``, ``completion``, ``reliable``
and, on the optimisation stages, ``grad`` (d loss / d log m_a, summed over
actuators) and ``grad_vec`` (per actuator); ``eval`` rows carry no gradient
(``grad`` NaN, ``grad_vec`` empty). ``summarize`` gives per system and noise
level the grid's best, the refined scalar and per-actuator optima, the range of
``m_a`` within 10% of the best error, held-out errors and the error the
per-actuator design saves, and how often the gradient's sign matches the grid's
own slope at reliable and at unreliable points.

Size: about 550 lines, one experiment's contract and the design summary's statistics (best point, flat
range, gradient check), which the report and the figures module read; the figures are in ``experiments/figures``.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, NamedTuple, TypeAlias

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import BaseModel, Field, field_validator, model_validator

from selfid_jax import control, design
from selfid_jax.control import paths
from selfid_jax.runner import Experiment, Part, precision
from selfid_jax.runner.config import STRICT, stop_after_start
from selfid_jax.runner.grids import decimal_points, grid_table, row_keys
from selfid_jax.systems import System

from .common.lazy_figures import figures_plot
from .common.schema import (
    NOISE_COLUMNS,
    ControllerConfig,
    PathConfig,
    SelfIdConfig,
    StartsConfig,
    StudyConfig,
    check_noise_pairs,
    controller_rows,
    resolve_m_a,
)
from .common.specs import (
    SystemSpec,
    build_system,
    needs_x64,
    spec_or_run,
    system_name,
    unique_system_names,
)

EVAL_DESIGNS = ("default", "grid", "scalar", "per_actuator")
"""The designs compared on held-out trials: the system's safe ``m_a``, the grid's best, the refined scalar, per
actuator."""

Noise = Annotated[list[Annotated[float, Field(ge=0, le=0.1)]], Field(min_length=1)]


class MagnitudeGrid(BaseModel):
    """A log-spaced grid of self-ID magnitudes ``m_a`` [rad or m]."""

    model_config = STRICT

    start: float = Field(gt=0, le=10, description="smallest magnitude [rad or m]")
    stop: float = Field(gt=0, le=10, description="largest magnitude, above start")
    num: int = Field(ge=2, le=1000, description="number of grid points (log-spaced)")

    _stop_after_start = field_validator("stop")(stop_after_start)

    def values(self) -> np.ndarray:
        """``(num,)`` magnitudes, ``geomspace(start, stop, num)``, each its 12-digit decimal (the value written)."""
        return decimal_points(np.geomspace(self.start, self.stop, self.num))


class RefineConfig(BaseModel):
    """The gradient refinement (Adam on ``log m_a``, cosine-decayed step; :func:`selfid_jax.design.refine`)."""

    model_config = STRICT

    steps: int = Field(40, ge=1, le=10**4, description="Adam steps per refinement (scalar, then per actuator)")
    learning_rate: float = Field(0.1, gt=0, le=10, description="initial step in log m_a (0.1: 10% of m_a)")
    max_failed: float = Field(0.1, ge=0, le=1, description="gradient unreliable above this fraction of failed "
                              "rollouts: not followed")


class SystemRun(SelfIdConfig):
    """A system with its own protocol (a hand needs mm paths, finer tracker noise and magnitudes): overrides the
    top level.

    ``m_a``: the reference ("default") design compared on held-out trials; the system's own unless given.
    """

    system: SystemSpec
    path: PathConfig | None = None
    controller: ControllerConfig | None = None
    m_a_grid: MagnitudeGrid | None = None
    pose_noise: Noise | None = None
    rot_noise: Noise | None = None


SystemEntry = spec_or_run(SystemRun)


class Protocol(NamedTuple):
    """One system's resolved protocol."""

    spec: Any
    path: PathConfig
    controller: ControllerConfig
    m_a_grid: MagnitudeGrid
    pose_noise: list[float]
    rot_noise: list[float]
    m_a: Any = None  # the reference design's m_a key (None: the system's own; common.schema.resolve_m_a)


class DesignConfig(StudyConfig, StartsConfig):
    """Self-ID magnitude design per system and tracker-noise level: grid, gradient refinement, held-out comparison."""

    experiment: Literal["design"] = "design"
    # SystemEntry is a discriminated union spec_or_run builds at runtime: pydantic reads it, mypy cannot
    systems: Annotated[list[SystemEntry], Field(  # type: ignore[valid-type]
        min_length=1, description="built-in names, {mjcf: ...} / {pose_fn: ...}, or {system: ..., path: ..., "
        "controller: ..., m_a_grid: ..., pose_noise: ..., rot_noise: ...}")]
    path: PathConfig
    controller: ControllerConfig = ControllerConfig()
    m_a_grid: MagnitudeGrid
    pose_noise: Noise = Field(description="tracker position noise sd per level [m]")
    rot_noise: Noise | None = Field(None, description="tracker rotation noise sd per level [rad] (default 0)")
    n_configs: int = Field(ge=1, le=10**4, description="start configurations (feasible for the true inverse)")
    n_trials: int = Field(1, ge=1, le=10**4, description="training trials per start (self-ID draws and noise)")
    eval_trials: int = Field(2, ge=1, le=10**4, description="held-out trials per start for comparing designs")
    iters: int = Field(12, ge=1, le=10**4, description="self-ID samples per estimate (no early stop)")
    refine: RefineConfig = RefineConfig()
    per_actuator: bool = Field(True, description="also refine one magnitude per actuator from the scalar optimum")
    follow_from: Literal["selfid_end", "start"] = Field(
        "selfid_end", description="the path starts where self-ID left the robot, or at the start configuration")

    _unique = field_validator("systems")(unique_system_names)

    @model_validator(mode="after")
    def _protocols_fit(self):
        for entry in self.systems:
            proto = protocol(self, entry)
            proto.path.check_controller(proto.controller)
            check_noise_pairs(proto.pose_noise, proto.rot_noise)
        return self


def protocol(cfg: DesignConfig, entry) -> Protocol:
    """The resolved protocol of one ``systems`` entry, the top level filling what it leaves out."""
    run = entry if isinstance(entry, SystemRun) else SystemRun(system=entry)
    pose = run.pose_noise if run.pose_noise is not None else cfg.pose_noise
    if run.rot_noise is not None:
        rot = run.rot_noise
    elif run.pose_noise is None and cfg.rot_noise is not None:  # the top level's levels, paired
        rot = cfg.rot_noise
    else:
        rot = [0.0] * len(pose)
    return Protocol(run.system, run.path or cfg.path, run.controller or cfg.controller, run.m_a_grid or cfg.m_a_grid,
                    list(pose), list(rot), run.m_a)


ParamArray: TypeAlias = jax.Array | np.ndarray
"""A leaf of :class:`Params`: numpy where :func:`build` fills the rows, a ``jax.Array`` once traced."""


class Static(NamedTuple):
    """What every row of one system shares (closed over by the compiled function)."""

    system: System
    path: jax.Array  # (W, task_dim) star waypoint offsets [m]
    iters: int  # self-ID samples per estimate
    n_trials: int  # training trials per start
    eval_trials: int  # held-out trials per start
    steps: int  # control-step budget per rollout
    opt_steps: int  # Adam steps per refinement
    per_actuator: bool
    follow_from: str


class Params(NamedTuple):
    """One row's traced inputs (batch axis first when batched): numpy rows from :func:`build`, traced in
    :func:`compute`."""

    pose_noise: ParamArray  # () tracker position noise sd [m]
    rot_noise: ParamArray  # () tracker rotation noise sd [rad]
    m_a_grid: ParamArray  # (G,) magnitudes [rad or m]
    default_m_a: ParamArray  # (n,) the reference design: the system's safe magnitude, or the entry's m_a
    key: ParamArray  # (2,) uint32 key data of the training trials
    eval_key: ParamArray  # (2,) uint32 key data of the held-out trials
    q0s: ParamArray  # (S, n) start configurations
    learning_rate: ParamArray  # () initial Adam step in log m_a
    max_failed: ParamArray  # () reliability threshold
    controller: control.ControllerParams  # () each


class HeldOut(NamedTuple):
    """The compared designs (:data:`EVAL_DESIGNS`, E = 4) evaluated on the held-out trials."""

    log_m_a: jax.Array  # (E, n) log of each design's per-actuator m_a [log rad or log m]
    info: design.DesignInfo  # each field (E,)


class Outputs(NamedTuple):
    """One row's results: the library's own result types (see the module docstring).

    The runner stores each leaf as a column named by its dotted path
    (``search.grid.info.loss``, ``search.scalar.grad``, ``held_out.log_m_a``,
    ...; :func:`selfid_jax.runner.sweep.named_leaves`); :func:`_outputs` reads
    them back into these tuples.
    """

    search: design.DesignResult  # grid (G points), scalar and per-actuator refinement (K steps each; None without
    # per_actuator) on the training trials
    held_out: HeldOut


def compute(static: Static, p: Params) -> Outputs:
    """Grid, scalar and per-actuator refinement on the training trials, then the designs on held-out trials."""
    system = static.system
    n = system.n_act
    params = design.DesignParams(jnp.zeros((n,)), jnp.asarray(p.pose_noise), jnp.asarray(p.rot_noise), p.controller)
    key, eval_key = jax.random.wrap_key_data(jnp.asarray(p.key)), jax.random.wrap_key_data(jnp.asarray(p.eval_key))
    res = design.optimize(system, params, p.m_a_grid, key, p.q0s, static.path, opt_steps=static.opt_steps,
                          learning_rate=p.learning_rate, max_failed=p.max_failed, per_actuator=static.per_actuator,
                          n_trials=static.n_trials, iters=static.iters, steps=static.steps,
                          follow_from=static.follow_from)
    g, per = res.grid, res.per_actuator
    scalar_vec = jnp.full((n,), res.scalar.best_log_m_a)
    designs = jnp.stack([jnp.log(p.default_m_a), jnp.full((n,), jnp.log(g.m_a[g.best])), scalar_vec,
                         per.best_log_m_a if per is not None else scalar_vec])

    def held_out(log_m_a):
        return design.design_loss(system, params._replace(log_m_a=log_m_a), eval_key, p.q0s, static.path,
                                  iters=static.iters, n_trials=static.eval_trials, steps=static.steps,
                                  follow_from=static.follow_from, return_info=True)

    _, info = jax.vmap(held_out)(designs)
    return Outputs(res, HeldOut(designs, info))


def build(cfg: DesignConfig) -> list[Part]:
    """One part per system (float64 where the system needs it): one row per tracker-noise level."""
    parts = []
    for index, entry in enumerate(cfg.systems):
        proto = protocol(cfg, entry)
        x64 = needs_x64(proto.spec)
        with precision(x64):
            parts.append(_system_part(cfg, proto, index)._replace(x64=x64))
    return parts


def _system_part(cfg: DesignConfig, proto: Protocol, index: int) -> Part:
    name, system = system_name(proto.spec), build_system(proto.spec)
    if not system.position_axes:
        raise ValueError(f"system {name!r}: the design loss needs a task with position components, got {system.axes}")
    path = paths.star(size=proto.path.size, dim=6)[:, list(system.axes)]
    ctrl = control.ControllerParams(**proto.controller.traced())
    q0s = np.asarray(control.feasible_starts(system, path, jax.random.key(cfg.seed + index), cfg.n_configs, ctrl,
                                             steps=proto.controller.steps, oversample=cfg.oversample))
    meta = grid_table({"system": [name], "noise_level": range(len(proto.pose_noise))})
    meta["pose_noise"] = np.asarray(proto.pose_noise, float)[meta["noise_level"]]
    meta["rot_noise"] = np.asarray(proto.rot_noise, float)[meta["noise_level"]]
    N = len(meta)
    grid = proto.m_a_grid.values()

    def rows(x):
        return np.repeat(np.asarray(x)[None], N, axis=0)

    params = Params(
        pose_noise=meta["pose_noise"].to_numpy(float),
        rot_noise=meta["rot_noise"].to_numpy(float),
        m_a_grid=rows(grid),
        default_m_a=rows(resolve_m_a(proto.m_a, system, f"systems[{name}].m_a").value),
        key=row_keys(cfg.seed, np.full(N, 2 * index)),  # the same trials at every noise level (common random numbers)
        eval_key=row_keys(cfg.seed, np.full(N, 2 * index + 1)),
        q0s=rows(q0s),
        learning_rate=np.full(N, cfg.refine.learning_rate),
        max_failed=np.full(N, cfg.refine.max_failed),
        controller=controller_rows(proto.controller, N),
    )
    static = Static(system, path, cfg.iters, cfg.n_trials, cfg.eval_trials, proto.controller.steps, cfg.refine.steps,
                    cfg.per_actuator, cfg.follow_from)
    return Part(name, static, params, meta)


# --------------------------------------------------------------------------- table

def _outputs(wide: pd.DataFrame) -> Outputs:
    """The wide table's output columns back as the :class:`Outputs` ``compute`` returned.

    Each leaf is ``(rows, size)``: the runner keeps one column per dotted leaf
    name, each row's values flattened; the per-actuator refinement is None
    where it was not run (its leaves have no columns).
    """

    def leaf(name: str) -> np.ndarray:
        return np.stack([np.asarray(v, float).ravel() for v in wide[name].to_numpy()])

    def tup(cls, prefix: str, **nested):
        return cls(**{f: nested[f] if f in nested else leaf(f"{prefix}.{f}") for f in cls._fields})

    def info(prefix: str) -> design.DesignInfo:
        return tup(design.DesignInfo, prefix)

    per = tup(design.RefineResult, "search.per_actuator") if "search.per_actuator.loss" in wide else None
    search = design.DesignResult(tup(design.GridResult, "search.grid", info=info("search.grid.info")),
                                 tup(design.RefineResult, "search.scalar"), per)
    return Outputs(search, tup(HeldOut, "held_out", info=info("held_out.info")))


def tabulate(wide: pd.DataFrame, part: Part, cfg: DesignConfig) -> pd.DataFrame:
    """One row per evaluated point: the grid, both gradient paths and the held-out designs (module docstring)."""
    n = part.static.system.n_act
    rows = len(wide)
    out = _outputs(wide)
    base = wide[["system", "noise_level", "pose_noise", "rot_noise"]]
    mf = cfg.refine.max_failed
    frames = []

    def add(stage: str, total: int, log_m_a, stats: design.DesignInfo | design.RefineResult, grad, designs=None,
            count: int | None = None) -> None:
        """The first ``count`` (default all) of a stage's ``total`` points; ``log_m_a`` and ``grad`` (None: none) per
        point a scalar or one value per actuator."""
        count = total if count is None else count

        def points(a):  # (rows, count, values per point)
            return np.asarray(a, float).reshape(rows, total, -1)[:, :count]

        x, loss, failed = points(log_m_a), points(stats.loss)[..., 0], points(stats.failed_fraction)[..., 0]
        completion, rms = points(stats.completion)[..., 0], points(stats.rms_error)[..., 0]
        for j in range(count):
            df = base.copy()
            df["stage"] = stage
            df["design"] = designs[j] if designs is not None else stage
            df["index"] = j
            vec = x[:, j] * np.ones((1, n))
            df["m_a"] = np.exp(vec.mean(axis=1))
            df["m_a_vec"] = list(np.exp(vec))
            df["loss"] = loss[:, j]
            df["gm_error_mm"] = 1e3 * np.exp(loss[:, j] / 2.0)
            df["rms_error_mm"] = 1e3 * rms[:, j]
            df["failed_fraction"] = failed[:, j]
            df["completion"] = completion[:, j]
            if grad is None:
                df["grad"] = np.nan
                df["grad_vec"] = [np.zeros(0)] * rows
            else:
                gv = points(grad)[:, j]
                df["grad"] = gv.sum(axis=1)
                df["grad_vec"] = list(gv) if gv.shape[1] == n else [np.zeros(0)] * rows
            df["reliable"] = np.isfinite(loss[:, j]) & (failed[:, j] <= mf)
            frames.append(df)

    G, K, E = int(np.shape(part.params.m_a_grid)[1]), cfg.refine.steps, len(EVAL_DESIGNS)
    grid, scalar, per = out.search.grid, out.search.scalar, out.search.per_actuator
    add("grid", G, np.log(grid.m_a), grid.info, grid.grad)
    add("scalar", K, scalar.log_m_a, scalar, scalar.grad)
    if per is not None:
        add("per_actuator", K, per.log_m_a, per, per.grad)
    keep = E if per is not None else E - 1  # without a per-actuator design its slot repeats the scalar one
    add("eval", E, out.held_out.log_m_a, out.held_out.info, None, designs=EVAL_DESIGNS[:keep], count=keep)
    return pd.concat(frames, ignore_index=True)


# --------------------------------------------------------------------------- summary

def best_point(g: pd.DataFrame) -> pd.Series:
    """The lowest-loss reliable row of a refinement trace (its first row if none is reliable)."""
    ok = g[g["reliable"]]
    return ok.loc[ok["loss"].idxmin()] if len(ok) else g.iloc[0]


FLAT_TOLERANCE = 1.1
"""``m_a_within_10pct``: the grid magnitudes whose geometric-mean error is within this factor of the best."""


def _flat_range(grid: pd.DataFrame) -> list[float]:
    """``[low, high]``: the contiguous grid range around the best point within :data:`FLAT_TOLERANCE` of its error."""
    g = grid.sort_values("index")
    err, m = g["gm_error_mm"].to_numpy(), g["m_a"].to_numpy()
    best = int(np.argmin(err))
    ok = err <= FLAT_TOLERANCE * err[best]
    lo = hi = best
    while lo > 0 and ok[lo - 1]:
        lo -= 1
    while hi < len(ok) - 1 and ok[hi + 1]:
        hi += 1
    return [float(m[lo]), float(m[hi])]


def _gradient_check(grid: pd.DataFrame) -> dict[str, Any]:
    """Does the gradient's sign match the grid's own slope? Central differences of the grid loss in log m_a at the
    interior points, split by the reliability flag (the detector of the unreliable regime)."""
    g = grid.sort_values("index")
    x, y = np.log(g["m_a"].to_numpy()), g["loss"].to_numpy()
    slope = (y[2:] - y[:-2]) / (x[2:] - x[:-2])
    grad, rel = g["grad"].to_numpy()[1:-1], g["reliable"].to_numpy()[1:-1]
    agree = np.sign(grad) == np.sign(slope)
    out = {}
    for name, mask in (("reliable", rel), ("unreliable", ~rel)):
        out[name] = {"points": int(mask.sum()),
                     "sign_agrees": float(agree[mask].mean()) if mask.any() else None}
    return out


def summarize(table: pd.DataFrame, cfg: DesignConfig) -> dict[str, Any]:
    """Per system and noise level: grid best, refined scalar and per-actuator optima, held-out errors and savings."""
    systems: dict[str, Any] = {}
    for entry in cfg.systems:
        proto = protocol(cfg, entry)
        name = system_name(proto.spec)
        t = table[table["system"] == name]
        if t.empty:
            continue
        levels = []
        for _level, g in t.groupby("noise_level", sort=True):
            grid = g[g["stage"] == "grid"]
            gb = grid.loc[grid["loss"].idxmin()]
            scalar = g[g["stage"] == "scalar"]
            sb = best_point(scalar)
            ev: dict[str, dict[str, Any]] = {str(r["design"]): {
                "m_a": [float(v) for v in r["m_a_vec"]], "loss": float(r["loss"]),
                "gm_error_mm": float(r["gm_error_mm"]), "rms_error_mm": float(r["rms_error_mm"]),
                "failed_fraction": float(r["failed_fraction"]), "completion": float(r["completion"]),
            } for _, r in g[g["stage"] == "eval"].iterrows()}
            item: dict[str, Any] = {
                "pose_noise": float(gb["pose_noise"]), "rot_noise": float(gb["rot_noise"]),
                "grid_best_m_a": float(gb["m_a"]), "grid_best_loss": float(gb["loss"]),
                "m_a_within_10pct": _flat_range(grid),
                # the refinement stays in the grid's range: an optimum on its edge asks for a wider grid
                "at_grid_edge": bool(np.isclose(sb["m_a"], grid["m_a"].min(), rtol=1e-3)
                                     or np.isclose(sb["m_a"], grid["m_a"].max(), rtol=1e-3)),
                "grid_failed_fraction": [float(v) for v in grid.sort_values("index")["failed_fraction"]],
                "scalar_m_a": float(sb["m_a"]), "scalar_loss": float(sb["loss"]),
                "scalar_unreliable_steps": int((~scalar["reliable"]).sum()),
                "gradient_check": _gradient_check(grid),
                "held_out": ev,
            }
            per = g[g["stage"] == "per_actuator"]
            if len(per):
                pb = best_point(per)
                item.update({"per_actuator_m_a": [float(v) for v in pb["m_a_vec"]],
                             "per_actuator_loss": float(pb["loss"]),
                             "per_actuator_unreliable_steps": int((~per["reliable"]).sum())})
            if "scalar" in ev and "per_actuator" in ev and len(per):
                # geometric-mean RMS error ratio on held-out trials: exp((L_per - L_scalar) / 2)
                item["per_actuator_error_saved"] = 1.0 - float(np.exp((ev["per_actuator"]["loss"]
                                                                       - ev["scalar"]["loss"]) / 2.0))
            if "scalar" in ev and "default" in ev:
                item["scalar_error_saved_vs_default"] = 1.0 - float(np.exp((ev["scalar"]["loss"]
                                                                            - ev["default"]["loss"]) / 2.0))
            levels.append(item)
        systems[name] = {
            "n_act": int(len(t[t["stage"] == "eval"]["m_a_vec"].iloc[0])),
            "protocol": {"path": proto.path.model_dump(), "controller": proto.controller.model_dump(),
                         "m_a_grid": proto.m_a_grid.model_dump(),
                         "m_a_source": "system" if proto.m_a is None else "config"},
            "noise_levels": levels,
        }
    return {
        "iters": cfg.iters, "n_configs": cfg.n_configs, "n_trials": cfg.n_trials, "eval_trials": cfg.eval_trials,
        "refine": cfg.refine.model_dump(), "per_actuator": cfg.per_actuator, "follow_from": cfg.follow_from,
        "loss": "mean over rollouts of log(mean squared path distance + (1e-3 tol)^2) [log m^2], failed rollouts "
                "(diverged, non-finite or incomplete) saturated at the divergence distance",
        "systems": systems,
    }


def report(summary: dict) -> str:
    """One line per system and noise level: grid best, refined scalar and per-actuator m_a, held-out savings."""
    lines = []
    for name, s in summary["systems"].items():
        for lv in s["noise_levels"]:
            ho = lv["held_out"]
            line = (f"{name}: noise {1e3 * lv['pose_noise']:g} mm: m_a grid {lv['grid_best_m_a']:.3g}, refined "
                    f"{lv['scalar_m_a']:.3g}")
            if "per_actuator_m_a" in lv:
                line += ", per actuator [" + ", ".join(f"{v:.3g}" for v in lv["per_actuator_m_a"]) + "]"
            lo, hi = lv["m_a_within_10pct"]
            line += f" (within 10% of the best error: {lo:.3g}-{hi:.3g})"
            line += "; held-out error (geometric mean RMS) " + ", ".join(
                f"{d} {ho[d]['gm_error_mm']:.3g} mm" for d in EVAL_DESIGNS if d in ho)
            if "per_actuator_error_saved" in lv:
                line += f"; per actuator saves {100 * lv['per_actuator_error_saved']:.1f}%"
            if lv.get("at_grid_edge"):
                line += " [optimum on the grid's edge: widen m_a_grid]"
            unrel = lv["scalar_unreliable_steps"] + lv.get("per_actuator_unreliable_steps", 0)
            if unrel:
                line += f" ({unrel} unreliable gradient steps not followed)"
            lines.append(line)
    return "\n".join(lines)


# --------------------------------------------------------------------------- figures

plot = figures_plot("design")  # experiments/figures/design.py, imported (with matplotlib) when called


COLUMNS = {
    "system": "system name [label]",
    **NOISE_COLUMNS,
    "stage": "'grid', 'scalar', 'per_actuator' (refinement paths) or 'eval' (held-out comparison) [label]",
    "design": "on eval rows the design compared ('default', 'grid', 'scalar', 'per_actuator'); else the stage "
              "[label]",
    "index": "the point's index within its stage, in evaluation order [id]",
    "m_a": "self-ID magnitude of the point, geometric mean over actuators [rad or m]",
    "m_a_vec": "(n_act,) self-ID magnitude of the point per actuator [rad or m: the actuator's unit]",
    "loss": "design loss: mean over rollouts of log(mse + floor), failures saturated [log m^2]",
    "gm_error_mm": "1e3 exp(loss / 2): geometric mean over rollouts of the RMS path error [mm]",
    "rms_error_mm": "RMS path error over the rollouts that did not fail [mm]",
    "failed_fraction": "fraction of the point's rollouts that failed [-]",
    "completion": "mean fraction of the path's waypoints reached [-]",
    "grad": "d loss / d log m_a summed over actuators; NaN on eval rows [log m^2 per unit log m_a]",
    "grad_vec": "(n_act,) d loss / d log m_a_i per actuator; empty on eval and scalar rows [log m^2 per unit log m_a]",
    "reliable": "finite loss and failed_fraction <= refine.max_failed: the gradient may be followed [bool]",
}
"""The results columns (``results.parquet``): one row per evaluated point (module docstring)."""


EXPERIMENT = Experiment(
    name="design",
    config=DesignConfig,
    build=build,
    compute=compute,
    summarize=summarize,
    columns=COLUMNS,
    tabulate=tabulate,
    plot=plot,
    report=report,
    description="self-ID design: the self-ID magnitude m_a per system and tracker noise, by grid and gradient",
)
