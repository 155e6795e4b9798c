"""Long studies beyond one process: the fault campaign gives the same rows in this
process, on local worker processes and on a Dask scheduler's workers, and a worker
killed mid-job has its job rerun elsewhere."""

import functools
import json
import operator
import os
import pickle
import signal
import threading
import time

import pytest
from distributed import Client, LocalCluster

from maglev_haptics.analysis.fault_campaign import plan_campaign, run_fault
from maglev_haptics.analysis.onset import bisect_onset, bracket_onset, onset_study
from maglev_haptics.analysis.parallel import map_jobs, run_searches
from maglev_haptics.cli import main
from maglev_haptics.diagrams.scenario import load_scenario, scenario_from_yaml, scenario_yaml

RUNS = 4  # the levitation kinds: a few seconds each


@pytest.fixture(scope="module")
def cluster():
    """A Dask scheduler and two single-threaded worker processes on 127.0.0.1."""
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        yield cluster


def campaign_rows(tmp_path, *where):
    out = tmp_path / "_".join(where).replace(":", "").replace("/", "")
    assert main(["faults", "--runs", str(RUNS), "--seed", "5", *where, "--out", str(out)]) == 0
    return json.loads((out / "faults.json").read_text())


@pytest.mark.slow
def test_the_campaign_gives_the_same_rows_wherever_it_runs(tmp_path, cluster):
    here = campaign_rows(tmp_path, "--workers", "1")
    local = campaign_rows(tmp_path, "--workers", "2")
    dask = campaign_rows(tmp_path, "--scheduler", cluster.scheduler_address)
    assert here["runs"] == local["runs"] == dask["runs"]
    assert [row["fault"] for row in here["runs"]] == [p.fault for p in plan_campaign(RUNS, 5)]
    assert here["jobs"]["where"] == "this process"
    assert local["jobs"] == {"where": "2 local worker processes", "workers": 2, "reran": 0}
    assert dask["jobs"]["where"] == f"Dask scheduler {cluster.scheduler_address}"


@pytest.mark.slow
def test_a_worker_killed_mid_job_has_its_job_rerun_elsewhere(cluster):
    plans = plan_campaign(RUNS, 5)
    expected = [run_fault(plan) for plan in plans]
    killed = []

    def kill_a_busy_worker():
        with Client(cluster.scheduler_address) as client:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                busy = [address for address, keys in client.processing().items() if keys]
                if busy:
                    time.sleep(1.0)  # well into its job (each takes seconds)
                    pid = client.run(os.getpid, workers=busy[:1])[busy[0]]
                    os.kill(pid, signal.SIGKILL)
                    killed.append(busy[0])
                    return
                time.sleep(0.05)

    killer = threading.Thread(target=kill_a_busy_worker)
    killer.start()
    results = map_jobs(run_fault, plans, scheduler=cluster.scheduler_address, progress=False)
    killer.join()
    assert killed, "no worker was busy to kill"
    assert results.reran >= 1
    assert results.results == expected


