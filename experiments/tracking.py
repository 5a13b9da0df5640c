"""Tracking (paper Sec. V-B to V-F, Tables I-II): self-ID on a system, then a path with the estimate and the truth.

Every row of the grid (start configuration x trial x tracker-noise level)
runs Algorithm 1 on the system, then follows the path (letters, a cube's 12
edges or a star) from where self-ID left the robot, once with the final
estimate and once with the true ("analytical") inverse Jacobian, recording
the trajectory. Self-ID and the follow loop read one tracker: the level's
Gaussian noise is on every pose reading of both (and a ``realism`` section's
latency and dropouts too); the metrics are of the true pose. Metrics per
rollout and inverse Jacobian: the mean per-axis distance of the POM to the
commanded path over the steps used (x, y, z, mm, Table I), the waypoint error
(mm), completion, the final orientation error (deg, Table II; 0 for position
tasks) and the self-ID convergence iteration, and per-step traces of the
per-axis and rotation errors (Fig. 6-9). A task may be any set of pose
components (``task_axes``: e.g. a hand's object height and tilt ``[z, rx,
ry]`` for the rotation experiment); rotation errors are measured within the
task's rotation components. All of it is one compiled function per system.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import BaseModel, Field, model_validator

from selfid_jax import control
from selfid_jax.control import metrics, paths
from selfid_jax.control import realism as realism_lib
from selfid_jax.identify import estimator
from selfid_jax.math import geometry
from selfid_jax.runner import Experiment, Part, precision
from selfid_jax.runner.config import STRICT
from selfid_jax.runner.grids import grid_table, row_keys
from selfid_jax.systems import System
from selfid_jax.systems.validation import AXIS_NAMES

from .common import realism as realistic
from .common.lazy_figures import figures_plot
from .common.schema import (
    NOISE_COLUMNS,
    ControllerConfig,
    HostOrDevice,
    SelfIdConfig,
    StartsConfig,
    StudyConfig,
    TrackerNoiseConfig,
    add_m_a_columns,
    controller_rows,
    m_a_columns,
    m_a_summary,
    realism_columns,
)
from .common.specs import SystemSpec, build_system, needs_x64, system_name

INVERSES = ("estimated", "analytical")


class TrackingPath(BaseModel):
    """The commanded path, as offsets from where self-ID ended (:mod:`selfid_jax.control.paths`)."""

    model_config = STRICT

    kind: Literal["text", "letters", "cube", "star", "rotation"]
    text: str = Field("E", min_length=1, description="letters for kinds 'text' (one path) and 'letters' "
                      "(one path per letter, each from a fresh self-ID, as the paper re-runs self-ID per letter)")
    angle: float = Field(0.2, gt=-3.1, lt=3.1, description="rotation angle [rad] (kind 'rotation')")
    about: Annotated[list[Literal["x", "y", "z"]], Field(min_length=1)] = ["x", "y"]  # world axes, one path each
    rotation_steps: int = Field(10, ge=1, le=1000, description="waypoints along each rotation (kind 'rotation')")
    height: float = Field(0.012, gt=0, le=1, description="letter height [m] (kind 'text')")
    edge: float = Field(0.15, gt=0, le=2, description="cube edge [m] (kind 'cube')")
    size: float = Field(0.05, gt=0, le=10, description="star radius [m] (kind 'star')")
    plane: Literal["xy", "xz", "yz"] = "xy"

    def check_axes(self, axes: tuple[int, ...]) -> None:
        """Raise ``ValueError`` if the path moves along a pose component outside the task ``axes``."""
        moved = np.flatnonzero(np.any(np.abs(np.concatenate(self._paths())) > 0, axis=0))
        missing = [AXIS_NAMES[a] for a in moved if a not in axes]
        if missing:
            raise ValueError(f"path ({self.kind}) moves along {missing}, which the task "
                             f"{[AXIS_NAMES[a] for a in axes]} does not control; set task_axes or another system")

    def waypoints(self, axes: tuple[int, ...]) -> jax.Array:
        """``(L, W, len(axes))`` waypoint offsets in the task components ``axes`` (indices into ``[dp, rotation
        vector]``): one path per letter (kind 'letters') or per rotation axis (kind 'rotation'), shorter ones padded
        by repeating their last waypoint (reached at once), else ``L = 1``; components not given are 0 (held)."""
        full = [np.asarray(w)[:, list(axes)] for w in self._paths()]
        W = max(len(w) for w in full)
        return jnp.asarray(np.stack([np.concatenate([w, np.repeat(w[-1:], W - len(w), axis=0)]) for w in full]))

    def labels(self) -> list[str]:
        """The path label of each of the ``L`` paths."""
        if self.kind == "letters":
            return list(self.text)
        if self.kind == "rotation":
            return [f"r{a}" for a in self.about]
        return [self.kind if self.kind != "text" else self.text]

    def _paths(self) -> list[np.ndarray]:
        """Each path as ``(W, 6)`` offsets ``[dp, rotation vector]``."""
        if self.kind == "letters":
            return [paths.text(c, height=self.height, plane=self.plane, dim=6) for c in self.text]
        if self.kind == "rotation":
            unit = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
            return [paths.rotation(axis=unit[a], angle=self.angle, steps=self.rotation_steps) for a in self.about]
        if self.kind == "text":
            return [paths.text(self.text, height=self.height, plane=self.plane, dim=6)]
        if self.kind == "cube":
            return [paths.cube(edge=self.edge, dim=6)]
        return [paths.star(size=self.size, plane=self.plane, dim=6)]

    def scale(self) -> float:
        """The path's smallest positional feature [m], for the tolerance check (inf for a pure rotation)."""
        return {"text": self.height / 6.0, "letters": self.height / 6.0, "cube": self.edge, "star": self.size,
                "rotation": float("inf")}[self.kind]


