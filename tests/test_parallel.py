"""Long studies beyond one process: the fault campaign gives the same rows in this
process, on local worker processes and on a Dask scheduler's workers, and a worker
killed mid-job has its job rerun elsewhere."""

import json
import os
import pickle
import signal
import threading
import time

import pytest
from distributed import Client, LocalCluster

from maglev_haptics.analysis.fault_campaign import plan_campaign, run_fault
from maglev_haptics.analysis.parallel import map_jobs
from maglev_haptics.diagrams.cli import main
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


def test_the_campaign_gives_the_same_rows_wherever_it_runs(tmp_path, cluster):
    here = campaign_rows(tmp_path, "--workers", "1")
    local = campaign_rows(tmp_path, "--workers", "2")
    dask = campaign_rows(tmp_path, "--scheduler", cluster.scheduler_address)
    assert here["runs"] == local["runs"] == dask["runs"]
    assert [row["fault"] for row in here["runs"]] == [p.fault for p in plan_campaign(RUNS, 5)]
    assert here["jobs"]["where"] == "this process"
    assert local["jobs"] == {"where": "2 local worker processes", "workers": 2, "reran": 0}
    assert dask["jobs"]["where"] == f"Dask scheduler {cluster.scheduler_address}"


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
