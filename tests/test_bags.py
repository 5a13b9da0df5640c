"""``read_bag``: ROS 1 / ROS 2 (sqlite3, mcap) bags and ``.mcap`` files -> the raw time-series table, matched by
header stamps.

The bags are written here with rosbags' own writers from one synthetic recording: a linear arm ``p = p0 + A q``
(constant orientation) whose three joints (ROS names, published in another order than the model's) hold still
and step by up to 0.03 rad every 0.5 s. Joint states at 100 Hz with stamp jitter and a 0.2 s recording gap, a
gripper publishing other joints on the same topic, one repeated stamp; the tracker at 50 Hz, 3 ms off the joints'
grid and starting before / ending after them. Receive times carry random latencies (0-25 ms joints, 40-120 ms
tracker), so the bag's order is not the stamps' and matching by arrival would pair poses with the wrong joints.
"""

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers_logs import (  # tests/ is on the path
    ARM,
    GAP,
    NS,
    P0,
    PUBLISHED,
    QUAT,
    REC,
    T0,
    TRACKER_TYPE,
    A,
    write_bag,
)
from rosbags.highlevel import AnyReader

from selfid_jax.robot import offline
from selfid_jax.robot.bags import BagInfo, read_bag
from selfid_jax.robot.log import LogError, samples_from_table


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """The recording as a ROS 1 bag, ROS 2 sqlite3 and mcap bags, and the mcap bag's file on its own."""
    root = tmp_path_factory.mktemp("bags")
    out = {fmt: write_bag(root / name, fmt) for fmt, name in
           (("ros1", "rec.bag"), ("sqlite3", "rec_sqlite3"), ("mcap", "rec_mcap"))}
    (mcap,) = out["mcap"].glob("*.mcap")
    out["mcap_file"] = Path(shutil.copy(mcap, root / "standalone.mcap"))
    return out


def _read(path, **kw):
    kw = {"joints": "/joint_states", "tracker": "/tracker", **kw}
    return read_bag(path, **kw)


def _kept_stamps():
    """Tracker stamps inside the joint span and not across the recording gap, and the drop counts."""
    tj, tt = np.sort(np.unique(REC["tj"])), REC["tt"]
    outside = (tt < tj[0]) | (tt > tj[-1])
    gap_lo, gap_hi = REC["tj"][GAP.start - 1], REC["tj"][GAP.start]  # the joint samples either side of the gap
    skewed = ~outside & (tt > gap_lo) & (tt < gap_hi)
    assert skewed.sum() == 10 and outside.sum() == 5 + 11  # both kinds to drop: poses in the gap, before and after
    return tt[~outside & ~skewed], int(outside.sum()), int(skewed.sum())


def test_bag_order_is_not_stamp_order(bags):
    """The premise: in every bag the receive order differs from the stamp order (so a reader must sort and match
    by stamps)."""
    with AnyReader([bags["sqlite3"]]) as reader:
        conns = [c for c in reader.connections if c.topic == "/tracker"]
        stamps = [reader.deserialize(raw, c.msgtype).header.stamp for c, _, raw in reader.messages(conns)]
    ns = np.array([s.sec * NS + s.nanosec for s in stamps])
    assert (np.diff(ns) < 0).sum() > 50


