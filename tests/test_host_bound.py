"""A host-bound backend (MuJoCo through a host callback) says so before it starts when the default device is an
accelerator (issue 44, item 1): the hands' native settling and the articulated rollout's native backend."""

from __future__ import annotations

import warnings

import jax
import pytest

from selfid_jax.math.checks import HostBoundWarning, warn_if_host_bound
from selfid_jax.systems.hands import model_o


@pytest.mark.slow
def test_native_hand_settling_warns_on_an_accelerator_only(monkeypatch):
    with warnings.catch_warnings():
        warnings.simplefilter("error", HostBoundWarning)
        model_o(backend="native")  # the CPU: no warning
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    with pytest.warns(HostBoundWarning, match=r"native settling .* not on the default device \(gpu\).*backend='mjx'"):
        model_o(backend="native")
    with warnings.catch_warnings():
        warnings.simplefilter("error", HostBoundWarning)
        model_o(backend="mjx")  # on the device: no warning


@pytest.mark.slow
def test_the_articulated_native_backend_warns_on_an_accelerator(monkeypatch):
    """sim.make_static('native') on a GPU default warns; 'mjx' does not (a door scene, the test arm)."""
    from helpers_articulated import PADS
    from helpers_articulated import ur5e_arm as _arm

    from selfid_jax.articulated import scenes, sim

    with jax.numpy_rank_promotion("allow"):
        arm, q0, p1, R1 = _arm()
        m, lay = scenes.compile_scene("revolute", p1, R1)
        monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
        with pytest.warns(HostBoundWarning, match="backend 'native'.*Use backend: mjx"):
            sim.make_static("native", lay, m, PADS, arm, q0, steps=5, substeps=2, stride=1)
        with warnings.catch_warnings():
            warnings.simplefilter("error", HostBoundWarning)
            sim.make_static("mjx", lay, m, PADS, arm, q0, steps=5, substeps=2, stride=1)
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
    assert not warn_if_host_bound("x", "y")
