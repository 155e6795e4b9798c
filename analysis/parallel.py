"""A long study's jobs, run here, on local processes, or on a Dask cluster.

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

A study whose jobs depend on earlier ones (the onset's bisections) is a list of
searches for ``run_searches``: each search, called with ``width`` (how many jobs it
may have running at once, now), is a generator that yields a round of jobs, is sent
their results, and returns its answer. More workers let a search speculate (a
bisection evaluates the next levels of its tree at once); what it finds must not
depend on ``width``.

A worker that dies mid-job (killed, out of memory, its node gone) has its job rerun
on another: Dask's scheduler does that by itself, up to ``distributed.scheduler.
allowed-failures`` times; ``map_jobs`` reports how many jobs it reran.
"""

import functools
import os
from dataclasses import dataclass
from typing import Any, Callable, Generator, List, Optional, Sequence

from tqdm import tqdm


@dataclass
class JobResults:
    results: List[Any]  # in the jobs' order
    reran: int = 0  # jobs rerun because the worker running them died
    where: str = "this process"  # what ran them, for the report
    workers: int = 1


Search = Callable[[Callable[[], int]], Generator[List[Any], List[Any], Any]]


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
    return run_searches(function, [functools.partial(_one_job, job) for job in jobs],
                        workers=workers, scheduler=scheduler, description=description,
                        unit="job", progress=progress, on_result=on_result)


def _one_job(job: Any, width: Callable[[], int]):
    """A search of one round of one job: its result."""
    (result,) = yield [job]
    return result


def run_searches(function: Callable[[Any], Any], searches: Sequence[Search], *,
                 workers: int = 1, scheduler: Optional[str] = None,
                 description: str = "searches", unit: str = "search", progress: bool = True,
                 on_result: Optional[Callable[[int, int], None]] = None) -> JobResults:
    """Each search's answer, in their order; their rounds' jobs (``function(job)``)
    run here one after another, or on the workers, every search's next round as soon
    as its last one ended. A search may speculate as wide as ``width()``: the workers
    over the searches still running (1 in this process). A job that raised raises
    its error in its search, at the round's ``yield``."""
    if scheduler is None and workers <= 1:
        return JobResults(results=_run_here(function, searches, description, unit, progress,
                                            on_result))
    from distributed import Client, LocalCluster
    arguments = (function, searches, description, unit, progress, on_result)
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="10s")
        except OSError as error:
            raise OSError(f"Dask scheduler {scheduler!r}: could not connect ({error})") from None
        with client:
            return _run_on(client, *arguments, where=f"Dask scheduler {scheduler}")
    # The scheduler's web server on any free port (":0"): where 8787 is taken (another
    # cluster, a second study), Dask would warn in four lines that it moved.
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      host="127.0.0.1", dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        return _run_on(client, *arguments, where=f"{workers} local worker processes")


def _next_round(rounds, resume: Callable[[], List[Any]]) -> List[Any]:
    """The search's next round of jobs after ``resume()`` (its ``next``, ``send`` or
    ``throw``), an empty round answered at once; StopIteration with its answer when
    it returned."""
    jobs = resume()
    while not jobs:
        jobs = rounds.send([])
    return jobs


def _run_here(function, searches, description, unit, progress, on_result) -> List[Any]:
    answers = []
    with tqdm(total=len(searches), desc=description, unit=unit, disable=not progress) as bar:
        for search in searches:
            rounds = search(lambda: 1)
            resume = rounds.__next__
            try:
                while True:
                    jobs = _next_round(rounds, resume)
                    try:
                        resume = functools.partial(rounds.send, [function(job) for job in jobs])
                    except Exception as error:  # the search handles it, or it ends the study
                        resume = functools.partial(rounds.throw, error)
            except StopIteration as answer:
                answers.append(answer.value)
            bar.update(1)
            if on_result is not None:
                on_result(len(answers), len(searches))
    return answers


def _run_on(client, function, searches, description, unit, progress, on_result,
            where: str) -> JobResults:
    from distributed import as_completed
    answers: List[Any] = [None] * len(searches)
    running = set(range(len(searches)))

    def width() -> int:
        # Read each time: a cluster's workers may join (or leave) while it runs.
        return max(1, len(client.scheduler_info()["workers"]) // len(running))

    rounds = [search(width) for search in searches]
    pending = {}  # search -> its round's futures
    left = {}  # search -> how many of its round's jobs have not ended
    owner = {}  # a job's key -> its search
    every_future = []  # held until the reruns are counted: a released task is forgotten
    completions = as_completed()

    with tqdm(total=len(searches), desc=description, unit=unit, disable=not progress) as bar:
        def start(index, resume):
            try:
                jobs = _next_round(rounds[index], resume)
            except StopIteration as answer:
                answers[index] = answer.value
                running.discard(index)
                bar.update(1)
                if on_result is not None:
                    on_result(len(searches) - len(running), len(searches))
                return
            # pure=False: two equal jobs (a campaign may repeat one) are both run and counted.
            futures = client.map(function, jobs, pure=False)
            every_future.extend(futures)
            owner.update((future.key, index) for future in futures)
            pending[index], left[index] = futures, len(futures)
            completions.update(futures)

        for index in range(len(searches)):
            start(index, rounds[index].__next__)
        for future in completions:
            index = owner[future.key]
            left[index] -= 1
            if left[index]:
                continue
            futures = pending.pop(index)
            errors = [f.exception() for f in futures if f.status == "error"]
            start(index, functools.partial(rounds[index].throw, errors[0]) if errors
                  else functools.partial(rounds[index].send, [f.result() for f in futures]))
    reran = client.run_on_scheduler(_times_rerun, keys=list(owner))
    return JobResults(results=answers, reran=sum(1 for n in reran.values() if n > 0),
                      where=where, workers=len(client.scheduler_info()["workers"]))


def _times_rerun(dask_scheduler, keys) -> dict:
    """How many times each task was on a worker that died (the scheduler's count)."""
    return {key: dask_scheduler.tasks[key].suspicious for key in keys
            if key in dask_scheduler.tasks}
