"""Tests of the ``closedchain`` subcommands and of its handling of bad input."""

from __future__ import annotations

import io
import json
import math
import os
import re
import signal

import numpy as np
import pytest
from conftest import DATA_DIR, MODELS, SHIPPED_MECHANISMS, fourbar_with_crank_limits

from closedchain import cli
from closedchain.dynamics import base as dynamics_base
from closedchain.trajectory import Trajectory

#: Samples for the CLI validation runs (the library test uses 100).
CLI_SAMPLES = "20"

#: The CLI reports numbers computed from the trajectory it writes.
EXACT_TOL = 1e-12


def run(capsys, *argv):
    """Return (exit status, stdout, stderr) of ``closedchain argv``."""
    status = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


# -- info -----------------------------------------------------------------------------------


def test_info_fourbar(capsys, mechanism_files):
    status, out, err = run(capsys, "info", mechanism_files["fourbar"])
    assert status == 0
    assert err == ""
    assert "constraint rows: 5 declared, 2 independent; mobility 1" in out
    assert re.search(r"independent coordinates: crank_joint \(actuated\)", out)
    assert re.search(r"dependent coordinates: +coupler_joint, rocker_joint", out)
    assert re.search(r"actuated coordinates: +crank_joint", out)
    assert re.search(r"^C +revolute +coupler +rocker +5 \(t1 t2 ta r1 r2\) +2 \(t1 t2\)", out, re.M)
    assert re.search(
        r"row selection: rank 2 of J over \d+ configurations along the motion .*"
        r"dropped: C\.ta C\.r1 C\.r2",
        out,
    )


def test_info_agile_eye(capsys, mechanism_files):
    status, out, _ = run(capsys, "info", mechanism_files["agile_eye"])
    assert status == 0
    assert "constraint rows: 15 declared, 6 independent; mobility 3" in out
    assert "independent coordinates: actuator_1, actuator_2, actuator_3 (actuated)" in out
    for leg in (1, 2, 3):
        assert re.search(rf"^leg{leg}_platform +revolute .* 2 \(r1 r2\)", out, re.M)


def test_info_json(capsys, mechanism_files):
    status, out, _ = run(capsys, "info", mechanism_files["fourbar"], "--json")
    assert status == 0
    s = json.loads(out)
    assert (s["nq"], s["nv"]) == (3, 3)
    assert (s["declared_rows"], s["independent_rows"], s["mobility"]) == (5, 2, 1)
    assert s["independent"] == ["crank_joint"]
    assert s["dependent"] == ["coupler_joint", "rocker_joint"]
    assert s["gravity"] == [0.0, 0.0, -9.81]
    assert s["loops"][0]["independent_rows"] == ["t1", "t2"]
    assert s["row_selection"]["rank"] == 2
    assert [t["joint"] for t in s["tree"]] == ["crank_joint", "coupler_joint", "rocker_joint"]


def test_info_gravity_override(capsys, mechanism_files):
    status, out, _ = run(
        capsys, "info", mechanism_files["fourbar"], "--json", "--gravity", "0", "0", "-1.62"
    )
    assert status == 0
    assert json.loads(out)["gravity"] == [0.0, 0.0, -1.62]


def test_info_notes_a_missing_pinocchio_reference(capsys, mechanism_files):
    status, out, _ = run(capsys, "info", mechanism_files["slider_crank"])
    assert status == 0
    assert "constraint rows: 5 declared, 5 independent; mobility 1" in out
    assert "no Pinocchio reference" in out


# -- validate -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SHIPPED_MECHANISMS)
def test_validate_json_passes(capsys, mechanism_files, name):
    path = mechanism_files[name]
    status, out, err = run(capsys, "validate", path, "--samples", CLI_SAMPLES, "--json")
    assert status == 0, err
    rep = json.loads(out)
    assert rep["passed"] is True
    assert rep["mechanism"] == name
    assert rep["method"] == "kkt"
    assert rep["n_samples"] == int(CLI_SAMPLES)
    assert rep["max_da"] <= rep["tol_a"] == 1e-9
    assert rep["max_dforce"] <= rep["tol_force"] == 1e-8


def test_validate_text(capsys, mechanism_files):
    status, out, _ = run(capsys, "validate", mechanism_files["fourbar"], "--samples", "5")
    assert status == 0
    assert "fourbar: method 'kkt' vs pinocchio.constraintDynamics at 5 random" in out
    assert re.search(
        r"^max \|a - a_pin\|_M \(mass-matrix norm, rel\. above 1\) +\S+ +1\.000e-09 +ok", out, re.M
    )
    assert re.search(r"^max \|a - a_pin\| +\S+ *$", out, re.M)  # information, not judged
    assert out.rstrip().endswith("PASSED")


@pytest.fixture
def biased_method(monkeypatch):
    """Register "kkt_biased": the KKT accelerations plus 1e-6 (deliberately wrong)."""
    kkt = dynamics_base.METHODS["kkt"]

    def method(mech, q, v, tau, settings):
        a, lam = kkt(mech, q, v, tau, settings)
        return a + 1e-6, lam

    # The parser builds --method choices from METHODS when main() runs.
    monkeypatch.setitem(dynamics_base.METHODS, "kkt_biased", method)
    return "kkt_biased"


