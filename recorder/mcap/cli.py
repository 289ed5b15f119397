"""Per-episode MCAP logs from the command line: salvage, summary, measurement.

::

    python -m recorder.mcap.cli recover data/raw/expert/hallway_d0.1_s3.mcap.partial
    python -m recorder.mcap.cli summary data/raw/expert/hallway_d0.1_s3.mcap
    python -m recorder.mcap.cli bench                       # the chunking/compression measurement (bench.py)
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

from pipeline.core.errors import reports_errors
from recorder.mcap.bench import benchmark_writer
from recorder.mcap.reader import count_frames, episode_summary
from recorder.mcap.recovery import recover


@reports_errors
def main(argv: list[str] | None = None) -> int:
    """``python -m recorder.mcap.cli {recover FILE | summary FILE | bench [--scene S --seconds T]}``."""
    ap = argparse.ArgumentParser(prog="python -m recorder.mcap.cli", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("recover", help="salvage the complete frames of a *.mcap.partial").add_argument("file", type=Path)
    sub.add_parser("summary", help="print a CRC-checked summary of an episode").add_argument("file", type=Path)
    b = sub.add_parser("bench", help="measure MCAP writing per compression and chunk size")
    b.add_argument("--scene", default="office_lobby")
    b.add_argument("--density", type=float, default=0.1)
    b.add_argument("--seconds", type=float, default=10.0)
    b.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.cmd == "recover":
        out = recover(args.file)
        print(f"recovered {count_frames(out)} frames into {out}")
    elif args.cmd == "summary":
        print(json.dumps(episode_summary(args.file), indent=2))
    else:
        # imported late: the simulator (pybullet) is only needed to measure, not to recover or summarise
        from recorder.drive import drive_episode  # lazy: the simulator, only for the bench subcommand
        from sim.env import SimConfig  # lazy: the simulator, only for the bench subcommand

        t0 = time.perf_counter()
        ep = drive_episode(SimConfig(scene=args.scene, density=args.density, max_episode_s=args.seconds), 0)
        frames = list(ep.frames)
        sim_ms = 1e3 * (time.perf_counter() - t0) / len(frames)
        with tempfile.TemporaryDirectory() as d:
            rows = benchmark_writer(frames, ep.meta, ep.occupancy, Path(d),
                                    [(c, s) for c in ("zstd", "lz4", "none") for s in (1 << 20, 4 << 20)],
                                    repeats=args.repeats)
        print(f"sim+render: {sim_ms:.1f} ms/frame over {len(frames)} frames")
        for r in rows:
            print(f"{r['compression']:5s} {r['chunk_size'] >> 20} MiB  {r['ms_per_frame']:6.2f} ms/frame  "
                  f"{r['kb_per_frame']:7.1f} kB/frame (raw {r['raw_kb_per_frame']} kB)  "
                  f"{100 * r['ms_per_frame'] / sim_ms:4.1f} % of sim+render, "
                  f"{100 * r['ms_per_frame'] / 20.0:4.1f} % of 20 ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
