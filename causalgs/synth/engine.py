"""Scenes whose true motion comes from MuJoCo, an engine independent of the project's MPM, rendered from posed meshes.

A scene (:class:`EngineSetup`) is a list of :class:`Body` on a ground plane at z = 0: rigid balls and boxes on free
joints, and soft balls (MuJoCo flexes with linear elasticity). The builder:

1. writes the scene as MJCF (:func:`mjcf`) and compiles it with the ``mujoco`` package, imported here only when a scene
   is built so that ``import causalgs.synth`` stays light;
2. steps it at a timestep that divides the frame interval, recording every body's state at every frame and which
   objects touch at every step (:func:`simulate`);
3. renders each rigid body's rest mesh posed by MuJoCo, and each flex's boundary faces carried by its vertices, with
   the z-buffer rasterizer of :mod:`causalgs.synth.mesh` — never the model's Gaussian rasterizer;
4. records poses, velocities, carried interior points, contacts, the engine's parameters and the MJCF itself.

Contacts (MuJoCo's soft constraints): every contact takes the parameters of its higher-priority geom, so a body's own
friction, solref and solimp act between it and the floor (priority 0). solref is in the direct form (-k, -b) and
solimp's impedance is constant (d0 = dmax), so the penetration r of a contact obeys r'' = -k r - b r' (MuJoCo's
reference acceleration with K = k / dmax², B = b / dmax, scaled by the impedance d = dmax): a damped spring whose
restitution is exp(-π ζ / sqrt(1 - ζ²)) with ζ = b / (2 sqrt(k)). :func:`contact_solref` inverts that for a target
restitution; :func:`first_bounce` measures what the simulation gives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from causalgs.errors import CausalGSError

GRAVITY = (0.0, 0.0, -9.81)
SOLIMP = (0.95, 0.95, 0.001, 0.5, 2.0)  # constant impedance: the contact is exactly the spring of contact_solref
CONTACT_STIFFNESS = 2.0e5  # k (1/s²): a 3 m/s impact penetrates ~7 mm and lasts ~7 ms (≥ 14 steps of 0.5 ms)
LATTICE = 0.02  # spacing (m) of the points that fill a rigid body (gt particles)
FLOOR_ID = 1


@dataclass(frozen=True)
class Contact:
    """A body's contact parameters (MuJoCo geom/flex attributes). ``friction``: slide (coefficient), spin and roll
    (torsional and rolling friction, metres); ``restitution``: the target of the spring-damper solref."""

    friction: tuple[float, float, float]
    restitution: float
    condim: int = 6
    stiffness: float = CONTACT_STIFFNESS
    priority: int = 1

    @property
    def solref(self) -> tuple[float, float]:
        return contact_solref(self.restitution, self.stiffness)


@dataclass(frozen=True)
class Elastic:
    """A soft ball's material and discretisation: Young's modulus (Pa), Poisson's ratio, MuJoCo's elasticity damping
    (s, stiffness-proportional), and vertices per axis of the ellipsoid flexcomp."""

    E: float
    nu: float
    damping: float
    count: int = 7


@dataclass
class Body:
    """A body of a scene. ``shape``: "ball" (``size`` = (radius,)) or "box" (``size`` = half extents); soft bodies
    (``elastic`` set) are balls. ``quat`` (wxyz) is a rigid body's orientation at t = 0; ``velocity`` and ``omega``
    are the initial velocity of its centre of mass and its angular velocity, world frame."""

    name: str
    shape: str
    size: tuple[float, ...]
    center: tuple[float, float, float]
    density: float
    color: tuple[float, float, float]
    contact: Contact
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    omega: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    checker: float = 0.05
    elastic: Elastic | None = None

    @property
    def kind(self) -> str:
        return "rigid" if self.elastic is None else "soft"

    def __post_init__(self):
        if self.shape not in ("ball", "box") or (self.elastic is not None and self.shape != "ball"):
            raise CausalGSError(f"body '{self.name}': shape '{self.shape}' is not a ball or a rigid box")


@dataclass
class EngineSetup:
    """Everything that defines an engine scene. ``max_timestep`` bounds MuJoCo's step, which is chosen to divide the
    frame interval; ``integrator`` is MuJoCo's ("RK4" for rigid scenes; flex elasticity needs "discrete")."""

    name: str
    bodies: list[Body]
    max_timestep: float = 0.0005
    integrator: str = "RK4"
    floor_friction: tuple[float, float, float] = (1.0, 0.005, 0.0001)

    def __post_init__(self):
        # A pair of equal priority would mix its members' parameters (MuJoCo's solmix), which the meta does not record.
        priorities = [b.contact.priority for b in self.bodies]
        if min(priorities) < 1 or len(set(priorities)) < len(priorities):
            raise CausalGSError(f"scene '{self.name}': contact priorities {priorities} must be distinct and >= 1")

    @property
    def floor(self) -> Contact:
        """The floor's contact parameters; priority 0, so they act on no pair (every body's are higher)."""
        return Contact(self.floor_friction, 0.5, condim=3, priority=0)


