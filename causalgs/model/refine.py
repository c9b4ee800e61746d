"""Per-frame refinement of the tracked motion: what the images of each frame say, without the velocity field's memory.

The kinematic stage tracks by integrating one smooth velocity field from t = 0 (:mod:`causalgs.model.kinematic`).
That is the right prior for a forecast and the wrong one for a *measurement* of an impact: a velocity that turns
within a frame is smoothed over several, and every error of the velocity is carried into every later frame. On
``causalgs synth toss --fps 120 --frames 96`` (a soft block landing a third of a second in; 20 views of 128²) the
tracked motion missed the true displacement by 18–22 mm at frames 34–43 (four pixels), though it was within 1–2 mm
in flight.

:func:`refine_tracks` fits, frame by frame and independently of the other frames' errors, one rigid correction per
motion pattern to that frame's training images:

    x = Σ_k h_k (A_k x0 + b_k),   A_k = Q_k R_k,   b_k = Q_k (t_k − c_k) + c_k + d_k,   Q_k = exp([r_k]×),

where (R_k, t_k) is pattern k's motion by the kinematic fit at that frame, c_k its h-weighted centroid there, and
the turn r_k and shift d_k the correction, started from the previous frame's (motion is continuous). The
Gaussians' covariances follow the blended Jacobian J = Σ_k h_k A_k (Σ = J Σ0 Jᵀ). Each frame is a small,
well-posed problem (6 numbers per pattern against every training view of that frame). On the landing above (the
defaults: 40 steps of two views a frame) it brought the whole window from 10.5 to 2.7 mm RMS: frames 26–38 from
5–17 mm to 0.5–0.8 mm, the impact (frames 40–44) from 14–21 mm to 1–8 mm, the bounce after it from 7–16 mm to 2–4 mm;
held-out cameras scored it at a median 31.7 dB per frame against 26.4. What it leaves at and after the impact is
mostly the body's own deformation, which one rigid motion per pattern cannot follow (the true block departs from its
best rigid motion by up to 5.7 mm at the impact and 2–3.5 mm in the wobble after it). A free affine correction per
pattern, tried on the same frames, followed the impact a little closer (3–6 mm) and then drifted to 9–11 mm after
it: the images of a plain block do not pin down its stretch. A stretch about each pattern's centroid, with the
tracks' rigid part (:func:`~causalgs.discover.observation.rigid_projection`) taken as the measurement, was tried on
the plastic landing, where the block flattens to a pancake (5 cm high, 34 × 31 cm across): it raised the held-out
PSNR after the impact from 22 to 24 dB, but moved the rigid part further from the truth's (12–16 → 17–20 mm after
the impact); on the elastic landing it made the impact worse (3.9 → 8.6 mm) and the bounce after it better (1.6–2.0
→ 1.1–1.3 mm). So the refinement is rigid by default, and a stretch per pattern is an option (``stretch``):

    A_k = Q_k exp(S_k) R_k,   b_k = Q_k exp(S_k) (t_k − c_k) + c_k + d_k,

S_k a symmetric log-strain (6 numbers), carried from frame to frame like r_k and d_k. A stretch can grow where no
camera sees it: under an opaque floor. On the dent of the video table (a block landing with a 5 kPa yield stress,
144 frames) the stretching tracks lengthened the block 2.6× downwards, to 25 cm under the floor, while its top stayed
where the images put it: 37–67 mm from the truth's material points after the impact (41.2 mm RMS over the window),
at the same held-out PSNR as the rigid tracks. So each frame's loss also counts the moving Gaussians' mean depth under
the floor the cameras see (``ground``, per metre; :func:`visible_floor`). With 10 per metre the same tracks stayed
4.4–6.6 mm from the truth after the impact (4.26 mm RMS; the rigid tracks: 6.6–8.6 mm, 6.37 mm RMS). Against the
physics' learned ground instead, 1.2 cm lower, they came out alike (4.15 mm RMS; their extent at the last observed
frame 22.0 × 17.9 × 10.7 cm, the truth's 22.3 × 19.0 × 9.7). On the splat (1.5 kPa) the term took the stretching
tracks from 19.5 to 15.6 mm RMS (the rigid ones: 21.3). The stretching tracks are affine and are measured through
an affine lens (:func:`~causalgs.discover.observation.affine_projection`), so a squash is compared in full, not
judged by its rigid part; discovery takes them only where held-out cameras show that the bodies deform for good
(:func:`causalgs.discover.video.choose_lens`). On images of a fitted motion whose last frame was squashed to 0.7 of
its height and 1.2 of its width (the test fixture, 32² images), the stretching tracks followed
the squashed positions within 9.5 mm RMS and the rigid ones within 47 mm (the squash itself: 52 mm).

One strain per pattern cannot show a body that tapers: on the dent the true foot spread on the ground (the lower
third of the block 12 mm further from the centre in the mean after the impact, the upper third 1 mm), while the
stretching tracks widened the whole block alike (4 mm at the foot, 3 mm at the top): 4.3 mm RMS from the truth over
the window, 5.4 mm after the impact, and the yield stress fitted to them 23.5% off. So the stretch may also bend
each body (``bend``): x += P_b φ((x0 − c_b)/r_b), φ the six second-order monomials about the body's rest centroid
c_b in units of its RMS radius r_b, P_b (3 × 6, metres) carried from frame to frame like the rest (a body is a
pattern dominant for 5% of the moving Gaussians, smaller ones joined to the body they mix with most, as discovery
groups its particles). On the dent that took the tracks to 2.1 mm RMS from the truth (0.8 mm before the impact, as
without; 2.6 mm after it), the foot's spread within 1.5 mm of the truth's, and held-out cameras from a median 28.0 to
30.8 dB after the impact; the bend stayed near 1 mm until the impact and reached 26–39 mm after it. Where the images
do not ask for it, a bend fits the fit's own errors: on the tiny falling ball of the tests, whose moving Gaussians
span 1.2 m, it grew to 12 mm at the first frame and lost 6 dB at the last, so discovery takes bent tracks only where
held-out cameras ask for them (:func:`causalgs.discover.video.choose_lens`).

The result (:class:`Tracks`) is each pattern's affine motion at every observed frame and the PSNR of the tracked
and the refined motion on the frame's held-out cameras (the dataset's val split; its training cameras where it has
none), so that what the refinement gained is measured on images it never fitted. :func:`cached_tracks` keeps it in
the run folder (``tracks.npz``, or ``tracks-affine.npz`` with the stretch, ``tracks-bent.npz`` with the bend;
keyed by the fit and the settings). Refined from one half of each frame's training cameras (``half``,
:func:`camera_half`; ``tracks-half0.npz``, ...), two such tracks land apart by what tracks from half the cameras err
independently (:func:`causalgs.discover.video.split_sigma`).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from causalgs.errors import CausalGSError
from causalgs.io import write_npz
from causalgs.model.kinematic import blend, pattern_motion, skew
from causalgs.render.reference import quat_scale_to_cov


@dataclass(frozen=True)
class RefineConfig:
    iterations: int = 40  # Adam steps per frame
    views: int = 2  # training images per step (drawn at random among the frame's cameras)
    lr_shift: float = 1e-3  # m per step, the correction's translation d_k
    lr_turn: float = 1e-2  # rad per step, the correction's rotation r_k
    score_views: int = 2  # held-out cameras per frame for the PSNR before and after
    seed: int = 0
    # also fit a stretch S_k per pattern (x ← Q_k exp(S_k)(x − c_k) + c_k + d_k, S_k symmetric): affine tracks, for
    # bodies that deform for good (see :func:`choose_lens`)
    stretch: bool = False
    lr_stretch: float = 1e-2  # per step, the stretch's log-strain S_k
    # weight (per metre) of the mean depth of the moving Gaussians under the floor the cameras see
    # (:func:`visible_floor`), added to each frame's image loss (0: none). No camera sees under an opaque floor, so
    # nothing else stops a stretch from growing there (see the module docstring)
    ground: float = 0.0
    # with the stretch, also a second-order displacement per body (x += P_b φ((x0 − c_b)/r_b), φ the six
    # second-order monomials, c_b and r_b the body's rest centroid and RMS radius): a body that tapers or bulges (a
    # foot spreading on the ground), which one strain per pattern cannot show (see the module docstring)
    bend: bool = False
    lr_bend: float = 5e-4  # m per step, the bend's coefficients P_b
    # before a frame's steps, compare the last frame's correction with none (the velocity field's own motion) on the
    # frame's first ``restart`` training images and start from the better (0: always the last frame's). At a bounce
    # the carried correction points the wrong way for a frame or two: a ball bouncing at 30 fps scored 27.2 dB on
    # held-out cameras at its third impact from the carried start, where the field's motion alone scored 32.2.
    restart: int = 0


@dataclass
class Tracks:
    """Every pattern's affine motion x = A x0 + b at observed frames 0..n−1 (``A`` [n, K, 3, 3], ``b`` [n, K, 3])
    and the mean PSNR per frame of the kinematic (``psnr_before``) and refined (``psnr_after``) motion on
    ``scored_on`` ("val" or "train") cameras. With a bend (``RefineConfig.bend``), also every body's second-order
    displacement ``P`` [n, B, 3, 6] (m) about its rest centroid ``centre`` [B, 3], in units of its RMS radius
    ``radius`` [B], a point's body being ``pattern_body`` [K] of its dominant pattern (:func:`pattern_bodies`)."""

    A: np.ndarray
    b: np.ndarray
    psnr_before: np.ndarray
    psnr_after: np.ndarray
    scored_on: str
    key: str
    stretch: bool = False  # refined with a stretch per pattern (``RefineConfig.stretch``): affine, not rigid
    P: np.ndarray | None = None
    centre: np.ndarray | None = None
    radius: np.ndarray | None = None
    pattern_body: np.ndarray | None = None

    @property
    def lens(self) -> str:
        """"affine" where the tracks stretch each pattern, else "rigid"."""
        return "affine" if self.stretch else "rigid"

    @property
    def kind(self) -> str:
        """How they were refined: "rigid", "affine" or "bent" (affine, and bent per body)."""
        return "bent" if self.P is not None else self.lens

    def bodies(self, h: torch.Tensor) -> np.ndarray | None:
        """[N] the bend's body of points with mixtures ``h`` [N, K] (None: the tracks have no bend)."""
        if self.P is None:
            return None
        return np.asarray(self.pattern_body)[h.argmax(1).cpu().numpy()]

    def positions(self, h: torch.Tensor, x0: torch.Tensor, frames=None) -> torch.Tensor:
        """Positions [F, N, 3] at ``frames`` (default all) of points with mixtures ``h`` [N, K] starting at ``x0``."""
        frames = range(len(self.A)) if frames is None else [int(k) for k in frames]
        A = torch.from_numpy(self.A).to(x0.dtype)
        b = torch.from_numpy(self.b).to(x0.dtype)
        out = torch.stack([place(h.to(x0.dtype), x0, A[k], b[k]) for k in frames])
        if self.P is None:
            return out
        phi = bend_basis(x0, torch.from_numpy(self.centre).to(x0.dtype), torch.from_numpy(self.radius).to(x0.dtype),
                         torch.from_numpy(self.bodies(h)))  # fmt: skip
        P = torch.from_numpy(self.P).to(x0.dtype)
        return out + torch.stack([bend(phi, P[k]) for k in frames])


