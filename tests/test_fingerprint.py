"""Resuming a run whose inputs changed is refused, naming what changed: model files, included files, pose-function
modules, the package's own source; the unchanged rerun still resumes, and versions.json names the package's revision."""

from __future__ import annotations

import json
import textwrap

import pytest
import yaml

from selfid_jax import cli
from selfid_jax.runner import fingerprint
from selfid_jax.systems.model_files import model_files

ARM = textwrap.dedent("""\
    <mujoco model="arm2">
      <compiler angle="radian"/>
      <include file="parts/links.xml"/>
      <actuator>
        <position name="a1" joint="j1" kp="10" ctrlrange="-3 3"/>
        <position name="a2" joint="j2" kp="10" ctrlrange="-3 3"/>
      </actuator>
    </mujoco>
    """)
LINKS = textwrap.dedent("""\
    <mujoco>
      <worldbody>
        <body name="l1">
          <joint name="j1" type="hinge" axis="0 0 1" range="-3 3"/>
          <geom type="capsule" fromto="0 0 0 {L} 0 0" size="0.02"/>
          <body name="l2" pos="{L} 0 0">
            <joint name="j2" type="hinge" axis="0 0 1" range="-3 3"/>
            <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.02"/>
            <site name="tip" pos="0.4 0 0"/>
          </body>
        </body>
      </worldbody>
    </mujoco>
    """)
POSE = textwrap.dedent("""\
    import jax.numpy as jnp

    def planar(params, q):
        return jnp.stack([{L} * jnp.cos(q[0]) + 0.4 * jnp.cos(q[0] + q[1]),
                          {L} * jnp.sin(q[0]) + 0.4 * jnp.sin(q[0] + q[1]), 0.0 * q[0]])
    """)


def _config(tmp_path, system) -> str:
    cfg = {
        "experiment": "valid_region",
        "systems": [system],
        "eps_limits": {"start": 0.5, "stop": 1.5, "num": 2},
        "n_configs": 1,
        "n_trials": 2,
        "path": {"kind": "star", "size": 0.1},
        "controller": {"max_step": 0.01, "tol": 0.002, "steps": 120},
        "chunk_size": 2,
    }
    path = tmp_path / "vr.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return str(path)


def _sweep(cfg, out) -> int:
    return cli.main(["sweep", cfg, "--out", str(out), "--no-progress"])


def test_model_files_follow_includes_and_assets(tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "arm.xml").write_text(ARM.replace("<mujoco model=\"arm2\">", "<mujoco model=\"arm2\">\n"
                                                  "  <compiler meshdir=\"meshes\"/>\n"
                                                  "  <asset><mesh name=\"m\" file=\"link.stl\"/></asset>"))
    (tmp_path / "parts" / "links.xml").write_text(LINKS.format(L=0.4))
    files = model_files(tmp_path / "arm.xml")
    assert files[0] == (tmp_path / "arm.xml").resolve() and len(files) == 3
    assert set(files[1:]) == {(tmp_path / "parts" / "links.xml").resolve(),
                              (tmp_path / "meshes" / "link.stl").resolve()}


@pytest.mark.slow  # three sweeps through the CLI
def test_edited_included_mjcf_file_refuses_resume(tmp_path, capsys):
    (tmp_path / "parts").mkdir()
    (tmp_path / "arm.xml").write_text(ARM)
    links = tmp_path / "parts" / "links.xml"
    links.write_text(LINKS.format(L=0.4))
    cfg = _config(tmp_path, {"mjcf": "arm.xml", "site": "tip", "task_dim": 2, "home": [0.3, 1.2]})
    out = tmp_path / "run"
    assert _sweep(cfg, out) == 0
    manifest = json.loads((out / "parts" / "arm" / "manifest.json").read_text())
    assert str(links.resolve()) in manifest["fingerprint"]["inputs"]
    versions = json.loads((out / "versions.json").read_text())
    assert versions["source_sha256"] == fingerprint.package_source()["source_sha256"]

    assert _sweep(cfg, out) == 0  # unchanged: resumes, nothing recomputed
    capsys.readouterr()
    links.write_text(LINKS.format(L=0.44))  # a link 0.40 -> 0.44 m, in the included file
    assert _sweep(cfg, out) == 2
    err = capsys.readouterr().err
    assert "changed since" in err and "links.xml" in err and "--fresh" in err
    assert cli.main(["sweep", cfg, "--out", str(out), "--no-progress", "--fresh"]) == 0


@pytest.mark.slow
def test_edited_pose_fn_module_and_package_source_refuse_resume(tmp_path, capsys, monkeypatch):
    pkg = tmp_path / "userbots"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "arm.py").write_text(POSE.format(L=0.4))
    monkeypatch.syspath_prepend(str(tmp_path))
    cfg = _config(tmp_path, {"pose_fn": "userbots.arm:planar", "n_act": 2, "task_dim": 2,
                             "sample_box": {"low": [0.2, 1.0], "high": [0.4, 1.4]}})
    out = tmp_path / "run"
    assert _sweep(cfg, out) == 0
    (pkg / "arm.py").write_text(POSE.format(L=0.44))
    capsys.readouterr()
    assert _sweep(cfg, out) == 2
    assert "arm.py" in capsys.readouterr().err
    (pkg / "arm.py").write_text(POSE.format(L=0.4))  # back as it was: resumes
    assert _sweep(cfg, out) == 0

    real = fingerprint.package_source()
    monkeypatch.setattr(fingerprint, "package_source", lambda: {**real, "source_sha256": "0" * 64})
    capsys.readouterr()
    assert _sweep(cfg, out) == 2
    assert "the selfid_jax source" in capsys.readouterr().err
