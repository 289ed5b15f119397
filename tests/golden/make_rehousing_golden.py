"""Regenerates ``tests/golden/rehousing.json``: behaviour that a re-organisation of the code must not change.

What it pins (all seeded, all on the CPU):

* the metrics rows (success, NT, PL, TPZ, min clearance, steps) of the privileged expert and of DWA on two seeded
  episodes per test scene (office lobby, hospital corridor, warehouse; 0.1 ped/m², 64 x 48 cameras, 16 s), driven
  through the benchmark's episode loop;
* the SHA-256 of one tiny MCAP episode (the recorder's writer on a driven episode) and of the parquet file the
  LeRobot export makes from the two tiny episodes.

Run it only when a behaviour change is intended, and say so in the commit::

    .venv/bin/python tests/golden/make_rehousing_golden.py
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path

GOLDEN = Path(__file__).with_name("rehousing.json")
SCENES = ("office_lobby", "hospital_corridor", "warehouse_routing")  # the shelf hall (named "warehouse" when recorded)
SEEDS = (7001, 7002)
METHODS = ("expert", "dwa")
KEYS = ("outcome", "steps", "success", "nav_time_s", "path_length_m", "tpz_s", "min_ped_clearance_m",
        "min_static_clearance_m")


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def metric_rows() -> list[dict]:
    """The expert's and DWA's rows on the golden episodes (``tests/test_golden.py`` runs the same)."""
    from tests.golden.episodes import golden_rows

    return golden_rows(SCENES, SEEDS, METHODS, KEYS)


def artifact_hashes(tmp: Path) -> dict[str, str]:
    from tests.golden.episodes import golden_artifacts

    mcap, parquets = golden_artifacts(tmp)
    listing = "".join(f"{p.relative_to(p.parents[2]).as_posix()} {sha256(p)}\n" for p in parquets)
    return {"mcap_sha256": sha256(mcap), "parquet_sha256": hashlib.sha256(listing.encode()).hexdigest()}


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        golden = {"rows": metric_rows(), **artifact_hashes(Path(tmp))}
    GOLDEN.write_text(json.dumps(golden, indent=1) + "\n")
    print(f"wrote {GOLDEN}: {len(golden['rows'])} rows")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    raise SystemExit(main())
