"""Stereo recordings: the side-by-side and anaglyph images, the PNG sequences, the MP4 videos
read back with ffmpeg, frames placed on simulated time, and the errors for bad input."""

import math

import matplotlib.image
import numpy as np
import pytest

from maglev_haptics.analysis import stereo_video
from maglev_haptics.analysis.stereo_video import StereoVideoWriter, anaglyph, side_by_side

RNG = np.random.default_rng(7)


def _random_eye(height: int, width: int) -> np.ndarray:
    return RNG.integers(0, 256, size=(height, width, 3), dtype=np.uint8)


def _solid(height: int, width: int, rgb) -> np.ndarray:
    return np.broadcast_to(np.array(rgb, dtype=np.uint8), (height, width, 3)).copy()


def _read_png(path) -> np.ndarray:
    """A PNG written by the writer as uint8 RGB (imread gives RGBA floats in [0, 1])."""
    return np.round(matplotlib.image.imread(path)[..., :3] * 255).astype(np.uint8)


def _read_mp4(path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    reader = imageio_ffmpeg.read_frames(str(path))
    width, height = next(reader)["size"]
    frames = [np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3) for data in reader]
    return (height, width), frames


def test_side_by_side_puts_left_left_and_right_right():
    left, right = _random_eye(5, 7), _random_eye(5, 7)
    sbs = side_by_side(left, right)
    assert sbs.shape == (5, 14, 3) and sbs.dtype == np.uint8
    np.testing.assert_array_equal(sbs[:, :7], left)
    np.testing.assert_array_equal(sbs[:, 7:], right)


def test_anaglyph_takes_red_from_left_green_and_blue_from_right():
    left, right = _random_eye(5, 7), _random_eye(5, 7)
    left_before, right_before = left.copy(), right.copy()
    red_cyan = anaglyph(left, right)
    assert red_cyan.shape == (5, 7, 3) and red_cyan.dtype == np.uint8
    np.testing.assert_array_equal(red_cyan[..., 0], left[..., 0])
    np.testing.assert_array_equal(red_cyan[..., 1:], right[..., 1:])
    np.testing.assert_array_equal(left, left_before)
    np.testing.assert_array_equal(right, right_before)


def test_png_sequences_hold_every_pair_and_the_first_pair(tmp_path):
    pairs = [(_random_eye(5, 7), _random_eye(5, 7)) for _ in range(3)]  # odd sizes stay unpadded
    with StereoVideoWriter(tmp_path, frame_rate_hz=30.0, encoder="png") as writer:
        for k, (left, right) in enumerate(pairs):
            writer.add(k / 30.0, left, right)
    summary = writer.close()

    sbs_files = [f"stereo_sbs/frame_{k:05d}.png" for k in range(3)]
    anaglyph_files = [f"stereo_anaglyph/frame_{k:05d}.png" for k in range(3)]
    assert summary == {"frames": 3, "format": "png", "frame_rate_hz": 30.0,
                       "files": ["stereo_first_sbs.png", "stereo_first_anaglyph.png",
                                 *sbs_files, *anaglyph_files]}
    for (left, right), sbs_file, anaglyph_file in zip(pairs, sbs_files, anaglyph_files):
        np.testing.assert_array_equal(_read_png(tmp_path / sbs_file), side_by_side(left, right))
        np.testing.assert_array_equal(_read_png(tmp_path / anaglyph_file), anaglyph(left, right))
    np.testing.assert_array_equal(_read_png(tmp_path / "stereo_first_sbs.png"),
                                  side_by_side(*pairs[0]))
    np.testing.assert_array_equal(_read_png(tmp_path / "stereo_first_anaglyph.png"),
                                  anaglyph(*pairs[0]))


def test_frames_sample_the_latest_pair_on_simulated_time(tmp_path):
    # One buffer per eye, refilled in place as a renderer would: add() must copy.
    left, right = np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2, 3), np.uint8)
    writer = StereoVideoWriter(tmp_path, frame_rate_hz=10.0, encoder="png")
    for t_s, value in ((0.0, 10), (0.05, 20), (0.1, 30), (0.4, 40)):
        left[:], right[:] = value, value
        writer.add(t_s, left, right)
    summary = writer.close()

    # Frames at 0, 0.1, ..., 0.4 s: the pair at 0.05 s is replaced before 0.1 s, the one at
    # 0.1 s is held through the gap, and the last frame is at the last pair's time.
    assert summary["frames"] == 5
    shown = [_read_png(tmp_path / f"stereo_sbs/frame_{k:05d}.png")[0, 0, 0] for k in range(5)]
    assert shown == [10, 30, 30, 30, 40]


