"""Every command the user docs show runs: each fenced ``bash``/``python`` block of README.md, docs/*.md and
deploy/k8s/README.md runs in order, as written, in a work folder holding a small scene and two robots' bags that the
test makes itself, against real processes; a block that cannot run here says why in its page
(``<!-- not run: REASON -->``; :mod:`tests.docs.blocks`)."""

from __future__ import annotations

import contextlib
import fcntl
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from tests.docs.blocks import PAGES, Block, PageRunner, blocks_of, runnable, section

#: the bag names the pages use for "your robot's recording" (made from the synthetic scene by the fixture)
BAGS = {"rosbag2_2026_11_22-10_00_00": "agent_a", "data/robot1_bag": "agent_a", "data/robot2_bag": "agent_b"}
#: the shortest reason a page may give for a block it does not run
MIN_REASON = 20


def test_the_extractor_reads_fences_markers_and_sections():
    text = ("# T\n## Run it\n```bash\necho 1\n```\n<!-- not run: needs a GPU that this machine lacks -->\n"
            "```python\nx = 1\n```\n## Next step\n<!-- after: README.md#run-it -->\n```python\ny = 2\n```\n"
            "```text\nusage\n```\n")
    bs = blocks_of("X.md", text)
    assert [(b.anchor, b.lang, b.code, b.skip, b.after) for b in bs] == [
        ("run-it", "bash", "echo 1", None, []),
        ("run-it", "python", "x = 1", "needs a GPU that this machine lacks", []),
        ("next-step", "python", "y = 2", None, ["README.md#run-it"]),
        ("next-step", "text", "usage", None, [])]
    with pytest.raises(ValueError, match="unclosed"):
        blocks_of("X.md", "```bash\necho\n")
    with pytest.raises(ValueError, match="right before a fence"):
        blocks_of("X.md", "<!-- not run: because it cannot here -->\nsome prose\n```bash\necho\n```\n")


def test_every_block_runs_or_says_why_and_every_link_to_a_block_resolves():
    counts = {"run": 0, "marked": 0}
    for page in PAGES:
        for b in runnable(page):
            if b.skip is not None:
                assert len(b.skip) >= MIN_REASON, f"{b.name}: say why it is not run ({b.skip!r})"
                counts["marked"] += 1
            else:
                counts["run"] += 1
            for ref in b.after:
                assert section(ref), ref
    # most of what a user types runs
    assert counts["run"] >= counts["marked"], counts


def test_the_runner_keeps_services_for_the_next_block_and_stops_them(tmp_path):
    r = PageRunner(tmp_path, timeout_s=60)
    try:
        r.run(Block("X.md", "a", "bash", f"{sys.executable} -m http.server 0 --bind 127.0.0.1 > port.txt 2>&1 &\n"
                                         "sleep 0.5; echo started", 1))
        r.run(Block("X.md", "a", "python", "import pathlib; seen = pathlib.Path('port.txt').exists()", 2))
        assert r.namespaces["X.md"]["seen"] and "started" in r.output()
        with pytest.raises(AssertionError, match="exit 3"):
            r.run(Block("X.md", "a", "bash", "exit 3", 3))
    finally:
        r.close()
    pgid = r.groups[0]
    with pytest.raises(ProcessLookupError):
        import os
        os.killpg(pgid, 0)


def test_a_section_that_ran_in_the_folder_and_left_nothing_running_is_not_run_again(tmp_path, monkeypatch):
    import tests.docs.blocks as blocks

    files = Block("A.md", "files", "bash", "echo x >> made.txt", 1)
    service = Block("A.md", "service", "bash", "sleep 60 &", 2)
    sections = {"A.md#files": [files], "A.md#service": [service]}
    monkeypatch.setattr(blocks, "section", lambda ref: sections.get(ref, []))
    ran: set = set()
    first = PageRunner(tmp_path, timeout_s=60, ran=ran)
    try:
        first.run(files)
        first.run(service)
    finally:
        first.close()
    assert ran == {"A.md#files"}  # the service's section left a process running: a page after it runs it again
    second = PageRunner(tmp_path, timeout_s=60, ran=ran)
    try:
        second.run(Block("B.md", "b", "bash", "cat made.txt", 1, after=["A.md#files"]))
    finally:
        second.close()
    assert (tmp_path / "made.txt").read_text() == "x\n"  # the files' section ran once in the folder
    assert len(second.groups) == 1 and "x" in second.output()


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """A user's folder: the synthetic scene (two robots' frames, ``objects.json``, ``tasks.json``) and each robot's
    recording as a ROS 2 bag under the names the pages use."""
    ws = tmp_path_factory.mktemp("user")
    scene = ws / "data" / "scene"
    venv = PageRunner(ws).env
    run = dict(cwd=ws, env=venv, check=True, capture_output=True, timeout=300)
    subprocess.run(["gausslite", "make-scene", "--out", str(scene), "--frames", "3", "--width", "128",
                    "--height", "96", "--quiet"], **run)
    for name, agent in BAGS.items():
        subprocess.run(["gausslite", "export", "bag", "--dataset", str(scene / agent), "--out", str(ws / name)],
                       **run)
    return ws


#: pages whose blocks a test of their own runs, in the environment the page describes (a fusion server's address and
#: a robot's token in the environment)
OWN_RUNNER = {"docs/robot-integration.md": "tests/services/test_robot_integration_doc.py",
              "docs/team.md": "tests/services/test_team_doc.py"}


def test_pages_with_a_runner_of_their_own_have_it():
    from tests.docs.blocks import REPO
    for page, runner in OWN_RUNNER.items():
        assert runnable(page) and (REPO / runner).is_file() and page in (REPO / runner).read_text(encoding="utf-8")


#: per work folder, the sections whose blocks ran there and left nothing running (:attr:`PageRunner.ran`): README's
#: Python API, which docs/mapper.md and docs/fusion-and-deploy.md run after, runs once a folder
RAN: dict = {}
#: held while a page that serves on the pages' fixed ports runs, so that one such page at a time runs on this machine,
#: whichever pytest worker or run it is in (the ports are the machine's); the other pages run side by side
PORTS_LOCK = Path(tempfile.gettempdir()) / "gausslite-doc-pages-ports.lock"
#: a command that serves on a port the page gives
_SERVES = re.compile(r"gausslite (serve|view)\b|--port\b")


def serves_on_fixed_ports(page: str) -> bool:
    """Whether a block the page runs, or a block of a section it runs first, starts a service on a port."""
    run = [b for b in runnable(page) if b.skip is None]
    codes = [b.code for b in run] + [d.code for b in run for ref in b.after for d in section(ref)]
    return any(_SERVES.search(code) for code in codes)


def test_the_pages_that_serve_on_fixed_ports_are_found():
    serving = {p for p in PAGES if serves_on_fixed_ports(p)}
    assert {"README.md", "docs/live.md", "docs/fusion-and-deploy.md"} <= serving
    assert not {"docs/ros.md", "docs/mapper.md"} & serving


@pytest.mark.integration
@pytest.mark.parametrize("page", [p for p in PAGES if p not in OWN_RUNNER and any(b.skip is None for b in runnable(p))])
def test_the_page_runs_as_written(page, workdir):
    with contextlib.ExitStack() as stack:
        if serves_on_fixed_ports(page):
            fcntl.flock(stack.enter_context(open(PORTS_LOCK, "w")), fcntl.LOCK_EX)  # released when the file closes
        runner = PageRunner(workdir, timeout_s=900, ran=RAN.setdefault(str(workdir), set()))
        stack.callback(runner.close)
        for block in runnable(page):
            if block.skip is None:
                runner.run(block)
