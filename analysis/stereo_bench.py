"""``maglev bench``'s stereo display numbers: the per-eye view matrices per frame,
the head predictor's and the view system's updates, and a rendered stereo frame pair (the peg-in-hole
scene through Drake's VTK renderer) at the default image size and at the panel's
full resolution."""

from typing import Dict

from maglev_haptics.analysis.timing import leaf_system_costs, time_per_call_us
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.runner import simulate
from maglev_haptics.diagrams.scenario import load_scenario, with_stereo
from maglev_haptics.systems.head_sensor import glasses_pose
from maglev_haptics.systems.stereo_renderer import StereoRenderer

PAIRS_TIMED = 10  # renders per size


def stereo_costs() -> Dict:
    scenario = with_stereo(load_scenario("peg_in_hole"), "peg_in_hole --stereo")
    built = BuildDiagram(scenario, frame_sink=lambda *frame: None)
    simulator, _, _ = simulate(built, 0.2, progress=False)
    view = built.stereo.view
    q_WG, p_WG = glasses_pose(scenario.stereo.head.start.vector())
    context = simulator.get_context()
    results = {
        "view_matrices_both_eyes_us": time_per_call_us(lambda: view.view_vector(q_WG, p_WG), 2000),
        # One update each (outputs and discrete update, inputs re-fixed), as for the loop.
        "systems_us": leaf_system_costs(built, context, n=1000,
                                        only={"head_pose_predictor", "stereo_view"}),
        "render_pair_ms": {},
    }
    renderer = built.stereo.renderer
    display_px = scenario.device.display.resolution_px
    for size in (tuple(scenario.stereo.images.size_px), tuple(display_px)):
        sized = StereoRenderer(rate_hz=1.0, image_px=size, display_px=display_px,
                               near_m=scenario.stereo.near_m, far_m=scenario.stereo.far_m,
                               sink=lambda *frame: None)
        # Same inputs as the diagram's renderer; only the image size differs.
        sized_context = sized.CreateDefaultContext()
        renderer_context = renderer.GetMyContextFromRoot(context)
        for i in range(renderer.num_input_ports()):
            port = renderer.get_input_port(i)
            sized.get_input_port(i).FixValue(sized_context, port.Eval(renderer_context))
        sized.render(sized_context)  # first render builds the VTK pipeline, off the clock
        results["render_pair_ms"][f"{size[0]}x{size[1]}"] = 1e-3 * time_per_call_us(
            lambda: sized.render(sized_context), PAIRS_TIMED)
    return results


def format_stereo_report(results: Dict) -> str:
    lines = ["Stereo display:",
             f"  view matrices, both eyes (projection + camera) {results['view_matrices_both_eyes_us']:.1f} us a frame"]
    for name, us in results["systems_us"].items():
        lines.append(f"  {name + ' update':<47}{us:.1f} us a frame")
    for size, ms in results["render_pair_ms"].items():
        lines.append(f"  rendered stereo pair {size:<26}{ms:.1f} ms")
    return "\n".join(lines)
