"""Per-eye off-axis views: projection matrices, cameras and actual renders against
the geometry of the display window."""

import time

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.multibody.tree import SpatialInertia
from pydrake.geometry import Sphere
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from maglev_haptics.hardware.device import DisplaySpec, GlassesSpec
from maglev_haptics.systems.head_sensor import glasses_pose
from maglev_haptics.systems.stereo import (
    StereoView, display_rectangle, eye_camera, eye_positions_W, off_axis_projection,
    projected_pixel, screen_pixel, screen_point)
from maglev_haptics.systems.stereo_renderer import (
    AddStereoRenderer, StereoRenderer, SurfaceLayer, vertex_normals)

SCREEN = display_rectangle(DisplaySpec())
# Grey, so that a pixel of the sphere tells from the background however dark its shading.
BACKGROUND_RGB = (0.5, 0.5, 0.5)
BACKGROUND_PIXEL = np.array([128, 128, 128], dtype=np.uint8)
IPD_M = GlassesSpec().ipd_m


def random_eyes(rng, n):
    """Eyes 0.25-0.7 m above the display, anywhere over a region twice its size."""
    return np.column_stack([rng.uniform(-0.45, 0.45, n), rng.uniform(-0.5, 0.3, n),
                            rng.uniform(0.25, 0.7, n)])


def random_points(rng, n):
    """Virtual points in the display's volume: 8 cm below to 6 cm above it."""
    return np.column_stack([rng.uniform(-0.18, 0.18, n), rng.uniform(-0.11, 0.11, n),
                            rng.uniform(-0.08, 0.06, n)])


def through_display_pixel(eye, p_W):
    return screen_pixel(SCREEN, screen_point(SCREEN, eye, p_W))


def test_projection_pixel_is_where_the_eye_ray_meets_the_display():
    rng = np.random.default_rng(1)
    for eye in random_eyes(rng, 50):
        P = off_axis_projection(SCREEN.pa, SCREEN.pb, SCREEN.pc, eye, 0.05, 2.0)
        for p_W in random_points(rng, 10):
            pixel = projected_pixel(P, p_W, SCREEN.width_px, SCREEN.height_px)
            np.testing.assert_allclose(pixel, through_display_pixel(eye, p_W), atol=1e-6)


def test_projection_is_kooimas_P_Mt_T():
    # Written out as matrices, for one off-centre eye: the compiled projection is
    # checked against the paper's formula, not against itself.
    eye, near, far = np.array([0.07, -0.21, 0.43]), 0.05, 2.0
    vr, vu, vn = SCREEN.axes
    distance = (eye - SCREEN.pa) @ vn
    scale = near / distance
    left, right = vr @ (SCREEN.pa - eye) * scale, vr @ (SCREEN.pb - eye) * scale
    bottom, top = vu @ (SCREEN.pa - eye) * scale, vu @ (SCREEN.pc - eye) * scale
    P = np.array([[2 * near / (right - left), 0, (right + left) / (right - left), 0],
                  [0, 2 * near / (top - bottom), (top + bottom) / (top - bottom), 0],
                  [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
                  [0, 0, -1, 0]])
    Mt, T = np.eye(4), np.eye(4)
    Mt[0:3, 0:3] = [vr, vu, vn]
    T[0:3, 3] = -eye
    np.testing.assert_allclose(off_axis_projection(SCREEN.pa, SCREEN.pb, SCREEN.pc, eye, near, far),
                               P @ Mt @ T, rtol=1e-12, atol=1e-12)


def test_display_corners_map_to_the_image_corners():
    eye = np.array([0.3, -0.4, 0.35])  # far off-centre
    P = off_axis_projection(SCREEN.pa, SCREEN.pb, SCREEN.pc, eye, 0.05, 2.0)
    W, H = SCREEN.width_px, SCREEN.height_px
    expected = [(-0.5, H - 0.5), (W - 0.5, H - 0.5), (W - 0.5, -0.5), (-0.5, -0.5)]
    for corner, pixel in zip(SCREEN.corners_W, expected):
        np.testing.assert_allclose(projected_pixel(P, corner, W, H), pixel, atol=1e-6)


def test_pinhole_camera_agrees_with_the_projection():
    rng = np.random.default_rng(2)
    for eye in random_eyes(rng, 20):
        R_WC, p_WC, fx, fy, cx, cy = eye_camera(SCREEN, eye, SCREEN.width_px, SCREEN.height_px)
        np.testing.assert_allclose(R_WC.T @ R_WC, np.eye(3), atol=1e-12)
        assert np.linalg.det(R_WC) == pytest.approx(1.0)
        for p_W in random_points(rng, 5):
            p_C = R_WC.T @ (p_W - p_WC)
            pixel = [fx * p_C[0] / p_C[2] + cx, fy * p_C[1] / p_C[2] + cy]
            np.testing.assert_allclose(pixel, through_display_pixel(eye, p_W), atol=1e-6)


def test_zero_parallax_on_the_display_and_uncrossed_below():
    rng = np.random.default_rng(3)
    for eye_mid in random_eyes(rng, 20):
        head = np.concatenate([eye_mid, [0.0, 0.0, 0.0], [rng.uniform(-0.5, 0.5), 0.0]])
        q_WG, p_WG = glasses_pose(head)
        left, right = eye_positions_W(q_WG, p_WG, IPD_M)
        on_screen = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.12, 0.12), 0.0])
        np.testing.assert_allclose(through_display_pixel(left, on_screen),
                                   through_display_pixel(right, on_screen), atol=1e-9)
        # Disparity along the eye axis, as the screen shows it: right minus left.
        eye_axis = (right - left)[0:2]
        for depth in (0.01, 0.04, 0.1):
            below = on_screen - [0.0, 0.0, depth]
            shift = screen_point(SCREEN, right, below) - screen_point(SCREEN, left, below)
            assert np.dot(shift[0:2], eye_axis) > 0  # uncrossed
            above = on_screen + [0.0, 0.0, depth]
            shift = screen_point(SCREEN, right, above) - screen_point(SCREEN, left, above)
            assert np.dot(shift[0:2], eye_axis) < 0  # crossed, in front of the screen


