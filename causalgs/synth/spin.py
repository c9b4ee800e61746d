"""The ``spin`` scene: a textured rigid fan that spins about a tilted axis and drifts at constant velocity.

It is the simplest scene with a known answer for the kinematic path: one rigid body, no gravity, no contact, so the
true velocity field is exactly v(p, t) = v + ω × (p − c(t)) and the future is a closed-form extrapolation. The motion
law is R(t) = exp(ω̂ t), c(t) = c0 + v t with t in seconds (frame / fps); x_world = R(t) x_body + c(t).

The fan is a sphere hub, three thin pitched blades (boxes) and an axle (cylinder), built about the body z axis and
then tilted so that its spin axis is ω's direction. The texture is a solid 3D checker in BODY coordinates times a
per-part colour, so it moves rigidly with the body and three-fold symmetry is broken by colour; shading is Lambertian
with a fixed world light plus ambient, so shading changes as the body turns (as in real video).
"""

from __future__ import annotations

import colorsys
import math

import numpy as np

from causalgs.cameras import Camera, fit_ring_distance, look_at, ring_direction
from causalgs.synth.raycast import Box, Cylinder, RigidBody, Sphere, rotation_exp
from causalgs.synth.writer import SynthScene

FPS = 24.0
FOV = 0.6911112070083618  # camera_angle_x of the D-NeRF / NVFi Blender scenes
ELEVATIONS_DEG = (18.0, 38.0)  # alternated around the ring
FILL = 0.9  # the body stays inside this fraction of the image (in tan-space about the centre) at every frame
N_POINTS = 2000
LIGHT = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
AMBIENT = 0.35
CHECKER = 0.15  # cell size of the solid checker, body units
SUPERSAMPLE = 2  # 2x2 subsamples per pixel for colour and coverage
PART_NAMES = ("hub", "blade_0", "blade_1", "blade_2", "axle")


def _z_to(axis: np.ndarray) -> np.ndarray:
    """A rotation taking +z onto the unit vector ``axis``."""
    z = np.array([0.0, 0.0, 1.0])
    cross = np.cross(z, axis)
    s = np.linalg.norm(cross)
    if s < 1e-12:
        return np.eye(3) if axis[2] > 0 else np.diag([1.0, -1.0, -1.0])
    return rotation_exp(cross / s * math.atan2(s, float(axis @ z)))


def _fan(tilt: np.ndarray) -> RigidBody:
    """The fan in its body frame: built about +z, then rotated by ``tilt`` (so its axis is ``tilt @ z``)."""
    prims = [Sphere(tuple(tilt @ np.zeros(3)), 0.25, part=0)]
    for j in range(3):
        phi = 2.0 * math.pi * j / 3.0
        radial = np.array([math.cos(phi), math.sin(phi), 0.0])
        # Blade frame: long axis radial, pitched 25 degrees about it (a fan, not a flat star).
        pitch = rotation_exp(radial * math.radians(25.0))
        frame = pitch @ np.stack([radial, np.cross([0.0, 0.0, 1.0], radial), [0.0, 0.0, 1.0]], axis=1)
        prims.append(Box(tuple(tilt @ (0.62 * radial)), (0.45, 0.2, 0.05), tilt @ frame, part=1 + j))
    prims.append(Cylinder((0.0, 0.0, 0.0), 0.07, 0.42, tilt, part=4))
    return RigidBody(prims, obj=1)


