"""E-KM (seed 002) against model-free self-ID on a 2-link star: the probe of issue 16.

How much does a wrong kinematic model plus a Sparse Online GP buy over
model-free self-ID, and when? For each start configuration and trial one
self-ID stream (``selfid.run``: uniform actuations of magnitude ``m_a``) is
fed to every method; each method's model after the first ``k`` samples
follows a star (``control.follow`` for the inverse-Jacobian estimates, the
Eq. 10-11 QP controller of :mod:`selfid_jax.control.qp` for the E-KM):

* ``true``: the true inverse Jacobian at every step;
* ``ours``: the paper's estimate (signed x magnitude, refined; Eq. 6-14),
  fixed, from the start configuration;
* ``nominal``: the wrong model alone (E-KM with an empty GP);
* ``ekm fixed`` / ``ekm online`` for each formulation (``incremental``: the
  seed's ``[q, da] -> ds - J_m da`` with mirrored samples; ``incremental,
  plain``: without the mirror, as the seed; ``absolute``: FK residual on
  ``q``): GP learned from the ``k`` self-ID samples only, or also from every
  control step.

Nominal errors (true arm: links 1 m / 1 m): ``hard`` = links 1.5 / 0.6 m,
joint offsets +0.6 / -0.6 rad (the issue's probe); ``easy`` = links 1.2 / 0.8 m
(+-20 %), offsets +0.1 / -0.1 rad. Protocol (the 2-link valid-region one):
0.2 m star, 10 mm steps, 2 mm tolerance, 435 steps, ``m_a = 0.05`` rad.

    python scripts/ekm_study.py [--configs 10] [--trials 2] [--case hard|easy|both] [--figures DIR]

With ``--figures DIR`` each case's two tables are also drawn
(:func:`study_figure`): ``DIR/ekm_study_<case>.png|pdf``, completion and path
error per method.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from selfid_jax import baselines, control
from selfid_jax.baselines import ekm
from selfid_jax.control import paths
from selfid_jax.identify import algorithm as selfid
from selfid_jax.systems.two_link import two_link

CASES = {
    "hard": dict(scale=(1.5, 0.6), offset=(0.6, -0.6)),
    "easy": dict(scale=(1.2, 0.8), offset=(0.1, -0.1)),
}
ITERATIONS = (1, 2, 5, 10, 20)
CONTROLLER = dict(max_step=0.01, tol=0.002)
STEPS = 435
CAPACITY = 64  # GP basis size of every E-KM (>= 2 x 20 mirrored self-ID samples: no pruning during self-ID)


def _rollouts(arm, nominal, path, ctrl, iterations, capacity, steps):
    """``(key, q0) -> {method: ((C,) completion, (C,) mean path error [m])}`` for one stream, one traced function."""
    checkpoints = jnp.asarray(iterations) - 1
    models = {"incremental": ekm.model(nominal), "absolute": ekm.model(nominal, formulation="absolute"),
              "incremental, plain": ekm.model(nominal, symmetric=False)}

    def one(key, q0):
        sid = selfid.run(arm, key, q0, iters=max(iterations), eps=1e-9, stop_at_convergence=False)
        truth = arm.true_inverse_jacobian(q0)
        out = {}
        true = control.follow(arm, control.true_inverse(arm), path, q0, ctrl, steps=steps)
        out["true"] = _metrics(true, checkpoints.shape)
        est = baselines.run_stream(baselines.ours(), None, sid.dtheta, sid.V, truth)[checkpoints]
        out["ours"] = _metrics(jax.vmap(
            lambda J: control.follow(arm, control.fixed(J), path, q0, ctrl, steps=steps))(est))
        empty = ekm.init(models["incremental"], q0, capacity=capacity)
        nom, _ = ekm.follow(models["incremental"], empty, arm, path, ctrl, steps=steps)
        out["nominal"] = _metrics(nom, checkpoints.shape)
        for f, mdl in models.items():
            def body(s, x, mdl=mdl):
                s = ekm.update(mdl, s, *x)
                return s, s

            _, states = jax.lax.scan(body, ekm.init(mdl, q0, capacity=capacity), (sid.dtheta, sid.V))
            at = jax.tree.map(lambda a: a[checkpoints], states)
            for mode in ekm.MODES:
                res = jax.vmap(lambda st, mdl=mdl, mode=mode:
                               ekm.follow(mdl, st, arm, path, ctrl, mode=mode, steps=steps)[0])(at)
                out[f"ekm {mode} ({f})"] = _metrics(res)
        return out

    return one


def _metrics(res, shape=None):
    pair = (res.completion, res.mean_error)
    return pair if shape is None else tuple(jnp.broadcast_to(x, shape) for x in pair)


def study(case: str = "hard", *, n_configs: int = 10, n_trials: int = 2, iterations=ITERATIONS, seed: int = 0,
          capacity: int = CAPACITY, steps: int = STEPS) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Mean completion and mean path error [mm] per method and self-ID iteration count on the 2-link star.

    Two ``(method x iterations)`` tables.

    Runs in float64 (the SOGP needs it). ``case``: a key of :data:`CASES`.
    """
    with jax.enable_x64(True):
        arm = two_link()
        nominal = ekm.nominal_system(arm, **CASES[case])
        path = paths.star(size=0.2, dim=2)
        ctrl = control.ControllerParams(**CONTROLLER)
        starts = control.feasible_starts(arm, path, jax.random.key(seed), n_configs, ctrl, steps=steps)
        q0 = jnp.repeat(starts, n_trials, axis=0)
        keys = jax.random.split(jax.random.key(seed + 1), q0.shape[0])
        fn = jax.jit(jax.vmap(_rollouts(arm, nominal, path, ctrl, tuple(iterations), capacity, steps)))
        out = jax.device_get(fn(keys, q0))
    tables = []
    for i, scale in ((0, 1.0), (1, 1e3)):
        t = pd.DataFrame({m: scale * np.asarray(v[i]).mean(axis=0) for m, v in out.items()}, index=list(iterations)).T
        t.index.name, t.columns.name = "method", "self-ID iterations"
        tables.append(t.sort_index())
    return tuple(tables)


