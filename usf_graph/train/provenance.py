"""Where a result came from: the code, the libraries, the command and the machine.

Every checkpoint and ``results.json`` carries it under ``"provenance"``, so a number in a
paper can be traced to the commit and the command that made it, and ``usf-graph eval``
says when a checkpoint was made by other code than the one scoring it.
"""

from __future__ import annotations

import functools
import platform
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path


@functools.lru_cache(maxsize=1)
def git_state() -> dict | None:
    """``{"commit": sha, "dirty": bool}`` of the git checkout usf-graph runs from (dirty:
    tracked files changed since the commit), or None outside one (an installed wheel)."""
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return None
    try:
        run = functools.partial(subprocess.run, cwd=root, capture_output=True, text=True,
                                timeout=10, check=True)
        sha = run(["git", "rev-parse", "HEAD"]).stdout.strip()
        dirty = bool(run(["git", "status", "--porcelain", "--untracked-files=no"]).stdout.strip())
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": sha, "dirty": dirty}


def provenance() -> dict:
    """What made a result, now: usf-graph's version and git state, the Python, torch, PyG
    and numpy versions, the command line, torch's threads and CUDA device, and the UTC
    time."""
    import numpy
    import torch
    import torch_geometric

    from .. import __version__

    cuda = torch.cuda.get_device_name() if torch.cuda.is_available() else None
    argv = [Path(sys.argv[0]).name] + sys.argv[1:] if sys.argv and sys.argv[0] else []
    return {"usf_graph": __version__, "git": git_state(), "python": platform.python_version(),
            "torch": str(torch.__version__), "torch_geometric": str(torch_geometric.__version__),
            "numpy": str(numpy.__version__), "command": shlex.join(argv),
            "threads": torch.get_num_threads(), "cuda": cuda,
            "time": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def describe(prov: dict | None) -> str:
    """One line for people: ``usf-graph V (commit abc1234[, changed]) on DATE: COMMAND``."""
    if not prov:
        return "no provenance recorded (made before session 51)"
    git = prov.get("git")
    code = f"usf-graph {prov.get('usf_graph', '?')}" + (
        f" (commit {git['commit'][:10]}{', with uncommitted changes' if git['dirty'] else ''})"
        if git else "")
    return f"{code}, {prov.get('time', '?')}: {prov.get('command') or '?'}"


def differs(prov: dict | None) -> str | None:
    """Why the running code is not the code that made a result with provenance ``prov``
    (another version or commit), or None when it is the same (or unknown)."""
    if not prov:
        return None
    from .. import __version__

    now, then = git_state(), prov.get("git")
    if now and then and now["commit"] != then["commit"]:
        return f"made at commit {then['commit'][:10]}, scored at {now['commit'][:10]}"
    if prov.get("usf_graph") not in (None, __version__):
        return f"made by usf-graph {prov['usf_graph']}, scored by {__version__}"
    return None


def announce(path, prov: dict | None) -> None:
    """Print what made the checkpoint at ``path`` and, where the running code differs, a
    note that its numbers may not be reproduced."""
    print(f"{path}: {describe(prov)}")
    why = differs(prov)
    if why:
        print(f"note: {path} was {why}; its recorded numbers may not be reproduced exactly")