def _palette(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` well-separated saturated colours: evenly spaced hues from a random start, jittered."""
    h0 = rng.uniform()
    hues = (h0 + np.arange(n) / n + rng.uniform(-0.04, 0.04, size=n)) % 1.0
    sat, val = rng.uniform(0.55, 0.85, size=n), rng.uniform(0.75, 0.95, size=n)
    return np.array([colorsys.hsv_to_rgb(h, s, v) for h, s, v in zip(hues, sat, val, strict=True)])


class SpinScene:
    """Motion, cameras and shading of the spin scene for one seed and size."""

    def __init__(self, *, views: int, frames: int, resolution: int, seed: int, fps: float = FPS):
        rng = np.random.default_rng(seed)
        self.views, self.frames, self.resolution, self.seed, self.fps = views, frames, resolution, seed, fps
        theta, phi = math.radians(rng.uniform(25.0, 45.0)), rng.uniform(0.0, 2.0 * math.pi)
        axis = np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)])
        self.tilt = _z_to(axis) @ rotation_exp([0.0, 0.0, rng.uniform(0.0, 2.0 * math.pi)])
        self.body = _fan(self.tilt)
        self.omega = axis * rng.uniform(1.2, 2.0) * rng.choice([-1.0, 1.0])
        heading = rng.uniform(0.0, 2.0 * math.pi)
        direction = np.array([math.cos(heading), math.sin(heading), rng.uniform(-0.4, 0.4)])
        self.velocity = direction / np.linalg.norm(direction) * rng.uniform(0.1, 0.2)
        self.duration = (frames - 1) / fps
        self.c0 = -0.5 * self.duration * self.velocity  # the path is centred on the origin, where cameras look
        self.palette = _palette(rng, len(PART_NAMES))
        self.checker_offset = rng.uniform(0.0, CHECKER, size=3)
        # Cameras: a ring at the closest distance where the body stays in frame over the whole sequence everywhere.
        self.distance = self._fit_distance()
        self.cameras = [self._camera(i) for i in range(views)]
        self._rays: dict[int, np.ndarray] = {}
        pts, nrm, part = self.body.sample_surface(rng, N_POINTS)
        self.body_points, self.body_normals, self.part_ids = pts, nrm, part

    # -- motion ---------------------------------------------------------------------------------------------------
    @property
    def seconds(self) -> np.ndarray:
        return np.arange(self.frames, dtype=np.float64) / self.fps

    def pose(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Body-to-world pose (R, c) at frame ``k``."""
        t = k / self.fps
        return rotation_exp(self.omega * t), self.c0 + self.velocity * t

    def _eye_direction(self, i: int) -> np.ndarray:
        return ring_direction(i, self.views, ELEVATIONS_DEG)

    def _camera(self, i: int) -> Camera:
        c2w = look_at(self.distance * self._eye_direction(i), (0.0, 0.0, 0.0))
        return Camera.from_blender(c2w, self.resolution, self.resolution, fov_x=FOV)

    def _fit_distance(self) -> float:
        """The smallest ring radius at which every view sees the whole body in frame at every frame.

        Boxes are tested by their corners (a box is inside the convex frustum iff its corners are), the hub and the
        axle by bounding spheres; the frustum is the image shrunk to ``FILL``.
        """
        local, radii = [], []
        for prim in self.body.prims:
            if isinstance(prim, Box):
                signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
                local.append((signs * np.asarray(prim.half)) @ prim.rotation.T + np.asarray(prim.center))
                radii.append(np.zeros(8))
            else:
                centre, r = prim.bsphere()
                local.append(centre[None])
                radii.append(np.array([r]))
        pts_b, radii = np.concatenate(local), np.concatenate(radii)
        pts = np.concatenate([pts_b @ R.T + c for R, c in (self.pose(k) for k in range(self.frames))])  # [F*M, 3]
        dirs = [self._eye_direction(i) for i in range(self.views)]
        return fit_ring_distance(pts, dirs, (0.0, 0.0, 0.0), FOV, FILL, np.tile(radii, self.frames), self.body.radius)

    # -- appearance -----------------------------------------------------------------------------------------------
    def albedo(self, p_body: np.ndarray, part: np.ndarray) -> np.ndarray:
        """Solid texture: the part's colour times a 3D checker in body coordinates."""
        q = np.floor((p_body + self.checker_offset) / CHECKER)
        cells = (q[..., 0] + q[..., 1] + q[..., 2]).astype(np.int64)
        return self.palette[np.clip(part, 0, None)] * np.where(cells % 2 == 0, 1.0, 0.55)[..., None]

    def shade(self, p_body, part, normal_world) -> np.ndarray:
        lambert = np.clip(normal_world @ LIGHT, 0.0, None)
        return self.albedo(p_body, part) * (AMBIENT + (1.0 - AMBIENT) * lambert)[..., None]

    # -- rendering ------------------------------------------------------------------------------------------------
    def _sample_uv(self) -> np.ndarray:
        """Sub-pixel positions [S*S + 1, H, W, 2]: the stratified subsamples, then the pixel centres (for masks)."""
        n = self.resolution
        u, v = np.meshgrid(np.arange(n, dtype=np.float64), np.arange(n, dtype=np.float64))
        offs = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE
        subs = [np.stack([u + ox, v + oy], axis=-1) for oy in offs for ox in offs]
        return np.stack([*subs, np.stack([u + 0.5, v + 0.5], axis=-1)])

    def _directions(self, i: int) -> np.ndarray:
        """World ray directions of camera ``i`` for every sample, cached while they fit in ~256 MB in all."""
        cached = self._rays.get(i)
        if cached is not None:
            return cached
        uv = self._sample_uv()
        _, d = self.cameras[i].rays(uv)
        if d.nbytes * self.views <= 256 * 2**20:
            self._rays[i] = d
        return d

    def render(self, k: int):
        """Yield ``(rgb, alpha, ids)`` for every camera at frame ``k`` (see :class:`SynthScene`)."""
        R, c = self.pose(k)
        n_sub = SUPERSAMPLE * SUPERSAMPLE
        for i, cam in enumerate(self.cameras):
            d = self._directions(i)
            hit = self.body.cast(cam.center, d, R, c)
            # Shade only the covered subsamples, then average them per pixel (straight colour, not premultiplied).
            sub = np.flatnonzero(hit.mask[:n_sub].ravel())
            px = sub % (self.resolution * self.resolution)
            flat = (hit.point.reshape(-1, 3)[sub], hit.part.ravel()[sub], hit.normal.reshape(-1, 3)[sub])
            colour = self.shade(*flat)
            count = np.bincount(px, minlength=self.resolution**2).astype(np.float64)
            rgb = np.stack([np.bincount(px, colour[:, j], minlength=self.resolution**2) for j in range(3)], axis=-1)
            rgb /= np.maximum(count, 1.0)[:, None]
            shape = (self.resolution, self.resolution)
            yield rgb.reshape(*shape, 3), (count / n_sub).reshape(shape), hit.obj[n_sub].astype(np.uint8)

    # -- ground truth ---------------------------------------------------------------------------------------------
    def motion(self) -> dict[str, np.ndarray]:
        poses = [self.pose(k) for k in range(self.frames)]
        R = np.stack([p[0] for p in poses])
        c = np.stack([p[1] for p in poses])
        return {
            "times": np.arange(self.frames, dtype=np.float64) / (self.frames - 1),
            "seconds": self.seconds,
            "fps": np.float64(self.fps),
            "R": R,
            "c": c,
            "omega": self.omega,
            "velocity": self.velocity,
            "c0": self.c0,
            "body_points": self.body_points,
            "body_normals": self.body_normals,
            "trajectories": np.einsum("fij,pj->fpi", R, self.body_points) + c[:, None, :],
            "object_ids": np.ones(len(self.body_points), dtype=np.int64),
            "part_ids": self.part_ids,
        }

    def meta(self) -> dict:
        speed = float(np.linalg.norm(self.omega))
        return {
            "motion": {
                "law": "rigid: x_world = R(t) x_body + c(t), R(t) = exp(hat(omega) t), c(t) = c0 + velocity t, "
                "t in seconds = frame / fps (normalised time = frame / (frames - 1))",
                "omega": self.omega.tolist(),
                "angular_speed": speed,
                "axis": (self.omega / speed).tolist(),
                "velocity": self.velocity.tolist(),
                "c0": self.c0.tolist(),
                "duration_s": self.duration,
                "gravity": None,
            },
            "objects": [
                {
                    "id": 1,
                    "name": "fan",
                    "kind": "rigid",
                    "parts": [
                        {"part": j, "name": name, "shape": type(p).__name__.lower(), "colour": self.palette[j].tolist()}
                        for j, (name, p) in enumerate(zip(PART_NAMES, self.body.prims, strict=True))
                    ],
                    "bounding_radius": self.body.radius,
                }
            ],
            "cameras": {
                "distance": self.distance,
                "elevations_deg": list(ELEVATIONS_DEG),
                "target": [0.0, 0.0, 0.0],
                "up": [0.0, 0.0, 1.0],
                "fit": f"closest ring radius keeping the whole body inside {FILL:g} of every image at every frame",
            },
            "appearance": {
                "texture": "per-part colour x 3D checker in body coordinates",
                "checker_size": CHECKER,
                "checker_offset": self.checker_offset.tolist(),
                "light_direction": LIGHT.tolist(),
                "ambient": AMBIENT,
                "shading": "lambertian",
            },
            "supersampling": SUPERSAMPLE,
            "masks": "object ids at pixel centres",
            "n_points": len(self.body_points),
        }

    def scene(self) -> SynthScene:
        R0, c0 = self.pose(0)
        xyz = self.body_points @ R0.T + c0
        rgb = self.shade(self.body_points, self.part_ids, self.body_normals @ R0.T)
        return SynthScene(
            "spin", self.cameras, self.fps, self.frames, self.render, xyz, rgb, self.motion(), self.meta()
        )


def build(*, views: int, frames: int, resolution: int, seed: int, fps: float = FPS) -> SynthScene:
    """The spin scene as a :class:`~causalgs.synth.writer.SynthScene`."""
    return SpinScene(views=views, frames=frames, resolution=resolution, seed=seed, fps=fps).scene()
