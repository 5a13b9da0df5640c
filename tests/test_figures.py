"""What the figures show, read back from their matplotlib artists (Agg canvas, no simulation).

Each figure is drawn from a small hand-made results table with the real
column names and the summary the experiment's own ``summarize`` writes from
it (with the shipped configs), and checked against independent computations:
no two titles, axis labels or legends overlap, threshold lines sit at the
thresholds, every ablation method has its own style, the valid-region
suptitle names only controllers the systems ran, letters do not overlap,
untracked axes are not drawn as zeros, the commanded cube is drawn, and the
path-error panel holds the results' error column.
"""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgba
from selfid_jax.experiments import ablation, demo, tracking, valid_region
from selfid_jax.experiments.common import figures
from selfid_jax.experiments.common.specs import system_name
from selfid_jax.experiments.figures import demo as demo_figures
from selfid_jax.experiments.figures import tracking as tracking_figures

from selfid_jax.control import paths
from selfid_jax.runner import registry

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def shipped(name: str) -> Path:
    """A shipped config by file name, in whichever subfolder of configs/ holds it."""
    (path,) = CONFIGS.rglob(name)
    return path


def _capture(monkeypatch, module):
    """Replace ``module.save_figure`` by one that keeps the figures (by name) instead of writing them."""
    drawn: dict = {}

    def keep(fig, out_dir, name, **_):
        drawn[name] = fig
        return [Path(out_dir) / f"{name}.png"]

    monkeypatch.setattr(module, "save_figure", keep)
    return drawn


def _text_boxes(fig):
    """``[(what, Bbox)]`` of every non-empty title, axis label, suptitle and legend, after a draw (pixels)."""
    FigureCanvasAgg(fig)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    out = []
    for i, ax in enumerate(fig.axes):
        if not ax.get_visible():
            continue
        texts = [("title", ax.title), ("left title", ax._left_title), ("right title", ax._right_title),
                 ("xlabel", ax.xaxis.label), ("ylabel", ax.yaxis.label)]
        if hasattr(ax, "zaxis"):
            texts.append(("zlabel", ax.zaxis.label))
        for what, t in texts:
            if t.get_visible() and t.get_text():
                out.append((f"axes {i} {what} {t.get_text()!r}", t.get_window_extent(r)))
        if ax.get_legend() is not None:
            out.append((f"axes {i} legend", ax.get_legend().get_window_extent(r)))
    for what in ("_suptitle", "_supxlabel", "_supylabel"):
        t = getattr(fig, what, None)
        if t is not None and t.get_text():
            out.append((what, t.get_window_extent(r)))
    out += [(f"figure legend {i}", leg.get_window_extent(r)) for i, leg in enumerate(fig.legends)]
    return out


def _assert_no_overlap(fig):
    boxes = _text_boxes(fig)
    assert len(boxes) > 3
    bad = [(a, b) for (a, ba), (b, bb) in itertools.combinations(boxes, 2) if ba.overlaps(bb)]
    assert not bad, f"overlapping texts: {bad}"


def _lines(ax, prefix):
    return {ln.get_gid().split(":", 1)[1]: ln for ln in ax.get_lines() if str(ln.get_gid()).startswith(prefix)}


# --------------------------------------------------------------------------- demo

def _demo_table(rng):
    """Two runs like the default demo: the UR5e (6 x 3 inverse) and the Model O (3 x 3), 2 configurations each."""
    rows = []
    star = 1e-3 * np.concatenate([np.zeros((1, 3)), np.asarray(paths.star(size=0.05, dim=3))])
    for system, n_act, iters, scale in (("ur5e", 6, 30, 1.0), ("model_o", 3, 20, 0.03)):
        for b in range(2):
            truth = rng.normal(size=(n_act, 3)) * (3.0 if system == "model_o" else 10.0)
            deltas = 5.0 * np.exp(-0.4 * np.arange(iters)) * (1 + 0.1 * b)
            traj = scale * np.repeat(star, 3, axis=0)
            rows.append(dict(system=system, config_id=b, m_a=tuple([0.03] * n_act), m_a_source="system",
                             q0=rng.normal(size=n_act), converged_at=8, relative_error=0.1, task_error=0.05,
                             completion_estimated=1.0, completion_true=1.0, mean_error_estimated=1e-4,
                             mean_error_true=1e-4, estimate=(truth * (1.05 + 0.05 * b)).ravel(),
                             truth=truth.ravel(), deltas=deltas, positions_estimated=(traj + 1e-4 * b).ravel(),
                             positions_true=traj.ravel()))
    return pd.DataFrame(rows)


