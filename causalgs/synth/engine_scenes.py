"""The MuJoCo scenes (bounce, tumble, knock, soft) and their packaging for the writer.

Each setup function draws a scene's bodies from the seed (colours, size, throw, spin, stiffness a little); the
builder simulates it (:func:`causalgs.synth.engine.simulate`), poses the bodies' meshes per frame, renders them with
a checkered floor by the z-buffer mesh rasterizer and records the ground truth (see data/README, "Engine scenes").
"""

from __future__ import annotations

import math

import numpy as np

from causalgs import _ti
from causalgs.cameras import Camera, fit_ring_distance, look_at, ring_direction
from causalgs.synth.engine import (
    FLOOR_ID,
    GRAVITY,
    LATTICE,
    SOLIMP,
    Body,
    Contact,
    Elastic,
    EngineSetup,
    Trace,
    first_bounce,
    simulate,
)
from causalgs.synth.mesh import AMBIENT, LIGHT, SUPERSAMPLE, Mesh, box_mesh, render_meshes, sphere_mesh
from causalgs.synth.physics import ELEVATIONS_DEG, FOV, STATIC_POINTS, _area, _surface_samples, palette
from causalgs.synth.writer import SynthScene

# Capture rates, within what real cameras record (24-60 fps), chosen so that the 22 future frames of the default 89
# still hold motion: a ball with restitution 0.8 bounces for ~2.7 s, so at 30 fps (2.9 s) the future holds its last
# small bounces and its roll; a tossed box tumbles and slides to rest within ~1.5 s of the throw, a knocked box
# falls within ~0.5 s of the impact and a soft ball rolls and wobbles for a few seconds: at 60 fps (1.47 s) the
# future holds the box's last tumbles, the knocking ball rolling on, the soft ball rolling and wobbling.
FPS = {"bounce": 30.0, "tumble": 60.0, "knock": 60.0, "soft": 60.0}
FLOOR_MARGIN = 0.15  # the floor square reaches this far (m) beyond the bodies' path


def _heading(rng: np.random.Generator) -> np.ndarray:
    a = rng.uniform(0.0, 2.0 * math.pi)
    return np.array([math.cos(a), math.sin(a), 0.0])


def _quat(axis, angle: float) -> tuple[float, float, float, float]:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return (math.cos(angle / 2), *(math.sin(angle / 2) * axis).tolist())


def _t(v) -> tuple[float, ...]:
    return tuple(float(x) for x in v)


def bounce_setup(*, seed: int) -> EngineSetup:
    """A textured ball thrown up with spin: it bounces several times (restitution 0.8) and rolls."""
    rng = np.random.default_rng(seed)
    (color,) = palette(rng, 1)
    h = _heading(rng)
    ball = Body("ball", "ball", (rng.uniform(0.085, 0.095),), _t(-0.25 * h + [0.0, 0.0, 0.5]), 400.0, color,
                Contact((0.7, 0.005, 0.0005), 0.8), velocity=_t(rng.uniform(0.15, 0.25) * h
                + [0.0, 0.0, rng.uniform(0.8, 1.2)]), omega=_t(rng.uniform(-4.0, 4.0, 3)), checker=0.04)  # fmt: skip
    return EngineSetup("bounce", [ball])


def tumble_setup(*, seed: int) -> EngineSetup:
    """A textured box (sides ~24 x 18 x 14 cm) tossed up with spin: it lands on an edge or a corner, tumbles and slides
    to rest under friction."""
    rng = np.random.default_rng(seed)
    (color,) = palette(rng, 1)
    h = _heading(rng)
    box = Body("box", "box", _t(np.array([0.12, 0.09, 0.07]) * rng.uniform(0.95, 1.05)), _t(-0.3 * h + [0, 0, 0.35]),
               500.0, color, Contact((0.3, 0.01, 0.001), 0.5, condim=4),
               velocity=_t(0.4 * rng.uniform(0.9, 1.1) * h + [0.0, 0.0, 3.0 * rng.uniform(0.93, 1.07)]),
               omega=_t(rng.uniform(-12.0, 12.0, 3)), quat=_quat(rng.normal(size=3), rng.uniform(0.5, 1.0)),
               checker=0.05)  # fmt: skip
    return EngineSetup("tumble", [box])


