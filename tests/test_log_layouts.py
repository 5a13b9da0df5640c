"""Logs as labs write them: units, column names, time stamps, CSV dialects; and a fit that says how far to trust it.

Each variant is the shipped example log (a UR5e time series, selfid_jax/robot/data) rewritten the way a lab's
tools write it; read with the matching flag it must give the example's own estimate, to 1e-9; read without it, it
must be refused with a message that names the unit or the flag.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from selfid_jax.cli import main
from selfid_jax.commands.fit import example_log

ROS_NAMES = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
             "wrist_3_joint"]


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """The example log as a DataFrame and its fitted estimate (the reference of every variant)."""
    out = tmp_path_factory.mktemp("fit") / "base"
    assert main(["fit", "--example", "--out", str(out)]) == 0
    return pd.read_csv(example_log()), np.load(out / "inverse_jacobian.npz")["inverse_jacobian"]


def _fit(path, tmp_path, *flags):
    out = tmp_path / "out"
    code = main(["fit", str(path), "--out", str(out), *flags])
    return code, out


def _same(out, want):
    got = np.load(out / "inverse_jacobian.npz")["inverse_jacobian"]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    return json.loads((out / "summary.json").read_text())


def _error(capsys, path, tmp_path, *flags):
    code, _ = _fit(path, tmp_path, *flags)
    assert code == 2
    return capsys.readouterr().err


def _mm(df):
    df[["p_x", "p_y", "p_z"]] *= 1000.0
    return df


def _ros_ns(df):
    df["t"] = (1_700_000_000_000_000_000 + np.round(df["t"] * 1e9)).astype("int64")
    return df


def _deg(df):
    cols = [f"q_{i}" for i in range(6)]
    df[cols] = np.degrees(df[cols])
    return df


@pytest.mark.slow
@pytest.mark.parametrize("rewrite, guess, flag", [(_mm, "look like mm", ["--length", "mm"]),
                                                   (_ros_ns, "look like ns", ["--time", "ns"]),
                                                   (_deg, "look like degrees", ["--angle", "deg"])])
def test_other_units_are_refused_naming_the_unit_and_read_with_its_flag(base, tmp_path, capsys, rewrite, guess,
                                                                        flag):
    """Positions in mm, ROS nanosecond epoch stamps, joints in degrees: refused, naming the unit and the flag;
    read with the flag, the example's own estimate."""
    df, want = base
    path = tmp_path / "log.csv"
    rewrite(df.copy()).to_csv(path, index=False)
    err = _error(capsys, path, tmp_path)
    assert guess in err and " ".join(flag) in err and str(path) in err
    code, out = _fit(path, tmp_path, *flag)
    assert code == 0
    info = _same(out, want)
    assert flag[1] in info["converted_from"].values() and info["estimate_units"] == ["rad/m"] * 3


@pytest.mark.slow
def test_joint_numbering_names_quaternion_spelling_and_column_maps(base, tmp_path, capsys):
    df, want = base
    one = df.rename(columns={f"q_{i}": f"q_{i + 1}" for i in range(6)})  # joints numbered from 1
    one = one.rename(columns={"q_w": "qw", "q_x": "qx", "q_y": "qy", "q_z": "qz"})
    path = tmp_path / "one.csv"
    one.to_csv(path, index=False)
    code, out = _fit(path, tmp_path, "--task", "x,y,z")
    assert code == 0
    info = _same(out, want)
    assert any("numbered from 1" in n for n in info["notes"]) and any("qw" in n for n in info["notes"])

    ros = df.rename(columns={f"q_{i}": name for i, name in enumerate(ROS_NAMES)})
    path = tmp_path / "ros.csv"
    ros.to_csv(path, index=False)
    assert "no dtheta_0/V_0 (sample pairs) or q_0 (time series) column" in _error(capsys, path, tmp_path)
    code, out = _fit(path, tmp_path, "--joint-names", ",".join(ROS_NAMES))
    assert code == 0
    _same(out, want)
    shuffled = ROS_NAMES[1:] + ROS_NAMES[:1]  # another order is another actuator numbering: rows permuted
    code, out = _fit(path, tmp_path, "--joint-names", ",".join(shuffled))
    got = np.load(out / "inverse_jacobian.npz")["inverse_jacobian"]
    np.testing.assert_allclose(got, want[[1, 2, 3, 4, 5, 0]], rtol=1e-9, atol=1e-12)

    mapped = df.rename(columns={"p_x": "tx", "p_y": "ty", "p_z": "tz", "t": "stamp"})
    path = tmp_path / "mapped.csv"
    mapped.to_csv(path, index=False)
    (tmp_path / "map.yaml").write_text("tx: p_x\nty: p_y\ntz: p_z\nstamp: t\n")
    for spec in ("tx=p_x,ty=p_y,tz=p_z,stamp=t", str(tmp_path / "map.yaml")):
        code, out = _fit(path, tmp_path, "--columns", spec)
        assert code == 0
        _same(out, want)
    assert "--columns names 'nope', which is not a column" in _error(capsys, path, tmp_path, "--columns", "nope=t")


