"""What ``causalgs discover`` leaves for people: ``report.json``, ``report.md`` and the plots.

- ``error.png``: the per-frame RMS distance between simulation and measurement before and after the repair, the fit
  window shaded, the noise floor and the first departure marked (log scale: a repair that works drops by a factor),
  and, seen through a lens, the base model's departure from rigid motion (the deformation rigid tracks cannot
  follow, and err by about as much);
- ``residuals.png``: the residual heat on the particles over the held-out frames, before and after, seen from the
  side and from above, on one colour scale;
- ``paths.png``: the measured centroid path of every body against the simulated ones before and after;
- ``trajectories.npz``: the measurement and both simulations, every point at every frame (``times`` [T], ``x``,
  ``before``, ``after`` [T, P, 3] in metres, ``body`` [P], ``observed``: frames from there on were held out), the
  simulations seen as the measurement sees them and starting from its first frame.

Every file is written atomically; the report's numbers are the ones :func:`causalgs.discover.search.discover`
returned, nothing recomputed here.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from causalgs.discover.observation import Observation
from causalgs.io import write_bytes, write_json, write_npz, write_text

# a signature explaining less of the residual acceleration than this is reported as not showing the effect
SIGNATURE_WEAK = 0.25


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    _plt().close(fig)
    write_bytes(path, buf.getvalue())


def plot_images(panels: list[tuple[str, np.ndarray]], title: str, path: Path) -> None:
    """``images.png``: [H, W, 3] images in [0, 1] side by side, each under its label, pixels shown as they are."""
    plt = _plt()
    h, w = panels[0][1].shape[:2]
    size = 2.6  # inches a panel is tall
    fig, axes = plt.subplots(1, len(panels), figsize=(size * w / max(h, 1) * len(panels), size + 0.6), squeeze=False)
    for ax, (label, img) in zip(axes[0], panels, strict=True):
        ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
        ax.set_title(label, fontsize=9)
        ax.set_axis_off()
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    _save(fig, path)


def _rms_curve(sim: np.ndarray, obs: Observation) -> np.ndarray:
    return np.sqrt(((sim - obs.x[1:]) ** 2).sum(-1).mean(-1))


def _after_label(report: dict) -> str:
    """The repaired model's curve: every effect added, or for an ambiguity set the first one (the model the repair
    keeps) with the candidates the data could not tell from it."""
    if report["discovered"]:
        return "after: " + " + ".join(d["effect"] for d in report["discovered"])
    first, *rest = [a["effect"] for a in report["ambiguous"]]
    return f"after: {first}" + (f" (not told apart from {', '.join(rest)})" if rest else "")


def _plain_log_ticks(ax) -> None:
    """Millimetres as plain numbers on a log axis (6, 8, 10 rather than 6×10⁰); the ticks between the decades are
    labelled only where the axis spans less than a decade and a half, as there they are the only labels."""
    from matplotlib.ticker import FuncFormatter, NullFormatter

    plain = FuncFormatter(lambda v, _: f"{v:g}")
    ax.yaxis.set_major_formatter(plain)
    lo, hi = ax.get_ylim()
    ax.yaxis.set_minor_formatter(plain if hi < 30 * lo else NullFormatter())


def plot_error(report: dict, traj: dict, obs: Observation, path: Path) -> None:
    plt = _plt()
    frames = np.arange(1, len(obs.times))
    fig, ax = plt.subplots(figsize=(7.0, 3.6))
    ax.axvspan(0, obs.observed - 0.5, color="0.92", label="fit window")
    ax.plot(frames, 1000 * _rms_curve(traj["before"], obs), color="tab:red", lw=1.6, label="before")
    if report["discovered"] or report["ambiguous"]:
        ax.plot(frames, 1000 * _rms_curve(traj["after"], obs), color="tab:blue", lw=1.6, label=_after_label(report))
    floor = report["disagreement"]["floor"]
    ax.axhline(1000 * floor, color="0.4", ls=":", lw=1, label="noise floor")
    blind = np.asarray(report["disagreement"].get("blind") or [])
    if len(blind) == len(frames) and (blind > 0.1 * floor).any():  # the deformation the tracks cannot follow
        ax.plot(frames, 1000 * np.sqrt(3) * np.maximum(blind, 1e-6), color="0.5", ls="--", lw=1,
                label=f"base model's departure from {_lens(report)}")  # fmt: skip
    dep = report["disagreement"].get("first_departure")
    if dep:
        ax.axvline(dep["frame"], color="tab:red", ls="--", lw=0.8)
        text = f"first departure\nframe {dep['frame']}, {dep['body']}, {dep['contact']}"
        ax.annotate(text, (dep["frame"], ax.get_ylim()[1]), xytext=(4, -4), textcoords="offset points", va="top",
                    fontsize=8)  # fmt: skip
    ax.set_yscale("log")
    _plain_log_ticks(ax)
    ax.set_xlabel("frame")
    ax.set_ylabel("RMS distance (mm)")
    ax.set_title(f"simulation vs measurement — {report['verdict']}")
    ax.legend(fontsize=8, loc="best")
    ax.grid(alpha=0.3, which="both")
    _save(fig, path)


def plot_residuals(traj: dict, obs: Observation, path: Path) -> None:
    """Per-particle RMS over the held-out frames (all frames after the first if nothing is held out)."""
    plt = _plt()
    fut = list(range(obs.observed, len(obs.times))) or list(range(1, len(obs.times)))
    errs = {k: 1000 * np.sqrt(((traj[k][[f - 1 for f in fut]] - obs.x[fut]) ** 2).sum(-1).mean(0))
            for k in ("before", "after")}  # fmt: skip
    vmax = max(float(errs["before"].max()), 1e-6)
    where = obs.x[fut[-1]]
    fig, axes = plt.subplots(2, 2, figsize=(8.4, 6.8), layout="constrained")
    for col, k in enumerate(("before", "after")):
        for row, (i, j, name) in enumerate(((0, 2, "side (x–z)"), (0, 1, "top (x–y)"))):
            ax = axes[row, col]
            order = np.argsort(where[:, 3 - i - j])  # far points first
            sc = ax.scatter(where[order, i], where[order, j], c=errs[k][order], s=9, cmap="inferno", vmin=0,
                            vmax=vmax)  # fmt: skip
            ax.set_aspect("equal")
            # one colour scale for both, so a repair that works turns dark; the median says by how much
            ax.set_title(f"{k}: {name}, median {float(np.median(errs[k])):.3g} mm", fontsize=9)
            ax.tick_params(labelsize=7)
            ax.locator_params(nbins=5)
            ax.set_xlabel("xyz"[i] + " (m)", fontsize=8)
            ax.set_ylabel("xyz"[j] + " (m)", fontsize=8)
    fig.suptitle(f"each particle's error over the held-out frames {fut[0]}–{fut[-1]}, where it is at frame {fut[-1]}",
                 fontsize=10)  # fmt: skip
    fig.colorbar(sc, ax=axes, shrink=0.8, label="held-out RMS distance (mm)")
    _save(fig, path)


def plot_paths(report: dict, traj: dict, obs: Observation, path: Path) -> None:
    """Each body's centroid path, measured and simulated before and after the repair; beside it the held-out frames
    alone, zoomed (a bounce or a slide of a few millimetres is lost at the scale of the whole throw)."""
    plt = _plt()
    held = obs.observed < len(obs.times)
    fig, axes = plt.subplots(1, 2 if held else 1, figsize=(10.0 if held else 6.0, 3.8), layout="constrained",
                             squeeze=False)  # fmt: skip
    panels = [(axes[0, 0], slice(None), "centroid paths")]
    if held:
        last = len(obs.times) - 1
        panels.append((axes[0, 1], slice(obs.observed - 1, None),
                       f"held-out frames {obs.observed}–{last}, from the fit window's end"))  # fmt: skip
    after = bool(report["discovered"] or report["ambiguous"])
    for ax, frames, title in panels:
        for b in range(obs.bodies):
            sel = obs.body == b
            meas = obs.x[:, sel].mean(1)
            ax.plot(meas[frames, 0], meas[frames, 2], "k.", ms=3, label="measured" if b == 0 else None)
            for key, colour in (("before", "tab:red"), ("after", "tab:blue")):
                if key == "after" and not after:
                    continue
                c = np.concatenate([obs.x[:1, sel], traj[key][:, sel]]).mean(1)
                ax.plot(c[frames, 0], c[frames, 2], color=colour, lw=1.2, label=key if b == 0 else None)
            ax.plot(*meas[obs.observed - 1, [0, 2]], "o", mfc="none", mec="k", ms=7,
                    label="end of fit window" if b == 0 else None)  # fmt: skip
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z (m)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    _save(fig, path)


def _open(closed) -> str:
    """What a profile's sides that did not reach the threshold mean (``closed``: [low, high] reached)."""
    sides = [s for s, c in zip(("below", "above"), closed or (True, True), strict=True) if not c]
    return f" (open {' and '.join(sides)}: within the threshold as far as was tried)" if sides else ""


