"""A stand-in for ``python -m pipeline train`` in the ``train-all`` tests: ``python -m tests.pipeline.standin_train
train --variant V --data-dir D ...`` appends its arguments to ``D/checkpoints/policy/V/runs.txt``, waits
``STANDIN_SECONDS`` (default 0.2), writes ``done`` and exits 0 — or exits 3 when V is in ``STANDIN_FAIL``
(comma-separated) after printing an ``error:`` line, as the real verb does."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path


def main(argv: list[str]) -> int:
    variant = argv[argv.index("--variant") + 1]
    data = Path(argv[argv.index("--data-dir") + 1])
    out = data / "checkpoints" / "policy" / variant
    out.mkdir(parents=True, exist_ok=True)
    opts = json.loads((data / "standin.json").read_text()) if (data / "standin.json").is_file() else {}
    parent = Path(f"/proc/{os.getppid()}/cmdline").read_bytes().split(b"\0")[0].decode().replace(" ", "_")
    with open(out / "runs.txt", "a") as f:
        f.write(f"{time.time():.3f} {parent} {' '.join(argv)}\n")
    time.sleep(float(opts.get("seconds", 0.2)))
    if variant in opts.get("fail", []):
        print(f"error: {variant} failed on purpose", file=sys.stderr)
        return 3
    (out / "done").write_text(f"{time.time():.3f}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
