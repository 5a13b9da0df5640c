"""Peg-in-hole (paper Sec. V-F, Table III): a Model O on a UR5e, both self-identified, in sequence.

The system is one composed kinematic chain (:func:`selfid_jax.systems.compose.mount`):
the UR5e's flange, a fixed mount, and the Model O holding the peg, whose POM
is the controlled point. Per layout (start yaw of the arm, grasp waypoint,
hole), trial and tracker-noise level, one compiled function runs:

1. arm self-ID (6-D task, the hand held at its grasp command);
2. the arm carries the peg to the grasp waypoint (6-D, constant orientation);
3. hand self-ID on the held peg (task ``[z, rx, ry]`` in the world frame, the
   arm held);
4. the hand tilts the peg by ``rotation.angle`` about a world axis;
5. the arm lifts, moves over the hole and lowers the peg to the insertion
   pose: the hole's position at the grasp height, the orientation the hand
   left (6-D, the arm's estimate from step 1 reused, as the paper self-IDs
   the arm once).

Once with the self-ID estimates ("estimated") and once with the true inverse
Jacobians ("analytical"). Table III's columns: the arm's waypoint error
[mm] (the paper's "UR5e waypoint errors": the position error at each of its
four waypoints, grasp, lift, over the hole and insertion, when reached;
mean +- sd over them), the final orientation [deg] error of the arm at the
insertion pose, and the hand's final rotation error [deg] within its task's
rotation components; beside them the final distance to the insertion
position [mm], the self-ID convergence iterations of both and whether the
peg ended within the insertion tolerance.

What is simulated: kinematics (the closed-chain Model O equilibrium, the
UR5e chain), actuator limits, tracker noise (on every reading of both self-IDs
and of the three motions). What is not: contact between the
peg and the hole, the grasp itself (the peg is in the hand from the start),
slip of the peg in the grasp, and the arm's dynamics. The paper rotates its
peg to perpendicular; our Model O model's safe tilt range is 15 degrees, so
the hand tilts the peg by ``rotation.angle`` (0.15 rad by default).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
from pydantic import BaseModel, Field, model_validator

from selfid_jax import control
from selfid_jax.control import realism as realism_lib
from selfid_jax.identify import estimator
from selfid_jax.math import geometry
from selfid_jax.runner import Experiment, Part, precision
from selfid_jax.runner.config import STRICT
from selfid_jax.runner.grids import grid_table, row_keys
from selfid_jax.systems import System, compose, hands
from selfid_jax.systems.ur5e import ur5e

from .common import realism as realistic
from .common.lazy_figures import figures_plot
from .common.schema import (
    NOISE_COLUMNS,
    ControllerConfig,
    HostOrDevice,
    SelfIdConfig,
    StudyConfig,
    TrackerNoiseConfig,
    add_m_a_columns,
    controller_rows,
    m_a_columns,
    m_a_summary,
    realism_columns,
)

INVERSES = ("estimated", "analytical")
HAND_AXES = ("z", "rx", "ry")
Vec3 = Annotated[list[Annotated[float, Field(ge=-1.0, le=1.0)]], Field(min_length=3, max_length=3)]


class Layout(BaseModel):
    """One start / grasp / hole arrangement (world frame, metres and radians)."""

    model_config = STRICT

    yaw: float = Field(0.0, ge=-1.0, le=1.0, description="added to the arm's base joint at the start [rad]")
    grasp: Vec3 = Field(description="grasp waypoint, offset from the POM's start position [m]")
    hole: Annotated[list[Annotated[float, Field(ge=-0.5, le=0.5)]], Field(min_length=2, max_length=2)] = Field(
        description="hole (x, y), offset from the grasp waypoint, at the grasp height [m]")


class PartSettings(SelfIdConfig):
    """Self-ID and control settings of one part (arm or hand); ``m_a`` defaults to the part's own (UR5e, Model O)."""

    iters: int = Field(ge=2, le=10**4, description="self-ID iterations")
    eps: float = Field(0.0, ge=0, le=1e6)
    eps_rel: float = Field(0.0, ge=0, le=10)
    controller: ControllerConfig

    @model_validator(mode="after")
    def _thresholds(self):
        estimator.check_thresholds(self.eps, self.eps_rel)
        return self