def _mm(v: float | None) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{1000 * v:.2f} mm"


def _signed(v: float, spec: str = ".1f") -> str:
    """A number with its sign always shown, the minus as the typographic one (−) that the percentages beside it use."""
    return format(v, "+" + spec).replace("-", "\u2212")


def _gap(gap) -> str:
    """A held-out difference against the first-named candidate with its paired-bootstrap 95% interval."""
    if not gap:
        return ""
    lo, hi = gap
    if lo == 0.0 and hi == 0.0:
        return ""
    return f"; its excess over the first, 95% paired bootstrap: [{_signed(lo, '.3g')}, {_signed(hi, '.3g')}] cm²"


def _lens(report: dict) -> str:
    """What the run's tracks move each motion pattern by: "affine" or "rigid"."""
    return "affine" if (report.get("tracking") or {}).get("lens") == "affine" else "rigid"


def _future_floor(report: dict) -> str:
    parts = [f"the floor {_mm(report['floor_rms_m'])}",
             f"the fit window's noise carried forward {_mm(report['predictive_rms_m'])}"]
    if report.get("extent_rms_m"):
        parts.append(f"the bodies' extent, known to ± {_mm(report['shape_resolution_m'] / 2)} a face, carried "
                     f"forward {_mm(report['extent_rms_m'])}")
    if report.get("blind_rms_m"):
        parts.append(f"the {_lens(report)} tracks' error where the bodies deform (an impact), carried forward "
                     f"{_mm(report['blind_rms_m'])}")
    return ", ".join(parts[:-1]) + (", and " if len(parts) > 2 else " and ") + parts[-1]