@pytest.mark.slow
def test_demo_labels_do_not_overlap_and_each_convergence_panel_has_its_threshold(monkeypatch, tmp_path):
    table = _demo_table(np.random.default_rng(0))
    cfg = demo.DemoConfig()
    summary = demo.summarize(table, cfg)
    drawn = _capture(monkeypatch, demo_figures)
    demo.plot(table, summary, tmp_path)
    fig = drawn["demo"]
    _assert_no_overlap(fig)
    conv = [ax for ax in fig.axes if "convergence" in ax.get_title()]
    assert len(conv) == len(cfg.runs) == 2
    for ax, run in zip(conv, cfg.runs):
        g = table[table["system"] == str(run.system)]
        # the Sec. IV-D test: ||J_t - J_{t-1}||_F <= eps + eps_rel ||J_t||_F, J_t -> the final estimate
        want = [run.eps + run.eps_rel * float(np.sqrt(np.sum(np.square(e)))) for e in g["estimate"]]
        lines = _lines(ax, "threshold:")
        assert lines and (len(lines) == len(want) or list(lines) == ["all"])
        for b, w in enumerate(want):  # each configuration's threshold: its own line, or the one for all
            y = np.asarray(lines[str(b) if str(b) in lines else "all"].get_ydata(), float)
            assert np.allclose(y, w, rtol=1e-12), (run.system, b)
            assert w > 0
    # the Model O's threshold is relative only (eps 0): its lines are still there, at 0.05 ||J_est||
    assert cfg.runs[1].eps == 0 and cfg.runs[1].eps_rel > 0
    # the UR5e (6 actuators, 3 axes) is shown as J Ĵ and J Ĵ - I, J the truth's pseudo-inverse (numpy here);
    # the square Model O as its estimated and true J+
    ur = table[table["system"] == "ur5e"].iloc[0]
    est, truth = np.reshape(ur["estimate"], (6, 3)), np.reshape(ur["truth"], (6, 3))
    product = np.linalg.solve(truth.T @ truth, truth.T) @ est
    heat = {ax.get_title(): np.asarray(ax.get_images()[0].get_array()) for ax in fig.axes if ax.get_images()}
    np.testing.assert_allclose(heat[r"ur5e, config 0: $J\hat J$ ($I$ for any right inverse of $J$)"], product,
                               rtol=1e-9, atol=1e-12)
    minus = [v for k, v in heat.items() if k.startswith(r"ur5e, config 0: $J\hat J - I$")]
    assert len(minus) == 1 and np.allclose(minus[0], product - np.eye(3), atol=1e-12)
    mo = table[table["system"] == "model_o"].iloc[0]
    np.testing.assert_allclose(heat["model_o: true $J^+$, config 0"], np.reshape(mo["truth"], (3, 3)))
    assert not any("POM" in ax.get_title() for ax in fig.axes)


# --------------------------------------------------------------------------- ablation

def _ablation_table(methods, rng, iterations=(1, 2, 5, 10), n_configs=3):
    rows = []
    for i, m in enumerate(methods):
        for it, cfg_id, noise in itertools.product(iterations, range(n_configs), (0.0, 1e-4)):
            failed = (i + cfg_id + it) % 7 == 0
            rows.append(dict(method=m, noise_level=int(noise > 0), pose_noise=noise, rot_noise=0.0, m_a_level=0,
                             m_a=0.03, config_id=cfg_id, trial=0, m_a_vec=(0.03,) * 6, m_a_source="config",
                             iterations=it, completion=float(np.clip(rng.uniform(0.2, 1.2), 0, 1)),
                             mean_error=np.inf if failed else float(rng.uniform(1e-4, 5e-3) / it),
                             failed=failed, converged_at=5))
    return pd.DataFrame(rows)


def _ablation_summary(table, config):
    cfg = registry.load(shipped(config))
    return ablation.summarize(table, cfg), cfg


