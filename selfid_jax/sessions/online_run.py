"""An online session from a config into a run directory: connect, self-ID live (and follow), write its files.

:func:`run_session` is ``selfid-jax online`` without the command line: from
an :class:`~selfid_jax.sessions.online_config.OnlineConfig` (read with
:func:`~selfid_jax.sessions.online_config.load_online_config`) it checks the
options and the run directory, takes the run directory's lock, opens the
camera of a ``tracker`` section (:func:`open_camera`: before the robot is
reached, and nothing moves before its first frame), connects
(:func:`selfid_jax.robot.drivers.connect`; with a camera, the driver behind
:class:`~selfid_jax.robot.camera.live.CameraTracked`), checks the per-actuator values
against the robot, writes ``online_config.json`` (the resolved config), runs
:func:`selfid_jax.robot.live.run_online` (the session log ``session.jsonl``
is appended as it happens) and writes, each whole
(:mod:`selfid_jax.runner.files`), ``summary.json`` (status, counts, step
latency; with a camera, its frames and dropouts by reason), for a converged
session only ``inverse_jacobian.npz`` / ``.json``
(the estimate, as ``selfid-jax fit`` writes it), and the figures
(:mod:`selfid_jax.sessions.online_figures`, from the log). It returns the
:class:`~selfid_jax.robot.live.OnlineResult` and the files written; a
session's own stop (a safety stop, a lost connection) is the result's
``status``, not an exception. Bad input (config, run directory, a log that
disagrees) raises :class:`~selfid_jax.runner.errors.ConfigError` before any
motion.

Under the console script's signal handling (:mod:`selfid_jax.runner.signals`)
a first SIGTERM or Ctrl-C stops the session after the move in flight and a
second one ends the process after appending a ``killed`` stop record; without
it, Ctrl-C (KeyboardInterrupt) stops the session as ``interrupted``.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from selfid_jax.sessions.online_config import OnlineConfig, options

if TYPE_CHECKING:
    from selfid_jax.robot.live import OnlineResult

__all__ = ["CONFIG_JSON", "JINV_JSON", "JINV_NPZ", "SUMMARY_FILE", "check_estimate", "connect_robot", "open_camera",
           "run_session", "session_lines", "summary", "write_run"]

SUMMARY_FILE = "summary.json"
CONFIG_JSON = "online_config.json"
JINV_NPZ = "inverse_jacobian.npz"
JINV_JSON = "inverse_jacobian.json"


def connect_robot(cfg: OnlineConfig, config_dir: str | Path | None = None):
    """A connected :class:`~selfid_jax.robot.protocol.Robot` from the config's ``robot`` section
    (:func:`selfid_jax.robot.drivers.connect`); ConfigError naming ``robot.driver`` / ``robot.host`` when the driver
    cannot be imported, is not a Robot, or the connection fails. ``config_dir``: the config's folder, where a driver
    module is looked for after the Python path."""
    from selfid_jax.robot.drivers.load import ConnectError, connect
    from selfid_jax.runner.errors import ConfigError

    r = cfg.robot
    try:
        return connect(host=r.host, port=r.port, timeout_s=r.timeout_s, driver=r.driver, args=r.args,
                       config_dir=config_dir)
    except ConnectError as err:
        raise ConfigError(f"robot.{err.key}: {err}") from None


def _config_file(name: str, config_dir: Path | None) -> Path:
    """A file the config names: beside the config where it is there, else as given (the current directory)."""
    path = Path(name)
    if config_dir is not None and not path.is_absolute() and (config_dir / path).is_file():
        return config_dir / path
    return path


def open_camera(cfg: OnlineConfig, config_dir: str | Path | None = None):
    """The config's ``tracker`` camera, open with its first frame, and the tag's tracker:
    ``(LiveCamera, TagTracker)`` (:mod:`selfid_jax.robot.camera.live`); None without a tracker section.

    The intrinsics (``tracker.camera_info``) are read first; the camera must
    open and send a frame of their size within ``tracker.open_timeout_s``.
    Raises ConfigError naming ``tracker.camera_info`` (a missing or unusable
    file) or ``tracker.camera`` (what OpenCV could not open, or no frame),
    before any robot is reached.
    """
    from selfid_jax.runner.errors import ConfigError

    tr = cfg.tracker
    if tr is None:
        return None
    try:
        from selfid_jax.robot.camera.intrinsics import IntrinsicsError, read_intrinsics
        from selfid_jax.robot.camera.live import CameraError, LiveCamera, parse_tag
        from selfid_jax.robot.camera.tracker import TagTracker, TrackerSettings
    except ImportError as err:
        raise ConfigError(f"tracker: a camera tracker needs the camera extra (OpenCV): pip install "
                          f"'selfid_jax[camera]' ({err})") from None
    info = _config_file(tr.camera_info, None if config_dir is None else Path(config_dir))
    if not info.is_file():
        where = "beside the config or in the current directory" if config_dir is not None else "here"
        raise ConfigError(f"tracker.camera_info: {tr.camera_info}: no such file (looked {where})")
    try:
        intrinsics = read_intrinsics(info)
    except IntrinsicsError as err:
        raise ConfigError(f"tracker.camera_info: {err}") from None
    family, tag_id, edge = parse_tag(tr.tag)
    chosen = {k: getattr(tr, k) for k in ("max_reprojection", "max_ambiguity", "border_margin", "min_contrast",
                                          "corner_refine") if getattr(tr, k) is not None}
    rotation = any(a >= 3 for a in _axes(cfg.selfid.task))
    try:
        tracker = TagTracker(intrinsics, TrackerSettings(family=family, tag_id=tag_id, edge=edge, rotation=rotation,
                                                         **chosen))
    except ValueError as err:
        raise ConfigError(f"tracker: {err}") from None
    try:
        camera = LiveCamera(tr.camera, latency_s=tr.latency_s, open_timeout_s=tr.open_timeout_s,
                            size=(intrinsics.width, intrinsics.height))
    except CameraError as err:
        raise ConfigError(f"tracker.camera: {err} (intrinsics {info})") from None
    return camera, tracker


def _axes(task: str) -> tuple[int, ...]:
    from selfid_jax.robot.log import parse_task

    return parse_task(task) or ()


def run_session(cfg: OnlineConfig, out: str | Path, *, config_path: str | Path | None = None, resume: bool = False,
                estimate: str | Path | None = None, progress: Callable[[dict[str, Any]], None] | None = None,
                stop_requested: Callable[[], bool] | None = None, accept_flagged_estimate: bool = False
                ) -> tuple[OnlineResult, dict[str, Path]]:
    """Run one online session of ``cfg`` in the run directory ``out``; ``(result, files written by name)``.

    ``config_path``: the YAML file ``cfg`` came from: a relative driver module
    or ``path.file`` is looked for beside it, and errors name it (else
    ``config``). ``resume``: continue the session logged in ``out``.
    ``estimate``: an ``inverse_jacobian.npz`` (of ``selfid-jax fit`` or an
    earlier session) to follow the config's path with, instead of
    self-identifying (no random move). ``progress``: called with each event of
    :func:`selfid_jax.robot.live.run_online` (e.g.
    :class:`~selfid_jax.sessions.online_progress.ProgressLine`).
    ``stop_requested``: polled before every read and command; True stops the
    session as ``interrupted``. ``accept_flagged_estimate``
    (``--accept-flagged-estimate``): follow with an ``estimate`` whose file is
    flagged (trust warnings, or not converged; :func:`check_estimate`), which
    is otherwise refused before connecting.

    The estimator runs in JAX's default float (float64 once
    ``jax_enable_x64`` is on, as ``selfid-jax online`` sets it); the session
    log records it and a resume in the other precision is refused.

    Raises:
      ConfigError: a bad estimate (not an estimate file, another task's, a flagged one unless accepted) or
        path, per-actuator values of the wrong length for the robot, options ``run_online``
        refuses, a log that disagrees; a driver that cannot be imported or a
        robot that cannot be reached (``robot.driver`` / ``robot.host``); a camera that cannot be opened or
        sends no frame of its intrinsics' size (``tracker.camera``), unusable intrinsics (``tracker.camera_info``).
      DriverFailure: the driver failed while connecting or in ``limits()`` (an exception of its own, or limits
        that cannot be used; :class:`selfid_jax.robot.drivers.load.DriverFailure`, exit 3).
      RunDirError: ``out`` holds a sweep, a log without ``resume``, or no log
        with ``resume``; RunDirBusy: another process holds its lock.
    """
    import threading

    from selfid_jax.robot import live
    from selfid_jax.robot.drivers.load import checked_limits
    from selfid_jax.robot.log import parse_task
    from selfid_jax.runner import signals
    from selfid_jax.runner.config import dump_config
    from selfid_jax.runner.errors import ConfigError, RunDirError
    from selfid_jax.runner.files import write_json
    from selfid_jax.runner.lock import hold

    label = "config" if config_path is None else str(config_path)
    config_dir = None if config_path is None else Path(config_path).resolve().parent
    out = Path(out)
    if estimate is not None and cfg.path is None:
        raise ConfigError(f"{label}: --estimate {estimate}: following with a given estimate needs a path "
                          "section in the config")
    if estimate is not None:
        check_estimate(estimate, cfg.selfid.task, accept_flagged=accept_flagged_estimate)
    opts = options(cfg, config_dir, estimate)
    if opts.path is not None:
        try:
            opts.path.offsets(parse_task(opts.task) or ())
        except ValueError as err:
            raise ConfigError(f"{label}: {err}") from None
    if (out / "config.yaml").exists():
        raise RunDirError(f"{out}: holds a sweep's run directory (config.yaml); choose another --out")
    log = out / live.LOG_FILE
    if log.exists() and not resume:
        raise RunDirError(f"{out}: already holds a session log ({live.LOG_FILE}); continue it with --resume or "
                          "choose another --out")
    if resume and not log.exists():
        raise RunDirError(f"{out}: no session log ({live.LOG_FILE}) to resume; run without --resume")

    stop = threading.Event()
    asked = stop_requested

    def stopping() -> bool:
        return stop.is_set() or (asked is not None and bool(asked()))

    with hold(out):
        signals.phase("connect")
        camera = open_camera(cfg, config_dir)  # before the robot: a camera that does not open moves nothing
        tracked = None
        try:
            robot = connect_robot(cfg, config_dir)
        except BaseException:
            if camera is not None:
                camera[0].close()
            raise
        if camera is not None and cfg.tracker is not None:
            from selfid_jax.robot.camera.live import CameraTracked

            robot = tracked = CameraTracked(robot, *camera, wait_s=cfg.tracker.wait_s)
        # run_online closes the robot however it ends; close (idempotent) here too if it never starts. A close
        # that raises is a note beside the cause (live.close_robot), never in its place
        try:
            n = checked_limits(robot, cfg.robot.driver or f"{cfg.robot.host}:{cfg.robot.port}").lower.shape[0]
            _check_sizes(cfg, n, label)
            write_json(out / CONFIG_JSON, dump_config(cfg))
            signals.phase("online")
            try:
                with signals.graceful(f"selfid-jax online: interrupted; the session log {log} is intact "
                                      "(continue with --resume)", stop.set, interrupt=True,
                                      last_words=lambda: _log_killed(log)):
                    result = live.run_online(robot, opts, out, resume=resume, stop_requested=stopping,
                                             progress=progress, accept_flagged_estimate=accept_flagged_estimate)
            except ValueError as err:  # bad options, a log that disagrees: all before any motion
                config_error = ConfigError(f"{label}: {' '.join(str(err).split())}")
                for note in getattr(err, "__notes__", ()):  # a close that failed after it
                    config_error.add_note(note)
                raise config_error from None
        except BaseException as err:
            note = live.close_robot(robot)
            if note is not None and note not in getattr(err, "__notes__", ()):
                err.add_note(note)
            raise
        note = live.close_robot(robot)
        if note is not None and result.close_error is None:
            result = result._replace(close_error=note)
        signals.phase("write")
        files = write_run(result, cfg, out, tracker=None if tracked is None else tracked.counts())
    return result, files


def check_estimate(path: str | Path, task: str, *, accept_flagged: bool = False) -> list[str]:
    """Check an estimate file for ``--estimate`` before connecting; the lines that show its trust figures.

    The file must be an estimate (:func:`selfid_jax.robot.live.read_estimate`)
    for the config's ``task``. One whose trust record is flagged
    (:func:`selfid_jax.robot.quality.record_flags`: trust warnings, or not
    converged) is refused unless ``accept_flagged``; one written before
    estimate files carried a trust record is accepted, and its lines say so.

    Raises:
      ConfigError: naming ``--estimate FILE`` and what is wrong (exit 2, before any motion).
    """
    from selfid_jax.robot.live import read_estimate, trust_lines
    from selfid_jax.runner.errors import ConfigError

    try:
        read = read_estimate(path)
    except ValueError as err:
        raise ConfigError(f"--estimate {' '.join(str(err).split())}") from None
    axes = _axes(task)
    names = [_axis_names(axes)[i] for i in range(len(axes))]
    if axes and read.task_axes != names:
        raise ConfigError(f"--estimate {path}: its task axes are {','.join(read.task_axes)}, the task is "
                          f"{','.join(names)} (selfid.task); an estimate serves only the task it was identified for")
    try:
        return trust_lines(path, read, accept_flagged=accept_flagged, accept="--accept-flagged-estimate")
    except ValueError as err:
        raise ConfigError(f"--estimate {err}") from None


def _axis_names(axes) -> list[str]:
    from selfid_jax.systems.validation import AXIS_NAMES

    return [AXIS_NAMES[a] for a in axes]


def summary(result: OnlineResult, cfg: OnlineConfig, tracker: dict[str, Any] | None = None) -> dict[str, Any]:
    """``summary.json`` of a session: its stop, counts, convergence, tracking error [m], wall times [s] and the
    estimator step's latency [ms]; ``tracker``: a camera tracker's counts
    (:meth:`~selfid_jax.robot.camera.live.CameraTracked.counts`), under ``"camera"``."""
    import numpy as np

    from selfid_jax.robot.quality import condition
    from selfid_jax.systems.validation import AXIS_NAMES

    ms = result.step_ms
    n, m = result.estimate.shape
    own = {} if result.trust is None else {**result.trust.figures(), "actuators": list(result.trust.actuators)}
    given = None if result.estimate_source is None else (result.given_trust or {})
    info = {
        "command": "online",
        "status": result.status.value,
        "detail": result.detail,
        "n": n,
        "m": m,
        "task_axes": [AXIS_NAMES[a] for a in result.axes],
        # with a given estimate (no self-ID here): its file's convergence (None where the file does not say)
        "converged": result.converged if given is None else _given_converged(result),
        "converged_at": result.converged_at if given is None else result.given_converged_at,
        "samples": result.samples,
        "rejected": result.rejected,
        "moves": result.moves,
        "follow_steps": result.follow_steps,
        "follow_rejected": result.follow_rejected,
        "heldout_error": own.get("heldout_error", (given or {}).get("heldout_error")),
        # ||J Ĵ - I||_F against the driver's model Jacobian (a driver with jacobian()) where self-ID started, or with a
        # given estimate where following started (reference_at)
        "reference_error": result.reference_error,
        "reference_at": None if result.reference is None else ("follow" if given is not None else "selfid"),
        "actuator_effect": own.get("actuator_effect", (given or {}).get("actuator_effect")),
        # the estimate's condition number s_max / s_min (selfid_jax.robot.quality.condition), as selfid-jax fit reports
        "condition": condition(result.estimate) if result.converged or given is not None else None,
        "actuators": own.get("actuators", (given or {}).get("actuators")),
        # the trust warnings: this session's samples', or with a given estimate its file's
        "warnings": list(result.trust.warnings) if result.trust is not None else list((given or {}).get("warnings")
                                                                                        or []),
        "estimate_trust": result.given_trust,  # --estimate: the file's trust record (None: it carries none)
        "waypoints": result.waypoints,
        "waypoints_total": result.waypoints_total,
        "replayed": result.replayed,
        "estimate_source": result.estimate_source,  # --estimate: the file followed with (no self-ID); else None
        "truncated_log_lines": result.truncated,
        # while following, the tracked point's distance from the path after each move [m] (every session of the log)
        "track_mean_m": float(np.nanmean(result.track)) if result.track.size else None,
        "track_max_m": float(np.nanmax(result.track)) if result.track.size else None,
        "selfid_s": result.selfid_s,  # wall time of self-ID [s]: moves, settling, reads, the estimator
        "follow_s": result.follow_s,  # wall time following the path [s]
        "step_ms_p50": float(np.percentile(ms, 50)) if ms.size else None,
        "step_ms_p99": float(np.percentile(ms, 99)) if ms.size else None,
        "eps": cfg.selfid.eps,
        "eps_rel": cfg.selfid.eps_rel,
        "log": str(result.log),
        "close_error": result.close_error,  # closing the driver after the stop failed: that failure (None: closed)
    }
    if tracker is not None:  # frames received, tracked and valid; dropouts by reason (stale: a frozen camera)
        info["camera"] = tracker
    return info


def _npz(**arrays) -> bytes:
    """The bytes of an ``.npz`` of ``arrays`` (written whole by the caller)."""
    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _check_sizes(cfg: OnlineConfig, n: int, label: str | Path) -> None:
    """Per-actuator config values against the robot's ``n`` (known once connected; before any motion)."""
    from selfid_jax.runner.errors import ConfigError

    for key, value in (("selfid.m_a", cfg.selfid.m_a), ("safety.max_step", cfg.safety.max_step),
                       ("safety.limits_lower", cfg.safety.limits_lower),
                       ("safety.limits_upper", cfg.safety.limits_upper)):
        if isinstance(value, list) and len(value) != n:
            raise ConfigError(f"{label}: key '{key}': {len(value)} values, but the robot has {n} actuators")


def _log_killed(log: Path) -> None:
    """Append the stop record of a process that a second signal ends at once (called from the signal thread)."""
    from selfid_jax.robot.journal import Journal

    with Journal(log) as journal:
        journal.append({"e": "stop", "reason": "killed", "detail": "a second signal ended the process at once; the "
                        "robot's connection closes with it (continue with --resume)"})


def _given_converged(result: OnlineResult) -> bool | None:
    """Whether a given estimate's self-ID converged, as its file says (None where it does not)."""
    record = result.given_trust
    if record is not None and "converged" in record:
        return bool(record["converged"])
    return None if result.given_converged_at is None else result.given_converged_at > 0


def session_lines(result: OnlineResult) -> list[str]:
    """How a session's estimate was made, one line each (the estimate file's ``report``): samples, moves, rejected
    draws, convergence and the session's stop."""
    rejected = ", ".join(f"{v} {k}" for k, v in result.rejected.items()) or "none"
    return [f"online self-ID: {result.samples} samples, {result.moves} random moves, rejected: {rejected}",
            f"converged at sample {result.converged_at}" if result.converged else "not converged",
            f"stopped: {result.status.value}: {result.detail}"]


def write_run(result: OnlineResult, cfg: OnlineConfig, out: str | Path, *,
              tracker: dict[str, Any] | None = None) -> dict[str, Path]:
    """Write ``summary.json`` and, for a converged session only, ``inverse_jacobian.npz``/``.json`` into ``out`` (each
    atomically), then the figures from the session log; the files written by name. A session that did not converge
    has its estimate so far in the summary (``estimate_so_far``), not in a file that could be taken for a result.
    ``tracker``: a camera tracker's counts for the summary (:func:`summary`)."""
    import json

    import numpy as np

    from selfid_jax.identify import estimator
    from selfid_jax.robot.quality import TRUST_KEY, trust_record
    from selfid_jax.runner.files import atomic_write_bytes, write_json
    from selfid_jax.sessions.online_figures import write_figures

    out = Path(out)
    info = summary(result, cfg, tracker)
    meta = {k: info[k] for k in ("n", "m", "task_axes", "converged_at", "converged", "samples", "eps", "eps_rel",
                                 "status")}
    guess = np.asarray(estimator.initial_guess(result.state))
    paths = {SUMMARY_FILE: out / SUMMARY_FILE}
    if result.converged:  # a session that never converged writes no file that could be taken for a result
        paths.update({name: out / name for name in (JINV_NPZ, JINV_JSON)})
        record = trust_record(source="online", log=str(result.log), converged=True,
                              converged_at=result.converged_at, trust=result.trust,
                              reference_error=result.reference_error, report=session_lines(result))
        atomic_write_bytes(paths[JINV_NPZ], _npz(
            inverse_jacobian=result.estimate, initial_guess=guess, task_axes=np.array(info["task_axes"]),
            **{k: np.asarray(v) for k, v in meta.items() if k != "task_axes"},
            **{TRUST_KEY: np.array(json.dumps(record))}))
        write_json(paths[JINV_JSON], {"inverse_jacobian": result.estimate, "initial_guess": guess, **meta,
                                      "log": str(result.log), TRUST_KEY: record})
    else:
        info["estimate_so_far"] = result.estimate if result.samples else None  # not converged: not a result
    write_json(paths[SUMMARY_FILE], info)
    for f in write_figures(out):  # from the session log, as `selfid-jax plot RUN` redraws them
        paths[f"figures/{f.name}"] = f
    return paths
