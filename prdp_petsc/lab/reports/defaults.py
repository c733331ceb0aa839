"""A shipped scene with PRDP's default construction beside its tuned settings.

``prdp-petsc defaults SCENE_FILE --preset P --seeds 0-2 --out DIR`` trains, per seed,
full fidelity (constant K_full), the scene's tuned PRDP (schedule ``prdp``) and the
default construction (schedule ``auto``: ``PRDP.for_problem(K_full)`` with a gradient
check) and writes ``DIR/defaults.json``: every run's final validation error, inner
iterations (checks included), final K and certificate, and per schedule the error ratios
over full fidelity with the savings at equal accuracy.  ``--baselines`` adds the
constant caps K_full/8, /4, /2 (`prdp_petsc.lab.training.accuracy.constant_caps`) and
names the one that saves the most at equal accuracy over the seeds.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from prdp_petsc import PRDP

from ..provenance import write_result
from ..training.accuracy import (
    ACCURACY_RATIO,
    constant_caps,
    equal_over_seeds,
    probe_errors,
    probed_at,
    worst_ratio,
)
from .kinds import DataSet, ReportKind, text_table

__all__ = ["KIND", "SCHEDULES", "defaults", "fewer", "format_defaults", "main", "notes", "summary"]

#: the reduced schedules compared, by the name the page gives them
SCHEDULES = {"tuned": "prdp", "default": "auto"}


def defaults(
    scene_file, preset: str, seeds: list[int], *, threads: int = 1, out=None,
    baselines: bool = False, resume: bool = False,
) -> dict:  # fmt: skip
    """Full fidelity, the tuned PRDP and the default construction on every seed; with
    `baselines`, each constant cap of `constant_caps` too (``result["baselines"]``:
    their labels; ``result["best_constant"]``: the one at equal accuracy over the seeds,
    `equal_over_seeds`, that saves the most, or None).  With `resume`, a run that
    finished in `out` with the same settings is read, not trained again
    (`prdp_petsc.lab.training.compare.finished_run`; ``result["reused"]`` names them)."""
    from ..training.building import build_scene, release
    from ..training.compare import finished_run
    from ..training.harness import run
    from ..training.probe import probe
    from ..training.scene import load_scene
    from ..training.seeds import equal_accuracy_savings, ratio_statistics

    module = load_scene(scene_file)
    per_seed, reused = [], []
    for seed in seeds:
        scene = build_scene(module, preset, seed)
        measured = probe(scene)  # K_full, and the capped solves' errors: the default's start
        k_full, start = int(measured), PRDP.for_problem(measured).k_init
        epochs = scene.epochs
        release(scene)
        row = {"seed": seed, "k_full": k_full, "start": start,
               "probe_errors": probe_errors(measured)}  # fmt: skip
        runs = {"full": f"fixed:{k_full}", **SCHEDULES}
        if baselines:
            runs.update({label: f"fixed:{k}" for label, k in constant_caps(k_full).items()})
        for name, schedule in runs.items():
            folder = None if out is None else Path(out) / f"seed_{seed}" / name.replace("/", "_")
            prdp = {"k_full": k_full, "k_init": start} if schedule == "auto" else None
            settings = {"schedule": schedule, "preset": preset, "seed": seed, "torch_seed": None}
            log = None
            if resume and folder is not None:
                log = finished_run(folder, settings, prdp or {}, epochs)
            if log is not None:
                reused.append(f"seed {seed} {name}")
            else:
                log = run(scene_file, schedule, preset=preset, seed=seed, threads=threads,
                          progress=False, module=module, out=folder, prdp=prdp)  # fmt: skip
            t = log["totals"]
            row[name] = {
                "final_val_error": t.get("final_val_error"),
                "iterations": t.get("fwd_iterations", 0) + t.get("adj_iterations", 0),
                "wall_time": t.get("wall_time"),
                "k_final": t.get("k_final"),
                "stopped": log["stopped"],
                "certified": (log.get("certificate") or {}).get("certified"),
            }
            if log.get("checks") is not None:
                row[name]["checks"] = log["checks"]
        full = row["full"]
        for name in list(runs)[1:]:
            r = row[name]
            if r["stopped"] or full["stopped"]:
                continue
            r["ratio"] = r["final_val_error"] / full["final_val_error"]
            r["saved"] = 1.0 - r["iterations"] / full["iterations"]
            r["equal_accuracy"] = r["ratio"] <= ACCURACY_RATIO
        per_seed.append(row)
    result = {"scene": Path(scene_file).stem, "preset": preset, "seeds": list(seeds),
              "per_seed": per_seed, "schedules": dict(SCHEDULES)}  # fmt: skip
    if baselines:
        result["baselines"] = list(constant_caps(1))
    if reused:
        result["reused"] = reused
    for name in _compared(result):
        done = [r[name] for r in per_seed if "ratio" in r[name]]
        if not done:
            continue
        ratios = [r["ratio"] for r in done]
        equal = equal_accuracy_savings(done, keys=("saved",))
        result[name] = {
            "ratio": ratio_statistics(ratios),
            "worst_ratio": worst_ratio(ratios),
            "equal_accuracy": equal["seeds"] if equal else 0,
            "compared": len(done),
            "saved_at_equal_accuracy": equal["saved"]["mean"] if equal else None,
            "saved": sum(r["saved"] for r in done) / len(done),
            "certified": sum(bool(r["certified"]) for r in done),
        }
        result[name]["equal_over_seeds"] = len(done) == len(per_seed) and equal_over_seeds(
            result[name]["ratio"]["geometric_mean"], result[name]["worst_ratio"]
        )
    if baselines:
        fits = [b for b in result["baselines"] if result.get(b, {}).get("equal_over_seeds")]
        result["best_constant"] = max(fits, key=lambda b: result[b]["saved"], default=None)
    return result


def _compared(result: dict) -> list[str]:
    """The schedules compared with full fidelity: `SCHEDULES`, then the baselines."""
    return [*SCHEDULES, *result.get("baselines", [])]


def format_defaults(result: dict, *, with_notes: bool = True, with_checks: bool = True) -> str:
    """The table ``prdp-petsc defaults`` prints: one row per seed, the summary,
    (`with_checks`) what the default decided from (`check_lines`) and (`with_notes`)
    what the rows mean (`notes`)."""
    header = ["seed", "K_full", "full error"]
    header += [f"{name} {column}" for name in SCHEDULES for column in ("ratio", "saved", "K")]
    rows = []
    for row in result["per_seed"]:
        cells = [row["seed"], row["k_full"], f"{row['full']['final_val_error']:.4e}"]
        for name in SCHEDULES:
            r = row[name]
            if "ratio" not in r:
                cells += ["stopped", "", ""]
                continue
            mark = "" if r["certified"] is None else (" c" if r["certified"] else " !")
            cells += [f"{r['ratio']:.3f}", f"{100 * r['saved']:.1f}%", f"{r['k_final']}{mark}"]
        rows.append(cells)
    lines = [
        f"{result['scene']} --preset {result['preset']}: full fidelity, tuned PRDP "
        "(the preset's settings) and the default construction (PRDP.for_problem)",
        text_table(header, rows),
    ]
    lines += [summary(result, name) for name in SCHEDULES]
    lines.append("(c: the default construction's last check certified its final K; !: it did not)")
    if with_checks:
        lines += check_lines(result)
    if "baselines" in result:
        lines += ["", baselines_table(result)]
    if with_notes:
        lines += notes(result)
    return "\n".join(lines)


def check_lines(result: dict) -> list[str]:
    """Per seed, what the default construction decided from: its start and the probe's
    error of the solve capped there, then every check (K against its reference, the gap
    and the descent, ✓ certified or ✗ not, and whether a certified K was refined all
    the same: a gap near the band that no recheck could follow).  Empty for a result
    without them (recorded before they were kept)."""
    lines = []
    for row in result["per_seed"]:
        errors = row.get("probe_errors")
        checks = row["default"].get("checks")
        if errors is None and checks is None:
            continue
        parts = []
        if errors is not None:
            error = errors.get(str(row["start"]))
            within = "" if error is None else f" (the probe's solve there: {100 * error:.1f} % off)"
            parts.append(f"started at K={row['start']}{within}")
        checks = checks or []
        for i, c in enumerate(checks):
            descent = "" if c.get("descent") is None else f", descent {100 * c['descent']:.1f} %"
            after = checks[i + 1]["k"] if i + 1 < len(checks) else row["default"]["k_final"]
            mark = "✓" if c["certified"] else "✗"
            if c["certified"] and after > c["k"]:  # PRDP's near-band rule
                mark += " (near the band, no recheck affordable: refined)"
            parts.append(
                f"epoch {c['epoch']}: K={c['k']} vs {c['reference'] or c['k_full']} "
                f"gap {100 * c['gap']:.2f} %{descent} {mark}"
            )
        lines.append(f"seed {row['seed']} default: " + "; ".join(parts))
    return lines


def baselines_table(result: dict) -> str:
    """Every schedule over the seeds, the constant caps beside the two PRDPs: error ratio
    (geometric mean, worst seed), mean saving, and whether that is equal accuracy over the
    seeds (`equal_over_seeds`), with the best constant cap named."""
    rows = []
    for name in _compared(result):
        s = result.get(name)
        if s is None:
            rows.append([name, "no seed finished", "", "", "", ""])
            continue
        equal = "yes" if s["equal_over_seeds"] else "no"
        rows.append([name, f"{s['ratio']['geometric_mean']:.3f}", f"{s['worst_ratio']:.3f}",
                     f"{100 * s['saved']:.1f}%", equal, _probe_errors(result, name)])  # fmt: skip
    best = result.get("best_constant")
    verdict = (
        f"best constant cap at equal accuracy: {best}, {fewer(result[best]['saved'])}"
        if best
        else "no constant cap below K_full reaches equal accuracy over the seeds"
    )
    header = ["schedule", "ratio (geo. mean)", "worst seed", "saved", "equal accuracy",
              "probe's solve error per seed"]  # fmt: skip
    return "\n".join([text_table(header, rows), verdict])


def _probe_errors(result: dict, name: str) -> str:
    """For a constant cap, the error of the probe's solve capped there on each seed
    (what `PRDP.for_problem` starts from), e.g. ``"2.9, 3.0, 7.5 %"``; else empty."""
    errors = probed_at(result["per_seed"], name) if name in result.get("baselines", []) else None
    return "" if errors is None else ", ".join(f"{100 * e:.1f}" for e in errors) + " %"


def summary(result: dict, name: str, *, detail: bool = True) -> str:
    """What schedule `name` did over the seeds: its error ratio (with the interval where
    `detail`) and the seeds at equal accuracy with what it saved there (and, where
    `detail`, on how many the default construction certified its stop)."""
    s = result.get(name)
    if s is None:
        return f"{name}: no seed finished"
    from ..training.seeds import format_ratio

    ratio = format_ratio(s["ratio"]) if detail else f"{s['ratio']['geometric_mean']:.3f}"
    text = (
        f"{name}: error ratio {ratio}; "
        f"equal accuracy on {s['equal_accuracy']} of {s['compared']} seeds"
    )
    if s["saved_at_equal_accuracy"] is not None:
        text += f", {fewer(s['saved_at_equal_accuracy'])} there"
    if detail and name == "default":
        text += f"; certified on {s['certified']}"
    return text


def fewer(saved: float) -> str:
    """``"28.6 % fewer inner iterations"``, or ``"8.7 % more ..."`` for a negative saving."""
    word = "fewer" if saved >= 0 else "more"
    return f"{100 * abs(saved):.1f} % {word} inner iterations"


def notes(result: dict) -> list[str]:
    """What the per-seed rows mean for the default construction, read off the data."""
    rows = [r for r in result["per_seed"] if "ratio" in r["default"]]
    if not rows:
        return []
    at_full = all(r["default"]["k_final"] >= r["k_full"] for r in rows)
    behind = [r for r in rows if not r["default"]["equal_accuracy"]]
    notes = []
    if at_full:
        notes.append(
            "The default construction ended at K_full on every seed: no smaller K kept passing "
            "its check, so what it saved is the epochs it trained below K_full, less the "
            "checks' solves."
        )
    if behind and all(r["default"]["k_final"] >= r["k_full"] for r in behind):
        notes.append(
            f"On {len(behind)} of {len(rows)} seeds it ended behind full fidelity although its "
            "final K was K_full: the accuracy was lost in its epochs below K_full, and "
            "training did not win it back in the epochs left; a certificate speaks of the "
            "final K, not of the path (see Known limitations in the guide)."
        )
    if any(r["default"]["saved"] < 0 for r in rows):
        notes.append(
            "Where it cost more than full fidelity, its checks (each one solve at K and one "
            "at K_full) cost more than its cheap early epochs saved: with a K_full of a few "
            "iterations there is little to save and the checks are not cheaper."
        )
    if result.get("reused"):
        notes.append(
            f"Read from an earlier invocation's finished runs (`--resume`), each with its own "
            f"provenance in its folder's results.json: {', '.join(result['reused'])}."
        )
    tuned = [r for r in rows if "ratio" in r["tuned"]]
    if tuned and all(r["default"]["ratio"] <= r["tuned"]["ratio"] for r in tuned):
        notes.append("Its error ratio is at most the tuned settings' on every seed.")
    return notes


def main(argv: list[str]) -> int:
    from ..cli.arguments import add_debug, add_out, add_preset, add_seeds, add_threads
    from ..training.threads import torch_threads

    parser = argparse.ArgumentParser(prog="prdp-petsc defaults", description=__doc__.split("\n")[0])
    parser.add_argument("scene_file", help="scene file (demos/heat.py)")
    add_preset(parser, "paper")
    add_seeds(parser)
    add_threads(parser)
    add_out(parser)
    parser.add_argument(
        "--baselines", action="store_true",
        help="also train the constant caps K_full/8, /4, /2 and name the best at equal accuracy",
    )  # fmt: skip
    parser.add_argument(
        "--resume", action="store_true",
        help="read the runs that finished in --out with the same settings, train the others",
    )  # fmt: skip
    add_debug(parser)
    args = parser.parse_args(argv)
    with torch_threads(args.threads):
        result = defaults(args.scene_file, args.preset, args.seeds, threads=args.threads,
                          out=args.out, baselines=args.baselines, resume=args.resume)  # fmt: skip
    write_result(args.out, "defaults.json", result)
    print(format_defaults(result))
    return 0


# -- the page of a recorded ``defaults`` ----------------------------------------------------------
def _headline(ds: DataSet) -> list[tuple[str, str]]:
    d = ds.main
    parts = [summary(d, name, detail=False) for name in ("default", "tuned")]
    what = (
        f"{d['scene']} --preset {d['preset']}, seeds {', '.join(map(str, d['seeds']))}: "
        "final error over full fidelity's, default construction (PRDP.for_problem) "
        "and tuned settings"
    )
    rows = [(what, "; ".join(parts))]
    if "baselines" in d:
        best = d.get("best_constant")
        rows.append((
            f"{d['scene']} --preset {d['preset']}: the constant cap below K_full that saves the "
            "most at equal accuracy over the seeds (K_full/8, /4, /2 tried)",
            f"{best}, {fewer(d[best]['saved'])}" if best else "none reaches equal accuracy",
        ))  # fmt: skip
    return rows


KIND = ReportKind(
    name="defaults",
    reads="defaults.json",
    title=lambda ds: (
        f"Default construction against tuned settings: {ds.main['scene']} {ds.main['preset']}"
    ),
    headline=_headline,
    intro="What `prdp-petsc defaults` printed: per seed, full fidelity (constant K_full), the "
    "scene's tuned PRDP (its preset's settings) and the default construction "
    "(`PRDP.for_problem(K_full)` with a gradient check of the scene's `check_loss`, by "
    "default its training loss on one fixed batch; the scene's PRDP settings unused) and, "
    "with `--baselines`, the constant caps K_full/8, /4, /2. Ratios are final validation "
    "errors over full fidelity's; savings count forward and adjoint inner iterations, the "
    "checks included.",
    output=lambda ds: format_defaults(ds.main, with_notes=False, with_checks=False),
    after=lambda ds: [*notes(ds.main), *_decided(ds.main)],
)


def _decided(result: dict) -> list[str]:
    """The page's `check_lines`: a heading and one list item per seed (none where the
    result has none)."""
    lines = check_lines(result)
    if not lines:
        return []
    return ["## What the default decided from", "\n".join(f"- {line}" for line in lines)]