@pytest.mark.slow
@pytest.mark.parametrize("n_methods", [14, 25])
def test_ablation_every_method_has_its_own_style(monkeypatch, tmp_path, n_methods):
    methods = [f"method {i}" for i in range(n_methods)]
    table = _ablation_table(methods, np.random.default_rng(1))
    drawn = _capture(monkeypatch, figures)
    figures.ablation_figures(table, {}, tmp_path)
    fig = drawn["ablation"]
    _assert_no_overlap(fig)
    lines = _lines(fig.axes[0], "completion:")
    assert sorted(lines) == sorted(methods)
    styles = {(to_rgba(ln.get_color()), ln.get_linestyle(), ln.get_marker()) for ln in lines.values()}
    assert len(styles) == n_methods
    legend = fig.legends[0]
    assert [t.get_text() for t in legend.get_texts()] == methods
    handles = legend.legend_handles
    assert len({(to_rgba(h.get_color()), h.get_linestyle(), h.get_marker()) for h in handles}) == n_methods


def test_method_styles_rejects_repeated_names():
    with pytest.raises(ValueError, match="unique"):
        figures.method_styles(["ours", "ours"])
    assert len(set(figures.method_styles([str(i) for i in range(280)]).values())) == 280


@pytest.mark.slow
@pytest.mark.parametrize("config", ["ablation_ekm_two_link.yaml", "ablation_ekm_ur5e.yaml"])
def test_ekm_ablation_has_a_path_error_panel_equal_to_the_error_column(monkeypatch, tmp_path, config):
    cfg = registry.load(shipped(config))
    methods = [m.name for m in cfg.methods]
    table = _ablation_table(methods, np.random.default_rng(2), iterations=tuple(cfg.iterations))
    summary, _ = _ablation_summary(table, config)
    drawn = _capture(monkeypatch, figures)
    figures.ablation_figures(table, summary, tmp_path)
    fig = drawn["ablation"]
    _assert_no_overlap(fig)
    panel = [ax for ax in fig.axes if "distance to the path" in ax.get_ylabel()]
    assert len(panel) == 1
    lines = _lines(panel[0], "path_error:")
    assert sorted(lines) == sorted(methods)
    for m in methods:  # noise-free, not failed rows: the mean of mean_error per iteration count, in mm
        x, y = (np.asarray(a, float) for a in lines[m].get_data())
        assert list(x) == list(cfg.iterations)
        for it, v in zip(x, y):
            sel = [1e3 * r.mean_error for r in table.itertuples()
                   if r.method == m and r.iterations == it and r.pose_noise == 0.0 and not r.failed]
            if sel:
                assert v == pytest.approx(sum(sel) / len(sel), rel=1e-12)
            else:
                assert np.isnan(v)


# --------------------------------------------------------------------------- valid region

def _valid_region_table(systems, eps=(0.0, 0.5, 1.0, 1.5, 2.0)):
    rows = []
    for k, system in enumerate(systems):
        for e, cfg_id, trial in itertools.product(eps, range(2), range(2)):
            c = 1.0 if abs(e - 1.0) <= 0.5 * (k % 2 + 1) else 0.4
            rows.append(dict(system=system, eps_limit=e, config_id=cfg_id, trial=trial, completion=c,
                             mean_error=1e-3 / c, max_error=3e-3 / c, waypoint_error=5e-4, steps_used=100,
                             failed=False))
    return pd.DataFrame(rows)