def markdown(report: dict) -> str:
    """The report for people: verdict first, then the law with its interval, the evidence, the runners-up, the base
    parameters before and after, and the errors."""
    L = [f"# Discovery report: {report['verdict']}", ""]
    src = report.get("source")
    if src:
        L += [f"Source: `{src}`", ""]
    eb, ea = report["error_before"], report["error_after"]
    drop = 1 - ea["future_rms_m"] / eb["future_rms_m"] if eb["future_rms_m"] > 0 else 0.0
    # the floors compare with the errors as the gate weighs them (the same where nothing is weighted)
    fit_w = eb.get("fit_rms_weighted_m", eb["fit_rms_m"])
    fut_w = eb.get("future_rms_weighted_m", eb["future_rms_m"])
    weighed = " (weighted)" if "future_rms_weighted_m" in eb else ""
    if report["discovered"]:
        L.append("## Found")
        for d in report["discovered"]:
            ev = d["evidence"]
            share = ev.get("signature_share")
            # the signature is a hint for the screen; the refit's held-out drop and BIC are what decided
            hint = (f"its signature `{ev['signature']}` explains {_pct(share)} of the residual acceleration"
                    + (" (the smoothed accelerations do not show it; the refit does)"
                       if share is not None and share < SIGNATURE_WEAK else ""))  # fmt: skip
            if share is None:  # a driver the residual accelerations have no measure of (a yield: a lasting strain)
                hint = f"its signature `{ev['signature']}` is not one the residual accelerations measure"
            against = ev.get("against", "base")
            L += [f"- **{d['law']}**"]
            true = {p: true_value(report.get("truth"), p) for p in d["params"]}
            if report.get("truth") and all(v is not None for v in true.values()):
                L.append("  - the scene's truth (a synthetic scene): "
                         + ", ".join(f"{p.split('.', 1)[1]} = {v:.4g}" for p, v in true.items()))  # fmt: skip
            was = d.get("found_as")
            if was:
                later = ", ".join(f"`{e}`" for e in d["refitted_with"])
                L.append(f"  - as the repaired model holds it, refitted with {later} found after it; when found: "
                         f"{was['law'].split(': ', 1)[-1]}")  # fmt: skip
            if d.get("fitted_with"):
                L.append(f"  - found together with `{d['fitted_with']}`, fitted jointly: neither passed the gate "
                         "alone; " + ("this one explained part of the discrepancy by itself, and the pair passes "
                                      "against the base" if against == "base" else
                                      f"beside `{against}` this one passes against `{against}` alone, and the pair "
                                      "against the base"))  # fmt: skip
            L += ["  - evidence" + ("" if against == "base" else f" (against `{against}` alone)") + ": held-out RMS "
                  f"−{100 * (1 - math.sqrt(max(0.0, 1 - ev['future_drop']))):.0f}%; ΔBIC {_signed(ev['delta_bic'])}; "
                  + "".join(f"{p} at {z:.1f} SE{_all(ev, p)}; " for p, z in ev["z"].items()) + hint]  # fmt: skip
            src = d.get("interval_sources") or {}
            rest = src.get("se_rest_shape") or {}
            track = src.get("se_tracking") or {}
            if any(v for v in rest.values()) or any(v for v in track.values()):
                names = ["the residuals' block bootstrap"]
                if any(v for v in rest.values()):
                    # a run's particles are its rest shape: its error there (shown as 0.00 mm) is the extent
                    err, res = src.get("rest_shape_error_m") or 0.0, src.get("shape_resolution_m")
                    shape = " and ".join(part for part in (
                        f"the rest shape's error of {_mm(err)}" if _mm(err) != _mm(0.0) else "",
                        f"the bodies' extent known to ± {_mm(res / 2)} a face" if res else "") if part)  # fmt: skip
                    names.append((shape or "the rest shape's error") + " carried through the fit")
                if any(v for v in track.values()):
                    names.append("the tracks' own smooth error, one for the whole window at the noise credited "
                                 "to them, sized frame by frame as the camera halves disagree, carried through the fit")
                ses = ", ".join(f"{p.split('.', 1)[1]} "
                                + " and ".join(f"{v:.3g}" for v in (src["se_noise"].get(p), rest.get(p), track.get(p))
                                               if v is not None) for p in d["params"])  # fmt: skip
                starts = src.get("starts_within")
                count = {2: "two", 3: "three"}[len(names)]
                L.append(f"  - interval (95%) from {count} sources, standard errors: {ses} ({'; '.join(names)})"
                         + ("" if starts is None else f"; {starts} refit start(s) within the profile threshold"))
            prof = {q: v for q, v in (src.get("profile") or {}).items() if v is not None}
            if prof:
                shut = src.get("profile_closed") or {}
                L.append("  - profile likelihood (every other parameter refitted with it held; 95%, the interval "
                         "spans it): " + ", ".join(f"{q.split('.', 1)[1]} [{lo:.4g}, {hi:.4g}]" + _open(shut.get(q))
                                                   for q, (lo, hi) in prof.items()))  # fmt: skip
            held = d.get("at_bounds") or {}
            if held:
                vals = d.get("base_after", {})
                L.append("  - held at an end of its range in the refit: "
                         + ", ".join(f"{p} = {vals.get(p, float('nan')):.4g} ({side})" for p, side in held.items())
                         + ". The data trade it against the effect; the interval holds given that value, and the "
                           "effect's parameter may be biased by it")  # fmt: skip
            for r in d.get("runners_up", []):
                if r["passed"]:
                    how = {"held-out frames": "told apart on the held-out frames",
                           "fit window": "as good on the held-out frames, told apart by BIC on the fit window"}
                    L.append(f"  - also passed, {how.get(r.get('told_apart_by'), 'told apart')}: `{r['effect']}` "
                             f"(ΔBIC {_signed(r['delta_bic'])}, held-out MSE {r['future_mse_cm2']:.3g} cm²"
                             f"{_gap(r.get('future_gap_cm2'))})")  # fmt: skip
        L.append("")
    elif report["ambiguous"]:
        L += ["## Ambiguous: the data does not separate these", ""]
        L += [f"- {a['law']} (ΔBIC {_signed(a.get('delta_bic', float('nan')))}, held-out MSE "
              f"{a['future_mse_cm2']:.3g} cm²{_gap(a.get('future_gap_cm2'))})"
              for a in report["ambiguous"]]  # fmt: skip
        L.append("")
    elif report["verdict"] == "unexplained discrepancy":
        ratio = fit_w / report["floor_rms_m"]
        fut = fut_w / report["floor_rms_m"]
        held = f"{fut:.1f}× on the held-out frames"
        if report.get("future_floor_rms_m"):
            held = (f"{fut_w / report['future_floor_rms_m']:.1f}× on the held-out frames above what a "
                    f"correct model would miss them by ({_mm(report['future_floor_rms_m'])}: {_future_floor(report)})")
        L += ["## Something is missing that the catalogue does not name", "",
              f"The calibrated model stays {ratio:.1f}× above the noise floor ({_mm(report['floor_rms_m'])} per "
              f"coordinate) on the fit window and {held}, in "
              + ("rigid motion of the bodies that a free force would remove" if _lens(report) == "rigid" else
                 "the bodies' motion and strain, which a free force and a free strain would remove")
              + ", but no candidate passed "
              f"the gate. A force constant over a few time blocks explains "
              f"{_pct(report['disagreement']['residual_force_gain'])} of the residual acceleration (low: impulses "
              "at contacts; high: a smooth force). Where and when: below.", ""]  # fmt: skip
    else:
        ratio = fit_w / report["floor_rms_m"]
        L += ["## No missing effect", "",
              f"The calibrated model is within {ratio:.2f}× of the noise floor ({_mm(report['floor_rms_m'])} per "
              "coordinate), and no candidate improves the held-out frames enough to pass the gate.", ""]  # fmt: skip
        if report.get("future_floor_rms_m"):
            L[-1:] = [f"On the held-out frames it misses by {_mm(fut_w)}{weighed}, "
                      f"{fut_w / report['future_floor_rms_m']:.1f}× what a correct model would miss them "
                      f"by ({_mm(report['future_floor_rms_m'])}: {_future_floor(report)}).", ""]  # fmt: skip
    L += ["## Errors (RMS per coordinate, as the noise; the plots show distances, about √3× as large)", "",
          "| | fit window | held-out future |", "|---|---|---|",
          f"| before | {_mm(eb['fit_rms_m'])} | {_mm(eb['future_rms_m'])} |",
          f"| after | {_mm(ea['fit_rms_m'])} | {_mm(ea['future_rms_m'])} |", "",
          f"Held-out error change: {_signed(-100 * drop, '.0f')}%. Noise per coordinate: {_mm(report['noise'])}.",
          ""]  # fmt: skip
    if weighed:
        L[-1:] = [f"Weighted as the calibrations and the gate weigh them (per coordinate; below): fit window "
                  f"{_mm(fit_w)} → {_mm(ea['fit_rms_weighted_m'])}, held-out future {_mm(fut_w)} → "
                  f"{_mm(ea['future_rms_weighted_m'])}.", ""]  # fmt: skip
    im = report.get("images")
    if im:
        L += [f"On images discovery never fitted ({im['images']} views of held-out cameras at frames "
              f"{im['frames'][0]}–{im['frames'][-1]}): PSNR {im['psnr_before']:.2f} dB before, "
              f"{im['psnr_after']:.2f} dB after (`images.png`: {im['panel']}).", ""]  # fmt: skip
    dis = report["disagreement"]
    dep = dis.get("first_departure")
    tr = report.get("tracking")
    L.append("## Where and when the base model departs")
    if dep:
        L.append(f"- first departure: frame {dep['frame']} (t = {dep['time']:.3f} s), in **{dep['body']}**, "
                 f"{dep['contact']}, around ({', '.join(f'{c:.3f}' for c in dep['centroid'])}) m"
                 + (" — a frame where the tracked motion has lost the images (below)"
                    if tr and dep["frame"] in tr["poor"] else ""))  # fmt: skip
    else:
        L.append("- the error never rises above three times the noise floor")
    bc = dis.get("by_contact", {})
    if any(v is not None for v in bc.values()):  # distances, as the plots; the table above is per coordinate
        L.append("- error by contact state over every frame (RMS distance, as the plots): "
                 + ", ".join(f"{k} {_mm(v)}" for k, v in bc.items() if v is not None))  # fmt: skip
    sig = dis.get("signatures", {})
    if sig:
        L.append("- residual acceleration explained by each driver: "
                 + ", ".join(f"`{k}` {_pct(v)}" for k, v in sorted(sig.items(), key=lambda kv: -kv[1])))  # fmt: skip
    L.append("")
    if tr:
        if tr.get("refined"):
            from causalgs.model.refine import tracks_name

            saved = tracks_name(tr.get("lens") == "affine", bool(tr.get("bend_bodies")))
            L += ["## The measurement", "",
                  "The measured motion is the run's tracked motion (its kinematic fit), refined frame by frame to "
                  f"that frame's images (`{saved}.npz` in "
                  f"the run). On {tr['views']} {tr['cameras']} camera(s) per "
                  f"frame it matches the images at a median PSNR of {tr['median']:.1f} dB over the "
                  f"{len(tr['frames'])} observed frames (the kinematic fit alone: {tr['median_kinematic']:.1f} dB; "
                  f"worst frame {min(tr['psnr']):.1f} dB against {min(tr['psnr_kinematic']):.1f})."]  # fmt: skip
        else:
            L += ["## The measurement", "",
                  f"The measured motion is the run's tracked motion (its kinematic fit). Rendered at {tr['views']} "
                  f"training cameras it matches the images at a median PSNR of {tr['median']:.1f} dB over the "
                  f"{len(tr['frames'])} observed frames."]  # fmt: skip
        if tr.get("lens_patterns"):
            n = tr["lens_patterns"]
            if _lens(report) == "affine":
                L.append(f"The tracks move and stretch each of the run's {n} motion pattern(s) (an affine motion per "
                         "pattern: a rigid one did not follow the images, see below), so the simulation is compared "
                         "through the same lens: every rollout is replaced by the affine motion per pattern that fits "
                         "it best. A bounce, a slide, a spin, a drag and a body's squash or stretch are compared; a "
                         "deformation finer than one strain per pattern is not.")  # fmt: skip
                if tr.get("bend_bodies"):
                    L.append(f"They also bend each of {tr['bend_bodies']} body(ies) by a second-order displacement "
                             "(a foot spread on the ground wider than the top, which one strain per pattern cannot "
                             "show), and the lens fits that too.")  # fmt: skip
            else:
                L.append(f"The tracks move each of the run's {n} motion pattern(s) rigidly, so the simulation is "
                         "compared through the same lens: every rollout is replaced by the rigid motion per pattern "
                         "that fits it best. A bounce, a slide, a spin or a drag is compared in full; a body's "
                         "deformation within a pattern (an elastic wobble) is in neither the measurement nor the "
                         "comparison.")  # fmt: skip
                if tr.get("stretched_frames"):
                    L.append(f"At frames {_ranges(tr['stretched_frames'])} the tracks refined with a stretch per "
                             "pattern strayed from the rigid ones by more than the noise: the bodies deform there (an "
                             "impact), and a rigid pose fitted to their images is off by about as much. There the "
                             "stretching tracks are the measurement, and the simulation is compared through the "
                             "affine motion per pattern that fits it best.")  # fmt: skip
            if tr.get("lens_choice"):
                L.append(tr["lens_choice"])
        blind = report.get("disagreement", {}).get("blind") or []
        if blind and max(blind) > 0.5 * report["noise"]:
            peak = int(np.argmax(blind))
            near = [f + 1 for f, b in enumerate(blind) if b > 0.5 * blind[peak]]
            kind = _lens(report)
            L.append(f"The base model's bodies depart from their {kind} motion by up to {_mm(blind[peak])} per "
                     f"coordinate (frame {peak + 1}; above half of that at frames {_ranges(near)}): {kind} tracks "
                     "cannot follow that deformation and err by about as much there (rigid tracks on the sticky "
                     "landing of `causalgs synth toss`: 2.7–6.4 mm at the impact against 2.8–5.7 mm of "
                     "departure), and the held-out floor carries that error forward.")  # fmt: skip
        w = report.get("weights")
        if w:
            low = [f for f, v in enumerate(w["per_frame_min"]) if f > 0 and v < 0.5]
            what = ("how far the run's stretching tracks stray from its rigid ones" if w.get("source") == "tracks"
                    else "the base fit's departure")
            L.append(f"Every calibration and the gate weigh a residual by σ/√(σ² + e²), e {what} "
                     f"at that frame and body: a residual of the size the tracks may err by there counts as much as "
                     f"the noise does elsewhere (weights down to {w['min_weight']:.2f}"
                     + (f"; below one half at frames {_ranges(low)}" if low else "") + ").")  # fmt: skip
        if report.get("shape_resolution_m"):
            L.append(f"The run filled its bodies with particles at {_mm(report['shape_resolution_m'])}, so a body's "
                     f"faces are known to ± {_mm(report['shape_resolution_m'] / 2)}; a landing's bounce depends on "
                     "them, and the held-out floor and the intervals carry that uncertainty forward.")  # fmt: skip
        if tr.get("pixel_m"):
            L.append(f"A pixel spans {_mm(tr['pixel_m'])} at the bodies; the noise credited to the measurement, "
                     f"{_mm(report['noise'])} per coordinate, is at least a quarter of it (tracking errs smoothly "
                     "over many frames, which the jitter of the tracks does not show).")  # fmt: skip
        if tr.get("split_sigma_m") is not None:
            from causalgs.discover.video import SPLIT

            L.append(f"Refined from each half of the cameras alone, the tracks disagreed by "
                     f"{_mm(tr['split_sigma_m'])} per coordinate and half; the noise credited is at least "
                     f"{SPLIT:g}× that (the halves share most of what tracks miss).")  # fmt: skip
        if tr.get("stray_particles"):
            L.append(f"{tr['stray_particles']} stray particle(s), apart from every body, were left out.")
        if tr["poor"]:
            worst = min(tr["psnr"])
            hint = "; a longer kinematic fit (`--set kinematic.iterations=…`) tracks better"
            hint = "" if tr.get("refined") else hint
            L.append(f"It loses them (more than {tr['drop_db']:.0f} dB below the median, down to {worst:.1f} dB) at "
                     f"frames {_ranges(tr['poor'])}: a disagreement there may be the tracking's, not the "
                     f"physics'{hint}.")  # fmt: skip
        else:
            L.append("No frame falls more than "
                     f"{tr['drop_db']:.0f} dB below it: the disagreement above is the physics'.")  # fmt: skip
        L.append("")
    for i, rnd in enumerate(report["rounds"]):
        L += [f"## Round {i + 1}", "", "| candidate | screen gain | refit held-out MSE (cm²) | passed | why not |",
              "|---|---|---|---|---|"]  # fmt: skip
        refits = {r["effect"]: r for r in rnd["refits"]}
        for s in rnd["screen"]:
            L.append(_round_row(s, refits.get(s["effect"])))
        jt = rnd.get("joint")
        if jt:
            L += ["", f"`{jt['lead']}` explained part of the discrepancy and nothing passed alone, so the other "
                  f"candidates were screened from its refit and refitted jointly with it (both gates: the pair against "
                  f"the base, the partner against `{jt['lead']}` alone):", "",
                  f"| with {jt['lead']} | screen gain | refit held-out MSE (cm²) | passed | why not |",
                  "|---|---|---|---|---|"]  # fmt: skip
            tried = {r["effect"]: r for r in jt["refits"]}
            for s in jt["screen"]:
                L.append(_round_row(s, tried.get(s["effect"])))
        rb = rnd.get("rebased")
        if rb:
            L += ["", f"The model without the candidates, recalibrated from where the `{rb['from']}` refit went, fit "
                  f"the window better ({rb['train_before_cm2']:.3g} → {rb['train_after_cm2']:.3g} cm²; held out "
                  f"{rb['future_before_cm2']:.3g} → {rb['future_after_cm2']:.3g} cm²): the candidates were judged "
                  "against it, as what they add must be more than a better minimum of the base."]  # fmt: skip
        L.append("")
    st = report.get("settled")
    if st:
        window = st.get("train_rms_ratio_to_window_floor", st.get("train_rms_ratio_to_noise"))
        L += [f"Round {st['round']} was not run: the repaired model fits the window at {window:.2f}× and misses the "
              f"held-out frames by {st['future_rms_ratio_to_floor']:.2f}× what a correct model would, so nothing is "
              "left to explain (a further effect could only fit the noise).", ""]  # fmt: skip
    if report["discovered"]:
        d0 = report["discovered"][0]
        before, after = d0["base_before"], report["discovered"][-1]["base_after"]
        truth = report.get("truth")
        keys = list({**before, **after})
        # a synthetic scene's truth beside them, where it holds any of these parameters
        known = truth is not None and any(true_value(truth, k) is not None for k in keys)
        L += ["## Base parameters before and after (the missing effect biases them)", "",
              "| parameter | before | after |" + (" truth |" if known else ""),
              "|---|---|---|" + ("---|" if known else "")]  # fmt: skip
        # a structural effect replaces a base term (sticky ground the Coulomb ground): its parameters are in one
        # model only, shown as "—" in the other
        L += [f"| {k} | {_cell(before, k)} | {_cell(after, k)} |" + (f" {_truth_cell(truth, k)} |" if known else "")
              for k in keys]  # fmt: skip
        gone = [k for k in before if k not in after]
        if gone:
            L += ["", f"The repaired model has no {' or '.join(f'`{k}`' for k in gone)}: a discovered effect "
                  "replaced the term they belong to."]  # fmt: skip
        L.append("")
        L += [f"Repaired model's effects: `{report['final_spec']}`", ""]
        if report.get("refit_config"):
            L += [f"Refit the scene with them: `causalgs fit DATA --config {report['refit_config']} --out NEW_RUN`",
                  ""]  # fmt: skip
    L += ["Plots: `error.png` (error per frame), `residuals.png` (held-out residual heat), `paths.png` (centroids).",
          "", f"Took {report['seconds']:.0f} s."]  # fmt: skip
    return "\n".join(L) + "\n"