class TrackingConfig(StudyConfig, SelfIdConfig, StartsConfig, TrackerNoiseConfig):
    """Self-ID then path tracking with the estimate and the truth, over configs x trials x tracker noise."""

    experiment: Literal["tracking"] = "tracking"
    system: SystemSpec = Field("ur5e", description="a built-in name or {mjcf: ...} / {pose_fn: ...}")
    task_axes: list[Literal["x", "y", "z", "rx", "ry", "rz"]] | None = Field(
        None, min_length=1, description="the task's pose components (default: the system's task_dim); e.g. "
        "[z, rx, ry] for a 3-actuator hand that tilts its object")
    path: TrackingPath
    controller: ControllerConfig = ControllerConfig()
    n_configs: int = Field(ge=1, le=10**5)
    n_trials: int = Field(1, ge=1, le=10**5)
    iters: int = Field(30, ge=2, le=10**4, description="self-ID iterations (Algorithm 1)")
    eps: float = Field(0.5, ge=0, le=1e6, description="Sec. IV-D threshold on ||J_t - J_{t-1}||_F")
    eps_rel: float = Field(0.0, ge=0, le=10, description="relative Sec. IV-D threshold (times ||J_t||_F)")

    @model_validator(mode="after")
    def _consistent(self):
        estimator.check_thresholds(self.eps, self.eps_rel)
        if self.path.kind == "rotation" and (self.task_axes is None or
                                             not {f"r{a}" for a in self.path.about} <= set(self.task_axes)):
            raise ValueError(f"task_axes must include the rotations of path.about {self.path.about} (e.g. "
                             "task_axes: [z, rx, ry]); otherwise they are not controlled")
        if not self.controller.tol < self.path.scale() / 2:
            raise ValueError(f"controller.tol ({self.controller.tol}) must be below half the path's smallest "
                             f"feature ({self.path.scale()} m)")
        return self


class Static(NamedTuple):
    system: System
    path: jax.Array  # (L, W, task_dim) waypoint offsets, one path per letter (L = 1 unless kind 'letters')
    iters: int
    steps: int
    # the follow loop's tracker history length - 1 [steps] (with realism; without, 0 if level_noise); None: the
    # ideal loop, which reads exact poses
    max_latency: int | None = None
    max_settle: int = 1  # with realism: the longest self-ID settle [steps]
    plant: realism_lib.Plant | None = None  # with realism.plant 'dynamic': the arm's physics; None: kinematic
    # some level has pose_noise or rot_noise > 0: the follow loop reads it too (False: the program of a config
    # without noise levels is the one it always was)
    level_noise: bool = False


