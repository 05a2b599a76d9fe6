"""What a benchmark's JSON says about where it ran: one function for the scripts that write it the same way."""
from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = ["alternating", "base_revision", "bootstrap", "provenance", "write_result"]


def provenance(script: str) -> dict:
    """{"date", "machine", "command", "commit"} of this run of benchmarks/`script` (its arguments from sys.argv)."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    return {"date": datetime.date.today().isoformat(),
            "machine": f"{platform.node()} ({os.cpu_count()} CPUs, {platform.machine()})",
            "command": f"benchmarks/{script} " + " ".join(sys.argv[1:]), "commit": commit}


def base_revision(python: str | None) -> str | None:
    """The short commit of the checkout whose `lodcast` the Python `python` imports (another worktree's virtual
    environment, the "base" of an A/B), or None without one."""
    if not python:
        return None
    root = subprocess.run([python, "-c", "import lodcast, pathlib; print(pathlib.Path(lodcast.__file__).resolve()"
                           ".parent.parent)"], capture_output=True, text=True, cwd="/").stdout.strip()
    return subprocess.run(["git", "-C", root, "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()


def bootstrap(ratios: np.ndarray, n: int = 4000, seed: int = 0) -> tuple[float, float]:
    """The 95 % interval of the median of `ratios`, resampled with replacement."""
    rng = np.random.default_rng(seed)
    meds = np.median(rng.choice(ratios, (n, ratios.size)), axis=1)
    return float(np.percentile(meds, 2.5)), float(np.percentile(meds, 97.5))


def write_result(path: Path, res: dict, indent: int = 2) -> None:
    """`res` as JSON at `path` and, where it has one, its "table" beside it (.md), printed first."""
    if "table" in res:
        print(res["table"])
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=indent))
    if "table" in res:
        path.with_suffix(".md").write_text(res["table"] + "\n")
    print(f"wrote {path}")


def alternating(pairs: int, run: Callable[[str], dict], base: bool) -> list[dict]:
    """`pairs` pairs of `run("base")` and `run("new")`, the order alternating (the base first in even pairs), each
    pair printed as it ends: its results by who ran, its order and the load average as its runs started. Without a
    base only "new" runs."""
    out = []
    for i in range(pairs):
        order = ["base", "new"] if i % 2 == 0 else ["new", "base"]
        got: dict = {"order": "/".join(order)}
        loads = []
        for who in order:
            if who == "base" and not base:
                continue
            loads.append(os.getloadavg()[0])
            got[who] = run(who)
        got["load"] = float(np.mean(loads))
        out.append(got)
        print(json.dumps(got), flush=True)
    return out
