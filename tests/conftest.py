"""Test configuration: float64 (references are compared to 1e-6 and tighter) and
strict rank promotion, so accidental broadcasting fails loudly."""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import pytest

import selfid_jax  # sets the CPU XLA flags before JAX initialises
from selfid_jax._gc import collect_less_often

try:  # the top-level experiments/ is selfid_jax.experiments only in an install (editable, for the tests)
    import selfid_jax.experiments  # noqa: F401
except ModuleNotFoundError as err:
    raise pytest.UsageError(f"{err}: the tests import the installed package; install this checkout editable first: "
                            "pip install -e '.[test,docs]' (the README's second command)") from None
from selfid_jax._xla import merged_xla_flags, quick_compile_flags

# The tests compile with LLVM's optimisation level 0: XLA's graph passes (fusion, simplification) are those of
# the shipped build, only the machine code is less optimised. Most test programs run once on small shapes, so
# compile time is most of the suite's time: level 0 takes the whole suite from 616 to 427 s and its fast tier
# from 102 to 75 s (2 cores, same hour). The results differ from level 3's by round-off (LLVM contracts other
# multiply-adds); tests marked `shipped_xla` re-run in a subprocess at the shipped level. A level set in
# XLA_FLAGS by the user wins (XLA_FLAGS=--xla_backend_optimization_level=3 runs every test as shipped).
# Set here, before JAX's first computation; pytest-xdist workers and subprocesses inherit it.
os.environ["XLA_FLAGS"] = merged_xla_flags(os.environ.get("XLA_FLAGS"), quick_compile_flags())
_OPT_FLAG = "--xla_backend_optimization_level"
_LEVEL_0 = f"{_OPT_FLAG}=0" in os.environ["XLA_FLAGS"].split()

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
collect_less_often()  # as the console script does: the tests are compile-bound (the tracing's share of the collector)

# No persistent XLA compilation cache by default: the tests' programs are nearly all distinct, so a shared cache
# for the run hit about a dozen times in the whole suite while writing every program over 0.2 s to disk (the whole
# suite 446 -> 424 s and XLA's compile seconds 247 -> 213 without it and with QUICK_COMPILE_FLAGS' whole-module
# compiles, 2026-12-07). The console script's own cache (runner.command_line) is off too, in the workers and in the
# subprocesses that inherit their environment, so no test reads or writes ~/.cache. SELFID_JAX_TEST_CACHE_DIR names
# a folder to keep the programs in across runs (a developer re-running the suite); tests that need a cold process
# set SELFID_JAX_CACHE_DIR=off themselves.
_CACHE_ENV = "SELFID_JAX_TEST_CACHE_DIR"


def pytest_configure(config):
    where = os.environ.get(_CACHE_ENV)
    if not where:
        os.environ["SELFID_JAX_CACHE_DIR"] = "off"
        return
    os.environ.setdefault("SELFID_JAX_CACHE_DIR", where)  # the console script's cache (runner.command_line)
    jax.config.update("jax_compilation_cache_dir", where)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


_SLOW_MODULE = re.compile(r"^pytestmark = \[?pytest\.mark\.slow\b", re.M)


def pytest_ignore_collect(collection_path, config):
    """Under ``-m "not slow"`` (the fast tier) a module marked slow as a whole is not imported: every test in it
    would be deselected, and importing it (and rewriting its asserts) in each worker costs the tier seconds."""
    if config.getoption("markexpr", "") != "not slow" or collection_path.suffix != ".py":
        return None
    if not collection_path.name.startswith("test_"):
        return None
    return True if _SLOW_MODULE.search(collection_path.read_text(encoding="utf-8")) else None