class Params(NamedTuple):
    letter: HostOrDevice  # () int32 index into Static.path
    key: HostOrDevice  # (2,) uint32 PRNG key data
    q0: HostOrDevice  # (n,) start configuration
    pose_noise: HostOrDevice  # () tracker position noise sd [m]
    rot_noise: HostOrDevice  # () tracker rotation noise sd [rad]
    m_a: HostOrDevice  # (n,) self-ID magnitude per actuator [rad or m]
    eps: HostOrDevice  # () Sec. IV-D threshold
    eps_rel: HostOrDevice  # () relative Sec. IV-D threshold
    controller: control.ControllerParams
    realism: realism_lib.Realism | None = None  # () each, with a realism section
    settle: HostOrDevice | None = None  # () int32 self-ID settle steps, with a realism section


class Outputs(NamedTuple):
    """Per rollout; axis 0 is (estimated, analytical)."""

    converged_at: jax.Array  # () int32 self-ID convergence iteration, -1 if never
    completion: jax.Array  # (2,) fraction of waypoints reached
    waypoint_error_mm: jax.Array  # (2,) mean position error when each waypoint was reached [mm]
    error_mm: jax.Array  # (2, 3) mean |distance to the path| along x, y, z over the steps used [mm]
    rot_final_deg: jax.Array  # (2,) orientation error to the last waypoint at the end [deg]; 0 without rotation
    rot_step_deg: jax.Array  # (2,) mean orientation error to the pursued waypoint over the steps used [deg]
    failed: jax.Array  # (2,) bool
    steps_used: jax.Array  # (2,) int32 control steps taken
    positions: jax.Array  # (2, steps + 1, 3) POM positions [m]
    error_trace_mm: jax.Array  # (2, steps + 1, 3) |distance to the path| along x, y, z at each step [mm]
    rot_trace_deg: jax.Array  # (2, steps + 1) orientation error to the pursued waypoint at each step [deg]
    selfid_dropouts: jax.Array | None = None  # () int32 tracker dropouts during self-ID, with realism
    selfid_rejected: jax.Array | None = None  # () int32 self-ID samples rejected (dropouts, non-finite), with realism
    dropouts: jax.Array | None = None  # (2,) int32 tracker dropouts during each path, with realism


