"""The stereo view's Meshcat drawing: frustum and outline segments, the glasses pose,
publishing, hiding on a lost head track."""

import struct

import numpy as np
import pytest
from pydrake.geometry import Meshcat
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.analysis import Simulator

from maglev_haptics.systems.rotations import pose_vector, rigid_transform
from maglev_haptics.systems.stereo_visualizer import (
    DISPLAY, EYES, FRUSTA, GLASSES, StereoVisualizer, frustum_segments, outline_segments)

PREFIX = "/stereo_test"
# A 520 x 320 mm active area in the display plane (m), lower-left first, counter-clockwise.
CORNERS_W = np.array([[-0.26, -0.16, 0.0], [0.26, -0.16, 0.0],
                      [0.26, 0.16, 0.0], [-0.26, 0.16, 0.0]])
P_GK_M = np.array([[-0.06, -0.02, 0.0], [0.06, -0.02, 0.0], [0.0, -0.03, 0.005]])
IPD_M = 0.064
# Looking down at the display from the user's side, head a little turned and tilted.
X_WG = RigidTransform(RollPitchYaw(np.pi - 0.5, 0.1, 0.05), [0.02, -0.25, 0.40])


def eyes_of(X: RigidTransform) -> np.ndarray:
    """[left xyz, right xyz] (m): +/- IPD/2 along G's x."""
    return np.concatenate([X @ [-IPD_M / 2, 0, 0], X @ [IPD_M / 2, 0, 0]])


# --- reading back what Meshcat holds (msgpack; only the fields used here) -------

def packed_transform(meshcat: Meshcat, path: str) -> np.ndarray:
    """The 4x4 matrix last set at ``path``: 16 float64s, column by column."""
    packed = meshcat._GetPackedTransform(path)
    start = packed.index(b"\xa6matrix\xdc\x00\x10") + 10
    return np.array(struct.unpack(">" + "xd" * 16, packed[start:start + 144])).reshape(
        4, 4, order="F")


def packed_visible(meshcat: Meshcat, path: str) -> bool:
    packed = meshcat._GetPackedProperty(path, "visible")
    return {0xC2: False, 0xC3: True}[packed[packed.index(b"\xa5value") + 6]]


def packed_segments(meshcat: Meshcat, path: str) -> tuple[np.ndarray, np.ndarray]:
    """(start, end), each (3, N), of the line segments at ``path`` (float32)."""
    packed = meshcat._GetPackedObject(path)
    header = packed.index(b"\xa5array\xc7", packed.index(b"\xa8position")) + 7
    assert packed[header + 1] == 0x17  # three.js's Float32Array extension
    size = packed[header]
    points = np.frombuffer(packed[header + 2:header + 2 + size], "<f4").reshape(-1, 3)
    return points[0::2].T, points[1::2].T


def packed_number(meshcat: Meshcat, path: str, key: str) -> float:
    """The float64 field ``key`` (< 32 characters) of the object at ``path``."""
    packed = meshcat._GetPackedObject(path)
    start = packed.index(bytes([0xA0 | len(key)]) + key.encode() + b"\xcb") + len(key) + 2
    return struct.unpack(">d", packed[start:start + 8])[0]


def packed_color(meshcat: Meshcat, path: str) -> tuple[int, int, int]:
    """(r, g, b), 0-255, of the object's material at ``path``: a uint32 0xRRGGBB."""
    packed = meshcat._GetPackedObject(path)
    start = packed.index(b"\xa5color\xce") + 7
    return tuple(packed[start + 1:start + 4])


@pytest.fixture
def visualizer(meshcat):
    system = StereoVisualizer(meshcat=meshcat, display_corners_W=CORNERS_W, p_GK_m=P_GK_M,
                              prefix=PREFIX)
    yield system
    meshcat.Delete(PREFIX)


def published(visualizer, X_WG_vector, eyes_W):
    context = visualizer.CreateDefaultContext()
    visualizer.GetInputPort("X_WG").FixValue(context, X_WG_vector)
    visualizer.GetInputPort("eye_positions_W").FixValue(context, eyes_W)
    visualizer.ForcedPublish(context)
    return context


# --- module functions -------------------------------------------------------