@pytest.mark.slow
@pytest.mark.parametrize("config", ["valid_region_all.yaml", "valid_region_two_link.yaml"])
def test_valid_region_suptitle_names_only_controllers_the_systems_ran(monkeypatch, tmp_path, config):
    cfg = registry.load(shipped(config))
    table = _valid_region_table([str(s if isinstance(s, str) else s.system) for s in cfg.systems])
    summary = valid_region.summarize(table, cfg)
    drawn = _capture(monkeypatch, figures)
    valid_region.plot(table, summary, tmp_path)
    fig = drawn["valid_region"]
    _assert_no_overlap(fig)
    # each controller the suptitle names ("controller (a, b): k=v, ..." or, for all systems, "controller: ...")
    # is the one every system it speaks for ran
    runs = {system_name(valid_region.protocol(cfg, e)[0]): valid_region.protocol(cfg, e)[2].model_dump()
            for e in cfg.systems}
    title = fig._suptitle.get_text()
    named = re.findall(r"controller(?: \(([^)]*)\))?: ((?:\w+=[^,;]+(?:, )?)+)", title)
    for who, pairs in named:
        said = dict(kv.split("=", 1) for kv in pairs.split(", "))
        for system in (who.split(", ") if who else runs):
            assert {k: str(v) for k, v in runs[system].items()} == said, (system, title)
    if len({str(c) for c in runs.values()}) > 1 and all(not isinstance(e, str) for e in cfg.systems):
        assert not named, title  # every system has its own: no controller for all in the suptitle
    # every completion panel has its threshold line
    threshold = 100.0 * cfg.completion_threshold
    completion_axes = [ax for ax in fig.axes if ax.get_ylim()[1] == 102]
    assert len(completion_axes) == len(cfg.systems)
    for ax in completion_axes:
        flat = [ln for ln in ax.get_lines() if np.allclose(np.asarray(ln.get_ydata(), float), threshold)]
        assert flat, ax.get_title()
    for system, g in table.groupby("system"):  # the error panel in mm: the mean of mean_error per eps_limit
        (ax,) = [ax for ax in fig.axes if system in _lines(ax, "mean_error:")]
        line = _lines(ax, "mean_error:")[system]
        want = [1e3 * np.mean(g[g["eps_limit"] == e]["mean_error"]) for e in sorted(g["eps_limit"].unique())]
        assert np.allclose(np.asarray(line.get_ydata(), float), want, rtol=1e-12)


# --------------------------------------------------------------------------- tracking

def _tracking_table(cfg, commanded_m, *, tracked, rng, steps=None):
    """Rows whose executed path is the commanded one (each letter from its own start), errors on ``tracked`` only."""
    labels = cfg.path.labels()
    rows = []
    for letter, inverse, noise_level, config_id in itertools.product(range(len(labels)), tracking.INVERSES,
                                                                    range(len(cfg.pose_noise)), range(2)):
        cmd = commanded_m[letter]
        dense = np.concatenate([np.linspace(a, b, 4, endpoint=False) for a, b in zip(cmd[:-1], cmd[1:])] + [cmd[-1:]])
        start = rng.normal(size=3) * 0.1  # where this letter's self-ID left the robot
        used = len(dense) - 1
        n = (steps or cfg.controller.steps) + 1
        pos = np.concatenate([dense, np.repeat(dense[-1:], n - len(dense), axis=0)]) + start
        err = np.zeros((n, 3))
        err[:, tracked] = rng.uniform(0.01, 0.1, size=(n, len(tracked)))
        rot = rng.uniform(0.0, 1.0, size=n) if cfg.path.kind == "rotation" else np.zeros(n)
        rows.append(dict(system=str(cfg.system), inverse=inverse, letter_id=letter, path=labels[letter],
                         noise_level=noise_level, pose_noise=cfg.pose_noise[noise_level],
                         rot_noise=cfg.rot_noise[noise_level], config_id=config_id, trial=0, converged_at=5,
                         m_a=(3e-4,) * 3, m_a_source="config", completion=1.0, waypoint_error_mm=0.1,
                         error_x_mm=0.1, error_y_mm=0.1, error_z_mm=0.1, rot_final_deg=0.0, rot_step_deg=0.0,
                         failed=False, steps_used=used, positions=pos.ravel(), error_trace_mm=err.ravel(),
                         rot_trace_deg=rot))
    return pd.DataFrame(rows)


def _tracking_figure(monkeypatch, tmp_path, config, tracked, steps=None):
    cfg = registry.load(shipped(config))
    commanded = [np.concatenate([np.zeros((1, 3)), np.asarray(w, float)[:, :3]]) for w in cfg.path._paths()]
    table = _tracking_table(cfg, commanded, tracked=tracked, rng=np.random.default_rng(3), steps=steps)
    summary = tracking.summarize(table, cfg)
    drawn = _capture(monkeypatch, tracking_figures)
    tracking.plot(table, summary, tmp_path)
    (fig,) = drawn.values()
    return fig, cfg, table


