"""Chunked, sharded, resumable sweeps with a synthetic compute function; CLI end to end."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import chex
import numpy as np
import pandas as pd
import pytest
from helpers_sweep import RUNS, TESTS, make_inputs, reference, subprocess_env, synthetic_fn

import selfid_jax.runner.sweep as sweep
from selfid_jax import cli
from selfid_jax import runner as experiment
from selfid_jax._xla import quick_compile_flags
from selfid_jax.runner.rundir import load_results, read_summary
from selfid_jax.runner.sweep import SweepResumeError, row_keys, run_chunked


def assert_matches_reference(df: pd.DataFrame, ref: dict[str, np.ndarray]) -> None:
    assert df["row"].tolist() == list(range(len(ref["final"])))
    np.testing.assert_allclose(df["final"].to_numpy(), ref["final"], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(np.stack(df["traj"].to_numpy()), ref["traj"], rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(df["negative"].to_numpy(), ref["negative"])


@pytest.mark.slow
@pytest.mark.parametrize("static_shapes, max_traces", [(True, 1), (False, 2)])
def test_chunked_equals_unchunked_and_compiles_once(tmp_path, static_shapes, max_traces):
    meta, params = make_inputs()
    chex.clear_trace_counter()
    fn = chex.assert_max_traces(synthetic_fn, n=max_traces)
    df = run_chunked(fn, params, chunk_size=5, out_dir=tmp_path, meta=meta, progress=False, static_shapes=static_shapes)
    assert_matches_reference(df, reference(params))
    assert list(df.columns) == ["row", "system", "a", "trial", "final", "negative", "traj"]
    assert df[["system", "a", "trial"]].equals(meta.reset_index(drop=True))
    assert df.attrs["sweep"]["computed"] == [0, 1, 2, 3, 4]
    pd.testing.assert_frame_equal(load_results(tmp_path), df, check_like=False)
    assert sorted(p.name for p in (tmp_path / "chunks").iterdir()) == [f"chunk_0000{i}.parquet" for i in range(5)]
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert (manifest["n_rows"], manifest["chunk_size"], manifest["n_chunks"]) == (23, 5, 5)


@pytest.mark.slow
def test_an_execution_lock_gates_every_chunk_and_changes_no_result(tmp_path):
    """With ``execution_lock`` each chunk's program runs while holding it (sweeps side by side in threads keep one
    program in flight): held elsewhere, no chunk is computed; released, every chunk is, as without it."""
    import threading

    class Counting:
        def __init__(self):
            self.inner, self.entered = threading.Lock(), 0

        def __enter__(self):
            self.inner.acquire()
            self.entered += 1

        def __exit__(self, *exc):
            self.inner.release()

    meta, params = make_inputs()
    gate = Counting()
    gate.inner.acquire()  # held by the test: the sweep's thread must wait at its first chunk
    out = {}
    worker = threading.Thread(target=lambda: out.update(df=run_chunked(
        synthetic_fn, params, chunk_size=5, out_dir=tmp_path, meta=meta, progress=False, execution_lock=gate)))
    worker.start()
    worker.join(timeout=0.3)
    assert worker.is_alive() and not list((tmp_path / "chunks").glob("*.parquet"))
    gate.inner.release()
    worker.join(timeout=60)
    assert not worker.is_alive() and gate.entered == 5  # one hold per chunk
    assert_matches_reference(out["df"], reference(params))


HANG_REPRO = TESTS.parent / "scripts" / "hang_repro.py"


def test_hang_reproducer_refuses_bad_arguments_with_exit_2():
    """``scripts/hang_repro.py`` (the two-thread reproducer the execution lock names) checks its arguments before
    it starts any child."""
    out = subprocess.run([sys.executable, str(HANG_REPRO), "--trials", "0"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2 and "must be positive" in out.stderr, out.stderr


@pytest.mark.slow
def test_hang_reproducer_runs_two_parts_without_the_lock_and_each_switch(tmp_path):
    """Tiny trials of the reproducer finish in every mode (two float64 ``run_chunked`` parts in two threads, two
    chunks each): exit 0 and one ``finished`` line each. The trials' children share a persistent
    XLA cache (the run's, else a fresh one), so a mode with the same XLA flags as one before it loads the
    compiled chunk program instead of compiling it again: the hang is in running programs, not compiling them."""
    cache = os.environ.get("SELFID_JAX_TEST_CACHE_DIR") or str(tmp_path)
    env = subprocess_env(JAX_ENABLE_X64="0", JAX_COMPILATION_CACHE_DIR=cache,
                         JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    for mode in ("none", "no-async", "no-eigen"):
        out = subprocess.run([sys.executable, str(HANG_REPRO), "--mode", mode, "--trials", "1", "--timeout", "120",
                              "--rows", "32", "--chunk", "16", "--steps", "4", "--width", "8"],
                             capture_output=True, text=True, timeout=600, env=env)
        assert out.returncode == 0 and f"mode {mode}: 0 of 1 hung" in out.stdout, (mode, out.stdout, out.stderr)


def test_row_keys_depend_only_on_seed_and_row():
    np.testing.assert_array_equal(row_keys(7, 10)[3:6], row_keys(7, np.arange(3, 6)))
    assert not np.array_equal(row_keys(7, 4), row_keys(8, 4))


@pytest.mark.slow
def test_resume_after_interrupt(tmp_path, monkeypatch):
    meta, params = make_inputs()
    ref = reference(params)
    real_write, writes = sweep._write_chunk, []

    def interrupted_write(path, data):
        if len(writes) == 2:
            raise KeyboardInterrupt  # Ctrl-C while the 3rd chunk is being saved
        writes.append(path.name)
        real_write(path, data)

    monkeypatch.setattr(sweep, "_write_chunk", interrupted_write)
    with pytest.raises(KeyboardInterrupt):
        run_chunked(synthetic_fn, params, chunk_size=5, out_dir=tmp_path, meta=meta, progress=False)
    monkeypatch.setattr(sweep, "_write_chunk", real_write)
    assert not (tmp_path / "results.parquet").exists()
    assert len(load_results(tmp_path, partial=True)) == 10
    stamps = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "chunks").iterdir()}
    assert sorted(stamps) == ["chunk_00000.parquet", "chunk_00001.parquet"]

    df = run_chunked(synthetic_fn, params, chunk_size=5, out_dir=tmp_path, meta=meta, progress=False)
    assert df.attrs["sweep"]["computed"] == [2, 3, 4] and df.attrs["sweep"]["skipped"] == [0, 1]
    assert {n: (tmp_path / "chunks" / n).stat().st_mtime_ns for n in stamps} == stamps
    assert not df["row"].duplicated().any()
    assert_matches_reference(df, ref)

    # lost chunk files and table: only those chunks are recomputed
    (tmp_path / "chunks" / "chunk_00001.parquet").unlink()
    (tmp_path / "chunks" / "chunk_00004.parquet").unlink()
    (tmp_path / "results.parquet").unlink()
    again = run_chunked(synthetic_fn, params, chunk_size=5, out_dir=tmp_path, meta=meta, progress=False)
    assert again.attrs["sweep"]["computed"] == [1, 4]
    again.attrs, df.attrs = {}, {}
    pd.testing.assert_frame_equal(again, df)


@pytest.mark.slow
def test_manifest_mismatch_errors_unless_fresh(tmp_path):
    meta, params = make_inputs()
    run_chunked(synthetic_fn, params, chunk_size=5, out_dir=tmp_path, meta=meta, progress=False)
    other = dict(params, a=params["a"] * 2)
    with pytest.raises(SweepResumeError, match=r"params_hash"):
        run_chunked(synthetic_fn, other, chunk_size=5, out_dir=tmp_path, meta=meta, progress=False)
    with pytest.raises(SweepResumeError, match=r"chunk_size \(was 5, now 6\)"):
        run_chunked(synthetic_fn, params, chunk_size=6, out_dir=tmp_path, meta=meta, progress=False)
    df = run_chunked(synthetic_fn, other, chunk_size=5, out_dir=tmp_path, meta=meta, progress=False, fresh=True)
    assert df.attrs["sweep"]["computed"] == [0, 1, 2, 3, 4]
    assert_matches_reference(df, reference(other))


def test_bad_inputs_raise():
    meta, params = make_inputs()
    with pytest.raises(ValueError, match="rows"):
        run_chunked(synthetic_fn, dict(params, a=params["a"][:5]), chunk_size=5, out_dir="unused", progress=False)
    with pytest.raises(ValueError, match="chunk_size"):
        run_chunked(synthetic_fn, params, chunk_size=0, out_dir="unused", progress=False)


TWO_DEVICE_SCRIPT = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {tests!r})
    import jax, pandas as pd
    import selfid_jax.runner.sweep as sweep
    from helpers_sweep import make_inputs, synthetic_fn
    assert len(jax.devices()) == 2, jax.devices()
    out = {out!r}
    meta, params = make_inputs()
    one = sweep.run_chunked(synthetic_fn, params, chunk_size=5, out_dir=out + "/one", meta=meta,
                            progress=False, devices=jax.devices()[:1])
    two = sweep.run_chunked(synthetic_fn, params, chunk_size=5, out_dir=out + "/two", meta=meta, progress=False)
    assert two.attrs["sweep"]["n_devices"] == 2 and two.attrs["sweep"]["batch"] == 6
    # a run started on one device resumes on two
    for i in (1, 3):
        (sweep.Path(out) / "one" / "chunks" / f"chunk_0000{{i}}.parquet").unlink()
    resumed = sweep.run_chunked(synthetic_fn, params, chunk_size=5, out_dir=out + "/one", meta=meta, progress=False)
    assert resumed.attrs["sweep"]["computed"] == [1, 3]
    for df in (one, two, resumed):
        df.attrs = {{}}
    pd.testing.assert_frame_equal(one, two, check_exact=True)
    pd.testing.assert_frame_equal(one, resumed, check_exact=True)
    one.to_parquet(out + "/one.parquet")
    print("OK")
    """
)


