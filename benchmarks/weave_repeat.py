"""The weave repeat that ``psmini describe`` reads from the default pipeline's reconstruction, on 45 captures.

Five woven fabrics of known repeat (cotton, jute and lurex: plain, 2; twill: 3; satin: 5), each at three orientations
(0°, 35°, 110°) and three crop sizes (160, 256 and 400 px at 0.025 mm, i.e. 4, 6.4 and 10 mm), the lift cycling
through 0, 0.5 and 1 mm above the card, noisy 8-bit renders of the rig, reconstructed by the default pipeline (near
light for these LED captures) and measured by :func:`psmini.fabric.fabric_structure` on the reconstruction's slopes
integrated without weights (:func:`psmini.fabric.structure_surface`, where ``describe_reconstruction`` reads it).
The fabric guide's "Known limits" quote the table. One capture per case, so a count moves by the occasional
borderline sample between runs.

Run:  python benchmarks/weave_repeat.py [--no-record]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import append_results, table  # noqa: E402

REPEATS = {"cotton": 2, "twill": 3, "satin": 5, "jute": 2, "lurex": 2}
ORIENTATIONS_DEG = (0.0, 35.0, 110.0)
SIZES_PX = (160, 256, 400)
LIFTS_MM = (0.0, 0.5, 1.0)


def measure() -> list[tuple[str, int, bool]]:
    """(fabric, size, repeat right) for every case."""
    from data_synth.rig import RigConfig, write_synthetic_capture
    from psmini.fabric import fabric_structure, structure_surface
    from psmini.io import load_sample
    from psmini.pipeline import reconstruct

    cases = []
    with tempfile.TemporaryDirectory() as folder:
        for index, (fabric, orientation, size) in enumerate(itertools.product(REPEATS, ORIENTATIONS_DEG, SIZES_PX)):
            root = Path(folder) / str(index)
            path, _ = write_synthetic_capture(root, fabric, seed=index, size=size, config=RigConfig(bit_depth=8),
                                              orientation_deg=orientation,
                                              height_offset_mm=LIFTS_MM[index % len(LIFTS_MM)])
            sample = load_sample(path)
            result = reconstruct(sample)
            pitch = float(sample.pixel_pitch_mm)
            found = fabric_structure(structure_surface(result.p, result.q, pitch, result.mask), pitch, result.mask)[0]
            cases.append((fabric, size, found.weave_repeat == REPEATS[fabric]))
    return cases


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-record", action="store_true", help="print only; do not append to results.md")
    args = parser.parse_args()
    cases = measure()
    rows = [[fabric, REPEATS[fabric], *(sum(right for f, s, right in cases if f == fabric and s == size)
                                        for size in SIZES_PX), sum(right for f, _, right in cases if f == fabric)]
            for fabric in REPEATS]
    rows.append(["**all**", "", *(sum(right for _, s, right in cases if s == size) for size in SIZES_PX),
                 sum(right for *_, right in cases)])
    report = table(["fabric", "true repeat", *(f"right at {size} px (of 3)" for size in SIZES_PX), "right (of 9)"],
                   rows)
    note = (f"{len(cases)} noisy 8-bit captures (orientations {', '.join(f'{o:g}' for o in ORIENTATIONS_DEG)}°, "
            f"lifts {', '.join(f'{h:g}' for h in LIFTS_MM)} mm in turn, seed = case index), default pipeline, "
            "weave repeat of psmini.fabric.fabric_structure where describe_reconstruction reads it: on the "
            "reconstruction's slopes integrated without weights (structure_surface).")
    print(report)
    print(note)
    if not args.no_record:
        append_results("Weave repeat from the default pipeline (benchmarks/weave_repeat.py)", report + "\n\n" + note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
