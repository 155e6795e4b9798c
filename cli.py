"""The ``maglev`` command line: run, device-sim, driver, diagram, bench, faults, sweep,
analyze, calibrate (docs/architecture.md). It stands at the package's root, above every folder,
since it dispatches to all of them (analysis included); no folder imports it.

Only the standard library and the light scenario-file helpers are imported here: every
``--help`` answers at once, and pydrake, numba and Dask are imported when a command
runs (inside its ``_cmd_<command>``)."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import re
import shutil
import signal
import sys
import tempfile
import textwrap
from importlib.metadata import version
from pathlib import Path

from maglev_haptics.diagrams.scenario_files import (
    LONGEST_S, ScenarioError, read_text_file, resolve_scenario_file, scenario_names,
    shipped_scenario_files)

# What `maglev diagram --out` may end in: graphviz's (dot -T) file formats for looking
# at or editing a diagram, all of them in every graphviz build.
DIAGRAM_FORMATS = ("svg", "png", "pdf", "jpg", "jpeg", "gif", "ps", "dot")
HELP_WIDTH = 88  # characters a line in the help texts


def _finite_number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number")
    return value


def _positive_seconds(text: str) -> float:
    """argparse type of a duration: a finite number of seconds > 0."""
    seconds = _finite_number(text)
    if seconds <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be > 0 simulated seconds")
    if seconds > LONGEST_S:
        raise argparse.ArgumentTypeError(f"{text!r}: a run lasts at most {LONGEST_S:g} s")
    return seconds


def _realtime_rate(text: str) -> float:
    """argparse type of a real-time rate: >= 0, 0 being as fast as possible."""
    rate = _finite_number(text)
    if rate < 0:
        raise argparse.ArgumentTypeError(
            f"{text!r}: must be >= 0 (1 = wall-clock speed, 0 = as fast as possible)")
    return rate


def _positive_rate(text: str) -> float:
    rate = _realtime_rate(text)
    if rate == 0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be > 0 (a station keeps a clock)")
    return rate


def _subsystem_levels(text: str) -> int:
    """argparse type of --depth: a whole number >= 0."""
    try:
        levels = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if levels < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be >= 0")
    return levels


def _diagram_file(text: str) -> Path:
    """argparse type of ``diagram --out``: a file whose suffix names a format graphviz
    writes (none: SVG)."""
    path = Path(text)
    suffix = path.suffix.lstrip(".").lower()
    if suffix and suffix not in DIAGRAM_FORMATS:
        raise argparse.ArgumentTypeError(
            f"{text!r}: unknown format {suffix!r}; end the file in one of "
            + ", ".join("." + fmt for fmt in DIAGRAM_FORMATS))
    return path


# The folders this command created (innermost first): what it leaves empty, a refused
# run's or study's, goes again when it ends (``_remove_empty_created_folders``).
_created_folders = []


def _writable_folder(folder: Path) -> Path:
    """``folder``, created if missing and checked by writing a file there, so a run that
    could not save its results stops before it starts; a ValueError naming --out if not."""
    try:
        missing = [path for path in (folder, *folder.parents) if not path.exists()]
        folder.mkdir(parents=True, exist_ok=True)
        _created_folders.extend(missing)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        reason = "a file, not a folder" if isinstance(error, FileExistsError) else error.strerror
        raise ValueError(f"cannot write to {folder} ({reason}): "
                         "give --out a place you can write to") from None
    return folder


@functools.cache
def _scenario_listing() -> str:
    """The shipped scenario files and the named scenarios in each, for the help texts."""
    lines = ["Shipped scenarios (file: names; --name picks one, the first is the default):"]
    for path in shipped_scenario_files():
        lines.append(textwrap.fill(f"{path.stem}: " + ", ".join(scenario_names(path)),
                                   width=HELP_WIDTH, initial_indent="  ",
                                   subsequent_indent="      "))
    return "\n".join(lines)


def _epilog(examples: str, *, with_scenarios: bool = True) -> str:
    text = "Examples:\n" + textwrap.indent(textwrap.dedent(examples).strip("\n"), "  ")
    return text + ("\n\n" + _scenario_listing() if with_scenarios else "")


def _add_scenario_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help="a scenario file's path, or the name of a shipped one "
                        "(listed below)")
    parser.add_argument("--name", help="which named scenario in the file (default: the first)")
    parser.add_argument("--scenario-text", default="{}",
                        help="YAML layered over the scenario, e.g. "
                        "'{device: {instrument: four_magnet}}'")


def _load(args):
    from maglev_haptics.diagrams.scenario import load_scenario

    scenario = load_scenario(args.scenario, args.name, args.scenario_text)
    path = resolve_scenario_file(args.scenario)
    name = args.name or scenario_names(path)[0]
    return scenario, f"{path.stem}:{name}"


def _cmd_run(args) -> int:
    from maglev_haptics.diagrams.haptics import interactive_variant, scene_warnings
    from maglev_haptics.analysis.run_metrics import for_people
    from maglev_haptics.analysis.run_results import run_scenario
    from maglev_haptics.diagrams.meshcat_lifetime import close_meshcat
    from maglev_haptics.diagrams.lcm_station import chosen_station
    from maglev_haptics.diagrams.runner import MISS_WARNING_FRACTION
    from maglev_haptics.diagrams.scenario import validate_scenario, with_stereo
    from maglev_haptics.diagrams.thermal_forecast import thermal_outlook
    from maglev_haptics.analysis.loop_studies import stability_warnings
    from maglev_haptics.analysis.run_outcome import (
        EXIT_DEVICE_IN_USE, EXIT_INSTRUMENT_LOST, device_cuts_sentence, injected_faults_outcome,
        instrument_outcome)
    from maglev_haptics.hardware.link.lease import DeviceInUseError

    scenario, label = _load(args)
    duration = args.duration
    if args.station is not None:
        scenario = dataclasses.replace(scenario, station=chosen_station(args.station, scenario))
    if args.stereo and scenario.stereo is None:
        scenario = with_stereo(scenario, label)
    if args.interactive:
        if args.no_meshcat:
            raise ScenarioError("--interactive drives the hand from Meshcat: drop --no-meshcat")
        scenario = interactive_variant(scenario, duration)
        duration = scenario.duration_s
    validate_scenario(scenario, label)
    out = _writable_folder(Path(args.out) if args.out else Path("out") / label.replace(":", "-"))
    for line in (thermal_outlook(scenario, label, duration) + stability_warnings(scenario, label)
                 + scene_warnings(scenario, label)):
        print(line)
    if args.interactive:
        print("interactive: move the hand with the sliders in Meshcat's Controls panel; "
              "'Grip / release' (or the G key) grips the instrument; Ctrl-C ends the run")
    meshcat = not args.no_meshcat
    realtime = args.realtime if args.realtime is not None else (1.0 if meshcat else 0.0)
    try:
        result = run_scenario(scenario, label=label, out_dir=out, meshcat=meshcat,
                              realtime_rate=realtime, duration_s=duration,
                              raise_priority=not args.normal_priority)
    except DeviceInUseError as error:  # another application holds the device's lease
        print(f"maglev run: {label}: {error}", file=sys.stderr)
        return EXIT_DEVICE_IN_USE
    printed = {k: v for k, v in result.summary.items() if k != "holds"}
    print(json.dumps(for_people(printed), indent=2))
    names = ["log.npz", "summary.json", "levitation.png"]
    names += ["haptics.png"] if scenario.haptics is not None else []
    names += ["stereo.png"] if "head_pose" in result.log else []
    names += ["realtime.png"] if "realtime" in result.summary else []
    print("wrote " + " ".join(str(out / name) for name in names))
    realtime_summary = result.summary.get("realtime")
    if realtime_summary and realtime_summary["miss_fraction"] > MISS_WARNING_FRACTION:
        print(f"warning: {realtime_summary['deadline_misses']} of {realtime_summary['ticks']} "
              f"ticks ({100 * realtime_summary['miss_fraction']:.2f}%) missed their "
              f"{realtime_summary['slot_us']:.0f} us slot (allowed: "
              f"{100 * MISS_WARNING_FRACTION:.1f}%); longest stall "
              f"{realtime_summary['longest_stall_ms']:.1f} ms: see {out}/realtime.png",
              file=sys.stderr)
    cuts = device_cuts_sentence(result.summary)
    if cuts is not None:
        print(f"warning: {cuts}: this application or the link stalled", file=sys.stderr)
    for name in result.summary.get("stereo", {}).get("video", {}).get("files", []):
        print(f"wrote {out / name}")
    stopped_by = result.summary.get("stopped_by")
    if stopped_by is not None:
        print(f"{label}: stopped by {stopped_by} at {result.summary['duration_s']:.3f} s"
              f"{_how_it_was_left(result.summary)}; the run so far is in {out}",
              file=sys.stderr)
        return 128 + signal.Signals[stopped_by].value
    if "landed_before_stopping" in result.summary:
        landed = ("it was landed first, as a device's must be"
                  if result.summary["landed_before_stopping"] else
                  "its landing did not bring it to rest" + _how_it_was_left(result.summary))
        print(f"{label}: the instrument was flying when the run's time ended: {landed} "
              f"(the run ended at {result.summary['duration_s']:.3f} s)", file=sys.stderr)
    injected = injected_faults_outcome(scenario, result.summary, result.log, label)
    if injected is not None:
        print(injected, file=sys.stderr)
    # A fault in a run that injected none: said in one line, last, with its own code.
    outcome = instrument_outcome(scenario, result.summary, result.log, label)
    if result.meshcat is not None:
        print(_meshcat_last_line(result.meshcat.web_url(), waits=sys.stdin.isatty(),
                                 replay=not args.interactive))
        if sys.stdin.isatty():
            input("press Enter to close Meshcat and exit ")
        close_meshcat(result.meshcat)
    if outcome is not None:
        print(outcome, file=sys.stderr)
        return EXIT_INSTRUMENT_LOST
    return 0


def _how_it_was_left(summary) -> str:
    """How a stopped run left the instrument, as its log's last sample shows."""
    if summary.get("landed_before_stopping"):
        return " after landing"
    final = summary["final_state"]
    if final["rests"]:
        return ", the instrument resting with its coils off"
    cut = (f" (signal {summary['signals_received']} ended its landing)"
           if summary.get("signals_received", 0) > 1 else "")
    return (f"{cut}: the instrument was left at z = {1e3 * final['z_m']:.1f} mm with "
            f"{final['busiest_coil_current_a']:.2f} A in the busiest coil")


