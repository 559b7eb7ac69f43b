"""Command line: readable output, JSON, and one-line errors with exit status 2."""

import json
import subprocess
import sys

import numpy as np
import pytest

from polins.cli import main


def test_sun_json(capsys):
    assert (
        main(
            [
                "sun",
                "--time",
                "2023-09-05T15:06+08:00",
                "--lat",
                "45.6234",
                "--lon",
                "126.7264",
                "--alt",
                "148.74",
                "--json",
            ]
        )
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["sun_azimuth_deg"] == pytest.approx(247.04, abs=0.01)
    assert np.linalg.norm(report["sun_n"]) == pytest.approx(1.0)
    assert report["sun_n"][0] < 0 and report["sun_n"][1] < 0  # west-south-west


def test_sun_text(capsys):
    assert (
        main(["sun", "--time", "2023-09-05T07:06Z", "--lat", "45.6234", "--lon", "126.7264"]) == 0
    )
    out = capsys.readouterr().out
    assert "sun azimuth" in out and "deg" in out and "sun vector (ENU)" in out


def test_naive_time_is_one_line_exit_2(capsys):
    code = main(["sun", "--time", "2023-09-05T15:06", "--lat", "45.6", "--lon", "126.7"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "naive datetime" in err
    assert "Traceback" not in err


def test_console_script_help():
    out = subprocess.run([sys.executable, "-m", "polins", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "sun" in out.stdout and "demo" in out.stdout


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["fuse", "nope.toml", "--out", "run", "--workers", "0"], "--workers 0: expected >= 1"),
        (["fuse", "nope.toml", "--out", "run", "--rot0", "1,2"], "--rot0 '1,2': expected ROLL"),
        (["fuse", "nope.toml", "--out", "run", "--rot0", "10,20"], "exactly 3 numbers"),
        (["fuse", "nope.toml", "--out", "run", "--rot0", "1,2,3,4"], "exactly 3 numbers"),
        (["fuse", "nope.toml", "--out", "run", "--rot0", "0,95,10"], "--rot0 pitch 95"),
        (["fuse", "nope.toml", "--out", "run", "--rot0", "0,nan,10"], "exactly 3 numbers"),
        (["fuse", "nope.toml", "--out", "run", "--nhc", "inf"], "expected a finite number"),
        (["fuse", "nope.toml", "--out", "run", "--max-image-failures", "150%"], "0%..100%"),
        (["fuse", "nope.toml", "--out", "run", "--set", "nhc_stdd=0.1"],
         "unknown filter option 'nhc_stdd' (did you mean 'nhc_std'?)"),
        (["fuse", "nope.toml", "--out", "run", "--set", "nhc_std=fast"], "nhc_std='fast'"),
        (["fuse", "nope.toml", "--out", "run", "--set", "vel_n0=1,x,0"], "--set vel_n0='1,x,0': expected 3 numbers"),
        (["fuse", "nope.toml", "--out", "run", "--set", "gate_prob=2"], "expected a probability in (0, 1)"),
        (["fuse", "nope.toml", "--out", "run", "--set", "solver=isam2"], "graph backend only"),
        (["fuse", "nope.toml", "--out", "run", "--set", "imu_model=x"], "with --imu"),
        (["fuse", "nope.toml", "--out", "run", "--imu", "no-such-imu"], "no-such-imu"),
        (["heading", "img.png", "--roll", "inf", "--time", "2023-09-05T07:06Z", "--lat", "45",
          "--lon", "126"], "--roll: 'inf': expected a finite number"),
        (["heading", "img.png", "--pitch", "100", "--time", "2023-09-05T07:06Z", "--lat", "45",
          "--lon", "126"], "--pitch 100: expected an angle in [-90, 90] deg"),
        (["demo", "--images", "0"], "--images 0"),
        (["simulate", "--scenario", "ugv", "--out", "sim", "--imu", "nope"], "nope"),
        (["fuse", "nope.toml", "--out", "run"], "manifest not found"),
        (["fuse", "nope.toml", "--out", "run", "--smooth", "--backend", "graph"], "--smooth needs"),
        (["simulate", "--scenario", "ugv", "--out", "sim", "--downscale", "3"], "--downscale 3"),
        (["simulate", "--scenario", "ugv", "--out", "sim", "--epoch", "2023-09-05T07:06"],
         "--epoch = '2023-09-05T07:06': naive datetime"),
        (["sun", "--time", "2023-09-05T07:06Z", "--lat", "145", "--lon", "126"], "Site.lat_deg"),
    ],
)  # fmt: skip
def test_user_mistakes_are_one_line_exit_2_before_any_work(tmp_path, monkeypatch, capsys, argv,
                                                           message):  # fmt: skip
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # nothing written


@pytest.mark.parametrize("command", ["fuse", "demo", "simulate"])
def test_out_folder_that_is_a_file_is_a_user_mistake(tmp_path, capsys, command):
    """Found: ``--out FILE`` ended in a FileExistsError traceback after the whole run."""
    (tmp_path / "run").write_text("")
    argv = {"fuse": ["fuse", str(tmp_path / "m.toml")], "demo": ["demo", "--images", "1"],
            "simulate": ["simulate", "--scenario", "ugv"]}[command]  # fmt: skip
    code = main([*argv, "--out", str(tmp_path / "run")])
    err = capsys.readouterr()
    assert code == 2 and "is a file" in err.err and len(err.err.strip().splitlines()) == 1
    assert "polins demo:" not in err.out  # refused before the demo started


def test_out_folder_that_cannot_be_created(tmp_path, capsys):
    (tmp_path / "f").write_text("")
    code = main(["simulate", "--scenario", "ugv", "--out", str(tmp_path / "f" / "sub" / "log")])
    assert code == 2 and "cannot be created" in capsys.readouterr().err


def test_workers_zero_is_refused(tmp_path, capsys):
    """Found: ``--workers 0`` silently meant all cores."""
    code = main(["fuse", str(tmp_path), "--out", str(tmp_path / "r"), "--workers", "0"])
    assert code == 2 and "--workers 0: expected >= 1" in capsys.readouterr().err


def test_argparse_errors_are_one_line_too(capsys):
    code = main(["heading", "x.png", "--lat", "abc", "--lon", "1", "--time", "2023-09-05T07:06Z"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--lat" in err


def test_closed_pipe_is_quiet():
    """Found: ``polins simulate ... | head -1`` gave a BrokenPipe traceback."""
    argv = [sys.executable, "-m", "polins", "sun", "--time", "2023-09-05T07:06Z", "--lat", "45",
            "--lon", "126", "--json"]  # fmt: skip
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the reader went away before polins wrote anything
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141 and err == ""


def test_help_shows_every_default_and_the_filter_options(capsys, monkeypatch):
    """Found: ``--help`` did not show the defaults of ``--imu`` and ``--camera``."""
    monkeypatch.setenv("COLUMNS", "300")  # no line breaks inside the names
    for command, expected in (("simulate", ["(default: fins-paper)", "(default: 8)"]),
                              ("heading", ["(default: paper-table1)"]),
                              ("fuse", ["(default: 0.5)", "nhc_std = auto", "--set KEY=VALUE",
                                        "scale_factors = auto", "smooth = False [eskf only]",
                                        "--nhc SIGMA|off|auto", "default auto: on (0.05 m/s) "
                                        "for a ground vehicle"])):  # fmt: skip
        assert main([command, "--help"]) == 0
        out = " ".join(capsys.readouterr().out.split())
        for text in expected:
            assert text in out, (command, text)
        # a required argument or one without a value by default shows no "default: None"
        assert "(default: None)" not in out, command
    assert "None:" not in out  # fuse's help says what happens without an option


def test_list_options(capsys):
    from polins.fusion.config import option_names

    assert main(["fuse", "--list-options"]) == 0
    out = capsys.readouterr().out
    assert all(f"  {n} = " in out for n in option_names() if n not in ("imu_model", "site"))


def test_a_bug_is_a_traceback_and_exit_1(monkeypatch):
    import polins.cli.sun

    def bug(args):
        return {}["no such key"]  # a KeyError inside polins is a bug, not a user mistake

    monkeypatch.setattr(polins.cli.sun, "cmd_sun", bug)
    with pytest.raises(KeyError):
        main(["sun", "--time", "2023-09-05T07:06Z", "--lat", "45", "--lon", "126"])
    code = (
        "import sys, polins.cli as c, polins.cli.sun as s\n"
        "s.cmd_sun = lambda args: [][1]\n"
        "sys.exit(c.main(['sun', '--time', '2023-09-05T07:06Z', '--lat', '45', '--lon', '1']))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 1 and "Traceback" in out.stderr and "IndexError" in out.stderr


def test_debug_shows_the_traceback_of_a_user_mistake():
    from polins.errors import UserInputError

    with pytest.raises(UserInputError, match="naive datetime"):
        main(["--debug", "sun", "--time", "2023-09-05T15:06", "--lat", "45.6", "--lon", "126.7"])