class Rotation(BaseModel):
    model_config = STRICT

    angle: float = Field(0.15, gt=-0.26, lt=0.26, description="hand tilt of the peg [rad] (the model's safe range "
                         "is 15 deg)")
    about: Literal["x", "y"] = "x"
    steps: int = Field(10, ge=1, le=1000, description="waypoints along the rotation")


class PegConfig(StudyConfig, TrackerNoiseConfig):
    """Peg-in-hole with a Model O on a UR5e, both self-identified (Table III)."""

    experiment: Literal["peg_in_hole"] = "peg_in_hole"
    arm_home: Annotated[list[Annotated[float, Field(ge=-6.3, le=6.3)]], Field(min_length=6, max_length=6)] = \
        [0.0, -1.3, 1.8, -2.07, -1.57, 0.0]  # flange pointing down [rad]
    mount_offset: Vec3 = [0.0, 0.0, 0.02]  # hand base in the flange frame [m]
    layouts: Annotated[list[Layout], Field(min_length=1)]
    n_trials: int = Field(1, ge=1, le=10**4)
    lift: float = Field(0.05, gt=0, le=0.5, description="height above the hole before lowering [m]")
    rotation: Rotation = Rotation()
    arm: PartSettings
    hand: PartSettings
    insert_tol: float = Field(0.002, gt=0, le=0.1, description="insertion accepted within this position error [m]")
    insert_rot_tol_deg: float = Field(1.0, gt=0, le=90, description="... and this orientation error [deg]")

    @model_validator(mode="after")
    def _consistent(self):
        if self.realism is not None and self.realism.plant != "servo":
            raise ValueError("realism.plant: peg_in_hole runs the kinematic servo only (plant 'servo'); the "
                             "dynamic plant serves tracking and valid_region, whose system is one arm")
        if not self.arm.controller.tol < self.insert_tol:
            raise ValueError(f"arm.controller.tol ({self.arm.controller.tol}) must be below insert_tol "
                             f"({self.insert_tol})")
        return self


class Static(NamedTuple):
    system: System  # the mounted UR5e + Model O
    rotation: jax.Array  # (S, 3) hand path: rotation-vector offsets in the hand task [z, rx, ry]
    arm_iters: int
    hand_iters: int
    arm_steps: int
    hand_steps: int
    insert_tol_mm: float
    insert_rot_tol_deg: float
    # the motions' tracker history length - 1 [steps] (with realism; without, 0 if level_noise); None: the ideal
    # loop, which reads exact poses
    max_latency: int | None = None
    max_settle: int = 1  # with realism: the longest self-ID settle [steps]
    # some level has pose_noise or rot_noise > 0: the motions read it too (False: the program of a config without
    # noise levels is the one it always was)
    level_noise: bool = False


class Params(NamedTuple):
    key: HostOrDevice  # (2,) uint32
    q_arm: HostOrDevice  # (6,) start configuration [rad]
    q_hand: HostOrDevice  # (3,) grasp command [m]
    grasp: HostOrDevice  # (3,) grasp waypoint offset [m]
    hole: HostOrDevice  # (2,) hole offset from the grasp waypoint [m]
    lift: HostOrDevice  # () [m]
    pose_noise: HostOrDevice  # () [m]
    rot_noise: HostOrDevice  # () [rad]
    arm_m_a: HostOrDevice  # (6,) arm self-ID magnitude per joint [rad]
    arm_eps: HostOrDevice
    arm_eps_rel: HostOrDevice
    hand_m_a: HostOrDevice  # (3,) hand self-ID magnitude per tendon [m]
    hand_eps: HostOrDevice
    hand_eps_rel: HostOrDevice
    arm_ctrl: control.ControllerParams
    hand_ctrl: control.ControllerParams
    realism: realism_lib.Realism | None = None  # () each, with a realism section
    settle: HostOrDevice | None = None  # () int32 self-ID settle steps, with a realism section


