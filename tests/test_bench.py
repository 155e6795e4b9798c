"""The benchmark's physics floor: the plants and wrench kernels of a tick, alone; the
tissue's kernel and system."""

import pytest

from maglev_haptics.analysis import bench
from maglev_haptics.analysis.bench import floor_us, physics_floor_us
from maglev_haptics.analysis.tissue_bench import tissue_costs
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.scenario import load_scenario


def test_floor_of_a_rigid_scene_adds_its_parts():
    floor = physics_floor_us(load_scenario("peg_in_hole"), other_core_tick_us=None)
    parts = ("station_plant_us", "scene_plant_us", "wrench_matrices_us", "allocation_us")
    assert all(floor[name] > 0 for name in parts)
    assert floor["total_us"] == pytest.approx(sum(floor[name] for name in parts))
    assert "other_core_tick_us" not in floor


def test_lattice_tick_is_listed_not_added():
    floor = physics_floor_us(load_scenario("levitate"), other_core_tick_us=400.0)
    assert "scene_plant_us" not in floor
    assert floor["other_core_tick_us"] == 400.0
    assert floor["total_us"] == pytest.approx(
        floor["station_plant_us"] + floor["wrench_matrices_us"] + floor["allocation_us"])


def test_the_tick_is_judged_against_the_longer_of_the_serial_floor_and_the_lattice():
    assert floor_us({"total_us": 150.0}) == 150.0
    assert floor_us({"total_us": 150.0, "other_core_tick_us": 400.0}) == 400.0
    assert floor_us({"total_us": 500.0, "other_core_tick_us": 400.0}) == 500.0


def test_paced_runs_report_every_tick_of_each_scenario(monkeypatch):
    monkeypatch.setattr(bench, "PACED_SCENARIOS", (("levitate", "square"),))
    results = bench.paced_runs(0.2, progress=False)
    assert list(results) == ["levitate:square"]
    report = results["levitate:square"]
    assert report["ticks"] == 200 and report["slot_us"] == pytest.approx(1000.0)
    assert 0 <= report["deadline_misses"] <= 200
    assert report["tick_compute_us_p50"] <= report["tick_compute_us_p99"] \
        <= report["tick_compute_us_max"]
    # Beside it, the machine alone paced as long at the run's median compute.
    host = report["host_alone"]
    assert host["ticks"] == 200 and host["compute_us"] == report["tick_compute_us_p50"]
    assert host["tick_compute_us_p50"] >= host["compute_us"]


@pytest.mark.slow  # the quick bench itself: about 30 s on a quiet 2-core machine
def test_bench_quick_runs_a_second_a_scenario_no_analysis_and_two_lattice_sizes(tmp_path):
    import json

    from maglev_haptics.analysis.bench import QUICK_DURATION_S, QUICK_LATTICE_SIZES
    from maglev_haptics.cli import main
    assert main(["bench", "--quick", "--json", "--out", str(tmp_path)]) == 0
    results = json.loads((tmp_path / "bench.json").read_text())
    assert {name: row["simulated_s"] for name, row in results["scenarios"].items()} == {
        name: QUICK_DURATION_S for name in results["scenarios"]}
    assert results["analysis"] == {}
    assert len(results["lattice"]["sizes"]) == QUICK_LATTICE_SIZES
    assert "Offline analysis (wall s): not run (--quick)" in results["report"]
    # The loop's thread split callback by callback, in levitation and over the lattice.
    assert set(results["loop_callbacks"]) == {"takeoff_hover_land", "deformable_surface"}
    for name, row in results["loop_callbacks"].items():
        assert row["callbacks_us"]["LevitationLaw._calc_command"] > 0.0
        assert f"  {name:<52}{row['tick_us']:>8.1f}  the tick" in results["report"]
    assert results["loop_callbacks"]["deformable_surface"]["callbacks_us"][
        "DeformableBody._update"] > 0.0
    # The other core's tick as the run ran it, for every scene with a deformable body.
    steps = {name: row["deformable_steps"] for name, row in results["scenarios"].items()
             if "deformable_steps" in row}
    assert set(steps) == {"deformable_surface", "palpate_inclusion", "palpate_organ"}
    for name, bodies in steps.items():
        for body, row in bodies.items():
            assert row["ticks_on_other_core"] > 0.9 * 1000 * QUICK_DURATION_S
            assert row["other_core_tick_us_p50"] > 0.0
            assert any(line.startswith(f"  {name:<20}{body:<30}p50 ")
                       for line in results["report"].splitlines())