def test_table_columns_order_counts_and_interpolation(bags):
    table, info = _read(bags["ros1"], joint_names=list(ARM))
    kept, outside, skewed = _kept_stamps()
    T = kept.size
    assert list(table) == ["t", "q_0", "q_1", "q_2", "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z"]
    assert all(v.shape == (T,) and v.dtype == np.float64 for v in table.values())
    np.testing.assert_array_equal(table["t"], kept / NS)  # stamps, nothing subtracted, in stamp order
    assert np.all(np.diff(table["t"]) > 0)
    # joints in the requested (model) order, linearly interpolated at each pose's stamp between the joint samples
    rel = lambda s: (s - T0).astype(np.float64)  # relative ns: float64 keeps them exact
    for i in range(3):
        np.testing.assert_allclose(table[f"q_{i}"], np.interp(rel(kept), rel(REC["tj"]), REC["qj"][:, i]),
                                   rtol=0, atol=1e-12)
    poses = np.array([p for s, _, p in REC["tracker"] if s in set(kept)])
    np.testing.assert_array_equal(np.stack([table[c] for c in ("p_x", "p_y", "p_z")], axis=1), poses)
    np.testing.assert_array_equal(np.stack([table[c] for c in ("q_w", "q_x", "q_y", "q_z")], axis=1),
                                  np.broadcast_to(QUAT, (T, 4)))
    # a pose between two joint samples (not at one) is a weighted mean, not either sample
    mid = np.flatnonzero(np.abs(np.diff(table["q_0"])) > 0)[0] + 1
    assert not np.isin(table["q_0"][mid], REC["qj"][:, 0])
    assert info == BagInfo(
        source=str(bags["ros1"]), joint_names=ARM, tracker_type=TRACKER_TYPE["pose"], frame="world", child_frame=None,
        joint_messages=len(REC["joints"]), duplicate_joint_stamps=1, other_joint_messages=len(REC["gripper"]),
        tracker_messages=len(REC["tracker"]), rows=T, outside_span=outside, skewed=skewed, max_skew=info.max_skew,
        joint_period=info.joint_period, tracker_period=0.02)
    assert abs(info.joint_period - 0.01) < 2e-4 and info.max_skew == 3 * info.joint_period
    assert info.lines()[0] == f"{bags['ros1']}: {T} rows" and len(info.lines()) == 7


@pytest.mark.slow
def test_default_joint_order_is_the_first_messages(bags):
    by_model, _ = _read(bags["mcap"], joint_names=ARM)
    by_message, info = _read(bags["mcap"])
    assert info.joint_names == PUBLISHED
    for i, name in enumerate(PUBLISHED):
        np.testing.assert_array_equal(by_message[f"q_{i}"], by_model[f"q_{ARM.index(name)}"])
    comma, _ = _read(bags["mcap"], joint_names="shoulder_pan_joint, shoulder_lift_joint,elbow_joint")
    np.testing.assert_array_equal(comma["q_2"], by_model["q_2"])
    single, info = _read(bags["mcap"], joint_names=["elbow_joint"])
    assert [c for c in single if c.startswith("q_") and c[2:].isdigit()] == ["q_0"]
    np.testing.assert_array_equal(single["q_0"], by_model["q_2"])
    gripper, info = _read(bags["mcap"], joint_names=["finger_joint"])  # the other publisher, on its own
    assert info.other_joint_messages == len(REC["joints"]) and np.all(gripper["q_0"] == 0.04)


@pytest.mark.slow
def test_every_format_gives_the_same_table(bags):
    """ROS 1, ROS 2 sqlite3, ROS 2 mcap and the bare .mcap file: the same table to 1e-12 (in fact bit for bit) and
    the same counts."""
    ref, ref_info = _read(bags["ros1"], joint_names=ARM)
    for fmt in ("sqlite3", "mcap", "mcap_file"):
        table, info = _read(bags[fmt], joint_names=ARM)
        assert list(table) == list(ref)
        for c in ref:
            np.testing.assert_allclose(table[c], ref[c], rtol=0, atol=1e-12, err_msg=f"{fmt}: {c}")
        assert info._replace(source="") == ref_info._replace(source=""), fmt


@pytest.mark.slow
def test_fit_recovers_the_inverse_jacobian(bags):
    """``A J_hat = I``: the pose is exactly linear in the joints, and the joints ramp linearly between samples, so
    every pair (dtheta, V) satisfies V = A dtheta up to float64 rounding of ~1 m positions (~1e-16 m against steps
    of ~1e-2 m: relative ~1e-14, times cond(A) ~ 2). Bound 1e-9, as tests/test_fit.py's exact-data TOL. Matching by
    arrival instead (poses 40-120 ms late) pairs poses with the wrong side of a step: ||A J_hat - I||_F = 1.7 on this
    recording."""
    table, _ = _read(bags["sqlite3"], joint_names=ARM)
    samples = samples_from_table(table, task="x,y,z", source="rec_sqlite3")
    moving = np.abs(samples.dtheta).sum(axis=1) > 0
    assert moving.sum() >= 19  # every step, some split over two pairs by a pose between its joint samples
    np.testing.assert_allclose(samples.V, samples.dtheta @ A.T, rtol=0, atol=1e-13)
    result = offline.fit(samples)
    assert result.estimate.shape == (3, 3)
    assert np.linalg.norm(A @ result.estimate - np.eye(3)) < 1e-9


