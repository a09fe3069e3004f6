"""Reliability round three (issue #48): the network where it cannot work. With three lights the
network's normals were 17-37 deg off on a Lambertian plate, exit 0 and no word (least squares
on the same lights: under 5 deg). The rule: the network needs NETWORK_MIN_LIGHTS lights; with
fewer, least squares runs and the result says so."""

from __future__ import annotations

import numpy as np
from _runtime_helpers import sphere_stack

from msfnet import Model
from msfnet.runtime.infer.estimators import NETWORK_MIN_LIGHTS


def test_three_lights_run_least_squares_and_say_so() -> None:
    assert NETWORK_MIN_LIGHTS == 4
    result = Model(maps=None)(sphere_stack(n=3, h=32, w=32))
    plain = Model.least_squares(maps=None)(sphere_stack(n=3, h=32, w=32))
    assert result.method["method"] == "l2"
    assert np.array_equal(result.normals, plain.normals)
    assert any("too few for the network" in w for w in result.stack.warnings)
    assert result.profile()["warnings"]


def test_four_lights_run_the_network() -> None:
    result = Model(maps=None)(sphere_stack(n=NETWORK_MIN_LIGHTS, h=32, w=32))
    assert result.method["method"] == "msf"
    assert not any("too few" in w for w in result.stack.warnings)
