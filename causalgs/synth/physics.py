"""Scenes whose true motion comes from the project's MPM at a reference resolution, rendered from embedded meshes.

A scene is a set of :class:`Body` objects (a box or a ball of particles on a lattice, with material, initial linear
and angular velocity, colour) and an effects spec (any terms of :data:`causalgs.sim.effects.REGISTRY`, so a scene
can carry an effect the model does not know of). The builder:

1. samples each body's particles at spacing dx/2 (8 per cell) on a grid finer than the model's (``REFERENCE_RES``),
2. simulates all frames with the project's MPM (CFL substeps, float32),
3. carries each body's surface mesh with its particles (:class:`~causalgs.synth.mesh.Embedding`) and renders it,
   with a static checkered floor on the ground plane, by the z-buffer mesh rasterizer — never the model's Gaussian
   rasterizer,
4. records the true particle and vertex trajectories, per-object materials and every effect with its parameters.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field

import numpy as np
import torch

from causalgs import _ti
from causalgs.cameras import Camera, fit_ring_distance, look_at, ring_direction
from causalgs.errors import CausalGSError
from causalgs.progress import progress_bar
from causalgs.synth.mesh import AMBIENT, LIGHT, SUPERSAMPLE, Embedding, Mesh, box_mesh, render_meshes, sphere_mesh
from causalgs.synth.writer import SynthScene

# 120 fps (a standard high-speed capture rate): the 89 frames span 0.73 s, so the observed 67 end while the bodies
# are still falling, bouncing and colliding, and the 22 future frames hold motion to predict. At 24 fps every body
# had come to rest about a second in, and holding the last frame was an oracle for the future.
FPS = 120.0
FOV = 0.6911112070083618  # camera_angle_x of the D-NeRF / NVFi Blender scenes
ELEVATIONS_DEG = (18.0, 38.0)
STATIC_POINTS = 4000  # initial-cloud samples on the static floor and walls
REFERENCE_RES = 64  # grid cells along the longest side of the simulation box (the model uses coarser grids)
FLOOR_ID = 1


@dataclass
class Body:
    """A simulated object. ``shape``: "box" (``size`` = half extents) or "ball" (``size[0]`` = radius)."""

    name: str
    shape: str
    center: tuple[float, float, float]
    size: tuple[float, ...]
    E: float
    nu: float
    density: float
    color: tuple[float, float, float]
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    omega: tuple[float, float, float] = (0.0, 0.0, 0.0)
    checker: float = 0.06
    kind: str = "elastic"  # for the object table: "elastic", or "stiff" for rigid-like bodies

    def inside(self, X: np.ndarray) -> np.ndarray:
        c = np.asarray(self.center)
        if self.shape == "box":
            return np.all(np.abs(X - c) <= np.asarray(self.size), axis=1)
        if self.shape == "ball":
            return np.linalg.norm(X - c, axis=1) <= self.size[0]
        raise CausalGSError(f"unknown body shape '{self.shape}'")

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        c = np.asarray(self.center, dtype=np.float64)
        h = np.asarray(self.size if self.shape == "box" else (self.size[0],) * 3, dtype=np.float64)
        return c - h, c + h

    def lattice(self, spacing: float) -> np.ndarray:
        """The body's particles: the centres of the cells of a grid of ``spacing`` (from the low corner of its
        bounds) that lie inside the shape. Raises if there is none."""
        lo, hi = self.bounds()
        axes = [np.arange(lo[d] + spacing / 2, hi[d], spacing) for d in range(3)]
        X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        X = X[self.inside(X)]
        if len(X) == 0:
            raise CausalGSError(f"body '{self.name}' is smaller than the particle spacing {spacing:g} m")
        return X

    def surface(self, spacing: float) -> tuple[np.ndarray, np.ndarray]:
        """The rest surface mesh: the boundary of what the particles' cells fill. For a box that is the union of
        the cells, whose sides are whole numbers of spacings (within half a spacing of ``size``): what is rendered
        is what is simulated, so a model fitted to the images can recover the simulated body's extent."""
        if self.shape == "box":
            X = self.lattice(spacing)
            lo, hi = X.min(0) - spacing / 2, X.max(0) + spacing / 2
            cells = max(2, round(float((hi - lo).max()) / spacing / 2))
            return box_mesh(lo, hi, cells)
        return sphere_mesh(self.center, self.size[0], subdivisions=3)


