"""What a process costs: its resident memory."""

from __future__ import annotations

import resource
import sys
from pathlib import Path


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far [MiB] (getrusage; kB on Linux,
    bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    per_mb = 1024.0 * 1024.0 if sys.platform == "darwin" else 1024.0
    return float(peak) / per_mb


def rss_mb(pid: int | None = None) -> float:
    """Current resident set size of a process (this one by default) [MiB], from Linux's
    /proc; 0 where that is not available."""
    try:
        status = Path(f"/proc/{pid or 'self'}/status").read_text()
    except OSError:
        return 0.0
    for line in status.splitlines():
        if line.startswith("VmRSS:"):
            return float(line.split()[1]) / 1024.0
    return 0.0
