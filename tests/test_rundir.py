"""A run directory never loses or mixes finished results: lock, chunk verification, exit codes, file modes."""

from __future__ import annotations

import builtins
import contextlib
import errno
import hashlib
import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pydantic
import pytest
from helpers_sweep import (
    TESTS,
    SyntheticConfig,
    make_inputs,
    reference,
    subprocess_env,
    synthetic_build,
    synthetic_fn,
)
from selfid_jax.experiments.common import figures as plots

from selfid_jax import cli
from selfid_jax import runner as experiment
from selfid_jax.runner import command_line as runner_cli
from selfid_jax.runner import sweep
from selfid_jax.runner.config import BaseConfig
from selfid_jax.runner.lock import RunDirBusy, RunDirError, hold
from selfid_jax.runner.rundir import create_run_dir, load_results, write_json, write_summary
from selfid_jax.runner.sweep import SweepResumeError, grid_table, row_keys, run_chunked

# --------------------------------------------------------------------------- helpers


def _slow_compute(static, p):
    """The synthetic row, after sleeping SELFID_TEST_SLEEP seconds (read when it runs)."""
    jax.debug.callback(lambda: time.sleep(float(os.environ.get("SELFID_TEST_SLEEP", "0"))))
    return jax.tree.map(lambda x: x[0], synthetic_fn({"a": p.a[None], "key": p.key[None]}))


SLOW = experiment.register(experiment.Experiment(
    name="slow_cli_test", config=SyntheticConfig, build=synthetic_build, compute=_slow_compute,
    summarize=lambda df, cfg: {"mean_final": float(df["final"].mean())},
))


def _config(tmp_path: Path, name: str = "slow_cli_test") -> Path:
    cfg = tmp_path / "synthetic.yaml"
    cfg.write_text(f"experiment: {name}\nchunk_size: 4\ngains: [0.3, 0.9]\nn_trials: 5\n")
    return cfg


def _sweep(cfg: Path, out: Path, *extra: str) -> int:
    return cli.main(["sweep", str(cfg), "--out", str(out), "--no-progress", *extra])


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def _snapshot(root: Path, skip: tuple[str, ...] = ()) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name not in skip}


HOLDER = textwrap.dedent(
    """
    import fcntl, os, sys, time
    fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o666)
    fcntl.flock(fd, fcntl.LOCK_EX)
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\\n".encode())
    print("locked", flush=True)
    time.sleep(120)
    """
)


@contextlib.contextmanager
def _lock_held_elsewhere(run_dir: Path):
    """Another process holding ``run_dir``'s lock as selfid-jax does (flock on RUN/.lock); yields its pid."""
    run_dir.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(run_dir / ".lock")], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        yield proc
    finally:
        proc.kill()
        proc.wait(timeout=30)
        proc.stdout.close()


# --------------------------------------------------------------------------- 1. lock


@pytest.mark.slow
def test_second_process_is_refused_and_fresh_deletes_nothing(tmp_path, capsys):
    cfg, out = _config(tmp_path), tmp_path / "run"
    assert _sweep(cfg, out) == 0
    capsys.readouterr()
    before = _snapshot(out, skip=(".lock",))

    with _lock_held_elsewhere(out) as holder:
        for extra in ((), ("--fresh",)):
            t0 = time.perf_counter()
            assert _sweep(cfg, out, *extra) == 2
            err = _one_line_error(capsys)
            assert f"run directory {out} is in use by process {holder.pid}" in err
            assert time.perf_counter() - t0 < 5  # at once, not after computing
        with pytest.MonkeyPatch.context() as mp:  # refused before the demo builds (its start searches compile)
            mp.setattr(runner_cli, "_build", lambda *a: pytest.fail("built the experiment of a busy run directory"))
            assert cli.main(["demo", "--out", str(out)]) == 2
        assert f"in use by process {holder.pid}" in capsys.readouterr().err
        meta, params = make_inputs()
        with pytest.raises(RunDirBusy, match=f"process {holder.pid}"):
            run_chunked(synthetic_fn, params, chunk_size=5, out_dir=out / "parts" / "synthetic", meta=meta,
                        progress=False, fresh=True)
        with pytest.raises(RunDirBusy), hold(out):  # the run's one lock (execute.run), then the directory
            create_run_dir(out, {"experiment": "x"}, fresh=True)
        assert _snapshot(out, skip=(".lock",)) == before  # nothing deleted, nothing written

    # the holder was killed: no stale lock; the finished run is found whole
    assert _sweep(cfg, out) == 0
    assert load_results(out)["final"].notna().all()


