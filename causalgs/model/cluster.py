"""``causalgs cluster``: segment a fitted scene into objects by its learned physics.

Features per dynamic Gaussian: its physics code z, log E and nu (the material the model inferred), each column
standardised. K-means (scipy's ``kmeans2``, k-means++ seeding, the best of several restarts by inertia) groups them;
with no K given, K in 2..``k_max`` is chosen by the silhouette score (on a subsample, so it stays cheap). Static
Gaussians are cluster 0, the background.

On datasets with ground truth every Gaussian also gets the true object of its nearest rest particle (as in
:mod:`causalgs.model.recovery`), clusters are matched to objects by the Hungarian method (scipy), and the report
gives the matched accuracy and per-object IoU over Gaussians.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from causalgs.errors import CausalGSError
from causalgs.io import read_json, write_json
from causalgs.model.recovery import true_objects

PALETTE = np.array([
    [0.75, 0.75, 0.75], [0.90, 0.30, 0.25], [0.25, 0.55, 0.90], [0.30, 0.75, 0.35], [0.95, 0.75, 0.20],
    [0.65, 0.35, 0.80], [0.20, 0.80, 0.80], [0.95, 0.50, 0.70], [0.55, 0.40, 0.25],
])  # fmt: skip


def features(npz: dict) -> np.ndarray:
    """Standardised [z, log E, nu] of every Gaussian [N, C + 2]."""
    f = np.concatenate([npz["code"], np.log(npz["E"])[:, None], npz["nu"][:, None]], axis=1).astype(np.float64)
    sd = f.std(0)
    return (f - f.mean(0)) / np.where(sd > 1e-12, sd, 1.0)


def kmeans(x: np.ndarray, k: int, seed: int = 0, restarts: int = 8) -> np.ndarray:
    best, best_inertia = None, np.inf
    for r in range(restarts):
        centres, labels = kmeans2(x, k, minit="++", seed=seed + r)
        inertia = float(((x - centres[labels]) ** 2).sum())
        if inertia < best_inertia and len(np.unique(labels)) == k:
            best, best_inertia = labels, inertia
    if best is None:
        raise CausalGSError(f"K-means found fewer than {k} non-empty clusters: ask for a smaller --k")
    return best


def silhouette(x: np.ndarray, labels: np.ndarray) -> float:
    d = cdist(x, x)
    ks = np.unique(labels)
    a = np.zeros(len(x))
    b = np.full(len(x), np.inf)
    for k in ks:
        m = labels == k
        mean_d = d[:, m].sum(1) / np.maximum(m.sum() - (labels == k), 1)
        a = np.where(m, mean_d, a)
        b = np.where(~m, np.minimum(b, d[:, m].mean(1)), b)
    s = (b - a) / np.maximum(np.maximum(a, b), 1e-12)
    return float(s.mean())


def choose_k(x: np.ndarray, k_max: int, seed: int = 0, sample: int = 1500) -> tuple[int, dict[int, float]]:
    rng = np.random.default_rng(seed)
    sub = x if len(x) <= sample else x[rng.choice(len(x), sample, replace=False)]
    scores = {}
    for k in range(2, min(k_max, len(sub) - 1) + 1):
        try:
            scores[k] = silhouette(sub, kmeans(sub, k, seed))
        except CausalGSError:
            break
    if not scores:
        return 1, scores
    return max(scores, key=scores.get), scores


def cluster_run(run_dir, k: int | None = None, k_max: int = 6, seed: int = 0, masks: int = 0) -> dict:
    """Cluster the run's Gaussians; writes ``RUN/cluster/labels.npy``, ``clusters.ply`` and ``cluster.json``. With
    ``masks`` > 0 also label masks at that many frames, scored against the truth
    (:func:`causalgs.model.segmentation.segment_run`; needs Taichi initialised)."""
    run_dir = Path(run_dir)
    path = run_dir / "physics.npz"
    if not path.is_file():
        raise CausalGSError(f"{run_dir}: no physics.npz (not a fitted run folder)")
    with np.load(path) as z:
        npz = {key: z[key] for key in z.files}
    dyn = npz["dynamic"].astype(bool)
    if dyn.sum() < 2:
        raise CausalGSError(f"{run_dir}: fewer than two dynamic Gaussians; nothing to cluster")
    x = features({key: npz[key][dyn] for key in ("code", "E", "nu")})
    scores: dict[int, float] = {}
    if k is None:
        k, scores = choose_k(x, k_max, seed)
    if k < 1 or k > len(x):
        raise CausalGSError(f"--k {k}: must be between 1 and the number of dynamic Gaussians ({len(x)})")
    dyn_labels = np.zeros(len(x), dtype=np.int64) if k == 1 else kmeans(x, k, seed)
    labels = np.zeros(len(dyn), dtype=np.int64)
    labels[dyn] = dyn_labels + 1
    clusters = []
    for c in range(1, k + 1):
        m = labels == c
        clusters.append({"id": c, "gaussians": int(m.sum()), "E_median": float(np.median(npz["E"][m])),
                         "nu_median": float(np.median(npz["nu"][m])),
                         "centroid": npz["means"][m].mean(0).tolist()})  # fmt: skip
    report = {"k": int(k), "silhouette": {str(a): b for a, b in scores.items()}, "clusters": clusters,
              "static_gaussians": int((~dyn).sum())}  # fmt: skip
    info_path = run_dir / "run.json"
    if info_path.is_file():
        truth = _ground_truth(npz["means"], dyn, Path(read_json(info_path, "run info")["data"]))
        if truth is not None:
            report["ground_truth"] = _match(labels, truth)
    out = run_dir / "cluster"
    out.mkdir(exist_ok=True)
    np.save(out / "labels.npy", labels)
    _write_ply(run_dir / "gaussians.ply", labels, out / "clusters.ply")
    if masks > 0:
        from causalgs.model.segmentation import segment_run  # it loads the model (torch, Taichi); clustering does not

        report["segmentation"] = segment_run(run_dir, labels, masks)
    write_json(out / "cluster.json", report)
    return report


def _ground_truth(means: np.ndarray, dyn: np.ndarray, data_dir: Path, reach: float = 0.03) -> np.ndarray | None:
    """Each Gaussian's true object (:func:`causalgs.model.recovery.true_objects`): 0 for static ones, -1 for dynamic
    ones near no true particle."""
    label = true_objects(means, data_dir, reach)
    return None if label is None else np.where(dyn, label, 0)


def _match(labels: np.ndarray, truth: np.ndarray) -> dict:
    """Hungarian matching of dynamic clusters to true bodies over the dynamic Gaussians near a body."""
    m = (truth > 0) & (labels > 0)
    cl, ob = np.unique(labels[m]), np.unique(truth[m])
    if len(cl) == 0 or len(ob) == 0:
        return {"matched_accuracy": None, "objects": []}
    overlap = np.array([[np.sum((labels[m] == c) & (truth[m] == o)) for o in ob] for c in cl])
    rows, cols = linear_sum_assignment(-overlap)
    objects = []
    for r, c in zip(rows, cols, strict=True):
        inter = overlap[r, c]
        union = np.sum((labels[m] == cl[r]) | (truth[m] == ob[c]))
        objects.append({"object": int(ob[c]), "cluster": int(cl[r]), "iou": float(inter / union)})
    return {"matched_accuracy": float(overlap[rows, cols].sum() / m.sum()), "objects": objects,
            "gaussians_compared": int(m.sum())}  # fmt: skip


def _write_ply(src: Path, labels: np.ndarray, dst: Path) -> None:
    """The run's Gaussians with their colour replaced by their cluster's (SH DC only), for any 3DGS viewer."""
    from causalgs.ply import read_gaussians_ply, write_gaussians_ply

    g = read_gaussians_ply(src)
    if len(g["means"]) != len(labels):
        raise CausalGSError(f"{src}: {len(g['means'])} Gaussians, but physics.npz has {len(labels)}")
    sh = np.zeros_like(g["sh"])
    sh[:, 0] = (PALETTE[labels % len(PALETTE)] - 0.5) / 0.28209479177387814
    write_gaussians_ply(dst, g["means"], g["quats"], g["scales"], g["opacities"], sh)
