"""Concurrent psmini processes on a small machine: do they share the cores, or stall each other?

Two workloads, each run by three processes: bilateral integration of DiLiGenT_depth/cat's ground-truth normals
(612 × 512, perspective) and near light on one noisy 8-bit 8 × 400² jute capture of the simulated rig. Each is
run under three thread policies:

- ``torch default``: torch imported first, OpenMP's default wait policy (idle threads spin), a thread per core;
- ``psmini``: what every ``psmini`` command does: psmini imported first, which makes OpenMP's idle threads sleep
  (``OMP_WAIT_POLICY=PASSIVE``), then one thread per idle core (``psmini.threads.choose_threads``, see
  :mod:`psmini.threads`);
- ``one thread``: ``OMP_NUM_THREADS=1``, torch's default wait policy.

For each: the three processes one after another (each timing its own compute: loading and imports excluded), then
the three started together (each waits for a common start time). The criterion of issue 48: each concurrent
process finishes within twice the time the same total work takes one after another (``concurrent / serial``
≤ 2). Timings depend on what else runs on the machine; the ratios come from the same minute.

    python benchmarks/concurrency.py [ROOT] [--processes 3] [--workloads bilateral,near] [--no-record]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

POLICIES = {
    "torch default": {"first": "torch", "env": {}},
    "psmini": {"first": "psmini", "env": {}},
    "one thread": {"first": "torch", "env": {"OMP_NUM_THREADS": "1"}},
}


def child(workload: str, data: Path, first: str, start_at: float) -> dict[str, float]:
    """Import in the policy's order, load the workload, wait for ``start_at``, time one run."""
    if first == "torch":
        import torch  # noqa: F401  (before psmini: OpenMP keeps its default wait policy)
    else:
        import psmini  # (before torch: psmini asks OpenMP's idle threads to sleep)

        psmini.threads.choose_threads()  # as the commands do: one thread per idle core
    import numpy as np
    import torch

    if workload == "bilateral":
        from psmini.integrate import integrate_normals
        from psmini.io.images import read_image_raw

        folder = data / "DiLiGenT_depth" / "cat"
        pixels, bits = read_image_raw(folder / "normal_map.png")
        normals = torch.from_numpy(pixels.astype(np.float32) / (2**bits - 1) * 2 - 1).permute(2, 0, 1)[None]
        normals = normals / normals.norm(dim=1, keepdim=True).clamp_min(1e-8)
        mask_pixels, _ = read_image_raw(folder / "mask.png")
        mask = torch.from_numpy((mask_pixels.reshape(*mask_pixels.shape[:2], -1) > 0).any(-1))[None, None]
        intrinsics = torch.from_numpy(np.loadtxt(folder / "K.txt")).float()

        def run() -> None:
            integrate_normals(normals, "bilateral", mask, intrinsics=intrinsics)
    else:
        from psmini import PhotometricStereo
        from psmini.config import ReconstructionConfig
        from psmini.lights import lights_from_dict

        saved = torch.load(data, weights_only=True)
        lights = lights_from_dict(json.loads(bytes(saved["lights"].tolist()).decode()))
        model = PhotometricStereo(lights, 0.025, ReconstructionConfig(solver="near"))

        def run() -> None:
            model(saved["images"], saved["card"], saved["dark"], saved["card_dark"], card_albedo=0.8,
                  saturation_level=1.0)

    while time.time() < start_at:
        time.sleep(0.002)
    start, cpu = time.perf_counter(), time.process_time()
    with torch.no_grad():
        run()
    return {"wall": time.perf_counter() - start, "cpu": time.process_time() - cpu, "threads": torch.get_num_threads(),
            "wait_policy": os.environ.get("OMP_WAIT_POLICY", "(default)")}