@pytest.mark.parametrize("kind", ["transform", "tf"])
def test_transform_and_tf_topics_with_child_frame(tmp_path, bags, kind):
    ref, _ = _read(bags["mcap"], joint_names=ARM)
    path = write_bag(tmp_path / "tf_bag", "mcap", tracker=kind)
    table, info = _read(path, joint_names=ARM, child_frame="/tool_marker")  # ROS 1 tf's leading "/" is ignored
    assert (info.tracker_type, info.frame, info.child_frame) == (TRACKER_TYPE[kind], "world", "tool_marker")
    assert info.tracker_messages == len(REC["tracker"])
    for c in ref:
        np.testing.assert_array_equal(table[c], ref[c])
    if kind == "transform":  # one child frame: it need not be named
        np.testing.assert_array_equal(_read(path, joint_names=ARM)[0]["p_x"], ref["p_x"])
    else:
        with pytest.raises(LogError, match=r"tf_bag: topic /tracker is a tf2_msgs/msg/TFMessage: name the tracked "
                           r"frame with child_frame; its child frames are: table_marker \(516 transforms\), "
                           r"tool_marker \(516 transforms\)$"):
            _read(path)


def _tiny(n=4, joint_stamps=None, tracker_offset=3_000_000):
    """A 4-message recording for the error cases."""
    tj = T0 + np.arange(n) * 10_000_000 if joint_stamps is None else np.asarray(joint_stamps)
    joints = [(int(s), int(s) + 1, ARM, [0.1 * i, 0.0, 0.0]) for i, s in enumerate(tj)]
    tracker = [(int(s) + tracker_offset, int(s) + 2, P0) for s in tj[:-1]]
    return dict(joints=joints, gripper=[], tracker=tracker)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny")
    return {"ros1": write_bag(root / "tiny.bag", "ros1", rec=_tiny(), extra=[("/empty", "sensor_msgs/msg/JointState")]),
            "tf": write_bag(root / "tiny_tf", "sqlite3", tracker="tf", rec=_tiny()),
            "clock": write_bag(root / "clock.bag", "ros1", rec=_tiny(tracker_offset=-3600 * NS)),
            "unstamped": write_bag(root / "unstamped.bag", "ros1", rec=_tiny(joint_stamps=[0, 0, 0, 0]))}


def test_a_pose_at_a_joint_stamp_takes_that_sample(tmp_path):
    """A pose stamped exactly at a joint message (the last one included) takes its positions, however far the
    next joint message is (max_skew bounds brackets only)."""
    rec = _tiny(joint_stamps=T0 + np.array([0, 10, 20, 500]) * 1_000_000)  # a 0.48 s gap before the last sample
    rec["tracker"] = [(s, r + 1, P0 + i) for i, (s, r, _, _) in enumerate(rec["joints"])]
    rec["tracker"].append((T0 + 100_000_000, T0 + 5, P0))  # inside the gap: dropped
    table, info = _read(write_bag(tmp_path / "exact.bag", "ros1", rec=rec))
    np.testing.assert_array_equal(table["q_0"], [0.1 * i for i in range(4)])
    np.testing.assert_array_equal(table["p_x"], P0[0] + np.arange(4))
    assert (info.rows, info.skewed, info.outside_span) == (4, 1, 0) and info.max_skew == pytest.approx(0.03)


