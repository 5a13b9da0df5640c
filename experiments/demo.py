"""The README's main job: self-identify the UR5e, then follow a star with the estimated inverse Jacobian.

From a few start configurations at once (one vmapped, compiled call), the arm
runs Algorithm 1 (random actuations of ``m_a`` rad, signed x magnitude initial
guess, closed-form refinement, convergence test of Sec. IV-D), then follows a
5 cm star with the final estimate and, for comparison, with the true inverse
Jacobian, both from where self-ID left the arm. ``selfid-jax demo`` runs it
with the defaults of :class:`DemoConfig` into ``runs/demo`` (``results.parquet``,
``summary.json``, ``figures/demo.png``) and prints the summary.
"""

from __future__ import annotations

from typing import Annotated, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import Field, field_validator, model_validator

from selfid_jax import control
from selfid_jax.control import paths
from selfid_jax.identify import algorithm as selfid
from selfid_jax.identify import estimator
from selfid_jax.math.linalg import pseudo_inverse
from selfid_jax.runner import Experiment, Part, part_threads, precision
from selfid_jax.runner.config import unique
from selfid_jax.runner.execute import side_by_side
from selfid_jax.systems import System

from .common.lazy_figures import figures_plot
from .common.schema import (
    ControllerConfig,
    HostOrDevice,
    PathConfig,
    SelfIdConfig,
    StudyConfig,
    add_m_a_columns,
    controller_rows,
    m_a_columns,
    m_a_summary,
)
from .common.specs import SystemSpec, build_system, needs_x64, system_name


class DemoRun(SelfIdConfig):
    """One robot of the demo: self-ID from ``n_configs`` start configurations, then a star with each estimate.

    ``m_a``: the system's own unless given (:class:`~selfid_jax.experiments.common.schema.SelfIdConfig`).
    """

    system: SystemSpec = Field("ur5e", description="a built-in name or {mjcf: ...} / {pose_fn: ...}")
    n_configs: int = Field(4, ge=1, le=10**4, description="start configurations")
    iters: int = Field(30, ge=2, le=10**4, description="self-ID iterations (Algorithm 1)")
    eps: float = Field(0.5, ge=0, le=1e6, description="Sec. IV-D threshold on ||J_t - J_{t-1}||_F [rad/m]")
    eps_rel: float = Field(0.0, ge=0, le=10, description="relative Sec. IV-D threshold (times ||J_t||_F)")
    path: PathConfig = PathConfig(size=0.05)
    controller: ControllerConfig = ControllerConfig(steps=400)

    @model_validator(mode="after")
    def _consistent(self):
        self.path.check_controller(self.controller)
        estimator.check_thresholds(self.eps, self.eps_rel)
        return self


class DemoConfig(StudyConfig):
    """The main job: each run self-identifies its robot and follows a star with the estimates and the truth.

    Default: the UR5e and the Model O hand (eps relative for the hand: its inverse Jacobian is dimensionless
    with a norm near 3, so a 5% change between estimates is the scale-free test).
    """

    experiment: Literal["demo"] = "demo"
    runs: Annotated[list[DemoRun], Field(min_length=1)] = [
        DemoRun(),  # the UR5e: its m_a 0.03 rad, eps 0.5 rad/m, a 5 cm star in 2.5 mm steps
        DemoRun(  # the Model O (float64): its tendon steps of 0.3 mm, 5% relative eps, a 1.5 mm star in 0.2 mm steps
            system="model_o", iters=20, eps=0.0, eps_rel=0.05, path=PathConfig(size=0.0015),
            controller=ControllerConfig(max_step=0.0002, tol=0.00005, steps=165),
        ),
    ]

    @field_validator("runs")
    @classmethod
    def _unique(cls, runs: list[DemoRun]) -> list[DemoRun]:
        unique([system_name(r.system) for r in runs], "run systems")
        return runs


class Static(NamedTuple):
    system: System
    path: jax.Array  # (W, 3) star waypoint offsets [m]
    iters: int
    steps: int


class Params(NamedTuple):
    key: HostOrDevice  # (2,) uint32 PRNG key data of the self-ID stream
    q0: HostOrDevice  # (n,) start configuration [rad]
    m_a: HostOrDevice  # (n_act,) self-ID magnitude per actuator [rad or m]
    eps: HostOrDevice  # () Sec. IV-D threshold [rad/m]
    eps_rel: HostOrDevice  # () relative Sec. IV-D threshold
    controller: control.ControllerParams


class Outputs(NamedTuple):
    q0: jax.Array  # (n,) start configuration of self-ID [rad]
    converged_at: jax.Array  # () int32 Sec. IV-D iteration, -1 if never
    relative_error: jax.Array  # () ||J_est - J_true||_F / ||J_true||_F at the start of the star
    task_error: jax.Array  # () ||J(q) J_est - I||_F: the part of the error the controller sees
    completion_estimated: jax.Array  # () star completion with the estimate
    completion_true: jax.Array  # () ... with the true inverse Jacobian
    mean_error_estimated: jax.Array  # () mean distance to the path [m]
    mean_error_true: jax.Array  # () [m]
    estimate: jax.Array  # (n, m) final self-ID estimate [rad/m]
    truth: jax.Array  # (n, m) true inverse Jacobian where the star starts [rad/m]
    deltas: jax.Array  # (iters,) ||J_t - J_{t-1}||_F per self-ID iteration [rad/m]
    positions_estimated: jax.Array  # (steps + 1, 3) end-effector positions [m]
    positions_true: jax.Array  # (steps + 1, 3) [m]