def _meshcat_last_line(url: str, *, waits: bool, replay: bool) -> str:
    """What the run says of its Meshcat at the end: it serves until Enter where there
    is a terminal to wait on, and closes with the process where there is none."""
    if waits:
        return f"Meshcat: {url}" + (" (the run's recording is replayable there)" if replay
                                    else "")
    return (f"Meshcat ({url}) closed with the run: no terminal to wait on"
            + (" (run it from a terminal to replay the recording there)" if replay else ""))


def _cmd_device_sim(args) -> int:
    from maglev_haptics.analysis.run_metrics import for_people
    from maglev_haptics.diagrams.device_sim import BuildDeviceSim
    from maglev_haptics.diagrams.lcm_station import lcm_config
    from maglev_haptics.diagrams.runner import StopOnSignal, realtime_report, simulate

    scenario, label = _load(args)
    device_sim = BuildDeviceSim(scenario)
    print(f"device-sim {label}: the simulated station on LCM "
          f"({lcm_config(scenario).url}); stops {device_sim.stop_after_silence_s:g} s after "
          "the application's last command, or after --duration", file=sys.stderr)
    with StopOnSignal() as stop_signal:  # Ctrl-C or SIGTERM: stop between ticks, report
        simulator, wall_s, tick_times = simulate(
            device_sim, args.duration, realtime_rate=args.realtime, label=f"device-sim {label}",
            stop=lambda context: stop_signal(context) or device_sim.application_gone(context),
            shares_cores=True, raise_priority=not args.normal_priority)
    context = simulator.get_context()
    gone = stop_signal.received is None and device_sim.application_gone(context)
    report = {"scenario": label, "duration_s": context.get_time(), "wall_time_s": wall_s,
              # The silence it stopped on is the application's end, not a gap in its commands.
              "commands": device_sim.command_counts(context, until_now=not gone),
              "lease": device_sim.lease_counts(context),
              "realtime": realtime_report(tick_times)}
    print(json.dumps(for_people(report), indent=2))  # 394.75 s, not 394.75000016864215
    if stop_signal.received is not None:
        print(f"device-sim {label}: stopped by {stop_signal.received} at "
              f"{context.get_time():.3f} s", file=sys.stderr)
        return 128 + signal.Signals[stop_signal.received].value
    if gone:
        print(f"device-sim {label}: no command since {device_sim.last_command_s(context):.3f} "
              f"s (the application ended, or was lost): stopped at {context.get_time():.3f} s",
              file=sys.stderr)
    return 0


