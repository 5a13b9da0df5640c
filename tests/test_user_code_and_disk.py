"""A pose_fn module that fails on import, a disk that fills while figures are written, a plot beside a running sweep:
each is one line naming the module, file or process, exit 2, and no partial file."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from matplotlib.figure import Figure

from selfid_jax import cli
from selfid_jax.runner import files
from selfid_jax.runner.figures import save_figure

CONFIG = textwrap.dedent("""\
    experiment: valid_region
    systems: [{{pose_fn: "{module}:fk", n_act: 2, task_dim: 2}}]
    eps_limits: {{start: 0.5, stop: 1.5, num: 2}}
    n_configs: 1
    n_trials: 1
    path: {{size: 0.1}}
    controller: {{max_step: 0.01, tol: 0.002, steps: 50}}
    """)

BROKEN = {
    "raises": ("raise RuntimeError('no robot here')\n", "RuntimeError: no robot here"),
    "syntax": ("def fk(params, q:\n    return q\n", "SyntaxError"),
    "exits": ("import sys\nsys.exit(7)\n", "exit(7)"),
}


@pytest.mark.parametrize("kind", sorted(BROKEN))
def test_pose_fn_module_failing_on_import_is_one_line(tmp_path, capsys, monkeypatch, kind):
    source, expected = BROKEN[kind]
    (tmp_path / f"bot_{kind}.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    cfg = tmp_path / "vr.yaml"
    cfg.write_text(CONFIG.format(module=f"bot_{kind}"))
    assert cli.main(["sweep", str(cfg), "--out", str(tmp_path / "run"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"importing module 'bot_{kind}' failed" in err[0] and expected in err[0], err
    assert not (tmp_path / "run").exists()  # nothing made before the error


@pytest.mark.slow
def test_full_disk_while_saving_a_figure_names_the_file_and_keeps_the_old_one(tmp_path, monkeypatch):
    fig = Figure()
    fig.add_subplot().plot(np.arange(3))
    old = save_figure(fig, tmp_path, "f")
    before = {p.name: p.read_bytes() for p in old}
    real_fsync = os.fsync

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.os, "fsync", full)
    with pytest.raises(OSError) as err:
        save_figure(fig, tmp_path, "f")
    monkeypatch.setattr(files.os, "fsync", real_fsync)
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(tmp_path / "f.png")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # the old figures, no temporary file


@pytest.mark.slow
def test_plot_beside_a_running_sweep_is_refused(tmp_path):
    """While another process holds the run directory, ``plot`` exits 2 naming it and draws nothing."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("experiment: valid_region\n")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from selfid_jax.runner.lock import hold\n"
         f"with hold({str(run)!r}):\n    print('held', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        out = subprocess.run([sys.executable, "-c", "import sys; from selfid_jax.cli import main; "
                              f"sys.exit(main(['plot', {str(run)!r}]))"], capture_output=True, text=True, timeout=120)
    finally:
        holder.kill()
    assert out.returncode == 2 and f"process {holder.pid}" in out.stderr, out.stderr
    assert not (run / "figures").exists()


def test_output_path_is_checked_before_any_compute(tmp_path, capsys, monkeypatch):
    """``--out`` naming a file (or a path through one) exits 2 naming it, before the experiment is even set up."""
    from selfid_jax.runner import command_line as runner_cli

    def no_compute(*args, **kwargs):
        raise AssertionError("the experiment was set up although --out is unusable")

    monkeypatch.setattr(runner_cli, "_build", no_compute)
    a_file = tmp_path / "results.txt"
    a_file.write_text("user data\n")
    for out, words in ((a_file, "exists and is a file, not a directory"), (a_file / "run", f"has a file, {a_file}")):
        assert cli.main(["demo", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert str(a_file) in err and words in err
    assert a_file.read_text() == "user data\n"