def pattern_bodies(h: torch.Tensor, min_share: float = 0.05) -> np.ndarray:
    """[K] the body of every motion pattern, for the mixtures ``h`` [N, K] of the moving points: a pattern that is
    the dominant one of at least ``min_share`` of the points is a body of its own (numbered 0..B−1), a smaller one
    joins the body it mixes with most (as discovery groups its particles, :func:`causalgs.discover.video._bodies`)."""
    hn = h.detach().double().cpu().numpy()
    K = hn.shape[1]
    counts = np.bincount(hn.argmax(1), minlength=K)
    big = counts >= max(1, min_share * len(hn))
    if not big.any():
        big[counts.argmax()] = True
    number = np.cumsum(big) - 1
    out = np.empty(K, dtype=np.int64)
    share = hn.T @ hn[:, big]  # [K, bodies]: how much each pattern mixes with each big one
    for k in range(K):
        out[k] = number[k] if big[k] else int(share[k].argmax())
    return out


def bend_basis(x0: torch.Tensor, centre: torch.Tensor, radius: torch.Tensor, body: torch.Tensor) -> tuple:
    """(φ [N, 6], ∂φ/∂x0 [N, 6, 3], body [N]): the second-order monomials of u = (x0 − c_body)/r_body,
    (u_x², u_y², u_z², u_y u_z, u_x u_z, u_x u_y), and their derivatives, for points of the given bodies (their
    centres [B, 3] and radii [B]: of order one over every body, whatever its size)."""
    r = radius[body][:, None]
    u = (x0 - centre[body]) / r
    ux, uy, uz = u.unbind(-1)
    z = torch.zeros_like(ux)
    phi = torch.stack([ux * ux, uy * uy, uz * uz, uy * uz, ux * uz, ux * uy], -1)
    rows = [[2 * ux, z, z], [z, 2 * uy, z], [z, z, 2 * uz], [z, uz, uy], [uz, z, ux], [uy, ux, z]]
    dphi = torch.stack([torch.stack(row, -1) for row in rows], -2) / r[..., None]
    return phi, dphi, body


