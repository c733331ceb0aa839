"""Recording a run's data for the results pages: ``prdp-petsc pages record``."""

from __future__ import annotations

import datetime
import json
import logging
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

from ..provenance import git_commit, load_average, machine, versions

__all__ = ["record"]

logger = logging.getLogger(__name__)

_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]*$")


def _out_folder(command: list[str]) -> Path:
    for i, arg in enumerate(command):
        if arg == "--out" and i + 1 < len(command):
            return Path(command[i + 1])
        if arg.startswith("--out="):
            return Path(arg.split("=", 1)[1])
    raise ValueError("the recorded command must name its output folder: --out DIR")


def _stamps(folder: Path) -> dict:
    """(modification time, size) of each file at the top of `folder`."""
    if not folder.is_dir():
        return {}
    return {p: (p.stat().st_mtime_ns, p.stat().st_size) for p in folder.iterdir() if p.is_file()}


def record(
    name: str,
    command: list[str],
    *,
    data: str | Path = "docs/data",
    images: str | Path = "docs/images",
) -> int:
    """Run ``prdp-petsc COMMAND``; keep its JSON and plots under `data` and `images`.

    `command` (the arguments of ``prdp-petsc``) must name its output folder with
    ``--out DIR``.  Only the files it wrote (new, or changed while it ran) at the top of
    DIR are copied: JSON files into ``data/name/`` with ``provenance.json`` (command
    line, start and wall time, exit status, git commit and changed files, machine with
    load average before and after, package versions), PNG files into ``images/name/``;
    the data set's old files there are removed first.  Returns the command's exit
    status; nothing is copied unless it is 0.
    """
    if not _NAME.match(name):
        raise ValueError(f"data set name {name!r}: use lower case letters, digits, _ and -")
    out = _out_folder(command)
    git = git_commit() or {"commit": None, "modified": []}
    provenance = {
        "command": shlex.join(["prdp-petsc", *command]),
        "argv": list(command),
        "started": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "git": {"commit": git["commit"], "modified": git["modified"]},
        "machine": machine(),
        "versions": versions(),
    }
    provenance["machine"]["load_average_start"] = provenance["machine"].pop("load_average")
    before = _stamps(out)
    start = time.time()
    from prdp_petsc.lab.subprocesses import child_env

    # the command may start MPI jobs: not with this process's MPI runtime variables
    status = subprocess.call(
        [sys.executable, "-m", "prdp_petsc.lab.cli", *command], env=child_env()
    )
    provenance["wall_s"] = round(time.time() - start, 1)
    provenance["exit_status"] = status
    provenance["machine"]["load_average_end"] = load_average()
    if status != 0:
        logger.error("%s exited with status %d: nothing recorded", provenance["command"], status)
        return status
    written = [p for p, stamp in sorted(_stamps(out).items()) if before.get(p) != stamp]
    data_dir, image_dir = Path(data) / name, Path(images) / name
    for folder, suffix in ((data_dir, ".json"), (image_dir, ".png")):
        if folder.exists():
            shutil.rmtree(folder)
        files = [p for p in written if p.suffix == suffix]
        if files:
            folder.mkdir(parents=True)
        for path in files:
            shutil.copy2(path, folder / path.name)
        provenance["json" if suffix == ".json" else "images"] = [p.name for p in files]
    if not provenance["json"]:
        raise FileNotFoundError(f"{provenance['command']} wrote no JSON file in {out}")
    (data_dir / "provenance.json").write_text(json.dumps(provenance, indent=1) + "\n")
    logger.info("recorded %s in %s", provenance["command"], data_dir)
    return 0