def test_validate_exit_status_1_above_tolerance(capsys, mechanism_files, biased_method):
    path = mechanism_files["fourbar"]
    status, out, _ = run(capsys, "validate", path, "--samples", "5", "--method", biased_method)
    assert status == 1
    assert re.search(r"^max \|a - a_pin\|_M .* +\S+ +1\.000e-09 +FAIL", out, re.M)
    assert re.search(r"^max \|a - a_pin\| +1\.000e-06 *$", out, re.M)
    assert out.rstrip().endswith("FAILED")
    status, out, _ = run(
        capsys, "validate", path, "--samples", "5", "--method", biased_method, "--json"
    )
    assert status == 1
    rep = json.loads(out)
    assert rep["passed"] is False
    assert rep["method"] == biased_method


def test_validate_unknown_method_is_a_usage_error(capsys, mechanism_files):
    with pytest.raises(SystemExit) as info:
        cli.main(["validate", str(mechanism_files["fourbar"]), "--method", "nope"])
    assert info.value.code == 2
    assert "invalid choice: 'nope'" in capsys.readouterr().err


def test_validate_prismatic_loops_exit_2(capsys, mechanism_files):
    status, out, err = run(capsys, "validate", mechanism_files["slider_crank"], "--samples", "1")
    assert status == 2
    assert out == ""
    assert "closedchain: error: loop 'P' is prismatic" in err


# -- bad files ------------------------------------------------------------------------------


@pytest.mark.parametrize("command", ["info", "validate"])
def test_bad_file_exit_2_with_message_on_stderr(capsys, tmp_path, mechanism_files, command):
    path = tmp_path / "broken.urdf"
    path.write_text(mechanism_files["fourbar"].read_text()[:500])
    status, out, err = run(capsys, command, path)
    assert status == 2
    assert out == ""
    assert err.startswith(f"closedchain: error: {path}: malformed XML")


def test_missing_file_exit_2(capsys, tmp_path):
    path = tmp_path / "missing.urdf"
    status, out, err = run(capsys, "info", path)
    assert status == 2
    assert f"closedchain: error: {path}: cannot read URDF file" in err


def test_validate_offers_no_pinocchio_self_comparison(capsys, mechanism_files):
    """Pinocchio is the reference of ``validate``: checking it against itself proves nothing."""
    with pytest.raises(SystemExit) as info:
        cli.main(["validate", str(mechanism_files["fourbar"]), "--method", "pinocchio"])
    assert info.value.code == 2
    assert "invalid choice: 'pinocchio'" in capsys.readouterr().err


# -- simulate -------------------------------------------------------------------------------

#: A short fixed-step run of the slider-crank (nq = 7 != nv = 6: a continuous crank).
SLIDER_CRANK_RUN = ("--t-final", "0.2", "--integrator", "rk4", "--dt", "0.005")


def test_simulate_reports_the_angle_of_a_continuous_joint(capsys, tmp_path, mechanism_files):
    out = tmp_path / "run.npz"
    argv = ["simulate", mechanism_files["slider_crank"], *SLIDER_CRANK_RUN, "--json"]
    status, text, err = run(capsys, *argv, "--out", out)
    assert status == 0, err
    final = json.loads(text)["final_independent"]
    # The crank is the first joint of the URDF: q[0:2] = (cos theta, sin theta).
    q_final = np.load(out)["q"][-1]
    theta = math.atan2(q_final[1], q_final[0])
    assert list(final) == ["crank_joint"]
    assert abs(final["crank_joint"] - theta) <= EXACT_TOL
    assert abs(theta - q_final[0]) > 0.1  # the crank has moved away from cos(theta) = theta


def test_simulate_constant_torque_per_actuated_joint(capsys, tmp_path, mechanism_files):
    """``--torque 0.7`` on the 4-bar is tau = 0.7 N m on its actuated crank (and 0 elsewhere):
    the same run as the library's with that tau."""
    from closedchain import load, simulate
    from closedchain.control import default_scene

    out = tmp_path / "run.npz"
    run_args = ("--t-final", "0.2", "--integrator", "rk4", "--dt", "0.005", "--fps", "10")
    argv = ["simulate", mechanism_files["fourbar"], *run_args, "--torque", "0.7", "--out", out]
    status, _, err = run(capsys, *argv)
    assert status == 0, err
    mech = load(mechanism_files["fourbar"])
    scene = default_scene(mech)
    tau = np.zeros(mech.nv)
    tau[mech.actuated_idx_v] = 0.7
    ref = simulate(
        mech, scene.q0, scene.v0, 0.2, dt=0.005, tau=tau, t_eval=cli.output_times(0.2, 10)
    )
    np.testing.assert_allclose(np.load(out)["q"], ref.q, rtol=0, atol=EXACT_TOL)
    np.testing.assert_allclose(np.load(out)["work"], ref.work, rtol=0, atol=EXACT_TOL)
    free = simulate(mech, scene.q0, scene.v0, 0.2, dt=0.005, t_eval=cli.output_times(0.2, 10))
    assert np.linalg.norm(free.q[-1] - ref.q[-1]) > 1e-3  # the torque moved it