def compute(static: Static, p: Params) -> Outputs:
    """Self-ID from ``p.q0`` with tracker noise, then the path with the estimate and with the truth.

    Both read one tracker (:func:`selfid_jax.control.realism.with_tracker_noise`):
    the noise level's ``p.pose_noise`` [m] and ``p.rot_noise`` [rad] on every
    self-ID reading and every pose the follow loop reads, and with a realism
    section (``p.realism``) its latency, dropouts and servo too
    (:mod:`selfid_jax.control.realism`). Self-ID draws from the row's key, the
    follow loop from ``fold_in(key, 1)``; the two paths see the same tracker
    noise and dropout draws. Without realism and without noise on any level
    (``static.level_noise`` False) the follow loop reads exact poses.
    """
    system = static.system
    key = jax.random.wrap_key_data(jnp.asarray(p.key))
    sid, sid_dropouts = realistic.self_identify(
        system, key, p.q0, iters=static.iters, eps=p.eps, eps_rel=p.eps_rel, m_a=p.m_a, pose_noise=p.pose_noise,
        rot_noise=p.rot_noise, realism=p.realism, settle=p.settle, max_latency=static.max_latency or 0,
        max_settle=static.max_settle, plant=static.plant)
    q_start = sid.env
    follow_key = jax.random.fold_in(key, 1)
    path = static.path[p.letter]
    pose0 = system.pose(q_start)
    pos, rot = list(system.position_axes), system.rotation_axes
    p_goal, R_goal = control.waypoint_poses(path, pose0, system.axes)
    vertices = jnp.concatenate([pose0[0][None], p_goal])[:, pos]

    def rot_error_deg(R_g, R):
        """Angle of the rotation error within the task's rotation components [deg] (all three: the full angle)."""
        w = geometry.so3_log(R_g @ jnp.swapaxes(R, -1, -2))[..., jnp.asarray(rot)]
        return jnp.degrees(jnp.sqrt(jnp.sum(w * w, axis=-1)))

    sensed = p.realism  # what the tracker adds to the poses the follow loop reads
    if static.level_noise:
        sensed = realism_lib.with_tracker_noise(p.realism, p.pose_noise, p.rot_noise)

    def track(jinv):
        res = control.follow(system, jinv, path, q_start, p.controller, steps=static.steps,
                             return_trajectory=True, realism=sensed, key=follow_key,
                             max_latency=static.max_latency, plant=static.plant)
        positions, orientations = res.positions, res.orientations  # the trajectory (return_trajectory=True)
        assert positions is not None and orientations is not None and res.targets is not None
        used = jnp.arange(positions.shape[0]) <= res.steps_used  # the steps taken, and where they ended
        dtype = positions.dtype
        err = jnp.zeros((positions.shape[0], 3), dtype)
        if pos:
            err = err.at[:, jnp.asarray(pos)].set(metrics.axis_errors(positions[:, pos], vertices))
        zero = jnp.zeros(positions.shape[0], dtype)
        # the goal orientation at each step is that of the waypoint then pursued (the last one once done)
        goal = R_goal[jnp.minimum(res.targets, path.shape[0] - 1)]
        per_step = rot_error_deg(goal, orientations) if rot else zero
        final = rot_error_deg(R_goal[-1], orientations[-1]) if rot else zero[0]
        mean = jnp.sum(used).astype(dtype)
        return (res.completion, 1e3 * res.waypoint_error, 1e3 * jnp.sum(jnp.where(used[:, None], err, 0.0), 0) / mean,
                final, jnp.sum(jnp.where(used, per_step, 0.0)) / mean, res.failed, res.steps_used, positions,
                1e3 * err, per_step), res.dropouts

    (est, est_drop), (true, true_drop) = track(control.fixed(sid.estimate)), track(control.true_inverse(system))
    stacked = [jnp.stack([a, b]) for a, b in zip(est, true)]
    out = Outputs(sid.converged_at, *stacked)
    if p.realism is None:
        return out
    return out._replace(selfid_dropouts=sid_dropouts, selfid_rejected=sid.state.rejected,
                        dropouts=jnp.stack([est_drop, true_drop]))


def build(cfg: TrackingConfig) -> Part:
    """Configs x trials x noise levels; float64 where the system needs it (closed-chain hands)."""
    x64 = needs_x64(cfg.system)
    with precision(x64):
        return _build(cfg)._replace(x64=x64)