ERRORS = [
    ("ros1", dict(joints="/js"), r"tiny\.bag: no topic /js \(the joint states\); the bag has: /empty "
     r"\(sensor_msgs/msg/JointState\), /joint_states \(sensor_msgs/msg/JointState\), /tracker "
     r"\(geometry_msgs/msg/PoseStamped\)$"),
    ("ros1", dict(tracker="/joint_states"), r"tiny\.bag: topic /joint_states is sensor_msgs/msg/JointState; the "
     r"tracker must be one of geometry_msgs/msg/PoseStamped, geometry_msgs/msg/TransformStamped, "
     r"tf2_msgs/msg/TFMessage$"),
    ("ros1", dict(joints="/tracker"), r"topic /tracker is geometry_msgs/msg/PoseStamped; the joint states must be "
     r"sensor_msgs/msg/JointState$"),
    ("ros1", dict(joints="/empty"), r"tiny\.bag: topic /empty \(the joint states\) has no messages$"),
    ("ros1", dict(joint_names=["shoulder_pan_joint", "wrist_9_joint"]), r"tiny\.bag: topic /joint_states: joint "
     r"wrist_9_joint is not in message 1 \(stamp 1700000000\.123456789 s\), whose joints are shoulder_pan_joint, "
     r"shoulder_lift_joint, elbow_joint$"),
    ("ros1", dict(joint_names=["wrist_9_joint"]), r"topic /joint_states: no message names the joints wrist_9_joint; "
     r"the messages name elbow_joint, shoulder_lift_joint, shoulder_pan_joint$"),
    ("ros1", dict(child_frame="tool_marker"), r"topic /tracker is a geometry_msgs/msg/PoseStamped, which has no "
     r"child frame; drop child_frame='tool_marker'$"),
    ("tf", dict(child_frame="hand"), r"tiny_tf: topic /tracker has no transform of child frame hand; its child "
     r"frames are: table_marker \(3 transforms\), tool_marker \(3 transforms\)$"),
    ("ros1", dict(max_skew=1e-3), r"tiny\.bag: no pose on /tracker could be matched to the joint positions on "
     r"/joint_states: 0 outside the joint messages' span, 3 between joint messages more than 0\.001 s apart "
     r"\(max_skew\)$"),
    ("clock", {}, r"clock\.bag: no pose on /tracker could be matched .*: the poses' stamps \(1699996400\.123456789 "
     r"s \.\. 1699996400\.143456789 s\) lie outside the joint messages' \(1700000000\.123456789 s \.\. "
     r"1700000000\.153456789 s\); are the two stamped by different clocks\?$"),
    ("unstamped", {}, r"topic /joint_states: the 4 joint messages all have the stamp 0\.000000000 s \(header\.stamp "
     r"is 0: the publisher does not stamp its messages\); matching by stamp needs at least two distinct ones$"),
]


@pytest.mark.parametrize("bag, options, message", ERRORS, ids=[f"{b}-{'-'.join(o) or 'none'}" for b, o, _ in ERRORS])
def test_errors_name_the_file_and_topic(tiny, bag, options, message):
    with pytest.raises(LogError, match=message) as err:
        _read(tiny[bag], **options)
    assert "\n" not in str(err.value) and str(err.value).startswith(str(tiny[bag]))


def test_paths_that_are_not_bags(tmp_path, monkeypatch, tiny):
    with pytest.raises(LogError, match=r"nothing\.bag: no such file or folder$"):
        _read(tmp_path / "nothing.bag")
    with pytest.raises(LogError, match=r"log\.csv: not a ROS bag: expected a ROS 1 \.bag, a ROS 2 bag folder or a "
                       r"\.mcap/\.db3 file, got '\.csv'$"):
        _read(Path(shutil.copy(tiny["ros1"], tmp_path / "log.csv")))
    with pytest.raises(LogError, match=r"a folder without metadata\.yaml is not a ROS 2 bag$"):
        _read(tmp_path)
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all\n" * 8)
    with pytest.raises(LogError, match=r"junk\.bag: cannot read as a ROS bag: "):
        _read(tmp_path / "junk.bag")
    with pytest.raises(ValueError, match=r"max_skew must be a positive number of seconds, got -1"):
        _read(tiny["ros1"], max_skew=-1)
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # as if rosbags were not installed
    with pytest.raises(LogError, match=r'tiny\.bag: reading ROS bags needs the rosbags package: '
                       r'pip install "selfid-jax\[ros\]"$'):
        _read(tiny["ros1"])