def study_figure(completion: pd.DataFrame, error_mm: pd.DataFrame, out_dir: str | Path, name: str,
                 title: str = "") -> list[Path]:
    """Draw the two tables of :func:`study`: mean completion [%] and mean path error [mm] vs self-ID iterations.

    Args:
      completion: ``(method x iterations)`` mean completion in [0, 1].
      error_mm: ``(method x iterations)`` mean distance to the path [mm], same index and columns.
      out_dir: folder of ``<name>.png`` and ``<name>.pdf``.
      name: file stem.
      title: the protocol, as the suptitle.

    Returns:
      the PNG and PDF paths. Each method has its own (colour, linestyle, marker)
      (:func:`selfid_jax.experiments.common.figures.method_styles`); the error
      axis is logarithmic when the errors span more than 2 decades.
    """
    from matplotlib.figure import Figure
    from selfid_jax.experiments.common.figures import method_styles, save_figure

    if list(completion.index) != list(error_mm.index) or list(completion.columns) != list(error_mm.columns):
        raise ValueError("completion and error_mm must have the same methods (index) and iteration counts (columns)")
    methods = [str(m) for m in completion.index]
    styles = method_styles(methods)
    fig = Figure(figsize=(12.0, 4.4), layout="constrained")
    ax_c, ax_e = fig.subplots(1, 2)
    x = np.asarray(completion.columns, float)
    for m, (_, c), (_, e) in zip(methods, completion.iterrows(), error_mm.iterrows()):
        color, ls, marker = styles[m]
        ax_c.plot(x, 100.0 * c.to_numpy(float), color=color, ls=ls, marker=marker, ms=4, label=m,
                  gid=f"completion:{m}")
        ax_e.plot(x, e.to_numpy(float), color=color, ls=ls, marker=marker, ms=4, gid=f"path_error:{m}")
    vals = error_mm.to_numpy(float)
    vals = vals[np.isfinite(vals)]
    if vals.size and (vals > 0).all() and vals.max() / vals.min() > 100:
        ax_e.set_yscale("log")
    for ax, label in ((ax_c, "mean path completion [%]"), (ax_e, "mean distance to the path [mm]")):
        ax.set_xscale("log")
        ax.set_xlabel("self-ID iterations")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    ax_c.set_ylim(-2, 102)
    fig.legend(*ax_c.get_legend_handles_labels(), fontsize=7, loc="outside right center")
    if title:
        fig.suptitle(title, fontsize=9)
    return save_figure(fig, out_dir, name)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", type=int, default=10)
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--case", choices=["hard", "easy", "both"], default="both")
    ap.add_argument("--figures", type=Path, default=None, help="also draw each case into this folder")
    args = ap.parse_args(argv)
    for case in (["hard", "easy"] if args.case == "both" else [args.case]):
        t0 = time.perf_counter()
        completion, error = study(case, n_configs=args.configs, n_trials=args.trials)
        print(f"\n{case} nominal {CASES[case]}: {args.configs} configurations x {args.trials} trials "
              f"({time.perf_counter() - t0:.0f} s)\nmean completion:")
        print(completion.to_string(float_format=lambda x: f"{x:.2f}"))
        print("mean distance to the path [mm]:")
        print(error.to_string(float_format=lambda x: f"{x:.2f}"))
        if args.figures is not None:
            args.figures.mkdir(parents=True, exist_ok=True)
            title = (f"2-link star 0.2 m, {case} nominal {CASES[case]}; {args.configs} configurations x "
                     f"{args.trials} trials")
            for path in study_figure(completion, error, args.figures, f"ekm_study_{case}", title):
                print(f"figure: {path}")


if __name__ == "__main__":
    main()
