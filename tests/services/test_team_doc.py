"""``docs/team.md`` runs: every ``bash`` and ``python`` block of the page is executed in a fresh folder, in page order
(the python blocks in one namespace; :class:`tests.docs.blocks.PageRunner`), unless an HTML comment
``<!-- not run: reason -->`` right before it says why not, so the page a robot team follows cannot drift from the
product."""

from __future__ import annotations

import numpy as np

from tests.docs.blocks import PageRunner, runnable

PAGE = "docs/team.md"


def test_every_bash_and_python_block_of_the_team_page_runs(tmp_path):
    blocks = runnable(PAGE)
    run = [b for b in blocks if b.skip is None]
    assert {b.lang for b in run} == {"bash", "python"} and len(run) >= 4
    assert all(len(b.skip) >= 20 for b in blocks if b.skip is not None)  # a block not run says why
    runner = PageRunner(tmp_path, timeout_s=300)
    try:
        for b in run:
            runner.run(b)
        out = runner.output()
        ns = runner.namespaces[PAGE]
    finally:
        runner.close()
    # the setting shown is in the effective tree, the refused one names its field (grep -c counts one line)
    assert "T_world_map:" in out and "\n1\n" in f"\n{out}"
    # the example's three maps: with the transform where the world-frame run puts it, without it a metre away
    assert np.allclose(ns["T_world_map"][:3, :3] @ [1.0, 0.0, 0.0], [np.cos(np.pi / 6), np.sin(np.pi / 6), 0.0], atol=1e-6)
    assert np.linalg.norm(ns["aligned"] - ns["reference"]) < 1e-3 < 1.0 < np.linalg.norm(ns["unaligned"] - ns["reference"])
    assert (tmp_path / "runs" / "scene" / "agent_b" / "traj.txt").is_file()