class Outputs(NamedTuple):
    """Per row; axis 0 of the (2,) fields is (estimated, analytical)."""

    arm_converged_at: jax.Array  # () int32, -1 if never
    hand_converged_at: jax.Array  # (2,) int32 (the hand's self-ID runs where each pipeline's arm left it)
    grasp_completion: jax.Array  # (2,)
    hand_completion: jax.Array  # (2,)
    insert_completion: jax.Array  # (2,)
    hand_rot_deg: jax.Array  # (2,) hand's final rotation error within [rx, ry] [deg]
    arm_pos_mm: jax.Array  # (2,) final distance to the insertion position [mm]
    arm_wp_mm: jax.Array  # (2, 4) arm's position error at each of its waypoints (grasp, lift, over, insert) [mm]
    arm_rot_deg: jax.Array  # (2,) final orientation error to the insertion orientation [deg]
    inserted: jax.Array  # (2,) bool: within insert_tol and insert_rot_tol_deg
    failed: jax.Array  # (2,) bool: a phase failed (non-finite pose, divergence)
    positions: jax.Array  # (2, 3, 3) POM position at the grasp waypoint, after the tilt, at the end [m]
    arm_selfid_dropouts: jax.Array | None = None  # () int32 tracker dropouts during the arm's self-ID, with realism
    hand_selfid_dropouts: jax.Array | None = None  # (2,) int32 ... during the hand's, with realism
    dropouts: jax.Array | None = None  # (2,) int32 tracker dropouts over the three motion phases, with realism