@pytest.mark.slow
def test_grablab_letters_are_drawn_side_by_side(monkeypatch, tmp_path):
    fig, cfg, _ = _tracking_figure(monkeypatch, tmp_path, "tracking_model_o_grablab.yaml", [0, 1, 2])
    _assert_no_overlap(fig)
    letters = cfg.path.labels()
    assert "".join(letters) == "GRABLAB"
    for ax in fig.axes[:3:2]:  # the two path panels (estimated, analytical)
        for prefix in ("executed:", "commanded:"):
            lines = _lines(ax, prefix)
            assert len(lines) == len(letters)
            xs = [np.asarray(lines[str(i)].get_xdata(), float) for i in range(len(letters))]
            for left, right in zip(xs[:-1], xs[1:]):
                assert left.max() < right.min(), prefix  # each letter entirely right of the one before
        height = 1e3 * cfg.path.height  # and the commanded letters stand on one baseline, 2 mm tall
        for ln in _lines(ax, "commanded:").values():
            y = np.asarray(ln.get_ydata(), float)
            assert y.min() == pytest.approx(0.0, abs=1e-9) and y.max() <= height + 1e-9


@pytest.mark.slow
def test_rotation_tracking_draws_no_zeros_for_untracked_axes(monkeypatch, tmp_path):
    fig, cfg, table = _tracking_figure(monkeypatch, tmp_path, "tracking_model_o_rotation.yaml", [2])
    _assert_no_overlap(fig)
    assert cfg.task_axes == ["z", "rx", "ry"]
    err_axes = [ax for ax in fig.axes if ax.get_ylabel() == "distance to the path [mm]"]
    assert len(err_axes) == 2
    for ax, inverse in zip(err_axes, tracking.INVERSES):
        lines = _lines(ax, "error:")
        assert sorted(lines) == ["z"]  # x and y are not in the task: absent, not a line of zeros
        rows = table[(table["inverse"] == inverse) & (table["noise_level"] == 0) & (table["config_id"] == 0)]
        want = np.concatenate([np.asarray(r.error_trace_mm).reshape(-1, 3)[: r.steps_used + 1, 2]
                               for r in rows.sort_values("letter_id").itertuples()])
        assert np.array_equal(np.asarray(lines["z"].get_ydata(), float), want)
        assert not any(np.all(np.asarray(ln.get_ydata(), float) == 0) for ln in ax.get_lines())


def test_tracked_axes_without_task_axes_come_from_the_traces():
    table = pd.DataFrame({"error_trace_mm": [np.array([[0.1, 0.0, 0.0], [0.2, 0.3, 0.0]]).ravel()]})
    assert tracking_figures.tracked_position_axes(table, None) == [0, 1]
    assert tracking_figures.tracked_position_axes(table, ["z", "rx"]) == [2]


@pytest.mark.slow
def test_cube_figure_draws_the_commanded_path(monkeypatch, tmp_path):
    fig, cfg, _ = _tracking_figure(monkeypatch, tmp_path, "tracking_ur5e_cube.yaml", [0, 1, 2], steps=80)
    _assert_no_overlap(fig)
    # independent: the cube route of paths.cube from the origin, in mm
    want = 1e3 * np.concatenate([np.zeros((1, 3)), np.asarray(paths.cube(edge=cfg.path.edge, dim=3), float)])
    assert want.shape == (17, 3) and np.isclose(want.max(), 150.0)
    for ax in fig.axes[:3:2]:
        found = [ln for ln in ax.get_lines()
                 if np.asarray(ln.get_data_3d()).T.shape == want.shape
                 and np.allclose(np.asarray(ln.get_data_3d(), float).T, want)]
        assert len(found) == 1
        executed = _lines(ax, "executed:")["0"]
        assert np.allclose(np.asarray(executed.get_data_3d(), float).T[[0, -1]], want[[0, -1]])


