"""The wheel holds what a checkout imports: experiments/ as selfid_jax.experiments, configs/ as selfid_jax.configs,
the type stubs that list the public names, the native kernels' library, and no top-level package of another name;
and the installed package finds its experiments, configs and kernels with the import system's own finders (no hook of
ours on ``sys.meta_path``)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# builds a wheel (about 25 s: the native kernels compile), once: both tests on one worker
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("wheel")]

PROBE = r"""
import json, sys
import selfid_jax, selfid_jax.configs, selfid_jax.experiments.demo
from selfid_jax import runner
print(json.dumps({
    "package": selfid_jax.__file__,
    "experiment": selfid_jax.experiments.demo.__file__,
    "configs": list(selfid_jax.configs.__path__),
    "demo": type(runner.get("demo")).__name__,
    "finders": [getattr(f, "__module__", None) or type(f).__module__ for f in sys.meta_path],
    "fit": selfid_jax.fit.__module__,
    "native": __import__("selfid_jax.math.native").math.native.load_error() or "loaded",
}))
"""


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(out),
                    str(ROOT)], check=True, capture_output=True, timeout=300)
    (path,) = out.glob("selfid_jax-*.whl")
    return path


def test_wheel_holds_the_experiments_configs_and_stubs(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"selfid_jax"}, tops
    experiments = {p.relative_to(ROOT / "experiments").as_posix() for p in (ROOT / "experiments").rglob("*.py")}
    assert {f"selfid_jax/experiments/{p}" for p in experiments} <= set(names)
    configs = {p.relative_to(ROOT / "configs").as_posix() for p in (ROOT / "configs").rglob("*.yaml")}
    assert configs and {f"selfid_jax/configs/{p}" for p in configs} <= set(names)
    stubs = {p.relative_to(ROOT).as_posix() for p in (ROOT / "selfid_jax").rglob("*.pyi")}
    assert stubs and stubs | {"selfid_jax/py.typed"} <= set(names)
    assert [n for n in names if n.startswith("selfid_jax/math/_native_kernels.")], "no native kernels in the wheel"


def test_installed_wheel_finds_its_experiments_without_a_hook(wheel, tmp_path):
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    env = {**os.environ, "PYTHONPATH": str(site), "PYTHONSAFEPATH": "1"}  # the wheel first, not the checkout
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=120, check=True).stdout
    got = json.loads(out.strip().splitlines()[-1])
    assert got["package"].startswith(str(site)) and got["experiment"].startswith(str(site)), got
    assert got["configs"] == [str(site / "selfid_jax" / "configs")], got
    assert got["demo"] and got["fit"] == "selfid_jax.robot.offline"
    assert got["native"] == "loaded", got["native"]  # the wheel's own kernels, built with it
    assert not [m for m in got["finders"] if m and m.startswith("selfid_jax")], got["finders"]
