"""Doctor for a directory of episode MCAPs: one line per problem, naming the file.

::

    python -m recorder.doctor_mcap data/raw/expert              # exit 0 and "ok: N episodes, M frames", or 1
    python -m recorder.doctor_mcap data/raw/expert --recover    # also salvage every *.mcap.partial first

Checks (see :func:`check_mcap_dir`): unfinished ``*.mcap.partial`` files, files that do not open or fail a CRC
check, missing ``episode`` metadata, frames that miss topics, log times that are not 0, dt, 2 dt, ..., steps
that are not 0..N-1, and episodes that do not end with ``done=True`` (or end earlier).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from pipeline.core.artifacts import stale_atomic_temps
from pipeline.core.errors import ICrowdNavError, InputMissingError, reports_errors
from recorder.mcap.layout import (
    METADATA_ABORTED,
    METADATA_RECOVERY,
    PARTIAL_SUFFIX,
    dt_ns_of,
    recovered_path_of,
)
from recorder.mcap.reader import EpisodeScan, count_frames, scan_episode
from recorder.mcap.recovery import recover
from recorder.schema import METADATA_EPISODE

log = logging.getLogger("icrowdnav")


def _episode_problems(scan: EpisodeScan) -> list[str]:
    """Problems of one scanned episode file, one line each (each line starts with the file path)."""
    p = scan.path
    out: list[str] = []
    if scan.meta is None:
        where = "missing" if METADATA_EPISODE not in scan.metadata_names else "malformed"
        out.append(f"{p}: '{METADATA_EPISODE}' metadata record {where} (not an episode log of recorder.mcap)")
    n = scan.n_frames
    if n == 0:
        out.append(f"{p}: no frames")
        return out
    if scan.missing:
        t, topics = scan.missing[0]
        out.append(f"{p}: {len(scan.missing)} of {n} frames miss topics (first at t={t / 1e9:.3f} s: "
                   f"{', '.join(topics)})")
    if scan.meta is not None:
        dt = dt_ns_of(scan.meta)
        bad = [k for k, t in enumerate(scan.log_times) if t != k * dt]
        if bad:
            k = bad[0]
            prev = f"{scan.log_times[k - 1] / 1e9:.3f} s" if k else "start"
            out.append(f"{p}: {len(bad)} frames off the dt={dt / 1e6:g} ms grid (frame {k} at "
                       f"t={scan.log_times[k] / 1e9:.3f} s after {prev}, expected {k * dt / 1e9:.3f} s)")
    bad_steps = [k for k, s in enumerate(scan.steps) if s != k]
    if bad_steps:
        k = bad_steps[0]
        out.append(f"{p}: frame count {n} does not match the steps: frame {k} has step {scan.steps[k]} "
                   f"(expected steps 0..{n - 1})")
    early = [k for k, d in enumerate(scan.done[:-1]) if d]
    if early:
        out.append(f"{p}: done=True already at frame {early[0]} of {n} (frames follow the end of the episode)")
    if not scan.done[-1]:
        why = (" (an aborted recording)" if METADATA_ABORTED in scan.metadata_names
               else " (a recovered, cut-short episode)" if METADATA_RECOVERY in scan.metadata_names else "")
        out.append(f"{p}: episode does not end with done=True (last frame {n - 1}, "
                   f"t={scan.log_times[-1] / 1e9:.3f} s){why}")
    return out


def check_mcap_dir(directory: Path) -> list[str]:
    """Checks every episode MCAP in ``directory`` (not recursive).

    Args:
        directory: A recording directory holding ``*.mcap`` (and maybe ``*.mcap.partial``) files.

    Returns:
        One line per problem, each starting with the file it is about; empty when everything is fine.

    Raises:
        InputMissingError: ``directory`` does not exist or is not a directory.
    """
    d = Path(directory)
    if not d.is_dir():
        raise InputMissingError(f"missing MCAP directory: {d}")
    problems: list[str] = []
    for p in sorted(d.glob(f"*.mcap{PARTIAL_SUFFIX}")):
        rec = recovered_path_of(p)
        final = p.with_name(p.name[: -len(PARTIAL_SUFFIX)])
        if final.exists() and final.samefile(p):
            problems.append(f"{p}: second name of the finished {final.name} (a crash while publishing it); delete "
                            f"the .partial")
        elif rec.exists():
            problems.append(f"{p}: unfinished episode, already recovered into {rec.name}; delete the .partial "
                            f"once {rec.name} is checked")
        else:
            problems.append(f"{p}: unfinished episode (the recording was killed or interrupted); salvage its "
                            f"complete frames with `python -m recorder.doctor_mcap {d} --recover` "
                            f"(writes {rec.name}) or delete it")
    for p in sorted({*d.glob(".*.tmp-*"), *stale_atomic_temps(d, recursive=False)}):
        problems.append(f"{p}: leftover temporary file of an interrupted write; delete it")
    for p in sorted(d.glob("*.mcap")):
        try:
            scan = scan_episode(p)
        except ICrowdNavError as e:
            problems.append(str(e) if str(p) in str(e) else f"{p}: {e}")
            continue
        problems.extend(_episode_problems(scan))
    return problems


def recover_dir(directory: Path) -> list[str]:
    """Runs :func:`recorder.mcap.recovery.recover` on every ``*.mcap.partial`` without a recovered sibling.

    Returns:
        One line per file: what was salvaged, or why nothing could be.
    """
    lines = []
    for p in sorted(Path(directory).glob(f"*.mcap{PARTIAL_SUFFIX}")):
        if recovered_path_of(p).exists():
            continue
        try:
            out = recover(p)
            lines.append(f"{p}: recovered {count_frames(out)} complete frames into {out.name}")
        except ICrowdNavError as e:
            lines.append(str(e) if str(p) in str(e) else f"{p}: {e}")
    return lines


@reports_errors
def main(argv: list[str] | None = None) -> int:
    """CLI: print problems (exit 1) or ``ok: N episodes, M frames`` (exit 0); bad arguments exit 2."""
    ap = argparse.ArgumentParser(prog="python -m recorder.doctor_mcap", description=__doc__.split("\n")[0])
    ap.add_argument("directory", type=Path, help="directory of episode MCAPs")
    ap.add_argument("--recover", action="store_true", help="salvage every *.mcap.partial first")
    args = ap.parse_args(argv)
    if args.recover:
        if not args.directory.is_dir():
            raise InputMissingError(f"missing MCAP directory: {args.directory}")
        for line in recover_dir(args.directory):
            print(line)
    problems = check_mcap_dir(args.directory)
    if problems:
        for line in problems:
            print(line)
        print(f"{len(problems)} problem(s) in {args.directory}", file=sys.stderr)
        return 1
    files = sorted(args.directory.glob("*.mcap"))
    frames = sum(count_frames(p) for p in files)
    print(f"ok: {len(files)} episodes, {frames} frames")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
