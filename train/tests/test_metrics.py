import numpy as np
import pytest

from gelstereo_train.metrics import Evaluator, hard_mask, match


def test_match_nearest_pairs_first_one_to_one():
    gt = np.array([[0.0, 0.0], [3.0, 0.0]])
    pred = np.array([[1.9, 0.0], [2.6, 0.0]])
    pi, gi, d = match(pred, gt, 2.5)
    # the nearest pair (pred 1, gt 1, 0.4) first; then pred 0 takes gt 0 (1.9)
    assert sorted(zip(pi.tolist(), gi.tolist())) == [(0, 0), (1, 1)]
    pi, gi, _ = match(pred, gt[1:], 2.5)
    assert pi.tolist() == [1] and gi.tolist() == [0]


def test_precision_recall_loss_and_splits():
    gt = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    hard = np.array([False, False, True, True])
    contact = np.array([False, False, False, True])
    pred = np.array([[0.5, 0.0], [10.0, 1.0], [29.0, 5.0], [21.0, 0.0]])
    ev = Evaluator()
    ev.add_image(pred, gt, hard, contact, 2.5, (200, 100))
    s = ev.summary()
    assert s["all"]["PT"] == 3 and s["all"]["PF"] == 1 and s["all"]["T"] == 4
    assert s["all"]["loss_px2"] == pytest.approx((0.25 + 1.0 + 1.0) / 3)
    assert s["easy"]["precision"] == 1.0 and s["easy"]["recall"] == 1.0
    # the false positive (29, 5) is nearest to gt 3: hard and contact
    assert s["hard"]["PF"] == 1 and s["hard"]["PT"] == 1 and s["contact"]["PF"] == 1
    assert s["hard"]["recall"] == 0.5 and s["contact"]["recall"] == 0.0
    # every marker lies on the top row, 0.5 px inside the image: all are border markers
    assert s["border"] == s["all"]


def test_border_markers_and_phantoms_on_the_edge():
    """The same rule as the Rust metrics' border split: within one pitch of an edge; a phantom on the
    edge counts against the border marker nearest it."""
    from gelstereo_train.metrics import border_mask

    gt = np.array([[5.0, 30.0], [15.0, 30.0], [25.0, 30.0], [35.0, 30.0]])
    assert border_mask(gt, (45, 60), 2.5).tolist() == [True, False, False, True]
    ev = Evaluator()
    ev.add_image(np.array([[3.0, 30.0], [15.0, 30.0], [25.0, 30.0], [44.0, 30.0]]), gt, np.zeros(4, bool),
                 np.zeros(4, bool), 2.5, (45, 60))
    b = ev.summary()["border"]
    assert (b["T"], b["PT"], b["PF"]) == (2, 1, 1) and b["loss_px2"] == pytest.approx(4.0)


def test_hard_mask_from_blob_points():
    gt = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    blob = np.array([[0.2, 0.0], [14.0, 0.0]])
    assert hard_mask(blob, gt, 2.5).tolist() == [False, True, True]
