"""What machine the probe ran on, as the results file records it."""

from __future__ import annotations

import os
import platform
import re

try:
    import numpy as np
except ImportError:  # the probe's main() says what to install, in one line
    np = None

from .power import _read_text


# -- device identity -----------------------------------------------------------------------------
def device_identity(provider: str, threads: int, root: str = "/") -> dict:
    import onnxruntime as ort
    cpuinfo = _read_text(os.path.join(root, "proc/cpuinfo"))
    cpu = ""
    for key in ("model name", "Model", "Hardware", "Processor", "cpu model"):
        m = re.search(rf"^{key}\s*:\s*(.+)$", cpuinfo, re.MULTILINE)
        if m:
            cpu = m.group(1).strip()
            break
    return {"host": platform.node(), "board": _read_text(os.path.join(root, "proc/device-tree/model")),
            "cpu": cpu or platform.processor() or platform.machine(), "machine": platform.machine(),
            "cores": os.cpu_count(), "system": f"{platform.system()} {platform.release()}",
            "python": platform.python_version(), "numpy": np.__version__, "onnxruntime": ort.__version__,
            "provider": provider, "threads": threads}