@pytest.mark.slow
def test_lock_is_reentrant_in_one_process_and_released_on_exit(tmp_path):
    run = tmp_path / "run"
    with hold(run), hold(run):
        meta, params = make_inputs()
        df = run_chunked(synthetic_fn, params, chunk_size=12, out_dir=run / "parts" / "p", meta=meta, progress=False)
    assert len(df) == 23
    with _lock_held_elsewhere(run):  # released: another process can take it
        pass


@pytest.mark.slow
def test_two_sweeps_into_one_directory(tmp_path, capsys):
    """Two real selfid-jax processes: the second is refused, the first finishes untouched."""
    cfg, out = _config(tmp_path), tmp_path / "run"
    script = (f"import sys; sys.path.insert(0, {str(TESTS)!r}); import test_rundir; from selfid_jax import cli; "
              f"sys.exit(cli.main(['sweep', {str(cfg)!r}, '--out', {str(out)!r}, '--no-progress']))")
    first = subprocess.Popen([sys.executable, "-c", script],
                             env=subprocess_env(JAX_PLATFORMS="cpu", SELFID_TEST_SLEEP="0.15"),
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    chunk_dir = out / "parts" / "synthetic" / "chunks"
    deadline = time.monotonic() + 90
    while first.poll() is None and not list(chunk_dir.glob("chunk_*.parquet")) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert first.poll() is None, first.communicate()[1][-3000:]
    for extra in (("--fresh",), ()):
        assert _sweep(cfg, out, *extra) == 2
        assert f"run directory {out} is in use by process {first.pid}" in _one_line_error(capsys)
    _, stderr = first.communicate(timeout=120)
    assert first.returncode == 0, stderr[-3000:]
    assert (out / "parts" / "synthetic" / "manifest.json").is_file()
    assert len(load_results(out)) == 10
    assert _sweep(cfg, out) == 0  # free again; nothing to recompute
    assert json.loads((out / "versions.json").read_text()).get("refused") is None


PROBE = textwrap.dedent(
    """
    import fcntl, os, sys
    fd = os.open(sys.argv[1], os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        print("busy")
    else:
        print("free")
    """
)


def _plot_probing_the_lock(df, summary, fig_dir: Path) -> list[Path]:
    """A figure hook that records whether another process could take the run directory's lock while it draws."""
    run_dir = fig_dir.parent
    probe = subprocess.run([sys.executable, "-c", PROBE, str(run_dir / ".lock")], capture_output=True, text=True,
                           timeout=60, check=True)
    fig_dir.mkdir(parents=True, exist_ok=True)
    (fig_dir / "probe.txt").write_text(probe.stdout.strip())
    return [fig_dir / "probe.txt"]


PLOTTING = experiment.register(experiment.Experiment(
    name="plotting_cli_test", config=SyntheticConfig, build=synthetic_build, compute=_slow_compute,
    summarize=lambda df, cfg: {"mean_final": float(df["final"].mean())}, plot=_plot_probing_the_lock,
))


@pytest.mark.slow
def test_lock_is_held_while_the_figures_are_drawn(tmp_path, capsys):
    """sweep and demo draw the figures under the run's lock: a second process asking for it then is refused."""
    cfg, out = _config(tmp_path, "plotting_cli_test"), tmp_path / "run"
    assert _sweep(cfg, out) == 0
    assert (out / "figures" / "probe.txt").read_text() == "busy"
    assert "figure:  " in capsys.readouterr().out
    with _lock_held_elsewhere(out):  # released once the figures are written
        pass


# --------------------------------------------------------------------------- 2. corrupt chunks


def _run(out: Path, seed: int = 0, **kw) -> pd.DataFrame:
    meta, params = make_inputs(seed)
    return run_chunked(synthetic_fn, params, chunk_size=5, out_dir=out, meta=meta, progress=False, **kw)


@pytest.mark.slow
def test_manifest_records_row_range_and_hash_of_each_chunk(tmp_path):
    _run(tmp_path)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["format"] == 4 and manifest["x64"] is True
    for i, (start, stop) in enumerate([(0, 5), (5, 10), (10, 15), (15, 20), (20, 23)]):
        data = (tmp_path / "chunks" / f"chunk_0000{i}.parquet").read_bytes()
        assert manifest["chunks"][str(i)] == {"rows": [start, stop], "sha256": hashlib.sha256(data).hexdigest()}


@pytest.mark.slow
def test_truncated_and_empty_chunks_are_recomputed(tmp_path, capsys):
    _run(tmp_path)
    chunk = tmp_path / "chunks"
    data = (chunk / "chunk_00001.parquet").read_bytes()
    (chunk / "chunk_00001.parquet").write_bytes(data[: len(data) // 2])
    (chunk / "chunk_00003.parquet").write_bytes(b"")
    (tmp_path / "results.parquet").unlink()
    capsys.readouterr()
    df = _run(tmp_path)
    err = capsys.readouterr().err.splitlines()
    assert [line.split(": ", 1)[1] for line in err] == [
        "chunk 1: corrupt (hash mismatch), recomputing", "chunk 3: corrupt (hash mismatch), recomputing"]
    assert df.attrs["sweep"]["computed"] == [1, 3]
    np.testing.assert_allclose(df["final"].to_numpy(), reference(make_inputs()[1])["final"], rtol=1e-6)


@pytest.mark.slow
def test_chunk_copied_from_another_run_is_recomputed(tmp_path, capsys):
    mine, other = tmp_path / "seed0", tmp_path / "seed1"
    _run(mine, seed=0)
    _run(other, seed=1)
    shutil.copyfile(other / "chunks" / "chunk_00002.parquet", mine / "chunks" / "chunk_00002.parquet")
    df = _run(mine, seed=0)
    assert "chunk 2: corrupt (hash mismatch), recomputing" in capsys.readouterr().err
    assert df.attrs["sweep"]["computed"] == [2]
    np.testing.assert_allclose(df["final"].to_numpy(), reference(make_inputs(0)[1])["final"], rtol=1e-6)
    assert len(load_results(mine, partial=True)) == 23


@pytest.mark.slow
def test_chunk_changed_during_the_run_is_never_assembled(tmp_path, monkeypatch):
    _run(tmp_path)
    (tmp_path / "chunks" / "chunk_00004.parquet").unlink()
    real_write = sweep._write_chunk

    def write_and_damage_chunk_0(path, data):
        real_write(path, data)
        (tmp_path / "chunks" / "chunk_00000.parquet").write_bytes(b"PAR1")

    monkeypatch.setattr(sweep, "_write_chunk", write_and_damage_chunk_0)
    with pytest.raises(RunDirError, match=r"chunk_00000.parquet: changed during the run \(hash mismatch\)"):
        _run(tmp_path)


@pytest.mark.slow
def test_old_manifest_format_is_refused(tmp_path):
    _run(tmp_path)
    path = tmp_path / "manifest.json"
    old = json.loads(path.read_text())
    old["format"] = 2
    del old["chunks"], old["x64"]
    path.write_text(json.dumps(old))
    with pytest.raises(SweepResumeError, match=r"made by an older selfid_jax .*use --fresh"):
        _run(tmp_path)
    assert _run(tmp_path, fresh=True).attrs["sweep"]["computed"] == [0, 1, 2, 3, 4]


@contextlib.contextmanager
def _x64(enabled: bool):
    was = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", enabled)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", was)


@pytest.mark.slow
def test_float_width_mismatch_is_named(tmp_path):
    _run(tmp_path)
    with _x64(False), pytest.raises(
        SweepResumeError, match=r"this run was made with float64 \(jax_enable_x64\); rerun with the same setting or "
        r"--fresh"):
        _run(tmp_path)


# --------------------------------------------------------------------------- 3. exit codes


def test_out_that_is_a_file_or_under_a_file_exits_2(tmp_path, capsys):
    cfg = _config(tmp_path)
    a_file = tmp_path / "a_file"
    a_file.write_text("mine\n")
    assert _sweep(cfg, a_file) == 2
    assert f"{a_file}: exists and is a file, not a directory; choose another --out" in _one_line_error(capsys)
    assert _sweep(cfg, a_file / "run") == 2
    assert f"has a file, {a_file}, as a parent" in _one_line_error(capsys)
    assert a_file.read_text() == "mine\n"


@contextlib.contextmanager
def _read_only(monkeypatch, root: Path):
    """``root`` made read-only (chmod); as root, which chmod does not stop, writes under it are refused too."""
    real_open, real_mkdir, real_builtin_open, inside = os.open, os.mkdir, builtins.open, str(root.resolve())

    def refuse(path):
        if os.path.abspath(os.fspath(path)).startswith(inside):
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(path))

    def open_(path, flags, mode=0o777, *, dir_fd=None):
        if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
            refuse(path)
        return real_open(path, flags, mode, dir_fd=dir_fd)

    def builtin_open(file, mode="r", *args, **kwargs):
        if isinstance(file, (str, os.PathLike)) and set(mode) & set("wax+"):
            refuse(file)
        return real_builtin_open(file, mode, *args, **kwargs)

    def mkdir_(path, mode=0o777, *, dir_fd=None):
        refuse(path)
        return real_mkdir(path, mode, dir_fd=dir_fd)

    modes = {p: p.stat().st_mode for p in [root, *root.rglob("*")]}
    for p, mode in modes.items():
        p.chmod(mode & ~0o222)
    try:
        with monkeypatch.context() as m:
            m.setattr(os, "open", open_)
            m.setattr(os, "mkdir", mkdir_)
            m.setattr(builtins, "open", builtin_open)
            yield
    finally:
        for p, mode in modes.items():
            p.chmod(mode)


@pytest.mark.slow
def test_read_only_run_directory_exits_2(tmp_path, capsys, monkeypatch):
    cfg, out = _config(tmp_path, "synthetic_cli_test"), tmp_path / "run"  # one that draws a figure
    assert _sweep(cfg, out) == 0
    capsys.readouterr()
    for f in (out / "figures").iterdir():
        f.unlink()
    with _read_only(monkeypatch, out):
        assert _sweep(cfg, out) == 2
        err = _one_line_error(capsys)
        assert f"{out / 'versions.json'}: Permission denied; make {out} writable, or choose another --out" in err
        assert cli.main(["plot", str(out)]) == 2
        assert f"Permission denied; make {out / 'figures'} writable" in _one_line_error(capsys)


@pytest.mark.slow
def test_corrupt_files_in_plot_exit_2(tmp_path, capsys):
    cfg, out = _config(tmp_path, "synthetic_cli_test"), tmp_path / "run"
    assert _sweep(cfg, out) == 0
    capsys.readouterr()
    rerun = f"rerun 'selfid-jax sweep {cfg.resolve()} --out {out}' to rebuild it"
    for name, junk, expect in [
        ("results.parquet", b"PAR1 not parquet", rerun),
        ("summary.json", b'{"mean_final": ', rerun),
        ("config.yaml", b"experiment: [unclosed\n",
         f"start over with 'selfid-jax sweep {cfg.resolve()} --out {out} --fresh'"),
    ]:
        good = (out / name).read_bytes()
        (out / name).write_bytes(junk)
        assert cli.main(["plot", str(out)]) == 2, name
        err = _one_line_error(capsys)
        assert f"{out / name}: unreadable (" in err and expect in err, err
        (out / name).write_bytes(good)
    assert cli.main(["plot", str(out)]) == 0


@pytest.mark.slow
def test_full_disk_exits_2_and_resumes(tmp_path, capsys, monkeypatch):
    cfg, out = _config(tmp_path), tmp_path / "run"
    real_write, calls = sweep._write_chunk, []

    def full_disk(path, data):
        calls.append(path)
        if len(calls) < 2:
            return real_write(path, data)
        with monkeypatch.context() as m:
            m.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left on device")))
            real_write(path, data)

    monkeypatch.setattr(sweep, "_write_chunk", full_disk)
    assert _sweep(cfg, out) == 2
    err = _one_line_error(capsys)
    assert (f"{calls[1]}: No space left on device; free some disk space, then run the same command again to resume"
            in err)
    chunk_dir = out / "parts" / "synthetic" / "chunks"
    assert [p.name for p in chunk_dir.iterdir()] == ["chunk_00000.parquet"]  # no temporary file left
    monkeypatch.setattr(sweep, "_write_chunk", real_write)
    assert _sweep(cfg, out) == 0 and len(load_results(out)) == 10


# --------------------------------------------------------------------------- 4. minor


@pytest.mark.slow
def test_refused_resume_is_recorded_and_nothing_else_changes(tmp_path, capsys):
    cfg, out = _config(tmp_path), tmp_path / "run"
    assert _sweep(cfg, out) == 0
    before = _snapshot(out, skip=("versions.json",))
    versions = json.loads((out / "versions.json").read_text())

    assert _sweep(cfg, out, "--set", "n_trials=6") == 2
    assert "n_trials (was 5, now 6)" in _one_line_error(capsys)
    with _x64(False):
        assert _sweep(cfg, out) == 2
    assert "this run was made with float64 (jax_enable_x64)" in _one_line_error(capsys)

    after = json.loads((out / "versions.json").read_text())
    refused = after.pop("refused")
    assert after == versions  # the resumptions recorded before are untouched
    assert "n_trials (was 5, now 6)" in refused[0]["reason"] and refused[0]["overrides"] == ["n_trials=6"]
    assert "float64" in refused[1]["reason"] and refused[1]["x64"] is False
    assert _snapshot(out, skip=("versions.json",)) == before


@pytest.mark.parametrize("umask", [0o022, 0o027], ids=["umask022", "umask027"])
def test_files_get_the_users_umask(tmp_path, umask):
    old = os.umask(umask)
    try:
        _run(tmp_path)
        write_summary(tmp_path, {"x": 1.0})
    finally:
        os.umask(old)
    for name in ("manifest.json", "results.parquet", "summary.json", "chunks/chunk_00000.parquet"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name


def test_json_floats_round_trip_exactly(tmp_path):
    """Run directories and session logs write a number one way, exactly (selfid_jax.strict_json)."""
    from selfid_jax.robot.journal import Journal, read_journal

    record = {"lower": 2.0500000000000003, "curve": np.array([0.1 + 0.2, 1 / 3]), "n": np.int64(3),
              "nan": float("nan"), "tiny": 1.2345678901234567e-9, "flag": np.bool_(True), 7: Path("a/b")}
    expected = {"lower": 2.0500000000000003, "curve": [0.30000000000000004, 1 / 3], "n": 3, "nan": None,
                "tiny": 1.2345678901234567e-9, "flag": True, "7": "a/b"}
    write_json(tmp_path / "s.json", record)
    assert json.loads((tmp_path / "s.json").read_text()) == expected
    with Journal(tmp_path / "log.jsonl") as journal:
        journal.append({"e": "header"})
        journal.append({"e": "x", **record})
    assert read_journal(tmp_path / "log.jsonl").records == [{"e": "x", **expected}]


def test_decimal_linspace_has_no_binary_noise():
    from selfid_jax.runner.grids import decimal_linspace

    grid = decimal_linspace(0.0, 3.0, 61)
    assert grid[7] == 0.35 and np.linspace(0.0, 3.0, 61)[7] != 0.35
    assert grid[0] == 0.0 and grid[-1] == 3.0 and grid.dtype == np.float64
    np.testing.assert_allclose(grid, np.linspace(0.0, 3.0, 61), rtol=1e-15, atol=0)
    assert json.dumps(grid.tolist()).count("0000000") == 0


class ThresholdConfig(BaseConfig):
    experiment: str = "threshold_cli_test"
    gains: list[float] = pydantic.Field(min_length=1)
    completion_threshold: float = pydantic.Field(0.95, gt=0, le=1)


SEEN: list[dict] = []


def _threshold_build(cfg):
    meta = grid_table({"system": ["s"], "eps_limit": cfg.gains})
    params = {"a": meta["eps_limit"].to_numpy(), "key": row_keys(cfg.seed, len(meta))}
    return experiment.Part("p", None, params, meta)


def _threshold_plot(df, summary, out_dir):
    SEEN.append(dict(summary))
    return plots.valid_region_figure(df, summary, out_dir)


experiment.register(experiment.Experiment(
    name="threshold_cli_test", config=ThresholdConfig, build=_threshold_build,
    compute=lambda static, p: {"completion": jnp.clip(1.0 - jnp.abs(p["a"] - 1.0), 0.0, 1.0),
                               "mean_error": 1e-3 * (1.0 + jnp.abs(p["a"] - 1.0))},
    summarize=lambda df, cfg: plots.valid_region_summary(df, cfg.completion_threshold),
    plot=_threshold_plot,
))


@pytest.mark.slow
def test_plot_without_summary_uses_the_configured_threshold(tmp_path):
    cfg = tmp_path / "t.yaml"
    cfg.write_text("experiment: threshold_cli_test\nchunk_size: 8\ngains: [0.2, 0.6, 1.0, 1.45, 2.3]\n"
                   "completion_threshold: 0.5\n")
    out = tmp_path / "run"
    assert _sweep(cfg, out) == 0
    from_summary = SEEN[-1]
    assert from_summary["systems"]["s"]["lower"] == 0.6 and from_summary["systems"]["s"]["upper"] == 1.45
    (out / "summary.json").unlink()
    assert cli.main(["plot", str(out)]) == 0
    assert SEEN[-1]["completion_threshold"] == 0.5
    assert {k: SEEN[-1]["systems"]["s"][k] for k in ("lower", "upper")} == {"lower": 0.6, "upper": 1.45}
    assert not (out / "summary.json").exists()  # plot only reads