def test_frustum_runs_from_each_eye_to_each_corner():
    eyes = eyes_of(X_WG).reshape(2, 3)
    start, end = frustum_segments(eyes, CORNERS_W)
    assert start.shape == end.shape == (3, 8)
    assert start.flags["F_CONTIGUOUS"] and end.flags["F_CONTIGUOUS"]
    np.testing.assert_array_equal(start[:, 0:4], np.tile(eyes[0][:, None], 4))
    np.testing.assert_array_equal(start[:, 4:8], np.tile(eyes[1][:, None], 4))
    np.testing.assert_array_equal(end[:, 0:4], CORNERS_W.T)
    np.testing.assert_array_equal(end[:, 4:8], CORNERS_W.T)


def test_frustum_of_one_eye_has_four_segments():
    start, end = frustum_segments(eyes_of(X_WG)[3:6], CORNERS_W)
    assert start.shape == end.shape == (3, 4)
    np.testing.assert_array_equal(start, np.tile(eyes_of(X_WG)[3:6, None], 4))
    np.testing.assert_array_equal(end, CORNERS_W.T)


def test_corners_must_be_four_points():
    with pytest.raises(ValueError, match=r"\(4, 3\)"):
        frustum_segments(np.zeros(3), CORNERS_W[0:3])
    with pytest.raises(ValueError, match=r"\(4, 3\)"):
        outline_segments(CORNERS_W.ravel())


def test_outline_closes_through_the_corners_in_order():
    start, end = outline_segments(CORNERS_W)
    assert start.shape == end.shape == (3, 4)
    np.testing.assert_array_equal(start, CORNERS_W.T)
    np.testing.assert_array_equal(end, CORNERS_W[[1, 2, 3, 0]].T)
    np.testing.assert_allclose(np.linalg.norm(end - start, axis=0), [0.52, 0.32, 0.52, 0.32])


def test_glasses_pose_is_drawn_with_its_quaternion_normalized():
    pose = pose_vector(X_WG)
    pose[0:4] *= 1.001  # a tracker's quaternion is unit only to rounding
    X = rigid_transform(pose)
    np.testing.assert_allclose(X.GetAsMatrix4(), X_WG.GetAsMatrix4(), atol=1e-12)


# --- the system -------------------------------------------------------------

def test_ports(visualizer):
    assert visualizer.num_input_ports() == 2 and visualizer.num_output_ports() == 0
    assert visualizer.GetInputPort("X_WG").size() == 7
    assert visualizer.GetInputPort("eye_positions_W").size() == 6


def test_nothing_tracked_is_shown_before_the_first_publish(meshcat, visualizer):
    for group in (GLASSES, EYES, FRUSTA):
        assert not packed_visible(meshcat, f"{PREFIX}/{group}")
    assert not meshcat.HasPath(f"{PREFIX}/{FRUSTA}/left")
    # The display is static: outlined at construction.
    start, end = packed_segments(meshcat, f"{PREFIX}/{DISPLAY}")
    np.testing.assert_allclose(start, CORNERS_W.T, atol=1e-7)
    np.testing.assert_allclose(end, CORNERS_W[[1, 2, 3, 0]].T, atol=1e-7)


def test_publish_draws_the_glasses_eyes_and_frusta_where_the_inputs_say(meshcat, visualizer):
    eyes = eyes_of(X_WG)
    published(visualizer, pose_vector(X_WG), eyes)
    glasses = f"{PREFIX}/{GLASSES}"
    assert packed_visible(meshcat, glasses)
    np.testing.assert_allclose(packed_transform(meshcat, glasses), X_WG.GetAsMatrix4(),
                               atol=1e-12)
    frame = f"{glasses}/frame"
    assert b"BoxGeometry" in meshcat._GetPackedObject(frame)
    # Wide along G's x (eye to eye), its thin side along the line of sight z.
    assert [packed_number(meshcat, frame, key) for key in ("width", "height", "depth")] == [
        0.150, 0.045, 0.015]
    for k, p_GK in enumerate(P_GK_M):
        marker = f"{glasses}/markers/{k}"
        assert packed_number(meshcat, marker, "radius") == 0.003
        np.testing.assert_allclose(packed_transform(meshcat, marker)[0:3, 3], p_GK)
    for k, name in enumerate(("left", "right")):
        eye, frustum = f"{PREFIX}/{EYES}/{name}", f"{PREFIX}/{FRUSTA}/{name}"
        assert packed_number(meshcat, eye, "radius") == 0.006
        p_WE = eyes[3 * k:3 * k + 3]
        np.testing.assert_allclose(packed_transform(meshcat, eye)[0:3, 3], p_WE)
        start, end = packed_segments(meshcat, frustum)
        np.testing.assert_allclose(start, np.tile(p_WE[:, None], 4), atol=1e-7)
        np.testing.assert_allclose(end, CORNERS_W.T, atol=1e-7)
        assert packed_color(meshcat, frustum) == packed_color(meshcat, eye)
    left_rgb, right_rgb = (packed_color(meshcat, f"{PREFIX}/{EYES}/{name}")
                           for name in ("left", "right"))
    assert left_rgb[2] > left_rgb[0] and right_rgb[0] > right_rgb[2]  # blue, red
    assert packed_color(meshcat, f"{PREFIX}/{DISPLAY}") == (255, 255, 255)
    assert packed_visible(meshcat, f"{PREFIX}/{EYES}")
    assert packed_visible(meshcat, f"{PREFIX}/{FRUSTA}")