def pytest_pyfunc_call(pyfuncitem):
    """A test marked ``shipped_xla`` runs at XLA's shipped optimisation level: in a subprocess when this one is at 0."""
    if not (_LEVEL_0 and pyfuncitem.get_closest_marker("shipped_xla")):
        return None
    flags = os.environ["XLA_FLAGS"].replace(f"{_OPT_FLAG}=0", f"{_OPT_FLAG}=3")
    nodeid, suffix = pyfuncitem.nodeid, _group_suffix(pyfuncitem)
    if suffix and nodeid.endswith(suffix):  # the id without pytest-xdist's group suffix, as a command line names it
        nodeid = nodeid[:-len(suffix)]
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", nodeid],
                          cwd=pyfuncitem.config.rootpath, env={**os.environ, "XLA_FLAGS": flags},
                          capture_output=True, text=True)
    if proc.returncode != 0 or not re.search(r"^1 passed", proc.stdout, re.M):
        pytest.fail(f"{pyfuncitem.nodeid} at {_OPT_FLAG}=3 (subprocess):\n{proc.stdout[-4000:]}{proc.stderr[-2000:]}",
                    pytrace=False)
    return True


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """``--dist loadgroup`` (pyproject.toml's addopts) keeps the tests of one ``xdist_group`` on one worker, as one
    unit of work: each pytest-xdist worker appends ``@GROUP`` to such a test's id and the controller groups by that
    suffix. pytest 9.2 builds ``item.nodeid`` from a structured id that xdist 3.8 does not write (it sets the old
    ``_nodeid``), so the suffix was lost and every grouped test went to whichever worker was free: the fixed-port
    simulators of test_trossen.py could start side by side, and the real-time tests ran beside each other
    (pytest-xdist issue 1386). Here, after xdist's own hook, the suffix is written where this pytest reads it."""
    if not getattr(config.option, "loadgroup", False):  # set on workers under --dist loadgroup only
        return
    for item in items:
        suffix = _group_suffix(item)
        if not suffix or item.nodeid.endswith(suffix):  # none, or xdist's own suffix took
            continue
        if not hasattr(item, "_id"):
            raise pytest.UsageError(f"cannot group {item.nodeid} under --dist loadgroup: this pytest keeps neither "
                                    "the id pytest-xdist writes nor a structured _id")
        item._id = type(item._id).parse(item.nodeid + suffix)
        assert item.nodeid.endswith(suffix), item.nodeid


def _group_suffix(item) -> str:
    """``"@NAME"`` that pytest-xdist's loadgroup appends to the id of a test marked ``xdist_group(NAME)`` (names
    sorted and joined by ``_`` for several marks); ``""`` for a test with none."""
    names = sorted({str(m.args[0] if m.args else m.kwargs.get("name", "default"))
                    for m in item.iter_markers("xdist_group")})
    return "@" + "_".join(names) if names else ""


@pytest.fixture(scope="session")
def console() -> list[str]:
    """The ``selfid-jax`` console script as a command list (its installed script, else ``python -c`` calling it)."""
    exe = shutil.which("selfid-jax", path=os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]]))
    return [exe] if exe else [sys.executable, "-c", "import sys; from selfid_jax.cli import main; sys.exit(main())"]


# ------------------------------------------------------------ the hands (test_model_o.py, test_stewart_hand.py)

@pytest.fixture(scope="session")
def poses():
    """``poses(system, q (B, n)) -> (p (B, 3), R (B, 3, 3))``, jitted: the System is a traced argument, so every
    system and test of one pose-map type and batch shares one compiled program."""
    return jax.jit(jax.vmap(lambda system, q: system.pose(q), in_axes=(None, 0)))


@pytest.fixture(scope="session")
def mjx_batch() -> int:
    """Commands per MJX settle in the hands' tests: every MJX settle of one hand is one compiled program."""
    return 16


# ------------------------------------------------------------ the online runner's fake arm (tests/test_online*.py)

@pytest.fixture
def driver_module(tmp_path, monkeypatch):
    """The fake arm's driver module ``fake_driver`` (``make(**kw)`` builds a FakeArm and appends it to CREATED),
    written in tmp_path and importable from there and from tests/ for the test's duration."""
    from helpers_online import DRIVER

    (tmp_path / "fake_driver.py").write_text(DRIVER)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    sys.modules.pop("fake_driver", None)
    import fake_driver

    yield fake_driver
    sys.modules.pop("fake_driver", None)


@pytest.fixture(scope="module")
def converged_run(tmp_path_factory):
    """One uninterrupted session to convergence (no path): the reference for resume and follow tests."""
    from helpers_online import FakeArm, opts

    from selfid_jax.robot import live

    run = tmp_path_factory.mktemp("online") / "ref"
    fake = FakeArm()
    result = live.run_online(fake, opts(), run)
    assert result.status == live.Stop.CONVERGED, result.detail
    return run, fake, result
