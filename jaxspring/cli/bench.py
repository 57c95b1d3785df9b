"""`jaxspring bench`: speed and accuracy benchmarks."""

from __future__ import annotations

import sys
from pathlib import Path


def add_parser(sub):
    parser = sub.add_parser("bench", help="benchmarks: speed against peers; speed against error of every integrator")
    parser.add_argument(
        "kind",
        choices=["speed", "accuracy"],
        help="speed: steps/s, gradient cost, compile time, memory, batches, against peers (float32); "
        "accuracy: dt sweep against float64 references",
    )
    parser.add_argument("--scenes", help="accuracy: comma-separated scenes (default: the four seed scenes)")
    parser.add_argument("--peers", default="jax_segment_sum,numpy,warp", help="speed: peers to measure")
    parser.add_argument("--quick", action="store_true", help="small workloads and short horizons (a smoke run)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per configuration; the median counts")
    parser.add_argument("--out-dir", default="bench_results", help="folder for the CSV, table and plot")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def command(args):
    if args.kind == "speed":
        return _bench_speed(args)
    return _bench_accuracy(args)


def _bench_folder(args) -> Path:
    from ..errors import InputError

    if args.repeats < 1:
        raise InputError("--repeats", f"must be >= 1, got {args.repeats}", "time at least one run")
    out = Path(args.out_dir)
    if not out.is_dir():
        if out.exists() or not out.parent.is_dir():
            raise InputError("--out-dir", f"cannot create folder {str(out)!r}", "choose a folder")
        out.mkdir()
    return out


def _bench_speed(args):
    import jax

    from ..bench import peers as _peers
    from ..bench import speed as _speed
    from ..errors import InputError

    peers = [p.strip() for p in args.peers.split(",") if p.strip()]
    for peer in peers:
        if peer not in ("jax_segment_sum", "numpy", "warp"):
            raise InputError("--peers", f"unknown peer {peer!r}", "use some of jax_segment_sum, numpy, warp")
    if "warp" in peers and not _peers.warp_available():
        print("jaxspring: notice: warp-lang is not installed; skipping the Warp peer", file=sys.stderr)
    out = _bench_folder(args)

    def progress(row):
        if not args.quiet:
            extra = f"  grad/fwd {row.gradient_ratio:.2f}" if row.implementation.startswith("jaxspring") else ""
            print(
                f"{row.workload:14s} {row.implementation:16s} {row.steps_per_second:12,.1f} steps/s"
                f"  {row.ns_per_spring_step:8.2f} ns/spring-step{extra}",
                file=sys.stderr,
                flush=True,
            )

    x64 = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", False)  # speed is measured in float32
    try:
        rows = _speed.sweep(quick=args.quick, repeats=args.repeats, peers=peers, progress=progress)
    finally:
        jax.config.update("jax_enable_x64", x64)
    _speed.write_csv(rows, out / "speed.csv")
    table = _speed.markdown(rows) + f"\nPeak process memory: {_speed.peak_rss_mib():.0f} MiB.\n"
    (out / "speed.md").write_text(table)
    _speed.plot(rows, out / "speed.png")
    print(table)
    print(f"wrote {out / 'speed.csv'}, {out / 'speed.md'}, {out / 'speed.png'}")


def _bench_accuracy(args):
    from ..bench import accuracy as _accuracy
    from ..errors import InputError

    table = _accuracy.QUICK_SWEEPS if args.quick else _accuracy.SWEEPS
    names = [n.strip() for n in args.scenes.split(",")] if args.scenes else list(table)
    for name in names:
        if name not in table:
            raise InputError("--scenes", f"no accuracy sweep for {name!r}", f"use some of {', '.join(table)}")
    out = _bench_folder(args)

    def progress(row):
        if not args.quiet:
            print(
                f"{row.scene:12s} {row.integrator:20s} dt {row.dt:9.3g}  {row.seconds_per_simulated_second:9.3g} s/s"
                f"  error {row.error:9.2e}  energy error {row.energy_error:9.2e}  {'stable' if row.stable else 'UNSTABLE'}",
                file=sys.stderr,
                flush=True,
            )

    rows = _accuracy.sweep(names, quick=args.quick, repeats=args.repeats, progress=progress)
    _accuracy.write_csv(rows, out / "accuracy.csv")
    (out / "accuracy.md").write_text(_accuracy.markdown(rows))
    _accuracy.plot(rows, out / "accuracy.png")
    print(_accuracy.markdown(rows))
    print(f"wrote {out / 'accuracy.csv'}, {out / 'accuracy.md'}, {out / 'accuracy.png'}")
