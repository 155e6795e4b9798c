"""A Meshcat ends on the thread that made it, whoever runs Python's collector."""

import gc
import re
import subprocess
import sys
import threading
import weakref
from pathlib import Path

import pytest
from pydrake.geometry import MeshcatParams

from maglev_haptics.diagrams.meshcat_lifetime import close_meshcat, start_meshcat

PROJECT = Path(__file__).resolve().parents[1]
LOCAL = MeshcatParams(host="127.0.0.1")
MAKES_A_MESHCAT = re.compile(r"(?<![\w.])(Start)?Meshcat\(")

# A Meshcat left in a reference cycle (as a diagram leaves it), and another thread that
# happens to run the collector (as Dask's scheduler thread does).
DROPPED_IN_A_CYCLE = """
import gc, sys, threading
from pydrake.geometry import Meshcat, MeshcatParams
from maglev_haptics.diagrams.meshcat_lifetime import start_meshcat
params = MeshcatParams(host="127.0.0.1")
meshcat = start_meshcat(params) if sys.argv[1] == "project" else Meshcat(params)
cycle = [meshcat]
cycle.append(cycle)
del meshcat, cycle
collector = threading.Thread(target=gc.collect)
collector.start()
collector.join()
print("survived the collector on another thread")
"""


def run_dropped(how: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", DROPPED_IN_A_CYCLE, how], capture_output=True,
                          text=True, timeout=120)


def test_a_bare_meshcat_collected_on_another_thread_aborts_the_process():
    # What the project guards against: Drake's check fails and the process dies.
    result = run_dropped("bare")
    assert result.returncode != 0
    assert "survived" not in result.stdout


def test_a_started_meshcat_dropped_in_a_cycle_survives_another_threads_collector():
    result = run_dropped("project")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "survived the collector on another thread" in result.stdout


def test_close_destroys_it_on_this_thread_once_unreferenced():
    meshcat = start_meshcat(LOCAL)
    alive = weakref.ref(meshcat)
    cycle = [meshcat]
    cycle.append(cycle)
    gc.collect()
    assert alive() is not None  # open: held, whatever the collector does
    close_meshcat(meshcat)
    assert alive() is not None  # the caller still holds it: kept, not left to the collector
    del meshcat, cycle
    gc.collect()
    assert alive() is not None  # closed but not yet released: still not the collector's
    other = start_meshcat(LOCAL)  # this thread's next start finds the closed one unreferenced
    assert alive() is None
    close_meshcat(other)


def test_close_on_another_thread_is_refused_and_keeps_it():
    meshcat = start_meshcat(LOCAL)
    errors = []

    def close_elsewhere():
        try:
            close_meshcat(meshcat)
        except RuntimeError as error:
            errors.append(str(error))

    closer = threading.Thread(target=close_elsewhere)
    closer.start()
    closer.join()
    assert errors and "made on thread" in errors[0]
    close_meshcat(meshcat)
    with pytest.raises(ValueError, match="closed already"):
        close_meshcat(meshcat)


def test_every_meshcat_the_project_makes_goes_through_start_meshcat():
    makers = []
    for path in PROJECT.rglob("*.py"):
        if ".venv" in path.parts or path.name in ("meshcat_lifetime.py", Path(__file__).name):
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if MAKES_A_MESHCAT.search(line):
                makers.append(f"{path.relative_to(PROJECT)}:{number}: {line.strip()}")
    assert not makers, "make Meshcats with start_meshcat:\n" + "\n".join(makers)
