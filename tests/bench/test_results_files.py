"""``bench/results/``: every file is named by the index (``bench/results/README.md``) or by a doc, the index names only
files that exist, no file holds a path of the machine that measured it, and every JSON carries its provenance; and
``bench/_results.py`` writes both for every new result."""

from __future__ import annotations

import fnmatch
import json
import re
import subprocess
import tempfile
from datetime import datetime, timezone
from pathlib import Path
from typing import List, Set

from bench import _results
from tests.docs.test_doc_links import broken_links

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "bench" / "results"
INDEX = RESULTS / "README.md"
DOC_PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
#: an absolute path of a machine: a ``/`` that does not follow a word, ``.``, ``~``, ``:`` or ``/`` (so URLs, relative
#: paths and ``~/`` are not), then a top-level folder of a machine's tree (not a ROS topic such as ``/tf``)
MACHINE_PATH = re.compile(r"(?<![\w.~:/\-])/(?:home|root|tmp|work|Users|mnt|media|opt|srv|data|scratch|private|var|"
                          r"nfs|usr|etc)/")
STATUSES = ("current", "kept")


def machine_paths(text: str) -> List[str]:
    """The absolute paths of a machine in ``text`` (this checkout's and home folder's included)."""
    found = [text[m.start():m.start() + 60].split()[0] for m in MACHINE_PATH.finditer(text)]
    found += [str(p) for p in (REPO, Path.home()) if str(p) not in ("/", "") and str(p) + "/" in text]
    return found


def expand(token: str) -> List[str]:
    """``a.{json,md}`` → ``a.json``, ``a.md`` (every brace group, left to right)."""
    m = re.search(r"\{([^{}]*)\}", token)
    if not m:
        return [token]
    return [x for alt in m.group(1).split(",") for x in expand(token[:m.start()] + alt + token[m.end():])]


def result_files() -> Set[str]:
    """The files of ``bench/results/`` (relative to it) that git tracks or would add (ignored ones left out), the
    index itself excepted."""
    try:
        out = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "--", "bench/results"], cwd=REPO,
                             capture_output=True, text=True, check=True, timeout=30).stdout.split("\n")
        files = {Path(f).relative_to("bench/results").as_posix() for f in out if f and (REPO / f).is_file()}
    except (OSError, subprocess.SubprocessError):
        files = {p.relative_to(RESULTS).as_posix() for p in RESULTS.rglob("*") if p.is_file()}
    return files - {"README.md"}


def index_rows() -> List[List[str]]:
    """The cells of every row of the index's tables (header and rule rows left out)."""
    rows = []
    for line in INDEX.read_text(encoding="utf-8").splitlines():
        if line.startswith("| ") and not line.startswith(("| files ", "|---")):
            rows.append([c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]])
    return rows


def indexed() -> Set[str]:
    """The files the index's first column names."""
    return {name for row in index_rows() for tok in re.findall(r"`([^`\s]+)`", row[0]) for name in expand(tok)}


def cited_by_docs(files: Set[str]) -> Set[str]:
    """The files of ``files`` that README.md or a page of docs/ names as ``bench/results/...`` (brace groups and
    ``*`` patterns included)."""
    out: Set[str] = set()
    for page in DOC_PAGES:
        for tok in re.findall(r"bench/results/([^\s`)\],;]+)", page.read_text(encoding="utf-8")):
            for name in expand(tok.rstrip(".")):
                if "*" in name and len(name.split("*")[0].rsplit("/", 1)[-1]) < 3:
                    continue  # "bench/results/*.md" names no run
                out |= {f for f in files if fnmatch.fnmatch(f, name)} if "*" in name else {name} & files
    return out


def test_every_result_file_is_indexed_or_cited_by_a_doc():
    files = result_files()
    assert len(files) > 50, "results not found"
    unnamed = files - indexed() - cited_by_docs(files)
    assert not unnamed, ("files in bench/results/ that neither bench/results/README.md nor a doc names (add a line to "
                         "the index, or git rm a superseded run):\n" + "\n".join(sorted(unnamed)))


def test_the_index_names_only_files_that_exist_each_with_its_status_and_command():
    missing = indexed() - result_files()
    assert not missing, "bench/results/README.md names files that do not exist:\n" + "\n".join(sorted(missing))
    rows = index_rows()
    assert len(rows) > 30
    for row in rows:
        assert len(row) == 5, f"an index row needs files | question | command | status | cited in: {row}"
        assert row[3].startswith(STATUSES), f"status must start with {STATUSES}: {row}"
        assert row[2] and row[1], f"a row without its question or command: {row}"


