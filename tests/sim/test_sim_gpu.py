"""The simulator on CUDA (float64): its substeps against the plain-torch reference and its checkpointed backward
against finite differences, with every registered effect. The same kernels are checked on the CPU by
``test_mpm_reference.py`` and ``test_backward.py``; here they are compiled for the GPU, where the particle-to-grid
scatter runs as concurrent atomic adds in an order that changes from run to run. Skipped without a CUDA device."""

from __future__ import annotations

import pytest

from causalgs.sim import MODELS, SimConfig

pytestmark = [pytest.mark.gpu]


@pytest.mark.parametrize("model", list(MODELS))
def test_cuda_substeps_match_reference(cuda64, mk, model):
    """Particles spread over the box (in the wall band, below the floor and grounds, in flight), random materials."""
    n = 400
    cfg = SimConfig(res=16, material=model, effects=mk.ALL_EFFECTS, segment=8)
    mk.against_reference(mk.store(n), mk.state(n, seed=2), mk.materials(n, seed=3), cfg, 3, 1e-3, f"{model}: ")


@pytest.mark.gradcheck
def test_cuda_gradients_match_finite_differences(cuda64, mk):
    """The CPU's gradient check (``test_backward.py``) on the GPU: the throw with every effect, over 14 substeps in
    checkpoint segments of 2."""
    sim, inp, w = mk.throw(segment=2)
    mk.check_gradients(sim, inp, w)


def test_cuda_backward_is_repeatable(cuda64, mk):
    """Two backward passes of one rollout agree to round-off, though the GPU's atomic adds sum in varying order."""
    sim, inp, w = mk.throw(segment=2)
    grads = []
    for _ in range(2):
        leaves = {k: v.clone().requires_grad_(True) for k, v in inp.items()}
        mk.throw_loss(sim, leaves, w).backward()
        grads.append({k: v.grad for k, v in leaves.items()})
    for k in grads[0]:
        scale = max(1.0, float(grads[0][k].abs().max()))
        assert float((grads[0][k] - grads[1][k]).abs().max()) <= 1e-9 * scale, k
