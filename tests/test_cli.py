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
