"""Units that cannot be swapped silently (issue 54, item 3): a log's motion per move against its declared units, and
multi-turn joints under a stated ``--angle rad``.

The log is tests/helpers_logs.py's 100 Hz UR5e stream (metres, radians, 40 moves of up to 0.03 rad per joint).
"""

import numpy as np
import pytest
from helpers_logs import _J, POS_COLS, Q_COLS, _stream  # tests/ is on the path

import selfid_jax as sj
from selfid_jax.robot.log import LogError
from selfid_jax.robot.quality import MAX_LEVER_M_PER_RAD, MIN_LEVER_M_PER_RAD, unit_warnings


@pytest.fixture(scope="module")
def stream():
    return _stream(seed=1)[0]


def _error(result):
    return float(np.linalg.norm(_J() @ result.estimate - np.eye(3)))


@pytest.mark.slow
def test_the_stream_in_its_own_units_has_no_unit_warning(stream):
    result = sj.fit(stream)
    assert _error(result) < 0.2
    assert result.warnings == ()


@pytest.mark.parametrize("declared, words", [
    (dict(length="mm"), "is the length unit m (or cm), not mm?"),  # the issue: Jhat 1000x too large, no warning
    (dict(angle="deg"), "is the angle unit rad, not deg?"),  # the issue: Jhat 57x too small, no warning
])
def test_a_swapped_unit_is_a_trust_warning_naming_it(stream, declared, words):
    result = sj.fit(stream, **declared)
    assert any(words in w for w in result.warnings), result.warnings
    assert result.warnings[0].startswith("tracked motion ")


def test_degrees_read_as_radians_are_refused_or_flagged(stream):
    deg = dict(stream)
    deg.update({c: np.degrees(stream[c]) for c in Q_COLS})
    with pytest.raises(LogError, match="no angle unit was stated"):  # UR5e home: joints beyond two turns in degrees
        sj.fit(deg)
    small = dict(deg)  # joints near zero in degrees: no magnitude gives them away, the moves do
    small.update({c: deg[c] - deg[c][0] for c in Q_COLS})
    small.update({c: stream[c] - stream[c][0] for c in POS_COLS})
    result = sj.fit(small, angle="rad")
    assert any("is the angle unit deg, not rad?" in w for w in result.warnings), result.warnings


def test_unit_warnings_bounds():
    rng = np.random.default_rng(0)
    D = rng.uniform(-0.03, 0.03, (30, 6))
    J = rng.normal(size=(3, 6)) * 0.3
    assert unit_warnings(D, D @ J.T, (0, 1, 2)) == ()
    assert "not mm?" in unit_warnings(D, 1e-3 * D @ J.T, (0, 1, 2), {"p_x": "mm"})[0]
    assert "not m?" in unit_warnings(D, 1e3 * D @ J.T, (0, 1, 2), {"p_x": "m"})[0]
    assert unit_warnings(D, 1e-3 * D @ J.T, None) == ()  # unnamed V columns: not checked
    assert unit_warnings(D, 1e-3 * D @ J.T, (3, 4, 5)) == ()  # rotation axes: no length
    assert MIN_LEVER_M_PER_RAD < 0.3 < MAX_LEVER_M_PER_RAD


@pytest.mark.slow
def test_a_multi_turn_joint_is_read_under_a_stated_rad(stream):
    turned = dict(stream)
    turned["q_0"] = stream["q_0"] + 4 * np.pi + 3.7  # 16.3 rad: a joint that has turned more than twice
    with pytest.raises(LogError) as err:  # unstated: refused, and the message names both readings
        sj.fit(turned)
    assert "--angle rad if a joint turns more than twice" in str(err.value)
    assert "--angle deg" in str(err.value)
    result = sj.fit(turned, angle="rad")  # the issue: refused as "looks like degrees" even with --angle rad
    assert _error(result) < 0.2 and result.warnings == ()
    wrong = sj.fit(turned, angle="deg")  # the old message's advice: now a warning, not a silent 57x
    assert any("is the angle unit rad, not deg?" in w for w in wrong.warnings)


def test_a_units_row_in_rad_states_the_unit(tmp_path, stream):
    import pandas as pd

    turned = dict(stream)
    turned["q_0"] = stream["q_0"] + 4 * np.pi + 3.7
    path = tmp_path / "log.csv"
    df = pd.DataFrame(turned)
    with open(path, "w") as f:
        f.write(",".join(df.columns) + "\n" + ",".join("s" if c == "t" else "rad" if c.startswith("q_") else "m"
                                                       for c in df.columns) + "\n")
        df.to_csv(f, header=False, index=False)
    assert _error(sj.fit(path)) < 0.2