def compute(static: Static, p: Params) -> Outputs:
    """The five phases from ``p.q_arm``, with the self-ID estimates and with the true inverse Jacobians.

    Both self-IDs and the three motions read one tracker
    (:func:`selfid_jax.control.realism.with_tracker_noise`): the noise level's
    ``p.pose_noise`` [m] and ``p.rot_noise`` [rad] on every reading, and under
    ``p.realism`` where given its latency, dropouts and servo too
    (:mod:`selfid_jax.control.realism`). Each motion draws from its own
    ``fold_in`` of its lane's key, apart from the self-IDs' draws.
    """
    system = static.system
    k_arm, k_est, k_true = jax.random.split(jax.random.wrap_key_data(jnp.asarray(p.key)), 3)
    arm0 = compose.arm_part(system, p.q_hand)
    real: dict[str, Any] = dict(realism=p.realism, settle=p.settle, max_latency=static.max_latency or 0,
                                max_settle=static.max_settle)
    sid_arm, arm_drop = realistic.self_identify(arm0, k_arm, p.q_arm, iters=static.arm_iters, eps=p.arm_eps,
                                                eps_rel=p.arm_eps_rel, m_a=p.arm_m_a, pose_noise=p.pose_noise,
                                                rot_noise=p.rot_noise, **real)
    zeros3 = jnp.zeros((3,), p.grasp.dtype)

    sensed = p.realism  # what the tracker adds to the poses the motions read
    if static.level_noise:
        sensed = realism_lib.with_tracker_noise(p.realism, p.pose_noise, p.rot_noise)

    def follow(part, src, path, q, ctrl, steps, key):
        return control.follow(part, src, path, q, ctrl, steps=steps, realism=sensed, key=key,
                              max_latency=static.max_latency)

    def pipeline(use_true, key):
        """One of the two lanes (``use_true`` False: the self-ID estimates; True: the true inverse Jacobians),
        vmapped as one program, so the hand's pose map (a Newton solve) is compiled once for both."""
        k_grasp, k_tilt, k_insert = (jax.random.fold_in(key, i) for i in (1, 2, 3))
        grasp = follow(arm0, control.estimate_or_true(sid_arm.estimate, use_true),
                       jnp.concatenate([p.grasp, zeros3])[None], sid_arm.env, p.arm_ctrl, static.arm_steps, k_grasp)
        grasp_pose = grasp.final_pose
        hand = compose.hand_part(system, grasp.final_q, task_axes=HAND_AXES)
        sid_hand, hand_drop = realistic.self_identify(hand, key, p.q_hand, iters=static.hand_iters, eps=p.hand_eps,
                                                      eps_rel=p.hand_eps_rel, m_a=p.hand_m_a, pose_noise=p.pose_noise,
                                                      rot_noise=p.rot_noise, **real)
        tilt = follow(hand, control.estimate_or_true(sid_hand.estimate, use_true), static.rotation, sid_hand.env,
                      p.hand_ctrl, static.hand_steps, k_tilt)
        R_goal = control.waypoint_poses(static.rotation, tilt.start_pose, hand.axes)[1][-1]
        R_now = tilt.final_pose[1]
        w = geometry.so3_log(R_goal @ R_now.T)[:2]  # the hand task's rotation components (rx, ry)
        hand_rot = jnp.degrees(jnp.sqrt(jnp.sum(w * w)))
        arm1 = compose.arm_part(system, tilt.final_q)
        p1, R1 = arm1.pose(grasp.final_q)
        target = grasp_pose[0] + jnp.concatenate([p.hole, zeros3[:1]])  # the hole at the grasp height
        up = jnp.stack([zeros3.at[2].set(p.lift), target - p1 + zeros3.at[2].set(p.lift), target - p1])
        insert_path = jnp.concatenate([up, jnp.zeros_like(up)], axis=1)
        insert = follow(arm1, control.estimate_or_true(sid_arm.estimate, use_true), insert_path, grasp.final_q,
                        p.arm_ctrl, static.arm_steps, k_insert)
        p_end, R_end = insert.final_pose
        pos_mm = 1e3 * jnp.sqrt(jnp.sum((p_end - target) ** 2))
        w_end = geometry.so3_log(R1 @ R_end.T)
        rot_deg = jnp.degrees(jnp.sqrt(jnp.sum(w_end * w_end)))
        failed = grasp.failed | tilt.failed | insert.failed
        drops = None if p.realism is None else (hand_drop, grasp.dropouts + tilt.dropouts + insert.dropouts)
        wp_mm = 1e3 * jnp.concatenate([grasp.waypoint_errors, insert.waypoint_errors])
        return (sid_hand.converged_at, grasp.completion, tilt.completion, insert.completion, hand_rot, pos_mm, rot_deg,
                wp_mm, failed, jnp.stack([grasp_pose[0], p1, p_end])), drops

    # INVERSES' order: the estimates, then the truth
    (hand_conv, g, h, i, hr, pm, rd, wp, failed, pos), drops = jax.vmap(pipeline)(jnp.array([False, True]),
                                                                                 jnp.stack([k_est, k_true]))
    safe = lambda x: jnp.where(failed.reshape(failed.shape + (1,) * (x.ndim - 1)), 0.0, x)
    out = Outputs(sid_arm.converged_at, hand_conv, g, h, i, safe(hr), safe(pm), safe(wp), safe(rd),
                  ~failed & (i >= 1.0) & (pm <= static.insert_tol_mm) & (rd <= static.insert_rot_tol_deg), failed, pos)
    if p.realism is None:
        return out
    return out._replace(arm_selfid_dropouts=arm_drop, hand_selfid_dropouts=drops[0], dropouts=drops[1])


def build(cfg: PegConfig) -> Part:
    """Layouts x trials x noise levels; float64 (the closed-chain hand)."""
    with precision(True):
        return _build(cfg)._replace(x64=True)


