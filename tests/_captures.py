"""A folder tree of synthetic captures shared by the batch tests (local and Dask)."""

from __future__ import annotations

from pathlib import Path

from data_synth.rig import write_synthetic_capture
from psmini.config import ReconstructionConfig

# The batch machinery is what these tests exercise: the fast classical solver (near light, the default for these
# LED captures, has its own tests and costs seconds per sample on a CPU)
DISTANT = ReconstructionConfig(solver="distant")

# the good captures of :func:`write_capture_tree`, relative to its root
GOOD = ["lotA/jute", "lotA/twill", "lotB/cotton"]


def write_capture_tree(root: Path, size: int) -> Path:
    """Two calibrations (lotA: two fabrics under one card, lotB: one) and a capture with a truncated image."""
    for seed, fabric in enumerate(["jute", "twill"]):
        write_synthetic_capture(root / "lotA", fabric, size=size, seed=seed)  # one card, kept
    write_synthetic_capture(root / "lotB", "cotton", size=size, seed=5)
    write_synthetic_capture(root / "lotC", "jute", size=size, seed=7)
    (root / "lotC" / "jute").rename(root / "lotC" / "broken")
    image = root / "lotC" / "broken" / "led_03.png"
    image.write_bytes(image.read_bytes()[:100])
    return root
