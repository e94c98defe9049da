"""``psmini rig info --port URL``: what the LED controller on a port says about itself."""

from __future__ import annotations

import argparse
import statistics
import time

from psmini.commands._common import add_json_flag, emit_json


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "rig",
        help="talk to the rig's LED controller",
        description="Talk to the rig's LED controller (psmini-leds firmware, docs/rig-protocol.md).",
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    info = actions.add_parser(
        "info",
        help="firmware identity, state and round-trip time of the LED controller",
        description="Open the port (the board resets), wait for its READY banner, and print the firmware's identity, "
        "its state and the round-trip time of PING. The LEDs are left off.",
    )
    info.add_argument("--port", required=True, metavar="URL", help="port or pyserial URL (/dev/ttyUSB0, COM3, "
                      "psminisim://, loop://...)")
    info.add_argument("--handshake-timeout", type=float, default=3.0, help="s to wait for READY (default: 3)")
    info.add_argument("--command-timeout", type=float, default=0.5, help="s to wait for each reply (default: 0.5)")
    info.add_argument("--pings", type=int, default=10, help="PINGs timed (default: 10)")
    add_json_flag(info)
    info.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from psmini.errors import InputError
    from psmini.rig import LEDController

    if args.pings < 1:
        raise InputError(f"--pings must be at least 1, got {args.pings}")
    with LEDController(args.port, handshake_timeout_s=args.handshake_timeout,
                       command_timeout_s=args.command_timeout) as leds:
        identity = leds.identify()
        state = leds.state()
        times = []
        for _ in range(args.pings):
            start = time.perf_counter()
            leds.ping()
            times.append((time.perf_counter() - start) * 1000)
    lit = "none" if state.lit is None else "all" if state.lit == "all" else f"LED {state.lit}"
    print(f"{args.port}: {identity.name} {identity.version}, {identity.led_count} LEDs")
    print(f"  lit: {lit}; watchdog {state.watchdog_ms} ms, tripped {state.trips} times since reset")
    print(f"  PING round trip: median {statistics.median(times):.2f} ms, max {max(times):.2f} ms over {len(times)}")
    if args.json:
        emit_json({"port": args.port, "firmware": identity.name, "version": identity.version,
                   "leds": identity.led_count, "watchdog_ms": state.watchdog_ms, "watchdog_trips": state.trips,
                   "lit": state.lit, "ping_ms_median": statistics.median(times), "ping_ms_max": max(times)})
    return 0
