"""The probe as one file: a zip application (``python3 probe.pyz``) holding this package, which needs
nothing but Python 3, numpy and onnxruntime on the device."""

from __future__ import annotations

import zipfile
from pathlib import Path

MAIN = "import sys\n\nfrom probe.run import main\n\nsys.exit(main())\n"


def write_zipapp(dst: Path) -> Path:
    """Writes ``dst`` (e.g. ``probe.pyz``): this package's modules as the top-level package ``probe``
    and a ``__main__.py`` that runs its command line."""
    here = Path(__file__).resolve().parent
    with zipfile.ZipFile(dst, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("__main__.py", MAIN)
        for src in sorted(here.glob("*.py")):
            zf.write(src, f"probe/{src.name}")
    return Path(dst)
