"""The paper's segmentation table (its Table 5): cluster labels rendered into 2D masks and scored against the truth.

Masks: the Gaussians at a frame's state (``mpm``: tracked inside the observed window, forecast after it) are
rendered once per three labels, each label's Gaussians with a one-hot colour and every other Gaussian black, so that
a body behind the floor stays hidden. A pixel takes the label with the largest accumulated weight; the background's
weight is its own Gaussians' plus the transmittance left (static Gaussians are label 0, the background).

Instances: the predicted ones are the dynamic clusters; the true ones are the moving objects of the ground truth's
masks (objects of kind ``static``, such as the floor, are background, as static Gaussians are). Scores, pooled over
every image (test camera × time):

- AP: COCO's 101-point interpolated average precision at IoU ≥ 0.5, predictions ranked by their confidence (the mean
  accumulated weight of their label over their mask), each true instance matched at most once per image;
- PQ = Σ IoU(TP) / (TP + FP/2 + FN/2), F1 = 2TP / (2TP + FP + FN), precision, recall, with a match at IoU > 0.5 (a
  match there is unique);
- mIoU: per image the Hungarian matching that maximises the summed IoU; the mean over true instances of their
  matched IoU (0 when unmatched).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from causalgs.errors import CausalGSError
from causalgs.io import read_json, write_image
from causalgs.model.evaluate import states
from causalgs.model.fit import load_model
from causalgs.render.sh import C0

IOU_MATCH = 0.5
RECALL_POINTS = np.linspace(0.0, 1.0, 101)


@dataclass
class Instance:
    """One predicted instance in one image: its mask [H, W] and confidence."""

    mask: np.ndarray
    score: float


def label_masks(model, state, camera, labels: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The label [H, W] (int) of every pixel and its accumulated weight [H, W], rendering ``labels`` [N] (0 =
    background) of the model's Gaussians at ``state`` from ``camera``."""
    g = model.gaussians
    n_labels = int(labels.max()) + 1
    weights = []
    alpha = None
    sh = torch.zeros(g.n, 1, 3, dtype=g.sh.dtype)
    with torch.no_grad():
        for first in range(0, n_labels, 3):
            colours = torch.zeros(g.n, 3, dtype=g.sh.dtype)
            for c in range(3):
                colours[labels == first + c, c] = 1.0
            sh[:, 0] = (colours - 0.5) / C0  # colour = C0·sh + 0.5: one-hot, exactly
            img, a, _ = g.render(camera, (0.0, 0.0, 0.0), sh=sh, sh_degree=0, **state.overrides())
            weights.append(img.double().clamp(0, 1).numpy())
            alpha = a.double().numpy()
    w = np.concatenate(weights, axis=-1)[..., :n_labels]
    w[..., 0] += 1.0 - alpha  # the background: its Gaussians and whatever nothing covers
    label = w.argmax(-1)
    return label, np.take_along_axis(w, label[..., None], -1)[..., 0]


def predicted_instances(label: np.ndarray, weight: np.ndarray) -> list[Instance]:
    """The non-background labels of one mask image as instances, scored by their mean weight."""
    return [Instance(label == k, float(weight[label == k].mean())) for k in np.unique(label) if k > 0]


def _iou(a: list[np.ndarray], b: list[np.ndarray]) -> np.ndarray:
    out = np.zeros((len(a), len(b)))
    for i, x in enumerate(a):
        for j, y in enumerate(b):
            union = np.logical_or(x, y).sum()
            out[i, j] = np.logical_and(x, y).sum() / union if union else 0.0
    return out


