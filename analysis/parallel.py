"""Independent jobs of a long study, run here, on local processes, or on a Dask cluster.

Every long study (the fault campaign, the stability map, the workspace maps, sweeps)
is a list of jobs, each a plain picklable value (a scenario's YAML text, a seed, the
numbers that vary) that a worker turns into a result on its own: it builds its own
diagram, so the results are the same whatever ran where. ``map_jobs`` returns them
in the jobs' order:

- ``workers`` 1 and no scheduler: one after another in this process;
- ``workers`` N > 1: a Dask ``LocalCluster`` of N single-threaded worker processes
  on 127.0.0.1 (Drake's and numba's work holds the GIL: threads would not help);
- ``scheduler`` ADDRESS: the workers of a running Dask scheduler (``dask scheduler``
  and ``dask worker ADDRESS`` on a lab's machines, or a Slurm or PBS cluster through
  ``dask-jobqueue``); this machine only submits and gathers.

A worker that dies mid-job (killed, out of memory, its node gone) has its job rerun
on another: Dask's scheduler does that by itself, up to ``distributed.scheduler.
allowed-failures`` times; ``map_jobs`` reports how many jobs it reran.
"""

import os
from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Sequence

from tqdm import tqdm


@dataclass
class JobResults:
    results: List[Any]  # in the jobs' order
    reran: int = 0  # jobs rerun because the worker running them died
    where: str = "this process"  # what ran them, for the report
    workers: int = 1


def report(message: str) -> None:
    """A line for the user while a job runs, printed here or, from a Dask worker, also
    on the submitting client's terminal (Dask forwards it)."""
    from distributed import print as forwarded_print
    forwarded_print(message, flush=True)


def default_workers() -> int:
    """The cores this process may use."""
    return len(os.sched_getaffinity(0))


def map_jobs(function: Callable[[Any], Any], jobs: Sequence, *, workers: int = 1,
             scheduler: Optional[str] = None, description: str = "jobs",
             progress: bool = True,
             on_result: Optional[Callable[[int, int], None]] = None) -> JobResults:
    """``function(job)`` for every job (``function`` importable by name on the
    workers: a module-level function of this package), one progress bar over all
    (or ``on_result(done, total)`` after each)."""
    jobs = list(jobs)
    if scheduler is None and workers <= 1:
        with tqdm(total=len(jobs), desc=description, unit="job", disable=not progress) as bar:
            results = []
            for job in jobs:
                results.append(function(job))
                bar.update(1)
                if on_result is not None:
                    on_result(len(results), len(jobs))
        return JobResults(results=results)
    from distributed import Client, LocalCluster
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except OSError as error:
            raise OSError(f"Dask scheduler {scheduler!r}: could not connect ({error})") from None
        with client:
            return _run_on(client, function, jobs, description, progress, on_result,
                           where=f"Dask scheduler {scheduler}")
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      host="127.0.0.1", dashboard_address=None) as cluster, \
            Client(cluster) as client:
        return _run_on(client, function, jobs, description, progress, on_result,
                       where=f"{workers} local worker processes")


def _run_on(client, function, jobs, description, progress, on_result,
            where: str) -> JobResults:
    from distributed import as_completed
    # pure=False: two equal jobs (a campaign may repeat one) are both run and counted.
    futures = client.map(function, jobs, pure=False)
    order = {future.key: index for index, future in enumerate(futures)}
    results: List[Any] = [None] * len(jobs)
    with tqdm(total=len(jobs), desc=description, unit="job", disable=not progress) as bar:
        for done, future in enumerate(as_completed(futures), start=1):
            results[order[future.key]] = future.result()
            bar.update(1)
            if on_result is not None:
                on_result(done, len(jobs))
    reran = client.run_on_scheduler(_times_rerun, keys=list(order))
    return JobResults(results=results, reran=sum(1 for n in reran.values() if n > 0),
                      where=where, workers=len(client.scheduler_info()["workers"]))


def _times_rerun(dask_scheduler, keys) -> dict:
    """How many times each task was on a worker that died (the scheduler's count)."""
    return {key: dask_scheduler.tasks[key].suspicious for key in keys
            if key in dask_scheduler.tasks}
