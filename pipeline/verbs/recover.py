"""``icrowdnav recover FILE.mcap.partial``: salvage the complete frames of a killed episode into FILE.recovered.mcap."""

from __future__ import annotations

from recorder.mcap.cli import main as mcap_main


def main(argv: list[str]) -> int:
    """salvage the complete frames of a killed episode (FILE.mcap.partial) into FILE.recovered.mcap"""
    return mcap_main(["recover", *argv])
