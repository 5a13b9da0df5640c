"""Any log a lab records -> self-ID sample pairs, and a report of how it was read (``sj.fit`` and ``selfid-jax fit``).

:func:`read_log` is the one reader behind :func:`selfid_jax.robot.offline.fit`
and the ``selfid-jax fit`` command, so both read a log the same way:

1. the table: a CSV, Parquet or NPZ file (:func:`selfid_jax.robot.log.read_table_units`,
   with a CSV's units row), a ROS 1/2 bag or MCAP file (:func:`selfid_jax.robot.bags.read_bag`,
   ``joints`` and ``tracker`` topics; or ``joints`` and a ``camera`` image
   topic tracked as ``tag``: :func:`selfid_jax.robot.camera.sources.bag_camera_table`),
   or a table given from Python (a mapping of column -> 1-D array, a ``pandas.DataFrame``);
2. its layout and units (:func:`selfid_jax.robot.log.prepare_table`: a column
   map, joint names, declared units or a units row, converted to m, s, rad);
   with ``video`` (a video or a folder of images, ``frame_times``,
   ``camera_info``, ``tag``), the camera's tag poses become the joint log's
   tracker columns, matched by time
   (:func:`selfid_jax.robot.camera.sources.video_camera_table`);
3. a raw time series logged continuously is reduced to one settled row per
   move (or, where the arm never rests, one row per edge of short windows of
   its motion), the tracker latency taken out (:func:`selfid_jax.robot.streams.reduce_stream`);
4. the rows paired into samples, bad rows dropped and counted
   (:func:`selfid_jax.robot.log.samples_from_table`: task axes, time window, gap limit).

Its options are one :class:`~selfid_jax.robot.fit_options.ReadOptions` value
whose defaults are the command's (:mod:`selfid_jax.robot.fit_options`); what was
done comes back as a :class:`ReadReport` (notes, units, the bag's and the
stream's figures). Loading this module loads neither numpy nor JAX (they
come when a log is read).
"""

from __future__ import annotations

from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from selfid_jax.robot.fit_options import ReadOptions

if TYPE_CHECKING:
    from selfid_jax.robot.bags import BagInfo
    from selfid_jax.robot.camera.sources import CameraReport
    from selfid_jax.robot.log import Samples
    from selfid_jax.robot.streams import StreamInfo

__all__ = ["BAG_SUFFIXES", "EXAMPLE_LOG", "ReadReport", "example_log", "is_bag", "read_log"]

EXAMPLE_LOG = "ur5e_example_log.csv"
"""The shipped example log (``selfid_jax/robot/data``; ``scripts/make_example_log.py``)."""
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
"""A file with one of these suffixes (or a folder) is read as a ROS bag (:func:`is_bag`)."""


def example_log() -> Path:
    """Path of the shipped example: a UR5e time series with a few bad rows (``scripts/make_example_log.py``)."""
    return Path(str(resources.files("selfid_jax.robot") / "data" / EXAMPLE_LOG))


def is_bag(path: str | Path) -> bool:
    """A ROS 1 bag, a ROS 2 bag folder or an MCAP/db3 file (read by :mod:`selfid_jax.robot.bags`)."""
    path = Path(path)
    return path.is_dir() or path.suffix.lower() in BAG_SUFFIXES


class ReadReport(NamedTuple):
    """How :func:`read_log` read a log: what a printout and ``summary.json`` say about it."""

    source: str  # the file (or "<table>")
    notes: tuple[str, ...]  # one line per thing done to the layout: a bag read, columns renamed, units converted,
    #   a continuous stream reduced (and why a step was not taken)
    units: dict[str, str]  # column -> the unit it was read in (every one converted to m, s, rad)
    bag: BagInfo | None  # what read_bag matched and dropped; None for a table
    stream: StreamInfo | None  # what reduce_stream did; None where the log is not a raw time series
    camera: CameraReport | None = None  # what the camera gave (frames, dropouts, tag, intrinsics); None without one


