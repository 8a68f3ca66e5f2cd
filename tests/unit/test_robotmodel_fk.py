"""The grasp point, placed alone (grasp_xyz, grasp_point), is where forward kinematics of every frame
puts it, to the last bit: safety's checks use the one, the executor the other."""

from __future__ import annotations

import numpy as np

from services.robotmodel import ArmModel


def test_the_grasp_point_alone_is_forwards_translation_to_the_bit() -> None:
    arm = ArmModel()
    rng = np.random.default_rng(7)
    for q in rng.uniform(arm.lower, arm.upper, (500, 7)):
        expected = arm.forward(q).translation.tolist()
        assert list(arm.grasp_xyz(q)) == expected
        assert list(arm.grasp_xyz(q.tolist())) == expected
        assert arm.grasp_point(q).tolist() == expected
