"""The MuJoCo scenes (bounce, tumble, knock, soft): layout and determinism at tiny sizes, and the physics of their
trajectories at the default 89 frames, simulated without rendering."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from causalgs.dataset import load_dataset
from causalgs.errors import CausalGSError
from causalgs.synth import DEFAULT_FPS, ENGINE, generate, protocol
from causalgs.synth.engine import GRAVITY, first_bounce, simulate
from causalgs.synth.engine_scenes import FPS, SETUPS, _bodies

SCENES = ("bounce", "tumble", "knock", "soft")
TINY = {"views": 3, "frames": 6, "resolution": 16, "progress": False}
FRAMES = 89
N_FUTURE = FRAMES - protocol(20, FRAMES).n_obs


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*"))
            if p.is_file()}  # fmt: skip


@pytest.fixture(scope="module")
def runs():
    """name -> (setup, trace, posed meshes) of seed 0 at the scene's fps and the default frame count."""
    out = {}
    for name in SCENES:
        setup = SETUPS[name](seed=0)
        trace = simulate(setup, FRAMES, FPS[name])
        out[name] = (setup, trace, _bodies(setup, trace))
    return out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("engine")
    for name in SCENES:
        generate(name, root / name, **TINY)
    return root


def _airborne_frames(trace, i: int) -> int:
    """Frames before body i's first contact (contact[k] covers the steps after frame k - 1, up to frame k)."""
    touched = trace.contact[:, i + 2, :].any(axis=1)
    return int(np.argmax(touched)) if touched.any() else len(touched)


def _landing(trace) -> int:
    """The first frame with any contact between objects that were apart at t = 0."""
    new = trace.contact & ~trace.contact[0]
    return int(np.argmax(new.any(axis=(1, 2))))


@pytest.mark.parametrize("name", SCENES)
def test_scene_generates_and_loads(tiny, name):
    """Each scene writes the shared layout; `causalgs info`'s reader accepts it; gt keys, shapes and the mask ids
    are those of the data contract; the true-object lookup of the recovery report reads its particles."""
    from causalgs.model.recovery import true_objects

    out = tiny / name
    ds = load_dataset(out)
    assert ds.fps == DEFAULT_FPS[name] == FPS[name] and name in ENGINE
    meta = json.loads((out / "gt" / "meta.json").read_text())
    ids = [o["id"] for o in meta["objects"]]
    assert ids == list(range(1, len(ids) + 1)) and meta["objects"][0]["name"] == "floor"
    assert meta["motion"]["gravity"] == list(GRAVITY) and meta["cameras"]["up"] == [0.0, 0.0, 1.0]
    assert meta["motion"]["law"].startswith("MuJoCo ") and "<mujoco" in meta["mjcf"]
    with np.load(out / "gt" / "motion.npz") as z:
        m = dict(z)
    F = TINY["frames"]
    for o in meta["objects"][1:]:
        k = o["id"]
        assert m[f"vertices_{k}"].shape[:2] == (F, m[f"vertices_{k}"].shape[1]) and m[f"triangles_{k}"].shape[1] == 3
        assert m[f"pose_c_{k}"].shape == m[f"velocity_{k}"].shape == (F, 3)
        if o["kind"] == "rigid":
            assert m[f"pose_R_{k}"].shape == (F, 3, 3) and m[f"omega_{k}"].shape == (F, 3)
            assert np.allclose(m[f"pose_R_{k}"] @ np.swapaxes(m[f"pose_R_{k}"], 1, 2), np.eye(3), atol=1e-9)
    P = len(m["particles_rest"])
    assert m["particles"].shape == (F, P, 3) and m["particle_object"].dtype == np.uint8
    assert set(np.unique(m["particle_object"]).tolist()) == set(ids[1:])
    assert np.array_equal(m["particles"][0], m["particles_rest"])
    n = len(ids) + 1
    assert m["contact"].shape == (F, n, n) and np.array_equal(m["contact"], np.swapaxes(m["contact"], 1, 2))
    assert not m["contact"][:, 0].any() and not np.diagonal(m["contact"], axis1=1, axis2=2).any()
    seen = set()
    for p in sorted((out / "gt" / "masks").iterdir()):
        seen |= set(np.unique(cv2.imread(str(p), cv2.IMREAD_UNCHANGED)).tolist())
    assert seen <= set([0, *ids]) and 1 in seen and 2 in seen
    owner = true_objects(m["particles_rest"], out)
    assert np.array_equal(owner, m["particle_object"])