def _build(cfg: TrackingConfig) -> Part:
    system = build_system(cfg.system)
    if cfg.task_axes is not None:
        system = system.with_task_axes(cfg.task_axes)
    cfg.path.check_axes(system.axes)
    path = cfg.path.waypoints(system.axes)
    labels = cfg.path.labels()
    meta = grid_table(realistic.add_realism_axis(
        {"letter_id": range(len(labels)), "noise_level": range(len(cfg.pose_noise)), "config_id": range(cfg.n_configs),
         "trial": range(cfg.n_trials)}, cfg.realism, before="config_id"))
    meta.insert(1, "path", np.asarray(labels, dtype=object)[meta["letter_id"]])
    meta.insert(3, "pose_noise", np.asarray(cfg.pose_noise)[meta["noise_level"]])
    meta.insert(4, "rot_noise", np.asarray(cfg.rot_noise)[meta["noise_level"]])
    meta.insert(0, "system", system_name(cfg.system))
    if cfg.realism is not None:
        cfg.realism.add_columns(meta)
    m_a = cfg.magnitude(system)
    add_m_a_columns(meta, m_a)
    longest = int(np.argmax([paths.path_length(w) for w in np.asarray(path)]))
    q0 = np.asarray(control.feasible_starts(system, path[longest], jax.random.key(cfg.seed), cfg.n_configs,
                                            control.ControllerParams(**cfg.controller.traced()),
                                            steps=cfg.controller.steps, oversample=cfg.oversample))
    n = len(meta)
    params = Params(
        letter=meta["letter_id"].to_numpy(np.int32), key=row_keys(cfg.seed, n), q0=q0[meta["config_id"].to_numpy()],
        pose_noise=meta["pose_noise"].to_numpy(float), rot_noise=meta["rot_noise"].to_numpy(float),
        m_a=np.repeat(m_a.value[None], n, axis=0), eps=np.full((n,), cfg.eps), eps_rel=np.full((n,), cfg.eps_rel),
        controller=controller_rows(cfg.controller, n),
    )
    static = Static(system, path, cfg.iters, cfg.controller.steps)
    if any(v > 0 for v in (*cfg.pose_noise, *cfg.rot_noise)):  # the follow loop reads the noisy tracker too
        static = static._replace(level_noise=True, max_latency=0)
    if cfg.realism is not None:
        rows = cfg.realism.rows(meta)
        params = params._replace(realism=rows.realism, settle=rows.settle)
        static = static._replace(max_latency=cfg.realism.max_latency(), max_settle=cfg.realism.max_settle(),
                                 plant=realistic.plant(cfg.realism, cfg.system, system))
    return Part(system_name(cfg.system), static, params, meta)


def tabulate(wide: pd.DataFrame, part: Part, cfg: TrackingConfig) -> pd.DataFrame:
    """One row per (rollout, inverse Jacobian) with scalar metric columns; trajectories stay as list columns."""
    base = ["system", "letter_id", "path", "noise_level", "pose_noise", "rot_noise", "config_id", "trial",
            "converged_at", "m_a", "m_a_vec", "m_a_source"]
    realism = [c for c in (*realism_columns(), "selfid_dropouts", "selfid_rejected") if c in wide.columns]
    base += realism
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
        if "dropouts" in wide.columns:
            df["dropouts"] = np.stack(wide["dropouts"].to_numpy())[:, i]
        for col in ("positions", "error_trace_mm", "rot_trace_deg"):
            df[col] = list(np.stack(wide[col].to_numpy()).reshape(len(wide), 2, -1)[:, i])
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
        for col in ("dropouts", "selfid_dropouts", "selfid_rejected"):
            if col in h.columns:
                level[str(inverse)][col] = float(h[col].mean())
    return level


def summarize(table: pd.DataFrame, cfg: TrackingConfig) -> dict[str, Any]:
    """Mean +- sd per system, tracker-noise level and inverse Jacobian (and per letter / rotation axis).

    With a realism section, per realism level too: the system's key becomes
    ``"<system> (<values>)"`` (the values that differ between levels) and
    its entry states the level's values under ``realism``; the mean tracker
    dropouts per path and during self-ID go into each inverse's entry.
    """
    systems: dict[str, Any] = {}
    labels = realistic.level_labels(table)
    for (system, level, noise), g in table.groupby(["system", realistic.level_of(table), "pose_noise"], sort=False):
        name = str(system) if not labels else f"{system} ({labels[int(level)]})"
        entry = systems.setdefault(name, {"self_id": m_a_summary(g), "pose_noise_mm": {}})
        if labels:
            entry.setdefault("realism", realistic.realism_summary(table, int(level)))
        entry["pose_noise_mm"][f"{1e3 * noise:g}"] = _stats(g)
        if cfg.path.kind in ("letters", "rotation"):  # per letter / per rotation axis, each from its own self-ID
            per = entry.setdefault("letters" if cfg.path.kind == "letters" else "rotations", {})
            for letter, h in g.groupby("letter_id", sort=True):
                per.setdefault(f"{int(letter)}:{h['path'].iloc[0]}", {})[f"{1e3 * noise:g}"] = _stats(h)
    return {
        "path": cfg.path.model_dump(),
        "task_axes": cfg.task_axes,
        "controller": cfg.controller.model_dump(),
        "self_id": {"iterations": cfg.iters, **m_a_summary(table), "eps": cfg.eps, "eps_rel": cfg.eps_rel},
        "systems": systems,
    }