@dataclass
class PhysicsSetup:
    """Everything that defines a physics scene."""

    name: str
    bodies: list[Body]
    effects: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    floor_half: float = 0.6  # the rendered floor square (m) on the ground plane, if a ground effect is active
    res: int = REFERENCE_RES  # grid cells along the longest side of the box [lo, hi]
    static: list[Mesh] = field(default_factory=list)  # static background besides the floor (object id 1)
    meta: dict = field(default_factory=dict)


def palette(rng: np.random.Generator, n: int) -> list[tuple[float, float, float]]:
    h0 = rng.uniform()
    return [colorsys.hsv_to_rgb((h0 + i / n) % 1.0, rng.uniform(0.55, 0.8), rng.uniform(0.75, 0.95)) for i in range(n)]


def _sample(bodies: list[Body], spacing: float):
    """Lattice particles of every body (cell centres of a grid of ``spacing``), with body indices."""
    xs, owner = [], []
    for i, b in enumerate(bodies):
        X = b.lattice(spacing)
        xs.append(X)
        owner.append(np.full(len(X), i))
    return np.concatenate(xs), np.concatenate(owner), spacing**3


def _floor(effects, half: float) -> Mesh | None:
    """A checkered square on the ground plane of a ``ground`` / ``ground_sticky`` / ``floor`` term whose normal is
    +z."""
    for name in ("ground", "ground_sticky", "floor"):
        if name in effects.names():
            n = effects.get(name, "n")
            n = n / np.linalg.norm(n)
            if abs(n[2]) < 0.999:
                return None  # a tilted plane is not drawn
            d = float(effects.get(name, "d")[0]) / n[2]
            X, T = box_mesh((-half, -half, d - 0.02), (half, half, d), 8)
            top = np.all(np.isclose(X[T][:, :, 2], d), axis=1)  # only the top face
            return Mesh(X, T[top], FLOOR_ID, (0.8, 0.8, 0.78), checker=0.1, dark=0.7)
    return None


