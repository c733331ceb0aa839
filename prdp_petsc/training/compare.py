"""PRDP against constant full fidelity: ``compare``, its summary and table.

Runs PRDP, the constant K_full baseline (K_full found by the harness from the
scene's tolerance) and a few constant coarse Ks for the same number of epochs,
then reports savings in inner iterations (forward + adjoint) and wall time next
to the validation errors, and plots error against cost.  Savings count only at
equal accuracy: the summary flags a PRDP validation error more than
`ACCURACY_RATIO` times K_full's.

Time to accuracy: every run's ``time_to_full_accuracy`` is the wall time from
which on its validation error stays within 5 % of full fidelity's final one
(`prdp_petsc.training.routes.time_to_accuracy`), and ``speedup_vs_best_full``
divides the least such time of a full-fidelity run (``fixed:K_full`` on the
scene's solver or on any route) by the least of a reduced one (PRDP, the ``rtol``
schedule or a coarse constant K, on any route): above 1, training with a reduced
solver reached full-fidelity accuracy sooner than the best full-fidelity route.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
from pathlib import Path

from ..core.results import SolverError
from ..errors import StructureError
from ..prdp import equal_accuracy_k, savings
from .checkpoint import CHECKPOINT
from .harness import (
    RESULTS,
    build_scene,
    check_epochs,
    find_k_full,
    release,
    run,
    torch_threads,
    write_json,
)
from .parallel import Parallel
from .provenance import provenance
from .routes import (
    REACH_FACTOR,
    accuracy_target,
    fastest,
    parse_route,
    parse_routes,
    route_options,
    time_to_accuracy,
)
from .scene import load_scene, preset_config

logger = logging.getLogger(__name__)

__all__ = [
    "ACCURACY_RATIO",
    "REDUCED_SCHEDULES",
    "compare",
    "format_table",
    "scene_routes",
    "speedup_vs_best_full",
    "stopped_runs",
    "summarize",
]

#: Largest PRDP / K_full ratio of final validation errors that still counts as equal accuracy.
ACCURACY_RATIO = 1.05

#: The ``twin`` run seeds torch (initial weights, batch order) with ``seed + TWIN_SEED_OFFSET``.
TWIN_SEED_OFFSET = 1000
TWIN = "twin"  # compare's schedule name for that run

#: The reduced-fidelity schedules `compare` can run next to full fidelity (``schedules``)
REDUCED_SCHEDULES = ("prdp", "rtol")


def scene_routes(module, preset: str) -> tuple[str, ...]:
    """The routes a scene declares for `preset`: its preset key ``routes``
    (`prdp_petsc.training.routes.parse_routes`; ``--set routes=...`` changes it),
    none where its presets have no such key."""
    config = preset_config(module, preset)
    return parse_routes(config["routes"]) if "routes" in config else ()


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
        Scene file (see `prdp_petsc.training.scene`).
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
        ``"cg/icc,cg/gamg"`` is split as `parse_routes` does): the `schedules` and
        full fidelity (the route's own K_full) run again with those options on every
        solver prefix of the scene (`prdp_petsc.training.routes`), as
        ``"prdp@cg/icc"``, ``"rtol@cg/icc"`` and ``"fixed:K@cg/icc"``; ``fastest`` in
        the summary says which run reached the full-fidelity validation error in the
        least wall time.  None (the default): the routes the scene declares in its
        preset key ``routes`` (`scene_routes`); ``()`` or ``""`` runs none.  A route
        that does not fit the scene (a `StructureError`: CG on a non-symmetric
        operator; a `SolverError` of its K_full probe: ILU on a zero diagonal
        block) is skipped and reported.
    schedules : sequence of str
        The reduced-fidelity schedules to run on the scene's solver and on every
        route, from `REDUCED_SCHEDULES`: ``"prdp"`` (the default) and ``"rtol"``, PRDP
        moving PETSc's rtol under a generous cap instead of K
        (`prdp_petsc.training.harness.run`).
    parallel : {None, "domain", "batch"}
        Every run uses the MPI ranks this way (`prdp_petsc.training.parallel`);
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
        ``provenance`` (`prdp_petsc.training.provenance.provenance`); with `resume`,
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
    if routes is None:
        routes = scene_routes(module, preset)
    elif isinstance(routes, str):  # "cg/icc,cg/gamg", as the preset key and the CLI write it
        routes = parse_routes(routes)
    routes = tuple(dict.fromkeys(routes))
    for route in routes:
        parse_route(route)
    ranks = Parallel(parallel)
    out = Path(out)
    if ranks.root:
        out.mkdir(parents=True, exist_ok=True)
    scene_name = Path(scene_file).stem
    write = write_json if ranks.root else lambda path, data: None
    with torch_threads(threads), ranks.solvers():
        scene = build_scene(module, preset, seed)
        k_full = find_k_full(scene)
        release(scene)  # its settings are read below, its solvers are not needed
        target = epochs or scene.epochs
        origin = provenance(threads, ranks.size)
        warmed = False
        coarse = scene.compare_ks or sorted({1, max(1, k_full // 4), max(1, k_full // 2)})
        own = [*schedules, f"fixed:{k_full}"] + [f"fixed:{k}" for k in coarse if k < k_full]
        prefixes = [s.prefix for s in scene.solvers]
        runs = [(schedule, None) for schedule in own] + [
            (schedule, route) for route in routes for schedule in (*schedules, "full")
        ]
        logs = {}
        k_fulls = {"": k_full}
        skipped = {}  # route -> why it does not fit the scene's solvers
        reused = []  # runs a resumed comparison read instead of training
        if twin:  # full fidelity again, torch seeded differently: the run-to-run noise
            runs.append((TWIN, None))
        for schedule, route in runs:
            if route in skipped:
                continue
            context = route_options(prefixes, route) if route else contextlib.nullcontext()
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
                    folder = out / name.replace(":", "_").replace("@", "_on_").replace("/", "-")
                    settings = {"schedule": schedule, "preset": preset, "seed": seed,
                                "torch_seed": torch_seed}  # fmt: skip
                    prdp = (
                        _prdp_for(scene.prdp, k_full, k_fulls.get(route, k_full))
                        if schedule == "prdp"
                        else {}  # rtol counts levels; fixed has no controller
                    )
                    done = _finished_run(folder, settings, prdp, target) if resume else None
                    if done is not None:
                        logger.info("%s: finished in %s, not trained again", name, folder)
                        logs[name] = done
                        reused.append(name)
                        continue
                    if not warmed:  # imports, PETSc and torch first-call costs: a fair first run
                        run(scene_file, "fixed:1", preset=preset, epochs=1, seed=seed,
                            progress=False, threads=threads, module=module,
                            parallel=parallel)  # fmt: skip
                        warmed = True
                    again = resume and _resumable(folder, target)
                    logs[name] = run(
                        scene_file,
                        **settings,
                        epochs=target,
                        out=folder,
                        progress=progress,
                        threads=threads,
                        module=module,
                        prdp=prdp or None,
                        parallel=parallel,
                        checkpoint_every=checkpoint_every,
                        resume=folder if again else None,
                    )
            except KeyboardInterrupt:
                # the interrupted run has written what it measured: summarise it too
                results = folder / RESULTS if folder else None
                if results is not None and results.is_file():
                    logs[name] = json.loads(results.read_text())
                interrupted = summarize(scene_name, k_fulls, logs, threads=threads, skipped=skipped)
                interrupted["provenance"] = origin
                write(out / "summary.json", interrupted)
                raise
    summary = summarize(scene_name, k_fulls, logs, threads=threads, skipped=skipped)
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


def summarize(
    scene: str,
    k_full: int | dict,
    logs: dict,
    *,
    threads: int | None = None,
    skipped: dict | None = None,
) -> dict:
    """Summary of a comparison: runs, PRDP savings against K_full, error ratio.

    `k_full` is an int, or ``{route: K_full}`` with ``""`` for the scene's own
    solver; routes add ``routes`` (their K_full and PRDP savings) and ``fastest``.
    A run ``twin:K`` (full fidelity again, torch seeded differently) adds
    ``noise_ratio``, its final validation error over K_full's; it is not a
    candidate for ``fastest`` nor for the speedup.  `skipped` maps routes that do
    not fit the scene's solvers (a `StructureError`: CG on a non-symmetric
    operator) to the reason; they appear in ``routes`` as ``{"skipped": reason}``.
    Every run gets ``time_to_full_accuracy``
    (`prdp_petsc.training.routes.time_to_accuracy` against full fidelity's final
    validation error; None if it never reached it, or without full fidelity), and
    the summary ``speedup_vs_best_full`` and ``speedup`` (`speedup_vs_best_full`).
    """
    k_fulls = k_full if isinstance(k_full, dict) else {"": k_full}
    k_full = k_fulls[""]
    full_name = f"fixed:{k_full}"
    twin_name = f"twin:{k_full}"
    runs = {}
    for schedule, log in logs.items():
        t = log["totals"]
        runs[schedule] = {
            "final_val_error": t.get("final_val_error"),
            "best_val_error": t.get("best_val_error"),
            "wall_time": t.get("wall_time"),
            "solver_time": t.get("solver_time"),
            "fwd_iterations": t.get("fwd_iterations"),
            "adj_iterations": t.get("adj_iterations"),
            "k_final": t.get("k_final"),
            "epochs": t["epochs"],
            "stopped": log["stopped"],
        }
        if log.get("rtol"):  # the rtol schedule: where its tolerance ended, what it cost
            runs[schedule]["rtol"] = _rtol_summary(log)
    target = accuracy_target(logs, full_name)
    for name, r in runs.items():
        reached = None if target is None else time_to_accuracy(logs[name], target)
        r["time_to_full_accuracy"] = reached
    summary = {"scene": scene, "k_full": k_full, "threads": threads, "runs": runs}
    summary.update(speedup_vs_best_full(logs, k_fulls))
    twin, full = logs.get(twin_name), logs.get(full_name)
    if twin and full and not (twin["stopped"] or full["stopped"]):
        summary["noise_ratio"] = _ratio(
            twin["totals"]["final_val_error"], full["totals"]["final_val_error"]
        )
    if len(k_fulls) > 1 or skipped:
        summary["routes"] = {
            route: {"k_full": k, **_savings(logs, f"prdp@{route}", f"fixed:{k}@{route}")}
            for route, k in k_fulls.items()
            if route
        }
        summary["routes"].update(
            {route: {"skipped": why} for route, why in (skipped or {}).items()}
        )
        candidates = {name: log for name, log in logs.items() if name != twin_name}
        summary["fastest"] = fastest(candidates, full_name)
    summary.update(_savings(logs, "prdp", full_name))
    constant = {
        int(name[6:]): log["totals"]["final_val_error"]
        for name, log in logs.items()
        if name.startswith("fixed:") and name[6:].isdigit() and not log["stopped"]
    }
    if k_full in constant and len(constant) > 1:
        summary["equal_accuracy_k"] = equal_accuracy_k(constant, k_full, ACCURACY_RATIO - 1)
    return summary


def _rtol_summary(log: dict) -> dict:
    """The ``rtol`` schedule of run `log`: first and last rtol, level, cap, and the mean
    forward iterations per solve in its first and last epoch (None without epochs)."""
    plan, epochs = log["rtol"], log["epochs"]

    def per_solve(epoch):
        return epoch["fwd_iterations"] / epoch["fwd_solves"] if epoch["fwd_solves"] else None

    return {
        "init": plan["rtol_init"],
        "final": epochs[-1]["rtol"] if epochs else None,
        "level": epochs[-1]["rtol_level"] if epochs else None,
        "levels": plan["levels"],
        "max_it": plan["max_it"],
        "max_it_factor": plan["max_it_factor"],
        "k_full": plan["k_full"],
        "fwd_per_solve_first": per_solve(epochs[0]) if epochs else None,
        "fwd_per_solve_last": per_solve(epochs[-1]) if epochs else None,
    }


def _kind(name: str, k_fulls: dict) -> str:
    """``"full"`` (``fixed:K_full`` of its route), ``"twin"``, or ``"reduced"`` (PRDP,
    ``rtol``, a coarse constant K) for a run named ``schedule[@route]``."""
    schedule, _, route = name.partition("@")
    if schedule.startswith(f"{TWIN}:"):
        return TWIN
    fixed = schedule.startswith("fixed:") and schedule[6:].isdigit()
    if fixed and int(schedule[6:]) == k_fulls.get(route):
        return "full"
    return "reduced"


def speedup_vs_best_full(logs: dict, k_fulls: dict | int) -> dict:
    """How much sooner the fastest reduced run reached full-fidelity accuracy.

    The target is `accuracy_target` of the scene's own solver at K_full
    (``fixed:K_full``), each run's time `time_to_accuracy`.  The best full-fidelity
    time is the least over ``fixed:K_full`` and every route's ``fixed:K@route`` at
    its own K_full; the best reduced time the least over PRDP, the ``rtol`` schedule
    and coarse constant Ks on any route.  A twin is neither.

    Parameters
    ----------
    logs : dict
        ``{run name: log}`` as `run` returns them, named as `compare` names runs.
    k_fulls : dict or int
        ``{route: K_full}`` with ``""`` for the scene's own solver (or that one int).

    Returns
    -------
    dict
        ``speedup_vs_best_full``: best full time / best reduced time (above 1: the
        reduced run was faster), or None; ``speedup``: ``target_val_error``,
        ``reference`` (the full-fidelity run that sets the target), ``full`` and
        ``full_seconds`` (the fastest full-fidelity run and its time), ``reduced`` and
        ``reduced_seconds`` (likewise, None where none reached), and, where the
        speedup is None, ``unavailable``: why, in words.
    """
    k_fulls = k_fulls if isinstance(k_fulls, dict) else {"": k_fulls}
    reference = f"fixed:{k_fulls['']}"
    target = accuracy_target(logs, reference)
    detail = {"target_val_error": target, "reference": reference}
    best = {}
    for kind in ("full", "reduced"):
        times = {
            name: time_to_accuracy(log, target)
            for name, log in logs.items()
            if _kind(name, k_fulls) == kind and target is not None
        }
        reached = {name: t for name, t in times.items() if t is not None}
        name = min(reached, key=reached.get) if reached else None
        detail[kind], detail[f"{kind}_seconds"] = name, reached.get(name)
        best[kind] = times
    why = None
    stop = (logs.get(reference) or {}).get("stopped")
    if target is None:
        why = f"{reference} (full fidelity, the target) did not run"
    elif stop:
        why = (
            f"{reference} (full fidelity, the target) stopped at epoch {stop['epoch']} "
            f"({stop['reason']}): no full-fidelity accuracy to reach"
        )
    elif detail["full"] is None:
        why = f"no full-fidelity run reached its own final validation error ({target:.4e})"
    elif not best["reduced"]:
        why = "no reduced run (PRDP, rtol, coarse K) ran"
    elif detail["reduced"] is None:
        why = (
            f"no reduced run ({', '.join(best['reduced'])}) reached full-fidelity accuracy: "
            f"validation error <= {REACH_FACTOR} x {reference}'s final, {target:.4e}, "
            "from some epoch on to the end"
        )
    if why:
        detail["unavailable"] = why
        return {"speedup_vs_best_full": None, "speedup": detail}
    ratio = _ratio(detail["full_seconds"], detail["reduced_seconds"])
    return {"speedup_vs_best_full": ratio, "speedup": detail}


def _savings(logs: dict, prdp_name: str, full_name: str) -> dict:
    """``savings``, ``val_error_ratio``, ``equal_accuracy`` (or ``savings_unavailable``)."""
    prdp, full = logs.get(prdp_name), logs.get(full_name)
    unavailable = _why_no_savings(prdp, full, prdp_name, full_name)
    if unavailable:
        return {"savings_unavailable": unavailable}
    summary = {}
    inner = [e["fwd_iterations"] + e["adj_iterations"] for e in prdp["epochs"]]
    inner_full = [e["fwd_iterations"] + e["adj_iterations"] for e in full["epochs"]]
    by_iter = savings(costs=inner, cost_full=inner_full)
    by_time = savings(
        costs=[e["wall_time"] for e in prdp["epochs"]],
        cost_full=[e["wall_time"] for e in full["epochs"]],
    )
    summary["savings"] = {
        "iterations": by_iter["total"],
        "wall_time": by_time["total"],
        "pr": by_iter["pr"],
        "ic": by_iter["ic"],
    }
    ratio = _ratio(prdp["totals"]["final_val_error"], full["totals"]["final_val_error"])
    summary["val_error_ratio"] = ratio
    summary["equal_accuracy"] = ratio <= ACCURACY_RATIO
    if not summary["equal_accuracy"]:
        summary["accuracy_warning"] = (
            f"val error ratio {ratio:.3g} > {ACCURACY_RATIO}: PRDP did not reach "
            "full-fidelity accuracy; savings are not at equal accuracy"
        )
    return summary


def _ratio(num: float, den: float) -> float:
    """``num / den`` for errors >= 0; 0 / 0 is 1, x / 0 is inf, NaN stays NaN (unequal)."""
    if den > 0 or math.isnan(den):
        return num / den
    return math.inf if num > 0 else 1.0


def _why_no_savings(prdp: dict | None, full: dict | None, prdp_name: str, full_name: str):
    """None if PRDP and K_full ran over the same epochs, else the reason in words."""
    reasons = []
    for name, log in ((prdp_name, prdp), (full_name, full)):
        if log is None:
            reasons.append(f"{name} did not run")
        elif log["stopped"]:
            stop = log["stopped"]
            reasons.append(f"{name} stopped at epoch {stop['epoch']} ({stop['reason']})")
    if not reasons and len(prdp["epochs"]) != len(full["epochs"]):
        reasons.append(
            f"{prdp_name} ran {len(prdp['epochs'])} epochs, {full_name} {len(full['epochs'])}"
        )
    if not reasons and not prdp["epochs"]:
        reasons.append("no epochs ran")
    if reasons:
        detail = "; ".join(reasons)
        return (
            f"no savings: {detail}; savings need {prdp_name} and {full_name} over the same epochs"
        )
    return None


def stopped_runs(summary: dict) -> list[str]:
    """Schedules of the summary whose run stopped early (diverged, invalid input, Ctrl-C)."""
    return [name for name, r in summary["runs"].items() if r["stopped"]]


def format_table(summary: dict) -> str:
    """Plain-text table of a comparison summary, with its savings line and warnings.

    Column ``reach s``: the run's ``time_to_full_accuracy`` (— where it never
    reached full-fidelity accuracy); the line ``speedup vs best full fidelity`` gives
    ``speedup_vs_best_full`` with the two runs it compares, or why there is none.
    """

    def cell(value, width: int, spec: str = "") -> str:
        return ("—" if value is None else format(value, spec)).rjust(width)

    width = max([12, *(len(name) + 2 for name in summary["runs"])])
    # summaries written before time_to_full_accuracy existed keep their old table
    reach = any("time_to_full_accuracy" in r for r in summary["runs"].values())
    lines = [
        f"scene {summary['scene']}   K_full = {summary['k_full']}",
        f"{'schedule':<{width}}{'val error':>12}{'K final':>9}{'inner its':>12}{'wall s':>9}"
        f"{'solver %':>10}" + (f"{'reach s':>9}" if reach else "") + "  stopped",
    ]
    for name, r in summary["runs"].items():
        its = (r["fwd_iterations"] or 0) + (r["adj_iterations"] or 0)
        stop = r["stopped"]
        share = (
            100 * r["solver_time"] / r["wall_time"]
            if r["wall_time"] and r["solver_time"] is not None
            else None
        )
        lines.append(
            f"{name:<{width}}{cell(r['final_val_error'], 12, '.4e')}{cell(r['k_final'], 9)}"
            f"{its:>12}{cell(r['wall_time'], 9, '.2f')}{cell(share, 10, '.1f')}"
            + (cell(r.get("time_to_full_accuracy"), 9, ".2f") if reach else "")
            + "  "
            + (f"{stop['reason']} at epoch {stop['epoch']}" if stop else "no")
        )
    for name, r in summary["runs"].items():
        if "rtol" in r:
            lines.append(_rtol_line(name, r["rtol"]))
    if "savings" in summary:
        s = summary["savings"]
        lines.append(
            f"PRDP vs K_full: {100 * s['iterations']:.1f} % fewer inner iterations "
            f"(PR {100 * s['pr']:.1f} %, IC {100 * s['ic']:.1f} %), "
            f"{100 * s['wall_time']:.1f} % less wall time, "
            f"val error ratio {summary['val_error_ratio']:.3f}"
        )
        if "accuracy_warning" in summary:
            lines.append(f"  !! {summary['accuracy_warning']}")
    else:
        lines.append(f"PRDP vs K_full: {summary['savings_unavailable']}")
    if "noise_ratio" in summary:
        lines.append(
            f"full fidelity twice (twin:{summary['k_full']}: other initial weights "
            f"and batch order): val error ratio {summary['noise_ratio']:.3f}, the run-to-run noise"
        )
    bound = summary.get("equal_accuracy_k")
    if bound:
        fit = bound["fitted"]
        lines.append(
            f"smallest constant K within 5 % of K_full: {bound['measured']} of the runs"
            + (
                f", ≈ {fit} fitting e_full + C ρ^K to fixed:{bound['pair'][0]}, "
                f"fixed:{bound['pair'][1]} (ρ = {bound['rho']:.3f})"
                if fit
                else ""
            )
            + f"; incomplete convergence alone saves at most {100 * bound['ic_bound']:.0f} %"
        )
        noise = summary.get("noise_ratio")
        if noise is not None and not 1 / ACCURACY_RATIO <= noise <= ACCURACY_RATIO:
            lines.append(
                f"  (the twin ends {noise:.3f}x full fidelity: below that noise the "
                "constant-K errors do not resolve a 5 % difference)"
            )
    for route, r in summary.get("routes", {}).items():
        if "skipped" in r:
            lines.append(f"{route}: skipped, it does not fit the scene's solver: {r['skipped']}")
        elif "savings" in r:
            lines.append(
                f"PRDP vs K_full on {route} (K_full = {r['k_full']}): "
                f"{100 * r['savings']['iterations']:.1f} % fewer inner iterations, "
                f"{100 * r['savings']['wall_time']:.1f} % less wall time, "
                f"val error ratio {r['val_error_ratio']:.3f}"
            )
        else:
            lines.append(f"PRDP vs K_full on {route}: {r['savings_unavailable']}")
    best = summary.get("fastest")
    if best:
        lines.append(
            f"fastest to the full-fidelity validation error ({best['target_val_error']:.4e}, "
            f"within 5 % of {best['reference']}): "
            + (
                f"{best['winner']} in {best['winner_seconds']:.2f} s"
                if best["winner"]
                else "no run reached it"
            )
        )
        if not reach:  # an older summary: the times per run, as the column would give them
            main = ["prdp", f"fixed:{summary['k_full']}"] + [
                name
                for route, r in summary.get("routes", {}).items()
                if "skipped" not in r
                for name in (f"prdp@{route}", f"fixed:{r['k_full']}@{route}")
            ]
            for name in main:
                if name in best["seconds_to_target"]:
                    t = best["seconds_to_target"][name]
                    lines.append(f"  {name}: " + ("not reached" if t is None else f"{t:.2f} s"))
    if "speedup" in summary:
        lines.append(_speedup_line(summary["speedup_vs_best_full"], summary["speedup"]))
    return "\n".join(lines)


def _speedup_line(ratio: float | None, detail: dict) -> str:
    """The table's line for `speedup_vs_best_full`."""
    if ratio is None:
        return f"speedup vs best full fidelity: none, {detail['unavailable']}"
    return (
        f"speedup vs best full fidelity: {ratio:.2f}x ({detail['full']} reached full-fidelity "
        f"accuracy, val error <= {detail['target_val_error']:.4e}, in "
        f"{detail['full_seconds']:.2f} s; {detail['reduced']} in {detail['reduced_seconds']:.2f} s)"
    )


def _rtol_line(name: str, r: dict) -> str:
    """The table's line for an ``rtol`` run: tolerances, cap, iterations per solve."""
    first, last = r["fwd_per_solve_first"], r["fwd_per_solve_last"]
    its = "" if first is None else f"; forward iterations per solve {first:.1f} -> {last:.1f}"
    final = "—" if r["final"] is None else f"{r['final']:.0e} (level {r['level']} of {r['levels']})"
    return (
        f"{name}: PETSc's rtol test under max_it = {r['max_it']} "
        f"({r['max_it_factor']} x K_full {r['k_full']}), rtol {r['init']:.0e} -> {final}{its}"
    )