def test_bad_display_eye_and_ipd_are_refused():
    with pytest.raises(ValueError, match=r"device.display.size_m = \[0.0, 0.3\].*positive"):
        display_rectangle(DisplaySpec(size_m=[0.0, 0.3]))
    with pytest.raises(ValueError, match=r"resolution_px"):
        display_rectangle(DisplaySpec(resolution_px=[1680, 0]))
    with pytest.raises(ValueError, match=r"mm in front of the display plane"):
        off_axis_projection(SCREEN.pa, SCREEN.pb, SCREEN.pc, [0.0, 0.0, -0.1], 0.05, 2.0)
    with pytest.raises(ValueError, match=r"near, far = 0.5, 0.1"):
        off_axis_projection(SCREEN.pa, SCREEN.pb, SCREEN.pc, [0.0, 0.0, 0.5], 0.5, 0.1)
    for ipd in (0.035, 0.09):
        with pytest.raises(ValueError, match=rf"ipd_m = {ipd}: must be within 0.040-0.080"):
            StereoView(screen=SCREEN, ipd_m=ipd, period_s=1 / 120, near_m=0.05, far_m=2.0)


def _view_context(view, x_WG):
    context = view.CreateDefaultContext()
    view.get_input_port().FixValue(context, x_WG)
    state = view.EvalUniquePeriodicDiscreteUpdate(context)
    context.SetDiscreteState(state)
    return context


def test_stereo_view_outputs_and_freezes_on_a_bad_pose():
    view = new_view()
    q_WG, p_WG = glasses_pose([0.05, -0.3, 0.45, 0.0, 0.0, 0.0, 0.1, 0.0])
    context = _view_context(view, np.concatenate([q_WG, p_WG]))
    eyes = view.GetOutputPort("eye_positions_W").Eval(context).reshape(2, 3)
    np.testing.assert_allclose(eyes, eye_positions_W(q_WG, p_WG, IPD_M))
    P_left = view.GetOutputPort("projection_left").Eval(context).reshape(4, 4)
    np.testing.assert_allclose(P_left, off_axis_projection(
        SCREEN.pa, SCREEN.pb, SCREEN.pc, eyes[0], 0.05, 2.0))
    assert view.GetOutputPort("view_ok").Eval(context)[0] == 1.0
    good = view.GetOutputPort("camera_right").Eval(context).copy()
    # No pose; the glasses below the screen; an eye exactly on its plane (zero distance).
    for bad in (np.full(7, np.nan), np.array([1.0, 0, 0, 0, 0.0, 0.0, -0.2]),
                np.array([1.0, 0, 0, 0, 0.0, 0.0, 0.0])):
        view.get_input_port().FixValue(context, bad)
        context.SetDiscreteState(view.EvalUniquePeriodicDiscreteUpdate(context))
        assert view.GetOutputPort("view_ok").Eval(context)[0] == 0.0
        np.testing.assert_array_equal(view.GetOutputPort("camera_right").Eval(context), good)