def _area(mesh: Mesh) -> float:
    a, b, c = (mesh.X[mesh.triangles[:, i]] for i in range(3))
    return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def _surface_samples(mesh: Mesh, count: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points uniform in area on a mesh's triangles, coloured with its base colour."""
    n = max(1, round(count))
    a, b, c = (mesh.X[mesh.triangles[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    tri = rng.choice(len(area), n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    pts = a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri])
    return pts, np.tile(np.asarray(mesh.color, dtype=np.float64), (n, 1))


def simulate(setup: PhysicsSetup, frames: int, fps: float, progress: bool = True) -> dict:
    """Run the reference MPM; returns rest particles, owners, per-frame positions and F (float32), and the effects."""
    from causalgs.sim import SimConfig, Simulator
    from causalgs.store import ParticleStore

    _ti.init("cpu", "float32", quiet=True)  # the data's precision is fixed, so the same seed gives the same bytes
    cfg = SimConfig(res=setup.res, lo=setup.lo, hi=setup.hi, effects=setup.effects, max_substeps=4000)
    spacing = cfg.geometry.dx / 2
    X, owner, vol = _sample(setup.bodies, spacing)
    n = len(X)
    store = ParticleStore(n, sh_degree=0)
    store.resize(n)
    mat = {
        k: np.array([getattr(setup.bodies[o], k) for o in range(len(setup.bodies))])[owner]
        for k in ("E", "nu", "density")
    }
    for k, a in mat.items():
        store.from_torch(k, torch.from_numpy(a))
    store.from_torch("vol", torch.full((n,), vol))
    store.from_torch("mass", torch.from_numpy(mat["density"] * vol))
    v0 = np.zeros((n, 3))
    for i, b in enumerate(setup.bodies):
        sel = owner == i
        # Spin about the particles' centre of mass, so that ``velocity`` is exactly the body's momentum / mass.
        v0[sel] = np.asarray(b.velocity) + np.cross(np.asarray(b.omega), X[sel] - X[sel].mean(0))
    sim = Simulator(store, cfg)
    sim.set_state(torch.from_numpy(X), torch.from_numpy(v0))
    xs = np.zeros((frames, n, 3), dtype=np.float32)
    Fs = np.zeros((frames, n, 3, 3), dtype=np.float32)
    xs[0], Fs[0] = X, np.eye(3)
    with progress_bar(progress) as bar:
        task = bar.add_task(f"simulating {setup.name} ({n} particles, {setup.res}³ grid)", total=frames - 1)
        for k in range(1, frames):
            st = sim.advance(1, fps)
            xs[k], Fs[k] = st["x"].numpy(), st["F"].numpy()
            bar.advance(task)
    substeps = [m for m, _ in sim.schedule]
    return {
        "X": X,
        "owner": owner,
        "x": xs,
        "F": Fs,
        "effects": sim.effects,
        "spacing": spacing,
        "substeps": substeps,
        "config": cfg,
    }


def build_scene(
    setup: PhysicsSetup,
    *,
    views: int,
    frames: int,
    resolution: int,
    seed: int,
    progress: bool = True,
    fps: float = FPS,
) -> SynthScene:
    """Simulate ``setup`` and package it for the writer (cameras, renderer, initial points, gt motion, meta)."""
    run = simulate(setup, frames, fps, progress)
    X, owner, spacing = run["X"], run["owner"], run["spacing"]
    meshes, embeds = [], []
    for i, b in enumerate(setup.bodies):
        V, T = b.surface(spacing)
        meshes.append(Mesh(V, T, i + 2, b.color, checker=b.checker))
        sel = np.nonzero(owner == i)[0]
        embeds.append((sel, Embedding(V, X[sel])))
    verts = [np.stack([emb(run["x"][k][sel], run["F"][k][sel]) for k in range(frames)]) for sel, emb in embeds]
    floor = _floor(run["effects"], setup.floor_half)
    # Cameras look at the centre of the bodies' path, from the closest ring that keeps them in every frame.
    allv = np.concatenate([v.reshape(-1, 3) for v in verts])
    target = 0.5 * (allv.min(0) + allv.max(0))
    dirs = [ring_direction(i, views, ELEVATIONS_DEG) for i in range(views)]
    dist = fit_ring_distance(allv[:: max(1, len(allv) // 20000)], dirs, target, FOV)
    cameras = [
        Camera.from_blender(look_at(target + dist * dirs[i], target), resolution, resolution, fov_x=FOV)
        for i in range(views)
    ]

    statics = ([floor] if floor is not None else []) + list(setup.static)

    def render(k: int):
        ms = statics + meshes
        pos = [m.X for m in statics] + [v[k] for v in verts]
        for cam in cameras:
            yield render_meshes(cam, ms, pos)

    # Initial points, as SfM would give them: the t = 0 surface samples (mesh vertices) of the bodies and area-uniform
    # samples of the static floor and walls, with their base colours.
    rng = np.random.default_rng(seed + 17)
    still = [_surface_samples(m, STATIC_POINTS * _area(m) / max(sum(_area(k) for k in statics), 1e-12), rng)
             for m in statics]  # fmt: skip
    pts = np.concatenate([v[0] for v in verts] + [p for p, _ in still])
    cols = np.concatenate([np.tile(np.asarray(m.color), (len(m.X), 1)) for m in meshes] + [c for _, c in still])
    eff = run["effects"]
    objects = [{"id": FLOOR_ID, "name": "floor" + (" and walls" if setup.static else ""), "kind": "static"}]
    objects = objects if statics else []
    for i, b in enumerate(setup.bodies):
        objects.append(
            {
                "id": i + 2,
                "name": b.name,
                "kind": b.kind,
                "shape": b.shape,
                "size": list(b.size),
                "center": list(b.center),
                "E": b.E,
                "nu": b.nu,
                "density": b.density,
                "velocity": list(b.velocity),
                "omega": list(b.omega),
                "color": list(b.color),
                "particles": int((owner == i).sum()),
            }
        )
    motion = {
        "particles_rest": X.astype(np.float32),
        "particle_object": (owner + 2).astype(np.uint8),
        "particles": run["x"],
        "F": run["F"],
        **{f"vertices_{i + 2}": v.astype(np.float32) for i, v in enumerate(verts)},
        **{f"triangles_{i + 2}": m.triangles for i, m in enumerate(meshes)},
        "seconds": (np.arange(frames) / fps).astype(np.float64),
    }
    cfg = run["config"]
    meta = {
        "motion": {
            "law": "MLS-MPM (causalgs.sim) at the reference resolution, float32",
            "effects": {t: {k: v.tolist() for k, v in eff.values(t).items()} for t in eff.names()},
            "effects_spec": eff.spec(),
            "material_model": cfg.material,
            "grid": {"res": cfg.res, "lo": list(cfg.lo), "hi": list(cfg.hi), "dx": cfg.geometry.dx},
            "particle_spacing": spacing,
            "substeps_per_frame": run["substeps"],
        },
        "objects": objects,
        "cameras": {
            "distance": dist,
            "target": target.tolist(),
            "elevations_deg": list(ELEVATIONS_DEG),
            "up": [0.0, 0.0, 1.0],
        },
        "appearance": {
            "texture": "object colour x 3D checker in rest coordinates",
            "light_direction": LIGHT.tolist(),
            "ambient": AMBIENT,
            "shading": "two-sided lambertian, flat",
        },
        "supersampling": SUPERSAMPLE,
        "masks": "object ids at pixel centres (0 none, 1 floor, 2.. bodies)",
        "renderer": "z-buffer triangle rasterizer of embedded surface meshes (causalgs.synth.mesh)",
        **setup.meta,
    }
    return SynthScene(setup.name, cameras, fps, frames, render, pts, cols, motion, meta)


# -- the scenes ----------------------------------------------------------------------------------------------------


def jelly_setup(*, seed: int, effects: str | None = None, reference_res: int = REFERENCE_RES) -> PhysicsSetup:
    """A soft elastic cube dropped on the ground: it lands, wobbles and slides (non-rigid)."""
    rng = np.random.default_rng(seed)
    (color,) = palette(rng, 1)
    half = 0.12
    body = Body(
        "jelly",
        "box",
        (rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 0.32),
        (half, half, half),
        E=rng.uniform(1.5e4, 2.5e4),
        nu=0.45,  # gelatin is nearly incompressible
        density=1.0e3,
        color=color,
        velocity=(rng.uniform(0.2, 0.4) * rng.choice([-1, 1]), rng.uniform(-0.2, 0.2), 0.0),
        omega=tuple(rng.uniform(-1.5, 1.5, size=3)),
        checker=0.06,
    )
    spec = effects or "gravity;ground:mu=0.4;walls"
    setup = PhysicsSetup("jelly", [body], spec, (-0.6, -0.6, -0.1), (0.6, 0.6, 1.1), res=reference_res)
    return setup


def fallingball_setup(*, seed: int, effects: str | None = None, reference_res: int = REFERENCE_RES) -> PhysicsSetup:
    """A stiff textured ball thrown up and sideways, falling under gravity and bouncing on the ground (rigid-like)."""
    rng = np.random.default_rng(seed)
    (color,) = palette(rng, 1)
    ball = Body(
        "ball",
        "ball",
        (rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 0.45),
        (0.09,),
        E=rng.uniform(1.5e5, 2.5e5),
        nu=0.3,
        density=1.2e3,
        color=color,
        velocity=(rng.uniform(0.2, 0.4) * rng.choice([-1, 1]), rng.uniform(-0.2, 0.2), rng.uniform(0.5, 1.0)),
        omega=tuple(rng.uniform(-3.0, 3.0, size=3)),
        checker=0.05,
        kind="stiff",
    )
    spec = effects or "gravity;ground:mu=0.3;walls"
    setup = PhysicsSetup("fallingball", [ball], spec, (-0.6, -0.6, -0.1), (0.6, 0.6, 1.1), res=reference_res)
    return setup


def collide_setup(*, seed: int, effects: str | None = None, reference_res: int = REFERENCE_RES) -> PhysicsSetup:
    """Two elastic bodies of very different stiffness: a stiff ball thrown into a soft block resting on the ground."""
    rng = np.random.default_rng(seed)
    c1, c2 = palette(rng, 2)
    side = rng.choice([-1.0, 1.0])
    block = Body("soft block", "box", (0.08 * side, 0.0, 0.101), (0.1, 0.1, 0.1), E=rng.uniform(0.8e4, 1.2e4),
                 nu=0.4, density=1.0e3, color=c1, checker=0.05)  # fmt: skip
    ball = Body("stiff ball", "ball", (-0.3 * side, rng.uniform(-0.03, 0.03), 0.2), (0.07,),
                E=rng.uniform(2.5e5, 3.5e5), nu=0.3, density=1.5e3, color=c2,
                velocity=(side * rng.uniform(1.6, 2.0), 0.0, rng.uniform(0.6, 0.9)), checker=0.04,
                kind="stiff")  # fmt: skip
    spec = effects or "gravity;ground:mu=0.5;walls"
    setup = PhysicsSetup("collide", [block, ball], spec, (-0.6, -0.6, -0.1), (0.6, 0.6, 1.1), res=reference_res)
    return setup


def toss_setup(*, seed: int, effects: str | None = None, reference_res: int = REFERENCE_RES) -> PhysicsSetup:
    """An elastic block tossed up and sideways without spin: a parabolic flight, a flat landing, then sliding and
    wobbling on the ground. No tumbling, so its motion is not chaotic: small changes of the causes make small changes
    of the trajectory, which is what a scene for finding a missing effect needs (``causalgs discover``). The flight
    shows forces and drag, the landing damping and plasticity, the slide friction."""
    rng = np.random.default_rng(seed)
    (color,) = palette(rng, 1)
    block = Body(
        "block",
        "box",
        (rng.uniform(-0.33, -0.27), rng.uniform(-0.03, 0.03), 0.22),
        (0.1, 0.08, 0.06),
        E=rng.uniform(2e4, 4e4),
        nu=0.3,
        density=1.0e3,
        color=color,
        velocity=(rng.uniform(0.7, 0.9), rng.uniform(-0.05, 0.05), rng.uniform(1.0, 1.3)),
        checker=0.05,
    )
    spec = effects or "gravity;ground:mu=0.3;walls"
    return PhysicsSetup("toss", [block], spec, (-0.5, -0.5, -0.1), (0.5, 0.5, 0.9), floor_half=0.5,
                        res=reference_res)  # fmt: skip


def _room_walls(half: float, height: float) -> list[Mesh]:
    """Four low walls around the floor square (their inner faces), textured like the floor."""
    out = []
    for axis in (0, 1):
        for sign in (-1.0, 1.0):
            lo = np.array([-half, -half, 0.0])
            hi = np.array([half, half, height])
            lo[axis], hi[axis] = (half, half + 0.02) if sign > 0 else (-half - 0.02, -half)
            X, T = box_mesh(lo, hi, 6)
            inner = np.isclose(X[T][:, :, axis], sign * half).all(axis=1)
            out.append(Mesh(X, T[inner], FLOOR_ID, (0.85, 0.78, 0.66), checker=0.08, dark=0.75))
    return out


def room_setup(*, seed: int, effects: str | None = None, reference_res: int = REFERENCE_RES) -> PhysicsSetup:
    """An indoor-like scene: a static room (floor, low walls) and three objects of different materials that move
    and run into each other: a soft jelly cube, a stiff ball and a medium-stiff slab."""
    rng = np.random.default_rng(seed)
    c1, c2, c3 = palette(rng, 3)
    jelly = Body("jelly", "box", (-0.22, -0.15, 0.2), (0.08, 0.08, 0.08), E=rng.uniform(0.8e4, 1.5e4), nu=0.45,
                 density=1.0e3, color=c1, velocity=(0.9, 0.5, 0.0), omega=(0.0, 0.0, 2.0), checker=0.04)  # fmt: skip
    ball = Body("ball", "ball", (0.25, -0.2, 0.3), (0.06,), E=rng.uniform(2e5, 3e5), nu=0.3, density=1.5e3,
                color=c2, velocity=(-0.8, 0.7, 0.5), omega=tuple(rng.uniform(-3, 3, size=3)), checker=0.04,
                kind="stiff")  # fmt: skip
    slab = Body("slab", "box", (0.05, 0.22, 0.051), (0.14, 0.07, 0.05), E=rng.uniform(4e4, 6e4), nu=0.35,
                density=800.0, color=c3, velocity=(0.0, -0.4, 0.0), checker=0.05)  # fmt: skip
    spec = effects or "gravity;ground:mu=0.4;walls"
    # The rendered walls stand where the simulation's domain walls act (the wall band of a 1.2 m box).
    lo, hi = (-0.6, -0.6, -0.1), (0.6, 0.6, 1.1)
    band = 3 * (hi[0] - lo[0]) / reference_res
    half = 0.6 - band
    setup = PhysicsSetup("room", [jelly, ball, slab], spec, lo, hi, floor_half=half, res=reference_res,
                         static=_room_walls(half, 0.12))  # fmt: skip
    return setup


def _builder(make_setup, name: str):
    def build(*, views: int, frames: int, resolution: int, seed: int, effects: str | None = None,
              progress: bool = True, reference_res: int = REFERENCE_RES, fps: float = FPS) -> SynthScene:  # fmt: skip
        setup = make_setup(seed=seed, effects=effects, reference_res=reference_res)
        return build_scene(setup, views=views, frames=frames, resolution=resolution, seed=seed, progress=progress,
                           fps=fps)  # fmt: skip

    build.__name__ = build.__qualname__ = name
    build.__doc__ = make_setup.__doc__
    return build


# name -> setup(seed=, effects=, reference_res=): the bodies and effects without simulating (tests use them to check
# effect switches on trajectories alone).
SETUPS = {"fallingball": fallingball_setup, "jelly": jelly_setup, "collide": collide_setup, "room": room_setup,
          "toss": toss_setup}
fallingball = _builder(fallingball_setup, "fallingball")
jelly = _builder(jelly_setup, "jelly")
collide = _builder(collide_setup, "collide")
room = _builder(room_setup, "room")
toss = _builder(toss_setup, "toss")