def _round_row(s: dict, r: dict | None) -> str:
    """A round table's row: a screened candidate ``s`` and its refit's row ``r`` (None: not refitted)."""
    if r is None:
        return f"| {s['effect']} | {s['gain']:.3f} | not refitted | | |"
    if "error" in r:
        return f"| {s['effect']} | {s['gain']:.3f} | failed: {r['error']} | no | |"
    return (f"| {s['effect']} | {s['gain']:.3f} | {r['future_mse_cm2']:.3g} | {'yes' if r['passed'] else 'no'} | "
            f"{'; '.join(r['reasons'])} |")


_BODY_KEYS = {"E": "E", "nu": "nu", "v0": "velocity", "omega0": "omega"}


def true_value(truth: dict | None, key: str) -> float | None:
    """A model parameter's true value (``block.E``, ``block.v0[0]``, ``ground.mu``, ``force.b[1]``) from the truth
    a synthetic observation carries (``report["truth"]``); 0.0 for a parameter of an effect the truth has not;
    None where there is no truth or it does not hold that parameter."""
    if not truth:
        return None
    owner, _, name = key.partition(".")
    name, _, index = name.partition("[")
    i = int(index.rstrip("]")) if index else 0
    body = next((b for b in truth.get("bodies", []) if b.get("name") == owner), None)
    if body is not None:
        v = body.get(_BODY_KEYS.get(name, name))
    elif name in _BODY_KEYS:  # a body's parameter, of a body the truth does not name
        return None
    else:
        effects = truth.get("effects") or {}
        if owner not in effects:
            return 0.0 if effects and "." in key else None
        v = effects[owner].get(name)
    if isinstance(v, list | tuple):
        v = v[i] if i < len(v) else None
    return float(v) if isinstance(v, int | float) else None


