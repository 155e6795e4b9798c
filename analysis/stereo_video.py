"""Recordings of the stereo display: the left and right eye images of a run, streamed frame by
frame into a side-by-side video and a red-cyan anaglyph video (H.264 MP4 through
``imageio_ffmpeg``, or PNG sequences where no encoder can start)."""

import contextlib
import math
import numbers
import warnings
from pathlib import Path

import matplotlib.image
import numpy as np

try:
    import imageio_ffmpeg
except ImportError:  # optional: without it the writer falls back to PNG sequences
    imageio_ffmpeg = None

ENCODERS = ("auto", "png")
SBS_NAME = "stereo_sbs"
ANAGLYPH_NAME = "stereo_anaglyph"
FIRST_SBS_FILE = "stereo_first_sbs.png"
FIRST_ANAGLYPH_FILE = "stereo_first_anaglyph.png"
# In frame periods: absorbs round-off in simulated times such as 3 * 0.1 != 0.3.
_FRAME_TOLERANCE = 1e-6


def _check_eye(name: str, image) -> None:
    if not isinstance(image, np.ndarray):
        raise ValueError(f"{name}: got a {type(image).__name__}; expected a numpy uint8 RGB "
                         f"array of shape (H, W, 3)")
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
        raise ValueError(f"{name}: got dtype {image.dtype} and shape {image.shape}; expected a "
                         f"uint8 RGB array of shape (H, W, 3) with H, W >= 1")


def _check_pair(left, right) -> None:
    _check_eye("left", left)
    _check_eye("right", right)
    if left.shape != right.shape:
        raise ValueError(f"right.shape = {right.shape} differs from left.shape = {left.shape}; "
                         f"both eyes' images must be the same size")


def side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The (H, 2W, 3) uint8 image with ``left`` in the left half and ``right`` in the right half
    (parallel-view layout, as stereo players and head-mounted displays expect)."""
    _check_pair(left, right)
    return np.concatenate((left, right), axis=1)


def anaglyph(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The (H, W, 3) uint8 red-cyan colour anaglyph: the red channel from ``left``, green and blue
    from ``right`` (the standard colour anaglyph, seen with the red filter over the left eye)."""
    _check_pair(left, right)
    out = right.copy()
    out[..., 0] = left[..., 0]
    return out


def _pad_to_even(frame: np.ndarray) -> np.ndarray:
    """``frame`` with a black row below and/or a black column on the right where its height or
    width is odd: yuv420p stores colour per 2 x 2 pixels, so H.264 needs even sizes."""
    rows, cols = frame.shape[0] % 2, frame.shape[1] % 2
    if rows == 0 and cols == 0:
        return frame
    return np.pad(frame, ((0, rows), (0, cols), (0, 0)))


class _PngSequence:
    """``<name>/frame_00000.png``, ``frame_00001.png``, ... in ``out_dir``."""

    def __init__(self, out_dir: Path, name: str):
        self._out_dir = out_dir
        self._name = name
        (out_dir / name).mkdir(exist_ok=True)
        self.files = []

    def write(self, frame: np.ndarray) -> None:
        relative = f"{self._name}/frame_{len(self.files):05d}.png"
        matplotlib.image.imsave(self._out_dir / relative, frame)
        self.files.append(relative)

    def close(self) -> None:
        pass  # every frame is complete on disk once written


