"""Every Meshcat the project makes, and its end on the thread that made it.

Drake aborts the process when a ``Meshcat`` is destroyed on a thread other than
the one that constructed it (``meshcat.cc``: ``IsThread(main_thread_id_)``). A
Meshcat held by a diagram sits in a reference cycle (systems keep bound methods
of themselves), so Python's cyclic collector frees it on whichever thread happens
to allocate at that moment: Dask's scheduler thread, the log writer.

So a Meshcat is never left to the collector: ``start_meshcat`` holds a strong
reference to it. ``close_meshcat``, on the thread that made it, collects the
cycles that held it and lets it go; one that its caller still references is
kept until that thread's next ``start_meshcat`` or ``close_meshcat`` finds it
unreferenced, or until the interpreter exits (on the main thread).
"""

from __future__ import annotations

import atexit
import gc
import threading
import weakref
from typing import List, Optional, Tuple

from pydrake.geometry import Meshcat, MeshcatParams, StartMeshcat

# (meshcat, ident of the thread that made it): started and not closed
_OPEN: List[Tuple[Meshcat, int]] = []
# closed, but still referenced by their caller when they were closed
_CLOSED: List[Tuple[Meshcat, int]] = []
_LOCK = threading.RLock()  # over both lists


def start_meshcat(params: Optional[MeshcatParams] = None) -> Meshcat:
    """A new Meshcat server (Drake's ``StartMeshcat`` when no params: it logs its URL),
    held until ``close_meshcat`` is called on this thread."""
    _release_unreferenced()
    meshcat = StartMeshcat() if params is None else Meshcat(params)
    with _LOCK:
        _OPEN.append((meshcat, threading.get_ident()))
    return meshcat


def close_meshcat(meshcat: Meshcat) -> None:
    """Release ``meshcat`` on the thread that made it (after the diagrams that used it are
    dropped): it is destroyed here once its caller's last reference goes."""
    with _LOCK:
        index = next((i for i, (held, _) in enumerate(_OPEN) if held is meshcat), None)
        if index is None:
            raise ValueError("close_meshcat: this Meshcat was not made by start_meshcat, "
                             "or it is closed already")
        owner = _OPEN[index][1]
        if owner != threading.get_ident():
            raise RuntimeError(
                f"close_meshcat: called on thread {threading.get_ident()}, but this Meshcat "
                f"was made on thread {owner}; Drake destroys a Meshcat only on the thread "
                "that made it")
        _CLOSED.append(_OPEN.pop(index))
        del meshcat
        _release_unreferenced()


def _release_unreferenced() -> None:
    """Destroy, on this thread, the closed Meshcats of this thread that nothing else holds."""
    with _LOCK:
        gc.collect()  # the cycles that held them die here, not on another thread
        me = threading.get_ident()
        mine = [entry for entry in _CLOSED if entry[1] == me]
        _CLOSED[:] = [entry for entry in _CLOSED if entry[1] != me]
        references = [weakref.ref(meshcat) for meshcat, _ in mine]
        del mine  # the last strong references: an unreferenced Meshcat is destroyed here
        _CLOSED.extend((meshcat, me) for meshcat in (ref() for ref in references)
                       if meshcat is not None)


@atexit.register
def _release_at_exit() -> None:
    """At exit (on the main thread) the main thread's Meshcats go; one another thread
    made and never closed is that thread's to close, and is left alone."""
    main = threading.main_thread().ident
    with _LOCK:
        _OPEN[:] = [entry for entry in _OPEN if entry[1] != main]
        _CLOSED[:] = [entry for entry in _CLOSED if entry[1] != main]
        gc.collect()