def _daq_channels(text: str) -> list:
    """NI physical channels, a comma list or NI's range (Dev1/ao0:26), in coil order."""
    channels = []
    for part in text.split(","):
        match = re.fullmatch(r"(.*?)(\d+):(\d+)", part.strip())
        if match:
            prefix, first, last = match[1], int(match[2]), int(match[3])
            channels += [f"{prefix}{i}" for i in range(first, last + 1)]
        elif part.strip():
            channels.append(part.strip())
    return channels


def _cmd_driver(args) -> int:
    from pydrake.math import RigidTransform, RollPitchYaw

    from maglev_haptics.diagrams.lcm_station import (
        COIL_CURRENTS_COMMANDED, GLASSES, LEASE, LEASE_REQUEST, channel, lcm_config, open_lcm)

    scenario, label = _load(args)
    config = lcm_config(scenario)
    device = scenario.device
    if args.kind == "head-tracker":
        from maglev_haptics.hardware.link.ndi_head_tracker import NdiHeadTracker

        if not args.romfile:
            raise ValueError("--romfile: the glasses' NDI tool definition (.rom) is required")
        settings = {"tracker type": args.tracker, "romfiles": args.romfile}
        if args.serial_port:
            settings["serial port"] = args.serial_port
        if args.ip_address:
            settings["ip address"] = args.ip_address
        x, y, z, roll, pitch, yaw = args.X_WN
        tracker = NdiHeadTracker(settings, lcm=open_lcm(config.url),
                                 channel=channel(config, GLASSES),
                                 X_WN=RigidTransform(RollPitchYaw(roll, pitch, yaw), [x, y, z]),
                                 latency_s=device.head_tracker.latency_s)
        try:
            sent = tracker.run(device.head_tracker.rate_hz, args.duration)
        finally:
            tracker.close()
        print(json.dumps({"driver": args.kind, "scenario": label, "glasses_messages": sent,
                          "unreadable_frames": tracker.refused}))
        return 0
    from maglev_haptics.hardware.link.daq_coil_output import CoilOutputContract, DaqCoilOutput

    if not args.channels or args.amps_per_volt is None:
        raise ValueError("--channels and --amps-per-volt: both are required for coil-daq")
    output = DaqCoilOutput(_daq_channels(args.channels), CoilOutputContract(
        n_coils=device.n_coils, current_limit_a=device.amplifier.current_limit_a,
        amps_per_volt=args.amps_per_volt, instrument=device.instrument))
    counts = output.serve(open_lcm(config.command_url),
                          channel(config, COIL_CURRENTS_COMMANDED), args.duration,
                          config.command_timeout_s, lease_channel=channel(config, LEASE_REQUEST),
                          reply_lcm=open_lcm(config.url), reply_channel=channel(config, LEASE),
                          lease_timeout_s=config.lease_timeout_s)
    print(json.dumps({"driver": args.kind, "scenario": label, **counts}))
    return 0


def _cmd_diagram(args) -> int:
    import pydot

    from maglev_haptics.diagrams.application import BuildDiagram

    if shutil.which("dot") is None:
        raise ValueError("graphviz's dot is not on the PATH: install graphviz "
                         "(apt install graphviz, brew install graphviz)")
    scenario, _ = _load(args)
    out = args.out
    _writable_folder(out.parent)
    built = BuildDiagram(scenario)
    graph = pydot.graph_from_dot_data(built.diagram.GetGraphvizString(max_depth=args.depth))[0]
    fmt = out.suffix.lstrip(".").lower() or "svg"
    try:
        graph.write(str(out), format=fmt)
    except OSError as error:
        raise ValueError(f"cannot write {out} ({error.strerror}): "
                         "give --out a file you can write to") from None
    except AssertionError as error:  # pydot's report of dot's non-zero exit
        raise ValueError(f"graphviz could not write {out}: {error}") from None
    print(f"wrote {out}")
    return 0


