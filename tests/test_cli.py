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


def test_out_folder_that_is_a_file_is_a_user_mistake(tmp_path, capsys):
    (tmp_path / "run").write_text("")
    code = main(["fuse", str(tmp_path / "m.toml"), "--out", str(tmp_path / "run")])
    assert code == 2 and "is a file" in capsys.readouterr().err


def test_a_bug_is_a_traceback_and_exit_1(monkeypatch):
    import polins.cli

    def bug(args):
        return {}["no such key"]  # a KeyError inside polins is a bug, not a user mistake

    monkeypatch.setattr(polins.cli, "_cmd_sun", bug)
    with pytest.raises(KeyError):
        main(["sun", "--time", "2023-09-05T07:06Z", "--lat", "45", "--lon", "126"])
    code = (
        "import sys, polins.cli as c\n"
        "c._cmd_sun = lambda args: [][1]\n"
        "sys.exit(c.main(['sun', '--time', '2023-09-05T07:06Z', '--lat', '45', '--lon', '1']))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 1 and "Traceback" in out.stderr and "IndexError" in out.stderr


def test_debug_shows_the_traceback_of_a_user_mistake():
    from polins.errors import UserInputError

    with pytest.raises(UserInputError, match="naive datetime"):
        main(["--debug", "sun", "--time", "2023-09-05T15:06", "--lat", "45.6", "--lon", "126.7"])