@pytest.mark.slow  # Dask's client waits out its 10 s connection timeout
def test_an_unreachable_scheduler_is_one_line(tmp_path, capsys):
    assert main(["faults", "--runs", "1", "--scheduler", "tcp://127.0.0.1:1",
                 "--out", str(tmp_path / "x")]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("maglev faults: error: Dask scheduler 'tcp://127.0.0.1:1': "
                            "could not connect") and "\n" not in error


@pytest.mark.parametrize("name", ["levitate", "peg_in_hole", "deformable_surface", "stereo_display"])
def test_a_scenario_travels_to_a_worker_as_yaml_text(name):
    """Drake's config types do not pickle: a study's job carries its scenario as YAML
    text, which reads back as it was."""
    scenario = load_scenario(name, None, "{faults: [!StuckAmplifier {coil: 3}]}")
    text = scenario_yaml(scenario)
    assert scenario_yaml(scenario_from_yaml(pickle.loads(pickle.dumps(text)))) == text


def onset_of(rounds, width):
    """A search for where ``threshold < stiffness`` turns true (the jobs are the
    stiffnesses; ``operator.lt`` with the threshold bound decides them), as the onset
    study searches, each round's size appended to ``rounds``."""
    def unstable(stiffnesses):
        rounds.append(len(stiffnesses))
        return (yield list(stiffnesses))
    low, high = yield from bracket_onset(unstable, 100.0, width)
    return (yield from bisect_onset(unstable, low, high, width))


THRESHOLD_N_M = 4321.0


def driven(width):
    """``onset_of`` run here with ``width`` jobs a round allowed: (answer, rounds)."""
    rounds = []
    search = onset_of(rounds, lambda: width)
    try:
        jobs = next(search)
        while True:
            jobs = search.send([THRESHOLD_N_M < stiffness for stiffness in jobs])
    except StopIteration as answer:
        return answer.value, rounds


def test_a_wider_search_speculates_and_finds_the_same_stiffness():
    """More workers: each round evaluates more of the bisection's tree, in fewer
    rounds, and the stiffness found is the serial search's exactly."""
    serial, serial_rounds = driven(1)
    assert serial == pytest.approx(THRESHOLD_N_M, rel=0.02)
    assert set(serial_rounds) == {1}
    rounds_taken = [len(serial_rounds)]
    for width in (2, 3, 7):
        found, rounds = driven(width)
        assert found == serial
        assert max(rounds) == width
        rounds_taken.append(len(rounds))
    assert rounds_taken == sorted(set(rounds_taken), reverse=True), rounds_taken


@pytest.mark.slow
def test_searches_find_the_same_on_workers_as_here(cluster):
    is_above = functools.partial(operator.lt, THRESHOLD_N_M)
    searches = [functools.partial(onset_of, []) for _ in range(3)]
    here = run_searches(is_above, searches, progress=False)
    there = run_searches(is_above, searches, scheduler=cluster.scheduler_address,
                         progress=False)
    assert here.results == there.results == [driven(1)[0]] * 3
    assert there.workers == 2
    # One search alone speculates two wide on the two workers, its rounds' jobs
    # ending in any order.
    rounds = []
    alone = run_searches(is_above, [functools.partial(onset_of, rounds)],
                         scheduler=cluster.scheduler_address, progress=False)
    assert alone.results == [driven(1)[0]]
    assert rounds == driven(2)[1]


def refusing(width):
    """A search whose round has a job that raises (1 / 0): it answers with the error's
    name; and before it, an empty round, answered at once."""
    assert (yield []) == []
    try:
        yield [1.0, 0.0]
    except ZeroDivisionError as error:
        return type(error).__name__


def answering_at_once(width):
    return "no jobs"
    yield


@pytest.mark.parametrize("where", ["here", pytest.param("there", marks=pytest.mark.slow)])
def test_a_search_hears_of_its_jobs_errors_and_may_need_no_jobs(where, request):
    place = ({"scheduler": request.getfixturevalue("cluster").scheduler_address}
             if where == "there" else {})
    found = run_searches(functools.partial(operator.truediv, 1.0),
                         [refusing, answering_at_once], progress=False, **place)
    assert found.results == ["ZeroDivisionError", "no jobs"]


def test_the_onset_study_says_why_it_does_not_apply():
    """Levitation alone has no hand holding the instrument with haptics on."""
    for point in onset_study(load_scenario("levitate")):
        assert "scripted hand holding the instrument" in point["not_found"], point


@pytest.mark.slow
def test_local_workers_start_quietly_where_port_8787_is_taken(capfd):
    """Dask's scheduler serves its web page on any free port: no 'Port 8787 is already
    in use' warning when another cluster (or anything) holds Dask's default port."""
    import socket
    import warnings
    holder = socket.socket()
    try:
        holder.bind(("127.0.0.1", 8787))
        holder.listen()
    except OSError:
        pass  # already taken by something else: the case this test is about
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        results = map_jobs(operator.neg, [1, 2, 3], workers=2, progress=False)
    holder.close()
    assert results.results == [-1, -2, -3]
    assert not [w for w in caught if "already in use" in str(w.message)]
    assert "already in use" not in capfd.readouterr().err