class _Mp4Stream:
    """``<name>.mp4`` in ``out_dir``: H.264, yuv420p, frames padded to even sizes."""

    def __init__(self, out_dir: Path, name: str, frame_shape: tuple, frame_rate_hz: float):
        self._path = out_dir / f"{name}.mp4"
        # A stale video from an earlier run must not pass the check in close().
        self._path.unlink(missing_ok=True)
        height, width = frame_shape[0] + frame_shape[0] % 2, frame_shape[1] + frame_shape[1] % 2
        # macro_block_size=1: the frames are padded here, so ffmpeg must not rescale them.
        self._frames = imageio_ffmpeg.write_frames(str(self._path), (width, height),
                                                   fps=frame_rate_hz, macro_block_size=1)
        self._frames.send(None)  # finds the H.264 encoder and starts ffmpeg; raises if it cannot
        self.files = [self._path.name]

    def write(self, frame: np.ndarray) -> None:
        try:
            self._frames.send(np.ascontiguousarray(_pad_to_even(frame)))
        except Exception as err:
            raise RuntimeError(f"ffmpeg stopped while writing {self._path}; frames from here on "
                               f"would be lost: {err}") from err

    def discard(self) -> None:
        self._frames.close()
        self._path.unlink(missing_ok=True)

    def close(self) -> None:
        self._frames.close()  # waits for ffmpeg to finish the file
        # imageio_ffmpeg does not check ffmpeg's exit status; an empty file is how a failure shows.
        if not self._path.is_file() or self._path.stat().st_size == 0:
            raise RuntimeError(f"ffmpeg exited without writing {self._path}; its messages are on "
                               f"stderr")


def _ffmpeg_found() -> bool:
    if imageio_ffmpeg is None:
        return False
    try:
        imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError:
        return False
    return True