@pytest.mark.parametrize("times_s", [
    [k * 0.1 for k in range(10)],  # 3 * 0.1 = 0.30000000000000004: just after frame 3
    [0.1, 0.2, 0.3],  # (0.3 - 0.1) * 10 = 1.9999999999999998: the last pair just before frame 2
])
def test_pairs_at_the_frame_rate_give_one_frame_each_despite_round_off(tmp_path, times_s):
    writer = StereoVideoWriter(tmp_path, frame_rate_hz=10.0, encoder="png")
    for k, t_s in enumerate(times_s):
        eye = np.full((2, 2, 3), 10 * k, np.uint8)
        writer.add(t_s, eye, eye)
    assert writer.close()["frames"] == len(times_s)
    shown = [_read_png(tmp_path / f"stereo_anaglyph/frame_{k:05d}.png")[0, 0, 0]
             for k in range(len(times_s))]
    assert shown == [10 * k for k in range(len(times_s))]


def test_mp4_videos_have_every_frame_padded_to_even_sizes(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    height, width, n_frames = 31, 45, 12  # odd: one black row and column are added
    left_rgb, right_rgb = (200, 40, 60), (30, 120, 220)
    left, right = _solid(height, width, left_rgb), _solid(height, width, right_rgb)
    with StereoVideoWriter(tmp_path, frame_rate_hz=24.0) as writer:
        for k in range(n_frames):
            writer.add(k / 24.0, left, right)
    summary = writer.close()
    assert summary == {"frames": n_frames, "format": "mp4", "frame_rate_hz": 24.0,
                       "files": ["stereo_first_sbs.png", "stereo_first_anaglyph.png",
                                 "stereo_sbs.mp4", "stereo_anaglyph.mp4"]}
    for name in ("stereo_sbs.mp4", "stereo_anaglyph.mp4"):
        assert (tmp_path / name).stat().st_size > 0

    size, frames = _read_mp4(tmp_path / "stereo_sbs.mp4")
    assert size == (32, 90) and len(frames) == n_frames
    frame = frames[n_frames // 2].astype(float)
    # Lossy codec and 4:2:0 colour: compare means away from the edges, within 8 levels.
    np.testing.assert_allclose(frame[4:-4, 4:40].mean(axis=(0, 1)), left_rgb, atol=8)
    np.testing.assert_allclose(frame[4:-4, 50:86].mean(axis=(0, 1)), right_rgb, atol=8)

    size, frames = _read_mp4(tmp_path / "stereo_anaglyph.mp4")
    assert size == (32, 46) and len(frames) == n_frames
    frame = frames[n_frames // 2].astype(float)
    np.testing.assert_allclose(frame[4:-4, 4:-4].mean(axis=(0, 1)),
                               (left_rgb[0], right_rgb[1], right_rgb[2]), atol=8)
    # The added column is black (its colour is shared with the image's last column in 4:2:0).
    assert frame[4:-4, -1].mean() < 40


def test_first_pair_is_also_written_as_png_next_to_the_videos(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    left, right = _random_eye(4, 6), _random_eye(4, 6)
    with StereoVideoWriter(tmp_path, frame_rate_hz=5.0) as writer:
        writer.add(2.0, left, right)
    assert writer.close()["frames"] == 1
    np.testing.assert_array_equal(_read_png(tmp_path / "stereo_first_sbs.png"),
                                  side_by_side(left, right))
    np.testing.assert_array_equal(_read_png(tmp_path / "stereo_first_anaglyph.png"),
                                  anaglyph(left, right))


def test_auto_falls_back_to_png_without_imageio_ffmpeg(tmp_path, monkeypatch):
    monkeypatch.setattr(stereo_video, "imageio_ffmpeg", None)
    eye = _random_eye(4, 6)
    with StereoVideoWriter(tmp_path, frame_rate_hz=10.0) as writer:
        writer.add(0.0, eye, eye)
    assert writer.close()["format"] == "png"
    np.testing.assert_array_equal(_read_png(tmp_path / "stereo_sbs/frame_00000.png"),
                                  side_by_side(eye, eye))
    assert not list(tmp_path.glob("*.mp4"))


def test_auto_falls_back_to_png_when_ffmpeg_cannot_start(tmp_path, monkeypatch):
    pytest.importorskip("imageio_ffmpeg")
    monkeypatch.setenv("IMAGEIO_FFMPEG_EXE", str(tmp_path / "no_such_ffmpeg"))
    eye = _random_eye(4, 6)
    writer = StereoVideoWriter(tmp_path, frame_rate_hz=10.0)
    with pytest.warns(RuntimeWarning, match="ffmpeg could not start"):
        writer.add(0.0, eye, eye)  # the first pair starts ffmpeg
    writer.add(0.1, eye, eye)
    summary = writer.close()
    assert summary["format"] == "png" and summary["frames"] == 2
    assert (tmp_path / "stereo_anaglyph/frame_00001.png").is_file()
    assert not list(tmp_path.glob("*.mp4"))


def test_ffmpeg_dying_mid_stream_raises_and_closes(tmp_path, monkeypatch):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")

    def write_frames_then_break(path, size, **kwargs):
        yield  # started
        for _ in range(2):
            yield  # two frames accepted
        raise OSError("[Errno 32] Broken pipe")

    monkeypatch.setattr(imageio_ffmpeg, "write_frames", write_frames_then_break)
    eye = _random_eye(4, 6)
    writer = StereoVideoWriter(tmp_path, frame_rate_hz=10.0)
    for k in range(3):
        writer.add(k / 10.0, eye, eye)
    with pytest.raises(RuntimeError, match="ffmpeg stopped while writing .*stereo_sbs.mp4"):
        writer.add(0.3, eye, eye)
    with pytest.raises(ValueError, match="after close"):
        writer.add(0.4, eye, eye)
    assert writer.close()["frames"] == 2


def test_ffmpeg_exiting_without_a_file_fails_close(tmp_path, monkeypatch):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")

    def write_frames_to_nowhere(path, size, **kwargs):
        while True:
            yield

    monkeypatch.setattr(imageio_ffmpeg, "write_frames", write_frames_to_nowhere)
    eye = _random_eye(4, 6)
    writer = StereoVideoWriter(tmp_path, frame_rate_hz=10.0)
    writer.add(0.0, eye, eye)
    with pytest.raises(RuntimeError, match="exited without writing .*stereo_sbs.mp4"):
        writer.close()


def test_close_is_idempotent(tmp_path):
    eye = _random_eye(4, 6)
    with StereoVideoWriter(tmp_path, frame_rate_hz=10.0, encoder="png") as writer:
        writer.add(0.0, eye, eye)
        first = writer.close()
    assert writer.close() == first and first["frames"] == 1
    assert sorted(p.name for p in (tmp_path / "stereo_sbs").iterdir()) == ["frame_00000.png"]


def test_no_pairs_writes_nothing(tmp_path):
    summary = StereoVideoWriter(tmp_path, frame_rate_hz=10.0, encoder="png").close()
    assert summary == {"frames": 0, "format": "png", "files": [], "frame_rate_hz": 10.0}
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("frame_rate_hz", [0.0, -30.0, math.nan, math.inf, "30"])
def test_bad_frame_rate_is_named(tmp_path, frame_rate_hz):
    with pytest.raises(ValueError, match=r"frame_rate_hz = .*must be a finite value > 0"):
        StereoVideoWriter(tmp_path, frame_rate_hz=frame_rate_hz)


def test_unknown_encoder_is_named(tmp_path):
    with pytest.raises(ValueError, match=r"encoder = 'mp5': must be 'auto' .* or 'png'"):
        StereoVideoWriter(tmp_path, frame_rate_hz=10.0, encoder="mp5")


GOOD = np.zeros((4, 6, 3), np.uint8)
BAD_PAIRS = [
    (np.zeros((4, 6, 3), np.float64), GOOD, r"left: got dtype float64 and shape \(4, 6, 3\)"),
    (GOOD, np.zeros((4, 6), np.uint8), r"right: got dtype uint8 and shape \(4, 6\)"),
    (np.zeros((4, 6, 4), np.uint8), GOOD, r"left: .*shape \(4, 6, 4\); expected .*\(H, W, 3\)"),
    (np.zeros((0, 6, 3), np.uint8), GOOD, r"left: .*shape \(0, 6, 3\).*H, W >= 1"),
    ([[0]], GOOD, "left: got a list; expected a numpy uint8 RGB array"),
    (GOOD, np.zeros((4, 8, 3), np.uint8),
     r"right.shape = \(4, 8, 3\) differs from left.shape = \(4, 6, 3\)"),
]


@pytest.mark.parametrize("left, right, message", BAD_PAIRS)
def test_bad_images_are_named(tmp_path, left, right, message):
    with pytest.raises(ValueError, match=message):
        side_by_side(left, right)
    with pytest.raises(ValueError, match=message):
        anaglyph(left, right)
    writer = StereoVideoWriter(tmp_path, frame_rate_hz=10.0, encoder="png")
    with pytest.raises(ValueError, match=message):
        writer.add(0.0, left, right)
    assert writer.close()["files"] == []


def test_frame_size_change_mid_stream_is_refused(tmp_path):
    writer = StereoVideoWriter(tmp_path, frame_rate_hz=10.0, encoder="png")
    writer.add(0.0, GOOD, GOOD)
    bigger = np.zeros((6, 6, 3), np.uint8)
    with pytest.raises(ValueError, match=r"left.shape = \(6, 6, 3\): the frame size changed "
                                         r"mid-stream; this run's pairs are \(4, 6, 3\)"):
        writer.add(0.1, bigger, bigger)


@pytest.mark.parametrize("t_s, message", [
    (math.nan, "t_s = nan: must be a finite simulated time"),
    (None, "t_s = None: must be a finite simulated time"),
    (0.5, r"t_s = 0.5: earlier than the previous pair's 1.0 s"),
])
def test_bad_times_are_named(tmp_path, t_s, message):
    writer = StereoVideoWriter(tmp_path, frame_rate_hz=10.0, encoder="png")
    writer.add(1.0, GOOD, GOOD)
    with pytest.raises(ValueError, match=message):
        writer.add(t_s, GOOD, GOOD)


def test_add_after_close_is_refused(tmp_path):
    writer = StereoVideoWriter(tmp_path, frame_rate_hz=10.0, encoder="png")
    writer.close()
    with pytest.raises(ValueError, match=r"add\(t_s=0.0\) after close\(\)"):
        writer.add(0.0, GOOD, GOOD)