def _ekm_study_module():
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "scripts" / "ekm_study.py"
    spec = importlib.util.spec_from_file_location("ekm_study_script", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_ekm_study_figure_shows_completion_and_path_error(monkeypatch, tmp_path):
    study = _ekm_study_module()
    methods = ["true", "ours", "nominal"] + [f"ekm {m} ({f})" for m in ("fixed", "online")
                                              for f in ("incremental", "absolute", "incremental, plain")]
    rng = np.random.default_rng(4)
    its = list(study.ITERATIONS)
    completion = pd.DataFrame(rng.uniform(0, 1, (len(methods), len(its))), index=methods, columns=its)
    error = pd.DataFrame(rng.uniform(0.1, 30.0, (len(methods), len(its))), index=methods, columns=its)
    drawn = _capture(monkeypatch, figures)
    study.study_figure(completion, error, tmp_path, "ekm_study_hard", "2-link star")
    fig = drawn["ekm_study_hard"]
    _assert_no_overlap(fig)
    comp, err = _lines(fig.axes[0], "completion:"), _lines(fig.axes[1], "path_error:")
    assert fig.axes[1].get_ylabel() == "mean distance to the path [mm]"
    for m in methods:
        assert np.array_equal(np.asarray(err[m].get_ydata(), float), error.loc[m].to_numpy(float))
        assert np.allclose(np.asarray(comp[m].get_ydata(), float), 100.0 * completion.loc[m].to_numpy(float))
    assert len({(to_rgba(ln.get_color()), ln.get_linestyle(), ln.get_marker()) for ln in comp.values()}) == 9
    with pytest.raises(ValueError, match="same methods"):
        study.study_figure(completion, error.iloc[:-1], tmp_path, "x")


@pytest.mark.slow
def test_peg_in_hole_bars_have_one_tick_per_layout(monkeypatch, tmp_path):
    from selfid_jax.experiments import peg_in_hole
    from selfid_jax.experiments.figures import peg_in_hole as peg_figures

    rows = [dict(noise_level=0, inverse=inv, failed=False, layout=layout, arm_pos_mm=0.1 + layout,
                 arm_rot_deg=0.01, hand_rot_deg=0.02) for inv in peg_in_hole.INVERSES for layout in (0, 1, 2)]
    ctrl = {"max_step": 0.0025, "tol": 0.0005}
    summary = {"protocol": {"arm": {"m_a": 0.03, "eps": 0.5, "controller": ctrl},
                            "hand": {"m_a": 0.0003, "eps_rel": 0.05}, "rotation": {"angle": 0.1, "about": "y"}}}
    drawn = _capture(monkeypatch, peg_figures)
    peg_in_hole.plot(pd.DataFrame(rows), summary, tmp_path)
    fig = drawn["peg_in_hole"]
    _assert_no_overlap(fig)
    for ax in fig.axes:
        assert list(ax.get_xticks()) == [0, 1, 2]
        assert [t.get_text() for t in ax.get_xticklabels()] == ["0", "1", "2"]


@pytest.mark.slow
def test_valid_region_workspace_cells_are_centred_and_the_threshold_outlined(monkeypatch, tmp_path):
    from selfid_jax.experiments import valid_region_workspace as vrw
    from selfid_jax.experiments.figures import valid_region_workspace as vrw_figures

    eps = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    comp = np.array([[0.2, 1.0, 1.0, 0.5, 0.1], [1.0, 1.0, 1.0, 1.0, 0.3], [0.9, 1.0, 0.97, 0.2, 0.0]])  # (bins, eps)
    rows = [dict(manipulability_bin=b, eps_limit=e, completion=comp[b, j], predicted_stable=0.5)
            for b in range(3) for j, e in enumerate(eps)]
    configs = [dict(manipulability=1e-3 * (k + 1), condition=2.0 + k, upper=2.0, lower=0.5, predicted_upper=1.5)
               for k in range(3)]
    summary = dict(configs=configs, system="arm5", fail_with_exact_inverse=0, n_configs=3, completion_threshold=0.95,
                   controller=dict(max_step=0.0025, tol=0.0005, gain=1.0, steps=435), path=dict(size=0.05))
    drawn = _capture(monkeypatch, vrw_figures)
    vrw.plot(pd.DataFrame(rows), summary, tmp_path)
    fig = drawn["valid_region_workspace"]
    _assert_no_overlap(fig)
    heat = [ax for ax in fig.axes if ax.get_images()]
    assert len(heat) == 2
    for ax in heat:  # each cell centred on its eps_limit: the image spans half a step beyond the first and last
        assert ax.get_images()[0].get_extent()[:2] == pytest.approx([-0.25, 2.25])
    (outline,) = [c for c in heat[0].collections if c.get_gid() == "threshold"]
    ok = np.pad(comp >= 0.95, 1)
    edges = int(np.sum(ok[1:, :] != ok[:-1, :]) + np.sum(ok[:, 1:] != ok[:, :-1]))  # passing next to failing
    assert len(outline.get_segments()) == edges
    xs = np.concatenate([np.asarray(s)[:, 0] for s in outline.get_segments()])
    assert np.allclose(np.sort(np.unique(np.round(xs, 9))), [-0.25, 0.25, 0.75, 1.25, 1.75])