def test_simulate_reports_a_joint_past_its_limit(capsys, tmp_path):
    """A negative --torque spins the 4-bar's crank past a <limit> of -3 rad: the summary
    lists it (joint, first time, value, limit)."""
    urdf = fourbar_with_crank_limits(tmp_path, -3.0, 3.0)
    argv = ["simulate", urdf, "--t-final", "0.5", "--fps", "100"]
    status, out, err = run(capsys, *argv, "--torque", "-3", "--json")
    assert status == 0, err
    summary = json.loads(out)
    found = {v[0]: v[1:] for v in summary["limit_violations"]}
    # the torque's work is most of E - E0: the balance is far below the drift
    assert summary["energy_balance"] < 1e-6 * summary["energy_drift"]
    t_first, value, limit = found["crank_joint"]
    assert limit == -3.0 and value < limit and 0 < t_first <= 0.5


# -- bad arguments --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["simulate", "{fourbar}", "--t-final", "-1"],
            "--t-final must be a positive number, got -1",
        ),
        (["simulate", "{fourbar}", "--t-final", "nan"], "--t-final must be a positive number"),
        (["animate", "{fourbar}", "--fps", "0", "-o", "{tmp}/a.html"], "--fps must be a positive"),
        (
            ["animate", "{fourbar}", "--mesh-budget", "nan", "-o", "{tmp}/a.html"],
            "--mesh-budget must be a number of MB >= 0, got nan",
        ),
        (["simulate", "{fourbar}", "--integrator", "rk4", "--dt", "0"], "--dt must be a positive"),
        (["simulate", "{fourbar}", "--rtol=-1e-9"], "--rtol must be a positive number"),
        (["validate", "{fourbar}", "--samples", "0"], "--samples must be at least 1, got 0"),
        (
            ["simulate", "{fourbar}", "--integrator", "rk4", "--dt", "inf"],
            "--dt must be a positive",
        ),
        (
            ["simulate", "{fourbar}", "--fps", "1e9"],
            "--fps 1e+09 over --t-final 5 s is 5000000001 output samples, more than the limit"
            " 10000000 (SimulationSettings.max_outputs); valid --fps: (0, 1999999.8]",
        ),
        (
            ["animate", "{fourbar}", "--fps", "1e9", "-o", "{tmp}/a.html"],
            "--fps 1e+09 over --t-final 5 s is 5000000001 keyframes, more than the limit 100000"
            " (AnimationSettings.max_keyframes); valid --fps: (0, 19999.8]",
        ),
        (
            ["simulate", "{fourbar}", "--integrator", "rk4", "--dt", "1e-12"],
            "dt = 1e-12 s over t_final = 5 s is 5e+12 steps, more than "
            "SimulationSettings.max_steps = 1e+08; use a larger dt (>= 5e-08 s)",
        ),
        (
            ["simulate", "{fourbar}", "--out", "{tmp}/t.txt"],
            "cannot save a trajectory as 't.txt'; valid suffixes: .npz, .csv",
        ),
        (
            ["simulate", "{fourbar}", "--out", "{tmp}/nodir/t.npz"],
            "{tmp}/nodir/t.npz: directory {tmp}/nodir does not exist",
        ),
        (
            ["animate", "{fourbar}", "-o", "{tmp}/nodir/a.html"],
            "{tmp}/nodir/a.html: directory {tmp}/nodir does not exist",
        ),
        (
            ["plot", "{fourbar}", "-o", "{tmp}/x.xyz"],
            "cannot write an image as 'x.xyz'; valid suffixes: .",
        ),
        (["plot", "{fourbar}", "-o", "{tmp}/noext"], "cannot write an image as 'noext'"),
        (
            ["plot", "{fourbar}", "--urdf", "{fourbar}", "-o", "{tmp}/x.png"],
            "--urdf is for a .npz trajectory",
        ),
        # commands and options added since the first hostile-input round
        (["bench", "--workers", "0", "--out", "{tmp}/b"], "--workers must be at least 1, got 0"),
        (["bench", "--workers", "-1", "--out", "{tmp}/b"], "--workers must be at least 1, got -1"),
        (["bench", "--repeats", "0", "--out", "{tmp}/b"], "--repeats must be at least 1, got 0"),
        (
            ["bench", "--scheduler", "garbage", "--out", "{tmp}/b"],
            "--scheduler 'garbage' is not a scheduler address; valid: [protocol://]host:port",
        ),
        (
            ["export-mjcf", "{fourbar}", "-o", "{tmp}/nodir/x.xml"],
            "{tmp}/nodir/x.xml: directory {tmp}/nodir does not exist",
        ),
        (["export-mjcf", "{fourbar}", "-o", "{tmp}"], "cannot write MJCF as '"),
        (["info", "erd:nonexistent"], "unknown example-robot-data model 'erd:nonexistent'; valid"),
        (["info", "{fourbar}", "--loops", "{tmp}/none.urdf"], "{tmp}/none.urdf: cannot read"),
        (["info", "{fourbar}", "--gravity", "nan", "0", "0"], "gravity must be 3 finite numbers"),
        (
            ["workspace", "{fourbar}", "-o", "{tmp}/w.xyz"],
            "cannot write an image as 'w.xyz'; valid suffixes: .",
        ),
        (["workspace", "{fourbar}", "-o", "{tmp}/w.png", "--points", "0"], "points must be in [2,"),
        (
            ["workspace", "{fourbar}", "-o", "{tmp}/w.png", "--points", "1000000000"],
            "points must be in [2, 100000], got 1000000000",
        ),
        (
            ["workspace", "{eye}", "-o", "{tmp}/w.png", "--points", "-5"],
            "points must be in [2, 201], got -5",
        ),
        (["workspace", "{eye}", "-o", "{tmp}/w.png", "--span", "nan"], "--span must be a positive"),
        (
            ["workspace", "{eye}", "-o", "{tmp}/w.png", "--span", "1e308"],
            "span must be a positive number [rad] of at most 1e+06",
        ),
        (
            ["simulate", "{no_joint}", "--t-final", "0.1"],
            "{no_joint}: the tree has no movable joint (nv = 0), so there is nothing to simulate",
        ),
        (["validate", "{no_joint}"], "{no_joint}: the tree has no movable joint (nv = 0)"),
        (
            ["plot", "{tmp}/t.csv", "-o", "{tmp}/p.png"],
            "{tmp}/t.csv: plot reads a .npz trajectory or a URDF file to simulate",
        ),
        (
            ["simulate", "{fourbar}", "--torque", "1", "2"],
            "--torque takes 1 number(s) for fourbar, got 2; actuated joints (<transmission>): "
            "crank_joint",
        ),
        (
            ["simulate", "{fourbar}", "--torque", "strong"],
            "--torque strong: valid: zero or gravity, or finite numbers [N m or N], one per "
            "actuated joint",
        ),
        (["simulate", "{fourbar}", "--torque", "1", "nan"], "--torque 1 nan: valid: zero or"),
        (
            ["workspace", "{eye}", "-o", "{tmp}/w.png", "--outputs", "nosuch"],
            "a singularity map needs two output coordinates, got ('nosuch',); valid: two of "
            "actuator_1,",
        ),
        (
            ["workspace", "{eye}", "-o", "{tmp}/w.png", "--outputs", "actuator_1", "actuator_1"],
            "--outputs names actuator_1 more than once; valid: distinct joints",
        ),
        (["validate", "{fourbar}", "--seed", "-1"], "--seed must be at least 0, got -1"),
        (
            ["validate", "{fourbar}", "--samples", "1000000000"],
            "--samples must be at most 100000, got 1000000000",
        ),
        (
            ["bench", "--workers", "100000", "--out", "{tmp}/b"],
            "--workers must be at most 256, got 100000",
        ),
        (
            ["bench", "--repeats", "1000000", "--out", "{tmp}/b"],
            "--repeats must be at most 1000, got 1000000",
        ),
        (
            ["animate", "{fourbar}", "-o", "{tmp}/a.htm"],
            "cannot write an HTML animation as 'a.htm'; valid suffixes: .html",
        ),
        (
            ["animate", "{fourbar}", "-o", "{fourbar}"],
            "cannot write an HTML animation as 'fourbar.urdf'; valid suffixes: .html",
        ),
        (
            ["export-mjcf", "{fourbar}", "-o", "{tmp}/m.urdf"],
            "cannot write MJCF as 'm.urdf'; valid suffixes: .xml",
        ),
        (
            ["simulate", "{fourbar}", "--t-final", "1e308"],
            "--fps 30 over --t-final 1e+308 s is inf output samples, more than the limit",
        ),
        (
            ["simulate", "{fourbar}", "--integrator", "rk4", "--dt", "1e-320", "--t-final", "1"],
            "dt = 9.99989e-321 s over t_final = 1 s is inf steps, more than",
        ),
        (["simulate", "{fourbar}", "--q0", "1", "2"], "--q0 has shape (2,), expected (3,)"),
        (["simulate", "{fourbar}", "--q0", "nan", "0", "0"], "--q0 contains non-finite values"),
        (["info", "/dev/zero"], "/dev/zero: URDF file is a character device; valid: a regular"),
        (["info", "{tmp}"], "{tmp}: URDF file is a directory; valid: a regular file"),
        (
            ["info", "{fourbar}", "--loops", "/dev/zero"],
            "/dev/zero: overlay file is a character device; valid: a regular file",
        ),
    ],
)
def test_bad_arguments_exit_2_with_one_line(capsys, tmp_path, mechanism_files, argv, message):
    fmt = {
        "fourbar": mechanism_files["fourbar"],
        "eye": mechanism_files["agile_eye"],
        "no_joint": DATA_DIR / "no_joint.urdf",
        "tmp": tmp_path,
    }
    status, out, err = run(capsys, *(a.format(**fmt) for a in argv))
    assert status == 2
    assert out == ""
    assert err.startswith("closedchain: error: " + message.format(**fmt))
    assert err.count("\n") == 1
    assert not list(tmp_path.iterdir())  # refused before any work