def read_log(log: str | Path | Mapping[str, Any], options: ReadOptions | None = None, **kwargs: Any
             ) -> tuple[Samples, ReadReport]:
    """The sample pairs ``dtheta (T, n)``, ``V (T, m)`` of a log and how it was read: ``(samples, report)``.

    ``log``: a CSV, Parquet or NPZ file, a ROS 1 ``.bag``, a ROS 2 bag folder,
    an ``.mcap``/``.db3`` file (``joints`` and ``tracker`` topics needed, or
    ``joints``, ``camera`` and ``tag``), or a table of columns (a mapping, a
    ``pandas.DataFrame``; with ``video``, ``frame_times``, ``camera_info``
    and ``tag``, the joint log of a camera's frames). ``options`` (or
    its fields as keywords, which override it): :class:`~selfid_jax.robot.fit_options.ReadOptions`.
    Every value is converted to m, s and rad (``samples``: float64).

    Raises:
      LogError: the log cannot be used (one line naming the file, column, row or topic).
      ValueError: an option out of range (naming the keyword and flag), checked before the log is read.
      TypeError: a keyword that is not a ``ReadOptions`` field.
    """
    unknown = sorted(set(kwargs) - set(ReadOptions._fields))
    if unknown:
        raise TypeError(f"read_log: unknown option {unknown[0]!r}; the options are {', '.join(ReadOptions._fields)}")
    opts = (options or ReadOptions())._replace(**kwargs).check()
    if opts.tag is not None:  # the family and id against OpenCV's dictionaries, before anything is read
        from selfid_jax.robot.camera.sources import tag_settings

        tag_settings(opts)
    from selfid_jax.robot.log import LogError, prepare_table, read_table_units, samples_from_table
    from selfid_jax.robot.tables import Units

    path = Path(log) if isinstance(log, (str, Path)) else None
    source = str(log) if path is not None else "<table>"
    notes: list[str] = []
    names = opts.joint_names
    bag_info: BagInfo | None = None
    row_units: dict[str, str] = {}
    table: Mapping[str, Any]
    camera: CameraReport | None = None
    if path is not None and is_bag(path):
        from selfid_jax.robot.bags import read_bag

        if opts.video is not None:
            raise LogError(f"{source}: --video (video=) goes with a table log (CSV, Parquet, NPZ); in a bag, name "
                           "the image topic with --camera")
        if not (opts.joints and (opts.tracker or opts.camera)):
            raise LogError(f"{source}: a bag needs --joints TOPIC (sensor_msgs/JointState) and --tracker TOPIC "
                           "(joints=, tracker=), or --camera TOPIC and --tag (camera=, tag=) for an image topic")
        if opts.camera:
            from selfid_jax.robot.camera.sources import bag_camera_table

            table, bag_info, camera = bag_camera_table(path, opts)
        else:
            assert opts.tracker is not None
            table, bag_info = read_bag(path, joints=opts.joints, tracker=opts.tracker,
                                       joint_names=None if names is None else list(names),
                                       child_frame=opts.child_frame)
        notes += [f"bag: {line.strip()}" for line in bag_info.lines()]
        names = None  # the bag's columns are q_0.. already, in joint_names order
    else:
        if opts.joints or opts.tracker or opts.child_frame or opts.camera:
            raise LogError(f"{source}: --joints, --tracker, --child-frame and --camera (joints=, tracker=, "
                           "child_frame=, camera=) are for a ROS bag or MCAP file")
        if isinstance(log, (str, Path)):
            table, row_units = read_table_units(log)
        elif isinstance(log, Mapping) or hasattr(log, "keys"):  # a DataFrame is no Mapping, but has its keys
            table = log
        else:
            raise TypeError(f"log: expected a file path or a table of columns (a mapping, a DataFrame), got "
                            f"{type(log).__name__}")
    table, more, units = prepare_table(table, columns=opts.columns, joint_names=names,
                                       units=Units(opts.length, opts.time, opts.angle), row_units=row_units,
                                       source=source)
    notes += more
    converted = {k: v for k, v in units.items() if v not in ("m", "s", "rad")}
    if converted:
        notes.append("converted to m, s, rad: " + ", ".join(f"{k} [{v}]" for k, v in converted.items()))
    if opts.video is not None:
        from selfid_jax.robot.camera.sources import video_camera_table

        table, camera, more = video_camera_table(table, opts, source)
        notes += more
    if camera is not None:
        notes += camera.lines()
    table, stream_info = _reduce(table, opts, source)
    if stream_info is not None:
        if stream_info.continuous:
            notes.append(stream_info.line())
        notes += list(stream_info.notes)
    samples = samples_from_table(table, task=opts.task, task_dim=opts.task_dim, start=opts.start, stop=opts.stop,
                                 max_gap=opts.max_gap, source=source)
    return samples, ReadReport(source, tuple(notes), dict(units), bag_info, stream_info, camera)


def _reduce(table: Mapping[str, Any], opts: ReadOptions, source: str) -> tuple[Mapping[str, Any], StreamInfo | None]:
    """A raw time series reduced to one settled row per move (or per window edge, without rests) where it is a
    stream (``opts.mode``); other layouts unchanged, with None."""
    from selfid_jax.robot import streams
    from selfid_jax.robot.log import LogError

    q_cols = sorted((c for c in table if c.startswith("q_") and c[2:].isdigit()), key=lambda c: int(c[2:]))
    if not (q_cols and "t" in table):
        return table, None
    quat = [c for c in ("q_w", "q_x", "q_y", "q_z") if c in table]
    rotvec = [c for c in ("r_x", "r_y", "r_z") if c in table]
    pose = [c for c in ("p_x", "p_y", "p_z") if c in table] + quat + rotvec
    try:
        return streams.reduce_stream(table, q_cols, pose, mode=opts.mode, latency=opts.latency,
                                     v_tol=opts.settle_speed, min_settle_s=opts.settle_time,
                                     quat_cols=quat or None, rotvec_cols=rotvec or None)
    except ValueError as err:
        raise LogError(f"{source}: {err}") from None