def test_the_index_links_reach_the_sections_it_cites():
    assert not broken_links("bench/results/README.md")


def test_names_are_expanded_and_a_stray_file_is_not_taken_for_cited():
    assert expand("a_{x,y}.{json,md}") == ["a_x.json", "a_x.md", "a_y.json", "a_y.md"]
    files = result_files()
    assert "realtime.json" in indexed() and "realtime.json" in cited_by_docs(files)
    assert not cited_by_docs({"stray_run_1seed.json", "stray_run_1seed.md"}) and "stray_run_1seed.json" not in indexed()


def test_no_result_file_holds_a_machine_path():
    bad = {}
    for name in sorted(result_files()):
        if name.endswith((".json", ".md")):
            found = machine_paths((RESULTS / name).read_text(encoding="utf-8"))
            if found:
                bad[name] = found[:3]
    assert not bad, f"absolute paths in bench/results/ (store them relative to the repository): {bad}"


def _check_provenance(name: str, p) -> None:
    assert isinstance(p, dict), f"{name}: no provenance object"
    for key in ("command", "date", "commit", "machine"):
        assert p.get(key), f"{name}: provenance without {key!r}"
    assert p["commit"] == "unknown" or re.fullmatch(r"[0-9a-f]{40}", p["commit"]), f"{name}: commit {p['commit']!r}"
    if p["date"] != "unknown":
        assert datetime.fromisoformat(p["date"]).utcoffset() is not None, f"{name}: date without a time zone"


def test_every_result_json_carries_its_provenance():
    names = sorted(n for n in result_files() if n.endswith(".json"))
    assert names
    for name in names:
        doc = json.loads((RESULTS / name).read_text(encoding="utf-8"))
        rows = doc if isinstance(doc, list) else [doc]  # list-shaped files (ablate's rows) carry it per row
        for row in rows:
            _check_provenance(name, row.get("provenance"))


def test_the_path_check_finds_machine_paths_and_only_them():
    assert machine_paths("--work /tmp/x --out /work/main/bench/results/a.json")
    assert machine_paths('"dataset": "/home/me/data/TUM"') and machine_paths(f"x {REPO}/bench y")
    assert not machine_paths("/tf /camera/color/image_raw http://host/a/b DATA/x ~/.cache/x runs/x TMP/y a/tmp/b")


def test_written_results_carry_provenance_and_portable_paths(tmp_path):
    out = tmp_path / "r.json"
    home_file = Path.home() / ".cache" / "gausslite" / "m.onnx"
    result = {"map": str(REPO / "runs" / "m" / "map.ply"), "dataset": str(_results.DATASETS / "Replica_room0" / "room0"),
              "overrides": [f"agent.onnx.detector_path={home_file}"], "work": tempfile.gettempdir() + "/w/x",
              "topic": "/camera/color/image_raw"}
    _results.write_json(out, result, "vote", ["--quick", "--out", str(out)])
    text = out.read_text()
    assert not machine_paths(text), text
    doc = json.loads(text)
    assert doc["map"] == "runs/m/map.ply" and doc["dataset"] == "DATA/Replica_room0/room0"
    assert doc["work"] == "TMP/w/x" and doc["topic"] == "/camera/color/image_raw"
    p = doc["provenance"]
    _check_provenance("r.json", p)
    assert p["command"].startswith("python -m bench.vote --quick --out ") and str(tmp_path) not in p["command"]
    assert abs((datetime.now(timezone.utc) - datetime.fromisoformat(p["date"])).total_seconds()) < 120
    assert p["dirty"] in (True, False, "unknown") and set(p["machine"]) == {"cores", "cpu", "ram_gb", "os"}
    # a bench that wrote its JSON itself: write_results adds the provenance and heads the table with the command
    own = tmp_path / "own.json"
    own.write_text(json.dumps({"path": str(REPO / "bench" / "results" / "x.json")}))
    md = _results.write_results(own, "mapper", ["--seeds", "3"], ": 3 seeds", "| a |\n|---|")
    assert json.loads(own.read_text())["path"] == "bench/results/x.json" and "provenance" in json.loads(own.read_text())
    assert md.read_text().startswith("# bench.mapper\n\n`python -m bench.mapper --seeds 3`: 3 seeds\n\n| a |")