def contact_solref(restitution: float, stiffness: float) -> tuple[float, float]:
    """solref (-k, -b) of the contact spring r'' = -k r - b r' that bounces back with ``restitution`` in (0, 1)."""
    if not 0.0 < restitution < 1.0:
        raise CausalGSError(f"restitution = {restitution!r} must be in (0, 1)")
    ln = math.log(restitution)
    zeta = -ln / math.sqrt(math.pi**2 + ln**2)
    return (-stiffness, -2.0 * zeta * math.sqrt(stiffness))


def substeps(fps: float, max_timestep: float) -> int:
    """Steps per frame: the fewest whose timestep 1 / (fps · n) is at most ``max_timestep``."""
    return max(1, math.ceil(1.0 / (fps * max_timestep) - 1e-9))


def _f(x) -> str:
    """A float as MJCF text: the shortest string that reads back to the same double (so the XML is exact)."""
    return repr(float(x))


def _v(xs) -> str:
    return " ".join(_f(x) for x in xs)


def _contact_attrs(c: Contact) -> str:
    return (f'condim="{c.condim}" friction="{_v(c.friction)}" solref="{_v(c.solref)}" solimp="{_v(SOLIMP)}" '
            f'priority="{c.priority}"')  # fmt: skip


def _body_xml(b: Body) -> str:
    if b.elastic is not None:
        el, r = b.elastic, b.size[0]
        volume = 4.0 / 3.0 * math.pi * r**3
        sp = 2.0 * r / (el.count - 1)
        return (f'    <flexcomp name="{b.name}" type="ellipsoid" dim="3" count="{el.count} {el.count} {el.count}" '
                f'spacing="{_v((sp, sp, sp))}" pos="{_v(b.center)}" radius="0.001" mass="{_f(b.density * volume)}">\n'
                f'      <contact {_contact_attrs(b.contact)} selfcollide="none"/>\n'
                f'      <elasticity young="{_f(el.E)}" poisson="{_f(el.nu)}" damping="{_f(el.damping)}"/>\n'
                f'    </flexcomp>\n')  # fmt: skip
    kind = "sphere" if b.shape == "ball" else "box"
    return (f'    <body name="{b.name}" pos="{_v(b.center)}" quat="{_v(b.quat)}">\n'
            f'      <freejoint name="{b.name}"/>\n'
            f'      <geom name="{b.name}" type="{kind}" size="{_v(b.size)}" density="{_f(b.density)}" '
            f'{_contact_attrs(b.contact)}/>\n'
            f'    </body>\n')  # fmt: skip


def mjcf(setup: EngineSetup, timestep: float) -> str:
    """The scene as MuJoCo XML: floor plane (priority 0), then the bodies in order."""
    return (f'<mujoco model="{setup.name}">\n'
            f'  <option timestep="{_f(timestep)}" integrator="{setup.integrator}" gravity="{_v(GRAVITY)}" '
            f'cone="elliptic"/>\n'
            f'  <worldbody>\n'
            f'    <geom name="floor" type="plane" size="0 0 0.05" {_contact_attrs(setup.floor)}/>\n'
            + "".join(_body_xml(b) for b in setup.bodies)
            + '  </worldbody>\n</mujoco>\n')  # fmt: skip


@dataclass
class Trace:
    """A simulated run, sampled at the frames (``seconds`` [F]); per body (by index in the setup) ``c`` [F, 3] centre
    of mass and ``v`` [F, 3] its velocity; rigid ``R`` [F, 3, 3] body-to-world rotation and ``w`` [F, 3] angular
    velocity (world); soft ``x`` [F, V, 3] flex vertices and ``shell`` [T, 3] their boundary triangles.
    ``contact`` [F, N, N]: objects (by id) that touched at a step after the previous frame, up to this one.
    ``events``: (seconds, id_a < id_b, position [3], normal a→b [3]) where a pair starts touching. ``steps``
    [S] seconds of every step and ``vz`` [S, B], ``floor`` [S, B] each body's vertical speed and floor contact."""

    seconds: np.ndarray
    timestep: float
    substeps: int
    bodies: list[dict]
    contact: np.ndarray
    events: list[tuple]
    steps: np.ndarray
    vz: np.ndarray
    floor: np.ndarray
    xml: str
    model: dict