def _cmd_bench(args) -> int:
    from maglev_haptics.analysis.bench import run_benchmarks

    out_dir = _writable_folder(Path(args.out))
    results = run_benchmarks(duration_s=args.duration, progress=not args.json, out_dir=out_dir,
                             quick=args.quick, runs=args.runs, paced_s=args.paced)
    print(json.dumps(results, indent=2) if args.json else results["report"])
    if not args.json:
        print(f"wrote {out_dir / 'bench.json'} {out_dir / 'lattice_scaling.png'}")
    return 0


def _positive_count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: must be a whole number >= 1")
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:  # numpy's generators take none below zero
        raise argparse.ArgumentTypeError(f"{text!r}: must be a whole number >= 0")
    return value


def _cores() -> int:
    """The cores this process may use (analysis.parallel.default_workers, without
    importing the analysis package for a help text)."""
    return len(os.sched_getaffinity(0))


def _add_job_arguments(parser) -> None:
    """--workers and --scheduler: where a long study's jobs run (analysis/parallel.py)."""
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_positive_count, default=_cores(),
                       help="local worker processes (default: this machine's cores, "
                       f"{_cores()}; 1: in this process)")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="a Dask distributed scheduler's address (tcp://HOST:PORT): its "
                       "workers run the jobs")


def _cmd_faults(args) -> int:
    from maglev_haptics.analysis.fault_campaign import run_campaign

    out_dir = _writable_folder(Path(args.out))
    results = run_campaign(args.runs, args.seed, out_dir, workers=args.workers,
                           scheduler=args.scheduler)
    print(results["report"])
    jobs = results["jobs"]
    print(f"ran on {jobs['where']}" + (f"; {jobs['reran']} runs rerun after their worker died"
                                        if jobs["reran"] else ""))
    failed = [r for r in results["runs"] if not r["passed"]]
    for row in failed:
        broken = [name for name, ok in row["checks"].items() if not ok]
        print(f"run {row['run']} ({row['fault']}, {row['scenario']}): "
              + (f"crashed: {row['error']}" if row["crashed"] else "failed " + ", ".join(broken)))
    print(f"{len(results['runs']) - len(failed)} of {len(results['runs'])} runs passed every "
          f"check; wrote {out_dir / 'faults.json'} {out_dir / 'faults.png'}")
    return 0 if not failed else 1


def _cmd_sweep(args) -> int:
    from maglev_haptics.analysis.sweep import format_table, parse_spec, run_sweep

    path = Path(args.spec)
    try:
        text = read_text_file(path, str(path))
    except OSError as error:
        raise OSError(f"sweep spec {args.spec}: {error.strerror}") from None
    spec = parse_spec(text, str(path))
    out_dir = _writable_folder(Path(args.out))
    results = run_sweep(spec, out_dir, workers=args.workers, scheduler=args.scheduler)
    failed = [row for row in results["rows"] if row["error"]]
    print(format_table(spec, results["rows"]))
    jobs = results["jobs"]
    print(f"{len(results['rows'])} points on {jobs['where']}"
          + (f" ({jobs['reran']} rerun after their worker died)" if jobs["reran"] else "")
          + "; wrote " + " ".join(str(path) for path in results["files"]))
    return 0 if not failed else 1


def _cmd_analyze(args) -> int:
    from maglev_haptics.analysis.run_metrics import for_people
    from maglev_haptics.analysis.studies import format_modes, run_study

    scenario, label = _load(args)
    out = _writable_folder(Path(args.out) if args.out
                           else Path("out") / "analyze" / label.replace(":", "-"))
    results = run_study(args.study, scenario, label=label, out_dir=out, quick=args.quick,
                        show_progress=not args.json, workers=args.workers,
                        scheduler=args.scheduler)
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        # Each study's numbers that fit a screen: its scalars, its parameters, the
        # scenario's own point and each instrument's workspace summary.
        headline = {key: value for key, value in results.items()
                    if not isinstance(value, (list, dict))
                    or key in ("parameters", "scenario_point")}
        for name, instrument in results.get("instruments", {}).items():
            headline[name] = {key: instrument["summary"][key] for key in (
                "hover_ceiling_m", "hover_current_a", "condition_number")}
        print(json.dumps(for_people(headline), indent=2))
        if "modes" in results:
            print(format_modes(results["modes"]))
        files = [f"{args.study.replace('-', '_')}.json"] + results["plots"]
        print("wrote " + " ".join(str(out / name) for name in files))
    return 0


# The studies of `maglev analyze` (analysis/studies.py's study_names; a test holds them
# equal): named here so that `maglev analyze --help` needs no import of the studies.
STUDIES = ("linearize", "multirate", "passivity", "zwidth", "stability-map", "workspace")

ANALYZE_STUDIES = """\
Studies:
  linearize      the single-rate loop's state map over a period at an operating point:
                 A, spectral radius, modes with frequency, damping and states
  multirate      the true 860 Hz / 1 kHz loop's monodromy over its 50 ms hyperperiod,
                 against the single-rate loop
  passivity      Colgate-Schenkel margin of the coupling, and the damping a maglev
                 device must get from the hand or controller
  zwidth         the stiffness-damping range renderable stably and passively
                 (both, in a tissue scene: the coupling in series with the contact
                 stiffness the tool meets 3 mm pressed into the tissue's top centre)
  stability-map  largest stable stiffness against damping over sample rates and
                 delays, with closed forms; and the whole loop's onsets, linearized and
                 simulated (minutes; --quick leaves them out)
  workspace      over x, y, height, tilt and yaw, for both instruments: the wrench
                 matrix's condition number, hover current and power, the largest
                 force and torque each way within the peak and thermal current limits"""