def start_jacobian_law(system: System, estimate, use_true) -> control.StepLaw:
    """:func:`control.inverse_jacobian_law` with :func:`control.estimate_or_true` (``dq = Jinv V``, the same
    arithmetic), whose state keeps the Jacobian ``J (m, n)`` read at the first step: the true Jacobian where the
    star starts, with no evaluation of the pose map outside the loop (on a closed-chain hand each place it is
    evaluated is a Newton solve compiled again). The state is NaN if the rollout never moved."""
    source = control.estimate_or_true(estimate, use_true)
    n, m = system.n_act, system.task_dim

    def init(q0):
        return jnp.full((m, n), jnp.nan, q0.dtype), jnp.zeros((), bool)

    def sense(state, q):
        pose, J = system.pose_and_jacobian(q)
        return pose, (J, jnp.where(source.use_true, pseudo_inverse(J), source.estimate))

    def step(state, q, pose, aux, V):
        J, Jinv = aux
        J0, seen = state
        return Jinv @ V, (jnp.where(seen, J0, J), jnp.ones((), bool)), jnp.all(jnp.isfinite(Jinv))

    return control.StepLaw(init=init, sense=sense, step=step)


def compute(static: Static, p: Params) -> Outputs:
    """Self-ID from ``p.q0``, then the star from where self-ID ended, with the estimate and with the truth."""
    system = static.system
    sid = selfid.run(system, jax.random.wrap_key_data(jnp.asarray(p.key)), p.q0, iters=static.iters, eps=p.eps,
                     eps_rel=p.eps_rel, m_a=p.m_a)
    q_start = sid.env  # follow from where self-ID left the arm
    # Both stars in one vmapped rollout, J and its inverse from one evaluation, J where the star starts from the
    # loop's first step: the pose map is evaluated at two places in this program (self-ID's and the loop's).
    both, (J_start, _) = jax.vmap(lambda use_true: control.follow_law(
        system, start_jacobian_law(system, sid.estimate, use_true), static.path, q_start, p.controller,
        steps=static.steps, return_trajectory=True))(jnp.array([False, True]))
    est, true = (jax.tree.map(lambda x, k=k: x[k], both) for k in (0, 1))
    J = J_start[1]  # the truth's lane (both lanes read the same J at the same start)
    truth = pseudo_inverse(J)
    return Outputs(
        q0=jnp.asarray(p.q0),
        converged_at=sid.converged_at,
        relative_error=jnp.linalg.norm(sid.estimate - truth) / jnp.linalg.norm(truth),
        task_error=jnp.linalg.norm(J @ sid.estimate - jnp.eye(system.task_dim, dtype=J.dtype)),
        completion_estimated=est.completion,
        completion_true=true.completion,
        mean_error_estimated=est.mean_error,
        mean_error_true=true.mean_error,
        estimate=sid.estimate,
        truth=truth,
        deltas=sid.deltas,
        positions_estimated=est.positions,
        positions_true=true.positions,
    )


def build(cfg: DemoConfig) -> list[Part]:
    """One part per run, each built (and later run) in float64 if its system needs it (closed-chain hands).

    The runs are built side by side in threads (:func:`~selfid_jax.runner.part_threads`: their start
    searches compile on a core each); each part is what it would be built alone.
    """

    def one(i: int, run: DemoRun) -> Part:
        x64 = needs_x64(run.system)
        with precision(x64):
            return _run_part(run, cfg.seed + 2 * i, x64)

    return side_by_side(one, cfg.runs, threads=part_threads(len(cfg.runs)), name="selfid-jax-build")


def _run_part(run: DemoRun, seed: int, x64: bool) -> Part:
    """``n_configs`` feasible starts (key ``seed``) and one self-ID stream each (keys from ``seed + 1``)."""
    system = build_system(run.system)
    path = paths.star(size=run.path.size, dim=system.task_dim)
    ctrl = control.ControllerParams(**run.controller.traced())
    q0 = np.asarray(control.feasible_starts(system, path, jax.random.key(seed), run.n_configs, ctrl,
                                            steps=run.controller.steps))
    n = run.n_configs
    keys = np.asarray(jax.random.key_data(jax.random.split(jax.random.key(seed + 1), n)))
    m_a = run.magnitude(system, f"runs[{system_name(run.system)}].m_a")
    params = Params(key=keys, q0=q0, m_a=np.repeat(m_a.value[None], n, axis=0), eps=np.full((n,), run.eps),
                    eps_rel=np.full((n,), run.eps_rel), controller=controller_rows(run.controller, n))
    meta = pd.DataFrame({"system": system_name(run.system), "config_id": np.arange(n)})
    add_m_a_columns(meta, m_a)
    return Part(system_name(run.system), Static(system, path, run.iters, run.controller.steps), params, meta, x64)