def test_periodic_publish_at_30_hz_follows_the_inputs(meshcat, visualizer):
    glasses = f"{PREFIX}/{GLASSES}"
    X_start = RigidTransform([0.0, -0.2, 0.4])
    X_moved = RigidTransform(RollPitchYaw(np.pi, 0, 0), [0.0, -0.1, 0.5])
    context = visualizer.CreateDefaultContext()
    visualizer.GetInputPort("X_WG").FixValue(context, pose_vector(X_start))
    visualizer.GetInputPort("eye_positions_W").FixValue(context, eyes_of(X_start))
    simulator = Simulator(visualizer, context)
    simulator.Initialize()  # publishes at t = 0
    np.testing.assert_allclose(packed_transform(meshcat, glasses), X_start.GetAsMatrix4())
    visualizer.GetInputPort("X_WG").FixValue(context, pose_vector(X_moved))
    simulator.AdvanceTo(0.033)  # (s) just before the next publish at 1/30 s
    np.testing.assert_allclose(packed_transform(meshcat, glasses), X_start.GetAsMatrix4())
    simulator.AdvanceTo(0.034)
    np.testing.assert_allclose(packed_transform(meshcat, glasses), X_moved.GetAsMatrix4(),
                               atol=1e-12)


def test_lost_head_track_hides_and_a_found_one_shows_again(meshcat, visualizer):
    groups = [f"{PREFIX}/{group}" for group in (GLASSES, EYES, FRUSTA)]
    context = published(visualizer, pose_vector(X_WG), eyes_of(X_WG))
    visualizer.GetInputPort("X_WG").FixValue(context, np.full(7, np.nan))
    visualizer.GetInputPort("eye_positions_W").FixValue(context, np.full(6, np.nan))
    visualizer.ForcedPublish(context)
    assert not any(packed_visible(meshcat, group) for group in groups)
    # Left where last seen, not moved to NaN.
    np.testing.assert_allclose(packed_transform(meshcat, groups[0]), X_WG.GetAsMatrix4(),
                               atol=1e-12)
    np.testing.assert_allclose(packed_transform(meshcat, f"{PREFIX}/{EYES}/left")[0:3, 3],
                               eyes_of(X_WG)[0:3])
    start, _ = packed_segments(meshcat, f"{PREFIX}/{FRUSTA}/right")
    np.testing.assert_allclose(start, np.tile(eyes_of(X_WG)[3:6, None], 4), atol=1e-7)
    X_found = RigidTransform(RollPitchYaw(np.pi - 0.2, 0, 0), [0.0, -0.2, 0.45])
    published(visualizer, pose_vector(X_found), eyes_of(X_found))
    assert all(packed_visible(meshcat, group) for group in groups)
    np.testing.assert_allclose(packed_transform(meshcat, groups[0]), X_found.GetAsMatrix4(),
                               atol=1e-12)


def test_each_input_hides_only_what_is_drawn_from_it(meshcat, visualizer):
    published(visualizer, np.full(7, np.nan), eyes_of(X_WG))
    assert not packed_visible(meshcat, f"{PREFIX}/{GLASSES}")
    assert packed_visible(meshcat, f"{PREFIX}/{EYES}")
    assert packed_visible(meshcat, f"{PREFIX}/{FRUSTA}")
    eyes = eyes_of(X_WG)
    eyes[4] = np.nan
    published(visualizer, pose_vector(X_WG), eyes)
    assert packed_visible(meshcat, f"{PREFIX}/{GLASSES}")
    assert not packed_visible(meshcat, f"{PREFIX}/{EYES}")
    assert not packed_visible(meshcat, f"{PREFIX}/{FRUSTA}")