def _soft_dofs(model, b: int) -> np.ndarray:
    """qvel indices [V, 3] of flex ``b``'s vertices (each a body on three world-aligned slide joints)."""
    bodies = model.flex_vertbodyid[model.flex_vertadr[b] : model.flex_vertadr[b] + model.flex_vertnum[b]]
    adr = model.body_dofadr[bodies]
    if np.any(model.body_dofnum[bodies] != 3) or np.any(model.body_quat[bodies] != [1.0, 0.0, 0.0, 0.0]):
        raise CausalGSError(f"flex {b}: vertices are not free points on world-aligned slide joints")
    return adr[:, None] + np.arange(3)


def simulate(setup: EngineSetup, frames: int, fps: float) -> Trace:
    """Run ``setup`` in MuJoCo for ``frames`` frames at ``fps``; see :class:`Trace`."""
    import mujoco

    n = substeps(fps, setup.max_timestep)
    dt = 1.0 / (fps * n)
    xml = mjcf(setup, dt)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    ids = np.arange(len(setup.bodies)) + 2
    geom_obj = np.zeros(model.ngeom, dtype=np.int64)
    flex_obj = np.zeros(max(model.nflex, 1), dtype=np.int64)
    geom_obj[0] = FLOOR_ID
    soft_dofs, rigid = {}, {}
    for i, b in enumerate(setup.bodies):
        if b.elastic is None:
            body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b.name)
            geom_obj[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, b.name)] = ids[i]
            rigid[i] = (body, model.body_dofadr[body])
        else:
            f = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, b.name)
            flex_obj[f] = ids[i]
            soft_dofs[i] = (f, _soft_dofs(model, f))
    # Initial velocities: a free joint's angular velocity is in the body frame; a flex's vertices get v + ω × (x − c).
    mujoco.mj_forward(model, data)
    for i, (body, dof) in rigid.items():
        b = setup.bodies[i]
        data.qvel[dof : dof + 3] = b.velocity
        data.qvel[dof + 3 : dof + 6] = data.xmat[body].reshape(3, 3).T @ np.asarray(b.omega)
    for i, (f, dofs) in soft_dofs.items():
        b, x = setup.bodies[i], _flex_x(model, data, f)
        data.qvel[dofs] = np.asarray(b.velocity) + np.cross(np.asarray(b.omega), x - x.mean(0))
    mujoco.mj_forward(model, data)

    n_ids = len(setup.bodies) + 2
    contact = np.zeros((frames, n_ids, n_ids), dtype=bool)
    events: list[tuple] = []
    total = (frames - 1) * n
    steps = np.arange(total + 1) * dt
    vz = np.zeros((total + 1, len(setup.bodies)))
    floor = np.zeros((total + 1, len(setup.bodies)), dtype=bool)
    states = [[] for _ in setup.bodies]
    touching = np.zeros((n_ids, n_ids), dtype=bool)

    def observe(s: int, k: int) -> None:
        nonlocal touching
        now = _touching(data, geom_obj, flex_obj, n_ids)
        for a, b in zip(*np.nonzero(np.triu(now[0] & ~touching)), strict=True):
            events.append((float(steps[s]), int(a), int(b), *_pair_contact(data, now[1], a, b)))
        touching = now[0]
        contact[k] |= touching
        floor[s] = touching[FLOOR_ID, ids]
        for i in range(len(setup.bodies)):
            vz[s, i] = _state(model, data, setup.bodies[i], rigid.get(i), soft_dofs.get(i))["v"][2]

    observe(0, 0)
    for k in range(frames):
        if k:
            for j in range(n):
                mujoco.mj_step(model, data)
                observe((k - 1) * n + j + 1, k)
            # mj_step leaves positions (xipos, xmat, flexvert_xpos) at the stage it last evaluated, not at the new
            # qpos: bring them to it. Solver warm starts are written only by the step, so the run is unchanged.
            mujoco.mj_forward(model, data)
        for i, b in enumerate(setup.bodies):
            states[i].append(_state(model, data, b, rigid.get(i), soft_dofs.get(i)))
    bodies = [{key: np.stack([st[key] for st in sts]) for key in sts[0]} for sts in states]
    for i, (f, _) in soft_dofs.items():
        adr = model.flex_shelldataadr[f]
        bodies[i]["shell"] = model.flex_shell[adr : adr + 3 * model.flex_shellnum[f]].reshape(-1, 3).astype(np.int32)
    return Trace(np.arange(frames) / fps, dt, n, bodies, contact, events, steps, vz, floor, xml,
                 _model_meta(mujoco, model, setup, rigid, soft_dofs))  # fmt: skip