@pytest.mark.parametrize("name", SCENES)
def test_same_seed_same_bytes_other_seed_differs(tiny, tmp_path, name):
    generate(name, tmp_path / "again", **TINY)
    generate(name, tmp_path / "other", **TINY, seed=1)
    assert _hashes(tmp_path / "again") == _hashes(tiny / name)
    other = _hashes(tmp_path / "other")
    assert other.keys() == _hashes(tiny / name).keys()
    assert other["gt/motion.npz"] != _hashes(tiny / name)["gt/motion.npz"]
    assert sum(other[k] != v for k, v in _hashes(tiny / name).items()) > len(other) // 2


@pytest.mark.parametrize("name", SCENES)
def test_free_flight_is_a_parabola_with_the_scene_gravity(runs, name):
    """Before a body's first contact its centre of mass follows x0 + v0 t + g t² / 2 with the recorded gravity, and
    v0 is the throw asked for (the COM velocity recorded at t = 0)."""
    setup, trace, _ = runs[name]
    g = np.asarray(GRAVITY)
    for i, b in enumerate(setup.bodies):
        k = _airborne_frames(trace, i)
        if k == 0:
            continue  # knock's box stands on the floor
        assert k >= 5, (name, b.name, k)
        t, c = trace.seconds[:k], trace.bodies[i]["c"][:k]
        A = np.stack([np.ones_like(t), t, 0.5 * t**2], 1)
        coef, *_ = np.linalg.lstsq(A, c, rcond=None)
        assert np.abs(A @ coef - c).max() < 1e-6
        assert abs(coef[2, 2] / g[2] - 1.0) < 0.01 and np.abs(coef[2, :2]).max() < 0.01 * abs(g[2])
        # Within one step's velocity change: the soft scene's "discrete" integrator is semi-implicit Euler, whose
        # positions follow the parabola of v0 + g dt / 2 (RK4's are exact).
        assert np.allclose(coef[1], b.velocity, atol=abs(g[2]) * trace.timestep)
        assert np.allclose(trace.bodies[i]["v"][0], b.velocity, atol=1e-12)


def test_initial_velocity_and_mjcf_in_meta_rerun_the_scene(tiny):
    """Anyone can re-run a scene from gt/meta.json alone: its MJCF and initial velocities give the recorded poses."""
    import mujoco

    meta = json.loads((tiny / "bounce" / "gt" / "meta.json").read_text())
    with np.load(tiny / "bounce" / "gt" / "motion.npz") as z:
        c, v = z["pose_c_2"], z["velocity_2"]
    ball = meta["objects"][1]
    assert np.allclose(ball["velocity"], v[0]) and np.allclose(ball["center"], c[0])
    model = mujoco.MjModel.from_xml_string(meta["mjcf"])
    data = mujoco.MjData(model)
    data.qvel[:3], data.qvel[3:6] = ball["velocity"], ball["omega"]  # the ball starts unrotated: body = world frame
    steps = meta["motion"]["engine"]["substeps_per_frame"]
    for _ in range(steps * (TINY["frames"] - 1)):
        mujoco.mj_step(model, data)
    mujoco.mj_forward(model, data)  # positions at the final state
    assert np.abs(data.xipos[1] - c[-1]).max() < 1e-12


def test_bounce_restitution_bounces_and_future_motion(runs):
    setup, trace, _ = runs["bounce"]
    fb = first_bounce(trace, 0)
    assert fb is not None and 0.7 <= fb["restitution"] <= 0.9
    assert abs(fb["restitution"] - setup.bodies[0].contact.restitution) < 0.03  # the solref rule holds
    onsets = [e[0] for e in trace.events if e[1:3] == (1, 2)]
    bounces = [t for j, t in enumerate(onsets) if j == 0 or t - onsets[j - 1] > 0.1]
    assert len(bounces) >= 3, onsets
    c = trace.bodies[0]["c"]
    assert np.linalg.norm(c[-1] - c[-1 - N_FUTURE]) > 0.03


@pytest.mark.parametrize("name", SCENES)
def test_future_frames_hold_motion(runs, name):
    """At the scene's fps some body still moves more than 3 cm (its farthest vertex) over the 22 future frames."""
    _, _, meshes = runs[name]
    moved = max(np.linalg.norm(v[-1] - v[-1 - N_FUTURE], axis=1).max() for _, v, _, _ in meshes)
    assert moved > 0.03, moved


