"""What every benchmark shares: the machine, the commit, timing, a markdown table, the results ledger."""

from __future__ import annotations

import datetime
import platform
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results.md"
SHARED_DATA = REPO.parent / "shared" / "data"


def commit() -> str:
    """Short hash of HEAD, with ``+dirty`` when the code that makes the figures (psmini, data_synth, the benchmark
    scripts) has uncommitted changes."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              check=True)
        # what a benchmark writes does not count (the ledger, a fitted model, a figure, a JSON result): a run that
        # rewrites its own outputs before appending to the ledger is still a run of HEAD's code
        dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", "psmini", "data_synth",
                                ":(glob)benchmarks/*.py"], cwd=REPO).returncode
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head.stdout.strip() + ("+dirty" if dirty else "")


def machine(device: torch.device | str = "cpu") -> str:
    """One line naming the machine: CPU model and cores, or the GPU."""
    if torch.device(device).type == "cuda":
        return f"{torch.cuda.get_device_name(device)} (CUDA {torch.version.cuda})"
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {torch.get_num_threads()} threads, torch {torch.__version__}"


def best_time(func: Callable[[], object], repeat: int = 5, warmup: int = 1, device: str = "cpu") -> float:
    """Best wall time of ``func`` in seconds over ``repeat`` runs (after ``warmup``), synchronising CUDA."""
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    for _ in range(warmup):
        func()
    sync()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        sync()
        times.append(time.perf_counter() - start)
    return min(times)


def table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A markdown table; floats printed with 4 significant digits."""

    def cell(value: object) -> str:
        return f"{value:.4g}" if isinstance(value, float) else str(value)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def append_results(title: str, body: str, device: torch.device | str = "cpu") -> None:
    """Append a dated section (commit, machine, body) to ``benchmarks/results.md``."""
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    section = f"\n## {title}\n\n{stamp} · commit `{commit()}` · {machine(device)}\n\n{body.strip()}\n"
    if not RESULTS.exists():
        RESULTS.write_text("# Benchmark results\n\nEach section is appended by a script in `benchmarks/`.\n")
    with RESULTS.open("a") as ledger:
        ledger.write(section)