def launch(workload: str, data: Path, policy: str, count: int, together: bool) -> list[dict[str, float]]:
    """``count`` child processes of ``policy``, started together or one after another."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}
    env.update(POLICIES[policy]["env"])
    lead = 8.0  # seconds for the children to import and load before the common start

    def command(start_at: float) -> list[str]:
        return [sys.executable, __file__, "--child", workload, "--data", str(data), "--first",
                POLICIES[policy]["first"], "--start-at", str(start_at)]

    if together:
        start_at = time.time() + lead
        procs = [subprocess.Popen(command(start_at), stdout=subprocess.PIPE, text=True, env=env) for _ in range(count)]
        outputs = [p.communicate()[0] for p in procs]
    else:
        outputs = [subprocess.run(command(0.0), stdout=subprocess.PIPE, text=True, env=env, check=True).stdout
                   for _ in range(count)]
    return [json.loads(out.strip().splitlines()[-1]) for out in outputs]


def render_near_capture(path: Path) -> None:
    """One noisy 8-bit jute capture 0.5 mm above the card, its card and the LEDs, saved for the children."""
    import torch

    from data_synth import make_fabric
    from data_synth.rig import RigConfig, render_capture, render_card
    from psmini.lights import lights_to_dict

    config = RigConfig(size=400, pixel_pitch_mm=0.025, noise=True, bit_depth=8)
    card = render_card(config, 0.8)
    capture = render_capture(make_fabric("jute", size=400, pixel_pitch_mm=0.025, seed=0), config,
                             height_offset_mm=0.5)
    lights = torch.tensor(list(json.dumps(lights_to_dict(capture.lights)).encode()), dtype=torch.uint8)
    torch.save({"images": capture.images[None], "dark": capture.dark[None], "card": card.images[None],
                "card_dark": card.dark[None], "lights": lights}, path)


def main(argv: list[str] | None = None) -> int:
    from benchmarks._ledger import SHARED_DATA

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", nargs="?", type=Path, default=SHARED_DATA, help="the shared data folder")
    parser.add_argument("--processes", type=int, default=3)
    parser.add_argument("--workloads", default="bilateral,near")
    parser.add_argument("--policies", default=",".join(POLICIES))
    parser.add_argument("--no-record", action="store_true")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--data", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--first", help=argparse.SUPPRESS)
    parser.add_argument("--start-at", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child, args.data, args.first, args.start_at)))
        return 0

    from benchmarks._ledger import append_results, table

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        capture = Path(tmp) / "jute.pt"
        for workload in args.workloads.split(","):
            if workload == "bilateral" and not (args.root / "DiLiGenT_depth" / "cat" / "K.txt").is_file():
                print(f"skipping bilateral: {args.root}/DiLiGenT_depth/cat is absent")
                continue
            if workload == "near" and not capture.exists():
                render_near_capture(capture)
            data = args.root if workload == "bilateral" else capture
            for policy in args.policies.split(","):
                serial = launch(workload, data, policy, args.processes, together=False)
                together = launch(workload, data, policy, args.processes, together=True)
                total = sum(r["wall"] for r in serial)
                slowest = max(r["wall"] for r in together)
                rows.append([workload, policy, together[0]["threads"], min(r["wall"] for r in serial), total,
                             ", ".join(f"{r['wall']:.2f}" for r in together), f"{slowest / total:.2f}",
                             "yes" if slowest <= 2 * total else "no"])
                print(table(["workload", "policy", "threads", "alone (s)", "one after another (s)",
                             "together, each (s)", "slowest / serial", "≤ 2"], rows[-1:]), flush=True)
    report = table(["workload", "policy", "threads", "alone (s)", f"{args.processes} one after another (s)",
                    f"{args.processes} together, each (s)", "slowest together / serial total", "≤ 2"], rows)
    note = (f"{args.processes} processes per workload and policy, one after another then started together; each "
            f"times its own compute (imports and loading excluded). bilateral: DiLiGenT_depth/cat ground-truth "
            f"normals, perspective; near: near light on a noisy 8-bit 8 × 400² jute capture. The machine's other "
            f"load is whatever ran in the same minute.")
    print(report)
    print(note)
    if not args.no_record:
        append_results("Concurrent processes (benchmarks/concurrency.py)", report + "\n\n" + note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