def knock_setup(*, seed: int) -> EngineSetup:
    """A heavy ball thrown into a light box standing on the ground: the box falls over and slides, the ball rolls
    on. The ball's contact parameters act between the two (priority 2)."""
    rng = np.random.default_rng(seed)
    c1, c2 = palette(rng, 2)
    h = _heading(rng)
    side = np.cross([0.0, 0.0, 1.0], h)
    box = Body("box", "box", (0.08, 0.08, 0.12), (0.0, 0.0, 0.12), 250.0, c1,
               Contact((0.5, 0.01, 0.001), 0.4, condim=4), quat=_quat((0.0, 0.0, 1.0), rng.uniform(0.0, math.pi / 2)),
               checker=0.05)  # fmt: skip
    ball = Body("ball", "ball", (0.07,), _t(-0.45 * h + rng.uniform(-0.03, 0.03) * side + [0.0, 0.0, 0.15]), 1500.0,
                c2, Contact((0.5, 0.005, 0.0005), 0.6, priority=2),
                velocity=_t(2.5 * rng.uniform(0.9, 1.1) * h + [0.0, 0.0, 0.8 * rng.uniform(0.9, 1.1)]),
                omega=_t(rng.uniform(-3.0, 3.0, 3)), checker=0.035)  # fmt: skip
    return EngineSetup("knock", [box, ball])


def soft_setup(*, seed: int) -> EngineSetup:
    """A soft elastic ball (a MuJoCo flex, radius 12 cm, E ~ 5e4 Pa) dropped with a forward roll: it lands, squashes
    by about a third, springs back and rolls on, wobbling."""
    rng = np.random.default_rng(seed)
    (color,) = palette(rng, 1)
    h, radius = _heading(rng), 0.12
    v = rng.uniform(0.9, 1.1) * h
    roll = np.cross([0.0, 0.0, 1.0], v) / radius  # rolling without slipping: v = ω × (radius ẑ)
    ball = Body("soft ball", "ball", (radius,), _t(-0.3 * h + [0.0, 0.0, 0.4]), 1000.0, color,
                Contact((0.6, 0.005, 0.0001), 0.3, condim=3, stiffness=2.0e4), velocity=_t(v),
                omega=_t(roll + np.array([0.0, 0.0, rng.uniform(-2.0, 2.0)])), checker=0.04,
                elastic=Elastic(4.8e4 * rng.uniform(0.85, 1.15), 0.4, 0.005))  # fmt: skip
    # Flex elasticity is integrated implicitly only by the "discrete" integrator (MuJoCo >= 3.13), stable at 1 ms.
    return EngineSetup("soft", [ball], max_timestep=0.001, integrator="discrete")


SETUPS = {"bounce": bounce_setup, "tumble": tumble_setup, "knock": knock_setup, "soft": soft_setup}


# -- packaging ------------------------------------------------------------------------------------------------------


def rest_mesh(b: Body) -> tuple[np.ndarray, np.ndarray]:
    """A rigid body's surface in its body frame (origin at the centre of mass)."""
    if b.shape == "ball":
        return sphere_mesh((0.0, 0.0, 0.0), b.size[0], subdivisions=3)
    h = np.asarray(b.size)
    return box_mesh(-h, h, 4)


def lattice(b: Body, spacing: float = LATTICE) -> np.ndarray:
    """Points filling a rigid body, body frame: a grid of ``spacing`` centred on it, inside its shape."""
    half = b.size if b.shape == "box" else (b.size[0],) * 3
    counts = [max(1, math.floor(2 * s / spacing)) for s in half]
    axes = [(np.arange(n) - (n - 1) / 2) * spacing for n in counts]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return X if b.shape == "box" else X[np.linalg.norm(X, axis=1) <= b.size[0]]


def _floor(center, half: float) -> Mesh:
    X, T = box_mesh((center[0] - half, center[1] - half, -0.02), (center[0] + half, center[1] + half, 0.0), 8)
    top = np.all(np.isclose(X[T][:, :, 2], 0.0), axis=1)
    return Mesh(X, T[top], FLOOR_ID, (0.8, 0.8, 0.78), checker=0.1, dark=0.7)


def _bodies(setup: EngineSetup, trace: Trace):
    """Per body: its mesh (rest coordinates), vertices [F, V, 3], rest particles [P, 3] and particles [F, P, 3]."""
    out = []
    for i, b in enumerate(setup.bodies):
        st = trace.bodies[i]
        if b.elastic is None:
            X, T = rest_mesh(b)
            P = lattice(b)
            verts = np.einsum("fij,vj->fvi", st["R"], X) + st["c"][:, None]
            parts = np.einsum("fij,pj->fpi", st["R"], P) + st["c"][:, None]
        else:
            X, T, verts = st["x"][0], st["shell"], st["x"]
            parts = verts
        out.append((Mesh(X, T, i + 2, b.color, checker=b.checker), verts, parts[0], parts))
    return out


