"""Every ```python block of the README and the guides runs, as written.

The blocks of one page run in order in one namespace, like a doctest session: a later
block may use what an earlier one of the same page defined, and nothing else. They run
from the repository root, the folder the pages' paths (``docs/examples/my_scene.py``)
are relative to. A block that includes a file (``--8<-- "docs/examples/quickstart.py"``
or a section of one, ``--8<-- "docs/examples/vector.py:stokes"``) runs what the
reader sees: the included text, as pymdownx.snippets shows it.

A block may be left out only when it is no Python a reader would paste, say a
fragment that documents part of a file with its own protocol; it is marked by the
comment ``<!-- not run: <why> -->`` on the line above its fence, which the page does not
show. Today no block is.

Tracebacks name the page and its line: ``docs/guide/library.md:131``.

Pages that need the lab (the scene guide) are why this file is among the lab's tests.
"""

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = [
    ROOT / "README.md",
    ROOT / "docs" / "index.md",
    ROOT / "docs" / "getting-started.md",
    *sorted((ROOT / "docs" / "guide").glob("*.md")),
]
SNIPPET_BASES = [ROOT / "docs", ROOT]  # mkdocs.yml: pymdownx.snippets base_path

# a fence at any indentation (a block inside a list item is indented), closed at the same
FENCE = re.compile(
    r"^(?P<indent>[ ]*)```(?P<lang>[\w-]*)[^\n]*\n(?P<body>.*?)^(?P=indent)```[ ]*$",
    re.MULTILINE | re.DOTALL,
)
NOT_RUN = re.compile(r"<!-- not run: (?P<why>.+?) -->\s*$")
INCLUDE = re.compile(r'^--8<-- "(?P<path>[^":]+)(?::(?P<section>[\w-]+))?"$')
SECTION_MARK = re.compile(r"--8<-- \[(start|end):[\w-]+\]")


@dataclass
class Block:
    page: Path
    line: int  # of the first line of the body in the page
    source: str
    not_run: str | None  # why, for a block marked not to run

    @property
    def where(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def included(path: str, section: str | None) -> str:
    """The text pymdownx.snippets puts in place of ``--8<-- "path[:section]"``."""
    file = next((base / path for base in SNIPPET_BASES if (base / path).is_file()), None)
    assert file is not None, f"snippet {path!r} not found under {SNIPPET_BASES}"
    lines = file.read_text().splitlines()
    if section is not None:
        start = lines.index(f"# --8<-- [start:{section}]")
        lines = lines[start + 1 : lines.index(f"# --8<-- [end:{section}]", start)]
    return "\n".join(line for line in lines if not SECTION_MARK.search(line)) + "\n"


def python_blocks(page: Path) -> list[Block]:
    text = page.read_text()
    blocks = []
    for match in FENCE.finditer(text):
        if match["lang"] != "python":
            continue
        indent = len(match["indent"])
        body = "".join(line[indent:] for line in match["body"].splitlines(keepends=True))
        body = "".join(
            included(m["path"], m["section"]) if (m := INCLUDE.match(line.strip())) else line
            for line in body.splitlines(keepends=True)
        )
        before = text[: match.start()].rstrip("\n").rpartition("\n")[2]
        marked = NOT_RUN.search(before)
        line = text.count("\n", 0, match.start("body")) + 1
        blocks.append(Block(page, line, body, marked["why"] if marked else None))
    return blocks


def run_page(page: Path) -> dict:
    """Run the page's blocks in one namespace; return it."""
    namespace = {"__name__": "__doc_snippets__"}
    for block in python_blocks(page):
        if block.not_run is None:
            # padded so that a traceback's line number is the page's
            code = compile("\n" * (block.line - 1) + block.source, str(block.page), "exec")
            exec(code, namespace)
    return namespace


RUN = [page for page in PAGES if python_blocks(page)]


def test_the_pages_have_blocks_to_run():
    """The parser finds the blocks (an empty list would pass everything below)."""
    names = {page.relative_to(ROOT).as_posix() for page in RUN}
    assert {"README.md", "docs/index.md", "docs/guide/library.md"} <= names
    assert sum(len(python_blocks(page)) for page in RUN) >= 15


def test_blocks_left_out_are_rare_and_say_why():
    left_out = [b for page in PAGES for b in python_blocks(page) if b.not_run is not None]
    assert len(left_out) <= 2, [b.where for b in left_out]
    assert all(len(b.not_run.split()) >= 4 for b in left_out), [b.where for b in left_out]


@pytest.mark.parametrize("page", RUN, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_page_runs_as_written(page, monkeypatch):
    monkeypatch.chdir(ROOT)
    namespace = run_page(page)
    check = CHECKS.get(page.relative_to(ROOT).as_posix())
    if check is not None:
        check(namespace)


# -- what the pages say their code gives ---------------------------------------------------
def _finite_nonzero(grad):
    return bool(np.isfinite(grad.numpy()).all()) and float(grad.norm()) > 0


def _readme(ns):
    """The quickstart: 20 iterations, capped; the PRDP loop: certified below K_full,
    the validation error of log κ less than half its first value."""
    assert ns["sol"].iterations == 20 and ns["sol"].reason == "DIVERGED_MAX_IT"
    assert _finite_nonzero(ns["theta"].grad) and _finite_nonzero(ns["g"].grad)
    prdp, savings = ns["prdp"], ns["prdp"].savings()
    assert savings["certified"] is True and prdp.k < ns["k_full"] and savings["total"] > 0
    assert prdp.history[-1].metric < 0.5 * prdp.history[0].metric


def _index(ns):
    assert ns["u"].shape == ns["b"].shape and _finite_nonzero(ns["theta"].grad)


def _library(ns):
    """The optimisation loop recovers κ = 2 below y = 1/2 and 1 above, roughly, and
    ends certified."""
    assert ns["sol"].adjoint.iterations.tolist() == [20]
    assert ns["batch"].iterations.tolist() == [20] * 8 == ns["batch"].adjoint.iterations.tolist()
    assert ns["thetas"].grad.shape == (8, ns["A"].n_params) and ns["thetas"].grad.norm() > 0
    kappa, y = ns["design"].detach().exp().numpy(), ns["y"]
    assert kappa[y < 0.5].mean() > 1.6 and kappa[y > 0.5].mean() < 1.3
    assert ns["prdp"].savings()["certified"] is True


def _scenes(ns):
    """The unrolled corrector trains: its 4-step loss falls tenfold."""
    assert ns["losses"][-1] < 0.1 * ns["losses"][0]
    assert ns["result"]["totals"]["final_val_error"] < 1e-3


def _solvers(ns):
    assert ns["ROUTES"]["schur"] == (
        "gmres/fieldsplit:ksp_gmres_restart=30:pc_fieldsplit_detect_saddle_point"
        ":pc_fieldsplit_type=schur"
    )


def _mpi(ns):
    assert ns["u"].shape == (ns["part"].owned_vertices,) and _finite_nonzero(ns["theta"].grad)


CHECKS = {
    "README.md": _readme,
    "docs/index.md": _index,
    "docs/guide/library.md": _library,
    "docs/guide/scenes.md": _scenes,
    "docs/guide/solvers.md": _solvers,
    "docs/guide/mpi.md": _mpi,
}
