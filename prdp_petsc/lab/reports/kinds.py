"""A kind of recorded data set, and what its page says: one `ReportKind` per kind.

Each report module declares its kind beside the code that prints it (``KIND =
ReportKind(...)``); `prdp_petsc.lab.reports.pages` collects them, reads the data sets
under ``docs/data/`` into `DataSet` objects and renders each page from
``templates/page.md.j2``.  Adding a kind is one module.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from fnmatch import fnmatch

__all__ = ["DataSet", "ReportKind", "markdown_table", "percent", "text_table"]


def _nothing(ds: DataSet) -> list[str]:
    return []


@dataclass(frozen=True)
class ReportKind:
    """One kind of recorded data set: the file it is made from, and what its page says.

    Attributes
    ----------
    name : str
        The kind's name (``"bench-jax"``).
    reads : str
        The JSON file (or pattern, ``"work_precision_*.json"``) a data set of this kind is
        made from; a recorded folder holds the file of exactly one kind.
    title, headline : callable
        ``title(ds)``: the page's title, also its row on the index; ``headline(ds)``:
        ``[(what, figure), ...]``, its rows in the index's headline table (the README
        shows the first row of a few data sets).
    intro : str or callable
        The paragraphs before the output (or ``intro(ds)``).
    output : callable
        ``output(ds)``: printed text, in a ``text`` block (`printed`; `snippet` marks it
        as the section ``output`` that other pages include), or Markdown.
    after : callable
        ``after(ds)``: paragraphs, tables and headings after the output.
    images : str
        The heading above the data set's plots, if it has any ("" for none).
    """

    name: str
    reads: str
    title: Callable[[DataSet], str]
    headline: Callable[[DataSet], list[tuple[str, str]]]
    intro: str | Callable[[DataSet], str]
    output: Callable[[DataSet], str]
    printed: bool = True
    snippet: bool = False
    after: Callable[[DataSet], list[str]] = _nothing
    images: str = ""

    def matches(self, file_name: str) -> bool:
        """Whether `file_name` is the file a data set of this kind is made from."""
        return fnmatch(file_name, self.reads)

    def parts(self, ds: DataSet) -> dict:
        """The parts of `ds`'s page after its provenance, by the names the template reads."""
        return {
            "intro": self.intro(ds) if callable(self.intro) else self.intro,
            "output": self.output(ds),
            "printed": self.printed,
            "snippet": self.snippet,
            "after": self.after(ds),
            "images_heading": self.images,
        }


@dataclass
class DataSet:
    """One recorded data set: its folder ``name`` under ``docs/data`` (also its page's
    name), its `kind`, ``provenance.json`` (`prdp_petsc.lab.reports.record`), every other
    JSON file of the folder parsed (`files`, by name) and its PNG files under
    ``docs/images/<name>/`` (`images`)."""

    name: str
    kind: ReportKind
    provenance: dict = field(default_factory=dict)
    files: dict = field(default_factory=dict)
    images: list = field(default_factory=list)

    @property
    def main_file(self) -> str:
        """Name of the JSON file the page is made from."""
        return next(name for name in self.files if self.kind.matches(name))

    @property
    def main(self) -> dict:
        """The JSON file the page is made from, parsed."""
        return self.files[self.main_file]


def text_table(header: Sequence[str], rows: Iterable[Sequence]) -> str:
    """A plain-text table (pandas `DataFrame.to_string`) of `rows`, sequences of cells
    written as they are, under `header`: what a command prints."""
    import pandas as pd

    cells = [[str(cell) for cell in row] for row in rows]
    if not cells:
        return "  ".join(header)
    return pd.DataFrame(cells, columns=list(header)).to_string(index=False)


def percent(value: float) -> str:
    """``0.4567`` -> ``45.7 %``."""
    return f"{100 * value:.1f} %"


def markdown_table(header: Sequence[str], rows: Iterable[Sequence], align: str = "") -> str:
    """A Markdown table (pandas `DataFrame.to_markdown`): `header`, then one line per row
    of `rows` (sequences of cells, written as they are); `align` has one letter per
    column, ``l`` (the default) or ``r``."""
    import pandas as pd

    cells = [[str(cell) for cell in row] for row in rows]
    sides = ["right" if a == "r" else "left" for a in align.ljust(len(header), "l")]
    frame = pd.DataFrame(cells, columns=list(header))
    return frame.to_markdown(index=False, disable_numparse=True, colalign=sides)
