"""``causalgs discover`` and ``causalgs discover-table``."""

from __future__ import annotations

import json
import os
from pathlib import Path

import click

from causalgs.errors import CausalGSError
from cli.options import out_option, precision_option


def _console_log():
    from rich.console import Console

    console = Console(stderr=True)
    return lambda msg: console.log(msg)


def _names(text: str | None, what: str) -> tuple[str, ...] | None:
    if text is None:
        return None
    items = tuple(s.strip() for s in text.split(",") if s.strip())
    if not items and what == "--candidates":
        raise CausalGSError("--candidates: give at least one candidate")
    return items


def _cpus(share: int = 1) -> int:
    """CPUs this process may use, over ``share`` (at least 1): the default count of rollout workers."""
    from causalgs import _ti

    allowed = _ti.allowed_cpus()
    return max(1, (len(allowed) if allowed else (os.cpu_count() or 1)) // share)


def _starts(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(s) for s in text.split(",") if s.strip())
    except ValueError:
        raise CausalGSError(f"--starts '{text}' must be comma-separated stiffnesses in Pa") from None
    if not vals or not all(v > 0 for v in vals):
        raise CausalGSError(f"--starts '{text}' must be comma-separated positive stiffnesses in Pa")
    return vals


@click.command()
@click.argument("source", type=click.Path(path_type=Path))
@out_option()
@click.option("--effects", "spec", default=None,
              help="The model's effects (a spec of the simulator's registry): what discovery starts from.  "
                   "[default: a run's own physics; for a file 'gravity;ground:mu=0.3;walls']")
@click.option("--learn", default=None,
              help="Effect parameters calibrated with the base model, comma-separated ('' for none).  "
                   "[default: what a run learned; for a file 'ground.mu']")
@click.option("--candidates", default=None,
              help="Candidates to consider, comma-separated: force, linear_drag, quadratic_drag, damping, friction, "
                   "sticky, plasticity.  [default: all that the model lacks]")  # fmt: skip
@click.option("--max-effects", type=click.IntRange(1, 5), default=2, show_default=True,
              help="Effects added at most (one per round, while one passes the gate).")
@click.option("--res", type=click.IntRange(0, 128), default=0,
              help="Grid cells across the simulation box of the calibrated model; 0: a run's own grid (20 for an "
                   "observation file). A coarser grid than the run's changes contact: the toss block landing at "
                   "120 fps rebounds to 0.21 m on 20 cells and to 0.10 m on 32 or 43 (the truth's spacing), so a "
                   "coarse model cannot reproduce a landing whatever its parameters.  [default: 0]")  # fmt: skip
@click.option("--starts", default="1e4,1e5", show_default=True,
              help="Starting stiffnesses (Pa) of the base calibration, comma-separated. Where the fit window "
                   "holds a contact, the base is also calibrated from the best point of a coarse scan of the "
                   "materials and the learned effect parameters (a bounce has many basins).")
@click.option("--iterations", type=click.IntRange(1, 500), default=25, show_default=True,
              help="Most Levenberg–Marquardt iterations per calibration (it stops when converged).")
@click.option("--tracking", type=click.Choice(["refined", "kinematic"]), default="refined", show_default=True,
              help="For a run: the measured motion. 'refined': the run's tracked motion corrected frame by frame to "
                   "that frame's images (one rigid correction per motion pattern; kept in RUN/tracks.npz, about ten "
                   "CPU-seconds a frame); 'kinematic': the run's velocity field as fitted, which smooths impacts.")
@click.option("--lens", type=click.Choice(["auto", "rigid", "affine", "bent"]), default="auto", show_default=True,
              help="For refined tracks of a run: what they move each motion pattern by, and so what the simulation "
                   "is compared through. 'rigid': a rotation and a shift; 'affine': also a stretch (a body squashed "
                   "for good, as by plastic flow); 'bent': also a second-order bend of each body (a foot spread on "
                   "the ground wider than the top); 'auto': rigid and affine are refined (RUN/tracks.npz, "
                   "RUN/tracks-affine.npz), and the stretching tracks are taken only where they match held-out "
                   "cameras better once the bodies have come to their final shape: over the last quarter of the "
                   "observed frames, by a median 0.25 dB or more and on three quarters of them, as for a body "
                   "deformed for good; then, by the same rule, bent tracks (RUN/tracks-bent.npz) over "
                   "those.")  # fmt: skip
@click.option("--split/--no-split", default=True, show_default=True,
              help="For refined tracks of a run: also refine them from each half of the training cameras over the "
                   "fit window (RUN/tracks-half0.npz, -half1; 1.5x one refinement's time) and credit the "
                   "measurement with 1.75x the error their disagreement shows, where that exceeds a quarter pixel "
                   "at the bodies. The halves share most of what the tracks miss: on the landings of the video "
                   "table the tracks erred 1.75-1.97x what the halves' disagreement alone says (in flight "
                   "0.9x, where the quarter pixel is more).")  # fmt: skip
@click.option("--stretch/--no-stretch", default=True, show_default=True,
              help="For refined tracks of a run, where --lens auto keeps the rigid ones: at every frame where the "
                   "stretching tracks stray from them by more than the noise (the bodies deform, as at an impact, "
                   "and a rigid pose fitted to their images is off by about as much), take the stretching tracks "
                   "and compare the simulation there through the affine lens. On by default since the video table's "
                   "landings were judged with it (README); --no-stretch keeps the rigid tracks throughout.")
@click.option("--weigh/--no-weigh", default=False, show_default=True,
              help="Through a run's rigid lens: weigh every residual by σ/√(σ² + e²), e what the rigid tracks may "
                   "err by at that frame and body (where they cannot follow a deforming body, as at an impact), in "
                   "every calibration and in the gate; e as --weigh-by says. Without a lens, or where e stays "
                   "below half the noise, nothing is weighted. Off by default until the video table's landings "
                   "have been judged with it (README).")
@click.option("--weigh-by", type=click.Choice(["tracks", "base"]), default="tracks", show_default=True,
              help="With --weigh, e is 'tracks': how far the run's stretching tracks stray from its rigid ones, "
                   "beyond their usual difference (from the images alone, the same for every model; with --lens "
                   "auto, where rigid tracks are chosen), else the base fit's departure from rigid motion; 'base': "
                   "the base fit's departure always (a stiff base, calibrated without the missing effect, barely "
                   "deforms and weighs little).")  # fmt: skip
@click.option("--joint/--no-joint", default=True, show_default=True,
              help="Where no candidate passes alone but one explains part of the discrepancy (every check but the "
                   "floor's), screen the others from its refit and refit them jointly with it: two effects missing "
                   "at once, named together where the pair passes against the base and the partner against the "
                   "lead alone. A pair counts as two of --max-effects.")
@click.option("--profile/--no-profile", default=True, show_default=True,
              help="Widen each named parameter's 95% interval to its profile likelihood: refits of every other "
                   "parameter with it held, on either side, out to where the fit window's error rises by the "
                   "chi-square threshold (over the gate's effective sample size). A few refits per parameter "
                   "and side; along a valley of compensating parameters it is the widest source.")
@click.option("--workers", type=click.IntRange(0, 256), default=0,
              help="Processes the independent rollouts of every calibration run in (a Jacobian's columns, a scan's "
                   "grid points, a step's damping trials), each on a CPU of its own; the results do not depend on "
                   "it. 0: one per CPU this process may use; 1: all here.  [default: 0]")  # fmt: skip
@precision_option
@click.option("--resume", is_flag=True,
              help="Continue the discovery run in --out (stopped, or to redo its outputs) from the calibrations it "
                   "finished (progress.json) and the one it was in (calibrating.json); the options must be the "
                   "same.")  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print report.json to stdout.")
def discover(source, out, spec, learn, candidates, max_effects, res, starts, iterations, tracking, lens, split, stretch,
             weigh, weigh_by, joint, profile, workers, precision, resume, as_json):  # fmt: skip
    """Find where simulation and measurement disagree, name the missing physical effect, add it, show the gap shrink.

    SOURCE is a fitted run folder (`causalgs fit`: the measurement is the tracked motion of its particles over the
    observed window, refined frame by frame to the images (--tracking), bodies from its motion segmentation, the
    last quarter held out; the base model is the run's physics) or an observation file (.npz: measured
    trajectories of material points and how many leading frames may be fitted; the rest are held out and only
    scored). The model (--effects) is calibrated on the fit window from several stiffnesses (and, past a
    contact, from a coarse scan), its throw started from the whole free flight; the disagreement is mapped by
    frame, body and contact state; every candidate of the catalogue is screened with one sensitivity rollout; the
    best (with those the catalogue names as confusable with them) are refitted jointly with the base through the
    differentiable MPM, and sticky ground (which replaces the sliding contact) wherever it applies, from a scan of
    its own (through a run's rigid lens, --weigh weighs residuals down where the bodies deform); a gate
    accepts one only if the held-out error drops, BIC (with an effective sample size)
    improves, its parameters are significant (block bootstrap) and inside their ranges, and the refit reaches the
    noise floor on the fit window (with what the lens cannot show of its own motion: a rigid track errs where a
    body deforms) and misses the held-out frames by at most 3x what a correct model would (its own
    window error, at most the floor, with the window's noise, the bodies' extent and the rigid tracks' error where
    the bodies deform carried forward). Among
    passers, the held-out frames choose first and BIC among those they do not tell apart. Where nothing passes
    alone but one candidate explains part of the discrepancy, the others are refitted jointly with it (--joint),
    and a pair that passes is named as two effects.

    \b
    Verdicts: the named effect(s) with their law and 95% interval (the residuals' block bootstrap, the rest shape's
    error and the bodies' extent, for a run the tracks' own smooth error at the noise credited to them, refit
    starts the data cannot tell apart and the profile likelihood, --profile); "ambiguous" (the data does not
    separate two candidates); "no missing effect"; "unexplained discrepancy" (the model stays well above the
    noise floor, a free force would help, but no named effect passes).

    Writes --out/report.json, report.md, error.png (error per frame before and after), residuals.png (held-out
    residual heat on the particles), paths.png, trajectories.npz (the measurement and both simulations, every
    point at every frame) and discover.json (the options); for a run also images.png (held-out
    cameras at held-out frames, rendered before and after) and, when an effect is found, config.toml (the run's
    config with it added: `causalgs fit DATA --config DIR/config.toml` refits the scene). Every calibration is
    saved as it finishes (progress.json), and the one under way keeps its state as it goes (calibrating.json):
    a stopped run goes on with --resume, redoing none of them and losing at most an iteration of that one.
    """
    from causalgs import _ti
    from causalgs.discover.candidates import select
    from causalgs.discover.run import run_discovery
    from causalgs.discover.search import DiscoverConfig

    cands = _names(candidates, "--candidates")
    if cands is not None:
        select(cands)  # unknown names: one line, before any work
    if 0 < res < 8:
        raise CausalGSError(f"--res {res}: give 0 (a run's own grid) or at least 8 cells")
    cfg = DiscoverConfig(res=res, starts=_starts(starts), iterations=iterations, max_effects=max_effects,
                         weigh=weigh, weigh_by=weigh_by, joint=joint, profile=profile,
                         workers=workers or _cpus())  # fmt: skip
    _ti.init("cpu", precision, quiet=True)
    from causalgs.progress import progress_bar

    with progress_bar(not as_json) as bar:
        task = None

        def refining(done: int, total: int) -> None:
            nonlocal task
            if task is None:
                task = bar.add_task("refining the tracked motion", total=total)
            bar.update(task, completed=done)

        report = run_discovery(source, out, spec=spec, learn=_names(learn, "--learn"), candidates=cands,
                               config=cfg, log=None if as_json else _console_log(), resume=resume,
                               refine=tracking == "refined", lens=lens, split=split, stretch=stretch,
                               progress=refining)  # fmt: skip
    if as_json:
        from causalgs.discover.report import finite

        click.echo(json.dumps(finite(report), indent=2))
        return
    click.echo(f"verdict: {report['verdict']}")
    for d in report["discovered"]:
        click.echo(f"  {d['law']}")
    for a in report["ambiguous"]:
        click.echo(f"  ambiguous: {a['law']}")
    eb, ea = report["error_before"]["future_rms_m"], report["error_after"]["future_rms_m"]
    click.echo(f"held-out RMS {1000 * eb:.2f} mm -> {1000 * ea:.2f} mm")
    click.echo(f"Wrote {out / 'report.md'}")


@click.command(name="discover-table")
@out_option()
@click.option("--seeds", type=click.IntRange(1, 100), default=1, show_default=True, help="Seeds per case.")
@click.option("--first-seed", type=click.IntRange(0, 10_000), default=0, show_default=True,
              help="The first seed (seeds FIRST .. FIRST+SEEDS-1), to spread one table over several runs.")
@click.option("--only", default=None,
              help="Cases to run, comma-separated: case names (e.g. 'linear_drag') or kinds (hidden, control, "
                   "outside, pair).  [default: all]")  # fmt: skip
@click.option("--control-seeds", type=click.IntRange(1, 100), default=None,
              help="Seeds per negative control (5 controls × 4 seeds = the 20 the goal counts).  [default: --seeds]")
@click.option("--res", type=click.IntRange(8, 64), default=None,
              help="Grid of the model (trajectory level: of the simulated measurement too; video: cells over each "
                   "run's box).  [default: trajectory 20; video: the truth's own grid, its box and cells]")
@click.option("--run-grid", is_flag=True,
              help="Video level: discover on each run's own grid (as a user without a truth would) instead of the "
                   "truth's. The landing's contact is not converged in the grid: a grid 10% off moves its held-out "
                   "prediction by 2-3 cm.")
@click.option("--jobs", type=click.IntRange(1, 64), default=1, show_default=True,
              help="Runs at once, each in its own process pinned to its own share of the CPUs "
                   "($CAUSALGS_TI_CPUS, else all this process may use).")
@click.option("--workers", type=click.IntRange(0, 256), default=0,
              help="Rollout workers of each run's discovery, as `causalgs discover --workers`. 0: the CPUs this "
                   "process may use over --jobs.  [default: 0]")
@click.option("--rigid-tracks", is_flag=True,
              help="Trajectory level: observe each body through its best rigid motion, as tracks from video do, and "
                   "discover through that lens: what rigid tracks hide (a wobble, a squash) without the errors of "
                   "tracking images.")
@click.option("--lens", type=click.Choice(["auto", "rigid", "affine", "bent"]), default="auto", show_default=True,
              help="Video level: the refined tracks' lens, as `causalgs discover --lens` (auto: the stretching or "
                   "bent tracks where held-out cameras ask for them).")
@click.option("--stretch/--no-stretch", default=None,
              help="Video level: discover as `causalgs discover --stretch` (the stretching tracks and the affine "
                   "lens at the frames where the bodies deform, where the rigid tracks are kept); on unless "
                   "--no-stretch.")
@click.option("--weigh", is_flag=True,
              help="Video level: discover as `causalgs discover --weigh` (residuals weighed down where the rigid "
                   "tracks and the stretching ones refined from the same images disagree, as at an impact).")
@click.option("--retry-failed", is_flag=True,
              help="Run again the rows table.json holds as failed (each resumes from its last finished stage), "
                   "once what made them fail is mended; without it a failed row is an outcome and is kept.")
@click.option("--level", type=click.Choice(["trajectory", "video"]), default="trajectory", show_default=True,
              help="trajectory: simulated particle tracks with noise (minutes a case); video: a rendered video, a "
                   "fit and discovery on the run, end to end (about 20 minutes a flight case on 2 cores).")
@click.option("--rescore", is_flag=True,
              help="Trajectory level: run nothing; score every row of --out/table.json again from its saved "
                   "report.json (after a change of the scoring) and rewrite the table.")
@click.option("--merge", "merge", multiple=True, type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Video level: run nothing; collect the rows of these tables (repeat the option; one table run in "
                   "pieces with --only and --first-seed) into --out, each row taken only where its video was "
                   "rendered as the case is defined now, a later table's row replacing an earlier one.")
def discover_table(out, seeds, first_seed, only, control_seeds, res, run_grid, jobs, workers, rigid_tracks, lens,
                   stretch, weigh, retry_failed, level, rescore, merge):
    """Reproduce the hidden-effect table: for every effect of the catalogue, a tossed block simulated with it and
    a model without it; negative controls; an effect outside the catalogue.

    \b
    --level trajectory  the measurement is the simulator's own particle tracks with noise, and the controls add
                        nuisances (a noisy rest shape, a throw or a stiffness started off the truth): it tests the
                        discovery logic on data whose answer is known
    --level video       each case is `causalgs synth toss --fps 120` with the effect, `causalgs fit` (the quick
                        preset; the model's physics lacks the effect) and `causalgs discover` on the run: forces
                        and drags in a flight of 48 frames, damping, friction, sticky ground and plasticity in a
                        landing of 144; every stage resumes

    Each run goes to --out/CASE-sSEED; --out/table.md and table.json collect the rows and the goals reached. Rows
    already in table.json are kept and not run again, so an interrupted table resumes (--retry-failed: failed
    rows too run again).
    """
    from causalgs import _ti
    from causalgs.discover.search import DiscoverConfig

    if rescore:
        from causalgs.discover.table import rescore as rescore_table
        from causalgs.discover.table import summary

        rows = rescore_table(out)
        click.echo(json.dumps(summary(rows)))
        click.echo(f"Wrote {out / 'table.md'} ({len(rows)} rows scored again)")
        return
    if merge:
        if level != "video":
            raise CausalGSError("--merge collects video tables: add --level video")
        from causalgs.discover.table import summary
        from causalgs.discover.video_table import merge as merge_tables

        rows = merge_tables(out, merge, log=_console_log())
        click.echo(json.dumps(summary(rows)))
        click.echo(f"Wrote {out / 'table.md'} ({len(rows)} rows)")
        return
    if level == "video" and rigid_tracks:
        raise CausalGSError("--rigid-tracks is for --level trajectory: video tracks have a lens of their own (--lens)")
    if level == "trajectory" and lens != "auto":
        raise CausalGSError("--lens is for --level video: trajectory tracks are the simulator's own (--rigid-tracks)")
    if level == "trajectory" and stretch:
        raise CausalGSError("--stretch is for --level video: it stretches the tracks of a run where its bodies deform")
    if level == "trajectory" and weigh:
        raise CausalGSError("--weigh is for --level video: it weighs the residuals of tracks from video")
    if level == "video":
        from causalgs.discover.video_table import CASES, VideoTableConfig, run_video_table
    else:
        from causalgs.discover.table import CASES, TableConfig, run_table
    from causalgs.discover.table import summary

    workers = workers or _cpus(jobs)
    names = _names(only, "--only") or ()
    known = {c.name for c in CASES} | {c.kind for c in CASES}
    bad = [n for n in names if n not in known]
    if bad:
        raise CausalGSError(f"--only: unknown case(s) {', '.join(bad)}; cases: {', '.join(c.name for c in CASES)}")
    if jobs == 1:
        _ti.init("cpu", "float32", quiet=True)
    if level == "video":
        vcfg = VideoTableConfig(seeds=seeds, first_seed=first_seed, only=names, control_seeds=control_seeds,
                                jobs=jobs, discover=DiscoverConfig(res=res or 0, weigh=weigh, workers=workers),
                                truth_grid=not (run_grid or res), lens=lens, stretch=stretch is not False)  # fmt: skip
        rows = run_video_table(out, vcfg, log=_console_log(), retry_failed=retry_failed)
    else:
        res = res or 20
        cfg = TableConfig(seeds=seeds, first_seed=first_seed, res=res, only=names, control_seeds=control_seeds,
                          jobs=jobs, rigid=rigid_tracks, discover=DiscoverConfig(res=res, workers=workers))  # fmt: skip
        rows = run_table(out, cfg, log=_console_log(), retry_failed=retry_failed)
    s = summary(rows)
    click.echo(json.dumps(s))
    click.echo(f"Wrote {out / 'table.md'}")
