"""The reach criterion: inclusive radius, strictly closest, ties and unknown positions."""

import numpy as np

from sim.outcome import NONE, reach_outcome


def _one(tcp, objs, r=0.10):
    return int(reach_outcome(np.array([tcp], float), np.array([objs], float), r)[0])


def test_exactly_at_radius_counts_as_reached():
    assert _one([0, 0, 0], [[0.10, 0, 0], [1.0, 0, 0]]) == 0


def test_just_outside_radius_is_not_reached():
    assert _one([0, 0, 0], [[0.1000001, 0, 0], [1.0, 0, 0]]) == NONE


def test_near_but_not_closest_object_is_not_reached():
    # Object 0 is within the radius, but object 1 is closer: object 1 is the one reached.
    assert _one([0, 0, 0], [[0.09, 0, 0], [0.05, 0, 0]]) == 1
    # Object 1 closer but outside? impossible; object 0 within, object 1 closer and within.
    assert _one([0, 0, 0], [[0.09, 0, 0], [0, 0.08, 0]]) == 1


def test_tie_for_closest_reaches_nothing():
    assert _one([0, 0, 0], [[0.05, 0, 0], [-0.05, 0, 0]]) == NONE


def test_unknown_position_is_never_reached():
    assert _one([0, 0, 0], [[np.nan, np.nan, np.nan], [0.05, 0, 0]]) == 1
    assert _one([0, 0, 0], [[np.nan, np.nan, np.nan]]) == NONE


def test_batched_rows_are_independent_and_empty_object_list():
    tcp = np.zeros((3, 3))
    objs = np.array([[[0.05, 0, 0], [1, 0, 0]], [[1, 0, 0], [0.0, 0.02, 0]], [[1, 0, 0], [2, 0, 0]]])
    assert reach_outcome(tcp, objs, 0.1).tolist() == [0, 1, NONE]
    assert reach_outcome(tcp, np.zeros((3, 0, 3)), 0.1).tolist() == [NONE] * 3