# The subprocesses below compile at the tests' quick level (tests/conftest.py): what they check (device counts,
# resuming, whole chunk files) does not depend on it, and their compile time is most of their run time.
QUICK = " ".join(f"{k}={v}" for k, v in quick_compile_flags().items())


@pytest.mark.slow
def test_two_devices_match_one_device(tmp_path):
    script = TWO_DEVICE_SCRIPT.format(tests=str(TESTS), out=str(tmp_path))
    res = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
        env=subprocess_env(XLA_FLAGS=f"--xla_force_host_platform_device_count=2 {QUICK}", JAX_PLATFORMS="cpu"),
    )
    assert res.returncode == 0 and "OK" in res.stdout, res.stderr[-3000:]
    _, params = make_inputs()
    assert_matches_reference(pd.read_parquet(tmp_path / "one.parquet"), reference(params))


KILL_SCRIPT = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {tests!r})
    import jax
    import selfid_jax.runner.sweep as sweep
    from helpers_sweep import make_inputs, synthetic_fn

    def slow_fn(p):
        jax.debug.callback(lambda: time.sleep(0.4))
        return synthetic_fn(p)

    meta, params = make_inputs()
    sweep.run_chunked(slow_fn, params, chunk_size=5, out_dir={out!r}, meta=meta, progress=False)
    """
)


@pytest.mark.slow
def test_resume_after_kill(tmp_path):
    """SIGKILL mid-sweep leaves only whole chunk files; the re-run finishes the rest."""
    proc = subprocess.Popen(
        [sys.executable, "-c", KILL_SCRIPT.format(tests=str(TESTS), out=str(tmp_path))],
        env=subprocess_env(JAX_PLATFORMS="cpu", XLA_FLAGS=QUICK), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )
    chunk_dir = tmp_path / "chunks"
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and proc.poll() is None:
        if chunk_dir.is_dir() and len(list(chunk_dir.glob("chunk_*.parquet"))) >= 2:
            break
        time.sleep(0.05)
    assert proc.poll() is None, proc.stderr.read().decode()[-3000:]
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    proc.stderr.close()
    finished = sorted(int(p.stem.split("_")[1]) for p in chunk_dir.glob("chunk_*.parquet"))
    assert 2 <= len(finished) < 5 and not (tmp_path / "results.parquet").exists()

    meta, params = make_inputs()
    df = run_chunked(synthetic_fn, params, chunk_size=5, out_dir=tmp_path, meta=meta, progress=False)
    assert df.attrs["sweep"]["skipped"] == finished
    assert sorted(df.attrs["sweep"]["computed"] + finished) == [0, 1, 2, 3, 4]
    assert not list(chunk_dir.glob(".*.tmp"))
    assert_matches_reference(df, reference(params))


# --------------------------------------------------------------------------- CLI


@pytest.mark.slow
def test_cli_sweep_resume_plot_and_errors(tmp_path, capsys, monkeypatch):
    cfg = tmp_path / "synthetic.yaml"
    cfg.write_text("experiment: synthetic_cli_test\nchunk_size: 4\ngains: [0.3, 0.9]\nn_trials: 5\n")
    out = tmp_path / "run"
    args = ["sweep", str(cfg), "--out", str(out), "--no-progress"]

    # SIGTERM while chunk 0 is saved: the chunk in flight (1) is saved too, exit 143
    real_write = sweep._write_chunk
    calls = []

    def terminated_write(path, data):
        calls.append(path)
        real_write(path, data)
        if len(calls) == 1:
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(sweep, "_write_chunk", terminated_write)
    assert cli.main(args) == 143
    assert "resume" in capsys.readouterr().err
    chunk_dir = out / "parts" / "synthetic" / "chunks"
    assert sorted(p.name for p in chunk_dir.iterdir()) == ["chunk_00000.parquet", "chunk_00001.parquet"]
    assert signal.getsignal(signal.SIGTERM) is not None and not sweep._STOP.is_set()

    # Ctrl-C while the last chunk is being saved: exit 130, nothing half-written
    def interrupted_write(path, data):
        raise KeyboardInterrupt

    monkeypatch.setattr(sweep, "_write_chunk", interrupted_write)
    assert cli.main(args) == 130
    assert "resume" in capsys.readouterr().err
    monkeypatch.setattr(sweep, "_write_chunk", real_write)

    assert cli.main(args) == 0
    assert "2 gains" in capsys.readouterr().out  # the experiment's report
    assert RUNS[-1]["skipped"] == [0, 1] and RUNS[-1]["computed"] == [2]
    for name in ("config.yaml", "versions.json", "parts/synthetic/manifest.json", "results.parquet", "summary.json",
                 "figures/synthetic.png", "figures/synthetic.pdf"):
        assert (out / name).is_file(), name
    versions = json.loads((out / "versions.json").read_text())
    assert {"selfid_jax", "jax", "jaxlib", "mujoco", "numpy", "python", "git_revision", "devices"} <= set(versions)
    assert len(versions["resumed"]) == 2
    assert len(pd.read_parquet(out / "results.parquet")) == 10
    assert read_summary(out)["nan"] is None

    assert cli.main(args) == 0 and RUNS[-1]["computed"] == []  # finished: nothing recomputed

    # a different config must not mix into this run dir
    assert cli.main([*args, "--set", "n_trials=6"]) == 2
    err = capsys.readouterr().err
    assert "n_trials (was 5, now 6)" in err and "--fresh" in err and "Traceback" not in err
    assert cli.main([*args, "--set", "n_trials=6", "--fresh"]) == 0
    assert RUNS[-1]["computed"] == [0, 1, 2] and len(load_results(out)) == 12

    # plot redraws from saved results only
    for f in (out / "figures").iterdir():
        f.unlink()
    monkeypatch.setattr(sweep, "run_chunked", None)  # any simulation would now fail
    monkeypatch.setattr(experiment, "run", None)
    assert cli.main(["plot", str(out)]) == 0
    assert (out / "figures" / "synthetic.png").stat().st_size > 0


def test_cli_bad_input_exits_2(tmp_path, capsys):
    missing = tmp_path / "missing.yaml"
    assert cli.main(["sweep", str(missing)]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "not found" in err and "Traceback" not in err

    cfg = tmp_path / "bad.yaml"
    cfg.write_text("experiment: synthetic_cli_test\ngains: [0.3]\nn_trials: 0\ncolour: red\n")
    assert cli.main(["sweep", str(cfg), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert str(cfg) in err and "key 'n_trials'" in err and "key 'colour'" in err and "allowed" in err
    assert not (tmp_path / "r").exists()  # validated before anything is created

    assert cli.main(["plot", str(tmp_path / "no_run")]) == 2
    assert "not found" in capsys.readouterr().err

    cfg.write_text("experiment: not_installed\ngains: [0.3]\nn_trials: 1\n")
    assert cli.main(["sweep", str(cfg), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "unknown experiment 'not_installed'" in err and "valid_region" in err and "synthetic_cli_test" in err
