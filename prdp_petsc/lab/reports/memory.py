"""A process's memory, measured one way for every report: its resident set.

`peak_rss_mb` is the high-water mark of the resident set (Linux ``VmHWM`` from
``/proc/self/status``; elsewhere ``ru_maxrss``), `reset_peak` restarts it from the
current size (``/proc/self/clear_refs``), so that what came before (building the
data, a warm-up) does not count, and `rss_mb` is the current size (``VmRSS``).
``bench mpi`` (per rank), ``bench bridge``'s unrolled comparison (a fresh process
per variant) and ``horizon`` read them.
"""

from __future__ import annotations

import resource
import sys
from pathlib import Path

__all__ = ["peak_rss_mb", "reset_peak", "rss_mb"]

_STATUS = Path("/proc/self/status")


def peak_rss_mb() -> float:
    """This process's peak resident size in MiB since it started or since `reset_peak`."""
    peak_kb = _status_kb("VmHWM")
    if peak_kb is None:  # no /proc: the peak since start, in kB (bytes on macOS)
        peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        peak_kb /= 1024 if sys.platform == "darwin" else 1
    return peak_kb / 1024


def rss_mb() -> float | None:
    """This process's resident size now, in MiB (None without ``/proc``)."""
    kb = _status_kb("VmRSS")
    return None if kb is None else kb / 1024


def reset_peak() -> bool:
    """Restart `peak_rss_mb` from the current resident size; False where the system
    cannot (no ``/proc/self/clear_refs``: the peak then counts from the start)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def _status_kb(field: str) -> int | None:
    try:
        text = _STATUS.read_text()
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return None
