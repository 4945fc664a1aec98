"""Subgoal spaces: the box and the element space (each task element done or at rest), against hand-computed values."""

import numpy as np
import pytest
import torch as th

from sb3_dipper.common.subgoals import ElementSubgoalSpace, SubgoalSpace

# Two elements: a hinge (entry 0) and a knob with a slide (entries 1 and 2), as in the kitchen.
LOW, HIGH = np.array([-2.0, -1.0, -0.1]), np.array([0.0, 0.0, 0.1])
DONE, START = np.array([-1.0, -0.8, 0.05]), np.array([0.0, 0.0, 0.0])


def element_space(**overrides) -> ElementSubgoalSpace:
    kwargs = dict(low=LOW, high=HIGH, threshold=0.3, elements=((0,), (1, 2)), done=DONE, start=START)
    return ElementSubgoalSpace(**{**kwargs, **overrides})


def test_the_box_maps_unit_actions_linearly_and_rewards_within_the_threshold():
    space = SubgoalSpace(LOW, HIGH, threshold=0.3)
    np.testing.assert_allclose(space.to_world(np.array([-1.0, 0.0, 1.0])), [-2.0, -0.5, 0.1], atol=1e-7)
    np.testing.assert_allclose(space.to_unit(np.array([-2.0, -0.5, 0.1])), [-1.0, 0.0, 1.0], atol=1e-7)
    # Euclidean over all entries: (0.2, 0.2, 0) is 0.283 away, (0.3, 0.1, 0) 0.316.
    assert space.compute_reward(np.array([0.2, 0.2, 0.0]), np.zeros(3)) == 0.0
    assert space.compute_reward(np.array([0.3, 0.1, 0.0]), np.zeros(3)) == -1.0


def test_an_element_is_asked_done_by_the_sign_of_its_first_entry():
    space = element_space()
    unit_actions = np.array([[0.1, -0.2, 0.9], [-0.1, 0.3, -0.9], [1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])
    expected = [
        [-1.0, 0.0, 0.0],  # hinge done, knob at rest (the slide's own sign does not matter)
        [0.0, -0.8, 0.05],  # knob done
        [-1.0, -0.8, 0.05],  # both done
        [0.0, 0.0, 0.0],  # neither
    ]
    np.testing.assert_allclose(space.to_world(unit_actions), expected, atol=1e-7)


def test_to_unit_asks_done_for_the_elements_done_in_a_subgoal():
    space = element_space()
    # Hinge at -0.8 (0.2 from done: done), knob at (-0.4, 0.05) (0.4 from done: not done).
    achieved = np.array([[-0.8, -0.4, 0.05], [-1.0, -0.8, 0.05]])
    np.testing.assert_allclose(space.to_unit(achieved), [[1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    np.testing.assert_allclose(space.to_world(space.to_unit(achieved)), [[-1.0, 0.0, 0.0], DONE], atol=1e-7)


def test_a_subgoal_is_reached_when_every_element_is_within_the_threshold():
    space = element_space()
    # Element distances 0.25 (hinge) and 0.2 (knob): reached; Euclidean over all entries (0.32) would say not.
    achieved = np.array([-0.75, -0.6, 0.05])
    assert space.distance(achieved, DONE) == pytest.approx(0.25)
    assert space.compute_reward(achieved, DONE) == 0.0
    # The knob 0.35 away: not reached, whatever the hinge.
    assert space.compute_reward(np.array([-1.0, -0.45, 0.05]), DONE) == -1.0


def test_gradients_pass_straight_through_the_snapping():
    space = element_space()
    unit_actions = th.tensor([[0.2, -0.5, 0.7]], dtype=th.float64, requires_grad=True)
    subgoals = space.to_world_tensor(unit_actions)
    np.testing.assert_allclose(subgoals.detach().numpy(), space.to_world(unit_actions.detach().numpy()), atol=1e-7)
    subgoals.sum().backward()
    assert unit_actions.grad is not None
    # The box's derivative, half the span per entry.
    np.testing.assert_allclose(unit_actions.grad.numpy(), [[1.0, 0.5, 0.1]])


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (dict(elements=((0,), (1,))), "every entry 0..2 exactly once"),
        (dict(elements=((0, 1), (1, 2))), "every entry 0..2 exactly once"),
        (dict(elements=((0, 1, 2), ())), "non-empty groups"),
        (dict(done=np.array([-1.0, -0.8, 0.5])), "done must be 3 values inside"),
        (dict(start=np.zeros(2)), "start must be 3 values inside"),
    ],
)
def test_bad_element_spaces_are_refused_at_construction(overrides, message):
    with pytest.raises(ValueError, match=message):
        element_space(**overrides)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (dict(threshold=float("nan")), "threshold must be a finite number > 0, got nan"),
        (dict(threshold=float("inf")), "threshold must be a finite number > 0, got inf"),
        (dict(threshold="0.1"), "threshold must be a finite number > 0, got '0.1'"),
        (dict(indices=(0, 0)), r"indices must be distinct entries of the achieved goal \(ints >= 0\), got \(0, 0\)"),
        (dict(indices=(-1, 1)), r"indices must be distinct entries"),
    ],
)
def test_bad_subgoal_spaces_are_refused_at_construction(overrides, message):
    with pytest.raises(ValueError, match=message):
        SubgoalSpace(**{**dict(low=[-1.0, -1.0], high=[1.0, 1.0], threshold=0.1), **overrides})


def test_the_goal_unit_map_is_to_unit_of_the_projected_goal():
    """A normalised goal x maps to to_unit(project(mean + std * x)): scale 2 std / span, shift 2 (mean - low) / span - 1."""
    space = SubgoalSpace(np.array([0.0, -1.0]), np.array([2.0, 1.0]), threshold=0.1, indices=(2, 0))
    mean, std = np.array([1.0, 5.0, 0.5]), np.array([0.5, 9.0, 0.25])
    scale, shift, indices = space.goal_unit_map(mean, std)
    np.testing.assert_allclose(scale, [0.25, 0.5])  # entry 2: 2 * 0.25 / 2; entry 0: 2 * 0.5 / 2
    np.testing.assert_allclose(shift, [-0.5, 1.0])  # 2 * 0.5 / 2 - 1; 2 * (1 + 1) / 2 - 1
    np.testing.assert_array_equal(indices, [2, 0])
    normalised = np.array([[0.4, -3.0, 2.0], [-1.0, 0.0, -2.0]])
    by_map = np.clip(scale * normalised[:, indices] + shift, -1.0, 1.0)
    np.testing.assert_allclose(by_map, space.to_unit(space.project(mean + std * normalised)), atol=1e-6)
    with pytest.raises(NotImplementedError, match=r"goal_anchored=True\) cannot take this subgoal space"):
        element_space().goal_unit_map(np.zeros(3), np.ones(3))
