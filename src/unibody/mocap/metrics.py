"""Labeling metrics (paper 003 §5; as SOMA reports them): accuracy and macro precision/recall/F1.

Every real point is one sample; its class is a marker label or the null label. Macro
averages run over the classes present in the truth or the prediction (null included), as
scikit-learn's ``classification_report`` does; a class that is never predicted has
precision 0, one that never occurs has recall 0, and F1 is the per-class harmonic mean
averaged over classes (not the harmonic mean of the averages).
"""

from __future__ import annotations

import torch

from .._checks import check_shape

__all__ = ["labeling_scores"]


def labeling_scores(pred: torch.Tensor, truth: torch.Tensor, null: int) -> dict[str, float]:
    """Score predicted labels against the truth.

    Args:
        pred: (K,) int predicted labels, one per real point, in [0, null].
        truth: (K,) int true labels (``null`` for ghost points).
        null: the null label (= number of marker labels L).

    Returns:
        ``{"accuracy", "f1", "precision", "recall"}``, each in [0, 1]; the last three are
        macro averages over the labels present in ``truth`` or ``pred`` (null included).

    Raises:
        ValueError: mismatched or empty inputs, labels outside [0, null].
    """
    sizes: dict[str, int] = {}
    check_shape(pred, "K", name="pred", sizes=sizes)
    check_shape(truth, "K", name="truth", sizes=sizes)
    if sizes["K"] == 0:
        raise ValueError("pred: expected at least one point, got 0")
    for x, name in ((pred, "pred"), (truth, "truth")):
        if x.is_floating_point() or bool(((x < 0) | (x > null)).any()):
            raise ValueError(f"{name}: expected integer labels in [0, {null}]")
    pred, truth = pred.long().cpu(), truth.long().cpu()
    k = null + 1
    tp = torch.bincount(truth[pred == truth], minlength=k).double()
    n_pred = torch.bincount(pred, minlength=k).double()
    n_true = torch.bincount(truth, minlength=k).double()
    present = (n_pred > 0) | (n_true > 0)
    precision = torch.where(n_pred > 0, tp / n_pred.clamp(min=1), 0.0)
    recall = torch.where(n_true > 0, tp / n_true.clamp(min=1), 0.0)
    f1 = torch.where(tp > 0, 2 * precision * recall / (precision + recall).clamp(min=1e-300), 0.0)
    return {
        "accuracy": float(tp.sum() / sizes["K"]),
        "f1": float(f1[present].mean()),
        "precision": float(precision[present].mean()),
        "recall": float(recall[present].mean()),
    }
