"""``docs/robot-integration.md`` runs: every Python block of the page is executed against an in-process fusion server
with a bearer token (the blocks of one ``##`` section in order, in one namespace), so the page an outside robot team
follows cannot drift from the server."""

from __future__ import annotations

import re
from pathlib import Path

import grpc
import pytest

from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.server import ServerOptions
from gausslite_services.fusion_server.server import serve

DOC = Path(__file__).resolve().parents[2] / "docs" / "robot-integration.md"
TOKEN = "doc-test-token"


def python_sections(text: str) -> dict:
    """``## heading`` → the ```` ```python ```` blocks under it, in order (code inside other fences is skipped)."""
    sections: dict = {}
    heading, block, lang = "", None, None
    for line in text.splitlines():
        fence = re.match(r"^```(\w*)\s*$", line)
        if block is None and fence:
            block, lang = [], fence.group(1)
        elif block is not None and line.startswith("```"):
            if lang == "python":
                sections.setdefault(heading, []).append("\n".join(block))
            block = None
        elif block is not None:
            block.append(line)
        elif line.startswith("## "):
            heading = line[3:].strip()
    assert block is None, "unclosed code fence"
    return sections


def test_the_extractor_reads_fences_and_sections():
    text = "## A\n```python\nx = 1\n```\n```bash\nrm -rf /\n```\n## B\n```python\ny = 2\n```\n```python\nz = 3\n```\n"
    assert python_sections(text) == {"A": ["x = 1"], "B": ["y = 2", "z = 3"]}
    with pytest.raises(AssertionError, match="unclosed"):
        python_sections("## A\n```python\nx = 1\n")


@pytest.fixture()
def fusion(tmp_path, monkeypatch):
    srv = serve(ServerOptions(port=0, max_workers=8, token=TOKEN), None, data_dir=str(tmp_path / "fusion"))
    for var in ("GAUSSLITE_FUSION_TOKEN_FILE", "GAUSSLITE_TOKEN", "GAUSSLITE_TLS_CA", "GAUSSLITE_TLS_CLIENT_CERT",
                "GAUSSLITE_TLS_CLIENT_KEY"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("GAUSSLITE_FUSION_ADDR", f"127.0.0.1:{srv.port}")
    monkeypatch.setenv("GAUSSLITE_FUSION_TOKEN", TOKEN)
    yield srv
    srv.stop(0.5)


def test_every_python_block_of_the_robot_integration_page_runs(fusion):
    sections = python_sections(DOC.read_text(encoding="utf-8"))
    # the page's runnable parts: a minimal client, delta pushes, a raw-stub client of several steps
    assert {"A minimal client", "4. Delta pushes", "A raw gRPC client"} <= set(sections), sorted(sections)
    assert len(sections["A raw gRPC client"]) >= 5
    for heading, blocks in sections.items():
        namespace: dict = {"__name__": f"robot_integration_doc.{heading}"}
        for i, code in enumerate(blocks):
            exec(compile(code, f"{DOC.name} [{heading}] block {i}", "exec"), namespace)  # noqa: S102 - our own doc
    # what the blocks did is on the server: robot1 pushed a full version and then a delta, robot2 a resumed upload
    # and a delta; the agents' latest versions are complete, and fused maps exist
    latest = fusion.store.latest_complete()
    assert set(latest) == {"robot1", "robot2"} and latest["robot1"] >= 3 and latest["robot2"] == 2
    assert len(fusion.store.fused_infos()) >= 2
    # the server took the blocks' token: without it, the same call is refused
    with grpc.insecure_channel(f"127.0.0.1:{fusion.port}") as ch:
        with pytest.raises(grpc.RpcError) as err:
            fusion_pb2_grpc.FusionStub(ch).GetStats(fusion_pb2.StatsRequest(), timeout=10)
    assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
