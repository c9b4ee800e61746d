"""What discovery compares the simulator with: measured particle trajectories, split into a fit window and a future.

An :class:`Observation` holds positions ``x [T, P, 3]`` of ``P`` material points at ``T`` frame times, the points'
rest volumes and body labels, and how many leading frames may be fitted (``observed``); the frames after them are
held out and only ever scored. It comes from a fitted run (the tracked positions of the model's particles,
:func:`causalgs.discover.video.observation_from_run`) or from a simulated scene (:func:`synthesize`, which also
records the truth for tests and the hidden-effect table).

:func:`synthesize` never measures the model's own discretisation: the truth is the reference MPM of
:mod:`causalgs.synth.physics` (a finer grid, 8 particles per cell), and the observation is a random subset of its
particles with measurement noise; the model simulates that subset on its own, coarser grid. The nuisances of the
negative controls enter here too: a noisy reconstructed rest shape (``rest_noise``).

A measurement sees only what its motion model can express. Tracks from video move each motion pattern rigidly
(:mod:`causalgs.model.refine`): an elastic block's wobble after a bounce, 2–3.5 mm on the landing of ``causalgs synth
toss``, is not in them. Compared point by point with such tracks, a model that wobbles looks wrong and one that is
damped looks right: the landing control's base model gained a viscosity it did not have. So an observation may carry
its measurement's lens, ``mix [P, K]`` (the weights of the rigid motions the tracks are blended from), and the
simulation is then compared through that lens: :func:`rigid_projection` replaces the simulated positions by the
blended rigid motions that fit them best (the observation operator of data assimilation). Motion a rigid pattern
can show (a bounce, a slide, a spin, drag) is compared in full; deformation within a pattern is not compared,
because it was not measured. Tracks that also stretch each pattern (a body squashed for good by plastic flow) are
compared through an affine lens instead (``lens_kind = "affine"``, :func:`affine_projection`): the affine motions
that fit the simulation best. Rigid tracks of an elastic body are wrong where it deforms for a moment (an impact,
a landing): there a run's observation may take the stretching tracks and the affine lens frame by frame
(``stretch``; ``causalgs discover --stretch``), and the rigid ones everywhere else.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from causalgs.errors import CausalGSError
from causalgs.io import write_npz


@dataclass
class Observation:
    """Measured trajectories (see the module docstring). ``lo, hi``: the simulation box; ``ground``: the height of
    the ground plane (z = ground) when the scene has one, for contact-state aggregation; ``noise``: the
    measurement noise (m, per coordinate) when known, else estimated from the data (:func:`noise_floor`)."""

    times: np.ndarray  # [T] seconds from the first frame
    x: np.ndarray  # [T, P, 3] measured positions (m)
    vol: np.ndarray  # [P] rest volume per point (m³)
    body: np.ndarray  # [P] body index 0..B-1
    observed: int  # frames 0..observed-1 may be fitted; the rest are held out
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    density: float = 1000.0
    ground: float | None = 0.0
    noise: float | None = None
    names: list[str] = field(default_factory=list)  # body names
    truth: dict | None = None  # synthetic scenes: the effects, materials and initial velocities used
    mix: np.ndarray | None = None  # [P, K] the tracks' rigid-motion weights (module docstring); None: points
    # what the tracks move each pattern by: "rigid" (:func:`rigid_projection`) or "affine" (:func:`affine_projection`,
    # tracks that also stretch each pattern)
    lens_kind: str = "rigid"
    # [P] affine tracks with a bend (:class:`~causalgs.model.refine.RefineConfig` ``bend``): the body whose
    # second-order displacement moves each point, which the lens fits too (:func:`affine_projection`); None: no bend
    bend: np.ndarray | None = None
    # [T] bool, rigid tracks only: the frames at which the tracks stretch each pattern and the simulation is compared
    # through the affine lens instead (where the images showed the bodies deforming, as at an impact; see
    # :func:`causalgs.discover.video.stretch_where_deforming`). None: ``lens_kind`` at every frame
    stretch: np.ndarray | None = None
    # (m) how finely the points describe each body's extent: a face is known to ± half of it (a fitted run: the
    # voxel its particles filled the bodies at); 0: the points are the material itself (a simulation's particles)
    shape_resolution: float = 0.0
    # [T, B] how far the tracks may be from the truth beyond the noise, per frame and body (m per coordinate): where
    # a rigid lens cannot follow a deforming body (:func:`causalgs.discover.search.lens_blind`). None: the noise
    # alone. Residuals are weighed by :meth:`residual_scale`.
    track_error: np.ndarray | None = None
    # [T, B] a run refined both ways: how far its stretching tracks stray from its rigid ones, per frame and body,
    # beyond their median over the frames (m per coordinate; :func:`causalgs.discover.video.disagreement`). Where the
    # bodies deform, as at an impact, the images pull the two apart; that is what discovery's weights measure the
    # rigid tracks' error by (``DiscoverConfig.weigh``). None: not refined both ways
    disagreement: np.ndarray | None = None
    # [T] tracked motion: how the tracks' own error, which drifts smoothly over the frames and which no block of
    # residuals shows, varies in size from frame to frame (relative; :func:`causalgs.discover.video.drift_profile`).
    # The reported intervals carry draws of such an error, of the size of the noise, through the fit
    # (:func:`causalgs.discover.search.drift_draws`). None: the noise is independent from frame to frame.
    drift: np.ndarray | None = None
    # [T, P, 3] synthetic scenes: the positions before the noise, to score predictions against the truth (the
    # hidden-effect tables); never used by discovery itself
    clean: np.ndarray | None = None

    def __post_init__(self):
        self.times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        self.x = np.asarray(self.x, dtype=np.float64)
        self.vol = np.asarray(self.vol, dtype=np.float64).reshape(-1)
        self.body = np.asarray(self.body).astype(np.int64).reshape(-1)
        T = len(self.times)
        if self.x.ndim != 3 or self.x.shape[0] != T or self.x.shape[2] != 3:
            raise CausalGSError(f"observation: positions have shape {list(self.x.shape)}, expected [{T}, P, 3]")
        P = self.x.shape[1]
        if P < 1:
            raise CausalGSError("observation: no points")
        for name, a in (("vol", self.vol), ("body", self.body)):
            if len(a) != P:
                raise CausalGSError(f"observation: '{name}' has {len(a)} entries for {P} points")
        if not np.isfinite(self.x).all():
            bad = np.argwhere(~np.isfinite(self.x))[0]
            raise CausalGSError(f"observation: position of point {bad[1]} at frame {bad[0]} is not finite")
        if not (np.isfinite(self.vol).all() and (self.vol > 0).all()):
            raise CausalGSError("observation: rest volumes must be positive numbers")
        if (np.diff(self.times) <= 0).any() or not np.isfinite(self.times).all():
            raise CausalGSError("observation: frame times must be finite and increasing")
        if not 3 <= int(self.observed) <= T:
            raise CausalGSError(f"observation: observed = {self.observed} frames must be in [3, {T}]")
        self.observed = int(self.observed)
        if self.body.min() < 0:
            raise CausalGSError("observation: body labels must be >= 0")
        self.lo = tuple(float(v) for v in self.lo)
        self.hi = tuple(float(v) for v in self.hi)
        if not self.names:
            self.names = [f"body {b}" for b in range(self.bodies)]
        self.shape_resolution = float(self.shape_resolution)
        if not (np.isfinite(self.shape_resolution) and self.shape_resolution >= 0):
            raise CausalGSError(f"observation: shape_resolution = {self.shape_resolution} must be a length >= 0 (m)")
        if self.clean is not None:
            self.clean = np.asarray(self.clean, dtype=np.float64)
            if self.clean.shape != self.x.shape or not np.isfinite(self.clean).all():
                raise CausalGSError(f"observation: 'clean' has shape {list(self.clean.shape)} or non-finite values, "
                                    f"expected finite [{T}, {P}, 3]")
        if self.mix is not None:
            self.mix = np.asarray(self.mix, dtype=np.float64)
            if self.mix.ndim != 2 or self.mix.shape[0] != P or self.mix.shape[1] < 1:
                raise CausalGSError(f"observation: 'mix' has shape {list(self.mix.shape)}, expected [{P}, K]")
            if not (np.isfinite(self.mix).all() and (self.mix >= 0).all()):
                raise CausalGSError("observation: 'mix' weights must be finite and >= 0")
            if not np.allclose(self.mix.sum(1), 1.0, atol=1e-6):
                raise CausalGSError("observation: every point's 'mix' weights must sum to 1")
        if self.lens_kind not in LENSES:
            raise CausalGSError(f"observation: lens '{self.lens_kind}' is not one of {', '.join(LENSES)}")
        if self.bend is not None:
            self.bend = np.asarray(self.bend).reshape(-1)
            if self.mix is None or self.lens_kind != "affine":
                raise CausalGSError("observation: a bend ('bend') belongs to an affine lens ('mix', lens 'affine')")
            if len(self.bend) != P or not np.issubdtype(self.bend.dtype, np.integer) or (self.bend < 0).any():
                raise CausalGSError(f"observation: 'bend' must hold {P} body numbers >= 0, one a point")
        if self.stretch is not None:
            self.stretch = np.asarray(self.stretch).reshape(-1)
            if self.mix is None or self.lens_kind != "rigid":
                raise CausalGSError("observation: stretched frames ('stretch') belong to a rigid lens ('mix', lens "
                                    "'rigid')")  # fmt: skip
            if len(self.stretch) != T or self.stretch.dtype != bool:
                raise CausalGSError(f"observation: 'stretch' must hold {T} booleans, one a frame")
            if self.stretch[0]:
                raise CausalGSError("observation: the first frame, where every simulation starts, cannot be stretched")
        if self.drift is not None:
            self.drift = np.asarray(self.drift, dtype=np.float64).reshape(-1)
            if len(self.drift) != T or not (np.isfinite(self.drift).all() and (self.drift >= 0).all()):
                raise CausalGSError(f"observation: 'drift' must hold {T} finite sizes >= 0, one a frame")
        if self.track_error is not None:
            self.track_error = np.asarray(self.track_error, dtype=np.float64)
            if self.track_error.shape != (T, self.bodies):
                raise CausalGSError(f"observation: 'track_error' has shape {list(self.track_error.shape)}, "
                                    f"expected [{T}, {self.bodies}]")  # fmt: skip
            if not (np.isfinite(self.track_error).all() and (self.track_error >= 0).all()):
                raise CausalGSError("observation: 'track_error' must be finite lengths >= 0 (m)")
        if self.disagreement is not None:
            self.disagreement = np.asarray(self.disagreement, dtype=np.float64)
            if self.disagreement.shape != (T, self.bodies) or not (
                    np.isfinite(self.disagreement).all() and (self.disagreement >= 0).all()):
                raise CausalGSError(f"observation: 'disagreement' must hold finite lengths >= 0 (m), shaped "
                                    f"[{T}, {self.bodies}]")  # fmt: skip

    @property
    def bodies(self) -> int:
        return int(self.body.max()) + 1

    @property
    def points(self) -> int:
        return self.x.shape[1]

    def residual_scale(self) -> np.ndarray | None:
        """[T, P] the factor σ / sqrt(σ² + e²) every residual coordinate is weighed by, σ the measurement noise
        (:attr:`noise`, else :func:`noise_floor`) and e the point's body's :attr:`track_error` at that frame: a
        residual of the size the tracks may err by counts as much as the noise does elsewhere, so the weighted
        error of a correct model stays at the noise on every frame. None without a track error (every weight 1)."""
        if self.track_error is None:
            return None
        sigma = self.noise if self.noise else noise_floor(self)
        if sigma <= 0:
            return None
        e = self.track_error[:, self.body]
        return sigma / np.sqrt(sigma**2 + e**2)

    @property
    def future(self) -> int:
        """Held-out frames after the fit window."""
        return len(self.times) - self.observed

    def save(self, path) -> None:
        """Write the observation as one npz (atomically); :func:`load_observation` reads it back."""
        extra = {"truth_json": np.array(_json(self.truth))} if self.truth is not None else {}
        if self.mix is not None:
            extra["mix"] = self.mix
            extra["lens_kind"] = np.array(self.lens_kind)
        if self.bend is not None:
            extra["bend"] = self.bend
        if self.stretch is not None:
            extra["stretch"] = self.stretch
        if self.clean is not None:
            extra["clean"] = self.clean
        if self.drift is not None:
            extra["drift"] = self.drift
        if self.disagreement is not None:
            extra["disagreement"] = self.disagreement
        write_npz(Path(path), times=self.times, x=self.x, vol=self.vol, body=self.body,
                  observed=np.int64(self.observed), lo=np.array(self.lo), hi=np.array(self.hi),
                  density=np.float64(self.density), ground=np.float64(np.nan if self.ground is None else self.ground),
                  noise=np.float64(np.nan if self.noise is None else self.noise), names=np.array(self.names),
                  shape_resolution=np.float64(self.shape_resolution), **extra)  # fmt: skip


def _json(obj) -> str:
    import json

    return json.dumps(obj, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))


def load_observation(path) -> Observation:
    """An observation written by :meth:`Observation.save`; a missing or malformed file is a one-line error."""
    import json

    path = Path(path)
    if not path.is_file():
        raise CausalGSError(f"{path}: no such observation file")
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except Exception as e:
        raise CausalGSError(f"{path}: not a readable npz archive ({type(e).__name__})") from None
    need = ("times", "x", "vol", "body", "observed", "lo", "hi")
    missing = [k for k in need if k not in d]
    if missing:
        raise CausalGSError(f"{path}: missing arrays {', '.join(missing)}")

    def opt(key):
        v = float(d[key]) if key in d else float("nan")
        return None if not np.isfinite(v) else v

    try:
        return Observation(
            times=d["times"], x=d["x"], vol=d["vol"], body=d["body"], observed=int(d["observed"]),
            lo=tuple(d["lo"].tolist()), hi=tuple(d["hi"].tolist()),
            density=float(d.get("density", 1000.0)), ground=opt("ground"), noise=opt("noise"),
            names=[str(s) for s in d["names"]] if "names" in d else [],
            truth=json.loads(str(d["truth_json"])) if "truth_json" in d else None, mix=d.get("mix"),
            lens_kind=str(d.get("lens_kind", "rigid")), shape_resolution=float(d.get("shape_resolution", 0.0)),
            clean=d.get("clean"), drift=d.get("drift"), bend=d.get("bend"), disagreement=d.get("disagreement"),
            stretch=d.get("stretch"),
        )  # fmt: skip
    except CausalGSError as e:
        raise CausalGSError(f"{path}: {e}") from None


def noise_floor(obs: Observation, window: int = 7) -> float:
    """The measurement noise σ (m, per coordinate), estimated from the fit window alone: the RMS of what a local
    cubic (Savitzky–Golay, ``window`` frames) leaves of every trajectory, corrected for the degrees of freedom the
    smoother takes. Smooth motion leaves nothing; noise leaves (1 − 4/window) of its variance."""
    from scipy.signal import savgol_filter

    x = obs.x[: obs.observed]
    w = min(window, len(x) - (1 - len(x) % 2))
    if w < 5:
        return 0.0
    smooth = savgol_filter(x, w, 3, axis=0, mode="interp")
    r = x - smooth
    dof = 1.0 - 4.0 / w
    return float(np.sqrt((r**2).mean() / max(dof, 1e-6)))


# -- the measurement's lens -------------------------------------------------------------------------------------------

MIN_WEIGHT = 1e-3  # of the mean point: a pattern holding less weight than this is dropped from a lens (and its
# points' weights renormalised): no rigid motion can be fitted to it


def lens(mix: np.ndarray) -> np.ndarray:
    """Rigid-motion weights [P, K'] for :attr:`Observation.mix`: the patterns of ``mix [P, K]`` that hold some weight,
    every point's weights summing to 1."""
    mix = np.clip(np.asarray(mix, dtype=np.float64), 0.0, None)
    keep = mix.sum(0) > MIN_WEIGHT
    if not keep.any():
        raise CausalGSError("observation: no motion pattern holds any point")
    out = mix[:, keep]
    total = out.sum(1, keepdims=True)
    if (total <= 0).any():
        raise CausalGSError("observation: a point belongs to no kept motion pattern")
    return out / total


def polar(H: torch.Tensor, iterations: int = 30) -> torch.Tensor:
    """The rotation factor R of H = R S (S symmetric positive definite), batched over leading dimensions, by scaled
    Newton iteration X ← (γX + X⁻ᵀ/γ)/2. Unlike an SVD, whose gradient divides by differences of singular values
    (a cube's points have three equal ones), its gradient stays finite for any invertible H."""
    X = H / H.flatten(-2).norm(dim=-1).clamp_min(1e-300)[..., None, None]
    for _ in range(iterations):
        Y = torch.linalg.inv(X).transpose(-1, -2)
        g = torch.sqrt(Y.flatten(-2).norm(dim=-1) / X.flatten(-2).norm(dim=-1))[..., None, None]
        X = 0.5 * (g * X + Y / g)
    return X


def rigid_projection(x: torch.Tensor, x0: torch.Tensor, mix: torch.Tensor, vol: torch.Tensor,
                     at: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
    """Positions ``x [T, P, 3]`` of points that started at ``x0 [P, 3]`` seen through a lens of blended rigid motions:
    for every frame and pattern k, the rotation and translation (R_k, c_k) that best fit the points' motion in the
    least-squares sense weighted by mix[:, k]·vol (Kabsch: R_k the rotation factor of the weighted cross-covariance),
    and every point placed at Σ_k mix_ik (R_k (x0_i − c0_k) + c_k). Where every point belongs to one pattern (as
    a fit's segmentation ends: on the toss landing 95% of the particles hold over 0.99999 of their weight in one
    pattern) this is the least-squares fit of the tracks' motion model and a rigid motion per pattern is returned
    as it is; points shared between patterns get the blend of the patterns' own fits. Differentiable in ``x``.
    ``at`` [P, 3]: the rest positions the fitted motions carry instead of ``x0`` (the measured points, where the
    simulated material started from another shape)."""
    w = mix * vol[:, None]  # [P, K]
    W = w.sum(0)  # [K]
    c0 = (w.T @ x0) / W[:, None]  # [K, 3]
    c = torch.einsum("pk,tpi->tki", w, x) / W[:, None]  # [T, K, 3]
    d0 = x0[:, None, :] - c0[None]  # [P, K, 3]
    H = torch.einsum("pk,tpi,pkj->tkij", w, x, d0)  # Σ w (x − c)(x0 − c0)ᵀ, as Σ w d0 = 0
    R = polar(H)  # [T, K, 3, 3]
    if at is not None:
        d0 = at[:, None, :] - c0[None]
    fit = torch.einsum("tkij,pkj->tpki", R, d0) + c[:, None]  # [T, P, K, 3]
    return torch.einsum("pk,tpki->tpi", mix, fit)


def affine_projection(x: torch.Tensor, x0: torch.Tensor, mix: torch.Tensor, vol: torch.Tensor,
                      at: torch.Tensor | None = None, bend: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
    """:func:`rigid_projection` with an affine motion per pattern: for every frame and pattern k the map
    x ≈ A_k (x0 − c0_k) + c_k that best fits the points' motion in the least-squares sense weighted by mix[:, k]·vol
    (A_k = H_k M_k⁻¹, H_k the weighted cross-covariance and M_k the rest shape's weighted covariance), and every
    point placed at Σ_k mix_ik (A_k (at_i − c0_k) + c_k). What tracks that stretch each pattern see
    (:class:`~causalgs.model.refine.RefineConfig` ``stretch``): a squash is compared, a wobble finer than one
    strain per pattern is not. Differentiable in ``x``. ``bend`` [P]: the tracks also bend each body (its points'
    body numbers): see :func:`bent_projection`."""
    if bend is not None:
        return bent_projection(x, x0, mix, vol, bend, at)
    w = mix * vol[:, None]  # [P, K]
    W = w.sum(0)  # [K]
    c0 = (w.T @ x0) / W[:, None]  # [K, 3]
    c = torch.einsum("pk,tpi->tki", w, x) / W[:, None]  # [T, K, 3]
    d0 = x0[:, None, :] - c0[None]  # [P, K, 3]
    H = torch.einsum("pk,tpi,pkj->tkij", w, x, d0)  # Σ w (x − c)(x0 − c0)ᵀ
    M = torch.einsum("pk,pki,pkj->kij", w, d0, d0)  # Σ w (x0 − c0)(x0 − c0)ᵀ
    # a pattern whose points lie in a plane or on a line has no stretch across it: a ridge of 1e-12 of its spread
    ridge = 1e-12 * torch.diagonal(M, dim1=-2, dim2=-1).sum(-1).clamp_min(1e-300)
    M = M + ridge[:, None, None] * torch.eye(3, dtype=M.dtype)
    A = torch.linalg.solve(M.expand(H.shape), H.transpose(-1, -2)).transpose(-1, -2)  # H M⁻¹, M symmetric
    if at is not None:
        d0 = at[:, None, :] - c0[None]
    fit = torch.einsum("tkij,pkj->tpki", A, d0) + c[:, None]  # [T, P, K, 3]
    return torch.einsum("pk,tpki->tpi", mix, fit)


def bent_projection(x: torch.Tensor, x0: torch.Tensor, mix: torch.Tensor, vol: torch.Tensor, bend: torch.Tensor,
                    at: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
    """What affine tracks with a bend see (:class:`~causalgs.model.refine.RefineConfig` ``bend``): the motion of
    their model, x ≈ Σ_k mix_k (A_k (x0 − c0_k) + c_k) + P_b φ((x0 − c_b)/r_b) (b = ``bend``, the point's body,
    c_b and r_b its rest centroid and RMS radius; φ the six second-order monomials of
    :func:`causalgs.model.refine.bend_basis`), fitted to the points'
    positions jointly for every frame by least squares weighted by ``vol``, and evaluated at ``at`` (default x0).
    The model is linear in its coefficients, so the projection is one linear map of ``x`` for every frame (and
    differentiable in it): a body that tapers or bulges (a foot spread on the ground) is compared, a deformation
    finer than that is not."""
    from causalgs.model.refine import bend_basis

    at = x0 if at is None else at
    body = torch.as_tensor(bend, dtype=torch.long)
    B = int(body.max()) + 1
    W = mix * vol[:, None]
    c0 = (W.T @ x0) / W.sum(0).clamp_min(1e-300)[:, None]  # [K, 3]
    one = torch.nn.functional.one_hot(body, B).to(x0.dtype)  # [P, B]
    wb = one * vol[:, None]
    cb = wb.T @ x0 / wb.sum(0).clamp_min(1e-300)[:, None]  # [B, 3]
    rb = ((wb * ((x0[:, None, :] - cb[None]) ** 2).sum(-1)).sum(0) / wb.sum(0).clamp_min(1e-300)).sqrt()
    rb = rb.clamp_min(1e-6)

    def design(p):
        lin = torch.cat([mix[:, :, None] * (p[:, None, :] - c0[None]), mix[:, :, None]], -1)  # [P, K, 4]
        phi = bend_basis(p, cb, rb, body)[0]  # [P, 6]
        quad = one[:, :, None] * phi[:, None, :]  # [P, B, 6]
        return torch.cat([lin.reshape(len(p), -1), quad.reshape(len(p), -1)], 1)

    root = vol.sqrt()[:, None]
    with torch.no_grad():  # the map does not depend on x; the projection is linear in it
        # coefficients no point pins down (a flat body has no bend across it; a pattern's blend weight that varies
        # linearly in space makes a square of the affine part) are left out: the pseudo-inverse
        fit = torch.linalg.pinv(root * design(x0), rtol=1e-10)  # [m, P]
        ev = design(at)
    T, P = x.shape[:2]
    coef = fit @ (root * x.permute(1, 0, 2).reshape(P, T * 3))  # [m, T·3]
    return (ev @ coef).reshape(P, T, 3).permute(1, 0, 2)


LENSES = {"rigid": rigid_projection, "affine": affine_projection}


# -- synthetic observations -------------------------------------------------------------------------------------------


def synthesize(
    scene: str,
    effects: str | None = None,
    *,
    seed: int = 0,
    points: int = 256,
    frames: int = 36,
    observed: int | None = None,
    fps: float = 24.0,
    noise: float = 0.0,
    rest_noise: float = 0.0,
    reference_res: int = 48,
    rigid: bool = False,
    progress: bool = False,
) -> Observation:
    """Simulate the built-in ``scene`` (``causalgs.synth.physics.SETUPS``) with the effects spec ``effects`` (None:
    the scene's own) on the reference grid and observe ``points`` of its particles (spread over the bodies by
    volume) with Gaussian noise of ``noise`` m per coordinate. ``rest_noise`` perturbs the first frame only (a
    noisy reconstruction of the rest shape). ``observed`` defaults to the paper's 3/4 protocol.

    ``rigid``: the points are seen as tracks from video see them, each body through its best rigid motion
    (:func:`rigid_projection` of all the body's particles, before the noise), and the observation carries that
    lens (``mix``, one pattern per body): what is measured is what a rigid tracker of a perfect video would give,
    so that what the lens hides (a wobble, a squash) is tested apart from the errors of tracking images."""
    from causalgs.synth import physics

    if scene not in physics.SETUPS:
        raise CausalGSError(f"unknown scene '{scene}'; choose one of: {', '.join(sorted(physics.SETUPS))}")
    if frames < 4 or points < 1:
        raise CausalGSError(f"frames = {frames} must be >= 4 and points = {points} >= 1")
    rng = np.random.default_rng(seed)
    setup = physics.SETUPS[scene](seed=seed, effects=effects, reference_res=reference_res)
    run = physics.simulate(setup, frames, fps, progress=progress)  # on the float32 runtime (it initialises it)
    owner = run["owner"]
    volume = np.array([(owner == b).sum() for b in range(len(setup.bodies))], dtype=np.float64) * run["spacing"] ** 3
    share = volume / volume.sum()
    counts = np.maximum(1, np.round(share * points).astype(int))
    idx, body, vol = [], [], []
    for b, n in enumerate(counts):
        mine = np.nonzero(owner == b)[0]
        pick = np.sort(rng.choice(mine, size=min(n, len(mine)), replace=False))
        idx.append(pick)
        body.append(np.full(len(pick), b))
        vol.append(np.full(len(pick), volume[b] / len(pick)))
    idx = np.concatenate(idx)
    x = run["x"][:, idx].astype(np.float64)
    one_pattern_a_body = np.eye(len(setup.bodies))
    if rigid:
        every = torch.from_numpy(run["x"].astype(np.float64))
        mix = torch.from_numpy(one_pattern_a_body[owner])
        x = rigid_projection(every, every[0], mix, torch.ones(len(owner), dtype=torch.float64))[:, idx].numpy()
    clean = x.copy()
    x = x + noise * rng.standard_normal(x.shape)
    x[0] += rest_noise * rng.standard_normal(x[0].shape)
    eff = run["effects"]
    truth = {
        "scene": scene,
        "effects_spec": eff.spec(),
        "effects": {t: {k: v.tolist() for k, v in eff.values(t).items()} for t in eff.names()},
        "bodies": [{"name": b.name, "E": b.E, "nu": b.nu, "density": b.density, "velocity": list(b.velocity),
                    "omega": list(b.omega)} for b in setup.bodies],
        "reference_res": reference_res,
        "noise": noise,
        "rest_noise": rest_noise,
        "seed": seed,
        "rigid": rigid,
    }
    planes = [name for name in ("ground", "ground_sticky", "floor") if name in eff.names()]
    ground = float(eff.get(planes[0], "d")[0]) if planes else None
    dens = float(np.average([b.density for b in setup.bodies], weights=volume))
    return Observation(
        times=np.arange(frames) / fps, x=x, vol=np.concatenate(vol), body=np.concatenate(body),
        observed=observed if observed is not None else max(3, round(frames * 67 / 89)), lo=setup.lo, hi=setup.hi,
        density=dens, ground=ground, noise=noise if noise > 0 else None, names=[b.name for b in setup.bodies],
        truth=truth, mix=one_pattern_a_body[np.concatenate(body)] if rigid else None, clean=clean,
    )  # fmt: skip