@pytest.mark.slow
def test_selfid_jax_fit_reads_every_format_like_the_csv_of_the_same_data(bags, tmp_path, capsys):
    """selfid-jax fit BAG --joints --tracker: ROS 1, ROS 2 sqlite3, ROS 2 mcap and the bare .mcap give the estimate
    of the CSV of the same table, to 1e-9, and A Ĵ = I to 1e-6; without the topics the bag is refused by name."""
    import pandas as pd

    from selfid_jax.cli import main

    table, _ = _read(bags["sqlite3"], joint_names=ARM)
    csv = tmp_path / "same.csv"
    pd.DataFrame(table).to_csv(csv, index=False, float_format="%.17g")
    assert main(["fit", str(csv), "--out", str(tmp_path / "csv")]) == 0
    want = np.load(tmp_path / "csv" / "inverse_jacobian.npz")["inverse_jacobian"]
    assert np.linalg.norm(A @ want - np.eye(3)) < 1e-6
    for fmt, path in bags.items():
        out = tmp_path / fmt
        assert main(["fit", str(path), "--joints", "/joint_states", "--tracker", "/tracker", "--joint-names",
                     ",".join(ARM), "--out", str(out)]) == 0, fmt
        got = np.load(out / "inverse_jacobian.npz")["inverse_jacobian"]
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12, err_msg=fmt)
    assert "bag: " in capsys.readouterr().out
    assert main(["fit", str(bags["ros1"]), "--out", str(tmp_path / "x")]) == 2
    assert "a bag needs --joints TOPIC" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("step_s, kind", [(-2.0, "pose"), (2.0, "pose"), (-2.0, "tf")])
def test_a_tracker_clock_that_steps_is_reported_and_dropped_not_resorted(tmp_path, step_s, kind):
    """Issue 54: the tracker's clock steps back (or jumps ahead) 2 s inside a bag. Sorted by stamp, its later poses
    were matched to the joints of 2 s earlier (later) without a word (A Jhat off by 0.70); now they are dropped and
    counted, as a CSV's backwards rows are, and the rest gives the bag's answer."""
    at = 300  # tracker messages from this one on carry the stepped clock (216 of 516: the majority keeps pace)
    tracker = [(s + int(step_s * NS) if i >= at else s, r, p) for i, (s, r, p) in enumerate(REC["tracker"])]
    fmt, name = ("ros1", "stepped.bag") if kind == "pose" else ("mcap", "stepped")  # ROS 2 types for /tf
    bag = write_bag(tmp_path / name, fmt, tracker=kind, rec={**REC, "tracker": tracker})
    frame = {"child_frame": "tool_marker"} if kind == "tf" else {}
    table, info = _read(bag, joint_names=ARM, **frame)
    assert info.clock_steps == len(tracker) - at and info.joint_clock_steps == 0
    assert "step off the bag's clock by more than 0.5 s" in "\n".join(info.lines())
    assert f"/tracker stamp {(REC['tracker'][at][0] + int(step_s * NS)) // NS}." in info.clock_step_first
    assert np.all(table["t"] < REC["tt"][at] / NS)  # only the poses before the step
    result = offline.fit(bag, joints="/joint_states", tracker="/tracker", joint_names=ARM, **frame)
    assert np.linalg.norm(A @ result.estimate - np.eye(3)) < 1e-6


def test_a_joint_clock_that_steps_is_reported_and_dropped(tmp_path):
    joints = [(s - 2 * NS if i >= 700 else s, r, n, q) for i, (s, r, n, q) in enumerate(REC["joints"])]
    bag = write_bag(tmp_path / "stepped.bag", "ros1", rec={**REC, "joints": joints})
    _, info = _read(bag, joint_names=ARM)
    assert info.joint_clock_steps == len(joints) - 700 and info.clock_steps == 0
    assert "joint messages whose stamps step off the bag's clock" in "\n".join(info.lines())
