"""``python -m pipeline <verb> ...``: same as the ``icrowdnav`` command."""

from pipeline.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
