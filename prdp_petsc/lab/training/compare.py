"""PRDP against constant full fidelity: ``compare`` runs the schedules and routes.

PRDP, constant K_full (from the scene's tolerance) and a few constant coarse Ks train
for the same epochs on the scene's solver and on each route
(`prdp_petsc.lab.training.routes`); `prdp_petsc.lab.training.summary.summarize` then
reports the savings at equal accuracy and each run's time to full-fidelity accuracy,
and `prdp_petsc.lab.training.plots` draws error against cost.
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
    "REDUCED_SCHEDULES",
    "SCENE_SOLVER",
    "TWIN_SEED_OFFSET",
    "compare",
    "finished_run",
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
        Preset name (with ``--set`` changes); epochs (default: the scene's); seed.
    out : str or Path
        Output folder: ``summary.json``, one folder per run, the plots.
    progress, plots : bool
        Show progress bars; write the plots.
    threads : int
        torch threads for every run; recorded in the summary.
    routes : sequence of str, or str, optional
        Other solvers (`prdp_petsc.lab.training.routes.route_settings`): the
        `schedules` and full fidelity at the route's own K_full run again with them,
        as ``"prdp@cg/icc"`` and ``"fixed:K@cg/icc"``.  None: the scene's preset key
        ``routes`` (`scene_routes`); ``()`` none; ``"auto"``: the one a pilot picks
        (`pilot_routes`).  A route that does not fit (a `StructureError` or a
        `SolverError` of its K_full probe) is skipped and reported.
    schedules : sequence of str
        Reduced-fidelity schedules from `REDUCED_SCHEDULES`: ``"prdp"`` (the scene's
        settings), ``"auto"`` (`PRDP.for_problem`) and ``"rtol"`` (PRDP moving
        PETSc's rtol under a generous cap).
    parallel : {None, "domain", "batch"}
        How every run uses the MPI ranks (`prdp_petsc.lab.training.parallel`).
    twin : bool
        Also run full fidelity with torch seeded ``seed + TWIN_SEED_OFFSET``.
    resume : bool
        Read the runs in `out` that finished the requested epochs with the same
        settings, continue those with a checkpoint, run the others afresh.
    checkpoint_every : int
        Epochs between a run's checkpoints (see `run`).

    Returns
    -------
    dict
        `summarize`'s summary plus ``schedules``, ``parallel``, ``provenance``, with
        ``routes="auto"`` the ``pilot`` (also in ``out/pilot.json``), with `resume`
        ``reused`` (the runs read, not trained), with `plots` ``plots``.

    Raises
    ------
    KeyboardInterrupt
        Re-raised after ``summary.json`` records the runs so far.
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

        def summary_now() -> dict:
            summary = summarize(scene_name, k_fulls, logs, threads=threads, skipped=skipped)
            if pilot is not None:
                summary["pilot"] = pilot
            summary.update(schedules=list(schedules), parallel=ranks.describe(), provenance=origin)
            if resume:
                summary["reused"] = reused
            return summary

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
                        k_fulls[route], why = _route_k_full(module, preset, seed)
                        if why:
                            logger.warning("route %s skipped: %s", route, why)
                            skipped[route] = why
                            del k_fulls[route]
                            continue
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
                    done = finished_run(folder, settings, prdp, target) if resume else None
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
                write(out / "summary.json", summary_now())
                raise
    summary = summary_now()
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
    """Time `epochs` full-fidelity epochs of the scene's own solver and of each route
    (at its own K_full) and pick the fastest, before anything else trains.

    Each candidate trains ``epochs + 1`` epochs from the same start; the first pays
    first-use costs and is not timed.  A candidate that does not fit (its K_full probe
    raises) or whose run stops is skipped with the reason.  `prefixes` are the scene's
    solver prefixes, `k_full` the scene solver's K_full.

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
            k, why = (k_full, None) if own else _route_k_full(module, preset, seed)
            if why:
                candidates[route] = {"skipped": why}
                continue
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


def _route_k_full(module, preset: str, seed: int) -> tuple[int | None, str | None]:
    """K_full of the scene under the route options now set, or None and why the route
    does not fit (CG on a non-symmetric operator, ILU on a zero diagonal block)."""
    probe = build_scene(module, preset, seed)
    try:
        return find_k_full(probe), None
    except (StructureError, SolverError) as err:
        return None, " ".join(str(err).split())
    finally:
        release(probe)


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


def finished_run(folder: Path, settings: dict, prdp: dict, epochs: int) -> dict | None:
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