def test_tumble_spin_changes_at_landing_and_it_rests_on_a_face():
    setup = SETUPS["tumble"](seed=0)
    long = simulate(setup, 300, FPS["tumble"])  # 5 s
    st, inertia = long.bodies[0], np.asarray(long.model["bodies"][0]["inertia"])
    L = np.einsum("fij,jk,flk,fl->fi", st["R"], inertia, st["R"], st["w"])  # world angular momentum about the COM
    k = _airborne_frames(long, 0)
    assert np.abs(L[:k] - L[0]).max() < 1e-6 * np.linalg.norm(L[0])  # torque-free in flight
    assert np.linalg.norm(L[k : k + 10] - L[0], axis=1).max() > 0.3 * np.linalg.norm(L[0])  # landing changes it
    assert np.linalg.norm(st["v"][-1]) < 1e-3 and np.linalg.norm(st["w"][-1]) < 1e-2
    axis = int(np.argmax(np.abs(st["R"][-1][2])))  # the body axis along world z
    assert abs(abs(st["R"][-1][2, axis]) - 1.0) < 1e-4
    assert abs(st["c"][-1, 2] - setup.bodies[0].size[axis]) < 1e-3


def test_knock_box_rests_until_the_ball_hits_then_both_move(runs):
    _, trace, _ = runs["knock"]
    hit = [e for e in trace.events if e[1:3] == (2, 3)]
    assert hit, "the ball never reaches the box"
    k = int(np.ceil(hit[0][0] * FPS["knock"]))
    box, ball = trace.bodies[0]["c"], trace.bodies[1]["c"]
    assert np.abs(box[:k] - box[0]).max() < 1e-3  # at rest on the floor before the impact
    assert np.linalg.norm(box[-1] - box[k]) > 0.05 and np.linalg.norm(ball[-1] - ball[k]) > 0.05
    speed = np.linalg.norm(trace.bodies[1]["v"], axis=1)
    assert speed[k + 2] < speed[k - 1]  # the ball gives momentum to the box


def test_soft_ball_deforms_after_landing_and_wobbles(runs):
    _, trace, _ = runs["soft"]
    x = trace.bodies[0]["x"]
    k = _airborne_frames(trace, 0)
    i, j = np.triu_indices(x.shape[1], 1)
    rest = np.linalg.norm(x[0, i] - x[0, j], axis=1)
    strain = np.array([np.abs(np.linalg.norm(f[i] - f[j], axis=1) / rest - 1.0).max() for f in x])
    assert strain[k:].max() > 0.1 and strain[k:].max() > 3 * strain[:k].max()
    height = np.ptp(x[:, :, 2], axis=1)
    dh = np.diff(height[k:])
    dh = dh[np.abs(dh) > 1e-4]
    assert np.sum(np.sign(dh[1:]) != np.sign(dh[:-1])) >= 4  # squashes and springs back several times


@pytest.mark.parametrize("name", SCENES)
def test_contacts_only_where_bodies_reach_the_floor_or_each_other(runs, name):
    """No contact involving a body before its lowest point reaches the floor; contacts after the first landing; the
    first landing's event lies on the floor with an upward normal."""
    _, trace, meshes = runs[name]
    landing = _landing(trace)
    assert 0 < landing < FRAMES and trace.contact[landing:].any(axis=0)[1, 2:].any()
    for i, (_, verts, _, _) in enumerate(meshes):
        low = verts[:, :, 2].min(1)
        k = _airborne_frames(trace, i)
        assert (low[:k] > 0).all() and (k == 0 or low[k - 1] > 0)
        assert trace.contact[low < -1e-3, 1, i + 2].all()  # penetrating the floor is touching it
    first = next(e for e in trace.events if e[0] > 0)
    assert (landing - 1) / FPS[name] < first[0] <= landing / FPS[name] + 1e-12
    if first[1] == 1:
        assert abs(first[3][2]) < 0.01 and first[4][2] > 0.99


def test_out_of_range_options_are_one_line_errors(tmp_path):
    for kw, word in (({"effects": "gravity"}, "--effects"), ({"reference_res": 32}, "--reference-res"),
                     ({"fps": 0}, "0"), ({"frames": 1}, "1")):  # fmt: skip
        with pytest.raises(CausalGSError) as err:
            generate("bounce", tmp_path / "x", **{**TINY, **kw})
        msg = str(err.value)
        assert "\n" not in msg and word in msg, msg
    with pytest.raises(CausalGSError, match="'knock' has MuJoCo motion"):
        generate("knock", tmp_path / "x", **TINY, effects="gravity")
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENES)
def test_future_motion_holds_for_other_seeds(name):
    for seed in range(1, 6):
        setup = SETUPS[name](seed=seed)
        meshes = _bodies(setup, simulate(setup, FRAMES, FPS[name]))
        moved = max(np.linalg.norm(v[-1] - v[-1 - N_FUTURE], axis=1).max() for _, v, _, _ in meshes)
        assert moved > 0.03, (seed, moved)