def _build(cfg: PegConfig) -> Part:
    arm, hand = ur5e(task_dim=6), hands.model_o(task_dim=6)
    system = compose.mount(arm, hand, offset=cfg.mount_offset, name="ur5e+model_o")
    unit = {"x": 0, "y": 1}[cfg.rotation.about]
    fractions = np.arange(1, cfg.rotation.steps + 1) / cfg.rotation.steps
    rotation = np.zeros((cfg.rotation.steps, 3))  # hand task [z, rx, ry]
    rotation[:, 1 + unit] = cfg.rotation.angle * fractions
    meta = grid_table(realistic.add_realism_axis({"layout": range(len(cfg.layouts)),
                                                  "noise_level": range(len(cfg.pose_noise)),
                                                  "trial": range(cfg.n_trials)}, cfg.realism, before="trial"))
    meta.insert(2, "pose_noise", np.asarray(cfg.pose_noise)[meta["noise_level"]])
    meta.insert(3, "rot_noise", np.asarray(cfg.rot_noise)[meta["noise_level"]])
    if cfg.realism is not None:
        cfg.realism.add_columns(meta)
    n = len(meta)
    lay = [cfg.layouts[i] for i in meta["layout"]]
    q_arm = np.asarray([np.asarray(cfg.arm_home) + np.array([lo.yaw, 0, 0, 0, 0, 0]) for lo in lay])
    q_hand = np.asarray((hand.sample_low + hand.sample_high) / 2)  # the grasp command
    for i, lo in enumerate(cfg.layouts):  # eager, before any compute: every start must be inside the limits
        q = np.asarray(cfg.arm_home) + np.array([lo.yaw, 0, 0, 0, 0, 0])
        if np.any(q < np.asarray(arm.q_low)) or np.any(q > np.asarray(arm.q_high)):
            raise ValueError(f"layouts[{i}]: start configuration {q} is outside the UR5e's joint limits")
    full = lambda v: np.full((n,), v)
    arm_m_a, hand_m_a = cfg.arm.magnitude(arm, "arm.m_a"), cfg.hand.magnitude(hand, "hand.m_a")
    add_m_a_columns(meta, arm_m_a, "arm_")
    add_m_a_columns(meta, hand_m_a, "hand_")
    params = Params(
        key=row_keys(cfg.seed, n), q_arm=q_arm, q_hand=np.repeat(q_hand[None], n, axis=0),
        grasp=np.asarray([lo.grasp for lo in lay]), hole=np.asarray([lo.hole for lo in lay]), lift=full(cfg.lift),
        pose_noise=meta["pose_noise"].to_numpy(float), rot_noise=meta["rot_noise"].to_numpy(float),
        arm_m_a=np.repeat(arm_m_a.value[None], n, axis=0), arm_eps=full(cfg.arm.eps), arm_eps_rel=full(cfg.arm.eps_rel),
        hand_m_a=np.repeat(hand_m_a.value[None], n, axis=0), hand_eps=full(cfg.hand.eps),
        hand_eps_rel=full(cfg.hand.eps_rel),
        arm_ctrl=controller_rows(cfg.arm.controller, n), hand_ctrl=controller_rows(cfg.hand.controller, n),
    )
    static = Static(system, jnp.asarray(rotation), cfg.arm.iters, cfg.hand.iters, cfg.arm.controller.steps,
                    cfg.hand.controller.steps, 1e3 * cfg.insert_tol, cfg.insert_rot_tol_deg)
    if any(v > 0 for v in (*cfg.pose_noise, *cfg.rot_noise)):  # the motions read the noisy tracker too
        static = static._replace(level_noise=True, max_latency=0)
    if cfg.realism is not None:
        rows = cfg.realism.rows(meta)
        params = params._replace(realism=rows.realism, settle=rows.settle)
        static = static._replace(max_latency=cfg.realism.max_latency(), max_settle=cfg.realism.max_settle())
    meta.insert(0, "system", system.name)
    return Part(system.name, static, params, meta)


