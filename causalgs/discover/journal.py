"""What a discovery run has finished so far, kept on disk so that a stopped run loses none of it.

Nearly all of a discovery run's time goes into calibrations (each a few hundred rollouts of the MPM; at the video
level a refit of one candidate takes a quarter of an hour on two cores). The loop is deterministic given its
inputs, so every calibration is named by where it happens (``"base/1e+05"``, ``"round 1/drag/start 2"``,
``"round 1/drag/polish"``) and its result — θ, loss, evaluations — is written to ``progress.json`` as soon as it
ends (atomically). A run resumed on the same inputs (the same options and the same measurement, checked by a
fingerprint) takes every finished calibration from the file and only computes what is left; a file of other inputs
is a one-line error rather than a silently mixed result. The calibration under way keeps its state as it goes
(``calibrating.json`` beside it: the scan's points so far, the warm-up, every accepted Levenberg–Marquardt
iteration; :class:`~causalgs.discover.calibrate.Resume`), so a stop loses at most an iteration of it.

A name says where a calibration happens, not where it starts: a change of the loop's starting rules (a refit's second
start taken elsewhere) keeps every name. So each entry and each kept state records its start θ (``"from"``), and one
whose start differs from the one asked for now (by more than :data:`SAME_START`, far above the last bits in which two
rollouts of one θ differ), or that scanned around it otherwise (:func:`same_scan`), is computed again and replaced
rather than silently returned. Entries written before starts were recorded carry none and are taken as they are.

The fingerprint covers what a calibration's result depends on (:func:`calibration_options`: the model, its grid,
the starts, the iteration budget), not what decides between results (the gate, the ambiguity margins, the number
of rounds): a run re-judged with another gate reuses every calibration it still needs. Names carry the effects
accepted before their round (``"round 2 after linear_drag/force/start 1"``), so a round that starts from another
model never takes a calibration of the old one.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch

from causalgs.discover.calibrate import Fit, Resume, calibrate
from causalgs.errors import CausalGSError
from causalgs.io import read_json, write_json

VERSION = 1
SAME_START = 1e-3  # θ's units (log-stiffness and logit ratios, m/s): a start further off in any entry is another start


def same_scan(entry: dict, scan: int) -> bool:
    """Whether the kept ``entry`` (or state) moved its start as ``scan`` says: 0 not at all, else the reach of the
    grid scan of its planes' heights (:func:`~causalgs.discover.calibrate.scanned_start`). Entries written before
    the scan was recorded carry none and are taken as they are, unless asked for a wider scan than any then."""
    return entry.get("scanned", scan if scan <= 1 else None) == scan


def calibration_options(spec: str, learn, cfg, start: dict | None = None) -> dict:
    """What the results of a discovery run's calibrations depend on, besides the measurement: the base model
    (``spec``, ``learn``, the start values ``start``) and of ``cfg`` (a
    :class:`~causalgs.discover.search.DiscoverConfig`) the grid, the starting stiffnesses, the iteration budget and
    the warm-up horizon, and whether residuals are weighted where rigid tracks cannot follow the bodies (and by
    what)."""
    out = {"spec": spec, "learn": list(learn), "start": start, "res": cfg.res, "starts": list(cfg.starts),
           "iterations": cfg.iterations, "warm": cfg.warm, "weigh": cfg.weigh}  # fmt: skip
    if cfg.weigh and cfg.weigh_by != "base":  # runs weighted by the base fit keep their key
        out["weigh_by"] = cfg.weigh_by
    return out


def fingerprint(options: dict, x: np.ndarray, mix: np.ndarray | None = None, lens_kind: str = "rigid",
                bend: np.ndarray | None = None, stretch: np.ndarray | None = None) -> str:  # fmt: skip
    """A digest of the run's options, its measurement (positions at full precision, and the lens the simulation is
    compared through, ``Observation.mix``, ``lens_kind``, ``bend`` and ``stretch``) and the causalgs version (a
    calibration of another version may mean other things by the same θ)."""
    from causalgs import __version__

    h = hashlib.sha256(json.dumps({"options": options, "version": __version__}, sort_keys=True).encode())
    h.update(np.ascontiguousarray(x, dtype=np.float64).tobytes())
    if mix is not None:
        h.update(b"mix")
        h.update(np.ascontiguousarray(mix, dtype=np.float64).tobytes())
        if lens_kind != "rigid":
            h.update(lens_kind.encode())
        if bend is not None:
            h.update(b"bend")
            h.update(np.ascontiguousarray(bend, dtype=np.int64).tobytes())
        if stretch is not None:
            h.update(b"stretch")
            h.update(np.ascontiguousarray(stretch, dtype=bool).tobytes())
    return h.hexdigest()[:16]


class Journal:
    """Finished calibrations by name (see the module docstring). ``path`` None: nothing is kept (a run in memory)."""

    def __init__(self, path: str | Path | None, key: str, *, resume: bool = False):
        self.path = None if path is None else Path(path)
        self.key = key
        self.entries: dict[str, dict] = {}
        self.screens: dict[str, dict] = {}  # finished screens by round name: their start θ, candidates and rows
        self.reused = 0
        self.screens_reused = 0
        self.restarted: list[str] = []  # names whose kept result began from another start: computed again
        self.partial: dict[str, dict] = {}  # the calibration under way: its name → its states (Resume)
        if self.path is None:
            return
        if self.path.exists():
            if not resume:
                raise CausalGSError(f"{self.path.parent} already holds a discovery run: use --resume to continue it "
                                    "or choose another --out")  # fmt: skip
            saved = read_json(self.path, "discovery progress")
            if not isinstance(saved, dict) or saved.get("version") != VERSION or "entries" not in saved:
                raise CausalGSError(f"{self.path}: not a progress file of this version of causalgs discover")
            if saved.get("fingerprint") != key:
                raise CausalGSError(f"{self.path}: made with other options or another measurement; move "
                                    f"{self.path.parent} away (or choose another --out) to start afresh")  # fmt: skip
            self.entries = dict(saved["entries"])
            self.screens = dict(saved.get("screens", {}))  # files written before screens were kept have none
        if self._partial_path.is_file() and resume:
            try:
                saved = read_json(self._partial_path, "calibration in progress")
            except CausalGSError:
                saved = None  # a state is only a shortcut: without it the calibration starts again
            if isinstance(saved, dict) and saved.get("fingerprint") == key and isinstance(saved.get("states"), dict):
                self.partial = saved["states"]

    @property
    def _partial_path(self) -> Path:
        return self.path.with_name("calibrating.json")

    def __len__(self) -> int:
        return len(self.entries)

    def calibrate(self, name: str, model, theta: torch.Tensor, **options) -> Fit:
        """The calibration ``name`` (:func:`~causalgs.discover.calibrate.calibrate` of ``model`` from ``theta`` with
        ``options``): from the file when finished before, else computed and recorded at once."""
        begin = _floats(theta)
        scan = int(options.get("scan", 0))
        e = self.entries.get(name)
        if e is not None and same_start(e.get("from"), begin) and same_scan(e, scan):
            self.reused += 1
            return Fit(torch.tensor(e["theta"], dtype=torch.float64), float(e["loss"]), int(e["evaluations"]),
                       float(e["start"]))  # fmt: skip
        if e is not None:
            self.restarted.append(name)
        t0 = time.monotonic()
        states = self.partial.get(name)
        if states is None or not same_start(states.get("from"), begin) or not same_scan(states, scan):
            states = self.partial[name] = {}
        states["from"] = begin
        states["scanned"] = scan
        spent = float(states.get("seconds", 0.0))  # before the stop, when it goes on from a kept state
        f = calibrate(model, theta, **options, resume=Resume(states, lambda: self._keep(name, t0, spent)))
        self.entries[name] = {"theta": [float(v) for v in f.theta.detach().double()], "loss": _finite(f.loss),
                              "evaluations": int(f.evaluations), "start": float(f.start), "from": begin,
                              "scanned": scan, "seconds": round(spent + time.monotonic() - t0, 2)}  # fmt: skip
        self._write()
        self.partial.pop(name, None)
        self._write_partial()
        return f

    def screened(self, name: str, theta: torch.Tensor, keys: list[str]) -> list[dict] | None:
        """The rows (:func:`~causalgs.discover.screen.screen_rows`) of the round ``name``'s screen where it was
        finished before from ``theta`` over the candidates ``keys``, else None. A screen is a few minutes of
        rollouts at the video level (one per parameter of the base and of every candidate), which a resumed run
        would otherwise run again."""
        e = self.screens.get(name)
        if e is None or e.get("keys") != list(keys) or not same_start(e.get("from"), _floats(theta)):
            return None
        self.screens_reused += 1
        return e["rows"]

    def keep_screen(self, name: str, theta: torch.Tensor, keys: list[str], rows: list[dict]) -> None:
        """Record the round ``name``'s finished screen from ``theta`` over ``keys`` (see :meth:`screened`)."""
        self.screens[name] = {"from": _floats(theta), "keys": list(keys), "rows": rows}
        self._write()

    def _keep(self, name: str, t0: float, spent: float) -> None:
        """The state of the calibration ``name`` changed: kept on disk, with the seconds it has taken so far."""
        self.partial[name]["seconds"] = round(spent + time.monotonic() - t0, 2)
        self._write_partial()

    def _write(self) -> None:
        if self.path is not None:
            write_json(self.path, {"version": VERSION, "fingerprint": self.key, "entries": self.entries,
                                   "screens": self.screens})  # fmt: skip

    def _write_partial(self) -> None:
        if self.path is None:
            return
        if self.partial:
            write_json(self._partial_path, {"version": VERSION, "fingerprint": self.key, "states": self.partial})
        else:
            self._partial_path.unlink(missing_ok=True)


def same_start(kept: list | None, begin: list[float]) -> bool:
    """Whether a kept calibration began from ``begin``: the same length and every entry within :data:`SAME_START`
    (absolute, plus as much relative). ``kept`` None (an entry written before starts were recorded) counts as the
    same."""
    return kept is None or (len(kept) == len(begin) and np.allclose(kept, begin, rtol=SAME_START, atol=SAME_START))


def _floats(theta: torch.Tensor) -> list[float]:
    return [float(v) for v in theta.detach().double()]


def _finite(v: float) -> float:
    """JSON has no infinity: an infinite loss (a blown-up fit) is kept as a very large one."""
    return float(v) if np.isfinite(v) else 1e300