def sphere_diagram(max_wall_share=None, sink=lambda *frame: None, surface=None,
                   wall_clock=time.perf_counter):
    """A small bright sphere (4 mm radius) on a free body, and the stereo display's
    renderer (cameras and view_ok exported as inputs)."""
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, 0.0)
    body = plant.AddRigidBody("marker", SpatialInertia.SolidSphereWithMass(0.01, 0.002))
    plant.RegisterVisualGeometry(body, RigidTransform(), Sphere(0.004), "marker",
                                 np.array([1.0, 1.0, 1.0, 1.0]))
    plant.Finalize()
    AddStereoRenderer(scene_graph, background_rgb=BACKGROUND_RGB)
    image_px = (SCREEN.width_px // 2, SCREEN.height_px // 2)
    renderer = builder.AddSystem(StereoRenderer(
        rate_hz=30.0, image_px=image_px, display_px=(SCREEN.width_px, SCREEN.height_px),
        near_m=0.05, far_m=2.0, sink=sink, max_wall_share=max_wall_share, surface=surface,
        wall_clock=wall_clock))
    if surface is not None:
        builder.ExportInput(renderer.GetInputPort("surface_positions_m"), "surface_positions_m")
    builder.Connect(scene_graph.get_query_output_port(), renderer.GetInputPort("query_object"))
    builder.ExportInput(renderer.GetInputPort("camera_left"), "camera_left")
    builder.ExportInput(renderer.GetInputPort("camera_right"), "camera_right")
    builder.ExportInput(renderer.GetInputPort("view_ok"), "view_ok")
    diagram = builder.Build()
    return diagram, plant, body, renderer, image_px


def new_view():
    return StereoView(screen=SCREEN, ipd_m=IPD_M, period_s=1 / 120, near_m=0.05, far_m=2.0)


SEATED_HEAD = [0.0, -0.3, 0.45, 0.0, 0.0, 0.0, 0.0, 0.0]


def fix_views(diagram, context, head):
    """The renderer diagram's cameras and view_ok fixed to the views for ``head``
    (a head_pose vector); returns the view system's context."""
    view = new_view()
    q_WG, p_WG = glasses_pose(head)
    view_context = _view_context(view, np.concatenate([q_WG, p_WG]))
    for name in ("camera_left", "camera_right"):
        diagram.GetInputPort(name).FixValue(context, view.GetOutputPort(name).Eval(view_context))
    diagram.GetInputPort("view_ok").FixValue(context, [1.0])
    return view, view_context


@pytest.fixture(scope="module")
def sphere_scene():
    return sphere_diagram()


def test_rendered_sphere_lies_where_the_eye_ray_meets_the_display(sphere_scene):
    diagram, plant, body, renderer, image_px = sphere_scene
    scale = image_px[0] / SCREEN.width_px
    rng = np.random.default_rng(4)
    for eye_mid, p_W in zip(random_eyes(rng, 6), random_points(rng, 6)):
        context = diagram.CreateDefaultContext()
        plant.SetFreeBodyPose(plant.GetMyMutableContextFromRoot(context), body,
                              RigidTransform(p_W))
        view, view_context = fix_views(diagram, context,
                                       np.concatenate([eye_mid, [0.0, 0.0, 0.0, 0.0, 0.0]]))
        images = renderer.render(renderer.GetMyContextFromRoot(context))
        eyes = view.GetOutputPort("eye_positions_W").Eval(view_context).reshape(2, 3)
        for eye, image in zip(eyes, images):
            rows, columns = np.nonzero(np.any(image != BACKGROUND_PIXEL, axis=2))
            assert len(rows) >= 3, "the sphere must show"
            expected = (through_display_pixel(eye, p_W) + 0.5) * scale - 0.5
            centroid = np.array([columns.mean(), rows.mean()])
            assert np.linalg.norm(centroid - expected) < 0.5, (eye, p_W, centroid, expected)


class RenderCostClock:
    """A wall clock that runs with simulated time, plus ``render_s`` (s) for each frame
    rendered: the renderer reads it once per frame, and once more after a render,
    at the same simulated time. The skip rule, free of the host's speed."""

    def __init__(self, render_s: float):
        self.render_s, self.rendering_s, self.context, self.last_t = render_s, 0.0, None, None

    def __call__(self) -> float:
        t = self.context.get_time()
        if t == self.last_t:
            self.rendering_s += self.render_s
        self.last_t = t
        return t + self.rendering_s


def test_real_time_rendering_skips_frames_within_its_share_of_the_wall_clock():
    frames = []
    clock = RenderCostClock(render_s=0.040)
    diagram, plant, body, renderer, _ = sphere_diagram(
        max_wall_share=0.25, sink=lambda t, left, right: frames.append(t), wall_clock=clock)
    simulator = Simulator(diagram)
    clock.context = simulator.get_context()
    fix_views(diagram, simulator.get_mutable_context(), SEATED_HEAD)
    simulator.AdvanceTo(1.0)  # 31 frames due at 30 Hz
    assert renderer.frames_rendered + renderer.frames_skipped == 31
    assert len(frames) == renderer.frames_rendered
    assert renderer.render_wall_s == pytest.approx(0.040 * renderer.frames_rendered)
    # 40 ms renders within a 25% share of the wall clock let 0.25 / 0.75 * 33 / 40
    # = 28% of the frames through: 8-9 of 31.
    assert 7 <= renderer.frames_rendered <= 10


def square_mesh(half_width_m: float, z_m: float):
    """Two counter-clockwise triangles: a horizontal square (4 vertices, 2 faces)."""
    h = half_width_m
    positions = np.array([[-h, -h, z_m], [h, -h, z_m], [h, h, z_m], [-h, h, z_m]])
    return positions, np.array([[0, 1, 2], [0, 2, 3]])


def test_vertex_normals_of_a_flat_square_point_up():
    positions, triangles = square_mesh(0.01, 0.0)
    np.testing.assert_allclose(vertex_normals(positions, triangles), np.tile([0, 0, 1.0], (4, 1)))


@pytest.mark.parametrize("surface_z_m, sphere_hidden", [(-0.02, False), (0.02, True)])
def test_surface_layer_is_drawn_where_it_is_nearer(surface_z_m, sphere_hidden):
    """A green square under the sphere leaves it seen; over it, hides it."""
    positions, triangles = square_mesh(0.03, surface_z_m)
    layer = SurfaceLayer(triangles, (0.0, 1.0, 0.0, 1.0))
    diagram, plant, body, renderer, image_px = sphere_diagram(surface=layer)
    context = diagram.CreateDefaultContext()
    plant.SetFreeBodyPose(plant.GetMyMutableContextFromRoot(context), body, RigidTransform())
    view, view_context = fix_views(diagram, context, SEATED_HEAD)
    diagram.GetInputPort("surface_positions_m").FixValue(context, positions.ravel())
    eye = view.GetOutputPort("eye_positions_W").Eval(view_context)[0:3]
    left, _ = renderer.render(renderer.GetMyContextFromRoot(context))
    scale = image_px[0] / SCREEN.width_px
    u, v = np.round((through_display_pixel(eye, np.zeros(3)) + 0.5) * scale - 0.5).astype(int)
    sphere_pixel = left[v, u].astype(int)
    green = sphere_pixel[1] > 100 and sphere_pixel[0] < 40 and sphere_pixel[2] < 40
    assert green == sphere_hidden, sphere_pixel
    corner = (through_display_pixel(eye, [0.025, 0.025, surface_z_m]) + 0.5) * scale - 0.5
    u, v = np.round(corner).astype(int)
    assert left[v, u, 1] > 100 and left[v, u, 0] < 40  # the square shows off the sphere