def _object(b: Body, oid: int, trace: Trace, engine: dict, particles: int) -> dict:
    st = trace.bodies[oid - 2]
    obj = {"id": oid, "name": b.name, "kind": b.kind, "shape": b.shape, "size": list(b.size),
           "center": st["c"][0].tolist(), "velocity": st["v"][0].tolist(), "omega": list(b.omega),
           "mass": engine["mass"], "density": b.density,
           "friction": dict(zip(("slide", "spin", "roll"), b.contact.friction, strict=True)),
           "condim": b.contact.condim, "solref": list(b.contact.solref), "solimp": list(SOLIMP),
           "restitution_target": b.contact.restitution, "contact_priority": b.contact.priority,
           "color": list(b.color), "checker": b.checker, "particles": particles}  # fmt: skip
    if b.elastic is None:
        obj.update(omega=st["w"][0].tolist(), quat=list(b.quat), inertia=engine["inertia"])
    else:
        el = b.elastic
        obj.update(E=el.E, nu=el.nu, damping=el.damping, flex={
            "type": "ellipsoid flexcomp, dim 3: the surface of a subdivided cube projected on the sphere, and a centre "
            "vertex; one tetrahedron per surface triangle and the centre; linear elasticity, equal vertex masses",
            "count": el.count, "vertices": engine["vertices"], "tetrahedra": engine["tetrahedra"]})  # fmt: skip
    return obj


def _pairs(setup: EngineSetup) -> list[dict]:
    """The parameters every pair of objects would touch with: those of its higher-priority member."""
    members = [(FLOOR_ID, setup.floor)] + [(i + 2, b.contact) for i, b in enumerate(setup.bodies)]
    out = []
    for j, (a, ca) in enumerate(members):
        for b, cb in members[j + 1 :]:
            c = cb if cb.priority > ca.priority else ca
            out.append({"pair": [a, b], "friction": list(c.friction), "condim": c.condim, "solref": list(c.solref),
                        "solimp": list(SOLIMP), "restitution_target": c.restitution})  # fmt: skip
    return out


def _motion(trace: Trace, fps: float, meshes, bodies: list[Body]) -> dict[str, np.ndarray]:
    ev = trace.events
    motion = {
        "seconds": trace.seconds.astype(np.float64),
        "particles_rest": np.concatenate([m[2] for m in meshes]).astype(np.float32),
        "particle_object": np.concatenate([np.full(len(m[2]), i + 2) for i, m in enumerate(meshes)]).astype(np.uint8),
        "particles": np.concatenate([m[3] for m in meshes], axis=1).astype(np.float32),
        "contact": trace.contact,
        "contact_event_seconds": np.array([e[0] for e in ev], dtype=np.float64),
        "contact_event_frame": np.array([math.ceil(e[0] * fps - 1e-9) for e in ev], dtype=np.int32),
        "contact_event_pair": np.array([e[1:3] for e in ev], dtype=np.uint8).reshape(-1, 2),
        "contact_event_position": np.array([e[3] for e in ev], dtype=np.float64).reshape(-1, 3),
        "contact_event_normal": np.array([e[4] for e in ev], dtype=np.float64).reshape(-1, 3),
    }
    for i, (b, (mesh, verts, _, _)) in enumerate(zip(bodies, meshes, strict=True)):
        st, oid = trace.bodies[i], i + 2
        motion[f"pose_c_{oid}"], motion[f"velocity_{oid}"] = st["c"], st["v"]
        if b.elastic is None:
            motion[f"pose_R_{oid}"], motion[f"omega_{oid}"] = st["R"], st["w"]
        motion[f"vertices_{oid}"] = verts.astype(np.float32)
        motion[f"triangles_{oid}"] = mesh.triangles.astype(np.int32)
    return motion


