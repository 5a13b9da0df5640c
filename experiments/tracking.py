"""Tracking (paper Sec. V-B to V-F, Tables I-II): self-ID on a system, then a path with the estimate and the truth.

Every row of the grid (start configuration x trial x tracker-noise level)
runs Algorithm 1 on the system (with Gaussian tracker noise on every pose
reading), then follows the path (letters, a cube's 12 edges or a star) from
where self-ID left the robot, once with the final estimate and once with the
true ("analytical") inverse Jacobian, recording the trajectory. Metrics per
rollout and inverse Jacobian: the mean per-axis distance of the POM to the
commanded path over the steps used (x, y, z, mm, Table I), the waypoint error
(mm), completion, the final orientation error (deg, Table II; 0 for position
tasks) and the self-ID convergence iteration. All of it is one compiled
function per system.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, Field, model_validator

from selfid_jax import control, estimator, geometry, metrics, paths, selfid
from selfid_jax.config import BaseConfig, ControllerConfig, check_noise_pairs
from selfid_jax.experiment import Experiment, Part, controller_rows, precision
from selfid_jax.plots import save_figure
from selfid_jax.sweep import grid_table, row_keys
from selfid_jax.systems import System
from selfid_jax.systems.spec import SystemSpec, build_system, needs_x64, system_name

INVERSES = ("estimated", "analytical")


class TrackingPath(BaseModel):
    """The commanded path, as offsets from where self-ID ended (:mod:`selfid_jax.paths`)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    kind: Literal["text", "letters", "cube", "star"]
    text: str = Field("E", min_length=1, description="letters for kinds 'text' (one path) and 'letters' "
                      "(one path per letter, each from a fresh self-ID, as the paper re-runs self-ID per letter)")
    height: float = Field(0.012, gt=0, le=1, description="letter height [m] (kind 'text')")
    edge: float = Field(0.15, gt=0, le=2, description="cube edge [m] (kind 'cube')")
    size: float = Field(0.05, gt=0, le=10, description="star radius [m] (kind 'star')")
    plane: Literal["xy", "xz", "yz"] = "xy"

    def waypoints(self, dim: int) -> jax.Array:
        """``(L, W, dim)`` waypoint offsets, one path per letter for kind 'letters' (shorter letters padded by
        repeating their last waypoint, reached at once), else ``L = 1``; rotation parts 0 (constant orientation)."""
        if self.kind == "letters":
            letters = [np.asarray(paths.text(c, height=self.height, plane=self.plane, dim=dim)) for c in self.text]
            W = max(len(w) for w in letters)
            return jnp.asarray(np.stack([np.concatenate([w, np.repeat(w[-1:], W - len(w), axis=0)]) for w in letters]))
        return self._one(dim)[None]

    def labels(self) -> list[str]:
        """The path label of each of the ``L`` paths."""
        return list(self.text) if self.kind == "letters" else [self.kind if self.kind != "text" else self.text]

    def _one(self, dim: int) -> jax.Array:
        if self.kind == "text":
            return paths.text(self.text, height=self.height, plane=self.plane, dim=dim)
        if self.kind == "cube":
            if dim == 2:
                raise ValueError("a cube needs a 3-D or 6-D task")
            return paths.cube(edge=self.edge, dim=dim)
        return paths.star(size=self.size, plane=self.plane, dim=dim)

    def scale(self) -> float:
        """The path's smallest feature [m], for the tolerance check."""
        return {"text": self.height / 6.0, "letters": self.height / 6.0, "cube": self.edge, "star": self.size}[self.kind]


class TrackingConfig(BaseConfig):
    """Self-ID then path tracking with the estimate and the truth, over configs x trials x tracker noise."""

    experiment: Literal["tracking"] = "tracking"
    system: SystemSpec = Field("ur5e", description="a built-in name or {mjcf: ...} / {pose_fn: ...}")
    path: TrackingPath
    controller: ControllerConfig = ControllerConfig()
    n_configs: int = Field(ge=1, le=10**5)
    n_trials: int = Field(1, ge=1, le=10**5)
    iters: int = Field(30, ge=2, le=10**4, description="self-ID iterations (Algorithm 1)")
    m_a: float = Field(gt=0, le=0.1, description="self-ID magnitude [rad or m]")
    eps: float = Field(0.5, ge=0, le=1e6, description="Sec. IV-D threshold on ||J_t - J_{t-1}||_F")
    eps_rel: float = Field(0.0, ge=0, le=10, description="relative Sec. IV-D threshold (times ||J_t||_F)")
    pose_noise: Annotated[list[Annotated[float, Field(ge=0, le=0.1)]], Field(min_length=1)] = [0.0]  # m
    rot_noise: Annotated[list[Annotated[float, Field(ge=0, le=1.0)]], Field(min_length=1)] = [0.0]  # rad

    @model_validator(mode="after")
    def _consistent(self):
        check_noise_pairs(self.pose_noise, self.rot_noise)
        estimator.check_thresholds(self.eps, self.eps_rel)
        if not self.controller.tol < self.path.scale() / 2:
            raise ValueError(f"controller.tol ({self.controller.tol}) must be below half the path's smallest "
                             f"feature ({self.path.scale()} m)")
        return self


