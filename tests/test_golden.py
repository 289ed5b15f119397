"""The re-housing golden test: seeded metrics rows and artifact hashes recorded before the code was moved.

Regenerate ``tests/golden/rehousing.json`` with ``tests/golden/make_rehousing_golden.py`` only for an intended
behaviour change (and say so in the commit).
"""

from __future__ import annotations

import json

import pytest

from tests.golden import make_rehousing_golden as golden


@pytest.fixture(scope="module")
def expected() -> dict:
    return json.loads(golden.GOLDEN.read_text())


@pytest.mark.slow
def test_expert_and_dwa_rows_are_unchanged(expected: dict) -> None:
    rows = golden.metric_rows()
    assert len(rows) == len(expected["rows"])
    for got, want in zip(rows, expected["rows"], strict=True):
        assert got == pytest.approx(want, abs=1e-6, nan_ok=True), (got, want)


def test_mcap_and_parquet_bytes_are_unchanged(expected: dict, tmp_path) -> None:
    hashes = golden.artifact_hashes(tmp_path)
    assert hashes["mcap_sha256"] == expected["mcap_sha256"]
    assert hashes["parquet_sha256"] == expected["parquet_sha256"]