def build_scene(setup: EngineSetup, *, views: int, frames: int, resolution: int, seed: int, fps: float) -> SynthScene:
    """Simulate ``setup`` in MuJoCo and package it for the writer (cameras, renderer, initial points, gt, meta)."""
    import mujoco

    trace = simulate(setup, frames, fps)
    meshes = _bodies(setup, trace)
    allv = np.concatenate([m[1].reshape(-1, 3) for m in meshes])
    # Cameras look at the centre of the bodies' path, from the closest ring that keeps them in every frame; the
    # floor square holds the whole path.
    target = 0.5 * (allv.min(0) + allv.max(0))
    dirs = [ring_direction(i, views, ELEVATIONS_DEG) for i in range(views)]
    dist = fit_ring_distance(allv[:: max(1, len(allv) // 20000)], dirs, target, FOV)
    cameras = [Camera.from_blender(look_at(target + dist * d, target), resolution, resolution, fov_x=FOV) for d in dirs]
    half = math.ceil((np.abs(allv[:, :2] - target[:2]).max() + FLOOR_MARGIN) / 0.05) * 0.05
    floor = _floor(target[:2], half)
    _ti.init("cpu", "float32", quiet=True)  # the rasterizer's precision is fixed: the same seed gives the same bytes

    def render(k: int):
        ms = [floor] + [m[0] for m in meshes]
        pos = [floor.X] + [m[1][k] for m in meshes]
        for cam in cameras:
            yield render_meshes(cam, ms, pos)

    # Initial points, as SfM would give them: the bodies' mesh vertices at t = 0 and area-uniform floor samples.
    rng = np.random.default_rng(seed + 17)
    fp, fc = _surface_samples(floor, STATIC_POINTS, rng)
    pts = np.concatenate([m[1][0] for m in meshes] + [fp])
    cols = np.concatenate([np.tile(np.asarray(m[0].color), (len(m[0].X), 1)) for m in meshes] + [fc])
    engine = trace.model
    objects = [{"id": FLOOR_ID, "name": "floor", "kind": "static", "shape": "plane z = 0",
                "rendered_square": {"center": target[:2].tolist(), "half_size": half, "area": _area(floor)},
                "friction": dict(zip(("slide", "spin", "roll"), setup.floor_friction, strict=True))}]  # fmt: skip
    objects += [_object(b, i + 2, trace, engine["bodies"][i], len(meshes[i][2])) for i, b in enumerate(setup.bodies)]
    bounces = {}
    for i, b in enumerate(setup.bodies):
        first = next((e for e in trace.events if i + 2 in e[1:3]), None)
        fb = first_bounce(trace, i) if b.elastic is None and b.shape == "ball" else None
        if fb is not None and first is not None and first[1] == FLOOR_ID:
            bounces[str(i + 2)] = {**fb, "target": b.contact.restitution}
    run = {"name": "mujoco", "version": mujoco.__version__, "timestep": trace.timestep,
           "substeps_per_frame": trace.substeps, "integrator": setup.integrator, "cone": "elliptic",
           **{k: engine[k] for k in ("solver", "iterations", "tolerance")}}  # fmt: skip
    cams = {"distance": dist, "target": target.tolist(), "elevations_deg": list(ELEVATIONS_DEG),
            "up": [0.0, 0.0, 1.0]}  # fmt: skip
    look = {"texture": "object colour x 3D checker in rest coordinates (rigid: body frame)",
            "light_direction": LIGHT.tolist(), "ambient": AMBIENT, "shading": "two-sided lambertian, flat"}  # fmt: skip
    meta = {
        "motion": {
            "law": f"MuJoCo {mujoco.__version__} rigid/flex dynamics",
            "engine": run,
            "gravity": list(GRAVITY),
            "contact_model": "soft constraints; solref (-k, -b) in the direct form with constant impedance "
            "(solimp d0 = dmax): penetration r'' = -k r - b r', restitution exp(-pi z / sqrt(1 - z^2)), "
            "z = b / (2 sqrt(k)); each pair takes its higher-priority member's parameters",
            "solimp": list(SOLIMP),
            "contact_pairs": _pairs(setup),
            "restitution_measured": {k: v["restitution"] for k, v in bounces.items()},
            "first_bounce": bounces,
            "contacts": "contact[k, a, b]: objects a and b (ids) touched at a step after frame k - 1, up to frame k; "
            "contact_event_*: where a pair starts touching (seconds, frame, ids, mean point, normal from a to b)",
        },
        "objects": objects,
        "mjcf": trace.xml,
        "cameras": cams,
        "appearance": look,
        "supersampling": SUPERSAMPLE,
        "masks": "object ids at pixel centres (0 none, 1 floor, 2.. bodies)",
        "renderer": "z-buffer triangle rasterizer of body meshes posed by MuJoCo (causalgs.synth.mesh)",
    }
    return SynthScene(setup.name, cameras, fps, frames, render, pts, cols, _motion(trace, fps, meshes, setup.bodies),
                      meta)  # fmt: skip


def _builder(name: str):
    def build(*, views: int, frames: int, resolution: int, seed: int, fps: float | None = None) -> SynthScene:
        setup = SETUPS[name](seed=seed)
        return build_scene(setup, views=views, frames=frames, resolution=resolution, seed=seed,
                           fps=FPS[name] if fps is None else fps)  # fmt: skip

    build.__name__ = build.__qualname__ = name
    build.__doc__ = SETUPS[name].__doc__
    return build


bounce, tumble, knock, soft = (_builder(n) for n in ("bounce", "tumble", "knock", "soft"))
