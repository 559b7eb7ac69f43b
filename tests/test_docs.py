"""Every code block of README.md and docs/*.md that is meant to run, run as written.

A page's ``python`` blocks share one namespace, and its ``bash``/``sh`` blocks one working
folder, in the order of the page; python blocks run as ``__main__``. A ``bash`` block runs line
by line: ``polins ...`` through :func:`polins.cli.main` (exit status 0 expected), ``python ...``
in a subprocess; no shell runs them, so a line with a shell operator (``;``, ``&&``, ``|``,
``>``, ...) fails. ``text`` and ``toml`` blocks are data, not run; a block without a language
fails. Fences follow CommonMark (backticks or tildes, the first word of the info string is the
language). An HTML comment right before a block tells this module how to run it, visibly in
the page's source:

``<!-- doctest: fixture log -->``
    before the block, copy the fixture files into the working folder and (python) define the
    fixture names: a 4 s simulated UGV log at 1/8 resolution (:func:`docs_log`).
``<!-- doctest: fixture camera -->``
    a camera file and clear-sky images to calibrate, check and measure with
    (:func:`docs_camera`).
``<!-- doctest: fixture broad -->``
    link ``tests/data/broad`` (the BROAD trials) into the working folder.
``<!-- doctest: replace `OLD` `NEW` -->``
    run the block with ``OLD`` replaced by ``NEW`` (a long flow shortened, a full-resolution
    camera downscaled); ``OLD`` must occur in the block.
``<!-- doctest: skip REASON -->``
    the block cannot run here; the reason says why.

A failing block fails its page's test with the page and line; a traceback of a python block
points into the Markdown file itself.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RUN_LANGUAGES = {"python", "bash", "sh"}
DATA_LANGUAGES = {"text", "toml"}
SHELL_OPERATOR_CHARS = "();<>|&"

# CommonMark fences: 3+ backticks or tildes; a backtick fence's info string has no backtick
FENCE_OPEN = re.compile(r"^(?P<indent> *)(?P<fence>`{3,}(?=[^`]*$)|~{3,})(?P<info>.*)$")
FENCE_LIKE = re.compile(r"^ *(`{3,}|~{3,})")
DIRECTIVE = re.compile(r"^\s*<!--\s*doctest:\s*(?P<body>.*?)\s*-->\s*$")
SKIP = re.compile(r"^skip\b\s*(?P<reason>.*)$")
REPLACE = re.compile(r"^replace\s+`(?P<old>[^`]+)`\s+`(?P<new>[^`]*)`$")


@dataclass
class Block:
    """One fenced code block of a page and the doctest directives written before it."""

    page: Path
    line: int  # 1-based line of the first code line
    lang: str
    code: str
    skip: str | None = None
    fixtures: list[str] = field(default_factory=list)
    replace: list[tuple[str, str]] = field(default_factory=list)

    @property
    def where(self) -> str:
        return f"{_shown(self.page)}:{self.line}"

    def source(self) -> str:
        code = self.code
        for old, new in self.replace:
            if old not in code:
                raise AssertionError(f"{self.where}: doctest replace `{old}` not in the block")
            code = code.replace(old, new)
        return code


def _shown(page: Path) -> str:
    return str(page.relative_to(ROOT)) if page.is_relative_to(ROOT) else str(page)


def _directive(block: Block, body: str, where: str) -> None:
    if match := SKIP.match(body):
        block.skip = match["reason"]
        assert block.skip, f"{where}: doctest skip needs a reason"
    elif body.startswith("fixture "):
        block.fixtures += body.split()[1:]
    elif match := REPLACE.match(body):
        block.replace.append((match["old"], match["new"]))
    else:
        raise AssertionError(f"{where}: unknown doctest directive {body!r}")


def _closing(lines: list[str], i: int, fence: str, where: str) -> int:
    """The index of the line that closes the block opened by ``fence`` at line ``i``."""
    close = re.compile(rf"^ *{fence[0]}{{{len(fence)},}}\s*$")
    for end in range(i + 1, len(lines)):
        if close.match(lines[end]):
            return end
        like = FENCE_LIKE.match(lines[end])
        if like and like[1][0] == fence[0] and len(like[1]) >= len(fence):
            raise AssertionError(f"{where}:{end + 1}: text after a closing fence")
    raise AssertionError(f"{where}:{i + 1}: unclosed code block")


def parse_blocks(page: Path) -> list[Block]:
    """The fenced blocks of ``page`` with the directives in the comment lines before each.

    Fences follow CommonMark (three or more backticks or tildes, then an info string whose
    first word is the language); a line that starts like a fence but is none fails.
    """
    lines = page.read_text(encoding="utf-8").splitlines()
    blocks: list[Block] = []
    pending: list[tuple[str, int]] = []
    i = 0
    while i < len(lines):
        if match := DIRECTIVE.match(lines[i]):
            pending.append((match["body"], i + 1))
        elif match := FENCE_OPEN.match(lines[i]):
            end = _closing(lines, i, match["fence"], _shown(page))
            indent = len(match["indent"])
            code = "\n".join(_dedent(line, indent) for line in lines[i + 1 : end])
            lang = (match["info"].split() or [""])[0]
            block = Block(page, i + 2, lang, code)
            for body, at in pending:
                _directive(block, body, f"{_shown(page)}:{at}")
            blocks.append(block)
            pending, i = [], end
        elif FENCE_LIKE.match(lines[i]):
            raise AssertionError(f"{_shown(page)}:{i + 1}: not a code fence: {lines[i].strip()!r}")
        elif lines[i].strip():
            assert not pending, (
                f"{page.name}:{pending[0][1]}: a doctest directive not before a block"
            )
        i += 1
    assert not pending, f"{page.name}: a doctest directive after the last block"
    return blocks


def _dedent(line: str, indent: int) -> str:
    """``line`` without up to ``indent`` leading spaces (the fence's indentation)."""
    return line[min(indent, len(line) - len(line.lstrip(" "))) :]


# ------------------------------------------------------------------------------ the fixture
@pytest.fixture(scope="session")
def docs_log(tmp_path_factory) -> tuple[Path, dict[str, Any]]:
    """The files and names of ``<!-- doctest: fixture log -->``.

    Files: ``drive/`` (``polins simulate --scenario ugv --imu mems-typical``, 4 s, images at
    2 Hz and 1/8 resolution), ``static.csv`` (60 s of a MEMS IMU at rest, 100 Hz),
    ``my-camera.toml`` (the log's camera, ``paper-table1`` at 1/8), ``my-imu.toml``
    (``mems-typical``), ``sky.png`` (one raw image of the log).
    Names: ``imu`` (the log's IMU table), ``measurements`` (``measurements.csv`` of
    ``polins fuse`` on the log), ``raw``, ``t_img``, ``t_utc``, ``lat_deg``, ``lon_deg``,
    ``alt_m``, ``rot_nb``, ``rot_nb_prior`` (an image, its log time, UTC time, site and
    true attitude), ``t``, ``gyro_b``, ``accel_b`` (the first IMU sample), ``dark_frames``,
    ``flat_frames`` (4 each for ``paper-table1`` at 1/8).
    """
    from polins.cli import main
    from polins.io import load_raw, read_log, write_imu
    from polins.models import shipped_folder
    from polins.sim.imu import imu_errors

    folder = tmp_path_factory.mktemp("docs-fixture")
    drive = folder / "drive"
    argv = ["simulate", "--scenario", "ugv", "--imu", "mems-typical", "--duration", "4"]
    assert main([*argv, "--image-rate", "2", "--out", str(drive), "--quiet"]) == 0
    run = tmp_path_factory.mktemp("docs-fixture-run")
    assert main(["fuse", str(drive), "--out", str(run), "--workers", "1", "--quiet"]) == 0
    log = read_log(drive / "manifest.toml")

    n = 6000  # 60 s at 100 Hz, at rest and level
    still = np.zeros((n, 7))
    still[:, 0], still[:, 6] = np.arange(n) / 100.0, 9.80665
    ideal = pd.DataFrame(still, columns=["t", "gx", "gy", "gz", "ax", "ay", "az"])
    static, _ = imu_errors(ideal, log.imu_model, np.random.default_rng(0))
    write_imu(folder / "static.csv", static)
    shutil.copy(drive / "camera.toml", folder / "my-camera.toml")
    shutil.copy(shipped_folder("imus") / "mems-typical.toml", folder / "my-imu.toml")

    t_img, item = list(log.images)[len(log.images.t) // 2]
    raw = load_raw(item)
    shutil.copy(item, folder / "sky.png")
    truth = log.truth.set_index("t")
    row = truth.iloc[int(np.argmin(np.abs(truth.index.to_numpy() - t_img)))]
    rot_nb = Rotation.from_euler("ZYX", [row["yaw"], row["pitch"], row["roll"]])

    cam = log.camera
    rng = np.random.default_rng(1)
    dark = np.empty(cam.shape)
    gain = np.empty(cam.shape)
    for r in range(2):
        for c in range(2):
            dark[r::2, c::2] = cam.dark_offset_dn[cam.channel_at[r, c]] + 20.0
            gain[r::2, c::2] = 1.0 + 0.02 * (2 * r + c - 1.5)
    noise = 1.5 * rng.standard_normal((4, *cam.shape))
    level = np.array([800.0, 1200.0, 1600.0, 2000.0])[:, None, None]
    names = {
        "imu": log.imu,
        "measurements": pd.read_csv(run / "measurements.csv"),
        "raw": raw,
        "t_img": t_img,
        "t_utc": log.times_utc(np.array([t_img]))[0],
        "lat_deg": log.lat_deg,
        "lon_deg": log.lon_deg,
        "alt_m": log.alt_m,
        "rot_nb": rot_nb,
        "rot_nb_prior": rot_nb,
        "t": float(log.imu["t"].iloc[0]),
        "gyro_b": log.imu[["gx", "gy", "gz"]].to_numpy()[0],
        "accel_b": log.imu[["ax", "ay", "az"]].to_numpy()[0],
        "dark_frames": np.rint(dark + noise).astype(np.uint16),
        "flat_frames": np.rint(dark + level * gain + 3.0 * noise).astype(np.uint16),
    }
    return folder, names


@pytest.fixture(scope="session")
def docs_camera(tmp_path_factory) -> tuple[Path, dict[str, Any]]:
    """The files of ``<!-- doctest: fixture camera -->``: ``mycam.toml`` (``paper-table1`` at
    1/8), ``sky/`` (12 clear-sky images over a full turn about the vertical, with the IFOV
    error), ``sky-test/`` (4 more) and ``sky.png`` (one more), all of the sun at Berlin
    (52.5, 13.3) on 2026-06-01T10:15+02:00; ``flats/`` (3 frames of uniform unpolarized
    light)."""
    import polins
    from polins.io import write_image
    from polins.io.model_files import camera_model_toml

    folder = tmp_path_factory.mktemp("docs-camera")
    cam = polins.load_camera("paper-table1").downscaled(8)
    (folder / "mycam.toml").write_text(camera_model_toml(cam))
    sun = polins.sun_position("2026-06-01T10:15+02:00", 52.5, 13.3)
    sun_n = polins.sun_vector_n(sun.azimuth, sun.zenith)
    rng = np.random.default_rng(2)
    for name, n in (("sky", 12), ("sky-test", 4)):
        (folder / name).mkdir()
        for i, turn_deg in enumerate(np.arange(n) * 360.0 / n + 10.0 * len(name)):
            rot_nb = Rotation.from_euler("z", turn_deg, degrees=True)
            raw = polins.sim.render_raw(cam, sun_n, rot_nb, rng=rng, ifov=True)
            write_image(folder / name / f"{i:03d}.png", raw)
    rot_nb = Rotation.from_euler("z", 40.0, degrees=True)
    write_image(folder / "sky.png", polins.sim.render_raw(cam, sun_n, rot_nb, rng=rng, ifov=True))
    (folder / "flats").mkdir()
    for i in range(3):  # uniform unpolarized light
        raw = polins.sim.render_raw(
            cam, sun_n, rot_nb, dop_max=0.0, epsilon=0.0, radiance=1500.0, rng=rng
        )
        write_image(folder / "flats" / f"{i:03d}.png", raw)
    return folder, {}


def _install_fixture(name: str, cwd: Path, namespace: dict[str, Any], request) -> None:
    if name == "broad":  # the BROAD trials at the path the page gives, tests/data/broad
        (cwd / "tests" / "data").mkdir(parents=True, exist_ok=True)
        (cwd / "tests" / "data" / "broad").symlink_to(ROOT / "tests" / "data" / "broad")
        return
    assert name in ("log", "camera"), f"unknown doctest fixture {name!r}"
    folder, names = request.getfixturevalue(f"docs_{name}")
    for path in folder.iterdir():
        target = cwd / path.name
        if path.is_dir():
            shutil.copytree(path, target, dirs_exist_ok=True)
        else:
            shutil.copy(path, target)
    namespace.update(names)


# ------------------------------------------------------------------------------ running
def _commands(code: str) -> list[tuple[int, str]]:
    """The shell commands of a block with the offset of their first line, continuation
    lines joined."""
    commands: list[tuple[int, str]] = []
    start, parts = 0, []
    for k, line in enumerate(code.splitlines()):
        parts.append(line.removesuffix("\\"))
        if not line.endswith("\\"):
            if "".join(parts).strip():
                commands.append((start, " ".join(parts)))
            start, parts = k + 1, []
    return commands


def _shell_operators(line: str) -> list[str]:
    """The shell operators (``;``, ``&&``, ``|``, ``>``, ``2>&1``, ...) outside quotes in
    ``line``."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    return [token for token in lexer if token and set(token) <= set(SHELL_OPERATOR_CHARS)]


def _run_shell(block: Block, code: str) -> None:
    from polins.cli import main

    for offset, line in _commands(code):
        argv = shlex.split(line, comments=True)
        where = f"{_shown(block.page)}:{block.line + offset}"
        if not argv:
            continue
        if operators := _shell_operators(line):
            raise AssertionError(
                f"{where}: shell operator {operators[0]!r} is not run by this harness: "
                "one command a line, or mark the block doctest skip with a reason"
            )
        if argv[0] == "polins":
            status = main(argv[1:])
        elif argv[0] == "python":
            status = subprocess.run([sys.executable, *argv[1:]], check=False).returncode
        else:
            raise AssertionError(f"{where}: cannot run {argv[0]!r}: mark the block doctest skip")
        assert status == 0, f"{where}: `{line.strip()}` exited {status}"


def _run_python(block: Block, code: str, namespace: dict[str, Any]) -> None:
    # leading newlines put the block's lines at their line numbers in the page: a traceback
    # names the Markdown file and shows the failing line of the snippet
    compiled = compile("\n" * (block.line - 1) + code, str(block.page), "exec")
    exec(compiled, namespace)


def run_page(page: Path, cwd: Path, request) -> list[Block]:
    """Run the page's runnable blocks in order in ``cwd``; return the blocks that ran."""
    namespace: dict[str, Any] = {"__name__": "__main__"}
    ran = []
    for block in parse_blocks(page):
        if block.lang not in RUN_LANGUAGES or block.skip:
            continue
        for name in block.fixtures:
            _install_fixture(name, cwd, namespace, request)
        try:
            code = block.source()
            if block.lang == "python":
                _run_python(block, code, namespace)
            else:
                _run_shell(block, code)
        except Exception as exc:
            pytest.fail(
                f"{block.where}: the {block.lang} block fails: {exc!r}\n{traceback.format_exc()}",
                pytrace=False,
            )
        ran.append(block)
    return ran


def inventory() -> dict[str, dict[str, int]]:
    """Per page: blocks run, marked skip, and data blocks."""
    counts = {}
    for page in PAGES:
        blocks = parse_blocks(page)
        run = [b for b in blocks if b.lang in RUN_LANGUAGES]
        counts[str(page.relative_to(ROOT))] = {
            "run": sum(not b.skip for b in run),
            "skip": sum(bool(b.skip) for b in run),
            "data": len(blocks) - len(run),
        }
    return counts


# ------------------------------------------------------------------------------ the tests
RUNNABLE = [p for p in PAGES if any(b.lang in RUN_LANGUAGES for b in parse_blocks(p))]


@pytest.mark.parametrize("page", RUNNABLE, ids=lambda p: str(p.relative_to(ROOT)))
def test_page_blocks_run(page, tmp_path, monkeypatch, request):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    ran = run_page(page, tmp_path, request)
    assert ran or all(b.skip for b in parse_blocks(page) if b.lang in RUN_LANGUAGES)


def check_block(block: Block) -> None:
    """A block's language says whether it runs; data blocks carry no doctest directive."""
    assert block.lang in RUN_LANGUAGES | DATA_LANGUAGES, (
        f"{block.where}: code block language {block.lang!r}: tag it with one of "
        f"{sorted(RUN_LANGUAGES | DATA_LANGUAGES)}"
    )
    if block.lang in DATA_LANGUAGES:
        assert not (block.skip or block.fixtures or block.replace), (
            f"{block.where}: a doctest directive on a block that does not run"
        )


def test_every_block_is_run_data_or_marked():
    """A block's language says whether it runs; an unknown or missing one is a mistake to fix."""
    for page in PAGES:
        for block in parse_blocks(page):
            check_block(block)
    totals = pd.DataFrame(inventory()).T.sum()
    assert totals["run"] >= 10


def test_fences_follow_commonmark(tmp_path):
    """Info strings, tildes and longer fences open blocks; a malformed fence fails the page."""
    page = tmp_path / "page.md"
    page.write_text(
        '```python title="a"\nx = 1\n```\n\nprose\n\n~~~python\ny = 2\n~~~\n\n'
        "````markdown\n```python\nnot run\n```\n````\n\n  ```bash\n  polins sun\n  ```\n"
    )
    blocks = parse_blocks(page)
    assert [(b.line, b.lang, b.code) for b in blocks] == [
        (2, "python", "x = 1"),
        (8, "python", "y = 2"),
        (12, "markdown", "```python\nnot run\n```"),
        (18, "bash", "polins sun"),
    ]
    with pytest.raises(AssertionError, match="'markdown'"):
        check_block(blocks[2])
    bad = {
        "```text\nx\n``` and prose\n": "page.md:3: text after a closing fence",
        "``` prose `code`\n": "page.md:1: not a code fence",
        "~~~python\nx = 1\n```\n": "page.md:1: unclosed code block",
    }
    for text, message in bad.items():
        page.write_text(text)
        with pytest.raises(AssertionError, match=message):
            parse_blocks(page)
    page.write_text("```\npolins sun\n```\n")
    with pytest.raises(AssertionError, match="language '': tag it"):
        check_block(parse_blocks(page)[0])
    page.write_text("<!-- doctest: skipping -->\n```bash\npolins sun\n```\n")
    with pytest.raises(AssertionError, match="unknown doctest directive 'skipping'"):
        parse_blocks(page)


def test_shell_operators_fail_and_python_runs_as_main(tmp_path):
    page = tmp_path / "page.md"
    quoted = "python -c \"import sys; sys.exit(0 if sys.argv[1] == 'a|b' else 1)\" 'a|b'"
    _run_shell(Block(page, 1, "bash", quoted), quoted)  # operators inside quotes are text
    for line in [
        'python -c "pass" ; python -c "import sys; sys.exit(3)"',
        "polins sun && polins nope",
        "polins sun || true",
        "polins sun | head",
        "polins sun > out.txt",
        "polins sun >> out.txt",
        "polins sun < in.txt",
        "polins sun 2>&1",
        "polins sun&",
    ]:
        with pytest.raises(AssertionError, match=r"page.md:1: shell operator .* doctest skip"):
            _run_shell(Block(page, 1, "bash", line), line)
    page.write_text('```python\nassert __name__ == "__main__"\n```\n')
    assert len(run_page(page, tmp_path, None)) == 1


def test_the_harness_reports_page_and_line(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        "# t\n\n<!-- doctest: replace `1 / 1` `1 / 0` -->\n```python\nx = 1\ny = 1 / 1\n```\n\n"
        "<!-- doctest: skip needs a camera -->\n```bash\npolins heading x.png\n```\n"
    )
    blocks = parse_blocks(page)
    assert [(b.line, b.lang, b.skip) for b in blocks] == [
        (5, "python", None),
        (11, "bash", "needs a camera"),
    ]
    namespace: dict[str, Any] = {}
    with pytest.raises(ZeroDivisionError) as info:
        _run_python(blocks[0], blocks[0].source(), namespace)
    frame = info.traceback[-1]
    assert Path(frame.path) == page and frame.lineno + 1 == 6  # the page's line 6
    with pytest.raises(AssertionError, match="not in the block"):
        Block(page, 1, "python", "x = 2", replace=[("y", "z")]).source()
    code = "# a comment\npolins sun --time 2023-09-05T07:06Z \\\n    --lat 45 --lon 126\n\npolins nope\n"
    assert _commands(code) == [
        (0, "# a comment"),
        (1, "polins sun --time 2023-09-05T07:06Z      --lat 45 --lon 126"),
        (4, "polins nope"),
    ]
    with pytest.raises(AssertionError, match=r"page.md:15: `polins nope` exited 2"):
        _run_shell(Block(page, 11, "bash", code), code)


if __name__ == "__main__":  # print the inventory: python tests/test_docs.py
    table = pd.DataFrame(inventory()).T
    print(table.to_string())
    print("total", dict(table.sum()))


def test_the_index_lists_the_pages_of_the_navigation():
    """docs/index.md's page table and mkdocs.yml's nav name the same pages in the same order."""
    nav = re.findall(r"^  - [^:]+: (\S+\.md)$", (ROOT / "mkdocs.yml").read_text(), re.M)
    table = re.findall(
        r"^\| \[[^\]]+\]\(([\w-]+\.md)\) \|", (ROOT / "docs" / "index.md").read_text(), re.M
    )
    assert nav[0] == "index.md"
    assert table == nav[1:]
    assert sorted(nav) == sorted(p.name for p in (ROOT / "docs").glob("*.md"))


def test_toml_blocks_parse():
    """A documented manifest or model file is valid TOML."""
    import tomllib

    for page in PAGES:
        for block in parse_blocks(page):
            if block.lang == "toml":
                try:
                    tomllib.loads(block.code)
                except tomllib.TOMLDecodeError as exc:
                    pytest.fail(f"{block.where}: not valid TOML: {exc}", pytrace=False)
