"""fallingball, collide and room: layout, masks, and the physics of their generated ground truth (coarse reference
grid for speed; the laws checked hold at any resolution)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from causalgs.dataset import load_dataset
from causalgs.synth import physics
from causalgs.synth.writer import write_dataset

VIEWS, RES, SIM_RES = 3, 32, 32


def _make(tmp_path_factory, name: str, frames: int):
    from causalgs import _ti

    _ti.init("cpu", "float32")
    out = tmp_path_factory.mktemp(name) / "data"
    scene = getattr(physics, name)(views=VIEWS, frames=frames, resolution=RES, seed=3, progress=False,
                                   reference_res=SIM_RES, fps=24.0)  # fmt: skip
    write_dataset(out, scene, background=(1, 1, 1), progress=False)
    with np.load(out / "gt" / "motion.npz") as z:
        motion = dict(z)
    return out, load_dataset(out), motion, json.loads((out / "gt" / "meta.json").read_text())


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    return _make(tmp_path_factory, "fallingball", 8)


@pytest.fixture(scope="module")
def collide(tmp_path_factory):
    return _make(tmp_path_factory, "collide", 12)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return _make(tmp_path_factory, "room", 6)


def _strain(F) -> np.ndarray:
    """max |FᵀF − I| per frame and particle (rotation-free)."""
    F = F.astype(np.float64)
    return np.abs(np.swapaxes(F, -1, -2) @ F - np.eye(3)).max(axis=(-1, -2))


def _mask_ids(out, ds) -> set[int]:
    ids = set()
    for f in ds.frames():
        mask = cv2.imread(str(out / "gt" / "masks" / f"r_{f.view:03d}_{f.frame:03d}.png"), cv2.IMREAD_UNCHANGED)
        ids |= set(np.unique(mask).tolist())
    return ids


def test_ball_follows_its_throw_until_contact(ball):
    """A stiff ball thrown up: its centre follows z0 + vz t − g t²/2 while in the air; it is seen in every image."""
    out, ds, motion, meta = ball
    (obj,) = [o for o in meta["objects"] if o["name"] == "ball"]
    assert obj["kind"] == "stiff" and _mask_ids(out, ds) == {0, 1, 2}
    com = motion["particles"].astype(np.float64).mean(1)
    t = motion["seconds"]
    vz = obj["velocity"][2]
    dt = 1.0 / (meta["fps"] * min(meta["motion"]["substeps_per_frame"]))
    for k in range(1, len(t)):
        if motion["particles"][k, :, 2].min() < 0.05:
            break
        law = com[0, 2] + vz * t[k] - 0.5 * 9.8 * t[k] ** 2
        assert abs(com[k, 2] - law) < 0.01 * abs(com[k, 2] - com[0, 2]) + 9.8 * t[k] * dt, k
    # Stiff: barely strains (F may rotate: the ball spins).
    assert _strain(motion["F"]).max() < 0.05


def test_collision_pushes_the_soft_block_and_deforms_it_more(collide):
    out, ds, motion, meta = collide
    assert _mask_ids(out, ds) == {0, 1, 2, 3}
    obj = {o["id"]: o for o in meta["objects"]}
    assert obj[2]["E"] * 10 < obj[3]["E"], "the ball is an order of magnitude stiffer than the block"
    owner = motion["particle_object"]
    x = motion["particles"].astype(np.float64)
    strain = _strain(motion["F"])
    assert strain[:, owner == 2].max() > 2 * strain[:, owner == 3].max(), "the soft block deforms more"
    # The ball flies along x towards the block; momentum passes to the block, which moves the same way.
    direction = np.sign(obj[3]["velocity"][0])
    block = x[:, owner == 2].mean(1)
    assert direction * (block[-1, 0] - block[0, 0]) > 0.005


def test_room_has_static_background_and_three_bodies(room):
    out, ds, _, meta = room
    assert _mask_ids(out, ds) == {0, 1, 2, 3, 4}
    kinds = sorted((o["name"], o["kind"]) for o in meta["objects"])
    assert kinds == [("ball", "stiff"), ("floor and walls", "static"), ("jelly", "elastic"), ("slab", "elastic")]
    Es = sorted(o["E"] for o in meta["objects"] if "E" in o)
    assert Es[0] * 3 < Es[1] and Es[1] * 3 < Es[2], "three clearly different stiffnesses"
    assert (out / "contact_sheet.png").is_file()


def _hashes(root) -> dict[str, str]:
    import hashlib

    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*"))
            if p.is_file()}  # fmt: skip


@pytest.mark.parametrize(
    "name",
    ["room", pytest.param("fallingball", marks=pytest.mark.slow), pytest.param("collide", marks=pytest.mark.slow)],
)
def test_deterministic_for_a_seed(tmp_path, name):
    from causalgs import _ti

    _ti.init("cpu", "float32")
    outs = []
    for i in range(2):
        scene = getattr(physics, name)(views=2, frames=3, resolution=16, seed=5, progress=False, reference_res=SIM_RES)
        outs.append(tmp_path / str(i))
        write_dataset(outs[-1], scene, background=(1, 1, 1), progress=False)
    assert _hashes(outs[0]) == _hashes(outs[1])


@pytest.mark.slow
def test_cli_writes_the_whole_suite(tmp_path):
    """Slow: simulates every scene at the default reference resolution."""
    from click.testing import CliRunner

    from cli.main import cli

    out = tmp_path / "suite"
    args = ["synth", "all", "--out", str(out), "--views", "2", "--frames", "3", "--resolution", "16"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    for name in ("spin", "fallingball", "jelly", "collide", "room"):
        assert f"Wrote '{name}'" in res.output
        assert load_dataset(out / name).image_size == (16, 16)
    res = CliRunner().invoke(cli, [*args, "--force", "--effects", "gravity"])
    assert res.exit_code != 0 and "not to 'all'" in res.output


def test_reference_res_option_sets_the_true_grid(tmp_path):
    """--reference-res sets the truth's simulation grid (recorded in gt/meta.json); analytic scenes and grids out of
    range are refused with one line."""
    from click.testing import CliRunner

    from cli.main import cli

    out = tmp_path / "toss"
    args = ["synth", "toss", "--out", str(out), "--views", "2", "--frames", "2", "--resolution", "16"]
    r = CliRunner().invoke(cli, [*args, "--reference-res", "16"])
    assert r.exit_code == 0, r.output
    meta = json.loads((out / "gt" / "meta.json").read_text())
    grid = meta["motion"]["grid"]
    assert grid["res"] == 16 and grid["dx"] == pytest.approx(1.0 / 16)
    r = CliRunner().invoke(cli, ["synth", "spin", "--out", str(tmp_path / "spin"), "--reference-res", "16"])
    assert r.exit_code != 0 and "--reference-res" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(cli, [*args, "--force", "--reference-res", "4"])
    assert r.exit_code != 0 and "--reference-res" in r.output


@pytest.mark.parametrize("size", [(0.1, 0.08, 0.06), (0.05, 0.05, 0.05), (0.07, 0.031, 0.044)])
def test_a_box_is_rendered_as_the_union_of_its_particles_cells(size):
    """The rendered box and the simulated one agree: every face of the mesh is a face of the lattice's cells, so
    the mesh encloses exactly the particles' volume (a side that is not a whole number of spacings used to be
    rendered at its nominal length, up to half a spacing off the simulated body)."""
    spacing = 0.011627
    body = physics.Body("b", "box", (0.01, -0.02, 0.2), size, E=1e4, nu=0.3, density=1e3, color=(1, 0, 0))
    X = body.lattice(spacing)
    V, T = body.surface(spacing)
    assert np.allclose(V.min(0), X.min(0) - spacing / 2) and np.allclose(V.max(0), X.max(0) + spacing / 2)
    a, b, c = (V[T[:, i]] for i in range(3))
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6  # divergence theorem over the closed mesh
    assert abs(abs(volume) - len(X) * spacing**3) < 1e-9
    assert np.all(np.abs(V.max(0) - V.min(0) - 2 * np.asarray(size)) <= spacing / 2 + 1e-12)
    # every particle's cell lies inside the mesh's box, and the lattice fills it with no gap
    counts = np.round((V.max(0) - V.min(0)) / spacing).astype(int)
    assert len(X) == counts.prod()


def test_a_body_smaller_than_the_particle_spacing_is_a_one_line_error():
    from causalgs.errors import CausalGSError

    grain = physics.Body("grain", "ball", (0.0, 0.0, 0.2), (0.001,), E=1e4, nu=0.3, density=1e3, color=(1, 0, 0))
    with pytest.raises(CausalGSError, match="'grain' is smaller than the particle spacing"):
        grain.lattice(0.01)
    with pytest.raises(CausalGSError, match="smaller than the particle spacing"):
        physics.Body("flake", "box", (0, 0, 0.2), (0.05, 0.05, 0.001), E=1e4, nu=0.3, density=1e3,
                     color=(1, 0, 0)).surface(0.01)  # fmt: skip
