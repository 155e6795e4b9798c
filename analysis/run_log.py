"""The run's log on disk as the run goes, so a run that is killed leaves it readable.

A run with an output folder moves its logger's samples to disk every
``CHUNK_WALL_S`` of wall clock (``RunLogWriter``): one ``.npy`` file a chunk in
``log_chunks/``, written under a temporary name and renamed, so a kill (even
SIGKILL) leaves only whole chunks, and the logger never holds more than a chunk
(an interactive run of an hour stays as small as one of a minute). The loop only
copies the samples out, between ticks and often (a paced run every 50 ms: each copy
short, and about as long as the last, so the gap it is given holds it), each piece
already laid out as it goes on disk; a thread writes them, since writing a chunk
takes a tick's whole slot or more (1.4-1.9 ms for half a second of levitate's log on
the test VM). The thread holds Python's GIL only between its ``write`` calls (a
join of the pieces there held it, and the loop, 100-230 us) and runs below the
loop's priority (``BACKGROUND_PRIORITY``). The finished run writes ``log.npz`` and
removes the chunks. ``load_run_log(out_dir)`` reads either: ``log.npz``, or what the
chunks of a killed run hold.
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Dict

import numpy as np

from maglev_haptics.analysis.run_metrics import log_arrays_from
from maglev_haptics.hardware.realtime_priority import (
    BACKGROUND_PRIORITY, add_follower, set_thread_priority)
from maglev_haptics.hardware.thermal import CoilThermal

LOG_FILE = "log.npz"
CHUNK_DIR = "log_chunks"
LAYOUT_FILE = "layout.json"
# A kill loses at most this much wall-clock time of log, and the chunk in writing (s).
CHUNK_WALL_S = 0.5


class RunLogWriter:
    """Moves ``logger``'s samples into ``out_dir/log_chunks/`` as the run goes.

    ``log_layout`` (name -> its rows) and the coils' ``thermal`` model are written
    first, so the chunks can be read without the diagram.
    """

    def __init__(self, out_dir: Path, logger, log_layout: Dict[str, slice], thermal: CoilThermal):
        self._logger = logger
        self._folder = Path(out_dir) / CHUNK_DIR
        # An earlier run's, in the same folder: its log.npz would be read for this run's.
        shutil.rmtree(self._folder, ignore_errors=True)
        (Path(out_dir) / LOG_FILE).unlink(missing_ok=True)
        self._folder.mkdir(parents=True)
        layout = {"rows": {name: [int(rows.start), int(rows.stop)]
                           for name, rows in log_layout.items()},
                  "thermal": asdict(thermal)}
        _write_atomically(self._folder / LAYOUT_FILE,
                          lambda file: file.write(json.dumps(layout).encode()))
        self._chunks = 0
        # Moved out of the logger since the last chunk: each (1 + rows, samples),
        # column-major, row 0 the sample times (s): the chunk's file is their bytes in turn.
        self._pieces = []
        self._last_wall_s = time.perf_counter()
        self._pending = queue.Queue()
        self._failure = None
        # A daemon: a run that dies does not wait for it.
        self._writer = threading.Thread(target=self._write_chunks, name="run log", daemon=True)
        self._writer.start()
        add_follower(self._follow_loop)

    def _follow_loop(self, realtime: bool) -> None:
        # Above normal threads: preempted by one of them between two writes, the writer
        # would hold the GIL, and the loop, for a time slice.
        if self._writer.is_alive():  # an ended thread's id may be another's by now
            set_thread_priority(self._writer.native_id, realtime, BACKGROUND_PRIORITY)

    def drain(self, context, force: bool = False) -> None:
        """Move what the logger holds out of it, and hand what was moved since the last
        chunk to the writer as the next chunk once ``CHUNK_WALL_S`` has passed (or now,
        with ``force``). Every call costs the loop's thread about the same: only copies
        of what was logged since the last call (the writer thread joins them)."""
        log = self._logger.FindMutableLog(context)
        if log.num_samples() > 0:
            # A copy: the logger's arrays are views that its next samples overwrite.
            data = log.data()
            piece = np.empty((1 + data.shape[0], data.shape[1]), order="F")
            piece[0] = log.sample_times()
            piece[1:] = data
            self._pieces.append(piece)
            log.Clear()
        now = time.perf_counter()
        if not self._pieces or (not force and now - self._last_wall_s < CHUNK_WALL_S):
            return
        self._last_wall_s = now
        self._hand_over()

    def _hand_over(self) -> None:
        """The pieces moved since the last chunk, to the writer as the next chunk."""
        self._pending.put((self._folder / f"chunk_{self._chunks:06d}.npy", self._pieces))
        self._pieces = []
        self._chunks += 1

    def finish(self, context) -> Dict[str, np.ndarray]:
        """The last chunk, then ``log.npz`` from all of them; the chunks are removed.
        Returns the log's arrays."""
        self.drain(context, force=True)
        self._pending.put(None)
        self._writer.join()
        if self._failure is not None:
            raise self._failure
        out_dir = self._folder.parent
        log = load_run_log(out_dir)
        _write_atomically(out_dir / LOG_FILE, lambda file: np.savez_compressed(file, **log))
        shutil.rmtree(self._folder)
        return log

    def abandon(self) -> None:
        """For a run that raised: the writer stops after what it was given, and the
        folder goes if no chunk was written (a run that stopped before it simulated
        leaves no empty folder; one that raised later keeps what it moved out)."""
        if self._pieces:
            self._hand_over()
        self._pending.put(None)
        self._writer.join()
        if self._chunks == 0:
            shutil.rmtree(self._folder, ignore_errors=True)

    def _write_chunks(self) -> None:
        while (item := self._pending.get()) is not None:
            path, pieces = item
            try:
                _write_atomically(path, lambda file: _write_columns_npy(file, pieces))
            except OSError as error:  # reported by finish(); the run goes on
                self._failure = self._failure or error


