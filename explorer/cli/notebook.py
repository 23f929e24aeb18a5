"""``explorer notebook``: the shipped analysis notebook, copied out of the installed package into a
folder of the user's, to open with Jupyter."""

from __future__ import annotations

from pathlib import Path

from explorer.errors import UserError
from explorer.cli._common import write_output

#: the shipped notebooks, package data (the repository links them as notebooks/ at its top)
NOTEBOOKS_DIR = Path(__file__).resolve().parents[1] / "notebooks"


def copy_notebooks(out: Path, force: bool = False) -> list[tuple[Path, bool]]:
    """Writes every shipped notebook into ``out`` (made if missing); returns (path, whether it was
    written: False where an identical copy was there already). An existing different file is refused,
    one line, unless ``force``: it may hold the user's own cells and outputs."""
    shipped = sorted(NOTEBOOKS_DIR.glob("*.ipynb"))
    if not shipped:
        raise UserError(f"{NOTEBOOKS_DIR}: no notebook shipped with this installation: reinstall anytime-explorer")
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: is a file; give a folder to write the notebook into")
    targets = [(src, out / src.name) for src in shipped]
    for src, dst in targets:
        if dst.is_dir():
            raise UserError(f"{dst}: is a folder; give another --out")
        if dst.exists() and not force and dst.read_bytes() != src.read_bytes():
            raise UserError(f"{dst}: exists and differs from the shipped notebook (your edits?): pass --force to "
                            "overwrite it, or give another --out")
    written = []
    for src, dst in targets:
        same = dst.is_file() and dst.read_bytes() == src.read_bytes()
        if not same:
            write_output(dst, src.read_text(encoding="utf-8"))
        written.append((dst, not same))
    return written


def cmd_notebook(args) -> None:
    from explorer.console import console
    for path, written in copy_notebooks(Path(args.out), args.force):
        console.print(f"{'wrote' if written else 'already there, unchanged:'} {path}", markup=False, highlight=False)
        console.print(f"  open it in Jupyter (`pip install jupyterlab`, then `jupyter lab {path}`) or VS Code; it "
                      "reads the study named in its first cell, from a reports/ folder beside or above it",
                      markup=False, highlight=False)


def register(sub, add, reports: dict) -> None:
    """Adds this group's commands to the ``explorer`` parser."""
    s = add("notebook", cmd_notebook, "copy the analysis notebook (reads a study through the Python API) into a "
            "folder, to open with Jupyter")
    s.add_argument("--out", required=True, help="folder to write the notebook into (made if missing)")
    s.add_argument("--force", action="store_true", help="overwrite a notebook of the same name that differs "
                   "from the shipped one")
