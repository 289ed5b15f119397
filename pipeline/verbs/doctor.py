"""``icrowdnav doctor PATH``: check a recording directory (MCAP episodes) or a LeRobot dataset.

::

    icrowdnav doctor data/raw/expert                          # MCAP logs: CRCs, topics, timing, partials
    icrowdnav doctor data/raw/expert --recover                # salvage *.mcap.partial first
    icrowdnav doctor data/datasets/icrowdnav/expert           # LeRobot dataset: footers, indices, videos, stats

One line per problem naming the file; exit 1 on any problem, 0 when clean, 2 on bad input.
"""

from __future__ import annotations

import sys
from pathlib import Path

from recorder.doctor_dataset import main as dataset_main
from recorder.doctor_mcap import main as mcap_main


def main(argv: list[str]) -> int:
    """check a recording (MCAP episodes) or a LeRobot dataset: one line per problem naming the file"""
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0 if argv else 2
    path = Path(argv[0])
    if (path / "meta" / "info.json").is_file():
        return dataset_main(argv)
    if path.is_dir():
        return mcap_main(argv)
    print(f"error: {path} is neither a recording directory nor a LeRobot dataset (no meta/info.json)",
          file=sys.stderr)
    return 2