class Static(NamedTuple):
    system: System
    path: jax.Array  # (L, W, task_dim) waypoint offsets, one path per letter (L = 1 unless kind 'letters')
    iters: int
    steps: int


class Params(NamedTuple):
    letter: jax.Array  # () int32 index into Static.path
    key: jax.Array  # (2,) uint32 PRNG key data
    q0: jax.Array  # (n,) start configuration
    pose_noise: jax.Array  # () tracker position noise sd [m]
    rot_noise: jax.Array  # () tracker rotation noise sd [rad]
    m_a: jax.Array  # () self-ID magnitude
    eps: jax.Array  # () Sec. IV-D threshold
    eps_rel: jax.Array  # () relative Sec. IV-D threshold
    controller: control.ControllerParams


class Outputs(NamedTuple):
    """Per rollout; axis 0 is (estimated, analytical)."""

    converged_at: jax.Array  # () int32 self-ID convergence iteration, -1 if never
    completion: jax.Array  # (2,) fraction of waypoints reached
    waypoint_error_mm: jax.Array  # (2,) mean position error when each waypoint was reached [mm]
    error_mm: jax.Array  # (2, 3) mean |distance to the path| along x, y, z over the steps used [mm]
    rot_final_deg: jax.Array  # (2,) orientation error to the last waypoint at the end [deg]
    rot_step_deg: jax.Array  # (2,) mean orientation error to the start orientation over the steps used [deg]
    failed: jax.Array  # (2,) bool
    steps_used: jax.Array  # (2,) int32 control steps taken
    positions: jax.Array  # (2, steps + 1, 3) POM positions [m]


def compute(static: Static, p: Params) -> Outputs:
    """Self-ID from ``p.q0`` with tracker noise, then the path with the estimate and with the truth."""
    system = static.system
    sid = selfid.run(system, jax.random.wrap_key_data(p.key), p.q0, iters=static.iters, eps=p.eps,
                     eps_rel=p.eps_rel, m_a=p.m_a, pose_noise=p.pose_noise, rot_noise=p.rot_noise)
    q_start = sid.env
    path = static.path[p.letter]
    p0, R0 = system.pose(q_start)
    pos_dim = min(system.task_dim, 3)
    vertices = jnp.concatenate([p0[None, :pos_dim], p0[None, :pos_dim] + path[:, :pos_dim]])
    R_goal = (geometry.so3_exp(path[-1, 3:]) @ R0) if system.task_dim == 6 else R0

    def track(jinv):
        res = control.follow(system, jinv, path, q_start, p.controller, steps=static.steps,
                             return_trajectory=True)
        used = jnp.arange(res.positions.shape[0]) <= res.steps_used  # the steps taken, and where they ended
        err = metrics.axis_errors(res.positions[:, :pos_dim], vertices)
        err = jnp.sum(jnp.where(used[:, None], err, 0.0), axis=0) / jnp.sum(used)
        err = jnp.concatenate([err, jnp.zeros((3 - pos_dim,), err.dtype)])
        rot = metrics.rotation_errors_deg(R_goal, system.pose(res.final_q)[1]) if system.task_dim == 6 else 0.0
        # the shipped paths hold the orientation constant, so the goal at every step is the start orientation
        per_step = metrics.rotation_errors_deg(R0, res.orientations) if system.task_dim == 6 else \
            jnp.zeros(res.positions.shape[0], err.dtype)
        rot_step = jnp.sum(jnp.where(used, per_step, 0.0)) / jnp.sum(used)
        return (res.completion, 1e3 * res.waypoint_error, 1e3 * err, jnp.asarray(rot, err.dtype),
                jnp.asarray(rot_step, err.dtype), res.failed, res.steps_used, res.positions)

    est, true = track(control.fixed(sid.estimate)), track(control.true_inverse(system))
    stacked = [jnp.stack([a, b]) for a, b in zip(est, true)]
    return Outputs(sid.converged_at, *stacked)


def build(cfg: TrackingConfig) -> Part:
    """Configs x trials x noise levels; float64 where the system needs it (closed-chain hands)."""
    x64 = needs_x64(cfg.system)
    with precision(x64):
        return _build(cfg)._replace(x64=x64)


