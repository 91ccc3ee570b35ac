"""Timestamp association: nearest stamp within max_diff, evo's tie and direction rules."""

from __future__ import annotations

import numpy as np
import pytest

from kvtracker_sdk.errors import ConfigError, EvaluationError
from kvtracker_sdk.eval.association import associate, associate_trajectories
from kvtracker_sdk.io.files.trajectory import Trajectory
from tests.helpers import dev_dependency


def _trajectory(stamps: list[float]) -> Trajectory:
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    poses[:, 0, 3] = np.arange(len(stamps))  # x = original index, to check which pose was kept
    return Trajectory(np.array(stamps), poses)


def test_nearest_within_max_diff_and_ties_to_the_earlier_stamp() -> None:
    query = np.array([0.0, 1.02, 2.5, 3.0, 9.0])
    target = np.array([0.01, 1.0, 1.04, 2.0, 3.0, 2.99])  # unsorted on purpose
    q, t = associate(query, target, max_diff=0.03)
    assert q.tolist() == [0, 1, 3]  # 2.5 and 9.0 have no stamp within 30 ms
    # 1.02 is 20 ms from both 1.0 and 1.04 -> the earlier; 3.0 matches exactly (index 4)
    assert t.tolist() == [0, 1, 4]
    q, t = associate(query, target, max_diff=0.03, target_offset=0.5)
    assert q.tolist() == [2] and t.tolist() == [3]  # 2.0 + 0.5 == 2.5
    empty_q, empty_t = associate(np.zeros(0), target)
    assert len(empty_q) == len(empty_t) == 0
    with pytest.raises(ConfigError):
        associate(query, target, max_diff=-1.0)


def test_trajectories_are_matched_from_the_shorter_one() -> None:
    est = _trajectory([1.0, 2.0, 3.0])
    ref = _trajectory([0.9, 0.995, 1.004, 2.003, 2.5, 3.2])
    association = associate_trajectories(est, ref, max_diff=0.01)
    assert association.est_indices.tolist() == [0, 1]
    assert association.ref_indices.tolist() == [2, 3]
    assert association.ref.positions[:, 0].tolist() == [2.0, 3.0]
    assert len(association) == 2
    assert association.max_gap == pytest.approx(0.004)
    assert association.to_dict() == {
        "matched": 2,
        "est_poses": 3,
        "ref_poses": 6,
        "max_diff_s": 0.01,
        "offset_s": 0.0,
        "max_gap_s": pytest.approx(0.004),
    }
    # a longer estimate is matched from the reference side; est + offset is on the ref clock:
    # 1.004 - 0.5 is nearest to 0.5 (0.995 - 0.5 is 1 ms further)
    shifted = associate_trajectories(ref, _trajectory([0.0, 0.5]), max_diff=0.01, offset=-0.5)
    assert shifted.est_indices.tolist() == [2] and shifted.ref_indices.tolist() == [1]


def test_no_match_is_a_typed_error_that_shows_both_spans() -> None:
    with pytest.raises(EvaluationError, match="no timestamps match.*estimate spans 100"):
        associate_trajectories(_trajectory([100.0, 101.0]), _trajectory([0.0, 1.0, 2.0]))


def test_same_pairs_as_evo_on_random_stamps() -> None:
    sync = dev_dependency("evo.core.sync")
    rng = np.random.default_rng(11)
    for _ in range(20):
        short = np.sort(rng.uniform(0, 10, size=40))
        long = np.sort(rng.uniform(0, 10, size=200))
        offset = float(rng.uniform(-0.05, 0.05))
        evo_q, evo_t = sync.matching_time_indices(short, long, max_diff=0.02, offset_2=offset)
        q, t = associate(short, long, max_diff=0.02, target_offset=offset)
        assert q.tolist() == evo_q and t.tolist() == evo_t