def tabulate(wide: pd.DataFrame, part: Part, cfg: PegConfig) -> pd.DataFrame:
    """One row per (layout, trial, noise level, inverse Jacobian)."""
    base = ["system", "layout", "noise_level", "pose_noise", "rot_noise", "trial", "arm_converged_at", "arm_m_a",
            "arm_m_a_vec", "arm_m_a_source", "hand_m_a", "hand_m_a_vec", "hand_m_a_source"]
    base += [c for c in (*realism_columns(), "arm_selfid_dropouts") if c in wide.columns]
    per_inverse = [c for c in ("hand_selfid_dropouts", "dropouts") if c in wide.columns]
    frames = []
    for i, inverse in enumerate(INVERSES):
        df = wide[base].copy()
        df.insert(1, "inverse", inverse)
        for col in ("hand_converged_at", "grasp_completion", "hand_completion", "insert_completion", "hand_rot_deg",
                    "arm_pos_mm", "arm_rot_deg", "inserted", "failed", *per_inverse):
            df[col] = np.stack(wide[col].to_numpy())[:, i]
        df["inserted"] = df["inserted"].astype(bool)
        df["failed"] = df["failed"].astype(bool)
        df["positions"] = list(np.stack(wide["positions"].to_numpy()).reshape(len(wide), 2, -1)[:, i])
        df["arm_wp_mm"] = list(np.stack(wide["arm_wp_mm"].to_numpy()).reshape(len(wide), 2, -1)[:, i])
        frames.append(df)
    return pd.concat(frames, ignore_index=True)


TABLE = ("arm_pos_mm", "arm_rot_deg", "hand_rot_deg")


def _wp(rows: pd.DataFrame) -> dict[str, float | None]:
    """Mean +- sd of the arm's waypoint errors [mm] pooled over the rows' four waypoints (Table III's metric)."""
    return _ms(np.concatenate([np.asarray(v, float) for v in rows["arm_wp_mm"]]) if len(rows) else [])


def _ms(x) -> dict[str, float | None]:
    x = np.asarray(x, float)
    return {"mean": float(x.mean()) if len(x) else None, "sd": float(x.std()) if len(x) else None}


def summarize(table: pd.DataFrame, cfg: PegConfig) -> dict[str, Any]:
    """Table III per layout, noise level and inverse Jacobian (mean +- sd over trials; failed rows left out).

    With a realism section, per realism level too: the noise level's key
    becomes ``"<noise mm> (<values>)"`` (the values that differ between
    levels), each level's values under ``realism_levels``, and the mean
    tracker dropouts go into each ``all`` entry.
    """
    out: dict[str, Any] = {}
    labels = realistic.level_labels(table)
    levels: dict[str, Any] = {}
    level_of = realistic.level_of(table)
    for (noise, lvl, inverse), g in table.groupby(["pose_noise", level_of, "inverse"], sort=False):
        key = f"{1e3 * noise:g}" + (f" ({labels[int(lvl)]})" if labels else "")
        if labels:
            levels[key] = realistic.realism_summary(table, int(lvl))
        level = out.setdefault(key, {}).setdefault(str(inverse), {"layouts": {}})
        for layout, h in g.groupby("layout", sort=True):
            ok = h[~h["failed"]]
            level["layouts"][str(int(layout))] = {m: _ms(ok[m]) for m in TABLE} | {"arm_wp_mm": _wp(ok),
                "inserted": float(h["inserted"].mean()), "failed_fraction": float(h["failed"].mean())}
        ok = g[~g["failed"]]
        conv_a, conv_h = g["arm_converged_at"].to_numpy(), g["hand_converged_at"].to_numpy()
        level["all"] = {m: _ms(ok[m]) for m in TABLE} | {"arm_wp_mm": _wp(ok),
            "inserted": float(g["inserted"].mean()), "failed_fraction": float(g["failed"].mean()),
            "arm_converged_at": _ms(conv_a[conv_a > 0]), "hand_converged_at": _ms(conv_h[conv_h > 0])}
        for col in ("arm_selfid_dropouts", "hand_selfid_dropouts", "dropouts"):
            if col in g.columns:
                level["all"][col] = float(g[col].mean())
    extra = {"realism_levels": levels} if labels else {}
    return {
        "layouts": [lo.model_dump() for lo in cfg.layouts],
        "protocol": {"arm": cfg.arm.model_dump() | m_a_summary(table, "arm_"),
                     "hand": cfg.hand.model_dump() | m_a_summary(table, "hand_"), "rotation": cfg.rotation.model_dump(),
                     "lift": cfg.lift, "insert_tol": cfg.insert_tol, "insert_rot_tol_deg": cfg.insert_rot_tol_deg,
                     "mount_offset": cfg.mount_offset},
        "pose_noise_mm": out,
        **extra,
    }


