"""Independent jobs (episodes) in a local process pool, results in job order, with a progress bar.

The one place where episodes fan out to processes (the benchmark, the acceptance runs): forked workers keep what
they load (a method's weights) for the jobs that follow. ``workers <= 1`` runs in this process.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any, TypeVar

from tqdm import tqdm

J = TypeVar("J")


def map_jobs(fn: Callable[[J], Any], jobs: Sequence[J], workers: int, desc: str, progress: bool = True,
             unit: str = "ep") -> list[Any]:
    """``[fn(j) for j in jobs]``, in a fork process pool of ``workers`` when ``workers > 1``."""
    if workers <= 1:
        return [fn(j) for j in tqdm(jobs, desc=desc, unit=unit, disable=not progress, dynamic_ncols=True)]
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("fork")) as pool:
        return list(tqdm(pool.map(fn, jobs, chunksize=1), total=len(jobs), desc=desc, unit=unit,
                         disable=not progress, dynamic_ncols=True))