@pytest.mark.slow
def test_iso_times_units_row_and_semicolon_decimal_comma(base, tmp_path, capsys):
    df, want = base
    iso = df.copy()
    stamps = pd.Timestamp("2026-12-05T06:10:43Z") + pd.to_timedelta(np.round(df["t"] * 1e9), unit="ns")
    iso["t"] = stamps.dt.strftime("%Y-%m-%dT%H:%M:%S.%fZ")
    path = tmp_path / "iso.csv"
    iso.to_csv(path, index=False)
    code, out = _fit(path, tmp_path)
    assert code == 0
    info = _same(out, want)
    assert any("ISO 8601" in n for n in info["notes"])

    path = tmp_path / "units.csv"  # a units row under the header, positions in mm
    mm = df.copy()
    mm[["p_x", "p_y", "p_z"]] *= 1000.0
    units = ["s"] + ["rad"] * 6 + ["mm"] * 3 + [""] * 4
    path.write_text(",".join(df.columns) + "\n" + ",".join(units) + "\n" + mm.to_csv(index=False, header=False))
    code, out = _fit(path, tmp_path)
    assert code == 0
    _same(out, want)
    assert "by the units row but --length m" not in capsys.readouterr().err
    assert "column p_x is in mm by the units row but --length cm" in _error(capsys, path, tmp_path, "--length", "cm")

    path = tmp_path / "excel.csv"  # a European spreadsheet: ';' between fields, ',' in numbers
    path.write_text(df.to_csv(index=False, sep=";", decimal=","))
    code, out = _fit(path, tmp_path)
    assert code == 0
    _same(out, want)


@pytest.mark.slow
def test_a_fit_that_did_not_converge_exits_1_and_writes_no_estimate(base, tmp_path, capsys):
    df, _ = base
    short = tmp_path / "short.csv"
    df.iloc[:6].to_csv(short, index=False)
    out = tmp_path / "out"
    out.mkdir()
    (out / "inverse_jacobian.npz").write_bytes(b"an earlier fit's result")
    assert main(["fit", str(short), "--out", str(out)]) == 1
    assert not (out / "inverse_jacobian.npz").exists() and not (out / "inverse_jacobian.json").exists()
    info = json.loads((out / "summary.json").read_text())
    assert not info["converged"] and np.shape(info["estimate_so_far"]) == (6, 3)
    assert "no inverse Jacobian written" in capsys.readouterr().out


@pytest.mark.slow
def test_trust_figures_are_reported_and_strict_fails_on_a_warning(base, tmp_path, capsys):
    """The example's figures against independent numbers (the estimate's singular values); a log whose tracker
    is one row late (an unexplained motion) warns, and --strict turns the warning into exit 1."""
    df, want = base
    code, out = _fit(example_log(), tmp_path)
    info = json.loads((out / "summary.json").read_text())
    s = np.linalg.svd(want, compute_uv=False)
    assert info["condition"] == pytest.approx(s[0] / s[-1], rel=1e-9)
    assert 0 < info["heldout_error"] < 0.5 and info["warnings"] == [] and len(info["actuator_effect"]) == 6
    assert info["refused_fraction"] == pytest.approx(3 / 65)  # a NaN row, a duplicated stamp, a gap pair
    late = df.copy()
    late[["p_x", "p_y", "p_z"]] = late[["p_x", "p_y", "p_z"]].shift(2).bfill()  # the tracker two rows late
    path = tmp_path / "late.csv"
    late.to_csv(path, index=False)
    code, out = _fit(path, tmp_path)
    info = json.loads((out / "summary.json").read_text())
    assert info["heldout_error"] > 0.5 and any("held-out error" in w for w in info["warnings"])
    if code == 0:  # converged despite it: --strict refuses to call it a result
        assert _fit(path, tmp_path, "--strict")[0] == 1
    assert "warning: held-out error" in capsys.readouterr().out


def test_the_convergence_figure_stays_readable_with_refused_and_zero_steps():
    """Many exactly-zero steps (refused by the estimator): finite axis limits around the drawn values and the
    threshold, the threshold line drawn, every refused sample marked (was: an axis from 1e-300 to 1e13)."""
    from selfid_jax.commands.fit import draw_convergence

    T = 40
    deltas = 10.0 * 0.8 ** np.arange(T)
    accepted = np.ones(T, bool)
    accepted[::3] = False
    deltas[~accepted] = 0.0
    thresholds = np.full(T, 0.05)
    fig = draw_convergence(deltas, thresholds, eps=0.0, eps_rel=0.05, converged_at=30, title="t", accepted=accepted)
    ax = fig.axes[0]
    lo, hi = ax.get_ylim()
    shown = deltas[accepted]
    assert lo >= shown.min() / 10 and hi <= 10 * shown.max() and lo <= 0.05 <= hi
    lines = {line.get_gid(): line for line in ax.get_lines() if line.get_gid()}
    assert len(lines["threshold"].get_xdata()) == T
    assert len(lines["refused"].get_xdata()) == int((~accepted).sum())
