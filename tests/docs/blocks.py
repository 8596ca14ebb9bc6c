"""The fenced ``bash`` and ``python`` blocks of the user docs (README.md, docs/*.md, deploy/k8s/README.md), and a
runner that executes them in order, as written, against real processes.

Markers, an HTML comment on the line right before a fence (invisible on a rendered page):

- ``<!-- not run: REASON -->``: the block is not run by the tests; REASON says why (a ROS 2 install, a Docker engine,
  a benchmark of an hour) and, where one exists, which test runs the same command on a smaller input.
- ``<!-- after: PAGE#ANCHOR -->``: before this block, the blocks of that section run first (the services the
  README starts, say), so that a page can link to a block instead of copying it; a section of another page that
  already ran in the same work folder and left nothing running (files it wrote, a map) is not run again.
- ``<!-- serves: URL -->``: the block serves until stopped (a viewer): it passes once URL answers HTTP 200, and is
  then stopped.
- ``<!-- writes: PATH -->``: the block (JSON, YAML, any language) is a file the user writes: the runner writes it to
  PATH in the work folder.

A page's ``bash`` blocks run with ``bash -euo pipefail`` in a work folder, in a process group of their own (services a
block starts in the background keep running for the blocks after it, and are stopped when the page is done); its
``python`` blocks run in one namespace per page, in the same folder.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

REPO = Path(__file__).resolve().parents[2]
#: the pages whose commands users run
PAGES = ["README.md", *sorted(p.relative_to(REPO).as_posix() for p in (REPO / "docs").glob("*.md")),
         "deploy/k8s/README.md"]
RUN_LANGS = ("bash", "python")
_FENCE = re.compile(r"^```(\w*)\s*$")
_MARK = re.compile(r"^<!--\s*(not run|after|serves|writes):\s*(.*?)\s*-->\s*$")


@dataclass
class Block:
    """One fenced block: its page, the ``#``-heading it sits under (as a GitHub anchor), its language and code,
    the line its fence opens on, and its markers (``skip``: the not-run reason; ``after``: ``PAGE#ANCHOR``)."""

    page: str
    anchor: str
    lang: str
    code: str
    line: int
    skip: Optional[str] = None
    after: List[str] = field(default_factory=list)
    serves: Optional[str] = None
    writes: Optional[str] = None

    @property
    def name(self) -> str:
        """``PAGE:LINE`` (for messages)."""
        return f"{self.page}:{self.line}"


def anchor_of(heading: str) -> str:
    """The GitHub anchor of a heading's text: lower case, punctuation dropped, spaces to hyphens."""
    h = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return h.replace(" ", "-")


def blocks_of(page: str, text: Optional[str] = None) -> List[Block]:
    """Every fenced block of ``page`` (a path relative to the repository) with a language, in order.

    Raises:
        ValueError: an unclosed fence, or a marker that is not followed by a fence.
    """
    text = (REPO / page).read_text(encoding="utf-8") if text is None else text
    out: List[Block] = []
    anchor, block, lang, start = "", None, "", 0
    pending: Dict[str, list] = {"not run": [], "after": [], "serves": [], "writes": []}
    for i, line in enumerate(text.splitlines(), 1):
        fence = _FENCE.match(line)
        if block is None and fence:
            block, lang, start = [], fence.group(1), i
            continue
        if block is not None:
            if line.startswith("```"):
                skip = pending["not run"][0] if pending["not run"] else None
                serves = pending["serves"][0] if pending["serves"] else None
                writes = pending["writes"][0] if pending["writes"] else None
                out.append(Block(page, anchor, lang, "\n".join(block), start, skip, list(pending["after"]), serves,
                                 writes))
                pending = {"not run": [], "after": [], "serves": [], "writes": []}
                block = None
            else:
                block.append(line)
            continue
        mark = _MARK.match(line)
        if mark:
            pending[mark.group(1)].append(mark.group(2))
            continue
        if line.strip() and any(pending.values()):
            raise ValueError(f"{page}:{i}: a marker must sit right before a fence")
        if line.startswith("#"):
            anchor = anchor_of(line.lstrip("#"))
    if block is not None:
        raise ValueError(f"{page}:{start}: unclosed code fence")
    return out


def runnable(page: str) -> List[Block]:
    """The ``bash``/``python`` blocks of ``page``, and the blocks it has the user write to a file."""
    return [b for b in blocks_of(page) if b.lang in RUN_LANGS or b.writes]


def section(ref: str) -> List[Block]:
    """The runnable blocks of ``PAGE#ANCHOR``.

    Raises:
        ValueError: the section has no runnable block.
    """
    page, _, anchor = ref.partition("#")
    found = [b for b in runnable(page) if b.anchor == anchor]
    if not found:
        raise ValueError(f"{ref}: no bash/python block under that heading")
    return found


class PageRunner:
    """Runs blocks in a work folder; stops every process group a ``bash`` block left running on :meth:`close`."""

    def __init__(self, workdir: Path, env: Optional[dict] = None, timeout_s: float = 600.0,
                 ran: Optional[set] = None):
        self.workdir = Path(workdir)
        self.env = dict(os.environ if env is None else env)
        venv_bin = str(Path(sys.executable).parent)
        self.env["PATH"] = venv_bin + os.pathsep + self.env.get("PATH", "")
        # the machine's Warp kernel cache, as a user's own after a first run: with an empty cache the first map of each
        # work folder compiles the rasterizer's kernels inside its time budget, and the budget, estimated from that
        # first keyframe, then keeps gausslite map on a 3-frame bag busy for 90 s instead of 20
        cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
        self.env.setdefault("WARP_CACHE_PATH", str(cache / "warp"))
        self.env["HOME"] = str(self.workdir / "home")  # a page's ~/ stays in the work folder
        (self.workdir / "home").mkdir(parents=True, exist_ok=True)
        for var in [v for v in self.env if v.startswith("GAUSSLITE_") and v != "GAUSSLITE_SHARED"]:
            del self.env[var]  # the pages say what they set
        self.timeout_s = timeout_s
        self.namespaces: Dict[str, dict] = {}
        self.groups: List[int] = []
        self.done: set = set()
        #: the sections (``PAGE#ANCHOR``) whose every block ran in this work folder and left no process running, by
        #: this runner or, through a ``ran`` shared by the runners of one folder, an earlier one: another page that is
        #: to run after such a section finds its files there and does not run it again (a section that starts
        #: services does run again, and a page's own sections always run in its namespace)
        self.ran: set = set() if ran is None else ran
        self.left_running: set = set()
        self.logs: List[Path] = []
        #: (block name, seconds) of each block run, in order
        self.timings: List[tuple] = []

    def run(self, block: Block) -> None:
        """Run ``block`` (and first the sections it is to run after, once each).

        Raises:
            AssertionError: the block failed (a bash exit status other than 0, with its output; a Python exception).
        """
        for ref in block.after:
            if ref in self.ran and not ref.startswith(f"{block.page}#"):
                continue
            for dep in section(ref):
                self.run(dep)
        key = (block.page, block.line)
        if key in self.done:
            return
        self.done.add(key)
        groups = len(self.groups)
        t0 = time.monotonic()
        try:
            self._dispatch(block)
        finally:
            self.timings.append((block.name, time.monotonic() - t0))
        self._note_section(block, self.groups[groups:])

    def _note_section(self, block: Block, groups: List[int]) -> None:
        """Add ``block``'s section to :attr:`ran` once its every block ran, unless one of them (``block``: with the
        process groups it started) left a process running."""
        ref = f"{block.page}#{block.anchor}"
        if any(_group_alive(g) for g in groups):
            self.left_running.add(ref)
        if ref in self.left_running:
            return
        try:
            blocks = section(ref)
        except (OSError, ValueError):  # a block of no page (the runner's own tests)
            return
        if all((b.page, b.line) in self.done for b in blocks):
            self.ran.add(ref)

    def _dispatch(self, block: Block) -> None:
        if block.writes:
            path = self.workdir / block.writes
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(block.code + "\n", encoding="utf-8")
        elif block.serves:
            self._serve(block)
        elif block.lang == "bash":
            self._bash(block)
        else:
            self._python(block)

    def _bash(self, block: Block) -> None:
        log = self.workdir / f".block-{len(self.logs):02d}.log"
        self.logs.append(log)
        with open(log, "wb") as out:  # a file, not a pipe: services left in the background keep it open
            proc = subprocess.Popen(["bash", "-euo", "pipefail", "-c", block.code], cwd=self.workdir, env=self.env,
                                    stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
            self.groups.append(proc.pid)
            try:
                rc = proc.wait(timeout=self.timeout_s)
            except subprocess.TimeoutExpired:
                rc = None
        text = log.read_text(errors="replace")
        assert rc == 0, f"{block.name} ({'timed out' if rc is None else f'exit {rc}'}):\n{block.code}\n--- output:\n{text[-4000:]}"

    def _serve(self, block: Block) -> None:
        log = self.workdir / f".block-{len(self.logs):02d}.log"
        self.logs.append(log)
        with open(log, "wb") as out:
            proc = subprocess.Popen(["bash", "-euo", "pipefail", "-c", block.code], cwd=self.workdir, env=self.env,
                                    stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        deadline, ok = time.monotonic() + min(self.timeout_s, 120.0), False
        try:
            while time.monotonic() < deadline and proc.poll() is None and not ok:
                ok = _answers(block.serves)
                time.sleep(0.3)
        finally:
            _stop_group(proc.pid, proc)
            proc.wait(10)
        assert ok, f"{block.name}: {block.serves} never answered:\n{block.code}\n--- output:\n{log.read_text(errors='replace')[-4000:]}"

    def _python(self, block: Block) -> None:
        ns = self.namespaces.setdefault(block.page, {"__name__": f"doc:{block.page}"})
        cwd = os.getcwd()
        os.chdir(self.workdir)
        try:
            exec(compile(block.code, block.name, "exec"), ns)  # noqa: S102 - our own docs
        finally:
            os.chdir(cwd)

    def output(self) -> str:
        """Everything the ``bash`` blocks printed so far (services in the background included)."""
        return "".join(p.read_text(errors="replace") for p in self.logs if p.exists())

    def close(self) -> None:
        """SIGTERM, then SIGKILL after 10 s, to every process group the blocks started."""
        for sig, wait in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 0.0)):
            alive = []
            for pgid in self.groups:
                try:
                    os.killpg(pgid, sig)
                    alive.append(pgid)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait
            while alive and time.monotonic() < deadline:
                alive = [g for g in alive if _group_alive(g)]
                time.sleep(0.1)
            if not alive:
                break


def _answers(url: str) -> bool:
    """Whether ``url`` answers HTTP 200 within 2 s."""
    try:
        with urllib.request.urlopen(url, timeout=2) as r:
            return r.status == 200
    except OSError:
        return False


def _stop_group(pgid: int, leader: Optional[subprocess.Popen] = None) -> None:
    """SIGTERM the process group, SIGKILL what is left after 5 s. ``leader``: the group's first process, ours to reap:
    until it is waited for, it counts as a member of its group after it exited."""
    for sig, wait in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 0.0)):
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            if leader is not None:
                leader.poll()  # reaped once it exited
            if not _group_alive(pgid):
                break
            time.sleep(0.1)


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
