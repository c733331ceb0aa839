"""PRDP against constant full fidelity: ``compare`` runs the schedules and routes.

Runs PRDP, the constant K_full baseline (K_full found by the harness from the
scene's tolerance) and a few constant coarse Ks for the same number of epochs,
then reports savings in inner iterations (forward + adjoint) and wall time next
to the validation errors, and plots error against cost.  Savings count only at
equal accuracy: the summary flags a PRDP validation error more than
`ACCURACY_RATIO` times K_full's.

Time to accuracy: every run's ``time_to_full_accuracy`` is the wall time from
which on its validation error stays within 5 % of full fidelity's final one
(`prdp_petsc.lab.training.routes.time_to_accuracy`), and ``speedup_vs_best_full``
divides the least such time of a full-fidelity run (``fixed:K_full`` on the
scene's solver or on any route) by the least of a reduced one (PRDP, the ``rtol``
schedule or a coarse constant K, on any route): above 1, training with a reduced
solver reached full-fidelity accuracy sooner than the best full-fidelity route.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
from pathlib import Path

from prdp_petsc import SolverError
from prdp_petsc.errors import StructureError

from ..parsing import check_epochs
from ..provenance import provenance
from .building import build_scene, release
from .checkpoint import CHECKPOINT
from .harness import RunSettings, run
from .parallel import Parallel
from .probe import find_k_full
from .records import RESULTS, write_json
from .routes import AUTO, parse_routes, route_options, route_settings
from .scene import load_scene, preset_config
from .summary import TWIN, summarize
from .threads import torch_threads

logger = logging.getLogger(__name__)

__all__ = [
    "AUTO",
    "REDUCED_SCHEDULES",
    "SCENE_SOLVER",
    "TWIN_SEED_OFFSET",
    "compare",
    "pilot_routes",
    "scene_routes",
]

#: The ``twin`` run seeds torch (initial weights, batch order) with ``seed + TWIN_SEED_OFFSET``.
TWIN_SEED_OFFSET = 1000

#: The pilot's name for the scene's own solver (no route)
SCENE_SOLVER = "scene solver"
#: ``out/pilot.json``: the pilot's result, kept for ``resume``
PILOT = "pilot.json"

#: The reduced-fidelity schedules `compare` can run next to full fidelity (``schedules``)
REDUCED_SCHEDULES = ("prdp", "auto", "rtol")


def scene_routes(module, preset: str) -> tuple[str, ...]:
    """The routes a scene declares for `preset`: its preset key ``routes``
    (`prdp_petsc.lab.training.routes.parse_routes`; ``--set routes=...`` changes it),
    none where its presets have no such key."""
    config = preset_config(module, preset)
    named = getattr(module, "ROUTES", None)
    return parse_routes(config["routes"], named) if "routes" in config else ()


def compare(
    scene_file,
    *,
    preset: str = "quick",
    epochs: int | None = None,
    seed: int = 0,
    out="results",
    progress: bool = True,
    plots: bool = True,
    threads: int = 1,
    routes: tuple[str, ...] | list[str] | None = None,
    schedules: tuple[str, ...] | list[str] = ("prdp",),
    parallel: str | None = None,
    twin: bool = False,
    resume: bool = False,
    checkpoint_every: int = 1,
) -> dict:
    """PRDP against constant K_full and constant coarse Ks; write ``summary.json``.

    Parameters
    ----------
    scene_file : str or Path
        Scene file (see `prdp_petsc.lab.training.scene`).
    preset, epochs, seed
        Preset name; number of epochs (>= 1; default: the scene's); random seed.
    out : str or Path
        Output folder: ``summary.json``, one ``<schedule>/results.json`` per run, plots.
    progress, plots : bool
        Show progress bars; write the plots.
    threads : int
        torch threads for every run (restored afterwards); recorded in the summary.
    routes : sequence of str, or str, optional
        Other solvers to try, ``"ksp_type/pc_type"`` (e.g. ``"cg/icc"``; a string
        ``"cg/icc,cg/gamg"`` is split as `parse_routes` does), with sub-options as
        ``":option=value"`` or by a name of the scene's ``ROUTES``
        (`prdp_petsc.lab.training.routes.route_settings`): the `schedules` and
        full fidelity (the route's own K_full) run again with those options on every
        solver prefix of the scene (`prdp_petsc.lab.training.routes`), as
        ``"prdp@cg/icc"``, ``"rtol@cg/icc"`` and ``"fixed:K@cg/icc"``; ``fastest`` in
        the summary says which run reached the full-fidelity validation error in the
        least wall time.  None (the default): the routes the scene declares in its
        preset key ``routes`` (`scene_routes`); ``()`` or ``""`` runs none; ``"auto"``
        lets a pilot pick one of those (`pilot_routes`: a timed full-fidelity epoch of
        the scene's solver and of each route, the fastest one's route runs).  A route
        that does not fit the scene (a `StructureError`: CG on a non-symmetric
        operator; a `SolverError` of its K_full probe: ILU on a zero diagonal
        block) is skipped and reported.
    schedules : sequence of str
        The reduced-fidelity schedules to run on the scene's solver and on every
        route, from `REDUCED_SCHEDULES`: ``"prdp"`` (the default, the scene's PRDP
        settings), ``"auto"`` (`PRDP.for_problem` from the route's K_full, with a
        gradient check; the summary's ``auto``) and ``"rtol"``, PRDP moving PETSc's
        rtol under a generous cap instead of K (`prdp_petsc.lab.training.harness.run`).
    parallel : {None, "domain", "batch"}
        Every run uses the MPI ranks this way (`prdp_petsc.lab.training.parallel`);
        rank 0 writes the files.
    twin : bool
        Also run full fidelity with torch seeded ``seed + TWIN_SEED_OFFSET``.
    resume : bool
        Continue an earlier comparison in `out`: a run whose ``results.json`` says
        it finished the requested epochs is read, not trained again; one with a
        ``checkpoint.pt`` continues from it (`run`'s ``resume``; refused if its
        recorded preset or seed differ); any other runs from the start.
    checkpoint_every : int
        Every run saves its ``checkpoint.pt`` after this many epochs (see `run`).

    Returns
    -------
    dict
        ``scene``, ``k_full``, ``threads``, ``runs`` (per schedule:
        ``final_val_error``, ``wall_time``, ``fwd_iterations``, ``adj_iterations``,
        ``k_final``, ``stopped``, ``time_to_full_accuracy``; for the ``rtol``
        schedule ``rtol``: first and last rtol, level, cap, forward iterations per
        solve in the first and last epoch; with `twin`, also ``twin:K``),
        ``speedup_vs_best_full`` and ``speedup`` (`speedup_vs_best_full`),
        ``noise_ratio`` (with `twin`: its final validation error over K_full's),
        ``savings`` of PRDP against K_full
        (``iterations``, ``wall_time``, ``pr``, ``ic``, in inner iterations forward +
        adjoint) with ``val_error_ratio`` and ``equal_accuracy`` (plus
        ``accuracy_warning`` when it is False), or ``savings_unavailable`` saying why;
        ``provenance`` (`prdp_petsc.lab.provenance.provenance`); with
        ``routes="auto"``, ``pilot`` (`pilot_routes`, also in ``out/pilot.json``
        from before the first run, so that `resume` keeps the pick); with `resume`,
        ``reused``: the runs read from an earlier comparison; ``schedules``.

    Raises
    ------
    KeyboardInterrupt
        Re-raised after ``summary.json`` records the runs so far, the interrupted one
        with ``stopped: {"reason": "interrupted"}``.
    """
    epochs = check_epochs(epochs)
    schedules = tuple(dict.fromkeys(schedules))
    if not schedules or any(s not in REDUCED_SCHEDULES for s in schedules):
        raise ValueError(
            f"schedules must be some of {', '.join(REDUCED_SCHEDULES)}, got {list(schedules)}"
        )
    module = load_scene(scene_file)
    named = getattr(module, "ROUTES", None)  # the scene's routes by name
    auto = routes in (AUTO, (AUTO,), [AUTO])
    if auto:
        routes = None  # the pilot picks among the scene's routes
    if routes is None:
        routes = scene_routes(module, preset)
    elif isinstance(routes, str):  # "cg/icc,cg/gamg", as the preset key and the CLI write it
        routes = parse_routes(routes, named)
    routes = tuple(dict.fromkeys(routes))
    for route in routes:
        route_settings(route, named)
    ranks = Parallel(parallel)
    out = Path(out)
    if ranks.root:
        out.mkdir(parents=True, exist_ok=True)
    scene_name = Path(scene_file).stem
    # every run's settings but its schedule, epochs and output (a run without output is quiet)
    quiet = RunSettings(preset=preset, seed=seed, progress=False, threads=threads,
                        parallel=parallel)  # fmt: skip
    write = write_json if ranks.root else lambda path, data: None
    with torch_threads(threads), ranks.solvers():
        scene = build_scene(module, preset, seed)
        k_full = find_k_full(scene)
        release(scene)  # its settings are read below, its solvers are not needed
        target = epochs or scene.epochs
        origin = provenance(threads, ranks.size)
        warmed = False
        coarse = scene.compare_ks
        if coarse is None:  # an empty list: no constant coarse K
            coarse = sorted({1, max(1, k_full // 4), max(1, k_full // 2)})
        own = [*schedules, f"fixed:{k_full}"] + [f"fixed:{k}" for k in coarse if k < k_full]
        prefixes = [s.prefix for s in scene.solvers]
        logs = {}
        k_fulls = {"": k_full}
        skipped = {}  # route -> why it does not fit the scene's solvers
        reused = []  # runs a resumed comparison read instead of training
        pilot = None
        if auto:
            kept = out / PILOT
            if resume and ranks.root and kept.is_file():  # the pick being resumed
                pilot = json.loads(kept.read_text())
            pilot = ranks.agree(pilot)
            if pilot is None:
                pilot = pilot_routes(scene_file, routes, module=module, preset=preset,
                                     seed=seed, prefixes=prefixes, k_full=k_full,
                                     threads=threads, parallel=parallel)  # fmt: skip
                warmed = warmed or bool(routes)  # the pilot's runs warmed the process up
                pilot = ranks.agree(pilot)  # each rank timed its own epochs: rank 0 decides
                write(kept, pilot)  # before anything trains: an interrupted run keeps it
            picked = pilot["picked"]
            routes = () if picked in (None, SCENE_SOLVER) else (picked,)
            k_fulls.update({r: pilot["candidates"][r]["k_full"] for r in routes})
        runs = [(schedule, None) for schedule in own] + [
            (schedule, route) for route in routes for schedule in (*schedules, "full")
        ]
        if twin:  # full fidelity again, torch seeded differently: the run-to-run noise
            runs.append((TWIN, None))
        for schedule, route in runs:
            if route in skipped:
                continue
            context = route_options(prefixes, route, named) if route else contextlib.nullcontext()
            name = folder = None
            try:
                with context:
                    if route and route not in k_fulls:  # the route's own K_full
                        probe = build_scene(module, preset, seed)
                        try:
                            k_fulls[route] = find_k_full(probe)
                        except (StructureError, SolverError) as err:  # it does not fit
                            # CG on a non-symmetric operator; ILU on a zero diagonal block
                            logger.warning("route %s skipped: %s", route, err)
                            skipped[route] = " ".join(str(err).split())
                            continue
                        finally:
                            release(probe)
                    torch_seed = None  # the run's default: `seed`
                    if schedule == TWIN:
                        schedule, name = f"fixed:{k_full}", f"twin:{k_full}"
                        torch_seed = seed + TWIN_SEED_OFFSET
                    else:
                        schedule = f"fixed:{k_fulls[route]}" if schedule == "full" else schedule
                        name = schedule if route is None else f"{schedule}@{route}"
                    folder = out / _folder_name(name)
                    settings = {"schedule": schedule, "preset": preset, "seed": seed,
                                "torch_seed": torch_seed}  # fmt: skip
                    prdp = (
                        _prdp_for(scene.prdp, k_full, k_fulls.get(route, k_full))
                        if schedule == "prdp"
                        else {"k_full": k_fulls.get(route, k_full)}
                        if schedule == "auto"
                        else {}  # rtol counts levels; fixed has no controller
                    )
                    done = _finished_run(folder, settings, prdp, target) if resume else None
                    if done is not None:
                        logger.info("%s: finished in %s, not trained again", name, folder)
                        logs[name] = done
                        reused.append(name)
                        continue
                    if not warmed:  # imports, PETSc and torch first-call costs: a fair first run
                        run(scene_file, "fixed:1", quiet.replace(epochs=1), module=module)
                        warmed = True
                    again = resume and _resumable(folder, target)
                    logs[name] = run(
                        scene_file,
                        schedule,
                        quiet.replace(
                            epochs=target, torch_seed=torch_seed, out=folder, progress=progress,
                            prdp=prdp or None, checkpoint_every=checkpoint_every,
                        ),
                        module=module,
                        resume=folder if again else None,
                    )  # fmt: skip
            except KeyboardInterrupt:
                # the interrupted run has written what it measured: summarise it too
                results = folder / RESULTS if folder else None
                if results is not None and results.is_file():
                    logs[name] = json.loads(results.read_text())
                interrupted = summarize(scene_name, k_fulls, logs, threads=threads, skipped=skipped)
                interrupted["provenance"] = origin
                if pilot is not None:
                    interrupted["pilot"] = pilot
                write(out / "summary.json", interrupted)
                raise
    summary = summarize(scene_name, k_fulls, logs, threads=threads, skipped=skipped)
    if pilot is not None:
        summary["pilot"] = pilot
    summary["schedules"] = list(schedules)
    summary["parallel"] = ranks.describe()
    summary["provenance"] = origin
    if resume:
        summary["reused"] = reused
    write(out / "summary.json", summary)
    if plots and ranks.root:
        from .plots import plot_compare

        drawn = {name: log for name, log in logs.items() if not name.startswith("twin:")}
        summary["plots"] = plot_compare(drawn, k_fulls, out)
        write_json(out / "summary.json", summary)
    return summary


def pilot_routes(
    scene_file,
    routes,
    *,
    module,
    preset: str,
    seed: int,
    prefixes,
    k_full: int,
    threads: int = 1,
    parallel: str | None = None,
    epochs: int = 1,
) -> dict:
    """Time `epochs` full-fidelity training epochs of the scene's own solver and of each
    route (at its own K_full) and pick the fastest, before anything else trains.

    Each candidate trains ``epochs + 1`` epochs; the first pays its first-use costs
    (imports, the PC type's first set-up) and is not timed.  A candidate whose run
    stops (a diverged solve, a non-finite loss) is skipped with the reason, as is one
    that does not fit; with no `routes` there is nothing to choose (``picked`` None).

    The operator is the scene's own, the network and data those of `seed`; each
    candidate trains from the same start.  `prefixes` are the scene's solver prefixes
    (the route's options go under each), `k_full` the scene solver's K_full.  A route
    that does not fit (its K_full probe raises `StructureError` or `SolverError`) is
    skipped, with the reason.  Full fidelity is the pilot's measure because it is the
    same accuracy for every candidate; a route whose capped solves are cheap but
    whose full ones are dear could win under PRDP yet lose the pilot (the comparison
    then shows it only if the route is given by name).

    Returns
    -------
    dict
        ``epochs``; ``candidates``: ``{SCENE_SOLVER or route: {"k_full": K,
        "epoch_seconds": mean wall time of a timed epoch}}`` or ``{"skipped": why}``;
        ``picked``: the candidate with the least ``epoch_seconds`` (None without one).
    """
    if not routes:  # nothing to choose between
        return {"epochs": 0, "candidates": {}, "picked": None}
    candidates = {}
    named = getattr(module, "ROUTES", None)
    for route in (SCENE_SOLVER, *routes):
        own = route == SCENE_SOLVER
        context = contextlib.nullcontext() if own else route_options(prefixes, route, named)
        with context:
            k = k_full
            if not own:
                probe = build_scene(module, preset, seed)
                try:
                    k = find_k_full(probe)
                except (StructureError, SolverError) as err:
                    candidates[route] = {"skipped": " ".join(str(err).split())}
                    continue
                finally:
                    release(probe)
            quiet = RunSettings(preset=preset, epochs=epochs + 1, seed=seed, progress=False,
                                threads=threads, parallel=parallel)  # fmt: skip
            log = run(scene_file, f"fixed:{k}", quiet, module=module)
        timed = log["epochs"][1:]  # the first epoch pays the candidate's first-use costs
        stop = log.get("stopped")
        if stop or len(timed) < epochs:  # a candidate that cannot train is no candidate
            why = stop["message"] if stop and stop.get("message") else str(stop)
            candidates[route] = {"skipped": f"its pilot run stopped: {' '.join(why.split())}"}
            continue
        seconds = sum(e["wall_time"] for e in timed) / len(timed)
        candidates[route] = {"k_full": k, "epoch_seconds": seconds}
        logger.info("pilot: %s at K_full %d, %.3f s per epoch", route, k, seconds)
    timed = {r: c["epoch_seconds"] for r, c in candidates.items() if "epoch_seconds" in c}
    return {
        "epochs": epochs,
        "candidates": candidates,
        "picked": min(timed, key=timed.get) if timed else None,
    }


def _folder_name(name: str) -> str:
    """A run's folder: ``prdp@cg/icc`` → ``prdp_on_cg-icc``, ``fixed:8`` → ``fixed_8``.

    A route with sub-options keeps only its pair and a digest of the whole route
    (``prdp_on_gmres-fieldsplit_3f2a…``): the options would make a name too long for
    a file system, and two routes must not share a folder.
    """
    schedule, at, route = name.partition("@")
    text = schedule.replace(":", "_")
    if at:
        pair, options, _ = route.partition(":")
        if options:
            pair += "_" + hashlib.sha1(route.encode()).hexdigest()[:12]
        text += "_on_" + pair.replace("/", "-")
    return text


def _finished_run(folder: Path, settings: dict, prdp: dict, epochs: int) -> dict | None:
    """The results of a run in `folder` that finished `epochs` epochs with `settings`
    (`run`'s; ``torch_seed`` None is ``seed``) and, for PRDP, `prdp`, else None."""
    if settings["torch_seed"] is None:
        settings = {**settings, "torch_seed": settings["seed"]}
    path = folder / RESULTS
    if not path.is_file():
        return None
    recorded = json.loads(path.read_text())
    if not recorded.get("finished") or recorded.get("requested_epochs") != epochs:
        return None
    if any(recorded.get(key) != value for key, value in settings.items()):
        return None  # `run` refuses to resume it, or it runs afresh without a checkpoint
    own = recorded.get("prdp")
    if own is not None and any(own.get(key) != value for key, value in prdp.items()):
        return None
    return recorded


def _resumable(folder: Path, epochs: int) -> bool:
    """Whether `folder` holds a checkpoint of at most `epochs` epochs to continue."""
    path = folder / RESULTS
    if not (path.is_file() and (folder / CHECKPOINT).is_file()):
        return False
    saved = json.loads(path.read_text()).get("checkpoint") or {}
    return saved.get("epoch", math.inf) <= epochs


def _prdp_for(settings: dict, k_full: int, k_route: int) -> dict:
    """PRDP settings of a run: K capped at the run's K_full (more buys nothing), and
    for another route K₀ and ΔK scaled by ``K_full(route) / K_full(scene)``."""
    scale = k_route / k_full
    out = {"k_max": k_route}
    for key, default in (("k_init", 1), ("k_step", 1)):
        out[key] = min(k_route, max(1, round(settings.get(key, default) * scale)))
    return out
