"""Tests of recorder.mcap.cli: the recover and summary verbs."""

from __future__ import annotations

import json
from pathlib import Path

from recorder.mcap.cli import main
from recorder.mcap.reader import count_frames
from tests.recorder.mcap.common import chunk_layout


def test_module_cli_recover_and_summary(recorded: Path, tmp_path: Path, capsys) -> None:
    part = tmp_path / "c.mcap.partial"
    part.write_bytes(recorded.read_bytes()[: chunk_layout(recorded)[3][0] + 5])
    assert main(["recover", str(part)]) == 0
    assert capsys.readouterr().out.strip() == f"recovered {count_frames(tmp_path / 'c.recovered.mcap')} frames " \
                                              f"into {tmp_path / 'c.recovered.mcap'}"
    assert main(["recover", str(part)]) == 2  # never overwrites
    assert "already exists" in capsys.readouterr().err
    assert main(["summary", str(recorded)]) == 0
    assert json.loads(capsys.readouterr().out)["n_frames"] == 21