def segmentation_scores(images: list[tuple[list[Instance], list[np.ndarray]]]) -> dict:
    """AP, PQ, F1, precision, recall and mIoU (see the module docstring) over ``images``: per image its predicted
    instances and its true instance masks."""
    tp = fp = fn = 0
    tp_iou = 0.0
    ranked: list[tuple[float, bool]] = []  # (score, true positive) of every prediction, for AP
    matched_iou: list[float] = []
    n_true = 0
    for preds, truths in images:
        n_true += len(truths)
        iou = _iou([p.mask for p in preds], truths)
        good = iou > IOU_MATCH
        tp += int(good.any(1).sum())
        fp += int((~good.any(1)).sum())
        fn += int((~good.any(0)).sum()) if len(preds) else len(truths)
        tp_iou += float(iou[good].sum())
        taken = set()
        for i in sorted(range(len(preds)), key=lambda i: -preds[i].score):  # COCO: greedy by confidence
            cand = [j for j in range(len(truths)) if j not in taken and iou[i, j] >= IOU_MATCH]
            hit = max(cand, key=lambda j: iou[i, j]) if cand else None
            if hit is not None:
                taken.add(hit)
            ranked.append((preds[i].score, hit is not None))
        rows, cols = linear_sum_assignment(-iou) if iou.size else ([], [])
        best = dict(zip(cols, iou[rows, cols], strict=True)) if iou.size else {}
        matched_iou += [float(best.get(j, 0.0)) for j in range(len(truths))]
    ranked.sort(key=lambda r: -r[0])
    hits = np.cumsum([h for _, h in ranked]) if ranked else np.zeros(0)
    precision_curve = hits / np.arange(1, len(ranked) + 1) if ranked else np.zeros(0)
    recall_curve = hits / max(n_true, 1)
    ap = 0.0
    if len(ranked):
        envelope = np.maximum.accumulate(precision_curve[::-1])[::-1]  # precision made monotone, as COCO does
        idx = np.searchsorted(recall_curve, RECALL_POINTS, side="left")
        ap = float(np.mean([envelope[i] if i < len(envelope) else 0.0 for i in idx]))
    return {
        "ap": ap,
        "pq": tp_iou / max(tp + 0.5 * fp + 0.5 * fn, 1e-12),
        "f1": 2 * tp / max(2 * tp + fp + fn, 1),
        "precision": tp / max(tp + fp, 1),
        "recall": tp / max(tp + fn, 1),
        "miou": float(np.mean(matched_iou)) if matched_iou else 0.0,
        "true_instances": n_true,
        "predicted_instances": len(ranked),
        "images": len(images),
    }


def segment_run(run_dir, labels: np.ndarray, times: int = 10, progress=None) -> dict:
    """Render ``labels`` (one per Gaussian of the run, 0 = static) into masks for every test camera at ``times``
    evenly spaced frames of the video, write them as ``RUN/cluster/masks/r_{view:03d}_{frame:03d}.png`` (uint8
    label), and score them against the dataset's ``gt/masks`` where it has them (:func:`segmentation_scores`)."""
    run_dir = Path(run_dir)
    model, data, tl = load_model(run_dir)
    if len(labels) != model.gaussians.n:
        raise CausalGSError(f"{run_dir}: {len(labels)} cluster labels for {model.gaussians.n} Gaussians")
    cams = {}
    for f in data.splits.get("test") or data.splits["val"] or data.train:
        cams.setdefault(f.view if f.view is not None else len(cams), f.camera)
    frames = sorted({int(k) for k in np.round(np.linspace(0, len(tl.times) - 1, max(1, times)))})
    dynamics = "mpm" if model.particles is not None else "velocity"
    st = states(model, frames, dynamics)
    truth_dir = Path(data.root) / "gt" / "masks"
    meta_path = Path(data.root) / "gt" / "meta.json"
    static = set()
    if meta_path.is_file():
        objects = read_json(meta_path, "ground-truth meta").get("objects") or []
        static = {int(o["id"]) for o in objects if isinstance(o, dict) and o.get("kind") == "static" and "id" in o}
    lab = torch.as_tensor(labels, dtype=torch.int64)
    out = run_dir / "cluster" / "masks"
    images = []
    for i, k in enumerate(frames):
        for view, cam in sorted(cams.items()):
            label, weight = label_masks(model, st[k], cam, lab)
            write_image(out / f"r_{view:03d}_{k:03d}.png", label.astype(np.uint8))
            gt_path = truth_dir / f"r_{view:03d}_{k:03d}.png"
            if gt_path.is_file():
                gt = cv2.imread(str(gt_path), cv2.IMREAD_UNCHANGED)
                truths = [gt == o for o in np.unique(gt) if o > 0 and int(o) not in static]
                images.append((predicted_instances(label, weight), truths))
        if progress:
            progress(i + 1, len(frames))
    result = {"frames": frames, "views": sorted(cams), "dynamics": dynamics, "masks": str(out)}
    if images:
        result["scores"] = segmentation_scores(images)
    return result