def load_run_log(out_dir) -> Dict[str, np.ndarray]:
    """The arrays of a run's ``log.npz``; for a run that was killed, those its chunks
    hold (up to ``CHUNK_WALL_S`` of wall clock before the kill). A FileNotFoundError
    names the folder when it holds neither."""
    out_dir = Path(out_dir)
    if (out_dir / LOG_FILE).exists():
        with np.load(out_dir / LOG_FILE) as log:
            return {name: log[name] for name in log.files}
    folder = out_dir / CHUNK_DIR
    chunks = sorted(folder.glob("chunk_*.npy"))
    if not (folder / LAYOUT_FILE).exists() or not chunks:
        raise FileNotFoundError(
            f"{out_dir}: no {LOG_FILE} and no logged chunks in {CHUNK_DIR}/ (was it a run's "
            "output folder, and did the run get past its first half second?)")
    layout = json.loads((folder / LAYOUT_FILE).read_text())
    # Column-major like the logger's own data, so the sums match it to the last bit.
    samples = np.asfortranarray(np.hstack([np.load(chunk) for chunk in chunks]))
    rows = {name: slice(start, stop) for name, (start, stop) in layout["rows"].items()}
    return log_arrays_from(samples[0], samples[1:], rows, CoilThermal(**layout["thermal"]))


def _write_columns_npy(file, pieces) -> None:
    """The column-major arrays ``pieces`` (equal rows), side by side, in ``.npy``
    format, one ``write`` a piece: no joined copy, and each write lets go of the GIL
    (np.save held it up to 2.9 ms: the loop's thread waited)."""
    header = {"descr": np.lib.format.dtype_to_descr(pieces[0].dtype), "fortran_order": True,
              "shape": (pieces[0].shape[0], sum(piece.shape[1] for piece in pieces))}
    np.lib.format.write_array_header_1_0(file, header)
    for piece in pieces:
        file.write(memoryview(piece.T).cast("B"))  # .T of column-major: C-contiguous


def _write_atomically(path: Path, write) -> None:
    """``write(file)`` into a temporary file beside ``path``, then rename it to ``path``:
    a reader (or a kill) never sees half a file."""
    temporary = path.with_name(path.name + ".partial")
    with open(temporary, "wb") as file:
        write(file)
    os.replace(temporary, path)
