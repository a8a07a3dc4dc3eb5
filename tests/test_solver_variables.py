"""Named pose variables: one column order, whatever order the poses come in."""

import numpy as np
import pytest

from slamtka.solver.geometry import Pose
from slamtka.solver.optimizer import State
from slamtka.solver.variables import BONE, Ordering, body_key, pin_key, view_key


def test_the_ordering_puts_views_by_position_then_pins_by_label():
    keys = [pin_key("pin2"), view_key(1), pin_key("pin1"), view_key(0)]
    ordering = Ordering.of(keys)
    assert ordering.keys == (view_key(0), view_key(1), pin_key("pin1"), pin_key("pin2"))
    assert [ordering.index(k) for k in keys] == [3, 1, 2, 0]
    assert list(ordering.columns([pin_key("pin1")])) == list(range(12, 18))
    assert body_key("bone") == BONE and body_key("pin2") == pin_key("pin2")
    assert [str(k) for k in ordering.keys] == ["view0", "view1", "pin1", "pin2"]
    with pytest.raises(ValueError, match="bone"):
        Ordering.of([view_key(0), BONE])


def test_masks_increments_and_marginals_go_by_key():
    ordering = Ordering.of([view_key(0), view_key(1), pin_key("pin1")])
    mask = ordering.mask({pin_key("pin1"): np.array([0, 0, 0, 0, 0, 1], bool)})
    assert np.flatnonzero(mask).tolist() == [17]
    steps = ordering.split(np.arange(18.0))
    assert steps[view_key(1)].tolist() == list(range(6, 12))
    covariance = np.arange(18.0 * 18).reshape(18, 18)
    block = ordering.marginal(covariance, [pin_key("pin1"), view_key(0)])
    assert block.shape == (12, 12) and block[0, 0] == covariance[12, 12] and block[6, 0] == covariance[0, 12]


def test_a_state_retracts_each_pose_by_its_own_columns():
    poses = {pin_key("pin1"): Pose.identity(), view_key(0): Pose.identity()}
    state = State(poses, np.zeros((0, 3)))
    step = np.zeros(12)
    step[8] = 2.0  # the pin's z translation: its columns follow the view's
    moved = state.retract(step, np.zeros((0, 3)))
    assert np.allclose(moved.poses[pin_key("pin1")].t, [0.0, 0.0, 2.0])
    assert np.allclose(moved.poses[view_key(0)].t, 0.0)