def _flex_x(model, data, f: int) -> np.ndarray:
    return data.flexvert_xpos[model.flex_vertadr[f] : model.flex_vertadr[f] + model.flex_vertnum[f]].copy()


def _state(model, data, b: Body, rigid, soft) -> dict:
    if soft is not None:
        f, dofs = soft
        x, v = _flex_x(model, data, f), data.qvel[dofs]
        return {"x": x, "c": x.mean(0), "v": v.mean(0)}  # the flexcomp's vertices have equal masses
    body, dof = rigid
    R = data.xmat[body].reshape(3, 3).copy()
    return {"R": R, "c": data.xipos[body].copy(), "v": data.qvel[dof : dof + 3].copy(),
            "w": R @ data.qvel[dof + 3 : dof + 6]}  # fmt: skip


def _touching(data, geom_obj, flex_obj, n_ids: int) -> tuple[np.ndarray, np.ndarray]:
    """The symmetric [N, N] matrix of object ids in contact now, and each contact's (id, id) [C, 2]."""
    pairs = np.zeros((data.ncon, 2), dtype=np.int64)
    if data.ncon:
        geom, flex = data.contact.geom, data.contact.flex
        pairs = np.where(geom >= 0, geom_obj[np.maximum(geom, 0)], flex_obj[np.maximum(flex, 0)])
    now = np.zeros((n_ids, n_ids), dtype=bool)
    now[pairs[:, 0], pairs[:, 1]] = True
    return now | now.T, pairs


def _pair_contact(data, pairs: np.ndarray, a: int, b: int) -> tuple[list[float], list[float]]:
    """Mean position and unit normal (from object a to b) of the contacts between a and b."""
    sel = ((pairs[:, 0] == a) & (pairs[:, 1] == b)) | ((pairs[:, 0] == b) & (pairs[:, 1] == a))
    sign = np.where(pairs[sel, 0] == a, 1.0, -1.0)[:, None]  # MuJoCo's normal points from geom1 to geom2
    normal = (sign * data.contact.frame[sel, :3]).sum(0)
    return data.contact.pos[sel].mean(0).tolist(), (normal / np.linalg.norm(normal)).tolist()


def _model_meta(mujoco, model, setup: EngineSetup, rigid: dict, soft: dict) -> dict:
    """Mass, density and inertia of every body as MuJoCo compiled them, and the solver's options."""
    out = []
    for i in range(len(setup.bodies)):
        if i in rigid:
            body = rigid[i][0]
            Ri = np.zeros(9)
            mujoco.mju_quat2Mat(Ri, model.body_iquat[body])
            Ri = Ri.reshape(3, 3)
            inertia = Ri @ np.diag(model.body_inertia[body]) @ Ri.T
            out.append({"mass": float(model.body_mass[body]), "inertia": inertia.tolist()})
        else:
            f = soft[i][0]
            verts = model.flex_vertbodyid[model.flex_vertadr[f] : model.flex_vertadr[f] + model.flex_vertnum[f]]
            out.append({"mass": float(model.body_mass[verts].sum()), "vertices": int(model.flex_vertnum[f]),
                        "tetrahedra": int(model.flex_elemnum[f])})  # fmt: skip
    solver = {0: "PGS", 1: "CG", 2: "Newton"}.get(int(model.opt.solver), str(int(model.opt.solver)))
    return {"bodies": out, "solver": solver, "iterations": int(model.opt.iterations),
            "tolerance": float(model.opt.tolerance)}  # fmt: skip


def first_bounce(trace: Trace, i: int) -> dict | None:
    """Body ``i``'s first floor contact: the vertical speeds of its centre of mass at the last step before it and the
    first step after it, and their ratio (the restitution, for a ball whose contact normal is vertical); None if it
    has not left the floor again within the run."""
    touch = trace.floor[:, i]
    if not touch.any():
        return None
    s0 = int(np.argmax(touch))
    rest = np.nonzero(~touch[s0:])[0]
    if s0 == 0 or len(rest) == 0:
        return None
    s1 = s0 + int(rest[0])
    before, after = float(trace.vz[s0 - 1, i]), float(trace.vz[s1, i])
    return {"seconds": float(trace.steps[s0]), "contact_s": float(trace.steps[s1] - trace.steps[s0]),
            "vz_before": before, "vz_after": after, "restitution": -after / before}  # fmt: skip