def _build(cfg: TrackingConfig) -> Part:
    system = build_system(cfg.system)
    path = cfg.path.waypoints(system.task_dim)
    labels = cfg.path.labels()
    meta = grid_table({"letter_id": range(len(labels)), "noise_level": range(len(cfg.pose_noise)),
                       "config_id": range(cfg.n_configs), "trial": range(cfg.n_trials)})
    meta.insert(1, "path", np.asarray(labels, dtype=object)[meta["letter_id"]])
    meta.insert(3, "pose_noise", np.asarray(cfg.pose_noise)[meta["noise_level"]])
    meta.insert(4, "rot_noise", np.asarray(cfg.rot_noise)[meta["noise_level"]])
    meta.insert(0, "system", system_name(cfg.system))
    longest = int(np.argmax([paths.path_length(w) for w in np.asarray(path)]))
    q0 = np.asarray(control.feasible_starts(system, path[longest], jax.random.key(cfg.seed), cfg.n_configs,
                                            control.ControllerParams(**cfg.controller.traced()),
                                            steps=cfg.controller.steps))
    n = len(meta)
    params = Params(
        letter=meta["letter_id"].to_numpy(np.int32), key=row_keys(cfg.seed, n), q0=q0[meta["config_id"].to_numpy()],
        pose_noise=meta["pose_noise"].to_numpy(float), rot_noise=meta["rot_noise"].to_numpy(float),
        m_a=np.full((n,), cfg.m_a), eps=np.full((n,), cfg.eps), eps_rel=np.full((n,), cfg.eps_rel),
        controller=controller_rows(cfg.controller, n),
    )
    return Part(system_name(cfg.system), Static(system, path, cfg.iters, cfg.controller.steps), params, meta)


def tabulate(wide: pd.DataFrame, part: Part, cfg: TrackingConfig) -> pd.DataFrame:
    """One row per (rollout, inverse Jacobian) with scalar metric columns; trajectories stay as list columns."""
    base = ["system", "letter_id", "path", "noise_level", "pose_noise", "rot_noise", "config_id", "trial",
            "converged_at"]
    frames = []
    for i, inverse in enumerate(INVERSES):
        df = wide[base].copy()
        df.insert(1, "inverse", inverse)
        err = np.stack(wide["error_mm"].to_numpy()).reshape(len(wide), 2, 3)[:, i]
        df["completion"] = np.stack(wide["completion"].to_numpy())[:, i]
        df["waypoint_error_mm"] = np.stack(wide["waypoint_error_mm"].to_numpy())[:, i]
        df["error_x_mm"], df["error_y_mm"], df["error_z_mm"] = err.T
        df["rot_final_deg"] = np.stack(wide["rot_final_deg"].to_numpy())[:, i]
        df["rot_step_deg"] = np.stack(wide["rot_step_deg"].to_numpy())[:, i]
        df["failed"] = np.stack(wide["failed"].to_numpy())[:, i].astype(bool)
        df["steps_used"] = np.stack(wide["steps_used"].to_numpy())[:, i]
        positions = np.stack(wide["positions"].to_numpy()).reshape(len(wide), 2, -1)[:, i]
        df["positions"] = list(positions)
        frames.append(df)
    return pd.concat(frames, ignore_index=True)


METRICS = ("waypoint_error_mm", "error_x_mm", "error_y_mm", "error_z_mm", "completion", "converged_at",
           "rot_final_deg", "rot_step_deg")


def _stats(g: pd.DataFrame) -> dict[str, Any]:
    """``{inverse: {metric: {mean, sd}}}`` over the rows ``g`` (failed rollouts left out of the error means)."""
    level: dict[str, Any] = {}
    for inverse, h in g.groupby("inverse", sort=False):
        ok = h[~h["failed"]]
        level[str(inverse)] = {
            m: {"mean": float(ok[m].mean()) if len(ok) else None, "sd": float(ok[m].std(ddof=0)) if len(ok) else None}
            for m in METRICS if m != "converged_at"
        }
        conv = h["converged_at"].to_numpy()
        level[str(inverse)]["converged_at"] = {"mean": float(conv[conv > 0].mean()) if (conv > 0).any() else None,
                                               "sd": float(conv[conv > 0].std()) if (conv > 0).any() else None}
        level[str(inverse)]["failed_fraction"] = float(h["failed"].mean())
    return level