class StereoVideoWriter:
    """Writes a run's stereo pairs into ``out_dir`` as they come, holding only the latest pair:

    - ``stereo_sbs.mp4`` (H, 2W) and ``stereo_anaglyph.mp4`` (H, W), H.264 yuv420p with odd
      sizes padded by one black row or column; or, with ``encoder="png"`` or where ffmpeg
      cannot start, ``stereo_sbs/frame_00000.png`` ... and ``stereo_anaglyph/frame_00000.png`` ...
      unpadded;
    - always ``stereo_first_sbs.png`` and ``stereo_first_anaglyph.png`` from the first pair.

    The videos run on simulated time at ``frame_rate_hz`` [frames per simulated second]: video
    frame k (at t0 + k / frame_rate_hz, t0 the first pair's time [s]) shows the latest pair
    added at or before that time, so pairs added faster than the frame rate are dropped and
    slower ones repeated. The last frame is the one at or before the last pair's time.
    """

    def __init__(self, out_dir: Path, *, frame_rate_hz: float, encoder: str = "auto"):
        if (not isinstance(frame_rate_hz, numbers.Real) or not math.isfinite(frame_rate_hz)
                or frame_rate_hz <= 0):
            raise ValueError(f"frame_rate_hz = {frame_rate_hz!r}: must be a finite value > 0 "
                             f"[frames per simulated second]")
        if encoder not in ENCODERS:
            raise ValueError(f"encoder = {encoder!r}: must be 'auto' (MP4 where ffmpeg can "
                             f"encode H.264, else PNG) or 'png'")
        self._out_dir = Path(out_dir)
        self._out_dir.mkdir(parents=True, exist_ok=True)
        self._frame_rate_hz = float(frame_rate_hz)
        # Provisional until the first pair starts ffmpeg, which may still fail.
        self._format = "mp4" if encoder == "auto" and _ffmpeg_found() else "png"
        self._frame_shape = None  # (H, W, 3) of every pair, fixed by the first
        self._t0_s = None
        self._held = None  # (t_s, left, right): the latest pair, not yet in every frame it shows
        self._frames_written = 0
        self._first_files = []
        self._sinks = ()
        self._closed = False

    def __enter__(self) -> "StereoVideoWriter":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def add(self, t_s: float, left: np.ndarray, right: np.ndarray) -> None:
        """Add the pair of eye images rendered at simulated time ``t_s`` [s]: uint8 RGB arrays of
        shape (H, W, 3), the same for both eyes and for the whole run. Copied, so the caller may
        reuse its buffers."""
        if self._closed:
            raise ValueError(f"add(t_s={t_s!r}) after close(): the writer for {self._out_dir} "
                             f"is closed (by close(), leaving its with-block, or an encoder "
                             f"failure)")
        _check_pair(left, right)
        if self._frame_shape is not None and left.shape != self._frame_shape:
            raise ValueError(f"left.shape = {left.shape}: the frame size changed mid-stream; "
                             f"this run's pairs are {self._frame_shape}")
        if not isinstance(t_s, numbers.Real) or not math.isfinite(t_s):
            raise ValueError(f"t_s = {t_s!r}: must be a finite simulated time [s]")
        if self._held is not None and t_s < self._held[0]:
            raise ValueError(f"t_s = {t_s!r}: earlier than the previous pair's {self._held[0]!r} "
                             f"s; pairs must come in time order")
        if self._frame_shape is None:
            self._start(t_s, left, right)
        else:
            # The held pair fills every frame strictly before the new pair's time.
            self._write_held_until(math.ceil(self._frame_of(t_s) - _FRAME_TOLERANCE))
        self._held = (t_s, left.copy(), right.copy())

    def close(self) -> dict:
        """Write the last frames, finish the files and return ``{"frames": video frames written,
        "format": "mp4" | "png", "files": paths relative to out_dir, "frame_rate_hz": ...}``.
        Calling it again only returns the summary."""
        if not self._closed:
            if self._held is not None:
                self._write_held_until(
                    math.floor(self._frame_of(self._held[0]) + _FRAME_TOLERANCE) + 1)
            self._shutdown()
        return {"frames": self._frames_written, "format": self._format,
                "files": self._first_files + [f for sink in self._sinks for f in sink.files],
                "frame_rate_hz": self._frame_rate_hz}

    def _frame_of(self, t_s: float) -> float:
        return (t_s - self._t0_s) * self._frame_rate_hz

    def _start(self, t_s: float, left: np.ndarray, right: np.ndarray) -> None:
        sbs, red_cyan = side_by_side(left, right), anaglyph(left, right)
        for name, image in ((FIRST_SBS_FILE, sbs), (FIRST_ANAGLYPH_FILE, red_cyan)):
            matplotlib.image.imsave(self._out_dir / name, image)
        if self._format == "mp4":
            started = []
            try:
                for name, image in ((SBS_NAME, sbs), (ANAGLYPH_NAME, red_cyan)):
                    started.append(_Mp4Stream(self._out_dir, name, image.shape,
                                              self._frame_rate_hz))
            # Whatever stops ffmpeg from starting (no H.264 encoder, a binary that will not run,
            # output it cannot parse), no frame is lost yet, so PNGs can take over.
            except Exception as err:
                for stream in started:
                    stream.discard()
                warnings.warn(f"ffmpeg could not start ({err!r}); writing PNG sequences to "
                              f"{self._out_dir} instead", RuntimeWarning, stacklevel=3)
                self._format = "png"
            else:
                self._sinks = tuple(started)
        if self._format == "png":
            self._sinks = (_PngSequence(self._out_dir, SBS_NAME),
                           _PngSequence(self._out_dir, ANAGLYPH_NAME))
        # Only once all is in place, so a failure above (a full disk) leaves a retry possible.
        self._first_files = [FIRST_SBS_FILE, FIRST_ANAGLYPH_FILE]
        self._frame_shape = left.shape
        self._t0_s = t_s

    def _write_held_until(self, end_frame: int) -> None:
        """Write the held pair into video frames up to, not including, ``end_frame``; on an
        encoder failure stop every encoder and raise."""
        if self._frames_written >= end_frame:
            return
        _, left, right = self._held
        sbs, red_cyan = side_by_side(left, right), anaglyph(left, right)
        try:
            while self._frames_written < end_frame:
                self._sinks[0].write(sbs)
                self._sinks[1].write(red_cyan)
                self._frames_written += 1
        except RuntimeError:
            with contextlib.suppress(RuntimeError):  # the first failure is the one to report
                self._shutdown()
            raise

    def _shutdown(self) -> None:
        """Finish every file, then raise the first failure."""
        self._closed = True
        self._held = None
        failures = []
        for sink in self._sinks:
            try:
                sink.close()
            except RuntimeError as err:
                failures.append(err)
        if failures:
            raise failures[0]