def report(summary: dict) -> str:
    """Table III: per noise level, inverse Jacobian and layout."""
    def f(m):
        return "-" if m["mean"] is None else f"{m['mean']:.2f} +- {m['sd']:.2f}"

    lines = [f"{'noise mm':>8s} {'inverse':>10s} {'layout':>6s} {'UR5e wp mm':>14s} {'UR5e pos mm':>14s} "
             f"{'UR5e rot deg':>14s} {'Model O rot deg':>15s} {'inserted':>8s}"]
    for noise, levels in summary["pose_noise_mm"].items():
        for inverse, level in levels.items():
            for name, m in list(level["layouts"].items()) + [("all", level["all"])]:
                lines.append(f"{noise:>8s} {inverse:>10s} {name:>6s} {f(m['arm_wp_mm']):>14s} "
                             f"{f(m['arm_pos_mm']):>14s} {f(m['arm_rot_deg']):>14s} {f(m['hand_rot_deg']):>15s} "
                             f"{100 * m['inserted']:>7.0f}%")
            a = level["all"]
            lines.append(f"{'':>8s} {'':>10s} self-ID iterations: arm {f(a['arm_converged_at'])}, "
                         f"hand {f(a['hand_converged_at'])}")
    return "\n".join(lines)


plot = figures_plot("peg_in_hole")  # experiments/figures/peg_in_hole.py, imported (with matplotlib) when called


COLUMNS = {
    "system": "the composed system's name (ur5e+model_o) [label]",
    "inverse": "inverse Jacobians used: 'estimated' (self-ID) or 'analytical' (the true ones) [label]",
    "layout": "layout index (arm yaw, grasp waypoint, hole) in the config's layouts [id]",
    **NOISE_COLUMNS,
    "trial": "trial index (self-ID streams) [id]",
    "arm_converged_at": "arm self-ID iteration meeting Sec. IV-D, -1 if never [iteration]",
    **m_a_columns("arm_", " of the arm"),
    **m_a_columns("hand_", " of the hand"),
    "hand_converged_at": "hand self-ID iteration meeting Sec. IV-D (run where this pipeline's arm left it), -1 if "
                         "never [iteration]",
    "grasp_completion": "fraction of the arm's move to the grasp waypoint completed [-]",
    "hand_completion": "fraction of the hand's tilt waypoints reached [-]",
    "insert_completion": "fraction of the arm's lift, move and lower waypoints reached [-]",
    "hand_rot_deg": "hand's final rotation error within its task's [rx, ry]; 0 where failed [deg]",
    "arm_pos_mm": "final distance to the insertion position; 0 where failed [mm]",
    "arm_wp_mm": "(4,) arm's position error at its grasp, lift, over-the-hole and insertion waypoints when each was "
                 "reached (at the end if not); Table III's metric, pooled mean +- sd in the summary; 0 where failed "
                 "[mm]",
    "arm_rot_deg": "final orientation error to the insertion orientation; 0 where failed [deg]",
    "inserted": "insertion completed within insert_tol and insert_rot_tol_deg, no phase failed [bool]",
    "failed": "a phase failed (non-finite pose, divergence) [bool]",
    "positions": "(9,) POM position at the grasp waypoint, after the tilt and at the end, row-major (3, 3) [m]",
    **realism_columns(),
    "arm_selfid_dropouts": "tracker readings that dropped out during the arm's self-ID (realism) [count]",
    "hand_selfid_dropouts": "tracker readings that dropped out during the hand's self-ID (realism) [count]",
    "dropouts": "tracker readings that dropped out during the grasp, tilt and insertion moves (realism) [count]",
}
"""The results columns (``results.parquet``): one row per layout, noise level, trial and inverse Jacobian."""


EXPERIMENT = Experiment(
    name="peg_in_hole",
    config=PegConfig,
    build=build,
    compute=compute,
    summarize=summarize,
    columns=COLUMNS,
    tabulate=tabulate,
    plot=plot,
    report=report,
    description="a Model O on a UR5e, both self-identified: grasp waypoint, tilt, insertion (Table III)",
)
