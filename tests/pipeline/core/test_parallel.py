"""pipeline.core.parallel: jobs in a process pool give the rows of a serial run, in job order."""

from __future__ import annotations

import os

from pipeline.core.parallel import map_jobs


def _square_and_pid(k: int) -> tuple[int, int]:
    return k * k, os.getpid()


def test_pool_and_serial_give_the_same_rows_in_job_order():
    jobs = list(range(7))
    serial = map_jobs(_square_and_pid, jobs, workers=1, desc="serial", progress=False)
    pooled = map_jobs(_square_and_pid, jobs, workers=2, desc="pool", progress=False)
    assert [r for r, _ in serial] == [r for r, _ in pooled] == [k * k for k in jobs]
    assert {p for _, p in serial} == {os.getpid()}
    assert os.getpid() not in {p for _, p in pooled}