BENCH_PARTS = """\
What it runs, and how long each part took on a quiet 2-core machine (a busy one
takes several times as long):
  scenarios      every levitate scenario and the first of each other shipped file
                 (stereo_display's head_sweep, the haptic scenes), each its whole
                 script (about 35 s in all); --duration S: S simulated seconds each
  systems        each leaf system's update at hover, best of five, and the physics
                 floors (about 3 s)
  in the loop    each Python callback's own time a tick in the running loop,
                 levitate and the deformable surface (about 10 s)
  allocation     the wrench matrix and the current allocation (about 2 s)
  stereo         view matrices and a rendered frame pair (about 5 s)
  analysis       the multirate, linearize and zwidth studies of peg_in_hole (about 25 s)
  lattice        the deformable lattice's step against its size (about 5 s)
  paced          --paced S: four scenarios paced at 1x, S seconds each (4 S in all)
--runs N: the scenarios N times each (N times as long).
--quick: one simulated second a scenario, no offline analysis, the lattice's two
smallest sizes (about 30 s in all; the whole bench about 75 s)."""


class _Parser(argparse.ArgumentParser):
    """argparse, but a bad argument is one line (the usage block is what --help is for)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


FORMATTER = argparse.RawDescriptionHelpFormatter  # keeps the epilogs' lines as written


def _add_run_parser(commands) -> None:
    run = commands.add_parser(
        "run", formatter_class=FORMATTER,
        help="simulate a scenario; write log.npz, summary.json, plots",
        description="Simulate a scenario; write log.npz, summary.json and plots to --out.\n"
        "Exit codes: 0 done; 2 bad input; 3 the simulation stopped on an internal check;\n"
        "4 the device (on LCM) is in use by another application;\n"
        "5 a fault latched, or the instrument was lost, in a run whose scenario injected no "
        "fault;\n128 + N stopped by signal N.",
        epilog=_epilog("""
            maglev run levitate                          # its first scenario, Meshcat at 1x
            maglev run levitate --name square --duration 2 --no-meshcat --out out/square
            maglev run peg_in_hole --realtime 0.5        # half speed, to watch it
            maglev run hanging_ball --interactive        # your hand, from Meshcat's sliders
            maglev run levitate --scenario-text '{device: {instrument: four_magnet}}'
            maglev run ./my_scenarios.yaml --name mine --stereo
            """))
    _add_scenario_arguments(run)
    run.add_argument("--duration", type=_positive_seconds,
                     help="simulated seconds (default: the script's length)")
    run.add_argument("--out", help="output folder (default: out/<file>-<name>)")
    run.add_argument("--no-meshcat", action="store_true", help="do not start Meshcat")
    run.add_argument("--interactive", action="store_true",
                     help="drive the simulated hand from Meshcat (sliders, grip button) in "
                     "real time instead of its script; haptic scenarios only")
    run.add_argument("--stereo", action="store_true",
                     help="turn on the head-tracked stereo display (the scenario's stereo: "
                     "block, or the defaults): per-eye views, rendered side-by-side and "
                     "anaglyph video, co-location errors, glasses and frusta in Meshcat")
    run.add_argument("--realtime", type=_realtime_rate,
                     help="target real-time rate >= 0 (default 1 with Meshcat, else 0 = as "
                     "fast as possible)")
    run.add_argument("--station", choices=("sim", "lcm"),
                     help="sim: the simulated station in this process; lcm: whatever answers "
                     "on LCM (maglev device-sim, or the device's drivers); default: the "
                     "scenario's station")
    run.add_argument("--normal-priority", action="store_true",
                     help="run the paced loop at normal priority (default: real-time "
                     "priority, SCHED_FIFO, where the OS grants it; summary.json says which)")
    run.set_defaults(func=_cmd_run)


def _add_device_sim_parser(commands) -> None:
    device_sim = commands.add_parser(
        "device-sim", formatter_class=FORMATTER,
        help="the simulated station alone, paced to the wall clock, speaking LCM",
        description="The simulated station (instrument, coils, amplifiers, tracker, scripted "
        "hand) as its own process, paced to the wall clock, on LCM: what a real device "
        "would be to `maglev run --station lcm`. Stops once the application's commands "
        "stop, or after --duration.",
        epilog=_epilog("""
            maglev device-sim levitate &                 # the device, in another process
            maglev run levitate --station lcm --no-meshcat
            """))
    _add_scenario_arguments(device_sim)
    device_sim.add_argument("--duration", type=_positive_seconds, default=3600.0,
                            help="longest it runs, in simulated seconds (default 3600; at "
                            "--realtime 1 the same in wall seconds)")
    device_sim.add_argument("--realtime", type=_positive_rate, default=1.0,
                            help="real-time rate > 0 (default 1); the application must run "
                            "at the same --realtime")
    device_sim.add_argument("--normal-priority", action="store_true",
                            help="run the paced loop at normal priority (default: real-time "
                            "priority, SCHED_FIFO, where the OS grants it; the report it "
                            "prints at the end says which, under realtime.priority)")
    device_sim.set_defaults(func=_cmd_device_sim)


def _add_driver_parser(commands) -> None:
    driver = commands.add_parser(
        "driver", formatter_class=FORMATTER,
        help="a real device's driver on LCM (needs the hardware extra)",
        description="Run one of the real device's drivers against the scenario's LCM "
        "station: head-tracker publishes the glasses from an NDI Polaris or Vega "
        "(scikit-surgerynditracker); coil-daq writes the commanded coil currents to an NI "
        "card's analog outputs (nidaqmx). pip install 'maglev-haptics[hardware]'.",
        epilog=_epilog("""
            maglev driver head-tracker levitate --romfile glasses.rom --serial-port /dev/ttyUSB0
            maglev driver coil-daq levitate --channels Dev1/ao0:26 --amps-per-volt 0.4
            """))
    driver.add_argument("kind", choices=("head-tracker", "coil-daq"))
    _add_scenario_arguments(driver)
    driver.add_argument("--duration", type=_positive_seconds, default=3600.0,
                        help="how long it runs (s; default 3600)")
    driver.add_argument("--tracker", choices=("polaris", "vega", "aurora", "dummy"),
                        default="polaris", help="head-tracker: the NDI tracker's kind")
    driver.add_argument("--romfile", action="append",
                        help="head-tracker: the glasses' tool definition (.rom)")
    driver.add_argument("--serial-port", help="head-tracker: Polaris or Aurora serial port")
    driver.add_argument("--ip-address", help="head-tracker: Vega's address")
    driver.add_argument("--X-WN", type=_finite_number, nargs=6, default=[0.0] * 6,
                        metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"),
                        help="head-tracker: the tracker's pose in W (m, rad; default identity)")
    driver.add_argument("--channels", help="coil-daq: NI analog outputs in coil order, "
                        "a comma list or a range (Dev1/ao0:26)")
    driver.add_argument("--amps-per-volt", type=_finite_number,
                        help="coil-daq: the amplifiers' transconductance (A/V)")
    driver.set_defaults(func=_cmd_driver)


def _add_diagram_parser(commands) -> None:
    diagram = commands.add_parser(
        "diagram", formatter_class=FORMATTER,
        help="draw the system diagram (pydot + graphviz)",
        description="Draw the scenario's system diagram with graphviz.",
        epilog=_epilog("""
            maglev diagram levitate --out levitate.svg
            maglev diagram peg_in_hole --depth 2 --out peg_in_hole.pdf
            """))
    _add_scenario_arguments(diagram)
    diagram.add_argument("--out", required=True, type=_diagram_file,
                         help="FILE.svg, or another of " + ", ".join(
                             "." + fmt for fmt in DIAGRAM_FORMATS[1:]))
    diagram.add_argument("--depth", type=_subsystem_levels, default=1,
                         help="subsystem levels to expand (default: 1)")
    diagram.set_defaults(func=_cmd_diagram)


def _add_bench_parser(commands) -> None:
    bench = commands.add_parser(
        "bench", formatter_class=FORMATTER,
        help="real-time factor of each scenario, per-tick costs",
        description="Real-time factor of each shipped scenario, per-tick cost of each\n"
        "system, lattice scaling and allocation cost (Meshcat off).\n\n" + BENCH_PARTS,
        epilog=_epilog("""
            maglev bench --quick
            maglev bench
            maglev bench --duration 1 --json > bench.json
            maglev bench --runs 3 --paced 60     # the README's performance table
            """, with_scenarios=False))
    bench.add_argument("--json", action="store_true", help="print JSON instead of a table")
    length = bench.add_mutually_exclusive_group()
    length.add_argument("--duration", type=_positive_seconds,
                        help="simulated seconds per scenario (default: each whole script)")
    length.add_argument("--quick", action="store_true",
                        help="a first look in about 30 s (see above)")
    bench.add_argument("--runs", type=_positive_count, default=1,
                       help="run each scenario this many times; the median is reported "
                       "(default 1; the README's table: 3)")
    bench.add_argument("--paced", type=_positive_seconds, metavar="S",
                       help="also fly levitate, peg_in_hole, paddle_ball and "
                       "deformable_surface paced at 1x for S seconds each: missed slots")
    bench.add_argument("--out", default="out/bench",
                       help="folder for bench.json and lattice_scaling.png (default: out/bench)")
    bench.set_defaults(func=_cmd_bench)


def _add_faults_parser(commands) -> None:
    faults = commands.add_parser(
        "faults", formatter_class=FORMATTER,
        help="randomized fault-injection campaign; writes faults.json and a plot",
        description="Randomized fault-injection campaign over the shipped scenarios (tracker "
        "dropouts, stalls and corrupt samples, stuck amplifiers, the hand letting go, shoves, "
        "gains near the stability edge, a hold that outlasts the coils' thermal budget), each "
        "run checked against the safety policy. Writes faults.json and faults.png; exits 1 "
        "if a run failed a check.",
        epilog=_epilog("""
            maglev faults --runs 20 --out out/faults
            maglev faults --runs 200 --seed 7 --workers 2
            maglev faults --runs 200 --scheduler tcp://10.0.0.5:8786
            """, with_scenarios=False))
    faults.add_argument("--runs", type=_positive_count, default=20,
                        help="how many runs (default 20; the kinds take turns)")
    faults.add_argument("--seed", type=_seed, default=0,
                        help="the campaign's random seed, a whole number >= 0 (default 0)")
    _add_job_arguments(faults)
    faults.add_argument("--out", default="out/faults",
                        help="folder for faults.json and faults.png (default: out/faults)")
    faults.set_defaults(func=_cmd_faults)


def _add_sweep_parser(commands) -> None:
    sweep = commands.add_parser(
        "sweep", formatter_class=FORMATTER,
        help="a scenario over a grid of its fields; writes sweep.csv, sweep.json, sweep.png",
        description="Run a scenario at every combination of the values a spec file gives "
        "its fields (YAML paths, dotted: lists, or {start, stop, num}); keep the metrics "
        "the spec names from each run's summary.json. Prints them as a table and writes "
        "sweep.csv, sweep.json and sweep.png (each metric against each field); exits 1 if "
        "a point's run failed (it raised, or lost the instrument: its error says how), 2 if "
        "a metric is in no point's summary.json (said after the runs).",
        epilog=_epilog("""
            maglev sweep docs/sweep_example.yaml --out out/sweep
            maglev sweep my_sweep.yaml --scheduler tcp://10.0.0.5:8786
            """, with_scenarios=False))
    sweep.add_argument("spec", help="the sweep's YAML spec (docs/sweep_example.yaml shows one)")
    sweep.add_argument("--out", default="out/sweep",
                       help="folder for sweep.csv, sweep.json and sweep.png (default: out/sweep)")
    _add_job_arguments(sweep)
    sweep.set_defaults(func=_cmd_sweep)


def _add_analyze_parser(commands) -> None:
    analyze = commands.add_parser(
        "analyze", formatter_class=FORMATTER,
        help="offline analysis of a scenario's loop; writes JSON and plots",
        description="Offline analysis of a scenario's loop; writes <study>.json and plots.\n\n"
        + ANALYZE_STUDIES,
        epilog=_epilog("""
            maglev analyze linearize levitate --quick
            maglev analyze passivity peg_in_hole --out out/passivity
            maglev analyze workspace levitate --name four_magnet_tilt --json
            """))
    analyze.add_argument("study", choices=STUDIES)
    _add_scenario_arguments(analyze)
    analyze.add_argument("--out", help="output folder (default: out/analyze/<file>-<name>)")
    analyze.add_argument("--json", action="store_true", help="print the whole result as JSON")
    analyze.add_argument("--quick", action="store_true", help="coarse settings (seconds)")
    _add_job_arguments(analyze)
    analyze.set_defaults(func=_cmd_analyze)


def _cmd_calibrate(args) -> int:
    return {"plan": _calibrate_plan, "fit": _calibrate_fit, "check": _calibrate_check}[
        args.step](args)


def _calibrate_plan(args) -> int:
    from maglev_haptics.analysis.calibration_plan import (
        FLIGHTS_FILE, MARKS_IMAGE, PAYLOAD_KG, flight_seconds, write_plan)

    out = _writable_folder(Path(args.out))
    flights = write_plan(out, args.instrument)
    total_s = sum(flight_seconds(flight) for flight in flights.values())
    plan_file = out / FLIGHTS_FILE
    print(f"wrote {plan_file} and {out / MARKS_IMAGE.format(flight='<flight>')}: "
          f"{len(flights)} flights, {total_s:.0f} s of flight in all")
    print("Fly each one, the instrument first resting on its mark (show its image full "
          "screen on the display):")
    for name in flights:
        step = (f"   (hang the {PAYLOAD_KG * 1e3:g} g payload centred under the instrument "
                "first)" if name == "payload" else "")
        print(f"  maglev run {plan_file} --name {name} --no-meshcat --out runs/{name}{step}")
    print("On a device over LCM add --station lcm; to try it on a simulated device unlike the "
          "model add --scenario-text '{station: !SimStation {device: {...}}}'.")
    fitted = " ".join(f"runs/{name}" for name in flights if name != "check")
    print(f"Then: maglev calibrate fit {fitted} --out lab_device.yaml")
    print("      maglev calibrate check runs/check --device lab_device.yaml")
    return 0


def _calibrate_fit(args) -> int:
    from maglev_haptics.analysis.calibration_fit import fit_device, overlay_text
    from maglev_haptics.analysis.calibration_report import (
        PLOT_FILE, REPORT_FILE, calibration_report, format_summary, plot_calibration)
    from maglev_haptics.analysis.run_metrics import for_people

    out = Path(args.out)
    if out.suffix not in (".yaml", ".yml"):
        raise ValueError(f"--out {out}: must name the overlay's .yaml file")
    calibration = fit_device(args.runs, rest_height_m=args.rest_height_m)
    report = for_people(calibration_report(calibration))
    folder = _writable_folder(out.parent)
    out.write_text(f"# maglev calibrate fit: the {calibration.instrument} instrument's device "
                   f"from {len(args.runs)} flights\n" + overlay_text(calibration.device))
    (folder / REPORT_FILE).write_text(json.dumps(report, indent=2))
    plot_calibration(calibration, folder / PLOT_FILE)
    print(format_summary(report))
    print(f"wrote {out}, {folder / REPORT_FILE}, {folder / PLOT_FILE}")
    print(f"Fly with it: maglev run levitate --scenario-text \"$(cat {out})\"")
    return 0


def _calibrate_check(args) -> int:
    from maglev_haptics.analysis.calibration_check import check_calibration
    from maglev_haptics.analysis.run_metrics import for_people

    source = str(args.device)
    text = read_text_file(Path(args.device), source)
    result = for_people(check_calibration(args.run, text, source,
                                          rest_height_m=args.rest_height_m))
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    rows = (("co-location error on the screen", "colocation_error_mm", "mm"),
            ("", "colocation_error_px", "px"),
            ("wrench residual at the holds", "force_residual_rms_n", "N"),
            ("", "torque_residual_rms_nm", "N m"),
            ("felt-force error", "felt_force_error_mn_per_n", "mN per N rendered"),
            ("hover current error", "hover_current_error_percent", "%"))
    print(f"{result['flight']} ({result['fitted']['holds']} holds): nominal -> fitted")
    for label, key, unit in rows:
        print(f"  {label:34s} {result['nominal'][key]:>10.4g} -> {result['fitted'][key]:<10.4g}"
              f" {unit}")
    return 0


def _add_calibrate_parser(commands) -> None:
    calibrate = commands.add_parser(
        "calibrate", formatter_class=FORMATTER,
        help="fit the device model to a device's own flights (plan, fit, check)",
        description="Calibrate the device model against a device (or a simulated one): plan\n"
        "the identification flights, fly them with maglev run, fit the device's own numbers\n"
        "to their logs, check the fit on a flight it did not see (README, \"Calibrate your\n"
        "device\"). Exit codes: 0 done; 2 bad input, or flights that do not make a fit.",
        epilog=_epilog("""
            maglev calibrate plan --out calibration
            maglev calibrate fit runs/holds_* runs/steps runs/payload --out lab_device.yaml
            maglev calibrate check runs/check --device lab_device.yaml
            """, with_scenarios=False))
    steps = calibrate.add_subparsers(dest="step", required=True)
    plan = steps.add_parser("plan", formatter_class=FORMATTER,
                            help="write the identification flights and their rest marks")
    plan.add_argument("--instrument", choices=("two_magnet", "four_magnet"), default="two_magnet")
    plan.add_argument("--out", required=True, help="folder for the flights and mark images")
    fit = steps.add_parser("fit", formatter_class=FORMATTER,
                           help="fit the device to the flights' run folders")
    fit.add_argument("runs", nargs="+", help="the --out folders of the plan's flights "
                     "(all but check)")
    fit.add_argument("--out", required=True, help="the device overlay to write (.yaml); the "
                     "report and plot go beside it")
    check = steps.add_parser("check", formatter_class=FORMATTER,
                             help="how well a fitted device predicts a flight it did not see")
    check.add_argument("run", help="the check flight's run folder")
    check.add_argument("--device", required=True, help="the overlay maglev calibrate fit wrote")
    check.add_argument("--json", action="store_true", help="print the whole result as JSON")
    for parser in (fit, check):
        parser.add_argument("--rest-height-m", type=_finite_number, default=None,
                            help="height of I above the glass while the instrument rests "
                            "(m); default the model's, pressed into the glass by its soft "
                            "contact")
    calibrate.set_defaults(func=_cmd_calibrate)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="maglev", formatter_class=FORMATTER,
        description="Simulate, drive and analyse the co-located maglev haptic display.",
        epilog=_epilog("""
            maglev run levitate                  # fly the first levitation scenario in Meshcat
            maglev run peg_in_hole --no-meshcat  # as fast as possible, plots in out/
            maglev COMMAND --help                # each command's options and examples
            """, with_scenarios=False))
    parser.add_argument("--version", action="version",
                        version=f"%(prog)s {version('maglev-haptics')}")
    commands = parser.add_subparsers(dest="command", required=True)
    _add_run_parser(commands)
    _add_device_sim_parser(commands)
    _add_driver_parser(commands)
    _add_diagram_parser(commands)
    _add_bench_parser(commands)
    _add_faults_parser(commands)
    _add_sweep_parser(commands)
    _add_analyze_parser(commands)
    _add_calibrate_parser(commands)
    parser.command_parsers = commands.choices
    return parser


def _remove_empty_created_folders() -> None:
    """Remove the folders this command created that hold no file (a refusal writes
    nothing), their empty subfolders first; a folder with anything in it stays."""
    for folder in _created_folders:
        for inner, _, _ in sorted(os.walk(folder), key=lambda entry: -len(entry[0])):
            try:
                os.rmdir(inner)
            except OSError:  # not empty: something was written there
                pass
    _created_folders.clear()


class _ClosedPipeTolerant:
    """A text stream whose reader may go away (``| head``, or a ``tee`` that the same
    Ctrl-C ended): once its pipe is closed, what is written goes to /dev/null, so a run
    whose results are written ends with its own exit code, not a broken pipe's."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._to_devnull()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._to_devnull()

    def _to_devnull(self) -> None:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, self._stream.fileno())  # the buffered rest goes there too
        os.close(devnull)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def main(argv=None) -> int:
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # said by the command's own parser: "maglev run: error: ..."
        parser.command_parsers[args.command].error(
            f"unrecognized arguments: {' '.join(unknown)}")
    streams = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = (_ClosedPipeTolerant(stream) for stream in streams)
    try:
        from maglev_haptics.hardware.link.extras import MissingExtraError

        return args.func(args)
    except (ScenarioError, ValueError, OSError, MissingExtraError) as error:
        print(f"maglev {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"maglev {args.command}: interrupted", file=sys.stderr)
        return 130  # the shell's code for a run ended by Ctrl-C
    except SystemExit as error:
        if error.code in (None, 0):
            raise
        # Drake's C++ assertions surface in Python as SystemExit.
        print(f"maglev {args.command}: error: the simulation stopped on an internal check "
              f"({error}); the scenario's values are likely outside what the model can handle",
              file=sys.stderr)
        return 3
    finally:
        _remove_empty_created_folders()
        for stream in (sys.stdout, sys.stderr):
            stream.flush()  # here, where a closed pipe is caught, not at the exit
        sys.stdout, sys.stderr = streams


if __name__ == "__main__":
    sys.exit(main())