def bend(basis: tuple, P: torch.Tensor) -> torch.Tensor:
    """[N, 3] the displacement P_body φ of every point (``basis`` from :func:`bend_basis`, P [B, 3, 6])."""
    phi, _, body = basis
    return torch.einsum("nij,nj->ni", P[body], phi)


def bend_jacobian(basis: tuple, P: torch.Tensor) -> torch.Tensor:
    """[N, 3, 3] ∂(P_body φ)/∂x0 of every point."""
    _, dphi, body = basis
    return P[body] @ dphi


def place(h: torch.Tensor, x0: torch.Tensor, A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """x = Σ_k h_k (A_k x0 + b_k) [N, 3] for mixtures h [N, K] and the patterns' affine motion A [K, 3, 3], b [K, 3]
    (the kinematic path's blend, :func:`causalgs.model.kinematic.blend`, without the rotations)."""
    return blend(h, x0, None, A, b, None)[0]


def jacobian(h: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    """∂x/∂x0 = Σ_k h_k A_k [N, 3, 3] (the mixtures are labels carried by the points, not functions of x)."""
    return torch.einsum("nk,kij->nij", h, A)


def symmetric(s: torch.Tensor) -> torch.Tensor:
    """[..., 6] → [..., 3, 3]: the symmetric matrix with diagonal s[0:3] and off-diagonal (yz, xz, xy) s[3:6]."""
    a, b, c, yz, xz, xy = s.unbind(-1)
    return torch.stack([a, xy, xz, xy, b, yz, xz, yz, c], dim=-1).reshape(*s.shape[:-1], 3, 3)


def corrected(A: torch.Tensor, b: torch.Tensor, c: torch.Tensor, r: torch.Tensor, d: torch.Tensor,
              s: torch.Tensor | None = None):  # fmt: skip
    """The patterns' motion (A, b) [K, 3, 3], [K, 3] after the correction x ← Q M (x − c) + c + d about their
    centroids c [K, 3], Q = exp([r]×) for the rotation vectors r [K, 3] and M = exp(S) for the log-strains s [K, 6]
    (:func:`symmetric`; None: M = I, a rigid correction)."""
    Q = torch.linalg.matrix_exp(skew(r))
    if s is not None:
        Q = Q @ torch.linalg.matrix_exp(symmetric(s))
    return Q @ A, (Q @ (b - c)[..., None])[..., 0] + c + d


def visible_floor(model) -> tuple[np.ndarray, float] | None:
    """(n, height) of the floor the cameras see under the moving Gaussians, the plane n·x = height with n = +z: the
    densest level of the static Gaussians at or below where the moving ones start
    (:func:`causalgs.model.scene.floor_level`: a floor is a plane full of Gaussians). None where no level stands
    out. This, not the physics' learned ground, is what hides a stretch: a grid's contact plane may sit a cell
    lower or higher than the surface it stands for (on the dent, the learned plane was 1.2 cm under this one).

    Where a body lands and stays, the fit moves patches of floor with it (see
    :func:`causalgs.model.scene.floor_patches`): the lowest moving Gaussians are the floor's own, the heights
    searched end just above the floor, and no slab of so few stands out. There the floor is the one under the
    moving Gaussians' median start, as :func:`~causalgs.model.scene.floor_patches` finds it. On the sticky ground of
    the video table (seed 0) the first search found none: the stretching tracks went without a floor, sank the
    block's lowest point up to 9.5 cm under it and made the block 1.76× its height at the rebound (25.6 mm RMS from
    the truth; the rigid tracks 4.6). The second search found the floor 5.2 mm under z = 0, and the tracks refined
    above it were 1.37 mm RMS from the truth over the fit window (the rigid ones 2.25)."""
    from causalgs.model.scene import floor_level

    dyn = model.dynamic
    if not bool(dyn.any()) or bool(dyn.all()):
        return None
    z = model.gaussians.means.detach().double()[:, 2]
    size = float((model.hi - model.lo).max())
    level = floor_level(z[~dyn], float(torch.quantile(z[dyn], 0.001)), size)
    if level is None:
        level = floor_level(z[~dyn], float(z[dyn].median()), size)
    return None if level is None else (np.array([0.0, 0.0, 1.0]), level)


def below(x: torch.Tensor, plane: tuple[np.ndarray, float]) -> torch.Tensor:
    """The mean depth (m) of the points x [N, 3] under the plane (n, d): mean of max(d − n·x, 0)."""
    n, d = plane
    return torch.relu(d - x @ torch.as_tensor(n, dtype=x.dtype)).mean()


def _key(model, cfg: RefineConfig, half: int | None = None, frames: int | None = None,
         floor=None) -> str:  # fmt: skip
    """A fingerprint of what the refinement depends on: the tracked fields, the Gaussians, the settings, the
    cameras (all of them, or a half), the frames (all of them, or the first so many) and, with a ground term, the
    floor it keeps the tracks above (``floor``; None: :func:`visible_floor`)."""
    settings = asdict(cfg)
    if half is not None:
        settings["half"] = half
    if frames is not None:
        settings["frames"] = int(frames)
    if not cfg.stretch:  # rigid tracks keep the key they had before the stretch existed
        del settings["stretch"], settings["lr_stretch"]
    if not cfg.bend:  # and tracks without a bend
        del settings["bend"], settings["lr_bend"]
    if not cfg.restart:  # and tracks that always start from the last frame's correction
        del settings["restart"]
    if not cfg.ground:  # and so do tracks without the ground's term
        del settings["ground"]
    else:  # the floor it keeps them above
        plane = floor if floor is not None else visible_floor(model)
        settings["floor"] = None if plane is None else (tuple(float(v) for v in plane[0]), round(plane[1], 9))
    h = hashlib.sha256(repr(sorted(settings.items())).encode())
    for name, t in sorted(model.kinematic_fields.state_dict().items()):
        h.update(name.encode())
        h.update(t.detach().cpu().numpy().tobytes())
    for t in (model.gaussians.means, model.gaussians.quats, model.gaussians.scales, model.dynamic):
        h.update(t.detach().cpu().numpy().tobytes())
    return h.hexdigest()[:16]


def camera_half(frames: list, half: int, views=None) -> list:
    """The images of ``frames`` (one time's) whose cameras are in ``half`` (0 or 1) of the cameras: those at even
    or odd places among ``views``, every view number of the dataset (default: the views of ``frames``), so that
    a camera falls in the same half at every time even where a time lacks some cameras. Images without a view number
    are split by their order. The two halves share no camera."""
    place = {v: i for i, v in enumerate(sorted({f.view for f in frames if f.view is not None} if views is None
                                               else set(views)))}  # fmt: skip
    loose = [f for f in frames if f.view is None]
    return [f for f in frames if f.view is not None and place[f.view] % 2 == half] + loose[half::2]


def refine_tracks(model, data, timeline, cfg: RefineConfig | None = None, progress=None, floor=None,
                  half: int | None = None, frames: int | None = None, checkpoint=None) -> Tracks:  # fmt: skip
    """The refinement described in the module docstring, over every observed frame of a fitted ``model`` with its
    dataset ``data`` and ``timeline``; ``progress(done, total)`` after every frame. ``floor``: the plane (n, d)
    that ``cfg.ground`` keeps the moving Gaussians above (None: :func:`visible_floor`). ``half`` 0 or 1: fitted to
    that half of each frame's training cameras only (:func:`camera_half`; None: all of them), for
    :func:`split_noise`. ``frames``: only the first so many observed frames (None: all).

    ``checkpoint``: a file that the state after every frame is written to (atomically), and that a refinement
    of the same fit and settings goes on from, at the frame after the last one written: the frames are refined
    one after another, each from the last one's correction, with one random stream, so going on from a checkpoint
    draws the same cameras as a run that was never stopped. The caller removes it once the tracks are kept."""
    from causalgs.metrics.pixel import psnr
    from causalgs.model.fit import tracking_loss

    cfg = cfg or RefineConfig()
    if cfg.iterations < 0 or cfg.views < 1 or cfg.score_views < 1 or not cfg.ground >= 0:
        raise CausalGSError(f"refinement settings {cfg}: iterations and ground must be ≥ 0, views and score_views "
                            "≥ 1")  # fmt: skip
    n = timeline.train_frames if frames is None else max(1, min(int(frames), timeline.train_frames))
    kc = model.config.kinematic
    g = model.gaussians
    dtype = g.means.dtype
    idx = torch.nonzero(model.dynamic).flatten()
    if len(idx) == 0:
        raise CausalGSError("the fit has no moving Gaussians: there is no motion to refine")
    if not model.kinematic_fields.structured:
        raise CausalGSError("the fit's motion is unstructured (fields.velocity=mlp): it has no patterns to refine")
    bg = tuple(float(v) for v in data.background)
    plane = (floor if floor is not None else visible_floor(model)) if cfg.ground else None
    if half not in (None, 0, 1):
        raise CausalGSError(f"camera half {half} must be 0 or 1")
    train = timeline.by_frame(data.train)
    if half is not None:
        views = {f.view for f in data.train if f.view is not None}
        train = {k: camera_half(v, half, views) for k, v in train.items()}
    val = timeline.by_frame(data.val)
    scored_on = "val" if all(val.get(k) for k in range(n)) else "train"
    scoring = val if scored_on == "val" else train
    rng = np.random.default_rng(cfg.seed)
    key = _key(model, cfg, half, frames, plane)
    with torch.no_grad():
        x0 = g.means[idx].detach()
        h = model.mixtures(x0).to(dtype)
        R, t, _ = pattern_motion(model.kinematic_fields, n - 1, 1.0 / timeline.fps, kc.substeps)
        R, t = R.to(dtype), t.to(dtype)
        cov_all = quat_scale_to_cov(g.quats, torch.exp(g.scales)).detach()
    cov0 = cov_all[idx]
    w = h / h.sum(0).clamp_min(1e-12)  # [N, K]: each pattern's centroid weights
    K = h.shape[1]
    r = torch.zeros(K, 3, dtype=dtype, requires_grad=True)
    d = torch.zeros(K, 3, dtype=dtype, requires_grad=True)
    s = torch.zeros(K, 6, dtype=dtype, requires_grad=True) if cfg.stretch else None
    steps = [(d, cfg.lr_shift), (r, cfg.lr_turn)] + ([(s, cfg.lr_stretch)] if s is not None else [])
    P, basis, centre, radius, pb = None, None, None, None, None
    if cfg.bend:
        if not cfg.stretch:
            raise CausalGSError("a bend is refined with the stretch (RefineConfig.stretch): a rigid pattern has none")
        pb = pattern_bodies(h)
        body = torch.from_numpy(pb[h.argmax(1).numpy()])
        B = int(pb.max()) + 1
        centre = torch.stack([x0[body == i].mean(0) for i in range(B)])  # a body has at least one point
        radius = torch.stack([((x0[body == i] - centre[i]) ** 2).sum(1).mean().sqrt() for i in range(B)])
        radius = radius.clamp_min(1e-6)
        basis = bend_basis(x0, centre, radius, body)
        P = torch.zeros(B, 3, 6, dtype=dtype, requires_grad=True)  # carried from frame to frame like r, d, s
        steps.append((P, cfg.lr_bend))
    still = None if P is None else torch.zeros_like(P)

    def state(A, b, Pk=None):
        x = place(h, x0, A, b)
        J = jacobian(h, A)
        if Pk is not None:
            x = x + bend(basis, Pk)
            J = J + bend_jacobian(basis, Pk)
        means, covs = g.means.detach().clone(), cov_all.clone()
        means[idx], covs[idx] = x, J @ cov0 @ J.transpose(1, 2)
        return means, covs

    def score(frames, A, b, Pk=None):
        with torch.no_grad():
            means, covs = state(A, b, Pk)
            vals = []
            for fr in frames:
                img, _, _ = g.render(fr.camera, bg, means=means, covs=covs)
                vals.append(float(psnr(img.double().clamp(0, 1), torch.from_numpy(fr.image).double())))
        return float(np.mean(vals))

    def frame_loss(frames, A, b, Pk=None) -> float:
        means, covs = state(A, b, Pk)
        return sum(float(tracking_loss(g.render(fr.camera, bg, means=means, covs=covs)[0],
                                       torch.from_numpy(fr.image).to(dtype), kc.lambda_dssim, kc.blur))
                   for fr in frames)  # fmt: skip

    A_out, b_out, P_out = [], [], []
    before, after = [], []
    start = _resume(checkpoint, key, n, rng, (r, d, s, P), (A_out, b_out, P_out, before, after))
    if start and progress is not None:
        progress(start, n)
    for k in range(start, n):
        images = train.get(k, [])
        judge = scoring[k][: cfg.score_views] if scoring.get(k) else images[: cfg.score_views]
        with torch.no_grad():
            c = w.T @ place(h, x0, R[k], t[k])  # [K, 3]
        if k > 1 and images and cfg.iterations > 0 and cfg.restart > 0:
            with torch.no_grad():
                first = images[: cfg.restart]
                if frame_loss(first, R[k], t[k], still) < frame_loss(first, *corrected(R[k], t[k], c, r, d, s), P):
                    for v in (r, d, s, P):
                        if v is not None:
                            v.zero_()
        if k > 0 and images and cfg.iterations > 0:
            opt = torch.optim.Adam([{"params": [v], "lr": lr} for v, lr in steps])
            for _ in range(cfg.iterations):
                pick = rng.choice(len(images), size=min(cfg.views, len(images)), replace=False)
                means, covs = state(*corrected(R[k], t[k], c, r, d, s), P)
                loss = 0.0
                for i in pick:
                    fr = images[int(i)]
                    img, _, _ = g.render(fr.camera, bg, means=means, covs=covs)
                    loss = loss + tracking_loss(img, torch.from_numpy(fr.image).to(dtype), kc.lambda_dssim,
                                                kc.blur) / len(pick)  # fmt: skip
                if plane is not None:
                    loss = loss + cfg.ground * below(means[idx], plane)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
        with torch.no_grad():
            A_k, b_k = corrected(R[k], t[k], c, r, d, s) if k > 0 else (R[k], t[k])
            P_k = None if P is None else (P.detach().clone() if k > 0 else still)
        if judge:
            before.append(score(judge, R[k], t[k]))
            after.append(score(judge, A_k, b_k, P_k) if k > 0 else before[-1])
        else:
            before.append(float("nan"))
            after.append(float("nan"))
        A_out.append(A_k.detach().double().numpy())
        b_out.append(b_k.detach().double().numpy())
        if P_k is not None:
            P_out.append(P_k.double().numpy())
        if checkpoint is not None and k + 1 < n:
            _save_partial(checkpoint, key, k + 1, rng, (r, d, s, P), (A_out, b_out, P_out, before, after))
        if progress is not None:
            progress(k + 1, n)
    bent = {} if P is None else {"P": np.stack(P_out), "centre": centre.double().numpy(),
                                 "radius": radius.double().numpy(), "pattern_body": pb}  # fmt: skip
    return Tracks(np.stack(A_out), np.stack(b_out), np.array(before), np.array(after), scored_on, key,
                  cfg.stretch, **bent)  # fmt: skip


_CARRIED = ("r", "d", "s", "P")  # the corrections carried from frame to frame (s, P: None without stretch, bend)
_MADE = ("A", "b", "P_out", "psnr_before", "psnr_after")  # the per-frame results so far


def _save_partial(path, key: str, done: int, rng, carried, made) -> None:
    """The state of :func:`refine_tracks` once ``done`` frames are refined: what it needs to go on."""
    arrays = {name: t.detach().double().numpy() for name, t in zip(_CARRIED, carried, strict=True) if t is not None}
    arrays.update({name: np.asarray(v) for name, v in zip(_MADE, made, strict=True) if len(v)})
    write_npz(path, key=np.array(key), done=np.array(done), rng=np.array(json.dumps(rng.bit_generator.state)),
              **arrays)  # fmt: skip


def _resume(path, key: str, n: int, rng, carried, made) -> int:
    """Restore the state :func:`_save_partial` wrote at ``path`` into ``rng``, the tensors ``carried`` and the lists
    ``made``, when it is of this refinement (``key``) and has fewer than ``n`` frames; the frames it has (0: none,
    nothing restored). A checkpoint of other settings, another fit or another version is ignored (overwritten)."""
    if path is None or not Path(path).is_file():
        return 0
    try:
        with np.load(path) as z:
            if str(z["key"]) != key:
                return 0
            done = int(z["done"])
            state = json.loads(str(z["rng"]))
            loaded = {name: z[name] for name in (*_CARRIED, *_MADE) if name in z.files}
    except (OSError, KeyError, ValueError):
        return 0
    shapes = {name: t.shape for name, t in zip(_CARRIED, carried, strict=True) if t is not None}
    per_frame = ("A", "b", "psnr_before", "psnr_after") + (("P_out",) if "P" in shapes else ())
    if (not 0 < done < n or any(loaded.get(name, np.empty(0)).shape != v for name, v in shapes.items())
            or any(len(loaded.get(name, ())) != done for name in per_frame)):  # fmt: skip
        return 0
    rng.bit_generator.state = state
    with torch.no_grad():
        for name, t in zip(_CARRIED, carried, strict=True):
            if t is not None:
                t.copy_(torch.from_numpy(loaded[name]).to(t.dtype))
    for name, out in zip(_MADE, made, strict=True):
        out.extend(list(loaded[name]) if name in loaded else [])
    return done


def tracks_name(stretch: bool, bend: bool) -> str:
    """The stem of the file :func:`cached_tracks` keeps tracks in: ``tracks``, ``tracks-affine`` with the stretch,
    ``tracks-bent`` with the bend too."""
    return ("tracks-bent" if bend else "tracks-affine") if stretch else "tracks"


def _tracks_file(run_dir, model, cfg: RefineConfig, half: int | None, frames: int | None) -> tuple[Path, str]:
    name = tracks_name(cfg.stretch, cfg.bend)
    return Path(run_dir) / (f"{name}.npz" if half is None else f"{name}-half{half}.npz"), _key(model, cfg, half, frames)


def _read_tracks(path: Path, key: str, cfg: RefineConfig) -> Tracks | None:
    if path.is_file():
        try:
            with np.load(path) as z:
                if str(z["key"]) == key:
                    bent = {k: z[k] for k in ("P", "centre", "radius", "pattern_body")} if cfg.bend else {}
                    return Tracks(z["A"], z["b"], z["psnr_before"], z["psnr_after"], str(z["scored_on"]), key,
                                  cfg.stretch, **bent)  # fmt: skip
        except (OSError, KeyError, ValueError):
            pass  # unreadable or of another version: made again
    return None


def tracks_kept(run_dir, model, cfg: RefineConfig | None = None, half: int | None = None,
                frames: int | None = None) -> bool:  # fmt: skip
    """Whether :func:`cached_tracks` with these arguments would read them from the run rather than refine them."""
    cfg = cfg or RefineConfig()
    return _read_tracks(*_tracks_file(run_dir, model, cfg, half, frames), cfg) is not None


def cached_tracks(run_dir, model, data, timeline, cfg: RefineConfig | None = None, progress=None,
                  half: int | None = None, frames: int | None = None) -> Tracks:  # fmt: skip
    """The refined tracks of the run at ``run_dir``: read from its ``tracks.npz`` when that was made from this fit
    with these settings, else computed by :func:`refine_tracks` and written there (atomically). ``half``,
    ``frames``: fitted to that half of the cameras over the first so many frames (``tracks-half0.npz``, ...)."""
    cfg = cfg or RefineConfig()
    path, key = _tracks_file(run_dir, model, cfg, half, frames)
    kept = _read_tracks(path, key, cfg)
    if kept is not None:
        return kept
    partial = path.with_name(f"{path.stem}.partial.npz")  # where an interrupted refinement goes on from
    tr = refine_tracks(model, data, timeline, cfg, progress, half=half, frames=frames, checkpoint=partial)
    bent = {} if tr.P is None else {k: getattr(tr, k) for k in ("P", "centre", "radius", "pattern_body")}
    write_npz(path, A=tr.A, b=tr.b, psnr_before=tr.psnr_before, psnr_after=tr.psnr_after,
              scored_on=np.array(tr.scored_on), key=np.array(key), **bent)  # fmt: skip
    partial.unlink(missing_ok=True)
    return tr
