"""The pages of ``prdp-petsc compare`` and ``compare --seeds``: their two report kinds.

`prdp_petsc.lab.training.compare` and `prdp_petsc.lab.training.seeds` write
``summary.json`` and ``seeds.json`` and print their tables; this module says what a
page of each shows and which figures reach the headline table.
"""

from __future__ import annotations

from ..training.seeds import equal_accuracy_savings, format_ratio, format_seeds
from ..training.summary import format_table
from .kinds import DataSet, ReportKind, percent

__all__ = ["COMPARE", "SEEDS"]


def _compare_headline(ds: DataSet) -> list[tuple[str, str]]:
    """PRDP's savings against constant K_full (said to be at equal accuracy only where
    PRDP reached it), and the fastest run to full fidelity's error."""
    d = ds.main
    out = []
    if "savings" in d:
        s = d["savings"]
        cost = (
            f"{percent(s['iterations'])} fewer inner iterations, {percent(s['wall_time'])} "
            f"less wall time, validation error ratio {d['val_error_ratio']:.3f}"
        )
        if not d["equal_accuracy"]:
            cost = f"not at equal accuracy: {cost}"
        out.append((f"{d['scene']}: PRDP against constant K_full = {d['k_full']}", cost))
    else:
        out.append((f"{d['scene']}: PRDP against constant K_full", d["savings_unavailable"]))
    best = d.get("fastest")
    if best and best["winner"]:
        out.append(
            (
                f"{d['scene']}: fastest run to the full-fidelity validation error",
                f"`{best['winner']}` in {best['winner_seconds']:.2f} s, against "
                f"{best['seconds_to_target'][best['reference']]:.2f} s for "
                f"`{best['reference']}`",
            )
        )
    return out


COMPARE = ReportKind(
    name="compare",
    reads="summary.json",
    title=lambda ds: f"PRDP against full fidelity: {ds.main['scene']}",
    headline=_compare_headline,
    intro="What `compare` printed (validation error at the last epoch, final K, inner "
    "iterations forward + adjoint, wall time, the solver's share of it):",
    output=lambda ds: format_table(ds.main).rstrip("\n"),
    snippet=True,
    images="Plots",
)


def _seeds_headline(ds: DataSet) -> list[tuple[str, str]]:
    """The speed-up of the fastest reduced run over the fastest full-fidelity one, and
    PRDP's error ratio with what it saved on the seeds at equal accuracy."""
    d = ds.main
    speedup = d.get("speedup") or {}
    seeds = f"{_setting(ds)} over seeds {', '.join(map(str, d['seeds']))}"
    what = f"{seeds}: speed-up of the fastest reduced run over the fastest full-fidelity one"
    if speedup.get("geometric_mean") is None:
        rows = [(what, "no reduced run reached full-fidelity accuracy")]
    else:
        goal = f"≥ {speedup['goal']:g} on {speedup['goal_met']} of {speedup['seeds']}"
        rows = [(what, format_ratio(speedup, ".2f", "×", f"{speedup['n']} seeds; {goal}"))]
    bound = (speedup.get("solver_bound") or {}).get("geometric_mean")
    if bound is not None:  # summary.solver_bound: no solver setting gets past it
        rows[0] = (what, rows[0][1] + f"; solver-only bound {bound:.2f}×")
    ratio = d.get("prdp_ratio") or {}
    if ratio.get("geometric_mean") is not None:
        equal = equal_accuracy_savings(d["per_seed"])
        n = sum("prdp_ratio" in r for r in d["per_seed"])
        saved = (
            f"; {percent(equal['iterations_saved']['mean'])} fewer inner iterations on the "
            f"{equal['seeds']} of {n} seeds at equal accuracy"
            if equal
            else f"; no seed of {n} at equal accuracy"
        )
        rows.append(
            (
                f"{seeds}: PRDP's final validation error over full fidelity's",
                format_ratio(ratio) + saved,
            )
        )
    return rows


def _setting(ds: DataSet) -> str:
    """``ns2d --preset large_k64 k_init=192, -ns2d_pc_type fieldsplit``: the scene, the
    preset, its ``--set`` changes and the PC a run set on the command line, from the
    recorded command."""
    argv = ds.provenance.get("argv", [])
    text = ds.main["scene"]
    if "--preset" in argv[:-1]:
        text += f" --preset {argv[argv.index('--preset') + 1]}"
    changes = [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--set"]
    if changes:  # --set k_init=192: another setting, another row
        text += " " + " ".join(changes)
    pcs = [f"{a} {argv[i + 1]}" for i, a in enumerate(argv[:-1]) if a.endswith("_pc_type")]
    return text + (f", {pcs[0]}" if pcs else "")


SEEDS = ReportKind(
    name="seeds",
    reads="seeds.json",
    title=lambda ds: f"PRDP against full fidelity over seeds: {ds.main['scene']}",
    headline=_seeds_headline,
    intro="What `compare --seeds` printed (per seed: validation errors of PRDP, full "
    "fidelity and its twin, their ratios, PRDP's savings, and the speed-up of the "
    "fastest reduced run over the fastest full-fidelity run; then geometric means "
    "with 95 % intervals over the seeds):",
    output=lambda ds: format_seeds(ds.main).rstrip("\n"),
    images="Plots",
)
