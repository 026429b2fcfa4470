"""Tracklets settled from the labeler's evidence (issue 38 item 3): spans, Hungarian, clashes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from unibody.mocap.relabel import body_stride
from unibody.mocap.tracklets import TrackletConfig, column_spans, label_tracklets, settle_tracklets

L = 4  # labels 0..3, null 4


def _prob(labels, sure=0.9):
    """(T, N, L+1) rows putting ``sure`` on each label and the rest spread over the others."""
    lab = torch.as_tensor(labels)
    p = torch.full((*lab.shape, L + 1), (1 - sure) / L)
    p.scatter_(2, lab[..., None], sure)
    return p


def _no_label_twice(out):
    for row in out:
        real = row[row != L]
        assert len(real) == len(real.unique())


def test_split_evidence_makes_two_spans():
    t = 100
    lab = torch.tensor([[0, 2]] * t)
    lab[60:, 0] = 1  # column 0 switches marker at frame 60 (two trajectories joined)
    lab[60:, 1] = 0  # ... and column 1 takes the other's marker
    lab[:60, 1] = 1
    vis = torch.ones(t, 2, dtype=torch.bool)
    spans = column_spans(_prob(lab), vis)
    assert spans[:, 0].unique().numel() == 2 and spans[:, 1].unique().numel() == 2
    assert int((spans[1:, 0] != spans[:-1, 0]).nonzero()[0]) == 59  # cut at frame 60
    out = settle_tracklets(_prob(lab), vis)
    assert torch.equal(out, lab)
    vote = label_tracklets(lab, vis, L)  # one label per column: 40 % of the frames wrong
    assert (vote == lab).float().mean() < 0.75


def test_short_or_unsure_runs_are_not_cut():
    t = 100
    lab = torch.zeros(t, 1, dtype=torch.long)
    lab[40:60, 0] = 3  # 20 frames: 17.5 frames of evidence, less than the two cuts of an island cost
    vis = torch.ones(t, 1, dtype=torch.bool)
    assert column_spans(_prob(lab), vis).unique().numel() == 1
    assert (settle_tracklets(_prob(lab), vis) == 0).all()
    lab[30:70, 0] = 3  # 40 frames: worth 35 > 2 switches, but an island between two runs of one label
    assert column_spans(_prob(lab), vis).unique().numel() == 1
    lab[70:, 0] = 2  # ... unless the column ends on a third label
    assert column_spans(_prob(lab), vis).unique().numel() == 3
    assert (settle_tracklets(_prob(lab), vis) == lab).all()
    lab[:] = 0
    lab[80:, 0] = 3  # 20 frames at the end: a lead of 0.875 each, 17.5 > switch
    assert column_spans(_prob(lab), vis).unique().numel() == 2
    assert column_spans(_prob(lab), vis, TrackletConfig(min_span=30)).unique().numel() == 1  # < min_span
    assert column_spans(_prob(lab), vis, TrackletConfig(switch=20.0)).unique().numel() == 1


def test_clash_goes_to_the_evidence_and_the_loser_takes_its_next_label():
    t = 50
    lab = torch.tensor([[0, 0, 4]] * t)
    p = _prob(lab)
    p[:, 1, 0], p[:, 1, 1] = 0.6, 0.35  # column 1 is less sure of 0, and next likes 1
    p[:, 1, 2:] = 0.05 / 3
    out = settle_tracklets(p, torch.ones(t, 3, dtype=torch.bool))
    assert (out[:, 0] == 0).all() and (out[:, 1] == 1).all() and (out[:, 2] == L).all()


def test_broken_trajectory_pieces_share_a_label():
    t = 80
    lab = torch.full((t, 3), L)
    lab[:, 0] = 2
    lab[:40, 1] = 1
    lab[40:, 2] = 1  # marker 1's trajectory broken in two columns
    vis = lab != L
    vis[:, 0] = True
    lab[10:14, 1] = 2  # the labeler errs in a few frames
    out = settle_tracklets(_prob(lab), vis)
    assert (out[:40, 1] == 1).all() and (out[40:, 2] == 1).all() and (out[:, 0] == 2).all()
    assert (out[~vis] == L).all()
    _no_label_twice(out)


def test_random_evidence_never_labels_twice():
    g = torch.Generator().manual_seed(0)
    p = torch.rand(60, 7, L + 1, generator=g) ** 4
    p /= p.sum(-1, keepdim=True)
    vis = torch.rand(60, 7, generator=g) > 0.2
    out = settle_tracklets(p, vis, config=TrackletConfig(min_span=5, switch=2.0))
    _no_label_twice(out)
    assert (out[~vis] == L).all()


def test_bad_arguments():
    with pytest.raises(ValueError, match="min_span"):
        TrackletConfig(min_span=0)
    with pytest.raises(ValueError, match="switch"):
        TrackletConfig(switch=-1.0)
    with pytest.raises(TypeError, match="visible"):
        settle_tracklets(torch.zeros(3, 2, L + 1), torch.ones(3, 2))
    with pytest.raises(ValueError, match="visible"):
        settle_tracklets(torch.zeros(3, 2, L + 1), torch.ones(3, 3, dtype=torch.bool))


def test_body_stride():
    assert body_stride(120.0) == 2 and body_stride(100.0) == 2 and body_stride(60.0) == 1 and body_stride(240.0) == 4
    assert np.isclose(120.0 / body_stride(120.0), 60.0)


def test_a_marker_column_unsure_for_a_while_is_not_cut():
    t = 150
    lab = torch.full((t, 1), 2)
    lab[50:100, 0] = L  # 50 frames the labeler calls it a ghost: one span, the marker's
    vis = torch.ones(t, 1, dtype=torch.bool)
    assert column_spans(_prob(lab), vis).unique().numel() == 1
    assert (settle_tracklets(_prob(lab), vis) == 2).all()
    lab[100:, 0] = 1  # ... but a ghost run between two markers' runs is a span of its own
    assert column_spans(_prob(lab), vis).unique().numel() == 3


@pytest.mark.slow
def test_body_check_on_tracklets_of_a_real_file():
    from dataclasses import replace
    from pathlib import Path

    from unibody.mocap.c3d import read_markers
    from unibody.mocap.layout import MarkerLayout
    from unibody.mocap.pipeline import label_sequence, load_labeler

    path = Path(__file__).resolve().parents[2] / "shared/evaldata/c3d/cmu_85_02.c3d"
    if not path.is_file():
        pytest.skip("needs ../shared/evaldata")
    seq = read_markers(path)
    seq = replace(seq, points=seq.points[200:320])
    model = load_labeler("cmu41")
    truth = np.array([model.label_names.index(x) for x in seq.labels])
    lines: list[str] = []
    plain = label_sequence(seq, model)
    checked = label_sequence(seq, model, layout=MarkerLayout.load("cmu41"), progress=lines.append)
    acc = [(x.point_labels == truth)[seq.visible].mean() for x in (plain, checked)]
    assert acc[1] >= acc[0] - 1e-3 and acc[1] > 0.99
    assert any("body check (every 2 frames solved)" in x for x in lines)
