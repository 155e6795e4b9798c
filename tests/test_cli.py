"""The ``maglev`` command line as a new user meets it: bad input ends in one clear
line and exit code 2, never a traceback; help texts list scenarios and examples."""

import os
import subprocess
import sys
from importlib.metadata import version

import pytest

from maglev_haptics.cli import DIAGRAM_FORMATS, main
from maglev_haptics.diagrams.scenario import SCENARIO_DIR, scenario_names, shipped_scenario_files

COMMANDS = ("run", "device-sim", "driver", "diagram", "bench", "analyze")


def exit_code_and_stderr(argv, capsys):
    """main's exit code, whether argparse exits or main returns, and what it printed to stderr."""
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code
    return code, capsys.readouterr().err


def help_text(command, capsys) -> str:
    with pytest.raises(SystemExit) as exit_:
        main([command, "--help"])
    assert exit_.value.code == 0
    return capsys.readouterr().out


def test_version_is_the_installed_distributions(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"maglev {version('maglev-haptics')}"


def test_run_help_lists_each_files_named_scenarios(capsys):
    text = help_text("run", capsys)
    for path in shipped_scenario_files():
        assert f"{path.stem}: {', '.join(scenario_names(path))}" in text.replace("\n      ", " ")


@pytest.mark.parametrize("command", COMMANDS)
def test_each_command_help_has_examples(command, capsys):
    assert "Examples:\n  maglev " + command in help_text(command, capsys)


@pytest.mark.parametrize("argv, message", [
    (["diagram", "levitate", "--out", "x.jpgg"],
     "argument --out: 'x.jpgg': unknown format 'jpgg'; end the file in one of "
     + ", ".join("." + fmt for fmt in DIAGRAM_FORMATS)),
    (["diagram", "levitate", "--out", "x.svg", "--depth", "-1"], "argument --depth: '-1'"),
    (["run", "levitate", "--realtime", "-2"], "argument --realtime: '-2': must be >= 0"),
    (["run", "levitate", "--realtime", "inf"], "argument --realtime: 'inf': must be a finite"),
    (["run", "levitate", "--duration", "-1"], "argument --duration: '-1': must be > 0"),
    (["run", "levitate", "--duration", "abc"], "argument --duration: 'abc' is not a number"),
    (["run", "levitate", "--duration", "nan"], "argument --duration: 'nan': must be a finite"),
    (["bench", "--duration", "0"], "argument --duration: '0': must be > 0"),
    (["run", "no_such_file", "--no-meshcat"], "scenario file 'no_such_file' not found"),
    (["run", "levitate", "--name", "no_such_name"], "no scenario named 'no_such_name'"),
])
def test_bad_input_is_one_clear_line_and_exit_code_2(argv, message, capsys):
    code, err = exit_code_and_stderr(argv, capsys)
    assert code == 2
    assert message in err
    assert "Traceback" not in err


@pytest.mark.parametrize("command", [["run", "levitate", "--no-meshcat"],
                                     ["analyze", "passivity", "levitate"],
                                     ["bench"]])
def test_an_unwritable_out_stops_before_the_work(command, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    code, err = exit_code_and_stderr(command + ["--out", str(a_file / "results")], capsys)
    assert code == 2
    assert f"cannot write to {a_file / 'results'}" in err


def test_diagram_into_an_unwritable_place_is_refused(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    code, err = exit_code_and_stderr(["diagram", "levitate", "--out", str(a_file / "d.svg")],
                                     capsys)
    assert code == 2
    assert f"cannot write to {a_file}" in err


def test_run_against_no_station_on_lcm_says_so_in_one_line(tmp_path, capsys):
    """... and leaves no empty log folder: it stopped before it simulated."""
    code, err = exit_code_and_stderr([
        "run", "levitate", "--no-meshcat", "--duration", "0.1", "--out", str(tmp_path),
        "--scenario-text",
        "{station: !LcmStation {url: 'udpm://239.255.76.67:7999?ttl=0', "
        "command_url: 'udpm://239.255.76.67:7998?ttl=0', "
        "channel_prefix: NOBODY_, wait_for_station_s: 0.2}}"], capsys)
    assert code == 2
    assert err.strip().splitlines()[-1] == ("maglev run: error: no message on LCM channel 'NOBODY_MARKERS' "
                           "within 0.2 s: is the station running (maglev device-sim SCENARIO, "
                           "or the device's drivers) on the same LCM URL?")
    assert list(tmp_path.iterdir()) == []


REFUSED_RUNS = [
    (["run", "levitate", "--no-meshcat", "--scenario-text",
      "{motion: {waypoints: [{pose: [0, 0, 0.03, 1.05, 0, 0]}]}}"], "tilt 60.2 deg is beyond"),
    (["run", "levitate", "--no-meshcat", "--scenario-text", "{device: {instrument_mass_kg: 1e30}}"],
     "takes 1.51e+31 A in the busiest coil at minimum power, and even spread over all coils it "
     "falls 1.18e+31 N short"),
    (["analyze", "passivity", "levitate"], "passivity does not apply to levitate"),
    (["run", "levitate", "--no-meshcat", "--duration", "0.1", "--scenario-text",
      "{station: !LcmStation {url: 'udpm://239.255.76.67:7997?ttl=0', "
      "command_url: 'udpm://239.255.76.67:7996?ttl=0', channel_prefix: NOBODY_, "
      "wait_for_station_s: 0.2}}"], "no message on LCM channel 'NOBODY_MARKERS'"),
]


@pytest.mark.parametrize("argv, message", REFUSED_RUNS)
def test_a_refused_command_writes_nothing(argv, message, tmp_path, capsys):
    """Not even the folders it would have written into: --out and its missing parents."""
    code, err = exit_code_and_stderr(argv + ["--out", str(tmp_path / "out" / "run")], capsys)
    assert code == 2 and message in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("make_file, message", [
    (lambda path: path.write_bytes(b"\x89PNG\r\n\x1a\n\x00"),
     "not a text file (byte 0x89 at offset 0 is not UTF-8): give a YAML file"),
    (lambda path: path.write_text((SCENARIO_DIR / "peg_in_hole.yaml").read_text()),
     "not a sweep spec: it has Defaults, peg_in_hole, peg_release_outside; a sweep spec has "
     "scenario, vary and metrics"),
])
@pytest.mark.parametrize("command", ["run", "sweep"])
def test_the_wrong_file_is_named_as_such(make_file, message, command, tmp_path, capsys):
    path = tmp_path / "given.yaml"
    make_file(path)
    if command == "run" and "sweep" in message:
        return  # a scenario file is what run takes
    code, err = exit_code_and_stderr([command, str(path)], capsys)
    assert code == 2
    assert err.strip() == f"maglev {command}: error: {path}: {message}" + (
        " (see maglev sweep --help)" if "sweep" in message else "")


def test_an_unknown_name_in_a_shipped_file_names_the_file_as_given(capsys):
    code, err = exit_code_and_stderr(["run", "levitate", "--name", "nope"], capsys)
    assert code == 2
    assert err.startswith("maglev run: error: levitate: no scenario named 'nope'; it has "
                          "takeoff_hover_land, ")


def test_a_run_whose_reader_went_away_ends_with_its_own_exit_code(tmp_path, monkeypatch):
    """``maglev run ... | tee`` and Ctrl-C ends tee too: the run's printing then meets a
    closed pipe, which must not turn its written results into a bad-input error."""
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone: a write raises BrokenPipeError
    with open(write_end, "w") as closed_pipe:
        monkeypatch.setattr(sys, "stdout", closed_pipe)
        code = main(["run", "levitate", "--no-meshcat", "--duration", "0.3", "--out",
                     str(tmp_path)])
        assert sys.stdout is closed_pipe
    assert code == 0
    assert {"log.npz", "summary.json", "levitation.png"} <= set(os.listdir(tmp_path))


@pytest.mark.parametrize("argv, message", [
    (["run", "levitate", "--fast"],
     "maglev run: error: unrecognized arguments: --fast (see maglev run --help)"),
    (["run", "levitate", "--duration", "-1"],
     "maglev run: error: argument --duration: '-1': must be > 0 simulated seconds "
     "(see maglev run --help)"),
    (["run", "levitate", "--realtime", "-1"], "maglev run: error: argument --realtime: '-1'"),
    (["faults", "--runs", "0"],
     "maglev faults: error: argument --runs: '0': must be a whole number >= 1"),
    (["faults", "--workers", "0"], "maglev faults: error: argument --workers: '0'"),
    (["faults", "--seed", "-1"],
     "maglev faults: error: argument --seed: '-1': must be a whole number >= 0"),
    (["sweep", "spec.yaml", "--workers", "two"], "maglev sweep: error: argument --workers: 'two'"),
    (["diagram", "levitate", "--out", "d.xyz"], "maglev diagram: error: argument --out: 'd.xyz'"),
    (["bench", "--quick", "--duration", "1"], "maglev bench: error: argument --duration: not "
     "allowed with argument --quick"),
    (["no-such-command"], "maglev: error: argument command: invalid choice: 'no-such-command'"),
])
def test_a_bad_flag_is_one_line_not_the_usage_block(argv, message, capsys):
    code, err = exit_code_and_stderr(argv, capsys)
    assert code == 2
    assert err.splitlines() == [err.strip()], err  # one line: no usage block before it
    assert err.startswith(message)
    assert err.rstrip().endswith("--help)")


def test_help_imports_neither_drake_nor_numba_nor_dask():
    """Every --help answers at once: the heavy packages load when a command runs."""
    code = ("import sys, contextlib, io\n"
            "from maglev_haptics.cli import main\n"
            "for argv in ([], ['run'], ['device-sim'], ['driver'], ['diagram'], ['bench'],\n"
            "             ['faults'], ['sweep'], ['analyze']):\n"
            "    with contextlib.redirect_stdout(io.StringIO()):\n"
            "        try:\n"
            "            main(argv + ['--help'])\n"
            "        except SystemExit as exit_:\n"
            "            assert exit_.code == 0, (argv, exit_.code)\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & "
            "{'pydrake', 'numba', 'distributed', 'dask', 'scipy', 'matplotlib'}))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True)
    assert result.stdout.strip() == "[]", result.stdout + result.stderr


def test_the_analyze_studies_named_in_the_cli_are_the_studies():
    from maglev_haptics.analysis.studies import study_names
    from maglev_haptics.cli import STUDIES
    assert sorted(STUDIES) == sorted(study_names())


def test_the_default_workers_are_this_machines_cores():
    from maglev_haptics.analysis.parallel import default_workers
    from maglev_haptics.cli import build_parser
    assert build_parser().parse_args(["faults"]).workers == default_workers()


@pytest.mark.parametrize("summary, said", [
    ({"landed_before_stopping": True, "final_state": {"rests": True}}, " after landing"),
    ({"landed_before_stopping": False, "signals_received": 2,
      "final_state": {"rests": False, "z_m": 0.0156, "busiest_coil_current_a": 2.464}},
     " (signal 2 ended its landing): the instrument was left at z = 15.6 mm with 2.46 A in "
     "the busiest coil"),
    ({"landed_before_stopping": False,
      "final_state": {"rests": False, "z_m": 0.0112, "busiest_coil_current_a": 4.0}},
     ": the instrument was left at z = 11.2 mm with 4.00 A in the busiest coil"),
    ({"final_state": {"rests": True, "z_m": 0.007, "busiest_coil_current_a": 0.0}},
     ", the instrument resting with its coils off"),
])
def test_a_stopped_run_says_where_its_last_sample_left_the_instrument(summary, said):
    """What `maglev run` ends with after a signal or a device's run end: read from the
    summary's final_state (the log's last sample), never from what was asked."""
    from maglev_haptics.cli import _how_it_was_left
    assert _how_it_was_left(summary) == said