def test_plot_lists_the_supported_image_suffixes(capsys, tmp_path, mechanism_files):
    status, _, err = run(capsys, "plot", mechanism_files["fourbar"], "-o", tmp_path / "x.xyz")
    assert status == 2
    for suffix in (".png", ".pdf", ".svg"):
        assert suffix in err


@pytest.mark.parametrize("command", ["simulate", "plot"])
def test_unwritable_output_exits_2(capsys, tmp_path, mechanism_files, command):
    """An OSError while writing (here: the output is a directory) is a one-line error."""
    target = tmp_path / ("t.npz" if command == "simulate" else "x.png")
    target.mkdir()
    flag = "--out" if command == "simulate" else "-o"
    argv = [command, mechanism_files["fourbar"], "--t-final", "0.05", flag, target]
    status, out, err = run(capsys, *argv)
    assert status == 2
    assert str(target) in err and err.startswith("closedchain: error: ")
    assert err.count("\n") == 1


# -- exit statuses, --debug, names in any case ---------------------------------------------

#: The 4-bar's open branch at theta2 = 10 deg (a guess the CLI assembles, crank held); from
#: rest it reaches its change point at t = 0.393 s (tests/test_simulate.py).
Q0_OPEN = ("0.17453292519943295", "0.8726646259971648", "0.5235987755982988")
#: A configuration that stops at the change point (the default passes it: tests/test_singular.py).
STOPPING = ("--method", "kkt", "--integrator", "DOP853")