def summarize(table: pd.DataFrame, cfg: DemoConfig) -> dict:
    """Per run and start configuration: convergence iteration, errors, completions; the protocol beside them."""
    runs = {}
    for run in cfg.runs:
        name = system_name(run.system)
        g = table[table["system"] == name]

        def col(column, g=g):
            return g[column].to_numpy().tolist()

        n_act = int(len(g["q0"].iloc[0]))
        runs[name] = {
            "n_act": n_act,
            "task_dim": int(len(g["estimate"].iloc[0]) // n_act),
            "self_id": {"iterations": run.iters, **m_a_summary(g), "eps": run.eps, "eps_rel": run.eps_rel},
            "controller": run.controller.model_dump(),
            "path": run.path.model_dump(),
            "start_configs": [np.asarray(q).tolist() for q in g["q0"]],
            "converged_at": col("converged_at"),
            "relative_error_vs_true_inverse": col("relative_error"),
            "task_error_J_Jest_minus_I": col("task_error"),
            "completion_estimated": col("completion_estimated"),
            "completion_true": col("completion_true"),
            "mean_tracking_error_estimated_m": col("mean_error_estimated"),
            "mean_tracking_error_true_m": col("mean_error_true"),
        }
    return {"runs": runs}


def report(summary: dict) -> str:
    """Per run: the per-configuration table and what its error columns mean."""
    lines = []
    for name, r in summary["runs"].items():
        n = len(r["converged_at"])
        lines += [
            f"{name} self-ID from {n} start configurations, then a {1e3 * r['path']['size']:g} mm star "
            f"(m_a {r['self_id']['m_a']}, eps {r['self_id']['eps']}, eps_rel {r['self_id']['eps_rel']})",
            f"{'config':>6s} {'converged at':>12s} {'rel. error':>10s} {'||J Jest - I||':>14s} "
            f"{'completion est/true':>20s} {'tracking error est/true [mm]':>29s}",
        ]
        for b in range(n):
            lines.append(
                f"{b:6d} {r['converged_at'][b]:12d} {r['relative_error_vs_true_inverse'][b]:10.3f} "
                f"{r['task_error_J_Jest_minus_I'][b]:14.3f} "
                f"{r['completion_estimated'][b]:9.0%} / {r['completion_true'][b]:4.0%} "
                f"{1e3 * r['mean_tracking_error_estimated_m'][b]:16.3f} / "
                f"{1e3 * r['mean_tracking_error_true_m'][b]:.3f}"
            )
        if r["n_act"] > r["task_dim"]:
            lines += [
                f"rel. error = ||J_est - J_true^+||_F / ||J_true^+||_F. With {r['n_act']} actuators and a "
                f"{r['task_dim']}-D task, any J_est with",
                "J J_est = I tracks perfectly; J_est may differ from the minimum-norm J^+ by null-space rows the task",
                "samples cannot pin down, so rel. error stays large while ||J J_est - I|| is what the controller sees.",
            ]
    return "\n".join(lines)


plot = figures_plot("demo")  # experiments/figures/demo.py, imported (with matplotlib) when called


COLUMNS = {
    "system": "the run's system name [label]",
    "config_id": "start configuration index [id]",
    **m_a_columns(),
    "q0": "(n_act,) start configuration of self-ID [rad or m]",
    "converged_at": "self-ID iteration meeting the Sec. IV-D test, -1 if never [iteration]",
    "relative_error": "||J_est - J_true^+||_F / ||J_true^+||_F where the star starts [-]",
    "task_error": "||J(q) J_est - I||_F where the star starts: the part of the error the controller sees [-]",
    "completion_estimated": "fraction of the star's waypoints reached with the self-ID estimate [-]",
    "completion_true": "fraction of the star's waypoints reached with the true inverse Jacobian [-]",
    "mean_error_estimated": "mean distance to the path over the steps used, with the estimate [m]",
    "mean_error_true": "mean distance to the path over the steps used, with the true inverse Jacobian [m]",
    "estimate": "(n_act * task_dim,) final self-ID estimate, row-major (n_act, task_dim) [actuator unit per task "
                "unit: rad/m for an arm's position task]",
    "truth": "(n_act * task_dim,) true inverse Jacobian where the star starts, row-major (n_act, task_dim) "
             "[actuator unit per task unit]",
    "deltas": "(iters,) ||J_t - J_{t-1}||_F per self-ID iteration [actuator unit per task unit]",
    "positions_estimated": "((steps + 1) * 3,) end-effector positions with the estimate, row-major (steps + 1, 3) [m]",
    "positions_true": "((steps + 1) * 3,) end-effector positions with the true inverse, row-major (steps + 1, 3) [m]",
}
"""The results columns (``results.parquet``): one row per system and start configuration."""


EXPERIMENT = Experiment(
    name="demo",
    config=DemoConfig,
    build=build,
    compute=compute,
    summarize=summarize,
    columns=COLUMNS,
    plot=plot,
    report=report,
    description="the main job: self-ID of each robot from 4 starts, then a star with the estimate and the truth",
)
