"""The ``maglev`` command line (DESIGN.md section 8)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from maglev_haptics.diagrams.scenario import (
    ScenarioError, load_scenario, resolve_scenario_file, scenario_names, shipped_scenario_files)


def _add_scenario_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help="a scenario file's path, or the name of a shipped one "
                        "(" + ", ".join(p.stem for p in shipped_scenario_files()) + ")")
    parser.add_argument("--name", help="which named scenario in the file (default: the first)")
    parser.add_argument("--scenario-text", default="{}",
                        help="YAML layered over the scenario, e.g. "
                        "'{device: {instrument: four_magnet}}'")


def _load(args):
    scenario = load_scenario(args.scenario, args.name, args.scenario_text)
    path = resolve_scenario_file(args.scenario)
    name = args.name or scenario_names(path)[0]
    return scenario, f"{path.stem}:{name}"


def _cmd_run(args) -> int:
    from maglev_haptics.diagrams.haptics import interactive_variant
    from maglev_haptics.analysis.run_results import run_scenario
    from maglev_haptics.diagrams.scenario import with_stereo

    if args.duration is not None and not args.duration > 0:
        raise ScenarioError(f"--duration = {args.duration}: must be > 0 simulated seconds")
    scenario, label = _load(args)
    duration = args.duration
    if args.stereo and scenario.stereo is None:
        scenario = with_stereo(scenario, label)
    if args.interactive:
        if args.no_meshcat:
            raise ScenarioError("--interactive drives the hand from Meshcat: drop --no-meshcat")
        scenario = interactive_variant(scenario, duration)
        duration = scenario.duration_s
        print("interactive: move the hand with the sliders in Meshcat's Controls panel; "
              "'Grip / release' (or the G key) grips the instrument; Ctrl-C ends the run")
    meshcat = not args.no_meshcat
    realtime = args.realtime if args.realtime is not None else (1.0 if meshcat else 0.0)
    out = Path(args.out) if args.out else Path("out") / label.replace(":", "-")
    result = run_scenario(scenario, label=label, out_dir=out, meshcat=meshcat,
                          realtime_rate=realtime, duration_s=duration)
    printed = {k: v for k, v in result.summary.items() if k != "holds"}
    print(json.dumps(printed, indent=2))
    plots = "levitation.png" + (", haptics.png" if scenario.haptics is not None else "")
    plots += ", stereo.png" if scenario.stereo is not None else ""
    print(f"wrote {out}/log.npz, {out}/summary.json, {out}/{plots}")
    for name in result.summary.get("stereo", {}).get("video", {}).get("files", []):
        print(f"wrote {out}/{name}")
    if result.meshcat is not None:
        replay = "" if args.interactive else " (the run's recording is replayable there)"
        print(f"Meshcat: {result.meshcat.web_url()}{replay}")
        if sys.stdin.isatty():
            input("press Enter to close Meshcat and exit ")
    return 0


def _cmd_diagram(args) -> int:
    import pydot

    from maglev_haptics.diagrams.application import BuildDiagram

    scenario, _ = _load(args)
    built = BuildDiagram(scenario)
    graph = pydot.graph_from_dot_data(built.diagram.GetGraphvizString(max_depth=args.depth))[0]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fmt = out.suffix.lstrip(".") or "svg"
    graph.write(str(out), format=fmt)
    print(f"wrote {out}")
    return 0


def _cmd_bench(args) -> int:
    from maglev_haptics.analysis.bench import run_benchmarks

    out_dir = Path(args.out)
    results = run_benchmarks(duration_s=args.duration, progress=not args.json, out_dir=out_dir)
    print(json.dumps(results, indent=2) if args.json else results["report"])
    if not args.json:
        print(f"wrote {out_dir / 'bench.json'}, {out_dir / 'lattice_scaling.png'}")
    return 0


def _cmd_analyze(args) -> int:
    from maglev_haptics.analysis.studies import format_modes, run_study

    scenario, label = _load(args)
    out = Path(args.out) if args.out else Path("out") / "analyze" / label.replace(":", "-")
    results = run_study(args.study, scenario, label=label, out_dir=out, quick=args.quick,
                        show_progress=not args.json)
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        headline = {key: value for key, value in results.items()
                    if not isinstance(value, (list, dict)) or key in ("parameters",)}
        print(json.dumps(headline, indent=2))
        if "modes" in results:
            print(format_modes(results["modes"]))
        files = [f"{args.study.replace('-', '_')}.json"] + results["plots"]
        print("wrote " + ", ".join(f"{out}/{name}" for name in files))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="maglev", description="Simulate, drive and analyse the co-located maglev haptic display.")
    commands = parser.add_subparsers(dest="command", required=True)

    run = commands.add_parser("run", help="simulate a scenario; write log.npz, summary.json, plots")
    _add_scenario_arguments(run)
    run.add_argument("--duration", type=float, help="simulated seconds (default: the script's length)")
    run.add_argument("--out", help="output folder (default: out/<file>-<name>)")
    run.add_argument("--no-meshcat", action="store_true", help="do not start Meshcat")
    run.add_argument("--interactive", action="store_true",
                     help="drive the simulated hand from Meshcat (sliders, grip button) in "
                     "real time instead of its script; haptic scenarios only")
    run.add_argument("--stereo", action="store_true",
                     help="turn on the head-tracked stereo display (the scenario's stereo: "
                     "block, or the defaults): per-eye views, rendered side-by-side and "
                     "anaglyph video, co-location errors, glasses and frusta in Meshcat")
    run.add_argument("--realtime", type=float,
                     help="target real-time rate (default 1 with Meshcat, else 0 = as fast as possible)")
    run.set_defaults(func=_cmd_run)

    diagram = commands.add_parser("diagram", help="draw the system diagram (pydot + graphviz)")
    _add_scenario_arguments(diagram)
    diagram.add_argument("--out", required=True, help="FILE.svg (or .png, .pdf)")
    diagram.add_argument("--depth", type=int, default=1, help="subsystem levels to expand")
    diagram.set_defaults(func=_cmd_diagram)

    bench = commands.add_parser("bench", help="real-time factor of each scenario, per-tick costs")
    bench.add_argument("--json", action="store_true", help="print JSON instead of a table")
    bench.add_argument("--duration", type=float,
                       help="simulated seconds per scenario (default: each whole script)")
    bench.add_argument("--out", default="out/bench",
                       help="folder for bench.json and lattice_scaling.png (default: out/bench)")
    bench.set_defaults(func=_cmd_bench)

    from maglev_haptics.analysis.studies import study_names
    analyze = commands.add_parser(
        "analyze", help="offline analysis of a scenario's loop; writes JSON and plots",
        description="Studies: linearize (the single-rate loop's state map over a period at "
        "an operating point: A, spectral radius, modes with frequency, damping and states), "
        "multirate (the true 860 Hz / 1 kHz loop's monodromy over its 50 ms hyperperiod, "
        "against the single-rate loop), passivity (Colgate-Schenkel margin of the coupling, and the "
        "damping a maglev device must get from the hand or controller), zwidth (the "
        "stiffness-damping range renderable stably and passively), stability-map (largest "
        "stable stiffness against damping over sample rates and delays, with closed forms), "
        "workspace (over x, y, height, tilt and yaw, for both instruments: the wrench matrix's "
        "condition number, hover current and power, the largest force and torque each way "
        "within the peak and thermal current limits).")
    analyze.add_argument("study", choices=study_names())
    _add_scenario_arguments(analyze)
    analyze.add_argument("--out", help="output folder (default: out/analyze/<file>-<name>)")
    analyze.add_argument("--json", action="store_true", help="print the whole result as JSON")
    analyze.add_argument("--quick", action="store_true", help="coarse settings (seconds)")
    analyze.set_defaults(func=_cmd_analyze)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ScenarioError, ValueError, OSError) as error:
        print(f"maglev {args.command}: error: {error}", file=sys.stderr)
        return 2
    except SystemExit as error:
        if error.code in (None, 0):
            raise
        # Drake's C++ assertions surface in Python as SystemExit.
        print(f"maglev {args.command}: error: the simulation stopped on an internal check "
              f"({error}); the scenario's values are likely outside what the model can handle",
              file=sys.stderr)
        return 3


if __name__ == "__main__":
    sys.exit(main())
