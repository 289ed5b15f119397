"""Records a few tiny episodes slowly, one MCAP each: the process that the kill/signal tests stop.

::

    python -m tests.recorder.helpers_mcap OUT_DIR --episodes 3 --frame-sleep 0.03 --chunk-size 60000

Episode ``i`` uses seed ``i`` and goes to ``OUT_DIR/ep<i>.mcap``. Stdout gets one flushed line per frame,
``frame ep=<i> step=<k> durable=<n>`` (``n`` = frames already in complete chunks on disk), and per finished
episode ``finished ep=<i> frames=<n> file=<name>``, so a test can stop the process at a known point. SIGTERM /
SIGINT are turned into :class:`recorder.mcap.signals.Interrupted` by
:func:`recorder.mcap.signals.graceful_signals` (the pattern the record stage uses): the open episode is closed as ``*.mcap.partial``, a line starting with
``interrupted`` says what is complete, and the exit status is ``128 + signum``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import Writer

from recorder.drive import drive_episode
from recorder.mcap.signals import Interrupted, graceful_signals
from recorder.mcap.writer import EpisodeWriter
from sim.env import CameraConfig, SimConfig


def tiny_config() -> SimConfig:
    """2 s of hallway at 0.2 ped/m² seen by 64 x 48 cameras: 21 frames with detections, ~0.2 s to simulate."""
    return SimConfig(scene="hallway", density=0.2, max_episode_s=2.0, camera=CameraConfig(width_px=64, height_px=48))


def record_episode(path: Path, seed: int, chunk_size: int = 60_000, compression: str = "zstd",
                   frame_sleep_s: float = 0.0, verbose: bool = False) -> EpisodeWriter:
    """Drives the tiny episode of ``seed`` and writes it to ``path`` (returns the finished writer)."""
    ep = drive_episode(tiny_config(), seed)
    with EpisodeWriter(path, ep.meta, ep.occupancy, chunk_size=chunk_size, compression=compression) as w:
        for fr in ep.frames:
            w.add(fr)
            if verbose:
                print(f"frame ep={path.stem[2:]} step={fr.step} durable={w.frames_durable}", flush=True)
            if frame_sleep_s:
                time.sleep(frame_sleep_s)
    return w


def rewrite(src: Path, dst: Path, keep: Callable[[str, int], bool] = lambda topic, t: True, metadata: bool = True,
            chunk_size: int = 1 << 20) -> None:
    """Copies an MCAP message by message with the plain mcap Writer (its own chunking: chunks may end inside a
    frame), keeping the messages for which ``keep(topic, log_time)`` holds."""
    with open(src, "rb") as f, open(dst, "wb") as g:
        r = make_reader(f)
        summ = r.get_summary()
        w = Writer(g, chunk_size=chunk_size)
        w.start()
        if metadata:
            for m in r.iter_metadata():
                w.add_metadata(m.name, m.metadata)
        sid = {k: w.register_schema(s.name, s.encoding, s.data) for k, s in sorted(summ.schemas.items())}
        cid = {k: w.register_channel(c.topic, c.message_encoding, sid[c.schema_id], c.metadata)
               for k, c in sorted(summ.channels.items())}
        for _, ch, m in r.iter_messages(log_time_order=False):
            if keep(ch.topic, m.log_time):
                w.add_message(cid[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence)
        w.finish()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.recorder.helpers_mcap")
    ap.add_argument("out", type=Path)
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--frame-sleep", type=float, default=0.03)
    ap.add_argument("--chunk-size", type=int, default=60_000)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    finished: list[str] = []
    current = ""
    try:
        with graceful_signals():
            for i in range(args.episodes):
                current = f"ep{i}.mcap"
                w = record_episode(args.out / current, i, args.chunk_size, frame_sleep_s=args.frame_sleep,
                                   verbose=True)
                finished.append(current)
                print(f"finished ep={i} frames={w.n_frames} file={current}", flush=True)
    except Interrupted as e:
        partial = sorted(p.name for p in args.out.glob("*.mcap.partial"))
        print(f"interrupted by {e.args[0].split()[-1]}: {len(finished)} episodes finished "
              f"({', '.join(finished) or 'none'}), left unfinished: {', '.join(partial) or 'none'}; exiting",
              flush=True)
        return e.exit_code
    print(f"done: {len(finished)} episodes", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
