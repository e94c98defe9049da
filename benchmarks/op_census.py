"""What an eager implementation of each pipeline must spend: the census of its operations, and their price here.

For one noisy 8-bit 8 × 400 × 400 capture (jute, 0.5 mm above the card), near light and the distant pipeline are
each run once under a ``TorchDispatchMode`` that counts every aten call and the bytes that the calls which compute
(not views: slices, selects, reshapes) read and write, grouped by the psmini function that made them. Beside the
census, in the same run: the wall time of each pipeline (best of three, one thread) and the price of eager work on
this machine, a tiny operation (dispatch alone) and an element-wise product over one capture's 8 × 400² floats.
From those two prices the script derives what the census costs at the least, calls times dispatch plus bytes at
the product's throughput: an eager floor for the same algorithm, whatever is trimmed around it. A pipeline whose
floor already exceeds a target needs fewer operations (another algorithm) or fused kernels (operations that do
several passes' work in one call), not leaner eager code.

    python benchmarks/op_census.py [--size 400] [--top 12] [--no-record]
"""

from __future__ import annotations

import argparse
import collections
import functools
import sys
from functools import partial
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import psmini  # noqa: E402
from benchmarks._ledger import append_results, best_time, table  # noqa: E402
from data_synth import make_fabric  # noqa: E402
from data_synth.rig import RigConfig, render_capture, render_card  # noqa: E402
from psmini import PhotometricStereo  # noqa: E402
from psmini.config import ReconstructionConfig  # noqa: E402

# aten operations that return views or metadata: they move no data
VIEWS = frozenset({"aten.slice", "aten.select", "aten.view", "aten.unbind", "aten.detach", "aten.expand",
                   "aten.as_strided", "aten.unsqueeze", "aten.squeeze", "aten.alias", "aten.t", "aten.permute",
                   "aten.reshape", "aten._unsafe_view", "aten.unflatten", "aten.split", "aten.chunk",
                   "aten.view_as_real", "aten.view_as_complex", "aten.transpose", "aten.sym_size"})


class Census(TorchDispatchMode):
    """Counts aten calls and the bytes of the tensors that computing calls read and write, by psmini caller."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: collections.Counter[str] = collections.Counter()
        self.bytes: collections.Counter[str] = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        caller = self._caller()
        self.calls[caller] += 1
        if str(func.overloadpacket) not in VIEWS:
            results = out if isinstance(out, (tuple, list)) else (out,)
            tensors = [x for x in (*args, *(kwargs or {}).values(), *results) if isinstance(x, torch.Tensor)]
            self.bytes[caller] += sum(x.numel() * x.element_size() for x in tensors)
        return out

    @staticmethod
    def _caller() -> str:
        frame = sys._getframe(2)
        while frame is not None:
            name = library_file(frame.f_code.co_filename)
            if name is not None and name != "_checks.py":
                return f"{name}:{frame.f_code.co_name}"
            frame = frame.f_back
        return "(outside psmini)"


#: The library's own folder, wherever this clone is: a path fragment such as "/psmini/" would also match a
#: virtual environment inside a clone named psmini (``psmini/.venv/.../torch/...``).
PACKAGE = Path(psmini.__file__).resolve().parent


@functools.cache
def library_file(filename: str) -> str | None:
    """``filename`` relative to the psmini package (``"integrate/poisson.py"``), or ``None`` outside it."""
    path = Path(filename).resolve()
    return path.relative_to(PACKAGE).as_posix() if path.is_relative_to(PACKAGE) else None


def eager_prices(size: int) -> tuple[float, float]:
    """Seconds of one tiny operation (dispatch alone) and bytes per second of an element-wise product over one
    capture's floats (two read, one written): the best of five runs of 200 and of 50 calls."""
    x, y = torch.rand(8, size, size), torch.rand(8, size, size)
    out, one = torch.empty_like(x), x[0, 0, :1]
    tiny = best_time(lambda: [torch.mul(one, 2.0) for _ in range(200)]) / 200
    product = best_time(lambda: [torch.mul(x, y, out=out) for _ in range(50)]) / 50
    return tiny, 3 * x.numel() * x.element_size() / product


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=400)
    parser.add_argument("--top", type=int, default=12, help="callers listed for near light")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    config = RigConfig(size=args.size, pixel_pitch_mm=0.025, noise=True, bit_depth=8, intensity_spread=0.05)
    card = render_card(config, 0.8)
    capture = render_capture(make_fabric("jute", size=args.size, pixel_pitch_mm=0.025, seed=0), config,
                             height_offset_mm=0.5)
    inputs = (capture.images[None], card.images[None], capture.dark[None], card.dark[None])
    tiny, throughput = eager_prices(args.size)
    rows, censuses = [], {}
    for label, solver in (("distant pipeline", "distant"), ("near light", "near")):
        model = PhotometricStereo(capture.lights, 0.025, ReconstructionConfig(solver=solver))
        with torch.no_grad():
            seconds = best_time(partial(model, *inputs, card_albedo=0.8, saturation_level=1.0), repeat=3)
            census = Census()
            with census:
                model(*inputs, card_albedo=0.8, saturation_level=1.0)
        calls, moved = sum(census.calls.values()), sum(census.bytes.values())
        floor = calls * tiny + moved / throughput
        censuses[label] = census
        rows.append([label, f"{1e3 * seconds:.1f}", f"{calls:,}", f"{moved / 1e9:.2f}", f"{1e3 * calls * tiny:.0f}",
                     f"{1e3 * moved / throughput:.0f}", f"{1e3 * floor:.0f}"])
    distant_ms = float(rows[0][1])
    rows.append(["near light at 10× the distant pipeline", f"{10 * distant_ms:.0f}", "", "", "", "", ""])
    report = table(["pipeline", "ms (best of 3)", "aten calls", "GB moved", "dispatch floor (ms)",
                    "traffic floor (ms)", "eager floor (ms)"], rows)
    near = censuses["near light"]
    callers = table(["near light's caller", "aten calls", "MB moved"],
                    [[name, f"{n:,}", f"{near.bytes[name] / 1e6:.0f}"] for name, n in near.calls.most_common(args.top)])
    note = (f"One noisy 8-bit jute capture, 8 × {args.size} × {args.size}, 0.5 mm above the card, one thread. "
            f"Eager prices measured in this run: {1e6 * tiny:.1f} µs per call (a one-element product), "
            f"{throughput / 1e9:.1f} GB/s in an element-wise product over one capture. Floors: calls × that price, "
            "bytes at that throughput, and their sum: what the same operations cost at the least in eager PyTorch.")
    print(report, callers, note, sep="\n\n")
    if not args.no_record:
        append_results("Operation census (benchmarks/op_census.py)", "\n\n".join([report, callers, note]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
