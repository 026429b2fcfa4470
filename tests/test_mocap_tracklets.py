"""Tracklet voting, conflict resolution and labeling metrics on hand-made cases."""

from __future__ import annotations

import pytest
import torch

from unibody.mocap.metrics import labeling_scores
from unibody.mocap.tracklets import label_tracklets, tracklet_labels, tracklet_votes

NULL = 3  # labels 0, 1, 2 and null 3


def _t(rows):
    return torch.tensor(rows)


def test_majority_vote_per_column():
    frame_labels = _t([[0, 1, 3, 2, 0], [0, 1, 3, 2, 0], [2, 1, 0, 3, 0], [0, 0, 3, 3, 0]])
    visible = torch.ones(4, 5, dtype=torch.bool)
    visible[:, 4] = False  # never visible -> null
    votes = tracklet_votes(frame_labels, visible, NULL)
    # col 0: 0,0,2,0 -> 0 (3/4); col 1: 1,1,1,0 -> 1 (3/4); col 2: mostly null -> null (3/4)
    # col 3: 2,2,null,null -> tie between 2 and null -> the marker label 2 (2/4)
    assert votes.labels.tolist() == [0, 1, 3, 2, 3]
    torch.testing.assert_close(votes.share, torch.tensor([0.75, 0.75, 0.75, 0.5, 0.0], dtype=torch.float64))
    assert torch.equal(tracklet_labels(frame_labels, visible, NULL), votes.labels)


def test_invisible_frames_do_not_vote():
    frame_labels = _t([[1], [1], [2], [2], [2]])
    visible = torch.tensor([[True], [True], [False], [False], [True]])
    assert tracklet_labels(frame_labels, visible, NULL).tolist() == [1]  # 1,1,2 over visible frames


def test_conflicts_keep_the_larger_share():
    # columns 0 and 1 both vote label 0: column 0 with share 1, column 1 with 2/3.
    # column 2 (visible in frames 2-3) also votes 0 with share 1: it ties column 0 and loses
    # to it in frame 2 (lower index wins), but keeps label 0 in frame 3 where it is alone.
    frame_labels = _t([[0, 0, 1], [0, 0, 1], [0, 2, 0], [0, 3, 0]])
    visible = torch.tensor([[True, True, False], [True, True, False], [True, True, True], [False, False, True]])
    out = label_tracklets(frame_labels, visible, NULL)
    expected = _t([[0, 3, 3], [0, 3, 3], [0, 3, 3], [3, 3, 0]])
    assert out.tolist() == expected.tolist()
    # no label twice in a frame
    for row in out:
        real = row[row != NULL]
        assert len(real) == len(real.unique())


def test_conflict_tie_goes_to_lower_column():
    frame_labels = _t([[1, 1], [1, 1]])
    visible = torch.ones(2, 2, dtype=torch.bool)
    assert label_tracklets(frame_labels, visible, NULL).tolist() == [[1, 3], [1, 3]]


def test_tracklet_errors():
    with pytest.raises(ValueError, match="visible: expected shape"):
        tracklet_labels(_t([[0, 1]]), torch.ones(2, 2, dtype=torch.bool), NULL)
    with pytest.raises(TypeError, match="visible: expected a bool"):
        tracklet_labels(_t([[0, 1]]), torch.ones(1, 2), NULL)
    with pytest.raises(ValueError, match="frame_labels: visible entries"):
        tracklet_labels(_t([[0, 4]]), torch.ones(1, 2, dtype=torch.bool), NULL)


def test_scores_hand_computed():
    truth = _t([0, 0, 1, 1, 2, 3, 3])
    pred = _t([0, 1, 1, 1, 3, 3, 0])
    # class 0: tp 1, pred 2, true 2 -> p 1/2, r 1/2, f 1/2
    # class 1: tp 2, pred 3, true 2 -> p 2/3, r 1,   f 0.8
    # class 2: tp 0, pred 0, true 1 -> p 0,   r 0,   f 0
    # class 3: tp 1, pred 2, true 2 -> p 1/2, r 1/2, f 1/2
    s = labeling_scores(pred, truth, null=NULL)
    assert s["accuracy"] == pytest.approx(4 / 7)
    assert s["precision"] == pytest.approx((0.5 + 2 / 3 + 0 + 0.5) / 4)
    assert s["recall"] == pytest.approx((0.5 + 1 + 0 + 0.5) / 4)
    assert s["f1"] == pytest.approx((0.5 + 0.8 + 0 + 0.5) / 4)


def test_scores_only_present_labels_count():
    # label 2 appears nowhere: the macro average runs over {0, 1, 3} only
    s = labeling_scores(_t([0, 1, 3]), _t([0, 1, 3]), null=NULL)
    assert s == {"accuracy": 1.0, "f1": 1.0, "precision": 1.0, "recall": 1.0}
    s = labeling_scores(_t([3, 3]), _t([0, 3]), null=NULL)
    # class 0: p 0 (never predicted), r 0; class 3: p 1/2, r 1, f 2/3
    assert s["precision"] == pytest.approx(0.25) and s["recall"] == pytest.approx(0.5)
    assert s["f1"] == pytest.approx(1 / 3)


def test_scores_errors():
    with pytest.raises(ValueError, match="truth: expected shape"):
        labeling_scores(_t([0, 1]), _t([0]), null=NULL)
    with pytest.raises(ValueError, match="at least one point"):
        labeling_scores(_t([]), _t([]), null=NULL)
    with pytest.raises(ValueError, match="pred: expected integer labels"):
        labeling_scores(_t([5]), _t([0]), null=NULL)