def test_python_dash_m_runs_the_cli(mechanism_files):
    """``python -m closedchain`` is the ``closedchain`` script (README commands use both)."""
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-m", "closedchain", "info", str(mechanism_files["fourbar"]), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["mobility"] == 1


def test_help_documents_every_exit_status(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for status in (*range(5), 130, 143):
        assert re.search(rf"^  {status}  \S", out, re.M), status
    assert "--debug" in out


def test_simulation_stopped_at_a_singularity_exits_3(capsys, mechanism_files):
    argv = ["simulate", mechanism_files["fourbar"], "--t-final", "1", "--q0", *Q0_OPEN, *STOPPING]
    status, out, err = run(capsys, *argv)
    assert status == cli.EXIT_STOPPED == 3
    # The summary of the motion up to the stop is printed, then the one-line error.
    assert out.startswith("fourbar: 1 s with method")
    assert len(err.splitlines()) == 1
    assert re.match(r"closedchain: error: fourbar:? at t = 0\.39\d+ s.*singular", err)


@pytest.fixture
def crashing_info(monkeypatch):
    """Make ``info`` fail with an unexpected exception (a stand-in for a bug)."""

    def crash(args):
        raise RuntimeError("boom")

    parser = cli.build_parser

    def build():
        p = parser()
        sub = next(a for a in p._actions if isinstance(a, cli.argparse._SubParsersAction))
        sub.choices["info"].set_defaults(handler=crash)
        return p

    monkeypatch.setattr(cli, "build_parser", build)


def test_internal_error_exits_4_without_traceback(capsys, mechanism_files, crashing_info):
    status, out, err = run(capsys, "info", mechanism_files["fourbar"])
    assert status == cli.EXIT_INTERNAL == 4
    assert err == (
        "closedchain: internal error: RuntimeError: boom (run with --debug for the traceback)\n"
    )
    assert "Traceback" not in err


@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_prints_the_traceback(capsys, mechanism_files, crashing_info, where):
    argv = ["info", mechanism_files["fourbar"]]
    argv = ["--debug", *argv] if where == "before" else [*argv, "--debug"]
    status, _, err = run(capsys, *argv)
    assert status == 4
    assert err.startswith("Traceback (most recent call last):")
    assert 'raise RuntimeError("boom")' in err


def test_bad_input_exit_2_and_failed_check_exit_1_are_distinct():
    from closedchain.simulate import SimulationError

    assert cli.exit_status(cli.ClosedChainError("x")) == 2
    assert cli.exit_status(OSError("x")) == 2
    assert cli.exit_status(cli.SingularConfigurationError("x")) == 3
    assert cli.exit_status(SimulationError("x", 0.0)) == 3
    assert cli.exit_status(cli.NonFiniteError("x")) == 3
    assert cli.exit_status(ZeroDivisionError()) == 4
    assert len({cli.EXIT_OK, cli.EXIT_FAILED, cli.EXIT_BAD_INPUT, 3, 4}) == 5


def test_names_are_case_insensitive(capsys, mechanism_files):
    argv = [
        "simulate",
        mechanism_files["fourbar"],
        "--t-final",
        "0.05",
        "--method",
        "KKT",
        "--integrator",
        "dop853",
        "--stabilization",
        "Projection",
        "--json",
    ]
    status, out, err = run(capsys, *argv)
    assert status == 0, err
    s = json.loads(out)
    assert (s["method"], s["integrator"], s["stabilization"]) == ("kkt", "DOP853", "projection")


def test_unknown_integrator_lists_the_choices(capsys, mechanism_files):
    with pytest.raises(SystemExit) as exc:
        cli.main(["simulate", str(mechanism_files["fourbar"]), "--integrator", "leapfrog"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'leapfrog'" in err
    for name in ("DOP853", "Radau", "rk4", "euler"):
        assert name in err


def test_fps_below_one_sample_keeps_start_and_end(capsys, tmp_path, mechanism_files):
    out_file = tmp_path / "t.npz"
    argv = ["simulate", mechanism_files["fourbar"], "--t-final", "1", "--fps", "0.05"]
    status, _, err = run(capsys, *argv, "--out", out_file)
    assert status == 0, err
    from closedchain import Trajectory

    np.testing.assert_array_equal(Trajectory.load(out_file).t, [0.0, 1.0])


def test_animate_writes_the_motion_up_to_a_singular_stop_and_exits_3(
    capsys, tmp_path, mechanism_files
):
    out_file = tmp_path / "stop.html"
    argv = ["animate", mechanism_files["fourbar"], "--t-final", "1", "--q0", *Q0_OPEN, *STOPPING]
    status, out, err = run(capsys, *argv, "-o", out_file)
    assert status == 3
    assert out.startswith(f"wrote {out_file} (")
    assert re.search(r"closedchain: error: fourbar: at t = 0\.39\d+ s .*animation written", err)
    page = out_file.read_text()
    banner = re.search(r'<div id="closedchain-stop" role="alert">([^<]*)</div>', page)
    assert banner and banner.group(1).startswith("Simulation stopped at t = 0.39")
    meta = json.loads(re.search(r'id="closedchain-scene">(.*?)</script>', page).group(1))["meta"]
    assert meta["stop"].startswith("Simulation stopped at t = 0.39")
    assert 0.36 <= meta["duration"] <= 0.393  # up to the last output sample before the stop


def test_animate_default_scene_has_no_stop_banner(capsys, tmp_path, mechanism_files):
    out_file = tmp_path / "fourbar.html"
    status, _, err = run(
        capsys, "animate", mechanism_files["fourbar"], "--t-final", "0.2", "-o", out_file
    )
    assert status == 0, err
    assert 'id="closedchain-stop"' not in out_file.read_text()


def test_start_outside_the_limits_exits_2_unless_ignored(capsys, mechanism_files):
    far = ("--q0", "1e17", "-1.13", "-1.81")
    argv = ["simulate", mechanism_files["fourbar"], "--t-final", "0.01"]
    status, _, err = run(capsys, *argv, *far)
    assert status == cli.EXIT_BAD_INPUT
    assert len(err.splitlines()) == 1 and "'crank_joint' is at 1e+17, outside" in err
    # --ignore-limits opens the URDF limits, never the bound a double can still resolve.
    status, _, err = run(capsys, *argv, *far, "--ignore-limits")
    assert status == cli.EXIT_BAD_INPUT and "[-1e+06, 1e+06]" in err
    one_turn_on = ("--q0", str(0.17453292519943295 + 2 * math.pi), "-1.13", "-1.81")
    status, _, err = run(capsys, *argv, *one_turn_on, "--ignore-limits")
    assert status == 0, err


def test_inaccurate_run_is_not_a_success(capsys, mechanism_files, tmp_path):
    """Explicit Euler at 1 ms: 9 % energy drift in 2 s, reported with exit 3, output kept."""
    out = tmp_path / "euler.npz"
    argv = ["simulate", mechanism_files["fourbar"], "--t-final", "2", "--integrator", "euler"]
    status, stdout, err = run(capsys, *argv, "--dt", "1e-3", "--out", out)
    assert status == cli.EXIT_STOPPED
    assert len(err.splitlines()) == 1 and "energy drift" in err and "--energy-tol" not in stdout
    assert Trajectory.load(out).t[-1] == pytest.approx(2.0)
    status, _, err = run(capsys, *argv, "--dt", "1e-3", "--energy-tol", "0.5")
    assert status == 0, err


def test_rtol_without_integrator_runs_the_adaptive_default(capsys, mechanism_files):
    argv = ["simulate", mechanism_files["fourbar"], "--t-final", "0.05", "--rtol", "1e-9"]
    status, out, err = run(capsys, *argv, "--json")
    assert status == 0, err
    summary = json.loads(out)
    assert summary["integrator"] == "dop853-rk43"
    assert summary["rejected_steps"] >= 0 and 0.0 < summary["error_estimate_max"] <= 1.0
    assert summary["error_estimate_sum"] > 0.0


def test_summary_prints_the_error_control_beside_max_phi(capsys, mechanism_files):
    """The default's run summary: rejected steps and the error estimates by max |phi|;
    a fixed-step run has no such rows."""
    argv = ["simulate", mechanism_files["fourbar"], "--t-final", "0.05"]
    status, out, err = run(capsys, *argv)
    assert status == 0, err
    assert "'dop853-rk43'" in out
    for row in ("rejected steps", "largest local error estimate", "max constraint residual"):
        assert row in out, row
    status, out, err = run(capsys, *argv, "--dt", "1e-3")
    assert status == 0, err
    assert "'rk4'" in out and "rejected steps" not in out


# -- files, bounds and one-line messages ----------------------------------------------------


def one_line_error(status: int, err: str, expected_status: int = cli.EXIT_BAD_INPUT) -> str:
    """Check the exit status and that stderr is exactly one ``closedchain: error:`` line."""
    assert status == expected_status, err
    assert err.startswith("closedchain: error: ") and err.count("\n") == 1, err
    return err


def test_a_fifo_input_is_refused_without_blocking(capsys, tmp_path):
    fifo = tmp_path / "pipe.urdf"
    os.mkfifo(fifo)
    err = one_line_error(*run(capsys, "info", fifo)[::2])
    assert f"{fifo}: URDF file is a named pipe (FIFO); valid: a regular file" in err
    fifo_npz = tmp_path / "pipe.npz"
    os.mkfifo(fifo_npz)
    err = one_line_error(*run(capsys, "plot", fifo_npz, "-o", tmp_path / "p.png")[::2])
    assert f"{fifo_npz}: trajectory is a named pipe (FIFO)" in err


def test_a_urdf_over_the_size_limit_is_refused_unread(capsys, tmp_path):
    from closedchain._io import MAX_XML_BYTES

    path = tmp_path / "huge.urdf"
    with path.open("wb") as f:
        f.truncate(MAX_XML_BYTES + 1)  # sparse: no disk space used
    err = one_line_error(*run(capsys, "info", path)[::2])
    assert f"{path}: URDF file of 6.711e+07 bytes is larger than the limit of 6.711e+07" in err


def test_an_npz_claiming_4_5_gb_is_refused_before_loading(capsys, tmp_path):
    import zipfile

    path = tmp_path / "huge.npz"
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": (562_500_000,)}
    )
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("t.npy", header.getvalue() + b"\0" * 64)
    err = one_line_error(*run(capsys, "plot", path, "-o", tmp_path / "p.png")[::2])
    assert "huge.npz: trajectory member 't.npy' claims an array of shape (562500000,)" in err
    assert not (tmp_path / "p.png").exists()


@pytest.fixture
def fourbar_as_xml(tmp_path, mechanism_files):
    """A copy of the 4-bar URDF named ``v.xml``, the suffix export-mjcf writes."""
    path = tmp_path / "v.xml"
    path.write_bytes(mechanism_files["fourbar"].read_bytes())
    return path


@pytest.mark.parametrize("same", ["path", "hard link", "symbolic link"])
def test_an_output_that_is_the_input_is_refused(capsys, tmp_path, fourbar_as_xml, same):
    original = fourbar_as_xml.read_bytes()
    out = {
        "path": fourbar_as_xml,
        "hard link": tmp_path / "h.xml",
        "symbolic link": tmp_path / "s.xml",
    }[same]
    if same == "hard link":
        os.link(fourbar_as_xml, out)
    elif same == "symbolic link":
        out.symlink_to(fourbar_as_xml)
    err = one_line_error(*run(capsys, "export-mjcf", fourbar_as_xml, "-o", out)[::2])
    assert f"-o/--output {out} is the input file FILE {fourbar_as_xml}; writing it would" in err
    assert fourbar_as_xml.read_bytes() == original


def test_an_output_that_is_the_overlay_is_refused(capsys, tmp_path, mechanism_files):
    overlay = tmp_path / "overlay.xml"
    overlay.write_text('<robot name="o"></robot>')
    argv = ["export-mjcf", mechanism_files["fourbar"], "--loops", overlay, "-o", overlay]
    err = one_line_error(*run(capsys, *argv)[::2])
    assert f"is the input file --loops {overlay}" in err
    assert overlay.read_text() == '<robot name="o"></robot>'


def test_gravity_torque_with_mobility_0_says_there_is_nothing_to_hold(
    capfd, tmp_path, mechanism_files
):
    text = mechanism_files["fourbar"].read_text()
    text = re.sub(r"<scene>.*?</scene>", "", text, flags=re.S)
    # A second loop, D, pins the crank's tip (0.2 m out) to the ground: mobility 0.
    loop_c = re.search(r'  <loop name="C".*?</loop>\n', text, flags=re.S).group(0)
    loop_d = (
        loop_c.replace('name="C"', 'name="D"')
        .replace('link="coupler"', 'link="ground"')
        .replace('link="rocker"', 'link="crank"')
        .replace('xyz="0.4 0 0"', 'xyz="0.2 0 0"')
        .replace('xyz="0.3 0 0"', 'xyz="0.2 0 0"')
    )
    path = tmp_path / "rigid.urdf"
    path.write_text(text.replace(loop_c, loop_c + loop_d, 1))
    status = cli.main(["simulate", str(path), "--t-final", "0.01", "--torque", "gravity"])
    out, err = capfd.readouterr()
    one_line_error(status, err)
    assert "--torque gravity: fourbar has no degree of freedom (mobility 0): nothing to hold" in err
    assert out == ""  # no LAPACK "** On entry to DGESDD" line


def test_a_tree_error_is_one_line(capfd, tmp_path, mechanism_files):
    path = tmp_path / "orphan.urdf"
    text = mechanism_files["fourbar"].read_text()
    path.write_text(text.replace('<parent link="crank"/>', '<parent link="nosuch"/>', 1))
    status = cli.main(["info", str(path)])
    err = one_line_error(status, capfd.readouterr().err)
    assert (
        "<joint name='coupler_joint'>: <parent link='nosuch'> names no <link> of this file; "
        "links: coupler, crank, ground, rocker" in err
    )


@pytest.mark.parametrize(
    ("model", "argv", "status", "message"),
    [
        ("eye_1e308_hz", [], 2, "frequency 1e+308 Hz overflow the reference's position"),
        (
            "fourbar",
            ["--gravity", "1e308", "0", "0"],
            2,
            "gravity [1.e+308 0.e+000 0.e+000] m/s^2 is beyond the limit; valid: a norm of at "
            "most 1e+06 m/s^2",
        ),
        (
            "fourbar",
            ["--integrator", "dop853", "--atol", "1e-320"],
            2,
            "atol = 9.99989e-321 is so small that scipy's error norm overflows; valid range: "
            "[1e-150, inf)",
        ),
    ],
)
def test_overflows_give_one_line_and_no_runtime_warning(
    capfd, tmp_path, mechanism_files, model, argv, status, message
):
    import warnings

    if model == "eye_1e308_hz":
        path = tmp_path / "eye.urdf"
        text = mechanism_files["agile_eye"].read_text()
        path.write_text(text.replace('frequency="0.1"', 'frequency="1e308"', 1))
    else:
        path = mechanism_files[model]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code = cli.main(["simulate", str(path), "--t-final", "0.01", *argv])
    err = one_line_error(code, capfd.readouterr().err, status)
    assert message in err
    assert [str(w.message) for w in caught] == []


def test_a_multi_line_message_is_printed_on_one_line():
    from closedchain.exceptions import ClosedChainError

    exc = ClosedChainError("v contains non-finite values: [0. 0.\n 0. inf]")
    assert cli.error_message(exc) == "v contains non-finite values: [0. 0. 0. inf]"


@pytest.fixture
def info_handler(monkeypatch):
    """Replace the handler of ``info`` with a given function."""

    def install(handler):
        parser = cli.build_parser

        def build():
            p = parser()
            sub = next(a for a in p._actions if isinstance(a, cli.argparse._SubParsersAction))
            sub.choices["info"].set_defaults(handler=handler)
            return p

        monkeypatch.setattr(cli, "build_parser", build)

    return install


def test_memory_error_is_a_one_line_bad_input_naming_the_command(
    capsys, mechanism_files, info_handler
):
    def exhaust(args):
        raise MemoryError("Unable to allocate 4.5 GiB for an array with shape (562500000,)")

    info_handler(exhaust)
    err = one_line_error(*run(capsys, "info", mechanism_files["fourbar"])[::2])
    assert f"not enough memory for info {mechanism_files['fourbar']} (Unable to allocate" in err


@pytest.mark.parametrize(
    ("signum", "status", "word"),
    [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")],
)
def test_a_signal_during_a_write_keeps_the_previous_file(
    capsys, tmp_path, mechanism_files, info_handler, signum, status, word
):
    from closedchain._io import atomic_write

    target = tmp_path / "out.html"
    target.write_bytes(b"previous")

    def write_and_die(args):
        with atomic_write(target) as f:
            f.write(b"half of the new ")
            os.kill(os.getpid(), signum)
            f.write(b"page")  # not reached: the handler raises
        return 0

    info_handler(write_and_die)
    code, out, err = run(capsys, "info", mechanism_files["fourbar"])
    assert (code, err) == (status, f"closedchain: {word}\n")
    assert target.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.html"]
    assert signal.getsignal(signal.SIGTERM) is not cli._raise_terminated  # restored


def test_a_full_disk_names_the_file_and_keeps_the_previous_one(tmp_path, mechanism_files):
    """RLIMIT_FSIZE (``ulimit -f``) makes the write fail with EFBIG (Python ignores SIGXFSZ)."""
    import resource
    import subprocess
    import sys

    target = tmp_path / "t.csv"
    target.write_bytes(b"previous")

    def limit_file_size():
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))

    argv = ["simulate", str(mechanism_files["fourbar"]), "--t-final", "1", "--out", str(target)]
    proc = subprocess.run(
        [sys.executable, "-m", "closedchain", *argv],
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=limit_file_size,
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr == f"closedchain: error: {target}: File too large\n"
    assert target.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.csv"]


def test_keyframe_option_chooses_the_mjcf_start(capsys):
    floating = DATA_DIR / "mjcf" / "floating.xml"
    status, out, _ = run(capsys, "info", floating, "--keyframe", "crouch")
    assert status == 0 and "q_ref" in out
    err = one_line_error(*run(capsys, "info", floating, "--keyframe", "stand")[::2])
    assert "unknown keyframe 'stand'; keyframes: crouch" in err


# -- message bounds (issue 32) ------------------------------------------------------------------

#: Longest stderr of a refused input [bytes]: argparse's usage lines and one message line
#: (closedchain.exceptions.MESSAGE_MAX = 2000 characters).
STDERR_BOUND = 4_000
#: Characters of the huge frame name (a 60 MB one gave 125 MB of stderr; lxml refuses an
#: attribute beyond 10 MB).
HUGE_NAME = 5_000_000


def test_a_huge_frame_name_gives_one_bounded_line(tmp_path, capsys):
    text = (MODELS / "fourbar.urdf").read_text()
    old = '<successor link="rocker"/>'
    assert text.count(old) == 1
    path = tmp_path / "huge_name.urdf"
    path.write_text(text.replace(old, f'<successor link="{"r" * HUGE_NAME}"/>'))
    status, _, err = run(capsys, "info", path)
    assert status == 2
    assert err.count("\n") == 1 and len(err) < STDERR_BOUND
    assert "rrr...rrr" in err and "names an unknown link" in err


@pytest.mark.parametrize("fps", ["9" * 300, "x" + "9" * 300_000])
def test_a_huge_fps_is_refused_without_echoing_it(tmp_path, capsys, fps):
    """A 300-digit --fps was echoed as a 300-digit sample count; a value argparse cannot
    read is quoted by argparse, cut to the message bound."""
    argv = ["animate", str(MODELS / "fourbar.urdf"), "--fps", fps, "-o", str(tmp_path / "a.html")]
    try:
        status = cli.main(argv)
    except SystemExit as exc:  # argparse's own refusal
        status = exc.code
    err = capsys.readouterr().err
    assert status == 2
    assert len(err) < STDERR_BOUND and "9" * 300 not in err
    assert (
        err.strip()
        .splitlines()[-1]
        .startswith(("closedchain: error: --fps", "closedchain animate: error: argument --fps"))
    )