def summarize(table: pd.DataFrame, cfg: TrackingConfig) -> dict[str, Any]:
    """Mean +- sd per system, tracker-noise level and inverse Jacobian (and per letter for kind 'letters')."""
    systems: dict[str, Any] = {}
    for (system, noise), g in table.groupby(["system", "pose_noise"], sort=False):
        entry = systems.setdefault(str(system), {"pose_noise_mm": {}})
        entry["pose_noise_mm"][f"{1e3 * noise:g}"] = _stats(g)
        if cfg.path.kind == "letters":
            per = entry.setdefault("letters", {})
            for letter, h in g.groupby("letter_id", sort=True):
                per.setdefault(f"{int(letter)}:{h['path'].iloc[0]}", {})[f"{1e3 * noise:g}"] = _stats(h)
    return {
        "path": cfg.path.model_dump(),
        "controller": cfg.controller.model_dump(),
        "self_id": {"iterations": cfg.iters, "m_a": cfg.m_a, "eps": cfg.eps, "eps_rel": cfg.eps_rel},
        "systems": systems,
    }


def report(summary: dict) -> str:
    """Table I/II-style lines: per system, noise level and inverse Jacobian."""
    lines = [f"{'system':14s} {'noise mm':>8s} {'inverse':>10s} {'waypoint mm':>14s} {'x mm':>6s} {'y mm':>6s} "
             f"{'z mm':>6s} {'rot end/step deg':>16s} {'completion':>10s} {'converged':>10s}"]
    for system, s in summary["systems"].items():
        for noise, level in s["pose_noise_mm"].items():
            for inverse, m in level.items():
                def f(key, scale=1.0, fmt=".2f"):
                    v = m[key]["mean"]
                    return "-" if v is None else format(scale * v, fmt)
                wp = "-" if m["waypoint_error_mm"]["mean"] is None else \
                    f"{m['waypoint_error_mm']['mean']:.2f} +- {m['waypoint_error_mm']['sd']:.2f}"
                lines.append(f"{system:14s} {noise:>8s} {inverse:>10s} {wp:>14s} {f('error_x_mm'):>6s} "
                             f"{f('error_y_mm'):>6s} {f('error_z_mm'):>6s} "
                             f"{f('rot_final_deg') + ' / ' + f('rot_step_deg'):>16s} "
                             f"{f('completion', 100, '.0f') + '%':>10s} {f('converged_at', fmt='.1f'):>10s}")
    return "\n".join(lines)


def plot(table: pd.DataFrame, summary: dict, out_dir: Path) -> list[Path]:
    """Executed paths (first start configuration, noise-free), estimated vs analytical, in 3-D for a cube.

    One figure per system, ``tracking_<system>.png|pdf``; the protocol is in the title.
    """
    from matplotlib.figure import Figure

    written: list[Path] = []
    three_d = summary["path"]["kind"] == "cube"
    for system, g in table.groupby("system", sort=False):
        first = g[(g["noise_level"] == 0) & (g["config_id"] == 0) & (g["trial"] == 0)]
        fig = Figure(figsize=(10, 4.8), layout="constrained")
        for k, inverse in enumerate(INVERSES):
            ax = fig.add_subplot(1, 2, k + 1, projection="3d" if three_d else None)
            color = "C0" if inverse == "estimated" else "C2"
            for _, row in first[first["inverse"] == inverse].iterrows():  # one row per letter
                pts = 1e3 * np.asarray(row["positions"]).reshape(-1, 3)[: int(row["steps_used"]) + 1]
                pts = pts - pts[0]
                if three_d:
                    ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], lw=1, color=color)
                    ax.set_zlabel("z [mm]")
                else:
                    ax.plot(pts[:, 0], pts[:, 1], lw=1, color=color)
                    ax.set_aspect("equal")
            ax.set_xlabel("x [mm]")
            ax.set_ylabel("y [mm]")
            ax.set_title(f"{system}: {inverse} inverse Jacobian", fontsize=9)
        c, s = summary["controller"], summary["self_id"]
        fig.suptitle(f"path {summary['path']['kind']}; step {1e3 * c['max_step']:g} mm, tol {1e3 * c['tol']:g} mm, "
                     f"{c['steps']} steps, gain {c['gain']:g}; self-ID m_a {s['m_a']:g}, eps {s['eps']:g}, "
                     f"eps_rel {s['eps_rel']:g}; noise-free rows, first configuration", fontsize=8)
        written += save_figure(fig, out_dir, f"tracking_{system}")
    return written


EXPERIMENT = Experiment(
    name="tracking",
    config=TrackingConfig,
    build=build,
    compute=compute,
    summarize=summarize,
    tabulate=tabulate,
    plot=plot,
    report=report,
    description="self-ID, then a path (letters, cube, star) with the estimate and the truth: Tables I-II",
)