def _truth_cell(truth: dict | None, key: str) -> str:
    v = true_value(truth, key)
    return "—" if v is None else f"{v:.4g}"


def _cell(values: dict, key: str) -> str:
    """A parameter's value, or "—" where the model has no such parameter."""
    return f"{values[key]:.4g}" if key in values else "—"


def _ranges(frames) -> str:
    """[3, 4, 5, 9] → "3–5, 9"."""
    out, start = [], None
    for i, f in enumerate(frames):
        if start is None:
            start = f
        if i + 1 == len(frames) or frames[i + 1] != f + 1:
            out.append(str(start) if start == f else f"{start}–{f}")
            start = None
    return ", ".join(out)


def _all(ev: dict, p: str) -> str:
    """`` (x of every source)`` where the evidence has a z over every source of error that differs from the
    bootstrap's (the tracks' and the shape's errors), else nothing."""
    z_all = (ev.get("z_all") or {}).get(p)
    return "" if z_all is None or math.isclose(z_all, ev["z"][p]) else f" ({z_all:.1f} of every source)"


def _pct(v) -> str:
    return "n/a" if v is None else f"{100 * v:.0f}%"


def finite(obj):
    """``obj`` with every non-finite float replaced by None (JSON has no inf or NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, np.generic):
        return finite(obj.item())
    if isinstance(obj, np.ndarray):
        return finite(obj.tolist())
    return obj


def write_outputs(out, report: dict, traj: dict, obs: Observation) -> None:
    """``report.json``, ``report.md``, the three plots and ``trajectories.npz`` in ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_npz(out / "trajectories.npz", **trajectories(traj, obs))
    write_json(out / "report.json", finite(report))
    write_text(out / "report.md", markdown(report))
    plot_error(report, traj, obs, out / "error.png")
    plot_residuals(traj, obs, out / "residuals.png")
    plot_paths(report, traj, obs, out / "paths.png")


def trajectories(traj: dict, obs: Observation) -> dict[str, np.ndarray]:
    """The arrays of ``trajectories.npz``: ``traj``'s simulations (frames 1..T-1) with the measured first frame,
    where every rollout starts, put before them."""
    full = {k: np.concatenate([obs.x[:1], np.asarray(traj[k], dtype=np.float64)]) for k in ("before", "after")}
    return {"times": obs.times, "x": obs.x, "body": obs.body, "observed": np.int64(obs.observed), **full}