def report(summary: dict) -> str:
    """Table I/II-style lines: per system, noise level and inverse Jacobian."""
    lines = [f"{'system':14s} {'noise mm':>8s} {'inverse':>10s} {'waypoint mm':>14s} {'x mm':>6s} {'y mm':>6s} "
             f"{'z mm':>6s} {'rot end/step deg':>16s} {'completion':>10s} {'converged':>10s}"]
    for system, s in summary["systems"].items():
        for noise, level in s["pose_noise_mm"].items():
            for inverse, m in level.items():
                def f(key, scale=1.0, fmt=".2f", m=m):
                    v = m[key]["mean"]
                    return "-" if v is None else format(scale * v, fmt)
                wp = "-" if m["waypoint_error_mm"]["mean"] is None else \
                    f"{m['waypoint_error_mm']['mean']:.2f} +- {m['waypoint_error_mm']['sd']:.2f}"
                lines.append(f"{system:14s} {noise:>8s} {inverse:>10s} {wp:>14s} {f('error_x_mm'):>6s} "
                             f"{f('error_y_mm'):>6s} {f('error_z_mm'):>6s} "
                             f"{f('rot_final_deg') + ' / ' + f('rot_step_deg'):>16s} "
                             f"{f('completion', 100, '.0f') + '%':>10s} {f('converged_at', fmt='.1f'):>10s}")
    return "\n".join(lines)


plot = figures_plot("tracking")  # experiments/figures/tracking.py, imported (with matplotlib) when called


COLUMNS = {
    "system": "system name [label]",
    "inverse": "inverse Jacobian followed: 'estimated' (self-ID) or 'analytical' (the true one) [label]",
    "letter_id": "index of the path (letter or rotation axis) in the config's path [id]",
    "path": "the path's label (its letter or rotation axis) [label]",
    **NOISE_COLUMNS,
    "config_id": "feasible start configuration index [id]",
    "trial": "self-ID stream index [id]",
    "converged_at": "self-ID iteration meeting the Sec. IV-D test, -1 if never [iteration]",
    **m_a_columns(),
    "completion": "fraction of the path's waypoints reached [-]",
    "waypoint_error_mm": "mean position error when each waypoint was reached [mm]",
    "error_x_mm": "mean |distance to the path| along x over the steps used [mm]",
    "error_y_mm": "mean |distance to the path| along y over the steps used [mm]",
    "error_z_mm": "mean |distance to the path| along z over the steps used [mm]",
    "rot_final_deg": "orientation error to the last waypoint at the end; 0 without rotation [deg]",
    "rot_step_deg": "mean orientation error to the pursued waypoint over the steps used; 0 without rotation [deg]",
    "failed": "non-finite state or divergence from the path [bool]",
    "steps_used": "control steps taken [steps]",
    "positions": "((steps + 1) * 3,) POM positions, row-major (steps + 1, 3) [m]",
    "error_trace_mm": "((steps + 1) * 3,) |distance to the path| along x, y, z at each step, row-major "
                      "(steps + 1, 3) [mm]",
    "rot_trace_deg": "(steps + 1,) orientation error to the pursued waypoint at each step [deg]",
    **realism_columns(),
    "selfid_dropouts": "tracker readings that dropped out during self-ID (realism) [count]",
    "selfid_rejected": "self-ID samples the estimator rejected: dropouts, non-finite or zero (realism) [count]",
    "dropouts": "tracker readings that dropped out while following the path (realism) [count]",
}
"""The results columns (``results.parquet``): one row per rollout and inverse Jacobian."""


EXPERIMENT = Experiment(
    name="tracking",
    config=TrackingConfig,
    build=build,
    compute=compute,
    summarize=summarize,
    columns=COLUMNS,
    tabulate=tabulate,
    plot=plot,
    report=report,
    description="self-ID, then a path (letters, cube, star, rotation) with the estimate and the truth: Tables I-II",
)
