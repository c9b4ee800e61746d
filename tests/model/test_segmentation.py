"""The segmentation table: label masks rendered with occlusion, and AP / PQ / F1 / precision / recall / mIoU against
hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from causalgs.cameras import Camera, look_at
from causalgs.model.segmentation import Instance, label_masks, predicted_instances, segmentation_scores


def _box(y0, y1, x0, x1, shape=(20, 20)) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    m[y0:y1, x0:x1] = True
    return m


def test_a_perfect_segmentation_scores_one_everywhere():
    truths = [_box(0, 5, 0, 5), _box(10, 15, 10, 15)]
    preds = [Instance(t.copy(), 0.9) for t in truths]
    s = segmentation_scores([(preds, truths), (preds[:1], truths[:1])])
    for key in ("ap", "pq", "f1", "precision", "recall", "miou"):
        assert s[key] == pytest.approx(1.0), key
    assert s["true_instances"] == 3 and s["predicted_instances"] == 3 and s["images"] == 2


def test_hand_computed_scores():
    """One truth (25 px); a confident stray prediction (IoU 0) and a less confident one covering 20 of its pixels plus
    nothing else (IoU 0.8); a second image whose truth is missed."""
    truth = _box(0, 5, 0, 5)
    hit = _box(0, 4, 0, 5)  # 20 px inside the truth: IoU 20 / 25
    stray = _box(10, 12, 10, 12)
    s = segmentation_scores([([Instance(stray, 0.95), Instance(hit, 0.9)], [truth]), ([], [_box(5, 9, 5, 9)])])
    tp, fp, fn = 1, 1, 1
    assert s["precision"] == pytest.approx(tp / (tp + fp)) and s["recall"] == pytest.approx(tp / (tp + fn))
    assert s["f1"] == pytest.approx(2 * tp / (2 * tp + fp + fn))
    assert s["pq"] == pytest.approx(0.8 / (tp + 0.5 * fp + 0.5 * fn))
    assert s["miou"] == pytest.approx((0.8 + 0.0) / 2)
    # ranked: stray (FP) then hit (TP): precision 0, 1/2 at recall 0, 1/2; the envelope is 1/2 up to recall 1/2 and
    # nothing reaches beyond it: 51 of the 101 recall points at 1/2
    assert s["ap"] == pytest.approx(51 * 0.5 / 101)


def test_a_match_needs_more_than_half_the_union():
    truth = _box(0, 10, 0, 10)
    half = _box(0, 5, 0, 10)  # IoU exactly 0.5: not a match for PQ (> 0.5); for AP at IoU ≥ 0.5 it is
    s = segmentation_scores([([Instance(half, 1.0)], [truth])])
    assert s["precision"] == 0.0 and s["pq"] == 0.0 and s["ap"] == pytest.approx(1.0)
    assert s["miou"] == pytest.approx(0.5)


def test_label_masks_render_each_body_where_it_is_and_hide_it_behind_a_static_wall(ti64):
    from causalgs.model.config import FitConfig
    from causalgs.model.gaussians import Gaussians
    from causalgs.model.scene import CausalGS, State

    rng = np.random.default_rng(0)
    blobs = [np.array([0.0, -0.3, 0.0]), np.array([0.0, 0.3, 0.0]), np.array([0.6, 0.3, 0.0])]  # body 1, body 2, wall
    pts = np.concatenate([c + 0.05 * rng.standard_normal((150, 3)) for c in blobs])
    g = Gaussians.from_points(pts, np.full((len(pts), 3), 0.5), sh_degree=0, opacity=0.99)
    with torch.no_grad():
        g.scales.fill_(math.log(0.04))
    m = CausalGS(FitConfig(), g, [-1.0] * 3, [1.0] * 3, fps=30.0, train_frames=4).double()
    labels = torch.tensor([1] * 150 + [2] * 150 + [0] * 150)
    cam = Camera.from_blender(look_at(np.array([2.5, 0.0, 0.0]), np.zeros(3)), 48, 48, fov_x=0.9)
    label, weight = label_masks(m, State(g.means.detach()), cam, labels)
    for c, want in ((blobs[0], 1), (blobs[1], 0), (np.array([0.0, 0.9, 0.9]), 0)):
        u, v = (int(a) for a in cam.project(c[None])[0][0])
        assert label[v, u] == want  # body 2 sits behind the wall (label 0); empty space is background
    assert (label == 2).sum() < 0.2 * (label == 1).sum()  # at most a fringe of body 2 peeks past the wall
    inst = predicted_instances(label, weight)
    assert inst[0].mask.sum() == (label == 1).sum() and 0.5 < inst[0].score <= 1.0
