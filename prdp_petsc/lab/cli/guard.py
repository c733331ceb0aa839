"""Running a command under the command line's conventions: an error prints one line
(``--debug``: the traceback) and exits 1, Ctrl-C exits 130, and an error on one rank
of a ``--parallel`` run stops all of them (`guarded`)."""

from __future__ import annotations

import argparse
import sys

__all__ = ["debug_flag", "guarded", "is_root"]


def is_root(args) -> bool:
    """False on the ranks other than 0 of a ``--parallel`` run (they print nothing)."""
    if getattr(args, "parallel", None) is None:
        return True
    from mpi4py import MPI

    return MPI.COMM_WORLD.Get_rank() == 0


def _abort_others(args) -> None:
    """After an error in a ``--parallel`` run, stop every rank (none waits forever)."""
    if getattr(args, "parallel", None) is not None:
        from mpi4py import MPI

        if MPI.COMM_WORLD.Get_size() > 1:
            sys.stderr.flush()
            MPI.COMM_WORLD.Abort(1)


def guarded(command, debug: bool, out: str | None = None, args=None) -> int:
    """Run ``command()``; an error prints one line (unless ``debug``) and returns 1."""
    try:
        return command()
    except KeyboardInterrupt:
        if debug:
            raise
        where = f"; results so far in {out}/" if out else ""
        print(f"prdp-petsc: interrupted (Ctrl-C){where}", file=sys.stderr)
        return 130
    except Exception as err:
        if debug:
            if getattr(args, "parallel", None) is not None:
                import traceback

                traceback.print_exc()
                _abort_others(args)  # the other ranks may be waiting in a collective call
            raise
        message = " ".join(str(err).split()) or "(no message)"
        print(
            f"prdp-petsc: error: {type(err).__name__}: {message} (--debug shows the traceback)",
            file=sys.stderr,
        )
        _abort_others(args)
        return 1


def debug_flag(argv: list[str]) -> bool:
    """Whether `argv` asks for tracebacks (``--debug``), before its own parser reads it."""
    debug = argparse.ArgumentParser(add_help=False)
    debug.add_argument("--debug", action="store_true")
    return debug.parse_known_args(argv)[0].debug
