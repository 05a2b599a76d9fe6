"""What a benchmark's JSON says about where it ran: one function for the scripts that write it the same way."""
from __future__ import annotations

import datetime
import os
import platform
import subprocess
import sys
from pathlib import Path

__all__ = ["provenance"]


def provenance(script: str) -> dict:
    """{"date", "machine", "command", "commit"} of this run of benchmarks/`script` (its arguments from sys.argv)."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    return {"date": datetime.date.today().isoformat(),
            "machine": f"{platform.node()} ({os.cpu_count()} CPUs, {platform.machine()})",
            "command": f"benchmarks/{script} " + " ".join(sys.argv[1:]), "commit": commit}