def test_the_one_system_loop_hovers_the_instrument_with_the_floors_kernels():
    from maglev_haptics.analysis.loop_floor import floor_loop_us
    for name in bench.FLOOR_LOOP_SCENARIOS:
        result = floor_loop_us(load_scenario("levitate", name), n_ticks=300, windows=1)
        # Held where it was put: a fallen instrument would cost a contact step a tick.
        assert result["drift_m"] < 1e-4


def test_the_one_system_loop_refuses_a_scene_with_a_hand():
    from maglev_haptics.analysis.loop_floor import floor_loop_us
    with pytest.raises(ValueError, match="scenario.hand is set: the one-system loop"):
        floor_loop_us(load_scenario("peg_in_hole"))


def test_every_figure_carries_the_machines_yardsticks(monkeypatch):
    results = {
        "machine": {"takeoff_floor_us": 66.4, "lattice_masses_per_us": 10.96,
                    "lattice_masses": 5474},
        "scenarios": {"takeoff_hover_land": {
            "instrument": "two_magnet", "simulated_s": 1.0, "realtime_factor": 8.0,
            "wall_us_per_1ms_tick": 125.0, "physics_floor": {"total_us": 66.4},
            "tick_over_floor": 1.88}},
        "one_system_loop": {"takeoff_hover_land": {"us_per_tick": 114.0,
                                                   "physics_floor_us": 66.4}},
        "systems_us": {"controller": 12.0}, "wrench_matrix_us": {}, "allocation": {},
        "stereo": {}, "analysis": {}, "lattice": {"sizes": []}}
    monkeypatch.setattr(bench, "format_stereo_report", lambda _: "Stereo:\n  views 3.0 us")
    monkeypatch.setattr(bench, "format_lattice_report", lambda _: "Lattice:\n  5474 600 us")
    report = bench.format_report(results)
    tag = "[takeoff floor 66 us, lattice 11.0 masses/us]"
    figures = [line for line in report.splitlines()
               if line.startswith("  ") and any(ch.isdigit() for ch in line)]
    assert figures and all(line.endswith(tag) for line in figures)
    assert report.splitlines()[-1] == f"Machine yardsticks: {tag} (5474 masses)"


def test_the_yardsticks_say_only_what_was_measured():
    assert bench.machine_yardsticks({}) == ""
    assert bench.machine_yardsticks({"takeoff_floor_us": 70.0}) == "  [takeoff floor 70 us]"
    assert bench.machine_yardsticks({"host_half_load": {"miss_fraction": 0.0068}}) == (
        "  [host alone misses 0.68% at half load]")


def test_tissue_costs_time_the_kernel_and_the_system():
    scenario = load_scenario("palpate_inclusion")
    built = BuildDiagram(scenario)
    (body, costs), = tissue_costs(scenario).items()
    assert body == "slab::palpation_slab"
    tissue = built.haptics.scene.tissue[0]
    assert (costs["tetrahedra"], costs["substeps"]) == (tissue.model.num_tetrahedra,
                                                       tissue.substeps)
    # A tick is at least its substeps' element passes.
    pass_us = costs["tetrahedra"] / costs["tetrahedra_per_us"]
    assert costs["kernel_tick_us"] > costs["substeps"] * pass_us * 0.8
    # The system's synchronous tick is the kernel's and a little more (state copies,
    # the contact): nothing like a second kernel.
    assert 0.5 * costs["kernel_tick_us"] < costs["system_tick_us"] < 1.5 * costs[
        "kernel_tick_us"] + 100.0
